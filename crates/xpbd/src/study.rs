//! `springtime xpbd descriptors <config> --out D`: the descriptor study of paper 001 §4.1.
//!
//! - **Fit with each descriptor** (Fig. 5): the config's estimate repeated with each of the
//!   four descriptors of Eq. 9 (each written as `D/<descriptor>/estimate.json`), and each fit
//!   re-simulated from its targets' shapes: the largest vertex error per descriptor.
//! - **Discrimination** (Fig. 7): can a descriptor tell two materials apart better than two
//!   equilibria of one material? Table 1's cotton, denim and silk are solved in each of the
//!   config's scenarios from a perturbed start and from a flat one (two wrinkle branches). Per
//!   descriptor, the within-material difference `Δ_m = ‖s_m(p₁) − s_m(p₂)‖` and, for every other
//!   material `m₂` and starts `i, j`, `‖s_m(p_i) − s_m₂(p_j)‖ − Δ_m`: 3 × 2 × 4 = 24 values per
//!   scenario, which should be positive.
//!
//! `springtime xpbd invariance <config> --out D` (the wrinkle-seed invariance): the config's
//! estimate with targets from `--seeds` differently perturbed starts (each a wrinkle branch)
//! and every fit's equilibria on a branch of their own (`--start flat`, the default) or started
//! at each target's shape (`--start target`, the paper's §3.4.1, which tests the descriptor only
//! where the targets' wrinkles cannot be reproduced exactly, e.g. the FEM's on a finer grid),
//! with the FFT and the position descriptors: the coefficient of variation of each fitted
//! parameter over the seeds (`D/invariance.json`, each fit in `D/<descriptor>_seed<k>/`).

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use serde::Serialize;

use super::cloth::XpbdCloth;
use super::descriptor::Descriptor;
use super::equilibrium::polish;
use super::estimate::{self, EstimateOptions, FitStart, ScenarioFit, TABLE_1, XpbdConfig};
use super::material::Gamma;
use super::material::NAMES;
use super::scenario::Setup;
use springtime_core::cloth::triangles::V3;
use springtime_core::progress::Progress;

/// What `descriptors` takes from the command line.
#[derive(Debug, Clone)]
pub struct StudyOptions {
    /// Output directory.
    pub out: PathBuf,
    /// Overwrite an earlier study there.
    pub force: bool,
    /// Out-of-plane amplitude of the perturbed start of the discrimination, m.
    pub noise: f64,
}

/// `descriptors.json`.
#[derive(Debug, Clone, Serialize)]
pub struct StudyReport {
    /// Job name.
    pub name: String,
    /// The fit with each descriptor.
    pub fits: Vec<DescriptorFit>,
    /// The discrimination per scenario.
    pub discrimination: Vec<Discrimination>,
    /// Per descriptor, positive relative differences over every scenario, and the cases.
    pub positive: BTreeMap<String, [usize; 2]>,
    /// Out-of-plane amplitude of the perturbed starts, m.
    pub noise: f64,
    /// Wall time, s.
    pub wall_seconds: f64,
}

/// One descriptor's fit (its `estimate.json` in `D/<descriptor>/`).
#[derive(Debug, Clone, Serialize)]
pub struct DescriptorFit {
    /// The descriptor.
    pub descriptor: Descriptor,
    /// `|fitted − true| / true` per parameter, and `iterations`.
    pub relative_error: BTreeMap<String, f64>,
    /// The largest vertex error of the fit re-simulated from the targets, over every scenario, m.
    pub max_vertex_error: f64,
    /// Per scenario.
    pub scenarios: Vec<ScenarioFit>,
}

/// The discrimination in one scenario.
#[derive(Debug, Clone, Serialize)]
pub struct Discrimination {
    /// Scenario name.
    pub scenario: String,
    /// The materials, in the order of the indices below.
    pub materials: Vec<String>,
    /// Per material, the largest vertex distance between its two equilibria, m (how different
    /// the two wrinkle branches are).
    pub branch_distance: Vec<f64>,
    /// Per descriptor.
    pub descriptors: Vec<DescriptorDiscrimination>,
}

/// One descriptor's differences in one scenario.
#[derive(Debug, Clone, Serialize)]
pub struct DescriptorDiscrimination {
    /// The descriptor.
    pub descriptor: Descriptor,
    /// `Δ_m` per material.
    pub within: Vec<f64>,
    /// Every `(m, m₂, i, j)` with its relative difference.
    pub relative: Vec<RelativeDifference>,
    /// How many relative differences are positive.
    pub positive: usize,
}

/// `‖s_m(p_i) − s_m₂(p_j)‖ − Δ_m`.
#[derive(Debug, Clone, Serialize)]
pub struct RelativeDifference {
    /// Material index.
    pub m: usize,
    /// The other material's index.
    pub m2: usize,
    /// Start of `m` (0 perturbed, 1 flat).
    pub i: usize,
    /// Start of `m₂`.
    pub j: usize,
    /// The value.
    pub value: f64,
}

fn distance(a: &[f64], b: &[f64]) -> f64 {
    a.iter()
        .zip(b)
        .map(|(p, q)| (p - q).powi(2))
        .sum::<f64>()
        .sqrt()
}

/// The discrimination of the four descriptors in every scenario of `cfg`.
fn discriminate(
    cfg: &XpbdConfig,
    cloth: &XpbdCloth,
    noise: f64,
    progress: &Progress,
) -> Result<Vec<Discrimination>> {
    let sw = cfg.swatch;
    let gammas: Vec<Gamma> = TABLE_1.iter().map(|(_, e)| e.gamma()).collect();
    let solve = estimate::resolved_solve(cfg, cloth, &gammas);
    let bar = progress.bar(
        (cfg.scenarios.len() * gammas.len() * 2) as u64,
        "equilibria",
    );
    let mut out = Vec::new();
    for (k, sc) in cfg.scenarios.iter().enumerate() {
        let seed = cfg.fit.seed + k as u64;
        let starts = [noise, 0.0].map(|a| sc.setup(cloth, sw.n, sw.size, sw.gravity, a, seed));
        // shapes[m][i]: material m from start i.
        let mut shapes: Vec<[Vec<V3>; 2]> = Vec::new();
        for g in &gammas {
            let solve_from = |setup: &Setup| -> Result<Vec<V3>> {
                let mut x = cloth.solve(g, &setup.load, &setup.start, &solve)?.x;
                polish(cloth, g, &setup.load, &mut x, 50, 1e-11)?;
                bar.inc(1);
                Ok(x)
            };
            shapes.push([solve_from(&starts[0])?, solve_from(&starts[1])?]);
        }
        let branch_distance = shapes
            .iter()
            .map(|[a, b]| {
                a.iter()
                    .zip(b)
                    .map(|(p, q)| distance(p, q))
                    .fold(0.0, f64::max)
            })
            .collect();
        let mut descriptors = Vec::new();
        for d in Descriptor::ALL {
            let s: Vec<[Vec<f64>; 2]> = shapes
                .iter()
                .zip(&gammas)
                .map(|(pair, g)| pair.each_ref().map(|x| d.of(cloth, sw.n, sw.n, g, x)))
                .collect();
            let within: Vec<f64> = s.iter().map(|[a, b]| distance(a, b)).collect();
            let mut relative = Vec::new();
            for m in 0..s.len() {
                for m2 in (0..s.len()).filter(|&m2| m2 != m) {
                    for i in 0..2 {
                        for j in 0..2 {
                            relative.push(RelativeDifference {
                                m,
                                m2,
                                i,
                                j,
                                value: distance(&s[m][i], &s[m2][j]) - within[m],
                            });
                        }
                    }
                }
            }
            descriptors.push(DescriptorDiscrimination {
                descriptor: d,
                within,
                positive: relative.iter().filter(|r| r.value > 0.0).count(),
                relative,
            });
        }
        out.push(Discrimination {
            scenario: sc.name(),
            materials: TABLE_1.iter().map(|(n, _)| n.to_string()).collect(),
            branch_distance,
            descriptors,
        });
    }
    bar.finish();
    Ok(out)
}

/// Runs the study and writes `D/descriptors.json` (and each fit's `D/<descriptor>/`).
pub fn study(cfg: &XpbdConfig, options: &StudyOptions, progress: &Progress) -> Result<StudyReport> {
    let start = Instant::now();
    let json = options.out.join("descriptors.json");
    springtime_core::io::refuse_overwrite(&json, options.force)?;
    if !(options.noise > 0.0 && options.noise.is_finite()) {
        bail!(
            "--noise must be a positive length in m, is {}",
            options.noise
        );
    }
    let sw = cfg.swatch;
    let cloth = XpbdCloth::grid(sw.n, sw.n, sw.size, sw.size, sw.density)?;
    progress.note("discrimination: Table 1's materials from perturbed and flat starts");
    let discrimination = discriminate(cfg, &cloth, options.noise, progress)?;
    let mut fits = Vec::new();
    for d in Descriptor::ALL {
        progress.note(&format!("fit with the {} descriptor", d.name()));
        let mut c = cfg.clone();
        c.fit.descriptor = d;
        let r = estimate::estimate(
            &c,
            &EstimateOptions {
                out: options.out.join(d.name()),
                force: options.force,
            },
            progress,
        )?;
        fits.push(DescriptorFit {
            descriptor: d,
            relative_error: r.relative_error,
            max_vertex_error: r
                .scenarios
                .iter()
                .map(|s| s.max_vertex_error)
                .fold(0.0, f64::max),
            scenarios: r.scenarios,
        });
    }
    let mut positive = BTreeMap::new();
    for d in Descriptor::ALL {
        let (mut p, mut n) = (0, 0);
        for s in &discrimination {
            for dd in s.descriptors.iter().filter(|dd| dd.descriptor == d) {
                p += dd.positive;
                n += dd.relative.len();
            }
        }
        positive.insert(d.name().to_string(), [p, n]);
    }
    let report = StudyReport {
        name: cfg.name.clone(),
        fits,
        discrimination,
        positive,
        noise: options.noise,
        wall_seconds: start.elapsed().as_secs_f64(),
    };
    springtime_core::io::write_json(&json, &report)?;
    Ok(report)
}

/// `invariance.json`.
#[derive(Debug, Clone, Serialize)]
pub struct InvarianceReport {
    /// Job name.
    pub name: String,
    /// Out-of-plane amplitude of the targets' perturbed starts, m.
    pub noise: f64,
    /// Where every fit's equilibria started.
    pub start: FitStart,
    /// Every fit.
    pub fits: Vec<SeedFit>,
    /// Per descriptor, per parameter: the coefficient of variation over the seeds
    /// (sample standard deviation / mean), and the mean relative error.
    pub summary: BTreeMap<String, InvarianceSummary>,
    /// Wall time, s.
    pub wall_seconds: f64,
}

/// One seed's fit with one descriptor.
#[derive(Debug, Clone, Serialize)]
pub struct SeedFit {
    /// The descriptor.
    pub descriptor: Descriptor,
    /// The targets' perturbation seed.
    pub seed: u64,
    /// The fitted γ, SI.
    pub gamma: Gamma,
    /// `|fitted − true| / true` per parameter, and `iterations`.
    pub relative_error: BTreeMap<String, f64>,
}

/// One descriptor over the seeds.
#[derive(Debug, Clone, Serialize)]
pub struct InvarianceSummary {
    /// Coefficient of variation per parameter.
    pub cv: BTreeMap<String, f64>,
    /// Mean relative error per parameter.
    pub mean_relative_error: BTreeMap<String, f64>,
    /// The largest coefficient of variation of the four membrane parameters.
    pub cv_membrane: f64,
    /// That of `b`.
    pub cv_b: f64,
}

/// Runs the invariance experiment over `seeds` seeds, every fit's equilibria started at
/// `start`, and writes `D/invariance.json`.
pub fn invariance(
    cfg: &XpbdConfig,
    options: &StudyOptions,
    seeds: u64,
    start_at: FitStart,
    progress: &Progress,
) -> Result<InvarianceReport> {
    let start = Instant::now();
    let json = options.out.join("invariance.json");
    springtime_core::io::refuse_overwrite(&json, options.force)?;
    if seeds < 2 {
        bail!("--seeds must be at least 2 for a spread, is {seeds}");
    }
    let truth = cfg
        .truth
        .context("the invariance experiment generates its targets: it needs `[truth]`")?
        .gamma()
        .to_array();
    let mut fits = Vec::new();
    let mut summary = BTreeMap::new();
    for d in [Descriptor::Fft, Descriptor::Positions] {
        let mut gammas = Vec::new();
        for seed in 0..seeds {
            progress.note(&format!("{} descriptor, wrinkle seed {seed}", d.name()));
            let mut c = cfg.clone();
            c.fit.descriptor = d;
            c.fit.seed = seed;
            c.fit.noise = options.noise;
            c.fit.start = start_at;
            c.targets.dir = None;
            let r = estimate::estimate(
                &c,
                &EstimateOptions {
                    out: options.out.join(format!("{}_seed{seed}", d.name())),
                    force: options.force,
                },
                progress,
            )?;
            gammas.push(r.gamma.to_array());
            fits.push(SeedFit {
                descriptor: d,
                seed,
                gamma: r.gamma,
                relative_error: r.relative_error,
            });
        }
        let n = gammas.len() as f64;
        let (mut cv, mut mean_err) = (BTreeMap::new(), BTreeMap::new());
        for (k, name) in NAMES.iter().enumerate() {
            let mean = gammas.iter().map(|g| g[k]).sum::<f64>() / n;
            let var = gammas.iter().map(|g| (g[k] - mean).powi(2)).sum::<f64>() / (n - 1.0);
            cv.insert(name.to_string(), var.sqrt() / mean.abs());
            let err = gammas
                .iter()
                .map(|g| ((g[k] - truth[k]) / truth[k]).abs())
                .sum::<f64>()
                / n;
            mean_err.insert(name.to_string(), err);
        }
        summary.insert(
            d.name().to_string(),
            InvarianceSummary {
                cv_membrane: NAMES[..4].iter().map(|k| cv[*k]).fold(0.0, f64::max),
                cv_b: cv["b"],
                cv,
                mean_relative_error: mean_err,
            },
        );
    }
    let report = InvarianceReport {
        name: cfg.name.clone(),
        noise: options.noise,
        start: start_at,
        fits,
        summary,
        wall_seconds: start.elapsed().as_secs_f64(),
    };
    springtime_core::io::write_json(&json, &report)?;
    Ok(report)
}
