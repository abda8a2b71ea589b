//! The surrogate's spring network: on a regular grid (paper §3.1, Fig. 5), or on the data's own
//! triangle mesh (ours).
//!
//! **Grid** (`cloth.layout = "grid"`): particle `p = row * nx + col` sits at rest at
//! `(col * hx, row * hy)` in the unrolled `width × height` rectangle, `hx = width / (nx - 1)`,
//! `hy = height / (ny - 1)`. Springs join grid neighbours: structural (horizontal, vertical),
//! shear (the two diagonals, each switchable) and bending (stride `bending_stride` horizontally
//! and vertically, 0 = none).
//!
//! **Data mesh** (`cloth.layout = "data"`): the particles are the data's landmarks, at their
//! `rest_uv`; structural springs are the edges of the data's triangles (key `triangles`, or the
//! Delaunay triangulation of `rest_uv` when the files have none), and bending springs join the
//! two vertices opposite each interior edge (the "hinge" pair; when `bending_stride > 0`). No
//! landmark is interpolated, so a per-spring stiffness sits where the data's forces act: on
//! an irregular mesh a grid's particles are averages of several vertices, whose accelerations
//! no spring attached to the particle produces (the book, "Data from another simulator").

use serde::{Deserialize, Serialize};

use super::resample::twice_area;

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
    /// Stride of the bending springs in grid steps (the paper uses 2); 0 disables them. With
    /// `layout = "data"`, any positive value adds the hinge springs.
    pub bending_stride: usize,
    /// Where the particles and springs come from: the paper's grid, or the data's mesh.
    pub layout: SpringLayout,
    /// Curvature elements (ours): every three consecutive particles along a grid row, column or
    /// diagonal resist their second difference `x_i − 2x_j + x_l` with a learned stiffness (grid
    /// only).
    /// Springs have no linear bending stiffness about the flat state; these do.
    pub curvature: bool,
    /// How the particles of a data mesh (`layout = "data"`) share the cloth's mass.
    pub masses: ParticleMasses,
}

/// How the particles of a data mesh share the cloth's mass: `cloth.masses`. A grid's particles
/// always weigh the same.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ParticleMasses {
    /// Each particle weighs its lumped rest area (a third of each adjacent triangle's): an
    /// FEM's or a density-based cloth's masses (border particles are lighter).
    #[default]
    Lumped,
    /// Every particle weighs the same (`total_mass / N`): the vertex masses of Blender's cloth,
    /// of Warp's and Newton's `add_cloth_grid`, of MuJoCo's `flexcomp`.
    Equal,
}

/// The surrogate's particles and springs: `cloth.layout`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SpringLayout {
    /// An `nx × ny` grid over the rest rectangle (paper §3.1); landmarks are resampled onto it.
    #[default]
    Grid,
    /// The data's landmarks and triangle edges, plus hinge springs (ours).
    Data,
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
            layout: SpringLayout::Grid,
            curvature: false,
            masses: ParticleMasses::Lumped,
        }
    }
}

/// How each grid cell is cut into two triangles.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Diagonal {
    /// Along `(r, c)–(r+1, c+1)` in every cell: a fold along the sheet's main diagonal follows
    /// mesh edges ("aligned").
    #[default]
    Main,
    /// Along `(r, c+1)–(r+1, c)` in every cell: a fold along the main diagonal cuts across the
    /// mesh edges ("misaligned").
    Anti,
    /// Main and anti diagonals in a checkerboard.
    Alternating,
}

/// The triangles of an `nx × ny` grid (counter-clockwise in the rest rectangle).
pub fn grid_triangles(nx: usize, ny: usize, diagonal: Diagonal) -> Vec<[usize; 3]> {
    let id = |r: usize, c: usize| r * nx + c;
    let mut tris = Vec::with_capacity(2 * (nx - 1) * (ny - 1));
    for r in 0..ny - 1 {
        for c in 0..nx - 1 {
            let main = match diagonal {
                Diagonal::Main => true,
                Diagonal::Anti => false,
                Diagonal::Alternating => (r + c) % 2 == 0,
            };
            let (p00, p01, p10, p11) = (id(r, c), id(r, c + 1), id(r + 1, c), id(r + 1, c + 1));
            if main {
                tris.push([p00, p01, p11]);
                tris.push([p00, p11, p10]);
            } else {
                tris.push([p00, p01, p10]);
                tris.push([p01, p11, p10]);
            }
        }
    }
    tris
}

/// The kind of a spring, for reports and per-family metrics.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SpringFamily {
    /// Grid edges (horizontal and vertical).
    Structural,
    /// Cell diagonals (on a data mesh: the hinge springs that are a quad cell's other
    /// diagonal, see [`Topology::mesh`]).
    Shear,
    /// Stride-`n` horizontal and vertical springs that resist bending (on a data mesh: the other
    /// hinge springs).
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
    /// Particles along x and y of a grid network; `None` on a data mesh.
    pub grid: Option<[usize; 2]>,
    /// The rest sheet's triangles (a grid's cells cut along their main diagonal, or the data's
    /// mesh), counter-clockwise: for drawing and exporting the cloth.
    pub triangles: Vec<[usize; 3]>,
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
    /// Curvature elements `(i, j, l)`: three consecutive particles of a grid row, column or
    /// diagonal, `j` in the middle (`cloth.curvature`; empty without). Each has the energy `½ κ |x_i − 2x_j +
    /// x_l|²`, which is zero on the flat rest grid and under every rigid motion, and grows with
    /// the square of the bend angle at `j`: the linear bending stiffness about the flat state
    /// that springs, whose lengths change only to second order in that angle, do not have.
    pub curvature: Vec<[usize; 3]>,
    /// Each particle's mass relative to the mean (mean 1): `None` for equal masses (a grid);
    /// on a data mesh, the lumped rest area (a third of each adjacent triangle's). The mean
    /// mass stays `total_mass / P` everywhere: a particle of relative mass `w` feels its spring
    /// forces divided by `w` ([`Topology::force_scale`]), which with gravity and Rayleigh
    /// damping per unit mass is exactly the network with masses `w · m̄`.
    pub mass_weight: Option<Vec<f64>>,
}

impl Topology {
    /// Whether the network has bending springs ([`SpringFamily::Bending`]).
    pub fn has_bending(&self) -> bool {
        self.family.contains(&SpringFamily::Bending)
    }

    /// Multiplies the entries of `family`'s springs in the per-spring values `k` by `factor`: a
    /// family's share of a network's stiffness (ours: the bending springs, hinge or stride
    /// springs which no other simulator has as such, and the shear springs, a cell's diagonals,
    /// are sized apart from the rest).
    pub fn scale_family(&self, k: &mut [f64], family: SpringFamily, factor: f64) {
        for (k, f) in k.iter_mut().zip(&self.family) {
            if *f == family {
                *k *= factor;
            }
        }
    }

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
        let mut curvature = Vec::new();
        if spec.curvature {
            for r in 0..ny {
                for c in 1..nx.saturating_sub(1) {
                    curvature.push([id(r, c - 1), id(r, c), id(r, c + 1)]);
                }
            }
            for r in 1..ny.saturating_sub(1) {
                for c in 0..nx {
                    curvature.push([id(r - 1, c), id(r, c), id(r + 1, c)]);
                }
            }
            // The diagonals resist twist, which rows and columns alone do not see.
            for r in 1..ny.saturating_sub(1) {
                for c in 1..nx.saturating_sub(1) {
                    curvature.push([id(r - 1, c - 1), id(r, c), id(r + 1, c + 1)]);
                    curvature.push([id(r - 1, c + 1), id(r, c), id(r + 1, c - 1)]);
                }
            }
        }
        let mut topo = Self {
            grid: Some([nx, ny]),
            triangles: grid_triangles(nx, ny, Diagonal::Main),
            width,
            height,
            rest_uv,
            springs,
            rest_length: Vec::new(),
            family,
            curvature,
            mass_weight: None,
        };
        topo.rest_length = topo
            .springs
            .iter()
            .map(|&[a, b]| distance(topo.rest_uv[a], topo.rest_uv[b]))
            .collect();
        topo
    }

    /// The network on a triangle mesh over a `width × height` rest rectangle (`layout =
    /// "data"`): particles at `rest_uv`, a spring on each of the triangles' edges and, with
    /// `hinges`, a hinge spring between the two vertices opposite each interior edge. Where an
    /// interior edge is the longest side of both its triangles, the two form a quad cell whose
    /// diagonal it is: that edge and its hinge spring (the cell's other diagonal) are shear
    /// springs, as on a grid. The other edges are structural springs, the other hinge springs
    /// bending springs.
    ///
    /// A triangle listed twice (e.g. both sides of a double-sided mesh) counts once. Errors (the
    /// caller names the file) on an index out of range, a degenerate triangle, a vertex in no
    /// triangle (it would fall freely), or two landmarks at the same rest position.
    pub fn mesh(
        rest_uv: &[[f64; 2]],
        triangles: &[[usize; 3]],
        width: f64,
        height: f64,
        hinges: bool,
    ) -> Result<Self, String> {
        let ccw = counter_clockwise(rest_uv, triangles, [width, height])?;
        // Each undirected edge with the vertices opposite it (one on the border, two inside).
        let opposite: std::collections::BTreeMap<[usize; 2], Vec<usize>> =
            crate::cloth::triangles::edges_with_opposites(&ccw)
                .into_iter()
                .map(|(e, w)| (e, w.into_iter().map(|(c, _)| c).collect()))
                .collect();
        let mut springs: Vec<[usize; 2]> = opposite.keys().copied().collect();
        // An edge that is the diagonal of the quad cell its two triangles form is a shear spring.
        let mut family: Vec<SpringFamily> = opposite
            .iter()
            .map(|(edge, far)| match far.as_slice() {
                &[a, b] if a != b && cell_diagonal(rest_uv, *edge, [a, b]) => SpringFamily::Shear,
                _ => SpringFamily::Structural,
            })
            .collect();
        if hinges {
            let mut seen: std::collections::BTreeSet<[usize; 2]> =
                opposite.keys().copied().collect();
            for (edge, far) in opposite
                .iter()
                .filter(|(_, o)| o.len() == 2 && o[0] != o[1])
            {
                let pair = [far[0].min(far[1]), far[0].max(far[1])];
                if seen.insert(pair) {
                    springs.push(pair);
                    family.push(if cell_diagonal(rest_uv, *edge, pair) {
                        SpringFamily::Shear
                    } else {
                        SpringFamily::Bending
                    });
                }
            }
        }
        let rest_length: Vec<f64> = springs
            .iter()
            .map(|&[a, b]| distance(rest_uv[a], rest_uv[b]))
            .collect();
        if let Some(s) = rest_length.iter().position(|&l| !(l > 0.0)) {
            let [a, b] = springs[s];
            return Err(format!(
                "landmarks {a} and {b} share a rest position: a spring between them has no length"
            ));
        }
        let mass_weight = Some(lumped_mass_weights(rest_uv, &ccw));
        Ok(Self {
            grid: None,
            triangles: ccw,
            width,
            height,
            rest_uv: rest_uv.to_vec(),
            springs,
            rest_length,
            family,
            curvature: Vec::new(),
            mass_weight,
        })
    }

    /// The same network with its particles' masses shared as `masses` says (a grid's stay equal).
    pub fn with_masses(mut self, masses: ParticleMasses) -> Self {
        if self.grid.is_none() {
            self.mass_weight = match masses {
                ParticleMasses::Lumped => Some(lumped_mass_weights(&self.rest_uv, &self.triangles)),
                ParticleMasses::Equal => None,
            };
        }
        self
    }

    /// The network on the Delaunay triangulation of `rest_uv` (slivers dropped), for data that
    /// brings points without a mesh; otherwise as [`Topology::mesh`].
    pub fn of_points(
        rest_uv: &[[f64; 2]],
        width: f64,
        height: f64,
        hinges: bool,
    ) -> Result<Self, String> {
        let triangles = super::resample::delaunay(rest_uv);
        Self::mesh(rest_uv, &triangles, width, height, hinges).map_err(|e| {
            format!(
                "{e} (the files have no `triangles`, so these are the Delaunay triangles of \
                 `rest_uv` without slivers: a landmark at the place of another, or on a straight \
                 line between its neighbours, can fall out)"
            )
        })
    }

    /// A typical distance between neighbouring particles, m: the grid step (the smaller of
    /// the two), or the median structural rest length of a mesh.
    pub fn spacing(&self) -> f64 {
        if let Some([nx, ny]) = self.grid {
            return (self.width / (nx - 1).max(1) as f64).min(self.height / (ny - 1).max(1) as f64);
        }
        let mut l: Vec<f64> = (0..self.num_springs())
            .filter(|&s| self.family[s] == SpringFamily::Structural)
            .map(|s| self.rest_length[s])
            .collect();
        l.sort_by(f64::total_cmp);
        l.get(l.len() / 2)
            .copied()
            .unwrap_or(self.width.min(self.height))
    }

    /// The rest sheet's edges, each once: what a wireframe draws.
    pub fn edges(&self) -> Vec<[usize; 2]> {
        let mut e: Vec<[usize; 2]> = self
            .triangles
            .iter()
            .flat_map(|t| (0..3).map(move |j| [t[j].min(t[(j + 1) % 3]), t[j].max(t[(j + 1) % 3])]))
            .collect();
        e.sort_unstable();
        e.dedup();
        e
    }

    /// "32 × 32 particles" or "625 particles on the data's mesh", for reports.
    pub fn describe(&self) -> String {
        match self.grid {
            Some([nx, ny]) => format!("{nx} × {ny} particles"),
            None => format!("{} particles on the data's mesh", self.num_particles()),
        }
    }

    /// Particle `i`'s mass relative to the mean ([`Topology::mass_weight`]; 1 on a grid).
    pub(crate) fn relative_mass(&self, i: usize) -> f64 {
        self.mass_weight.as_ref().map_or(1.0, |w| w[i])
    }

    /// Every particle's mass, kg, for particles of `mean` mass on average.
    pub fn masses(&self, mean: f64) -> Vec<f64> {
        (0..self.num_particles())
            .map(|i| mean * self.relative_mass(i))
            .collect()
    }

    /// The factor `1 / w` on each particle's spring forces ([`Topology::mass_weight`]);
    /// `None` for equal masses.
    pub fn force_scale(&self) -> Option<Vec<f64>> {
        self.mass_weight
            .as_ref()
            .map(|w| w.iter().map(|w| 1.0 / w).collect())
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

    /// Largest eigenvalue of `Σ_s w_s u_s u_sᵀ` (3P × 3P, `u_s` the unit rest direction of
    /// spring `s`, assembled through the signed incidence matrix) by power iteration; with
    /// [`Topology::mass_weight`] `W`, of `W^{-1/2} (Σ_s w_s u_s u_sᵀ) W^{-1/2}` (the stiffness
    /// per unit of the mean mass).
    ///
    /// With `w = k` this is the largest `ω²·m` of the rest-state stiffness matrix; with `w = b`
    /// the largest damping rate times `m` (see [`crate::sim::Stability`]).
    pub(crate) fn max_eigenvalue(&self, weights: &[f64]) -> f64 {
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
        let scale: Vec<f64> = match &self.mass_weight {
            Some(w) => w.iter().map(|w| 1.0 / w.sqrt()).collect(),
            None => vec![1.0; p],
        };
        super::power_iteration(p, 300, |y, z| {
            for (s, &[a, b]) in self.springs.iter().enumerate() {
                let u = dirs[s];
                let (ya, yb) = (y[a].map(|c| c * scale[a]), y[b].map(|c| c * scale[b]));
                let proj = weights[s]
                    * (u[0] * (yb[0] - ya[0]) + u[1] * (yb[1] - ya[1]) + u[2] * (yb[2] - ya[2]));
                for i in 0..3 {
                    z[b][i] += proj * u[i] * scale[b];
                    z[a][i] -= proj * u[i] * scale[a];
                }
            }
        })
    }
}

/// The data mesh's triangles counter-clockwise in the rest plane, duplicates dropped; refuses a
/// vertex index beyond the landmarks, a degenerate triangle (zero rest area relative to the
/// `[width, height]` rectangle) and a landmark in no triangle.
fn counter_clockwise(
    rest_uv: &[[f64; 2]],
    triangles: &[[usize; 3]],
    [width, height]: [f64; 2],
) -> Result<Vec<[usize; 3]>, String> {
    let n = rest_uv.len();
    let mut used = vec![false; n];
    let mut ccw = Vec::with_capacity(triangles.len());
    let mut seen = std::collections::BTreeSet::new();
    for (i, &t) in triangles.iter().enumerate() {
        if t.iter().any(|&v| v >= n) {
            return Err(format!(
                "triangle {i} {t:?} names a vertex beyond the {n} landmarks"
            ));
        }
        let area2 = twice_area(rest_uv, t);
        if area2.abs() <= 1e-12 * width * height {
            return Err(format!("triangle {i} {t:?} is degenerate (zero rest area)"));
        }
        t.iter().for_each(|&v| used[v] = true);
        let mut key = t;
        key.sort_unstable();
        if seen.insert(key) {
            ccw.push(if area2 > 0.0 { t } else { [t[0], t[2], t[1]] });
        }
    }
    if let Some(v) = used.iter().position(|u| !u) {
        return Err(format!(
            "landmark {v} is in no triangle: the data mesh would leave it without springs"
        ));
    }
    Ok(ccw)
}

/// Whether the interior `edge`, with `far` the vertices opposite it, is the diagonal of a quad
/// cell: the longest side of both triangles on it. Then the edge and the hinge spring across it
/// (the cell's other diagonal) are a triangulated grid's diagonals, where a mass-spring cloth has
/// its shear springs; a hinge spring across any other edge (a cell's side) spans two cells and
/// resists bending.
fn cell_diagonal(rest_uv: &[[f64; 2]], edge: [usize; 2], far: [usize; 2]) -> bool {
    let shared = distance(rest_uv[edge[0]], rest_uv[edge[1]]);
    far.iter().all(|&c| {
        edge.iter()
            .all(|&a| distance(rest_uv[a], rest_uv[c]) <= shared * (1.0 + 1e-9))
    })
}

/// Lumped masses: a third of every adjacent triangle's rest area, relative to the mean.
fn lumped_mass_weights(rest_uv: &[[f64; 2]], ccw: &[[usize; 3]]) -> Vec<f64> {
    let n = rest_uv.len();
    let mut area = vec![0.0; n];
    for &t in ccw {
        let third = twice_area(rest_uv, t) / 6.0;
        t.iter().for_each(|&v| area[v] += third);
    }
    let mean = area.iter().sum::<f64>() / n as f64;
    area.iter().map(|a| a / mean).collect()
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
    fn a_data_mesh_has_its_edges_and_one_hinge_per_interior_edge() {
        // Two triangles sharing the diagonal 0–2 of a unit square (one listed clockwise), and a
        // third on edge 1–2 with apex 4.
        let uv = [[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0], [2.0, 0.5]];
        let tris = [[0, 1, 2], [0, 3, 2], [1, 4, 2]];
        let topo = Topology::mesh(&uv, &tris, 2.0, 1.0, true).unwrap();
        assert_eq!(topo.grid, None);
        let structural: Vec<[usize; 2]> = (0..topo.num_springs())
            .filter(|&s| topo.family[s] == SpringFamily::Structural)
            .map(|s| topo.springs[s])
            .collect();
        assert_eq!(
            structural,
            vec![[0, 1], [0, 3], [1, 2], [1, 4], [2, 3], [2, 4]]
        );
        let hinges = |family| -> Vec<[usize; 2]> {
            (0..topo.num_springs())
                .filter(|&s| topo.family[s] == family)
                .map(|s| topo.springs[s])
                .collect()
        };
        // 0–2 is the square's diagonal, the longest side of both its triangles: a shear spring,
        // and so is the hinge across it, vertices 1 and 3, the square's other diagonal. Across
        // 1–2, a side of the square: vertices 0 and 4, a bending spring.
        assert_eq!(hinges(SpringFamily::Shear), vec![[0, 2], [1, 3]]);
        assert_eq!(hinges(SpringFamily::Bending), vec![[0, 4]]);
        assert!((topo.rest_length[topo.num_springs() - 1] - 2.0615528128088303).abs() < 1e-12);
        // Every triangle counter-clockwise.
        for t in &topo.triangles {
            let (a, b, c) = (uv[t[0]], uv[t[1]], uv[t[2]]);
            assert!((b[0] - a[0]) * (c[1] - a[1]) - (c[0] - a[0]) * (b[1] - a[1]) > 0.0);
        }
        assert_eq!(topo.edges().len(), 7);
        assert_eq!(
            Topology::mesh(&uv, &tris, 2.0, 1.0, false)
                .unwrap()
                .num_springs(),
            7
        );
        let lonely = Topology::mesh(&uv, &tris[..2], 2.0, 1.0, true).unwrap_err();
        assert!(lonely.contains("landmark 4 is in no triangle"), "{lonely}");
        // Both sides of a double-sided mesh count once: no zero-length hinge.
        let twice = [[0, 1, 2], [0, 2, 1], [0, 3, 2], [1, 4, 2]];
        let once = Topology::mesh(&uv, &twice, 2.0, 1.0, true).unwrap();
        assert_eq!(once.springs, topo.springs);
        let degenerate = [[0, 1, 1], [0, 2, 3], [1, 4, 2]];
        let err = Topology::mesh(&uv, &degenerate, 2.0, 1.0, true).unwrap_err();
        assert!(err.contains("triangle 0"), "{err}");
    }

    #[test]
    fn a_grid_laid_out_as_a_data_mesh_has_the_grid_s_structural_and_shear_springs_and_families() {
        // The grid's own triangles as a "data mesh": edges = structural + main-diagonal shear.
        let spec = GridSpec {
            nx: 4,
            ny: 3,
            ..GridSpec::default()
        };
        let grid = Topology::grid(&spec, 3.0, 2.0);
        let mesh = Topology::mesh(&grid.rest_uv, &grid.triangles, 3.0, 2.0, false).unwrap();
        let mut expect: Vec<[usize; 2]> = (0..grid.num_springs())
            .filter(|&s| match grid.family[s] {
                SpringFamily::Structural => true,
                SpringFamily::Shear => grid.springs[s][1] == grid.springs[s][0] + 5,
                SpringFamily::Bending => false,
            })
            .map(|s| grid.springs[s])
            .collect();
        expect.sort_unstable();
        assert_eq!(mesh.springs, expect);
        // With the grid's families: the cut diagonals are shear springs.
        for (s, pair) in mesh.springs.iter().enumerate() {
            let g = grid.springs.iter().position(|p| p == pair).unwrap();
            assert_eq!(mesh.family[s], grid.family[g], "spring {pair:?}");
        }
        assert!((mesh.spacing() - grid.spacing()).abs() < 1e-12);
    }

    #[test]
    fn a_data_mesh_s_particles_weigh_their_lumped_area_or_the_same() {
        // A triangulated 3 × 3 grid: its corners touch one or two triangles, its middle six.
        let spec = GridSpec {
            nx: 3,
            ny: 3,
            ..GridSpec::default()
        };
        let grid = Topology::grid(&spec, 2.0, 2.0);
        let lumped = Topology::mesh(&grid.rest_uv, &grid.triangles, 2.0, 2.0, true).unwrap();
        let w = lumped
            .mass_weight
            .clone()
            .expect("a mesh lumps its masses by default");
        // Areas (in units of one triangle's third): corners 1 or 2, sides 3, middle 6; mean 8/3.
        let mean = 24.0 / 9.0;
        let expect = [2.0, 3.0, 1.0, 3.0, 6.0, 3.0, 1.0, 3.0, 2.0].map(|a| a / mean);
        for (i, (w, e)) in w.iter().zip(expect).enumerate() {
            assert!((w - e).abs() < 1e-12, "particle {i}: {w} against {e}");
        }
        let equal = lumped.clone().with_masses(ParticleMasses::Equal);
        assert_eq!(equal.mass_weight, None);
        assert_eq!((0..9).map(|i| equal.relative_mass(i)).sum::<f64>(), 9.0);
        assert_eq!(equal.springs, lumped.springs);
        // Back to lumped: the same weights; a grid's particles weigh the same either way.
        assert_eq!(
            equal.with_masses(ParticleMasses::Lumped).mass_weight,
            Some(w)
        );
        assert_eq!(grid.with_masses(ParticleMasses::Lumped).mass_weight, None);
    }

    #[test]
    fn power_iteration_matches_the_peer_constant() {
        // The peer's stability_number() finds λ ≈ 10.07 for the 32 × 32 unit-weight grid.
        let topo = Topology::grid(&GridSpec::default(), 1.0, 1.0);
        let lam = topo.max_eigenvalue(&vec![1.0; topo.num_springs()]);
        assert!((lam - 10.07).abs() < 0.05, "λ = {lam}");
    }
}
