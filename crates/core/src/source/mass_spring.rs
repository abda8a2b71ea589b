//! The mass-spring source system (paper §4.1 (i)): a ground-truth spring cloth with spatially
//! varying stiffness and uniform damping, stepped in f64 with the same semi-implicit Euler as
//! the surrogate, so that a surrogate with the true `k`, `b` reproduces it exactly.

use crate::cloth::{GridSpec, SpringFamily, SpringLayout, Topology};
use crate::data::SpringTruth;
use crate::sim::Stability;

use super::{ClothSim, SourceConfig, StiffnessMap};

/// A spring cloth with known per-spring parameters.
#[derive(Debug, Clone)]
pub struct SpringCloth {
    /// Its grid.
    pub topology: Topology,
    /// Stiffness per spring, N/m.
    pub k: Vec<f64>,
    /// Damping per spring, N·s/m.
    pub b: Vec<f64>,
    /// Mean particle mass, kg (particle `i` weighs `mass · w_i` with the topology's
    /// [`Topology::mass_weight`] `w`, else `mass`).
    pub mass: f64,
    /// Rayleigh damping constant of a particle of the mean mass, N·s/m (`rayleigh · w_i` on
    /// particle `i`: damping per unit mass, as the surrogate's).
    pub rayleigh: f64,
    /// Gravity, m/s².
    pub gravity: [f64; 3],
    /// Isotropic viscosity per unit stiffness `β`, s: each spring also puts `β k_s (v_b − v_a)`
    /// on `a` and its opposite on `b` (the surrogate's `sim.viscosity`; 0 from a config).
    pub viscosity: f64,
    /// The shear springs' stiffness in compression per unit `k` (the surrogate's
    /// `sim.shear_compression`; 1, linear springs, from a config).
    pub shear_compression: f64,
}

impl SpringCloth {
    /// The source cloth of a config: the paper's grid with every spring family, `k` from the
    /// stiffness map at each spring's rest midpoint, one `b` for all.
    pub fn from_config(cfg: &SourceConfig) -> Self {
        Self::from_config_scaled(cfg, &[])
    }

    /// The spring cloth of a source config with spring `s`'s stiffness multiplied by
    /// `scale[s]` (all 1 where `scale` is empty): a perturbed copy of the source's material.
    pub(crate) fn from_config_scaled(cfg: &SourceConfig, scale: &[f64]) -> Self {
        let spec = GridSpec {
            nx: cfg.nx,
            ny: cfg.ny,
            shear_main: true,
            shear_anti: true,
            bending_stride: 2,
            layout: SpringLayout::Grid,
            ..GridSpec::default()
        };
        let topology = Topology::grid(&spec, cfg.width, cfg.height);
        let map = StiffnessMap {
            layout: cfg.layout,
            levels: cfg.stiffness_levels.clone(),
        };
        let k = (0..topology.num_springs())
            .map(|s| {
                let [u, v] = topology.midpoint(s);
                map.at(u / cfg.width, v / cfg.height)
            })
            .zip(scale.iter().chain(std::iter::repeat(&1.0)))
            .map(|(k, s)| k * s)
            .collect();
        let b = vec![cfg.damping; topology.num_springs()];
        let mass = cfg.areal_density * cfg.width * cfg.height / topology.num_particles() as f64;
        Self {
            topology,
            k,
            b,
            mass,
            rayleigh: cfg.rayleigh,
            gravity: cfg.gravity,
            viscosity: 0.0,
            shear_compression: 1.0,
        }
    }

    /// Net force on every particle at `(x, v)` (Eq. 4, Eq. 2, gravity, Rayleigh damping, the
    /// springs' viscosity, the shear springs softer in compression).
    pub fn forces(&self, x: &[[f64; 3]], v: &[[f64; 3]], out: &mut [[f64; 3]]) {
        for (i, (o, vi)) in out.iter_mut().zip(v).enumerate() {
            let w = self.weight(i);
            for c in 0..3 {
                o[c] = w * (self.gravity[c] * self.mass - self.rayleigh * vi[c]);
            }
        }
        for (s, &[a, b]) in self.topology.springs.iter().enumerate() {
            let d = [x[b][0] - x[a][0], x[b][1] - x[a][1], x[b][2] - x[a][2]];
            let w = [v[b][0] - v[a][0], v[b][1] - v[a][1], v[b][2] - v[a][2]];
            let len2 = d[0] * d[0] + d[1] * d[1] + d[2] * d[2];
            let inv = 1.0 / len2.sqrt();
            let stretch = 1.0 - self.topology.rest_length[s] * inv;
            let k = if stretch < 0.0 && self.topology.family[s] == SpringFamily::Shear {
                self.k[s] * self.shear_compression
            } else {
                self.k[s]
            };
            let coef =
                k * stretch + self.b[s] * (w[0] * d[0] + w[1] * d[1] + w[2] * d[2]) * inv * inv;
            let nu = self.viscosity * self.k[s];
            for c in 0..3 {
                out[a][c] += coef * d[c] + nu * w[c];
                out[b][c] -= coef * d[c] + nu * w[c];
            }
        }
    }
}

impl SpringCloth {
    /// Particle `i`'s mass relative to the mean.
    fn weight(&self, i: usize) -> f64 {
        self.topology.relative_mass(i)
    }
}

impl ClothSim for SpringCloth {
    fn rest_uv(&self) -> &[[f64; 2]] {
        &self.topology.rest_uv
    }

    fn particle_mass(&self) -> f64 {
        self.mass
    }

    fn mass_of(&self, i: usize) -> f64 {
        self.mass * self.weight(i)
    }

    fn net_forces(&self, x: &[[f64; 3]], v: &[[f64; 3]], out: &mut [[f64; 3]]) {
        self.forces(x, v, out);
    }

    fn stability(&self, dt: f64) -> Stability {
        // The viscosity's rate on any mode is at most that of a damper `β k` along the spring.
        let b: Vec<f64> = (self.b.iter().zip(&self.k))
            .map(|(b, k)| b + self.viscosity * k)
            .collect();
        Stability::estimate(&self.topology, &self.k, &b, self.mass, self.rayleigh, dt)
    }

    fn spring_truth(&self) -> Option<SpringTruth> {
        Some(SpringTruth {
            springs: self.topology.springs.clone(),
            k: self.k.clone(),
            b: self.b.clone(),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn internal_forces_cancel_and_vanish_at_rest() {
        let cfg = SourceConfig {
            nx: 5,
            ny: 4,
            gravity: [0.0; 3],
            rayleigh: 0.0,
            ..SourceConfig::default()
        };
        let cloth = SpringCloth::from_config(&cfg);
        let rest = cloth.topology.rest_positions();
        let zero = vec![[0.0; 3]; rest.len()];
        let mut f = vec![[0.0; 3]; rest.len()];
        cloth.forces(&rest, &zero, &mut f);
        assert!(
            f.iter().flatten().all(|c| c.abs() < 1e-12),
            "no force at rest"
        );
        let moved: Vec<[f64; 3]> = rest
            .iter()
            .enumerate()
            .map(|(i, p)| {
                [
                    p[0] * 1.1 + (i as f64).sin() * 0.05,
                    p[1],
                    (i as f64 * 0.3).cos() * 0.1,
                ]
            })
            .collect();
        let vel: Vec<[f64; 3]> = (0..rest.len())
            .map(|i| [(i as f64).cos(), 0.2, -0.1])
            .collect();
        cloth.forces(&moved, &vel, &mut f);
        let total: [f64; 3] = [0, 1, 2].map(|c| f.iter().map(|v| v[c]).sum());
        let scale: f64 = f.iter().flatten().map(|c| c.abs()).sum();
        assert!(scale > 1.0);
        assert!(total.iter().all(|c| c.abs() < 1e-9 * scale), "{total:?}");
    }
}
