//! The library's quickstart: generate a small spring cloth, train the surrogate, evaluate it.
//!
//! `cargo run --release --example quickstart` (about a minute on two cores). The same steps as
//! `springtime train configs/quickstart.toml`, as library calls; the run goes to
//! `runs/example-quickstart/`.

use anyhow::Result;
use springtime::config::Config;
use springtime::progress::Progress;
use springtime::settings::Job;
use springtime::train::{self, TrainOptions};

fn main() -> Result<()> {
    // The shipped config, with the run renamed so it does not touch the main job's folder.
    let config = Config::load(
        "configs/quickstart.toml".as_ref(),
        &["name=\"example-quickstart\"".into()],
    )?;
    let progress = Progress::auto();

    // 1. Data: `[source]` generates `data.dir` when it holds no rollouts yet.
    springtime::ensure_data(&config, &progress)?;

    // 2. Training: per-spring k and b fitted by differentiating simulated rollouts.
    let summary = train::train(&config, &TrainOptions::default(), &progress)?;
    println!(
        "trained {} iterations in {:.1} s",
        summary.iterations, summary.wall_seconds
    );
    if let (Some(k), Some(b)) = (summary.rmse_k, summary.rmse_b) {
        println!("parameter error: rmse_k {k:.4} N/m, rmse_b {b:.4} N·s/m");
    }

    // 3. Evaluation on the held-out test rollouts: writes eval.json in the run directory.
    let report = springtime::run::evaluate(&summary.run_dir, None, None, &[], &progress)?;
    println!(
        "motion RMSE over the test rollouts: {:.4e} m (short horizon), {:.4e} m (long)",
        report.motion_rmse.short.mean, report.motion_rmse.long.mean
    );
    println!("run: {}", summary.run_dir.display());
    Ok(())
}
