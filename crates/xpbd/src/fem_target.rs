//! Static targets from another simulator: the FEM source's cloth (`source::fem`, a StVK
//! membrane of triangles and its own dihedral bending with length-and-area hinge weights)
//! brought to equilibrium by Newton's method (`source::implicit`), on a grid finer than the
//! fit's, standing in for the FEM-generated targets of paper 001 §5.
//!
//! The FEM membrane is isotropic, so a target of this kind needs an isotropic `[truth]`
//! (`e_u = e_v`, `mu = E / 2(1 + ν)`). Its bending is another discretisation than the XPBD
//! hinges (`½ b θ²` per hinge): the FEM's `k_b θ²` with `k_b = 3 B ℓ² / (A₁ + A₂)` equals the
//! XPBD hinge of an axis-aligned grid edge for `B = b / 6`, and is twice that across the
//! diagonals, so the fitted `b` need not equal the truth's; the re-simulated shape is the test.
//!
//! The equilibrium is a sequence of proximal Newton solves: implicit-Euler steps of `STEP` s
//! with no momentum (`x̃ = x`), each minimising `E(x) − Σ mᵢ g·xᵢ + ‖x − x̃‖²_M / 2h²` with the
//! clamps as Dirichlet conditions (the exact Hessian; in a Newton iteration where it is not
//! positive definite, every element block projected),
//! until a step moves no vertex by more than `1e-10` of the swatch — in practice until Newton
//! finds the start of a step already within its tolerance, a force residual of `1e-6` of the
//! heaviest vertex's weight on every free vertex (`1e-5`, `1e-4`, `1e-3` where Newton stalls
//! above that: round-off, or on finer grids slow convergence in the wrinkles). A fixed point of that map is an equilibrium of the cloth.

use anyhow::{Result, bail};

use super::cloth::XpbdCloth;
use super::material::Gamma;
use super::scenario::Setup;
use springtime_core::cloth::triangles::{V3, dot};
use springtime_core::cloth::{Diagonal, grid_triangles};
use springtime_core::source::fem::{FemCloth, FemMaterial, Membrane};
use springtime_core::source::implicit::{ImplicitEuler, NewtonConfig};

/// The proximal step, s: long enough that the inertia term only regularises the flat sheet's
/// singular out-of-plane directions.
const STEP: f64 = 0.01;

/// At most this many proximal steps.
const MAX_STEPS: usize = 20_000;

/// Newton's tolerances, tightest first (fractions of the heaviest vertex's weight).
const TOLERANCES: [f64; 4] = [1e-6, 1e-5, 1e-4, 1e-3];

/// A target whose relative residual `‖∇E − f‖ / ‖f‖` is above this gets a warning (measured:
/// 2e-6 to 5e-5 on the `xpbd_fem` targets, whose per-vertex forces are within the tolerance).
pub const WARN_RESIDUAL: f64 = 1e-4;

/// How [`settle`] ended.
enum Settled {
    /// A step moved no vertex by more than the threshold.
    AtRest,
    /// Newton failed at this tolerance; `x` is where it stood.
    Stalled(anyhow::Error),
}

/// Proximal steps from `x` until one moves no vertex by more than `still`; an error when
/// `MAX_STEPS` do not get there.
fn settle(
    stepper: &ImplicitEuler,
    x: &mut Vec<V3>,
    pinned: &[usize],
    at: &[V3],
    still: f64,
) -> Result<Settled> {
    for _ in 0..MAX_STEPS {
        let next = match stepper.step(x, x, pinned, at) {
            Ok((next, _)) => next,
            Err(e) => return Ok(Settled::Stalled(e.context("a Newton solve failed"))),
        };
        let moved = x
            .iter()
            .zip(&next)
            .map(|(a, b)| (0..3).map(|c| (a[c] - b[c]).abs()).fold(0.0, f64::max))
            .fold(0.0, f64::max);
        *x = next;
        if moved <= still {
            return Ok(Settled::AtRest);
        }
    }
    bail!("FEM target: not at rest after {MAX_STEPS} proximal steps of {STEP} s")
}

/// A target solved by the FEM cloth: positions on the fine grid, the relative equilibrium
/// residual `‖∇E − f‖ / ‖f‖` over the free vertices, and the magnitude of each clamp group's
/// reaction, N.
#[derive(Debug, Clone)]
pub struct FemTarget {
    /// Positions on the fine grid.
    pub x: Vec<V3>,
    /// Relative equilibrium residual.
    pub residual: f64,
    /// Reaction magnitudes of the setup's groups, N.
    pub reactions: Vec<f64>,
}

/// Young's modulus (N/m) and Poisson ratio of an isotropic γ; an error names `[truth]`
/// otherwise.
fn isotropic(truth: &Gamma) -> Result<(f64, f64)> {
    // To the digits a config holds (`mu = 76923` for E = 2e5, ν = 0.3 is 1e-6 off).
    let close = |a: f64, b: f64| (a - b).abs() <= 1e-5 * a.abs().max(b.abs());
    let nu = truth.c01 / truth.c00;
    let youngs = truth.c00 * (1.0 - nu * nu);
    if !close(truth.c00, truth.c11) || !close(truth.c22, youngs / (2.0 * (1.0 + nu))) {
        bail!(
            "`targets.simulator = \"fem\"`: the FEM cloth is isotropic, but `[truth]` is not \
             (C00 {:.4e}, C11 {:.4e}, C22 {:.4e} N/m; an isotropic one has C00 = C11 and \
             C22 = E / 2(1 + ν)): set e_u = e_v and mu = E / (2 (1 + nu))",
            truth.c00,
            truth.c11,
            truth.c22
        );
    }
    Ok((youngs, nu))
}

/// The equilibrium of `setup` on the FEM cloth over `fine`'s `n × n` grid (same triangles and
/// lumped masses) with the material `truth` and gravity `gravity`.
pub fn solve(
    fine: &XpbdCloth,
    n: usize,
    truth: &Gamma,
    density: f64,
    gravity: V3,
    setup: &Setup,
) -> Result<FemTarget> {
    let (youngs, nu) = isotropic(truth)?;
    if setup.load.added_mass.iter().any(|&m| m > 0.0) {
        bail!(
            "`targets.simulator = \"fem\"` does not hang weights (the FEM cloth carries gravity \
             only): use the XPBD targets for `hanging_weight`"
        );
    }
    if setup.load.contact.is_some() {
        bail!(
            "`targets.simulator = \"fem\"` has no contact (its Newton solve knows no collider): \
             use the XPBD targets for `ledge_drape`"
        );
    }
    let triangles = grid_triangles(n, n, Diagonal::Alternating);
    let cloth = FemCloth::new(
        fine.rest_uv.clone(),
        &triangles,
        &vec![youngs; triangles.len()],
        FemMaterial {
            poisson: nu,
            bending: truth.b / 6.0,
            strain_damping: 0.0,
            membrane: Membrane::Stvk,
            areal_density: density,
            rayleigh: 0.0,
            gravity,
        },
    );
    let (pinned, at): (Vec<usize>, Vec<V3>) = setup
        .load
        .clamped
        .iter()
        .enumerate()
        .filter_map(|(i, c)| c.map(|p| (i, p)))
        .unzip();
    let size = fine.rest_uv.iter().flat_map(|p| *p).fold(0.0f64, f64::max);
    let mut stepper = ImplicitEuler::new(
        cloth,
        STEP,
        NewtonConfig {
            tolerance: TOLERANCES[0],
            max_iterations: 200,
            exact_hessian: true,
        },
    )?;
    // The tightest tolerance Newton reaches: a wrinkled equilibrium's force residual can stall
    // at round-off above it, and then the next looser one carries on from where it stalled.
    // Running out of proximal steps is not a stall: that is an error at once.
    let mut x = setup.start.clone();
    let mut failures = Vec::new();
    for &tolerance in &TOLERANCES {
        stepper.newton.tolerance = tolerance;
        match settle(&stepper, &mut x, &pinned, &at, 1e-10 * size)? {
            Settled::AtRest => {
                failures.clear();
                break;
            }
            Settled::Stalled(e) => failures.push(format!("at {tolerance:e}: {e:#}")),
        }
    }
    if !failures.is_empty() {
        bail!(
            "FEM target: Newton stalls at every tolerance (fractions of the heaviest vertex's \
             weight): {}",
            failures.join("; ")
        );
    }
    // ∇E = −(internal forces); the load's forces are gravity on the same lumped masses.
    let mut grad = vec![[0.0; 3]; x.len()];
    stepper
        .cloth
        .internal_forces(&x, &vec![[0.0; 3]; x.len()], &mut grad);
    let grad: Vec<V3> = grad.iter().map(|f| f.map(|c| -c)).collect();
    let reactions = setup
        .groups
        .iter()
        .map(|g| {
            let r = setup.load.reaction(&grad, g);
            dot(r, r).sqrt()
        })
        .collect();
    Ok(FemTarget {
        residual: setup.load.residual(&grad),
        x,
        reactions,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cloth::Solve;
    use crate::equilibrium::polish;
    use crate::scenario::{Axis, Scenario};

    const G: V3 = [0.0, 0.0, -9.81];

    /// Without bending the FEM's StVK membrane is the XPBD membrane's energy exactly (same
    /// triangles and masses), so where the equilibrium is unique (stretched between two edges,
    /// no slack) the two simulators must land on the same shape and reactions by their
    /// different solvers. (A corner pull leaves slack cloth, whose shape zero bending does not
    /// determine.)
    #[test]
    fn without_bending_the_fem_target_is_the_xpbd_equilibrium() {
        let (n, size, density) = (5, 0.1, 0.224);
        let cloth = XpbdCloth::grid(n, n, size, size, density).unwrap();
        let gamma = Gamma::isotropic(200.0, 0.3, 0.0);
        for sc in [
            Scenario::Stretch {
                strain: 0.03,
                axis: Axis::V,
            },
            Scenario::Stretch {
                strain: 0.05,
                axis: Axis::U,
            },
        ] {
            let setup = sc.setup(&cloth, n, size, G, 0.0, 0);
            let fem = solve(&cloth, n, &gamma, density, G, &setup).unwrap();
            let lightest = cloth.mass.iter().copied().fold(f64::INFINITY, f64::min);
            let xpbd_solve = Solve {
                dt: (0.1 * lightest / gamma.c00).sqrt(),
                steps: 4000,
                ..Solve::auto()
            };
            let mut x = cloth
                .solve(&gamma, &setup.load, &setup.start, &xpbd_solve)
                .unwrap()
                .x;
            let residual = polish(&cloth, &gamma, &setup.load, &mut x, 50, 1e-12).unwrap();
            assert!(residual < 1e-8, "{}: XPBD residual {residual}", sc.name());
            let worst = x
                .iter()
                .zip(&fem.x)
                .flat_map(|(a, b)| (0..3).map(move |c| (a[c] - b[c]).abs()))
                .fold(0.0, f64::max);
            assert!(worst < 1e-6 * size, "{}: {worst} m apart", sc.name());
            for (g, r) in setup.groups.iter().zip(&fem.reactions) {
                let want = cloth.reaction(&gamma, &setup.load, &x, g);
                let want = dot(want, want).sqrt();
                assert!(
                    (r - want).abs() <= 1e-5 * want,
                    "{}: reaction {r} vs {want}",
                    sc.name()
                );
            }
        }
    }

    #[test]
    fn an_orthotropic_truth_or_a_weight_is_refused_by_name() {
        let (n, size) = (4, 0.1);
        let cloth = XpbdCloth::grid(n, n, size, size, 0.2).unwrap();
        let stretch = Scenario::Stretch {
            strain: 0.01,
            axis: Axis::U,
        }
        .setup(&cloth, n, size, G, 0.0, 0);
        let orthotropic = Gamma::from_engineering(100.0, 280.0, 40.0, 0.4, 5e-6);
        let err = solve(&cloth, n, &orthotropic, 0.2, G, &stretch).unwrap_err();
        assert!(err.to_string().contains("[truth]"), "{err}");
        let hanging = Scenario::HangingWeight { mass: 0.01 }.setup(&cloth, n, size, G, 0.0, 0);
        let iso = Gamma::isotropic(200.0, 0.3, 5e-6);
        let err = solve(&cloth, n, &iso, 0.2, G, &hanging).unwrap_err();
        assert!(err.to_string().contains("hanging_weight"), "{err}");
    }
}
