//! The fused spring-force op: Eq. 4 and the incidence scatter (Eq. 2) for every spring of
//! every clip in one kernel, with a hand-written backward registered with Burn's autodiff
//! through a backend extension.
//!
//! Three ops, from small to whole: [`spring_forces`] (Eqs. 2, 4), [`cloth_step`] (one
//! semi-implicit Euler step, Eq. 5, with pins) and [`rollout_loss`] (a batch of clips rolled out
//! and scored by Eqs. 7–10, with the adjoint of the integrator as its backward). Beside them,
//! for free rollouts that keep positions only (the evaluation and the recipe's searches),
//! [`cloth_frame`] steps a whole data frame on the CPU with the clips kept in lanes across its
//! substeps (no gradient).
//!
//! Backends: `Flex` and `NdArray` run the CPU kernels of [`cpu`] and [`rollout`] (SIMD across
//! clips, chunks of clips in parallel; `host.rs`); `Cube` (wgpu) runs the CubeCL kernels of
//! `cube.rs` for the forces and the step (the whole-rollout op is CPU-only); `Autodiff<B>` records one node per op whose
//! backward is the matching hand-written kernel of `B` (`autodiff.rs`). The tensor-op versions
//! ([`super::SpringGraph::spring_forces_reference`], [`crate::sim::rollout`] with
//! [`super::Kernel::Reference`]) are the references the tests compare against.
// The NdArray backend is deprecated upstream; the design card keeps it for tests.
#![allow(deprecated)]

mod autodiff;
pub mod cpu;
#[cfg(feature = "wgpu")]
mod cube;
mod host;
pub mod rollout;
pub mod segment;

pub use cpu::StepParams;
pub use rollout::RolloutParams;

use std::sync::Arc;

use burn::backend::tensor::FloatTensor;
use burn::backend::{Backend, Dispatch, backend_extension};
use burn::tensor::Tensor;

/// The spring network on the host, shared by every call of the fused op.
///
/// Built only through [`HostGraph::new`], which checks every endpoint, so that the kernels
/// may index without bounds checks.
#[derive(Debug, Clone, PartialEq)]
pub struct HostGraph {
    ends: Vec<(u32, u32)>,
    /// Curvature elements `(i, j, l)` ([`HostGraph::with_curvature`]); their stiffness follows
    /// the springs' in the ops' `k` (their entries of `b`, which keep the two paired, are unused).
    triples: Vec<(u32, u32, u32)>,
    rest_length: Vec<f64>,
    particles: usize,
    /// `1 / w` on each particle's spring forces (relative masses `w`); `None`: equal masses.
    force_scale: Option<Vec<f64>>,
    /// Which springs are shear springs ([`HostGraph::with_shear`]; empty: none), the ones a
    /// step's `shear_compression` softens in compression.
    shear: Vec<bool>,
    /// The graph's buffers on the CubeCL devices it ran on.
    #[cfg(feature = "wgpu")]
    cube: cube::CubeCache<cube::DeviceGraph>,
}

impl HostGraph {
    /// The springs `ends` with their rest lengths over `particles` particles.
    ///
    /// Panics if an endpoint is not a particle index or the lengths disagree.
    pub fn new(ends: &[[usize; 2]], rest_length: &[f64], particles: usize) -> Self {
        assert_eq!(ends.len(), rest_length.len(), "one rest length per spring");
        assert!(particles <= u32::MAX as usize);
        let ends = ends
            .iter()
            .map(|&[a, b]| {
                assert!(
                    a < particles && b < particles,
                    "spring ({a}, {b}) outside {particles} particles"
                );
                (a as u32, b as u32)
            })
            .collect();
        Self {
            ends,
            triples: Vec::new(),
            rest_length: rest_length.to_vec(),
            particles,
            force_scale: None,
            shear: Vec::new(),
            #[cfg(feature = "wgpu")]
            cube: Default::default(),
        }
    }

    /// The same graph with the shear springs marked (`shear[s]`: whether spring `s` is one, see
    /// [`crate::cloth::SpringFamily::Shear`]): the fused step and rollout soften them in
    /// compression by [`StepParams::shear_compression`].
    ///
    /// Panics unless `shear` holds one flag per spring.
    pub(crate) fn with_shear(mut self, shear: &[bool]) -> Self {
        assert_eq!(shear.len(), self.ends.len(), "one shear flag per spring");
        self.shear = if shear.contains(&true) {
            shear.to_vec()
        } else {
            Vec::new()
        };
        self
    }

    /// The same graph with every particle's spring forces multiplied by `scale` (one factor
    /// per particle: `1 / w` for relative masses `w`, see [`crate::cloth::Topology::mass_weight`]).
    ///
    /// Panics if `scale` does not hold one finite positive value per particle.
    pub(crate) fn with_force_scale(mut self, scale: Option<Vec<f64>>) -> Self {
        if let Some(s) = &scale {
            assert!(
                s.len() == self.particles && s.iter().all(|&v| v.is_finite() && v > 0.0),
                "one finite positive force scale per particle"
            );
        }
        self.force_scale = scale;
        #[cfg(feature = "wgpu")]
        {
            self.cube = Default::default();
        }
        self
    }

    /// The same graph with the curvature elements `triples` (grid rows, columns and diagonals of three
    /// particles, [`crate::cloth::Topology::curvature`]): the ops' `k` and `b` then hold one
    /// value per spring, then one per element.
    ///
    /// Panics if an element names a particle past the graph's.
    pub fn with_curvature(mut self, triples: &[[usize; 3]]) -> Self {
        self.triples = triples
            .iter()
            .map(|t| {
                assert!(
                    t.iter().all(|&i| i < self.particles),
                    "curvature element {t:?} outside {} particles",
                    self.particles
                );
                (t[0] as u32, t[1] as u32, t[2] as u32)
            })
            .collect();
        self
    }

    /// Number of springs.
    pub fn num_springs(&self) -> usize {
        self.ends.len()
    }

    /// Number of curvature elements.
    pub(crate) fn num_triples(&self) -> usize {
        self.triples.len()
    }

    /// Entries of the ops' `k` and `b`: one per spring and per curvature element.
    pub(crate) fn num_params(&self) -> usize {
        self.ends.len() + self.triples.len()
    }

    /// Number of particles.
    pub fn num_particles(&self) -> usize {
        self.particles
    }
}

/// What the spring forces read: positions `x` and velocities `v` `[B, P, 3]` and per-spring
/// `k`, `b` `[S]` (then one per curvature element).
#[derive(burn::backend::ExtensionType, Debug, Clone)]
pub struct SpringInputs<B: Backend> {
    /// Positions `[B, P, 3]`.
    pub x: FloatTensor<B>,
    /// Velocities `[B, P, 3]`.
    pub v: FloatTensor<B>,
    /// Stiffness `[S]`.
    pub k: FloatTensor<B>,
    /// Damping `[S]`.
    pub b: FloatTensor<B>,
}

impl SpringInputs<Dispatch> {
    /// The state `(x, v)` and the per-spring `(k, b)` of the tensor API.
    fn of((x, v): (Tensor<3>, Tensor<3>), (k, b): (Tensor<1>, Tensor<1>)) -> Self {
        Self {
            x: x.into_dispatch(),
            v: v.into_dispatch(),
            k: k.into_dispatch(),
            b: b.into_dispatch(),
        }
    }
}

/// The pins of a step, data (no gradient flows to them): `pinned` `[B, P, 1]` (1 = pinned) and
/// the pinned particles' prescribed state after the step, `x` and `v` `[B, P, 3]`.
#[derive(burn::backend::ExtensionType, Debug, Clone)]
pub struct StepPins<B: Backend> {
    /// 1 for pinned particles, `[B, P, 1]`.
    pub pinned: FloatTensor<B>,
    /// Prescribed positions `[B, P, 3]`.
    pub x: FloatTensor<B>,
    /// Prescribed velocities `[B, P, 3]`.
    pub v: FloatTensor<B>,
}

/// Backends that run the fused spring-force op.
#[backend_extension(Autodiff, Cube: cfg(feature = "wgpu"), Flex, NdArray)]
pub trait SpringBackend: Backend {
    /// Spring forces `[B, P, 3]` at the state of `s`.
    fn spring_forces(
        #[extension_type] s: SpringInputs<Self>,
        graph: Arc<HostGraph>,
    ) -> FloatTensor<Self>;

    /// The vector-Jacobian product of [`spring_forces`](Self::spring_forces): `(∂ℓ/∂x, ∂ℓ/∂v,
    /// ∂ℓ/∂k, ∂ℓ/∂b)` given `grad = ∂ℓ/∂F`.
    fn spring_forces_backward(
        #[extension_type] s: SpringInputs<Self>,
        grad: FloatTensor<Self>,
        graph: Arc<HostGraph>,
    ) -> SpringGrads<Self>;

    /// One semi-implicit Euler step with spring forces, gravity, Rayleigh damping and `pins`
    /// (see [`cpu`]): returns `x'`, `v'` and the net force `f` stacked as `[3, B, P, 3]`.
    fn cloth_step(
        #[extension_type] s: SpringInputs<Self>,
        #[extension_type] pins: StepPins<Self>,
        graph: Arc<HostGraph>,
        params: StepParams,
    ) -> FloatTensor<Self>;

    /// A whole batch of clips rolled out and scored in one op (see [`rollout`]): returns
    /// `[L_f, L_J, L_x]`. Only `k` and `b` receive gradients; the rest is data.
    fn rollout_loss(
        #[extension_type] inputs: RolloutInputs<Self>,
        graph: Arc<HostGraph>,
        params: RolloutParams,
    ) -> FloatTensor<Self>;

    /// The vector-Jacobian product of [`cloth_step`](Self::cloth_step) for `x`, `v`, `k`, `b`,
    /// given `grad = ∂ℓ/∂(x', v', f)` `[3, B, P, 3]`; `pinned` as in [`StepPins`].
    fn cloth_step_backward(
        #[extension_type] s: SpringInputs<Self>,
        pinned: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        graph: Arc<HostGraph>,
        params: StepParams,
    ) -> SpringGrads<Self>;
}

/// Gradients of the fused op.
#[derive(burn::backend::ExtensionType)]
pub struct SpringGrads<B: Backend> {
    /// `∂ℓ/∂x`, `[B, P, 3]`.
    pub x: FloatTensor<B>,
    /// `∂ℓ/∂v`, `[B, P, 3]`.
    pub v: FloatTensor<B>,
    /// `∂ℓ/∂k`, `[S]`.
    pub k: FloatTensor<B>,
    /// `∂ℓ/∂b`, `[S]`.
    pub b: FloatTensor<B>,
}

/// Spring forces through the fused op (see [`SpringBackend::spring_forces`]).
pub fn spring_forces(
    x: Tensor<3>,
    v: Tensor<3>,
    k: Tensor<1>,
    b: Tensor<1>,
    graph: &Arc<HostGraph>,
) -> Tensor<3> {
    let s = SpringInputs::of((x, v), (k, b));
    Tensor::from_dispatch(<Dispatch as SpringBackend>::spring_forces(s, graph.clone()))
}

/// One fused integration step (see [`SpringBackend::cloth_step`]) from `(x, v)` with
/// per-spring `k`, `b`: returns `(x', v', f)`.
pub fn cloth_step(
    (x, v): (Tensor<3>, Tensor<3>),
    (k, b): (Tensor<1>, Tensor<1>),
    pins: [Tensor<3>; 3],
    graph: &Arc<HostGraph>,
    params: StepParams,
) -> (Tensor<3>, Tensor<3>, Tensor<3>) {
    let [bsz, p, _] = x.dims();
    let s = SpringInputs::of((x, v), (k, b));
    let [pinned, pin_x, pin_v] = pins.map(Tensor::into_dispatch);
    let pins = StepPins {
        pinned,
        x: pin_x,
        v: pin_v,
    };
    let out: Tensor<4> = Tensor::from_dispatch(<Dispatch as SpringBackend>::cloth_step(
        s,
        pins,
        graph.clone(),
        params,
    ));
    let part = |i: usize| {
        out.clone()
            .slice([i..i + 1, 0..bsz, 0..p, 0..3])
            .reshape([bsz, p, 3])
    };
    (part(0), part(1), part(2))
}

/// One whole data frame of `substeps` fused steps on the CPU (see [`cpu::frame`]) from
/// `(x, v)` with per-spring `k`, `b`: returns `(x', v')`. `pins` are `[pinned, here, next]`:
/// the pin flags `[B, P, 1]` and the frame's first and last positions `[B, P, 3]`. The tensors
/// are read to the host and the results uploaded to `x`'s device once per frame, not per step.
pub fn cloth_frame(
    (x, v): (Tensor<3>, Tensor<3>),
    (k, b): (Tensor<1>, Tensor<1>),
    pins: [&Tensor<3>; 3],
    graph: &HostGraph,
    params: StepParams,
    span: (usize, f64),
) -> (Tensor<3>, Tensor<3>) {
    if x.dtype() == burn::tensor::DType::F64 {
        cloth_frame_as::<f64>((x, v), (k, b), pins, graph, params, span)
    } else {
        cloth_frame_as::<f32>((x, v), (k, b), pins, graph, params, span)
    }
}

fn cloth_frame_as<T: num_traits::Float + burn::tensor::Element + Send + Sync>(
    (x, v): (Tensor<3>, Tensor<3>),
    (k, b): (Tensor<1>, Tensor<1>),
    [pinned, here, next]: [&Tensor<3>; 3],
    graph: &HostGraph,
    params: StepParams,
    span: (usize, f64),
) -> (Tensor<3>, Tensor<3>) {
    fn host<T: burn::tensor::Element, const D: usize>(t: Tensor<D>) -> Vec<T> {
        t.into_data()
            .try_into_vec_as::<T>()
            .expect("float tensor data")
    }
    let (dims, device) = (x.dims(), x.device());
    let (x, v, k, b) = (host::<T, 3>(x), host(v), host::<T, 1>(k), host(b));
    let [pinned, here, next] = [pinned, here, next].map(|t| host::<T, 3>(t.clone()));
    let n = x.len();
    let mut out = vec![T::zero(); 2 * n];
    cpu::frame(
        graph,
        cpu::Inputs {
            x: &x,
            v: &v,
            k: &k,
            b: &b,
        },
        cpu::FramePins {
            pinned: &pinned,
            here: &here,
            next: &next,
        },
        params,
        span,
        &mut out,
    );
    let vo = out.split_off(n);
    let upload = |values: Vec<T>| {
        Tensor::<3>::from_data(burn::tensor::TensorData::new(values, dims), &device)
    };
    (upload(out), upload(vo))
}

/// The fused rollout and loss (see [`SpringBackend::rollout_loss`]): `[L_f, L_J, L_x]` of the
/// clips starting at `(x0, v0)` with per-spring `k`, `b`, `pinned` particles, the target
/// positions `path` `[B, T + 1, P, 3]` and forces `target` `[B, T, P, 3]`.
pub fn rollout_loss(
    (x0, v0): (Tensor<3>, Tensor<3>),
    (k, b): (Tensor<1>, Tensor<1>),
    pinned: Tensor<3>,
    (path, target): (Tensor<4>, Tensor<4>),
    graph: &Arc<HostGraph>,
    params: RolloutParams,
) -> Tensor<1> {
    let inputs = RolloutInputs {
        x0: x0.into_dispatch(),
        v0: v0.into_dispatch(),
        k: k.into_dispatch(),
        b: b.into_dispatch(),
        pinned: pinned.into_dispatch(),
        path: path.into_dispatch(),
        target: target.into_dispatch(),
    };
    Tensor::from_dispatch(<Dispatch as SpringBackend>::rollout_loss(
        inputs,
        graph.clone(),
        params,
    ))
}

/// The forward tape of a fused rollout, in the precision it ran in.
#[derive(Debug, Clone)]
pub(crate) enum RolloutTape {
    /// An f32 rollout.
    F32(Arc<rollout::Tape<f32>>),
    /// An f64 rollout.
    F64(Arc<rollout::Tape<f64>>),
}

/// The inputs of a fused rollout ([`SpringBackend::rollout_loss`]), kept for its backward.
#[derive(burn::backend::ExtensionType, Debug, Clone)]
pub struct RolloutInputs<B: Backend> {
    /// Start positions `[B, P, 3]`.
    pub x0: FloatTensor<B>,
    /// Start velocities `[B, P, 3]`.
    pub v0: FloatTensor<B>,
    /// Stiffness `[S]`.
    pub k: FloatTensor<B>,
    /// Damping `[S]`.
    pub b: FloatTensor<B>,
    /// 1 for pinned particles, `[B, P, 1]`.
    pub pinned: FloatTensor<B>,
    /// Target positions `[B, T + 1, P, 3]`.
    pub path: FloatTensor<B>,
    /// Target forces `[B, T, P, 3]`.
    pub target: FloatTensor<B>,
}

/// Host-side halves of the fused rollout, which the autodiff wrapper calls separately.
pub(crate) trait RolloutKernels: Backend {
    /// Forward: the losses `[3]` and the tape for the backward.
    fn rollout_forward(
        inputs: &RolloutInputs<Self>,
        graph: &HostGraph,
        params: RolloutParams,
    ) -> (FloatTensor<Self>, RolloutTape);

    /// Backward: `(∂ℓ/∂k, ∂ℓ/∂b)` for `ℓ = w · losses`.
    fn rollout_backward(
        inputs: &RolloutInputs<Self>,
        graph: &HostGraph,
        params: RolloutParams,
        tape: &RolloutTape,
        w: [f64; 3],
    ) -> (FloatTensor<Self>, FloatTensor<Self>);
}
