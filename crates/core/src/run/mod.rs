//! A finished run opened once ([`Run`]): the one way every command that uses a trained model
//! reads it — `eval` ([`evaluate`]), `simulate`, `report`, `export`, `diagnose`, `drape`,
//! `fold`, the Python `load_run` — and what is derived from it: the whole-run evaluation and
//! the portable `surrogate.json` ([`surrogate`]). Above [`crate::train`] and [`crate::eval`].

mod evaluate;
pub mod surrogate;
mod yardstick;

use crate::settings::Job;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, anyhow, bail};
use burn::module::Module;
use burn::tensor::Device;

use crate::backend::Backend;
use crate::cloth::{SpringLayout, Topology};
use crate::config::Config;
use crate::data::npz::Npz;
use crate::model::{ModelKind, SpringNet};
use crate::sim::Physics;
use crate::train::{ModelMeta, RunDir, RunState, Trained};

pub use evaluate::evaluate;
pub use surrogate::SurrogateJson;

/// A finished run opened once, for every command that uses a trained model (`eval`,
/// `simulate`, `report`, `export`, `diagnose`, `drape`, `fold`, the Python `load_run`): its
/// directory, configuration (with `--set` and `--backend` applied), device, grid, model and
/// constants.
pub struct Run {
    /// The directory's paths.
    pub dir: RunDir,
    /// `run.json` (status `finished`).
    pub state: RunState,
    /// The run's configuration (with `--set` overrides and `--backend`).
    pub config: Config,
    /// The device the model lives on (`config.backend`).
    pub device: Device,
    /// The particles' grid.
    pub topology: Topology,
    /// The model.
    pub model: Trained,
    /// The model's constants (`model.json`).
    pub meta: ModelMeta,
}

impl Run {
    /// Opens the finished run in `run_dir`: refuses a directory that is not a run or whose run
    /// is not finished (naming the file), reads `config.toml` with `set` applied, places the
    /// model on `backend` (the config's when `None`) and loads it (`springs.npz` for a spring
    /// network, `model.bpk` for a baseline).
    pub fn open(run_dir: &Path, set: &[String], backend: Option<Backend>) -> Result<Self> {
        let dir = RunDir::new(run_dir);
        let state = dir.finished()?;
        let mut config = Config::load(&dir.config(), set)
            .with_context(|| format!("{} is not a run directory", run_dir.display()))?;
        if let Some(b) = backend {
            config.backend = b;
        }
        let device = config.backend.device()?;
        let incomplete = |file: PathBuf| -> Result<()> {
            if !file.exists() {
                bail!(
                    "{} not found: the run in {} is incomplete",
                    file.display(),
                    run_dir.display()
                );
            }
            Ok(())
        };
        incomplete(dir.meta())?;
        let meta = ModelMeta::read(&dir.meta())?;
        incomplete(match meta.kind {
            ModelKind::Springs => dir.springs(),
            _ => dir.model(),
        })?;
        let topology = match (config.cloth.layout, meta.kind) {
            (SpringLayout::Grid, _) => Topology::grid(&config.cloth, meta.width, meta.height),
            (SpringLayout::Data, ModelKind::Springs) => {
                read_mesh_topology(&dir.springs())?.with_masses(config.cloth.masses)
            }
            (SpringLayout::Data, kind) => bail!(
                "{}: a {} run with cloth.layout = \"data\" (only the spring surrogate takes the \
                 data's mesh)",
                run_dir.display(),
                kind.name()
            ),
        };
        let model = match meta.kind {
            ModelKind::Springs => {
                Trained::Springs(read_springs(&dir, &config, &topology, &device)?)
            }
            kind => {
                let path = dir.model();
                let record = burn::store::ModuleRecord::load(&path)
                    .map_err(|e| anyhow::anyhow!("{} has no trained model: {e}", path.display()))?;
                let load_err =
                    |e| anyhow::anyhow!("{} does not fit the run's config: {e}", path.display());
                match kind {
                    ModelKind::NeuralOde => Trained::NeuralOde(
                        meta.neural_ode(&config, &device)
                            .try_load_record(record)
                            .map_err(load_err)?,
                    ),
                    _ => Trained::Gnn(
                        meta.gnn(&config, &device)?
                            .try_load_record(record)
                            .map_err(load_err)?,
                    ),
                }
            }
        };
        Ok(Self {
            dir,
            state,
            config,
            device,
            topology,
            model,
            meta,
        })
    }

    /// The spring network, or a refusal naming the run for a baseline (commands that need
    /// per-spring `k` and `b`).
    pub fn springs(&self) -> Result<&SpringNet> {
        match &self.model {
            Trained::Springs(m) => Ok(m),
            _ => bail!(
                "{} holds a {} model, not a spring surrogate: only `springtime eval`, `compare` \
                 and `drape` take baseline runs",
                self.dir.dir.display(),
                self.meta.kind.name()
            ),
        }
    }

    /// Mass of one particle, kg.
    pub fn particle_mass(&self) -> f64 {
        self.meta.particle_mass
    }

    /// The integrator constants of the run's model at a data frame step of `frame_dt`.
    pub fn physics(&self, frame_dt: f64) -> Physics {
        Physics::new(&self.config.sim, frame_dt, self.meta.particle_mass)
    }
}

/// The data-mesh topology stored in a surrogate's `springs.npz` (`cloth.layout = "data"`).
fn read_mesh_topology(path: &Path) -> Result<Topology> {
    let npz = Npz::read(path)?;
    let at = |e: anyhow::Error| e.context(format!("{}", path.display()));
    let (uv, _) = npz.f32("rest_uv", &[None, Some(2)]).map_err(at)?;
    let rest_uv: Vec<[f64; 2]> = uv
        .chunks_exact(2)
        .map(|c| [c[0] as f64, c[1] as f64])
        .collect();
    let (tri, _) = npz.int("triangles", &[None, Some(3)]).map_err(at)?;
    let triangles: Vec<[usize; 3]> = tri
        .chunks_exact(3)
        .map(|c| [c[0] as usize, c[1] as usize, c[2] as usize])
        .collect();
    let (width, height) = (
        npz.scalar("width").map_err(at)?,
        npz.scalar("height").map_err(at)?,
    );
    // The springs are the mesh's edges, and hinge springs where there are more of them.
    let (ends, _) = npz.int("springs", &[None, Some(2)]).map_err(at)?;
    let hinges = ends.len() > 2 * crate::cloth::triangles::edges_with_opposites(&triangles).len();
    let topo = Topology::mesh(&rest_uv, &triangles, width, height, hinges)
        .map_err(|e| anyhow!("{}: {e}", path.display()))?;
    let same = ends.len() == 2 * topo.num_springs()
        && ends
            .chunks_exact(2)
            .zip(&topo.springs)
            .all(|(e, s)| e[0] as usize == s[0] && e[1] as usize == s[1]);
    if !same {
        bail!(
            "{}: key `springs` does not match the springs of its `triangles`",
            path.display()
        );
    }
    Ok(topo)
}

/// The trained spring network of a run from its `springs.npz`.
fn read_springs(
    dir: &RunDir,
    config: &Config,
    topology: &Topology,
    device: &Device,
) -> Result<SpringNet> {
    let path = dir.springs();
    let npz = Npz::read(&path)
        .with_context(|| format!("{} has no trained surrogate", dir.dir.display()))?;
    let s = topology.num_springs();
    let read = |key: &str| -> Result<Vec<f64>> {
        Ok(npz
            .f32(key, &[Some(s)])?
            .0
            .into_iter()
            .map(f64::from)
            .collect())
    };
    if npz.has("curvature") {
        let (ends, _) = npz.int("curvature", &[Some(topology.curvature.len()), Some(3)])?;
        let same = ends
            .chunks(3)
            .zip(&topology.curvature)
            .all(|(a, b)| a.iter().zip(b).all(|(&x, &y)| x == y as i64));
        if !same {
            bail!(
                "{}: its curvature elements are not those of the run's grid",
                path.display()
            );
        }
    }
    let kappa = match topology.curvature.len() {
        0 => Vec::new(),
        t => npz
            .f32("curvature_k", &[Some(t)])
            .with_context(|| {
                format!(
                    "{}: the run's config has `cloth.curvature = true`",
                    path.display()
                )
            })?
            .0
            .into_iter()
            .map(f64::from)
            .collect(),
    };
    Ok(SpringNet::new(topology, &read("k")?, &read("b")?, device)
        .with_kernel(config.model.kernel)
        .with_curvature(&kappa))
}
