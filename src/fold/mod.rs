//! The membrane-locking fold test (paper §4.4, Fig. 2 b–e, App. B.2), with numbers.
//!
//! A square sheet pinned at the neighbourhoods of two opposite corners settles under gravity
//! ([`scenario`]). A coarse FEM mesh whose fold runs across its triangles (`misaligned`) locks:
//! it folds less than when the fold follows its edges (`aligned`). `springtime fold` settles the
//! FEM source's mesh (the surrogate's training mesh) and a nested fine mesh (with and without
//! bending) in both cases, trains a spring surrogate on ordinary random rollouts of the coarse
//! mesh (`train::train`), settles it in both cases too, and writes `fold.json`, `fold.csv` and
//! `fold.png` with the criteria L1–L4 ([`metrics`] has the numbers).

pub mod metrics;
pub mod scenario;

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result, bail};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::config::{Config, Job};
use crate::model::ModelKind;
use crate::progress::Progress;
use crate::source::{ClothSim, FemCloth, Layout, SourceConfig, SourceKind, SpringCloth};
use crate::train::{RunDir, TrainOptions, TrainSummary};

pub use scenario::{FoldCase, SettleConfig};

/// A fold job (`springtime fold <config>`): the `[fold]` section and the surrogate's ordinary
/// training config under `[surrogate]`, whose `[surrogate.source]` (a uniform FEM sheet) is
/// also the material of every reference mesh.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FoldConfig {
    /// The fold test itself.
    #[serde(default)]
    pub fold: FoldParams,
    /// The surrogate's training job (any `springtime train` config with an FEM source).
    pub surrogate: Config,
}

/// The `[fold]` section.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct FoldParams {
    /// Vertices per side of the fine reference mesh; `fine − 1` must be a multiple of the
    /// source's `nx − 1` so that the coarse vertices are fine vertices.
    pub fine: usize,
    /// Radius of each pinned corner neighbourhood in the rest square, m (the same at every
    /// resolution).
    pub pin_radius: f64,
    /// How the equilibria are found.
    pub settle: SettleConfig,
}

impl Default for FoldParams {
    fn default() -> Self {
        Self {
            fine: 61,
            pin_radius: 0.1,
            settle: SettleConfig::default(),
        }
    }
}

impl Job for FoldConfig {
    const KIND: &'static str = "fold";
    /// The surrogate's training job needs an FEM source of one material on a grid whose
    /// vertices the fine reference holds (16 × 16 inside the default 61 × 61, as in
    /// `configs/fold.toml`): every other key has a default.
    const EXAMPLE: &'static str = "[surrogate.cloth]\nnx = 16\nny = 16\n\n\
                                   [surrogate.source]\nkind = \"fem\"\nlayout = \"uniform\"\n\
                                   nx = 16\nny = 16\n";

    /// Checks what the test needs; errors name the key.
    fn validate(&self) -> Result<()> {
        self.surrogate
            .validate()
            .map_err(|e| anyhow::anyhow!("in [surrogate]: {e}"))?;
        let Some(src) = &self.surrogate.source else {
            bail!("`surrogate.source` is missing: the fold test needs the FEM source's material");
        };
        if src.kind != SourceKind::Fem {
            bail!("`surrogate.source.kind` must be \"fem\" for the fold test");
        }
        if src.nx != src.ny || src.width != src.height {
            bail!(
                "`surrogate.source`: the fold test needs a square sheet and grid (nx = ny, width = height)"
            );
        }
        if src.layout != Layout::Uniform {
            bail!(
                "`surrogate.source.layout` must be \"uniform\": the references share one material"
            );
        }
        if self.surrogate.model.kind != ModelKind::Springs {
            bail!("`surrogate.model.kind` must be \"springs\"");
        }
        let coarse = self.coarse();
        metrics::nested_indices(coarse, self.fold.fine)
            .map_err(|e| anyhow::anyhow!("`fold.fine`: {e}"))?;
        let c = &self.surrogate.cloth;
        if c.nx != c.ny {
            bail!("`surrogate.cloth`: the fold test needs a square grid (nx = ny)");
        }
        metrics::nested_indices(c.nx, self.fold.fine)
            .map_err(|e| anyhow::anyhow!("`surrogate.cloth.nx`: {e}"))?;
        FoldCase::Aligned
            .corners(coarse, coarse, src.fem.diagonal)
            .map_err(|e| anyhow::anyhow!("`surrogate.source.fem.diagonal`: {e}"))?;
        if !(self.fold.pin_radius >= 0.0 && self.fold.pin_radius < 0.25 * src.width) {
            bail!(
                "`fold.pin_radius` must lie in [0, width/4), is {}",
                self.fold.pin_radius
            );
        }
        self.fold.settle.validate()
    }
}

impl FoldConfig {
    fn source(&self) -> &SourceConfig {
        self.surrogate.source.as_ref().expect("validated")
    }

    /// Vertices per side of the source (training) mesh.
    pub fn coarse(&self) -> usize {
        self.surrogate.source.as_ref().map_or(0, |s| s.nx)
    }
}

/// One of the systems the test settles.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum System {
    /// The FEM source's own mesh (the surrogate's training mesh).
    FemCoarse,
    /// The nested fine FEM mesh, same material.
    FemFine,
    /// The fine FEM mesh without bending (Fig. 2 e).
    FemFineNoBending,
    /// The spring surrogate trained on the coarse mesh's random rollouts.
    Surrogate,
}

impl System {
    /// Every system, in table order.
    pub const ALL: [System; 4] = [
        System::FemCoarse,
        System::FemFine,
        System::FemFineNoBending,
        System::Surrogate,
    ];

    /// A short name with the resolution, e.g. `fem16`, `fem61_no_bending`.
    pub fn label(self, coarse: usize, fine: usize) -> String {
        match self {
            System::FemCoarse => format!("fem{coarse}"),
            System::FemFine => format!("fem{fine}"),
            System::FemFineNoBending => format!("fem{fine}_no_bending"),
            System::Surrogate => "surrogate".into(),
        }
    }
}

/// The equilibrium of one system in one case.
#[derive(Debug, Clone, Serialize)]
pub struct CaseResult {
    /// `fem16`, `fem61`, `fem61_no_bending`, `surrogate`.
    pub system: String,
    /// `aligned` or `misaligned`.
    pub case: FoldCase,
    /// Vertices (particles) per side.
    pub n: usize,
    /// Opening angle of the fold from the distance between the free corners, degrees.
    pub alpha_deg: f64,
    /// Mean drop of the free vertices below the pins, m.
    pub sag_m: f64,
    /// Shape RMSE to the fine FEM mesh (with bending) in the same case on the shared points, m.
    pub rmse_fine_m: f64,
    /// Shape RMSE to the fine FEM mesh without bending in the same case, m.
    pub rmse_fine_no_bending_m: f64,
    /// Membrane energy / (membrane + bending energy) at equilibrium (FEM only).
    pub membrane_share: Option<f64>,
    /// Elastic energy at equilibrium, J (FEM only).
    pub elastic_energy_j: Option<f64>,
    /// Pinned vertices.
    pub pinned: usize,
    /// Simulated time to equilibrium, s.
    pub settle_seconds: f64,
    /// Step used, s.
    pub dt: f64,
    /// Fastest free vertex at the end, m/s.
    pub max_speed: f64,
    /// Whether the velocity tolerance was met before the cap.
    pub converged: bool,
    /// Wall time of the settling, s.
    pub wall_seconds: f64,
    /// The side-view profile across the fold (for the figure), not written to JSON.
    #[serde(skip)]
    pub profile: Vec<(f64, f64)>,
}

/// One acceptance criterion.
#[derive(Debug, Clone, Serialize)]
pub struct Criterion {
    /// The measured value.
    pub value: f64,
    /// The threshold it is compared with.
    pub threshold: f64,
    /// Whether it passes.
    pub pass: bool,
    /// What is compared.
    pub rule: String,
}

/// `fold.json`.
#[derive(Debug, Clone, Serialize)]
pub struct FoldReport {
    /// The config (with overrides).
    pub config: FoldConfig,
    /// Every system in both cases.
    pub results: Vec<CaseResult>,
    /// Locking gap Δα = α(misaligned) − α(aligned) per system, degrees.
    pub locking_gap_deg: std::collections::BTreeMap<String, f64>,
    /// L1–L4.
    pub criteria: std::collections::BTreeMap<String, Criterion>,
    /// The surrogate's training.
    pub surrogate_training: Option<TrainSummary>,
    /// Wall time of the whole command, s.
    pub wall_seconds: f64,
    /// The build.
    pub build: crate::BuildInfo,
}

/// Command-line choices of a fold job.
#[derive(Debug, Clone, Default)]
pub struct FoldOptions {
    /// Output directory.
    pub out: PathBuf,
    /// Overwrite a finished output directory (and retrain the surrogate).
    pub force: bool,
}

/// A settled system: its cloth and grid.
struct Setup {
    sim: Box<dyn ClothSim>,
    fem: Option<FemCloth>,
    n: usize,
}

fn fem_setup(cfg: &FoldConfig, n: usize, bending: Option<f64>) -> Setup {
    let src = cfg.source();
    let rest_mass = src.areal_density * src.width * src.height / (n * n) as f64;
    let mut s = src.clone();
    s.nx = n;
    s.ny = n;
    s.rayleigh = cfg.fold.settle.damping_rate * rest_mass;
    s.fem.strain_damping = cfg.fold.settle.strain_damping;
    if let Some(b) = bending {
        s.fem.bending = b;
    }
    let fem = FemCloth::from_config(&s);
    Setup {
        sim: Box::new(fem.clone()),
        fem: Some(fem),
        n,
    }
}

/// Settles `setup` in `case` and measures it (without the comparison to the fine mesh).
fn settle_case(
    cfg: &FoldConfig,
    setup: &Setup,
    case: FoldCase,
    on_time: impl FnMut(f64),
) -> Result<(CaseResult, Vec<[f64; 3]>)> {
    let src = cfg.source();
    let (side, n) = (src.width, setup.n);
    let rest = setup.sim.rest_uv();
    let (pins, free) = case.corners(n, n, src.fem.diagonal)?;
    let pinned = scenario::corner_pins(rest, n, &pins, cfg.fold.pin_radius);
    let dt = scenario::settle_dt(setup.sim.as_ref(), &cfg.fold.settle);
    let start = Instant::now();
    let eq = scenario::settle(
        setup.sim.as_ref(),
        crate::cloth::flat(rest, side, side),
        &pinned,
        dt,
        &cfg.fold.settle,
        on_time,
    )?;
    let free_idx = free.map(|(r, c)| r * n + c);
    let axis = {
        let [(r0, c0), (r1, c1)] = pins;
        [c1 as f64 - c0 as f64, r1 as f64 - r0 as f64]
    };
    let (share, energy) = match &setup.fem {
        Some(fem) => {
            let m = fem.membrane_energy(&eq.x);
            let b = fem.bending_energy(&eq.x);
            (Some(m / (m + b).max(f64::MIN_POSITIVE)), Some(m + b))
        }
        None => (None, None),
    };
    let result = CaseResult {
        system: String::new(),
        case,
        n,
        alpha_deg: metrics::opening_angle(&eq.x, free_idx, side * 2f64.sqrt()),
        sag_m: metrics::sag(&eq.x, &pinned),
        rmse_fine_m: f64::NAN,
        rmse_fine_no_bending_m: f64::NAN,
        membrane_share: share,
        elastic_energy_j: energy,
        pinned: pinned.iter().filter(|p| **p).count(),
        settle_seconds: eq.seconds,
        dt: eq.dt,
        max_speed: eq.max_speed,
        converged: eq.converged,
        wall_seconds: start.elapsed().as_secs_f64(),
        profile: metrics::profile(&eq.x, n, free, axis),
    };
    Ok((result, eq.x))
}

/// The spring surrogate of a finished run as a host cloth (the same Eq. 4 forces as the
/// surrogate's simulator), damped for settling.
fn surrogate_setup(cfg: &FoldConfig, run_dir: &Path) -> Result<Setup> {
    let run = crate::run::Run::open(run_dir, &[], Some(crate::backend::Backend::Flex))?;
    let model = run.springs()?;
    let mass = run.particle_mass();
    let Some([n, _]) = run.topology.grid else {
        bail!(
            "{}: the fold test needs a grid surrogate (this one lives on its data's mesh)",
            run_dir.display()
        );
    };
    if !run.topology.curvature.is_empty() {
        bail!(
            "{}: the fold test's host simulator has springs only, and this surrogate has \
             curvature elements (cloth.curvature = true): fold a run trained without them",
            run_dir.display()
        );
    }
    let cloth = SpringCloth {
        k: model.k_values(),
        b: model.b_values(),
        mass,
        rayleigh: cfg.fold.settle.damping_rate * mass,
        gravity: run.config.sim.gravity.or(crate::sim::GRAVITY),
        viscosity: run.config.sim.viscosity,
        shear_compression: run.config.sim.shear_compression,
        topology: run.topology.clone(),
    };
    Ok(Setup {
        sim: Box::new(cloth),
        fem: None,
        n,
    })
}

/// A settled system: which, its numbers and its positions.
type Settled = (System, CaseResult, Vec<[f64; 3]>);

/// Runs the whole fold test into `options.out` (see the module docs).
pub fn run(cfg: &FoldConfig, options: &FoldOptions, progress: &Progress) -> Result<FoldReport> {
    let start = Instant::now();
    let out = &options.out;
    let json = out.join("fold.json");
    if json.exists() && !options.force {
        bail!(
            "{} holds a finished fold test; pass --force to run it again or --out to write elsewhere",
            out.display()
        );
    }
    // The data and the surrogate of an interrupted job are reused when they come from the
    // same config; --force starts both over.
    let data_dir = out.join("data");
    let run_dir = out.join("surrogate");
    let mut train_cfg = cfg.surrogate.clone();
    train_cfg.data.dir = data_dir.clone();
    if options.force {
        for dir in [&data_dir, &run_dir] {
            if dir.exists() {
                std::fs::remove_dir_all(dir)
                    .with_context(|| format!("cannot clear {}", dir.display()))?;
            }
        }
    } else {
        check_reusable(&train_cfg, &data_dir, &run_dir)?;
    }
    std::fs::create_dir_all(out).with_context(|| format!("cannot create {}", out.display()))?;
    let (coarse, fine) = (cfg.coarse(), cfg.fold.fine);
    let bending = cfg.source().fem.bending;

    // 1. The FEM references, two at a time.
    progress.note(&format!(
        "fold: settling FEM {coarse}×{coarse} and {fine}×{fine} (k_b = {bending} and 0), aligned and misaligned"
    ));
    let mut settled = settle_references(cfg, coarse, fine, progress)?;

    // 2. The surrogate: trained on random rollouts of the coarse mesh only.
    let summary = train_surrogate(&train_cfg, &run_dir, options.force, coarse, progress)?;
    settled.extend(settle_surrogate(cfg, &run_dir, coarse, fine, progress)?);

    // 3. Metrics against the fine meshes on the shared points.
    let results = shape_errors(&settled, fine)?;
    let get = |s: System, c: FoldCase| {
        let label = s.label(coarse, fine);
        results
            .iter()
            .find(|r| r.system == label && r.case == c)
            .expect("result")
    };
    let gap =
        |s: System| get(s, FoldCase::Misaligned).alpha_deg - get(s, FoldCase::Aligned).alpha_deg;
    let locking_gap_deg = System::ALL
        .iter()
        .map(|&s| (s.label(coarse, fine), gap(s)))
        .collect();
    let criteria = criteria(
        gap(System::FemCoarse),
        gap(System::FemFine),
        gap(System::Surrogate),
        get(System::Surrogate, FoldCase::Misaligned).rmse_fine_m,
        get(System::FemCoarse, FoldCase::Misaligned).rmse_fine_m,
        get(System::Surrogate, FoldCase::Aligned).rmse_fine_m,
        get(System::Surrogate, FoldCase::Aligned).rmse_fine_no_bending_m,
    );

    // 4. Outputs.
    write_csv(&out.join("fold.csv"), &results)?;
    figure(&out.join("fold.png"), &results, coarse, fine)?;
    let report = FoldReport {
        config: cfg.clone(),
        results,
        locking_gap_deg,
        criteria,
        surrogate_training: summary,
        wall_seconds: start.elapsed().as_secs_f64(),
        build: crate::BuildInfo::current(),
    };
    crate::io::write_json(&json, &report)?;
    Ok(report)
}

/// Settles the FEM references (coarse; fine; fine without bending) in both cases, as many at a
/// time as there are cores, the fine meshes first (they take longest).
fn settle_references(
    cfg: &FoldConfig,
    coarse: usize,
    fine: usize,
    progress: &Progress,
) -> Result<Vec<Settled>> {
    let systems = [
        (System::FemCoarse, coarse, None),
        (System::FemFine, fine, None),
        (System::FemFineNoBending, fine, Some(0.0)),
    ];
    // The fine meshes first (they take longest); one task per settling, as many at a time as
    // there are cores.
    let tasks: Vec<(System, usize, Option<f64>, FoldCase)> = systems
        .iter()
        .rev()
        .flat_map(|&(system, n, kb)| FoldCase::ALL.map(|case| (system, n, kb, case)))
        .collect();
    tasks
        .into_par_iter()
        .with_max_len(1)
        .map(|(system, n, kb, case)| -> Result<Settled> {
            let setup = fem_setup(cfg, n, kb);
            let label = system.label(coarse, fine);
            let bar_note = |t: f64| {
                if n > coarse {
                    progress.note(&format!("  {label} {}: t = {t:.2} s", case.name()));
                }
            };
            let (mut r, x) = settle_case(cfg, &setup, case, bar_note)?;
            r.system = label;
            progress.note(&format!(
                "  {} {}: α = {:.1}°, sag {:.3} m, membrane share {:.2}, settled in {:.2} s \
                 ({} steps of {:.2e} s, {:.0} s wall{})",
                r.system,
                case.name(),
                r.alpha_deg,
                r.sag_m,
                r.membrane_share.unwrap_or(f64::NAN),
                r.settle_seconds,
                (r.settle_seconds / r.dt).round(),
                r.dt,
                r.wall_seconds,
                if r.converged { "" } else { ", NOT converged" }
            ));
            Ok((system, r, x))
        })
        .collect::<Result<Vec<_>>>()
}

/// Trains the surrogate on random rollouts of the coarse mesh, or reuses a finished one
/// (`None`).
fn train_surrogate(
    train_cfg: &Config,
    run_dir: &Path,
    force: bool,
    coarse: usize,
    progress: &Progress,
) -> Result<Option<crate::train::TrainSummary>> {
    let run = RunDir::new(run_dir);
    let finished = matches!(
        run.state().ok().flatten().map(|s| s.status),
        Some(crate::train::Status::Finished)
    );
    if finished && !force {
        progress.note(&format!(
            "fold: reusing the trained surrogate in {}",
            run_dir.display()
        ));
        return Ok(None);
    }
    progress.note(&format!(
        "fold: training the surrogate on random rollouts of FEM {coarse}×{coarse} into {}",
        run_dir.display()
    ));
    Ok(Some(crate::train::train(
        train_cfg,
        &TrainOptions {
            out: Some(run_dir.to_path_buf()),
            resume: false,
            force: true,
        },
        progress,
    )?))
}

/// Settles the trained surrogate in both cases.
fn settle_surrogate(
    cfg: &FoldConfig,
    run_dir: &Path,
    coarse: usize,
    fine: usize,
    progress: &Progress,
) -> Result<Vec<Settled>> {
    let setup = surrogate_setup(cfg, run_dir)?;
    let mut settled = Vec::new();
    for case in FoldCase::ALL {
        let (mut r, x) = settle_case(cfg, &setup, case, |_| {})?;
        r.system = System::Surrogate.label(coarse, fine);
        progress.note(&format!(
            "  surrogate {}: α = {:.1}°, sag {:.3} m, settled in {:.2} s{}",
            case.name(),
            r.alpha_deg,
            r.sag_m,
            r.settle_seconds,
            if r.converged { "" } else { " (NOT converged)" }
        ));
        settled.push((System::Surrogate, r, x));
    }
    Ok(settled)
}

/// Every system's results with its shape RMSE to the fine meshes on the shared points.
fn shape_errors(settled: &[Settled], fine: usize) -> Result<Vec<CaseResult>> {
    let find = |s: System, c: FoldCase| {
        settled
            .iter()
            .position(|(sys, r, _)| *sys == s && r.case == c)
            .expect("settled")
    };
    let mut results = Vec::new();
    for system in System::ALL {
        for case in FoldCase::ALL {
            let i = find(system, case);
            let (_, r, x) = &settled[i];
            let at = metrics::nested_indices(r.n, fine)?;
            let fine_x = &settled[find(System::FemFine, case)].2;
            let flat_x = &settled[find(System::FemFineNoBending, case)].2;
            let mut r = r.clone();
            r.rmse_fine_m = metrics::shape_rmse(x, fine_x, &at);
            r.rmse_fine_no_bending_m = metrics::shape_rmse(x, flat_x, &at);
            results.push(r);
        }
    }
    Ok(results)
}

/// Fails when `data_dir` or `run_dir` (left by an interrupted job) came from another config
/// than `train_cfg`, so that nothing stale is reused without `--force`.
fn check_reusable(train_cfg: &Config, data_dir: &Path, run_dir: &Path) -> Result<()> {
    let index = crate::data::Index::path(data_dir);
    if index.exists() {
        let text = std::fs::read_to_string(&index)
            .with_context(|| format!("cannot read {}", index.display()))?;
        let index: crate::data::Index = serde_json::from_str(&text)
            .with_context(|| format!("cannot parse {}", index.display()))?;
        if index.generator.get("source") != Some(&serde_json::to_value(&train_cfg.source)?) {
            bail!(
                "{} was generated from another [surrogate.source]; pass --force to start over",
                data_dir.display()
            );
        }
    }
    let requested = RunDir::new(run_dir).requested_config();
    if requested.exists() && Config::load(&requested, &[])? != *train_cfg {
        bail!(
            "{} was trained from another [surrogate] config; pass --force to start over",
            run_dir.display()
        );
    }
    Ok(())
}

/// L1–L4 of the issue from the measured figures.
#[allow(clippy::too_many_arguments)]
pub fn criteria(
    gap_coarse: f64,
    gap_fine: f64,
    gap_surrogate: f64,
    rmse_surrogate_mis: f64,
    rmse_coarse_mis: f64,
    rmse_surrogate_al: f64,
    rmse_surrogate_al_no_bending: f64,
) -> std::collections::BTreeMap<String, Criterion> {
    let l1 = 5f64.max(3.0 * gap_fine.abs());
    [
        (
            "L1",
            Criterion {
                value: gap_coarse,
                threshold: l1,
                pass: gap_coarse >= l1,
                rule: "locking exists: Δα(FEM coarse) ≥ max(5°, 3·|Δα(FEM fine)|)".into(),
            },
        ),
        (
            "L2",
            Criterion {
                value: rmse_surrogate_mis,
                threshold: rmse_coarse_mis,
                pass: rmse_surrogate_mis < rmse_coarse_mis,
                rule: "misaligned: RMSE(surrogate, FEM fine) < RMSE(FEM coarse, FEM fine), m"
                    .into(),
            },
        ),
        (
            "L3",
            Criterion {
                value: gap_surrogate.abs(),
                threshold: gap_coarse / 3.0,
                pass: gap_surrogate.abs() <= gap_coarse / 3.0,
                rule: "no locking: |Δα(surrogate)| ≤ Δα(FEM coarse)/3, degrees".into(),
            },
        ),
        (
            "L4",
            Criterion {
                value: rmse_surrogate_al,
                threshold: rmse_surrogate_al_no_bending,
                pass: rmse_surrogate_al < rmse_surrogate_al_no_bending,
                rule: "aligned: RMSE(surrogate, FEM fine) < RMSE(surrogate, FEM fine without \
                       bending), m"
                    .into(),
            },
        ),
    ]
    .into_iter()
    .map(|(k, v)| (k.to_string(), v))
    .collect()
}

fn write_csv(path: &Path, results: &[CaseResult]) -> Result<()> {
    use std::fmt::Write;
    let mut s = String::from(
        "system,case,n,alpha_deg,sag_m,rmse_fine_m,rmse_fine_no_bending_m,membrane_share,\
         settle_seconds,dt,converged\n",
    );
    for r in results {
        writeln!(
            s,
            "{},{},{},{:.4},{:.6},{:.6},{:.6},{},{:.4},{:.3e},{}",
            r.system,
            r.case.name(),
            r.n,
            r.alpha_deg,
            r.sag_m,
            r.rmse_fine_m,
            r.rmse_fine_no_bending_m,
            r.membrane_share
                .map_or(String::new(), |m| format!("{m:.4}")),
            r.settle_seconds,
            r.dt,
            r.converged
        )?;
    }
    crate::io::write_text(path, &s)
}

/// Fig. 2 (b–e) as side views: each case's profile across the fold (the free-corner
/// diagonal) for every system.
fn figure(path: &Path, results: &[CaseResult], coarse: usize, fine: usize) -> Result<()> {
    use springtime_plot::{self as plot, Series};
    let (w, h) = (1400, 620);
    plot::png_figure(path, w, h, |root| {
        let panels = root.split_evenly((1, 2));
        for (area, case) in panels.iter().zip(FoldCase::ALL) {
            let series: Vec<Series> = System::ALL
                .iter()
                .map(|&s| {
                    let label = s.label(coarse, fine);
                    let r = results
                        .iter()
                        .find(|r| r.system == label && r.case == case)
                        .expect("result");
                    Series::new(
                        format!("{label}: α = {:.1}°", r.alpha_deg),
                        r.profile.clone(),
                    )
                })
                .collect();
            plot::draw_curves(
                area,
                &format!("{} fold: side view along the pinned diagonal", case.name()),
                "across the fold (m)",
                "height (m)",
                &series,
                false,
                &[],
            )?;
        }
        Ok(())
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_shipped_fold_config_parses_and_errors_name_the_key() {
        let path = Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/configs/fold.toml"));
        let cfg = FoldConfig::load(path, &[]).unwrap();
        assert_eq!(cfg.fold.fine, 61);
        assert_eq!(cfg.coarse(), 16);
        let cfg = FoldConfig::load(path, &["fold.settle.tolerance=0.01".into()]).unwrap();
        assert_eq!(cfg.fold.settle.tolerance, 0.01);
        for (set, key) in [
            ("fold.pin_radus=0.1", "pin_radus"),
            ("fold.settle.tolerance=-1", "fold.settle.tolerance"),
            ("fold.fine=60", "fold.fine"),
            (
                "surrogate.source.layout=\"stripes\"",
                "surrogate.source.layout",
            ),
            ("surrogate.source.fem.diagonal=\"alternating\"", "diagonal"),
            ("surrogate.train.stiffness.lrr=1", "lrr"),
        ] {
            let err = format!("{:#}", FoldConfig::load(path, &[set.into()]).unwrap_err());
            assert!(err.contains(key), "{set}: {err}");
        }
    }

    #[test]
    fn criteria_compare_the_right_figures() {
        // Locking in the coarse mesh (20° gap, fine 2°), a surrogate that does not lock (1°),
        // is closer to the fine mesh (0.05 < 0.08) and to the one with bending (0.05 < 0.2).
        let c = criteria(20.0, 2.0, 1.0, 0.05, 0.08, 0.05, 0.2);
        assert!(c.values().all(|c| c.pass), "{c:?}");
        assert_eq!(c["L1"].threshold, 6.0);
        // A fine mesh that locks nearly as much fails L1; a locking surrogate fails L3.
        let c = criteria(20.0, 8.0, 10.0, 0.1, 0.08, 0.3, 0.2);
        assert_eq!(c["L1"].threshold, 24.0);
        assert!(c.values().all(|c| !c.pass), "{c:?}");
    }
}
