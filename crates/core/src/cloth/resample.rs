//! Landmarks to particles (paper §3.1, Eq. 3): each surrogate particle takes the barycentric
//! combination of three landmarks around it in the rest rectangle.
//!
//! Works for any landmark set (no mesh needed): the landmarks' rest positions are triangulated
//! (Delaunay, by the `delaunator` crate) and a particle takes the weights of the triangle that
//! holds it, so the resampled positions are one continuous piecewise-linear field. (The paper's
//! three *nearest* landmarks make a field that jumps between neighbouring particles and, on an
//! irregular mesh, sliver triples whose weights reach ±40: a folded sheet then gains strains of
//! 100 % that are not in the data, and the target forces follow them.) A particle that coincides
//! with a landmark (to the f32 rounding of stored rest positions) copies it; one outside the
//! landmarks' hull takes the nearest triangle's weights (a short extrapolation); if the landmarks
//! are collinear, a particle is interpolated along the line through its two nearest landmarks.

/// Per-particle landmark indices and weights (rows sum to 1).
#[derive(Debug, Clone, PartialEq)]
pub struct Resampler {
    /// Three landmark indices per particle.
    pub index: Vec<[usize; 3]>,
    /// Their barycentric weights.
    pub weight: Vec<[f64; 3]>,
    /// The particle nearest to each landmark (ties by index).
    pub nearest_particle: Vec<usize>,
}

/// A particle this close to a landmark, as a fraction of the landmarks' bounding-box diagonal,
/// copies it. Files store `rest_uv` in f32, whose rounding (up to 6e-8 of a coordinate) puts a
/// grid's vertices at spacings like 1/6 m that far off the surrogate's f64 grid over them.
const COINCIDENT: f64 = 1e-6;

/// Triangles of area below this fraction of the bounding box's squared diagonal are dropped.
const SLIVER: f64 = 1e-9;

impl Resampler {
    /// Weights mapping `landmarks` (rest positions) to `particles` (rest positions).
    ///
    /// Panics if there are fewer than 3 landmarks (rollout loading rejects such files).
    pub fn new(landmarks: &[[f64; 2]], particles: &[[f64; 2]]) -> Self {
        assert!(
            landmarks.len() >= 3,
            "resampling needs at least 3 landmarks"
        );
        let scale = bbox_diagonal(landmarks).max(f64::MIN_POSITIVE);
        let mesh = Locator::new(landmarks, scale);
        let mut index = Vec::with_capacity(particles.len());
        let mut weight = Vec::with_capacity(particles.len());
        for &p in particles {
            let near = nearest(landmarks, p, 3);
            let (i, w) = if dist2(landmarks[near[0]], p) <= (COINCIDENT * scale).powi(2) {
                ([near[0], near[1], near[2]], [1.0, 0.0, 0.0])
            } else if let Some(found) = mesh.locate(p) {
                found
            } else {
                along_line(landmarks, p, &near)
            };
            index.push(i);
            weight.push(w);
        }
        let nearest_particle = landmarks
            .iter()
            .map(|&l| nearest(particles, l, 1)[0])
            .collect();
        Self {
            index,
            weight,
            nearest_particle,
        }
    }

    /// Whether every particle copies exactly one landmark (the identity map when the grids agree).
    pub fn is_exact(&self) -> bool {
        self.weight.iter().all(|w| w[0] == 1.0)
    }

    /// Whether particle `p` copies landmark `p` for every `p` of `landmarks` landmarks.
    pub(crate) fn is_identity(&self, landmarks: usize) -> bool {
        self.index.len() == landmarks
            && self
                .index
                .iter()
                .zip(&self.weight)
                .enumerate()
                .all(|(p, (i, w))| i[0] == p && w[0] == 1.0)
    }

    /// Number of particles.
    pub fn num_particles(&self) -> usize {
        self.index.len()
    }

    /// Resamples per-landmark 3-vectors `[N, 3]` (row-major) to particles `[P, 3]`, in f64.
    pub fn apply3(&self, src: &[f32], out: &mut [f64]) {
        for (p, (idx, w)) in self.index.iter().zip(&self.weight).enumerate() {
            for c in 0..3 {
                out[p * 3 + c] = (0..3).map(|j| w[j] * src[idx[j] * 3 + c] as f64).sum();
            }
        }
    }

    /// Resamples a per-landmark scalar.
    pub(crate) fn apply1(&self, src: &[f64]) -> Vec<f64> {
        self.index
            .iter()
            .zip(&self.weight)
            .map(|(idx, w)| (0..3).map(|j| w[j] * src[idx[j]]).sum())
            .collect()
    }

    /// Seen particles of one frame, from its seen landmarks: a particle is seen where every
    /// landmark it takes a share of is.
    pub fn visible(&self, landmark_seen: &[bool]) -> Vec<bool> {
        self.index
            .iter()
            .zip(&self.weight)
            .map(|(idx, w)| (0..3).all(|j| w[j] == 0.0 || landmark_seen[idx[j]]))
            .collect()
    }

    /// Pinned particles: those whose interpolated pin flag is at least one half, and the
    /// particle nearest to each pinned landmark.
    ///
    /// The second rule keeps every pin of the data: a user's simulator often pins single
    /// vertices, which a coarser or shifted particle grid would otherwise miss, leaving the
    /// surrogate's cloth to fall where the data's hangs.
    pub fn pinned(&self, landmark_pinned: &[bool]) -> Vec<bool> {
        let flags: Vec<f64> = landmark_pinned.iter().map(|&p| p as u8 as f64).collect();
        let mut pinned: Vec<bool> = self.apply1(&flags).into_iter().map(|f| f >= 0.5).collect();
        for (l, _) in landmark_pinned.iter().enumerate().filter(|(_, p)| **p) {
            pinned[self.nearest_particle[l]] = true;
        }
        pinned
    }
}

/// Smallest and largest coordinates of `points`.
fn bbox(points: &[[f64; 2]]) -> ([f64; 2], [f64; 2]) {
    let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
    for p in points {
        for c in 0..2 {
            lo[c] = lo[c].min(p[c]);
            hi[c] = hi[c].max(p[c]);
        }
    }
    (lo, hi)
}

fn bbox_diagonal(points: &[[f64; 2]]) -> f64 {
    let (lo, hi) = bbox(points);
    ((hi[0] - lo[0]).powi(2) + (hi[1] - lo[1]).powi(2)).sqrt()
}

fn dist2(a: [f64; 2], b: [f64; 2]) -> f64 {
    (a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2)
}

/// Indices of the `k` landmarks nearest to `p`, nearest first (ties by index).
pub(crate) fn nearest(landmarks: &[[f64; 2]], p: [f64; 2], k: usize) -> Vec<usize> {
    let mut best: Vec<(f64, usize)> = Vec::with_capacity(k + 1);
    for (i, &l) in landmarks.iter().enumerate() {
        let d = dist2(l, p);
        if best.len() < k || d < best[best.len() - 1].0 {
            let at = best.partition_point(|&(bd, _)| bd <= d);
            best.insert(at, (d, i));
            best.truncate(k);
        }
    }
    best.into_iter().map(|(_, i)| i).collect()
}

/// The landmarks' triangulation, bucketed on a uniform grid for point location.
struct Locator<'a> {
    points: &'a [[f64; 2]],
    triangles: Vec<[usize; 3]>,
    lo: [f64; 2],
    cell: f64,
    cells: [usize; 2],
    buckets: Vec<Vec<u32>>,
}

impl<'a> Locator<'a> {
    /// Delaunay triangles of `points` without slivers, each listed in every grid cell its
    /// bounding box touches.
    fn new(points: &'a [[f64; 2]], scale: f64) -> Self {
        let triangles = delaunay(points);
        let (lo, hi) = bbox(points);
        let side = (triangles.len().max(1) as f64).sqrt().ceil() as usize;
        let cell = ((hi[0] - lo[0]).max(hi[1] - lo[1]) / side as f64).max(scale * 1e-12);
        let cells = [
            ((hi[0] - lo[0]) / cell).floor() as usize + 1,
            ((hi[1] - lo[1]) / cell).floor() as usize + 1,
        ];
        let mut buckets = vec![Vec::new(); cells[0] * cells[1]];
        for (n, t) in triangles.iter().enumerate() {
            let (mut a, mut b) = ([usize::MAX; 2], [0usize; 2]);
            for &v in t {
                for c in 0..2 {
                    let i = ((points[v][c] - lo[c]) / cell).floor() as usize;
                    a[c] = a[c].min(i.min(cells[c] - 1));
                    b[c] = b[c].max(i.min(cells[c] - 1));
                }
            }
            for y in a[1]..=b[1] {
                for x in a[0]..=b[0] {
                    buckets[y * cells[0] + x].push(n as u32);
                }
            }
        }
        Self {
            points,
            triangles,
            lo,
            cell,
            cells,
            buckets,
        }
    }

    /// The triangle holding `p` and its barycentric weights: among the candidates, the one whose
    /// smallest weight is largest (non-negative inside the hull; outside it, the nearest
    /// triangle, extrapolated). `None` when the landmarks are collinear.
    fn locate(&self, p: [f64; 2]) -> Option<([usize; 3], [f64; 3])> {
        let cell = |c: usize| {
            (((p[c] - self.lo[c]) / self.cell).floor().max(0.0) as usize).min(self.cells[c] - 1)
        };
        let best = |candidates: &mut dyn Iterator<Item = usize>| {
            candidates
                .map(|n| {
                    let t = self.triangles[n];
                    let w = barycentric(self.points, t, p);
                    (w[0].min(w[1]).min(w[2]), t, w)
                })
                .max_by(|a, b| a.0.total_cmp(&b.0))
        };
        let bucket = &self.buckets[cell(1) * self.cells[0] + cell(0)];
        match best(&mut bucket.iter().map(|&n| n as usize)) {
            Some((min, t, w)) if min >= -1e-12 => Some((t, w)),
            _ => best(&mut (0..self.triangles.len())).map(|(_, t, w)| (t, w)),
        }
    }
}

/// The Delaunay triangles of `points` (by `delaunator`), counter-clockwise, without slivers
/// (twice the area below `SLIVER` times the bounding box's squared diagonal).
pub(crate) fn delaunay(points: &[[f64; 2]]) -> Vec<[usize; 3]> {
    let scale = bbox_diagonal(points).max(f64::MIN_POSITIVE);
    let pts: Vec<delaunator::Point> = points
        .iter()
        .map(|p| delaunator::Point { x: p[0], y: p[1] })
        .collect();
    delaunator::triangulate(&pts)
        .triangles
        .chunks_exact(3)
        .map(|t| {
            let t = [t[0], t[1], t[2]];
            if twice_area(points, t) < 0.0 {
                [t[0], t[2], t[1]]
            } else {
                t
            }
        })
        .filter(|t| twice_area(points, *t).abs() > SLIVER * scale * scale)
        .collect()
}

/// Twice the signed area of triangle `t` (positive when counter-clockwise).
pub fn twice_area(points: &[[f64; 2]], t: [usize; 3]) -> f64 {
    let (a, b, c) = (points[t[0]], points[t[1]], points[t[2]]);
    (b[0] - a[0]) * (c[1] - a[1]) - (c[0] - a[0]) * (b[1] - a[1])
}

/// Barycentric weights of `p` in triangle `t` (they sum to 1; all non-negative inside).
fn barycentric(points: &[[f64; 2]], t: [usize; 3], p: [f64; 2]) -> [f64; 3] {
    let (a, b, c) = (points[t[0]], points[t[1]], points[t[2]]);
    let det = twice_area(points, t);
    let wb = ((p[0] - a[0]) * (c[1] - a[1]) - (c[0] - a[0]) * (p[1] - a[1])) / det;
    let wc = ((b[0] - a[0]) * (p[1] - a[1]) - (p[0] - a[0]) * (b[1] - a[1])) / det;
    [1.0 - wb - wc, wb, wc]
}

/// Collinear landmarks: interpolation along the line through the two nearest, `near[0..2]`.
fn along_line(landmarks: &[[f64; 2]], p: [f64; 2], near: &[usize]) -> ([usize; 3], [f64; 3]) {
    let (a, b) = (near[0], near[1]);
    let (pa, pb) = (landmarks[a], landmarks[b]);
    let len2 = dist2(pa, pb).max(f64::MIN_POSITIVE);
    let t = ((p[0] - pa[0]) * (pb[0] - pa[0]) + (p[1] - pa[1]) * (pb[1] - pa[1])) / len2;
    ([a, b, near[2]], [1.0 - t, t, 0.0])
}

#[cfg(test)]
mod tests {
    use super::*;

    fn grid(nx: usize, ny: usize, w: f64, h: f64) -> Vec<[f64; 2]> {
        (0..ny)
            .flat_map(|r| {
                (0..nx).map(move |c| {
                    [
                        c as f64 * w / (nx - 1) as f64,
                        r as f64 * h / (ny - 1) as f64,
                    ]
                })
            })
            .collect()
    }

    #[test]
    fn identity_when_landmarks_are_the_particles() {
        let g = grid(5, 4, 2.0, 1.5);
        let r = Resampler::new(&g, &g);
        assert!(r.is_exact() && r.is_identity(g.len()));
        assert!(!Resampler::new(&g, &g[1..]).is_identity(g.len() - 1));
        for (p, idx) in r.index.iter().enumerate() {
            assert_eq!(idx[0], p);
        }
    }

    #[test]
    fn single_pinned_vertices_of_a_finer_mesh_pin_their_nearest_particles() {
        // A user's simulator pins two single vertices of a 21 × 21 mesh; a 16 × 16 surrogate has
        // no particle there, and the interpolated flag is below one half everywhere.
        let landmarks = grid(21, 21, 2.0, 2.0);
        let particles = grid(16, 16, 2.0, 2.0);
        let r = Resampler::new(&landmarks, &particles);
        let mut flags = vec![false; landmarks.len()];
        let (a, b) = (21 * 20 + 2, 21 * 6 + 20); // top edge at x = 0.2; right edge at y = 0.6
        flags[a] = true;
        flags[b] = true;
        let interpolated = r.apply1(&flags.iter().map(|&f| f as u8 as f64).collect::<Vec<_>>());
        assert!(
            interpolated.iter().all(|&f| f < 0.5),
            "the old rule would pin nothing"
        );
        let pinned = r.pinned(&flags);
        assert_eq!(pinned.iter().filter(|&&p| p).count(), 2);
        for l in [a, b] {
            let p = r.nearest_particle[l];
            assert!(pinned[p]);
            assert!(dist2(particles[p], landmarks[l]).sqrt() <= 2.0 / 15.0 * 0.75);
        }
    }

    #[test]
    fn weights_sum_to_one_and_reproduce_affine_fields() {
        // Barycentric weights reproduce any affine function of the rest position exactly.
        let src = grid(7, 7, 3.0, 3.0);
        let dst = grid(8, 8, 3.0, 3.0);
        let r = Resampler::new(&src, &dst);
        let f = |p: [f64; 2]| 0.3 + 1.7 * p[0] - 0.4 * p[1];
        let values: Vec<f64> = src.iter().map(|&p| f(p)).collect();
        let out = r.apply1(&values);
        for (p, w) in dst.iter().zip(&r.weight) {
            assert!((w.iter().sum::<f64>() - 1.0).abs() < 1e-12);
            let _ = p;
        }
        for (p, v) in dst.iter().zip(out) {
            assert!((f(*p) - v).abs() < 1e-9, "{p:?}");
        }
    }

    #[test]
    fn irregular_landmarks_give_a_continuous_field_without_extrapolation() {
        // A jittered 13 × 13 mesh resampled to 16 × 16 particles: every particle lies in a
        // triangle of the landmarks, so its weights are in [0, 1] (the three nearest landmarks
        // made sliver triples with weights beyond ±10 here), and a smooth fold of the sheet
        // (no stretch along x) gives the particles' springs along x no spurious strain beyond
        // the interpolation error of a curved surface.
        let mut rng = 0x2545_f491_4f6c_dd1du64;
        let mut jitter = || {
            rng ^= rng << 13;
            rng ^= rng >> 7;
            rng ^= rng << 17;
            (rng >> 11) as f64 / (1u64 << 53) as f64 - 0.5
        };
        let h = 4.0 / 12.0;
        let landmarks: Vec<[f64; 2]> = grid(13, 13, 4.0, 4.0)
            .into_iter()
            .map(|p| {
                let inner = |v: f64| v > 1e-9 && v < 4.0 - 1e-9;
                if inner(p[0]) && inner(p[1]) {
                    [p[0] + 0.5 * h * jitter(), p[1] + 0.5 * h * jitter()]
                } else {
                    p
                }
            })
            .collect();
        let particles = grid(16, 16, 4.0, 4.0);
        let r = Resampler::new(&landmarks, &particles);
        for w in &r.weight {
            assert!(
                w.iter().all(|&x| (-1e-9..=1.0 + 1e-9).contains(&x)),
                "{w:?}"
            );
            assert!((w.iter().sum::<f64>() - 1.0).abs() < 1e-12);
        }
        // The sheet rolled around the y axis into a cylinder of radius 1 m: lengths along x
        // are arc lengths, so a spring along x of the particles spans a chord of its rest length.
        let fold = |p: [f64; 2]| [p[0].sin(), p[1], 1.0 - p[0].cos()];
        let src: Vec<f32> = landmarks
            .iter()
            .flat_map(|&p| fold(p))
            .map(|v| v as f32)
            .collect();
        let mut out = vec![0.0; particles.len() * 3];
        r.apply3(&src, &mut out);
        let spacing: f64 = 4.0 / 15.0;
        let mut worst: f64 = 0.0;
        for j in 0..16 {
            for i in 0..15 {
                let (a, b) = (j * 16 + i, j * 16 + i + 1);
                let d: f64 = (0..3)
                    .map(|c| (out[a * 3 + c] - out[b * 3 + c]).powi(2))
                    .sum();
                let chord = 2.0 * (spacing / 2.0).sin();
                worst = worst.max((d.sqrt() / chord - 1.0).abs());
            }
        }
        // Linear interpolation of a unit-radius arc over landmark spacing ≤ 1.5 h moves points
        // inwards by at most (1.5 h)² / 8 ≈ 0.03 m.
        assert!(worst < 0.15, "spurious strain {worst}");
    }

    #[test]
    fn collinear_landmarks_do_not_divide_by_zero() {
        let line: Vec<[f64; 2]> = (0..6).map(|i| [i as f64, 0.0]).collect();
        let r = Resampler::new(&line, &[[2.5, 0.0], [0.2, 0.0]]);
        for w in &r.weight {
            assert!(w.iter().all(|x| x.is_finite()));
            assert!((w.iter().sum::<f64>() - 1.0).abs() < 1e-12);
        }
        let out = r.apply1(&line.iter().map(|p| p[0]).collect::<Vec<_>>());
        assert!((out[0] - 2.5).abs() < 1e-12 && (out[1] - 0.2).abs() < 1e-12);
    }
}
