//! What the source's own stiffness map is worth as this surrogate's `k`.
//!
//! When the rollouts carry the source's stiffness map (`tri_stiffness`, as the cross-simulator
//! bench and the FEM source write it), a network is built whose structural springs follow that
//! map exactly, and so do its shear springs — `k_s = k̄ · m_s / m̄`, with `m_s` the map at the
//! spring's rest midpoint (as `stiffness_map_corr` reads it) and `m̄` its mean; the bending
//! springs at a share of `k̄`, every `b` at `b̄`, `(k̄, b̄)` the best uniform network of
//! `eval.json` — and sized on the training takes: the scale search ([`train::scale::search`]:
//! one factor for every `k`, one for every `b`) at each share of the bending springs
//! ([`train::scale::BENDING_FACTORS`], and 1), the closest kept. The best uniform network is
//! searched again at the sized network's step (a finer explicit step alone moves a network
//! closer), and both are simulated on the test takes as `eval` does.
//!
//! Its gain over the best uniform network is what a perfectly ranked map (Spearman 1) wins when
//! sized like the recipe's maps. It is a reference, not a bound: a learned map may beat it (on an
//! irregular FEM mesh the right spring `k` depends on the triangles' shapes as well as on the
//! material, and a learned map can absorb some of the model's mismatch). Where the source's own
//! map wins little, the motion the surrogate misses is not in `k`'s spatial variation.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use serde::{Deserialize, Serialize};

use super::Inputs;
use crate::cloth::SpringFamily;
use crate::data::Rollout;
use crate::eval::{self, EvalReport, MotionRmse, Takes};
use crate::model::SpringNet;
use crate::progress::Progress;
use crate::sim::Physics;
use crate::train::{self, scale::ScaleSearch};

/// `source_map.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SourceMap {
    /// Where `(k̄, b̄)` came from: `"uniform_baseline"` (eval.json's best uniform network) or
    /// `"learned_mean"` (the learned network's means, when eval.json has no uniform baseline).
    pub start: String,
    /// `k̄`, N/m.
    pub k_uniform: f64,
    /// `b̄`, N·s/m.
    pub b_uniform: f64,
    /// The last scale search of the map network on the training takes (at the kept share).
    pub search: ScaleSearch,
    /// The share of the bending springs' stiffness kept (their `k` over the shear springs').
    pub bending_factor: f64,
    /// `(share, mean motion RMSE on the training takes)` of every share sized, share 1 first
    /// (each at its own sizes).
    pub bending_search: Vec<(f64, f64)>,
    /// The best uniform network at the map network's step, searched on the training takes
    /// from `(k̄, b̄)`, and its test figures.
    pub uniform: eval::uniform::UniformBaseline,
    /// The map network on the test takes.
    pub map: MotionRmse,
    /// `1 − map / uniform` at the short horizon.
    pub gain_short: f64,
    /// The same over the long horizon.
    pub gain_long: f64,
    /// The run's own gains over the best uniform network (eval.json), short and long.
    pub run_gain: Option<[f64; 2]>,
    /// Springs that follow the map (the structural and shear ones).
    pub springs: usize,
}

/// The reference, or why it could not be measured.
pub enum Outcome {
    /// The reference.
    Measured(Box<SourceMap>),
    /// Why not (a note for `diagnose.md`).
    Skipped(String),
}

/// Sizes the source's own stiffness map on a run's surrogate and measures it against the best
/// uniform network; skipped (with the reason) where the rollouts carry no map.
pub fn source_map(
    inputs: &Inputs,
    run_dir: &Path,
    train_files: &[PathBuf],
    progress: &Progress,
) -> Result<Outcome> {
    let map = match springs_on_map(inputs, train_files)? {
        Ok(map) => map,
        Err(why) => return Ok(Outcome::Skipped(why)),
    };
    let first = &inputs.tests[0];
    let report = crate::report::read_eval(&train::RunDir {
        dir: run_dir.to_path_buf(),
    })?;
    let (start, k_uniform, b_uniform) = uniform_start(report.as_ref(), inputs);
    let physics = inputs.physics(first.frame_dt);
    let batch = inputs.config.eval.batch;
    let cache = eval::TrackCache::default();
    let takes = |files| Takes {
        topology: &inputs.topology,
        files,
        batch,
        device: &inputs.device,
        progress,
        cache: Some(&cache),
        objective: eval::Objective::WholeTake,
    };
    let Sized {
        net: sized,
        physics: sized_physics,
        search,
        bending_factor,
        bending,
    } = size_map(
        inputs,
        &map,
        (k_uniform, b_uniform),
        &physics,
        &takes(train_files),
    )?;
    let test_files: Vec<PathBuf> = inputs.tests.iter().map(|t| t.path.clone()).collect();
    let curves = eval::motion_curves(&sized, &sized_physics, &takes(&test_files))
        .context("the map network on the test takes")?;
    let eval_config = &inputs.config.eval;
    let mapped = eval::summarize(
        &curves.curves,
        sized_physics.frame_dt,
        eval_config.short_seconds,
        eval_config.long_seconds,
    );
    // The best uniform network at the map network's step: a finer step alone moves an explicit
    // network closer (less numerical damping), so both are compared at the same one.
    let uniform = eval::uniform::search(
        &inputs.topology,
        &sized_physics,
        (k_uniform, b_uniform),
        train_files,
        &test_files,
        &mapped,
        eval_config,
        eval::Objective::WholeTake,
        true,
        &inputs.device,
        progress,
    )
    .context("the best uniform network at the map network's step")?;
    let run_gain = report
        .and_then(|r| r.uniform_baseline)
        .map(|u| [u.improvement_short, u.improvement_long]);
    Ok(Outcome::Measured(Box::new(SourceMap {
        start: start.into(),
        k_uniform,
        b_uniform,
        gain_short: uniform.improvement_short,
        gain_long: uniform.improvement_long,
        search,
        bending_factor,
        bending_search: bending,
        uniform,
        map: mapped,
        run_gain,
        springs: map.len(),
    })))
}

/// The source's map at the run's structural and shear springs (`(spring, value)`, from the first
/// test rollout), or why there is no reference.
fn springs_on_map(
    inputs: &Inputs,
    train_files: &[PathBuf],
) -> Result<std::result::Result<Vec<(usize, f64)>, String>> {
    let Some(first) = inputs.tests.first() else {
        return Ok(Err("no test rollouts".into()));
    };
    let rollout = Rollout::load(&first.path)?;
    let Some(map) = rollout.mesh.as_ref().and_then(|mesh| {
        eval::map_at_springs(
            &inputs.topology,
            &rollout.rest_uv,
            mesh,
            &[SpringFamily::Structural, SpringFamily::Shear],
        )
    }) else {
        return Ok(Err(
            "no source-map reference: the rollouts carry no stiffness map of their source (tri_stiffness)"
                .into(),
        ));
    };
    if train_files.is_empty() {
        return Ok(Err(
            "no source-map reference: the run's training rollouts are gone".into(),
        ));
    }
    Ok(Ok(map))
}

/// Where the map network's sizes start: eval.json's best uniform network, else the learned
/// network's means (`(start, k̄, b̄)`, see [`SourceMap::start`]).
fn uniform_start(report: Option<&EvalReport>, inputs: &Inputs) -> (&'static str, f64, f64) {
    match report.and_then(|r| r.uniform_baseline.as_ref()) {
        Some(u) => ("uniform_baseline", u.k, u.b),
        None => {
            let mean = |v: Vec<f64>| v.iter().sum::<f64>() / v.len().max(1) as f64;
            (
                "learned_mean",
                mean(inputs.model.k_values()),
                mean(inputs.model.b_values()),
            )
        }
    }
}

/// The source's map sized on the training takes.
struct Sized {
    net: SpringNet,
    physics: Physics,
    search: ScaleSearch,
    bending_factor: f64,
    bending: Vec<(f64, f64)>,
}

/// The sizes of the map network from `(k̄, b̄)` at each share of the bending springs (the
/// surrogate's own: no source has them), and the closest kept where it moves
/// [`train::scale::BENDING_MARGIN`] closer than share 1. Each share is sized by its own scale
/// search from `(k̄, b̄)`, as the bending-apart yardstick sizes each of its shares
/// ([`eval::uniform::BendingApart`]): the size for one share is not the size for another, and a
/// network without its bending springs moves closer only when stiffer.
fn size_map(
    inputs: &Inputs,
    map: &[(usize, f64)],
    (k, b): (f64, f64),
    physics: &Physics,
    train_takes: &Takes,
) -> Result<Sized> {
    let size = |share: f64| {
        train::scale::search(&map_network(inputs, map, k, b, share), physics, train_takes)
            .context("the source map's scale search")
    };
    let whole = size(1.0)?;
    let shares = eval::uniform::closest_bending_share(whole.2.after, |f| {
        // A share no size keeps stable is not a candidate.
        let sized = size(f).ok()?;
        Some((sized.2.after, sized))
    });
    let (bending_factor, (net, physics, search)) = shares.kept.unwrap_or((1.0, whole));
    let bending = shares.row;
    Ok(Sized {
        net,
        physics,
        search,
        bending_factor,
        bending,
    })
}

/// The network whose springs in `map` (`(spring, value)`: the structural and shear ones)
/// follow it about `k`, the bending springs at `k · share`, every damping `b`; the run's kernel.
fn map_network(inputs: &Inputs, map: &[(usize, f64)], k: f64, b: f64, share: f64) -> SpringNet {
    let n = inputs.topology.num_springs();
    let mean = map.iter().map(|m| m.1).sum::<f64>() / map.len() as f64;
    let mut ks = vec![k; n];
    inputs
        .topology
        .scale_family(&mut ks, SpringFamily::Bending, share);
    for &(s, v) in map {
        ks[s] = k * v / mean;
    }
    SpringNet::new(&inputs.topology, &ks, &vec![b; n], &inputs.device)
        .with_kernel(inputs.config.model.kernel)
}

/// `source_map.json`.
impl SourceMap {
    /// Writes `source_map.json` into `dir`.
    pub fn write(&self, dir: &Path) -> Result<PathBuf> {
        let json = dir.join("source_map.json");
        crate::io::write_json(&json, self)?;
        Ok(json)
    }
}
