//! The incremental potential of an implicit-Euler step (the latent paper's Eq. 4) as Burn
//! tensor ops over a batch of states `[B, N, 3]`:
//!
//! `Φ(x) = (1/2h²)(x − x̃)ᵀM(x − x̃) + E(x) − Σᵢ mᵢ g·xᵢ + w_bc Σ_{i pinned} |xᵢ − x*ᵢ|²`,
//!
//! with `E` the [`FemCloth`]'s StVK membrane and hinge bending, element for element the same
//! maths as the host code (triangles gathered with `select`, `F = Ds Dm⁻¹`, Green strain,
//! `ψ = μ E:E + ½λ tr(E)²`; hinges by the signed `atan2` angle). Autodiff through it gives the
//! forces; `tests/latent.rs` checks both against the host energy and forces.

use anyhow::{Result, bail};
use burn::tensor::{Device, Int, Tensor, TensorData};

use crate::source::fem::{FemCloth, Membrane};

/// The potential's constant data on a device.
#[derive(Debug, Clone)]
pub struct Potential {
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
    /// Lumped masses, `[1, N, 1]`.
    mass: Tensor<3>,
    gravity: [f64; 3],
    dt: f64,
    pinned: Tensor<1, Int>,
    /// Number of pinned vertices.
    pub num_pinned: usize,
    /// Weight of the soft boundary condition `w_bc`, J/m².
    pub w_bc: f64,
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
        let int = |v: Vec<i64>| {
            let n = v.len();
            Tensor::<1, Int>::from_data(TensorData::new(v, [n]), device)
        };
        let elements: Vec<_> = cloth.elements().collect();
        let m = elements.len();
        let tri = [0, 1, 2].map(|k| int(elements.iter().map(|e| e.0.v[k] as i64).collect()));
        let col = |f: &dyn Fn(&(crate::cloth::triangles::RestTriangle, f64, f64)) -> f64| {
            let v: Vec<f32> = elements.iter().map(|e| f(e) as f32).collect();
            Tensor::<1>::from_data(TensorData::new(v, [m]), device)
        };
        let dm_inv = [(0, 0), (0, 1), (1, 0), (1, 1)]
            .map(|(r, c)| col(&|e| e.0.dm_inv[r][c]).reshape([1, m, 1]));
        let area_mu = col(&|e| e.0.area * e.1).reshape([1, m]);
        let area_lambda = col(&|e| e.0.area * e.2).reshape([1, m]);
        let hinges: Vec<_> = cloth.weighted_hinges().collect();
        let h = hinges.len();
        let hinge = [0, 1, 2, 3].map(|k| {
            int(hinges
                .iter()
                .map(|(hg, _)| [hg.a, hg.b, hg.c, hg.d][k] as i64)
                .collect())
        });
        let hw: Vec<f32> = hinges.iter().map(|(_, w)| *w as f32).collect();
        let mass: Vec<f32> = cloth.masses().iter().map(|&m| m as f32).collect();
        let n = mass.len();
        Ok(Self {
            tri,
            dm_inv,
            area_mu,
            area_lambda,
            hinge,
            hinge_weight: Tensor::from_data(TensorData::new(hw, [1, h]), device),
            mass: Tensor::from_data(TensorData::new(mass, [1, n, 1]), device),
            gravity: cloth.gravity(),
            dt,
            pinned: int(pinned.iter().map(|&i| i as i64).collect()),
            num_pinned: pinned.len(),
            w_bc,
        })
    }

    /// Membrane and bending energy of every state of the batch `x` `[B, N, 3]`, J, `[B]`.
    pub fn elastic(&self, x: Tensor<3>) -> Tensor<1> {
        self.membrane(x.clone()) + self.bending(x)
    }

    /// StVK membrane energy, `[B]`.
    pub fn membrane(&self, x: Tensor<3>) -> Tensor<1> {
        let [x0, x1, x2] = self.tri.clone().map(|i| x.clone().select(1, i));
        let (e1, e2) = (x1 - x0.clone(), x2 - x0);
        let [d00, d01, d10, d11] = self.dm_inv.clone();
        // F = [e1 e2] Dm⁻¹: column 0 = e1 d00 + e2 d10, column 1 = e1 d01 + e2 d11.
        let f0 = e1.clone() * d00 + e2.clone() * d10;
        let f1 = e1 * d01 + e2 * d11;
        let dot = |a: Tensor<3>, b: Tensor<3>| (a * b).sum_dim(2).squeeze_dim::<2>(2);
        let e00 = (dot(f0.clone(), f0.clone()) - 1.0) * 0.5;
        let e11 = (dot(f1.clone(), f1.clone()) - 1.0) * 0.5;
        let e01 = dot(f0, f1) * 0.5;
        let tr = e00.clone() + e11.clone();
        let ee = e00.powi_scalar(2) + e01.powi_scalar(2) * 2.0 + e11.powi_scalar(2);
        let psi = ee * self.area_mu.clone() + tr.powi_scalar(2) * self.area_lambda.clone() * 0.5;
        psi.sum_dim(1).squeeze_dim::<1>(1)
    }

    /// Hinge bending energy `Σ w θ²`, `[B]`.
    pub fn bending(&self, x: Tensor<3>) -> Tensor<1> {
        let [xa, xb, xc, xd] = self.hinge.clone().map(|i| x.clone().select(1, i));
        let e = xb.clone() - xa.clone();
        let n1 = (xc.clone() - xa.clone()).cross(xc - xb.clone(), 2);
        let n2 = (xd.clone() - xb).cross(xd - xa, 2);
        let dot = |a: Tensor<3>, b: Tensor<3>| (a * b).sum_dim(2).squeeze_dim::<2>(2);
        let len = dot(e.clone(), e.clone()).sqrt();
        let sin = dot(n2.clone().cross(n1.clone(), 2), e);
        let cos = dot(n1, n2) * len;
        let theta = sin.atan2(cos);
        (theta.powi_scalar(2) * self.hinge_weight.clone())
            .sum_dim(1)
            .squeeze_dim::<1>(1)
    }

    /// The incremental potential of every state of the batch: `x` at `t`, `x_tilde =
    /// 2x_{t−1} − x_{t−2}`, `targets` `[B, P, 3]` the pinned vertices' prescribed positions,
    /// J, `[B]`.
    pub fn incremental(&self, x: Tensor<3>, x_tilde: Tensor<3>, targets: Tensor<3>) -> Tensor<1> {
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
        inertia + external + bc + self.elastic(x)
    }
}
