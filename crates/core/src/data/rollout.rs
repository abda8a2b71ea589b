//! One recorded rollout: the `.npz` format that the sources write and users bring.
//!
//! | key | dtype | shape | meaning |
//! |---|---|---|---|
//! | `positions` | f32 | `[F, N, 3]` | landmark positions per frame, m |
//! | `rest_uv` | f32 | `[N, 2]` | landmark positions in the unrolled rest rectangle, m |
//! | `pinned` | bool | `[N]` | landmarks that follow a prescribed path |
//! | `frame_dt` | f64 | scalar | time between frames, s |
//! | `total_mass` | f64 | scalar | mass of the whole cloth, kg |
//! | `width`, `height` | f64 | scalar | size of the rest rectangle, m |
//! | `velocities` | f32 | `[F, N, 3]` | optional; landmark velocities per frame, m/s |
//! | `visible` | bool | `[F, N]` | optional; whether each landmark was seen in each frame (tracked markers: occlusions, dropped tracks). A hidden landmark's position (and velocity) may be NaN; the reader fills it from its seen frames before and after, carried by the motion of its nearest seen neighbours (`fill_hidden`), which serves only as a start state or a pin's path: every loss, fit and motion RMSE of the spring network and the Neural ODE skips hidden landmarks (the per-spring least-squares fit reads a spring's far end from the fill across a gap of at most `train.least_squares.bridge` frames; the GNN baseline reads the filled positions). Absent, or all true: every landmark seen |
//! | `position_noise` | f64 | scalar | optional; the positions' measurement noise, m per axis (a capture's marker accuracy): `train.least_squares.noise = "auto"` takes it (absent: exact positions) |
//! | `segments` | i64 | `[K, 2]` | optional; `(first frame, frame count)` of each stored window of a longer rollout, in order (default: one window from frame 0) |
//! | `springs`, `spring_k`, `spring_b` | i32, f32, f32 | `[S, 2]`, `[S]`, `[S]` | optional ground truth of a mass-spring source |
//! | `triangles` | i32 | `[M, 3]` | optional; the landmarks' triangle mesh (the surrogate's springs with `cloth.layout = "data"`) |
//! | `tri_stiffness` | f32 | `[M]` | optional, with `triangles`; the stiffness map of an FEM source (ground truth) |
//!
//! Unknown keys are ignored, whatever their dtype ([`KEYS`] are the known ones). Loading validates shapes, dtypes, ranges and finiteness; every
//! error names the file and the key.

use std::path::{Path, PathBuf};

use anyhow::{Result, bail};

use super::npz::{Array, Npz};

/// A stored window of a rollout's timeline.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Segment {
    /// Index of the window's first frame in the full rollout.
    pub start: usize,
    /// Index of the window's first frame in the stored arrays.
    pub offset: usize,
    /// Number of frames.
    pub len: usize,
}

/// Ground-truth springs of a mass-spring source.
#[derive(Debug, Clone, PartialEq)]
pub struct SpringTruth {
    /// Endpoints, indices into the landmarks.
    pub springs: Vec<[usize; 2]>,
    /// Stiffness, N/m.
    pub k: Vec<f64>,
    /// Damping, N·s/m.
    pub b: Vec<f64>,
}

/// The landmarks' triangle mesh, with an FEM source's per-triangle stiffness.
#[derive(Debug, Clone, PartialEq)]
pub struct MeshTruth {
    /// Triangles, indices into the landmarks.
    pub triangles: Vec<[usize; 3]>,
    /// Stiffness map value of every triangle.
    pub stiffness: Option<Vec<f64>>,
}

/// One rollout as stored on disk.
#[derive(Debug, Clone)]
pub struct Rollout {
    /// Where it was read from (or will be written to).
    pub path: PathBuf,
    /// Number of stored frames `F`.
    pub frames: usize,
    /// Number of landmarks `N`.
    pub landmarks: usize,
    /// Positions `[F, N, 3]`, row-major.
    pub positions: Vec<f32>,
    /// Velocities `[F, N, 3]` if recorded.
    pub velocities: Option<Vec<f32>>,
    /// Rest positions in the unrolled rectangle.
    pub rest_uv: Vec<[f64; 2]>,
    /// Pinned landmarks.
    pub pinned: Vec<bool>,
    /// Time between frames, s.
    pub frame_dt: f64,
    /// Mass of the cloth, kg.
    pub total_mass: f64,
    /// Rest rectangle width, m.
    pub width: f64,
    /// Rest rectangle height, m.
    pub height: f64,
    /// Stored windows of the timeline.
    pub segments: Vec<Segment>,
    /// Ground-truth springs, when the source is a mass-spring network.
    pub springs: Option<SpringTruth>,
    /// Mesh and stiffness map, when the source is an FEM mesh.
    pub mesh: Option<MeshTruth>,
    /// Gravity the cloth moved under, m/s² (key `gravity`), when the file says.
    pub gravity: Option<[f64; 3]>,
    /// Rayleigh damping `c` of `−c ẋ` on every landmark, N·s/m, the landmarks sharing
    /// `total_mass` equally (key `rayleigh`), when the file says.
    pub rayleigh: Option<f64>,
    /// Whether each landmark was seen in each frame, `[F, N]` (key `visible`); `None` when
    /// every landmark was seen in every frame. Hidden positions hold the reader's fill.
    pub visible: Option<Vec<bool>>,
    /// The positions' measurement noise, m per axis (key `position_noise`), when the file says.
    pub position_noise: Option<f64>,
}

/// The plausible range `(low, high, unit)` of a rollout's scalar `key` (SI units, generous for
/// any cloth from a 1 cm swatch at 1 MHz to a 1 km sail at one frame a second): a value outside
/// is a unit mix-up or a damaged file, which the reader refuses naming the file and the key
/// instead of letting a later stage fail without them.
pub(crate) fn plausible_range(key: &str) -> (f64, f64, &'static str) {
    match key {
        "frame_dt" => (1e-6, 1.0, "s"),
        "total_mass" => (1e-6, 1e4, "kg"),
        "width" | "height" => (1e-3, 1e3, "m"),
        _ => (f64::MIN_POSITIVE, f64::MAX, ""),
    }
}

/// The largest plausible gravity, m/s² (ten times Jupiter's surface gravity).
const MAX_GRAVITY: f64 = 250.0;

/// The keys a rollout file may hold; any other key is ignored.
pub const KEYS: &[&str] = &[
    "positions",
    "rest_uv",
    "pinned",
    "frame_dt",
    "total_mass",
    "width",
    "height",
    "velocities",
    "segments",
    "springs",
    "spring_k",
    "spring_b",
    "triangles",
    "tri_stiffness",
    "gravity",
    "rayleigh",
    "visible",
    "position_noise",
];

impl Rollout {
    /// The first frame a simulation can start from: frame 0 when velocities are stored, else
    /// frame 1 (its velocity is the backward difference to frame 0).
    pub fn first_usable_frame(&self) -> usize {
        if self.velocities.is_some() { 0 } else { 1 }
    }

    /// The frame a free simulation of the whole take starts from: the first usable frame, or,
    /// where landmarks are hidden from the take's first frame, the first whose state every
    /// landmark's seen frames give (the last landmark's first seen frame, plus one where
    /// velocities are differences of positions). Before it, a hidden landmark's state is
    /// extrapolated from later frames alone — centimetres off at a free corner — and a stiff
    /// network released from it rings. At most half the take is skipped. The first usable frame
    /// for a rollout stored in windows (`segments`) or with every landmark seen.
    pub fn first_state_frame(&self) -> usize {
        let first = self.first_usable_frame();
        let (Some(seen), [_]) = (&self.visible, self.segments.as_slice()) else {
            return first;
        };
        let n = self.landmarks;
        let observed = (0..n)
            .map(|i| (0..self.frames).find(|&f| seen[f * n + i]).unwrap_or(0))
            .max()
            .unwrap_or(0);
        first.max((observed + first).min((self.frames - 1) / 2))
    }

    /// Reads and validates a rollout file.
    pub fn load(path: &Path) -> Result<Self> {
        Self::from_npz(&Npz::read(path)?)
    }

    /// Validates the arrays of a rollout file read with [`Npz::read`].
    pub fn from_npz(npz: &Npz) -> Result<Self> {
        let path = npz.path.as_path();
        let shown = path.display();
        // Every landmark seen: every value must be finite; else the hidden ones may be NaN.
        let (mut positions, shape) = if npz.has("visible") {
            npz.f32_any("positions", &[None, None, Some(3)])?
        } else {
            npz.f32("positions", &[None, None, Some(3)])?
        };
        let (frames, n) = (shape[0], shape[1]);
        if frames < 2 || n < 3 {
            bail!(
                "{shown}: key `positions` has shape {shape:?}: need at least 2 frames and 3 landmarks"
            );
        }
        let (uv, _) = npz.f32("rest_uv", &[Some(n), Some(2)])?;
        let rest_uv: Vec<[f64; 2]> = uv
            .chunks_exact(2)
            .map(|c| [c[0] as f64, c[1] as f64])
            .collect();
        let visible = if npz.has("visible") {
            let seen = npz.bool("visible", &[Some(frames), Some(n)])?;
            fill_hidden(&shown, "positions", &mut positions, &seen, &rest_uv)?;
            (!seen.iter().all(|&v| v)).then_some(seen)
        } else {
            None
        };
        let velocities = velocities_of(npz, frames, visible.as_deref(), &rest_uv)?;
        let pinned = npz.bool("pinned", &[Some(n)])?;
        let frame_dt = plausible(npz, "frame_dt")?;
        let total_mass = plausible(npz, "total_mass")?;
        let width = plausible(npz, "width")?;
        let height = plausible(npz, "height")?;
        check_rest_uv(npz, &rest_uv, width, height)?;
        Ok(Self {
            path: path.to_path_buf(),
            frames,
            landmarks: n,
            positions,
            velocities,
            segments: segments_of(npz, frames)?,
            springs: springs_of(npz, n)?,
            mesh: mesh_of(npz, &rest_uv, [width, height])?,
            gravity: gravity_of(npz)?,
            rayleigh: rayleigh_of(npz)?,
            position_noise: position_noise_of(npz)?,
            rest_uv,
            pinned,
            frame_dt,
            total_mass,
            width,
            height,
            visible,
        })
    }

    /// Writes the rollout to `path` atomically.
    pub fn save(&self, path: &Path) -> Result<()> {
        let (f, n) = (self.frames, self.landmarks);
        let mut npz = Npz::default();
        npz.insert("positions", Array::f32(&[f, n, 3], &self.positions));
        if let Some(v) = &self.velocities {
            npz.insert("velocities", Array::f32(&[f, n, 3], v));
        }
        let uv: Vec<f32> = self
            .rest_uv
            .iter()
            .flat_map(|p| [p[0] as f32, p[1] as f32])
            .collect();
        npz.insert("rest_uv", Array::f32(&[n, 2], &uv));
        npz.insert("pinned", Array::bool(&[n], &self.pinned));
        npz.insert("frame_dt", Array::scalar(self.frame_dt));
        npz.insert("total_mass", Array::scalar(self.total_mass));
        npz.insert("width", Array::scalar(self.width));
        npz.insert("height", Array::scalar(self.height));
        if let Some(g) = self.gravity {
            npz.insert("gravity", Array::f64(&[3], &g));
        }
        if let Some(c) = self.rayleigh {
            npz.insert("rayleigh", Array::scalar(c));
        }
        if let Some(seen) = &self.visible {
            npz.insert("visible", Array::bool(&[f, n], seen));
        }
        if let Some(sigma) = self.position_noise {
            npz.insert("position_noise", Array::scalar(sigma));
        }
        let whole = self.segments.len() == 1 && self.segments[0].start == 0;
        if !whole {
            let seg: Vec<i64> = self
                .segments
                .iter()
                .flat_map(|s| [s.start as i64, s.len as i64])
                .collect();
            npz.insert("segments", Array::i64(&[self.segments.len(), 2], &seg));
        }
        if let Some(t) = &self.springs {
            let s = t.springs.len();
            let ends: Vec<i32> = t
                .springs
                .iter()
                .flat_map(|e| [e[0] as i32, e[1] as i32])
                .collect();
            npz.insert("springs", Array::i32(&[s, 2], &ends));
            let f32s = |v: &[f64]| v.iter().map(|&x| x as f32).collect::<Vec<_>>();
            npz.insert("spring_k", Array::f32(&[s], &f32s(&t.k)));
            npz.insert("spring_b", Array::f32(&[s], &f32s(&t.b)));
        }
        if let Some(m) = &self.mesh {
            let tri: Vec<i32> = m
                .triangles
                .iter()
                .flat_map(|t| t.map(|i| i as i32))
                .collect();
            npz.insert("triangles", Array::i32(&[m.triangles.len(), 3], &tri));
            if let Some(st) = &m.stiffness {
                let st: Vec<f32> = st.iter().map(|&x| x as f32).collect();
                npz.insert("tri_stiffness", Array::f32(&[m.triangles.len()], &st));
            }
        }
        npz.write(path)
    }

    /// Number of frames of the full timeline (the end of the last stored window).
    pub(crate) fn timeline_frames(&self) -> usize {
        self.segments.last().map_or(0, |s| s.start + s.len)
    }

    /// Whether landmark `i` was seen in stored frame `f`.
    pub fn seen(&self, f: usize, i: usize) -> bool {
        self.visible
            .as_ref()
            .is_none_or(|v| v[f * self.landmarks + i])
    }

    /// Position of landmark `i` at stored frame `f`.
    pub fn position(&self, f: usize, i: usize) -> [f32; 3] {
        let o = (f * self.landmarks + i) * 3;
        [
            self.positions[o],
            self.positions[o + 1],
            self.positions[o + 2],
        ]
    }
}

/// Landmarks whose motion fills a hidden one's: the nearest seen ones in the rest rectangle.
const FILL_NEIGHBOURS: usize = 6;

/// Candidates searched for them, nearest first.
const FILL_CANDIDATES: usize = 32;

/// The stored velocities, if any, with the hidden ones filled like the positions.
fn velocities_of(
    npz: &Npz,
    frames: usize,
    visible: Option<&[bool]>,
    rest_uv: &[[f64; 2]],
) -> Result<Option<Vec<f32>>> {
    if !npz.has("velocities") {
        return Ok(None);
    }
    let shape = [Some(frames), Some(rest_uv.len()), Some(3)];
    Ok(Some(match visible {
        None => npz.f32("velocities", &shape)?.0,
        Some(seen) => {
            let (mut v, _) = npz.f32_any("velocities", &shape)?;
            fill_hidden(&npz.path.display(), "velocities", &mut v, seen, rest_uv)?;
            v
        }
    }))
}

/// The positive scalar `key`, refused outside the plausible range for cloth.
fn plausible(npz: &Npz, key: &str) -> Result<f64> {
    let shown = npz.path.display();
    let v = npz.scalar(key)?;
    if v <= 0.0 {
        bail!("{shown}: key `{key}` must be positive, is {v}");
    }
    let (lo, hi, unit) = plausible_range(key);
    if !(lo..=hi).contains(&v) {
        bail!(
            "{shown}: key `{key}` is {v} {unit}, outside the plausible {lo:e}–{hi:e} {unit} \
             for cloth (a unit mix-up or a damaged file?)"
        );
    }
    Ok(v)
}

/// Refuses a rest coordinate outside the `width` × `height` rectangle (beyond a tolerance).
fn check_rest_uv(npz: &Npz, rest_uv: &[[f64; 2]], width: f64, height: f64) -> Result<()> {
    let tol = 1e-4 * width.max(height);
    if let Some((i, p)) = rest_uv
        .iter()
        .enumerate()
        .find(|(_, p)| p[0] < -tol || p[0] > width + tol || p[1] < -tol || p[1] > height + tol)
    {
        bail!(
            "{}: key `rest_uv`: landmark {i} at ({}, {}) lies outside the {width} × {height} rest rectangle",
            npz.path.display(),
            p[0],
            p[1]
        );
    }
    Ok(())
}

/// The key `segments` (one whole segment without it), checked to cover the `frames`.
fn segments_of(npz: &Npz, frames: usize) -> Result<Vec<Segment>> {
    let shown = npz.path.display();
    if !npz.has("segments") {
        return Ok(vec![Segment {
            start: 0,
            offset: 0,
            len: frames,
        }]);
    }
    let (seg, _) = npz.int("segments", &[None, Some(2)])?;
    let mut out = Vec::new();
    let (mut offset, mut end) = (0usize, 0usize);
    for (i, w) in seg.chunks_exact(2).enumerate() {
        if w[0] < 0 || w[1] < 1 || (w[0] as usize) < end {
            bail!(
                "{shown}: key `segments`: row {i} = ({}, {}) must start at or after frame {end} and hold at least one frame",
                w[0],
                w[1]
            );
        }
        out.push(Segment {
            start: w[0] as usize,
            offset,
            len: w[1] as usize,
        });
        offset += w[1] as usize;
        end = (w[0] + w[1]) as usize;
    }
    if offset != frames {
        bail!("{shown}: key `segments` covers {offset} frames, `positions` holds {frames}");
    }
    Ok(out)
}

/// The source's springs (`springs`, `spring_k`, `spring_b`), when stored.
fn springs_of(npz: &Npz, n: usize) -> Result<Option<SpringTruth>> {
    if !npz.has("springs") {
        return Ok(None);
    }
    let (ends, _) = npz.int("springs", &[None, Some(2)])?;
    let s = ends.len() / 2;
    check_indices(&npz.path.display(), "springs", &ends, n)?;
    let k = npz.f32("spring_k", &[Some(s)])?.0;
    let b = npz.f32("spring_b", &[Some(s)])?.0;
    Ok(Some(SpringTruth {
        springs: ends
            .chunks_exact(2)
            .map(|c| [c[0] as usize, c[1] as usize])
            .collect(),
        k: k.into_iter().map(f64::from).collect(),
        b: b.into_iter().map(f64::from).collect(),
    }))
}

/// The source's triangles and their stiffness map, when stored; a degenerate triangle (zero
/// rest area relative to the `[width, height]` rectangle) is refused.
fn mesh_of(
    npz: &Npz,
    rest_uv: &[[f64; 2]],
    [width, height]: [f64; 2],
) -> Result<Option<MeshTruth>> {
    let shown = npz.path.display();
    if npz.has("tri_stiffness") && !npz.has("triangles") {
        bail!("{shown}: key `tri_stiffness` needs the key `triangles` it maps");
    }
    if !npz.has("triangles") {
        return Ok(None);
    }
    let (tri, _) = npz.int("triangles", &[None, Some(3)])?;
    let m = tri.len() / 3;
    check_indices(&shown, "triangles", &tri, rest_uv.len())?;
    let triangles: Vec<[usize; 3]> = tri
        .chunks_exact(3)
        .map(|c| [c[0] as usize, c[1] as usize, c[2] as usize])
        .collect();
    for (i, t) in triangles.iter().enumerate() {
        let (a, b, c) = (rest_uv[t[0]], rest_uv[t[1]], rest_uv[t[2]]);
        let area = 0.5 * ((b[0] - a[0]) * (c[1] - a[1]) - (c[0] - a[0]) * (b[1] - a[1]));
        if area.abs() <= 1e-12 * width * height {
            bail!("{shown}: key `triangles`: triangle {i} {t:?} is degenerate (zero rest area)");
        }
    }
    let stiffness = if npz.has("tri_stiffness") {
        let st = npz.f32("tri_stiffness", &[Some(m)])?.0;
        Some(st.into_iter().map(f64::from).collect())
    } else {
        None
    };
    Ok(Some(MeshTruth {
        triangles,
        stiffness,
    }))
}

/// The key `gravity`, when stored, refused beyond a plausible length.
fn gravity_of(npz: &Npz) -> Result<Option<[f64; 3]>> {
    if !npz.has("gravity") {
        return Ok(None);
    }
    let (g, _) = npz.f32("gravity", &[Some(3)])?;
    let g = [g[0] as f64, g[1] as f64, g[2] as f64];
    let norm = g.iter().map(|c| c * c).sum::<f64>().sqrt();
    if !(norm <= MAX_GRAVITY) {
        bail!(
            "{}: key `gravity` is {g:?} m/s² ({norm} m/s² long), beyond the plausible \
             {MAX_GRAVITY} m/s² (a unit mix-up or a damaged file?)",
            npz.path.display()
        );
    }
    Ok(Some(g))
}

/// The key `rayleigh`, when stored, refused when negative.
fn rayleigh_of(npz: &Npz) -> Result<Option<f64>> {
    if !npz.has("rayleigh") {
        return Ok(None);
    }
    let c = npz.scalar("rayleigh")?;
    if !(c >= 0.0) {
        bail!(
            "{}: key `rayleigh` must be non-negative, is {c}",
            npz.path.display()
        );
    }
    Ok(Some(c))
}

/// The largest plausible measurement noise, m per axis (beyond it, a unit mix-up: millimetres
/// written as metres).
const MAX_POSITION_NOISE: f64 = 0.1;

fn position_noise_of(npz: &Npz) -> Result<Option<f64>> {
    if !npz.has("position_noise") {
        return Ok(None);
    }
    let sigma = npz.scalar("position_noise")?;
    if !(0.0..=MAX_POSITION_NOISE).contains(&sigma) {
        bail!(
            "{}: key `position_noise` must be a standard deviation in m per axis, from 0 to \
             {MAX_POSITION_NOISE} m, is {sigma}",
            npz.path.display()
        );
    }
    Ok(Some(sigma))
}

/// Checks that `values` (`[F, N, 3]`, of `key`) are finite wherever `seen`, then fills each
/// hidden value of a landmark from its seen frames `a` before and `b` after, carried by its
/// neighbours: from `a`, its value there plus the mean change since `a` of the
/// [`FILL_NEIGHBOURS`] nearest landmarks (in `rest_uv`) seen at both frames; likewise from `b`;
/// the two blended linearly in time (one of them before the first seen frame or after the
/// last). A sheet that moves as a whole is filled exactly, however it moves during an
/// occlusion; a landmark with no seen neighbour keeps its value at `a` and `b`, blended.
/// Refuses a landmark seen in no frame.
fn fill_hidden(
    shown: &std::path::Display<'_>,
    key: &str,
    values: &mut [f32],
    seen: &[bool],
    rest_uv: &[[f64; 2]],
) -> Result<()> {
    let n = rest_uv.len();
    let frames = seen.len() / n;
    check_seen_finite(shown, key, values, seen, n)?;
    let source: Vec<f32> = values.to_vec();
    let at = |f: usize, i: usize| -> [f64; 3] {
        let o = (f * n + i) * 3;
        [source[o] as f64, source[o + 1] as f64, source[o + 2] as f64]
    };
    for i in 0..n {
        let known: Vec<usize> = (0..frames).filter(|&f| seen[f * n + i]).collect();
        if known.is_empty() {
            bail!(
                "{shown}: key `visible`: landmark {i} is seen in no frame (drop it from the file, \
                 or mark the frames it was seen in)"
            );
        }
        if known.len() == frames {
            continue;
        }
        let near = nearest_landmarks(rest_uv, i);
        // Landmark i at hidden frame f carried from its seen frame r by its neighbours.
        let carried = |f: usize, r: usize| -> [f64; 3] {
            let mut x = at(r, i);
            let movers: Vec<usize> = near
                .iter()
                .map(|&(_, j)| j)
                .filter(|&j| seen[f * n + j] && seen[r * n + j])
                .take(FILL_NEIGHBOURS)
                .collect();
            for &j in &movers {
                let (now, then) = (at(f, j), at(r, j));
                for c in 0..3 {
                    x[c] += (now[c] - then[c]) / movers.len() as f64;
                }
            }
            x
        };
        let mut next = 0usize; // index into `known` of the first seen frame after f
        for f in 0..frames {
            if seen[f * n + i] {
                next += 1;
                continue;
            }
            let (a, b) = (
                next.checked_sub(1).map(|k| known[k]),
                known.get(next).copied(),
            );
            let x = match (a, b) {
                (Some(a), Some(b)) => {
                    let s = (f - a) as f64 / (b - a) as f64;
                    let (xa, xb) = (carried(f, a), carried(f, b));
                    [0, 1, 2].map(|c| xa[c] + s * (xb[c] - xa[c]))
                }
                (Some(a), None) => carried(f, a),
                (None, Some(b)) => carried(f, b),
                (None, None) => unreachable!("landmark {i} is seen in some frame"),
            };
            for c in 0..3 {
                values[(f * n + i) * 3 + c] = x[c] as f32;
            }
        }
    }
    Ok(())
}

/// Refuses a non-finite value of `key` (`[F, N, 3]`) where `seen` says its landmark was seen.
fn check_seen_finite(
    shown: &std::path::Display<'_>,
    key: &str,
    values: &[f32],
    seen: &[bool],
    n: usize,
) -> Result<()> {
    for (at, chunk) in values.chunks_exact(3).enumerate() {
        if seen[at] && chunk.iter().any(|c| !c.is_finite()) {
            bail!(
                "{shown}: key `{key}`: landmark {} of frame {} is {chunk:?}, but `visible` says it \
                 was seen (a hidden landmark is marked false in `visible`)",
                at % n,
                at / n
            );
        }
    }
    Ok(())
}

/// The [`FILL_CANDIDATES`] landmarks nearest to landmark `i` in the rest rectangle, nearest
/// first, as (squared distance, index).
fn nearest_landmarks(rest_uv: &[[f64; 2]], i: usize) -> Vec<(f64, usize)> {
    let mut near: Vec<(f64, usize)> = (0..rest_uv.len())
        .filter(|&j| j != i)
        .map(|j| {
            let d =
                (rest_uv[j][0] - rest_uv[i][0]).powi(2) + (rest_uv[j][1] - rest_uv[i][1]).powi(2);
            (d, j)
        })
        .collect();
    let keep = FILL_CANDIDATES.min(near.len());
    if keep < near.len() {
        near.select_nth_unstable_by(keep, |a, b| a.0.total_cmp(&b.0));
        near.truncate(keep);
    }
    near.sort_by(|a, b| a.0.total_cmp(&b.0));
    near
}

fn check_indices(shown: &std::path::Display<'_>, key: &str, idx: &[i64], n: usize) -> Result<()> {
    if let Some((i, &v)) = idx
        .iter()
        .enumerate()
        .find(|(_, v)| **v < 0 || **v as usize >= n)
    {
        bail!("{shown}: key `{key}`: entry {i} = {v} is not a landmark index (0..{n})");
    }
    Ok(())
}
