//! Sweeps: many training jobs from one plan (`springtime sweep PLAN.toml`), run by any engine
//! that can hand out indices — a shell loop, a Slurm array, a Kubernetes Indexed Job, Ray
//! (`springtime.sweep` in the Python package).
//!
//! The contract every engine drives is three calls: [`Plan::jobs`] (`--list`), [`run_index`]
//! (`--index I`: job `I` into `OUT/<I>-<slug>/`, resuming an interrupted run and skipping a
//! finished one) and [`gather`] (`--gather`: one table of every job, missing and failed ones
//! listed). A job is a function of the plan and its index only, so the same index gives the
//! same figures on any machine and after any number of retries.

mod plan;

use std::path::{Path, PathBuf};
use std::time::{Instant, SystemTime, UNIX_EPOCH};

use anyhow::{Context, Result};
use serde::{Deserialize, Serialize};

pub use plan::{Axis, Job, Plan};

use crate::eval::EvalReport;
use crate::progress::Progress;
use crate::train::run::{RunDir, Status};
use crate::train::{self, TrainOptions};

/// The file in a job's folder that records what the sweep did with it.
pub const JOB_FILE: &str = "sweep_job.json";

/// The default output folder of a plan: `runs/<plan name>`.
pub fn default_out(plan: &Plan) -> PathBuf {
    Path::new("runs").join(&plan.name)
}

/// `sweep_job.json`: a job's index, its overrides and how it ended.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct JobRecord {
    /// Position in the plan.
    pub index: usize,
    /// The overrides it applied to the base config.
    pub overrides: Vec<String>,
    /// The plan file.
    pub plan: PathBuf,
    /// `finished` or `failed`.
    pub status: JobStatus,
    /// The error, when failed.
    #[serde(default)]
    pub error: Option<String>,
    /// Whether this attempt continued an interrupted run (`true`) or started it.
    pub resumed: bool,
    /// Wall time of this attempt, s.
    pub seconds: f64,
    /// Unix times of this attempt's start and end, s.
    pub started_unix: f64,
    /// See `started_unix`.
    pub finished_unix: f64,
    /// The machine that ran it.
    pub host: String,
}

/// Where a job stands.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum JobStatus {
    /// Trained and evaluated.
    Finished,
    /// Stopped on an error (the record says which).
    Failed,
    /// Started and not finished: under way, or interrupted (running it again resumes it).
    Unfinished,
    /// Never started: its folder does not exist.
    Missing,
}

impl JobStatus {
    /// The lower-case name written in tables.
    pub fn name(self) -> &'static str {
        match self {
            Self::Finished => "finished",
            Self::Failed => "failed",
            Self::Unfinished => "unfinished",
            Self::Missing => "missing",
        }
    }
}

/// What [`run_index`] did.
#[derive(Debug, Clone, PartialEq)]
pub enum Outcome {
    /// The job was already finished: nothing ran.
    Skipped(PathBuf),
    /// The job ran (or resumed) to the end.
    Finished(JobRecord),
}

/// What draws a finished job's report page (`report = true` in a plan): the command line
/// passes its `report` command; without one the page is left out with a note.
pub(crate) type Reporter<'a> = &'a dyn Fn(&Path, &Progress) -> Result<()>;

/// Runs job `index` of `plan` into `out/<index>-<slug>/`: trains it (resuming an interrupted
/// run from its last checkpoint), evaluates it, draws its report page when the plan asks and a
/// `reporter` is given, and writes [`JOB_FILE`]. A job already finished is skipped. On failure
/// the record says why and the error is returned.
pub fn run_index(
    plan: &Plan,
    index: usize,
    out: &Path,
    progress: &Progress,
    reporter: Option<Reporter<'_>>,
) -> Result<Outcome> {
    let job = plan.job(index)?;
    let dir = out.join(&job.dir_name);
    if read_record(&dir)?.is_some_and(|r| r.status == JobStatus::Finished) {
        return Ok(Outcome::Skipped(dir));
    }
    let started = Instant::now();
    let started_unix = unix_now();
    let run = RunDir::new(dir.clone());
    let state = run.state().ok().flatten();
    let resumed = state.as_ref().is_some_and(|s| s.status != Status::Finished);
    progress.note(&format!(
        "sweep job {index} of {} ({}): {}{}",
        plan.len(),
        job.dir_name,
        if job.overrides.is_empty() {
            "the base config".to_string()
        } else {
            job.overrides.join(" ")
        },
        if resumed { " — resuming" } else { "" }
    ));
    let result = (|| -> Result<()> {
        let config = plan.config(&job)?;
        if state.as_ref().is_none_or(|s| s.status != Status::Finished) {
            let options = TrainOptions {
                out: Some(dir.clone()),
                resume: resumed,
                // A folder without a run (a failed start's record) is started over.
                force: !resumed,
            };
            train::train(&config, &options, progress)?;
        }
        if !config.data.split()?.test.is_empty() {
            crate::run::evaluate(&dir, None, None, &[], progress)?;
        }
        if plan.report && config.model.kind == crate::model::ModelKind::Springs {
            match reporter {
                Some(report) => report(&dir, progress)?,
                None => progress.note(&format!(
                    "report = true: the page is drawn by the command line (`springtime report {}`)",
                    dir.display()
                )),
            }
        }
        Ok(())
    })();
    let record = JobRecord {
        index,
        overrides: job.overrides.clone(),
        plan: plan.path.clone(),
        status: if result.is_ok() {
            JobStatus::Finished
        } else {
            JobStatus::Failed
        },
        error: result.as_ref().err().map(|e| format!("{e:#}")),
        resumed,
        seconds: started.elapsed().as_secs_f64(),
        started_unix,
        finished_unix: unix_now(),
        host: host(),
    };
    std::fs::create_dir_all(&dir).with_context(|| format!("cannot create {}", dir.display()))?;
    crate::io::write_json(&dir.join(JOB_FILE), &record)?;
    result.with_context(|| format!("sweep job {index} ({})", dir.display()))?;
    Ok(Outcome::Finished(record))
}

fn read_record(dir: &Path) -> Result<Option<JobRecord>> {
    let path = dir.join(JOB_FILE);
    if !path.is_file() {
        return Ok(None);
    }
    crate::io::read_json(&path).map(Some)
}

fn unix_now() -> f64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0.0, |d| d.as_secs_f64())
}

fn host() -> String {
    std::env::var("HOSTNAME")
        .ok()
        .filter(|h| !h.is_empty())
        .or_else(|| {
            std::fs::read_to_string("/proc/sys/kernel/hostname")
                .ok()
                .map(|h| h.trim().to_string())
        })
        .unwrap_or_else(|| "unknown".into())
}

/// One row of the gathered table: a job, its axis values and its figures.
#[derive(Debug, Clone, PartialEq)]
pub struct Row {
    /// The job's index.
    pub index: usize,
    /// One value per axis.
    pub values: Vec<toml::Value>,
    /// Where it stands.
    pub status: JobStatus,
    /// RMSE of the learned `k` against the source's, N/m, where known.
    pub rmse_k: Option<f64>,
    /// RMSE of `b`, N·s/m, where known.
    pub rmse_b: Option<f64>,
    /// Motion RMSE over the test rollouts' short horizon, m.
    pub motion_rmse_short: Option<f64>,
    /// Motion RMSE over the long horizon, m.
    pub motion_rmse_long: Option<f64>,
    /// Gain over the best uniform network over the short horizon (`eval.uniform_baseline`).
    pub uniform_gain_short: Option<f64>,
    /// Gain over the best uniform network over the long horizon.
    pub uniform_gain_long: Option<f64>,
    /// Spearman correlation of the learned map with the source's, where known.
    pub spearman: Option<f64>,
    /// Wall time of the job's last attempt, s.
    pub seconds: Option<f64>,
    /// The job's folder.
    pub dir: PathBuf,
    /// Why it failed.
    pub error: Option<String>,
}

/// The gathered table of a plan.
#[derive(Debug, Clone, PartialEq)]
pub struct Table {
    /// The axes' keys, the columns after `index`.
    pub axes: Vec<String>,
    /// One row per job, in index order.
    pub rows: Vec<Row>,
}

impl Table {
    /// The indices with `status`.
    pub fn indices(&self, status: JobStatus) -> Vec<usize> {
        self.rows
            .iter()
            .filter(|r| r.status == status)
            .map(|r| r.index)
            .collect()
    }

    /// The columns: `index`, one per axis, `status`, the figures, `seconds`, `dir`, `error`.
    pub fn header(&self) -> Vec<String> {
        let mut h = vec!["index".to_string()];
        h.extend(self.axes.iter().cloned());
        h.extend(
            [
                "status",
                "rmse_k",
                "rmse_b",
                "motion_rmse_short",
                "motion_rmse_long",
                "uniform_gain_short",
                "uniform_gain_long",
                "spearman",
                "seconds",
                "dir",
                "error",
            ]
            .map(String::from),
        );
        h
    }

    /// A row's cells as JSON values, in [`header`](Self::header)'s order.
    pub fn cells(row: &Row) -> Vec<serde_json::Value> {
        use serde_json::Value as J;
        let num = |v: Option<f64>| v.map_or(J::Null, |x| serde_json::json!(x));
        let mut c = vec![serde_json::json!(row.index)];
        c.extend(row.values.iter().map(toml_to_json));
        c.extend([
            J::String(row.status.name().into()),
            num(row.rmse_k),
            num(row.rmse_b),
            num(row.motion_rmse_short),
            num(row.motion_rmse_long),
            num(row.uniform_gain_short),
            num(row.uniform_gain_long),
            num(row.spearman),
            num(row.seconds),
            J::String(row.dir.display().to_string()),
            row.error.clone().map_or(J::Null, J::String),
        ]);
        c
    }

    /// The rows as JSON objects keyed by the header.
    pub fn to_json(&self) -> serde_json::Value {
        let header = self.header();
        serde_json::Value::Array(
            self.rows
                .iter()
                .map(|r| {
                    serde_json::Value::Object(header.iter().cloned().zip(Self::cells(r)).collect())
                })
                .collect(),
        )
    }
}

fn toml_to_json(v: &toml::Value) -> serde_json::Value {
    match v {
        toml::Value::String(s) => serde_json::Value::String(s.clone()),
        toml::Value::Integer(i) => serde_json::json!(i),
        toml::Value::Float(f) => serde_json::json!(f),
        toml::Value::Boolean(b) => serde_json::json!(b),
        other => serde_json::Value::String(other.to_string()),
    }
}

/// An axis value as a table or figure shows it: numbers in full, strings bare.
pub fn value_text(v: &toml::Value) -> String {
    cell_text(&toml_to_json(v))
}

/// A cell as CSV or Markdown text: numbers in full, strings bare, nothing for null.
fn cell_text(v: &serde_json::Value) -> String {
    match v {
        serde_json::Value::Null => String::new(),
        serde_json::Value::String(s) => s.clone(),
        other => other.to_string(),
    }
}

/// Reads every job's folder under `out` into one table (nothing is written).
pub fn collect(plan: &Plan, out: &Path) -> Result<Table> {
    let mut rows = Vec::with_capacity(plan.len());
    for job in plan.jobs()? {
        let dir = out.join(&job.dir_name);
        let mut row = Row {
            index: job.index,
            values: job.values.clone(),
            status: JobStatus::Missing,
            rmse_k: None,
            rmse_b: None,
            motion_rmse_short: None,
            motion_rmse_long: None,
            uniform_gain_short: None,
            uniform_gain_long: None,
            spearman: None,
            seconds: None,
            dir: dir.clone(),
            error: None,
        };
        if dir.exists() {
            row.status = JobStatus::Unfinished;
            if let Some(record) = read_record(&dir)? {
                row.status = record.status;
                row.seconds = Some(record.seconds);
                row.error = record.error;
            }
            let eval = dir.join("eval.json");
            if row.status == JobStatus::Finished && eval.is_file() {
                let e: EvalReport = crate::io::read_json(&eval)?;
                row.rmse_k = e.rmse_k;
                row.rmse_b = e.rmse_b;
                row.motion_rmse_short = Some(e.motion_rmse.short.mean);
                row.motion_rmse_long = Some(e.motion_rmse.long.mean);
                row.uniform_gain_short = e.uniform_baseline.as_ref().map(|u| u.improvement_short);
                row.uniform_gain_long = e.uniform_baseline.as_ref().map(|u| u.improvement_long);
                row.spearman = e.stiffness_map_corr;
            }
        }
        rows.push(row);
    }
    Ok(Table {
        axes: plan.axes.iter().map(|a| a.key.clone()).collect(),
        rows,
    })
}

/// What [`gather`] wrote.
#[derive(Debug, Clone)]
pub struct Gathered {
    /// The table.
    pub table: Table,
    /// `sweep.csv` and `sweep.md` (and `sweep.png` from the command line's gather).
    pub files: Vec<PathBuf>,
}

/// Reads every job under `out` and writes `out/sweep.csv` and `out/sweep.md`; the command
/// line's gather adds the figure `out/sweep.png`.
pub fn gather(plan: &Plan, out: &Path) -> Result<Gathered> {
    let table = collect(plan, out)?;
    std::fs::create_dir_all(out).with_context(|| format!("cannot create {}", out.display()))?;
    let csv_path = out.join("sweep.csv");
    crate::io::write_atomic(&csv_path, |file| {
        let mut w = csv::Writer::from_writer(file);
        w.write_record(table.header())?;
        for r in &table.rows {
            w.write_record(Table::cells(r).iter().map(cell_text))?;
        }
        w.flush()?;
        Ok(())
    })?;
    let md_path = out.join("sweep.md");
    crate::io::write_text(&md_path, &markdown(plan, &table))?;
    Ok(Gathered {
        table,
        files: vec![csv_path, md_path],
    })
}

fn markdown(plan: &Plan, table: &Table) -> String {
    let mut s = format!(
        "# Sweep `{}`\n\nPlan `{}`, base config `{}`: {} jobs.\n\n",
        plan.name,
        plan.path.display(),
        plan.base.display(),
        plan.len()
    );
    for status in [
        JobStatus::Finished,
        JobStatus::Failed,
        JobStatus::Unfinished,
        JobStatus::Missing,
    ] {
        let ids = table.indices(status);
        s += &format!("- {}: {}", status.name(), ids.len());
        if !ids.is_empty() && status != JobStatus::Finished {
            s += &format!(
                " (indices {})",
                ids.iter()
                    .map(|i| i.to_string())
                    .collect::<Vec<_>>()
                    .join(", ")
            );
        }
        s += "\n";
    }
    let header = table.header();
    // The folder and the error make the table too wide: failures are listed below it.
    let shown = header.len() - 2;
    s += &format!("\n| {} |\n", header[..shown].join(" | "));
    s += &format!("|{}\n", "---|".repeat(shown));
    for r in &table.rows {
        // Axis values as written; the figures (after `status`) with five digits.
        let figures = 2 + table.axes.len();
        let cells: Vec<String> = Table::cells(r)[..shown]
            .iter()
            .enumerate()
            .map(|(i, c)| match c {
                serde_json::Value::Number(n) if n.is_f64() && i >= figures => {
                    format!("{:.4e}", n.as_f64().unwrap_or(f64::NAN))
                }
                other => cell_text(other),
            })
            .collect();
        s += &format!("| {} |\n", cells.join(" | "));
    }
    for r in table.rows.iter().filter(|r| r.error.is_some()) {
        s += &format!(
            "\nJob {} failed: {}\n",
            r.index,
            r.error.as_deref().unwrap_or_default()
        );
    }
    s
}
