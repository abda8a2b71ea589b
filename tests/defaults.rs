//! Defaults derived from the data: the least-squares uniform fit, external forces read from the
//! files, automatic substeps, and training that stays inside the stable region.

mod common;

use springtime::config::{Auto, Config};
use springtime::data::ClipSet;
use springtime::progress::Progress;
use springtime::settings::Job;
use springtime::source::Layout;
use springtime::train::init::{UniformFit, resolve};
use springtime::train::{TrainOptions, train};

/// A uniform 6 × 6 spring source (k = 40 N/m, b = 6 N·s/m, Rayleigh 0.1) written to `dir`,
/// with its `rayleigh` key dropped when `keep_rayleigh` is false and gravity replaced.
fn write_uniform_source(dir: &std::path::Path, keep_rayleigh: bool, gravity: [f64; 3]) {
    let mut cfg = common::source(6, &[40.0], 0.6);
    cfg.layout = Layout::Uniform;
    cfg.gravity = gravity;
    std::fs::create_dir_all(dir).unwrap();
    for seed in 0..3 {
        let (_, mut r) = common::rollout(&cfg, seed);
        if !keep_rayleigh {
            r.rayleigh = None;
        }
        r.save(&dir.join(format!("r{seed}.npz"))).unwrap();
    }
}

fn open(dir: &std::path::Path, config: &Config) -> ClipSet {
    let files = springtime::data::npz_files(dir).unwrap();
    ClipSet::open(
        &files,
        &config.data.clips,
        |r| springtime::train::topology(config, r),
        256 << 20,
        |_| {},
    )
    .unwrap()
}

fn config(dir: &std::path::Path) -> Config {
    let mut c = Config::parse("[cloth]\nnx = 6\nny = 6\n[data.clips]\nsteps = 100\n", &[]).unwrap();
    c.data.dir = dir.to_path_buf();
    c
}

#[test]
fn the_uniform_fit_recovers_k_b_and_rayleigh_of_a_uniform_source() {
    let dir = common::temp_dir("defaults_fit");
    write_uniform_source(&dir, false, [0.0, 0.0, -9.81]);
    let cfg = config(&dir);
    let clips = open(&dir, &cfg);
    let fit = UniformFit::fit(&clips, [0.0, 0.0, -9.81], None).unwrap();
    eprintln!("{fit:?}");
    // The surrogate is the source's own network: the fit is exact up to the central
    // differences' O(dt²) error at 1 ms.
    assert!((fit.k - 40.0).abs() < 0.02 * 40.0, "k = {}", fit.k);
    assert!((fit.b - 6.0).abs() < 0.05 * 6.0, "b = {}", fit.b);
    assert!((fit.c - 0.1).abs() < 0.05, "c = {}", fit.c);
    assert!(fit.residual_rms < 0.05 * fit.target_rms, "{fit:?}");
    // A given Rayleigh constant is kept and the rest still fits.
    let fixed = UniformFit::fit(&clips, [0.0, 0.0, -9.81], Some(0.1)).unwrap();
    assert!(!fixed.fitted_c && fixed.c == 0.1);
    assert!((fixed.k - 40.0).abs() < 0.02 * 40.0, "k = {}", fixed.k);
    // Wrong gravity cannot be explained by springs: the residual grows.
    let wrong = UniformFit::fit(&clips, [0.0, 0.0, -5.0], None).unwrap();
    assert!(
        wrong.residual_rms > 5.0 * fit.residual_rms,
        "{wrong:?} vs {fit:?}"
    );
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn auto_values_come_from_the_files_and_are_written_resolved() {
    let dir = common::temp_dir("defaults_resolve");
    write_uniform_source(&dir, true, [0.0, -2.0, -9.0]);
    let cfg = config(&dir);
    let clips = open(&dir, &cfg);
    let (resolved, how) = resolve(&cfg, &clips, None).unwrap();
    assert_eq!(how.gravity, [0.0, -2.0, -9.0]);
    assert_eq!(how.gravity_from, "data");
    // Same particles as landmarks: the files' Rayleigh constant is taken as it is.
    assert!((how.rayleigh - 0.1).abs() < 1e-12 && how.rayleigh_from == "data");
    assert!((how.k_init - 40.0).abs() < 0.02 * 40.0, "{how:?}");
    assert!(how.stability_number <= springtime::train::init::AUTO_SUBSTEPS_TARGET);
    for v in [
        resolved.sim.substeps.value().map(|n| n as f64),
        resolved.sim.rayleigh.value(),
        resolved.model.k_init.value(),
        resolved.model.b_init.value(),
        resolved.data.clips.steps.value().map(|n| n as f64),
    ] {
        assert!(v.is_some(), "an \"auto\" left unresolved: {resolved:?}");
    }
    // The resolved config reads back as the same numbers.
    let back = Config::parse(&resolved.to_toml(), &[]).unwrap();
    assert_eq!(back, resolved);
    // A value the config gives wins over the data.
    let mut given = cfg.clone();
    given.sim.gravity = Auto::Value([0.0, -2.0, -9.0]);
    given.sim.rayleigh = Auto::Value(0.5);
    let (_, how) = resolve(&given, &clips, None).unwrap();
    assert_eq!((how.gravity_from, how.rayleigh_from), ("config", "config"));
    assert_eq!(how.rayleigh, 0.5);
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn training_is_projected_back_into_the_stable_region() {
    // A damping learning rate far too large for the explicit step: without the projection the
    // damping pass drives b past dt²ω² + 2·dt·γ = 4 and the loss becomes NaN.
    let dir = common::temp_dir("defaults_projection");
    let data = dir.join("data");
    write_uniform_source(&data, true, [0.0, 0.0, -9.81]);
    let mut cfg = config(&data);
    cfg.runs_dir = dir.join("runs");
    cfg.name = "proj".into();
    cfg.train.stiffness.iterations = 4;
    cfg.train.damping.iterations = 12;
    cfg.train.damping.lr = 50.0;
    cfg.train.stiffness.batch = 2;
    cfg.train.damping.batch = 2;
    let summary = train(&cfg, &TrainOptions::default(), &Progress::quiet()).unwrap();
    let metrics = std::fs::read_to_string(summary.run_dir.join("metrics.csv")).unwrap();
    let header: Vec<&str> = metrics.lines().next().unwrap().split(',').collect();
    let col = header.iter().position(|h| *h == "clamped").unwrap();
    let clamped: usize = metrics
        .lines()
        .skip(1)
        .map(|l| l.split(',').nth(col).unwrap().parse::<usize>().unwrap())
        .sum();
    assert!(clamped > 0, "the limit never became active:\n{metrics}");
    // The final network is inside the region the projection promises, with no negative value.
    let resolved = Config::load(&summary.run_dir.join("config.toml"), &[]).unwrap();
    let springs = springtime::data::npz::Npz::read(&summary.run_dir.join("springs.npz")).unwrap();
    let b = springs.f32("b", &[None]).unwrap().0;
    let k = springs.f32("k", &[None]).unwrap().0;
    let clips = open(&data, &resolved);
    let physics =
        springtime::sim::Physics::new(&resolved.sim, clips.info.frame_dt, clips.particle_mass());
    let st = springtime::sim::Stability::estimate(
        &clips.topology,
        &k.iter().map(|&x| x as f64).collect::<Vec<_>>(),
        &b.iter().map(|&x| x as f64).collect::<Vec<_>>(),
        physics.mass,
        physics.rayleigh,
        physics.sim_dt(),
    );
    assert!(
        st.number() <= springtime::train::TRAIN_STABILITY_LIMIT * 1.001,
        "{}",
        st.describe()
    );
    assert!(b.iter().chain(&k).all(|&x| x >= 0.0));
    std::fs::remove_dir_all(&dir).ok();
}

/// The yardstick of spatial learning: from a stiffness 4× too low and almost no damping, the
/// uniform-baseline search of `eval` finds the uniform source's stiffness, and raises the
/// damping towards the source's (b = 6 N·s/m, far above every candidate).
#[test]
fn the_uniform_baseline_finds_the_stiffness_and_damping_of_a_uniform_source() {
    let dir = common::temp_dir("defaults_baseline");
    write_uniform_source(&dir.join("data"), true, [0.0, 0.0, -9.81]);
    let config = "name = \"baseline\"\n[cloth]\nnx = 6\nny = 6\n\
                  [model]\nk_init = 10.0\nb_init = 0.001\n\
                  [data]\ndir = \"data\"\ntest_dir = \"data\"\n[data.clips]\nsteps = 100\n\
                  [train.stiffness]\niterations = 0\n[train.damping]\niterations = 0\n\
                  [eval]\nuniform_baseline = true\n";
    std::fs::write(dir.join("baseline.toml"), config).unwrap();
    common::ok(&common::springtime(&["train", "baseline.toml"], &dir));
    common::ok(&common::springtime(&["eval", "runs/baseline"], &dir));
    let eval: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.join("runs/baseline/eval.json")).unwrap())
            .unwrap();
    let u = &eval["uniform_baseline"];
    let (k, b) = (u["k"].as_f64().unwrap(), u["b"].as_f64().unwrap());
    eprintln!("best uniform k = {k} N/m, b = {b} N·s/m");
    assert!((k - 40.0).abs() < 0.2 * 40.0, "k = {k}: {u}");
    assert!(b > 0.01, "b = {b}: {u}");
    assert!(u["b_search"].as_array().unwrap().len() > 1, "{u}");
    std::fs::remove_dir_all(&dir).ok();
}

/// `train.scale_search`: from a uniform network 4× too soft (and untrained), the search over one
/// factor for every `k` and one for every `b` finds the source's size (k = 40 N/m), keeps the
/// network's shape (every spring scaled by the same factor), lowers the training rollouts' error
/// and writes the substeps the scaled network needs into the run's config.
#[test]
fn the_scale_search_finds_the_size_and_keeps_the_shape() {
    let dir = common::temp_dir("defaults_scale");
    let data = dir.join("data");
    write_uniform_source(&data, true, [0.0, 0.0, -9.81]);
    let mut cfg = config(&data);
    cfg.runs_dir = dir.join("runs");
    cfg.name = "scale".into();
    cfg.model.k_init = Auto::Value(10.0);
    cfg.model.b_init = Auto::Value(1.0);
    cfg.train.stiffness.iterations = 0;
    cfg.train.damping.iterations = 0;
    cfg.train.scale_search = true;
    let summary = train(&cfg, &TrainOptions::default(), &Progress::quiet()).unwrap();
    let record: springtime::train::scale::ScaleSearch =
        serde_json::from_slice(&std::fs::read(summary.run_dir.join("scale.json")).unwrap())
            .unwrap();
    eprintln!("{record:?}");
    assert!(
        (2.8..=5.7).contains(&record.k_factor),
        "k factor {} (expected about 4)",
        record.k_factor
    );
    assert!(record.after <= record.before.unwrap(), "{record:?}");
    let springs = springtime::data::npz::Npz::read(&summary.run_dir.join("springs.npz")).unwrap();
    let k = springs.f32("k", &[None]).unwrap().0;
    let b = springs.f32("b", &[None]).unwrap().0;
    for (&k, &b) in k.iter().zip(&b) {
        assert!(
            (k as f64 - 10.0 * record.k_factor).abs() < 1e-4 * k as f64,
            "k = {k}"
        );
        assert!(
            (b as f64 - record.b_factor).abs() < 1e-4 * b as f64,
            "b = {b}"
        );
    }
    let resolved = Config::load(&summary.run_dir.join("config.toml"), &[]).unwrap();
    assert_eq!(resolved.sim.substeps, Auto::Value(record.substeps));
    std::fs::remove_dir_all(&dir).ok();
}
