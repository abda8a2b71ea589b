//! The strain-compliance start (ours, `train.compliance`): a spring network shaped by how little
//! each spring stretches in the training rollouts.
//!
//! Under a load shared by neighbouring springs, a spring's strain is inversely proportional to
//! its stiffness; a stiff region of a cloth is the one that stretches least. At camera rate that
//! static reading is what the frames resolve best: the forces of a force fit are second
//! differences of positions, noisy where a stiff spring's strain is small, so least squares
//! leaves the stiffest springs least determined (and biased low), while the strains themselves
//! are measured directly. Each spring's `k` is its group's median RMS strain over every frame
//! of the training clips divided by its own (ratios kept within 100× either way; the
//! positions' noise taken out of each mean square, `rms_strains`),
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
    /// How the mixed map (`compliance::mixed`, searched where the least-squares fit runs too)
    /// weighs the fit's and this map's shapes: `"equal"` (half each) or `"halves"` (each as it
    /// reads alike off the even and the odd training takes, [`MapWeights::from_halves`]).
    pub weights: MapWeighting,
    /// Which map's blend the run keeps where the least-squares fit runs too: `"mixed"` (the
    /// mixed map alone is searched, the other two as well where its blend stays uniform) or
    /// `"closest"` (the fit's, this map's and the mixed map are each searched and polished, and
    /// another than the mixed one is kept where it moves closer to the training takes and the
    /// held-out takes agree).
    pub keep: MapKeep,
    /// How the positions' noise is taken out of the compliance map's mean square strains:
    /// `"per_spring"` (each spring's own fourth differences), `"pooled"` (one marker noise
    /// for every spring, [`StrainNoise::Pooled`]) or `"stated"` (the marker noise the run
    /// states, the fit's `train.least_squares.noise`, [`StrainNoise::Stated`]).
    pub noise: StrainNoise,
}

/// How the positions' noise is estimated for each spring (`train.compliance.noise`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum StrainNoise {
    /// Each spring's strain noise from its own frames: its mean square fourth difference over
    /// 70.
    #[default]
    PerSpring,
    /// One marker noise for every spring (ours): white noise of `σ` per axis on each end adds
    /// `2σ²/l²` to a spring's mean square strain, `l` its rest length. `σ²` is the median over
    /// the springs of their own estimates times `l²/2`, and each spring's noise is `2σ²/l²`. A
    /// capture's markers share one accuracy; a spring's own estimate adds its sampling error,
    /// and on clean frames the motion the frames barely resolve (a stiff cloth's membrane
    /// at camera rate), to its rank.
    Pooled,
    /// The marker noise `σ` the run states, as the least-squares fit takes it out
    /// (`train.least_squares.noise`, whose `"auto"` is the files' `position_noise` and exact
    /// positions where they state none): each spring's noise is `2σ²/l²`. Frames a simulator
    /// wrote have no marker noise, and what their fourth differences hold is motion.
    Stated,
}

impl StrainNoise {
    /// The name the configuration gives it.
    pub fn name(self) -> &'static str {
        match self {
            StrainNoise::PerSpring => "per_spring",
            StrainNoise::Pooled => "pooled",
            StrainNoise::Stated => "stated",
        }
    }
}

/// Which map's blend the run keeps (`train.compliance.keep`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum MapKeep {
    /// The three maps searched, the mixed one kept unless another moves closer to both kinds of
    /// takes.
    Closest,
    /// The mixed map alone, unless its blend stays uniform; then as `Closest`.
    #[default]
    Mixed,
}

/// How the mixed map weighs its two shapes (`train.compliance.weights`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum MapWeighting {
    /// Half each.
    Equal,
    /// Each map as its split-half reliability ([`MapWeights::from_halves`]); two least-squares
    /// fits more.
    #[default]
    Halves,
}

/// The largest ratio of a spring's `k` to its group's median, either way.
const MAX_RATIO: f64 = 100.0;

/// The springs' RMS strains, with the share of their mean square that the positions' noise
/// made and that was taken out.
#[derive(Debug, Clone)]
pub(crate) struct RmsStrains {
    /// Per-spring RMS strain, noise taken out.
    pub rms: Vec<f64>,
    /// The noise's share of the springs' summed mean square strain before it was taken out.
    pub noise_share: f64,
    /// The marker noise `σ` (m per axis) the springs share, where pooled ([`StrainNoise`]).
    pub sigma: Option<f64>,
}

/// White noise's variance in a fourth difference `ε₀ − 4ε₁ + 6ε₂ − 4ε₃ + ε₄`: `1+16+36+16+1`
/// times its own.
const FOURTH_DIFFERENCE_GAIN: f64 = 70.0;

/// A spring's mean square strain keeps at least this share of itself after the noise is taken
/// out (a spring whose strain is all noise ranks as the most compliant, not as undefined).
const NOISE_FLOOR: f64 = 0.01;

/// Per-spring RMS strain `|x_a − x_b| / l₀ − 1` over every frame of the training rollouts of
/// `share` in which both ends are seen (a spring seen in no frame gets 0: it takes its group's median),
/// less the strain noise of the positions.
///
/// Measured positions (a capture's markers) carry noise, which adds its variance to every
/// spring's mean square strain and would rank the springs by their rest length instead of
/// their stiffness. A motion the frames resolve has almost no fourth difference in time, white
/// noise has 70 times its variance there: each spring's noise variance is its strain's mean
/// square fourth difference inside the training clips over 70, or with `noise` pooled one
/// marker noise for every spring, or with `noise` stated the marker noise `stated` (m per axis)
/// ([`StrainNoise`]), and is subtracted (the share taken out is reported in the log).
pub(crate) fn rms_strains(
    clips: &ClipSet,
    share: Share,
    noise: StrainNoise,
    stated: f64,
) -> Result<RmsStrains> {
    let topo = &clips.topology;
    let springs = topo.num_springs();
    let mut sum = vec![0.0; springs];
    let mut count = vec![0usize; springs];
    let (mut d4_sum, mut d4_count) = (vec![0.0; springs], vec![0usize; springs]);
    let mut frames = 0usize;
    let all = clips.all_clips();
    for r in (0..clips.len()).filter(|&r| share.has(r)) {
        let track = clips.track(r)?;
        let p = track.particles;
        // Strain of every spring in every frame, NaN where an end is hidden.
        let mut strain = vec![f64::NAN; track.frames * springs];
        for f in 0..track.frames {
            let x = &track.positions[f * p * 3..(f + 1) * p * 3];
            for (s, &[a, b]) in topo.springs.iter().enumerate() {
                if !(track.seen(f, a) && track.seen(f, b)) {
                    continue;
                }
                let d: f64 = (0..3)
                    .map(|c| (x[3 * b + c] as f64 - x[3 * a + c] as f64).powi(2))
                    .sum::<f64>()
                    .sqrt();
                let e = d / topo.rest_length[s] - 1.0;
                strain[f * springs + s] = e;
                sum[s] += e * e;
                count[s] += 1;
            }
            frames += 1;
        }
        // Fourth differences inside this rollout's clips (a clip lies in one stored window).
        for clip in all.iter().filter(|c| c.rollout == r) {
            for s in 0..springs {
                let series: Vec<f64> = (clip.offset..=clip.offset + clips.steps)
                    .map(|f| strain[f * springs + s])
                    .collect();
                add_fourth_differences(&series, &mut d4_sum[s], &mut d4_count[s]);
            }
        }
    }
    if frames == 0 {
        bail!("`train.compliance`: the training rollouts hold no frame");
    }
    let own: Vec<Option<f64>> = (0..springs)
        .map(|s| (d4_count[s] > 0).then(|| d4_sum[s] / d4_count[s] as f64 / FOURTH_DIFFERENCE_GAIN))
        .collect();
    let (variances, sigma) = noise_variances(&own, &topo.rest_length, noise, stated);
    let (mut raw_total, mut noise_total) = (0.0, 0.0);
    let rms = (0..springs)
        .map(|s| {
            if count[s] == 0 {
                return 0.0;
            }
            let ms = sum[s] / count[s] as f64;
            let noise = variances[s];
            raw_total += ms;
            noise_total += noise.min(ms);
            (ms - noise).max(NOISE_FLOOR * ms).sqrt()
        })
        .collect();
    Ok(RmsStrains {
        rms,
        noise_share: if raw_total > 0.0 {
            noise_total / raw_total
        } else {
            0.0
        },
        sigma,
    })
}

/// Each spring's strain noise variance from its own estimate `own` (`None`: no fourth
/// difference seen) and rest length `rest`, as `noise` says ([`StrainNoise`], `stated` the
/// marker noise the run states); with the marker noise `σ` (m per axis) where one is shared.
fn noise_variances(
    own: &[Option<f64>],
    rest: &[f64],
    noise: StrainNoise,
    stated: f64,
) -> (Vec<f64>, Option<f64>) {
    // One marker noise of variance `sigma2` per axis for every spring.
    let marker = |sigma2: f64| {
        let variances = rest.iter().map(|l| 2.0 * sigma2 / (l * l)).collect();
        (variances, Some(sigma2.sqrt()))
    };
    match noise {
        StrainNoise::PerSpring => (own.iter().map(|v| v.unwrap_or(0.0)).collect(), None),
        StrainNoise::Stated => marker(stated * stated),
        StrainNoise::Pooled => {
            let mut sigma2: Vec<f64> = own
                .iter()
                .zip(rest)
                .filter_map(|(v, l)| v.map(|v| v * l * l / 2.0))
                .collect();
            if sigma2.is_empty() {
                return (vec![0.0; own.len()], None);
            }
            sigma2.sort_by(f64::total_cmp);
            marker(sigma2[sigma2.len() / 2])
        }
    }
}

/// Adds the squares of the fourth differences of `series` (those of five finite values) to
/// `sum`, counting them in `count`.
fn add_fourth_differences(series: &[f64], sum: &mut f64, count: &mut usize) {
    for e in series.windows(5) {
        let d4 = e[0] - 4.0 * e[1] + 6.0 * e[2] - 4.0 * e[3] + e[4];
        if d4.is_finite() {
            *sum += d4 * d4;
            *count += 1;
        }
    }
}

/// The compliance map: each group's median RMS strain over the spring's own (a grid's
/// families; a data mesh's edges together, its hinge springs by family), scaled so that the
/// largest is `k_init`.
pub fn stiffness(topo: &Topology, strains: &[f64], k_init: f64) -> Vec<f64> {
    let mut k = vec![k_init; topo.num_springs()];
    for members in strain_groups(topo) {
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

/// The fit's and the compliance map's stiffness together (ours): in each strain group, each
/// map over its own mean, the two averaged with the weights of `weights` (the fit's weight per
/// group, in the order of the groups; [`MapWeights`]), times the fit's mean there. The fit's
/// values carry the frames' forces and the group sizes (hinge springs against edges), the
/// compliance map the ranks where the forces are weakest — a stiff spring's strain is small and
/// its force noisy, so the fit ranks it worst; the strains rank it best. A group one map leaves
/// at zero takes the other's shape.
pub fn mixed(topo: &Topology, fit: &[f64], compliance: &[f64], weights: &MapWeights) -> Vec<f64> {
    let mut k = fit.to_vec();
    let groups = strain_groups(topo);
    assert_eq!(
        groups.len(),
        weights.groups.len(),
        "a weight per strain group"
    );
    for (members, weight) in groups.iter().zip(&weights.groups) {
        let mean = |v: &[f64]| members.iter().map(|&s| v[s]).sum::<f64>() / members.len() as f64;
        // The maps with a shape here, each with its mean and weight; the size is the fit's
        // where it has one.
        let w = weight.fit_weight;
        let mut shaped: Vec<(&[f64], f64, f64)> =
            [(fit, mean(fit), w), (compliance, mean(compliance), 1.0 - w)]
                .into_iter()
                .filter(|&(_, m, _)| m > 0.0)
                .collect();
        // Two maps weigh `w` and `1 − w`; one alone has the whole weight, whatever its own.
        if let [alone] = shaped.as_mut_slice() {
            alone.2 = 1.0;
        }
        let Some(&(_, size, _)) = shaped.first() else {
            continue;
        };
        for &s in members {
            k[s] = size * shaped.iter().map(|&(v, m, w)| w * v[s] / m).sum::<f64>();
        }
    }
    k
}

/// How far each map read off the training takes is the cloth's and how far the takes' chance
/// (ours): per strain group, the Spearman correlation of each map read off one half of the
/// training rollouts (alternate ones, [`Share::Half`]) with the same map read off the other
/// half, and the fit's weight in the mixed map that follows from them.
///
/// Both maps estimate the same spatial stiffness, each with an error of its own. A map's
/// split-half correlation `r` is its reliability on half the takes; on all of them it is
/// `R = 2r / (1 + r)` (Spearman–Brown), and its ratio of signal to error variance `R / (1 − R)
/// = 2r / (1 − r)`. Two estimates of one signal with independent errors are combined best with
/// weights proportional to that ratio (inverse error variance): a map that half the takes read
/// one way and the other half another is mostly error and weighs little; two maps the halves
/// agree on equally weigh half each, as in the default mixed map (`train.compliance.weights`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MapWeights {
    /// One per strain group, in the order of the groups (a data mesh's edges first).
    pub groups: Vec<GroupWeight>,
}

/// One strain group's split-half correlations and the fit's weight ([`MapWeights`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct GroupWeight {
    /// Springs in the group.
    pub springs: usize,
    /// Spearman correlation of the fit's map on one half with the other's (`None`: not split).
    pub fit_halves: Option<f64>,
    /// The same of the compliance map.
    pub compliance_halves: Option<f64>,
    /// The fit's weight in the mixed map (the compliance map's is one less it).
    pub fit_weight: f64,
}

/// The training rollouts a map is read off: every one, or one of two halves.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Share {
    /// Every training rollout.
    All,
    /// The even-numbered rollouts (`Half(0)`) or the odd ones (`Half(1)`).
    Half(usize),
}

impl Share {
    /// Whether training rollout `rollout` is in the share.
    pub fn has(self, rollout: usize) -> bool {
        match self {
            Share::All => true,
            Share::Half(h) => rollout % 2 == h,
        }
    }
}

impl MapWeights {
    /// Equal weights in every group of `topo` (the two maps averaged, as without halves).
    pub fn equal(topo: &Topology) -> Self {
        MapWeights {
            groups: strain_groups(topo)
                .iter()
                .map(|members| GroupWeight {
                    springs: members.len(),
                    fit_halves: None,
                    compliance_halves: None,
                    fit_weight: 0.5,
                })
                .collect(),
        }
    }

    /// The weights from the maps read off the two halves: `fit[h]`, `compliance[h]` per spring.
    pub fn from_halves(topo: &Topology, fit: [&[f64]; 2], compliance: [&[f64]; 2]) -> Self {
        let correlation = |halves: [&[f64]; 2], members: &[usize]| {
            let [a, b] = halves.map(|v| members.iter().map(|&s| v[s]).collect::<Vec<_>>());
            // A map constant on a half (a group the fit left at zero) ranks nothing.
            crate::eval::spearman(&a, &b).unwrap_or(0.0)
        };
        MapWeights {
            groups: strain_groups(topo)
                .iter()
                .map(|members| {
                    let (f, c) = (correlation(fit, members), correlation(compliance, members));
                    let (sf, sc) = (signal_to_error(f), signal_to_error(c));
                    GroupWeight {
                        springs: members.len(),
                        fit_halves: Some(f),
                        compliance_halves: Some(c),
                        fit_weight: if sf + sc > 0.0 { sf / (sf + sc) } else { 0.5 },
                    }
                })
                .collect(),
        }
    }

    /// The group of the most springs (a data mesh's edges, a grid's structural springs).
    pub fn largest(&self) -> Option<&GroupWeight> {
        self.groups.iter().max_by_key(|g| g.springs)
    }
}

/// The largest split-half correlation [`signal_to_error`] takes (a map the halves read alike
/// to the last rank is not infinitely reliable).
const MAX_HALVES_CORRELATION: f64 = 0.999;

/// A map's ratio of signal to error variance on all the takes from its split-half correlation
/// `r` ([`MapWeights`]): `2r / (1 − r)`, 0 where the halves do not agree.
fn signal_to_error(r: f64) -> f64 {
    let r = if r.is_finite() {
        r.clamp(0.0, MAX_HALVES_CORRELATION)
    } else {
        0.0
    };
    2.0 * r / (1.0 - r)
}

/// `values` smoothed over the spring graph by `passes` rounds of averaging (ours,
/// `train.map_smoothing`): each round, each spring takes the mean of its own value and its
/// neighbours' mean — the springs of its strain group (a data mesh's edges together, its hinge
/// springs by family; a grid's families) that share a particle with it. A stiffness map of a
/// cloth is spatially coherent (regions painted or assigned a material), while each spring's
/// value read from the frames carries its own error; the neighbours average that error down,
/// and a spring the data leaves at zero takes its neighbours' value. Each group's values stay
/// inside their own range.
pub fn smoothed(topo: &Topology, values: &[f64], passes: usize) -> Vec<f64> {
    let mut group = vec![0usize; topo.num_springs()];
    for (g, members) in strain_groups(topo).into_iter().enumerate() {
        for s in members {
            group[s] = g;
        }
    }
    let mut at_particle = vec![Vec::new(); topo.num_particles()];
    for (s, pair) in topo.springs.iter().enumerate() {
        for &p in pair {
            at_particle[p].push(s);
        }
    }
    let neighbours: Vec<Vec<usize>> = topo
        .springs
        .iter()
        .enumerate()
        .map(|(s, pair)| {
            let mut n: Vec<usize> = pair
                .iter()
                .flat_map(|&p| at_particle[p].iter().copied())
                .filter(|&r| r != s && group[r] == group[s])
                .collect();
            n.sort_unstable();
            n.dedup();
            n
        })
        .collect();
    let mut v = values.to_vec();
    for _ in 0..passes {
        v = neighbours
            .iter()
            .enumerate()
            .map(|(s, n)| {
                if n.is_empty() {
                    v[s]
                } else {
                    0.5 * (v[s] + n.iter().map(|&r| v[r]).sum::<f64>() / n.len() as f64)
                }
            })
            .collect();
    }
    v
}

/// The springs whose strains the compliance map compares with each other: a grid's families;
/// on a data mesh its edges together — the quad cells' sides and the diagonals that cut them
/// alike, so that a diagonal that stretches more than the sides around it (a cloth weaker in
/// shear) comes out softer — and its hinge springs by family.
fn strain_groups(topo: &Topology) -> Vec<Vec<usize>> {
    let edges: std::collections::BTreeSet<[usize; 2]> = match topo.grid {
        Some(_) => Default::default(),
        None => topo.edges().into_iter().collect(),
    };
    let mut groups: std::collections::BTreeMap<Option<usize>, Vec<usize>> = Default::default();
    for (s, (pair, family)) in topo.springs.iter().zip(&topo.family).enumerate() {
        let edge = edges.contains(&[pair[0].min(pair[1]), pair[0].max(pair[1])]);
        let key = (!edge).then_some(*family as usize);
        groups.entry(key).or_default().push(s);
    }
    groups.into_values().collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cloth::SpringFamily;
    use rand::{Rng, SeedableRng, rngs::StdRng};

    /// The fourth differences of a motion the frames resolve (a swing of 12 frames a period)
    /// under white noise measure the noise's variance (×70), not the swing's.
    #[test]
    fn fourth_differences_measure_white_noise_not_resolved_motion() {
        let mut rng = StdRng::seed_from_u64(5);
        let sigma = 0.01;
        // Uniform noise on ±a has variance a²/3.
        let a = sigma * 3f64.sqrt();
        let series: Vec<f64> = (0..20_000)
            .map(|f| {
                0.05 * (f as f64 * std::f64::consts::TAU / 12.0).sin()
                    + a * (2.0 * rng.random::<f64>() - 1.0)
            })
            .collect();
        let (mut sum, mut count) = (0.0, 0);
        add_fourth_differences(&series, &mut sum, &mut count);
        let noise = sum / count as f64 / FOURTH_DIFFERENCE_GAIN;
        assert!(
            (noise / (sigma * sigma) - 1.0).abs() < 0.1,
            "estimated variance {noise:e}, true {:e}",
            sigma * sigma
        );
        // Without noise the swing alone leaves a small fraction of its mean square (0.00125).
        let clean: Vec<f64> = (0..2000)
            .map(|f| 0.05 * (f as f64 * std::f64::consts::TAU / 12.0).sin())
            .collect();
        let (mut sum, mut count) = (0.0, 0);
        add_fourth_differences(&clean, &mut sum, &mut count);
        assert!(sum / count as f64 / FOURTH_DIFFERENCE_GAIN < 0.03 * 0.00125);
        // A NaN (a hidden end) drops the five windows that hold it.
        let mut gap = clean[..20].to_vec();
        gap[10] = f64::NAN;
        let (mut sum, mut count) = (0.0, 0);
        add_fourth_differences(&gap, &mut sum, &mut count);
        assert_eq!(count, 16 - 5);
    }

    /// Pooled, every spring's strain noise is `2σ²/l²` with one `σ`: the median of the
    /// springs' own estimates, which one spring whose frames carry much more (a vibration the
    /// frames barely resolve) does not move and does not get; per spring each keeps its own.
    #[test]
    fn pooled_strain_noise_is_one_marker_noise_over_each_rest_length() {
        let sigma: f64 = 0.002;
        let rest = [0.05, 0.1, 0.1, 0.2, 0.07];
        let exact: Vec<f64> = rest.iter().map(|l| 2.0 * sigma * sigma / (l * l)).collect();
        // Each spring's own estimate off by its sampling error, the third one by far more.
        let errors = [1.1, 0.9, 25.0, 1.05, 0.97];
        let mut own: Vec<Option<f64>> =
            exact.iter().zip(errors).map(|(v, e)| Some(v * e)).collect();
        let (per_spring, none) = noise_variances(&own, &rest, StrainNoise::PerSpring, sigma);
        assert_eq!(none, None);
        assert_eq!(per_spring[2], own[2].unwrap());
        let (pooled, found) = noise_variances(&own, &rest, StrainNoise::Pooled, 0.0);
        // The median's spring is the one off by 1.05.
        let found = found.unwrap();
        assert!((found / sigma - 1.05f64.sqrt()).abs() < 1e-12, "σ {found}");
        for (p, e) in pooled.iter().zip(&exact) {
            assert!((p / e - 1.05).abs() < 1e-12, "{p} against {e}");
        }
        // A spring with no fourth difference seen still gets the shared noise; none seen at all
        // takes nothing out.
        own[4] = None;
        let (pooled, _) = noise_variances(&own, &rest, StrainNoise::Pooled, 0.0);
        assert!(pooled[4] > 0.0);
        let (nothing, sigma) =
            noise_variances(&[None, None], &rest[..2], StrainNoise::Pooled, sigma);
        assert_eq!((nothing, sigma), (vec![0.0, 0.0], None));
    }

    /// Stated, every spring's strain noise is `2σ²/l²` with the `σ` the run states, whatever
    /// the springs' own estimates hold (motion, on a simulator's frames); a run that states
    /// none (exact positions) takes nothing out.
    #[test]
    fn stated_strain_noise_is_the_runs_marker_noise_over_each_rest_length() {
        let rest = [0.05, 0.1, 0.2];
        let own = [Some(1e-4), Some(3e-3), None];
        let (stated, sigma) = noise_variances(&own, &rest, StrainNoise::Stated, 0.002);
        assert_eq!(sigma, Some(0.002));
        for (v, l) in stated.iter().zip(rest) {
            assert!(
                (v * l * l / (2.0 * 0.002 * 0.002) - 1.0).abs() < 1e-12,
                "{v} at {l}"
            );
        }
        let (exact, _) = noise_variances(&own, &rest, StrainNoise::Stated, 0.0);
        assert_eq!(exact, vec![0.0; 3]);
    }

    /// Within a group the map is the inverse of the strain; a spring that never stretches
    /// takes the group's median; the stiffest spring has `k_init`.
    #[test]
    fn stiffness_is_the_inverse_strain_scaled_to_the_initial_k() {
        let points: Vec<[f64; 2]> = (0..3)
            .flat_map(|j| (0..3).map(move |i| [i as f64 * 0.5, j as f64 * 0.5 + 0.01 * i as f64]))
            .collect();
        let topo = Topology::of_points(&points, 1.0, 1.01, false).expect("a mesh");
        let n = topo.num_springs();
        // Without hinge springs every spring is an edge of the mesh: one group, the cells'
        // sides (structural) and diagonals (shear) together.
        assert_eq!(strain_groups(&topo), vec![(0..n).collect::<Vec<_>>()]);
        assert!(topo.family.contains(&SpringFamily::Shear));
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

    /// A data mesh's edges share one group, sides and cut diagonal alike; its hinge springs
    /// are grouped by family. A grid's groups are its families.
    #[test]
    fn a_data_mesh_compares_its_edges_together_and_its_hinges_by_family() {
        let uv = [[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0], [2.0, 0.5]];
        let topo = Topology::mesh(&uv, &[[0, 1, 2], [0, 3, 2], [1, 4, 2]], 2.0, 1.0, true).unwrap();
        let springs =
            |g: &[usize]| -> Vec<[usize; 2]> { g.iter().map(|&s| topo.springs[s]).collect() };
        let groups: Vec<Vec<[usize; 2]>> =
            strain_groups(&topo).iter().map(|g| springs(g)).collect();
        let edges = vec![[0, 1], [0, 2], [0, 3], [1, 2], [1, 4], [2, 3], [2, 4]];
        assert_eq!(groups, vec![edges, vec![[1, 3]], vec![[0, 4]]]);
        assert_eq!(topo.family[1], SpringFamily::Shear, "0–2 cuts the square");
        let grid = Topology::grid(&crate::cloth::GridSpec::default(), 1.0, 1.0);
        for g in strain_groups(&grid) {
            assert!(g.iter().all(|&s| grid.family[s] == grid.family[g[0]]));
        }
        assert_eq!(strain_groups(&grid).len(), 3);
    }

    /// The mixed map averages the two maps' shapes within each group at the fit's group size;
    /// a group the fit leaves at zero takes the compliance map's shape at its size.
    #[test]
    fn the_mixed_map_averages_shapes_at_the_fits_size() {
        let uv = [[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0], [2.0, 0.5]];
        let topo = Topology::mesh(&uv, &[[0, 1, 2], [0, 3, 2], [1, 4, 2]], 2.0, 1.0, true).unwrap();
        let groups = strain_groups(&topo);
        let (edges, hinge) = (&groups[0], groups[1][0]);
        let mut fit = vec![0.0; topo.num_springs()];
        let mut compliance = vec![1.0; topo.num_springs()];
        // The edges: the fit at 10 but one at 40 (mean 100/7), the compliance map at 1 but
        // another at 8 (mean 2).
        for &s in edges {
            fit[s] = 10.0;
        }
        fit[edges[0]] = 40.0;
        compliance[edges[1]] = 8.0;
        let k = mixed(&topo, &fit, &compliance, &MapWeights::equal(&topo));
        let fit_mean = 100.0 / 7.0;
        let expect = |f: f64, c: f64| fit_mean * (f / fit_mean + c / 2.0) / 2.0;
        assert!((k[edges[0]] - expect(40.0, 1.0)).abs() < 1e-12);
        assert!((k[edges[1]] - expect(10.0, 8.0)).abs() < 1e-12);
        assert!((k[edges[2]] - expect(10.0, 1.0)).abs() < 1e-12);
        let edge_mean = edges.iter().map(|&s| k[s]).sum::<f64>() / edges.len() as f64;
        assert!(
            (edge_mean - fit_mean).abs() < 1e-12,
            "the fit's size is kept"
        );
        // A hinge group the fit left at zero: the compliance map's value.
        assert_eq!(k[hinge], 1.0);
        // Weighted: the edges' shapes weigh 1/4 (the fit's) and 3/4, at the fit's size still;
        // the hinge group, whose fit is at zero, the compliance map's whatever its weight.
        let mut weights = MapWeights::equal(&topo);
        for g in &mut weights.groups {
            g.fit_weight = 0.25;
        }
        let k = mixed(&topo, &fit, &compliance, &weights);
        let expect = |f: f64, c: f64| fit_mean * (0.25 * f / fit_mean + 0.75 * c / 2.0);
        assert!((k[edges[0]] - expect(40.0, 1.0)).abs() < 1e-12);
        assert!((k[edges[1]] - expect(10.0, 8.0)).abs() < 1e-12);
        let edge_mean = edges.iter().map(|&s| k[s]).sum::<f64>() / edges.len() as f64;
        assert!((edge_mean - fit_mean).abs() < 1e-12);
        assert_eq!(k[hinge], 1.0);
        // A map alone in its group has the whole weight even where its own is zero: the hinge
        // group, whose fit is at zero, with the compliance map weighing nothing.
        for g in &mut weights.groups {
            g.fit_weight = 1.0;
        }
        let k = mixed(&topo, &fit, &compliance, &weights);
        assert_eq!(k[hinge], 1.0);
        assert!((k[edges[0]] - 40.0).abs() < 1e-12, "the fit's shape alone");
    }

    /// The weights follow the halves' agreement: two maps whose halves agree alike weigh half
    /// each; a map whose halves rank its springs in opposite orders weighs nothing, and the
    /// other everything; `r` 0.8 against 0.4 weighs as `2r / (1 − r)`, 8 against 4/3.
    #[test]
    fn each_map_weighs_as_its_halves_agree() {
        let uv = [
            [0.0, 0.0],
            [1.0, 0.0],
            [1.0, 1.0],
            [0.0, 1.0],
            [2.0, 0.5],
            [2.0, 1.5],
        ];
        let tris = [[0, 1, 2], [0, 3, 2], [1, 4, 2], [2, 4, 5]];
        let topo = Topology::mesh(&uv, &tris, 2.0, 1.0, true).unwrap();
        let edges = &strain_groups(&topo)[0];
        let n = topo.num_springs();
        let rising: Vec<f64> = (0..n).map(|s| 1.0 + s as f64).collect();
        let falling: Vec<f64> = (0..n).map(|s| (n - s) as f64).collect();
        let w = MapWeights::from_halves(&topo, [&rising, &rising], [&rising, &rising]);
        assert_eq!(w.groups[0].fit_halves, Some(1.0));
        assert_eq!(w.groups[0].fit_weight, 0.5);
        let w = MapWeights::from_halves(&topo, [&rising, &falling], [&rising, &rising]);
        assert_eq!(w.groups[0].fit_halves, Some(-1.0));
        assert_eq!(w.groups[0].fit_weight, 0.0);
        let w = MapWeights::from_halves(&topo, [&rising, &rising], [&falling, &rising]);
        assert_eq!(w.groups[0].fit_weight, 1.0);
        // Neither agrees: half each.
        let w = MapWeights::from_halves(&topo, [&rising, &falling], [&falling, &rising]);
        assert_eq!(w.groups[0].fit_weight, 0.5);
        // A map constant on a half ranks nothing.
        let flat = vec![2.0; n];
        let w = MapWeights::from_halves(&topo, [&flat, &rising], [&rising, &rising]);
        assert_eq!(w.groups[0].fit_halves, Some(0.0));
        assert_eq!(w.groups[0].fit_weight, 0.0);
        assert_eq!(w.largest().unwrap().springs, edges.len());
        assert!((signal_to_error(0.8) - 8.0).abs() < 1e-12);
        assert!((signal_to_error(0.4) - 4.0 / 3.0).abs() < 1e-12);
        assert_eq!(signal_to_error(-0.3), 0.0);
        assert_eq!(signal_to_error(f64::NAN), 0.0);
    }

    /// A spring the data left at zero takes half its neighbours' mean in one round; springs of
    /// other strain groups (the hinge springs) neither enter the edges' means nor move; many
    /// rounds even a connected group out.
    #[test]
    fn smoothing_averages_each_spring_with_its_own_groups_neighbours() {
        let uv = [[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0], [2.0, 0.5]];
        let topo = Topology::mesh(&uv, &[[0, 1, 2], [0, 3, 2], [1, 4, 2]], 2.0, 1.0, true).unwrap();
        let groups = strain_groups(&topo);
        let edges = &groups[0];
        let hinges: Vec<usize> = groups[1..].concat();
        assert!(!hinges.is_empty());
        let mut k = vec![100.0; topo.num_springs()];
        for &s in edges {
            k[s] = 10.0;
        }
        k[edges[0]] = 0.0;
        assert_eq!(smoothed(&topo, &k, 0), k);
        let once = smoothed(&topo, &k, 1);
        assert_eq!(
            once[edges[0]], 5.0,
            "half its neighbours' mean, hinges left out"
        );
        for &s in &hinges {
            assert_eq!(once[s], 100.0);
        }
        for &s in &edges[1..] {
            let [a, b] = topo.springs[s];
            let touches = topo.springs[edges[0]].iter().any(|&p| p == a || p == b);
            assert_eq!(once[s] < 10.0, touches, "spring {s}");
            assert!(once[s] > 5.0);
        }
        let many = smoothed(&topo, &k, 200);
        let (lo, hi) = edges.iter().fold((f64::MAX, f64::MIN), |(lo, hi), &s| {
            (lo.min(many[s]), hi.max(many[s]))
        });
        assert!(hi - lo < 1e-9 && lo > 5.0 && hi < 10.0, "{lo}..{hi}");
        let constant = vec![3.0; topo.num_springs()];
        assert_eq!(smoothed(&topo, &constant, 3), constant);
    }
}
