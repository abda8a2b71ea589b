//! `import obj`: a folder of OBJ frame meshes (read by [`crate::formats::obj`]), and the rest
//! shape of an OBJ mesh (a point cache's rest mesh too).

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};

pub use crate::formats::obj::{Corner, Face, ObjMesh};

use super::{ImportOptions, ImportSummary, Motion, RestShape, rest_rectangle, write_rollout};

/// How to find the rest rectangle of `mesh`: its texture coordinates scaled by its edge
/// lengths, or, without any `vt`, its own flat shape.
pub fn rest_shape(mesh: &ObjMesh) -> Result<RestShape> {
    let what = mesh.path.display().to_string();
    if mesh.uvs.is_empty() {
        return Ok(RestShape::Flat {
            reference: mesh.vertices.clone(),
            what,
        });
    }
    Ok(RestShape::Uv {
        uv: mesh.vertex_uvs()?,
        edges: mesh.edges(),
        reference: mesh.vertices.clone(),
        what,
    })
}

/// The `.obj` files of `dir`, in natural name order.
pub fn frame_files(dir: &Path) -> Result<Vec<PathBuf>> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
        .with_context(|| format!("cannot read folder {}", dir.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.is_file() && p.extension().is_some_and(|e| e.eq_ignore_ascii_case("obj")))
        .collect();
    files.sort_by(|a, b| {
        super::natural_cmp(
            &a.file_name().unwrap_or_default().to_string_lossy(),
            &b.file_name().unwrap_or_default().to_string_lossy(),
        )
    });
    if files.len() < 2 {
        bail!(
            "{} holds {} .obj file(s): a rollout needs at least 2 frames",
            dir.display(),
            files.len()
        );
    }
    Ok(files)
}

/// Imports a folder of OBJ frames (sorted by name; vertex `i` of every frame is point `i`) as
/// `<out>/<folder name>.npz`.
pub fn import_sequence(dir: &Path, options: &ImportOptions) -> Result<ImportSummary> {
    let files = frame_files(dir)?;
    let first = ObjMesh::read(&files[0]).context("frame 0")?;
    let n = first.vertices.len();
    let rest = rest_rectangle(&rest_shape(&first)?, options.size).context("frame 0")?;
    let rest_from = if first.uvs.is_empty() {
        format!("the flat first frame {}", files[0].display())
    } else {
        format!(
            "the texture coordinates of {}{}",
            files[0].display(),
            if options.size.is_some() {
                ", scaled to --width/--height"
            } else {
                ", scaled to its edge lengths"
            }
        )
    };
    let mut positions = Vec::with_capacity(files.len() * n * 3);
    for (f, path) in files.iter().enumerate() {
        let mesh = if f == 0 {
            first.clone()
        } else {
            ObjMesh::read(path).with_context(|| format!("frame {f}"))?
        };
        if mesh.vertices.len() != n {
            bail!(
                "{} (frame {f}) has {} vertices, the first frame {} has {n}: every frame must \
                 have the same vertices in the same order",
                path.display(),
                mesh.vertices.len(),
                files[0].display()
            );
        }
        for (i, v) in mesh.vertices.iter().enumerate() {
            for &c in v {
                let c32 = c as f32;
                if !c32.is_finite() {
                    bail!(
                        "{} (frame {f}), line {}: vertex {i} coordinate {c} does not fit float32",
                        path.display(),
                        mesh.vertex_lines[i]
                    );
                }
                positions.push(c32);
            }
        }
    }
    let motion = Motion {
        name: super::folder_name(dir),
        frames: files.len(),
        points: n,
        positions,
        triangles: Some(first.triangles()),
        visible: None,
    };
    write_rollout(&motion, rest, &rest_from, options)
}
