//! `springtime latent eval R` and `springtime latent bench R`: a trained latent model rolled
//! out autoregressively over the reference's unseen frames, and the time of one frame against
//! the full-space implicit step on the same machine.
//!
//! The rollout starts from the encoded reference frames `T − 2`, `T − 1` (`T` =
//! `integrator.train_frames`) and runs on its own to the last frame; only the pinned vertices'
//! prescribed paths come from the reference. A frame's positions are the decoded latent plus
//! the pinned vertices' prescribed mean.

use springtime_core::settings::Job;
use std::path::Path;
use std::time::Instant;

use anyhow::Result;
use burn::module::Module;
use burn::tensor::{Device, Tensor, TensorData};
use serde::{Deserialize, Serialize};

use super::LatentConfig;
use super::autoencoder::Autoencoder;
use super::full::FullSpace;
use super::infer::PlainModel;
use super::integrator::{Integrator, step_input};
use super::subspace::{Sample, SolveConfig, Subspace};
use super::train::{
    LatentMeta, LatentRun, Reference, Scales, absolute, encode_all, load_autoencoder, read_meta,
};
use springtime_core::cloth::triangles::V3;
use springtime_core::data::Rollout;

/// A finished latent run, loaded.
pub struct LatentModel {
    /// Its files.
    pub run: LatentRun,
    /// Its config.
    pub config: LatentConfig,
    /// `latent.json`.
    pub meta: LatentMeta,
    /// The reference motion.
    pub reference: Reference,
    /// The autoencoder (inference mode, CPU).
    pub autoencoder: Autoencoder,
    /// The integrator (CPU).
    pub integrator: Integrator,
    /// The same networks in plain Rust.
    pub plain: PlainModel,
    /// The latents' standardisation.
    pub scales: Scales,
    /// The device of the Burn networks.
    pub device: Device,
    /// The encoded reference, every frame (not standardised).
    pub latents: Vec<Vec<f32>>,
}

impl LatentModel {
    /// Opens the finished run in `dir`; errors name the missing or unreadable file.
    pub fn open(dir: &Path) -> Result<Self> {
        let run = LatentRun::new(dir);
        let meta = read_meta(&run)?;
        let config = LatentConfig::load(&run.config(), &[])?;
        let rollout = Rollout::load(&run.rollout())?;
        let reference = Reference::from_rollout(&rollout, &config)?;
        let device = burn::tensor::Device::flex();
        let load = |path: &Path| {
            burn::store::ModuleRecord::load(path)
                .map_err(|e| anyhow::anyhow!("cannot read {}: {e}", path.display()))
        };
        let fit = |path: &Path| {
            let p = path.display().to_string();
            move |e| anyhow::anyhow!("{p} does not fit the run's config: {e}")
        };
        let autoencoder = load_autoencoder(&config, meta.dof, &run.autoencoder(), &device)?.valid();
        let integrator = Integrator::new(
            &config.integrator,
            config.autoencoder.latent,
            meta.features,
            &device,
        )
        .try_load_record(load(&run.integrator())?)
        .map_err(fit(&run.integrator()))?;
        let plain = PlainModel::new(&autoencoder, &integrator);
        let latents = encode_all(&autoencoder, &reference, &device);
        Ok(Self {
            latents,
            scales: Scales::of(&meta),
            run,
            config,
            meta,
            reference,
            autoencoder,
            integrator,
            plain,
            device,
        })
    }

    /// Rolls the latent model out from the encoded frames `start − 2`, `start − 1` to the last
    /// frame; returns the positions of frames `start ..`.
    pub fn rollout(&self, start: usize) -> Vec<Vec<V3>> {
        let r = &self.reference;
        let l = self.config.autoencoder.latent;
        let mut z2 = self.scales.standardise(&self.latents[start - 2]);
        let mut z1 = self.scales.standardise(&self.latents[start - 1]);
        let mut scratch = (Vec::new(), Vec::new());
        let mut out = Vec::with_capacity(r.frames.len() - start);
        for t in start..r.frames.len() {
            let input = step_input(&z1, &z2, &r.features(t, self.scales.length));
            let z = self.plain.step(&input, l, &mut scratch);
            let rel = self
                .plain
                .decoder
                .apply(&self.scales.restore(&z), &mut scratch);
            let c = r.centre(t);
            out.push(
                rel.chunks(3)
                    .map(|p| [0, 1, 2].map(|k| p[k] as f64 + c[k]))
                    .collect(),
            );
            z2 = std::mem::replace(&mut z1, z);
        }
        out
    }

    /// The solved rollout from the encoded frames `start − 2`, `start − 1`: each step's latent
    /// minimises the potential of its decoded state, from `2z_{t−1} − z_{t−2}`; returns the
    /// positions of frames `start .. end`.
    pub fn solved_rollout(
        &self,
        start: usize,
        end: usize,
        solve: &SolveConfig,
    ) -> Result<SolvedRollout> {
        Ok(self.roll_solved(&self.subspace()?, start, end, solve))
    }

    fn roll_solved(
        &self,
        owned: &Subspace,
        start: usize,
        end: usize,
        solve: &SolveConfig,
    ) -> SolvedRollout {
        let r = &self.reference;
        let loss = owned.loss();
        let mut unconverged = 0;
        let mut scratch = (Vec::new(), Vec::new());
        let mut state = |z: &[f32], t: usize| -> Vec<f32> {
            let rel = self
                .plain
                .decoder
                .apply(&self.scales.restore(z), &mut scratch);
            absolute(rel, r.centre(t))
        };
        let mut z2 = self.scales.standardise(&self.latents[start - 2]);
        let mut z1 = self.scales.standardise(&self.latents[start - 1]);
        let (mut x2, mut x1) = (state(&z2, start - 2), state(&z1, start - 1));
        let mut out = Vec::with_capacity(r.frames.len() - start);
        for t in start..end.min(r.frames.len()) {
            let sample = Sample::at(r, t, &x1, &x2, 1.0);
            let guess: Vec<f32> = z1.iter().zip(&z2).map(|(a, b)| 2.0 * a - b).collect();
            let mut solved = loss.solve(&[&sample], &[guess], solve);
            unconverged += solved.unconverged;
            let z = solved.latents.remove(0);
            let x = state(&z, t);
            out.push(
                x.chunks(3)
                    .map(|p| [0, 1, 2].map(|k| p[k] as f64))
                    .collect(),
            );
            x2 = std::mem::replace(&mut x1, x);
            z2 = std::mem::replace(&mut z1, z);
        }
        SolvedRollout {
            positions: out,
            unconverged,
        }
    }

    /// The full-space cloth the run compresses (its FEM sheet or distilled surrogate).
    pub fn full_space(&self) -> Result<FullSpace> {
        FullSpace::of_run(&self.config, &self.run)
    }

    /// The decoder and the potential on an autodiff device, for solved steps.
    fn subspace(&self) -> Result<Subspace> {
        let ad = self.device.clone().autodiff();
        let decoder = load_autoencoder(&self.config, self.meta.dof, &self.run.autoencoder(), &ad)?
            .decoder
            .freeze();
        let r = &self.reference;
        let w_bc = self.config.integrator.w_bc;
        let potential = self.full_space()?.potential(r.dt, &r.pinned, w_bc, &ad)?;
        let row =
            |v: &[f32]| Tensor::<2>::from_data(TensorData::new(v.to_vec(), [1, v.len()]), &ad);
        Ok(Subspace {
            decoder,
            potential,
            z_mean: row(&self.scales.mean),
            z_std: row(&self.scales.std),
            vertices: r.frames[0].len(),
            pinned: r.pinned.len(),
        })
    }

    /// Step `t` solved from the encoded reference frames `t − 1`, `t − 2` (teacher forcing):
    /// its latent minimiser and the potential there, at the search's start `2z_{t−1} − z_{t−2}`
    /// and at the encoded frame `t`.
    pub fn solve_step(&self, t: usize, solve: &SolveConfig) -> Result<SolvedStep> {
        let r = &self.reference;
        let owned = self.subspace()?;
        let loss = owned.loss();
        let decoded = super::train::decode(
            &self.autoencoder.decoder,
            &self.latents[t - 2..t],
            &self.device,
        );
        let (x1, x2) = (
            absolute(&decoded[1], r.centre(t - 1)),
            absolute(&decoded[0], r.centre(t - 2)),
        );
        let sample = Sample::at(r, t, &x1, &x2, 1.0);
        let (z1, z2) = (
            self.scales.standardise(&self.latents[t - 1]),
            self.scales.standardise(&self.latents[t - 2]),
        );
        let guess: Vec<f32> = z1.iter().zip(&z2).map(|(a, b)| 2.0 * a - b).collect();
        let truth = self.scales.standardise(&self.latents[t]);
        let at = |z: &[f32]| {
            let device = loss.z_mean.device();
            let row = Tensor::<2>::from_data(TensorData::new(z.to_vec(), [1, z.len()]), &device);
            loss.potential(&[&sample], row).into_scalar::<f32>() as f64
        };
        let potential_at_reference = at(&truth);
        let mut solved = loss.solve(&[&sample], &[guess], solve);
        Ok(SolvedStep {
            latent: solved.latents.remove(0),
            potential: solved.mean_potential,
            potential_at_guess: solved.mean_potential_at_start,
            potential_at_reference,
        })
    }

    /// The integrator's input of step `t` from the encoded reference frames `t − 1`, `t − 2`
    /// (teacher forcing: one step without accumulated error).
    pub fn teacher_input(&self, t: usize) -> Vec<f32> {
        step_input(
            &self.scales.standardise(&self.latents[t - 1]),
            &self.scales.standardise(&self.latents[t - 2]),
            &self.reference.features(t, self.scales.length),
        )
    }

    /// Decodes standardised latents with the Burn decoder (for the parity test and bench).
    pub fn decode_burn(&self, z: &[f32]) -> Vec<f32> {
        let z = self.scales.restore(z);
        let t = Tensor::<2>::from_data(TensorData::new(z.clone(), [1, z.len()]), &self.device);
        self.autoencoder
            .decoder
            .forward(t)
            .into_data()
            .try_into_vec_as::<f32>()
            .expect("float tensor")
    }
}

/// A rollout of solved latent steps.
#[derive(Debug, Clone, PartialEq)]
pub struct SolvedRollout {
    /// Positions of every rolled-out frame.
    pub positions: Vec<Vec<V3>>,
    /// Steps whose Newton solve did not converge.
    pub unconverged: usize,
}

/// One step solved by [`LatentModel::solve_step`]; latents standardised.
#[derive(Debug, Clone, PartialEq)]
pub struct SolvedStep {
    /// The latent minimiser.
    pub latent: Vec<f32>,
    /// The potential there.
    pub potential: f64,
    /// The potential at the search's start, `2z_{t−1} − z_{t−2}`.
    pub potential_at_guess: f64,
    /// The potential at the encoded reference frame.
    pub potential_at_reference: f64,
}

/// `latent_eval.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EvalReport {
    /// Unseen frames rolled out.
    pub frames: usize,
    /// First rolled-out frame.
    pub first_frame: usize,
    /// A position became non-finite, or a frame's RMSE exceeded the sheet's size.
    pub diverged: bool,
    /// Vertex RMSE over all rolled-out frames, m.
    pub rmse: f64,
    /// Largest vertex error over all rolled-out frames, m.
    pub max_error: f64,
    /// Largest distance of a pinned vertex from its prescribed position, m.
    pub pinned_max_error: f64,
    /// Vertex RMSE of the frame 300 frames into the rollout (the supervised-baseline ablation's
    /// mark), m; `null` when the rollout is shorter.
    pub rmse_at_300: Option<f64>,
    /// Mean RMSE of the last 50 frames against the reference's last frame (the cantilever
    /// ablation's distance to the rest state), m.
    pub rest_rmse_last_50: f64,
    /// Mean RMS vertex displacement from one frame to the next over the last 50 frames, m per
    /// frame: whether the rollout is still moving there. A rollout that oscillates about the
    /// rest state shows it here; one that settled at an offset from it does not.
    #[serde(default)]
    pub rest_motion_last_50: f64,
    /// Kinetic energy of the rollout over the reference's, summed over the frames (the paper's
    /// limitation: below 1).
    pub kinetic_energy_ratio: f64,
    /// Autoencoder reconstruction RMSE over the same frames (the floor of `rmse`), m.
    pub reconstruction_rmse: f64,
    /// Vertex RMSE of single steps from the encoded reference frames `t − 1`, `t − 2` over the
    /// same frames (the integrator's local error, without accumulation), m.
    pub one_step_rmse: f64,
    /// Vertex RMSE of every rolled-out frame, m.
    pub rmse_per_frame: Vec<f64>,
    /// The solved rollout (`--subspace`): every step the minimiser of the potential over the
    /// decoder's manifold, the ceiling of what training the integrator can reach.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub subspace: Option<SubspaceReport>,
}

/// `latent_eval.json`'s `subspace`: the solved rollout's errors, m.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SubspaceReport {
    /// The solver's settings (the run's `integrator.solve`, `--solve-iterations` over it).
    pub solve: SolveConfig,
    /// Steps whose Newton solve did not converge.
    pub unconverged_steps: usize,
    /// A frame's RMSE exceeded the sheet's size or a position was not finite.
    pub diverged: bool,
    /// Vertex RMSE over all rolled-out frames.
    pub rmse: f64,
    /// Largest vertex error.
    pub max_error: f64,
    /// RMSE 300 frames in.
    pub rmse_at_300: Option<f64>,
    /// Kinetic energy over the reference's.
    pub kinetic_energy_ratio: f64,
    /// Wall time of the solved rollout, s.
    pub seconds: f64,
    /// Vertex RMSE of every frame.
    pub rmse_per_frame: Vec<f64>,
}

/// A rollout of frames `start ..` scored against the reference.
struct Track {
    diverged: bool,
    rmse: f64,
    max_error: f64,
    pinned_max_error: f64,
    rest_rmse_last_50: f64,
    rest_motion_last_50: f64,
    kinetic_energy_ratio: f64,
    rmse_per_frame: Vec<f64>,
}

impl Track {
    /// Scores `rolled`; a frame whose RMSE exceeds `size` (or is not finite) is a divergence.
    fn of(rolled: &[Vec<V3>], r: &Reference, start: usize, size: f64) -> Self {
        let n = r.frames[0].len();
        let (mut se_all, mut max_error, mut pinned_max) = (0.0, 0.0f64, 0.0f64);
        let mut diverged = false;
        let mut per_frame = Vec::with_capacity(rolled.len());
        let (mut ke_model, mut ke_ref) = (0.0, 0.0);
        let last = r.frames.len() - 1;
        let (mut rest, mut motion) = (Vec::new(), Vec::new());
        for (k, x) in rolled.iter().enumerate() {
            let t = start + k;
            let truth = &r.frames[t];
            let mut se = 0.0;
            for i in 0..n {
                let d2: f64 = (0..3).map(|c| (x[i][c] - truth[i][c]).powi(2)).sum();
                if !d2.is_finite() {
                    diverged = true;
                }
                se += d2;
                max_error = max_error.max(d2.sqrt());
            }
            for &i in &r.pinned {
                let d2: f64 = (0..3).map(|c| (x[i][c] - truth[i][c]).powi(2)).sum();
                pinned_max = pinned_max.max(d2.sqrt());
            }
            let rmse = (se / n as f64).sqrt();
            if !(rmse <= size) {
                diverged = true;
            }
            per_frame.push(rmse);
            se_all += se;
            if k > 0 {
                let prev = &rolled[k - 1];
                for i in 0..n {
                    for c in 0..3 {
                        ke_model += (x[i][c] - prev[i][c]).powi(2);
                        ke_ref += (truth[i][c] - r.frames[t - 1][i][c]).powi(2);
                    }
                }
            }
            if k + 50 >= rolled.len() {
                rest.push(rms_distance(x, &r.frames[last]));
                if k > 0 {
                    motion.push(rms_distance(x, &rolled[k - 1]));
                }
            }
        }
        let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len().max(1) as f64;
        Self {
            diverged,
            rmse: (se_all / (rolled.len().max(1) * n) as f64).sqrt(),
            max_error,
            pinned_max_error: pinned_max,
            rest_rmse_last_50: mean(&rest),
            rest_motion_last_50: mean(&motion),
            kinetic_energy_ratio: if ke_ref > 0.0 {
                ke_model / ke_ref
            } else {
                f64::NAN
            },
            rmse_per_frame: per_frame,
        }
    }
}

/// Root-mean-square distance between two frames of the same vertices, m.
fn rms_distance(a: &[V3], b: &[V3]) -> f64 {
    let sum: f64 = a
        .iter()
        .zip(b)
        .map(|(p, q)| (0..3).map(|c| (p[c] - q[c]).powi(2)).sum::<f64>())
        .sum();
    (sum / a.len().max(1) as f64).sqrt()
}

/// Evaluates a finished run and writes `R/latent_eval.json`; with `subspace`, the solved
/// rollout too, by the run's `integrator.solve` with `iterations` over it when given.
pub fn evaluate(dir: &Path, subspace: bool, iterations: Option<usize>) -> Result<EvalReport> {
    let model = LatentModel::open(dir)?;
    let solve = SolveConfig {
        iterations: iterations.unwrap_or(model.config.integrator.solve.iterations),
        ..model.config.integrator.solve
    };
    let subspace = subspace.then_some(&solve);
    let r = &model.reference;
    let start = model.meta.train_frames;
    let rolled = model.rollout(start);
    let size = model.config.cloth.width.max(model.config.cloth.height);
    let track = Track::of(&rolled, r, start, size);
    let subspace = match subspace {
        Some(solve) => Some(model.subspace_report(start, size, solve)?),
        None => None,
    };
    let n = r.frames[0].len();
    let frames = rolled.len();
    let rec = model.reconstruction_error(start);
    let one_step = model.one_step_error(start);
    let report = EvalReport {
        frames,
        first_frame: start,
        diverged: track.diverged,
        rmse: track.rmse,
        max_error: track.max_error,
        pinned_max_error: track.pinned_max_error,
        rmse_at_300: track.rmse_per_frame.get(300).copied(),
        rest_rmse_last_50: track.rest_rmse_last_50,
        rest_motion_last_50: track.rest_motion_last_50,
        kinetic_energy_ratio: track.kinetic_energy_ratio,
        reconstruction_rmse: (rec / (frames * n) as f64).sqrt(),
        one_step_rmse: (one_step / (frames * n) as f64).sqrt(),
        rmse_per_frame: track.rmse_per_frame,
        subspace,
    };
    springtime_core::io::write_json(&model.run.dir.join("latent_eval.json"), &report)?;
    error_figure(
        &model.run.dir.join("latent_eval.png"),
        &report,
        model.reference.dt,
    )?;
    Ok(report)
}

impl LatentModel {
    /// The solved rollout from frame `start` by `solve`, scored against the reference
    /// (`size` the divergence threshold).
    fn subspace_report(
        &self,
        start: usize,
        size: f64,
        solve: &SolveConfig,
    ) -> Result<SubspaceReport> {
        let r = &self.reference;
        let clock = Instant::now();
        let rollout = self.solved_rollout(start, r.frames.len(), solve)?;
        let solved = Track::of(&rollout.positions, r, start, size);
        Ok(SubspaceReport {
            solve: *solve,
            unconverged_steps: rollout.unconverged,
            diverged: solved.diverged,
            rmse: solved.rmse,
            max_error: solved.max_error,
            rmse_at_300: solved.rmse_per_frame.get(300).copied(),
            kinetic_energy_ratio: solved.kinetic_energy_ratio,
            seconds: clock.elapsed().as_secs_f64(),
            rmse_per_frame: solved.rmse_per_frame,
        })
    }

    /// The autoencoder's squared reconstruction error summed over the frames from `start`.
    fn reconstruction_error(&self, start: usize) -> f64 {
        let r = &self.reference;
        let decoded = super::train::decode(
            &self.autoencoder.decoder,
            &self.latents[start..],
            &self.device,
        );
        decoded
            .iter()
            .enumerate()
            .map(|(k, y)| {
                let rel = r.relative(start + k);
                rel.iter()
                    .zip(y)
                    .map(|(a, b)| (a - *b as f64).powi(2))
                    .sum::<f64>()
            })
            .sum()
    }

    /// The squared error of single steps from the encoded reference frames `t − 1`, `t − 2`,
    /// summed over the frames from `start` (plain Rust).
    fn one_step_error(&self, start: usize) -> f64 {
        let r = &self.reference;
        let l = self.config.autoencoder.latent;
        let mut scratch = (Vec::new(), Vec::new());
        let mut one_step = 0.0;
        for t in start..r.frames.len() {
            let z = self.plain.step(&self.teacher_input(t), l, &mut scratch);
            let y = self
                .plain
                .decoder
                .apply(&self.scales.restore(&z), &mut scratch);
            one_step += r
                .relative(t)
                .iter()
                .zip(y)
                .map(|(a, b)| (a - *b as f64).powi(2))
                .sum::<f64>();
        }
        one_step
    }
}

/// `latent_eval.png`: the vertex RMSE of every rolled-out frame, the learned integrator's and
/// (with `--subspace`) the solved steps', with the autoencoder's reconstruction floor.
fn error_figure(path: &Path, report: &EvalReport, dt: f64) -> Result<()> {
    use springtime_plot::{Series, curves_png};
    let curve = |label: &str, rmse: &[f64]| {
        let points = rmse
            .iter()
            .enumerate()
            .map(|(k, e)| ((report.first_frame + k) as f64 * dt, e * 1e3))
            .collect();
        Series::new(label, points)
    };
    let mut series = vec![curve("learned integrator", &report.rmse_per_frame)];
    if let Some(s) = &report.subspace {
        series.push(curve("solved latent steps (ceiling)", &s.rmse_per_frame));
    }
    let floor = vec![report.reconstruction_rmse; report.frames];
    series.push(curve("autoencoder reconstruction (mean)", &floor));
    curves_png(
        path,
        "latent rollout over the unseen frames: vertex RMSE",
        "time (s)",
        "RMSE (mm)",
        &series,
        true,
    )
}

/// `bench.json`, and the last line `latent bench` prints.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct BenchReport {
    /// One frame of the latent model in plain Rust (integrator + decoder), µs.
    pub latent_us_per_frame: f64,
    /// Its integrator part, µs.
    pub integrator_us: f64,
    /// Its decoder part, µs.
    pub decoder_us: f64,
    /// The same frame through the Burn networks on the CPU (batch 1), µs.
    pub burn_us_per_frame: f64,
    /// One full-space frame of the reference simulator, µs: an implicit-Euler Newton step of
    /// the FEM cloth, or the explicit substeps of one frame of a distilled surrogate.
    pub full_us_per_frame: f64,
    /// Newton iterations per full-space step, mean (0 for a distilled surrogate).
    pub full_newton_iterations: f64,
    /// `full_us_per_frame / latent_us_per_frame`.
    pub speedup: f64,
    /// Frames timed for the latent model.
    pub latent_frames: usize,
    /// Steps timed for the full-space solver.
    pub full_frames: usize,
    /// One solved latent step (the optimisation-based latent integrator: damped Newton through
    /// the Burn decoder and potential, batch 1), µs, over `full_frames` frames.
    #[serde(default)]
    pub solved_us_per_frame: f64,
}

/// Times a finished run's latent frame and the full-space step; writes `R/bench.json`.
pub fn bench(dir: &Path, full_frames: usize) -> Result<BenchReport> {
    let model = LatentModel::open(dir)?;
    let r = &model.reference;
    let l = model.config.autoencoder.latent;
    let start = model.meta.train_frames;
    let inputs: Vec<Vec<f32>> = (start..r.frames.len())
        .map(|t| model.teacher_input(t))
        .collect();
    let mut scratch = (Vec::new(), Vec::new());
    let mut sink = 0.0f32;
    let repeat = 20;
    // Warm-up, then the integrator alone and the integrator with the decoder.
    for input in &inputs {
        sink += model.plain.step(input, l, &mut scratch)[0];
    }
    let clock = Instant::now();
    let mut steps = Vec::with_capacity(inputs.len());
    for _ in 0..repeat {
        steps.clear();
        for input in &inputs {
            steps.push(model.plain.step(input, l, &mut scratch));
        }
    }
    let integrator_us = clock.elapsed().as_secs_f64() * 1e6 / (repeat * inputs.len()) as f64;
    let clock = Instant::now();
    for _ in 0..repeat {
        for input in &inputs {
            let z = model.plain.step(input, l, &mut scratch);
            let z = model.scales.restore(&z);
            sink += model.plain.decoder.apply(&z, &mut scratch)[0];
        }
    }
    let latent_us = clock.elapsed().as_secs_f64() * 1e6 / (repeat * inputs.len()) as f64;
    let burn_frames = inputs.len().min(200);
    let clock = Instant::now();
    for input in &inputs[..burn_frames] {
        let t = Tensor::<2>::from_data(
            TensorData::new(input.clone(), [1, input.len()]),
            &model.device,
        );
        let z: Vec<f32> = model
            .integrator
            .forward(t)
            .into_data()
            .try_into_vec_as::<f32>()
            .expect("float tensor");
        sink += model.decode_burn(&z)[0];
    }
    let burn_us = clock.elapsed().as_secs_f64() * 1e6 / burn_frames as f64;
    std::hint::black_box(sink);

    let full_frames = full_frames.min(r.frames.len() - start).max(1);
    let full = model.full_space()?.time(r, start, full_frames)?;
    let full_us = full.us_per_frame;
    let owned = model.subspace()?;
    let clock = Instant::now();
    model.roll_solved(
        &owned,
        start,
        start + full_frames,
        &model.config.integrator.solve,
    );
    let solved_us = clock.elapsed().as_secs_f64() * 1e6 / full_frames as f64;
    let report = BenchReport {
        latent_us_per_frame: latent_us,
        integrator_us,
        decoder_us: latent_us - integrator_us,
        burn_us_per_frame: burn_us,
        full_us_per_frame: full_us,
        full_newton_iterations: full.newton_iterations,
        speedup: full_us / latent_us,
        latent_frames: inputs.len(),
        full_frames,
        solved_us_per_frame: solved_us,
    };
    springtime_core::io::write_json(&model.run.dir.join("bench.json"), &report)?;
    Ok(report)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A reference of two vertices at rest for 60 frames.
    fn resting() -> Reference {
        Reference {
            frames: vec![vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]; 60],
            pinned: vec![0],
            dt: 1.0 / 30.0,
        }
    }

    #[test]
    fn rest_metrics_tell_an_offset_from_an_oscillation() {
        let r = resting();
        let shifted = |dz: f64| vec![[0.0, 0.0, dz], [1.0, 0.0, dz]];
        // Settled 1 mm off the rest state: 1 mm away, not moving.
        let offset: Vec<Vec<V3>> = (0..60).map(|_| shifted(1e-3)).collect();
        let t = Track::of(&offset, &r, 0, 1.0);
        assert!((t.rest_rmse_last_50 - 1e-3).abs() < 1e-12);
        assert!(t.rest_motion_last_50.abs() < 1e-12);
        // Swinging ±1 mm about it, frame by frame: as far away, but moving 2 mm a frame.
        let swing: Vec<Vec<V3>> = (0..60)
            .map(|k| shifted(if k % 2 == 0 { 1e-3 } else { -1e-3 }))
            .collect();
        let t = Track::of(&swing, &r, 0, 1.0);
        assert!((t.rest_rmse_last_50 - 1e-3).abs() < 1e-12);
        assert!((t.rest_motion_last_50 - 2e-3).abs() < 1e-12);
        // Only the last 50 frames count: a swing that stopped before them leaves no motion.
        let settled: Vec<Vec<V3>> = (0..60)
            .map(|k| shifted(if k < 8 && k % 2 == 1 { 5e-3 } else { 0.0 }))
            .collect();
        let t = Track::of(&settled, &r, 0, 1.0);
        assert!(t.rest_rmse_last_50.abs() < 1e-12);
        assert!(t.rest_motion_last_50.abs() < 1e-12);
    }
}
