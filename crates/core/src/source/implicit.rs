//! Implicit Euler for the FEM cloth, as energy minimisation (Martin et al. 2011; the
//! full-space simulator of the latent-dynamics paper, `002`, §3.1, Eq. 1):
//!
//! `x_t = argmin_x Φ(x)`, `Φ(x) = (1/2h²)(x − x̃)ᵀM(x − x̃) + E(x) − Σᵢ mᵢ g·xᵢ`,
//! `x̃ = 2x_{t−1} − x_{t−2}`,
//!
//! with `E` the [`FemCloth`]'s membrane and bending energy and the pinned vertices as Dirichlet
//! conditions (their degrees of freedom are removed and set to their prescribed positions).
//! Newton's method with the element Hessian blocks projected to positive semi-definite
//! (Teran et al. 2005), a banded Cholesky factorisation of the assembled system (the grid's
//! vertex order keeps the band narrow) and a backtracking (Armijo) line search on `Φ`.
//! Implicit Euler dissipates: without forcing, the energy of the discrete motion decreases.

use std::borrow::Cow;

use anyhow::{Result, bail};
use nalgebra::{DMatrix, SymmetricEigen};
use serde::{Deserialize, Serialize};

use super::fem::{FemCloth, HessianBlock};
use crate::cloth::band::BandMatrix;
use crate::cloth::triangles::V3;

/// Newton's stopping rule and budget (`[solver]` of the latent configs).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct NewtonConfig {
    /// Stop when the largest force residual `|∂Φ/∂xᵢ|` over the free vertices falls below
    /// this fraction of the heaviest vertex's weight `max mᵢ|g|` (with `|g| ≥ 1` m/s²).
    pub tolerance: f64,
    /// At most this many Newton iterations per step; not converging is an error.
    pub max_iterations: usize,
    /// Try the exact Hessian first, and fall back to the PSD-projected one in a Newton
    /// iteration where the assembled system is not positive definite. Projection keeps every step a descent step, but where elements
    /// are compressed (wrinkles) it turns Newton into a slow linear iteration; near a stable
    /// equilibrium the exact Hessian converges quadratically (static targets use it).
    pub exact_hessian: bool,
}

impl Default for NewtonConfig {
    /// `1e-4` of a vertex's weight, 50 iterations.
    fn default() -> Self {
        Self {
            tolerance: 1e-4,
            max_iterations: 50,
            exact_hessian: false,
        }
    }
}

impl NewtonConfig {
    /// Checks ranges; errors name the key.
    pub fn validate(&self) -> Result<()> {
        if !(self.tolerance > 0.0 && self.tolerance.is_finite()) {
            bail!("solver.tolerance must be positive, is {}", self.tolerance);
        }
        if self.max_iterations == 0 {
            bail!("solver.max_iterations must be at least 1");
        }
        Ok(())
    }
}

/// What one implicit step did.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepReport {
    /// Newton iterations taken.
    pub iterations: usize,
    /// Largest force residual over the free vertices at the end, N.
    pub residual: f64,
}

/// The implicit-Euler stepper of a [`FemCloth`] with time step `dt`.
#[derive(Debug, Clone)]
pub struct ImplicitEuler {
    /// The cloth: energies, masses and gravity.
    pub cloth: FemCloth,
    /// Time step `h`, s.
    pub dt: f64,
    /// Newton's settings.
    pub newton: NewtonConfig,
}

impl ImplicitEuler {
    /// A stepper; fails on a non-positive step.
    pub fn new(cloth: FemCloth, dt: f64, newton: NewtonConfig) -> Result<Self> {
        if !(dt > 0.0 && dt.is_finite()) {
            bail!("the implicit step needs a positive time step, got {dt}");
        }
        newton.validate()?;
        Ok(Self { cloth, dt, newton })
    }

    /// `Φ(x)` of the step towards `x_tilde`, J.
    pub fn potential(&self, x: &[V3], x_tilde: &[V3]) -> f64 {
        let g = self.cloth.gravity();
        let h2 = self.dt * self.dt;
        let mut phi = self.cloth.energy(x);
        for ((xi, ti), &m) in x.iter().zip(x_tilde).zip(self.cloth.masses()) {
            let mut d2 = 0.0;
            for c in 0..3 {
                d2 += (xi[c] - ti[c]).powi(2);
                phi -= m * g[c] * xi[c];
            }
            phi += 0.5 * m * d2 / h2;
        }
        phi
    }

    /// `∂Φ/∂x` at `x`, N.
    pub fn gradient(&self, x: &[V3], x_tilde: &[V3]) -> Vec<V3> {
        let n = x.len();
        let mut forces = vec![[0.0; 3]; n];
        self.cloth
            .internal_forces(x, &vec![[0.0; 3]; n], &mut forces);
        let g = self.cloth.gravity();
        let h2 = self.dt * self.dt;
        (0..n)
            .map(|i| {
                let m = self.cloth.masses()[i];
                [0, 1, 2].map(|c| m * (x[i][c] - x_tilde[i][c]) / h2 - forces[i][c] - m * g[c])
            })
            .collect()
    }

    /// One step: the positions at `t` from those at `t − 1` and `t − 2`, with vertex
    /// `pinned[k]` held at `targets[k]`.
    pub fn step(
        &self,
        prev: &[V3],
        prev2: &[V3],
        pinned: &[usize],
        targets: &[V3],
    ) -> Result<(Vec<V3>, StepReport)> {
        let n = prev.len();
        if prev2.len() != n || pinned.len() != targets.len() {
            bail!("implicit step: mismatched state sizes");
        }
        let x_tilde: Vec<V3> = (0..n)
            .map(|i| [0, 1, 2].map(|c| 2.0 * prev[i][c] - prev2[i][c]))
            .collect();
        let mut x = x_tilde.clone();
        let mut fixed = vec![false; n];
        for (&i, t) in pinned.iter().zip(targets) {
            x[i] = *t;
            fixed[i] = true;
        }
        // Free vertex i has degrees of freedom 3 · slot[i] + c.
        let mut slot = vec![usize::MAX; n];
        let mut free = 0;
        for i in 0..n {
            if !fixed[i] {
                slot[i] = free;
                free += 1;
            }
        }
        let gnorm = self
            .cloth
            .gravity()
            .iter()
            .map(|c| c * c)
            .sum::<f64>()
            .sqrt();
        let heaviest = self.cloth.masses().iter().copied().fold(0.0, f64::max);
        let tol = self.newton.tolerance * heaviest * gnorm.max(1.0);
        let residual = |g: &[V3]| {
            (0..n)
                .filter(|&i| !fixed[i])
                .flat_map(|i| g[i])
                .fold(0.0f64, |m, v| m.max(v.abs()))
        };
        let mut phi = self.potential(&x, &x_tilde);
        for iteration in 0..self.newton.max_iterations {
            let grad = self.gradient(&x, &x_tilde);
            let r = residual(&grad);
            if !r.is_finite() {
                bail!("implicit step diverged: the force residual is {r}");
            }
            if r <= tol {
                return Ok((
                    x,
                    StepReport {
                        iterations: iteration,
                        residual: r,
                    },
                ));
            }
            let minus_grad: Vec<f64> = (0..n)
                .filter(|&i| !fixed[i])
                .flat_map(|i| grad[i].map(|v| -v))
                .collect();
            let blocks = self.cloth.hessian_blocks(&x);
            let mut rhs = minus_grad.clone();
            let exact = self.newton.exact_hessian
                && self
                    .assemble(&blocks, &slot, free, false)
                    .solve(&mut rhs)
                    .is_ok();
            if !exact {
                rhs = minus_grad;
                self.assemble(&blocks, &slot, free, true).solve(&mut rhs)?;
            }
            let slope: f64 = (0..n)
                .filter(|&i| !fixed[i])
                .map(|i| {
                    (0..3)
                        .map(|c| grad[i][c] * rhs[3 * slot[i] + c])
                        .sum::<f64>()
                })
                .sum();
            let mut alpha = 1.0;
            let mut accepted = false;
            for _ in 0..40 {
                let trial: Vec<V3> = (0..n)
                    .map(|i| match fixed[i] {
                        true => x[i],
                        false => [0, 1, 2].map(|c| x[i][c] + alpha * rhs[3 * slot[i] + c]),
                    })
                    .collect();
                let p = self.potential(&trial, &x_tilde);
                if p <= phi + 1e-4 * alpha * slope {
                    x = trial;
                    phi = p;
                    accepted = true;
                    break;
                }
                alpha *= 0.5;
            }
            if !accepted {
                // At round-off level Φ cannot decrease any more: accept the point when its
                // residual is small compared with the tolerance's scale, else give up.
                if r <= 1e3 * tol {
                    return Ok((
                        x,
                        StepReport {
                            iterations: iteration + 1,
                            residual: r,
                        },
                    ));
                }
                bail!(
                    "implicit step: the line search found no decrease (force residual {r:.3e} N, \
                     tolerance {tol:.3e} N)"
                );
            }
        }
        let r = residual(&self.gradient(&x, &x_tilde));
        if r <= tol {
            return Ok((
                x,
                StepReport {
                    iterations: self.newton.max_iterations,
                    residual: r,
                },
            ));
        }
        bail!(
            "implicit step: Newton did not converge in {} iterations (force residual {r:.3e} N, \
             tolerance {tol:.3e} N); raise solver.max_iterations or lower the time step",
            self.newton.max_iterations
        )
    }

    /// `M/h²` plus the element blocks, PSD-projected with `project`, over the free degrees of
    /// freedom.
    fn assemble(
        &self,
        blocks: &[HessianBlock],
        slot: &[usize],
        free: usize,
        project: bool,
    ) -> BandMatrix {
        let blocks: Vec<(&HessianBlock, Cow<'_, [f64]>)> = blocks
            .iter()
            .map(|b| {
                let p = match project {
                    true => Cow::Owned(project_psd(&b.matrix, 3 * b.vertices.len())),
                    false => Cow::Borrowed(b.matrix.as_slice()),
                };
                (b, p)
            })
            .collect();
        let bw = blocks
            .iter()
            .map(|(b, _)| {
                let s: Vec<usize> = b
                    .vertices
                    .iter()
                    .filter(|&&v| slot[v] != usize::MAX)
                    .map(|&v| slot[v])
                    .collect();
                match (s.iter().min(), s.iter().max()) {
                    (Some(lo), Some(hi)) => 3 * (hi - lo) + 2,
                    _ => 0,
                }
            })
            .max()
            .unwrap_or(0)
            .max(2);
        let mut a = BandMatrix::zeros(3 * free, bw);
        let h2 = self.dt * self.dt;
        for (i, &m) in self.cloth.masses().iter().enumerate() {
            if slot[i] != usize::MAX {
                for c in 0..3 {
                    a.add(3 * slot[i] + c, 3 * slot[i] + c, m / h2);
                }
            }
        }
        for (b, p) in &blocks {
            let m = 3 * b.vertices.len();
            for (ki, &vi) in b.vertices.iter().enumerate() {
                if slot[vi] == usize::MAX {
                    continue;
                }
                for (kj, &vj) in b.vertices.iter().enumerate() {
                    if slot[vj] == usize::MAX {
                        continue;
                    }
                    for ci in 0..3 {
                        for cj in 0..3 {
                            let (row, col) = (3 * slot[vi] + ci, 3 * slot[vj] + cj);
                            if row >= col {
                                a.add(row, col, p[(3 * ki + ci) * m + 3 * kj + cj]);
                            }
                        }
                    }
                }
            }
        }
        a
    }
}

/// The nearest positive semi-definite matrix (negative eigenvalues set to zero) of a symmetric
/// `m × m` row-major matrix.
pub(crate) fn project_psd(matrix: &[f64], m: usize) -> Vec<f64> {
    let eig = SymmetricEigen::new(DMatrix::from_row_slice(m, m, matrix));
    if eig.eigenvalues.iter().all(|&l| l >= 0.0) {
        return matrix.to_vec();
    }
    let clamped = eig.eigenvalues.map(|l| l.max(0.0));
    let p = &eig.eigenvectors * DMatrix::from_diagonal(&clamped) * eig.eigenvectors.transpose();
    let mut out = vec![0.0; m * m];
    for i in 0..m {
        for j in 0..m {
            out[i * m + j] = p[(i, j)];
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn psd_projection_clamps_negative_eigenvalues_only() {
        let a = [2.0, 0.0, 0.0, -1.0];
        assert_eq!(project_psd(&a, 2), vec![2.0, 0.0, 0.0, 0.0]);
        let spd = [2.0, 1.0, 1.0, 2.0];
        assert_eq!(project_psd(&spd, 2), spd.to_vec());
    }
}
