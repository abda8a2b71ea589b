//! A drape scene file (`configs/scenes/*.toml`): colliders, contact constants and how the
//! cloth is released.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use serde::{Deserialize, Serialize};

use crate::settings::Job;
use crate::sim::contact::{Collider, ColliderConfig};
use crate::sim::{Contact, ContactConfig, ContactParams};

/// The scene file: a `[scene]` section.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SceneFile {
    /// The scene.
    pub scene: SceneConfig,
}

impl Job for SceneFile {
    const KIND: &'static str = "scene";
    const EXAMPLE: &'static str = "[scene]\n";

    fn validate(&self) -> Result<()> {
        self.scene.validate()
    }
}

/// The `[scene]` section.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SceneConfig {
    /// Simulated time of the experiment (the motion RMSE's window), s.
    pub seconds: f64,
    /// Further time every system keeps running after `seconds` so that it settles (paper §4.5:
    /// "the steady state after each system settles"); the steady-state figures are taken at
    /// `seconds + settle`, s.
    pub settle: f64,
    /// Relative perturbation `ε` of a third reference: the source with every element's
    /// stiffness times `1 + ε·N(0, 1)` (seeded), whose distance to the source is the drape's
    /// sensitivity to parameter error (its chaos floor); 0: none.
    pub perturb: f64,
    /// Height of the flat sheet at release (its plane `z`), m.
    pub release_height: f64,
    /// Horizontal position `[x, y]` of the sheet's centre at release, m.
    pub centre: [f64; 2],
    /// Interval of the recorded frames (metrics over time, figure, OBJ frames), s; rounded
    /// to whole frames of every simulator.
    pub record_every: f64,
    /// Refinement of the fine FEM reference: `(n − 1)·fine + 1` vertices per side of the
    /// source's `n`, so that the source's vertices are fine vertices.
    pub fine: usize,
    /// The contact layer.
    pub contact: ContactConfig,
    /// The colliders.
    pub colliders: Vec<ColliderConfig>,
}

impl Default for SceneConfig {
    fn default() -> Self {
        Self {
            seconds: 8.0,
            settle: 22.0,
            perturb: 0.01,
            release_height: 1.0,
            centre: [0.0, 0.0],
            record_every: 0.02,
            fine: 2,
            contact: ContactConfig::default(),
            colliders: Vec::new(),
        }
    }
}

/// A loaded scene: its name (the file stem), file, config and colliders.
#[derive(Debug, Clone)]
pub struct Scene {
    /// The file's stem (`table` for `table.toml`).
    pub name: String,
    /// The scene file.
    pub path: PathBuf,
    /// The `[scene]` section.
    pub config: SceneConfig,
    /// The built colliders (meshes read).
    pub colliders: Vec<Collider>,
}

impl SceneConfig {
    /// Checks ranges; errors name the key.
    pub fn validate(&self) -> Result<()> {
        let pos = |key: &str, v: f64| -> Result<()> {
            if !(v.is_finite() && v > 0.0) {
                bail!("`scene.{key}` must be positive, is {v}");
            }
            Ok(())
        };
        pos("seconds", self.seconds)?;
        pos("record_every", self.record_every)?;
        if !(self.settle.is_finite() && self.settle >= 0.0) {
            bail!("`scene.settle` must be 0 or positive, is {}", self.settle);
        }
        if !(self.perturb.is_finite() && (0.0..1.0).contains(&self.perturb)) {
            bail!("`scene.perturb` must be in [0, 1), is {}", self.perturb);
        }
        if !self.release_height.is_finite() || !self.centre.iter().all(|c| c.is_finite()) {
            bail!("`scene.release_height` and `scene.centre` must be finite");
        }
        if self.fine < 1 {
            bail!("`scene.fine` must be at least 1");
        }
        self.contact.validate()?;
        for (i, c) in self.colliders.iter().enumerate() {
            c.validate(&format!("scene.colliders[{i}]"))?;
        }
        Ok(())
    }
}

impl Scene {
    /// Reads a scene file (with `--set`-style `overrides`) and builds its colliders; errors name
    /// the file and the key, or the mesh file.
    pub fn load(path: &Path, overrides: &[String]) -> Result<Self> {
        let config = SceneFile::load(path, overrides)?.scene;
        let base = path.parent().unwrap_or(Path::new("."));
        let colliders = config
            .colliders
            .iter()
            .enumerate()
            .map(|(i, c)| c.build(base, &format!("scene.colliders[{i}]")))
            .collect::<Result<Vec<_>>>()
            .with_context(|| format!("in config {}", path.display()))?;
        let name = path
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_else(|| "scene".into());
        Ok(Self {
            name,
            path: path.to_path_buf(),
            config,
            colliders,
        })
    }

    /// The contact of this scene with constants resolved for a sheet whose larger side is
    /// `size`, stepped at `h` with stability number `number` ([`ContactConfig::resolve`]).
    pub fn contact(&self, size: f64, h: f64, number: f64) -> Contact {
        Contact::new(self.colliders.clone(), self.params(size, h, number))
    }

    /// The resolved contact constants (see [`Scene::contact`]).
    pub fn params(&self, size: f64, h: f64, number: f64) -> ContactParams {
        self.config.contact.resolve(size, h, number)
    }

    /// The flat sheet at release: `rest_uv` (in a `width × height` rectangle) centred at
    /// `scene.centre`, at `z = release_height`.
    pub fn release(&self, rest_uv: &[[f64; 2]], width: f64, height: f64) -> Vec<[f64; 3]> {
        let [cx, cy] = self.config.centre;
        crate::cloth::flat(rest_uv, width, height)
            .into_iter()
            .map(|p| [p[0] + cx, p[1] + cy, self.config.release_height])
            .collect()
    }
}
