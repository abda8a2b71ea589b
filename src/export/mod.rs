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
//! NumPy: `springs.npz`'s keys plus `mass`, `rest_positions`, `pinned`, `rayleigh`, `gravity`,
//! `viscosity`).
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

use crate::backend::Backend;
use crate::cloth::Resampler;
use crate::data::npz::Array;
use crate::data::{Rollout, Track};
use crate::eval;
use crate::import::pc2::PointCache;
use crate::model::SpringNet;
use crate::progress::Progress;
use crate::run::Run;
pub use crate::run::surrogate::{
    FORMAT, FORMAT_COMPRESSION, FORMAT_CURVATURE, FORMAT_VISCOSITY, StabilityJson, SurrogateJson,
};
use crate::sim::Physics;

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
        let first = r.first_state_frame();
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
        let sim = eval::FreeRun::new(&plan.track, plan.first, plan.frames)
            .keeping(&plan.keep)
            .contact(plan.contact.as_ref())
            .simulate(self.model, &plan.physics, &self.run.device, |_| bar.inc(1))?;
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
        let (rayleigh, gravity, viscosity) = (json.rayleigh, json.gravity, json.viscosity);
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
        npz.insert("viscosity", Array::scalar(viscosity));
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
