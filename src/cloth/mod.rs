//! The cloth's rest geometry: the surrogate grid and its springs (paper §3.1), and the
//! triangle-mesh maths the FEM source and the XPBD estimator share (`triangles`).

mod topology;

mod resample;
pub mod triangles;

pub use resample::Resampler;
pub use topology::{GridSpec, SpringFamily, Topology};
