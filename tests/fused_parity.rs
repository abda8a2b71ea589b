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
/// gradients with respect to k and b, with and without substeps and checkpointing.
#[test]
fn fused_rollout_loss_matches_tensor_ops() {
    compare_losses(&Device::flex(), &[(1, 1024), (1, 0), (3, 1024), (3, 0)]);
}

/// Loss terms and their `k`, `b` gradients, fused against tensor ops on `device`, for each
/// `(substeps, state budget in MiB)`.
fn compare_losses(device: &Device, cases: &[(usize, usize)]) {
    let cfg = common::source(6, &[10.0, 50.0, 100.0], 0.4);
    for topo in topologies(&cfg) {
        let rollouts: Vec<_> = (0..3).map(|i| common::rollout(&cfg, i).1).collect();
        for &(substeps, budget) in cases {
            let case = common::LossCase {
                cfg: &cfg,
                topo: &topo,
                rollouts: &rollouts,
                substeps,
                budget,
            };
            let (rv, rk, rb) = case.evaluate(Kernel::Reference, device);
            let (fv, fk, fb) = case.evaluate(Kernel::Fused, device);
            common::assert_losses_close(&format!("substeps {substeps}"), &rv, &fv);
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
