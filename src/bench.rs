//! `springtime bench`: the training workload of `../shared/bench/peer_torch.py`, timed.
//!
//! Same definition as the peer: a 32 × 32 cloth on a 1 m square (1 kg, Rayleigh 0.001),
//! structural + both shear + stride-2 bending springs (5,826), ground truth k in three vertical
//! stripes (10 / 50 / 100 N/m) and b = 0.06; `B` clips of `T` steps at 1 ms that start at rest
//! from the flat grid under random rotations with the two top corners pinned; force + impulse
//! loss (λ_f = 1, λ_J = 10) on the simulated states; one iteration = rollout, loss, backward
//! and an Adam step on k and b.

use std::time::Instant;

use anyhow::Result;
use burn::module::Module;
use burn::optim::{AdamConfig, GradientsParams};
use burn::tensor::Device;
use rand::{SeedableRng, rngs::StdRng};
use rayon::prelude::*;
use serde::Serialize;

use crate::backend::Backend;
use crate::cloth::{Resampler, Topology};
use crate::data::{ClipBatch, Track};
use crate::model::{Kernel, SpringNet};
use crate::sim::{self, Physics, State};
use crate::source::{Layout, Scenario, SourceConfig, SpringCloth, simulate_rollout};
use crate::train::{ForceOn, LossWeights, loss};

/// What to time.
#[derive(Debug, Clone)]
pub struct BenchOptions {
    /// Clips per iteration.
    pub batch: usize,
    /// Steps per clip.
    pub steps: usize,
    /// Backend.
    pub backend: Backend,
    /// Timed training iterations (after one warm-up).
    pub iters: usize,
    /// Spring-force implementation.
    pub kernel: Kernel,
    /// Particles per side.
    pub n: usize,
}

/// The bench's JSON line.
#[derive(Debug, Clone, Serialize)]
pub struct BenchReport {
    /// Training µs per clip·step: rollout, loss, backward, Adam step.
    pub train_us_per_clip_step: f64,
    /// Forward µs per clip·step: rollout without autodiff.
    pub fwd_us_per_clip_step: f64,
    /// Seconds per training iteration.
    pub sec_per_iter: f64,
    /// Peak resident memory of the process, MiB.
    pub peak_rss_mib: f64,
    /// Backend.
    pub backend: String,
    /// Kernel asked for.
    pub kernel: Kernel,
    /// The spring-force path that ran: `"fused"` (the CPU kernels of `flex` and `ndarray`, the
    /// CubeCL kernels on `wgpu`) or `"tensor"` (the tensor-op reference, when asked for).
    pub kernel_used: &'static str,
    /// The device: Burn's backend name with the adapter (e.g. `cubecl<wgpu<vulkan>>` and the
    /// GPU's name) or the CPU backend.
    pub device: String,
    /// The largest buffer the device allocates, bytes (`null` on the CPU): a batch's
    /// `[B, T + 1, P, 3]` positions must fit in one.
    pub max_buffer_bytes: Option<u64>,
    /// Whether Burn's matmul and reduce kernels are autotuned (the `autotune` build feature;
    /// the spring kernels are springtime's own either way).
    pub autotune: bool,
    /// Clips per iteration.
    pub batch: usize,
    /// Steps per clip.
    pub steps: usize,
    /// Springs.
    pub springs: usize,
    /// Particles.
    pub particles: usize,
    /// Timed iterations.
    pub iters: usize,
    /// Worker threads available to the CPU kernels.
    pub threads: usize,
    /// The loss of the last iteration (a sanity check that the work was done).
    pub loss: f64,
}

/// The peer's cloth: 1 m square, 1 kg, stripes 10/50/100, b = 0.06, Rayleigh 0.001.
fn peer_source(n: usize, steps: usize) -> SourceConfig {
    SourceConfig {
        nx: n,
        ny: n,
        width: 1.0,
        height: 1.0,
        areal_density: 1.0,
        stiffness_levels: vec![10.0, 50.0, 100.0],
        layout: Layout::Stripes,
        damping: 0.06,
        rayleigh: 0.001,
        seconds: steps as f64 * 1e-3,
        dt: 1e-3,
        ..SourceConfig::default()
    }
}

/// Runs the bench.
pub fn run(options: &BenchOptions) -> Result<BenchReport> {
    let (n, b, t) = (options.n, options.batch, options.steps);
    anyhow::ensure!(
        n >= 2 && b >= 1 && t >= 1,
        "bench needs --n ≥ 2, --batch ≥ 1 and --steps ≥ 1 (got {n}, {b}, {t})"
    );
    let cfg = peer_source(n, t);
    let cloth = SpringCloth::from_config(&cfg);
    let topo = cloth.topology.clone();
    let p = topo.num_particles();
    let work = Workload {
        tracks: peer_tracks(&cloth, &cfg, n, b)?,
        physics: Physics {
            frame_dt: 1e-3,
            substeps: 1,
            mass: cloth.mass,
            rayleigh: cfg.rayleigh,
            gravity: cfg.gravity,
            viscosity: 0.0,
            shear_compression: 1.0,
        },
        batch: b,
        steps: t,
        particles: p,
    };
    let plain = options.backend.device()?;
    let training = work.train(
        &topo,
        options.kernel,
        &plain.clone().autodiff(),
        options.iters,
    )?;
    let sec_per_iter = training.sec_per_iter;
    // Forward only: the rollout on the plain device, no graph.
    let fwd_model = training.model.valid().to_device(&plain);
    let fwd = work.forward(&fwd_model, &plain, options.iters.max(1))?;
    Ok(BenchReport {
        train_us_per_clip_step: sec_per_iter / (b * t) as f64 * 1e6,
        fwd_us_per_clip_step: fwd / (b * t) as f64 * 1e6,
        sec_per_iter,
        peak_rss_mib: crate::train::run::peak_rss_mib(),
        backend: options.backend.to_string(),
        kernel: options.kernel,
        kernel_used: if training.fused { "fused" } else { "tensor" },
        device: crate::backend::describe(&plain),
        max_buffer_bytes: crate::backend::max_buffer_bytes(&plain),
        autotune: cfg!(feature = "autotune"),
        batch: b,
        steps: t,
        springs: topo.num_springs(),
        particles: p,
        iters: options.iters,
        threads: rayon::current_num_threads(),
        loss: training.loss,
    })
}

/// The peer's `b` clips: random rotations at rest, the two top corners (of `n` per side)
/// pinned, drawn in order (one seed, any thread count) and simulated in parallel.
fn peer_tracks(cloth: &SpringCloth, cfg: &SourceConfig, n: usize, b: usize) -> Result<Vec<Track>> {
    let topo = &cloth.topology;
    let p = topo.num_particles();
    let mut rng = StdRng::seed_from_u64(0);
    let identity = Resampler::new(&topo.rest_uv, &topo.rest_uv);
    let scenarios: Vec<Scenario> = (0..b)
        .map(|_| {
            let mut scenario = Scenario::random(&topo.rest_uv, 0.0, &mut rng);
            scenario.pinned = (0..p).map(|i| i == (n - 1) * n || i == n * n - 1).collect();
            scenario
        })
        .collect();
    scenarios
        .par_iter()
        .map(|scenario| {
            let r = simulate_rollout(cloth, cfg, scenario, None, "bench")?;
            Ok(Track::new(&r, &identity))
        })
        .collect::<Result<_>>()
}

/// The timed work: the clips and the surrogate's physics.
struct Workload {
    tracks: Vec<Track>,
    physics: Physics,
    /// Clips per iteration.
    batch: usize,
    /// Steps per clip.
    steps: usize,
    /// Particles per clip.
    particles: usize,
}

/// The training iterations' outcome.
struct Training {
    /// The model after the last iteration.
    model: SpringNet,
    /// Whether its spring forces ran the fused kernels.
    fused: bool,
    /// Seconds per timed iteration.
    sec_per_iter: f64,
    /// The loss of the last iteration.
    loss: f64,
}

impl Workload {
    /// Every clip, from its first frame.
    fn views(&self) -> Vec<(&Track, usize)> {
        self.tracks.iter().map(|tr| (tr, 0)).collect()
    }

    /// A uniform surrogate trained on the clips on the autodiff `device`: one warm-up
    /// iteration, then `iters` timed.
    fn train(
        &self,
        topo: &Topology,
        kernel: Kernel,
        device: &Device,
        iters: usize,
    ) -> Result<Training> {
        let physics = &self.physics;
        let batch = ClipBatch::new(&self.views(), self.steps, physics.mass, 1e-3, device)?;
        let mut model = SpringNet::uniform(topo, 50.0, 0.01, device).with_kernel(kernel);
        let fused = model.graph.fused_forces();
        let mut optim = AdamConfig::new().with_epsilon(1e-8).init();
        let weights = LossWeights::default();
        let ids = [model.k.id, model.b.id];
        let mut last = 0.0;
        let mut step = |model: SpringNet| {
            let terms = loss(&model, physics, &batch, &weights, ForceOn::Simulated);
            last = terms.total.clone().into_scalar::<f32>() as f64;
            let mut grads = terms.total.backward();
            let grads = GradientsParams::from_params(&mut grads, &model, &ids);
            optim.step(1e-3, model, grads)
        };
        model = step(model); // warm-up
        let start = Instant::now();
        for _ in 0..iters {
            model = step(model);
        }
        let sec_per_iter = start.elapsed().as_secs_f64() / iters.max(1) as f64;
        Ok(Training {
            model,
            fused,
            sec_per_iter,
            loss: last,
        })
    }

    /// Seconds per forward rollout of the clips (no graph) with `model` on `device`: one
    /// warm-up, then the mean of `reps`.
    fn forward(&self, model: &SpringNet, device: &Device, reps: usize) -> Result<f64> {
        let (b, t, p) = (self.batch, self.steps, self.particles);
        let physics = &self.physics;
        let plain_batch = ClipBatch::new(&self.views(), t, physics.mass, 1e-3, device)?;
        let pinned = plain_batch.pinned.clone();
        let frame = |j: usize| {
            plain_batch
                .positions
                .clone()
                .slice([0..b, j..j + 1, 0..p, 0..3])
                .reshape([b, p, 3])
        };
        let frames: Vec<_> = (0..=t).map(frame).collect();
        let forward = || {
            let mut state = State {
                x: frames[0].clone(),
                v: plain_batch
                    .velocities
                    .clone()
                    .slice([0..b, 0..1, 0..p, 0..3])
                    .reshape([b, p, 3]),
            };
            for j in 0..t {
                state = sim::step_frame(
                    model,
                    physics,
                    None,
                    state,
                    &pinned,
                    &frames[j],
                    &frames[j + 1],
                )
                .0;
            }
            state.x.sum().into_scalar::<f32>()
        };
        forward(); // warm-up
        let start = Instant::now();
        for _ in 0..reps {
            forward();
        }
        Ok(start.elapsed().as_secs_f64() / reps as f64)
    }
}
