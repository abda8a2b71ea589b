//! A run directory: `runs/<name>/` with the resolved config, metrics, checkpoints and the
//! trained surrogate. A finished run is never overwritten unless asked.

use std::io::Write;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use burn::module::Module;
use serde::{Deserialize, Serialize};

use crate::cloth::Topology;
use crate::data::npz::{Array, Npz};
use crate::model::ModelKind;
use crate::model::gnn::GnnStats;
use crate::model::neural_ode::OdeScales;

/// Status of a run (`run.json`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Status {
    /// Training is under way or was interrupted.
    Running,
    /// Training stopped on an error (e.g. a non-finite loss).
    Failed,
    /// Training completed; `model.bpk` and `springs.npz` are written.
    Finished,
}

/// `run.json`: the run's status and where training stands.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RunState {
    /// Status.
    pub status: Status,
    /// Iterations completed over all passes.
    pub iteration: usize,
    /// Iteration of the last checkpoint (0 = none).
    pub checkpoint: usize,
    /// Backend used.
    pub backend: String,
    /// Training wall time so far, s.
    pub wall_seconds: f64,
    /// Peak resident memory of the training process, MiB.
    pub peak_rss_mib: f64,
    /// Error message when failed.
    #[serde(default)]
    pub error: Option<String>,
}

/// Paths of a run directory.
#[derive(Debug, Clone)]
pub struct RunDir {
    /// The directory.
    pub dir: PathBuf,
}

/// Metrics columns, in order.
pub const METRICS_HEADER: &str =
    "iteration,pass,loss,force,impulse,position,k_neg,b_neg,rmse_k,rmse_b,seconds,clamped";

/// An exclusive hold on a run directory for one training process: an OS file lock on
/// `.<name>.lock` beside the directory (the directory itself may be cleared and recreated
/// under it). The operating system releases it when the process ends, however it ends.
#[derive(Debug)]
pub struct RunLock {
    _file: std::fs::File,
}

impl RunDir {
    /// A run directory at `dir` (not created yet).
    pub fn new(dir: impl Into<PathBuf>) -> Self {
        Self { dir: dir.into() }
    }

    /// The lock file guarding the directory: `.<name>.lock` in its parent.
    pub fn lock_path(&self) -> PathBuf {
        let name = self
            .dir
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_else(|| "run".into());
        let parent = self
            .dir
            .parent()
            .filter(|p| !p.as_os_str().is_empty())
            .unwrap_or(Path::new("."));
        parent.join(format!(".{name}.lock"))
    }

    /// Takes the directory for this process, or fails when another process holds it (two
    /// `train` processes on one run would interleave their writes).
    pub fn lock(&self) -> Result<RunLock> {
        let path = self.lock_path();
        if let Some(parent) = path.parent() {
            std::fs::create_dir_all(parent)
                .with_context(|| format!("cannot create {}", parent.display()))?;
        }
        let file = std::fs::OpenOptions::new()
            .create(true)
            .truncate(false)
            .write(true)
            .open(&path)
            .with_context(|| format!("cannot open the run lock {}", path.display()))?;
        match file.try_lock() {
            Ok(()) => Ok(RunLock { _file: file }),
            Err(std::fs::TryLockError::WouldBlock) => bail!(
                "another springtime process is training in {} (it holds {}); wait for it to \
                 end or train into another --out",
                self.dir.display(),
                path.display()
            ),
            Err(std::fs::TryLockError::Error(e)) => {
                Err(e).with_context(|| format!("cannot lock {}", path.display()))
            }
        }
    }

    /// `config.toml`: the resolved configuration.
    pub fn config(&self) -> PathBuf {
        self.dir.join("config.toml")
    }
    /// The config as the user gave it (`"auto"` values unresolved), `config.requested.toml`.
    pub fn requested_config(&self) -> PathBuf {
        self.dir.join("config.requested.toml")
    }

    /// What the run derived from its data (`defaults.json`).
    pub fn defaults(&self) -> PathBuf {
        self.dir.join("defaults.json")
    }

    /// `run.json`.
    pub fn state_path(&self) -> PathBuf {
        self.dir.join("run.json")
    }
    /// `metrics.csv`.
    pub fn metrics(&self) -> PathBuf {
        self.dir.join("metrics.csv")
    }
    /// `model.bpk`: the trained module in Burn's burnpack format.
    pub fn model(&self) -> PathBuf {
        self.dir.join("model.bpk")
    }
    /// `springs.npz`: the exportable surrogate.
    pub fn springs(&self) -> PathBuf {
        self.dir.join("springs.npz")
    }
    /// `model.json`: the model's family, size and constants ([`ModelMeta`]).
    pub fn meta(&self) -> PathBuf {
        self.dir.join("model.json")
    }
    /// `eval.json`.
    pub fn eval(&self) -> PathBuf {
        self.dir.join("eval.json")
    }
    /// `drapes.json`: the output folders of `springtime drape` runs of this run (for the report).
    pub fn drapes(&self) -> PathBuf {
        self.dir.join("drapes.json")
    }
    /// `motion_rmse.csv`: per-frame motion RMSE of every test rollout (written by eval).
    pub fn motion_curves(&self) -> PathBuf {
        self.dir.join("motion_rmse.csv")
    }
    /// Checkpoint of the module at `iteration`.
    pub fn checkpoint(&self, iteration: usize) -> PathBuf {
        self.dir
            .join("checkpoints")
            .join(format!("model_{iteration:06}.bpk"))
    }
    /// Optimizer state at `iteration`.
    pub fn optimizer(&self, iteration: usize) -> PathBuf {
        self.dir
            .join("checkpoints")
            .join(format!("optim_{iteration:06}.bpk"))
    }

    /// The run's state, if it has one.
    pub fn state(&self) -> Result<Option<RunState>> {
        let path = self.state_path();
        if !path.exists() {
            return Ok(None);
        }
        let text = std::fs::read_to_string(&path)
            .with_context(|| format!("cannot read {}", path.display()))?;
        Ok(Some(serde_json::from_str(&text).with_context(|| {
            format!("{} is not a valid run state", path.display())
        })?))
    }

    /// The state of a finished run of any model family; refuses a run that is missing or not
    /// finished, naming the file.
    pub fn finished(&self) -> Result<RunState> {
        let state = self.state()?.with_context(|| {
            format!(
                "{} not found: {} is not a run directory",
                self.state_path().display(),
                self.dir.display()
            )
        })?;
        if state.status != Status::Finished {
            bail!(
                "{} is not finished ({} says status `{}`{}): finish training first (springtime train --resume)",
                self.dir.display(),
                self.state_path().display(),
                serde_json::to_value(state.status)?
                    .as_str()
                    .unwrap_or("unknown"),
                state
                    .error
                    .as_deref()
                    .map(|e| format!(", error: {e}"))
                    .unwrap_or_default()
            );
        }
        Ok(state)
    }

    /// Writes `run.json`.
    pub fn write_state(&self, state: &RunState) -> Result<()> {
        // The build that wrote the run: `springtime.version` and `springtime.commit`.
        let mut value = serde_json::to_value(state)?;
        value["springtime"] = serde_json::json!(crate::BuildInfo::current());
        crate::io::write_json(&self.state_path(), &value)
    }

    /// Refuses to start a fresh run over a finished or started one unless `force`.
    pub fn check_fresh(&self, force: bool) -> Result<()> {
        let occupied = self.dir.exists() && std::fs::read_dir(&self.dir)?.next().is_some();
        if !occupied || force {
            return Ok(());
        }
        match self.state().ok().flatten().map(|s| s.status) {
            Some(Status::Finished) => bail!(
                "{} holds a finished run; pass --force to overwrite it or --out to train elsewhere",
                self.dir.display()
            ),
            Some(_) => bail!(
                "{} holds an unfinished run; pass --resume to continue it or --force to start over",
                self.dir.display()
            ),
            None => bail!(
                "{} exists and is not empty; pass --force to overwrite it or --out to train elsewhere",
                self.dir.display()
            ),
        }
    }

    /// Empties (after [`check_fresh`](Self::check_fresh)) and creates the directory with an
    /// empty `metrics.csv`.
    pub fn create_fresh(&self) -> Result<()> {
        if self.dir.exists() {
            std::fs::remove_dir_all(&self.dir)
                .with_context(|| format!("cannot clear {}", self.dir.display()))?;
        }
        std::fs::create_dir_all(self.dir.join("checkpoints"))
            .with_context(|| format!("cannot create {}", self.dir.display()))?;
        crate::io::write_text(&self.metrics(), &format!("{METRICS_HEADER}\n"))
    }

    /// Keeps the metrics rows up to `iteration` (used when resuming from a checkpoint).
    pub fn truncate_metrics(&self, iteration: usize) -> Result<()> {
        let path = self.metrics();
        let text = std::fs::read_to_string(&path).unwrap_or_default();
        let mut out = format!("{METRICS_HEADER}\n");
        for line in text.lines().skip(1) {
            let it: Option<usize> = line.split(',').next().and_then(|s| s.parse().ok());
            if it.is_some_and(|it| it <= iteration) {
                out.push_str(line);
                out.push('\n');
            }
        }
        crate::io::write_text(&path, &out)
    }

    /// Appends metrics rows.
    pub fn append_metrics(&self, rows: &[String]) -> Result<()> {
        if rows.is_empty() {
            return Ok(());
        }
        let mut f = std::fs::OpenOptions::new()
            .append(true)
            .create(true)
            .open(self.metrics())
            .with_context(|| format!("cannot append to {}", self.metrics().display()))?;
        for r in rows {
            writeln!(f, "{r}")?;
        }
        Ok(())
    }

    /// Saves a module to `path` atomically (burnpack).
    pub fn save_module<M: Module>(model: &M, path: &Path) -> Result<()> {
        crate::io::write_atomic_with_path(path, |tmp| {
            model
                .clone()
                .into_record()
                .save(tmp)
                .map_err(|e| anyhow::anyhow!("cannot save the model: {e}"))
        })
    }
}

/// `model.json`: what a run's `model.bpk` needs besides its config to be rebuilt.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ModelMeta {
    /// The model family.
    pub kind: ModelKind,
    /// Particles the model simulates.
    pub particles: usize,
    /// Rest rectangle, m.
    pub width: f64,
    /// Rest rectangle, m.
    pub height: f64,
    /// Mass of every particle, kg.
    pub particle_mass: f64,
    /// Time between data frames, s.
    pub frame_dt: f64,
    /// Learnable parameters.
    pub parameters: usize,
    /// The Neural ODE's input and output scales.
    #[serde(default)]
    pub ode_scales: Option<OdeScales>,
    /// The GNN's normalisation.
    #[serde(default)]
    pub gnn_stats: Option<GnnStats>,
}

impl ModelMeta {
    /// Reads `model.json`.
    pub fn read(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path)
            .with_context(|| format!("cannot read {}", path.display()))?;
        serde_json::from_str(&text)
            .with_context(|| format!("{} is not a valid model.json", path.display()))
    }
}

/// Writes the exportable surrogate: `springs` `[S, 2]`, `rest_length`, `k`, `b` `[S]`, and the
/// grid (`rest_uv` `[P, 2]`, `grid` = `[nx, ny]`, `width`, `height`, `particle_mass`, `family`).
pub fn write_springs(
    path: &Path,
    topology: &Topology,
    k: &[f64],
    b: &[f64],
    particle_mass: f64,
) -> Result<()> {
    springs_npz(topology, k, b, particle_mass).write(path)
}

/// The arrays of [`write_springs`], to write or to extend.
pub fn springs_npz(topology: &Topology, k: &[f64], b: &[f64], particle_mass: f64) -> Npz {
    let s = topology.num_springs();
    let f32s = |v: &[f64]| v.iter().map(|&x| x as f32).collect::<Vec<_>>();
    let mut npz = Npz::default();
    let ends: Vec<i32> = topology
        .springs
        .iter()
        .flat_map(|e| [e[0] as i32, e[1] as i32])
        .collect();
    npz.insert("springs", Array::i32(&[s, 2], &ends));
    npz.insert(
        "rest_length",
        Array::f32(&[s], &f32s(&topology.rest_length)),
    );
    npz.insert("k", Array::f32(&[s], &f32s(k)));
    npz.insert("b", Array::f32(&[s], &f32s(b)));
    let fam: Vec<i32> = topology.family.iter().map(|f| f.code()).collect();
    npz.insert("family", Array::i32(&[s], &fam));
    let uv: Vec<f32> = topology
        .rest_uv
        .iter()
        .flat_map(|p| [p[0] as f32, p[1] as f32])
        .collect();
    npz.insert("rest_uv", Array::f32(&[topology.num_particles(), 2], &uv));
    npz.insert(
        "grid",
        Array::i32(&[2], &[topology.nx as i32, topology.ny as i32]),
    );
    npz.insert("width", Array::scalar(topology.width));
    npz.insert("height", Array::scalar(topology.height));
    npz.insert("particle_mass", Array::scalar(particle_mass));
    npz
}

/// Peak resident set size of this process, MiB (`VmHWM`), or 0 where unknown.
pub fn peak_rss_mib() -> f64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("VmHWM:"))
                .and_then(|l| l.split_whitespace().nth(1))
                .and_then(|kb| kb.parse::<f64>().ok())
        })
        .map_or(0.0, |kb| kb / 1024.0)
}
