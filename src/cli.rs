//! The command line: one function per subcommand, each a few library calls.
// The doc comments below are clap's `--help` text, written for a terminal (`<run-dir>`,
// `[source]`), not rustdoc markup.
#![allow(rustdoc::invalid_html_tags, rustdoc::broken_intra_doc_links)]

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result, bail};
use clap::{Parser, Subcommand};

use crate::backend::Backend;
use crate::cloth::Resampler;
use crate::config::{Config, Job};
use crate::data::{Rollout, Segment, SpringTruth, Track};
use crate::eval::{self, EvalReport};
use crate::progress::Progress;
use crate::train::{self, TrainOptions};

/// Learn simulatable mass-spring cloth models from motion.
#[derive(Debug, Parser)]
#[command(
    name = "springtime",
    version,
    long_version = long_version(),
    about
)]
pub struct Cli {
    /// What to do.
    #[command(subcommand)]
    pub command: Command,
}

/// Subcommands.
#[derive(Debug, Subcommand)]
pub enum Command {
    /// Generate the rollouts of a config's [source] into its data.dir.
    #[command(
        after_help = "Example:\n  springtime generate configs/quickstart.toml --set source.train_rollouts=64"
    )]
    Generate {
        /// Config file.
        config: PathBuf,
        /// Write only share i of n (rollout j of the fixed order belongs to shard j mod n); the
        /// shard that completes the set writes index.json. The union of the shards is the
        /// unsharded generation, byte for byte.
        #[arg(long, value_name = "i/n")]
        shard: Option<crate::source::Shard>,
        /// Override a config value: section.key=value (repeatable).
        #[arg(long = "set", value_name = "KEY=VALUE")]
        set: Vec<String>,
    },
    /// Run a sweep plan's jobs by index (any engine that hands out indices: a shell loop, a
    /// Slurm array, a Kubernetes Indexed Job, Ray) and gather their figures into one table.
    #[command(
        group(clap::ArgGroup::new("what").required(true).args(["list", "index", "gather"])),
        after_help = "A plan (TOML):\n  base = \"configs/quickstart.toml\"   # beside the plan, or from the working directory\n  \
                      [axes]                              # the product, the last axis fastest\n  \
                      \"train.seed\" = [0, 1, 2, 3]\n  \
                      \"model.k_init\" = [40.0, 60.0]\n\n\
                      Examples:\n  springtime sweep plan.toml --list\n  \
                      springtime sweep plan.toml --index 3 --out runs/plan\n  \
                      springtime sweep plan.toml --index 0-7 --out runs/plan\n  \
                      springtime sweep plan.toml --gather --out runs/plan"
    )]
    Sweep {
        /// The plan file.
        plan: PathBuf,
        /// Print the jobs: index, folder name and overrides, one per line.
        #[arg(long)]
        list: bool,
        /// Run these jobs into OUT/<I>-<slug>/ (one index, or a list like 0,3,5-7): a finished
        /// job is skipped, an interrupted one resumed.
        #[arg(long, value_name = "I")]
        index: Option<String>,
        /// Read every job under OUT and write OUT/sweep.csv, sweep.md and sweep.png, listing
        /// missing and failed jobs.
        #[arg(long)]
        gather: bool,
        /// Output folder (default runs/<plan name>).
        #[arg(long)]
        out: Option<PathBuf>,
    },
    /// Print a configuration as TOML: every key of a job's schema with its default (--defaults
    /// [KIND]), or a training config file resolved (defaults filled in, --set applied).
    #[command(after_help = "Examples:\n  springtime config --defaults > my.toml\n  \
                            springtime config --defaults fold\n  \
                            springtime config configs/quickstart.toml --set sim.substeps=2")]
    Config {
        /// Config file to resolve.
        #[arg(required_unless_present = "defaults", conflicts_with = "defaults")]
        config: Option<PathBuf>,
        /// Print every key of a job's schema with its default (keys without one hold an
        /// example value): `train` (the default; with comments), `fold`, `xpbd`, `latent`,
        /// `scene`.
        #[arg(long, value_name = "KIND", num_args = 0..=1, default_missing_value = "train")]
        defaults: Option<JobKind>,
        /// Override a config value: section.key=value (repeatable).
        #[arg(long = "set", value_name = "KEY=VALUE")]
        set: Vec<String>,
    },
    /// Print a shell completion script (bash, zsh, fish, elvish, powershell) to standard output.
    #[command(
        after_help = "Examples:\n  springtime completions bash > ~/.local/share/bash-completion/completions/springtime\n  \
                            springtime completions zsh > ~/.zfunc/_springtime\n  \
                            springtime completions fish > ~/.config/fish/completions/springtime.fish"
    )]
    Completions {
        /// The shell.
        #[arg(value_enum)]
        shell: clap_complete::Shell,
    },
    /// Dataset tools: `data check DIR`.
    Data {
        /// What to do with the data.
        #[command(subcommand)]
        command: DataCommand,
    },
    /// Static cloth parameters from drapes (paper 001): `xpbd estimate|descriptors CONFIG --out
    /// DIR`.
    Xpbd {
        /// What to do.
        #[command(subcommand)]
        command: XpbdCommand,
    },
    /// Latent-space cloth dynamics (paper 002): `latent generate|train CONFIG`,
    /// `latent eval|bench RUN`.
    Latent {
        /// What to do.
        #[command(subcommand)]
        command: LatentCommand,
    },
    /// Convert other tools' cloth motion (OBJ frames, .pc2 point caches, CSV tracks) into a
    /// springtime rollout file.
    Import {
        /// The input's format.
        #[command(subcommand)]
        source: ImportCommand,
    },
    /// Train a surrogate (generating missing data first), then evaluate it.
    #[command(
        after_help = "Examples:\n  springtime train configs/quickstart.toml\n  springtime train my.toml --set data.dir=data/flag --set sim.substeps=4 --out runs/flag"
    )]
    Train {
        /// Config file.
        config: PathBuf,
        /// Compute backend (default: the config's `backend`).
        #[arg(long, value_enum)]
        backend: Option<Backend>,
        /// Run directory (default runs/<name>).
        #[arg(long)]
        out: Option<PathBuf>,
        /// Continue an interrupted run from its last checkpoint.
        #[arg(long)]
        resume: bool,
        /// Overwrite an existing run.
        #[arg(long, conflicts_with = "resume")]
        force: bool,
        /// Skip the evaluation after training.
        #[arg(long)]
        no_eval: bool,
        /// Skip the report after training.
        #[arg(long)]
        no_report: bool,
        /// Override a config value: section.key=value (repeatable).
        #[arg(long = "set", value_name = "KEY=VALUE")]
        set: Vec<String>,
    },
    /// Evaluate a trained run on its test rollouts (or those in --data) and write eval.json.
    #[command(after_help = "Example:\n  springtime eval runs/quickstart --data data/held_out")]
    Eval {
        /// Run directory.
        run_dir: PathBuf,
        /// Directory of test rollouts (every .npz in it).
        #[arg(long)]
        data: Option<PathBuf>,
        /// Compute backend.
        #[arg(long, value_enum)]
        backend: Option<Backend>,
        /// Override a config value: section.key=value (repeatable).
        #[arg(long = "set", value_name = "KEY=VALUE")]
        set: Vec<String>,
        /// Float type of the simulation: f64 on the CPU backends takes a rollout's own
        /// rounding out of long chaotic horizons (eval.json's `precision`).
        #[arg(long, value_enum, default_value = "f32")]
        precision: crate::backend::Precision,
    },
    /// Draw a finished run's figures and write <run-dir>/report/report.html (self-contained).
    #[command(after_help = "Example:\n  springtime report runs/quickstart")]
    Report {
        /// Run directory.
        run_dir: PathBuf,
        /// Directory of test rollouts (every .npz in it), instead of the run's test split.
        #[arg(long)]
        data: Option<PathBuf>,
        /// Compute backend for the simulations.
        #[arg(long, value_enum)]
        backend: Option<Backend>,
    },
    /// Diagnose a finished run before tuning it: the chaos floor, the observability of every
    /// spring, where the motion error lives, and (where the data carries its source's stiffness
    /// map) what that map is worth as the surrogate's k; writes <run-dir>/diagnose/ and prints a
    /// table.
    Diagnose {
        /// Run directory.
        run_dir: PathBuf,
        /// Directory of test rollouts (every .npz in it), instead of the run's test split.
        #[arg(long)]
        data: Option<PathBuf>,
        /// Output directory (default <run-dir>/diagnose).
        #[arg(long)]
        out: Option<PathBuf>,
        /// Overwrite an existing diagnosis.
        #[arg(long)]
        force: bool,
        /// Relative perturbations ε of k and b for the chaos floor (level 0 is always added).
        #[arg(long, value_delimiter = ',', default_value = "0.005,0.01,0.02")]
        levels: Vec<f64>,
        /// Seed of the chaos floor's perturbation.
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Compute backend for the simulations.
        #[arg(long, value_enum)]
        backend: Option<Backend>,
    },
    /// Export a finished run: the rest mesh and a simulated rollout (OBJ or PLY frames, a glTF
    /// animation, or a .pc2 point cache), the surrogate as JSON and .npz.
    #[command(
        after_help = "Examples:\n  springtime export runs/quickstart --format gltf --out export\n  \
                            springtime export runs/quickstart --format pc2 --out export --seconds 4 --fps 24"
    )]
    Export {
        /// Run directory.
        run_dir: PathBuf,
        /// File format of the meshes and the animation.
        #[arg(long, value_enum, default_value_t = crate::export::Format::Obj)]
        format: crate::export::Format,
        /// Output directory.
        #[arg(long)]
        out: PathBuf,
        /// Rollout file that starts the simulated rollout (default: the run's first test
        /// rollout).
        #[arg(long)]
        init: Option<PathBuf>,
        /// Directory of test rollouts to take the first of.
        #[arg(long)]
        data: Option<PathBuf>,
        /// Seconds to simulate (default: the length of the initial rollout).
        #[arg(long)]
        seconds: Option<f64>,
        /// Frames per second of the exported sequence.
        #[arg(long, default_value_t = 30.0)]
        fps: f64,
        /// Compute backend.
        #[arg(long, value_enum)]
        backend: Option<Backend>,
        /// Overwrite existing files.
        #[arg(long)]
        force: bool,
        /// Drape scene (TOML): export the cloth released flat above its colliders, with
        /// contact, instead of a test rollout.
        #[arg(long, conflicts_with_all = ["init", "data"])]
        scene: Option<PathBuf>,
    },
    /// Train (or reuse) the spring surrogate, the Neural ODE and the GNN on the same data and
    /// write comparison.md, comparison.csv and comparison_rmse.png (paper Table 2).
    #[command(after_help = "Example:\n  springtime compare configs/compare_quick.toml")]
    Compare {
        /// Config file (TOML); its `model.kind` is ignored, every family is trained.
        config: PathBuf,
        /// Output directory (default runs/<name>); runs go to its springs/, gnn/, neural_ode/.
        #[arg(long)]
        out: Option<PathBuf>,
        /// Compute backend for every model.
        #[arg(long, value_enum)]
        backend: Option<Backend>,
        /// Retrain every model even where a finished run exists.
        #[arg(long)]
        force: bool,
        /// Override a config value: section.key=value (repeatable).
        #[arg(long = "set", value_name = "KEY=VALUE")]
        set: Vec<String>,
    },
    /// The membrane-locking fold test (paper §4.4, Fig. 2): settle the FEM source's mesh and a
    /// nested fine mesh pinned at two opposite corners, train a spring surrogate on random
    /// rollouts of the coarse mesh, settle it too, and write fold.json (criteria L1–L4),
    /// fold.csv and fold.png.
    #[command(
        after_help = "Examples:\n  springtime fold configs/fold.toml --out runs/fold\n  \
                      springtime fold configs/fold.toml --out runs/fold_kb --set surrogate.source.fem.bending=0.01"
    )]
    Fold {
        /// Fold config (TOML): a `[fold]` section and the surrogate's training config under
        /// `[surrogate]`.
        config: PathBuf,
        /// Output directory (fold.json, fold.csv, fold.png, surrogate/, data/).
        #[arg(long)]
        out: PathBuf,
        /// Overwrite a finished output directory and retrain the surrogate.
        #[arg(long)]
        force: bool,
        /// Override a config value: section.key=value (repeatable).
        #[arg(long = "set", value_name = "KEY=VALUE")]
        set: Vec<String>,
    },
    /// The drape experiment (paper §4.5, Figs. 8 and 11): release the trained cloth flat above
    /// colliders it never saw, with contact, beside the run's source and a fine FEM reference;
    /// write drape.json, <scene>.png and <scene>_motion_rmse.csv.
    #[command(
        after_help = "Examples:\n  springtime drape runs/drape_quick --scene configs/scenes/table.toml --out runs/drape\n  \
                      springtime drape runs/springs runs/neural_ode --scene configs/scenes/sphere.toml \
                      --scene configs/scenes/mesh.toml --out runs/drape_all --set scene.seconds=4"
    )]
    Drape {
        /// Trained run directories (spring surrogate, Neural ODE; a GNN is reported as not
        /// applicable). The first run's source is the reference.
        #[arg(required = true)]
        runs: Vec<PathBuf>,
        /// Scene file (TOML, `[scene]` with `[[scene.colliders]]`; repeatable).
        #[arg(long, required = true)]
        scene: Vec<PathBuf>,
        /// Output directory (drape.json, <scene>.png, <scene>_motion_rmse.csv).
        #[arg(long)]
        out: PathBuf,
        /// Overwrite a finished output directory.
        #[arg(long)]
        force: bool,
        /// Compute backend of the models (default: each run's).
        #[arg(long, value_enum)]
        backend: Option<Backend>,
        /// Override a scene value: scene.key=value (repeatable, applies to every scene).
        #[arg(long = "set", value_name = "KEY=VALUE")]
        set: Vec<String>,
    },
    /// Time the training workload of ../shared/bench/peer_torch.py; prints one JSON line.
    #[command(after_help = "Example:\n  springtime bench --batch 8 --steps 500 --backend flex")]
    Bench {
        /// Clips per iteration.
        #[arg(long, default_value_t = 8)]
        batch: usize,
        /// Steps per clip.
        #[arg(long, default_value_t = 500)]
        steps: usize,
        /// Compute backend.
        #[arg(long, value_enum, default_value_t = Backend::Flex)]
        backend: Backend,
        /// Timed iterations.
        #[arg(long, default_value_t = 3)]
        iters: usize,
        /// Spring-force implementation.
        #[arg(long, value_enum, default_value_t = crate::model::Kernel::Fused)]
        kernel: crate::model::Kernel,
        /// Particles per side.
        #[arg(long, default_value_t = 32)]
        n: usize,
    },
    /// Simulate a trained surrogate from the first frame of a rollout file, or (--rest) from its
    /// rest state with the pins held.
    #[command(
        after_help = "Examples:\n  springtime simulate runs/quickstart --init data/quickstart/test_0000.npz --seconds 2 --out sim.npz\n  \
                      springtime simulate runs/quickstart --rest --seconds 2 --out rest.npz"
    )]
    Simulate {
        /// Run directory.
        run_dir: PathBuf,
        /// Rollout file giving the initial state and the pinned particles' path (with --rest:
        /// only which particles are pinned; default the run's first test rollout).
        #[arg(long, required_unless_present = "rest")]
        init: Option<PathBuf>,
        /// Start from the surrogate's rest state at zero velocity with the pinned particles held
        /// where they are: the start of `export --format web`'s page (`springtime.reset()`).
        #[arg(long)]
        rest: bool,
        /// Seconds to simulate.
        #[arg(long)]
        seconds: f64,
        /// Output rollout file (.npz).
        #[arg(long)]
        out: PathBuf,
        /// Compute backend.
        #[arg(long, value_enum)]
        backend: Option<Backend>,
        /// Overwrite the output file.
        #[arg(long)]
        force: bool,
        /// Override a config value: section.key=value (repeatable).
        #[arg(long = "set", value_name = "KEY=VALUE")]
        set: Vec<String>,
    },
}

/// `springtime data …`: dataset tools.
#[derive(Debug, Subcommand)]
pub enum DataCommand {
    /// Validate a dataset folder and summarise it: files, frames, frame_dt, mass, rest
    /// rectangle, landmarks, pins, velocities, ignored keys, and the stability number of the
    /// surrogate a config would train (default config unless --config). Exits non-zero, naming
    /// the file and the key, when springtime cannot use the data.
    #[command(after_help = "Example:\n  springtime data check data/rollouts\n  \
                            springtime data check my_takes --config configs/quickstart.toml --set sim.substeps=4")]
    Check {
        /// Folder of .npz rollouts (with or without index.json).
        dir: PathBuf,
        /// Config whose surrogate (cloth grid, model.k_init/b_init, sim) the stability number is
        /// computed for (default: the built-in defaults).
        #[arg(long)]
        config: Option<PathBuf>,
        /// Override a config value: section.key=value (repeatable).
        #[arg(long = "set", value_name = "KEY=VALUE")]
        set: Vec<String>,
    },
}

/// What every `springtime xpbd` job takes: its config, where it writes, whether it may
/// overwrite an earlier result there, and config overrides.
#[derive(Debug, clap::Args)]
pub struct XpbdJob {
    /// The job's TOML (e.g. `configs/xpbd_cotton.toml`).
    pub config: PathBuf,
    /// Output directory.
    #[arg(long)]
    pub out: PathBuf,
    /// Overwrite an earlier result in DIR.
    #[arg(long)]
    pub force: bool,
    /// Override a config value: section.key=value (repeatable).
    #[arg(long = "set", value_name = "KEY=VALUE")]
    pub set: Vec<String>,
}

impl XpbdJob {
    fn load(&self) -> Result<crate::xpbd::estimate::XpbdConfig> {
        crate::xpbd::estimate::XpbdConfig::load(&self.config, &self.set)
    }
}

/// `springtime xpbd` subcommands.
#[derive(Debug, Subcommand)]
pub enum XpbdCommand {
    /// The sim-to-sim experiment of paper 001 §4.2: targets from the XPBD cloth with the
    /// config's true material in its scenarios, γ = (C00, C11, C01, C22, b) fitted from its
    /// initial guess by Levenberg–Marquardt on the shape descriptor and the clamps' reactions.
    /// Writes DIR/estimate.json (γ in SI and CGS, relative errors, iterations, objective).
    #[command(
        after_help = "Example:\n  springtime xpbd estimate configs/xpbd_cotton.toml --out runs/xpbd_cotton"
    )]
    Estimate {
        /// The config, the output directory, --force and --set.
        #[command(flatten)]
        job: XpbdJob,
    },
    /// The config's targets (its [truth] material in its scenarios, with [targets]' refine and
    /// noise) written as static-target files DIR/<scenario>.npz (`positions` [n², 3] on the
    /// template grid, `reactions` [G] in N, `grid`, `size`), the format `targets.dir` reads.
    #[command(
        after_help = "Example:\n  springtime xpbd generate configs/xpbd_cotton.toml --out data/cotton_targets --set targets.refine=2"
    )]
    Generate {
        /// The config, the output directory, --force and --set.
        #[command(flatten)]
        job: XpbdJob,
    },
    /// Re-simulate the γ of an earlier estimate in the config's scenarios (e.g. ones the fit
    /// never saw), from each target's shape, against the targets. Writes DIR/resim.json (each
    /// scenario's largest vertex error).
    #[command(
        after_help = "Example:\n  springtime xpbd resim configs/xpbd_cotton.toml --estimate runs/xpbd_cotton/estimate.json --out runs/xpbd_resim --set 'scenarios=[{kind=\"diagonal_pull\",strain=0.03}]'"
    )]
    Resim {
        /// The config, the output directory, --force and --set.
        #[command(flatten)]
        job: XpbdJob,
        /// The estimate.json whose `gamma` is re-simulated.
        #[arg(long)]
        estimate: PathBuf,
    },
    /// The descriptor study of paper 001 §4.1: the config's estimate with each of the four
    /// descriptors of Eq. 9 (positions, energy, strain, FFT; Fig. 5) into DIR/<descriptor>/,
    /// and how well each tells Table 1's cotton, denim and silk apart against two wrinkle
    /// branches of one material in the config's scenarios (Fig. 7). Writes
    /// DIR/descriptors.json and prints the table.
    #[command(
        after_help = "Example:\n  springtime xpbd descriptors configs/xpbd_cotton.toml --out runs/xpbd_descriptors"
    )]
    Descriptors {
        /// The config, the output directory, --force and --set.
        #[command(flatten)]
        job: XpbdJob,
        /// Out-of-plane amplitude of the perturbed start (the other start is flat), m.
        #[arg(long, default_value_t = 0.01)]
        noise: f64,
    },
    /// The wrinkle-seed invariance of paper 001: the config's estimate with targets from
    /// SEEDS differently perturbed starts (wrinkle branches) and the fit's equilibria on a
    /// branch of their own (from the flat start) or from each target's shape (--start target),
    /// with the FFT and the position descriptors.
    /// Writes DIR/invariance.json (each parameter's coefficient of variation over the seeds)
    /// and prints the table.
    #[command(
        after_help = "Example:\n  springtime xpbd invariance configs/xpbd_cotton.toml --out runs/xpbd_invariance"
    )]
    Invariance {
        /// The config, the output directory, --force and --set.
        #[command(flatten)]
        job: XpbdJob,
        /// Wrinkle seeds (targets).
        #[arg(long, default_value_t = 5)]
        seeds: u64,
        /// Out-of-plane amplitude of the targets' perturbed starts, m.
        #[arg(long, default_value_t = 0.01)]
        noise: f64,
        /// Where every fit's equilibria start: `flat` (a branch of their own) or `target` (each
        /// target's shape, the paper's §3.4.1).
        #[arg(long, value_enum, default_value_t = crate::xpbd::estimate::FitStart::Flat)]
        start: crate::xpbd::estimate::FitStart,
    },
}

/// `springtime latent` subcommands.
#[derive(Debug, Subcommand)]
pub enum LatentCommand {
    /// Simulate the config's full-space reference (the FEM cloth by implicit Euler and Newton,
    /// or with --from a trained spring surrogate) into DIR/rollout.npz and DIR/generate.json.
    #[command(
        after_help = "Example:\n  springtime latent generate configs/latent_cloth.toml --out runs/latent_ref"
    )]
    Generate {
        /// The job's TOML (`configs/latent_cloth.toml`).
        config: PathBuf,
        /// Output directory.
        #[arg(long)]
        out: PathBuf,
        /// Overwrite an earlier rollout in DIR.
        #[arg(long)]
        force: bool,
        /// Simulate a trained spring surrogate (a run directory or an exported
        /// surrogate.json) instead of the config's FEM cloth; its grid replaces `[cloth]`.
        #[arg(long, value_name = "RUN")]
        from: Option<PathBuf>,
        /// Override config values, `section.key=value` (repeatable).
        #[arg(long = "set", value_name = "KEY=VALUE")]
        set: Vec<String>,
    },
    /// Train the autoencoder, then the latent integrator (self-supervised by default;
    /// `--set integrator.loss=supervised` for the baseline). Simulates the reference first
    /// unless --data names one.
    #[command(
        after_help = "Examples:\n  springtime latent train configs/latent_cloth.toml --out runs/latent_cloth\n  springtime latent train configs/latent_distill.toml --from runs/quickstart --out runs/latent_quickstart"
    )]
    Train {
        /// The job's TOML (`configs/latent_cloth.toml`).
        config: PathBuf,
        /// The run directory.
        #[arg(long)]
        out: PathBuf,
        /// A reference rollout (from `latent generate`) to train on.
        #[arg(long)]
        data: Option<PathBuf>,
        /// Reuse a finished run's reference and autoencoder; train only the integrator.
        #[arg(long, value_name = "RUN")]
        autoencoder_from: Option<PathBuf>,
        /// Distill a trained spring surrogate (a run directory or an exported surrogate.json):
        /// its own rollouts are the reference and its springs the potential; its grid replaces
        /// `[cloth]`.
        #[arg(long, value_name = "RUN")]
        from: Option<PathBuf>,
        /// Overwrite a finished run in DIR.
        #[arg(long)]
        force: bool,
        /// Override config values, `section.key=value` (repeatable).
        #[arg(long = "set", value_name = "KEY=VALUE")]
        set: Vec<String>,
    },
    /// Roll the trained model out over the unseen frames; writes RUN/latent_eval.json
    /// (frames, diverged, rmse, max_error, pinned_max_error in metres).
    Eval {
        /// The run directory.
        run: PathBuf,
        /// Also roll out the solved latent step (each step's latent minimises the potential
        /// over the decoder's manifold): the ceiling of what the integrator can learn.
        #[arg(long)]
        subspace: bool,
        /// Newton iterations per solved step at most (with --subspace; default: the run's
        /// `integrator.solve.iterations`).
        #[arg(long)]
        solve_iterations: Option<usize>,
    },
    /// Time one latent frame (integrator + decoder, plain Rust and Burn) against the
    /// full-space Newton step; prints one JSON object as its last line, writes RUN/bench.json.
    Bench {
        /// The run directory.
        run: PathBuf,
        /// Full-space steps to time.
        #[arg(long, default_value_t = 100)]
        full_frames: usize,
    },
}

/// What `springtime import` reads.
#[derive(Debug, Subcommand)]
pub enum ImportCommand {
    /// A folder of OBJ frames (sorted by name, numbers in names compared as numbers; vertex i of
    /// every frame is point i). Rest rectangle: the texture coordinates (`vt`, through `f v/vt`)
    /// scaled so that the mean edge length equals the first frame's, or the flat first frame
    /// when there are no `vt`. Writes OUT/<folder name>.npz.
    #[command(
        after_help = "Example:\n  springtime import obj takes/flag_wave --out data/flag \
                            --frame-dt 0.0416667 --mass 0.3 --pinned 0,20"
    )]
    Obj {
        /// Folder of .obj frames.
        folder: PathBuf,
        /// Output folder, frame step, mass, pins.
        #[command(flatten)]
        args: ImportArgs,
    },
    /// A Blender/Houdini point cache (.pc2) with the OBJ of the cached mesh (same vertex
    /// order) for the rest rectangle. Writes OUT/<cache name>.npz.
    #[command(
        after_help = "Example:\n  springtime import pc2 cache/cloth.pc2 --rest cache/cloth_rest.obj \
                            --out data/cloth --frame-dt 0.04 --mass 0.5 --pinned 0,31"
    )]
    Pc2 {
        /// The .pc2 file.
        file: PathBuf,
        /// OBJ of the cached mesh: its texture coordinates (or flat shape) give the rest
        /// rectangle.
        #[arg(long)]
        rest: PathBuf,
        /// Output folder, frame step, mass, pins.
        #[command(flatten)]
        args: ImportArgs,
    },
    /// Tracked points as CSV: a header naming the columns frame, point, x, y, z and optionally
    /// u, v (rest coordinates, m); one row per point per frame. A point missing from a frame, or
    /// with empty or nan coordinates, was not seen there: the rollout's `visible` mask records
    /// it, and training and evaluation skip it. Without u, v the first frame must be flat and
    /// see every point. Writes OUT/<file stem>.npz.
    #[command(
        after_help = "Example:\n  springtime import csv markers.csv --out data/markers \
                            --frame-dt 0.01 --mass 0.2\n\nmarkers.csv:\n  frame,point,x,y,z,u,v\n  \
                            0,0,0.0,0.0,1.5,0.0,0.0\n  0,1,0.5,0.0,1.5,0.5,0.0\n  …"
    )]
    Csv {
        /// The .csv file.
        file: PathBuf,
        /// Output folder, frame step, mass, pins.
        #[command(flatten)]
        args: ImportArgs,
    },
}

/// The options every importer takes.
#[derive(Debug, clap::Args)]
pub struct ImportArgs {
    /// Output folder (created if needed).
    #[arg(long)]
    pub out: PathBuf,
    /// Seconds between frames (samples).
    #[arg(long, value_name = "S")]
    pub frame_dt: f64,
    /// Mass of the whole cloth, kg.
    #[arg(long, value_name = "KG")]
    pub mass: f64,
    /// Pinned points, 0-based in the source's vertex/point order (default: none, the cloth
    /// moves freely).
    #[arg(long, value_name = "I,J,…", value_delimiter = ',')]
    pub pinned: Vec<usize>,
    /// Rest rectangle width, m (with --height; default: derived from the geometry).
    #[arg(long, value_name = "W", requires = "height")]
    pub width: Option<f64>,
    /// Rest rectangle height, m (with --width).
    #[arg(long, value_name = "H", requires = "width")]
    pub height: Option<f64>,
    /// Gravity the cloth moved under, m/s², as x,y,z in the file's axes (stored in the rollout;
    /// default: none stored, training then uses 0,0,-9.81). Write it as --gravity=0,-9.81,0
    /// when it starts with a minus sign.
    #[arg(
        long,
        value_name = "X,Y,Z",
        value_delimiter = ',',
        allow_negative_numbers = true
    )]
    pub gravity: Option<Vec<f64>>,
    /// Rayleigh damping c of −c·v on every point, N·s/m, when the tool that made the motion
    /// used one (stored in the rollout; default: none stored, training fits it).
    #[arg(long, value_name = "C")]
    pub rayleigh: Option<f64>,
    /// The positions' measurement noise, m per axis (a capture's marker accuracy; stored in
    /// the rollout as `position_noise`, which the least-squares fit takes out; default: none
    /// stored, exact positions).
    #[arg(long, value_name = "SIGMA")]
    pub position_noise: Option<f64>,
    /// Overwrite an existing rollout file.
    #[arg(long)]
    pub force: bool,
}

impl ImportArgs {
    fn options(&self) -> Result<crate::import::ImportOptions> {
        let size = match (self.width, self.height) {
            (Some(w), Some(h)) => {
                if !(w > 0.0 && h > 0.0 && w.is_finite() && h.is_finite()) {
                    bail!("--width and --height must be positive, are {w} and {h}");
                }
                Some([w, h])
            }
            _ => None,
        };
        let gravity = match self.gravity.as_deref() {
            None => None,
            Some(&[x, y, z]) => Some([x, y, z]),
            Some(other) => bail!("--gravity takes three numbers x,y,z, got {}", other.len()),
        };
        Ok(crate::import::ImportOptions {
            out: self.out.clone(),
            frame_dt: self.frame_dt,
            total_mass: self.mass,
            pinned: self.pinned.clone(),
            size,
            gravity,
            rayleigh: self.rayleigh,
            position_noise: self.position_noise,
            force: self.force,
        })
    }
}

/// Runs a parsed command line: the data, config and study commands here, the commands that
/// train and evaluate a run in `train_or_evaluate`, those that put a trained run to use in
/// `use_trained`.
pub fn run(cli: Cli) -> Result<()> {
    let progress = Progress::auto();
    match cli.command {
        Command::Generate { config, shard, set } => generate(&config, shard, &set, &progress),
        Command::Sweep {
            plan,
            list,
            index,
            gather,
            out,
        } => sweep(&plan, list, index.as_deref(), gather, out, &progress),
        Command::Config {
            config,
            defaults,
            set,
        } => print_config(config.as_deref(), defaults, &set),
        Command::Completions { shell } => completions(shell),
        Command::Import { source } => import(&source),
        Command::Xpbd { command } => xpbd(command, &progress),
        Command::Latent { command } => latent(command, &progress),
        Command::Data {
            command: DataCommand::Check { dir, config, set },
        } => data_check(&dir, config.as_deref(), &set),
        Command::Compare {
            config,
            out,
            backend,
            force,
            set,
        } => compare(
            &config,
            &set,
            &crate::compare::CompareOptions {
                out,
                force,
                backend,
            },
            &progress,
        ),
        Command::Fold {
            config,
            out,
            force,
            set,
        } => fold(&config, out, force, &set, &progress),
        Command::Bench {
            batch,
            steps,
            backend,
            iters,
            kernel,
            n,
        } => bench(&crate::bench::BenchOptions {
            batch,
            steps,
            backend,
            iters,
            kernel,
            n,
        }),
        // Listed by name, so that a new command fails to compile here instead of reaching an
        // `unreachable!` below.
        command @ (Command::Train { .. }
        | Command::Eval { .. }
        | Command::Report { .. }
        | Command::Diagnose { .. }
        | Command::Export { .. }
        | Command::Simulate { .. }
        | Command::Drape { .. }) => train_or_evaluate(command, &progress),
    }
}

/// `train`, `eval`, `report` and `diagnose`; the other commands go on to [`use_trained`].
fn train_or_evaluate(command: Command, progress: &Progress) -> Result<()> {
    match command {
        Command::Train {
            config,
            backend,
            out,
            resume,
            force,
            no_eval,
            no_report,
            set,
        } => train_command(
            &config,
            backend,
            TrainOptions { out, resume, force },
            !no_eval,
            !no_report,
            &set,
            progress,
        ),
        Command::Eval {
            run_dir,
            data,
            backend,
            set,
            precision,
        } => evaluate(
            &run_dir,
            data.as_deref(),
            backend,
            &set,
            precision,
            progress,
        ),
        Command::Report {
            run_dir,
            data,
            backend,
        } => report(&run_dir, data, backend, progress),
        Command::Diagnose {
            run_dir,
            data,
            out,
            force,
            levels,
            seed,
            backend,
        } => diagnose(
            &run_dir,
            &crate::diagnose::DiagnoseOptions {
                data,
                out,
                force,
                levels,
                seed,
                backend,
            },
            progress,
        ),
        command @ (Command::Export { .. } | Command::Simulate { .. } | Command::Drape { .. }) => {
            use_trained(command, progress)
        }
        _ => unreachable!("run dispatches every other command"),
    }
}

/// `export`, `simulate` and `drape`: what [`run`] and [`train_or_evaluate`] leave.
fn use_trained(command: Command, progress: &Progress) -> Result<()> {
    match command {
        Command::Export {
            run_dir,
            format,
            out,
            init,
            data,
            seconds,
            fps,
            backend,
            force,
            scene,
        } => export(
            &run_dir,
            &crate::export::ExportOptions {
                format,
                out,
                init,
                data,
                seconds,
                fps,
                force,
                backend,
                scene,
            },
            progress,
        ),
        Command::Simulate {
            run_dir,
            init,
            rest,
            seconds,
            out,
            backend,
            force,
            set,
        } => simulate(
            &run_dir,
            SimulateJob {
                init: init.as_deref(),
                rest,
                seconds,
                out: &out,
                force,
            },
            backend,
            &set,
            progress,
        ),
        Command::Drape {
            runs,
            scene,
            out,
            force,
            backend,
            set,
        } => drape(
            &crate::drape::DrapeOptions {
                runs,
                scenes: scene,
                out,
                force,
                backend,
                set,
            },
            progress,
        ),
        _ => unreachable!("run and train_or_evaluate dispatch every other command"),
    }
}

/// `springtime completions`: the shell's completion script on standard output.
fn completions(shell: clap_complete::Shell) -> Result<()> {
    let mut command = <Cli as clap::CommandFactory>::command();
    clap_complete::generate(shell, &mut command, "springtime", &mut std::io::stdout());
    Ok(())
}

/// `springtime eval`: the run evaluated and its figures printed; f64 only on the CPU backends.
fn evaluate(
    run_dir: &Path,
    data: Option<&Path>,
    backend: Option<Backend>,
    set: &[String],
    precision: crate::backend::Precision,
    progress: &Progress,
) -> Result<()> {
    if precision == crate::backend::Precision::F64 {
        let run = train::RunDir::new(run_dir);
        let configured = Config::load(&run.config(), set).map(|c| c.backend).ok();
        if backend.or(configured) == Some(Backend::Wgpu) {
            bail!(
                "--precision f64 runs on the CPU backends; the run's backend is wgpu \
                 (pass --backend flex)"
            );
        }
    }
    precision.apply()?;
    let report = crate::run::evaluate(run_dir, data, backend, set, progress)?;
    print_eval(&report);
    Ok(())
}

/// `springtime bench`: the report as one JSON line.
fn bench(options: &crate::bench::BenchOptions) -> Result<()> {
    let report = crate::bench::run(options)?;
    println!("{}", serde_json::to_string(&report)?);
    Ok(())
}

/// The config schemas of springtime's jobs (`config --defaults KIND`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum JobKind {
    /// `train`, `eval`, `compare`, `sweep` jobs: [`Config`].
    Train,
    /// `fold`: [`crate::fold::FoldConfig`].
    Fold,
    /// `xpbd estimate|generate|resim`: [`crate::xpbd::estimate::XpbdConfig`].
    Xpbd,
    /// `latent train`: [`crate::latent::LatentConfig`].
    Latent,
    /// `drape --scene`: [`crate::drape::scene::SceneFile`].
    Scene,
}

impl JobKind {
    /// Every key of the schema with its default, as TOML that parses back.
    pub fn defaults_toml(self) -> String {
        match self {
            Self::Train => Config::defaults_toml(),
            Self::Fold => crate::fold::FoldConfig::defaults_toml(),
            Self::Xpbd => crate::xpbd::estimate::XpbdConfig::defaults_toml(),
            Self::Latent => crate::latent::LatentConfig::defaults_toml(),
            Self::Scene => crate::drape::scene::SceneFile::defaults_toml(),
        }
    }
}

/// `springtime config`: a config file resolved, or every default of a schema.
fn print_config(config: Option<&Path>, defaults: Option<JobKind>, set: &[String]) -> Result<()> {
    match (config, defaults) {
        (Some(path), _) => print!("{}", Config::load(path, set)?.to_toml()),
        (None, Some(kind)) if set.is_empty() => print!("{}", kind.defaults_toml()),
        (None, _) => print!("{}", Config::parse("", set)?.to_toml()),
    }
    Ok(())
}

/// `springtime import`: another tool's motion as a rollout file.
fn import(source: &ImportCommand) -> Result<()> {
    let summary = match source {
        ImportCommand::Obj { folder, args } => {
            crate::import::obj::import_sequence(folder, &args.options()?)?
        }
        ImportCommand::Pc2 { file, rest, args } => {
            crate::import::pc2::import_cache(file, rest, &args.options()?)?
        }
        ImportCommand::Csv { file, args } => {
            crate::import::csv::import_tracks(file, &args.options()?)?
        }
    };
    println!("wrote {summary}");
    Ok(())
}

/// `springtime latent …`.
fn latent(command: LatentCommand, progress: &Progress) -> Result<()> {
    match command {
        LatentCommand::Generate {
            config,
            out,
            force,
            from,
            set,
        } => latent_generate(&config, &set, from.as_deref(), &out, force, progress),
        LatentCommand::Train {
            config,
            out,
            data,
            autoencoder_from,
            from,
            force,
            set,
        } => latent_train(
            &config,
            &set,
            &crate::latent::train::TrainOptions {
                out,
                data,
                force,
                autoencoder_from,
                from,
            },
            progress,
        ),
        LatentCommand::Eval {
            run,
            subspace,
            solve_iterations,
        } => latent_eval(&run, subspace, solve_iterations),
        LatentCommand::Bench { run, full_frames } => latent_bench(&run, full_frames),
    }
}

/// `springtime latent generate`: the full-space reference rollout.
fn latent_generate(
    config: &Path,
    set: &[String],
    from: Option<&Path>,
    out: &Path,
    force: bool,
    progress: &Progress,
) -> Result<()> {
    let mut cfg = crate::latent::LatentConfig::load(config, set)?;
    let full = crate::latent::full::FullSpace::new(&mut cfg, from)?;
    let (_, stats) = crate::latent::train::generate_reference(&cfg, &full, out, force, progress)?;
    println!(
        "{} frames, {:.2} Newton iterations per step (at most {}), {:.1} ms per step",
        stats.frames,
        stats.mean_iterations,
        stats.max_iterations,
        stats.us_per_step / 1e3
    );
    println!("reference: {}", out.join("rollout.npz").display());
    Ok(())
}

/// `springtime latent train`: the autoencoder, then the latent integrator.
fn latent_train(
    config: &Path,
    set: &[String],
    options: &crate::latent::train::TrainOptions,
    progress: &Progress,
) -> Result<()> {
    let cfg = crate::latent::LatentConfig::load(config, set)?;
    let meta = crate::latent::train::train(&cfg, options, progress)?;
    println!(
        "autoencoder: {} epochs in {:.0} s, reconstruction RMSE {:.3} mm (train) / {:.3} mm (unseen)",
        meta.autoencoder.epochs,
        meta.autoencoder.seconds,
        meta.reconstruction_rmse_train * 1e3,
        meta.reconstruction_rmse_test * 1e3
    );
    println!(
        "integrator: {} epochs in {:.0} s, final loss {:.5e}",
        meta.integrator.epochs, meta.integrator.seconds, meta.integrator.final_loss
    );
    println!("run: {}", options.out.display());
    Ok(())
}

/// `springtime latent eval`: the unseen frames' errors (and the solved latent steps').
fn latent_eval(run: &Path, subspace: bool, solve_iterations: Option<usize>) -> Result<()> {
    if solve_iterations == Some(0) {
        bail!("--solve-iterations must be at least 1");
    }
    let r = crate::latent::eval::evaluate(run, subspace, solve_iterations)?;
    if let Some(s) = &r.subspace {
        println!(
            "solved latent steps: RMSE {:.2} mm, max error {:.2} mm, kinetic energy ratio {:.2}, {}, {:.0} s, {} of {} steps unconverged",
            s.rmse * 1e3,
            s.max_error * 1e3,
            s.kinetic_energy_ratio,
            if s.diverged {
                "DIVERGED"
            } else {
                "no divergence"
            },
            s.seconds,
            s.unconverged_steps,
            r.frames
        );
    }
    println!(
        "{} unseen frames from frame {}: RMSE {:.2} mm, max error {:.2} mm, pinned within {:.3} mm, {}",
        r.frames,
        r.first_frame,
        r.rmse * 1e3,
        r.max_error * 1e3,
        r.pinned_max_error * 1e3,
        if r.diverged {
            "DIVERGED"
        } else {
            "no divergence"
        }
    );
    println!(
        "last 50 frames: {:.2} mm from the reference's last frame, moving {:.3} mm per frame",
        r.rest_rmse_last_50 * 1e3,
        r.rest_motion_last_50 * 1e3
    );
    println!("eval: {}", run.join("latent_eval.json").display());
    Ok(())
}

/// `springtime latent bench`: the timings, a summary line and one JSON line.
fn latent_bench(run: &Path, full_frames: usize) -> Result<()> {
    let r = crate::latent::eval::bench(run, full_frames)?;
    println!(
        "latent frame {:.1} µs (integrator {:.1} + decoder {:.1}; Burn {:.0} µs), full-space step {:.0} µs: {:.0}× faster; a solved latent step {:.0} µs",
        r.latent_us_per_frame,
        r.integrator_us,
        r.decoder_us,
        r.burn_us_per_frame,
        r.full_us_per_frame,
        r.speedup,
        r.solved_us_per_frame
    );
    println!("{}", serde_json::to_string(&r)?);
    Ok(())
}

/// `springtime xpbd`: each subcommand.
fn xpbd(command: XpbdCommand, progress: &Progress) -> Result<()> {
    match command {
        XpbdCommand::Estimate { job } => xpbd_estimate(&job, progress),
        XpbdCommand::Generate { job } => {
            let cfg = job.load()?;
            for path in crate::xpbd::estimate::generate(&cfg, &job.out, job.force, progress)? {
                println!("target: {}", path.display());
            }
            Ok(())
        }
        XpbdCommand::Resim { job, estimate } => xpbd_resim(&job, &estimate, progress),
        XpbdCommand::Descriptors { job, noise } => xpbd_descriptors(&job, noise, progress),
        XpbdCommand::Invariance {
            job,
            seeds,
            noise,
            start,
        } => xpbd_invariance(&job, seeds, noise, start, progress),
    }
}

/// `springtime xpbd estimate`: the fit, then the fitted γ beside the truth.
fn xpbd_estimate(job: &XpbdJob, progress: &Progress) -> Result<()> {
    use crate::xpbd::estimate;
    let cfg = job.load()?;
    let r = estimate::estimate(
        &cfg,
        &estimate::EstimateOptions {
            out: job.out.clone(),
            force: job.force,
        },
        progress,
    )?;
    println!(
        "{:<6} {:>14} {:>14} {:>14} {:>10}",
        "γ", "truth", "initial", "fitted", "error"
    );
    let (i, f) = (r.initial.to_array(), r.gamma.to_array());
    let t = r.truth.map(|t| t.to_array());
    for (k, name) in crate::xpbd::material::NAMES.iter().enumerate() {
        match t {
            Some(t) => println!(
                "{name:<6} {:>14.6e} {:>14.6e} {:>14.6e} {:>9.3}%",
                t[k],
                i[k],
                f[k],
                100.0 * r.signed_error[*name]
            ),
            None => println!("{name:<6} {:>14} {:>14.6e} {:>14.6e}", "-", i[k], f[k]),
        }
    }
    println!(
        "{} {} steps, objective {:.3e} → {:.3e}, {:.1} s",
        r.iterations,
        r.optimizer.describe(),
        r.objective.first().copied().unwrap_or(f64::NAN),
        r.objective.last().copied().unwrap_or(f64::NAN),
        r.wall_seconds
    );
    println!("estimate: {}", job.out.join("estimate.json").display());
    Ok(())
}

/// `springtime xpbd descriptors`: the study, then its two tables.
fn xpbd_descriptors(job: &XpbdJob, noise: f64, progress: &Progress) -> Result<()> {
    use crate::xpbd::study;
    let cfg = job.load()?;
    let options = study::StudyOptions {
        out: job.out.clone(),
        force: job.force,
        noise,
    };
    let r = study::study(&cfg, &options, progress)?;
    println!(
        "| descriptor | worst parameter error | steps | re-simulated, max vertex error (m) | discrimination: positive of |"
    );
    println!("|---|---|---|---|---|");
    for f in &r.fits {
        let worst = crate::xpbd::material::NAMES
            .iter()
            .map(|n| f.relative_error[*n])
            .fold(0.0, f64::max);
        let [p, n] = r.positive[f.descriptor.name()];
        println!(
            "| {} | {:.2e} | {} | {:.3e} | {p} of {n} |",
            f.descriptor.name(),
            worst,
            f.relative_error["iterations"],
            f.max_vertex_error
        );
    }
    for s in &r.discrimination {
        let branches: Vec<String> = s
            .materials
            .iter()
            .zip(&s.branch_distance)
            .map(|(m, d)| format!("{m} {:.2} mm", 1e3 * d))
            .collect();
        println!(
            "{}: the two branches differ by {}",
            s.scenario,
            branches.join(", ")
        );
    }
    println!(
        "descriptors: {}",
        job.out.join("descriptors.json").display()
    );
    Ok(())
}

/// `springtime xpbd resim`: the re-simulation error per scenario.
fn xpbd_resim(job: &XpbdJob, estimate: &Path, progress: &Progress) -> Result<()> {
    use crate::xpbd::material::Gamma;
    let cfg = job.load()?;
    let text = std::fs::read_to_string(estimate)
        .with_context(|| format!("cannot read {}", estimate.display()))?;
    let json: serde_json::Value = serde_json::from_str(&text)
        .with_context(|| format!("{} is not JSON", estimate.display()))?;
    let gamma: Gamma = serde_json::from_value(json["gamma"].clone())
        .with_context(|| format!("{}: key `gamma` is not a γ", estimate.display()))?;
    let r = crate::xpbd::estimate::resim(&cfg, gamma, &job.out, job.force, progress)?;
    for s in &r.scenarios {
        println!(
            "{:<24} max vertex error {:.4} mm",
            s.name,
            1e3 * s.max_vertex_error
        );
    }
    println!("resim: {}", job.out.join("resim.json").display());
    Ok(())
}

/// `springtime xpbd invariance`: the fits over the seeds, then each descriptor's spread.
fn xpbd_invariance(
    job: &XpbdJob,
    seeds: u64,
    noise: f64,
    start: crate::xpbd::estimate::FitStart,
    progress: &Progress,
) -> Result<()> {
    use crate::xpbd::{material::NAMES, study};
    let cfg = job.load()?;
    let options = study::StudyOptions {
        out: job.out.clone(),
        force: job.force,
        noise,
    };
    let r = study::invariance(&cfg, &options, seeds, start, progress)?;
    println!(
        "| descriptor | coefficient of variation over {seeds} seeds: C00, C11, C01, C22, b | mean relative error: C00, C11, C01, C22, b |"
    );
    println!("|---|---|---|");
    for (name, s) in &r.summary {
        let row = |m: &std::collections::BTreeMap<String, f64>| {
            NAMES
                .iter()
                .map(|k| format!("{:.2}%", 100.0 * m[*k]))
                .collect::<Vec<_>>()
                .join(", ")
        };
        println!(
            "| {name} | {} | {} |",
            row(&s.cv),
            row(&s.mean_relative_error)
        );
    }
    println!("invariance: {}", job.out.join("invariance.json").display());
    Ok(())
}

/// `springtime data check`.
fn data_check(dir: &Path, config: Option<&Path>, set: &[String]) -> Result<()> {
    let cfg = match config {
        Some(path) => Config::load(path, set)?,
        None => Config::parse("", set)?,
    };
    print!("{}", crate::check::check_dir(dir, &cfg)?.render());
    Ok(())
}

/// `springtime train`, then (unless asked not to) `eval` and `report` of the new run.
fn train_command(
    config: &Path,
    backend: Option<Backend>,
    options: TrainOptions,
    evaluate: bool,
    with_report: bool,
    set: &[String],
    progress: &Progress,
) -> Result<()> {
    let mut cfg = Config::load(config, set)?;
    if let Some(b) = backend {
        cfg.backend = b;
    }
    let summary = train::train(&cfg, &options, progress)?;
    println!(
        "trained {} iterations in {:.1} s (peak memory {:.0} MiB){}",
        summary.iterations,
        summary.wall_seconds,
        summary.peak_rss_mib,
        match (summary.rmse_k, summary.rmse_b) {
            (Some(k), Some(b)) => format!(": rmse_k {k:.4} N/m, rmse_b {b:.4} N·s/m"),
            _ => String::new(),
        }
    );
    println!("run: {}", summary.run_dir.display());
    // A finished training is a success: without test rollouts the evaluation is skipped with a
    // note that says how to run it, rather than failing the command.
    let has_test = !cfg.data.split()?.test.is_empty();
    if evaluate && !has_test {
        progress.note(&format!(
            "note: no test rollouts (the data's index lists none and `data.test_dir` is not \
             set): the run is trained but not evaluated; evaluate it with `springtime eval {} \
             --data DIR` on takes it was not trained on",
            summary.run_dir.display()
        ));
    } else if evaluate {
        let report = crate::run::evaluate(&summary.run_dir, None, None, &[], progress)?;
        print_eval(&report);
    }
    if with_report && cfg.model.kind == crate::model::ModelKind::Springs {
        report(&summary.run_dir, None, None, progress)
            .context("training finished, but its report failed")?;
    }
    Ok(())
}

/// A command's notes, on standard error.
fn print_notes(notes: &[String]) {
    for note in notes {
        eprintln!("note: {note}");
    }
}

/// `springtime diagnose`.
fn diagnose(
    run_dir: &Path,
    options: &crate::diagnose::DiagnoseOptions,
    progress: &Progress,
) -> Result<()> {
    let s = crate::diagnose::diagnose(run_dir, options, progress)?;
    print_notes(&s.notes);
    print!("{}", s.table);
    println!("diagnosis: {}", s.dir.display());
    Ok(())
}

/// `springtime compare`: the table printed with the configured horizons.
fn compare(
    config: &Path,
    set: &[String],
    options: &crate::compare::CompareOptions,
    progress: &Progress,
) -> Result<()> {
    let cfg = Config::load(config, set)?;
    let c = crate::compare::compare(&cfg, options, progress)?;
    let (short, long) = (cfg.eval.short_seconds, cfg.eval.long_seconds);
    println!(
        "{:<16} {:>22} {:>22} {:>12} {:>10} {:>14}",
        "model",
        format!("RMSE ≤ {short} s (m)"),
        format!("RMSE ≤ {long} s (m)"),
        "train (s)",
        "params",
        "µs/step"
    );
    for r in &c.rows {
        let m = &r.eval.motion_rmse;
        println!(
            "{:<16} {:>10.3e} ± {:<9.2e} {:>10.3e} ± {:<9.2e} {:>12.1} {:>10} {:>14.1}",
            r.kind.name(),
            m.short.mean,
            m.short.std,
            m.long.mean,
            m.long.std,
            r.train_seconds,
            r.parameters,
            r.eval
                .inference
                .as_ref()
                .map_or(f64::NAN, |i| i.us_per_step)
        );
    }
    println!("comparison: {}", c.files[0].display());
    Ok(())
}

fn report(
    run_dir: &Path,
    data: Option<PathBuf>,
    backend: Option<Backend>,
    progress: &Progress,
) -> Result<()> {
    let options = crate::report::ReportOptions { data, backend };
    let summary = crate::report::build(run_dir, &options, progress)?;
    print_notes(&summary.notes);
    println!("report: {}", summary.html.display());
    Ok(())
}

fn export(
    run_dir: &Path,
    options: &crate::export::ExportOptions,
    progress: &Progress,
) -> Result<()> {
    let s = crate::export::export_run(run_dir, options, progress)?;
    if options.format == crate::export::Format::Web {
        println!(
            "wrote {} files to {}: open {} in a browser (offline; the pins of {})",
            s.files.len(),
            options.out.display(),
            options.out.join("index.html").display(),
            s.rollout
                .as_ref()
                .map_or("no rollout: none pinned".into(), |r| r
                    .display()
                    .to_string())
        );
        return Ok(());
    }
    if let Some(note) = &s.note {
        eprintln!("note: no rollout exported: {note}; pass --init <rollout.npz>");
    }
    match &s.rollout {
        Some(r) => println!(
            "wrote {} files to {}: rest mesh, {} frames at {:.1} fps simulated from {}, surrogate.json, surrogate.npz",
            s.files.len(),
            options.out.display(),
            s.frames,
            s.fps,
            r.display()
        ),
        None => println!(
            "wrote {} files to {}: rest mesh, surrogate.json, surrogate.npz",
            s.files.len(),
            options.out.display()
        ),
    }
    Ok(())
}

fn generate(
    config: &Path,
    shard: Option<crate::source::Shard>,
    set: &[String],
    progress: &Progress,
) -> Result<()> {
    let cfg = Config::load(config, set)?;
    let Some(source) = &cfg.source else {
        bail!(
            "{} has no [source] section: nothing to generate",
            config.display()
        );
    };
    let start = Instant::now();
    let shard = shard.unwrap_or(crate::source::Shard::WHOLE);
    let total = source.train_rollouts + source.test_rollouts;
    let owned = (0..total).filter(|&j| shard.owns(j)).count();
    let bar = progress.bar(owned as u64, "generate");
    let g = crate::source::generate(source, &cfg.data.clips, &cfg.data.dir, shard, |n| {
        bar.set_position(n as u64)
    })?;
    bar.finish();
    let seconds = start.elapsed().as_secs_f64();
    match &g.index {
        Some(index) if shard == crate::source::Shard::WHOLE => println!(
            "wrote {} train and {} test rollouts to {} in {seconds:.1} s",
            index.train.len(),
            index.test.len(),
            cfg.data.dir.display(),
        ),
        Some(_) => println!(
            "shard {}/{}: {} of {} rollouts in {} in {seconds:.1} s; the set is complete and \
             index.json written",
            shard.index,
            shard.count,
            g.owned,
            g.total,
            cfg.data.dir.display()
        ),
        None => println!(
            "shard {}/{}: {} of {} rollouts in {} in {seconds:.1} s; {} rollouts of other shards \
             are missing, so index.json waits for them (the shard that completes the set writes \
             it; `springtime generate` without --shard completes a set and writes it too)",
            shard.index,
            shard.count,
            g.owned,
            g.total,
            cfg.data.dir.display(),
            g.missing
        ),
    }
    Ok(())
}

/// `springtime sweep`.
fn sweep(
    plan: &Path,
    list: bool,
    index: Option<&str>,
    gather: bool,
    out: Option<PathBuf>,
    progress: &Progress,
) -> Result<()> {
    let plan = crate::sweep::Plan::load(plan)?;
    let out = out.unwrap_or_else(|| crate::sweep::default_out(&plan));
    if list {
        return sweep_list(&plan);
    }
    if let Some(spec) = index {
        return sweep_run(&plan, spec, &out, progress);
    }
    debug_assert!(gather);
    sweep_gather(&plan, &out)
}

/// `sweep --list`: each job's index, folder name and overrides.
fn sweep_list(plan: &crate::sweep::Plan) -> Result<()> {
    for job in plan.jobs()? {
        println!(
            "{}\t{}\t{}",
            job.index,
            job.dir_name,
            job.overrides.join(" ")
        );
    }
    Ok(())
}

/// `sweep --index SPEC`: the jobs run in turn; fails after the last naming those that failed.
fn sweep_run(plan: &crate::sweep::Plan, spec: &str, out: &Path, progress: &Progress) -> Result<()> {
    use crate::sweep::Outcome;
    let indices = parse_indices(spec, plan.len())?;
    let mut failed = Vec::new();
    for i in indices {
        match crate::sweep::run_index(plan, i, out, progress) {
            Ok(Outcome::Skipped(dir)) => {
                println!("job {i}: already finished in {}", dir.display())
            }
            Ok(Outcome::Finished(r)) => println!(
                "job {i}: finished in {:.1} s{}",
                r.seconds,
                if r.resumed { " (resumed)" } else { "" }
            ),
            Err(e) => {
                eprintln!("error: {e:#}");
                failed.push(i);
            }
        }
    }
    if !failed.is_empty() {
        bail!(
            "{} job(s) failed: {}",
            failed.len(),
            failed
                .iter()
                .map(|i| i.to_string())
                .collect::<Vec<_>>()
                .join(", ")
        );
    }
    Ok(())
}

/// `sweep --gather`: the jobs counted by status and the gathered files listed.
fn sweep_gather(plan: &crate::sweep::Plan, out: &Path) -> Result<()> {
    use crate::sweep::JobStatus;
    let g = crate::sweep::gather(plan, out)?;
    let count = |s| g.table.indices(s);
    let listed = |ids: Vec<usize>| {
        ids.iter()
            .map(|i| i.to_string())
            .collect::<Vec<_>>()
            .join(", ")
    };
    println!(
        "{} jobs: {} finished, {} failed, {} unfinished, {} missing",
        plan.len(),
        count(JobStatus::Finished).len(),
        count(JobStatus::Failed).len(),
        count(JobStatus::Unfinished).len(),
        count(JobStatus::Missing).len()
    );
    for status in [JobStatus::Failed, JobStatus::Unfinished, JobStatus::Missing] {
        let ids = count(status);
        if !ids.is_empty() {
            println!("{}: {}", status.name(), listed(ids));
        }
    }
    for f in &g.files {
        println!("wrote {}", f.display());
    }
    Ok(())
}

/// `--index`: `I`, or a comma list of indices and ranges `A-B` (inclusive), all below `n`.
fn parse_indices(spec: &str, n: usize) -> Result<Vec<usize>> {
    let mut out = Vec::new();
    for part in spec.split(',').map(str::trim) {
        let parse = |s: &str| -> Result<usize> {
            s.trim()
                .parse()
                .map_err(|_| anyhow::anyhow!("--index {spec:?}: {s:?} is not an index"))
        };
        let (a, b) = match part.split_once('-') {
            Some((a, b)) => (parse(a)?, parse(b)?),
            None => (parse(part)?, parse(part)?),
        };
        if a > b || b >= n {
            bail!(
                "--index {spec:?}: {part} is not within the plan's {n} jobs (0 to {})",
                n.saturating_sub(1)
            );
        }
        out.extend(a..=b);
    }
    Ok(out)
}

/// A yardstick's test figures and the trained network's gains over it, for `eval`'s lines.
fn against_yardstick(
    test: &eval::MotionRmse,
    improvement_long: f64,
    improvement_short: f64,
) -> String {
    format!(
        "test motion RMSE {:.4e} m (short horizon {:.4e}, long {:.4e}); training improves on it \
         by {:.1} % (long) and {:.1} % (short)",
        test.mean,
        test.short.mean,
        test.long.mean,
        100.0 * improvement_long,
        100.0 * improvement_short
    )
}

fn print_eval(r: &EvalReport) {
    let m = &r.motion_rmse;
    if let (Some(k), Some(b)) = (r.rmse_k, r.rmse_b) {
        println!("rmse_k {k:.4} N/m, rmse_b {b:.4} N·s/m");
    }
    if let Some(c) = r.stiffness_map_corr {
        println!(
            "stiffness map: Spearman correlation {c:.4} (structural springs vs the source's triangles)"
        );
    }
    if let Some(c) = r.learned_map_corr {
        println!(
            "stiffness map of the learned springs the run set aside for the uniform network \
             (springs.learned.npz): Spearman correlation {c:.4}"
        );
    }
    println!(
        "motion RMSE over {} test rollouts: {:.4e} ± {:.4e} m (≤ {} s: {:.4e} ± {:.4e}; ≤ {} s: {:.4e} ± {:.4e})",
        m.rollouts,
        m.mean,
        m.std,
        m.short.seconds,
        m.short.mean,
        m.short.std,
        m.long.seconds,
        m.long.mean,
        m.long.std
    );
    if r.precision != "f32" {
        println!("(simulated in {})", r.precision);
    }
    if let Some(u) = &r.uniform_baseline {
        println!(
            "best uniform network: k {:.4} N/m, b {:.4e} N·s/m (searched on {} training rollouts): {}",
            u.k,
            u.b,
            u.search_rollouts,
            against_yardstick(&u.test, u.improvement_long, u.improvement_short)
        );
        if let Some(t) = &u.bending_apart {
            println!(
                "best bending-apart network (uniform, the bending springs' k × {:.4} of the \
                 others'): k {:.4} N/m, b {:.4e} N·s/m: {}",
                t.bending_factor,
                t.k,
                t.b,
                against_yardstick(&t.test, t.improvement_long, t.improvement_short)
            );
        }
        if let Some(o) = &u.own_damping {
            println!(
                "best uniform network with its own damping ({}: drag {:.4e} N·s/m, viscosity \
                 {:.3e} s · k): k {:.4} N/m, b {:.4e} N·s/m, {:.4e} m on the training rollouts \
                 against the uniform network's {:.4e} m: {}",
                o.found_by,
                o.rayleigh,
                o.viscosity,
                o.k,
                o.b,
                o.train_rmse,
                o.yardstick_train_rmse,
                against_yardstick(&o.test, o.improvement_long, o.improvement_short)
            );
        }
    }
    if let Some(v) = &r.validation {
        println!("validation (`data.holdout`): {}", v.summary());
    }
    if let Some(i) = &r.inference {
        println!(
            "inference: {:.1} µs per rollout·step of {} ms (batch {}), {:.3} s per simulated second",
            i.us_per_step,
            i.step_dt * 1e3,
            i.batch,
            i.seconds_per_second
        );
    }
}

/// What `springtime simulate` does: where it starts, for how long, into which file.
struct SimulateJob<'a> {
    /// The rollout file (`--init`).
    init: Option<&'a Path>,
    /// `--rest`.
    rest: bool,
    /// `--seconds`.
    seconds: f64,
    /// `--out`.
    out: &'a Path,
    /// `--force`.
    force: bool,
}

fn simulate(
    run_dir: &Path,
    job: SimulateJob,
    backend: Option<Backend>,
    set: &[String],
    progress: &Progress,
) -> Result<()> {
    let SimulateJob {
        init,
        rest,
        seconds,
        out,
        force,
    } = job;
    crate::io::refuse_overwrite(out, force)?;
    if !(seconds > 0.0 && seconds.is_finite()) {
        bail!("--seconds must be positive, is {seconds}");
    }
    let run = crate::run::Run::open(run_dir, set, backend)?;
    let (model, topo, config) = (run.springs()?, &run.topology, &run.config);
    let start = SimulateStart::new(&run, init, rest)?;
    let physics = &start.physics;
    physics
        .stability_of(topo, model)
        .check("the trained surrogate", config.sim.allow_unstable)?;
    let frames = (seconds / physics.frame_dt).round() as usize;
    let bar = progress.bar(frames as u64, "simulate");
    let sim = eval::FreeRun::new(&start.track, start.first, frames).simulate(
        model,
        physics,
        &run.device,
        |_| bar.inc(1),
    )?;
    bar.finish();
    start.rollout(topo, model, sim, frames, out).save(out)?;
    println!(
        "wrote {} frames ({seconds} s) to {}",
        frames + 1,
        out.display()
    );
    Ok(())
}

/// Where `springtime simulate` starts: the track that holds the pins, its first frame and the
/// physics.
struct SimulateStart {
    /// The pinned particles' path (at rest, or the `--init` rollout's).
    track: Track,
    /// The track's first usable frame.
    first: usize,
    /// The simulation's physics.
    physics: crate::sim::Physics,
}

impl SimulateStart {
    /// From the surrogate's rest state (`--rest`) or from the first usable frame of `init`.
    fn new(run: &crate::run::Run, init: Option<&Path>, rest: bool) -> Result<Self> {
        let topo = &run.topology;
        if rest {
            let rest = crate::export::rest_start(run, init, None)?;
            let mut track = Track::at_rest(&topo.rest_positions());
            for &i in &rest.pinned {
                track.pinned[i] = true;
            }
            Ok(Self {
                track,
                first: 0,
                physics: rest.physics,
            })
        } else {
            let init = init.expect("clap requires --init without --rest");
            let rollout = Rollout::load(init)?;
            let res = Resampler::new(&rollout.rest_uv, &topo.rest_uv);
            let first = rollout.first_state_frame();
            Ok(Self {
                track: Track::new(&rollout, &res),
                first,
                physics: run.physics(rollout.frame_dt),
            })
        }
    }

    /// The simulated `frames` (after the start) as a rollout file's contents, with the
    /// surrogate's springs as its truth.
    fn rollout(
        &self,
        topo: &crate::cloth::Topology,
        model: &crate::model::SpringNet,
        sim: eval::FreeRollout,
        frames: usize,
        out: &Path,
    ) -> Rollout {
        let physics = &self.physics;
        let p = topo.num_particles();
        Rollout {
            path: out.to_path_buf(),
            frames: frames + 1,
            landmarks: p,
            positions: sim.positions,
            velocities: Some(sim.velocities),
            rest_uv: topo.rest_uv.clone(),
            pinned: self.track.pinned.clone(),
            frame_dt: physics.frame_dt,
            total_mass: physics.mass * p as f64,
            width: topo.width,
            height: topo.height,
            segments: vec![Segment {
                start: 0,
                offset: 0,
                len: frames + 1,
            }],
            springs: Some(SpringTruth {
                springs: topo.springs.clone(),
                k: model.k_values(),
                b: model.b_values(),
            }),
            mesh: None,
            gravity: Some(physics.gravity),
            rayleigh: Some(physics.rayleigh),
            position_noise: None,
            visible: None,
        }
    }
}

/// `springtime drape`: drapes the runs over the scenes and prints each model's figures.
fn drape(options: &crate::drape::DrapeOptions, progress: &Progress) -> Result<()> {
    let report = crate::drape::run(options, progress)?;
    println!(
        "{:<10} {:<22} {:>13} {:>13} {:>13} {:>11} {:>8} {:>9}",
        "scene",
        "system",
        "RMSE end (m)",
        "rest-src (m)",
        "rest-fine (m)",
        "deepest (m)",
        "settled",
        "diverged"
    );
    for (name, s) in &report.scenes {
        print_drape_scene(name, s);
    }
    println!("drape: {}", options.out.join("drape.json").display());
    Ok(())
}

/// One scene's rows of the `drape` table (the source's, the perturbed source's, each model's,
/// and those relaxed from another's drape), then its warnings.
fn print_drape_scene(name: &str, s: &crate::drape::SceneResult) {
    for r in [&s.source, &s.perturbed].into_iter().flatten() {
        DrapeRow {
            scene: name,
            system: &r.label,
            end: None,
            vs_source: r.steady_rmse_vs_source,
            vs_fine: r.steady_rmse_vs_fine,
            deepest: Some(r.max_penetration),
            settled: &r.settled.to_string(),
            diverged: &r.diverged.to_string(),
        }
        .print();
        if let Some(x) = &r.relaxed_from_fine {
            DrapeRow::relaxed(name, &format!("{} from fine", r.label), x);
        }
    }
    for (kind, m) in &s.models {
        let (settled, diverged) = if m.applicable {
            (m.settled.to_string(), m.diverged.to_string())
        } else {
            ("n/a".into(), "n/a".into())
        };
        DrapeRow {
            scene: name,
            system: kind,
            end: m.motion_rmse_end,
            vs_source: m.steady_rmse_vs_source,
            vs_fine: m.steady_rmse_vs_fine,
            deepest: m.max_penetration,
            settled: &settled,
            diverged: &diverged,
        }
        .print();
        for (from, r) in [
            ("source", &m.relaxed_from_source),
            ("fine", &m.relaxed_from_fine),
        ] {
            if let Some(r) = r {
                DrapeRow::relaxed(name, &format!("{kind} from {from}"), r);
            }
        }
    }
    for w in &s.warnings {
        eprintln!("warning: {name}: {w}");
    }
}

/// A row of the `drape` table: a system's distances in a scene (`—` where it has none).
struct DrapeRow<'a> {
    /// The scene's name.
    scene: &'a str,
    /// The system's label.
    system: &'a str,
    /// The motion RMSE at the end (m).
    end: Option<f64>,
    /// The steady RMSE against the source (m).
    vs_source: Option<f64>,
    /// The steady RMSE against the fine reference (m).
    vs_fine: Option<f64>,
    /// The deepest penetration (m).
    deepest: Option<f64>,
    /// Whether it settled.
    settled: &'a str,
    /// Whether it diverged.
    diverged: &'a str,
}

impl DrapeRow<'_> {
    /// A system started from another's settled drape: its distances at rest.
    fn relaxed(scene: &str, system: &str, r: &crate::drape::Relaxed) {
        DrapeRow {
            scene,
            system,
            end: None,
            vs_source: r.steady_rmse_vs_source,
            vs_fine: r.steady_rmse_vs_fine,
            deepest: None,
            settled: &r.settled.to_string(),
            diverged: &r.diverged.to_string(),
        }
        .print()
    }

    fn print(&self) {
        let show = |v: Option<f64>| v.map_or("—".to_string(), |v| format!("{v:.4}"));
        println!(
            "{:<10} {:<22} {:>13} {:>13} {:>13} {:>11} {:>8} {:>9}",
            self.scene,
            self.system,
            show(self.end),
            show(self.vs_source),
            show(self.vs_fine),
            show(self.deepest),
            self.settled,
            self.diverged
        );
    }
}

fn fold(
    config: &Path,
    out: PathBuf,
    force: bool,
    set: &[String],
    progress: &Progress,
) -> Result<()> {
    let cfg = crate::fold::FoldConfig::load(config, set)?;
    let report = crate::fold::run(
        &cfg,
        &crate::fold::FoldOptions {
            out: out.clone(),
            force,
        },
        progress,
    )?;
    println!(
        "{:<20} {:<11} {:>9} {:>9} {:>12} {:>16} {:>9}",
        "system", "case", "α (°)", "sag (m)", "RMSE fine", "RMSE fine k_b=0", "membrane"
    );
    for r in &report.results {
        println!(
            "{:<20} {:<11} {:>9.2} {:>9.4} {:>12.4} {:>16.4} {:>9}",
            r.system,
            r.case.name(),
            r.alpha_deg,
            r.sag_m,
            r.rmse_fine_m,
            r.rmse_fine_no_bending_m,
            r.membrane_share.map_or("-".into(), |m| format!("{m:.3}"))
        );
    }
    for (system, gap) in &report.locking_gap_deg {
        println!("Δα {system:<20} {gap:>8.2}°");
    }
    for (name, c) in &report.criteria {
        println!(
            "{name} {:<4} value {:>10.4}  threshold {:>10.4}  ({})",
            if c.pass { "PASS" } else { "FAIL" },
            c.value,
            c.threshold,
            c.rule
        );
    }
    println!(
        "wall time {:.0} s; wrote {}",
        report.wall_seconds,
        out.join("fold.json").display()
    );
    Ok(())
}

/// `--version`: the version and the git commit of the build.
fn long_version() -> &'static str {
    static TEXT: std::sync::OnceLock<String> = std::sync::OnceLock::new();
    TEXT.get_or_init(|| {
        let build = crate::BuildInfo::current();
        format!("{} (commit {})", build.version, build.commit)
    })
}
