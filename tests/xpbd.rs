//! `springtime xpbd estimate` end to end on a small swatch: the sim-to-sim fit recovers the
//! targets' material from another starting guess, writes `estimate.json` with the interface's
//! keys, refuses to overwrite it, and a bad config names its key; `xpbd descriptors` fits with
//! each of the four descriptors and counts their discrimination; a drape over a ledge (contact)
//! identifies b.

mod common;

use common::springtime;

const SMALL: &str = r#"
name = "xpbd_small"

[swatch]
size = 0.1
n = 5
density = 0.224

[truth]
e_u = 1.0e5
e_v = 2.8e5
mu = 4.0e4
nu = 0.4
b = 50.0

[initial]
e_u = 2.0e5
e_v = 1.8e5
mu = 5.0e4
nu = 0.3
b = 10.0

[solve]
steps = 5000

[fit]
max_iterations = 20

[[scenarios]]
kind = "frame_shear"
angle_deg = 15.0

[[scenarios]]
kind = "stretch"
strain = 0.03
axis = "u"

[[scenarios]]
kind = "stretch"
strain = 0.03
axis = "v"
"#;

/// A fresh directory for the test `name` with the small job in it as `small.toml`.
fn with_small(name: &str) -> common::TestDir {
    let dir = common::temp_dir(name);
    std::fs::write(dir.join("small.toml"), SMALL).unwrap();
    dir
}

/// Runs `springtime xpbd <command> <config> --out <out>` and then `extra` in `dir`.
fn xpbd(
    dir: &std::path::Path,
    [command, config, out]: [&str; 3],
    extra: &[&str],
) -> std::process::Output {
    let mut args = vec!["xpbd", command, config, "--out", out];
    args.extend_from_slice(extra);
    springtime(&args, dir)
}

/// [`xpbd`], requiring success (showing its stderr otherwise).
fn xpbd_ok(dir: &std::path::Path, what: [&str; 3], extra: &[&str]) {
    let out = xpbd(dir, what, extra);
    assert!(
        out.status.success(),
        "{what:?} {extra:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
}

/// The JSON file `path` under `dir`.
fn read_json(dir: &std::path::Path, path: &str) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(dir.join(path)).unwrap()).unwrap()
}

/// `est/estimate.json` under `dir`.
fn estimate_json(dir: &std::path::Path) -> serde_json::Value {
    read_json(dir, "est/estimate.json")
}

#[test]
fn the_sim_to_sim_fit_recovers_the_targets_material_and_writes_estimate_json() {
    let dir = with_small("xpbd-estimate");
    xpbd_ok(&dir, ["estimate", "small.toml", "est"], &[]);
    let json = estimate_json(&dir);
    assert!(dir.join("est/error_map.png").exists());
    let rel = &json["relative_error"];
    for key in ["C00", "C11", "C01", "C22", "b"] {
        let e = rel[key]
            .as_f64()
            .unwrap_or_else(|| panic!("no relative_error.{key}: {json}"));
        // The initial guess is off by 20–70 %; the fit must land within 0.5 % (the paper's
        // membrane figure) on every parameter.
        assert!(e < 5e-3, "relative error of {key}: {e}");
    }
    let iterations = json["iterations"].as_u64().unwrap();
    assert!((1..=20).contains(&iterations), "{iterations}");
    assert_eq!(rel["iterations"].as_f64(), Some(iterations as f64));
    // SI and CGS agree (1 dyn/cm = 1e-3 N/m, 1 erg = 1e-7 J).
    let (si, cgs) = (&json["gamma"], &json["gamma_cgs"]);
    assert!((cgs["C11"].as_f64().unwrap() / si["C11"].as_f64().unwrap() - 1e3).abs() < 1e-6);
    assert!((cgs["b"].as_f64().unwrap() / si["b"].as_f64().unwrap() - 1e7).abs() < 1e-2);
    let objective = json["objective"].as_array().unwrap();
    assert!(objective.last().unwrap().as_f64().unwrap() < 1e-3 * objective[0].as_f64().unwrap());
    // A finished estimate is not overwritten without --force.
    let again = xpbd(&dir, ["estimate", "small.toml", "est"], &[]);
    assert!(!again.status.success());
    assert!(String::from_utf8_lossy(&again.stderr).contains("--force"));
    // A bad key is named.
    std::fs::write(
        dir.join("bad.toml"),
        SMALL.replace("angle_deg = 15.0", "angle = 15.0"),
    )
    .unwrap();
    let bad = xpbd(&dir, ["estimate", "bad.toml", "b"], &[]);
    let err = String::from_utf8_lossy(&bad.stderr);
    assert!(
        !bad.status.success() && err.contains("bad.toml") && err.contains("scenarios"),
        "{err}"
    );
}

#[test]
fn the_adam_fit_through_the_burn_equilibrium_op_descends_and_bad_combinations_are_named() {
    let dir = with_small("xpbd-adam");
    xpbd_ok(
        &dir,
        ["estimate", "small.toml", "est"],
        &[
            "--set",
            "fit.optimizer=\"adam\"",
            "--set",
            "fit.adam_steps=30",
            "--set",
            "fit.adam_lr=0.05",
        ],
    );
    let json = estimate_json(&dir);
    assert_eq!(json["optimizer"], "adam");
    assert_eq!(json["iterations"], 30);
    // The objective after every step, and the final one: Adam descends through the op's
    // adjoint gradients.
    let objective: Vec<f64> = json["objective"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_f64().unwrap())
        .collect();
    assert_eq!(objective.len(), 31);
    assert!(
        objective[30] < 0.2 * objective[0],
        "objective {} → {}",
        objective[0],
        objective[30]
    );
    // Adam needs the FFT descriptor (its Burn form) and the joint schedule.
    let bad = xpbd(
        &dir,
        ["estimate", "small.toml", "b"],
        &[
            "--set",
            "fit.optimizer=\"adam\"",
            "--set",
            "fit.descriptor=\"positions\"",
        ],
    );
    common::fails(&bad, &["fit.optimizer", "fit.descriptor"]);
}

#[test]
fn the_bending_first_schedule_fits_b_on_the_cantilever_then_the_membrane() {
    let dir = common::temp_dir("xpbd-bending-first");
    let cfg = SMALL.replace(
        "max_iterations = 20",
        "max_iterations = 20\nschedule = \"bending_first\"\nrounds = 2\nstarts = 2",
    ) + "\n[[scenarios]]\nkind = \"cantilever\"\n";
    std::fs::write(dir.join("bf.toml"), cfg).unwrap();
    xpbd_ok(&dir, ["estimate", "bf.toml", "est"], &[]);
    let json = estimate_json(&dir);
    assert_eq!(json["schedule"], "bending_first");
    let starts = json["starts"].as_array().unwrap();
    assert_eq!(starts.len(), 2);
    // The second start differs from the first (a random guess around it).
    assert_ne!(starts[0]["start"]["C00"], starts[1]["start"]["C00"]);
    for key in ["C00", "C11", "C01", "C22", "b"] {
        let e = json["relative_error"][key].as_f64().unwrap();
        assert!(e < 5e-3, "relative error of {key}: {e}");
    }
    let best = starts
        .iter()
        .map(|s| s["objective"].as_f64().unwrap())
        .fold(f64::INFINITY, f64::min);
    assert_eq!(json["final_objective"].as_f64().unwrap(), best);
}

#[test]
fn the_descriptor_study_fits_with_each_descriptor_and_counts_the_discrimination() {
    let dir = with_small("xpbd-descriptors");
    xpbd_ok(
        &dir,
        ["descriptors", "small.toml", "d"],
        &["--noise", "0.005"],
    );
    let json = read_json(&dir, "d/descriptors.json");
    let fits = json["fits"].as_array().unwrap();
    let names: Vec<&str> = fits
        .iter()
        .map(|f| f["descriptor"].as_str().unwrap())
        .collect();
    assert_eq!(names, ["positions", "energy", "strain", "fft"]);
    for f in fits {
        // Each fit is a full estimate of its own, beside the study.
        let d = f["descriptor"].as_str().unwrap();
        assert!(dir.join("d").join(d).join("estimate.json").exists());
        // Position, strain and FFT residuals vanish only at the truth on these three targets.
        if d != "energy" {
            for key in ["C00", "C11", "C01", "C22", "b"] {
                let e = f["relative_error"][key].as_f64().unwrap();
                assert!(e < 5e-3, "{d}: relative error of {key}: {e}");
            }
            assert!(f["max_vertex_error"].as_f64().unwrap() < 1e-5);
        }
    }
    // Three materials × another two × two starts each = 24 differences per scenario.
    let scenarios = json["discrimination"].as_array().unwrap();
    assert_eq!(scenarios.len(), 3);
    for s in scenarios {
        let branch = s["branch_distance"].as_array().unwrap();
        for d in s["descriptors"].as_array().unwrap() {
            let rel = d["relative"].as_array().unwrap();
            assert_eq!(rel.len(), 24);
            let positive = rel
                .iter()
                .filter(|r| r["value"].as_f64().unwrap() > 0.0)
                .count();
            assert_eq!(d["positive"].as_u64().unwrap() as usize, positive);
            // The positions' difference is the two branches' distance: at least the largest
            // vertex distance, at most √25 times it.
            if d["descriptor"] == "positions" {
                for (m, w) in d["within"].as_array().unwrap().iter().enumerate() {
                    let (w, b) = (w.as_f64().unwrap(), branch[m].as_f64().unwrap());
                    assert!(
                        w >= b * (1.0 - 1e-12) && w <= 5.0 * b * (1.0 + 1e-12),
                        "{w} {b}"
                    );
                }
            }
        }
    }
    let total = json["positive"]["fft"].as_array().unwrap();
    assert_eq!(total[1].as_u64(), Some(72));
}

#[test]
fn the_invariance_experiment_fits_every_seed_from_its_own_branch_and_reports_the_spread() {
    let dir = with_small("xpbd-invariance");
    xpbd_ok(
        &dir,
        ["invariance", "small.toml", "inv"],
        &["--seeds", "2", "--noise", "0.002"],
    );
    let json = read_json(&dir, "inv/invariance.json");
    let fits = json["fits"].as_array().unwrap();
    assert_eq!(fits.len(), 4, "two descriptors × two seeds");
    for descriptor in ["fft", "positions"] {
        let mine: Vec<&serde_json::Value> = fits
            .iter()
            .filter(|f| f["descriptor"] == descriptor)
            .collect();
        assert_eq!(mine.len(), 2);
        // Each fit is a full estimate from the flat start's branch, in its own folder.
        for f in &mine {
            let seed = f["seed"].as_u64().unwrap();
            let est = read_json(&dir, &format!("inv/{descriptor}_seed{seed}/estimate.json"));
            assert_eq!(est["gamma"], f["gamma"]);
        }
        // The reported spread is that of the two fits.
        let s = &json["summary"][descriptor];
        for key in ["C00", "C11", "C01", "C22", "b"] {
            let (a, b) = (
                mine[0]["gamma"][key].as_f64().unwrap(),
                mine[1]["gamma"][key].as_f64().unwrap(),
            );
            let mean = 0.5 * (a + b);
            let cv = (a - b).abs() / std::f64::consts::SQRT_2 / mean;
            let got = s["cv"][key].as_f64().unwrap();
            assert!(
                (got - cv).abs() <= 1e-9 * (1.0 + cv),
                "{descriptor} {key}: {got} vs {cv}"
            );
        }
        let membrane = ["C00", "C11", "C01", "C22"]
            .iter()
            .map(|k| s["cv"][*k].as_f64().unwrap())
            .fold(0.0, f64::max);
        assert_eq!(s["cv_membrane"].as_f64().unwrap(), membrane);
    }
    assert_eq!(json["start"], "flat");
    // From each target's own shape (the paper's protocol) every fit stays on its target's
    // branch, so on targets from the fit's own simulator each seed recovers the truth and the
    // spread vanishes, for either descriptor.
    xpbd_ok(
        &dir,
        ["invariance", "small.toml", "own"],
        &["--seeds", "2", "--noise", "0.002", "--start", "target"],
    );
    let own = read_json(&dir, "own/invariance.json");
    assert_eq!(own["start"], "target");
    for descriptor in ["fft", "positions"] {
        let s = &own["summary"][descriptor];
        for key in ["C00", "C11", "C01", "C22", "b"] {
            let cv = s["cv"][key].as_f64().unwrap();
            let err = s["mean_relative_error"][key].as_f64().unwrap();
            assert!(
                cv < 1e-4 && err < 1e-3,
                "{descriptor} {key}: cv {cv}, error {err}"
            );
        }
    }
    // Too few seeds for a spread is refused.
    let one = xpbd(&dir, ["invariance", "small.toml", "one"], &["--seeds", "1"]);
    assert!(!one.status.success());
    assert!(String::from_utf8_lossy(&one.stderr).contains("--seeds"));
}

#[test]
fn targets_written_by_generate_fit_as_the_synthetic_ones_and_bad_files_are_named() {
    use springtime::data::npz::{Array, Npz};
    let dir = with_small("xpbd-targets");
    xpbd_ok(&dir, ["generate", "small.toml", "tg"], &[]);
    xpbd_ok(&dir, ["estimate", "small.toml", "synthetic"], &[]);
    // The same job without its truth, reading the files: a user's measured drapes.
    let a = SMALL.find("[truth]").unwrap();
    let b = SMALL.find("[initial]").unwrap();
    let user = format!("{}{}\n[targets]\ndir = \"tg\"\n", &SMALL[..a], &SMALL[b..]);
    std::fs::write(dir.join("user.toml"), &user).unwrap();
    xpbd_ok(&dir, ["estimate", "user.toml", "user"], &[]);
    let (s, u) = (
        read_json(&dir, "synthetic/estimate.json"),
        read_json(&dir, "user/estimate.json"),
    );
    assert!(u["truth"].is_null() && u["relative_error"]["C00"].is_null());
    for key in ["C00", "C11", "C01", "C22", "b"] {
        let (x, y) = (
            s["gamma"][key].as_f64().unwrap(),
            u["gamma"][key].as_f64().unwrap(),
        );
        assert!((x - y).abs() <= 1e-9 * x.abs(), "{key}: {x} vs {y}");
    }
    // The fitted γ re-simulated in a configuration the fit never saw.
    xpbd_ok(
        &dir,
        ["resim", "small.toml", "rs"],
        &[
            "--estimate",
            "synthetic/estimate.json",
            "--set",
            "scenarios=[{kind=\"frame_shear\",angle_deg=25.0}]",
        ],
    );
    let rs = read_json(&dir, "rs/resim.json");
    assert!(dir.join("rs/error_map.png").exists());
    assert!(rs["max_vertex_error"].as_f64().unwrap() < 1e-6, "{rs}");
    // Bad files: each error names the file and the key or the scenario.
    let fails = |cfg: &str, want: &[&str]| {
        std::fs::write(dir.join("bad.toml"), cfg).unwrap();
        let out = xpbd(&dir, ["estimate", "bad.toml", "bad"], &["--force"]);
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "{cfg}");
        for w in want {
            assert!(err.contains(w), "`{w}` not in: {err}");
        }
    };
    let target = dir.join("tg/stretch_u_0.03.npz");
    let good = Npz::read(&target).unwrap();
    let mut npz = good.clone();
    npz.insert("grid", Array::i64(&[2], &[6, 6]));
    npz.write(&target).unwrap();
    fails(&user, &["stretch_u_0.03.npz", "grid"]);
    let mut npz = good.clone();
    let (mut p, _) = good.f64("positions", &[None, Some(3)]).unwrap();
    p[40] = f64::NAN;
    npz.insert("positions", Array::f64(&[25, 3], &p));
    npz.write(&target).unwrap();
    fails(&user, &["stretch_u_0.03.npz", "positions", "non-finite"]);
    // Another scenario's shape: its clamps are elsewhere.
    std::fs::copy(dir.join("tg/stretch_v_0.03.npz"), &target).unwrap();
    fails(&user, &["stretch_u_0.03.npz", "positions", "clamped"]);
    std::fs::remove_file(&target).unwrap();
    fails(&user, &["stretch_u_0.03.npz", "no target"]);
    // Neither a truth nor a folder of targets.
    fails(
        &user.replace("dir = \"tg\"", ""),
        &["[truth]", "targets.dir"],
    );
    // generate does not overwrite without --force.
    let again = xpbd(&dir, ["generate", "small.toml", "tg"], &[]);
    assert!(!again.status.success());
}

#[test]
fn a_ledge_drape_identifies_b_and_what_it_cannot_do_is_named() {
    let dir = common::temp_dir("xpbd-ledge");
    let ledge = |overhang: &str| {
        SMALL.replace(
            "max_iterations = 20",
            "max_iterations = 20\nschedule = \"bending_first\"\nrounds = 2",
        ) + &format!("\n[[scenarios]]\nkind = \"ledge_drape\"\noverhang = {overhang}\n")
    };
    std::fs::write(dir.join("ledge.toml"), ledge("0.4")).unwrap();
    xpbd_ok(&dir, ["estimate", "ledge.toml", "est"], &[]);
    let json = estimate_json(&dir);
    // The drape over the ledge is the only bending target: b comes from it.
    for key in ["C00", "C11", "C01", "C22", "b"] {
        let e = json["relative_error"][key].as_f64().unwrap();
        assert!(e < 5e-3, "relative error of {key}: {e}");
    }
    let refused = |what: [&str; 3], extra: &[&str], want: &[&str]| {
        let out = xpbd(&dir, what, extra);
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "{what:?} {extra:?} succeeded");
        for w in want {
            assert!(err.contains(w), "{what:?} {extra:?}: {err}");
        }
    };
    std::fs::write(dir.join("far.toml"), ledge("0.9")).unwrap();
    refused(
        ["estimate", "far.toml", "far"],
        &[],
        &["far.toml", "scenarios.overhang"],
    );
    refused(
        ["estimate", "ledge.toml", "fwd"],
        &["--set", "fit.derivatives=\"forward\""],
        &["fit.derivatives", "ledge_drape_0.4"],
    );
    refused(
        ["estimate", "ledge.toml", "stamp"],
        &["--set", "targets.stamp=5"],
        &["targets.stamp"],
    );
    // The FEM targets (an isotropic truth) have no collider.
    refused(
        ["estimate", "ledge.toml", "fem"],
        &[
            "--set",
            "targets.simulator=\"fem\"",
            "--set",
            "truth.e_v=1.0e5",
            "--set",
            "truth.mu=35714.2857142857",
        ],
        &["ledge_drape_0.4", "no contact"],
    );
}
