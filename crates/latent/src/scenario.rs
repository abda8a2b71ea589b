//! The full-space reference of the latent paper's cloth example: an FEM sheet (StVK membrane,
//! dihedral bending, the paper's material) stepped by implicit Euler at 30 fps with pinned
//! vertices on prescribed paths.
//!
//! - `moving_corners` (§4.2): the sheet hangs in the `x–z` plane from its two top corners,
//!   which then move together along the line `direction`, `s(t) = A sin φ(t)`, at a speed that
//!   varies: `φ̇ = 2πf (1 + m sin(2πt/T))`.
//! - `cantilever` (the noise ablation, Fig. 10): the sheet lies flat in the `x–y` plane,
//!   clamped along its first row, and sags under gravity to rest.

use std::time::Instant;

use anyhow::{Result, bail};
use serde::{Deserialize, Serialize};

use springtime_core::cloth::triangles::V3;
use springtime_core::data::{MeshTruth, Rollout, Segment, SpringTruth};
use springtime_core::progress::Progress;
use springtime_core::source::fem::{Diagonal, FemCloth, FemMaterial, Membrane, grid_triangles};
use springtime_core::source::implicit::{ImplicitEuler, NewtonConfig};

/// The `[cloth]` section: an `nx × ny` vertex grid over a `width × height` sheet of the
/// paper's cloth (E = 10⁶ Pa, ν = 0.45, 3 mm thick, 1500 kg/m³; the paper prints "GPa",
/// physically absurd for cloth, so Pa is read).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ClothConfig {
    /// Vertices along the width (the grid's rows are `nx` long).
    pub nx: usize,
    /// Vertices along the height.
    pub ny: usize,
    /// Sheet width, m.
    pub width: f64,
    /// Sheet height, m.
    pub height: f64,
    /// Young's modulus of the material, Pa.
    pub youngs: f64,
    /// Poisson ratio.
    pub poisson: f64,
    /// Thickness, m.
    pub thickness: f64,
    /// Volume density, kg/m³.
    pub density: f64,
    /// Gravity, m/s².
    pub gravity: V3,
}

impl Default for ClothConfig {
    /// 12 × 16 vertices (the paper's 576 degrees of freedom) over 0.44 m × 0.6 m (the paper
    /// gives no size).
    fn default() -> Self {
        Self {
            nx: 12,
            ny: 16,
            width: 0.44,
            height: 0.6,
            youngs: 1e6,
            poisson: 0.45,
            thickness: 0.003,
            density: 1500.0,
            gravity: springtime_core::sim::GRAVITY,
        }
    }
}

impl ClothConfig {
    /// Checks ranges; errors name the key.
    pub fn validate(&self) -> Result<()> {
        if self.nx < 2 || self.ny < 2 {
            bail!("cloth.nx and cloth.ny must be at least 2");
        }
        for (key, v) in [
            ("cloth.width", self.width),
            ("cloth.height", self.height),
            ("cloth.youngs", self.youngs),
            ("cloth.thickness", self.thickness),
            ("cloth.density", self.density),
        ] {
            if !(v > 0.0 && v.is_finite()) {
                bail!("{key} must be positive, is {v}");
            }
        }
        if !(0.0..0.5).contains(&self.poisson) {
            bail!("cloth.poisson must lie in [0, 0.5), is {}", self.poisson);
        }
        Ok(())
    }

    /// Surface modulus `E t`, N/m.
    pub fn surface_modulus(&self) -> f64 {
        self.youngs * self.thickness
    }

    /// Plate bending modulus `D = E t³ / 12(1 − ν²)`, N·m.
    pub fn bending(&self) -> f64 {
        self.youngs * self.thickness.powi(3) / (12.0 * (1.0 - self.poisson * self.poisson))
    }

    /// Rest coordinates of vertex `r · nx + c`: `(c · width/(nx−1), r · height/(ny−1))`.
    pub fn rest_uv(&self) -> Vec<[f64; 2]> {
        let (hx, hy) = (
            self.width / (self.nx - 1) as f64,
            self.height / (self.ny - 1) as f64,
        );
        (0..self.ny)
            .flat_map(|r| (0..self.nx).map(move |c| [c as f64 * hx, r as f64 * hy]))
            .collect()
    }

    /// The FEM cloth: StVK membrane (discrete shells, as the paper), hinge bending `D`, no
    /// damping besides implicit Euler's own.
    pub fn fem(&self) -> FemCloth {
        let rest = self.rest_uv();
        let triangles = grid_triangles(self.nx, self.ny, Diagonal::Main);
        let youngs = vec![self.surface_modulus(); triangles.len()];
        FemCloth::new(
            rest,
            &triangles,
            &youngs,
            FemMaterial {
                poisson: self.poisson,
                bending: self.bending(),
                strain_damping: 0.0,
                membrane: Membrane::Stvk,
                areal_density: self.density * self.thickness,
                rayleigh: 0.0,
                gravity: self.gravity,
            },
        )
    }
}

/// What the pinned vertices do.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ScenarioKind {
    /// Two top corners moving along a line at varying speed (§4.2).
    MovingCorners,
    /// The first row clamped, the sheet flat and sagging (Fig. 10).
    Cantilever,
}

/// The `[scenario]` section.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ScenarioConfig {
    /// The scenario.
    pub kind: ScenarioKind,
    /// Frames to simulate (frame 0 is the start).
    pub frames: usize,
    /// Frames per second (the implicit step is one frame).
    pub fps: f64,
    /// Corner path amplitude `A`, m.
    pub amplitude: f64,
    /// Corner path direction (normalised).
    pub direction: V3,
    /// Base frequency `f` of the corner motion, Hz.
    pub frequency: f64,
    /// Speed modulation depth `m` in `[0, 1)`.
    pub modulation: f64,
    /// Speed modulation period `T`, s.
    pub modulation_period: f64,
}

impl Default for ScenarioConfig {
    /// Moving corners, 1500 frames at 30 fps (the paper trains on 0–750, tests on 750–1500),
    /// `A = 0.12` m along `(0.6, 0.8, 0)`, 0.5 Hz with speeds varying 0.4×–1.6× over 17 s.
    fn default() -> Self {
        Self {
            kind: ScenarioKind::MovingCorners,
            frames: 1500,
            fps: 30.0,
            amplitude: 0.12,
            direction: [0.6, 0.8, 0.0],
            frequency: 0.5,
            modulation: 0.6,
            modulation_period: 17.0,
        }
    }
}

impl ScenarioConfig {
    /// Checks ranges; errors name the key.
    pub fn validate(&self) -> Result<()> {
        if self.frames < 4 {
            bail!("scenario.frames must be at least 4, is {}", self.frames);
        }
        if !(self.fps > 0.0 && self.fps.is_finite()) {
            bail!("scenario.fps must be positive, is {}", self.fps);
        }
        if !(0.0..1.0).contains(&self.modulation) {
            bail!(
                "scenario.modulation must lie in [0, 1), is {}",
                self.modulation
            );
        }
        if !(self.modulation_period > 0.0) || !(self.frequency >= 0.0) {
            bail!("scenario.modulation_period must be positive and scenario.frequency ≥ 0");
        }
        if self.direction.iter().map(|c| c * c).sum::<f64>() == 0.0 {
            bail!("scenario.direction must not be the zero vector");
        }
        Ok(())
    }

    /// Time step, s.
    pub fn dt(&self) -> f64 {
        1.0 / self.fps
    }
}

/// A scenario made concrete on a sheet: the pinned vertices, the start and the paths.
#[derive(Debug, Clone)]
pub struct Scene {
    /// The scenario.
    pub config: ScenarioConfig,
    /// The pinned vertices.
    pub pinned: Vec<usize>,
    /// Positions at frame 0 (and −1: the sheet starts at rest).
    pub start: Vec<V3>,
}

impl Scene {
    /// The scene of `config` on the sheet `cloth`.
    pub fn new(cloth: &ClothConfig, config: &ScenarioConfig) -> Self {
        let rest = cloth.rest_uv();
        let (w, nx) = (cloth.width, cloth.nx);
        let (pinned, start) = match config.kind {
            ScenarioKind::MovingCorners => (
                vec![0, nx - 1],
                rest.iter().map(|p| [p[0] - 0.5 * w, 0.0, -p[1]]).collect(),
            ),
            ScenarioKind::Cantilever => (
                (0..nx).collect(),
                rest.iter().map(|p| [p[0] - 0.5 * w, p[1], 0.0]).collect(),
            ),
        };
        Self {
            config: config.clone(),
            pinned,
            start,
        }
    }

    /// The pinned vertices' prescribed positions at `frame`.
    pub fn targets(&self, frame: usize) -> Vec<V3> {
        let c = &self.config;
        let offset = match c.kind {
            ScenarioKind::Cantilever => [0.0; 3],
            ScenarioKind::MovingCorners => {
                let t = frame as f64 / c.fps;
                let two_pi = std::f64::consts::TAU;
                let (p, m) = (c.modulation_period, c.modulation);
                // φ(t) = 2πf (t + m T/2π (1 − cos 2πt/T)), so φ̇ = 2πf (1 + m sin 2πt/T).
                let phase =
                    two_pi * c.frequency * (t + m * p / two_pi * (1.0 - (two_pi * t / p).cos()));
                let s = c.amplitude * phase.sin();
                let n = c.direction.iter().map(|v| v * v).sum::<f64>().sqrt();
                c.direction.map(|d| s * d / n)
            }
        };
        self.pinned
            .iter()
            .map(|&i| [0, 1, 2].map(|k| self.start[i][k] + offset[k]))
            .collect()
    }
}

/// What generating a reference cost.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct GenerateStats {
    /// Frames simulated.
    pub frames: usize,
    /// Mean Newton iterations per step.
    pub mean_iterations: f64,
    /// Most Newton iterations of a step.
    pub max_iterations: usize,
    /// Mean wall time of one implicit step, µs.
    pub us_per_step: f64,
}

/// What a reference rollout records of the sheet it was simulated on, besides the motion.
pub(crate) struct SheetRecord {
    /// Rest positions in the sheet's plane, m.
    pub rest_uv: Vec<[f64; 2]>,
    /// Mass of the sheet, kg.
    pub total_mass: f64,
    /// Width, m.
    pub width: f64,
    /// Height, m.
    pub height: f64,
    /// The springs of a spring surrogate.
    pub springs: Option<SpringTruth>,
    /// The triangles of an FEM cloth.
    pub mesh: Option<MeshTruth>,
    /// Gravity, m/s².
    pub gravity: V3,
    /// Rayleigh damping.
    pub rayleigh: f64,
}

impl Scene {
    /// The scene's reference rollout: `positions` of every frame (frame-major) on `sheet`, one
    /// segment, its pinned vertices marked.
    pub(crate) fn rollout(&self, positions: Vec<f32>, sheet: SheetRecord) -> Rollout {
        let (frames, n) = (self.config.frames, self.start.len());
        let mut pinned = vec![false; n];
        for &i in &self.pinned {
            pinned[i] = true;
        }
        Rollout {
            path: Default::default(),
            frames,
            landmarks: n,
            positions,
            velocities: None,
            rest_uv: sheet.rest_uv,
            pinned,
            frame_dt: self.config.dt(),
            total_mass: sheet.total_mass,
            width: sheet.width,
            height: sheet.height,
            segments: vec![Segment {
                start: 0,
                offset: 0,
                len: frames,
            }],
            springs: sheet.springs,
            mesh: sheet.mesh,
            gravity: Some(sheet.gravity),
            rayleigh: Some(sheet.rayleigh),
            position_noise: None,
            visible: None,
        }
    }
}

/// Simulates the scene with implicit Euler; returns the rollout and its cost.
pub fn generate(
    cloth: &ClothConfig,
    scene: &Scene,
    newton: NewtonConfig,
    progress: &Progress,
) -> Result<(Rollout, GenerateStats)> {
    let fem = cloth.fem();
    let stepper = ImplicitEuler::new(fem.clone(), scene.config.dt(), newton)?;
    let frames = scene.config.frames;
    let n = scene.start.len();
    let mut positions: Vec<f32> = Vec::with_capacity(frames * n * 3);
    let push = |positions: &mut Vec<f32>, x: &[V3]| {
        positions.extend(x.iter().flat_map(|p| p.map(|v| v as f32)));
    };
    let (mut prev2, mut prev) = (scene.start.clone(), scene.start.clone());
    push(&mut positions, &prev);
    let bar = progress.bar(frames as u64, "implicit Euler");
    bar.set_position(1);
    let (mut iters, mut most) = (0usize, 0usize);
    let clock = Instant::now();
    for f in 1..frames {
        let (x, report) = stepper
            .step(&prev, &prev2, &scene.pinned, &scene.targets(f))
            .map_err(|e| anyhow::anyhow!("frame {f}: {e}"))?;
        iters += report.iterations;
        most = most.max(report.iterations);
        push(&mut positions, &x);
        prev2 = std::mem::replace(&mut prev, x);
        bar.set_position(f as u64 + 1);
    }
    bar.finish();
    let steps = (frames - 1).max(1) as f64;
    let stats = GenerateStats {
        frames,
        mean_iterations: iters as f64 / steps,
        max_iterations: most,
        us_per_step: clock.elapsed().as_secs_f64() * 1e6 / steps,
    };
    let triangles = fem.triangles();
    let rollout = scene.rollout(
        positions,
        SheetRecord {
            rest_uv: cloth.rest_uv(),
            total_mass: fem.masses().iter().sum(),
            width: cloth.width,
            height: cloth.height,
            springs: None,
            mesh: Some(MeshTruth {
                stiffness: Some(vec![cloth.surface_modulus(); triangles.len()]),
                triangles,
            }),
            gravity: cloth.gravity,
            rayleigh: 0.0,
        },
    );
    Ok((rollout, stats))
}
