//! The command line end to end on a tiny cloth, and the errors bad input gets (never a panic).

mod common;

use common::{fails, ok, springtime};

use springtime::data::Rollout;
use springtime::data::npz::{Array, Npz};

/// The tiny config without its source, reading user data from `data_dir`.
fn user_data_config(data_dir: &str) -> String {
    let head = common::TINY.split("[source]").next().unwrap();
    let tail = common::TINY.split("[train]").nth(1).unwrap();
    format!(
        "{}[train]{tail}",
        head.replace("dir = \"data\"", &format!("dir = \"{data_dir}\""))
    )
}

/// Runs `springtime train tiny.toml` and then `extra` in `dir`.
fn train_tiny(extra: &[&str], dir: &std::path::Path) -> std::process::Output {
    let mut args = vec!["train", "tiny.toml"];
    args.extend_from_slice(extra);
    springtime(&args, dir)
}

fn setup(name: &str) -> common::TestDir {
    let dir = common::temp_dir(name);
    std::fs::write(dir.join("tiny.toml"), common::TINY).unwrap();
    dir
}

#[test]
fn train_eval_simulate_resume_and_refuse_to_overwrite() {
    let dir = setup("cli-flow");
    let out = ok(&train_tiny(&[], &dir));
    assert!(
        out.contains("rmse_k") && out.contains("motion RMSE"),
        "{out}"
    );
    let run = dir.join("runs/tiny");
    for f in [
        "config.toml",
        "run.json",
        "metrics.csv",
        "model.bpk",
        "springs.npz",
        "eval.json",
    ] {
        assert!(run.join(f).exists(), "missing {f}");
    }
    let metrics = std::fs::read_to_string(run.join("metrics.csv")).unwrap();
    assert_eq!(metrics.lines().count(), 1 + 15);
    let eval: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(run.join("eval.json")).unwrap()).unwrap();
    for key in ["mean", "std", "per_frame", "times"] {
        assert!(
            eval["motion_rmse"].get(key).is_some(),
            "eval.json lacks motion_rmse.{key}"
        );
    }
    for (horizon, seconds) in [("short", 0.8), ("long", 8.0)] {
        let h = &eval["motion_rmse"][horizon];
        assert_eq!(h["seconds"], seconds, "motion_rmse.{horizon}: {h}");
        assert!(h["mean"].as_f64().is_some() && h["std"].as_f64().is_some());
    }
    assert!(eval["rmse_k"].as_f64().is_some());
    assert!(
        out.contains("(≤ 0.8 s: ") && out.contains("; ≤ 8 s: "),
        "{out}"
    );
    // The printout and eval.json name the horizons the config sets, not the paper's.
    let out = ok(&springtime(
        &[
            "eval",
            "runs/tiny",
            "--set",
            "eval.short_seconds=0.1",
            "--set",
            "eval.long_seconds=0.2",
        ],
        &dir,
    ));
    assert!(
        out.contains("(≤ 0.1 s: ") && out.contains("; ≤ 0.2 s: "),
        "{out}"
    );
    let eval: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(run.join("eval.json")).unwrap()).unwrap();
    assert_eq!(eval["motion_rmse"]["long"]["seconds"], 0.2);
    assert_eq!(eval["precision"], "f32");
    // In f64 (a process of its own): the same run's figures over a short, unchaotic horizon
    // agree with f32's to its rounding, and eval.json says which it was.
    let short = |e: &serde_json::Value| e["motion_rmse"]["short"]["mean"].as_f64().unwrap();
    let out = ok(&springtime(
        &[
            "eval",
            "runs/tiny",
            "--precision",
            "f64",
            "--set",
            "eval.short_seconds=0.1",
        ],
        &dir,
    ));
    assert!(out.contains("(simulated in f64)"), "{out}");
    let eval64: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(run.join("eval.json")).unwrap()).unwrap();
    assert_eq!(eval64["precision"], "f64");
    let (e32, e64) = (short(&eval), short(&eval64));
    assert!(
        e64 != e32 && (e64 - e32).abs() < 1e-3 * e32,
        "{e32} vs {e64}"
    );
    fails(
        &springtime(
            &[
                "eval",
                "runs/tiny",
                "--precision",
                "f64",
                "--backend",
                "wgpu",
            ],
            &dir,
        ),
        &["--precision f64", "wgpu"],
    );
    // run.json names the build.
    let state: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(run.join("run.json")).unwrap()).unwrap();
    assert_eq!(state["springtime"]["version"], env!("CARGO_PKG_VERSION"));
    let commit = state["springtime"]["commit"].as_str().unwrap();
    assert!(
        commit == "unknown"
            || (commit.len() == 40 && commit.bytes().all(|b| b.is_ascii_hexdigit())),
        "{commit}"
    );

    // A finished run is not overwritten unless asked.
    fails(&train_tiny(&[], &dir), &["finished run", "--force"]);
    fails(&train_tiny(&["--resume"], &dir), &["already finished"]);

    // Resume: pretend the run stopped at its first checkpoint.
    let state_path = run.join("run.json");
    let mut state: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&state_path).unwrap()).unwrap();
    state["status"] = "running".into();
    state["checkpoint"] = 5.into();
    std::fs::write(&state_path, state.to_string()).unwrap();
    ok(&train_tiny(&["--resume", "--no-eval"], &dir));
    let metrics = std::fs::read_to_string(run.join("metrics.csv")).unwrap();
    let iterations: Vec<usize> = metrics
        .lines()
        .skip(1)
        .map(|l| l.split(',').next().unwrap().parse().unwrap())
        .collect();
    assert_eq!(
        iterations,
        (1..=15).collect::<Vec<_>>(),
        "each iteration once after resuming"
    );

    ok(&train_tiny(
        &[
            "--force",
            "--no-eval",
            "--set",
            "train.damping.iterations=1",
        ],
        &dir,
    ));

    // Simulate from a test rollout; the output is a valid rollout file.
    let init = dir.join("data/test_0000.npz");
    let simulate = || {
        springtime(
            &[
                "simulate",
                "runs/tiny",
                "--init",
                init.to_str().unwrap(),
                "--seconds",
                "0.1",
                "--out",
                "sim.npz",
            ],
            &dir,
        )
    };
    ok(&simulate());
    let sim = Rollout::load(&dir.join("sim.npz")).unwrap();
    assert_eq!((sim.frames, sim.landmarks), (101, 36));
    fails(&simulate(), &["sim.npz", "--force"]);
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn bad_configs_name_the_key() {
    let dir = setup("cli-config");
    std::fs::write(
        dir.join("typo.toml"),
        common::TINY.replace("[train]\n", "[train]\nlearning_rate = 1.0\n"),
    )
    .unwrap();
    fails(
        &springtime(&["train", "typo.toml"], &dir),
        &["typo.toml", "train", "learning_rate"],
    );
    std::fs::write(
        dir.join("type.toml"),
        common::TINY.replace("steps = 50", "steps = \"fifty\""),
    )
    .unwrap();
    fails(
        &springtime(&["train", "type.toml"], &dir),
        &["data.clips.steps"],
    );
    fails(
        &train_tiny(&["--set", "train.stiffness.batch=0"], &dir),
        &["train.stiffness.batch"],
    );
    fails(
        &train_tiny(&["--set", "train.damping.lr_decay=0"], &dir),
        &["train.damping.lr_decay"],
    );
    fails(
        &train_tiny(&["--set", "train.stiffness.lr_b=0.1"], &dir),
        &["train.stiffness.lr_b", "single pass"],
    );
    fails(
        &springtime(&["train", "missing.toml"], &dir),
        &["missing.toml"],
    );
    // Frame differences need three steps per clip: an error naming the key, not a panic.
    fails(
        &train_tiny(
            &[
                "--set",
                "train.force_on=frames",
                "--set",
                "data.clips.steps=2",
            ],
            &dir,
        ),
        &["train.force_on", "data.clips.steps"],
    );
    fails(&train_tiny(&["--backend", "cuda"], &dir), &["cuda"]);
    // A source that would blow up at its time step is refused with the largest stable step.
    fails(
        &springtime(
            &[
                "generate",
                "tiny.toml",
                "--set",
                "source.areal_density=0.0001",
            ],
            &dir,
        ),
        &["unstable", "largest stable dt", "allow_unstable"],
    );
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn bad_rollout_files_name_the_file_and_key() {
    let dir = setup("cli-data");
    ok(&springtime(&["generate", "tiny.toml"], &dir));
    let good = Npz::read(&dir.join("data/train_0000.npz")).unwrap();
    let user = dir.join("user");
    std::fs::create_dir_all(&user).unwrap();
    type Edit = Box<dyn Fn(&mut Npz)>;
    let cases: Vec<(&str, Edit, Vec<&str>)> = vec![
        (
            "nan",
            Box::new(|n: &mut Npz| {
                let (mut v, shape) = n.f32("positions", &[None, None, Some(3)]).unwrap();
                v[40] = f32::NAN;
                n.insert("positions", Array::f32(&shape, &v));
            }),
            vec!["nan.npz", "`positions`", "non-finite"],
        ),
        (
            "shape",
            Box::new(|n: &mut Npz| n.insert("rest_uv", Array::f32(&[36, 3], &[0.0; 108]))),
            vec!["shape.npz", "`rest_uv`", "shape"],
        ),
        (
            "missing",
            Box::new(|n: &mut Npz| drop(n.arrays.remove("total_mass"))),
            vec!["missing.npz", "`total_mass`"],
        ),
        (
            "outside",
            Box::new(|n: &mut Npz| {
                let (mut v, _) = n.f32("rest_uv", &[None, Some(2)]).unwrap();
                v[0] = -3.0;
                n.insert("rest_uv", Array::f32(&[36, 2], &v));
            }),
            vec!["outside.npz", "`rest_uv`", "outside"],
        ),
        (
            "dtype",
            Box::new(|n: &mut Npz| n.insert("pinned", Array::f32(&[36], &[0.0; 36]))),
            vec!["dtype.npz", "`pinned`", "dtype"],
        ),
    ];
    for (name, edit, needles) in cases {
        let case_dir = user.join(name);
        std::fs::create_dir_all(&case_dir).unwrap();
        let mut npz = good.clone();
        edit(&mut npz);
        npz.write(&case_dir.join(format!("{name}.npz"))).unwrap();
        std::fs::write(
            dir.join(format!("{name}.toml")),
            user_data_config(&format!("user/{name}")),
        )
        .unwrap();
        let out = springtime(&["train", &format!("{name}.toml"), "--no-eval"], &dir);
        fails(&out, &needles);
        assert!(
            !dir.join("runs/tiny").exists(),
            "a run that never started leaves no directory"
        );
    }
    // Not a zip at all.
    std::fs::create_dir_all(user.join("garbage")).unwrap();
    std::fs::write(user.join("garbage/garbage.npz"), b"not a zip").unwrap();
    std::fs::write(dir.join("garbage.toml"), user_data_config("user/garbage")).unwrap();
    fails(
        &springtime(&["train", "garbage.toml"], &dir),
        &["garbage.npz", "zip"],
    );
    // A directory with no rollouts and no source to make them.
    std::fs::create_dir_all(user.join("empty")).unwrap();
    std::fs::write(dir.join("empty.toml"), user_data_config("user/empty")).unwrap();
    fails(
        &springtime(&["train", "empty.toml"], &dir),
        &["user/empty", "no rollouts"],
    );
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn a_diverging_training_run_stops_with_a_clear_error_and_keeps_its_checkpoint() {
    let dir = setup("cli-diverge");
    let out = train_tiny(
        &[
            "--set",
            "train.stiffness.lr=1e5",
            "--set",
            "train.checkpoint_every=1",
            "--set",
            "train.project_stable=false",
        ],
        &dir,
    );
    fails(&out, &["loss became", "stiffness pass", "checkpoint"]);
    let state: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("runs/tiny/run.json")).unwrap())
            .unwrap();
    assert_eq!(state["status"], "failed");
    let ckpt = state["checkpoint"].as_u64().unwrap();
    assert!(ckpt >= 1, "a good checkpoint was kept");
    assert!(
        dir.join(format!("runs/tiny/checkpoints/model_{ckpt:06}.bpk"))
            .exists()
    );
    // The same learning rate with the projection on (the default) stays stable and finishes.
    let out = train_tiny(
        &["--force", "--no-report", "--set", "train.stiffness.lr=1e5"],
        &dir,
    );
    let text = ok(&out);
    assert!(text.contains("stability limit was active"), "{text}");
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn a_generating_config_never_writes_beside_someone_elses_rollouts() {
    let dir = setup("cli-foreign");
    ok(&springtime(&["generate", "tiny.toml"], &dir));
    // The user's own folder: one take of theirs, no index.json.
    let mine = dir.join("mine");
    std::fs::create_dir_all(&mine).unwrap();
    std::fs::copy(dir.join("data/train_0000.npz"), mine.join("my_take.npz")).unwrap();
    let out = train_tiny(&["--set", "data.dir=mine", "--no-eval"], &dir);
    fails(&out, &["mine", "my_take.npz", "[source]", "another folder"]);
    let left: Vec<_> = std::fs::read_dir(&mine)
        .unwrap()
        .map(|e| e.unwrap().file_name().into_string().unwrap())
        .collect();
    assert_eq!(
        left,
        ["my_take.npz"],
        "nothing written into the user's folder"
    );
    fails(
        &springtime(&["generate", "tiny.toml", "--set", "data.dir=mine"], &dir),
        &["my_take.npz"],
    );
    // An interrupted generation (its own files, no index yet) still resumes.
    std::fs::remove_file(dir.join("data/index.json")).unwrap();
    std::fs::remove_file(dir.join("data/test_0000.npz")).unwrap();
    ok(&springtime(&["generate", "tiny.toml"], &dir));
    assert!(dir.join("data/index.json").exists() && dir.join("data/test_0000.npz").exists());
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn a_plain_folder_of_takes_without_a_test_split_trains_and_says_how_to_evaluate() {
    let dir = setup("cli-no-test");
    ok(&springtime(&["generate", "tiny.toml"], &dir));
    // A user's folder: takes only, no index.json, a config naming only `data.dir`.
    let mine = dir.join("takes");
    std::fs::create_dir_all(&mine).unwrap();
    for i in 0..2 {
        let name = format!("train_{i:04}.npz");
        std::fs::copy(dir.join("data").join(&name), mine.join(&name)).unwrap();
    }
    std::fs::write(dir.join("mine.toml"), user_data_config("takes")).unwrap();
    let out = springtime(&["train", "mine.toml", "--no-report"], &dir);
    let text = ok(&out);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.contains("no test rollouts") && stderr.contains("springtime eval"),
        "{text}\n{stderr}"
    );
    assert!(!dir.join("runs/tiny/eval.json").exists());
    // The note's command evaluates it.
    let eval = ok(&springtime(&["eval", "runs/tiny", "--data", "data"], &dir));
    assert!(eval.contains("motion RMSE"), "{eval}");
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn held_out_training_takes_check_the_learned_network_against_the_best_uniform_one() {
    let dir = setup("cli-holdout");
    // Four training rollouts: the last one is held out of the fit.
    let out = train_tiny(&["--set", "data.holdout=1", "--no-report"], &dir);
    let text = ok(&out);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.contains("validation: on 1 held-out"), "{stderr}");
    assert!(text.contains("validation (`data.holdout`)"), "{text}");
    let v: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(dir.join("runs/tiny/validation.json")).unwrap(),
    )
    .unwrap();
    let rollouts = v["rollouts"].as_array().unwrap();
    assert_eq!(rollouts.len(), 1);
    assert!(
        rollouts[0].as_str().unwrap().ends_with("train_0003.npz"),
        "{v}"
    );
    let (trained, uniform) = (
        v["trained"]["long"]["mean"].as_f64().unwrap(),
        v["uniform"]["test"]["long"]["mean"].as_f64().unwrap(),
    );
    assert!(trained > 0.0 && uniform > 0.0, "{v}");
    let short = 1.0
        - v["trained"]["short"]["mean"].as_f64().unwrap()
            / v["uniform"]["test"]["short"]["mean"].as_f64().unwrap();
    assert_eq!(
        v["wins"].as_bool().unwrap(),
        short > 0.0 && 1.0 - trained / uniform > 0.0,
        "{v}"
    );
    let eval: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("runs/tiny/eval.json")).unwrap())
            .unwrap();
    assert_eq!(eval["validation"], v);
    // Holding out every training rollout is refused, naming the key.
    fails(
        &train_tiny(&["--set", "data.holdout=4", "--force"], &dir),
        &["`data.holdout`", "leave at least one"],
    );
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn a_second_training_process_on_the_same_run_refuses() {
    let dir = setup("cli-lock");
    let run = springtime::train::RunDir::new(dir.join("runs/tiny"));
    // Another process (this test) is training in runs/tiny.
    let held = run.lock().unwrap();
    fails(
        &train_tiny(&["--no-eval", "--no-report"], &dir),
        &["another springtime process", "runs/tiny", ".tiny.lock"],
    );
    assert!(
        !dir.join("runs/tiny/run.json").exists(),
        "the refused process wrote nothing"
    );
    // Once the holder is done, training goes ahead (and a lock of its own is released on exit).
    drop(held);
    ok(&train_tiny(&["--no-eval", "--no-report"], &dir));
    run.lock().expect("the finished process released its lock");
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn a_learned_network_the_held_out_takes_turn_down_gives_way_to_the_best_uniform_one() {
    let dir = setup("cli-fallback");
    // No training step: the learned network is its start, k 2 N/m, far softer than the
    // source's 10–100 N/m; the last training rollout is held out.
    let soft = [
        "--set",
        "data.holdout=1",
        "--set",
        "model.k_init=2",
        "--set",
        "train.stiffness.iterations=0",
        "--set",
        "train.damping.iterations=0",
        "--set",
        "eval.uniform_baseline=true",
        "--no-report",
    ];
    let k_of = |file: &str| {
        Npz::read(&dir.join("runs/tiny").join(file))
            .unwrap()
            .f32("k", &[None])
            .unwrap()
            .0
    };
    let read = |file: &str| -> serde_json::Value {
        serde_json::from_str(&std::fs::read_to_string(dir.join("runs/tiny").join(file)).unwrap())
            .unwrap()
    };
    let text = ok(&train_tiny(&soft, &dir));
    assert!(
        text.contains("the run keeps that uniform network"),
        "{text}"
    );
    let v = read("validation.json");
    assert_eq!(v["wins"], false, "{v}");
    assert_eq!(v["kept_uniform"], true, "{v}");
    for h in ["short", "long"] {
        assert!(
            v["uniform"]["test"][h]["mean"].as_f64().unwrap()
                < v["trained"][h]["mean"].as_f64().unwrap(),
            "{v}"
        );
    }
    // The run's springs are the uniform network's; the learned ones are kept beside them.
    let k = v["uniform"]["k"].as_f64().unwrap() as f32;
    assert!(k > 2.0, "{v}");
    assert!(k_of("springs.npz").iter().all(|&x| x == k), "{k}");
    assert!(k_of("springs.learned.npz").iter().all(|&x| x == 2.0));
    // `eval` simulates the kept network: the test takes' uniform baseline is the same network,
    // searched on the same training takes, so it moves exactly as far.
    let eval = read("eval.json");
    assert_eq!(
        eval["uniform_baseline"]["k"].as_f64().unwrap() as f32,
        k,
        "{text}"
    );
    for h in ["short", "long"] {
        assert_eq!(
            eval["motion_rmse"][h]["mean"], eval["uniform_baseline"]["test"][h]["mean"],
            "{h}: {text}"
        );
    }
    // Off, the learned network stays and says so.
    let mut kept = soft.to_vec();
    kept.extend(["--set", "train.uniform_fallback=false", "--force"]);
    let text = ok(&train_tiny(&kept, &dir));
    assert!(text.contains("does NOT beat"), "{text}");
    assert_eq!(read("validation.json")["kept_uniform"], false);
    assert!(k_of("springs.npz").iter().all(|&x| x == 2.0));
    assert!(!dir.join("runs/tiny/springs.learned.npz").exists());
    std::fs::remove_dir_all(&dir).ok();
}

/// `k`, `b` of a finished run's `springs.npz`.
fn learned(run: &std::path::Path) -> (Vec<f32>, Vec<f32>) {
    let npz = Npz::read(&run.join("springs.npz")).unwrap();
    (
        npz.f32("k", &[None]).unwrap().0,
        npz.f32("b", &[None]).unwrap().0,
    )
}

#[test]
fn a_run_killed_with_sigkill_resumes_to_the_uninterrupted_result() {
    let dir = setup("cli-kill");
    let long = [
        "--no-eval",
        "--no-report",
        "--set",
        "train.stiffness.iterations=1000",
        "--set",
        "train.damping.iterations=20",
        "--set",
        "train.checkpoint_every=5",
    ];
    // The uninterrupted reference.
    let mut args = vec!["train", "tiny.toml", "--out", "runs/whole"];
    args.extend_from_slice(&long);
    ok(&springtime(&args, &dir));
    // The same job, killed (SIGKILL: no chance to clean up) once its first checkpoint is on disk.
    let mut args = vec!["train", "tiny.toml", "--out", "runs/killed"];
    args.extend_from_slice(&long);
    let mut child = std::process::Command::new(env!("CARGO_BIN_EXE_springtime"))
        .args(&args)
        .current_dir(&dir)
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let state = dir.join("runs/killed/run.json");
    common::kill_after_checkpoint(&mut child, &state, 5);
    let killed: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&state).unwrap()).unwrap();
    assert_eq!(killed["status"], "running", "killed mid-run: {killed}");
    // The lock died with the process: --resume finishes the run.
    let mut args = vec!["train", "tiny.toml", "--out", "runs/killed", "--resume"];
    args.extend_from_slice(&long);
    ok(&springtime(&args, &dir));
    let (whole, resumed) = (
        learned(&dir.join("runs/whole")),
        learned(&dir.join("runs/killed")),
    );
    assert_eq!(
        whole, resumed,
        "resumed after SIGKILL ≠ uninterrupted (same seed, flex)"
    );
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn a_run_with_curvature_elements_learns_saves_reloads_and_exports_them() {
    let dir = setup("cli-curvature");
    let out = ok(&train_tiny(&["--set", "cloth.curvature=true"], &dir));
    let run = dir.join("runs/tiny");
    assert!(run.join("report/curvature_map.png").exists(), "{out}");
    let npz = Npz::read(&run.join("springs.npz")).unwrap();
    let (ends, shape) = npz.int("curvature", &[None, Some(3)]).unwrap();
    // 6 rows of 4 elements, 4 interior rows of 6 columns, 4 × 4 interior particles × 2 diagonals.
    assert_eq!(shape, [80, 3], "{out}");
    assert_eq!(&ends[..3], &[0, 1, 2]);
    let kappa = npz.f32("curvature_k", &[Some(80)]).unwrap().0;
    let model: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(run.join("defaults.json")).unwrap()).unwrap();
    let k_init = model["k_init"].as_f64().unwrap() as f32;
    // The stiffness pass moved κ from `k_init / 20`, and kept it non-negative.
    assert!(
        kappa.iter().all(|&v| v >= 0.0) && kappa.iter().any(|&v| (v - k_init / 20.0).abs() > 1e-3),
        "κ {kappa:?} from {}",
        k_init / 20.0
    );
    // eval reloads the run with its elements: the same figure as training's evaluation.
    let motion = |text: &str| {
        text.lines()
            .find(|l| l.starts_with("motion RMSE"))
            .unwrap_or_default()
            .to_string()
    };
    let again = ok(&springtime(&["eval", "runs/tiny"], &dir));
    assert_eq!(motion(&again), motion(&out));
    assert!(!motion(&out).is_empty(), "{out}");
    ok(&springtime(&["export", "runs/tiny", "--out", "e"], &dir));
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("e/surrogate.json")).unwrap())
            .unwrap();
    // A reader of the first format, which knows springs only, must not take it for one.
    assert_eq!(json["format"], "springtime-surrogate/2");
    assert_eq!(json["curvature"].as_array().unwrap().len(), 80);
    assert_eq!(json["curvature_k"].as_array().unwrap().len(), 80);
    // Curvature elements live on a grid.
    fails(
        &train_tiny(
            &[
                "--out",
                "runs/mesh",
                "--set",
                "cloth.curvature=true",
                "--set",
                "cloth.layout=\"data\"",
            ],
            &dir,
        ),
        &["cloth.curvature", "cloth.layout"],
    );
}

/// A run with the springs' viscosity (`sim.viscosity`) trains through the fused rollout with it,
/// keeps it in its `config.toml`, and `eval` reloads it (the same figure as training's
/// evaluation, which differs from the same run's without it); `export` writes it into
/// `surrogate.json` and `surrogate.npz`, and the latent pipeline, which has none, refuses it.
#[test]
fn a_run_with_a_viscosity_keeps_it_and_exports_it() {
    let dir = setup("cli-viscosity");
    let motion = |text: &str| {
        text.lines()
            .find(|l| l.starts_with("motion RMSE"))
            .unwrap_or_default()
            .to_string()
    };
    let out = ok(&train_tiny(&["--set", "sim.viscosity=2e-3"], &dir));
    let config = <springtime::config::Config as springtime::settings::Job>::load(
        &dir.join("runs/tiny/config.toml"),
        &[],
    )
    .unwrap();
    assert_eq!(config.sim.viscosity, 2e-3);
    let again = ok(&springtime(&["eval", "runs/tiny"], &dir));
    assert!(!motion(&out).is_empty(), "{out}");
    assert_eq!(motion(&again), motion(&out));
    let plain = ok(&train_tiny(&["--out", "runs/plain"], &dir));
    assert_ne!(
        motion(&plain),
        motion(&out),
        "the viscosity changed nothing"
    );
    // The export carries it under its own format tag (an older reader refuses the file rather
    // than step it without the viscosity); the latent pipeline, which has none, refuses it.
    ok(&springtime(&["export", "runs/tiny", "--out", "e"], &dir));
    let json = springtime::export::SurrogateJson::read(&dir.join("e/surrogate.json")).unwrap();
    assert_eq!(json.viscosity, 2e-3);
    assert_eq!(json.format, springtime::export::FORMAT_VISCOSITY);
    let npz = Npz::read(&dir.join("e/surrogate.npz")).unwrap();
    assert_eq!(npz.scalar("viscosity").unwrap(), 2e-3);
    ok(&springtime(&["export", "runs/plain", "--out", "p"], &dir));
    let plain = springtime::export::SurrogateJson::read(&dir.join("p/surrogate.json")).unwrap();
    assert_eq!(plain.format, springtime::export::FORMAT);
    assert!(
        !std::fs::read_to_string(dir.join("p/surrogate.json"))
            .unwrap()
            .contains("viscosity"),
        "a surrogate without a viscosity is written as before"
    );
    let Err(err) = springtime::latent::surrogate::SpringSheet::open(&dir.join("runs/tiny")) else {
        panic!("the latent pipeline took a run with a viscosity");
    };
    assert!(format!("{err:#}").contains("viscosity"), "{err:#}");
}
