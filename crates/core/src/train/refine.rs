//! Per-spring refinement of a searched network by its own motion (ours; `train.refine`).
//!
//! PhysTwin's order: the global parameters by a zero-order search first (the blend or scale
//! search), then per-spring first-order steps of a multi-step *position* loss over short windows
//! of the training takes (multiple shooting: every clip starts from the data's own state). The
//! steps are Adam's on `log k` (and with `train_b` on `log b`), so a spring moves by a share of
//! its own size whatever the material's scale, and no value crosses zero. The substeps rise as
//! the refined network needs (within the searches' cap). The refined network is kept only where
//! its free rollouts of the searches' training takes move closer than the searched one's.

use std::sync::Arc;

use anyhow::{Result, bail};
use serde::{Deserialize, Serialize};

use burn::tensor::{Device, Tensor};

use crate::cloth::Topology;
use crate::data::{ClipSet, Sampler};
use crate::eval::Takes;
use crate::model::SpringNet;
use crate::model::springs::to_f64;
use crate::progress::Progress;
use crate::sim::Physics;
use crate::train::losses::{ForceOn, LossWeights, loss_with_budget};
use crate::train::scale;

/// The shift of the refinement's log parameter, as a share of the mean `k`.
const SHIFT_SHARE: f64 = 0.01;

/// `[train.refine]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RefineConfig {
    /// Adam steps; 0: no refinement.
    pub iterations: usize,
    /// Clips per step.
    pub batch: usize,
    /// Adam's step in `log k` (a share of each spring's own size) at the first iteration.
    pub lr: f64,
    /// The step at the last iteration as a fraction of `lr` (geometric decay).
    pub lr_decay: f64,
    /// Refine each spring's `b` too (on `log b`; springs without damping keep none).
    pub train_b: bool,
}

impl Default for RefineConfig {
    fn default() -> Self {
        Self {
            iterations: 0,
            batch: 16,
            lr: 0.02,
            lr_decay: 0.1,
            train_b: false,
        }
    }
}

impl RefineConfig {
    /// Checks ranges; errors name the key.
    pub fn validate(&self) -> Result<()> {
        if self.batch == 0 {
            bail!("`train.refine.batch` must be at least 1");
        }
        if !(self.lr >= 0.0 && self.lr.is_finite()) {
            bail!(
                "`train.refine.lr` must be a non-negative number, is {}",
                self.lr
            );
        }
        if !(self.lr_decay > 0.0 && self.lr_decay <= 1.0) {
            bail!(
                "`train.refine.lr_decay` must be in (0, 1], is {}",
                self.lr_decay
            );
        }
        Ok(())
    }

    /// The step of iteration `i` (from 0).
    fn lr_at(&self, i: usize) -> f64 {
        let f = i as f64 / (self.iterations.max(2) - 1) as f64;
        self.lr * self.lr_decay.powf(f)
    }
}

/// `refine.json`: what the refinement did and kept.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Refinement {
    /// Adam steps taken (fewer than `train.refine.iterations` where the loss stopped being
    /// finite).
    pub iterations: usize,
    /// The position loss of every step's batch (m²; each step draws its own clips).
    pub losses: Vec<f64>,
    /// Mean motion RMSE of the searched network on the searches' training takes (m).
    pub before: f64,
    /// The same of the refined network; `None` when it is unstable or diverged.
    pub after: Option<f64>,
    /// The substeps per frame the refined network runs at.
    pub substeps: usize,
    /// Whether the refined network was kept.
    pub kept: bool,
    /// RMS of the change of `log k` over the springs.
    pub log_k_change: f64,
}

impl Refinement {
    /// The mean position loss of the first and of the last eighth of the steps (each step's
    /// batch is its own draw, so one step's figure is noisy).
    pub fn loss_change(&self) -> (f64, f64) {
        let n = self.losses.len().div_ceil(8).max(1);
        let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len().max(1) as f64;
        let tail = self.losses.len().saturating_sub(n);
        (
            mean(&self.losses[..n.min(self.losses.len())]),
            mean(&self.losses[tail..]),
        )
    }
}

/// Adam's moments of a vector of log-parameters.
struct Adam {
    m: Vec<f64>,
    v: Vec<f64>,
    t: i32,
}

impl Adam {
    const BETA1: f64 = 0.9;
    const BETA2: f64 = 0.999;
    const EPS: f64 = 1e-12;

    fn new(n: usize) -> Self {
        Self {
            m: vec![0.0; n],
            v: vec![0.0; n],
            t: 0,
        }
    }

    /// One step of `x` down the gradient `g` at rate `lr`.
    fn step(&mut self, x: &mut [f64], g: &[f64], lr: f64) {
        self.t += 1;
        let (c1, c2) = (
            1.0 - Self::BETA1.powi(self.t),
            1.0 - Self::BETA2.powi(self.t),
        );
        for i in 0..x.len() {
            self.m[i] = Self::BETA1 * self.m[i] + (1.0 - Self::BETA1) * g[i];
            self.v[i] = Self::BETA2 * self.v[i] + (1.0 - Self::BETA2) * g[i] * g[i];
            x[i] -= lr * (self.m[i] / c1) / ((self.v[i] / c2).sqrt() + Self::EPS);
        }
    }
}

/// What the refinement works on.
pub(crate) struct Refiner<'a> {
    pub config: &'a RefineConfig,
    /// The training clips (windows of the training takes).
    pub clips: &'a Arc<ClipSet>,
    /// The training takes the kept network is chosen on.
    pub takes: &'a Takes<'a>,
    /// The autodiff device of the steps.
    pub device: &'a burn::tensor::Device,
    pub seed: u64,
    pub state_budget_mib: usize,
    pub progress: &'a Progress,
}

/// The refined parameters: `θ = log(k + c)` per spring (and `log b` with `train_b`), each with
/// its Adam moments.
struct LogParams {
    log_k: Vec<f64>,
    log_b: Option<Vec<f64>>,
    /// The untrained `b` (without `train_b`).
    b: Vec<f64>,
    /// `c`: springs at zero start exactly there and can rise (`k = max(e^θ − c, 0)`).
    shift: f64,
    adam_k: Adam,
    adam_b: Adam,
}

impl LogParams {
    fn new(k: &[f64], b: &[f64], train_b: bool) -> Result<Self> {
        let mean = k.iter().sum::<f64>() / k.len().max(1) as f64;
        if !(mean > 0.0) {
            bail!("`train.refine` steps log k; every k of the searched network is 0");
        }
        let shift = SHIFT_SHARE * mean;
        let train_b = train_b && b.iter().all(|&x| x > 0.0);
        Ok(Self {
            log_k: k.iter().map(|k| (k.max(0.0) + shift).ln()).collect(),
            log_b: train_b.then(|| b.iter().map(|b| b.ln()).collect()),
            b: b.to_vec(),
            shift,
            adam_k: Adam::new(k.len()),
            adam_b: Adam::new(b.len()),
        })
    }

    fn k(&self) -> Vec<f64> {
        self.log_k
            .iter()
            .map(|t| (t.exp() - self.shift).max(0.0))
            .collect()
    }

    fn b(&self) -> Vec<f64> {
        match &self.log_b {
            Some(log_b) => log_b.iter().map(|t| t.exp()).collect(),
            None => self.b.clone(),
        }
    }

    /// One Adam step of rate `lr` from the gradients with respect to `k` and `b` (a gradient
    /// that is missing or not finite steps nothing).
    fn step(&mut self, g_k: Option<Tensor<1>>, g_b: Option<Tensor<1>>, lr: f64) {
        // dk/dθ = e^θ for both parameters.
        let chain = |g: Option<Tensor<1>>, theta: &[f64]| -> Option<Vec<f64>> {
            let g: Vec<f64> = to_f64(g?)
                .iter()
                .zip(theta)
                .map(|(g, t)| g * t.exp())
                .collect();
            g.iter().all(|v| v.is_finite()).then_some(g)
        };
        if let Some(g) = chain(g_k, &self.log_k) {
            self.adam_k.step(&mut self.log_k, &g, lr);
        }
        if let Some(log_b) = &mut self.log_b
            && let Some(g) = chain(g_b, log_b)
        {
            self.adam_b.step(log_b, &g, lr);
        }
    }

    /// The RMS change of `θ` from the network `k`.
    fn change_from(&self, k: &[f64]) -> f64 {
        let sum: f64 = self
            .log_k
            .iter()
            .zip(k)
            .map(|(t, k)| (t - (k.max(0.0) + self.shift).ln()).powi(2))
            .sum();
        (sum / k.len().max(1) as f64).sqrt()
    }
}

impl Refiner<'_> {
    /// Refines `net` (running at `physics`); returns the kept network, its physics and the
    /// record.
    pub fn refine(
        &self,
        net: &SpringNet,
        physics: &Physics,
    ) -> Result<(SpringNet, Physics, Refinement)> {
        let k0 = net.k_values();
        let mut params = LogParams::new(&k0, &net.b_values(), self.config.train_b)?;
        let losses = self.steps(net, physics, &mut params)?;
        let refined = like(
            net,
            self.takes.topology,
            &params.k(),
            &params.b(),
            self.takes.device,
        );
        let before = scale::score_network(net, physics, self.takes)
            .map(|(_, r)| r)
            .ok_or_else(|| anyhow::anyhow!("refine: the searched network does not roll out"))?;
        let scored = scale::score_network(&refined, physics, self.takes);
        let kept = scored.is_some_and(|(_, r)| r < before);
        let record = Refinement {
            iterations: losses.len(),
            losses,
            before,
            after: scored.map(|(_, r)| r),
            substeps: scored.map_or(physics.substeps, |(n, _)| n),
            kept,
            log_k_change: params.change_from(&k0),
        };
        Ok(match scored {
            Some((substeps, _)) if kept => (
                refined,
                Physics {
                    substeps,
                    ..*physics
                },
                record,
            ),
            _ => (net.clone(), *physics, record),
        })
    }

    /// The Adam steps on `params` from `net`'s shape; returns each step's position loss (they
    /// stop early where it is not finite).
    fn steps(
        &self,
        net: &SpringNet,
        physics: &Physics,
        params: &mut LogParams,
    ) -> Result<Vec<f64>> {
        let config = self.config;
        let weights = LossWeights {
            force: 0.0,
            impulse: 0.0,
            position: 1.0,
            k_neg: 0.0,
            b_neg: 0.0,
        };
        let pool = self.clips.all_clips();
        if pool.is_empty() {
            bail!("`train.refine`: the training data has no clips");
        }
        let mut sampler = Sampler::new(pool.len(), self.seed ^ 0x2545_F491_4F6C_DD1D);
        let mut at = *physics;
        let mut losses = Vec::with_capacity(config.iterations);
        let bar = self.progress.bar(config.iterations as u64, "refine");
        for it in 0..config.iterations {
            let refs: Vec<_> = sampler
                .next(config.batch)
                .into_iter()
                .map(|i| pool[i])
                .collect();
            let batch = self
                .clips
                .host_batch_of(&refs, self.clips.steps)?
                .to_device(self.device)?;
            let model = like(
                net,
                self.takes.topology,
                &params.k(),
                &params.b(),
                self.device,
            );
            if let Some(n) = scale::stable_substeps(self.takes.topology, &at, &model) {
                at.substeps = n;
            }
            let terms = loss_with_budget(
                &model,
                &at,
                &batch,
                &weights,
                ForceOn::Simulated,
                self.state_budget_mib,
            );
            let loss = terms.total.clone().into_scalar::<f32>() as f64;
            if !loss.is_finite() {
                self.progress.note(&format!(
                    "refine: the loss became {loss} at step {}; the refinement stops there",
                    it + 1
                ));
                break;
            }
            losses.push(loss);
            let grads = terms.total.backward();
            params.step(
                model.k.val().grad(&grads),
                model.b.val().grad(&grads),
                config.lr_at(it),
            );
            bar.set_message(format!("position loss {loss:.3e} m²"));
            bar.inc(1);
        }
        bar.finish();
        Ok(losses)
    }
}

/// A network of `net`'s springs (`topology`'s), kernel and curvature elements with the values `k`, `b`.
fn like(net: &SpringNet, topology: &Topology, k: &[f64], b: &[f64], device: &Device) -> SpringNet {
    SpringNet::new(topology, k, b, device)
        .with_kernel(net.graph.kernel)
        .with_curvature(&net.curvature_values())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bad_settings_are_refused_naming_the_key() {
        let bad = [
            RefineConfig {
                batch: 0,
                ..RefineConfig::default()
            },
            RefineConfig {
                lr: f64::NAN,
                ..RefineConfig::default()
            },
            RefineConfig {
                lr_decay: 0.0,
                ..RefineConfig::default()
            },
        ];
        for (config, key) in bad.iter().zip(["batch", "lr", "lr_decay"]) {
            let err = config.validate().unwrap_err().to_string();
            assert!(err.contains(&format!("`train.refine.{key}`")), "{err}");
        }
        RefineConfig::default().validate().unwrap();
    }

    /// The step decays geometrically from `lr` at the first step to `lr · lr_decay` at the last.
    #[test]
    fn the_step_decays_from_lr_to_lr_times_decay() {
        let c = RefineConfig {
            iterations: 11,
            lr: 0.1,
            lr_decay: 0.01,
            ..RefineConfig::default()
        };
        assert!((c.lr_at(0) - 0.1).abs() < 1e-15);
        assert!((c.lr_at(5) - 0.01).abs() < 1e-12);
        assert!((c.lr_at(10) - 0.001).abs() < 1e-15);
    }

    /// Adam reaches the bottom of a bowl whose coordinates' gradients differ by 10⁹ in scale:
    /// each coordinate steps by about `lr`, whatever its gradient's size.
    #[test]
    fn adam_steps_each_coordinate_by_about_lr() {
        let mut adam = Adam::new(2);
        let mut x = vec![0.0, 0.0];
        let target = [1.0, -2.0];
        for _ in 0..2000 {
            let g: Vec<f64> = x
                .iter()
                .zip(target)
                .zip([1e-6, 1e3])
                .map(|((x, t), scale)| scale * (x - t))
                .collect();
            adam.step(&mut x, &g, 0.01);
        }
        assert!(
            (x[0] - 1.0).abs() < 0.02 && (x[1] + 2.0).abs() < 0.02,
            "{x:?}"
        );
    }
}
