//! The latent step as an optimisation: the incremental potential (Eq. 4) of a decoded state,
//! minimised over the decoder's manifold, `z_t = argmin_z Φ(D(z))`, one independent problem
//! per step and a whole batch of them solved together by damped Newton on the latents.
//!
//! The learned integrator is trained to output exactly this minimiser, so the solved
//! rollout (`latent eval R --subspace`) is the ceiling of what training the integrator can
//! reach with this autoencoder and loss: what is left is the autoencoder's manifold and
//! implicit Euler's own damping. The same solver gives the integrator solved targets
//! (`integrator.loss = "solved"`, ours): the argmins of the training steps first, then a
//! regression onto them — the paper's loss, minimised in two stages.

use burn::tensor::{Tensor, TensorData};
use serde::{Deserialize, Serialize};

use super::autoencoder::Decoder;
use super::energy::Potential;
use super::train::Reference;
use springtime_core::model::springs::to_f64;

/// One step's host data: the integrator's input, the potential's `x̃` and previous state, the
/// step's centre and
/// pinned targets, its balancing weight, the encoded reference latent and (for
/// `loss = "solved"`) the step's latent minimiser, both standardised.
pub(crate) struct Sample {
    pub input: Vec<f32>,
    pub x_prev: Vec<f32>,
    pub x_tilde: Vec<f32>,
    pub centre: [f32; 3],
    pub targets: Vec<f32>,
    pub weight: f32,
    pub truth: Vec<f32>,
    pub solved: Vec<f32>,
}

impl Sample {
    /// Step `t` of `reference` after the absolute states `x1`, `x2` (frames `t − 1`, `t − 2`,
    /// flattened): `x̃ = 2x₁ − x₂` and the centre and pinned targets of frame `t`, with the
    /// balancing weight `1 / max(|v̄|, floor)`; no input and no latents yet.
    pub fn at(reference: &Reference, t: usize, x1: &[f32], x2: &[f32], floor: f64) -> Self {
        let n = (x1.len() / 3) as f64;
        let mut v = [0.0f64; 3];
        for (i, (a, b)) in x1.iter().zip(x2).enumerate() {
            v[i % 3] += (*a - *b) as f64 / reference.dt / n;
        }
        let speed = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
        Self {
            input: Vec::new(),
            x_prev: x1.to_vec(),
            x_tilde: x1.iter().zip(x2).map(|(a, b)| 2.0 * a - b).collect(),
            centre: reference.centre(t).map(|v| v as f32),
            targets: reference
                .targets(t)
                .iter()
                .flat_map(|q| q.map(|v| v as f32))
                .collect(),
            weight: (1.0 / speed.max(floor)) as f32,
            truth: Vec::new(),
            solved: Vec::new(),
        }
    }
}

/// How the latent minimiser is searched: damped Newton on the standardised latent, the
/// Hessian from forward differences of the autodiff gradient (the latent has a few
/// coordinates), projected to positive definite, and a backtracking line search per step.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SolveConfig {
    /// Newton iterations at most.
    pub iterations: usize,
    /// Stop when every step's Newton update is below this, standardised latent units.
    pub tolerance: f64,
    /// Forward-difference step of the Hessian, standardised latent units.
    pub epsilon: f64,
}

impl Default for SolveConfig {
    fn default() -> Self {
        Self {
            iterations: 20,
            tolerance: 1e-4,
            epsilon: 1e-3,
        }
    }
}

/// What a batch of latent solves found.
#[derive(Debug, Clone, PartialEq)]
pub struct Solved {
    /// The minimisers, standardised, a row per step.
    pub latents: Vec<Vec<f32>>,
    /// The mean potential at them.
    pub mean_potential: f64,
    /// The mean potential where the search started.
    pub mean_potential_at_start: f64,
    /// Steps whose Newton update did not fall below the tolerance within the iterations (or
    /// whose gradient was not finite, or whose line search found no descent).
    pub unconverged: usize,
}

/// The decoder (frozen) and the potential on an autodiff device, owned: what a
/// [`SelfLoss`] borrows.
pub(crate) struct Subspace {
    pub decoder: Decoder,
    pub potential: Potential,
    pub z_mean: Tensor<2>,
    pub z_std: Tensor<2>,
    pub vertices: usize,
    pub pinned: usize,
}

impl Subspace {
    /// The unbalanced loss over it.
    pub fn loss(&self) -> SelfLoss<'_> {
        SelfLoss {
            decoder: &self.decoder,
            potential: &self.potential,
            z_mean: self.z_mean.clone(),
            z_std: self.z_std.clone(),
            balance: false,
            vertices: self.vertices,
            pinned: self.pinned,
        }
    }
}

/// The self-supervised loss (Eq. 4, balanced by Eq. 6 when asked) of a batch's standardised
/// latents, through the frozen decoder.
pub(crate) struct SelfLoss<'a> {
    pub decoder: &'a Decoder,
    pub potential: &'a Potential,
    pub z_mean: Tensor<2>,
    pub z_std: Tensor<2>,
    pub balance: bool,
    pub vertices: usize,
    pub pinned: usize,
}

impl SelfLoss<'_> {
    /// Per step, `[B]`.
    pub fn potential(&self, batch: &[&Sample], z_hat: Tensor<2>) -> Tensor<1> {
        let device = z_hat.device();
        let (b, n) = (batch.len(), self.vertices);
        let z = z_hat * self.z_std.clone() + self.z_mean.clone();
        let centre: Vec<f32> = batch.iter().flat_map(|s| s.centre).collect();
        let centre = Tensor::<3>::from_data(TensorData::new(centre, [b, 1, 3]), &device);
        let x = self.decoder.forward(z).reshape([b, n, 3]) + centre;
        let cat = |f: &dyn Fn(&Sample) -> &[f32], k: usize| {
            let v: Vec<f32> = batch.iter().flat_map(|s| f(s).iter().copied()).collect();
            Tensor::<3>::from_data(TensorData::new(v, [b, k, 3]), &device)
        };
        let x_prev = self.potential.is_damped().then(|| cat(&|s| &s.x_prev, n));
        let x_tilde = cat(&|s| &s.x_tilde, n);
        let targets = cat(&|s| &s.targets, self.pinned);
        let phi = self.potential.incremental(x, x_prev, x_tilde, targets);
        if self.balance {
            let w: Vec<f32> = batch.iter().map(|s| s.weight).collect();
            phi * Tensor::<1>::from_data(TensorData::new(w, [b]), &device)
        } else {
            phi
        }
    }

    /// The potential of every step at the standardised latents `z` (row per step).
    fn values(&self, batch: &[&Sample], z: &[Vec<f32>]) -> Vec<f64> {
        let device = self.z_mean.device().inner();
        let t = Tensor::<2>::from_data(TensorData::new(z.concat(), [z.len(), z[0].len()]), &device);
        let phi = self.potential(batch, Tensor::from_inner(t));
        to_f64(phi.inner())
    }

    /// The minimisers of every step's potential, standardised, from the standardised `start`
    /// (row per step). The problems are independent, so one batch holds them all (and each
    /// one's `L` difference points). Eigenvalues of the Hessian enter by their magnitude
    /// (floored at 1e-6 of the largest), so negative curvature is stepped away from, not
    /// towards.
    pub fn solve(&self, batch: &[&Sample], start: &[Vec<f32>], config: &SolveConfig) -> Solved {
        let device = self.z_mean.device();
        let (b, l) = (batch.len(), start.first().map_or(0, |z| z.len()));
        let mut z: Vec<Vec<f32>> = start.to_vec();
        let eps = config.epsilon as f32;
        let mut value = self.values(batch, &z);
        let at_start = value.iter().sum::<f64>() / b.max(1) as f64;
        let mut active = vec![true; b];
        let mut converged = vec![false; b];
        for _ in 0..config.iterations {
            // Only the steps still searching are evaluated.
            let live: Vec<usize> = (0..b).filter(|&i| active[i]).collect();
            if live.is_empty() {
                break;
            }
            // Each step with its `L` forward-difference points.
            let spread: Vec<&Sample> = live
                .iter()
                .flat_map(|&i| std::iter::repeat_n(batch[i], l + 1))
                .collect();
            let points: Vec<f32> = live
                .iter()
                .flat_map(|&i| {
                    let zi = &z[i];
                    (0..=l).flat_map(move |k| {
                        zi.iter()
                            .enumerate()
                            .map(move |(j, v)| if k > 0 && j == k - 1 { v + eps } else { *v })
                    })
                })
                .collect();
            let rows = live.len() * (l + 1);
            let zt =
                Tensor::<2>::from_data(TensorData::new(points, [rows, l]), &device).require_grad();
            let phi = self.potential(&spread, zt.clone()).sum();
            let g = to_f64(
                zt.grad(&phi.backward())
                    .expect("the latents require a gradient"),
            );
            let mut step = vec![vec![0.0f32; l]; b];
            let mut slope = vec![0.0f64; b];
            for (p, &i) in live.iter().enumerate() {
                let row = |k: usize| &g[(p * (l + 1) + k) * l..(p * (l + 1) + k + 1) * l];
                let g0 = nalgebra::DVector::from_row_slice(row(0));
                let mut h = nalgebra::DMatrix::from_fn(l, l, |r, c| {
                    (row(c + 1)[r] - g0[r]) / config.epsilon
                });
                h = (&h + h.transpose()) * 0.5;
                let finite = g0.iter().chain(h.iter()).all(|v| v.is_finite());
                let Some(eig) = finite
                    .then(|| nalgebra::SymmetricEigen::try_new(h, 1e-12, 200))
                    .flatten()
                else {
                    active[i] = false;
                    continue;
                };
                let top = eig.eigenvalues.amax().max(1e-12);
                let inv = eig.eigenvalues.map(|v| 1.0 / v.abs().max(1e-6 * top));
                let d = -(&eig.eigenvectors
                    * nalgebra::DMatrix::from_diagonal(&inv)
                    * eig.eigenvectors.transpose()
                    * &g0);
                slope[i] = g0.dot(&d);
                step[i] = d.iter().map(|&v| v as f32).collect();
                if d.amax() < config.tolerance {
                    active[i] = false;
                    converged[i] = true;
                }
            }
            // Backtracking per step: halve until the Armijo condition holds (or give up).
            let mut alpha = vec![1.0f32; b];
            let mut pending: Vec<bool> = (0..b).map(|i| slope[i] < 0.0).collect();
            for _ in 0..12 {
                let trying: Vec<usize> = (0..b).filter(|&i| pending[i]).collect();
                if trying.is_empty() {
                    break;
                }
                let trial: Vec<Vec<f32>> = trying
                    .iter()
                    .map(|&i| {
                        z[i].iter()
                            .zip(&step[i])
                            .map(|(a, d)| a + alpha[i] * d)
                            .collect()
                    })
                    .collect();
                let steps: Vec<&Sample> = trying.iter().map(|&i| batch[i]).collect();
                let at = self.values(&steps, &trial);
                for ((&i, at), trial) in trying.iter().zip(at).zip(trial) {
                    if at <= value[i] + 1e-4 * alpha[i] as f64 * slope[i] {
                        z[i] = trial;
                        value[i] = at;
                        pending[i] = false;
                    } else {
                        alpha[i] *= 0.5;
                    }
                }
            }
            for i in 0..b {
                // No descent along the Newton direction: converged when the decrease it
                // predicts is below the potential's f32 resolution, stuck otherwise.
                if pending[i] {
                    active[i] = false;
                    converged[i] = -slope[i] <= 1e-6 * value[i].abs().max(1.0);
                }
            }
        }
        Solved {
            mean_potential: value.iter().sum::<f64>() / b.max(1) as f64,
            mean_potential_at_start: at_start,
            unconverged: converged.iter().filter(|&&c| !c).count(),
            latents: z,
        }
    }
}
