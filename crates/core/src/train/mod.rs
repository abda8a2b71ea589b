//! Training (paper §3.3): dual-pass curriculum with Adam, checkpoints and resume.
//!
//! The stiffness pass trains `k` with `b` frozen on low-velocity clips; the damping pass
//! trains `b` with `k` frozen on regular clips. `mode = "single"` trains both at once.

pub mod compliance;
pub mod guard;
pub mod init;
pub mod least_squares;
pub mod losses;
pub mod refine;
pub mod run;
pub mod scale;

pub use losses::{
    ForceOn, LossTerms, LossValues, LossWeights, loss, loss_with_budget, motion_loss,
};
pub use run::{MetricsRow, ModelMeta, RunDir, RunState, Status};

use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;

use anyhow::{Result, anyhow, bail};
use burn::module::{Module, Param, ParamId};
use burn::optim::module_optimizer::ModuleOptimizer;
use burn::optim::{AdamConfig, GradientsParams};
use burn::tensor::{Device, Gradients, Tensor};
use rand::{Rng, SeedableRng, rngs::StdRng};
use serde::{Deserialize, Serialize};

use crate::cloth::{Resampler, SpringLayout, Topology};
use crate::config::Config;
use crate::data::{ClipBatch, ClipRef, ClipSet, HostBatch, Rollout, Sampler, Split, SpringTruth};
use crate::eval::Takes;
use crate::model::neural_ode::OdeScales;
use crate::model::{Gnn, GnnConfig, ModelKind, NeuralOde, SpringNet, gnn};
use crate::progress::Progress;
use crate::sim::Physics;

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
    /// The learning rate at the pass's last iteration as a fraction of `lr`, reached by a
    /// geometric decay; 1 keeps it constant (the paper).
    pub lr_decay: f64,
    /// The fraction of the pass's iterations at the constant `lr` before the decay starts.
    pub lr_hold: f64,
    /// A learning rate of its own for the damping `b` of a spring surrogate in a pass that
    /// trains `k` and `b` together (`single`; ours, App. C.2's single pass has one): `b` then
    /// steps with `lr_b`, `k` with `lr`, under the same schedule. `None`: one rate for both.
    pub lr_b: Option<f64>,
    /// Loss weights.
    pub weights: LossWeights,
    /// Where the clips come from.
    pub clips: ClipPool,
}

impl PassConfig {
    /// The learning rate of the pass's `i`-th iteration (from 0): `lr` for the first
    /// `lr_hold` of the pass, then decayed geometrically to `lr · lr_decay` at the last one.
    pub(crate) fn lr_at(&self, i: usize) -> f64 {
        self.lr * self.schedule(i)
    }

    /// The learning rate of `b` at iteration `i` ([`Self::lr_b`] under the same schedule).
    pub(crate) fn lr_b_at(&self, i: usize) -> Option<f64> {
        self.lr_b.map(|lr_b| lr_b * self.schedule(i))
    }

    /// The schedule's factor at iteration `i`.
    fn schedule(&self, i: usize) -> f64 {
        decay_factor(i, self.iterations, self.lr_decay, self.lr_hold)
    }
}

/// A learning rate's factor at step `i` of `iterations`: 1 for the first `hold` of them, then
/// decayed geometrically to `decay` at the last.
pub(crate) fn decay_factor(i: usize, iterations: usize, decay: f64, hold: f64) -> f64 {
    let f = i as f64 / (iterations.max(2) - 1) as f64;
    let decayed = ((f - hold) / (1.0 - hold)).clamp(0.0, 1.0);
    decay.powf(decayed)
}

/// Checks the clips per step, the learning rate and its decay of the steps `train.{name}`;
/// errors name the key.
pub(crate) fn check_steps(name: &str, batch: usize, lr: f64, lr_decay: f64) -> Result<()> {
    if batch == 0 {
        bail!("`train.{name}.batch` must be at least 1");
    }
    if !(lr >= 0.0 && lr.is_finite()) {
        bail!("`train.{name}.lr` must be a non-negative number, is {lr}");
    }
    if !(lr_decay > 0.0 && lr_decay <= 1.0) {
        bail!("`train.{name}.lr_decay` must be in (0, 1], is {lr_decay}");
    }
    Ok(())
}

impl Default for PassConfig {
    fn default() -> Self {
        Self {
            iterations: 128,
            batch: 32,
            lr: 1.0,
            lr_decay: 1.0,
            lr_hold: 0.0,
            lr_b: None,
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
    /// `k` and `b` together (`train.single`, best with its own `lr_b`), then the damping pass
    /// (`train.damping`) for `b` alone (ours).
    SingleThenDamping,
}

/// How the searches over free rollouts of the training takes score a network
/// (`train.search_objective`; ours).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SearchObjective {
    /// The mean motion RMSE over the whole takes, as `eval`'s uniform yardstick is searched.
    #[default]
    WholeTake,
    /// The geometric mean of the mean up to `eval.short_seconds` and over the whole takes
    /// ([`crate::eval::Objective::BothHorizons`]).
    BothHorizons,
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
    /// Project `k` and `b` back into the explicit step's stable region (and to non-negative
    /// values) after every Adam step (springs); off: the paper's unconstrained steps, which may
    /// diverge.
    pub project_stable: bool,
    /// After training a spring network, search one factor for every `k` and one for every `b`
    /// over free rollouts of training data, keeping the network's shape (ours; off: the
    /// paper). For a force-level fit (`force_on = "target"`), whose values least squares
    /// shrinks; the substeps are raised as the scaled network needs.
    pub scale_search: bool,
    /// After training a spring network, search the best uniform network on free rollouts of
    /// training data first, then how much of the learned map to blend into it (ours; the
    /// uniform network is a candidate, so the kept one is never worse on those rollouts;
    /// replaces `scale_search`, whose candidates are the blend's `α = 1`).
    pub blend_search: bool,
    /// Where the blend search keeps the whole learned map (`α = 1`), also try it with its
    /// contrast within each spring family raised, `α = 1.5` then `2` while each moves closer to
    /// the training takes; kept where, polished beside the share kept without it, the held-out
    /// takes prefer it (ours, off by default). Needs `train.blend_search`.
    pub blend_contrast: bool,
    /// Rounds of averaging over the spring graph applied to each stiffness map before the
    /// blend search blends it ([`compliance::smoothed`]; ours): each round, each spring takes
    /// the mean of its own `k` and its neighbours' (the springs of its strain group that share
    /// a particle). 0 (the default): the maps as fitted.
    pub map_smoothing: usize,
    /// After the blend search's drag search, also search spring damping proportional to
    /// stiffness, `b_s = β k_s` ([`scale::ProportionalDamping`]; ours, off by
    /// default), kept only where the held-out training takes prefer it. Needs
    /// `train.blend_search`; runs where the drag was searched (in its place) or is stated by
    /// the files or the config (beside it).
    pub proportional_damping: bool,
    /// After those, also search an isotropic viscosity proportional to stiffness on the springs,
    /// `sim.viscosity` ([`scale::Proportional::Viscosity`]; ours, off by
    /// default), kept only where the held-out training takes prefer it. Needs
    /// `train.blend_search`; runs where the drag was searched (in its place) or is stated by
    /// the files or the config (beside it).
    pub viscosity_search: bool,
    /// Last, also search the shear springs' stiffness in compression, `sim.shear_compression`
    /// ([`scale::shear_compression`]; ours, off by default): from linear springs to springs that
    /// pull only, as Blender's cloth's shear springs do; and their share of the network's
    /// stiffness ([`scale::SHEAR_SHARES`]): the training takes searched pick each setting's
    /// closest `k` ([`scale::finalists`]), and the one closest to those and the held-out ones
    /// together is kept where the held-out takes agree. Needs `train.blend_search` and
    /// held-out training takes (`data.holdout`); runs on a network with shear springs (a grid's
    /// cell diagonals, a data mesh's quad cells' diagonals).
    pub compression_search: bool,
    /// Where training takes are held out (`data.holdout`) and the best uniform network moves
    /// closer to them than the learned one at both horizons, keep that uniform network as the
    /// run's model (ours; on by default): a learned map worse than one `k` and one `b` is not
    /// worth shipping. The learned springs stay in the run's `springs.learned.npz`.
    pub uniform_fallback: bool,
    /// How the searches (the uniform start's, the scale and blend searches, the polish, the
    /// drag and viscosity searches, and the uniform network `train` checks the kept one
    /// against) score a network by its free rollouts of the training takes: `"whole_take"`
    /// (the default: the mean motion RMSE over the whole takes) or `"both_horizons"` (the
    /// geometric mean of the mean up to `eval.short_seconds` and over the whole takes, so that
    /// the late frames, where a cloth parts from any model by chaos, do not alone decide).
    /// `eval`'s yardsticks are searched over the whole takes either way.
    pub search_objective: SearchObjective,
    /// Start a spring network from the strain-compliance map (ours; replaces the
    /// least-squares start).
    pub compliance: compliance::ComplianceConfig,
    /// Start a spring network from the per-spring least-squares fit of the data's forces
    /// (ours; off: the paper's uniform start).
    pub least_squares: least_squares::LeastSquaresConfig,
    /// After the searches, refine a spring network per spring by Adam on `log k` of a
    /// multiple-shooting position loss (ours; PhysTwin's second stage; off by default).
    pub refine: refine::RefineConfig,
    /// The stiffness pass.
    pub stiffness: PassConfig,
    /// The damping pass.
    pub damping: PassConfig,
    /// The single pass (also the Neural ODE's only pass).
    pub single: PassConfig,
    /// The GNN's one-step training.
    pub gnn: PassConfig,
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
            project_stable: true,
            scale_search: false,
            blend_search: false,
            blend_contrast: false,
            map_smoothing: 0,
            proportional_damping: false,
            viscosity_search: false,
            compression_search: false,
            uniform_fallback: true,
            search_objective: SearchObjective::WholeTake,
            compliance: compliance::ComplianceConfig::default(),
            least_squares: least_squares::LeastSquaresConfig::default(),
            refine: refine::RefineConfig::default(),
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
            gnn: PassConfig {
                iterations: 2000,
                batch: 8,
                lr: 1e-4,
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
            ("gnn", &self.gnn),
        ] {
            check_steps(name, p.batch, p.lr, p.lr_decay)?;
            if !(0.0..1.0).contains(&p.lr_hold) {
                bail!("`train.{name}.lr_hold` must be in [0, 1), is {}", p.lr_hold);
            }
            if let Some(lr_b) = p.lr_b {
                if !(lr_b >= 0.0 && lr_b.is_finite()) {
                    bail!("`train.{name}.lr_b` must be a non-negative number, is {lr_b}");
                }
                if name != "single" {
                    bail!(
                        "`train.{name}.lr_b` is for the single pass, which trains k and b \
                         together; the {name} pass trains one of them at `train.{name}.lr`"
                    );
                }
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
        if self.compliance.enabled && self.least_squares.enabled && !self.blend_search {
            bail!(
                "`train.compliance.enabled` and `train.least_squares.enabled` both choose the \
                 start of the spring network; keep one, or turn on `train.blend_search`, which \
                 blends each map into the uniform network and keeps the better"
            );
        }
        if self.blend_contrast && !self.blend_search {
            bail!(
                "`train.blend_contrast` raises the contrast of the blend search's map; turn on \
                 `train.blend_search`, or set `train.blend_contrast = false`"
            );
        }
        if self.map_smoothing > 0 && !self.blend_search {
            bail!(
                "`train.map_smoothing` smooths the maps that the blend search blends; turn on \
                 `train.blend_search`, or set `train.map_smoothing = 0`"
            );
        }
        if self.proportional_damping && !self.blend_search {
            bail!(
                "`train.proportional_damping` is searched after the blend search's drag search; \
                 turn on `train.blend_search`, or set `train.proportional_damping = false`"
            );
        }
        if self.compression_search && !self.blend_search {
            bail!(
                "`train.compression_search` is searched after the blend search; turn on \
                 `train.blend_search`, or set `train.compression_search = false`"
            );
        }
        if self.viscosity_search && !self.blend_search {
            bail!(
                "`train.viscosity_search` is searched after the blend search's drag search; turn \
                 on `train.blend_search`, or set `train.viscosity_search = false`"
            );
        }
        if self.scale_search && self.blend_search {
            bail!(
                "`train.scale_search` and `train.blend_search` are both on: the blend search's \
                 candidates include the scale search's (α = 1); keep one"
            );
        }
        self.refine.validate()?;
        self.least_squares.validate()
    }

    /// The passes to run for a model family. Spring networks follow `mode`; the Neural ODE
    /// trains in one pass (`train.single`), the GNN in its own (`train.gnn`).
    pub fn passes(&self, kind: ModelKind) -> Vec<Pass<'_>> {
        let pass = |name, config, train_k, train_b| Pass {
            name,
            config,
            train_k,
            train_b,
        };
        match (kind, self.mode) {
            (ModelKind::Springs, Mode::Dual) => vec![
                pass("stiffness", &self.stiffness, true, false),
                pass("damping", &self.damping, false, true),
            ],
            (ModelKind::Springs, Mode::Single) | (ModelKind::NeuralOde, _) => {
                vec![pass("single", &self.single, true, true)]
            }
            (ModelKind::Springs, Mode::SingleThenDamping) => vec![
                pass("single", &self.single, true, true),
                pass("damping", &self.damping, false, true),
            ],
            (ModelKind::Gnn, _) => vec![pass("gnn", &self.gnn, true, true)],
        }
    }
}

/// One training pass of a model family (see [`TrainConfig::passes`]).
#[derive(Debug, Clone, Copy)]
pub struct Pass<'a> {
    /// Its name in `metrics.csv` (`stiffness`, `damping`, `single`, `gnn`).
    pub name: &'static str,
    /// Its iterations, learning rate and loss weights.
    pub config: &'a PassConfig,
    /// Whether the springs' `k` are trained in it (always for the baselines' parameters).
    pub train_k: bool,
    /// Whether the springs' `b` are trained in it.
    pub train_b: bool,
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

/// The surrogate topology of a config for the data that `first` (a rollout of the set)
/// belongs to: the config's grid over its rest rectangle, or its own mesh (`cloth.layout =
/// "data"`: the file's `triangles`, else the Delaunay triangulation of its `rest_uv`).
pub fn topology(config: &Config, first: &Rollout) -> Result<Topology> {
    let cloth = &config.cloth;
    match cloth.layout {
        SpringLayout::Grid => Ok(Topology::grid(cloth, first.width, first.height)),
        SpringLayout::Data => {
            let (uv, w, h, hinges) = (
                &first.rest_uv,
                first.width,
                first.height,
                cloth.bending_stride > 0,
            );
            match &first.mesh {
                Some(m) => Topology::mesh(uv, &m.triangles, w, h, hinges),
                None => Topology::of_points(uv, w, h, hinges),
            }
            .map(|topo| topo.with_masses(cloth.masses))
            .map_err(|e| anyhow!("{}: cloth.layout = \"data\": {e}", first.path.display()))
        }
    }
}

/// The training device of a config.
pub(crate) fn training_device(config: &Config) -> Result<Device> {
    let device = config.backend.device()?.autodiff();
    // Fresh parameters (the baselines' layers) are drawn from the device's generator.
    device.seed(config.train.seed);
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
        |first| topology(config, first),
        config.data.cache_bytes(config.backend),
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

/// Runs the training job of `config`: the model family of `config.model.kind` on the clips
/// of `config.data`.
pub fn train(config: &Config, options: &TrainOptions, progress: &Progress) -> Result<TrainSummary> {
    let run = RunDir::new(config.run_dir(options.out.as_deref()));
    let _lock = run.lock()?;
    let previous = previous_state(&run, options)?;
    let (clips, truth) = open_training_clips(config, progress)?;
    check_frame_forces(config, &clips)?;
    let clips = Arc::new(clips);
    let requested = config;
    let split = config.data.split()?;
    let search_device = config.backend.device()?;
    let (resolved, resolution) = init::resolve(
        config,
        &clips,
        Some(&init::SearchContext {
            files: &split.train,
            device: &search_device,
            objective: config.search_objective(),
        }),
    )?;
    let config = &resolved;
    for line in resolution.lines() {
        progress.note(&format!("from the data: {line}"));
    }
    if !options.resume {
        run.create_fresh()?;
    }
    crate::io::write_text(&run.requested_config(), &requested.to_toml())?;
    crate::io::write_text(&run.config(), &config.to_toml())?;
    crate::io::write_json(&run.defaults(), &resolution)?;
    let device = training_device(config)?;
    note_fixed_kernels(config, progress);
    let physics = Physics::new(&config.sim, clips.info.frame_dt, clips.particle_mass());
    let topo = clips.topology.clone();
    let job = Job {
        config,
        physics,
        topology: &topo,
        truth: truth.as_ref(),
        device: &device,
        curvature_lr_factor: config.model.curvature_init_for(resolution.k_init) / resolution.k_init,
    };
    let meta = model_meta(&run, previous.is_some(), config, &clips, &physics, progress)?;
    crate::io::write_json(&run.meta(), &meta)?;
    let fit = Fit {
        run: &run,
        job: &job,
        clips: &clips,
        previous: previous.as_ref(),
        progress,
    };
    note_spring_only(config, progress);
    let summary = match config.model.kind {
        ModelKind::Springs => {
            let start = fit.initial_springs(&resolution)?;
            let model = start.net.with_kernel(config.model.kernel);
            let (summary, model) = fit.run(model)?;
            let after = AfterFit {
                fit: &fit,
                resolution: &resolution,
                split: &split,
                device: &search_device,
                tracks: Default::default(),
                fit_stencil: start.fit_stencil,
            };
            after.finish(model)?;
            summary
        }
        ModelKind::NeuralOde => fit.run(meta.neural_ode(config, &device))?.0,
        ModelKind::Gnn => fit.run(meta.gnn(config, &device)?)?.0,
    };
    let mut state = run.state()?.expect("written by the fit");
    state.status = Status::Finished;
    run.write_state(&state)?;
    Ok(summary)
}

/// Says which of the config's spring-network stages a baseline family trains without.
fn note_spring_only(config: &Config, progress: &Progress) {
    if config.model.kind == ModelKind::Springs {
        return;
    }
    let kind = config.model.kind.name();
    if config.train.least_squares.enabled {
        progress.note(&format!(
            "`train.least_squares` starts a spring network; `model.kind = \"{kind}\"` starts as \
             it would without it"
        ));
    }
    if config.train.refine.iterations > 0 {
        progress.note(&format!(
            "`train.refine` refines a spring network; `model.kind = \"{kind}\"` trains without it"
        ));
    }
}

/// Refuses frame-difference forces on clips too short to difference.
fn check_frame_forces(config: &Config, clips: &ClipSet) -> Result<()> {
    if config.train.force_on == ForceOn::Frames && clips.steps < 3 {
        bail!(
            "`train.force_on = \"frames\"` differences positions over clips of at least 3 \
             steps; `data.clips.steps` is {}",
            clips.steps
        );
    }
    Ok(())
}

/// The state of the run `--resume` goes on from (`None` without it), after checking that there
/// is one and that it is unfinished; without `--resume`, checks that the folder may be written.
fn previous_state(run: &RunDir, options: &TrainOptions) -> Result<Option<RunState>> {
    if !options.resume {
        run.check_fresh(options.force)?;
        return Ok(None);
    }
    match run.state()? {
        None => bail!("--resume: {} holds no run to resume", run.dir.display()),
        Some(s) if s.status == Status::Finished => {
            bail!(
                "--resume: the run in {} is already finished (pass --force to train it again)",
                run.dir.display()
            )
        }
        state => Ok(state),
    }
}

/// Says, when a Neural ODE or GNN trains on wgpu without `autotune`, what that feature buys.
fn note_fixed_kernels(config: &Config, progress: &Progress) {
    if config.backend != crate::backend::Backend::Wgpu
        || config.model.kind == ModelKind::Springs
        || cfg!(feature = "autotune")
    {
        return;
    }
    let (model, speedup) = match config.model.kind {
        ModelKind::Gnn => ("GNN", "3.3x"),
        _ => ("Neural ODE", "1.7x"),
    };
    progress.note(&format!(
        "note: the {model} trains on wgpu with Burn's fixed matmul and reduce kernels; on a GPU a \
         build with `--features autotune` trains it {speedup} faster (H100; the book, \"On a \
         GPU\")"
    ));
}

/// The model's constants: those of the run being resumed (which must be of the configured
/// family), else new ones.
fn model_meta(
    run: &RunDir,
    resuming: bool,
    config: &Config,
    clips: &ClipSet,
    physics: &Physics,
    progress: &Progress,
) -> Result<ModelMeta> {
    match (resuming, ModelMeta::read(&run.meta())) {
        (true, Ok(meta)) => {
            if meta.kind != config.model.kind {
                bail!(
                    "--resume: {} holds a `{}` run, the config asks for `{}`",
                    run.dir.display(),
                    meta.kind.name(),
                    config.model.kind.name()
                );
            }
            Ok(meta)
        }
        _ => ModelMeta::new(config, clips, physics, progress),
    }
}

/// What follows a spring network's fit: the blend and scale searches, the springs file and the
/// check on the held-out training rollouts.
struct AfterFit<'a> {
    fit: &'a Fit<'a>,
    resolution: &'a init::Resolution,
    split: &'a Split,
    /// The device of the searches and the check (the config's backend).
    device: &'a Device,
    /// The training takes the searches and the check have read.
    tracks: crate::eval::TrackCache,
    /// The stencil of the least-squares fit training started from (`None`: it started from
    /// none).
    fit_stencil: Option<usize>,
}

impl AfterFit<'_> {
    fn finish(&self, mut model: SpringNet) -> Result<()> {
        let job = self.fit.job;
        let config = job.config;
        let mut final_physics = job.physics;
        // The learned map the run sets aside where it keeps a uniform network instead.
        let mut set_aside = None;
        if config.train.blend_search {
            (model, final_physics, set_aside) = self.blend(model)?;
        }
        if config.train.scale_search {
            (model, final_physics) = self.scale(&model)?;
        }
        if config.train.refine.iterations > 0 {
            (model, final_physics) = self.refine(&model, &final_physics)?;
        }
        if config.train.blend_search {
            final_physics = self.with_margin(&model, final_physics)?;
        }
        run::write_springs(
            &self.fit.run.springs(),
            job.topology,
            &model,
            job.physics.mass,
        )?;
        if !self.split.validation.is_empty() && self.validate(&model, &final_physics)? {
            // A map the blend kept stays the one set aside; else the network just turned down.
            set_aside = set_aside.or(Some(model));
        }
        let learned = self.fit.run.learned_springs();
        match set_aside {
            Some(map) => run::write_springs(&learned, job.topology, &map, job.physics.mass)?,
            // A resumed run's, from a finish that set a map aside.
            None if learned.exists() => std::fs::remove_file(&learned)?,
            None => {}
        }
        Ok(())
    }

    /// `physics` with the substeps `model` needs to run at a stability number of at most
    /// [`KEPT_STABILITY`] (the config's substeps written to the run where they change): the
    /// searches after the blend (the polish, the drag, the viscosity) run their candidates at
    /// fixed substeps and keep any that the flat sheet's estimate calls stable, up to its limit
    /// of 4, while a folded sheet can align a particle's springs and put their stiffness into
    /// one direction — up to twice the flat sheet's largest eigenvalue. On Newton's stiff cloth
    /// at 60 fps the kept network ran at 3.91 and diverged 2.7 s into one of 12 test takes; at
    /// 120 substeps (2.06) it does not.
    fn with_margin(&self, model: &SpringNet, physics: Physics) -> Result<Physics> {
        let (job, progress) = (self.fit.job, self.fit.progress);
        let stability = physics.stability_of(job.topology, model);
        let number = stability.number();
        if number <= KEPT_STABILITY {
            return Ok(physics);
        }
        let Some(substeps) = stability.fewest_substeps(
            physics.frame_dt,
            physics.substeps..=physics.substeps * 4,
            KEPT_STABILITY,
        ) else {
            return Ok(physics);
        };
        let raised = Physics {
            substeps,
            ..physics
        };
        progress.note(&format!(
            "stability margin: the kept network runs at dt²ω² + 2·dt·γ = {number:.2} at {} \
             substep(s) per frame; raised to {substeps} ({:.2}), so that a folded sheet stays \
             within the explicit step's limit of 4",
            physics.substeps,
            stability.number_at(raised.sim_dt())
        ));
        write_physics(self.fit.run, job.config, &raised)?;
        Ok(raised)
    }

    /// The fitted training rollouts, for the searches.
    fn train_takes(&self) -> Takes<'_> {
        Takes {
            topology: self.fit.job.topology,
            files: &self.split.train,
            batch: self.fit.job.config.eval.batch,
            device: self.device,
            progress: self.fit.progress,
            cache: Some(&self.tracks),
            objective: self.fit.job.config.search_objective(),
        }
    }

    /// The blend search on the maps to blend: the trained network, or with both starts on the
    /// two mixed ([`compliance::mixed`], each shape weighed by `train.compliance.weights`) —
    /// and the trained network and the compliance map too with `train.compliance.keep =
    /// "closest"`, or where the mixed map's blend stays uniform — each smoothed by
    /// `train.map_smoothing` first; each map's blend is polished at the substeps it runs at
    /// ([`scale::polish`]) and the map is chosen by [`choose_map`] among the polished blends.
    ///
    /// Where the kept blend is a uniform network (no share of the map, or a polish that found
    /// the uniform network closer), the chosen map itself, as the fit and the compliance map read
    /// it (smoothed, before the blend sizes it), is returned as the map set aside
    /// (`springs.learned.npz`).
    fn blend(&self, model: SpringNet) -> Result<(SpringNet, Physics, Option<SpringNet>)> {
        let (job, progress) = (self.fit.job, self.fit.progress);
        let config = job.config;
        let passes = config.train.map_smoothing;
        // `net` with the stiffness `k`, its damping, kernel and curvature kept.
        let with_k = |net: &SpringNet, k: &[f64]| {
            SpringNet::new(job.topology, k, &net.b_values(), self.device)
                .with_kernel(net.graph.kernel)
                .with_curvature(&net.curvature_values())
        };
        let smooth_k = |k: &[f64]| match passes {
            0 => k.to_vec(),
            _ => compliance::smoothed(job.topology, k, passes),
        };
        let smooth = |net: SpringNet| match passes {
            0 => net,
            _ => with_k(&net, &smooth_k(&net.k_values())),
        };
        if passes > 0 {
            progress.note(&format!(
                "blend search: each map's k smoothed by {passes} round(s) of averaging with its \
                 neighbours' (`train.map_smoothing`)"
            ));
        }
        let mut maps = vec![("trained", smooth(model))];
        // With `keep = "mixed"`, the maps searched only where the mixed map's blend stays
        // uniform.
        let mut fallback = Vec::new();
        let mut weights = None;
        if config.train.compliance.enabled && config.train.least_squares.enabled {
            let compliance = smooth(self.fit.compliance_springs(self.resolution)?);
            let trained = &maps[0].1;
            let w = self.map_weights(&smooth_k)?;
            let k = compliance::mixed(
                job.topology,
                &trained.k_values(),
                &compliance.k_values(),
                &w,
            );
            let mixed = with_k(trained, &k);
            match config.train.compliance.keep {
                compliance::MapKeep::Closest => {
                    maps.push(("compliance", compliance));
                    maps.push((MIXED_MAP, mixed));
                }
                compliance::MapKeep::Mixed => {
                    fallback = std::mem::replace(&mut maps, vec![(MIXED_MAP, mixed)]);
                    fallback.push(("compliance", compliance));
                }
            }
            weights = Some(w);
        }
        let several = maps.len() > 1 || !fallback.is_empty();
        let mut found = Vec::new();
        for (name, map) in &maps {
            found.push(self.blend_map(name, map, several)?);
        }
        if found.len() == 1 && !fallback.is_empty() && found[0].2.kept_uniform() {
            progress.note(
                "blend search: no share or size of the mixed map moves closer to the training \
                 rollouts than the best uniform network; the fit's and the compliance map are \
                 searched too (`train.compliance.keep`)",
            );
            for (name, map) in &fallback {
                found.push(self.blend_map(name, map, several)?);
            }
        }
        let scores = self.map_scores(&found)?;
        let choice = choose_map(&scores);
        if scores.len() > 1 {
            for (s, (short, long)) in scores.iter().filter_map(|s| Some((s, s.held_out?))) {
                progress.note(&format!(
                    "blend search of the {} map: on the {} held-out rollouts {short:.4e} / \
                     {long:.4e} m (short / long)",
                    s.map,
                    self.split.validation.len()
                ));
            }
            progress.note(&format!("blend search: {}", choice.why));
        }
        let (blended, blended_physics, mut record) = found.swap_remove(choice.kept);
        let set_aside = if record.kept_uniform() {
            maps.into_iter()
                .chain(fallback)
                .find(|(name, _)| *name == record.map)
                .map(|(_, map)| map)
        } else {
            None
        };
        record.maps = scores;
        record.weights = weights;
        progress.note(&format!(
            "blend search: the best uniform network on {} training rollouts is k {:.4} N/m, b \
             {:.4e} N·s/m ({:.4e} m); kept {:.0} % of the {} map, k × {:.3} (bending springs' \
             × {:.3} more), b × {:.3} at {} substep(s) per frame: mean motion RMSE {} (as \
             trained) -> {:.4e} m",
            record.rollouts,
            record.uniform.0,
            record.uniform.1,
            record.uniform.2,
            100.0 * record.alpha,
            record.map,
            record.k_factor,
            record.bending_factor,
            record.b_factor,
            record.substeps,
            before_text(record.before),
            record.after
        ));
        if record.alpha == 0.0 {
            progress.note(
                "WARNING: blend search: no share of the learned map moves closer to the training \
                 rollouts than the best uniform network; the run keeps that uniform network (the \
                 map is set aside in springs.learned.npz)",
            );
        }
        let polish = record.polish.take().expect("polished above");
        progress.note(&format!(
            "polish at {} substep(s) per frame: the best uniform network there is k {:.4} N/m, b \
             {:.4e} N·s/m ({:.4e} m); the searched network {:.4e} m -> {}",
            polish.substeps,
            polish.uniform.0,
            polish.uniform.1,
            polish.uniform.2,
            polish.before,
            if polish.kept_uniform {
                "no size or damping of it moves as close: the run keeps that uniform network"
                    .to_string()
            } else {
                format!(
                    "k × {:.3}, b × {:.3}: {:.4e} m",
                    polish.k_factor, polish.b_factor, polish.after
                )
            }
        ));
        if polish.kept_uniform && record.alpha > 0.0 {
            progress.note(
                "WARNING: polish: at the substeps the learned map needs, the best uniform network \
                 moves closer to the training rollouts than any size of the map; the run keeps \
                 that uniform network (the map is set aside in springs.learned.npz)",
            );
        }
        let (blended, blended_physics, drag) = self.drag(blended, blended_physics, &polish)?;
        // The damping searches below run where the drag was searched (in its place), and where
        // the files or the config state it (beside it).
        let stated_drag = !self.resolution.drag_fitted();
        let searched = match &drag {
            Some(d) => Some(d.held_out_kept()),
            None if stated_drag && !polish.kept_uniform && !self.split.validation.is_empty() => {
                Some(None)
            }
            None => None,
        };
        record.polish = Some(polish);
        record.drag = drag;
        let (mut blended, mut blended_physics) = (blended, blended_physics);
        // The held-out figures of the network kept so far, where a search measured them.
        let mut known = searched.flatten();
        if searched.is_some() {
            let forms = [
                (
                    scale::Proportional::Springs,
                    config.train.proportional_damping,
                ),
                (
                    scale::Proportional::Viscosity,
                    config.train.viscosity_search,
                ),
            ];
            for (form, on) in forms {
                if !on {
                    continue;
                }
                let (net, physics, found) =
                    self.proportional_damping(blended, blended_physics, known, form, stated_drag)?;
                (blended, blended_physics) = (net, physics);
                // The held-out figures of the network kept now, for the next search.
                known = found.as_ref().and_then(|r| {
                    r.held_out
                        .map(|(before, after)| if r.kept { after } else { before })
                });
                match form {
                    scale::Proportional::Springs => record.damping = found,
                    scale::Proportional::Viscosity => record.viscosity = found,
                }
            }
        }
        if config.train.compression_search && !self.split.validation.is_empty() {
            let found;
            (blended, blended_physics, found) = self.shear_compression(blended, blended_physics)?;
            record.shear_compression = found;
        }
        let run = self.fit.run;
        keep_searched(
            run,
            config,
            &blended,
            &blended_physics,
            "blend.json",
            &record,
        )?;
        Ok((blended, blended_physics, set_aside))
    }

    /// The blend search of the map `name` ([`scale::blend_search`]) and its blend polished at
    /// the substeps it runs at ([`scale::polish`]), so that maps are compared as the run would
    /// keep them; says so in the log where `several` maps may be searched.
    fn blend_map(
        &self,
        name: &str,
        map: &SpringNet,
        several: bool,
    ) -> Result<(SpringNet, Physics, scale::BlendSearch)> {
        let job = self.fit.job;
        let found = scale::blend_search(
            map,
            (self.resolution.k_init, self.resolution.b_init),
            &job.physics,
            &self.train_takes(),
            job.config.train.blend_contrast,
        )?;
        let (net, p, mut record) = self.contrast_check(name, found)?;
        record.map = name.to_string();
        let polish = record.polish.as_ref().expect("polished");
        if several {
            self.fit.progress.note(&format!(
                "blend search of the {name} map: {:.0} % kept, mean motion RMSE {:.4e} m; \
                 polished at {} substep(s) per frame: {:.4e} m{}",
                100.0 * record.alpha,
                record.after,
                polish.substeps,
                polish.after,
                if polish.kept_uniform {
                    " (the uniform network kept)"
                } else {
                    ""
                }
            ));
        }
        Ok((net, p, record))
    }

    /// The blend search's closest network polished, or where its share lies past the whole map
    /// (`train.blend_contrast`), that share checked against the network kept without it, both
    /// polished: kept where the held-out takes prefer it ([`scale::held_out_agrees`]), or
    /// without held-out takes where it is still the closer to the training takes; the verdict
    /// in the record ([`scale::ContrastCheck`]) and the log.
    fn contrast_check(
        &self,
        name: &str,
        found: scale::BlendFound,
    ) -> Result<(SpringNet, Physics, scale::BlendSearch)> {
        let closest = self.polished(found.closest)?;
        let Some(plain) = found.plain else {
            return Ok(closest);
        };
        let (plain_net, plain_physics, plain_record) = self.polished(plain)?;
        let (closest_net, closest_physics, closest_record) = closest;
        let (after, plain_after) = (
            closest_record.polished_after(),
            plain_record.polished_after(),
        );
        let (net, physics, kept, verdict) = if self.split.validation.is_empty() {
            let kept = after < plain_after;
            let (net, physics) = if kept {
                (closest_net, closest_physics)
            } else {
                (plain_net, plain_physics)
            };
            (net, physics, kept, None)
        } else {
            let (net, physics, verdict) = self.judge(
                (plain_net, plain_physics),
                (closest_net, closest_physics),
                None,
            )?;
            (net, physics, verdict.kept, Some(verdict))
        };
        let check = scale::ContrastCheck {
            alpha: closest_record.alpha,
            after,
            plain_alpha: plain_record.alpha,
            plain_after,
            held_out: verdict.as_ref().map(|v| (v.before, v.after)),
            kept,
        };
        let held = verdict.map_or(String::new(), |v| {
            format!("; {}", v.figures(self.split.validation.len()))
        });
        self.fit.progress.note(&format!(
            "blend search of the {name} map: {:.0} % of it (its contrast raised), polished, moves \
             {:.4e} m from the training rollouts against {:.4e} m at {:.0} %{held} -> the run \
             keeps {:.0} %",
            100.0 * check.alpha,
            check.after,
            check.plain_after,
            100.0 * check.plain_alpha,
            100.0 * if kept { check.alpha } else { check.plain_alpha }
        ));
        let mut record = if kept { closest_record } else { plain_record };
        record.contrast = Some(check);
        Ok((net, physics, record))
    }

    /// A blend polished at the substeps it runs at ([`scale::polish`]), the polish in its record.
    fn polished(&self, blend: scale::Blended) -> Result<(SpringNet, Physics, scale::BlendSearch)> {
        let job = self.fit.job;
        let (net, polish) = scale::polish(
            &blend.net,
            &blend.physics,
            job.config.model.uniform_start(),
            &self.train_takes(),
        )?;
        let mut record = blend.record;
        record.polish = Some(polish);
        Ok((net, blend.physics, record))
    }

    /// The drag searched after the polish ([`scale::DragSearch`]) where the run fitted it, the
    /// polish kept the map and training takes were held out; returns the network and physics kept
    /// and the record.
    fn drag(
        &self,
        net: SpringNet,
        physics: Physics,
        polish: &scale::Polish,
    ) -> Result<(SpringNet, Physics, Option<scale::DragSearch>)> {
        if !self.resolution.drag_fitted() || polish.kept_uniform || self.split.validation.is_empty()
        {
            return Ok((net, physics, None));
        }
        let (config, progress) = (self.fit.job.config, self.fit.progress);
        let row = scale::drag_row(&net, &physics, Some(polish.after), &self.train_takes());
        let best = row
            .iter()
            .copied()
            .min_by(|a, b| a.1.total_cmp(&b.1))
            .map_or(physics.rayleigh, |r| r.0);
        let mut record = scale::DragSearch {
            fitted: physics.rayleigh,
            row,
            best,
            polish: None,
            held_out: None,
            kept: physics.rayleigh,
        };
        if best == physics.rayleigh {
            progress.note(&format!(
                "drag search: no drag of the row moves the map closer to the training rollouts \
                 than the fitted sim.rayleigh {:.4e} N·s/m",
                physics.rayleigh
            ));
            return Ok((net, physics, Some(record)));
        }
        let at_best = Physics {
            rayleigh: best,
            ..physics
        };
        let (other, again) = scale::polish(
            &net,
            &at_best,
            config.model.uniform_start(),
            &self.train_takes(),
        )?;
        let (at_fitted, at_other) = (
            self.held_out_rmse(&net, &physics)?,
            self.held_out_rmse(&other, &at_best)?,
        );
        let closer = !again.kept_uniform && at_other.0 < at_fitted.0 && at_other.1 < at_fitted.1;
        progress.note(&format!(
            "drag search: the map moves closest to the training rollouts at sim.rayleigh {:.4e} \
             N·s/m (fitted {:.4e}); polished there, on the {} held-out rollouts it moves {:.4e} / \
             {:.4e} m (short / long) against {:.4e} / {:.4e} m at the fitted drag -> {}",
            best,
            physics.rayleigh,
            self.split.validation.len(),
            at_other.0,
            at_other.1,
            at_fitted.0,
            at_fitted.1,
            if closer {
                "the run keeps that drag"
            } else {
                "the run keeps the fitted drag"
            }
        ));
        record.polish = Some(again);
        record.held_out = Some((at_fitted, at_other));
        Ok(if closer {
            record.kept = best;
            (other, at_best, Some(record))
        } else {
            (net, physics, Some(record))
        })
    }

    /// Damping proportional to stiffness in `form` ([`scale::ProportionalDamping`]), without
    /// drag where the drag was searched, beside it where it is stated (`keep_drag`); kept only
    /// where the held-out training takes agree ([`scale::held_out_agrees`]). `known` is `net`'s
    /// `(short, long)` held-out RMSE where an earlier search measured it. Returns the network and
    /// physics kept and the record.
    fn proportional_damping(
        &self,
        net: SpringNet,
        physics: Physics,
        known: Option<(f64, f64)>,
        form: scale::Proportional,
        keep_drag: bool,
    ) -> Result<(SpringNet, Physics, Option<scale::ProportionalDamping>)> {
        let progress = self.fit.progress;
        let Some((other, at, mut record)) =
            scale::proportional_damping(&net, &physics, &self.train_takes(), form, keep_drag)
        else {
            progress.note(&format!(
                "{}: no {} is stable at the run's substeps",
                form.name(),
                form.form()
            ));
            return Ok((net, physics, None));
        };
        let drag = physics.rayleigh;
        let (net, physics, verdict) = self.judge((net, physics), (other, at), known)?;
        let (before, after) = (verdict.before, verdict.after);
        (record.kept, record.held_out) = (verdict.kept, Some((before, after)));
        progress.note(&format!(
            "{}: {} the map moves closest to the training rollouts at {} = {:.3e} s · k, k × \
             {:.3} ({:.4e} m); {} as kept so far -> {}",
            form.name(),
            if keep_drag {
                format!("with the stated drag {drag:.4e} N·s/m")
            } else {
                "without drag".to_string()
            },
            match form {
                scale::Proportional::Springs => "b",
                scale::Proportional::Viscosity => "the viscosity",
            },
            record.beta,
            record.k_factor,
            record.after,
            verdict.figures(self.split.validation.len()),
            verdict.outcome()
        ));
        Ok((net, physics, Some(record)))
    }

    /// `current` or a search's `candidate`, whichever the held-out training takes prefer
    /// ([`scale::held_out_agrees`]: the candidate only where they agree), with the verdict:
    /// both networks' `(short, long)` held-out motion RMSE, `current`'s taken from `known` where
    /// an earlier search measured it.
    fn judge(
        &self,
        current: (SpringNet, Physics),
        candidate: (SpringNet, Physics),
        known: Option<(f64, f64)>,
    ) -> Result<(SpringNet, Physics, HeldOutVerdict)> {
        let before = match known {
            Some(r) => r,
            None => self.held_out_rmse(&current.0, &current.1)?,
        };
        let after = self.held_out_rmse(&candidate.0, &candidate.1)?;
        let kept = scale::held_out_agrees(before, after);
        let (net, physics) = if kept { candidate } else { current };
        Ok((
            net,
            physics,
            HeldOutVerdict {
                before,
                after,
                kept,
            },
        ))
    }

    /// The shear springs' stiffness in compression and their share of the network's stiffness
    /// ([`scale::shear_compression`]): the search's training takes pick each setting's closest
    /// `k` ([`scale::finalists`]); of those, the one closest to the training takes searched and
    /// the held-out ones together ([`scale::pooled`]) is kept where the held-out takes agree
    /// ([`scale::held_out_agrees`]). Ties on the training takes searched are broken by the
    /// held-out ones, and a clear margin on ten takes is not overturned by two: on tpcloth stiff
    /// at 30 fps ¼ at `k` × √2 and ½ at `k` tie on the training takes (0.2372 against 0.2375 m)
    /// where the held-out ones do not (0.2517 against 0.2309 m over the take). Returns the
    /// network and physics kept and the record.
    fn shear_compression(
        &self,
        net: SpringNet,
        physics: Physics,
    ) -> Result<(SpringNet, Physics, Option<scale::CompressionSearch>)> {
        let progress = self.fit.progress;
        let takes = self.train_takes();
        let Some((mut record, searched)) = scale::shear_compression(&net, &physics, &takes) else {
            return Ok((net, physics, None));
        };
        let before_kappa = physics.shear_compression;
        let unchanged =
            |s: &scale::ShearSetting| s.same_shear(&scale::ShearSetting::unchanged(before_kappa));
        let held = self.split.validation.len();
        for candidate in scale::finalists(&record.candidates) {
            let setting = candidate.setting;
            let (n, p) = scale::compression_candidate(&net, &physics, &takes, setting);
            let figures = self.held_out_figures(&n, &p)?;
            record.finalists.push(scale::Finalist {
                setting,
                train: candidate.rmse,
                held_out: figures.horizons,
                pooled: scale::pooled((candidate.rmse, searched), (figures.score, held)),
            });
        }
        let rows = record
            .finalists
            .iter()
            .map(|f| {
                format!(
                    "{} in compression, shear springs' k × {:.3}, at k × {:.3}: {:.4e} m (held \
                     out {:.4e} / {:.4e} m; together {:.4e} m)",
                    f.setting.shear_compression,
                    f.setting.shear_share,
                    f.setting.k_factor,
                    f.train,
                    f.held_out.0,
                    f.held_out.1,
                    f.pooled
                )
            })
            .collect::<Vec<_>>()
            .join("; ");
        let found = format!(
            "shear springs' search: each setting's closest k on the {searched} training rollouts \
             searched (held out: short / long; together with the {held} held out): {rows}"
        );
        let current = record
            .finalists
            .iter()
            .find(|f| unchanged(&f.setting))
            .cloned();
        let Some(current) = current else {
            progress.note(&format!(
                "{found}; the shear springs as they are (sim.shear_compression {before_kappa}) \
                 are not stable at the run's substeps there, so no other setting is weighed \
                 against them; kept as they are"
            ));
            return Ok((net, physics, Some(record)));
        };
        let best = record
            .finalists
            .iter()
            .min_by(|a, b| a.pooled.total_cmp(&b.pooled))
            .cloned()
            .expect("the finalists hold the shear springs as they are");
        record.setting = best.setting;
        record.after = best.train;
        if unchanged(&best.setting) {
            progress.note(&format!(
                "{found}; the shear springs as they are move closest (sim.shear_compression \
                 {before_kappa}); kept"
            ));
            return Ok((net, physics, Some(record)));
        }
        record.held_out = Some((current.held_out, best.held_out));
        record.kept = scale::held_out_agrees(current.held_out, best.held_out);
        let verdict = HeldOutVerdict {
            before: current.held_out,
            after: best.held_out,
            kept: record.kept,
        };
        progress.note(&format!(
            "{found}; closest together with the shear springs pushing at {} of their k when \
             compressed and their k × {:.3}, the network's k × {:.3}; {} at sim.shear_compression \
             {} -> {}",
            record.setting.shear_compression,
            record.setting.shear_share,
            record.setting.k_factor,
            verdict.figures(held),
            before_kappa,
            verdict.outcome()
        ));
        let (net, physics) = if record.kept {
            scale::compression_candidate(&net, &physics, &takes, record.setting)
        } else {
            (net, physics)
        };
        Ok((net, physics, Some(record)))
    }

    /// The fit's weight in the mixed map per strain group ([`compliance::MapWeights`]): half
    /// each unless `train.compliance.weights = "halves"`; then the least-squares fit (at the
    /// stencil of the fit on every training rollout) and the compliance map each read off the
    /// even and the odd training rollouts, smoothed by `smooth` as the maps are, and each map's
    /// two halves compared. Equal weights where training did not start from the fit or fewer
    /// than two rollouts were fitted.
    fn map_weights(&self, smooth: &dyn Fn(&[f64]) -> Vec<f64>) -> Result<compliance::MapWeights> {
        let (job, clips, progress) = (self.fit.job, self.fit.clips, self.fit.progress);
        let topo = job.topology;
        if job.config.train.compliance.weights == compliance::MapWeighting::Equal {
            return Ok(compliance::MapWeights::equal(topo));
        }
        let Some(stencil) = self.fit_stencil.filter(|_| clips.len() >= 2) else {
            progress.note(
                "mixed map: the fit's and the compliance map's shapes weigh half each (training \
                 did not start from a fit of two rollouts or more, so the maps' halves are not \
                 compared)",
            );
            return Ok(compliance::MapWeights::equal(topo));
        };
        let (k0, b0) = (self.resolution.k_init, self.resolution.b_init);
        let mut fit = Vec::new();
        let mut strains = Vec::new();
        for half in [0, 1].map(compliance::Share::Half) {
            let config = &job.config.train.least_squares;
            let f = least_squares::fit_share(config, clips, &job.physics, (k0, b0), stencil, half)?;
            fit.push(smooth(&f.k));
            let rms = compliance_strains(job.config, clips, half)?.rms;
            strains.push(smooth(&compliance::stiffness(topo, &rms, k0)));
        }
        let w = compliance::MapWeights::from_halves(
            topo,
            [&fit[0], &fit[1]],
            [&strains[0], &strains[1]],
        );
        if let Some(g) = w.largest() {
            progress.note(&format!(
                "mixed map: read off the even and the odd training rollouts apart, the fit's map \
                 of the {} springs of its largest strain group ranks alike on both at Spearman \
                 {:.2}, the compliance map's at {:.2}; the fit's shape weighs {:.2} there, the \
                 compliance map's {:.2} (weights as each map's signal to its error, \
                 `blend.json` `weights`)",
                g.springs,
                g.fit_halves.unwrap_or(f64::NAN),
                g.compliance_halves.unwrap_or(f64::NAN),
                g.fit_weight,
                1.0 - g.fit_weight
            ));
        }
        Ok(w)
    }

    /// `(short, long)` motion RMSE of `net` on the held-out training rollouts (m).
    fn held_out_rmse(&self, net: &SpringNet, physics: &Physics) -> Result<(f64, f64)> {
        Ok(self.held_out_figures(net, physics)?.horizons)
    }

    /// `net`'s motion on the held-out training rollouts: RMSE at both horizons and the searches'
    /// objective.
    fn held_out_figures(&self, net: &SpringNet, physics: &Physics) -> Result<HeldOutFigures> {
        let config = self.fit.job.config;
        let takes = Takes {
            files: &self.split.validation,
            ..self.train_takes()
        };
        let curves = crate::eval::motion_curves(net, physics, &takes)?;
        let s = crate::eval::summarize(
            &curves.curves,
            physics.frame_dt,
            config.eval.short_seconds,
            config.eval.long_seconds,
        );
        Ok(HeldOutFigures {
            horizons: (s.short.mean, s.long.mean),
            score: takes.objective.score(&curves.curves, physics.frame_dt),
        })
    }

    /// Each map's blend: its share and motion RMSE on the search's training takes, and where
    /// several maps were searched and training takes were held out, on those.
    fn map_scores(
        &self,
        found: &[(SpringNet, Physics, scale::BlendSearch)],
    ) -> Result<Vec<scale::MapScore>> {
        let judge = found.len() > 1 && !self.split.validation.is_empty();
        found
            .iter()
            .map(|(net, p, record)| {
                Ok(scale::MapScore {
                    map: record.map.clone(),
                    alpha: record.alpha,
                    after: record.polished_after(),
                    held_out: if judge {
                        Some(self.held_out_rmse(net, p)?)
                    } else {
                        None
                    },
                })
            })
            .collect()
    }

    /// The scale search of `model` (from the fit's physics).
    fn scale(&self, model: &SpringNet) -> Result<(SpringNet, Physics)> {
        let job = self.fit.job;
        let config = job.config;
        let (scaled, scaled_physics, record) =
            scale::search(model, &job.physics, &self.train_takes())?;
        self.fit.progress.note(&format!(
            "scale search: k × {:.3}, b × {:.3} at {} substep(s) per frame: mean motion RMSE on \
             {} training rollouts {} -> {:.4e} m",
            record.k_factor,
            record.b_factor,
            record.substeps,
            record.rollouts,
            before_text(record.before),
            record.after
        ));
        let run = self.fit.run;
        keep_searched(run, config, &scaled, &scaled_physics, "scale.json", &record)?;
        Ok((scaled, scaled_physics))
    }

    /// The per-spring refinement of the searched `model` (`train.refine`), kept where it moves
    /// closer to the searches' training takes.
    fn refine(&self, model: &SpringNet, physics: &Physics) -> Result<(SpringNet, Physics)> {
        let (job, progress) = (self.fit.job, self.fit.progress);
        let config = job.config;
        let train = self.train_takes();
        let files = scale::search_files(&train);
        let takes = Takes {
            files: &files,
            ..train
        };
        let refiner = refine::Refiner {
            config: &config.train.refine,
            clips: self.fit.clips,
            takes: &takes,
            device: job.device,
            seed: config.train.seed,
            adam_epsilon: config.train.adam_epsilon,
            state_budget_mib: config.train.state_budget_mib,
            progress,
        };
        let (net, p, record) = refiner.refine(model, physics)?;
        let (first, last) = record.loss_change();
        progress.note(&format!(
            "refine: {} Adam steps on log k, position loss {first:.4e} -> {last:.4e} m² (the \
             first and last eighth of the steps), RMS change of log k {:.3}; mean motion RMSE \
             on {} training rollouts {:.4e} -> {} m ({})",
            record.iterations,
            record.log_k_change,
            files.len(),
            record.before,
            record
                .after
                .map_or("(diverged)".into(), |r| format!("{r:.4e}")),
            if record.kept {
                "kept"
            } else {
                "not kept: the searched network stays"
            }
        ));
        keep_searched(self.fit.run, config, &net, &p, "refine.json", &record)?;
        Ok((net, p))
    }

    /// The learned network against the best uniform one on the held-out training rollouts,
    /// written to the run; where the uniform network moves closer at both horizons and
    /// `train.uniform_fallback` is on, the run keeps it and this returns true (the caller sets
    /// the learned springs aside in `springs.learned.npz`).
    fn validate(&self, model: &SpringNet, physics: &Physics) -> Result<bool> {
        let job = self.fit.job;
        let (config, progress, run) = (job.config, self.fit.progress, self.fit.run);
        let mut v = guard::validate(
            model,
            job.topology,
            physics,
            config.model.uniform_start(),
            &self.split.train,
            &self.split.validation,
            &config.eval,
            config.search_objective(),
            self.device,
            progress,
        )?;
        if config.train.uniform_fallback && v.uniform_closer() {
            let uniform = SpringNet::uniform(job.topology, v.uniform.k, v.uniform.b, self.device)
                .with_kernel(model.graph.kernel);
            run::write_springs(&run.springs(), job.topology, &uniform, job.physics.mass)?;
            RunDir::save_module(&uniform, &run.model())?;
            v.kept_uniform = true;
        }
        progress.note(&format!("validation: {}", v.summary()));
        crate::io::write_json(&guard::Validation::path(&run.dir), &v)?;
        Ok(v.kept_uniform)
    }
}

/// The map of the blend search that averages the other two ([`compliance::mixed`]).
const MIXED_MAP: &str = "mixed";

/// The largest stability number `dt²ω² + 2·dt·γ` a network the blend search keeps runs at
/// ([`AfterFit::with_margin`]): half the explicit step's limit of 4.
const KEPT_STABILITY: f64 = 2.0;

/// Of the maps `among`, the one whose blend moves closest to the search's training takes (a
/// figure that is not finite loses); `None` where `among` is empty.
fn closest_map(scores: &[scale::MapScore], among: impl Iterator<Item = usize>) -> Option<usize> {
    among.min_by(|&a, &b| finite(scores[a].after).total_cmp(&finite(scores[b].after)))
}

/// The map the run keeps ([`choose_map`]): its index among the scores, and why, in words.
struct MapChoice {
    kept: usize,
    why: String,
}

/// The map the run keeps. The search's training takes are the ones the maps were read off, so
/// they favour the fitted map, and a fifth of them held out are few: the mixed map (the fit's
/// forces and the compliance map's ranks averaged) is kept unless another map moves closer than
/// it to the training takes and the held-out takes agree — that map is closer than the mixed
/// map there at both horizons too; of such maps, the one closest to the training takes. Without
/// held-out figures, or without a mixed map, the closest on the training takes.
fn choose_map(scores: &[scale::MapScore]) -> MapChoice {
    let closest = closest_map(scores, 0..scores.len()).expect("one map at least");
    let keep = |kept: usize, why| MapChoice { kept, why };
    let unconfirmed = |why: &str| {
        keep(
            closest,
            format!(
                "the {} map's blend moves closest to the training rollouts{why}; the run keeps it",
                scores[closest].map
            ),
        )
    };
    // Without a mixed map, or where it is the closest, the closest.
    let Some(mixed) = scores
        .iter()
        .position(|s| s.map == MIXED_MAP)
        .filter(|&m| m != closest)
    else {
        return unconfirmed("");
    };
    let Some(m) = scores[mixed].held_out else {
        return unconfirmed(" (no held-out rollouts to confirm it)");
    };
    let beats_mixed = |s: &scale::MapScore| {
        finite(s.after) < finite(scores[mixed].after)
            && s.held_out
                .is_some_and(|h| finite(h.0) < finite(m.0) && finite(h.1) < finite(m.1))
    };
    let confirmed = closest_map(
        scores,
        (0..scores.len()).filter(|&i| i != mixed && beats_mixed(&scores[i])),
    );
    match confirmed {
        Some(kept) => {
            let aside = if kept == closest {
                String::from(", closest there,")
            } else {
                format!(" (the {} map's moves closest there)", scores[closest].map)
            };
            keep(
                kept,
                format!(
                    "the {} map's blend moves closer than the mixed map's to the training \
                     rollouts{aside} and to the held-out rollouts at both horizons; the run keeps \
                     it",
                    scores[kept].map
                ),
            )
        }
        None => keep(
            mixed,
            format!(
                "the {} map's blend moves closest to the training rollouts, but no map's moves \
                 closer than the mixed map's ({:.4e} / {:.4e} m) to the held-out rollouts at \
                 both horizons as well; the run keeps the mixed map",
                scores[closest].map, m.0, m.1
            ),
        ),
    }
}

/// `r`, or infinity where it is not finite (a diverged rollout loses every comparison).
fn finite(r: f64) -> f64 {
    if r.is_finite() { r } else { f64::INFINITY }
}

/// A search's motion RMSE before it: the figure, or `(diverged)`.
fn before_text(before: Option<f64>) -> String {
    before.map_or("(diverged)".to_string(), |r| format!("{r:.4e}"))
}

/// Keeps a network a search after training found: its substeps and drag into the run's
/// `config.toml` (when they differ from the config's), its record as `file`, the network as the
/// run's model.
fn keep_searched(
    run: &RunDir,
    config: &Config,
    net: &SpringNet,
    physics: &Physics,
    file: &str,
    record: &impl Serialize,
) -> Result<()> {
    write_physics(run, config, physics)?;
    crate::io::write_json(&run.dir.join(file), record)?;
    RunDir::save_module(net, &run.model())
}

/// What the held-out training takes say of a search's closest network
/// ([`AfterFit::held_out_verdict`]).
struct HeldOutVerdict {
    /// `(short, long)` motion RMSE of the network kept before, m.
    before: (f64, f64),
    /// `(short, long)` motion RMSE of the search's closest network, m.
    after: (f64, f64),
    /// Whether they prefer the closest ([`scale::held_out_agrees`]).
    kept: bool,
}

/// A network's motion on the held-out training rollouts.
struct HeldOutFigures {
    /// `(short, long)` motion RMSE, m.
    horizons: (f64, f64),
    /// The searches' objective ([`crate::eval::Objective::score`]), m.
    score: f64,
}

impl HeldOutVerdict {
    /// Both networks' held-out figures, for the log.
    fn figures(&self, rollouts: usize) -> String {
        format!(
            "on the {rollouts} held-out rollouts it moves {:.4e} / {:.4e} m (short / long) \
             against {:.4e} / {:.4e} m",
            self.after.0, self.after.1, self.before.0, self.before.1
        )
    }

    /// What the run does, for the log.
    fn outcome(&self) -> &'static str {
        if self.kept {
            "the run keeps it"
        } else {
            "the run keeps the network as it was"
        }
    }
}

/// Writes `physics`' substeps, drag, viscosity and shear springs' compression into the run's
/// `config.toml` where they differ from the config's.
fn write_physics(run: &RunDir, config: &Config, physics: &Physics) -> Result<()> {
    if config.sim.substeps.value() != Some(physics.substeps)
        || config.sim.rayleigh.value() != Some(physics.rayleigh)
        || config.sim.viscosity != physics.viscosity
        || config.sim.shear_compression != physics.shear_compression
    {
        let mut updated = config.clone();
        updated.sim.substeps = crate::settings::Auto::Value(physics.substeps);
        updated.sim.rayleigh = crate::settings::Auto::Value(physics.rayleigh);
        updated.sim.viscosity = physics.viscosity;
        updated.sim.shear_compression = physics.shear_compression;
        crate::io::write_text(&run.config(), &updated.to_toml())?;
    }
    Ok(())
}

/// A trained model of any family.
#[derive(Debug)]
// One value per opened run, never stored in bulk: boxing the spring network would only add an
// indirection to every use.
#[allow(clippy::large_enum_variant)]
pub enum Trained {
    /// The spring network.
    Springs(SpringNet),
    /// The Neural ODE.
    NeuralOde(NeuralOde),
    /// The GNN.
    Gnn(Gnn),
}

/// What a loss needs besides the model and the batch.
pub struct Job<'a> {
    /// The job's configuration.
    pub config: &'a Config,
    /// Constants of the integrator.
    pub physics: Physics,
    /// The particles' grid.
    pub topology: &'a Topology,
    /// Ground-truth `k`, `b` per spring, when known.
    pub truth: Option<&'a Truth>,
    /// The training device.
    pub device: &'a Device,
    /// The curvature elements' learning rate as a fraction of the pass's: `κ_init / k_init`.
    pub curvature_lr_factor: f64,
}

/// A model family the clip-training loop can fit.
pub(crate) trait Trainable: Module + Sized {
    /// The loss on a batch of clips at global iteration `iteration` (0-based).
    fn batch_loss(
        &self,
        job: &Job,
        batch: &ClipBatch,
        pass: &PassConfig,
        iteration: usize,
    ) -> LossTerms;

    /// Readies the model for a pass that trains `k` and/or `b` (spring networks); returns the
    /// parameters the optimizer updates, `k`'s before `b`'s (`None`: all of them).
    fn begin_pass(self, _train_k: bool, _train_b: bool) -> (Self, Option<Vec<ParamId>>) {
        (self, None)
    }

    /// A parameter the pass steps at its own learning rate, `factor × lr` (spring networks: the
    /// curvature stiffness in a pass that trains `k`), after [`Trainable::begin_pass`].
    fn own_rate(&self, _job: &Job, _train_k: bool) -> Option<(ParamId, f64)> {
        None
    }

    /// RMSE of `k` and `b` against the ground truth, when the model has springs and it is known.
    fn parameter_rmse(&self, _truth: Option<&Truth>) -> Option<(f64, f64)> {
        None
    }

    /// Refuses to start when the model would blow up the integrator (spring networks).
    fn check_start(&self, _job: &Job) -> Result<()> {
        Ok(())
    }

    /// What to say when the loss stops being finite.
    fn divergence_hint(&self, _job: &Job) -> String {
        "the surrogate's rollout diverged".into()
    }

    /// The stored frames of each clip that the loss reads, when it reads one window of each
    /// clip rather than all of it (the GNN): the batch then holds a random window of that many
    /// frames of each clip, cut on the host, so only the window is uploaded.
    fn clip_window(&self, _job: &Job) -> Option<usize> {
        None
    }

    /// Whether the gradients are finite (spring networks check `k` and `b`; others trust them).
    fn gradients_finite(&self, _grads: &GradientsParams) -> bool {
        true
    }

    /// Projects the trained parameters back into the explicit step's stable region after an
    /// optimizer step (spring networks: `0 ≤ k, b ≤ cap`; a negative `k` or `b` grows
    /// exponentially, whatever the step); returns how many values were clamped.
    fn project_stable(self, _job: &Job, _train_k: bool, _train_b: bool) -> (Self, usize) {
        (self, 0)
    }
}

/// Training keeps `dt²ω² + 2·dt·γ` at or below this (the limit is 4): a step that would leave
/// the region is projected back by clamping the trained `k` (or `b`) from above.
pub const TRAIN_STABILITY_LIMIT: f64 = 3.6;

impl Trainable for SpringNet {
    fn batch_loss(&self, job: &Job, batch: &ClipBatch, pass: &PassConfig, _: usize) -> LossTerms {
        loss_with_budget(
            self,
            &job.physics,
            batch,
            &pass.weights,
            job.config.train.force_on,
            job.config.train.state_budget_mib,
        )
    }

    fn begin_pass(mut self, train_k: bool, train_b: bool) -> (Self, Option<Vec<ParamId>>) {
        self.k = self.k.clone().set_require_grad(train_k);
        self.b = self.b.clone().set_require_grad(train_b);
        if let Some(c) = &mut self.curvature {
            c.kappa = c.kappa.clone().set_require_grad(train_k);
        }
        let ids = [(train_k, self.k.id), (train_b, self.b.id)]
            .into_iter()
            .filter_map(|(t, id)| t.then_some(id))
            .collect();
        (self, Some(ids))
    }

    /// The curvature stiffness steps at the rate that moves it by the same fraction of its size
    /// as `k` (Adam's steps are about `lr` whatever the gradient's scale): `lr · κ_init /
    /// k_init`, from the run's initial values (so a resumed run steps as an uninterrupted one).
    fn own_rate(&self, job: &Job, train_k: bool) -> Option<(ParamId, f64)> {
        let c = self.curvature.as_ref().filter(|_| train_k)?;
        Some((c.kappa.id, job.curvature_lr_factor))
    }

    fn parameter_rmse(&self, truth: Option<&Truth>) -> Option<(f64, f64)> {
        truth.map(|(k, b)| (rmse(&self.k_values(), k), rmse(&self.b_values(), b)))
    }

    fn check_start(&self, job: &Job) -> Result<()> {
        job.physics.stability_of(job.topology, self).check(
            "the surrogate at its initial k and b",
            job.config.sim.allow_unstable,
        )
    }

    fn divergence_hint(&self, job: &Job) -> String {
        format!(
            "the rollout likely diverged: {}",
            job.physics.stability_of(job.topology, self).describe()
        )
    }

    fn gradients_finite(&self, grads: &GradientsParams) -> bool {
        let kappa = self.curvature.as_ref().map(|c| c.kappa.id);
        [Some(self.k.id), Some(self.b.id), kappa]
            .into_iter()
            .flatten()
            .all(|id| {
                grads.get::<1>(id).is_none_or(|g| {
                    crate::model::springs::to_f64(g)
                        .iter()
                        .all(|x| x.is_finite())
                })
            })
    }

    /// `ω²` grows with every `k_s` and `γ` with every `b_s` (sums of positive semi-definite
    /// terms), so clamping the trained values to the cap of a uniform network that uses the
    /// remaining budget keeps the whole network inside the guard's region; the untrained
    /// parameter keeps its share, and with both trained the budget is split as they use it now.
    fn project_stable(mut self, job: &Job, train_k: bool, train_b: bool) -> (Self, usize) {
        let topo = job.topology;
        let (dt, m, c) = (job.physics.sim_dt(), job.physics.mass, job.physics.rayleigh);
        let (k, b) = (self.k_values(), self.b_values());
        let st = job.physics.stability_of(topo, &self);
        let k_part = dt * dt * st.omega2;
        let b_part = 2.0 * dt * (st.gamma - c / m);
        let budget = TRAIN_STABILITY_LIMIT - 2.0 * dt * c / m;
        let negative = |v: &[f64], trained: bool| trained && v.iter().any(|&x| x < 0.0);
        let kappa = self.curvature_values();
        if k_part + b_part <= budget
            && !negative(&k, train_k)
            && !negative(&b, train_b)
            && !negative(&kappa, train_k)
        {
            return (self, 0);
        }
        let (k_budget, b_budget) = match (train_k, train_b) {
            (true, false) => (budget - b_part, b_part),
            (false, true) => (k_part, budget - k_part),
            _ => {
                let share = k_part / (k_part + b_part).max(f64::MIN_POSITIVE);
                (budget * share, budget * (1.0 - share))
            }
        };
        let (k_budget, b_budget) = (k_budget.max(0.0), b_budget.max(0.0));
        let unit = topo.max_eigenvalue(&vec![1.0; topo.num_springs()]);
        let mut clamped = 0;
        let mut clamp = |param: Param<Tensor<1>>, cap: f64| {
            let values = crate::model::springs::to_f64(param.val());
            clamped += values.iter().filter(|&&v| v > cap || v < 0.0).count();
            param.map(|t| Tensor::from_inner(t.inner().clamp(0.0, cap as f32)).require_grad())
        };
        if train_k {
            // With curvature elements the springs get nine tenths of the stiffness budget and
            // the elements the rest, bounded as `Stability::with_curvature` bounds them (an
            // element adds 8 κ to its middle particle's row of the stiffness matrix and 4 κ to
            // each end's), so the sum stays within the budget.
            let spring_share = if self.curvature.is_some() { 0.9 } else { 1.0 };
            self.k = clamp(self.k, spring_share * k_budget * m / (dt * dt * unit));
            if let Some(c) = self.curvature.as_mut() {
                let ones = vec![1.0; topo.curvature.len()];
                let unit_c =
                    crate::sim::curvature_bound(&topo.curvature, &ones, topo.num_particles());
                c.kappa = clamp(
                    c.kappa.clone(),
                    (1.0 - spring_share) * k_budget * m / (dt * dt * unit_c),
                );
            }
        }
        if train_b {
            self.b = clamp(self.b, b_budget * m / (2.0 * dt * unit));
        }
        (self, clamped)
    }
}

impl Trainable for NeuralOde {
    fn batch_loss(&self, job: &Job, batch: &ClipBatch, pass: &PassConfig, _: usize) -> LossTerms {
        motion_loss(
            self,
            &job.physics,
            batch,
            &pass.weights,
            job.config.train.force_on,
        )
    }

    fn divergence_hint(&self, _job: &Job) -> String {
        "the Neural ODE's rollout diverged (its learned forces blew up); lower \
         `train.single.lr`"
            .into()
    }
}

impl Trainable for Gnn {
    fn batch_loss(
        &self,
        job: &Job,
        batch: &ClipBatch,
        _: &PassConfig,
        iteration: usize,
    ) -> LossTerms {
        let mut rng = StdRng::seed_from_u64(
            job.config.train.seed ^ (iteration as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15),
        );
        let host = gnn_windows(batch, &job.config.model.gnn, &mut rng);
        let windows: Vec<gnn::Window> = host.iter().map(|w| w.view()).collect();
        let value = self.loss(&windows, &mut rng, job.device);
        let zero = || Tensor::<1>::zeros([1], job.device);
        LossTerms {
            total: value.clone(),
            force: zero(),
            impulse: zero(),
            position: zero(),
            k_neg: zero(),
            b_neg: zero(),
        }
    }

    fn divergence_hint(&self, _job: &Job) -> String {
        "the GNN's one-step loss is not finite; lower `train.gnn.lr`".into()
    }

    fn clip_window(&self, job: &Job) -> Option<usize> {
        Some(job.config.model.gnn.window_frames())
    }
}

/// One training window of the GNN on the host: `C + 2` GNN frames of one clip.
pub(crate) struct HostWindow {
    frames: Vec<Vec<[f32; 3]>>,
    pinned: Vec<bool>,
}

impl HostWindow {
    /// The window as the GNN reads it.
    pub fn view(&self) -> gnn::Window<'_> {
        gnn::Window {
            frames: self.frames.iter().map(|f| f.as_slice()).collect(),
            pinned: &self.pinned,
        }
    }
}

/// One random window of `C + 2` GNN frames (`downsample` data frames apart) from every clip.
pub(crate) fn gnn_windows(
    batch: &ClipBatch,
    config: &GnnConfig,
    rng: &mut StdRng,
) -> Vec<HostWindow> {
    let [b, stored, p, _] = batch.positions.dims();
    let span = config.window_frames();
    // Refused by name before training starts (`ModelMeta::new`).
    assert!(
        stored >= span,
        "GNN windows span {span} data frames, the clips have {stored}"
    );
    let pinned: Vec<f32> = batch
        .pinned
        .clone()
        .into_data()
        .try_into_vec_as::<f32>()
        .expect("float tensor");
    let starts: Vec<usize> = (0..b)
        .map(|_| rng.random_range(0..=stored - span))
        .collect();
    // The windows cut on the device and read in one transfer (on a GPU one wait, not one per
    // clip).
    let windows = if stored == span {
        batch.positions.clone()
    } else {
        Tensor::cat(
            starts
                .iter()
                .enumerate()
                .map(|(i, &start)| {
                    batch
                        .positions
                        .clone()
                        .slice([i..i + 1, start..start + span, 0..p, 0..3])
                })
                .collect(),
            0,
        )
    };
    let data: Vec<f32> = windows
        .into_data()
        .try_into_vec_as::<f32>()
        .expect("float tensor");
    (0..b)
        .map(|i| {
            let frames = (0..=config.history + 1)
                .map(|k| {
                    let f = i * span + k * config.downsample;
                    (0..p)
                        .map(|q| {
                            let o = (f * p + q) * 3;
                            [data[o], data[o + 1], data[o + 2]]
                        })
                        .collect()
                })
                .collect();
            HostWindow {
                frames,
                pinned: pinned[i * p..(i + 1) * p]
                    .iter()
                    .map(|&v| v > 0.5)
                    .collect(),
            }
        })
        .collect()
}

/// A least-squares fit leaving more than this relative force residual gets a warning.
const UNRELIABLE_RESIDUAL: f64 = 0.9;

/// The spring network training starts from, and the stencil of the least-squares fit it was
/// read off (`None` where it was read off none).
struct Start {
    net: SpringNet,
    fit_stencil: Option<usize>,
}

/// The training loop shared by every model family: passes of Adam over clip batches, metrics,
/// checkpoints, resume and a clear stop on a non-finite loss.
struct Fit<'a> {
    run: &'a RunDir,
    job: &'a Job<'a>,
    clips: &'a Arc<ClipSet>,
    previous: Option<&'a RunState>,
    progress: &'a Progress,
}

impl Fit<'_> {
    /// The model of the last checkpoint of an interrupted run and the iteration to go on from
    /// (the metrics after it dropped), or the fresh model and 0.
    fn resume<M: Trainable>(&self, model: M) -> Result<(M, usize)> {
        let run = self.run;
        let mut out = (model, 0);
        if let Some(state) = self.previous
            && state.checkpoint > 0
        {
            let path = run.checkpoint(state.checkpoint);
            let record = burn::store::ModuleRecord::load(&path)
                .map_err(|e| anyhow::anyhow!("cannot read checkpoint {}: {e}", path.display()))?;
            out.0 = out
                .0
                .try_load_record(record)
                .map_err(|e| anyhow::anyhow!("checkpoint does not fit this config: {e}"))?;
            out.1 = state.checkpoint;
        }
        if self.previous.is_some() {
            run.truncate_metrics(out.1)?;
        }
        Ok(out)
    }

    /// The strain-compliance network ([`compliance`]) with a uniform `b_init`.
    fn compliance_springs(&self, resolution: &init::Resolution) -> Result<SpringNet> {
        let (topo, device) = (self.job.topology, self.job.device);
        let (k0, b0) = (resolution.k_init, resolution.b_init);
        let kappa = vec![self.job.config.model.curvature_init_for(k0); topo.curvature.len()];
        let noise = self.job.config.train.compliance.noise;
        let strains = compliance_strains(self.job.config, self.clips, compliance::Share::All)?;
        let k = compliance::stiffness(topo, &strains.rms, k0);
        let lo = k.iter().copied().fold(f64::INFINITY, f64::min);
        self.progress.note(&format!(
            "compliance map: k from the springs' RMS strains over the training frames \
             ({:.1} % of their mean square was the positions' noise, taken out{}), \
             {lo:.4}–{k0:.4} N/m; b uniform {b0:.4e} N·s/m",
            100.0 * strains.noise_share,
            match strains.sigma {
                Some(sigma) => format!(
                    "; one marker noise for every spring, {:.3} mm per axis \
                     (`train.compliance.noise = \"{}\"`)",
                    1e3 * sigma,
                    noise.name()
                ),
                None => String::new(),
            }
        ));
        let b = vec![b0; topo.num_springs()];
        Ok(SpringNet::new(topo, &k, &b, device)
            .with_curvature(&kappa)
            .with_kernel(self.job.config.model.kernel))
    }

    /// The spring network training starts from (with its curvature elements at their initial
    /// `κ`): the uniform `k_init`, `b_init`, or with `train.least_squares.enabled` the
    /// per-spring least-squares fit of the data's forces, projected into the stable region;
    /// its record goes to `least_squares.json`. A run resumed from a checkpoint loads it over
    /// this network, so the fit is skipped there.
    fn initial_springs(&self, resolution: &init::Resolution) -> Result<Start> {
        let (job, config) = (self.job, &self.job.config.train.least_squares);
        let (topo, device) = (job.topology, job.device);
        let (k0, b0) = (resolution.k_init, resolution.b_init);
        let kappa = vec![job.config.model.curvature_init_for(k0); topo.curvature.len()];
        let checkpointed = self.previous.is_some_and(|s| s.checkpoint > 0);
        let without_fit = |net| Start {
            net,
            fit_stencil: None,
        };
        if job.config.train.compliance.enabled && !config.enabled && !checkpointed {
            return Ok(without_fit(self.compliance_springs(resolution)?));
        }
        if !config.enabled || checkpointed {
            let net = SpringNet::uniform(topo, k0, b0, device).with_curvature(&kappa);
            return Ok(without_fit(net));
        }
        if !job.topology.curvature.is_empty() {
            self.progress.note(
                "least squares fits the springs only: the curvature elements start at their \
                 initial κ, whose forces the fit does not see",
            );
        }
        if !self.clips.particles_are_landmarks() {
            self.progress.note(
                "least squares: the particles are interpolated between the data's landmarks, \
                 whose averaged accelerations no spring attached to one produces; the fit is \
                 reliable on the data's own vertices (`cloth.layout = \"data\"`, or a grid of \
                 the data's grid)",
            );
        }
        let fit = least_squares::fit(config, self.clips, &job.physics, (k0, b0), self.progress)?;
        let r = &fit.record;
        self.progress.note(&fit_summary(&fit, job.truth));
        if r.residual_fitted > UNRELIABLE_RESIDUAL {
            self.progress.note(&format!(
                "least squares: the springs explain only {:.1} % of the data's force (mean \
                 square); the rest is noise of the differenced target or forces springs do not \
                 make, and least squares shrinks values fitted to noisy strains \
                 (`train.scale_search = true` rescales the network)",
                100.0 * (1.0 - r.residual_fitted.powi(2))
            ));
        }
        if r.hidden_samples > 0 {
            self.progress.note(&format!(
                "least squares: hidden markers left out {:.1} % of the free particles' samples \
                 (the particle hidden over its stencil, or a far end of its springs hidden for \
                 more than {} frames in a row, `train.least_squares.bridge`)",
                100.0 * r.hidden_samples as f64 / (r.hidden_samples + r.samples) as f64,
                config.bridge
            ));
        }
        if r.noise > 0.0 {
            self.progress.note(&format!(
                "least squares: the positions' noise ({:.2} mm per axis, \
                 `train.least_squares.noise`) diluted the fitted k of the median spring to {:.0} \
                 % of its value; the fit divided it out, spring by spring ({} of {} springs' \
                 strains not resolved above the noise: divided by two standard deviations of its \
                 part instead)",
                1e3 * r.noise,
                100.0 * r.dilution_median,
                r.unresolved,
                r.unknowns / 2
            ));
        }
        crate::io::write_json(&self.run.least_squares(), r)?;
        if !r.settled {
            self.progress.note(
                "least squares: the non-negativity's active set did not settle in its rounds; \
                 the values are the last round's (non-negative, not the constrained optimum)",
            );
        }
        if !r.converged {
            self.progress.note(&format!(
                "least squares: the solve stopped at a relative residual of {:.1e} (tolerance \
                 {:.0e}) after {} conjugate-gradient iterations; raise \
                 `train.least_squares.max_iterations` or `prior`",
                r.normal_residual, config.tolerance, r.iterations
            ));
        }
        let (model, clamped) = SpringNet::new(topo, &fit.k, &fit.b, device)
            .with_curvature(&kappa)
            .project_stable(job, true, true);
        if clamped > 0 {
            self.progress.note(&format!(
                "least squares: {clamped} spring values clamped into the stable region \
                 (dt²ω² + 2·dt·γ ≤ {TRAIN_STABILITY_LIMIT})"
            ));
        }
        Ok(Start {
            net: model,
            fit_stencil: Some(r.stencil),
        })
    }

    /// Says what training did besides plain Adam steps: skipped steps, clips left out of a
    /// gradient, springs clamped into the stable region.
    fn note_interventions(&self, skipped: usize, dropped_clips: usize, clamped: usize) {
        if skipped > 0 {
            self.progress.note(&format!(
                "{skipped} step(s) skipped: the loss was finite but its gradient was not"
            ));
        }
        if dropped_clips > 0 {
            self.progress.note(&format!(
                "{dropped_clips} clip(s) left out of their step's gradient: their adjoint was not \
                 finite or over {}× the batch's median (a buckling clip; shorter \
                 `data.clips.steps` leave out fewer)",
                crate::model::kernels::rollout::CHUNK_OUTLIER_RATIO
            ));
        }
        if clamped > 0 {
            self.progress.note(&format!(
                "the stability limit was active: {clamped} spring values clamped so that \
                 dt²ω² + 2·dt·γ ≤ {TRAIN_STABILITY_LIMIT} (see the `clamped` column of metrics.csv)"
            ));
        }
    }

    fn run<M: Trainable>(&self, model: M) -> Result<(TrainSummary, M)> {
        let (run, job, config) = (self.run, self.job, self.job.config);
        let (mut model, mut start_iteration) = self.resume(model)?;
        model.check_start(job)?;
        let passes = config.train.passes(config.model.kind);
        let total: usize = passes.iter().map(|p| p.config.iterations).sum();
        let clock = Clock {
            started: Instant::now(),
            prior: self.previous.map_or(0.0, |s| s.wall_seconds),
        };
        let state = RunState {
            status: Status::Running,
            iteration: start_iteration,
            checkpoint: start_iteration,
            backend: config.backend.to_string(),
            wall_seconds: clock.prior,
            peak_rss_mib: 0.0,
            error: None,
        };
        run.write_state(&state)?;
        let bar = self.progress.bar(total as u64, "train");
        bar.set_position(start_iteration as u64);
        let mut tally = Tally {
            state,
            clock,
            bar,
            last: LossValues::default(),
            rmse_now: model.parameter_rmse(job.truth),
            pending: Vec::new(),
            clamped: 0,
            skipped: 0,
            dropped_clips: 0,
        };
        let mut global = 0;
        for (index, stage) in passes.into_iter().enumerate() {
            let span = PassSpan {
                index,
                start: global,
                from: start_iteration.max(global),
                end: global + stage.config.iterations,
            };
            global = span.end;
            if start_iteration >= global {
                continue;
            }
            model = self.run_pass(model, &stage, span, &mut tally)?;
            start_iteration = global;
        }
        let Tally {
            mut state,
            clock,
            bar,
            last,
            rmse_now,
            pending,
            ..
        } = tally;
        bar.finish();
        self.note_interventions(tally.skipped, tally.dropped_clips, tally.clamped);
        run.append_metrics(&pending)?;
        let model = model.valid();
        RunDir::save_module(&model, &run.model())?;
        state.wall_seconds = clock.seconds();
        state.peak_rss_mib = run::peak_rss_mib();
        run.write_state(&state)?;
        let summary = TrainSummary {
            run_dir: run.dir.clone(),
            iterations: total,
            wall_seconds: state.wall_seconds,
            peak_rss_mib: state.peak_rss_mib,
            last,
            rmse_k: rmse_now.map(|r| r.0),
            rmse_b: rmse_now.map(|r| r.1),
        };
        Ok((summary, model))
    }

    /// The iterations `span.from..span.end` of one pass of the curriculum.
    fn run_pass<M: Trainable>(
        &self,
        model: M,
        stage: &Pass,
        span: PassSpan,
        tally: &mut Tally,
    ) -> Result<M> {
        let (job, config, clips) = (self.job, self.job.config, self.clips);
        let pass = stage.config;
        let pool: Vec<ClipRef> = pool_of(clips, pass.clips, stage.name, self.progress)?;
        let mut sampler = Sampler::new(
            pool.len(),
            config.train.seed ^ ((span.index as u64 + 1) * 0x5851_F42D),
        );
        // Skip what was done before a resume, keeping the clip order reproducible.
        for _ in span.start..span.from {
            sampler.next(pass.batch);
        }
        let mut optim = AdamConfig::new()
            .with_epsilon(config.train.adam_epsilon as f32)
            .init();
        if span.from > span.start && self.run.optimizer(span.from).exists() {
            optim = optim
                .load(self.run.optimizer(span.from))
                .map_err(|e| anyhow::anyhow!("cannot read optimizer state: {e}"))?;
        }
        let (mut model, trained) = model.begin_pass(stage.train_k, stage.train_b);
        let rates = Rates {
            trained,
            own: model.own_rate(job, stage.train_k),
        };
        // A model that reads one window of each clip gets only that window, drawn per
        // iteration (so a resumed run draws the same ones); a window longer than the clips
        // is left to the model to refuse by name.
        let draw = Draw {
            pool: &pool,
            seed: config.train.seed,
            batch: pass.batch,
            steps: clips.steps,
            window: model
                .clip_window(job)
                .filter(|&frames| (2..=clips.steps + 1).contains(&frames)),
        };
        let window_steps = draw.window.map_or(clips.steps, |frames| frames - 1);
        // The next batch is read and assembled on another thread while this one trains.
        let prefetch = |refs: Vec<ClipRef>| {
            let clips = Arc::clone(clips);
            std::thread::spawn(move || clips.host_batch_of(&refs, window_steps))
        };
        let mut upcoming = None;
        for it in span.from..span.end {
            let host = match upcoming.take() {
                Some(handle) => join_batch(handle)?,
                None => clips.host_batch_of(&draw.refs(&mut sampler, it), window_steps)?,
            };
            if it + 1 < span.end {
                upcoming = Some(prefetch(draw.refs(&mut sampler, it + 1)));
            }
            let batch = host.to_device(job.device)?;
            let at = Iteration {
                stage,
                it,
                span: &span,
            };
            model = self.iterate(model, &batch, &mut optim, &rates, &at, tally)?;
        }
        Ok(model)
    }

    /// One iteration: the loss, the Adam steps, the projection, the metrics row and, when due,
    /// a checkpoint; a non-finite loss ends the run as failed.
    fn iterate<M: Trainable>(
        &self,
        model: M,
        batch: &ClipBatch,
        optim: &mut ModuleOptimizer,
        rates: &Rates,
        at: &Iteration,
        tally: &mut Tally,
    ) -> Result<M> {
        let (job, config) = (self.job, self.job.config);
        let (name, pass, it) = (at.stage.name, at.stage.config, at.it);
        let terms = model.batch_loss(job, batch, pass, it);
        let values = terms.values();
        if !values.total.is_finite() {
            return Err(self.diverged(&model, &values, at, tally));
        }
        let grads = terms.total.backward();
        let lr = pass.lr_at(it - at.span.start);
        let steps = rates.steps(&model, grads, lr, pass.lr_b_at(it - at.span.start));
        tally.dropped_clips += crate::model::kernels::rollout::take_dropped_clips();
        let mut model = model;
        if steps.iter().all(|(_, g)| model.gradients_finite(g)) {
            for (lr, grads) in steps {
                model = optim.step(lr, model, grads);
            }
        } else {
            tally.skipped += 1; // a finite loss with a non-finite gradient: no step
        }
        let clamped = if config.train.project_stable {
            let (projected, clamped) =
                model.project_stable(job, at.stage.train_k, at.stage.train_b);
            model = projected;
            clamped
        } else {
            0
        };
        tally.clamped += clamped;
        tally.last = values;
        if job.truth.is_some() {
            tally.rmse_now = model.parameter_rmse(job.truth);
        }
        let elapsed = tally.clock.seconds();
        let rmse_now = tally.rmse_now;
        tally.pending.push(MetricsRow {
            iteration: it + 1,
            pass: name.to_string(),
            loss: values.total,
            force: values.force,
            impulse: values.impulse,
            position: values.position,
            k_neg: values.k_neg,
            b_neg: values.b_neg,
            rmse_k: rmse_now.map(|r| r.0),
            rmse_b: rmse_now.map(|r| r.1),
            seconds: elapsed,
            clamped,
        });
        tally.bar.set_message(match rmse_now {
            Some((k, b)) => format!(
                "{name} loss {:.3e} rmse_k {k:.3} rmse_b {b:.3}",
                values.total
            ),
            None => format!("{name} loss {:.3e}", values.total),
        });
        tally.bar.inc(1);
        tally.state.iteration = it + 1;
        if (it + 1) % config.train.checkpoint_every == 0 || it + 1 == at.span.end {
            self.checkpoint(&model, optim, it + 1, elapsed, tally)?;
        }
        Ok(model)
    }

    /// The error that ends a run whose loss is not finite, after the metrics so far and the
    /// failed state are written.
    fn diverged<M: Trainable>(
        &self,
        model: &M,
        values: &LossValues,
        at: &Iteration,
        tally: &mut Tally,
    ) -> anyhow::Error {
        let name = at.stage.name;
        let message = format!(
            "training stopped: the loss became {} at iteration {} ({name} pass; force {:.4e}, \
             impulse {:.4e}). {}. The last good model is checkpoint {} in {}; lower \
             `train.{name}.lr`, use more `sim.substeps`, or resume from the checkpoint",
            values.total,
            at.it + 1,
            values.force,
            values.impulse,
            model.divergence_hint(self.job),
            tally.state.checkpoint,
            self.run.dir.display(),
        );
        if let Err(e) = self.run.append_metrics(&tally.pending) {
            return e;
        }
        tally.state.status = Status::Failed;
        tally.state.error = Some(message.clone());
        if let Err(e) = self.run.write_state(&tally.state) {
            return e;
        }
        tally.bar.abandon();
        anyhow!(message)
    }

    /// Writes the pending metrics, the model and optimizer at `iteration` and the state, and
    /// drops the previous checkpoint's optimizer state.
    fn checkpoint<M: Trainable>(
        &self,
        model: &M,
        optim: &ModuleOptimizer,
        iteration: usize,
        elapsed: f64,
        tally: &mut Tally,
    ) -> Result<()> {
        let run = self.run;
        run.append_metrics(&tally.pending)?;
        tally.pending.clear();
        RunDir::save_module(model, &run.checkpoint(iteration))?;
        let optim_path = run.optimizer(iteration);
        crate::io::write_atomic_with_path(&optim_path, |tmp| {
            optim
                .save(tmp)
                .map_err(|e| anyhow::anyhow!("cannot save optimizer state: {e}"))
        })?;
        let state = &mut tally.state;
        let old = state.checkpoint;
        state.checkpoint = iteration;
        state.wall_seconds = elapsed;
        state.peak_rss_mib = run::peak_rss_mib();
        run.write_state(state)?;
        if old > 0 && old != state.checkpoint {
            let _ = std::fs::remove_file(run.optimizer(old));
        }
        Ok(())
    }
}

/// The run's clock: the seconds of the sessions before a resume plus this one's.
struct Clock {
    started: Instant,
    prior: f64,
}

impl Clock {
    fn seconds(&self) -> f64 {
        self.prior + self.started.elapsed().as_secs_f64()
    }
}

/// What the training loop carries from iteration to iteration and pass to pass.
struct Tally {
    state: RunState,
    clock: Clock,
    bar: crate::progress::Bar,
    /// The last iteration's loss terms.
    last: LossValues,
    /// The parameters' RMSE against the truth, when known.
    rmse_now: Option<(f64, f64)>,
    /// Metrics rows not yet written.
    pending: Vec<MetricsRow>,
    /// Parameters clamped by the stability projection.
    clamped: usize,
    /// Iterations whose gradient was not finite (no step taken).
    skipped: usize,
    /// Clips the rollout kernels dropped.
    dropped_clips: usize,
}

/// Where a pass lies among the run's iterations.
struct PassSpan {
    /// The pass's place in the curriculum.
    index: usize,
    /// Its first global iteration.
    start: usize,
    /// The first one this session runs (later than `start` on a resume).
    from: usize,
    /// One past its last.
    end: usize,
}

/// One global iteration of a pass.
struct Iteration<'a> {
    stage: &'a Pass<'a>,
    it: usize,
    span: &'a PassSpan,
}

/// How a pass's clips are drawn: batches of the pool and, for a model that reads one window of
/// each clip, a window per clip drawn per iteration.
struct Draw<'a> {
    pool: &'a [ClipRef],
    seed: u64,
    batch: usize,
    /// Steps of every clip.
    steps: usize,
    /// Frames of the window, when the model reads one.
    window: Option<usize>,
}

impl Draw<'_> {
    /// The clips of iteration `it`.
    fn refs(&self, sampler: &mut Sampler, it: usize) -> Vec<ClipRef> {
        let mut rng =
            StdRng::seed_from_u64(self.seed ^ (it as u64 + 1).wrapping_mul(0xD1B5_4A32_D192_ED03));
        sampler
            .next(self.batch)
            .into_iter()
            .map(|i| {
                let mut clip = self.pool[i];
                if let Some(frames) = self.window {
                    let shift = rng.random_range(0..=self.steps + 1 - frames);
                    clip.offset += shift;
                    clip.start += shift;
                }
                clip
            })
            .collect()
    }
}

/// A pass's learning rates beyond the pass's own: the parameters it trains (with `lr_b`, `k`'s
/// and `b`'s step apart) and a parameter with its own factor of the rate.
struct Rates {
    trained: Option<Vec<ParamId>>,
    own: Option<(ParamId, f64)>,
}

impl Rates {
    /// One Adam step per learning rate: with `lr_b`, k's and b's gradients step separately
    /// (Adam's moments are per parameter, so this is Adam with two rates).
    fn steps<M: Module>(
        &self,
        model: &M,
        mut grads: Gradients,
        lr: f64,
        lr_b: Option<f64>,
    ) -> Vec<(f64, GradientsParams)> {
        let own_step = self.own.map(|(id, factor)| {
            (
                lr * factor,
                GradientsParams::from_params(&mut grads, model, &[id]),
            )
        });
        let steps: Vec<(f64, GradientsParams)> = match (&self.trained, lr_b) {
            (Some(ids), Some(lr_b)) if ids.len() == 2 => vec![
                (
                    lr,
                    GradientsParams::from_params(&mut grads, model, &ids[..1]),
                ),
                (
                    lr_b,
                    GradientsParams::from_params(&mut grads, model, &ids[1..]),
                ),
            ],
            (Some(ids), _) => vec![(lr, GradientsParams::from_params(&mut grads, model, ids))],
            (None, _) => vec![(lr, GradientsParams::from_grads(grads, model))],
        };
        steps.into_iter().chain(own_step).collect()
    }
}

/// The log line of a least-squares fit, with its parameter errors where the truth is known.
fn fit_summary(fit: &least_squares::LeastSquaresFit, truth: Option<&Truth>) -> String {
    let r = &fit.record;
    let mut line = format!(
        "least squares: stencil ±{} over {} frames ({} samples): force residual {:.3} of \
         the target (uniform start {:.3}); {} CG iterations; {} of {} unknowns fixed at 0, \
         {} unconstrained",
        r.stencil,
        r.frames,
        r.samples,
        r.residual_fitted,
        r.residual_initial,
        r.iterations,
        r.fixed_at_zero,
        r.unknowns,
        r.unconstrained
    );
    if let Some((k, b)) = truth {
        line += &format!(
            "; rmse_k {:.3e}, rmse_b {:.3e}",
            rmse(&fit.k, k),
            rmse(&fit.b, b)
        );
    }
    line
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
        ClipPool::All => clips.all_clips(),
    };
    if !chosen.is_empty() {
        return Ok(chosen);
    }
    let all: Vec<ClipRef> = clips.all_clips();
    if all.is_empty() {
        bail!("the {name} pass has no clips");
    }
    progress.note(&format!(
        "warning: the {name} pass asks for {pool:?} clips and the data has none; using every clip"
    ));
    Ok(all)
}

impl ModelMeta {
    /// The constants of a new model of `config.model.kind` for the clips of a training set:
    /// the Neural ODE's scales, the GNN's normalisation (from up to 64 clips).
    pub fn new(
        config: &Config,
        clips: &ClipSet,
        physics: &Physics,
        progress: &Progress,
    ) -> Result<Self> {
        let topo = &clips.topology;
        let (width, height) = (clips.info.width, clips.info.height);
        let kind = config.model.kind;
        let particles = topo.num_particles();
        let mut meta = ModelMeta {
            kind,
            particles,
            width,
            height,
            particle_mass: physics.mass,
            frame_dt: physics.frame_dt,
            parameters: 0,
            ode_scales: None,
            gnn_stats: None,
        };
        match kind {
            ModelKind::Springs => meta.parameters = 2 * topo.num_springs(),
            ModelKind::NeuralOde => {
                meta.ode_scales =
                    Some(OdeScales::new(width, height, physics.mass, physics.gravity));
                meta.parameters = config.model.neural_ode.parameter_count(particles);
            }
            ModelKind::Gnn => {
                let cfg = &config.model.gnn;
                let span = cfg.window_frames();
                if clips.steps + 1 < span {
                    bail!(
                        "the GNN trains on windows of {span} data frames ({} velocities of frames \
                         `model.gnn.downsample` = {} apart, and the next frame), but the clips \
                         have {} frames: raise `data.clips.steps` to at least {} or lower \
                         `model.gnn.history` / `model.gnn.downsample`",
                        cfg.history,
                        cfg.downsample,
                        clips.steps + 1,
                        span - 1
                    );
                }
                let pool: Vec<ClipRef> = clips.all_clips();
                let mut sampler = Sampler::new(pool.len(), config.train.seed ^ 0x0005_7A75);
                let refs: Vec<ClipRef> = sampler.next(64).into_iter().map(|i| pool[i]).collect();
                progress.note(&format!("GNN: normalisation from {} clips", refs.len()));
                let plain = config.backend.device()?;
                let batch = clips.batch(&refs, &plain)?;
                let mut rng = StdRng::seed_from_u64(config.train.seed);
                let host = gnn_windows(&batch, cfg, &mut rng);
                let windows: Vec<gnn::Window> = host.iter().map(|w| w.view()).collect();
                meta.gnn_stats = Some(gnn::statistics(&windows, cfg, topo.spacing()));
                meta.parameters = cfg.parameter_count();
            }
        }
        Ok(meta)
    }

    /// A new Neural ODE with these constants.
    pub fn neural_ode(&self, config: &Config, device: &Device) -> NeuralOde {
        NeuralOde::new(
            &config.model.neural_ode,
            self.particles,
            self.ode_scales.expect("a Neural ODE run has scales"),
            device,
        )
    }

    /// A new GNN with these constants.
    pub fn gnn(&self, config: &Config, device: &Device) -> Result<Gnn> {
        let stats = self
            .gnn_stats
            .ok_or_else(|| anyhow::anyhow!("model.json of a GNN run has no `gnn_stats`"))?;
        Ok(Gnn::new(&config.model.gnn, stats, device))
    }
}

/// The springs' RMS strains over the training rollouts of `share` for the compliance map, with
/// the positions' noise taken out as `train.compliance.noise` says; `"stated"` takes the marker
/// noise the fit takes out (`train.least_squares.noise`, resolved; none where unresolved).
fn compliance_strains(
    config: &Config,
    clips: &ClipSet,
    share: compliance::Share,
) -> Result<compliance::RmsStrains> {
    let stated = config.train.least_squares.noise.value().unwrap_or(0.0);
    compliance::rms_strains(clips, share, config.train.compliance.noise, stated)
}

#[cfg(test)]
mod schedule_tests {
    use super::{Mode, PassConfig, TrainConfig};
    use crate::model::ModelKind;

    #[test]
    fn each_mode_runs_its_passes_in_order() {
        let names = |mode: Mode| -> Vec<(&str, bool, bool)> {
            let c = TrainConfig {
                mode,
                ..TrainConfig::default()
            };
            c.passes(ModelKind::Springs)
                .iter()
                .map(|p| (p.name, p.train_k, p.train_b))
                .collect()
        };
        assert_eq!(
            names(Mode::Dual),
            [("stiffness", true, false), ("damping", false, true)]
        );
        assert_eq!(names(Mode::Single), [("single", true, true)]);
        assert_eq!(
            names(Mode::SingleThenDamping),
            [("single", true, true), ("damping", false, true)]
        );
    }

    /// Map smoothing acts on the blend search's maps: without the search it is refused,
    /// naming both keys.
    #[test]
    fn map_smoothing_needs_the_blend_search() {
        let mut c = TrainConfig {
            map_smoothing: 1,
            ..TrainConfig::default()
        };
        let e = c.validate().unwrap_err().to_string();
        assert!(
            e.contains("`train.map_smoothing`") && e.contains("`train.blend_search`"),
            "{e}"
        );
        c.blend_search = true;
        c.validate().unwrap();
    }

    #[test]
    fn the_damping_searches_need_the_blend_search() {
        for (key, on) in [
            (
                "proportional_damping",
                TrainConfig {
                    proportional_damping: true,
                    ..TrainConfig::default()
                },
            ),
            (
                "viscosity_search",
                TrainConfig {
                    viscosity_search: true,
                    ..TrainConfig::default()
                },
            ),
            (
                "blend_contrast",
                TrainConfig {
                    blend_contrast: true,
                    ..TrainConfig::default()
                },
            ),
        ] {
            let mut c = on;
            let e = c.validate().unwrap_err().to_string();
            assert!(
                e.contains(&format!("`train.{key}`")) && e.contains("`train.blend_search`"),
                "{e}"
            );
            c.blend_search = true;
            c.validate().unwrap();
        }
    }

    #[test]
    fn the_learning_rate_decays_geometrically_from_lr_to_lr_times_decay() {
        let pass = PassConfig {
            iterations: 5,
            lr: 2.0,
            lr_decay: 0.01,
            ..PassConfig::default()
        };
        assert_eq!(pass.lr_at(0), 2.0);
        assert!((pass.lr_at(4) - 0.02).abs() < 1e-12);
        assert!(
            (pass.lr_at(2) - 0.2).abs() < 1e-12,
            "the middle is the geometric mean"
        );
        let constant = PassConfig::default();
        assert_eq!(constant.lr_at(0), constant.lr_at(127));
        let held = PassConfig {
            iterations: 11,
            lr_hold: 0.5,
            ..pass
        };
        assert_eq!(held.lr_at(5), 2.0, "held for the first half");
        assert_eq!(held.lr_b_at(5), None);
        let two = PassConfig {
            lr_b: Some(0.2),
            ..held.clone()
        };
        assert_eq!(two.lr_b_at(5), Some(0.2));
        assert!(
            (two.lr_b_at(10).unwrap() - 0.002).abs() < 1e-12,
            "b under the same schedule"
        );
        assert!((held.lr_at(10) - 0.02).abs() < 1e-12);
        assert!(held.lr_at(8) < held.lr_at(7));
    }
}

#[cfg(test)]
mod map_choice_tests {
    use super::choose_map;
    use crate::train::scale::MapScore;

    fn score(map: &str, after: f64, held_out: Option<(f64, f64)>) -> MapScore {
        MapScore {
            map: map.into(),
            alpha: 1.0,
            after,
            held_out,
        }
    }

    #[test]
    fn another_map_than_the_mixed_one_is_kept_only_where_the_held_out_takes_agree() {
        // The fitted map moves closest to the training takes and is closer on the held-out
        // takes at both horizons too: kept.
        let agree = [
            score("trained", 0.20, Some((0.05, 0.24))),
            score("compliance", 0.23, Some((0.04, 0.29))),
            score("mixed", 0.21, Some((0.06, 0.25))),
        ];
        assert_eq!(choose_map(&agree).kept, 0);
        // Closer over the whole take, not at the short horizon: the mixed map.
        let long_only = [
            score("trained", 0.20, Some((0.07, 0.24))),
            score("compliance", 0.23, Some((0.04, 0.29))),
            score("mixed", 0.21, Some((0.06, 0.25))),
        ];
        assert_eq!(choose_map(&long_only).kept, 2);
        let why = choose_map(&long_only).why;
        assert!(
            why.contains("the trained map's") && why.contains("keeps the mixed map"),
            "{why}"
        );
        // The compliance map is the held-out takes' closest but not the training takes': the
        // mixed map.
        let held_out_only = [
            score("trained", 0.20, Some((0.07, 0.26))),
            score("compliance", 0.23, Some((0.01, 0.01))),
            score("mixed", 0.21, Some((0.06, 0.25))),
        ];
        assert_eq!(choose_map(&held_out_only).kept, 2);
        // The closest on the training takes is not confirmed by the held-out takes, but another
        // map closer than the mixed one there is (Warp's stiff cloth): that one.
        let second = [
            score("trained", 0.2304, Some((0.104, 0.322))),
            score("compliance", 0.2289, Some((0.130, 0.383))),
            score("mixed", 0.2321, Some((0.127, 0.342))),
        ];
        let choice = choose_map(&second);
        assert_eq!(choice.kept, 0);
        assert!(
            choice.why.contains("the trained map's") && choice.why.contains("compliance map's"),
            "{}",
            choice.why
        );
        // A map the held-out takes prefer but the training takes do not: still the mixed map.
        let not_on_training = [
            score("trained", 0.2330, Some((0.104, 0.322))),
            score("compliance", 0.2289, Some((0.130, 0.383))),
            score("mixed", 0.2321, Some((0.127, 0.342))),
        ];
        assert_eq!(choose_map(&not_on_training).kept, 2);
        // Without held-out figures the training takes decide.
        let plain: Vec<MapScore> = agree.iter().map(|s| score(&s.map, s.after, None)).collect();
        assert_eq!(choose_map(&plain).kept, 0);
        // Without a mixed map too.
        assert_eq!(choose_map(&agree[..2]).kept, 0);
        // A mixed map that diverged on the held-out takes loses; one that diverged on the
        // training takes is not the closest there.
        let diverged = [
            score("trained", 0.20, Some((0.05, 0.30))),
            score("mixed", f64::NAN, Some((f64::NAN, f64::NAN))),
        ];
        assert_eq!(choose_map(&diverged).kept, 0);
    }
}
