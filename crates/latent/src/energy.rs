//! The incremental potential of an implicit-Euler step (the latent paper's Eq. 4) as Burn
//! tensor ops over a batch of states `[B, N, 3]`:
//!
//! `Φ(x) = (1/2h²)(x − x̃)ᵀM(x − x̃) + E(x) + D(x; x₋) − Σᵢ mᵢ g·xᵢ + w_bc Σ_{i pinned} |xᵢ − x*ᵢ|²`,
//!
//! with `E` the elastic energy of the full-space cloth and `D` its damping as a dissipation
//! potential of the step from the previous state `x₋`:
//! - the [`FemCloth`] (the paper): StVK membrane and hinge bending, element for element the
//!   same maths as the host code (triangles gathered with `select`, `F = Ds Dm⁻¹`, Green strain,
//!   `ψ = μ E:E + ½λ tr(E)²`; hinges by the signed `atan2` angle), no damping besides implicit
//!   Euler's own;
//! - a trained springtime surrogate ([`SpringSheet`], distillation): `E = Σ ½kₛ(|dₛ| − lₛ)²`,
//!   and `D = (1/2h) Σ bₛ (Δdₛ·d̂ₛ)² + (c/2h) Σᵢ |Δxᵢ|²` (`Δ = x − x₋`, `d̂` the spring's
//!   direction at `x₋`), whose gradient is the surrogate's dashpot (Eq. 4) and Rayleigh forces
//!   at the step's velocity `Δ/h`.
//!
//! Autodiff through it gives the forces; `tests/latent.rs` checks both against the host
//! energy and forces, and the spring terms against the surrogate's force kernel.

use anyhow::{Result, bail};
use burn::tensor::{Device, Int, Tensor, TensorData};

use super::surrogate::SpringSheet;
use springtime_core::source::fem::{FemCloth, Membrane};

/// The potential's constant data on a device.
#[derive(Debug, Clone)]
pub struct Potential {
    elastic: Elastic,
    /// Lumped masses, `[1, N, 1]`.
    mass: Tensor<3>,
    gravity: [f64; 3],
    dt: f64,
    /// Rayleigh damping `c` per particle, N·s/m.
    rayleigh: f64,
    pinned: Tensor<1, Int>,
    /// Number of pinned vertices.
    pub num_pinned: usize,
    /// Weight of the soft boundary condition `w_bc`, J/m².
    pub w_bc: f64,
}

/// The elastic (and damping) terms of the full-space cloth.
#[derive(Debug, Clone)]
enum Elastic {
    Fem(Box<FemTerms>),
    Springs(Box<SpringTerms>),
}

/// StVK triangles and hinges.
#[derive(Debug, Clone)]
struct FemTerms {
    tri: [Tensor<1, Int>; 3],
    /// `Dm⁻¹` entries `[0][0], [0][1], [1][0], [1][1]`, each `[1, M, 1]`.
    dm_inv: [Tensor<3>; 4],
    /// `A μ` and `A λ` per triangle, `[1, M]`.
    area_mu: Tensor<2>,
    area_lambda: Tensor<2>,
    /// Hinge vertices `a, b, c, d`.
    hinge: [Tensor<1, Int>; 4],
    /// Hinge weights, `[1, H]`.
    hinge_weight: Tensor<2>,
}

/// Springs with stiffness and dashpot damping.
#[derive(Debug, Clone)]
struct SpringTerms {
    /// Endpoints `a`, `b`.
    ends: [Tensor<1, Int>; 2],
    /// Rest lengths, stiffness and damping, each `[1, S]`.
    rest: Tensor<2>,
    k: Tensor<2>,
    b: Tensor<2>,
}

fn int(v: Vec<i64>, device: &Device) -> Tensor<1, Int> {
    let n = v.len();
    Tensor::<1, Int>::from_data(TensorData::new(v, [n]), device)
}

fn row(v: Vec<f32>, device: &Device) -> Tensor<2> {
    let n = v.len();
    Tensor::from_data(TensorData::new(v, [1, n]), device)
}

/// Dot product along the last axis, `[B, K, 3] → [B, K]`.
fn dot(a: Tensor<3>, b: Tensor<3>) -> Tensor<2> {
    (a * b).sum_dim(2).squeeze_dim::<2>(2)
}

impl Potential {
    /// The potential of `cloth` stepped with `dt`, with `pinned` held softly with weight `w_bc`.
    /// Only the StVK membrane is written as tensor ops.
    pub fn new(
        cloth: &FemCloth,
        dt: f64,
        pinned: &[usize],
        w_bc: f64,
        device: &Device,
    ) -> Result<Self> {
        if cloth.membrane() != Membrane::Stvk {
            bail!("the latent energy is written for the StVK membrane only");
        }
        let elements: Vec<_> = cloth.elements().collect();
        let m = elements.len();
        let tri =
            [0, 1, 2].map(|k| int(elements.iter().map(|e| e.0.v[k] as i64).collect(), device));
        let col =
            |f: &dyn Fn(&(springtime_core::cloth::triangles::RestTriangle, f64, f64)) -> f64| {
                row(elements.iter().map(|e| f(e) as f32).collect(), device)
            };
        let dm_inv = [(0, 0), (0, 1), (1, 0), (1, 1)]
            .map(|(r, c)| col(&|e| e.0.dm_inv[r][c]).reshape([1, m, 1]));
        let hinges: Vec<_> = cloth.weighted_hinges().collect();
        let hinge = [0, 1, 2, 3].map(|k| {
            int(
                hinges
                    .iter()
                    .map(|(hg, _)| [hg.a, hg.b, hg.c, hg.d][k] as i64)
                    .collect(),
                device,
            )
        });
        let terms = FemTerms {
            tri,
            dm_inv,
            area_mu: col(&|e| e.0.area * e.1),
            area_lambda: col(&|e| e.0.area * e.2),
            hinge,
            hinge_weight: row(hinges.iter().map(|(_, w)| *w as f32).collect(), device),
        };
        Ok(Self::with(
            Elastic::Fem(Box::new(terms)),
            cloth.masses(),
            cloth.gravity(),
            0.0,
            dt,
            pinned,
            w_bc,
            device,
        ))
    }

    /// The potential of the spring surrogate `sheet` stepped with `dt` (its springs' energy,
    /// its dashpots and Rayleigh damping as a dissipation potential), with `pinned` held softly
    /// with weight `w_bc`.
    pub fn springs(
        sheet: &SpringSheet,
        dt: f64,
        pinned: &[usize],
        w_bc: f64,
        device: &Device,
    ) -> Self {
        let s = &sheet.surrogate;
        let ends = [0, 1].map(|k| int(s.springs.iter().map(|e| e[k] as i64).collect(), device));
        let terms = SpringTerms {
            ends,
            rest: row(s.rest_length.iter().map(|&v| v as f32).collect(), device),
            k: row(s.k.clone(), device),
            b: row(s.b.clone(), device),
        };
        Self::with(
            Elastic::Springs(Box::new(terms)),
            &s.masses,
            s.gravity,
            s.rayleigh,
            dt,
            pinned,
            w_bc,
            device,
        )
    }

    #[allow(clippy::too_many_arguments)]
    fn with(
        elastic: Elastic,
        masses: &[f64],
        gravity: [f64; 3],
        rayleigh: f64,
        dt: f64,
        pinned: &[usize],
        w_bc: f64,
        device: &Device,
    ) -> Self {
        let n = masses.len();
        let mass: Vec<f32> = masses.iter().map(|&m| m as f32).collect();
        Self {
            elastic,
            mass: Tensor::from_data(TensorData::new(mass, [1, n, 1]), device),
            gravity,
            dt,
            rayleigh,
            pinned: int(pinned.iter().map(|&i| i as i64).collect(), device),
            num_pinned: pinned.len(),
            w_bc,
        }
    }

    /// Elastic energy of every state of the batch `x` `[B, N, 3]` (membrane and bending, or
    /// springs), J, `[B]`.
    pub fn elastic(&self, x: Tensor<3>) -> Tensor<1> {
        match &self.elastic {
            Elastic::Fem(f) => f.membrane(x.clone()) + f.bending(x),
            Elastic::Springs(s) => s.energy(x),
        }
    }

    /// The damping's dissipation potential of the steps `x_prev → x` (`[B, N, 3]` each), J,
    /// `[B]`: zero for the FEM cloth.
    pub fn dissipation(&self, x: Tensor<3>, x_prev: Tensor<3>) -> Tensor<1> {
        let [batch, _, _] = x.dims();
        let mut d = Tensor::<1>::zeros([batch], &x.device());
        let h = self.dt;
        if self.rayleigh != 0.0 {
            let dx = x.clone() - x_prev.clone();
            d = d + dx.powi_scalar(2).sum_dim(2).sum_dim(1).reshape([-1])
                * (0.5 * self.rayleigh / h);
        }
        if let Elastic::Springs(s) = &self.elastic {
            d = d + s.dashpots(x, x_prev) * (0.5 / h);
        }
        d
    }

    /// Whether the potential has a dissipation term (a surrogate's damping), i.e. whether
    /// [`Self::incremental`] needs the previous state.
    pub fn is_damped(&self) -> bool {
        self.rayleigh != 0.0 || matches!(self.elastic, Elastic::Springs(_))
    }

    /// The incremental potential of every state of the batch: `x` at `t`, `x_prev` at `t − 1`
    /// (needed only when [`Self::is_damped`]), `x_tilde = 2x_{t−1} − x_{t−2}`, `targets`
    /// `[B, P, 3]` the pinned vertices' prescribed positions, J, `[B]`.
    pub fn incremental(
        &self,
        x: Tensor<3>,
        x_prev: Option<Tensor<3>>,
        x_tilde: Tensor<3>,
        targets: Tensor<3>,
    ) -> Tensor<1> {
        let h2 = self.dt * self.dt;
        let device = x.device();
        let inertia = ((x.clone() - x_tilde).powi_scalar(2) * self.mass.clone())
            .sum_dim(2)
            .sum_dim(1)
            .reshape([-1])
            * (0.5 / h2);
        let g: Vec<f32> = self.gravity.iter().map(|&v| v as f32).collect();
        let g = Tensor::<3>::from_data(TensorData::new(g, [1, 1, 3]), &device);
        let external = (x.clone() * g * self.mass.clone())
            .sum_dim(2)
            .sum_dim(1)
            .reshape([-1])
            .neg();
        let bc = (x.clone().select(1, self.pinned.clone()) - targets)
            .powi_scalar(2)
            .sum_dim(2)
            .sum_dim(1)
            .reshape([-1])
            * self.w_bc;
        let phi = inertia + external + bc;
        let phi = match self.is_damped() {
            true => {
                let x_prev = x_prev.expect("a damped potential needs the previous state");
                phi + self.dissipation(x.clone(), x_prev)
            }
            false => phi,
        };
        phi + self.elastic(x)
    }
}

impl FemTerms {
    /// StVK membrane energy, `[B]`.
    fn membrane(&self, x: Tensor<3>) -> Tensor<1> {
        let [x0, x1, x2] = self.tri.clone().map(|i| x.clone().select(1, i));
        let (e1, e2) = (x1 - x0.clone(), x2 - x0);
        let [d00, d01, d10, d11] = self.dm_inv.clone();
        // F = [e1 e2] Dm⁻¹: column 0 = e1 d00 + e2 d10, column 1 = e1 d01 + e2 d11.
        let f0 = e1.clone() * d00 + e2.clone() * d10;
        let f1 = e1 * d01 + e2 * d11;
        let e00 = (dot(f0.clone(), f0.clone()) - 1.0) * 0.5;
        let e11 = (dot(f1.clone(), f1.clone()) - 1.0) * 0.5;
        let e01 = dot(f0, f1) * 0.5;
        let tr = e00.clone() + e11.clone();
        let ee = e00.powi_scalar(2) + e01.powi_scalar(2) * 2.0 + e11.powi_scalar(2);
        let psi = ee * self.area_mu.clone() + tr.powi_scalar(2) * self.area_lambda.clone() * 0.5;
        psi.sum_dim(1).squeeze_dim::<1>(1)
    }

    /// Hinge bending energy `Σ w θ²`, `[B]`.
    fn bending(&self, x: Tensor<3>) -> Tensor<1> {
        let [xa, xb, xc, xd] = self.hinge.clone().map(|i| x.clone().select(1, i));
        let e = xb.clone() - xa.clone();
        let n1 = (xc.clone() - xa.clone()).cross(xc - xb.clone(), 2);
        let n2 = (xd.clone() - xb).cross(xd - xa, 2);
        let len = dot(e.clone(), e.clone()).sqrt();
        let sin = dot(n2.clone().cross(n1.clone(), 2), e);
        let cos = dot(n1, n2) * len;
        let theta = sin.atan2(cos);
        (theta.powi_scalar(2) * self.hinge_weight.clone())
            .sum_dim(1)
            .squeeze_dim::<1>(1)
    }
}

impl SpringTerms {
    /// `d = x_b − x_a` of every spring, `[B, S, 3]`.
    fn spans(&self, x: Tensor<3>) -> Tensor<3> {
        let [a, b] = self.ends.clone();
        x.clone().select(1, b) - x.select(1, a)
    }

    /// `Σ ½ k (|d| − l)²`, `[B]`.
    fn energy(&self, x: Tensor<3>) -> Tensor<1> {
        let d = self.spans(x);
        let stretch = dot(d.clone(), d).sqrt() - self.rest.clone();
        (stretch.powi_scalar(2) * self.k.clone() * 0.5)
            .sum_dim(1)
            .squeeze_dim::<1>(1)
    }

    /// `Σ b (Δd·d̂₋)²` with `d̂₋` the direction at `x_prev`, `[B]`.
    fn dashpots(&self, x: Tensor<3>, x_prev: Tensor<3>) -> Tensor<1> {
        let before = self.spans(x_prev);
        let change = self.spans(x) - before.clone();
        let along = dot(change, before.clone()).powi_scalar(2) / dot(before.clone(), before);
        (along * self.b.clone()).sum_dim(1).squeeze_dim::<1>(1)
    }
}
