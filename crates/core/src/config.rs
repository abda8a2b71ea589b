//! Job configuration: one TOML file per job, `--set section.key=value` overrides, and
//! validation whose errors name the key.

use std::path::{Path, PathBuf};

use anyhow::{Result, bail};
use serde::{Deserialize, Serialize};

use crate::backend::Backend;
use crate::cloth::{GridSpec, SpringLayout};
use crate::data::DataConfig;
use crate::eval::EvalConfig;
use crate::model::{ModelConfig, ModelKind};
use crate::sim::SimConfig;
use crate::source::SourceConfig;
use crate::train::TrainConfig;

pub use crate::settings::{Auto, Job, parse_toml};

/// A whole job: data, surrogate, training and evaluation.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Config {
    /// Run name: the run directory is `runs/<name>` unless `--out` says otherwise.
    pub name: String,
    /// Compute backend.
    pub backend: Backend,
    /// Directory of runs.
    pub runs_dir: PathBuf,
    /// The surrogate's grid.
    pub cloth: GridSpec,
    /// Initial parameters.
    pub model: ModelConfig,
    /// Surrogate integration.
    pub sim: SimConfig,
    /// Rollout data.
    pub data: DataConfig,
    /// Synthetic data generator; `train` runs it when `data.dir` has no `index.json`.
    pub source: Option<SourceConfig>,
    /// Training curriculum.
    pub train: TrainConfig,
    /// Evaluation.
    pub eval: EvalConfig,
}

impl Default for Config {
    fn default() -> Self {
        Self {
            name: "run".into(),
            backend: Backend::Flex,
            runs_dir: PathBuf::from("runs"),
            cloth: GridSpec::default(),
            model: ModelConfig::default(),
            sim: SimConfig::default(),
            data: DataConfig::default(),
            source: None,
            train: TrainConfig::default(),
            eval: EvalConfig::default(),
        }
    }
}

impl Job for Config {
    const KIND: &'static str = "train";

    /// Checks ranges; errors name the key.
    fn validate(&self) -> Result<()> {
        if self.name.is_empty() || self.name.contains('/') {
            bail!("`name` must be a non-empty file name, is {:?}", self.name);
        }
        if self.cloth.nx < 2 || self.cloth.ny < 2 {
            bail!("`cloth.nx` and `cloth.ny` must be at least 2");
        }
        if self.cloth.layout == SpringLayout::Data && self.model.kind != ModelKind::Springs {
            bail!(
                "`cloth.layout = \"data\"` is for the spring surrogate; `model.kind` is {:?}",
                self.model.kind.name()
            );
        }
        if self.cloth.curvature
            && (self.cloth.layout != SpringLayout::Grid || self.model.kind != ModelKind::Springs)
        {
            bail!(
                "`cloth.curvature = true` adds curvature elements to a grid of springs: it needs \
                 `cloth.layout = \"grid\"` and `model.kind = \"springs\"`"
            );
        }
        if self.sim.substeps == Auto::Value(0) {
            bail!("`sim.substeps` must be at least 1");
        }
        if let Auto::Value(c) = self.sim.rayleigh
            && !(c >= 0.0)
        {
            bail!("`sim.rayleigh` must be non-negative");
        }
        let nu = self.sim.viscosity;
        if !(nu.is_finite() && nu >= 0.0) {
            bail!("`sim.viscosity` must be finite and non-negative, is {nu}");
        }
        if nu != 0.0 && self.model.kind != ModelKind::Springs {
            bail!(
                "`sim.viscosity` acts on the springs of the spring surrogate; `model.kind` is {:?}",
                self.model.kind.name()
            );
        }
        let kc = self.sim.shear_compression;
        if !(0.0..=1.0).contains(&kc) {
            bail!(
                "`sim.shear_compression` is the shear springs' stiffness in compression per unit \
                 k, from 0 (they pull only) to 1 (linear springs); is {kc}"
            );
        }
        if kc != 1.0 && self.model.kind != ModelKind::Springs {
            bail!(
                "`sim.shear_compression` acts on the shear springs of the spring surrogate; \
                 `model.kind` is {:?}",
                self.model.kind.name()
            );
        }
        self.model.validate()?;
        let c = &self.data.clips;
        if c.steps.value().is_some_and(|t| t < 2) {
            bail!("`data.clips.steps` must be at least 2");
        }
        for (key, v) in [
            ("fraction", c.fraction),
            ("low_velocity_fraction", c.low_velocity_fraction),
        ] {
            if !(0.0..=1.0).contains(&v) {
                bail!("`data.clips.{key}` must lie in [0, 1], is {v}");
            }
        }
        if let Some(s) = &self.source {
            s.validate().map_err(|e| anyhow::anyhow!("`{e}`"))?;
        }
        self.train.validate()?;
        Ok(())
    }

    /// The defaults, with the `[source]` section (absent by default) at its defaults too.
    fn template() -> Self {
        Config {
            source: Some(crate::source::SourceConfig::default()),
            ..Config::default()
        }
    }

    /// Every key with its default, as TOML that parses back to the defaults, with a comment
    /// above the keys and sections that have one (`springtime config --defaults`). The
    /// `[source]` section, absent by default, is shown with its defaults too.
    fn defaults_toml() -> String {
        let config = Self::template();
        let mut out = String::from(
            "# springtime configuration: every key with its default (`springtime config --defaults`).\n\
             # A job's TOML needs only the keys it changes; unknown keys are errors.\n\
             # data.test_dir (a folder of test rollouts) has no default and is not shown.\n",
        );
        let mut section = String::new();
        for line in config.to_toml().lines() {
            let trimmed = line.trim();
            let key =
                if let Some(name) = trimmed.strip_prefix('[').and_then(|l| l.strip_suffix(']')) {
                    section = name.to_string();
                    Some(section.clone())
                } else {
                    trimmed.split_once(" = ").map(|(k, _)| {
                        if section.is_empty() {
                            k.to_string()
                        } else {
                            format!("{section}.{k}")
                        }
                    })
                };
            if let Some(help) = key.as_deref().and_then(key_help) {
                if trimmed.starts_with('[') {
                    out.push('\n');
                }
                out.push_str(&format!("# {help}\n"));
            }
            out.push_str(line);
            out.push('\n');
        }
        out
    }
}

impl Config {
    /// The run directory: `out` when given, else `runs_dir/name`.
    pub fn run_dir(&self, out: Option<&Path>) -> PathBuf {
        out.map_or_else(|| self.runs_dir.join(&self.name), Path::to_path_buf)
    }

    /// How `train`'s searches score a network by its free rollouts (`train.search_objective`,
    /// its short horizon `eval.short_seconds`).
    pub fn search_objective(&self) -> crate::eval::Objective {
        match self.train.search_objective {
            crate::train::SearchObjective::WholeTake => crate::eval::Objective::WholeTake,
            crate::train::SearchObjective::BothHorizons => crate::eval::Objective::BothHorizons {
                short_seconds: self.eval.short_seconds,
            },
        }
    }

    /// The config as TOML text.
    pub fn to_toml(&self) -> String {
        toml::to_string_pretty(self).expect("config serializes")
    }
}

/// One line about a config key or section, where there is something to say (the book's
/// configuration table has the rest).
fn key_help(key: &str) -> Option<&'static str> {
    // A pass's keys are the same in every pass.
    let generic = key
        .strip_prefix("train.")
        .and_then(|k| k.split_once('.'))
        .filter(|(pass, _)| ["stiffness", "damping", "single", "gnn"].contains(pass))
        .map(|(_, k)| k);
    Some(match (key, generic) {
        ("name", _) => "run name: runs/<name>",
        ("backend", _) => "compute backend: flex, ndarray or wgpu",
        ("runs_dir", _) => "where runs go",
        ("cloth", _) => "the surrogate's particles and springs",
        ("cloth.layout", _) => "grid (the paper's) or data (the data's landmarks and mesh edges)",
        ("cloth.masses", _) => {
            "layout = data: each particle's lumped rest area, or equal masses (total_mass / N)"
        }
        ("cloth.nx" | "cloth.ny", _) => "particles along width / height (layout = grid)",
        ("cloth.bending_stride", _) => {
            "stride of the bending springs (0 = none; layout = data: > 0 adds the hinge springs)"
        }
        ("model", _) => "the model family and its initial parameters",
        ("model.kind", _) => "springs, neural_ode or gnn",
        ("model.k_init", _) => "uniform initial stiffness, N/m",
        ("model.b_init", _) => "uniform initial damping, N·s/m",
        ("sim", _) => "how the surrogate is stepped",
        ("sim.substeps", _) => "integration steps per data frame",
        ("sim.rayleigh", _) => "Rayleigh damping c of the force -c v, N·s/m",
        ("sim.gravity", _) => "m/s²",
        ("sim.viscosity", _) => {
            "isotropic viscosity per unit stiffness β, s: each spring damps its ends' whole \
             relative velocity with β k (0 = none)"
        }
        ("sim.shear_compression", _) => {
            "the shear springs' stiffness in compression per unit k: 1 = linear springs, 0 = they \
             pull only (Blender's shear springs)"
        }
        ("sim.allow_unstable", _) => "run even when the stability guard refuses",
        ("data", _) => "the rollouts (see `springtime data check DIR`)",
        ("data.dir", _) => "folder of .npz rollouts (with index.json, or every file trains)",
        ("data.cache_mib", _) => "memory for resampled rollouts kept between batches, MiB",
        ("data.holdout", _) => {
            "training rollouts held out of the fit to check the result against uniform"
        }
        ("data.clips.steps", _) => "steps per clip",
        ("data.clips.fraction", _) => "fraction of regular clips kept (paper: 0.06)",
        ("data.clips.low_velocity_seconds", _) => {
            "the low-velocity clips: the last seconds of each rollout"
        }
        ("data.clips.low_velocity_fraction", _) => "fraction of those kept (paper: 0.5)",
        ("train", _) => "the training curriculum",
        ("train.mode", _) => "dual (stiffness pass, then damping pass) or single",
        ("train.force_on", _) => {
            "forces of the loss: simulated (the integrator's, paper), target (teacher forcing) \
             or frames (simulated frames differenced like camera-rate data)"
        }
        ("train.checkpoint_every", _) => "iterations between checkpoints",
        ("train.gradient_checkpointing", _) => "recompute instead of storing activations",
        (_, Some("iterations")) => "Adam steps of this pass",
        (_, Some("batch")) => "clips per step",
        (_, Some("lr")) => "learning rate",
        (_, Some("clips")) => "clip pool: low_velocity, regular or all",
        ("eval", _) => "evaluation",
        ("eval.short_seconds" | "eval.long_seconds", _) => {
            "horizons of the short / long motion RMSE, s"
        }
        ("eval.max_rollouts", _) => "evaluate at most this many test rollouts (0 = all)",
        ("source", _) => "synthetic data: present = `train` and `generate` make the rollouts",
        ("source.kind", _) => "mass_spring or fem",
        ("source.width" | "source.height", _) => "sheet size, m",
        ("source.areal_density", _) => "kg/m²",
        ("source.stiffness_levels", _) => "stiffness levels of the map, N/m",
        ("source.layout", _) => "uniform, stripes or patches",
        ("source.storage", _) => "full, or clips: store only the training windows",
        ("source.fem.diagonal", _) => "main, anti or alternating",
        ("source.fem.membrane", _) => "corotational or stvk",
        _ => return None,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn overrides_and_unknown_keys() {
        let c = Config::parse(
            "name = \"a\"\n[data]\ndir = \"x\"\n",
            &[
                "data.dir=/my/rollouts".into(),
                "train.stiffness.lr=0.5".into(),
            ],
        )
        .unwrap();
        assert_eq!(c.data.dir, PathBuf::from("/my/rollouts"));
        assert_eq!(c.train.stiffness.lr, 0.5);
        let err = Config::parse("[train.stiffness]\nlrr = 1\n", &[])
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("train.stiffness") && err.contains("lrr"),
            "{err}"
        );
        let err = Config::parse("[sim]\nsubsteps = \"three\"\n", &[])
            .unwrap_err()
            .to_string();
        assert!(err.contains("sim.substeps"), "{err}");
        let err = Config::parse("", &["sim.substeps=0".into()])
            .unwrap_err()
            .to_string();
        assert!(err.contains("sim.substeps"), "{err}");
        for bad in ["sim.viscosity=-1e-3", "sim.viscosity=nan"] {
            let err = Config::parse("", &[bad.into()]).unwrap_err().to_string();
            assert!(err.contains("sim.viscosity"), "{bad}: {err}");
        }
        let err = Config::parse("[model]\nkind = \"gnn\"\n", &["sim.viscosity=1e-5".into()])
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("sim.viscosity") && err.contains("gnn"),
            "{err}"
        );
        let ok = Config::parse("", &["sim.viscosity=1e-5".into()]).unwrap();
        assert_eq!(ok.sim.viscosity, 1e-5);
        for bad in [
            "sim.shear_compression=-0.1",
            "sim.shear_compression=1.5",
            "sim.shear_compression=nan",
        ] {
            let err = Config::parse("", &[bad.into()]).unwrap_err().to_string();
            assert!(err.contains("sim.shear_compression"), "{bad}: {err}");
        }
        let err = Config::parse(
            "[model]\nkind = \"gnn\"\n",
            &["sim.shear_compression=0".into()],
        )
        .unwrap_err()
        .to_string();
        assert!(
            err.contains("sim.shear_compression") && err.contains("gnn"),
            "{err}"
        );
        let ok = Config::parse("", &["sim.shear_compression=0".into()]).unwrap();
        assert_eq!(ok.sim.shear_compression, 0.0);
        let err = Config::parse("", &["train.least_squares.stencil=0".into()])
            .unwrap_err()
            .to_string();
        assert!(err.contains("train.least_squares.stencil"), "{err}");
        let err = Config::parse("[train.least_squares]\ntarget = \"forces\"\n", &[])
            .unwrap_err()
            .to_string();
        assert!(err.contains("train.least_squares.target"), "{err}");
        let err = Config::parse("backend = \"cuda\"", &[])
            .unwrap_err()
            .to_string();
        assert!(err.contains("backend"), "{err}");
    }

    #[test]
    fn defaults_toml_lists_every_key_and_parses_back() {
        let text = Config::defaults_toml();
        let back = Config::parse(&text, &[]).unwrap();
        assert_eq!(
            back,
            Config {
                source: Some(crate::source::SourceConfig::default()),
                ..Config::default()
            }
        );
        for key in [
            "k_init = \"auto\"",
            "[train.stiffness.weights]",
            "substeps = \"auto\"",
            "# Adam steps",
        ] {
            assert!(text.contains(key), "no {key:?} in\n{text}");
        }
    }

    /// Every key `config --defaults` prints, as `section.key` → value.
    fn default_leaves() -> Vec<(String, toml::Value)> {
        fn walk(prefix: &str, table: &toml::Table, out: &mut Vec<(String, toml::Value)>) {
            for (k, v) in table {
                let key = if prefix.is_empty() {
                    k.clone()
                } else {
                    format!("{prefix}.{k}")
                };
                match v {
                    toml::Value::Table(t) => walk(&key, t, out),
                    v => out.push((key, v.clone())),
                }
            }
        }
        let table: toml::Table = toml::from_str(&Config::defaults_toml()).unwrap();
        let mut out = Vec::new();
        walk("", &table, &mut out);
        out
    }

    /// The keys a cell of the book's configuration table names: `a.b.c`, `d` → `a.b.c`,
    /// `a.b.d` (a bare name shares the first key's section); `a.{x,y}.c` → `a.x.c`, `a.y.c`;
    /// `a.*.c` stays a pattern.
    fn readme_keys(cell: &str) -> Vec<String> {
        let mut keys = Vec::new();
        let mut section = String::new();
        for part in cell.split("`, `") {
            let part = part.trim_matches('`');
            let full = if part.contains('.') || section.is_empty() {
                section = part
                    .rsplit_once('.')
                    .map(|(s, _)| s.to_string())
                    .unwrap_or_default();
                part.to_string()
            } else {
                format!("{section}.{part}")
            };
            match (full.find('{'), full.find('}')) {
                (Some(a), Some(b)) => {
                    for alt in full[a + 1..b].split(',') {
                        keys.push(format!("{}{alt}{}", &full[..a], &full[b + 1..]));
                    }
                }
                _ => keys.push(full),
            }
        }
        keys
    }

    /// Whether table key `pattern` (`*` = one name) covers `key` or the table `key` lies in.
    fn covers(pattern: &str, key: &str) -> bool {
        let (p, k): (Vec<&str>, Vec<&str>) =
            (pattern.split('.').collect(), key.split('.').collect());
        k.len() >= p.len() && p.iter().zip(&k).all(|(a, b)| *a == "*" || a == b)
    }

    /// The same value, numbers compared as numbers (`1e-4` = `0.0001`, `2` = `2.0`).
    fn same_value(a: &toml::Value, b: &toml::Value) -> bool {
        use toml::Value::{Array, Float, Integer};
        match (a, b) {
            (Integer(_) | Float(_), Integer(_) | Float(_)) => {
                let f =
                    |v: &toml::Value| v.as_float().or(v.as_integer().map(|i| i as f64)).unwrap();
                (f(a) - f(b)).abs() <= 1e-12 * f(a).abs().max(f(b).abs())
            }
            (Array(x), Array(y)) => {
                x.len() == y.len() && x.iter().zip(y).all(|(a, b)| same_value(a, b))
            }
            _ => a == b,
        }
    }

    /// The book's configuration table (`docs/src/reference/configuration.md`) cannot drift from the code: every key
    /// `config --defaults` prints has a row, every row names real keys, and where a row lists
    /// one default per key, the defaults are the code's.
    #[test]
    fn the_books_configuration_table_matches_the_defaults() {
        let readme = std::fs::read_to_string(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../../docs/src/reference/configuration.md"
        ))
        .unwrap();
        let table = readme
            .split("\n## Configuration\n")
            .nth(1)
            .expect("the book's configuration page has a Configuration section");
        let rows: Vec<(Vec<String>, String)> = table
            .lines()
            .skip_while(|l| !l.starts_with("| section.key"))
            .skip(2)
            .take_while(|l| l.starts_with('|'))
            .map(|l| {
                let cells: Vec<&str> = l.split(" | ").collect();
                (
                    readme_keys(cells[0].trim_start_matches("| ")),
                    cells[1].to_string(),
                )
            })
            .collect();
        assert!(
            rows.len() > 30,
            "only {} rows read from the book's table",
            rows.len()
        );
        let leaves = default_leaves();
        let missing: Vec<&str> = leaves
            .iter()
            .map(|(key, _)| key.as_str())
            .filter(|key| {
                !rows
                    .iter()
                    .any(|(keys, _)| keys.iter().any(|p| covers(p, key)))
            })
            .collect();
        assert!(
            missing.is_empty(),
            "keys of `springtime config --defaults` without a row in the book's configuration \
             table: {missing:?}"
        );
        let mut checked = 0;
        for (keys, defaults) in &rows {
            for p in keys {
                assert!(
                    // Keys without a default (absent from `config --defaults`).
                    ["data.test_dir", "train.single.lr_b"].contains(&p.as_str())
                        || leaves.iter().any(|(k, _)| covers(p, k)),
                    "the book's configuration table names `{p}`, which is not a config key"
                );
            }
            // One default per key (values may hold commas only inside brackets).
            let values: Vec<toml::Value> = split_top_level(defaults)
                .iter()
                .filter_map(|v| {
                    toml::from_str::<toml::Table>(&format!("v = {}", v.trim().trim_matches('`')))
                        .ok()
                })
                .map(|t| t["v"].clone())
                .collect();
            if values.len() != keys.len() || keys.iter().any(|k| k.contains('*')) {
                continue;
            }
            for (key, want) in keys.iter().zip(&values) {
                let (_, have) = leaves.iter().find(|(k, _)| k == key).unwrap_or_else(|| {
                    panic!("configuration table row `{key}`: not a key with a value")
                });
                assert!(
                    same_value(have, want),
                    "the configuration table says `{key}` defaults to {want}, the code to {have}"
                );
                checked += 1;
            }
        }
        assert!(checked > 40, "only {checked} defaults compared");
    }

    /// `s` split at commas outside brackets and quotes.
    fn split_top_level(s: &str) -> Vec<String> {
        let (mut parts, mut cur, mut depth, mut quoted) = (Vec::new(), String::new(), 0, false);
        for c in s.chars() {
            match c {
                '"' => quoted = !quoted,
                '[' if !quoted => depth += 1,
                ']' if !quoted => depth -= 1,
                ',' if depth == 0 && !quoted => {
                    parts.push(std::mem::take(&mut cur));
                    continue;
                }
                _ => {}
            }
            cur.push(c);
        }
        parts.push(cur);
        parts
    }
}
