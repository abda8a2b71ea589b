//! Training (paper §3.3): dual-pass curriculum with Adam, checkpoints and resume.
//!
//! The stiffness pass trains `k` with `b` frozen on low-velocity clips; the damping pass
//! trains `b` with `k` frozen on regular clips. `mode = "single"` trains both at once.

pub mod losses;
pub mod run;

pub use losses::{ForceOn, LossTerms, LossValues, LossWeights, loss, loss_with_budget};
pub use run::{RunDir, RunState, Status};

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use burn::module::Module;
use burn::optim::{AdamConfig, GradientsParams};
use burn::tensor::Device;
use serde::{Deserialize, Serialize};

use crate::cloth::{Resampler, Topology};
use crate::config::Config;
use crate::data::{ClipRef, ClipSet, HostBatch, Rollout, Sampler, SpringTruth};
use crate::model::SpringNet;
use crate::progress::Progress;
use crate::sim::{Physics, Stability};

/// Which clips a pass draws from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ClipPool {
    /// Clips of the last second of each rollout (App. A).
    LowVelocity,
    /// The regular clips.
    Regular,
    /// Both.
    All,
}

/// One pass of the curriculum.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PassConfig {
    /// Adam iterations.
    pub iterations: usize,
    /// Clips per iteration.
    pub batch: usize,
    /// Adam learning rate.
    pub lr: f64,
    /// Loss weights.
    pub weights: LossWeights,
    /// Where the clips come from.
    pub clips: ClipPool,
}

impl Default for PassConfig {
    fn default() -> Self {
        Self {
            iterations: 128,
            batch: 32,
            lr: 1.0,
            weights: LossWeights::default(),
            clips: ClipPool::Regular,
        }
    }
}

/// Dual pass (the paper) or a single pass.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Mode {
    /// Stiffness pass, then damping pass.
    #[default]
    Dual,
    /// `k` and `b` together (`train.single`).
    Single,
}

/// The `[train]` section.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TrainConfig {
    /// Curriculum.
    pub mode: Mode,
    /// Where the simulated forces are evaluated.
    pub force_on: ForceOn,
    /// Adam's ε (Burn's default 1e-5 is too large for these gradients).
    pub adam_epsilon: f64,
    /// Iterations between checkpoints.
    pub checkpoint_every: usize,
    /// Seed of the clip order.
    pub seed: u64,
    /// Recompute activations in the backward pass instead of storing them (tensor-op path).
    pub gradient_checkpointing: bool,
    /// Memory the fused rollout may keep for its backward pass, MiB; beyond it, states are
    /// checkpointed every ⌈√T⌉ frames and recomputed.
    pub state_budget_mib: usize,
    /// The stiffness pass.
    pub stiffness: PassConfig,
    /// The damping pass.
    pub damping: PassConfig,
    /// The single pass.
    pub single: PassConfig,
}

impl Default for TrainConfig {
    fn default() -> Self {
        Self {
            mode: Mode::Dual,
            force_on: ForceOn::Simulated,
            adam_epsilon: 1e-8,
            checkpoint_every: 16,
            seed: 0,
            gradient_checkpointing: false,
            state_budget_mib: losses::DEFAULT_STATE_BUDGET_MIB,
            stiffness: PassConfig {
                lr: 2.0,
                clips: ClipPool::LowVelocity,
                ..PassConfig::default()
            },
            damping: PassConfig {
                lr: 0.1,
                ..PassConfig::default()
            },
            single: PassConfig {
                iterations: 256,
                clips: ClipPool::All,
                ..PassConfig::default()
            },
        }
    }
}

impl TrainConfig {
    /// Checks ranges; errors name the key.
    pub fn validate(&self) -> Result<()> {
        for (name, p) in [
            ("stiffness", &self.stiffness),
            ("damping", &self.damping),
            ("single", &self.single),
        ] {
            if p.batch == 0 {
                bail!("`train.{name}.batch` must be at least 1");
            }
            if !(p.lr >= 0.0 && p.lr.is_finite()) {
                bail!(
                    "`train.{name}.lr` must be a non-negative number, is {}",
                    p.lr
                );
            }
            let w = &p.weights;
            for (key, v) in [
                ("force", w.force),
                ("impulse", w.impulse),
                ("position", w.position),
                ("k_neg", w.k_neg),
                ("b_neg", w.b_neg),
            ] {
                if !(v >= 0.0 && v.is_finite()) {
                    bail!("`train.{name}.weights.{key}` must be non-negative, is {v}");
                }
            }
        }
        if self.checkpoint_every == 0 {
            bail!("`train.checkpoint_every` must be at least 1");
        }
        if !(self.adam_epsilon > 0.0) {
            bail!("`train.adam_epsilon` must be positive");
        }
        Ok(())
    }

    /// The passes to run: name, config, whether `k` and `b` are trained.
    pub fn passes(&self) -> Vec<(&'static str, &PassConfig, bool, bool)> {
        match self.mode {
            Mode::Dual => vec![
                ("stiffness", &self.stiffness, true, false),
                ("damping", &self.damping, false, true),
            ],
            Mode::Single => vec![("single", &self.single, true, true)],
        }
    }

    /// Total iterations over all passes.
    pub fn total_iterations(&self) -> usize {
        self.passes().iter().map(|p| p.1.iterations).sum()
    }
}

/// Command-line choices of a training job.
#[derive(Debug, Clone, Default)]
pub struct TrainOptions {
    /// Run directory (default `runs/<name>`).
    pub out: Option<PathBuf>,
    /// Continue from the last checkpoint.
    pub resume: bool,
    /// Overwrite an existing run.
    pub force: bool,
}

/// What a finished training job reports.
#[derive(Debug, Clone, Serialize)]
pub struct TrainSummary {
    /// Run directory.
    pub run_dir: PathBuf,
    /// Iterations done.
    pub iterations: usize,
    /// Wall time, s.
    pub wall_seconds: f64,
    /// Peak resident memory, MiB.
    pub peak_rss_mib: f64,
    /// Final losses.
    pub last: LossValues,
    /// Final RMSE of `k` (when the data has ground-truth springs).
    pub rmse_k: Option<f64>,
    /// Final RMSE of `b`.
    pub rmse_b: Option<f64>,
}

/// Ground-truth `k` and `b` per surrogate spring.
pub type Truth = (Vec<f64>, Vec<f64>);

/// Ground-truth `k`, `b` per surrogate spring, when the source's springs are the surrogate's.
pub fn matching_truth(
    truth: &SpringTruth,
    topology: &Topology,
    resampler: &Resampler,
) -> Option<(Vec<f64>, Vec<f64>)> {
    if !resampler.is_exact() || truth.springs.len() != topology.num_springs() {
        return None;
    }
    // Landmark index → particle index (the resampler is a permutation here).
    let mut to_particle = vec![usize::MAX; resampler.num_particles()];
    for (p, idx) in resampler.index.iter().enumerate() {
        if idx[0] >= to_particle.len() {
            return None;
        }
        to_particle[idx[0]] = p;
    }
    let mut by_ends = std::collections::HashMap::new();
    for (s, &[a, b]) in truth.springs.iter().enumerate() {
        let (a, b) = (*to_particle.get(a)?, *to_particle.get(b)?);
        by_ends.insert((a.min(b), a.max(b)), s);
    }
    let mut k = Vec::with_capacity(topology.num_springs());
    let mut b = Vec::with_capacity(topology.num_springs());
    for &[pa, pb] in &topology.springs {
        let s = *by_ends.get(&(pa.min(pb), pa.max(pb)))?;
        k.push(truth.k[s]);
        b.push(truth.b[s]);
    }
    Some((k, b))
}

/// Root-mean-square difference (Eq. 13).
pub fn rmse(a: &[f64], b: &[f64]) -> f64 {
    (a.iter().zip(b).map(|(x, y)| (x - y).powi(2)).sum::<f64>() / a.len().max(1) as f64).sqrt()
}

/// The surrogate topology of a config over a `width × height` rectangle.
pub fn topology(config: &Config, width: f64, height: f64) -> Topology {
    Topology::grid(&config.cloth, width, height)
}

/// The training device of a config.
pub fn training_device(config: &Config) -> Result<Device> {
    let device = config.backend.device()?.autodiff();
    Ok(if config.train.gradient_checkpointing {
        device.gradient_checkpointing()
    } else {
        device
    })
}

/// Opens the training clips of `config` (generating the data first when it is missing and the
/// config has a source).
pub fn open_training_clips(
    config: &Config,
    progress: &Progress,
) -> Result<(ClipSet, Option<Truth>)> {
    crate::ensure_data(config, progress)?;
    let split = config.data.split()?;
    let bar = progress.bar(split.train.len() as u64, "load");
    let set = ClipSet::open(
        &split.train,
        &config.data.clips,
        |w, h| topology(config, w, h),
        config.data.cache_mib,
        |n| bar.set_position(n as u64),
    )?;
    bar.finish();
    // Ground truth, if the first rollout carries springs that match the surrogate's.
    let first = Rollout::load(&split.train[0])?;
    let resampler = Resampler::new(&first.rest_uv, &set.topology.rest_uv);
    let truth = first
        .springs
        .as_ref()
        .and_then(|t| matching_truth(t, &set.topology, &resampler));
    Ok((set, truth))
}

/// Runs the training job of `config`.
pub fn train(config: &Config, options: &TrainOptions, progress: &Progress) -> Result<TrainSummary> {
    let run = RunDir::new(config.run_dir(options.out.as_deref()));
    let previous = if options.resume { run.state()? } else { None };
    if options.resume {
        match &previous {
            None => bail!("--resume: {} holds no run to resume", run.dir.display()),
            Some(s) if s.status == Status::Finished => {
                bail!(
                    "--resume: the run in {} is already finished (pass --force to train it again)",
                    run.dir.display()
                )
            }
            _ => {}
        }
    } else {
        run.check_fresh(options.force)?;
    }
    let (clips, truth) = open_training_clips(config, progress)?;
    let clips = Arc::new(clips);
    if !options.resume {
        run.create_fresh()?;
    }
    crate::io::write_text(&run.config(), &config.to_toml())?;
    let device = training_device(config)?;
    let physics = Physics {
        frame_dt: clips.info.frame_dt,
        substeps: config.sim.substeps,
        mass: clips.particle_mass(),
        rayleigh: config.sim.rayleigh,
        gravity: config.sim.gravity,
    };
    let topo = clips.topology.clone();
    let mut model = SpringNet::uniform(&topo, config.model.k_init, config.model.b_init, &device)
        .with_kernel(config.model.kernel);
    let mut start_iteration = 0;
    if let Some(state) = &previous {
        if state.checkpoint > 0 {
            let record = burn::store::ModuleRecord::load(run.checkpoint(state.checkpoint))
                .map_err(|e| {
                    anyhow::anyhow!(
                        "cannot read checkpoint {}: {e}",
                        run.checkpoint(state.checkpoint).display()
                    )
                })?;
            model = model
                .try_load_record(record)
                .map_err(|e| anyhow::anyhow!("checkpoint does not fit this config: {e}"))?;
            start_iteration = state.checkpoint;
        }
        run.truncate_metrics(start_iteration)?;
    }
    Stability::estimate(
        &topo,
        &model.k_values(),
        &model.b_values(),
        physics.mass,
        physics.rayleigh,
        physics.sim_dt(),
    )
    .check(
        "the surrogate at its initial k and b",
        config.sim.allow_unstable,
    )?;

    let total = config.train.total_iterations();
    let started = Instant::now();
    let prior_wall = previous.as_ref().map_or(0.0, |s| s.wall_seconds);
    let mut state = RunState {
        status: Status::Running,
        iteration: start_iteration,
        checkpoint: start_iteration,
        backend: config.backend.to_string(),
        wall_seconds: prior_wall,
        peak_rss_mib: 0.0,
        error: None,
    };
    run.write_state(&state)?;
    let bar = progress.bar(total as u64, "train");
    bar.set_position(start_iteration as u64);
    let mut last = LossValues::default();
    let mut rmse_now = truth
        .as_ref()
        .map(|(k, b)| (rmse(&model.k_values(), k), rmse(&model.b_values(), b)));
    let mut global = 0;
    let mut pending = Vec::new();
    for (pass_index, (name, pass, train_k, train_b)) in
        config.train.passes().into_iter().enumerate()
    {
        let pass_start = global;
        global += pass.iterations;
        if start_iteration >= global {
            continue;
        }
        let pool: Vec<ClipRef> = pool_of(&clips, pass.clips, name, progress)?;
        let mut sampler = Sampler::new(
            pool.len(),
            config.train.seed ^ ((pass_index as u64 + 1) * 0x5851_F42D),
        );
        // Skip what was done before a resume, keeping the clip order reproducible.
        for _ in pass_start..start_iteration.max(pass_start) {
            sampler.next(pass.batch);
        }
        let mut optim = AdamConfig::new()
            .with_epsilon(config.train.adam_epsilon as f32)
            .init();
        if start_iteration > pass_start && run.optimizer(start_iteration).exists() {
            optim = optim
                .load(run.optimizer(start_iteration))
                .map_err(|e| anyhow::anyhow!("cannot read optimizer state: {e}"))?;
        }
        model.k = model.k.clone().set_require_grad(train_k);
        model.b = model.b.clone().set_require_grad(train_b);
        let trained: Vec<_> = [(train_k, model.k.id), (train_b, model.b.id)]
            .into_iter()
            .filter_map(|(t, id)| t.then_some(id))
            .collect();
        // The next batch is read and assembled on another thread while this one trains.
        let next_refs = |sampler: &mut Sampler| -> Vec<ClipRef> {
            sampler
                .next(pass.batch)
                .into_iter()
                .map(|i| pool[i])
                .collect()
        };
        let prefetch = |refs: Vec<ClipRef>| {
            let clips = Arc::clone(&clips);
            std::thread::spawn(move || clips.host_batch(&refs))
        };
        let mut upcoming = None;
        for it in start_iteration.max(pass_start)..global {
            let host = match upcoming.take() {
                Some(handle) => join_batch(handle)?,
                None => clips.host_batch(&next_refs(&mut sampler))?,
            };
            if it + 1 < global {
                upcoming = Some(prefetch(next_refs(&mut sampler)));
            }
            let batch = host.to_device(&device);
            let terms = loss(
                &model,
                &physics,
                &batch,
                &pass.weights,
                config.train.force_on,
            );
            let values = terms.values();
            if !values.total.is_finite() {
                let message = format!(
                    "training stopped: the loss became {} at iteration {} ({name} pass; force {:.4e}, impulse {:.4e}). \
                     The rollout likely diverged: {}. The last good model is checkpoint {} in {}; lower \
                     `train.{name}.lr`, use more `sim.substeps`, or resume from the checkpoint",
                    values.total,
                    it + 1,
                    values.force,
                    values.impulse,
                    Stability::estimate(
                        &topo,
                        &model.k_values(),
                        &model.b_values(),
                        physics.mass,
                        physics.rayleigh,
                        physics.sim_dt()
                    )
                    .describe(),
                    state.checkpoint,
                    run.dir.display(),
                );
                run.append_metrics(&pending)?;
                state.status = Status::Failed;
                state.error = Some(message.clone());
                run.write_state(&state)?;
                bar.abandon();
                bail!(message);
            }
            let mut grads = terms.total.backward();
            let grads = GradientsParams::from_params(&mut grads, &model, &trained);
            model = optim.step(pass.lr, model, grads);
            last = values;
            if let Some((k, b)) = &truth {
                rmse_now = Some((rmse(&model.k_values(), k), rmse(&model.b_values(), b)));
            }
            let elapsed = prior_wall + started.elapsed().as_secs_f64();
            let (rk, rb) = rmse_now.map_or((String::new(), String::new()), |(k, b)| {
                (format!("{k:.6}"), format!("{b:.6}"))
            });
            pending.push(format!(
                "{},{name},{:.8e},{:.8e},{:.8e},{:.8e},{:.8e},{:.8e},{rk},{rb},{elapsed:.3}",
                it + 1,
                values.total,
                values.force,
                values.impulse,
                values.position,
                values.k_neg,
                values.b_neg
            ));
            bar.set_message(match rmse_now {
                Some((k, b)) => format!(
                    "{name} loss {:.3e} rmse_k {k:.3} rmse_b {b:.3}",
                    values.total
                ),
                None => format!("{name} loss {:.3e}", values.total),
            });
            bar.inc(1);
            state.iteration = it + 1;
            if (it + 1) % config.train.checkpoint_every == 0 || it + 1 == global {
                run.append_metrics(&pending)?;
                pending.clear();
                RunDir::save_module(&model, &run.checkpoint(it + 1))?;
                let optim_path = run.optimizer(it + 1);
                crate::io::write_atomic_with_path(&optim_path, |tmp| {
                    optim
                        .save(tmp)
                        .map_err(|e| anyhow::anyhow!("cannot save optimizer state: {e}"))
                })?;
                let old = state.checkpoint;
                state.checkpoint = it + 1;
                state.wall_seconds = elapsed;
                state.peak_rss_mib = run::peak_rss_mib();
                run.write_state(&state)?;
                if old > 0 && old != state.checkpoint {
                    let _ = std::fs::remove_file(run.optimizer(old));
                }
            }
        }
        start_iteration = global;
    }
    bar.finish();
    run.append_metrics(&pending)?;
    let model = model.valid();
    RunDir::save_module(&model, &run.model())?;
    run::write_springs(
        &run.springs(),
        &topo,
        &model.k_values(),
        &model.b_values(),
        physics.mass,
    )?;
    state.status = Status::Finished;
    state.wall_seconds = prior_wall + started.elapsed().as_secs_f64();
    state.peak_rss_mib = run::peak_rss_mib();
    run.write_state(&state)?;
    Ok(TrainSummary {
        run_dir: run.dir.clone(),
        iterations: total,
        wall_seconds: state.wall_seconds,
        peak_rss_mib: state.peak_rss_mib,
        last,
        rmse_k: rmse_now.map(|r| r.0),
        rmse_b: rmse_now.map(|r| r.1),
    })
}

/// The batch a prefetch thread assembled.
fn join_batch(handle: std::thread::JoinHandle<Result<HostBatch>>) -> Result<HostBatch> {
    handle
        .join()
        .map_err(|_| anyhow::anyhow!("the batch-loading thread panicked"))?
}

fn pool_of(
    clips: &ClipSet,
    pool: ClipPool,
    name: &str,
    progress: &Progress,
) -> Result<Vec<ClipRef>> {
    let chosen = match pool {
        ClipPool::LowVelocity => clips.low_velocity.clone(),
        ClipPool::Regular => clips.regular.clone(),
        ClipPool::All => clips
            .regular
            .iter()
            .chain(&clips.low_velocity)
            .copied()
            .collect(),
    };
    if !chosen.is_empty() {
        return Ok(chosen);
    }
    let all: Vec<ClipRef> = clips
        .regular
        .iter()
        .chain(&clips.low_velocity)
        .copied()
        .collect();
    if all.is_empty() {
        bail!("the {name} pass has no clips");
    }
    progress.note(&format!(
        "warning: the {name} pass asks for {pool:?} clips and the data has none; using every clip"
    ));
    Ok(all)
}

/// Loads the trained surrogate of a run directory from its `springs.npz`.
pub fn load_surrogate(
    run_dir: &Path,
    device: &Device,
) -> Result<(Config, Topology, SpringNet, f64)> {
    let run = RunDir::new(run_dir);
    let config = Config::load(&run.config(), &[])
        .with_context(|| format!("{} is not a run directory", run_dir.display()))?;
    let npz = crate::data::npz::Npz::read(&run.springs()).with_context(|| {
        format!(
            "{} has no trained surrogate (is the run finished?)",
            run_dir.display()
        )
    })?;
    let width = npz.scalar("width")?;
    let height = npz.scalar("height")?;
    let mass = npz.scalar("particle_mass")?;
    let topo = topology(&config, width, height);
    let s = topo.num_springs();
    let k: Vec<f64> = npz
        .f32("k", &[Some(s)])?
        .0
        .into_iter()
        .map(f64::from)
        .collect();
    let b: Vec<f64> = npz
        .f32("b", &[Some(s)])?
        .0
        .into_iter()
        .map(f64::from)
        .collect();
    let model = SpringNet::new(&topo, &k, &b, device).with_kernel(config.model.kernel);
    Ok((config, topo, model, mass))
}
