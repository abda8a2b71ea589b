//! `springtime diagnose <run-dir>`: where a trained surrogate's error comes from, before any
//! tuning (issue 11). Writes into `<run-dir>/diagnose/` (or `--out`):
//!
//! | file | what |
//! |---|---|
//! | `chaos.json`, `chaos_floor.png` | the chaos floor: motion RMSE between a reference spring network and itself with every `k`, `b` perturbed by a relative `ε` ([`chaos`]) |
//! | `observability.json`, `observability.png` | per spring, how strongly the training data constrains `k` and `b` (the Fisher diagonal of the force loss, [`observability`]) |
//! | `error_map.json`, `error_map.png` | the run's free rollouts: per-rollout RMSE and the per-particle time-averaged error ([`error_map`]) |
//! | `source_map.json` | where the rollouts carry their source's stiffness map: that map on the structural springs, sized on the training takes, against the best uniform network at its step ([`source_map`]) |
//! | `diagnose.md` | the headline numbers, also printed |
//!
//! The run is opened as every command opens it ([`crate::run::Run::open`], [`report::data_files`]); test rollouts are simulated with [`eval::FreeRun`].

pub mod chaos;
pub mod error_map;
pub mod observability;
pub mod source_map;

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use burn::tensor::Device;

use crate::backend::Backend;
use crate::cloth::{Resampler, Topology};
use crate::config::Config;
use crate::data::Rollout;
use crate::eval::{self, FreeRollout, TestTrack};
use crate::model::SpringNet;
use crate::progress::Progress;
use crate::report;
use crate::sim::Physics;
use crate::train::{self, Truth};
use springtime_plot as plot;

pub use chaos::ChaosFloor;
pub use error_map::ErrorMap;
pub use observability::ObservabilityReport;
pub use source_map::SourceMap;

/// The files a diagnosis writes, in its output directory.
pub const FILES: [&str; 8] = [
    "chaos.json",
    "chaos_floor.png",
    "observability.json",
    "observability.png",
    "error_map.json",
    "error_map.png",
    "source_map.json",
    "diagnose.md",
];

/// Choices of `springtime diagnose`.
#[derive(Debug, Clone)]
pub struct DiagnoseOptions {
    /// Directory of test rollouts (every `.npz` in it), instead of the run's test split.
    pub data: Option<PathBuf>,
    /// Output directory (default `<run-dir>/diagnose`).
    pub out: Option<PathBuf>,
    /// Overwrite an existing diagnosis.
    pub force: bool,
    /// Relative perturbations `ε` of the chaos floor (level 0 is always added).
    pub levels: Vec<f64>,
    /// Seed of the perturbations.
    pub seed: u64,
    /// Backend of the simulations (default: the run's).
    pub backend: Option<Backend>,
}

impl Default for DiagnoseOptions {
    fn default() -> Self {
        Self {
            data: None,
            out: None,
            force: false,
            levels: vec![0.005, 0.01, 0.02],
            seed: 0,
            backend: None,
        }
    }
}

/// What a diagnosis wrote.
#[derive(Debug, Clone)]
pub struct DiagnoseSummary {
    /// The output directory.
    pub dir: PathBuf,
    /// Every file written.
    pub files: Vec<PathBuf>,
    /// The headline table of `diagnose.md` (Markdown).
    pub table: String,
    /// Parts left out and why.
    pub notes: Vec<String>,
}

/// The output directory of a diagnosis: `--out`, or `<run-dir>/diagnose`.
pub fn output_dir(run_dir: &Path, out: Option<&Path>) -> PathBuf {
    out.map_or_else(|| run_dir.join("diagnose"), Path::to_path_buf)
}

/// What every part of a diagnosis works on: the opened run and its test rollouts.
pub struct Inputs {
    /// The run's configuration.
    pub config: Config,
    /// The particles' grid.
    pub topology: Topology,
    /// The learned surrogate.
    pub model: SpringNet,
    /// Particle mass, kg.
    pub mass: f64,
    /// Ground-truth `k`, `b` per spring, when the data's springs are the surrogate's.
    pub truth: Option<Truth>,
    /// Test rollouts on the particles.
    pub tests: Vec<TestTrack>,
    /// Device of the simulations.
    pub device: Device,
}

impl Inputs {
    /// The simulation constants for rollouts `frame_dt` apart.
    pub fn physics(&self, frame_dt: f64) -> Physics {
        Physics::new(&self.config.sim, frame_dt, self.mass)
    }

    /// A spring network on the run's grid with the run's kernel (and the learned curvature
    /// elements, when the run has them: the chaos floor perturbs `k` and `b` only).
    pub fn network(&self, k: &[f64], b: &[f64]) -> SpringNet {
        SpringNet::new(&self.topology, k, b, &self.device)
            .with_kernel(self.config.model.kernel)
            .with_curvature(&self.model.curvature_values())
    }
}

/// Simulates `model` over the whole of a test rollout from its first usable frame, pinned
/// particles following the data, keeping every frame (`[steps + 1, P, 3]`); refuses an
/// unstable network (unless `sim.allow_unstable`), naming `what`.
pub fn free_rollout(
    inputs: &Inputs,
    model: &SpringNet,
    test: &TestTrack,
    what: &str,
    mut on_frame: impl FnMut(),
) -> Result<FreeRollout> {
    let physics = inputs.physics(test.frame_dt);
    physics
        .stability_of(&inputs.topology, model)
        .check(what, inputs.config.sim.allow_unstable)?;
    let steps = test.steps();
    eval::FreeRun::new(&test.track, test.first, steps)
        .simulate(model, &physics, &inputs.device, |_| on_frame())
        .with_context(|| format!("{what} on {}", test.path.display()))
}

/// Per-frame Eq. 14 RMSE between two free rollouts (or a rollout and the data) of one test
/// rollout: `(time, rmse)` for frames `1..=steps`.
pub fn curve_between(
    test: &TestTrack,
    x: &FreeRollout,
    target: impl Fn(usize) -> Vec<f32>,
) -> eval::Curve {
    let n = test.track.particles * 3;
    (1..x.frames.len())
        .map(|j| {
            let here = &x.positions[j * n..(j + 1) * n];
            (j as f64 * test.frame_dt, eval::frame_rmse(here, &target(j)))
        })
        .collect()
}

/// Drops the points of log-scale `series` more than `decades` below their largest value (the
/// first frames of a drift are many decades smaller and would flatten the rest).
pub fn log_window(series: &mut [plot::Series], decades: f64) {
    let top = series
        .iter()
        .flat_map(|s| s.points.iter().map(|p| p.1))
        .filter(|y| y.is_finite())
        .fold(0.0, f64::max);
    let floor = top * 10f64.powf(-decades);
    for s in series {
        s.points.retain(|p| p.1 >= floor);
    }
}

/// Refuses to overwrite an earlier diagnosis in `dir` unless `force`.
fn check_fresh(dir: &Path, force: bool) -> Result<()> {
    if force {
        return Ok(());
    }
    if let Some(f) = FILES.iter().map(|f| dir.join(f)).find(|f| f.exists()) {
        bail!(
            "{} holds a diagnosis already ({} exists); pass --force to overwrite it",
            dir.display(),
            f.display()
        );
    }
    Ok(())
}

/// Opens a finished spring run and its test rollouts.
pub fn open(run_dir: &Path, options: &DiagnoseOptions, progress: &Progress) -> Result<Inputs> {
    let run = crate::run::Run::open(run_dir, &[], options.backend)?;
    let model = run.springs()?.clone();
    let mass = run.particle_mass();
    let crate::run::Run {
        config,
        device,
        topology,
        ..
    } = run;
    let files = report::data_files(&config, options.data.as_deref())?;
    if files.test.is_empty() {
        bail!("no test rollouts: the data's index lists none; pass --data DIR with test rollouts");
    }
    let bar = progress.bar(files.test.len() as u64, "load");
    let mut tests = Vec::new();
    for f in &files.test {
        tests.push(TestTrack::load(f, &topology)?);
        bar.inc(1);
    }
    bar.finish();
    // Ground truth from the first rollout (every rollout of a set shares it).
    let first = Rollout::load(&files.test[0])?;
    let truth = first.springs.as_ref().and_then(|t| {
        train::matching_truth(
            t,
            &topology,
            &Resampler::new(&first.rest_uv, &topology.rest_uv),
        )
    });
    Ok(Inputs {
        config,
        topology,
        model,
        mass,
        truth,
        tests,
        device,
    })
}

/// Runs every diagnosis of a finished spring run and writes its files.
pub fn diagnose(
    run_dir: &Path,
    options: &DiagnoseOptions,
    progress: &Progress,
) -> Result<DiagnoseSummary> {
    let dir = output_dir(run_dir, options.out.as_deref());
    check_fresh(&dir, options.force)?;
    let levels = chaos::levels(&options.levels)?;
    let inputs = open(run_dir, options, progress)?;
    std::fs::create_dir_all(&dir).with_context(|| format!("cannot create {}", dir.display()))?;
    let mut files = Vec::new();
    let mut notes = Vec::new();

    let errors = error_map::error_map(&inputs, progress)?;
    files.extend(errors.write(&dir, &inputs)?);

    let floor = chaos::chaos_floor(&inputs, &levels, options.seed, progress)?;
    files.extend(floor.write(&dir, Some(&errors))?);

    let obs = match train::open_training_clips(&inputs.config, progress) {
        Ok((set, _)) => {
            let o = observability::observability(&set, &inputs, progress)?;
            files.extend(o.write(&dir, &inputs.topology)?);
            Some(o)
        }
        Err(e) => {
            notes.push(format!(
                "no observability map: the training rollouts cannot be opened ({e:#})"
            ));
            None
        }
    };

    let train_files = report::data_files(&inputs.config, options.data.as_deref())
        .map(|f| f.train)
        .unwrap_or_default();
    let source = match source_map::source_map(&inputs, run_dir, &train_files, progress)? {
        source_map::Outcome::Measured(c) => {
            files.push(c.write(&dir)?);
            Some(c)
        }
        source_map::Outcome::Skipped(why) => {
            notes.push(why);
            None
        }
    };

    let mut table = headline(&floor, obs.as_ref(), &errors);
    if let Some(c) = &source {
        table.push_str(&source_map_row(c, &floor));
    }
    let md = dir.join("diagnose.md");
    let mut text = format!("# Diagnosis of {}\n\n{table}", run_dir.display());
    for n in &notes {
        writeln!(text, "\nNote: {n}")?;
    }
    crate::io::write_text(&md, &text)?;
    files.push(md);
    Ok(DiagnoseSummary {
        dir,
        files,
        table,
        notes,
    })
}

/// The source-map reference's row of the headline table.
fn source_map_row(c: &SourceMap, floor: &ChaosFloor) -> String {
    let percent = |g: f64| format!("{:+.1} %", 100.0 * g);
    let run = c.run_gain.map_or(String::new(), |[s, l]| {
        format!("; the run: {} / {}", percent(s), percent(l))
    });
    let apart = c.uniform.bending_apart.as_ref().map_or(String::new(), |t| {
        format!(
            "; over the best bending-apart network (bending × {}): {} / {}",
            t.bending_factor,
            percent(t.improvement_short),
            percent(t.improvement_long)
        )
    });
    format!(
        "| the source's own stiffness map, sized: mean ≤ {} s / ≤ {} s (best uniform) | {:.3e} / {:.3e} m ({:.3e} / {:.3e}): {} / {}{apart}{run} |\n",
        floor.short_seconds,
        floor.long_seconds,
        c.map.short.mean,
        c.map.long.mean,
        c.uniform.test.short.mean,
        c.uniform.test.long.mean,
        percent(c.gain_short),
        percent(c.gain_long),
    )
}

/// The headline numbers as a Markdown table.
pub fn headline(
    floor: &ChaosFloor,
    obs: Option<&ObservabilityReport>,
    errors: &ErrorMap,
) -> String {
    let mut t = String::from("| quantity | value |\n|---|---|\n");
    let (short, long) = (floor.short_seconds, floor.long_seconds);
    let row = |t: &mut String, q: String, v: String| {
        let _ = writeln!(t, "| {q} | {v} |");
    };
    row(
        &mut t,
        format!("run's motion RMSE, mean ≤ {short} s / ≤ {long} s"),
        format!(
            "{:.3e} / {:.3e} m",
            errors.motion.short.mean, errors.motion.long.mean
        ),
    );
    for l in &floor.levels {
        row(
            &mut t,
            format!(
                "chaos floor ({} k, b), ε = {}: mean ≤ {long} s / at end",
                floor.reference, l.level
            ),
            format!("{:.3e} / {:.3e} m", l.mean_long, l.at_end),
        );
    }
    if let Some(o) = obs {
        for (sym, unit, ex) in [("k", "m", &o.extremes_k), ("b", "m/s", &o.extremes_b)] {
            row(
                &mut t,
                format!("observability of {sym}: least / most (RMS, {unit})"),
                format!(
                    "{:.3e} ({} #{}) / {:.3e} ({} #{}); {} springs unobserved",
                    ex.least.value,
                    ex.least.family,
                    ex.least.spring,
                    ex.most.value,
                    ex.most.family,
                    ex.most.spring,
                    ex.unobserved
                ),
            );
        }
        match &o.truth {
            Some(c) => {
                for (sym, s) in [("k", &c.k), ("b", &c.b)] {
                    row(
                        &mut t,
                        format!("Spearman(|{sym} error|, observability)"),
                        format!(
                            "{}; mean |error| of the 10 % least observable {:.3e}, of the rest {:.3e}",
                            s.spearman.map_or("undefined".into(), |r| format!("{r:.3}")),
                            s.least_observable.mean_error_least,
                            s.least_observable.mean_error_rest
                        ),
                    );
                }
            }
            None => row(
                &mut t,
                "Spearman(|error|, observability)".into(),
                "no per-spring ground truth".into(),
            ),
        }
    }
    for &i in errors.worst.iter().take(3) {
        let r = &errors.rollouts[i];
        row(
            &mut t,
            format!("worst rollout: {}", r.name),
            format!(
                "mean ≤ {short} s {:.3e} m, ≤ {long} s {:.3e} m, at end {:.3e} m",
                r.mean_short, r.mean_long, r.at_end
            ),
        );
    }
    t
}
