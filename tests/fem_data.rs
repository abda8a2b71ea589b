//! Files of the FEM source: a rollout written to `.npz` reads back identical, mesh and
//! stiffness map included; a degenerate mesh gives an error naming the file and the key.

mod common;

use rand::{SeedableRng, rngs::StdRng};
use springtime::data::Rollout;
use springtime::data::npz::{Array, Npz};
use springtime::source::fem::FemCloth;
use springtime::source::{ClothSim, Layout, Scenario, SourceConfig, SourceKind, simulate_rollout};

fn fem_rollout() -> Rollout {
    let cfg = SourceConfig {
        kind: SourceKind::Fem,
        nx: 7,
        ny: 6,
        width: 3.0,
        height: 2.5,
        stiffness_levels: vec![100.0, 400.0, 1000.0],
        layout: Layout::Patches,
        seconds: 0.05,
        ..SourceConfig::default()
    };
    let cloth = FemCloth::from_config(&cfg);
    let scenario = Scenario::random(
        cloth.rest_uv(),
        cfg.anchor_radius,
        &mut StdRng::seed_from_u64(3),
    );
    simulate_rollout(&cloth, &cfg, &scenario, None, "memory").unwrap()
}

#[test]
fn an_fem_rollout_reads_back_identical() {
    let dir = common::temp_dir("fem_data_round_trip");
    let r = fem_rollout();
    let mesh = r.mesh.as_ref().expect("the FEM source writes its mesh");
    assert_eq!(mesh.triangles.len(), 2 * 6 * 5);
    let levels: std::collections::BTreeSet<u32> = mesh
        .stiffness
        .as_ref()
        .unwrap()
        .iter()
        .map(|&s| s.round() as u32)
        .collect();
    assert!(levels.len() >= 2, "{levels:?}");
    let path = dir.join("fem.npz");
    r.save(&path).unwrap();
    let back = Rollout::load(&path).unwrap();
    assert_eq!(back.frames, r.frames);
    assert_eq!(back.landmarks, 42);
    assert_eq!(back.positions, r.positions);
    assert_eq!(back.velocities, r.velocities);
    assert_eq!(back.pinned, r.pinned);
    assert_eq!(back.frame_dt, r.frame_dt);
    assert_eq!(back.total_mass, r.total_mass);
    assert_eq!((back.width, back.height), (r.width, r.height));
    assert_eq!(back.segments, r.segments);
    assert!(back.springs.is_none());
    // rest_uv is stored as float32.
    for (a, b) in back.rest_uv.iter().zip(&r.rest_uv) {
        assert!((a[0] - b[0]).abs() < 1e-6 && (a[1] - b[1]).abs() < 1e-6);
    }
    let back_mesh = back.mesh.as_ref().unwrap();
    assert_eq!(back_mesh.triangles, mesh.triangles);
    let (st_back, st) = (
        back_mesh.stiffness.as_ref().unwrap(),
        mesh.stiffness.as_ref().unwrap(),
    );
    for (a, b) in st_back.iter().zip(st) {
        assert_eq!(*a as f32, *b as f32);
    }
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn a_degenerate_mesh_is_refused_naming_file_and_key() {
    let dir = common::temp_dir("fem_data_degenerate");
    let path = dir.join("flat.npz");
    fem_rollout().save(&path).unwrap();
    let mut npz = Npz::read(&path).unwrap();
    let (mut tri, shape) = npz.int("triangles", &[None, Some(3)]).unwrap();
    // Triangle 4 gets a repeated vertex: zero rest area.
    tri[4 * 3 + 2] = tri[4 * 3 + 1];
    let tri: Vec<i32> = tri.iter().map(|&i| i as i32).collect();
    npz.insert("triangles", Array::i32(&shape, &tri));
    npz.write(&path).unwrap();
    let err = format!("{:#}", Rollout::load(&path).unwrap_err());
    for needle in ["flat.npz", "`triangles`", "triangle 4", "degenerate"] {
        assert!(err.contains(needle), "{needle:?} missing from: {err}");
    }
    // An index out of range is refused too.
    let mut npz = Npz::read(&path).unwrap();
    let (tri, shape) = npz.int("triangles", &[None, Some(3)]).unwrap();
    let mut tri: Vec<i32> = tri.iter().map(|&i| i as i32).collect();
    tri[0] = 42;
    npz.insert("triangles", Array::i32(&shape, &tri));
    npz.write(&path).unwrap();
    let err = format!("{:#}", Rollout::load(&path).unwrap_err());
    assert!(
        err.contains("flat.npz") && err.contains("`triangles`"),
        "{err}"
    );
    std::fs::remove_dir_all(&dir).ok();
}
