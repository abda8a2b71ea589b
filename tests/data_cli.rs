//! The data commands end to end: `data check`, `import`, and their errors.

mod common;

use springtime::settings::Job;
use std::path::{Path, PathBuf};

use common::{fails, import, ok, springtime};

fn fixture(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures")
        .join(name)
}

fn copy_fixtures(dir: &Path, names: &[&str]) {
    std::fs::create_dir_all(dir).unwrap();
    for n in names {
        std::fs::copy(fixture(n), dir.join(n)).unwrap();
    }
}

#[test]
fn data_check_summarises_a_usable_folder() {
    let dir = common::temp_dir("data-check");
    copy_fixtures(
        &dir.join("takes"),
        &[
            "npz_savez.npz",
            "npz_compressed_extras.npz",
            "npz_bigendian_fortran.npz",
        ],
    );
    let out = ok(&springtime(&["data", "check", "takes"], &dir));
    for needle in [
        "files            3 (3 train, 0 test)",
        "index.json       none",
        "frames           4 per file, 12 in all",
        "frame_dt         0.01 s",
        "total mass       0.5 kg",
        "rest rectangle   1 m × 1 m",
        "landmarks        9",
        "pinned           2",
        "velocities       no",
        "name (<U5)",
        "meta (|O)",
        "half (float16 [2, 3])",
        "labels (<U1)",
        "dt²ω² + 2dtγ =",
        "32 × 32 particles, k = 50 N/m, b = 3 N·s/m",
        // 9 landmarks on a square: a 3 × 3 grid holds what they resolve.
        "--set cloth.nx=3 --set cloth.ny=3",
    ] {
        assert!(out.contains(needle), "no {needle:?} in:\n{out}");
    }
    // A 0.5 kg sheet of 32 × 32 particles at 100 fps is too stiff for one step per frame; the
    // check says how many substeps would do, and they do. With every default "auto" and no
    // usable force fit (4 frames), train searches k itself: the check makes no prediction.
    assert!(
        out.contains("not a prediction: `train` searches k"),
        "{out}"
    );
    let fixed = ["--set", "model.k_init=50", "--set", "model.b_init=3"];
    let mut args = vec!["data", "check", "takes"];
    args.extend_from_slice(&fixed);
    let out = ok(&springtime(&args, &dir));
    assert!(out.contains("UNSTABLE"), "{out}");
    let need: usize = out
        .split("`sim.substeps` to at least ")
        .nth(1)
        .and_then(|t| t.split_whitespace().next())
        .and_then(|n| n.parse().ok())
        .unwrap_or_else(|| panic!("no substep advice in:\n{out}"));
    let substeps = format!("sim.substeps={need}");
    let mut args = vec!["data", "check", "takes", "--set", &substeps];
    args.extend_from_slice(&fixed);
    let out = ok(&springtime(&args, &dir));
    assert!(out.contains(": stable (below 4"), "{out}");

    // Another tool's index.json is ignored with a warning.
    let out = springtime(
        &["data", "check", fixture("foreign_index").to_str().unwrap()],
        &dir,
    );
    let text = ok(&out);
    assert!(text.contains("files            1"), "{text}");
    assert!(
        String::from_utf8_lossy(&out.stderr).contains("warning: ignoring"),
        "{text}"
    );
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn data_check_fails_naming_the_file_and_key() {
    let dir = common::temp_dir("data-check-bad");
    copy_fixtures(
        &dir.join("bad"),
        &["npz_savez.npz", "npz_object_positions.npz"],
    );
    fails(
        &springtime(&["data", "check", "bad"], &dir),
        &["npz_object_positions.npz", "`positions`", "|O"],
    );
    // Files that disagree on the frame step.
    let mut npz = springtime::data::npz::Npz::read(&fixture("npz_savez.npz")).unwrap();
    npz.insert("frame_dt", springtime::data::npz::Array::scalar(0.02));
    copy_fixtures(&dir.join("mixed"), &["npz_savez.npz"]);
    npz.write(&dir.join("mixed/z_slow.npz")).unwrap();
    fails(
        &springtime(&["data", "check", "mixed"], &dir),
        &["z_slow.npz", "`frame_dt`", "differs"],
    );
    // A damaged scalar (a frame step of 1e9 s, a mass in grams read as kg, gravity in cm/s²) is
    // refused by the reader, naming the file and the key, before any later stage sees it.
    for (key, value, name) in [
        ("frame_dt", 1e9, "a_frame_dt.npz"),
        ("total_mass", 5e5, "b_total_mass.npz"),
    ] {
        let mut npz = springtime::data::npz::Npz::read(&fixture("npz_savez.npz")).unwrap();
        npz.insert(key, springtime::data::npz::Array::scalar(value));
        let sub = format!("damaged_{key}");
        std::fs::create_dir_all(dir.join(&sub)).unwrap();
        npz.write(&dir.join(&sub).join(name)).unwrap();
        fails(
            &springtime(&["data", "check", &sub], &dir),
            &[name, &format!("`{key}`"), "plausible"],
        );
    }
    let mut npz = springtime::data::npz::Npz::read(&fixture("npz_savez.npz")).unwrap();
    npz.insert(
        "gravity",
        springtime::data::npz::Array::f32(&[3], &[0.0, 0.0, -981.0]),
    );
    std::fs::create_dir_all(dir.join("damaged_gravity")).unwrap();
    npz.write(&dir.join("damaged_gravity/g.npz")).unwrap();
    fails(
        &springtime(&["data", "check", "damaged_gravity"], &dir),
        &["g.npz", "`gravity`", "plausible"],
    );
    // A marker accuracy in millimetres written as metres; a plausible one is read as stated.
    for (value, name) in [(2.0, "mm_as_m.npz"), (0.002, "capture.npz")] {
        let mut npz = springtime::data::npz::Npz::read(&fixture("npz_savez.npz")).unwrap();
        npz.insert(
            "position_noise",
            springtime::data::npz::Array::scalar(value),
        );
        std::fs::create_dir_all(dir.join("noise")).unwrap();
        npz.write(&dir.join("noise").join(name)).unwrap();
        let read = springtime::data::Rollout::load(&dir.join("noise").join(name));
        match read {
            Ok(r) => assert_eq!((name, r.position_noise), ("capture.npz", Some(0.002))),
            Err(e) => {
                let e = format!("{e:#}");
                assert!(
                    name == "mm_as_m.npz" && e.contains(name) && e.contains("`position_noise`"),
                    "{e}"
                );
            }
        }
    }
    fails(
        &springtime(&["data", "check", "nowhere"], &dir),
        &["nowhere"],
    );
    std::fs::remove_dir_all(&dir).ok();
}

/// A 5 × 4 sheet, 0.2 m spacing, hanging from its top edge in the x-z plane and swinging about
/// it: vertex `j * 5 + i` at column `i`, row `j` (row 0 on top). Frame 0 is at rest (flat).
fn swinging_cloth(frames: usize) -> Vec<Vec<[f64; 3]>> {
    (0..frames)
        .map(|f| {
            let angle = 0.3 * (2.0 * std::f64::consts::PI * f as f64 / 12.0).sin();
            (0..4)
                .flat_map(|j| {
                    (0..5).map(move |i| {
                        let r = 0.2 * j as f64;
                        [0.2 * i as f64, r * angle.sin(), 1.0 - r * angle.cos()]
                    })
                })
                .collect()
        })
        .collect()
}

/// OBJ text of one frame: quads split into triangles, texture coordinates on the unit square
/// (as most tools write them, whatever the aspect ratio) when `uv`.
fn obj_text(vertices: &[[f64; 3]], uv: bool) -> String {
    let mut s = String::from("# swinging cloth\no cloth\n");
    for v in vertices {
        s += &format!("v {} {} {}\n", v[0], v[1], v[2]);
    }
    if uv {
        for j in 0..4 {
            for i in 0..5 {
                s += &format!("vt {} {}\n", i as f64 / 4.0, 1.0 - j as f64 / 3.0);
            }
        }
    }
    s += "s off\n";
    for j in 0..3 {
        for i in 0..4 {
            let a = j * 5 + i + 1;
            let (b, c, d) = (a + 1, a + 6, a + 5);
            for t in [[a, b, c], [a, c, d]] {
                if uv {
                    s += &format!("f {0}/{0} {1}/{1} {2}/{2}\n", t[0], t[1], t[2]);
                } else {
                    s += &format!("f {} {} {}\n", t[0], t[1], t[2]);
                }
            }
        }
    }
    s
}

fn write_sequence(dir: &Path, frames: &[Vec<[f64; 3]>], uv: bool) {
    std::fs::create_dir_all(dir).unwrap();
    for (f, v) in frames.iter().enumerate() {
        // Unpadded numbers: the import must sort frame_2 before frame_10.
        std::fs::write(dir.join(format!("frame_{f}.obj")), obj_text(v, uv)).unwrap();
    }
}

/// The swinging cloth's frame step (s) and mass (kg), as `import` takes them.
const SWING: [&str; 2] = ["0.04", "0.25"];

fn close(a: f64, b: f64) -> bool {
    (a - b).abs() < 1e-5
}

#[test]
fn import_obj_sequence_pc2_and_csv_give_the_same_loadable_rollout() {
    use springtime::data::Rollout;
    let dir = common::temp_dir("import");
    let cloth = swinging_cloth(13);
    write_sequence(&dir.join("swing"), &cloth, true);
    let out = ok(&import(
        ["obj", "swing", "data"],
        SWING,
        &["--pinned", "0,4"],
        &dir,
    ));
    assert!(out.contains("13 frames of 20 points"), "{out}");
    let r = Rollout::load(&dir.join("data/swing.npz")).unwrap();
    assert_eq!((r.frames, r.landmarks), (13, 20));
    // The faces come along as the key `triangles` (0-based), without a stiffness map.
    let mesh = r.mesh.as_ref().expect("the OBJ's faces are stored");
    assert_eq!(mesh.triangles.len(), 24);
    assert_eq!(mesh.triangles[0], [0, 1, 6]);
    assert_eq!(mesh.stiffness, None);
    // Texture coordinates on the unit square, scaled per axis to the 0.8 m × 0.6 m sheet.
    assert!(
        close(r.width, 0.8) && close(r.height, 0.6),
        "{} × {}",
        r.width,
        r.height
    );
    assert!(
        close(r.rest_uv[7][0], 0.4) && close(r.rest_uv[7][1], 0.4),
        "{:?}",
        r.rest_uv[7]
    );
    assert_eq!(r.pinned.iter().filter(|&&p| p).count(), 2);
    assert!(r.pinned[0] && r.pinned[4]);
    assert_eq!((r.frame_dt, r.total_mass), (0.04, 0.25));
    for f in [0, 2, 10, 12] {
        for i in [0, 7, 19] {
            let p = r.position(f, i);
            for a in 0..3 {
                assert!(close(p[a] as f64, cloth[f][i][a]), "frame {f}, vertex {i}");
            }
        }
    }
    // Nothing is overwritten without --force.
    let swing = ["obj", "swing", "data"];
    fails(&import(swing, SWING, &[], &dir), &["swing.npz", "--force"]);
    ok(&import(swing, SWING, &["--force"], &dir));
    // The imported folder is a usable dataset.
    let out = ok(&springtime(&["data", "check", "data"], &dir));
    assert!(out.contains("frames           13 per file"), "{out}");

    // The same motion as a point cache with its rest mesh.
    let cache = springtime::import::pc2::PointCache {
        start_frame: 1.0,
        sample_rate: 1.0,
        points: 20,
        samples: 13,
        positions: cloth
            .iter()
            .flatten()
            .flat_map(|p| p.map(|c| c as f32))
            .collect(),
    };
    cache.write(&dir.join("swing_cache.pc2")).unwrap();
    std::fs::write(dir.join("rest.obj"), obj_text(&cloth[0], true)).unwrap();
    ok(&import(
        ["pc2", "swing_cache.pc2", "data"],
        SWING,
        &["--rest", "rest.obj"],
        &dir,
    ));
    let p = Rollout::load(&dir.join("data/swing_cache.npz")).unwrap();
    assert_eq!(p.positions, r.positions);
    assert_eq!(p.rest_uv, r.rest_uv);
    assert_eq!(p.mesh, r.mesh);

    // And as tracked points with rest coordinates, rows shuffled.
    let mut csv = String::from("point,frame,x,y,z,u,v,confidence\n");
    for f in (0..13).rev() {
        for i in 0..20 {
            let q = cloth[f][i];
            let (u, v) = (0.2 * (i % 5) as f64, 0.6 - 0.2 * (i / 5) as f64);
            csv += &format!("{i},{f},{},{},{},{u},{v},0.9\n", q[0], q[1], q[2]);
        }
    }
    std::fs::write(dir.join("markers.csv"), csv).unwrap();
    ok(&import(["csv", "markers.csv", "data"], SWING, &[], &dir));
    let c = Rollout::load(&dir.join("data/markers.npz")).unwrap();
    assert_eq!(c.positions, r.positions);
    assert!(c.mesh.is_none(), "tracked points have no mesh");
    assert!(close(c.width, 0.8) && close(c.height, 0.6));
    for (a, b) in c.rest_uv.iter().zip(&r.rest_uv) {
        assert!(close(a[0], b[0]) && close(a[1], b[1]), "{a:?} vs {b:?}");
    }
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn import_obj_without_texture_coordinates_unrolls_the_flat_first_frame() {
    let dir = common::temp_dir("import-flat");
    write_sequence(&dir.join("flat"), &swinging_cloth(4), false);
    let flat = ["obj", "flat", "out"];
    ok(&import(flat, SWING, &[], &dir));
    let r = springtime::data::Rollout::load(&dir.join("out/flat.npz")).unwrap();
    let (w, h) = (r.width.max(r.height), r.width.min(r.height));
    assert!(close(w, 0.8) && close(h, 0.6), "{w} × {h}");
    // --width/--height set the rectangle outright.
    ok(&import(
        flat,
        SWING,
        &["--width", "2", "--height", "1.5", "--force"],
        &dir,
    ));
    let r = springtime::data::Rollout::load(&dir.join("out/flat.npz")).unwrap();
    assert_eq!((r.width, r.height), (2.0, 1.5));
    assert_eq!(
        (r.gravity, r.rayleigh),
        (None, None),
        "nothing stored unless given"
    );
    // --gravity and --rayleigh are stored in the rollout (a y-up tool's gravity here).
    ok(&import(
        flat,
        SWING,
        &["--gravity", "0,-9.8,0", "--rayleigh", "0.05", "--force"],
        &dir,
    ));
    let r = springtime::data::Rollout::load(&dir.join("out/flat.npz")).unwrap();
    assert_eq!(
        r.gravity,
        Some([0.0, -9.8f32 as f64, 0.0]),
        "stored as float32"
    );
    assert_eq!(r.rayleigh, Some(0.05));
    // A gravity of two components is refused, naming the flag.
    fails(
        &import(flat, SWING, &["--gravity", "0,-9.8", "--force"], &dir),
        &["--gravity", "three numbers"],
    );
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn import_errors_name_the_file_frame_and_line() {
    let dir = common::temp_dir("import-bad");
    let cloth = swinging_cloth(4);
    let obj = |folder: &str, extra: &[&str]| import(["obj", folder, "out"], SWING, extra, &dir);
    // A frame with a vertex too few.
    write_sequence(&dir.join("short"), &cloth, true);
    let mut v = cloth[2].clone();
    v.pop();
    let text = obj_text(&v, true).replace("f 15/15 16/16 20/20\n", "");
    let text: String = text
        .lines()
        .filter(|l| !l.contains(" 20/20"))
        .map(|l| format!("{l}\n"))
        .collect();
    std::fs::write(dir.join("short/frame_2.obj"), text).unwrap();
    fails(
        &obj("short", &[]),
        &["frame_2.obj", "frame 2", "19 vertices", "20"],
    );
    // NaN in a frame: file and line.
    write_sequence(&dir.join("nan"), &cloth, true);
    let text = obj_text(&cloth[3], true).replacen("v 0.2 ", "v NaN ", 1);
    std::fs::write(dir.join("nan/frame_3.obj"), text).unwrap();
    fails(
        &obj("nan", &[]),
        &["frame 3", "frame_3.obj", "line 4", "non-finite"],
    );
    // A vertex that no face gives a texture coordinate.
    write_sequence(&dir.join("loose"), &cloth, true);
    let text = obj_text(&cloth[0], true) + "v 9 9 9\n";
    let last_line = text.lines().count().to_string();
    std::fs::write(dir.join("loose/frame_0.obj"), text).unwrap();
    fails(
        &obj("loose", &[]),
        &[
            "frame_0.obj",
            &format!("line {last_line}"),
            "vertex 20",
            "no texture coordinate",
        ],
    );
    // No texture coordinates and a bent first frame: no rest rectangle.
    let mut bent = swinging_cloth(4);
    bent.rotate_left(2);
    write_sequence(&dir.join("bent"), &bent, false);
    let mut curved = bent[0].clone();
    for (k, p) in curved.iter_mut().enumerate() {
        p[1] += 0.05 * ((k % 5) as f64 - 2.0).powi(2);
    }
    std::fs::write(dir.join("bent/frame_0.obj"), obj_text(&curved, false)).unwrap();
    fails(&obj("bent", &[]), &["frame_0.obj", "not flat", "vt"]);
    // A pin that does not exist.
    write_sequence(&dir.join("pins"), &cloth, true);
    fails(
        &obj("pins", &["--pinned", "3,20"]),
        &["--pinned 20", "20 points"],
    );
    // One frame only.
    std::fs::create_dir_all(dir.join("one")).unwrap();
    std::fs::write(dir.join("one/a.obj"), obj_text(&cloth[0], true)).unwrap();
    fails(&obj("one", &[]), &["one", "at least 2 frames"]);
    // A CSV without rest coordinates whose first frame misses a point (a point missing from a
    // later frame is a hidden marker: tests/visibility.rs).
    std::fs::write(
        dir.join("gap.csv"),
        "frame,point,x,y,z\n0,0,0,0,0\n0,2,0,1,0\n1,0,0,0,0\n1,1,1,0,0\n1,2,0,1,0\n",
    )
    .unwrap();
    fails(
        &import(["csv", "gap.csv", "out"], ["0.1", "1"], &[], &dir),
        &["gap.csv", "frame 0 does not see point 1", "u`, `v`"],
    );
    // A truncated point cache.
    std::fs::write(dir.join("bad.pc2"), b"POINTCACHE2\0\x01\0\0\0\x14\0\0\0").unwrap();
    std::fs::write(dir.join("rest.obj"), obj_text(&cloth[0], true)).unwrap();
    fails(
        &import(
            ["pc2", "bad.pc2", "out"],
            ["0.1", "1"],
            &["--rest", "rest.obj"],
            &dir,
        ),
        &["bad.pc2"],
    );
    assert!(!dir.join("out").exists() || std::fs::read_dir(dir.join("out")).unwrap().count() == 0);
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn the_cli_explains_itself() {
    let dir = common::temp_dir("cli-help");
    // Enum options list their values; each subcommand ends with an example.
    let help = ok(&springtime(&["export", "--help"], &dir));
    for needle in [
        "obj",
        "ply-ascii",
        "gltf",
        "glb",
        "pc2",
        "flex",
        "ndarray",
        "wgpu",
        "Example",
    ] {
        assert!(
            help.contains(needle),
            "no {needle:?} in export --help:\n{help}"
        );
    }
    let help = ok(&springtime(&["bench", "--help"], &dir));
    assert!(
        help.contains("fused") && help.contains("reference"),
        "{help}"
    );
    // The bench says which spring-force path ran, not only which was asked for.
    for (backend, kernel, used) in [
        ("flex", "fused", "fused"),
        ("flex", "reference", "tensor"),
        ("wgpu", "fused", "fused"),
        ("wgpu", "reference", "tensor"),
    ] {
        let out = ok(&springtime(
            &[
                "bench",
                "--batch",
                "2",
                "--steps",
                "3",
                "--iters",
                "1",
                "--n",
                "5",
                "--backend",
                backend,
                "--kernel",
                kernel,
            ],
            &dir,
        ));
        let json = out
            .lines()
            .find(|l| l.starts_with('{'))
            .expect("a JSON line");
        let line: serde_json::Value = serde_json::from_str(json).unwrap();
        assert_eq!(line["kernel_used"], used, "{backend} {kernel}: {out}");
        // The test build has no `autotune` feature, and the line says so.
        assert_eq!(line["autotune"], cfg!(feature = "autotune"), "{out}");
    }
    for sub in [
        &["train"][..],
        &["data", "check"],
        &["import", "obj"],
        &["import", "pc2"],
        &["import", "csv"],
        &["config"],
    ] {
        let mut args = sub.to_vec();
        args.push("--help");
        let help = ok(&springtime(&args, &dir));
        assert!(
            help.contains("Example"),
            "no example in {sub:?} --help:\n{help}"
        );
    }
    fails(
        &springtime(&["export", "runs/x", "--format", "stl", "--out", "x"], &dir),
        &["stl", "gltf"],
    );
    // Every config key with its default, as TOML that reads back as a config.
    let defaults = ok(&springtime(&["config", "--defaults"], &dir));
    std::fs::write(dir.join("defaults.toml"), &defaults).unwrap();
    let parsed = springtime::config::Config::load(&dir.join("defaults.toml"), &[]).unwrap();
    assert_eq!(
        parsed.model,
        springtime::config::Config::default().model,
        "{defaults}"
    );
    assert!(defaults.contains("k_init = \"auto\""), "{defaults}");
    assert!(
        defaults.contains("[source.fem]") && defaults.contains("# "),
        "{defaults}"
    );
    let resolved = ok(&springtime(
        &["config", "defaults.toml", "--set", "sim.substeps=3"],
        &dir,
    ));
    assert!(resolved.contains("substeps = 3"), "{resolved}");
    // Shell completions know the subcommands and their options.
    let bash = ok(&springtime(&["completions", "bash"], &dir));
    for needle in ["_springtime()", "import", "--frame-dt", "--gravity", "gltf"] {
        assert!(
            bash.contains(needle),
            "no {needle:?} in the bash completions"
        );
    }
    let fish = ok(&springtime(&["completions", "fish"], &dir));
    assert!(fish.contains("complete -c springtime"), "{fish}");
    fails(
        &springtime(&["completions", "tcsh"], &dir),
        &["tcsh", "bash"],
    );
    let version = ok(&springtime(&["--version"], &dir));
    assert!(version.contains(env!("CARGO_PKG_VERSION")), "{version}");
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn takes_imported_one_by_one_into_one_folder_share_one_rest_rectangle() {
    use springtime::data::Rollout;
    let dir = common::temp_dir("import-takes");
    // Two takes of one cloth; the second starts stretched by 0.5 %, so its first frame's edge
    // lengths give another scale for the same texture coordinates.
    let take_a = swinging_cloth(6);
    let mut take_b = swinging_cloth(6);
    take_b.rotate_left(3);
    for v in take_b[0].iter_mut() {
        v[0] *= 1.005;
    }
    write_sequence(&dir.join("take_a"), &take_a, true);
    write_sequence(&dir.join("take_b"), &take_b, true);
    let into_set = |take: &str| import(["obj", take, "set"], SWING, &[], &dir);
    ok(&into_set("take_a"));
    let joined = into_set("take_b");
    ok(&joined);
    let said = String::from_utf8_lossy(&joined.stdout);
    assert!(said.contains("matched to the set already in"), "{said}");
    let a = Rollout::load(&dir.join("set/take_a.npz")).unwrap();
    let b = Rollout::load(&dir.join("set/take_b.npz")).unwrap();
    assert_eq!((a.width, a.height), (b.width, b.height));
    assert_eq!(a.rest_uv, b.rest_uv);
    // ... so the folder is one usable set.
    ok(&springtime(&["data", "check", "set"], &dir));
    // Imported into another folder, take_b keeps its own (stretched) scale, and a set of the
    // two is refused by `data check`, naming the key.
    ok(&import(["obj", "take_b", "alone"], SWING, &[], &dir));
    let alone = Rollout::load(&dir.join("alone/take_b.npz")).unwrap();
    assert!(
        (alone.width / a.width - 1.005).abs() < 2e-3,
        "{} vs {}",
        alone.width,
        a.width
    );
    std::fs::copy(dir.join("set/take_a.npz"), dir.join("alone/take_a.npz")).unwrap();
    fails(&springtime(&["data", "check", "alone"], &dir), &["width"]);
    std::fs::remove_dir_all(&dir).ok();
}
