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
    SpringGrads, StepParams,
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

#[derive(Debug)]
struct SpringForcesBackward;

impl<B: SpringBackend + RolloutKernels> Backward<B, 4> for SpringForcesBackward {
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
        let grad = grads.consume::<B>(&ops.node);
        let (x, v, k, b, graph) = ops.state;
        let g = B::spring_forces_backward(x, v, k, b, grad, graph);
        register!(B, grads, ops.parents, [g.x, g.v, g.k, g.b]);
    }
}

/// What the fused step's backward needs.
#[derive(Debug, Clone)]
struct StepState<B: Backend> {
    x: FloatTensor<B>,
    v: FloatTensor<B>,
    k: FloatTensor<B>,
    b: FloatTensor<B>,
    pinned: FloatTensor<B>,
    graph: Arc<HostGraph>,
    params: StepParams,
}

#[derive(Debug)]
struct ClothStepBackward;

impl<B: SpringBackend + RolloutKernels> Backward<B, 4> for ClothStepBackward {
    type State = StepState<B>;

    fn backward(
        self,
        ops: Ops<Self::State, 4>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        let grad = grads.consume::<B>(&ops.node);
        let s = ops.state;
        let g = B::cloth_step_backward(s.x, s.v, s.k, s.b, s.pinned, grad, s.graph, s.params);
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

    fn backward(
        self,
        ops: Ops<Self::State, 2>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
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
        let (pinned, pin_x, pin_v) = (
            pinned.into_primitive(),
            pin_x.into_primitive(),
            pin_v.into_primitive(),
        );
        match ClothStepBackward
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
                let out = B::cloth_step(
                    x.clone(),
                    v.clone(),
                    k.clone(),
                    b.clone(),
                    pinned.clone(),
                    pin_x,
                    pin_v,
                    graph.clone(),
                    params,
                );
                let state = StepState {
                    x,
                    v,
                    k,
                    b,
                    pinned,
                    graph,
                    params,
                };
                prep.finish(state, out)
            }
            OpsKind::UnTracked(prep) => prep.finish(B::cloth_step(
                x.into_primitive(),
                v.into_primitive(),
                k.into_primitive(),
                b.into_primitive(),
                pinned,
                pin_x,
                pin_v,
                graph,
                params,
            )),
        }
    }

    fn cloth_step_backward(
        _x: FloatTensor<Self>,
        _v: FloatTensor<Self>,
        _k: FloatTensor<Self>,
        _b: FloatTensor<Self>,
        _pinned: FloatTensor<Self>,
        _grad: FloatTensor<Self>,
        _graph: Arc<HostGraph>,
        _params: StepParams,
    ) -> SpringGrads<Self> {
        unimplemented!("the backward of the fused step is not itself differentiable")
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
        let data = |t: FloatTensor<Self>| t.into_primitive();
        let (x0, v0, pinned, path, target) =
            (data(x0), data(v0), data(pinned), data(path), data(target));
        let prepared = RolloutBackward
            .prepare::<C>([k.node(), b.node()])
            .compute_bound()
            .stateful();
        let inputs = RolloutInputs {
            x0,
            v0,
            k: k.into_primitive(),
            b: b.into_primitive(),
            pinned,
            path,
            target,
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
