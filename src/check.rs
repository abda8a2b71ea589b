//! `springtime data check DIR`: what a dataset folder holds, whether springtime can use it, and
//! how stable a surrogate of the configuration would be on it.

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use anyhow::{Result, bail};

use crate::config::Config;
use crate::data::clips::{ClipSet, SetInfo, check_same, check_same_landmarks, check_same_mesh};
use crate::data::npz::Npz;
use crate::data::rollout::{KEYS, Rollout};
use crate::data::strain::{StrainStats, StrainSummary};
use crate::data::{DataConfig, Index, IndexFile};
use crate::sim::Stability;

/// Smallest and largest of a count over the files of a set.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Range {
    /// Smallest.
    pub min: usize,
    /// Largest.
    pub max: usize,
}

impl Range {
    fn add(this: &mut Option<Range>, v: usize) {
        *this = Some(match *this {
            None => Range { min: v, max: v },
            Some(r) => Range {
                min: r.min.min(v),
                max: r.max.max(v),
            },
        });
    }

    fn show(self) -> String {
        if self.min == self.max {
            self.min.to_string()
        } else {
            format!("{} to {}", self.min, self.max)
        }
    }
}

/// The stability of the configured surrogate on the data (uniform `k_init`, `b_init`).
#[derive(Debug, Clone)]
pub struct SurrogateStability {
    /// Particles along width and height of a grid surrogate (`None` on the data's mesh).
    pub grid: Option<[usize; 2]>,
    /// The surrogate's layout in words ([`crate::cloth::Topology::describe`]).
    pub layout: String,
    /// Whether some particles are interpolated between landmarks (not on one).
    pub interpolated: bool,
    /// Uniform stiffness, N/m.
    pub k: f64,
    /// Uniform damping, N·s/m.
    pub b: f64,
    /// Integration steps per frame.
    pub substeps: usize,
    /// The estimate at `frame_dt / substeps`.
    pub stability: Stability,
    /// What `train` would derive from the data (one line each), or why it cannot.
    pub defaults: std::result::Result<Vec<String>, String>,
    /// `train` picks the stiffness and the substeps itself (a search over free rollouts, which
    /// `data check` does not run): the estimate above is for fallback values only.
    pub decided_by_train: bool,
}

/// What a dataset folder holds.
#[derive(Debug, Clone)]
pub struct DatasetReport {
    /// The folder.
    pub dir: PathBuf,
    /// `index.json`: springtime's (train/test counts), none, or another tool's (ignored).
    pub index: String,
    /// Training files.
    pub train: usize,
    /// Test files.
    pub test: usize,
    /// Stored frames per file.
    pub frames: Range,
    /// Stored frames of all files together.
    pub total_frames: usize,
    /// Shared frame step, mass and rest rectangle.
    pub info: SetInfo,
    /// Landmarks per frame.
    pub landmarks: usize,
    /// Pinned landmarks per file.
    pub pinned: Range,
    /// Files that store velocities.
    pub with_velocities: usize,
    /// Files with ground-truth springs / an FEM mesh.
    pub with_springs: usize,
    /// Files with an FEM mesh and stiffness map.
    pub with_mesh: usize,
    /// Keys springtime ignores: key → dtype, over every file.
    pub ignored_keys: BTreeMap<String, String>,
    /// How far the cloth stretches over the files' frames (`None` without measurable edges).
    pub strain: Option<StrainSummary>,
    /// The configured surrogate's stability on this data.
    pub surrogate: SurrogateStability,
}

/// Reads and validates every rollout of `dir` (the `index.json` split when springtime wrote
/// one, else every `.npz`), checks that they share frame step, mass, rectangle and landmarks,
/// and estimates the stability of `config`'s initial surrogate at the data's frame step. An
/// error names the file and the key.
pub fn check_dir(dir: &Path, config: &Config) -> Result<DatasetReport> {
    if !dir.is_dir() {
        bail!("{} is not a directory", dir.display());
    }
    let index = describe_index(dir)?;
    let data = DataConfig {
        dir: dir.to_path_buf(),
        ..DataConfig::default()
    };
    let split = data.split()?;
    let paths: Vec<&PathBuf> = split.train.iter().chain(&split.test).collect();
    if paths.is_empty() {
        bail!("{} lists no rollout files", Index::path(dir).display());
    }
    let mut survey = Survey::default();
    for path in &paths {
        survey.add(path, paths[0])?;
    }
    let (info, first) = survey.first.expect("at least one file");
    // The surrogate training would start from: the config's values, its "auto"s resolved from
    // the training files exactly as `train` resolves them.
    let train_files = if split.train.is_empty() {
        &split.test
    } else {
        &split.train
    };
    let surrogate = SurrogateStability::of(config, &info, &first, train_files)?;
    Ok(DatasetReport {
        dir: dir.to_path_buf(),
        index,
        train: split.train.len(),
        test: split.test.len(),
        frames: survey.frames.expect("at least one file"),
        total_frames: survey.total_frames,
        info,
        landmarks: first.rest_uv.len(),
        pinned: survey.pinned.expect("at least one file"),
        with_velocities: survey.with_velocities,
        with_springs: survey.with_springs,
        with_mesh: survey.with_mesh,
        ignored_keys: survey.ignored_keys,
        strain: survey.strain.summary(),
        surrogate,
    })
}

/// `index.json` of `dir` in words: springtime's (with its counts), none, or another tool's.
fn describe_index(dir: &Path) -> Result<String> {
    Ok(match Index::probe(dir)? {
        IndexFile::Missing => "none (every .npz is a training rollout)".to_string(),
        IndexFile::Springtime(i) => format!(
            "springtime's ({} train, {} test)",
            i.train.len(),
            i.test.len()
        ),
        IndexFile::Foreign(why) => format!("ignored: {why}"),
    })
}

/// What the files read so far hold.
#[derive(Default)]
struct Survey {
    /// The first file's shared values and contents.
    first: Option<(SetInfo, Rollout)>,
    frames: Option<Range>,
    pinned: Option<Range>,
    total_frames: usize,
    with_velocities: usize,
    with_springs: usize,
    with_mesh: usize,
    ignored_keys: BTreeMap<String, String>,
    strain: StrainStats,
}

impl Survey {
    /// Reads the rollout at `path`, checking that it matches the first file (`first_path`).
    fn add(&mut self, path: &Path, first_path: &Path) -> Result<()> {
        let npz = Npz::read(path)?;
        for (key, a) in &npz.arrays {
            if !KEYS.contains(&key.as_str()) {
                self.ignored_keys
                    .entry(key.clone())
                    .or_insert_with(|| format!("{} {:?}", a.dtype.name(), a.shape));
            }
        }
        for (key, u) in &npz.unreadable {
            if !KEYS.contains(&key.as_str()) {
                self.ignored_keys
                    .entry(key.clone())
                    .or_insert_with(|| u.descr.clone());
            }
        }
        let r = Rollout::from_npz(&npz)?;
        let info = SetInfo::of(&r);
        if let Some((info0, r0)) = &self.first {
            check_same(info0, &info, path, first_path)?;
            check_same_landmarks(&r0.rest_uv, &r.rest_uv, path, first_path)?;
            let first_mesh = r0.mesh.as_ref().map(|m| &m.triangles);
            check_same_mesh(first_mesh, r.mesh.as_ref(), path, first_path)?;
        }
        Range::add(&mut self.frames, r.frames);
        Range::add(&mut self.pinned, r.pinned.iter().filter(|&&p| p).count());
        self.total_frames += r.frames;
        self.with_velocities += usize::from(r.velocities.is_some());
        self.with_springs += usize::from(r.springs.is_some());
        self.with_mesh += usize::from(r.mesh.is_some());
        self.strain.add(&r);
        if self.first.is_none() {
            self.first = Some((info, r));
        }
        Ok(())
    }
}

impl SurrogateStability {
    /// The surrogate `config` would train on the data (first file `first`, shared values
    /// `info`), its "auto"s resolved from `train_files` as `train` resolves them.
    fn of(
        config: &Config,
        info: &SetInfo,
        first: &Rollout,
        train_files: &[PathBuf],
    ) -> Result<Self> {
        let topo = crate::train::topology(config, first)?;
        let mass = info.total_mass / topo.num_particles() as f64;
        let opened = ClipSet::open(
            train_files,
            &config.data.clips,
            |r| crate::train::topology(config, r),
            config.data.cache_bytes(config.backend).min(1 << 30),
            |_| {},
        );
        let (resolved, defaults) =
            match opened.and_then(|clips| crate::train::init::resolve(config, &clips, None)) {
                Ok((c, how)) => (c, Ok(how.lines())),
                Err(e) => (config.clone(), Err(format!("{e:#}"))),
            };
        let s = topo.num_springs();
        let (k, b) = (
            resolved.model.k_init.or(50.0),
            resolved.model.b_init.or(3.0),
        );
        let substeps = resolved.sim.substeps.or(1);
        let stability = Stability::estimate(
            &topo,
            &vec![k; s],
            &vec![b; s],
            mass,
            resolved.sim.rayleigh.or(crate::sim::RAYLEIGH),
            info.frame_dt / substeps as f64,
        );
        Ok(Self {
            grid: topo.grid,
            layout: topo.describe(),
            interpolated: !crate::cloth::Resampler::new(&first.rest_uv, &topo.rest_uv).is_exact(),
            k,
            b,
            substeps,
            decided_by_train: defaults.is_err()
                && config.model.k_init.value().is_none()
                && config.sim.substeps.value().is_none(),
            stability,
            defaults,
        })
    }
}

impl DatasetReport {
    /// Number of files.
    pub fn files(&self) -> usize {
        self.train + self.test
    }

    /// The report as lines of text.
    pub fn render(&self) -> String {
        let mut s = String::new();
        self.render_files(&mut s);
        self.render_grid(&mut s);
        self.render_contents(&mut s);
        self.render_defaults(&mut s);
        self.render_stability(&mut s);
        s
    }

    /// The folder, its files, frames, frame step, mass, rectangle and landmarks.
    fn render_files(&self, s: &mut String) {
        let i = &self.info;
        let files = self.files();
        let _ = writeln!(s, "dataset {}", self.dir.display());
        let _ = writeln!(
            s,
            "  files            {files} ({} train, {} test)",
            self.train, self.test
        );
        let _ = writeln!(s, "  index.json       {}", self.index);
        let _ = writeln!(
            s,
            "  frames           {} per file, {} in all ({:.4} s per file at most)",
            self.frames.show(),
            self.total_frames,
            (self.frames.max.saturating_sub(1)) as f64 * i.frame_dt
        );
        let _ = writeln!(
            s,
            "  frame_dt         {} s ({:.1} fps)",
            i.frame_dt,
            1.0 / i.frame_dt
        );
        let _ = writeln!(s, "  total mass       {} kg", i.total_mass);
        let _ = writeln!(s, "  rest rectangle   {} m × {} m", i.width, i.height);
        let _ = writeln!(s, "  landmarks        {}", self.landmarks);
    }

    /// A note where the surrogate's grid particles are interpolated between the landmarks.
    fn render_grid(&self, s: &mut String) {
        let i = &self.info;
        if let Some([gx, gy]) = self.surrogate.grid
            && gx * gy <= 2 * self.landmarks
            && self.surrogate.interpolated
        {
            let _ = writeln!(
                s,
                "  surrogate grid   {gx} × {gy} particles, not on the landmarks: they are \
                 interpolated between them, whose accelerations no spring produces (the \
                 landmarks themselves: --set cloth.layout=data)"
            );
        }
        if let Some([gx, gy]) = self.surrogate.grid
            && gx * gy > 2 * self.landmarks
        {
            // A grid of about as many particles as landmarks, with the rectangle's aspect.
            let aspect = i.width / i.height;
            let nx = ((self.landmarks as f64 * aspect).sqrt().round() as usize).max(2);
            let ny = ((self.landmarks as f64 / aspect).sqrt().round() as usize).max(2);
            let _ = writeln!(
                s,
                "  surrogate grid   {gx} × {gy} particles for {} landmarks: most particles are \
                 interpolated between landmarks (the landmarks themselves: --set \
                 cloth.layout=data; a grid of about as many particles: --set cloth.nx={nx} \
                 --set cloth.ny={ny})",
                self.landmarks
            );
        }
    }

    /// Pins, velocities, ground truth, ignored keys and the strain.
    fn render_contents(&self, s: &mut String) {
        let files = self.files();
        let all_or = |n: usize| match n {
            0 => "no".to_string(),
            n if n == files => "yes".to_string(),
            n => format!("in {n} of {files} files"),
        };
        let _ = writeln!(s, "  pinned           {}", self.pinned.show());
        let _ = writeln!(s, "  velocities       {}", all_or(self.with_velocities));
        if self.with_springs > 0 || self.with_mesh > 0 {
            let _ = writeln!(
                s,
                "  ground truth     springs {}, FEM mesh {}",
                all_or(self.with_springs),
                all_or(self.with_mesh)
            );
        }
        let ignored = if self.ignored_keys.is_empty() {
            "none".to_string()
        } else {
            self.ignored_keys
                .iter()
                .map(|(k, d)| format!("{k} ({d})"))
                .collect::<Vec<_>>()
                .join(", ")
        };
        let _ = writeln!(s, "  extra keys       ignored: {ignored}");
        if let Some(strain) = &self.strain {
            let _ = writeln!(s, "  strain           {}", strain.line());
            for w in strain.warnings() {
                let _ = writeln!(s, "  WARNING          {w}");
            }
        }
    }

    /// What `train` would derive from the data, or why it cannot.
    fn render_defaults(&self, s: &mut String) {
        let g = &self.surrogate;
        match &g.defaults {
            Ok(lines) => {
                for (n, line) in lines.iter().enumerate() {
                    let head = if n == 0 { "from the data" } else { "" };
                    let _ = writeln!(s, "  {head:<16} {line}");
                }
            }
            Err(why) => {
                let _ = writeln!(
                    s,
                    "  from the data    cannot derive the defaults: {why}{}",
                    if g.decided_by_train {
                        ""
                    } else {
                        " (set them in the config)"
                    }
                );
            }
        }
    }

    /// The surrogate's stability number and what it means for training.
    fn render_stability(&self, s: &mut String) {
        let i = &self.info;
        let g = &self.surrogate;
        let st = &g.stability;
        let _ = writeln!(
            s,
            "  stability        dt²ω² + 2dtγ = {:.4} for the surrogate ({}, k = {} N/m, b = {} N·s/m, {} substep{} per frame, dt = {:.3e} s): {}",
            st.number(),
            g.layout,
            g.k,
            g.b,
            g.substeps,
            if g.substeps == 1 { "" } else { "s" },
            st.dt,
            if g.decided_by_train {
                "not a prediction: `train` searches k over free rollouts and then picks the \
                 substeps that keep it stable"
                    .to_string()
            } else if st.is_stable() {
                format!(
                    "stable (below 4; largest stable dt {:.3e} s)",
                    st.max_stable_dt()
                )
            } else {
                let need = (i.frame_dt / st.max_stable_dt()).ceil() as usize;
                format!(
                    "UNSTABLE (4 or more): training would refuse; set `sim.substeps` to at least {} or a larger mass",
                    need.max(g.substeps + 1)
                )
            }
        );
    }
}
