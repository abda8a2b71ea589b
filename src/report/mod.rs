//! The run report: `springtime report <run-dir>` draws a finished run's figures into
//! `<run-dir>/report/` and writes `report.html` beside them, self-contained (every image
//! embedded as a `data:` URI, no network access).
//!
//! | file | shows |
//! |---|---|
//! | `training_curves.png` | each loss term per training pass and `rmse_k`/`rmse_b` (when the data has ground truth), log scale |
//! | `stiffness_map.png`, `damping_map.png` | learned `k` and `b` on the rest sheet, one panel per spring family, above the ground truth when known, one colour range |
//! | `curvature_map.png` | with `cloth.curvature`: the curvature elements' `κ` at their middle particles, one panel per direction (rows, columns, both diagonals) |
//! | `fem_stiffness.png` | an FEM source's triangle stiffness map beside the learned structural springs (FEM data only) |
//! | `fig7.png` | learned against true `k` and `b` (or their distributions without ground truth) and the per-frame motion RMSE over the test rollouts |
//! | `rollout.gif`, `rollout_frames.png` | the first test rollout: source landmarks and the surrogate's free rollout side by side |
//!
//! Figures that need rollouts (ground truth, motion RMSE, the animation) are skipped with a
//! note in the report when the run's data is not available; `--data DIR` points at test
//! rollouts elsewhere.

use springtime_plot as plot;
use springtime_plot::anim;

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use base64::Engine as _;
use plotters::prelude::*;

use crate::backend::Backend;
use crate::cloth::{Resampler, SpringFamily, Topology};
use crate::config::Config;
use crate::data::{MeshTruth, Rollout, Track};
use crate::eval::{self, Curve, EvalReport};
use crate::model::SpringNet;
use crate::progress::Progress;
use crate::run::Run;
use crate::sim::Physics;
use crate::train::{self, MetricsRow, RunState};

use anim::{Layer, View};
use plot::{Area, Series};

/// Choices of a report.
#[derive(Debug, Clone, Default)]
pub struct ReportOptions {
    /// Directory of test rollouts (every `.npz` in it), instead of the run's test split.
    pub data: Option<PathBuf>,
    /// Backend for the simulations (default: the run's).
    pub backend: Option<Backend>,
}

/// What a report wrote.
#[derive(Debug, Clone)]
pub struct ReportSummary {
    /// `report.html`.
    pub html: PathBuf,
    /// Every file written, `report.html` last.
    pub files: Vec<PathBuf>,
    /// Figures skipped and why.
    pub notes: Vec<String>,
}

/// The report directory of a run: `<run-dir>/report`.
pub fn report_dir(run_dir: &Path) -> PathBuf {
    run_dir.join("report")
}

/// A run's test and training rollout files, as its config (or `--data`) names them.
pub struct DataFiles {
    /// Test rollouts (at most `eval.max_rollouts`).
    pub test: Vec<PathBuf>,
    /// Training rollouts (empty when only `--data` is at hand).
    pub train: Vec<PathBuf>,
}

/// The rollout files of a run's config; `data` names a directory of test rollouts instead of
/// the config's split (which then serves alone when the training data is gone).
pub fn data_files(config: &Config, data: Option<&Path>) -> Result<DataFiles> {
    let mut data_cfg = config.data.clone();
    if let Some(d) = data {
        data_cfg.test_dir = Some(d.to_path_buf());
    }
    let (train, mut test) = match (data_cfg.split(), data) {
        (Ok(split), _) => (split.train, split.test),
        // The training data is gone but --data names test rollouts: they serve alone.
        (Err(_), Some(d)) => (Vec::new(), crate::data::npz_files(d)?),
        (Err(e), None) => return Err(e),
    };
    if config.eval.max_rollouts > 0 {
        test.truncate(config.eval.max_rollouts);
    }
    Ok(DataFiles { test, train })
}

/// Everything the figures draw from.
struct Inputs {
    name: String,
    /// The run's files.
    run: train::RunDir,
    config: Config,
    state: RunState,
    topology: Topology,
    model: SpringNet,
    mass: f64,
    k: Vec<f64>,
    b: Vec<f64>,
    metrics: Vec<MetricsRow>,
    eval: Option<EvalReport>,
    truth: Option<(Vec<f64>, Vec<f64>)>,
    mesh: Option<(Vec<[f64; 2]>, MeshTruth)>,
    test: Vec<PathBuf>,
    curves: Option<Vec<Curve>>,
    device: burn::tensor::Device,
}

/// Writes the report of a finished run into `<run-dir>/report/` and returns what it wrote.
pub fn build(
    run_dir: &Path,
    options: &ReportOptions,
    progress: &Progress,
) -> Result<ReportSummary> {
    let mut notes = Vec::new();
    let mut inputs = Inputs::read(run_dir, options, &mut notes)?;
    inputs.curves = motion_curves(&inputs, options, progress, &mut notes)?;
    if inputs.test.is_empty() && !notes.iter().any(|n| n.contains("not available")) {
        notes.push("no test rollouts: the rollout animation is left out".into());
    }
    let dir = report_dir(run_dir);
    std::fs::create_dir_all(&dir).with_context(|| format!("cannot create {}", dir.display()))?;
    let mut figures = figures(&dir, &inputs)?;
    if let Some(test) = inputs.test.first() {
        match rollout_figures(&dir, &inputs, test, progress) {
            Ok(f) => figures.extend(f),
            Err(e) => notes.push(format!(
                "rollout animation of {} left out: {e:#}",
                test.display()
            )),
        }
    }
    let html = dir.join("report.html");
    crate::io::write_text(&html, &html_page(&inputs, &figures, &notes)?)?;
    let mut written: Vec<PathBuf> = figures.iter().map(|f| f.path.clone()).collect();
    written.push(html.clone());
    Ok(ReportSummary {
        html,
        files: written,
        notes,
    })
}

impl Inputs {
    /// The finished run in `run_dir`, its metrics, evaluation and ground truth (the motion
    /// curves are left for [`motion_curves`]); notes what is missing or how training started.
    fn read(run_dir: &Path, options: &ReportOptions, notes: &mut Vec<String>) -> Result<Self> {
        let opened = Run::open(run_dir, &[], options.backend)?;
        let model = opened.springs()?.clone();
        let Run {
            dir: run,
            state,
            config,
            device,
            topology,
            meta,
            ..
        } = opened;
        let mass = meta.particle_mass;
        let metrics = train::run::read_metrics(&run.metrics(), false)?;
        let eval = read_eval(&run)?;
        let files = available_files(&config, options, notes)?;
        let truth = GroundTruth::read(&files, &topology, notes)?;
        note_least_squares(&run, notes)?;
        if let Some(v) = train::guard::Validation::read(&run.dir)? {
            notes.push(format!("validation (`data.holdout`): {}", v.summary()));
        }
        let (k, b) = (model.k_values(), model.b_values());
        Ok(Self {
            name: config.name.clone(),
            run,
            state,
            topology,
            model,
            mass,
            k,
            b,
            metrics,
            eval,
            truth: truth.springs,
            mesh: truth.mesh,
            test: files.test,
            curves: None,
            device,
            config,
        })
    }
}

/// The run's `eval.json`, when there is one.
pub(crate) fn read_eval(run: &train::RunDir) -> Result<Option<EvalReport>> {
    Ok(match std::fs::read_to_string(run.eval()) {
        Ok(text) => Some(
            serde_json::from_str(&text)
                .with_context(|| format!("{} is not a valid eval report", run.eval().display()))?,
        ),
        Err(_) => None,
    })
}

/// The run's rollout files ([`data_files`]), or none with a note when the run's own are gone
/// (rollouts named by `--data` must be there).
fn available_files(
    config: &Config,
    options: &ReportOptions,
    notes: &mut Vec<String>,
) -> Result<DataFiles> {
    Ok(match data_files(config, options.data.as_deref()) {
        Ok(f) => f,
        // Rollouts named on the command line must be there.
        Err(e) if options.data.is_some() => return Err(e),
        Err(e) => {
            notes.push(format!(
                "the run's rollouts are not available ({e:#}): the ground truth and the rollout \
                 animation are left out; pass --data DIR with test rollouts"
            ));
            DataFiles {
                test: Vec::new(),
                train: Vec::new(),
            }
        }
    })
}

/// What the data knows of the source: its springs' `k` and `b` (where they match the
/// surrogate's) and its mesh.
struct GroundTruth {
    springs: Option<(Vec<f64>, Vec<f64>)>,
    mesh: Option<(Vec<[f64; 2]>, MeshTruth)>,
}

impl GroundTruth {
    /// From the first rollout at hand (every rollout of a set shares it).
    fn read(files: &DataFiles, topology: &Topology, notes: &mut Vec<String>) -> Result<Self> {
        let (mut springs, mut mesh) = (None, None);
        if let Some(first) = files.test.first().or(files.train.first()) {
            let r = Rollout::load(first)?;
            springs = r.springs.as_ref().and_then(|t| {
                train::matching_truth(t, topology, &Resampler::new(&r.rest_uv, &topology.rest_uv))
            });
            if r.springs.is_some() && springs.is_none() {
                notes.push(
                    "the source's springs differ from the surrogate's: no per-spring ground truth"
                        .into(),
                );
            }
            mesh = r.mesh.clone().map(|m| (r.rest_uv.clone(), m));
        }
        Ok(Self { springs, mesh })
    }
}

/// Notes the least-squares start of training, when the run had one.
fn note_least_squares(run: &train::RunDir, notes: &mut Vec<String>) -> Result<()> {
    if let Ok(text) = std::fs::read_to_string(run.least_squares()) {
        let r: serde_json::Value = serde_json::from_str(&text)
            .map_err(|e| anyhow::anyhow!("{}: {e}", run.least_squares().display()))?;
        notes.push(format!(
            "training started from the per-spring least-squares fit of the data's forces \
             (`train.least_squares`, least_squares.json): stencil ±{} over {} frames, force \
             residual {:.3} of the target against the uniform start's {:.3}; {} of {} values \
             fixed at 0",
            r["stencil"],
            r["frames"],
            r["residual_fitted"].as_f64().unwrap_or(f64::NAN),
            r["residual_initial"].as_f64().unwrap_or(f64::NAN),
            r["fixed_at_zero"],
            r["unknowns"]
        ));
    }
    Ok(())
}

/// Per-rollout motion curves: from the last evaluation, or simulated now for --data; `None`
/// with a note when neither is at hand.
fn motion_curves(
    inputs: &Inputs,
    options: &ReportOptions,
    progress: &Progress,
    notes: &mut Vec<String>,
) -> Result<Option<Vec<Curve>>> {
    let csv = inputs.run.motion_curves();
    if options.data.is_none() && csv.exists() {
        return Ok(Some(eval::read_curves_csv(&csv)?));
    }
    if !inputs.test.is_empty() {
        match simulate_curves(inputs, progress) {
            Ok(c) => return Ok(Some(c)),
            Err(e) => notes.push(format!("no motion RMSE: {e:#}")),
        }
    } else {
        notes.push(format!(
            "no motion RMSE: {} is missing (run `springtime eval`) and no test rollouts are at hand",
            csv.display()
        ));
    }
    Ok(None)
}

/// Every figure but the rollout's: training curves, spring maps, curvature map, the FEM
/// source's map, Fig. 7 and the run's drapes.
fn figures(dir: &Path, inputs: &Inputs) -> Result<Vec<Figure>> {
    let mut figures: Vec<Figure> = Vec::new();
    figures.push(training_curves(dir, inputs)?);
    figures.extend(maps(dir, inputs)?);
    if !inputs.topology.curvature.is_empty() {
        figures.push(curvature_figure(dir, inputs)?);
    }
    if let Some(f) = fem_figure(dir, inputs)? {
        figures.push(f);
    }
    figures.push(fig7(dir, inputs)?);
    for (png, caption) in crate::drape::report_figures(&inputs.run.drapes()) {
        figures.push(Figure {
            path: png,
            heading: "Drape with contact (paper §4.5, Fig. 8)".into(),
            caption,
        });
    }
    Ok(figures)
}

/// The learned curvature stiffness of every curvature element.
fn curvature_figure(dir: &Path, inputs: &Inputs) -> Result<Figure> {
    let file = "curvature_map.png";
    let kappa = inputs.model.curvature_values();
    plot::curvature_map_png(
        &dir.join(file),
        &inputs.topology,
        &kappa,
        &format!("{}: curvature stiffness κ per element (N/m)", inputs.name),
    )?;
    let (lo, hi) = plot::value_range(&[&kappa]);
    Ok(figure(
        dir,
        file,
        "Learned curvature stiffness on the rest sheet",
        format!(
            "Every curvature element (three consecutive particles of a row, column or \
             diagonal, energy ½κ|x_i − 2x_j + x_l|²) drawn at its middle particle, coloured by \
             its κ ({lo:.3} to {hi:.3} N/m), one panel per direction: along the rows, the \
             columns, the main and the anti diagonal (border particles, the middle of none, \
             grey)."
        ),
    ))
}

fn physics_for(inputs: &Inputs, frame_dt: f64) -> Physics {
    Physics::new(&inputs.config.sim, frame_dt, inputs.mass)
}

fn simulate_curves(inputs: &Inputs, progress: &Progress) -> Result<Vec<Curve>> {
    let first = Rollout::load(&inputs.test[0])?;
    eval::motion_curves(
        &inputs.model,
        &physics_for(inputs, first.frame_dt),
        &eval::Takes {
            topology: &inputs.topology,
            files: &inputs.test,
            batch: inputs.config.eval.batch,
            device: &inputs.device,
            progress,
            cache: None,
            objective: eval::Objective::WholeTake,
        },
    )
    .map(|m| m.curves)
}

/// A written figure and its caption.
struct Figure {
    path: PathBuf,
    heading: String,
    caption: String,
}

fn figure(dir: &Path, file: &str, heading: &str, caption: String) -> Figure {
    Figure {
        path: dir.join(file),
        heading: heading.into(),
        caption,
    }
}

/// One panel of the training curves.
struct Panel {
    caption: String,
    series: Vec<Series>,
    y_label: &'static str,
    /// Marked iterations and their labels.
    marks: Vec<(f64, String)>,
}

fn training_curves(dir: &Path, inputs: &Inputs) -> Result<Figure> {
    let rows = &inputs.metrics;
    let mut passes: Vec<&str> = Vec::new();
    for r in rows {
        if !passes.contains(&r.pass.as_str()) {
            passes.push(&r.pass);
        }
    }
    let has_rmse = rows
        .iter()
        .any(|r| r.rmse_k.is_some() || r.rmse_b.is_some());
    let mut panels: Vec<Panel> = passes.iter().map(|p| loss_panel(inputs, p)).collect();
    if has_rmse {
        panels.push(rmse_panel(rows, &passes));
    }
    let cols = panels.len().clamp(1, 3);
    let rows_n = panels.len().div_ceil(cols).max(1);
    let (pw, ph) = plot::PLOT_PANEL;
    let path = dir.join("training_curves.png");
    plot::png_figure(&path, pw * cols as u32, ph * rows_n as u32, |root| {
        let cells = root.split_evenly((rows_n, cols));
        for (cell, p) in cells.iter().zip(&panels) {
            let marks: Vec<(f64, &str)> = p.marks.iter().map(|(x, s)| (*x, s.as_str())).collect();
            plot::draw_curves(
                cell,
                &p.caption,
                "iteration",
                p.y_label,
                &p.series,
                true,
                &marks,
            )?;
        }
        Ok(())
    })?;
    let total = rows.last().map_or(0, |r| r.iteration);
    Ok(figure(
        dir,
        "training_curves.png",
        "Training curves",
        format!(
            "Each loss term per iteration of every training pass ({} iterations in all), log scale: \
             in black the weighted sum that Adam minimises, in colour the unweighted terms with \
             their weights in the legend (force Eq. 7, impulse Eq. 9, position, and the k_neg/b_neg \
             penalties Eqs. 11–12; a term of weight 0 is only monitored); terms that stay zero \
             are not drawn. Each point is one batch of clips, so the curves are noisy.{}",
            total,
            if has_rmse {
                " The last panel is the RMSE of the learned k and b against the source's springs \
                 (Eq. 13) after each iteration; the stiffness pass trains k only, the damping pass b only."
            } else {
                ""
            }
        ),
    ))
}

/// One training pass's loss terms (each labelled with its weight) and their weighted sum.
fn loss_panel(inputs: &Inputs, pass: &str) -> Panel {
    let mine: Vec<&MetricsRow> = inputs.metrics.iter().filter(|r| r.pass == pass).collect();
    let weights = inputs
        .config
        .train
        .passes(crate::model::ModelKind::Springs)
        .into_iter()
        .find(|p| p.name == pass)
        .map(|p| p.config.weights.clone());
    let mut series = Vec::new();
    let mut total = None;
    for (t, (name, _)) in MetricsRow::default().terms().iter().enumerate() {
        let pts: Vec<(f64, f64)> = mine
            .iter()
            .map(|r| (r.iteration as f64, r.terms()[t].1))
            .collect();
        if !pts.iter().any(|p| p.1 > 0.0 && p.1.is_finite()) {
            continue;
        }
        let weight = weights.as_ref().map(|w| match *name {
            "force" => w.force,
            "impulse" => w.impulse,
            "position" => w.position,
            "k_neg" => w.k_neg,
            _ => w.b_neg,
        });
        match (*name, weight) {
            ("loss", _) => {
                total = Some(
                    Series::new("loss (weighted sum)", pts)
                        .with_color(RGBColor(0, 0, 0))
                        .with_width(1),
                )
            }
            (_, Some(0.0)) => series.push(Series::new(
                format!("{name} (weight 0: not in the loss)"),
                pts,
            )),
            (_, Some(w)) => series.push(Series::new(format!("{name} × {}", plot::tick(w)), pts)),
            (_, None) => series.push(Series::new(*name, pts)),
        }
    }
    // The total last, on top of the terms it sums.
    series.extend(total);
    Panel {
        caption: format!("{pass} pass: loss terms"),
        series,
        y_label: "loss",
        marks: Vec::new(),
    }
}

/// `rmse_k` and `rmse_b` over every pass, marking where each pass starts.
fn rmse_panel(rows: &[MetricsRow], passes: &[&str]) -> Panel {
    let bounds: Vec<(f64, String)> = passes
        .iter()
        .filter_map(|p| {
            rows.iter()
                .find(|r| r.pass == *p)
                .map(|r| (r.iteration as f64 - 0.5, format!("{p} pass →")))
        })
        .collect();
    let series = vec![
        Series::new(
            "rmse_k (N/m)",
            rows.iter()
                .filter_map(|r| r.rmse_k.map(|v| (r.iteration as f64, v)))
                .collect(),
        ),
        Series::new(
            "rmse_b (N·s/m)",
            rows.iter()
                .filter_map(|r| r.rmse_b.map(|v| (r.iteration as f64, v)))
                .collect(),
        ),
    ];
    Panel {
        caption: "parameter error against the ground truth".into(),
        series,
        y_label: "RMSE",
        marks: bounds,
    }
}

fn family_index(f: SpringFamily) -> usize {
    match f {
        SpringFamily::Structural => 0,
        SpringFamily::Shear => 1,
        SpringFamily::Bending => 2,
    }
}

const FAMILY_NAMES: [&str; 3] = ["structural", "shear", "bending"];

/// Ground truth with at most this many distinct values is drawn as per-level columns.
const MAX_LEVELS: usize = 12;

fn maps(dir: &Path, inputs: &Inputs) -> Result<Vec<Figure>> {
    let mut out = Vec::new();
    for (file, heading, sym, unit, learned, truth) in [
        (
            "stiffness_map.png",
            "Learned stiffness on the rest sheet",
            "k",
            "N/m",
            &inputs.k,
            inputs.truth.as_ref().map(|t| &t.0),
        ),
        (
            "damping_map.png",
            "Learned damping on the rest sheet",
            "b",
            "N·s/m",
            &inputs.b,
            inputs.truth.as_ref().map(|t| &t.1),
        ),
    ] {
        let mut rows: Vec<(&str, &[f64])> = vec![("learned", learned)];
        if let Some(t) = truth {
            rows.push(("true", t));
        }
        let sets: Vec<&[f64]> = rows.iter().map(|r| r.1).collect();
        let range = plot::value_range(&sets);
        plot::spring_maps_png(
            &dir.join(file),
            &inputs.topology,
            &rows,
            &format!(
                "{}: {} per spring ({unit})",
                inputs.name,
                if sym == "k" {
                    "stiffness k"
                } else {
                    "damping b"
                }
            ),
            range,
            &format!("{sym} ({unit})"),
        )?;
        out.push(figure(
            dir,
            file,
            heading,
            format!(
                "Every spring of the surrogate drawn between its rest endpoints on the unrolled \
                 sheet (u, v in metres), coloured by its {sym} on one scale ({} to {} {unit}), one \
                 panel per family: structural (grid edges), shear (cell diagonals, which cross \
                 in each cell) and bending (stride-{} springs, shifted sideways by their phase so \
                 that overlapping springs stay visible).{}",
                plot::tick(range.0),
                plot::tick(range.1),
                inputs.config.cloth.bending_stride,
                if truth.is_some() {
                    " The bottom row is the source's ground truth on the same scale."
                } else {
                    " The data carries no per-spring ground truth."
                }
            ),
        ));
    }
    Ok(out)
}

fn fem_figure(dir: &Path, inputs: &Inputs) -> Result<Option<Figure>> {
    let Some((uv, mesh)) = &inputs.mesh else {
        return Ok(None);
    };
    let Some(src_stiffness) = &mesh.stiffness else {
        return Ok(None);
    };
    let src_range = plot::value_range(&[src_stiffness]);
    let structural: Vec<f64> = inputs
        .k
        .iter()
        .zip(&inputs.topology.family)
        .filter(|(_, f)| **f == SpringFamily::Structural)
        .map(|(k, _)| *k)
        .collect();
    let k_range = plot::value_range(&[&structural]);
    let (pw, ph) = plot::MAP_PANEL;
    let bw = plot::COLORBAR_WIDTH;
    let path = dir.join("fem_stiffness.png");
    plot::png_figure(&path, 2 * (pw + bw), ph + plot::TITLE_HEIGHT, |root| {
        let body = plot::title(
            root,
            "FEM source stiffness map and learned structural springs",
            18,
        )?;
        let halves = body.split_evenly((1, 2));
        let (a, abar) = halves[0].split_horizontally(pw);
        plot::draw_map(
            &a,
            plot::Map::Triangles {
                rest_uv: uv,
                triangles: &mesh.triangles,
            },
            src_stiffness,
            "source: triangles",
            src_range,
        )?;
        plot::draw_colorbar(&abar, src_range, "source stiffness")?;
        let (b, bbar) = halves[1].split_horizontally(pw);
        plot::draw_map(
            &b,
            plot::Map::Springs {
                topology: &inputs.topology,
                family: Some(SpringFamily::Structural),
            },
            &inputs.k,
            "learned: structural springs",
            k_range,
        )?;
        plot::draw_colorbar(&bbar, k_range, "k (N/m)")
    })?;
    Ok(Some(figure(
        dir,
        "fem_stiffness.png",
        "FEM source and learned stiffness",
        "Left: the FEM source's stiffness map, each mesh triangle filled by its value. Right: the \
         learned stiffness of the surrogate's structural springs (cf. the paper's Fig. 10 a–b). \
         The two have different units and each has its own colour scale: compare patterns, not \
         colours."
            .into(),
    )))
}

/// `(x, min, mean, max)` of the curves at each frame index, subsampled to at most `n` points.
fn spread(curves: &[Curve], n: usize) -> plot::Band {
    let longest = curves.iter().map(Vec::len).max().unwrap_or(0);
    let step = longest.div_ceil(n.max(1)).max(1);
    (0..longest)
        .step_by(step)
        .filter_map(|j| {
            let v: Vec<(f64, f64)> = curves.iter().filter_map(|c| c.get(j).copied()).collect();
            if v.is_empty() {
                return None;
            }
            let mean = v.iter().map(|p| p.1).sum::<f64>() / v.len() as f64;
            let lo = v.iter().map(|p| p.1).fold(f64::INFINITY, f64::min);
            let hi = v.iter().map(|p| p.1).fold(f64::NEG_INFINITY, f64::max);
            Some((v[0].0, lo, mean, hi))
        })
        .collect()
}

fn fig7(dir: &Path, inputs: &Inputs) -> Result<Figure> {
    let (pw, ph) = plot::PLOT_PANEL;
    let path = dir.join("fig7.png");
    let curves = inputs.curves.as_deref().unwrap_or(&[]);
    plot::png_figure(&path, 3 * pw, ph + plot::TITLE_HEIGHT, |root| {
        let body = plot::title(
            root,
            &format!("{}: learned parameters and motion error", inputs.name),
            18,
        )?;
        let cells = body.split_evenly((1, 3));
        draw_parameters(&cells[0], &cells[1], inputs)?;
        draw_motion_rmse(&cells[2], curves)
    })?;
    Ok(figure(
        dir,
        "fig7.png",
        "Parameters and motion error (cf. the paper's Fig. 7)",
        fig7_caption(inputs, curves.len()),
    ))
}

/// Fig. 7 (a) and (b): learned against true `k` and `b`, or their distributions without
/// ground truth, coloured by spring family.
fn draw_parameters<'a>(k_cell: &Area<'a>, b_cell: &Area<'a>, inputs: &Inputs) -> Result<()> {
    let groups: Vec<usize> = inputs
        .topology
        .family
        .iter()
        .map(|f| family_index(*f))
        .collect();
    match &inputs.truth {
        Some((tk, tb)) => {
            for (cell, caption, quantity, truth, learned) in [
                (k_cell, "(a) stiffness per spring", "k (N/m)", tk, &inputs.k),
                (b_cell, "(b) damping per spring", "b (N·s/m)", tb, &inputs.b),
            ] {
                // A few true levels: strips per level; a continuous truth: a scatter.
                let draw = if plot::levels(truth).len() <= MAX_LEVELS {
                    plot::draw_level_strips
                } else {
                    plot::draw_truth_scatter
                };
                draw(
                    cell,
                    caption,
                    quantity,
                    truth,
                    learned,
                    &groups,
                    &FAMILY_NAMES,
                )?;
            }
        }
        None => {
            plot::draw_histogram(
                k_cell,
                "(a) learned stiffness",
                "k (N/m)",
                &inputs.k,
                &groups,
                &FAMILY_NAMES,
                40,
            )?;
            plot::draw_histogram(
                b_cell,
                "(b) learned damping",
                "b (N·s/m)",
                &inputs.b,
                &groups,
                &FAMILY_NAMES,
                40,
            )?;
        }
    }
    Ok(())
}

/// Fig. 7 (c): the per-frame motion RMSE of every test rollout, their mean and range.
fn draw_motion_rmse(cell: &Area, curves: &[Curve]) -> Result<()> {
    let members: Vec<Vec<(f64, f64)>> = curves
        .iter()
        .map(|c| {
            let step = c.len().div_ceil(600).max(1);
            c.iter().step_by(step).copied().collect()
        })
        .collect();
    if curves.is_empty() {
        return plot::draw_message(
            cell,
            "(c) per-frame motion RMSE (Eq. 14)",
            "no motion RMSE: no evaluation and no test rollouts",
        );
    }
    let band = spread(curves, 600);
    let mean_label = format!("mean over {} test rollouts", curves.len());
    plot::draw_band(
        cell,
        "(c) per-frame motion RMSE (Eq. 14)",
        "time since start (s)",
        "RMSE (m)",
        &members,
        &band,
        (&mean_label, "min – max over rollouts", "each rollout"),
    )
}

/// Fig. 7's caption, for what its panels show and `rollouts` test rollouts.
fn fig7_caption(inputs: &Inputs, rollouts: usize) -> String {
    let m = inputs.eval.as_ref().map(|e| &e.motion_rmse);
    format!(
        "{} (c) The per-frame motion RMSE of the surrogate simulated freely from the first \
         frame of each of {} test rollouts, pinned particles following the data: the bold line is \
         the mean over rollouts, the band their range, thin grey lines each rollout (empty \
         without an evaluation or test rollouts).{}",
        match &inputs.truth {
            Some((tk, tb))
                if plot::levels(tk).len() <= MAX_LEVELS && plot::levels(tb).len() <= MAX_LEVELS =>
            {
                "(a), (b) Learned stiffness and damping of every spring, grouped by the \
                 source's true value (x axis) and coloured by family; points are spread \
                 sideways within their column only to keep them apart. The red line is the \
                 true value, the black tick the mean of each column: a column centred on \
                 the red line with little spread is an exact recovery."
            }
            Some(_) => {
                "(a), (b) Learned against true stiffness and damping, one point per spring, \
                 coloured by family (or true levels as columns when there are few); points \
                 on the black identity line are exact."
            }
            None => {
                "(a), (b) Distributions of the learned stiffness and damping (the data has \
                 no per-spring ground truth), stacked by spring family."
            }
        },
        rollouts,
        match m {
            Some(m) => format!(
                " Over all frames: {:.3e} ± {:.3e} m (eval.json).",
                m.mean, m.std
            ),
            None => String::new(),
        }
    )
}

/// Frames of the animation: at most `n` from `0..=frames`, evenly spaced, with the first and
/// the last.
fn animation_frames(frames: usize, n: usize) -> Vec<usize> {
    let n = n.min(frames + 1);
    if n < 2 {
        return (0..=frames).collect();
    }
    let mut v: Vec<usize> = (0..n)
        .map(|i| ((i as f64 / (n - 1) as f64) * frames as f64).round() as usize)
        .collect();
    v.dedup();
    v
}

/// Edges to draw for the source's landmarks: its mesh edges, or its shortest springs (the
/// structural grid of a mass-spring source), or none.
fn source_edges(r: &Rollout) -> Vec<[usize; 2]> {
    if let Some(m) = &r.mesh {
        let mut e: Vec<[usize; 2]> = m
            .triangles
            .iter()
            .flat_map(|t| [[t[0], t[1]], [t[1], t[2]], [t[2], t[0]]])
            .map(|[a, b]| [a.min(b), a.max(b)])
            .collect();
        e.sort_unstable();
        e.dedup();
        return e;
    }
    let Some(s) = &r.springs else {
        return Vec::new();
    };
    let len = |[a, b]: [usize; 2]| {
        let (p, q) = (r.rest_uv[a], r.rest_uv[b]);
        ((p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2)).sqrt()
    };
    let shortest = s
        .springs
        .iter()
        .map(|&e| len(e))
        .fold(f64::INFINITY, f64::min);
    s.springs
        .iter()
        .copied()
        .filter(|&e| len(e) <= 1.2 * shortest)
        .collect()
}

fn rollout_figures(
    dir: &Path,
    inputs: &Inputs,
    test: &Path,
    progress: &Progress,
) -> Result<Vec<Figure>> {
    let scene = RolloutScene::simulate(inputs, test, progress)?;
    scene.write_gif(&dir.join("rollout.gif"))?;
    scene.write_stills(&dir.join("rollout_frames.png"))?;
    let caption = |what: &str| {
        format!(
            "{what} Test rollout {}: on the left (top) the source's landmarks{}, on the right \
             (bottom) the surrogate's particles and structural springs simulated freely from the \
             first frame, its pinned particles (red) following the data; light grey dots behind \
             the surrogate are the source, so any gap is the motion error. A fixed oblique view \
             (z up, gravity along −z; the triad shows the axes), the same scale in every frame.",
            scene.name,
            if scene.src_edges.is_empty() {
                ""
            } else {
                " and their edges"
            }
        )
    };
    let duration = scene.frames as f64 * scene.r.frame_dt;
    Ok(vec![
        figure(
            dir,
            "rollout.gif",
            "Rollout animation",
            caption(&format!(
                "{} frames over {duration:.2} s, played in real time, holding the last frame.",
                scene.sim.frames.len(),
            )),
        ),
        figure(
            dir,
            "rollout_frames.png",
            "Key frames",
            caption("The start, early motion and the last frame of the rollout."),
        ),
    ])
}

/// A test rollout and the surrogate's free rollout beside it, ready to draw.
struct RolloutScene {
    name: String,
    r: Rollout,
    sim: eval::FreeRollout,
    src_edges: Vec<[usize; 2]>,
    structural: Vec<[usize; 2]>,
    /// The surrogate's pinned particles.
    pinned: Vec<bool>,
    view: View,
    bounds: ((f64, f64), (f64, f64)),
    particles: usize,
    /// The rollout's first usable frame.
    first: usize,
    /// Frames simulated.
    frames: usize,
}

impl RolloutScene {
    /// The surrogate simulated freely from the first state frame of the rollout file `test`,
    /// its pinned particles following the data, keeping the animation's frames.
    fn simulate(inputs: &Inputs, test: &Path, progress: &Progress) -> Result<Self> {
        let r = Rollout::load(test)?;
        if r.segments.len() != 1 {
            bail!("a test rollout must be stored in full (it has `segments`)");
        }
        let topo = &inputs.topology;
        let res = Resampler::new(&r.rest_uv, &topo.rest_uv);
        let track = Track::new(&r, &res);
        let first = r.first_state_frame();
        let frames = r.frames - 1 - first;
        let physics = physics_for(inputs, r.frame_dt);
        let keep = animation_frames(frames, 80);
        let bar = progress.bar(frames as u64, "animate");
        let sim = eval::FreeRun::new(&track, first, frames)
            .keeping(&keep)
            .simulate(&inputs.model, &physics, &inputs.device, |_| bar.inc(1))?;
        bar.finish();
        let mut scene = RolloutScene {
            name: test
                .file_name()
                .map(|f| f.to_string_lossy().into_owned())
                .unwrap_or_default(),
            src_edges: source_edges(&r),
            structural: topo
                .springs
                .iter()
                .zip(&topo.family)
                .filter(|(_, f)| **f == SpringFamily::Structural)
                .map(|(s, _)| *s)
                .collect(),
            pinned: track.pinned.clone(),
            view: View::default(),
            bounds: ((0.0, 0.0), (0.0, 0.0)),
            particles: topo.num_particles(),
            first,
            frames,
            r,
            sim,
        };
        scene.bounds = scene.view.bounds(
            scene
                .sim
                .frames
                .iter()
                .map(|&j| scene.src(j))
                .chain((0..scene.sim.frames.len()).map(|i| scene.sur(i))),
        );
        Ok(scene)
    }

    /// The source's landmarks at simulated frame `j`.
    fn src(&self, j: usize) -> &[f32] {
        let n = self.r.landmarks;
        &self.r.positions[(self.first + j) * n * 3..(self.first + j + 1) * n * 3]
    }

    /// The surrogate's particles at kept frame `i`.
    fn sur(&self, i: usize) -> &[f32] {
        let p = self.particles;
        &self.sim.positions[i * p * 3..(i + 1) * p * 3]
    }

    /// Source (left or top) and surrogate (right or bottom) at kept frame `i`.
    fn pair(&self, left: &Area, right: &Area, i: usize, captions: (&str, &str)) -> Result<()> {
        plot_pair(
            left,
            right,
            &self.view,
            self.bounds,
            (
                self.src(self.sim.frames[i]),
                &self.src_edges,
                &self.r.pinned,
            ),
            (self.sur(i), &self.structural, &self.pinned),
            captions,
        )
    }

    /// The animation: each frame shown for its time in the rollout (rounded to the GIF's
    /// hundredths of a second without drifting), the last held.
    fn write_gif(&self, path: &Path) -> Result<()> {
        let (w, h) = (760u32, 430u32);
        let dt = self.r.frame_dt;
        let duration = self.frames as f64 * dt;
        let frames = &self.sim.frames;
        let mut rgb_frames = Vec::with_capacity(frames.len());
        let mut delays = Vec::with_capacity(frames.len());
        let cs = |j: usize| (j as f64 * dt * 100.0).round() as i64;
        for (i, &j) in frames.iter().enumerate() {
            let t = j as f64 * dt;
            rgb_frames.push(plot::render(w, h, |root| {
                let body = plot::title(
                    root,
                    &format!(
                        "test rollout {}   t = {t:.3} s of {duration:.2} s",
                        self.name
                    ),
                    16,
                )?;
                let (pair, legend) = body.split_vertically(h - plot::TITLE_HEIGHT - 22);
                let halves = pair.split_evenly((1, 2));
                self.pair(
                    &halves[0],
                    &halves[1],
                    i,
                    ("source: landmarks", "surrogate: learned springs"),
                )?;
                legend
                    .draw(&Text::new(
                        "red: pinned, following the data  ·  grey dots (right): the source  ·  \
                         fixed oblique view, z up",
                        (12, 2),
                        plot::text(12).color(&RGBColor(90, 90, 90)),
                    ))
                    .map_err(|e| anyhow::anyhow!("drawing failed: {e}"))?;
                Ok(())
            })?);
            let delay = match frames.get(i + 1) {
                Some(&next) => cs(next) - cs(j),
                None => 150, // hold the last state
            };
            delays.push(delay.clamp(2, u16::MAX as i64) as u16);
        }
        plot::write_gif(path, w, h, &rgb_frames, &delays)
    }

    /// Key frames: the start, early motion and the end, source above surrogate.
    fn write_stills(&self, path: &Path) -> Result<()> {
        let frames = &self.sim.frames;
        let picks: Vec<usize> = [0.0, 0.05, 0.15, 0.4, 1.0]
            .iter()
            .map(|f| {
                let target = (f * self.frames as f64).round() as usize;
                (0..frames.len())
                    .min_by_key(|&i| frames[i].abs_diff(target))
                    .unwrap_or(0)
            })
            .collect::<std::collections::BTreeSet<_>>()
            .into_iter()
            .collect();
        let (cw, ch) = (270u32, 250u32);
        plot::png_figure(
            path,
            cw * picks.len() as u32,
            2 * ch + plot::TITLE_HEIGHT,
            |root| {
                let body = plot::title(
                    root,
                    &format!(
                        "test rollout {}: source (top) and surrogate (bottom)",
                        self.name
                    ),
                    16,
                )?;
                let cells = body.split_evenly((2, picks.len()));
                for (c, &i) in picks.iter().enumerate() {
                    let t = frames[i] as f64 * self.r.frame_dt;
                    let end = if frames[i] == self.frames {
                        " (end)"
                    } else {
                        ""
                    };
                    self.pair(
                        &cells[c],
                        &cells[picks.len() + c],
                        i,
                        (
                            &format!("source, t = {t:.2} s{end}"),
                            &format!("surrogate, t = {t:.2} s{end}"),
                        ),
                    )?;
                }
                Ok(())
            },
        )
    }
}

type Cloth<'a> = (&'a [f32], &'a [[usize; 2]], &'a [bool]);

fn plot_pair(
    left: &Area,
    right: &Area,
    view: &View,
    bounds: ((f64, f64), (f64, f64)),
    source: Cloth,
    surrogate: Cloth,
    captions: (&str, &str),
) -> Result<()> {
    let dark = RGBColor(60, 60, 60);
    let blue = RGBColor(31, 119, 180);
    anim::draw_cloth(
        left,
        captions.0,
        view,
        bounds,
        &[Layer {
            positions: source.0,
            edges: source.1,
            pinned: source.2,
            color: dark,
            radius: 2,
        }],
    )?;
    anim::draw_cloth(
        right,
        captions.1,
        view,
        bounds,
        &[
            Layer {
                positions: source.0,
                edges: &[],
                pinned: &[],
                color: RGBColor(200, 200, 200),
                radius: 2,
            },
            Layer {
                positions: surrogate.0,
                edges: surrogate.1,
                pinned: surrogate.2,
                color: blue,
                radius: 2,
            },
        ],
    )
}

fn escape(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
        .replace('"', "&quot;")
}

fn data_uri(path: &Path) -> Result<String> {
    let bytes = std::fs::read(path).with_context(|| format!("cannot read {}", path.display()))?;
    let mime = match path.extension().and_then(|e| e.to_str()) {
        Some("gif") => "image/gif",
        _ => "image/png",
    };
    Ok(format!(
        "data:{mime};base64,{}",
        base64::engine::general_purpose::STANDARD.encode(bytes)
    ))
}

/// The learned values of the springs that share one true value.
struct Level {
    truth: f64,
    count: usize,
    mean: f64,
    std: f64,
    min: f64,
    max: f64,
}

/// Learned values grouped by true level, in increasing order of the true value.
fn per_level(truth: &[f64], learned: &[f64]) -> Vec<Level> {
    let mut by: BTreeMap<i64, (f64, Vec<f64>)> = BTreeMap::new();
    for (t, l) in truth.iter().zip(learned) {
        let key = (t * 1e6).round() as i64;
        by.entry(key).or_insert((*t, Vec::new())).1.push(*l);
    }
    by.into_values()
        .map(|(t, v)| {
            let n = v.len() as f64;
            let mean = v.iter().sum::<f64>() / n;
            let std = (v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / n).sqrt();
            let min = v.iter().copied().fold(f64::INFINITY, f64::min);
            let max = v.iter().copied().fold(f64::NEG_INFINITY, f64::max);
            Level {
                truth: t,
                count: v.len(),
                mean,
                std,
                min,
                max,
            }
        })
        .collect()
}

fn html_page(inputs: &Inputs, figures: &[Figure], notes: &[String]) -> Result<String> {
    let mut h = String::new();
    let name = escape(&inputs.name);
    writeln!(
        h,
        "<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n\
         <title>springtime report: {name}</title>\n<style>\n\
         body {{ font-family: sans-serif; max-width: 1700px; margin: 1.5em auto; padding: 0 1em; color: #222; }}\n\
         table {{ border-collapse: collapse; margin: 0.5em 0 1em; }}\n\
         td, th {{ border: 1px solid #ccc; padding: 0.25em 0.6em; text-align: left; }}\n\
         th {{ background: #f3f3f3; }}\n\
         figure {{ margin: 1em 0 2em; }}\n\
         img {{ max-width: 100%; border: 1px solid #ddd; }}\n\
         figcaption {{ max-width: 70em; margin-top: 0.4em; line-height: 1.4; }}\n\
         pre {{ background: #f6f6f6; padding: 0.8em; overflow-x: auto; }}\n\
         </style>\n</head>\n<body>\n<h1>springtime run <code>{name}</code></h1>"
    )?;
    h.push_str("<table>\n");
    for (k, v) in &summary_rows(inputs) {
        writeln!(h, "<tr><th>{}</th><td>{}</td></tr>", escape(k), escape(v))?;
    }
    h.push_str("</table>\n");
    if let Some((tk, tb)) = &inputs.truth {
        for (sym, unit, t, l) in [("k", "N/m", tk, &inputs.k), ("b", "N·s/m", tb, &inputs.b)] {
            level_table(&mut h, sym, unit, &per_level(t, l))?;
        }
    }
    if !notes.is_empty() {
        h.push_str("<h2>Left out</h2>\n<ul>\n");
        for n in notes {
            writeln!(h, "<li>{}</li>", escape(n))?;
        }
        h.push_str("</ul>\n");
    }
    for f in figures {
        let file = f
            .path
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        writeln!(
            h,
            "<h2>{}</h2>\n<figure>\n<img src=\"{}\" alt=\"{}\">\n<figcaption><code>{}</code>: {}</figcaption>\n</figure>",
            escape(&f.heading),
            data_uri(&f.path)?,
            escape(&f.heading),
            escape(&file),
            escape(&f.caption)
        )?;
    }
    let config = inputs.config.to_toml();
    writeln!(
        h,
        "<h2>Configuration</h2>\n<pre>{}</pre>\n</body>\n</html>",
        escape(&config)
    )?;
    Ok(h)
}

/// The report's summary table: status, training, surrogate, the learned values and (where
/// known) their error and the motion RMSE.
fn summary_rows(inputs: &Inputs) -> Vec<(String, String)> {
    let s = &inputs.state;
    let topo = &inputs.topology;
    let count = |f: SpringFamily| topo.family.iter().filter(|x| **x == f).count();
    let mut rows: Vec<(String, String)> = vec![
        ("status".into(), "finished".into()),
        (
            "training".into(),
            format!(
                "{} iterations in {:.1} s on {}, peak memory {:.0} MiB",
                s.iteration, s.wall_seconds, s.backend, s.peak_rss_mib
            ),
        ),
        (
            "surrogate".into(),
            format!(
                "{} of {:.4} kg on a {} × {} m sheet; {} springs ({} structural, {} shear, {} bending)",
                topo.describe(),
                inputs.mass,
                plot::tick(topo.width),
                plot::tick(topo.height),
                topo.num_springs(),
                count(SpringFamily::Structural),
                count(SpringFamily::Shear),
                count(SpringFamily::Bending)
            ),
        ),
        ("learned k (N/m)".into(), stats(&inputs.k)),
        ("learned b (N·s/m)".into(), stats(&inputs.b)),
    ];
    if let Some((tk, tb)) = &inputs.truth {
        rows.push((
            "RMSE of k, b (Eq. 13)".into(),
            format!(
                "{:.4} N/m, {:.4} N·s/m",
                train::rmse(&inputs.k, tk),
                train::rmse(&inputs.b, tb)
            ),
        ));
    }
    if let Some(e) = &inputs.eval {
        let m = &e.motion_rmse;
        rows.push((
            "motion RMSE (Eq. 14)".into(),
            format!(
                "{:.4e} ± {:.4e} m over {} test rollouts; first {} s: {:.4e} ± {:.4e} m; first {} s: {:.4e} ± {:.4e} m",
                m.mean,
                m.std,
                m.rollouts,
                inputs.config.eval.short_seconds,
                m.short.mean,
                m.short.std,
                inputs.config.eval.long_seconds,
                m.long.mean,
                m.long.std
            ),
        ));
    }
    rows
}

/// The learned `sym` per true level as an HTML table (none for more than 12 levels).
fn level_table(h: &mut String, sym: &str, unit: &str, levels: &[Level]) -> std::fmt::Result {
    if levels.len() > 12 {
        return Ok(());
    }
    writeln!(
        h,
        "<table>\n<tr><th>true {sym} ({unit})</th><th>springs</th><th>learned mean</th>\
         <th>std</th><th>min</th><th>max</th></tr>"
    )?;
    for l in levels {
        writeln!(
            h,
            "<tr><td>{}</td><td>{}</td><td>{:.3}</td><td>{:.3}</td><td>{:.3}</td><td>{:.3}</td></tr>",
            plot::tick(l.truth),
            l.count,
            l.mean,
            l.std,
            l.min,
            l.max
        )?;
    }
    h.push_str("</table>\n");
    Ok(())
}

fn stats(v: &[f64]) -> String {
    let n = v.len().max(1) as f64;
    let mean = v.iter().sum::<f64>() / n;
    let std = (v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / n).sqrt();
    let min = v.iter().copied().fold(f64::INFINITY, f64::min);
    let max = v.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    format!("mean {mean:.3}, std {std:.3}, range {min:.3} to {max:.3}")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn animation_frames_keep_the_ends_and_never_exceed_the_count() {
        assert_eq!(animation_frames(0, 80), vec![0]);
        assert_eq!(animation_frames(1, 80), vec![0, 1]);
        assert_eq!(animation_frames(3, 80), vec![0, 1, 2, 3]);
        let f = animation_frames(2000, 80);
        assert_eq!(f.len(), 80);
        assert_eq!((f[0], f[79]), (0, 2000));
        assert!(f.windows(2).all(|w| w[0] < w[1]));
    }

    #[test]
    fn per_level_groups_by_true_value() {
        let levels = per_level(&[10.0, 10.0, 50.0], &[9.0, 11.0, 50.0]);
        assert_eq!(levels.len(), 2);
        assert_eq!((levels[0].truth, levels[0].count), (10.0, 2));
        assert!((levels[0].mean - 10.0).abs() < 1e-12 && (levels[0].std - 1.0).abs() < 1e-12);
        assert_eq!((levels[0].min, levels[0].max), (9.0, 11.0));
    }
}
