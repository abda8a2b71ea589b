//! The browser export end to end: `springtime export RUN --format web` opened in a real
//! headless browser (Chromium, through `web/tools/browser.mjs`), against `springtime simulate`:
//! from the rest state with the pins held, and from a recorded rollout's first frame with the
//! pins on their recorded path, on a grid run and on a run on an irregular data mesh; loaded
//! offline; a dragged pin pulling its neighbours. And the JavaScript step's own unit tests
//! (`node --test web/test/`).
//!
//! Needs `node` and Chromium (or Chrome). Where either is missing the tests say so and pass,
//! unless `SPRINGTIME_REQUIRE_BROWSER=1` (CI sets it), which makes a missing one an error.

mod common;

use std::path::{Path, PathBuf};
use std::process::Command;

use common::{ok, springtime};
use rand::{SeedableRng, rngs::StdRng};
use springtime::cloth::Topology;
use springtime::data::npz::Npz;
use springtime::source::{Scenario, SpringCloth, simulate_rollout};

fn required() -> bool {
    std::env::var("SPRINGTIME_REQUIRE_BROWSER").is_ok_and(|v| v == "1")
}

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// `node`, when present (else a skip note, or a failure where required).
fn node() -> Option<&'static str> {
    let found = Command::new("node")
        .arg("--version")
        .output()
        .is_ok_and(|o| o.status.success());
    if !found {
        assert!(!required(), "SPRINGTIME_REQUIRE_BROWSER=1 but no `node`");
        eprintln!("skipped: no `node` on PATH");
        return None;
    }
    Some("node")
}

#[test]
fn the_js_step_passes_its_hand_computed_cases() {
    let Some(node) = node() else { return };
    let out = Command::new(node)
        .args(["--test", "web/test/"])
        .current_dir(root())
        .output()
        .unwrap();
    let text =
        String::from_utf8_lossy(&out.stdout).into_owned() + &String::from_utf8_lossy(&out.stderr);
    assert!(
        out.status.success(),
        "node --test web/test/ failed:\n{text}"
    );
    assert!(text.contains("# fail 0"), "{text}");
}

/// Runs a scenario in the headless browser on the exported folder `page`; `None` where no
/// browser is found (and not required).
fn browser(page: &Path, steps: serde_json::Value) -> Option<serde_json::Value> {
    let node = node()?;
    // The scenario goes in a file: a state of every particle is too long for a command line.
    let scenario = page.with_extension("scenario.json");
    std::fs::write(&scenario, serde_json::json!({ "steps": steps }).to_string()).unwrap();
    let out = Command::new(node)
        .arg(root().join("web/tools/browser.mjs"))
        .arg(page)
        .arg(&scenario)
        .args(["--timeout", "300"])
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    if out.status.code() == Some(3) {
        assert!(
            !required(),
            "SPRINGTIME_REQUIRE_BROWSER=1 but no browser: {stdout}"
        );
        eprintln!("skipped: no Chromium or Chrome found ({stdout})");
        return None;
    }
    let value: serde_json::Value = serde_json::from_str(stdout.trim()).unwrap_or_else(|e| {
        panic!(
            "browser driver: {e}: {stdout}\n{}",
            String::from_utf8_lossy(&out.stderr)
        )
    });
    assert_eq!(value["ok"], true, "browser driver failed: {value}");
    // Offline and clean: the page asked for nothing over the network and logged no error.
    assert_eq!(value["blocked_requests"], serde_json::json!([]), "{value}");
    assert_eq!(value["console_errors"], serde_json::json!([]), "{value}");
    Some(value)
}

fn floats(v: &serde_json::Value) -> Vec<f32> {
    v.as_array()
        .unwrap()
        .iter()
        .map(|x| x.as_f64().unwrap() as f32)
        .collect()
}

/// `positions` `[F, P, 3]` (flat), `velocities` and `pinned` of a rollout file.
fn rollout(path: &Path) -> (Vec<f32>, Vec<f32>, Vec<usize>, usize) {
    let npz = Npz::read(path).unwrap();
    let (x, shape) = npz.f32("positions", &[None, None, Some(3)]).unwrap();
    let (v, _) = npz.f32("velocities", &[None, None, Some(3)]).unwrap();
    let pinned = npz.bool("pinned", &[None]).unwrap();
    let pinned = pinned
        .iter()
        .enumerate()
        .filter_map(|(i, &p)| p.then_some(i))
        .collect();
    (x, v, pinned, shape[1])
}

fn max_diff(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

/// The page against `springtime simulate` on the run in `dir/run` (its data in `dir`): rest
/// start over 2 s, the first test rollout's start over 1 s, and a drag. Returns the two
/// largest differences.
fn parity(dir: &Path, test_rollout: &str) -> Option<(f32, f32)> {
    ok(&springtime(
        &["export", "run", "--format", "web", "--out", "web"],
        dir,
    ));
    for f in [
        "index.html",
        "surrogate.js",
        "vendor/three.min.js",
        "vendor/three.LICENSE",
    ] {
        assert!(dir.join("web").join(f).is_file(), "the export lacks {f}");
    }
    // Self-contained and small: no file over 2 MB but the bundled library.
    for f in [
        "index.html",
        "src/sim.js",
        "src/app.js",
        "surrogate.js",
        "surrogate.json",
    ] {
        let size = std::fs::metadata(dir.join("web").join(f)).unwrap().len();
        assert!(size < 2 << 20, "{f} is {size} bytes");
    }
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("web/surrogate.json")).unwrap())
            .unwrap();
    let frame_dt = json["frame_dt"].as_f64().unwrap();
    assert!(json["substeps"].as_u64().unwrap() >= 1);
    assert!(json["stability"]["number"].as_f64().unwrap() < 4.0);

    // From rest with the pins held.
    ok(&springtime(
        &[
            "simulate",
            "run",
            "--rest",
            "--seconds",
            "2",
            "--out",
            "rest.npz",
        ],
        dir,
    ));
    let (x, _, pinned, p) = rollout(&dir.join("rest.npz"));
    assert_eq!(
        pinned,
        json["pinned"]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_u64().unwrap() as usize)
            .collect::<Vec<_>>(),
        "simulate --rest and the export pin the same particles"
    );
    assert!(!pinned.is_empty(), "the start has pins");
    let frames = x.len() / (3 * p) - 1;
    assert_eq!(frames, (2.0 / frame_dt).round() as usize);
    let every = (frames / 20).max(1);
    let run = browser(
        &dir.join("web"),
        serde_json::json!([{"op": "reset"}, {"op": "rollout", "frames": frames, "every": every}]),
    )?;
    let r = &run["results"][1];
    assert_eq!(r["finite"], true);
    let mut rest = 0.0f32;
    for (q, f) in r["frames"].as_array().unwrap().iter().enumerate() {
        let f = f.as_u64().unwrap() as usize;
        let js = floats(&r["positions"][q]);
        rest = rest.max(max_diff(&js, &x[f * p * 3..(f + 1) * p * 3]));
    }
    // The cloth moved: the comparison is not of a sheet at rest.
    let drop = max_diff(&x[..p * 3], &x[frames * p * 3..]);
    assert!(drop > 0.05, "the sheet hardly moved ({drop} m)");
    assert!(rest <= 1e-4, "page ≠ simulate --rest by {rest} m");

    // From a recorded rollout's first frame, its pins following their recorded path.
    ok(&springtime(
        &[
            "simulate",
            "run",
            "--init",
            test_rollout,
            "--seconds",
            "1",
            "--out",
            "init.npz",
        ],
        dir,
    ));
    let (x, v, pinned, _) = rollout(&dir.join("init.npz"));
    let frames = x.len() / (3 * p) - 1;
    let path: Vec<f32> = (0..=frames)
        .flat_map(|f| {
            pinned
                .iter()
                .flat_map(move |&i| (0..3).map(move |c| (f, i, c)))
                .map(|(f, i, c)| x[(f * p + i) * 3 + c])
                .collect::<Vec<_>>()
        })
        .collect();
    let run = browser(
        &dir.join("web"),
        serde_json::json!([
            {"op": "set_state", "x": &x[..p * 3], "v": &v[..p * 3], "pinned": pinned},
            {"op": "pin_path", "frames": path},
            {"op": "rollout", "frames": frames, "every": (frames / 10).max(1)}
        ]),
    )?;
    let r = &run["results"][2];
    let mut init = 0.0f32;
    for (q, f) in r["frames"].as_array().unwrap().iter().enumerate() {
        let f = f.as_u64().unwrap() as usize;
        init = init.max(max_diff(
            &floats(&r["positions"][q]),
            &x[f * p * 3..(f + 1) * p * 3],
        ));
    }
    assert!(init <= 1e-4, "page ≠ simulate --init by {init} m");

    // Dragging a pinned particle moves its free neighbours.
    let springs = Npz::read(&dir.join("run/springs.npz")).unwrap();
    let (ends, _) = springs.int("springs", &[None, Some(2)]).unwrap();
    let pins: Vec<usize> = json["pinned"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_u64().unwrap() as usize)
        .collect();
    let (pin, free) = ends
        .chunks(2)
        .find_map(|e| {
            let (a, b) = (e[0] as usize, e[1] as usize);
            match (pins.contains(&a), pins.contains(&b)) {
                (true, false) => Some((a, b)),
                (false, true) => Some((b, a)),
                _ => None,
            }
        })
        .expect("a pinned particle with a free neighbour");
    let rest_x = json["rest_positions"][pin].as_array().unwrap();
    let to: Vec<f64> = rest_x
        .iter()
        .enumerate()
        .map(|(c, v)| v.as_f64().unwrap() + if c == 2 { 0.3 } else { 0.0 })
        .collect();
    let n = (0.2 / frame_dt).round() as usize;
    let run = browser(
        &dir.join("web"),
        serde_json::json!([
            {"op": "reset"}, {"op": "step", "frames": n}, {"op": "positions"},
            {"op": "reset"}, {"op": "drag", "particle": pin, "to": to},
            {"op": "step", "frames": n}, {"op": "positions"}
        ]),
    )?;
    let (still, dragged) = (
        floats(&run["results"][2]["positions"]),
        floats(&run["results"][6]["positions"]),
    );
    assert!(
        (dragged[pin * 3 + 2] - to[2] as f32).abs() < 1e-3,
        "the dragged pin is where it was dragged"
    );
    let moved = dragged[free * 3 + 2] - still[free * 3 + 2];
    assert!(
        moved > 1e-3,
        "dragging pin {pin} up 0.3 m lifted its neighbour {free} by only {moved} m"
    );
    Some((rest, init))
}

/// The tiny job on an 8 × 8 cloth 3.5 m square, over 1 s rollouts, from 50 N/m and 3 N·s/m at
/// 2 substeps a frame with a viscosity (`sim.viscosity`) and shear springs softer in compression
/// (`sim.shear_compression`; the page's `springtime-surrogate/4`), without checkpoints.
fn grid() -> String {
    common::tiny_with(&[
        ("name = \"tiny\"", "name = \"web\""),
        ("nx = 6", "nx = 8"),
        ("ny = 6", "ny = 8"),
        ("= 2.5", "= 3.5"),
        ("seconds = 0.3", "seconds = 1.0"),
        (
            "[train]\ncheckpoint_every = 5\n",
            "[model]\nk_init = 50.0\nb_init = 3.0\n[sim]\nsubsteps = 2\nrayleigh = 0.1\n\
             viscosity = 0.004\nshear_compression = 0.3\n",
        ),
    ])
}

#[test]
fn the_page_simulates_a_grid_run_as_springtime_simulate_does() {
    let dir = common::temp_dir("web-grid");
    std::fs::write(dir.join("web.toml"), grid()).unwrap();
    ok(&springtime(
        &["train", "web.toml", "--out", "run", "--no-report"],
        &dir,
    ));
    if let Some((rest, init)) = parity(&dir, "data/test_0000.npz") {
        eprintln!(
            "grid: max |page − simulate| {rest:.3e} m from rest, {init:.3e} m from a rollout"
        );
    }
    let json = springtime::export::SurrogateJson::read(&dir.join("web/surrogate.json")).unwrap();
    assert_eq!(json.viscosity, 0.004, "the page steps the run's viscosity");
    assert_eq!(
        json.shear_compression, 0.3,
        "and its shear springs' compression"
    );
    assert_eq!(json.format, springtime::export::FORMAT_COMPRESSION);
}

#[test]
fn the_page_simulates_a_data_mesh_run_as_springtime_simulate_does() {
    let dir = common::temp_dir("web-mesh");
    // Takes of a spring cloth on jittered points: the surrogate's triangles are irregular.
    let n = 7;
    let cfg = common::source(n, &[40.0], 1.0);
    let size = 0.5 * (n - 1) as f64;
    let topology = Topology::of_points(&common::jittered_points(n, 11), size, size, true).unwrap();
    let base = SpringCloth::from_config(&cfg);
    let cloth = SpringCloth {
        k: vec![40.0; topology.num_springs()],
        b: vec![4.0; topology.num_springs()],
        mass: base.mass,
        topology,
        ..base
    };
    for (seed, folder) in [(0u64, "train"), (1, "train"), (2, "train"), (3, "test")] {
        let scenario = Scenario::random(
            &cloth.topology.rest_uv,
            cfg.anchor_radius,
            &mut StdRng::seed_from_u64(seed),
        );
        let name = format!("take_{seed}.npz");
        std::fs::create_dir_all(dir.join(folder)).unwrap();
        simulate_rollout(&cloth, &cfg, &scenario, None, &name)
            .unwrap()
            .save(&dir.join(folder).join(&name))
            .unwrap();
    }
    std::fs::write(
        dir.join("mesh.toml"),
        "name = \"mesh\"\n[cloth]\nlayout = \"data\"\n[model]\nk_init = 40.0\nb_init = 3.0\n\
         [data]\ndir = \"train\"\ntest_dir = \"test\"\n[data.clips]\nsteps = 50\n\
         [train.stiffness]\niterations = 10\nbatch = 3\n[train.damping]\niterations = 5\nbatch = 3\n",
    )
    .unwrap();
    ok(&springtime(
        &["train", "mesh.toml", "--out", "run", "--no-report"],
        &dir,
    ));
    if let Some((rest, init)) = parity(&dir, "test/take_3.npz") {
        eprintln!(
            "mesh: max |page − simulate| {rest:.3e} m from rest, {init:.3e} m from a rollout"
        );
    }
}
