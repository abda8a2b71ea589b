//! The fused ops under Burn's autodiff: each records one graph node whose backward calls the
//! hand-written backward kernel of the inner backend.

use std::sync::Arc;

use burn::backend::Backend;
use burn::backend::autodiff::Autodiff;
use burn::backend::autodiff::checkpoint::{base::Checkpointer, strategy::CheckpointStrategy};
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
use burn::backend::tensor::FloatTensor;

use super::{
    HostGraph, RolloutInputs, RolloutKernels, RolloutParams, RolloutTape, SpringBackend,
    SpringGrads, SpringInputs, StepParams, StepPins,
};

/// Registers the gradients of the tracked parents.
macro_rules! register {
    ($b:ty, $grads:expr, $parents:expr, [$($value:expr),*]) => {
        for (node, value) in $parents.into_iter().zip([$($value),*]) {
            if let Some(node) = node {
                $grads.register::<$b>(node.id, value);
            }
        }
    };
}

/// The inner backend's inputs of an autodiff op: its tensors' primitives.
fn primitives<B: Backend, C: CheckpointStrategy>(
    s: SpringInputs<Autodiff<B, C>>,
) -> SpringInputs<B> {
    SpringInputs {
        x: s.x.into_primitive(),
        v: s.v.into_primitive(),
        k: s.k.into_primitive(),
        b: s.b.into_primitive(),
    }
}

#[derive(Debug)]
struct SpringForcesBackward;

impl<B: SpringBackend + RolloutKernels> Backward<B, 4> for SpringForcesBackward {
    type State = (SpringInputs<B>, Arc<HostGraph>);

    fn backward(self, ops: Ops<Self::State, 4>, grads: &mut Gradients, _: &mut Checkpointer) {
        let grad = grads.consume::<B>(&ops.node);
        let (s, graph) = ops.state;
        let g = B::spring_forces_backward(s, grad, graph);
        register!(B, grads, ops.parents, [g.x, g.v, g.k, g.b]);
    }
}

/// What the fused step's backward needs.
#[derive(Debug, Clone)]
struct StepState<B: Backend> {
    s: SpringInputs<B>,
    pinned: FloatTensor<B>,
    graph: Arc<HostGraph>,
    params: StepParams,
}

#[derive(Debug)]
struct ClothStepBackward;

impl<B: SpringBackend + RolloutKernels> Backward<B, 4> for ClothStepBackward {
    type State = StepState<B>;

    fn backward(self, ops: Ops<Self::State, 4>, grads: &mut Gradients, _: &mut Checkpointer) {
        let grad = grads.consume::<B>(&ops.node);
        let s = ops.state;
        let g = B::cloth_step_backward(s.s, s.pinned, grad, s.graph, s.params);
        register!(B, grads, ops.parents, [g.x, g.v, g.k, g.b]);
    }
}

/// What the fused rollout's backward needs.
#[derive(Debug, Clone)]
struct RolloutState<B: Backend> {
    inputs: RolloutInputs<B>,
    graph: Arc<HostGraph>,
    params: RolloutParams,
    tape: RolloutTape,
}

#[derive(Debug)]
struct RolloutBackward;

impl<B: SpringBackend + RolloutKernels> Backward<B, 2> for RolloutBackward {
    type State = RolloutState<B>;

    fn backward(self, ops: Ops<Self::State, 2>, grads: &mut Gradients, _: &mut Checkpointer) {
        let grad = grads.consume::<B>(&ops.node);
        let data = burn::tensor::read_sync(B::float_into_data(grad)).expect("gradient is readable");
        let w: Vec<f64> = data.try_into_vec_as::<f64>().expect("float gradient");
        let s = ops.state;
        let (gk, gb) =
            B::rollout_backward(&s.inputs, &s.graph, s.params, &s.tape, [w[0], w[1], w[2]]);
        register!(B, grads, ops.parents, [gk, gb]);
    }
}

impl<B: SpringBackend + RolloutKernels, C: CheckpointStrategy> SpringBackend for Autodiff<B, C> {
    fn spring_forces(s: SpringInputs<Self>, graph: Arc<HostGraph>) -> FloatTensor<Self> {
        let parents = [s.x.node(), s.v.node(), s.k.node(), s.b.node()];
        let s = primitives(s);
        match SpringForcesBackward
            .prepare::<C>(parents)
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => {
                let out = B::spring_forces(s.clone(), graph.clone());
                prep.finish((s, graph), out)
            }
            OpsKind::UnTracked(prep) => prep.finish(B::spring_forces(s, graph)),
        }
    }

    fn spring_forces_backward(
        _s: SpringInputs<Self>,
        _grad: FloatTensor<Self>,
        _graph: Arc<HostGraph>,
    ) -> SpringGrads<Self> {
        unimplemented!("the backward of the fused op is not itself differentiable")
    }

    fn cloth_step(
        s: SpringInputs<Self>,
        pins: StepPins<Self>,
        graph: Arc<HostGraph>,
        params: StepParams,
    ) -> FloatTensor<Self> {
        let pins: StepPins<B> = StepPins {
            pinned: pins.pinned.into_primitive(),
            x: pins.x.into_primitive(),
            v: pins.v.into_primitive(),
        };
        let parents = [s.x.node(), s.v.node(), s.k.node(), s.b.node()];
        let s = primitives(s);
        match ClothStepBackward
            .prepare::<C>(parents)
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => {
                let pinned = pins.pinned.clone();
                let out = B::cloth_step(s.clone(), pins, graph.clone(), params);
                let state = StepState {
                    s,
                    pinned,
                    graph,
                    params,
                };
                prep.finish(state, out)
            }
            OpsKind::UnTracked(prep) => prep.finish(B::cloth_step(s, pins, graph, params)),
        }
    }

    fn cloth_step_backward(
        _s: SpringInputs<Self>,
        _pinned: FloatTensor<Self>,
        _grad: FloatTensor<Self>,
        _graph: Arc<HostGraph>,
        _params: StepParams,
    ) -> SpringGrads<Self> {
        unimplemented!("the backward of the fused step is not itself differentiable")
    }

    fn rollout_loss(
        inputs: RolloutInputs<Self>,
        graph: Arc<HostGraph>,
        params: RolloutParams,
    ) -> FloatTensor<Self> {
        let prepared = RolloutBackward
            .prepare::<C>([inputs.k.node(), inputs.b.node()])
            .compute_bound()
            .stateful();
        let data = |t: FloatTensor<Self>| t.into_primitive();
        let inputs = RolloutInputs {
            x0: data(inputs.x0),
            v0: data(inputs.v0),
            k: data(inputs.k),
            b: data(inputs.b),
            pinned: data(inputs.pinned),
            path: data(inputs.path),
            target: data(inputs.target),
        };
        let (losses, tape) = B::rollout_forward(&inputs, &graph, params);
        match prepared {
            OpsKind::Tracked(prep) => prep.finish(
                RolloutState {
                    inputs,
                    graph,
                    params,
                    tape,
                },
                losses,
            ),
            OpsKind::UnTracked(prep) => prep.finish(losses),
        }
    }
}
