//! Shared fixtures: tiny spring cloths simulated in memory, and temporary directories.
#![allow(dead_code)]

pub mod finite_difference;

use burn::tensor::Device;
use rand::{Rng, SeedableRng, rngs::StdRng};
use springtime::cloth::{GridSpec, Resampler, Topology};
use springtime::data::{ClipBatch, Rollout, Track};
use springtime::model::{Kernel, SpringNet, springs::to_f64};
use springtime::source::{Layout, Scenario, SourceConfig, SpringCloth, simulate_rollout};
use springtime::train::LossValues;

/// A small source: `n × n` landmarks 0.5 m apart, stiffness stripes `levels`, b = 6.
pub fn source(n: usize, levels: &[f64], seconds: f64) -> SourceConfig {
    SourceConfig {
        nx: n,
        ny: n,
        width: 0.5 * (n - 1) as f64,
        height: 0.5 * (n - 1) as f64,
        stiffness_levels: levels.to_vec(),
        layout: Layout::Stripes,
        seconds,
        train_rollouts: 4,
        test_rollouts: 1,
        ..SourceConfig::default()
    }
}

/// The surrogate grid matching a source (every spring family).
pub fn grid_of(cfg: &SourceConfig) -> Topology {
    let spec = GridSpec {
        nx: cfg.nx,
        ny: cfg.ny,
        ..GridSpec::default()
    };
    Topology::grid(&spec, cfg.width, cfg.height)
}

/// One rollout of the source, simulated in memory.
pub fn rollout(cfg: &SourceConfig, seed: u64) -> (SpringCloth, Rollout) {
    let cloth = SpringCloth::from_config(cfg);
    let scenario = Scenario::random(
        &cloth.topology.rest_uv,
        cfg.anchor_radius,
        &mut StdRng::seed_from_u64(seed),
    );
    let r = simulate_rollout(&cloth, cfg, &scenario, None, "memory").expect("stable source");
    (cloth, r)
}

/// A batch of `steps`-step clips starting at stored frame `offset` of each rollout.
pub fn batch(
    cfg: &SourceConfig,
    rollouts: &[Rollout],
    offset: usize,
    steps: usize,
    device: &Device,
) -> ClipBatch {
    let topo = grid_of(cfg);
    let tracks: Vec<Track> = rollouts
        .iter()
        .map(|r| Track::new(r, &Resampler::new(&r.rest_uv, &topo.rest_uv)))
        .collect();
    let views: Vec<(&Track, usize)> = tracks.iter().map(|t| (t, offset)).collect();
    let mass = rollouts[0].total_mass / topo.num_particles() as f64;
    ClipBatch::new(&views, steps, mass, rollouts[0].frame_dt, device).unwrap()
}

/// The drive of a free rollout over every clip of `batch`: its first frame's positions and
/// velocities, the pinned particles following the clip's path.
pub fn clip_drive(batch: &ClipBatch) -> springtime::sim::Drive {
    let [bsz, _, p, _] = batch.positions.dims();
    springtime::sim::Drive {
        x0: batch
            .positions
            .clone()
            .slice([0..bsz, 0..1, 0..p, 0..3])
            .reshape([bsz, p, 3]),
        v0: batch
            .velocities
            .clone()
            .slice([0..bsz, 0..1, 0..p, 0..3])
            .reshape([bsz, p, 3]),
        pinned: batch.pinned.clone(),
        path: batch.positions.clone(),
    }
}

/// `model` simulated freely over the first `frames` frames of `track` (with `contact` where
/// given), pinned particles following the track: the positions of its last frame, `[P × 3]`.
pub fn last_frame(
    model: &dyn springtime::model::ForceModel,
    physics: &springtime::sim::Physics,
    contact: Option<&springtime::sim::Contact>,
    track: &Track,
    frames: usize,
    device: &Device,
) -> Vec<f32> {
    springtime::eval::FreeRun::new(track, 0, frames)
        .keeping(&[frames])
        .contact(contact)
        .simulate(model, physics, device, |_| {})
        .unwrap()
        .positions
}

/// A fresh, empty, uniquely named temporary directory for one test, removed when the test ends
/// (passing or panicking); set `SPRINGTIME_KEEP_TEST_DIRS=1` to keep it for inspection.
pub fn temp_dir(name: &str) -> TestDir {
    let keep = std::env::var_os("SPRINGTIME_KEEP_TEST_DIRS").is_some();
    TestDir(
        tempfile::Builder::new()
            .prefix(&format!("springtime-test-{name}-"))
            .disable_cleanup(keep)
            .tempdir()
            .expect("a temporary directory"),
    )
}

/// A test's scratch directory (see [`temp_dir`]); usable wherever a `Path` is.
pub struct TestDir(tempfile::TempDir);

impl std::ops::Deref for TestDir {
    type Target = std::path::Path;
    fn deref(&self) -> &std::path::Path {
        self.0.path()
    }
}

impl AsRef<std::path::Path> for TestDir {
    fn as_ref(&self) -> &std::path::Path {
        self.0.path()
    }
}

/// Runs the `springtime` binary in `cwd`.
pub fn springtime(args: &[&str], cwd: &std::path::Path) -> std::process::Output {
    std::process::Command::new(env!("CARGO_BIN_EXE_springtime"))
        .args(args)
        .current_dir(cwd)
        .output()
        .unwrap()
}

/// Runs `springtime import <format> <input> --out <out> --frame-dt <frame_dt> --mass <mass>`,
/// then `extra`, in `cwd`: `what` is `[format, input, out]`, `step_and_mass` `[frame_dt, mass]`.
pub fn import(
    what: [&str; 3],
    step_and_mass: [&str; 2],
    extra: &[&str],
    cwd: &std::path::Path,
) -> std::process::Output {
    let ([format, input, out], [frame_dt, mass]) = (what, step_and_mass);
    let mut args = vec![
        "import",
        format,
        input,
        "--out",
        out,
        "--frame-dt",
        frame_dt,
        "--mass",
        mass,
    ];
    args.extend_from_slice(extra);
    springtime(&args, cwd)
}

/// Asserts that a command succeeded; its stdout and stderr.
pub fn ok(out: &std::process::Output) -> String {
    let stderr = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(out.status.success(), "command failed: {stderr}");
    String::from_utf8_lossy(&out.stdout).into_owned() + &stderr
}

/// Asserts that a command failed with an error (not a panic) mentioning every needle.
pub fn fails(out: &std::process::Output, needles: &[&str]) {
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success(),
        "expected a failure, got success: {stderr}"
    );
    assert!(
        !stderr.contains("panicked"),
        "a panic instead of an error: {stderr}"
    );
    for n in needles {
        assert!(stderr.contains(n), "error does not mention {n:?}: {stderr}");
    }
}

/// The wgpu device when this build has it and the machine has an adapter (CI: Mesa's software
/// Vulkan); `None` otherwise, unless `SPRINGTIME_REQUIRE_WGPU` is set, which makes a missing
/// adapter a failure.
pub fn wgpu() -> Option<Device> {
    #[cfg(feature = "wgpu")]
    {
        let device = Device::wgpu(burn::tensor::DeviceKind::DefaultDevice);
        let usable = std::panic::catch_unwind(|| {
            burn::tensor::Tensor::<1>::from_floats([1.0, 2.0], &device)
                .sum()
                .into_scalar::<f32>()
        });
        if usable.is_ok() {
            return Some(device);
        }
    }
    assert!(
        std::env::var_os("SPRINGTIME_REQUIRE_WGPU").is_none(),
        "no wgpu adapter, and SPRINGTIME_REQUIRE_WGPU is set"
    );
    eprintln!("skipping wgpu: no adapter on this machine (or a build without `wgpu`)");
    None
}

/// Asserts that `b` equals `a` within `rel` of `a`'s largest magnitude, which must not be zero
/// (a comparison of zeros cannot fail).
pub fn assert_close(name: &str, a: &[f64], b: &[f64], rel: f64) {
    assert_eq!(a.len(), b.len(), "{name}: lengths");
    // `f64::max` passes a NaN over: refuse non-finite values first.
    assert!(
        a.iter().chain(b).all(|x| x.is_finite()),
        "{name}: a value is not finite"
    );
    let scale = a.iter().fold(0.0f64, |m, x| m.max(x.abs()));
    let worst = a
        .iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f64::max);
    assert!(scale > 0.0, "{name} is all zero");
    assert!(
        worst <= rel * scale,
        "{name}: largest difference {worst:e} against a scale of {scale:e}"
    );
}

/// The paper's grid of a source, and the same particles as a data mesh: its cells' two
/// triangles, hinge springs and lumped (unequal) masses.
pub fn grid_and_mesh(cfg: &SourceConfig) -> [Topology; 2] {
    let grid = grid_of(cfg);
    let mesh = Topology::mesh(
        &grid.rest_uv,
        &grid.triangles,
        grid.width,
        grid.height,
        true,
    )
    .unwrap();
    assert!(mesh.force_scale().is_some());
    [grid, mesh]
}

/// Asserts that the loss terms `b` equal `a`'s, which must be positive: force and impulse
/// within 1e-5 relative, the position loss within 1e-4 (it squares differences of millimetres
/// between positions of metres, so f32 rounding shows at 1e-5).
pub fn assert_losses_close(name: &str, a: &LossValues, b: &LossValues) {
    for (term, x, y, tol) in [
        ("force", a.force, b.force, 1e-5),
        ("impulse", a.impulse, b.impulse, 1e-5),
        ("position", a.position, b.position, 1e-4),
    ] {
        assert!(
            x > 0.0 && (x - y).abs() <= tol * x,
            "{name}: {term} loss {x} vs {y}"
        );
    }
}

/// A training loss of the spring surrogate: 90-step clips from stored frame 150 of `rollouts`
/// of the source `cfg`, simulated on `topo` with `substeps`, the springs' isotropic `viscosity`
/// (`sim.viscosity`, s) and a state budget of `budget` MiB.
pub struct LossCase<'a> {
    pub cfg: &'a SourceConfig,
    pub topo: &'a Topology,
    pub rollouts: &'a [Rollout],
    pub substeps: usize,
    pub viscosity: f64,
    pub shear_compression: f64,
    pub budget: usize,
}

impl LossCase<'_> {
    /// The loss terms (force, impulse and position weighted in) and their gradients with
    /// respect to `k` and `b`, on `device` (made an autodiff device here), with `kernel`. The
    /// network's `k` and `b` are fixed smooth patterns, so every spring's gradient differs.
    pub fn evaluate(&self, kernel: Kernel, device: &Device) -> (LossValues, Vec<f64>, Vec<f64>) {
        use springtime::sim::Physics;
        use springtime::train::{ForceOn, LossWeights, loss_with_budget};
        let s = self.topo.num_springs();
        let k: Vec<f64> = (0..s)
            .map(|i| 40.0 + 25.0 * ((i as f64) * 0.37).sin())
            .collect();
        let b: Vec<f64> = (0..s).map(|i| 4.0 + ((i as f64) * 0.91).cos()).collect();
        let weights = LossWeights {
            force: 1.0,
            impulse: 10.0,
            position: 30.0,
            k_neg: 1.0,
            b_neg: 1.0,
        };
        let device = device.clone().autodiff();
        let batch = batch(self.cfg, self.rollouts, 150, 90, &device);
        let physics = Physics {
            frame_dt: self.rollouts[0].frame_dt,
            substeps: self.substeps,
            mass: self.rollouts[0].total_mass / self.topo.num_particles() as f64,
            rayleigh: self.cfg.rayleigh,
            gravity: self.cfg.gravity,
            viscosity: self.viscosity,
            shear_compression: self.shear_compression,
        };
        let model = SpringNet::new(self.topo, &k, &b, &device).with_kernel(kernel);
        let terms = loss_with_budget(
            &model,
            &physics,
            &batch,
            &weights,
            ForceOn::Simulated,
            self.budget,
        );
        let values = terms.values();
        let grads = terms.total.backward();
        (
            values,
            to_f64(model.k.val().grad(&grads).unwrap()),
            to_f64(model.b.val().grad(&grads).unwrap()),
        )
    }
}

/// `n × n` points over a `(n − 1)·0.5 m` square, interior points jittered by up to a quarter of
/// the spacing (the border stays straight, as a cut sheet's does).
pub fn jittered_points(n: usize, seed: u64) -> Vec<[f64; 2]> {
    let mut rng = StdRng::seed_from_u64(seed);
    let h = 0.5;
    let mut uv = Vec::new();
    for r in 0..n {
        for c in 0..n {
            let inner = |i: usize| i > 0 && i < n - 1;
            let (mut u, mut v) = (c as f64 * h, r as f64 * h);
            if inner(r) && inner(c) {
                u += rng.random_range(-0.25..0.25) * h;
                v += rng.random_range(-0.25..0.25) * h;
            }
            uv.push([u, v]);
        }
    }
    uv
}

/// A tiny training job: a 6 × 6 cloth, four 0.3 s rollouts to train on and one to test, a few
/// Adam steps per pass, checkpoints every 5 iterations (data in `data/`).
pub const TINY: &str = r#"
name = "tiny"
[cloth]
nx = 6
ny = 6
[data]
dir = "data"
[data.clips]
steps = 50
[source]
nx = 6
ny = 6
width = 2.5
height = 2.5
seconds = 0.3
train_rollouts = 4
test_rollouts = 1
[train]
checkpoint_every = 5
[train.stiffness]
iterations = 10
batch = 4
[train.damping]
iterations = 5
batch = 4
"#;

/// [`TINY`] with each `(from, to)` of `changes` made wherever `from` stands, in turn; a `from`
/// that is not there fails, so that no change is silently lost.
pub fn tiny_with(changes: &[(&str, &str)]) -> String {
    changes.iter().fold(TINY.to_string(), |text, (from, to)| {
        assert!(text.contains(from), "no {from:?} in the tiny job");
        text.replace(from, to)
    })
}

/// A 4 × 4 surrogate of a 1 m square FEM sheet (0.3 s rollouts, three to train and one to
/// test), trained for a few steps: a job's tables but its `name` and `[data]` folders.
pub const FEM_4X4: &str = r#"
[cloth]
nx = 4
ny = 4

[model]
k_init = 100.0
b_init = 0.05

[sim]
substeps = 2
rayleigh = 0.1

[data.clips]
steps = 20

[source]
kind = "fem"
nx = 4
ny = 4
width = 1.0
height = 1.0
stiffness_levels = [300.0]
layout = "uniform"
seconds = 0.3
dt = 5e-4
frame_stride = 2
train_rollouts = 3
test_rollouts = 1
anchor_radius = 0.2

[source.fem]
bending = 0.002
strain_damping = 0.0

[train.stiffness]
iterations = 4
batch = 2

[train.damping]
iterations = 2
batch = 2
"#;

/// SIGKILLs `child` (no chance to clean up) once the run whose `run.json` is `state` has a
/// checkpoint at iteration `at` or later on disk; panics if the child ends first.
pub fn kill_after_checkpoint(child: &mut std::process::Child, state: &std::path::Path, at: u64) {
    loop {
        let checkpoint = std::fs::read_to_string(state)
            .ok()
            .and_then(|t| serde_json::from_str::<serde_json::Value>(&t).ok())
            .and_then(|v| v["checkpoint"].as_u64())
            .unwrap_or(0);
        if checkpoint >= at {
            break;
        }
        assert!(
            child.try_wait().unwrap().is_none(),
            "the run ended before its checkpoint {at}"
        );
        std::thread::sleep(std::time::Duration::from_millis(2));
    }
    child.kill().unwrap();
    child.wait().unwrap();
}

/// The recovery tests' start and schedule (tests/recovery.rs, tests/data_mesh.rs): a uniform
/// 50 N/m and 3 N·s/m, 100-step clips, 120 stiffness iterations (batch 8, lr 2) and 40 damping
/// iterations (batch 8, lr 0.1).
pub const RECOVERY: &str = r#"
[model]
k_init = 50.0
b_init = 3.0
[data.clips]
steps = 100
[train.stiffness]
iterations = 120
batch = 8
lr = 2.0
[train.damping]
iterations = 40
batch = 8
lr = 0.1
"#;
