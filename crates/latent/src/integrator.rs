//! The latent integrator (the latent paper's Eq. 3): an MLP with SiLU,
//! `ẑ_t = I(ẑ_{t−1}, ẑ_{t−2}, p)`, on latents standardised by the training frames' mean and
//! deviation. The boundary conditions `p` (the paper leaves them undefined for cloth, gap G11)
//! are the pinned vertices' prescribed positions at `t`, `t − 1` and `t − 2`, relative to
//! their mean at `t − 1` and divided by the sheet's size: they carry the pins' velocity and
//! acceleration and nothing absolute.

use anyhow::{Result, bail};
use burn::module::Module;
use burn::nn::{Linear, LinearConfig};
use burn::tensor::activation::silu;
use burn::tensor::{Device, Tensor};
use serde::{Deserialize, Serialize};

use super::subspace::SolveConfig;
use springtime_core::cloth::triangles::V3;

/// What the integrator is trained to minimise.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[serde(rename_all = "snake_case")]
pub enum LossKind {
    /// The incremental potential of the decoded step (Eq. 4): no ground truth needed.
    #[default]
    #[cfg_attr(feature = "clap", value(name = "self"))]
    #[serde(rename = "self")]
    SelfSupervised,
    /// The baseline: `‖ẑ_t − ẑ_t^GT‖²` against the encoded reference (§4.5).
    Supervised,
    /// Ours: Eq. 4 minimised in two stages — every training step's latent minimiser of the
    /// potential solved first (and that of `noisy_copies` noisy copies of each, Eq. 5's
    /// states), then `‖ẑ_t − argmin Φ‖²`. The loss uses no ground truth; with `rounds > 1`
    /// the integrator's own rollouts restart from the encoded reference where they leave it
    /// by more than the sheet's size.
    Solved,
}

/// The `[integrator]` section.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct IntegratorConfig {
    /// Hidden widths (the paper's cloth: 32, 32).
    pub hidden: Vec<usize>,
    /// Epochs over the training steps (the paper: 10,000).
    pub epochs: usize,
    /// Steps per batch (the paper does not say).
    pub batch: usize,
    /// Adam learning rate (the paper: 1e-4).
    pub lr: f64,
    /// Learning rate of the last epoch: the rate decays geometrically from `lr` to it.
    pub lr_end: f64,
    /// The loss.
    pub loss: LossKind,
    /// Uniform noise on `ẑ_{t−1}`, `ẑ_{t−2}` as a fraction of the batch's deviation (Eq. 5; the
    /// paper: 0.1); 0 disables the noisy copies.
    pub noise: f64,
    /// Divide each step's loss by its decoded mean velocity `|v̄_{t−1}|` (Eq. 6).
    pub balance: bool,
    /// Floor of `|v̄|` in the balancing, m/s (gap G13: `|v̄| → 0` at rest).
    pub velocity_floor: f64,
    /// Weight of the soft boundary condition, J/m² (the paper: 1e5).
    pub w_bc: f64,
    /// Frames `0 .. train_frames` train; the rest are unseen (the paper: 750 of 1500).
    pub train_frames: usize,
    /// Predict `2ẑ_{t−1} − ẑ_{t−2} + I(…)` instead of `I(…)` (gap G10; the paper: off).
    pub residual: bool,
    /// With `loss = "solved"`: noisy copies of every training step, each solved once.
    pub noisy_copies: usize,
    /// With `loss = "solved"`: the latent minimiser's search.
    pub solve: SolveConfig,
    /// With `loss = "solved"`: rounds of `epochs` each; every round after the first adds the
    /// steps the integrator visits rolling out over the training frames, solved (ours). The
    /// learning rate decays once over all rounds, and Adam's state carries over.
    pub rounds: usize,
}

impl Default for IntegratorConfig {
    /// The paper's cloth: 32, 32; noise 0.1; balancing on; `w_bc = 1e5`; 750 training frames.
    /// 400 epochs of batch 250 at 1e-3 instead of 10,000 at 1e-4 (two CPU cores).
    fn default() -> Self {
        Self {
            hidden: vec![32, 32],
            epochs: 400,
            batch: 250,
            lr: 1e-3,
            lr_end: 1e-5,
            loss: LossKind::SelfSupervised,
            noise: 0.1,
            balance: true,
            velocity_floor: 0.01,
            w_bc: 1e5,
            train_frames: 750,
            residual: false,
            noisy_copies: 4,
            solve: SolveConfig::default(),
            rounds: 1,
        }
    }
}

impl IntegratorConfig {
    /// The learning rate of `epoch` of `epochs`: geometric from `lr` to `lr_end`.
    pub fn rate(&self, epoch: usize, epochs: usize) -> f64 {
        let f = epoch as f64 / (epochs.max(2) - 1) as f64;
        self.lr * (self.lr_end / self.lr).powf(f)
    }

    /// Checks ranges; errors name the key.
    pub fn validate(&self) -> Result<()> {
        if self.hidden.is_empty() || self.hidden.contains(&0) || self.batch == 0 {
            bail!("integrator.hidden must list positive widths and integrator.batch be ≥ 1");
        }
        if !(self.lr > 0.0 && self.lr.is_finite() && self.lr_end > 0.0 && self.lr_end <= self.lr) {
            bail!(
                "integrator.lr must be positive and integrator.lr_end in (0, lr], are {} and {}",
                self.lr,
                self.lr_end
            );
        }
        if !(self.noise >= 0.0 && self.noise.is_finite()) {
            bail!("integrator.noise must be ≥ 0, is {}", self.noise);
        }
        if !(self.w_bc > 0.0) || !(self.velocity_floor > 0.0) {
            bail!("integrator.w_bc and integrator.velocity_floor must be positive");
        }
        let positive = |v: f64| v > 0.0 && v.is_finite();
        if self.solve.iterations == 0
            || !positive(self.solve.tolerance)
            || !positive(self.solve.epsilon)
        {
            bail!(
                "integrator.solve.iterations, .tolerance and .epsilon must be positive and \
                 finite, are {}, {} and {}",
                self.solve.iterations,
                self.solve.tolerance,
                self.solve.epsilon
            );
        }
        if self.rounds == 0 {
            bail!("integrator.rounds must be at least 1");
        }
        if self.train_frames < 3 {
            bail!("integrator.train_frames must be at least 3");
        }
        Ok(())
    }
}

/// The MLP.
#[derive(Module, Debug)]
pub struct Integrator {
    /// Hidden layers (SiLU after each).
    pub layers: Vec<Linear>,
    /// Output layer.
    pub out: Linear,
    /// Whether the output is added to `2ẑ_{t−1} − ẑ_{t−2}`.
    #[module(skip)]
    pub residual: bool,
    /// Latent dimension.
    #[module(skip)]
    pub latent: usize,
}

impl Integrator {
    /// A fresh integrator for `latent` coordinates and `features` boundary features.
    pub fn new(config: &IntegratorConfig, latent: usize, features: usize, device: &Device) -> Self {
        let mut widths = vec![2 * latent + features];
        widths.extend(&config.hidden);
        Self {
            layers: widths
                .windows(2)
                .map(|w| LinearConfig::new(w[0], w[1]).init(device))
                .collect(),
            out: LinearConfig::new(*widths.last().unwrap(), latent).init(device),
            residual: config.residual,
            latent,
        }
    }

    /// `[B, 2L + P] → [B, L]`: the input is `[ẑ_{t−1}, ẑ_{t−2}, p]`.
    pub fn forward(&self, input: Tensor<2>) -> Tensor<2> {
        let mut h = input.clone();
        for layer in &self.layers {
            h = silu(layer.forward(h));
        }
        let out = self.out.forward(h);
        if self.residual {
            let l = self.latent;
            let z1 = input.clone().slice([0..input.dims()[0], 0..l]);
            let z2 = input.clone().slice([0..input.dims()[0], l..2 * l]);
            out + z1 * 2.0 - z2
        } else {
            out
        }
    }
}

/// The integrator's input `[ẑ_{t−1}, ẑ_{t−2}, p]`.
pub fn step_input(z1: &[f32], z2: &[f32], features: &[f32]) -> Vec<f32> {
    [z1, z2, features].concat()
}

/// The boundary features `p` of step `t` from the pinned targets at `t`, `t − 1`, `t − 2`
/// (each `[P]`), relative to the mean at `t − 1`, over `length`.
pub fn boundary_features(now: &[V3], prev: &[V3], prev2: &[V3], length: f64) -> Vec<f32> {
    let centre = mean(prev);
    [now, prev, prev2]
        .iter()
        .flat_map(|frame| {
            frame
                .iter()
                .flat_map(|p| [0, 1, 2].map(|c| ((p[c] - centre[c]) / length) as f32))
        })
        .collect()
}

/// The mean of points.
pub fn mean(points: &[V3]) -> V3 {
    let n = points.len().max(1) as f64;
    [0, 1, 2].map(|c| points.iter().map(|p| p[c]).sum::<f64>() / n)
}
