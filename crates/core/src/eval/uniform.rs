//! The best uniform surrogate: the yardstick a learned spatially varying one must beat.
//!
//! A search over one stiffness shared by every spring (damping held at the run's initial `b`),
//! then coordinate descent over one shared damping (fractions of critical damping: a `b` fitted
//! to data it cannot explain is no fair yardstick) and the stiffness around the best: each
//! candidate is rolled out freely on training rollouts, and the one
//! with the lowest mean motion RMSE is evaluated on the test rollouts like the trained model.

use std::path::PathBuf;

use anyhow::Result;
use burn::tensor::Device;
use serde::{Deserialize, Serialize};

use crate::cloth::{SpringFamily, Topology};
use crate::eval::{self, MotionRmse};
use crate::model::SpringNet;
use crate::progress::Progress;
use crate::sim::Physics;

/// Candidates are `k₀ · 2^(i/2)` for `i` in `−SPAN..=SPAN`, then `2^(±1/4)` around the best.
const SPAN: i32 = 6;
/// Training rollouts the search simulates (the first ones of the split).
pub(crate) const SEARCH_ROLLOUTS: usize = 8;
/// Damping candidates as fractions of a spring's critical damping `√(2 k m)`.
pub(crate) const DAMPING_RATIOS: [f64; 7] = [0.003, 0.01, 0.03, 0.1, 0.3, 1.0, 3.0];
/// Factors of the bending springs' `k` over the others' tried at the best share (1 is the
/// share's own): the blend search's row ([`crate::train::scale`]) and the bending-apart yardstick's
/// ([`search`] with `bending_apart`).
pub const BENDING_FACTORS: [f64; 5] = [0.0, 1.0 / 16.0, 0.25, 0.5, 2.0];
/// The share of the bending springs moves only for a candidate this much closer (relative) to
/// the training takes: a share chosen on less is chosen by chance.
pub const BENDING_MARGIN: f64 = 0.01;

/// The score of free rollouts of the uniform network `(k, b)` on `takes` (`takes.objective`, the
/// mean motion RMSE over the whole takes for the yardsticks; `None` when it is unstable at
/// `physics`' step or a rollout diverges).
pub(crate) fn rollout_rmse(physics: &Physics, k: f64, b: f64, takes: &eval::Takes) -> Option<f64> {
    let model = SpringNet::uniform(takes.topology, k, b, takes.device);
    network_rollout_rmse(&model, physics, takes)
}

/// The score of free rollouts of the spring network `model` on `takes` (`takes.objective`;
/// `None` when it is unstable at `physics`' step or a rollout diverges). Quiet:
/// `takes.progress` is not used.
pub(crate) fn network_rollout_rmse(
    model: &SpringNet,
    physics: &Physics,
    takes: &eval::Takes,
) -> Option<f64> {
    if !physics.stability_of(takes.topology, model).is_stable() {
        return None;
    }
    stable_rollout_rmse(model, physics, takes)
}

/// [`network_rollout_rmse`] of a network already known to be stable at `physics`' step (its
/// stability estimate not repeated).
pub(crate) fn stable_rollout_rmse(
    model: &SpringNet,
    physics: &Physics,
    takes: &eval::Takes,
) -> Option<f64> {
    let quiet = Progress::quiet();
    let takes = eval::Takes {
        progress: &quiet,
        ..*takes
    };
    let curves = eval::motion_curves(model, physics, &takes).ok()?;
    let score = takes.objective.score(&curves.curves, physics.frame_dt);
    score.is_finite().then_some(score)
}

/// `eval.json`'s `uniform_baseline`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct UniformBaseline {
    /// The best uniform stiffness on the training rollouts, N/m.
    pub k: f64,
    /// The best uniform damping on the training rollouts, N·s/m.
    pub b: f64,
    /// `(k, score on the training rollouts)` of every stable stiffness candidate, at the run's
    /// `b` for the coarse search, at the damping then best for the refinement (the score: the
    /// mean motion RMSE for `eval`'s yardstick; `train`'s check scores as its searches do).
    pub search: Vec<(f64, f64)>,
    /// `(b, score on the training rollouts)` of every stable damping candidate.
    #[serde(default)]
    pub b_search: Vec<(f64, f64)>,
    /// Training rollouts the search used.
    pub search_rollouts: usize,
    /// The best uniform surrogate on the test rollouts.
    pub test: MotionRmse,
    /// `1 − trained / uniform` of the long-horizon test RMSE (positive: training helps).
    pub improvement_long: f64,
    /// The same for the short horizon.
    pub improvement_short: f64,
    /// The best bending-apart network beside it: one `k` for the cells' springs, another for
    /// the bending springs ([`BendingApart`]; `eval` only, where the network has bending springs).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub bending_apart: Option<BendingApart>,
    /// The best uniform network with its own drag and viscosity beside it ([`OwnDamping`];
    /// `eval` only).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub own_damping: Option<OwnDamping>,
}

impl UniformBaseline {
    /// Its score on the training rollouts it was searched on (the mean motion RMSE for `eval`'s
    /// yardstick): the lowest of the candidates its search lists, its pick.
    pub fn train_rmse(&self) -> f64 {
        self.search
            .iter()
            .chain(&self.b_search)
            .map(|c| c.1)
            .fold(f64::INFINITY, f64::min)
    }
}

/// `eval.json`'s `uniform_baseline.own_damping`: the best uniform network where it also chooses
/// its own damping, as the recipe chooses the map's. The uniform yardstick above is searched at
/// the run's kept physics: the drag (`sim.rayleigh`) and viscosity (`sim.viscosity`) the run chose
/// for its map, which may move a uniform network farther than one of its own would. This one is
/// searched as the recipe searches the map's (a drag row where the files state no drag, the
/// uniform network's sizes at the closest drag, then an isotropic viscosity on each spring with
/// the drag at zero, or beside the stated one) and the closest of those and the yardstick itself
/// on the training takes is kept: the uniform network a user could have had, damped its own way.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct OwnDamping {
    /// Its drag, N·s/m per particle.
    pub rayleigh: f64,
    /// Its viscosity `β` on each spring, s.
    pub viscosity: f64,
    /// Its stiffness, N/m.
    pub k: f64,
    /// Its damping, N·s/m.
    pub b: f64,
    /// Which search found it: `"run's physics"` (the yardstick itself), `"drag"` (`"no
    /// viscosity"` where the files state the drag) or `"viscosity"`.
    pub found_by: String,
    /// `(drag, mean motion RMSE on the training takes)` of the yardstick's network at each drag of
    /// the rows, without viscosity, sorted by drag; empty where the files state the drag.
    pub drag_row: Vec<(f64, f64)>,
    /// Its mean motion RMSE on the training takes, m.
    pub train_rmse: f64,
    /// The yardstick's mean motion RMSE on the same training takes, m.
    pub yardstick_train_rmse: f64,
    /// It on the test rollouts.
    pub test: MotionRmse,
    /// `1 − trained / own-damping` of the long-horizon test RMSE (positive: training helps).
    pub improvement_long: f64,
    /// The same for the short horizon.
    pub improvement_short: f64,
}

/// `eval.json`'s `uniform_baseline.bending_apart`: the best network whose structural and shear
/// springs share one stiffness and whose bending springs (the hinge springs across a cell's
/// side, which no other simulator has as such) share that times `bending_factor`, one damping
/// for all; searched like the uniform one, at the same step and on the same training rollouts.
/// A learned map's gain over it is what the map's spatial variation wins, not the bending
/// springs' share.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct BendingApart {
    /// The bending springs' `k` over the others'.
    pub bending_factor: f64,
    /// The cells' springs' stiffness, N/m.
    pub k: f64,
    /// The damping of every spring, N·s/m.
    pub b: f64,
    /// `(factor, mean motion RMSE on the training rollouts)` of every factor tried at its best
    /// sizes, the yardstick's own (factor 1) first.
    pub factor_search: Vec<(f64, f64)>,
    /// Its mean motion RMSE on the training rollouts.
    pub train_rmse: f64,
    /// It on the test rollouts.
    pub test: MotionRmse,
    /// `1 − trained / bending-apart` of the long-horizon test RMSE (positive: the map wins).
    pub improvement_long: f64,
    /// The same for the short horizon.
    pub improvement_short: f64,
}

/// Searches the uniform stiffness around `k0` (damping `b0`), then the damping, on `train_files`
/// (scored by `objective`: [`eval::Objective::WholeTake`] for `eval`'s yardstick) and evaluates
/// the best on `test_files`; `trained` is the trained model's test RMSE to compare with. With
/// `bending_apart`, where the topology has bending springs, also the best bending-apart
/// network beside it ([`BendingApart`]).
#[allow(clippy::too_many_arguments)]
pub fn search(
    topology: &Topology,
    physics: &Physics,
    (k0, b0): (f64, f64),
    train_files: &[PathBuf],
    test_files: &[PathBuf],
    trained: &MotionRmse,
    eval_config: &eval::EvalConfig,
    objective: eval::Objective,
    bending_apart: bool,
    device: &Device,
    progress: &Progress,
) -> Result<UniformBaseline> {
    let train: Vec<PathBuf> = train_files.iter().take(SEARCH_ROLLOUTS).cloned().collect();
    let cache = eval::TrackCache::default();
    let takes = eval::Takes {
        topology,
        files: &train,
        batch: eval_config.batch,
        device,
        progress,
        cache: Some(&cache),
        objective,
    };
    let tests = eval::Takes {
        files: test_files,
        cache: None,
        ..takes
    };
    let score = |k: f64, b: f64| rollout_rmse(physics, k, b, &takes);
    let bar = progress.bar(DESCENT_CANDIDATES, "uniform search");
    let Descent {
        k,
        b,
        rmse,
        search,
        b_search,
        ..
    } = descend(&score, (k0, b0), physics.mass, Pick::Lowest, &bar)?;
    bar.finish();
    let test = test_figures(
        &SpringNet::uniform(topology, k, b, device),
        physics,
        &tests,
        eval_config,
    )?;
    let bending_apart = if bending_apart && topology.has_bending() {
        Some(bending_apart_search(
            &takes,
            &tests,
            physics,
            (k, b, rmse),
            trained,
            eval_config,
        )?)
    } else {
        None
    };
    Ok(UniformBaseline {
        k,
        b,
        b_search,
        improvement_long: 1.0 - trained.long.mean / test.long.mean,
        improvement_short: 1.0 - trained.short.mean / test.short.mean,
        search,
        search_rollouts: train.len(),
        test,
        bending_apart,
        own_damping: None,
    })
}

/// A yardstick's network `model` on the test rollouts `tests`, as `eval` measures the trained
/// one.
pub(crate) fn test_figures(
    model: &SpringNet,
    physics: &Physics,
    tests: &eval::Takes,
    eval_config: &eval::EvalConfig,
) -> Result<MotionRmse> {
    let curves = eval::motion_curves(model, physics, tests)?;
    Ok(eval::summarize(
        &curves.curves,
        physics.frame_dt,
        eval_config.short_seconds,
        eval_config.long_seconds,
    ))
}

/// The network of one `k` for every spring but the bending springs, which have `k · factor`,
/// and one `b`.
fn bending_apart_network(
    topology: &Topology,
    k: f64,
    b: f64,
    factor: f64,
    device: &Device,
) -> SpringNet {
    let n = topology.num_springs();
    let mut ks = vec![k; n];
    topology.scale_family(&mut ks, SpringFamily::Bending, factor);
    SpringNet::new(topology, &ks, &vec![b; n], device)
}

/// The best bending-apart network ([`BendingApart`]) beside the uniform yardstick `(k̄, b̄)`
/// (searched at `physics` on `takes`, where it moved `yardstick` from them), evaluated on
/// `tests` against the trained model's test RMSE `trained`.
/// Each of [`BENDING_FACTORS`] is sized by the yardstick's descent of `k` and `b` from
/// `(k̄, b̄)`, and the closest kept where it moves [`BENDING_MARGIN`] closer to the training
/// rollouts than the yardstick (factor 1) itself.
fn bending_apart_search(
    takes: &eval::Takes,
    tests: &eval::Takes,
    physics: &Physics,
    (k_bar, b_bar, yardstick): (f64, f64, f64),
    trained: &MotionRmse,
    eval_config: &eval::EvalConfig,
) -> Result<BendingApart> {
    let network =
        |k: f64, b: f64, f: f64| bending_apart_network(takes.topology, k, b, f, takes.device);
    let score = |k: f64, b: f64, f: f64| network_rollout_rmse(&network(k, b, f), physics, takes);
    let bar = takes.progress.bar(
        (BENDING_FACTORS.len() as u64) * DESCENT_CANDIDATES,
        "bending-apart search",
    );
    // Factor 1 is the yardstick itself; every other factor is sized by the yardstick's own
    // descent from the yardstick's sizes (a network whose bending springs are softer wants its
    // others stiffer).
    let shares = closest_bending_share(yardstick, |f| {
        let at = |k: f64, b: f64| score(k, b, f);
        let d = descend(&at, (k_bar, b_bar), physics.mass, Pick::Lowest, &bar).ok()?;
        Some((d.rmse, d))
    });
    bar.finish();
    let factor_search = shares.row;
    let (factor, k, b, rmse) = shares
        .kept
        .map_or((1.0, k_bar, b_bar, yardstick), |(f, d)| {
            (f, d.k, d.b, d.rmse)
        });
    let test = test_figures(&network(k, b, factor), physics, tests, eval_config)?;
    Ok(BendingApart {
        bending_factor: factor,
        k,
        b,
        factor_search,
        train_rmse: rmse,
        improvement_long: 1.0 - trained.long.mean / test.long.mean,
        improvement_short: 1.0 - trained.short.mean / test.short.mean,
        test,
    })
}

/// A row of the bending springs' shares ([`closest_bending_share`]).
pub struct BendingShares<T> {
    /// `(factor, mean motion RMSE on the training takes)` of every share sized, share 1 first.
    pub row: Vec<(f64, f64)>,
    /// The share kept and what sizing it found; `None`: share 1.
    pub kept: Option<(f64, T)>,
}

/// Each of [`BENDING_FACTORS`] sized by `size` (its mean motion RMSE on the training takes and
/// what it found; `None` where no size keeps it stable: not a candidate), beside share 1, which
/// moved `own`; the closest is kept where it moves [`BENDING_MARGIN`] closer than share 1. The
/// rule of the bending-apart yardstick and of `diagnose`'s source map.
pub fn closest_bending_share<T>(
    own: f64,
    mut size: impl FnMut(f64) -> Option<(f64, T)>,
) -> BendingShares<T> {
    let mut row = vec![(1.0, own)];
    let mut kept: Option<(f64, f64, T)> = None;
    for f in BENDING_FACTORS {
        let Some((r, found)) = size(f) else {
            continue;
        };
        row.push((f, r));
        let closest = kept.as_ref().map_or(own, |k| k.1);
        if r < closest && r < own * (1.0 - BENDING_MARGIN) {
            kept = Some((f, r, found));
        }
    }
    BendingShares {
        row,
        kept: kept.map(|(f, _, found)| (f, found)),
    }
}

/// How a [`descend`] picks the best of a row of `(value, RMSE)` candidates.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Pick {
    /// The candidate of the lowest RMSE.
    Lowest,
    /// The candidate whose RMSE averaged with its row neighbours' (the next lower and higher
    /// value tried) is the lowest: a free rollout's RMSE over a chaotic take jumps between
    /// neighbouring candidates, and a minimum among such jumps is the takes' chance, not the
    /// cloth's. Its own RMSE is returned.
    Neighbourhood,
}

impl Pick {
    /// The pick of `row` (any order), `(value, its own RMSE)`; `None` where it is empty.
    pub(crate) fn of(self, row: &[(f64, f64)]) -> Option<(f64, f64)> {
        let mut sorted = row.to_vec();
        sorted.sort_by(|a, b| a.0.total_cmp(&b.0));
        sorted.dedup_by(|a, b| a.0 == b.0);
        let score = |i: usize| match self {
            Self::Lowest => sorted[i].1,
            Self::Neighbourhood => {
                let near = &sorted[i.saturating_sub(1)..(i + 2).min(sorted.len())];
                near.iter().map(|c| c.1).sum::<f64>() / near.len() as f64
            }
        };
        (0..sorted.len())
            .min_by(|&a, &b| score(a).total_cmp(&score(b)))
            .map(|i| sorted[i])
    }
}

/// Candidates a [`descend`] scores at most: its stiffness row, two damping rows and the
/// stiffness around the best between them (a progress bar's length).
pub(crate) const DESCENT_CANDIDATES: u64 = (2 * SPAN + 5) as u64 + 2 * DAMPING_RATIOS.len() as u64;

/// The network a coordinate descent found, its mean motion RMSE, and every `(k, RMSE)` and
/// `(b, RMSE)` it tried, sorted.
pub(crate) struct Descent {
    pub k: f64,
    pub b: f64,
    pub rmse: f64,
    pub search: Vec<(f64, f64)>,
    pub b_search: Vec<(f64, f64)>,
    /// The pair of the lowest RMSE of every pair tried, `(k, b, RMSE)`: the pick itself under
    /// [`Pick::Lowest`].
    pub lowest: (f64, f64, f64),
}

/// Searches `k` on a row around `k0`, then by coordinate descent: the damping at the best
/// stiffness (fractions of a spring's critical damping `√(2 k m)`, `m` the particle `mass`), the
/// stiffness around it at the best damping, then the damping once more. `score` takes a
/// network's mean `k` and `b`: a uniform network's, or a spatial map's sizes
/// ([`crate::train::scale::polish`]); each pair is simulated once (the second damping row
/// repeats the first where the stiffness stayed).
pub(crate) fn descend(
    score: &dyn Fn(f64, f64) -> Option<f64>,
    (k0, b0): (f64, f64),
    mass: f64,
    pick: Pick,
    bar: &crate::progress::Bar,
) -> Result<Descent> {
    let mut tried: Vec<((f64, f64), Option<f64>)> = Vec::new();
    let mut score = |k: f64, b: f64| {
        if let Some(&(_, known)) = tried.iter().find(|t| t.0 == (k, b)) {
            return known;
        }
        let found = score(k, b);
        tried.push(((k, b), found));
        found
    };
    let best = |s: &[(f64, f64)]| {
        pick.of(s)
            .ok_or_else(|| anyhow::anyhow!("no uniform stiffness around {k0} N/m is stable"))
    };
    let mut search: Vec<(f64, f64)> = Vec::new();
    for i in -SPAN..=SPAN {
        let k = k0 * 2f64.powf(i as f64 / 2.0);
        if let Some(r) = score(k, b0) {
            search.push((k, r));
        }
        bar.inc(1);
    }
    let (mut k, mut k_rmse) = best(&search)?;
    // Coordinate descent: the damping at the best stiffness, the stiffness around it at the best
    // damping, then the damping once more.
    let mut b_search = vec![(b0, k_rmse)];
    let mut b = b0;
    for round in 0..2 {
        let mut candidates = vec![(b, k_rmse)];
        for ratio in DAMPING_RATIOS {
            let c = ratio * (2.0 * k * mass).sqrt();
            if let Some(r) = score(k, c) {
                candidates.push((c, r));
            }
            bar.inc(1);
        }
        (b, k_rmse) = best(&candidates)?;
        b_search.extend(candidates.into_iter().skip(1));
        if round == 1 {
            break;
        }
        let mut around = vec![(k, k_rmse)];
        for f in [-1.0, -0.5, 0.5, 1.0] {
            let c = k * 2f64.powf(f);
            if let Some(r) = score(c, b) {
                around.push((c, r));
            }
            bar.inc(1);
        }
        (k, k_rmse) = best(&around)?;
        search.extend(around.into_iter().skip(1));
    }
    let by_value = |a: &(f64, f64), b: &(f64, f64)| a.0.total_cmp(&b.0).then(a.1.total_cmp(&b.1));
    b_search.sort_by(by_value);
    search.sort_by(by_value);
    // A pair met twice is one candidate.
    b_search.dedup();
    search.dedup();
    let lowest = tried
        .iter()
        .filter_map(|&((k, b), r)| Some((k, b, r?)))
        .min_by(|a, b| a.2.total_cmp(&b.2))
        .unwrap_or((k, b, k_rmse));
    Ok(Descent {
        lowest,
        k,
        b,
        rmse: k_rmse,
        search,
        b_search,
    })
}

#[cfg(test)]
mod tests {
    use super::Pick;

    #[test]
    fn the_neighbourhood_pick_prefers_a_basin_to_a_lone_dip() {
        // A lone dip at 16 between high neighbours, a broad basin around 2; any order.
        let row = [
            (16.0, 0.200),
            (1.0, 0.215),
            (8.0, 0.250),
            (2.0, 0.210),
            (4.0, 0.214),
            (32.0, 0.260),
            (0.5, 0.230),
        ];
        assert_eq!(Pick::Lowest.of(&row), Some((16.0, 0.200)));
        // Means with the neighbours: 2 → (0.215 + 0.210 + 0.214) / 3 = 0.2130; 16 → 0.2367;
        // the ends average two: 32 → 0.2300.
        assert_eq!(Pick::Neighbourhood.of(&row), Some((2.0, 0.210)));
        // A row of one is its own pick; an empty row has none.
        assert_eq!(Pick::Neighbourhood.of(&[(3.0, 0.1)]), Some((3.0, 0.1)));
        assert_eq!(Pick::Neighbourhood.of(&[]), None);
    }
}
