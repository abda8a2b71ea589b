//! Curvature elements (`cloth.curvature`, ours): forces against the finite differences of
//! their energy, momentum, rigid-motion invariance, the linear bending stiffness that springs
//! lack, the loss gradient with respect to `κ` against finite differences, and the stability
//! bound. In f64: this binary configures the flex device before any tensor exists.

mod common;

use std::sync::OnceLock;

use burn::tensor::{Device, FloatDType, Tensor, TensorData};
use springtime::cloth::{GridSpec, Topology};
use springtime::model::springs::to_f64;
use springtime::model::{Kernel, SpringNet};
use springtime::sim::Stability;
use springtime::train::{ForceOn, loss_with_budget};

/// The f64 flex device, configured once before any test makes a tensor.
fn device() -> Device {
    static DEVICE: OnceLock<Device> = OnceLock::new();
    DEVICE
        .get_or_init(|| {
            let mut d = Device::flex();
            d.configure(FloatDType::F64).expect("flex supports f64");
            d
        })
        .clone()
}

fn grid(n: usize, curvature: bool) -> Topology {
    let spec = GridSpec {
        nx: n,
        ny: n,
        curvature,
        ..GridSpec::default()
    };
    Topology::grid(&spec, 0.5 * (n - 1) as f64, 0.5 * (n - 1) as f64)
}

fn positions(x: &[[f64; 3]], device: &Device) -> Tensor<3> {
    let flat: Vec<f64> = x.iter().flatten().copied().collect();
    Tensor::from_data(TensorData::new(flat, [1, x.len(), 3]), device)
}

fn rest(topo: &Topology) -> Vec<[f64; 3]> {
    topo.rest_uv.iter().map(|p| [p[0], p[1], 0.0]).collect()
}

/// `½ Σ κ_t |x_i − 2x_j + x_l|²` on the host.
fn energy(topo: &Topology, kappa: &[f64], x: &[[f64; 3]]) -> f64 {
    topo.curvature
        .iter()
        .zip(kappa)
        .map(|(&[i, j, l], k)| {
            let e: f64 = (0..3)
                .map(|c| (x[i][c] - 2.0 * x[j][c] + x[l][c]).powi(2))
                .sum();
            0.5 * k * e
        })
        .sum()
}

/// The curvature elements' forces alone (springs at zero stiffness and damping).
fn curvature_forces(topo: &Topology, kappa: &[f64], x: &[[f64; 3]]) -> Vec<f64> {
    let device = device();
    let s = topo.num_springs();
    let net = SpringNet::new(topo, &vec![0.0; s], &vec![0.0; s], &device).with_curvature(kappa);
    let x = positions(x, &device);
    to_f64(net.forces(x.clone(), x.zeros_like()))
}

#[test]
fn forces_are_minus_the_energy_gradient_sum_to_zero_and_vanish_under_rigid_motion() {
    let topo = grid(5, true);
    // 5 rows of 3, 3 interior rows of 5 columns, and 3 × 3 interior particles × 2 diagonals.
    assert_eq!(topo.curvature.len(), 2 * 5 * 3 + 2 * 3 * 3);
    let kappa: Vec<f64> = (0..topo.curvature.len())
        .map(|t| 2.0 + (t as f64 * 0.7).sin())
        .collect();
    let x: Vec<[f64; 3]> = rest(&topo)
        .iter()
        .enumerate()
        .map(|(i, p)| {
            let t = i as f64;
            [
                p[0] + 0.05 * (1.3 * t).sin(),
                p[1] + 0.04 * (0.7 * t).cos(),
                0.1 * (0.9 * t).sin(),
            ]
        })
        .collect();
    let f = curvature_forces(&topo, &kappa, &x);
    for i in 0..x.len() {
        for c in 0..3 {
            let eps = 1e-6;
            let (mut up, mut down) = (x.clone(), x.clone());
            up[i][c] += eps;
            down[i][c] -= eps;
            let fd = -(energy(&topo, &kappa, &up) - energy(&topo, &kappa, &down)) / (2.0 * eps);
            assert!(
                (fd - f[3 * i + c]).abs() <= 1e-7 * (1.0 + fd.abs()),
                "particle {i} axis {c}: force {} vs −dE/dx {fd}",
                f[3 * i + c]
            );
        }
    }
    for c in 0..3 {
        let sum: f64 = (0..x.len()).map(|i| f[3 * i + c]).sum();
        assert!(sum.abs() < 1e-12, "axis {c}: forces sum to {sum}");
    }
    // The flat rest grid, rotated and moved, feels nothing.
    let (a, b) = (0.6f64, 0.3f64);
    let moved: Vec<[f64; 3]> = rest(&topo)
        .iter()
        .map(|p| {
            let (x1, z1) = (p[0] * a.cos(), p[0] * a.sin());
            let (y2, z2) = (p[1] * b.cos(), p[1] * b.sin());
            [x1 + 1.0, y2 - 2.0, z1 + z2 + 0.5]
        })
        .collect();
    // (a linear map of the flat sheet keeps every second difference zero)
    let f = curvature_forces(&topo, &kappa, &moved);
    let max = f.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    assert!(max < 1e-12, "rigidly moved flat sheet: largest force {max}");
}

/// Restoring force on the middle of a row of three particles 0.5 m apart, lifted by `θ/2` (a
/// bend angle of about `2θ` at the middle), per unit `θ`.
fn stiffness_at(topo: &Topology, k: f64, kappa: f64, theta: f64) -> f64 {
    let device = device();
    let s = topo.num_springs();
    let net = SpringNet::new(topo, &vec![k; s], &vec![0.0; s], &device)
        .with_curvature(&vec![kappa; topo.curvature.len()]);
    let mut x = rest(topo);
    x[1][2] = 0.5 * theta;
    let x = positions(&x, &device);
    let f = to_f64(net.forces(x.clone(), x.zeros_like()));
    -f[3 + 2] / theta
}

#[test]
fn curvature_elements_give_the_linear_bending_stiffness_that_springs_lack() {
    // Three particles in a row: one structural spring each side, one stride-2 bending spring.
    let spec = GridSpec {
        nx: 3,
        ny: 2,
        curvature: true,
        ..GridSpec::default()
    };
    let topo = Topology::grid(&spec, 1.0, 0.5);
    let springs = [1e-2, 1e-3, 1e-4].map(|t| stiffness_at(&topo, 100.0, 0.0, t));
    let curved = [1e-2, 1e-3, 1e-4].map(|t| stiffness_at(&topo, 100.0, 5.0, t));
    // Springs: the restoring force per unit angle vanishes with the angle (it is cubic)...
    assert!(
        springs[2] < 1e-3 * springs[0] && springs[0] > 0.0,
        "springs alone: {springs:?}"
    );
    // ...the curvature element's is constant: lifting the middle by θ/2 makes e = −θ in z,
    // and the middle particle feels 2κe: 2κ per unit θ whatever θ.
    for (s, c) in springs.iter().zip(&curved) {
        assert!(
            ((c - s) - 2.0 * 5.0).abs() < 1e-6,
            "curvature stiffness per unit angle {}",
            c - s
        );
    }
}

#[test]
fn the_loss_gradient_in_kappa_matches_central_differences() {
    let plain = device();
    let ad = plain.clone().autodiff();
    let (cfg, rollouts) = common::finite_difference::data();
    let topo = Topology::grid(
        &GridSpec {
            nx: 4,
            ny: 4,
            curvature: true,
            ..GridSpec::default()
        },
        cfg.width,
        cfg.height,
    );
    let (s, t) = (topo.num_springs(), topo.curvature.len());
    let physics = common::finite_difference::physics(&rollouts[0], &topo);
    let k0: Vec<f64> = (0..s)
        .map(|i| 30.0 + 7.0 * (i as f64 * 0.37).sin())
        .collect();
    let b0 = vec![4.0; s];
    let kappa0: Vec<f64> = (0..t).map(|i| 3.0 + (i as f64 * 0.53).cos()).collect();
    let weights = common::finite_difference::WEIGHTS;
    // The fused rollout (states kept, or recomputed from checkpoints), the fused step under
    // teacher forcing, and the tensor-op reference: the same gradient.
    for (on, kernel, budget) in [
        (ForceOn::Simulated, Kernel::Fused, 1024),
        (ForceOn::Simulated, Kernel::Fused, 0),
        (ForceOn::Frames, Kernel::Fused, 1024),
        (ForceOn::Simulated, Kernel::Reference, 1024),
    ] {
        let eval = |kappa: &[f64], device: &Device| {
            // The clips come from a cloth without curvature: what is checked is the gradient.
            let batch = common::batch(&cfg, &rollouts, 30, 20, device);
            let model = SpringNet::new(&topo, &k0, &b0, device)
                .with_kernel(kernel)
                .with_curvature(kappa);
            let terms = loss_with_budget(&model, &physics, &batch, &weights, on, budget);
            (model, terms)
        };
        let (model, terms) = eval(&kappa0, &ad);
        let grads = terms.total.backward();
        let g = to_f64(
            model
                .curvature
                .as_ref()
                .expect("curvature elements")
                .kappa
                .val()
                .grad(&grads)
                .expect("κ has a gradient"),
        );
        let scale = g.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        assert!(scale > 0.0);
        for &i in &[0, 1, t / 2, t - 1] {
            let eps = 1e-5 * kappa0[i];
            let (mut up, mut down) = (kappa0.clone(), kappa0.clone());
            up[i] += eps;
            down[i] -= eps;
            let l = |v: &[f64]| eval(v, &plain).1.total.into_scalar::<f64>();
            let fd = (l(&up) - l(&down)) / (2.0 * eps);
            assert!(
                (fd - g[i]).abs() <= 1e-6 * scale + 1e-6 * fd.abs(),
                "{on:?} {kernel:?} budget {budget}: dL/dκ[{i}]: autodiff {} vs finite difference \
                 {fd} (scale {scale})",
                g[i]
            );
        }
    }
}

/// The fused CPU kernel's forces (springs and curvature elements together) equal the tensor-op
/// reference's, at a bent, moving state.
#[test]
fn fused_and_reference_forces_agree_with_curvature_elements() {
    let device = device();
    let topo = grid(6, true);
    let s = topo.num_springs();
    let k: Vec<f64> = (0..s)
        .map(|i| 20.0 + 5.0 * (i as f64 * 0.3).sin())
        .collect();
    let b: Vec<f64> = (0..s).map(|i| 1.0 + 0.5 * (i as f64 * 0.7).cos()).collect();
    let kappa: Vec<f64> = (0..topo.curvature.len())
        .map(|i| 2.0 + (i as f64).sin())
        .collect();
    let x: Vec<[f64; 3]> = rest(&topo)
        .iter()
        .enumerate()
        .map(|(i, p)| {
            [
                p[0],
                p[1] + 0.03 * (i as f64).cos(),
                0.2 * (0.8 * i as f64).sin(),
            ]
        })
        .collect();
    let v: Vec<[f64; 3]> = (0..x.len())
        .map(|i| [(i as f64 * 0.4).sin(), 0.1, (i as f64 * 0.9).cos()])
        .collect();
    let forces = |kernel: Kernel| {
        let net = SpringNet::new(&topo, &k, &b, &device)
            .with_kernel(kernel)
            .with_curvature(&kappa);
        to_f64(net.forces(positions(&x, &device), positions(&v, &device)))
    };
    let (fused, reference) = (forces(Kernel::Fused), forces(Kernel::Reference));
    let scale = reference.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    for (i, (a, r)) in fused.iter().zip(&reference).enumerate() {
        assert!(
            (a - r).abs() <= 1e-12 * scale,
            "entry {i}: fused {a}, reference {r}"
        );
    }
}

#[test]
fn the_stability_bound_grows_with_kappa_and_holds_the_uniform_sheets_stiffest_mode() {
    let topo = grid(8, true);
    let s = topo.num_springs();
    let (m, dt) = (0.05, 1e-3);
    let base = Stability::estimate(&topo, &vec![0.0; s], &vec![0.0; s], m, 0.0, dt);
    let with = |kappa: f64| {
        base.clone()
            .with_curvature(&topo.curvature, &vec![kappa; topo.curvature.len()], 64)
            .omega2
    };
    assert_eq!(with(0.0), base.omega2);
    // Interior particles: 4κ + 4κ + 8κ along a row, and as much along a column and each diagonal.
    assert!((with(3.0) - 64.0 * 3.0 / m).abs() < 1e-9 * with(3.0));
    // The bound holds the true largest eigenvalue of the curvature stiffness matrix, found by
    // power iteration on the forces of a network with curvature only.
    let kappa = vec![3.0; topo.curvature.len()];
    let mut y: Vec<[f64; 3]> = (0..64)
        .map(|i| [((i * 7) % 5) as f64 - 2.0, 0.0, ((i * 3) % 4) as f64 - 1.5])
        .collect();
    let mut lambda = 0.0;
    // (forces at the rest grid plus `y`: the curvature forces are linear and zero at rest, and
    // the zero-stiffness springs need distinct particles to have a direction)
    let at = |y: &[[f64; 3]]| -> Vec<[f64; 3]> {
        rest(&topo)
            .iter()
            .zip(y)
            .map(|(p, d)| [p[0] + 0.01 * d[0], p[1] + 0.01 * d[1], p[2] + 0.01 * d[2]])
            .collect()
    };
    for _ in 0..300 {
        let f: Vec<f64> = curvature_forces(&topo, &kappa, &at(&y))
            .iter()
            .map(|v| v / 0.01)
            .collect();
        let norm = f.iter().map(|v| v * v).sum::<f64>().sqrt();
        let ynorm = y.iter().flatten().map(|v| v * v).sum::<f64>().sqrt();
        lambda = norm / ynorm;
        y = f
            .chunks(3)
            .map(|c| [-c[0] / norm, -c[1] / norm, -c[2] / norm])
            .collect();
    }
    assert!(lambda > 0.25 * 64.0 * 3.0, "power iteration found {lambda}");
    assert!(
        lambda / m <= with(3.0) * (1.0 + 1e-9),
        "{lambda} above the bound"
    );
}
