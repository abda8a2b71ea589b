//! `springtime import obj|pc2|csv`: other tools' cloth motion as springtime rollout files.
//!
//! Every importer reads the motion of `N` points over `F` frames ([`Motion`]) and how to find
//! their rest positions ([`RestShape`]: texture coordinates of a mesh, a flat reference frame,
//! or rest coordinates given outright); [`rest_rectangle`] turns that into the unrolled rest
//! rectangle and [`write_rollout`] writes one `.npz` in the rollout schema of
//! [`crate::data::Rollout`] (positions, `rest_uv`, `pinned`, `frame_dt`, `total_mass`,
//! `width`, `height`). Velocities are not stored: training takes backward differences.
//!
//! Errors name the file and the frame, line or element; nothing is written over an existing
//! file without `--force`.

pub mod csv;
pub mod obj;
pub mod pc2;

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};

use crate::data::{MeshTruth, Rollout, Segment};

/// The choices every importer shares.
#[derive(Debug, Clone)]
pub struct ImportOptions {
    /// Output folder; the rollout is `<out>/<name>.npz`.
    pub out: PathBuf,
    /// Time between frames, s.
    pub frame_dt: f64,
    /// Mass of the whole cloth, kg.
    pub total_mass: f64,
    /// Pinned points, 0-based in the source's point order.
    pub pinned: Vec<usize>,
    /// The rest rectangle's width and height, m (default: from the geometry).
    pub size: Option<[f64; 2]>,
    /// Gravity the cloth moved under, m/s² (stored as the key `gravity`; default: not stored,
    /// so training assumes `[0, 0, −9.81]`).
    pub gravity: Option<[f64; 3]>,
    /// Rayleigh damping `c` of `−c ẋ` on every point, N·s/m (stored as the key `rayleigh`;
    /// default: not stored, so training fits it).
    pub rayleigh: Option<f64>,
    /// The positions' measurement noise, m per axis (stored as the key `position_noise`;
    /// default: not stored, exact positions).
    pub position_noise: Option<f64>,
    /// Overwrite an existing output file.
    pub force: bool,
}

/// Point positions over time.
#[derive(Debug, Clone)]
pub struct Motion {
    /// Name of the rollout (the output file's stem).
    pub name: String,
    /// Frames `F`.
    pub frames: usize,
    /// Points per frame `N`.
    pub points: usize,
    /// Positions `[F, N, 3]`, row-major; finite wherever the point was seen.
    pub positions: Vec<f32>,
    /// Whether each point was seen in each frame, `[F, N]` (tracked markers); `None`: always.
    pub visible: Option<Vec<bool>>,
    /// The mesh's faces cut into triangles (point indices), when the points come with a mesh;
    /// stored as the key `triangles` when none is degenerate in the rest rectangle.
    pub triangles: Option<Vec<[usize; 3]>>,
}

/// How to find the rest positions of the points.
#[derive(Debug, Clone)]
pub enum RestShape {
    /// Texture coordinates of a mesh: `uv` per point and the mesh's `edges`; the 3-D
    /// `reference` positions give the scale per axis (edge lengths equal in the least-squares
    /// sense).
    Uv {
        /// Texture coordinate of each point.
        uv: Vec<[f64; 2]>,
        /// Unique mesh edges.
        edges: Vec<[usize; 2]>,
        /// The 3-D shape whose edge lengths set the scale.
        reference: Vec<[f64; 3]>,
        /// Where the reference comes from (for messages).
        what: String,
    },
    /// A flat 3-D shape: the rest positions are its coordinates in its plane.
    Flat {
        /// The points.
        reference: Vec<[f64; 3]>,
        /// Where it comes from (for messages).
        what: String,
    },
    /// Rest coordinates in metres.
    Given {
        /// Rest coordinate of each point.
        uv: Vec<[f64; 2]>,
        /// Where they come from (for messages).
        what: String,
    },
}

/// The rest rectangle: landmarks in `[0, width] × [0, height]`.
#[derive(Debug, Clone, PartialEq)]
pub struct RestRectangle {
    /// Rest coordinates per point, m.
    pub rest_uv: Vec<[f64; 2]>,
    /// Width, m.
    pub width: f64,
    /// Height, m.
    pub height: f64,
}

/// What an import wrote.
#[derive(Debug, Clone)]
pub struct ImportSummary {
    /// The rollout file.
    pub path: PathBuf,
    /// Frames.
    pub frames: usize,
    /// Points.
    pub points: usize,
    /// The rest rectangle's size, m.
    pub width: f64,
    /// The rest rectangle's height, m.
    pub height: f64,
    /// How the rest rectangle was found.
    pub rest_from: String,
}

impl std::fmt::Display for ImportSummary {
    /// `path: F frames of N points, rest rectangle W m × H m from …`, as `springtime import`
    /// prints it.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{}: {} frames of {} points, rest rectangle {:.6} m × {:.6} m from {}",
            self.path.display(),
            self.frames,
            self.points,
            self.width,
            self.height,
            self.rest_from
        )
    }
}

/// Whether triangle `t` has no area in the rest rectangle (of area `area`): such a mesh is not
/// stored (rollout loading refuses it), the points alone are.
fn degenerate(rest_uv: &[[f64; 2]], t: &[usize; 3], area: f64) -> bool {
    (0.5 * crate::cloth::twice_area(rest_uv, *t)).abs() <= 1e-12 * area
}

/// Derives the rest rectangle (see [`RestShape`]); `size` overrides the scale per axis.
pub fn rest_rectangle(shape: &RestShape, size: Option<[f64; 2]>) -> Result<RestRectangle> {
    let (mut coords, natural_scale, what) = match shape {
        RestShape::Uv {
            uv,
            edges,
            reference,
            what,
        } => {
            if edges.is_empty() {
                bail!("{what}: no faces, so the texture coordinates cannot be scaled to the sheet");
            }
            (
                uv.clone(),
                uv_scale(uv, edges, reference, what)?,
                what.as_str(),
            )
        }
        RestShape::Flat { reference, what } => (flatten(reference, what)?, [1.0; 2], what.as_str()),
        RestShape::Given { uv, what } => (uv.clone(), [1.0; 2], what.as_str()),
    };
    let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
    for p in &coords {
        for a in 0..2 {
            lo[a] = lo[a].min(p[a]);
            hi[a] = hi[a].max(p[a]);
        }
    }
    let span = [hi[0] - lo[0], hi[1] - lo[1]];
    if !(span[0] > 0.0 && span[1] > 0.0 && span.iter().all(|s| s.is_finite())) {
        bail!(
            "{what}: the rest rectangle cannot be derived: the rest coordinates span {} × {} \
             (the points lie on a line or a point)",
            span[0],
            span[1]
        );
    }
    let scale = match size {
        Some([w, h]) => [w / span[0], h / span[1]],
        None => natural_scale,
    };
    for p in &mut coords {
        for a in 0..2 {
            p[a] = ((p[a] - lo[a]) * scale[a]).clamp(0.0, span[a] * scale[a]);
        }
    }
    Ok(RestRectangle {
        rest_uv: coords,
        width: span[0] * scale[0],
        height: span[1] * scale[1],
    })
}

/// The scale of texture space per axis that makes the mesh's edges as long as in 3-D: the
/// least-squares fit of `L² = su² du² + sv² dv²` over the edges (texture maps are often
/// normalised to the unit square whatever the sheet's aspect ratio); where that is not
/// determined, one scale with equal mean edge lengths.
fn uv_scale(
    uv: &[[f64; 2]],
    edges: &[[usize; 2]],
    reference: &[[f64; 3]],
    what: &str,
) -> Result<[f64; 2]> {
    let (mut m, mut r) = ([[0.0; 2]; 2], [0.0; 2]);
    let (mut sum_uv, mut sum_3d) = (0.0, 0.0);
    for e in edges {
        let (du, dv) = (uv[e[1]][0] - uv[e[0]][0], uv[e[1]][1] - uv[e[0]][1]);
        let l = dist3(reference[e[0]], reference[e[1]]);
        let x = [du * du, dv * dv];
        for i in 0..2 {
            for j in 0..2 {
                m[i][j] += x[i] * x[j];
            }
            r[i] += x[i] * l * l;
        }
        sum_uv += (du * du + dv * dv).sqrt();
        sum_3d += l;
    }
    let det = m[0][0] * m[1][1] - m[0][1] * m[1][0];
    if det > 1e-9 * (m[0][0] * m[1][1]).max(f64::MIN_POSITIVE) {
        let a = (r[0] * m[1][1] - r[1] * m[0][1]) / det;
        let b = (m[0][0] * r[1] - m[1][0] * r[0]) / det;
        if a > 0.0 && b > 0.0 && a.is_finite() && b.is_finite() {
            return Ok([a.sqrt(), b.sqrt()]);
        }
    }
    if !(sum_uv > 0.0) || !(sum_3d > 0.0) {
        bail!(
            "{what}: the rest rectangle cannot be derived: the edges are {sum_uv} long in texture              space and {sum_3d} m in 3-D (give --width and --height)"
        );
    }
    Ok([sum_3d / sum_uv; 2])
}

fn dist3(a: [f64; 3], b: [f64; 3]) -> f64 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
}

/// In-plane coordinates of a flat point set: its best-fit plane (least squares), axes along the
/// smallest bounding rectangle. Errors when the points are not flat.
fn flatten(points: &[[f64; 3]], what: &str) -> Result<Vec<[f64; 2]>> {
    let n = points.len() as f64;
    let mut c = [0.0; 3];
    for p in points {
        for a in 0..3 {
            c[a] += p[a] / n;
        }
    }
    let mut cov = [[0.0; 3]; 3];
    for p in points {
        let d = [p[0] - c[0], p[1] - c[1], p[2] - c[2]];
        for i in 0..3 {
            for j in 0..3 {
                cov[i][j] += d[i] * d[j];
            }
        }
    }
    let (values, vectors) = symmetric_eigen3(cov);
    // Columns sorted by eigenvalue, largest first: two in-plane axes, then the normal.
    let mut order = [0, 1, 2];
    order.sort_by(|&a, &b| values[b].total_cmp(&values[a]));
    let axis = |k: usize| [vectors[0][k], vectors[1][k], vectors[2][k]];
    let (e1, e2, normal) = (axis(order[0]), axis(order[1]), axis(order[2]));
    let dot = |a: [f64; 3], b: [f64; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
    let extent = points.iter().map(|p| dist3(*p, c)).fold(0.0, f64::max);
    let (worst, off) = points
        .iter()
        .enumerate()
        .map(|(i, p)| {
            (
                i,
                dot([p[0] - c[0], p[1] - c[1], p[2] - c[2]], normal).abs(),
            )
        })
        .fold((0, 0.0), |a, b| if b.1 > a.1 { b } else { a });
    if off > 1e-3 * extent {
        bail!(
            "{what} is not flat (point {worst} lies {off:.3e} m off the best plane of a sheet \
             {extent:.3e} m across), so it cannot give the rest rectangle: give texture \
             coordinates (vt) or rest coordinates"
        );
    }
    let planar: Vec<[f64; 2]> = points
        .iter()
        .map(|p| {
            let d = [p[0] - c[0], p[1] - c[1], p[2] - c[2]];
            [dot(d, e1), dot(d, e2)]
        })
        .collect();
    // The rotation with the smallest bounding rectangle: a coarse search, then a fine one.
    let area = |t: f64| {
        let (s, co) = t.sin_cos();
        let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
        for p in &planar {
            let q = [co * p[0] + s * p[1], -s * p[0] + co * p[1]];
            for a in 0..2 {
                lo[a] = lo[a].min(q[a]);
                hi[a] = hi[a].max(q[a]);
            }
        }
        (hi[0] - lo[0]) * (hi[1] - lo[1])
    };
    let best = |from: f64, step: f64, count: usize| {
        (0..=count)
            .map(|i| from + step * i as f64)
            .min_by(|&a, &b| area(a).total_cmp(&area(b)))
            .expect("non-empty")
    };
    let coarse = best(0.0, std::f64::consts::FRAC_PI_2 / 90.0, 90);
    let step = std::f64::consts::FRAC_PI_2 / 9000.0;
    let t = best(coarse - 100.0 * step, step, 200);
    let (s, co) = t.sin_cos();
    Ok(planar
        .iter()
        .map(|p| [co * p[0] + s * p[1], -s * p[0] + co * p[1]])
        .collect())
}

/// Eigenvalues and eigenvectors (columns) of a symmetric 3 × 3 matrix (cyclic Jacobi).
fn symmetric_eigen3(mut a: [[f64; 3]; 3]) -> ([f64; 3], [[f64; 3]; 3]) {
    let mut v = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
    for _ in 0..50 {
        let off = a[0][1].powi(2) + a[0][2].powi(2) + a[1][2].powi(2);
        if off < 1e-30 * (a[0][0].powi(2) + a[1][1].powi(2) + a[2][2].powi(2)).max(1e-300) {
            break;
        }
        for (p, q) in [(0, 1), (0, 2), (1, 2)] {
            if a[p][q] == 0.0 {
                continue;
            }
            let theta = (a[q][q] - a[p][p]) / (2.0 * a[p][q]);
            let t = theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt());
            let t = if theta == 0.0 { 1.0 } else { t };
            let c = 1.0 / (t * t + 1.0).sqrt();
            let s = t * c;
            for k in 0..3 {
                let (akp, akq) = (a[k][p], a[k][q]);
                a[k][p] = c * akp - s * akq;
                a[k][q] = s * akp + c * akq;
            }
            for k in 0..3 {
                let (apk, aqk) = (a[p][k], a[q][k]);
                a[p][k] = c * apk - s * aqk;
                a[q][k] = s * apk + c * aqk;
            }
            for row in &mut v {
                let (vp, vq) = (row[p], row[q]);
                row[p] = c * vp - s * vq;
                row[q] = s * vp + c * vq;
            }
        }
    }
    ([a[0][0], a[1][1], a[2][2]], v)
}

/// Writes `motion` with its rest rectangle as `<out>/<name>.npz` (validated by loading it
/// back). Refuses to overwrite without `force`.
pub fn write_rollout(
    motion: &Motion,
    rest: RestRectangle,
    rest_from: &str,
    options: &ImportOptions,
) -> Result<ImportSummary> {
    check_options(options)?;
    let pinned = pinned_points(motion, options)?;
    let path = options.out.join(format!("{}.npz", motion.name));
    crate::io::refuse_overwrite(&path, options.force)?;
    let (rest, rest_from) = match join_set(&rest, &options.out, &path)? {
        Some((shared, file)) => (
            shared,
            format!(
                "{rest_from}, matched to the set already in {}",
                file.display()
            ),
        ),
        None => (rest, rest_from.to_string()),
    };
    let (mesh, rest_from) = stored_faces(motion, &rest, rest_from);
    let rollout = Rollout {
        path: path.clone(),
        frames: motion.frames,
        landmarks: motion.points,
        positions: motion.positions.clone(),
        velocities: None,
        rest_uv: rest.rest_uv,
        pinned,
        frame_dt: options.frame_dt,
        total_mass: options.total_mass,
        width: rest.width,
        height: rest.height,
        segments: vec![Segment {
            start: 0,
            offset: 0,
            len: motion.frames,
        }],
        springs: None,
        mesh,
        gravity: options.gravity,
        rayleigh: options.rayleigh,
        position_noise: options.position_noise,
        visible: motion
            .visible
            .clone()
            .filter(|seen| !seen.iter().all(|&v| v)),
    };
    rollout.save(&path)?;
    Rollout::load(&path).with_context(|| {
        format!(
            "the imported rollout {} does not validate (a bug in the importer)",
            path.display()
        )
    })?;
    Ok(ImportSummary {
        path,
        frames: motion.frames,
        points: motion.points,
        width: rollout.width,
        height: rollout.height,
        rest_from,
    })
}

/// Checks the options' frame step, mass, gravity and damping.
fn check_options(options: &ImportOptions) -> Result<()> {
    if !(options.frame_dt > 0.0 && options.frame_dt.is_finite()) {
        bail!("--frame-dt must be positive, is {}", options.frame_dt);
    }
    if !(options.total_mass > 0.0 && options.total_mass.is_finite()) {
        bail!("--mass must be positive, is {}", options.total_mass);
    }
    if let Some(g) = options.gravity
        && g.iter().any(|c| !c.is_finite())
    {
        bail!("--gravity must be three finite numbers, is {g:?}");
    }
    if let Some(c) = options.rayleigh
        && !(c >= 0.0 && c.is_finite())
    {
        bail!("--rayleigh must be non-negative, is {c}");
    }
    Ok(())
}

/// The pinned mask of `--pinned`, once the motion has enough frames and points for a rollout.
fn pinned_points(motion: &Motion, options: &ImportOptions) -> Result<Vec<bool>> {
    if motion.frames < 2 {
        bail!(
            "{}: {} frame(s): a rollout needs at least 2",
            motion.name,
            motion.frames
        );
    }
    if motion.points < 3 {
        bail!(
            "{}: {} point(s): a rollout needs at least 3",
            motion.name,
            motion.points
        );
    }
    let mut pinned = vec![false; motion.points];
    for &i in &options.pinned {
        if i >= motion.points {
            bail!(
                "--pinned {i}: there are {} points (indices 0 to {})",
                motion.points,
                motion.points - 1
            );
        }
        pinned[i] = true;
    }
    Ok(pinned)
}

/// The motion's faces as the rollout's mesh, unless one has no area in the rest rectangle:
/// then none, and `rest_from` says why.
fn stored_faces(
    motion: &Motion,
    rest: &RestRectangle,
    rest_from: String,
) -> (Option<MeshTruth>, String) {
    let area = rest.width * rest.height;
    let flat_face = motion
        .triangles
        .as_ref()
        .and_then(|t| t.iter().position(|t| degenerate(&rest.rest_uv, t, area)));
    let mesh = motion
        .triangles
        .as_ref()
        .filter(|t| !t.is_empty() && flat_face.is_none())
        .map(|t| MeshTruth {
            triangles: t.clone(),
            stiffness: None,
        });
    let rest_from = match flat_face {
        Some(i) => format!(
            "{rest_from}; the faces are not stored (`triangles`): triangle {i} of the faces has \
             no area in the rest rectangle"
        ),
        None => rest_from,
    };
    (mesh, rest_from)
}

/// Largest landmark mismatch, as a fraction of the rectangle's size, under which a new import
/// takes the rest rectangle of the rollouts already in its output folder: takes of one cloth
/// imported one by one get their scale from each take's first frame, which differs by float
/// noise (and by the first frame's strain); a set must share one rectangle.
const JOIN_TOLERANCE: f64 = 0.01;

/// The rest rectangle of the first rollout already in `out` (other than `path`), when `rest`
/// has the same landmarks within [`JOIN_TOLERANCE`]; `None` when the folder has none, or
/// they differ (then the new file starts a set of its own, and `data check` says so).
fn join_set(
    rest: &RestRectangle,
    out: &Path,
    path: &Path,
) -> Result<Option<(RestRectangle, PathBuf)>> {
    let Ok(entries) = std::fs::read_dir(out) else {
        return Ok(None);
    };
    let mut files: Vec<PathBuf> = entries
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|e| e == "npz") && p != path)
        .collect();
    files.sort();
    let Some(first) = files.first() else {
        return Ok(None);
    };
    let Ok(other) = Rollout::load(first) else {
        return Ok(None);
    };
    if other.rest_uv.len() != rest.rest_uv.len() {
        return Ok(None);
    }
    let size = other.width.max(other.height);
    let worst = other
        .rest_uv
        .iter()
        .zip(&rest.rest_uv)
        .map(|(a, b)| (a[0] - b[0]).hypot(a[1] - b[1]))
        .fold(0.0, f64::max);
    if worst > JOIN_TOLERANCE * size {
        eprintln!(
            "warning: the rest rectangle differs from {} by up to {worst:.3e} m ({:.2} % of its \
             size): this file starts a set of its own (same cloth? import with the same \
             --width/--height)",
            first.display(),
            100.0 * worst / size
        );
        return Ok(None);
    }
    Ok(Some((
        RestRectangle {
            rest_uv: other.rest_uv,
            width: other.width,
            height: other.height,
        },
        first.clone(),
    )))
}

/// Parses a list of point indices `I,J,…` (0-based).
pub fn parse_indices(text: &str) -> std::result::Result<Vec<usize>, String> {
    text.split(',')
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .map(|s| {
            s.parse::<usize>()
                .map_err(|_| format!("`{s}` is not a point index (0, 1, 2, …)"))
        })
        .collect()
}

/// The file stem of `path` (the rollout's default name).
pub(crate) fn stem(path: &Path) -> String {
    path.file_stem()
        .or_else(|| path.file_name())
        .map(|s| s.to_string_lossy().into_owned())
        .filter(|s| !s.is_empty() && s != "." && s != "..")
        .unwrap_or_else(|| "imported".into())
}

/// The name of folder `dir` (resolving `.` and `..`).
pub(crate) fn folder_name(dir: &Path) -> String {
    dir.canonicalize()
        .ok()
        .as_deref()
        .and_then(Path::file_name)
        .or_else(|| dir.file_name())
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| "imported".into())
}

/// Orders names with their digit runs compared as numbers (`frame_2` before `frame_10`).
pub(crate) fn natural_cmp(a: &str, b: &str) -> std::cmp::Ordering {
    fn chunks(s: &str) -> Vec<(bool, String)> {
        let mut out: Vec<(bool, String)> = Vec::new();
        for c in s.chars() {
            let digit = c.is_ascii_digit();
            match out.last_mut() {
                Some((d, text)) if *d == digit => text.push(c),
                _ => out.push((digit, c.to_string())),
            }
        }
        out
    }
    let (ca, cb) = (chunks(a), chunks(b));
    for (x, y) in ca.iter().zip(&cb) {
        let ord = match (x, y) {
            ((true, p), (true, q)) => {
                let (p, q) = (p.trim_start_matches('0'), q.trim_start_matches('0'));
                p.len().cmp(&q.len()).then_with(|| p.cmp(q))
            }
            _ => x.1.cmp(&y.1),
        };
        if ord.is_ne() {
            return ord;
        }
    }
    ca.len().cmp(&cb.len()).then_with(|| a.cmp(b))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_tilted_flat_sheet_unrolls_to_its_rectangle() {
        // A 3 m × 2 m grid rotated about two axes and shifted.
        let (ca, sa) = (0.6f64.cos(), 0.6f64.sin());
        let (cb, sb) = (0.3f64.cos(), 0.3f64.sin());
        let mut pts = Vec::new();
        for j in 0..5 {
            for i in 0..7 {
                let (x, y) = (i as f64 * 0.5, j as f64 * 0.5);
                let (x, z) = (ca * x, sa * x);
                let (y, z) = (cb * y - sb * z, sb * y + cb * z);
                pts.push([x + 10.0, y - 3.0, z + 1.0]);
            }
        }
        let shape = RestShape::Flat {
            reference: pts,
            what: "test".into(),
        };
        let r = rest_rectangle(&shape, None).unwrap();
        let (w, h) = (r.width.max(r.height), r.width.min(r.height));
        assert!(
            (w - 3.0).abs() < 1e-6 && (h - 2.0).abs() < 1e-6,
            "{w} × {h}"
        );
        let r = rest_rectangle(&shape, Some([6.0, 4.0])).unwrap();
        assert_eq!((r.width, r.height), (6.0, 4.0));
    }

    #[test]
    fn names_sort_naturally_and_indices_parse() {
        let mut v = vec!["f10.obj", "f2.obj", "f1.obj", "f02b.obj"];
        v.sort_by(|a, b| natural_cmp(a, b));
        assert_eq!(v, ["f1.obj", "f2.obj", "f02b.obj", "f10.obj"]);
        assert_eq!(parse_indices("0, 5,7").unwrap(), [0, 5, 7]);
        assert!(parse_indices("1,x").is_err());
    }
}
