//! The fused spring-force kernels against the tensor-op reference: values and gradients with
//! respect to positions, velocities, k and b, on every CPU backend and on wgpu (the CubeCL
//! kernels; CI runs them on Mesa's software Vulkan).

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

/// The paper's grid of a source, and the same particles as a data mesh: its cells' two
/// triangles, hinge springs and lumped (unequal) masses.
fn topologies(cfg: &springtime::source::SourceConfig) -> [Topology; 2] {
    let grid = common::grid_of(cfg);
    let mesh = Topology::mesh(
        &grid.rest_uv,
        &grid.triangles,
        grid.width,
        grid.height,
        true,
    )
    .unwrap();
    assert!(mesh.force_scale().is_some());
    [grid, mesh]
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
/// gradients with respect to k and b, with and without substeps and checkpointing.
#[test]
fn fused_rollout_loss_matches_tensor_ops() {
    compare_losses(&Device::flex(), &[(1, 1024), (1, 0), (3, 1024), (3, 0)]);
}

/// On wgpu the fused path is a rollout of fused steps (CubeCL kernels, each with its
/// hand-written backward) inside the tensor-op losses.
#[test]
fn fused_steps_on_wgpu_match_tensor_ops() {
    if let Some(device) = common::wgpu() {
        compare_losses(&device, &[(1, 1024), (3, 1024)]);
    }
}

/// Loss terms and their `k`, `b` gradients, fused against tensor ops on `device`, for each
/// `(substeps, state budget in MiB)`.
fn compare_losses(device: &Device, cases: &[(usize, usize)]) {
    use springtime::sim::Physics;
    use springtime::train::{ForceOn, LossWeights, loss_with_budget};
    let cfg = common::source(6, &[10.0, 50.0, 100.0], 0.4);
    for topo in topologies(&cfg) {
        let s = topo.num_springs();
        let rollouts: Vec<_> = (0..3).map(|i| common::rollout(&cfg, i).1).collect();
        let k: Vec<f64> = (0..s)
            .map(|i| 40.0 + 25.0 * ((i as f64) * 0.37).sin())
            .collect();
        let b: Vec<f64> = (0..s).map(|i| 4.0 + ((i as f64) * 0.91).cos()).collect();
        let weights = LossWeights {
            force: 1.0,
            impulse: 10.0,
            position: 30.0,
            k_neg: 1.0,
            b_neg: 1.0,
        };
        let device = device.clone().autodiff();
        for &(substeps, budget) in cases {
            let batch = common::batch(&cfg, &rollouts, 150, 90, &device);
            let physics = Physics {
                frame_dt: rollouts[0].frame_dt,
                substeps,
                mass: rollouts[0].total_mass / topo.num_particles() as f64,
                rayleigh: cfg.rayleigh,
                gravity: cfg.gravity,
            };
            let run = |kernel: Kernel| {
                let model = SpringNet::new(&topo, &k, &b, &device).with_kernel(kernel);
                let terms = loss_with_budget(
                    &model,
                    &physics,
                    &batch,
                    &weights,
                    ForceOn::Simulated,
                    budget,
                );
                let values = terms.values();
                let grads = terms.total.backward();
                (
                    values,
                    to_f64(model.k.val().grad(&grads).unwrap()),
                    to_f64(model.b.val().grad(&grads).unwrap()),
                )
            };
            let (rv, rk, rb) = run(Kernel::Reference);
            let (fv, fk, fb) = run(Kernel::Fused);
            // The position loss squares differences of millimetres between positions of metres, so
            // f32 rounding (the reference sums spring forces in another order) shows at 1e-5.
            for (name, r, f, tol) in [
                ("force", rv.force, fv.force, 1e-5),
                ("impulse", rv.impulse, fv.impulse, 1e-5),
                ("position", rv.position, fv.position, 1e-4),
            ] {
                assert!(
                    r > 0.0 && (r - f).abs() <= tol * r,
                    "substeps {substeps}: {name} loss {r} vs {f}"
                );
            }
            assert_close(
                &format!("substeps {substeps} budget {budget} dL/dk"),
                &rk,
                &fk,
            );
            assert_close(
                &format!("substeps {substeps} budget {budget} dL/db"),
                &rb,
                &fb,
            );
        }
    }
}
