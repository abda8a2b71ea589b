//! A sweep plan (`PLAN.toml`): a base config and the axes it varies, expanded into jobs in a
//! fixed order. The plan and a job's index decide everything the job does, so any machine that
//! runs index `I` runs the same job.

use crate::settings::Job as _;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use serde::Deserialize;

use crate::config::Config;

/// A parsed plan: the base config, the axes in the plan's order, and the keys that take the
/// job's index as their seed.
#[derive(Debug, Clone, PartialEq)]
pub struct Plan {
    /// The plan file.
    pub path: PathBuf,
    /// Name of the sweep (the plan file's stem unless `name` is given): the default output is
    /// `runs/<name>`.
    pub name: String,
    /// The base config, resolved against the plan's folder first, then the working directory.
    pub base: PathBuf,
    /// Overrides every job applies before its own (`set = ["sim.substeps=2", …]`).
    pub set: Vec<String>,
    /// The axes in the order of the plan file; the product varies the last one fastest.
    pub axes: Vec<Axis>,
    /// Integer config keys that each job sets to the base config's value plus its index
    /// (`index_seeds = ["train.seed"]`), so that repeats differ and stay reproducible.
    pub index_seeds: Vec<String>,
    /// Whether each job also writes its run's report page (`report = true`; default false).
    pub report: bool,
}

/// One axis: a config key (any `--set` key) and the values it takes; or several keys that
/// change together (`"data.dir,data.test_dir" = [["a", "a/test"], ["b", "b/test"]]`).
#[derive(Debug, Clone, PartialEq)]
pub struct Axis {
    /// The key as written in the plan (the column's name).
    pub key: String,
    /// The config keys it sets: one, or the linked ones.
    pub keys: Vec<String>,
    /// Its values, in the plan's order (for linked keys, a list per value).
    pub values: Vec<toml::Value>,
}

impl Axis {
    /// The `key=value` overrides of `value`.
    fn overrides(&self, value: &toml::Value) -> Vec<String> {
        match value {
            toml::Value::Array(items) if self.keys.len() > 1 => self
                .keys
                .iter()
                .zip(items)
                .map(|(k, v)| format!("{k}={v}"))
                .collect(),
            v => vec![format!("{}={v}", self.keys[0])],
        }
    }

    /// The value that names a job: the value, or the first of linked ones.
    fn naming<'a>(&self, value: &'a toml::Value) -> &'a toml::Value {
        match value {
            toml::Value::Array(items) if self.keys.len() > 1 => &items[0],
            v => v,
        }
    }

    /// The folder-name fragment of `value`: the last segment of the (first) key and the value;
    /// paths by the components that differ between the axis' values (`data/a/train`,
    /// `data/b/train` → `a`, `b`).
    fn slug(&self, value: &toml::Value) -> String {
        let value = self.naming(value);
        let toml::Value::String(path) = value else {
            return format!("{}-{}", last_segment(&self.keys[0]), value_slug(value));
        };
        let parts = |s: &str| -> Vec<String> {
            s.split('/')
                .filter(|c| !c.is_empty() && *c != ".")
                .map(String::from)
                .collect()
        };
        let all: Vec<Vec<String>> = self
            .values
            .iter()
            .filter_map(|v| self.naming(v).as_str().map(parts))
            .collect();
        let mine = parts(path);
        let shortest = all.iter().map(Vec::len).min().unwrap_or(0);
        let same =
            |f: &dyn Fn(&Vec<String>) -> Option<String>| all.iter().all(|p| f(p) == f(&all[0]));
        let prefix = (0..shortest)
            .take_while(|&i| same(&|p| p.get(i).cloned()))
            .count();
        let suffix = (0..shortest - prefix)
            .take_while(|&i| same(&|p| p.get(p.len() - 1 - i).cloned()))
            .count();
        let middle = &mine[prefix.min(mine.len())
            ..mine
                .len()
                .saturating_sub(suffix)
                .max(prefix.min(mine.len()))];
        let text = if middle.is_empty() || all.len() < 2 {
            value_slug(value)
        } else {
            value_slug(&toml::Value::String(middle.join("-")))
        };
        format!("{}-{text}", last_segment(&self.keys[0]))
    }
}

/// One job of a plan: its index and the overrides it applies to the base config.
#[derive(Debug, Clone, PartialEq)]
pub struct Job {
    /// Position in the plan's fixed order, from 0.
    pub index: usize,
    /// One value per axis, in axis order.
    pub values: Vec<toml::Value>,
    /// `key=value` overrides, in the order they apply: the plan's `set`, the axes, the index
    /// seeds.
    pub overrides: Vec<String>,
    /// The job's folder name, `<index>-<slug>` (the axis values, made file-name safe).
    pub dir_name: String,
}

/// The plan file as written.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct PlanFile {
    base: String,
    name: Option<String>,
    #[serde(default)]
    set: Vec<String>,
    #[serde(default)]
    axes: BTreeMap<String, toml::Spanned<toml::Value>>,
    #[serde(default)]
    index_seeds: Vec<String>,
    #[serde(default)]
    report: bool,
}

impl Plan {
    /// Reads and checks a plan file; errors name the file and the key.
    pub fn load(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path)
            .with_context(|| format!("cannot read sweep plan {}", path.display()))?;
        Self::parse(path, &text).with_context(|| format!("in sweep plan {}", path.display()))
    }

    /// Parses plan text; `path` places relative paths and names the sweep.
    pub fn parse(path: &Path, text: &str) -> Result<Self> {
        let file: PlanFile =
            toml::from_str(text).map_err(|e: toml::de::Error| anyhow::anyhow!("{e}"))?;
        // The axes in the order they are written: TOML tables carry no order, their spans do.
        let mut spanned: Vec<(String, toml::Spanned<toml::Value>)> =
            file.axes.into_iter().collect();
        spanned.sort_by_key(|(_, v)| v.span().start);
        let mut axes = Vec::with_capacity(spanned.len());
        for (key, value) in spanned {
            axes.push(parse_axis(key, value.into_inner())?);
        }
        for s in &file.set {
            if !s.contains('=') {
                bail!("`set`: {s:?} is not key=value");
            }
        }
        for key in &file.index_seeds {
            if axes.iter().any(|a| a.keys.contains(key)) {
                bail!("`index_seeds`: `{key}` is also an axis; it can be one or the other");
            }
        }
        let name = match file.name {
            Some(n) => n,
            None => path
                .file_stem()
                .map(|s| s.to_string_lossy().into_owned())
                .context("the plan file has no name; set `name`")?,
        };
        if name.is_empty() || name.contains('/') {
            bail!("`name` must be a non-empty file name, is {name:?}");
        }
        let base = resolve_base(path, &file.base)?;
        Ok(Self {
            path: path.to_path_buf(),
            name,
            base,
            set: file.set,
            axes,
            index_seeds: file.index_seeds,
            report: file.report,
        })
    }

    /// Number of jobs: the product of the axes' lengths (1 without axes).
    pub fn len(&self) -> usize {
        self.axes.iter().map(|a| a.values.len()).product()
    }

    /// Whether the plan has no jobs (never, once parsed: every axis has a value).
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Job `index`: the Cartesian product in row-major order, the last axis fastest.
    pub fn job(&self, index: usize) -> Result<Job> {
        let n = self.len();
        if index >= n {
            bail!(
                "job index {index} is out of range: {} has {n} jobs (0 to {})",
                self.path.display(),
                n.saturating_sub(1)
            );
        }
        let mut rest = index;
        let mut values = vec![toml::Value::Boolean(false); self.axes.len()];
        for (slot, axis) in values.iter_mut().zip(&self.axes).rev() {
            *slot = axis.values[rest % axis.values.len()].clone();
            rest /= axis.values.len();
        }
        let mut overrides = self.set.clone();
        overrides.extend(
            self.axes
                .iter()
                .zip(&values)
                .flat_map(|(a, v)| a.overrides(v)),
        );
        if !self.index_seeds.is_empty() {
            let base = self.base_table()?;
            for key in &self.index_seeds {
                let start = lookup(&base, key)
                    .map(|v| {
                        v.as_integer().with_context(|| {
                            format!("`index_seeds`: `{key}` in the base config is not an integer")
                        })
                    })
                    .transpose()?
                    .unwrap_or(0);
                overrides.push(format!("{key}={}", start + index as i64));
            }
        }
        let slug: Vec<String> = self
            .axes
            .iter()
            .zip(&values)
            .map(|(a, v)| a.slug(v))
            .collect();
        let mut dir_name = format!("{index}-{}", slug.join("_"));
        if self.axes.is_empty() {
            dir_name = format!("{index}-{}", self.name);
        }
        // Long names stay readable and unique: the index leads.
        if dir_name.len() > 96 {
            let mut cut = 96;
            while !dir_name.is_char_boundary(cut) {
                cut -= 1;
            }
            dir_name.truncate(cut);
        }
        Ok(Job {
            index,
            values,
            overrides,
            dir_name,
        })
    }

    /// Every job, in index order.
    pub fn jobs(&self) -> Result<Vec<Job>> {
        (0..self.len()).map(|i| self.job(i)).collect()
    }

    /// The base config with a job's overrides applied (checked like `train` checks it).
    pub fn config(&self, job: &Job) -> Result<Config> {
        Config::load(&self.base, &job.overrides).with_context(|| {
            format!(
                "job {} of {} ({})",
                job.index,
                self.path.display(),
                job.overrides.join(" ")
            )
        })
    }

    /// The base config's TOML table, for the index seeds' starting values.
    fn base_table(&self) -> Result<toml::Table> {
        let text = std::fs::read_to_string(&self.base)
            .with_context(|| format!("cannot read config {}", self.base.display()))?;
        let mut table: toml::Table = text
            .parse()
            .map_err(|e: toml::de::Error| anyhow::anyhow!("{}: {e}", self.base.display()))?;
        for s in &self.set {
            crate::settings::apply_override(&mut table, s)?;
        }
        Ok(table)
    }
}

/// One axis of a plan file: `key` (one config key, or several joined by commas that move
/// together) and its list of values.
fn parse_axis(key: String, value: toml::Value) -> Result<Axis> {
    let values = match value {
        toml::Value::Array(values) => values,
        toml::Value::Table(_) => {
            bail!("`axes.{key}` is a table: quote a dotted key, e.g. \"{key}.seed\" = [0, 1]")
        }
        other => bail!(
            "`axes.\"{key}\"` must be a list of values, e.g. [{other}], is {} ",
            other.type_str()
        ),
    };
    if values.is_empty() {
        bail!("`axes.\"{key}\"` lists no values: the sweep would have no jobs");
    }
    let keys: Vec<String> = key.split(',').map(|k| k.trim().to_string()).collect();
    if keys.iter().any(|k| k.split('.').any(str::is_empty)) {
        bail!("`axes.\"{key}\"` is not a config key (section.key, or keys joined by commas)");
    }
    for v in &values {
        check_axis_value(&key, &keys, v)?;
    }
    Ok(Axis { key, keys, values })
}

/// Checks one value of the axis `key` over `keys`: a scalar, or for linked keys a list of one
/// scalar per key.
fn check_axis_value(key: &str, keys: &[String], v: &toml::Value) -> Result<()> {
    let scalars: &[toml::Value] = match v {
        toml::Value::Array(items) if keys.len() > 1 => {
            if items.len() != keys.len() {
                bail!(
                    "`axes.\"{key}\"` links {} keys: every value must be a list of {} \
                     (one per key), {v} is not",
                    keys.len(),
                    keys.len()
                );
            }
            items
        }
        _ if keys.len() > 1 => bail!(
            "`axes.\"{key}\"` links {} keys: every value must be a list of {}, {v} \
             is not",
            keys.len(),
            keys.len()
        ),
        scalar => std::slice::from_ref(scalar),
    };
    if let Some(v) = scalars
        .iter()
        .find(|v| matches!(v, toml::Value::Table(_) | toml::Value::Array(_)))
    {
        bail!(
            "`axes.\"{key}\"`: a value must be a number, string or boolean, not a {}",
            v.type_str()
        );
    }
    Ok(())
}

/// `base` relative to the plan's folder when it exists there, else to the working directory.
fn resolve_base(plan: &Path, base: &str) -> Result<PathBuf> {
    let given = PathBuf::from(base);
    if given.is_absolute() {
        if !given.is_file() {
            bail!("`base`: config {} not found", given.display());
        }
        return Ok(given);
    }
    let beside = plan.parent().unwrap_or(Path::new(".")).join(&given);
    if beside.is_file() {
        return Ok(beside);
    }
    if given.is_file() {
        return Ok(given);
    }
    bail!(
        "`base`: config {base:?} not found beside the plan ({}) or in the working directory",
        beside.display()
    )
}

fn lookup<'a>(table: &'a toml::Table, key: &str) -> Option<&'a toml::Value> {
    let mut parts = key.split('.');
    let mut value = table.get(parts.next()?)?;
    for p in parts {
        value = value.as_table()?.get(p)?;
    }
    Some(value)
}

fn last_segment(key: &str) -> &str {
    key.rsplit('.').next().unwrap_or(key)
}

/// A value as a file-name fragment: strings by their last path component, every character
/// outside `[A-Za-z0-9.+-]` as `_`.
fn value_slug(v: &toml::Value) -> String {
    let text = match v {
        toml::Value::String(s) => Path::new(s)
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_else(|| s.clone()),
        other => other.to_string(),
    };
    let slug: String = text
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || matches!(c, '.' | '+' | '-') {
                c
            } else {
                '_'
            }
        })
        .collect();
    if slug.is_empty() { "_".into() } else { slug }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn plan(text: &str) -> Plan {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(
            dir.path().join("base.toml"),
            "name = \"b\"\n[train]\nseed = 7\n",
        )
        .unwrap();
        let path = dir.path().join("p.toml");
        let p = Plan::parse(&path, text).unwrap();
        // Keep the folder alive for the base config's reads.
        std::mem::forget(dir);
        p
    }

    #[test]
    fn expansion_order_and_overrides_are_pinned() {
        let p = plan(
            "base = \"base.toml\"\n[axes]\n\"train.seed\" = [0, 1, 2, 3]\n\"model.k_init\" = [40.0, 60.0]\n",
        );
        assert_eq!(p.len(), 8);
        assert_eq!(p.name, "p");
        let keys: Vec<&str> = p.axes.iter().map(|a| a.key.as_str()).collect();
        assert_eq!(keys, ["train.seed", "model.k_init"]);
        let jobs = p.jobs().unwrap();
        let seen: Vec<(String, Vec<String>)> = jobs
            .iter()
            .map(|j| (j.dir_name.clone(), j.overrides.clone()))
            .collect();
        let want = |i: usize, s: i64, k: &str| {
            (
                format!("{i}-seed-{s}_k_init-{k}"),
                vec![format!("train.seed={s}"), format!("model.k_init={k}")],
            )
        };
        assert_eq!(
            seen,
            vec![
                want(0, 0, "40.0"),
                want(1, 0, "60.0"),
                want(2, 1, "40.0"),
                want(3, 1, "60.0"),
                want(4, 2, "40.0"),
                want(5, 2, "60.0"),
                want(6, 3, "40.0"),
                want(7, 3, "60.0"),
            ]
        );
        // The order of the file, not the alphabet.
        let q =
            plan("base = \"base.toml\"\n[axes]\n\"z.b\" = [1, 2]\n\"a.c\" = [\"x\", \"y/z\"]\n");
        assert_eq!(q.axes[0].key, "z.b");
        assert_eq!(q.job(1).unwrap().overrides, ["z.b=1", "a.c=\"y/z\""]);
        assert_eq!(q.job(1).unwrap().dir_name, "1-b-1_c-y-z");
        assert!(q.job(4).is_err());
        // Linked keys change together.
        let l = plan(
            "base = \"base.toml\"\n[axes]\n\"data.dir, data.test_dir\" = [[\"a/train\", \"a/test\"], [\"b/train\", \"b/test\"]]\n",
        );
        assert_eq!(l.len(), 2);
        assert_eq!(
            l.job(1).unwrap().overrides,
            ["data.dir=\"b/train\"", "data.test_dir=\"b/test\""]
        );
        assert_eq!(l.job(1).unwrap().dir_name, "1-dir-b");
    }

    #[test]
    fn index_seeds_start_from_the_base_value() {
        let p = plan(
            "base = \"base.toml\"\nindex_seeds = [\"train.seed\", \"source.seed\"]\n[axes]\n\"model.k_init\" = [1.0, 2.0]\n",
        );
        assert_eq!(
            p.job(1).unwrap().overrides,
            ["model.k_init=2.0", "train.seed=8", "source.seed=1"]
        );
    }

    #[test]
    fn bad_plans_name_the_key() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("base.toml"), "name = \"b\"\n").unwrap();
        let path = dir.path().join("p.toml");
        let err = |text: &str| format!("{:#}", Plan::parse(&path, text).unwrap_err());
        assert!(err("base = \"nope.toml\"\n").contains("`base`"));
        assert!(err("base = \"base.toml\"\n[axes]\n\"a.b\" = []\n").contains("axes.\"a.b\""));
        assert!(err("base = \"base.toml\"\n[axes]\n\"a.b\" = 3\n").contains("list of values"));
        assert!(err("base = \"base.toml\"\n[axes]\na.b = [1]\n").contains("quote a dotted key"));
        assert!(err("base = \"base.toml\"\nbogus = 1\n").contains("bogus"));
        assert!(
            err("base = \"base.toml\"\n[axes]\n\"a.b,c.d\" = [[1], [2, 3]]\n")
                .contains("list of 2")
        );
    }
}
