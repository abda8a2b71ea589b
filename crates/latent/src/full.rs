//! The full-space cloth a latent model compresses: the paper's FEM sheet stepped by implicit
//! Euler, or a trained springtime surrogate stepped by its explicit integrator
//! ([`super::surrogate`], distillation). One type answers the three questions the pipeline
//! asks of it: the reference motion of a scene, the incremental potential the latent loss
//! minimises, and the time of one full-space frame for the benchmark.

use springtime_core::settings::Job;
use std::path::Path;
use std::time::Instant;

use anyhow::{Context, Result};
use burn::tensor::Device;

use super::LatentConfig;
use super::energy::Potential;
use super::scenario::{GenerateStats, Scene, generate};
use super::surrogate::SpringSheet;
use super::train::{LatentRun, Reference};
use springtime_core::data::Rollout;
use springtime_core::progress::Progress;
use springtime_core::source::implicit::ImplicitEuler;

/// The full-space cloth.
#[derive(Debug, Clone)]
pub enum FullSpace {
    /// The config's FEM sheet and Newton solver (the paper).
    Fem(Box<LatentConfig>),
    /// A spring surrogate (distillation).
    Springs(Box<SpringSheet>),
}

/// The measured cost of full-space frames.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FullTiming {
    /// Wall time of one frame, µs.
    pub us_per_frame: f64,
    /// Newton iterations per frame, mean (0 for the explicit surrogate).
    pub newton_iterations: f64,
}

impl FullSpace {
    /// The full-space cloth of a job: the spring surrogate of `from` (a finished run's directory
    /// or a `surrogate.json`), whose grid then replaces `config.cloth`'s, or else `config`'s
    /// FEM sheet.
    pub fn new(config: &mut LatentConfig, from: Option<&Path>) -> Result<Self> {
        Ok(match from {
            Some(path) => {
                let sheet = SpringSheet::open(path)?;
                config.cloth = sheet.cloth(&config.cloth)?;
                config.validate().with_context(|| {
                    format!("the config does not fit the grid of {}", path.display())
                })?;
                Self::Springs(Box::new(sheet))
            }
            None => Self::Fem(Box::new(config.clone())),
        })
    }

    /// The full-space cloth of a latent run: the surrogate in its `surrogate.json` when it has
    /// one, else `config`'s FEM sheet.
    pub fn of_run(config: &LatentConfig, run: &LatentRun) -> Result<Self> {
        let path = run.surrogate();
        Ok(if path.exists() {
            Self::Springs(Box::new(SpringSheet::open(&path)?))
        } else {
            Self::Fem(Box::new(config.clone()))
        })
    }

    /// Writes the surrogate to `path` (a run's `surrogate.json`), or removes a stale one there
    /// for the FEM cloth.
    pub fn record(&self, path: &Path) -> Result<()> {
        match self {
            Self::Springs(sheet) => sheet.write(path),
            Self::Fem(_) if path.exists() => std::fs::remove_file(path)
                .with_context(|| format!("cannot remove {}", path.display())),
            Self::Fem(_) => Ok(()),
        }
    }

    /// What steps the reference, for messages.
    pub fn describe(&self) -> String {
        match self {
            Self::Fem(_) => "the FEM cloth, implicit Euler (Newton)".into(),
            Self::Springs(s) => format!("the spring surrogate of {}", s.source.display()),
        }
    }

    /// Simulates `scene` from rest; returns the rollout and its cost.
    pub fn generate(&self, scene: &Scene, progress: &Progress) -> Result<(Rollout, GenerateStats)> {
        match self {
            Self::Fem(c) => generate(&c.cloth, scene, c.solver, progress),
            Self::Springs(s) => s.generate(scene, progress),
        }
    }

    /// The incremental potential of a step of `dt`, `pinned` held with weight `w_bc`.
    pub fn potential(
        &self,
        dt: f64,
        pinned: &[usize],
        w_bc: f64,
        device: &Device,
    ) -> Result<Potential> {
        match self {
            Self::Fem(c) => Potential::new(&c.cloth.fem(), dt, pinned, w_bc, device),
            Self::Springs(s) => Ok(Potential::springs(s, dt, pinned, w_bc, device)),
        }
    }

    /// Times `frames` full-space frames of `reference` from frame `start`: FEM steps each from
    /// the reference's two previous frames (the latent model's inputs), or one surrogate
    /// rollout from the reference at `start − 1`.
    pub fn time(&self, reference: &Reference, start: usize, frames: usize) -> Result<FullTiming> {
        let r = reference;
        let frames = frames.min(r.frames.len() - start).max(1);
        let mut iterations = 0;
        let elapsed = match self {
            Self::Fem(c) => {
                let stepper = ImplicitEuler::new(c.cloth.fem(), r.dt, c.solver)?;
                let clock = Instant::now();
                for t in start..start + frames {
                    let (_, report) = stepper.step(
                        &r.frames[t - 1],
                        &r.frames[t - 2],
                        &r.pinned,
                        &r.targets(t),
                    )?;
                    iterations += report.iterations;
                }
                clock.elapsed()
            }
            Self::Springs(s) => {
                // One rollout of the frames from the reference at `start − 1` (a frame of the
                // surrogate is its explicit substeps; no per-frame setup is timed).
                let stepper = s.stepper(r.dt)?;
                let (x1, x2) = (&r.frames[start - 1], &r.frames[start - 2]);
                let v: Vec<_> = x1
                    .iter()
                    .zip(x2)
                    .map(|(a, b)| [0, 1, 2].map(|k| (a[k] - b[k]) / r.dt))
                    .collect();
                let targets = |f: usize| r.targets(start - 1 + f);
                let clock = Instant::now();
                stepper.roll((x1, &v), &r.pinned, &targets, frames, None)?;
                clock.elapsed()
            }
        };
        Ok(FullTiming {
            us_per_frame: elapsed.as_secs_f64() * 1e6 / frames as f64,
            newton_iterations: iterations as f64 / frames as f64,
        })
    }
}
