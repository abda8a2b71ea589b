//! Per-spring refinement of a searched network by its own motion (ours; `train.refine`).
//!
//! PhysTwin's order: the global parameters by a zero-order search first (the blend or scale
//! search), then per-spring first-order steps of a multi-step *position* loss over short windows
//! of the training takes (multiple shooting: every clip starts from the data's own state). The
//! steps are Burn's Adam on `log k` (and with `train_b` on `log b`), so a spring moves by a share of
//! its own size whatever the material's scale, and no value crosses zero. The substeps rise as
//! the refined network needs (within the searches' cap). The refined network is kept only where
//! its free rollouts of the searches' training takes move closer than the searched one's.

use std::sync::Arc;

use anyhow::{Result, bail};
use serde::{Deserialize, Serialize};

use burn::module::{Module, Param, ParamId};
use burn::optim::{AdamConfig, GradientsParams};
use burn::tensor::{Device, Tensor, TensorData};

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
        super::check_steps("refine", self.batch, self.lr, self.lr_decay)
    }

    /// The step of iteration `i` (from 0).
    fn lr_at(&self, i: usize) -> f64 {
        self.lr * super::decay_factor(i, self.iterations, self.lr_decay, 0.0)
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
    /// Adam's ε (`train.adam_epsilon`).
    pub adam_epsilon: f64,
    pub state_budget_mib: usize,
    pub progress: &'a Progress,
}

/// The refined parameters, which Burn's Adam steps: `θ_k = log(k + c)` per spring (`c` a share
/// of the mean `k`, so that springs at zero start exactly there and can rise:
/// `k = max(e^θ − c, 0)`), and with `train_b` `θ_b = log b`.
#[derive(Module, Debug)]
struct LogSprings {
    k: Param<Tensor<1>>,
    b: Option<Param<Tensor<1>>>,
}

impl LogSprings {
    /// `θ` of the network `k`, `b` on `device`, and the shift `c`.
    fn new(k: &[f64], b: &[f64], train_b: bool, device: &Device) -> Result<(Self, f64)> {
        let mean = k.iter().sum::<f64>() / k.len().max(1) as f64;
        if !(mean > 0.0) {
            bail!("`train.refine` steps log k; every k of the searched network is 0");
        }
        let shift = SHIFT_SHARE * mean;
        let param = |v: Vec<f64>| {
            let n = v.len();
            Param::from_tensor(Tensor::<1>::from_data(TensorData::new(v, [n]), device))
        };
        let theta = Self {
            k: param(k.iter().map(|k| (k.max(0.0) + shift).ln()).collect()),
            b: (train_b && b.iter().all(|&x| x > 0.0))
                .then(|| param(b.iter().map(|b| b.ln()).collect())),
        };
        Ok((theta, shift))
    }

    /// `base` with the springs' `k` (and with `train_b` their `b`) of `θ`, as functions of it.
    fn network(&self, base: &SpringNet, shift: f64) -> SpringNet {
        let mut net = base.clone();
        let k = (self.k.val().exp() - shift).clamp_min(0.0);
        net.k = Param::initialized(ParamId::new(), k);
        if let Some(b) = &self.b {
            net.b = Param::initialized(ParamId::new(), b.val().exp());
        }
        net
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
        let (k0, b0) = (net.k_values(), net.b_values());
        let base = like(net, self.takes.topology, &k0, &b0, self.device);
        let (theta, shift) = LogSprings::new(&k0, &b0, self.config.train_b, self.device)?;
        let theta0 = to_f64(theta.k.val());
        let (theta, losses) = self.steps(&base, theta, shift, physics)?;
        let stepped = theta.network(&base, shift);
        let refined = like(
            net,
            self.takes.topology,
            &stepped.k_values(),
            &stepped.b_values(),
            self.takes.device,
        );
        let before = scale::score_network(net, physics, self.takes)
            .map(|(_, r)| r)
            .ok_or_else(|| anyhow::anyhow!("refine: the searched network does not roll out"))?;
        let scored = scale::score_network(&refined, physics, self.takes);
        let kept = scored.is_some_and(|(_, r)| r < before);
        let change = to_f64(theta.k.val())
            .iter()
            .zip(&theta0)
            .map(|(t, t0)| (t - t0).powi(2))
            .sum::<f64>()
            / theta0.len().max(1) as f64;
        let record = Refinement {
            iterations: losses.len(),
            losses,
            before,
            after: scored.map(|(_, r)| r),
            substeps: scored.map_or(physics.substeps, |(n, _)| n),
            kept,
            log_k_change: change.sqrt(),
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

    /// Adam's steps on `theta` from the network `base`; returns `θ` and each step's position
    /// loss (they stop early where it is not finite; a step whose gradient is not finite is
    /// skipped).
    fn steps(
        &self,
        base: &SpringNet,
        mut theta: LogSprings,
        shift: f64,
        physics: &Physics,
    ) -> Result<(LogSprings, Vec<f64>)> {
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
        let mut optim = AdamConfig::new()
            .with_epsilon(self.adam_epsilon as f32)
            .init();
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
            let model = theta.network(base, shift);
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
            let grads = GradientsParams::from_grads(terms.total.backward(), &theta);
            let finite = [Some(theta.k.id), theta.b.as_ref().map(|b| b.id)]
                .into_iter()
                .flatten()
                .all(|id| {
                    grads
                        .get::<1>(id)
                        .is_none_or(|g| to_f64(g).iter().all(|x| x.is_finite()))
                });
            if finite {
                theta = optim.step(config.lr_at(it), theta, grads);
            }
            bar.set_message(format!("position loss {loss:.3e} m²"));
            bar.inc(1);
        }
        bar.finish();
        Ok((theta, losses))
    }
}

/// A network of `net`'s springs (`topology`'s), kernel and curvature elements with the values
/// `k`, `b`.
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

    /// `θ` maps back to the searched network (springs at zero stay there, `b` kept without
    /// `train_b`), and the gradient with respect to `θ` is autodiff's chain rule through the map:
    /// `∂L/∂θ_k = ∂L/∂k · e^θ` for `L = Σ w_s k_s + Σ v_s b_s`.
    #[test]
    fn the_log_parameters_map_back_to_the_network_and_carry_its_gradient() {
        use crate::cloth::{GridSpec, Topology};
        let device = Device::flex().autodiff();
        let spec = GridSpec {
            nx: 3,
            ny: 3,
            ..GridSpec::default()
        };
        let topology = Topology::grid(&spec, 1.0, 1.0);
        let s = topology.num_springs();
        let k: Vec<f64> = (0..s)
            .map(|i| if i % 4 == 0 { 0.0 } else { 10.0 + i as f64 })
            .collect();
        let b: Vec<f64> = (0..s).map(|i| 0.5 + 0.1 * i as f64).collect();
        let base = SpringNet::new(&topology, &k, &b, &device);
        for train_b in [false, true] {
            let (theta, shift) = LogSprings::new(&k, &b, train_b, &device).unwrap();
            let net = theta.network(&base, shift);
            for (x, y) in net
                .k_values()
                .iter()
                .zip(&k)
                .chain(net.b_values().iter().zip(&b))
            {
                assert!((x - y).abs() <= 1e-5 * y.max(1.0), "{x} against {y}");
            }
            let w: Vec<f64> = (0..s).map(|i| 1.0 + (i % 3) as f64).collect();
            let v: Vec<f64> = (0..s).map(|i| 2.0 - (i % 2) as f64).collect();
            let row = |x: &[f64]| Tensor::<1>::from_data(TensorData::new(x.to_vec(), [s]), &device);
            let loss = (net.k.val() * row(&w)).sum() + (net.b.val() * row(&v)).sum();
            let grads = loss.backward();
            let g_k = to_f64(theta.k.val().grad(&grads).expect("θ_k has a gradient"));
            let theta_k = to_f64(theta.k.val());
            for i in 0..s {
                let expected = w[i] * theta_k[i].exp();
                assert!((g_k[i] - expected).abs() <= 1e-4 * expected, "spring {i}");
            }
            assert_eq!(theta.b.is_some(), train_b);
            if let Some(theta_b) = &theta.b {
                let g_b = to_f64(theta_b.val().grad(&grads).expect("θ_b has a gradient"));
                for i in 0..s {
                    assert!(
                        (g_b[i] - v[i] * b[i]).abs() <= 1e-4 * v[i] * b[i],
                        "spring {i}"
                    );
                }
            }
        }
    }
}
