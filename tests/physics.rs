//! Conservation laws and Eq. 4 against an independent f64 implementation.

mod common;

use burn::tensor::{Device, Tensor, TensorData};
use rand::{Rng, SeedableRng, rngs::StdRng};
use springtime::model::{SpringNet, springs::to_f64};
use springtime::sim::{self, Physics, State};
use springtime::source::SpringCloth;

fn random_state(p: usize, b: usize, seed: u64) -> (Vec<f64>, Vec<f64>) {
    let mut rng = StdRng::seed_from_u64(seed);
    let cfg = common::source(5, &[10.0, 50.0, 100.0], 1.0);
    let rest = common::grid_of(&cfg).rest_positions();
    assert_eq!(rest.len(), p);
    let mut x = Vec::new();
    let mut v = Vec::new();
    for _ in 0..b {
        for r in &rest {
            for c in r {
                x.push(c + rng.random_range(-0.2..0.2));
                v.push(rng.random_range(-1.0..1.0));
            }
        }
    }
    (x, v)
}

#[test]
fn internal_forces_sum_to_zero_and_match_the_f64_reference() {
    let device = Device::flex();
    let cfg = common::source(5, &[10.0, 50.0, 100.0], 1.0);
    let cloth = SpringCloth::from_config(&cfg);
    let topo = &cloth.topology;
    let (p, b) = (topo.num_particles(), 3);
    let model = SpringNet::new(topo, &cloth.k, &cloth.b, &device);
    for seed in 0..4 {
        let (x, v) = random_state(p, b, seed);
        let xt = Tensor::<3>::from_data(TensorData::new(x.clone(), [b, p, 3]), &device);
        let vt = Tensor::<3>::from_data(TensorData::new(v.clone(), [b, p, 3]), &device);
        let f = to_f64(model.forces(xt, vt));
        for clip in 0..b {
            let fc = &f[clip * p * 3..(clip + 1) * p * 3];
            // Σ_p f_p = 0: each spring adds +f_s and −f_s (Newton's third law).
            let magnitude: f64 = fc.iter().map(|c| c.abs()).sum();
            for c in 0..3 {
                let net: f64 = fc.iter().skip(c).step_by(3).sum();
                assert!(
                    net.abs() <= 1e-6 * magnitude,
                    "clip {clip}: net internal force {net} (Σ|f| = {magnitude})"
                );
            }
            // The f64 source computes Eq. 4 + gravity + Rayleigh; remove the external part.
            let xs: Vec<[f64; 3]> = x[clip * p * 3..(clip + 1) * p * 3]
                .chunks(3)
                .map(|c| [c[0], c[1], c[2]])
                .collect();
            let vs: Vec<[f64; 3]> = v[clip * p * 3..(clip + 1) * p * 3]
                .chunks(3)
                .map(|c| [c[0], c[1], c[2]])
                .collect();
            let mut reference = vec![[0.0; 3]; p];
            cloth.forces(&xs, &vs, &mut reference);
            let largest = fc.iter().fold(0.0f64, |m, c| m.max(c.abs()));
            for i in 0..p {
                for c in 0..3 {
                    let external = cloth.mass * cloth.gravity[c] - cloth.rayleigh * vs[i][c];
                    let want = reference[i][c] - external;
                    assert!(
                        (fc[i * 3 + c] - want).abs() <= 1e-5 * largest,
                        "particle {i}: {} vs {want}",
                        fc[i * 3 + c]
                    );
                }
            }
        }
    }
}

#[test]
fn free_flight_conserves_momentum_and_rest_is_an_equilibrium() {
    let device = Device::flex();
    let cfg = common::source(5, &[10.0, 50.0, 100.0], 1.0);
    let cloth = SpringCloth::from_config(&cfg);
    let topo = &cloth.topology;
    let p = topo.num_particles();
    let model = SpringNet::new(topo, &cloth.k, &cloth.b, &device);
    let physics = Physics {
        frame_dt: 1e-3,
        substeps: 1,
        mass: cloth.mass,
        rayleigh: 0.0,
        gravity: [0.0; 3],
        viscosity: 0.0,
        shear_compression: 1.0,
    };
    let pinned = Tensor::<3>::zeros([1, p, 1], &device);
    // At rest, with no gravity, nothing moves.
    let rest: Vec<f64> = topo.rest_positions().into_iter().flatten().collect();
    let x_rest = Tensor::<3>::from_data(TensorData::new(rest, [1, p, 3]), &device);
    let f_rest = to_f64(model.forces(x_rest.clone(), Tensor::zeros([1, p, 3], &device)));
    assert!(
        f_rest.iter().all(|f| f.abs() < 1e-4),
        "spring force at rest: {:?}",
        f_rest.iter().fold(0.0f64, |m, f| m.max(f.abs()))
    );
    // From a deformed, moving state the total momentum stays constant.
    let (x, v) = random_state(p, 1, 7);
    let momentum = |v: &Tensor<3>| {
        let s = to_f64(v.clone().sum_dim(1));
        [s[0] * cloth.mass, s[1] * cloth.mass, s[2] * cloth.mass]
    };
    let mut state = State {
        x: Tensor::from_data(TensorData::new(x, [1, p, 3]), &device),
        v: Tensor::from_data(TensorData::new(v, [1, p, 3]), &device),
    };
    let p0 = momentum(&state.v);
    let scale = to_f64(state.v.clone().abs().sum()).iter().sum::<f64>() * cloth.mass;
    let mut moved = 0.0;
    for _ in 0..300 {
        let here = state.x.clone();
        let (s, _) = sim::step_frame(&model, &physics, None, state, &pinned, &here, &here);
        moved += to_f64((s.x.clone() - here).abs().sum())[0];
        state = s;
    }
    assert!(moved > 1.0, "the cloth moved");
    let p1 = momentum(&state.v);
    for c in 0..3 {
        assert!(
            (p1[c] - p0[c]).abs() <= 1e-4 * scale,
            "momentum[{c}]: {} → {}",
            p0[c],
            p1[c]
        );
    }
}

/// The springs' isotropic viscosity (`sim.viscosity = β`): the net force of a step with it less
/// the step without it is `β k_s (v_b − v_a)` on each spring's `a` and its opposite on `b`,
/// against an f64 sum here, through the fused step and the tensor-op step alike; it sums to zero
/// (momentum), dissipates (its power is `−Σ β k_s |v_b − v_a|²`) and vanishes when the cloth
/// translates as a whole.
#[test]
fn viscosity_matches_the_f64_sum_conserves_momentum_and_dissipates() {
    use springtime::model::Kernel;
    let device = Device::flex();
    let cfg = common::source(5, &[10.0, 50.0, 100.0], 1.0);
    let cloth = SpringCloth::from_config(&cfg);
    let topo = &cloth.topology;
    let p = topo.num_particles();
    let beta = 0.01;
    let physics = |viscosity: f64| Physics {
        frame_dt: 1e-3,
        substeps: 1,
        mass: cloth.mass,
        rayleigh: 0.0,
        gravity: [0.0; 3],
        viscosity,
        shear_compression: 1.0,
    };
    let pinned = Tensor::<3>::zeros([1, p, 1], &device);
    let (x, v) = random_state(p, 1, 3);
    let translating = [0.7, -0.2, 0.4].repeat(p);
    for kernel in [Kernel::Fused, Kernel::Reference] {
        let model = SpringNet::new(topo, &cloth.k, &cloth.b, &device).with_kernel(kernel);
        let viscous = |v: &[f64]| {
            let state = || State {
                x: Tensor::from_data(TensorData::new(x.clone(), [1, p, 3]), &device),
                v: Tensor::from_data(TensorData::new(v.to_vec(), [1, p, 3]), &device),
            };
            let here = state().x;
            let (_, with) =
                sim::step_frame(&model, &physics(beta), None, state(), &pinned, &here, &here);
            let (_, without) =
                sim::step_frame(&model, &physics(0.0), None, state(), &pinned, &here, &here);
            to_f64(with - without)
        };
        let f = viscous(&v);
        let mut expected = vec![0.0; 3 * p];
        let mut power = 0.0;
        for (s, &[a, b]) in topo.springs.iter().enumerate() {
            let nu = beta * cloth.k[s];
            for c in 0..3 {
                let w = v[3 * b + c] - v[3 * a + c];
                expected[3 * a + c] += nu * w;
                expected[3 * b + c] -= nu * w;
                power -= nu * w * w;
            }
        }
        common::assert_close(&format!("{kernel:?} viscous forces"), &expected, &f, 1e-4);
        let magnitude: f64 = f.iter().map(|c| c.abs()).sum();
        assert!(
            magnitude > 1.0,
            "{kernel:?}: the viscosity acts ({magnitude} N)"
        );
        for c in 0..3 {
            let net: f64 = f.iter().skip(c).step_by(3).sum();
            assert!(
                net.abs() <= 1e-5 * magnitude,
                "{kernel:?}: net viscous force {net}"
            );
        }
        let done: f64 = f.iter().zip(&v).map(|(f, v)| f * v).sum();
        assert!(power < 0.0 && (done - power).abs() <= 1e-4 * power.abs());
        let still = viscous(&translating);
        assert!(
            still.iter().all(|f| f.abs() <= 1e-5 * magnitude),
            "{kernel:?}: a translating cloth feels the viscosity"
        );
    }
}
