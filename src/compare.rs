//! `springtime compare`: the spring surrogate against the Neural ODE and GNN baselines, trained
//! and evaluated on the same data with the same code paths (paper §4.5, Table 2).
//!
//! One config drives all three: `model.kind` is set per family, everything else (data, cloth
//! grid, physics, evaluation) is shared. Runs go to `<out>/springs`, `<out>/gnn` and
//! `<out>/neural_ode`; finished runs trained with the same config are reused.

use crate::settings::Job;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use serde::{Deserialize, Serialize};

use crate::backend::Backend;
use crate::cloth::SpringLayout;
use crate::config::Config;
use crate::eval::EvalReport;
use crate::model::ModelKind;
use crate::progress::Progress;
use crate::train::{self, ModelMeta, RunDir, Status, TrainOptions};
use springtime_plot::{Series, curves_png};

/// Command-line choices of a comparison.
#[derive(Debug, Clone, Default)]
pub struct CompareOptions {
    /// Output directory (default `runs/<name>`).
    pub out: Option<PathBuf>,
    /// Retrain and re-evaluate every model even where a finished run exists.
    pub force: bool,
    /// Compute backend for every model (overrides the config's).
    pub backend: Option<Backend>,
}

/// One model family's line of the table.
#[derive(Debug, Clone)]
pub struct Row {
    /// The family.
    pub kind: ModelKind,
    /// Its run directory.
    pub run_dir: PathBuf,
    /// Learnable parameters.
    pub parameters: usize,
    /// Training wall time, s.
    pub train_seconds: f64,
    /// Peak resident memory while training, MiB.
    pub peak_rss_mib: f64,
    /// The larger side of the rest rectangle, m (to read the RMSE relative to the sheet).
    pub sheet_size: f64,
    /// Its evaluation.
    pub eval: EvalReport,
    /// Whether the run was reused rather than trained now.
    pub reused: bool,
}

/// What a comparison wrote.
#[derive(Debug, Clone)]
pub struct Comparison {
    /// Output directory.
    pub dir: PathBuf,
    /// One row per family, in Table 2's order.
    pub rows: Vec<Row>,
    /// `comparison.md`, `comparison.csv` and `comparison_rmse.png`.
    pub files: Vec<PathBuf>,
}

/// Trains (or reuses) and evaluates the three families, then writes the comparison.
pub fn compare(
    config: &Config,
    options: &CompareOptions,
    progress: &Progress,
) -> Result<Comparison> {
    if config.cloth.layout == SpringLayout::Data {
        bail!(
            "compare: `cloth.layout = \"data\"` is for the spring surrogate alone (the Neural ODE \
             and the GNN take the grid); train it with `springtime train`"
        );
    }
    let dir = config.run_dir(options.out.as_deref());
    std::fs::create_dir_all(&dir).with_context(|| format!("cannot create {}", dir.display()))?;
    let mut rows = Vec::new();
    for kind in ModelKind::ALL {
        let mut cfg = config.clone();
        cfg.model.kind = kind;
        cfg.name = format!("{}_{}", config.name, kind.name());
        if let Some(b) = options.backend {
            cfg.backend = b;
        }
        rows.push(
            compare_one(&cfg, &dir.join(kind.name()), options.force, progress)
                .with_context(|| format!("compare: the {} model", kind.name()))?,
        );
    }
    let files = vec![
        dir.join("comparison.md"),
        dir.join("comparison.csv"),
        dir.join("comparison_rmse.png"),
    ];
    crate::io::write_text(&files[0], &markdown(config, &rows))?;
    crate::io::write_text(&files[1], &csv(&rows)?)?;
    let series: Vec<Series> = rows
        .iter()
        .map(|r| {
            let m = &r.eval.motion_rmse;
            let times: Vec<f64> = if m.times.len() == m.per_frame.len() {
                m.times.clone()
            } else {
                (1..=m.per_frame.len())
                    .map(|j| j as f64 * m.frame_dt)
                    .collect()
            };
            Series::new(
                label(r.kind),
                times.into_iter().zip(m.per_frame.iter().copied()).collect(),
            )
        })
        .collect();
    curves_png(
        &files[2],
        &format!("{}: motion RMSE over the test rollouts", config.name),
        "time (s)",
        "motion RMSE (m), mean over rollouts",
        &series,
        true,
    )?;
    Ok(Comparison { dir, rows, files })
}

/// Trains, resumes or reuses one family's run in `run_dir`, then evaluates it.
fn compare_one(cfg: &Config, run_dir: &Path, force: bool, progress: &Progress) -> Result<Row> {
    let run = RunDir::new(run_dir);
    let state = run.state()?;
    let reused = reusable(cfg, &run, state.as_ref(), force)?;
    if reused {
        progress.note(&format!(
            "compare: reusing the finished {} run in {}",
            cfg.model.kind.name(),
            run_dir.display()
        ));
    } else {
        let resume = matches!(&state, Some(s) if s.status == Status::Running) && !force;
        progress.note(&format!(
            "compare: {} the {} model in {}",
            if resume { "resuming" } else { "training" },
            cfg.model.kind.name(),
            run_dir.display()
        ));
        train::train(
            cfg,
            &TrainOptions {
                out: Some(run_dir.to_path_buf()),
                resume,
                force,
            },
            progress,
        )?;
    }
    // A reused run keeps its evaluation when it has every figure the table needs.
    let previous_eval = if reused { complete_eval(&run) } else { None };
    let eval = match previous_eval {
        Some(e) => e,
        None => crate::run::evaluate(run_dir, None, Some(cfg.backend), &[], progress)?,
    };
    let state = run
        .state()?
        .with_context(|| format!("{} has no run.json", run_dir.display()))?;
    let meta = ModelMeta::read(&run.meta())?;
    Ok(Row {
        kind: cfg.model.kind,
        run_dir: run_dir.to_path_buf(),
        parameters: meta.parameters,
        train_seconds: state.wall_seconds,
        peak_rss_mib: state.peak_rss_mib,
        sheet_size: meta.width.max(meta.height),
        eval,
        reused,
    })
}

/// Whether the run in `run` (state `state`) is finished with the same config and is reused;
/// refuses, without `force`, a finished run of another config and a failed run.
fn reusable(
    cfg: &Config,
    run: &RunDir,
    state: Option<&train::RunState>,
    force: bool,
) -> Result<bool> {
    let run_dir = &run.dir;
    Ok(match state {
        Some(s) if s.status == Status::Finished && !force => {
            // Compared as requested: `config.toml` holds the values resolved from the data.
            let requested = run.requested_config();
            let path = if requested.exists() {
                requested
            } else {
                run.config()
            };
            let mut previous = Config::load(&path, &[])?;
            previous.backend = cfg.backend;
            if previous.to_toml() != cfg.to_toml() {
                bail!(
                    "{} holds a finished run trained with another config; pass --force to \
                     retrain it or --out to compare elsewhere",
                    run_dir.display()
                );
            }
            true
        }
        Some(s) if s.status == Status::Failed && !force => bail!(
            "{} holds a failed run ({}); pass --force to train it again",
            run_dir.display(),
            s.error.as_deref().unwrap_or("no message")
        ),
        _ => false,
    })
}

/// The run's `eval.json`, when it is readable and has the inference timing the table needs.
fn complete_eval(run: &RunDir) -> Option<EvalReport> {
    std::fs::read_to_string(run.eval())
        .ok()
        .and_then(|t| serde_json::from_str(&t).ok())
        .filter(|e: &EvalReport| e.inference.is_some())
}

fn label(kind: ModelKind) -> &'static str {
    match kind {
        ModelKind::Springs => "springs (ours)",
        ModelKind::Gnn => "GNN",
        ModelKind::NeuralOde => "Neural ODE",
    }
}

/// Paper Table 2 (FEM source, 15.5 m sheet): motion RMSE at 0.8 s and 8 s, training time.
const PAPER: [(ModelKind, &str, &str, &str); 3] = [
    (
        ModelKind::Springs,
        "4.2e-2 ± 4.4e-2",
        "0.77 ± 0.49",
        "≈ 1.5 h",
    ),
    (ModelKind::Gnn, "4.5e-2", "2.07", "≈ 48 h"),
    (ModelKind::NeuralOde, "14e-2", "3.18", "≈ 1.5 h"),
];

fn markdown(config: &Config, rows: &[Row]) -> String {
    let (short, long) = (config.eval.short_seconds, config.eval.long_seconds);
    let mut s = String::new();
    let _ = writeln!(s, "# Comparison: {}\n", config.name);
    if let Some(r) = rows.first() {
        let m = &r.eval.motion_rmse;
        let _ = writeln!(
            s,
            "Data `{}`: {} test rollouts; cloth model {} × {} particles (grid); backend {}.\n",
            config.data.dir.display(),
            m.rollouts,
            config.cloth.nx,
            config.cloth.ny,
            r.eval.backend
        );
    }
    let _ = writeln!(
        s,
        "| model | motion RMSE ≤ {short} s (m) | motion RMSE ≤ {long} s (m) | ≤ {long} s / sheet size | \
         training (s) | peak memory (MiB) | parameters | inference (µs / rollout·step) | step (ms) | \
         wall s per simulated s |"
    );
    let _ = writeln!(s, "|---|---|---|---|---|---|---|---|---|---|");
    for r in rows {
        let m = &r.eval.motion_rmse;
        let (us, step, rate) = r.eval.inference.as_ref().map_or(
            ("–".to_string(), "–".to_string(), "–".to_string()),
            |i| {
                (
                    format!("{:.1}", i.us_per_step),
                    format!("{:.0}", i.step_dt * 1e3),
                    format!("{:.3}", i.seconds_per_second),
                )
            },
        );
        let _ = writeln!(
            s,
            "| {} | {:.3e} ± {:.3e} | {:.3e} ± {:.3e} | {:.2}% | {:.1}{} | {:.0} | {} | {} | {} | {} |",
            label(r.kind),
            m.short.mean,
            m.short.std,
            m.long.mean,
            m.long.std,
            100.0 * m.long.mean / r.sheet_size,
            r.train_seconds,
            if r.reused { " (reused)" } else { "" },
            r.peak_rss_mib,
            r.parameters,
            us,
            step,
            rate
        );
    }
    let _ = writeln!(
        s,
        "\nPaper Table 2 (FEM source, 15.5 m sheet, 512 training rollouts, GPU), for reference:\n"
    );
    let _ = writeln!(s, "| model | ≤ 0.8 s (m) | ≤ 8 s (m) | training |");
    let _ = writeln!(s, "|---|---|---|---|");
    for (kind, a, b, t) in PAPER {
        let _ = writeln!(s, "| {} | {a} | {b} | {t} |", label(kind));
    }
    let _ = writeln!(
        s,
        "\nMotion RMSE (Eq. 14) is over every frame of every test rollout, on the surrogate's \
         particles (the source resampled to them); the GNN steps every `model.gnn.downsample` \
         frames, so its curve has fewer points. Inference is the model's steps only, batched as \
         `eval.batch`, on the backend above. Peak memory is the training process's: models \
         trained by one `compare` share a process, so a row includes the rows above it.\n\n![motion RMSE over time](comparison_rmse.png)"
    );
    s
}

/// One line of `comparison.csv` (columns in this order; the `csv` crate quotes what needs it,
/// e.g. a run directory with a comma).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CsvRow {
    /// Model family.
    pub model: String,
    /// Learnable parameters.
    pub parameters: usize,
    /// Training wall time, s.
    pub train_seconds: f64,
    /// Peak resident memory while training, MiB.
    pub peak_rss_mib: f64,
    /// Motion RMSE over the short horizon (`eval.short_seconds`), m.
    pub rmse_short_mean: f64,
    /// Its standard deviation.
    pub rmse_short_std: f64,
    /// Motion RMSE over the long horizon (`eval.long_seconds`), m.
    pub rmse_long_mean: f64,
    /// Its standard deviation.
    pub rmse_long_std: f64,
    /// Motion RMSE over whole test rollouts, m.
    pub rmse_mean: f64,
    /// Its standard deviation.
    pub rmse_std: f64,
    /// Inference cost, µs per rollout·step (empty when not measured).
    pub inference_us_per_step: Option<f64>,
    /// Simulated time one step advances, s.
    pub step_dt: Option<f64>,
    /// Wall seconds per simulated second.
    pub seconds_per_simulated_second: Option<f64>,
    /// The model's run directory.
    pub run_dir: String,
}

fn csv(rows: &[Row]) -> Result<String> {
    let mut w = ::csv::Writer::from_writer(Vec::new());
    for r in rows {
        let m = &r.eval.motion_rmse;
        let i = r.eval.inference.as_ref();
        w.serialize(CsvRow {
            model: r.kind.name().to_string(),
            parameters: r.parameters,
            train_seconds: r.train_seconds,
            peak_rss_mib: r.peak_rss_mib,
            rmse_short_mean: m.short.mean,
            rmse_short_std: m.short.std,
            rmse_long_mean: m.long.mean,
            rmse_long_std: m.long.std,
            rmse_mean: m.mean,
            rmse_std: m.std,
            inference_us_per_step: i.map(|i| i.us_per_step),
            step_dt: i.map(|i| i.step_dt),
            seconds_per_simulated_second: i.map(|i| i.seconds_per_second),
            run_dir: r.run_dir.display().to_string(),
        })?;
    }
    let bytes = w
        .into_inner()
        .map_err(|e| anyhow::anyhow!("comparison.csv: {e}"))?;
    Ok(String::from_utf8(bytes)?)
}

/// Reads a `comparison.csv`; errors name the file and the record.
pub fn read_csv(path: &Path) -> Result<Vec<CsvRow>> {
    let mut r = ::csv::Reader::from_path(path)
        .with_context(|| format!("cannot read {}", path.display()))?;
    r.deserialize()
        .map(|row| row.with_context(|| format!("{}: a malformed row", path.display())))
        .collect()
}
