//! The best uniform surrogate: the yardstick a learned spatially varying one must beat.
//!
//! A 1-D search over one stiffness shared by every spring (damping held at the run's initial
//! `b`): each candidate is rolled out freely on training rollouts, and the one with the lowest
//! mean motion RMSE is then evaluated on the test rollouts like the trained model.

use std::path::PathBuf;

use anyhow::Result;
use burn::tensor::Device;
use serde::{Deserialize, Serialize};

use crate::cloth::Topology;
use crate::eval::{self, MotionRmse};
use crate::model::SpringNet;
use crate::progress::Progress;
use crate::sim::Physics;

/// Candidates are `k₀ · 2^(i/2)` for `i` in `−SPAN..=SPAN`, then `2^(±1/4)` around the best.
const SPAN: i32 = 6;
/// Training rollouts the search simulates (the first ones of the split).
const SEARCH_ROLLOUTS: usize = 8;

/// Mean motion RMSE of free rollouts of the uniform network `(k, b)` on `files` (`None` when it
/// is unstable at `physics`' step or a rollout diverges).
pub fn rollout_rmse(
    topology: &Topology,
    physics: &Physics,
    k: f64,
    b: f64,
    files: &[PathBuf],
    batch: usize,
    device: &Device,
) -> Option<f64> {
    let model = SpringNet::uniform(topology, k, b, device);
    if !physics.stability_of(topology, &model).is_stable() {
        return None;
    }
    let curves = eval::motion_curves(
        &model,
        physics,
        topology,
        files,
        batch,
        device,
        &Progress::quiet(),
    )
    .ok()?;
    let mean = eval::summarize(&curves.curves, physics.frame_dt, 0.0, 0.0).mean;
    mean.is_finite().then_some(mean)
}

/// `eval.json`'s `uniform_baseline`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct UniformBaseline {
    /// The best uniform stiffness on the training rollouts, N/m.
    pub k: f64,
    /// The damping every spring kept, N·s/m.
    pub b: f64,
    /// `(k, mean motion RMSE on the training rollouts)` of every stable candidate.
    pub search: Vec<(f64, f64)>,
    /// Training rollouts the search used.
    pub search_rollouts: usize,
    /// The best uniform surrogate on the test rollouts.
    pub test: MotionRmse,
    /// `1 − trained / uniform` of the long-horizon test RMSE (positive: training helps).
    pub improvement_long: f64,
    /// The same for the short horizon.
    pub improvement_short: f64,
}

/// Searches the uniform stiffness around `k0` (damping `b`) on `train_files` and evaluates the
/// best on `test_files`; `trained` is the trained model's test RMSE to compare with.
#[allow(clippy::too_many_arguments)]
pub fn search(
    topology: &Topology,
    physics: &Physics,
    k0: f64,
    b: f64,
    train_files: &[PathBuf],
    test_files: &[PathBuf],
    trained: &MotionRmse,
    eval_config: &eval::EvalConfig,
    device: &Device,
    progress: &Progress,
) -> Result<UniformBaseline> {
    let train: Vec<PathBuf> = train_files.iter().take(SEARCH_ROLLOUTS).cloned().collect();
    let score = |k: f64| rollout_rmse(topology, physics, k, b, &train, eval_config.batch, device);
    let bar = progress.bar((2 * SPAN + 3) as u64, "uniform search");
    let mut search: Vec<(f64, f64)> = Vec::new();
    for i in -SPAN..=SPAN {
        let k = k0 * 2f64.powf(i as f64 / 2.0);
        if let Some(r) = score(k) {
            search.push((k, r));
        }
        bar.inc(1);
    }
    let best = |s: &[(f64, f64)]| {
        s.iter()
            .copied()
            .min_by(|a, b| a.1.total_cmp(&b.1))
            .ok_or_else(|| anyhow::anyhow!("no uniform stiffness around {k0} N/m is stable"))
    };
    let (coarse, _) = best(&search)?;
    for f in [-0.25, 0.25] {
        let k = coarse * 2f64.powf(f);
        if let Some(r) = score(k) {
            search.push((k, r));
        }
        bar.inc(1);
    }
    bar.finish();
    search.sort_by(|a, b| a.0.total_cmp(&b.0));
    let (k, _) = best(&search)?;
    let model = SpringNet::uniform(topology, k, b, device);
    let curves = eval::motion_curves(
        &model,
        physics,
        topology,
        test_files,
        eval_config.batch,
        device,
        progress,
    )?;
    let test = eval::summarize(
        &curves.curves,
        physics.frame_dt,
        eval_config.short_seconds,
        eval_config.long_seconds,
    );
    Ok(UniformBaseline {
        k,
        b,
        improvement_long: 1.0 - trained.mean_8s / test.mean_8s,
        improvement_short: 1.0 - trained.mean_0_8s / test.mean_0_8s,
        search,
        search_rollouts: train.len(),
        test,
    })
}
