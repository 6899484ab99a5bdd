//! `drivelab compare`: several runs on one set of axes (speed, i_q, i_d, like Kyslan et al.
//! Fig. 3 and 4) and their metrics side by side.
//!
//! The metrics are recomputed from each run's `trace.csv` and `scenario.toml` (and the faults
//! of its `summary.json`, which end the metrics' windows) with the same function as
//! `summary.json`'s, so runs recorded before a metric existed compare too.

use anyhow::{anyhow, bail, Context, Result};
use drivelab_runtime::config::Scenario;
use drivelab_runtime::trace::TraceRow;
use drivelab_tools::metrics::{speed_metrics_with_faults, SpeedMetrics};
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
    if !dir.exists() {
        bail!("{}: no such run folder", dir.display());
    }
    // A path that is no folder: trace_csv_of says so.
    let trace = crate::plotcmd::trace_csv_of(dir)?;
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
    // Its faults end the metrics' windows, as in the summary.
    let faults = crate::plotcmd::summary_if_any(dir)?.fault_starts();
    let rows = drivelab_runtime::trace::read_csv(&trace)?;
    if rows.is_empty() {
        bail!("{}: trace.csv has no samples", dir.display());
    }
    let metrics = speed_metrics_with_faults(&scenario, &rows, &faults);
    Ok(LoadedRun {
        label: scenario.name.clone(),
        scenario,
        rows,
        metrics,
    })
}

/// A metric with `digits` decimals; one too big to write out (a diverged run's trace can hold
/// 1e308) in exponent form, as `drivelab_runtime::text::readable_numbers` writes it.
fn fmt(v: Option<f64>, digits: usize) -> String {
    v.map(|x| drivelab_runtime::text::readable_numbers(&format!("{x:.digits$}")).into_owned())
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

/// Legend labels: each run's scenario name, and where names repeat (e.g. two clocks of one
/// scenario), the name followed by the shortest tail of its folder's path that tells it from
/// every other run of that name: `kyslan-pi (a/run)`, `kyslan-pi (b/run)`. A folder given
/// twice gets its position on the command line as well (`(run, #2)`), so every label is
/// unique and names one run.
pub fn labels(names: &[String], folders: &[PathBuf]) -> Vec<String> {
    let parts = |p: &PathBuf| -> Vec<String> {
        p.components()
            .filter(|c| matches!(c, std::path::Component::Normal(_)))
            .map(|c| c.as_os_str().to_string_lossy().into_owned())
            .collect()
    };
    let tail = |p: &[String], n: usize| p[p.len().saturating_sub(n)..].join("/");
    let all: Vec<Vec<String>> = folders.iter().map(parts).collect();
    (0..names.len())
        .map(|i| {
            let twins: Vec<usize> = (0..names.len())
                .filter(|&j| j != i && names[j] == names[i])
                .collect();
            if twins.is_empty() {
                return names[i].clone();
            }
            let longest = all[i].len().max(1);
            let n = (1..=longest)
                .find(|&n| twins.iter().all(|&j| tail(&all[j], n) != tail(&all[i], n)))
                .unwrap_or(longest);
            let mut folder = tail(&all[i], n);
            if folder.is_empty() {
                folder = folders[i].display().to_string();
            }
            if twins.iter().any(|&j| all[j] == all[i]) {
                folder = format!("{folder}, #{}", i + 1);
            }
            format!("{} ({folder})", names[i])
        })
        .collect()
}

/// Runs the comparison: loads the runs, prints the table, writes the plots and
/// comparison.json.
pub fn run(args: &CompareArgs) -> Result<()> {
    let mut runs = args
        .runs
        .iter()
        .map(|d| load_run(d))
        .collect::<Result<Vec<_>>>()?;
    let names: Vec<String> = runs.iter().map(|r| r.scenario.name.clone()).collect();
    for (run, label) in runs.iter_mut().zip(labels(&names, &args.runs)) {
        run.label = label;
    }
    let out = match &args.out {
        Some(o) => o.clone(),
        None => args.runs[0]
            .parent()
            .map(|p| p.join("compare"))
            .unwrap_or_else(|| PathBuf::from("compare")),
    };
    crate::launcher::make_folder(&out, "output folder")?;
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
    drivelab_runtime::files::write(
        out.join("comparison.json"),
        serde_json::to_vec_pretty(&summary)?,
    )?;
    crate::outln!("plots and comparison.json in {}", out.display());
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn label_of(runs: &[(&str, &str)]) -> Vec<String> {
        let names: Vec<String> = runs.iter().map(|(n, _)| n.to_string()).collect();
        let folders: Vec<PathBuf> = runs.iter().map(|(_, f)| PathBuf::from(f)).collect();
        labels(&names, &folders)
    }

    #[test]
    fn a_metric_too_big_to_write_out_is_printed_in_exponent_form() {
        // A diverged run's trace can hold 1e308: its overshoot was printed as 311 digits.
        assert_eq!(fmt(Some(1e308), 1), "1e308");
        assert_eq!(fmt(Some(-2.5e300), 2), "-2.5e300");
        assert_eq!(fmt(Some(12.345), 1), "12.3");
        assert_eq!(fmt(Some(f64::NAN), 1), "NaN");
        assert_eq!(fmt(None, 1), "n/a");
    }

    #[test]
    fn labels_are_the_scenario_names_when_they_differ() {
        assert_eq!(
            label_of(&[("kyslan-pi", "runs/a"), ("kyslan-nl", "runs/b")]),
            ["kyslan-pi", "kyslan-nl"]
        );
    }

    #[test]
    fn every_run_of_a_repeated_name_is_labelled_by_its_folder() {
        // Three runs of one scenario: all three get their folder, not only the first two.
        assert_eq!(
            label_of(&[
                ("kyslan-pi", "runs/rt"),
                ("kyslan-pi", "runs/ls"),
                ("kyslan-pi", "runs/x"),
                ("low-rst", "runs/y"),
            ]),
            [
                "kyslan-pi (rt)",
                "kyslan-pi (ls)",
                "kyslan-pi (x)",
                "low-rst"
            ]
        );
    }

    #[test]
    fn equal_folder_names_are_told_apart_by_their_parents() {
        assert_eq!(
            label_of(&[
                ("kyslan-pi", "/tmp/a/run"),
                ("kyslan-pi", "/tmp/b/run"),
                ("kyslan-pi", "/tmp/b/other"),
            ]),
            [
                "kyslan-pi (a/run)",
                "kyslan-pi (b/run)",
                "kyslan-pi (other)"
            ]
        );
    }

    #[test]
    fn a_folder_given_twice_gets_its_position() {
        let l = label_of(&[("kyslan-pi", "runs/rt"), ("kyslan-pi", "runs/rt")]);
        assert_eq!(l, ["kyslan-pi (runs/rt, #1)", "kyslan-pi (runs/rt, #2)"]);
    }
}
