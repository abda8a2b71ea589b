//! A run directory: `runs/<name>/` with the resolved config, metrics, checkpoints and the
//! trained surrogate. A finished run is never overwritten unless asked.

use std::io::Write;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use burn::module::Module;
use serde::{Deserialize, Serialize};

use crate::cloth::Topology;
use crate::data::npz::{Array, Npz};
use crate::model::gnn::GnnStats;
use crate::model::neural_ode::OdeScales;
use crate::model::{ModelKind, SpringNet};

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

/// One row of `metrics.csv`: one training iteration (read and written with the `csv` crate;
/// columns are matched by header name).
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct MetricsRow {
    /// Iteration over all passes, from 1.
    pub iteration: usize,
    /// Pass name (`stiffness`, `damping`, `single`, `gnn`).
    pub pass: String,
    /// The weighted loss.
    pub loss: f64,
    /// Force loss.
    pub force: f64,
    /// Impulse loss.
    pub impulse: f64,
    /// Position loss.
    pub position: f64,
    /// Negative-stiffness penalty.
    pub k_neg: f64,
    /// Negative-damping penalty.
    pub b_neg: f64,
    /// RMSE of `k` against the data's springs, when it has them.
    pub rmse_k: Option<f64>,
    /// RMSE of `b`, when known.
    pub rmse_b: Option<f64>,
    /// Training wall time so far, s.
    #[serde(default)]
    pub seconds: f64,
    /// Springs clamped back into the stable region after this step.
    #[serde(default)]
    pub clamped: usize,
}

impl MetricsRow {
    /// The loss terms by column name, the weighted sum first.
    pub fn terms(&self) -> [(&'static str, f64); 6] {
        [
            ("loss", self.loss),
            ("force", self.force),
            ("impulse", self.impulse),
            ("position", self.position),
            ("k_neg", self.k_neg),
            ("b_neg", self.b_neg),
        ]
    }
}

/// Metrics columns, in order (the header [`MetricsRow`] writes).
pub(crate) const METRICS_HEADER: &str =
    "iteration,pass,loss,force,impulse,position,k_neg,b_neg,rmse_k,rmse_b,seconds,clamped";

/// Reads a `metrics.csv` (columns by header name). With `lenient`, rows that do not parse (the
/// last line of a killed process) are dropped; otherwise they are errors that name the file and
/// line.
pub fn read_metrics(path: &Path, lenient: bool) -> Result<Vec<MetricsRow>> {
    let mut reader = csv::ReaderBuilder::new()
        .flexible(lenient)
        .from_path(path)
        .with_context(|| format!("cannot read {} (the run's metrics)", path.display()))?;
    let mut rows = Vec::new();
    for row in reader.deserialize::<MetricsRow>() {
        match row {
            Ok(r) => rows.push(r),
            Err(_) if lenient => {}
            Err(e) => {
                let line = e.position().map_or(0, |p| p.line());
                bail!("{}: line {line} is malformed: {e}", path.display());
            }
        }
    }
    Ok(rows)
}

/// Writes `rows` to `to` as CSV, with the header when `header`.
fn write_metrics<W: Write>(to: W, rows: &[MetricsRow], header: bool) -> Result<()> {
    let mut w = csv::WriterBuilder::new()
        .has_headers(header)
        .from_writer(to);
    if header && rows.is_empty() {
        w.write_record(METRICS_HEADER.split(','))?;
    }
    for r in rows {
        w.serialize(r)?;
    }
    w.flush()?;
    Ok(())
}

/// An exclusive hold on a run directory for one training process: an OS file lock on
/// `.<name>.lock` beside the directory (see [`crate::io::FileLock`]).
pub(crate) type RunLock = crate::io::FileLock;

impl RunDir {
    /// A run directory at `dir` (not created yet).
    pub fn new(dir: impl Into<PathBuf>) -> Self {
        Self { dir: dir.into() }
    }

    /// The lock file guarding the directory: `.<name>.lock` in its parent.
    pub(crate) fn lock_path(&self) -> PathBuf {
        crate::io::lock_path_beside(&self.dir, "lock", "run")
    }

    /// Takes the directory for this process, or fails when another process holds it (two
    /// `train` processes on one run would interleave their writes).
    pub fn lock(&self) -> Result<RunLock> {
        let path = self.lock_path();
        match RunLock::try_take(&path)? {
            Some(lock) => Ok(lock),
            None => bail!(
                "another springtime process is training in {} (it holds {}); wait for it to \
                 end or train into another --out",
                self.dir.display(),
                path.display()
            ),
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

    /// `least_squares.json`: the per-spring least-squares start (`train.least_squares`).
    pub fn least_squares(&self) -> PathBuf {
        self.dir.join("least_squares.json")
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
    /// `springs.learned.npz`: the learned springs, where the run keeps the best uniform network
    /// instead (`train.uniform_fallback`).
    pub fn learned_springs(&self) -> PathBuf {
        self.dir.join("springs.learned.npz")
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
    pub(crate) fn write_state(&self, state: &RunState) -> Result<()> {
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
    pub(crate) fn create_fresh(&self) -> Result<()> {
        if self.dir.exists() {
            std::fs::remove_dir_all(&self.dir)
                .with_context(|| format!("cannot clear {}", self.dir.display()))?;
        }
        std::fs::create_dir_all(self.dir.join("checkpoints"))
            .with_context(|| format!("cannot create {}", self.dir.display()))?;
        self.write_metrics(&[])
    }

    /// Replaces `metrics.csv` by `rows` (atomically, with the header).
    fn write_metrics(&self, rows: &[MetricsRow]) -> Result<()> {
        crate::io::write_atomic_with_path(&self.metrics(), |tmp| {
            write_metrics(std::fs::File::create(tmp)?, rows, true)
        })
    }

    /// Keeps the metrics rows up to `iteration` (used when resuming from a checkpoint; a row
    /// cut short by a kill is dropped).
    pub(crate) fn truncate_metrics(&self, iteration: usize) -> Result<()> {
        let path = self.metrics();
        let rows = if path.exists() {
            read_metrics(&path, true)?
        } else {
            Vec::new()
        };
        let keep: Vec<MetricsRow> = rows
            .into_iter()
            .filter(|r| r.iteration <= iteration)
            .collect();
        self.write_metrics(&keep)
    }

    /// Appends metrics rows.
    pub(crate) fn append_metrics(&self, rows: &[MetricsRow]) -> Result<()> {
        if rows.is_empty() {
            return Ok(());
        }
        let f = std::fs::OpenOptions::new()
            .append(true)
            .create(true)
            .open(self.metrics())
            .with_context(|| format!("cannot append to {}", self.metrics().display()))?;
        write_metrics(f, rows, false)
            .with_context(|| format!("cannot append to {}", self.metrics().display()))
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
/// sheet (`rest_uv` `[P, 2]`, `grid` = `[nx, ny]` on a grid, `triangles` `[M, 3]`, `width`,
/// `height`, `particle_mass` (the mean), `family`); with curvature elements also `curvature`
/// `[T, 3]` (`i, j, l`) and `curvature_k` `[T]`.
pub fn write_springs(
    path: &Path,
    topology: &Topology,
    model: &SpringNet,
    particle_mass: f64,
) -> Result<()> {
    springs_npz(topology, model, particle_mass).write(path)
}

/// The arrays of [`write_springs`], to write or to extend.
pub fn springs_npz(topology: &Topology, model: &SpringNet, particle_mass: f64) -> Npz {
    let (k, b) = (&model.k_values()[..], &model.b_values()[..]);
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
    if let Some([nx, ny]) = topology.grid {
        npz.insert("grid", Array::i32(&[2], &[nx as i32, ny as i32]));
    }
    let tris: Vec<i32> = topology
        .triangles
        .iter()
        .flatten()
        .map(|&v| v as i32)
        .collect();
    npz.insert(
        "triangles",
        Array::i32(&[topology.triangles.len(), 3], &tris),
    );
    npz.insert("width", Array::scalar(topology.width));
    npz.insert("height", Array::scalar(topology.height));
    npz.insert("particle_mass", Array::scalar(particle_mass));
    if !topology.curvature.is_empty() {
        let t = topology.curvature.len();
        let ends: Vec<i32> = topology
            .curvature
            .iter()
            .flatten()
            .map(|&v| v as i32)
            .collect();
        npz.insert("curvature", Array::i32(&[t, 3], &ends));
        npz.insert(
            "curvature_k",
            Array::f32(&[t], &f32s(&model.curvature_values())),
        );
    }
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn metrics_rows_round_trip_by_column_name_and_errors_name_the_line() {
        let dir = tempfile::tempdir().unwrap();
        let run = RunDir::new(dir.path().join("run"));
        run.create_fresh().unwrap();
        let text = std::fs::read_to_string(run.metrics()).unwrap();
        assert_eq!(text.trim_end(), METRICS_HEADER);
        let row = |iteration, pass: &str, rmse| MetricsRow {
            iteration,
            pass: pass.into(),
            loss: 1e-2 / iteration as f64,
            force: 3.25e-3,
            rmse_k: rmse,
            rmse_b: rmse,
            seconds: 0.1 * iteration as f64,
            ..MetricsRow::default()
        };
        let rows = vec![row(1, "stiffness", Some(3.5)), row(2, "damping, 2nd", None)];
        run.append_metrics(&rows).unwrap();
        assert_eq!(read_metrics(&run.metrics(), false).unwrap(), rows);
        // Columns are found by name, in any order; a row cut short by a kill is dropped on
        // resume and is an error naming the line otherwise.
        std::fs::write(
            run.metrics(),
            "pass,iteration,loss,force,impulse,position,k_neg,b_neg,rmse_k,rmse_b\n\
             single,1,1,2,3,4,5,6,,\nsingle,2,1,2",
        )
        .unwrap();
        let read = read_metrics(&run.metrics(), true).unwrap();
        assert_eq!(read.len(), 1);
        assert_eq!(
            (read[0].iteration, read[0].b_neg, read[0].rmse_k),
            (1, 6.0, None)
        );
        let e = format!("{:#}", read_metrics(&run.metrics(), false).unwrap_err());
        assert!(e.contains("metrics.csv") && e.contains("line 3"), "{e}");
        run.truncate_metrics(5).unwrap();
        assert_eq!(read_metrics(&run.metrics(), false).unwrap().len(), 1);
    }
}
