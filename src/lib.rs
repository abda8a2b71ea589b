//! springtime: learn simulatable mass-spring cloth models with per-spring stiffness and damping
//! from observed motion (Chen et al. 2025, "Mass-Spring Net" / SpringTime).
//!
//! This crate is the application: the command line ([`cli`]), the run report ([`report`]),
//! import and export of other tools' files ([`import`], [`export`]) and the studies built on the
//! library — [`compare`], [`diagnose`], [`fold`], [`drape`], [`bench`](mod@bench). The method itself lives
//! in `springtime-core` and is re-exported here module by module ([`source`], [`data`],
//! [`cloth`], [`model`], [`sim`], [`train`], [`eval`], …), so `springtime::train::train` is the
//! same function as `springtime_core::train::train`. [`xpbd`] holds the static parameter
//! estimation of the second seed paper, [`latent`] the latent-space dynamics of the third. See
//! `ARCHITECTURE.md`.
#![warn(missing_docs)]

pub mod bench;
pub mod check;
pub mod cli;
pub mod compare;
pub mod diagnose;
pub mod drape;
pub mod export;
pub mod fold;
pub mod import;
pub mod report;
pub mod sweep;

pub use springtime_core::{
    BuildInfo, backend, cloth, config, data, ensure_data, eval, formats, io, model, progress, run,
    settings, sim, source, train,
};
/// Latent-space dynamics (paper 002): the `springtime-latent` crate.
pub use springtime_latent as latent;
/// Figure primitives: the `springtime-plot` crate.
pub use springtime_plot as plot;
/// Static cloth parameters from drapes (paper 001): the `springtime-xpbd` crate.
pub use springtime_xpbd as xpbd;
