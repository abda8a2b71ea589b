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
use super::{HostGraph, RolloutInputs, RolloutKernels, RolloutTape, SpringBackend, SpringGrads};

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

fn forces<B: HostAccess, T: HostFloat>(
    x: FloatTensor<B>,
    v: FloatTensor<B>,
    k: FloatTensor<B>,
    b: FloatTensor<B>,
    graph: &HostGraph,
) -> FloatTensor<B> {
    let (xs, vs, ks, bs) = (
        B::read::<T>(&x),
        B::read::<T>(&v),
        B::read::<T>(&k),
        B::read::<T>(&b),
    );
    let mut out = vec![T::zero(); xs.len()];
    cpu::forces(graph, &xs, &vs, &ks, &bs, &mut out);
    upload::<B, T>(out, x.shape().to_vec(), &x.device())
}

fn forces_backward<B: HostAccess, T: HostFloat>(
    x: FloatTensor<B>,
    v: FloatTensor<B>,
    k: FloatTensor<B>,
    b: FloatTensor<B>,
    grad: FloatTensor<B>,
    graph: &HostGraph,
) -> SpringGrads<B> {
    let (xs, vs, ks, bs) = (
        B::read::<T>(&x),
        B::read::<T>(&v),
        B::read::<T>(&k),
        B::read::<T>(&b),
    );
    let gs = B::read::<T>(&grad);
    let s = graph.num_params();
    let (mut gx, mut gv) = (vec![T::zero(); xs.len()], vec![T::zero(); xs.len()]);
    let (mut gk, mut gb) = (vec![T::zero(); s], vec![T::zero(); s]);
    cpu::forces_backward(
        graph, &xs, &vs, &ks, &bs, &gs, &mut gx, &mut gv, &mut gk, &mut gb,
    );
    let (shape, device) = (x.shape().to_vec(), x.device());
    SpringGrads {
        x: upload::<B, T>(gx, shape.clone(), &device),
        v: upload::<B, T>(gv, shape, &device),
        k: upload::<B, T>(gk, vec![s], &device),
        b: upload::<B, T>(gb, vec![s], &device),
    }
}

#[allow(clippy::too_many_arguments)]
fn step<B: HostAccess, T: HostFloat>(
    x: FloatTensor<B>,
    v: FloatTensor<B>,
    k: FloatTensor<B>,
    b: FloatTensor<B>,
    pinned: FloatTensor<B>,
    pin_x: FloatTensor<B>,
    pin_v: FloatTensor<B>,
    graph: &HostGraph,
    params: StepParams,
) -> FloatTensor<B> {
    let (xs, vs, ks, bs) = (
        B::read::<T>(&x),
        B::read::<T>(&v),
        B::read::<T>(&k),
        B::read::<T>(&b),
    );
    let (ps, pxs, pvs) = (
        B::read::<T>(&pinned),
        B::read::<T>(&pin_x),
        B::read::<T>(&pin_v),
    );
    let mut out = vec![T::zero(); 3 * xs.len()];
    let pins = Pins {
        pinned: &ps,
        x: &pxs,
        v: &pvs,
    };
    cpu::step(graph, &xs, &vs, &ks, &bs, pins, params, &mut out);
    let mut shape = x.shape().to_vec();
    shape.insert(0, 3);
    upload::<B, T>(out, shape, &x.device())
}

#[allow(clippy::too_many_arguments)]
fn step_backward<B: HostAccess, T: HostFloat>(
    x: FloatTensor<B>,
    v: FloatTensor<B>,
    k: FloatTensor<B>,
    b: FloatTensor<B>,
    pinned: FloatTensor<B>,
    grad: FloatTensor<B>,
    graph: &HostGraph,
    params: StepParams,
) -> SpringGrads<B> {
    let (xs, vs, ks, bs) = (
        B::read::<T>(&x),
        B::read::<T>(&v),
        B::read::<T>(&k),
        B::read::<T>(&b),
    );
    let (ps, gs) = (B::read::<T>(&pinned), B::read::<T>(&grad));
    let s = graph.num_params();
    let (mut gx, mut gv) = (vec![T::zero(); xs.len()], vec![T::zero(); xs.len()]);
    let (mut gk, mut gb) = (vec![T::zero(); s], vec![T::zero(); s]);
    cpu::step_backward(
        graph, &xs, &vs, &ks, &bs, &ps, params, &gs, &mut gx, &mut gv, &mut gk, &mut gb,
    );
    let (shape, device) = (x.shape().to_vec(), x.device());
    SpringGrads {
        x: upload::<B, T>(gx, shape.clone(), &device),
        v: upload::<B, T>(gv, shape, &device),
        k: upload::<B, T>(gk, vec![s], &device),
        b: upload::<B, T>(gb, vec![s], &device),
    }
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
    let (gk, gb) = with_data::<B, T, _>(inputs, |d| {
        rollout::backward(graph, d, params, T::untape(tape), w)
    });
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
            fn spring_forces(
                x: FloatTensor<Self>,
                v: FloatTensor<Self>,
                k: FloatTensor<Self>,
                b: FloatTensor<Self>,
                graph: Arc<HostGraph>,
            ) -> FloatTensor<Self> {
                by_dtype!(x, forces::<Self>(x, v, k, b, &graph))
            }

            fn spring_forces_backward(
                x: FloatTensor<Self>,
                v: FloatTensor<Self>,
                k: FloatTensor<Self>,
                b: FloatTensor<Self>,
                grad: FloatTensor<Self>,
                graph: Arc<HostGraph>,
            ) -> SpringGrads<Self> {
                by_dtype!(x, forces_backward::<Self>(x, v, k, b, grad, &graph))
            }

            fn cloth_step(
                x: FloatTensor<Self>,
                v: FloatTensor<Self>,
                k: FloatTensor<Self>,
                b: FloatTensor<Self>,
                pinned: FloatTensor<Self>,
                pin_x: FloatTensor<Self>,
                pin_v: FloatTensor<Self>,
                graph: Arc<HostGraph>,
                params: StepParams,
            ) -> FloatTensor<Self> {
                by_dtype!(
                    x,
                    step::<Self>(x, v, k, b, pinned, pin_x, pin_v, &graph, params)
                )
            }

            fn cloth_step_backward(
                x: FloatTensor<Self>,
                v: FloatTensor<Self>,
                k: FloatTensor<Self>,
                b: FloatTensor<Self>,
                pinned: FloatTensor<Self>,
                grad: FloatTensor<Self>,
                graph: Arc<HostGraph>,
                params: StepParams,
            ) -> SpringGrads<Self> {
                by_dtype!(
                    x,
                    step_backward::<Self>(x, v, k, b, pinned, grad, &graph, params)
                )
            }

            fn rollout_loss(
                x0: FloatTensor<Self>,
                v0: FloatTensor<Self>,
                k: FloatTensor<Self>,
                b: FloatTensor<Self>,
                pinned: FloatTensor<Self>,
                path: FloatTensor<Self>,
                target: FloatTensor<Self>,
                graph: Arc<HostGraph>,
                params: RolloutParams,
            ) -> FloatTensor<Self> {
                let inputs = RolloutInputs::<Self> {
                    x0,
                    v0,
                    k,
                    b,
                    pinned,
                    path,
                    target,
                };
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
