//! The Neural ODE baseline (paper §4.5, Fig. 12, App. B): an MLP maps the whole cloth's state
//! to the internal force on every particle, and the shared integrator
//! ([`crate::sim::step_frame`]) steps it with gravity, Rayleigh damping and pins, exactly like
//! the spring network. It knows nothing of the cloth's topology.
//!
//! Input `6P`: positions relative to the centroid of the pinned particles (of all particles when
//! none is pinned) divided by the sheet size `L`, and velocities divided by `√(gL)`; `H` hidden
//! layers of width `W` with ELU after each; output `3P` forces in units of a particle's weight
//! `m|g|`. The last layer starts near zero, so training starts from a cloth without internal
//! forces rather than from random ones. Parameters:
//! `(6P + 1)W + (H − 1)(W + 1)W + (W + 1)3P` (over 6 M for the paper's 32 × 32, 6 × 512).

use burn::module::Module;
use burn::nn::{Initializer, Linear, LinearConfig};
use burn::tensor::activation::elu;
use burn::tensor::{Device, Tensor};
use serde::{Deserialize, Serialize};

use super::ForceModel;

/// The `[model.neural_ode]` section.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct NeuralOdeConfig {
    /// Hidden layers `H`.
    pub layers: usize,
    /// Width `W` of every hidden layer.
    pub hidden: usize,
}

impl Default for NeuralOdeConfig {
    /// App. B: 6 hidden layers of 512.
    fn default() -> Self {
        Self {
            layers: 6,
            hidden: 512,
        }
    }
}

impl NeuralOdeConfig {
    /// Checks ranges; errors name the key.
    pub fn validate(&self) -> anyhow::Result<()> {
        if self.layers == 0 || self.hidden == 0 {
            anyhow::bail!(
                "`model.neural_ode.layers` and `model.neural_ode.hidden` must be at least 1"
            );
        }
        Ok(())
    }

    /// Learnable parameters for `particles` particles.
    pub(crate) fn parameter_count(&self, particles: usize) -> usize {
        let (w, h, p) = (self.hidden, self.layers, particles);
        (6 * p + 1) * w + (h - 1) * (w + 1) * w + (w + 1) * 3 * p
    }
}

/// Physical scales that make the network's inputs and outputs of order one.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct OdeScales {
    /// Sheet size `L`, m.
    pub length: f64,
    /// Velocity scale `√(g L)`, m/s.
    pub velocity: f64,
    /// Force scale `m |g|`, N.
    pub force: f64,
}

impl OdeScales {
    /// The scales of a `width × height` sheet of particles of `mass` under `gravity`.
    pub fn new(width: f64, height: f64, mass: f64, gravity: [f64; 3]) -> Self {
        let g = gravity.iter().map(|c| c * c).sum::<f64>().sqrt().max(1e-3);
        let length = width.max(height);
        Self {
            length,
            velocity: (g * length).sqrt(),
            force: mass * g,
        }
    }
}

/// The Neural ODE force model.
#[derive(Module, Debug)]
pub struct NeuralOde {
    /// Hidden layers, then the output layer.
    pub layers: Vec<Linear>,
    /// Particles `P`.
    #[module(skip)]
    pub particles: usize,
    /// Input and output scales.
    #[module(skip)]
    pub scales: OdeScales,
}

impl NeuralOde {
    /// A freshly initialised network for `particles` particles.
    pub fn new(
        config: &NeuralOdeConfig,
        particles: usize,
        scales: OdeScales,
        device: &Device,
    ) -> Self {
        let mut layers = Vec::with_capacity(config.layers + 1);
        let mut width = 6 * particles;
        for _ in 0..config.layers {
            layers.push(LinearConfig::new(width, config.hidden).init(device));
            width = config.hidden;
        }
        let bound = 1e-3 / (width as f64).sqrt();
        layers.push(
            LinearConfig::new(width, 3 * particles)
                .with_initializer(Initializer::Uniform {
                    min: -bound,
                    max: bound,
                })
                .init(device),
        );
        Self {
            layers,
            particles,
            scales,
        }
    }
}

impl ForceModel for NeuralOde {
    fn internal_forces(&self, x: Tensor<3>, v: Tensor<3>, pinned: &Tensor<3>) -> Tensor<3> {
        let [b, p, _] = x.dims();
        assert_eq!(
            p, self.particles,
            "the network was built for {} particles",
            self.particles
        );
        // Centroid of the pinned particles (the plain mean when none is pinned).
        let w = pinned.clone().add_scalar(1e-6);
        let centroid = (x.clone() * w.clone()).sum_dim(1) / w.sum_dim(1);
        let rel = (x - centroid).div_scalar(self.scales.length);
        let vel = v.div_scalar(self.scales.velocity);
        let mut h = Tensor::cat(vec![rel.reshape([b, 3 * p]), vel.reshape([b, 3 * p])], 1);
        let last = self.layers.len() - 1;
        for (i, layer) in self.layers.iter().enumerate() {
            h = layer.forward(h);
            if i < last {
                h = elu(h, 1.0);
            }
        }
        h.mul_scalar(self.scales.force).reshape([b, p, 3])
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parameter_count_matches_the_formula_and_the_paper() {
        let device = Device::flex();
        let cfg = NeuralOdeConfig {
            layers: 3,
            hidden: 16,
        };
        let scales = OdeScales::new(1.0, 1.0, 0.01, [0.0, 0.0, -9.81]);
        let net = NeuralOde::new(&cfg, 10, scales, &device);
        assert_eq!(net.num_params(), cfg.parameter_count(10));
        // The paper's network on a 32 × 32 surrogate: "over 6M learnable parameters".
        assert_eq!(NeuralOdeConfig::default().parameter_count(1024), 6_035_456);
    }

    #[test]
    fn forces_have_the_state_shape_and_ignore_a_common_translation() {
        let device = Device::flex();
        let cfg = NeuralOdeConfig {
            layers: 2,
            hidden: 8,
        };
        let scales = OdeScales::new(2.0, 2.0, 0.1, [0.0, 0.0, -9.81]);
        let net = NeuralOde::new(&cfg, 4, scales, &device);
        let x = Tensor::<3>::random(
            [2, 4, 3],
            burn::tensor::Distribution::Uniform(-1.0, 1.0),
            &device,
        );
        let v = Tensor::<3>::zeros([2, 4, 3], &device);
        let pinned = Tensor::<3>::zeros([2, 4, 1], &device);
        let f = net.internal_forces(x.clone(), v.clone(), &pinned);
        assert_eq!(f.dims(), [2, 4, 3]);
        let shifted = net.internal_forces(x.add_scalar(5.0), v, &pinned);
        let diff = (f - shifted).abs().max().into_scalar::<f32>();
        assert!(diff < 1e-5, "{diff}");
    }
}
