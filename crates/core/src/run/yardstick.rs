//! The uniform yardstick with its own damping (`eval.json`'s `uniform_baseline.own_damping`):
//! the best uniform network searched at the run's kept physics ([`eval::uniform::search`]),
//! given the drag and viscosity searches the recipe gives the map ([`scale::drag_row`],
//! [`scale::proportional_damping`]). Here, above both, since it takes the yardstick from
//! [`crate::eval`] and the searches from [`crate::train`].

use std::path::PathBuf;

use anyhow::Result;
use burn::tensor::Device;

use crate::cloth::Topology;
use crate::eval::uniform::{
    self, DESCENT_CANDIDATES, OwnDamping, Pick, SEARCH_ROLLOUTS, UniformBaseline,
};
use crate::eval::{self, EvalConfig, MotionRmse};
use crate::model::SpringNet;
use crate::progress::Progress;
use crate::sim::Physics;
use crate::train::scale::{self, Proportional};

/// Where the yardstick's network is searched and measured.
pub(super) struct Ground<'a> {
    /// The run's particles and springs.
    pub topology: &'a Topology,
    /// The run's kept physics, the yardstick's.
    pub physics: &'a Physics,
    /// The split's training rollouts (the first [`SEARCH_ROLLOUTS`] are searched on).
    pub train: &'a [PathBuf],
    /// The test rollouts.
    pub test: &'a [PathBuf],
    /// Whether the files state the drag (the recipe then keeps it, and so does this search).
    pub stated_drag: bool,
    pub eval: &'a EvalConfig,
    pub device: &'a Device,
    pub progress: &'a Progress,
}

/// The best uniform network with its own damping ([`OwnDamping`]) beside `yardstick`, the
/// trained model's test figures `trained` compared with it. The candidates, each on the
/// training takes the yardstick was searched on:
/// - the yardstick itself, at the run's physics;
/// - where the files state no drag, the yardstick's network at each drag of the recipe's row
///   without viscosity (and of the row around its closest, where that is another drag), and its
///   sizes searched again at the closest (`"drag"`; where the files
///   state the drag, at it without viscosity: `"no viscosity"`), unless that is the run's
///   physics, where the yardstick is those sizes;
/// - that network with an isotropic viscosity on each spring, the drag at zero or the stated one
///   (`"viscosity"`: the recipe's row of `β`, then `k` around it).
///
/// The closest on the training takes is kept, as the yardstick itself is picked.
pub(super) fn own_damping(
    ground: &Ground,
    yardstick: &UniformBaseline,
    trained: &MotionRmse,
) -> Result<OwnDamping> {
    let train: Vec<PathBuf> = ground.train.iter().take(SEARCH_ROLLOUTS).cloned().collect();
    let cache = eval::TrackCache::default();
    let takes = eval::Takes {
        topology: ground.topology,
        files: &train,
        batch: ground.eval.batch,
        device: ground.device,
        progress: ground.progress,
        cache: Some(&cache),
        objective: eval::Objective::WholeTake,
    };
    let network = |k: f64, b: f64| SpringNet::uniform(ground.topology, k, b, ground.device);
    let run = *ground.physics;
    let (k_bar, b_bar) = (yardstick.k, yardstick.b);
    let own = yardstick.train_rmse();
    // (network, physics, training RMSE, found by)
    let mut candidates: Vec<(SpringNet, Physics, f64, &str)> =
        vec![(network(k_bar, b_bar), run, own, "run's physics")];
    let no_viscosity = Physics {
        viscosity: 0.0,
        ..run
    };
    let (drag_row, at_drag) = if ground.stated_drag {
        (Vec::new(), no_viscosity)
    } else {
        // The recipe's row around the run's drag, then the same row around its closest where
        // that is another (a run without drag has no octaves around it: its row is rates).
        let yardstick_net = network(k_bar, b_bar);
        let closest = |row: &[(f64, f64)]| {
            row.iter()
                .copied()
                .min_by(|a, b| a.1.total_cmp(&b.1))
                .unwrap_or((run.rayleigh, own))
        };
        let known = (no_viscosity == run).then_some(own);
        let mut row = scale::drag_row(&yardstick_net, &no_viscosity, known, &takes);
        let first = closest(&row);
        if first.0 != run.rayleigh && first.0 > 0.0 {
            let around = Physics {
                rayleigh: first.0,
                ..no_viscosity
            };
            row.extend(scale::drag_row(
                &yardstick_net,
                &around,
                Some(first.1),
                &takes,
            ));
            row.sort_by(|a, b| a.0.total_cmp(&b.0));
            row.dedup_by(|a, b| a.0 == b.0);
        }
        let best = closest(&row).0;
        (
            row,
            Physics {
                rayleigh: best,
                ..no_viscosity
            },
        )
    };
    // The uniform network's sizes at that physics: the yardstick's own where it is the run's.
    let sized = if at_drag == run {
        Some((k_bar, b_bar))
    } else {
        let bar = ground
            .progress
            .bar(DESCENT_CANDIDATES, "own-damping search");
        let score = |k: f64, b: f64| uniform::rollout_rmse(&at_drag, k, b, &takes);
        let found = uniform::descend(&score, (k_bar, b_bar), run.mass, Pick::Lowest, &bar);
        bar.finish();
        let name = if ground.stated_drag {
            "no viscosity"
        } else {
            "drag"
        };
        found.ok().map(|d| {
            candidates.push((network(d.k, d.b), at_drag, d.rmse, name));
            (d.k, d.b)
        })
    };
    if let Some((k, b)) = sized
        && let Some((with, at, record)) = scale::proportional_damping(
            &network(k, b),
            &at_drag,
            &takes,
            Proportional::Viscosity,
            ground.stated_drag,
        )
    {
        candidates.push((with, at, record.after, "viscosity"));
    }
    let (net, physics, train_rmse, found_by) = candidates
        .into_iter()
        .min_by(|a, b| a.2.total_cmp(&b.2))
        .expect("the yardstick is a candidate");
    let tests = eval::Takes {
        files: ground.test,
        cache: None,
        ..takes
    };
    let test = uniform::test_figures(&net, &physics, &tests, ground.eval)?;
    let (k, b) = (net.k_values()[0], net.b_values()[0]);
    Ok(OwnDamping {
        rayleigh: physics.rayleigh,
        viscosity: physics.viscosity,
        k,
        b,
        found_by: found_by.to_string(),
        drag_row,
        train_rmse,
        yardstick_train_rmse: own,
        improvement_long: 1.0 - trained.long.mean / test.long.mean,
        improvement_short: 1.0 - trained.short.mean / test.short.mean,
        test,
    })
}
