//! Data: the rollout `.npz` format, the `index.json` beside it, and clip datasets.

pub mod clips;
pub mod npz;
pub mod rollout;
pub mod strain;

pub use clips::{ClipBatch, ClipConfig, ClipRef, ClipSet, HostBatch, Sampler, SeenMask, Track};
pub use rollout::{MeshTruth, Rollout, Segment, SpringTruth};

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use serde::{Deserialize, Serialize};

use crate::settings::Auto;

/// The `[data]` section: where rollouts are and how they are cut.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct DataConfig {
    /// Directory of rollout files (with an `index.json` listing the train and test split, or
    /// plain `.npz` files that are all used for training).
    pub dir: PathBuf,
    /// Optional directory of test rollouts (every `.npz` in it); overrides the index's split.
    pub test_dir: Option<PathBuf>,
    /// Memory for resampled rollouts kept between batches, MiB; `"auto"` (default): half the
    /// memory available when the run starts ([`DataConfig::cache_bytes`]).
    pub cache_mib: Auto<usize>,
    /// Training rollouts held out of the fit (the last ones of the training split): `train`
    /// checks the learned network against the best uniform one on them ([`Split::validation`];
    /// 0 = none; `"auto"`: [`auto_holdout`]).
    pub holdout: Auto<usize>,
    /// How rollouts are cut into clips.
    pub clips: ClipConfig,
}

impl Default for DataConfig {
    fn default() -> Self {
        Self {
            dir: PathBuf::from("data/rollouts"),
            test_dir: None,
            cache_mib: Auto::Auto,
            holdout: Auto::Value(0),
            clips: ClipConfig::default(),
        }
    }
}

impl DataConfig {
    /// The rollout cache's size, bytes, for a run on `backend`: `cache_mib`, or for `"auto"` a
    /// share of the memory available when the run starts (the system's `MemAvailable`,
    /// `/proc/meminfo`, or what the container's cgroup still allows if that is less; 4 GiB
    /// read as available where neither can be read): half with `wgpu`, whose batches and
    /// states live on the device; an eighth on the CPU backends, whose batches, saved states,
    /// autodiff graph and allocator share the host's memory with the cache (Fig. 7's paper-scale
    /// run on 24 GB peaked at 14.8 GB with half, 6.9 GB with 3 GiB). A cache smaller than the
    /// training rollouts makes every batch read most of its clips from disk again (Table 2's
    /// 512 rollouts hold about 15 GB).
    pub fn cache_bytes(&self, backend: crate::backend::Backend) -> usize {
        match self.cache_mib.value() {
            Some(mib) => mib << 20,
            None => {
                let share = match backend {
                    crate::backend::Backend::Wgpu => 2,
                    crate::backend::Backend::Flex | crate::backend::Backend::Ndarray => 8,
                };
                available_memory().unwrap_or(4 << 30) / share
            }
        }
    }
}

/// The memory this process may still take, bytes: `MemAvailable` of `/proc/meminfo`, capped
/// by a cgroup v2 limit (`memory.max − memory.current`) where one is set.
fn available_memory() -> Option<usize> {
    let text = std::fs::read_to_string("/proc/meminfo").ok()?;
    let line = text.lines().find(|l| l.starts_with("MemAvailable:"))?;
    let system = line.split_whitespace().nth(1)?.parse::<usize>().ok()? << 10;
    let read = |name: &str| -> Option<usize> {
        std::fs::read_to_string(format!("/sys/fs/cgroup/{name}"))
            .ok()?
            .trim()
            .parse()
            .ok()
    };
    let cgroup =
        read("memory.max").map(|max| max.saturating_sub(read("memory.current").unwrap_or(0)));
    Some(cgroup.map_or(system, |c| c.min(system)))
}

/// Format tag of `index.json`.
pub const INDEX_FORMAT: &str = "springtime-rollouts/1";

/// `index.json`: the files of a data directory and how they were made.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Index {
    /// Always [`INDEX_FORMAT`].
    pub format: String,
    /// Training rollouts, relative to the directory.
    pub train: Vec<String>,
    /// Test rollouts, relative to the directory.
    pub test: Vec<String>,
    /// The generator and its parameters (free-form).
    #[serde(default)]
    pub generator: serde_json::Value,
}

impl Index {
    /// Path of the index in `dir`.
    pub fn path(dir: &Path) -> PathBuf {
        dir.join("index.json")
    }

    /// Reads `dir/index.json`, if springtime wrote it. An `index.json` of another tool
    /// (unparseable, or without the `train`/`test` lists) is ignored with a warning on stderr;
    /// one of a later springtime format is an error.
    pub fn read(dir: &Path) -> Result<Option<Self>> {
        match Self::probe(dir)? {
            IndexFile::Springtime(index) => Ok(Some(index)),
            IndexFile::Missing => Ok(None),
            IndexFile::Foreign(why) => {
                eprintln!(
                    "warning: ignoring {}: {why}; every .npz of the directory is a training rollout",
                    Self::path(dir).display()
                );
                Ok(None)
            }
        }
    }

    /// What `dir/index.json` is, without warnings.
    pub fn probe(dir: &Path) -> Result<IndexFile> {
        let path = Self::path(dir);
        if !path.exists() {
            return Ok(IndexFile::Missing);
        }
        let text = match std::fs::read_to_string(&path) {
            Ok(t) => t,
            Err(e) => return Ok(IndexFile::Foreign(format!("cannot be read as text ({e})"))),
        };
        let value: serde_json::Value = match serde_json::from_str(&text) {
            Ok(v) => v,
            Err(e) => return Ok(IndexFile::Foreign(format!("not JSON ({e})"))),
        };
        let format = value.get("format").and_then(|f| f.as_str()).unwrap_or("");
        if format.starts_with("springtime-rollouts/") && format != INDEX_FORMAT {
            bail!(
                "{}: unknown format `{format}` (this springtime reads `{INDEX_FORMAT}`)",
                path.display()
            );
        }
        if format != INDEX_FORMAT {
            return Ok(IndexFile::Foreign(
                "not a springtime index (no `format`, `train` and `test` fields as springtime \
                 writes them)"
                    .into(),
            ));
        }
        let index: Index = serde_json::from_value(value)
            .with_context(|| format!("{} is not a valid springtime index", path.display()))?;
        Ok(IndexFile::Springtime(index))
    }
}

/// What a directory's `index.json` turned out to be.
#[derive(Debug, Clone)]
pub enum IndexFile {
    /// There is none.
    Missing,
    /// One that springtime wrote.
    Springtime(Index),
    /// Another tool's file (the reason it is not springtime's).
    Foreign(String),
}

/// The train and test files of a data configuration.
#[derive(Debug, Clone)]
pub struct Split {
    /// Training rollouts.
    pub train: Vec<PathBuf>,
    /// Test rollouts (may be empty).
    pub test: Vec<PathBuf>,
    /// Training rollouts held out of the fit (`data.holdout`, the last of the training files),
    /// on which `train` compares the learned network with the best uniform one.
    pub validation: Vec<PathBuf>,
}

impl DataConfig {
    /// Resolves the train and test files: from `index.json` when present, else every `.npz` of
    /// `dir` is a training file; `test_dir` overrides the test files; the last `holdout`
    /// training files are held out of the fit as validation files.
    pub fn split(&self) -> Result<Split> {
        let (mut train, mut test): (Vec<PathBuf>, Vec<PathBuf>) = match Index::read(&self.dir)? {
            Some(index) => (
                index.train.iter().map(|f| self.dir.join(f)).collect(),
                index.test.iter().map(|f| self.dir.join(f)).collect(),
            ),
            None => (npz_files(&self.dir)?, Vec::new()),
        };
        if let Some(dir) = &self.test_dir {
            test = npz_files(dir)?;
        }
        for p in train.iter().chain(&test) {
            if !p.exists() {
                bail!(
                    "{} is listed in {} but does not exist",
                    p.display(),
                    Index::path(&self.dir).display()
                );
            }
        }
        let holdout = self.holdout.value().unwrap_or(auto_holdout(train.len()));
        if holdout > 0 && holdout >= train.len() {
            bail!(
                "`data.holdout` = {holdout} holds out every training rollout of {} ({} in all): \
                 leave at least one to train on",
                self.dir.display(),
                train.len()
            );
        }
        let validation = train.split_off(train.len() - holdout);
        Ok(Split {
            train,
            test,
            validation,
        })
    }
}

/// `data.holdout = "auto"`: a fifth of `train` training rollouts (rounded down) where there
/// are at least five, else none (a smaller set needs every take to fit).
pub fn auto_holdout(train: usize) -> usize {
    if train >= 5 { train / 5 } else { 0 }
}

/// Every `.npz` file of `dir`, sorted.
pub fn npz_files(dir: &Path) -> Result<Vec<PathBuf>> {
    let rd = std::fs::read_dir(dir)
        .with_context(|| format!("cannot read data directory {}", dir.display()))?;
    let mut files: Vec<PathBuf> = rd
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|e| e == "npz"))
        .collect();
    files.sort();
    if files.is_empty() {
        bail!("{} holds no .npz rollout files", dir.display());
    }
    Ok(files)
}
