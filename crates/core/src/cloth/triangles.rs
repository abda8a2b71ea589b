//! Triangle-mesh cloth maths shared by the FEM source and the XPBD estimator: a triangle's rest
//! frame, its deformation gradient and Green strain, the interior hinges of a mesh and their
//! signed dihedral angle with its gradient.

use super::lanes::{Real, each3};

/// A point or vector in 3-D.
pub type V3 = [f64; 3];

/// `a − b`.
#[inline(always)]
pub fn sub<R: Real>(a: [R; 3], b: [R; 3]) -> [R; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

/// `a · b`.
#[inline(always)]
pub fn dot<R: Real>(a: [R; 3], b: [R; 3]) -> R {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// `a × b`.
#[inline(always)]
pub fn cross<R: Real>(a: [R; 3], b: [R; 3]) -> [R; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

/// `s a`.
#[inline(always)]
pub fn scale<R: Real>(a: [R; 3], s: R) -> [R; 3] {
    [a[0] * s, a[1] * s, a[2] * s]
}

/// `a` where `mask` holds, else `b`, per coordinate.
#[inline(always)]
pub(crate) fn select3<R: Real>(mask: R::Mask, a: [R; 3], b: [R; 3]) -> [R; 3] {
    each3!(|c| R::select(mask, a[c], b[c]))
}

/// `acc += a`.
#[inline]
pub fn add_to<R: Real>(acc: &mut [R; 3], a: [R; 3]) {
    for c in 0..3 {
        acc[c] = acc[c] + a[c];
    }
}

/// A triangle's rest frame in the material (u, v) plane.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RestTriangle {
    /// Its vertices.
    pub v: [usize; 3],
    /// `Dm⁻¹` (row-major 2 × 2), `Dm = [X₁ − X₀, X₂ − X₀]` in (u, v).
    pub dm_inv: [[f64; 2]; 2],
    /// Rest area.
    pub area: f64,
}

impl RestTriangle {
    /// The rest frame of triangle `v` over the rest coordinates `rest_uv`; `None` when it is
    /// degenerate (zero area).
    pub fn new(rest_uv: &[[f64; 2]], v: [usize; 3]) -> Option<Self> {
        let [p0, p1, p2] = v.map(|i| rest_uv[i]);
        let dm = [
            [p1[0] - p0[0], p2[0] - p0[0]],
            [p1[1] - p0[1], p2[1] - p0[1]],
        ];
        let det = dm[0][0] * dm[1][1] - dm[0][1] * dm[1][0];
        if det.abs() <= 0.0 || !det.is_finite() {
            return None;
        }
        Some(Self {
            v,
            dm_inv: [
                [dm[1][1] / det, -dm[0][1] / det],
                [-dm[1][0] / det, dm[0][0] / det],
            ],
            area: 0.5 * det.abs(),
        })
    }

    /// `F = Ds Dm⁻¹` (3 × 2; columns `f_u`, `f_v`) at positions (or velocities) `x`.
    #[inline]
    pub fn deformation(&self, x: &[V3]) -> [[f64; 2]; 3] {
        deformation([x[self.v[0]], x[self.v[1]], x[self.v[2]]], self.dm_inv)
    }
}

/// `F = Ds Dm⁻¹` (3 × 2) of a triangle with corners `x` (positions or velocities) and rest
/// frame `Dm⁻¹`.
#[inline(always)]
pub fn deformation<R: Real>(x: [[R; 3]; 3], dm_inv: [[R; 2]; 2]) -> [[R; 2]; 3] {
    let (d1, d2) = (sub(x[1], x[0]), sub(x[2], x[0]));
    let m = dm_inv;
    each3!(|r| {
        [
            d1[r] * m[0][0] + d2[r] * m[1][0],
            d1[r] * m[0][1] + d2[r] * m[1][1],
        ]
    })
}

/// Green strain `½(FᵀF − I)` (2 × 2, symmetric).
#[inline(always)]
pub fn green<R: Real>(f: [[R; 2]; 3]) -> [[R; 2]; 2] {
    let (half, one) = (R::splat(0.5), R::splat(1.0));
    let c01 = f[0][0] * f[0][1] + f[1][0] * f[1][1] + f[2][0] * f[2][1];
    let c10 = f[0][1] * f[0][0] + f[1][1] * f[1][0] + f[2][1] * f[2][0];
    let c00 = f[0][0] * f[0][0] + f[1][0] * f[1][0] + f[2][0] * f[2][0];
    let c11 = f[0][1] * f[0][1] + f[1][1] * f[1][1] + f[2][1] * f[2][1];
    [
        [half * (c00 - one), half * c01],
        [half * c10, half * (c11 - one)],
    ]
}

/// An interior edge `(a, b)` between the triangles holding the wings `c` and `d`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Hinge {
    /// First end of the shared edge (the smaller index).
    pub a: usize,
    /// Second end.
    pub b: usize,
    /// Wing vertex of the first triangle.
    pub c: usize,
    /// Wing vertex of the second triangle.
    pub d: usize,
    /// The two triangles (indices into the mesh's triangle list), `c`'s first.
    pub triangles: [usize; 2],
}

/// Every interior edge of a triangle mesh, sorted by `(a, b)`.
pub fn hinges(triangles: &[[usize; 3]]) -> Vec<Hinge> {
    let mut out: Vec<Hinge> = edges_with_opposites(triangles)
        .into_iter()
        .filter(|(_, w)| w.len() == 2)
        .map(|([a, b], w)| Hinge {
            a,
            b,
            c: w[0].0,
            d: w[1].0,
            triangles: [w[0].1, w[1].1],
        })
        .collect();
    out.sort_by_key(|h| (h.a, h.b));
    out
}

/// Every undirected edge `[a, b]` (`a < b`) of `triangles` with, for each triangle on it (one
/// on the border, two inside), the vertex opposite it and the triangle's index.
pub fn edges_with_opposites(
    triangles: &[[usize; 3]],
) -> std::collections::BTreeMap<[usize; 2], Vec<(usize, usize)>> {
    let mut edges: std::collections::BTreeMap<[usize; 2], Vec<(usize, usize)>> = Default::default();
    for (e, t) in triangles.iter().enumerate() {
        for k in 0..3 {
            let (a, b, c) = (t[k], t[(k + 1) % 3], t[(k + 2) % 3]);
            edges.entry([a.min(b), a.max(b)]).or_default().push((c, e));
        }
    }
    edges
}

/// Signed dihedral angle of a hinge and its gradient with respect to `(c, d, a, b)`.
///
/// With `N₁ = (x_c − x_a) × (x_c − x_b)`, `N₂ = (x_d − x_b) × (x_d − x_a)`, `E = x_b − x_a`:
/// `θ = atan2((N₂ × N₁)·Ê, N₁·N₂)` (0 when flat, smooth through it, unlike an `arccos` of the
/// normals' product) and
/// `∇_c θ = |E| N₁/|N₁|²`, `∇_d θ = |E| N₂/|N₂|²`,
/// `∇_a θ = (x_c − x_b)·E/|E| N₁/|N₁|² + (x_d − x_b)·E/|E| N₂/|N₂|²`,
/// `∇_b θ = −(x_c − x_a)·E/|E| N₁/|N₁|² − (x_d − x_a)·E/|E| N₂/|N₂|²`.
#[inline]
pub fn dihedral(h: &Hinge, x: &[V3]) -> (f64, [V3; 4]) {
    dihedral_of([x[h.a], x[h.b], x[h.c], x[h.d]])
}

/// [`dihedral`] of the corners `[a, b, c, d]`; 0 with a zero gradient when the edge or a
/// triangle is degenerate.
#[inline(always)]
pub fn dihedral_of<R: Real>([xa, xb, xc, xd]: [[R; 3]; 4]) -> (R, [[R; 3]; 4]) {
    let e = sub(xb, xa);
    let len = dot(e, e).sqrt();
    let n1 = cross(sub(xc, xa), sub(xc, xb));
    let n2 = cross(sub(xd, xb), sub(xd, xa));
    let (q1, q2) = (dot(n1, n1), dot(n2, n2));
    let zero = R::splat(0.0);
    let degenerate = len.eq(zero) | q1.eq(zero) | q2.eq(zero);
    let theta = dot(cross(n2, n1), e).atan2(dot(n1, n2) * len);
    let one = R::splat(1.0);
    let (u1, u2) = (scale(n1, one / q1), scale(n2, one / q2));
    let ga = {
        let s1 = dot(sub(xc, xb), e) / len;
        let s2 = dot(sub(xd, xb), e) / len;
        each3!(|i| s1 * u1[i] + s2 * u2[i])
    };
    let gb = {
        let s1 = dot(sub(xc, xa), e) / len;
        let s2 = dot(sub(xd, xa), e) / len;
        each3!(|i| -s1 * u1[i] - s2 * u2[i])
    };
    let grads = [scale(u1, len), scale(u2, len), ga, gb];
    let none = [zero; 3];
    (
        R::select(degenerate, zero, theta),
        [
            select3(degenerate, none, grads[0]),
            select3(degenerate, none, grads[1]),
            select3(degenerate, none, grads[2]),
            select3(degenerate, none, grads[3]),
        ],
    )
}
