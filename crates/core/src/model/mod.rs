//! Learnable cloth models: the mass-spring surrogate ([`springs`]) and the neural baselines
//! the paper compares it with ([`neural_ode`], [`gnn`]).

pub mod gnn;
pub mod kernels;
pub mod neural_ode;
pub mod springs;

pub use gnn::{Gnn, GnnConfig};
pub use neural_ode::{NeuralOde, NeuralOdeConfig};
pub use springs::{FusedOn, Kernel, SpringGraph, SpringNet};

use burn::tensor::Tensor;
use serde::{Deserialize, Serialize};

use crate::settings::Auto;
use kernels::StepParams;

/// The model families: the paper's surrogate and its two baselines.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ModelKind {
    /// The mass-spring surrogate ([`SpringNet`]).
    #[default]
    Springs,
    /// The Neural ODE baseline ([`NeuralOde`]).
    NeuralOde,
    /// The graph-network baseline ([`Gnn`]).
    Gnn,
}

impl ModelKind {
    /// Every kind, in the order of the paper's Table 2.
    pub const ALL: [ModelKind; 3] = [ModelKind::Springs, ModelKind::Gnn, ModelKind::NeuralOde];

    /// The name used in configs and tables.
    pub fn name(self) -> &'static str {
        match self {
            ModelKind::Springs => "springs",
            ModelKind::NeuralOde => "neural_ode",
            ModelKind::Gnn => "gnn",
        }
    }
}

/// The `[model]` section: which model, and its initial parameters or architecture.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ModelConfig {
    /// The model family.
    pub kind: ModelKind,
    /// Initial stiffness of every spring, N/m (springs); `"auto"`: the least-squares uniform
    /// stiffness of the training data's forces (Eq. 4 is linear in `k`), kept stable.
    pub k_init: Auto<f64>,
    /// Initial damping of every spring, N·s/m (springs); `"auto"`: fitted with `k_init`.
    pub b_init: Auto<f64>,
    /// Initial stiffness of every curvature element (`cloth.curvature`), N/m; `"auto"`:
    /// `k_init / 20` (ours: a bending stiffness `κ h²` small beside the membrane's).
    pub curvature_init: Auto<f64>,
    /// Spring-force implementation: the fused kernel or the tensor-op reference (springs).
    pub kernel: Kernel,
    /// The Neural ODE's architecture.
    pub neural_ode: NeuralOdeConfig,
    /// The GNN's architecture.
    pub gnn: GnnConfig,
}

impl Default for ModelConfig {
    /// Springs whose uniform initial `k` and `b` are fitted to the data.
    fn default() -> Self {
        Self {
            kind: ModelKind::Springs,
            k_init: Auto::Auto,
            b_init: Auto::Auto,
            curvature_init: Auto::Auto,
            kernel: Kernel::Fused,
            neural_ode: NeuralOdeConfig::default(),
            gnn: GnnConfig::default(),
        }
    }
}

impl ModelConfig {
    /// Checks ranges; errors name the key.
    pub fn validate(&self) -> anyhow::Result<()> {
        for (key, v) in [("k_init", self.k_init), ("b_init", self.b_init)] {
            if let Auto::Value(x) = v
                && !x.is_finite()
            {
                anyhow::bail!("`model.{key}` must be finite or \"auto\", is {x}");
            }
        }
        if let Auto::Value(x) = self.curvature_init
            && !(x.is_finite() && x > 0.0)
        {
            anyhow::bail!(
                "`model.curvature_init` must be positive (its learning rate is a fraction of \
                 it) or \"auto\", is {x}"
            );
        }
        self.neural_ode.validate()?;
        self.gnn.validate()
    }

    /// Where the search for the best uniform network starts — the yardstick a learned network is
    /// measured against (`eval.uniform_baseline`, the held-out check, the blend search's polish):
    /// the run's initial uniform network (`train` resolves `"auto"`), else 50 N/m, undamped.
    pub fn uniform_start(&self) -> (f64, f64) {
        (self.k_init.or(50.0), self.b_init.or(0.0))
    }

    /// The curvature elements' initial stiffness beside springs of initial stiffness `k_init`.
    pub(crate) fn curvature_init_for(&self, k_init: f64) -> f64 {
        self.curvature_init.or(k_init / 20.0)
    }
}

/// A model of the internal forces of a cloth, stepped by the shared integrator
/// ([`crate::sim::step_frame`]): the spring network, or the Neural ODE baseline. Shared between
/// threads: the evaluation steps pieces of a batch side by side on the CPU.
pub trait ForceModel: Sync {
    /// Internal forces `[B, P, 3]` at positions and velocities `[B, P, 3]`; `pinned` is
    /// `[B, P, 1]` (1 = pinned).
    fn internal_forces(&self, x: Tensor<3>, v: Tensor<3>, pinned: &Tensor<3>) -> Tensor<3>;

    /// The forces `[B, P, 3]` of an isotropic viscosity `viscosity` per unit stiffness on the
    /// model's springs ([`crate::sim::SimConfig::viscosity`]) at velocities `v`. Only spring
    /// networks have springs: the config refuses `sim.viscosity` for the other models.
    fn viscous_forces(&self, _v: Tensor<3>, _viscosity: f64) -> Tensor<3> {
        panic!("`sim.viscosity` acts on a spring network's springs only")
    }

    /// What softening the shear springs in compression to `shear_compression · k` changes in the
    /// forces at positions `x` (`[B, P, 3]`; [`crate::sim::SimConfig::shear_compression`]), added
    /// to [`ForceModel::internal_forces`]. Only spring networks have shear springs: the config
    /// refuses `sim.shear_compression` for the other models.
    fn compression_forces(&self, _x: Tensor<3>, _shear_compression: f64) -> Tensor<3> {
        panic!("`sim.shear_compression` acts on a spring network's shear springs only")
    }

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

    /// One whole data frame of `span = (substeps, frame_dt)` fused steps `(x', v')`, the pinned
    /// particles moving from `here` to `next`, when the model has a kernel for it on this device
    /// (see [`kernels::cloth_frame`]); `None` steps substep by substep
    /// ([`crate::sim::step_frame`]). It keeps no mean force: for rollouts that keep positions.
    #[allow(clippy::too_many_arguments)]
    fn fused_frame(
        &self,
        _x: Tensor<3>,
        _v: Tensor<3>,
        _pinned: &Tensor<3>,
        _here: &Tensor<3>,
        _next: &Tensor<3>,
        _params: StepParams,
        _span: (usize, f64),
    ) -> Option<(Tensor<3>, Tensor<3>)> {
        None
    }
}

impl ForceModel for SpringNet {
    fn internal_forces(&self, x: Tensor<3>, v: Tensor<3>, _pinned: &Tensor<3>) -> Tensor<3> {
        self.forces(x, v)
    }

    fn viscous_forces(&self, v: Tensor<3>, viscosity: f64) -> Tensor<3> {
        self.graph.viscous_forces(v, self.k.val(), viscosity)
    }

    fn compression_forces(&self, x: Tensor<3>, shear_compression: f64) -> Tensor<3> {
        self.graph
            .compression_forces(x, self.k.val(), shear_compression)
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
        // The CubeCL step has no viscosity and linear shear springs: its tensor-op step adds
        // those terms to the fused forces.
        let fused = self.graph.fused_curvature()
            && ((params.viscosity == 0.0 && params.shear_compression == 1.0)
                || self.graph.fused_on == FusedOn::Host);
        fused.then(|| {
            let (k, b) = self.kernel_params();
            kernels::cloth_step(
                (x, v),
                (k, b),
                [pinned.clone(), pin_x, pin_v],
                &self.graph.host,
                params,
            )
        })
    }

    fn fused_frame(
        &self,
        x: Tensor<3>,
        v: Tensor<3>,
        pinned: &Tensor<3>,
        here: &Tensor<3>,
        next: &Tensor<3>,
        params: StepParams,
        span: (usize, f64),
    ) -> Option<(Tensor<3>, Tensor<3>)> {
        let host = self.graph.fused_curvature() && self.graph.fused_on == FusedOn::Host;
        host.then(|| {
            kernels::cloth_frame(
                (x, v),
                self.kernel_params(),
                [pinned, here, next],
                &self.graph.host,
                params,
                span,
            )
        })
    }
}
