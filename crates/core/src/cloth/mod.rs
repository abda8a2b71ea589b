//! The cloth's rest geometry: the surrogate grid and its springs (paper §3.1), and the
//! triangle-mesh maths the FEM source and the XPBD estimator share (`triangles`, written over
//! `lanes`' number types so that the FEM evaluates it eight elements at a time), and the banded
//! solver their Newton steps share (`band`).

mod topology;

pub mod band;
pub mod dual;
pub mod lanes;
pub(crate) mod resample;
pub mod triangles;

pub use resample::{Resampler, twice_area};
pub use topology::{
    Diagonal, GridSpec, ParticleMasses, SpringFamily, SpringLayout, Topology, grid_triangles,
};

/// The flat sheet at rest in the horizontal plane, centred at the origin.
pub fn flat(rest_uv: &[[f64; 2]], width: f64, height: f64) -> Vec<[f64; 3]> {
    rest_uv
        .iter()
        .map(|p| [p[0] - 0.5 * width, p[1] - 0.5 * height, 0.0])
        .collect()
}

/// Largest eigenvalue of a symmetric positive semi-definite operator on `[n]` 3-vectors by
/// `iterations` steps of power iteration from a fixed start vector with components in every
/// direction; `apply(y, z)` adds the operator's action on `y` to `z` (zeroed before each call).
/// The stability estimates of the surrogate ([`Topology`]) and of the FEM source share it.
pub(crate) fn power_iteration(
    n: usize,
    iterations: usize,
    mut apply: impl FnMut(&[[f64; 3]], &mut [[f64; 3]]),
) -> f64 {
    let mut y: Vec<[f64; 3]> = (0..n)
        .map(|i| {
            let t = i as f64;
            [
                (t * 0.7548).sin() + 0.3,
                (t * 1.3247).cos() - 0.2,
                (t * 0.5698).sin(),
            ]
        })
        .collect();
    let mut z = vec![[0.0f64; 3]; n];
    let mut lambda = 0.0;
    for _ in 0..iterations {
        z.iter_mut().for_each(|v| *v = [0.0; 3]);
        apply(&y, &mut z);
        let norm_z = z.iter().flatten().map(|v| v * v).sum::<f64>().sqrt();
        let norm_y = y.iter().flatten().map(|v| v * v).sum::<f64>().sqrt();
        if norm_z == 0.0 || norm_y == 0.0 {
            return 0.0;
        }
        lambda = norm_z / norm_y;
        for (y, z) in y.iter_mut().zip(&z) {
            *y = [z[0] / norm_z, z[1] / norm_z, z[2] / norm_z];
        }
    }
    lambda
}
