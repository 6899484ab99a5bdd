//! `drivelab plot RUNDIR`: redraws every figure of a run (traces with references and limits,
//! latency percentiles, fault windows), optionally for a time window.

use crate::expect::usage;
use anyhow::{anyhow, bail, Context, Result};
use std::path::{Path, PathBuf};

/// Arguments of `drivelab plot`.
#[derive(Debug, clap::Args)]
pub struct PlotArgs {
    /// Run folder (with trace.csv and summary.json).
    pub run: PathBuf,
    /// Only this time window, in seconds: START:END (e.g. 0.02:0.06).
    #[arg(long, value_name = "START:END")]
    pub window: Option<String>,
    /// Output folder (default: the run folder).
    #[arg(long, value_name = "DIR")]
    pub out: Option<PathBuf>,
    /// Read the samples from trace.mcap instead of trace.csv, and also draw
    /// latency-per-second.png: the cycle latency's p50, p99 and maximum of each second, µs.
    #[arg(long)]
    pub from_mcap: bool,
}

fn parse_window(w: &str) -> Result<(f64, f64)> {
    let (a, b) = w
        .split_once(':')
        .ok_or_else(|| usage(format!("--window '{w}': expected START:END in seconds")))?;
    let a: f64 = a
        .trim()
        .parse()
        .map_err(|_| usage(format!("--window '{w}': START is not a number of seconds")))?;
    let b: f64 = b
        .trim()
        .parse()
        .map_err(|_| usage(format!("--window '{w}': END is not a number of seconds")))?;
    if !(a.is_finite() && b.is_finite()) {
        return Err(usage(format!(
            "--window '{w}': START and END must be finite numbers of seconds"
        )));
    }
    if a >= b {
        return Err(usage(format!("--window '{w}': START must be before END")));
    }
    Ok((a, b))
}

/// The figures of a run's `summary.json` that plot and export read: each may be absent or
/// null (a run exported or recorded before it existed), but one that is there has its type.
#[derive(Debug, Default, serde::Deserialize)]
pub struct SummaryView {
    scenario: Option<String>,
    clock: Option<String>,
    rate_hz: Option<f64>,
    samples: Option<u64>,
    faults: Option<Vec<FaultView>>,
    /// Export logs them (read there from the JSON; only checked here).
    #[allow(dead_code)]
    supervisor_events: Option<Vec<EventView>>,
}

/// One entry of `summary.json` → `faults`, as plot shades it and export logs it.
#[derive(Debug, serde::Deserialize)]
struct FaultView {
    injected_t_s: Option<f64>,
    /// Export logs the fault at this sample (read there from the JSON); the metrics' windows
    /// end there.
    injected_k: Option<u64>,
    speed_recovered_ms: Option<f64>,
    republished_ms: Option<f64>,
    fault: Option<String>,
    service: Option<String>,
}

/// One entry of `summary.json` → `supervisor_events`, as export logs it (read there from the
/// JSON; only checked here).
#[derive(Debug, serde::Deserialize)]
#[allow(dead_code)]
struct EventView {
    k: Option<u64>,
    event: Option<String>,
    service: Option<String>,
    process: Option<String>,
    detail: Option<String>,
}

impl SummaryView {
    /// The sample time in µs (10 kHz when the summary does not say).
    fn ts_us(&self) -> f64 {
        1e6 / self.rate_hz.unwrap_or(10_000.0)
    }

    /// The sample rate, Hz, when the summary says (finite and above 0).
    pub fn rate_hz(&self) -> Option<f64> {
        self.rate_hz
    }

    /// The number of samples the run recorded (the rows of its trace.csv), when it says.
    pub fn samples(&self) -> Option<u64> {
        self.samples
    }

    /// Where the run's faults began, as its metrics were cut by them.
    pub fn fault_starts(&self) -> Vec<drivelab_tools::metrics::FaultStart> {
        self.faults
            .iter()
            .flatten()
            .filter_map(|f| {
                let t_s = match (f.injected_k, self.rate_hz) {
                    (Some(k), Some(hz)) => k as f64 / hz,
                    _ => f.injected_t_s?,
                };
                Some(drivelab_tools::metrics::FaultStart {
                    t_s,
                    fault: f.fault.clone().unwrap_or_default(),
                })
            })
            .collect()
    }
}

/// The trace.csv of run folder `run`. The error names the folder when it has none, and says
/// what is wrong when the path is there but is no regular file, `run` is no folder, or the
/// file cannot be looked at (no permission): each was "has no trace.csv" before.
pub fn trace_csv_of(run: &Path) -> Result<PathBuf> {
    let path = run.join("trace.csv");
    match std::fs::metadata(&path) {
        Ok(m) if m.is_file() => Ok(path),
        Ok(_) => bail!("{} is not a file (a run's trace is one)", path.display()),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            if run.is_dir() {
                bail!("{} has no trace.csv (not a run folder)", run.display())
            }
            bail!("{} does not exist", run.display())
        }
        Err(e) if e.raw_os_error() == Some(libc::ENOTDIR) => {
            bail!("{} is not a folder (not a run folder)", run.display())
        }
        Err(e) => bail!("cannot read {}: {e}", path.display()),
    }
}

/// A file of a run folder read by `read`, or `None` when the folder has none.
fn file_if_any<T>(path: &Path, read: fn(&Path) -> std::io::Result<T>) -> Result<Option<T>> {
    match read(path) {
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
        r => r
            .map(Some)
            .with_context(|| format!("cannot read {}", path.display())),
    }
}

/// The summary.json of run folder `run`, or the empty view when the folder has none (plot
/// and compare work from trace.csv and do without it). One that is there but cannot be read,
/// is not JSON, is not a JSON object, or has a figure plot or export reads of the wrong type
/// or out of range is an error naming the file.
pub fn summary_if_any(run: &Path) -> Result<SummaryView> {
    Ok(summary_json_if_any(run)?
        .map(|(view, _)| view)
        .unwrap_or_default())
}

/// The summary.json of run folder `run` checked as [`summary_if_any`] checks it: its view
/// and the whole JSON, or `None` when the folder has none.
pub fn summary_json_if_any(run: &Path) -> Result<Option<(SummaryView, serde_json::Value)>> {
    let path = run.join("summary.json");
    let Some(bytes) = file_if_any(&path, |p| std::fs::read(p))? else {
        return Ok(None);
    };
    let v: serde_json::Value =
        serde_json::from_slice(&bytes).with_context(|| format!("{}: not JSON", path.display()))?;
    if !v.is_object() {
        bail!(
            "{}: not a run summary (a JSON object of figures)",
            path.display()
        );
    }
    let view = <SummaryView as serde::Deserialize>::deserialize(&v)
        .with_context(|| format!("{}: not a run summary", path.display()))?;
    if let Some(hz) = view.rate_hz.filter(|hz| !(hz.is_finite() && *hz > 0.0)) {
        bail!(
            "{}: not a run summary: rate_hz = {hz} is not a rate in Hz",
            path.display()
        );
    }
    Ok(Some((view, v)))
}

/// The scenario.toml of run folder `run` (for plot, the figures' current and voltage limit
/// lines) and its text, or `None` when the folder has none. One that is there but cannot be
/// read or is not a scenario is an error naming the file: drawn without it, the limits would
/// be missing without a word.
pub fn scenario_if_any(run: &Path) -> Result<Option<(drivelab_runtime::config::Scenario, String)>> {
    let path = run.join("scenario.toml");
    let Some(text) = file_if_any(&path, |p| std::fs::read_to_string(p))? else {
        return Ok(None);
    };
    let sc = drivelab_runtime::config::Scenario::from_toml(&text, &path.display().to_string())
        .map_err(|e| anyhow!(e))?;
    Ok(Some((sc, text)))
}

/// The error of a plot that a stop signal (SIGINT, SIGTERM …) ended: how far it got.
fn interrupted(how_far: &str) -> anyhow::Error {
    anyhow!(
        "plot interrupted ({}) {how_far}",
        drivelab_runtime::service::stop_signal_name()
    )
}

/// Stops the plot when a stop signal arrived, after `files` were written to `out`.
fn check_stop(files: &[PathBuf], out: &Path) -> Result<()> {
    if !drivelab_runtime::service::stop_requested() {
        return Ok(());
    }
    Err(interrupted(&if files.is_empty() {
        "before any figure was drawn; nothing written".to_string()
    } else {
        format!(
            "after writing {} files to {}; the others not drawn",
            files.len(),
            out.display()
        )
    }))
}

/// Redraws the figures; returns the files written. A stop signal (SIGINT, SIGTERM …) ends
/// it while the trace is read (nothing written) or between two figures (each file written
/// is whole), with an error that says how far it got.
pub fn run(a: &PlotArgs) -> Result<Vec<PathBuf>> {
    drivelab_runtime::service::install_signal_handlers()?;
    let stop = drivelab_runtime::service::stop_requested;
    // Checked before any file is read.
    let window_s = a.window.as_deref().map(parse_window).transpose()?;
    let (rows, seconds) = if a.from_mcap {
        let path = a.run.join("trace.mcap");
        let m = crate::trace_mcap::read(&path).map_err(|e| {
            if stop() {
                interrupted(&format!("reading {}; nothing written", path.display()))
            } else {
                e
            }
        })?;
        (m.rows, m.seconds)
    } else {
        let trace = trace_csv_of(&a.run)?;
        let mut rows = Vec::new();
        drivelab_runtime::trace::for_each_csv_row(&trace, |row| {
            if stop() {
                return Err(interrupted(&format!(
                    "after reading {} rows of {}; nothing written",
                    rows.len(),
                    trace.display()
                )));
            }
            rows.push(row);
            Ok(())
        })?;
        (rows, Vec::new())
    };
    if rows.is_empty() {
        bail!("{}: the trace has no samples", a.run.display());
    }
    if let (Some((t0, t1)), Some(first), Some(last)) = (window_s, rows.first(), rows.last()) {
        if !rows.iter().any(|r| (t0..=t1).contains(&r.t)) {
            bail!(
                "--window '{}': no sample inside; the run covers {} to {} s",
                a.window.as_deref().unwrap_or_default(),
                first.t,
                last.t
            );
        }
    }
    // Before the output folder is made: a refused run folder leaves nothing behind.
    let summary = summary_if_any(&a.run)?;
    let scenario = scenario_if_any(&a.run)?.map(|(sc, _)| sc);
    let out = a.out.clone().unwrap_or_else(|| a.run.clone());
    check_stop(&[], &out)?;
    crate::launcher::make_folder(&out, "output folder")?;
    let windows = summary
        .faults
        .iter()
        .flatten()
        .filter_map(|x| {
            let t0 = x.injected_t_s?;
            let dur = x.speed_recovered_ms.or(x.republished_ms).unwrap_or(200.0) * 1e-3;
            Some((
                t0,
                t0 + dur,
                format!("{} {}", x.fault.as_deref()?, x.service.as_deref()?),
            ))
        })
        .collect();
    let opts = drivelab_tools::plot::TraceFigureOptions {
        window_s,
        current_limit_a: scenario.as_ref().map(|s| s.i_q_max()),
        voltage_limit_v: scenario.as_ref().map(|s| s.u_max()),
        shaded_windows: windows,
        title: format!(
            "{} ({})",
            summary.scenario.as_deref().unwrap_or("run"),
            summary.clock.as_deref().unwrap_or("?")
        ),
    };
    let mut files = drivelab_tools::plot::plot_trace(&rows, &out, &opts)?;
    check_stop(&files, &out)?;
    if !seconds.is_empty() {
        files.extend(latency_per_second(&seconds, &summary, &out)?);
        check_stop(&files, &out)?;
    } else if a.from_mcap {
        crate::errln!(
            "drivelab: note: {} has no per-second figures (an exported trace has none): \
             latency-per-second.png not drawn",
            a.run.join("trace.mcap").display()
        );
    }
    let mut curves = Vec::new();
    let mut hdrs: Vec<PathBuf> = std::fs::read_dir(&a.run)?
        .flatten()
        .map(|e| e.path())
        .filter(|p| p.extension().is_some_and(|e| e == "hdr"))
        .collect();
    hdrs.sort();
    for f in hdrs {
        let key = f
            .file_stem()
            .unwrap_or_default()
            .to_string_lossy()
            .into_owned();
        if key == "cycle" || key.ends_with(".wake") || key.ends_with(".lateness") {
            curves.push((
                key,
                drivelab_runtime::timing::LatencyHist::read_v2("h", &f)?.curve(),
            ));
        }
    }
    if !curves.is_empty() {
        check_stop(&files, &out)?;
        let ts_us = summary.ts_us();
        files.extend(drivelab_tools::plot::plot_percentiles(
            &curves,
            "latency percentiles",
            Some((ts_us, format!("T_s = {ts_us:.0} µs"))),
            true,
            &out.join("latency"),
        )?);
    }
    Ok(files)
}

/// The plant's cycle latency second by second (`/services` of `trace.mcap`).
fn latency_per_second(
    seconds: &[serde_json::Value],
    summary: &SummaryView,
    out: &std::path::Path,
) -> Result<Vec<PathBuf>> {
    let plant = seconds.iter().filter(|s| s["service"] == "plant");
    let mut series: Vec<(String, Vec<(f64, f64)>)> = ["p50", "p99", "max"]
        .iter()
        .map(|q| (format!("cycle {q}"), Vec::new()))
        .collect();
    // Each second's figure held over that second (a step), not a line between the ends of
    // the seconds: a line drew a steady rise where one second had a stall.
    let mut start = 0.0;
    for s in plant {
        let t = s["t_s"].as_f64().unwrap_or(f64::NAN);
        for (i, q) in ["p50", "p99", "max"].iter().enumerate() {
            let v = s["cycle_us"][q].as_f64().unwrap_or(f64::NAN);
            series[i].1.extend([(start, v), (t, v)]);
        }
        start = t;
    }
    if !series
        .iter()
        .any(|(_, p)| p.iter().any(|(_, y)| y.is_finite()))
    {
        // No cycle latency (lockstep or an exported run): no figure.
        return Ok(Vec::new());
    }
    let ts_us = summary.ts_us();
    drivelab_tools::plot::plot_lines(
        &series,
        "cycle latency of each second (trace.mcap, /services)",
        "t, s (each second's figure over that second)",
        "µs",
        &[(ts_us, format!("T_s = {ts_us:.0} µs"))],
        &out.join("latency-per-second"),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_trace_that_is_not_there_or_not_a_file_is_named_for_what_it_is() {
        let dir = std::env::temp_dir().join(format!("drivelab-trace-of-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(dir.join("a/trace.csv")).unwrap();
        std::fs::create_dir_all(dir.join("b")).unwrap();
        std::fs::write(dir.join("b/trace.csv"), "").unwrap();
        std::fs::write(dir.join("c"), "").unwrap();
        let err = |p: &str| format!("{:#}", trace_csv_of(&dir.join(p)).unwrap_err());
        let d = dir.display();
        assert_eq!(
            err("a"),
            format!("{d}/a/trace.csv is not a file (a run's trace is one)")
        );
        assert_eq!(
            trace_csv_of(&dir.join("b")).unwrap(),
            dir.join("b/trace.csv")
        );
        assert_eq!(
            err("c"),
            format!("{d}/c is not a folder (not a run folder)")
        );
        assert_eq!(err("missing"), format!("{d}/missing does not exist"));
        std::fs::create_dir_all(dir.join("empty")).unwrap();
        assert_eq!(
            err("empty"),
            format!("{d}/empty has no trace.csv (not a run folder)")
        );
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
