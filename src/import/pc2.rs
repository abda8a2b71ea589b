//! Point caches: `.pc2` files of Blender (*Export › Point Cache*, the Mesh Cache modifier) and
//! Houdini, read for `import pc2` and written by `export --format pc2`.
//!
//! Layout (little-endian): the 12 bytes `POINTCACHE2\0`, `i32` version (1), `i32` point count,
//! `f32` start frame, `f32` sample rate (scene frames per sample), `i32` sample count, then
//! `f32` x, y, z per point per sample.

use std::io::Write;
use std::path::Path;

use anyhow::{Context, Result, bail};

use super::obj::{ObjMesh, rest_shape};
use super::{ImportOptions, ImportSummary, Motion, rest_rectangle, write_rollout};

/// The signature at the start of a `.pc2` file.
pub const MAGIC: &[u8; 12] = b"POINTCACHE2\0";

/// A point cache.
#[derive(Debug, Clone, PartialEq)]
pub struct PointCache {
    /// Scene frame of the first sample.
    pub start_frame: f32,
    /// Scene frames between samples.
    pub sample_rate: f32,
    /// Points per sample.
    pub points: usize,
    /// Samples.
    pub samples: usize,
    /// Positions `[samples, points, 3]`.
    pub positions: Vec<f32>,
}

impl PointCache {
    /// Reads a `.pc2` file; errors name the file and the sample and point.
    pub fn read(path: &Path) -> Result<Self> {
        let bytes =
            std::fs::read(path).with_context(|| format!("cannot read {}", path.display()))?;
        let shown = path.display();
        if bytes.len() < 12 || &bytes[..12] != MAGIC {
            bail!("{shown} is not a point cache (no POINTCACHE2 header)");
        }
        if bytes.len() < 32 {
            bail!("{shown}: truncated header ({} of 32 bytes)", bytes.len());
        }
        let i32_at = |o: usize| i32::from_le_bytes(bytes[o..o + 4].try_into().expect("4 bytes"));
        let f32_at = |o: usize| f32::from_le_bytes(bytes[o..o + 4].try_into().expect("4 bytes"));
        let version = i32_at(12);
        if version != 1 {
            bail!("{shown}: point cache version {version} (springtime reads version 1)");
        }
        let (points, samples) = (i32_at(16), i32_at(28));
        if points <= 0 || samples < 0 {
            bail!("{shown}: header says {points} points and {samples} samples");
        }
        let (points, samples) = (points as usize, samples as usize);
        let need = 32 + samples * points * 12;
        if bytes.len() != need {
            bail!(
                "{shown}: {samples} samples of {points} points need {need} bytes, the file has {}",
                bytes.len()
            );
        }
        let positions: Vec<f32> = bytes[32..]
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes(c.try_into().expect("4 bytes")))
            .collect();
        if let Some(k) = positions.iter().position(|v| !v.is_finite()) {
            bail!(
                "{shown}: sample {}, point {}: non-finite coordinate {}",
                k / (points * 3),
                (k / 3) % points,
                positions[k]
            );
        }
        Ok(Self {
            start_frame: f32_at(20),
            sample_rate: f32_at(24),
            points,
            samples,
            positions,
        })
    }

    /// Writes the cache to `path` atomically.
    pub fn write(&self, path: &Path) -> Result<()> {
        assert_eq!(self.positions.len(), self.samples * self.points * 3);
        crate::io::write_atomic(path, |file| {
            let mut w = std::io::BufWriter::new(file);
            w.write_all(MAGIC)?;
            w.write_all(&1i32.to_le_bytes())?;
            w.write_all(&(self.points as i32).to_le_bytes())?;
            w.write_all(&self.start_frame.to_le_bytes())?;
            w.write_all(&self.sample_rate.to_le_bytes())?;
            w.write_all(&(self.samples as i32).to_le_bytes())?;
            for v in &self.positions {
                w.write_all(&v.to_le_bytes())?;
            }
            w.flush()?;
            Ok(())
        })
    }
}

/// Imports a point cache whose points are the vertices of `rest` (an OBJ with the same vertex
/// order; its texture coordinates, or its flat shape, give the rest rectangle) as
/// `<out>/<cache name>.npz`; `options.frame_dt` is the time between samples.
pub fn import_cache(cache: &Path, rest: &Path, options: &ImportOptions) -> Result<ImportSummary> {
    let pc = PointCache::read(cache)?;
    let mesh = ObjMesh::read(rest)?;
    if mesh.vertices.len() != pc.points {
        bail!(
            "{} has {} vertices, the point cache {} has {} points: the rest mesh must be the \
             cached mesh",
            rest.display(),
            mesh.vertices.len(),
            cache.display(),
            pc.points
        );
    }
    let rect = rest_rectangle(&rest_shape(&mesh)?, options.size)?;
    let rest_from = if mesh.uvs.is_empty() {
        format!("the flat rest mesh {}", rest.display())
    } else {
        format!("the texture coordinates of {}", rest.display())
    };
    let motion = Motion {
        name: super::stem(cache),
        frames: pc.samples,
        points: pc.points,
        positions: pc.positions,
        triangles: Some(mesh.triangles()),
        visible: None,
    };
    write_rollout(&motion, rect, &rest_from, options)
}
