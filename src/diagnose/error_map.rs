//! Where the error lives: the run's free rollout on every test rollout (as `eval` simulates it),
//! which rollouts carry the error at the short and long horizons, and which particles.

use std::path::{Path, PathBuf};

use anyhow::Result;
use serde::{Deserialize, Serialize};

use super::{Inputs, curve_between, free_rollout, log_window};
use crate::eval::{self, Curve, MotionRmse};
use crate::progress::Progress;
use springtime_plot::{self as plot, Series};

/// One test rollout's error.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RolloutError {
    /// The file.
    pub file: PathBuf,
    /// Its file name.
    pub name: String,
    /// Mean Eq. 14 RMSE over the frames within `short_seconds`, m.
    pub mean_short: f64,
    /// Mean over the frames within `long_seconds`, m.
    pub mean_long: f64,
    /// RMSE at the last frame, m.
    pub at_end: f64,
    /// Seconds simulated.
    pub seconds: f64,
}

/// `error_map.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ErrorMap {
    /// The short horizon, s.
    pub short_seconds: f64,
    /// The long horizon, s.
    pub long_seconds: f64,
    /// The motion RMSE over all test rollouts, as `eval.json` has it.
    pub motion: MotionRmse,
    /// Per test rollout, in the order of the files.
    pub rollouts: Vec<RolloutError>,
    /// Indices into `rollouts`, largest `mean_long` first.
    pub worst: Vec<usize>,
    /// Per particle, the position error `|x − x̂|` averaged over every simulated frame of every
    /// test rollout, m (a particle pinned in a rollout follows the data there and adds 0).
    pub per_particle: Vec<f64>,
    /// Per test rollout, `(time, RMSE)` of every frame (the figure's; `eval` writes them to
    /// `motion_rmse.csv`).
    #[serde(skip)]
    pub curves: Vec<Curve>,
}

/// Simulates the run's surrogate on every test rollout and measures where its error is.
pub fn error_map(inputs: &Inputs, progress: &Progress) -> Result<ErrorMap> {
    let (short, long) = (
        inputs.config.eval.short_seconds,
        inputs.config.eval.long_seconds,
    );
    let total: usize = inputs.tests.iter().map(|t| t.steps()).sum();
    let bar = progress.bar(total as u64, "error map");
    let p = inputs.topology.num_particles();
    let mut sum = vec![0.0; p];
    let mut count = 0usize;
    let mut curves: Vec<Curve> = Vec::new();
    let mut rollouts = Vec::new();
    for test in &inputs.tests {
        let x = free_rollout(inputs, &inputs.model, test, "the trained surrogate", || {
            bar.inc(1)
        })?;
        for j in 1..x.frames.len() {
            let (sim, obs) = (&x.positions[j * p * 3..(j + 1) * p * 3], test.observed(j));
            for (i, s) in sum.iter_mut().enumerate() {
                let d2: f64 = (0..3)
                    .map(|c| (sim[3 * i + c] as f64 - obs[3 * i + c] as f64).powi(2))
                    .sum();
                *s += d2.sqrt();
            }
            count += 1;
        }
        let curve = curve_between(test, &x, |j| test.observed(j).to_vec());
        let one = eval::summarize(std::slice::from_ref(&curve), test.frame_dt, short, long);
        rollouts.push(RolloutError {
            file: test.path.clone(),
            name: test.path.file_name().map_or_else(
                || test.path.display().to_string(),
                |n| n.to_string_lossy().into(),
            ),
            mean_short: one.short.mean,
            mean_long: one.long.mean,
            at_end: curve.last().map_or(0.0, |c| c.1),
            seconds: test.steps() as f64 * test.frame_dt,
        });
        curves.push(curve);
    }
    bar.finish();
    let mut worst: Vec<usize> = (0..rollouts.len()).collect();
    worst.sort_by(|&a, &b| rollouts[b].mean_long.total_cmp(&rollouts[a].mean_long));
    Ok(ErrorMap {
        short_seconds: short,
        long_seconds: long,
        motion: eval::summarize(&curves, inputs.tests[0].frame_dt, short, long),
        worst,
        per_particle: sum.iter().map(|s| s / count.max(1) as f64).collect(),
        rollouts,
        curves,
    })
}

impl ErrorMap {
    /// Writes `error_map.json` and `error_map.png` (the per-particle map beside each rollout's
    /// RMSE over time); returns the paths.
    pub fn write(&self, dir: &Path, inputs: &Inputs) -> Result<Vec<PathBuf>> {
        let json = dir.join("error_map.json");
        crate::io::write_json(&json, self)?;
        let png = dir.join("error_map.png");
        let range = plot::value_range(&[&self.per_particle]);
        let (mw, mh) = plot::MAP_PANEL;
        let (cw, ch) = plot::PLOT_PANEL;
        let (w, h) = (
            mw + plot::COLORBAR_WIDTH + cw,
            plot::TITLE_HEIGHT + mh.max(ch),
        );
        let mut curves: Vec<Series> = self
            .rollouts
            .iter()
            .zip(&self.curves)
            .map(|(r, c)| Series::new(r.name.clone(), c.clone()).with_width(1))
            .collect();
        log_window(&mut curves, 6.0);
        plot::png_figure(&png, w, h, |root| {
            let body = plot::title(
                root,
                &format!(
                    "Where the error lives: {} test rollouts, mean RMSE ≤ {} s {:.3e} m",
                    self.rollouts.len(),
                    self.long_seconds,
                    self.motion.long.mean
                ),
                18,
            )?;
            let (left, right) = body.split_horizontally(mw + plot::COLORBAR_WIDTH);
            let (map, bar) = left.split_horizontally(mw);
            plot::draw_map(
                &map,
                plot::Map::Particles {
                    topology: &inputs.topology,
                },
                &self.per_particle,
                "time-averaged |x − x̂| per particle",
                range,
            )?;
            plot::draw_colorbar(&bar, range, "error (m)")?;
            plot::draw_curves(
                &right,
                "RMSE per test rollout",
                "time (s)",
                "RMSE (m)",
                &curves,
                true,
                &[],
            )
        })?;
        Ok(vec![json, png])
    }
}
