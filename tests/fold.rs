//! `springtime fold` end to end on a tiny sheet: a 4 × 4 FEM source, its nested 7 × 7 fine
//! mesh and a 4 × 4 surrogate trained for a few steps. Checks the interface (fold.json with
//! criteria L1–L4, each {value, threshold, pass}; fold.csv; fold.png) and the refusal to
//! overwrite, not the physics (the unit tests in src/fold and configs/fold.toml do that).

mod common;

use common::{fails, ok, springtime};

/// The fold job over the tiny FEM surrogate ([`common::FEM_4X4`], its tables under
/// `[surrogate]`).
fn tiny() -> String {
    let surrogate = common::FEM_4X4.replace("\n[", "\n[surrogate.");
    format!(
        r#"
[fold]
fine = 7
pin_radius = 0.2

[fold.settle]
tolerance = 5e-3
hold = 0.05
max_seconds = 6.0

[surrogate]
name = "tiny_fold"
{surrogate}"#
    )
}

#[test]
fn fold_writes_the_criteria_and_refuses_to_overwrite() {
    let dir = common::temp_dir("fold");
    std::fs::write(dir.join("fold.toml"), tiny()).unwrap();
    let out = ok(&springtime(&["fold", "fold.toml", "--out", "out"], &dir));
    for needle in [
        "L1",
        "L2",
        "L3",
        "L4",
        "threshold",
        "surrogate",
        "fem7_no_bending",
    ] {
        assert!(out.contains(needle), "no {needle:?} in\n{out}");
    }
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("out/fold.json")).unwrap()).unwrap();
    for name in ["L1", "L2", "L3", "L4"] {
        let c = &json["criteria"][name];
        assert!(c["value"].is_f64(), "{name}: {c}");
        assert!(c["threshold"].is_f64(), "{name}: {c}");
        assert!(c["pass"].is_boolean(), "{name}: {c}");
    }
    let results = json["results"].as_array().unwrap();
    assert_eq!(results.len(), 8, "4 systems × 2 cases");
    for r in results {
        let alpha = r["alpha_deg"].as_f64().unwrap();
        assert!((0.0..=180.0).contains(&alpha), "{r}");
        // The sheet fell: its free vertices hang below the pins.
        assert!(r["sag_m"].as_f64().unwrap() > 0.0, "{r}");
        let fem = r["system"].as_str().unwrap().starts_with("fem");
        assert_eq!(r["membrane_share"].is_f64(), fem, "{r}");
    }
    // The fine mesh is its own reference.
    let fine = results.iter().find(|r| r["system"] == "fem7").unwrap();
    assert_eq!(fine["rmse_fine_m"].as_f64().unwrap(), 0.0);
    assert!(json["locking_gap_deg"]["fem4"].is_f64());
    let csv = std::fs::read_to_string(dir.join("out/fold.csv")).unwrap();
    assert_eq!(csv.lines().count(), 9, "{csv}");
    let png = std::fs::read(dir.join("out/fold.png")).unwrap();
    assert_eq!(&png[1..4], b"PNG");
    // A finished output is not overwritten without --force.
    fails(
        &springtime(&["fold", "fold.toml", "--out", "out"], &dir),
        &["--force"],
    );
    // An interrupted job's data and surrogate are not reused for another config.
    std::fs::remove_file(dir.join("out/fold.json")).unwrap();
    fails(
        &springtime(
            &[
                "fold",
                "fold.toml",
                "--out",
                "out",
                "--set",
                "surrogate.source.seed=7",
            ],
            &dir,
        ),
        &["surrogate.source", "--force"],
    );
    // Errors name the key.
    fails(
        &springtime(
            &["fold", "fold.toml", "--out", "o2", "--set", "fold.fine=8"],
            &dir,
        ),
        &["fold.fine"],
    );
}
