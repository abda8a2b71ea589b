//! `surrogate.json`: a trained spring network with everything needed to simulate it elsewhere
//! (written by `springtime export`, read by the browser page and by paper 002's distillation).

use std::path::Path;

use anyhow::{Context, Result, bail};
use serde::{Deserialize, Serialize};

use crate::cloth::{SpringFamily, Topology};
use crate::model::SpringNet;
use crate::run::Run;
use crate::sim::Physics;

/// The `format` tag of [`SurrogateJson`].
pub const FORMAT: &str = "springtime-surrogate/1";
/// The format tag of a surrogate with curvature elements: a reader of the first version, which
/// knows springs only, must not take it for one.
pub const FORMAT_CURVATURE: &str = "springtime-surrogate/2";
/// The format tag of a surrogate with a viscosity (`viscosity`, with or without curvature
/// elements): a reader of the earlier versions would step it without the viscosity, so it must
/// not take it for one.
pub const FORMAT_VISCOSITY: &str = "springtime-surrogate/3";
/// The format tag of a surrogate whose shear springs are softer in compression
/// (`shear_compression` below 1, with or without curvature elements and a viscosity): a reader
/// of the earlier versions would step them as linear springs, so it must not take it for one.
pub const FORMAT_COMPRESSION: &str = "springtime-surrogate/4";

/// The format tag of a surrogate with or without curvature elements, a viscosity and shear
/// springs softer in compression.
fn format_of(curvature: bool, viscosity: f64, shear_compression: f64) -> &'static str {
    if shear_compression != 1.0 {
        FORMAT_COMPRESSION
    } else if viscosity != 0.0 {
        FORMAT_VISCOSITY
    } else if curvature {
        FORMAT_CURVATURE
    } else {
        FORMAT
    }
}

/// `surrogate.json`: everything needed to simulate the learned cloth elsewhere (and what
/// `springtime latent train --from` distills; [`SurrogateJson::read`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SurrogateJson {
    /// Always `springtime-surrogate/1`.
    pub format: String,
    /// Units of the values.
    pub units: String,
    /// Particles along width and height of a grid surrogate, particle `row * nx + col`; `null`
    /// for a surrogate on the data's mesh (`cloth.layout = "data"`).
    pub grid: Option<[usize; 2]>,
    /// The rest sheet's triangles (particle indices, counter-clockwise in the rest rectangle).
    #[serde(default)]
    pub triangles: Vec<[usize; 3]>,
    /// Rest rectangle width, m.
    pub width: f64,
    /// Rest rectangle height, m.
    pub height: f64,
    /// Mass of every particle, kg.
    pub masses: Vec<f64>,
    /// Rest positions `(u, v, 0)`, m.
    pub rest_positions: Vec<[f64; 3]>,
    /// Spring endpoints (particle indices).
    pub springs: Vec<[usize; 2]>,
    /// `structural`, `shear` or `bending` per spring.
    pub family: Vec<SpringFamily>,
    /// Rest length per spring, m.
    pub rest_length: Vec<f64>,
    /// Stiffness per spring, N/m (the model's single precision).
    pub k: Vec<f32>,
    /// Damping per spring (along the spring, Eq. 4), N·s/m.
    pub b: Vec<f32>,
    /// Particles pinned in the exported rollout (its anchors), empty without one.
    pub pinned: Vec<usize>,
    /// Rayleigh damping `c` of the force `−c ẋ` on a particle of the mean mass, N·s/m (on a
    /// particle of mass `m_i`, `c · m_i / mean(m)`: damping per unit mass).
    pub rayleigh: f64,
    /// Gravity, m/s².
    pub gravity: [f64; 3],
    /// Isotropic viscosity per unit stiffness `β`, s (`sim.viscosity`): each spring also puts
    /// `β k (v_b − v_a)` on its first end and the opposite on its second; absent where 0.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub viscosity: f64,
    /// The shear springs' stiffness in compression per unit `k` (`sim.shear_compression`): a
    /// spring of `family` `"shear"` shorter than its rest length pushes with
    /// `shear_compression · k`; absent where 1 (linear springs).
    #[serde(default = "one", skip_serializing_if = "is_one")]
    pub shear_compression: f64,
    /// Integration step the surrogate was trained with (frame time / substeps), s, when known.
    pub dt: Option<f64>,
    /// Curvature elements `(i, j, l)` of a grid (`cloth.curvature`), each with the energy
    /// `½ κ |x_i − 2x_j + x_l|²`; absent without.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub curvature: Vec<[usize; 3]>,
    /// Stiffness `κ` per curvature element, N/m.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub curvature_k: Vec<f32>,
    /// Time between frames, s: `substeps` steps of `dt` make one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub frame_dt: Option<f64>,
    /// Integration steps per frame.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub substeps: Option<usize>,
    /// The integrator's particle mass `m` (Rayleigh damping per unit mass is `rayleigh / m`),
    /// kg.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mass: Option<f64>,
    /// The explicit step's stability estimate at `dt` (without contact).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stability: Option<StabilityJson>,
}

/// `surrogate.json`'s `stability`: the step is stable while `number < limit`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StabilityJson {
    /// `dt²ω² + 2·dt·γ` of the stiffest mode.
    pub number: f64,
    /// 4: the explicit step's limit.
    pub limit: f64,
}

impl SurrogateJson {
    /// The spring network `model` of `run`, with the particles `pinned`, stepped by `physics`
    /// (its frame time, substeps, mass and stability) when known.
    pub fn of(run: &Run, model: &SpringNet, pinned: &[usize], physics: Option<&Physics>) -> Self {
        let (topo, config) = (&run.topology, &run.config);
        let to_f32 = |values: Vec<f64>| values.iter().map(|&x| x as f32).collect();
        let (viscosity, shear_compression) = (config.sim.viscosity, config.sim.shear_compression);
        Self {
            format: format_of(!topo.curvature.is_empty(), viscosity, shear_compression).into(),
            pinned: pinned.to_vec(),
            rayleigh: config.sim.rayleigh.or(crate::sim::RAYLEIGH),
            gravity: config.sim.gravity.or(crate::sim::GRAVITY),
            viscosity,
            shear_compression,
            dt: physics.map(Physics::sim_dt),
            curvature_k: to_f32(model.curvature_values()),
            frame_dt: physics.map(|p| p.frame_dt),
            substeps: physics.map(|p| p.substeps),
            mass: physics.map(|p| p.mass),
            stability: physics.map(|p| StabilityJson {
                number: p.stability_of(topo, model).number(),
                limit: 4.0,
            }),
            ..Self::springs(
                topo,
                topo.masses(run.particle_mass()),
                to_f32(model.k_values()),
                to_f32(model.b_values()),
            )
        }
    }

    /// The springs of `topology` with particle `masses` and per-spring `k`, `b`: nothing
    /// pinned, springtime's default Rayleigh damping and gravity, no step, no curvature
    /// stiffness (set `curvature_k` where `topology` has curvature elements).
    pub fn springs(topology: &Topology, masses: Vec<f64>, k: Vec<f32>, b: Vec<f32>) -> Self {
        let topo = topology;
        Self {
            format: format_of(!topo.curvature.is_empty(), 0.0, 1.0).into(),
            units: "SI: m, kg, s, N/m, N·s/m".into(),
            grid: topo.grid,
            triangles: topo.triangles.clone(),
            width: topo.width,
            height: topo.height,
            masses,
            rest_positions: topo.rest_positions(),
            springs: topo.springs.clone(),
            family: topo.family.clone(),
            rest_length: topo.rest_length.clone(),
            k,
            b,
            pinned: Vec::new(),
            rayleigh: crate::sim::RAYLEIGH,
            gravity: crate::sim::GRAVITY,
            viscosity: 0.0,
            shear_compression: 1.0,
            dt: None,
            curvature: topo.curvature.clone(),
            curvature_k: Vec::new(),
            frame_dt: None,
            substeps: None,
            mass: None,
            stability: None,
        }
    }

    /// Reads and checks a `surrogate.json`; errors name the file and the key.
    pub fn read(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path)
            .with_context(|| format!("cannot read {}", path.display()))?;
        let json: Self = serde_json::from_str(&text)
            .with_context(|| format!("{} is not a springtime surrogate.json", path.display()))?;
        json.validate()
            .with_context(|| format!("{} is not a valid surrogate", path.display()))?;
        Ok(json)
    }

    /// Checks the format tag and that the per-particle and per-spring arrays agree.
    pub fn validate(&self) -> Result<()> {
        let p = self.validate_sheet()?;
        self.validate_springs(p)?;
        self.validate_curvature(p)?;
        self.validate_values(p)?;
        self.validate_rest_state()
    }

    /// Checks the format tag, the sheet's size and the per-particle arrays; returns the number
    /// of particles.
    fn validate_sheet(&self) -> Result<usize> {
        let expected = format_of(
            !self.curvature.is_empty(),
            self.viscosity,
            self.shear_compression,
        );
        if self.format != expected {
            bail!("key `format` is {:?}, expected {expected:?}", self.format);
        }
        if let Some([nx, ny]) = self.grid
            && (nx < 2 || ny < 2)
        {
            bail!("key `grid` is [{nx}, {ny}]: at least 2 particles along each side");
        }
        if !(self.width > 0.0 && self.height > 0.0) {
            bail!("keys `width` and `height` must be positive");
        }
        let p = match self.grid {
            Some([nx, ny]) => nx * ny,
            None => self.rest_positions.len(),
        };
        for (key, len) in [
            ("masses", self.masses.len()),
            ("rest_positions", self.rest_positions.len()),
        ] {
            if len != p {
                bail!("key `{key}` has {len} entries, the sheet has {p} particles");
            }
        }
        if self.grid.is_none() && self.triangles.is_empty() {
            bail!("key `triangles` is empty: a surrogate without a `grid` needs its mesh");
        }
        if let Some(t) = self.triangles.iter().find(|t| t.iter().any(|&v| v >= p)) {
            bail!("key `triangles` has a triangle {t:?} past the {p} particles");
        }
        Ok(p)
    }

    /// Checks that the per-spring arrays agree and every spring joins particles of the sheet
    /// (`p` of them).
    fn validate_springs(&self, p: usize) -> Result<()> {
        let s = self.springs.len();
        for (key, len) in [
            ("family", self.family.len()),
            ("rest_length", self.rest_length.len()),
            ("k", self.k.len()),
            ("b", self.b.len()),
        ] {
            if len != s {
                bail!("key `{key}` has {len} entries, key `springs` has {s}");
            }
        }
        if let Some(&[a, b]) = self.springs.iter().find(|&&[a, b]| a >= p || b >= p) {
            bail!("key `springs` has a spring ({a}, {b}) past the {p} particles");
        }
        Ok(())
    }

    /// Checks the curvature elements (on the `p` particles) and their stiffnesses.
    fn validate_curvature(&self, p: usize) -> Result<()> {
        if self.curvature_k.len() != self.curvature.len() {
            bail!(
                "key `curvature_k` has {} entries, key `curvature` has {}",
                self.curvature_k.len(),
                self.curvature.len()
            );
        }
        if let Some(e) = self.curvature.iter().find(|e| e.iter().any(|&i| i >= p)) {
            bail!("key `curvature` has an element {e:?} past the {p} particles");
        }
        if let Some(v) = self
            .curvature_k
            .iter()
            .find(|v| !(v.is_finite() && **v >= 0.0))
        {
            bail!("key `curvature_k` holds {v}: every value must be finite and non-negative");
        }
        Ok(())
    }

    /// Checks the pinned particles (of `p`) and the ranges of masses, `k`, `b`, `rayleigh` and
    /// `viscosity`.
    fn validate_values(&self, p: usize) -> Result<()> {
        if let Some(i) = self.pinned.iter().find(|&&i| i >= p) {
            bail!("key `pinned` has particle {i}, past the {p} particles");
        }
        if let Some(m) = self.masses.iter().find(|m| !(m.is_finite() && **m > 0.0)) {
            bail!("key `masses` holds {m}: every mass must be finite and positive");
        }
        for (key, values) in [("k", &self.k), ("b", &self.b)] {
            if let Some(v) = values.iter().find(|v| !(v.is_finite() && **v >= 0.0)) {
                bail!("key `{key}` holds {v}: every value must be finite and non-negative");
            }
        }
        for (key, v) in [("rayleigh", self.rayleigh), ("viscosity", self.viscosity)] {
            if !(v.is_finite() && v >= 0.0) {
                bail!("key `{key}` is {v}: finite and non-negative");
            }
        }
        let kc = self.shear_compression;
        if !(0.0..=1.0).contains(&kc) {
            bail!("key `shear_compression` is {kc}: from 0 to 1");
        }
        Ok(())
    }

    /// Checks the rest state: the grid (a run's rest rectangle), and every rest length the
    /// distance between its ends there.
    fn validate_rest_state(&self) -> Result<()> {
        let tol = 1e-5 * self.width.max(self.height);
        for (i, q) in self.rest_positions.iter().enumerate() {
            let Some([nx, ny]) = self.grid else { break };
            let (r, c) = (i / nx, i % nx);
            let grid = [
                self.width * c as f64 / (nx - 1) as f64,
                self.height * r as f64 / (ny - 1) as f64,
            ];
            if (q[0] - grid[0]).abs() > tol || (q[1] - grid[1]).abs() > tol || q[2].abs() > tol {
                bail!(
                    "key `rest_positions`: particle {i} is at {q:?}, not at its grid point \
                     ({}, {}, 0) of the {nx} × {ny} grid over {} × {} m",
                    grid[0],
                    grid[1],
                    self.width,
                    self.height
                );
            }
        }
        for (s, (&[a, b], &l)) in self.springs.iter().zip(&self.rest_length).enumerate() {
            let (pa, pb) = (self.rest_positions[a], self.rest_positions[b]);
            let d = ((pa[0] - pb[0]).powi(2) + (pa[1] - pb[1]).powi(2) + (pa[2] - pb[2]).powi(2))
                .sqrt();
            if a == b || !(l > 0.0) || (l - d).abs() > tol {
                bail!(
                    "key `rest_length`: spring {s} ({a}, {b}) has rest length {l}, its ends are \
                     {d} m apart at rest"
                );
            }
        }
        Ok(())
    }

    /// JSON text with one key per line and each array on its line (readable and compact, where
    /// pretty printing would put every number on a line of its own).
    pub fn to_text(&self) -> Result<String> {
        // Destructured so that a new field cannot be forgotten here.
        let SurrogateJson {
            format,
            units,
            grid,
            triangles,
            width,
            height,
            masses,
            rest_positions,
            springs,
            family,
            rest_length,
            k,
            b,
            pinned,
            rayleigh,
            gravity,
            viscosity,
            shear_compression,
            dt,
            curvature,
            curvature_k,
            frame_dt,
            substeps,
            mass,
            stability,
        } = self;
        fn j<T: Serialize>(v: &T) -> Result<String> {
            Ok(serde_json::to_string(v)?)
        }
        let mut fields: Vec<(&str, String)> = vec![
            ("format", j(format)?),
            ("units", j(units)?),
            ("grid", j(grid)?),
            ("triangles", j(triangles)?),
            ("width", j(width)?),
            ("height", j(height)?),
            ("masses", j(masses)?),
            ("rest_positions", j(rest_positions)?),
            ("springs", j(springs)?),
            ("family", j(family)?),
            ("rest_length", j(rest_length)?),
            ("k", j(k)?),
            ("b", j(b)?),
            ("pinned", j(pinned)?),
            ("rayleigh", j(rayleigh)?),
            ("gravity", j(gravity)?),
            ("dt", j(dt)?),
        ];
        if *viscosity != 0.0 {
            fields.push(("viscosity", j(viscosity)?));
        }
        if *shear_compression != 1.0 {
            fields.push(("shear_compression", j(shear_compression)?));
        }
        if !curvature.is_empty() {
            fields.push(("curvature", j(curvature)?));
            fields.push(("curvature_k", j(curvature_k)?));
        }
        if let Some(v) = frame_dt {
            fields.push(("frame_dt", j(v)?));
        }
        if let Some(v) = substeps {
            fields.push(("substeps", j(v)?));
        }
        if let Some(v) = mass {
            fields.push(("mass", j(v)?));
        }
        if let Some(v) = stability {
            fields.push(("stability", j(v)?));
        }
        let body: Vec<String> = fields
            .iter()
            .map(|(key, v)| format!("  \"{key}\": {v}"))
            .collect();
        Ok(format!("{{\n{}\n}}\n", body.join(",\n")))
    }
}

/// Serde's test for an absent `viscosity`.
fn is_zero(v: &f64) -> bool {
    *v == 0.0
}

/// Serde's test for an absent `shear_compression`.
fn is_one(v: &f64) -> bool {
    *v == 1.0
}

/// Serde's default of an absent `shear_compression`: linear springs.
fn one() -> f64 {
    1.0
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn surrogate_json_text_parses_back_to_the_same_value() {
        // A 2 × 2 grid of 1 m cells without diagonals: every value prints exactly.
        let spec = crate::cloth::GridSpec {
            nx: 2,
            ny: 2,
            shear_main: false,
            shear_anti: false,
            bending_stride: 0,
            ..Default::default()
        };
        let topo = Topology::grid(&spec, 1.0, 1.0);
        let (p, s) = (topo.num_particles(), topo.num_springs());
        let j = SurrogateJson {
            pinned: vec![0],
            dt: Some(1e-3),
            ..SurrogateJson::springs(&topo, vec![0.1; p], vec![10.0; s], vec![1.0; s])
        };
        let text = j.to_text().unwrap();
        let back: serde_json::Value = serde_json::from_str(&text).unwrap();
        assert_eq!(back, serde_json::to_value(&j).unwrap());
        assert_eq!(text.lines().count(), 19);
        j.validate().unwrap();

        // A viscosity: one more line, its own format tag, read back the same; under an older
        // tag the file is refused by key.
        let v = SurrogateJson {
            viscosity: 0.01,
            format: FORMAT_VISCOSITY.into(),
            ..j.clone()
        };
        let text = v.to_text().unwrap();
        assert_eq!(text.lines().count(), 20);
        let back: SurrogateJson = serde_json::from_str(&text).unwrap();
        assert_eq!(back, v);
        v.validate().unwrap();
        let old = SurrogateJson {
            format: FORMAT.into(),
            ..v.clone()
        };
        let err = old.validate().unwrap_err().to_string();
        assert!(
            err.contains("`format`") && err.contains(FORMAT_VISCOSITY),
            "{err}"
        );
        let bad = SurrogateJson {
            viscosity: -1.0,
            ..v
        };
        assert!(
            bad.validate()
                .unwrap_err()
                .to_string()
                .contains("`viscosity`")
        );
    }
}
