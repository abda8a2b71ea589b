//! Learnable cloth models: the mass-spring surrogate ([`springs`]) and the neural baselines
//! the paper compares it with ([`neural_ode`], [`gnn`]).

pub mod kernels;
pub mod springs;

pub use springs::{Kernel, SpringGraph, SpringNet, spring_forces};

use burn::tensor::Tensor;

use kernels::StepParams;

/// A model of the internal forces of a cloth, stepped by the shared integrator
/// ([`crate::sim::step_frame`]): the spring network, or the Neural ODE baseline.
pub trait ForceModel {
    /// Internal forces `[B, P, 3]` at positions and velocities `[B, P, 3]`; `pinned` is
    /// `[B, P, 1]` (1 = pinned).
    fn internal_forces(&self, x: Tensor<3>, v: Tensor<3>, pinned: &Tensor<3>) -> Tensor<3>;

    /// One fused semi-implicit Euler step `(x', v', f)` when the model has a kernel for it on
    /// this device (see [`kernels::cloth_step`]); `None` steps with tensor ops.
    fn fused_step(
        &self,
        _x: Tensor<3>,
        _v: Tensor<3>,
        _pinned: &Tensor<3>,
        _pin_x: Tensor<3>,
        _pin_v: Tensor<3>,
        _params: StepParams,
    ) -> Option<(Tensor<3>, Tensor<3>, Tensor<3>)> {
        None
    }
}

impl ForceModel for SpringNet {
    fn internal_forces(&self, x: Tensor<3>, v: Tensor<3>, _pinned: &Tensor<3>) -> Tensor<3> {
        self.forces(x, v)
    }

    fn fused_step(
        &self,
        x: Tensor<3>,
        v: Tensor<3>,
        pinned: &Tensor<3>,
        pin_x: Tensor<3>,
        pin_v: Tensor<3>,
        params: StepParams,
    ) -> Option<(Tensor<3>, Tensor<3>, Tensor<3>)> {
        self.graph.fused_rollout().then(|| {
            kernels::cloth_step(
                x,
                v,
                self.k.val(),
                self.b.val(),
                pinned.clone(),
                pin_x,
                pin_v,
                &self.graph.host,
                params,
            )
        })
    }
}
