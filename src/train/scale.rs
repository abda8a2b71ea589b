//! The learned network's overall scale, searched over free rollouts (ours; `train.scale_search`).
//!
//! A fit of the forces on the data's own states (`train.force_on = "target"`, teacher forcing) ranks
//! the springs by stiffness where a rollout loss cannot (third-party data: see README "Data from
//! another simulator"), but its values are attenuated: the regressors — spring strains measured
//! from positions that no spring network explains exactly — are noisy, and least squares shrinks
//! their coefficients towards zero. A network with the right shape and too small a size then
//! simulates worse than a uniform one. The search keeps the shape and finds the size: every `k`
//! is multiplied by one factor and every `b` by another, each candidate rolled out freely on
//! training rollouts (at the fewest substeps that keep it stable), and the pair with the lowest
//! mean motion RMSE is kept. Ranks — and so the stiffness map's Spearman correlation — do not
//! change.

use std::path::PathBuf;

use anyhow::{Result, bail};
use burn::tensor::Device;
use serde::{Deserialize, Serialize};

use crate::cloth::Topology;
use crate::eval::uniform::network_rollout_rmse;
use crate::model::SpringNet;
use crate::progress::Progress;
use crate::sim::Physics;
use crate::train::init::AUTO_SUBSTEPS_TARGET;

/// Training rollouts every candidate is simulated on (the first ones of the split).
const SEARCH_ROLLOUTS: usize = 8;
/// Stiffness factors `2^(i/2)`, `i` in this range; then `2^(±1/4)` around the best.
const K_STEPS: std::ops::RangeInclusive<i32> = -2..=8;
/// Damping factors `2^i`, `i` in this range.
const B_STEPS: std::ops::RangeInclusive<i32> = -4..=4;
/// The search raises the substeps at most this many times over the run's.
const MAX_SUBSTEP_FACTOR: usize = 8;

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

/// The fewest substeps from `physics.substeps` up that start `model` at
/// `dt²ω² + 2·dt·γ ≤ 1`, or `None` beyond [`MAX_SUBSTEP_FACTOR`] times the run's.
fn stable_substeps(topology: &Topology, physics: &Physics, model: &SpringNet) -> Option<usize> {
    let mut p = *physics;
    (physics.substeps..=physics.substeps * MAX_SUBSTEP_FACTOR).find(|&n| {
        p.substeps = n;
        p.stability_of(topology, model).number() <= AUTO_SUBSTEPS_TARGET
    })
}

/// Searches the factors of `model`'s `k` and `b` on `train_files`; returns the scaled network,
/// the physics it runs at (substeps possibly raised) and the record.
pub fn search(
    model: &SpringNet,
    topology: &Topology,
    physics: &Physics,
    train_files: &[PathBuf],
    batch: usize,
    device: &Device,
    progress: &Progress,
) -> Result<(SpringNet, Physics, ScaleSearch)> {
    let files: Vec<PathBuf> = train_files.iter().take(SEARCH_ROLLOUTS).cloned().collect();
    let (k, b, kappa) = (model.k_values(), model.b_values(), model.curvature_values());
    // The curvature elements are stiffnesses: they scale with `k`.
    let scaled = |fk: f64, fb: f64| {
        let times = |v: &[f64], f: f64| -> Vec<f64> { v.iter().map(|x| x * f).collect() };
        SpringNet::new(topology, &times(&k, fk), &times(&b, fb), device)
            .with_kernel(model.graph.kernel)
            .with_curvature(&times(&kappa, fk))
    };
    // Every pair is simulated once: the coarse k row meets the b row at its best k, and the
    // start (1, 1) lies on the k row.
    let mut tried: Vec<(f64, f64, Scored)> = Vec::new();
    let mut score = |fk: f64, fb: f64| -> Scored {
        if let Some(&(_, _, known)) = tried.iter().find(|t| t.0 == fk && t.1 == fb) {
            return known;
        }
        let net = scaled(fk, fb);
        let found = stable_substeps(topology, physics, &net).and_then(|n| {
            let p = Physics {
                substeps: n,
                ..*physics
            };
            network_rollout_rmse(&net, topology, &p, &files, batch, device).map(|r| (n, r))
        });
        tried.push((fk, fb, found));
        found
    };
    let bar = progress.bar(
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
