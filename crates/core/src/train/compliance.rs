//! The strain-compliance start (ours, `train.compliance`): a spring network shaped by how little
//! each spring stretches in the training rollouts.
//!
//! Under a load shared by neighbouring springs, a spring's strain is inversely proportional to
//! its stiffness; a stiff region of a cloth is the one that stretches least. At camera rate that
//! static reading is what the frames resolve best: the forces of a force fit are second
//! differences of positions, noisy where a stiff spring's strain is small, so least squares
//! leaves the stiffest springs least determined (and biased low), while the strains themselves
//! are measured directly. Each spring's `k` is its family's median RMS strain over every frame
//! of the training clips divided by its own (ratios kept within 100× either way),
//! scaled so that the stiffest spring has the run's initial uniform `k` (stable at the run's
//! substeps); `b` starts uniform. The map's ranks are the point; its
//! size and how much of it to keep are found by free rollouts (`train.blend_search`).

use anyhow::{Result, bail};
use serde::{Deserialize, Serialize};

use crate::cloth::Topology;
use crate::data::ClipSet;

/// The `[train.compliance]` section.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
#[serde(deny_unknown_fields, default)]
pub struct ComplianceConfig {
    /// Start the spring network from the strain-compliance map instead of a uniform one (or
    /// the least-squares fit, which this replaces).
    pub enabled: bool,
}

/// The largest ratio of a spring's `k` to its family's median, either way.
const MAX_RATIO: f64 = 100.0;

/// Per-spring RMS strain `|x_a − x_b| / l₀ − 1` over every frame of the training rollouts in
/// which both ends are seen (a spring seen in no frame gets 0: it takes its family's median).
pub(crate) fn rms_strains(clips: &ClipSet) -> Result<Vec<f64>> {
    let topo = &clips.topology;
    let mut sum = vec![0.0; topo.num_springs()];
    let mut count = vec![0usize; topo.num_springs()];
    let mut frames = 0usize;
    for r in 0..clips.len() {
        let track = clips.track(r)?;
        let p = track.particles;
        for f in 0..track.frames {
            let x = &track.positions[f * p * 3..(f + 1) * p * 3];
            let seen = |i: usize| track.visible.as_ref().is_none_or(|v| v[f * p + i]);
            for (s, &[a, b]) in topo.springs.iter().enumerate() {
                if !(seen(a) && seen(b)) {
                    continue;
                }
                let d: f64 = (0..3)
                    .map(|c| (x[3 * b + c] as f64 - x[3 * a + c] as f64).powi(2))
                    .sum::<f64>()
                    .sqrt();
                sum[s] += (d / topo.rest_length[s] - 1.0).powi(2);
                count[s] += 1;
            }
            frames += 1;
        }
    }
    if frames == 0 {
        bail!("`train.compliance`: the training rollouts hold no frame");
    }
    Ok(sum
        .into_iter()
        .zip(count)
        .map(|(v, n)| if n == 0 { 0.0 } else { (v / n as f64).sqrt() })
        .collect())
}

/// The compliance map: each family's median RMS strain over the spring's own, scaled so that
/// the largest is `k_init`.
pub fn stiffness(topo: &Topology, strains: &[f64], k_init: f64) -> Vec<f64> {
    let mut k = vec![k_init; topo.num_springs()];
    let mut families = topo.family.clone();
    families.sort_by_key(|f| *f as usize);
    families.dedup();
    for family in families {
        let members: Vec<usize> = (0..topo.num_springs())
            .filter(|&s| topo.family[s] == family)
            .collect();
        let mut moving: Vec<f64> = members
            .iter()
            .map(|&s| strains[s])
            .filter(|&e| e > 0.0)
            .collect();
        if moving.is_empty() {
            continue;
        }
        moving.sort_by(f64::total_cmp);
        let median = moving[moving.len() / 2];
        for &s in &members {
            let ratio = if strains[s] > 0.0 {
                (median / strains[s]).clamp(1.0 / MAX_RATIO, MAX_RATIO)
            } else {
                1.0
            };
            k[s] = k_init * ratio;
        }
    }
    // The stiffest spring at `k_init`, whose uniform network the run's substeps keep stable:
    // the map's size is the blend search's to find, its shape is what this start gives.
    let top = k.iter().copied().fold(0.0, f64::max);
    k.iter().map(|v| v * k_init / top).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Within a family the map is the inverse of the strain; a spring that never stretches
    /// takes the family's median; the stiffest spring has `k_init`.
    #[test]
    fn stiffness_is_the_inverse_strain_scaled_to_the_initial_k() {
        let points: Vec<[f64; 2]> = (0..3)
            .flat_map(|j| (0..3).map(move |i| [i as f64 * 0.5, j as f64 * 0.5 + 0.01 * i as f64]))
            .collect();
        let topo = Topology::of_points(&points, 1.0, 1.01, false).expect("a mesh");
        let n = topo.num_springs();
        assert!(topo.family.iter().all(|f| *f == topo.family[0]));
        let mut strains: Vec<f64> = (0..n).map(|s| 0.01 * (1 + s % 3) as f64).collect();
        strains[0] = 0.0;
        let k = stiffness(&topo, &strains, 10.0);
        let top = k.iter().copied().fold(0.0, f64::max);
        assert!((top - 10.0).abs() < 1e-12, "{k:?}");
        // The median strain is 0.02 (ratio 1); the smallest, 0.01, gives the top (ratio 2).
        assert!((k[0] - 5.0).abs() < 1e-12, "{k:?}");
        for s in 1..n {
            assert!(
                (k[s] * strains[s] - 0.1).abs() < 1e-12,
                "spring {s}: {}",
                k[s]
            );
        }
    }
}
