//! Never silently worse than uniform (ours): the learned network against the best uniform one on
//! training rollouts held out of the fit (`data.holdout`).
//!
//! A spatially varying network is worth shipping only where it moves closer to the data than
//! the best network with one `k` and one `b`. The held-out rollouts were seen by neither the fit
//! nor the scale search, so the comparison is an honest estimate of what the test rollouts will
//! say; `train` writes it to `validation.json`, says loudly in the log when the learned network
//! does not win at both horizons, and `eval.json` and the report carry it.

use std::path::{Path, PathBuf};

use anyhow::Result;
use burn::tensor::Device;
use serde::{Deserialize, Serialize};

use crate::cloth::Topology;
use crate::eval::uniform::{self, UniformBaseline};
use crate::eval::{self, EvalConfig, MotionRmse};
use crate::model::SpringNet;
use crate::progress::Progress;
use crate::sim::Physics;

/// `validation.json`: the learned network and the best uniform one on held-out training
/// rollouts.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Validation {
    /// The held-out training rollouts.
    pub rollouts: Vec<PathBuf>,
    /// The learned network's motion RMSE on them.
    pub trained: MotionRmse,
    /// The best uniform network (searched on the fitted training rollouts) and its motion RMSE
    /// on the held-out ones (`uniform.test`), with the learned network's improvement on it.
    pub uniform: UniformBaseline,
    /// Whether the learned network beats the uniform one at both horizons.
    pub wins: bool,
}

impl Validation {
    /// The file in a run directory.
    pub fn path(run_dir: &Path) -> PathBuf {
        run_dir.join("validation.json")
    }

    /// Reads a run's `validation.json`, `None` when the run has none.
    pub fn read(run_dir: &Path) -> Result<Option<Self>> {
        let path = Self::path(run_dir);
        if !path.exists() {
            return Ok(None);
        }
        crate::io::read_json(&path).map(Some)
    }

    /// One line for a log or a report.
    pub fn summary(&self) -> String {
        let u = &self.uniform;
        let verdict = if self.wins {
            "the learned network beats it"
        } else {
            "WARNING: the learned network does NOT beat the best uniform network; a uniform \
             cloth with these k and b moves closer to the data"
        };
        format!(
            "on {} held-out training rollouts: learned {:.4e} / {:.4e} m (short / long horizon), \
             best uniform (k {:.4} N/m, b {:.4e} N·s/m) {:.4e} / {:.4e} m: {:+.1} % / {:+.1} %; \
             {verdict}",
            self.rollouts.len(),
            self.trained.short.mean,
            self.trained.long.mean,
            u.k,
            u.b,
            u.test.short.mean,
            u.test.long.mean,
            100.0 * u.improvement_short,
            100.0 * u.improvement_long,
        )
    }
}

/// Compares `model` (at `physics`) with the best uniform network around `(k0, b0)`, searched on
/// `train_files`, on the held-out `validation_files`.
#[allow(clippy::too_many_arguments)]
pub fn validate(
    model: &SpringNet,
    topology: &Topology,
    physics: &Physics,
    (k0, b0): (f64, f64),
    train_files: &[PathBuf],
    validation_files: &[PathBuf],
    config: &EvalConfig,
    device: &Device,
    progress: &Progress,
) -> Result<Validation> {
    let curves = eval::motion_curves(
        model,
        physics,
        topology,
        validation_files,
        config.batch,
        device,
        progress,
    )?;
    let trained = eval::summarize(
        &curves.curves,
        physics.frame_dt,
        config.short_seconds,
        config.long_seconds,
    );
    let uniform = uniform::search(
        topology,
        physics,
        k0,
        b0,
        train_files,
        validation_files,
        &trained,
        config,
        device,
        progress,
    )?;
    let wins = uniform.improvement_short > 0.0 && uniform.improvement_long > 0.0;
    Ok(Validation {
        rollouts: validation_files.to_vec(),
        trained,
        uniform,
        wins,
    })
}
