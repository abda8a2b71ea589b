//! The learned network's overall scale, searched over free rollouts (ours; `train.scale_search`).
//!
//! A fit of the forces on the data's own states (`train.force_on = "target"`, teacher forcing) ranks
//! the springs by stiffness where a rollout loss cannot (third-party data: see the book (docs/), "Data from
//! another simulator"), but its values are attenuated: the regressors — spring strains measured
//! from positions that no spring network explains exactly — are noisy, and least squares shrinks
//! their coefficients towards zero. A network with the right shape and too small a size then
//! simulates worse than a uniform one. The search keeps the shape and finds the size: every `k`
//! is multiplied by one factor and every `b` by another, each candidate rolled out freely on
//! training rollouts (at the fewest substeps that keep it stable), and the pair with the lowest
//! mean motion RMSE is kept. Ranks — and so the stiffness map's Spearman correlation — do not
//! change.
//!
//! The blend search (`train.blend_search`) anchors the same search at the best uniform network
//! (PhysTwin's order: the global parameters by a zero-order search first, the spatial detail
//! after): every candidate is `k_s = f_k ((1 − α) k̄ + α k_s)`, `b_s = f_b ((1 − α) b̄ + α b_s)`
//! with `k̄`, `b̄` the learned network's means, so `α = 0` is a uniform network and `α = 1` the
//! scale search's. Each share gets a row of stiffness factors, a row of damping factors at the
//! best and a quarter octave either side: the ends `α = 0` (from the run's initial uniform
//! network: the best uniform network on the training rollouts) and `α = 1` (from the uniform
//! end's factors, since a fit's values are shrunk and a map with soft springs in series is softer
//! than its mean) from wide rows, the shares between from narrow rows about the geometric mean of
//! the ends' factors. That chain runs twice from the same start, sharing every candidate: once
//! with the ends' rows octaves around their starts, once with them also descending over the
//! uniform search's fractions of critical damping; the chain that moves closer to the training
//! rollouts is kept (each stage starts from the one before, so a closer uniform end alone does
//! not make a closer blend). The learned map is kept only where it moves closer to the training
//! rollouts than the best uniform network does; ranks (for `α > 0`) stay the learned ones.
//!
//! The searches score each candidate at its own fewest stable substeps; [`polish`] then descends
//! the kept network's size and damping once more at the substeps it runs at, beside the best
//! uniform network there — the yardstick `eval.uniform_baseline` measures the run against.

use std::path::PathBuf;

use anyhow::{Result, bail};
use serde::{Deserialize, Serialize};

use crate::cloth::{SpringFamily, Topology};
use crate::eval::Takes;
use crate::eval::uniform::{self, DAMPING_RATIOS, network_rollout_rmse, stable_rollout_rmse};
use crate::model::SpringNet;
use crate::sim::Physics;
use crate::train::compliance::MapWeights;
use crate::train::init::AUTO_SUBSTEPS_TARGET;

/// Training rollouts every candidate is simulated on (the first ones of the split): every
/// fitted take of the bench's sets (12 training takes, two held out); at 8 two of them were
/// left out (the book, Results → Other simulators, "Past 8 times the substeps where the
/// stiffness asks, and all ten fitted takes in the searches").
const SEARCH_ROLLOUTS: usize = 10;
/// Stiffness factors `2^(i/2)`, `i` in this range; then `2^(±1/4)` around the best.
const K_STEPS: std::ops::RangeInclusive<i32> = -2..=8;
/// Damping factors `2^i`, `i` in this range.
const B_STEPS: std::ops::RangeInclusive<i32> = -4..=4;
/// The search raises the substeps at most this many times over the run's for a network whose
/// damping sets them. The cap keeps the searches out of networks so overdamped that their
/// damping alone asks for the substeps: at 16 for every network, tried on the bench
/// (2026-12-05), on a spring cloth of known viscosity the chain of row searches settled on a soft
/// network damped sixteen times its start's at 466 substeps, and the viscosity was no longer
/// found (the book, Results → Other simulators, "The searches' substeps: 16 times the run's,
/// tried").
const MAX_SUBSTEP_FACTOR: usize = 8;
/// A network whose stiffness sets its substeps (`dt²ω² ≥ 2·dt·γ` at its fewest) may be raised up
/// to this many times the run's: the stiffest sets' maps, sized stiffer than 8× allows, move
/// closer to their takes (the book, Results → Other simulators, "Past 8 times the substeps
/// where the stiffness asks, and all ten fitted takes in the searches").
const STIFF_SUBSTEP_FACTOR: usize = 2 * MAX_SUBSTEP_FACTOR;

/// A candidate's substeps and mean motion RMSE; `None` when it is unstable or diverged.
type Scored = Option<(usize, f64)>;

/// `scale.json`: what the search tried and kept.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ScaleSearch {
    /// The factor every `k` was multiplied by.
    pub k_factor: f64,
    /// The factor every `b` was multiplied by.
    pub b_factor: f64,
    /// Substeps per frame of the kept network (the run's config is updated to them).
    pub substeps: usize,
    /// Mean motion RMSE on the search's training rollouts before the search (factors 1, 1), m;
    /// `None` when the trained network diverged there.
    pub before: Option<f64>,
    /// The same for the kept factors, m.
    pub after: f64,
    /// `(k factor, b factor, substeps, mean motion RMSE)` of every stable candidate.
    pub candidates: Vec<(f64, f64, usize, f64)>,
    /// Training rollouts simulated per candidate.
    pub rollouts: usize,
}

/// `blend.json`: what the blend search tried and kept.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub(crate) struct BlendSearch {
    /// Which map was blended: `trained` (the trained network's), `compliance`, or `mixed`
    /// (the two together).
    pub map: String,
    /// The share of the learned map kept (0: uniform).
    pub alpha: f64,
    /// The factor of the blended `k`.
    pub k_factor: f64,
    /// The factor of the blended `b`.
    pub b_factor: f64,
    /// The learned network's mean `k`, N/m (`k̄`).
    pub k_mean: f64,
    /// The learned network's mean `b`, N·s/m (`b̄`).
    pub b_mean: f64,
    /// Substeps per frame of the kept network (the run's config is updated to them).
    pub substeps: usize,
    /// The best uniform network on the search's rollouts: `(k, b, mean motion RMSE)`.
    pub uniform: (f64, f64, f64),
    /// Mean motion RMSE of the learned network as trained (`α = 1`, factors 1), m; `None` when
    /// it diverged.
    pub before: Option<f64>,
    /// Mean motion RMSE of the kept network, m.
    pub after: f64,
    /// `(α, k factor, b factor, substeps, mean motion RMSE)` of every stable candidate at the
    /// bending springs' factor the shares' rows ran at ([`Self::rows_bending_factor`]).
    pub candidates: Vec<(f64, f64, f64, usize, f64)>,
    /// The bending springs' factor settled on the uniform network, at which the shares' rows
    /// ran (1 in a record written before it existed).
    #[serde(default = "one")]
    pub rows_bending_factor: f64,
    /// The factor of the bending springs' `k` kept (1 when the network has none, or none moves
    /// closer).
    #[serde(default = "one")]
    pub bending_factor: f64,
    /// `(bending factor, k factor, b factor, substeps, mean motion RMSE)` of every stable
    /// candidate of the bending springs' search, at the kept share.
    #[serde(default)]
    pub bending_candidates: Vec<(f64, f64, f64, usize, f64)>,
    /// Training rollouts simulated per candidate.
    pub rollouts: usize,
    /// The chain kept: `octaves` (the ends' rows are octaves around their starts) or
    /// `critical` (they also descend over fractions of critical damping).
    #[serde(default = "octaves")]
    pub chain: String,
    /// The kept network polished at the substeps it runs at ([`polish`]); `None` in a record
    /// written before there was a polish.
    #[serde(default)]
    pub polish: Option<Polish>,
    /// The drag searched after the polish where the run fitted it ([`DragSearch`]); `None`
    /// where the data or the config states the drag, the polish kept the uniform network, no
    /// training take was held out, or in a record written before there was a drag search.
    #[serde(default)]
    pub drag: Option<DragSearch>,
    /// The search of spring damping proportional to stiffness without drag after the drag
    /// search, where it ran.
    #[serde(default)]
    pub damping: Option<ProportionalDamping>,
    /// The search of an isotropic viscosity proportional to stiffness without drag
    /// (`sim.viscosity`) after those, where it ran.
    #[serde(default)]
    pub viscosity: Option<ProportionalDamping>,
    /// The search of the shear springs' stiffness in compression (`sim.shear_compression`)
    /// after those, where it ran ([`CompressionSearch`]).
    #[serde(default)]
    pub shear_compression: Option<CompressionSearch>,
    /// Every map's blend searched, the kept one among them ([`MapScore`]); empty in a record
    /// written before the maps were judged on held-out takes.
    #[serde(default)]
    pub maps: Vec<MapScore>,
    /// The fit's weight in the mixed map per strain group, from the two maps read off two
    /// halves of the training takes ([`MapWeights`]); `None` where no mixed map was searched,
    /// or in a record written before the maps were weighed.
    #[serde(default)]
    pub weights: Option<MapWeights>,
    /// Where the closest share lay past the whole map (`train.blend_contrast`), that share
    /// against the share kept without it ([`ContrastCheck`]); `None` otherwise, or in a record
    /// written before the check.
    #[serde(default)]
    pub contrast: Option<ContrastCheck>,
}

/// A share past the whole map (`train.blend_contrast`), which the training takes chose,
/// against the share kept without it, both polished ([`polish`]; a polish can move one share
/// much more than another): the run keeps it where the held-out training takes agree
/// ([`held_out_agrees`]), as it keeps each search after the blend; without held-out takes,
/// where it is still the closer to the training takes once polished.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ContrastCheck {
    /// The share past the whole map closest to the search's training takes.
    pub alpha: f64,
    /// Its blend's mean motion RMSE on the search's training takes once polished, m.
    pub after: f64,
    /// The share the search keeps without the shares past the whole map.
    pub plain_alpha: f64,
    /// Its blend's mean motion RMSE on the search's training takes once polished, m.
    pub plain_after: f64,
    /// `(short, long)` motion RMSE on the held-out training takes of the network without the
    /// shares past the whole map, and of the one with (m), both polished; `None` where none
    /// were held out.
    pub held_out: Option<((f64, f64), (f64, f64))>,
    /// Whether the run keeps the share past the whole map: where the held-out takes prefer it
    /// ([`held_out_agrees`]), or without them, where it is the closer once polished.
    pub kept: bool,
}

impl BlendSearch {
    /// Mean motion RMSE on the search's training takes of the kept blend polished at the
    /// substeps it runs at ([`polish`]; in a record written before there was a polish, of the
    /// blend), m.
    pub fn polished_after(&self) -> f64 {
        self.polish.as_ref().map_or(self.after, |p| p.after)
    }

    /// Whether the search kept the uniform network: no share of the map, or no size or damping
    /// of its blend in the polish, moved as close.
    pub fn kept_uniform(&self) -> bool {
        self.alpha == 0.0 || self.polish.as_ref().is_some_and(|p| p.kept_uniform)
    }
}

/// One map's blend in the blend search: what the search kept of it and how close it moves.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MapScore {
    /// `trained`, `compliance` or `mixed`.
    pub map: String,
    /// The share of the map kept (0: uniform).
    pub alpha: f64,
    /// Mean motion RMSE on the search's training takes (m) of its blend polished at the
    /// substeps it runs at ([`polish`]; in a record written before the maps were polished, of
    /// the blend).
    pub after: f64,
    /// `(short, long)` motion RMSE on the held-out training takes (m) of the polished blend;
    /// `None` where none were held out or one map was searched.
    pub held_out: Option<(f64, f64)>,
}

/// The chain of a record written before there were two.
fn octaves() -> String {
    "octaves".into()
}

/// The default of a factor a record written before it existed lacks.
fn one() -> f64 {
    1.0
}

pub use crate::eval::uniform::{BENDING_FACTORS, BENDING_MARGIN};
/// Rounds of the bending springs' row and the sizes at most.
pub const BENDING_ROUNDS: usize = 4;

/// Blend shares searched between the ends `α = 0` (uniform) and `α = 1` (the learned map).
const ALPHAS: [f64; 3] = [0.25, 0.5, 0.75];
/// Shares past the learned end (`train.blend_contrast`), tried in turn while the last moved
/// closer: the map's contrast within each spring family raised to the power `α`
/// ([`amplified`]). The fit shrinks a map's values and the smoothing and the mixing of two maps
/// flatten it, so a share of 1 can still be short of the source's contrast.
const CONTRASTS: [f64; 2] = [1.5, 2.0];

/// A row search's reach: stiffness factors `2^(i/2)` and damping factors `2^i` around its start,
/// `i` in these, and with `critical` also the uniform search's coordinate descent over
/// fractions of critical damping (`eval.uniform_baseline`'s [`DAMPING_RATIOS`]) at the mean `k`
/// and the stiffness around it — a start from a fit or the data's `b_init` can lie decades from
/// the damping that moves closest, a row of octaves around it does not reach that far, and the
/// stiffness that moves closest at one damping is not the one at another.
#[derive(Debug, Clone)]
struct Span {
    k: std::ops::RangeInclusive<i32>,
    b: std::ops::RangeInclusive<i32>,
    critical: bool,
}

impl Span {
    /// Candidates of a row search at most: its stiffness and damping factors, and the
    /// stiffness a quarter octave either side (with `critical`, the descent's too).
    const fn candidates(&self) -> usize {
        let ratios = if self.critical {
            2 * DAMPING_RATIOS.len() + 4
        } else {
            0
        };
        (*self.k.end() - *self.k.start() + *self.b.end() - *self.b.start() + 4) as usize + ratios
    }
}

/// The ends' rows of the chain from the octaves (the rows around the starts alone).
const WIDE: Span = Span {
    k: -6..=10,
    b: -6..=4,
    critical: false,
};
/// The ends' rows of the chain that also descends over fractions of critical damping.
const WIDE_CRITICAL: Span = Span {
    critical: true,
    ..WIDE
};
/// The shares between: around the geometric mean of the ends' factors.
const NARROW: Span = Span {
    k: -2..=2,
    b: -2..=2,
    critical: false,
};
/// The sizes' rows between the bending springs' rows.
const BENDING_ROW: Span = Span {
    k: -1..=1,
    b: -1..=1,
    critical: false,
};
/// Candidates of one bending springs' search at most: each round's factors and sizes' rows.
const BENDING_CANDIDATES: usize =
    BENDING_ROUNDS * (BENDING_FACTORS.len() + 1 + BENDING_ROW.candidates());
/// Candidates of one chain at most, from its ends' rows `wide`.
const fn chain_candidates(wide: &Span) -> usize {
    2 * wide.candidates()
        + (ALPHAS.len() + CONTRASTS.len()) * NARROW.candidates()
        + 3 * BENDING_CANDIDATES
}
/// Candidates the search considers at most (some twice, simulated once): the bar's length.
const BLEND_CANDIDATES: usize = chain_candidates(&WIDE) + chain_candidates(&WIDE_CRITICAL);

/// What one chain of the blend search found ([`Blender::chain`]).
#[derive(Debug, Clone, Copy)]
struct Chain {
    /// Its name in `blend.json`: `octaves` or `critical`.
    name: &'static str,
    /// The best uniform network the chain found (`α = 0`).
    uniform: Candidate,
    /// The bending springs' factor the shares' rows ran at.
    rows_bending_factor: f64,
    /// The bending springs' factor kept.
    bending_factor: f64,
    /// The candidate kept.
    best: Candidate,
    /// Where the kept share lies past the whole map ([`CONTRASTS`]), the bending springs'
    /// factor and the candidate the chain keeps without it.
    plain: Option<(f64, Candidate)>,
}

impl Chain {
    /// The chain as it ends without the shares past the whole map.
    fn plain(&self) -> Chain {
        match self.plain {
            Some((bending_factor, best)) => Chain {
                bending_factor,
                best,
                plain: None,
                ..*self
            },
            None => *self,
        }
    }
}

/// A network the blend search keeps: the network, the physics it runs at and the record.
pub(crate) struct Blended {
    pub net: SpringNet,
    pub physics: Physics,
    pub record: BlendSearch,
}

/// What the blend search found: the network closest to its training takes, and, where that one's
/// share lies past the whole map (`train.blend_contrast`), the network the search keeps
/// without the shares past it, for the held-out training takes to judge
/// ([`ContrastCheck`]).
pub(crate) struct BlendFound {
    pub closest: Blended,
    pub plain: Option<Blended>,
}

/// Searches the best uniform network around `model`'s means on the training takes `train`, the
/// bending springs' share on it, then the share of `model`'s map blended into it and the factors
/// around the best, and the bending springs' share again there; returns the closest network, the
/// physics it runs at (substeps possibly raised) and the record, and where its share lies past
/// the whole map the network kept without that ([`BlendFound`]).
pub(crate) fn blend_search(
    model: &SpringNet,
    (k_init, b_init): (f64, f64),
    physics: &Physics,
    train: &Takes,
    contrast: bool,
) -> Result<BlendFound> {
    let files = search_files(train);
    let (k, b) = (model.k_values(), model.b_values());
    let (k_mean, b_mean) = blend_means(&k, &b, physics.mass)?;
    let mut search = Blender {
        model,
        kappa: model.curvature_values(),
        k,
        b,
        k_mean,
        b_mean,
        physics,
        takes: Takes {
            files: &files,
            ..*train
        },
        contrast,
        tried: Vec::new(),
        bar: train.progress.bar(BLEND_CANDIDATES as u64, "blend search"),
    };
    let before = search.score(1.0, 1.0, 1.0, 1.0).map(|(_, r)| r);
    // The uniform end starts from the run's initial uniform network (derived from the data).
    let start = (
        k_init / k_mean,
        if b_init > 0.0 { b_init / b_mean } else { 1.0 },
    );
    // Two chains from the same start, sharing every candidate scored: one whose ends' rows are
    // octaves around their starts, one whose ends also descend over fractions of critical
    // damping (a start can lie decades from the damping that moves closest). Each later stage
    // starts from the one before it, so a closer uniform end does not make a closer blend; the
    // chain that moves closer to the training takes is kept, so the search is never worse than
    // either chain alone.
    let chains: Vec<Chain> = [("octaves", WIDE), ("critical", WIDE_CRITICAL)]
        .into_iter()
        .filter_map(|(name, wide)| search.chain(name, start, wide))
        .collect();
    search.bar.finish();
    let Some(&kept) = chains.iter().min_by(|a, b| a.best.4.total_cmp(&b.best.4)) else {
        bail!("the blend search found no stable uniform network around k = {k_init:.4} N/m");
    };
    let uniform = chains
        .iter()
        .map(|c| c.uniform)
        .min_by(|a, b| a.4.total_cmp(&b.4))
        .expect("one chain at least");
    let keep = |kept: &Chain| {
        let record = search.record(kept, uniform, before);
        let best = kept.best;
        Blended {
            net: search.blended(best.0, best.1, best.2, kept.bending_factor),
            physics: Physics {
                substeps: record.substeps,
                ..*physics
            },
            record,
        }
    };
    let closest = keep(&kept);
    let plain = (kept.best.0 > 1.0).then(|| {
        let plain = chains
            .iter()
            .map(Chain::plain)
            .min_by(|a, b| a.best.4.total_cmp(&b.best.4))
            .expect("one chain at least");
        keep(&plain)
    });
    Ok(BlendFound { closest, plain })
}

/// `k` with its contrast within each spring family raised to the power `alpha`: each spring's
/// `k (k / k̄_f)^(α − 1)`, rescaled so that each family keeps its mean `k̄_f` (springs at zero
/// stay there, and the ranks within a family do not change). By family, as measured:
/// raising within the compliance map's strain groups instead (a data mesh's sides and cut
/// diagonals together) left three of four sets farther from their takes, and within those
/// groups split by family (cut diagonals apart from hinge diagonals) two of two (the book's
/// Other simulators, "The share past the whole map, checked on the held-out takes").
fn amplified(k: &[f64], family: &[SpringFamily], alpha: f64) -> Vec<f64> {
    let mut out = k.to_vec();
    for f in [
        SpringFamily::Structural,
        SpringFamily::Shear,
        SpringFamily::Bending,
    ] {
        let members: Vec<usize> = (0..k.len()).filter(|&s| family[s] == f).collect();
        let mean = members.iter().map(|&s| k[s]).sum::<f64>() / members.len().max(1) as f64;
        if mean <= 0.0 {
            continue;
        }
        let raised: Vec<f64> = members
            .iter()
            .map(|&s| mean * (k[s] / mean).powf(alpha))
            .collect();
        let scale = mean / (raised.iter().sum::<f64>() / members.len() as f64);
        for (&s, r) in members.iter().zip(raised) {
            out[s] = r * scale;
        }
    }
    out
}

/// The means the blend search blends towards: the learned `k`'s (which must be positive) and
/// `b`'s, or for a network without damping a tenth of a mean spring's critical damping.
fn blend_means(k: &[f64], b: &[f64], mass: f64) -> Result<(f64, f64)> {
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len().max(1) as f64;
    let k_mean = mean(k);
    if !(k_mean > 0.0) {
        bail!("the blend search needs a network with some stiffness; every learned k is 0");
    }
    let b_mean = match mean(b) {
        m if m > 0.0 => m,
        _ => 0.1 * (2.0 * k_mean * mass).sqrt(),
    };
    Ok((k_mean, b_mean))
}

/// A blend search's candidate: `(α, k factor, b factor, substeps, mean motion RMSE)`.
type Candidate = (f64, f64, f64, usize, f64);

/// The blend search's state: the learned map, its means, and every candidate scored so far.
struct Blender<'a> {
    model: &'a SpringNet,
    k: Vec<f64>,
    b: Vec<f64>,
    kappa: Vec<f64>,
    k_mean: f64,
    b_mean: f64,
    physics: &'a Physics,
    /// The training takes of the search ([`search_files`]).
    takes: Takes<'a>,
    /// Whether shares past the learned end are searched ([`CONTRASTS`]).
    contrast: bool,
    /// `((α, k factor, b factor, bending factor), score)` of every candidate simulated.
    tried: Vec<((f64, f64, f64, f64), Scored)>,
    bar: crate::progress::Bar,
}

impl Blender<'_> {
    /// The network keeping the share `alpha` of the learned map (the rest uniform at the
    /// means; past 1, the learned `k` with its contrast raised, [`amplified`], and the learned
    /// `b`), its `k` scaled by `fk` (the bending springs' by `fk · fh`) and its `b` by `fb`.
    fn blended(&self, alpha: f64, fk: f64, fb: f64, fh: f64) -> SpringNet {
        let mix = |v: &[f64], m: f64, f: f64, alpha: f64| -> Vec<f64> {
            v.iter()
                .map(|x| f * ((1.0 - alpha) * m + alpha * x))
                .collect()
        };
        let kappa: Vec<f64> = self.kappa.iter().map(|x| x * fk).collect();
        let (mut k, b) = if alpha > 1.0 {
            let k = amplified(&self.k, &self.takes.topology.family, alpha);
            (
                mix(&k, self.k_mean, fk, 1.0),
                mix(&self.b, self.b_mean, fb, 1.0),
            )
        } else {
            (
                mix(&self.k, self.k_mean, fk, alpha),
                mix(&self.b, self.b_mean, fb, alpha),
            )
        };
        self.takes
            .topology
            .scale_family(&mut k, SpringFamily::Bending, fh);
        SpringNet::new(self.takes.topology, &k, &b, self.takes.device)
            .with_kernel(self.model.graph.kernel)
            .with_curvature(&kappa)
    }

    /// A candidate's score, simulated once.
    fn score(&mut self, alpha: f64, fk: f64, fb: f64, fh: f64) -> Scored {
        let key = (alpha, fk, fb, fh);
        if let Some(&(_, known)) = self.tried.iter().find(|t| t.0 == key) {
            return known;
        }
        let net = self.blended(alpha, fk, fb, fh);
        let found = score_network(&net, self.physics, &self.takes);
        self.tried.push((key, found));
        found
    }

    /// One chain, `name`, from the uniform network's factors `start`, with the ends' rows `wide`: the
    /// uniform end (`α = 0`), the bending springs' share on it (a map blended into a network
    /// whose bending springs are far off has to make up for them), the learned end (`α = 1`,
    /// from the uniform end's factors, since a fit's values are shrunk), the shares between from
    /// the geometric mean of the ends' factors, and the bending springs' share again at the
    /// best; `None` when no uniform network is stable.
    fn chain(&mut self, name: &'static str, start: (f64, f64), wide: Span) -> Option<Chain> {
        let uniform = self.rows(0.0, start, 1.0, wide.clone())?;
        let (fh, start) = self.bending_search(uniform, 1.0);
        let mut rows = vec![start];
        let learned = self.rows(1.0, (start.1, start.2), fh, wide);
        let far = learned.unwrap_or(start);
        rows.extend(learned);
        for alpha in ALPHAS {
            let at = |a: f64, b: f64| a.powf(1.0 - alpha) * b.powf(alpha);
            let centre = (at(start.1, far.1), at(start.2, far.2));
            rows.extend(self.rows(alpha, centre, fh, NARROW));
        }
        let mut best = rows
            .into_iter()
            .min_by(|a, b| a.4.total_cmp(&b.4))
            .expect("the uniform network is a candidate");
        let plain = best;
        // Past the learned end, while each share moves closer than the last (from its factors).
        if self.contrast && best.0 == 1.0 {
            for alpha in CONTRASTS {
                match self.rows(alpha, (best.1, best.2), fh, NARROW) {
                    Some(c) if c.4 < best.4 => best = c,
                    _ => break,
                }
            }
        }
        let (bending_factor, best) = self.bending_search(best, fh);
        // The chain's end without the shares past the whole map, for the held-out takes.
        let plain = (best.0 > 1.0).then(|| self.bending_search(plain, fh));
        Some(Chain {
            name,
            uniform,
            rows_bending_factor: fh,
            bending_factor,
            best,
            plain,
        })
    }

    /// `candidate` if it scores and beats `best`.
    fn consider(&mut self, alpha: f64, fk: f64, fb: f64, fh: f64, best: &mut Option<Candidate>) {
        if let Some((n, r)) = self.score(alpha, fk, fb, fh)
            && best.is_none_or(|b| r < b.4)
        {
            *best = Some((alpha, fk, fb, n, r));
        }
        self.bar.inc(1);
    }

    /// One share's search with the bending springs' factor `fh` over `span`: a row of
    /// stiffness factors, a row of damping factors at the best, then the stiffness a quarter
    /// octave either side; returns the share's best.
    fn rows(
        &mut self,
        alpha: f64,
        (fk0, fb0): (f64, f64),
        fh: f64,
        span: Span,
    ) -> Option<Candidate> {
        let mut best: Option<Candidate> = None;
        for i in span.k {
            self.consider(alpha, fk0 * 2f64.powf(i as f64 / 2.0), fb0, fh, &mut best);
        }
        let fk = best.map_or(fk0, |b| b.1);
        for i in span.b {
            self.consider(alpha, fk, fb0 * 2f64.powi(i), fh, &mut best);
        }
        if span.critical {
            // The uniform search's coordinate descent (`eval.uniform_baseline`): fractions of a
            // mean spring's critical damping `√(2 k m)` at the best stiffness, the stiffness a
            // half and a whole octave either side at the best damping, then the fractions again.
            self.critical_row(alpha, fh, &mut best);
            let (fk, fb) = best.map_or((fk, fb0), |b| (b.1, b.2));
            for f in [-1.0, -0.5, 0.5, 1.0] {
                self.consider(alpha, fk * 2f64.powf(f), fb, fh, &mut best);
            }
            self.critical_row(alpha, fh, &mut best);
        }
        let (fk, fb) = best.map_or((fk0, fb0), |b| (b.1, b.2));
        for f in [-0.25, 0.25] {
            self.consider(alpha, fk * 2f64.powf(f), fb, fh, &mut best);
        }
        best
    }

    /// Damping factors of [`DAMPING_RATIOS`] of a mean spring's critical damping at `best`'s
    /// stiffness (none while no candidate is stable).
    fn critical_row(&mut self, alpha: f64, fh: f64, best: &mut Option<Candidate>) {
        let Some(fk) = best.map(|b| b.1) else {
            return;
        };
        let critical = (2.0 * fk * self.k_mean * self.physics.mass).sqrt();
        for ratio in DAMPING_RATIOS {
            self.consider(alpha, fk, ratio * critical / self.b_mean, fh, best);
        }
    }

    /// The bending springs' share, after the blend (ours): they are the surrogate's own
    /// construct — hinge springs across a cell's side, or a grid's stride springs — that no
    /// other simulator has as such, so how stiff they are beside the mesh's edges is a global
    /// parameter of the fit like the size. A row of factors of their `k` at `best`, then, at
    /// the best factor, the size rows again (narrow), in turn until the factor stays (at most
    /// [`BENDING_ROUNDS`] rows; a factor moves only for [`BENDING_MARGIN`] closer); returns the
    /// factor and the candidate kept (`share` and `best` when the network has no bending springs
    /// or no factor moves closer). `best` was scored with the bending springs' factor `share`.
    fn bending_search(&mut self, best: Candidate, share: f64) -> (f64, Candidate) {
        if !self.takes.topology.has_bending() {
            return (share, best);
        }
        let mut kept = (share, best);
        // Coordinate descent: the size found for one share of the bending springs is not the
        // size for another (a uniform network softens everything to make up for stiff
        // bending springs), so the row and the sizes alternate until the share stays.
        for _ in 0..BENDING_ROUNDS {
            let (alpha, fk, fb, ..) = kept.1;
            let share = kept.0;
            for fh in BENDING_FACTORS.into_iter().chain([1.0]) {
                if let Some((n, r)) = self.score(alpha, fk, fb, fh)
                    && r < kept.1.4 * (1.0 - BENDING_MARGIN)
                {
                    kept = (fh, (alpha, fk, fb, n, r));
                }
                self.bar.inc(1);
            }
            if kept.0 == share {
                break;
            }
            if let Some(c) = self.rows(alpha, (fk, fb), kept.0, BENDING_ROW)
                && c.4 < kept.1.4
            {
                kept.1 = c;
            }
        }
        kept
    }

    /// The search's record: the `kept` chain, the best `uniform` network, and the learned map's
    /// score `before`.
    fn record(&self, kept: &Chain, uniform: Candidate, before: Option<f64>) -> BlendSearch {
        let (alpha, fk, fb, substeps, after) = kept.best;
        let (rows_bending_factor, bending_factor) = (kept.rows_bending_factor, kept.bending_factor);
        BlendSearch {
            map: "trained".into(),
            alpha,
            k_factor: fk,
            b_factor: fb,
            k_mean: self.k_mean,
            b_mean: self.b_mean,
            substeps,
            uniform: (uniform.1 * self.k_mean, uniform.2 * self.b_mean, uniform.4),
            before,
            after,
            candidates: self.candidates(rows_bending_factor),
            rows_bending_factor,
            bending_candidates: BENDING_FACTORS
                .iter()
                .flat_map(|&fh| {
                    self.candidates(fh)
                        .into_iter()
                        .filter(|c| c.0 == alpha)
                        .map(move |c| (fh, c.1, c.2, c.3, c.4))
                })
                .collect(),
            bending_factor,
            rollouts: self.takes.files.len(),
            chain: kept.name.into(),
            polish: None,
            drag: None,
            damping: None,
            viscosity: None,
            shear_compression: None,
            maps: Vec::new(),
            weights: None,
            contrast: None,
        }
    }

    /// Every stable candidate tried at the bending springs' factor `fh`, sorted by share and
    /// factors.
    fn candidates(&self, fh: f64) -> Vec<Candidate> {
        let mut candidates: Vec<Candidate> = self
            .tried
            .iter()
            .filter(|t| t.0.3 == fh)
            .filter_map(|&((a, fk, fb, _), found)| found.map(|(n, r)| (a, fk, fb, n, r)))
            .collect();
        candidates.sort_by(|x, y| {
            x.0.total_cmp(&y.0)
                .then(x.1.total_cmp(&y.1))
                .then(x.2.total_cmp(&y.2))
        });
        candidates
    }
}

/// A candidate's fewest stable substeps (from `physics.substeps` up, at a stability number of
/// 1 or less) and its mean motion RMSE on `takes` there; `None` when no substeps within the cap
/// keep it stable or a rollout diverged.
pub fn score_network(net: &SpringNet, physics: &Physics, takes: &Takes) -> Option<(usize, f64)> {
    stable_substeps(takes.topology, physics, net).and_then(|n| {
        let p = Physics {
            substeps: n,
            ..*physics
        };
        // Stable: its stability number at `n` substeps is at most 1.
        stable_rollout_rmse(net, &p, takes).map(|r| (n, r))
    })
}

/// The training takes a search simulates: the first [`SEARCH_ROLLOUTS`].
pub(crate) fn search_files(train: &Takes) -> Vec<PathBuf> {
    train.files.iter().take(SEARCH_ROLLOUTS).cloned().collect()
}

/// The fewest substeps from `physics.substeps` up that start `model` at
/// `dt²ω² + 2·dt·γ ≤ 1`, or `None` beyond [`MAX_SUBSTEP_FACTOR`] times the run's, or beyond
/// [`STIFF_SUBSTEP_FACTOR`] times where the stiffness term `dt²ω²` is the larger there.
pub(crate) fn stable_substeps(
    topology: &Topology,
    physics: &Physics,
    model: &SpringNet,
) -> Option<usize> {
    let stability = physics.stability_of(topology, model);
    let n = stability.fewest_substeps(
        physics.frame_dt,
        physics.substeps..=physics.substeps * STIFF_SUBSTEP_FACTOR,
        AUTO_SUBSTEPS_TARGET,
    )?;
    let stiffness_limits = stability.stiffness_limits_at(physics.frame_dt / n as f64);
    (n <= physics.substeps * MAX_SUBSTEP_FACTOR || stiffness_limits).then_some(n)
}

/// Searches the factors of `model`'s `k` and `b` on the training takes `train`; returns the scaled network,
/// the physics it runs at (substeps possibly raised) and the record.
pub fn search(
    model: &SpringNet,
    physics: &Physics,
    train: &Takes,
) -> Result<(SpringNet, Physics, ScaleSearch)> {
    let files = search_files(train);
    let takes = Takes {
        files: &files,
        ..*train
    };
    let sizes = Sizes::of(model);
    let scaled = |fk: f64, fb: f64| sizes.scaled(train, fk, fb);
    // Every pair is simulated once: the coarse k row meets the b row at its best k, and the
    // start (1, 1) lies on the k row.
    let mut tried: Vec<(f64, f64, Scored)> = Vec::new();
    let mut score = |fk: f64, fb: f64| -> Scored {
        if let Some(&(_, _, known)) = tried.iter().find(|t| t.0 == fk && t.1 == fb) {
            return known;
        }
        let found = score_network(&scaled(fk, fb), physics, &takes);
        tried.push((fk, fb, found));
        found
    };
    let bar = train.progress.bar(
        (K_STEPS.count() + B_STEPS.count() + 2) as u64,
        "scale search",
    );
    let before = score(1.0, 1.0).map(|(_, r)| r);
    let mut best = (1.0, 1.0, physics.substeps, before.unwrap_or(f64::INFINITY));
    let mut consider = |fk: f64, fb: f64, best: &mut (f64, f64, usize, f64)| {
        if let Some((n, r)) = score(fk, fb)
            && r < best.3
        {
            *best = (fk, fb, n, r);
        }
        bar.inc(1);
    };
    for i in K_STEPS {
        consider(2f64.powf(i as f64 / 2.0), 1.0, &mut best);
    }
    let fk = best.0;
    for i in B_STEPS {
        consider(fk, 2f64.powi(i), &mut best);
    }
    let (fk, fb) = (best.0, best.1);
    for f in [-0.25, 0.25] {
        consider(fk * 2f64.powf(f), fb, &mut best);
    }
    bar.finish();
    let (fk, fb, substeps, after) = best;
    if !after.is_finite() {
        bail!("the scale search found no stable scaling of the trained network");
    }
    let net = scaled(fk, fb);
    let physics = Physics {
        substeps,
        ..*physics
    };
    let mut candidates: Vec<(f64, f64, usize, f64)> = tried
        .into_iter()
        .filter_map(|(fk, fb, found)| found.map(|(n, r)| (fk, fb, n, r)))
        .collect();
    candidates.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.total_cmp(&b.1)));
    let record = ScaleSearch {
        k_factor: fk,
        b_factor: fb,
        substeps,
        before,
        after,
        candidates,
        rollouts: files.len(),
    };
    Ok((net, physics, record))
}

/// `blend.json`'s `polish`: the kept network's size and damping descended once more at the
/// substeps it runs at, beside the best uniform network there.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Polish {
    /// Substeps per frame every candidate ran at: the searched network's fewest stable ones.
    pub substeps: usize,
    /// The best uniform network at these substeps, `(k, b, mean motion RMSE)`: the search
    /// `eval.uniform_baseline` and the held-out check run, from the same start on the same takes.
    pub uniform: (f64, f64, f64),
    /// Mean motion RMSE of the searched network at these substeps, m.
    pub before: f64,
    /// The factor of the searched network's `k` kept (its curvature elements' too).
    pub k_factor: f64,
    /// The factor of its `b` kept.
    pub b_factor: f64,
    /// Mean motion RMSE of the kept network, m.
    pub after: f64,
    /// Whether the uniform network was kept: no size or damping of the map moved as close.
    pub kept_uniform: bool,
    /// `(mean k, mean motion RMSE)` of every stable size of the map tried, sorted.
    pub search: Vec<(f64, f64)>,
    /// `(mean b, mean motion RMSE)` of every stable damping of the map tried, sorted.
    pub b_search: Vec<(f64, f64)>,
}

/// The searched network `model` polished at the substeps it runs at (`physics`, ours): the
/// searches before score every candidate at its own fewest stable substeps, but the step decides
/// a stiff, heavily damped cloth's motion as much as its parameters do — on Warp's stiff cloth
/// one uniform network moves 0.239 m from the training takes at 32 substeps and 0.246 m at 187,
/// and the best damping there is a thousand times the one found at 32 — while the run, its
/// evaluation and its uniform yardstick all run at `physics`. So here every candidate runs at
/// `physics` exactly: the best uniform network from `(k0, b0)` by the yardstick's own descent
/// (`eval.uniform_baseline`), and the same descent over the map's mean `k` and `b` (its shape
/// kept), each of its rows picked by the candidates' figures averaged with their neighbours'
/// (`uniform::Pick::Neighbourhood`: a free rollout's figure over a chaotic take jumps between
/// neighbouring sizes and dampings by more than the map's worth, and a lone dip among the
/// jumps is the training takes' chance); the closer by their own figures is kept (where the
/// pick is farther than the uniform network but another size of the map tried is not, the
/// closest of those), so on these takes the kept network never moves farther than the
/// yardstick does. Returns the kept network and the record.
pub fn polish(
    model: &SpringNet,
    physics: &Physics,
    (k0, b0): (f64, f64),
    train: &Takes,
) -> Result<(SpringNet, Polish)> {
    let files = search_files(train);
    let takes = Takes {
        files: &files,
        ..*train
    };
    let rmse = |net: &SpringNet| network_rollout_rmse(net, physics, &takes);
    let sizes = Sizes::of(model);
    let (k_mean, b_mean) = blend_means(&sizes.k, &sizes.b, physics.mass)?;
    let bar = train
        .progress
        .bar(2 * uniform::DESCENT_CANDIDATES, "polish");
    let flat = uniform::descend(
        &|k, b| rmse(&SpringNet::uniform(train.topology, k, b, train.device)),
        (k0, b0),
        physics.mass,
        uniform::Pick::Lowest,
        &bar,
    )?;
    let before = rmse(model).unwrap_or(f64::INFINITY);
    let map = uniform::descend(
        &|k, b| rmse(&sizes.scaled(train, k / k_mean, b / b_mean)),
        (k_mean, b_mean),
        physics.mass,
        uniform::Pick::Neighbourhood,
        &bar,
    )
    .ok();
    bar.finish();
    let record = |fk: f64, fb: f64, after: f64, kept_uniform: bool| Polish {
        substeps: physics.substeps,
        uniform: (flat.k, flat.b, flat.rmse),
        before,
        k_factor: fk,
        b_factor: fb,
        after,
        kept_uniform,
        search: map.as_ref().map_or(Vec::new(), |m| m.search.clone()),
        b_search: map.as_ref().map_or(Vec::new(), |m| m.b_search.clone()),
    };
    // The map's pick where it moves as close as the uniform network; else, where a size and
    // damping of it the descent tried does, the closest of those: the uniform network is kept
    // only where no size of the map moves as close.
    let kept = map.as_ref().and_then(|m| {
        if m.rmse <= flat.rmse {
            Some((m.k, m.b, m.rmse))
        } else {
            Some(m.lowest).filter(|l| l.2 <= flat.rmse)
        }
    });
    Ok(match kept {
        Some((k, b, rmse)) => {
            let (fk, fb) = (k / k_mean, b / b_mean);
            (sizes.scaled(train, fk, fb), record(fk, fb, rmse, false))
        }
        None => (
            SpringNet::uniform(train.topology, flat.k, flat.b, train.device),
            record(1.0, 1.0, flat.rmse, true),
        ),
    })
}

/// A network's per-spring values, read once, for the searches that scale them as a whole.
struct Sizes<'a> {
    model: &'a SpringNet,
    k: Vec<f64>,
    b: Vec<f64>,
    kappa: Vec<f64>,
}

impl<'a> Sizes<'a> {
    fn of(model: &'a SpringNet) -> Self {
        Self {
            model,
            k: model.k_values(),
            b: model.b_values(),
            kappa: model.curvature_values(),
        }
    }

    /// The network with every `k` times `fk` (the curvature elements too: they are
    /// stiffnesses) and every `b` times `fb`, on `takes`' springs and device.
    fn scaled(&self, takes: &Takes, fk: f64, fb: f64) -> SpringNet {
        self.with(takes, fk, &times(&self.b, fb))
    }

    /// The network with every `k` times `fk` (the curvature elements too) and every `b` set to
    /// `beta` times its spring's new `k`.
    fn proportional(&self, takes: &Takes, fk: f64, beta: f64) -> SpringNet {
        self.with(takes, fk, &times(&self.k, fk * beta))
    }

    /// The network with every `k` and curvature element times `fk` and the damping `b`.
    fn with(&self, takes: &Takes, fk: f64, b: &[f64]) -> SpringNet {
        self.with_family(takes, fk, (SpringFamily::Shear, 1.0), b)
    }

    /// [`Self::with`] with the `k` of the springs of `family.0` times `family.1` on top of `fk`.
    fn with_family(
        &self,
        takes: &Takes,
        fk: f64,
        family: (SpringFamily, f64),
        b: &[f64],
    ) -> SpringNet {
        let mut k = times(&self.k, fk);
        takes.topology.scale_family(&mut k, family.0, family.1);
        SpringNet::new(takes.topology, &k, b, takes.device)
            .with_kernel(self.model.graph.kernel)
            .with_curvature(&times(&self.kappa, fk))
    }
}

/// Every value of `v` times `f`.
fn times(v: &[f64], f: f64) -> Vec<f64> {
    v.iter().map(|x| x * f).collect()
}

/// Drag rates `γ = c/m` the drag row tries besides none and octaves around the run's, s⁻¹.
pub const DRAG_RATES: [f64; 4] = [0.1, 0.3, 1.0, 3.0];

/// The drag `sim.rayleigh` searched after the polish where the run fitted it (ours): the least-
/// squares fit of the frames' forces with the uniform start lets the drag absorb what one `b`
/// cannot explain, which can cost a map a third of its error over a take (MuJoCo's), while on
/// tpcloth no drag at all moves the map farther over a whole take, on the held-out takes as on
/// the test takes, and lets the yardstick trade the drag for near-critical spring damping. So a
/// row of drags runs at the polished map's size on the training takes, the map is polished again
/// at the closest, and that drag is kept only where the polished map moves closer to the held-out
/// training takes than at the fitted drag, at both horizons.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DragSearch {
    /// The run's drag, fitted by least squares (N·s/m).
    pub fitted: f64,
    /// `(drag, mean motion RMSE on the training takes)` of the polished map for every stable
    /// drag of the row ([`drag_row`]), sorted by drag.
    pub row: Vec<(f64, f64)>,
    /// The drag of the row the map moved closest at.
    pub best: f64,
    /// The polish again at `best`; `None` where `best` is the fitted drag.
    pub polish: Option<Polish>,
    /// `(short, long)` motion RMSE on the held-out training takes of the map polished at the
    /// fitted drag, and at `best` (m); `None` where `best` is the fitted drag.
    pub held_out: Option<((f64, f64), (f64, f64))>,
    /// The drag the run keeps.
    pub kept: f64,
}

impl DragSearch {
    /// `(short, long)` motion RMSE on the held-out training takes of the network the run keeps,
    /// where the search measured it.
    pub fn held_out_kept(&self) -> Option<(f64, f64)> {
        self.held_out.map(|(fitted, best)| {
            if self.kept == self.fitted {
                fitted
            } else {
                best
            }
        })
    }
}

/// `(drag, mean motion RMSE on the first training takes)` of `model` for every stable drag of a
/// row around `physics.rayleigh` (itself, none, octaves `2^±1…±3` around it, and rates
/// `γ = c/m` of [`DRAG_RATES`]), sorted by drag; `model`'s `k` and `b` are kept. `at_run` is
/// `model`'s RMSE at `physics` where known (the polish measured it), so it is not simulated again.
pub fn drag_row(
    model: &SpringNet,
    physics: &Physics,
    at_run: Option<f64>,
    train: &Takes,
) -> Vec<(f64, f64)> {
    let files = search_files(train);
    let takes = Takes {
        files: &files,
        ..*train
    };
    let c0 = physics.rayleigh;
    let octaves = [-3, -2, -1, 1, 2, 3].map(|i| c0 * 2f64.powi(i));
    let rates = DRAG_RATES.map(|g| g * physics.mass);
    let mut drags: Vec<f64> = std::iter::once(c0)
        .chain(std::iter::once(0.0))
        .chain(octaves.into_iter().filter(|c| *c > 0.0))
        .chain(rates)
        .collect();
    drags.sort_by(f64::total_cmp);
    drags.dedup();
    let bar = train.progress.bar(drags.len() as u64, "drag row");
    let row = drags
        .into_iter()
        .filter_map(|c| {
            let r = match at_run {
                Some(r) if c == c0 => Some(r),
                _ => {
                    let p = Physics {
                        rayleigh: c,
                        ..*physics
                    };
                    network_rollout_rmse(model, &p, &takes)
                }
            };
            bar.inc(1);
            r.map(|r| (c, r))
        })
        .collect();
    bar.finish();
    row
}

/// Damping rates `β = b/k` the proportional-damping row tries: `h · 2^i` for `i` in this
/// range, `h` the run's substep, up to the first that is unstable at the run's substeps or
/// diverges (a stiff cloth's substeps leave room for `β ≈ h` at most), or the second in a row
/// that moves farther than the one before.
pub const BETA_STEPS: std::ops::RangeInclusive<i32> = -6..=12;

/// Which damping [`proportional_damping`] makes proportional to each spring's stiffness.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Proportional {
    /// Each spring's `b` along itself: `b_s = β k_s` (MuJoCo's damping; `blend.json`'s
    /// `damping`).
    Springs,
    /// An isotropic viscosity `β k_s (v_b − v_a)` on each spring besides its `b`
    /// (`sim.viscosity`; Warp's FEM damping; `blend.json`'s `viscosity`).
    Viscosity,
}

impl Proportional {
    /// How the logs and the progress bar name it.
    pub fn name(self) -> &'static str {
        match self {
            Self::Springs => "proportional damping",
            Self::Viscosity => "viscosity",
        }
    }

    /// The form in words, for the logs.
    pub fn form(self) -> &'static str {
        match self {
            Self::Springs => "b = β k",
            Self::Viscosity => "a viscosity β k on each spring",
        }
    }
}

/// Damping proportional to stiffness, in place of a searched drag (ours; `blend.json`'s
/// `damping` for the springs' `b`, [`Proportional::Springs`], and `viscosity` for an isotropic
/// viscosity, [`Proportional::Viscosity`]).
///
/// Spring damping, `b_s = β k_s`: MuJoCo's flex cloth damps each edge along itself by `β k` (its `damping`), with no
/// drag, and a cloth whose damping follows its stiffness map is damped by neither one learned
/// `b` shape nor an air drag. On MuJoCo's stiff takes the learned map, replayed with
/// `b = 2·10⁻⁵ s · k` and no drag, moves 28 % closer over the whole take than with the fitted
/// drag and its own `b` (`benches/foreign/damping_probe.py`). So after the drag search a row of
/// `β` runs at the map's stiffness with the drag at zero, the map's size is searched around the
/// best, then `β` once more; the result is kept only where the held-out training takes prefer it
/// to the network kept so far ([`held_out_agrees`]).
///
/// Viscosity, `β k_s (v_b − v_a)` on each spring (`sim.viscosity`): Warp's FEM triangles damp
/// the whole velocity gradient (`k_damp · dF/dt`, with `k_damp` following the stiffness map on
/// the bench), rotations and bending included, which neither a spring's `b` nor a drag carries.
/// The same search runs with the springs' `b` kept and the viscosity's `β` in place of theirs.
///
/// Both replace a drag the run searched (an air drag fitted to the frames stands in for the
/// damping the source has); where the files or the config state the drag, it is kept beside
/// them. An implicit solver's own damping is of this form: a backward Euler step of `h` damps
/// a spring's mode like a viscosity `β ≈ h` times its stiffness, so a stiff cloth baked by
/// Blender's implicit solver, whose files state its air drag, carries one too.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ProportionalDamping {
    /// `(β s, k factor, mean motion RMSE on the training takes)` of every stable candidate, in
    /// the order tried.
    pub candidates: Vec<(f64, f64, f64)>,
    /// The closest candidate's `β`, s.
    pub beta: f64,
    /// The closest candidate's factor on the map's `k` (its curvature elements' too).
    pub k_factor: f64,
    /// The closest candidate's mean motion RMSE on the training takes, m.
    pub after: f64,
    /// `(short, long)` motion RMSE on the held-out training takes of the network kept before,
    /// and of the closest candidate (m).
    pub held_out: Option<((f64, f64), (f64, f64))>,
    /// Whether the run keeps it.
    pub kept: bool,
}

/// Whether the held-out training takes prefer the `after` network's `(short, long)` motion RMSE
/// over `before`'s: the two horizons' ratios `after / before` multiply to less than 1, so a
/// change that moves the takes farther at one horizon is kept only where it moves them closer
/// at the other by more, both counted as shares, as the goal counts its gains. A strict test
/// at both horizons lets the less informative one decide: the damping barely moves a cloth in
/// its first 0.8 s (on a spring cloth damped by `b = β k` the source's damping moves the
/// held-out takes 16 % closer over the take and 0.02 % farther at 0.8 s), and with two
/// held-out takes the short horizon's figure moves as much as 17 % with the drag alone
/// (Warp stiff, the book's Other simulators).
pub fn held_out_agrees(before: (f64, f64), after: (f64, f64)) -> bool {
    (after.0 / before.0) * (after.1 / before.1) < 1.0
}

/// The closest network with damping proportional to stiffness (`form`) on the first training
/// takes ([`ProportionalDamping`]), with `physics`' drag where `keep_drag` (the data or the
/// config state it), else none: a row of `β` ([`BETA_STEPS`]) at `model`'s `k`, the factors
/// `2^(±1/2, ±1)` of its `k` at the best `β`, then `β · 2^(±1/2)`. Returns the network, the
/// physics it runs at (the drag, `physics`' substeps, and for [`Proportional::Viscosity`] the
/// viscosity `β`) and the record (not yet judged on held-out takes); `None` where no candidate
/// is stable.
pub fn proportional_damping(
    model: &SpringNet,
    physics: &Physics,
    train: &Takes,
    form: Proportional,
    keep_drag: bool,
) -> Option<(SpringNet, Physics, ProportionalDamping)> {
    let rayleigh = if keep_drag { physics.rayleigh } else { 0.0 };
    let files = search_files(train);
    let takes = Takes {
        files: &files,
        ..*train
    };
    let sizes = Sizes::of(model);
    let candidate = |beta: f64, fk: f64| match form {
        Proportional::Springs => (
            sizes.proportional(train, fk, beta),
            Physics {
                rayleigh,
                ..*physics
            },
        ),
        Proportional::Viscosity => (
            sizes.scaled(train, fk, 1.0),
            Physics {
                rayleigh,
                viscosity: beta,
                ..*physics
            },
        ),
    };
    let h = physics.frame_dt / physics.substeps as f64;
    let bar = train
        .progress
        .bar(BETA_STEPS.count() as u64 + 6, form.name());
    let mut candidates: Vec<(f64, f64, f64)> = Vec::new();
    let consider = |beta: f64, fk: f64, candidates: &mut Vec<(f64, f64, f64)>| {
        let (net, at) = candidate(beta, fk);
        let found = network_rollout_rmse(&net, &at, &takes);
        if let Some(r) = found {
            candidates.push((beta, fk, r));
        }
        bar.inc(1);
        found.is_some()
    };
    for i in BETA_STEPS {
        if !consider(h * 2f64.powi(i), 1.0, &mut candidates) {
            break;
        }
        // Past the closest, two octaves in a row that move farther end the row.
        if let [.., x, y, z] = candidates[..]
            && z.2 > y.2
            && y.2 > x.2
        {
            break;
        }
    }
    let (beta, _, _) = closest(&candidates)?;
    for f in [-1.0, -0.5, 0.5, 1.0] {
        consider(beta, 2f64.powf(f), &mut candidates);
    }
    let (beta, fk, _) = closest(&candidates)?;
    for f in [-0.5, 0.5] {
        consider(beta * 2f64.powf(f), fk, &mut candidates);
    }
    bar.finish();
    let (beta, k_factor, after) = closest(&candidates)?;
    let (net, at) = candidate(beta, k_factor);
    Some((
        net,
        at,
        ProportionalDamping {
            candidates,
            beta,
            k_factor,
            after,
            held_out: None,
            kept: false,
        },
    ))
}

/// The closest of a row's candidates `(value, k factor, mean motion RMSE)`: the least RMSE.
fn closest(candidates: &[(f64, f64, f64)]) -> Option<(f64, f64, f64)> {
    candidates
        .iter()
        .copied()
        .min_by(|a, b| a.2.total_cmp(&b.2))
}

/// The shear springs' stiffness in compression per unit `k` that [`shear_compression`] tries
/// beside the run's ([`crate::sim::SimConfig::shear_compression`]): from linear springs to
/// springs that pull only.
pub const SHEAR_COMPRESSIONS: [f64; 4] = [1.0, 0.5, 0.25, 0.0];

/// The shear springs' shares of their stiffness that [`shear_compression`] tries beside the
/// network's own (1), half an octave apart: their `k` times each. No other search sizes a cell's
/// diagonals apart from its sides, which keep whatever share of the sides' stiffness the map
/// read off the frames (0.43-0.55 of it on the bench's FEM runs): on a square spring lattice
/// that share sets the sheet's shear stiffness, and halving it moved Newton stiff, Newton soft
/// and Warp soft 5-7 % closer over their 48 test takes (the book, "Other simulators").
pub const SHEAR_SHARES: [f64; 3] = [
    std::f64::consts::FRAC_1_SQRT_2,
    0.5,
    0.5 * std::f64::consts::FRAC_1_SQRT_2,
];

/// One setting of the shear springs searched by [`shear_compression`], with the network's `k`
/// factor.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ShearSetting {
    /// Stiffness in compression per unit `k` (`sim.shear_compression`).
    pub shear_compression: f64,
    /// Factor on the shear springs' `k` (their share of the network's stiffness), on top of
    /// `k_factor`.
    #[serde(default = "one")]
    pub shear_share: f64,
    /// Factor on the network's `k` (its curvature elements' too).
    pub k_factor: f64,
}

impl ShearSetting {
    /// The network as it is: its own stiffness in compression `shear_compression`.
    pub fn unchanged(shear_compression: f64) -> Self {
        Self {
            shear_compression,
            shear_share: 1.0,
            k_factor: 1.0,
        }
    }

    /// Whether `other` sets the shear springs alike (the `k` factor aside).
    pub fn same_shear(&self, other: &Self) -> bool {
        self.shear_compression == other.shear_compression && self.shear_share == other.shear_share
    }
}

/// A stable candidate of [`shear_compression`] and its score.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ShearCandidate {
    /// What it sets.
    #[serde(flatten)]
    pub setting: ShearSetting,
    /// The searches' objective on the training takes searched, m.
    pub rmse: f64,
}

/// The search of the shear springs' stiffness in compression (`sim.shear_compression`) and their
/// share of the network's stiffness (ours; `blend.json`'s `shear_compression`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CompressionSearch {
    /// Every stable candidate, in the order tried.
    pub candidates: Vec<ShearCandidate>,
    /// Each setting of the shear springs' closest candidate on the training takes
    /// ([`finalists`]) with its figures on the held-out training takes, in the order tried.
    #[serde(default)]
    pub finalists: Vec<Finalist>,
    /// What the finalist closest to the training takes searched and the held-out ones together
    /// sets (the closest on the training takes searched where none was held out),
    #[serde(flatten)]
    pub setting: ShearSetting,
    /// and its mean motion RMSE on the training takes, m.
    pub after: f64,
    /// `(short, long)` motion RMSE on the held-out training takes of the network kept before,
    /// and of that finalist (m); `None` where it is the network as it was.
    pub held_out: Option<((f64, f64), (f64, f64))>,
    /// Whether the run keeps it.
    pub kept: bool,
}

/// One setting of the shear springs' closest candidate on the training takes, judged on the
/// held-out training takes too ([`CompressionSearch::finalists`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Finalist {
    /// What it sets.
    #[serde(flatten)]
    pub setting: ShearSetting,
    /// The searches' objective on the training takes searched (mean motion RMSE over the whole
    /// take unless `train.search_objective` says otherwise), m.
    pub train: f64,
    /// `(short, long)` motion RMSE on the held-out training takes, m.
    pub held_out: (f64, f64),
    /// The searches' objective on the training takes searched and the held-out ones together,
    /// each set weighed by its number of takes ([`pooled`]), m.
    pub pooled: f64,
}

/// The searches' objective over two sets of takes together: `(score, takes)` each, weighed by
/// their number of takes.
pub fn pooled(a: (f64, usize), b: (f64, usize)) -> f64 {
    (a.0 * a.1 as f64 + b.0 * b.1 as f64) / (a.1 + b.1) as f64
}

/// Each setting of the shear springs' closest candidate of `candidates`, in the order the
/// settings first appear.
pub fn finalists(candidates: &[ShearCandidate]) -> Vec<ShearCandidate> {
    let mut out: Vec<ShearCandidate> = Vec::new();
    for &c in candidates {
        match out.iter_mut().find(|f| f.setting.same_shear(&c.setting)) {
            Some(f) if c.rmse < f.rmse => *f = c,
            Some(_) => {}
            None => out.push(c),
        }
    }
    out
}

/// `model` with its `k` (and curvature elements) times `setting.k_factor` and its shear springs'
/// `k` times `setting.shear_share` too, and `physics` with the shear springs' stiffness in
/// compression `setting.shear_compression`: a candidate of [`shear_compression`].
pub fn compression_candidate(
    model: &SpringNet,
    physics: &Physics,
    train: &Takes,
    setting: ShearSetting,
) -> (SpringNet, Physics) {
    let sizes = Sizes::of(model);
    (
        sizes.with_family(
            train,
            setting.k_factor,
            (SpringFamily::Shear, setting.shear_share),
            &sizes.b,
        ),
        Physics {
            shear_compression: setting.shear_compression,
            ..*physics
        },
    )
}

/// The search of `model`'s shear springs on the training takes searched ([`CompressionSearch`]):
/// `physics`' own stiffness in compression at `model`'s `k` and `b`, every other value of
/// [`SHEAR_COMPRESSIONS`], and at `physics`' own each share of [`SHEAR_SHARES`], each at its `k`
/// and at the factors `2^(±1/2)` of it. A softer cloth wants stiffer springs, and the network was
/// sized with `physics`' own and its shear springs as they are: searched one after the other,
/// the setting closest at the sized `k` need not be the closest at its best `k`. Returns the
/// record with the closest candidate (not yet judged on held-out takes: the run judges the
/// [`finalists`]) and the number of takes searched; `None` where the network has no shear
/// springs or no candidate is stable.
pub fn shear_compression(
    model: &SpringNet,
    physics: &Physics,
    train: &Takes,
) -> Option<(CompressionSearch, usize)> {
    if !train.topology.family.contains(&SpringFamily::Shear) {
        return None;
    }
    let files = search_files(train);
    let takes = Takes {
        files: &files,
        ..*train
    };
    let own = physics.shear_compression;
    let settings: Vec<(f64, f64)> = SHEAR_COMPRESSIONS
        .iter()
        .filter(|&&kc| kc != own)
        .map(|&kc| (kc, 1.0))
        .chain(SHEAR_SHARES.iter().map(|&share| (own, share)))
        .collect();
    let bar = train
        .progress
        .bar(1 + 3 * settings.len() as u64, "shear springs' search");
    let mut candidates: Vec<ShearCandidate> = Vec::new();
    let mut consider = |setting: ShearSetting| {
        let (net, at) = compression_candidate(model, physics, train, setting);
        if let Some(rmse) = network_rollout_rmse(&net, &at, &takes) {
            candidates.push(ShearCandidate { setting, rmse });
        }
        bar.inc(1);
    };
    consider(ShearSetting::unchanged(own));
    for &(shear_compression, shear_share) in &settings {
        for f in [0.0, -0.5, 0.5] {
            consider(ShearSetting {
                shear_compression,
                shear_share,
                k_factor: 2f64.powf(f),
            });
        }
    }
    bar.finish();
    let best = candidates
        .iter()
        .copied()
        .min_by(|a, b| a.rmse.total_cmp(&b.rmse))?;
    let record = CompressionSearch {
        candidates,
        finalists: Vec::new(),
        setting: best.setting,
        after: best.rmse,
        held_out: None,
        kept: false,
    };
    Some((record, files.len()))
}

#[cfg(test)]
mod tests {
    use burn::tensor::Device;

    use super::{
        MAX_SUBSTEP_FACTOR, STIFF_SUBSTEP_FACTOR, ShearCandidate, ShearSetting, amplified,
        compression_candidate, finalists, held_out_agrees, pooled, stable_substeps,
    };
    use crate::cloth::{GridSpec, SpringFamily, Topology};
    use crate::eval::Takes;
    use crate::model::SpringNet;
    use crate::sim::Physics;
    use crate::train::init::AUTO_SUBSTEPS_TARGET;

    /// The paper's 32 × 32 cloth's step at 30 fps and 4 substeps, without drag.
    fn grid_physics() -> Physics {
        Physics {
            frame_dt: 1.0 / 30.0,
            substeps: 4,
            mass: 0.5 / 1024.0,
            rayleigh: 0.0,
            gravity: [0.0, 0.0, -9.81],
            viscosity: 0.0,
            shear_compression: 1.0,
        }
    }

    #[test]
    fn each_shear_setting_s_finalist_is_its_closest_candidate() {
        let c =
            |shear_compression: f64, shear_share: f64, k_factor: f64, rmse: f64| ShearCandidate {
                setting: ShearSetting {
                    shear_compression,
                    shear_share,
                    k_factor,
                },
                rmse,
            };
        let (r2, h) = (2f64.sqrt(), 0.5f64.sqrt());
        let candidates = [
            c(1.0, 1.0, 1.0, 0.246),
            c(0.5, 1.0, 1.0, 0.2375),
            c(0.5, 1.0, h, 0.247),
            c(0.5, 1.0, r2, 0.242),
            c(0.25, 1.0, 1.0, 0.241),
            c(0.25, 1.0, r2, 0.2372),
            c(0.0, 1.0, r2, 0.307),
            // The shares at the network's own stiffness in compression are settings of their
            // own, not the network as it is.
            c(1.0, h, 1.0, 0.25),
            c(1.0, h, r2, 0.239),
            c(1.0, 0.5, h, 0.26),
        ];
        assert_eq!(
            finalists(&candidates),
            vec![
                c(1.0, 1.0, 1.0, 0.246),
                c(0.5, 1.0, 1.0, 0.2375),
                c(0.25, 1.0, r2, 0.2372),
                c(0.0, 1.0, r2, 0.307),
                c(1.0, h, r2, 0.239),
                c(1.0, 0.5, h, 0.26),
            ]
        );
        assert!(finalists(&[]).is_empty());
    }

    #[test]
    fn a_shear_share_scales_the_shear_springs_alone_on_top_of_the_k_factor() {
        let topology = Topology::grid(&GridSpec::default(), 1.0, 1.0);
        let device = Device::flex();
        let n = topology.num_springs();
        let k: Vec<f64> = (0..n).map(|s| 10.0 + (s % 7) as f64).collect();
        let b: Vec<f64> = (0..n).map(|s| 0.1 + 0.01 * (s % 5) as f64).collect();
        let model = SpringNet::new(&topology, &k, &b, &device);
        let physics = grid_physics();
        let progress = crate::progress::Progress::quiet();
        let takes = Takes {
            topology: &topology,
            files: &[],
            batch: 1,
            device: &device,
            progress: &progress,
            cache: None,
            objective: crate::eval::Objective::WholeTake,
        };
        let setting = ShearSetting {
            shear_compression: 0.25,
            shear_share: 0.5,
            k_factor: 2.0,
        };
        let (net, at) = compression_candidate(&model, &physics, &takes, setting);
        assert_eq!(at.shear_compression, 0.25);
        let shear = topology
            .family
            .iter()
            .filter(|&&f| f == SpringFamily::Shear)
            .count();
        assert!(shear > 0 && shear < n);
        for ((got, k), family) in net.k_values().iter().zip(&k).zip(&topology.family) {
            let want = if *family == SpringFamily::Shear {
                *k
            } else {
                2.0 * k
            };
            assert!((got - want).abs() < 1e-4 * want, "{got} vs {want}");
        }
        for (got, b) in net.b_values().iter().zip(&b) {
            assert!((got - b).abs() < 1e-4 * b, "{got} vs {b}");
        }
    }

    #[test]
    fn the_held_out_takes_break_a_tie_on_the_takes_searched_and_not_a_margin() {
        // tpcloth stiff at 30 fps: ¼ at k × √2 and ½ at k tie on ten takes searched; two held
        // out tell them apart.
        let quarter = pooled((0.23722, 10), (0.25170, 2));
        let half = pooled((0.23751, 10), (0.23092, 2));
        assert!(half < quarter, "{half} vs {quarter}");
        // Blender stiff at 24 fps: 0 at k × √2 is 17 % closer on the ten, farther on the two.
        let none = pooled((0.15774, 10), (0.29955, 2));
        let quarter = pooled((0.18937, 10), (0.25434, 2));
        assert!(none < quarter, "{none} vs {quarter}");
        // Equal counts weigh equally.
        assert_eq!(pooled((1.0, 3), (3.0, 3)), 2.0);
    }

    #[test]
    fn a_map_s_contrast_is_raised_within_each_family_keeping_its_mean_ranks_and_zeros() {
        use SpringFamily::{Bending, Shear, Structural};
        let family = [
            Structural, Structural, Structural, Shear, Shear, Bending, Bending,
        ];
        let k = [10.0, 20.0, 60.0, 5.0, 15.0, 0.0, 2.0];
        // α = 1 is the map itself.
        for (a, b) in amplified(&k, &family, 1.0).iter().zip(&k) {
            assert!((a - b).abs() < 1e-12, "{a} vs {b}");
        }
        let out = amplified(&k, &family, 2.0);
        let mean =
            |idx: &[usize], v: &[f64]| idx.iter().map(|&i| v[i]).sum::<f64>() / idx.len() as f64;
        for idx in [&[0, 1, 2][..], &[3, 4], &[5, 6]] {
            assert!(
                (mean(idx, &out) - mean(idx, &k)).abs() < 1e-9,
                "a family's mean moved"
            );
        }
        // Squared contrast: 10, 20, 60 (mean 30) -> k² / 30 = 10/3, 40/3, 120, rescaled to the
        // mean 30.
        let want = [10.0 / 3.0, 40.0 / 3.0, 120.0];
        let scale = 30.0 / ((want[0] + want[1] + want[2]) / 3.0);
        for (i, w) in want.iter().enumerate() {
            assert!(
                (out[i] - w * scale).abs() < 1e-9,
                "spring {i}: {} vs {}",
                out[i],
                w * scale
            );
        }
        assert!(out[2] / out[0] > k[2] / k[0], "the contrast did not rise");
        assert_eq!(out[5], 0.0, "a spring at zero left zero");
        assert!(out[6] > 0.0 && out[3] < out[4]);
    }

    #[test]
    fn a_search_reaches_a_network_up_to_its_substep_caps_and_no_further() {
        let topo = Topology::grid(&GridSpec::default(), 2.0, 2.0);
        let physics = grid_physics();
        let device = Device::flex();
        let net = |k: f64, b: f64| SpringNet::uniform(&topo, k, b, &device);
        // The substeps a uniform network needs, uncapped.
        let needs = |k: f64, b: f64| {
            physics
                .stability_of(&topo, &net(k, b))
                .fewest_substeps(physics.frame_dt, 1..=1_000_000, AUTO_SUBSTEPS_TARGET)
                .unwrap()
        };
        let searched = |k: f64, b: f64| stable_substeps(&topo, &physics, &net(k, b));
        let cap = MAX_SUBSTEP_FACTOR * physics.substeps;
        let stiff_cap = STIFF_SUBSTEP_FACTOR * physics.substeps;
        // An undamped network that asks for three quarters of the cap (ω ∝ √k) is reached at
        // its fewest.
        let near_cap = (1..)
            .map(|i| 10.0 * 1.05f64.powi(i))
            .find(|&k| 4 * needs(k, 0.0) >= 3 * cap)
            .unwrap();
        assert!(needs(near_cap, 0.0) > physics.substeps);
        assert!(needs(near_cap, 0.0) <= cap);
        assert_eq!(searched(near_cap, 0.0), Some(needs(near_cap, 0.0)));
        // One four times as stiff asks for about twice its substeps, past the cap but within the
        // stiff cap, and its stiffness sets them: reached.
        let beyond = near_cap * 4.0;
        assert!(needs(beyond, 0.0) > cap && needs(beyond, 0.0) <= stiff_cap);
        assert_eq!(searched(beyond, 0.0), Some(needs(beyond, 0.0)));
        // Sixteen times as stiff, past the stiff cap: refused.
        assert!(needs(near_cap * 16.0, 0.0) > stiff_cap);
        assert_eq!(searched(near_cap * 16.0, 0.0), None);
        // A soft network damped so that it asks for as many substeps as `beyond`, its damping
        // setting them: refused.
        let soft = near_cap / 16.0;
        let damped = (1..)
            .map(|i| 1e-4 * 1.05f64.powi(i))
            .find(|&b| needs(soft, b) >= needs(beyond, 0.0))
            .unwrap();
        assert!(needs(soft, damped) > cap && needs(soft, damped) <= stiff_cap);
        assert_eq!(searched(soft, damped), None);
    }

    #[test]
    fn the_held_out_verdict_weighs_both_horizons_as_shares() {
        // Closer at both horizons, or at one by more than farther at the other: kept.
        assert!(held_out_agrees((0.10, 0.30), (0.09, 0.29)));
        assert!(held_out_agrees((0.10, 0.30), (0.11, 0.24)));
        assert!(held_out_agrees((0.10, 0.30), (0.08, 0.32)));
        // Farther at both, or farther at one by more than closer at the other: refused.
        assert!(!held_out_agrees((0.10, 0.30), (0.11, 0.31)));
        assert!(!held_out_agrees((0.10, 0.30), (0.13, 0.27)));
        assert!(!held_out_agrees((0.10, 0.30), (0.095, 0.33)));
        // Unchanged: refused (the network kept so far stays).
        assert!(!held_out_agrees((0.10, 0.30), (0.10, 0.30)));
    }
}
