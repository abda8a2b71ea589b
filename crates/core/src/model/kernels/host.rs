//! The fused ops on the CPU backends (`Flex`, `NdArray`): tensors are read as host slices
//! (without a copy where the backend allows), the kernels of [`super::cpu`] and
//! [`super::rollout`] run, and the results are uploaded as new tensors.

use std::borrow::Cow;
use std::sync::Arc;

use burn::backend::tensor::FloatTensor;
use burn::backend::{Backend, TensorMetadata};
use burn::tensor::{DType, Element, TensorData};
use num_traits::Float;

use super::cpu::{self, Pins, StepParams};
use super::rollout::{self, RolloutData, RolloutParams, Tape};
use super::{
    HostGraph, RolloutInputs, RolloutKernels, RolloutTape, SpringBackend, SpringGrads,
    SpringInputs, StepPins,
};

/// The element types the CPU kernels run in.
trait HostFloat: Float + Element + Send + Sync + 'static {
    /// A zero-copy view of a contiguous flex tensor of this type.
    fn flex_slice(t: &burn::backend::flex::FlexTensor) -> Option<&[Self]>;
    /// A zero-copy view of a standard-layout ndarray tensor of this type.
    fn ndarray_slice(t: &burn::backend::ndarray::NdArrayTensor) -> Option<&[Self]>;
    /// The values of any tensor data, converted to this type.
    fn from_data(data: TensorData) -> Vec<Self>;
    /// The tape variant of a rollout in this type.
    fn tape(tape: Arc<Tape<Self>>) -> RolloutTape;
    /// The tape of a rollout in this type.
    fn untape(tape: &RolloutTape) -> &Tape<Self>;
}

macro_rules! host_float {
    ($t:ty, $variant:ident) => {
        impl HostFloat for $t {
            fn flex_slice(t: &burn::backend::flex::FlexTensor) -> Option<&[Self]> {
                t.as_slice::<$t>()
            }
            fn ndarray_slice(t: &burn::backend::ndarray::NdArrayTensor) -> Option<&[Self]> {
                match t {
                    burn::backend::ndarray::NdArrayTensor::$variant(s) => s.view().to_slice(),
                    _ => None,
                }
            }
            fn from_data(data: TensorData) -> Vec<Self> {
                data.try_into_vec_as::<$t>().expect("float tensor data")
            }
            fn tape(tape: Arc<Tape<Self>>) -> RolloutTape {
                RolloutTape::$variant(tape)
            }
            fn untape(tape: &RolloutTape) -> &Tape<Self> {
                match tape {
                    RolloutTape::$variant(t) => t,
                    _ => panic!("a rollout tape read in another precision"),
                }
            }
        }
    };
}

host_float!(f32, F32);
host_float!(f64, F64);

/// Reading float tensors on the host.
trait HostAccess: Backend {
    /// The values of `t` as `T`: borrowed when the backend stores them contiguously as `T`.
    fn read<T: HostFloat>(t: &FloatTensor<Self>) -> Cow<'_, [T]>;
}

fn read_copy<B: Backend, T: HostFloat>(t: &FloatTensor<B>) -> Vec<T> {
    let data =
        burn::tensor::read_sync(B::float_into_data(t.clone())).expect("tensor data is readable");
    T::from_data(data)
}

impl HostAccess for burn::backend::Flex {
    fn read<T: HostFloat>(t: &FloatTensor<Self>) -> Cow<'_, [T]> {
        match T::flex_slice(t) {
            Some(s) => Cow::Borrowed(s),
            None => Cow::Owned(read_copy::<Self, T>(t)),
        }
    }
}

#[allow(deprecated)]
impl HostAccess for burn::backend::NdArray {
    fn read<T: HostFloat>(t: &FloatTensor<Self>) -> Cow<'_, [T]> {
        // Reading through `TensorData` walks the array element by element: ten times the cost of
        // the whole kernel on a rollout's worth of states.
        match T::ndarray_slice(t) {
            Some(s) => Cow::Borrowed(s),
            None => Cow::Owned(read_copy::<Self, T>(t)),
        }
    }
}

fn upload<B: Backend, T: HostFloat>(
    values: Vec<T>,
    shape: Vec<usize>,
    device: &B::Device,
) -> FloatTensor<B> {
    B::float_from_data(TensorData::new(values, shape), device)
}

/// Runs `$f::<B, f32>` or `$f::<B, f64>` by the dtype of `$t`.
macro_rules! by_dtype {
    ($t:expr, $f:ident::<$b:ty>($($arg:expr),*)) => {
        if $t.dtype() == DType::F64 { $f::<$b, f64>($($arg),*) } else { $f::<$b, f32>($($arg),*) }
    };
}

/// A fused op's `x`, `v`, `k`, `b` on the host.
struct HostInputs<'a, T: Clone> {
    x: Cow<'a, [T]>,
    v: Cow<'a, [T]>,
    k: Cow<'a, [T]>,
    b: Cow<'a, [T]>,
}

impl<'a, T: HostFloat> HostInputs<'a, T> {
    fn read<B: HostAccess>(s: &'a SpringInputs<B>) -> Self {
        let [x, v, k, b] = [&s.x, &s.v, &s.k, &s.b].map(|t| B::read::<T>(t));
        Self { x, v, k, b }
    }

    fn view(&self) -> cpu::Inputs<'_, T> {
        cpu::Inputs {
            x: &self.x,
            v: &self.v,
            k: &self.k,
            b: &self.b,
        }
    }
}

/// Runs a backward kernel into fresh gradient buffers shaped like `x` (`[B, P, 3]`) and
/// `[params]`, and uploads them next to `x`.
fn spring_grads<B: HostAccess, T: HostFloat>(
    x: &FloatTensor<B>,
    params: usize,
    kernel: impl FnOnce(cpu::Grads<T>),
) -> SpringGrads<B> {
    let (shape, device) = (x.shape().to_vec(), x.device());
    let n = shape.iter().product();
    let (mut gx, mut gv) = (vec![T::zero(); n], vec![T::zero(); n]);
    let (mut gk, mut gb) = (vec![T::zero(); params], vec![T::zero(); params]);
    kernel(cpu::Grads {
        x: &mut gx,
        v: &mut gv,
        k: &mut gk,
        b: &mut gb,
    });
    SpringGrads {
        x: upload::<B, T>(gx, shape.clone(), &device),
        v: upload::<B, T>(gv, shape, &device),
        k: upload::<B, T>(gk, vec![params], &device),
        b: upload::<B, T>(gb, vec![params], &device),
    }
}

fn forces<B: HostAccess, T: HostFloat>(s: SpringInputs<B>, graph: &HostGraph) -> FloatTensor<B> {
    let inputs = HostInputs::<T>::read(&s);
    let mut out = vec![T::zero(); inputs.x.len()];
    cpu::forces(graph, inputs.view(), &mut out);
    upload::<B, T>(out, s.x.shape().to_vec(), &s.x.device())
}

fn forces_backward<B: HostAccess, T: HostFloat>(
    s: SpringInputs<B>,
    grad: FloatTensor<B>,
    graph: &HostGraph,
) -> SpringGrads<B> {
    let (inputs, gs) = (HostInputs::<T>::read(&s), B::read::<T>(&grad));
    spring_grads::<B, T>(&s.x, graph.num_params(), |grads| {
        cpu::forces_backward(graph, inputs.view(), &gs, grads)
    })
}

fn step<B: HostAccess, T: HostFloat>(
    s: SpringInputs<B>,
    pins: StepPins<B>,
    graph: &HostGraph,
    params: StepParams,
) -> FloatTensor<B> {
    let inputs = HostInputs::<T>::read(&s);
    let [ps, pxs, pvs] = [&pins.pinned, &pins.x, &pins.v].map(|t| B::read::<T>(t));
    let mut out = vec![T::zero(); 3 * inputs.x.len()];
    let pins = Pins {
        pinned: &ps,
        x: &pxs,
        v: &pvs,
    };
    cpu::step(graph, inputs.view(), pins, params, &mut out);
    let mut shape = s.x.shape().to_vec();
    shape.insert(0, 3);
    upload::<B, T>(out, shape, &s.x.device())
}

fn step_backward<B: HostAccess, T: HostFloat>(
    s: SpringInputs<B>,
    [pinned, grad]: [FloatTensor<B>; 2],
    graph: &HostGraph,
    params: StepParams,
) -> SpringGrads<B> {
    let inputs = HostInputs::<T>::read(&s);
    let (ps, gs) = (B::read::<T>(&pinned), B::read::<T>(&grad));
    spring_grads::<B, T>(&s.x, graph.num_params(), |grads| {
        cpu::step_backward(graph, inputs.view(), &ps, params, &gs, grads)
    })
}

/// Runs `body` on the host data of a rollout's inputs.
fn with_data<B: HostAccess, T: HostFloat, R>(
    inputs: &RolloutInputs<B>,
    body: impl FnOnce(RolloutData<T>) -> R,
) -> R {
    let [batch, frames, _, _] = inputs.target.shape().dims::<4>();
    let (x0, v0, k, b) = (
        B::read::<T>(&inputs.x0),
        B::read::<T>(&inputs.v0),
        B::read::<T>(&inputs.k),
        B::read::<T>(&inputs.b),
    );
    let (pinned, path, target) = (
        B::read::<T>(&inputs.pinned),
        B::read::<T>(&inputs.path),
        B::read::<T>(&inputs.target),
    );
    body(RolloutData {
        x0: &x0,
        v0: &v0,
        pinned: &pinned,
        path: &path,
        target: &target,
        k: &k,
        b: &b,
        batch,
        frames,
    })
}

fn rollout_forward<B: HostAccess, T: HostFloat>(
    inputs: &RolloutInputs<B>,
    graph: &HostGraph,
    params: RolloutParams,
) -> (FloatTensor<B>, RolloutTape) {
    let (losses, tape) = with_data::<B, T, _>(inputs, |d| rollout::forward(graph, d, params));
    let values: Vec<T> = losses.iter().map(|&l| T::from(l).expect("float")).collect();
    (
        upload::<B, T>(values, vec![3], &inputs.k.device()),
        T::tape(tape),
    )
}

fn rollout_backward<B: HostAccess, T: HostFloat>(
    inputs: &RolloutInputs<B>,
    graph: &HostGraph,
    params: RolloutParams,
    tape: &RolloutTape,
    w: [f64; 3],
) -> (FloatTensor<B>, FloatTensor<B>) {
    let (gk, gb) = with_data::<B, T, _>(inputs, |d| T::untape(tape).backward(graph, d, params, w));
    let (s, device) = (graph.num_params(), inputs.k.device());
    (
        upload::<B, T>(gk, vec![s], &device),
        upload::<B, T>(gb, vec![s], &device),
    )
}

/// Implements [`SpringBackend`] and [`RolloutKernels`] for a CPU backend.
macro_rules! cpu_backend {
    ($backend:ty) => {
        impl SpringBackend for $backend {
            fn spring_forces(s: SpringInputs<Self>, graph: Arc<HostGraph>) -> FloatTensor<Self> {
                by_dtype!(s.x, forces::<Self>(s, &graph))
            }

            fn spring_forces_backward(
                s: SpringInputs<Self>,
                grad: FloatTensor<Self>,
                graph: Arc<HostGraph>,
            ) -> SpringGrads<Self> {
                by_dtype!(s.x, forces_backward::<Self>(s, grad, &graph))
            }

            fn cloth_step(
                s: SpringInputs<Self>,
                pins: StepPins<Self>,
                graph: Arc<HostGraph>,
                params: StepParams,
            ) -> FloatTensor<Self> {
                by_dtype!(s.x, step::<Self>(s, pins, &graph, params))
            }

            fn cloth_step_backward(
                s: SpringInputs<Self>,
                pinned: FloatTensor<Self>,
                grad: FloatTensor<Self>,
                graph: Arc<HostGraph>,
                params: StepParams,
            ) -> SpringGrads<Self> {
                by_dtype!(
                    s.x,
                    step_backward::<Self>(s, [pinned, grad], &graph, params)
                )
            }

            fn rollout_loss(
                inputs: RolloutInputs<Self>,
                graph: Arc<HostGraph>,
                params: RolloutParams,
            ) -> FloatTensor<Self> {
                <Self as RolloutKernels>::rollout_forward(&inputs, &graph, params).0
            }
        }

        impl RolloutKernels for $backend {
            fn rollout_forward(
                inputs: &RolloutInputs<Self>,
                graph: &HostGraph,
                params: RolloutParams,
            ) -> (FloatTensor<Self>, RolloutTape) {
                by_dtype!(inputs.x0, rollout_forward::<Self>(inputs, graph, params))
            }

            fn rollout_backward(
                inputs: &RolloutInputs<Self>,
                graph: &HostGraph,
                params: RolloutParams,
                tape: &RolloutTape,
                w: [f64; 3],
            ) -> (FloatTensor<Self>, FloatTensor<Self>) {
                by_dtype!(
                    inputs.x0,
                    rollout_backward::<Self>(inputs, graph, params, tape, w)
                )
            }
        }
    };
}

cpu_backend!(burn::backend::Flex);
#[allow(deprecated)]
mod ndarray_impl {
    use super::*;
    cpu_backend!(burn::backend::NdArray);
}
