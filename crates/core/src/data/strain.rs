//! How far the recorded cloth stretches: the relative length change of the landmarks' edges over
//! the frames of a dataset (`data check`). It is the first thing that decides what training can
//! identify: a cloth that hardly stretches constrains its stiffness hardly at all, and edges
//! stretched to several times their length (a single vertex carrying the cloth, a tear, a
//! tracking error) are motion that no spring network follows.

use super::rollout::Rollout;

/// Strains stored per file at most (frames are strided to stay below it).
const SAMPLES_PER_FILE: usize = 200_000;

/// Neighbours per landmark when the data has no mesh.
const NEIGHBOURS: usize = 4;

/// Landmark pairs whose length change is measured, with their rest lengths.
#[derive(Debug, Clone)]
pub struct Edges {
    /// Where the pairs come from: the mesh's edges or each landmark's nearest neighbours.
    pub from: &'static str,
    pairs: Vec<[usize; 2]>,
    rest: Vec<f64>,
}

impl Edges {
    /// The edges of the rollout's triangle mesh when it has one, else each landmark's
    /// four nearest landmarks in the rest rectangle; pairs of coinciding rest
    /// positions are left out.
    pub fn of(r: &Rollout) -> Edges {
        let uv = &r.rest_uv;
        let (from, mut pairs) = match &r.mesh {
            Some(mesh) => (
                "mesh edges",
                mesh.triangles
                    .iter()
                    .flat_map(|t| [[t[0], t[1]], [t[1], t[2]], [t[2], t[0]]])
                    .collect::<Vec<_>>(),
            ),
            None => (
                "each landmark's 4 nearest",
                (0..uv.len())
                    .flat_map(|i| nearest(uv, i).into_iter().map(move |j| [i, j]))
                    .collect(),
            ),
        };
        for p in &mut pairs {
            p.sort_unstable();
        }
        pairs.sort_unstable();
        pairs.dedup();
        let dist = |[a, b]: [usize; 2]| {
            ((uv[a][0] - uv[b][0]).powi(2) + (uv[a][1] - uv[b][1]).powi(2)).sqrt()
        };
        pairs.retain(|&p| dist(p) > 0.0);
        let rest = pairs.iter().map(|&p| dist(p)).collect();
        Edges { from, pairs, rest }
    }

    /// Number of edges.
    pub fn len(&self) -> usize {
        self.pairs.len()
    }

    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.pairs.is_empty()
    }

    /// Strains `|x_a − x_b| / l₀ − 1` of every edge in frames `0, s, 2s, …` of `r` (with `s`
    /// chosen to keep at most 200,000 strains; edges with a hidden end skipped), with the
    /// largest one and where it is.
    pub fn strains(&self, r: &Rollout, out: &mut Vec<f32>) -> Option<Peak> {
        if self.is_empty() {
            return None;
        }
        let stride = (r.frames * self.len()).div_ceil(SAMPLES_PER_FILE).max(1);
        let n = r.landmarks;
        let mut peak: Option<Peak> = None;
        for f in (0..r.frames).step_by(stride) {
            let x = &r.positions[f * n * 3..(f + 1) * n * 3];
            for (e, (&[a, b], &l0)) in self.pairs.iter().zip(&self.rest).enumerate() {
                if !(r.seen(f, a) && r.seen(f, b)) {
                    continue;
                }
                let d: f64 = (0..3)
                    .map(|c| (x[a * 3 + c] as f64 - x[b * 3 + c] as f64).powi(2))
                    .sum();
                let s = d.sqrt() / l0 - 1.0;
                out.push(s as f32);
                if peak.as_ref().is_none_or(|p| s > p.strain) {
                    peak = Some(Peak {
                        strain: s,
                        frame: f,
                        landmarks: self.pairs[e],
                    });
                }
            }
        }
        peak
    }
}

/// The largest strain of a file: its value, frame and the edge's landmarks.
#[derive(Debug, Clone)]
pub struct Peak {
    /// `l / l₀ − 1`.
    pub strain: f64,
    /// Frame index.
    pub frame: usize,
    /// The edge's two landmarks.
    pub landmarks: [usize; 2],
}

/// The strain distribution of a dataset.
#[derive(Debug, Clone)]
pub struct StrainSummary {
    /// Where the edges come from.
    pub edges_from: &'static str,
    /// Edges per frame.
    pub edges: usize,
    /// Strain samples summarised.
    pub samples: usize,
    /// Root mean square.
    pub rms: f64,
    /// 5th, 50th and 95th percentiles.
    pub p5: f64,
    /// Median.
    pub p50: f64,
    /// 95th percentile.
    pub p95: f64,
    /// 95th percentile of `|strain|`.
    pub abs_p95: f64,
    /// Share of the samples above [`OVERSTRETCHED`].
    pub overstretched: f64,
    /// The largest strain, its file name, frame and edge.
    pub max: Option<(Peak, String)>,
}

/// Strain of the landmark edges across the files of a set (which share landmarks, so the
/// first file's edges serve all).
#[derive(Debug, Default)]
pub struct StrainStats {
    edges: Option<Edges>,
    samples: Vec<f32>,
    max: Option<(Peak, String)>,
}

impl StrainStats {
    /// Adds a rollout's frames.
    pub fn add(&mut self, r: &Rollout) {
        let edges = self.edges.get_or_insert_with(|| Edges::of(r));
        if let Some(p) = edges.strains(r, &mut self.samples)
            && self.max.as_ref().is_none_or(|(m, _)| p.strain > m.strain)
        {
            let name = r
                .path
                .file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_default();
            self.max = Some((p, name));
        }
    }

    /// The summary, or `None` when there was nothing to measure.
    pub fn summary(mut self) -> Option<StrainSummary> {
        let edges = self.edges?;
        if self.samples.is_empty() {
            return None;
        }
        let n = self.samples.len();
        let rms = (self
            .samples
            .iter()
            .map(|&s| (s as f64).powi(2))
            .sum::<f64>()
            / n as f64)
            .sqrt();
        self.samples.sort_unstable_by(f32::total_cmp);
        let at = |v: &[f32], q: f64| v[((q * (n - 1) as f64).round() as usize).min(n - 1)] as f64;
        let (p5, p50, p95) = (
            at(&self.samples, 0.05),
            at(&self.samples, 0.5),
            at(&self.samples, 0.95),
        );
        let mut abs: Vec<f32> = self.samples.iter().map(|s| s.abs()).collect();
        abs.sort_unstable_by(f32::total_cmp);
        Some(StrainSummary {
            edges_from: edges.from,
            edges: edges.len(),
            samples: n,
            rms,
            p5,
            p50,
            p95,
            abs_p95: at(&abs, 0.95),
            overstretched: (n - self.samples.partition_point(|&s| s as f64 <= OVERSTRETCHED))
                as f64
                / n as f64,
            max: self.max,
        })
    }
}

/// Below this 95th percentile of `|strain|` the cloth counts as barely stretching.
pub(crate) const BARELY_STRETCHES: f64 = 0.005;

/// Above this strain an edge is more than twice its rest length.
pub const OVERSTRETCHED: f64 = 1.0;

/// Above this share of overstretched edge samples the data is flagged.
pub(crate) const OVERSTRETCHED_SHARE: f64 = 1e-3;

impl StrainSummary {
    /// What the distribution means for training, one warning a line (none when it is ordinary).
    pub fn warnings(&self) -> Vec<String> {
        let mut out = Vec::new();
        if self.abs_p95 < BARELY_STRETCHES {
            out.push(format!(
                "the cloth barely stretches (95 % of edge strains within ±{:.2} %): its stiffness \
                 is hardly observable from this motion and the learned k will stay near its \
                 initial value (`springtime diagnose` draws the observability map)",
                100.0 * self.abs_p95
            ));
        }
        if let Some((p, file)) = &self.max
            && self.overstretched > OVERSTRETCHED_SHARE
        {
            out.push(format!(
                "{:.2} % of the edge samples are stretched past twice their rest length, up to \
                 {:.1}× ({file}, frame {}, landmarks {} and {}): a vertex carrying the cloth \
                 alone, a tear or a tracking error; no spring network follows that, and it \
                 dominates the force loss near it",
                100.0 * self.overstretched,
                1.0 + p.strain,
                p.frame,
                p.landmarks[0],
                p.landmarks[1]
            ));
        }
        out
    }

    /// One line for `data check`.
    pub fn line(&self) -> String {
        let pct = |v: f64| format!("{:.2} %", 100.0 * v);
        let max = match &self.max {
            Some((p, file)) => format!("{} ({file}, frame {})", pct(p.strain), p.frame),
            None => "—".to_string(),
        };
        format!(
            "{} edges ({}): rms {}, 5 / 50 / 95 % {} / {} / {}, over 100 % {:.3} %, max {max}",
            self.edges,
            self.edges_from,
            pct(self.rms),
            pct(self.p5),
            pct(self.p50),
            pct(self.p95),
            100.0 * self.overstretched
        )
    }
}

/// The [`NEIGHBOURS`] landmarks nearest to landmark `i` in the rest rectangle (the resampler's
/// search, which counts `i` itself).
fn nearest(uv: &[[f64; 2]], i: usize) -> Vec<usize> {
    crate::cloth::resample::nearest(uv, uv[i], (NEIGHBOURS + 1).min(uv.len()))
        .into_iter()
        .filter(|&j| j != i)
        .take(NEIGHBOURS)
        .collect()
}

#[cfg(test)]
mod tests {
    use super::super::rollout::{MeshTruth, Segment};
    use super::*;

    /// A 5 × 4 sheet of 2 m × 1.5 m whose frame `f` places landmark `(i, j)` at `at(f, u, v)`.
    fn sheet(frames: usize, mesh: bool, at: impl Fn(usize, f64, f64) -> [f64; 3]) -> Rollout {
        let (nx, ny) = (5, 4);
        let rest_uv: Vec<[f64; 2]> = (0..ny)
            .flat_map(|j| (0..nx).map(move |i| [i as f64 * 0.5, j as f64 * 0.5]))
            .collect();
        let mut positions = Vec::with_capacity(frames * nx * ny * 3);
        for f in 0..frames {
            for p in &rest_uv {
                positions.extend(at(f, p[0], p[1]).map(|v| v as f32));
            }
        }
        let triangles = (0..ny - 1)
            .flat_map(|j| {
                (0..nx - 1).flat_map(move |i| {
                    let a = j * nx + i;
                    [[a, a + 1, a + nx + 1], [a, a + nx + 1, a + nx]]
                })
            })
            .collect::<Vec<_>>();
        Rollout {
            path: "sheet.npz".into(),
            frames,
            landmarks: nx * ny,
            positions,
            velocities: None,
            rest_uv,
            pinned: vec![false; nx * ny],
            frame_dt: 0.01,
            total_mass: 1.0,
            width: 2.0,
            height: 1.5,
            segments: vec![Segment {
                start: 0,
                offset: 0,
                len: frames,
            }],
            springs: None,
            mesh: mesh.then(|| MeshTruth {
                stiffness: Some(vec![1.0; triangles.len()]),
                triangles,
            }),
            gravity: None,
            rayleigh: None,
            position_noise: None,
            visible: None,
        }
    }

    fn summary(r: &Rollout) -> StrainSummary {
        let mut stats = StrainStats::default();
        stats.add(r);
        stats.summary().expect("edges")
    }

    #[test]
    fn a_rigid_motion_has_no_strain_and_is_flagged_as_unobservable() {
        for mesh in [true, false] {
            let r = sheet(6, mesh, |f, u, v| {
                let (s, c) = (0.3 * f as f64).sin_cos();
                [c * u - s * v + f as f64, s * u + c * v, 2.0]
            });
            let s = summary(&r);
            assert!(s.rms < 1e-6 && s.abs_p95 < 1e-6, "{s:?}");
            let w = s.warnings();
            assert_eq!(w.len(), 1, "{w:?}");
            assert!(w[0].contains("barely stretches"));
        }
    }

    #[test]
    fn a_uniform_stretch_is_measured_and_not_flagged() {
        // 10 % along x: horizontal edges stretch by 0.1, vertical ones not at all.
        let r = sheet(3, true, |_, u, v| [1.1 * u, v, 0.0]);
        let s = summary(&r);
        assert_eq!(s.edges_from, "mesh edges");
        assert!((s.max.as_ref().unwrap().0.strain - 0.1).abs() < 1e-6);
        assert!(s.p5.abs() < 1e-6, "{s:?}");
        assert!(s.warnings().is_empty(), "{:?}", s.warnings());
        let knn = summary(&sheet(3, false, |_, u, v| [1.1 * u, v, 0.0]));
        assert_eq!(knn.edges_from, "each landmark's 4 nearest");
        assert!((knn.max.unwrap().0.strain - 0.1).abs() < 1e-6);
    }

    #[test]
    fn an_edge_pulled_to_several_times_its_length_is_named() {
        // Landmark 7 dragged 3 m away in every frame after the first.
        let r = sheet(4, true, |f, u, v| {
            let moved = f > 0 && (u - 1.0).abs() < 1e-9 && (v - 0.5).abs() < 1e-9;
            [u, v, if moved { 3.0 } else { 0.0 }]
        });
        let s = summary(&r);
        let (peak, file) = s.max.clone().unwrap();
        assert!(peak.landmarks.contains(&7) && peak.frame > 0 && file == "sheet.npz");
        let w = s.warnings();
        assert!(
            w.iter()
                .any(|l| l.contains("past twice their rest length") && l.contains("sheet.npz")),
            "{w:?}"
        );
    }
}
