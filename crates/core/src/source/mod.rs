//! Source systems: simulators that generate the rollouts the surrogate learns from
//! (paper §4.1). Each rollout pins two random anchor neighbourhoods and starts from the flat
//! sheet under a random rotation (Fig. 6); the cloth falls under gravity and Rayleigh damping.

pub mod fem;
mod fem_forces;
pub mod implicit;
pub mod mass_spring;
pub mod stiffness;

pub use fem::{Diagonal, FemCloth, FemConfig};
pub use mass_spring::SpringCloth;
pub use stiffness::{Layout, StiffnessMap};

use std::path::Path;
use std::sync::Mutex;
use std::sync::atomic::{AtomicUsize, Ordering};

use anyhow::{Context, Result, bail};
use rand::{Rng, SeedableRng, rngs::StdRng};
use rand_distr::StandardNormal;
use serde::{Deserialize, Serialize};

use crate::data::{ClipConfig, INDEX_FORMAT, Index, MeshTruth, Rollout, Segment, SpringTruth};
use crate::sim::{ContactAt, Stability};

/// Which simulator generates the data.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SourceKind {
    /// A ground-truth spring network (§4.1 (i)).
    #[default]
    MassSpring,
    /// A triangle mesh with an FEM membrane and dihedral bending (§4.1 (ii), [`fem`]).
    Fem,
}

/// What the generator writes for each training rollout.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Storage {
    /// Every frame.
    #[default]
    Full,
    /// Only the windows of the clips that training keeps (`data.clips`): App. A's subsampled
    /// dataset without storing the rest. Test rollouts are always stored in full.
    Clips,
}

/// The `[source]` section: a synthetic data generator.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SourceConfig {
    /// The simulator.
    pub kind: SourceKind,
    /// Landmarks along the width.
    pub nx: usize,
    /// Landmarks along the height.
    pub ny: usize,
    /// Sheet width, m.
    pub width: f64,
    /// Sheet height, m.
    pub height: f64,
    /// Areal density ρ, kg/m²; particle mass is ρ·W·H / (nx·ny).
    pub areal_density: f64,
    /// Stiffness levels, N/m: spring stiffness (`mass_spring`) or surface Young's modulus
    /// (`fem`).
    pub stiffness_levels: Vec<f64>,
    /// Where the levels go.
    pub layout: Layout,
    /// Damping of every spring, N·s/m (`mass_spring` only; see `fem.strain_damping`).
    pub damping: f64,
    /// Rayleigh damping constant, N·s/m.
    pub rayleigh: f64,
    /// Gravity, m/s².
    pub gravity: [f64; 3],
    /// Length of a rollout, s.
    pub seconds: f64,
    /// Simulation step, s.
    pub dt: f64,
    /// Simulation steps per stored frame (`frame_dt = frame_stride · dt`).
    pub frame_stride: usize,
    /// Training rollouts.
    pub train_rollouts: usize,
    /// Test rollouts.
    pub test_rollouts: usize,
    /// Radius of an anchor neighbourhood in the rest rectangle, m (0 pins single landmarks).
    pub anchor_radius: f64,
    /// Store velocities beside positions (exact target forces; see the book's rollout format page).
    pub save_velocities: bool,
    /// What is stored of training rollouts.
    pub storage: Storage,
    /// Seed of rotations and anchors.
    pub seed: u64,
    /// Generate even when the stability guard predicts a blow-up.
    pub allow_unstable: bool,
    /// Material and mesh of the FEM source.
    pub fem: FemConfig,
}

impl Default for SourceConfig {
    /// The paper's mass-spring source (15.5 m sheet, 32 × 32, 10/50/100 N/m, b = 6, Rayleigh
    /// 0.1, 8 s at 1 ms) made stable at 1 ms by an areal density of 0.2 kg/m²
    /// (m ≈ 0.047 kg per particle: dt²ω² + 2·dt·γ ≈ 2.6 < 4).
    fn default() -> Self {
        Self {
            kind: SourceKind::MassSpring,
            nx: 32,
            ny: 32,
            width: 15.5,
            height: 15.5,
            areal_density: 0.2,
            stiffness_levels: vec![10.0, 50.0, 100.0],
            layout: Layout::Stripes,
            damping: 6.0,
            rayleigh: 0.1,
            gravity: crate::sim::GRAVITY,
            seconds: 8.0,
            dt: 1e-3,
            frame_stride: 1,
            train_rollouts: 512,
            test_rollouts: 16,
            anchor_radius: 0.5,
            save_velocities: true,
            storage: Storage::Full,
            seed: 0,
            allow_unstable: false,
            fem: FemConfig::default(),
        }
    }
}

impl SourceConfig {
    /// Checks values that would make generation meaningless; errors name the key.
    pub fn validate(&self) -> Result<()> {
        let pos = |key: &str, v: f64| -> Result<()> {
            if !(v > 0.0 && v.is_finite()) {
                bail!("source.{key} must be positive, is {v}");
            }
            Ok(())
        };
        if self.nx < 2 || self.ny < 2 {
            bail!("source.nx and source.ny must be at least 2");
        }
        pos("width", self.width)?;
        pos("height", self.height)?;
        pos("areal_density", self.areal_density)?;
        pos("seconds", self.seconds)?;
        pos("dt", self.dt)?;
        if self.frame_stride == 0 {
            bail!("source.frame_stride must be at least 1");
        }
        if self.stiffness_levels.is_empty() || self.stiffness_levels.iter().any(|&k| !(k >= 0.0)) {
            bail!("source.stiffness_levels must list at least one non-negative stiffness");
        }
        if !(self.damping >= 0.0) || !(self.rayleigh >= 0.0) {
            bail!("source.damping and source.rayleigh must be non-negative");
        }
        if self.train_rollouts == 0 {
            bail!("source.train_rollouts must be at least 1");
        }
        self.fem.validate()
    }

    /// Time between stored frames, s.
    pub fn frame_dt(&self) -> f64 {
        self.dt * self.frame_stride as f64
    }

    /// Simulation steps of one rollout.
    pub fn steps(&self) -> usize {
        (self.seconds / self.dt).round() as usize
    }
}

/// A forward simulator of a cloth that a generator can drive.
pub trait ClothSim: Sync {
    /// Landmark rest positions in the rectangle.
    fn rest_uv(&self) -> &[[f64; 2]];
    /// Mean mass of a landmark, kg.
    fn particle_mass(&self) -> f64;
    /// Mass of landmark `i`, kg.
    fn mass_of(&self, i: usize) -> f64;
    /// Net force on every landmark at `(x, v)`: internal forces, gravity, Rayleigh damping.
    fn net_forces(&self, x: &[[f64; 3]], v: &[[f64; 3]], out: &mut [[f64; 3]]);
    /// One semi-implicit Euler step, `v ← v + dt/m f`, `x ← x + dt v`, with the contact
    /// forces of `contact` when given ([`Contact::apply`](crate::sim::Contact::apply));
    /// pinned landmarks stay where they are.
    fn step(
        &self,
        x: &mut [[f64; 3]],
        v: &mut [[f64; 3]],
        pinned: &[bool],
        dt: f64,
        contact: Option<ContactAt>,
        scratch: &mut Vec<[f64; 3]>,
    ) {
        scratch.resize(x.len(), [0.0; 3]);
        self.net_forces(x, v, scratch);
        if let Some(c) = contact {
            c.contact
                .apply(c.time, dt, x, v, pinned, |i| self.mass_of(i), scratch);
        }
        for i in 0..x.len() {
            if pinned[i] {
                v[i] = [0.0; 3];
                continue;
            }
            let h_over_m = dt / self.mass_of(i);
            for c in 0..3 {
                v[i][c] += h_over_m * scratch[i][c];
                x[i][c] += dt * v[i][c];
            }
        }
    }
    /// The explicit-step stability estimate at `dt`.
    fn stability(&self, dt: f64) -> Stability;
    /// Ground-truth springs, if the source is a spring network.
    fn spring_truth(&self) -> Option<SpringTruth> {
        None
    }
    /// Mesh and stiffness map, if the source is a mesh.
    fn mesh_truth(&self) -> Option<MeshTruth> {
        None
    }
}

/// Initial and boundary conditions of one rollout.
#[derive(Debug, Clone, PartialEq)]
pub struct Scenario {
    /// Rotation applied to the centred flat sheet.
    pub rotation: [[f64; 3]; 3],
    /// Pinned landmarks (two anchor neighbourhoods).
    pub pinned: Vec<bool>,
}

impl Scenario {
    /// A uniformly random rotation and two random anchor neighbourhoods of `radius`.
    pub fn random(rest_uv: &[[f64; 2]], radius: f64, rng: &mut StdRng) -> Self {
        // Uniform rotation from a uniform unit quaternion.
        let q: [f64; 4] = std::array::from_fn(|_| rng.sample::<f64, _>(StandardNormal));
        let n = q.iter().map(|c| c * c).sum::<f64>().sqrt().max(1e-12);
        let [w, x, y, z] = q.map(|c| c / n);
        let rotation = [
            [
                1.0 - 2.0 * (y * y + z * z),
                2.0 * (x * y - w * z),
                2.0 * (x * z + w * y),
            ],
            [
                2.0 * (x * y + w * z),
                1.0 - 2.0 * (x * x + z * z),
                2.0 * (y * z - w * x),
            ],
            [
                2.0 * (x * z - w * y),
                2.0 * (y * z + w * x),
                1.0 - 2.0 * (x * x + y * y),
            ],
        ];
        let n = rest_uv.len();
        let a = rng.random_range(0..n);
        let mut b = rng.random_range(0..n - 1);
        if b >= a {
            b += 1;
        }
        let r2 = radius * radius + 1e-12;
        let near = |c: usize, p: [f64; 2]| {
            (p[0] - rest_uv[c][0]).powi(2) + (p[1] - rest_uv[c][1]).powi(2) <= r2
        };
        let pinned = rest_uv.iter().map(|&p| near(a, p) || near(b, p)).collect();
        Self { rotation, pinned }
    }

    /// Initial positions: the flat sheet centred at the origin, rotated.
    pub fn initial_positions(&self, rest_uv: &[[f64; 2]]) -> Vec<[f64; 3]> {
        let n = rest_uv.len() as f64;
        let cu = rest_uv.iter().map(|p| p[0]).sum::<f64>() / n;
        let cv = rest_uv.iter().map(|p| p[1]).sum::<f64>() / n;
        let r = &self.rotation;
        rest_uv
            .iter()
            .map(|p| {
                let q = [p[0] - cu, p[1] - cv, 0.0];
                [0, 1, 2].map(|i| r[i][0] * q[0] + r[i][1] * q[1] + r[i][2] * q[2])
            })
            .collect()
    }
}

/// Frame windows `(first, count)` of the timeline that hold the planned clips (merged).
fn windows(
    plan: &[crate::data::clips::PlannedClip],
    steps: usize,
    first: usize,
) -> Vec<(usize, usize)> {
    let mut spans: Vec<(usize, usize)> = plan
        .iter()
        .map(|c| (c.start - first, c.start + steps + 1))
        .collect();
    spans.sort();
    let mut merged: Vec<(usize, usize)> = Vec::new();
    for (a, b) in spans {
        match merged.last_mut() {
            Some(last) if a <= last.1 => last.1 = last.1.max(b),
            _ => merged.push((a, b)),
        }
    }
    merged.into_iter().map(|(a, b)| (a, b - a)).collect()
}

/// Simulates one rollout of `sim` under `scenario`, keeping the frames in `keep` (all frames
/// when `None`).
pub fn simulate_rollout(
    sim: &dyn ClothSim,
    cfg: &SourceConfig,
    scenario: &Scenario,
    keep: Option<&[(usize, usize)]>,
    name: &str,
) -> Result<Rollout> {
    let rest = sim.rest_uv();
    let n = rest.len();
    let mut x = scenario.initial_positions(rest);
    let mut v = vec![[0.0f64; 3]; n];
    let mut scratch = Vec::new();
    let steps = cfg.steps();
    let stride = cfg.frame_stride;
    let timeline = steps / stride + 1;
    let segments = stored_segments(keep, timeline);
    let stored: usize = segments.iter().map(|s| s.len).sum();
    let mut positions = Vec::with_capacity(stored * n * 3);
    let mut velocities = Vec::with_capacity(if cfg.save_velocities {
        stored * n * 3
    } else {
        0
    });
    let limit = 100.0 * cfg.width.max(cfg.height);
    let in_window = |frame: usize| {
        segments
            .iter()
            .any(|s| frame >= s.start && frame < s.start + s.len)
    };
    for step in 0..=steps {
        if step % stride == 0 && in_window(step / stride) {
            positions.extend(x.iter().flat_map(|p| p.map(|c| c as f32)));
            if cfg.save_velocities {
                velocities.extend(v.iter().flat_map(|p| p.map(|c| c as f32)));
            }
        }
        if step == steps {
            break;
        }
        sim.step(&mut x, &mut v, &scenario.pinned, cfg.dt, None, &mut scratch);
        if step % 64 == 0
            && x.iter()
                .flatten()
                .any(|c| !c.is_finite() || c.abs() > limit)
        {
            bail!(
                "{name}: the source rollout diverged at step {step} (t = {:.3} s): {}",
                step as f64 * cfg.dt,
                sim.stability(cfg.dt).describe()
            );
        }
    }
    let frames = positions.len() / (n * 3);
    debug_assert_eq!(frames, stored);
    Ok(Rollout {
        path: name.into(),
        frames,
        landmarks: n,
        positions,
        velocities: cfg.save_velocities.then_some(velocities),
        rest_uv: rest.to_vec(),
        pinned: scenario.pinned.clone(),
        frame_dt: cfg.frame_dt(),
        total_mass: sim.particle_mass() * n as f64,
        width: cfg.width,
        height: cfg.height,
        segments,
        springs: sim.spring_truth(),
        mesh: sim.mesh_truth(),
        gravity: Some(cfg.gravity),
        rayleigh: Some(cfg.rayleigh),
        position_noise: None,
        visible: None,
    })
}

/// The stored windows of a rollout of `timeline` frames that keeps the frame windows `keep`
/// (`(first, count)`; all frames when `None`), in order in the stored arrays.
fn stored_segments(keep: Option<&[(usize, usize)]>, timeline: usize) -> Vec<Segment> {
    match keep {
        None => vec![Segment {
            start: 0,
            offset: 0,
            len: timeline,
        }],
        Some(w) => {
            let mut offset = 0;
            w.iter()
                .map(|&(start, len)| {
                    let s = Segment { start, offset, len };
                    offset += len;
                    s
                })
                .collect()
        }
    }
}

/// Builds the simulator of a source config.
pub fn build(cfg: &SourceConfig) -> Box<dyn ClothSim> {
    build_perturbed(cfg, 0.0, 0)
}

/// The standard-normal draw `n_s` per spring of a seed.
pub fn perturbation(springs: usize, seed: u64) -> Vec<f64> {
    let mut rng = StdRng::seed_from_u64(seed);
    (0..springs).map(|_| rng.sample(StandardNormal)).collect()
}

/// `values[s] · (1 + level · noise[s])`.
pub fn perturbed(values: &[f64], noise: &[f64], level: f64) -> Vec<f64> {
    values
        .iter()
        .zip(noise)
        .map(|(v, n)| v * (1.0 + level * n))
        .collect()
}

/// Builds the simulator of a source config with its material perturbed: every triangle's
/// Young's modulus (FEM) or spring's stiffness (mass-spring) times `1 + level · n`, `n` standard
/// normal from `seed` ([`perturbation`], the chaos floor's draw too).
/// `level = 0` is the source itself.
pub fn build_perturbed(cfg: &SourceConfig, level: f64, seed: u64) -> Box<dyn ClothSim> {
    let scale: Vec<f64> = if level == 0.0 {
        Vec::new()
    } else {
        // More draws than a grid has triangles or springs (structural, shear and bending:
        // under 6 per vertex); each element takes its own, whatever the count.
        let noise = perturbation(6 * cfg.nx * cfg.ny, seed);
        perturbed(&vec![1.0; noise.len()], &noise, level)
    };
    match cfg.kind {
        SourceKind::MassSpring => Box::new(SpringCloth::from_config_scaled(cfg, &scale)),
        SourceKind::Fem => Box::new(FemCloth::from_config_scaled(cfg, &scale)),
    }
}

/// Errors when `dir` holds `.npz` files that are not among the rollouts a generation writes
/// (`jobs`' names): someone's own data, which generating beside it would mix with synthetic
/// rollouts (and training would then use those instead).
fn refuse_foreign_rollouts(dir: &Path, jobs: &[(String, bool, u64)]) -> Result<()> {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return Ok(());
    };
    let mut foreign: Vec<String> = entries
        .filter_map(|e| e.ok())
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .filter(|name| name.ends_with(".npz") && !jobs.iter().any(|(job, _, _)| job == name))
        .collect();
    foreign.sort();
    if let Some(first) = foreign.first() {
        bail!(
            "data.dir {} holds {} rollout file(s) that this config's [source] does not write \
             (e.g. {first}): refusing to generate synthetic rollouts beside them. To train on \
             those files, remove [source] from the config; to generate, point data.dir at \
             another folder",
            dir.display(),
            foreign.len()
        );
    }
    Ok(())
}

/// A share of a generation: rollout `j` of the fixed order (train files, then test files)
/// belongs to shard `j mod count`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Shard {
    /// This shard, from 0.
    pub index: usize,
    /// Number of shards.
    pub count: usize,
}

impl Shard {
    /// The whole generation in one process.
    pub const WHOLE: Shard = Shard { index: 0, count: 1 };

    /// Whether rollout `j` of the fixed order is this shard's.
    pub fn owns(self, j: usize) -> bool {
        j % self.count == self.index
    }
}

impl std::str::FromStr for Shard {
    type Err = anyhow::Error;

    /// `i/n`, with `0 ≤ i < n`.
    fn from_str(s: &str) -> Result<Self> {
        let parsed = s
            .split_once('/')
            .and_then(|(i, n)| Some((i.trim().parse().ok()?, n.trim().parse().ok()?)));
        match parsed {
            Some((index, count)) if index < count => Ok(Self { index, count }),
            _ => bail!("--shard {s:?}: expected i/n with 0 <= i < n, e.g. 0/4"),
        }
    }
}

/// What [`generate`] did.
#[derive(Debug, Clone)]
pub struct Generation {
    /// The written `index.json`, once every rollout of every shard exists.
    pub index: Option<Index>,
    /// Train and test rollouts in the whole generation.
    pub total: usize,
    /// Rollouts that are this shard's.
    pub owned: usize,
    /// Rollouts (of any shard) still missing, after this shard's.
    pub missing: usize,
}

/// Takes the exclusive hold on generating into the data folder `dir` (`.<dir>.generate.lock`
/// beside it), waiting with a note while another process holds it, so that processes sharing
/// the folder (a sweep's jobs) generate it once. Released on drop or when the process ends.
pub(crate) fn generation_lock(
    dir: &Path,
    progress: &crate::progress::Progress,
) -> Result<crate::io::FileLock> {
    let path = crate::io::lock_path_beside(dir, "generate.lock", "data");
    if let Some(lock) = crate::io::FileLock::try_take(&path)? {
        return Ok(lock);
    }
    progress.note(&format!(
        "another process is generating {}: waiting for it",
        dir.display()
    ));
    crate::io::FileLock::wait(&path)
}

/// Generates the train and test rollouts of `cfg` into `dir` with an `index.json`: all of them,
/// or with `shard` one share (`springtime generate --shard i/n`).
///
/// Files that already exist are kept (an interrupted generation resumes, and shards fill one
/// folder); the index is written last, once every rollout exists, so a directory with an index
/// is complete, and the union of the shards is byte for byte the unsharded generation.
/// `progress` is called with the number of finished rollouts of this shard.
pub fn generate(
    cfg: &SourceConfig,
    clips: &ClipConfig,
    dir: &Path,
    shard: Shard,
    progress: impl Fn(usize) + Sync,
) -> Result<Generation> {
    cfg.validate()?;
    let sim = build(cfg);
    sim.stability(cfg.dt)
        .check("source", cfg.allow_unstable)
        .context("the source system would blow up")?;
    let jobs: Vec<(String, bool, u64)> = (0..cfg.train_rollouts)
        .map(|i| (format!("train_{i:04}.npz"), true, i as u64))
        .chain(
            (0..cfg.test_rollouts)
                .map(|i| (format!("test_{i:04}.npz"), false, 1_000_000 + i as u64)),
        )
        .collect();
    refuse_foreign_rollouts(dir, &jobs)?;
    std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
    let all = jobs;
    let jobs: Vec<&(String, bool, u64)> = all
        .iter()
        .enumerate()
        .filter(|(j, _)| shard.owns(*j))
        .map(|(_, job)| job)
        .collect();
    let generator = Generator {
        cfg,
        clips,
        dir,
        sim: sim.as_ref(),
    };
    generator.run(&jobs, progress)?;
    let missing = all.iter().filter(|j| !dir.join(&j.0).exists()).count();
    if missing > 0 {
        return Ok(Generation {
            index: None,
            total: all.len(),
            owned: jobs.len(),
            missing,
        });
    }
    let index = Index {
        format: INDEX_FORMAT.to_string(),
        train: all.iter().filter(|j| j.1).map(|j| j.0.clone()).collect(),
        test: all.iter().filter(|j| !j.1).map(|j| j.0.clone()).collect(),
        generator: serde_json::json!({
            "source": cfg,
            "clips": clips,
            "particle_mass": sim.particle_mass(),
            "stability_number": sim.stability(cfg.dt).number(),
        }),
    };
    crate::io::write_json(&Index::path(dir), &index)?;
    Ok(Generation {
        index: Some(index),
        total: all.len(),
        owned: jobs.len(),
        missing: 0,
    })
}

/// What [`generate`] writes rollouts with: the source, its simulator, the clip plan and the
/// data folder.
struct Generator<'a> {
    cfg: &'a SourceConfig,
    clips: &'a ClipConfig,
    dir: &'a Path,
    sim: &'a dyn ClothSim,
}

impl Generator<'_> {
    /// Writes the rollouts `jobs` (file name, training or not, seed id) that do not exist yet,
    /// on as many threads as there are cores; `progress` is called with the number finished.
    /// The first error stops the workers and is returned.
    fn run(&self, jobs: &[&(String, bool, u64)], progress: impl Fn(usize) + Sync) -> Result<()> {
        let next = AtomicUsize::new(0);
        let done = AtomicUsize::new(0);
        let error: Mutex<Option<anyhow::Error>> = Mutex::new(None);
        let workers = std::thread::available_parallelism()
            .map_or(1, |n| n.get())
            .min(jobs.len().max(1));
        std::thread::scope(|scope| {
            for _ in 0..workers {
                scope.spawn(|| {
                    loop {
                        let i = next.fetch_add(1, Ordering::SeqCst);
                        if i >= jobs.len() || error.lock().expect("lock").is_some() {
                            break;
                        }
                        let (name, train, id) = jobs[i];
                        let path = self.dir.join(name);
                        if !path.exists()
                            && let Err(e) = self.write_rollout(name, *train, *id, &path)
                        {
                            *error.lock().expect("lock") = Some(e);
                            break;
                        }
                        progress(done.fetch_add(1, Ordering::SeqCst) + 1);
                    }
                });
            }
        });
        match error.into_inner().expect("lock") {
            Some(e) => Err(e),
            None => Ok(()),
        }
    }

    /// Simulates rollout `name` (a training one when `train`) from seed id `id` and saves it
    /// to `path`.
    fn write_rollout(&self, name: &str, train: bool, id: u64, path: &Path) -> Result<()> {
        let cfg = self.cfg;
        let mut rng = StdRng::seed_from_u64(cfg.seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ id);
        let scenario = Scenario::random(self.sim.rest_uv(), cfg.anchor_radius, &mut rng);
        let first = if cfg.save_velocities { 0 } else { 1 };
        let timeline = cfg.steps() / cfg.frame_stride + 1;
        let keep = (train && cfg.storage == Storage::Clips).then(|| {
            let w = windows(
                &self.clips.plan(name, timeline, cfg.frame_dt(), first),
                self.clips.steps_for(cfg.frame_dt()),
                first,
            );
            // A rollout none of whose clips is kept still stores its last
            // two frames, so that the file is a valid rollout.
            if w.is_empty() {
                vec![(timeline - 2, 2)]
            } else {
                w
            }
        });
        let rollout = simulate_rollout(self.sim, cfg, &scenario, keep.as_deref(), name)?;
        rollout.save(path)
    }
}
