//! Levenberg–Marquardt with box constraints (the least-squares solver of paper 001, Eq. 8):
//! Marquardt's scaled damping on the normal equations, steps projected into the box, accepted
//! when the actual reduction of `½‖r‖²` is a fair share of the predicted one.

use anyhow::{Result, bail};

/// The problem: residuals `r(p)` and their Jacobian `∂r/∂p` (rows: residuals).
pub trait LeastSquares {
    /// Residuals at `p`.
    fn residuals(&mut self, p: &[f64]) -> Result<Vec<f64>>;
    /// Residuals and Jacobian at `p`.
    fn jacobian(&mut self, p: &[f64]) -> Result<(Vec<f64>, Vec<Vec<f64>>)>;
}

/// Settings of the solver.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Lm {
    /// Accepted steps at most.
    pub max_iterations: usize,
    /// Initial damping relative to the Gauss–Newton matrix's diagonal.
    pub damping: f64,
    /// Stop when a step changes every parameter by less than this fraction of its magnitude.
    pub step_tolerance: f64,
    /// Stop when an accepted step lowers the objective by less than this fraction.
    pub cost_tolerance: f64,
}

impl Default for Lm {
    fn default() -> Self {
        Self {
            max_iterations: 50,
            damping: 1e-3,
            step_tolerance: 1e-10,
            cost_tolerance: 1e-12,
        }
    }
}

/// The solver's result.
#[derive(Debug, Clone, PartialEq)]
pub struct Fit {
    /// The parameters found.
    pub p: Vec<f64>,
    /// `½‖r‖²` there.
    pub cost: f64,
    /// Accepted steps.
    pub iterations: usize,
    /// `½‖r‖²` after each accepted step, the start first.
    pub history: Vec<f64>,
}

/// Minimises `½‖r(p)‖²` over `lower ≤ p ≤ upper` from `start`.
pub fn minimize(
    problem: &mut dyn LeastSquares,
    start: &[f64],
    lower: &[f64],
    upper: &[f64],
    cfg: &Lm,
) -> Result<Fit> {
    let n = start.len();
    if lower.len() != n || upper.len() != n || (0..n).any(|i| !(lower[i] <= upper[i])) {
        bail!("the bounds must be one interval lower ≤ upper per parameter");
    }
    let clamp = |p: &mut [f64]| {
        for i in 0..n {
            p[i] = p[i].clamp(lower[i], upper[i]);
        }
    };
    let mut p = start.to_vec();
    clamp(&mut p);
    let (mut r, mut j) = problem.jacobian(&p)?;
    let cost = |r: &[f64]| 0.5 * r.iter().map(|v| v * v).sum::<f64>();
    let mut c = cost(&r);
    let mut history = vec![c];
    let mut mu = cfg.damping;
    let mut iterations = 0;
    while iterations < cfg.max_iterations {
        // Normal equations JᵀJ δ = −Jᵀr, damped by μ diag(JᵀJ).
        let mut a = vec![vec![0.0; n]; n];
        let mut g = vec![0.0; n];
        for (row, ri) in j.iter().zip(&r) {
            for i in 0..n {
                g[i] += row[i] * ri;
                for k in 0..n {
                    a[i][k] += row[i] * row[k];
                }
            }
        }
        // Parameters on a bound that the descent direction pushes outwards stay there: the
        // step is solved for the others (an active set), then projected into the box.
        let active: Vec<bool> = (0..n)
            .map(|i| (p[i] <= lower[i] && g[i] > 0.0) || (p[i] >= upper[i] && g[i] < 0.0))
            .collect();
        let mut accepted = false;
        for _ in 0..30 {
            let mut m = a.clone();
            let mut rhs: Vec<f64> = g.iter().map(|v| -v).collect();
            for i in 0..n {
                m[i][i] += mu * a[i][i].max(1e-300);
            }
            for i in (0..n).filter(|&i| active[i]) {
                for k in 0..n {
                    m[i][k] = 0.0;
                    m[k][i] = 0.0;
                }
                m[i][i] = 1.0;
                rhs[i] = 0.0;
            }
            let Some(delta) = solve(m, rhs) else {
                mu *= 10.0;
                continue;
            };
            let mut trial: Vec<f64> = p.iter().zip(&delta).map(|(a, b)| a + b).collect();
            clamp(&mut trial);
            let step: Vec<f64> = trial.iter().zip(&p).map(|(a, b)| a - b).collect();
            if step
                .iter()
                .zip(&p)
                .all(|(s, v)| s.abs() <= cfg.step_tolerance * v.abs().max(1e-300))
            {
                return Ok(Fit {
                    p,
                    cost: c,
                    iterations,
                    history,
                });
            }
            let rt = problem.residuals(&trial)?;
            let ct = cost(&rt);
            // The reduction the linear model predicts for the projected step.
            let jd: Vec<f64> = j
                .iter()
                .map(|row| row.iter().zip(&step).map(|(a, b)| a * b).sum())
                .collect();
            let predicted = c - cost(&r.iter().zip(&jd).map(|(a, b)| a + b).collect::<Vec<_>>());
            if ct.is_finite() && ct < c && (predicted <= 0.0 || (c - ct) >= 1e-4 * predicted) {
                let improvement = (c - ct) / c.max(1e-300);
                p = trial;
                (r, j) = problem.jacobian(&p)?;
                c = cost(&r);
                history.push(c);
                iterations += 1;
                mu = (mu / 3.0).max(1e-12);
                accepted = true;
                if improvement < cfg.cost_tolerance || c == 0.0 {
                    return Ok(Fit {
                        p,
                        cost: c,
                        iterations,
                        history,
                    });
                }
                break;
            }
            mu *= 4.0;
        }
        if !accepted {
            break;
        }
    }
    Ok(Fit {
        p,
        cost: c,
        iterations,
        history,
    })
}

/// Solves a small dense system (`None` when singular or not finite).
fn solve(a: Vec<Vec<f64>>, b: Vec<f64>) -> Option<Vec<f64>> {
    let n = b.len();
    let x = nalgebra::DMatrix::from_fn(n, n, |r, c| a[r][c])
        .lu()
        .solve(&nalgebra::DVector::from_vec(b))?;
    x.iter()
        .all(|v| v.is_finite())
        .then(|| x.iter().copied().collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `r = A p − y`.
    struct Linear {
        a: Vec<Vec<f64>>,
        y: Vec<f64>,
    }

    impl LeastSquares for Linear {
        fn residuals(&mut self, p: &[f64]) -> Result<Vec<f64>> {
            Ok(self
                .a
                .iter()
                .zip(&self.y)
                .map(|(row, y)| row.iter().zip(p).map(|(a, b)| a * b).sum::<f64>() - y)
                .collect())
        }
        fn jacobian(&mut self, p: &[f64]) -> Result<(Vec<f64>, Vec<Vec<f64>>)> {
            Ok((self.residuals(p)?, self.a.clone()))
        }
    }

    #[test]
    fn lm_solves_a_linear_least_squares_problem_exactly_and_respects_its_bounds() {
        let a = vec![
            vec![1.0, 2.0, 0.5],
            vec![0.3, -1.0, 2.0],
            vec![2.0, 0.1, 1.0],
            vec![1.0, 1.0, 1.0],
        ];
        let truth = [0.7, -1.3, 2.1];
        let y: Vec<f64> = a
            .iter()
            .map(|row| row.iter().zip(&truth).map(|(a, b)| a * b).sum())
            .collect();
        let mut problem = Linear { a: a.clone(), y };
        let fit = minimize(
            &mut problem,
            &[0.0; 3],
            &[-10.0; 3],
            &[10.0; 3],
            &Lm::default(),
        )
        .unwrap();
        for (p, t) in fit.p.iter().zip(truth) {
            assert!((p - t).abs() < 1e-9, "{:?}", fit.p);
        }
        assert!(fit.cost < 1e-18 && fit.iterations <= 5, "{fit:?}");
        // With the second parameter bounded below at −1, the fit stays in the box and is the
        // constrained minimum (the other two solve the reduced problem with p₁ = −1).
        let fit = minimize(
            &mut problem,
            &[0.0; 3],
            &[-10.0, -1.0, -10.0],
            &[10.0; 3],
            &Lm::default(),
        )
        .unwrap();
        assert!((fit.p[1] + 1.0).abs() < 1e-12, "{:?}", fit.p);
        let mut reduced = Linear {
            a: a.iter().map(|r| vec![r[0], r[2]]).collect(),
            y: problem.y.iter().zip(&a).map(|(y, r)| y + r[1]).collect(),
        };
        let free = minimize(
            &mut reduced,
            &[0.0; 2],
            &[-10.0; 2],
            &[10.0; 2],
            &Lm::default(),
        )
        .unwrap();
        assert!(
            (fit.p[0] - free.p[0]).abs() < 1e-6 && (fit.p[2] - free.p[1]).abs() < 1e-6,
            "{:?} vs {:?}",
            fit.p,
            free.p
        );
    }
}
