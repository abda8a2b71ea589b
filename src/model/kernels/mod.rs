//! The fused spring-force op: Eq. 4 and the incidence scatter (Eq. 2) for every spring of
//! every clip in one kernel, with a hand-written backward registered with Burn's autodiff
//! through a backend extension.
//!
//! Backends: `Flex` and `NdArray` run the CPU kernels of [`cpu`] (clips in parallel);
//! `Autodiff<B>` records one node whose backward is the fused backward kernel of `B`. The
//! reference implementation made of Burn tensor ops is [`super::springs::spring_forces_reference`];
//! the tests compare the two.
// The NdArray backend is deprecated upstream; the design card keeps it for tests.
#![allow(deprecated)]

pub mod cpu;

use std::sync::Arc;

use burn::backend::autodiff::Autodiff;
use burn::backend::autodiff::checkpoint::{base::Checkpointer, strategy::CheckpointStrategy};
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
use burn::backend::tensor::FloatTensor;
use burn::backend::{Backend, Dispatch, TensorMetadata, backend_extension};
use burn::tensor::{DType, Tensor, TensorData};

/// The spring network on the host, shared by every call of the fused op.
///
/// Built only through [`HostGraph::new`], which checks every endpoint, so that the kernels
/// may index without bounds checks.
#[derive(Debug, Clone, PartialEq)]
pub struct HostGraph {
    ends: Vec<(u32, u32)>,
    rest_length: Vec<f64>,
    particles: usize,
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
                assert!(a < particles && b < particles, "spring ({a}, {b}) outside {particles} particles");
                (a as u32, b as u32)
            })
            .collect();
        Self {
            ends,
            rest_length: rest_length.to_vec(),
            particles,
        }
    }

    /// Number of springs.
    pub fn num_springs(&self) -> usize {
        self.ends.len()
    }

    /// Number of particles.
    pub fn num_particles(&self) -> usize {
        self.particles
    }
}

/// Backends that run the fused spring-force op.
#[backend_extension(Autodiff, Flex, NdArray)]
pub trait SpringBackend: Backend {
    /// Spring forces `[B, P, 3]` at positions `x` and velocities `v` `[B, P, 3]` with
    /// per-spring `k`, `b` `[S]`.
    fn spring_forces(
        x: FloatTensor<Self>,
        v: FloatTensor<Self>,
        k: FloatTensor<Self>,
        b: FloatTensor<Self>,
        graph: Arc<HostGraph>,
    ) -> FloatTensor<Self>;

    /// The vector-Jacobian product of [`spring_forces`](Self::spring_forces): `(∂ℓ/∂x, ∂ℓ/∂v,
    /// ∂ℓ/∂k, ∂ℓ/∂b)` given `grad = ∂ℓ/∂F`.
    fn spring_forces_backward(
        x: FloatTensor<Self>,
        v: FloatTensor<Self>,
        k: FloatTensor<Self>,
        b: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        graph: Arc<HostGraph>,
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
    Tensor::from_dispatch(<Dispatch as SpringBackend>::spring_forces(
        x.into_dispatch(),
        v.into_dispatch(),
        k.into_dispatch(),
        b.into_dispatch(),
        graph.clone(),
    ))
}

/// Host data of a float tensor primitive, as `f32` or `f64` values.
enum HostData {
    F32(Vec<f32>),
    F64(Vec<f64>),
}

fn host<B: Backend>(t: FloatTensor<B>) -> HostData {
    let data: TensorData =
        burn::tensor::read_sync(B::float_into_data(t)).expect("tensor data is readable");
    match data.dtype() {
        DType::F64 => HostData::F64(data.try_into_vec_as::<f64>().expect("f64 data")),
        _ => HostData::F32(data.try_into_vec_as::<f32>().expect("f32 data")),
    }
}

fn host_as<B: Backend>(t: FloatTensor<B>, f64s: bool) -> HostData {
    match (host::<B>(t), f64s) {
        (HostData::F32(v), true) => HostData::F64(v.into_iter().map(f64::from).collect()),
        (HostData::F64(v), false) => HostData::F32(v.into_iter().map(|x| x as f32).collect()),
        (d, _) => d,
    }
}

fn upload<B: Backend>(data: HostData, shape: Vec<usize>, device: &B::Device) -> FloatTensor<B> {
    let data = match data {
        HostData::F32(v) => TensorData::new(v, shape),
        HostData::F64(v) => TensorData::new(v, shape),
    };
    B::float_from_data(data, device)
}

/// The fused forward on any CPU backend, through host slices.
fn cpu_forces<B: Backend>(
    x: FloatTensor<B>,
    v: FloatTensor<B>,
    k: FloatTensor<B>,
    b: FloatTensor<B>,
    graph: &HostGraph,
) -> FloatTensor<B> {
    let shape = x.shape().to_vec();
    let device = x.device();
    let f64s = x.dtype() == DType::F64;
    let out = match (
        host_as::<B>(x, f64s),
        host_as::<B>(v, f64s),
        host_as::<B>(k, f64s),
        host_as::<B>(b, f64s),
    ) {
        (HostData::F32(x), HostData::F32(v), HostData::F32(k), HostData::F32(b)) => {
            let mut out = vec![0f32; x.len()];
            cpu::forces(graph, &x, &v, &k, &b, &mut out);
            HostData::F32(out)
        }
        (HostData::F64(x), HostData::F64(v), HostData::F64(k), HostData::F64(b)) => {
            let mut out = vec![0f64; x.len()];
            cpu::forces(graph, &x, &v, &k, &b, &mut out);
            HostData::F64(out)
        }
        _ => unreachable!("inputs converted to one precision"),
    };
    upload::<B>(out, shape, &device)
}

/// The fused backward on any CPU backend, through host slices.
fn cpu_backward<B: Backend>(
    x: FloatTensor<B>,
    v: FloatTensor<B>,
    k: FloatTensor<B>,
    b: FloatTensor<B>,
    grad: FloatTensor<B>,
    graph: &HostGraph,
) -> SpringGrads<B> {
    let shape = x.shape().to_vec();
    let device = x.device();
    let s = graph.num_springs();
    let f64s = x.dtype() == DType::F64;
    let h = |t| host_as::<B>(t, f64s);
    macro_rules! run {
        ($x:expr, $v:expr, $k:expr, $b:expr, $g:expr, $ty:ty, $wrap:ident) => {{
            let (mut gx, mut gv) = (vec![0 as $ty; $x.len()], vec![0 as $ty; $x.len()]);
            let (mut gk, mut gb) = (vec![0 as $ty; s], vec![0 as $ty; s]);
            cpu::forces_backward(
                graph, &$x, &$v, &$k, &$b, &$g, &mut gx, &mut gv, &mut gk, &mut gb,
            );
            (
                HostData::$wrap(gx),
                HostData::$wrap(gv),
                HostData::$wrap(gk),
                HostData::$wrap(gb),
            )
        }};
    }
    let (gx, gv, gk, gb) = match (h(x), h(v), h(k), h(b), h(grad)) {
        (
            HostData::F32(x),
            HostData::F32(v),
            HostData::F32(k),
            HostData::F32(b),
            HostData::F32(g),
        ) => {
            run!(x, v, k, b, g, f32, F32)
        }
        (
            HostData::F64(x),
            HostData::F64(v),
            HostData::F64(k),
            HostData::F64(b),
            HostData::F64(g),
        ) => {
            run!(x, v, k, b, g, f64, F64)
        }
        _ => unreachable!("inputs converted to one precision"),
    };
    SpringGrads {
        x: upload::<B>(gx, shape.clone(), &device),
        v: upload::<B>(gv, shape, &device),
        k: upload::<B>(gk, vec![s], &device),
        b: upload::<B>(gb, vec![s], &device),
    }
}

impl SpringBackend for burn::backend::Flex {
    fn spring_forces(
        x: FloatTensor<Self>,
        v: FloatTensor<Self>,
        k: FloatTensor<Self>,
        b: FloatTensor<Self>,
        graph: Arc<HostGraph>,
    ) -> FloatTensor<Self> {
        cpu_forces::<Self>(x, v, k, b, &graph)
    }

    fn spring_forces_backward(
        x: FloatTensor<Self>,
        v: FloatTensor<Self>,
        k: FloatTensor<Self>,
        b: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        graph: Arc<HostGraph>,
    ) -> SpringGrads<Self> {
        cpu_backward::<Self>(x, v, k, b, grad, &graph)
    }
}

#[allow(deprecated)]
impl SpringBackend for burn::backend::NdArray {
    fn spring_forces(
        x: FloatTensor<Self>,
        v: FloatTensor<Self>,
        k: FloatTensor<Self>,
        b: FloatTensor<Self>,
        graph: Arc<HostGraph>,
    ) -> FloatTensor<Self> {
        cpu_forces::<Self>(x, v, k, b, &graph)
    }

    fn spring_forces_backward(
        x: FloatTensor<Self>,
        v: FloatTensor<Self>,
        k: FloatTensor<Self>,
        b: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        graph: Arc<HostGraph>,
    ) -> SpringGrads<Self> {
        cpu_backward::<Self>(x, v, k, b, grad, &graph)
    }
}

#[derive(Debug)]
struct SpringForcesBackward;

impl<B: SpringBackend> Backward<B, 4> for SpringForcesBackward {
    type State = (
        FloatTensor<B>,
        FloatTensor<B>,
        FloatTensor<B>,
        FloatTensor<B>,
        Arc<HostGraph>,
    );

    fn backward(
        self,
        ops: Ops<Self::State, 4>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        let [node_x, node_v, node_k, node_b] = ops.parents;
        let grad = grads.consume::<B>(&ops.node);
        let (x, v, k, b, graph) = ops.state;
        let g = B::spring_forces_backward(x, v, k, b, grad, graph);
        for (node, value) in [(node_x, g.x), (node_v, g.v), (node_k, g.k), (node_b, g.b)] {
            if let Some(node) = node {
                grads.register::<B>(node.id, value);
            }
        }
    }
}

impl<B: SpringBackend, C: CheckpointStrategy> SpringBackend for Autodiff<B, C> {
    fn spring_forces(
        x: FloatTensor<Self>,
        v: FloatTensor<Self>,
        k: FloatTensor<Self>,
        b: FloatTensor<Self>,
        graph: Arc<HostGraph>,
    ) -> FloatTensor<Self> {
        match SpringForcesBackward
            .prepare::<C>([x.node(), v.node(), k.node(), b.node()])
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => {
                let (x, v, k, b) = (
                    x.into_primitive(),
                    v.into_primitive(),
                    k.into_primitive(),
                    b.into_primitive(),
                );
                let out =
                    B::spring_forces(x.clone(), v.clone(), k.clone(), b.clone(), graph.clone());
                prep.finish((x, v, k, b, graph), out)
            }
            OpsKind::UnTracked(prep) => prep.finish(B::spring_forces(
                x.into_primitive(),
                v.into_primitive(),
                k.into_primitive(),
                b.into_primitive(),
                graph,
            )),
        }
    }

    fn spring_forces_backward(
        _x: FloatTensor<Self>,
        _v: FloatTensor<Self>,
        _k: FloatTensor<Self>,
        _b: FloatTensor<Self>,
        _grad: FloatTensor<Self>,
        _graph: Arc<HostGraph>,
    ) -> SpringGrads<Self> {
        unimplemented!("the backward of the fused op is not itself differentiable")
    }
}
