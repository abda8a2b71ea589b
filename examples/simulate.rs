//! Open a trained run and simulate it from a recorded start.
//!
//! `cargo run --release --example simulate -- RUN_DIR ROLLOUT.npz [SECONDS]`, e.g. after the
//! quickstart: `cargo run --release --example simulate -- runs/quickstart
//! data/quickstart/test_000.npz 2`. Prints the surrogate's distance to the recording per second.

use anyhow::{Context, Result};
use springtime::cloth::Resampler;
use springtime::data::{Rollout, Track};
use springtime::eval::{FreeRun, frame_rmse};
use springtime::run::Run;

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let (run_dir, init) = match args.as_slice() {
        [run, init, ..] => (run.as_str(), init.as_str()),
        _ => anyhow::bail!("usage: simulate RUN_DIR ROLLOUT.npz [SECONDS]"),
    };
    let seconds: f64 = args
        .get(2)
        .map_or(Ok(2.0), |s| s.parse())
        .context("SECONDS")?;

    // The run as every command opens it: config, device, grid and the learned springs.
    let run = Run::open(run_dir.as_ref(), &[], None)?;
    let (model, topo) = (run.springs()?, &run.topology);

    // The recording, resampled from its landmarks to the surrogate's particles (Eq. 3).
    let rollout = Rollout::load(init.as_ref())?;
    let track = Track::new(&rollout, &Resampler::new(&rollout.rest_uv, &topo.rest_uv));
    let physics = run.physics(rollout.frame_dt);
    physics
        .stability_of(topo, model)
        .check("the trained surrogate", false)?;

    // A free rollout from the first usable frame, pinned particles following the recording.
    let first = rollout.first_usable_frame();
    let frames = ((seconds / physics.frame_dt).round() as usize).min(track.frames - 1 - first);
    let sim = FreeRun::new(&track, first, frames).simulate(model, &physics, &run.device, |_| {})?;

    let p = topo.num_particles();
    let per_second = (1.0 / physics.frame_dt).round().max(1.0) as usize;
    for f in (0..=frames).step_by(per_second) {
        let ours = &sim.positions[f * p * 3..(f + 1) * p * 3];
        let theirs = &track.positions[(first + f) * p * 3..(first + f + 1) * p * 3];
        let rmse = frame_rmse(ours, theirs);
        println!(
            "t = {:5.2} s: RMSE to the recording {rmse:.4e} m",
            f as f64 * physics.frame_dt
        );
    }
    Ok(())
}
