//! `springtime latent train <config> --out R`: the reference (generated, or read with
//! `--data`), then the two stages of the latent paper — the autoencoder on the training frames,
//! then the integrator through the frozen decoder with the self-supervised loss (Eq. 4), noise
//! (Eq. 5) and balancing (Eq. 6), or the supervised latent-L2 baseline.
//!
//! A run directory holds `config.toml`, `rollout.npz` (the reference) and `generate.json` (its
//! cost), `autoencoder.bpk`, `integrator.bpk`, `train_log.csv` and `latent.json`, written last:
//! a directory with `latent.json` is a finished run and is not overwritten without `--force`.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result, bail};
use burn::module::Module;
use burn::optim::{AdamConfig, GradientsParams, ModuleOptimizer};
use burn::tensor::{Device, Tensor, TensorData};
use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng, rngs::StdRng};
use serde::{Deserialize, Serialize};

use super::LatentConfig;
use super::autoencoder::{Autoencoder, Decoder, Pca};
use super::energy::Potential;
use super::full::FullSpace;
use super::integrator::{
    Integrator, IntegratorConfig, LossKind, boundary_features, mean, step_input,
};
use super::scenario::{GenerateStats, Scene};
use super::subspace::{Sample, SelfLoss, SolveConfig};
use springtime_core::cloth::triangles::V3;
use springtime_core::data::Rollout;
use springtime_core::progress::Progress;

/// The files of a latent run.
#[derive(Debug, Clone)]
pub struct LatentRun {
    /// The directory.
    pub dir: PathBuf,
}

impl LatentRun {
    /// The run in `dir`.
    pub fn new(dir: &Path) -> Self {
        Self {
            dir: dir.to_path_buf(),
        }
    }
    /// The resolved config.
    pub fn config(&self) -> PathBuf {
        self.dir.join("config.toml")
    }
    /// The reference rollout.
    pub fn rollout(&self) -> PathBuf {
        self.dir.join("rollout.npz")
    }
    /// The reference's cost.
    pub fn generate(&self) -> PathBuf {
        self.dir.join("generate.json")
    }
    /// The autoencoder's weights.
    pub fn autoencoder(&self) -> PathBuf {
        self.dir.join("autoencoder.bpk")
    }
    /// The integrator's weights.
    pub fn integrator(&self) -> PathBuf {
        self.dir.join("integrator.bpk")
    }
    /// The loss per epoch.
    pub fn log(&self) -> PathBuf {
        self.dir.join("train_log.csv")
    }
    /// The distilled spring surrogate (runs trained with `--from` only).
    pub fn surrogate(&self) -> PathBuf {
        self.dir.join("surrogate.json")
    }
    /// What a finished run needs besides its weights; written last.
    pub fn meta(&self) -> PathBuf {
        self.dir.join("latent.json")
    }
}

/// One training stage's summary.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Stage {
    /// Epochs run.
    pub epochs: usize,
    /// Loss of the last epoch (mean over its batches).
    pub final_loss: f64,
    /// Wall time, s.
    pub seconds: f64,
    /// The integrator's self-supervised loss on the clean training steps at its own latents.
    #[serde(default)]
    pub potential_at_fit: Option<f64>,
    /// The same at the encoded reference's latents.
    #[serde(default)]
    pub potential_at_reference: Option<f64>,
}

/// `latent.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LatentMeta {
    /// Job name.
    pub name: String,
    /// Vertices of the sheet.
    pub vertices: usize,
    /// Degrees of freedom (`3 × vertices`).
    pub dof: usize,
    /// The pinned vertices.
    pub pinned: Vec<usize>,
    /// PCA modes' standard deviations, m.
    pub pca_std: Vec<f64>,
    /// Latent means over the training frames (the integrator's standardisation).
    pub z_mean: Vec<f32>,
    /// Latent deviations over the training frames.
    pub z_std: Vec<f32>,
    /// Length that divides the boundary features, m.
    pub length: f64,
    /// Boundary features per step.
    pub features: usize,
    /// Frames `0 .. train_frames` trained.
    pub train_frames: usize,
    /// Autoencoder reconstruction RMSE over the training frames, m.
    pub reconstruction_rmse_train: f64,
    /// Autoencoder reconstruction RMSE over the unseen frames, m.
    pub reconstruction_rmse_test: f64,
    /// The autoencoder stage.
    pub autoencoder: Stage,
    /// The integrator stage.
    pub integrator: Stage,
    /// The reference's cost.
    pub generate: Option<GenerateStats>,
    /// The springtime build that trained it (`version (commit)`).
    pub build: String,
}

/// Loads an autoencoder of `config`'s shape for `dof`-dimensional frames from `path`.
pub fn load_autoencoder(
    config: &LatentConfig,
    dof: usize,
    path: &Path,
    device: &Device,
) -> Result<Autoencoder> {
    let record = burn::store::ModuleRecord::load(path)
        .map_err(|e| anyhow::anyhow!("cannot read {}: {e}", path.display()))?;
    Autoencoder::new(&config.autoencoder, dof, device)
        .try_load_record(record)
        .map_err(|e| anyhow::anyhow!("{} does not fit the config: {e}", path.display()))
}

/// Reads a finished run's `latent.json`; errors name the file.
pub fn read_meta(run: &LatentRun) -> Result<LatentMeta> {
    if !run.meta().exists() {
        bail!(
            "{} is not a finished latent run (no latent.json); train one with `springtime latent \
             train CONFIG --out {}`",
            run.dir.display(),
            run.dir.display()
        );
    }
    let text = std::fs::read_to_string(run.meta())
        .with_context(|| format!("cannot read {}", run.meta().display()))?;
    serde_json::from_str(&text)
        .with_context(|| format!("{} is not a latent.json", run.meta().display()))
}

/// The reference motion in the form training and evaluation read it.
#[derive(Debug, Clone)]
pub struct Reference {
    /// Positions of every frame, m.
    pub frames: Vec<Vec<V3>>,
    /// The pinned vertices.
    pub pinned: Vec<usize>,
    /// Time step, s.
    pub dt: f64,
}

impl Reference {
    /// Reads a rollout for the sheet of `config`; errors name the file.
    pub fn from_rollout(rollout: &Rollout, config: &LatentConfig) -> Result<Self> {
        let shown = rollout.path.display();
        let n = config.cloth.nx * config.cloth.ny;
        if rollout.landmarks != n {
            bail!(
                "{shown}: {} vertices, but the config's cloth has nx × ny = {n}",
                rollout.landmarks
            );
        }
        let pinned: Vec<usize> = (0..n).filter(|&i| rollout.pinned[i]).collect();
        if pinned.is_empty() {
            bail!(
                "{shown}: key `pinned` marks no vertex; the latent model needs Dirichlet vertices"
            );
        }
        if rollout.frames < 4 {
            bail!("{shown}: {} frames; at least 4 are needed", rollout.frames);
        }
        let frames = (0..rollout.frames)
            .map(|f| {
                (0..n)
                    .map(|i| rollout.position(f, i).map(|v| v as f64))
                    .collect()
            })
            .collect();
        Ok(Self {
            frames,
            pinned,
            dt: rollout.frame_dt,
        })
    }

    /// The pinned vertices' positions at frame `f`.
    pub fn targets(&self, f: usize) -> Vec<V3> {
        self.pinned.iter().map(|&i| self.frames[f][i]).collect()
    }

    /// The mean of the pinned vertices at frame `f` (the frame's origin for the autoencoder).
    pub fn centre(&self, f: usize) -> V3 {
        mean(&self.targets(f))
    }

    /// Frame `f` relative to its centre, flattened.
    pub fn relative(&self, f: usize) -> Vec<f64> {
        let c = self.centre(f);
        self.frames[f]
            .iter()
            .flat_map(|p| [0, 1, 2].map(|k| p[k] - c[k]))
            .collect()
    }

    /// The boundary features of step `t` (`t ≥ 2`).
    pub fn features(&self, t: usize, length: f64) -> Vec<f32> {
        boundary_features(
            &self.targets(t),
            &self.targets(t - 1),
            &self.targets(t - 2),
            length,
        )
    }
}

/// Where `latent train` writes and what it reads.
#[derive(Debug, Clone)]
pub struct TrainOptions {
    /// The run directory.
    pub out: PathBuf,
    /// A reference rollout to train on instead of generating one.
    pub data: Option<PathBuf>,
    /// Overwrite a finished run.
    pub force: bool,
    /// A finished run whose reference and autoencoder to reuse (the integrator ablations
    /// share one autoencoder, as the paper's do); its config's cloth and autoencoder must match.
    pub autoencoder_from: Option<PathBuf>,
    /// A trained spring surrogate to distill (a run directory or a `surrogate.json`) instead of
    /// the config's FEM cloth.
    pub from: Option<PathBuf>,
}

/// `latent generate`: simulates the config's scenario on `full` into `out/rollout.npz` and
/// `out/generate.json`.
pub fn generate_reference(
    config: &LatentConfig,
    full: &FullSpace,
    out: &Path,
    force: bool,
    progress: &Progress,
) -> Result<(Rollout, GenerateStats)> {
    let run = LatentRun::new(out);
    springtime_core::io::refuse_overwrite(&run.rollout(), force)?;
    std::fs::create_dir_all(out).with_context(|| format!("cannot create {}", out.display()))?;
    let scene = Scene::new(&config.cloth, &config.scenario);
    let (mut rollout, stats) = full.generate(&scene, progress)?;
    full.record(&run.surrogate())?;
    rollout.path = run.rollout();
    rollout.save(&run.rollout())?;
    springtime_core::io::write_json(&run.generate(), &stats)?;
    Ok((rollout, stats))
}

/// Trains a latent model; returns its `latent.json`.
pub fn train(
    config: &LatentConfig,
    options: &TrainOptions,
    progress: &Progress,
) -> Result<LatentMeta> {
    let run = LatentRun::new(&options.out);
    if run.meta().exists() && !options.force {
        bail!(
            "{} holds a finished latent run; pass --force to overwrite it",
            run.dir.display()
        );
    }
    let sources = Sources::of(options)?;
    let mut config = config.clone();
    let full = FullSpace::new(&mut config, sources.from.as_deref())?;
    let config = &config;
    let given = sources.data.as_deref().map(Rollout::load).transpose()?;
    if let (FullSpace::Springs(sheet), Some(rollout)) = (&full, &given) {
        // A distilled surrogate's reference must be its own motion.
        sheet.check_reference(rollout)?;
    }
    prepare_run(&run, config, &full)?;
    let (rollout, generated) = reference_rollout(config, &full, &run, given, progress)?;
    let reference = training_reference(&rollout, config)?;
    let device = config.backend.device()?;
    device.seed(config.seed);
    let ad = device.clone().autodiff();
    let mut log = TrainLog::create(&run.log())?;

    let (ae, pca_std, ae_stage) = match &sources.reused {
        None => train_autoencoder(config, &reference, &ad, &mut log, progress)?,
        Some(from) => reuse_autoencoder(config, &reference, from, &ad, progress)?,
    };
    springtime_core::train::run::RunDir::save_module(&ae, &run.autoencoder())?;
    // Everything after reads the saved autoencoder, as `latent eval` will (BatchNorm's running
    // statistics are synchronised on saving).
    let dof = 3 * reference.frames[0].len();
    let ae = load_autoencoder(config, dof, &run.autoencoder(), &ad)?;
    let plain = ae.valid();
    let latents = encode_all(&plain, &reference, &device);
    let t = config.integrator.train_frames;
    let (rec_train, rec_test) =
        reconstruction(&plain.decoder, &latents, &reference, t, &device, progress);

    let scales = Scales::new(&latents[..t], config.cloth.width.max(config.cloth.height));
    let potential = full.potential(reference.dt, &reference.pinned, config.integrator.w_bc, &ad)?;
    let stage = IntegratorData {
        config,
        reference: &reference,
        potential: &potential,
        ae: &ae,
        latents: &latents,
        scales: &scales,
        ad: &ad,
    };
    let (integrator, int_stage) = train_integrator(&stage, &mut log, progress)?;
    springtime_core::train::run::RunDir::save_module(&integrator, &run.integrator())?;
    let meta = LatentMeta {
        name: config.name.clone(),
        vertices: reference.frames[0].len(),
        dof: 3 * reference.frames[0].len(),
        pinned: reference.pinned.clone(),
        pca_std,
        z_mean: scales.mean.clone(),
        z_std: scales.std.clone(),
        length: scales.length,
        features: 9 * reference.pinned.len(),
        train_frames: t,
        reconstruction_rmse_train: rec_train,
        reconstruction_rmse_test: rec_test,
        autoencoder: ae_stage,
        integrator: int_stage,
        generate: generated,
        build: build_string(),
    };
    springtime_core::io::write_json(&run.meta(), &meta)?;
    Ok(meta)
}

/// The reference of `rollout` for training: enough frames for `integrator.train_frames` and
/// two more.
fn training_reference(rollout: &Rollout, config: &LatentConfig) -> Result<Reference> {
    let reference = Reference::from_rollout(rollout, config)?;
    if reference.frames.len() < config.integrator.train_frames + 2 {
        bail!(
            "{}: {} frames, fewer than integrator.train_frames + 2 = {}",
            rollout.path.display(),
            reference.frames.len(),
            config.integrator.train_frames + 2
        );
    }
    Ok(reference)
}

/// Where `latent train` takes its reference, autoencoder and surrogate from.
struct Sources {
    /// The finished run whose reference and autoencoder are reused (`--autoencoder-from`).
    reused: Option<LatentRun>,
    /// The reference rollout to read: `--data`, or the reused run's.
    data: Option<PathBuf>,
    /// The surrogate to distill: `--from`'s, or the reused run's.
    from: Option<PathBuf>,
}

impl Sources {
    fn of(options: &TrainOptions) -> Result<Self> {
        let reused = options.autoencoder_from.as_deref().map(LatentRun::new);
        let data = match (&options.data, &reused) {
            (Some(_), Some(_)) => bail!("give either --data or --autoencoder-from, not both"),
            (None, Some(r)) => Some(r.rollout()),
            (d, None) => d.clone(),
        };
        let from = match (&options.from, &reused) {
            (Some(f), _) => Some(f.clone()),
            (None, Some(r)) => Some(r.surrogate()).filter(|p| p.exists()),
            (None, None) => None,
        };
        Ok(Self { reused, data, from })
    }
}

/// Clears an earlier run from `run`'s directory (the inputs are valid: only now is it
/// replaced) and writes the surrogate distilled, if any, and the resolved config.
fn prepare_run(run: &LatentRun, config: &LatentConfig, full: &FullSpace) -> Result<()> {
    std::fs::create_dir_all(&run.dir)
        .with_context(|| format!("cannot create {}", run.dir.display()))?;
    for stale in [run.meta(), run.log()] {
        if stale.exists() {
            std::fs::remove_file(&stale)
                .with_context(|| format!("cannot remove {}", stale.display()))?;
        }
    }
    full.record(&run.surrogate())?;
    springtime_core::io::write_text(&run.config(), &toml::to_string(config)?)?;
    Ok(())
}

/// The reference: the `given` rollout saved into the run, or simulated on `full` (with its
/// cost).
fn reference_rollout(
    config: &LatentConfig,
    full: &FullSpace,
    run: &LatentRun,
    given: Option<Rollout>,
    progress: &Progress,
) -> Result<(Rollout, Option<GenerateStats>)> {
    match given {
        Some(rollout) => {
            rollout.save(&run.rollout())?;
            Ok((rollout, None))
        }
        None => {
            progress.note(&format!(
                "simulating the full-space reference: {}",
                full.describe()
            ));
            let (r, s) = generate_reference(config, full, &run.dir, true, progress)?;
            Ok((r, Some(s)))
        }
    }
}

/// The autoencoder of the finished run `from`, with its PCA deviations and stage.
fn reuse_autoencoder(
    config: &LatentConfig,
    reference: &Reference,
    from: &LatentRun,
    ad: &Device,
    progress: &Progress,
) -> Result<(Autoencoder, Vec<f64>, Stage)> {
    let meta: LatentMeta = read_meta(from)?;
    let ae = load_autoencoder(
        config,
        3 * reference.frames[0].len(),
        &from.autoencoder(),
        ad,
    )?;
    progress.note(&format!("autoencoder reused from {}", from.dir.display()));
    Ok((ae, meta.pca_std, meta.autoencoder))
}

/// The autoencoder's reconstruction RMSE (m) over the training frames `0 .. t` and over the
/// unseen ones, noted.
fn reconstruction(
    decoder: &Decoder,
    latents: &[Vec<f32>],
    reference: &Reference,
    t: usize,
    device: &Device,
    progress: &Progress,
) -> (f64, f64) {
    let rmse = |range: std::ops::Range<usize>| {
        let decoded = decode(decoder, &latents[range.clone()], device);
        let mut se = 0.0;
        for (k, f) in range.clone().enumerate() {
            let rel = reference.relative(f);
            se += rel
                .iter()
                .zip(&decoded[k])
                .map(|(a, b)| (a - *b as f64).powi(2))
                .sum::<f64>();
        }
        (se / (range.len() * reference.frames[0].len()) as f64).sqrt()
    };
    let (rec_train, rec_test) = (rmse(0..t), rmse(t..reference.frames.len()));
    progress.note(&format!(
        "autoencoder: reconstruction RMSE {:.3} mm on the training frames, {:.3} mm unseen",
        rec_train * 1e3,
        rec_test * 1e3
    ));
    (rec_train, rec_test)
}

/// The springtime build, `version (commit)`.
fn build_string() -> String {
    let b = springtime_core::BuildInfo::current();
    format!("{} ({})", b.version, b.commit)
}

/// The integrator's standardisation of the latents and the boundary features' length.
#[derive(Debug, Clone, PartialEq)]
pub struct Scales {
    /// Latent means.
    pub mean: Vec<f32>,
    /// Latent deviations.
    pub std: Vec<f32>,
    /// Length dividing the boundary features, m.
    pub length: f64,
}

impl Scales {
    fn new(latents: &[Vec<f32>], length: f64) -> Self {
        let l = latents[0].len();
        let n = latents.len() as f64;
        let mean: Vec<f32> = (0..l)
            .map(|k| (latents.iter().map(|z| z[k] as f64).sum::<f64>() / n) as f32)
            .collect();
        let std = (0..l)
            .map(|k| {
                let v = latents
                    .iter()
                    .map(|z| (z[k] - mean[k]) as f64)
                    .map(|d| d * d)
                    .sum::<f64>()
                    / n;
                (v.sqrt() as f32).max(1e-6)
            })
            .collect();
        Self { mean, std, length }
    }

    /// From a finished run's `latent.json`.
    pub fn of(meta: &LatentMeta) -> Self {
        Self {
            mean: meta.z_mean.clone(),
            std: meta.z_std.clone(),
            length: meta.length,
        }
    }

    /// `(z − μ)/σ`.
    pub fn standardise(&self, z: &[f32]) -> Vec<f32> {
        z.iter()
            .zip(&self.mean)
            .zip(&self.std)
            .map(|((v, m), s)| (v - m) / s)
            .collect()
    }

    /// `μ + σ ẑ`.
    pub fn restore(&self, z: &[f32]) -> Vec<f32> {
        z.iter()
            .zip(&self.mean)
            .zip(&self.std)
            .map(|((v, m), s)| m + s * v)
            .collect()
    }
}

/// `train_log.csv`: `stage, epoch, loss, seconds`.
struct TrainLog {
    writer: csv::Writer<std::fs::File>,
}

impl TrainLog {
    fn create(path: &Path) -> Result<Self> {
        let mut writer = csv::Writer::from_path(path)
            .with_context(|| format!("cannot write {}", path.display()))?;
        writer.write_record(["stage", "epoch", "loss", "seconds"])?;
        Ok(Self { writer })
    }

    fn row(&mut self, stage: &str, epoch: usize, loss: f64, seconds: f64) -> Result<()> {
        self.writer.write_record([
            stage.to_string(),
            epoch.to_string(),
            format!("{loss:.8e}"),
            format!("{seconds:.3}"),
        ])?;
        self.writer.flush()?;
        Ok(())
    }
}

/// An epoch's batch losses.
#[derive(Default)]
struct EpochLoss {
    sum: f64,
    batches: usize,
}

impl EpochLoss {
    fn add(&mut self, value: f64) {
        self.sum += value;
        self.batches += 1;
    }

    /// The mean over the batches (NaN without any).
    fn mean(&self) -> f64 {
        self.sum / self.batches.max(1) as f64
    }
}

fn rows_tensor(rows: &[&[f32]], device: &Device) -> Tensor<2> {
    let d = rows.first().map_or(0, |r| r.len());
    let data: Vec<f32> = rows.iter().flat_map(|r| r.iter().copied()).collect();
    Tensor::from_data(TensorData::new(data, [rows.len(), d]), device)
}

fn to_rows(t: Tensor<2>) -> Vec<Vec<f32>> {
    let [_, d] = t.dims();
    let v: Vec<f32> = t
        .into_data()
        .try_into_vec_as::<f32>()
        .expect("float tensor");
    v.chunks(d.max(1)).map(|c| c.to_vec()).collect()
}

/// Encodes every frame of the reference (inference mode).
pub fn encode_all(ae: &Autoencoder, reference: &Reference, device: &Device) -> Vec<Vec<f32>> {
    let rows: Vec<Vec<f32>> = (0..reference.frames.len())
        .map(|f| reference.relative(f).iter().map(|&v| v as f32).collect())
        .collect();
    rows.chunks(512)
        .flat_map(|chunk| {
            let refs: Vec<&[f32]> = chunk.iter().map(|r| r.as_slice()).collect();
            to_rows(ae.encoder.forward(rows_tensor(&refs, device)))
        })
        .collect()
}

/// Decodes latents (inference mode) to relative positions.
pub fn decode(decoder: &Decoder, latents: &[Vec<f32>], device: &Device) -> Vec<Vec<f32>> {
    latents
        .chunks(512)
        .flat_map(|chunk| {
            let refs: Vec<&[f32]> = chunk.iter().map(|r| r.as_slice()).collect();
            to_rows(decoder.forward(rows_tensor(&refs, device)))
        })
        .collect()
}

/// One Adam step of `module` on the scalar `loss` at rate `lr`; returns the module and the
/// loss's value, or an error naming the stage and epoch when the loss is not finite.
fn descend<M: Module>(
    optim: &mut ModuleOptimizer,
    module: M,
    loss: Tensor<1>,
    lr: f64,
    stage: &str,
    epoch: usize,
) -> Result<(M, f64)> {
    let value = loss.clone().into_scalar::<f32>() as f64;
    if !value.is_finite() {
        bail!("{stage} training diverged at epoch {epoch} (loss {value})");
    }
    let grads = GradientsParams::from_grads(loss.backward(), &module);
    Ok((optim.step(lr, module, grads), value))
}

/// Trains the autoencoder (initialised by the PCA of the training frames); returns it, the
/// PCA modes' deviations and the stage.
fn train_autoencoder(
    config: &LatentConfig,
    reference: &Reference,
    ad: &Device,
    log: &mut TrainLog,
    progress: &Progress,
) -> Result<(Autoencoder, Vec<f64>, Stage)> {
    let c = &config.autoencoder;
    let t = config.integrator.train_frames;
    let d = 3 * reference.frames[0].len();
    let data: Vec<f64> = (0..t).flat_map(|f| reference.relative(f)).collect();
    let pca = Pca::fit(&data, t, d, c.pca_modes)?;
    let mut ae = Autoencoder::new(c, d, ad).with_pca(&pca, ad);
    let rows: Vec<Vec<f32>> = (0..t)
        .map(|f| reference.relative(f).iter().map(|&v| v as f32).collect())
        .collect();
    let mut optim = AdamConfig::new().init();
    let mut rng = StdRng::seed_from_u64(config.seed);
    let mut order: Vec<usize> = (0..t).collect();
    let bar = progress.bar(c.epochs as u64, "autoencoder");
    let clock = Instant::now();
    let mut last = f64::NAN;
    for epoch in 0..c.epochs {
        order.shuffle(&mut rng);
        let mut losses = EpochLoss::default();
        for chunk in order.chunks(c.batch) {
            // BatchNorm needs more than one frame in a batch.
            if chunk.len() < 2 {
                continue;
            }
            let refs: Vec<&[f32]> = chunk.iter().map(|&i| rows[i].as_slice()).collect();
            let x = rows_tensor(&refs, ad);
            let loss = (ae.forward(x.clone()) - x).powi_scalar(2).mean();
            let value;
            (ae, value) = descend(
                &mut optim,
                ae,
                loss,
                c.rate(epoch, c.epochs),
                "autoencoder",
                epoch,
            )?;
            losses.add(value);
        }
        last = losses.mean();
        log.row("autoencoder", epoch, last, clock.elapsed().as_secs_f64())?;
        bar.set_message(format!("RMSE {:.3} mm", last.sqrt() * 1e3));
        bar.inc(1);
    }
    bar.finish();
    Ok((
        ae,
        pca.std,
        Stage {
            epochs: c.epochs,
            final_loss: last,
            seconds: clock.elapsed().as_secs_f64(),
            potential_at_fit: None,
            potential_at_reference: None,
        },
    ))
}

/// Relative positions (flattened) moved to `centre`.
pub(crate) fn absolute(relative: &[f32], centre: V3) -> Vec<f32> {
    relative
        .iter()
        .enumerate()
        .map(|(i, v)| v + centre[i % 3] as f32)
        .collect()
}

/// What the integrator trains on: the reference, its latents through the trained autoencoder
/// and the potential of the self-supervised loss.
struct IntegratorData<'a> {
    config: &'a LatentConfig,
    reference: &'a Reference,
    potential: &'a Potential,
    ae: &'a Autoencoder,
    /// Every frame's latent.
    latents: &'a [Vec<f32>],
    scales: &'a Scales,
    ad: &'a Device,
}

fn train_integrator(
    data: &IntegratorData,
    log: &mut TrainLog,
    progress: &Progress,
) -> Result<(Integrator, Stage)> {
    let (config, reference, scales, ad) = (data.config, data.reference, data.scales, data.ad);
    let c = &config.integrator;
    let plain_device = ad.clone().inner();
    let plain = data.ae.valid();
    let frozen = data.ae.decoder.clone().freeze();
    let l = data.latents[0].len();
    let (std, mut samples) = clean_samples(data, &plain.decoder, &plain_device);
    let clean_count = samples.len();
    let z_mean = Tensor::<2>::from_data(TensorData::new(scales.mean.clone(), [1, l]), ad);
    let z_std = Tensor::<2>::from_data(TensorData::new(scales.std.clone(), [1, l]), ad);
    let loss_of = SelfLoss {
        decoder: &frozen,
        potential: data.potential,
        z_mean: z_mean.clone(),
        z_std: z_std.clone(),
        balance: c.balance,
        vertices: reference.frames[0].len(),
        pinned: reference.pinned.len(),
    };
    let noisy = NoisyCopies {
        noise: c.noise,
        decoder: &plain.decoder,
        scales,
        reference,
        device: &plain_device,
        floor: c.velocity_floor,
    };
    let mut rng = StdRng::seed_from_u64(config.seed.wrapping_add(1));
    if c.loss == LossKind::Solved {
        solve_targets(c, &mut samples, &loss_of, &noisy, &mut rng, progress);
    }
    let fit = IntegratorFit {
        c,
        loss_of: &loss_of,
        noisy: &noisy,
        std: &std,
        ad,
    };
    let features = 9 * reference.pinned.len();
    let integrator = Integrator::new(c, l, features, ad);
    let clock = Instant::now();
    let (integrator, last) =
        fit.epochs(integrator, &mut samples, &mut rng, log, clock, progress)?;
    let (at_fit, at_truth) = clean_potentials(&samples[..clean_count], &loss_of, &integrator, ad);
    let count = clean_count.max(1) as f64;
    Ok((
        integrator,
        Stage {
            epochs: fit.total_epochs(),
            final_loss: last,
            seconds: clock.elapsed().as_secs_f64(),
            potential_at_fit: Some(at_fit / count),
            potential_at_reference: Some(at_truth / count),
        },
    ))
}

/// Every latent standardised, and the clean training steps `2 .. train_frames`: the encoded
/// reference's latents, the previous states decoded from them.
fn clean_samples(
    data: &IntegratorData,
    decoder: &Decoder,
    device: &Device,
) -> (Vec<Vec<f32>>, Vec<Sample>) {
    let (c, reference, scales) = (&data.config.integrator, data.reference, data.scales);
    let t_end = c.train_frames;
    let decoded = decode(decoder, &data.latents[..t_end], device);
    let abs: Vec<Vec<f32>> = decoded
        .iter()
        .enumerate()
        .map(|(f, r)| absolute(r, reference.centre(f)))
        .collect();
    let std: Vec<Vec<f32>> = data.latents.iter().map(|z| scales.standardise(z)).collect();
    let samples: Vec<Sample> = (2..t_end)
        .map(|t| Sample {
            input: step_input(
                &std[t - 1],
                &std[t - 2],
                &reference.features(t, scales.length),
            ),
            truth: std[t].clone(),
            ..Sample::at(reference, t, &abs[t - 1], &abs[t - 2], c.velocity_floor)
        })
        .collect();
    (std, samples)
}

/// What the integrator's training loop reads: the config's loss, the noisy copies of the
/// steps for the self-supervised loss with noise, every latent standardised, and the autodiff
/// device `ad`.
struct IntegratorFit<'a> {
    c: &'a IntegratorConfig,
    loss_of: &'a SelfLoss<'a>,
    noisy: &'a NoisyCopies<'a>,
    std: &'a [Vec<f32>],
    ad: &'a Device,
}

impl IntegratorFit<'_> {
    /// Epochs in all: `integrator.rounds` rounds of `integrator.epochs` with the solved loss.
    fn total_epochs(&self) -> usize {
        let c = self.c;
        let rounds = if c.loss == LossKind::Solved {
            c.rounds.max(1)
        } else {
            1
        };
        c.epochs * rounds
    }

    /// Trains `integrator` on `samples` (more join them each round); returns it and the last
    /// epoch's mean loss. Each epoch is logged with its time since `clock`.
    fn epochs(
        &self,
        mut integrator: Integrator,
        samples: &mut Vec<Sample>,
        rng: &mut StdRng,
        log: &mut TrainLog,
        clock: Instant,
        progress: &Progress,
    ) -> Result<(Integrator, f64)> {
        let c = self.c;
        let mut optim = AdamConfig::new().init();
        let mut order: Vec<usize> = (0..samples.len()).collect();
        let total = self.total_epochs();
        let bar = progress.bar(total as u64, "integrator");
        let mut last = f64::NAN;
        for epoch in 0..total {
            if epoch > 0 && epoch % c.epochs == 0 {
                self.add_visited_steps(&integrator, samples, progress);
                order = (0..samples.len()).collect();
            }
            order.shuffle(rng);
            let mut losses = EpochLoss::default();
            for chunk in order.chunks(c.batch) {
                let loss = self.batch_loss(&integrator, samples, chunk, rng);
                let value;
                (integrator, value) = descend(
                    &mut optim,
                    integrator,
                    loss,
                    c.rate(epoch, total),
                    "integrator",
                    epoch,
                )?;
                losses.add(value);
            }
            last = losses.mean();
            log.row("integrator", epoch, last, clock.elapsed().as_secs_f64())?;
            bar.set_message(format!("loss {last:.5e}"));
            bar.inc(1);
        }
        bar.finish();
        Ok((integrator, last))
    }

    /// A new round: the steps the integrator itself visits on the training frames, solved, join
    /// the training set (the states its own errors lead it to).
    fn add_visited_steps(
        &self,
        integrator: &Integrator,
        samples: &mut Vec<Sample>,
        progress: &Progress,
    ) {
        let noisy = self.noisy;
        let from = samples.len();
        samples.extend(visited_steps(
            &integrator.valid(),
            noisy.decoder,
            self.std,
            noisy.reference,
            noisy.scales,
            self.c,
            noisy.device,
        ));
        solve_samples(&mut samples[from..], self.loss_of, &self.c.solve, progress);
    }

    /// The loss of the batch of `samples` at the steps `chunk`, at the integrator's latents.
    fn batch_loss(
        &self,
        integrator: &Integrator,
        samples: &[Sample],
        chunk: &[usize],
        rng: &mut StdRng,
    ) -> Tensor<1> {
        let (c, ad) = (self.c, self.ad);
        let clean: Vec<&Sample> = chunk.iter().map(|&i| &samples[i]).collect();
        let copies = if c.noise > 0.0 && c.loss == LossKind::SelfSupervised {
            self.noisy.of(&clean, chunk, rng)
        } else {
            Vec::new()
        };
        let batch: Vec<&Sample> = clean.into_iter().chain(&copies).collect();
        let input = rows_tensor(
            &batch.iter().map(|s| s.input.as_slice()).collect::<Vec<_>>(),
            ad,
        );
        let z_hat = integrator.forward(input);
        let rows = |f: &dyn Fn(&Sample) -> &[f32]| {
            rows_tensor(&batch.iter().map(|s| f(s)).collect::<Vec<_>>(), ad)
        };
        match c.loss {
            LossKind::Supervised => (z_hat - rows(&|s| &s.truth)).powi_scalar(2).mean(),
            LossKind::Solved => (z_hat - rows(&|s| &s.solved)).powi_scalar(2).mean(),
            LossKind::SelfSupervised => self.loss_of.potential(&batch, z_hat).mean(),
        }
    }
}

/// The self-supervised loss summed over the clean training steps at the integrator's latents
/// and at the encoded reference's: a fit below the reference means the loss's minimum over the
/// decoder's manifold lies away from the reference (an autoencoder not accurate enough).
fn clean_potentials(
    clean: &[Sample],
    loss_of: &SelfLoss,
    integrator: &Integrator,
    ad: &Device,
) -> (f64, f64) {
    let (mut at_fit, mut at_truth) = (0.0, 0.0);
    for chunk in clean.chunks(512) {
        let chunk: Vec<&Sample> = chunk.iter().collect();
        let input = rows_tensor(
            &chunk.iter().map(|s| s.input.as_slice()).collect::<Vec<_>>(),
            ad,
        );
        let truth = rows_tensor(
            &chunk.iter().map(|s| s.truth.as_slice()).collect::<Vec<_>>(),
            ad,
        );
        let sum = |t: Tensor<1>| t.sum().into_scalar::<f32>() as f64;
        at_fit += sum(loss_of.potential(&chunk, integrator.forward(input)));
        at_truth += sum(loss_of.potential(&chunk, truth));
    }
    (at_fit, at_truth)
}

/// `loss = "solved"`: adds `noisy_copies` noisy copies of every clean sample (Eq. 5) and sets
/// every sample's `solved` to its step's latent minimiser of the potential, solved from
/// `2ẑ_{t−1} − ẑ_{t−2}` of its own input.
fn solve_targets(
    c: &IntegratorConfig,
    samples: &mut Vec<Sample>,
    loss: &SelfLoss,
    noisy: &NoisyCopies,
    rng: &mut StdRng,
    progress: &Progress,
) {
    if c.noise > 0.0 {
        let mut steps: Vec<usize> = (0..samples.len()).collect();
        let mut copies = Vec::new();
        for _ in 0..c.noisy_copies {
            // Random batches, as in training: the noise scale is each batch's deviation.
            steps.shuffle(rng);
            for idx in steps.chunks(c.batch) {
                let clean: Vec<&Sample> = idx.iter().map(|&i| &samples[i]).collect();
                copies.extend(noisy.of(&clean, idx, rng));
            }
        }
        samples.extend(copies);
    }
    solve_samples(samples, loss, &c.solve, progress);
}

/// Sets every sample's `solved` to its step's latent minimiser, searched from
/// `2ẑ_{t−1} − ẑ_{t−2}` of its own input.
fn solve_samples(
    samples: &mut [Sample],
    loss: &SelfLoss,
    solve: &SolveConfig,
    progress: &Progress,
) {
    let l = loss.z_mean.dims()[1];
    let bar = progress.bar(samples.len() as u64, "solving the steps' latents");
    let (mut before, mut after, mut unconverged) = (0.0, 0.0, 0);
    for chunk in samples.chunks_mut(512) {
        let guess: Vec<Vec<f32>> = chunk
            .iter()
            .map(|s| (0..l).map(|k| 2.0 * s.input[k] - s.input[l + k]).collect())
            .collect();
        let refs: Vec<&Sample> = chunk.iter().collect();
        let solved = loss.solve(&refs, &guess, solve);
        before += solved.mean_potential_at_start * chunk.len() as f64;
        after += solved.mean_potential * chunk.len() as f64;
        unconverged += solved.unconverged;
        for (s, z) in chunk.iter_mut().zip(solved.latents) {
            s.solved = z;
        }
        bar.inc(chunk.len() as u64);
    }
    bar.finish();
    let count = samples.len().max(1) as f64;
    progress.note(&format!(
        "solved {} steps' latents: mean potential {:.5e} at 2z₁ − z₂, {:.5e} at the minimisers{}",
        samples.len(),
        before / count,
        after / count,
        if unconverged > 0 {
            format!(
                "; {unconverged} did not converge within integrator.solve.iterations = {}",
                solve.iterations
            )
        } else {
            String::new()
        }
    ));
}

/// The steps the (plain) integrator visits when it rolls out over the training frames from
/// the first two, restarted from the encoded reference wherever a decoded frame leaves the
/// sheet's size from the reference; `solved` is left empty.
fn visited_steps(
    integrator: &Integrator,
    decoder: &Decoder,
    std: &[Vec<f32>],
    reference: &Reference,
    scales: &Scales,
    c: &IntegratorConfig,
    device: &Device,
) -> Vec<Sample> {
    let size = scales.length;
    let state = |z: &[f32], f: usize| {
        let rel = decode(decoder, &[scales.restore(z)], device).remove(0);
        absolute(&rel, reference.centre(f))
    };
    let (mut z2, mut z1) = (std[0].clone(), std[1].clone());
    let (mut x2, mut x1) = (state(&z2, 0), state(&z1, 1));
    let mut out = Vec::with_capacity(c.train_frames);
    for t in 2..c.train_frames {
        let input = step_input(&z1, &z2, &reference.features(t, size));
        let z = to_rows(integrator.forward(rows_tensor(&[input.as_slice()], device))).remove(0);
        out.push(Sample {
            input,
            truth: std[t].clone(),
            ..Sample::at(reference, t, &x1, &x2, c.velocity_floor)
        });
        let x = state(&z, t);
        let n = x.len() / 3;
        let se: f64 = x
            .iter()
            .zip(reference.frames[t].iter().flatten())
            .map(|(a, b)| (*a as f64 - b).powi(2))
            .sum();
        if (se / n as f64).sqrt() <= size {
            (z2, x2) = (std::mem::replace(&mut z1, z), std::mem::replace(&mut x1, x));
        } else {
            (z2, x2) = (std[t - 1].clone(), state(&std[t - 1], t - 1));
            (z1, x1) = (std[t].clone(), state(&std[t], t));
        }
    }
    out
}

/// Eq. 5's perturbation: uniform noise in `±noise · σ_k` on the first `dims` coordinates of
/// every row, `σ_k` the batch's deviation of coordinate `k`; the other coordinates unchanged.
/// `noise = 0` returns the rows as they are.
pub fn perturb(rows: &[Vec<f32>], dims: usize, noise: f64, rng: &mut StdRng) -> Vec<Vec<f32>> {
    let b = rows.len().max(1) as f64;
    let spread: Vec<f32> = (0..dims)
        .map(|k| {
            let m = rows.iter().map(|r| r[k] as f64).sum::<f64>() / b;
            let v = rows.iter().map(|r| (r[k] as f64 - m).powi(2)).sum::<f64>() / b;
            (noise * v.sqrt()) as f32
        })
        .collect();
    rows.iter()
        .map(|r| {
            let mut r = r.clone();
            if noise > 0.0 {
                for k in 0..dims {
                    r[k] += spread[k] * rng.random_range(-1.0f32..=1.0);
                }
            }
            r
        })
        .collect()
}

/// The noisy copies of a batch (Eq. 5): uniform noise of `noise` × the batch's deviation per
/// latent coordinate on `ẑ_{t−1}` and `ẑ_{t−2}`, the previous states decoded from the noisy
/// latents (gap G12), the boundary features unchanged.
struct NoisyCopies<'a> {
    noise: f64,
    decoder: &'a Decoder,
    scales: &'a Scales,
    reference: &'a Reference,
    device: &'a Device,
    /// The balancing's velocity floor, m/s.
    floor: f64,
}

impl NoisyCopies<'_> {
    /// The noisy copies of `batch`, the samples of steps `steps` (`t − 2`).
    fn of(&self, batch: &[&Sample], steps: &[usize], rng: &mut StdRng) -> Vec<Sample> {
        let (scales, reference, l) = (self.scales, self.reference, self.scales.mean.len());
        let clean: Vec<Vec<f32>> = batch.iter().map(|s| s.input.clone()).collect();
        let inputs = perturb(&clean, 2 * l, self.noise, rng);
        let restore = |k0: usize| -> Vec<Vec<f32>> {
            inputs
                .iter()
                .map(|i| scales.restore(&i[k0..k0 + l]))
                .collect()
        };
        let (prev, prev2) = (
            decode(self.decoder, &restore(0), self.device),
            decode(self.decoder, &restore(l), self.device),
        );
        batch
            .iter()
            .zip(steps)
            .enumerate()
            .map(|(k, (s, &i))| {
                let t = i + 2;
                let x1 = absolute(&prev[k], reference.centre(t - 1));
                let x2 = absolute(&prev2[k], reference.centre(t - 2));
                Sample {
                    input: inputs[k].clone(),
                    truth: s.truth.clone(),
                    ..Sample::at(reference, t, &x1, &x2, self.floor)
                }
            })
            .collect()
    }
}
