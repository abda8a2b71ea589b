//! Evaluation (paper §4.2): parameter RMSE (Eq. 13) and motion RMSE over test rollouts
//! (Eq. 14).

use std::path::PathBuf;

use anyhow::{Result, bail};
use burn::tensor::{Device, Tensor, TensorData};
use serde::{Deserialize, Serialize};

use crate::cloth::{Resampler, Topology};
use crate::data::{Rollout, Track};
use crate::model::SpringNet;
use crate::progress::Progress;
use crate::sim::{self, Physics, State};

/// The `[eval]` section.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct EvalConfig {
    /// The short horizon of Table 2, s (`mean_0_8s`).
    pub short_seconds: f64,
    /// The long horizon, s (`mean_8s`).
    pub long_seconds: f64,
    /// Test rollouts simulated together.
    pub batch: usize,
    /// Evaluate at most this many test rollouts (0 = all).
    pub max_rollouts: usize,
}

impl Default for EvalConfig {
    fn default() -> Self {
        Self {
            short_seconds: 0.8,
            long_seconds: 8.0,
            batch: 16,
            max_rollouts: 0,
        }
    }
}

/// Motion RMSE statistics over every frame of every test rollout (Eq. 14).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MotionRmse {
    /// Mean over all frames of all rollouts, m.
    pub mean: f64,
    /// Standard deviation over all frames of all rollouts, m.
    pub std: f64,
    /// Mean over the frames within `short_seconds` of the start.
    pub mean_0_8s: f64,
    /// Its standard deviation.
    pub std_0_8s: f64,
    /// Mean over the frames within `long_seconds` of the start.
    pub mean_8s: f64,
    /// Its standard deviation.
    pub std_8s: f64,
    /// Mean over rollouts at each frame after the start, m.
    pub per_frame: Vec<f64>,
    /// Time between frames, s.
    pub frame_dt: f64,
    /// Rollouts evaluated.
    pub rollouts: usize,
}

/// `eval.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EvalReport {
    /// RMSE of `k` against the source's springs (Eq. 13), when known.
    pub rmse_k: Option<f64>,
    /// RMSE of `b`, when known.
    pub rmse_b: Option<f64>,
    /// Motion RMSE over the test rollouts.
    pub motion_rmse: MotionRmse,
    /// Test rollout files.
    pub test_rollouts: Vec<PathBuf>,
    /// Backend used.
    pub backend: String,
    /// Wall time of the evaluation, s.
    pub seconds: f64,
}

/// Per-frame motion RMSE of one rollout: `(time since start, rmse)` for every simulated frame.
pub type Curve = Vec<(f64, f64)>;

/// Simulates every test rollout from its first frame with a known velocity to its end, pinned
/// particles following the data, and returns the per-frame motion RMSE of each.
pub fn motion_curves(
    model: &SpringNet,
    physics_template: &Physics,
    topology: &Topology,
    files: &[PathBuf],
    batch: usize,
    device: &Device,
    progress: &Progress,
) -> Result<Vec<Curve>> {
    let mut tracks = Vec::new();
    for f in files {
        let r = Rollout::load(f)?;
        if r.segments.len() != 1 {
            bail!(
                "{}: a test rollout must be stored in full (it has `segments`)",
                f.display()
            );
        }
        let res = Resampler::new(&r.rest_uv, &topology.rest_uv);
        let first = if r.velocities.is_some() { 0 } else { 1 };
        tracks.push((f.clone(), Track::new(&r, &res), first, r.frame_dt));
    }
    // Every rollout is stepped from its first usable frame to its last.
    let total_frames: usize = tracks.iter().map(|t| t.1.frames - 1 - t.2).sum();
    let bar = progress.bar(total_frames as u64, "eval");
    let mut curves = vec![Vec::new(); tracks.len()];
    let p = topology.num_particles();
    let mut order: Vec<usize> = (0..tracks.len()).collect();
    order.sort_by_key(|&i| (tracks[i].1.frames, tracks[i].2));
    for group in order
        .chunk_by(|&a, &b| tracks[a].1.frames == tracks[b].1.frames && tracks[a].2 == tracks[b].2)
    {
        for chunk in group.chunks(batch.max(1)) {
            let b = chunk.len();
            let (frames, first, frame_dt) = (
                tracks[chunk[0]].1.frames,
                tracks[chunk[0]].2,
                tracks[chunk[0]].3,
            );
            let physics = Physics {
                frame_dt,
                ..*physics_template
            };
            let frame_of = |j: usize, vel: bool| {
                let mut v = Vec::with_capacity(b * p * 3);
                for &i in chunk {
                    let t = &tracks[i].1;
                    let src = if vel { &t.velocities } else { &t.positions };
                    v.extend_from_slice(&src[j * p * 3..(j + 1) * p * 3]);
                }
                Tensor::<3>::from_data(TensorData::new(v, [b, p, 3]), device)
            };
            let pinned: Vec<f32> = chunk
                .iter()
                .flat_map(|&i| tracks[i].1.pinned.iter().map(|&x| x as u8 as f32))
                .collect();
            let pinned = Tensor::<3>::from_data(TensorData::new(pinned, [b, p, 1]), device);
            let mut state = State {
                x: frame_of(first, false),
                v: frame_of(first, true),
            };
            let mut here = frame_of(first, false);
            let mut errs: Vec<Tensor<1>> = Vec::new();
            let flush = |errs: &mut Vec<Tensor<1>>,
                         upto: usize,
                         curves: &mut Vec<Curve>|
             -> Result<()> {
                if errs.is_empty() {
                    return Ok(());
                }
                let n = errs.len();
                let data: Vec<f32> = Tensor::cat(std::mem::take(errs), 0)
                    .into_data()
                    .try_into_vec_as::<f32>()
                    .map_err(|e| anyhow::anyhow!("{e:?}"))?;
                for (k, row) in data.chunks_exact(b).enumerate() {
                    let j = upto + k + 2 - n; // the frame this error belongs to
                    for (slot, &e) in row.iter().enumerate() {
                        let i = chunk[slot];
                        if !e.is_finite() {
                            bail!(
                                "{}: the surrogate's rollout diverged at frame {j} (t = {:.3} s)",
                                tracks[i].0.display(),
                                j as f64 * frame_dt
                            );
                        }
                        curves[i].push(((j - first) as f64 * frame_dt, e as f64));
                    }
                }
                Ok(())
            };
            for j in first..frames - 1 {
                let next = frame_of(j + 1, false);
                let (s, _) = sim::step_frame(model, &physics, state, &pinned, &here, &next);
                state = s;
                let d = state.x.clone() - next.clone();
                errs.push(
                    (d.clone() * d)
                        .sum_dim(2)
                        .sum_dim(1)
                        .div_scalar(p as f64)
                        .sqrt()
                        .reshape([b]),
                );
                here = next;
                if errs.len() == 100 {
                    flush(&mut errs, j, &mut curves)?;
                    bar.inc(100 * b as u64);
                }
            }
            let left = errs.len();
            flush(&mut errs, frames - 2, &mut curves)?;
            bar.inc((left * b) as u64);
        }
    }
    bar.finish();
    Ok(curves)
}

/// Summarises per-frame curves into Table 2's statistics.
pub fn summarize(curves: &[Curve], frame_dt: f64, short: f64, long: f64) -> MotionRmse {
    let stats = |limit: f64| {
        let v: Vec<f64> = curves
            .iter()
            .flatten()
            .filter(|(t, _)| *t <= limit + 1e-9)
            .map(|c| c.1)
            .collect();
        let n = v.len().max(1) as f64;
        let mean = v.iter().sum::<f64>() / n;
        let var = v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / n;
        (mean, var.sqrt())
    };
    let (mean, std) = stats(f64::INFINITY);
    let (mean_0_8s, std_0_8s) = stats(short);
    let (mean_8s, std_8s) = stats(long);
    let longest = curves.iter().map(Vec::len).max().unwrap_or(0);
    let per_frame = (0..longest)
        .map(|j| {
            let v: Vec<f64> = curves
                .iter()
                .filter_map(|c| c.get(j).map(|e| e.1))
                .collect();
            v.iter().sum::<f64>() / v.len().max(1) as f64
        })
        .collect();
    MotionRmse {
        mean,
        std,
        mean_0_8s,
        std_0_8s,
        mean_8s,
        std_8s,
        per_frame,
        frame_dt,
        rollouts: curves.len(),
    }
}
