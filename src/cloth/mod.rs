//! The cloth's rest geometry: the surrogate grid and its springs (paper §3.1).

mod topology;

mod resample;

pub use resample::Resampler;
pub use topology::{GridSpec, SpringFamily, Topology};
