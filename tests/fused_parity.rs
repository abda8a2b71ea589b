//! The fused spring-force kernels against the tensor-op reference: values and gradients with
//! respect to positions, velocities, k and b, on every CPU backend and on wgpu (the CubeCL
//! kernels; CI runs them on Mesa's software Vulkan). Whole rollouts on wgpu are in
//! `wgpu_rollout.rs`.

mod common;

use burn::tensor::{Device, Tensor, TensorData};
use rand::{Rng, SeedableRng, rngs::StdRng};
use springtime::cloth::Topology;
use springtime::model::{Kernel, SpringNet, springs::to_f64};

struct Outcome {
    forces: Vec<f64>,
    gx: Vec<f64>,
    gv: Vec<f64>,
    gk: Vec<f64>,
    gb: Vec<f64>,
}

fn topologies(cfg: &springtime::source::SourceConfig) -> [Topology; 2] {
    common::grid_and_mesh(cfg)
}

fn run(device: &Device, kernel: Kernel, seed: u64, topo: &Topology) -> Outcome {
    let (p, s, b) = (topo.num_particles(), topo.num_springs(), 5);
    let mut rng = StdRng::seed_from_u64(seed);
    let rest = topo.rest_positions();
    let x: Vec<f64> = (0..b)
        .flat_map(|_| {
            rest.iter()
                .flatten()
                .map(|c| c + 0.1 * rng.random_range(-1.0..1.0))
                .collect::<Vec<_>>()
        })
        .collect();
    let v: Vec<f64> = (0..b * p * 3)
        .map(|_| rng.random_range(-1.0..1.0))
        .collect();
    let k: Vec<f64> = (0..s).map(|_| rng.random_range(5.0..100.0)).collect();
    let bb: Vec<f64> = (0..s).map(|_| rng.random_range(0.0..6.0)).collect();
    let weights: Vec<f64> = (0..b * p * 3)
        .map(|_| rng.random_range(-1.0..1.0))
        .collect();
    let ad = device.clone().autodiff();
    let xt = Tensor::<3>::from_data(TensorData::new(x, [b, p, 3]), &ad).require_grad();
    let vt = Tensor::<3>::from_data(TensorData::new(v, [b, p, 3]), &ad).require_grad();
    let model = SpringNet::new(topo, &k, &bb, &ad).with_kernel(kernel);
    let f = model.forces(xt.clone(), vt.clone());
    // ℓ = Σ w · F: its gradient with respect to F is w, a generic upstream gradient.
    let w = Tensor::<3>::from_data(TensorData::new(weights, [b, p, 3]), &ad);
    let grads = (f.clone() * w).sum().backward();
    Outcome {
        forces: to_f64(f.detach()),
        gx: to_f64(xt.grad(&grads).unwrap()),
        gv: to_f64(vt.grad(&grads).unwrap()),
        gk: to_f64(model.k.val().grad(&grads).unwrap()),
        gb: to_f64(model.b.val().grad(&grads).unwrap()),
    }
}

/// Within 1e-5 of the reference's largest magnitude.
fn assert_close(name: &str, a: &[f64], b: &[f64]) {
    common::assert_close(name, a, b, 1e-5);
}

#[test]
#[allow(deprecated)]
fn fused_kernel_matches_tensor_ops() {
    for (device, topo) in [Device::flex(), Device::ndarray()]
        .into_iter()
        .chain(common::wgpu())
        .flat_map(|d| {
            topologies(&common::source(7, &[10.0, 50.0, 100.0], 1.0)).map(|t| (d.clone(), t))
        })
    {
        for seed in 0..3 {
            let reference = run(&device, Kernel::Reference, seed, &topo);
            let fused = run(&device, Kernel::Fused, seed, &topo);
            assert_close("forces", &reference.forces, &fused.forces);
            assert_close("dℓ/dx", &reference.gx, &fused.gx);
            assert_close("dℓ/dv", &reference.gv, &fused.gv);
            assert_close("dℓ/dk", &reference.gk, &fused.gk);
            assert_close("dℓ/db", &reference.gb, &fused.gb);
        }
    }
}

/// The fused rollout-and-loss op against the tensor-op rollout and losses: loss terms and their
/// gradients with respect to k and b, with and without substeps and checkpointing, with the
/// springs' isotropic viscosity (`sim.viscosity`, 2 ms: `β k` up to 0.2 N·s/m beside `b` of 3–5)
/// and with the shear springs softer in compression (`sim.shear_compression`).
#[test]
fn fused_rollout_loss_matches_tensor_ops() {
    compare_losses(
        &Device::flex(),
        &[
            (1, 0.0, 1.0, 1024),
            (1, 0.0, 1.0, 0),
            (3, 0.0, 1.0, 1024),
            (3, 0.0, 1.0, 0),
            (3, 2e-3, 1.0, 1024),
            (3, 2e-3, 1.0, 0),
            (3, 0.0, 0.2, 1024),
            (3, 2e-3, 0.0, 0),
        ],
    );
}

/// Loss terms and their `k`, `b` gradients, fused against tensor ops on `device`, for each
/// `(substeps, viscosity, shear_compression, state budget in MiB)`.
fn compare_losses(device: &Device, cases: &[(usize, f64, f64, usize)]) {
    let cfg = common::source(6, &[10.0, 50.0, 100.0], 0.4);
    for topo in topologies(&cfg) {
        let rollouts: Vec<_> = (0..3).map(|i| common::rollout(&cfg, i).1).collect();
        for &(substeps, viscosity, shear_compression, budget) in cases {
            let case = common::LossCase {
                cfg: &cfg,
                topo: &topo,
                rollouts: &rollouts,
                substeps,
                viscosity,
                shear_compression,
                budget,
            };
            let (rv, rk, rb) = case.evaluate(Kernel::Reference, device);
            let (fv, fk, fb) = case.evaluate(Kernel::Fused, device);
            let case = format!(
                "substeps {substeps} viscosity {viscosity} shear compression {shear_compression} \
                 budget {budget}"
            );
            common::assert_losses_close(&case, &rv, &fv);
            assert_close(&format!("{case} dL/dk"), &rk, &fk);
            assert_close(&format!("{case} dL/db"), &rb, &fb);
        }
    }
}

/// Per-spring `k` (15–65 N/m) and `b` (0.3–0.7 N·s/m) that vary smoothly along the spring list.
fn varied_params(springs: usize) -> (Vec<f64>, Vec<f64>) {
    let k = (0..springs)
        .map(|i| 40.0 + 25.0 * ((i as f64) * 0.37).sin())
        .collect();
    let b = (0..springs)
        .map(|i| 0.5 + 0.2 * ((i as f64) * 0.91).cos())
        .collect();
    (k, b)
}

/// The fused step with the springs' isotropic viscosity (`sim.viscosity`) against the tensor-op
/// step, on every CPU backend and on wgpu (whose step falls back to tensor ops around its fused
/// forces there): positions after 30 frames of 3 substeps and the gradients of a weighted sum of
/// them with respect to `k` and `b`, through the step's backward. The viscosity moves the cloth:
/// without it the positions differ by far more than the tolerance.
#[test]
fn fused_step_with_viscosity_matches_tensor_ops() {
    fused_step_with_physics_matches_tensor_ops(0.01, 1.0, "the viscosity", 1e-5);
}

/// The same with the shear springs softer in compression (`sim.shear_compression`): the fused
/// kernels' forces and backward switch each shear spring's `k` where it is shorter than at rest.
/// The gradients within 5e-4 of their scale rather than 1e-5: the force's Jacobian jumps at the
/// rest length (by `(1 − κ) k l0 / L³`), and a spring within rounding of it can sit on either
/// side in the two implementations; over the 90 steps' backward that moves `dℓ/dk` by 1.2e-4 of
/// its scale on flex. The positions, where the force is continuous, agree to 1e-5 (the fused
/// rollout's backward, over fewer steps, agrees to 1e-5 as well: `fused_rollout_loss_matches_tensor_ops`).
#[test]
fn fused_step_with_soft_shear_springs_matches_tensor_ops() {
    fused_step_with_physics_matches_tensor_ops(0.0, 0.3, "softer shear springs", 5e-4);
}

/// The fused step at `viscosity` and `shear_compression` against the tensor-op step (positions
/// and the gradients of `k` and `b`), and apart from the plain fused step by more than the
/// tolerance; the gradients within `grad_rel` of their scale.
#[allow(deprecated)]
fn fused_step_with_physics_matches_tensor_ops(
    viscosity: f64,
    shear_compression: f64,
    what: &str,
    grad_rel: f64,
) {
    use springtime::sim::{self, Physics};
    let cfg = common::source(6, &[10.0, 50.0, 100.0], 0.4);
    let rollouts: Vec<_> = (0..3).map(|i| common::rollout(&cfg, i).1).collect();
    let topo = common::grid_of(&cfg);
    let (k, b) = varied_params(topo.num_springs());
    let physics = |viscosity: f64, shear_compression: f64| Physics {
        frame_dt: rollouts[0].frame_dt,
        substeps: 3,
        mass: rollouts[0].total_mass / topo.num_particles() as f64,
        rayleigh: cfg.rayleigh,
        gravity: cfg.gravity,
        viscosity,
        shear_compression,
    };
    let frames = 30;
    let run = |device: &Device, kernel: Kernel, at: Physics| {
        let ad = device.clone().autodiff();
        let batch = common::batch(&cfg, &rollouts, 150, frames, &ad);
        let model = SpringNet::new(&topo, &k, &b, &ad).with_kernel(kernel);
        let out = sim::rollout(&model, &at, &common::clip_drive(&batch), frames);
        let x = out.positions;
        let w = x.clone().detach().sin();
        let grads = (x.clone() * w).sum().backward();
        (
            to_f64(x.detach()),
            to_f64(model.k.val().grad(&grads).unwrap()),
            to_f64(model.b.val().grad(&grads).unwrap()),
        )
    };
    let at = physics(viscosity, shear_compression);
    for device in [Device::flex(), Device::ndarray()]
        .into_iter()
        .chain(common::wgpu())
    {
        let (rx, rk, rb) = run(&device, Kernel::Reference, at);
        let (fx, fk, fb) = run(&device, Kernel::Fused, at);
        assert_close("positions", &rx, &fx);
        common::assert_close("dℓ/dk", &rk, &fk, grad_rel);
        common::assert_close("dℓ/db", &rb, &fb, grad_rel);
        let (plain, _, _) = run(&device, Kernel::Fused, physics(0.0, 1.0));
        let apart = plain
            .iter()
            .zip(&fx)
            .fold(0.0f64, |m, (a, b)| m.max((a - b).abs()));
        assert!(apart > 1e-3, "{what} moves the cloth only {apart} m");
    }
}

/// A whole frame fused on the host (`sim::advance_frame`, which the evaluation and the searches
/// step with) against `sim::step_frame`'s substep-by-substep fused steps, to the bit: 20 frames
/// of 7 substeps with pinned particles moving along the data's path, Rayleigh drag, the
/// springs' viscosity and shear springs softer in compression, on the grid and on the mesh layout (lumped masses), on both CPU backends.
/// The pinned particles move, and the fused frame runs there (the test fails if it falls back).
#[test]
#[allow(deprecated)]
fn fused_frame_steps_as_step_frame_does_to_the_bit() {
    use springtime::model::ForceModel;
    use springtime::sim::{self, Physics, State};
    let cfg = common::source(6, &[10.0, 50.0, 100.0], 0.4);
    let rollouts: Vec<_> = (0..3).map(|i| common::rollout(&cfg, i).1).collect();
    for topo in topologies(&cfg) {
        let (k, b) = varied_params(topo.num_springs());
        let physics = Physics {
            frame_dt: rollouts[0].frame_dt,
            substeps: 7,
            mass: rollouts[0].total_mass / topo.num_particles() as f64,
            rayleigh: 0.05,
            gravity: cfg.gravity,
            viscosity: 2e-3,
            shear_compression: 0.4,
        };
        for device in [Device::flex(), Device::ndarray()] {
            let batch = common::batch(&cfg, &rollouts, 100, 20, &device);
            let model = SpringNet::new(&topo, &k, &b, &device);
            let [bsz, frames, p, _] = batch.positions.dims();
            // The data's frames carried along a straight line, so that the pins move.
            let frame = |j: usize| {
                batch
                    .positions
                    .clone()
                    .slice([0..bsz, j..j + 1, 0..p, 0..3])
                    .reshape([bsz, p, 3])
                    .add_scalar(0.013 * j as f64)
            };
            let start = || State {
                x: frame(0),
                v: batch
                    .velocities
                    .clone()
                    .slice([0..bsz, 0..1, 0..p, 0..3])
                    .reshape([bsz, p, 3]),
            };
            let (mut fused, mut stepped) = (start(), start());
            let span = (physics.substeps, physics.frame_dt);
            assert!(
                model
                    .fused_frame(
                        fused.x.clone(),
                        fused.v.clone(),
                        &batch.pinned,
                        &frame(0),
                        &frame(1),
                        physics.step_params(),
                        span,
                    )
                    .is_some(),
                "the whole-frame kernel runs on the host"
            );
            for j in 0..frames - 1 {
                let (here, next) = (frame(j), frame(j + 1));
                fused =
                    sim::advance_frame(&model, &physics, None, fused, &batch.pinned, &here, &next);
                stepped =
                    sim::step_frame(&model, &physics, None, stepped, &batch.pinned, &here, &next).0;
                for (name, a, b) in [
                    ("positions", &fused.x, &stepped.x),
                    ("velocities", &fused.v, &stepped.v),
                ] {
                    let (a, b) = (to_f64(a.clone()), to_f64(b.clone()));
                    let apart = a.iter().zip(&b).filter(|(a, b)| a != b).count();
                    assert_eq!(
                        apart,
                        0,
                        "{name} of frame {} differ in {apart} values",
                        j + 1
                    );
                }
            }
            // The pins carry their particles along the path: without them the test would not
            // cover the pinned branch.
            let pinned = to_f64(batch.pinned.clone());
            let (first, last) = (to_f64(frame(0)), to_f64(fused.x.clone()));
            let moved = pinned
                .iter()
                .enumerate()
                .filter(|&(_, &q)| q > 0.0)
                .map(|(i, _)| {
                    (0..3)
                        .map(|d| (last[3 * i + d] - first[3 * i + d]).abs())
                        .sum::<f64>()
                })
                .fold(0.0f64, f64::max);
            assert!(moved > 1e-3, "the pinned particles move {moved} m");
        }
    }
}
