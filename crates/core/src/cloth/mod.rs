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
pub use topology::{Diagonal, GridSpec, SpringFamily, SpringLayout, Topology, grid_triangles};

/// The flat sheet at rest in the horizontal plane, centred at the origin.
pub fn flat(rest_uv: &[[f64; 2]], width: f64, height: f64) -> Vec<[f64; 3]> {
    rest_uv
        .iter()
        .map(|p| [p[0] - 0.5 * width, p[1] - 0.5 * height, 0.0])
        .collect()
}
