//! The observability map: per spring, how strongly the training data constrains `k` and `b`.
//!
//! The target forces are linear in `k_s` and `b_s` (Eq. 4): on a free endpoint of spring `s`,
//! `∂f/∂k_s = ±(|d_s| − l0_s) d̂_s` and `∂f/∂b_s = ±(w_s · d̂_s) d̂_s` (`d` the spring's
//! vector, `w` its endpoints' relative velocity). The Gauss–Newton (Fisher) diagonal of the
//! force loss at the target states is therefore
//! `O_k(s) = Σ_frames Σ_free endpoints (|d_s| − l0_s)²` and
//! `O_b(s) = Σ_frames Σ_free endpoints (w_s · d̂_s)²`; a pinned endpoint's force is not in the
//! loss and adds nothing. Reported as `√(O / (2 · frames))`: the RMS strain (m) and strain
//! rate (m/s) of a spring with two free ends (one pinned end gives `1/√2` of it).

use std::path::{Path, PathBuf};

use anyhow::Result;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::Inputs;
use crate::cloth::{SpringFamily, Topology};
use crate::data::{ClipRef, ClipSet};
use crate::eval::spearman;
use crate::progress::Progress;
use springtime_plot::{self as plot, MapRow};

/// Running sums of the Fisher diagonal over frames.
#[derive(Debug, Clone, PartialEq)]
pub struct Accumulator {
    /// `Σ (|d| − l0)²` over frames and free endpoints, per spring.
    pub sum_k: Vec<f64>,
    /// `Σ (w · d̂)²`, per spring.
    pub sum_b: Vec<f64>,
    /// Frames added.
    pub frames: usize,
}

impl Accumulator {
    /// Empty sums for `springs` springs.
    pub fn new(springs: usize) -> Self {
        Self {
            sum_k: vec![0.0; springs],
            sum_b: vec![0.0; springs],
            frames: 0,
        }
    }

    /// Adds one state: positions and velocities `[P, 3]`, `pinned` per particle.
    pub fn add_frame(&mut self, topology: &Topology, x: &[f32], v: &[f32], pinned: &[bool]) {
        let at = |a: &[f32], i: usize| [a[3 * i] as f64, a[3 * i + 1] as f64, a[3 * i + 2] as f64];
        for (s, &[i, j]) in topology.springs.iter().enumerate() {
            let free = (!pinned[i]) as u8 + (!pinned[j]) as u8;
            if free == 0 {
                continue;
            }
            let (xi, xj, vi, vj) = (at(x, i), at(x, j), at(v, i), at(v, j));
            let d = [xj[0] - xi[0], xj[1] - xi[1], xj[2] - xi[2]];
            let len = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
            let strain = len - topology.rest_length[s];
            let rate = if len > 0.0 {
                ((vj[0] - vi[0]) * d[0] + (vj[1] - vi[1]) * d[1] + (vj[2] - vi[2]) * d[2]) / len
            } else {
                0.0
            };
            self.sum_k[s] += free as f64 * strain * strain;
            self.sum_b[s] += free as f64 * rate * rate;
        }
        self.frames += 1;
    }

    /// Adds another accumulator's sums.
    pub fn merge(mut self, other: Self) -> Self {
        for (a, b) in self.sum_k.iter_mut().zip(&other.sum_k) {
            *a += b;
        }
        for (a, b) in self.sum_b.iter_mut().zip(&other.sum_b) {
            *a += b;
        }
        self.frames += other.frames;
        self
    }

    /// `(obs_k, obs_b)` per spring: `√(O / (2 · frames))` (0 without frames).
    pub fn finish(&self) -> (Vec<f64>, Vec<f64>) {
        let n = 2.0 * self.frames.max(1) as f64;
        let f = |v: &[f64]| v.iter().map(|s| (s / n).sqrt()).collect();
        (f(&self.sum_k), f(&self.sum_b))
    }
}

/// Sums the Fisher diagonal over the states of the training clips: the `T` frames of each clip
/// at which the force loss compares forces (`offset .. offset + T`).
pub fn accumulate(set: &ClipSet, clips: &[ClipRef], progress: &Progress) -> Result<Accumulator> {
    let bar = progress.bar(clips.len() as u64, "observability");
    let s = set.topology.num_springs();
    let p = set.topology.num_particles() * 3;
    let acc = clips
        .par_iter()
        .map(|c| -> Result<Accumulator> {
            let track = set.track(c.rollout)?;
            let mut acc = Accumulator::new(s);
            for j in c.offset..c.offset + set.steps {
                acc.add_frame(
                    &set.topology,
                    &track.positions[j * p..(j + 1) * p],
                    &track.velocities[j * p..(j + 1) * p],
                    &track.pinned,
                );
            }
            bar.inc(1);
            Ok(acc)
        })
        .try_reduce(|| Accumulator::new(s), |a, b| Ok(a.merge(b)))?;
    bar.finish();
    Ok(acc)
}

/// Order statistics of one quantity over a family's springs.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Stats {
    /// Smallest value.
    pub min: f64,
    /// Median.
    pub median: f64,
    /// Mean.
    pub mean: f64,
    /// Largest value.
    pub max: f64,
    /// Springs with value 0 (unobserved).
    pub zero: usize,
}

impl Stats {
    fn of(v: &[f64]) -> Self {
        let mut s = v.to_vec();
        s.sort_by(f64::total_cmp);
        let n = s.len();
        Self {
            min: s.first().copied().unwrap_or(0.0),
            median: if n == 0 {
                0.0
            } else if n % 2 == 1 {
                s[n / 2]
            } else {
                (s[n / 2 - 1] + s[n / 2]) / 2.0
            },
            mean: s.iter().sum::<f64>() / n.max(1) as f64,
            max: s.last().copied().unwrap_or(0.0),
            zero: s.iter().filter(|&&x| x == 0.0).count(),
        }
    }
}

/// One family's observability.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FamilySummary {
    /// `structural`, `shear` or `bending`.
    pub family: String,
    /// Springs of the family.
    pub springs: usize,
    /// `obs_k` over them, m.
    pub obs_k: Stats,
    /// `obs_b` over them, m/s.
    pub obs_b: Stats,
}

/// A spring singled out.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SpringAt {
    /// Its index.
    pub spring: usize,
    /// Its family.
    pub family: String,
    /// Its rest midpoint `(u, v)`, m.
    pub midpoint: [f64; 2],
    /// The value there.
    pub value: f64,
}

/// The least and most observable springs of one parameter.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Extremes {
    /// The least observable spring.
    pub least: SpringAt,
    /// The most observable spring.
    pub most: SpringAt,
    /// Springs with zero observability (no training frame moves them, or both ends pinned).
    pub unobserved: usize,
}

/// Recovery error against observability for one parameter.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ErrorVsObservability {
    /// Spearman correlation of `|learned − true|` with the observability (expected negative);
    /// `None` when either is constant.
    pub spearman: Option<f64>,
    /// The 10 % least observable springs against the rest.
    pub least_observable: LeastObservable,
}

/// Mean recovery error of the least observable springs and of the rest.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LeastObservable {
    /// Springs in the least observable 10 % (at least 1).
    pub springs: usize,
    /// Their mean `|learned − true|`.
    pub mean_error_least: f64,
    /// The others' mean `|learned − true|`.
    pub mean_error_rest: f64,
}

/// Recovery error against observability, with ground truth.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TruthCorrelation {
    /// For `k` (N/m errors against `obs_k`).
    pub k: ErrorVsObservability,
    /// For `b` (N·s/m errors against `obs_b`).
    pub b: ErrorVsObservability,
}

/// `observability.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ObservabilityReport {
    /// What the numbers are.
    pub definition: String,
    /// Training clips summed over.
    pub clips: usize,
    /// Frames summed over.
    pub frames: usize,
    /// RMS strain `|d| − l0` per spring, m (the root-mean of `O_k` over frames).
    pub obs_k: Vec<f64>,
    /// RMS strain rate `w · d̂` per spring, m/s.
    pub obs_b: Vec<f64>,
    /// Each spring's family.
    pub family: Vec<String>,
    /// Per-family summaries.
    pub families: Vec<FamilySummary>,
    /// Extremes of `obs_k`.
    pub extremes_k: Extremes,
    /// Extremes of `obs_b`.
    pub extremes_b: Extremes,
    /// Recovery error against observability, when the data carries ground truth.
    pub truth: Option<TruthCorrelation>,
}

fn extremes(topology: &Topology, v: &[f64]) -> Extremes {
    let at = |s: usize| SpringAt {
        spring: s,
        family: topology.family[s].name().into(),
        midpoint: topology.midpoint(s),
        value: v[s],
    };
    let order = |a: &usize, b: &usize| v[*a].total_cmp(&v[*b]);
    Extremes {
        least: at((0..v.len()).min_by(order).unwrap_or(0)),
        most: at((0..v.len()).max_by(order).unwrap_or(0)),
        unobserved: v.iter().filter(|&&x| x == 0.0).count(),
    }
}

/// Correlates `|learned − truth|` with `obs` and compares the 10 % least observable springs
/// with the rest.
pub fn error_vs_observability(learned: &[f64], truth: &[f64], obs: &[f64]) -> ErrorVsObservability {
    let err: Vec<f64> = learned
        .iter()
        .zip(truth)
        .map(|(a, b)| (a - b).abs())
        .collect();
    let mut order: Vec<usize> = (0..obs.len()).collect();
    order.sort_by(|&a, &b| obs[a].total_cmp(&obs[b]));
    let n = (obs.len() / 10).max(1).min(obs.len());
    let mean = |ids: &[usize]| ids.iter().map(|&i| err[i]).sum::<f64>() / ids.len().max(1) as f64;
    ErrorVsObservability {
        spearman: spearman(&err, obs),
        least_observable: LeastObservable {
            springs: n,
            mean_error_least: mean(&order[..n]),
            mean_error_rest: mean(&order[n..]),
        },
    }
}

/// The observability map of a run's training clips (its `regular` and `low_velocity` sets).
pub fn observability(
    set: &ClipSet,
    inputs: &Inputs,
    progress: &Progress,
) -> Result<ObservabilityReport> {
    let clips: Vec<ClipRef> = set.all_clips();
    let acc = accumulate(set, &clips, progress)?;
    Ok(summarize(&inputs.topology, &acc, clips.len(), inputs))
}

fn summarize(
    topology: &Topology,
    acc: &Accumulator,
    clips: usize,
    inputs: &Inputs,
) -> ObservabilityReport {
    let (obs_k, obs_b) = acc.finish();
    let families = [
        SpringFamily::Structural,
        SpringFamily::Shear,
        SpringFamily::Bending,
    ]
    .into_iter()
    .filter_map(|f| {
        let ids: Vec<usize> = (0..topology.num_springs())
            .filter(|&s| topology.family[s] == f)
            .collect();
        (!ids.is_empty()).then(|| {
            let pick = |v: &[f64]| ids.iter().map(|&s| v[s]).collect::<Vec<_>>();
            FamilySummary {
                family: f.name().into(),
                springs: ids.len(),
                obs_k: Stats::of(&pick(&obs_k)),
                obs_b: Stats::of(&pick(&obs_b)),
            }
        })
    })
    .collect();
    let truth = inputs.truth.as_ref().map(|(k, b)| TruthCorrelation {
        k: error_vs_observability(&inputs.model.k_values(), k, &obs_k),
        b: error_vs_observability(&inputs.model.b_values(), b, &obs_b),
    });
    ObservabilityReport {
        definition: "Gauss–Newton (Fisher) diagonal of the force loss at the training clips' \
                     target states: obs_k = √(Σ_frames Σ_free endpoints (|d|−l0)² / (2·frames)) \
                     in m, obs_b the same with the strain rate w·d̂ in m/s; pinned endpoints add \
                     nothing"
            .into(),
        clips,
        frames: acc.frames,
        extremes_k: extremes(topology, &obs_k),
        extremes_b: extremes(topology, &obs_b),
        family: topology.family.iter().map(|f| f.name().into()).collect(),
        families,
        obs_k,
        obs_b,
        truth,
    }
}

/// Colour values of a map: `log10` when the positive values span more than two decades (zeros
/// then NaN: drawn grey), else the values; with the colour range and whether it is a log scale.
fn colour_values(v: &[f64]) -> (Vec<f64>, (f64, f64), bool) {
    let pos: Vec<f64> = v.iter().copied().filter(|&x| x > 0.0).collect();
    let (lo, hi) = plot::value_range(&[&pos]);
    if !pos.is_empty() && hi > 100.0 * lo {
        let logs: Vec<f64> = v
            .iter()
            .map(|&x| if x > 0.0 { x.log10() } else { f64::NAN })
            .collect();
        let range = plot::value_range(&[&logs]);
        (logs, range, true)
    } else {
        let range = plot::value_range(&[v]);
        (v.to_vec(), range, false)
    }
}

impl ObservabilityReport {
    /// Writes `observability.json` and `observability.png`; returns the paths.
    pub fn write(&self, dir: &Path, topology: &Topology) -> Result<Vec<PathBuf>> {
        let json = dir.join("observability.json");
        crate::io::write_json(&json, self)?;
        let (k, k_range, k_log) = colour_values(&self.obs_k);
        let (b, b_range, b_log) = colour_values(&self.obs_b);
        let label = |log: bool, q: &str, unit: &str| {
            if log {
                format!("log10 {q} ({unit})")
            } else {
                format!("{q} ({unit})")
            }
        };
        let (k_label, b_label) = (
            label(k_log, "RMS strain", "m"),
            label(b_log, "RMS strain rate", "m/s"),
        );
        let png = dir.join("observability.png");
        plot::spring_map_rows_png(
            &png,
            topology,
            &[
                MapRow {
                    name: "k",
                    values: &k,
                    range: k_range,
                    label: &k_label,
                },
                MapRow {
                    name: "b",
                    values: &b,
                    range: b_range,
                    label: &b_label,
                },
            ],
            &format!(
                "Observability per spring over {} training clips (grey: unobserved)",
                self.clips
            ),
        )?;
        Ok(vec![json, png])
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cloth::GridSpec;

    fn grid() -> Topology {
        Topology::grid(
            &GridSpec {
                nx: 4,
                ny: 4,
                ..GridSpec::default()
            },
            1.5,
            1.5,
        )
    }

    /// The rest sheet with particle 5 displaced by `a` along x and moving at `a` m/s.
    fn state(topo: &Topology, a: f64) -> (Vec<f32>, Vec<f32>) {
        let mut x: Vec<f32> = topo
            .rest_positions()
            .iter()
            .flat_map(|p| p.map(|c| c as f32))
            .collect();
        let mut v = vec![0f32; x.len()];
        x[15] += a as f32;
        v[15] = a as f32;
        (x, v)
    }

    #[test]
    fn a_sheet_at_rest_or_pinned_springs_are_unobserved_and_strain_raises_it() {
        let topo = grid();
        let p = topo.num_particles();
        let free = vec![false; p];
        // At rest, nothing is observed.
        let (x, v) = state(&topo, 0.0);
        let mut acc = Accumulator::new(topo.num_springs());
        acc.add_frame(&topo, &x, &v, &free);
        let (k, b) = acc.finish();
        assert!(k.iter().chain(&b).all(|&o| o < 1e-7), "{k:?}");

        // Stretched around particle 5: its springs are observed, and twice the strain doubles it.
        let obs = |a: f64, pinned: &[bool]| {
            let (x, v) = state(&topo, a);
            let mut acc = Accumulator::new(topo.num_springs());
            acc.add_frame(&topo, &x, &v, pinned);
            acc.finish()
        };
        let (k1, b1) = obs(0.05, &free);
        let (k2, b2) = obs(0.10, &free);
        let touching: Vec<usize> = (0..topo.num_springs())
            .filter(|&s| topo.springs[s].contains(&5))
            .collect();
        assert!(!touching.is_empty());
        for s in 0..topo.num_springs() {
            if touching.contains(&s) {
                assert!(
                    k1[s] > 1e-3 && k2[s] > 1.5 * k1[s],
                    "spring {s}: {} {}",
                    k1[s],
                    k2[s]
                );
            } else {
                assert!(k1[s] < 1e-7 && b1[s] < 1e-7, "spring {s} does not move");
            }
        }
        // The structural spring 5–6 along x: strain rate = the velocity along it.
        let s56 = (0..topo.num_springs())
            .find(|&s| {
                let [i, j] = topo.springs[s];
                (i.min(j), i.max(j)) == (5, 6)
            })
            .unwrap();
        assert!((b1[s56] - 0.05).abs() < 1e-6 && (b2[s56] - 0.10).abs() < 1e-6);

        // Pin both ends of 5–6: it drops out; pinning one end leaves 1/√2 of it.
        let mut pinned = free.clone();
        pinned[5] = true;
        pinned[6] = true;
        let (k_both, b_both) = obs(0.05, &pinned);
        assert_eq!((k_both[s56], b_both[s56]), (0.0, 0.0));
        pinned[6] = false;
        let (k_one, _) = obs(0.05, &pinned);
        assert!((k_one[s56] - k1[s56] / 2f64.sqrt()).abs() < 1e-9);
    }

    #[test]
    fn error_correlates_with_observability() {
        // Errors shrinking with observability: Spearman −1, the least observable tenth worst.
        let obs: Vec<f64> = (1..=20).map(|i| i as f64).collect();
        let truth = vec![50.0; 20];
        let learned: Vec<f64> = obs.iter().map(|o| 50.0 + 10.0 / o).collect();
        let c = error_vs_observability(&learned, &truth, &obs);
        assert!((c.spearman.unwrap() + 1.0).abs() < 1e-12);
        assert_eq!(c.least_observable.springs, 2);
        assert!(c.least_observable.mean_error_least > c.least_observable.mean_error_rest);
    }
}
