//! Landmarks to particles (paper §3.1, Eq. 3): each surrogate particle takes the barycentric
//! combination of its three nearest landmarks in the rest rectangle.
//!
//! Works for any landmark set (no mesh needed). A particle that coincides with a landmark copies
//! it; a nearest triple that is (nearly) collinear is replaced by the nearest non-collinear
//! triple among the closest candidates; if every candidate is collinear, the particle is
//! interpolated along the line through its two nearest landmarks.

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

/// How many nearest landmarks are searched for a non-degenerate triangle.
const CANDIDATES: usize = 12;

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
        let mut index = Vec::with_capacity(particles.len());
        let mut weight = Vec::with_capacity(particles.len());
        for &p in particles {
            let near = nearest(landmarks, p, CANDIDATES.min(landmarks.len()));
            let (i, w) = weights_for(landmarks, p, &near, scale);
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
    pub fn is_identity(&self, landmarks: usize) -> bool {
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
    pub fn apply1(&self, src: &[f64]) -> Vec<f64> {
        self.index
            .iter()
            .zip(&self.weight)
            .map(|(idx, w)| (0..3).map(|j| w[j] * src[idx[j]]).sum())
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

fn bbox_diagonal(points: &[[f64; 2]]) -> f64 {
    let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
    for p in points {
        for c in 0..2 {
            lo[c] = lo[c].min(p[c]);
            hi[c] = hi[c].max(p[c]);
        }
    }
    ((hi[0] - lo[0]).powi(2) + (hi[1] - lo[1]).powi(2)).sqrt()
}

fn dist2(a: [f64; 2], b: [f64; 2]) -> f64 {
    (a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2)
}

/// Indices of the `k` landmarks nearest to `p`, nearest first (ties by index).
fn nearest(landmarks: &[[f64; 2]], p: [f64; 2], k: usize) -> Vec<usize> {
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

fn weights_for(
    landmarks: &[[f64; 2]],
    p: [f64; 2],
    near: &[usize],
    scale: f64,
) -> ([usize; 3], [f64; 3]) {
    let a = near[0];
    if dist2(landmarks[a], p) <= (1e-9 * scale).powi(2) {
        return ([a, near[1], near[2]], [1.0, 0.0, 0.0]);
    }
    let b = near[1];
    // The nearest third landmark that makes a triangle of non-negligible area with a and b.
    let area_tol = 1e-6 * scale * scale;
    for &c in &near[2..] {
        let (pa, pb, pc) = (landmarks[a], landmarks[b], landmarks[c]);
        let det = (pb[0] - pa[0]) * (pc[1] - pa[1]) - (pc[0] - pa[0]) * (pb[1] - pa[1]);
        if det.abs() > area_tol {
            let wb = ((p[0] - pa[0]) * (pc[1] - pa[1]) - (pc[0] - pa[0]) * (p[1] - pa[1])) / det;
            let wc = ((pb[0] - pa[0]) * (p[1] - pa[1]) - (p[0] - pa[0]) * (pb[1] - pa[1])) / det;
            return ([a, b, c], [1.0 - wb - wc, wb, wc]);
        }
    }
    // Every candidate is collinear with a and b: interpolate along the line a–b.
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
