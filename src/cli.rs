//! The command line: one function per subcommand, each a few library calls.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result, bail};
use clap::{Parser, Subcommand};

use crate::backend::Backend;
use crate::cloth::Resampler;
use crate::config::Config;
use crate::data::{Rollout, Segment, SpringTruth, Track};
use crate::eval::{self, EvalReport};
use crate::progress::Progress;
use crate::sim::{self, Physics, Stability, State};
use crate::train::{self, RunDir, TrainOptions, Trained};

/// Learn simulatable mass-spring cloth models from motion.
#[derive(Debug, Parser)]
#[command(name = "springtime", version, about)]
pub struct Cli {
    /// What to do.
    #[command(subcommand)]
    pub command: Command,
}

/// Subcommands.
#[derive(Debug, Subcommand)]
pub enum Command {
    /// Generate the rollouts of a config's [source] into its data.dir.
    Generate {
        /// Config file.
        config: PathBuf,
        /// Override a config value: section.key=value (repeatable).
        #[arg(long = "set", value_name = "KEY=VALUE")]
        set: Vec<String>,
    },
    /// Train a surrogate (generating missing data first), then evaluate it.
    Train {
        /// Config file.
        config: PathBuf,
        /// Compute backend: flex, ndarray or wgpu.
        #[arg(long)]
        backend: Option<Backend>,
        /// Run directory (default runs/<name>).
        #[arg(long)]
        out: Option<PathBuf>,
        /// Continue an interrupted run from its last checkpoint.
        #[arg(long)]
        resume: bool,
        /// Overwrite an existing run.
        #[arg(long, conflicts_with = "resume")]
        force: bool,
        /// Skip the evaluation after training.
        #[arg(long)]
        no_eval: bool,
        /// Override a config value: section.key=value (repeatable).
        #[arg(long = "set", value_name = "KEY=VALUE")]
        set: Vec<String>,
    },
    /// Evaluate a trained run on its test rollouts (or those in --data) and write eval.json.
    Eval {
        /// Run directory.
        run_dir: PathBuf,
        /// Directory of test rollouts (every .npz in it).
        #[arg(long)]
        data: Option<PathBuf>,
        /// Compute backend.
        #[arg(long)]
        backend: Option<Backend>,
        /// Override a config value: section.key=value (repeatable).
        #[arg(long = "set", value_name = "KEY=VALUE")]
        set: Vec<String>,
    },
    /// Time the training workload of ../shared/bench/peer_torch.py; prints one JSON line.
    Bench {
        /// Clips per iteration.
        #[arg(long, default_value_t = 8)]
        batch: usize,
        /// Steps per clip.
        #[arg(long, default_value_t = 500)]
        steps: usize,
        /// Compute backend.
        #[arg(long, default_value = "flex")]
        backend: Backend,
        /// Timed iterations.
        #[arg(long, default_value_t = 3)]
        iters: usize,
        /// Spring-force implementation: fused or reference.
        #[arg(long, default_value = "fused", value_parser = parse_kernel)]
        kernel: crate::model::Kernel,
        /// Particles per side.
        #[arg(long, default_value_t = 32)]
        n: usize,
    },
    /// Simulate a trained surrogate from the first frame of a rollout file.
    Simulate {
        /// Run directory.
        run_dir: PathBuf,
        /// Rollout file giving the initial state and the pinned particles' path.
        #[arg(long)]
        init: PathBuf,
        /// Seconds to simulate.
        #[arg(long)]
        seconds: f64,
        /// Output rollout file (.npz).
        #[arg(long)]
        out: PathBuf,
        /// Compute backend.
        #[arg(long)]
        backend: Option<Backend>,
        /// Overwrite the output file.
        #[arg(long)]
        force: bool,
        /// Override a config value: section.key=value (repeatable).
        #[arg(long = "set", value_name = "KEY=VALUE")]
        set: Vec<String>,
    },
}

/// Runs a parsed command line.
pub fn run(cli: Cli) -> Result<()> {
    let progress = Progress::auto();
    match cli.command {
        Command::Generate { config, set } => generate(&config, &set, &progress),
        Command::Train {
            config,
            backend,
            out,
            resume,
            force,
            no_eval,
            set,
        } => {
            let mut cfg = Config::load(&config, &set)?;
            if let Some(b) = backend {
                cfg.backend = b;
            }
            let summary = train::train(&cfg, &TrainOptions { out, resume, force }, &progress)?;
            println!(
                "trained {} iterations in {:.1} s (peak memory {:.0} MiB){}",
                summary.iterations,
                summary.wall_seconds,
                summary.peak_rss_mib,
                match (summary.rmse_k, summary.rmse_b) {
                    (Some(k), Some(b)) => format!(": rmse_k {k:.4} N/m, rmse_b {b:.4} N·s/m"),
                    _ => String::new(),
                }
            );
            println!("run: {}", summary.run_dir.display());
            if !no_eval {
                let report = evaluate(&summary.run_dir, None, None, &[], &progress)?;
                print_eval(&report);
            }
            Ok(())
        }
        Command::Eval {
            run_dir,
            data,
            backend,
            set,
        } => {
            let report = evaluate(&run_dir, data.as_deref(), backend, &set, &progress)?;
            print_eval(&report);
            Ok(())
        }
        Command::Bench {
            batch,
            steps,
            backend,
            iters,
            kernel,
            n,
        } => {
            let report = crate::bench::run(&crate::bench::BenchOptions {
                batch,
                steps,
                backend,
                iters,
                kernel,
                n,
            })?;
            println!("{}", serde_json::to_string(&report)?);
            Ok(())
        }
        Command::Simulate {
            run_dir,
            init,
            seconds,
            out,
            backend,
            force,
            set,
        } => simulate(
            &run_dir, &init, seconds, &out, backend, force, &set, &progress,
        ),
    }
}

fn parse_kernel(s: &str) -> std::result::Result<crate::model::Kernel, String> {
    match s {
        "fused" => Ok(crate::model::Kernel::Fused),
        "reference" => Ok(crate::model::Kernel::Reference),
        other => Err(format!(
            "unknown kernel `{other}` (expected fused or reference)"
        )),
    }
}

fn generate(config: &Path, set: &[String], progress: &Progress) -> Result<()> {
    let cfg = Config::load(config, set)?;
    let Some(source) = &cfg.source else {
        bail!(
            "{} has no [source] section: nothing to generate",
            config.display()
        );
    };
    let start = Instant::now();
    let total = (source.train_rollouts + source.test_rollouts) as u64;
    let bar = progress.bar(total, "generate");
    let index = crate::source::generate(source, &cfg.data.clips, &cfg.data.dir, |n| {
        bar.set_position(n as u64)
    })?;
    bar.finish();
    println!(
        "wrote {} train and {} test rollouts to {} in {:.1} s",
        index.train.len(),
        index.test.len(),
        cfg.data.dir.display(),
        start.elapsed().as_secs_f64()
    );
    Ok(())
}

/// Evaluates a run and writes its `eval.json`.
pub fn evaluate(
    run_dir: &Path,
    data: Option<&Path>,
    backend: Option<Backend>,
    set: &[String],
    progress: &Progress,
) -> Result<EvalReport> {
    let start = Instant::now();
    let run = RunDir::new(run_dir);
    let mut overrides = set.to_vec();
    if let Some(b) = backend {
        overrides.push(format!("backend={b}"));
    }
    let device = match backend {
        Some(b) => b.device()?,
        None => Config::load(&run.config(), set)
            .with_context(|| format!("{} is not a run directory", run_dir.display()))?
            .backend
            .device()?,
    };
    let loaded = train::load_run(run_dir, &overrides, &device)?;
    let mut config = loaded.config;
    if let Some(d) = data {
        config.data.test_dir = Some(d.to_path_buf());
    }
    let topo = loaded.topology;
    let mass = loaded.meta.particle_mass;
    let split = config.data.split()?;
    let mut files = split.test;
    if files.is_empty() {
        bail!("no test rollouts: the data's index lists none; pass --data DIR with test rollouts");
    }
    if config.eval.max_rollouts > 0 {
        files.truncate(config.eval.max_rollouts);
    }
    let first = Rollout::load(&files[0])?;
    let physics = Physics {
        frame_dt: first.frame_dt,
        substeps: config.sim.substeps,
        mass,
        rayleigh: config.sim.rayleigh,
        gravity: config.sim.gravity,
    };
    let (curves, frame_dt) = match &loaded.model {
        Trained::Springs(model) => {
            Stability::estimate(
                &topo,
                &model.k_values(),
                &model.b_values(),
                mass,
                physics.rayleigh,
                physics.sim_dt(),
            )
            .check("the trained surrogate", config.sim.allow_unstable)?;
            let c = eval::motion_curves(
                model,
                &physics,
                &topo,
                &files,
                config.eval.batch,
                &device,
                progress,
            )?;
            (c, first.frame_dt)
        }
        Trained::NeuralOde(model) => {
            let c = eval::motion_curves(
                model,
                &physics,
                &topo,
                &files,
                config.eval.batch,
                &device,
                progress,
            )?;
            (c, first.frame_dt)
        }
        Trained::Gnn(model) => {
            let ds = config.model.gnn.downsample;
            let c = eval::gnn_motion_curves(
                model,
                ds,
                &topo,
                &files,
                config.eval.batch,
                &device,
                progress,
            )?;
            (c, first.frame_dt * ds as f64)
        }
    };
    let motion = eval::summarize(
        &curves,
        frame_dt,
        config.eval.short_seconds,
        config.eval.long_seconds,
    );
    let (mut rmse_k, mut rmse_b, mut stiffness_map_corr) = (None, None, None);
    if let Trained::Springs(model) = &loaded.model {
        let truth = first.springs.as_ref().and_then(|t| {
            let res = Resampler::new(&first.rest_uv, &topo.rest_uv);
            train::matching_truth(t, &topo, &res)
        });
        if let Some((k, b)) = truth {
            rmse_k = Some(train::rmse(&model.k_values(), &k));
            rmse_b = Some(train::rmse(&model.b_values(), &b));
        }
        stiffness_map_corr = first.mesh.as_ref().and_then(|mesh| {
            eval::stiffness_map_corr(&topo, &model.k_values(), &first.rest_uv, mesh)
        });
    }
    let report = EvalReport {
        rmse_k,
        rmse_b,
        stiffness_map_corr,
        motion_rmse: motion,
        test_rollouts: files,
        backend: config.backend.to_string(),
        seconds: start.elapsed().as_secs_f64(),
    };
    crate::io::write_json(&run.eval(), &report)?;
    Ok(report)
}

fn print_eval(r: &EvalReport) {
    let m = &r.motion_rmse;
    if let (Some(k), Some(b)) = (r.rmse_k, r.rmse_b) {
        println!("rmse_k {k:.4} N/m, rmse_b {b:.4} N·s/m");
    }
    if let Some(c) = r.stiffness_map_corr {
        println!(
            "stiffness map: Spearman correlation {c:.4} (structural springs vs the source's triangles)"
        );
    }
    println!(
        "motion RMSE over {} test rollouts: {:.4e} ± {:.4e} m (≤ 0.8 s: {:.4e} ± {:.4e}; ≤ 8 s: {:.4e} ± {:.4e})",
        m.rollouts, m.mean, m.std, m.mean_0_8s, m.std_0_8s, m.mean_8s, m.std_8s
    );
}

#[allow(clippy::too_many_arguments)]
fn simulate(
    run_dir: &Path,
    init: &Path,
    seconds: f64,
    out: &Path,
    backend: Option<Backend>,
    force: bool,
    set: &[String],
    progress: &Progress,
) -> Result<()> {
    if out.exists() && !force {
        bail!("{} exists; pass --force to overwrite it", out.display());
    }
    if !(seconds > 0.0 && seconds.is_finite()) {
        bail!("--seconds must be positive, is {seconds}");
    }
    let mut config = Config::load(&RunDir::new(run_dir).config(), set)?;
    if let Some(b) = backend {
        config.backend = b;
    }
    let device = config.backend.device()?;
    let (_, topo, model, mass) = train::load_surrogate(run_dir, &device)?;
    let rollout = Rollout::load(init)?;
    let res = Resampler::new(&rollout.rest_uv, &topo.rest_uv);
    let track = Track::new(&rollout, &res);
    let first = if rollout.velocities.is_some() { 0 } else { 1 };
    let physics = Physics {
        frame_dt: rollout.frame_dt,
        substeps: config.sim.substeps,
        mass,
        rayleigh: config.sim.rayleigh,
        gravity: config.sim.gravity,
    };
    Stability::estimate(
        &topo,
        &model.k_values(),
        &model.b_values(),
        mass,
        physics.rayleigh,
        physics.sim_dt(),
    )
    .check("the trained surrogate", config.sim.allow_unstable)?;
    let p = topo.num_particles();
    let frames = (seconds / rollout.frame_dt).round() as usize;
    let t3 = |v: &[f32]| {
        burn::tensor::Tensor::<3>::from_data(
            burn::tensor::TensorData::new(v.to_vec(), [1, p, 3]),
            &device,
        )
    };
    // Pinned particles follow the file's path while it lasts, then stay at its last frame.
    let observed = |j: usize| {
        let j = (first + j).min(track.frames - 1);
        &track.positions[j * p * 3..(j + 1) * p * 3]
    };
    let pinned_host: Vec<f32> = track.pinned.iter().map(|&x| x as u8 as f32).collect();
    let pinned = burn::tensor::Tensor::<3>::from_data(
        burn::tensor::TensorData::new(pinned_host, [1, p, 1]),
        &device,
    );
    let mut state = State {
        x: t3(observed(0)),
        v: t3(&track.velocities[first * p * 3..(first + 1) * p * 3]),
    };
    let mut positions: Vec<f32> = observed(0).to_vec();
    let mut velocities: Vec<f32> = track.velocities[first * p * 3..(first + 1) * p * 3].to_vec();
    let bar = progress.bar(frames as u64, "simulate");
    for j in 0..frames {
        let (here, next) = (t3(observed(j)), t3(observed(j + 1)));
        let (s, _) = sim::step_frame(&model, &physics, state, &pinned, &here, &next);
        state = s;
        let x: Vec<f32> = state
            .x
            .clone()
            .into_data()
            .try_into_vec_as::<f32>()
            .map_err(|e| anyhow::anyhow!("{e:?}"))?;
        if x.iter().any(|c| !c.is_finite()) {
            bail!(
                "the surrogate diverged at frame {} (t = {:.3} s)",
                j + 1,
                (j + 1) as f64 * physics.frame_dt
            );
        }
        positions.extend_from_slice(&x);
        velocities.extend(
            state
                .v
                .clone()
                .into_data()
                .try_into_vec_as::<f32>()
                .map_err(|e| anyhow::anyhow!("{e:?}"))?,
        );
        bar.inc(1);
    }
    bar.finish();
    let out_rollout = Rollout {
        path: out.to_path_buf(),
        frames: frames + 1,
        landmarks: p,
        positions,
        velocities: Some(velocities),
        rest_uv: topo.rest_uv.clone(),
        pinned: track.pinned.clone(),
        frame_dt: physics.frame_dt,
        total_mass: mass * p as f64,
        width: topo.width,
        height: topo.height,
        segments: vec![Segment {
            start: 0,
            offset: 0,
            len: frames + 1,
        }],
        springs: Some(SpringTruth {
            springs: topo.springs.clone(),
            k: model.k_values(),
            b: model.b_values(),
        }),
        mesh: None,
    };
    out_rollout.save(out)?;
    println!(
        "wrote {} frames ({seconds} s) to {}",
        frames + 1,
        out.display()
    );
    Ok(())
}
