//! What every config file of springtime shares, below the sections that use it: `Auto` (a
//! setting derived from the data unless given) and reading TOML with `--set section.key=value`
//! overrides, errors naming the key. It imports no section, so every section can import it.

use std::path::Path;

use anyhow::{Context, Result, bail};
use serde::de::DeserializeOwned;
use serde::{Deserialize, Serialize};

/// A setting springtime derives from the data unless the config gives it: `"auto"` (the
/// default of such keys) or a value.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Auto<T> {
    /// Derived from the data when a run starts (the resolved value is written to the run's
    /// `config.toml`).
    #[default]
    Auto,
    /// Given by the config.
    Value(T),
}

impl<T: Copy> Auto<T> {
    /// The value, if the config gives one.
    pub fn value(self) -> Option<T> {
        match self {
            Auto::Auto => None,
            Auto::Value(v) => Some(v),
        }
    }

    /// The value, or `fallback` while it is still `"auto"`.
    pub fn or(self, fallback: T) -> T {
        self.value().unwrap_or(fallback)
    }
}

impl<T: Serialize> Serialize for Auto<T> {
    fn serialize<S: serde::Serializer>(&self, s: S) -> std::result::Result<S::Ok, S::Error> {
        match self {
            Auto::Auto => s.serialize_str("auto"),
            Auto::Value(v) => v.serialize(s),
        }
    }
}

impl<'de, T: Deserialize<'de>> Deserialize<'de> for Auto<T> {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> std::result::Result<Self, D::Error> {
        #[derive(Deserialize)]
        #[serde(untagged)]
        enum Either<T> {
            Value(T),
            Word(String),
        }
        match Either::<T>::deserialize(d).map_err(|_| {
            serde::de::Error::custom("expected \"auto\" or a value of the key's type")
        })? {
            Either::Value(v) => Ok(Auto::Value(v)),
            Either::Word(w) if w == "auto" => Ok(Auto::Auto),
            Either::Word(w) => Err(serde::de::Error::custom(format!(
                "expected \"auto\" or a value of the key's type, found {w:?}"
            ))),
        }
    }
}

/// A job's config file: one TOML schema (unknown keys refused), `--set section.key=value`
/// overrides, validation whose errors name the key, and the template `springtime config
/// --defaults KIND` prints. Every config of springtime is read through it: the training job
/// (`Config`, `train`), `fold`, `xpbd`, `latent` and drape scenes (`scene`).
pub trait Job: Serialize + DeserializeOwned {
    /// The schema's name in `springtime config --defaults KIND`.
    const KIND: &'static str;
    /// TOML for the keys that have no default (empty when every key has one): the template
    /// is this with every other key at its default.
    const EXAMPLE: &'static str = "";

    /// Checks ranges and combinations; errors name the key.
    fn validate(&self) -> Result<()>;

    /// Parses TOML text, applies `overrides`, then validates.
    fn parse(text: &str, overrides: &[String]) -> Result<Self> {
        let job: Self = parse_toml(text, overrides)?;
        job.validate()?;
        Ok(job)
    }

    /// Reads the file `path` with `overrides`; errors name the file and the key.
    fn load(path: &Path, overrides: &[String]) -> Result<Self> {
        let text = std::fs::read_to_string(path)
            .with_context(|| format!("cannot read config {}", path.display()))?;
        Self::parse(&text, overrides).with_context(|| format!("in config {}", path.display()))
    }

    /// Every key at its default; keys without one hold [`Job::EXAMPLE`]'s values.
    fn template() -> Self {
        parse_toml(Self::EXAMPLE, &[]).expect("a schema's example parses")
    }

    /// [`Job::template`] as TOML text that parses back to it.
    fn defaults_toml() -> String {
        let body = toml::to_string_pretty(&Self::template()).expect("a config serializes");
        let mut head = format!(
            "# springtime {} configuration: every key with its default \
             (`springtime config --defaults {}`).\n\
             # A job's TOML needs only the keys it changes; unknown keys are errors.\n",
            Self::KIND,
            Self::KIND
        );
        if !Self::EXAMPLE.is_empty() {
            head += "# Keys without a default hold an example value.\n";
        }
        head + "\n" + &body
    }
}

/// Parses TOML text into `T` after applying `overrides` (`section.key=value`); errors name the
/// key (`` `section.key`: … ``). Any config file of springtime is read this way.
pub fn parse_toml<T: serde::de::DeserializeOwned>(text: &str, overrides: &[String]) -> Result<T> {
    let mut table: toml::Table = text
        .parse()
        .map_err(|e: toml::de::Error| anyhow::anyhow!("{e}"))?;
    for o in overrides {
        apply_override(&mut table, o)?;
    }
    serde_path_to_error::deserialize(toml::Value::Table(table)).map_err(|e| {
        let path = e.path().to_string();
        let inner = e.into_inner();
        if path == "." || path.is_empty() {
            anyhow::anyhow!("{inner}")
        } else {
            anyhow::anyhow!("`{path}`: {inner}")
        }
    })
}

/// Sets `section.key=value` in a TOML table, creating sections as needed.
pub(crate) fn apply_override(table: &mut toml::Table, assignment: &str) -> Result<()> {
    let Some((key, value)) = assignment.split_once('=') else {
        bail!("--set {assignment:?}: expected section.key=value");
    };
    let key = key.trim();
    let parts: Vec<&str> = key.split('.').collect();
    if parts.iter().any(|p| p.is_empty()) {
        bail!("--set {assignment:?}: malformed key `{key}`");
    }
    let value = value.trim();
    let parsed = format!("v = {value}")
        .parse::<toml::Table>()
        .ok()
        .and_then(|mut t| t.remove("v"))
        .unwrap_or_else(|| toml::Value::String(value.to_string()));
    let mut node = table;
    for p in &parts[..parts.len() - 1] {
        let entry = node
            .entry(p.to_string())
            .or_insert_with(|| toml::Value::Table(toml::Table::new()));
        node = match entry {
            toml::Value::Table(t) => t,
            _ => bail!("--set {assignment:?}: `{p}` is not a section"),
        };
    }
    node.insert(parts[parts.len() - 1].to_string(), parsed);
    Ok(())
}
