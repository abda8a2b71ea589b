//! glTF 2.0 output: the cloth as one triangle mesh whose animation is a morph target per frame
//! driven by a step-interpolated `weights` channel — the standard form of vertex animation that
//! Blender (shape keys) and three.js (morph targets) import without add-ons.
//!
//! Positions are converted from springtime's z-up to glTF's y-up: `(x, y, z) → (x, z, −y)` (a
//! rotation; triangle winding is kept). Texture coordinates are flipped to glTF's top-left
//! origin. `.gltf` embeds the buffer as base64; `.glb` is the binary container.

use std::io::Write;
use std::path::Path;

use anyhow::Result;
use base64::Engine;
use serde_json::{Value, json};

/// A mesh and its animation, in springtime's coordinates (metres, z up).
#[derive(Debug, Clone, Copy)]
pub struct AnimatedMesh<'a> {
    /// Name of the mesh and node.
    pub name: &'a str,
    /// Base (rest) positions, flat `[P, 3]`.
    pub rest: &'a [f32],
    /// Texture coordinates per vertex, `[0, 1]`, origin bottom left.
    pub uv: &'a [[f64; 2]],
    /// Triangles, counter-clockwise.
    pub triangles: &'a [[usize; 3]],
    /// Animation frames, flat `[K, P, 3]` (may be empty).
    pub frames: &'a [f32],
    /// Time of each frame, s.
    pub times: &'a [f64],
}

/// Buffer being assembled: 4-byte aligned views.
struct Builder {
    bin: Vec<u8>,
    views: Vec<Value>,
    accessors: Vec<Value>,
}

impl Builder {
    fn view(&mut self, bytes: &[u8], target: Option<u32>) -> usize {
        while !self.bin.len().is_multiple_of(4) {
            self.bin.push(0);
        }
        let mut v = json!({"buffer": 0, "byteOffset": self.bin.len(), "byteLength": bytes.len()});
        if let Some(t) = target {
            v["target"] = t.into();
        }
        self.bin.extend_from_slice(bytes);
        self.views.push(v);
        self.views.len() - 1
    }

    fn accessor(&mut self, mut a: Value) -> usize {
        if a.get("byteOffset").is_some_and(|o| o == 0) {
            a.as_object_mut().expect("object").remove("byteOffset");
        }
        self.accessors.push(a);
        self.accessors.len() - 1
    }
}

const FLOAT: u32 = 5126;
const UNSIGNED_INT: u32 = 5125;
const ARRAY_BUFFER: u32 = 34962;
const ELEMENT_ARRAY_BUFFER: u32 = 34963;

fn y_up(p: &[f32]) -> [f32; 3] {
    [p[0], p[2], -p[1]]
}

fn le(values: impl IntoIterator<Item = f32>) -> Vec<u8> {
    values.into_iter().flat_map(f32::to_le_bytes).collect()
}

fn bounds(points: &[[f32; 3]]) -> (Value, Value) {
    let mut lo = [f32::INFINITY; 3];
    let mut hi = [f32::NEG_INFINITY; 3];
    for p in points {
        for a in 0..3 {
            lo[a] = lo[a].min(p[a]);
            hi[a] = hi[a].max(p[a]);
        }
    }
    (json!(lo), json!(hi))
}

/// The glTF JSON document and its binary buffer.
pub fn document(mesh: &AnimatedMesh) -> (Value, Vec<u8>) {
    let p = mesh.rest.len() / 3;
    let k = mesh.times.len();
    assert_eq!(mesh.frames.len(), k * p * 3, "frames and times disagree");
    let mut b = Builder {
        bin: Vec::new(),
        views: Vec::new(),
        accessors: Vec::new(),
    };
    let rest: Vec<[f32; 3]> = mesh.rest.chunks_exact(3).map(y_up).collect();
    let mut primitive = b.primitive(mesh, &rest);
    let mut gltf_mesh = json!({"name": mesh.name, "primitives": []});
    let mut root = json!({
        "asset": {
            "version": "2.0",
            "generator": concat!("springtime ", env!("CARGO_PKG_VERSION")),
        },
        "scene": 0,
        "scenes": [{"name": mesh.name, "nodes": [0]}],
        "nodes": [{"name": mesh.name, "mesh": 0}],
    });
    if k > 0 {
        primitive["targets"] = b.morph_targets(mesh, &rest).into();
        let mut weights = vec![0.0; k];
        weights[0] = 1.0;
        gltf_mesh["weights"] = json!(weights);
        gltf_mesh["extras"] =
            json!({"targetNames": (0..k).map(|f| format!("frame_{f:04}")).collect::<Vec<_>>()});
        root["animations"] = b.animation(mesh.times);
    }
    gltf_mesh["primitives"] = json!([primitive]);
    root["meshes"] = json!([gltf_mesh]);
    while !b.bin.len().is_multiple_of(4) {
        b.bin.push(0);
    }
    root["bufferViews"] = b.views.into();
    root["accessors"] = b.accessors.into();
    root["buffers"] = json!([{"byteLength": b.bin.len()}]);
    (root, b.bin)
}

impl Builder {
    /// The triangles with the rest positions (`rest`, y up) and texture coordinates.
    fn primitive(&mut self, mesh: &AnimatedMesh, rest: &[[f32; 3]]) -> Value {
        let p = rest.len();
        let indices: Vec<u8> = mesh
            .triangles
            .iter()
            .flat_map(|t| t.map(|i| i as u32))
            .flat_map(u32::to_le_bytes)
            .collect();
        let view = self.view(&indices, Some(ELEMENT_ARRAY_BUFFER));
        let max_index = mesh.triangles.iter().flatten().copied().max().unwrap_or(0);
        let indices = self.accessor(json!({
            "bufferView": view, "componentType": UNSIGNED_INT, "count": mesh.triangles.len() * 3,
            "type": "SCALAR", "min": [0], "max": [max_index],
        }));
        let view = self.view(&le(rest.iter().flatten().copied()), Some(ARRAY_BUFFER));
        let (lo, hi) = bounds(rest);
        let position = self.accessor(json!({
            "bufferView": view, "componentType": FLOAT, "count": p, "type": "VEC3",
            "min": lo, "max": hi,
        }));
        let view = self.view(
            &le(mesh
                .uv
                .iter()
                .flat_map(|t| [t[0] as f32, 1.0 - t[1] as f32])),
            Some(ARRAY_BUFFER),
        );
        let texcoord = self.accessor(json!({
            "bufferView": view, "componentType": FLOAT, "count": p, "type": "VEC2",
        }));
        json!({
            "attributes": {"POSITION": position, "TEXCOORD_0": texcoord},
            "indices": indices,
            "mode": 4,
        })
    }

    /// One morph target per frame of the mesh: its displacement from the rest positions
    /// `rest` (y up).
    fn morph_targets(&mut self, mesh: &AnimatedMesh, rest: &[[f32; 3]]) -> Vec<Value> {
        let (p, k) = (rest.len(), mesh.times.len());
        let displacements: Vec<[f32; 3]> = mesh
            .frames
            .chunks_exact(3)
            .map(y_up)
            .enumerate()
            .map(|(i, q)| {
                let r = rest[i % p];
                [q[0] - r[0], q[1] - r[1], q[2] - r[2]]
            })
            .collect();
        let view = self.view(
            &le(displacements.iter().flatten().copied()),
            Some(ARRAY_BUFFER),
        );
        let mut targets = Vec::with_capacity(k);
        for f in 0..k {
            let (lo, hi) = bounds(&displacements[f * p..(f + 1) * p]);
            let a = self.accessor(json!({
                "bufferView": view, "byteOffset": f * p * 12, "componentType": FLOAT, "count": p,
                "type": "VEC3", "min": lo, "max": hi,
            }));
            targets.push(json!({"POSITION": a}));
        }
        targets
    }

    /// The animation: key f (at `times[f]`, from the first) shows frame f alone until the next
    /// key.
    fn animation(&mut self, times: &[f64]) -> Value {
        let k = times.len();
        let t0 = times[0];
        let times: Vec<f32> = times.iter().map(|t| (t - t0) as f32).collect();
        let view = self.view(&le(times.iter().copied()), None);
        let input = self.accessor(json!({
            "bufferView": view, "componentType": FLOAT, "count": k, "type": "SCALAR",
            "min": [times[0]], "max": [times[k - 1]],
        }));
        let view = self.view(
            &le((0..k * k).map(|i| if i / k == i % k { 1.0 } else { 0.0 })),
            None,
        );
        let output = self.accessor(json!({
            "bufferView": view, "componentType": FLOAT, "count": k * k, "type": "SCALAR",
        }));
        json!([{
            "name": "rollout",
            "samplers": [{"input": input, "output": output, "interpolation": "STEP"}],
            "channels": [{"sampler": 0, "target": {"node": 0, "path": "weights"}}],
        }])
    }
}

/// Writes `.gltf` (JSON with the buffer embedded as base64) or, with `binary`, `.glb`,
/// atomically.
pub fn write(path: &Path, mesh: &AnimatedMesh, binary: bool) -> Result<()> {
    let (mut root, bin) = document(mesh);
    if !binary {
        root["buffers"][0]["uri"] = format!(
            "data:application/octet-stream;base64,{}",
            base64::engine::general_purpose::STANDARD.encode(&bin)
        )
        .into();
        return crate::io::write_text(path, &(serde_json::to_string(&root)? + "\n"));
    }
    let mut json = serde_json::to_vec(&root)?;
    while !json.len().is_multiple_of(4) {
        json.push(b' ');
    }
    let total = 12 + 8 + json.len() + 8 + bin.len();
    crate::io::write_atomic(path, |file| {
        let mut w = std::io::BufWriter::new(file);
        w.write_all(b"glTF")?;
        w.write_all(&2u32.to_le_bytes())?;
        w.write_all(&(total as u32).to_le_bytes())?;
        w.write_all(&(json.len() as u32).to_le_bytes())?;
        w.write_all(b"JSON")?;
        w.write_all(&json)?;
        w.write_all(&(bin.len() as u32).to_le_bytes())?;
        w.write_all(b"BIN\0")?;
        w.write_all(&bin)?;
        w.flush()?;
        Ok(())
    })
}
