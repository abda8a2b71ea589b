//! The static equilibrium as a Burn op (paper 001 §3.3 under Burn's autodiff): γ `[5]` in,
//! the equilibrium's positions and clamp reactions out; forward by the XPBD solve and the
//! Newton polish, backward by the adjoint of the implicit-function theorem
//! ([`super::equilibrium::adjoint`]: one linear solve for all five parameters). So the shape
//! descriptor and the loss can be Burn tensor programs over the equilibrium
//! ([`super::descriptor::fft_descriptor_tensor`]) and any Burn optimiser can fit γ
//! (`fit.optimizer = "adam"` in `xpbd estimate`).
//!
//! The op runs on the CPU backends (`Flex`, `NdArray`) and under `Autodiff` of them; a solve that
//! fails returns NaN values (and a backward that cannot solve, NaN gradients), which
//! [`static_equilibrium`] turns into an error.

// The NdArray backend is deprecated upstream; the design card keeps it for tests.
#![allow(deprecated)]

use std::sync::Arc;

use anyhow::{Result, bail};
use burn::backend::autodiff::Autodiff;
use burn::backend::autodiff::checkpoint::{base::Checkpointer, strategy::CheckpointStrategy};
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
use burn::backend::tensor::FloatTensor;
use burn::backend::{Backend, Dispatch, TensorMetadata, backend_extension};
use burn::tensor::{Tensor, TensorData};

use super::cloth::{Load, Solve, XpbdCloth};
use super::equilibrium::{adjoint, polish};
use super::material::Gamma;
use springtime_core::cloth::triangles::V3;

/// One static problem: the cloth, its load, the clamp groups whose reactions are measured,
/// where its equilibria start and how they are solved.
#[derive(Debug, Clone)]
pub struct StaticProblem {
    /// The cloth.
    pub cloth: XpbdCloth,
    /// Clamps, forces and weights.
    pub load: Load,
    /// Clamp groups whose reaction vectors follow the positions in the op's output.
    pub groups: Vec<Vec<usize>>,
    /// Where every solve starts (at rest).
    pub start: Vec<V3>,
    /// The XPBD solve.
    pub solve: Solve,
    /// Newton steps polishing the equilibrium.
    pub polish_iterations: usize,
}

impl StaticProblem {
    /// Rows of the op's output: the vertices, then one per clamp group.
    pub fn rows(&self) -> usize {
        self.cloth.len() + self.groups.len()
    }

    /// The equilibrium at γ and its clamp reactions, rows of 3 (see [`Self::rows`]).
    pub fn forward(&self, gamma: [f64; 5]) -> Result<Vec<f64>> {
        let g = Gamma::from_array(gamma);
        let mut x = self
            .cloth
            .solve(&g, &self.load, &self.start, &self.solve)?
            .x;
        polish(
            &self.cloth,
            &g,
            &self.load,
            &mut x,
            self.polish_iterations,
            1e-10,
        )?;
        let mut out: Vec<f64> = x.iter().flatten().copied().collect();
        for group in &self.groups {
            out.extend(self.cloth.reaction(&g, &self.load, &x, group));
        }
        Ok(out)
    }

    /// `dL/dγ` from the forward's output `out` and the gradient `grad` of `L` with respect to
    /// it (both as [`Self::forward`] lays them out).
    pub fn backward(&self, gamma: [f64; 5], out: &[f64], grad: &[f64]) -> Result<[f64; 5]> {
        let n = self.cloth.len();
        let rows = |v: &[f64]| -> Vec<V3> { v.chunks(3).map(|p| [p[0], p[1], p[2]]).collect() };
        let (x, gx, gr) = (
            rows(&out[..3 * n]),
            rows(&grad[..3 * n]),
            rows(&grad[3 * n..]),
        );
        adjoint(
            &self.cloth,
            &Gamma::from_array(gamma),
            &self.load,
            &x,
            &self.groups,
            &gx,
            &gr,
        )
    }
}

/// The op on a backend.
#[backend_extension(Autodiff, Flex, NdArray)]
pub trait EquilibriumBackend: Backend {
    /// γ `[5]` → `[rows, 3]` (NaN when the solve fails).
    fn static_equilibrium(
        gamma: FloatTensor<Self>,
        problem: Arc<StaticProblem>,
    ) -> FloatTensor<Self>;

    /// `dL/dγ` `[5]` from γ, the forward's output and `dL/d output` (NaN when the Hessian is
    /// singular).
    fn static_equilibrium_backward(
        gamma: FloatTensor<Self>,
        out: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        problem: Arc<StaticProblem>,
    ) -> FloatTensor<Self>;
}

fn host<B: Backend>(t: &FloatTensor<B>) -> Vec<f64> {
    burn::tensor::read_sync(B::float_into_data(t.clone()))
        .expect("tensor data is readable")
        .try_into_vec_as::<f64>()
        .expect("float tensor data")
}

fn upload<B: Backend>(
    values: Vec<f64>,
    shape: Vec<usize>,
    like: &FloatTensor<B>,
) -> FloatTensor<B> {
    B::float_from_data(
        TensorData::new(values, shape).convert_dtype(like.dtype()),
        &like.device(),
    )
}

fn gamma_of(values: &[f64]) -> [f64; 5] {
    [values[0], values[1], values[2], values[3], values[4]]
}

fn forward_on<B: Backend>(gamma: FloatTensor<B>, problem: &StaticProblem) -> FloatTensor<B> {
    let g = gamma_of(&host::<B>(&gamma));
    let rows = problem.rows();
    let values = problem
        .forward(g)
        .unwrap_or_else(|_| vec![f64::NAN; 3 * rows]);
    upload::<B>(values, vec![rows, 3], &gamma)
}

fn backward_on<B: Backend>(
    gamma: FloatTensor<B>,
    out: FloatTensor<B>,
    grad: FloatTensor<B>,
    problem: &StaticProblem,
) -> FloatTensor<B> {
    let g = gamma_of(&host::<B>(&gamma));
    let d = problem
        .backward(g, &host::<B>(&out), &host::<B>(&grad))
        .unwrap_or([f64::NAN; 5]);
    upload::<B>(d.to_vec(), vec![5], &gamma)
}

macro_rules! cpu_equilibrium {
    ($backend:ty) => {
        impl EquilibriumBackend for $backend {
            fn static_equilibrium(
                gamma: FloatTensor<Self>,
                problem: Arc<StaticProblem>,
            ) -> FloatTensor<Self> {
                forward_on::<Self>(gamma, &problem)
            }

            fn static_equilibrium_backward(
                gamma: FloatTensor<Self>,
                out: FloatTensor<Self>,
                grad: FloatTensor<Self>,
                problem: Arc<StaticProblem>,
            ) -> FloatTensor<Self> {
                backward_on::<Self>(gamma, out, grad, &problem)
            }
        }
    };
}

cpu_equilibrium!(burn::backend::Flex);
cpu_equilibrium!(burn::backend::NdArray);

#[derive(Debug)]
struct EquilibriumBackward;

impl<B: EquilibriumBackend> Backward<B, 1> for EquilibriumBackward {
    type State = (FloatTensor<B>, FloatTensor<B>, Arc<StaticProblem>);

    fn backward(self, ops: Ops<Self::State, 1>, grads: &mut Gradients, _: &mut Checkpointer) {
        let grad = grads.consume::<B>(&ops.node);
        let (gamma, out, problem) = ops.state;
        let d = B::static_equilibrium_backward(gamma, out, grad, problem);
        if let [Some(node)] = ops.parents {
            grads.register::<B>(node.id, d);
        }
    }
}

impl<B: EquilibriumBackend, C: CheckpointStrategy> EquilibriumBackend for Autodiff<B, C> {
    fn static_equilibrium(
        gamma: FloatTensor<Self>,
        problem: Arc<StaticProblem>,
    ) -> FloatTensor<Self> {
        match EquilibriumBackward
            .prepare::<C>([gamma.node()])
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => {
                let gamma = gamma.into_primitive();
                let out = B::static_equilibrium(gamma.clone(), problem.clone());
                prep.finish((gamma, out.clone(), problem), out)
            }
            OpsKind::UnTracked(prep) => {
                prep.finish(B::static_equilibrium(gamma.into_primitive(), problem))
            }
        }
    }

    fn static_equilibrium_backward(
        _gamma: FloatTensor<Self>,
        _out: FloatTensor<Self>,
        _grad: FloatTensor<Self>,
        _problem: Arc<StaticProblem>,
    ) -> FloatTensor<Self> {
        unimplemented!("the backward of the equilibrium op is not itself differentiable")
    }
}

/// The equilibrium of `problem` at γ `[5]` (SI, `[C00, C11, C01, C22, b]`), differentiable
/// with respect to γ: its positions `[n, 3]` and clamp reactions `[G, 3]`.
pub fn static_equilibrium(
    gamma: Tensor<1>,
    problem: &Arc<StaticProblem>,
) -> Result<(Tensor<2>, Tensor<2>)> {
    let out: Tensor<2> =
        Tensor::from_dispatch(<Dispatch as EquilibriumBackend>::static_equilibrium(
            gamma.into_dispatch(),
            problem.clone(),
        ));
    let n = problem.cloth.len();
    let rows = problem.rows();
    if out.clone().is_nan().any().into_scalar::<bool>() {
        bail!("no equilibrium found at this γ (the XPBD solve or its polish failed)");
    }
    Ok((out.clone().slice([0..n, 0..3]), out.slice([n..rows, 0..3])))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cloth::Sweep;
    use crate::descriptor::{fft_descriptor, fft_descriptor_tensor};
    use crate::equilibrium::{pulled_sheet, sensitivity};

    /// A 5 × 5 sheet clamped along one edge and pulled sideways at the other, under gravity,
    /// the pulled edge's reaction measured.
    fn problem() -> StaticProblem {
        let (cloth, load, group) = pulled_sheet();
        let start = cloth.rest();
        StaticProblem {
            cloth,
            load,
            groups: vec![group],
            start,
            solve: Solve {
                steps: 3000,
                sweep: Sweep::GaussSeidel,
                tolerance: 1e-9,
                ..Solve::default()
            },
            polish_iterations: 30,
        }
    }

    fn gamma() -> [f64; 5] {
        Gamma::from_engineering(180.0, 500.0, 40.0, 0.3, 5e-5).to_array()
    }

    /// Deterministic weights for a linear functional of the op's output.
    fn weights(len: usize) -> Vec<f64> {
        (0..len).map(|i| (i as f64 * 0.37).sin() + 0.2).collect()
    }

    #[test]
    fn the_adjoint_equals_the_forward_sensitivities_contracted_with_the_gradient() {
        let p = problem();
        let g = gamma();
        let out = p.forward(g).unwrap();
        let w = weights(out.len());
        let adj = p.backward(g, &out, &w).unwrap();
        let n = p.cloth.len();
        let x: Vec<V3> = out[..3 * n].chunks(3).map(|v| [v[0], v[1], v[2]]).collect();
        let sens = sensitivity(&p.cloth, &Gamma::from_array(g), &p.load, &x, &p.groups).unwrap();
        for k in 0..5 {
            let mut fwd: f64 = (0..n)
                .map(|i| (0..3).map(|c| w[3 * i + c] * sens.dx[k][i][c]).sum::<f64>())
                .sum();
            fwd += (0..3)
                .map(|c| w[3 * n + c] * sens.reactions[0][k][c])
                .sum::<f64>();
            assert!(
                (adj[k] - fwd).abs() <= 1e-6 * fwd.abs().max(1e-12),
                "γ{k}: adjoint {} vs forward {fwd}",
                adj[k]
            );
        }
    }

    #[test]
    fn the_burn_op_differentiates_to_finite_differences_of_the_solve() {
        let p = Arc::new(problem());
        let g = gamma();
        let device = burn::tensor::Device::flex().autodiff();
        let gt = Tensor::<1>::from_data(TensorData::new(g.to_vec(), [5]), &device)
            .cast(burn::tensor::DType::F64)
            .require_grad();
        let (x, r) = static_equilibrium(gt.clone(), &p).unwrap();
        let out = Tensor::cat(vec![x, r], 0);
        let rows = p.rows();
        let w = weights(3 * rows);
        let wt = Tensor::<2>::from_data(TensorData::new(w.clone(), [rows, 3]), &device)
            .cast(burn::tensor::DType::F64);
        let loss = (out * wt).sum();
        let grad: Vec<f64> = gt
            .grad(&loss.backward())
            .unwrap()
            .into_data()
            .try_into_vec_as::<f64>()
            .unwrap();
        let value = |q: [f64; 5]| -> f64 {
            p.forward(q)
                .unwrap()
                .iter()
                .zip(&w)
                .map(|(a, b)| a * b)
                .sum()
        };
        for k in 0..5 {
            let h = 1e-4 * g[k];
            let (mut up, mut dn) = (g, g);
            up[k] += h;
            dn[k] -= h;
            let fd = (value(up) - value(dn)) / (2.0 * h);
            assert!(
                (grad[k] - fd).abs() <= 1e-3 * fd.abs().max(1e-9),
                "γ{k}: autodiff {} vs finite differences {fd}",
                grad[k]
            );
        }
    }

    #[test]
    fn the_burn_fft_descriptor_equals_the_host_one() {
        let (nx, ny) = (4, 6);
        let x: Vec<V3> = (0..nx * ny)
            .map(|i| {
                let t = i as f64;
                [0.1 * (t * 0.7).sin(), 0.05 * t, 0.02 * (t * 1.3).cos()]
            })
            .collect();
        let host = fft_descriptor(&x, nx, ny);
        let device = burn::tensor::Device::flex();
        let flat: Vec<f32> = x.iter().flatten().map(|&v| v as f32).collect();
        let t = Tensor::<2>::from_data(TensorData::new(flat, [nx * ny, 3]), &device);
        let burn: Vec<f32> = fft_descriptor_tensor(t, nx, ny)
            .into_data()
            .try_into_vec_as::<f32>()
            .unwrap();
        assert_eq!(burn.len(), host.len());
        let scale = host.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        for (i, (a, b)) in burn.iter().zip(&host).enumerate() {
            assert!((*a as f64 - b).abs() <= 1e-5 * scale, "bin {i}: {a} vs {b}");
        }
    }
}
