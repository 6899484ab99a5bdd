//! `trace.mcap`: a run as an MCAP file, beside `trace.csv` (docs/architecture.md, "Open a run
//! in Foxglove or PlotJuggler"). Every message is JSON with a JSON schema and is timestamped
//! at simulated time (t_k, ns):
//!
//! - `/trace`: every row of `trace.csv` (same names, same values; NaN and empty cells as
//!   null), with `t_wall_unix_ns`, when the plant published the sample (null when unknown);
//! - `/services`: per stage and per second of the run, its rate, misses and latency
//!   percentiles of that second ([`crate::per_second`]);
//! - `/log`: the supervisor's events and the fault reports (`foxglove.Log`);
//! - metadata `scenario` (the resolved `scenario.toml`) and `summary` (`summary.json`).
//!
//! Written by the launcher's recorder and supervisor threads as the drive runs, in zstd
//! chunks of at most [`CHUNK_BYTES`]: memory does not grow with the run beyond the chunk
//! index. `drivelab export RUNDIR --mcap` writes the same file from an older run folder.

use crate::per_second::ServiceSecond;
use anyhow::{anyhow, bail, Context, Result};
use drivelab_runtime::trace::TraceRow;
use serde::Serialize;
use std::collections::BTreeMap;
use std::io::BufWriter;
use std::path::Path;

/// Uncompressed size of a chunk, bytes: what the writer holds before it compresses.
pub const CHUNK_BYTES: u64 = 1 << 20;

/// JSON schema of a `/trace` message (the columns of `trace.csv`, plus the wall time).
pub const TRACE_SCHEMA: &str = r#"{"title":"drivelab.TraceRow","description":"One plant sample, as a row of trace.csv; null where trace.csv has NaN or an empty cell","type":"object","properties":{
"k":{"type":"integer","description":"sample index"},
"t":{"type":"number","description":"t_k = k Ts, s"},
"omega_ref":{"type":["number","null"],"description":"speed reference, mechanical rad/s"},
"omega_m":{"type":"number","description":"true speed, mechanical rad/s"},
"omega_hat":{"type":["number","null"],"description":"estimated speed, mechanical rad/s"},
"theta_e":{"type":"number","description":"true electrical angle, rad"},
"theta_hat":{"type":["number","null"],"description":"estimated electrical angle, rad"},
"i_d_ref":{"type":["number","null"],"description":"d current reference, A"},
"i_q_ref":{"type":["number","null"],"description":"q current reference, A"},
"i_d":{"type":"number","description":"d current, A"},
"i_q":{"type":"number","description":"q current, A"},
"u_d":{"type":"number","description":"d voltage applied on [t_k, t_k+1), V"},
"u_q":{"type":"number","description":"q voltage applied on [t_k, t_k+1), V"},
"t_load":{"type":"number","description":"load torque, N m"},
"theta_m":{"type":"number","description":"true mechanical position, unwrapped, rad"},
"theta_m_ref":{"type":["number","null"],"description":"position reference of an outer loop, rad"},
"plant_flags":{"type":"integer"},
"ctrl_flags":{"type":"integer"},
"miss":{"type":"integer","description":"1: the plant held a stale command"},
"t_wall_unix_ns":{"type":["integer","null"],"description":"wall time (Unix) when the plant published the sample, ns"}}}"#;

/// JSON schema of a `/services` message ([`ServiceSecond`]).
pub const SERVICES_SCHEMA: &str = r##"{"title":"drivelab.ServiceSecond","description":"One stage over one second of the run: rate, misses and latency percentiles of that second","type":"object","definitions":{"pct":{"type":["object","null"],"properties":{"count":{"type":"integer"},"p50":{"type":"number"},"p99":{"type":"number"},"p999":{"type":"number"},"max":{"type":"number"}}}},"properties":{
"service":{"type":"string"},
"k_from":{"type":"integer","description":"first sample of the second"},
"k_to":{"type":"integer","description":"sample after its last"},
"t_s":{"type":"number","description":"end of the second, simulated s"},
"samples":{"type":"integer"},
"rate_hz":{"type":"number","description":"samples per wall second"},
"misses":{"type":"integer"},
"stale_inputs":{"type":"integer"},
"rejected_inputs":{"type":"integer"},
"wake_us":{"$ref":"#/definitions/pct","description":"plant: release lateness; controllers: bus hop, us"},
"exec_us":{"$ref":"#/definitions/pct","description":"execution time of the step, us"},
"cycle_us":{"$ref":"#/definitions/pct","description":"plant only: t_k to command k, us"}}}"##;

/// JSON schema of Foxglove's `foxglove.Log` (levels 1 debug … 5 fatal).
pub const LOG_SCHEMA: &str = r#"{"title":"foxglove.Log","type":"object","properties":{"timestamp":{"type":"object","properties":{"sec":{"type":"integer"},"nsec":{"type":"integer"}}},"level":{"type":"integer"},"message":{"type":"string"},"name":{"type":"string"},"file":{"type":"string"},"line":{"type":"integer"}}}"#;

/// `foxglove.Log` level of an information.
pub const LOG_INFO: u8 = 2;
/// `foxglove.Log` level of a warning.
pub const LOG_WARNING: u8 = 3;

/// A `/trace` message.
#[derive(Serialize)]
struct TraceMsg<'a> {
    #[serde(flatten)]
    row: &'a TraceRow,
    t_wall_unix_ns: Option<u64>,
}

/// A `foxglove.Log` message.
#[derive(Serialize)]
pub struct LogMsg<'a> {
    timestamp: Stamp,
    level: u8,
    message: &'a str,
    name: &'a str,
    file: &'a str,
    line: u32,
}

#[derive(Serialize)]
struct Stamp {
    sec: u64,
    nsec: u32,
}

impl<'a> LogMsg<'a> {
    /// Entry `message` from `name` at `t_ns` (simulated), of `level`.
    pub fn new(t_ns: u64, level: u8, name: &'a str, message: &'a str) -> Self {
        Self {
            timestamp: Stamp {
                sec: t_ns / 1_000_000_000,
                nsec: (t_ns % 1_000_000_000) as u32,
            },
            level,
            message,
            name,
            file: "",
            line: 0,
        }
    }
}

/// Simulated time t in s as MCAP nanoseconds.
pub fn ns(t_s: f64) -> u64 {
    (t_s.max(0.0) * 1e9).round() as u64
}

/// A `trace.mcap` being written.
pub struct McapTrace {
    w: mcap::Writer<BufWriter<std::fs::File>>,
    path: std::path::PathBuf,
    trace: u16,
    services: u16,
    log: u16,
    seq: u32,
}

/// "cannot write PATH: WHY" with the innermost cause (the system's, "No space left on
/// device", rather than the MCAP writer's "I/O error from writing").
fn cannot_write(path: &Path, e: mcap::McapError) -> anyhow::Error {
    let mut why: &dyn std::error::Error = &e;
    while let Some(inner) = why.source() {
        why = inner;
    }
    anyhow!("cannot write {}: {why}", path.display())
}

impl McapTrace {
    /// Creates (truncates) the file with its three channels.
    pub fn create(path: &Path) -> Result<Self> {
        let file = drivelab_runtime::files::create(path)
            .with_context(|| format!("cannot create {}", path.display()))?;
        let mut w = mcap::WriteOptions::new()
            .compression(Some(mcap::Compression::Zstd))
            // zstd's fastest level: the recorder compresses every chunk on the launcher's
            // core as the drive runs (docs/architecture.md, "The recorder's cost").
            .compression_level(1)
            // One thread: the recorder's, on the launcher's core.
            .compression_threads(0)
            .chunk_size(Some(CHUNK_BYTES))
            .library(format!("drivelab {}", env!("CARGO_PKG_VERSION")))
            .create(BufWriter::new(file))
            .map_err(|e| cannot_write(path, e))?;
        let mut channel = |schema: &str, name: &str, topic: &str| -> Result<u16> {
            let s = w.add_schema(name, "jsonschema", schema.as_bytes())?;
            Ok(w.add_channel(s, topic, "json", &BTreeMap::new())?)
        };
        let trace = channel(TRACE_SCHEMA, "drivelab.TraceRow", "/trace")?;
        let services = channel(SERVICES_SCHEMA, "drivelab.ServiceSecond", "/services")?;
        let log = channel(LOG_SCHEMA, "foxglove.Log", "/log")?;
        Ok(Self {
            w,
            path: path.to_path_buf(),
            trace,
            services,
            log,
            seq: 0,
        })
    }

    fn write(&mut self, channel_id: u16, t_ns: u64, data: &[u8]) -> Result<()> {
        self.seq = self.seq.wrapping_add(1);
        let header = mcap::records::MessageHeader {
            channel_id,
            sequence: self.seq,
            log_time: t_ns,
            publish_time: t_ns,
        };
        self.w
            .write_to_known_channel(&header, data)
            .map_err(|e| cannot_write(&self.path, e))
    }

    /// Appends one trace row; `t_wall_unix_ns`: when the plant published it.
    pub fn row(&mut self, row: &TraceRow, t_wall_unix_ns: Option<u64>) -> Result<()> {
        let msg = serde_json::to_vec(&TraceMsg {
            row,
            t_wall_unix_ns,
        })?;
        self.write(self.trace, ns(row.t), &msg)
    }

    /// Appends one stage's second.
    pub fn second(&mut self, s: &ServiceSecond) -> Result<()> {
        let msg = serde_json::to_vec(s)?;
        self.write(self.services, ns(s.t_s), &msg)
    }

    /// Appends a log entry at `t_ns` (simulated).
    pub fn log(&mut self, t_ns: u64, level: u8, name: &str, message: &str) -> Result<()> {
        let msg = serde_json::to_vec(&LogMsg::new(t_ns, level, name, message))?;
        self.write(self.log, t_ns, &msg)
    }

    /// Writes the supervisor's events and the fault reports of `summary` (as `summary.json`
    /// holds them) to `/log`, the scenario's TOML text and the summary as metadata, and closes
    /// the file. `fs`: the sample rate, Hz.
    pub fn finish(
        mut self,
        scenario_toml: &str,
        summary: &serde_json::Value,
        fs: f64,
    ) -> Result<()> {
        for (t_ns, level, name, text) in log_entries(summary, fs) {
            self.log(t_ns, level, name, &text)?;
        }
        let meta = |name: &str, key: &str, value: String| mcap::records::Metadata {
            name: name.into(),
            metadata: BTreeMap::from([(key.to_string(), value)]),
        };
        let summary_text = serde_json::to_string_pretty(summary)?;
        for m in [
            meta("scenario", "scenario.toml", scenario_toml.to_string()),
            meta("summary", "summary.json", summary_text),
        ] {
            self.w
                .write_metadata(&m)
                .map_err(|e| cannot_write(&self.path, e))?;
        }
        self.w.finish().map_err(|e| cannot_write(&self.path, e))?;
        Ok(())
    }
}

/// The `/log` entries of a summary: each of `supervisor_events` at its sample (`k`: the
/// drive's progress then), each of `faults` at its injection.
fn log_entries(summary: &serde_json::Value, fs: f64) -> Vec<(u64, u8, &'static str, String)> {
    let arr = |key: &str| summary[key].as_array().cloned().unwrap_or_default();
    let t_ns = |k: Option<u64>| ns(k.unwrap_or(0) as f64 / fs);
    let mut v = Vec::new();
    for e in arr("supervisor_events") {
        let text = format!(
            "{} {} ({}): {}",
            e["event"].as_str().unwrap_or("?"),
            e["service"].as_str().unwrap_or("-"),
            e["process"].as_str().unwrap_or("-"),
            e["detail"].as_str().unwrap_or("")
        );
        v.push((t_ns(e["k"].as_u64()), LOG_INFO, "supervisor", text));
    }
    for f in arr("faults") {
        v.push((
            t_ns(f["injected_k"].as_u64()),
            LOG_WARNING,
            "fault",
            serde_json::to_string(&f).unwrap_or_default(),
        ));
    }
    v
}

/// The Unix time of a `CLOCK_MONOTONIC` instant (as the bus's headers carry), ns.
#[derive(Debug, Clone, Copy)]
pub struct WallClock {
    offset_ns: i128,
}

impl WallClock {
    /// Takes the offset between the two clocks now.
    pub fn now() -> Self {
        let unix = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map(|d| d.as_nanos() as i128)
            .unwrap_or(0);
        Self {
            offset_ns: unix - i128::from(drivelab_runtime::rt::now_ns()),
        }
    }

    /// The Unix time of monotonic instant `mono_ns`; None for 0 (not stamped).
    pub fn unix_ns(&self, mono_ns: u64) -> Option<u64> {
        (mono_ns > 0).then(|| (i128::from(mono_ns) + self.offset_ns).max(0) as u64)
    }
}

/// `drivelab export RUNDIR --mcap`: writes `RUNDIR/trace.mcap` from its `trace.csv` (read
/// row by row), `scenario.toml` and `summary.json`. An older run has no per-second service
/// figures and no wall time per sample: `/services` stays empty, `t_wall_unix_ns` null.
///
/// The run folder is checked as `drivelab plot` and `drivelab compare` check it (the
/// scenario parsed, the summary's figures of their types) before anything is written. A stop
/// signal (SIGINT, SIGTERM …) ends the export between two rows: nothing is written, and the
/// error says how far it got. A finished run's folder (with summary.json) that has a
/// trace.mcap already, the run's own with the per-second figures and wall times an export
/// cannot rebuild, is refused unless `force`; an unfinished run's (its launcher killed) is
/// left without its index and is rebuilt.
pub fn export(dir: &Path, force: bool) -> Result<std::path::PathBuf> {
    drivelab_runtime::service::install_signal_handlers()?;
    let csv_path = crate::plotcmd::trace_csv_of(dir)?;
    let missing = |name: &str| anyhow!("{} has no {name}: not a run folder", dir.display());
    let (sc, scenario_toml) =
        crate::plotcmd::scenario_if_any(dir)?.ok_or_else(|| missing("scenario.toml"))?;
    // A run whose launcher was killed has its trace and scenario but no summary: the
    // recording is exported with the scenario's rate, and says what it lacks.
    let (samples, summary, fs) = match crate::plotcmd::summary_json_if_any(dir)? {
        Some((view, summary)) => {
            let fs = view.rate_hz().ok_or_else(|| {
                anyhow!(
                    "{}: not a run summary: no rate_hz (the sample rate, Hz)",
                    dir.join("summary.json").display()
                )
            })?;
            (view.samples(), summary, fs)
        }
        None => {
            let why = "no summary.json: the run did not finish (its launcher was killed?)";
            crate::errln!(
                "drivelab: warning: {}: {why}; trace.mcap gets the trace and the scenario, \
                 without the summary and its events",
                dir.display()
            );
            (
                None,
                serde_json::json!({ "not_finished": why }),
                sc.rates.sample_hz,
            )
        }
    };
    let out = dir.join("trace.mcap");
    let finished = summary.get("not_finished").is_none();
    if out.exists() && finished && !force {
        bail!(
            "{} exists: a run writes its own, with the per-second latency and the wall time of \
             each sample, which an export from trace.csv cannot rebuild; to replace it anyway, \
             pass --force",
            out.display()
        );
    }
    // Written beside it and renamed when complete: a failed export leaves no partial file
    // and does not replace a trace.mcap that is there.
    let part = dir.join("trace.mcap.part");
    let mut done = 0u64;
    let interrupted = |done: u64| {
        let of = samples
            .filter(|m| *m >= done)
            .map_or(String::new(), |m| format!(" of {m}"));
        anyhow!(
            "export interrupted ({}) after {done}{of} rows of {}; nothing written",
            drivelab_runtime::service::stop_signal_name(),
            csv_path.display()
        )
    };
    let written = (|| -> Result<()> {
        let mut m = McapTrace::create(&part)?;
        // Checked as plot and compare check it: a trace that runs backwards is refused.
        let rows = drivelab_runtime::trace::for_each_csv_row(&csv_path, |row| {
            if drivelab_runtime::service::stop_requested() {
                return Err(interrupted(done));
            }
            m.row(&row, None)?;
            done += 1;
            Ok(())
        })?;
        if rows == 0 {
            bail!("{} has no samples", csv_path.display());
        }
        m.finish(&scenario_toml, &summary, fs)?;
        // A signal during the last rows or the chunk index still stops it.
        if drivelab_runtime::service::stop_requested() {
            return Err(interrupted(done));
        }
        Ok(())
    })();
    let renamed = written.and_then(|()| {
        std::fs::rename(&part, &out).with_context(|| format!("cannot write {}", out.display()))
    });
    if let Err(e) = renamed {
        // Its partial file (a link in its place was refused and is not ours to remove).
        if part.symlink_metadata().is_ok_and(|m| m.is_file()) {
            let _ = std::fs::remove_file(&part);
        }
        return Err(e);
    }
    Ok(out)
}

/// A `/trace` message as a row (null: NaN, or no position reference).
fn row_of(v: &serde_json::Value) -> TraceRow {
    let f = |k: &str| v[k].as_f64().unwrap_or(f64::NAN);
    let u = |k: &str| v[k].as_u64().unwrap_or(0);
    TraceRow {
        k: u("k"),
        t: f("t"),
        omega_ref: f("omega_ref"),
        omega_m: f("omega_m"),
        omega_hat: f("omega_hat"),
        theta_e: f("theta_e"),
        theta_hat: f("theta_hat"),
        i_d_ref: f("i_d_ref"),
        i_q_ref: f("i_q_ref"),
        i_d: f("i_d"),
        i_q: f("i_q"),
        u_d: f("u_d"),
        u_q: f("u_q"),
        t_load: f("t_load"),
        theta_m: f("theta_m"),
        theta_m_ref: v["theta_m_ref"].as_f64(),
        plant_flags: u("plant_flags") as u32,
        ctrl_flags: u("ctrl_flags") as u32,
        miss: u("miss") as u8,
    }
}

/// What `trace.mcap` holds, read back (the whole file in memory: for figures).
#[derive(Debug, Default)]
pub struct ReadBack {
    /// `/trace`, in order.
    pub rows: Vec<TraceRow>,
    /// `/services`, as JSON.
    pub seconds: Vec<serde_json::Value>,
    /// `/log` messages.
    pub log: Vec<serde_json::Value>,
}

/// Reads a `trace.mcap` with the `mcap` crate's reader.
pub fn read(path: &Path) -> Result<ReadBack> {
    let bytes = std::fs::read(path).with_context(|| format!("cannot read {}", path.display()))?;
    let mut r = ReadBack::default();
    for m in mcap::MessageStream::new(&bytes)
        .map_err(|e| anyhow!("{}: not an MCAP file: {e}", path.display()))?
    {
        if drivelab_runtime::service::stop_requested() {
            bail!(
                "{}: reading stopped by {}",
                path.display(),
                drivelab_runtime::service::stop_signal_name()
            );
        }
        let m = m.map_err(|e| anyhow!("{}: {e}", path.display()))?;
        let v: serde_json::Value = serde_json::from_slice(&m.data)
            .with_context(|| format!("{}: a message that is not JSON", path.display()))?;
        match m.channel.topic.as_str() {
            "/trace" => r.rows.push(row_of(&v)),
            "/services" => r.seconds.push(v),
            "/log" => r.log.push(v),
            _ => {}
        }
    }
    Ok(r)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn schemas_are_json_and_name_every_trace_column() {
        for s in [TRACE_SCHEMA, SERVICES_SCHEMA, LOG_SCHEMA] {
            serde_json::from_str::<serde_json::Value>(s).unwrap();
        }
        let schema: serde_json::Value = serde_json::from_str(TRACE_SCHEMA).unwrap();
        let row = serde_json::to_value(TraceMsg {
            row: &TraceRow::default(),
            t_wall_unix_ns: None,
        })
        .unwrap();
        let cols: Vec<&String> = row.as_object().unwrap().keys().collect();
        let props: Vec<&String> = schema["properties"].as_object().unwrap().keys().collect();
        let (mut a, mut b) = (cols.clone(), props.clone());
        a.sort();
        b.sort();
        assert_eq!(a, b);
    }

    #[test]
    fn rows_written_are_read_back_equal_nan_and_all() {
        let dir = std::env::temp_dir().join(format!("drivelab-mcap-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("trace.mcap");
        let rows: Vec<TraceRow> = (0..5000u64)
            .map(|k| TraceRow {
                k,
                t: k as f64 * 1e-4,
                omega_m: (k as f64).sqrt() / 3.0,
                omega_ref: if k == 7 { f64::NAN } else { 70.0 },
                theta_m_ref: (k % 2 == 0).then_some(0.1 * k as f64),
                plant_flags: (k % 3) as u32,
                miss: (k % 5 == 0) as u8,
                ..Default::default()
            })
            .collect();
        let mut m = McapTrace::create(&path).unwrap();
        for r in &rows {
            m.row(r, Some(1)).unwrap();
        }
        let summary = serde_json::json!({"supervisor_events": [], "faults": []});
        m.finish("name = 'x'", &summary, 1e4).unwrap();
        let back = read(&path).unwrap();
        std::fs::remove_dir_all(&dir).unwrap();
        assert_eq!(back.rows.len(), rows.len());
        for (a, b) in rows.iter().zip(&back.rows) {
            assert!(a.omega_ref.is_nan() == b.omega_ref.is_nan());
            let nan_free = |r: &TraceRow| TraceRow {
                omega_ref: 0.0,
                ..*r
            };
            assert_eq!(nan_free(a), nan_free(b));
        }
    }

    #[test]
    fn log_entries_are_the_events_then_the_faults_at_their_samples() {
        let s = serde_json::json!({
            "supervisor_events": [{"k": 5000, "event": "exited", "service": "observer", "process": "observer", "detail": "SIGKILL"}],
            "faults": [{"fault": "kill", "service": "observer", "injected_k": 4000}],
        });
        let e = log_entries(&s, 10_000.0);
        assert_eq!(e.len(), 2);
        assert_eq!((e[0].0, e[0].2), (500_000_000, "supervisor"));
        assert_eq!(e[0].3, "exited observer (observer): SIGKILL");
        assert_eq!((e[1].0, e[1].1), (400_000_000, LOG_WARNING));
    }
}
