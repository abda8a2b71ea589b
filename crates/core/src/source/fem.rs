//! The FEM cloth source (paper §4.1 (ii)): a triangle mesh with a StVK membrane, dihedral-angle
//! bending on interior edges and strain-rate damping, stepped with the same semi-implicit Euler
//! as every other source. It generates data only (no gradients), in f64 over plain slices.
//!
//! Mesh: an `nx × ny` vertex grid over the `width × height` rest rectangle, every cell cut into
//! two triangles along its main diagonal `(r, c)–(r+1, c+1)`, its anti-diagonal, or alternating
//! in a checkerboard ([`Diagonal`]). Vertex masses are lumped: a third of the mass `ρA` of every
//! triangle goes to each of its corners.
//!
//! Forces, per triangle with rest-shape inverse `Dm⁻¹` and rest area `A`:
//! - membrane (StVK): `F = Ds Dm⁻¹`, Green strain `E = ½(FᵀF − I)`, second Piola–Kirchhoff
//!   stress `S = λ tr(E) I + 2μE`, energy `A (μ E:E + ½λ tr(E)²)`, force on corner `i = 1, 2`
//!   the `i`-th column of `−A F S Dm⁻ᵀ` and on corner 0 minus their sum; Lamé parameters from
//!   the triangle's Young's modulus `Y` (surface modulus, N/m) and Poisson ratio `ν` in plane
//!   stress, `μ = Y / 2(1 + ν)`, `λ = Yν / (1 − ν²)`;
//! - strain-rate damping: the same map applied to `β (λ tr(Ė) I + 2μĖ)`, `Ė = ½(ḞᵀF + FᵀḞ)`,
//!   `Ḟ = Dv Dm⁻¹` (stiffness-proportional, so it vanishes under rigid motion and only
//!   dissipates);
//! - bending, per interior edge `e` with rest length `|ē|` between triangles of rest areas
//!   `Ā₁`, `Ā₂` (discrete shells): energy `k_b · 3|ē|² / (Ā₁ + Ā₂) · θ²`, `θ` the signed
//!   dihedral angle (0 for the flat rest state), with the analytic gradient of `θ`.
//!
//! Gravity acts on the lumped masses and Rayleigh damping is `−c v` per vertex.

use serde::{Deserialize, Serialize};

use super::fem_forces::ElementLanes;
use super::{ClothSim, SourceConfig, StiffnessMap};
use crate::cloth::lanes::{Real, each3};
use crate::cloth::triangles::{self, Hinge, RestTriangle, V3, cross, dot, scale, select3};
use crate::data::MeshTruth;
use crate::sim::Stability;

pub use crate::cloth::{Diagonal, grid_triangles};

/// The membrane's constitutive law.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Membrane {
    /// Co-rotational linear elasticity: `Ψ = μ‖F − R‖² + ½λ (tr S − 2)²` with the polar
    /// decomposition `F = RS`. Resists compression all the way to a collapsed triangle.
    #[default]
    Corotational,
    /// Saint Venant–Kirchhoff: `Ψ = μ E:E + ½λ tr(E)²`, `E = ½(FᵀF − I)`. Its resistance
    /// vanishes under strong compression, so triangles next to a single pinned vertex can
    /// collapse and snap through (measured: 50–80 m/s spikes in 8 s rollouts of the default
    /// sheet).
    Stvk,
}

/// The `[source.fem]` section: material and mesh of the FEM source (`source.kind = "fem"`).
///
/// The stiffness map of `source.stiffness_levels` / `source.layout` gives each triangle's
/// surface Young's modulus in N/m; `source.damping` is not used by this source.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct FemConfig {
    /// Poisson ratio `ν` (plane stress), in `[0, 0.5)`.
    pub poisson: f64,
    /// Bending stiffness `k_b`, N·m.
    pub bending: f64,
    /// Strain-rate damping `β`, s: the damping stress is `β` times the elastic stress of the
    /// strain rate.
    pub strain_damping: f64,
    /// Triangulation of the grid cells.
    pub diagonal: Diagonal,
    /// Constitutive law of the membrane.
    pub membrane: Membrane,
}

impl Default for FemConfig {
    /// `ν = 0.3`, `k_b = 0.5` N·m, `β = 0.004` s, main diagonals, co-rotational membrane.
    ///
    /// Chosen with `configs/table2_fem.toml` (the paper's 15.5 m, 31 × 31 sheet at 0.2 kg/m²,
    /// Young's moduli 100 / 400 / 1000 N/m, anchors of radius 0.8 m): the stiffest mode has
    /// `dt²ω² + 2·dt·γ ≈ 1.4` at 1 ms, and 8 s rollouts stretch edges by at most ~2.6× next to
    /// the anchors with speeds below 10 m/s. Softer sheets (moduli of 20–200 N/m) stretch up to
    /// 10× under their own weight and collapse the triangles next to a pinned vertex.
    fn default() -> Self {
        Self {
            poisson: 0.3,
            bending: 0.5,
            strain_damping: 0.004,
            diagonal: Diagonal::Main,
            membrane: Membrane::Corotational,
        }
    }
}

impl FemConfig {
    /// Checks ranges; errors name the key.
    pub fn validate(&self) -> anyhow::Result<()> {
        if !(0.0..0.5).contains(&self.poisson) {
            anyhow::bail!(
                "source.fem.poisson must lie in [0, 0.5), is {}",
                self.poisson
            );
        }
        if !(self.bending >= 0.0 && self.bending.is_finite()) {
            anyhow::bail!(
                "source.fem.bending must be non-negative, is {}",
                self.bending
            );
        }
        if !(self.strain_damping >= 0.0 && self.strain_damping.is_finite()) {
            anyhow::bail!(
                "source.fem.strain_damping must be non-negative, is {}",
                self.strain_damping
            );
        }
        Ok(())
    }
}

/// One triangle: its rest frame and Lamé constants.
#[derive(Debug, Clone, Copy)]
struct Element {
    tri: RestTriangle,
    mu: f64,
    lambda: f64,
}

/// A triangle-mesh cloth with a per-triangle stiffness map.
#[derive(Debug, Clone)]
pub struct FemCloth {
    rest_uv: Vec<[f64; 2]>,
    elements: Vec<Element>,
    hinges: Vec<Hinge>,
    /// `k_b · 3|ē|² / (Ā₁ + Ā₂)` of each hinge.
    hinge_weight: Vec<f64>,
    /// Lumped vertex masses, kg.
    mass: Vec<f64>,
    /// Young's modulus of every triangle, N/m (the ground-truth map).
    youngs: Vec<f64>,
    beta: f64,
    membrane: Membrane,
    rayleigh: f64,
    gravity: [f64; 3],
    /// Summary of the material for messages.
    material: String,
    /// The elements laid out for the force loop.
    lanes: ElementLanes,
}

impl FemCloth {
    /// The FEM cloth of a source config (`source.kind = "fem"`).
    pub fn from_config(cfg: &SourceConfig) -> Self {
        Self::from_config_scaled(cfg, &[])
    }

    /// The FEM cloth of a source config with triangle `t`'s Young's modulus multiplied by
    /// `scale[t]` (all 1 where `scale` is empty): a perturbed copy of the source's material.
    pub(crate) fn from_config_scaled(cfg: &SourceConfig, scale: &[f64]) -> Self {
        let (nx, ny) = (cfg.nx, cfg.ny);
        let (hx, hy) = (cfg.width / (nx - 1) as f64, cfg.height / (ny - 1) as f64);
        let rest_uv: Vec<[f64; 2]> = (0..ny)
            .flat_map(|r| (0..nx).map(move |c| [c as f64 * hx, r as f64 * hy]))
            .collect();
        let triangles = grid_triangles(nx, ny, cfg.fem.diagonal);
        let map = StiffnessMap {
            layout: cfg.layout,
            levels: cfg.stiffness_levels.clone(),
        };
        let nu = cfg.fem.poisson;
        let youngs: Vec<f64> = triangles
            .iter()
            .map(|t| {
                let u = t.iter().map(|&i| rest_uv[i][0]).sum::<f64>() / 3.0;
                let v = t.iter().map(|&i| rest_uv[i][1]).sum::<f64>() / 3.0;
                map.at(u / cfg.width, v / cfg.height)
            })
            .zip(scale.iter().chain(std::iter::repeat(&1.0)))
            .map(|(y, s)| y * s)
            .collect();
        Self::new(
            rest_uv,
            &triangles,
            &youngs,
            FemMaterial {
                poisson: nu,
                bending: cfg.fem.bending,
                strain_damping: cfg.fem.strain_damping,
                membrane: cfg.fem.membrane,
                areal_density: cfg.areal_density,
                rayleigh: cfg.rayleigh,
                gravity: cfg.gravity,
            },
        )
    }

    /// A cloth over any triangle mesh of the rest rectangle, with Young's modulus `youngs` per
    /// triangle. Panics on a degenerate triangle (callers build valid meshes).
    pub fn new(
        rest_uv: Vec<[f64; 2]>,
        triangles: &[[usize; 3]],
        youngs: &[f64],
        material: FemMaterial,
    ) -> Self {
        let n = rest_uv.len();
        let nu = material.poisson;
        let mut mass = vec![0.0; n];
        let mut elements = Vec::with_capacity(triangles.len());
        for (t, &y) in triangles.iter().zip(youngs) {
            let tri = RestTriangle::new(&rest_uv, *t)
                .unwrap_or_else(|| panic!("degenerate triangle {t:?}"));
            for &i in t {
                mass[i] += material.areal_density * tri.area / 3.0;
            }
            elements.push(Element {
                tri,
                mu: y / (2.0 * (1.0 + nu)),
                lambda: y * nu / (1.0 - nu * nu),
            });
        }
        let hinges = triangles::hinges(triangles);
        let hinge_weight: Vec<f64> = hinges
            .iter()
            .map(|h| {
                let len2 = (rest_uv[h.b][0] - rest_uv[h.a][0]).powi(2)
                    + (rest_uv[h.b][1] - rest_uv[h.a][1]).powi(2);
                let areas = elements[h.triangles[0]].tri.area + elements[h.triangles[1]].tri.area;
                material.bending * 3.0 * len2 / areas
            })
            .collect();
        let ymax = youngs.iter().copied().fold(0.0, f64::max);
        let lanes = ElementLanes::new(
            n,
            &elements
                .iter()
                .map(|e| (e.tri, e.mu, e.lambda))
                .collect::<Vec<_>>(),
            &hinges
                .iter()
                .copied()
                .zip(hinge_weight.iter().copied())
                .collect::<Vec<_>>(),
        );
        Self {
            lanes,
            rest_uv,
            elements,
            hinges,
            hinge_weight,
            mass,
            youngs: youngs.to_vec(),
            beta: material.strain_damping,
            membrane: material.membrane,
            rayleigh: material.rayleigh,
            gravity: material.gravity,
            material: format!(
                "{:?} FEM membrane with Young's modulus up to {ymax:.4} N/m (ν = {nu}), bending \
                 {:.4} N·m, strain-rate damping β = {:.4} s",
                material.membrane, material.bending, material.strain_damping
            ),
        }
    }

    /// Triangles of the mesh.
    pub fn triangles(&self) -> Vec<[usize; 3]> {
        self.elements.iter().map(|e| e.tri.v).collect()
    }

    /// Lumped vertex masses, kg.
    pub fn masses(&self) -> &[f64] {
        &self.mass
    }

    /// Elastic energy (membrane and bending) at positions `x`, J.
    pub fn energy(&self, x: &[V3]) -> f64 {
        self.membrane_energy(x) + self.bending_energy(x)
    }

    /// Membrane (in-plane) elastic energy at positions `x`, J.
    pub fn membrane_energy(&self, x: &[V3]) -> f64 {
        self.elements
            .iter()
            .map(|el| el.tri.area * elastic(el.mu, el.lambda, deformation(el, x), self.membrane).1)
            .sum()
    }

    /// Bending (dihedral) energy at positions `x`, J.
    pub fn bending_energy(&self, x: &[V3]) -> f64 {
        self.hinges
            .iter()
            .zip(&self.hinge_weight)
            .map(|(h, w)| w * triangles::dihedral(h, x).0.powi(2))
            .sum()
    }

    /// Internal forces (membrane, strain-rate damping, bending) at `(x, v)`, added to `out`
    /// (eight elements at a time: see `source/fem_forces.rs`).
    pub fn internal_forces(&self, x: &[V3], v: &[V3], out: &mut [V3]) {
        self.lanes.add_forces(self.law(), x, v, out);
    }

    /// Membrane and strain-rate damping forces on a triangle's corners (in the order of
    /// `el.tri.v`) at `(x, v)`.
    fn membrane_forces(&self, el: &Element, x: &[V3], v: &[V3]) -> [V3; 3] {
        let corners = |y: &[V3]| el.tri.v.map(|i| y[i]);
        triangle_forces(
            self.law(),
            el.constants(),
            corners(x),
            (self.beta > 0.0).then(|| corners(v)),
        )
    }

    /// The membrane law and strain-rate damping shared by every triangle.
    fn law(&self) -> Law {
        Law {
            membrane: self.membrane,
            beta: self.beta,
        }
    }

    /// The step of central differences of the forces: `1e-6` of the sheet's size.
    fn difference_step(&self) -> f64 {
        let size = self
            .rest_uv
            .iter()
            .fold(0.0f64, |m, p| m.max(p[0].abs()).max(p[1].abs()))
            .max(1e-12);
        1e-6 * size
    }

    /// The elastic energy's Hessian, element by element: one block per triangle (its membrane,
    /// 9 × 9) and one per hinge (its bending, 12 × 12), each by central differences of the
    /// element's exact forces (so it is as accurate as the step allows, about 1e-8 relative),
    /// symmetrised. Damping is left out (the forces are taken at zero velocity, where the
    /// strain-rate term vanishes). The blocks are not projected: a Newton solver projects
    /// them to positive semi-definite before assembly.
    pub fn hessian_blocks(&self, x: &[V3]) -> Vec<HessianBlock> {
        let eps = self.difference_step();
        let mut blocks = Vec::with_capacity(self.elements.len() + self.hinges.len());
        for el in &self.elements {
            let local = Element {
                tri: RestTriangle {
                    v: [0, 1, 2],
                    ..el.tri
                },
                ..*el
            };
            let corners = el.tri.v.map(|i| x[i]);
            let zero = [[0.0; 3]; 3];
            let forces = |y: &[V3]| self.membrane_forces(&local, y, &zero).to_vec();
            blocks.push(HessianBlock::by_differences(
                el.tri.v.to_vec(),
                &corners,
                eps,
                forces,
            ));
        }
        for (hinge, &weight) in self.hinges.iter().zip(&self.hinge_weight) {
            let local = Hinge {
                c: 0,
                d: 1,
                a: 2,
                b: 3,
                ..*hinge
            };
            let vertices = vec![hinge.c, hinge.d, hinge.a, hinge.b];
            let corners: Vec<V3> = vertices.iter().map(|&i| x[i]).collect();
            let forces = |y: &[V3]| {
                let (theta, grads) = triangles::dihedral(&local, y);
                grads.map(|g| scale(g, -2.0 * weight * theta)).to_vec()
            };
            blocks.push(HessianBlock::by_differences(
                vertices, &corners, eps, forces,
            ));
        }
        blocks
    }

    /// The membrane's constitutive law.
    pub fn membrane(&self) -> Membrane {
        self.membrane
    }

    /// Gravity on the lumped masses, m/s².
    pub fn gravity(&self) -> [f64; 3] {
        self.gravity
    }

    /// The membrane elements: rest frame and Lamé constants `(μ, λ)` of every triangle.
    pub fn elements(&self) -> impl Iterator<Item = (RestTriangle, f64, f64)> + '_ {
        self.elements.iter().map(|e| (e.tri, e.mu, e.lambda))
    }

    /// The bending hinges and their weights `k_b · 3|ē|² / (Ā₁ + Ā₂)` (energy `w θ²`).
    pub fn weighted_hinges(&self) -> impl Iterator<Item = (Hinge, f64)> + '_ {
        self.hinges
            .iter()
            .copied()
            .zip(self.hinge_weight.iter().copied())
    }

    /// Net force: internal forces, gravity on the lumped masses and Rayleigh damping.
    pub fn forces(&self, x: &[V3], v: &[V3], out: &mut [V3]) {
        for ((o, vi), &m) in out.iter_mut().zip(v).zip(&self.mass) {
            for c in 0..3 {
                o[c] = m * self.gravity[c] - self.rayleigh * vi[c];
            }
        }
        self.internal_forces(x, v, out);
    }

    /// Largest eigenvalue of `M^{-1/2} A M^{-1/2}` for a symmetric positive semi-definite
    /// operator `A` given by its action, by power iteration.
    fn mass_weighted_max(&self, apply: impl Fn(&[V3], &mut [V3])) -> f64 {
        let n = self.rest_uv.len();
        let inv_sqrt: Vec<f64> = self.mass.iter().map(|m| 1.0 / m.sqrt()).collect();
        let mut scaled = vec![[0.0; 3]; n];
        crate::cloth::power_iteration(n, 200, |y, z| {
            for i in 0..n {
                scaled[i] = scale(y[i], inv_sqrt[i]);
            }
            apply(&scaled, z);
            for i in 0..n {
                z[i] = scale(z[i], inv_sqrt[i]);
            }
        })
    }
}

/// Material constants of an FEM cloth besides the per-triangle Young's modulus.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FemMaterial {
    /// Poisson ratio.
    pub poisson: f64,
    /// Bending stiffness, N·m.
    pub bending: f64,
    /// Strain-rate damping, s.
    pub strain_damping: f64,
    /// Constitutive law of the membrane.
    pub membrane: Membrane,
    /// Areal density, kg/m².
    pub areal_density: f64,
    /// Rayleigh constant, N·s/m.
    pub rayleigh: f64,
    /// Gravity, m/s².
    pub gravity: [f64; 3],
}

/// One element's block of the elastic energy's Hessian `∂²E/∂x²` over its vertices.
#[derive(Debug, Clone, PartialEq)]
pub struct HessianBlock {
    /// The element's vertices; the block's rows are `3 · k + c` for vertex `vertices[k]`,
    /// coordinate `c`.
    pub vertices: Vec<usize>,
    /// The block, row-major, `3k × 3k`.
    pub matrix: Vec<f64>,
}

impl HessianBlock {
    /// The block of an element with forces `forces(corners)` (one per corner): `−∂f/∂x` by
    /// central differences of step `eps`, symmetrised.
    fn by_differences(
        vertices: Vec<usize>,
        corners: &[V3],
        eps: f64,
        forces: impl Fn(&[V3]) -> Vec<V3>,
    ) -> Self {
        let m = 3 * corners.len();
        let mut matrix = vec![0.0; m * m];
        let mut y = corners.to_vec();
        for col in 0..m {
            let (k, c) = (col / 3, col % 3);
            y[k][c] = corners[k][c] + eps;
            let plus = forces(&y);
            y[k][c] = corners[k][c] - eps;
            let minus = forces(&y);
            y[k][c] = corners[k][c];
            for row in 0..m {
                let (r, rc) = (row / 3, row % 3);
                matrix[row * m + col] = -(plus[r][rc] - minus[r][rc]) / (2.0 * eps);
            }
        }
        for i in 0..m {
            for j in 0..i {
                let s = 0.5 * (matrix[i * m + j] + matrix[j * m + i]);
                matrix[i * m + j] = s;
                matrix[j * m + i] = s;
            }
        }
        Self { vertices, matrix }
    }
}

/// `F = Ds Dm⁻¹` (3 × 2) of a triangle at positions `x`.
#[inline]
fn deformation(el: &Element, x: &[V3]) -> [[f64; 2]; 3] {
    el.tri.deformation(x)
}

/// What every triangle of a cloth shares: the membrane's law and the strain-rate damping `β`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) struct Law {
    pub membrane: Membrane,
    pub beta: f64,
}

/// One triangle's (or, with [`Lanes`](crate::cloth::lanes::Lanes), eight triangles') Lamé
/// constants and rest frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) struct Constants<R> {
    pub mu: R,
    pub lambda: R,
    pub area: R,
    pub dm_inv: [[R; 2]; 2],
}

impl Element {
    fn constants(&self) -> Constants<f64> {
        Constants {
            mu: self.mu,
            lambda: self.lambda,
            area: self.tri.area,
            dm_inv: self.tri.dm_inv,
        }
    }
}

/// Membrane and strain-rate damping forces on a triangle's corners at corner positions `x`
/// and velocities `v` (`None` when `β = 0`).
#[inline(always)]
pub(super) fn triangle_forces<R: Real>(
    law: Law,
    c: Constants<R>,
    x: [[R; 3]; 3],
    v: Option<[[R; 3]; 3]>,
) -> [[R; 3]; 3] {
    let f = triangles::deformation(x, c.dm_inv);
    let (mut p, _) = elastic(c.mu, c.lambda, f, law.membrane);
    if let Some(v) = v {
        let fd = triangles::deformation(v, c.dm_inv);
        // Ė = ½(ḞᵀF + FᵀḞ); the damping stress β(λ tr(Ė) I + 2μĖ) maps to F S_d.
        let ed = [
            [strain_rate(f, fd, 0, 0), strain_rate(f, fd, 0, 1)],
            [strain_rate(f, fd, 1, 0), strain_rate(f, fd, 1, 1)],
        ];
        let sd = stress(c.mu, c.lambda, ed);
        let beta = R::splat(law.beta);
        for r in 0..3 {
            for k in 0..2 {
                p[r][k] = p[r][k] + beta * (f[r][0] * sd[0][k] + f[r][1] * sd[1][k]);
            }
        }
    }
    // H = −A P Dm⁻ᵀ (3 × 2): the forces on corners 1 and 2.
    let m = c.dm_inv;
    // (Dm⁻ᵀ)[k][col] = Dm⁻¹[col][k]
    let h = each3!(|r| {
        [
            -c.area * (p[r][0] * m[0][0] + p[r][1] * m[0][1]),
            -c.area * (p[r][0] * m[1][0] + p[r][1] * m[1][1]),
        ]
    });
    let f1 = [h[0][0], h[1][0], h[2][0]];
    let f2 = [h[0][1], h[1][1], h[2][1]];
    [
        scale(
            [f1[0] + f2[0], f1[1] + f2[1], f1[2] + f2[2]],
            R::splat(-1.0),
        ),
        f1,
        f2,
    ]
}

/// `Ė[i][j] = ½(ḞᵀF + FᵀḞ)[i][j]`.
#[inline(always)]
fn strain_rate<R: Real>(f: [[R; 2]; 3], fd: [[R; 2]; 3], i: usize, j: usize) -> R {
    let mut acc = fd[0][i] * f[0][j] + f[0][i] * fd[0][j];
    for r in 1..3 {
        acc = acc + (fd[r][i] * f[r][j] + f[r][i] * fd[r][j]);
    }
    R::splat(0.5) * acc
}

/// The first Piola–Kirchhoff stress `P = ∂Ψ/∂F` (3 × 2) and the energy density `Ψ` of a
/// membrane with Lamé constants `μ`, `λ` at deformation gradient `f`.
#[inline(always)]
fn elastic<R: Real>(mu: R, lambda: R, f: [[R; 2]; 3], model: Membrane) -> ([[R; 2]; 3], R) {
    let (one, two, half) = (R::splat(1.0), R::splat(2.0), R::splat(0.5));
    match model {
        Membrane::Stvk => {
            let e = triangles::green(f);
            let s = stress(mu, lambda, e);
            let tr = e[0][0] + e[1][1];
            let ee = e[0][0] * e[0][0] + two * e[0][1] * e[0][1] + e[1][1] * e[1][1];
            let p = each3!(|r| {
                [
                    f[r][0] * s[0][0] + f[r][1] * s[1][0],
                    f[r][0] * s[0][1] + f[r][1] * s[1][1],
                ]
            });
            (p, mu * ee + half * lambda * tr * tr)
        }
        Membrane::Corotational => {
            // Polar decomposition F = RS in the deformed triangle's own plane: with the
            // orthonormal frame Q = [e₁ e₂] (e₁ along the first column of F, e₂ in the plane
            // of both columns), F = Q F₂ with F₂ upper triangular of non-negative determinant,
            // whose rotation has the closed form R₂ = rot(atan2(F₂₁₀ − F₂₀₁, F₂₀₀ + F₂₁₁)) and
            // tr S = |(F₂₀₀ + F₂₁₁, F₂₁₀ − F₂₀₁)|. R = Q R₂ has orthonormal columns however
            // flat the triangle is, so the force stays bounded through a collapse. The
            // degenerate cases are selected, not branched to, so that lanes stay in step.
            let zero = R::splat(0.0);
            let f0 = [f[0][0], f[1][0], f[2][0]];
            let f1 = [f[0][1], f[1][1], f[2][1]];
            let tr_c = dot(f0, f0) + dot(f1, f1);
            let l0 = dot(f0, f0).sqrt();
            // The alternatives for (nearly) collapsed triangles are computed only when a lane
            // needs them.
            let long = l0.gt(R::splat(1e-12));
            let mut e1 = scale(f0, one / l0);
            if !R::all(long) {
                let q1 = dot(f1, f1);
                let along_f1 = select3(
                    q1.gt(R::splat(1e-24)),
                    scale(f1, one / q1.sqrt()),
                    [one, zero, zero],
                );
                e1 = select3(long, e1, along_f1);
            }
            let m = cross(e1, f1);
            let nm = dot(m, m).sqrt();
            let planar = nm.gt(zero);
            let mut normal = scale(m, one / nm);
            if !R::all(planar) {
                // Without a plane: any unit vector perpendicular to e₁.
                let t = select3(
                    e1[0].abs().lt(R::splat(0.9)),
                    [one, zero, zero],
                    [zero, one, zero],
                );
                let q = cross(e1, t);
                normal = select3(planar, normal, scale(q, one / dot(q, q).sqrt()));
            }
            let e2 = cross(normal, e1);
            let (a00, a01, a10, a11) = (dot(f0, e1), dot(f1, e1), dot(f0, e2), dot(f1, e2));
            let (ca, sa) = (a00 + a11, a10 - a01);
            let tr_s = (ca * ca + sa * sa).sqrt();
            let turned = tr_s.gt(zero);
            let inv = one / tr_s;
            let cos = R::select(turned, ca * inv, one);
            let sin = R::select(turned, sa * inv, zero);
            let r0 = each3!(|i| cos * e1[i] + sin * e2[i]);
            let r1 = each3!(|i| -sin * e1[i] + cos * e2[i]);
            let vol = lambda * (tr_s - two);
            let p = each3!(|r| {
                [
                    two * mu * (f[r][0] - r0[r]) + vol * r0[r],
                    two * mu * (f[r][1] - r1[r]) + vol * r1[r],
                ]
            });
            let psi = mu * (tr_c - two * tr_s + two) + half * lambda * (tr_s - two) * (tr_s - two);
            (p, psi)
        }
    }
}

/// StVK stress `λ tr(E) I + 2μE`.
#[inline(always)]
fn stress<R: Real>(mu: R, lambda: R, e: [[R; 2]; 2]) -> [[R; 2]; 2] {
    let tr = e[0][0] + e[1][1];
    let two = R::splat(2.0);
    [
        [lambda * tr + two * mu * e[0][0], two * mu * e[0][1]],
        [two * mu * e[1][0], lambda * tr + two * mu * e[1][1]],
    ]
}

impl ClothSim for FemCloth {
    fn rest_uv(&self) -> &[[f64; 2]] {
        &self.rest_uv
    }

    fn particle_mass(&self) -> f64 {
        self.mass.iter().sum::<f64>() / self.mass.len() as f64
    }

    fn mass_of(&self, i: usize) -> f64 {
        self.mass[i]
    }

    fn net_forces(&self, x: &[V3], v: &[V3], out: &mut [V3]) {
        self.forces(x, v, out);
    }

    /// The stiffest mode of the linearisation at the flat rest state: `ω²` from the
    /// mass-weighted stiffness (membrane and bending, by central differences of the elastic
    /// forces) and `γ` from the mass-weighted damping operator plus Rayleigh damping.
    fn stability(&self, dt: f64) -> Stability {
        let rest: Vec<V3> = self.rest_uv.iter().map(|p| [p[0], p[1], 0.0]).collect();
        let n = rest.len();
        let zero = vec![[0.0; 3]; n];
        // The forces at zero velocity are the elastic ones: the strain-rate term vanishes.
        let eps = self.difference_step();
        let omega2 = self.mass_weighted_max(|y, out| {
            let plus: Vec<V3> = rest
                .iter()
                .zip(y)
                .map(|(r, d)| [0, 1, 2].map(|c| r[c] + eps * d[c]))
                .collect();
            let minus: Vec<V3> = rest
                .iter()
                .zip(y)
                .map(|(r, d)| [0, 1, 2].map(|c| r[c] - eps * d[c]))
                .collect();
            let (mut fp, mut fm) = (vec![[0.0; 3]; n], vec![[0.0; 3]; n]);
            self.internal_forces(&plus, &zero, &mut fp);
            self.internal_forces(&minus, &zero, &mut fm);
            for i in 0..n {
                out[i] = [0, 1, 2].map(|c| -(fp[i][c] - fm[i][c]) / (2.0 * eps));
            }
        });
        let gamma_springs = if self.beta > 0.0 {
            // The damping operator: the part of the internal forces at the rest state that is
            // linear in the velocity.
            let mut elastic_at_rest = vec![[0.0; 3]; n];
            self.internal_forces(&rest, &zero, &mut elastic_at_rest);
            self.mass_weighted_max(|y, out| {
                let mut f = vec![[0.0; 3]; n];
                self.internal_forces(&rest, y, &mut f);
                for i in 0..n {
                    out[i] = [0, 1, 2].map(|c| -(f[i][c] - elastic_at_rest[i][c]));
                }
            })
        } else {
            0.0
        };
        let m_min = self.mass.iter().copied().fold(f64::INFINITY, f64::min);
        Stability {
            dt,
            mass: m_min,
            omega2,
            gamma: gamma_springs + self.rayleigh / m_min,
            parameters: self.material.clone(),
        }
    }

    fn mesh_truth(&self) -> Option<MeshTruth> {
        Some(MeshTruth {
            triangles: self.triangles(),
            stiffness: Some(self.youngs.clone()),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cloth::triangles::{add_to, sub};
    use crate::source::Layout;

    fn cloth(diagonal: Diagonal, layout: Layout, gravity: [f64; 3], rayleigh: f64) -> FemCloth {
        let cfg = SourceConfig {
            kind: crate::source::SourceKind::Fem,
            nx: 5,
            ny: 4,
            width: 2.0,
            height: 1.5,
            layout,
            gravity,
            rayleigh,
            fem: FemConfig {
                diagonal,
                ..FemConfig::default()
            },
            ..SourceConfig::default()
        };
        FemCloth::from_config(&cfg)
    }

    fn rest(c: &FemCloth) -> Vec<V3> {
        c.rest_uv.iter().map(|p| [p[0], p[1], 0.0]).collect()
    }

    fn deformed(c: &FemCloth, seed: f64) -> (Vec<V3>, Vec<V3>) {
        let x = rest(c)
            .iter()
            .enumerate()
            .map(|(i, p)| {
                let t = i as f64 + seed;
                [
                    p[0] * 1.05 + 0.04 * (t * 1.3).sin(),
                    p[1] * 0.97 + 0.03 * (t * 0.7).cos(),
                    0.15 * (t * 0.9).sin(),
                ]
            })
            .collect();
        let v = (0..c.rest_uv.len())
            .map(|i| {
                let t = i as f64 + seed;
                [(t * 0.3).cos(), (t * 1.1).sin(), 0.5 * (t * 0.2).cos()]
            })
            .collect();
        (x, v)
    }

    /// The internal forces as the loop before [`ElementLanes`] computed them: element by
    /// element, with the library's `atan2`.
    fn forces_elementwise(c: &FemCloth, x: &[V3], v: &[V3]) -> Vec<V3> {
        let mut out = vec![[0.0; 3]; x.len()];
        for el in &c.elements {
            for (&i, fi) in el.tri.v.iter().zip(c.membrane_forces(el, x, v)) {
                add_to(&mut out[i], fi);
            }
        }
        for (hinge, &weight) in c.hinges.iter().zip(&c.hinge_weight) {
            let (theta, grads) = triangles::dihedral(hinge, x);
            let coef = -2.0 * weight * theta;
            for (i, g) in [hinge.c, hinge.d, hinge.a, hinge.b].into_iter().zip(grads) {
                add_to(&mut out[i], scale(g, coef));
            }
        }
        out
    }

    #[test]
    fn chunked_forces_equal_the_elementwise_loop() {
        // 18 and 24 triangles (a padded last chunk and none), both laws, with and without
        // strain-rate damping, folded far from flat.
        for (nx, ny) in [(4, 4), (5, 4)] {
            for membrane in [Membrane::Corotational, Membrane::Stvk] {
                for beta in [0.0, 0.004] {
                    let cfg = SourceConfig {
                        kind: crate::source::SourceKind::Fem,
                        nx,
                        ny,
                        layout: Layout::Patches,
                        stiffness_levels: vec![100.0, 400.0, 1000.0],
                        fem: FemConfig {
                            diagonal: Diagonal::Alternating,
                            membrane,
                            strain_damping: beta,
                            ..FemConfig::default()
                        },
                        ..SourceConfig::default()
                    };
                    let c = FemCloth::from_config(&cfg);
                    let (mut x, v) = deformed(&c, 0.3);
                    for (i, p) in x.iter_mut().enumerate() {
                        p[2] *= 20.0 * (i % 3) as f64;
                    }
                    let want = forces_elementwise(&c, &x, &v);
                    let mut got = vec![[0.0; 3]; x.len()];
                    c.internal_forces(&x, &v, &mut got);
                    let scale = want.iter().flatten().fold(0.0f64, |m, f| m.max(f.abs()));
                    assert!(scale > 1.0);
                    for (g, w) in got.iter().zip(&want) {
                        for k in 0..3 {
                            assert!(
                                (g[k] - w[k]).abs() <= 1e-14 * scale,
                                "{nx}x{ny} {membrane:?} β {beta}: {g:?} vs {w:?}"
                            );
                        }
                    }
                    // Without bending the lanes are the scalar code bit for bit.
                    let flat = FemCloth {
                        lanes: ElementLanes::new(x.len(), &c.elements().collect::<Vec<_>>(), &[]),
                        hinges: Vec::new(),
                        hinge_weight: Vec::new(),
                        ..c.clone()
                    };
                    let mut got = vec![[0.0; 3]; x.len()];
                    flat.internal_forces(&x, &v, &mut got);
                    assert_eq!(got, forces_elementwise(&flat, &x, &v));
                }
            }
        }
    }

    #[test]
    fn a_rollout_matches_the_element_by_element_implementation() {
        // An 11 × 9 sheet of three moduli, pinned at two random anchors, 1.5 s at 1 ms. The
        // pinned figures were printed by the element-by-element loop this crate had before the
        // chunked one (commit e49fce3): weighted sums of the net forces and of the positions
        // after 500 and 1500 steps. The chunked forces may differ by rounding only.
        let cfg = SourceConfig {
            kind: crate::source::SourceKind::Fem,
            nx: 11,
            ny: 9,
            width: 5.0,
            height: 4.0,
            stiffness_levels: vec![100.0, 400.0, 1000.0],
            layout: Layout::Patches,
            anchor_radius: 0.5,
            ..SourceConfig::default()
        };
        let cloth = FemCloth::from_config(&cfg);
        let scenario = crate::source::Scenario::random(
            cloth.rest_uv(),
            cfg.anchor_radius,
            &mut <rand::rngs::StdRng as rand::SeedableRng>::seed_from_u64(7),
        );
        let mut x = scenario.initial_positions(cloth.rest_uv());
        let mut v = vec![[0.0; 3]; x.len()];
        let (mut scratch, mut f) = (Vec::new(), vec![[0.0; 3]; x.len()]);
        let weighted = |y: &[V3]| -> f64 {
            y.iter()
                .enumerate()
                .map(|(i, p)| {
                    (0..3)
                        .map(|c| ((i * 3 + c) as f64 * 0.61).sin() * p[c])
                        .sum::<f64>()
                })
                .sum()
        };
        let pinned = [
            (500, -12.936283217005283, -4.006555176923781),
            (1500, -14.791764947158613, -3.967557195536814),
        ];
        let mut at = pinned.iter();
        let mut next = at.next();
        for step in 0..=1500 {
            if let Some(&(when, forces, positions)) = next.filter(|p| p.0 == step) {
                cloth.net_forces(&x, &v, &mut f);
                let (fs, xs) = (weighted(&f), weighted(&x));
                assert!(
                    (fs - forces).abs() < 1e-11 * forces.abs(),
                    "step {when}: {fs} vs {forces}"
                );
                assert!(
                    (xs - positions).abs() < 1e-12 * positions.abs(),
                    "step {when}: {xs} vs {positions}"
                );
                next = at.next();
            }
            cloth.step(&mut x, &mut v, &scenario.pinned, cfg.dt, None, &mut scratch);
        }
        assert!(next.is_none());
    }

    #[test]
    fn grid_triangles_cover_every_cell_counter_clockwise() {
        let (nx, ny) = (4, 3);
        let uv = |i: usize| [(i % nx) as f64 * 1.0, (i / nx) as f64 * 1.0];
        for diagonal in [Diagonal::Main, Diagonal::Anti, Diagonal::Alternating] {
            let t = grid_triangles(nx, ny, diagonal);
            assert_eq!(t.len(), 2 * (nx - 1) * (ny - 1));
            let mut area = 0.0;
            for tri in &t {
                let [a, b, c] = tri.map(uv);
                let cross = (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]);
                assert!(
                    cross > 0.0,
                    "{diagonal:?}: {tri:?} is not counter-clockwise"
                );
                area += 0.5 * cross;
            }
            // The triangles tile the rectangle.
            assert!((area - ((nx - 1) * (ny - 1)) as f64).abs() < 1e-12);
        }
    }

    #[test]
    fn no_force_at_rest_and_flat_sheet_has_no_bending_force() {
        for d in [Diagonal::Main, Diagonal::Anti, Diagonal::Alternating] {
            let c = cloth(d, Layout::Stripes, [0.0; 3], 0.0);
            let x = rest(&c);
            let mut f = vec![[0.0; 3]; x.len()];
            c.internal_forces(&x, &vec![[0.0; 3]; x.len()], &mut f);
            assert!(f.iter().flatten().all(|v| v.abs() < 1e-12), "{d:?}");
            // A flat but in-plane stretched sheet: membrane forces only, none out of plane.
            let stretched: Vec<V3> = x.iter().map(|p| [p[0] * 1.2, p[1] * 0.9, 0.0]).collect();
            let mut f = vec![[0.0; 3]; x.len()];
            c.internal_forces(&stretched, &vec![[0.0; 3]; x.len()], &mut f);
            assert!(f.iter().all(|v| v[2] == 0.0));
            assert!(
                c.hinges
                    .iter()
                    .all(|h| triangles::dihedral(h, &stretched).0.abs() < 1e-12)
            );
            assert_eq!(c.energy(&x), 0.0);
        }
    }

    #[test]
    fn forces_are_minus_the_energy_gradient() {
        for membrane in [Membrane::Corotational, Membrane::Stvk] {
            let c = cloth(Diagonal::Alternating, Layout::Patches, [0.0; 3], 0.0);
            check_energy_gradient(&FemCloth {
                beta: 0.0,
                membrane,
                ..c
            });
        }
    }

    fn check_energy_gradient(c: &FemCloth) {
        let (x, _) = deformed(c, 0.3);
        let mut f = vec![[0.0; 3]; x.len()];
        c.internal_forces(&x, &vec![[0.0; 3]; x.len()], &mut f);
        let scale_f = f.iter().flatten().fold(0.0f64, |m, v| m.max(v.abs()));
        assert!(scale_f > 1.0);
        let h = 1e-6;
        for i in 0..x.len() {
            for k in 0..3 {
                let (mut up, mut down) = (x.clone(), x.clone());
                up[i][k] += h;
                down[i][k] -= h;
                let fd = -(c.energy(&up) - c.energy(&down)) / (2.0 * h);
                assert!(
                    (fd - f[i][k]).abs() <= 1e-6 * scale_f,
                    "{:?} vertex {i}[{k}]: force {} vs −dE/dx {fd}",
                    c.membrane,
                    f[i][k]
                );
            }
        }
    }

    #[test]
    fn dihedral_gradient_matches_finite_differences() {
        let c = cloth(Diagonal::Main, Layout::Uniform, [0.0; 3], 0.0);
        let (x, _) = deformed(&c, 1.7);
        for hinge in &c.hinges {
            let (theta, g) = triangles::dihedral(hinge, &x);
            assert!(theta.abs() < 1.5);
            for (slot, vtx) in [hinge.c, hinge.d, hinge.a, hinge.b].into_iter().enumerate() {
                for k in 0..3 {
                    let (mut up, mut down) = (x.clone(), x.clone());
                    up[vtx][k] += 1e-7;
                    down[vtx][k] -= 1e-7;
                    let fd = (triangles::dihedral(hinge, &up).0
                        - triangles::dihedral(hinge, &down).0)
                        / 2e-7;
                    assert!((fd - g[slot][k]).abs() < 1e-6, "{fd} vs {}", g[slot][k]);
                }
            }
        }
    }

    #[test]
    fn momentum_is_conserved_without_gravity_damping_and_pins() {
        let c = cloth(Diagonal::Anti, Layout::Patches, [0.0; 3], 0.0);
        let (mut x, mut v) = deformed(&c, 0.9);
        let momentum = |v: &[V3]| -> V3 {
            let mut p = [0.0; 3];
            for (vi, m) in v.iter().zip(&c.mass) {
                add_to(&mut p, scale(*vi, *m));
            }
            p
        };
        let p0 = momentum(&v);
        let pinned = vec![false; x.len()];
        let mut scratch = Vec::new();
        for _ in 0..500 {
            c.step(&mut x, &mut v, &pinned, 1e-3, None, &mut scratch);
        }
        let p1 = momentum(&v);
        let total: f64 = c.mass.iter().sum();
        for k in 0..3 {
            assert!((p1[k] - p0[k]).abs() < 1e-9 * total, "{p0:?} → {p1:?}");
        }
        // Internal forces sum to zero, damping included.
        let mut f = vec![[0.0; 3]; x.len()];
        c.internal_forces(&x, &v, &mut f);
        let net: V3 = f.iter().fold([0.0; 3], |mut a, fi| {
            add_to(&mut a, *fi);
            a
        });
        assert!(net.iter().all(|n| n.abs() < 1e-9), "{net:?}");
    }

    #[test]
    fn uniform_stretch_gives_the_same_stress_in_every_triangle() {
        for membrane in [Membrane::Corotational, Membrane::Stvk] {
            let c = FemCloth {
                membrane,
                ..cloth(Diagonal::Alternating, Layout::Uniform, [0.0; 3], 0.0)
            };
            let x: Vec<V3> = rest(&c)
                .iter()
                .map(|p| [1.1 * p[0], 0.95 * p[1], 0.0])
                .collect();
            let stresses: Vec<[[f64; 2]; 3]> = c
                .elements
                .iter()
                .map(|el| elastic(el.mu, el.lambda, deformation(el, &x), membrane).0)
                .collect();
            for s in &stresses {
                for i in 0..3 {
                    for j in 0..2 {
                        assert!((s[i][j] - stresses[0][i][j]).abs() < 1e-9, "{s:?}");
                    }
                }
            }
            // Stretched along x, compressed along y: tension in x, no shear, nothing out of plane.
            let p = stresses[0];
            assert!(p[0][0] > 0.0 && p[0][1].abs() < 1e-12 && p[1][0].abs() < 1e-12);
            assert!(p[2] == [0.0, 0.0]);
            // Interior vertices of a uniformly stretched sheet feel no net force.
            let mut f = vec![[0.0; 3]; x.len()];
            c.internal_forces(&x, &vec![[0.0; 3]; x.len()], &mut f);
            let interior = |i: usize| {
                let (r, col) = (i / 5, i % 5);
                r > 0 && r < 3 && col > 0 && col < 4
            };
            for (i, fi) in f.iter().enumerate().filter(|(i, _)| interior(*i)) {
                assert!(fi.iter().all(|v| v.abs() < 1e-9), "vertex {i}: {fi:?}");
            }
        }
    }

    #[test]
    fn corotational_membrane_resists_collapse() {
        // A triangle squashed to 10 % of its height still pushes back; StVK has stopped.
        let c = cloth(Diagonal::Main, Layout::Uniform, [0.0; 3], 0.0);
        let el = c.elements[0];
        let squash = [[1.0, 0.0], [0.0, 0.1], [0.0, 0.0]];
        let co = elastic(el.mu, el.lambda, squash, Membrane::Corotational).0;
        let st = elastic(el.mu, el.lambda, squash, Membrane::Stvk).0;
        assert!(co[1][1] < -0.5 * el.mu, "{co:?}");
        assert!(st[1][1].abs() < 0.1 * co[1][1].abs(), "{st:?} vs {co:?}");
        // Near and through the collapse the force stays bounded (the garbage rotation of an
        // ill-conditioned S⁻¹ once gave 1000 m/s spikes), varies continuously on either side,
        // and the reflected triangle feels the mirrored force (in 3-D the two are congruent).
        let bound = 2.0 * el.mu * 3.0 + el.lambda * 3.0;
        let p_of = |h: f64| {
            elastic(
                el.mu,
                el.lambda,
                [[1.0, 0.3], [0.0, h], [0.0, 0.0]],
                Membrane::Corotational,
            )
            .0
        };
        let heights = [1e-3, 1e-7, 1e-12, 0.0];
        for pair in heights.windows(2) {
            let (p, q) = (p_of(pair[0]), p_of(pair[1]));
            assert!(
                p.iter().flatten().all(|v| v.is_finite() && v.abs() < bound),
                "{p:?}"
            );
            let jump = p
                .iter()
                .flatten()
                .zip(q.iter().flatten())
                .map(|(a, b)| (a - b).abs());
            assert!(jump.fold(0.0, f64::max) < 0.05 * bound, "{p:?} → {q:?}");
            let mirror = p_of(-pair[0]);
            for c in 0..2 {
                assert!(
                    (mirror[0][c] - p[0][c]).abs() < 1e-9 && (mirror[1][c] + p[1][c]).abs() < 1e-9
                );
            }
        }
    }

    #[test]
    fn strain_rate_damping_vanishes_for_rigid_motion_and_dissipates() {
        let c = cloth(Diagonal::Main, Layout::Stripes, [0.0; 3], 0.0);
        let elastic = FemCloth {
            beta: 0.0,
            ..c.clone()
        };
        let damping = |x: &[V3], v: &[V3]| -> Vec<V3> {
            let (mut a, mut b) = (vec![[0.0; 3]; x.len()], vec![[0.0; 3]; x.len()]);
            c.internal_forces(x, v, &mut a);
            elastic.internal_forces(x, v, &mut b);
            a.iter().zip(&b).map(|(a, b)| sub(*a, *b)).collect()
        };
        // A translation plus a rotation about z of the rest sheet: Ė = 0, no damping force.
        let r = rest(&c);
        let rigid: Vec<V3> = r
            .iter()
            .map(|p| [0.3 - 0.5 * p[1], -0.2 + 0.5 * p[0], 0.1])
            .collect();
        assert!(damping(&r, &rigid).iter().flatten().all(|d| d.abs() < 1e-9));
        // Any other motion loses energy: the damping power Σ f_d · v is negative.
        let (x, v) = deformed(&c, 2.1);
        let power: f64 = damping(&x, &v)
            .iter()
            .zip(&v)
            .map(|(f, vi)| dot(*f, *vi))
            .sum();
        assert!(power < 0.0, "damping power {power}");
    }

    #[test]
    fn stability_estimate_matches_the_table2_sheet_and_refuses_too_much_damping() {
        let cfg = SourceConfig {
            kind: crate::source::SourceKind::Fem,
            nx: 31,
            ny: 31,
            stiffness_levels: vec![100.0, 400.0, 1000.0],
            layout: Layout::Patches,
            ..SourceConfig::default()
        };
        let st = FemCloth::from_config(&cfg).stability(1e-3);
        assert!((st.number() - 1.44).abs() < 0.05, "{}", st.describe());
        // Ten times the damping is past the limit, and the guard says so.
        let mut heavy = cfg.clone();
        heavy.fem.strain_damping = 0.04;
        let st = FemCloth::from_config(&heavy).stability(1e-3);
        assert!(!st.is_stable(), "{}", st.describe());
        assert!(st.describe().contains("FEM membrane"));
    }
}
