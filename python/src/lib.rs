//! Python bindings of springtime (`import springtime`): load a finished run, simulate it from
//! NumPy arrays or from a rollout file, and start training or evaluation from a config path.
//!
//! Every entry point is a thin wrapper of the library calls the command line makes; errors are
//! raised as `RuntimeError` (`ValueError` for arrays of the wrong shape) with springtime's
//! message, which names the file, key or field.

use springtime::settings::Job;
use std::path::PathBuf;

use numpy::{PyArray1, PyArrayDyn, PyArrayMethods, PyReadonlyArrayDyn, PyUntypedArrayMethods};
use pyo3::exceptions::{PyRuntimeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyAny;

use springtime::cloth::Resampler;
use springtime::config::Config;
use springtime::data::{Rollout, Track};
use springtime::model::ForceModel;
use springtime::progress::Progress;
use springtime::sim::Physics;
use springtime::train::{self, TrainOptions, Trained};

/// springtime's error, with its chain of causes, as a Python `RuntimeError`.
fn runtime(e: anyhow::Error) -> PyErr {
    PyRuntimeError::new_err(format!("{e:#}"))
}

/// `obj` as a C-contiguous float32 array (any array-like NumPy accepts), with its shape.
fn f32_array(
    py: Python<'_>,
    obj: &Bound<'_, PyAny>,
    name: &str,
) -> PyResult<(Vec<f32>, Vec<usize>)> {
    let np = py.import("numpy")?;
    let arr = np
        .call_method1("ascontiguousarray", (obj, "float32"))
        .map_err(|e| PyValueError::new_err(format!("`{name}` is not a numeric array: {e}")))?;
    let arr: PyReadonlyArrayDyn<'_, f32> = arr.extract()?;
    let shape = arr.shape().to_vec();
    let values = arr.as_slice()?.to_vec();
    Ok((values, shape))
}

/// A `[*shape]` float32 NumPy array holding `values`.
fn f32_out<'py>(
    py: Python<'py>,
    values: Vec<f32>,
    shape: &[usize],
) -> PyResult<Bound<'py, PyArrayDyn<f32>>> {
    PyArray1::from_vec(py, values).reshape(shape.to_vec())
}

/// A finished training run, opened once: its configuration, particle grid and trained model.
///
/// Spring networks and Neural ODEs can be simulated; every run kind can be evaluated.
#[pyclass(name = "Run", module = "springtime", unsendable)]
struct Run {
    path: PathBuf,
    loaded: springtime::run::Run,
}

impl Run {
    fn force_model(&self) -> PyResult<&dyn ForceModel> {
        match &self.loaded.model {
            Trained::Springs(m) => Ok(m),
            Trained::NeuralOde(m) => Ok(m),
            Trained::Gnn(_) => Err(PyRuntimeError::new_err(format!(
                "{} holds a GNN, which steps by its own learned update: simulate a spring or \
                 Neural ODE run",
                self.path.display()
            ))),
        }
    }

    /// The physics a simulation with frames `frame_dt` apart uses (the run's gravity, Rayleigh
    /// damping and substeps), refused when the trained springs are unstable at that step.
    fn physics(&self, frame_dt: f64) -> PyResult<Physics> {
        let cfg = &self.loaded.config;
        let physics = Physics::new(&cfg.sim, frame_dt, self.loaded.meta.particle_mass);
        if let Trained::Springs(springs) = &self.loaded.model {
            physics
                .stability_of(&self.loaded.topology, springs)
                .check("the trained surrogate", cfg.sim.allow_unstable)
                .map_err(runtime)?;
        }
        Ok(physics)
    }

    /// Simulates `frames` frames of `track` from its frame `first`; returns positions and
    /// velocities `[frames + 1, P, 3]`.
    fn run_track<'py>(
        &self,
        py: Python<'py>,
        track: &Track,
        first: usize,
        frames: usize,
        frame_dt: f64,
    ) -> PyResult<(Bound<'py, PyArrayDyn<f32>>, Bound<'py, PyArrayDyn<f32>>)> {
        let physics = self.physics(frame_dt)?;
        let model = self.force_model()?;
        let sim = springtime::eval::FreeRun::new(track, first, frames)
            .simulate(model, &physics, &self.loaded.device, |_| {})
            .map_err(runtime)?;
        let shape = [frames + 1, track.particles, 3];
        Ok((
            f32_out(py, sim.positions, &shape)?,
            f32_out(py, sim.velocities, &shape)?,
        ))
    }
}

#[pymethods]
impl Run {
    /// The run directory.
    #[getter]
    fn path(&self) -> String {
        self.path.display().to_string()
    }

    /// The model family: `springs`, `neural_ode` or `gnn`.
    #[getter]
    fn kind(&self) -> &'static str {
        self.loaded.meta.kind.name()
    }

    /// Particles of the surrogate (grid or data mesh).
    #[getter]
    fn particles(&self) -> usize {
        self.loaded.topology.num_particles()
    }

    /// Mean mass of a particle, kg (every particle's on a grid surrogate).
    #[getter]
    fn particle_mass(&self) -> f64 {
        self.loaded.meta.particle_mass
    }

    /// Mass of each particle, kg, `[P]`: equal on a grid surrogate, the lumped rest areas' share
    /// of the total on a data mesh (`cloth.layout = "data"`).
    #[getter]
    fn masses(&self) -> Vec<f64> {
        self.loaded.topology.masses(self.loaded.meta.particle_mass)
    }

    /// Time between the training data's frames, s (the default step of `simulate`).
    #[getter]
    fn frame_dt(&self) -> f64 {
        self.loaded.meta.frame_dt
    }

    /// The constants `simulate` steps with, as a dict: `frame_dt` (s), `substeps` per frame,
    /// `dt` (s per step), `mass` (kg, the mean particle's; see `masses`), `rayleigh` (N·s/m on
    /// a particle of the mean mass, the force `−rayleigh·v`; per unit mass the same on every
    /// particle), `gravity` (m/s², 3 components) and `viscosity` (s: each spring's isotropic
    /// damper `viscosity · k (v_b − v_a)`, `sim.viscosity`; 0 without) and `shear_compression`
    /// (the shear springs' stiffness in compression per unit `k`, `sim.shear_compression`; 1:
    /// linear springs).
    #[getter(physics)]
    fn physics_constants<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, pyo3::types::PyDict>> {
        let p = Physics::new(
            &self.loaded.config.sim,
            self.loaded.meta.frame_dt,
            self.loaded.meta.particle_mass,
        );
        let d = pyo3::types::PyDict::new(py);
        d.set_item("frame_dt", p.frame_dt)?;
        d.set_item("substeps", p.substeps)?;
        d.set_item("dt", p.sim_dt())?;
        d.set_item("mass", p.mass)?;
        d.set_item("rayleigh", p.rayleigh)?;
        d.set_item("gravity", p.gravity.to_vec())?;
        d.set_item("viscosity", p.viscosity)?;
        d.set_item("shear_compression", p.shear_compression)?;
        Ok(d)
    }

    /// Rest positions of the particles, `[P, 3]` (the rest rectangle in the z = 0 plane).
    #[getter]
    fn rest<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArrayDyn<f32>>> {
        let topo = &self.loaded.topology;
        let flat = topo
            .rest_positions()
            .iter()
            .flatten()
            .map(|&c| c as f32)
            .collect();
        f32_out(py, flat, &[topo.num_particles(), 3])
    }

    /// Spring end points, `[S, 2]` particle indices.
    #[getter]
    fn springs<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArrayDyn<i64>>> {
        let topo = &self.loaded.topology;
        let flat: Vec<i64> = topo.springs.iter().flatten().map(|&i| i as i64).collect();
        PyArray1::from_vec(py, flat).reshape(vec![topo.num_springs(), 2])
    }

    /// Per-spring stiffness `k`, N/m (`[S]`; spring runs only).
    #[getter]
    fn k<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray1<f64>>> {
        Ok(PyArray1::from_vec(py, self.spring_net()?.k_values()))
    }

    /// Per-spring damping `b`, N·s/m (`[S]`; spring runs only).
    #[getter]
    fn b<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray1<f64>>> {
        Ok(PyArray1::from_vec(py, self.spring_net()?.b_values()))
    }

    /// Simulates the surrogate for `frames` frames from positions `x0` `[P, 3]`.
    ///
    /// `v0` `[P, 3]` are the initial velocities (zero by default); `pinned` `[P]` marks the
    /// particles that follow `path` `[F, P, 3]` (frame j of the simulation takes path frame
    /// min(j, F − 1); without a path the pinned particles hold `x0`); `frame_dt` is the time
    /// between returned frames (the training data's by default). Returns `(positions,
    /// velocities)`, each `[frames + 1, P, 3]` float32, frame 0 being the initial state.
    #[pyo3(signature = (x0, frames, *, v0=None, pinned=None, path=None, frame_dt=None))]
    #[allow(clippy::too_many_arguments)]
    fn simulate<'py>(
        &self,
        py: Python<'py>,
        x0: &Bound<'py, PyAny>,
        frames: usize,
        v0: Option<&Bound<'py, PyAny>>,
        pinned: Option<Vec<bool>>,
        path: Option<&Bound<'py, PyAny>>,
        frame_dt: Option<f64>,
    ) -> PyResult<(Bound<'py, PyArrayDyn<f32>>, Bound<'py, PyArrayDyn<f32>>)> {
        let p = self.particles();
        let state_shape = vec![p, 3];
        let (x0, shape) = f32_array(py, x0, "x0")?;
        if shape != state_shape {
            return Err(PyValueError::new_err(format!(
                "`x0` has shape {shape:?}; this run's surrogate has {p} particles: expected [{p}, 3]"
            )));
        }
        let v0 = match v0 {
            Some(v) => {
                let (v, shape) = f32_array(py, v, "v0")?;
                if shape != state_shape {
                    return Err(PyValueError::new_err(format!(
                        "`v0` has shape {shape:?}, expected [{p}, 3]"
                    )));
                }
                v
            }
            None => vec![0.0; p * 3],
        };
        let pinned = pinned.unwrap_or_else(|| vec![false; p]);
        if pinned.len() != p {
            return Err(PyValueError::new_err(format!(
                "`pinned` has {} entries, expected {p}",
                pinned.len()
            )));
        }
        let (positions, path_frames) = match path {
            Some(path) => {
                let (mut values, shape) = f32_array(py, path, "path")?;
                if shape.len() != 3 || shape[1] != p || shape[2] != 3 || shape[0] == 0 {
                    return Err(PyValueError::new_err(format!(
                        "`path` has shape {shape:?}, expected [F, {p}, 3] with F ≥ 1"
                    )));
                }
                // Frame 0 is the initial state itself; the path moves the pinned particles.
                values[..p * 3].copy_from_slice(&x0);
                (values, shape[0])
            }
            None => (x0, 1),
        };
        let mut velocities = vec![0.0; path_frames * p * 3];
        velocities[..p * 3].copy_from_slice(&v0);
        let track = Track {
            frames: path_frames,
            particles: p,
            positions,
            velocities,
            // Only frame 0's are given (the path's frames move pinned particles only).
            stored_velocities: false,
            pinned,
            visible: None,
        };
        let frame_dt = frame_dt.unwrap_or(self.loaded.meta.frame_dt);
        if !(frame_dt > 0.0 && frame_dt.is_finite()) {
            return Err(PyValueError::new_err(format!(
                "`frame_dt` must be positive, is {frame_dt}"
            )));
        }
        self.run_track(py, &track, 0, frames, frame_dt)
    }

    /// Simulates the surrogate from the first usable frame of a rollout file (resampled to the
    /// particles, pinned particles following the file's path), as `springtime simulate` does.
    /// `frames` defaults to the file's length. Returns `(positions, velocities)`, each
    /// `[frames + 1, P, 3]`.
    #[pyo3(signature = (rollout, frames=None))]
    fn simulate_file<'py>(
        &self,
        py: Python<'py>,
        rollout: PathBuf,
        frames: Option<usize>,
    ) -> PyResult<(Bound<'py, PyArrayDyn<f32>>, Bound<'py, PyArrayDyn<f32>>)> {
        let data = Rollout::load(&rollout).map_err(runtime)?;
        let res = Resampler::new(&data.rest_uv, &self.loaded.topology.rest_uv);
        let track = Track::new(&data, &res);
        let first = if data.velocities.is_some() { 0 } else { 1 };
        let frames = frames.unwrap_or(data.frames.saturating_sub(first + 1));
        self.run_track(py, &track, first, frames, data.frame_dt)
    }

    /// Evaluates the run on its test rollouts (or those in `data`), writes its `eval.json` and
    /// returns it as a dict.
    #[pyo3(signature = (data=None))]
    fn evaluate<'py>(&self, py: Python<'py>, data: Option<PathBuf>) -> PyResult<Bound<'py, PyAny>> {
        evaluate(py, self.path.clone(), data)
    }

    fn __repr__(&self) -> String {
        format!(
            "springtime.Run('{}', kind={}, particles={})",
            self.path.display(),
            self.kind(),
            self.particles()
        )
    }
}

impl Run {
    fn spring_net(&self) -> PyResult<&springtime::model::SpringNet> {
        match &self.loaded.model {
            Trained::Springs(m) => Ok(m),
            _ => Err(PyRuntimeError::new_err(format!(
                "{} holds a {} model, which has no per-spring k and b",
                self.path.display(),
                self.kind()
            ))),
        }
    }
}

/// Opens a finished run directory. `backend` (`flex`, `ndarray` or `wgpu`) overrides the one
/// the run was trained on.
#[pyfunction]
#[pyo3(signature = (path, backend=None))]
fn load_run(path: PathBuf, backend: Option<String>) -> PyResult<Run> {
    let overrides: Vec<String> = backend.iter().map(|b| format!("backend={b}")).collect();
    let loaded = springtime::run::Run::open(&path, &overrides, None).map_err(runtime)?;
    Ok(Run { path, loaded })
}

/// Trains the model of a config file (as `springtime train`), evaluates it unless
/// `evaluate=False`, and returns the opened run. `set` holds `key=value` overrides.
#[pyfunction]
#[pyo3(name = "train", signature = (config, *, out=None, set=None, force=false, resume=false, evaluate=true))]
fn train_config(
    py: Python<'_>,
    config: PathBuf,
    out: Option<PathBuf>,
    set: Option<Vec<String>>,
    force: bool,
    resume: bool,
    evaluate: bool,
) -> PyResult<Run> {
    let set = set.unwrap_or_default();
    let cfg = Config::load(&config, &set).map_err(runtime)?;
    let progress = Progress::auto();
    let summary = py
        .detach(|| train::train(&cfg, &TrainOptions { out, resume, force }, &progress))
        .map_err(runtime)?;
    if evaluate {
        let run_dir = summary.run_dir.clone();
        py.detach(|| springtime::run::evaluate(&run_dir, None, None, &[], &progress))
            .map_err(runtime)?;
    }
    load_run(summary.run_dir, None)
}

/// Evaluates a finished run (as `springtime eval`), writes its `eval.json` and returns it as a
/// dict; `data` is a folder of test rollouts other than the run's own.
#[pyfunction]
#[pyo3(signature = (run, data=None))]
fn evaluate(py: Python<'_>, run: PathBuf, data: Option<PathBuf>) -> PyResult<Bound<'_, PyAny>> {
    let progress = Progress::auto();
    let report = py
        .detach(|| springtime::run::evaluate(&run, data.as_deref(), None, &[], &progress))
        .map_err(runtime)?;
    let json = serde_json::to_string(&report).map_err(|e| runtime(e.into()))?;
    py.import("json")?.call_method1("loads", (json,))
}

/// A JSON value as the Python object `json.loads` makes of it.
fn json_to_py<'py>(py: Python<'py>, value: &serde_json::Value) -> PyResult<Bound<'py, PyAny>> {
    let text = serde_json::to_string(value).map_err(|e| runtime(e.into()))?;
    py.import("json")?.call_method1("loads", (text,))
}

fn load_plan(plan: &std::path::Path) -> PyResult<springtime::sweep::Plan> {
    springtime::sweep::Plan::load(plan).map_err(runtime)
}

/// A sweep plan's jobs in index order (as `springtime sweep PLAN --list`): a list of dicts with
/// `index`, `dir` (the folder name under the output) and `overrides`.
#[pyfunction]
fn sweep_list(py: Python<'_>, plan: PathBuf) -> PyResult<Bound<'_, PyAny>> {
    let plan = load_plan(&plan)?;
    let jobs = plan.jobs().map_err(runtime)?;
    let rows: Vec<serde_json::Value> = jobs
        .iter()
        .map(|j| serde_json::json!({"index": j.index, "dir": j.dir_name, "overrides": j.overrides}))
        .collect();
    json_to_py(py, &serde_json::Value::Array(rows))
}

/// The output folder a plan uses when none is given: `runs/<plan name>`.
#[pyfunction]
fn sweep_default_out(plan: PathBuf) -> PyResult<PathBuf> {
    Ok(springtime::sweep::default_out(&load_plan(&plan)?))
}

/// Runs job `index` of a sweep plan into `out/<index>-<slug>/` (as `springtime sweep PLAN
/// --index I --out OUT`): skips a finished job, resumes an interrupted one. Returns a dict:
/// `index`, `status` (`skipped` or `finished`), `dir`, and for a run job `seconds` and
/// `resumed`. A failed job raises `RuntimeError` (its `sweep_job.json` records the error).
#[pyfunction]
#[pyo3(signature = (plan, index, out=None))]
fn sweep_index(
    py: Python<'_>,
    plan: PathBuf,
    index: usize,
    out: Option<PathBuf>,
) -> PyResult<Bound<'_, PyAny>> {
    use springtime::sweep::{self, Outcome};
    let plan = load_plan(&plan)?;
    let out = out.unwrap_or_else(|| sweep::default_out(&plan));
    let progress = Progress::auto();
    let outcome = py
        .detach(|| sweep::run_index(&plan, index, &out, &progress, None))
        .map_err(runtime)?;
    let value = match outcome {
        Outcome::Skipped(dir) => {
            serde_json::json!({"index": index, "status": "skipped", "dir": dir})
        }
        Outcome::Finished(r) => serde_json::json!({
            "index": index,
            "status": "finished",
            "dir": out.join(plan.job(index).map_err(runtime)?.dir_name),
            "seconds": r.seconds,
            "resumed": r.resumed,
            "host": r.host,
        }),
    };
    json_to_py(py, &value)
}

/// Gathers a sweep (as `springtime sweep PLAN --gather --out OUT`, less the figure): writes
/// `sweep.csv` and `sweep.md` (`sweep.png` is drawn by the command line's gather) and returns the table's rows as dicts keyed by its columns
/// (`index`, one per axis, `status`, `rmse_k`, `rmse_b`, `motion_rmse_short`,
/// `motion_rmse_long`, …).
#[pyfunction]
#[pyo3(signature = (plan, out=None))]
fn sweep_gather(py: Python<'_>, plan: PathBuf, out: Option<PathBuf>) -> PyResult<Bound<'_, PyAny>> {
    let plan = load_plan(&plan)?;
    let out = out.unwrap_or_else(|| springtime::sweep::default_out(&plan));
    let gathered = py
        .detach(|| springtime::sweep::gather(&plan, &out))
        .map_err(runtime)?;
    json_to_py(py, &gathered.table.to_json())
}

/// The springtime version and the git commit the extension was built from.
#[pyfunction]
fn version() -> String {
    let b = springtime::BuildInfo::current();
    format!("{} ({})", b.version, b.commit)
}

/// The native part of the `springtime` package (re-exported by `springtime/__init__.py`):
/// `load_run`, `train`, `evaluate`, and the sweep contract (`sweep_list`, `sweep_index`,
/// `sweep_gather`) that `springtime.sweep` drives on Ray.
#[pymodule]
#[pyo3(name = "_springtime")]
fn springtime_py(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(sweep_list, m)?)?;
    m.add_function(wrap_pyfunction!(sweep_default_out, m)?)?;
    m.add_function(wrap_pyfunction!(sweep_index, m)?)?;
    m.add_function(wrap_pyfunction!(sweep_gather, m)?)?;
    m.add_class::<Run>()?;
    m.add_function(wrap_pyfunction!(load_run, m)?)?;
    m.add_function(wrap_pyfunction!(train_config, m)?)?;
    m.add_function(wrap_pyfunction!(evaluate, m)?)?;
    m.add_function(wrap_pyfunction!(version, m)?)?;
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    Ok(())
}
