//! `springtime diagnose`: the chaos floor on a tiny spring cloth, the command end to end, and
//! the App. C.2 ablation configs running through the command line on tiny data.

mod common;

use common::{fails, ok, springtime};
use springtime::settings::Job;

use burn::tensor::Device;
use springtime::cloth::Resampler;
use springtime::config::Config;
use springtime::data::Track;
use springtime::diagnose::{self, Inputs};
use springtime::eval::TestTrack;
use springtime::model::SpringNet;
use springtime::progress::Progress;
use springtime::train;

#[test]
fn chaos_floor_is_zero_at_level_zero_and_grows_with_the_level() {
    // A 6 × 6 mass-spring cloth with three stiffness stripes, two 0.4 s test rollouts.
    let cfg = common::source(6, &[10.0, 50.0, 100.0], 0.4);
    let topo = common::grid_of(&cfg);
    let mut tests = Vec::new();
    let mut truth = None;
    let mut mass = 0.0;
    for seed in [1, 2] {
        let (cloth, r) = common::rollout(&cfg, seed);
        let res = Resampler::new(&r.rest_uv, &topo.rest_uv);
        truth = train::matching_truth(r.springs.as_ref().unwrap(), &topo, &res);
        mass = cloth.mass;
        tests.push(TestTrack {
            path: format!("memory_{seed}").into(),
            track: Track::new(&r, &res),
            first: 0,
            frame_dt: r.frame_dt,
        });
    }
    let truth = truth.expect("the source's springs are the surrogate's");
    let device = Device::flex();
    let inputs = Inputs {
        config: Config::parse(
            "name = \"chaos\"\n[eval]\nshort_seconds = 0.1\nlong_seconds = 0.4\n",
            &[],
        )
        .unwrap(),
        // A learned model 10 % off: the floor must use the truth, not this.
        model: SpringNet::new(
            &topo,
            &truth.0.iter().map(|k| 1.1 * k).collect::<Vec<_>>(),
            &truth.1,
            &device,
        ),
        topology: topo,
        mass,
        truth: Some(truth),
        tests,
        device,
    };
    let levels = diagnose::chaos::levels(&[0.02, 0.005, 0.01]).unwrap();
    let floor = diagnose::chaos::chaos_floor(&inputs, &levels, 0, &Progress::quiet()).unwrap();
    assert_eq!(floor.reference, "truth");
    assert_eq!(floor.levels.len(), 4);
    assert_eq!(floor.times.len(), 400);
    assert!((floor.times[399] - 0.4).abs() < 1e-9);
    let zero = &floor.levels[0];
    assert_eq!(zero.level, 0.0);
    assert!(
        zero.per_frame_mean.iter().all(|&e| e == 0.0),
        "level 0 must reproduce the reference exactly"
    );
    assert_eq!(
        (zero.mean_short, zero.mean_long, zero.at_end),
        (0.0, 0.0, 0.0)
    );
    for w in floor.levels.windows(2) {
        assert!(
            w[1].at_end > w[0].at_end && w[1].mean_long > w[0].mean_long,
            "the floor grows with the level: {} at {} vs {} at {}",
            w[0].at_end,
            w[0].level,
            w[1].at_end,
            w[1].level
        );
    }
    // Small enough to be a floor: well below the cloth's size.
    assert!(floor.levels[3].at_end < 0.05, "{}", floor.levels[3].at_end);
    // Same seed, same floor; another seed, another draw.
    let again = diagnose::chaos::chaos_floor(&inputs, &levels, 0, &Progress::quiet()).unwrap();
    assert_eq!(again.levels, floor.levels);
    let other = diagnose::chaos::chaos_floor(&inputs, &levels, 5, &Progress::quiet()).unwrap();
    assert_ne!(other.levels[3].at_end, floor.levels[3].at_end);
}

#[test]
fn diagnose_end_to_end_and_refuses_to_overwrite() {
    let dir = common::temp_dir("diagnose-cli");
    // The shared tiny job with two test rollouts: the error map lists one row per rollout.
    let tiny = common::TINY.replace("test_rollouts = 1", "test_rollouts = 2");
    std::fs::write(dir.join("tiny.toml"), tiny).unwrap();
    ok(&springtime(&["train", "tiny.toml", "--no-report"], &dir));
    let out = ok(&springtime(&["diagnose", "runs/tiny"], &dir));
    assert!(
        out.contains("chaos floor") && out.contains("observability") && out.contains("worst"),
        "the headline table is printed: {out}"
    );
    let diag = dir.join("runs/tiny/diagnose");
    for f in diagnose::FILES {
        // The mass-spring source writes no stiffness map: no source-map reference, and a note.
        assert_eq!(diag.join(f).exists(), f != "source_map.json", "{f}");
    }
    assert!(out.contains("no source-map reference"), "{out}");
    let json = |f: &str| -> serde_json::Value {
        serde_json::from_str(&std::fs::read_to_string(diag.join(f)).unwrap()).unwrap()
    };
    let chaos = json("chaos.json");
    assert_eq!(chaos["reference"], "truth");
    let levels = chaos["levels"].as_array().unwrap();
    assert_eq!(levels.len(), 4);
    for key in [
        "level",
        "per_frame_mean",
        "mean_short",
        "mean_long",
        "at_end",
    ] {
        assert!(levels[1].get(key).is_some(), "chaos.json levels lack {key}");
    }
    assert_eq!(levels[0]["at_end"].as_f64(), Some(0.0));
    for key in ["times", "short_seconds", "long_seconds"] {
        assert!(chaos.get(key).is_some(), "chaos.json lacks {key}");
    }
    let obs = json("observability.json");
    let springs = obs["obs_k"].as_array().unwrap().len();
    assert!(springs > 0 && obs["obs_b"].as_array().unwrap().len() == springs);
    for key in ["families", "extremes_k", "extremes_b", "clips", "frames"] {
        assert!(obs.get(key).is_some(), "observability.json lacks {key}");
    }
    assert!(obs["truth"]["k"].get("spearman").is_some());
    assert!(obs["truth"]["b"]["least_observable"]["mean_error_rest"].is_number());
    let err = json("error_map.json");
    assert_eq!(err["rollouts"].as_array().unwrap().len(), 2);
    assert_eq!(err["per_particle"].as_array().unwrap().len(), 36);
    for key in ["mean_short", "mean_long", "at_end", "name"] {
        assert!(
            err["rollouts"][0].get(key).is_some(),
            "error_map.json lacks {key}"
        );
    }
    assert!(err["motion"]["long"]["mean"].as_f64().unwrap() > 0.0);
    let md = std::fs::read_to_string(diag.join("diagnose.md")).unwrap();
    assert!(md.contains("| quantity | value |"));

    // An existing diagnosis is kept unless --force.
    let before = std::fs::read_to_string(diag.join("chaos.json")).unwrap();
    fails(
        &springtime(&["diagnose", "runs/tiny", "--levels", "0.05"], &dir),
        &["diagnose", "--force"],
    );
    assert_eq!(
        std::fs::read_to_string(diag.join("chaos.json")).unwrap(),
        before
    );
    ok(&springtime(
        &[
            "diagnose",
            "runs/tiny",
            "--force",
            "--levels",
            "0.05",
            "--seed",
            "3",
        ],
        &dir,
    ));
    assert_eq!(json("chaos.json")["levels"].as_array().unwrap().len(), 2);
    // --out elsewhere; bad levels are an error, not a panic.
    ok(&springtime(
        &["diagnose", "runs/tiny", "--out", "elsewhere"],
        &dir,
    ));
    assert!(dir.join("elsewhere/diagnose.md").exists());
    fails(
        &springtime(&["diagnose", "runs/tiny", "--force", "--levels=-0.1"], &dir),
        &["--levels"],
    );
    fails(
        &springtime(&["diagnose", "runs/none"], &dir),
        &["runs/none"],
    );
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn the_sources_own_map_beats_the_best_uniform_network_on_a_striped_fem_sheet() {
    // An FEM sheet of three stripes 1 : 4 : 10, learned by no pass at all (the surrogate is the
    // initial uniform network): `diagnose` sizes the source's own map on the structural springs.
    let dir = common::temp_dir("diagnose-source-map");
    let job = common::FEM_4X4
        .replace("nx = 4\nny = 4", "nx = 7\nny = 7")
        .replace(
            "stiffness_levels = [300.0]",
            "stiffness_levels = [100.0, 400.0, 1000.0]",
        )
        .replace("layout = \"uniform\"", "layout = \"stripes\"")
        .replace("seconds = 0.3", "seconds = 0.6")
        .replace(
            "train_rollouts = 3\ntest_rollouts = 1",
            "train_rollouts = 4\ntest_rollouts = 2",
        )
        .replace("iterations = 4", "iterations = 0")
        .replace("iterations = 2", "iterations = 0");
    let job = format!(
        "name = \"fem\"\n{job}\n[data]\ndir = \"data\"\n[eval]\nuniform_baseline = true\nshort_seconds = 0.2\nlong_seconds = 0.6\n"
    );
    assert_eq!(job.matches("nx = 7").count(), 2, "{job}");
    std::fs::write(dir.join("fem.toml"), job).unwrap();
    ok(&springtime(&["train", "fem.toml", "--no-report"], &dir));
    let out = ok(&springtime(&["diagnose", "runs/fem"], &dir));
    assert!(
        out.contains("the source's own stiffness map, sized"),
        "{out}"
    );
    let text = std::fs::read_to_string(dir.join("runs/fem/diagnose/source_map.json")).unwrap();
    let c: diagnose::SourceMap = serde_json::from_str(&text).unwrap();
    assert_eq!(c.start, "uniform_baseline");
    // Every structural and shear spring of the 7 × 7 grid follows the map.
    assert_eq!(c.springs, 2 * 7 * 6 + 2 * 6 * 6);
    // The search keeps the best it tried: never worse than where it started.
    assert!(c.search.after <= c.search.before.unwrap(), "{:?}", c.search);
    assert!(c.bending_search.iter().any(|&(f, _)| f == c.bending_factor));
    // The right map, sized, moves closer to the sheet than any one stiffness does.
    assert!(
        c.gain_short > 0.0 && c.gain_long > 0.0,
        "{} / {}: map {:?}, uniform {:?}",
        c.gain_short,
        c.gain_long,
        c.map.long.mean,
        c.uniform.test.long.mean
    );
    std::fs::remove_dir_all(&dir).ok();
}

/// `--set`s that shrink a Fig. 7 config to a 6 × 6 cloth, 0.3 s rollouts and 2 iterations.
const SHRINK: &[&str] = &[
    "cloth.nx=6",
    "cloth.ny=6",
    "source.nx=6",
    "source.ny=6",
    "source.width=2.5",
    "source.height=2.5",
    "source.seconds=0.3",
    "source.train_rollouts=3",
    "source.test_rollouts=1",
    "source.storage=\"full\"",
    "data.dir=\"data\"",
    "data.clips.steps=50",
    "data.clips.fraction=1.0",
    "data.clips.low_velocity_fraction=1.0",
    "train.stiffness.iterations=2",
    "train.damping.iterations=2",
    "train.single.iterations=2",
    "train.stiffness.batch=2",
    "train.damping.batch=2",
    "train.single.batch=2",
];

#[test]
fn ablation_configs_train_through_the_command_line() {
    let dir = common::temp_dir("ablations");
    let configs = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("configs");
    for (name, pass) in [
        ("ablation_single_pass", "single"),
        ("ablation_position_loss", "stiffness"),
    ] {
        let config = configs.join(format!("{name}.toml"));
        let mut args = vec![
            "train".to_string(),
            config.display().to_string(),
            "--out".into(),
            format!("runs/{name}"),
            "--no-report".into(),
        ];
        for s in SHRINK {
            args.push("--set".into());
            args.push(s.to_string());
        }
        let args: Vec<&str> = args.iter().map(String::as_str).collect();
        let out = ok(&springtime(&args, &dir));
        assert!(out.contains("motion RMSE"), "{out}");
        let metrics =
            std::fs::read_to_string(dir.join(format!("runs/{name}/metrics.csv"))).unwrap();
        assert!(
            metrics.lines().skip(1).any(|l| l.contains(pass)),
            "{name} trains a {pass} pass: {metrics}"
        );
        let resolved =
            std::fs::read_to_string(dir.join(format!("runs/{name}/config.toml"))).unwrap();
        let c = Config::parse(&resolved, &[]).unwrap();
        if name == "ablation_single_pass" {
            assert_eq!(c.train.mode, springtime::train::Mode::Single);
            assert_eq!(metrics.lines().count(), 1 + 2);
        } else {
            let w = &c.train.stiffness.weights;
            assert_eq!(
                (w.force, w.impulse, w.position, w.k_neg),
                (0.0, 0.0, 1.0, 100.0)
            );
            assert_eq!(c.train.damping.weights.force, 1.0);
            assert_eq!(metrics.lines().count(), 1 + 4);
        }
    }
    // `train.single.lr_b` steps b at a rate of its own: at 0, b stays at its initial 3 N·s/m
    // while k learns.
    let config = configs.join("ablation_single_pass.toml");
    let mut args = vec![
        "train".to_string(),
        config.display().to_string(),
        "--out".into(),
        "runs/single_lr_b0".into(),
        "--no-report".into(),
        "--set".into(),
        "train.single.lr_b=0.0".into(),
    ];
    for s in SHRINK {
        args.push("--set".into());
        args.push(s.to_string());
    }
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    ok(&springtime(&args, &dir));
    let springs =
        springtime::data::npz::Npz::read(&dir.join("runs/single_lr_b0/springs.npz")).unwrap();
    let (k, _) = springs.f64("k", &[None]).unwrap();
    let (b, _) = springs.f64("b", &[None]).unwrap();
    assert!(
        b.iter().all(|&v| (v - 3.0).abs() < 1e-6),
        "b moved: {:?}",
        &b[..4]
    );
    assert!(k.iter().any(|&v| (v - 50.0).abs() > 1e-3), "k did not move");
    std::fs::remove_dir_all(&dir).ok();
}
