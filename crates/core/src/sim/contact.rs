//! Contact with colliders: ground planes, spheres, capsules, rounded boxes and triangle meshes
//! read from OBJ files, static or moving along a prescribed path (paper §4.5, App. B.1).
//!
//! The model, per particle of mass `m` and collider with signed distance `d` (positive
//! outside), outward normal `n` at the closest surface point and surface velocity `u`:
//! - **normal**: a penalty force inside the contact layer of thickness `δ`,
//!   `f_n = m (κ φ + ζ max(0, −n·(v − u)))`, `φ = max(0, δ − d)`: a contact *pressure* (force
//!   per unit mass, so the same `κ` [1/s²] and `ζ` [1/s] hold at every resolution), damped on
//!   approach only, so the cloth does not stick to the surface;
//! - **friction**: Coulomb, regularised by the step: with `w` the tangential part of the
//!   velocity `v* = v + h/m (f + f_n n)` the other forces would give after the step `h`,
//!   `f_t = −min(μ f_n / |w|, m/h) w` (with `|w|² + 10⁻²⁴` under the root) — sliding friction `μ f_n` against the motion, and below
//!   that limit exactly the force that stops the tangential motion (static friction), which
//!   never reverses a velocity and so adds nothing to the step's stability limit.
//!
//! The guard ([`Stability::with_contact`]) adds `κ` to `ω²` and `ζ` to `γ`. The geometry
//! queries (closest point, inside/outside, BVH of meshes) are parry3d's, except a rounded box's
//! rounding, added here to its inner box's exact projection (parry projects onto round shapes
//! by GJK, 1e-5 m off at worst on `tests/contact.rs`'s points); the force is computed
//! by one host function ([`Contact::apply`], the FEM and mass-spring sources) and by the same
//! formula in tensor ops ([`Contact::apply_tensor`], the surrogate and the Neural ODE:
//! differentiable in the positions and velocities, with the contact normals and closest points
//! held at their values at the start of the step).

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

use anyhow::{Context, Result, bail};
use burn::tensor::{Tensor, TensorData};
use parry3d_f64::bounding_volume::{Aabb, BoundingVolume};
use parry3d_f64::math::{Pose, Rot3, Vector};
use parry3d_f64::query::PointQuery;
use parry3d_f64::shape::{SharedShape, TriMesh, TriMeshFlags};
use serde::{Deserialize, Serialize};

use crate::settings::Auto;

use super::Stability;

type V3 = [f64; 3];

/// What a collider is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ColliderKind {
    /// The half-space below the plane `z = 0` of the collider's frame (tilt it by rotating).
    Plane,
    /// A ball of `radius`.
    Sphere,
    /// A capsule along the frame's z axis: `half_height` of its segment, `radius`.
    Capsule,
    /// A box of `half_extents` whose edges and corners are rounded by `radius` (continuous
    /// normals everywhere; the outer half-size is `half_extents + radius`).
    RoundedBox,
    /// A closed, consistently oriented triangle mesh from the OBJ file `mesh`, scaled by
    /// `scale`.
    Mesh,
}

/// One `[[scene.colliders]]` entry.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ColliderConfig {
    /// The shape.
    pub kind: ColliderKind,
    /// Radius, m (sphere, capsule, rounded box).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub radius: Option<f64>,
    /// Half length of a capsule's segment, m.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub half_height: Option<f64>,
    /// Half sizes of a rounded box's inner box, m.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub half_extents: Option<[f64; 3]>,
    /// OBJ file of a mesh collider; a relative path resolves against the scene file.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mesh: Option<PathBuf>,
    /// Scale of a mesh's coordinates.
    #[serde(default = "one")]
    pub scale: f64,
    /// Position of the collider's frame, m.
    #[serde(default)]
    pub translation: V3,
    /// Rotation of the collider's frame: degrees about the x, then the y, then the z axis
    /// (fixed axes).
    #[serde(default)]
    pub rotation_deg: V3,
    /// Coulomb friction coefficient μ.
    #[serde(default = "default_friction")]
    pub friction: f64,
    /// Prescribed motion: `[t, dx, dy, dz]` keyframes (s, m) of an offset added to
    /// `translation`, linear between keyframes and held outside them; empty: static.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub path: Vec<[f64; 4]>,
}

fn one() -> f64 {
    1.0
}

fn default_friction() -> f64 {
    0.5
}

/// The `[scene.contact]` section: the contact layer and its pressure.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ContactConfig {
    /// Contact thickness δ, m: the penalty acts within this distance of a surface;
    /// `"auto"`: 1 % of the sheet's larger side.
    pub thickness: Auto<f64>,
    /// Contact stiffness κ per unit mass, 1/s²; `"auto"`: `0.25/h²` for the surrogate's step
    /// `h` (adds 0.25 to `h²ω²`; a particle resting on a surface sinks `g/κ` into the layer),
    /// less where the surrogate is near its stability limit (see [`ContactConfig::resolve`]).
    pub stiffness: Auto<f64>,
    /// Approach damping ζ per unit mass, 1/s; `"auto"`: `0.25/h` (adds 0.5 to `2hγ`), scaled
    /// with the stiffness.
    pub damping: Auto<f64>,
}

impl Default for ContactConfig {
    fn default() -> Self {
        Self {
            thickness: Auto::Auto,
            stiffness: Auto::Auto,
            damping: Auto::Auto,
        }
    }
}

impl ContactConfig {
    /// The constants for a sheet whose larger side is `size` (m), stepped at `h` (s), whose
    /// own stability number `dt²ω² + 2·dt·γ` is `number`. The automatic stiffness and damping
    /// add 0.25 + 0.5 to it, scaled down together when that would pass 3.9 (a surrogate that
    /// training left near its stability limit gets a softer layer instead of a refusal).
    pub fn resolve(&self, size: f64, h: f64, number: f64) -> ContactParams {
        let s = ((3.9 - number) / 0.75).clamp(0.02, 1.0);
        ContactParams {
            thickness: self.thickness.or(0.01 * size),
            stiffness: self.stiffness.or(0.25 * s / (h * h)),
            damping: self.damping.or(0.25 * s / h),
        }
    }

    /// Checks ranges; errors name the key.
    pub fn validate(&self) -> Result<()> {
        for (key, v) in [
            ("thickness", self.thickness),
            ("stiffness", self.stiffness),
            ("damping", self.damping),
        ] {
            if let Auto::Value(x) = v
                && !(x.is_finite() && (x > 0.0 || (key == "damping" && x == 0.0)))
            {
                bail!("`scene.contact.{key}` must be positive or \"auto\", is {x}");
            }
        }
        Ok(())
    }
}

/// Resolved contact constants.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ContactParams {
    /// Contact thickness δ, m.
    pub thickness: f64,
    /// Stiffness κ per unit mass, 1/s².
    pub stiffness: f64,
    /// Approach damping ζ per unit mass, 1/s.
    pub damping: f64,
}

impl Stability {
    /// The estimate with a contact's stiffness and damping added to the stiffest mode (an upper
    /// bound: a particle in contact feels both its springs and the contact layer).
    pub fn with_contact(mut self, p: &ContactParams) -> Self {
        self.omega2 += p.stiffness;
        self.gamma += p.damping;
        self.parameters = format!(
            "{}, contact stiffness κ = {:.4e}/s² and damping ζ = {:.4e}/s",
            self.parameters, p.stiffness, p.damping
        );
        self
    }
}

/// A built collider.
#[derive(Clone)]
pub struct Collider {
    /// `colliders[i] (kind)` or the mesh file, for messages.
    pub name: String,
    shape: SharedShape,
    /// The collider is the points within this distance of `shape` (a rounded box: its inner
    /// box, rounded exactly), m.
    rounding: f64,
    /// The shape's bounding box in its own frame (infinite for a plane): a point farther from
    /// it than the reach is skipped without projecting onto the shape.
    local_aabb: Aabb,
    translation: V3,
    rotation: Rot3,
    friction: f64,
    path: Vec<[f64; 4]>,
}

impl std::fmt::Debug for Collider {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Collider")
            .field("name", &self.name)
            .field("translation", &self.translation)
            .field("friction", &self.friction)
            .finish_non_exhaustive()
    }
}

/// Where a particle meets a collider.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Hit {
    /// Signed distance to the surface, m (negative inside).
    pub distance: f64,
    /// Outward unit normal.
    pub normal: V3,
    /// The closest surface point.
    pub point: V3,
    /// Velocity of the surface, m/s.
    pub velocity: V3,
}

impl ColliderConfig {
    /// Checks the shape parameters of this kind; `at` names the entry (`scene.colliders[2]`).
    pub fn validate(&self, at: &str) -> Result<()> {
        let need = |key: &str, v: Option<f64>| -> Result<f64> {
            match v {
                Some(x) if x.is_finite() && x > 0.0 => Ok(x),
                Some(x) => bail!("`{at}.{key}` must be positive, is {x}"),
                None => bail!("`{at}`: a {:?} collider needs `{key}`", self.kind),
            }
        };
        let unused = |key: &str, set: bool| -> Result<()> {
            if set {
                bail!("`{at}.{key}` does not apply to a {:?} collider", self.kind);
            }
            Ok(())
        };
        match self.kind {
            ColliderKind::Plane => {
                unused("radius", self.radius.is_some())?;
                unused("half_height", self.half_height.is_some())?;
                unused("half_extents", self.half_extents.is_some())?;
                unused("mesh", self.mesh.is_some())?;
            }
            ColliderKind::Sphere => {
                need("radius", self.radius)?;
                unused("half_height", self.half_height.is_some())?;
                unused("half_extents", self.half_extents.is_some())?;
                unused("mesh", self.mesh.is_some())?;
            }
            ColliderKind::Capsule => {
                need("radius", self.radius)?;
                need("half_height", self.half_height)?;
                unused("half_extents", self.half_extents.is_some())?;
                unused("mesh", self.mesh.is_some())?;
            }
            ColliderKind::RoundedBox => {
                let r = self.radius.unwrap_or(0.0);
                if !(r.is_finite() && r >= 0.0) {
                    bail!("`{at}.radius` must be non-negative, is {r}");
                }
                let Some(h) = self.half_extents else {
                    bail!("`{at}`: a RoundedBox collider needs `half_extents`");
                };
                if !h.iter().all(|x| x.is_finite() && *x >= 0.0) {
                    bail!("`{at}.half_extents` must be non-negative, is {h:?}");
                }
                unused("half_height", self.half_height.is_some())?;
                unused("mesh", self.mesh.is_some())?;
            }
            ColliderKind::Mesh => {
                if self.mesh.is_none() {
                    bail!("`{at}`: a Mesh collider needs `mesh = \"<file.obj>\"`");
                }
                unused("radius", self.radius.is_some())?;
                unused("half_height", self.half_height.is_some())?;
                unused("half_extents", self.half_extents.is_some())?;
            }
        }
        if !(self.scale.is_finite() && self.scale > 0.0) {
            bail!("`{at}.scale` must be positive, is {}", self.scale);
        }
        if !(self.friction.is_finite() && self.friction >= 0.0) {
            bail!("`{at}.friction` must be non-negative, is {}", self.friction);
        }
        if self
            .translation
            .iter()
            .chain(&self.rotation_deg)
            .any(|x| !x.is_finite())
        {
            bail!("`{at}`: translation and rotation_deg must be finite");
        }
        if self.path.iter().flatten().any(|x| !x.is_finite())
            || self.path.windows(2).any(|w| !(w[1][0] > w[0][0]))
        {
            bail!("`{at}.path` must list finite [t, dx, dy, dz] keyframes with increasing t");
        }
        Ok(())
    }

    /// Builds the collider; a relative `mesh` resolves against `base` (the scene file's
    /// folder). `at` names the entry in messages.
    pub fn build(&self, base: &Path, at: &str) -> Result<Collider> {
        self.validate(at)?;
        let (shape, name) = match self.kind {
            ColliderKind::Plane => (
                SharedShape::halfspace(Vector::new(0.0, 0.0, 1.0)),
                format!("{at} (plane)"),
            ),
            ColliderKind::Sphere => (
                SharedShape::ball(self.radius.expect("validated")),
                format!("{at} (sphere)"),
            ),
            ColliderKind::Capsule => (
                SharedShape::capsule_z(
                    self.half_height.expect("validated"),
                    self.radius.expect("validated"),
                ),
                format!("{at} (capsule)"),
            ),
            ColliderKind::RoundedBox => {
                // The inner box, rounded in `hit`: parry projects onto a round shape by GJK,
                // up to 1e-5 m off, too coarse for a Newton solve's Hessian.
                let [x, y, z] = self.half_extents.expect("validated");
                (SharedShape::cuboid(x, y, z), format!("{at} (rounded box)"))
            }
            ColliderKind::Mesh => {
                let file = self.mesh.as_ref().expect("validated");
                let path = if file.is_relative() {
                    base.join(file)
                } else {
                    file.clone()
                };
                let mesh = closed_mesh(&path, self.scale)
                    .with_context(|| format!("{at}: mesh collider {}", path.display()))?;
                (SharedShape::new(mesh), format!("{at} ({})", path.display()))
            }
        };
        let [rx, ry, rz] = self.rotation_deg.map(f64::to_radians);
        let rotation =
            Rot3::from_rotation_z(rz) * Rot3::from_rotation_y(ry) * Rot3::from_rotation_x(rx);
        let rounding = match self.kind {
            ColliderKind::RoundedBox => self.radius.unwrap_or(0.0),
            _ => 0.0,
        };
        Ok(Collider {
            name,
            local_aabb: shape.compute_local_aabb().loosened(rounding),
            shape,
            rounding,
            translation: self.translation,
            rotation,
            friction: self.friction,
            path: self.path.clone(),
        })
    }
}

/// Reads an OBJ file as a closed, consistently oriented triangle mesh (polygons are split
/// into fans; an inward-facing mesh is turned outwards). Errors name the file and what is
/// wrong: no faces, an edge with one face (a hole) or more than two (non-manifold), or
/// neighbours that disagree on orientation.
fn closed_mesh(path: &Path, scale: f64) -> Result<TriMesh> {
    let ext_ok = path
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("obj"));
    if !ext_ok {
        bail!("{} is not an .obj file", path.display());
    }
    let obj = crate::formats::obj::ObjMesh::read(path)?;
    let mut triangles: Vec<[u32; 3]> = Vec::new();
    for face in &obj.faces {
        let c: Vec<u32> = face.corners.iter().map(|c| c.vertex as u32).collect();
        if c.len() < 3 {
            bail!(
                "{} line {}: a face needs at least 3 corners",
                path.display(),
                face.line
            );
        }
        for i in 1..c.len() - 1 {
            triangles.push([c[0], c[i], c[i + 1]]);
        }
    }
    if triangles.is_empty() || obj.vertices.is_empty() {
        bail!(
            "{} has no triangles: a mesh collider needs a closed surface",
            path.display()
        );
    }
    check_closed(path, &triangles)?;
    let vertices: Vec<Vector> = obj
        .vertices
        .iter()
        .map(|p| Vector::new(p[0] * scale, p[1] * scale, p[2] * scale))
        .collect();
    // Signed volume: negative for a mesh whose faces point inwards.
    let volume: f64 = triangles
        .iter()
        .map(|t| {
            let [a, b, c] = t.map(|i| vertices[i as usize]);
            a.dot(b.cross(c)) / 6.0
        })
        .sum();
    if volume.abs() < 1e-15 {
        bail!("{} encloses no volume", path.display());
    }
    if volume < 0.0 {
        for t in &mut triangles {
            t.swap(1, 2);
        }
    }
    let mut mesh = TriMesh::new(vertices, triangles)
        .map_err(|e| anyhow::anyhow!("{}: {e:?}", path.display()))?;
    mesh.set_flags(TriMeshFlags::ORIENTED | TriMeshFlags::HALF_EDGE_TOPOLOGY)
        .map_err(|e| anyhow::anyhow!("{}: bad topology: {e:?}", path.display()))?;
    Ok(mesh)
}

/// Every undirected edge of `triangles` must be used by exactly two of them, once in each
/// direction; the error names the first edge (in vertex order) that is not.
fn check_closed(path: &Path, triangles: &[[u32; 3]]) -> Result<()> {
    let mut edges: std::collections::HashMap<(u32, u32), (usize, usize)> = Default::default();
    for t in triangles {
        for (a, b) in [(t[0], t[1]), (t[1], t[2]), (t[2], t[0])] {
            let e = edges.entry((a.min(b), a.max(b))).or_default();
            if a < b {
                e.0 += 1;
            } else {
                e.1 += 1;
            }
        }
    }
    let mut keys: Vec<_> = edges.iter().collect();
    keys.sort();
    for (&(a, b), &(fwd, back)) in keys {
        let (a1, b1) = (a + 1, b + 1);
        match fwd + back {
            1 => bail!(
                "{} is not closed: the edge between vertices {a1} and {b1} has one face (a hole); \
                 a mesh collider must be a closed surface",
                path.display()
            ),
            2 if fwd == 1 => {}
            2 => bail!(
                "{} is not consistently oriented: the two faces at the edge between vertices {a1} \
                 and {b1} run the same way",
                path.display()
            ),
            n => bail!(
                "{} is non-manifold: the edge between vertices {a1} and {b1} has {n} faces",
                path.display()
            ),
        }
    }
    Ok(())
}

impl Collider {
    /// The path offset and its velocity at time `t`.
    fn motion(&self, t: f64) -> (V3, V3) {
        let p = &self.path;
        match p.len() {
            0 => ([0.0; 3], [0.0; 3]),
            _ if t <= p[0][0] => ([p[0][1], p[0][2], p[0][3]], [0.0; 3]),
            n if t >= p[n - 1][0] => ([p[n - 1][1], p[n - 1][2], p[n - 1][3]], [0.0; 3]),
            _ => {
                let i = p.partition_point(|k| k[0] <= t) - 1;
                let (a, b) = (p[i], p[i + 1]);
                let s = (t - a[0]) / (b[0] - a[0]);
                let off = [1, 2, 3].map(|c| a[c] + s * (b[c] - a[c]));
                let vel = [1, 2, 3].map(|c| (b[c] - a[c]) / (b[0] - a[0]));
                (off, vel)
            }
        }
    }

    /// The collider's pose and surface velocity at time `t`.
    fn pose(&self, t: f64) -> (Pose, V3) {
        let (off, vel) = self.motion(t);
        let tr = Vector::new(
            self.translation[0] + off[0],
            self.translation[1] + off[1],
            self.translation[2] + off[2],
        );
        (Pose::from_parts(tr, self.rotation), vel)
    }

    /// The signed distance, normal and closest surface point of `x` at time `t`.
    pub fn query(&self, t: f64, x: V3) -> Hit {
        let (pose, vel) = self.pose(t);
        self.hit(&pose, vel, x, f64::INFINITY)
            .expect("every point is within an infinite reach")
    }

    /// The closest surface point to `x` and the signed distance, when `x` lies within `reach`
    /// of the surface or inside the collider.
    fn hit(&self, pose: &Pose, velocity: V3, x: V3, reach: f64) -> Option<Hit> {
        let q = Vector::new(x[0], x[1], x[2]);
        // The shape is no nearer than its box: far points need no projection (on a mesh, a
        // BVH descent per particle and step).
        if reach.is_finite()
            && self
                .local_aabb
                .distance_to_local_point(pose.inverse_transform_point(q), true)
                >= reach
        {
            return None;
        }
        let proj = self.shape.project_point(pose, q, false);
        let delta = q - proj.point;
        let len = delta.length();
        let distance = if proj.is_inside { -len } else { len } - self.rounding;
        if distance >= reach {
            return None;
        }
        let normal = if len > 1e-12 {
            if proj.is_inside {
                -delta / len
            } else {
                delta / len
            }
        } else {
            // On the surface: the feature's normal.
            let (p, feature) = self.shape.project_point_and_get_feature(pose, q);
            let local = pose.inverse_transform_point(p.point);
            self.shape
                .feature_normal_at_point(p.subshape, feature, local)
                .map(|n| pose.rotation * n)
                .unwrap_or(Vector::new(0.0, 0.0, 1.0))
        };
        let point = proj.point + normal * self.rounding;
        Some(Hit {
            distance,
            normal: [normal.x, normal.y, normal.z],
            point: [point.x, point.y, point.z],
            velocity,
        })
    }
}

/// Colliders with their contact constants, and the deepest intrusion into the contact layer
/// seen so far (see [`Contact::deepest`]).
#[derive(Debug)]
pub struct Contact {
    /// The colliders, in scene order.
    pub colliders: Vec<Collider>,
    /// The contact layer.
    pub params: ContactParams,
    deepest: AtomicU64,
}

impl Clone for Contact {
    /// A copy with its own, fresh, intrusion record.
    fn clone(&self) -> Self {
        Self::new(self.colliders.clone(), self.params)
    }
}

/// The per-particle contact geometry of one collider at one step, for the tensor formula.
struct Frame {
    /// 1 where the particle is within the layer.
    active: Vec<f32>,
    normal: Vec<f32>,
    /// `n · p` for the closest point `p`.
    offset: Vec<f32>,
    velocity: Vec<f32>,
}

impl Contact {
    /// Colliders with constants `params`.
    pub fn new(colliders: Vec<Collider>, params: ContactParams) -> Self {
        Self {
            colliders,
            params,
            deepest: AtomicU64::new(0f64.to_bits()),
        }
    }

    /// The deepest intrusion into the contact layer so far, `max(δ − d)` over every particle
    /// and step, m: `g/κ` for cloth resting on a surface; beyond `δ` the cloth touched the
    /// collider itself.
    pub fn deepest(&self) -> f64 {
        f64::from_bits(self.deepest.load(Ordering::Relaxed))
    }

    /// Moves every point of `x` nearer than `rest` to a collider's surface at time `t` out
    /// along that surface's normal to `rest` (pass the resting depth `δ − g/κ` to start cloth
    /// where it would rest). A drape resampled onto other particles cuts corners (a particle
    /// interpolated between two that rest on a rounded edge lies inside it). Repeated while a
    /// point moves (a point lifted out of one collider into another), at most 8 times; a point
    /// inside a collider thinner than itself leaves by the nearest side.
    pub fn lift_out(&self, t: f64, x: &mut [V3], rest: f64) {
        for _ in 0..8 {
            let mut moved = false;
            for c in &self.colliders {
                for p in x.iter_mut() {
                    let hit = c.query(t, *p);
                    let gap = rest - hit.distance;
                    if gap > 1e-12 * rest.abs().max(1.0) {
                        for (pi, ni) in p.iter_mut().zip(hit.normal) {
                            *pi += gap * ni;
                        }
                        moved = true;
                    }
                }
            }
            if !moved {
                break;
            }
        }
    }

    fn record(&self, intrusion: f64) {
        // Non-negative floats order like their bit patterns.
        self.deepest
            .fetch_max(intrusion.max(0.0).to_bits(), Ordering::Relaxed);
    }

    /// The contact force of one collider on one particle (see the module docs): `f` is the
    /// particle's other forces (including earlier colliders'), `h` the step.
    fn force(&self, c: &Collider, hit: &Hit, m: f64, h: f64, v: V3, f: V3) -> V3 {
        let p = &self.params;
        let n = hit.normal;
        let dot = |a: V3, b: V3| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
        let phi = (p.thickness - hit.distance).max(0.0);
        if phi <= 0.0 {
            return [0.0; 3];
        }
        let rel = [0, 1, 2].map(|i| v[i] - hit.velocity[i]);
        let fn_mag = m * (p.stiffness * phi + p.damping * (-dot(n, rel)).max(0.0));
        let w: V3 = [0, 1, 2].map(|i| v[i] + h / m * (f[i] + fn_mag * n[i]) - hit.velocity[i]);
        let wn = dot(n, w);
        let wt: V3 = [0, 1, 2].map(|i| w[i] - wn * n[i]);
        let norm = (dot(wt, wt) + 1e-24).sqrt();
        let r = (c.friction * fn_mag / norm).min(m / h);
        [0, 1, 2].map(|i| fn_mag * n[i] - r * wt[i])
    }

    /// Adds the contact forces at time `t` to the forces `f` of particles at `(x, v)` stepped
    /// by `h`; pinned particles and colliders take none. `mass(i)` is particle `i`'s mass.
    #[allow(clippy::too_many_arguments)]
    pub fn apply(
        &self,
        t: f64,
        h: f64,
        x: &[V3],
        v: &[V3],
        pinned: &[bool],
        mass: impl Fn(usize) -> f64,
        f: &mut [V3],
    ) {
        let reach = self.params.thickness;
        let mut deepest = 0.0f64;
        for c in &self.colliders {
            let (pose, vel) = c.pose(t);
            for i in 0..x.len() {
                if pinned[i] {
                    continue;
                }
                if let Some(hit) = c.hit(&pose, vel, x[i], reach) {
                    deepest = deepest.max(reach - hit.distance);
                    let fc = self.force(c, &hit, mass(i), h, v[i], f[i]);
                    for k in 0..3 {
                        f[i][k] += fc[k];
                    }
                }
            }
        }
        self.record(deepest);
    }

    /// Host geometry of collider `c` for the flat host positions `x` (`[N·3]`).
    fn frame(&self, c: &Collider, t: f64, x: &[f32]) -> (Frame, f64) {
        let (pose, vel) = c.pose(t);
        let n = x.len() / 3;
        let mut fr = Frame {
            active: vec![0.0; n],
            normal: vec![0.0; n * 3],
            offset: vec![0.0; n],
            velocity: vec![0.0; n * 3],
        };
        let reach = self.params.thickness;
        let mut deepest = 0.0f64;
        for i in 0..n {
            let p = [0, 1, 2].map(|k| x[i * 3 + k] as f64);
            if let Some(hit) = c.hit(&pose, vel, p, reach) {
                deepest = deepest.max(reach - hit.distance);
                fr.active[i] = 1.0;
                let nn = hit.normal;
                fr.offset[i] =
                    (nn[0] * hit.point[0] + nn[1] * hit.point[1] + nn[2] * hit.point[2]) as f32;
                for k in 0..3 {
                    fr.normal[i * 3 + k] = nn[k] as f32;
                    fr.velocity[i * 3 + k] = vel[k] as f32;
                }
            }
        }
        (fr, deepest)
    }

    /// The forces `f` `[B, P, 3]` with the contact forces at time `t` added, for particles of
    /// uniform `mass` at `(x, v)` stepped by `h`; `free` is `[B, P, 1]` (0 = pinned). The same
    /// formula as [`Contact::apply`] in tensor ops: differentiable in `x`, `v` and `f`, with
    /// each active particle's normal and closest point fixed at their values at `x`.
    #[allow(clippy::too_many_arguments)]
    pub fn apply_tensor(
        &self,
        t: f64,
        h: f64,
        mass: f64,
        x: &Tensor<3>,
        v: &Tensor<3>,
        mut f: Tensor<3>,
        free: &Tensor<3>,
    ) -> Tensor<3> {
        if self.colliders.is_empty() {
            return f;
        }
        let dims = x.dims();
        let [b, p, _] = dims;
        let device = x.device();
        let host: Vec<f32> = x
            .clone()
            .into_data()
            .convert::<f32>()
            .try_into_vec::<f32>()
            .expect("f32 positions");
        let prm = self.params;
        let mut deepest = 0.0f64;
        for c in &self.colliders {
            let (fr, d) = self.frame(c, t, &host);
            deepest = deepest.max(d);
            if fr.active.iter().all(|a| *a == 0.0) {
                continue;
            }
            let t1 = |v: Vec<f32>| Tensor::<3>::from_data(TensorData::new(v, [b, p, 1]), &device);
            let t3 = |v: Vec<f32>| Tensor::<3>::from_data(TensorData::new(v, [b, p, 3]), &device);
            let active = t1(fr.active) * free.clone();
            let n = t3(fr.normal);
            let u = t3(fr.velocity);
            let dist = (n.clone() * x.clone()).sum_dim(2) - t1(fr.offset);
            let phi = dist.neg().add_scalar(prm.thickness).clamp_min(0.0) * active.clone();
            let vn = (n.clone() * (v.clone() - u.clone())).sum_dim(2);
            let approach = vn.neg().clamp_min(0.0) * active;
            let fn_mag =
                (phi.mul_scalar(prm.stiffness) + approach.mul_scalar(prm.damping)).mul_scalar(mass);
            let w = v.clone() + (f.clone() + n.clone() * fn_mag.clone()).mul_scalar(h / mass) - u;
            let wt = w.clone() - n.clone() * (n.clone() * w).sum_dim(2);
            let norm = (wt.clone() * wt.clone())
                .sum_dim(2)
                .add_scalar(1e-24)
                .sqrt();
            let r = (fn_mag.clone().mul_scalar(c.friction) / norm).clamp_max(mass / h);
            f = f + n * fn_mag - wt * r;
        }
        self.record(deepest);
        f
    }
}
