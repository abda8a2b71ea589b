//! `springtime sweep`: the library's sweep contract ([`springtime_core::sweep`]) with what the
//! command adds — each job's report page where the plan asks for one (`report = true`) and the
//! gathered figure `sweep.png`.

use std::path::Path;

use anyhow::Result;

use crate::progress::Progress;
pub use springtime_core::sweep::*;
use springtime_plot::{Area, Series, draw_curves, png_figure};

/// [`springtime_core::sweep::run_index`] with the run's report page drawn when the plan asks.
pub fn run_index(plan: &Plan, index: usize, out: &Path, progress: &Progress) -> Result<Outcome> {
    let report = |dir: &Path, progress: &Progress| {
        crate::report::build(dir, &crate::report::ReportOptions::default(), progress).map(|_| ())
    };
    springtime_core::sweep::run_index(plan, index, out, progress, Some(&report))
}

/// [`springtime_core::sweep::gather`] (`sweep.csv`, `sweep.md`) and the figure `sweep.png`.
pub fn gather(plan: &Plan, out: &Path) -> Result<Gathered> {
    let mut gathered = springtime_core::sweep::gather(plan, out)?;
    let png = out.join("sweep.png");
    figure(&png, plan, &gathered.table)?;
    gathered.files.push(png);
    Ok(gathered)
}

/// One panel per axis: the metric against the axis' values (mean, min and max over the other
/// axes' jobs that finished).
fn figure(path: &Path, plan: &Plan, table: &Table) -> Result<()> {
    let long = table.rows.iter().any(|r| r.motion_rmse_long.is_some());
    let metric = if long {
        Metric {
            of: |r| r.motion_rmse_long,
            label: "motion RMSE, long horizon (m)",
        }
    } else {
        Metric {
            of: |r| r.rmse_k,
            label: "rmse_k (N/m)",
        }
    };
    let label = metric.label;
    let panels = plan.axes.len().max(1);
    png_figure(path, 480 * panels as u32, 360, |root| {
        let areas = root.split_evenly((1, panels));
        if plan.axes.is_empty() {
            let points: Vec<(f64, f64)> = table
                .rows
                .iter()
                .filter_map(|r| (metric.of)(r).map(|m| (r.index as f64, m)))
                .collect();
            return draw_curves(
                &areas[0],
                &plan.name,
                "job",
                label,
                &[Series::new(label, points)],
                false,
                &[],
            );
        }
        for (a, area) in areas.iter().enumerate().take(plan.axes.len()) {
            draw_axis(area, plan, table, a, &metric)?;
        }
        Ok(())
    })
}

/// The figure's metric of a job and its label.
struct Metric {
    of: fn(&Row) -> Option<f64>,
    label: &'static str,
}

/// The panel of axis `a`: the metric's mean, min and max over the jobs at each of its values.
fn draw_axis(area: &Area, plan: &Plan, table: &Table, a: usize, metric: &Metric) -> Result<()> {
    let axis = &plan.axes[a];
    let numeric = axis.values.iter().all(|v| v.is_integer() || v.is_float());
    let x_of = |i: usize| -> f64 {
        if numeric {
            axis.values[i]
                .as_float()
                .or(axis.values[i].as_integer().map(|n| n as f64))
                .unwrap_or(i as f64)
        } else {
            i as f64
        }
    };
    let mut mean = Vec::new();
    let mut lo = Vec::new();
    let mut hi = Vec::new();
    for (i, value) in axis.values.iter().enumerate() {
        let m: Vec<f64> = table
            .rows
            .iter()
            .filter(|r| &r.values[a] == value)
            .filter_map(metric.of)
            .collect();
        if m.is_empty() {
            continue;
        }
        let x = x_of(i);
        mean.push((x, m.iter().sum::<f64>() / m.len() as f64));
        lo.push((x, m.iter().copied().fold(f64::INFINITY, f64::min)));
        hi.push((x, m.iter().copied().fold(f64::NEG_INFINITY, f64::max)));
    }
    let x_label = if numeric {
        axis.key.clone()
    } else {
        let names: Vec<String> = axis
            .values
            .iter()
            .enumerate()
            .map(|(i, v)| format!("{i} = {}", value_text(v)))
            .collect();
        format!("{} ({})", axis.key, names.join(", "))
    };
    draw_curves(
        area,
        &format!("{} against {}", plan.name, axis.key),
        &x_label,
        metric.label,
        &[
            Series::new("mean", mean).with_width(2),
            Series::new("min", lo),
            Series::new("max", hi),
        ],
        false,
        &[],
    )
}
