//! Never silently worse than uniform (ours): the learned network against the best uniform one on
//! training rollouts held out of the fit (`data.holdout`).
//!
//! A spatially varying network is worth shipping only where it moves closer to the data than
//! the best network with one `k` and one `b`. The held-out rollouts were seen by neither the fit
//! nor the scale search, so the comparison is an honest estimate of what the test rollouts will
//! say; `train` writes it to `validation.json`, says loudly in the log when the learned network
//! does not win at both horizons, and `eval.json` and the report carry it. Where the uniform
//! network moves closer at both horizons, the run keeps it (`train.uniform_fallback`).

use std::path::PathBuf;

use anyhow::Result;
use burn::tensor::Device;

use crate::cloth::Topology;
use crate::eval::uniform::{self};
use crate::eval::{self, EvalConfig};
use crate::model::SpringNet;
use crate::progress::Progress;
use crate::sim::Physics;

pub use crate::eval::Validation;

/// Compares `model` (at `physics`) with the best uniform network around `(k0, b0)`, searched on
/// `train_files` (scored by `objective`, as the run's searches are), on the held-out
/// `validation_files`.
#[allow(clippy::too_many_arguments)]
pub fn validate(
    model: &SpringNet,
    topology: &Topology,
    physics: &Physics,
    (k0, b0): (f64, f64),
    train_files: &[PathBuf],
    validation_files: &[PathBuf],
    config: &EvalConfig,
    objective: eval::Objective,
    device: &Device,
    progress: &Progress,
) -> Result<Validation> {
    let curves = eval::motion_curves(
        model,
        physics,
        &eval::Takes {
            topology,
            files: validation_files,
            batch: config.batch,
            device,
            progress,
            cache: None,
            objective,
        },
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
        (k0, b0),
        train_files,
        validation_files,
        &trained,
        config,
        objective,
        false,
        device,
        progress,
    )?;
    let wins = uniform.improvement_short > 0.0 && uniform.improvement_long > 0.0;
    Ok(Validation {
        rollouts: validation_files.to_vec(),
        trained,
        uniform,
        wins,
        kept_uniform: false,
    })
}
