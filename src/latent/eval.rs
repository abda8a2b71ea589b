//! `springtime latent eval R` and `springtime latent bench R`: a trained latent model rolled
//! out autoregressively over the reference's unseen frames, and the time of one frame against
//! the full-space implicit step on the same machine.
//!
//! The rollout starts from the encoded reference frames `T − 2`, `T − 1` (`T` =
//! `integrator.train_frames`) and runs on its own to the last frame; only the pinned vertices'
//! prescribed paths come from the reference. A frame's positions are the decoded latent plus
//! the pinned vertices' prescribed mean.

use std::path::Path;
use std::time::Instant;

use anyhow::Result;
use burn::module::Module;
use burn::tensor::{Device, Tensor, TensorData};
use serde::{Deserialize, Serialize};

use super::LatentConfig;
use super::autoencoder::Autoencoder;
use super::infer::PlainModel;
use super::integrator::{Integrator, step_input};
use super::train::{
    LatentMeta, LatentRun, Reference, Scales, encode_all, load_autoencoder, read_meta,
};
use crate::cloth::triangles::V3;
use crate::data::Rollout;
use crate::source::implicit::ImplicitEuler;

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
}

/// Evaluates a finished run and writes `R/latent_eval.json`.
pub fn evaluate(dir: &Path) -> Result<EvalReport> {
    let model = LatentModel::open(dir)?;
    let r = &model.reference;
    let start = model.meta.train_frames;
    let rolled = model.rollout(start);
    let n = r.frames[0].len();
    let size = model.config.cloth.width.max(model.config.cloth.height);
    let (mut se_all, mut max_error, mut pinned_max) = (0.0, 0.0f64, 0.0f64);
    let mut diverged = false;
    let mut per_frame = Vec::with_capacity(rolled.len());
    let (mut ke_model, mut ke_ref) = (0.0, 0.0);
    let last = r.frames.len() - 1;
    let mut rest = Vec::new();
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
            let d: f64 = (0..n)
                .map(|i| {
                    (0..3)
                        .map(|c| (x[i][c] - r.frames[last][i][c]).powi(2))
                        .sum::<f64>()
                })
                .sum();
            rest.push((d / n as f64).sqrt());
        }
    }
    let frames = rolled.len();
    let decoded = super::train::decode(
        &model.autoencoder.decoder,
        &model.latents[start..],
        &model.device,
    );
    let rec: f64 = decoded
        .iter()
        .enumerate()
        .map(|(k, y)| {
            let rel = r.relative(start + k);
            rel.iter()
                .zip(y)
                .map(|(a, b)| (a - *b as f64).powi(2))
                .sum::<f64>()
        })
        .sum();
    let l = model.config.autoencoder.latent;
    let mut scratch = (Vec::new(), Vec::new());
    let mut one_step = 0.0;
    for t in start..r.frames.len() {
        let z = model.plain.step(&model.teacher_input(t), l, &mut scratch);
        let y = model
            .plain
            .decoder
            .apply(&model.scales.restore(&z), &mut scratch);
        one_step += r
            .relative(t)
            .iter()
            .zip(y)
            .map(|(a, b)| (a - *b as f64).powi(2))
            .sum::<f64>();
    }
    let report = EvalReport {
        frames,
        first_frame: start,
        diverged,
        rmse: (se_all / (frames * n) as f64).sqrt(),
        max_error,
        pinned_max_error: pinned_max,
        rmse_at_300: per_frame.get(300).copied(),
        rest_rmse_last_50: rest.iter().sum::<f64>() / rest.len().max(1) as f64,
        kinetic_energy_ratio: if ke_ref > 0.0 {
            ke_model / ke_ref
        } else {
            f64::NAN
        },
        reconstruction_rmse: (rec / (frames * n) as f64).sqrt(),
        one_step_rmse: (one_step / (frames * n) as f64).sqrt(),
        rmse_per_frame: per_frame,
    };
    crate::io::write_json(&model.run.dir.join("latent_eval.json"), &report)?;
    Ok(report)
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
    /// One full-space implicit-Euler Newton step of the reference simulator, µs.
    pub full_us_per_frame: f64,
    /// Newton iterations per full-space step, mean.
    pub full_newton_iterations: f64,
    /// `full_us_per_frame / latent_us_per_frame`.
    pub speedup: f64,
    /// Frames timed for the latent model.
    pub latent_frames: usize,
    /// Steps timed for the full-space solver.
    pub full_frames: usize,
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

    let stepper = ImplicitEuler::new(model.config.cloth.fem(), r.dt, model.config.solver)?;
    let full_frames = full_frames.min(r.frames.len() - start).max(1);
    let mut iterations = 0;
    let clock = Instant::now();
    for t in start..start + full_frames {
        let (_, report) =
            stepper.step(&r.frames[t - 1], &r.frames[t - 2], &r.pinned, &r.targets(t))?;
        iterations += report.iterations;
    }
    let full_us = clock.elapsed().as_secs_f64() * 1e6 / full_frames as f64;
    let report = BenchReport {
        latent_us_per_frame: latent_us,
        integrator_us,
        decoder_us: latent_us - integrator_us,
        burn_us_per_frame: burn_us,
        full_us_per_frame: full_us,
        full_newton_iterations: iterations as f64 / full_frames as f64,
        speedup: full_us / latent_us,
        latent_frames: inputs.len(),
        full_frames,
    };
    crate::io::write_json(&model.run.dir.join("bench.json"), &report)?;
    Ok(report)
}
