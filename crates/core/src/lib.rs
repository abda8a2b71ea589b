//! springtime's library: learn simulatable mass-spring cloth models with per-spring stiffness
//! and damping from observed motion (Chen et al. 2025, "Mass-Spring Net" / SpringTime).
//!
//! The pipeline, in the order of the paper: [`source`] generates rollouts, [`data`] reads them
//! and cuts clips, [`cloth`] builds the surrogate grid and resamples landmarks to it, [`model`]
//! holds the per-spring parameters and the spring forces, [`sim`] rolls the surrogate out,
//! [`train`] fits it with the force-and-impulse loss, and [`eval`] measures it; [`sweep`] runs a
//! plan of such jobs by index. No command line, plotting or file-format policy lives here: the
//! `springtime` crate (the CLI) adds those, `springtime-xpbd` and `springtime-latent` hold the
//! second and third papers. See `ARCHITECTURE.md`.
#![warn(missing_docs)]

pub mod backend;
pub mod cloth;
pub mod config;
pub mod data;
pub mod eval;
pub mod formats;
pub mod io;
pub mod model;
pub mod progress;
pub mod run;
pub mod settings;
pub mod sim;
pub mod source;
pub mod sweep;
pub mod train;

use anyhow::{Result, bail};
use serde::Serialize;

/// The springtime build: crate version and the git commit it was built from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub struct BuildInfo {
    /// `CARGO_PKG_VERSION`.
    pub version: &'static str,
    /// `git rev-parse HEAD` at build time, or `unknown` outside a checkout.
    pub commit: &'static str,
}

impl BuildInfo {
    /// This binary's build.
    pub fn current() -> Self {
        Self {
            version: env!("CARGO_PKG_VERSION"),
            commit: env!("SPRINGTIME_GIT_COMMIT"),
        }
    }
}

use config::Config;
use progress::Progress;

/// Makes sure `config.data.dir` holds rollouts: generates them from `config.source` when the
/// directory has no `index.json` and no `.npz` files.
pub fn ensure_data(config: &Config, progress: &Progress) -> Result<()> {
    let dir = &config.data.dir;
    if matches!(data::Index::probe(dir)?, data::IndexFile::Springtime(_)) {
        return Ok(());
    }
    // Jobs of a sweep may share one data folder: one of them generates it while the others wait
    // for it, then find its index.
    let _lock = match &config.source {
        Some(_) => Some(source::generation_lock(dir, progress)?),
        None => None,
    };
    if matches!(data::Index::probe(dir)?, data::IndexFile::Springtime(_)) {
        return Ok(());
    }
    let has_files = dir.is_dir() && data::npz_files(dir).is_ok();
    match (&config.source, has_files) {
        (_, true) if config.source.is_none() => Ok(()),
        (Some(source), _) => {
            let total = (source.train_rollouts + source.test_rollouts) as u64;
            progress.note(&format!(
                "generating {total} rollouts into {}",
                dir.display()
            ));
            let bar = progress.bar(total, "generate");
            source::generate(source, &config.data.clips, dir, source::Shard::WHOLE, |n| {
                bar.set_position(n as u64)
            })?;
            bar.finish();
            Ok(())
        }
        (None, _) => bail!(
            "{} holds no rollouts and the config has no [source] section to generate them",
            dir.display()
        ),
    }
}
