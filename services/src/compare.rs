//! `drivelab compare`: several runs on one set of axes (speed, i_q, i_d, like Kyslan et al.
//! Fig. 3 and 4) and their metrics side by side.
//!
//! The metrics are recomputed from each run's `trace.csv` and `scenario.toml` with the same
//! function as `summary.json`'s, so runs recorded before a metric existed compare too.

use anyhow::{anyhow, bail, Context, Result};
use drivelab_runtime::config::Scenario;
use drivelab_runtime::trace::TraceRow;
use drivelab_tools::metrics::{speed_metrics, SpeedMetrics};
use serde_json::json;
use std::fmt::Write;
use std::path::{Path, PathBuf};

/// Arguments of `drivelab compare`.
#[derive(Debug, clap::Args)]
pub struct CompareArgs {
    /// Run folders (each with trace.csv and scenario.toml, as written by `drivelab run`).
    #[arg(required = true, num_args = 1..)]
    pub runs: Vec<PathBuf>,
    /// Output folder for the comparison plots and comparison.json (default: `compare/` next
    /// to the first run folder).
    #[arg(long, value_name = "DIR")]
    pub out: Option<PathBuf>,
}

/// One run loaded for comparison.
#[derive(Debug)]
pub struct LoadedRun {
    /// Legend label (the scenario name, or the folder name when names repeat).
    pub label: String,
    /// The run's scenario.
    pub scenario: Scenario,
    /// The trace.
    pub rows: Vec<TraceRow>,
    /// Metrics recomputed from the trace.
    pub metrics: SpeedMetrics,
}

/// Loads a run folder; the error names the folder and what is missing, on one line.
pub fn load_run(dir: &Path) -> Result<LoadedRun> {
    if !dir.is_dir() {
        bail!("{}: no such run folder", dir.display());
    }
    let trace = dir.join("trace.csv");
    if !trace.is_file() {
        bail!(
            "{}: no trace.csv in this folder (not a drivelab run folder?)",
            dir.display()
        );
    }
    let sc_path = dir.join("scenario.toml");
    let text = std::fs::read_to_string(&sc_path).with_context(|| {
        format!(
            "{}: cannot read scenario.toml (not a drivelab run folder?)",
            dir.display()
        )
    })?;
    let scenario =
        Scenario::from_toml(&text, &sc_path.display().to_string()).map_err(|e| anyhow!(e))?;
    // The metrics are recomputed from the trace, not read from summary.json; but a
    // summary.json that is there and damaged says the folder is, so it is refused as
    // `drivelab plot` and `drivelab export` refuse it (a folder without one is fine).
    crate::plotcmd::summary_if_any(dir)?;
    let rows = drivelab_runtime::trace::read_csv(&trace)?;
    if rows.is_empty() {
        bail!("{}: trace.csv has no samples", dir.display());
    }
    let metrics = speed_metrics(&scenario, &rows);
    Ok(LoadedRun {
        label: scenario.name.clone(),
        scenario,
        rows,
        metrics,
    })
}

fn fmt(v: Option<f64>, digits: usize) -> String {
    v.map(|x| format!("{x:.digits$}"))
        .unwrap_or_else(|| "n/a".into())
}

/// A row of the table: its name and how to print the metric.
type Row = (&'static str, fn(&SpeedMetrics) -> String);

/// The side-by-side metrics table.
pub fn table(runs: &[LoadedRun]) -> String {
    let rows: [Row; 6] = [
        ("rise time (ms)", |m| fmt(m.rise_time_ms, 2)),
        ("overshoot (%)", |m| fmt(m.overshoot_pct, 1)),
        ("load dip (rad/s)", |m| fmt(m.load_dip_rad_s, 2)),
        ("load recovery (ms)", |m| fmt(m.load_recovery_ms, 1)),
        ("i_d tracking error (A)", |m| fmt(m.id_tracking_error_a, 5)),
        ("steady-state error (rad/s)", |m| {
            fmt(m.steady_state_error_rad_s, 4)
        }),
    ];
    let w0 = rows.iter().map(|r| r.0.len()).max().unwrap_or(0);
    let widths: Vec<usize> = runs.iter().map(|r| r.label.len().max(10)).collect();
    let mut o = String::new();
    let _ = write!(o, "{:<w0$}", "metric");
    for (r, w) in runs.iter().zip(&widths) {
        let _ = write!(o, "  {:>w$}", r.label);
    }
    o.push('\n');
    for (name, f) in &rows {
        let _ = write!(o, "{name:<w0$}");
        for (r, w) in runs.iter().zip(&widths) {
            let _ = write!(o, "  {:>w$}", f(&r.metrics));
        }
        o.push('\n');
    }
    o
}

fn distinct(values: impl Iterator<Item = f64>) -> Vec<f64> {
    let mut v: Vec<f64> = Vec::new();
    for x in values {
        if !v.iter().any(|y| (y - x).abs() < 1e-9) {
            v.push(x);
        }
    }
    v
}

/// Draws speed, i_q and i_d of every run on one set of axes each; returns the files written.
pub fn plot(runs: &[LoadedRun], out: &Path) -> Result<Vec<PathBuf>> {
    type Col = fn(&TraceRow) -> f64;
    let series = |f: Col| -> Vec<(String, Vec<(f64, f64)>)> {
        runs.iter()
            .map(|r| {
                (
                    r.label.clone(),
                    r.rows.iter().map(|x| (x.t * 1e3, f(x))).collect(),
                )
            })
            .collect()
    };
    let speed_refs = distinct(runs.iter().flat_map(|r| {
        r.scenario
            .reference
            .speed_rad_s
            .iter()
            .map(|s| s.value)
            .collect::<Vec<_>>()
    }));
    let id_refs = distinct(runs.iter().flat_map(|r| {
        r.scenario
            .reference
            .i_d_a
            .iter()
            .map(|s| s.value)
            .collect::<Vec<_>>()
    }));
    let iq_limits = distinct(runs.iter().map(|r| r.scenario.i_q_max()));
    let mut files = Vec::new();
    let names = runs
        .iter()
        .map(|r| r.label.as_str())
        .collect::<Vec<_>>()
        .join(" vs ");
    files.extend(drivelab_tools::plot::plot_lines(
        &series(|x| x.omega_m),
        &format!("speed: {names}"),
        "t (ms)",
        "ω_m (rad/s, mechanical)",
        &speed_refs
            .iter()
            .map(|v| (*v, format!("ω* = {v} rad/s")))
            .collect::<Vec<_>>(),
        &out.join("compare_speed"),
    )?);
    files.extend(drivelab_tools::plot::plot_lines(
        &series(|x| x.i_q),
        &format!("q current: {names}"),
        "t (ms)",
        "i_q (A)",
        &iq_limits
            .iter()
            .flat_map(|v| [(*v, format!("i_q limit {v} A")), (-v, format!("-{v} A"))])
            .collect::<Vec<_>>(),
        &out.join("compare_iq"),
    )?);
    files.extend(drivelab_tools::plot::plot_lines(
        &series(|x| x.i_d),
        &format!("d current: {names}"),
        "t (ms)",
        "i_d (A)",
        &id_refs
            .iter()
            .map(|v| (*v, format!("i_d* = {v} A")))
            .collect::<Vec<_>>(),
        &out.join("compare_id"),
    )?);
    Ok(files)
}

/// Runs the comparison: loads the runs, prints the table, writes the plots and
/// comparison.json.
pub fn run(args: &CompareArgs) -> Result<()> {
    let mut runs = args
        .runs
        .iter()
        .map(|d| load_run(d))
        .collect::<Result<Vec<_>>>()?;
    // Repeated scenario names (e.g. two clocks of one scenario): label by folder instead.
    for i in 0..runs.len() {
        if runs.iter().filter(|r| r.label == runs[i].label).count() > 1 {
            let folder = args.runs[i]
                .file_name()
                .map(|f| f.to_string_lossy().into_owned())
                .unwrap_or_else(|| args.runs[i].display().to_string());
            runs[i].label = format!("{} ({folder})", runs[i].scenario.name);
        }
    }
    let out = match &args.out {
        Some(o) => o.clone(),
        None => args.runs[0]
            .parent()
            .map(|p| p.join("compare"))
            .unwrap_or_else(|| PathBuf::from("compare")),
    };
    std::fs::create_dir_all(&out)
        .with_context(|| format!("cannot create output folder {}", out.display()))?;
    crate::out!("{}", table(&runs));
    let files = plot(&runs, &out)?;
    let summary = json!({
        "runs": runs.iter().zip(&args.runs).map(|(r, d)| json!({
            "label": r.label,
            "folder": d.display().to_string(),
            "scenario": r.scenario.name,
            "reproduces": r.scenario.reproduces,
            "metrics": r.metrics,
        })).collect::<Vec<_>>(),
        "plots": files.iter().map(|f| f.file_name().unwrap_or_default().to_string_lossy().into_owned()).collect::<Vec<_>>(),
    });
    std::fs::write(
        out.join("comparison.json"),
        serde_json::to_vec_pretty(&summary)?,
    )?;
    crate::outln!("plots and comparison.json in {}", out.display());
    Ok(())
}
