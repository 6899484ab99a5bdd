//! `drivelab run`: starts the four services on a private bus, records every sample, stops
//! them cleanly, removes the bus files and writes the run folder.

use crate::common::BusClock;
use anyhow::{anyhow, bail, Context, Result};
use drivelab_runtime::bus::{self, DriveTopics, MAX_BUFFER};
use drivelab_runtime::config::{Scenario, SERVICES};
use drivelab_runtime::drive::{trace_row, DriveDesign};
use drivelab_runtime::messages::{PlantTruth, VoltageCommand};
use drivelab_runtime::service::TopologyPlan;
use drivelab_runtime::topology::{ProcessSpec, StageInfo};
use drivelab_runtime::trace::TraceRow;
use drivelab_tools::metrics::speed_metrics;
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
    /// The topology's processes; the plant sleeps to absolute deadlines.
    Realtime,
    /// The topology's processes; the plant waits for each command; as fast as possible.
    Lockstep,
    /// The same stages on the same host in one thread, no bus.
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
    /// Faults to inject (realtime only).
    pub faults: Vec<crate::faults::FaultSpec>,
    /// Restart policy of the supervisor.
    pub restart: Restart,
    /// Seed of `random:N` fault plans.
    pub fault_seed: u64,
    /// Topology override: a shipped name or a file with `[[process]]` tables.
    pub topology: Option<String>,
}

/// What the supervisor does when a service dies.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, Serialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum Restart {
    /// Leave it dead; the rest of the drive goes on in its degraded mode.
    Never,
    /// Restart it (with --rejoin) after a back-off of 10 ms, doubling per restart of the same
    /// service up to 1 s.
    #[default]
    OnFailure,
}

/// One supervisor event.
#[derive(Debug, Clone, Serialize)]
pub struct SupEvent {
    /// Wall time since the start signal, s.
    pub t_wall_s: f64,
    /// Newest sample the recorder had seen (k + 1), i.e. the drive's progress.
    pub k: u64,
    /// inject, resume, exited, reaped, restarted, ready.
    pub event: String,
    /// Stage (inject, resume) or process (exited, restarted, ready); "-" for the bus.
    pub service: String,
    /// The process concerned.
    #[serde(default)]
    pub process: String,
    /// Details.
    pub detail: String,
}

/// What a run produced.
#[derive(Debug)]
pub struct RunResult {
    /// The run folder.
    pub out: PathBuf,
    /// The summary as written to `summary.json`.
    pub summary: serde_json::Value,
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
    meas: Vec<Option<PlantTruth>>,
    cmd: Vec<Option<VoltageCommand>>,
    /// Position references of an outer loop, as (k, θ_m*), in arrival order.
    wref: Vec<(u64, f64)>,
    rejected: u64,
}

/// What the recorder shares with the supervisor while the drive runs.
#[derive(Default)]
struct Progress {
    /// Newest measurement index seen + 1 (0 = none yet).
    next_k: std::sync::atomic::AtomicU64,
    /// The plant's newest true state (for a restarted plant to resume from).
    last: std::sync::Mutex<Option<PlantTruth>>,
    /// Decimated trace for `drivelab monitor`.
    tail: crate::hub::TraceTail,
}

fn run_recorder(
    bus_id: String,
    wake: drivelab_runtime::bus::WakeKind,
    n: u64,
    stop: Arc<AtomicBool>,
    progress: Arc<Progress>,
    ready: mpsc::Sender<Result<()>>,
) -> Result<Recorder> {
    let setup = (|| -> Result<_> {
        let node = bus::node(&bus_id, "recorder")?;
        let topics = DriveTopics::open_with(&node, wake, &bus_id)?;
        // Polled: a listener would cost the real-time senders a wake-up syscall per sample.
        // The trace is the plant's true state (its own topic), joined with the commands.
        let meas_rx = topics.truth.polled_receiver(MAX_BUFFER)?;
        let cmd_rx = topics.cmd.polled_receiver(MAX_BUFFER)?;
        let wref_rx = topics.wref.polled_receiver(MAX_BUFFER)?;
        let rec_tx = topics.rec.sender()?;
        Ok((node, topics, meas_rx, cmd_rx, wref_rx, rec_tx))
    })();
    let (_node, _topics, meas_rx, cmd_rx, wref_rx, rec_tx) = match setup {
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
        wref: Vec::new(),
        rejected: 0,
    };
    let (mut meas_end, mut cmd_end) = (false, false);
    let (mut next_meas, mut next_cmd) = (0u64, 0u64);
    let mut last_progress = 0u64;
    let mut last_cmd = VoltageCommand::default();
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
                progress
                    .tail
                    .offer(drivelab_runtime::telemetry::TracePoint {
                        k: m.hdr.k,
                        omega: m.omega_m,
                        omega_ref: last_cmd.omega_ref,
                        i_d: m.i_dq[0],
                        i_q: m.i_dq[1],
                        i_d_ref: last_cmd.i_dq_ref[0],
                        i_q_ref: last_cmd.i_dq_ref[1],
                    });
                if m.hdr.k + 1 > progress.next_k.load(Ordering::Relaxed) {
                    progress.next_k.store(m.hdr.k + 1, Ordering::Relaxed);
                    if let Ok(mut l) = progress.last.lock() {
                        *l = Some(m);
                    }
                }
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
                last_cmd = c;
            } else {
                r.rejected += 1;
            }
        }
        while let Some(w) = wref_rx.try_recv()? {
            if !w.hdr.is_warmup() && !w.hdr.is_end() && w.theta_m_ref.is_finite() {
                r.wref.push((w.hdr.k, w.theta_m_ref));
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
    /// Process name in the topology.
    name: String,
    /// Stages it hosts.
    stages: Vec<String>,
    /// It hosts the source (the plant).
    source: bool,
    spec: ProcessSpec,
    exe: PathBuf,
    child: Child,
    stdin: Option<ChildStdin>,
    lines: mpsc::Receiver<String>,
    rt: Option<serde_json::Value>,
}

/// The executable of process `p`: its `exec` (relative to the scenario's folder) or the
/// built-in host next to this executable.
fn process_binary(p: &ProcessSpec, base: &Path) -> Result<PathBuf> {
    match drivelab_runtime::topology::exec_path(p, base) {
        Some(e) if e.is_file() => Ok(e),
        Some(e) => bail!(
            "process '{}': executable {} not found (build it first: cargo build --release --workspace)",
            p.name,
            e.display()
        ),
        None => service_binary("drivelab-host"),
    }
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

struct Spawn<'a> {
    sc_path: &'a Path,
    topo_path: &'a Path,
    bus_id: &'a str,
    clock: BusClock,
    o: &'a RunOptions,
    out: &'a Path,
}

fn spawn_service(
    p: &ProcessSpec,
    exe: &Path,
    source: bool,
    sp: &Spawn,
    rejoin_from: Option<&Path>,
) -> Result<ChildProc> {
    let mut cmd = Command::new(exe);
    cmd.arg("--scenario").arg(sp.sc_path);
    cmd.arg("--topology").arg(sp.topo_path);
    cmd.arg("--process").arg(&p.name);
    cmd.arg("--hosts").arg(p.stages.join(","));
    cmd.arg("--bus").arg(sp.bus_id);
    cmd.arg("--clock").arg(match sp.clock {
        BusClock::Realtime => "realtime",
        BusClock::Lockstep => "lockstep",
    });
    cmd.arg("--out").arg(sp.out);
    if sp.o.rt_strict {
        cmd.arg("--rt-strict");
    }
    if sp.o.no_rt {
        cmd.arg("--no-rt");
    }
    if source {
        cmd.arg("--recorder");
    }
    if let Some(f) = rejoin_from {
        cmd.arg("--rejoin");
        if source {
            cmd.arg("--rejoin-from").arg(f);
        }
    }
    cmd.stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit());
    let name = p.name.clone();
    let mut child = cmd
        .spawn()
        .with_context(|| format!("cannot start process {name} ({})", exe.display()))?;
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
        stages: p.stages.clone(),
        source,
        spec: p.clone(),
        exe: exe.to_path_buf(),
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
    plan_topo: &TopologyPlan,
    plan: &[crate::faults::Fault],
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
    let progress = Arc::new(Progress {
        tail: crate::hub::TraceTail::new(sc.rates.sample_hz),
        ..Default::default()
    });
    let (ready_tx, ready_rx) = mpsc::channel();
    let rec = {
        let (b, s, w, pr) = (
            bus_id.clone(),
            stop.clone(),
            sc.timing.wake,
            progress.clone(),
        );
        std::thread::Builder::new()
            .name("recorder".into())
            .spawn(move || run_recorder(b, w, n, s, pr, ready_tx))?
    };
    let topo_path = out.join("topology.json");
    let sp = Spawn {
        sc_path,
        topo_path: &topo_path,
        bus_id: &bus_id,
        clock,
        o,
        out,
    };
    let mut events: Vec<SupEvent> = Vec::new();
    let result = (|| -> Result<(Vec<ChildProc>, Option<String>)> {
        ready_rx
            .recv()
            .map_err(|_| anyhow!("recorder thread died"))??;
        // The telemetry hub subscribes to the services' statuses before they start.
        let mut hub = crate::hub::Hub::new(&bus_id, sc, clock == BusClock::Lockstep)?;
        let mut children = Vec::new();
        for (i, p) in plan_topo.processes.iter().enumerate() {
            // `exec` paths were made absolute when the topology was resolved.
            let spawned = process_binary(p, Path::new("/"))
                .and_then(|exe| spawn_service(p, &exe, i == 0, &sp, None));
            match spawned {
                Ok(c) => children.push(c),
                Err(e) => return Ok((children, Some(format!("{e:#}")))),
            }
        }
        // Handshake: each service reports its RT setup and READY.
        let t = Instant::now();
        for c in children.iter_mut() {
            loop {
                if crate::common::stop_requested() {
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
                            let name = c.name.clone();
                            return Ok((
                                children,
                                Some(format!("{name} exited during start-up ({st})")),
                            ));
                        }
                        if t.elapsed() > Duration::from_secs(20) {
                            let name = c.name.clone();
                            return Ok((
                                children,
                                Some(format!("{name} did not become ready within 20 s")),
                            ));
                        }
                    }
                    Err(mpsc::RecvTimeoutError::Disconnected) => {
                        let st = c.child.wait().ok();
                        let name = c.name.clone();
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
        // Supervise until the services finish.
        let started = Instant::now();
        let limit = match clock {
            BusClock::Realtime => Duration::from_secs_f64(sc.duration_s * 1.5 + 20.0),
            BusClock::Lockstep => Duration::from_secs_f64(sc.duration_s * 2000.0 + 120.0),
        };
        // Progress on a terminal only (indicatif draws nothing when stderr is not a tty).
        let bar = if o.verbose {
            indicatif::ProgressBar::new(n)
        } else {
            indicatif::ProgressBar::hidden()
        };
        bar.set_style(
            indicatif::ProgressStyle::with_template(
                "{spinner} [{elapsed_precise}] {bar:30} {pos}/{len} samples {msg}",
            )
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
        );
        let failure = supervise(
            &mut hub,
            &bar,
            &mut children,
            plan,
            &mut events,
            &progress,
            sc,
            &sp,
            started,
            limit,
        )?;
        bar.finish_and_clear();
        // Let attached monitors see the end and detach before the bus goes away.
        hub.finish(
            progress.next_k.load(Ordering::Relaxed),
            &progress.tail,
            Duration::from_secs(1),
        )?;
        Ok((children, failure))
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
            c.name.clone(),
            json!({ "stages": c.stages, "executable": c.exe, "pid": c.child.id(), "cpu": rt.get("cpu"), "policy": rt.get("policy"), "priority": rt.get("priority"), "memory_locked": rt.get("memory_locked") }),
        );
        for st in &c.stages {
            let stats_path = out.join(format!("{st}.stats.json"));
            if let Ok(text) = std::fs::read_to_string(&stats_path) {
                let v: serde_json::Value = serde_json::from_str(&text).unwrap_or_default();
                let mut cv = v.get("counters").cloned().unwrap_or_default();
                if let Some(d) = v.get("diagnostics") {
                    cv["diagnostics"] = d.clone();
                }
                counters.insert(st.clone(), cv);
            }
        }
    }
    let (rows, gaps) = assemble(sc, &rec, counters.contains_key("plant"));
    let mut info = json!({ "bus": bus_id, "counters": counters, "recorder_rejected": rec.rejected, "events": events, "plan": plan });
    if let Some(p) = counters.get("plant") {
        info["deadline_misses"] = p["deadline_misses"].clone();
        info["longest_miss_run"] = p["longest_miss_run"].clone();
    }
    Ok((rows, gaps, serde_json::Value::Object(processes), info))
}

/// Applies `--topology`, resolves the scenario's topology against the stages' declarations
/// (a user's executable is asked with `--describe`) and makes `exec` paths absolute.
pub fn resolve_topology(sc: &mut Scenario, sc_src: &Path, o: &RunOptions) -> Result<TopologyPlan> {
    if let Some(t) = &o.topology {
        let (file, path) =
            drivelab_runtime::topology::load(t).map_err(|e| anyhow!("--topology: {e}"))?;
        let base = path.parent().unwrap_or(Path::new(".")).to_path_buf();
        sc.process = file.process;
        for p in sc.process.iter_mut() {
            if let Some(e) = drivelab_runtime::topology::exec_path(p, &base) {
                p.exec = Some(e.display().to_string());
            }
        }
        sc.placement = drivelab_runtime::config::Placement::default();
        sc.validate().map_err(|e| anyhow!("--topology {t}: {e}"))?;
    }
    let base = sc_src.parent().unwrap_or(Path::new(".")).to_path_buf();
    let mut procs = sc.topology();
    for p in procs.iter_mut() {
        if let Some(e) = drivelab_runtime::topology::exec_path(p, &base) {
            p.exec = Some(e.display().to_string());
        }
    }
    let mut described: BTreeMap<String, Vec<StageInfo>> = BTreeMap::new();
    let scc = sc.clone();
    let sc_text = toml::to_string(&scc)?;
    let resolved = drivelab_runtime::topology::resolve(&procs, &mut |p, stage| {
        if let Some(i) = drivelab_runtime::topology::builtin_info(&scc, stage) {
            if p.exec.is_none() || drivelab_runtime::stages::BUILTIN.contains(&stage) {
                return Ok(i);
            }
        }
        let exe = p
            .exec
            .clone()
            .ok_or_else(|| format!("unknown stage '{stage}'"))?;
        if !described.contains_key(&exe) {
            described.insert(
                exe.clone(),
                describe(&exe, &sc_text).map_err(|e| format!("process '{}': {e:#}", p.name))?,
            );
        }
        described[&exe]
            .iter()
            .find(|i| i.name == stage)
            .cloned()
            .ok_or_else(|| {
                format!(
                    "process '{}': its executable {exe} hosts no stage '{stage}'",
                    p.name
                )
            })
    })
    .map_err(|e| anyhow!(e))?;
    sc.process = resolved.processes.iter().map(|(p, _)| p.clone()).collect();
    sc.placement = drivelab_runtime::config::Placement::default();
    Ok(TopologyPlan::from_resolved(&resolved))
}

/// Asks a user's stage executable which stages it hosts.
fn describe(exe: &str, sc_text: &str) -> Result<Vec<StageInfo>> {
    if !Path::new(exe).is_file() {
        bail!("executable {exe} not found (build it first: cargo build --release --workspace)");
    }
    let dir = std::env::temp_dir().join(format!("drivelab-describe-{}", std::process::id()));
    std::fs::create_dir_all(&dir)?;
    let f = dir.join("scenario.toml");
    std::fs::write(&f, sc_text)?;
    let out = Command::new(exe)
        .arg("--describe")
        .arg("--scenario")
        .arg(&f)
        .stdin(Stdio::null())
        .output()
        .with_context(|| format!("cannot run {exe} --describe"));
    let _ = std::fs::remove_dir_all(&dir);
    let out = out?;
    if !out.status.success() {
        bail!(
            "{exe} --describe failed: {}",
            String::from_utf8_lossy(&out.stderr).trim()
        );
    }
    serde_json::from_slice(&out.stdout)
        .with_context(|| format!("{exe} --describe: not a stage list"))
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
    // The outer loop's position reference in use at k: the newest computed before k.
    let mut wref = rec.wref.clone();
    wref.sort_by_key(|w| w.0);
    let mut wi = 0;
    let mut theta_ref = None;
    for (k, m) in rec.meas.iter().enumerate() {
        let k = k as u64;
        while wi < wref.len() && wref[wi].0 < k {
            theta_ref = Some(wref[wi].1);
            wi += 1;
        }
        match (m, &rec.cmd[k as usize]) {
            (Some(m), Some(c)) => {
                let mut row = trace_row(ts, m, c);
                row.theta_m_ref = theta_ref;
                rows.push(row);
            }
            (Some(m), None) => {
                let nan = f64::NAN;
                let c = VoltageCommand {
                    hdr: drivelab_runtime::messages::Header {
                        k: m.hdr.k,
                        flags: drivelab_runtime::messages::FLAG_MISSING,
                        ..Default::default()
                    },
                    u_ab: [nan; 2],
                    u_dq: [nan; 2],
                    i_dq_ref: [nan; 2],
                    omega_ref: nan,
                    omega_hat: nan,
                    theta_hat: nan,
                };
                let mut row = trace_row(ts, m, &c);
                row.theta_m_ref = theta_ref;
                rows.push(row);
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
    // The launcher stops on SIGINT/SIGTERM the same way the services do.
    crate::common::install_signal_handlers()?;
    if let Some(b) = &o.bus {
        bus::check_bus_id(b)?;
    }
    let (mut sc, sc_src) = Scenario::load(&o.scenario).map_err(|e| anyhow!(e))?;
    if let Some(d) = o.duration_s {
        sc.duration_s = d;
        sc.validate().map_err(|e| anyhow!("--duration {d}: {e}"))?;
    }
    let topo = resolve_topology(&mut sc, &sc_src, o)?;
    // Faults are checked before anything is created: a bad plan leaves nothing behind.
    let stage_names: Vec<String> = topo.stages.iter().map(|s| s.name.clone()).collect();
    let plan = crate::faults::plan(&o.faults, sc.duration_s, o.fault_seed, 0.3, &stage_names)?;
    if !plan.is_empty() && o.clock != Clock::Realtime {
        bail!("fault injection needs --clock realtime");
    }
    let out = o.out.clone().unwrap_or_else(|| default_out(&sc, o.clock));
    std::fs::create_dir_all(&out)
        .with_context(|| format!("cannot create run folder {}", out.display()))?;
    let out = out.canonicalize()?;
    let sc_path = out.join("scenario.toml");
    std::fs::write(&sc_path, toml::to_string(&sc)?)
        .with_context(|| format!("write {}", sc_path.display()))?;
    std::fs::write(out.join("topology.json"), serde_json::to_vec_pretty(&topo)?)?;
    let wall = Instant::now();
    let (rows, gaps, processes, info) = match o.clock {
        Clock::Inprocess => {
            if let Some(p) = topo.processes.iter().find(|p| p.exec.is_some()) {
                bail!(
                    "--clock inprocess runs the built-in stages only; process '{}' hosts user stages ({}): use --clock lockstep",
                    p.name,
                    p.stages.join(", ")
                );
            }
            (
                drivelab_runtime::stages::run_inprocess(&sc),
                Vec::new(),
                json!({}),
                json!({ "deadline_misses": 0 }),
            )
        }
        Clock::Lockstep => run_bus(&sc, &sc_path, &topo, &plan, o, &out, BusClock::Lockstep)?,
        Clock::Realtime => run_bus(&sc, &sc_path, &topo, &plan, o, &out, BusClock::Realtime)?,
    };
    let wall_s = wall.elapsed().as_secs_f64();
    let events: Vec<SupEvent> = info
        .get("events")
        .and_then(|e| serde_json::from_value::<Vec<serde_json::Value>>(e.clone()).ok())
        .unwrap_or_default()
        .into_iter()
        .filter_map(|v| {
            Some(SupEvent {
                t_wall_s: v["t_wall_s"].as_f64()?,
                k: v["k"].as_u64()?,
                event: v["event"].as_str()?.into(),
                service: v["service"].as_str()?.into(),
                process: v["process"].as_str().unwrap_or_default().into(),
                detail: v["detail"].as_str()?.into(),
            })
        })
        .collect();
    let (faults, windows) = fault_reports(&sc, &rows, &events);
    // Name the cause of every gap that a plant fault explains.
    let mut gaps = gaps;
    for g in gaps.iter_mut() {
        let fs = sc.rates.sample_hz;
        // The fault whose window (injection → recovery) holds the gap.
        let in_window = |f: &&FaultReport| {
            let end = f.injected_k
                + ((f.speed_recovered_ms.or(f.republished_ms).unwrap_or(200.0)) * 1e-3 * fs) as u64;
            f.injected_k <= g.from && g.from <= end
        };
        if let Some(f) = faults.iter().rev().find(in_window) {
            g.cause = match (g.part, f.service.as_str()) {
                ("measurement", "plant") => format!("plant {} at sample {} (fault); the model is not simulated while the plant is down", f.fault, f.injected_k),
                (part, svc) => format!("no {part} recorded during fault '{} {svc}' injected at sample {}", f.fault, f.injected_k),
            };
        }
    }
    drivelab_runtime::trace::write_csv(&out.join("trace.csv"), &rows)?;
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
        "faults": faults,
        "supervisor_events": events,
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
        drivelab_tools::plot::plot_percentiles(
            &curves,
            &format!("{}: latency percentiles", sc.name),
            budget,
            true,
            &out.join("latency"),
        )?;
    }
    if !o.no_plots && !rows.is_empty() {
        let opts = drivelab_tools::plot::TraceFigureOptions {
            current_limit_a: Some(sc.i_q_max()),
            voltage_limit_v: Some(sc.u_max()),
            title: format!("{} ({:?})", sc.name, o.clock).to_lowercase(),
            shaded_windows: windows.clone(),
            ..Default::default()
        };
        let mut files = drivelab_tools::plot::plot_trace(&rows, &out, &opts)?;
        if drivelab_runtime::wiring::polar::mode_of(&sc).is_some() || !sc.reference.i_q_a.is_empty()
        {
            files.extend(drivelab_tools::plot_polar::plot_polar_panels(
                &sc,
                &rows,
                &out,
                &opts.title,
            )?);
        }
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
    BTreeMap<String, drivelab_runtime::timing::Percentiles>,
    Vec<drivelab_tools::plot::PercentileSeries>,
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
        let h = drivelab_runtime::timing::LatencyHist::read_v2("hist", &f)?;
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

/// The supervisor: injects the planned faults when the drive reaches their sample, notices
/// dead services (waitpid, then iceoryx2's node liveness, whose stale resources it removes),
/// restarts them per policy with `--rejoin`, and records every event. Returns a failure
/// message when the run cannot go on.
#[allow(clippy::too_many_arguments)]
fn supervise(
    hub: &mut crate::hub::Hub,
    bar: &indicatif::ProgressBar,
    children: &mut [ChildProc],
    plan: &[crate::faults::Fault],
    events: &mut Vec<SupEvent>,
    progress: &Progress,
    sc: &Scenario,
    sp: &Spawn,
    started: Instant,
    limit: Duration,
) -> Result<Option<String>> {
    let (bus_id, clock, o, out) = (sp.bus_id, sp.clock, sp.o, sp.out);
    use crate::faults::{signal, FaultKind};
    let fs = sc.rates.sample_hz;
    let mut next_fault = 0;
    let mut pending_cont: Vec<(Instant, usize)> = Vec::new();
    let mut pending_restart: Vec<(Instant, usize)> = Vec::new();
    let mut restarts = vec![0u32; children.len()];
    // Back-off grows with restarts in quick succession and resets after 2 s of good health.
    let mut backoff_level = vec![0u32; children.len()];
    let mut last_restart: Vec<Option<Instant>> = vec![None; children.len()];
    let mut dead = vec![false; children.len()];
    let mut done = vec![false; children.len()];
    let mut awaiting_ready = vec![false; children.len()];
    let ev =
        |events: &mut Vec<SupEvent>, event: &str, service: &str, process: &str, detail: String| {
            events.push(SupEvent {
                t_wall_s: started.elapsed().as_secs_f64(),
                k: progress.next_k.load(Ordering::Relaxed),
                event: event.into(),
                service: service.into(),
                process: process.into(),
                detail,
            });
        };
    const MAX_RESTARTS: u32 = 1000;
    loop {
        if crate::common::stop_requested() {
            return Ok(Some("interrupted (SIGINT/SIGTERM): drive stopped".into()));
        }
        if started.elapsed() > limit {
            return Ok(Some(format!("the drive did not finish within {limit:?}")));
        }
        let now = Instant::now();
        let k_now = progress.next_k.load(Ordering::Relaxed);
        bar.set_position(k_now);
        // Faults due at this point of the run (in samples, so lockstep and realtime agree),
        // then those a monitor asked for, each with a note on where it came from.
        let mut due: Vec<(crate::faults::Fault, String)> = Vec::new();
        while next_fault < plan.len() && k_now as f64 >= plan[next_fault].at_s * fs {
            due.push((plan[next_fault].clone(), String::new()));
            next_fault += 1;
        }
        for r in hub.poll(events, k_now, &progress.tail)? {
            match crate::hub::to_fault(&r, k_now as f64 / fs) {
                Ok(f) => due.push((f, format!(" (from monitor pid {})", r.pid))),
                Err(e) => ev(events, "inject-refused", "-", "-", format!("{e:#}")),
            }
        }
        for (f, origin) in due {
            // A stage's fault hits the whole process that hosts it.
            let Some(i) = children.iter().position(|c| c.stages.contains(&f.service)) else {
                continue;
            };
            let pname = children[i].name.clone();
            if clock != BusClock::Realtime {
                // Only a monitor's request can get here: a plan is refused before the start.
                ev(
                    events,
                    "inject-refused",
                    &f.service,
                    &pname,
                    "faults need --clock realtime".into(),
                );
                continue;
            }
            if dead[i] || done[i] || pending_cont.iter().any(|&(_, j)| j == i) {
                ev(
                    events,
                    "inject-skipped",
                    &f.service,
                    &pname,
                    "its process is not running".into(),
                );
                continue;
            }
            let sig = match f.kind {
                FaultKind::Kill => libc::SIGKILL,
                FaultKind::Stop => libc::SIGSTOP,
            };
            signal(children[i].child.id(), sig)?;
            ev(
                events,
                "inject",
                &f.service,
                &pname,
                format!(
                    "{}{}{origin}",
                    crate::faults::kind_name(f.kind),
                    if f.kind == FaultKind::Stop {
                        format!(" for {} s", f.duration_s)
                    } else {
                        String::new()
                    }
                ),
            );
            if f.kind == FaultKind::Stop {
                pending_cont.push((now + Duration::from_secs_f64(f.duration_s), i));
            }
        }
        pending_cont.retain(|&(t, i)| {
            if now >= t {
                let _ = signal(children[i].child.id(), libc::SIGCONT);
                let n = children[i].name.clone();
                ev(events, "resume", &n, &n, "SIGCONT".into());
                false
            } else {
                true
            }
        });
        // Liveness: our own children first (waitpid), then iceoryx2's view of the bus.
        let mut any_dead = false;
        for i in 0..children.len() {
            if dead[i] || done[i] {
                continue;
            }
            if awaiting_ready[i] {
                while let Ok(l) = children[i].lines.try_recv() {
                    if l == "READY" {
                        awaiting_ready[i] = false;
                        let n = children[i].name.clone();
                        ev(
                            events,
                            "ready",
                            &n,
                            &n,
                            format!("pid {}", children[i].child.id()),
                        );
                    } else if let Some(j) = l.strip_prefix("RT ") {
                        children[i].rt = serde_json::from_str(j).ok();
                    }
                }
            }
            match children[i].child.try_wait()? {
                None => {}
                Some(st) if st.success() => done[i] = true,
                Some(st) => {
                    dead[i] = true;
                    any_dead = true;
                    let n = children[i].name.clone();
                    ev(events, "exited", &n, &n, format!("{st}"));
                    let injected = events.iter().any(|e| e.event == "inject" && e.process == n);
                    if o.restart == Restart::Never || restarts[i] >= MAX_RESTARTS {
                        if !injected {
                            return Ok(Some(format!("process {n} failed ({st})")));
                        }
                        if children[i].source {
                            // Without a plant there is no drive: stop the rest.
                            return Ok(None);
                        }
                    } else {
                        if last_restart[i]
                            .is_some_and(|t| now.duration_since(t) > Duration::from_secs(2))
                        {
                            backoff_level[i] = 0;
                        }
                        let backoff = Duration::from_millis(
                            10u64.saturating_mul(1 << backoff_level[i].min(7)).min(1000),
                        );
                        backoff_level[i] += 1;
                        pending_restart.push((now + backoff, i));
                    }
                }
            }
        }
        if any_dead {
            let reaped = bus::reap_dead_nodes(bus_id)?;
            ev(
                events,
                "reaped",
                "-",
                "-",
                format!("dead iceoryx2 nodes cleaned: {}", reaped.join(", ")),
            );
        }
        let mut still = Vec::new();
        for (t, i) in pending_restart.drain(..) {
            if now < t {
                still.push((t, i));
                continue;
            }
            let name = children[i].name.clone();
            let rejoin_file = out.join(format!("rejoin-{name}.json"));
            if children[i].source {
                let last = progress.last.lock().ok().and_then(|l| *l);
                let Some(last) = last else {
                    return Ok(Some(
                        "plant died before its first sample; cannot resume".into(),
                    ));
                };
                std::fs::write(
                    &rejoin_file,
                    serde_json::to_vec(&crate::common::truth_to_json(&last))?,
                )?;
            }
            let (spec, exe, source) = (
                children[i].spec.clone(),
                children[i].exe.clone(),
                children[i].source,
            );
            let c = spawn_service(&spec, &exe, source, sp, Some(&rejoin_file))?;
            children[i] = c;
            restarts[i] += 1;
            last_restart[i] = Some(now);
            dead[i] = false;
            awaiting_ready[i] = true;
            ev(
                events,
                "restarted",
                &name,
                &name,
                format!("restart #{}, pid {}", restarts[i], children[i].child.id()),
            );
        }
        pending_restart = still;
        for i in 0..children.len() {
            use drivelab_runtime::telemetry::ProcState;
            let state = if done[i] {
                ProcState::Finished
            } else if dead[i] {
                if pending_restart.iter().any(|&(_, j)| j == i) {
                    ProcState::Restarting
                } else {
                    ProcState::Dead
                }
            } else if awaiting_ready[i] {
                ProcState::Restarting
            } else if pending_cont.iter().any(|&(_, j)| j == i) {
                ProcState::Frozen
            } else {
                ProcState::Alive
            };
            for st in &children[i].stages {
                if let Some(j) = SERVICES.iter().position(|s| s == st) {
                    hub.set_process(j, state, children[i].child.id(), restarts[i]);
                }
            }
        }
        let plant_done = children.iter().zip(&done).any(|(c, d)| c.source && *d);
        if done.iter().zip(&dead).all(|(d, x)| *d || *x) && pending_restart.is_empty() {
            return Ok(None);
        }
        if plant_done && pending_restart.is_empty() {
            // The plant has finished; anyone not done within 2 s is stopped by the caller.
            let t = Instant::now();
            while t.elapsed() < Duration::from_secs(2) {
                if children
                    .iter_mut()
                    .zip(&done)
                    .all(|(c, d)| *d || matches!(c.child.try_wait(), Ok(Some(_))))
                {
                    break;
                }
                std::thread::sleep(Duration::from_millis(5));
            }
            return Ok(None);
        }
        std::thread::sleep(Duration::from_millis(1));
    }
}

/// One entry of `summary.json` → `faults`. Times are in ms from the injection.
#[derive(Debug, Clone, Serialize)]
pub struct FaultReport {
    /// kill or stop (with its duration).
    pub fault: String,
    /// Target stage.
    pub service: String,
    /// The process that was signalled (it hosts the stage, perhaps with others).
    pub process: String,
    /// Injection: sample index and simulated time, s.
    pub injected_k: u64,
    /// Injection time, s (sample time).
    pub injected_t_s: f64,
    /// First sample at which a consumer saw a stale input (data path), ms after injection.
    pub detected_data_path_ms: Option<f64>,
    /// Which consumer saw it first: "plant" (stale command) or "current-loop" (fallback).
    pub detected_by: Option<String>,
    /// The supervisor saw the process dead (waitpid), ms of wall time after injection.
    pub detected_supervisor_ms: Option<f64>,
    /// The plant's inverter reached its safe state, ms after injection.
    pub safe_state_ms: Option<f64>,
    /// Peak current magnitude |i_dq| from injection to recovery, A.
    pub peak_current_a: f64,
    /// The restarted (or resumed) service published a fresh output again, ms after injection.
    pub republished_ms: Option<f64>,
    /// Speed back within ±2 % of its reference (and staying there 10 ms), ms after injection.
    pub speed_recovered_ms: Option<f64>,
}

/// Builds the fault reports from the supervisor's events and the trace, and the windows to
/// shade on the plots.
pub fn fault_reports(
    sc: &Scenario,
    rows: &[TraceRow],
    events: &[SupEvent],
) -> (Vec<FaultReport>, Vec<(f64, f64, String)>) {
    use drivelab_runtime::messages::{FLAG_SAFE_STATE, FLAG_STALE_CMD, FLAG_STALE_INPUT};
    let fs = sc.rates.sample_hz;
    let ms = |dk: u64| dk as f64 / fs * 1e3;
    let by_k: BTreeMap<u64, &TraceRow> = rows.iter().map(|r| (r.k, r)).collect();
    let mut out = Vec::new();
    let mut windows = Vec::new();
    let injects: Vec<&SupEvent> = events.iter().filter(|e| e.event == "inject").collect();
    for (n, inj) in injects.iter().enumerate() {
        let k0 = inj.k;
        let k_end_window = injects.get(n + 1).map(|e| e.k).unwrap_or(u64::MAX);
        let after = || by_k.range(k0..k_end_window).map(|(_, r)| *r);
        // Data-path detection: the first stale flag, or the first sample the plant did not produce.
        let mut det = None;
        for (expect, r) in (k0..).zip(after()) {
            if r.k != expect {
                det = Some((expect, "recorder (plant produced no sample)".to_string()));
                break;
            }
            if r.plant_flags & FLAG_STALE_CMD != 0 {
                det = Some((r.k, "plant".into()));
                break;
            }
            if r.ctrl_flags & FLAG_STALE_INPUT != 0 {
                det = Some((r.k, "current-loop".into()));
                break;
            }
        }
        let safe = after()
            .find(|r| r.plant_flags & FLAG_SAFE_STATE != 0)
            .map(|r| ms(r.k - k0));
        let sup = events
            .iter()
            .find(|e| e.event == "exited" && e.process == inj.process && e.t_wall_s >= inj.t_wall_s)
            .map(|e| (e.t_wall_s - inj.t_wall_s) * 1e3);
        // Fresh again: the first sample after the detection with no stale flag at all.
        let k_det = det.as_ref().map(|d| d.0).unwrap_or(k0);
        let fresh = after()
            .filter(|r| r.k > k_det)
            .find(|r| r.plant_flags & (FLAG_STALE_CMD | FLAG_SAFE_STATE) == 0 && r.ctrl_flags == 0)
            .map(|r| r.k);
        let hold = (0.01 * fs).ceil() as usize;
        let within = |r: &TraceRow| {
            let w = drivelab_runtime::config::profile_at(&sc.reference.speed_rad_s, r.t);
            (r.omega_m - w).abs() <= 0.02 * w.abs().max(1e-9)
        };
        let tail: Vec<&TraceRow> = after()
            .filter(|r| fresh.is_some_and(|f| r.k >= f))
            .collect();
        let rec = (0..tail.len())
            .find(|&i| tail[i..].iter().take(hold).all(|r| within(r)) && tail.len() - i >= hold)
            .map(|i| tail[i].k);
        let k_rec = rec
            .or(fresh)
            .unwrap_or(k_end_window.min(k0 + (0.2 * fs) as u64));
        let peak = after()
            .filter(|r| r.k <= k_rec)
            .map(|r| (r.i_d * r.i_d + r.i_q * r.i_q).sqrt())
            .fold(0.0, f64::max);
        windows.push((
            k0 as f64 / fs,
            k_rec as f64 / fs,
            format!("{} {}", inj.detail, inj.service),
        ));
        out.push(FaultReport {
            fault: inj.detail.clone(),
            service: inj.service.clone(),
            process: inj.process.clone(),
            injected_k: k0,
            injected_t_s: k0 as f64 / fs,
            detected_data_path_ms: det.as_ref().map(|d| ms(d.0 - k0)),
            detected_by: det.map(|d| d.1),
            detected_supervisor_ms: sup,
            safe_state_ms: safe,
            peak_current_a: peak,
            republished_ms: fresh.map(|f| ms(f - k0)),
            speed_recovered_ms: rec.map(|r| ms(r - k0)),
        });
    }
    (out, windows)
}
