//! The autoencoder of the latent paper (§3.2): an MLP-ResNet with BatchNorm and SiLU whose first
//! encoder layer and last decoder layer start from a PCA of the training frames (Fulton et al.
//! 2019). For the cloth: `576 → PCA 50 → 200 → 200 → 200 → 4` and back,
//! `4 → 200 → 200 → 200 → 50 → PCA 576`; a hidden layer of the width of its input is residual,
//! `x + SiLU(BN(W x + b))`.
//!
//! The PCA layers hold the basis scaled by the first mode's standard deviation `σ₁`, so the
//! coefficients the inner layers see are of order one; they stay trainable. Ours: a linear skip
//! passes the first `L` PCA coefficients straight to the latent and back, and the MLPs' last
//! layers start at zero, so the untrained autoencoder is the rank-`L` PCA and training only
//! improves on it (without it, 1500 epochs ended at 3.8 mm unseen RMSE, worse than the 2.5 mm
//! of PCA with 4 modes).

use anyhow::{Result, bail};
use burn::module::{Module, Param};
use burn::nn::{BatchNorm, BatchNormConfig, Linear, LinearConfig};
use burn::tensor::activation::silu;
use burn::tensor::{Device, Tensor, TensorData};
use nalgebra::DMatrix;
use serde::{Deserialize, Serialize};

/// The `[autoencoder]` section.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct AutoencoderConfig {
    /// Latent dimension.
    pub latent: usize,
    /// PCA modes of the outer layers.
    pub pca_modes: usize,
    /// Hidden widths, from the PCA side inwards (the decoder mirrors them).
    pub hidden: Vec<usize>,
    /// Epochs over the training frames (the paper: 20,000).
    pub epochs: usize,
    /// Frames per batch (the paper: 500).
    pub batch: usize,
    /// Adam learning rate (the paper: 1e-4).
    pub lr: f64,
    /// Learning rate of the last epoch: the rate decays geometrically from `lr` to it.
    pub lr_end: f64,
}

impl Default for AutoencoderConfig {
    /// The paper's cloth: latent 4, 50 PCA modes, hidden 200, 200, 200, batch 500; 1500 epochs
    /// at learning rate 1e-3 instead of 20,000 at 1e-4 (two CPU cores).
    fn default() -> Self {
        Self {
            latent: 4,
            pca_modes: 50,
            hidden: vec![200, 200, 200],
            epochs: 1500,
            batch: 500,
            lr: 1e-3,
            lr_end: 1e-5,
        }
    }
}

impl AutoencoderConfig {
    /// The learning rate of `epoch` of `epochs`: geometric from `lr` to `lr_end`.
    pub fn rate(&self, epoch: usize, epochs: usize) -> f64 {
        let f = epoch as f64 / (epochs.max(2) - 1) as f64;
        self.lr * (self.lr_end / self.lr).powf(f)
    }

    /// Checks ranges; errors name the key.
    pub fn validate(&self) -> Result<()> {
        if self.latent == 0 || self.pca_modes == 0 || self.batch == 0 {
            bail!("autoencoder.latent, autoencoder.pca_modes and autoencoder.batch must be ≥ 1");
        }
        if self.latent > self.pca_modes {
            bail!(
                "autoencoder.latent ({}) must not exceed autoencoder.pca_modes ({})",
                self.latent,
                self.pca_modes
            );
        }
        if self.hidden.is_empty() || self.hidden.contains(&0) {
            bail!("autoencoder.hidden must list at least one positive width");
        }
        if !(self.lr > 0.0 && self.lr.is_finite() && self.lr_end > 0.0 && self.lr_end <= self.lr) {
            bail!(
                "autoencoder.lr must be positive and autoencoder.lr_end in (0, lr], are {} and {}",
                self.lr,
                self.lr_end
            );
        }
        Ok(())
    }
}

/// A PCA of row vectors: mean and the leading directions.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Pca {
    /// Mean, `[D]`.
    pub mean: Vec<f64>,
    /// Directions, `[K][D]`, orthonormal, by decreasing variance.
    pub basis: Vec<Vec<f64>>,
    /// Standard deviation of the data along each direction.
    pub std: Vec<f64>,
}

impl Pca {
    /// The leading `k` modes of the rows of `data` (`rows × d`, row-major), by SVD of the
    /// centred data (at most `min(rows, d)` modes).
    pub fn fit(data: &[f64], rows: usize, d: usize, k: usize) -> Result<Self> {
        if rows < 2 || data.len() != rows * d {
            bail!("PCA needs at least two frames");
        }
        let mean: Vec<f64> = (0..d)
            .map(|j| (0..rows).map(|r| data[r * d + j]).sum::<f64>() / rows as f64)
            .collect();
        let centred = DMatrix::from_fn(rows, d, |r, j| data[r * d + j] - mean[j]);
        let svd = centred.svd(false, true);
        let v_t = svd
            .v_t
            .ok_or_else(|| anyhow::anyhow!("the PCA's SVD did not converge"))?;
        let mut order: Vec<usize> = (0..svd.singular_values.len()).collect();
        order.sort_by(|&a, &b| svd.singular_values[b].total_cmp(&svd.singular_values[a]));
        let k = k.min(order.len());
        let basis = order[..k]
            .iter()
            .map(|&m| (0..d).map(|j| v_t[(m, j)]).collect())
            .collect();
        let std = order[..k]
            .iter()
            .map(|&m| svd.singular_values[m] / ((rows - 1) as f64).sqrt())
            .collect();
        Ok(Self { mean, basis, std })
    }
}

/// `SiLU(BN(W x + b))`, plus `x` when residual.
#[derive(Module, Debug)]
pub struct Dense {
    /// The affine map.
    pub linear: Linear,
    /// Its batch normalisation.
    pub norm: BatchNorm,
    /// Whether the input is added back (input and output of the same width).
    #[module(skip)]
    pub residual: bool,
}

impl Dense {
    fn new(d_in: usize, d_out: usize, device: &Device) -> Self {
        Self {
            linear: LinearConfig::new(d_in, d_out).init(device),
            norm: BatchNormConfig::new(d_out).init(device),
            residual: d_in == d_out,
        }
    }

    /// The layer on a batch `[B, d_in]`.
    pub fn forward(&self, x: Tensor<2>) -> Tensor<2> {
        let y = silu(self.norm.forward(self.linear.forward(x.clone())));
        if self.residual { x + y } else { y }
    }
}

/// Positions (relative to the pinned vertices' mean) to latent coordinates.
#[derive(Module, Debug)]
pub struct Encoder {
    /// `D → K`, from the PCA.
    pub pca: Linear,
    /// Hidden layers.
    pub layers: Vec<Dense>,
    /// To the latent coordinates.
    pub out: Linear,
}

/// Latent coordinates to positions.
#[derive(Module, Debug)]
pub struct Decoder {
    /// Hidden layers.
    pub layers: Vec<Dense>,
    /// To the PCA coefficients.
    pub modes: Linear,
    /// `K → D`, from the PCA.
    pub pca: Linear,
}

/// The autoencoder.
#[derive(Module, Debug)]
pub struct Autoencoder {
    /// Encoder.
    pub encoder: Encoder,
    /// Decoder.
    pub decoder: Decoder,
}

impl Encoder {
    /// `[B, D] → [B, L]`: the MLP of the PCA coefficients plus their first `L` (the linear
    /// skip that makes the untrained autoencoder the rank-`L` PCA).
    pub fn forward(&self, x: Tensor<2>) -> Tensor<2> {
        let coefficients = self.pca.forward(x);
        let [b, _] = coefficients.dims();
        let [_, l] = self.out.weight.dims();
        let mut h = coefficients.clone();
        for layer in &self.layers {
            h = layer.forward(h);
        }
        self.out.forward(h) + coefficients.slice([0..b, 0..l])
    }
}

impl Decoder {
    /// `[B, L] → [B, D]`: the MLP's PCA coefficients plus the latent as the first `L` of them.
    pub fn forward(&self, z: Tensor<2>) -> Tensor<2> {
        let [b, l] = z.dims();
        let [_, k] = self.modes.weight.dims();
        let mut h = z.clone();
        for layer in &self.layers {
            h = layer.forward(h);
        }
        let skip = Tensor::cat(vec![z.clone(), Tensor::zeros([b, k - l], &z.device())], 1);
        self.pca.forward(self.modes.forward(h) + skip)
    }
}

impl Autoencoder {
    /// A fresh autoencoder for `d`-dimensional frames (random inner layers, PCA layers zero
    /// until [`Autoencoder::with_pca`]).
    pub fn new(config: &AutoencoderConfig, d: usize, device: &Device) -> Self {
        let k = config.pca_modes.min(d);
        let mut widths = vec![k];
        widths.extend(&config.hidden);
        let zero = |d_in: usize, d_out: usize| {
            LinearConfig::new(d_in, d_out)
                .with_initializer(burn::nn::Initializer::Zeros)
                .init(device)
        };
        let encoder = Encoder {
            pca: LinearConfig::new(d, k).init(device),
            layers: widths
                .windows(2)
                .map(|w| Dense::new(w[0], w[1], device))
                .collect(),
            out: zero(*widths.last().unwrap(), config.latent),
        };
        let mut back: Vec<usize> = config.hidden.iter().rev().copied().collect();
        back.insert(0, config.latent);
        let decoder = Decoder {
            layers: back
                .windows(2)
                .map(|w| Dense::new(w[0], w[1], device))
                .collect(),
            modes: zero(*back.last().unwrap(), k),
            pca: LinearConfig::new(k, d).init(device),
        };
        Self { encoder, decoder }
    }

    /// Sets the PCA layers from `pca` (its modes scaled by the first mode's deviation `σ₁`).
    pub fn with_pca(mut self, pca: &Pca, device: &Device) -> Self {
        let (k, d) = (pca.basis.len(), pca.mean.len());
        let s = pca.std.first().copied().unwrap_or(1.0).max(1e-12);
        let mut enc = vec![0.0f32; d * k];
        let mut dec = vec![0.0f32; k * d];
        for (m, dir) in pca.basis.iter().enumerate() {
            for j in 0..d {
                enc[j * k + m] = (dir[j] / s) as f32;
                dec[m * d + j] = (dir[j] * s) as f32;
            }
        }
        let enc_bias: Vec<f32> = (0..k)
            .map(|m| (-(0..d).map(|j| pca.mean[j] * pca.basis[m][j]).sum::<f64>() / s) as f32)
            .collect();
        let dec_bias: Vec<f32> = pca.mean.iter().map(|&v| v as f32).collect();
        let t2 = |v: Vec<f32>, shape: [usize; 2]| {
            Tensor::<2>::from_data(TensorData::new(v, shape), device)
        };
        let t1 = |v: Vec<f32>| {
            let n = v.len();
            Tensor::<1>::from_data(TensorData::new(v, [n]), device)
        };
        self.encoder.pca.weight = Param::from_tensor(t2(enc, [d, k]));
        self.encoder.pca.bias = Some(Param::from_tensor(t1(enc_bias)));
        self.decoder.pca.weight = Param::from_tensor(t2(dec, [k, d]));
        self.decoder.pca.bias = Some(Param::from_tensor(t1(dec_bias)));
        self
    }

    /// `decode(encode(x))`.
    pub fn forward(&self, x: Tensor<2>) -> Tensor<2> {
        self.decoder.forward(self.encoder.forward(x))
    }
}
