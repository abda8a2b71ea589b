//! Wavefront OBJ, read: `v x y z` (extra columns such as vertex colours ignored), `vt u v`, and
//! `f` with `v`, `v/vt`, `v/vt/vn` or `v//vn` corners (negative indices count back from the
//! end). Everything else (`vn`, `o`, `g`, `s`, `usemtl`, `mtllib`, `l`, comments) is skipped.
//! A codec without policy: `import obj` (frames), `import pc2` (the rest mesh) and contact
//! (mesh colliders) read it.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};

/// One corner of a face: vertex and texture coordinate indices, 0-based.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Corner {
    /// Vertex index.
    pub vertex: usize,
    /// Texture coordinate index, if the corner has one.
    pub uv: Option<usize>,
}

/// A face and the line it is on.
#[derive(Debug, Clone, PartialEq)]
pub struct Face {
    /// Corners in order.
    pub corners: Vec<Corner>,
    /// 1-based line number.
    pub line: usize,
}

/// One OBJ file.
#[derive(Debug, Clone, PartialEq)]
pub struct ObjMesh {
    /// The file.
    pub path: PathBuf,
    /// Vertex positions.
    pub vertices: Vec<[f64; 3]>,
    /// 1-based line number of each vertex.
    pub vertex_lines: Vec<usize>,
    /// Texture coordinates.
    pub uvs: Vec<[f64; 2]>,
    /// Faces.
    pub faces: Vec<Face>,
}

/// One non-empty line of an OBJ file: its number (from 1), text and first word, for parsing
/// and for messages that name the file and line.
struct ObjLine<'a> {
    shown: &'a std::path::Display<'a>,
    number: usize,
    line: &'a str,
    tag: &'a str,
}

impl ObjLine<'_> {
    /// The first `count` words as finite numbers.
    fn floats(&self, words: std::str::SplitWhitespace<'_>, count: usize) -> Result<Vec<f64>> {
        let Self {
            shown,
            number,
            line,
            tag,
        } = self;
        let values: Vec<f64> = words
            .take(count)
            .map(|w| w.parse::<f64>())
            .collect::<std::result::Result<_, _>>()
            .map_err(|_| anyhow::anyhow!("{shown}, line {number}: malformed `{line}`"))?;
        if values.len() < count {
            bail!("{shown}, line {number}: `{tag}` needs {count} numbers: `{line}`");
        }
        if let Some(v) = values.iter().find(|v| !v.is_finite()) {
            bail!("{shown}, line {number}: non-finite coordinate {v} in `{line}`");
        }
        Ok(values)
    }

    /// A face of at least 3 corners, each `v`, `v/vt`, `v//vn` or `v/vt/vn` (negative indices
    /// count back from the last defined), given how many vertices and texture coordinates are
    /// defined above it.
    fn face(
        &self,
        words: std::str::SplitWhitespace<'_>,
        vertices: usize,
        uvs: usize,
    ) -> Result<Face> {
        let Self {
            shown,
            number,
            line,
            ..
        } = self;
        let mut corners = Vec::new();
        for w in words {
            let mut parts = w.split('/');
            let vertex = self
                .corner_index(w, parts.next(), vertices, "vertex")?
                .ok_or_else(|| {
                    anyhow::anyhow!("{shown}, line {number}: face corner `{w}` has no vertex")
                })?;
            let uv = self.corner_index(w, parts.next(), uvs, "texture coordinate")?;
            corners.push(Corner { vertex, uv });
        }
        if corners.len() < 3 {
            bail!("{shown}, line {number}: a face needs at least 3 corners: `{line}`");
        }
        Ok(Face {
            corners,
            line: *number,
        })
    }

    /// One index `s` of face corner `w` into `count` defined items (`None` where empty).
    fn corner_index(
        &self,
        w: &str,
        s: Option<&str>,
        count: usize,
        what: &str,
    ) -> Result<Option<usize>> {
        let Self { shown, number, .. } = self;
        let Some(s) = s.filter(|s| !s.is_empty()) else {
            return Ok(None);
        };
        let k: i64 = s
            .parse()
            .map_err(|_| anyhow::anyhow!("{shown}, line {number}: malformed face corner `{w}`"))?;
        let idx = if k > 0 { k - 1 } else { count as i64 + k };
        if k == 0 || idx < 0 || idx as usize >= count {
            bail!(
                "{shown}, line {number}: face corner `{w}` refers to {what} {k}, \
                 but {count} are defined above it"
            );
        }
        Ok(Some(idx as usize))
    }
}

impl ObjMesh {
    /// Reads an OBJ file; errors name the file and the line. Vertex coordinates must be finite.
    pub fn read(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path)
            .with_context(|| format!("cannot read {}", path.display()))?;
        Self::parse(&text, path)
    }

    /// Parses OBJ text (`path` is for messages).
    pub fn parse(text: &str, path: &Path) -> Result<Self> {
        let shown = path.display();
        let mut mesh = ObjMesh {
            path: path.to_path_buf(),
            vertices: Vec::new(),
            vertex_lines: Vec::new(),
            uvs: Vec::new(),
            faces: Vec::new(),
        };
        for (i, line) in text.lines().enumerate() {
            let mut words = line.split_whitespace();
            let Some(tag) = words.next() else { continue };
            let at = ObjLine {
                shown: &shown,
                number: i + 1,
                line,
                tag,
            };
            match tag {
                "v" => {
                    let v = at.floats(words, 3)?;
                    mesh.vertices.push([v[0], v[1], v[2]]);
                    mesh.vertex_lines.push(at.number);
                }
                "vt" => {
                    let v = at.floats(words, 2)?;
                    mesh.uvs.push([v[0], v[1]]);
                }
                "f" => {
                    let face = at.face(words, mesh.vertices.len(), mesh.uvs.len())?;
                    mesh.faces.push(face);
                }
                _ => {}
            }
        }
        Ok(mesh)
    }

    /// Unique edges of the faces (polygon sides), sorted.
    pub fn edges(&self) -> Vec<[usize; 2]> {
        let mut edges: Vec<[usize; 2]> = self
            .faces
            .iter()
            .flat_map(|f| {
                let n = f.corners.len();
                (0..n).map(move |i| {
                    let (a, b) = (f.corners[i].vertex, f.corners[(i + 1) % n].vertex);
                    [a.min(b), a.max(b)]
                })
            })
            .filter(|e| e[0] != e[1])
            .collect();
        edges.sort_unstable();
        edges.dedup();
        edges
    }

    /// The faces cut into triangles (fans from each face's first corner), vertex indices.
    pub fn triangles(&self) -> Vec<[usize; 3]> {
        self.faces
            .iter()
            .flat_map(|f| {
                let c = &f.corners;
                (1..c.len().saturating_sub(1))
                    .map(move |i| [c[0].vertex, c[i].vertex, c[i + 1].vertex])
            })
            .collect()
    }

    /// The texture coordinate of every vertex, through the faces. Errors name the file and the
    /// line: a vertex no face gives a texture coordinate, or one with two different ones (a UV
    /// seam: springtime needs one rest position per point).
    pub fn vertex_uvs(&self) -> Result<Vec<[f64; 2]>> {
        let shown = self.path.display();
        let mut uv: Vec<Option<([f64; 2], usize)>> = vec![None; self.vertices.len()];
        for f in &self.faces {
            for c in &f.corners {
                let Some(t) = c.uv else {
                    bail!(
                        "{shown}, line {}: face corner of vertex {} has no texture coordinate (write `v/vt`)",
                        f.line,
                        c.vertex
                    );
                };
                let value = self.uvs[t];
                let current = uv[c.vertex];
                match current {
                    None => uv[c.vertex] = Some((value, f.line)),
                    Some((old, line))
                        if (old[0] - value[0]).abs() + (old[1] - value[1]).abs() > 1e-9 =>
                    {
                        bail!(
                            "{shown}, line {}: vertex {} has texture coordinate ({}, {}) here and ({}, {}) on line {line}: \
                         a UV seam; springtime needs one rest position per vertex",
                            f.line,
                            c.vertex,
                            value[0],
                            value[1],
                            old[0],
                            old[1]
                        )
                    }
                    Some(_) => {}
                }
            }
        }
        uv.iter()
            .enumerate()
            .map(|(i, u)| {
                u.map(|(v, _)| v).ok_or_else(|| {
                    anyhow::anyhow!(
                        "{shown}, line {}: vertex {i} has no texture coordinate (no face uses it with `v/vt`)",
                        self.vertex_lines[i]
                    )
                })
            })
            .collect()
    }
}
