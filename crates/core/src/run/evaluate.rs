//! Evaluating a finished run of any model family: `eval.json` and `motion_rmse.csv`.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Result, bail};

use crate::backend::Backend;
use crate::cloth::{Resampler, Topology};
use crate::data::{Rollout, Split};
use crate::eval::{self, EvalReport, MotionCurves};
use crate::model::SpringNet;
use crate::progress::Progress;
use crate::sim::Physics;
use crate::train::{self, Trained};

/// Evaluates a run and writes its `eval.json`.
pub fn evaluate(
    run_dir: &Path,
    data: Option<&Path>,
    backend: Option<Backend>,
    set: &[String],
    progress: &Progress,
) -> Result<EvalReport> {
    let start = Instant::now();
    let mut loaded = super::Run::open(run_dir, set, backend)?;
    if let Some(d) = data {
        loaded.config.data.test_dir = Some(d.to_path_buf());
    }
    let (config, topo, device, run) = (
        &loaded.config,
        &loaded.topology,
        &loaded.device,
        &loaded.dir,
    );
    let split = config.data.split()?;
    let files = test_files(&split, config.eval.max_rollouts)?;
    let first = Rollout::load(&files[0])?;
    let physics = loaded.physics(first.frame_dt);
    let (curves, frame_dt) = motion_curves(&loaded, &physics, &first, &files, progress)?;
    let motion = eval::summarize(
        &curves.curves,
        frame_dt,
        config.eval.short_seconds,
        config.eval.long_seconds,
    );
    let (rmse_k, rmse_b, stiffness_map_corr) = match &loaded.model {
        Trained::Springs(model) => truth_metrics(model, topo, &first),
        _ => (None, None, None),
    };
    let uniform_baseline = match &loaded.model {
        Trained::Springs(_) if config.eval.uniform_baseline => {
            let mut yardstick = eval::uniform::search(
                topo,
                &physics,
                config.model.uniform_start(),
                &split.train,
                &files,
                &motion,
                &config.eval,
                eval::Objective::WholeTake,
                true,
                device,
                progress,
            )?;
            let ground = super::yardstick::Ground {
                topology: topo,
                physics: &physics,
                train: &split.train,
                test: &files,
                stated_drag: first.rayleigh.is_some(),
                eval: &config.eval,
                device,
                progress,
            };
            yardstick.own_damping =
                Some(super::yardstick::own_damping(&ground, &yardstick, &motion)?);
            Some(yardstick)
        }
        _ => None,
    };
    let report = EvalReport {
        rmse_k,
        rmse_b,
        stiffness_map_corr,
        learned_map_corr: learned_map_corr(&run.learned_springs(), topo, &first)?,
        uniform_baseline,
        validation: eval::Validation::read(&run.dir)?,
        motion_rmse: motion,
        inference: Some(eval::Inference {
            us_per_step: curves.us_per_step(),
            step_dt: frame_dt,
            batch: config.eval.batch.max(1).min(files.len()),
            seconds_per_second: curves.us_per_step() * 1e-6 / frame_dt,
        }),
        test_rollouts: files,
        backend: config.backend.to_string(),
        precision: crate::backend::Precision::of(device),
        seconds: start.elapsed().as_secs_f64(),
    };
    crate::io::write_json(&run.eval(), &report)?;
    eval::write_curves_csv(&run.motion_curves(), &curves.curves)?;
    Ok(report)
}

/// The test rollouts to evaluate on: the split's, at most `max_rollouts` of them (0: all).
fn test_files(split: &Split, max_rollouts: usize) -> Result<Vec<PathBuf>> {
    let mut files = split.test.clone();
    if files.is_empty() {
        bail!("no test rollouts: the data's index lists none; pass --data DIR with test rollouts");
    }
    if max_rollouts > 0 {
        files.truncate(max_rollouts);
    }
    Ok(files)
}

/// The loaded model's motion error curves over `files` and the time step between their
/// points (a trained surrogate is first checked for stability).
fn motion_curves(
    loaded: &super::Run,
    physics: &Physics,
    first: &Rollout,
    files: &[PathBuf],
    progress: &Progress,
) -> Result<(MotionCurves, f64)> {
    let (config, topo, device) = (&loaded.config, &loaded.topology, &loaded.device);
    let takes = eval::Takes {
        topology: topo,
        files,
        batch: config.eval.batch,
        device,
        progress,
        cache: None,
        objective: eval::Objective::WholeTake,
    };
    Ok(match &loaded.model {
        Trained::Springs(_) | Trained::NeuralOde(_) => {
            let model: &dyn crate::model::ForceModel = match &loaded.model {
                Trained::Springs(springs) => {
                    physics
                        .stability_of(topo, springs)
                        .check("the trained surrogate", config.sim.allow_unstable)?;
                    springs
                }
                Trained::NeuralOde(ode) => ode,
                Trained::Gnn(_) => unreachable!("matched above"),
            };
            let c = eval::motion_curves(model, physics, &takes)?;
            (c, first.frame_dt)
        }
        Trained::Gnn(model) => {
            let ds = config.model.gnn.downsample;
            let c = eval::gnn_motion_curves(model, ds, &takes)?;
            (c, first.frame_dt * ds as f64)
        }
    })
}

/// The Spearman correlation with the source's map of the learned springs a run set aside for
/// a uniform network (`springs.learned.npz`: `train.uniform_fallback`, or a blend search that
/// kept no share of the map); `None` where the run kept its learned springs or the data carries
/// no map.
fn learned_map_corr(path: &Path, topo: &Topology, first: &Rollout) -> Result<Option<f64>> {
    let Some(mesh) = first.mesh.as_ref().filter(|_| path.exists()) else {
        return Ok(None);
    };
    let (k, _) = crate::data::npz::Npz::read(path)?.f32("k", &[Some(topo.num_springs())])?;
    let k: Vec<f64> = k.into_iter().map(f64::from).collect();
    Ok(eval::stiffness_map_corr(topo, &k, &first.rest_uv, mesh))
}

/// A spring surrogate against the ground truth of the first test rollout: the RMSE of `k` and
/// of `b` (where the rollout has true springs) and the stiffness map correlation (where it
/// has a mesh).
fn truth_metrics(
    model: &SpringNet,
    topo: &Topology,
    first: &Rollout,
) -> (Option<f64>, Option<f64>, Option<f64>) {
    let (mut rmse_k, mut rmse_b) = (None, None);
    let truth = first.springs.as_ref().and_then(|t| {
        let res = Resampler::new(&first.rest_uv, &topo.rest_uv);
        train::matching_truth(t, topo, &res)
    });
    if let Some((k, b)) = truth {
        rmse_k = Some(train::rmse(&model.k_values(), &k));
        rmse_b = Some(train::rmse(&model.b_values(), &b));
    }
    let stiffness_map_corr = first
        .mesh
        .as_ref()
        .and_then(|mesh| eval::stiffness_map_corr(topo, &model.k_values(), &first.rest_uv, mesh));
    (rmse_k, rmse_b, stiffness_map_corr)
}
