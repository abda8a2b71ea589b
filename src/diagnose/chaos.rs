//! The chaos floor: how far two spring networks whose `k` and `b` differ by a relative `ε` drift
//! apart on the test rollouts. A surrogate cannot be asked to track the data more closely than
//! the reference model tracks itself under parameter noise of the size training can resolve.
//!
//! The reference is the source's ground truth when the data carries springs matching the
//! surrogate's, else the run's learned `k`, `b`. Every spring's `k` and `b` are multiplied by
//! `1 + ε·n_s` with one `n_s ~ N(0, 1)` per spring (seeded, the same draw at every level), and
//! both networks are simulated from each test rollout's first usable frame with the pinned
//! particles following the data; the per-frame Eq. 14 RMSE between them is summarised as
//! `eval` summarises motion RMSE.

use std::path::{Path, PathBuf};

use crate::source::{perturbation, perturbed};
use anyhow::{Result, bail};
use serde::{Deserialize, Serialize};

use super::{ErrorMap, Inputs, curve_between, free_rollout, log_window};
use crate::eval::{self, Curve};
use crate::progress::Progress;
use springtime_plot::{self as plot, Series};

/// One perturbation level's drift from the reference.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ChaosLevel {
    /// Relative perturbation `ε`.
    pub level: f64,
    /// Mean over test rollouts of the RMSE at each frame, m (times in [`ChaosFloor::times`]).
    pub per_frame_mean: Vec<f64>,
    /// Mean over the frames within `short_seconds`, m.
    pub mean_short: f64,
    /// Mean over the frames within `long_seconds`, m.
    pub mean_long: f64,
    /// `per_frame_mean` at the last frame, m.
    pub at_end: f64,
}

/// `chaos.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ChaosFloor {
    /// `"truth"` (the source's springs) or `"learned"` (the run's).
    pub reference: String,
    /// Seed of the perturbation.
    pub seed: u64,
    /// How the RMSE is measured.
    pub metric: String,
    /// One entry per level, level 0 first.
    pub levels: Vec<ChaosLevel>,
    /// Time since the start of each entry of `per_frame_mean`, s.
    pub times: Vec<f64>,
    /// The short horizon (`eval.short_seconds`), s.
    pub short_seconds: f64,
    /// The long horizon (`eval.long_seconds`), s.
    pub long_seconds: f64,
    /// Test rollouts simulated.
    pub rollouts: Vec<PathBuf>,
}

/// The levels to simulate: 0 first, then the given ones in increasing order without repeats.
pub fn levels(given: &[f64]) -> Result<Vec<f64>> {
    if let Some(l) = given
        .iter()
        .find(|l| !(l.is_finite() && **l >= 0.0 && **l < 1.0))
    {
        bail!("--levels: every level must be in [0, 1), got {l}");
    }
    let mut out = vec![0.0];
    out.extend(given.iter().copied().filter(|&l| l > 0.0));
    out.sort_by(f64::total_cmp);
    out.dedup();
    Ok(out)
}

/// Simulates the reference network and its perturbations on every test rollout.
pub fn chaos_floor(
    inputs: &Inputs,
    levels: &[f64],
    seed: u64,
    progress: &Progress,
) -> Result<ChaosFloor> {
    let (reference, k, b) = match &inputs.truth {
        Some((k, b)) => ("truth", k.clone(), b.clone()),
        None => ("learned", inputs.model.k_values(), inputs.model.b_values()),
    };
    let noise = perturbation(k.len(), seed);
    let base = inputs.network(&k, &b);
    let total: usize = inputs.tests.iter().map(|t| t.steps()).sum::<usize>() * (levels.len() + 1);
    let bar = progress.bar(total as u64, "chaos");
    let mut curves: Vec<Vec<Curve>> = vec![Vec::new(); levels.len()];
    for test in &inputs.tests {
        let what = format!("the {reference} spring network");
        let x0 = free_rollout(inputs, &base, test, &what, || bar.inc(1))?;
        let n = test.track.particles * 3;
        for (curves, &level) in curves.iter_mut().zip(levels) {
            let model =
                inputs.network(&perturbed(&k, &noise, level), &perturbed(&b, &noise, level));
            let what = format!("the {reference} spring network perturbed by ε = {level}");
            let x = free_rollout(inputs, &model, test, &what, || bar.inc(1))?;
            curves.push(curve_between(test, &x, |j| {
                x0.positions[j * n..(j + 1) * n].to_vec()
            }));
        }
    }
    bar.finish();
    let (short, long) = (
        inputs.config.eval.short_seconds,
        inputs.config.eval.long_seconds,
    );
    let frame_dt = inputs.tests[0].frame_dt;
    let mut times = Vec::new();
    let levels = curves
        .iter()
        .zip(levels)
        .map(|(c, &level)| {
            let m = eval::summarize(c, frame_dt, short, long);
            times = m.times.clone();
            ChaosLevel {
                level,
                at_end: m.per_frame.last().copied().unwrap_or(0.0),
                per_frame_mean: m.per_frame,
                mean_short: m.short.mean,
                mean_long: m.long.mean,
            }
        })
        .collect();
    Ok(ChaosFloor {
        reference: reference.into(),
        seed,
        metric:
            "Eq. 14 between the perturbed and the unperturbed rollout: √(Σ_i |x_i − x'_i|² / P) \
                 over all P particles (pinned ones follow the data in both and add nothing), \
                 per frame, mean over test rollouts"
                .into(),
        levels,
        times,
        short_seconds: short,
        long_seconds: long,
        rollouts: inputs.tests.iter().map(|t| t.path.clone()).collect(),
    })
}

impl ChaosFloor {
    /// Writes `chaos.json` and `chaos_floor.png` (with the run's own motion RMSE for scale,
    /// when given); returns the paths.
    pub fn write(&self, dir: &Path, run: Option<&ErrorMap>) -> Result<Vec<PathBuf>> {
        let json = dir.join("chaos.json");
        crate::io::write_json(&json, self)?;
        let mut series: Vec<Series> = self
            .levels
            .iter()
            .map(|l| {
                Series::new(
                    format!("ε = {}", l.level),
                    self.times
                        .iter()
                        .copied()
                        .zip(l.per_frame_mean.clone())
                        .collect(),
                )
            })
            .collect();
        if let Some(e) = run {
            series.push(
                Series::new(
                    "the run's motion RMSE",
                    e.motion
                        .times
                        .iter()
                        .copied()
                        .zip(e.motion.per_frame.clone())
                        .collect(),
                )
                .with_color(plotters::style::BLACK)
                .with_width(3),
            );
        }
        log_window(&mut series, 6.0);
        let png = dir.join("chaos_floor.png");
        plot::curves_png(
            &png,
            &format!(
                "Chaos floor: {} k, b perturbed by 1 + ε·N(0,1)",
                self.reference
            ),
            "time (s)",
            "RMSE (m), mean over test rollouts",
            &series,
            true,
        )?;
        Ok(vec![json, png])
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn levels_start_at_zero_sorted_and_unique() {
        assert_eq!(
            levels(&[0.02, 0.005, 0.01, 0.01]).unwrap(),
            vec![0.0, 0.005, 0.01, 0.02]
        );
        assert_eq!(levels(&[0.0]).unwrap(), vec![0.0]);
        assert!(levels(&[-0.1]).is_err());
        assert!(levels(&[f64::NAN]).is_err());
    }

    #[test]
    fn perturbation_is_seeded_and_level_zero_is_the_identity() {
        let n = perturbation(1000, 7);
        assert_eq!(n, perturbation(1000, 7));
        assert_ne!(n, perturbation(1000, 8));
        let mean = n.iter().sum::<f64>() / 1000.0;
        let var = n.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / 1000.0;
        assert!(mean.abs() < 0.1 && (var - 1.0).abs() < 0.15, "{mean} {var}");
        let k: Vec<f64> = (0..1000).map(|i| 10.0 + i as f64).collect();
        assert_eq!(perturbed(&k, &n, 0.0), k);
        let p = perturbed(&k, &n, 0.01);
        assert!((p[3] / k[3] - 1.0 - 0.01 * n[3]).abs() < 1e-12);
    }
}
