//! Export for other tools: `springtime export <run-dir> --format F --out DIR` writes
//!
//! | format | files |
//! |---|---|
//! | `obj` | `rest.obj` and `rollout/frame_NNNN.obj`, one mesh per frame |
//! | `ply` | `rest.ply` and `rollout/frame_NNNN.ply`, binary little-endian |
//! | `ply-ascii` | the same as ASCII PLY |
//! | `gltf` / `glb` | `cloth.gltf` (buffer embedded as base64) / `cloth.glb`: the rest mesh with the rollout as one morph target per frame and a step-interpolated weights animation (Blender: *File › Import › glTF*; three.js: `GLTFLoader`) — see [`gltf`] |
//! | `pc2` | `rest.obj` and `rollout.pc2`, a point cache for Blender's Mesh Cache modifier (or Houdini) |
//!
//! and always `surrogate.json` (topology, rest positions and lengths, `k`, `b`, masses, the
//! rollout's pinned particles, simulation constants) and `surrogate.npz` (the same arrays for
//! NumPy: `springs.npz`'s keys plus `mass`, `rest_positions`, `pinned`, `rayleigh`, `gravity`).
//!
//! Meshes are the grid's quads split into two counter-clockwise triangles (normals +z at
//! rest); vertex `i` is particle `i`. OBJ, PLY and PC2 keep springtime's z-up metres; glTF is
//! y-up. Existing files are never overwritten without `--force`.

pub mod gltf;
pub mod web;

use std::fmt::Write as _;
use std::io::Write as _;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use serde::{Deserialize, Serialize};

use crate::backend::Backend;
use crate::cloth::{Resampler, SpringFamily};
use crate::data::npz::Array;
use crate::data::{Rollout, Track};
use crate::eval;
use crate::import::pc2::PointCache;
use crate::model::SpringNet;
use crate::progress::Progress;
use crate::sim::Physics;
use crate::train::Run;

/// Export file format.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Format {
    /// Wavefront OBJ per frame (`v`, `vt`, `f` lines).
    Obj,
    /// Binary little-endian PLY per frame (vertex `x y z s t`, face lists).
    Ply,
    /// ASCII PLY per frame.
    PlyAscii,
    /// glTF 2.0 JSON with an embedded buffer: morph-target animation.
    Gltf,
    /// glTF 2.0 binary container.
    Glb,
    /// Point cache (`rollout.pc2`) plus the rest mesh as OBJ.
    Pc2,
    /// A folder that opens offline in a browser (`index.html`) and simulates the surrogate live:
    /// a JavaScript step reading `surrogate.json`, drawn with three.js (see `web/README.md`).
    Web,
}

impl Format {
    /// Extension of the rest mesh file, without the dot.
    pub fn extension(self) -> &'static str {
        match self {
            Format::Obj | Format::Pc2 | Format::Web => "obj",
            Format::Ply | Format::PlyAscii => "ply",
            Format::Gltf => "gltf",
            Format::Glb => "glb",
        }
    }

    /// Whether the rollout is one mesh file per frame.
    pub fn per_frame(self) -> bool {
        matches!(self, Format::Obj | Format::Ply | Format::PlyAscii)
    }
}

/// Writes a triangle mesh as Wavefront OBJ, atomically: `positions` flat `[N, 3]`, optional
/// texture coordinates `uv` `[N]` (in `[0, 1]`), `triangles` of vertex indices from 0.
pub fn write_obj(
    path: &Path,
    comment: &str,
    positions: &[f32],
    uv: Option<&[[f64; 2]]>,
    triangles: &[[usize; 3]],
) -> Result<()> {
    let mut s = String::with_capacity(positions.len() * 12 + triangles.len() * 30);
    for line in comment.lines() {
        writeln!(s, "# {line}")?;
    }
    s.push_str("o cloth\n");
    for p in positions.chunks_exact(3) {
        writeln!(s, "v {} {} {}", p[0], p[1], p[2])?;
    }
    if let Some(uv) = uv {
        for t in uv {
            writeln!(s, "vt {:.6} {:.6}", t[0], t[1])?;
        }
    }
    for t in triangles {
        let [a, b, c] = t.map(|i| i + 1);
        if uv.is_some() {
            writeln!(s, "f {a}/{a} {b}/{b} {c}/{c}")?;
        } else {
            writeln!(s, "f {a} {b} {c}")?;
        }
    }
    crate::io::write_text(path, &s)
}

/// Writes a triangle mesh as PLY, atomically (arguments as [`write_obj`]; `uv` become the
/// vertex properties `s`, `t`): binary little-endian, or ASCII with `ascii`.
pub fn write_ply(
    path: &Path,
    comment: &str,
    positions: &[f32],
    uv: Option<&[[f64; 2]]>,
    triangles: &[[usize; 3]],
    ascii: bool,
) -> Result<()> {
    let n = positions.len() / 3;
    let mut s = String::with_capacity(positions.len() * 12 + triangles.len() * 24);
    s.push_str("ply\n");
    s.push_str(if ascii {
        "format ascii 1.0\n"
    } else {
        "format binary_little_endian 1.0\n"
    });
    for line in comment.lines() {
        writeln!(s, "comment {line}")?;
    }
    writeln!(
        s,
        "element vertex {n}\nproperty float x\nproperty float y\nproperty float z"
    )?;
    if uv.is_some() {
        s.push_str("property float s\nproperty float t\n");
    }
    writeln!(
        s,
        "element face {}\nproperty list uchar int vertex_indices\nend_header",
        triangles.len()
    )?;
    if ascii {
        for (i, p) in positions.chunks_exact(3).enumerate() {
            write!(s, "{} {} {}", p[0], p[1], p[2])?;
            if let Some(uv) = uv {
                write!(s, " {:.6} {:.6}", uv[i][0], uv[i][1])?;
            }
            s.push('\n');
        }
        for [a, b, c] in triangles {
            writeln!(s, "3 {a} {b} {c}")?;
        }
        return crate::io::write_text(path, &s);
    }
    let mut bytes = s.into_bytes();
    for (i, p) in positions.chunks_exact(3).enumerate() {
        for c in p {
            bytes.extend_from_slice(&c.to_le_bytes());
        }
        if let Some(uv) = uv {
            bytes.extend_from_slice(&(uv[i][0] as f32).to_le_bytes());
            bytes.extend_from_slice(&(uv[i][1] as f32).to_le_bytes());
        }
    }
    for t in triangles {
        bytes.push(3);
        for &i in t {
            bytes.extend_from_slice(&(i as i32).to_le_bytes());
        }
    }
    crate::io::write_atomic(path, |mut f| {
        f.write_all(&bytes)?;
        f.sync_all()?;
        Ok(())
    })
}

/// The `format` tag of [`SurrogateJson`].
pub const FORMAT: &str = "springtime-surrogate/1";
/// The format tag of a surrogate with curvature elements: a reader of the first version, which
/// knows springs only, must not take it for one.
pub const FORMAT_CURVATURE: &str = "springtime-surrogate/2";

/// `surrogate.json`: everything needed to simulate the learned cloth elsewhere (and what
/// `springtime latent train --from` distills; [`SurrogateJson::read`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SurrogateJson {
    /// Always `springtime-surrogate/1`.
    pub format: String,
    /// Units of the values.
    pub units: String,
    /// Particles along width and height of a grid surrogate, particle `row * nx + col`; `null`
    /// for a surrogate on the data's mesh (`cloth.layout = "data"`).
    pub grid: Option<[usize; 2]>,
    /// The rest sheet's triangles (particle indices, counter-clockwise in the rest rectangle).
    #[serde(default)]
    pub triangles: Vec<[usize; 3]>,
    /// Rest rectangle width, m.
    pub width: f64,
    /// Rest rectangle height, m.
    pub height: f64,
    /// Mass of every particle, kg.
    pub masses: Vec<f64>,
    /// Rest positions `(u, v, 0)`, m.
    pub rest_positions: Vec<[f64; 3]>,
    /// Spring endpoints (particle indices).
    pub springs: Vec<[usize; 2]>,
    /// `structural`, `shear` or `bending` per spring.
    pub family: Vec<SpringFamily>,
    /// Rest length per spring, m.
    pub rest_length: Vec<f64>,
    /// Stiffness per spring, N/m (the model's single precision).
    pub k: Vec<f32>,
    /// Damping per spring (along the spring, Eq. 4), N·s/m.
    pub b: Vec<f32>,
    /// Particles pinned in the exported rollout (its anchors), empty without one.
    pub pinned: Vec<usize>,
    /// Rayleigh damping `c` of the force `−c ẋ` on a particle of the mean mass, N·s/m (on a
    /// particle of mass `m_i`, `c · m_i / mean(m)`: damping per unit mass).
    pub rayleigh: f64,
    /// Gravity, m/s².
    pub gravity: [f64; 3],
    /// Integration step the surrogate was trained with (frame time / substeps), s, when known.
    pub dt: Option<f64>,
    /// Curvature elements `(i, j, l)` of a grid (`cloth.curvature`), each with the energy
    /// `½ κ |x_i − 2x_j + x_l|²`; absent without.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub curvature: Vec<[usize; 3]>,
    /// Stiffness `κ` per curvature element, N/m.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub curvature_k: Vec<f32>,
    /// Time between frames, s: `substeps` steps of `dt` make one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub frame_dt: Option<f64>,
    /// Integration steps per frame.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub substeps: Option<usize>,
    /// The integrator's particle mass `m` (Rayleigh damping per unit mass is `rayleigh / m`),
    /// kg.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mass: Option<f64>,
    /// The explicit step's stability estimate at `dt` (without contact).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stability: Option<StabilityJson>,
}

/// `surrogate.json`'s `stability`: the step is stable while `number < limit`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StabilityJson {
    /// `dt²ω² + 2·dt·γ` of the stiffest mode.
    pub number: f64,
    /// 4: the explicit step's limit.
    pub limit: f64,
}

impl SurrogateJson {
    /// The spring network `model` of `run`, with the particles `pinned`, stepped by `physics`
    /// (its frame time, substeps, mass and stability) when known.
    pub fn of(run: &Run, model: &SpringNet, pinned: &[usize], physics: Option<&Physics>) -> Self {
        let (topo, config) = (&run.topology, &run.config);
        Self {
            format: if topo.curvature.is_empty() {
                FORMAT
            } else {
                FORMAT_CURVATURE
            }
            .into(),
            units: "SI: m, kg, s, N/m, N·s/m".into(),
            grid: topo.grid,
            triangles: topo.triangles.clone(),
            width: topo.width,
            height: topo.height,
            masses: topo.masses(run.particle_mass()),
            rest_positions: topo.rest_positions(),
            springs: topo.springs.clone(),
            family: topo.family.clone(),
            rest_length: topo.rest_length.clone(),
            k: model.k_values().iter().map(|&x| x as f32).collect(),
            b: model.b_values().iter().map(|&x| x as f32).collect(),
            pinned: pinned.to_vec(),
            rayleigh: config.sim.rayleigh.or(crate::sim::RAYLEIGH),
            gravity: config.sim.gravity.or(crate::sim::GRAVITY),
            dt: physics.map(Physics::sim_dt),
            curvature: topo.curvature.clone(),
            curvature_k: model.curvature_values().iter().map(|&x| x as f32).collect(),
            frame_dt: physics.map(|p| p.frame_dt),
            substeps: physics.map(|p| p.substeps),
            mass: physics.map(|p| p.mass),
            stability: physics.map(|p| StabilityJson {
                number: p.stability_of(topo, model).number(),
                limit: 4.0,
            }),
        }
    }

    /// Reads and checks a `surrogate.json`; errors name the file and the key.
    pub fn read(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path)
            .with_context(|| format!("cannot read {}", path.display()))?;
        let json: Self = serde_json::from_str(&text)
            .with_context(|| format!("{} is not a springtime surrogate.json", path.display()))?;
        json.validate()
            .with_context(|| format!("{} is not a valid surrogate", path.display()))?;
        Ok(json)
    }

    /// Checks the format tag and that the per-particle and per-spring arrays agree.
    pub fn validate(&self) -> Result<()> {
        let expected = if self.curvature.is_empty() {
            FORMAT
        } else {
            FORMAT_CURVATURE
        };
        if self.format != expected {
            bail!("key `format` is {:?}, expected {expected:?}", self.format);
        }
        if let Some([nx, ny]) = self.grid
            && (nx < 2 || ny < 2)
        {
            bail!("key `grid` is [{nx}, {ny}]: at least 2 particles along each side");
        }
        if !(self.width > 0.0 && self.height > 0.0) {
            bail!("keys `width` and `height` must be positive");
        }
        let p = match self.grid {
            Some([nx, ny]) => nx * ny,
            None => self.rest_positions.len(),
        };
        for (key, len) in [
            ("masses", self.masses.len()),
            ("rest_positions", self.rest_positions.len()),
        ] {
            if len != p {
                bail!("key `{key}` has {len} entries, the sheet has {p} particles");
            }
        }
        if self.grid.is_none() && self.triangles.is_empty() {
            bail!("key `triangles` is empty: a surrogate without a `grid` needs its mesh");
        }
        if let Some(t) = self.triangles.iter().find(|t| t.iter().any(|&v| v >= p)) {
            bail!("key `triangles` has a triangle {t:?} past the {p} particles");
        }
        let s = self.springs.len();
        for (key, len) in [
            ("family", self.family.len()),
            ("rest_length", self.rest_length.len()),
            ("k", self.k.len()),
            ("b", self.b.len()),
        ] {
            if len != s {
                bail!("key `{key}` has {len} entries, key `springs` has {s}");
            }
        }
        if let Some(&[a, b]) = self.springs.iter().find(|&&[a, b]| a >= p || b >= p) {
            bail!("key `springs` has a spring ({a}, {b}) past the {p} particles");
        }
        if self.curvature_k.len() != self.curvature.len() {
            bail!(
                "key `curvature_k` has {} entries, key `curvature` has {}",
                self.curvature_k.len(),
                self.curvature.len()
            );
        }
        if let Some(e) = self.curvature.iter().find(|e| e.iter().any(|&i| i >= p)) {
            bail!("key `curvature` has an element {e:?} past the {p} particles");
        }
        if let Some(v) = self
            .curvature_k
            .iter()
            .find(|v| !(v.is_finite() && **v >= 0.0))
        {
            bail!("key `curvature_k` holds {v}: every value must be finite and non-negative");
        }
        if let Some(i) = self.pinned.iter().find(|&&i| i >= p) {
            bail!("key `pinned` has particle {i}, past the {p} particles");
        }
        if let Some(m) = self.masses.iter().find(|m| !(m.is_finite() && **m > 0.0)) {
            bail!("key `masses` holds {m}: every mass must be finite and positive");
        }
        for (key, values) in [("k", &self.k), ("b", &self.b)] {
            if let Some(v) = values.iter().find(|v| !(v.is_finite() && **v >= 0.0)) {
                bail!("key `{key}` holds {v}: every value must be finite and non-negative");
            }
        }
        if !(self.rayleigh.is_finite() && self.rayleigh >= 0.0) {
            bail!(
                "key `rayleigh` is {}: finite and non-negative",
                self.rayleigh
            );
        }
        // The rest state is the grid (a run's rest rectangle), and every rest length the
        // distance between its ends there.
        let tol = 1e-5 * self.width.max(self.height);
        for (i, q) in self.rest_positions.iter().enumerate() {
            let Some([nx, ny]) = self.grid else { break };
            let (r, c) = (i / nx, i % nx);
            let grid = [
                self.width * c as f64 / (nx - 1) as f64,
                self.height * r as f64 / (ny - 1) as f64,
            ];
            if (q[0] - grid[0]).abs() > tol || (q[1] - grid[1]).abs() > tol || q[2].abs() > tol {
                bail!(
                    "key `rest_positions`: particle {i} is at {q:?}, not at its grid point \
                     ({}, {}, 0) of the {nx} × {ny} grid over {} × {} m",
                    grid[0],
                    grid[1],
                    self.width,
                    self.height
                );
            }
        }
        for (s, (&[a, b], &l)) in self.springs.iter().zip(&self.rest_length).enumerate() {
            let (pa, pb) = (self.rest_positions[a], self.rest_positions[b]);
            let d = ((pa[0] - pb[0]).powi(2) + (pa[1] - pb[1]).powi(2) + (pa[2] - pb[2]).powi(2))
                .sqrt();
            if a == b || !(l > 0.0) || (l - d).abs() > tol {
                bail!(
                    "key `rest_length`: spring {s} ({a}, {b}) has rest length {l}, its ends are \
                     {d} m apart at rest"
                );
            }
        }
        Ok(())
    }

    /// JSON text with one key per line and each array on its line (readable and compact, where
    /// pretty printing would put every number on a line of its own).
    pub fn to_text(&self) -> Result<String> {
        // Destructured so that a new field cannot be forgotten here.
        let SurrogateJson {
            format,
            units,
            grid,
            triangles,
            width,
            height,
            masses,
            rest_positions,
            springs,
            family,
            rest_length,
            k,
            b,
            pinned,
            rayleigh,
            gravity,
            dt,
            curvature,
            curvature_k,
            frame_dt,
            substeps,
            mass,
            stability,
        } = self;
        fn j<T: Serialize>(v: &T) -> Result<String> {
            Ok(serde_json::to_string(v)?)
        }
        let mut fields: Vec<(&str, String)> = vec![
            ("format", j(format)?),
            ("units", j(units)?),
            ("grid", j(grid)?),
            ("triangles", j(triangles)?),
            ("width", j(width)?),
            ("height", j(height)?),
            ("masses", j(masses)?),
            ("rest_positions", j(rest_positions)?),
            ("springs", j(springs)?),
            ("family", j(family)?),
            ("rest_length", j(rest_length)?),
            ("k", j(k)?),
            ("b", j(b)?),
            ("pinned", j(pinned)?),
            ("rayleigh", j(rayleigh)?),
            ("gravity", j(gravity)?),
            ("dt", j(dt)?),
        ];
        if !curvature.is_empty() {
            fields.push(("curvature", j(curvature)?));
            fields.push(("curvature_k", j(curvature_k)?));
        }
        if let Some(v) = frame_dt {
            fields.push(("frame_dt", j(v)?));
        }
        if let Some(v) = substeps {
            fields.push(("substeps", j(v)?));
        }
        if let Some(v) = mass {
            fields.push(("mass", j(v)?));
        }
        if let Some(v) = stability {
            fields.push(("stability", j(v)?));
        }
        let body: Vec<String> = fields
            .iter()
            .map(|(key, v)| format!("  \"{key}\": {v}"))
            .collect();
        Ok(format!("{{\n{}\n}}\n", body.join(",\n")))
    }
}

/// Choices of an export.
#[derive(Debug, Clone)]
pub struct ExportOptions {
    /// Mesh format.
    pub format: Format,
    /// Output directory.
    pub out: PathBuf,
    /// Rollout file whose first frame starts the simulated rollout and whose pinned particles
    /// it follows (default: the run's first test rollout).
    pub init: Option<PathBuf>,
    /// Directory of test rollouts to take the first of (instead of the run's test split).
    pub data: Option<PathBuf>,
    /// Seconds to simulate (default: the length of the initial rollout).
    pub seconds: Option<f64>,
    /// Frames per second of the exported sequence.
    pub fps: f64,
    /// Overwrite existing files.
    pub force: bool,
    /// Compute backend (default: the run's).
    pub backend: Option<Backend>,
    /// Drape scene: export the cloth released flat above its colliders instead of a test
    /// rollout (see [`crate::drape`]).
    pub scene: Option<PathBuf>,
}

/// What an export simulates.
struct Plan {
    physics: Physics,
    track: Track,
    first: usize,
    frames: usize,
    keep: Vec<usize>,
    /// Frames per second of the kept frames.
    fps: f64,
    /// The rollout or scene file it starts from.
    from: PathBuf,
    contact: Option<crate::sim::Contact>,
}

/// What an export wrote.
#[derive(Debug, Clone)]
pub struct ExportSummary {
    /// Every file written.
    pub files: Vec<PathBuf>,
    /// The rollout the sequence starts from, if any.
    pub rollout: Option<PathBuf>,
    /// Frames of the sequence (0 without a rollout).
    pub frames: usize,
    /// Frames per second of the sequence as written.
    pub fps: f64,
    /// Why there is no sequence, when there is none.
    pub note: Option<String>,
}

/// The simulated sequence, as written.
#[derive(Default)]
struct Sequence {
    /// Pinned particles (the starting rollout's).
    pinned: Vec<usize>,
    /// Frames written.
    frames: usize,
    /// Positions `[frames, P, 3]` and times of a glTF animation (empty for the other formats).
    animation: (Vec<f32>, Vec<f64>),
}

/// The files of one export.
struct Paths {
    /// `rest.<ext>` (or `cloth.gltf`/`.glb`).
    mesh: PathBuf,
    json: PathBuf,
    npz: PathBuf,
    pc2: PathBuf,
    /// Directory of per-frame meshes.
    frames: PathBuf,
}

impl Paths {
    fn frame(&self, i: usize, ext: &str) -> PathBuf {
        self.frames.join(format!("frame_{i:04}.{ext}"))
    }
}

/// An export under way: the opened run, its surrogate and the rest sheet's mesh.
struct Export<'a> {
    run_dir: &'a Path,
    options: &'a ExportOptions,
    run: &'a Run,
    model: &'a SpringNet,
    paths: Paths,
    triangles: Vec<[usize; 3]>,
    /// Texture coordinates of the particles (the rest rectangle scaled to [0, 1]²).
    uv: Vec<[f64; 2]>,
    /// Rest positions `[P, 3]`.
    rest: Vec<f32>,
}

/// Exports a finished run (see the module documentation).
pub fn export_run(
    run_dir: &Path,
    options: &ExportOptions,
    progress: &Progress,
) -> Result<ExportSummary> {
    if !(options.fps > 0.0 && options.fps.is_finite()) {
        bail!("--fps must be positive, is {}", options.fps);
    }
    if let Some(s) = options.seconds
        && !(s > 0.0 && s.is_finite())
    {
        bail!("--seconds must be positive, is {s}");
    }
    let run = Run::open(run_dir, &[], options.backend)?;
    let model = run.springs()?;
    let ex = Export::new(run_dir, options, &run, model);
    if options.format == Format::Web {
        return ex.web();
    }
    let (plan, note) = ex.plan()?;
    ex.check_fresh(plan.as_ref())?;
    let out = &options.out;
    std::fs::create_dir_all(out).with_context(|| format!("cannot create {}", out.display()))?;
    let mut files = Vec::new();
    let gltf = matches!(options.format, Format::Gltf | Format::Glb);
    if !gltf {
        let topo = &run.topology;
        ex.write_mesh(
            &ex.paths.mesh,
            &format!(
                "springtime surrogate of {}: rest sheet, {}, metres",
                run_dir.display(),
                topo.describe()
            ),
            &ex.rest,
        )?;
        files.push(ex.paths.mesh.clone());
    }
    let sequence = match &plan {
        Some(plan) => ex.write_sequence(plan, &mut files, progress)?,
        None => Sequence::default(),
    };
    if gltf {
        let mesh = gltf::AnimatedMesh {
            name: "cloth",
            rest: &ex.rest,
            uv: &ex.uv,
            triangles: &ex.triangles,
            frames: &sequence.animation.0,
            times: &sequence.animation.1,
        };
        gltf::write(&ex.paths.mesh, &mesh, options.format == Format::Glb)?;
        files.push(ex.paths.mesh.clone());
    }
    ex.write_surrogate(&sequence.pinned, plan.as_ref().map(|p| &p.physics))?;
    files.push(ex.paths.json.clone());
    files.push(ex.paths.npz.clone());
    Ok(ExportSummary {
        files,
        rollout: plan.as_ref().map(|p| p.from.clone()),
        frames: sequence.frames,
        fps: plan.as_ref().map_or(0.0, |p| p.fps),
        note,
    })
}

impl<'a> Export<'a> {
    fn new(
        run_dir: &'a Path,
        options: &'a ExportOptions,
        run: &'a Run,
        model: &'a SpringNet,
    ) -> Self {
        let topo = &run.topology;
        let out = &options.out;
        let ext = options.format.extension();
        let gltf = matches!(options.format, Format::Gltf | Format::Glb);
        Self {
            run_dir,
            options,
            run,
            model,
            paths: Paths {
                mesh: out.join(format!("{}.{ext}", if gltf { "cloth" } else { "rest" })),
                json: out.join("surrogate.json"),
                npz: out.join("surrogate.npz"),
                pc2: out.join("rollout.pc2"),
                frames: out.join("rollout"),
            },
            triangles: topo.triangles.clone(),
            uv: topo
                .rest_uv
                .iter()
                .map(|p| [p[0] / topo.width, p[1] / topo.height])
                .collect(),
            rest: topo
                .rest_positions()
                .iter()
                .flat_map(|p| p.map(|c| c as f32))
                .collect(),
        }
    }

    /// The rollout the sequence starts from: `--init`, else the run's first test rollout
    /// (`None` with the reason when there is none, or with a scene).
    fn start(&self) -> Result<(Option<Rollout>, Option<String>)> {
        if self.options.scene.is_some() {
            return Ok((None, None));
        }
        starting_rollout(
            self.run,
            self.options.init.as_deref(),
            self.options.data.as_deref(),
        )
    }

    /// What to simulate: the drape scene, or the starting rollout; checked for stability.
    fn plan(&self) -> Result<(Option<Plan>, Option<String>)> {
        let (topo, model, config) = (&self.run.topology, self.model, &self.run.config);
        let stability = |physics: &Physics, contact: Option<&crate::sim::Contact>| {
            let st = physics.stability_of(topo, model);
            let st = match contact {
                Some(c) => st.with_contact(&c.params),
                None => st,
            };
            st.check("the trained surrogate", config.sim.allow_unstable)
        };
        let plan = |physics: Physics, track, first, seconds: f64, from, contact| {
            let frame_dt = physics.frame_dt;
            let frames = ((seconds / frame_dt).round() as usize).max(1);
            let stride = ((1.0 / (self.options.fps * frame_dt)).round() as usize).max(1);
            Plan {
                physics,
                track,
                first,
                frames,
                keep: (0..=frames).step_by(stride).collect(),
                fps: 1.0 / (stride as f64 * frame_dt),
                from,
                contact,
            }
        };
        if let Some(scene_path) = &self.options.scene {
            let scene = crate::drape::Scene::load(scene_path, &[])?;
            let physics = self.run.physics(self.run.meta.frame_dt);
            let number = physics.stability_of(topo, model).number();
            let contact = scene.contact(topo.width.max(topo.height), physics.sim_dt(), number);
            stability(&physics, Some(&contact))?;
            let x0 = scene.release(&topo.rest_uv, topo.width, topo.height);
            let seconds = self.options.seconds.unwrap_or(scene.config.seconds);
            let track = Track::at_rest(&x0);
            return Ok((
                Some(plan(
                    physics,
                    track,
                    0,
                    seconds,
                    scene_path.clone(),
                    Some(contact),
                )),
                None,
            ));
        }
        let (rollout, note) = self.start()?;
        let Some(r) = rollout else {
            return Ok((None, note));
        };
        let track = Track::new(&r, &Resampler::new(&r.rest_uv, &topo.rest_uv));
        let first = r.first_usable_frame();
        let physics = self.run.physics(r.frame_dt);
        stability(&physics, None)?;
        let seconds = self
            .options
            .seconds
            .unwrap_or((r.frames - 1 - first) as f64 * r.frame_dt);
        Ok((
            Some(plan(physics, track, first, seconds, r.path.clone(), None)),
            note,
        ))
    }

    /// Refuses to overwrite any file of this export unless `--force`; with it, removes stale
    /// frames of an earlier, longer export (they would join the sequence).
    fn check_fresh(&self, plan: Option<&Plan>) -> Result<()> {
        let (paths, options) = (&self.paths, self.options);
        let ext = options.format.extension();
        let mut all = vec![paths.mesh.clone(), paths.json.clone(), paths.npz.clone()];
        if let Some(plan) = plan {
            match options.format {
                f if f.per_frame() => all.extend((0..plan.keep.len()).map(|i| paths.frame(i, ext))),
                Format::Pc2 => all.push(paths.pc2.clone()),
                _ => {}
            }
        }
        let existing: Vec<&PathBuf> = all.iter().filter(|p| p.exists()).collect();
        if let Some(first) = existing.first()
            && !options.force
        {
            bail!(
                "{} exists{}; pass --force to overwrite",
                first.display(),
                match existing.len() {
                    1 => String::new(),
                    n => format!(" (and {} more of the files to write)", n - 1),
                }
            );
        }
        if options.force && paths.frames.is_dir() {
            for e in std::fs::read_dir(&paths.frames)?.flatten() {
                let name = e.file_name().to_string_lossy().into_owned();
                if name.starts_with("frame_") && (name.ends_with(".obj") || name.ends_with(".ply"))
                {
                    std::fs::remove_file(e.path())
                        .with_context(|| format!("cannot remove {}", e.path().display()))?;
                }
            }
        }
        Ok(())
    }

    /// Writes one mesh of the sheet in the export's format (OBJ or PLY).
    fn write_mesh(&self, path: &Path, comment: &str, pos: &[f32]) -> Result<()> {
        let (uv, tris) = (Some(self.uv.as_slice()), &self.triangles);
        match self.options.format {
            Format::Ply => write_ply(path, comment, pos, uv, tris, false),
            Format::PlyAscii => write_ply(path, comment, pos, uv, tris, true),
            _ => write_obj(path, comment, pos, uv, tris),
        }
    }

    /// Simulates the plan and writes its frames (per-frame meshes or a point cache; a glTF
    /// animation is returned to be written with the mesh).
    fn write_sequence(
        &self,
        plan: &Plan,
        files: &mut Vec<PathBuf>,
        progress: &Progress,
    ) -> Result<Sequence> {
        let bar = progress.bar(plan.frames as u64, "simulate");
        let sim = eval::simulate_track(
            self.model,
            &plan.physics,
            plan.contact.as_ref(),
            &plan.track,
            plan.first,
            plan.frames,
            &plan.keep,
            &self.run.device,
            |_| bar.inc(1),
        )?;
        bar.finish();
        let p = self.run.topology.num_particles();
        let mut seq = Sequence {
            pinned: plan
                .track
                .pinned
                .iter()
                .enumerate()
                .filter_map(|(i, &p)| p.then_some(i))
                .collect(),
            frames: sim.frames.len(),
            animation: Default::default(),
        };
        let times: Vec<f64> = sim
            .frames
            .iter()
            .map(|&j| j as f64 * plan.physics.frame_dt)
            .collect();
        let positions = &sim.positions[..seq.frames * p * 3];
        match self.options.format {
            f if f.per_frame() => {
                let bar = progress.bar(seq.frames as u64, "export");
                for (i, t) in times.iter().enumerate() {
                    let path = self.paths.frame(i, f.extension());
                    self.write_mesh(
                        &path,
                        &format!(
                            "springtime surrogate of {}: frame {i}, t = {t:.6} s, simulated from {}",
                            self.run_dir.display(),
                            plan.from.display()
                        ),
                        &positions[i * p * 3..(i + 1) * p * 3],
                    )?;
                    files.push(path);
                    bar.inc(1);
                }
                bar.finish();
            }
            Format::Pc2 => {
                PointCache {
                    start_frame: 0.0,
                    sample_rate: 1.0,
                    points: p,
                    samples: seq.frames,
                    positions: positions.to_vec(),
                }
                .write(&self.paths.pc2)?;
                files.push(self.paths.pc2.clone());
            }
            _ => seq.animation = (positions.to_vec(), times),
        }
        Ok(seq)
    }

    /// `surrogate.json` and `surrogate.npz`: the springs, masses, rest state and constants.
    /// Returns the text of `surrogate.json`.
    fn write_surrogate(&self, pinned: &[usize], physics: Option<&Physics>) -> Result<String> {
        let topo = &self.run.topology;
        let json = SurrogateJson::of(self.run, self.model, pinned, physics);
        let (rayleigh, gravity) = (json.rayleigh, json.gravity);
        let p = topo.num_particles();
        let text = json.to_text()?;
        crate::io::write_text(&self.paths.json, &text)?;
        let mut npz = crate::train::run::springs_npz(topo, self.model, self.run.particle_mass());
        npz.insert("mass", Array::f64(&[p], &json.masses));
        npz.insert("rest_positions", Array::f32(&[p, 3], &self.rest));
        let mut pin_mask = vec![false; p];
        for &i in pinned {
            pin_mask[i] = true;
        }
        npz.insert("pinned", Array::bool(&[p], &pin_mask));
        npz.insert("rayleigh", Array::scalar(rayleigh));
        npz.insert("gravity", Array::f64(&[3], &gravity));
        npz.write(&self.paths.npz)?;
        Ok(text)
    }

    /// `--format web`: the page, and the surrogate with the pins and physics of the rest start
    /// ([`rest_start`]), which `springtime simulate --rest` simulates too.
    fn web(&self) -> Result<ExportSummary> {
        let options = self.options;
        if options.scene.is_some() {
            bail!(
                "--scene is not for --format web: the page has its own scenes (a sphere and a \
                 table to drop the cloth on)"
            );
        }
        let start = rest_start(self.run, options.init.as_deref(), options.data.as_deref())?;
        start
            .physics
            .stability_of(&self.run.topology, self.model)
            .check("the trained surrogate", self.run.config.sim.allow_unstable)?;
        let mut files = vec![self.paths.json.clone(), self.paths.npz.clone()];
        files.extend(web::files(&options.out));
        if let Some(first) = files.iter().find(|p| p.exists())
            && !options.force
        {
            bail!("{} exists; pass --force to overwrite", first.display());
        }
        std::fs::create_dir_all(&options.out)
            .with_context(|| format!("cannot create {}", options.out.display()))?;
        let text = self.write_surrogate(&start.pinned, Some(&start.physics))?;
        web::write(&options.out, &text)?;
        Ok(ExportSummary {
            files,
            rollout: start.from,
            frames: 0,
            fps: 0.0,
            note: start.note,
        })
    }
}

/// The rollout an export or a simulation starts from: `init`, else the first test rollout of
/// the run's data (or of `data`); `None` with the reason when there is none.
fn starting_rollout(
    run: &Run,
    init: Option<&Path>,
    data: Option<&Path>,
) -> Result<(Option<Rollout>, Option<String>)> {
    let (init, note) = match init {
        Some(p) => (Some(p.to_path_buf()), None),
        None => {
            let mut config = run.config.data.clone();
            if let Some(d) = data {
                config.test_dir = Some(d.to_path_buf());
            }
            match config.split() {
                Ok(s) if !s.test.is_empty() => (Some(s.test[0].clone()), None),
                Ok(_) => (
                    None,
                    Some("the run's data lists no test rollouts".to_string()),
                ),
                Err(e) => (None, Some(format!("{e:#}"))),
            }
        }
    };
    Ok((init.as_deref().map(Rollout::load).transpose()?, note))
}

/// The rest start of the web page and of `springtime simulate --rest`: the surrogate's rest
/// sheet at zero velocity, with the particles pinned in the starting rollout (`--init`, else the
/// run's first test rollout; none without one) held where they are, stepped at that rollout's
/// frame time (else the run's).
#[derive(Debug, Clone)]
pub struct RestStart {
    /// Pinned particles, ascending.
    pub pinned: Vec<usize>,
    /// The surrogate's physics at the start's frame time.
    pub physics: Physics,
    /// The rollout the pins come from.
    pub from: Option<PathBuf>,
    /// Why there is no rollout, when there is none.
    pub note: Option<String>,
}

/// See [`RestStart`].
pub fn rest_start(run: &Run, init: Option<&Path>, data: Option<&Path>) -> Result<RestStart> {
    let (rollout, note) = starting_rollout(run, init, data)?;
    let topo = &run.topology;
    let pinned = match &rollout {
        Some(r) => Track::new(r, &Resampler::new(&r.rest_uv, &topo.rest_uv))
            .pinned
            .iter()
            .enumerate()
            .filter_map(|(i, &p)| p.then_some(i))
            .collect(),
        None => Vec::new(),
    };
    let frame_dt = rollout.as_ref().map_or(run.meta.frame_dt, |r| r.frame_dt);
    Ok(RestStart {
        pinned,
        physics: run.physics(frame_dt),
        from: rollout.map(|r| r.path),
        note,
    })
}

/// Counts the vertices and faces of an OBJ or PLY (ASCII or binary) file (for checks).
pub fn count_mesh(path: &Path) -> Result<(usize, usize)> {
    let bytes = std::fs::read(path).with_context(|| format!("cannot read {}", path.display()))?;
    if bytes.starts_with(b"ply") {
        let end = bytes
            .windows(10)
            .position(|w| w == b"end_header")
            .unwrap_or(bytes.len());
        let text = String::from_utf8_lossy(&bytes[..end]);
        let count = |key: &str| -> Result<usize> {
            text.lines()
                .find_map(|l| l.strip_prefix(key))
                .and_then(|n| n.trim().parse().ok())
                .with_context(|| format!("{}: no `{key}` line", path.display()))
        };
        return Ok((count("element vertex ")?, count("element face ")?));
    }
    let text = String::from_utf8_lossy(&bytes);
    let mut v = 0;
    let mut f = 0;
    for l in text.lines() {
        if l.starts_with("v ") {
            v += 1;
        } else if l.starts_with("f ") {
            f += 1;
        }
    }
    Ok((v, f))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn surrogate_json_text_parses_back_to_the_same_value() {
        let j = SurrogateJson {
            format: "springtime-surrogate/1".into(),
            units: "SI".into(),
            grid: Some([2, 2]),
            triangles: vec![[0, 1, 3], [0, 3, 2]],
            width: 1.0,
            height: 1.0,
            masses: vec![0.1; 4],
            rest_positions: vec![[0.0, 0.0, 0.0]; 4],
            springs: vec![[0, 1], [2, 3]],
            family: vec![SpringFamily::Structural; 2],
            rest_length: vec![1.0, 1.0],
            k: vec![10.0, 20.0],
            b: vec![1.0, 2.0],
            pinned: vec![0],
            rayleigh: 0.1,
            gravity: [0.0, 0.0, -9.81],
            dt: None,
            curvature: Vec::new(),
            curvature_k: Vec::new(),
            frame_dt: None,
            substeps: None,
            mass: None,
            stability: None,
        };
        let text = j.to_text().unwrap();
        let back: serde_json::Value = serde_json::from_str(&text).unwrap();
        assert_eq!(back, serde_json::to_value(&j).unwrap());
        assert_eq!(text.lines().count(), 19);
    }
}
