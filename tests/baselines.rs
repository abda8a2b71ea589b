//! The baselines end to end through the command line: each overfits one short clip, and
//! `springtime compare` trains the three families on the same data, writes its table and figure,
//! and reuses finished runs.

mod common;

use common::{ok, springtime};

use std::path::Path;

/// One 6 × 6 rollout of 15 ms: a single clip of 15 steps to train on (for the GNN: exactly one
/// window of its 3 input frames and target, 5 frames apart), one rollout to test on.
const ONE_CLIP: &str = r#"
name = "one_clip"
[cloth]
nx = 6
ny = 6
[model.neural_ode]
layers = 2
hidden = 64
[model.gnn]
latent = 32
mlp_layers = 1
message_passing = 2
history = 2
downsample = 5
noise = 0.0
[data]
dir = "data"
[data.clips]
steps = 15
[source]
nx = 6
ny = 6
width = 2.5
height = 2.5
seconds = 0.015
train_rollouts = 1
test_rollouts = 1
[train.stiffness]
iterations = 10
batch = 1
[train.damping]
iterations = 5
batch = 1
[train.single]
iterations = 600
batch = 1
lr = 3e-3
[train.gnn]
iterations = 300
batch = 16
lr = 1e-3
"#;

/// The training loss of a run at its start and at its end, from its `metrics.csv`.
fn first_and_last_loss(run: &Path) -> (f64, f64) {
    let text = std::fs::read_to_string(run.join("metrics.csv")).unwrap();
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().unwrap().split(',').collect();
    let col = header.iter().position(|h| *h == "loss").unwrap();
    let losses: Vec<f64> = lines
        .map(|l| l.split(',').nth(col).unwrap().parse().unwrap())
        .collect();
    assert!(losses.len() >= 100, "{} rows", losses.len());
    // The mean of the first iterations against the median of the last ones (Adam wobbles).
    let first = losses[..5].iter().sum::<f64>() / 5.0;
    let mut last = losses[losses.len() - 21..].to_vec();
    last.sort_by(f64::total_cmp);
    (first, last[10])
}

#[test]
fn each_baseline_overfits_one_short_clip() {
    let dir = common::temp_dir("baselines_overfit");
    std::fs::write(dir.join("one.toml"), ONE_CLIP).unwrap();
    for kind in ["neural_ode", "gnn"] {
        let out = ok(&springtime(
            &[
                "train",
                "one.toml",
                "--no-eval",
                "--set",
                &format!("model.kind={kind}"),
                "--out",
                kind,
            ],
            &dir,
        ));
        assert!(out.contains("trained "), "{out}");
        let (first, last) = first_and_last_loss(&dir.join(kind));
        assert!(
            last < first / 100.0,
            "{kind}: the loss fell only from {first:.3e} to {last:.3e}"
        );
        // Baseline runs are evaluated like the surrogate, and say what a step costs.
        ok(&springtime(&["eval", kind], &dir));
        let eval: serde_json::Value = serde_json::from_str(
            &std::fs::read_to_string(dir.join(kind).join("eval.json")).unwrap(),
        )
        .unwrap();
        assert!(eval["motion_rmse"]["mean"].as_f64().unwrap().is_finite());
        assert!(eval["inference"]["us_per_step"].as_f64().unwrap() > 0.0);
        // Clips shorter than the GNN's window are refused by name, not by a panic.
        if kind == "gnn" {
            common::fails(
                &springtime(
                    &[
                        "train",
                        "one.toml",
                        "--no-eval",
                        "--set",
                        "model.kind=gnn",
                        "--set",
                        "model.gnn.downsample=1000",
                        "--out",
                        "gnn_short",
                    ],
                    &dir,
                ),
                &["data.clips.steps", "model.gnn.downsample"],
            );
        }
        // Spring-only commands refuse a baseline run with a clear error.
        let out = springtime(&["report", kind], &dir);
        assert!(!out.status.success());
        assert!(
            String::from_utf8_lossy(&out.stderr).contains("not a spring surrogate"),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
    }
}

#[test]
fn compare_trains_the_three_families_and_reuses_finished_runs() {
    let dir = common::temp_dir("baselines_compare");
    let config = ONE_CLIP
        .replace("seconds = 0.015", "seconds = 0.12")
        .replace("iterations = 600", "iterations = 20")
        .replace("iterations = 300", "iterations = 20");
    std::fs::write(dir.join("cmp.toml"), config).unwrap();
    // An output folder with a comma in its name: comparison.csv must quote it.
    let out = ok(&springtime(
        &["compare", "cmp.toml", "--out", "cmp,1"],
        &dir,
    ));
    let cmp = dir.join("cmp,1");
    for kind in ["springs", "gnn", "neural_ode"] {
        assert!(cmp.join(kind).join("eval.json").exists(), "{kind}: {out}");
    }
    let rows = springtime::compare::read_csv(&cmp.join("comparison.csv")).unwrap();
    assert_eq!(
        rows.iter().map(|r| r.model.as_str()).collect::<Vec<_>>(),
        ["springs", "gnn", "neural_ode"]
    );
    for r in &rows {
        assert!(
            r.parameters > 0 && r.rmse_long_mean.is_finite() && r.rmse_long_mean > 0.0,
            "{r:?}"
        );
        assert!(r.run_dir.ends_with(&format!("cmp,1/{}", r.model)), "{r:?}");
        assert!(r.inference_us_per_step.is_some_and(|us| us > 0.0), "{r:?}");
    }
    // The spring surrogate's parameters are k and b of every spring.
    let springs: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(cmp.join("springs").join("model.json")).unwrap(),
    )
    .unwrap();
    assert_eq!(
        rows[0].parameters.to_string(),
        springs["parameters"].to_string()
    );
    let md = std::fs::read_to_string(cmp.join("comparison.md")).unwrap();
    assert!(md.contains("| springs (ours) |") && md.contains("| Neural ODE |"));
    let png = std::fs::read(cmp.join("comparison_rmse.png")).unwrap();
    assert_eq!(&png[1..4], b"PNG");
    // A second comparison reuses the finished runs; a changed config is refused.
    let again = ok(&springtime(
        &["compare", "cmp.toml", "--out", "cmp,1"],
        &dir,
    ));
    assert_eq!(again.matches("reusing the finished").count(), 3, "{again}");
    let out = springtime(
        &[
            "compare",
            "cmp.toml",
            "--out",
            "cmp,1",
            "--set",
            "model.k_init=7",
        ],
        &dir,
    );
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("another config"));
}
