//! Real NumPy files (written by `tests/fixtures/make_npz_fixtures.py`, checked in): the reader
//! skips keys it does not use whatever their dtype, decodes used keys from any numeric dtype,
//! byte order and memory order, and names file, key and dtype when a used key is unusable.

mod common;

use std::path::PathBuf;

use springtime::data::npz::{Dtype, Npz};
use springtime::data::{DataConfig, Rollout};

fn fixture(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures")
        .join(name)
}

/// The values the generator wrote (see `rollout()` in the script).
fn expected_position(f: usize, i: usize) -> [f32; 3] {
    let (u, v) = ((i % 3) as f64 * 0.5, (i / 3) as f64 * 0.5);
    [
        (u + 0.001 * f as f64) as f32,
        (0.01 * f as f64 * v + 0.0001 * i as f64) as f32,
        (-v - 0.002 * f as f64) as f32,
    ]
}

#[test]
fn savez_file_loads_with_the_generators_values() {
    let r = Rollout::load(&fixture("npz_savez.npz")).unwrap();
    assert_eq!((r.frames, r.landmarks), (4, 9));
    for f in 0..4 {
        for i in 0..9 {
            assert_eq!(
                r.position(f, i),
                expected_position(f, i),
                "frame {f}, landmark {i}"
            );
        }
    }
    assert_eq!(r.rest_uv[5], [1.0, 0.5]);
    assert_eq!(
        r.pinned,
        [true, false, true, false, false, false, false, false, false]
    );
    assert_eq!(
        (r.frame_dt, r.total_mass, r.width, r.height),
        (0.01, 0.5, 1.0, 1.0)
    );
}

#[test]
fn compressed_file_with_awkward_extra_keys_loads_and_keeps_them() {
    let path = fixture("npz_compressed_extras.npz");
    let r = Rollout::load(&path).unwrap();
    let plain = Rollout::load(&fixture("npz_savez.npz")).unwrap();
    assert_eq!(r.positions, plain.positions);
    assert_eq!(r.pinned, plain.pinned);

    let npz = Npz::read(&path).unwrap();
    // Strings, bytes, pickled objects, records, complex numbers and datetimes are kept aside.
    for (key, descr) in [
        ("name", "<U5"),
        ("tag", "|S3"),
        ("meta", "|O"),
        ("complex", "<c8"),
        ("when", "<M8[D]"),
    ] {
        assert_eq!(npz.unreadable[key].descr, descr, "{key}");
    }
    assert!(npz.unreadable["record"].descr.contains("('id', '<i4')"));
    // Every numeric width is decoded.
    let half = npz.get("half").unwrap();
    assert_eq!(half.dtype, Dtype::F16);
    assert_eq!(half.to_f32().unwrap(), [0.0, 1.0, 2.0, 3.0, 4.0, 5.0]);
    assert_eq!(npz.int("i8", &[Some(6)]).unwrap().0, [-3, -2, -1, 0, 1, 2]);
    for key in ["i16", "u16", "u32"] {
        assert_eq!(npz.int(key, &[Some(4)]).unwrap().0, [0, 1, 2, 3], "{key}");
    }
    // 2⁶⁴ − 1 does not fit an index, but reads as a number.
    assert!(npz.int("u64", &[Some(1)]).is_err());
    assert_eq!(npz.scalar("u64").unwrap(), 18446744073709551615.0);
    // Asking for an unusable key as numbers names the file, the key and the dtype.
    let err = format!("{:#}", npz.f32("name", &[None]).unwrap_err());
    assert!(
        err.contains("npz_compressed_extras.npz") && err.contains("`name`") && err.contains("<U5"),
        "{err}"
    );

    // A rewrite keeps the keys springtime could not read, byte for byte.
    let dir = common::temp_dir("npz-rewrite");
    let copy = dir.join("copy.npz");
    npz.write(&copy).unwrap();
    let back = Npz::read(&copy).unwrap();
    assert_eq!(back.keys(), npz.keys());
    assert_eq!(back.unreadable, npz.unreadable);
    assert_eq!(back.arrays, npz.arrays);
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn big_endian_fortran_ordered_keys_are_decoded_to_c_order() {
    let r = Rollout::load(&fixture("npz_bigendian_fortran.npz")).unwrap();
    let plain = Rollout::load(&fixture("npz_savez.npz")).unwrap();
    assert_eq!(r.positions, plain.positions);
    assert_eq!(r.rest_uv, plain.rest_uv);
    assert_eq!(r.pinned, plain.pinned);
    assert_eq!(
        (r.frame_dt, r.total_mass, r.width, r.height),
        (0.01, 0.5, 1.0, 1.0)
    );
    let npz = Npz::read(&fixture("npz_bigendian_fortran.npz")).unwrap();
    assert_eq!(npz.unreadable["labels"].descr, "<U1");
}

#[test]
fn an_unusable_dtype_in_a_used_key_names_file_key_and_dtype() {
    let err = format!(
        "{:#}",
        Rollout::load(&fixture("npz_object_positions.npz")).unwrap_err()
    );
    assert!(
        err.contains("npz_object_positions.npz")
            && err.contains("`positions`")
            && err.contains("|O")
            && err.contains("pickled"),
        "{err}"
    );
}

#[test]
fn an_index_json_of_another_tool_is_ignored() {
    let data = DataConfig {
        dir: fixture("foreign_index"),
        ..DataConfig::default()
    };
    let split = data.split().unwrap();
    assert_eq!(split.train, [fixture("foreign_index/take_01.npz")]);
    assert!(split.test.is_empty());

    // Not JSON at all: ignored too.
    let dir = common::temp_dir("npz-foreign-index");
    std::fs::copy(fixture("npz_savez.npz"), dir.join("a.npz")).unwrap();
    std::fs::write(dir.join("index.json"), "<html>not json</html>").unwrap();
    let data = DataConfig {
        dir: dir.to_path_buf(),
        ..DataConfig::default()
    };
    assert_eq!(data.split().unwrap().train, [dir.join("a.npz")]);
    // A later springtime format is an error, not silently ignored.
    std::fs::write(
        dir.join("index.json"),
        r#"{"format": "springtime-rollouts/9", "train": [], "test": []}"#,
    )
    .unwrap();
    let err = format!("{:#}", data.split().unwrap_err());
    assert!(err.contains("springtime-rollouts/9"), "{err}");
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn a_mesh_without_a_stiffness_map_loads_and_a_map_without_a_mesh_is_refused() {
    use springtime::data::npz::Array;
    let dir = common::temp_dir("npz_mesh_keys");
    let mut npz = Npz::read(&fixture("npz_savez.npz")).unwrap();
    // The 3 × 3 landmarks' cells cut along their main diagonals.
    let tris: Vec<i32> = [
        0, 1, 4, 0, 4, 3, 1, 2, 5, 1, 5, 4, 3, 4, 7, 3, 7, 6, 4, 5, 8, 4, 8, 7,
    ]
    .to_vec();
    npz.insert("triangles", Array::i32(&[8, 3], &tris));
    let with_mesh = dir.join("mesh.npz");
    npz.write(&with_mesh).unwrap();
    let r = Rollout::load(&with_mesh).unwrap();
    let mesh = r.mesh.expect("the mesh is read");
    assert_eq!((mesh.triangles.len(), mesh.triangles[1]), (8, [0, 4, 3]));
    assert_eq!(mesh.stiffness, None);

    let mut npz = Npz::read(&fixture("npz_savez.npz")).unwrap();
    npz.insert("tri_stiffness", Array::f32(&[8], &[1.0; 8]));
    let map_only = dir.join("map_only.npz");
    npz.write(&map_only).unwrap();
    let err = format!("{:#}", Rollout::load(&map_only).unwrap_err());
    assert!(
        err.contains("map_only.npz")
            && err.contains("`tri_stiffness`")
            && err.contains("`triangles`"),
        "{err}"
    );
}
