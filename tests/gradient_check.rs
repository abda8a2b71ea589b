//! Finite-difference check of ∂loss/∂k and ∂loss/∂b through a short rollout, in f64.
//!
//! This binary configures the flex device for f64 before any tensor exists, so it holds only
//! this test.

mod common;

use burn::tensor::{Device, FloatDType};
use springtime::model::{Kernel, SpringNet};
use springtime::train::{ForceOn, loss_with_budget};

#[test]
fn autodiff_gradients_match_central_differences() {
    let mut plain = Device::flex();
    plain.configure(FloatDType::F64).expect("flex supports f64");
    let ad = plain.clone().autodiff();

    let (cfg, rollouts) = common::finite_difference::data();
    let topo = common::grid_of(&cfg);
    let s = topo.num_springs();
    let physics = common::finite_difference::physics(&rollouts[0], &topo);
    // A guess away from the truth, so that every term of the loss is non-zero.
    let k0: Vec<f64> = (0..s)
        .map(|i| 30.0 + 7.0 * ((i as f64) * 0.37).sin())
        .collect();
    let b0: Vec<f64> = (0..s)
        .map(|i| 4.0 + 0.5 * ((i as f64) * 0.91).cos())
        .collect();
    let weights = common::finite_difference::WEIGHTS;

    // The fused rollout keeps every state (budget 1 GiB) or recomputes from checkpoints (0);
    // with the springs' isotropic viscosity (`sim.viscosity`, s) too.
    for (on, kernel, budget, viscosity) in [
        (ForceOn::Simulated, Kernel::Fused, 1024, 0.0),
        (ForceOn::Simulated, Kernel::Fused, 0, 0.0),
        (ForceOn::Target, Kernel::Fused, 1024, 0.0),
        (ForceOn::Simulated, Kernel::Reference, 1024, 0.0),
        (ForceOn::Frames, Kernel::Fused, 1024, 0.0),
        (ForceOn::Simulated, Kernel::Fused, 0, 0.02),
        (ForceOn::Simulated, Kernel::Reference, 1024, 0.02),
    ] {
        let physics = springtime::sim::Physics {
            viscosity,
            ..physics
        };
        let eval = |k: &[f64], b: &[f64], device: &Device| {
            let batch = common::batch(&cfg, &rollouts, 30, 20, device);
            let model = SpringNet::new(&topo, k, b, device).with_kernel(kernel);
            (
                model.clone(),
                loss_with_budget(&model, &physics, &batch, &weights, on, budget),
            )
        };
        let (model, terms) = eval(&k0, &b0, &ad);
        let base = terms.total.clone().into_scalar::<f64>();
        assert!(base > 0.0);
        let grads = terms.total.backward();
        let gk = springtime::model::springs::to_f64(
            model.k.val().grad(&grads).expect("k has a gradient"),
        );
        let gb = springtime::model::springs::to_f64(
            model.b.val().grad(&grads).expect("b has a gradient"),
        );
        let scale_k = gk.iter().fold(0.0f64, |m, g| m.max(g.abs()));
        let scale_b = gb.iter().fold(0.0f64, |m, g| m.max(g.abs()));
        assert!(scale_k > 0.0 && scale_b > 0.0);
        // dL/dθ ≈ (L(θ + ε) − L(θ − ε)) / 2ε, checked on springs of every family.
        for &i in &[0, 3, s / 3, s / 2, s - 5, s - 1] {
            for (which, g, scale) in [("k", &gk, scale_k), ("b", &gb, scale_b)] {
                let (mut up, mut down) = (
                    if which == "k" { k0.clone() } else { b0.clone() },
                    if which == "k" { k0.clone() } else { b0.clone() },
                );
                let eps = 1e-5 * up[i].abs();
                up[i] += eps;
                down[i] -= eps;
                let l = |v: &[f64]| {
                    let (kk, bb) = if which == "k" {
                        (v, &b0[..])
                    } else {
                        (&k0[..], v)
                    };
                    eval(kk, bb, &plain).1.total.into_scalar::<f64>()
                };
                let fd = (l(&up) - l(&down)) / (2.0 * eps);
                let err = (fd - g[i]).abs();
                assert!(
                    err <= 1e-6 * scale + 1e-6 * fd.abs(),
                    "{on:?} {kernel:?} budget {budget} viscosity {viscosity}: dL/d{which}[{i}]: autodiff {} vs finite difference {fd} (scale {scale})",
                    g[i]
                );
            }
        }
    }
}
