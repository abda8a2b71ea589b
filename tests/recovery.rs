//! Recovery of known parameters: a small two-level spring cloth trained from a uniform guess.

mod common;

use std::path::Path;

use springtime::config::Config;
use springtime::progress::Progress;
use springtime::settings::Job;
use springtime::source::SourceConfig;
use springtime::train::{TrainOptions, TrainSummary, train};

/// Trains an 8 × 8 surrogate named `name` on data of `source` (generated into `dir/data`, runs in
/// `dir/runs`): the config `body` after the name and cloth, with the overrides `set`.
fn train_8x8(
    dir: &Path,
    name: &str,
    body: &str,
    set: &[String],
    source: SourceConfig,
) -> TrainSummary {
    let text = format!("name = \"{name}\"\n[cloth]\nnx = 8\nny = 8\n{body}");
    let mut config = Config::parse(&text, set).unwrap();
    config.data.dir = dir.join("data");
    config.runs_dir = dir.join("runs");
    config.source = Some(source);
    train(&config, &TrainOptions::default(), &Progress::quiet()).unwrap()
}

#[test]
fn dual_pass_training_recovers_two_stiffness_levels() {
    let dir = common::temp_dir("recovery");
    let mut source = common::source(8, &[20.0, 80.0], 1.0);
    source.train_rollouts = 16;
    source.test_rollouts = 2;
    let summary = train_8x8(&dir, "recovery", common::RECOVERY, &[], source);
    let (rmse_k, rmse_b) = (summary.rmse_k.unwrap(), summary.rmse_b.unwrap());
    eprintln!("rmse_k {rmse_k:.3} N/m, rmse_b {rmse_b:.3} N·s/m");
    // Stated tolerance: RMSE of k within 10 % of the mean stiffness (50 N/m) from a start of
    // RMSE 30 N/m, and RMSE of b within 25 % of the true 6 N·s/m from a start of 3 N·s/m.
    assert!(rmse_k < 5.0, "rmse_k = {rmse_k}");
    assert!(rmse_b < 1.5, "rmse_b = {rmse_b}");
    std::fs::remove_dir_all(&dir).ok();
}

/// On camera-rate data without stored velocities (10 ms frames, the velocities estimated by
/// central differences), the frame-difference loss (`train.force_on = "frames"`) of the true
/// network is small (what is left comes from the pins, which the surrogate interpolates
/// linearly between frames, and the estimated initial velocities), and a uniform network
/// stiffer or softer than the truth
/// scores worse in both its force and impulse terms: the loss ranks uniform stiffnesses as the
/// motion does.
#[test]
fn frame_difference_loss_is_zero_at_the_truth_and_ranks_uniform_stiffness() {
    use springtime::model::SpringNet;
    use springtime::sim::Physics;
    use springtime::train::{ForceOn, LossWeights, loss};
    let device = burn::tensor::Device::flex().autodiff();
    let mut cfg = common::source(6, &[40.0], 1.0);
    cfg.frame_stride = 10;
    cfg.save_velocities = false;
    let rollouts: Vec<_> = (0..3).map(|s| common::rollout(&cfg, s).1).collect();
    assert!(rollouts[0].velocities.is_none());
    let topo = common::grid_of(&cfg);
    let physics = Physics {
        frame_dt: rollouts[0].frame_dt,
        substeps: cfg.frame_stride,
        mass: rollouts[0].total_mass / topo.num_particles() as f64,
        rayleigh: cfg.rayleigh,
        gravity: cfg.gravity,
        viscosity: 0.0,
        shear_compression: 1.0,
    };
    assert!((physics.frame_dt - 0.01).abs() < 1e-12);
    let batch = common::batch(&cfg, &rollouts, 20, 30, &device);
    let s = topo.num_springs();
    let score_on = |k: f64, on: ForceOn| {
        let model = SpringNet::new(&topo, &vec![k; s], &vec![cfg.damping; s], &device);
        let t = loss(&model, &physics, &batch, &LossWeights::default(), on);
        (
            t.force.into_scalar::<f64>(),
            t.impulse.into_scalar::<f64>(),
            t.position.into_scalar::<f64>(),
        )
    };
    let score = |k: f64| score_on(k, ForceOn::Frames);
    let truth = score(40.0);
    // Against a particle's weight: an RMS force error under 0.5 % of it.
    let m_g = physics.mass * 9.81;
    assert!(
        truth.0 < (5e-3 * m_g).powi(2),
        "force term at the truth {truth:?}"
    );
    for k in [10.0, 20.0, 80.0, 160.0] {
        let other = score(k);
        assert!(
            other.0 > 100.0 * truth.0.max(1e-30) && other.1 > truth.1 && other.2 > truth.2,
            "k = {k}: {other:?} vs the truth's {truth:?}"
        );
    }
}

/// Trains `source` data with `train.least_squares` and no Adam iterations; returns the summary's
/// `(rmse_k, rmse_b)` and the fit's record.
fn least_squares_only(
    name: &str,
    source: SourceConfig,
    extra: &[&str],
) -> (f64, f64, serde_json::Value) {
    let dir = common::temp_dir(name);
    let mut set = vec![
        "train.least_squares.enabled=true".to_string(),
        "train.stiffness.iterations=0".to_string(),
        "train.damping.iterations=0".to_string(),
    ];
    set.extend(extra.iter().map(|s| s.to_string()));
    let body = "[model]\nk_init = 50.0\nb_init = 3.0\n[data.clips]\nsteps = 40\n";
    let summary = train_8x8(&dir, "least_squares", body, &set, source);
    let record: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(summary.run_dir.join("least_squares.json")).unwrap(),
    )
    .unwrap();
    (summary.rmse_k.unwrap(), summary.rmse_b.unwrap(), record)
}

/// The per-spring least-squares start (`train.least_squares`, ours): on a semi-implicit Euler
/// source whose files store velocities at its own 1 ms step, the force fit is exact, and the
/// solve returns the source's network (two stiffness levels, 20 and 80 N/m, from a uniform 50:
/// RMSE 30 N/m) to a small fraction of a N/m — with no gradient step at all.
#[test]
fn least_squares_recovers_the_source_network_from_stored_velocities() {
    let source = common::source(8, &[20.0, 80.0], 0.5);
    let (rmse_k, rmse_b, record) = least_squares_only("ls_exact", source, &[]);
    eprintln!("rmse_k {rmse_k:.3e}, rmse_b {rmse_b:.3e}; {record}");
    assert_eq!(record["velocity_frames"], record["frames"]);
    assert_eq!(record["unconstrained"], 0);
    assert_eq!(record["settled"], true);
    assert_eq!(record["converged"], true);
    assert!(
        record["residual_fitted"].as_f64().unwrap() < 1e-3,
        "{record}"
    );
    assert!(
        record["residual_initial"].as_f64().unwrap() > 0.1,
        "{record}"
    );
    assert!(rmse_k < 0.05, "rmse_k = {rmse_k}");
    assert!(rmse_b < 0.05, "rmse_b = {rmse_b}");
}

/// Camera-rate frames without velocities (10 ms, the source stepping at 1 ms): the target is a
/// second difference of positions over the stencil, the force an average over it, and the fit
/// is no longer exact — but it still separates the two stiffness levels far better than the
/// uniform start (RMSE 30 N/m): measured 0.35 N/m and 0.14 N·s/m.
#[test]
fn least_squares_learns_the_levels_from_camera_rate_positions() {
    let mut source = common::source(8, &[20.0, 80.0], 2.0);
    source.frame_stride = 10;
    source.save_velocities = false;
    source.train_rollouts = 8;
    let (rmse_k, rmse_b, record) =
        least_squares_only("ls_camera", source, &["data.clips.steps=20"]);
    eprintln!("rmse_k {rmse_k:.3e}, rmse_b {rmse_b:.3e}; {record}");
    assert_eq!(record["velocity_frames"], 0);
    assert!(rmse_k < 2.0, "rmse_k = {rmse_k}");
    assert!(rmse_b < 1.0, "rmse_b = {rmse_b}");
}

/// `train.refine` (ours; PhysTwin's per-spring stage): on camera-rate frames without velocities,
/// from a uniform network at the levels' mean (k 50 N/m against 20 and 80: RMSE 30 N/m), Adam
/// steps on `log k` of the multiple-shooting position loss move the springs towards their
/// levels. The refined network is kept (its free rollouts of the training takes move closer
/// than the uniform one's) and its `k` is closer to the source's.
#[test]
fn the_refinement_moves_a_uniform_network_towards_the_levels() {
    let dir = common::temp_dir("refine");
    let mut source = common::source(8, &[20.0, 80.0], 2.0);
    source.frame_stride = 10;
    source.save_velocities = false;
    source.train_rollouts = 8;
    let set: Vec<String> = [
        "train.stiffness.iterations=0",
        "train.damping.iterations=0",
        "train.refine.iterations=60",
        "train.refine.lr=0.05",
        "train.refine.batch=8",
    ]
    .map(String::from)
    .to_vec();
    let body = "[model]\nk_init = 50.0\nb_init = 6.0\n[data.clips]\nsteps = 20\n";
    let summary = train_8x8(&dir, "refine", body, &set, source);
    let record: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(summary.run_dir.join("refine.json")).unwrap(),
    )
    .unwrap();
    let (before, after) = (
        record["before"].as_f64().unwrap(),
        record["after"].as_f64().unwrap(),
    );
    eprintln!("training takes' motion RMSE {before:.4} -> {after:.4} m");
    assert_eq!(record["kept"], true, "{record}");
    assert!(after < before, "{record}");
    let config = Config::load(&summary.run_dir.join("config.toml"), &[]).unwrap();
    let (_, truth) = springtime::train::open_training_clips(&config, &Progress::quiet()).unwrap();
    let truth = truth.expect("the source's springs are the surrogate's").0;
    let npz = springtime::data::npz::Npz::read(&summary.run_dir.join("springs.npz")).unwrap();
    let k: Vec<f64> = npz
        .f32("k", &[None])
        .unwrap()
        .0
        .iter()
        .map(|&x| x as f64)
        .collect();
    let start = summary.rmse_k.unwrap();
    let refined = springtime::train::rmse(&k, &truth);
    eprintln!("rmse_k {start:.3} (uniform) -> {refined:.3} N/m (refined)");
    assert!(refined < 0.7 * start, "rmse_k {start} -> {refined}");
    std::fs::remove_dir_all(&dir).ok();
}

/// Takes of a uniform 8 × 8 spring cloth (50 N/m, damping 6 N·s/m) whose stride-2 bending
/// springs have `bending` times that stiffness: 8 training and 2 test takes under `dir`, the
/// files stating the source's drag where `state_drag`.
fn spring_cloth_takes(
    dir: &std::path::Path,
    bending: f64,
    state_drag: bool,
) -> springtime::source::SourceConfig {
    use springtime::cloth::SpringFamily;
    use springtime::source::mass_spring::SpringCloth;

    let mut source = common::source(8, &[50.0], 2.0);
    source.frame_stride = 10;
    source.save_velocities = false;
    let mut cloth = SpringCloth::from_config(&source);
    for (k, family) in cloth.k.iter_mut().zip(&cloth.topology.family) {
        if *family == SpringFamily::Bending {
            *k *= bending;
        }
    }
    save_takes(dir, &cloth, &source, 2, state_drag);
    source
}

/// Simulates `cloth` (of `source`) from random scenarios: 8 training takes and `test` test takes
/// under `dir`, the files stating the source's drag where `state_drag`.
fn save_takes(
    dir: &std::path::Path,
    cloth: &springtime::source::mass_spring::SpringCloth,
    source: &springtime::source::SourceConfig,
    test: u64,
    state_drag: bool,
) {
    use rand::{SeedableRng, rngs::StdRng};
    use springtime::source::{Scenario, simulate_rollout};

    for (split, seeds) in [("train", 0..8u64), ("test", 100..100 + test)] {
        std::fs::create_dir_all(dir.join(split)).unwrap();
        for seed in seeds {
            let scenario = Scenario::random(
                &cloth.topology.rest_uv,
                source.anchor_radius,
                &mut StdRng::seed_from_u64(seed),
            );
            let path = dir.join(split).join(format!("take_{seed:03}.npz"));
            let mut take =
                simulate_rollout(cloth, source, &scenario, None, &path.to_string_lossy()).unwrap();
            if !state_drag {
                take.rayleigh = None;
            }
            take.save(&path).unwrap();
        }
    }
}

/// A blend search on `dir`'s takes from a uniform network `(k_init, b_init)`, no fit: its
/// `blend.json`.
fn blend_record(dir: &std::path::Path, k_init: f64, b_init: f64) -> serde_json::Value {
    blend_run(dir, k_init, b_init).1
}

/// A blend search on `dir`'s takes from a uniform network `(k_init, b_init)`, no fit: its run
/// directory and `blend.json`.
fn blend_run(
    dir: &std::path::Path,
    k_init: f64,
    b_init: f64,
) -> (std::path::PathBuf, serde_json::Value) {
    blend_run_holding_out(dir, k_init, b_init, 0)
}

/// [`blend_run`] with the last `holdout` training takes held out of it (`data.holdout`).
fn blend_run_holding_out(
    dir: &std::path::Path,
    k_init: f64,
    b_init: f64,
    holdout: usize,
) -> (std::path::PathBuf, serde_json::Value) {
    blend_run_with(dir, k_init, b_init, holdout, "")
}

/// [`blend_run_holding_out`] with `train` (lines of the `[train]` section) added.
fn blend_run_with(
    dir: &std::path::Path,
    k_init: f64,
    b_init: f64,
    holdout: usize,
    train_lines: &str,
) -> (std::path::PathBuf, serde_json::Value) {
    let text = format!(
        "name = \"blend\"\n[cloth]\nnx = 8\nny = 8\n[model]\nk_init = {k_init}\n\
         b_init = {b_init}\n[data]\nholdout = {holdout}\n[train]\nblend_search = true\n\
         {train_lines}[train.stiffness]\niterations = 0\n[train.damping]\niterations = 0\n"
    );
    let mut config = Config::parse(&text, &[]).unwrap();
    config.data.dir = dir.join("train");
    config.data.test_dir = Some(dir.join("test"));
    config.runs_dir = dir.join("runs");
    let summary = train(&config, &TrainOptions::default(), &Progress::quiet()).unwrap();
    let record =
        serde_json::from_str(&std::fs::read_to_string(summary.run_dir.join("blend.json")).unwrap())
            .unwrap();
    // Every network a blend search keeps runs at half the explicit step's limit at most, at the
    // substeps its `config.toml` names.
    let run = springtime::run::Run::open(&summary.run_dir, &[], None).unwrap();
    let physics = run.physics(run.meta.frame_dt);
    let number = physics
        .stability_of(&run.topology, run.springs().unwrap())
        .number();
    assert!(number <= 2.0, "stability number {number} at {physics:?}");
    (summary.run_dir, record)
}

/// A run of the uniform network of `dir`'s takes' source (50 N/m, 6 N·s/m), untrained, with the
/// uniform yardstick asked for: its directory.
fn uniform_run(dir: &std::path::Path) -> std::path::PathBuf {
    let text = "name = \"uniform\"\n[cloth]\nnx = 8\nny = 8\n[model]\nk_init = 50\n\
                b_init = 6\n[data]\nholdout = 0\n[train.stiffness]\niterations = 0\n\
                [train.damping]\niterations = 0\n[eval]\nuniform_baseline = true\n";
    let mut config = Config::parse(text, &[]).unwrap();
    config.data.dir = dir.join("train");
    config.data.test_dir = Some(dir.join("test"));
    config.runs_dir = dir.join("runs");
    train(&config, &TrainOptions::default(), &Progress::quiet())
        .unwrap()
        .run_dir
}

/// The blend search's bending stage recovers how stiff a cloth's bending springs are beside its
/// others: takes of a uniform 8 × 8 spring cloth (50 N/m) whose stride-2 bending springs have a
/// sixteenth of that, learned from a uniform network over every spring by no fit at all.
#[test]
fn the_blend_search_finds_the_bending_springs_share() {
    let dir = common::temp_dir("bending-share");
    spring_cloth_takes(&dir, 1.0 / 16.0, true);
    let (run_dir, record) = blend_run(&dir, 50.0, 6.0);
    let factor = record["bending_factor"].as_f64().unwrap();
    eprintln!(
        "bending factor {factor}; candidates {}",
        record["bending_candidates"]
    );
    assert_eq!(factor, 1.0 / 16.0, "{record}");
    // ... and settles it on the uniform network, before the map's shares are searched.
    assert_eq!(
        record["rows_bending_factor"].as_f64(),
        Some(1.0 / 16.0),
        "{record}"
    );
    // The map is the uniform start itself, so no share of it moves closer: the run keeps the
    // uniform network with its bending springs sized, and sets the map aside beside it.
    assert_eq!(record["alpha"].as_f64(), Some(0.0), "{record}");
    let k_of = |file: &str| {
        springtime::data::npz::Npz::read(&run_dir.join(file))
            .unwrap()
            .f32("k", &[None])
            .unwrap()
            .0
    };
    assert!(k_of("springs.learned.npz").iter().all(|&k| k == 50.0));
    let kept = k_of("springs.npz");
    assert!(kept.iter().any(|&k| k != 50.0), "{kept:?}");
    std::fs::remove_dir_all(&dir).ok();
}

/// The shear compression search (`train.compression_search`) finds that a cloth's shear springs
/// are soft in compression, and only there: takes of a uniform 8 × 8 spring cloth (50 N/m) whose
/// cell diagonals push back with nothing when shorter than at rest (`shear_compression` 0, as
/// Blender's cloth's), learned from the source's uniform network with two training takes held
/// out to confirm it, keep the source's pull-only shear springs, closer to the held-out takes;
/// takes of the same cloth with linear springs keep them linear. (The search runs after the
/// blend search and its polish, which size `k` and `b` as if the springs were linear: at those
/// sizes a half is closer to the pull-only cloth's takes than none, and only with its `k`
/// searched at each softening, not at the closest alone, does the search find the source's 0.)
/// The same search sizes the shear springs' share of the stiffness: takes of the cloth whose
/// linear shear springs have half the sides' `k` (25 N/m), learned from the uniform 50 N/m,
/// keep a share below 1 on the shear springs, closer to the held-out takes, where the uniform
/// cloth's keep their share.
#[test]
fn the_compression_search_finds_shear_springs_that_pull_only() {
    use springtime::cloth::SpringFamily;
    use springtime::source::mass_spring::SpringCloth;
    for (source_compression, source_share) in [(0.0, 1.0), (1.0, 1.0), (1.0, 0.5)] {
        let dir = common::temp_dir("shear-compression");
        let mut source = common::source(8, &[50.0], 2.0);
        source.frame_stride = 10;
        source.save_velocities = false;
        let mut cloth = SpringCloth {
            shear_compression: source_compression,
            ..SpringCloth::from_config(&source)
        };
        cloth
            .topology
            .scale_family(&mut cloth.k, SpringFamily::Shear, source_share);
        save_takes(&dir, &cloth, &source, 2, true);
        let (run_dir, record) = blend_run_with(&dir, 50.0, 6.0, 2, "compression_search = true\n");
        let search = &record["shear_compression"];
        eprintln!("source {source_compression}, share {source_share}: {search}");
        let run = springtime::run::Run::open(&run_dir, &[], None).unwrap();
        let kept = run.config.sim.shear_compression;
        let share = if search["kept"].as_bool() == Some(true) {
            search["shear_share"].as_f64().unwrap()
        } else {
            1.0
        };
        if source_compression == 0.0 || source_share < 1.0 {
            assert_eq!(kept, source_compression, "{search}");
            assert_eq!(search["kept"].as_bool(), Some(true), "{search}");
            let held_out = &search["held_out"];
            let (before, after) = (
                held_out[0][1].as_f64().unwrap(),
                held_out[1][1].as_f64().unwrap(),
            );
            assert!(after < before, "{search}");
        } else {
            assert_eq!(kept, 1.0, "{search}");
        }
        if source_share < 1.0 {
            assert!(share < 1.0, "{search}");
        } else {
            assert_eq!(share, 1.0, "{search}");
        }
        std::fs::remove_dir_all(&dir).ok();
    }
}

/// The blend search past the whole map (`train.blend_contrast`): on takes of a two-level 8 × 8
/// spring cloth (20 and 80 N/m in stripes), the least-squares map smoothed six times over the spring
/// graph (`train.map_smoothing`) is flatter than the source's, so the blend search keeps all of
/// it (`α = 1`) and stops there; with the contrast search it goes on to a map whose contrast is
/// raised (`α > 1`), closer to the training takes, and a map closer to the source's `k`. With
/// two takes held out, that share is checked against the share kept without it, both polished
/// (`blend.json`'s `contrast`), and the run keeps the one the held-out takes prefer.
#[test]
fn the_blend_search_raises_the_contrast_of_a_flattened_map() {
    use springtime::source::mass_spring::SpringCloth;
    let lines = "map_smoothing = 6\n[train.least_squares]\nenabled = true\n";
    let mut found = Vec::new();
    let mut checked = None;
    for (contrast, holdout) in [(false, 0), (true, 0), (true, 2)] {
        let dir = common::temp_dir("blend-contrast");
        let mut source = common::source(8, &[20.0, 80.0], 2.0);
        source.frame_stride = 10;
        source.save_velocities = false;
        let cloth = SpringCloth::from_config(&source);
        save_takes(&dir, &cloth, &source, 2, true);
        let (run_dir, record) = blend_run_with(
            &dir,
            50.0,
            6.0,
            holdout,
            &format!("blend_contrast = {contrast}\n{lines}"),
        );
        if holdout > 0 {
            checked = Some(record);
            std::fs::remove_dir_all(&dir).ok();
            continue;
        }
        let k = springtime::data::npz::Npz::read(&run_dir.join("springs.npz"))
            .unwrap()
            .f32("k", &[None])
            .unwrap()
            .0;
        // The structural springs' spread about their mean, against the source's.
        let spread = |v: &[f64]| {
            let m = v.iter().sum::<f64>() / v.len() as f64;
            (v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / v.len() as f64).sqrt() / m
        };
        let structural: Vec<usize> = (0..cloth.k.len())
            .filter(|&s| cloth.topology.family[s] == springtime::cloth::SpringFamily::Structural)
            .collect();
        let kept: Vec<f64> = structural.iter().map(|&s| k[s] as f64).collect();
        let truth: Vec<f64> = structural.iter().map(|&s| cloth.k[s]).collect();
        eprintln!(
            "contrast search {contrast}: alpha {}, after {}, spread {:.3} (source {:.3})",
            record["alpha"],
            record["after"],
            spread(&kept),
            spread(&truth)
        );
        found.push((
            record["alpha"].as_f64().unwrap(),
            record["after"].as_f64().unwrap(),
            spread(&kept),
            spread(&truth),
        ));
        std::fs::remove_dir_all(&dir).ok();
    }
    // With takes held out, the share past the whole map is checked against the share kept
    // without it, both polished, and kept where the held-out takes prefer it; the run keeps
    // what its record says.
    let record = checked.expect("the run with held-out takes");
    let check = &record["contrast"];
    let value = |key: &str| check[key].as_f64().unwrap();
    assert!(
        value("alpha") > 1.0 && value("plain_alpha") <= 1.0,
        "{check}"
    );
    let pair = |v: &serde_json::Value| (v[0].as_f64().unwrap(), v[1].as_f64().unwrap());
    let (without, with) = (pair(&check["held_out"][0]), pair(&check["held_out"][1]));
    let kept = (with.0 / without.0) * (with.1 / without.1) < 1.0;
    assert_eq!(check["kept"].as_bool(), Some(kept), "{check}");
    let share = if kept { "alpha" } else { "plain_alpha" };
    assert_eq!(record["alpha"], check[share], "{record}");
    let polished = record["polish"]["after"].as_f64().unwrap();
    let want = if kept {
        value("after")
    } else {
        value("plain_after")
    };
    assert_eq!(polished, want, "{record}");
    let (flat, raised) = (found[0], found[1]);
    assert_eq!(flat.0, 1.0, "{found:?}");
    assert!(raised.0 > 1.0, "{found:?}");
    assert!(raised.1 < flat.1, "{found:?}");
    // The flattened map's spread is short of the source's; the raised one's is closer to it.
    assert!(flat.2 < flat.3, "{found:?}");
    assert!(
        (raised.2 - raised.3).abs() < (flat.2 - flat.3).abs(),
        "{found:?}"
    );
}

/// The bending-apart yardstick (`eval.json`'s `uniform_baseline.bending_apart`) finds how stiff a
/// cloth's bending springs are beside its others, where the uniform yardstick cannot: on takes
/// of a uniform 8 × 8 spring cloth (50 N/m) whose stride-2 bending springs have a sixteenth of
/// that, a run that keeps a uniform network over every spring (no fit, no search) is beaten by
/// the bending-apart network, which keeps the source's factor and moves far closer to the test takes
/// than the uniform yardstick does.
#[test]
fn the_bending_apart_yardstick_finds_the_bending_springs_share() {
    let dir = common::temp_dir("bending-apart");
    spring_cloth_takes(&dir, 1.0 / 16.0, true);
    let run_dir = uniform_run(&dir);
    let report = springtime::run::evaluate(&run_dir, None, None, &[], &Progress::quiet()).unwrap();
    let uniform = report.uniform_baseline.expect("asked for");
    let apart = uniform
        .bending_apart
        .as_ref()
        .expect("the grid has bending springs");
    eprintln!(
        "uniform k {} b {}: {} m; bending-apart × {} k {} b {}: {} m; rows {:?}",
        uniform.k,
        uniform.b,
        uniform.test.long.mean,
        apart.bending_factor,
        apart.k,
        apart.b,
        apart.test.long.mean,
        apart.factor_search
    );
    assert_eq!(apart.bending_factor, 1.0 / 16.0, "{apart:?}");
    assert_eq!(apart.k, 50.0, "{apart:?}");
    assert!(
        apart.test.long.mean < 0.1 * uniform.test.long.mean,
        "bending-apart {} m, uniform {} m",
        apart.test.long.mean,
        uniform.test.long.mean
    );
    // The run's network, uniform over every spring, loses to it.
    assert!(apart.improvement_long < 0.0, "{apart:?}");
    // Its factor 1 is the uniform yardstick itself: it moves as the yardstick did on the
    // training takes.
    let yardstick = uniform.train_rmse();
    assert_eq!(
        apart.factor_search.first(),
        Some(&(1.0, yardstick)),
        "{apart:?}"
    );
    std::fs::remove_dir_all(&dir).ok();
}

/// The uniform yardstick with its own damping (`uniform_baseline.own_damping`) finds the drag
/// the run's physics misses: on takes of a uniform spring cloth whose files do not state their
/// drag, a run evaluated at eight times the source's drag searches the yardstick there (it is
/// the run's kept physics), while the own-damping yardstick's drag row comes back to the
/// source's drag within a factor of 2, at the source's stiffness within a factor of 2, and moves
/// closer than the yardstick on the training takes and on the test takes.
#[test]
fn the_uniform_yardstick_with_its_own_damping_finds_the_drag_the_run_misses() {
    let dir = common::temp_dir("own-damping");
    let source = spring_cloth_takes(&dir, 1.0, false);
    let run_dir = uniform_run(&dir);
    let wrong = 8.0 * source.rayleigh;
    let report = springtime::run::evaluate(
        &run_dir,
        None,
        None,
        &[format!("sim.rayleigh={wrong}")],
        &Progress::quiet(),
    )
    .unwrap();
    let uniform = report.uniform_baseline.expect("asked for");
    let own = uniform.own_damping.as_ref().expect("eval searches it");
    eprintln!(
        "source drag {}, run's {wrong}: yardstick k {} b {} ({} m train, {} m test); own \
         damping ({}) drag {} k {} b {} ({} m train, {} m test); drag row {:?}",
        source.rayleigh,
        uniform.k,
        uniform.b,
        uniform.train_rmse(),
        uniform.test.long.mean,
        own.found_by,
        own.rayleigh,
        own.k,
        own.b,
        own.train_rmse,
        own.test.long.mean,
        own.drag_row
    );
    // It starts from the yardstick at the run's physics, as the yardstick moved there.
    let own_text = format!(
        "{} drag {} k {} b {}",
        own.found_by, own.rayleigh, own.k, own.b
    );
    assert_eq!(own.yardstick_train_rmse, uniform.train_rmse(), "{own_text}");
    assert_eq!(own.found_by, "drag", "{own_text}");
    let ratio = own.rayleigh / source.rayleigh;
    assert!(
        (0.5..=2.0).contains(&ratio),
        "drag {}: {own_text}",
        own.rayleigh
    );
    assert!((25.0..=100.0).contains(&own.k), "k {}: {own_text}", own.k);
    assert!(own.drag_row.len() >= 8, "{own_text}");
    assert!(own.train_rmse < own.yardstick_train_rmse, "{own_text}");
    assert!(own.test.long.mean < uniform.test.long.mean, "{own_text}");
    assert!(own.test.short.mean < uniform.test.short.mean, "{own_text}");
    std::fs::remove_dir_all(&dir).ok();
}

/// The blend search reaches a damping decades from its start: from a `b_init` a thousand times
/// below the source's 6 N·s/m (three times a spring's critical damping here), where its rows
/// of octaves reach 16 × 0.006 ≈ 0.1 N·s/m at most, the uniform end's damping row also tries
/// the fractions of critical damping and keeps one within a factor of 4 of the source's (the
/// critical damping itself, 1.96 N·s/m: three times that needs more substeps than the search's
/// cap), moving closer to the takes than any damping the octaves reach. Of its apart chains (the
/// octaves alone, and with the descent) it keeps the closer: no candidate it lists moves closer
/// than the network it kept.
#[test]
fn the_blend_search_reaches_a_damping_far_from_its_start() {
    let dir = common::temp_dir("blend-damping");
    spring_cloth_takes(&dir, 1.0, true);
    let record = blend_record(&dir, 50.0, 0.006);
    let b = record["uniform"][1].as_f64().unwrap();
    let b_mean = record["b_mean"].as_f64().unwrap();
    eprintln!("uniform end: {}", record["uniform"]);
    assert!((1.5..=24.0).contains(&b), "uniform damping {b}: {record}");
    let octaves = record["candidates"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|c| c[0].as_f64() == Some(0.0) && c[2].as_f64().unwrap() * b_mean <= 0.1)
        .map(|c| c[4].as_f64().unwrap())
        .fold(f64::INFINITY, f64::min);
    let kept = record["uniform"][2].as_f64().unwrap();
    assert!(
        kept < 0.8 * octaves,
        "{kept} m against {octaves} m within the octaves' reach"
    );
    let after = record["after"].as_f64().unwrap();
    let closest = record["candidates"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| c[4].as_f64().unwrap())
        .fold(f64::INFINITY, f64::min);
    eprintln!("kept the {} chain at {after} m", record["chain"]);
    assert!(after <= closest, "kept {after} m, a candidate {closest} m");
    std::fs::remove_dir_all(&dir).ok();
}

/// The blend search's polish measures the kept network against the yardstick itself: at the
/// substeps the run keeps, from the run's initial network, on the same training takes, its best
/// uniform network is the one `eval.uniform_baseline` then finds — the same `k`, `b` and
/// training-take RMSE to the bit — and the network it keeps, read back from the run's
/// `springs.npz`, moves no farther from those takes than that one. On takes of a uniform cloth
/// started a thousand times under its damping, that is the source's cloth.
#[test]
fn the_polish_measures_the_kept_network_against_the_yardstick() {
    let dir = common::temp_dir("blend-polish");
    spring_cloth_takes(&dir, 1.0, true);
    let (run_dir, record) = blend_run(&dir, 50.0, 0.006);
    let polish = &record["polish"];
    eprintln!("polish: {polish}");
    let report = springtime::run::evaluate(
        &run_dir,
        None,
        None,
        &["eval.uniform_baseline=true".to_string()],
        &Progress::quiet(),
    )
    .unwrap();
    let baseline = report.uniform_baseline.expect("asked for");
    let config = Config::load(&run_dir.join("config.toml"), &[]).unwrap();
    assert_eq!(
        polish["substeps"].as_u64(),
        config.sim.substeps.value().map(|n| n as u64),
        "{polish}"
    );
    assert_eq!(polish["uniform"][0].as_f64(), Some(baseline.k), "{polish}");
    assert_eq!(polish["uniform"][1].as_f64(), Some(baseline.b), "{polish}");
    let yardstick = baseline.train_rmse();
    assert_eq!(polish["uniform"][2].as_f64(), Some(yardstick), "{polish}");
    let after = polish["after"].as_f64().unwrap();
    assert!(
        after <= yardstick,
        "kept {after} m, the yardstick {yardstick} m"
    );
    // At the run's substeps the descent reaches the source's own uniform cloth (50 N/m, 6 N·s/m),
    // which the blend search, each candidate at its fewest substeps at a stability number of 1,
    // does not.
    assert_eq!(baseline.k, 50.0, "{polish}");
    assert!((baseline.b / 6.0 - 1.0).abs() < 0.1, "{polish}");
    assert!(after < 0.5 * record["after"].as_f64().unwrap(), "{record}");
    // The kept network, read back from the run, moves as the polish measured it on the takes.
    let kept = springtime::run::evaluate(
        &run_dir,
        Some(&dir.join("train")),
        None,
        &[],
        &Progress::quiet(),
    )
    .unwrap()
    .motion_rmse
    .mean;
    assert!(
        (kept - after).abs() <= 1e-6 * after,
        "the run's network moves {kept} m, the polish kept {after} m"
    );
    std::fs::remove_dir_all(&dir).ok();
}

/// Where the data does not state its drag, the run also tries spring damping proportional to
/// stiffness without drag after the drag search: on takes of a spring cloth damped by
/// `b = β k` with no drag (two stiffness levels, so its `b` follows its map; the run, with no
/// fit, stays uniform), the run keeps that damping, with the source's `β` within a factor of 2,
/// the drag at zero in its `config.toml` and every spring's `b / k` equal; it kept it because
/// the held-out takes agree ([`springtime::train::scale::held_out_agrees`]).
#[test]
fn the_run_finds_damping_proportional_to_stiffness() {
    use springtime::source::mass_spring::SpringCloth;

    let dir = common::temp_dir("blend-proportional");
    let beta = 0.04;
    let mut source = common::source(8, &[30.0, 90.0], 2.0);
    source.frame_stride = 10;
    source.save_velocities = false;
    let mut cloth = SpringCloth::from_config(&source);
    cloth.b = cloth.k.iter().map(|k| beta * k).collect();
    cloth.rayleigh = 0.0;
    save_takes(&dir, &cloth, &source, 1, false);
    let (run_dir, record) = blend_run_with(&dir, 50.0, 6.0, 2, "proportional_damping = true\n");
    let damping = &record["damping"];
    eprintln!("source β {beta}; proportional damping: {damping}");
    assert_eq!(damping["kept"].as_bool(), Some(true), "{damping}");
    let found = damping["beta"].as_f64().unwrap();
    assert!(
        (0.5..=2.0).contains(&(found / beta)),
        "β {found} against the source's {beta}: {damping}"
    );
    let held = &damping["held_out"];
    let pair = |i: usize| (held[i][0].as_f64().unwrap(), held[i][1].as_f64().unwrap());
    assert!(
        springtime::train::scale::held_out_agrees(pair(0), pair(1)),
        "{damping}"
    );
    let config = Config::load(&run_dir.join("config.toml"), &[]).unwrap();
    assert_eq!(config.sim.rayleigh.value(), Some(0.0));
    let npz = springtime::data::npz::Npz::read(&run_dir.join("springs.npz")).unwrap();
    let read = |key: &str| -> Vec<f64> {
        npz.f32(key, &[None])
            .unwrap()
            .0
            .iter()
            .map(|&x| x as f64)
            .collect()
    };
    for (k, b) in read("k").iter().zip(read("b")).filter(|(k, _)| **k > 0.0) {
        assert!(
            (b / k - found).abs() <= 1e-5 * found,
            "b {b} k {k}: b / k is not β {found}"
        );
    }
    std::fs::remove_dir_all(&dir).ok();
}

/// The viscosity search (`train.viscosity_search`) recovers an isotropic viscosity
/// proportional to stiffness: takes of an 8 × 8 spring cloth (30 and 90 N/m, `b` 0.5 N·s/m)
/// whose springs also damp their ends' whole relative velocity with `β k` (β = 0.01 s), no drag,
/// files that state no drag. The run keeps a viscosity within a factor of 2 of the source's, confirmed on its
/// held-out takes, and writes it (with no drag) to its `config.toml`.
#[test]
fn the_run_finds_a_viscosity_proportional_to_stiffness() {
    viscosity_recovered("blend-viscosity", 0.0, false);
}

/// Where the files state the source's drag (Blender's air damping beside its implicit solver's
/// damping), the viscosity is searched beside that drag, which the run keeps: on the same source
/// with a drag of 0.0625 N·s/m, stated, the held-out takes confirm a viscosity. Its `β` is not the
/// source's (4.5e-6 s against 0.01 s): the springs' `b`, sized by the polish beside the drag,
/// already carries the share of the damping the viscosity's takes along the springs.
#[test]
fn the_run_searches_a_viscosity_beside_the_drag_the_files_state() {
    let (record, config) = viscosity_run("blend-viscosity-drag", 0.0625, true);
    let viscosity = &record["viscosity"];
    assert_eq!(viscosity["kept"].as_bool(), Some(true), "{viscosity}");
    assert_eq!(config.sim.rayleigh.value(), Some(0.0625));
    assert_eq!(Some(config.sim.viscosity), viscosity["beta"].as_f64());
    // No drag was searched: the files state it.
    assert!(record["drag"].is_null(), "{record}");
}

/// [`the_run_finds_a_viscosity_proportional_to_stiffness`] on a source of drag `rayleigh`, whose
/// files state it where `state_drag`.
fn viscosity_recovered(name: &str, rayleigh: f64, state_drag: bool) {
    let (record, config) = viscosity_run(name, rayleigh, state_drag);
    let beta = VISCOSITY;
    let viscosity = &record["viscosity"];
    assert_eq!(viscosity["kept"].as_bool(), Some(true), "{viscosity}");
    let found = viscosity["beta"].as_f64().unwrap();
    assert!(
        (0.5..=2.0).contains(&(found / beta)),
        "β {found} against the source's {beta}: {viscosity}"
    );
    let held = &viscosity["held_out"];
    let pair = |i: usize| (held[i][0].as_f64().unwrap(), held[i][1].as_f64().unwrap());
    assert!(
        springtime::train::scale::held_out_agrees(pair(0), pair(1)),
        "{viscosity}"
    );
    assert_eq!(config.sim.rayleigh.value(), Some(rayleigh));
    assert_eq!(config.sim.viscosity, found);
}

/// The viscosity of the sources of [`viscosity_run`], s.
const VISCOSITY: f64 = 0.01;

/// A blend search with the viscosity search on takes of an 8 × 8 spring cloth (30 and 90 N/m,
/// `b` 0.5 N·s/m, drag `rayleigh`, stated in the files where `state_drag`) whose springs also
/// damp their ends' whole relative velocity with [`VISCOSITY`] `· k`: the run's `blend.json` and
/// `config.toml`.
fn viscosity_run(name: &str, rayleigh: f64, state_drag: bool) -> (serde_json::Value, Config) {
    use springtime::source::mass_spring::SpringCloth;

    let dir = common::temp_dir(name);
    let mut source = common::source(8, &[30.0, 90.0], 2.0);
    source.damping = 0.5;
    source.frame_stride = 10;
    source.save_velocities = false;
    // The drag the files state is the source's.
    source.rayleigh = rayleigh;
    let mut cloth = SpringCloth::from_config(&source);
    cloth.rayleigh = rayleigh;
    cloth.viscosity = VISCOSITY;
    save_takes(&dir, &cloth, &source, 1, state_drag);
    let (run_dir, record) = blend_run_with(&dir, 50.0, 6.0, 2, "viscosity_search = true\n");
    eprintln!(
        "source β {VISCOSITY}; viscosity search: {}",
        record["viscosity"]
    );
    let config = Config::load(&run_dir.join("config.toml"), &[]).unwrap();
    std::fs::remove_dir_all(&dir).ok();
    (record, config)
}

/// Where neither the data nor the config states the drag, the run searches it after the polish:
/// on takes of a uniform spring cloth whose files do not state their drag, the drag the run keeps
/// (and writes to its `config.toml`) is the source's within a factor of 2, a drag other than the
/// fitted one only where the held-out takes agree at both horizons; and from a drag eight times
/// the source's, the row of drags comes back to it.
#[test]
fn the_run_searches_a_drag_the_data_does_not_state() {
    let dir = common::temp_dir("blend-drag");
    let source = spring_cloth_takes(&dir, 1.0, false);
    let (run_dir, record) = blend_run_holding_out(&dir, 50.0, 6.0, 2);
    let drag = &record["drag"];
    eprintln!("source drag {}; drag search: {drag}", source.rayleigh);
    let kept = drag["kept"].as_f64().unwrap();
    let ratio = kept / source.rayleigh;
    assert!((0.5..=2.0).contains(&ratio), "kept drag {kept}: {drag}");
    assert!(drag["row"].as_array().unwrap().len() >= 8, "{drag}");
    let (fitted, best) = (
        drag["fitted"].as_f64().unwrap(),
        drag["best"].as_f64().unwrap(),
    );
    if kept != fitted {
        assert_eq!(kept, best, "{drag}");
        let held = &drag["held_out"];
        for horizon in 0..2 {
            assert!(
                held[1][horizon].as_f64() < held[0][horizon].as_f64(),
                "kept a drag the held-out takes do not prefer: {drag}"
            );
        }
    }
    let config = Config::load(&run_dir.join("config.toml"), &[]).unwrap();
    assert_eq!(
        config.sim.rayleigh.value(),
        Some(kept),
        "the run runs at the kept drag"
    );
    // From a drag eight times the source's, the row comes back to it.
    let run = springtime::run::Run::open(&run_dir, &[], None).unwrap();
    let train_files = run.config.data.split().unwrap().train;
    let first = springtime::data::Rollout::load(&train_files[0]).unwrap();
    let physics = springtime::sim::Physics {
        rayleigh: 8.0 * source.rayleigh,
        ..run.physics(first.frame_dt)
    };
    let progress = Progress::quiet();
    let takes = springtime::eval::Takes {
        topology: &run.topology,
        files: &train_files,
        batch: run.config.eval.batch,
        device: &run.device,
        progress: &progress,
        cache: None,
        objective: springtime::eval::Objective::WholeTake,
    };
    let row = springtime::train::scale::drag_row(run.springs().unwrap(), &physics, None, &takes);
    let found = row
        .iter()
        .min_by(|a, b| a.1.total_cmp(&b.1))
        .expect("a stable drag")
        .0;
    let ratio = found / source.rayleigh;
    assert!((0.5..=2.0).contains(&ratio), "from 8 ×: {row:?}");
    std::fs::remove_dir_all(&dir).ok();
}
