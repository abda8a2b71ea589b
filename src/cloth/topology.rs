//! The surrogate's spring network on a regular grid (paper §3.1, Fig. 5).
//!
//! Particle `p = row * nx + col` sits at rest at `(col * hx, row * hy)` in the unrolled
//! `width × height` rectangle, `hx = width / (nx - 1)`, `hy = height / (ny - 1)`. Springs join
//! grid neighbours: structural (horizontal, vertical), shear (the two diagonals, each
//! switchable) and bending (stride `bending_stride` horizontally and vertically, 0 = none).

use serde::{Deserialize, Serialize};

/// How a grid of springs is laid out: the `[cloth]` section of a config.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct GridSpec {
    /// Particles along the rectangle's width (x, columns).
    pub nx: usize,
    /// Particles along the rectangle's height (y, rows).
    pub ny: usize,
    /// Shear springs along the main diagonal, `(r, c) – (r+1, c+1)`.
    pub shear_main: bool,
    /// Shear springs along the anti-diagonal, `(r, c+1) – (r+1, c)`.
    pub shear_anti: bool,
    /// Stride of the bending springs in grid steps (the paper uses 2); 0 disables them.
    pub bending_stride: usize,
}

impl Default for GridSpec {
    /// The paper's surrogate: 32 × 32 particles, both shear diagonals, stride-2 bending.
    fn default() -> Self {
        Self {
            nx: 32,
            ny: 32,
            shear_main: true,
            shear_anti: true,
            bending_stride: 2,
        }
    }
}

/// The kind of a spring, for reports and per-family metrics.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SpringFamily {
    /// Grid edges (horizontal and vertical).
    Structural,
    /// Cell diagonals.
    Shear,
    /// Stride-`n` horizontal and vertical springs that resist bending.
    Bending,
}

impl SpringFamily {
    /// Short name used in files and tables.
    pub fn name(self) -> &'static str {
        match self {
            SpringFamily::Structural => "structural",
            SpringFamily::Shear => "shear",
            SpringFamily::Bending => "bending",
        }
    }

    /// Integer code stored in `.npz` files (0 structural, 1 shear, 2 bending).
    pub fn code(self) -> i32 {
        match self {
            SpringFamily::Structural => 0,
            SpringFamily::Shear => 1,
            SpringFamily::Bending => 2,
        }
    }
}

/// A mass-spring network over a rectangle: particles at rest, springs, rest lengths.
#[derive(Debug, Clone)]
pub struct Topology {
    /// Particles along x.
    pub nx: usize,
    /// Particles along y.
    pub ny: usize,
    /// Rectangle width in metres.
    pub width: f64,
    /// Rectangle height in metres.
    pub height: f64,
    /// Rest position of every particle in the rectangle, `[P]` of `(u, v)` in metres.
    pub rest_uv: Vec<[f64; 2]>,
    /// Spring endpoints `(a, b)`; the force of Eq. 4 acts on `a` and its opposite on `b`.
    pub springs: Vec<[usize; 2]>,
    /// Rest length of every spring (its length in the rest rectangle).
    pub rest_length: Vec<f64>,
    /// Family of every spring.
    pub family: Vec<SpringFamily>,
}

impl Topology {
    /// Builds the grid network of `spec` over a `width × height` rectangle.
    ///
    /// Panics if the grid has fewer than 2 particles along a side or the rectangle is not
    /// positive: configs are validated before they get here.
    pub fn grid(spec: &GridSpec, width: f64, height: f64) -> Self {
        let (nx, ny) = (spec.nx, spec.ny);
        assert!(nx >= 2 && ny >= 2, "a grid needs at least 2 x 2 particles");
        assert!(
            width > 0.0 && height > 0.0,
            "the rectangle must have a positive size"
        );
        let (hx, hy) = (width / (nx - 1) as f64, height / (ny - 1) as f64);
        let id = |r: usize, c: usize| r * nx + c;
        let rest_uv = (0..ny)
            .flat_map(|r| (0..nx).map(move |c| [c as f64 * hx, r as f64 * hy]))
            .collect();
        let mut springs = Vec::new();
        let mut family = Vec::new();
        let mut add = |fam: SpringFamily, dr: usize, dc0: usize, dc1: usize| {
            // Springs from (r, c + dc0) to (r + dr, c + dc1) for every cell where both exist.
            let span = dc0.max(dc1);
            for r in 0..ny.saturating_sub(dr) {
                for c in 0..nx.saturating_sub(span) {
                    springs.push([id(r, c + dc0), id(r + dr, c + dc1)]);
                    family.push(fam);
                }
            }
        };
        add(SpringFamily::Structural, 0, 0, 1);
        add(SpringFamily::Structural, 1, 0, 0);
        if spec.shear_main {
            add(SpringFamily::Shear, 1, 0, 1);
        }
        if spec.shear_anti {
            add(SpringFamily::Shear, 1, 1, 0);
        }
        let s = spec.bending_stride;
        if s > 0 {
            add(SpringFamily::Bending, 0, 0, s);
            add(SpringFamily::Bending, s, 0, 0);
        }
        let mut topo = Self {
            nx,
            ny,
            width,
            height,
            rest_uv,
            springs,
            rest_length: Vec::new(),
            family,
        };
        topo.rest_length = topo
            .springs
            .iter()
            .map(|&[a, b]| distance(topo.rest_uv[a], topo.rest_uv[b]))
            .collect();
        topo
    }

    /// Number of particles `P`.
    pub fn num_particles(&self) -> usize {
        self.rest_uv.len()
    }

    /// Number of springs `S`.
    pub fn num_springs(&self) -> usize {
        self.springs.len()
    }

    /// Rest midpoint of spring `s` in the rectangle.
    pub fn midpoint(&self, s: usize) -> [f64; 2] {
        let [a, b] = self.springs[s];
        let (pa, pb) = (self.rest_uv[a], self.rest_uv[b]);
        [0.5 * (pa[0] + pb[0]), 0.5 * (pa[1] + pb[1])]
    }

    /// Rest positions in 3-D: the rectangle in the z = 0 plane, `[P]` of `(x, y, 0)`.
    pub fn rest_positions(&self) -> Vec<[f64; 3]> {
        self.rest_uv.iter().map(|&[u, v]| [u, v, 0.0]).collect()
    }

    /// An upper bound of the largest eigenvalue of `Σ_s w_s u_s u_sᵀ` for any spring directions
    /// `u_s` (block Gershgorin): `max_i 2 Σ_{s∋i} max(w_s, 0)`.
    pub fn max_eigenvalue_bound(&self, weights: &[f64]) -> f64 {
        assert_eq!(weights.len(), self.num_springs());
        let mut sum = vec![0f64; self.num_particles()];
        for (&[a, b], &w) in self.springs.iter().zip(weights) {
            sum[a] += w.max(0.0);
            sum[b] += w.max(0.0);
        }
        2.0 * sum.into_iter().fold(0.0, f64::max)
    }

    /// Largest eigenvalue of `Σ_s w_s u_s u_sᵀ` (3P × 3P, `u_s` the unit rest direction of
    /// spring `s`, assembled through the signed incidence matrix) by power iteration.
    ///
    /// With `w = k` this is the largest `ω²·m` of the rest-state stiffness matrix; with `w = b`
    /// the largest damping rate times `m` (see [`crate::sim::Stability`]).
    pub fn max_eigenvalue(&self, weights: &[f64]) -> f64 {
        assert_eq!(weights.len(), self.num_springs());
        let p = self.num_particles();
        let dirs: Vec<[f64; 3]> = self
            .springs
            .iter()
            .zip(&self.rest_length)
            .map(|(&[a, b], &l)| {
                let (pa, pb) = (self.rest_uv[a], self.rest_uv[b]);
                [(pb[0] - pa[0]) / l, (pb[1] - pa[1]) / l, 0.0]
            })
            .collect();
        // Deterministic start vector with components in every direction.
        let mut y: Vec<[f64; 3]> = (0..p)
            .map(|i| {
                let t = i as f64;
                [
                    (t * 0.7548).sin() + 0.3,
                    (t * 1.3247).cos() - 0.2,
                    (t * 0.5698).sin(),
                ]
            })
            .collect();
        let mut lambda = 0.0;
        for _ in 0..300 {
            let mut z = vec![[0.0f64; 3]; p];
            for (s, &[a, b]) in self.springs.iter().enumerate() {
                let u = dirs[s];
                let proj = weights[s]
                    * (u[0] * (y[b][0] - y[a][0])
                        + u[1] * (y[b][1] - y[a][1])
                        + u[2] * (y[b][2] - y[a][2]));
                for i in 0..3 {
                    z[b][i] += proj * u[i];
                    z[a][i] -= proj * u[i];
                }
            }
            let norm_z = z.iter().flatten().map(|v| v * v).sum::<f64>().sqrt();
            let norm_y = y.iter().flatten().map(|v| v * v).sum::<f64>().sqrt();
            if norm_z == 0.0 || norm_y == 0.0 {
                return 0.0;
            }
            lambda = norm_z / norm_y;
            y = z
                .iter()
                .map(|v| [v[0] / norm_z, v[1] / norm_z, v[2] / norm_z])
                .collect();
        }
        lambda
    }
}

fn distance(a: [f64; 2], b: [f64; 2]) -> f64 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2)).sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn paper_grid_has_5826_springs() {
        // 2·31·32 structural + 2·31·31 shear + 2·30·32 bending = 1984 + 1922 + 1920.
        let topo = Topology::grid(&GridSpec::default(), 15.5, 15.5);
        assert_eq!(topo.num_particles(), 1024);
        assert_eq!(topo.num_springs(), 5826);
        let count = |f| topo.family.iter().filter(|&&x| x == f).count();
        assert_eq!(count(SpringFamily::Structural), 1984);
        assert_eq!(count(SpringFamily::Shear), 1922);
        assert_eq!(count(SpringFamily::Bending), 1920);
    }

    #[test]
    fn rest_lengths_follow_the_grid() {
        let spec = GridSpec {
            nx: 3,
            ny: 4,
            ..GridSpec::default()
        };
        let topo = Topology::grid(&spec, 2.0, 6.0);
        for (s, &[a, b]) in topo.springs.iter().enumerate() {
            let (ca, ra) = (a % 3, a / 3);
            let (cb, rb) = (b % 3, b / 3);
            let expect =
                ((cb as f64 - ca as f64).powi(2) + (2.0 * (rb as f64 - ra as f64)).powi(2)).sqrt();
            assert!((topo.rest_length[s] - expect).abs() < 1e-12);
        }
        let no_shear = GridSpec {
            shear_main: false,
            shear_anti: false,
            bending_stride: 0,
            ..spec
        };
        assert_eq!(
            Topology::grid(&no_shear, 2.0, 6.0).num_springs(),
            2 * 4 + 3 * 3
        );
    }

    #[test]
    fn power_iteration_matches_the_peer_constant() {
        // The peer's stability_number() finds λ ≈ 10.07 for the 32 × 32 unit-weight grid.
        let topo = Topology::grid(&GridSpec::default(), 1.0, 1.0);
        let lam = topo.max_eigenvalue(&vec![1.0; topo.num_springs()]);
        assert!((lam - 10.07).abs() < 0.05, "λ = {lam}");
    }
}
