//! The force-and-impulse loss (paper Eqs. 6–12) and the position loss of the ablation.

use burn::tensor::{Tensor, activation::relu};
use serde::{Deserialize, Serialize};

use crate::data::ClipBatch;
use crate::model::kernels::{self, RolloutParams};
use crate::model::{ForceModel, SpringNet};
use crate::sim::{self, Drive, Physics};

/// Memory the fused rollout may keep between its forward and backward passes by default, MiB
/// (beyond it, states are checkpointed and recomputed).
pub(crate) const DEFAULT_STATE_BUDGET_MIB: usize = 1024;

/// Weights `λ` of the loss terms (Eq. 6).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LossWeights {
    /// `λ_f`: force loss (Eq. 7).
    pub force: f64,
    /// `λ_J`: impulse loss (Eq. 9).
    pub impulse: f64,
    /// Position loss `|x − x̂|²` (the ablation of App. C.2); 0 = off.
    pub position: f64,
    /// `λ_k neg.` (Eq. 11).
    pub k_neg: f64,
    /// `λ_b neg.` (Eq. 12).
    pub b_neg: f64,
}

impl Default for LossWeights {
    /// App. B for mass-spring data: `λ_f = 1`, `λ_J = 10`.
    fn default() -> Self {
        Self {
            force: 1.0,
            impulse: 10.0,
            position: 0.0,
            k_neg: 1.0,
            b_neg: 1.0,
        }
    }
}

/// Where the simulated forces of the force and impulse losses are evaluated.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ForceOn {
    /// On the surrogate's own rollout from each clip's first frame (the paper).
    #[default]
    Simulated,
    /// On the target states (teacher forcing): no rollout, every frame in parallel.
    Target,
    /// On the surrogate's own rollout, but estimated from its frames' positions by the same
    /// central differences that give the targets of data without stored velocities (camera-rate
    /// data): `f̃_j = m (ṽ_{j+1} − ṽ_j)/Δt`, `ṽ_j = (x_{j+1} − x_{j−1})/(2Δt)`, compared with the
    /// same estimate of the clip's frames for `j = 1..T−2`. Oscillations faster than the frame
    /// rate then count by their displacement, as in the data, not by their velocity (which grows
    /// with `√k`).
    Frames,
}

/// The loss and its terms, each a one-element tensor.
#[derive(Debug, Clone)]
pub struct LossTerms {
    /// The weighted sum (Eq. 6).
    pub total: Tensor<1>,
    /// Force loss `L_f`.
    pub force: Tensor<1>,
    /// Impulse loss `L_J`.
    pub impulse: Tensor<1>,
    /// Position loss (zero unless weighted).
    pub position: Tensor<1>,
    /// `Σ ReLU(−k)`.
    pub k_neg: Tensor<1>,
    /// `Σ ReLU(−b)`.
    pub b_neg: Tensor<1>,
}

/// Plain values of [`LossTerms`].
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize)]
pub struct LossValues {
    /// The weighted sum.
    pub total: f64,
    /// Force loss.
    pub force: f64,
    /// Impulse loss.
    pub impulse: f64,
    /// Position loss.
    pub position: f64,
    /// Negative-stiffness penalty.
    pub k_neg: f64,
    /// Negative-damping penalty.
    pub b_neg: f64,
}

impl LossTerms {
    /// Reads the terms back to the host.
    pub fn values(&self) -> LossValues {
        let v = |t: &Tensor<1>| t.clone().into_scalar::<f32>() as f64;
        LossValues {
            total: v(&self.total),
            force: v(&self.force),
            impulse: v(&self.impulse),
            position: v(&self.position),
            k_neg: v(&self.k_neg),
            b_neg: v(&self.b_neg),
        }
    }
}

/// Evaluates the loss of the spring network `model` on a batch of clips: the terms of
/// [`motion_loss`] plus the penalties on negative `k` and `b` (Eqs. 11, 12).
pub fn loss(
    model: &SpringNet,
    physics: &Physics,
    batch: &ClipBatch,
    weights: &LossWeights,
    on: ForceOn,
) -> LossTerms {
    loss_with_budget(model, physics, batch, weights, on, DEFAULT_STATE_BUDGET_MIB)
}

/// [`loss`] with the fused rollout's memory budget for stored states, MiB.
///
/// With the fused kernel and simulated forces, the rollout and the three loss terms are one op
/// ([`kernels::rollout_loss`]) whose backward is the adjoint of the integrator; otherwise (and
/// for clips with hidden particles, whose terms the fused op does not mask) the loss is built
/// from tensor ops around [`sim::rollout`] ([`motion_loss`]).
pub fn loss_with_budget(
    model: &SpringNet,
    physics: &Physics,
    batch: &ClipBatch,
    weights: &LossWeights,
    on: ForceOn,
    budget_mib: usize,
) -> LossTerms {
    if on == ForceOn::Simulated && model.graph.fused_rollout() && batch.seen.is_none() {
        return fused_loss(model, physics, batch, weights, budget_mib);
    }
    let mut terms = motion_loss(model, physics, batch, weights, on);
    let (k_neg, b_neg) = negativity(model);
    terms.total = terms.total
        + k_neg.clone().mul_scalar(weights.k_neg)
        + b_neg.clone().mul_scalar(weights.b_neg);
    terms.k_neg = k_neg;
    terms.b_neg = b_neg;
    terms
}

/// The first frame of every clip of `batch`: positions and velocities, `[B, P, 3]` each.
fn clip_start(batch: &ClipBatch) -> (Tensor<3>, Tensor<3>) {
    let [b, _, p, _] = batch.positions.dims();
    let first = |t: &Tensor<4>| t.clone().slice([0..b, 0..1, 0..p, 0..3]).reshape([b, p, 3]);
    (first(&batch.positions), first(&batch.velocities))
}

/// The surrogate's own rollout over every clip of `batch` from its first frame, pinned
/// particles following the clip's path.
fn free_rollout(model: &dyn ForceModel, physics: &Physics, batch: &ClipBatch) -> sim::Trajectory {
    let (x0, v0) = clip_start(batch);
    let drive = Drive {
        x0,
        v0,
        pinned: batch.pinned.clone(),
        path: batch.positions.clone(),
    };
    sim::rollout(model, physics, &drive, batch.positions.dims()[1] - 1)
}

/// [`ForceOn::Frames`]: the difference of the force estimates from the simulated and the
/// target frames' positions, at frames `1..=T−2`, `[B, T−2, P, 3]`. Both are central
/// differences of positions, so their difference is a stencil of the position error
/// `e = x − x̂`: `m/(2Δt²) (e_{j+2} − e_{j+1} − e_j + e_{j−1})`.
fn frame_force_error(traj: &sim::Trajectory, batch: &ClipBatch, physics: &Physics) -> Tensor<4> {
    let [b, frames, p, _] = batch.positions.dims();
    let t = frames - 1;
    assert!(
        t >= 3,
        "frame-difference forces need clips of at least 3 steps, got {t}"
    );
    let e = traj.positions.clone() - batch.positions.clone();
    let at = |from: usize, to: usize| e.clone().slice([0..b, from..to, 0..p, 0..3]);
    (at(3, t + 1) - at(2, t) - at(1, t - 1) + at(0, t - 2))
        .mul_scalar(physics.mass / (2.0 * physics.frame_dt * physics.frame_dt))
}

/// The penalties on negative parameters: the sum of `relu(−k)` over the springs and the
/// curvature elements' `κ`, and the sum of `relu(−b)`.
fn negativity(model: &SpringNet) -> (Tensor<1>, Tensor<1>) {
    let mut k_neg = relu(model.k.val().neg()).sum();
    if let Some(c) = &model.curvature {
        k_neg = k_neg + relu(c.kappa.val().neg()).sum();
    }
    (k_neg, relu(model.b.val().neg()).sum())
}

/// The force, impulse and position losses of any [`ForceModel`] on a batch of clips, built
/// from tensor ops (the penalty terms are zero).
///
/// With `T` steps per clip, `P` particles and pinned particles masked out, and `N` frames whose
/// forces are compared (`T`, or `T − 2` for [`ForceOn::Frames`]):
/// - `L_f = 1/(B·N·P) Σ_clips Σ_j Σ_p |f_j − f̂_j|²` with `f̂_j = M (v̂_{j+1} − v̂_j)/Δt`;
/// - `J = Δt [Σ_j f_j − (f_0 + f_{N−1})/2]` (trapezoid, Eq. 10), `L_J = 1/(B·P) Σ |J − Ĵ|²`;
/// - position loss `1/(B·T·P) Σ_{j≥1} |x_j − x̂_j|²` (when there is a simulated rollout).
///
/// With hidden particles (`batch.seen`), a force or position term counts only where its target
/// rests on seen positions, and each sum is divided by the number of such terms instead of
/// `B·N·P` (or `B·T·P`); the impulse sums the seen force errors.
pub fn motion_loss(
    model: &dyn ForceModel,
    physics: &Physics,
    batch: &ClipBatch,
    weights: &LossWeights,
    on: ForceOn,
) -> LossTerms {
    let [b, _, p, _] = batch.positions.dims();
    let device = batch.positions.device();
    let free = batch
        .pinned
        .clone()
        .neg()
        .add_scalar(1.0)
        .reshape([b, 1, p, 1]);
    let zero = || Tensor::<1>::zeros([1], &device);
    // The force error of every compared frame, and the simulated rollout when there is one.
    let (error, trajectory) = match on {
        ForceOn::Simulated => {
            let traj = free_rollout(model, physics, batch);
            (traj.forces.clone() - batch.forces.clone(), Some(traj))
        }
        ForceOn::Frames => {
            let traj = free_rollout(model, physics, batch);
            (frame_force_error(&traj, batch, physics), Some(traj))
        }
        ForceOn::Target => (target_force_error(model, physics, batch), None),
    };
    let Masked {
        error,
        force_count,
        position_mask,
        position_count,
    } = Masked::of(error, &free, batch);
    let n = error.dims()[1];
    let force = (error.clone() * error.clone())
        .sum()
        .div_scalar(force_count);
    // The trapezoid impulse is linear in the forces: J − Ĵ is the impulse of the error.
    let ends = error.clone().slice([0..b, 0..1, 0..p, 0..3])
        + error.clone().slice([0..b, n - 1..n, 0..p, 0..3]);
    let dj = (error.sum_dim(1) - ends.mul_scalar(0.5)).mul_scalar(physics.frame_dt);
    let impulse = (dj.clone() * dj).sum().div_scalar((b * p) as f64);
    let position = match &trajectory {
        Some(traj) => position_error(traj, batch, free, position_mask, position_count),
        None => zero(),
    };
    let mut total =
        force.clone().mul_scalar(weights.force) + impulse.clone().mul_scalar(weights.impulse);
    if weights.position != 0.0 {
        total = total + position.clone().mul_scalar(weights.position);
    }
    LossTerms {
        total,
        force,
        impulse,
        position,
        k_neg: zero(),
        b_neg: zero(),
    }
}

/// The force error of teacher forcing (`ForceOn::Target`): the model's forces on the data's own
/// states of every frame but the last, against the target forces.
fn target_force_error(model: &dyn ForceModel, physics: &Physics, batch: &ClipBatch) -> Tensor<4> {
    let [b, frames, p, _] = batch.positions.dims();
    let t = frames - 1;
    let x = batch
        .positions
        .clone()
        .slice([0..b, 0..t, 0..p, 0..3])
        .reshape([b * t, p, 3]);
    let v = batch
        .velocities
        .clone()
        .slice([0..b, 0..t, 0..p, 0..3])
        .reshape([b * t, p, 3]);
    let pinned = batch
        .pinned
        .clone()
        .reshape([b, 1, p, 1])
        .repeat_dim(1, t)
        .reshape([b * t, p, 1]);
    let forces = physics
        .net_force(model, x, v, &pinned)
        .reshape([b, t, p, 3]);
    forces - batch.forces.clone()
}

/// The force error on free particles where the targets rest on seen positions (all of them
/// without a mask), and how many terms that leaves per sum.
struct Masked {
    error: Tensor<4>,
    force_count: f64,
    /// Which simulated frames' positions are compared (`None`: all).
    position_mask: Option<Tensor<4>>,
    position_count: f64,
}

impl Masked {
    fn of(error: Tensor<4>, free: &Tensor<4>, batch: &ClipBatch) -> Masked {
        let [b, frames, p, _] = batch.positions.dims();
        let t = frames - 1;
        let n = error.dims()[1];
        let Some(seen) = &batch.seen else {
            return Masked {
                error: error * free.clone(),
                force_count: (b * n * p) as f64,
                position_mask: None,
                position_count: (b * t * p) as f64,
            };
        };
        let forces = if n == t {
            seen.forces.clone()
        } else {
            // The frame-difference force of frame j (1..=T−2) rests on positions j−1..=j+2:
            // seen where the target forces of frames j−1, j and j+1 are.
            let f =
                |from: usize, to: usize| seen.forces.clone().slice([0..b, from..to, 0..p, 0..1]);
            f(0, t - 2) * f(1, t - 1) * f(2, t)
        };
        let positions = seen.positions.clone().slice([0..b, 1..t + 1, 0..p, 0..1]);
        let count = |m: &Tensor<4>| (m.clone().sum().into_scalar::<f32>() as f64).max(1.0);
        let (force_count, position_count) = (count(&forces), count(&positions));
        Masked {
            error: error * free.clone() * forces,
            force_count,
            position_mask: Some(positions),
            position_count,
        }
    }
}

/// The mean square position error of the simulated frames 1..=T on free (and seen) particles.
fn position_error(
    traj: &sim::Trajectory,
    batch: &ClipBatch,
    free: Tensor<4>,
    mask: Option<Tensor<4>>,
    count: f64,
) -> Tensor<1> {
    let [b, frames, p, _] = batch.positions.dims();
    let t = frames - 1;
    let mut dx = (traj.positions.clone().slice([0..b, 1..t + 1, 0..p, 0..3])
        - batch.positions.clone().slice([0..b, 1..t + 1, 0..p, 0..3]))
        * free;
    if let Some(mask) = mask {
        dx = dx * mask;
    }
    (dx.clone() * dx).sum().div_scalar(count)
}

fn fused_loss(
    model: &SpringNet,
    physics: &Physics,
    batch: &ClipBatch,
    weights: &LossWeights,
    budget_mib: usize,
) -> LossTerms {
    let (x0, v0) = clip_start(batch);
    let params = RolloutParams {
        frame_dt: physics.frame_dt,
        substeps: physics.substeps,
        mass: physics.mass,
        rayleigh: physics.rayleigh,
        gravity: physics.gravity,
        viscosity: physics.viscosity,
        shear_compression: physics.shear_compression,
        state_budget: budget_mib << 20,
    };
    let (k, b) = model.kernel_params();
    let terms = kernels::rollout_loss(
        (x0, v0),
        (k, b),
        batch.pinned.clone(),
        (batch.positions.clone(), batch.forces.clone()),
        &model.graph.host,
        params,
    );
    // One range per tensor dimension (clippy reads it as a one-element Vec of a range).
    #[allow(clippy::single_range_in_vec_init)]
    let term = |i: usize| terms.clone().slice([i..i + 1]);
    let (force, impulse, position) = (term(0), term(1), term(2));
    let (k_neg, b_neg) = negativity(model);
    let total = force.clone().mul_scalar(weights.force)
        + impulse.clone().mul_scalar(weights.impulse)
        + position.clone().mul_scalar(weights.position)
        + k_neg.clone().mul_scalar(weights.k_neg)
        + b_neg.clone().mul_scalar(weights.b_neg);
    LossTerms {
        total,
        force,
        impulse,
        position,
        k_neg,
        b_neg,
    }
}
