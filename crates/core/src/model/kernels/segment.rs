//! Gathers and sums by index without a scatter: the message passing of the GNN baseline.
//!
//! A graph network gathers node rows onto edges (`h[senders]`) and sums edge rows into their
//! receiving nodes. With Burn's tensor ops those are `select` and `select_assign(Add)`, and the
//! backward of `select` is again a `select_assign`. On the CubeCL backend `select_assign` runs
//! one thread per *column* that walks every index in turn (for 65 k edges of width 128: 128
//! threads, each 65 k dependent read-modify-writes): on an H200 a GNN training step of the
//! paper's size took 2.05 s with them and 1.19 s without. Here both directions are gathers:
//!
//! - [`SegmentBackend::segment_sum`]: `out[n] = Σ values[e]` over the entries `e` with
//!   `owner[e] = n`, one thread per output element walking its segment in a CSR list (no float
//!   atomics: neither portable on wgpu nor deterministic); its backward is `select(grad, owner)`;
//! - [`SegmentBackend::gather_rows`]: `out[e] = x[owner[e]]` (`select`), whose backward is
//!   [`SegmentBackend::segment_sum`].
//!
//! The CPU backends sum with their own `select_assign` (one pass over the entries is what a
//! CPU does anyway); `Autodiff<B>` records one node per op whose backward is the other op.

use std::sync::Arc;

use burn::backend::autodiff::Autodiff;
use burn::backend::autodiff::checkpoint::{base::Checkpointer, strategy::CheckpointStrategy};
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
use burn::backend::tensor::{FloatTensor, IntTensor};
use burn::backend::{Backend, Dispatch, TensorMetadata, backend_extension};
use burn::tensor::{IndexingUpdateOp, Int, Shape, Tensor, TensorData};

/// Which segment every entry belongs to, and the entries grouped by segment (CSR).
///
/// Built only through [`Segments::new`], which checks every index, so that the kernels may
/// index without bounds checks.
#[derive(Debug)]
pub struct Segments {
    /// Entries `E`.
    entries: usize,
    /// `offsets[n]..offsets[n + 1]` are segment `n`'s positions in `order`, `[N + 1]`.
    offsets: Vec<u32>,
    /// Entries grouped by segment, in increasing order within each, `[E]`.
    order: Vec<u32>,
    /// The CSR list on the CubeCL devices it ran on.
    #[cfg(feature = "wgpu")]
    pub(super) cube: super::cube::CubeCache<super::cube::CubeSegments>,
}

impl Segments {
    /// Entries `owner[e] ∈ 0..segments`.
    ///
    /// Panics if an owner is out of range or there are more than `u32::MAX` of either.
    pub fn new(owner: &[i64], segments: usize) -> Self {
        assert!(
            segments < u32::MAX as usize && owner.len() < u32::MAX as usize,
            "{segments} segments or {} entries do not fit 32-bit indices",
            owner.len()
        );
        let owner: Vec<u32> = owner
            .iter()
            .map(|&n| {
                assert!(
                    (0..segments as i64).contains(&n),
                    "segment {n} outside {segments}"
                );
                n as u32
            })
            .collect();
        let mut offsets = vec![0u32; segments + 1];
        for &n in &owner {
            offsets[n as usize + 1] += 1;
        }
        for n in 0..segments {
            offsets[n + 1] += offsets[n];
        }
        let mut fill = offsets.clone();
        let mut order = vec![0u32; owner.len()];
        for (e, &n) in owner.iter().enumerate() {
            order[fill[n as usize] as usize] = e as u32;
            fill[n as usize] += 1;
        }
        Self {
            entries: owner.len(),
            offsets,
            order,
            #[cfg(feature = "wgpu")]
            cube: Default::default(),
        }
    }

    /// Number of segments `N`.
    pub(crate) fn num_segments(&self) -> usize {
        self.offsets.len() - 1
    }

    /// Number of entries `E`.
    pub(crate) fn num_entries(&self) -> usize {
        self.entries
    }

    /// CSR offsets `[N + 1]`.
    pub(crate) fn offsets(&self) -> &[u32] {
        &self.offsets
    }

    /// Entries grouped by segment `[E]`.
    pub fn order(&self) -> &[u32] {
        &self.order
    }
}

/// Backends that run [`SegmentBackend::segment_sum`] and [`SegmentBackend::gather_rows`].
#[backend_extension(Autodiff, Cube: cfg(feature = "wgpu"), Flex, NdArray)]
pub trait SegmentBackend: Backend {
    /// `[E, L] → [N, L]`: the rows of `values` summed by segment. `owner` `[E]` is
    /// `segments`' owner list on the device.
    fn segment_sum(
        values: FloatTensor<Self>,
        owner: IntTensor<Self>,
        segments: Arc<Segments>,
    ) -> FloatTensor<Self>;

    /// `[N, L] → [E, L]`: row `owner[e]` of `x` for every entry.
    fn gather_rows(
        x: FloatTensor<Self>,
        owner: IntTensor<Self>,
        segments: Arc<Segments>,
    ) -> FloatTensor<Self>;
}

/// A segmentation and its owner list on a device, built once and shared by every op over it.
#[derive(Debug, Clone)]
pub struct DeviceSegments {
    host: Arc<Segments>,
    owner: Tensor<1, Int>,
}

impl DeviceSegments {
    /// `owner[e] ∈ 0..segments` for every entry, uploaded to `device`.
    pub fn new(owner: &[i64], segments: usize, device: &burn::tensor::Device) -> Self {
        let host = Arc::new(Segments::new(owner, segments));
        let owner =
            Tensor::<1, Int>::from_data(TensorData::new(owner.to_vec(), [owner.len()]), device);
        Self { host, owner }
    }

    /// `segments` with its owner list `owner` already on a device (a module's field, which
    /// moves with the module).
    pub fn over(segments: Arc<Segments>, owner: Tensor<1, Int>) -> Self {
        assert_eq!(
            owner.dims()[0],
            segments.num_entries(),
            "one owner per entry of the segmentation"
        );
        Self {
            host: segments,
            owner,
        }
    }

    /// `[E, L] → [N, L]`: the rows of `values` summed by segment.
    pub fn sum(&self, values: Tensor<2>) -> Tensor<2> {
        Tensor::from_dispatch(<Dispatch as SegmentBackend>::segment_sum(
            values.into_dispatch(),
            self.owner.clone().into_dispatch(),
            self.host.clone(),
        ))
    }

    /// `[N, L] → [E, L]`: each entry's row of `x`.
    pub fn gather(&self, x: Tensor<2>) -> Tensor<2> {
        Tensor::from_dispatch(<Dispatch as SegmentBackend>::gather_rows(
            x.into_dispatch(),
            self.owner.clone().into_dispatch(),
            self.host.clone(),
        ))
    }
}

/// [`SegmentBackend::segment_sum`] by the backend's own indexed add (the CPU backends).
pub(super) fn sum_by_select_assign<B: Backend>(
    values: FloatTensor<B>,
    owner: IntTensor<B>,
    segments: &Segments,
) -> FloatTensor<B> {
    let shape = values.shape();
    let zeros = B::float_zeros(
        Shape::from(vec![segments.num_segments(), shape[1]]),
        &values.device(),
        values.dtype().into(),
    );
    B::float_select_assign(zeros, 0, owner, values, IndexingUpdateOp::Add)
}

/// [`SegmentBackend::gather_rows`] by the backend's own `select` (a gather on every backend).
pub(super) fn select_rows<B: Backend>(x: FloatTensor<B>, owner: IntTensor<B>) -> FloatTensor<B> {
    B::float_select(x, 0, owner)
}

/// Implements [`SegmentBackend`] for a CPU backend.
macro_rules! cpu_segments {
    ($backend:ty) => {
        impl SegmentBackend for $backend {
            fn segment_sum(
                values: FloatTensor<Self>,
                owner: IntTensor<Self>,
                segments: Arc<Segments>,
            ) -> FloatTensor<Self> {
                sum_by_select_assign::<Self>(values, owner, &segments)
            }

            fn gather_rows(
                x: FloatTensor<Self>,
                owner: IntTensor<Self>,
                _segments: Arc<Segments>,
            ) -> FloatTensor<Self> {
                select_rows::<Self>(x, owner)
            }
        }
    };
}

cpu_segments!(burn::backend::Flex);
#[allow(deprecated)]
mod ndarray_impl {
    use super::*;
    cpu_segments!(burn::backend::NdArray);
}

/// The two ops, each the other's adjoint.
#[derive(Debug, Clone, Copy)]
enum SegmentOp {
    /// [`SegmentBackend::segment_sum`].
    Sum,
    /// [`SegmentBackend::gather_rows`].
    Gather,
}

impl SegmentOp {
    fn run<B: SegmentBackend>(
        self,
        x: FloatTensor<B>,
        owner: IntTensor<B>,
        segments: Arc<Segments>,
    ) -> FloatTensor<B> {
        match self {
            Self::Sum => B::segment_sum(x, owner, segments),
            Self::Gather => B::gather_rows(x, owner, segments),
        }
    }

    /// The op whose forward is this one's vector-Jacobian product.
    fn adjoint(self) -> Self {
        match self {
            Self::Sum => Self::Gather,
            Self::Gather => Self::Sum,
        }
    }

    /// The op on `Autodiff<B>`: one node whose backward is the adjoint op.
    fn record<B: SegmentBackend, C: CheckpointStrategy>(
        self,
        x: FloatTensor<Autodiff<B, C>>,
        owner: IntTensor<B>,
        segments: Arc<Segments>,
    ) -> FloatTensor<Autodiff<B, C>> {
        match (SegmentBackward(self.adjoint()))
            .prepare::<C>([x.node()])
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => {
                let out = self.run::<B>(x.into_primitive(), owner.clone(), segments.clone());
                prep.finish((owner, segments), out)
            }
            OpsKind::UnTracked(prep) => {
                prep.finish(self.run::<B>(x.into_primitive(), owner, segments))
            }
        }
    }
}

/// The backward of a segment op: its adjoint op applied to the upstream gradient.
#[derive(Debug)]
struct SegmentBackward(SegmentOp);

impl<B: SegmentBackend> Backward<B, 1> for SegmentBackward {
    type State = (IntTensor<B>, Arc<Segments>);

    fn backward(self, ops: Ops<Self::State, 1>, grads: &mut Gradients, _: &mut Checkpointer) {
        let grad = grads.consume::<B>(&ops.node);
        let (owner, segments) = ops.state;
        if let Some(node) = &ops.parents[0] {
            grads.register::<B>(node.id, self.0.run::<B>(grad, owner, segments));
        }
    }
}

impl<B: SegmentBackend, C: CheckpointStrategy> SegmentBackend for Autodiff<B, C> {
    fn segment_sum(
        values: FloatTensor<Self>,
        owner: IntTensor<Self>,
        segments: Arc<Segments>,
    ) -> FloatTensor<Self> {
        SegmentOp::Sum.record::<B, C>(values, owner, segments)
    }

    fn gather_rows(
        x: FloatTensor<Self>,
        owner: IntTensor<Self>,
        segments: Arc<Segments>,
    ) -> FloatTensor<Self> {
        SegmentOp::Gather.record::<B, C>(x, owner, segments)
    }
}
