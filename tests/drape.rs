//! `springtime drape` end to end on a tiny sheet: a 4 × 4 FEM source, a 4 × 4 surrogate
//! trained for a few steps on free pinned rollouts, a mesh and an analytic scene. Checks the
//! interface (drape.json keys, figure, curves, relaxations), the refusals (finished output,
//! bad mesh, unstable contact) and `export --scene`; then the relaxations' meaning on a 5 × 5
//! mass-spring source with surrogates holding its springs or softer ones. The physics is in
//! tests/contact.rs.

mod common;

use common::{fails, ok, springtime};

/// The tiny FEM job, its data in `data/`.
fn tiny() -> String {
    format!(
        "name = \"tiny_drape\"\n[data]\ndir = \"data\"\n{}",
        common::FEM_4X4
    )
}

/// A `[scene]` of `timing` over the sphere both tests drape on: 0.3 m in radius, its top at the
/// origin, friction 0.5.
fn sphere_scene(timing: &str) -> String {
    format!(
        r#"
[scene]
{timing}

[[scene.colliders]]
kind = "sphere"
radius = 0.3
translation = [0.0, 0.0, -0.3]
friction = 0.5
"#
    )
}

/// Dropped from 0.2 m, perturbed by 5 %, recorded every 0.02 s over 0.4 s, then settled 0.2 s.
const SPHERE: &str =
    "seconds = 0.4\nsettle = 0.2\nperturb = 0.05\nrelease_height = 0.2\nrecord_every = 0.02";

/// A closed tetrahedron, outward faces, in `meshes/` beside the scene file.
const TET: &str = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n";

const MESH: &str = r#"
[scene]
seconds = 0.3
settle = 0.1
perturb = 0.0
release_height = 0.1

[[scene.colliders]]
kind = "mesh"
mesh = "meshes/tet.obj"
scale = 0.5
translation = [-0.2, -0.2, -0.5]
"#;

/// Runs `springtime drape <run>` with a `--scene` for each of `scenes`, `--out <out>` and then
/// `extra`, in `dir`.
fn drape(
    run: &str,
    scenes: &[&str],
    out: &str,
    extra: &[&str],
    dir: &std::path::Path,
) -> std::process::Output {
    let mut args = vec!["drape", run];
    for scene in scenes {
        args.extend(["--scene", scene]);
    }
    args.extend(["--out", out]);
    args.extend_from_slice(extra);
    springtime(&args, dir)
}

#[test]
fn drape_writes_its_metrics_and_refuses_bad_scenes() {
    let dir = common::temp_dir("drape");
    std::fs::write(dir.join("tiny.toml"), tiny()).unwrap();
    std::fs::create_dir_all(dir.join("scenes/meshes")).unwrap();
    std::fs::write(dir.join("scenes/sphere.toml"), sphere_scene(SPHERE)).unwrap();
    std::fs::write(dir.join("scenes/meshes/tet.obj"), TET).unwrap();
    std::fs::write(dir.join("scenes/mesh.toml"), MESH).unwrap();
    ok(&springtime(&["train", "tiny.toml", "--out", "run"], &dir));
    let out = ok(&drape(
        "run",
        &["scenes/sphere.toml", "scenes/mesh.toml"],
        "d",
        &[],
        &dir,
    ));
    assert!(out.contains("springs") && out.contains("fem4x4"), "{out}");
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("d/drape.json")).unwrap()).unwrap();
    for name in ["sphere", "mesh"] {
        let s = &json["scenes"][name];
        let m = &s["models"]["springs"];
        for key in ["motion_rmse_end", "steady_rmse_vs_fine", "max_penetration"] {
            assert!(m[key].as_f64().unwrap() >= 0.0, "{name}.{key}: {m}");
        }
        assert_eq!(m["diverged"], false, "{m}");
        assert!(
            s["source"]["steady_rmse_vs_fine"].as_f64().unwrap() > 0.0,
            "{s}"
        );
        assert_eq!(s["fine"]["label"], "fem7x7", "{s}");
        let thickness = s["contact_thickness"].as_f64().unwrap();
        assert!(
            (thickness - 0.01).abs() < 1e-12,
            "1 % of the 1 m sheet: {thickness}"
        );
        let png = std::fs::read(dir.join(format!("d/{name}.png"))).unwrap();
        assert_eq!(&png[1..4], b"PNG");
        let csv = std::fs::read_to_string(dir.join(format!("d/{name}_motion_rmse.csv"))).unwrap();
        assert!(csv.starts_with("time,springs_rmse_m"), "{csv}");
    }
    // The motion RMSE's window ends at `seconds`; the steady figures come after settling.
    let sphere = &json["scenes"]["sphere"];
    let m = &sphere["models"]["springs"];
    let curve = m["motion_rmse_over_time"].as_array().unwrap();
    assert_eq!(curve.len(), 31, "0.6 s recorded every 0.02 s: {m}");
    assert!((curve[20][0].as_f64().unwrap() - 0.4).abs() < 1e-9, "{m}");
    assert_eq!(m["motion_rmse_end"], curve[20][1], "{m}");
    assert_eq!(m["steady_rmse_vs_source"], curve[30][1], "{m}");
    assert!(m["settled"].is_boolean() && m["speed_rms_end"].as_f64().unwrap() >= 0.0);
    assert_eq!(sphere["source"]["steady_rmse_vs_source"], 0.0, "{sphere}");
    // The perturbed source: 5 % on every triangle's modulus moves its drape, but not to
    // another place (the 1 m sheet on a 0.3 m sphere).
    let p = &sphere["perturbed"];
    assert_eq!(p["label"], "fem4x4 ±5%", "{p}");
    let moved = p["steady_rmse_vs_source"].as_f64().unwrap();
    assert!(moved > 0.0 && moved < 0.05, "{p}");
    assert!(
        json["scenes"]["mesh"]["perturbed"].is_null(),
        "perturb = 0: none"
    );
    // Relaxations (`settle` long) from the settled drapes: the model from the source's and
    // the fine mesh's, the source from the fine mesh's; not the fine mesh itself.
    for r in [
        &m["relaxed_from_source"],
        &m["relaxed_from_fine"],
        &sphere["source"]["relaxed_from_fine"],
    ] {
        assert!((r["seconds"].as_f64().unwrap() - 0.2).abs() < 1e-9, "{r}");
        assert!(r["steady_rmse_vs_fine"].as_f64().unwrap() >= 0.0, "{r}");
        assert_eq!(r["diverged"], false, "{r}");
    }
    assert_eq!(
        sphere["fine"].get("relaxed_from_fine"),
        Some(&serde_json::Value::Null),
        "the fine mesh does not relax from itself: {sphere}"
    );
    // The sheet fell onto the sphere and stayed on it.
    let sphere = &json["scenes"]["sphere"]["models"]["springs"];
    assert!(
        sphere["max_penetration"].as_f64().unwrap() > 0.0,
        "{sphere}"
    );
    // A finished drape is not overwritten without --force.
    let on_sphere = ["scenes/sphere.toml"];
    fails(&drape("run", &on_sphere, "d", &[], &dir), &["--force"]);
    // Contact too stiff for the step: the guard's refusal with the largest stable step.
    fails(
        &drape(
            "run",
            &on_sphere,
            "d2",
            &["--set", "scene.contact.stiffness=1e9"],
            &dir,
        ),
        &["unstable", "largest stable dt", "contact stiffness"],
    );
    // A broken mesh: the error names the file.
    std::fs::write(
        dir.join("scenes/meshes/tet.obj"),
        "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n",
    )
    .unwrap();
    fails(
        &drape("run", &["scenes/mesh.toml"], "d3", &[], &dir),
        &["tet.obj", "not closed", "scene.colliders[0]"],
    );
    fails(
        &drape("run", &["scenes/nothing.toml"], "d3", &[], &dir),
        &["nothing.toml"],
    );
    // export --scene writes the surrogate's drape as OBJ frames.
    let out = ok(&springtime(
        &[
            "export",
            "run",
            "--scene",
            "scenes/sphere.toml",
            "--out",
            "e",
            "--fps",
            "25",
        ],
        &dir,
    ));
    assert!(out.contains("sphere"), "{out}");
    let frames: Vec<_> = std::fs::read_dir(dir.join("e/rollout")).unwrap().collect();
    assert_eq!(frames.len(), 11, "0.4 s at 25 fps: 11 frames");
    let last = std::fs::read_to_string(dir.join("e/rollout/frame_0010.obj")).unwrap();
    let lowest = last
        .lines()
        .filter_map(|l| l.strip_prefix("v "))
        .map(|l| l.split_whitespace().nth(2).unwrap().parse::<f64>().unwrap())
        .fold(f64::INFINITY, f64::min);
    assert!(lowest < 0.15, "the exported sheet fell: lowest z {lowest}");
}

/// A 5 × 5 mass-spring source and surrogates built from its values without training.
const SPRING_SOURCE: &str = r#"
name = "spring_drape"

[cloth]
nx = 5
ny = 5

[model]
k_init = 300.0
b_init = 0.05

[sim]
substeps = 2
rayleigh = 0.1

[data]
dir = "data"

[data.clips]
steps = 20

[source]
kind = "mass_spring"
nx = 5
ny = 5
width = 1.0
height = 1.0
stiffness_levels = [300.0]
layout = "uniform"
damping = 0.05
rayleigh = 0.1
seconds = 0.2
dt = 5e-4
frame_stride = 2
train_rollouts = 2
test_rollouts = 1
anchor_radius = 0.2

[train.stiffness]
iterations = 0

[train.damping]
iterations = 0
"#;

/// Dropped from 0.1 m, recorded every 0.05 s over 0.5 s, then settled 1.5 s.
const SPHERE_AT_REST: &str =
    "seconds = 0.5\nsettle = 1.5\nperturb = 0.0\nrelease_height = 0.1\nrecord_every = 0.05";

/// `relaxed_from_source`: a surrogate with its source's own springs, started from the source's
/// settled drape, stays on it; one with a third of the stiffness sags away from it.
#[test]
fn a_surrogate_started_from_its_source_drape_keeps_it_only_with_the_source_springs() {
    let dir = common::temp_dir("drape_relax");
    std::fs::write(dir.join("springs.toml"), SPRING_SOURCE).unwrap();
    std::fs::write(dir.join("sphere.toml"), sphere_scene(SPHERE_AT_REST)).unwrap();
    ok(&springtime(
        &["train", "springs.toml", "--out", "same"],
        &dir,
    ));
    ok(&springtime(
        &[
            "train",
            "springs.toml",
            "--out",
            "soft",
            "--set",
            "model.k_init=100.0",
        ],
        &dir,
    ));
    let relaxed = |run: &str| {
        let out = format!("d_{run}");
        ok(&drape(run, &["sphere.toml"], &out, &[], &dir));
        let json: serde_json::Value = serde_json::from_str(
            &std::fs::read_to_string(dir.join(&out).join("drape.json")).unwrap(),
        )
        .unwrap();
        let scene = &json["scenes"]["sphere"];
        assert_eq!(scene["source"]["settled"], true, "{scene}");
        let m = &scene["models"]["springs"];
        let r = &m["relaxed_from_source"];
        assert!((r["seconds"].as_f64().unwrap() - 1.5).abs() < 1e-9, "{r}");
        assert_eq!(r["diverged"], false, "{r}");
        (
            m["steady_rmse_vs_source"].as_f64().unwrap(),
            r["steady_rmse_vs_source"].as_f64().unwrap(),
        )
    };
    let (fall, same) = relaxed("same");
    let (_, soft) = relaxed("soft");
    assert!(same < 1e-4, "the source's springs hold its drape: {same} m");
    assert!(fall < 1e-3, "and fall onto it: {fall} m");
    assert!(
        soft > 100.0 * same.max(1e-5),
        "softer springs sag away: {soft} m"
    );
}
