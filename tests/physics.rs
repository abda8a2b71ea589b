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
