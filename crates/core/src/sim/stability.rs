//! The explicit-step stability guard.
//!
//! Semi-implicit Euler on `ẍ = −ω² x − γ ẋ` is stable iff `dt²ω² + 2·dt·γ < 4`. For a spring
//! network at rest the stiffest mode has `ω² = λ_max(Σ k_s u_s u_sᵀ)/m` and the fastest damping
//! rate `γ = (λ_max(Σ b_s u_s u_sᵀ) + c)/m`, with `u_s` the unit rest direction of spring `s`
//! (both found by power iteration on the grid). Using the two largest eigenvalues separately is
//! an upper bound of the true joint mode, so the guard errs on the safe side.

use crate::cloth::Topology;

/// The stability estimate of a spring network at a time step.
#[derive(Debug, Clone, PartialEq)]
pub struct Stability {
    /// Integration step, s.
    pub dt: f64,
    /// Particle mass, kg.
    pub mass: f64,
    /// Largest `ω²` of the stiffness matrix, 1/s².
    pub omega2: f64,
    /// Largest damping rate `γ` including Rayleigh damping, 1/s.
    pub gamma: f64,
    /// The material behind `ω²` and `γ`, in words (reported in messages).
    pub parameters: String,
}

/// The Gershgorin bound of the curvature elements' stiffness matrix `Σ κ_t a aᵀ` (`a = (1, −2,
/// 1)` on `(i, j, l)`): its largest absolute row sum, `max_p Σ_t 4 |a_p| κ_t` (negative `κ` count
/// as zero); 64 κ inside a grid with row, column and diagonal elements.
pub fn curvature_bound(triples: &[[usize; 3]], kappa: &[f64], particles: usize) -> f64 {
    let mut row = vec![0.0; particles];
    for (&[i, j, l], &k) in triples.iter().zip(kappa) {
        let k = 4.0 * k.max(0.0);
        row[i] += k;
        row[j] += 2.0 * k;
        row[l] += k;
    }
    row.iter().copied().fold(0.0, f64::max)
}

impl Stability {
    /// Estimates the stiffest mode of `topology` with per-spring `k`, `b` (negative values count
    /// as zero), particle `mass` and Rayleigh constant `rayleigh`, at step `dt`.
    pub fn estimate(
        topology: &Topology,
        k: &[f64],
        b: &[f64],
        mass: f64,
        rayleigh: f64,
        dt: f64,
    ) -> Self {
        let pos = |v: &[f64]| v.iter().map(|x| x.max(0.0)).collect::<Vec<_>>();
        let (k, b) = (pos(k), pos(b));
        // The two power iterations are independent: side by side.
        let (k_eig, b_eig) = rayon::join(
            || topology.max_eigenvalue(&k),
            || topology.max_eigenvalue(&b),
        );
        let omega2 = k_eig / mass;
        let gamma = (b_eig + rayleigh.max(0.0)) / mass;
        let max = |v: &[f64]| v.iter().copied().fold(0.0, f64::max);
        let (k_max, b_max) = (max(&k), max(&b));
        Self {
            dt,
            mass,
            omega2,
            gamma,
            parameters: format!(
                "largest k = {k_max:.4} N/m (k/m = {:.4e}), largest b = {b_max:.4} N·s/m \
                 (b/m = {:.4e})",
                k_max / mass,
                b_max / mass
            ),
        }
    }

    /// The same estimate with the curvature elements `triples` of stiffness `kappa` added to
    /// `ω²` (negative values count as zero): their stiffness matrix `Σ κ_t a aᵀ`, `a = (1, −2,
    /// 1)` on `(i, j, l)`, is bounded by its largest absolute row sum (Gershgorin), `max_p Σ_t
    /// 4 |a_p| κ_t`, and the largest eigenvalue of a sum of positive semi-definite matrices by
    /// the sum of theirs, so the bound stays on the safe side.
    pub fn with_curvature(
        mut self,
        triples: &[[usize; 3]],
        kappa: &[f64],
        particles: usize,
    ) -> Self {
        if triples.is_empty() {
            return self;
        }
        let bound = curvature_bound(triples, kappa, particles);
        let max = kappa.iter().copied().fold(0.0, f64::max);
        self.omega2 += bound / self.mass;
        self.parameters
            .push_str(&format!(", largest curvature κ = {max:.4} N/m"));
        self
    }

    /// `dt²ω² + 2·dt·γ`: the step is stable while this is below 4.
    pub fn number(&self) -> f64 {
        self.number_at(self.dt)
    }

    /// The stability number at another step `dt`: `ω²` and `γ` do not depend on it, so one
    /// estimate serves every substep count.
    pub fn number_at(&self, dt: f64) -> f64 {
        dt * dt * self.omega2 + 2.0 * dt * self.gamma
    }

    /// Whether the stiffness term `dt²ω²` of the stability number at step `dt` is at least its
    /// damping term `2·dt·γ`: the stiffness, not the damping, limits the step.
    pub fn stiffness_limits_at(&self, dt: f64) -> bool {
        dt * dt * self.omega2 >= 2.0 * dt * self.gamma
    }

    /// The fewest of `substeps` per `frame_dt` frame whose step keeps the stability number at or
    /// below `target`, or `None` where none does.
    pub fn fewest_substeps(
        &self,
        frame_dt: f64,
        substeps: std::ops::RangeInclusive<usize>,
        target: f64,
    ) -> Option<usize> {
        substeps
            .into_iter()
            .find(|&n| self.number_at(frame_dt / n as f64) <= target)
    }

    /// Whether the step is stable.
    pub fn is_stable(&self) -> bool {
        self.number() < 4.0
    }

    /// The largest step with `dt²ω² + 2·dt·γ = 4`.
    pub fn max_stable_dt(&self) -> f64 {
        if self.omega2 <= 0.0 {
            return if self.gamma > 0.0 {
                2.0 / self.gamma
            } else {
                f64::INFINITY
            };
        }
        (-self.gamma + (self.gamma * self.gamma + 4.0 * self.omega2).sqrt()) / self.omega2
    }

    /// A one-line account of the estimate.
    pub fn describe(&self) -> String {
        format!(
            "dt = {:.3e} s, particle mass m = {:.4e} kg, {}, stiffest mode ω² = {:.4e}/s², \
             damping rate γ = {:.4e}/s: dt²ω² + 2·dt·γ = {:.3} (stable below 4; largest stable \
             dt = {:.3e} s)",
            self.dt,
            self.mass,
            self.parameters,
            self.omega2,
            self.gamma,
            self.number(),
            self.max_stable_dt()
        )
    }

    /// `Ok` when stable (or `allow` is set); otherwise an error that names the values, the
    /// largest stable step and the override.
    pub fn check(&self, what: &str, allow: bool) -> anyhow::Result<()> {
        if self.is_stable() || allow {
            return Ok(());
        }
        anyhow::bail!(
            "{what}: the explicit step is unstable: {}. Use a smaller step (more `sim.substeps`), \
             heavier particles (larger total mass) or smaller k/b; set `sim.allow_unstable = true` \
             to run anyway",
            self.describe()
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cloth::GridSpec;

    #[test]
    fn paper_values_need_heavy_particles() {
        // 15.5 m sheet, 32 × 32, areal density 0.2 kg/m²: m ≈ 0.0469 kg, k ≤ 100, b = 6.
        let topo = Topology::grid(&GridSpec::default(), 15.5, 15.5);
        let s = topo.num_springs();
        let m = 0.2 * 15.5 * 15.5 / 1024.0;
        let st = Stability::estimate(&topo, &vec![100.0; s], &vec![6.0; s], m, 0.1, 1e-3);
        assert!((st.number() - 2.6).abs() < 0.1, "{}", st.describe());
        assert!(st.check("test", false).is_ok());
        // The literal 0.1 kg sheet is far past the limit (the peer reports ≈ 1250).
        let light = Stability::estimate(
            &topo,
            &vec![100.0; s],
            &vec![6.0; s],
            0.1 / 1024.0,
            0.1,
            1e-3,
        );
        assert!(light.number() > 1000.0);
        let err = light.check("source", false).unwrap_err().to_string();
        assert!(err.contains("largest stable dt"), "{err}");
        assert!(light.max_stable_dt() < 1e-4);
        let at_limit = Stability {
            dt: light.max_stable_dt(),
            ..light
        };
        assert!((at_limit.number() - 4.0).abs() < 1e-9);
    }

    #[test]
    fn one_estimate_finds_the_fewest_substeps_an_estimate_per_step_finds() {
        let topo = Topology::grid(&GridSpec::default(), 2.0, 2.0);
        let s = topo.num_springs();
        let (k, b) = (vec![400.0; s], vec![0.5; s]);
        let (m, frame_dt) = (0.5 / 1024.0, 0.02);
        let at = |dt: f64| Stability::estimate(&topo, &k, &b, m, 0.1, dt);
        let n = at(frame_dt)
            .fewest_substeps(frame_dt, 1..=10_000, 1.0)
            .unwrap();
        assert!(n > 1);
        assert_eq!(
            at(frame_dt / n as f64).number(),
            at(frame_dt).number_at(frame_dt / n as f64)
        );
        assert!(at(frame_dt / n as f64).number() <= 1.0);
        assert!(at(frame_dt / (n - 1) as f64).number() > 1.0);
        // None within the range: the range's end is too few.
        assert_eq!(at(frame_dt).fewest_substeps(frame_dt, 1..=n - 1, 1.0), None);
    }
}
