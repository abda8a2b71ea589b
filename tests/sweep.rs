//! Sweeps and sharded generation end to end: `springtime sweep PLAN --list | --index | --gather`
//! and `springtime generate CONFIG --shard i/n`.

mod common;

use std::path::Path;
use std::process::{Command, Stdio};

use common::{fails, ok, springtime};
use springtime::data::npz::Npz;

/// A scratch folder with `tiny.toml` and `plan.toml` (three values of `model.k_init` after a
/// `set` of its own, `extra` appended).
fn setup(name: &str, extra: &str) -> common::TestDir {
    let dir = common::temp_dir(name);
    std::fs::write(dir.join("tiny.toml"), common::TINY).unwrap();
    std::fs::write(
        dir.join("plan.toml"),
        format!(
            "base = \"tiny.toml\"\nset = [\"train.damping.iterations=4\"]\n{extra}\n[axes]\n\
             \"model.k_init\" = [40.0, 60.0, 80.0]\n"
        ),
    )
    .unwrap();
    dir
}

/// The figures of a finished job: learned `k` and `b`, and the evaluation's motion RMSE.
fn figures(job: &Path) -> (Vec<f32>, Vec<f32>, f64, f64) {
    let npz = Npz::read(&job.join("springs.npz")).unwrap();
    let eval: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(job.join("eval.json")).unwrap()).unwrap();
    (
        npz.f32("k", &[None]).unwrap().0,
        npz.f32("b", &[None]).unwrap().0,
        eval["motion_rmse"]["short"]["mean"].as_f64().unwrap(),
        eval["motion_rmse"]["long"]["mean"].as_f64().unwrap(),
    )
}

fn spawn(args: &[&str], cwd: &Path) -> std::process::Child {
    Command::new(env!("CARGO_BIN_EXE_springtime"))
        .args(args)
        .current_dir(cwd)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap()
}

#[test]
fn list_pins_the_order_and_the_overrides() {
    let dir = setup("sweep-list", "");
    let out = ok(&springtime(&["sweep", "plan.toml", "--list"], &dir));
    let lines: Vec<&str> = out.lines().collect();
    assert_eq!(
        lines,
        [
            "0\t0-k_init-40.0\ttrain.damping.iterations=4 model.k_init=40.0",
            "1\t1-k_init-60.0\ttrain.damping.iterations=4 model.k_init=60.0",
            "2\t2-k_init-80.0\ttrain.damping.iterations=4 model.k_init=80.0",
        ]
    );
    fails(
        &springtime(&["sweep", "plan.toml", "--index", "3"], &dir),
        &["--index", "3 jobs"],
    );
    fails(
        &springtime(&["sweep", "nope.toml", "--list"], &dir),
        &["nope.toml"],
    );
}

#[test]
fn two_processes_give_the_files_of_one_and_gather_lists_the_missing() {
    let dir = setup("sweep-two", "");
    // Jobs 0 and 1 in one process, into `one`.
    let out = ok(&springtime(
        &["sweep", "plan.toml", "--index", "0,1", "--out", "one"],
        &dir,
    ));
    assert!(out.contains("job 0: finished") && out.contains("job 1: finished"));
    // The same jobs in two processes at once, into `two`, each starting from a fresh data folder
    // that both need: one generates it while the other waits.
    std::fs::remove_dir_all(dir.join("data")).unwrap();
    let a = spawn(
        &["sweep", "plan.toml", "--index", "0", "--out", "two"],
        &dir,
    );
    let b = spawn(
        &["sweep", "plan.toml", "--index", "1", "--out", "two"],
        &dir,
    );
    for child in [a, b] {
        ok(&child.wait_with_output().unwrap());
    }
    for job in ["0-k_init-40.0", "1-k_init-60.0"] {
        let (one, two) = (dir.join("one").join(job), dir.join("two").join(job));
        assert_eq!(figures(&one), figures(&two), "{job}: one process ≠ two");
        // (`model.bpk` holds Burn's random parameter ids besides the values: not compared.)
        for file in ["springs.npz", "config.toml"] {
            assert!(
                std::fs::read(one.join(file)).unwrap() == std::fs::read(two.join(file)).unwrap(),
                "{job}/{file}: one process ≠ two"
            );
        }
    }
    // The two jobs learned different networks (the axis reached the config).
    assert_ne!(
        figures(&dir.join("one/0-k_init-40.0")).0,
        figures(&dir.join("one/1-k_init-60.0")).0
    );
    // A finished job is skipped.
    let again = ok(&springtime(
        &["sweep", "plan.toml", "--index", "1", "--out", "two"],
        &dir,
    ));
    assert!(again.contains("job 1: already finished"), "{again}");
    // Gather: job 2 was never run.
    let g = ok(&springtime(
        &["sweep", "plan.toml", "--gather", "--out", "two"],
        &dir,
    ));
    assert!(
        g.contains("2 finished, 0 failed, 0 unfinished, 1 missing"),
        "{g}"
    );
    assert!(g.contains("missing: 2"), "{g}");
    let mut csv = csv::Reader::from_path(dir.join("two/sweep.csv")).unwrap();
    let header: Vec<String> = csv.headers().unwrap().iter().map(String::from).collect();
    for column in [
        "index",
        "model.k_init",
        "status",
        "rmse_k",
        "rmse_b",
        "motion_rmse_long",
    ] {
        assert!(header.iter().any(|h| h == column), "no column {column}");
    }
    let col = |name: &str| header.iter().position(|h| h == name).unwrap();
    let rows: Vec<csv::StringRecord> = csv.records().map(Result::unwrap).collect();
    assert_eq!(rows.len(), 3);
    assert_eq!(&rows[2][col("status")], "missing");
    assert_eq!(&rows[1][col("model.k_init")], "60.0");
    let long: f64 = rows[0][col("motion_rmse_long")].parse().unwrap();
    assert_eq!(long, figures(&dir.join("two/0-k_init-40.0")).3);
    assert!(dir.join("two/sweep.md").is_file() && dir.join("two/sweep.png").is_file());
}

#[test]
fn a_failed_job_is_recorded_and_the_others_run() {
    let dir = common::temp_dir("sweep-failed");
    std::fs::write(dir.join("tiny.toml"), common::TINY).unwrap();
    std::fs::write(
        dir.join("plan.toml"),
        "base = \"tiny.toml\"\n[axes]\n\"model.k_init\" = [-1.0, 50.0]\n",
    )
    .unwrap();
    fails(
        &springtime(&["sweep", "plan.toml", "--index", "0-1"], &dir),
        &["1 job(s) failed: 0", "k_init"],
    );
    let g = ok(&springtime(&["sweep", "plan.toml", "--gather"], &dir));
    assert!(g.contains("1 finished, 1 failed"), "{g}");
    assert!(g.contains("failed: 0"), "{g}");
    let md = std::fs::read_to_string(dir.join("runs/plan/sweep.md")).unwrap();
    assert!(md.contains("Job 0 failed") && md.contains("k_init"), "{md}");
}

#[test]
fn a_killed_job_resumes_to_the_uninterrupted_figures() {
    let dir = setup(
        "sweep-kill",
        "set = [\"train.stiffness.iterations=1000\", \"train.damping.iterations=20\"]",
    );
    // `set` is given twice by setup + extra: keep the last (the plan above has one `set`).
    let plan = std::fs::read_to_string(dir.join("plan.toml"))
        .unwrap()
        .replace("set = [\"train.damping.iterations=4\"]\n", "");
    std::fs::write(dir.join("plan.toml"), plan).unwrap();
    ok(&springtime(
        &["sweep", "plan.toml", "--index", "0", "--out", "whole"],
        &dir,
    ));
    let mut child = spawn(
        &["sweep", "plan.toml", "--index", "0", "--out", "killed"],
        &dir,
    );
    let state = dir.join("killed/0-k_init-40.0/run.json");
    common::kill_after_checkpoint(&mut child, &state, 5);
    let g = ok(&springtime(
        &["sweep", "plan.toml", "--gather", "--out", "killed"],
        &dir,
    ));
    assert!(g.contains("unfinished: 0"), "{g}");
    let out = ok(&springtime(
        &["sweep", "plan.toml", "--index", "0", "--out", "killed"],
        &dir,
    ));
    assert!(
        out.contains("job 0: finished") && out.contains("(resumed)"),
        "{out}"
    );
    assert_eq!(
        figures(&dir.join("whole/0-k_init-40.0")),
        figures(&dir.join("killed/0-k_init-40.0")),
        "resumed ≠ uninterrupted"
    );
}

#[test]
fn shards_together_are_the_unsharded_generation_byte_for_byte() {
    let dir = common::temp_dir("sweep-shards");
    std::fs::write(dir.join("tiny.toml"), common::TINY).unwrap();
    let set_dir = |d: &str| format!("data.dir=\"{d}\"");
    ok(&springtime(
        &["generate", "tiny.toml", "--set", &set_dir("whole")],
        &dir,
    ));
    let first = ok(&springtime(
        &[
            "generate",
            "tiny.toml",
            "--shard",
            "1/3",
            "--set",
            &set_dir("sharded"),
        ],
        &dir,
    ));
    assert!(first.contains("index.json waits"), "{first}");
    assert!(!dir.join("sharded/index.json").exists());
    for shard in ["2/3", "0/3"] {
        ok(&springtime(
            &[
                "generate",
                "tiny.toml",
                "--shard",
                shard,
                "--set",
                &set_dir("sharded"),
            ],
            &dir,
        ));
    }
    let names = |d: &str| {
        let mut n: Vec<String> = std::fs::read_dir(dir.join(d))
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        n.sort();
        n
    };
    assert_eq!(names("whole"), names("sharded"));
    assert_eq!(names("whole").len(), 6, "5 rollouts and index.json");
    for name in names("whole") {
        assert!(
            std::fs::read(dir.join("whole").join(&name)).unwrap()
                == std::fs::read(dir.join("sharded").join(&name)).unwrap(),
            "{name}: sharded ≠ unsharded"
        );
    }
    fails(
        &springtime(&["generate", "tiny.toml", "--shard", "3/3"], &dir),
        &["--shard", "i/n"],
    );
}

#[test]
fn the_shipped_plans_expand_into_loadable_configs() {
    let dir = std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("configs/sweeps");
    let mut seen = 0;
    for entry in std::fs::read_dir(&dir).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().is_none_or(|e| e != "toml") {
            continue;
        }
        let plan = springtime::sweep::Plan::load(&path).unwrap();
        let jobs = plan.jobs().unwrap();
        assert!(!jobs.is_empty(), "{}", path.display());
        for job in &jobs {
            plan.config(job)
                .unwrap_or_else(|e| panic!("{}: {e:#}", path.display()));
        }
        seen += 1;
    }
    assert!(seen >= 2, "configs/sweeps/ holds the example plans");
}
