//! The trained networks as plain Rust: every layer an affine map (BatchNorm in its inference
//! form folded into the preceding weights) with an optional SiLU and residual. One frame of the
//! latent model is a few small matrix–vector products, far below Burn's per-operation overhead
//! at batch size one; `tests/latent.rs` checks that it equals the Burn networks.

use burn::nn::{BatchNorm, Linear};
use burn::tensor::Tensor;

use super::autoencoder::{Autoencoder, Dense};
use super::integrator::Integrator;

/// `y = act(W x + b)` (+ `x`).
#[derive(Debug, Clone)]
struct Layer {
    d_in: usize,
    d_out: usize,
    /// `[d_in][d_out]`, row-major (Burn's layout).
    weight: Vec<f32>,
    bias: Vec<f32>,
    silu: bool,
    residual: bool,
}

fn values<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    t.into_data()
        .try_into_vec_as::<f32>()
        .expect("float tensor")
}

impl Layer {
    fn affine(linear: &Linear) -> Self {
        let [d_in, d_out] = linear.weight.val().dims();
        Self {
            d_in,
            d_out,
            weight: values(linear.weight.val()),
            bias: linear
                .bias
                .as_ref()
                .map_or(vec![0.0; d_out], |b| values(b.val())),
            silu: false,
            residual: false,
        }
    }

    /// `Linear → BatchNorm (inference) → SiLU`, folded.
    fn dense(d: &Dense) -> Self {
        let mut layer = Self::affine(&d.linear);
        fold(&mut layer, &d.norm);
        layer.silu = true;
        layer.residual = d.residual;
        layer
    }

    fn apply(&self, x: &[f32], out: &mut Vec<f32>) {
        out.clear();
        out.extend_from_slice(&self.bias);
        for (i, &xi) in x.iter().enumerate().take(self.d_in) {
            let row = &self.weight[i * self.d_out..(i + 1) * self.d_out];
            for (o, w) in out.iter_mut().zip(row) {
                *o += xi * w;
            }
        }
        if self.silu {
            for o in out.iter_mut() {
                *o /= 1.0 + (-*o).exp();
            }
        }
        if self.residual {
            for (o, xi) in out.iter_mut().zip(x) {
                *o += xi;
            }
        }
    }
}

/// Folds `γ (y − μ)/√(σ² + ε) + β` into the affine layer before it.
fn fold(layer: &mut Layer, norm: &BatchNorm) {
    let gamma = values(norm.gamma.val());
    let beta = values(norm.beta.val());
    let mean = values(norm.running_mean.value());
    let var = values(norm.running_var.value());
    for j in 0..layer.d_out {
        let s = gamma[j] / (var[j] + norm.epsilon as f32).sqrt();
        for i in 0..layer.d_in {
            layer.weight[i * layer.d_out + j] *= s;
        }
        layer.bias[j] = (layer.bias[j] - mean[j]) * s + beta[j];
    }
}

/// A chain of layers.
#[derive(Debug, Clone)]
pub struct Net {
    layers: Vec<Layer>,
}

impl Net {
    /// Applies the net to `x`, using `scratch` (two buffers) to avoid allocation; the result is
    /// in `scratch.0`.
    pub fn apply<'a>(&self, x: &[f32], scratch: &'a mut (Vec<f32>, Vec<f32>)) -> &'a [f32] {
        let (a, b) = scratch;
        a.clear();
        a.extend_from_slice(x);
        for layer in &self.layers {
            layer.apply(a, b);
            std::mem::swap(a, b);
        }
        a
    }

    /// Applies the net to `x`.
    pub fn eval(&self, x: &[f32]) -> Vec<f32> {
        let mut scratch = (Vec::new(), Vec::new());
        self.apply(x, &mut scratch).to_vec()
    }
}

/// The encoder: PCA layer, then the MLP plus the first `L` coefficients.
#[derive(Debug, Clone)]
pub struct PlainEncoder {
    pca: Layer,
    mlp: Net,
}

impl PlainEncoder {
    /// Relative positions → latent.
    pub fn eval(&self, x: &[f32]) -> Vec<f32> {
        let mut coefficients = Vec::new();
        self.pca.apply(x, &mut coefficients);
        let mut z = self.mlp.eval(&coefficients);
        for (v, c) in z.iter_mut().zip(&coefficients) {
            *v += c;
        }
        z
    }
}

/// The decoder: the MLP plus the latent as the first `L` coefficients, then the PCA layer.
#[derive(Debug, Clone)]
pub struct PlainDecoder {
    mlp: Net,
    pca: Layer,
}

impl PlainDecoder {
    /// Latent → relative positions, in `scratch.0`.
    pub fn apply<'a>(&self, z: &[f32], scratch: &'a mut (Vec<f32>, Vec<f32>)) -> &'a [f32] {
        self.mlp.apply(z, scratch);
        for (c, v) in scratch.0.iter_mut().zip(z) {
            *c += v;
        }
        let (a, b) = scratch;
        self.pca.apply(a, b);
        std::mem::swap(a, b);
        a
    }

    /// Latent → relative positions.
    pub fn eval(&self, z: &[f32]) -> Vec<f32> {
        let mut scratch = (Vec::new(), Vec::new());
        self.apply(z, &mut scratch).to_vec()
    }
}

/// The latent model in plain Rust.
#[derive(Debug, Clone)]
pub struct PlainModel {
    /// Positions → latents.
    pub encoder: PlainEncoder,
    /// Latents → positions.
    pub decoder: PlainDecoder,
    /// The latent step (standardised latents).
    pub integrator: Net,
    /// Whether the integrator adds `2ẑ_{t−1} − ẑ_{t−2}`.
    pub residual: bool,
}

impl PlainModel {
    /// Copies the weights of trained Burn networks.
    pub fn new(ae: &Autoencoder, integrator: &Integrator) -> Self {
        let mut encoder: Vec<Layer> = ae.encoder.layers.iter().map(Layer::dense).collect();
        encoder.push(Layer::affine(&ae.encoder.out));
        let mut decoder: Vec<Layer> = ae.decoder.layers.iter().map(Layer::dense).collect();
        decoder.push(Layer::affine(&ae.decoder.modes));
        let mut steps: Vec<Layer> = integrator
            .layers
            .iter()
            .map(|l| Layer {
                silu: true,
                ..Layer::affine(l)
            })
            .collect();
        steps.push(Layer::affine(&integrator.out));
        Self {
            encoder: PlainEncoder {
                pca: Layer::affine(&ae.encoder.pca),
                mlp: Net { layers: encoder },
            },
            decoder: PlainDecoder {
                mlp: Net { layers: decoder },
                pca: Layer::affine(&ae.decoder.pca),
            },
            integrator: Net { layers: steps },
            residual: integrator.residual,
        }
    }

    /// The next standardised latent from `input = [ẑ_{t−1}, ẑ_{t−2}, p]`.
    pub fn step(
        &self,
        input: &[f32],
        latent: usize,
        scratch: &mut (Vec<f32>, Vec<f32>),
    ) -> Vec<f32> {
        let mut z = self.integrator.apply(input, scratch).to_vec();
        if self.residual {
            for (k, v) in z.iter_mut().enumerate() {
                *v += 2.0 * input[k] - input[latent + k];
            }
        }
        z
    }
}
