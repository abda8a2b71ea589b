//! Import an OBJ frame sequence (one mesh per frame, as Blender, Houdini or Marvelous export
//! it) as a rollout file springtime trains on.
//!
//! `cargo run --release --example import_obj -- [DIR]`: imports the `.obj` frames in `DIR`; with
//! no argument it first writes a small sequence of its own (a sheet falling for 0.5 s) to
//! `target/example-obj/` so the example runs anywhere. The CLI's `springtime import DIR` does
//! the same.

use std::fmt::Write as _;
use std::path::PathBuf;

use anyhow::Result;
use springtime::data::Rollout;
use springtime::import::{ImportOptions, obj};

fn main() -> Result<()> {
    let dir = match std::env::args().nth(1) {
        Some(dir) => PathBuf::from(dir),
        None => write_falling_sheet("target/example-obj/frames".into(), 0.04)?,
    };
    let options = ImportOptions {
        out: "target/example-obj/rollouts".into(),
        frame_dt: 0.04,
        total_mass: 0.1,
        pinned: vec![],
        size: None,
        gravity: None,
        rayleigh: None,
        position_noise: None,
        force: true,
    };
    let summary = obj::import_sequence(&dir, &options)?;
    println!("{summary}");
    // The file is an ordinary rollout: `springtime data check` and training read it as is.
    let rollout = Rollout::load(&summary.path)?;
    println!(
        "frame step {} s, {} landmarks",
        rollout.frame_dt, rollout.landmarks
    );
    Ok(())
}

/// A 6 × 6 sheet with texture coordinates falling freely: `frame_0000.obj`, … in `dir`.
fn write_falling_sheet(dir: PathBuf, dt: f64) -> Result<PathBuf> {
    std::fs::create_dir_all(&dir)?;
    let n = 6;
    for frame in 0..13 {
        let t = frame as f64 * dt;
        let z = 1.0 - 0.5 * 9.81 * t * t;
        let mut text = String::new();
        for j in 0..n {
            for i in 0..n {
                let (u, v) = (i as f64 / (n - 1) as f64, j as f64 / (n - 1) as f64);
                writeln!(text, "v {:.6} {:.6} {z:.6}", 0.5 * u, 0.5 * v)?;
                writeln!(text, "vt {u:.6} {v:.6}")?;
            }
        }
        for j in 0..n - 1 {
            for i in 0..n - 1 {
                let a = j * n + i + 1;
                let (b, c, d) = (a + 1, a + n, a + n + 1);
                writeln!(text, "f {a}/{a} {b}/{b} {d}/{d}\nf {a}/{a} {d}/{d} {c}/{c}")?;
            }
        }
        std::fs::write(dir.join(format!("frame_{frame:04}.obj")), text)?;
    }
    Ok(dir)
}
