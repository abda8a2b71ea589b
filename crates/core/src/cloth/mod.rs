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
