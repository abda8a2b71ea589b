//! Evaluation (paper §4.2): parameter RMSE (Eq. 13) and motion RMSE over test rollouts
//! (Eq. 14).

pub mod uniform;

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::Instant;

use anyhow::{Result, bail};
use burn::tensor::{Device, Tensor, TensorData};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::cloth::{Resampler, SpringFamily, Topology};
use crate::data::MeshTruth;
use crate::data::{Rollout, Track};
use crate::model::{ForceModel, Gnn};
use crate::progress::Progress;
use crate::sim::{self, Physics, State};
use uniform::UniformBaseline;

/// The `[eval]` section.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct EvalConfig {
    /// The short horizon of Table 2, s (`motion_rmse.short`).
    pub short_seconds: f64,
    /// The long horizon, s (`motion_rmse.long`).
    pub long_seconds: f64,
    /// Test rollouts simulated together.
    pub batch: usize,
    /// Evaluate at most this many test rollouts (0 = all).
    pub max_rollouts: usize,
    /// Also search the best uniform stiffness on the training rollouts and evaluate it on the
    /// test rollouts (`eval.json`'s `uniform_baseline`: the yardstick of spatial learning).
    pub uniform_baseline: bool,
}

impl Default for EvalConfig {
    fn default() -> Self {
        Self {
            short_seconds: 0.8,
            long_seconds: 8.0,
            batch: 16,
            max_rollouts: 0,
            uniform_baseline: false,
        }
    }
}

/// Motion RMSE over the frames within a horizon of the start.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Horizon {
    /// The horizon, s (`eval.short_seconds` or `eval.long_seconds`).
    pub seconds: f64,
    /// Mean over those frames of every rollout, m.
    pub mean: f64,
    /// Its standard deviation, m.
    pub std: f64,
    /// Each rollout's mean over those frames, m, in the order of the files: two networks'
    /// figures on the same takes can be compared take by take (the bench's confidence
    /// interval of a gain). Empty in the files of a springtime before 2026-12-06.
    #[serde(default)]
    pub per_rollout: Vec<f64>,
}

/// Motion RMSE statistics over every frame of every test rollout (Eq. 14).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(from = "MotionRmseFile")]
pub struct MotionRmse {
    /// Mean over all frames of all rollouts, m.
    pub mean: f64,
    /// Standard deviation over all frames of all rollouts, m.
    pub std: f64,
    /// Over the short horizon (Table 2's 0.8 s by default).
    pub short: Horizon,
    /// Over the long horizon (Table 2's 8 s by default).
    pub long: Horizon,
    /// Mean over rollouts at each simulated frame, m.
    pub per_frame: Vec<f64>,
    /// Time since the start of each entry of `per_frame`, s.
    pub times: Vec<f64>,
    /// Time between frames, s.
    pub frame_dt: f64,
    /// Rollouts evaluated.
    pub rollouts: usize,
}

/// `motion_rmse` as stored in `eval.json`, now (`short`, `long`) or by an older springtime
/// (`mean_0_8s`, `std_0_8s`, `mean_8s`, `std_8s`, optional `short_seconds`, `long_seconds`).
#[derive(Deserialize)]
struct MotionRmseFile {
    mean: f64,
    std: f64,
    short: Option<Horizon>,
    long: Option<Horizon>,
    mean_0_8s: Option<f64>,
    std_0_8s: Option<f64>,
    mean_8s: Option<f64>,
    std_8s: Option<f64>,
    short_seconds: Option<f64>,
    long_seconds: Option<f64>,
    per_frame: Vec<f64>,
    #[serde(default)]
    times: Vec<f64>,
    frame_dt: f64,
    rollouts: usize,
}

impl From<MotionRmseFile> for MotionRmse {
    fn from(f: MotionRmseFile) -> Self {
        let old =
            |seconds: Option<f64>, default: f64, mean: Option<f64>, std: Option<f64>| Horizon {
                seconds: seconds.unwrap_or(default),
                mean: mean.unwrap_or(f64::NAN),
                std: std.unwrap_or(f64::NAN),
                per_rollout: Vec::new(),
            };
        Self {
            mean: f.mean,
            std: f.std,
            short: f
                .short
                .unwrap_or_else(|| old(f.short_seconds, 0.8, f.mean_0_8s, f.std_0_8s)),
            long: f
                .long
                .unwrap_or_else(|| old(f.long_seconds, 8.0, f.mean_8s, f.std_8s)),
            per_frame: f.per_frame,
            times: f.times,
            frame_dt: f.frame_dt,
            rollouts: f.rollouts,
        }
    }
}

/// Inference cost measured while evaluating: the model's steps only, batched as `eval.batch`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Inference {
    /// Wall time per rollout·step, µs.
    pub us_per_step: f64,
    /// Simulated time one step advances, s (a data frame; the GNN's step spans `downsample`).
    pub step_dt: f64,
    /// Rollouts stepped together.
    pub batch: usize,
    /// Wall time per simulated second of one rollout, s.
    pub seconds_per_second: f64,
}

/// `eval.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EvalReport {
    /// RMSE of `k` against the source's springs (Eq. 13), when known.
    pub rmse_k: Option<f64>,
    /// RMSE of `b`, when known.
    pub rmse_b: Option<f64>,
    /// Spearman correlation between the learned `k` of the structural springs and the FEM
    /// source's `tri_stiffness` at each spring's rest midpoint, when the data has a mesh.
    #[serde(default)]
    pub stiffness_map_corr: Option<f64>,
    /// Where the run kept a uniform network instead of what it learned (the best uniform one
    /// on the held-out takes, `train.uniform_fallback`, or the blend search's, where no share
    /// of the map moves closer), the same correlation of the springs it set aside
    /// (`springs.learned.npz`), whose map the uniform network no longer carries.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub learned_map_corr: Option<f64>,
    /// Motion RMSE over the test rollouts.
    pub motion_rmse: MotionRmse,
    /// The best uniform surrogate beside the trained one (`eval.uniform_baseline`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub uniform_baseline: Option<uniform::UniformBaseline>,
    /// `train`'s check of the learned network against the best uniform one on training
    /// rollouts held out of the fit (`data.holdout`; the run's `validation.json`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub validation: Option<Validation>,
    /// What the model's steps cost during this evaluation.
    #[serde(default)]
    pub inference: Option<Inference>,
    /// Test rollout files.
    pub test_rollouts: Vec<PathBuf>,
    /// Backend used.
    pub backend: String,
    /// The float type the model was simulated in (`"f32"`, or `"f64"` with `springtime eval
    /// --precision f64`).
    #[serde(default = "default_precision")]
    pub precision: String,
    /// Wall time of the evaluation, s.
    pub seconds: f64,
}

/// The float type of an `eval.json` written before the field existed.
fn default_precision() -> String {
    "f32".into()
}

/// Per-frame motion RMSE of one rollout: `(time since start, rmse)` for every simulated frame.
pub type Curve = Vec<(f64, f64)>;

/// A test rollout resampled to the surrogate's particles, with the frame a free rollout starts
/// from (the first with a known velocity).
#[derive(Debug, Clone)]
pub struct TestTrack {
    /// The rollout file.
    pub path: PathBuf,
    /// Its frames on the particles.
    pub track: Track,
    /// The frame its free rollout starts from ([`Rollout::first_state_frame`]): 0 with stored
    /// velocities, else 1, or later where landmarks are hidden from its first frame.
    pub first: usize,
    /// Time between frames, s.
    pub frame_dt: f64,
}

impl TestTrack {
    /// Loads and resamples a test rollout; refuses one stored in windows (`segments`).
    pub fn load(path: &std::path::Path, topology: &Topology) -> Result<Self> {
        let r = Rollout::load(path)?;
        if r.segments.len() != 1 {
            bail!(
                "{}: a test rollout must be stored in full (it has `segments`)",
                path.display()
            );
        }
        let res = Resampler::new(&r.rest_uv, &topology.rest_uv);
        Ok(Self {
            path: path.to_path_buf(),
            track: Track::new(&r, &res),
            first: r.first_state_frame(),
            frame_dt: r.frame_dt,
        })
    }

    /// Memory its frames hold, bytes.
    fn bytes(&self) -> usize {
        let t = &self.track;
        4 * (t.positions.len() + t.velocities.len())
            + t.pinned.len()
            + t.visible.as_ref().map_or(0, Vec::len)
    }

    /// Frames a free rollout steps: from its first state frame to the last.
    pub fn steps(&self) -> usize {
        self.track.frames - 1 - self.first
    }

    /// Observed positions of frame `j` counted from its first state frame, `[P, 3]`.
    pub fn observed(&self, j: usize) -> &[f32] {
        let n = self.track.particles * 3;
        let j = self.first + j;
        &self.track.positions[j * n..(j + 1) * n]
    }
}

/// Motion RMSE of one frame (Eq. 14): `√(Σᵢ |xᵢ − x̂ᵢ|² / P)` over `[P, 3]` positions, every
/// particle counted (pinned ones follow the data and add nothing), as [`motion_curves`] does.
pub fn frame_rmse(x: &[f32], target: &[f32]) -> f64 {
    assert_eq!(x.len(), target.len());
    let sum: f64 = x
        .iter()
        .zip(target)
        .map(|(&a, &b)| (a as f64 - b as f64).powi(2))
        .sum();
    (sum / (x.len() / 3).max(1) as f64).sqrt()
}

/// How a search scores a network by its free rollouts of [`Takes`] (lower is closer).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Objective {
    /// The mean motion RMSE over every frame of the takes: the long horizon over the whole
    /// take, as the uniform yardstick is searched.
    WholeTake,
    /// The geometric mean of the mean motion RMSE up to `short_seconds` and over the whole
    /// takes: both of `eval`'s horizons weigh alike, so the late frames, where a cloth's
    /// motion parts from any model's by chaos, do not alone decide (`train.search_objective =
    /// "both_horizons"`).
    BothHorizons {
        /// The short horizon, s (`eval.short_seconds`).
        short_seconds: f64,
    },
}

impl Objective {
    /// The score of the motion curves `curves` (frames `frame_dt` apart).
    pub fn score(self, curves: &[Curve], frame_dt: f64) -> f64 {
        match self {
            Objective::WholeTake => summarize(curves, frame_dt, 0.0, 0.0).mean,
            Objective::BothHorizons { short_seconds } => {
                let s = summarize(curves, frame_dt, short_seconds, 0.0);
                (s.short.mean * s.mean).sqrt()
            }
        }
    }
}

/// Rollouts of the data to simulate from their own starts: the files, read onto `topology`,
/// simulated `batch` at a time on `device` (the motion curves, the searches over free
/// rollouts, which score them by `objective`).
#[derive(Clone, Copy)]
pub struct Takes<'a> {
    /// The surrogate's particles and springs the files are read onto.
    pub topology: &'a Topology,
    /// The rollouts (`.npz`).
    pub files: &'a [PathBuf],
    /// Rollouts simulated together.
    pub batch: usize,
    /// Where they are simulated.
    pub device: &'a Device,
    /// Where the progress bars go.
    pub progress: &'a Progress,
    /// Where the rollouts read are kept for the evaluations after (a search's); `None`: read
    /// anew by each.
    pub cache: Option<&'a TrackCache>,
    /// How a search over free rollouts of these takes scores a network.
    pub objective: Objective,
}

impl Takes<'_> {
    /// Rollout `path` on the surrogate's particles, from the cache where there is one.
    fn track(&self, path: &Path) -> Result<Arc<TestTrack>> {
        match self.cache {
            Some(cache) => cache.load(path, self.topology),
            None => TestTrack::load(path, self.topology).map(Arc::new),
        }
    }
}

/// Test rollouts read once and kept for the evaluations that follow: a search scores hundreds
/// of networks on the same few takes, and reading (inflating the `.npz`) and resampling them
/// anew for each took a fifth of its time. Kept by path and by the surrogate's particles they
/// were resampled onto, up to [`TrackCache::BUDGET`] bytes; beyond it a take is read anew each
/// time. The files are not expected to change while the cache lives (a training run).
#[derive(Default)]
pub struct TrackCache {
    kept: Mutex<Kept>,
}

#[derive(Default)]
struct Kept {
    tracks: HashMap<(PathBuf, u64), Arc<TestTrack>>,
    bytes: usize,
}

impl TrackCache {
    /// The most memory the kept takes hold, bytes.
    pub const BUDGET: usize = 512 << 20;

    /// Rollout `path` resampled onto `topology`'s particles: the kept copy, else read (and
    /// kept while within the budget).
    pub fn load(&self, path: &Path, topology: &Topology) -> Result<Arc<TestTrack>> {
        let key = (path.to_path_buf(), particles_key(topology));
        if let Some(track) = self.lock().tracks.get(&key) {
            return Ok(track.clone());
        }
        let track = Arc::new(TestTrack::load(path, topology)?);
        let bytes = track.bytes();
        let mut kept = self.lock();
        if kept.bytes + bytes <= Self::BUDGET && !kept.tracks.contains_key(&key) {
            kept.bytes += bytes;
            kept.tracks.insert(key, track.clone());
        }
        Ok(track)
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Kept> {
        self.kept.lock().unwrap_or_else(|e| e.into_inner())
    }
}

/// A hash of `topology`'s particles (their rest coordinates), which a take is resampled onto.
fn particles_key(topology: &Topology) -> u64 {
    use std::hash::{Hash, Hasher};
    let mut h = std::collections::hash_map::DefaultHasher::new();
    for uv in &topology.rest_uv {
        uv.map(f64::to_bits).hash(&mut h);
    }
    h.finish()
}

/// Rollouts a piece of a batch holds on a CPU device: one chunk of the CPU kernels' narrow
/// lanes, so that a piece steps on one thread and the pieces run side by side.
const HOST_PIECE: usize = crate::model::kernels::cpu::NARROW_LANES;

/// Simulates every test rollout from its first frame with a known velocity to its end, pinned
/// particles following the data, and returns the per-frame motion RMSE of each (over the
/// particles seen in that frame, where the rollout has a `visible` mask).
///
/// On a GPU the rollouts of one length step together, `takes.batch` at a time. On the CPU
/// backends they step in pieces of at most four, the pieces on the threads side by side: a step
/// of a few rollouts of a small cloth is too little work to split across threads every substep.
/// Each rollout's curve is the same either way (its lanes do not mix with the others').
pub fn motion_curves(
    model: &dyn ForceModel,
    physics_template: &Physics,
    takes: &Takes,
) -> Result<MotionCurves> {
    let tracks = takes
        .files
        .iter()
        .map(|f| takes.track(f))
        .collect::<Result<Vec<_>>>()?;
    // Every rollout is stepped from its first state frame to its last.
    let total_frames: usize = tracks.iter().map(|t| t.track.frames - 1 - t.first).sum();
    let bar = takes.progress.bar(total_frames as u64, "eval");
    let mut order: Vec<usize> = (0..tracks.len()).collect();
    order.sort_by_key(|&i| (tracks[i].track.frames, tracks[i].first));
    let alike = |a: &usize, b: &usize| {
        tracks[*a].track.frames == tracks[*b].track.frames && tracks[*a].first == tracks[*b].first
    };
    let host = crate::backend::is_host(takes.device);
    let width = match host {
        true => takes.batch.clamp(1, HOST_PIECE),
        false => takes.batch.max(1),
    };
    let batches: Vec<EvalBatch> = order
        .chunk_by(alike)
        .flat_map(|group| group.chunks(width))
        .map(|chunk| {
            let lead = &tracks[chunk[0]];
            EvalBatch {
                tracks: &tracks,
                chunk,
                particles: takes.topology.num_particles(),
                frames: lead.track.frames,
                first: lead.first,
                frame_dt: lead.frame_dt,
                device: takes.device,
            }
        })
        .collect();
    let clock = Instant::now();
    let simulate = |batch: &EvalBatch| batch.simulate(model, physics_template, &bar);
    let done: Vec<Result<Vec<Curve>>> = match host {
        true => batches.par_iter().map(simulate).collect(),
        false => batches.iter().map(simulate).collect(),
    };
    let mut out = MotionCurves {
        curves: vec![Vec::new(); tracks.len()],
        step_seconds: clock.elapsed().as_secs_f64(),
        steps: 0,
    };
    for (batch, curves) in batches.iter().zip(done) {
        for (&i, curve) in batch.chunk.iter().zip(curves?) {
            out.curves[i] = curve;
        }
        out.steps += (batch.frames - 1 - batch.first) * batch.chunk.len();
    }
    bar.finish();
    Ok(out)
}

/// Test rollouts of one length and first frame, simulated side by side by [`motion_curves`].
struct EvalBatch<'a> {
    tracks: &'a [Arc<TestTrack>],
    /// Which of `tracks`.
    chunk: &'a [usize],
    particles: usize,
    frames: usize,
    first: usize,
    frame_dt: f64,
    device: &'a Device,
}

impl EvalBatch<'_> {
    /// Steps the rollouts from their first usable frame to their last; returns each one's
    /// per-frame RMSE curve (in the order of `chunk`); a non-finite error is refused naming the
    /// rollout and frame.
    fn simulate(
        &self,
        model: &dyn ForceModel,
        physics_template: &Physics,
        bar: &crate::progress::Bar,
    ) -> Result<Vec<Curve>> {
        let (b, first, frames) = (self.chunk.len(), self.first, self.frames);
        let physics = Physics {
            frame_dt: self.frame_dt,
            ..*physics_template
        };
        let pinned = self.pinned();
        let mut state = State {
            x: self.frame(first, false),
            v: self.frame(first, true),
        };
        let mut here = self.frame(first, false);
        let mut errs: Vec<Tensor<1>> = Vec::new();
        let mut curves = vec![Vec::new(); b];
        // Tracked markers: each frame's RMSE over the particles seen in it.
        let masked = self
            .chunk
            .iter()
            .any(|&i| self.tracks[i].track.visible.is_some());
        for j in first..frames - 1 {
            let next = self.frame(j + 1, false);
            state = sim::advance_frame(model, &physics, None, state, &pinned, &here, &next);
            let d = state.x.clone() - next.clone();
            errs.push(if masked {
                let (mask, counts) = self.seen_at(j + 1);
                let d = d * mask;
                (d.clone() * d)
                    .sum_dim(2)
                    .sum_dim(1)
                    .reshape([b])
                    .div(counts)
                    .sqrt()
            } else {
                (d.clone() * d)
                    .sum_dim(2)
                    .sum_dim(1)
                    .div_scalar(self.particles as f64)
                    .sqrt()
                    .reshape([b])
            });
            here = next;
            if errs.len() == 100 {
                self.flush(&mut errs, j, &mut curves)?;
                bar.inc(100 * b as u64);
            }
        }
        let left = errs.len();
        self.flush(&mut errs, frames - 2, &mut curves)?;
        bar.inc((left * b) as u64);
        Ok(curves)
    }

    /// Frame `j`'s positions (or, with `vel`, velocities) of the batch, [B, P, 3].
    fn frame(&self, j: usize, vel: bool) -> Tensor<3> {
        let p = self.particles;
        let mut v = Vec::with_capacity(self.chunk.len() * p * 3);
        for &i in self.chunk {
            let t = &self.tracks[i].track;
            let src = if vel { &t.velocities } else { &t.positions };
            v.extend_from_slice(&src[j * p * 3..(j + 1) * p * 3]);
        }
        Tensor::<3>::from_data(TensorData::new(v, [self.chunk.len(), p, 3]), self.device)
    }

    /// 1 where a particle is pinned, [B, P, 1].
    fn pinned(&self) -> Tensor<3> {
        let pinned: Vec<f32> = self
            .chunk
            .iter()
            .flat_map(|&i| self.tracks[i].track.pinned.iter().map(|&x| x as u8 as f32))
            .collect();
        let shape = [self.chunk.len(), self.particles, 1];
        Tensor::<3>::from_data(TensorData::new(pinned, shape), self.device)
    }

    /// Which particles frame `j` sees, [B, P, 1], and how many per rollout (at least 1), [B].
    fn seen_at(&self, j: usize) -> (Tensor<3>, Tensor<1>) {
        let (b, p) = (self.chunk.len(), self.particles);
        let mut mask = Vec::with_capacity(b * p);
        let mut counts = Vec::with_capacity(b);
        for &i in self.chunk {
            let t = &self.tracks[i].track;
            let before = mask.len();
            mask.extend((0..p).map(|q| t.seen(j, q) as u8 as f32));
            counts.push(mask[before..].iter().sum::<f32>().max(1.0));
        }
        (
            Tensor::<3>::from_data(TensorData::new(mask, [b, p, 1]), self.device),
            Tensor::<1>::from_data(TensorData::new(counts, [b]), self.device),
        )
    }

    /// Reads the pending per-frame errors (the last of them is frame `upto + 1`) into the
    /// curves (one per rollout of `chunk`, in its order).
    fn flush(&self, errs: &mut Vec<Tensor<1>>, upto: usize, curves: &mut [Curve]) -> Result<()> {
        if errs.is_empty() {
            return Ok(());
        }
        let n = errs.len();
        let data: Vec<f32> = Tensor::cat(std::mem::take(errs), 0)
            .into_data()
            .try_into_vec_as::<f32>()
            .map_err(|e| anyhow::anyhow!("{e:?}"))?;
        for (k, row) in data.chunks_exact(self.chunk.len()).enumerate() {
            let j = upto + k + 2 - n; // the frame this error belongs to
            for (slot, &e) in row.iter().enumerate() {
                if !e.is_finite() {
                    bail!(
                        "{}: the surrogate's rollout diverged at frame {j} (t = {:.3} s)",
                        self.tracks[self.chunk[slot]].path.display(),
                        j as f64 * self.frame_dt
                    );
                }
                curves[slot].push(((j - self.first) as f64 * self.frame_dt, e as f64));
            }
        }
        Ok(())
    }
}

/// [`motion_curves`] for the GNN: each test rollout starts from its first `C + 1` GNN frames
/// (every `downsample`-th data frame) and is rolled out autoregressively, pinned particles
/// following the data; the curve holds the error of every predicted GNN frame.
pub(crate) fn gnn_motion_curves(
    model: &Gnn,
    downsample: usize,
    takes: &Takes,
) -> Result<MotionCurves> {
    let c = model.history;
    let mut tracks = Vec::new();
    for f in takes.files {
        let t = TestTrack::load(f, takes.topology)?;
        if t.track.frames <= t.first + (c + 1) * downsample {
            bail!(
                "{}: {} frames are too few for the GNN's {} input frames {} apart",
                f.display(),
                t.track.frames,
                c + 1,
                downsample
            );
        }
        tracks.push(t);
    }
    let eval = GnnEval {
        model,
        downsample,
        particles: takes.topology.num_particles(),
        tracks: &tracks,
        device: takes.device,
    };
    let total: usize = (0..tracks.len()).map(|i| eval.steps_of(i)).sum();
    let bar = takes.progress.bar(total as u64, "eval");
    let mut out = MotionCurves {
        curves: vec![Vec::new(); tracks.len()],
        step_seconds: 0.0,
        steps: 0,
    };
    let order: Vec<usize> = (0..tracks.len()).collect();
    for chunk in order.chunks(takes.batch.max(1)) {
        eval.roll_out(chunk, &mut out, &bar)?;
    }
    bar.finish();
    Ok(out)
}

/// The GNN rolled out autoregressively on test rollouts by [`gnn_motion_curves`].
struct GnnEval<'a> {
    model: &'a Gnn,
    downsample: usize,
    particles: usize,
    tracks: &'a [TestTrack],
    device: &'a Device,
}

impl GnnEval<'_> {
    /// The GNN frames predicted on rollout `i`.
    fn steps_of(&self, i: usize) -> usize {
        let t = &self.tracks[i];
        (t.track.frames - 1 - t.first) / self.downsample - self.model.history
    }

    /// Data frame `j` of rollout `i`.
    fn frame_at(&self, i: usize, j: usize) -> Vec<[f32; 3]> {
        let p = self.particles;
        self.tracks[i].track.positions[j * p * 3..(j + 1) * p * 3]
            .chunks_exact(3)
            .map(|q| [q[0], q[1], q[2]])
            .collect()
    }

    /// Rolls out the rollouts `chunk` side by side, appending each predicted frame's RMSE.
    fn roll_out(
        &self,
        chunk: &[usize],
        out: &mut MotionCurves,
        bar: &crate::progress::Bar,
    ) -> Result<()> {
        let (c, downsample) = (self.model.history, self.downsample);
        let mut hist: Vec<Vec<Vec<[f32; 3]>>> = chunk
            .iter()
            .map(|&i| {
                let first = self.tracks[i].first;
                (0..=c)
                    .map(|k| self.frame_at(i, first + k * downsample))
                    .collect()
            })
            .collect();
        let pinned: Vec<Vec<bool>> = chunk
            .iter()
            .map(|&i| self.tracks[i].track.pinned.clone())
            .collect();
        let steps = chunk.iter().map(|&i| self.steps_of(i)).max().unwrap_or(0);
        for k in 0..steps {
            // Rollouts of different lengths: the shorter ones stop, the rest go on.
            let live: Vec<usize> = (0..chunk.len())
                .filter(|&s| k < self.steps_of(chunk[s]))
                .collect();
            let targets: Vec<Vec<[f32; 3]>> = live
                .iter()
                .map(|&s| {
                    let first = self.tracks[chunk[s]].first;
                    self.frame_at(chunk[s], first + (c + 1 + k) * downsample)
                })
                .collect();
            let live_hist: Vec<Vec<Vec<[f32; 3]>>> =
                live.iter().map(|&s| hist[s].clone()).collect();
            let live_pins: Vec<Vec<bool>> = live.iter().map(|&s| pinned[s].clone()).collect();
            let target_refs: Vec<&[[f32; 3]]> = targets.iter().map(|t| t.as_slice()).collect();
            let clock = Instant::now();
            let next = self
                .model
                .step(&live_hist, &live_pins, &target_refs, self.device);
            out.step_seconds += clock.elapsed().as_secs_f64();
            out.steps += live.len();
            for ((&s, x), target) in live.iter().zip(next).zip(&targets) {
                let i = chunk[s];
                self.record(i, (c + 1 + k) * downsample, &x, target, &mut out.curves[i])?;
                hist[s].remove(0);
                hist[s].push(x);
            }
            bar.inc(live.len() as u64);
        }
        Ok(())
    }

    /// Appends the RMSE of prediction `x` against `target`, `after` data frames past rollout
    /// `i`'s first; a non-finite one is refused naming the rollout and frame.
    fn record(
        &self,
        i: usize,
        after: usize,
        x: &[[f32; 3]],
        target: &[[f32; 3]],
        curve: &mut Curve,
    ) -> Result<()> {
        let (first, dt) = (self.tracks[i].first, self.tracks[i].frame_dt);
        let frame = first + after;
        let err = (x
            .iter()
            .zip(target)
            .map(|(a, b)| (0..3).map(|d| ((a[d] - b[d]) as f64).powi(2)).sum::<f64>())
            .sum::<f64>()
            / self.particles as f64)
            .sqrt();
        if !err.is_finite() {
            bail!(
                "{}: the GNN's rollout diverged at frame {frame} (t = {:.3} s)",
                self.tracks[i].path.display(),
                frame as f64 * dt
            );
        }
        curve.push(((frame - first) as f64 * dt, err));
        Ok(())
    }
}

/// Per-rollout motion curves and what simulating them cost.
#[derive(Debug, Clone, Default)]
pub struct MotionCurves {
    /// One curve per test rollout, in the order of the files.
    pub curves: Vec<Curve>,
    /// Wall time of the model's steps (data loading and resampling excluded; on the CPU, its
    /// pieces side by side), s.
    pub step_seconds: f64,
    /// Rollout·steps simulated (a batch of `B` rollouts stepped once counts `B`).
    pub steps: usize,
}

impl MotionCurves {
    /// Inference cost per rollout·step, µs (batched as the evaluation was).
    pub fn us_per_step(&self) -> f64 {
        1e6 * self.step_seconds / self.steps.max(1) as f64
    }
}

/// Summarises per-frame curves into Table 2's statistics.
pub fn summarize(curves: &[Curve], frame_dt: f64, short: f64, long: f64) -> MotionRmse {
    let within = |curve: &Curve, limit: f64| -> Vec<f64> {
        curve
            .iter()
            .filter(|(t, _)| *t <= limit + 1e-9)
            .map(|c| c.1)
            .collect()
    };
    let mean_std = |v: &[f64]| {
        let n = v.len().max(1) as f64;
        let mean = v.iter().sum::<f64>() / n;
        let var = v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / n;
        (mean, var.sqrt())
    };
    let all: Vec<f64> = curves.iter().flatten().map(|c| c.1).collect();
    let (mean, std) = mean_std(&all);
    // Each rollout's frames within the horizon, read once for its own mean and the pooled ones.
    let horizon = |seconds: f64| {
        let parts: Vec<Vec<f64>> = curves.iter().map(|c| within(c, seconds)).collect();
        let (mean, std) = mean_std(&parts.concat());
        let per_rollout = parts.iter().map(|v| mean_std(v).0).collect();
        Horizon {
            seconds,
            mean,
            std,
            per_rollout,
        }
    };
    let longest = curves.iter().map(Vec::len).max().unwrap_or(0);
    let times = curves
        .iter()
        .find(|c| c.len() == longest)
        .map(|c| c.iter().map(|e| e.0).collect())
        .unwrap_or_default();
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
        short: horizon(short),
        long: horizon(long),
        per_frame,
        times,
        frame_dt,
        rollouts: curves.len(),
    }
}

/// The source's stiffness map at every structural spring's rest midpoint, with the spring's
/// index: the value of the mesh triangle that contains the midpoint (the nearest triangle
/// centroid when none does, e.g. on the boundary in floating point). `None` when the mesh
/// carries no stiffness map.
pub fn map_at_structural_springs(
    topology: &Topology,
    rest_uv: &[[f64; 2]],
    mesh: &MeshTruth,
) -> Option<Vec<(usize, f64)>> {
    map_at_springs(topology, rest_uv, mesh, &[SpringFamily::Structural])
}

/// [`map_at_structural_springs`] for the springs of `families`.
pub fn map_at_springs(
    topology: &Topology,
    rest_uv: &[[f64; 2]],
    mesh: &MeshTruth,
    families: &[SpringFamily],
) -> Option<Vec<(usize, f64)>> {
    let stiffness = mesh.stiffness.as_ref()?;
    let corners = |t: &[usize; 3]| t.map(|i| rest_uv[i]);
    let contains = |t: &[usize; 3], p: [f64; 2]| {
        let [a, b, c] = corners(t);
        let d = (b[0] - a[0]) * (c[1] - a[1]) - (c[0] - a[0]) * (b[1] - a[1]);
        let u = ((p[0] - a[0]) * (c[1] - a[1]) - (c[0] - a[0]) * (p[1] - a[1])) / d;
        let v = ((b[0] - a[0]) * (p[1] - a[1]) - (p[0] - a[0]) * (b[1] - a[1])) / d;
        let tol = -1e-9;
        u >= tol && v >= tol && 1.0 - u - v >= tol
    };
    let centroid = |t: &[usize; 3]| {
        let [a, b, c] = corners(t);
        [(a[0] + b[0] + c[0]) / 3.0, (a[1] + b[1] + c[1]) / 3.0]
    };
    Some(
        (0..topology.num_springs())
            .filter(|&s| families.contains(&topology.family[s]))
            .map(|s| {
                let m = topology.midpoint(s);
                let tri = mesh
                    .triangles
                    .iter()
                    .position(|t| contains(t, m))
                    .unwrap_or_else(|| {
                        let d = |t: &[usize; 3]| {
                            let c = centroid(t);
                            (c[0] - m[0]).powi(2) + (c[1] - m[1]).powi(2)
                        };
                        (0..mesh.triangles.len())
                            .min_by(|&i, &j| {
                                d(&mesh.triangles[i]).total_cmp(&d(&mesh.triangles[j]))
                            })
                            .expect("a mesh has triangles")
                    });
                (s, stiffness[tri])
            })
            .collect(),
    )
}

/// Spearman's rank correlation of `a` and `b` (ties get their average rank); `None` when
/// either is constant or they have fewer than two values.
pub fn spearman(a: &[f64], b: &[f64]) -> Option<f64> {
    assert_eq!(a.len(), b.len());
    let ranks = |v: &[f64]| {
        let mut order: Vec<usize> = (0..v.len()).collect();
        order.sort_by(|&i, &j| v[i].total_cmp(&v[j]));
        let mut r = vec![0.0; v.len()];
        let mut i = 0;
        while i < order.len() {
            let mut j = i;
            while j + 1 < order.len() && v[order[j + 1]] == v[order[i]] {
                j += 1;
            }
            let avg = (i + j) as f64 / 2.0;
            for &k in &order[i..=j] {
                r[k] = avg;
            }
            i = j + 1;
        }
        r
    };
    let (ra, rb) = (ranks(a), ranks(b));
    let n = a.len() as f64;
    let mean = (n - 1.0) / 2.0;
    let (mut sab, mut saa, mut sbb) = (0.0, 0.0, 0.0);
    for (x, y) in ra.iter().zip(&rb) {
        sab += (x - mean) * (y - mean);
        saa += (x - mean).powi(2);
        sbb += (y - mean).powi(2);
    }
    (a.len() >= 2 && saa > 0.0 && sbb > 0.0).then(|| sab / (saa * sbb).sqrt())
}

/// Spearman correlation between the learned stiffness `k` of the structural springs and the
/// FEM source's stiffness map at their rest midpoints (Table 2's `stiffness_map_corr`); `None`
/// when the mesh carries no map.
pub fn stiffness_map_corr(
    topology: &Topology,
    k: &[f64],
    rest_uv: &[[f64; 2]],
    mesh: &MeshTruth,
) -> Option<f64> {
    let pairs = map_at_structural_springs(topology, rest_uv, mesh)?;
    let learned: Vec<f64> = pairs.iter().map(|&(s, _)| k[s]).collect();
    let truth: Vec<f64> = pairs.iter().map(|&(_, v)| v).collect();
    spearman(&learned, &truth)
}

/// A free rollout of the surrogate along a track: `frames` data frames from frame `first` of
/// `track` (a rollout resampled to the particles), pinned particles following the track's path
/// while it lasts and then holding its last frame.
#[derive(Debug, Clone, Copy)]
pub struct FreeRun<'a> {
    /// The recording: the start state and the pinned particles' path.
    pub track: &'a Track,
    /// The frame of `track` the surrogate starts from.
    pub first: usize,
    /// How many data frames to simulate.
    pub frames: usize,
    /// The frames kept (sorted, within `0..=frames`); `None` keeps every frame.
    pub keep: Option<&'a [usize]>,
    /// Colliders acting on the cloth from frame `first` on (time 0 at `first`).
    pub contact: Option<&'a crate::sim::Contact>,
}

impl<'a> FreeRun<'a> {
    /// `frames` frames from frame `first` of `track`, every frame kept, no colliders.
    pub fn new(track: &'a Track, first: usize, frames: usize) -> Self {
        Self {
            track,
            first,
            frames,
            keep: None,
            contact: None,
        }
    }

    /// Keeps only the frames listed in `keep` (sorted, within `0..=frames`).
    pub fn keeping(self, keep: &'a [usize]) -> Self {
        Self {
            keep: Some(keep),
            ..self
        }
    }

    /// With colliders (`None`: none).
    pub fn contact(self, contact: Option<&'a crate::sim::Contact>) -> Self {
        Self { contact, ..self }
    }

    /// Simulates `model` with `physics` on `device`, calling `on_frame(j)` after each simulated
    /// frame (for progress). Fails, naming the time, when the simulation diverges.
    pub fn simulate(
        &self,
        model: &dyn ForceModel,
        physics: &Physics,
        device: &Device,
        mut on_frame: impl FnMut(usize),
    ) -> Result<FreeRollout> {
        let &Self {
            track,
            first,
            frames,
            contact,
            ..
        } = self;
        let p = track.particles;
        if first >= track.frames {
            bail!(
                "the rollout has {} frames; cannot start at frame {first}",
                track.frames
            );
        }
        let t3 = |v: &[f32]| Tensor::<3>::from_data(TensorData::new(v.to_vec(), [1, p, 3]), device);
        let observed = |j: usize| {
            let j = (first + j).min(track.frames - 1);
            &track.positions[j * p * 3..(j + 1) * p * 3]
        };
        let pinned: Vec<f32> = track.pinned.iter().map(|&x| x as u8 as f32).collect();
        let pinned = Tensor::<3>::from_data(TensorData::new(pinned, [1, p, 1]), device);
        let v0 = &track.velocities[first * p * 3..(first + 1) * p * 3];
        let mut state = State {
            x: t3(observed(0)),
            v: t3(v0),
        };
        let mut out = FreeRollout {
            frames: Vec::new(),
            positions: Vec::new(),
            velocities: Vec::new(),
        };
        let every: Vec<usize>;
        let keep = match self.keep {
            Some(keep) => keep,
            None => {
                every = (0..=frames).collect();
                &every
            }
        };
        let mut keep = keep.iter().copied().filter(|&j| j <= frames).peekable();
        if keep.next_if_eq(&0).is_some() {
            out.record(0, observed(0).to_vec(), v0.to_vec(), physics.frame_dt)?;
        }
        for j in 0..frames {
            let (here, next) = (t3(observed(j)), t3(observed(j + 1)));
            let at = contact.map(|contact| sim::ContactAt {
                contact,
                time: j as f64 * physics.frame_dt,
            });
            state = sim::advance_frame(model, physics, at, state, &pinned, &here, &next);
            if keep.next_if_eq(&(j + 1)).is_some() {
                out.record(j + 1, host(&state.x)?, host(&state.v)?, physics.frame_dt)?;
            }
            on_frame(j + 1);
        }
        if out.frames.last() != Some(&frames) {
            // A divergence leaves non-finite values behind: check the end state too.
            let x = host(&state.x)?;
            if x.iter().any(|c| !c.is_finite()) {
                bail!(
                    "the surrogate diverged within {:.3} s",
                    frames as f64 * physics.frame_dt
                );
            }
        }
        Ok(out)
    }
}

/// A tensor's values on the host.
fn host(t: &Tensor<3>) -> Result<Vec<f32>> {
    t.clone()
        .into_data()
        .try_into_vec_as::<f32>()
        .map_err(|e| anyhow::anyhow!("{e:?}"))
}

impl FreeRollout {
    /// Keeps frame `j`'s state (frames `frame_dt` apart); a non-finite one is refused.
    fn record(&mut self, j: usize, x: Vec<f32>, v: Vec<f32>, frame_dt: f64) -> Result<()> {
        if x.iter().chain(&v).any(|c| !c.is_finite()) {
            bail!(
                "the surrogate diverged by frame {j} (t = {:.3} s)",
                j as f64 * frame_dt
            );
        }
        self.frames.push(j);
        self.positions.extend_from_slice(&x);
        self.velocities.extend_from_slice(&v);
        Ok(())
    }
}

/// Writes per-rollout motion RMSE curves as CSV: `time,rollout_0,…` (empty where a rollout
/// is shorter than the longest).
pub fn write_curves_csv(path: &std::path::Path, curves: &[Curve]) -> Result<()> {
    let mut header = vec!["time".to_string()];
    header.extend((0..curves.len()).map(|i| format!("rollout_{i}")));
    let longest = curves.iter().max_by_key(|c| c.len());
    crate::io::write_atomic(path, |file| {
        let mut w = csv::Writer::from_writer(file);
        w.write_record(&header)?;
        for (j, &(t, _)) in longest.into_iter().flatten().enumerate() {
            let mut row = vec![format!("{t:.6}")];
            row.extend(
                curves
                    .iter()
                    .map(|c| c.get(j).map_or(String::new(), |e| format!("{:.6e}", e.1))),
            );
            w.write_record(&row)?;
        }
        w.flush()?;
        Ok(())
    })
}

/// Reads the curves that [`write_curves_csv`] wrote; errors name the file, line and column.
pub fn read_curves_csv(path: &std::path::Path) -> Result<Vec<Curve>> {
    use anyhow::Context;
    let mut reader =
        csv::Reader::from_path(path).with_context(|| format!("cannot read {}", path.display()))?;
    let header = reader
        .headers()
        .with_context(|| format!("{} has no header", path.display()))?
        .clone();
    if header.get(0) != Some("time") {
        anyhow::bail!("{}: the first column must be `time`", path.display());
    }
    let mut curves = vec![Vec::new(); header.len().saturating_sub(1)];
    for record in reader.records() {
        let record = record.with_context(|| format!("{} is malformed", path.display()))?;
        let line = record.position().map_or(0, |p| p.line());
        let cell = |c: usize| -> Result<Option<f64>> {
            match record.get(c).unwrap_or("") {
                "" => Ok(None),
                v => v.parse().map(Some).with_context(|| {
                    format!(
                        "{}: line {line}, column `{}` is not a number: {v}",
                        path.display(),
                        &header[c]
                    )
                }),
            }
        };
        let t = cell(0)?.with_context(|| format!("{}: line {line} has no time", path.display()))?;
        for (i, curve) in curves.iter_mut().enumerate() {
            if let Some(e) = cell(i + 1)? {
                curve.push((t, e));
            }
        }
    }
    Ok(curves)
}

/// A free rollout of the surrogate (see [`FreeRun`]): the kept frames, `[K, P, 3]` each.
#[derive(Debug, Clone)]
pub struct FreeRollout {
    /// Frames kept, counted from the start (0 = the initial state).
    pub frames: Vec<usize>,
    /// Positions of the kept frames, `[K, P, 3]`, row-major.
    pub positions: Vec<f32>,
    /// Velocities of the kept frames, `[K, P, 3]`.
    pub velocities: Vec<f32>,
}

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
    /// Whether the run keeps the uniform network instead: it moves closer to the held-out
    /// rollouts at both horizons and `train.uniform_fallback` is on (the learned network's
    /// springs are then the run's `springs.learned.npz`).
    #[serde(default)]
    pub kept_uniform: bool,
}

impl Validation {
    /// Whether the uniform network moves closer than the learned one to the held-out rollouts
    /// at both horizons (a learned network that diverged there loses, a uniform one that
    /// diverged wins nothing).
    pub fn uniform_closer(&self) -> bool {
        let closer = |learned: f64, uniform: f64| {
            uniform.is_finite() && (uniform < learned || !learned.is_finite())
        };
        let (t, u) = (&self.trained, &self.uniform.test);
        closer(t.short.mean, u.short.mean) && closer(t.long.mean, u.long.mean)
    }

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
        } else if self.kept_uniform {
            "WARNING: the learned network does NOT beat the best uniform network at either \
             horizon; the run keeps that uniform network (`train.uniform_fallback`; the learned \
             springs are in springs.learned.npz)"
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cloth::GridSpec;
    use crate::source::{Diagonal, fem::grid_triangles};

    #[test]
    fn the_both_horizons_objective_weighs_the_early_frames_the_whole_take_drowns() {
        // Two networks' curves over a 2 s take: `early` is close for the first 0.8 s and far
        // after (the late frames parting by chaos), `late` is farther early, a little closer late.
        let curve = |first: f64, rest: f64| -> Vec<Curve> {
            vec![
                (1..=20)
                    .map(|j| (j as f64 * 0.1, if j <= 8 { first } else { rest }))
                    .collect(),
            ]
        };
        let (early, late) = (curve(0.1, 0.5), curve(0.2, 0.45));
        let whole = Objective::WholeTake;
        let both = Objective::BothHorizons { short_seconds: 0.8 };
        // The whole take: (8·0.1 + 12·0.5) / 20 = 0.34 against (8·0.2 + 12·0.45) / 20 = 0.35.
        assert!((whole.score(&early, 0.1) - 0.34).abs() < 1e-12);
        assert!((whole.score(&late, 0.1) - 0.35).abs() < 1e-12);
        // Both horizons: √(0.1 · 0.34) against √(0.2 · 0.35).
        assert!((both.score(&early, 0.1) - (0.1f64 * 0.34).sqrt()).abs() < 1e-12);
        assert!((both.score(&late, 0.1) - (0.2f64 * 0.35).sqrt()).abs() < 1e-12);
        // Where the two horizons agree, so do the objectives; here the late frames' small edge
        // does not outweigh twice the error up to 0.8 s.
        let nearly_early = curve(0.1, 0.52);
        assert!(whole.score(&nearly_early, 0.1) > whole.score(&late, 0.1));
        assert!(both.score(&nearly_early, 0.1) < both.score(&late, 0.1));
    }

    #[test]
    fn motion_rmse_stores_horizons_with_their_seconds_and_reads_old_files() {
        let curves = vec![vec![(0.1, 1.0), (0.2, 3.0), (0.3, 5.0)]];
        let m = summarize(&curves, 0.1, 0.2, 0.3);
        assert_eq!(
            (m.short.seconds, m.short.mean, m.short.std),
            (0.2, 2.0, 1.0)
        );
        assert_eq!((m.long.seconds, m.long.mean), (0.3, 3.0));
        let json = serde_json::to_value(&m).unwrap();
        assert_eq!(json["short"]["seconds"], 0.2);
        assert_eq!(json["long"]["mean"], 3.0);
        assert!(json.get("mean_8s").is_none());
        let back: MotionRmse = serde_json::from_value(json).unwrap();
        assert_eq!(back, m);
        // An eval.json of an older springtime: fixed names, horizons absent (0.8 s and 8 s).
        let old: MotionRmse = serde_json::from_str(
            r#"{"mean":1.0,"std":0.5,"mean_0_8s":0.1,"std_0_8s":0.01,"mean_8s":0.9,
                "std_8s":0.2,"per_frame":[0.1],"frame_dt":0.01,"rollouts":2}"#,
        )
        .unwrap();
        assert_eq!(
            (old.short.seconds, old.short.mean, old.short.std),
            (0.8, 0.1, 0.01)
        );
        assert_eq!(
            (old.long.seconds, old.long.mean, old.long.std),
            (8.0, 0.9, 0.2)
        );
    }

    #[test]
    fn each_rollouts_mean_within_a_horizon_is_stored_and_weighs_into_the_mean() {
        // Two takes of equal length: the horizon's mean is the mean of their means.
        let curves = vec![
            vec![(0.1, 1.0), (0.2, 3.0), (0.3, 5.0)],
            vec![(0.1, 2.0), (0.2, 2.0), (0.3, 8.0)],
        ];
        let m = summarize(&curves, 0.1, 0.2, 0.3);
        assert_eq!(m.short.per_rollout, vec![2.0, 2.0]);
        assert_eq!(m.long.per_rollout, vec![3.0, 4.0]);
        assert_eq!(m.long.mean, 3.5);
        // A shorter take counts only its own frames.
        let m = summarize(&[curves[0].clone(), vec![(0.1, 4.0)]], 0.1, 0.2, 0.3);
        assert_eq!(m.long.per_rollout, vec![3.0, 4.0]);
        let json = serde_json::to_value(&m).unwrap();
        assert_eq!(json["long"]["per_rollout"][1], 4.0);
        // A file written before the key existed reads with none.
        let mut old = json;
        old["long"].as_object_mut().unwrap().remove("per_rollout");
        let back: MotionRmse = serde_json::from_value(old).unwrap();
        assert!(back.long.per_rollout.is_empty());
        assert_eq!(back.short.per_rollout, vec![2.0, 4.0]);
    }

    #[test]
    fn motion_curves_csv_round_trips_rollouts_of_different_lengths() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("motion_rmse.csv");
        let curves = vec![
            vec![(0.01, 1.5e-3), (0.02, 2.5e-3), (0.03, 4.0e-3)],
            vec![(0.01, 7.0e-4)],
        ];
        write_curves_csv(&path, &curves).unwrap();
        assert_eq!(read_curves_csv(&path).unwrap(), curves);
        let text = std::fs::read_to_string(&path).unwrap();
        assert!(text.starts_with("time,rollout_0,rollout_1\n"), "{text}");
        std::fs::write(&path, "time,rollout_0\n0.01,1e-3\n0.02,oops\n").unwrap();
        let e = format!("{:#}", read_curves_csv(&path).unwrap_err());
        assert!(
            e.contains("line 3") && e.contains("rollout_0") && e.contains("oops"),
            "{e}"
        );
    }

    #[test]
    fn spearman_handles_ties_and_monotone_maps() {
        assert_eq!(spearman(&[1.0, 2.0, 3.0], &[10.0, 20.0, 30.0]), Some(1.0));
        assert_eq!(spearman(&[1.0, 2.0, 3.0], &[3.0, 2.0, 1.0]), Some(-1.0));
        // Any monotone transform keeps the value; ties share their rank.
        let a = [1.0, 5.0, 5.0, 9.0, 2.0];
        let b = [1.0f64, 25.0, 25.0, 81.0, 4.0];
        assert!((spearman(&a, &b).unwrap() - 1.0).abs() < 1e-12);
        assert_eq!(spearman(&a, &[2.0; 5]), None);
        // With ties: ranks (0, 2.5, 2.5, 4, 1) against (0, 1, 2, 3, 4) give 3.5 / √(9.5 · 10).
        let r = spearman(&a, &[0.0, 1.0, 2.0, 3.0, 4.0]).unwrap();
        assert!((r - 3.5 / 95f64.sqrt()).abs() < 1e-12, "{r}");
    }

    #[test]
    fn map_lookup_finds_the_triangle_under_each_midpoint() {
        // A 4 × 4 mesh whose first cell column is soft and the rest stiff, read at a 5 × 5 grid.
        let (w, h) = (3.0, 3.0);
        let uv: Vec<[f64; 2]> = (0..4)
            .flat_map(|r| (0..4).map(move |c| [c as f64, r as f64]))
            .collect();
        let triangles = grid_triangles(4, 4, Diagonal::Alternating);
        let stiffness = triangles
            .iter()
            .map(|t| {
                if t.iter().map(|&i| uv[i][0]).sum::<f64>() / 3.0 < 1.0 {
                    1.0
                } else {
                    9.0
                }
            })
            .collect();
        let mesh = MeshTruth {
            triangles,
            stiffness: Some(stiffness),
        };
        let topo = Topology::grid(
            &GridSpec {
                nx: 5,
                ny: 5,
                ..GridSpec::default()
            },
            w,
            h,
        );
        let pairs = map_at_structural_springs(&topo, &uv, &mesh).unwrap();
        assert_eq!(pairs.len(), 2 * 5 * 4);
        for &(s, v) in &pairs {
            let m = topo.midpoint(s);
            if m[0] < 0.95 {
                assert_eq!(v, 1.0, "{m:?}");
            } else if m[0] > 1.05 {
                assert_eq!(v, 9.0, "{m:?}");
            }
        }
        // A surrogate whose stiffness follows the map correlates perfectly.
        let k: Vec<f64> = (0..topo.num_springs())
            .map(|s| {
                if topo.midpoint(s)[0] < 1.0 {
                    10.0
                } else {
                    90.0
                }
            })
            .collect();
        assert!(stiffness_map_corr(&topo, &k, &uv, &mesh).unwrap() > 0.95);
    }
}
