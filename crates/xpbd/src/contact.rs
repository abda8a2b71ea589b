//! Contact for the quasi-static cloth: a rigid collider (the drape scenes' [`Collider`], parry3d
//! geometry) with the drapes' penalty layer, frictionless and without damping since nothing
//! moves at equilibrium. Vertex `i` of mass `m_i` at signed distance `d` (outward normal `n`)
//! stores `½ m_i κ φ²`, `φ = max(0, δ − d)`: the same contact pressure per unit mass `κ` (1/s²)
//! and thickness `δ` as [`springtime_core::sim::contact`], so a vertex resting on a surface sinks `g/κ`
//! into the layer whatever the grid. The energy is a function of the positions only, part of
//! the load's potential: the equilibrium `∇U + ∇E_c = f`, its Newton polish and its
//! implicit-function derivatives take it in through [`super::cloth::XpbdCloth::net_gradient`];
//! the XPBD steps apply its force at the start of each step.

use springtime_core::cloth::triangles::{V3, add_to, scale};
use springtime_core::sim::contact::Collider;

/// A collider under the cloth, with its penalty layer.
#[derive(Debug, Clone)]
pub struct StaticContact {
    /// The rigid body.
    pub collider: Collider,
    /// Contact thickness δ, m.
    pub thickness: f64,
    /// `m_i κ` per vertex, N/m: the vertex's mass (its lumped cloth mass and any weight hung on
    /// it) times the contact pressure per unit mass κ.
    pub stiffness: Vec<f64>,
}

impl StaticContact {
    /// Vertex `i`'s intrusion `φ = max(0, δ − d)` into the layer, m, and the outward normal.
    fn intrusion(&self, x: V3) -> (f64, V3) {
        let hit = self.collider.query(0.0, x);
        ((self.thickness - hit.distance).max(0.0), hit.normal)
    }

    /// The penalty energy `Σ ½ m_i κ φ_i²`, J.
    pub fn energy(&self, x: &[V3]) -> f64 {
        x.iter()
            .zip(&self.stiffness)
            .map(|(&p, &k)| 0.5 * k * self.intrusion(p).0.powi(2))
            .sum()
    }

    /// `∂E_c/∂x_i` of vertex `i` at `p`: `−m_i κ φ n` in the layer, zero outside (the contact
    /// force is its negative, along the normal). A vertex's term depends on its own position
    /// only, so the contact's Hessian is block diagonal.
    pub fn vertex_gradient(&self, i: usize, p: V3) -> V3 {
        let (phi, n) = self.intrusion(p);
        if phi > 0.0 {
            scale(n, -self.stiffness[i] * phi)
        } else {
            [0.0; 3]
        }
    }

    /// `out += ∇E_c` (see [`Self::vertex_gradient`]).
    pub fn add_gradient(&self, x: &[V3], out: &mut [V3]) {
        for (i, (&p, o)) in x.iter().zip(out).enumerate() {
            add_to(o, self.vertex_gradient(i, p));
        }
    }

    /// The deepest intrusion `max φ` over the vertices, m (`g/κ` for cloth resting on a top;
    /// beyond `δ`, a vertex passed the collider's surface).
    pub fn deepest(&self, x: &[V3]) -> f64 {
        x.iter().map(|&p| self.intrusion(p).0).fold(0.0, f64::max)
    }

    /// The total contact force on the cloth, N.
    pub fn force(&self, x: &[V3]) -> V3 {
        let mut f = [0.0; 3];
        for (i, &p) in x.iter().enumerate() {
            add_to(&mut f, scale(self.vertex_gradient(i, p), -1.0));
        }
        f
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use springtime_core::sim::contact::ColliderConfig;
    use std::path::Path;

    /// A rounded box's edge under three vertices, one above the flat top, one at the rounded
    /// edge, one beside the vertical face, each inside the layer.
    fn edge() -> (StaticContact, Vec<V3>) {
        // Top at z = 0, face at y = 0, the edge rounded about (y, z) = (−0.01, −0.01).
        let config: ColliderConfig = toml::from_str(
            "kind = \"rounded_box\"\nradius = 0.01\nhalf_extents = [1.0, 1.0, 1.0]\n\
             translation = [0.0, -1.01, -1.01]",
        )
        .unwrap();
        let collider = config.build(Path::new("."), "ledge").unwrap();
        let contact = StaticContact {
            collider,
            thickness: 0.002,
            stiffness: vec![3.0, 5.0, 7.0],
        };
        // 1.5 mm from the top and from the rounded edge (φ = 0.5 mm), 1.3 mm from the face.
        let s = 0.0115 / 2f64.sqrt();
        let x = vec![
            [0.1, -0.05, 0.0015],
            [0.2, -0.01 + s, -0.01 + s],
            [0.3, 0.0013, -0.04],
        ];
        (contact, x)
    }

    #[test]
    fn the_contact_gradient_is_the_derivative_of_its_energy() {
        let (contact, x) = edge();
        // The rounded edge is exact (parry's own round shapes are projected by GJK, to about
        // 1e-5 m: too coarse for Newton).
        for (p, d) in x.iter().zip([0.0015, 0.0015, 0.0013]) {
            let hit = contact.collider.query(0.0, *p);
            assert!((hit.distance - d).abs() < 1e-15, "{p:?}: {}", hit.distance);
        }
        let mut g = vec![[0.0; 3]; x.len()];
        contact.add_gradient(&x, &mut g);
        let eps = 1e-7;
        for i in 0..x.len() {
            for c in 0..3 {
                let mut y = x.clone();
                y[i][c] += eps;
                let up = contact.energy(&y);
                y[i][c] -= 2.0 * eps;
                let down = contact.energy(&y);
                let fd = (up - down) / (2.0 * eps);
                assert!(
                    (fd - g[i][c]).abs() < 1e-6 * g[i].iter().map(|v| v.abs()).sum::<f64>(),
                    "vertex {i}.{c}: gradient {} vs finite difference {fd}",
                    g[i][c]
                );
            }
        }
        // Each vertex is in the layer and pushed out along its own normal: up on the top,
        // out of the face beside it.
        assert!(g.iter().all(|p| p.iter().any(|v| v.abs() > 0.0)));
        assert!(g[0][2] < 0.0 && g[2][1] < 0.0, "{g:?}");
        assert!((g[1][1] - g[1][2]).abs() < 1e-12 && g[1][1] < 0.0, "{g:?}");
        assert!((contact.deepest(&x) - 0.0007).abs() < 1e-9);
        // Out of the layer: no force, no energy.
        let far = vec![[0.0, -0.05, 0.01]; 3];
        assert_eq!(contact.energy(&far), 0.0);
        assert_eq!(contact.force(&far), [0.0; 3]);
    }
}
