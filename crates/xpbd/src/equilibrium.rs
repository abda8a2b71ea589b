//! The equilibrium `∇U(x) = f` beyond XPBD's iterates: a Newton polish (so that targets and
//! fits are true equilibria, whatever XPBD's step left), and its derivatives with respect to
//! γ by the implicit-function theorem (paper 001 §3.3.2; the paper accumulates forward-mode
//! derivatives through the iterations instead — [`XpbdCloth::solve_with_derivatives`] — which
//! at a converged equilibrium give the same values, a test checks). The energy is linear in γ, `U = Σ_k γ_k U_k`, so
//! `dx_f/dγ_k = −H_ff⁻¹ ∇_f U_k` over the free coordinates `f`, and a clamp group's reaction
//! `R_G = Σ_{i∈G} (∇_i U − f_i)` changes by `Σ_{i∈G} (H_{i f} dx_f/dγ_k + ∇_i U_k)`.
//! The Hessian's columns are central differences of the exact gradient. A load's contact
//! (`super::contact`) is part of the potential, `Π = U + E_c − f·x`, and of the Hessian; it
//! does not depend on γ, so `∇U_k` stays the elastic energy's alone.

use anyhow::{Result, bail};
use nalgebra::{DMatrix, DVector};

use super::cloth::{Load, XpbdCloth};
use super::material::Gamma;
use springtime_core::cloth::band::{BandCholesky, BandLu, BandMatrix};
use springtime_core::cloth::triangles::{V3, add_to, dot};

/// The derivatives of an equilibrium with respect to γ.
#[derive(Debug, Clone)]
pub struct Sensitivity {
    /// `dx/dγ_k` for each of the five parameters, per vertex (zero on clamped vertices).
    pub dx: [Vec<V3>; 5],
    /// `dR_G/dγ_k` per clamp group (outer index: group).
    pub reactions: Vec<[V3; 5]>,
}

/// The free vertices of a load.
fn free_vertices(load: &Load) -> Vec<usize> {
    (0..load.clamped.len())
        .filter(|&i| load.clamped[i].is_none())
        .collect()
}

/// Each vertex's stencil: the vertices it shares a triangle or a hinge with, itself included
/// (the only rows of the gradient that moving it changes).
fn stencils(cloth: &XpbdCloth) -> Vec<Vec<usize>> {
    let mut out: Vec<Vec<usize>> = (0..cloth.rest_uv.len()).map(|v| vec![v]).collect();
    let elements = cloth
        .triangles
        .iter()
        .map(|t| t.v.to_vec())
        .chain(cloth.hinges.iter().map(|h| vec![h.a, h.b, h.c, h.d]));
    for e in elements {
        for &v in &e {
            out[v].extend(&e);
        }
    }
    for s in &mut out {
        s.sort_unstable();
        s.dedup();
    }
    out
}

/// The free vertices in classes whose stencils are disjoint (a greedy distance-2 colouring):
/// moving every vertex of a class at once changes each gradient row through one of them only,
/// so one gradient difference gives all their Hessian columns — bit for bit the ones moving
/// each alone gives. On a grid that is a few dozen classes whatever its size.
fn colour_classes(stencils: &[Vec<usize>], free: &[usize]) -> Vec<Vec<usize>> {
    let mut colour = vec![usize::MAX; stencils.len()];
    let mut classes: Vec<Vec<usize>> = Vec::new();
    let mut taken = Vec::new();
    for &v in free {
        taken.clear();
        for &i in &stencils[v] {
            taken.extend(stencils[i].iter().map(|&w| colour[w]));
        }
        let c = (0..).find(|c| !taken.contains(c)).unwrap_or(0);
        colour[v] = c;
        if c == classes.len() {
            classes.push(Vec::new());
        }
        classes[c].push(v);
    }
    classes
}

/// Columns `∂(∇U + ∇E_c)/∂x_j` for every free coordinate `j` (rows: every coordinate), the
/// contact of `load` included: central differences of the exact gradient, a colour class of
/// free vertices (`colour_classes`) at a time.
fn hessian_columns(
    cloth: &XpbdCloth,
    gamma: &Gamma,
    load: &Load,
    x: &[V3],
    free: &[usize],
) -> DMatrix<f64> {
    let n = x.len();
    let size = cloth
        .rest_uv
        .iter()
        .fold(0.0f64, |m, p| m.max(p[0].abs()).max(p[1].abs()))
        .max(1e-9);
    let eps = 1e-7 * size;
    let stencils = stencils(cloth);
    let mut column = vec![usize::MAX; n];
    for (col, &v) in free.iter().enumerate() {
        column[v] = col;
    }
    let mut h = DMatrix::zeros(3 * n, 3 * free.len());
    let (mut gp, mut gm) = (vec![[0.0; 3]; n], vec![[0.0; 3]; n]);
    let mut y = x.to_vec();
    for class in colour_classes(&stencils, free) {
        for c in 0..3 {
            let mut shifted = |sign: f64, g: &mut [V3]| {
                for &v in &class {
                    y[v][c] = x[v][c] + sign * eps;
                }
                cloth.gradient(gamma, &y, g);
            };
            shifted(1.0, &mut gp);
            shifted(-1.0, &mut gm);
            for &v in &class {
                y[v][c] = x[v][c];
                let col = 3 * column[v] + c;
                for &i in &stencils[v] {
                    for d in 0..3 {
                        h[(3 * i + d, col)] = (gp[i][d] - gm[i][d]) / (2.0 * eps);
                    }
                }
                // The contact's block is the moved vertex's own: one query each way, not a
                // gradient over every vertex.
                if let Some(contact) = &load.contact {
                    let (mut up, mut down) = (x[v], x[v]);
                    up[c] += eps;
                    down[c] -= eps;
                    let (gu, gd) = (
                        contact.vertex_gradient(v, up),
                        contact.vertex_gradient(v, down),
                    );
                    for d in 0..3 {
                        h[(3 * v + d, col)] += (gu[d] - gd[d]) / (2.0 * eps);
                    }
                }
            }
        }
    }
    // Symmetrise the free block (the differences are symmetric only to rounding); entries
    // outside the stencils are zero on both sides.
    for (a, &va) in free.iter().enumerate() {
        for &vb in &stencils[va] {
            let b = column[vb];
            if b == usize::MAX || b < a {
                continue;
            }
            for ca in 0..3 {
                for cb in 0..3 {
                    let (r1, c1) = (3 * va + ca, 3 * b + cb);
                    let (r2, c2) = (3 * vb + cb, 3 * a + ca);
                    let m = 0.5 * (h[(r1, c1)] + h[(r2, c2)]);
                    h[(r1, c1)] = m;
                    h[(r2, c2)] = m;
                }
            }
        }
    }
    h
}

/// The free-by-free block of [`hessian_columns`], factorised once for any number of
/// right-hand sides: banded Cholesky where it is positive definite (a stable equilibrium),
/// banded LU with partial pivoting otherwise (a saddle, a buckle in the making, or an iterate
/// off the equilibrium). The grid's vertex order keeps the band a few rows wide, so a
/// 31 × 31 swatch factorises in a tenth of a second instead of a dense LU's ten.
enum FreeSolver {
    Cholesky(BandCholesky),
    Lu(BandLu),
    Singular,
}

impl FreeSolver {
    fn new(h: &DMatrix<f64>, free: &[usize]) -> Self {
        let nf = 3 * free.len();
        let entry = |r: usize, c: usize| h[(3 * free[r / 3] + r % 3, c)];
        let bw = (0..nf)
            .flat_map(|c| (c..nf).rev().find(|&r| entry(r, c) != 0.0).map(|r| r - c))
            .max()
            .unwrap_or(0);
        let mut band = BandMatrix::zeros(nf, bw);
        for c in 0..nf {
            for r in c..(c + bw + 1).min(nf) {
                band.add(r, c, entry(r, c));
            }
        }
        match band.clone().factor() {
            Ok(l) => FreeSolver::Cholesky(l),
            Err(_) => band.lu().map_or(FreeSolver::Singular, FreeSolver::Lu),
        }
    }

    /// `H_ff⁻¹ b`, or `None` where `H_ff` is singular.
    fn solve(&self, b: &DVector<f64>) -> Option<DVector<f64>> {
        let mut x = b.clone();
        match self {
            FreeSolver::Cholesky(l) => l.solve(x.as_mut_slice()),
            FreeSolver::Lu(lu) => lu.solve(x.as_mut_slice()),
            FreeSolver::Singular => return None,
        }
        x.iter().all(|v| v.is_finite()).then_some(x)
    }
}

/// `Π(x) = U(x) + E_c(x) − f·x`, the potential whose stationary points are the equilibria.
fn potential(cloth: &XpbdCloth, gamma: &Gamma, load: &Load, x: &[V3]) -> f64 {
    cloth.energy(gamma, x) + load.contact_energy(x)
        - x.iter()
            .zip(&load.force)
            .map(|(a, b)| dot(*a, *b))
            .sum::<f64>()
}

/// Newton steps on `∇U + ∇E_c = f` from `x` (clamped vertices held), each with a backtracking line
/// search on `Π`, until the relative residual is below `tolerance` or `iterations` are done.
/// Returns the residual reached.
pub fn polish(
    cloth: &XpbdCloth,
    gamma: &Gamma,
    load: &Load,
    x: &mut [V3],
    iterations: usize,
    tolerance: f64,
) -> Result<f64> {
    let free = free_vertices(load);
    let n = x.len();
    let mut g = vec![[0.0; 3]; n];
    let mut residual = cloth.residual(gamma, load, x);
    for _ in 0..iterations {
        if residual < tolerance {
            break;
        }
        cloth.net_gradient(gamma, load, x, &mut g);
        let r = DVector::from_fn(3 * free.len(), |k, _| {
            let (v, c) = (free[k / 3], k % 3);
            g[v][c] - load.force[v][c]
        });
        let h = FreeSolver::new(&hessian_columns(cloth, gamma, load, x, &free), &free);
        let mut step = h.solve(&(-&r)).unwrap_or_else(|| -&r);
        if step.dot(&r) >= 0.0 {
            // Not a descent direction (an indefinite Hessian near a buckle): steepest descent.
            step = -&r * (1.0 / r.norm().max(1e-300)) * 1e-4;
        }
        let p0 = potential(cloth, gamma, load, x);
        let base = x.to_vec();
        let mut alpha = 1.0;
        let mut improved = false;
        for _ in 0..30 {
            for (k, &v) in free.iter().enumerate() {
                for c in 0..3 {
                    x[v][c] = base[v][c] + alpha * step[3 * k + c];
                }
            }
            if potential(cloth, gamma, load, x) <= p0 {
                improved = true;
                break;
            }
            alpha *= 0.5;
        }
        if !improved {
            x.copy_from_slice(&base);
            break;
        }
        residual = cloth.residual(gamma, load, x);
    }
    if !residual.is_finite() {
        bail!("the equilibrium polish diverged (residual {residual})");
    }
    Ok(residual)
}

/// The derivatives of the equilibrium `x` of `load` with respect to γ, and of the reactions of
/// the clamp `groups`.
pub fn sensitivity(
    cloth: &XpbdCloth,
    gamma: &Gamma,
    load: &Load,
    x: &[V3],
    groups: &[Vec<usize>],
) -> Result<Sensitivity> {
    let free = free_vertices(load);
    let n = x.len();
    let h = hessian_columns(cloth, gamma, load, x, &free);
    let hf = FreeSolver::new(&h, &free);
    let mut dx: [Vec<V3>; 5] = std::array::from_fn(|_| vec![[0.0; 3]; n]);
    let mut reactions = vec![[[0.0; 3]; 5]; groups.len()];
    let mut gk = vec![[0.0; 3]; n];
    for k in 0..5 {
        let mut unit = [0.0; 5];
        unit[k] = 1.0;
        cloth.gradient(&Gamma::from_array(unit), x, &mut gk);
        let rhs = DVector::from_fn(3 * free.len(), |j, _| -gk[free[j / 3]][j % 3]);
        let Some(sol) = hf.solve(&rhs) else {
            bail!("the equilibrium's Hessian is singular: its derivatives are undefined here");
        };
        for (j, &v) in free.iter().enumerate() {
            dx[k][v] = [sol[3 * j], sol[3 * j + 1], sol[3 * j + 2]];
        }
        let hx = &h * &sol;
        for (g, group) in groups.iter().enumerate() {
            for &i in group {
                add_to(
                    &mut reactions[g][k],
                    [0, 1, 2].map(|c| hx[3 * i + c] + gk[i][c]),
                );
            }
        }
    }
    Ok(Sensitivity { dx, reactions })
}

/// The gradient with respect to γ of a scalar `L(x, R)` of the equilibrium `x` of `load` and
/// the reaction vectors `R_G` of the clamp `groups`, given `∂L/∂x` (`grad_x`, per vertex; its
/// clamped rows are ignored) and `∂L/∂R_G` (`grad_r`, per group): the adjoint of the
/// implicit-function theorem, one linear solve whatever the number of parameters.
///
/// With `w_f = ∂L/∂x_f + Σ_G Σ_{i∈G} H_{i f}ᵀ ∂L/∂R_G` and `λ = H_ff⁻¹ w_f` (`H` symmetric),
/// `dL/dγ_k = −λᵀ ∇_f U_k + Σ_G Σ_{i∈G} ∂L/∂R_G · ∇_i U_k`.
pub fn adjoint(
    cloth: &XpbdCloth,
    gamma: &Gamma,
    load: &Load,
    x: &[V3],
    groups: &[Vec<usize>],
    grad_x: &[V3],
    grad_r: &[V3],
) -> Result<[f64; 5]> {
    let free = free_vertices(load);
    let h = hessian_columns(cloth, gamma, load, x, &free);
    let mut w = DVector::from_fn(3 * free.len(), |j, _| grad_x[free[j / 3]][j % 3]);
    for (group, gr) in groups.iter().zip(grad_r) {
        for &i in group {
            for c in 0..3 {
                w += h.row(3 * i + c).transpose() * gr[c];
            }
        }
    }
    let Some(lambda) = FreeSolver::new(&h, &free).solve(&w) else {
        bail!("the equilibrium's Hessian is singular: its derivatives are undefined here");
    };
    let mut out = [0.0; 5];
    let mut gk = vec![[0.0; 3]; x.len()];
    for (k, o) in out.iter_mut().enumerate() {
        let mut unit = [0.0; 5];
        unit[k] = 1.0;
        cloth.gradient(&Gamma::from_array(unit), x, &mut gk);
        *o = -free
            .iter()
            .enumerate()
            .map(|(j, &v)| (0..3).map(|c| lambda[3 * j + c] * gk[v][c]).sum::<f64>())
            .sum::<f64>();
        for (group, gr) in groups.iter().zip(grad_r) {
            *o += group.iter().map(|&i| dot(*gr, gk[i])).sum::<f64>();
        }
    }
    Ok(out)
}

/// The tests' sheet: 5 × 5 vertices over 10 cm, clamped along one edge and pulled sideways at
/// the other, under gravity; the pulled edge is the clamp group measured.
#[cfg(test)]
pub(crate) fn pulled_sheet() -> (XpbdCloth, Load, Vec<usize>) {
    let cloth = XpbdCloth::grid(5, 5, 0.1, 0.1, 0.2).unwrap();
    let rest = cloth.rest();
    let mut load = Load::gravity(&cloth, [0.0, 0.0, -9.81]);
    for c in 0..5 {
        load.clamped[c] = Some(rest[c]);
        load.clamped[20 + c] = Some([rest[20 + c][0] + 0.01, rest[20 + c][1] + 0.006, 0.0]);
    }
    (cloth, load, (20..25).collect())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cloth::{Solve, Sweep};

    /// The colour classes' Hessian is, bit for bit, the one moving each free vertex alone gives;
    /// the free block's banded Cholesky solves it as a dense LU does.
    #[test]
    fn the_coloured_hessian_equals_the_column_by_column_one() {
        let (cloth, load, _) = pulled_sheet();
        let gamma = Gamma::from_engineering(180.0, 500.0, 40.0, 0.3, 5e-5);
        let mut x = cloth
            .solve(&gamma, &load, &cloth.rest(), &Solve::default())
            .unwrap()
            .x;
        // Off the equilibrium and out of plane, so that every block is generic.
        for (i, p) in x.iter_mut().enumerate() {
            p[2] += 1e-3 * (i as f64 * 0.7).sin();
        }
        let free = free_vertices(&load);
        let stencils = stencils(&cloth);
        assert!(colour_classes(&stencils, &free).len() < free.len());
        let h = hessian_columns(&cloth, &gamma, &load, &x, &free);
        let big = h.amax();
        for (col, &v) in free.iter().enumerate() {
            let one = hessian_columns(&cloth, &gamma, &load, &x, &[v]);
            for c in 0..3 {
                for r in 0..3 * x.len() {
                    let (a, b) = (h[(r, 3 * col + c)], one[(r, c)]);
                    if free.contains(&(r / 3)) && r / 3 != v {
                        // Symmetrisation averages the free-free entries with their
                        // transposes: the differences' asymmetry is rounding.
                        assert!(
                            (a - b).abs() < 1e-6 * big,
                            "row {r}, vertex {v}.{c}: {a} {b}"
                        );
                    } else {
                        assert_eq!(a, b, "row {r}, vertex {v}.{c}");
                    }
                }
            }
        }
        let nf = 3 * free.len();
        let dense = DMatrix::from_fn(nf, nf, |r, c| h[(3 * free[r / 3] + r % 3, c)]);
        let b = DVector::from_fn(nf, |i, _| (i as f64).cos());
        let solver = FreeSolver::new(&h, &free);
        assert!(matches!(solver, FreeSolver::Cholesky(_)));
        let (band, lu) = (solver.solve(&b).unwrap(), dense.lu().solve(&b).unwrap());
        assert!(
            (&band - &lu).norm() < 1e-9 * lu.norm(),
            "{} vs {}",
            band.norm(),
            lu.norm()
        );
    }

    /// Forward mode through the XPBD iterations (dual numbers, as the paper) against the
    /// implicit-function theorem at the polished equilibrium, for every parameter.
    #[test]
    fn dual_number_derivatives_of_the_iterations_equal_the_implicit_ones() {
        let (cloth, load, group) = pulled_sheet();
        let gamma = Gamma::from_engineering(180.0, 500.0, 40.0, 0.3, 5e-5);
        let solve = Solve {
            steps: 6000,
            sweep: Sweep::GaussSeidel,
            tolerance: 1e-10,
            ..Solve::default()
        };
        let (eq, dual) = cloth
            .solve_with_derivatives(
                &gamma,
                &load,
                &cloth.rest(),
                &solve,
                std::slice::from_ref(&group),
            )
            .unwrap();
        // The values are the plain solve's, bit for bit.
        let plain = cloth.solve(&gamma, &load, &cloth.rest(), &solve).unwrap();
        assert_eq!(eq.x, plain.x);
        assert_eq!(eq.steps, plain.steps);
        let mut x = eq.x.clone();
        polish(&cloth, &gamma, &load, &mut x, 30, 1e-12).unwrap();
        let sens = sensitivity(&cloth, &gamma, &load, &x, std::slice::from_ref(&group)).unwrap();
        for k in 0..5 {
            let scale = sens.dx[k]
                .iter()
                .flatten()
                .fold(0.0f64, |m, v| m.max(v.abs()));
            assert!(scale > 0.0, "γ{k} moves nothing");
            let worst = (0..x.len())
                .flat_map(|i| (0..3).map(move |c| (i, c)))
                .map(|(i, c)| (dual.dx[k][i][c] - sens.dx[k][i][c]).abs())
                .fold(0.0f64, f64::max);
            // Measured: 1e-9 to 5e-7 relative (b the largest) at a residual of 6.5e-11.
            assert!(
                worst < 1e-5 * scale,
                "γ{k}: forward mode and implicit differ by {worst:e} (scale {scale:e})"
            );
            // Reactions: the change a doubling of γ_k makes, against the reaction itself (the
            // bending stiffness barely moves the pulled edge's reaction: its derivative is
            // nearly zero, and the iterate's dx errors, times the membrane's stiffness, are
            // what is left of it).
            let (fr, ir) = (dual.reactions[0][k], sens.reactions[0][k]);
            let reaction = cloth.reaction(&gamma, &load, &x, &group);
            let size = dot(reaction, reaction).sqrt();
            let gk = gamma.to_array()[k];
            for c in 0..3 {
                assert!(
                    (fr[c] - ir[c]).abs() * gk < 1e-6 * size,
                    "reaction γ{k}.{c}: forward {} vs implicit {} (reaction {size:e} N)",
                    fr[c],
                    ir[c]
                );
            }
        }
    }

    #[test]
    fn implicit_derivatives_of_the_equilibrium_equal_finite_differences() {
        let (cloth, load, group) = pulled_sheet();
        let rest = cloth.rest();
        let gamma = Gamma::from_engineering(180.0, 500.0, 40.0, 0.3, 5e-5);
        let solve = Solve {
            steps: 3000,
            sweep: Sweep::GaussSeidel,
            tolerance: 1e-9,
            ..Solve::default()
        };
        let settle = |g: &Gamma, start: &[V3]| {
            let mut x = cloth.solve(g, &load, start, &solve).unwrap().x;
            let r = polish(&cloth, g, &load, &mut x, 30, 1e-12).unwrap();
            assert!(r < 1e-9, "polished residual {r}");
            x
        };
        let x = settle(&gamma, &rest);
        let sens = sensitivity(&cloth, &gamma, &load, &x, std::slice::from_ref(&group)).unwrap();
        let params = gamma.to_array();
        for k in 0..5 {
            let step = 1e-4 * params[k];
            let (mut up, mut dn) = (params, params);
            up[k] += step;
            dn[k] -= step;
            let (xu, xd) = (
                settle(&Gamma::from_array(up), &x),
                settle(&Gamma::from_array(dn), &x),
            );
            let scale = sens.dx[k]
                .iter()
                .flatten()
                .fold(0.0f64, |m, v| m.max(v.abs()));
            assert!(scale > 0.0);
            for i in 0..x.len() {
                for c in 0..3 {
                    let fd = (xu[i][c] - xd[i][c]) / (2.0 * step);
                    assert!(
                        (fd - sens.dx[k][i][c]).abs() < 1e-3 * scale,
                        "γ{k} vertex {i}.{c}: {fd} vs {}",
                        sens.dx[k][i][c]
                    );
                }
            }
            let (ru, rd) = (
                cloth.reaction(&Gamma::from_array(up), &load, &xu, &group),
                cloth.reaction(&Gamma::from_array(dn), &load, &xd, &group),
            );
            let rscale = sens.reactions[0][k]
                .iter()
                .fold(0.0f64, |m, v| m.max(v.abs()));
            for c in 0..3 {
                let fd = (ru[c] - rd[c]) / (2.0 * step);
                assert!(
                    (fd - sens.reactions[0][k][c]).abs() < 1e-3 * rscale.max(1e-12),
                    "reaction γ{k}.{c}: {fd} vs {}",
                    sens.reactions[0][k][c]
                );
            }
        }
    }
}
