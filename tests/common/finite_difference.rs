//! The setting the finite-difference gradient checks share (tests/gradient_check.rs for `k` and
//! `b`, tests/curvature.rs for `κ`; tests/visibility.rs's physics too).

use springtime::cloth::Topology;
use springtime::data::Rollout;
use springtime::sim::Physics;
use springtime::source::SourceConfig;
use springtime::train::LossWeights;

/// A 4 × 4 source with stiffness levels 10 and 50 N/m, and two of its 0.08 s rollouts (seeds 1
/// and 2).
pub fn data() -> (SourceConfig, [Rollout; 2]) {
    let cfg = super::source(4, &[10.0, 50.0], 0.08);
    let (_, r1) = super::rollout(&cfg, 1);
    let (_, r2) = super::rollout(&cfg, 2);
    (cfg, [r1, r2])
}

/// The frame step of `r` and its mass shared equally by the particles of `topo`, 2 substeps a
/// frame, Rayleigh damping 0.1 and standard gravity.
pub fn physics(r: &Rollout, topo: &Topology) -> Physics {
    Physics {
        frame_dt: r.frame_dt,
        substeps: 2,
        mass: r.total_mass / topo.num_particles() as f64,
        rayleigh: 0.1,
        gravity: springtime::sim::GRAVITY,
        viscosity: 0.0,
        shear_compression: 1.0,
    }
}

/// Every term of the loss weighted in: force 1, impulse 10, position 100, both penalties 1.
pub const WEIGHTS: LossWeights = LossWeights {
    force: 1.0,
    impulse: 10.0,
    position: 100.0,
    k_neg: 1.0,
    b_neg: 1.0,
};
