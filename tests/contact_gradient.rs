//! Finite-difference check of ∂loss/∂k and ∂loss/∂b through a rollout in contact (the tensor
//! path of `Contact::apply_tensor`), in f64: a sheet resting in the contact layer of a slope,
//! sliding (μ = 0.1) or held by static friction (μ = 0.6), so that no particle enters or
//! leaves the layer and no friction regime flips within the differences.
//!
//! This binary configures the flex device for f64 before any tensor exists, so it holds only
//! this test.

mod common;

use std::path::Path;

use burn::tensor::{Device, FloatDType, Tensor, TensorData};
use springtime::model::SpringNet;
use springtime::sim::contact::ColliderConfig;
use springtime::sim::{Contact, ContactAt, ContactParams, Physics, State, step_frame};
use springtime::source::SpringCloth;

#[test]
fn gradients_through_contact_match_central_differences() {
    let mut plain = Device::flex();
    plain.configure(FloatDType::F64).expect("flex supports f64");
    let ad = plain.clone().autodiff();

    let mut cfg = common::source(4, &[20.0, 60.0], 1.0);
    cfg.damping = 0.5;
    let cloth = SpringCloth::from_config(&cfg);
    let topo = &cloth.topology;
    let (p, s) = (topo.num_particles(), topo.num_springs());
    let physics = Physics {
        frame_dt: 1e-3,
        substeps: 1,
        mass: cloth.mass,
        rayleigh: 0.1,
        gravity: springtime::sim::GRAVITY,
        viscosity: 0.0,
        shear_compression: 1.0,
    };
    let tilt = 20f64.to_radians();
    let params = ContactParams {
        thickness: 0.05,
        stiffness: 2.5e5,
        damping: 250.0,
    };
    // Resting in the layer, slightly stretched and moving down the slope.
    let (sn, cs) = tilt.sin_cos();
    let lift = 0.04;
    let x0: Vec<f64> = topo
        .rest_positions()
        .iter()
        .enumerate()
        .flat_map(|(i, q)| {
            let (x, y) = (1.05 * q[0], q[1] + 0.01 * (i as f64).sin());
            [x, y * cs - lift * sn, y * sn + lift * cs]
        })
        .collect();
    // Sliding at 0.3 m/s (μ = 0.1), or starting at rest where static friction holds it.
    let v0 = |slide: f64| -> Vec<f64> {
        (0..p)
            .flat_map(|i| [0.02 * slide * (i as f64).cos(), -slide * cs, -slide * sn])
            .collect()
    };
    let k0: Vec<f64> = (0..s)
        .map(|i| 40.0 + 9.0 * (i as f64 * 0.37).sin())
        .collect();
    let b0: Vec<f64> = (0..s)
        .map(|i| 0.4 + 0.1 * (i as f64 * 0.91).cos())
        .collect();
    let w: Vec<f64> = (0..p * 3).map(|i| (i as f64 * 1.3).sin()).collect();

    for (mu, slide) in [(0.1, 0.3), (0.6, 0.0)] {
        let v0 = v0(slide);
        let plane: ColliderConfig = toml::from_str(&format!(
            "kind = \"plane\"\nrotation_deg = [20.0, 0.0, 0.0]\nfriction = {mu}"
        ))
        .unwrap();
        let contact = Contact::new(vec![plane.build(Path::new("."), "slope").unwrap()], params);
        let eval = |k: &[f64], b: &[f64], device: &Device| {
            let t3 =
                |v: &[f64]| Tensor::<3>::from_data(TensorData::new(v.to_vec(), [1, p, 3]), device);
            let model = SpringNet::new(topo, k, b, device);
            let pinned = Tensor::<3>::zeros([1, p, 1], device);
            let here = t3(&x0);
            let mut state = State {
                x: t3(&x0),
                v: t3(&v0),
            };
            for j in 0..40 {
                let at = ContactAt {
                    contact: &contact,
                    time: j as f64 * 1e-3,
                };
                state = step_frame(&model, &physics, Some(at), state, &pinned, &here, &here).0;
            }
            let loss = (state.x * t3(&w)).sum() + (state.v * t3(&w)).sum().mul_scalar(0.1);
            (model, loss)
        };
        let (model, loss) = eval(&k0, &b0, &ad);
        let grads = loss.backward();
        let gk = springtime::model::springs::to_f64(model.k.val().grad(&grads).unwrap());
        let gb = springtime::model::springs::to_f64(model.b.val().grad(&grads).unwrap());
        let scale_k = gk.iter().fold(0.0f64, |m, g| m.max(g.abs()));
        let scale_b = gb.iter().fold(0.0f64, |m, g| m.max(g.abs()));
        assert!(scale_k > 0.0 && scale_b > 0.0);
        for &i in &[0, 5, s / 3, s / 2, s - 1] {
            for (which, g, scale) in [("k", &gk, scale_k), ("b", &gb, scale_b)] {
                let base = if which == "k" { &k0 } else { &b0 };
                let eps = 1e-6 * base[i].abs();
                let l = |delta: f64| {
                    let mut v = base.clone();
                    v[i] += delta;
                    let (kk, bb) = if which == "k" {
                        (&v[..], &b0[..])
                    } else {
                        (&k0[..], &v[..])
                    };
                    eval(kk, bb, &plain).1.into_scalar::<f64>()
                };
                let fd = (l(eps) - l(-eps)) / (2.0 * eps);
                let err = (fd - g[i]).abs();
                assert!(
                    err <= 1e-5 * scale + 1e-5 * fd.abs(),
                    "μ = {mu}: dL/d{which}[{i}]: autodiff {} vs finite difference {fd} (scale {scale})",
                    g[i]
                );
            }
        }
        assert!(contact.deepest() > 0.0, "the sheet is in contact");
    }
}
