//! The GNN baseline (paper §4.5, App. B): "Learning to simulate" (Sanchez-Gonzalez et al.
//! 2020) — an encode–process–decode graph network over the particles that predicts each
//! particle's acceleration from its recent velocities, trained one step at a time on noisy
//! inputs and rolled out autoregressively. Like the paper's baseline it knows no cloth
//! topology: the graph joins every pair of particles closer than a connectivity radius, rebuilt
//! at every step from the current positions.
//!
//! Time runs in frames of `downsample` data frames (App. B: 10 × 1 ms). With positions
//! `x_{t−C} … x_t`:
//! - node features: the `C` velocities `x_{k+1} − x_k` (normalised), the pinned flag, and the
//!   distance to the nearest pinned particle over the radius (clipped to 1);
//! - edge features (sender `s`, receiver `r`): `(x_s − x_r)/R` and its norm;
//! - encoder: an MLP per node and per edge to a latent of size `L`; processor: `M` rounds of
//!   `e ← e + MLP_e([e, h_s, h_r])`, `h ← h + MLP_h([h, Σ_{e→r} e])`; decoder: an MLP to the
//!   normalised acceleration. MLPs have `n` hidden layers of width `L` with ReLU; all but the
//!   decoder end in a layer norm.
//! - step: `x_{t+1} = 2x_t − x_{t−1} + a_t`; pinned particles follow their observed path.
//! - training: the input velocities get random-walk noise (std `σ` at the last frame),
//!   integrated into the positions `x̃`; the target is `a = (x_{t+1} + ñ_t) − 2x̃_t + x̃_{t−1}`
//!   with `ñ_t` the last frame's position noise, so that the network learns to undo the velocity
//!   noise; the loss is the mean squared error of the normalised acceleration over free
//!   particles.

use std::collections::HashMap;

use burn::module::Module;
use burn::nn::{LayerNorm, LayerNormConfig, Linear, LinearConfig};
use burn::tensor::activation::relu;
use burn::tensor::{Device, Tensor, TensorData};
use rand::Rng;
use rand_distr::StandardNormal;
use serde::{Deserialize, Serialize};

use super::kernels::segment::DeviceSegments;

/// The `[model.gnn]` section.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct GnnConfig {
    /// Latent size `L` of nodes, edges and MLP hidden layers.
    pub latent: usize,
    /// Hidden layers `n` of every MLP.
    pub mlp_layers: usize,
    /// Message-passing rounds `M`.
    pub message_passing: usize,
    /// Velocities in the node features `C`.
    pub history: usize,
    /// Connectivity radius in rest spacings of the particle grid.
    pub radius: f64,
    /// Data frames per GNN step.
    pub downsample: usize,
    /// Standard deviation of the input noise at the last input frame, as a fraction of the
    /// data's per-frame velocity standard deviation.
    pub noise: f64,
}

impl Default for GnnConfig {
    /// "Learning to simulate": latent 128, 2-layer MLPs, 10 rounds, 5 velocities; a radius of
    /// 1.5 rest spacings (the structural and shear neighbours at rest), 10 × downsampling
    /// (App. B), input noise of a tenth of the typical per-frame displacement.
    fn default() -> Self {
        Self {
            latent: 128,
            mlp_layers: 2,
            message_passing: 10,
            history: 5,
            radius: 1.5,
            downsample: 10,
            noise: 0.1,
        }
    }
}

impl GnnConfig {
    /// Checks ranges; errors name the key.
    pub fn validate(&self) -> anyhow::Result<()> {
        for (key, v) in [
            ("latent", self.latent),
            ("mlp_layers", self.mlp_layers),
            ("history", self.history),
            ("downsample", self.downsample),
        ] {
            if v == 0 {
                anyhow::bail!("`model.gnn.{key}` must be at least 1");
            }
        }
        if !(self.radius > 0.0 && self.radius.is_finite()) {
            anyhow::bail!("`model.gnn.radius` must be positive, is {}", self.radius);
        }
        if !(self.noise >= 0.0 && self.noise.is_finite()) {
            anyhow::bail!("`model.gnn.noise` must be non-negative, is {}", self.noise);
        }
        Ok(())
    }

    /// Node features: `3C` velocities, the pinned flag and the distance to the pins.
    pub(crate) fn node_features(&self) -> usize {
        3 * self.history + 2
    }

    /// Learnable parameters of the network.
    pub(crate) fn parameter_count(&self) -> usize {
        let l = self.latent;
        let mlp = |input: usize, out: usize, norm: bool| {
            (input + 1) * l
                + (self.mlp_layers - 1) * (l + 1) * l
                + (l + 1) * out
                + if norm { 2 * out } else { 0 }
        };
        mlp(self.node_features(), l, true)
            + mlp(4, l, true)
            + self.message_passing * (mlp(3 * l, l, true) + mlp(2 * l, l, true))
            + mlp(l, 3, false)
    }

    /// Data frames a training window spans: `C + 2` GNN frames.
    pub(crate) fn window_frames(&self) -> usize {
        (self.history + 1) * self.downsample + 1
    }
}

/// Normalisation of velocities and accelerations (per axis), in metres per GNN frame.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct GnnStats {
    /// Mean velocity.
    pub vel_mean: [f64; 3],
    /// Standard deviation of the velocity.
    pub vel_std: [f64; 3],
    /// Mean acceleration.
    pub acc_mean: [f64; 3],
    /// Standard deviation of the acceleration.
    pub acc_std: [f64; 3],
    /// Connectivity radius, m.
    pub radius: f64,
    /// Noise at the last input frame, m.
    pub noise: f64,
}

/// An MLP: `n` hidden layers of width `L` with ReLU, an output layer, an optional layer norm.
#[derive(Module, Debug)]
pub struct Mlp {
    /// Hidden layers and the output layer.
    pub layers: Vec<Linear>,
    /// Output normalisation.
    pub norm: Option<LayerNorm>,
}

impl Mlp {
    fn new(input: usize, hidden: usize, layers: usize, out: usize, norm: bool, d: &Device) -> Self {
        let mut v = Vec::with_capacity(layers + 1);
        let mut width = input;
        for _ in 0..layers {
            v.push(LinearConfig::new(width, hidden).init(d));
            width = hidden;
        }
        v.push(LinearConfig::new(width, out).init(d));
        Self {
            layers: v,
            norm: norm.then(|| LayerNormConfig::new(out).init(d)),
        }
    }

    /// `[N, in] → [N, out]`.
    pub fn forward(&self, mut h: Tensor<2>) -> Tensor<2> {
        let last = self.layers.len() - 1;
        for (i, layer) in self.layers.iter().enumerate() {
            h = layer.forward(h);
            if i < last {
                h = relu(h);
            }
        }
        match &self.norm {
            Some(n) => n.forward(h),
            None => h,
        }
    }
}

/// One message-passing round.
#[derive(Module, Debug)]
pub struct Block {
    /// Edge update.
    pub edge: Mlp,
    /// Node update.
    pub node: Mlp,
}

/// The graph network.
#[derive(Module, Debug)]
pub struct Gnn {
    /// Node encoder.
    pub node_encoder: Mlp,
    /// Edge encoder.
    pub edge_encoder: Mlp,
    /// Processor.
    pub blocks: Vec<Block>,
    /// Decoder to the normalised acceleration.
    pub decoder: Mlp,
    /// Velocities in the features.
    #[module(skip)]
    pub history: usize,
    /// Normalisation and radius.
    #[module(skip)]
    pub stats: GnnStats,
}

/// A batch of graphs on the host: nodes of every graph one after the other.
#[derive(Debug, Clone, Default)]
pub struct Graph {
    /// Node features `[N, F]`, row-major.
    pub nodes: Vec<f32>,
    /// Edge features `[E, 4]`.
    pub edges: Vec<f32>,
    /// Sender of every edge.
    pub senders: Vec<i64>,
    /// Receiver of every edge.
    pub receivers: Vec<i64>,
    /// Nodes `N`.
    pub num_nodes: usize,
}

impl Gnn {
    /// A freshly initialised network.
    pub fn new(config: &GnnConfig, stats: GnnStats, device: &Device) -> Self {
        let (l, n) = (config.latent, config.mlp_layers);
        Self {
            node_encoder: Mlp::new(config.node_features(), l, n, l, true, device),
            edge_encoder: Mlp::new(4, l, n, l, true, device),
            blocks: (0..config.message_passing)
                .map(|_| Block {
                    edge: Mlp::new(3 * l, l, n, l, true, device),
                    node: Mlp::new(2 * l, l, n, l, true, device),
                })
                .collect(),
            decoder: Mlp::new(l, l, n, 3, false, device),
            history: config.history,
            stats,
        }
    }

    /// Normalised accelerations `[N, 3]` of a batch of graphs.
    pub fn forward(&self, graph: &Graph, device: &Device) -> Tensor<2> {
        let n = graph.num_nodes;
        let e = graph.senders.len();
        let f = graph.nodes.len() / n.max(1);
        let nodes = Tensor::<2>::from_data(TensorData::new(graph.nodes.clone(), [n, f]), device);
        let mut h = self.node_encoder.forward(nodes);
        if e == 0 {
            return self.decoder.forward(h);
        }
        let edges = Tensor::<2>::from_data(TensorData::new(graph.edges.clone(), [e, 4]), device);
        // Gathers and sums by segment in both directions (no scatter; see `segment`).
        let senders = DeviceSegments::new(&graph.senders, n, device);
        let receivers = DeviceSegments::new(&graph.receivers, n, device);
        let mut m = self.edge_encoder.forward(edges);
        for block in &self.blocks {
            let input = Tensor::cat(
                vec![
                    m.clone(),
                    senders.gather(h.clone()),
                    receivers.gather(h.clone()),
                ],
                1,
            );
            m = m + block.edge.forward(input);
            let agg = receivers.sum(m.clone());
            h = h.clone() + block.node.forward(Tensor::cat(vec![h, agg], 1));
        }
        self.decoder.forward(h)
    }

    /// The graph of one cloth from its last `C + 1` positions (`frames[k]` is `[P]` of xyz,
    /// oldest first), appended to `graph`.
    pub(crate) fn append_graph(&self, graph: &mut Graph, frames: &[&[[f32; 3]]], pinned: &[bool]) {
        let s = &self.stats;
        let p = pinned.len();
        let now = frames[frames.len() - 1];
        let base = graph.num_nodes as i64;
        let pins: Vec<[f32; 3]> = (0..p).filter(|&i| pinned[i]).map(|i| now[i]).collect();
        let r = s.radius as f32;
        for i in 0..p {
            for k in 0..self.history {
                let (a, b) = (frames[k][i], frames[k + 1][i]);
                for c in 0..3 {
                    let vel = (b[c] - a[c]) as f64;
                    graph
                        .nodes
                        .push(((vel - s.vel_mean[c]) / s.vel_std[c]) as f32);
                }
            }
            graph.nodes.push(if pinned[i] { 1.0 } else { 0.0 });
            let d = pins
                .iter()
                .map(|q| dist(now[i], *q))
                .fold(f32::INFINITY, f32::min);
            graph.nodes.push((d / r).min(1.0));
        }
        for (a, b) in radius_pairs(now, r) {
            for (snd, rcv) in [(a, b), (b, a)] {
                let d = [0, 1, 2].map(|c| (now[snd][c] - now[rcv][c]) / r);
                graph.edges.extend_from_slice(&d);
                graph
                    .edges
                    .push((d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt());
                graph.senders.push(base + snd as i64);
                graph.receivers.push(base + rcv as i64);
            }
        }
        graph.num_nodes += p;
    }

    /// Accelerations in metres per frame² from normalised predictions.
    pub(crate) fn denormalize(&self, pred: &[f32]) -> Vec<[f64; 3]> {
        let s = &self.stats;
        pred.chunks_exact(3)
            .map(|a| [0, 1, 2].map(|c| a[c] as f64 * s.acc_std[c] + s.acc_mean[c]))
            .collect()
    }

    /// One autoregressive step of a batch of cloths: from each cloth's last `C + 1` positions
    /// (oldest first), the next positions; pinned particles take `pin_next`.
    pub fn step(
        &self,
        histories: &[Vec<Vec<[f32; 3]>>],
        pinned: &[Vec<bool>],
        pin_next: &[&[[f32; 3]]],
        device: &Device,
    ) -> Vec<Vec<[f32; 3]>> {
        let mut graph = Graph::default();
        for (hist, pins) in histories.iter().zip(pinned) {
            let frames: Vec<&[[f32; 3]]> = hist.iter().map(|f| f.as_slice()).collect();
            self.append_graph(&mut graph, &frames, pins);
        }
        let pred: Vec<f32> = self
            .forward(&graph, device)
            .into_data()
            .try_into_vec_as::<f32>()
            .expect("float tensor");
        let acc = self.denormalize(&pred);
        let mut out = Vec::with_capacity(histories.len());
        let mut at = 0;
        for ((hist, pins), next) in histories.iter().zip(pinned).zip(pin_next) {
            let (prev, now) = (&hist[hist.len() - 2], &hist[hist.len() - 1]);
            let x: Vec<[f32; 3]> = (0..pins.len())
                .map(|i| {
                    if pins[i] {
                        next[i]
                    } else {
                        let a = acc[at + i];
                        [0, 1, 2]
                            .map(|c| (2.0 * now[i][c] as f64 - prev[i][c] as f64 + a[c]) as f32)
                    }
                })
                .collect();
            at += pins.len();
            out.push(x);
        }
        out
    }
}

fn dist(a: [f32; 3], b: [f32; 3]) -> f32 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
}

/// Every unordered pair of points closer than `r`, by a uniform grid of cell size `r`.
pub(crate) fn radius_pairs(points: &[[f32; 3]], r: f32) -> Vec<(usize, usize)> {
    let cell = |p: [f32; 3]| p.map(|c| (c / r).floor() as i64);
    let mut grid: HashMap<[i64; 3], Vec<usize>> = HashMap::new();
    for (i, &p) in points.iter().enumerate() {
        if p.iter().all(|c| c.is_finite()) {
            grid.entry(cell(p)).or_default().push(i);
        }
    }
    let mut pairs = Vec::new();
    for (i, &p) in points.iter().enumerate() {
        if !p.iter().all(|c| c.is_finite()) {
            continue;
        }
        let c = cell(p);
        for dx in -1..=1 {
            for dy in -1..=1 {
                for dz in -1..=1 {
                    if let Some(list) = grid.get(&[c[0] + dx, c[1] + dy, c[2] + dz]) {
                        for &j in list {
                            if j > i && dist(p, points[j]) < r {
                                pairs.push((i, j));
                            }
                        }
                    }
                }
            }
        }
    }
    pairs.sort_unstable();
    pairs
}

/// One training example: a window of `C + 2` GNN frames of one clip, `[frame][particle]`.
pub struct Window<'a> {
    /// Positions per frame, oldest first.
    pub frames: Vec<&'a [[f32; 3]]>,
    /// Pinned particles.
    pub pinned: &'a [bool],
}

impl Gnn {
    /// The training graph and the normalised target accelerations `[N, 3]` (0 for pinned
    /// particles) and free-particle mask `[N]` of a set of windows, with random-walk noise.
    pub(crate) fn training_batch(
        &self,
        windows: &[Window],
        rng: &mut impl Rng,
    ) -> (Graph, Vec<f32>, Vec<f32>) {
        let c = self.history;
        let s = self.stats;
        let mut graph = Graph::default();
        let (mut target, mut mask) = (Vec::new(), Vec::new());
        for w in windows {
            let p = w.pinned.len();
            // Noisy inputs x̃_{t−C..t}: the velocity noise is a random walk with std σ/√C per
            // step, accumulated into the positions; the first frame and the pins stay exact.
            let step_std = s.noise / (c as f64).sqrt();
            let mut noisy: Vec<Vec<[f32; 3]>> = vec![w.frames[0].to_vec()];
            let mut walk = vec![[0.0f64; 3]; p];
            let mut offset = vec![[0.0f64; 3]; p];
            for k in 1..=c {
                let frame: Vec<[f32; 3]> = (0..p)
                    .map(|i| {
                        if !w.pinned[i] && step_std > 0.0 {
                            for d in 0..3 {
                                walk[i][d] += step_std * rng.sample::<f64, _>(StandardNormal);
                                offset[i][d] += walk[i][d];
                            }
                        }
                        [0, 1, 2].map(|d| (w.frames[k][i][d] as f64 + offset[i][d]) as f32)
                    })
                    .collect();
                noisy.push(frame);
            }
            let refs: Vec<&[[f32; 3]]> = noisy.iter().map(|f| f.as_slice()).collect();
            self.append_graph(&mut graph, &refs, w.pinned);
            // The target next position moves with the last frame's noise offset, so the
            // network learns to undo the velocity noise, not to jump back to the data.
            let (prev, now, next) = (&noisy[c - 1], &noisy[c], w.frames[c + 1]);
            for i in 0..p {
                for d in 0..3 {
                    let next = next[i][d] as f64 + offset[i][d];
                    let a = next - 2.0 * now[i][d] as f64 + prev[i][d] as f64;
                    target.push(((a - s.acc_mean[d]) / s.acc_std[d]) as f32);
                }
                mask.push(if w.pinned[i] { 0.0 } else { 1.0 });
            }
        }
        (graph, target, mask)
    }

    /// The one-step loss: mean squared normalised acceleration error over free particles.
    pub fn loss(&self, windows: &[Window], rng: &mut impl Rng, device: &Device) -> Tensor<1> {
        let (graph, target, mask) = self.training_batch(windows, rng);
        let n = graph.num_nodes;
        let pred = self.forward(&graph, device);
        let target = Tensor::<2>::from_data(TensorData::new(target, [n, 3]), device);
        // Counted on the host: no wait for the device.
        let free = mask.iter().sum::<f32>().max(1.0) as f64;
        let mask = Tensor::<2>::from_data(TensorData::new(mask, [n, 1]), device);
        let d = (pred - target) * mask;
        (d.clone() * d).sum().div_scalar(3.0 * free)
    }
}

/// Normalisation statistics from example windows (velocities and accelerations of free
/// particles in GNN frames), with the radius and noise in metres for a rest `spacing`.
pub fn statistics(windows: &[Window], config: &GnnConfig, spacing: f64) -> GnnStats {
    let mut vel: Vec<[f64; 3]> = Vec::new();
    let mut acc: Vec<[f64; 3]> = Vec::new();
    for w in windows {
        let f = &w.frames;
        for i in 0..w.pinned.len() {
            if w.pinned[i] {
                continue;
            }
            for k in 0..f.len() - 1 {
                vel.push([0, 1, 2].map(|c| (f[k + 1][i][c] - f[k][i][c]) as f64));
            }
            for k in 1..f.len() - 1 {
                acc.push([0, 1, 2].map(|c| {
                    f[k + 1][i][c] as f64 - 2.0 * f[k][i][c] as f64 + f[k - 1][i][c] as f64
                }));
            }
        }
    }
    let moments = |v: &[[f64; 3]], floor: f64| {
        let n = v.len().max(1) as f64;
        let mean = [0, 1, 2].map(|c| v.iter().map(|x| x[c]).sum::<f64>() / n);
        let std = [0, 1, 2].map(|c| {
            let var = v.iter().map(|x| (x[c] - mean[c]).powi(2)).sum::<f64>() / n;
            var.sqrt().max(floor)
        });
        (mean, std)
    };
    let (vel_mean, vel_std) = moments(&vel, 1e-9 * spacing);
    let noise = config.noise * (vel_std.iter().map(|s| s * s).sum::<f64>() / 3.0).sqrt();
    // As "Learning to simulate": the target's spread includes the input noise it must undo.
    let (acc_mean, acc_raw) = moments(&acc, 1e-9 * spacing);
    let acc_std = acc_raw.map(|s| (s * s + noise * noise).sqrt());
    GnnStats {
        vel_mean,
        vel_std,
        acc_mean,
        acc_std,
        radius: config.radius * spacing,
        noise,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn stats() -> GnnStats {
        GnnStats {
            vel_mean: [0.0; 3],
            vel_std: [0.01; 3],
            acc_mean: [0.0; 3],
            acc_std: [0.001; 3],
            radius: 1.6,
            noise: 0.0,
        }
    }

    fn sheet(n: usize, shift: [f32; 3]) -> Vec<[f32; 3]> {
        (0..n * n)
            .map(|i| {
                let (r, c) = (i / n, i % n);
                [
                    c as f32 + shift[0] + 0.1 * (i as f32).sin(),
                    r as f32 + shift[1],
                    shift[2] + 0.2 * (i as f32 * 0.7).cos(),
                ]
            })
            .collect()
    }

    #[test]
    fn parameter_count_matches_the_formula_and_the_paper() {
        let cfg = GnnConfig {
            latent: 16,
            mlp_layers: 2,
            message_passing: 3,
            history: 2,
            ..GnnConfig::default()
        };
        let net = Gnn::new(&cfg, stats(), &Device::flex());
        assert_eq!(net.num_params(), cfg.parameter_count());
        // The paper's GNN has 1.6 M parameters: latent 128, 10 rounds.
        let paper = GnnConfig::default().parameter_count();
        assert!((1_500_000..1_700_000).contains(&paper), "{paper}");
    }

    #[test]
    fn message_passing_respects_the_radius() {
        let pts = sheet(6, [0.0; 3]);
        let pairs = radius_pairs(&pts, 1.6);
        let brute: Vec<(usize, usize)> = (0..pts.len())
            .flat_map(|i| (i + 1..pts.len()).map(move |j| (i, j)))
            .filter(|&(i, j)| dist(pts[i], pts[j]) < 1.6)
            .collect();
        assert_eq!(pairs, brute);
        assert!(!pairs.is_empty());
        // Two far-apart clusters exchange no messages: moving one leaves the other's
        // prediction unchanged.
        let cfg = GnnConfig {
            latent: 8,
            message_passing: 2,
            history: 1,
            ..GnnConfig::default()
        };
        let device = Device::flex();
        let net = Gnn::new(&cfg, stats(), &device);
        let a = sheet(3, [0.0; 3]);
        let far = |dz: f32| sheet(3, [100.0, 0.0, dz]);
        let predict = |b: Vec<[f32; 3]>| {
            let pts: Vec<[f32; 3]> = a.iter().chain(&b).copied().collect();
            let prev: Vec<[f32; 3]> = pts.iter().map(|p| [p[0], p[1], p[2] + 0.01]).collect();
            let mut g = Graph::default();
            net.append_graph(&mut g, &[&prev, &pts], &vec![false; pts.len()]);
            let out: Vec<f32> = net
                .forward(&g, &device)
                .into_data()
                .try_into_vec_as()
                .unwrap();
            out[..a.len() * 3].to_vec()
        };
        let (p1, p2) = (predict(far(0.0)), predict(far(0.5)));
        assert!(p1.iter().zip(&p2).all(|(x, y)| (x - y).abs() < 1e-6));
    }

    #[test]
    fn acceleration_is_invariant_to_translating_the_cloth() {
        let cfg = GnnConfig {
            latent: 16,
            message_passing: 2,
            history: 2,
            ..GnnConfig::default()
        };
        let device = Device::flex();
        let net = Gnn::new(&cfg, stats(), &device);
        let pinned: Vec<bool> = (0..16).map(|i| i == 3 || i == 15).collect();
        let predict = |shift: [f32; 3]| {
            let frames: Vec<Vec<[f32; 3]>> = (0..3)
                .map(|k| {
                    sheet(4, shift)
                        .into_iter()
                        .map(|p| [p[0], p[1], p[2] - 0.01 * k as f32])
                        .collect()
                })
                .collect();
            let refs: Vec<&[[f32; 3]]> = frames.iter().map(|f| f.as_slice()).collect();
            let mut g = Graph::default();
            net.append_graph(&mut g, &refs, &pinned);
            let out: Vec<f32> = net
                .forward(&g, &device)
                .into_data()
                .try_into_vec_as()
                .unwrap();
            out
        };
        let (a, b) = (predict([0.0; 3]), predict([3.25, -7.5, 11.0]));
        assert_eq!(a.len(), 16 * 3);
        for (x, y) in a.iter().zip(&b) {
            assert!((x - y).abs() < 1e-4, "{x} vs {y}");
        }
    }
}
