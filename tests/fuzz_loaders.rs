//! Thousands of damaged inputs through the public loaders: `.npz` rollouts (byte flips,
//! truncations and insertions in the archive; damaged `.npy` headers and payloads inside a valid
//! archive) and TOML configs. None may panic, and every rollout error names the file.
//! Deterministic (seeded), so a failure reproduces.

use springtime::settings::Job;
use std::io::{Read, Write};
use std::panic::{AssertUnwindSafe, catch_unwind};
use std::path::{Path, PathBuf};

use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

mod common;

fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures")
        .join(name)
}

/// Loads `path` as a rollout: no panic, and an error names the file. Whether it was refused.
fn load_checked(path: &Path, what: &str) -> bool {
    let result = catch_unwind(AssertUnwindSafe(|| springtime::data::Rollout::load(path)));
    match result {
        Err(_) => panic!(
            "Rollout::load panicked on {what} (kept at {})",
            path.display()
        ),
        Ok(Err(e)) => {
            let text = format!("{e:#}");
            let name = path.file_name().unwrap().to_string_lossy();
            assert!(
                text.contains(&*name),
                "{what}: the error does not name the file: {text}"
            );
            true
        }
        Ok(Ok(_)) => false,
    }
}

/// One random damage to `bytes`: flipped bytes, a truncation, an insertion or a run of one
/// byte value (0x00, 0xFF, '9', ' ') over a random span.
fn damage(bytes: &mut Vec<u8>, rng: &mut StdRng, focus: usize) {
    let span = focus.min(bytes.len()).max(1);
    match rng.random_range(0..4) {
        0 => {
            for _ in 0..rng.random_range(1..4) {
                let i = rng.random_range(0..span);
                bytes[i] ^= 1 << rng.random_range(0..8);
            }
        }
        1 => {
            let keep = rng.random_range(0..bytes.len());
            bytes.truncate(keep);
        }
        2 => {
            let i = rng.random_range(0..span);
            let extra: Vec<u8> = (0..rng.random_range(1..16)).map(|_| rng.random()).collect();
            bytes.splice(i..i, extra);
        }
        _ => {
            let value = [0u8, 0xFF, b'9', b' '][rng.random_range(0..4)];
            let i = rng.random_range(0..span);
            let n = rng.random_range(1..8).min(bytes.len() - i);
            bytes[i..i + n].fill(value);
        }
    }
}

#[test]
fn damaged_npz_archives_never_panic_and_errors_name_the_file() {
    let dir = common::temp_dir("fuzz-npz");
    let mut rng = StdRng::seed_from_u64(7);
    let fixtures = [
        "npz_savez.npz",
        "npz_compressed_extras.npz",
        "npz_bigendian_fortran.npz",
        "npz_object_positions.npz",
    ];
    let mut refused = 0;
    for case in 0..1200 {
        let name = fixtures[case % fixtures.len()];
        let mut bytes = std::fs::read(fixture(name)).unwrap();
        let len = bytes.len();
        damage(&mut bytes, &mut rng, len);
        let path = dir.join(format!("case_{case}.npz"));
        std::fs::write(&path, &bytes).unwrap();
        refused += usize::from(load_checked(
            &path,
            &format!("{name} damaged (case {case})"),
        ));
        std::fs::remove_file(&path).ok();
    }
    eprintln!("refused {refused} damaged files");
    // The damage is real: most damaged files are refused (the rest hit unused bytes).
    assert!(refused > 500, "only {refused} damaged files refused");
    std::fs::remove_dir_all(&dir).ok();
}

/// The entries of an archive, in order.
fn entries(path: &Path) -> Vec<(String, Vec<u8>)> {
    let mut zip = zip::ZipArchive::new(std::fs::File::open(path).unwrap()).unwrap();
    (0..zip.len())
        .map(|i| {
            let mut e = zip.by_index(i).unwrap();
            let mut raw = Vec::new();
            e.read_to_end(&mut raw).unwrap();
            (e.name().unwrap().to_string(), raw)
        })
        .collect()
}

#[test]
fn damaged_npy_entries_in_a_valid_archive_never_panic_and_errors_name_the_file() {
    let dir = common::temp_dir("fuzz-npy");
    let mut rng = StdRng::seed_from_u64(11);
    let sources = [
        entries(&fixture("npz_savez.npz")),
        entries(&fixture("npz_bigendian_fortran.npz")),
    ];
    let mut refused = 0;
    for case in 0..1500 {
        let mut files = sources[case % sources.len()].clone();
        let which = rng.random_range(0..files.len());
        // Mostly the header (magic, version, length, the dict with descr/shape/order), where a
        // parser has the most to get wrong; sometimes anywhere.
        let focus = if rng.random_bool(0.8) {
            128
        } else {
            usize::MAX
        };
        damage(&mut files[which].1, &mut rng, focus);
        let path = dir.join(format!("case_{case}.npz"));
        let mut w = zip::ZipWriter::new(std::fs::File::create(&path).unwrap());
        let options = zip::write::SimpleFileOptions::default()
            .compression_method(zip::CompressionMethod::Stored);
        for (name, raw) in &files {
            w.start_file(name.as_str(), options).unwrap();
            w.write_all(raw).unwrap();
        }
        w.finish().unwrap();
        refused += usize::from(load_checked(
            &path,
            &format!("entry {} damaged (case {case})", files[which].0),
        ));
        std::fs::remove_file(&path).ok();
    }
    eprintln!("refused {refused} damaged files");
    // The damage is real: most damaged files are refused (the rest hit unused bytes).
    assert!(refused > 500, "only {refused} damaged files refused");
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn damaged_configs_never_panic() {
    let text = std::fs::read_to_string(
        Path::new(env!("CARGO_MANIFEST_DIR")).join("configs/quickstart.toml"),
    )
    .unwrap();
    let mut rng = StdRng::seed_from_u64(3);
    let mut rejected = 0;
    for case in 0..3000 {
        let mut bytes = text.clone().into_bytes();
        let len = bytes.len();
        damage(&mut bytes, &mut rng, len);
        let damaged = String::from_utf8_lossy(&bytes).into_owned();
        let result = catch_unwind(AssertUnwindSafe(|| {
            springtime::config::Config::parse(&damaged, &[])
        }));
        match result {
            Err(_) => panic!("Config::parse panicked on case {case}:\n{damaged}"),
            Ok(Err(_)) => rejected += 1,
            Ok(Ok(_)) => {}
        }
    }
    // The damage is real: most damaged configs are refused.
    assert!(
        rejected > 1000,
        "only {rejected} of 3000 damaged configs refused"
    );
}
