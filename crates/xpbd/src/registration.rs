//! The template registration of paper 001 §3.2, as a stand-in for its real scans: a scanned
//! drape (a triangle mesh with measurement noise, finer than the template) is brought onto the
//! template grid through the landmarks stamped on the swatch. Template vertices on the stamped
//! pattern take their landmark's scanned position; the others are interpolated between the
//! landmarks (harmonic on the template's edges, along the border on the border: the smoothness
//! term of a non-rigid ICP alone, exact for an affine map)
//! and then, as the paper does, projected along the template's normal onto the scanned surface
//! (a ray cast both ways with parry3d, the nearer hit within `reach`). So the registration is
//! exact in the normal direction up to the scan's noise, and off in the tangential one by what
//! the interpolation misses between landmarks: the paper's "accuracy limited to the resolution
//! of the stamped pattern".

use anyhow::{Result, bail};
use parry3d_f64::math::Vector;
use parry3d_f64::query::{Ray, RayCast};
use parry3d_f64::shape::TriMesh;
use serde::Serialize;

use springtime_core::cloth::triangles::{V3, add_to, cross, dot, edges_with_opposites, sub};

/// A scanned surface: vertices and triangles.
#[derive(Debug, Clone)]
pub struct Scan {
    /// Vertex positions, m.
    pub vertices: Vec<V3>,
    /// Triangles, as vertex indices.
    pub triangles: Vec<[usize; 3]>,
}

/// How far a registration landed from the true positions of the template's material points.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct RegistrationError {
    /// Root mean square over the template's vertices, m.
    pub rms: f64,
    /// Largest, m.
    pub max: f64,
    /// Template vertices on the stamped pattern (or clamped), whose positions come from the
    /// landmarks.
    pub landmarks: usize,
    /// Vertices whose projection along the normal found the scan within reach.
    pub projected: usize,
}

impl RegistrationError {
    /// The distances between `x` and `truth`, with the counts of a registration.
    pub fn of(x: &[V3], truth: &[V3], landmarks: usize, projected: usize) -> Self {
        let d: Vec<f64> = x
            .iter()
            .zip(truth)
            .map(|(a, b)| {
                let e = sub(*a, *b);
                dot(e, e).sqrt()
            })
            .collect();
        Self {
            rms: (d.iter().map(|v| v * v).sum::<f64>() / d.len().max(1) as f64).sqrt(),
            max: d.iter().copied().fold(0.0, f64::max),
            landmarks,
            projected,
        }
    }
}

/// A template registered to a scan.
#[derive(Debug, Clone)]
pub struct Registered {
    /// The template's vertex positions, m.
    pub x: Vec<V3>,
    /// Vertices that came from landmarks.
    pub landmarks: usize,
    /// Vertices projected onto the scan.
    pub projected: usize,
}

/// Registers a template (`len` vertices, `triangles`) to `scan`: `landmarks[i]` is vertex `i`'s
/// position where it lies on the stamped pattern (or is clamped), `None` elsewhere. Rays along
/// the normals reach `reach` (m) each way.
pub fn register(
    len: usize,
    triangles: &[[usize; 3]],
    landmarks: &[Option<V3>],
    scan: &Scan,
    reach: f64,
) -> Result<Registered> {
    if landmarks.len() != len {
        bail!(
            "{} landmark entries for {len} template vertices",
            landmarks.len()
        );
    }
    let count = landmarks.iter().flatten().count();
    if count == 0 {
        bail!("a registration needs at least one landmark");
    }
    let neighbours = neighbours(len, triangles);
    let mut x = interpolate(landmarks, &neighbours, count);
    let normal = vertex_normals(&x, triangles);
    let projected = project(&mut x, &normal, landmarks, scan, reach)?;
    Ok(Registered {
        x,
        landmarks: count,
        projected,
    })
}

/// The template's neighbours along its edges; a vertex on the border takes only its border
/// neighbours, so that the interpolation runs along the border there (with every neighbour,
/// a border vertex would be pulled inwards by a third of a cell, and an affine map would not
/// be reproduced).
fn neighbours(len: usize, triangles: &[[usize; 3]]) -> Vec<Vec<usize>> {
    let edges = edges_with_opposites(triangles);
    let mut border = vec![false; len];
    for ([a, b], faces) in &edges {
        if faces.len() == 1 {
            border[*a] = true;
            border[*b] = true;
        }
    }
    let mut neighbours = vec![Vec::new(); len];
    for (&[a, b], faces) in &edges {
        let on_border = faces.len() == 1;
        if !border[a] || on_border {
            neighbours[a].push(b);
        }
        if !border[b] || on_border {
            neighbours[b].push(a);
        }
    }
    neighbours
}

/// Harmonic interpolation between the `count` landmarks (Gauss–Seidel to rest), from their
/// mean.
fn interpolate(landmarks: &[Option<V3>], neighbours: &[Vec<usize>], count: usize) -> Vec<V3> {
    let mut mean = [0.0; 3];
    for p in landmarks.iter().flatten() {
        add_to(&mut mean, p.map(|c| c / count as f64));
    }
    let mut x: Vec<V3> = landmarks.iter().map(|l| l.unwrap_or(mean)).collect();
    let scale = landmarks
        .iter()
        .flatten()
        .map(|p| dot(sub(*p, mean), sub(*p, mean)).sqrt())
        .fold(0.0, f64::max)
        .max(1e-9);
    for _ in 0..100_000 {
        let mut moved = 0.0f64;
        for i in 0..x.len() {
            if landmarks[i].is_some() || neighbours[i].is_empty() {
                continue;
            }
            let k = neighbours[i].len() as f64;
            let mut p = [0.0; 3];
            for &j in &neighbours[i] {
                add_to(&mut p, x[j].map(|c| c / k));
            }
            moved = moved.max(sub(p, x[i]).iter().fold(0.0, |m, c| m.max(c.abs())));
            x[i] = p;
        }
        if moved < 1e-13 * scale {
            break;
        }
    }
    x
}

/// Vertex normals of the template at `x` (area-weighted, not normalised).
fn vertex_normals(x: &[V3], triangles: &[[usize; 3]]) -> Vec<V3> {
    let mut normal = vec![[0.0; 3]; x.len()];
    for t in triangles {
        let n = cross(sub(x[t[1]], x[t[0]]), sub(x[t[2]], x[t[0]]));
        for &v in t {
            add_to(&mut normal[v], n);
        }
    }
    normal
}

/// Moves every vertex of `x` but the landmarks along its `normal` onto `scan`, to the nearer
/// hit within `reach` either way; returns how many found it.
fn project(
    x: &mut [V3],
    normal: &[V3],
    landmarks: &[Option<V3>],
    scan: &Scan,
    reach: f64,
) -> Result<usize> {
    let to = |p: V3| Vector::new(p[0], p[1], p[2]);
    let mesh = TriMesh::new(
        scan.vertices.iter().map(|&p| to(p)).collect(),
        scan.triangles.iter().map(|t| t.map(|v| v as u32)).collect(),
    )
    .map_err(|e| anyhow::anyhow!("the scan is not a triangle mesh: {e:?}"))?;
    let mut projected = 0;
    for i in 0..x.len() {
        let n = normal[i];
        let norm = dot(n, n).sqrt();
        if landmarks[i].is_some() || norm == 0.0 {
            continue;
        }
        let dir = n.map(|c| c / norm);
        let hit = [1.0, -1.0]
            .into_iter()
            .filter_map(|s| {
                let ray = Ray::new(to(x[i]), to(dir.map(|c| s * c)));
                mesh.cast_local_ray(&ray, reach, false).map(|t| s * t)
            })
            .min_by(|a, b| a.abs().total_cmp(&b.abs()));
        if let Some(t) = hit {
            x[i] = [0, 1, 2].map(|c| x[i][c] + t * dir[c]);
            projected += 1;
        }
    }
    Ok(projected)
}

#[cfg(test)]
mod tests {
    use super::*;
    use springtime_core::cloth::{Diagonal, grid_triangles};

    /// A grid of `n × n` over the square `[−m, 1 + m]²` shaped by `f(u, v)`.
    fn sheet_over(n: usize, m: f64, f: impl Fn(f64, f64) -> V3) -> (Vec<V3>, Vec<[usize; 3]>) {
        let h = (1.0 + 2.0 * m) / (n - 1) as f64;
        let x = (0..n * n)
            .map(|k| f((k % n) as f64 * h - m, (k / n) as f64 * h - m))
            .collect();
        (x, grid_triangles(n, n, Diagonal::Alternating))
    }

    /// A grid of `n × n` over the unit square shaped by `f(u, v)`.
    fn sheet(n: usize, f: impl Fn(f64, f64) -> V3) -> (Vec<V3>, Vec<[usize; 3]>) {
        sheet_over(n, 0.0, f)
    }

    #[test]
    fn a_registration_follows_the_scan_along_the_normal_and_keeps_the_landmarks() {
        // A bump of 5 cm on a 1 m sheet, scanned 4 times finer than the 9 × 9 template and a
        // little beyond it (so that no ray leaves past the scan's border); every other
        // template vertex is stamped.
        let shape = |u: f64, v: f64| {
            let r2 = (u - 0.5).powi(2) + (v - 0.5).powi(2);
            [u, v, 0.05 * (-r2 / 0.05).exp()]
        };
        let (fine, tris) = sheet_over(41, 0.125, shape);
        let scan = Scan {
            vertices: fine,
            triangles: tris,
        };
        let (truth, template) = sheet(9, shape);
        let stamped = |k: usize| (k % 9).is_multiple_of(2) && (k / 9).is_multiple_of(2);
        let landmarks: Vec<Option<V3>> = (0..81).map(|k| stamped(k).then_some(truth[k])).collect();
        let reg = register(81, &template, &landmarks, &scan, 0.1).unwrap();
        assert_eq!(reg.landmarks, 25);
        assert_eq!(reg.projected, 56);
        let mut worst_off = 0.0f64;
        for k in 0..81 {
            if stamped(k) {
                assert_eq!(reg.x[k], truth[k]);
            }
            // On the scanned surface: its height there, to the fine mesh's chord error.
            let p = reg.x[k];
            worst_off = worst_off.max((p[2] - shape(p[0], p[1])[2]).abs());
        }
        assert!(worst_off < 2e-4, "{worst_off} m off the surface");
        // Without the projection (reach 0) the interpolation cuts through the bump.
        let flat = register(81, &template, &landmarks, &scan, 0.0).unwrap();
        assert_eq!(flat.projected, 0);
        let before = RegistrationError::of(&flat.x, &truth, 25, 0);
        let after = RegistrationError::of(&reg.x, &truth, 25, 56);
        assert!(after.rms < 0.5 * before.rms, "{after:?} vs {before:?}");
    }

    #[test]
    fn an_affine_map_is_registered_exactly_from_sparse_landmarks() {
        // Stretched and sheared in the plane: every template vertex, the border ones
        // included, lands on its material point.
        let map = |u: f64, v: f64| [1.03 * u + 0.2 * v, 0.98 * v, 0.0];
        let (fine, tris) = sheet(17, map);
        let (truth, template) = sheet(9, map);
        let on = |i: usize| i.is_multiple_of(3) || i == 8;
        let landmarks: Vec<Option<V3>> = (0..81)
            .map(|k| (on(k % 9) && on(k / 9)).then_some(truth[k]))
            .collect();
        let scan = Scan {
            vertices: fine,
            triangles: tris,
        };
        let reg = register(81, &template, &landmarks, &scan, 0.1).unwrap();
        let err = RegistrationError::of(&reg.x, &truth, reg.landmarks, reg.projected);
        assert!(err.max < 1e-12, "{err:?}");
    }
}
