//! `springtime xpbd estimate <config> --out D`: the sim-to-sim experiment of paper 001 §4.2.
//! Targets are equilibria of the XPBD cloth with the config's true γ in its scenarios; γ is
//! then fitted from the config's initial guess by Levenberg–Marquardt on the shape descriptor
//! of every target plus the magnitudes of the clamps' reactions, with the paper's Poisson
//! penalty (Eq. 8), every equilibrium solved from its target's shape as the paper does (or from
//! a branch of its own, `fit.start = "flat"`), and
//! the Jacobian from the implicit-function derivatives of the equilibria. Writes
//! `D/estimate.json`.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result, bail};
use rand::{Rng, SeedableRng, rngs::StdRng};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use std::sync::Arc;

use super::adam::{self, AdamSettings, AdamTarget};
use super::cloth::{Solve, XpbdCloth};
use super::descriptor::Descriptor;
use super::equilibrium::{Sensitivity, polish, sensitivity};
use super::lm::{self, LeastSquares, Lm};
use super::material::{Gamma, NAMES};
use super::op::StaticProblem;
use super::registration::{RegistrationError, Scan, register};
use super::scenario::{Scenario, Setup, SetupGrid};
use springtime_core::cloth::triangles::{V3, dot};
use springtime_core::cloth::{Diagonal, grid_triangles};
use springtime_core::data::npz::{Array, Npz};
use springtime_core::progress::{Bar, Progress};
use springtime_core::settings::Job;

/// Engineering constants in the paper's CGS units (its Tables 1–3): moduli in dyn/cm, bending
/// in erg.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Engineering {
    /// Warp Young's modulus, dyn/cm.
    pub e_u: f64,
    /// Weft Young's modulus, dyn/cm.
    pub e_v: f64,
    /// Shear modulus, dyn/cm.
    pub mu: f64,
    /// Poisson ratio ν_uv.
    pub nu: f64,
    /// Bending stiffness, erg.
    pub b: f64,
}

impl Engineering {
    /// γ in SI.
    pub fn gamma(&self) -> Gamma {
        let g = Gamma::from_engineering(self.e_u, self.e_v, self.mu, self.nu, self.b);
        Gamma::from_cgs(g.to_array())
    }
}

/// The paper's three synthetic materials (its Table 1, top), CGS.
pub const TABLE_1: [(&str, Engineering); 3] = [
    (
        "cotton",
        Engineering {
            e_u: 1.0e5,
            e_v: 2.8e5,
            mu: 4.0e4,
            nu: 0.4,
            b: 50.0,
        },
    ),
    (
        "denim",
        Engineering {
            e_u: 5.0e5,
            e_v: 7.0e5,
            mu: 2.0e4,
            nu: 0.45,
            b: 200.0,
        },
    ),
    (
        "silk",
        Engineering {
            e_u: 2.0e5,
            e_v: 3.0e5,
            mu: 1.5e4,
            nu: 0.35,
            b: 10.0,
        },
    ),
];

/// The swatch: a square grid.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Swatch {
    /// Side, m.
    pub size: f64,
    /// Vertices per side.
    pub n: usize,
    /// Areal density, kg/m².
    pub density: f64,
    /// Gravity, m/s².
    pub gravity: V3,
}

impl Default for Swatch {
    fn default() -> Self {
        // The paper's 15 cm validation swatch; cotton's density from its Table 2.
        Self {
            size: 0.15,
            n: 11,
            density: 0.224,
            gravity: [0.0, 0.0, -9.81],
        }
    }
}

/// How the parameters are fitted.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Schedule {
    /// All five at once on every target.
    Joint,
    /// The paper's §5 schedule: `b` alone on the bending targets (cantilevers and ledge
    /// drapes), then the four
    /// membrane parameters on the others, `rounds` times.
    BendingFirst,
}

/// What minimises the objective.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Optimizer {
    /// Levenberg–Marquardt with implicit-function Jacobians (the paper).
    #[default]
    Lm,
    /// Adam on `ln γ` through Burn's autodiff and the equilibrium op's adjoint (ours; the FFT
    /// descriptor and the joint schedule only).
    Adam,
}

/// How Levenberg–Marquardt's Jacobian gets the equilibria's derivatives `dx/dγ`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Derivatives {
    /// The implicit-function theorem at the polished equilibrium: one linear solve (ours).
    #[default]
    Implicit,
    /// Forward mode through `fit.forward_steps` XPBD steps from the polished equilibrium, dual
    /// numbers carried beside the iterates (the paper's way, §3.3.2).
    Forward,
}

/// Where each of the fit's equilibria starts.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[serde(rename_all = "snake_case")]
pub enum FitStart {
    /// The target's own shape (paper §3.4.1): the fit stays on the target's wrinkle branch.
    #[default]
    Target,
    /// The scenario's unperturbed (flat) start, solved to equilibrium with the initial guess:
    /// a wrinkle branch of the fit's own, as when the target was captured elsewhere (the
    /// invariance experiment).
    Flat,
}

/// `[fit]`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct FitConfig {
    /// Shape descriptor.
    pub descriptor: Descriptor,
    /// Levenberg–Marquardt (`"lm"`, the paper) or Adam through Burn's autodiff (`"adam"`).
    pub optimizer: Optimizer,
    /// Adam's steps (`optimizer = "adam"`).
    pub adam_steps: usize,
    /// Adam's learning rate on `ln γ` (`optimizer = "adam"`).
    pub adam_lr: f64,
    /// Levenberg–Marquardt's accepted steps at most (per pass).
    pub max_iterations: usize,
    /// Joint or bending-first.
    pub schedule: Schedule,
    /// Rounds of the bending-first schedule.
    pub rounds: usize,
    /// Starts: the initial guess, then guesses with every parameter scaled by a factor drawn
    /// log-uniformly within `1/start_spread … start_spread` (seeded by `seed`); the start
    /// whose fit has the lowest objective over every target wins.
    pub starts: usize,
    /// See `starts`.
    pub start_spread: f64,
    /// Weight of the reactions' relative errors beside the descriptors'.
    pub force_weight: f64,
    /// The Poisson penalty's scale `s_ν` (Eq. 8).
    pub poisson_penalty: f64,
    /// Bounds: every parameter within this factor of its initial value.
    pub bounds_factor: f64,
    /// XPBD steps each of the fit's equilibria takes from its target's shape before the
    /// Newton polish (the targets themselves take `solve.steps`).
    pub xpbd_steps: usize,
    /// Newton steps polishing every equilibrium.
    pub polish_iterations: usize,
    /// Where the Jacobian's `dx/dγ` come from.
    pub derivatives: Derivatives,
    /// XPBD steps the forward-mode derivatives take (`derivatives = "forward"`).
    pub forward_steps: usize,
    /// Out-of-plane perturbation of the targets' starts, m.
    pub noise: f64,
    /// Where the fit's equilibria start.
    pub start: FitStart,
    /// Seed of the perturbation.
    pub seed: u64,
}

impl Optimizer {
    /// Its name in messages.
    pub fn describe(self) -> &'static str {
        match self {
            Optimizer::Lm => "Levenberg–Marquardt",
            Optimizer::Adam => "Adam",
        }
    }
}

impl Default for FitConfig {
    fn default() -> Self {
        Self {
            descriptor: Descriptor::Fft,
            optimizer: Optimizer::Lm,
            adam_steps: 300,
            adam_lr: 0.02,
            max_iterations: 20,
            schedule: Schedule::Joint,
            rounds: 3,
            starts: 1,
            start_spread: 2.0,
            force_weight: 1.0,
            poisson_penalty: 1e8,
            bounds_factor: 100.0,
            xpbd_steps: 200,
            polish_iterations: 30,
            derivatives: Derivatives::Implicit,
            forward_steps: 2000,
            noise: 1e-4,
            start: FitStart::Target,
            seed: 0,
        }
    }
}

/// `[targets]`: how the synthetic targets are made.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TargetsConfig {
    /// Solve each target on a grid this many times finer and sample it at the template's
    /// vertices (the grids are nested): another discretisation of the same material, standing
    /// in for another simulator (paper 001 §5); 1 = the fit's own grid.
    pub refine: usize,
    /// Standard deviation of Gaussian noise added to every sampled target coordinate, m (a
    /// registered scan's); seeded by `fit.seed`. With `stamp`, the noise of the scan instead.
    pub noise: f64,
    /// `stamp = s > 0`: each target is a registered scan (paper 001 §3.2, `xpbd::registration`)
    /// instead of the equilibrium sampled at the template's vertices. The scan is the solved
    /// (`refine` times finer) mesh with `noise` on every free vertex; every `s`-th template
    /// row and column (and the last) is stamped as landmarks, which take the scan's positions;
    /// the other vertices are interpolated between them and projected along the normal onto
    /// the scan. 0 (default): no registration.
    pub stamp: usize,
    /// The simulator that solves the synthetic targets: springtime's XPBD cloth (`"xpbd"`,
    /// the fit's own model) or the FEM source's cloth brought to rest by Newton's method
    /// (`"fem"`: another element formulation and bending discretisation; isotropic `[truth]`
    /// only, no weights; see `xpbd::fem_target`).
    pub simulator: TargetSimulator,
    /// Read the targets from this folder instead (`<scenario name>.npz` each, as `springtime
    /// xpbd generate` writes them: `positions` `[n², 3]` on the template grid, `reactions` `[G]`):
    /// a user's measured drapes.
    pub dir: Option<PathBuf>,
}

impl Default for TargetsConfig {
    fn default() -> Self {
        Self {
            refine: 1,
            noise: 0.0,
            stamp: 0,
            simulator: TargetSimulator::Xpbd,
            dir: None,
        }
    }
}

/// `targets.simulator`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TargetSimulator {
    /// springtime's XPBD cloth.
    #[default]
    Xpbd,
    /// The FEM source's cloth at equilibrium (`xpbd::fem_target`).
    Fem,
}

/// An estimation job (`configs/xpbd_*.toml`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct XpbdConfig {
    /// Name of the job.
    #[serde(default = "default_name")]
    pub name: String,
    /// The swatch.
    #[serde(default)]
    pub swatch: Swatch,
    /// The material of the synthetic targets (CGS); without it, the targets come from
    /// `targets.dir` and the report has no errors against a truth.
    #[serde(default)]
    pub truth: Option<Engineering>,
    /// The fit's starting guess (CGS).
    pub initial: Engineering,
    /// The equilibrium solve (`dt = 0`: chosen from the stiffest element, `dt² C / m = 0.1`).
    #[serde(default)]
    pub solve: Solve,
    /// The fit.
    #[serde(default)]
    pub fit: FitConfig,
    /// How the targets are made.
    #[serde(default)]
    pub targets: TargetsConfig,
    /// The target scenarios.
    pub scenarios: Vec<Scenario>,
}

fn default_name() -> String {
    "xpbd".into()
}

impl XpbdConfig {
    /// The materials of the job (the truth where given, the initial guess): what the solve's
    /// step must be stable for.
    pub fn materials(&self) -> Vec<Gamma> {
        self.truth
            .iter()
            .chain([&self.initial])
            .map(|e| e.gamma())
            .collect()
    }
}

impl Job for XpbdConfig {
    const KIND: &'static str = "xpbd";
    /// The targets' material (γ_cotton of the paper's Table 1), the initial guess
    /// (γ_initial,c) and one loading: every other key has a default.
    const EXAMPLE: &'static str = "[truth]\ne_u = 1.0e5\ne_v = 2.8e5\nmu = 4.0e4\nnu = 0.4\nb = 50.0\n\n\
                                   [initial]\ne_u = 2.0e5\ne_v = 1.8e5\nmu = 5.0e4\nnu = 0.3\nb = 10.0\n\n\
                                   [[scenarios]]\nkind = \"frame_shear\"\nangle_deg = 10.0\n";

    /// Checks ranges; errors name the key.
    fn validate(&self) -> Result<()> {
        self.check_swatch_and_materials()?;
        self.check_targets()?;
        self.check_fit()?;
        if self.targets.stamp > 0 && self.targets.dir.is_some() {
            bail!(
                "`targets.stamp` registers synthetic scans, but `targets.dir` reads the targets \
                 from files: give one of them"
            );
        }
        for sc in &self.scenarios {
            sc.validate()?;
            self.check_scenario(sc)?;
        }
        if self.truth.is_none() && self.targets.dir.is_none() {
            bail!("give the targets' material `[truth]` or a folder of targets `targets.dir`");
        }
        if !(self.solve.damping > 0.0 && self.solve.damping <= 1.0) {
            bail!("`solve.damping` must be in (0, 1]");
        }
        Ok(())
    }
}

impl XpbdConfig {
    /// The swatch, that there are scenarios, and the stability of the truth and initial guess.
    fn check_swatch_and_materials(&self) -> Result<()> {
        let s = &self.swatch;
        if s.n < 3 || !(s.size > 0.0) || !(s.density > 0.0) {
            bail!("`swatch` needs n ≥ 3, size > 0 and density > 0");
        }
        if self.scenarios.is_empty() {
            bail!("`scenarios` is empty: give at least one [[scenarios]]");
        }
        let materials = [
            ("truth", self.truth.as_ref()),
            ("initial", Some(&self.initial)),
        ];
        for (key, e) in materials.into_iter().filter_map(|(k, e)| Some((k, e?))) {
            let g = e.gamma();
            let d = 1.0 - g.c01 * g.c01 / (g.c00 * g.c11);
            if !(g.c00 > 0.0 && g.c11 > 0.0 && g.c22 > 0.0 && g.b >= 0.0 && d > 0.0) {
                bail!("`{key}` is not a stable material (moduli > 0, ν_uv ν_vu < 1): {e:?}");
            }
        }
        Ok(())
    }

    /// `[targets]`: the refinement, noise and stamp, and that files and the FEM exclude each
    /// other.
    fn check_targets(&self) -> Result<()> {
        let t = &self.targets;
        if t.refine == 0 || t.refine > 8 || !(t.noise >= 0.0 && t.noise.is_finite()) {
            bail!(
                "`targets.refine` must be 1 to 8 and `targets.noise` a length ≥ 0 (m), are {} and {}",
                t.refine,
                t.noise
            );
        }
        if t.stamp >= self.swatch.n {
            bail!(
                "`targets.stamp` ({}) must be below the template's {} vertices per side: every \
                 `stamp`-th row and column is a landmark",
                t.stamp,
                self.swatch.n
            );
        }
        if t.dir.is_some() && t.simulator == TargetSimulator::Fem {
            bail!(
                "`targets.dir` reads the targets from files, so `targets.simulator = \"fem\"` \
                 would not be used: give one of them"
            );
        }
        Ok(())
    }

    /// `[fit]`: the forward derivatives' steps and what Adam needs.
    fn check_fit(&self) -> Result<()> {
        if self.fit.derivatives == Derivatives::Forward && self.fit.forward_steps == 0 {
            bail!("`fit.forward_steps` must be positive with `fit.derivatives = \"forward\"`");
        }
        if self.fit.optimizer == Optimizer::Adam {
            if self.fit.descriptor != Descriptor::Fft || self.fit.schedule != Schedule::Joint {
                bail!(
                    "`fit.optimizer = \"adam\"` needs `fit.descriptor = \"fft\"` and \
                     `fit.schedule = \"joint\"`"
                );
            }
            if self.fit.adam_steps == 0 || !(self.fit.adam_lr > 0.0) {
                bail!("`fit.adam_steps` and `fit.adam_lr` must be positive");
            }
        }
        Ok(())
    }

    /// What a scenario needs of the rest of the config: a ledge drape's held rows on the top,
    /// gravity down and XPBD targets; contact with implicit derivatives.
    fn check_scenario(&self, sc: &Scenario) -> Result<()> {
        let s = &self.swatch;
        if let Scenario::LedgeDrape {
            overhang, radius, ..
        } = *sc
        {
            let cell = s.size / (s.n - 1) as f64;
            if (1.0 - overhang) * s.size - radius < cell {
                bail!(
                    "`scenarios.overhang` = {overhang} of `{}` leaves the held rows (the first \
                     {cell} m) off the ledge's flat top on this swatch: lower it, or \
                     `scenarios.radius`",
                    sc.name()
                );
            }
            let g = s.gravity;
            if !(g[0] == 0.0 && g[1] == 0.0 && g[2] < 0.0) {
                bail!(
                    "`swatch.gravity` must point down (−z) for `{}`: the ledge's top faces +z, \
                     is {g:?}",
                    sc.name()
                );
            }
            if self.targets.simulator == TargetSimulator::Fem {
                bail!(
                    "`targets.simulator = \"fem\"` has no contact (its Newton solve knows no \
                     collider): `{}` needs the XPBD targets",
                    sc.name()
                );
            }
        }
        if sc.contact_stiffness().is_some() && self.fit.derivatives == Derivatives::Forward {
            bail!(
                "`fit.derivatives = \"forward\"` does not follow the contact of `{}`: use \
                 \"implicit\"",
                sc.name()
            );
        }
        Ok(())
    }
}

/// `estimate.json`.
#[derive(Debug, Clone, Serialize)]
pub struct EstimateReport {
    /// Job name.
    pub name: String,
    /// The fitted γ, SI (N/m, J).
    pub gamma: Gamma,
    /// The fitted γ in the paper's CGS units (dyn/cm, erg), as `C00 … b`.
    pub gamma_cgs: std::collections::BTreeMap<String, f64>,
    /// The fitted engineering constants `E_u, E_v, μ` (dyn/cm) and `ν`, as the paper's tables.
    pub engineering_cgs: std::collections::BTreeMap<String, f64>,
    /// The true γ of the targets, SI (synthetic targets only).
    pub truth: Option<Gamma>,
    /// The starting γ, SI.
    pub initial: Gamma,
    /// `|fitted − true| / true` per parameter, and `iterations`.
    pub relative_error: std::collections::BTreeMap<String, f64>,
    /// `(fitted − true) / true` per parameter.
    pub signed_error: std::collections::BTreeMap<String, f64>,
    /// Accepted Levenberg–Marquardt steps.
    pub iterations: usize,
    /// `½‖r‖²` at the start and after every accepted step.
    pub objective: Vec<f64>,
    /// `½‖r‖²` of the chosen fit over every target (the bending-first passes each see a part).
    pub final_objective: f64,
    /// The schedule.
    pub schedule: Schedule,
    /// Levenberg–Marquardt or Adam.
    pub optimizer: Optimizer,
    /// Every start's guess, fit and objective over every target.
    pub starts: Vec<StartFit>,
    /// The descriptor.
    pub descriptor: Descriptor,
    /// Per scenario: name and the fitted equilibrium's largest vertex distance to its target, m.
    pub scenarios: Vec<ScenarioFit>,
    /// The equilibrium solve used (with its resolved step).
    pub solve: Solve,
    /// Wall time, s.
    pub wall_seconds: f64,
}

/// One start of the fit.
#[derive(Debug, Clone, Serialize)]
pub struct StartFit {
    /// Its initial guess, SI.
    pub start: Gamma,
    /// Its result, SI.
    pub fitted: Gamma,
    /// `½‖r‖²` over every target at its result.
    pub objective: f64,
    /// Its accepted Levenberg–Marquardt steps.
    pub iterations: usize,
}

/// One scenario's fit.
#[derive(Debug, Clone, Serialize)]
pub struct ScenarioFit {
    /// Scenario name.
    pub name: String,
    /// Largest vertex distance between the fitted equilibrium and the target, m.
    pub max_vertex_error: f64,
    /// The target's equilibrium residual.
    pub target_residual: f64,
    /// The target's reaction magnitude, N.
    pub target_reaction: f64,
    /// A registered target's distance to the true positions of its material points
    /// (`targets.stamp`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub registration: Option<RegistrationError>,
    /// Every vertex's distance to the target, m (drawn in `error_map.png`).
    #[serde(skip)]
    pub vertex_error: Vec<f64>,
}

/// A target: its scenario set up, the equilibrium with the true γ and what the fit compares.
struct Target {
    name: String,
    bending: bool,
    setup: Setup,
    x: Vec<V3>,
    residual: f64,
    reactions: Vec<f64>,
    /// The norm of its descriptor at the initial γ: the scale of its residuals.
    norm: f64,
    /// Its descriptor, when that does not depend on γ (computed once).
    descriptor: Option<Vec<f64>>,
    /// Where the fit's equilibria start (`fit.start`).
    branch: Vec<V3>,
    /// How far a registered target is from its material points.
    registration: Option<RegistrationError>,
}

impl Target {
    /// The target as the Adam fit reads it (the FFT descriptor, computed once).
    fn adam(&self, cloth: &XpbdCloth, fit: &FitConfig, solve: Solve) -> AdamTarget {
        AdamTarget {
            problem: Arc::new(StaticProblem {
                cloth: cloth.clone(),
                load: self.setup.load.clone(),
                groups: self.setup.groups.clone(),
                start: self.branch.clone(),
                solve: Solve {
                    steps: fit.xpbd_steps,
                    ..solve
                },
                polish_iterations: fit.polish_iterations,
            }),
            descriptor: self
                .descriptor
                .clone()
                .expect("the FFT descriptor does not depend on γ"),
            norm: self.norm,
            reactions: self.reactions.clone(),
        }
    }

    /// A target of scenario `sc` at `x` (the fit starts there and its residuals are unscaled
    /// until `norm` is set).
    fn new(sc: &Scenario, setup: Setup, x: Vec<V3>, residual: f64, reactions: Vec<f64>) -> Self {
        Self {
            name: sc.name(),
            bending: sc.is_bending(),
            norm: 1.0,
            descriptor: None,
            branch: x.clone(),
            setup,
            x,
            residual,
            reactions,
            registration: None,
        }
    }
}

/// The fit as a least-squares problem over γ (SI, `[C00, C11, C01, C22, b]`).
struct Problem<'a> {
    cloth: &'a XpbdCloth,
    cfg: &'a XpbdConfig,
    solve: Solve,
    targets: Vec<&'a Target>,
    /// The equilibria of the last γ evaluated: Levenberg–Marquardt asks for the Jacobian at
    /// the very γ whose residuals it has just accepted.
    last: Option<(Vec<f64>, Vec<Vec<V3>>)>,
    /// Counts the Jacobians (the start and every accepted step) and shows the objective.
    bar: Option<&'a Bar>,
}

impl Problem<'_> {
    /// The config's shape descriptor of positions `x` at `gamma`.
    fn descriptor(&self, gamma: &Gamma, x: &[V3]) -> Vec<f64> {
        let n = self.cfg.swatch.n;
        self.cfg.fit.descriptor.of(self.cloth, n, n, gamma, x)
    }

    /// The equilibrium of a scenario with γ, from the target's shape (paper §3.4.1) or from the
    /// fit's own branch (`fit.start = "flat"`).
    fn equilibrium(&self, gamma: &Gamma, t: &Target) -> Result<Vec<V3>> {
        let solve = Solve {
            steps: self.cfg.fit.xpbd_steps,
            ..self.solve
        };
        let mut x = self.cloth.solve(gamma, &t.setup.load, &t.branch, &solve)?.x;
        polish(
            self.cloth,
            gamma,
            &t.setup.load,
            &mut x,
            self.cfg.fit.polish_iterations,
            1e-10,
        )?;
        Ok(x)
    }

    /// The equilibria of every target at `p`, solved once per `p`.
    fn equilibria(&mut self, p: &[f64]) -> Result<Vec<Vec<V3>>> {
        if let Some((q, xs)) = self.last.take()
            && q == p
        {
            self.last = Some((q, xs.clone()));
            return Ok(xs);
        }
        let gamma = Gamma::from_array([p[0], p[1], p[2], p[3], p[4]]);
        let xs = self
            .targets
            .par_iter()
            .map(|t| self.equilibrium(&gamma, t))
            .collect::<Result<Vec<_>>>()?;
        self.last = Some((p.to_vec(), xs.clone()));
        Ok(xs)
    }

    /// One target's residual rows at `p` (its descriptor's, then its reactions') and, with
    /// `with_jacobian`, their Jacobian rows, from its equilibrium `x`.
    fn target_rows(
        &self,
        p: &[f64],
        t: &Target,
        x: &[V3],
        with_jacobian: bool,
    ) -> Result<(Vec<f64>, Vec<Vec<f64>>)> {
        let at = TargetAt {
            problem: self,
            p,
            gamma: Gamma::from_array([p[0], p[1], p[2], p[3], p[4]]),
            t,
            x,
        };
        let (mut r, mut j) = (Vec::new(), Vec::new());
        let s = self.descriptor(&at.gamma, x);
        let at_gamma;
        let target = match &t.descriptor {
            Some(d) => d,
            None => {
                at_gamma = self.descriptor(&at.gamma, &t.x);
                &at_gamma
            }
        };
        r.extend(s.iter().zip(target).map(|(a, b)| (a - b) / t.norm));
        let sens = if with_jacobian {
            Some(at.sensitivity()?)
        } else {
            None
        };
        if let Some(sens) = &sens {
            let cols: Vec<Vec<f64>> = sens
                .dx
                .iter()
                .enumerate()
                .map(|(k, dx)| at.descriptor_column(k, dx, s.len()))
                .collect();
            for row in 0..s.len() {
                j.push((0..5).map(|k| cols[k][row]).collect());
            }
        }
        at.reaction_rows(sens.as_ref(), &mut r, &mut j);
        Ok((r, j))
    }

    fn evaluate(&mut self, p: &[f64], with_jacobian: bool) -> Result<(Vec<f64>, Vec<Vec<f64>>)> {
        let xs = self.equilibria(p)?;
        let rows = self
            .targets
            .par_iter()
            .zip(&xs)
            .map(|(&t, x)| self.target_rows(p, t, x, with_jacobian))
            .collect::<Result<Vec<_>>>()?;
        let (mut r, mut j) = (Vec::new(), Vec::new());
        for (tr, tj) in rows {
            r.extend(tr);
            j.extend(tj);
        }
        // The Poisson penalty, as a residual: √s_ν · max(0, ν_uv − 0.5), ν_uv = C01 / C11.
        let root = self.cfg.fit.poisson_penalty.sqrt();
        let nu = p[2] / p[1];
        r.push(root * (nu - 0.5).max(0.0));
        if with_jacobian {
            let mut row = vec![0.0; 5];
            if nu > 0.5 {
                row[1] = -root * p[2] / (p[1] * p[1]);
                row[2] = root / p[1];
            }
            j.push(row);
        }
        Ok((r, j))
    }
}

/// One target's rows of the fit at `p` (`gamma`), from its equilibrium `x` there.
struct TargetAt<'a> {
    problem: &'a Problem<'a>,
    p: &'a [f64],
    gamma: Gamma,
    t: &'a Target,
    x: &'a [V3],
}

impl TargetAt<'_> {
    /// `dx/dγ` and the reactions' derivatives at the equilibrium, by the implicit function
    /// theorem or by forward differentiation of the solve (`fit.derivatives`).
    fn sensitivity(&self) -> Result<Sensitivity> {
        let (problem, t) = (self.problem, self.t);
        match problem.cfg.fit.derivatives {
            Derivatives::Implicit => sensitivity(
                problem.cloth,
                &self.gamma,
                &t.setup.load,
                self.x,
                &t.setup.groups,
            ),
            Derivatives::Forward => {
                // From the equilibrium itself: the values stay, the derivatives converge.
                let solve = Solve {
                    steps: problem.cfg.fit.forward_steps,
                    tolerance: 0.0,
                    ..problem.solve
                };
                let (_, sens) = problem.cloth.solve_with_derivatives(
                    &self.gamma,
                    &t.setup.load,
                    self.x,
                    &solve,
                    &t.setup.groups,
                )?;
                Ok(sens)
            }
        }
    }

    /// The descriptor residuals' derivatives (`len` of them) along `dx = dx/dγ_k`, by central
    /// differences; the energy descriptor also depends on γ directly (on both sides), linearly.
    fn descriptor_column(&self, k: usize, dx: &[V3], len: usize) -> Vec<f64> {
        let (problem, p, x, norm) = (self.problem, self.p, self.x, self.t.norm);
        let big = dx.iter().flatten().fold(0.0f64, |m, v| m.max(v.abs()));
        let eps = if big > 0.0 {
            1e-6 * problem.cfg.swatch.size / big
        } else {
            0.0
        };
        let mut col: Vec<f64> = if eps == 0.0 {
            vec![0.0; len]
        } else {
            let shifted = |sign: f64| -> Vec<V3> {
                x.iter()
                    .zip(dx)
                    .map(|(a, d)| [0, 1, 2].map(|c| a[c] + sign * eps * d[c]))
                    .collect()
            };
            let (up, dn) = (
                problem.descriptor(&self.gamma, &shifted(1.0)),
                problem.descriptor(&self.gamma, &shifted(-1.0)),
            );
            up.iter()
                .zip(&dn)
                .map(|(a, b)| (a - b) / (2.0 * eps * norm))
                .collect()
        };
        if problem.cfg.fit.descriptor.depends_on_gamma() {
            let h = 1e-6 * p[k].abs().max(1e-300);
            let at = |sign: f64| {
                let mut q = [p[0], p[1], p[2], p[3], p[4]];
                q[k] += sign * h;
                Gamma::from_array(q)
            };
            let (up, dn) = (at(1.0), at(-1.0));
            let (su, sd) = (problem.descriptor(&up, x), problem.descriptor(&dn, x));
            let (tu, td) = (
                problem.descriptor(&up, &self.t.x),
                problem.descriptor(&dn, &self.t.x),
            );
            for (i, c) in col.iter_mut().enumerate() {
                *c += ((su[i] - sd[i]) - (tu[i] - td[i])) / (2.0 * h * norm);
            }
        }
        col
    }

    /// Appends every clamp group's reaction residual to `r` and, with `sens`, its Jacobian row
    /// to `j`.
    fn reaction_rows(&self, sens: Option<&Sensitivity>, r: &mut Vec<f64>, j: &mut Vec<Vec<f64>>) {
        let (problem, t, x) = (self.problem, self.t, self.x);
        for (g, group) in t.setup.groups.iter().enumerate() {
            let react = problem.cloth.reaction(&self.gamma, &t.setup.load, x, group);
            let mag = dot(react, react).sqrt();
            let target = t.reactions[g].max(1e-300);
            let w = problem.cfg.fit.force_weight;
            r.push(w * (mag - t.reactions[g]) / target);
            if let Some(sens) = sens {
                let unit = [0, 1, 2].map(|c| react[c] / mag.max(1e-300));
                j.push(
                    (0..5)
                        .map(|k| w * dot(unit, sens.reactions[g][k]) / target)
                        .collect(),
                );
            }
        }
    }
}

impl Problem<'_> {
    /// Each target's equilibrium at `p` against the target: the largest vertex distance.
    fn fits(&mut self, p: &[f64]) -> Result<Vec<ScenarioFit>> {
        let xs = self.equilibria(p)?;
        Ok(self
            .targets
            .iter()
            .zip(xs)
            .map(|(t, x)| {
                let vertex_error: Vec<f64> = x
                    .iter()
                    .zip(&t.x)
                    .map(|(a, b)| {
                        let d = [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
                        dot(d, d).sqrt()
                    })
                    .collect();
                ScenarioFit {
                    name: t.name.clone(),
                    max_vertex_error: vertex_error.iter().copied().fold(0.0, f64::max),
                    target_residual: t.residual,
                    target_reaction: t.reactions.first().copied().unwrap_or(0.0),
                    registration: t.registration,
                    vertex_error,
                }
            })
            .collect())
    }
}

/// `error_map.png`: every scenario's vertex distances to its target on the rest swatch, one
/// panel each on one colour scale (mm), as the paper's Figs. 5 and 8.
pub fn error_map_png(path: &Path, cfg: &XpbdConfig, fits: &[ScenarioFit]) -> Result<()> {
    use springtime_core::cloth::{GridSpec, Topology};
    use springtime_plot as plot;
    let sw = cfg.swatch;
    let topology = Topology::grid(
        &GridSpec {
            nx: sw.n,
            ny: sw.n,
            ..GridSpec::default()
        },
        sw.size,
        sw.size,
    );
    let mm: Vec<Vec<f64>> = fits
        .iter()
        .map(|f| f.vertex_error.iter().map(|e| 1e3 * e).collect())
        .collect();
    let top = mm.iter().flatten().copied().fold(0.0, f64::max);
    let range = (0.0, if top > 0.0 { top } else { 1.0 });
    let panel = 260u32;
    let (w, h) = (
        panel * fits.len().max(1) as u32 + plot::COLORBAR_WIDTH,
        plot::TITLE_HEIGHT + panel,
    );
    plot::png_figure(path, w, h, |root| {
        let body = plot::title(
            root,
            &format!("Distance to the target per vertex (max {top:.3} mm)"),
            16,
        )?;
        let (maps, bar) = body.split_horizontally(panel * fits.len().max(1) as u32);
        for (area, (f, v)) in maps
            .split_evenly((1, fits.len().max(1)))
            .iter()
            .zip(fits.iter().zip(&mm))
        {
            plot::draw_map(
                area,
                plot::Map::Particles {
                    topology: &topology,
                },
                v,
                &f.name,
                range,
            )?;
        }
        plot::draw_colorbar(&bar, range, "mm")
    })
}

impl LeastSquares for Problem<'_> {
    fn residuals(&mut self, p: &[f64]) -> Result<Vec<f64>> {
        // A trial γ whose equilibrium cannot be found is a rejected step, not an error.
        match self.evaluate(p, false) {
            Ok((r, _)) => Ok(r),
            Err(_) => Ok(vec![f64::INFINITY]),
        }
    }

    fn jacobian(&mut self, p: &[f64]) -> Result<(Vec<f64>, Vec<Vec<f64>>)> {
        let (r, j) = self.evaluate(p, true)?;
        let cost = 0.5 * r.iter().map(|v| v * v).sum::<f64>();
        if let Some(bar) = self.bar {
            bar.inc(1);
            bar.set_message(format!("objective {cost:.4e}"));
        }
        Ok((r, j))
    }
}

/// The config's solve with its step resolved for the given materials: `dt = 0` becomes
/// `√(0.1 m_min / C_max)` over their stiffest membrane modulus, or `√(0.1 / κ)` for the
/// stiffest contact of the scenarios where that is shorter.
pub fn resolved_solve(cfg: &XpbdConfig, cloth: &XpbdCloth, materials: &[Gamma]) -> Solve {
    let mut solve = cfg.solve;
    if solve.dt <= 0.0 {
        let stiff = materials
            .iter()
            .flat_map(|g| [g.c00, g.c11, g.c22])
            .fold(0.0, f64::max);
        let m = cloth.mass.iter().copied().fold(f64::INFINITY, f64::min);
        solve.dt = (0.1 * m / stiff).sqrt();
        // The contact's explicit force as well: `dt² κ = 0.1` at most.
        if let Some(kappa) = cfg
            .scenarios
            .iter()
            .filter_map(Scenario::contact_stiffness)
            .reduce(f64::max)
        {
            solve.dt = solve.dt.min((0.1 / kappa).sqrt());
        }
    }
    solve
}

/// A scenario's target: the equilibrium with the true γ, solved on the fit's grid or on one
/// `targets.refine` times finer and sampled at the fit's vertices, with `targets.noise`.
fn make_target(
    cfg: &XpbdConfig,
    cloth: &XpbdCloth,
    sc: &Scenario,
    seed: u64,
    progress: &Progress,
) -> Result<Target> {
    let sw = cfg.swatch;
    let truth = cfg
        .truth
        .context("generating targets needs the material `[truth]`")?
        .gamma();
    let setup = sc.setup(cloth, sw.n, sw.size, sw.gravity, cfg.fit.noise, seed);
    let refine = cfg.targets.refine;
    let nf = (sw.n - 1) * refine + 1;
    let fine_cloth;
    let (fine, fine_setup) = if refine == 1 {
        (cloth, setup.clone())
    } else {
        fine_cloth = XpbdCloth::grid(nf, nf, sw.size, sw.size, sw.density)?;
        let s = sc.setup_refined(
            &fine_cloth,
            &SetupGrid {
                n: nf,
                size: sw.size,
                gravity: sw.gravity,
                noise: cfg.fit.noise,
                seed,
                refine,
            },
        );
        (&fine_cloth, s)
    };
    let grid = SolveGrid {
        cloth: fine,
        n: nf,
        setup: fine_setup,
        template_n: sw.n,
        refine,
    };
    let solved = match cfg.targets.simulator {
        TargetSimulator::Xpbd => grid.solve_xpbd(&TruthSolve {
            cfg,
            truth,
            sc,
            progress,
        })?,
        TargetSimulator::Fem => grid.solve_fem(&TruthSolve {
            cfg,
            truth,
            sc,
            progress,
        })?,
    };
    let mut noise = TargetNoise::new(cfg.targets.noise, seed)?;
    if cfg.targets.stamp == 0 {
        let x: Vec<V3> = (0..sw.n * sw.n)
            .map(|k| {
                let mut p = solved.x[grid.node(k)];
                noise.apply(&mut p, setup.load.clamped[k].is_some());
                p
            })
            .collect();
        return Ok(Target::new(sc, setup, x, solved.residual, solved.reactions));
    }
    registered_target(cfg, sc, setup, &grid, solved, &mut noise)
}

/// A target's equilibrium on the grid it was solved on, with its relative residual and its
/// clamp groups' reaction magnitudes (N).
struct Solved {
    x: Vec<V3>,
    residual: f64,
    reactions: Vec<f64>,
}

/// A target's solve with the true material `truth` in scenario `sc` of `cfg`.
struct TruthSolve<'a> {
    cfg: &'a XpbdConfig,
    truth: Gamma,
    sc: &'a Scenario,
    progress: &'a Progress,
}

/// The grid a target is solved on: the template's, or one `refine` times finer.
struct SolveGrid<'a> {
    cloth: &'a XpbdCloth,
    /// Vertices per side.
    n: usize,
    /// The scenario set up on this grid.
    setup: Setup,
    /// The template's vertices per side.
    template_n: usize,
    refine: usize,
}

impl SolveGrid<'_> {
    /// The template vertex `k`'s node on this grid.
    fn node(&self, k: usize) -> usize {
        (k / self.template_n) * self.refine * self.n + (k % self.template_n) * self.refine
    }

    /// The XPBD cloth's equilibrium with `truth`, polished by Newton; a warning where it is not
    /// at rest.
    fn solve_xpbd(&self, job: &TruthSolve) -> Result<Solved> {
        let (cfg, truth, sc) = (job.cfg, &job.truth, job.sc);
        let (fine, setup) = (self.cloth, &self.setup);
        let solve = resolved_solve(cfg, fine, &cfg.materials());
        let mut xf = fine.solve(truth, &setup.load, &setup.start, &solve)?.x;
        let residual = polish(fine, truth, &setup.load, &mut xf, 50, 1e-11)?;
        if residual > 1e-6 {
            job.progress.note(&format!(
                "warning: the target {} is not at equilibrium (relative residual \
                 {residual:.2e} after {} steps and the Newton polish): raise `solve.steps`",
                sc.name(),
                solve.steps
            ));
        }
        let reactions = setup
            .groups
            .iter()
            .map(|g| {
                let r = fine.reaction(truth, &setup.load, &xf, g);
                dot(r, r).sqrt()
            })
            .collect();
        Ok(Solved {
            x: xf,
            residual,
            reactions,
        })
    }

    /// The FEM source's equilibrium with `truth` (`targets.simulator = "fem"`); a warning where
    /// it is not at rest.
    fn solve_fem(&self, job: &TruthSolve) -> Result<Solved> {
        let (sw, truth, sc) = (job.cfg.swatch, &job.truth, job.sc);
        let t = super::fem_target::solve(
            self.cloth,
            self.n,
            truth,
            sw.density,
            sw.gravity,
            &self.setup,
        )
        .with_context(|| format!("the FEM target of scenario `{}`", sc.name()))?;
        if t.residual > super::fem_target::WARN_RESIDUAL {
            job.progress.note(&format!(
                "warning: the FEM target {} is not at equilibrium (relative residual {:.2e})",
                sc.name(),
                t.residual
            ));
        }
        Ok(Solved {
            x: t.x,
            residual: t.residual,
            reactions: t.reactions,
        })
    }
}

/// `targets.noise`: Gaussian noise of that deviation (m) on a target's free vertices, seeded by
/// its scenario.
struct TargetNoise {
    deviation: f64,
    rng: StdRng,
    normal: rand_distr::Normal<f64>,
}

impl TargetNoise {
    fn new(deviation: f64, seed: u64) -> Result<Self> {
        let rng = StdRng::seed_from_u64(seed ^ 0x7A67_E75E);
        let normal = rand_distr::Normal::new(0.0, deviation.max(f64::MIN_POSITIVE))?;
        Ok(Self {
            deviation,
            rng,
            normal,
        })
    }

    /// Adds the noise to `p` unless it is `clamped`.
    fn apply(&mut self, p: &mut V3, clamped: bool) {
        if self.deviation > 0.0 && !clamped {
            for v in p.iter_mut() {
                *v += self.rng.sample(self.normal);
            }
        }
    }
}

/// The target as a registered scan (`targets.stamp`): the solved mesh with noise, registered to
/// the template through its stamped landmarks, and its distance to the true material points.
fn registered_target(
    cfg: &XpbdConfig,
    sc: &Scenario,
    setup: Setup,
    grid: &SolveGrid,
    solved: Solved,
    noise: &mut TargetNoise,
) -> Result<Target> {
    let sw = cfg.swatch;
    let (nf, xf) = (grid.n, &solved.x);
    let mut vertices = xf.clone();
    for (p, c) in vertices.iter_mut().zip(&grid.setup.load.clamped) {
        noise.apply(p, c.is_some());
    }
    let scan = Scan {
        vertices,
        triangles: grid_triangles(nf, nf, Diagonal::Alternating),
    };
    let s = cfg.targets.stamp;
    let on = |i: usize| i.is_multiple_of(s) || i == sw.n - 1;
    let landmarks: Vec<Option<V3>> = (0..sw.n * sw.n)
        .map(|k| match setup.load.clamped[k] {
            Some(p) => Some(p),
            None => (on(k / sw.n) && on(k % sw.n)).then(|| scan.vertices[grid.node(k)]),
        })
        .collect();
    let template = grid_triangles(sw.n, sw.n, Diagonal::Alternating);
    let cell = sw.size / (sw.n - 1) as f64;
    let reg = register(sw.n * sw.n, &template, &landmarks, &scan, cell)
        .with_context(|| format!("registering the scan of `{}`", sc.name()))?;
    let truth: Vec<V3> = (0..sw.n * sw.n).map(|k| xf[grid.node(k)]).collect();
    let mut target = Target::new(sc, setup, reg.x, solved.residual, solved.reactions);
    target.registration = Some(RegistrationError::of(
        &target.x,
        &truth,
        reg.landmarks,
        reg.projected,
    ));
    Ok(target)
}

/// The job's targets: read from `targets.dir`, or generated with the true material.
fn load_targets(cfg: &XpbdConfig, cloth: &XpbdCloth, progress: &Progress) -> Result<Vec<Target>> {
    let bar = progress.bar(cfg.scenarios.len() as u64, "targets");
    // Scenario `i`'s perturbation is seeded `fit.seed + i`, whichever thread solves it.
    let targets = cfg
        .scenarios
        .par_iter()
        .enumerate()
        .map(|(i, sc)| {
            let seed = cfg.fit.seed + i as u64;
            let target = match &cfg.targets.dir {
                Some(dir) => read_target(cfg, cloth, sc, &dir.join(format!("{}.npz", sc.name()))),
                None => make_target(cfg, cloth, sc, seed, progress),
            };
            bar.inc(1);
            target
        })
        .collect::<Result<Vec<_>>>()?;
    bar.finish();
    Ok(targets)
}

/// A static target file: `positions` `[n², 3]` (m, the template grid row-major, `u` along a
/// row) and `reactions` `[G]` (N, the magnitudes of the scenario's measured clamp groups), with
/// `grid` `[2]` and `size` (m) to check it against the swatch.
fn read_target(cfg: &XpbdConfig, cloth: &XpbdCloth, sc: &Scenario, path: &Path) -> Result<Target> {
    let sw = cfg.swatch;
    if !path.exists() {
        bail!(
            "{}: no target for scenario `{}` (targets.dir holds `<scenario name>.npz`)",
            path.display(),
            sc.name()
        );
    }
    let npz = Npz::read(path)?;
    let (grid, _) = npz.int("grid", &[Some(2)])?;
    if grid != [sw.n as i64, sw.n as i64] {
        bail!(
            "{}: key `grid` is {grid:?}, but the config's swatch is {} × {}",
            path.display(),
            sw.n,
            sw.n
        );
    }
    let size = npz.scalar("size")?;
    if (size - sw.size).abs() > 1e-9 * sw.size {
        bail!(
            "{}: key `size` is {size} m, but the config's swatch is {} m",
            path.display(),
            sw.size
        );
    }
    let (p, _) = npz.f64("positions", &[Some(sw.n * sw.n), Some(3)])?;
    let x: Vec<V3> = p.chunks(3).map(|c| [c[0], c[1], c[2]]).collect();
    let setup = sc.setup(cloth, sw.n, sw.size, sw.gravity, 0.0, 0);
    let (reactions, _) = npz.f64("reactions", &[Some(setup.groups.len())])?;
    if let Some(r) = reactions.iter().find(|r| !(**r > 0.0)) {
        bail!(
            "{}: key `reactions` holds {r}: reactions are magnitudes > 0 (N)",
            path.display()
        );
    }
    // The clamped vertices must sit where the scenario clamps them.
    for (k, c) in setup.load.clamped.iter().enumerate() {
        if let Some(c) = c {
            let d = [0, 1, 2].map(|i| x[k][i] - c[i]);
            if dot(d, d).sqrt() > 0.01 * sw.size {
                bail!(
                    "{}: key `positions`: vertex {k} is clamped by scenario `{}` at {c:?} but is \
                     at {:?} (more than 1 % of the swatch away): is this the scenario's target?",
                    path.display(),
                    sc.name(),
                    x[k]
                );
            }
        }
    }
    Ok(Target::new(sc, setup, x, f64::NAN, reactions))
}

/// `springtime xpbd generate <config> --out D`: the config's targets (with `[targets]`'s
/// refinement and noise) as the static-target files `targets.dir` reads.
pub fn generate(
    cfg: &XpbdConfig,
    out: &Path,
    force: bool,
    progress: &Progress,
) -> Result<Vec<PathBuf>> {
    let sw = cfg.swatch;
    let cloth = XpbdCloth::grid(sw.n, sw.n, sw.size, sw.size, sw.density)?;
    let paths: Vec<PathBuf> = cfg
        .scenarios
        .iter()
        .map(|sc| out.join(format!("{}.npz", sc.name())))
        .collect();
    for p in &paths {
        springtime_core::io::refuse_overwrite(p, force)?;
    }
    let mut synthetic = cfg.clone();
    synthetic.targets.dir = None;
    let targets = load_targets(&synthetic, &cloth, progress)?;
    std::fs::create_dir_all(out)?;
    for (t, path) in targets.iter().zip(&paths) {
        let mut npz = Npz::default();
        let flat: Vec<f64> = t.x.iter().flatten().copied().collect();
        npz.insert("positions", Array::f64(&[t.x.len(), 3], &flat));
        npz.insert("reactions", Array::f64(&[t.reactions.len()], &t.reactions));
        npz.insert("grid", Array::i64(&[2], &[sw.n as i64, sw.n as i64]));
        npz.insert("size", Array::scalar(sw.size));
        npz.write(path)?;
    }
    Ok(paths)
}

/// `resim.json`: a fitted γ re-simulated in the config's scenarios from its targets' shapes.
#[derive(Debug, Clone, Serialize)]
pub struct ResimReport {
    /// The γ re-simulated, SI.
    pub gamma: Gamma,
    /// Per scenario: the largest vertex distance to the target.
    pub scenarios: Vec<ScenarioFit>,
    /// The largest over every scenario, m.
    pub max_vertex_error: f64,
}

/// `springtime xpbd resim <config> --estimate E --out D`: the γ of an earlier estimate solved to
/// equilibrium in the config's scenarios (from the targets' shapes, as the fit does) against
/// those targets, e.g. configurations the fit never saw. Writes `D/resim.json`.
pub fn resim(
    cfg: &XpbdConfig,
    gamma: Gamma,
    out: &Path,
    force: bool,
    progress: &Progress,
) -> Result<ResimReport> {
    let json = out.join("resim.json");
    springtime_core::io::refuse_overwrite(&json, force)?;
    let sw = cfg.swatch;
    let cloth = XpbdCloth::grid(sw.n, sw.n, sw.size, sw.size, sw.density)?;
    let mut materials = cfg.materials();
    materials.push(gamma);
    let solve = resolved_solve(cfg, &cloth, &materials);
    let targets = load_targets(cfg, &cloth, progress)?;
    let mut problem = Problem {
        cloth: &cloth,
        cfg,
        solve,
        targets: targets.iter().collect(),
        last: None,
        bar: None,
    };
    let scenarios = problem.fits(&gamma.to_array())?;
    let report = ResimReport {
        gamma,
        max_vertex_error: scenarios
            .iter()
            .map(|s| s.max_vertex_error)
            .fold(0.0, f64::max),
        scenarios,
    };
    springtime_core::io::write_json(&json, &report)?;
    error_map_png(&out.join("error_map.png"), cfg, &report.scenarios)?;
    Ok(report)
}

/// What `estimate` takes from the command line.
#[derive(Debug, Clone)]
pub struct EstimateOptions {
    /// Output directory.
    pub out: PathBuf,
    /// Overwrite an earlier estimate there.
    pub force: bool,
}

/// Runs the sim-to-sim estimation of a config and writes `estimate.json`.
pub fn estimate(
    cfg: &XpbdConfig,
    options: &EstimateOptions,
    progress: &Progress,
) -> Result<EstimateReport> {
    let start = Instant::now();
    let json = options.out.join("estimate.json");
    springtime_core::io::refuse_overwrite(&json, options.force)?;
    let sw = cfg.swatch;
    let cloth = XpbdCloth::grid(sw.n, sw.n, sw.size, sw.size, sw.density)?;
    let solve = resolved_solve(cfg, &cloth, &cfg.materials());
    let truth = cfg.truth.map(|e| e.gamma());
    let mut targets = load_targets(cfg, &cloth, progress)?;
    let initial = cfg.initial.gamma();
    scale_and_branch(cfg, &cloth, solve, &initial, &mut targets)?;
    // Jacobians at most: one per start and pass, plus one per accepted step.
    let passes = match cfg.fit.schedule {
        Schedule::Joint => 1,
        Schedule::BendingFirst => 2 * cfg.fit.rounds.max(1),
    };
    let bar = (cfg.fit.optimizer == Optimizer::Lm).then(|| {
        progress.bar(
            (cfg.fit.starts.max(1) * passes * (cfg.fit.max_iterations + 1)) as u64,
            "LM",
        )
    });
    let fitter = Fitter::new(cfg, &cloth, solve, &targets, bar.as_ref(), progress);
    let mut all = fitter.problem(&|_| true);
    let (fit, chosen, start_fits) = fitter.fit_starts(&initial, &mut all)?;
    if let Some(bar) = &bar {
        bar.finish();
    }
    let mut problem = all;
    let gamma = Gamma::from_array([fit.p[0], fit.p[1], fit.p[2], fit.p[3], fit.p[4]]);
    let scenarios = problem.fits(&fit.p)?;
    let (relative_error, signed_error) = parameter_errors(&gamma, truth, fit.iterations);
    let cgs = gamma.to_cgs();
    let eng = Gamma::from_array(cgs).engineering();
    let report = EstimateReport {
        name: cfg.name.clone(),
        gamma,
        gamma_cgs: NAMES.iter().map(|n| n.to_string()).zip(cgs).collect(),
        engineering_cgs: ["E_u", "E_v", "mu", "nu"]
            .iter()
            .map(|n| n.to_string())
            .zip(eng)
            .collect(),
        truth,
        initial,
        relative_error,
        signed_error,
        iterations: fit.iterations,
        objective: fit.history,
        final_objective: chosen.objective,
        schedule: cfg.fit.schedule,
        optimizer: cfg.fit.optimizer,
        starts: start_fits,
        descriptor: cfg.fit.descriptor,
        scenarios,
        solve,
        wall_seconds: start.elapsed().as_secs_f64(),
    };
    springtime_core::io::write_json(&json, &report)?;
    error_map_png(&options.out.join("error_map.png"), cfg, &report.scenarios)?;
    Ok(report)
}

/// Sets every target's residual scale (its descriptor's norm at the `initial` γ), its
/// descriptor where that does not depend on γ, and with `fit.start = "flat"` the branch the
/// fit's equilibria start from: the initial γ's own, solved from the scenario's flat start.
fn scale_and_branch(
    cfg: &XpbdConfig,
    cloth: &XpbdCloth,
    solve: Solve,
    initial: &Gamma,
    targets: &mut [Target],
) -> Result<()> {
    let sw = cfg.swatch;
    for (i, t) in targets.iter_mut().enumerate() {
        let d = cfg.fit.descriptor.of(cloth, sw.n, sw.n, initial, &t.x);
        t.norm = d.iter().map(|v| v * v).sum::<f64>().sqrt().max(1e-300);
        t.descriptor = (!cfg.fit.descriptor.depends_on_gamma()).then_some(d);
        if cfg.fit.start == FitStart::Flat {
            let seed = cfg.fit.seed + i as u64;
            let flat = cfg.scenarios[i].setup(cloth, sw.n, sw.size, sw.gravity, 0.0, seed);
            let mut x = cloth.solve(initial, &flat.load, &flat.start, &solve)?.x;
            polish(cloth, initial, &flat.load, &mut x, 50, 1e-11)?;
            t.branch = x;
        }
    }
    Ok(())
}

/// `(fitted − true) / true` per parameter, absolute (with `iterations`) and signed; empty
/// without a truth.
fn parameter_errors(
    gamma: &Gamma,
    truth: Option<Gamma>,
    iterations: usize,
) -> (BTreeMap<String, f64>, BTreeMap<String, f64>) {
    let mut relative_error = BTreeMap::new();
    let mut signed_error = BTreeMap::new();
    if let Some(truth) = truth {
        let (fitted, true_) = (gamma.to_array(), truth.to_array());
        for k in 0..5 {
            let e = (fitted[k] - true_[k]) / true_[k];
            relative_error.insert(NAMES[k].to_string(), e.abs());
            signed_error.insert(NAMES[k].to_string(), e);
        }
    }
    relative_error.insert("iterations".into(), iterations as f64);
    (relative_error, signed_error)
}

/// The fit of γ over the targets within the bounds around the initial guess: by
/// Levenberg–Marquardt or Adam, jointly or bending first, from each of `fit.starts` starts.
struct Fitter<'a> {
    cfg: &'a XpbdConfig,
    cloth: &'a XpbdCloth,
    solve: Solve,
    targets: &'a [Target],
    /// Counts the Levenberg–Marquardt Jacobians.
    bar: Option<&'a Bar>,
    lower: Vec<f64>,
    upper: Vec<f64>,
    lm: Lm,
    /// The targets as Adam reads them (`fit.optimizer = "adam"` only).
    adam_targets: Vec<AdamTarget>,
    progress: &'a Progress,
}

impl<'a> Fitter<'a> {
    /// The fit of `targets`; notes what it fits.
    fn new(
        cfg: &'a XpbdConfig,
        cloth: &'a XpbdCloth,
        solve: Solve,
        targets: &'a [Target],
        bar: Option<&'a Bar>,
        progress: &'a Progress,
    ) -> Self {
        let p0 = cfg.initial.gamma().to_array();
        let f = cfg.fit.bounds_factor;
        let lower: Vec<f64> = p0
            .iter()
            .enumerate()
            .map(|(k, v)| if k == 2 { 0.0 } else { v / f })
            .collect();
        let upper: Vec<f64> = p0.iter().map(|v| v * f).collect();
        progress.note(&format!(
            "fitting γ from {} targets ({} descriptor, {:?} schedule, {} start(s), step {:.2e} s)",
            targets.len(),
            cfg.fit.descriptor.name(),
            cfg.fit.schedule,
            cfg.fit.starts.max(1),
            solve.dt
        ));
        let lm = Lm {
            max_iterations: cfg.fit.max_iterations,
            ..Lm::default()
        };
        let adam_targets: Vec<AdamTarget> = match cfg.fit.optimizer {
            Optimizer::Adam => targets
                .iter()
                .map(|t| t.adam(cloth, &cfg.fit, solve))
                .collect(),
            Optimizer::Lm => Vec::new(),
        };
        Self {
            cfg,
            cloth,
            solve,
            targets,
            bar,
            lower,
            upper,
            lm,
            adam_targets,
            progress,
        }
    }

    /// The least-squares problem over the targets in `subset`.
    fn problem(&self, subset: &dyn Fn(&Target) -> bool) -> Problem<'a> {
        Problem {
            cloth: self.cloth,
            cfg: self.cfg,
            solve: self.solve,
            targets: self.targets.iter().filter(|t| subset(t)).collect(),
            last: None,
            bar: self.bar,
        }
    }

    /// Fits from every start (the first the `initial` guess, the others random around it),
    /// each judged on every target (`all`): the best fit, its record and every start's.
    fn fit_starts(
        &self,
        initial: &Gamma,
        all: &mut Problem,
    ) -> Result<(lm::Fit, StartFit, Vec<StartFit>)> {
        let p0 = initial.to_array();
        let mut rng = StdRng::seed_from_u64(self.cfg.fit.seed);
        let mut best: Option<(lm::Fit, StartFit)> = None;
        let mut start_fits = Vec::new();
        for start in 0..self.cfg.fit.starts.max(1) {
            let s0: Vec<f64> = p0
                .iter()
                .enumerate()
                .map(|(k, &v)| {
                    let factor = if start == 0 {
                        1.0
                    } else {
                        self.cfg.fit.start_spread.powf(rng.random_range(-1.0..1.0))
                    };
                    (v * factor).clamp(self.lower[k], self.upper[k])
                })
                .collect();
            let fit = self.fit_from(&s0, all)?;
            // Every start is judged on every target.
            let r = all.residuals(&fit.p)?;
            let objective = 0.5 * r.iter().map(|v| v * v).sum::<f64>();
            let record = StartFit {
                start: Gamma::from_array([s0[0], s0[1], s0[2], s0[3], s0[4]]),
                fitted: Gamma::from_array([fit.p[0], fit.p[1], fit.p[2], fit.p[3], fit.p[4]]),
                objective,
                iterations: fit.iterations,
            };
            start_fits.push(record.clone());
            if best.as_ref().is_none_or(|b| objective < b.1.objective) {
                best = Some((fit, record));
            }
        }
        let (fit, chosen) = best.expect("at least one start");
        Ok((fit, chosen, start_fits))
    }

    /// One start's fit from `s0` by the config's optimizer and schedule.
    fn fit_from(&self, s0: &[f64], all: &mut Problem) -> Result<lm::Fit> {
        let fit = &self.cfg.fit;
        match fit.schedule {
            Schedule::Joint if fit.optimizer == Optimizer::Adam => {
                let settings = AdamSettings {
                    n: self.cfg.swatch.n,
                    force_weight: fit.force_weight,
                    poisson_penalty: fit.poisson_penalty,
                    steps: fit.adam_steps,
                    lr: fit.adam_lr,
                };
                adam::fit(
                    &self.adam_targets,
                    &settings,
                    s0,
                    &self.lower,
                    &self.upper,
                    self.progress,
                )
            }
            Schedule::Joint => lm::minimize(all, s0, &self.lower, &self.upper, &self.lm),
            Schedule::BendingFirst => self.bending_first(s0, all),
        }
    }

    /// The bending-first schedule: `fit.rounds` rounds of b on the bending targets, then the
    /// membrane on the others, each pass holding the other parameters.
    fn bending_first(&self, s0: &[f64], all: &mut Problem) -> Result<lm::Fit> {
        let (mut p, mut history, mut iterations) = (s0.to_vec(), Vec::new(), 0);
        for _ in 0..self.cfg.fit.rounds.max(1) {
            for bending in [true, false] {
                let mut part = self.problem(&|t: &Target| t.bending == bending);
                if part.targets.is_empty() {
                    continue;
                }
                // Hold the other parameters at their current values.
                let (lo, hi): (Vec<f64>, Vec<f64>) = (0..5)
                    .map(|k| {
                        if (k == 4) == bending {
                            (self.lower[k], self.upper[k])
                        } else {
                            (p[k], p[k])
                        }
                    })
                    .unzip();
                let pass = lm::minimize(&mut part, &p, &lo, &hi, &self.lm)?;
                p = pass.p;
                iterations += pass.iterations;
                history.extend(pass.history);
            }
        }
        let r = all.residuals(&p)?;
        let cost = 0.5 * r.iter().map(|v| v * v).sum::<f64>();
        Ok(lm::Fit {
            p,
            cost,
            iterations,
            history,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn config(refine: usize, noise: f64) -> XpbdConfig {
        let cotton = TABLE_1[0].1;
        XpbdConfig {
            name: "t".into(),
            swatch: Swatch {
                size: 0.1,
                n: 5,
                density: 0.224,
                gravity: [0.0; 3],
            },
            truth: Some(cotton),
            initial: cotton,
            solve: Solve {
                steps: 4000,
                ..Solve::auto()
            },
            fit: FitConfig {
                noise: 0.0,
                ..FitConfig::default()
            },
            targets: TargetsConfig {
                refine,
                noise,
                ..TargetsConfig::default()
            },
            scenarios: vec![Scenario::FrameShear { angle_deg: 10.0 }],
        }
    }

    #[test]
    fn a_refined_target_is_sampled_at_the_templates_vertices() {
        // A picture frame sheared without gravity strains uniformly: the equilibrium is the
        // frame's affine map on any grid (the solve starts there and stays), so the 9 × 9 target sampled at the 5 × 5 template's
        // vertices must equal the 5 × 5 one, and the total reaction on the frame's side is the
        // same traction.
        let progress = Progress::quiet();
        let (coarse_cfg, fine_cfg) = (config(1, 0.0), config(2, 0.0));
        let cloth = XpbdCloth::grid(5, 5, 0.1, 0.1, 0.224).unwrap();
        let sc = &coarse_cfg.scenarios[0];
        let a = make_target(&coarse_cfg, &cloth, sc, 0, &progress).unwrap();
        let b = make_target(&fine_cfg, &cloth, sc, 0, &progress).unwrap();
        for (p, q) in a.x.iter().zip(&b.x) {
            for c in 0..3 {
                assert!((p[c] - q[c]).abs() < 1e-9, "{p:?} vs {q:?}");
            }
        }
        let (ra, rb) = (a.reactions[0], b.reactions[0]);
        assert!(ra > 0.0 && (ra - rb).abs() < 0.1 * ra, "{ra} vs {rb}");
        // Noise moves the free vertices only, by about its standard deviation.
        let noisy = make_target(&config(1, 1e-3), &cloth, sc, 0, &progress).unwrap();
        let (mut moved, mut sum2) = (0, 0.0);
        for (k, (p, q)) in noisy.x.iter().zip(&a.x).enumerate() {
            let d2: f64 = (0..3).map(|c| (p[c] - q[c]).powi(2)).sum();
            if a.setup.load.clamped[k].is_some() {
                assert_eq!(d2, 0.0);
            } else {
                moved += 1;
                sum2 += d2;
            }
        }
        let rms = (sum2 / (3 * moved) as f64).sqrt();
        assert!(
            moved == 9 && (0.4e-3..2.5e-3).contains(&rms),
            "{moved} {rms}"
        );
    }

    #[test]
    fn a_registered_scan_keeps_its_landmarks_and_every_stamped_vertex_is_exact() {
        // A 7 × 7 cantilever (bent out of plane) scanned from its 13 × 13 solve.
        let progress = Progress::quiet();
        let mut cfg = config(2, 0.0);
        cfg.swatch.n = 7;
        cfg.swatch.gravity = [0.0, 0.0, -9.81];
        cfg.scenarios = vec![Scenario::Cantilever];
        let cloth = XpbdCloth::grid(7, 7, 0.1, 0.1, 0.224).unwrap();
        let sc = &cfg.scenarios[0];
        let sampled = make_target(&cfg, &cloth, sc, 0, &progress).unwrap();
        assert!(sampled.registration.is_none());
        let drop = sampled.x.iter().map(|p| -p[2]).fold(0.0, f64::max);
        assert!(drop > 0.02, "the cantilever drops {drop} m");
        // Every vertex stamped: the registration is the sampling.
        cfg.targets.stamp = 1;
        let all = make_target(&cfg, &cloth, sc, 0, &progress).unwrap();
        assert_eq!(all.x, sampled.x);
        let err = all.registration.unwrap();
        assert_eq!((err.max, err.landmarks, err.projected), (0.0, 49, 0));
        // Every other row and column: 16 stamped vertices (4 of them on the clamped first
        // row) and 10 more clamped ones keep their positions; the others are registered.
        cfg.targets.stamp = 2;
        let reg = make_target(&cfg, &cloth, sc, 0, &progress).unwrap();
        let err = reg.registration.unwrap();
        assert_eq!(err.landmarks, 26);
        for k in 0..49 {
            let (r, c) = (k / 7, k % 7);
            if (r % 2 == 0 && c % 2 == 0) || r < 2 {
                assert_eq!(reg.x[k], sampled.x[k], "landmark {k}");
            }
        }
        assert!(
            err.projected > 0 && err.max > 0.0 && err.max < 0.02,
            "{err:?}"
        );
    }
}
