//! Forward dynamics: batched semi-implicit Euler rollouts as Burn tensor programs (Eq. 5), and
//! the explicit-step stability guard.

pub mod contact;
mod stability;

pub use contact::{Contact, ContactConfig, ContactParams};
pub use stability::{Stability, curvature_bound};

use burn::tensor::Tensor;
use serde::{Deserialize, Serialize};

use crate::model::ForceModel;
use crate::model::kernels::StepParams;
use crate::settings::Auto;

/// Standard gravity, m/s², along −z.
pub const GRAVITY: [f64; 3] = [0.0, 0.0, -9.81];

/// The paper's Rayleigh damping constant, N·s/m: used where `sim.rayleigh` is still `"auto"`
/// outside a training run (a run resolves it from the data).
pub const RAYLEIGH: f64 = 0.1;

/// The `[sim]` section: how the surrogate is stepped.
///
/// `"auto"` values are resolved from the training data when a run starts
/// ([`crate::train::init`]) and written to the run's `config.toml`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SimConfig {
    /// Integration steps per data frame (`frame_dt = substeps · sim_dt`); `"auto"`: the fewest
    /// that keep the initial surrogate well inside the stability region.
    pub substeps: Auto<usize>,
    /// Rayleigh damping constant `c` of the external force `−c ẋ`, N·s/m (paper: 0.1);
    /// `"auto"`: the data's `rayleigh` key, else a least-squares fit to the data's forces.
    pub rayleigh: Auto<f64>,
    /// Gravity vector, m/s²; `"auto"`: the data's `gravity` key, else `[0, 0, −9.81]`.
    pub gravity: Auto<[f64; 3]>,
    /// Isotropic viscosity of the springs per unit stiffness `β`, s (ours; 0: none): each spring
    /// also damps the whole relative velocity of its ends, `β k_s (v_b − v_a)` on `a` and its
    /// opposite on `b`, rotations and bending included, as a viscous sheet (Warp's FEM
    /// triangles, `k_damp · dF/dt`) does; a spring's `b` damps only the stretching along it.
    /// Spring networks only; `train.viscosity_search` searches it.
    pub viscosity: f64,
    /// The shear springs' stiffness in compression, a fraction of their `k` (ours; 1: linear
    /// springs): a shear spring ([`crate::cloth::SpringFamily::Shear`], a cell's diagonal)
    /// shorter than at rest pushes back with `shear_compression · k_s`, and pulls with `k_s` when
    /// longer. 0: the shear springs pull only, as Blender's cloth's do (its shear springs resist
    /// no compression). Spring networks only; `train.compression_search` searches it.
    pub shear_compression: f64,
    /// Run even when the stability guard predicts a blow-up.
    pub allow_unstable: bool,
}

impl Default for SimConfig {
    fn default() -> Self {
        Self {
            substeps: Auto::Auto,
            rayleigh: Auto::Auto,
            gravity: Auto::Auto,
            viscosity: 0.0,
            shear_compression: 1.0,
            allow_unstable: false,
        }
    }
}

/// The physical constants of one rollout.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Physics {
    /// Time between data frames, s.
    pub frame_dt: f64,
    /// Integration steps per frame.
    pub substeps: usize,
    /// Mass of every particle, kg (`ρA/P`).
    pub mass: f64,
    /// Rayleigh damping constant, N·s/m.
    pub rayleigh: f64,
    /// Gravity, m/s².
    pub gravity: [f64; 3],
    /// The springs' isotropic viscosity per unit stiffness `β`, s ([`SimConfig::viscosity`]).
    pub viscosity: f64,
    /// The shear springs' stiffness in compression per unit `k` ([`SimConfig::shear_compression`]).
    pub shear_compression: f64,
}

impl Physics {
    /// The constants of data recorded every `frame_dt` on particles of `mass`, with the
    /// integrator settings of `sim`.
    pub fn new(sim: &SimConfig, frame_dt: f64, mass: f64) -> Self {
        Self {
            frame_dt,
            substeps: sim.substeps.or(1),
            mass,
            rayleigh: sim.rayleigh.or(RAYLEIGH),
            gravity: sim.gravity.or(GRAVITY),
            viscosity: sim.viscosity,
            shear_compression: sim.shear_compression,
        }
    }

    /// The explicit-step stability estimate of a spring network at this step (`.check(..)` it
    /// before simulating). The viscosity counts as damping `β k` along each spring: its rate on
    /// any mode is at most that of such a damper's. Shear springs softer in compression
    /// ([`SimConfig::shear_compression`] < 1) count at their full `k`: the bound still holds.
    pub fn stability_of(
        &self,
        topology: &crate::cloth::Topology,
        model: &crate::model::SpringNet,
    ) -> Stability {
        let k = model.k_values();
        let b: Vec<f64> = model
            .b_values()
            .iter()
            .zip(&k)
            .map(|(b, k)| b + self.viscosity * k)
            .collect();
        Stability::estimate(topology, &k, &b, self.mass, self.rayleigh, self.sim_dt())
            .with_curvature(
                &topology.curvature,
                &model.curvature_values(),
                topology.num_particles(),
            )
    }

    /// The integration step `frame_dt / substeps`.
    pub fn sim_dt(&self) -> f64 {
        self.frame_dt / self.substeps as f64
    }

    /// The constants of one integration step ([`StepParams`]).
    pub fn step_params(&self) -> StepParams {
        StepParams {
            h: self.sim_dt(),
            mass: self.mass,
            rayleigh: self.rayleigh,
            gravity: self.gravity,
            viscosity: self.viscosity,
            shear_compression: self.shear_compression,
        }
    }

    /// Net force at a state: the model's internal forces plus gravity, Rayleigh damping, the
    /// springs' viscosity and the shear springs' softening in compression, `[B, P, 3]`
    /// (`pinned`: `[B, P, 1]`, 1 = pinned).
    pub(crate) fn net_force(
        &self,
        model: &dyn ForceModel,
        x: Tensor<3>,
        v: Tensor<3>,
        pinned: &Tensor<3>,
    ) -> Tensor<3> {
        let device = x.device();
        let g = Tensor::<1>::from_floats(
            [
                (self.mass * self.gravity[0]) as f32,
                (self.mass * self.gravity[1]) as f32,
                (self.mass * self.gravity[2]) as f32,
            ],
            &device,
        )
        .reshape([1, 1, 3]);
        let mut f = model.internal_forces(x.clone(), v.clone(), pinned) + g;
        if self.shear_compression != 1.0 {
            f = f + model.compression_forces(x, self.shear_compression);
        }
        if self.viscosity != 0.0 {
            f = f + model.viscous_forces(v.clone(), self.viscosity);
        }
        if self.rayleigh != 0.0 {
            f = f - v.mul_scalar(self.rayleigh);
        }
        f
    }
}

/// Prescribed motion of the pinned particles and the initial state of a batch of clips.
#[derive(Debug, Clone)]
pub struct Drive {
    /// Initial positions `[B, P, 3]`.
    pub x0: Tensor<3>,
    /// Initial velocities `[B, P, 3]`.
    pub v0: Tensor<3>,
    /// 1 for pinned particles, 0 for free ones, `[B, P, 1]`.
    pub pinned: Tensor<3>,
    /// Observed positions at every frame `[B, F, P, 3]` (F ≥ frames + 1): pinned particles
    /// follow them; free particles ignore them.
    pub path: Tensor<4>,
}

/// A simulated batch of clips.
#[derive(Debug, Clone)]
pub struct Trajectory {
    /// Positions at frames `0..=T`, `[B, T + 1, P, 3]`.
    pub positions: Tensor<4>,
    /// Mean net force over each frame interval `j → j + 1` (the force of step `j` when there
    /// are no substeps), `[B, T, P, 3]`.
    pub forces: Tensor<4>,
}

/// State of a batch of cloths between frames.
#[derive(Debug, Clone)]
pub struct State {
    /// Positions `[B, P, 3]`.
    pub x: Tensor<3>,
    /// Velocities `[B, P, 3]`.
    pub v: Tensor<3>,
}

/// The colliders a frame meets, and the time the frame starts (s), for moving colliders.
#[derive(Debug, Clone, Copy)]
pub struct ContactAt<'a> {
    /// The colliders and contact constants.
    pub contact: &'a Contact,
    /// Time at the start of the frame, s.
    pub time: f64,
}

/// Advances `state` by one data frame: `substeps` semi-implicit Euler steps (Eq. 5),
/// `v ← v + dt/m · f(x, v)`, then `x ← x + dt · v`. Pinned particles (`pinned` = 1, `[B, P, 1]`)
/// move from `here` to `next` (`[B, P, 3]`) along a straight line at constant velocity.
/// With `contact`, the net force includes the contact forces ([`Contact::apply_tensor`]) and
/// the step runs in tensor ops: the fused kernels keep the state inside the kernel, where the
/// host collider queries cannot reach it.
/// Returns the new state and the mean net force over the frame.
pub fn step_frame(
    model: &dyn ForceModel,
    physics: &Physics,
    contact: Option<ContactAt>,
    state: State,
    pinned: &Tensor<3>,
    here: &Tensor<3>,
    next: &Tensor<3>,
) -> (State, Tensor<3>) {
    let n = physics.substeps.max(1);
    let h = physics.sim_dt();
    let free = pinned.clone().neg().add_scalar(1.0);
    let pin_v = (next.clone() - here.clone()).mul_scalar(1.0 / physics.frame_dt) * pinned.clone();
    let State { mut x, mut v } = state;
    let mut f_sum: Option<Tensor<3>> = None;
    let params = physics.step_params();
    for sub in 0..n {
        let target = if sub + 1 == n {
            next.clone()
        } else {
            let t = (sub + 1) as f64 / n as f64;
            here.clone().mul_scalar(1.0 - t) + next.clone().mul_scalar(t)
        };
        let fused = match contact {
            Some(_) => None,
            None => model.fused_step(
                x.clone(),
                v.clone(),
                pinned,
                target.clone(),
                pin_v.clone(),
                params,
            ),
        };
        let f = match fused {
            Some((xn, vn, f)) => {
                (x, v) = (xn, vn);
                f
            }
            None => {
                let mut f = physics.net_force(model, x.clone(), v.clone(), pinned);
                if let Some(c) = contact {
                    let t = c.time + sub as f64 * h;
                    f = c.contact.apply_tensor(t, h, physics.mass, &x, &v, f, &free);
                }
                v = v + f.clone().mul_scalar(h / physics.mass);
                x = x + v.clone().mul_scalar(h);
                x = x * free.clone() + target * pinned.clone();
                v = v * free.clone() + pin_v.clone();
                f
            }
        };
        f_sum = Some(match f_sum {
            None => f,
            Some(acc) => acc + f,
        });
    }
    let f_sum = f_sum.expect("at least one substep");
    let f_mean = if n == 1 {
        f_sum
    } else {
        f_sum.div_scalar(n as f64)
    };
    (State { x, v }, f_mean)
}

/// Advances `state` by one data frame as [`step_frame`] does, to the bit, for rollouts that keep
/// positions only (without the mean force): without `contact`, the whole frame in one fused op
/// where the model has one on this device ([`ForceModel::fused_frame`]).
pub fn advance_frame(
    model: &dyn ForceModel,
    physics: &Physics,
    contact: Option<ContactAt>,
    state: State,
    pinned: &Tensor<3>,
    here: &Tensor<3>,
    next: &Tensor<3>,
) -> State {
    let span = (physics.substeps.max(1), physics.frame_dt);
    let fused = match contact {
        Some(_) => None,
        None => {
            let (x, v) = (state.x.clone(), state.v.clone());
            model.fused_frame(x, v, pinned, here, next, physics.step_params(), span)
        }
    };
    match fused {
        Some((x, v)) => State { x, v },
        None => step_frame(model, physics, contact, state, pinned, here, next).0,
    }
}

/// Simulates `frames` data frames from `drive`'s initial state (see [`step_frame`]), keeping
/// every frame's positions and mean force for the losses.
pub fn rollout(
    model: &dyn ForceModel,
    physics: &Physics,
    drive: &Drive,
    frames: usize,
) -> Trajectory {
    let [batch, f_avail, p, _] = drive.path.dims();
    assert!(
        f_avail > frames,
        "the drive path has {f_avail} frames, a {frames}-frame rollout needs {}",
        frames + 1
    );
    let frame = |j: usize| {
        drive
            .path
            .clone()
            .slice([0..batch, j..j + 1, 0..p, 0..3])
            .reshape([batch, p, 3])
    };
    let mut state = State {
        x: drive.x0.clone(),
        v: drive.v0.clone(),
    };
    let mut positions = vec![state.x.clone()];
    let mut forces = Vec::with_capacity(frames);
    let mut here = frame(0);
    for j in 0..frames {
        let next = frame(j + 1);
        let (s, f) = step_frame(model, physics, None, state, &drive.pinned, &here, &next);
        state = s;
        forces.push(f);
        positions.push(state.x.clone());
        here = next;
    }
    Trajectory {
        positions: Tensor::stack(positions, 1),
        forces: Tensor::stack(forces, 1),
    }
}
