//! `drivelab run`: starts the four services on a private bus, records every sample, stops
//! them cleanly, removes the bus files and writes the run folder.

use crate::common::BusClock;
use anyhow::{anyhow, bail, Context, Result};
use drivelab::bus::{self, DriveTopics, MAX_BUFFER};
use drivelab::config::{Scenario, SERVICES};
use drivelab::drive::{trace_row, DriveDesign};
use drivelab::messages::{Measurement, VoltageCommand};
use drivelab::metrics::speed_metrics;
use drivelab::trace::TraceRow;
use serde::Serialize;
use serde_json::json;
use std::collections::BTreeMap;
use std::io::{BufRead, BufReader, Write};
use std::path::{Path, PathBuf};
use std::process::{Child, ChildStdin, Command, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc;
use std::sync::Arc;
use std::time::{Duration, Instant};

/// Which clock paces the run.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Clock {
    /// Four processes; the plant sleeps to absolute deadlines.
    Realtime,
    /// Four processes; the plant waits for each command; as fast as possible.
    Lockstep,
    /// The same step functions in one thread, no bus.
    Inprocess,
}

/// Options of one run.
#[derive(Debug, Clone)]
pub struct RunOptions {
    /// Scenario name or file.
    pub scenario: String,
    /// Clock.
    pub clock: Clock,
    /// Override of the scenario's duration, s.
    pub duration_s: Option<f64>,
    /// Output folder.
    pub out: Option<PathBuf>,
    /// Bus id (default: derived from the process id).
    pub bus: Option<String>,
    /// Strict RT setup.
    pub rt_strict: bool,
    /// No pinning / FIFO / mlock.
    pub no_rt: bool,
    /// Skip the PNG plots.
    pub no_plots: bool,
    /// Print progress lines.
    pub verbose: bool,
}

/// What a run produced.
#[derive(Debug)]
pub struct RunResult {
    /// The run folder.
    pub out: PathBuf,
    /// The summary as written to `summary.json`.
    pub summary: serde_json::Value,
}

static STOP: AtomicBool = AtomicBool::new(false);

extern "C" fn on_signal(_s: libc::c_int) {
    STOP.store(true, Ordering::SeqCst);
}

fn install_stop_handler() {
    for sig in [libc::SIGINT, libc::SIGTERM] {
        // SAFETY: installs an async-signal-safe handler (one atomic store) with an empty mask.
        unsafe {
            let mut sa: libc::sigaction = std::mem::zeroed();
            sa.sa_sigaction = on_signal as *const () as libc::sighandler_t;
            libc::sigemptyset(&mut sa.sa_mask);
            libc::sigaction(sig, &sa, std::ptr::null_mut());
        }
    }
}

/// Loads the scenario and applies the duration override, with a one-line error.
pub fn load_scenario(name: &str, duration_s: Option<f64>) -> Result<Scenario> {
    let (mut sc, _) = Scenario::load(name).map_err(|e| anyhow!(e))?;
    if let Some(d) = duration_s {
        sc.duration_s = d;
        sc.validate().map_err(|e| anyhow!("--duration {d}: {e}"))?;
    }
    Ok(sc)
}

fn default_out(sc: &Scenario, clock: Clock) -> PathBuf {
    let secs = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_secs())
        .unwrap_or(0);
    PathBuf::from("runs").join(format!("{}-{:?}-{}", sc.name, clock, secs).to_lowercase())
}

/// A contiguous range of samples missing from the trace and why.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct Gap {
    /// First missing k.
    pub from: u64,
    /// Last missing k.
    pub to: u64,
    /// Which part is missing ("measurement", "command").
    pub part: &'static str,
    /// Why.
    pub cause: String,
}

/// Recorder: subscribes to measurements and commands with large buffers and keeps every one.
struct Recorder {
    meas: Vec<Option<Measurement>>,
    cmd: Vec<Option<VoltageCommand>>,
    rejected: u64,
}

fn run_recorder(
    bus_id: String,
    wake: drivelab::bus::WakeKind,
    n: u64,
    stop: Arc<AtomicBool>,
    ready: mpsc::Sender<Result<()>>,
) -> Result<Recorder> {
    let setup = (|| -> Result<_> {
        let node = bus::node(&bus_id, "recorder")?;
        let topics = DriveTopics::open_with(&node, wake, &bus_id)?;
        // Polled: a listener would cost the real-time senders a wake-up syscall per sample.
        let meas_rx = topics.meas.polled_receiver(MAX_BUFFER)?;
        let cmd_rx = topics.cmd.polled_receiver(MAX_BUFFER)?;
        let rec_tx = topics.rec.sender()?;
        Ok((node, topics, meas_rx, cmd_rx, rec_tx))
    })();
    let (_node, _topics, meas_rx, cmd_rx, rec_tx) = match setup {
        Ok(v) => {
            let _ = ready.send(Ok(()));
            v
        }
        Err(e) => {
            let _ = ready.send(Err(anyhow!("{e:#}")));
            return Err(e);
        }
    };
    let mut r = Recorder {
        meas: vec![None; n as usize],
        cmd: vec![None; n as usize],
        rejected: 0,
    };
    let (mut meas_end, mut cmd_end) = (false, false);
    let (mut next_meas, mut next_cmd) = (0u64, 0u64);
    let mut last_progress = 0u64;
    loop {
        let mut got = false;
        while let Some(m) = meas_rx.try_recv()? {
            got = true;
            if m.hdr.is_warmup() {
                continue;
            }
            if m.hdr.is_warmup() {
                continue;
            }
            if m.hdr.is_end() {
                meas_end = true;
            } else if m.hdr.k < n {
                r.meas[m.hdr.k as usize] = Some(m);
            } else {
                r.rejected += 1;
            }
        }
        while let Some(c) = cmd_rx.try_recv()? {
            got = true;
            if c.hdr.is_warmup() {
                continue;
            }
            if c.hdr.is_warmup() {
                continue;
            }
            if c.hdr.is_end() {
                cmd_end = true;
            } else if c.hdr.k < n {
                r.cmd[c.hdr.k as usize] = Some(c);
            } else {
                r.rejected += 1;
            }
        }
        while next_meas < n && r.meas[next_meas as usize].is_some() {
            next_meas += 1;
        }
        while next_cmd < n && r.cmd[next_cmd as usize].is_some() {
            next_cmd += 1;
        }
        let progress = next_meas.min(next_cmd);
        if progress >= last_progress + 256 || (progress > last_progress && !got) {
            rec_tx.send(progress)?;
            last_progress = progress;
        }
        if (meas_end && cmd_end) || stop.load(Ordering::SeqCst) {
            // Take what is still buffered, then stop.
            while let Some(m) = meas_rx.try_recv()? {
                if !m.hdr.is_end() && !m.hdr.is_warmup() && m.hdr.k < n {
                    r.meas[m.hdr.k as usize] = Some(m);
                }
            }
            while let Some(c) = cmd_rx.try_recv()? {
                if !c.hdr.is_end() && !c.hdr.is_warmup() && c.hdr.k < n {
                    r.cmd[c.hdr.k as usize] = Some(c);
                }
            }
            return Ok(r);
        }
        if !got {
            meas_rx.wait(Duration::from_millis(1))?;
        }
    }
}

struct ChildProc {
    name: &'static str,
    child: Child,
    stdin: Option<ChildStdin>,
    lines: mpsc::Receiver<String>,
    rt: Option<serde_json::Value>,
}

fn service_binary(name: &str) -> Result<PathBuf> {
    let exe = std::env::current_exe().context("cannot locate the drivelab executable")?;
    let p = exe
        .parent()
        .ok_or_else(|| anyhow!("executable has no folder"))?
        .join(name);
    if !p.is_file() {
        bail!(
            "service binary {} not found next to drivelab (build the workspace first)",
            p.display()
        );
    }
    Ok(p)
}

fn spawn_service(
    name: &'static str,
    sc_path: &Path,
    bus_id: &str,
    clock: BusClock,
    o: &RunOptions,
    out: &Path,
) -> Result<ChildProc> {
    let mut cmd = Command::new(service_binary(name)?);
    cmd.arg("--scenario").arg(sc_path).arg("--bus").arg(bus_id);
    cmd.arg("--clock").arg(match clock {
        BusClock::Realtime => "realtime",
        BusClock::Lockstep => "lockstep",
    });
    cmd.arg("--out").arg(out);
    if o.rt_strict {
        cmd.arg("--rt-strict");
    }
    if o.no_rt {
        cmd.arg("--no-rt");
    }
    if name == "plant" {
        cmd.arg("--recorder");
    }
    cmd.stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit());
    let mut child = cmd
        .spawn()
        .with_context(|| format!("cannot start {name}"))?;
    let stdout = child.stdout.take().expect("piped");
    let stdin = child.stdin.take();
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(stdout).lines().map_while(Result::ok) {
            if tx.send(line).is_err() {
                break;
            }
        }
    });
    Ok(ChildProc {
        name,
        child,
        stdin,
        lines: rx,
        rt: None,
    })
}

fn terminate(children: &mut [ChildProc]) {
    for c in children.iter_mut() {
        if let Ok(None) = c.child.try_wait() {
            // SAFETY: kill(2) on a pid we spawned and have not reaped; no memory is touched.
            unsafe {
                libc::kill(c.child.id() as libc::pid_t, libc::SIGTERM);
            }
        }
    }
    let t = Instant::now();
    for c in children.iter_mut() {
        loop {
            match c.child.try_wait() {
                Ok(Some(_)) | Err(_) => break,
                Ok(None) if t.elapsed() > Duration::from_secs(3) => {
                    let _ = c.child.kill();
                    let _ = c.child.wait();
                    break;
                }
                Ok(None) => std::thread::sleep(Duration::from_millis(5)),
            }
        }
    }
}

/// Runs the four processes on a bus and returns the recorder's data and the process info.
fn run_bus(
    sc: &Scenario,
    sc_path: &Path,
    o: &RunOptions,
    out: &Path,
    clock: BusClock,
) -> Result<(
    Vec<TraceRow>,
    Vec<Gap>,
    serde_json::Value,
    serde_json::Value,
)> {
    let bus_id = o
        .bus
        .clone()
        .unwrap_or_else(|| format!("{}", std::process::id()));
    bus::check_bus_id(&bus_id)?;
    // Leftovers of an earlier crashed run with the same id would confuse this one.
    bus::cleanup(&bus_id)?;
    let n = sc.samples();
    let stop = Arc::new(AtomicBool::new(false));
    let (ready_tx, ready_rx) = mpsc::channel();
    let rec = {
        let (b, s, w) = (bus_id.clone(), stop.clone(), sc.timing.wake);
        std::thread::Builder::new()
            .name("recorder".into())
            .spawn(move || run_recorder(b, w, n, s, ready_tx))?
    };
    let result = (|| -> Result<(Vec<ChildProc>, Option<String>)> {
        ready_rx
            .recv()
            .map_err(|_| anyhow!("recorder thread died"))??;
        let mut children = Vec::new();
        for name in SERVICES {
            match spawn_service(name, sc_path, &bus_id, clock, o, out) {
                Ok(c) => children.push(c),
                Err(e) => return Ok((children, Some(format!("{e:#}")))),
            }
        }
        // Handshake: each service reports its RT setup and READY.
        let t = Instant::now();
        for c in children.iter_mut() {
            loop {
                if STOP.load(Ordering::SeqCst) {
                    return Ok((children, Some("interrupted during start-up".into())));
                }
                match c.lines.recv_timeout(Duration::from_millis(50)) {
                    Ok(l) if l == "READY" => break,
                    Ok(l) => {
                        if let Some(j) = l.strip_prefix("RT ") {
                            c.rt = serde_json::from_str(j).ok();
                        }
                    }
                    Err(mpsc::RecvTimeoutError::Timeout) => {
                        if let Ok(Some(st)) = c.child.try_wait() {
                            let name = c.name;
                            return Ok((
                                children,
                                Some(format!("{name} exited during start-up ({st})")),
                            ));
                        }
                        if t.elapsed() > Duration::from_secs(20) {
                            let name = c.name;
                            return Ok((
                                children,
                                Some(format!("{name} did not become ready within 20 s")),
                            ));
                        }
                    }
                    Err(mpsc::RecvTimeoutError::Disconnected) => {
                        let st = c.child.wait().ok();
                        let name = c.name;
                        return Ok((
                            children,
                            Some(format!("{name} exited during start-up ({st:?})")),
                        ));
                    }
                }
            }
        }
        if let Some(stdin) = children[0].stdin.as_mut() {
            stdin.write_all(b"GO\n")?;
            stdin.flush()?;
        }
        if o.verbose {
            eprintln!(
                "drivelab: {} samples at {} Hz, clock {clock:?}, bus {bus_id}",
                n, sc.rates.sample_hz
            );
        }
        // Wait for the services to finish.
        let started = Instant::now();
        let limit = match clock {
            BusClock::Realtime => Duration::from_secs_f64(sc.duration_s * 1.5 + 20.0),
            BusClock::Lockstep => Duration::from_secs_f64(sc.duration_s * 2000.0 + 120.0),
        };
        loop {
            if STOP.load(Ordering::SeqCst) {
                return Ok((
                    children,
                    Some("interrupted (SIGINT/SIGTERM): drive stopped".into()),
                ));
            }
            let mut all_done = true;
            for c in children.iter_mut() {
                match c.child.try_wait()? {
                    Some(st) if !st.success() => {
                        let name = c.name;
                        return Ok((children, Some(format!("{name} failed ({st})"))));
                    }
                    Some(_) => {}
                    None => all_done = false,
                }
            }
            if all_done {
                return Ok((children, None));
            }
            if started.elapsed() > limit {
                return Ok((
                    children,
                    Some(format!("the drive did not finish within {limit:?}")),
                ));
            }
            std::thread::sleep(Duration::from_millis(5));
        }
    })();
    let (mut children, failure) = match result {
        Ok(v) => v,
        Err(e) => (Vec::new(), Some(format!("{e:#}"))),
    };
    terminate(&mut children);
    stop.store(true, Ordering::SeqCst);
    let rec = rec
        .join()
        .map_err(|_| anyhow!("recorder thread panicked"))?;
    bus::cleanup(&bus_id)?;
    if let Some(f) = failure {
        bail!(f);
    }
    let rec = rec?;
    let left = bus::leftovers(&bus_id);
    if !left.is_empty() {
        bail!("bus files left behind: {}", left.join(", "));
    }
    let mut processes = serde_json::Map::new();
    let mut counters = serde_json::Map::new();
    for c in &children {
        let rt = c.rt.clone().unwrap_or(serde_json::Value::Null);
        processes.insert(
            c.name.into(),
            json!({ "pid": c.child.id(), "cpu": rt.get("cpu"), "policy": rt.get("policy"), "priority": rt.get("priority"), "memory_locked": rt.get("memory_locked") }),
        );
        let stats_path = out.join(format!("{}.stats.json", c.name));
        if let Ok(text) = std::fs::read_to_string(&stats_path) {
            let v: serde_json::Value = serde_json::from_str(&text).unwrap_or_default();
            counters.insert(
                c.name.into(),
                v.get("counters").cloned().unwrap_or_default(),
            );
        }
    }
    let (rows, gaps) = assemble(sc, &rec, counters.contains_key("plant"));
    let mut info =
        json!({ "bus": bus_id, "counters": counters, "recorder_rejected": rec.rejected });
    if let Some(p) = counters.get("plant") {
        info["deadline_misses"] = p["deadline_misses"].clone();
        info["longest_miss_run"] = p["longest_miss_run"].clone();
    }
    Ok((rows, gaps, serde_json::Value::Object(processes), info))
}

/// Joins measurements and commands into trace rows. A sample whose command is missing keeps
/// its row with NaN in the command's columns; every missing part is listed as a gap.
fn assemble(sc: &Scenario, rec: &Recorder, _plant_ok: bool) -> (Vec<TraceRow>, Vec<Gap>) {
    let ts = sc.rates.ts();
    let mut rows = Vec::with_capacity(rec.meas.len());
    let mut gaps: Vec<Gap> = Vec::new();
    let last_meas = rec.meas.iter().rposition(Option::is_some);
    let mut push_gap = |k: u64, part: &'static str, cause: String| {
        if let Some(g) = gaps.last_mut() {
            if g.part == part && g.to + 1 == k && g.cause == cause {
                g.to = k;
                return;
            }
        }
        gaps.push(Gap {
            from: k,
            to: k,
            part,
            cause,
        });
    };
    for (k, m) in rec.meas.iter().enumerate() {
        let k = k as u64;
        match (m, &rec.cmd[k as usize]) {
            (Some(m), Some(c)) => rows.push(trace_row(ts, m, c)),
            (Some(m), None) => {
                let nan = f64::NAN;
                let c = VoltageCommand {
                    hdr: m.hdr,
                    u_ab: [nan; 2],
                    u_dq: [nan; 2],
                    i_dq_ref: [nan; 2],
                    omega_ref: nan,
                    omega_hat: nan,
                    theta_hat: nan,
                };
                rows.push(trace_row(ts, m, &c));
                push_gap(
                    k,
                    "command",
                    "current-loop produced no command for this sample".into(),
                );
            }
            (None, _) => {
                let cause = match last_meas {
                    Some(l) if k < l as u64 => {
                        "measurement lost between plant and recorder (recorder buffer overflow)"
                    }
                    _ => "the plant stopped before this sample",
                };
                push_gap(k, "measurement", cause.into());
            }
        }
    }
    (rows, gaps)
}

/// Runs a scenario end to end and writes the run folder.
pub fn run(o: &RunOptions) -> Result<RunResult> {
    install_stop_handler();
    if let Some(b) = &o.bus {
        bus::check_bus_id(b)?;
    }
    let sc = load_scenario(&o.scenario, o.duration_s)?;
    let out = o.out.clone().unwrap_or_else(|| default_out(&sc, o.clock));
    std::fs::create_dir_all(&out)
        .with_context(|| format!("cannot create run folder {}", out.display()))?;
    let out = out.canonicalize()?;
    let sc_path = out.join("scenario.toml");
    std::fs::write(&sc_path, toml::to_string(&sc)?)
        .with_context(|| format!("write {}", sc_path.display()))?;
    let wall = Instant::now();
    let (rows, gaps, processes, info) = match o.clock {
        Clock::Inprocess => (
            drivelab::drive::run_inprocess(&sc),
            Vec::new(),
            json!({}),
            json!({ "deadline_misses": 0 }),
        ),
        Clock::Lockstep => run_bus(&sc, &sc_path, o, &out, BusClock::Lockstep)?,
        Clock::Realtime => run_bus(&sc, &sc_path, o, &out, BusClock::Realtime)?,
    };
    let wall_s = wall.elapsed().as_secs_f64();
    drivelab::trace::write_csv(&out.join("trace.csv"), &rows)?;
    let metrics = speed_metrics(&sc, &rows);
    let design = DriveDesign::from_scenario(&sc);
    let mut summary = json!({
        "scenario": sc.name,
        "clock": o.clock,
        "rate_hz": sc.rates.sample_hz,
        "speed_loop_hz": sc.rates.sample_hz / f64::from(sc.rates.speed_divider),
        "samples": rows.len(),
        "samples_expected": sc.samples(),
        "deadline_misses": info.get("deadline_misses").cloned().unwrap_or(json!(0)),
        "longest_miss_run": info.get("longest_miss_run").cloned().unwrap_or(json!(0)),
        "processes": processes,
        "metrics": metrics,
        "missing_samples": gaps,
        "design": design,
        "wall_time_s": wall_s,
        "simulated_s_per_wall_s": sc.duration_s / wall_s.max(1e-9),
    });
    if let Some(c) = info.get("counters") {
        summary["counters"] = c.clone();
        if let Some(ns) = c["plant"]["loop_wall_ns"].as_u64().filter(|&n| n > 0) {
            summary["loop_simulated_s_per_wall_s"] = json!(sc.duration_s / (ns as f64 * 1e-9));
        }
    } else {
        summary["loop_simulated_s_per_wall_s"] = summary["simulated_s_per_wall_s"].clone();
    }
    if let Some(b) = info.get("bus") {
        summary["bus"] = b.clone();
    }
    let (latency, curves) = collect_histograms(&out)?;
    if !latency.is_empty() {
        summary["latency_us"] = serde_json::to_value(&latency)?;
    }
    if !o.no_plots && !curves.is_empty() {
        let budget = Some((
            1e6 / sc.rates.sample_hz,
            format!("T_s = {:.0} µs", 1e6 / sc.rates.sample_hz),
        ));
        drivelab::plot::plot_percentiles(
            &curves,
            &format!("{}: latency percentiles", sc.name),
            budget,
            true,
            &out.join("latency"),
        )?;
    }
    if !o.no_plots && !rows.is_empty() {
        let opts = drivelab::plot::TraceFigureOptions {
            current_limit_a: Some(sc.i_q_max()),
            voltage_limit_v: Some(sc.u_max()),
            title: format!("{} ({:?})", sc.name, o.clock).to_lowercase(),
            ..Default::default()
        };
        let files = drivelab::plot::plot_trace(&rows, &out, &opts)?;
        summary["plots"] = json!(files
            .iter()
            .map(|f| f
                .file_name()
                .unwrap_or_default()
                .to_string_lossy()
                .into_owned())
            .collect::<Vec<_>>());
    }
    std::fs::write(
        out.join("summary.json"),
        serde_json::to_vec_pretty(&summary)?,
    )?;
    Ok(RunResult { out, summary })
}

/// Reads every `<key>.hdr` histogram the services wrote, writes `<key>.hgrm` beside it and
/// returns the percentiles by key and the percentile curves for the plot.
fn collect_histograms(
    out: &Path,
) -> Result<(
    BTreeMap<String, drivelab::timing::Percentiles>,
    Vec<drivelab::plot::PercentileSeries>,
)> {
    let mut lat = BTreeMap::new();
    let mut curves = Vec::new();
    let mut files: Vec<PathBuf> = std::fs::read_dir(out)?
        .flatten()
        .map(|e| e.path())
        .filter(|p| p.extension().is_some_and(|e| e == "hdr"))
        .collect();
    files.sort();
    for f in files {
        let key = f
            .file_stem()
            .unwrap_or_default()
            .to_string_lossy()
            .into_owned();
        let h = drivelab::timing::LatencyHist::read_v2("hist", &f)?;
        std::fs::write(f.with_extension("hgrm"), h.hgrm())?;
        lat.insert(key.clone(), h.percentiles());
        if key == "cycle" || key.ends_with(".wake") || key.ends_with(".lateness") {
            curves.push((key, h.curve()));
        }
    }
    Ok((lat, curves))
}

/// Per-service statistics keyed by service name (for tests and reports).
pub fn counters(summary: &serde_json::Value) -> BTreeMap<String, serde_json::Value> {
    summary["counters"]
        .as_object()
        .map(|m| m.clone().into_iter().collect())
        .unwrap_or_default()
}
