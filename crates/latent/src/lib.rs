//! Self-supervised latent-space cloth dynamics (the third seed paper, Li et al. 2025,
//! "Self-supervised Learning of Latent Space Dynamics"; only its cloth example).
//!
//! The pipeline, each a module:
//! - [`scenario`]: the full-space reference — the FEM cloth stepped by implicit Euler
//!   ([`springtime_core::source::implicit`]) with pinned vertices on prescribed paths (two corners moving
//!   along a line at varying speed, §4.2; a sheet clamped along one edge sagging to rest, the
//!   cantilever ablation), written as ordinary rollout `.npz` files at 30 fps;
//! - [`autoencoder`]: positions relative to the mean of the pinned vertices, compressed by an
//!   MLP-ResNet (BatchNorm, SiLU) whose outer layers start from PCA (§3.2);
//! - [`integrator`]: the latent step `z_t = I(z_{t−1}, z_{t−2}, p_t, p_{t−1}, p_{t−2})` (Eq. 3);
//! - [`energy`]: the incremental potential of the implicit step (Eq. 4) as Burn tensor ops,
//!   the self-supervised loss through the frozen decoder;
//! - [`surrogate`] (beyond the paper): a trained springtime spring surrogate as the full-space
//!   cloth instead of the FEM sheet — distillation, `latent train --from runs/<name>`;
//!   [`full`] is either of the two;
//! - [`train`]: the two stages, with noise (Eq. 5), balancing (Eq. 6) and the supervised
//!   latent-L2 baseline;
//! - [`infer`]: the trained networks as plain Rust (BatchNorm folded), the real-time path;
//! - [`eval`]: autoregressive rollouts of unseen frames and the timing benchmark.
#![warn(missing_docs)]

pub mod autoencoder;
pub mod energy;
pub mod eval;
pub mod full;
pub mod infer;
pub mod integrator;
pub mod scenario;
pub mod subspace;
pub mod surrogate;
pub mod train;

use anyhow::{Result, bail};
use serde::{Deserialize, Serialize};

pub use scenario::{ClothConfig, ScenarioConfig};
use springtime_core::backend::Backend;
use springtime_core::settings::Job;
use springtime_core::source::implicit::NewtonConfig;

/// A latent-dynamics job (`configs/latent_cloth.toml`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LatentConfig {
    /// Job name.
    #[serde(default = "default_name")]
    pub name: String,
    /// Burn backend for training.
    #[serde(default)]
    pub backend: Backend,
    /// Seed of the networks' initialisation and of the noise.
    #[serde(default)]
    pub seed: u64,
    /// The sheet and its material.
    #[serde(default)]
    pub cloth: ClothConfig,
    /// What the pinned vertices do.
    #[serde(default)]
    pub scenario: ScenarioConfig,
    /// The full-space Newton solver.
    #[serde(default)]
    pub solver: NewtonConfig,
    /// The autoencoder and its training.
    #[serde(default)]
    pub autoencoder: autoencoder::AutoencoderConfig,
    /// The latent integrator and its training.
    #[serde(default)]
    pub integrator: integrator::IntegratorConfig,
}

fn default_name() -> String {
    "latent".into()
}

impl Job for LatentConfig {
    const KIND: &'static str = "latent";

    /// Checks ranges; errors name the key.
    fn validate(&self) -> Result<()> {
        self.cloth.validate()?;
        self.scenario.validate()?;
        self.solver.validate()?;
        self.autoencoder.validate()?;
        self.integrator.validate()?;
        // A PCA of `train_frames` frames has at most that many modes.
        if self.autoencoder.pca_modes > self.integrator.train_frames {
            bail!(
                "autoencoder.pca_modes ({}) exceeds integrator.train_frames ({}): a PCA of that \
                 many frames has fewer modes",
                self.autoencoder.pca_modes,
                self.integrator.train_frames
            );
        }
        let frames = self.scenario.frames;
        if self.integrator.train_frames + 2 > frames {
            bail!(
                "integrator.train_frames ({}) leaves no unseen frames of the {frames} in \
                 scenario.frames",
                self.integrator.train_frames
            );
        }
        Ok(())
    }
}
