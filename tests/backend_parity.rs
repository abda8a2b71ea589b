//! The same rollout and gradients on every backend: ndarray and flex always, wgpu when the
//! crate is built with `--features wgpu` (CI runs it on Mesa's software Vulkan).

mod common;

use burn::tensor::Device;
use springtime::data::Rollout;
use springtime::model::{SpringNet, springs::to_f64};
use springtime::sim::{self, Physics};
use springtime::train::{ForceOn, LossWeights, loss};

struct Outcome {
    positions: Vec<f64>,
    loss: f64,
    grad_k: Vec<f64>,
    grad_b: Vec<f64>,
    /// `∂L/∂κ` of the curvature elements (empty without).
    grad_kappa: Vec<f64>,
}

fn run(device: &Device, rollouts: &[Rollout], on: ForceOn, curvature: bool) -> Outcome {
    let cfg = common::source(6, &[10.0, 50.0, 100.0], 0.3);
    let mut topo = common::grid_of(&cfg);
    if curvature {
        let spec = springtime::cloth::GridSpec {
            nx: cfg.nx,
            ny: cfg.ny,
            curvature: true,
            ..Default::default()
        };
        topo = springtime::cloth::Topology::grid(&spec, cfg.width, cfg.height);
    }
    let kappa: Vec<f64> = (0..topo.curvature.len())
        .map(|i| 3.0 + ((i as f64) * 0.53).sin())
        .collect();
    let s = topo.num_springs();
    let k: Vec<f64> = (0..s)
        .map(|i| 40.0 + 20.0 * ((i as f64) * 0.37).sin())
        .collect();
    let b: Vec<f64> = (0..s).map(|i| 5.0 + ((i as f64) * 0.91).cos()).collect();
    let ad = device.clone().autodiff();
    let batch = common::batch(&cfg, rollouts, 100, 60, &ad);
    let model = SpringNet::new(&topo, &k, &b, &ad).with_curvature(&kappa);
    let physics = Physics {
        frame_dt: rollouts[0].frame_dt,
        substeps: 1,
        mass: rollouts[0].total_mass / topo.num_particles() as f64,
        rayleigh: cfg.rayleigh,
        gravity: cfg.gravity,
        viscosity: 0.0,
        shear_compression: 1.0,
    };
    let frames = batch.positions.dims()[1];
    let drive = common::clip_drive(&batch);
    let positions = to_f64(
        sim::rollout(&model, &physics, &drive, frames - 1)
            .positions
            .detach(),
    );
    let terms = loss(&model, &physics, &batch, &LossWeights::default(), on);
    let value = terms.total.clone().into_scalar::<f32>() as f64;
    let grads = terms.total.backward();
    Outcome {
        positions,
        loss: value,
        grad_k: to_f64(model.k.val().grad(&grads).unwrap()),
        grad_b: to_f64(model.b.val().grad(&grads).unwrap()),
        grad_kappa: model
            .curvature
            .as_ref()
            .map(|c| to_f64(c.kappa.val().grad(&grads).unwrap()))
            .unwrap_or_default(),
    }
}

fn compare(reference: &Device, other: &Device, label: &str) {
    let cfg = common::source(6, &[10.0, 50.0, 100.0], 0.3);
    let rollouts: Vec<Rollout> = (0..2).map(|s| common::rollout(&cfg, s).1).collect();
    // With curvature elements wgpu adds their forces in tensor ops beside its spring kernels.
    for (on, curvature) in [
        (ForceOn::Simulated, false),
        (ForceOn::Target, false),
        (ForceOn::Simulated, true),
    ] {
        let label = &format!("{label} (curvature {curvature})");
        let a = run(reference, &rollouts, on, curvature);
        let b = run(other, &rollouts, on, curvature);
        common::assert_close(
            &format!("{label} {on:?} positions"),
            &a.positions,
            &b.positions,
            1e-5,
        );
        assert!(
            (a.loss - b.loss).abs() <= 1e-4 * a.loss,
            "{label} {on:?} loss: {} vs {}",
            a.loss,
            b.loss
        );
        common::assert_close(&format!("{label} {on:?} dL/dk"), &a.grad_k, &b.grad_k, 1e-4);
        common::assert_close(&format!("{label} {on:?} dL/db"), &a.grad_b, &b.grad_b, 1e-4);
        assert_eq!(a.grad_kappa.is_empty(), !curvature);
        if curvature {
            common::assert_close(
                &format!("{label} {on:?} dL/dκ"),
                &a.grad_kappa,
                &b.grad_kappa,
                1e-4,
            );
        }
    }
}

#[test]
#[allow(deprecated)]
fn ndarray_matches_flex() {
    compare(&Device::flex(), &Device::ndarray(), "ndarray");
}

/// wgpu runs the CubeCL kernels (forces and steps) where flex runs the CPU ones.
#[test]
fn wgpu_matches_flex() {
    if let Some(device) = common::wgpu() {
        compare(&Device::flex(), &device, "wgpu");
    }
}
