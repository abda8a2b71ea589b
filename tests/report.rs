//! `report` and `export` end to end on a tiny trained run: every file is written, images
//! decode at their size, the HTML embeds everything, meshes read back with the right counts.

mod common;

use common::{fails, ok, springtime};

use std::path::{Path, PathBuf};

use springtime::cloth::{GridSpec, Topology};
use springtime::data::{MeshTruth, Rollout};

/// The tiny job with two test rollouts, 6 stiffness and 4 damping iterations.
fn tiny() -> String {
    common::tiny_with(&[
        ("test_rollouts = 1", "test_rollouts = 2"),
        ("iterations = 10", "iterations = 6"),
        ("iterations = 5", "iterations = 4"),
    ])
}

/// Trains the tiny run in a fresh directory (with its report) and returns the directory.
fn trained(name: &str) -> (common::TestDir, String) {
    let dir = common::temp_dir(name);
    std::fs::write(dir.join("tiny.toml"), tiny()).unwrap();
    let out = ok(&springtime(&["train", "tiny.toml"], &dir));
    (dir, out)
}

/// Width and height of a PNG, decoding the whole image.
fn png_size(path: &Path) -> (u32, u32) {
    let file = std::fs::File::open(path).unwrap();
    let mut reader = png::Decoder::new(std::io::BufReader::new(file))
        .read_info()
        .unwrap_or_else(|e| panic!("{} is not a PNG: {e}", path.display()));
    let mut buf = vec![0; reader.output_buffer_size().unwrap()];
    let info = reader.next_frame(&mut buf).unwrap();
    assert_eq!(info.color_type, png::ColorType::Rgb);
    // Not a blank canvas: some pixels are dark (text, axes).
    let px = &buf[..info.buffer_size()];
    assert!(
        px.chunks_exact(3).any(|p| p.iter().all(|&c| c < 80)),
        "{} has no dark pixels",
        path.display()
    );
    (info.width, info.height)
}

#[test]
fn train_writes_a_report_with_every_figure_embedded() {
    let (dir, out) = trained("report-train");
    let report = dir.join("runs/tiny/report");
    assert!(
        out.contains("report: runs/tiny/report/report.html"),
        "train does not say where the report is: {out}"
    );
    // Every figure, with the expected pixel size.
    for (file, size) in [
        ("training_curves.png", (3 * 560, 400)),
        ("stiffness_map.png", (3 * 360 + 110, 30 + 2 * 360)),
        ("damping_map.png", (3 * 360 + 110, 30 + 2 * 360)),
        ("fig7.png", (3 * 560, 30 + 400)),
        ("rollout_frames.png", (5 * 270, 30 + 2 * 250)),
    ] {
        let path = report.join(file);
        assert!(path.exists(), "missing {file}");
        assert_eq!(png_size(&path), size, "{file}");
    }
    // The animation: a looping GIF of at most 80 frames of one size.
    let gif_file = std::fs::File::open(report.join("rollout.gif")).unwrap();
    let mut options = gif::DecodeOptions::new();
    options.set_color_output(gif::ColorOutput::RGBA);
    let mut decoder = options.read_info(gif_file).unwrap();
    assert_eq!((decoder.width(), decoder.height()), (760, 430));
    let mut frames = 0;
    while let Some(frame) = decoder.read_next_frame().unwrap() {
        assert!(frame.delay >= 2);
        frames += 1;
    }
    assert!((2..=80).contains(&frames), "{frames} frames");
    // The HTML is self-contained: every image a data: URI, nothing fetched from elsewhere.
    let html = std::fs::read_to_string(report.join("report.html")).unwrap();
    let imgs: Vec<&str> = html.split("<img ").skip(1).collect();
    assert_eq!(imgs.len(), 6, "one <img> per figure");
    for img in &imgs {
        assert!(
            img.starts_with("src=\"data:image/png;base64,")
                || img.starts_with("src=\"data:image/gif;base64,"),
            "an image that is not embedded: {}",
            &img[..img.len().min(80)]
        );
    }
    for external in [
        "src=\"http",
        "href=\"http",
        "src='http",
        "url(",
        "<script",
        "<link",
        "@import",
    ] {
        assert!(!html.contains(external), "the report contains {external}");
    }
    // eval wrote the per-rollout curves the motion panel draws.
    let csv = std::fs::read_to_string(dir.join("runs/tiny/motion_rmse.csv")).unwrap();
    assert!(csv.starts_with("time,rollout_0,rollout_1\n"), "{csv:.80}");
    // A second report over the first, with --data naming test rollouts elsewhere that carry
    // an FEM mesh and stiffness map: the report adds the triangle map.
    let test_dir = dir.join("fem_tests");
    std::fs::create_dir_all(&test_dir).unwrap();
    let index: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("data/index.json")).unwrap())
            .unwrap();
    for f in index["test"].as_array().unwrap() {
        let f = f.as_str().unwrap();
        let mut r = Rollout::load(&dir.join("data").join(f)).unwrap();
        let topo = Topology::grid(
            &GridSpec {
                nx: 6,
                ny: 6,
                ..GridSpec::default()
            },
            r.width,
            r.height,
        );
        let triangles = topo.triangles.clone();
        let stiffness = (0..triangles.len())
            .map(|t| if (t / 2) % 5 < 2 { 1e4 } else { 1e3 })
            .collect();
        r.mesh = Some(MeshTruth {
            triangles,
            stiffness: Some(stiffness),
        });
        r.save(&test_dir.join(f)).unwrap();
    }
    let out = ok(&springtime(
        &["report", "runs/tiny", "--data", "fem_tests"],
        &dir,
    ));
    assert!(out.contains("report.html"), "{out}");
    assert_eq!(
        png_size(&report.join("fem_stiffness.png")),
        (2 * (360 + 110), 30 + 360)
    );
    let html = std::fs::read_to_string(report.join("report.html")).unwrap();
    assert_eq!(html.matches("<img src=\"data:").count(), 7);
    // --data that does not exist is an error naming it.
    fails(
        &springtime(&["report", "runs/tiny", "--data", "no_such_dir"], &dir),
        &["no_such_dir"],
    );
}

#[test]
fn report_without_data_leaves_out_what_needs_rollouts() {
    let dir = common::temp_dir("report-nodata");
    std::fs::write(dir.join("tiny.toml"), tiny()).unwrap();
    ok(&springtime(&["train", "tiny.toml", "--no-report"], &dir));
    assert!(
        !dir.join("runs/tiny/report").exists(),
        "--no-report wrote a report"
    );
    std::fs::remove_dir_all(dir.join("data")).unwrap();
    let out = ok(&springtime(&["report", "runs/tiny"], &dir));
    assert!(out.contains("not available"), "{out}");
    let report = dir.join("runs/tiny/report");
    for f in [
        "training_curves.png",
        "stiffness_map.png",
        "fig7.png",
        "report.html",
    ] {
        assert!(report.join(f).exists(), "missing {f}");
    }
    assert!(!report.join("rollout.gif").exists());
    let html = std::fs::read_to_string(report.join("report.html")).unwrap();
    assert!(html.contains("Left out"));
}

#[test]
fn export_writes_meshes_that_read_back_and_refuses_to_overwrite() {
    let dir = common::temp_dir("export");
    std::fs::write(dir.join("tiny.toml"), tiny()).unwrap();
    ok(&springtime(&["train", "tiny.toml", "--no-report"], &dir));
    // 6 × 6 particles: 36 vertices, 5 × 5 cells of 2 triangles.
    let (verts, faces) = (36, 50);
    for format in ["obj", "ply-ascii"] {
        let ext = &format[..3];
        let (out, out_dir) = export_at_100_fps(&dir, format);
        assert!(out.contains("frames"), "{out}");
        let rest = out_dir.join(format!("rest.{ext}"));
        assert_eq!(
            springtime::export::count_mesh(&rest).unwrap(),
            (verts, faces)
        );
        let frames: Vec<PathBuf> = std::fs::read_dir(out_dir.join("rollout"))
            .unwrap()
            .map(|e| e.unwrap().path())
            .collect();
        // 0.3 s at 100 fps: frames 0, 0.01, …, 0.3 s (the first frame has velocities).
        assert_eq!(frames.len(), 31, "{frames:?}");
        for f in &frames {
            assert_eq!(springtime::export::count_mesh(f).unwrap(), (verts, faces));
        }
        // An independent parse of one frame: every face indexes an existing vertex.
        let text =
            std::fs::read_to_string(out_dir.join(format!("rollout/frame_0030.{ext}"))).unwrap();
        let max_index = if format == "obj" {
            text.lines()
                .filter_map(|l| l.strip_prefix("f "))
                .flat_map(|l| l.split_whitespace())
                .map(|v| v.split('/').next().unwrap().parse::<usize>().unwrap())
                .max()
                .unwrap()
        } else {
            let body = text.split("end_header\n").nth(1).unwrap();
            body.lines()
                .skip(verts)
                .flat_map(|l| l.split_whitespace().skip(1))
                .map(|v| v.parse::<usize>().unwrap() + 1)
                .max()
                .unwrap()
        };
        assert_eq!(max_index, verts);
        // The surrogate as JSON and .npz.
        let json: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(out_dir.join("surrogate.json")).unwrap())
                .unwrap();
        let s = json["springs"].as_array().unwrap().len();
        for key in ["k", "b", "rest_length", "family"] {
            assert_eq!(json[key].as_array().unwrap().len(), s, "{key}");
        }
        assert_eq!(json["masses"].as_array().unwrap().len(), verts);
        assert!(!json["pinned"].as_array().unwrap().is_empty());
        let npz = springtime::data::npz::Npz::read(&out_dir.join("surrogate.npz")).unwrap();
        for key in [
            "springs",
            "rest_length",
            "k",
            "b",
            "mass",
            "pinned",
            "rest_positions",
        ] {
            assert!(npz.has(key), "surrogate.npz lacks {key}");
        }
    }
    check_binary_exports(&dir, verts, faces);
    // Existing files are not overwritten without --force.
    fails(
        &springtime(&["export", "runs/tiny", "--out", "export_obj"], &dir),
        &["rest.obj", "exists", "--force"],
    );
    ok(&springtime(
        &[
            "export",
            "runs/tiny",
            "--out",
            "export_obj",
            "--force",
            "--seconds",
            "0.05",
        ],
        &dir,
    ));
    let n = std::fs::read_dir(dir.join("export_obj/rollout"))
        .unwrap()
        .count();
    assert_eq!(n, 2, "--force left stale frames behind"); // 0.05 s at 30 fps: frames 0 and 1
}

/// `export runs/tiny --format <format> --out export_<format> --fps 100` in `dir`: what it
/// printed, and the folder.
fn export_at_100_fps(dir: &Path, format: &str) -> (String, PathBuf) {
    let out_dir = format!("export_{format}");
    let out = ok(&springtime(
        &[
            "export",
            "runs/tiny",
            "--format",
            format,
            "--out",
            &out_dir,
            "--fps",
            "100",
        ],
        dir,
    ));
    (out, dir.join(out_dir))
}

/// Binary PLY, glTF (JSON and binary, read back with the `gltf` crate) and the point cache of
/// the same 31-frame rollout.
fn check_binary_exports(dir: &Path, verts: usize, faces: usize) {
    let export = |format: &str| export_at_100_fps(dir, format).1;
    // Binary PLY: the header, then vertex 1 as five little-endian floats (x y z s t).
    let ply = export("ply");
    let frame = std::fs::read(ply.join("rollout/frame_0000.ply")).unwrap();
    let end = frame
        .windows(11)
        .position(|w| w == b"end_header\n")
        .unwrap()
        + 11;
    let header = String::from_utf8_lossy(&frame[..end]);
    assert!(
        header.starts_with("ply\nformat binary_little_endian 1.0\n"),
        "{header}"
    );
    assert!(
        header.contains(&format!("element vertex {verts}\n")),
        "{header}"
    );
    assert_eq!(frame.len(), end + verts * 20 + faces * 13);
    let float = |o: usize| f32::from_le_bytes(frame[o..o + 4].try_into().unwrap());
    let rest = std::fs::read(ply.join("rest.ply")).unwrap();
    let rest_float = |o: usize| f32::from_le_bytes(rest[o..o + 4].try_into().unwrap());
    // The rest sheet: vertex 1 is one particle spacing (2.5 m / 5) along x, at uv (0.2, 0).
    let rest_end = rest.windows(11).position(|w| w == b"end_header\n").unwrap() + 11;
    let v1 = rest_end + 20;
    assert_eq!(
        [
            rest_float(v1),
            rest_float(v1 + 4),
            rest_float(v1 + 8),
            rest_float(v1 + 12)
        ],
        [0.5, 0.0, 0.0, 0.2]
    );
    let f1 = end + 20;
    assert!(float(f1).is_finite() && float(f1 + 8).is_finite());
    assert_eq!(
        springtime::export::count_mesh(&ply.join("rest.ply")).unwrap(),
        (verts, faces)
    );
    // The first face: 3 corners, indices below the vertex count.
    let f0 = end + verts * 20;
    assert_eq!(frame[f0], 3);
    let corner =
        |k: usize| i32::from_le_bytes(frame[f0 + 1 + 4 * k..f0 + 5 + 4 * k].try_into().unwrap());
    assert!((0..3).all(|k| (0..verts as i32).contains(&corner(k))));

    // glTF: morph targets, one per frame, and a step animation of their weights.
    for format in ["gltf", "glb"] {
        let path = export(format).join(format!("cloth.{format}"));
        let bytes = std::fs::read(&path).unwrap();
        let doc = gltf::Gltf::from_slice(&bytes)
            .unwrap_or_else(|e| panic!("{} does not validate: {e}", path.display()));
        let buffer: Vec<u8> = match doc.blob.clone() {
            Some(blob) => blob,
            None => {
                use base64::Engine;
                let uri = doc.buffers().next().unwrap();
                let gltf::buffer::Source::Uri(uri) = uri.source() else {
                    panic!("no buffer")
                };
                let data = uri.split_once("base64,").unwrap().1;
                base64::engine::general_purpose::STANDARD
                    .decode(data)
                    .unwrap()
            }
        };
        let mesh = doc.meshes().next().unwrap();
        let prim = mesh.primitives().next().unwrap();
        let reader = prim.reader(|_| Some(buffer.as_slice()));
        let rest: Vec<[f32; 3]> = reader.read_positions().unwrap().collect();
        assert_eq!(rest.len(), verts);
        assert_eq!(reader.read_indices().unwrap().into_u32().count(), faces * 3);
        assert_eq!(reader.read_tex_coords(0).unwrap().into_f32().count(), verts);
        // y-up: the rest sheet (z = 0 in springtime) lies in the x-z plane, y = 0.
        assert!(rest.iter().all(|p| p[1] == 0.0));
        let pos = prim.get(&gltf::Semantic::Positions).unwrap();
        assert_eq!(pos.count(), verts);
        let max: Vec<f64> = serde_json::from_value(pos.max().unwrap()).unwrap();
        assert!((max[0] - 2.5).abs() < 1e-6, "{max:?}");
        let targets: Vec<Vec<[f32; 3]>> = reader
            .read_morph_targets()
            .map(|(p, _, _)| p.unwrap().collect())
            .collect();
        assert_eq!(targets.len(), 31);
        // Frame 0 starts where the test rollout starts: not at rest, and the cloth falls.
        let y_mean = |k: usize| -> f32 {
            targets[k]
                .iter()
                .zip(&rest)
                .map(|(d, r)| d[1] + r[1])
                .sum::<f32>()
                / verts as f32
        };
        assert!(y_mean(30).is_finite() && y_mean(30) != y_mean(0));
        let anim = doc.animations().next().unwrap();
        let channel = anim.channels().next().unwrap();
        assert_eq!(
            channel.target().property(),
            gltf::animation::Property::MorphTargetWeights
        );
        assert_eq!(
            channel.sampler().interpolation(),
            gltf::animation::Interpolation::Step
        );
        let input = channel.sampler().input();
        assert_eq!(input.count(), 31);
        let t_max: Vec<f64> = serde_json::from_value(input.max().unwrap()).unwrap();
        assert!((t_max[0] - 0.3).abs() < 1e-5, "{t_max:?}");
        let r = channel.reader(|_| Some(buffer.as_slice()));
        let gltf::animation::util::ReadOutputs::MorphTargetWeights(w) = r.read_outputs().unwrap()
        else {
            panic!("not weights")
        };
        let w: Vec<f32> = w.into_f32().collect();
        assert_eq!(w.len(), 31 * 31);
        assert_eq!(&w[31 * 5..31 * 6].iter().position(|&x| x == 1.0), &Some(5));
    }

    // Point cache: header, then frame 30 equals the OBJ export's frame 30.
    let pc2 = export("pc2");
    assert_eq!(
        springtime::export::count_mesh(&pc2.join("rest.obj")).unwrap(),
        (verts, faces)
    );
    let cache = springtime::import::pc2::PointCache::read(&pc2.join("rollout.pc2")).unwrap();
    assert_eq!((cache.points, cache.samples), (verts, 31));
    let bytes = std::fs::read(pc2.join("rollout.pc2")).unwrap();
    assert_eq!(&bytes[..12], b"POINTCACHE2\0");
    assert_eq!(bytes.len(), 32 + 31 * verts * 12);
    let obj = std::fs::read_to_string(dir.join("export_obj/rollout/frame_0030.obj")).unwrap();
    let first_v: Vec<f32> = obj
        .lines()
        .find_map(|l| l.strip_prefix("v "))
        .unwrap()
        .split_whitespace()
        .map(|x| x.parse().unwrap())
        .collect();
    let o = 30 * verts * 3;
    assert_eq!(&cache.positions[o..o + 3], &first_v[..]);
}

#[test]
fn report_and_export_refuse_unfinished_or_missing_runs() {
    let dir = common::temp_dir("report-errors");
    fails(
        &springtime(&["report", "no_such_run"], &dir),
        &["no_such_run/run.json", "not a run directory"],
    );
    fails(
        &springtime(&["export", "no_such_run", "--out", "x"], &dir),
        &["no_such_run/run.json"],
    );
    // An interrupted run.
    let run = dir.join("runs/half");
    std::fs::create_dir_all(&run).unwrap();
    std::fs::write(
        run.join("run.json"),
        r#"{"status":"running","iteration":3,"checkpoint":0,"backend":"flex","wall_seconds":1.0,"peak_rss_mib":10.0}"#,
    )
    .unwrap();
    fails(
        &springtime(&["report", "runs/half"], &dir),
        &["not finished", "running"],
    );
    // Finished but missing its model.
    std::fs::write(
        run.join("run.json"),
        r#"{"status":"finished","iteration":3,"checkpoint":0,"backend":"flex","wall_seconds":1.0,"peak_rss_mib":10.0}"#,
    )
    .unwrap();
    std::fs::write(run.join("config.toml"), "name = \"half\"\n").unwrap();
    fails(
        &springtime(&["report", "runs/half"], &dir),
        &["model.json", "incomplete"],
    );
    fails(
        &springtime(
            &["export", "runs/half", "--format", "stl", "--out", "x"],
            &dir,
        ),
        &["stl"],
    );
}

#[test]
fn plotting_primitives_write_pngs_of_their_size() {
    use springtime::cloth::SpringFamily;
    use springtime::plot;
    let dir = common::temp_dir("plot-primitives");
    let topo = Topology::grid(
        &GridSpec {
            nx: 5,
            ny: 4,
            ..GridSpec::default()
        },
        2.0,
        1.5,
    );
    let values: Vec<f64> = (0..topo.num_springs()).map(|s| s as f64).collect();
    let range = plot::value_range(&[&values]);
    let map = dir.join("map.png");
    let bending = plot::Map::Springs {
        topology: &topo,
        family: Some(SpringFamily::Bending),
    };
    plot::map_png(&map, bending, &values, "k", range, "k (N/m)").unwrap();
    assert_eq!(
        png_size(&map),
        (plot::MAP_PANEL.0 + plot::COLORBAR_WIDTH, plot::MAP_PANEL.1)
    );
    let tris = topo.triangles.clone();
    let tv: Vec<f64> = (0..tris.len()).map(|t| (t % 3) as f64).collect();
    let tmap = dir.join("tri.png");
    let triangles = |triangles| plot::Map::Triangles {
        rest_uv: &topo.rest_uv,
        triangles,
    };
    plot::map_png(&tmap, triangles(&tris), &tv, "FEM", (0.0, 2.0), "E").unwrap();
    assert_eq!(
        png_size(&tmap),
        (plot::MAP_PANEL.0 + plot::COLORBAR_WIDTH, plot::MAP_PANEL.1)
    );
    let curves = dir.join("curves.png");
    let series = vec![
        plot::Series::new("a", (1..50).map(|i| (i as f64, 1.0 / i as f64)).collect()),
        plot::Series::new("b", (1..50).map(|i| (i as f64, 0.0)).collect()),
    ];
    plot::curves_png(&curves, "curves", "x", "y", &series, true).unwrap();
    assert_eq!(png_size(&curves), plot::PLOT_PANEL);
    // Mismatched lengths are errors, not panics.
    let all = plot::Map::Springs {
        topology: &topo,
        family: None,
    };
    assert!(plot::map_png(&map, all, &[1.0], "k", range, "k").is_err());
    assert!(plot::map_png(&tmap, triangles(&[[0, 1, 99]]), &[1.0], "t", range, "E").is_err());
}
