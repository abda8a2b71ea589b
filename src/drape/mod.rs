//! The drape experiment (paper §4.5, Figs. 8 and 11): `springtime drape <run>… --scene S… --out D`.
//!
//! A trained model (spring surrogate or Neural ODE, trained on free, pinned rollouts only) is
//! released flat above colliders it never saw, without pins, and simulated with contact
//! ([`crate::sim::contact`]). The same happens to the run's source (the coarse FEM or
//! mass-spring cloth that made its data) and, for an FEM source, to a fine FEM mesh with the
//! same material at `scene.fine` times the resolution, and to the source with its material
//! perturbed by `scene.perturb` (the drape's sensitivity to parameter error). Every system
//! runs `scene.seconds` and then `scene.settle` more, so that it comes to rest. `drape.json`
//! has, per scene and model, the motion RMSE (Eq. 14) against the source over time and at
//! `seconds`, the steady-state RMSE against the source and the fine reference at the end (for
//! the models *and* the coarse source: the paper's claim is that the surrogate drapes closer to
//! the fine mesh than the coarse FEM that trained it), the deepest intrusion into the contact
//! layer, the kinetic energy and RMS speed at the end, whether it settled and whether it
//! diverged. Each model is also started at rest from the source's settled drape and left to
//! settle again (`relaxed_from_source`): how far its own equilibrium lies from the source's,
//! which separates the static part of its drape error from the part the fall's path left behind
//! (friction holds whatever the path laid down); each model and the source likewise from the
//! fine mesh's drape (`relaxed_from_fine`: the Fig. 8 comparison without a fall). `<scene>.png` shows the drapes at the end side
//! by side with the motion RMSE over time; `<scene>_motion_rmse.csv` has the curves.

pub mod scene;

pub use scene::{Scene, SceneConfig};

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result, bail};
use burn::tensor::Device;
use serde::Serialize;

use crate::backend::Backend;
use crate::cloth::Resampler;
use crate::data::Track;
use crate::eval;
use crate::model::ForceModel;
use crate::progress::Progress;
use crate::run::Run;
use crate::sim::{Contact, ContactAt, ContactParams, Physics};
use crate::source::{ClothSim, SourceConfig, SourceKind};
use crate::train::Trained;

type V3 = [f64; 3];

/// Command-line choices of a drape job.
#[derive(Debug, Clone, Default)]
pub struct DrapeOptions {
    /// Trained runs (the first one's source and step set the scene's references and defaults).
    pub runs: Vec<PathBuf>,
    /// Scene files.
    pub scenes: Vec<PathBuf>,
    /// Output directory.
    pub out: PathBuf,
    /// Overwrite a finished output directory.
    pub force: bool,
    /// Compute backend of the models (default: each run's).
    pub backend: Option<Backend>,
    /// Overrides of the scene files (`scene.seconds=2`).
    pub set: Vec<String>,
}

/// `drape.json`.
#[derive(Debug, Clone, Serialize)]
pub struct DrapeReport {
    /// Per scene (the file's stem).
    pub scenes: BTreeMap<String, SceneResult>,
    /// The runs, in command-line order.
    pub runs: Vec<PathBuf>,
    /// Wall time of the command, s.
    pub wall_seconds: f64,
    /// The build.
    pub build: crate::BuildInfo,
}

/// One scene's results.
#[derive(Debug, Clone, Serialize)]
pub struct SceneResult {
    /// The scene file.
    pub scene_file: PathBuf,
    /// The scene as run.
    pub scene: SceneConfig,
    /// Contact thickness δ, m.
    pub contact_thickness: f64,
    /// The resolved contact constants.
    pub contact: ContactParams,
    /// Interval of the recorded frames, s.
    pub record_dt: f64,
    /// The run's source (coarse FEM or mass-spring cloth), if the run has a `[source]`.
    pub source: Option<Reference>,
    /// The fine FEM reference (FEM sources only).
    pub fine: Option<Reference>,
    /// The source with its material perturbed by `scene.perturb` (when positive).
    pub perturbed: Option<Reference>,
    /// Per model kind (`springs`, `neural_ode`, `gnn`).
    pub models: BTreeMap<String, ModelResult>,
    /// Penetrations beyond the contact thickness and divergences, in words.
    pub warnings: Vec<String>,
    /// Wall time of the scene, s.
    pub wall_seconds: f64,
}

/// A reference simulator's drape.
#[derive(Debug, Clone, Serialize)]
pub struct Reference {
    /// `fem31x31`, `mass_spring32x32`, …
    pub label: String,
    /// Step, s.
    pub dt: f64,
    /// Steady-state (end) RMSE to the fine reference at this mesh's vertices, m.
    pub steady_rmse_vs_fine: Option<f64>,
    /// Steady-state (end) RMSE to the source at this mesh's vertices, m (0 for the source).
    pub steady_rmse_vs_source: Option<f64>,
    /// Deepest intrusion into the contact layer, m.
    pub max_penetration: f64,
    /// Kinetic energy at the end, J.
    pub kinetic_energy_end: Option<f64>,
    /// RMS speed at the end, `√(2 KE / M)`, m/s.
    pub speed_rms_end: Option<f64>,
    /// Whether it came to rest: RMS speed at the end below [`SETTLED_SPEED`].
    pub settled: bool,
    /// Whether it diverged.
    pub diverged: bool,
    /// The source only: started at rest from the fine reference's settled drape (its
    /// vertices are fine vertices) and left to settle; its `steady_rmse_vs_fine` is how far
    /// the coarse mesh's own equilibrium lies from the fine one's (membrane locking).
    pub relaxed_from_fine: Option<Relaxed>,
    /// Wall time of the simulation, s.
    pub wall_seconds: f64,
}

/// A model's drape.
#[derive(Debug, Clone, Serialize)]
pub struct ModelResult {
    /// The run directory.
    pub run: PathBuf,
    /// Whether the model can take contact (the GNN cannot: it predicts positions).
    pub applicable: bool,
    /// Motion RMSE (Eq. 14) to the source at the end of the experiment (`scene.seconds`), m.
    pub motion_rmse_end: Option<f64>,
    /// Mean of the motion RMSE over the recorded frames up to `scene.seconds`, m.
    pub motion_rmse_mean: Option<f64>,
    /// Steady-state RMSE to the fine FEM reference at the model's particles, after settling
    /// (`scene.seconds + scene.settle`), m.
    pub steady_rmse_vs_fine: Option<f64>,
    /// Steady-state RMSE to the source, after settling, m.
    pub steady_rmse_vs_source: Option<f64>,
    /// Deepest intrusion into the contact layer, m.
    pub max_penetration: Option<f64>,
    /// Kinetic energy at the end (after settling), J.
    pub kinetic_energy_end: Option<f64>,
    /// RMS speed at the end, `√(2 KE / M)`, m/s.
    pub speed_rms_end: Option<f64>,
    /// Whether it came to rest: RMS speed at the end below [`SETTLED_SPEED`].
    pub settled: bool,
    /// Whether the simulation diverged.
    pub diverged: bool,
    /// Why, if it diverged or does not apply.
    pub note: Option<String>,
    /// Motion RMSE to the source over time (settling included), `[t, rmse]`.
    pub motion_rmse_over_time: Vec<[f64; 2]>,
    /// The model started at rest from the source's drape at the end (static scenes, a source
    /// that did not diverge, `scene.settle` at least `scene.record_every`; otherwise `None` and
    /// a warning, as when that drape had not come to rest).
    pub relaxed_from_source: Option<Relaxed>,
    /// The model started at rest from the fine reference's settled drape (an FEM source, the
    /// same conditions): with the source's `relaxed_from_fine`, the Fig. 8 comparison without
    /// the path of a fall.
    pub relaxed_from_fine: Option<Relaxed>,
    /// Wall time of the simulation, s.
    pub wall_seconds: f64,
}

/// A system started at rest from another's settled drape (resampled to its particles) and
/// simulated `scene.settle` seconds with the same contact: its equilibrium near that drape.
/// Started from the source's drape, a small `steady_rmse_vs_source` beside a large one after
/// the fall says the model holds the source's drape and the difference comes from the path of
/// the fall (where the sheet landed and what friction then held); a large one says its statics
/// differ. Started from the fine mesh's, `steady_rmse_vs_fine` is how far the system's own
/// equilibrium lies from the fine one's.
#[derive(Debug, Clone, Serialize)]
pub struct Relaxed {
    /// RMSE at the end to the source's settled drape, m.
    pub steady_rmse_vs_source: Option<f64>,
    /// RMSE at the end to the fine reference's settled drape, m.
    pub steady_rmse_vs_fine: Option<f64>,
    /// RMS speed at the end, m/s.
    pub speed_rms_end: Option<f64>,
    /// Whether it came to rest: RMS speed at the end below [`SETTLED_SPEED`].
    pub settled: bool,
    /// Whether the simulation diverged.
    pub diverged: bool,
    /// Simulated time, s.
    pub seconds: f64,
}

/// What one simulation recorded.
#[derive(Debug, Clone)]
pub struct Recording {
    /// `fem31x31`, `springs`, …
    pub label: String,
    /// Rest positions of its vertices or particles.
    pub rest_uv: Vec<[f64; 2]>,
    /// The sheet's edges, for drawing.
    pub edges: Vec<[usize; 2]>,
    /// Recorded positions, `[P, 3]` per record.
    pub frames: Vec<Vec<f32>>,
    /// Kinetic energy at the end, J (None when diverged).
    pub kinetic_energy_end: Option<f64>,
    /// RMS speed at the end, `√(2 KE / M)`, m/s (None when diverged).
    pub speed_rms_end: Option<f64>,
    /// Deepest intrusion into the contact layer, m.
    pub deepest: f64,
    /// Why it stopped early.
    pub diverged: Option<String>,
    /// Step, s.
    pub dt: f64,
    /// Wall time, s.
    pub wall_seconds: f64,
}

/// RMS speed below which a drape counts as settled, m/s.
pub const SETTLED_SPEED: f64 = 0.01;

impl Recording {
    /// Sets the kinetic energy and RMS speed at the end from the velocities `v` (flat, three
    /// per particle) and the particles' masses.
    fn set_end_motion(&mut self, v: impl Iterator<Item = f64>, masses: &[f64]) {
        let v: Vec<f64> = v.collect();
        let ke: f64 = v
            .chunks_exact(3)
            .zip(masses)
            .map(|(c, m)| 0.5 * m * c.iter().map(|c| c * c).sum::<f64>())
            .sum();
        let total: f64 = masses.iter().sum();
        self.kinetic_energy_end = Some(ke);
        self.speed_rms_end = Some((2.0 * ke / total).sqrt());
    }

    /// Whether it finished at rest.
    fn settled(&self) -> bool {
        self.diverged.is_none() && self.speed_rms_end.is_some_and(|s| s < SETTLED_SPEED)
    }
}

/// Simulates a host cloth (a source) released at `x0`, for `steps` steps of `dt`, recording
/// every `every` steps.
#[allow(clippy::too_many_arguments)]
pub fn simulate_host(
    label: &str,
    sim: &dyn ClothSim,
    edges: Vec<[usize; 2]>,
    x0: Vec<V3>,
    contact: &Contact,
    dt: f64,
    steps: usize,
    every: usize,
    progress: &Progress,
) -> Recording {
    let start = Instant::now();
    let n = x0.len();
    let size = x0.iter().flatten().fold(1.0f64, |m, c| m.max(c.abs()));
    let limit = 1e3 * size;
    let (mut x, mut v) = (x0, vec![[0.0; 3]; n]);
    let pinned = vec![false; n];
    let mut scratch = Vec::new();
    let mut rec = Recording {
        label: label.into(),
        rest_uv: sim.rest_uv().to_vec(),
        edges,
        frames: Vec::new(),
        kinetic_energy_end: None,
        speed_rms_end: None,
        deepest: 0.0,
        diverged: None,
        dt,
        wall_seconds: 0.0,
    };
    let bar = progress.bar(steps as u64, label);
    for step in 0..=steps {
        if step % every == 0 {
            if x.iter()
                .flatten()
                .any(|c| !c.is_finite() || c.abs() > limit)
            {
                rec.diverged = Some(format!("{label} diverged by t = {:.3} s", step as f64 * dt));
                break;
            }
            rec.frames
                .push(x.iter().flat_map(|p| p.map(|c| c as f32)).collect());
        }
        if step == steps {
            break;
        }
        let at = ContactAt {
            contact,
            time: step as f64 * dt,
        };
        sim.step(&mut x, &mut v, &pinned, dt, Some(at), &mut scratch);
        if step % 256 == 0 {
            bar.set_position(step as u64);
        }
    }
    bar.finish();
    if rec.diverged.is_none() {
        let masses: Vec<f64> = (0..n).map(|i| sim.mass_of(i)).collect();
        rec.set_end_motion(v.iter().flatten().copied(), &masses);
    }
    rec.deepest = contact.deepest();
    rec.wall_seconds = start.elapsed().as_secs_f64();
    rec
}

/// Simulates a trained force model released at `x0` (its particles), for `frames` frames,
/// recording every `every` frames.
#[allow(clippy::too_many_arguments)]
pub fn simulate_model(
    label: &str,
    model: &dyn ForceModel,
    physics: &Physics,
    topology: &crate::cloth::Topology,
    x0: &[V3],
    contact: &Contact,
    frames: usize,
    every: usize,
    device: &Device,
    progress: &Progress,
) -> Recording {
    let start = Instant::now();
    let p = x0.len();
    let track = Track::at_rest(x0);
    let keep: Vec<usize> = (0..=frames).step_by(every).collect();
    let bar = progress.bar(frames as u64, label);
    let sim = eval::FreeRun::new(&track, 0, frames)
        .keeping(&keep)
        .contact(Some(contact))
        .simulate(model, physics, device, |j| {
            if j % 64 == 0 {
                bar.set_position(j as u64)
            }
        });
    bar.finish();
    let mut rec = Recording {
        label: label.into(),
        rest_uv: topology.rest_uv.clone(),
        edges: match topology.grid {
            Some([nx, ny]) => grid_edges(nx, ny),
            None => topology.edges(),
        },
        frames: Vec::new(),
        kinetic_energy_end: None,
        speed_rms_end: None,
        deepest: contact.deepest(),
        diverged: None,
        dt: physics.sim_dt(),
        wall_seconds: 0.0,
    };
    match sim {
        Ok(s) => {
            rec.frames = s.positions.chunks(p * 3).map(<[f32]>::to_vec).collect();
            let n = s.frames.len();
            let v_end = &s.velocities[(n - 1) * p * 3..];
            let masses = topology.masses(physics.mass);
            rec.set_end_motion(v_end.iter().map(|&c| c as f64), &masses);
            let size = x0.iter().flatten().fold(1.0f64, |m, c| m.max(c.abs()));
            if rec
                .frames
                .iter()
                .flatten()
                .any(|c| c.abs() as f64 > 1e3 * size)
            {
                rec.diverged = Some(format!(
                    "{label} left the scene (|x| > {:.0} m)",
                    1e3 * size
                ));
            }
        }
        Err(e) => rec.diverged = Some(format!("{label}: {e:#}")),
    }
    rec.wall_seconds = start.elapsed().as_secs_f64();
    rec
}

/// `src` frame (`res`'s landmarks) resampled to `res`'s particles.
fn resample(res: &Resampler, src: &[f32]) -> Vec<f32> {
    let mut out = vec![0.0f64; res.num_particles() * 3];
    res.apply3(src, &mut out);
    out.into_iter().map(|c| c as f32).collect()
}

/// The last frame of `rec` resampled to the particles at `rest_uv`, lifted out of the
/// colliders to where cloth under `gravity` rests in the contact layer: the start of a
/// relaxation.
fn relaxation_start(
    rec: &Recording,
    rest_uv: &[[f64; 2]],
    contact: &Contact,
    gravity: V3,
) -> Vec<V3> {
    let res = Resampler::new(&rec.rest_uv, rest_uv);
    let last = rec
        .frames
        .last()
        .expect("a relaxation starts from a recorded drape");
    let mut x0: Vec<V3> = resample(&res, last)
        .chunks(3)
        .map(|c| [c[0] as f64, c[1] as f64, c[2] as f64])
        .collect();
    // Where resting cloth sits: `g/κ` into the layer.
    let g = gravity.iter().map(|c| c * c).sum::<f64>().sqrt();
    let p = &contact.params;
    contact.lift_out(0.0, &mut x0, p.thickness - g / p.stiffness);
    x0
}

/// Why a GNN run has no drape.
const GNN_NOT_APPLICABLE: &str = "not applicable: the GNN predicts positions, not forces, so \
                                  contact forces cannot enter its step (as in the paper)";

/// A model's simulation in one scene: `recording` is `None` where contact does not apply.
struct Draped {
    kind: String,
    run: PathBuf,
    recording: Option<Recording>,
}

/// The source config of a run with the fine mesh's resolution, damping per unit mass kept.
fn fine_config(src: &SourceConfig, fine: usize) -> SourceConfig {
    let mut s = src.clone();
    s.nx = (src.nx - 1) * fine + 1;
    s.ny = (src.ny - 1) * fine + 1;
    s.rayleigh = src.rayleigh * (src.nx * src.ny) as f64 / (s.nx * s.ny) as f64;
    s
}

/// The largest step `dt / 2^j` (`j ≥ 0`) at which `sim` with `contact` is comfortably stable
/// (`dt²ω² + 2·dt·γ ≤ 3`).
fn stable_step(sim: &dyn ClothSim, params: &ContactParams, dt: f64) -> f64 {
    let mut h = dt;
    for _ in 0..12 {
        if sim.stability(h).with_contact(params).number() <= 3.0 {
            return h;
        }
        h *= 0.5;
    }
    h
}

fn label_of(src: &SourceConfig) -> String {
    let kind = match src.kind {
        SourceKind::Fem => "fem",
        SourceKind::MassSpring => "mass_spring",
    };
    format!("{kind}{}x{}", src.nx, src.ny)
}

/// Runs every scene for every run into `options.out` and writes `drape.json`.
pub fn run(options: &DrapeOptions, progress: &Progress) -> Result<DrapeReport> {
    let start = Instant::now();
    if options.runs.is_empty() || options.scenes.is_empty() {
        bail!("drape needs at least one run directory and one --scene");
    }
    let out = &options.out;
    let json = out.join("drape.json");
    if json.exists() && !options.force {
        bail!(
            "{} holds a finished drape; pass --force to run it again or --out to write elsewhere",
            out.display()
        );
    }
    let scenes = options
        .scenes
        .iter()
        .map(|p| Scene::load(p, &options.set))
        .collect::<Result<Vec<_>>>()?;
    let models = options
        .runs
        .iter()
        .map(|dir| Run::open(dir, &[], options.backend))
        .collect::<Result<Vec<_>>>()?;
    let job = Job::new(&models, progress)?;
    std::fs::create_dir_all(out).with_context(|| format!("cannot create {}", out.display()))?;
    let mut results = BTreeMap::new();
    for scene in &scenes {
        results.insert(scene.name.clone(), job.scene(scene, out)?);
    }
    let report = DrapeReport {
        scenes: results,
        runs: options.runs.clone(),
        wall_seconds: start.elapsed().as_secs_f64(),
        build: crate::BuildInfo::current(),
    };
    crate::io::write_json(&json, &report)?;
    // Let each run's report find this drape.
    let here = std::fs::canonicalize(out).unwrap_or_else(|_| out.clone());
    for m in &models {
        let list = m.dir.drapes();
        let mut dirs = read_drapes(&list);
        if !dirs.contains(&here) {
            dirs.push(here.clone());
            crate::io::write_json(&list, &dirs)?;
        }
    }
    Ok(report)
}

/// What every scene of one drape job shares: the runs, their common sheet and frame step, and
/// the source that generated their data.
struct Job<'a> {
    models: &'a [Run],
    width: f64,
    height: f64,
    frame_dt: f64,
    /// The surrogates' simulation step, s.
    step: f64,
    /// The stiffest surrogate's own stability number (the automatic contact keeps to the rest).
    number: f64,
    source: Option<SourceConfig>,
    progress: &'a Progress,
}

/// One scene's timing: frames simulated and recorded.
#[derive(Clone, Copy)]
struct Frames {
    /// Data frames simulated (settling included).
    total: usize,
    /// Data frames per recorded frame.
    every: usize,
    /// Index of the recorded frame at `scene.seconds` (the end of the motion RMSE's window).
    scored: usize,
    /// Time between recorded frames, s.
    record_dt: f64,
}

impl<'a> Job<'a> {
    /// Checks that the runs share one data set (sheet and frame step).
    fn new(models: &'a [Run], progress: &'a Progress) -> Result<Self> {
        let first = &models[0];
        let (width, height, frame_dt) = (first.meta.width, first.meta.height, first.meta.frame_dt);
        for m in models {
            if m.meta.frame_dt != frame_dt || m.meta.width != width || m.meta.height != height {
                bail!(
                    "{} has another frame step or sheet than {}: drape runs of one data set together",
                    m.dir.dir.display(),
                    first.dir.dir.display()
                );
            }
        }
        let number = models
            .iter()
            .filter_map(|m| match &m.model {
                Trained::Springs(s) => {
                    Some(m.physics(frame_dt).stability_of(&m.topology, s).number())
                }
                _ => None,
            })
            .fold(0.0, f64::max);
        Ok(Self {
            models,
            width,
            height,
            frame_dt,
            step: frame_dt / first.config.sim.substeps.or(1) as f64,
            number,
            source: first.config.source.clone(),
            progress,
        })
    }

    /// Drapes the references and every model over one scene; writes its figure and curves.
    fn scene(&self, scene: &Scene, out: &Path) -> Result<SceneResult> {
        let start = Instant::now();
        let params = scene.params(self.width.max(self.height), self.step, self.number);
        let cfg = &scene.config;
        self.progress.note(&format!(
            "drape {}: {} collider(s), {:.1} s, contact thickness {:.4} m, κ = {:.3e}/s², ζ = {:.3e}/s",
            scene.name,
            scene.colliders.len(),
            cfg.seconds,
            params.thickness,
            params.stiffness,
            params.damping
        ));
        let frames = self.frames(cfg);
        let mut warnings = Vec::new();
        let refs = match &self.source {
            Some(src) => self.references(scene, &params, src, frames)?,
            None => {
                warnings.push(
                    "the run has no [source]: no reference drape, only the models' contact figures"
                        .into(),
                );
                References::default()
            }
        };
        let recs = self.simulate_models(scene, &params, frames, None)?;
        let relaxations = self.relaxations(scene, &params, frames, &refs, &mut warnings)?;
        let score = Score {
            coarse: refs.coarse.as_ref(),
            fine: refs.fine.as_ref(),
            thickness: params.thickness,
            record_dt: frames.record_dt,
            scored: frames.scored,
        };
        let scored = score.scene(&refs, &recs, &relaxations, &mut warnings);
        self.note_scores(scene, &scored);
        let mut drawn: Vec<&Recording> = Vec::new();
        drawn.extend(refs.coarse.as_ref());
        drawn.extend(recs.iter().filter_map(|r| r.recording.as_ref()));
        drawn.extend(refs.fine.as_ref());
        figure(
            &out.join(format!("{}.png", scene.name)),
            scene,
            &params,
            &drawn,
            &scored.models,
        )?;
        write_curves(
            &out.join(format!("{}_motion_rmse.csv", scene.name)),
            &scored.models,
        )?;
        Ok(SceneResult {
            scene_file: scene.path.clone(),
            scene: scene.config.clone(),
            contact_thickness: params.thickness,
            contact: params,
            record_dt: frames.record_dt,
            source: scored.source,
            fine: scored.fine,
            perturbed: scored.perturbed,
            models: scored.models,
            warnings,
            wall_seconds: start.elapsed().as_secs_f64(),
        })
    }

    /// The scene's timing in data frames.
    fn frames(&self, cfg: &SceneConfig) -> Frames {
        let every = ((cfg.record_every / self.frame_dt).round() as usize).max(1);
        Frames {
            total: ((cfg.seconds + cfg.settle) / self.frame_dt).round() as usize,
            every,
            scored: (cfg.seconds / self.frame_dt).round() as usize / every,
            record_dt: every as f64 * self.frame_dt,
        }
    }

    /// Every model started at rest from the source's and from the fine mesh's settled drape,
    /// and the source from the fine mesh's, where [`relaxable`] allows (warning where not).
    fn relaxations(
        &self,
        scene: &Scene,
        params: &ContactParams,
        frames: Frames,
        refs: &References,
        warnings: &mut Vec<String>,
    ) -> Result<Relaxations> {
        let cfg = &scene.config;
        let relax = Frames {
            total: (cfg.settle / self.frame_dt).round() as usize / frames.every * frames.every,
            ..frames
        };
        let (coarse, fine) = (refs.coarse.as_ref(), refs.fine.as_ref());
        let mut from_source = Vec::new();
        if relaxable(coarse, relax, cfg, warnings) {
            from_source = self.simulate_models(scene, params, relax, coarse)?;
        }
        let mut from_fine = Vec::new();
        let mut source_from_fine = None;
        if let (true, Some(src)) = (relaxable(fine, relax, cfg, warnings), &self.source) {
            from_fine = self.simulate_models(scene, params, relax, fine)?;
            source_from_fine = Some(self.host_run(scene, params, src, 0.0, relax, fine)?);
        }
        Ok(Relaxations {
            from_source,
            from_fine,
            source_from_fine,
            seconds: relax.total as f64 * self.frame_dt,
        })
    }

    /// Prints each model's and reference's figures in the scene.
    fn note_scores(&self, scene: &Scene, scored: &Scored) {
        for (who, r) in &scored.models {
            self.progress.note(&format!(
                "  {who}: motion RMSE at {:.1} s {}; at rest to the source {}, to the fine mesh {}{}; deepest {:.4} m, {:.1} s wall{}",
                scene.config.seconds,
                fmt_m(r.motion_rmse_end),
                fmt_m(r.steady_rmse_vs_source),
                fmt_m(r.steady_rmse_vs_fine),
                match &r.relaxed_from_source {
                    Some(x) => format!(
                        "; started from the source's drape, at rest {} from it",
                        fmt_m(x.steady_rmse_vs_source)
                    ),
                    None => String::new(),
                },
                r.max_penetration.unwrap_or(0.0),
                r.wall_seconds,
                if r.diverged { ", DIVERGED" } else { "" }
            ));
        }
        for (who, r) in [("source", &scored.source), ("perturbed", &scored.perturbed)] {
            if let Some(s) = r {
                self.progress.note(&format!(
                    "  {who} {}: at rest to the source {}, to the fine mesh {}; deepest {:.4} m, {:.1} s wall",
                    s.label,
                    fmt_m(s.steady_rmse_vs_source),
                    fmt_m(s.steady_rmse_vs_fine),
                    s.max_penetration,
                    s.wall_seconds
                ));
            }
        }
    }

    /// The coarse source, (for an FEM source) the fine FEM mesh and (for `scene.perturb > 0`)
    /// the perturbed source over the scene, side by side.
    fn references(
        &self,
        scene: &Scene,
        params: &ContactParams,
        src: &SourceConfig,
        frames: Frames,
    ) -> Result<References> {
        let host_run = |src: &SourceConfig, perturb: f64| {
            self.host_run(scene, params, src, perturb, frames, None)
        };
        let fine_src = (src.kind == SourceKind::Fem).then(|| fine_config(src, scene.config.fine));
        let perturb = scene.config.perturb;
        let ((c, p), f) = rayon::join(
            || {
                rayon::join(
                    || host_run(src, 0.0),
                    || (perturb > 0.0).then(|| host_run(src, perturb)).transpose(),
                )
            },
            || fine_src.as_ref().map(|f| host_run(f, 0.0)).transpose(),
        );
        Ok(References {
            coarse: Some(c?),
            fine: f?,
            perturbed: p?,
        })
    }

    /// A host cloth (the source, perturbed by `perturb`, or the fine mesh) over the scene,
    /// released flat or, with `start`, at rest from that recording's last frame.
    fn host_run(
        &self,
        scene: &Scene,
        params: &ContactParams,
        src: &SourceConfig,
        perturb: f64,
        frames: Frames,
        start: Option<&Recording>,
    ) -> Result<Recording> {
        let sim = crate::source::build_perturbed(src, perturb, PERTURB_SEED);
        let dt = stable_step(sim.as_ref(), params, src.dt);
        let record_dt = frames.record_dt;
        let every = (record_dt / dt).round() as usize;
        if every == 0 || (every as f64 * dt - record_dt).abs() > 1e-6 * record_dt {
            bail!("the source's step {dt} s does not divide the recorded interval {record_dt} s");
        }
        let steps = frames.total / frames.every * every;
        let contact = Contact::new(scene.colliders.clone(), *params);
        let mut label = if perturb > 0.0 {
            format!("{} ±{}%", label_of(src), 100.0 * perturb)
        } else {
            label_of(src)
        };
        let x0 = match start {
            Some(r) => {
                label = format!("{label} from {}", r.label);
                relaxation_start(r, sim.rest_uv(), &contact, src.gravity)
            }
            None => scene.release(sim.rest_uv(), src.width, src.height),
        };
        Ok(simulate_host(
            &label,
            sim.as_ref(),
            grid_edges(src.nx, src.ny),
            x0,
            &contact,
            dt,
            steps,
            every,
            self.progress,
        ))
    }

    /// Every model over the scene (the GNN is recorded as not applicable), released flat or,
    /// with `start`, at rest from that recording's last frame.
    fn simulate_models(
        &self,
        scene: &Scene,
        params: &ContactParams,
        frames: Frames,
        start: Option<&Recording>,
    ) -> Result<Vec<Draped>> {
        let mut recs = Vec::new();
        for m in self.models {
            let kind = m.config.model.kind.name().to_string();
            let physics = m.physics(self.frame_dt);
            let model: &dyn ForceModel = match &m.model {
                Trained::Springs(s) => {
                    physics
                        .stability_of(&m.topology, s)
                        .with_contact(params)
                        .check(
                            &format!("{} in scene {}", m.dir.dir.display(), scene.name),
                            m.config.sim.allow_unstable,
                        )?;
                    s
                }
                Trained::NeuralOde(o) => o,
                Trained::Gnn(_) => {
                    recs.push(Draped {
                        kind,
                        run: m.dir.dir.clone(),
                        recording: None,
                    });
                    continue;
                }
            };
            let contact = Contact::new(scene.colliders.clone(), *params);
            let (x0, label) = match start {
                Some(r) => (
                    relaxation_start(r, &m.topology.rest_uv, &contact, physics.gravity),
                    format!("{kind} from {}", r.label),
                ),
                None => (
                    scene.release(&m.topology.rest_uv, self.width, self.height),
                    kind.clone(),
                ),
            };
            let rec = simulate_model(
                &label,
                model,
                &physics,
                &m.topology,
                &x0,
                &contact,
                frames.total / frames.every * frames.every,
                frames.every,
                &m.device,
                self.progress,
            );
            recs.push(Draped {
                kind,
                run: m.dir.dir.clone(),
                recording: Some(rec),
            });
        }
        Ok(recs)
    }
}

/// Seed of the perturbed source's draw.
const PERTURB_SEED: u64 = 1;

/// One scene's reference drapes.
#[derive(Default)]
struct References {
    /// The run's source.
    coarse: Option<Recording>,
    /// The fine FEM mesh.
    fine: Option<Recording>,
    /// The source with its material perturbed.
    perturbed: Option<Recording>,
}

/// Whether a relaxation can start from the settled drape `r` (`relax` long) in a scene:
/// relaxations start at rest from a settled drape, at t = 0 with the colliders where they
/// stand then, not where a drape ended: static scenes only. Warns where it cannot, or where
/// `r` had not come to rest.
fn relaxable(
    r: Option<&Recording>,
    relax: Frames,
    cfg: &SceneConfig,
    warnings: &mut Vec<String>,
) -> bool {
    let Some(r) = r else {
        return false;
    };
    let why = if relax.total == 0 {
        "scene.settle is shorter than scene.record_every"
    } else if cfg.colliders.iter().any(|k| k.path.len() >= 2) {
        "a collider moves"
    } else if r.diverged.is_some() || r.frames.is_empty() {
        "it diverged"
    } else {
        if !r.settled() {
            warnings.push(format!(
                "the {} drape had not come to rest: the relaxations from it include \
                 its own unfinished motion",
                r.label
            ));
        }
        return true;
    };
    warnings.push(format!("no relaxation from the {} drape: {why}", r.label));
    false
}

/// One scene's drapes started at rest from a reference's settled drape.
struct Relaxations {
    /// Every model from the source's drape (none where it cannot relax).
    from_source: Vec<Draped>,
    /// Every model from the fine mesh's drape.
    from_fine: Vec<Draped>,
    /// The source from the fine mesh's drape.
    source_from_fine: Option<Recording>,
    /// How long each ran, s.
    seconds: f64,
}

/// One scene's figures: the references' and every model's.
struct Scored {
    source: Option<Reference>,
    fine: Option<Reference>,
    perturbed: Option<Reference>,
    models: BTreeMap<String, ModelResult>,
}

/// Scores one scene's recordings against its references.
struct Score<'a> {
    coarse: Option<&'a Recording>,
    fine: Option<&'a Recording>,
    thickness: f64,
    record_dt: f64,
    /// Index of the recorded frame at `scene.seconds`.
    scored: usize,
}

impl Score<'_> {
    /// RMSE of the last frame to the reference's last frame (resampled), when both finished.
    fn steady(rec: &Recording, reference: Option<&Recording>) -> Option<f64> {
        let f = reference?;
        if f.diverged.is_some() || rec.diverged.is_some() {
            return None;
        }
        let res = Resampler::new(&f.rest_uv, &rec.rest_uv);
        Some(eval::frame_rmse(
            rec.frames.last()?,
            &resample(&res, f.frames.last()?),
        ))
    }

    /// [`Score::steady`] against the fine mesh.
    fn vs_fine(&self, rec: &Recording) -> Option<f64> {
        Self::steady(rec, self.fine)
    }

    /// [`Score::steady`] against the source.
    fn vs_source(&self, rec: &Recording) -> Option<f64> {
        Self::steady(rec, self.coarse)
    }

    /// Warns when `rec` reached the collider's surface or diverged.
    fn warn(&self, who: &str, rec: &Recording, warnings: &mut Vec<String>) {
        if rec.deepest > self.thickness {
            warnings.push(format!(
                "{who}: penetrated {:.4} m into the contact layer of {:.4} m: it reached the \
                 collider's surface",
                rec.deepest, self.thickness
            ));
        }
        if let Some(d) = &rec.diverged {
            warnings.push(d.clone());
        } else if !rec.settled() {
            warnings.push(format!(
                "{who}: still moving at the end (RMS speed {:.3} m/s ≥ {SETTLED_SPEED} m/s): its \
                 steady-state figures are not at rest; raise scene.settle",
                rec.speed_rms_end.unwrap_or(f64::NAN)
            ));
        }
    }

    /// A reference simulation's figures.
    fn reference(&self, rec: &Recording, who: &str, warnings: &mut Vec<String>) -> Reference {
        self.warn(who, rec, warnings);
        Reference {
            label: rec.label.clone(),
            dt: rec.dt,
            steady_rmse_vs_fine: self.vs_fine(rec),
            steady_rmse_vs_source: self.vs_source(rec),
            max_penetration: rec.deepest,
            kinetic_energy_end: rec.kinetic_energy_end,
            speed_rms_end: rec.speed_rms_end,
            settled: rec.settled(),
            diverged: rec.diverged.is_some(),
            relaxed_from_fine: None,
            wall_seconds: rec.wall_seconds,
        }
    }

    /// A relaxation's figures: `rec` ran `seconds` from another system's drape.
    fn relaxed(&self, rec: &Recording, seconds: f64, warnings: &mut Vec<String>) -> Relaxed {
        self.warn(&rec.label, rec, warnings);
        Relaxed {
            steady_rmse_vs_source: self.vs_source(rec),
            steady_rmse_vs_fine: self.vs_fine(rec),
            speed_rms_end: rec.speed_rms_end,
            settled: rec.settled(),
            diverged: rec.diverged.is_some(),
            seconds,
        }
    }

    /// The scene's figures: the source (with its relaxation from the fine mesh), the fine mesh,
    /// the perturbed source and every model (with its relaxations).
    fn scene(
        &self,
        refs: &References,
        recs: &[Draped],
        relaxations: &Relaxations,
        warnings: &mut Vec<String>,
    ) -> Scored {
        let seconds = relaxations.seconds;
        let source = refs.coarse.as_ref().map(|c| {
            let mut r = self.reference(c, "source", warnings);
            r.relaxed_from_fine = relaxations
                .source_from_fine
                .as_ref()
                .map(|x| self.relaxed(x, seconds, warnings));
            r
        });
        let fine = refs.fine.as_ref().map(|f| {
            let mut r = self.reference(f, "fine reference", warnings);
            r.steady_rmse_vs_fine = Some(0.0);
            r
        });
        let perturbed = refs
            .perturbed
            .as_ref()
            .map(|p| self.reference(p, "perturbed source", warnings));
        let models = recs
            .iter()
            .enumerate()
            .map(|(i, d)| {
                let mut m = self.model(d, warnings);
                let mut relaxed = |from: &[Draped]| {
                    let r = from.get(i).and_then(|r| r.recording.as_ref())?;
                    Some(self.relaxed(r, seconds, warnings))
                };
                m.relaxed_from_source = relaxed(&relaxations.from_source);
                m.relaxed_from_fine = relaxed(&relaxations.from_fine);
                (d.kind.clone(), m)
            })
            .collect();
        Scored {
            source,
            fine,
            perturbed,
            models,
        }
    }

    /// A model's figures: motion RMSE to the coarse source over time, to the fine mesh at rest
    /// (the relaxations are the caller's).
    fn model(&self, draped: &Draped, warnings: &mut Vec<String>) -> ModelResult {
        let Some(rec) = &draped.recording else {
            return ModelResult {
                run: draped.run.clone(),
                applicable: false,
                motion_rmse_end: None,
                motion_rmse_mean: None,
                steady_rmse_vs_fine: None,
                steady_rmse_vs_source: None,
                max_penetration: None,
                kinetic_energy_end: None,
                speed_rms_end: None,
                settled: false,
                diverged: false,
                note: Some(GNN_NOT_APPLICABLE.into()),
                motion_rmse_over_time: Vec::new(),
                relaxed_from_source: None,
                relaxed_from_fine: None,
                wall_seconds: 0.0,
            };
        };
        self.warn(&draped.kind, rec, warnings);
        let curve: Vec<[f64; 2]> = match self.coarse {
            Some(c) => {
                let res = Resampler::new(&c.rest_uv, &rec.rest_uv);
                rec.frames
                    .iter()
                    .zip(&c.frames)
                    .enumerate()
                    .map(|(r, (x, y))| {
                        [
                            r as f64 * self.record_dt,
                            eval::frame_rmse(x, &resample(&res, y)),
                        ]
                    })
                    .collect()
            }
            None => Vec::new(),
        };
        let complete = rec.diverged.is_none() && curve.len() > self.scored;
        let window = &curve[..curve.len().min(self.scored + 1)];
        ModelResult {
            run: draped.run.clone(),
            applicable: true,
            motion_rmse_end: complete.then(|| curve[self.scored][1]),
            motion_rmse_mean: complete
                .then(|| window.iter().map(|c| c[1]).sum::<f64>() / window.len() as f64),
            steady_rmse_vs_fine: self.vs_fine(rec),
            steady_rmse_vs_source: self.vs_source(rec),
            max_penetration: Some(rec.deepest),
            kinetic_energy_end: rec.kinetic_energy_end,
            speed_rms_end: rec.speed_rms_end,
            settled: rec.settled(),
            diverged: rec.diverged.is_some(),
            note: rec.diverged.clone(),
            motion_rmse_over_time: curve,
            relaxed_from_source: None,
            relaxed_from_fine: None,
            wall_seconds: rec.wall_seconds,
        }
    }
}

/// The drape folders listed in a run's `drapes.json` (none when it is missing or unreadable).
pub fn read_drapes(path: &Path) -> Vec<PathBuf> {
    std::fs::read_to_string(path)
        .ok()
        .and_then(|t| serde_json::from_str(&t).ok())
        .unwrap_or_default()
}

/// The figures of the drapes listed in `drapes.json` that still exist, as `(png, caption)`.
pub fn report_figures(list: &Path) -> Vec<(PathBuf, String)> {
    let mut out = Vec::new();
    for dir in read_drapes(list) {
        let Ok(text) = std::fs::read_to_string(dir.join("drape.json")) else {
            continue;
        };
        let Ok(json) = serde_json::from_str::<serde_json::Value>(&text) else {
            continue;
        };
        let Some(scenes) = json["scenes"].as_object() else {
            continue;
        };
        for (name, s) in scenes {
            let png = dir.join(format!("{name}.png"));
            if !png.exists() {
                continue;
            }
            let num =
                |v: &serde_json::Value| v.as_f64().map_or("—".into(), |x| format!("{x:.4} m"));
            let seconds = s["scene"]["seconds"].as_f64().unwrap_or(f64::NAN);
            // A drape written before `scene.settle` existed ended at `seconds`.
            let end = match s["scene"]["settle"].as_f64() {
                Some(settle) => format!("after {seconds:.1} s and {settle:.1} s of settling"),
                None => format!("at {seconds:.1} s (no settling phase)"),
            };
            let mut caption = format!(
                "drape on `{name}` ({}): {end}; RMSE at the end to the fine FEM mesh: source {}",
                dir.display(),
                num(&s["source"]["steady_rmse_vs_fine"])
            );
            if let Some(models) = s["models"].as_object() {
                for (kind, m) in models {
                    caption += &format!(
                        ", {kind} {} (to the source at the end {}, motion RMSE at {seconds:.1} s {}, deepest {})",
                        num(&m["steady_rmse_vs_fine"]),
                        num(&m["steady_rmse_vs_source"]),
                        num(&m["motion_rmse_end"]),
                        num(&m["max_penetration"])
                    );
                }
            }
            // Without the path of a fall: each started from the fine mesh's settled drape.
            let from_fine = &s["source"]["relaxed_from_fine"];
            if from_fine.is_object() {
                caption += &format!(
                    "; started from the fine mesh's drape, at rest from it: source {}",
                    num(&from_fine["steady_rmse_vs_fine"])
                );
                for (kind, m) in s["models"].as_object().into_iter().flatten() {
                    caption += &format!(
                        ", {kind} {}",
                        num(&m["relaxed_from_fine"]["steady_rmse_vs_fine"])
                    );
                }
            }
            out.push((png, caption));
        }
    }
    out
}

fn fmt_m(v: Option<f64>) -> String {
    v.map_or("—".into(), |v| format!("{v:.4} m"))
}

/// `time,<model>,…` motion RMSE curves.
fn write_curves(path: &Path, models: &BTreeMap<String, ModelResult>) -> Result<()> {
    let cols: Vec<(&String, &ModelResult)> = models
        .iter()
        .filter(|(_, m)| !m.motion_rmse_over_time.is_empty())
        .collect();
    let rows = cols
        .iter()
        .map(|(_, m)| m.motion_rmse_over_time.len())
        .max()
        .unwrap_or(0);
    let mut w = csv::Writer::from_writer(Vec::new());
    let mut header = vec!["time".to_string()];
    header.extend(cols.iter().map(|(k, _)| format!("{k}_rmse_m")));
    w.write_record(&header)?;
    for r in 0..rows {
        let t = cols
            .iter()
            .find_map(|(_, m)| m.motion_rmse_over_time.get(r))
            .map_or(0.0, |c| c[0]);
        let mut row = vec![format!("{t:.4}")];
        row.extend(cols.iter().map(|(_, m)| {
            m.motion_rmse_over_time
                .get(r)
                .map_or(String::new(), |c| format!("{:.6e}", c[1]))
        }));
        w.write_record(&row)?;
    }
    let bytes = w.into_inner().map_err(|e| anyhow::anyhow!("{e}"))?;
    crate::io::write_text(path, &String::from_utf8(bytes)?)
}

/// Grid edges (rows and columns) of an `nx × ny` row-major grid.
fn grid_edges(nx: usize, ny: usize) -> Vec<[usize; 2]> {
    let mut e = Vec::new();
    for r in 0..ny {
        for c in 0..nx {
            let i = r * nx + c;
            if c + 1 < nx {
                e.push([i, i + 1]);
            }
            if r + 1 < ny {
                e.push([i, i + nx]);
            }
        }
    }
    e
}

/// The drapes at the end side by side (source, models, fine reference) over the colliders'
/// surface points, and the motion RMSE over time.
fn figure(
    path: &Path,
    scene: &Scene,
    params: &ContactParams,
    recs: &[&Recording],
    models: &BTreeMap<String, ModelResult>,
) -> Result<()> {
    use springtime_plot::{self as plot, anim::View};
    let view = View::default();
    let ends: Vec<&[f32]> = recs
        .iter()
        .filter_map(|r| r.frames.last().map(Vec::as_slice))
        .collect();
    let bounds = view.bounds(ends.iter().copied());
    let (lo, hi) = extent(&ends);
    let surface: Vec<f32> = surface_points(scene, lo, hi, params.thickness);
    let panels = recs.len().max(1);
    let (w, h) = (380 * panels as u32, 760);
    plot::png_figure(path, w.max(760), h, |root| {
        let (top, bottom) = root.split_vertically(400);
        let cells = top.split_evenly((1, panels));
        let panel = DrapePanel {
            scene,
            surface: &surface,
            view: &view,
            bounds,
        };
        for (area, rec) in cells.iter().zip(recs) {
            panel.draw(area, rec)?;
        }
        draw_motion_rmse(&bottom, scene, models)
    })
}

/// The smallest and largest coordinate of the frames' points, per axis.
fn extent(frames: &[&[f32]]) -> (V3, V3) {
    let lo = [0, 1, 2].map(|c| {
        frames
            .iter()
            .flat_map(|f| f.chunks_exact(3).map(move |p| p[c] as f64))
            .fold(f64::INFINITY, f64::min)
    });
    let hi = [0, 1, 2].map(|c| {
        frames
            .iter()
            .flat_map(|f| f.chunks_exact(3).map(move |p| p[c] as f64))
            .fold(f64::NEG_INFINITY, f64::max)
    });
    (lo, hi)
}

/// What every drape panel of a scene's figure shares.
struct DrapePanel<'a> {
    scene: &'a Scene,
    /// Points on the colliders' surfaces.
    surface: &'a [f32],
    view: &'a springtime_plot::anim::View,
    /// The drawn extent of every panel.
    bounds: ((f64, f64), (f64, f64)),
}

impl DrapePanel<'_> {
    /// `rec`'s last frame over the colliders, or a note that it diverged.
    fn draw(&self, area: &springtime_plot::Area, rec: &Recording) -> Result<()> {
        use springtime_plot::anim::{Layer, draw_cloth};
        let scene = self.scene;
        let edges = &rec.edges;
        let (caption, pos) = match (&rec.diverged, rec.frames.last()) {
            (None, Some(f)) => (
                format!(
                    "{}: t = {:.1} s",
                    rec.label,
                    scene.config.seconds + scene.config.settle
                ),
                f,
            ),
            (_, _) => {
                return springtime_plot::draw_message(area, &rec.label, "diverged");
            }
        };
        let layers = [
            Layer {
                positions: self.surface,
                edges: &[],
                pinned: &[],
                color: plotters::style::RGBColor(170, 170, 170),
                radius: 1,
            },
            Layer {
                positions: pos,
                edges,
                pinned: &[],
                color: plotters::style::RGBColor(31, 119, 180),
                radius: 0,
            },
        ];
        draw_cloth(area, &caption, self.view, self.bounds, &layers)
    }
}

/// Each model's motion RMSE to the source over time, marking where settling starts.
fn draw_motion_rmse(
    area: &springtime_plot::Area,
    scene: &Scene,
    models: &BTreeMap<String, ModelResult>,
) -> Result<()> {
    use springtime_plot::Series;
    let series: Vec<Series> = models
        .iter()
        .filter(|(_, m)| !m.motion_rmse_over_time.is_empty())
        .map(|(k, m)| {
            Series::new(
                k.clone(),
                m.motion_rmse_over_time
                    .iter()
                    .map(|c| (c[0], c[1]))
                    .collect(),
            )
        })
        .collect();
    springtime_plot::draw_curves(
        area,
        &format!("{}: motion RMSE to the source (Eq. 14)", scene.name),
        "time (s)",
        "RMSE (m)",
        &series,
        false,
        &if scene.config.settle > 0.0 {
            vec![(scene.config.seconds, "settling from here")]
        } else {
            Vec::new()
        },
    )
}

/// Points on the colliders' surfaces within the box `lo..hi` (grown by a margin), for the
/// figure: a lattice projected onto each collider.
fn surface_points(scene: &Scene, lo: V3, hi: V3, thickness: f64) -> Vec<f32> {
    if !lo.iter().chain(&hi).all(|c| c.is_finite()) {
        return Vec::new();
    }
    let margin = 0.1 * (0..3).map(|c| hi[c] - lo[c]).fold(thickness, f64::max);
    let (lo, hi) = (lo.map(|c| c - margin), hi.map(|c| c + margin));
    let n = 20;
    let mut pts = Vec::new();
    for i in 0..n {
        for j in 0..n {
            for k in 0..n {
                let q = [
                    lo[0] + (hi[0] - lo[0]) * i as f64 / (n - 1) as f64,
                    lo[1] + (hi[1] - lo[1]) * j as f64 / (n - 1) as f64,
                    lo[2] + (hi[2] - lo[2]) * k as f64 / (n - 1) as f64,
                ];
                for c in &scene.colliders {
                    let p = c.query(scene.config.seconds, q).point;
                    if (0..3).all(|a| p[a] >= lo[a] && p[a] <= hi[a]) {
                        pts.extend(p.map(|a| a as f32));
                    }
                }
            }
        }
    }
    pts
}
