//! Distillation (beyond the latent paper): a trained springtime surrogate as the full-space
//! cloth a latent model compresses, `springtime latent train CONFIG --from runs/<name>`.
//!
//! The learned spring network *is* a potential: its springs' energy, with its dashpots and
//! Rayleigh damping as a dissipation potential ([`super::energy`]), so the latent paper's
//! self-supervised loss applies unchanged. The reference motion is the surrogate's own: the
//! config's scenario on the surrogate's grid, stepped by springtime's explicit integrator
//! ([`springtime_core::sim::advance_frame`], the step the run was trained with) and recorded at the
//! scenario's frame rate. The latent run keeps the surrogate as `surrogate.json` (the export
//! format, [`SurrogateJson`]), so it needs neither the run nor its data afterwards.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result, bail};
use burn::tensor::{Device, Tensor, TensorData};

use super::scenario::{ClothConfig, GenerateStats, Scene, SheetRecord};
use springtime_core::cloth::triangles::V3;
use springtime_core::cloth::{Diagonal, Topology, grid_triangles};
use springtime_core::data::{Rollout, SpringTruth};
use springtime_core::model::SpringNet;
use springtime_core::progress::Progress;
use springtime_core::run::Run;
use springtime_core::run::surrogate::SurrogateJson;
use springtime_core::sim::{Physics, SimConfig, State, advance_frame};

/// A spring surrogate to distill.
#[derive(Debug, Clone)]
pub struct SpringSheet {
    /// Its springs, masses and constants.
    pub surrogate: SurrogateJson,
    /// Where it was read from (a run directory or a `surrogate.json`).
    pub source: PathBuf,
}

impl SpringSheet {
    /// The spring surrogate of a finished run's directory, or of an exported
    /// `surrogate.json`; errors name the path.
    pub fn open(path: &Path) -> Result<Self> {
        let surrogate = if path.is_dir() {
            let run = Run::open(path, &[], Some(springtime_core::backend::Backend::Flex))?;
            let physics = run.physics(run.meta.frame_dt);
            SurrogateJson::of(&run, run.springs()?, &[], Some(&physics))
        } else {
            SurrogateJson::read(path)?
        };
        let sheet = Self {
            surrogate,
            source: path.to_path_buf(),
        };
        sheet
            .check()
            .with_context(|| format!("{} cannot be distilled", path.display()))?;
        Ok(sheet)
    }

    /// What the latent pipeline needs beyond a valid file: one particle mass and a step.
    fn check(&self) -> Result<()> {
        let s = &self.surrogate;
        s.validate()?;
        if s.viscosity != 0.0 {
            bail!(
                "key `viscosity` is {} s (`sim.viscosity`): the full-space model the latent \
                 pipeline distills has no viscosity yet; distill a run trained without it",
                s.viscosity
            );
        }
        if s.shear_compression != 1.0 {
            bail!(
                "key `shear_compression` is {} (`sim.shear_compression`): the full-space model \
                 the latent pipeline distills has linear springs only; distill a run trained \
                 with linear shear springs",
                s.shear_compression
            );
        }
        let m = s.masses[0];
        if s.masses.iter().any(|&v| v != m) {
            bail!("key `masses` must hold one mass for every particle (a uniform sheet)");
        }
        match s.dt {
            Some(dt) if dt > 0.0 && dt.is_finite() => Ok(()),
            _ => bail!(
                "key `dt` (the surrogate's integration step) is missing or not positive; export \
                 the surrogate from its run, or distill the run directory itself"
            ),
        }
    }

    /// Refuses a reference rollout that this surrogate did not make (its springs or stiffness
    /// differ, or it has none): the latent loss would fit one cloth's motion with another's
    /// potential.
    pub fn check_reference(&self, rollout: &Rollout) -> Result<()> {
        let s = &self.surrogate;
        let same = rollout.springs.as_ref().is_some_and(|t| {
            t.springs == s.springs
                && t.k.len() == s.k.len()
                && t.k.iter().zip(&s.k).all(|(a, b)| (*a as f32) == *b)
        });
        if !same {
            bail!(
                "{} was not simulated by the surrogate of {} (its springs or stiffness differ, or \
                 it has none): distill from the surrogate's own reference (`springtime latent \
                 generate CONFIG --from RUN`)",
                rollout.path.display(),
                self.source.display()
            );
        }
        Ok(())
    }

    /// Writes `surrogate.json` (atomically).
    pub fn write(&self, path: &Path) -> Result<()> {
        springtime_core::io::write_text(path, &self.surrogate.to_text()?)
    }

    /// The latent `[cloth]` of the surrogate's grid: its `nx`, `ny`, `width`, `height` replace
    /// `base`'s (the material keys are the FEM's and are not used).
    pub fn cloth(&self, base: &ClothConfig) -> Result<ClothConfig> {
        let s = &self.surrogate;
        if !s.curvature.is_empty() {
            bail!(
                "the surrogate has curvature elements (cloth.curvature = true), which the latent \
                 potential does not model yet: distill a surrogate trained without them"
            );
        }
        let Some([nx, ny]) = s.grid else {
            bail!(
                "the surrogate lives on its data's mesh (cloth.layout = \"data\"): latent \
                 distillation needs a grid surrogate"
            );
        };
        Ok(ClothConfig {
            nx,
            ny,
            width: s.width,
            height: s.height,
            gravity: s.gravity,
            ..base.clone()
        })
    }

    /// The surrogate's grid and springs.
    pub fn topology(&self) -> Topology {
        let s = &self.surrogate;
        Topology {
            grid: s.grid,
            // Files written before the key existed hold a grid without it.
            triangles: match s.grid {
                Some([nx, ny]) if s.triangles.is_empty() => grid_triangles(nx, ny, Diagonal::Main),
                _ => s.triangles.clone(),
            },
            width: s.width,
            height: s.height,
            rest_uv: s.rest_positions.iter().map(|p| [p[0], p[1]]).collect(),
            springs: s.springs.clone(),
            rest_length: s.rest_length.clone(),
            family: s.family.clone(),
            curvature: s.curvature.clone(),
            mass_weight: {
                let mean = s.masses.iter().sum::<f64>() / s.masses.len().max(1) as f64;
                let equal = s.masses.iter().all(|&m| (m - mean).abs() <= 1e-12 * mean);
                (!equal).then(|| s.masses.iter().map(|m| m / mean).collect())
            },
        }
    }

    /// The spring network on `device`.
    pub fn net(&self, device: &Device) -> SpringNet {
        let s = &self.surrogate;
        let f64s = |v: &[f32]| -> Vec<f64> { v.iter().map(|&x| x as f64).collect() };
        SpringNet::new(&self.topology(), &f64s(&s.k), &f64s(&s.b), device)
            .with_curvature(&f64s(&s.curvature_k))
    }

    /// The explicit integrator's constants for frames `frame_dt` apart: as many substeps as
    /// keep the step at or below the surrogate's own.
    pub fn physics(&self, frame_dt: f64) -> Physics {
        let s = &self.surrogate;
        let dt = s.dt.expect("checked on opening");
        let sim = SimConfig {
            substeps: springtime_core::settings::Auto::Value(
                ((frame_dt / dt) - 1e-9).ceil().max(1.0) as usize,
            ),
            rayleigh: springtime_core::settings::Auto::Value(s.rayleigh),
            gravity: springtime_core::settings::Auto::Value(s.gravity),
            viscosity: 0.0,
            shear_compression: 1.0,
            allow_unstable: false,
        };
        Physics::new(&sim, frame_dt, s.masses[0])
    }

    /// The explicit stepper for frames `frame_dt` apart; refuses a step the stability
    /// estimate predicts to blow up.
    pub fn stepper(&self, frame_dt: f64) -> Result<SheetStepper> {
        let device = Device::flex();
        let net = self.net(&device);
        let physics = self.physics(frame_dt);
        physics.stability_of(&self.topology(), &net).check(
            &format!(
                "the surrogate of {} at {} substeps of {:.3e} s",
                self.source.display(),
                physics.substeps,
                physics.sim_dt()
            ),
            false,
        )?;
        Ok(SheetStepper {
            net,
            physics,
            device,
        })
    }

    /// Simulates `scene` on the surrogate from rest; returns the rollout and its cost (no
    /// Newton iterations: the step is explicit).
    pub fn generate(&self, scene: &Scene, progress: &Progress) -> Result<(Rollout, GenerateStats)> {
        let s = &self.surrogate;
        let frames = scene.config.frames;
        let dt = scene.config.dt();
        let n = scene.start.len();
        let still = vec![[0.0; 3]; n];
        let clock = Instant::now();
        let rolled = self.stepper(dt)?.roll(
            (&scene.start, &still),
            &scene.pinned,
            &|f| scene.targets(f),
            frames - 1,
            Some(progress),
        )?;
        let steps = (frames - 1).max(1) as f64;
        let stats = GenerateStats {
            frames,
            mean_iterations: 0.0,
            max_iterations: 0,
            us_per_step: clock.elapsed().as_secs_f64() * 1e6 / steps,
        };
        let positions: Vec<f32> = std::iter::once(&scene.start)
            .chain(&rolled)
            .flat_map(|x| x.iter().flat_map(|p| p.map(|v| v as f32)))
            .collect();
        let rollout = scene.rollout(
            positions,
            SheetRecord {
                rest_uv: s.rest_positions.iter().map(|p| [p[0], p[1]]).collect(),
                total_mass: s.masses.iter().sum(),
                width: s.width,
                height: s.height,
                springs: Some(SpringTruth {
                    springs: s.springs.clone(),
                    k: s.k.iter().map(|&v| v as f64).collect(),
                    b: s.b.iter().map(|&v| v as f64).collect(),
                }),
                mesh: None,
                gravity: s.gravity,
                rayleigh: s.rayleigh,
            },
        );
        Ok((rollout, stats))
    }
}

/// A surrogate ready to step ([`SpringSheet::stepper`]).
pub struct SheetStepper {
    net: SpringNet,
    physics: Physics,
    device: Device,
}

impl SheetStepper {
    /// Rolls the surrogate out for `frames` frames from positions and velocities `start`, the
    /// `pinned` particles at `targets(f)` at frame `f`; returns frames `1 ..= frames`.
    pub fn roll(
        &self,
        start: (&[V3], &[V3]),
        pinned: &[usize],
        targets: &dyn Fn(usize) -> Vec<V3>,
        frames: usize,
        progress: Option<&Progress>,
    ) -> Result<Vec<Vec<V3>>> {
        let device = &self.device;
        let n = start.0.len();
        let tensor = |x: &[V3]| {
            let v: Vec<f32> = x.iter().flat_map(|p| p.map(|c| c as f32)).collect();
            Tensor::<3>::from_data(TensorData::new(v, [1, n, 3]), device)
        };
        let mut mask = vec![0.0f32; n];
        for &i in pinned {
            mask[i] = 1.0;
        }
        let mask = Tensor::<3>::from_data(TensorData::new(mask, [1, n, 1]), device);
        let placed = |f: usize| {
            let mut x = vec![[0.0; 3]; n];
            for (&i, q) in pinned.iter().zip(targets(f)) {
                x[i] = q;
            }
            tensor(&x)
        };
        let mut state = State {
            x: tensor(start.0),
            v: tensor(start.1),
        };
        let bar = progress.map(|p| p.bar(frames as u64, "surrogate"));
        let mut here = placed(0);
        let mut out = Vec::with_capacity(frames);
        for f in 1..=frames {
            let next = placed(f);
            state = advance_frame(&self.net, &self.physics, None, state, &mask, &here, &next);
            here = next;
            let x: Vec<f32> = state
                .x
                .clone()
                .into_data()
                .try_into_vec_as::<f32>()
                .expect("float tensor");
            let x: Vec<V3> = x
                .chunks(3)
                .map(|p| [p[0] as f64, p[1] as f64, p[2] as f64])
                .collect();
            if x.iter().flatten().any(|v| !v.is_finite()) {
                bail!("the surrogate's rollout diverged at frame {f}");
            }
            out.push(x);
            if let Some(b) = &bar {
                b.set_position(f as u64);
            }
        }
        if let Some(b) = bar {
            b.finish();
        }
        Ok(out)
    }
}
