//! Capture-grade tracks: the rollout format's `visible` mask. A hidden landmark changes no loss,
//! gradient or motion RMSE; the reader fills hidden positions and names bad ones; a set with
//! every marker seen is today's result, byte for byte.

mod common;

use burn::tensor::Device;
use springtime::cloth::Resampler;
use springtime::data::npz::{Array, Npz};
use springtime::data::{ClipBatch, Rollout, Track};
use springtime::eval;
use springtime::model::SpringNet;
use springtime::progress::Progress;
use springtime::sim::Physics;
use springtime::train::{ForceOn, LossWeights, loss};

/// A rollout without stored velocities (so velocities are differences of positions, as in a
/// capture) and the first free landmark away from the edge.
fn capture() -> (springtime::source::SourceConfig, Rollout, usize) {
    let cfg = common::source(4, &[10.0, 50.0], 0.08);
    let (_, mut r) = common::rollout(&cfg, 1);
    r.velocities = None;
    let q = (6..r.landmarks)
        .find(|&i| !r.pinned[i])
        .expect("a free landmark");
    (cfg, r, q)
}

/// `r` with landmark `q` hidden in `frames`, its positions there moved by `shift` m.
fn hide(r: &Rollout, q: usize, frames: std::ops::RangeInclusive<usize>, shift: f32) -> Rollout {
    let mut out = r.clone();
    let mut seen = vec![true; r.frames * r.landmarks];
    for f in frames {
        seen[f * r.landmarks + q] = false;
        for c in 0..3 {
            out.positions[(f * r.landmarks + q) * 3 + c] += shift;
        }
    }
    out.visible = Some(seen);
    out
}

fn batch_of(r: &Rollout, topo: &springtime::cloth::Topology, device: &Device) -> ClipBatch {
    let track = Track::new(r, &Resampler::new(&r.rest_uv, &topo.rest_uv));
    let mass = r.total_mass / topo.num_particles() as f64;
    ClipBatch::new(&[(&track, 20)], 30, mass, r.frame_dt, device).unwrap()
}

/// The motion curves of `files` under a uniform network, at `r`'s frame rate and mass.
fn uniform_curves(
    topo: &springtime::cloth::Topology,
    r: &Rollout,
    files: &[std::path::PathBuf],
) -> Vec<eval::Curve> {
    let device = Device::flex();
    let s = topo.num_springs();
    let model = SpringNet::new(topo, &vec![40.0; s], &vec![3.0; s], &device);
    let physics = Physics {
        substeps: 4,
        ..common::finite_difference::physics(r, topo)
    };
    let takes = eval::Takes {
        topology: topo,
        files,
        batch: 1,
        device: &device,
        progress: &Progress::quiet(),
        cache: None,
        objective: eval::Objective::WholeTake,
    };
    eval::motion_curves(&model, &physics, &takes)
        .unwrap()
        .curves
}

/// The loss and its gradients with respect to `k` and `b`.
fn loss_and_grads(
    batch: &ClipBatch,
    topo: &springtime::cloth::Topology,
    physics: &Physics,
    on: ForceOn,
    device: &Device,
) -> (f32, Vec<f64>, Vec<f64>) {
    let s = topo.num_springs();
    let k: Vec<f64> = (0..s)
        .map(|i| 30.0 + 7.0 * (i as f64 * 0.37).sin())
        .collect();
    let b: Vec<f64> = vec![3.0; s];
    let model = SpringNet::new(topo, &k, &b, device);
    let weights = LossWeights {
        position: 100.0,
        ..LossWeights::default()
    };
    let terms = loss(&model, physics, batch, &weights, on);
    let value = terms.total.clone().into_scalar::<f32>();
    let grads = terms.total.backward();
    let g = |t: burn::tensor::Tensor<1>| springtime::model::springs::to_f64(t);
    (
        value,
        g(model.k.val().grad(&grads).expect("k has a gradient")),
        g(model.b.val().grad(&grads).expect("b has a gradient")),
    )
}

/// Moving a hidden landmark's positions changes neither the loss nor its gradients (they are
/// bit-identical), for simulated and frame-difference forces; without the mask the same move
/// changes the loss.
#[test]
fn a_hidden_landmark_changes_no_loss_or_gradient() {
    let device = Device::flex().autodiff();
    let (cfg, r, q) = capture();
    let topo = common::grid_of(&cfg);
    let physics = common::finite_difference::physics(&r, &topo);
    // Frames 20..=50 form the clip; q is hidden in 28..=33.
    let hidden = || hide(&r, q, 28..=33, 0.0);
    let moved = || hide(&r, q, 28..=33, 0.25);
    for on in [ForceOn::Simulated, ForceOn::Frames] {
        let a = loss_and_grads(
            &batch_of(&hidden(), &topo, &device),
            &topo,
            &physics,
            on,
            &device,
        );
        let b = loss_and_grads(
            &batch_of(&moved(), &topo, &device),
            &topo,
            &physics,
            on,
            &device,
        );
        assert!(a.0 > 0.0 && a.0.is_finite(), "{on:?}: loss {}", a.0);
        assert_eq!(a.0, b.0, "{on:?}: the loss moved with a hidden landmark");
        assert_eq!(a.1, b.1, "{on:?}: ∂L/∂k moved with a hidden landmark");
        assert_eq!(a.2, b.2, "{on:?}: ∂L/∂b moved with a hidden landmark");
        // The same move, seen, moves the loss: the mask is what keeps it out.
        let mut seen = moved();
        seen.visible = None;
        let c = loss_and_grads(
            &batch_of(&seen, &topo, &device),
            &topo,
            &physics,
            on,
            &device,
        );
        assert!(
            c.0 != a.0,
            "{on:?}: a seen landmark's move must change the loss"
        );
    }
}

/// The motion RMSE skips hidden landmarks: frames where all are seen score as without a mask
/// (bit-identical), frames with a hidden one score over the seen ones only.
#[test]
fn the_motion_rmse_skips_hidden_landmarks() {
    let dir = common::temp_dir("visibility_eval");
    let (cfg, r, q) = capture();
    let topo = common::grid_of(&cfg);
    let (clean, masked) = (dir.join("clean.npz"), dir.join("masked.npz"));
    r.save(&clean).unwrap();
    // Hidden landmarks' positions are NaN on disk, as a capture writes them.
    let mut m = hide(&r, q, 40..=49, 0.0);
    for f in 40..=49 {
        for c in 0..3 {
            m.positions[(f * r.landmarks + q) * 3 + c] = f32::NAN;
        }
    }
    m.save(&masked).unwrap();
    let curves = uniform_curves(&topo, &r, &[clean, masked]);
    let (a, b) = (&curves[0], &curves[1]);
    assert_eq!(a.len(), b.len());
    let first = r.first_usable_frame();
    for (i, (x, y)) in a.iter().zip(b).enumerate() {
        let frame = first + 1 + i;
        if (40..=49).contains(&frame) {
            assert!(
                x.1 != y.1,
                "frame {frame}: the hidden landmark still counts"
            );
        } else {
            assert_eq!(x, y, "frame {frame}: a frame with every landmark seen");
        }
    }
}

/// A take whose landmark is hidden from its first frame is simulated from the first frame whose
/// state its seen frames give (before it, the landmark's state is extrapolated from later frames
/// alone): its curve is the clean take's, cut to start there, value for value. At most half the
/// take is skipped.
#[test]
fn a_take_starts_where_its_landmarks_have_been_seen() {
    let dir = common::temp_dir("visibility_start");
    let (cfg, r, q) = capture();
    let topo = common::grid_of(&cfg);
    assert_eq!(r.first_state_frame(), r.first_usable_frame());
    let mut m = hide(&r, q, 0..=7, 0.0);
    for f in 0..=7 {
        for c in 0..3 {
            m.positions[(f * r.landmarks + q) * 3 + c] = f32::NAN;
        }
    }
    // First seen in frame 8; its velocity there differences frames 7 and 9.
    assert_eq!(m.first_state_frame(), 9);
    assert_eq!(
        hide(&r, q, 0..=r.frames - 2, 0.0).first_state_frame(),
        (r.frames - 1) / 2,
        "at most half the take is skipped"
    );
    // The clean take from frame 8: its first usable frame is the masked take's frame 9.
    let mut cut = r.clone();
    let n = r.landmarks * 3;
    cut.positions = r.positions[8 * n..].to_vec();
    cut.frames = r.frames - 8;
    cut.segments[0].len = cut.frames;
    let (cut_path, masked) = (dir.join("cut.npz"), dir.join("masked.npz"));
    cut.save(&cut_path).unwrap();
    m.save(&masked).unwrap();
    let curves = uniform_curves(&topo, &r, &[cut_path, masked]);
    assert_eq!(curves[1].len(), r.frames - 1 - 9);
    let values = |c: &[(f64, f64)]| c.iter().map(|x| x.1).collect::<Vec<_>>();
    assert_eq!(values(&curves[0]), values(&curves[1]));
}

/// The reader fills hidden positions by interpolation in time, and refuses a non-finite
/// position that `visible` says was seen, or a landmark seen in no frame, naming file and key.
#[test]
fn the_reader_fills_hidden_positions_and_names_bad_ones() {
    let dir = common::temp_dir("visibility_reader");
    let (_, mut r, q) = capture();
    let n = r.landmarks;
    // The sheet falls and drifts as a whole: x = rest + (0.3 t, 0, −g t²/2).
    let sheet = |f: usize, i: usize| {
        let t = f as f64 * r.frame_dt;
        let [u, v] = r.rest_uv[i];
        [u + 0.3 * t, v, 1.0 - 4.905 * t * t]
    };
    for f in 0..r.frames {
        for i in 0..n {
            for (c, x) in sheet(f, i).into_iter().enumerate() {
                r.positions[(f * n + i) * 3 + c] = x as f32;
            }
        }
    }
    let path = dir.join("take.npz");
    let mut m = hide(&r, q, 3..=9, 0.0);
    for f in 3..=9 {
        for c in 0..3 {
            m.positions[(f * n + q) * 3 + c] = f32::NAN;
        }
    }
    m.save(&path).unwrap();
    let back = Rollout::load(&path).unwrap();
    let seen = back.visible.as_ref().expect("the mask is kept");
    assert!(!seen[4 * n + q] && seen[4 * n + q + 1]);
    // The hidden landmark is carried by its neighbours: on the parabola, not on the chord
    // between its seen frames 2 and 10 (which is off by up to g·(4Δt)²/2).
    for f in 3..=9 {
        let truth = sheet(f, q);
        for c in 0..3 {
            let got = back.position(f, q)[c] as f64;
            assert!(
                (got - truth[c]).abs() < 1e-5,
                "frame {f}, axis {c}: {got} vs {}",
                truth[c]
            );
        }
    }
    // Every other value is the file's.
    for f in 0..r.frames {
        for i in (0..n).filter(|&i| i != q || !(3..=5).contains(&f)) {
            assert_eq!(back.position(f, i), r.position(f, i));
        }
    }

    // A NaN where `visible` says seen.
    let mut npz = Npz::read(&path).unwrap();
    let mut seen = seen.clone();
    seen[4 * n + q] = true;
    npz.insert("visible", Array::bool(&[r.frames, n], &seen));
    npz.write(&path).unwrap();
    let err = format!("{:#}", Rollout::load(&path).unwrap_err());
    assert!(
        err.contains("take.npz")
            && err.contains("`positions`")
            && err.contains(&format!("landmark {q} of frame 4")),
        "{err}"
    );

    // A landmark seen in no frame.
    let mut never = vec![true; r.frames * n];
    for f in 0..r.frames {
        never[f * n + q] = false;
    }
    npz.insert("visible", Array::bool(&[r.frames, n], &never));
    npz.write(&path).unwrap();
    let err = format!("{:#}", Rollout::load(&path).unwrap_err());
    assert!(
        err.contains("take.npz")
            && err.contains("`visible`")
            && err.contains(&format!("landmark {q} is seen in no frame")),
        "{err}"
    );

    // All seen: no mask, the file's own values.
    npz.insert(
        "visible",
        Array::bool(&[r.frames, n], &vec![true; r.frames * n]),
    );
    npz.insert("positions", Array::f32(&[r.frames, n, 3], &r.positions));
    npz.write(&path).unwrap();
    let back = Rollout::load(&path).unwrap();
    assert!(back.visible.is_none());
    assert_eq!(back.positions, r.positions);
}

/// A set whose files say every marker was seen trains to the same bytes as the set without
/// the key: `springs.npz` and the motion figures are those of today.
#[test]
fn every_marker_seen_trains_to_todays_bytes() {
    let dir = common::temp_dir("visibility_all_seen");
    let cwd: &std::path::Path = &dir;
    std::fs::write(cwd.join("tiny.toml"), common::TINY).unwrap();
    common::ok(&common::springtime(&["generate", "tiny.toml"], cwd));
    // A copy of the set with `visible` all true in every file.
    let copy = cwd.join("seen");
    std::fs::create_dir_all(&copy).unwrap();
    let mut files = 0;
    for entry in walk(&cwd.join("data")) {
        let rel = entry.strip_prefix(cwd.join("data")).unwrap();
        let to = copy.join(rel);
        if entry.extension().is_some_and(|e| e == "npz") {
            let mut npz = Npz::read(&entry).unwrap();
            let shape = npz.get("positions").unwrap().shape.clone();
            npz.insert(
                "visible",
                Array::bool(&shape[..2], &vec![true; shape[0] * shape[1]]),
            );
            npz.write(&to).unwrap();
            files += 1;
        } else {
            std::fs::copy(&entry, &to).unwrap();
        }
    }
    assert!(files >= 5, "{files} rollouts copied");
    let train = |data: &str, out: &str| {
        common::ok(&common::springtime(
            &[
                "train",
                "tiny.toml",
                "--set",
                &format!("data.dir={data}"),
                "--out",
                out,
            ],
            cwd,
        ))
    };
    train("data", "runs/plain");
    train("seen", "runs/seen");
    let read = |p: &str| std::fs::read(cwd.join(p)).unwrap();
    assert_eq!(
        read("runs/plain/springs.npz"),
        read("runs/seen/springs.npz"),
        "springs.npz differs"
    );
    let motion = |p: &str| -> serde_json::Value {
        let v: serde_json::Value = serde_json::from_slice(&read(p)).unwrap();
        v["motion_rmse"].clone()
    };
    assert_eq!(
        motion("runs/plain/eval.json"),
        motion("runs/seen/eval.json")
    );
}

fn walk(dir: &std::path::Path) -> Vec<std::path::PathBuf> {
    let mut out = Vec::new();
    for e in std::fs::read_dir(dir).unwrap() {
        let p = e.unwrap().path();
        if p.is_dir() {
            out.extend(walk(&p));
        } else {
            out.push(p);
        }
    }
    out
}

/// `import csv`: a point missing from a frame, or given with empty or `nan` coordinates, is
/// hidden there; the rollout's `visible` mask says so and the reader fills its position.
#[test]
fn import_csv_marks_missing_rows_hidden() {
    let dir = common::temp_dir("visibility_csv");
    let mut csv = String::from("frame,point,x,y,z\n");
    for f in 0..4 {
        for i in 0..4 {
            let (x, y, z) = ((i % 2) as f64, (i / 2) as f64, -0.1 * f as f64);
            match (f, i) {
                (1, 3) => {}                                        // missing row
                (2, 3) => csv += &format!("{f},{i},nan,nan,nan\n"), // NaN coordinates
                (2, 1) => csv += &format!("{f},{i},,,\n"),          // empty coordinates
                _ => csv += &format!("{f},{i},{x},{y},{z}\n"),
            }
        }
    }
    std::fs::write(dir.join("marks.csv"), csv).unwrap();
    common::ok(&common::import(
        ["csv", "marks.csv", "out"],
        ["0.1", "1"],
        &[],
        &dir,
    ));
    let r = Rollout::load(&dir.join("out/marks.npz")).unwrap();
    let seen = r.visible.clone().expect("a mask");
    let hidden: Vec<(usize, usize)> = (0..16)
        .filter(|&k| !seen[k])
        .map(|k| (k / 4, k % 4))
        .collect();
    assert_eq!(hidden, vec![(1, 3), (2, 1), (2, 3)]);
    // Point 3 falls 0.1 m a frame: its hidden frames are filled on that line.
    for f in 0..4 {
        assert!(
            (r.position(f, 3)[2] + 0.1 * f as f32).abs() < 1e-6,
            "frame {f}"
        );
    }
}
