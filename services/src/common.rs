//! What every service does the same way: arguments, signals, RT setup, the start handshake
//! with the launcher, and the statistics file written at exit.

use anyhow::{anyhow, Context, Result};
use clap::{Parser, ValueEnum};
use drivelab_runtime::config::Scenario;
use drivelab_runtime::rt::{setup_rt, RtPolicy, RtReport, RtRequest};
use drivelab_runtime::timing::LatencyHist;
use serde::Serialize;
use std::io::Write;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};

/// How the plant paces the samples.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum BusClock {
    /// Plant sleeps to absolute deadlines; a late command is a deadline miss.
    Realtime,
    /// Plant waits for each command; no wall clock; reproducible bit for bit.
    Lockstep,
}

/// Arguments shared by the four service binaries (normally given by `drivelab run`).
#[derive(Debug, Parser)]
pub struct ServiceArgs {
    /// Resolved scenario file (TOML), as written by `drivelab run` into the run folder.
    #[arg(long)]
    pub scenario: PathBuf,
    /// Bus id: isolates this drive's shared memory (1-24 characters of A-Z, a-z, 0-9, _).
    #[arg(long)]
    pub bus: String,
    /// Pacing of the cycle.
    #[arg(long, value_enum, default_value_t = BusClock::Realtime)]
    pub clock: BusClock,
    /// Fail instead of warning when a core, SCHED_FIFO priority or mlock is refused.
    #[arg(long)]
    pub rt_strict: bool,
    /// Skip pinning, SCHED_FIFO and mlock entirely.
    #[arg(long)]
    pub no_rt: bool,
    /// Folder for this service's statistics file (`<service>.stats.json`).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Plant only: in lockstep, do not run more than half a recorder buffer ahead of the
    /// recorder (so that it never loses a sample).
    #[arg(long)]
    pub recorder: bool,
    /// Restarted by the supervisor: skip the start handshake and take over bumplessly from
    /// the running drive.
    #[arg(long)]
    pub rejoin: bool,
    /// Plant only, with --rejoin: JSON file with the last measurement the recorder saw.
    #[arg(long, value_name = "FILE")]
    pub rejoin_from: Option<PathBuf>,
}

static STOP: AtomicBool = AtomicBool::new(false);

extern "C" fn on_signal(_sig: libc::c_int) {
    STOP.store(true, Ordering::SeqCst);
}

/// Installs SIGINT/SIGTERM handlers that set the stop flag (iceoryx2's own handling is off).
pub fn install_signal_handlers() -> Result<()> {
    for sig in [libc::SIGINT, libc::SIGTERM] {
        // SAFETY: `sigaction` is given a zero-initialised struct whose handler is an
        // `extern "C"` function that only stores to an atomic, which is async-signal-safe.
        let rc = unsafe {
            let mut sa: libc::sigaction = std::mem::zeroed();
            sa.sa_sigaction = on_signal as *const () as libc::sighandler_t;
            libc::sigemptyset(&mut sa.sa_mask);
            libc::sigaction(sig, &sa, std::ptr::null_mut())
        };
        if rc != 0 {
            return Err(anyhow!(
                "cannot install handler for signal {sig}: {}",
                std::io::Error::last_os_error()
            ));
        }
    }
    Ok(())
}

/// True once SIGINT or SIGTERM arrived.
pub fn stop_requested() -> bool {
    STOP.load(Ordering::Relaxed)
}

/// Loads the (already validated) scenario a service was given.
pub fn load_scenario(args: &ServiceArgs) -> Result<Scenario> {
    let text = std::fs::read_to_string(&args.scenario)
        .with_context(|| format!("cannot read scenario {}", args.scenario.display()))?;
    Scenario::from_toml(&text, &args.scenario.display().to_string()).map_err(|e| anyhow!(e))
}

/// Applies the scenario's placement for `service` and prints the one-line report to stderr.
/// Also sends `RT <json>` on stdout for the launcher.
pub fn apply_placement(service: &str, sc: &Scenario, args: &ServiceArgs) -> Result<RtReport> {
    let p = sc
        .placement
        .get(service)
        .ok_or_else(|| anyhow!("unknown service '{service}'"))?;
    let req = if args.no_rt {
        RtRequest {
            core: None,
            fifo_priority: None,
            lock_memory: false,
            prefault_stack_bytes: 0,
        }
    } else {
        RtRequest {
            core: p.core,
            fifo_priority: p.priority,
            lock_memory: true,
            prefault_stack_bytes: 256 * 1024,
        }
    };
    let policy = if args.rt_strict {
        RtPolicy::Strict
    } else {
        RtPolicy::Warn
    };
    let report = setup_rt(&req, policy).map_err(|e| anyhow!("{service}: {e}"))?;
    eprintln!("{}", report.one_line(service));
    protocol_line(&format!("RT {}", serde_json::to_string(&report)?))?;
    Ok(report)
}

/// Writes one protocol line to stdout (to the launcher) and flushes it.
pub fn protocol_line(line: &str) -> Result<()> {
    let mut out = std::io::stdout().lock();
    writeln!(out, "{line}")?;
    out.flush()?;
    Ok(())
}

/// Tells the launcher this service's ports exist.
pub fn ready() -> Result<()> {
    protocol_line("READY")
}

/// Counters every service keeps (no allocation in the loop: plain integers).
#[derive(Debug, Clone, Copy, Default, Serialize)]
pub struct Counters {
    /// Samples processed.
    pub samples: u64,
    /// Inputs that were not there (or not the expected index) when needed.
    pub stale_inputs: u64,
    /// Inputs rejected because they held NaN/∞ or an index that went backwards.
    pub rejected_inputs: u64,
    /// Plant only: samples that used a held or safe command (deadline misses).
    pub deadline_misses: u64,
    /// Plant only: longest run of consecutive misses.
    pub longest_miss_run: u64,
    /// Plant only: commands that arrived after their deadline and were discarded.
    pub late_commands: u64,
    /// Inputs deliberately skipped to catch up after falling behind (real time only).
    pub skipped: u64,
    /// Plant only: wall time from sample 0 to the end marker, ns.
    pub loop_wall_ns: u64,
    /// Controllers only: outputs published after the end of their sample period
    /// (t_k + T_s; real time only), and the longest run of them.
    pub late_outputs: u64,
    /// Controllers only: longest run of consecutive late outputs.
    pub longest_late_run: u64,
}

/// Statistics file of one service.
#[derive(Debug, Serialize)]
pub struct ServiceStats<'a> {
    /// Service name.
    pub service: &'a str,
    /// Process id.
    pub pid: u32,
    /// RT setup report.
    pub rt: &'a RtReport,
    /// Counters.
    pub counters: Counters,
    /// Tail summary of each histogram, µs, keyed `<service>.<metric>` (and `cycle`).
    pub latency_us: std::collections::BTreeMap<String, drivelab_runtime::timing::Percentiles>,
}

/// Per-service histograms, preallocated before the loop.
#[derive(Debug)]
pub struct ServiceHists {
    /// Wake-up: for the plant, release lateness (wake − deadline); for the others, the bus
    /// hop (wake − the input's publish time).
    pub wake: LatencyHist,
    /// Execution time of the step (input taken → output published).
    pub exec: LatencyHist,
    /// Age of the input when used, from its sample instant t_k (realtime only).
    pub input_age: LatencyHist,
    /// Controllers: outputs published after t_k + T_s (deadline misses of this stage).
    pub late: drivelab_runtime::timing::MissCounter,
    ts_ns: u64,
}

impl ServiceHists {
    /// Creates the three histograms for a drive sampled every `ts_ns`.
    pub fn new(plant: bool, ts_ns: u64) -> Self {
        Self {
            wake: LatencyHist::new(if plant { "lateness" } else { "wake" }),
            exec: LatencyHist::new("exec"),
            input_age: LatencyHist::new("input_age"),
            late: drivelab_runtime::timing::MissCounter::default(),
            ts_ns,
        }
    }

    /// Records the wake-up and input age of an input published at `t_pub` for sample
    /// instant `t_sample` (0 in lockstep: no age). Returns the time taken (the exec start).
    #[inline]
    pub fn input(&mut self, t_pub: u64, t_sample: u64) -> u64 {
        let t_in = drivelab_runtime::rt::now_ns();
        self.wake.record_ns(t_in as i64 - t_pub as i64);
        if t_sample != 0 {
            self.input_age.record_ns(t_in as i64 - t_sample as i64);
        }
        t_in
    }

    /// Records the execution time since `t_in` of the step for sample instant `t_sample`
    /// (0 in lockstep) and whether its output came after t_sample + T_s (a late output).
    #[inline]
    pub fn done(&mut self, t_in: u64, t_sample: u64) {
        let now = drivelab_runtime::rt::now_ns();
        self.exec.record_ns(now as i64 - t_in as i64);
        self.late
            .record(t_sample != 0 && now > t_sample + self.ts_ns);
    }
}

/// Live status for the supervisor (and through it `drivelab monitor`), published ten times
/// per simulated second on [`drivelab_runtime::telemetry::TOPIC_STATUS`]. The supervisor subscribes
/// before the services start and the publisher connects here, before the loop, so the loop
/// only ever copies a message into a loaned sample.
pub struct StatusPublisher {
    _topic: drivelab_runtime::telemetry::Plain<drivelab_runtime::telemetry::ServiceStatus>,
    tx: drivelab_runtime::telemetry::PlainSender<drivelab_runtime::telemetry::ServiceStatus>,
    st: drivelab_runtime::telemetry::ServiceStatus,
    every: u64,
    next_k: u64,
}

impl StatusPublisher {
    /// Opens the status topic for `service` of scenario `sc`.
    pub fn new(
        node: &iceoryx2::prelude::Node<iceoryx2::prelude::ipc::Service>,
        service: &str,
        sc: &Scenario,
    ) -> Result<Self> {
        use drivelab_runtime::telemetry::*;
        let topic = open_plain::<ServiceStatus>(node, TOPIC_STATUS, 16, 0)?;
        let tx = PlainSender::new(&topic)?;
        let idx = drivelab_runtime::config::SERVICES
            .iter()
            .position(|s| *s == service)
            .ok_or_else(|| anyhow!("unknown service '{service}'"))?;
        let st = ServiceStatus {
            service: idx as u32,
            pid: std::process::id(),
            ..Default::default()
        };
        Ok(Self {
            _topic: topic,
            tx,
            st,
            every: ((sc.rates.sample_hz / 10.0).round() as u64).max(1),
            next_k: 0,
        })
    }

    /// Publishes a status if sample `k` has reached the next tenth of a simulated second.
    /// `cycle` is the plant's cycle monitor (deadline misses and cycle latency). No
    /// allocation: a copy into a loaned sample.
    #[inline]
    pub fn tick(
        &mut self,
        k: u64,
        c: &Counters,
        h: &ServiceHists,
        cycle: Option<&drivelab_runtime::timing::CycleMonitor>,
    ) -> Result<()> {
        if k < self.next_k {
            return Ok(());
        }
        self.next_k = (k / self.every + 1) * self.every;
        let st = &mut self.st;
        st.hdr.k = k;
        st.hdr.t_pub_ns = drivelab_runtime::rt::now_ns();
        st.samples = c.samples;
        st.stale_inputs = c.stale_inputs;
        st.rejected_inputs = c.rejected_inputs;
        st.skipped = c.skipped;
        st.wake = h.wake.compact;
        st.exec = h.exec.compact;
        match cycle {
            Some(m) => {
                st.misses = m.misses.misses;
                st.longest_miss_run = m.misses.longest_run;
                st.cycle = m.cycle.compact;
            }
            None => {
                st.misses = h.late.misses;
                st.longest_miss_run = h.late.longest_run;
            }
        }
        self.tx.send(st)
    }
}

/// Writes `<out>/<service>.stats.json` and one `<key>.hdr` per non-empty histogram (plus
/// `extra`, e.g. the plant's `cycle`) if an output folder was given.
pub fn write_stats(
    args: &ServiceArgs,
    service: &str,
    rt: &RtReport,
    counters: Counters,
    hists: &ServiceHists,
    extra: &[&LatencyHist],
) -> Result<()> {
    let Some(dir) = &args.out else { return Ok(()) };
    let mut counters = counters;
    if service != "plant" {
        counters.late_outputs = hists.late.misses;
        counters.longest_late_run = hists.late.longest_run;
    }
    let mut latency_us = std::collections::BTreeMap::new();
    for h in [&hists.wake, &hists.exec, &hists.input_age]
        .into_iter()
        .chain(extra.iter().copied())
    {
        if h.is_empty() {
            continue;
        }
        let key = if h.name == "cycle" {
            "cycle".to_string()
        } else {
            format!("{service}.{}", h.name)
        };
        h.write_v2(&dir.join(format!("{key}.hdr")))?;
        latency_us.insert(key, h.percentiles());
    }
    let stats = ServiceStats {
        service,
        pid: std::process::id(),
        rt,
        counters,
        latency_us,
    };
    let p = dir.join(format!("{service}.stats.json"));
    std::fs::write(&p, serde_json::to_vec_pretty(&stats)?)
        .with_context(|| format!("write {}", p.display()))?;
    Ok(())
}

/// Runs a service's `main`: prints a one-line error and exits non-zero on failure.
pub fn service_main(
    name: &str,
    f: impl FnOnce(ServiceArgs) -> Result<()>,
) -> std::process::ExitCode {
    let args = ServiceArgs::parse();
    if let Err(e) = install_signal_handlers().and_then(|_| f(args)) {
        eprintln!("{name}: error: {e:#}");
        return std::process::ExitCode::from(1);
    }
    std::process::ExitCode::SUCCESS
}

/// Poll period of waits that must also notice a stop request, ms.
pub const WAIT_SLICE: std::time::Duration = std::time::Duration::from_millis(50);

/// In lockstep, how long a service waits for its input before it gives up (the upstream
/// process is considered gone).
pub const LOCKSTEP_WATCHDOG: std::time::Duration = std::time::Duration::from_secs(10);

/// The last measurement as JSON (the supervisor hands it to a restarted plant).
pub fn measurement_to_json(m: &drivelab_runtime::messages::Measurement) -> serde_json::Value {
    serde_json::json!({
        "k": m.hdr.k, "t_sample_ns": m.hdr.t_sample_ns,
        "i_abc": m.i_abc, "theta_m_enc": m.theta_m_enc, "u_ab_applied": m.u_ab_applied,
        "i_dq_true": m.i_dq_true, "omega_m_true": m.omega_m_true, "theta_e_true": m.theta_e_true,
        "u_dq_applied": m.u_dq_applied, "t_load": m.t_load,
    })
}

/// Reads a measurement written by [`measurement_to_json`].
pub fn measurement_from_json(
    v: &serde_json::Value,
) -> Result<drivelab_runtime::messages::Measurement> {
    let f = |key: &str| {
        v[key]
            .as_f64()
            .ok_or_else(|| anyhow!("rejoin file: '{key}' missing"))
    };
    let a2 = |key: &str| -> Result<[f64; 2]> {
        let a = v[key]
            .as_array()
            .ok_or_else(|| anyhow!("rejoin file: '{key}' missing"))?;
        Ok([
            a.first().and_then(|x| x.as_f64()).unwrap_or(0.0),
            a.get(1).and_then(|x| x.as_f64()).unwrap_or(0.0),
        ])
    };
    let i3 = v["i_abc"]
        .as_array()
        .ok_or_else(|| anyhow!("rejoin file: 'i_abc' missing"))?;
    let mut m = drivelab_runtime::messages::Measurement::default();
    m.hdr.k = v["k"]
        .as_u64()
        .ok_or_else(|| anyhow!("rejoin file: 'k' missing"))?;
    m.hdr.t_sample_ns = v["t_sample_ns"].as_u64().unwrap_or(0);
    for (i, x) in i3.iter().take(3).enumerate() {
        m.i_abc[i] = x.as_f64().unwrap_or(0.0);
    }
    m.theta_m_enc = f("theta_m_enc")?;
    m.u_ab_applied = a2("u_ab_applied")?;
    m.i_dq_true = a2("i_dq_true")?;
    m.omega_m_true = f("omega_m_true")?;
    m.theta_e_true = f("theta_e_true")?;
    m.u_dq_applied = a2("u_dq_applied")?;
    m.t_load = f("t_load")?;
    use drivelab_runtime::messages::Finite;
    if !m.is_finite() {
        return Err(anyhow!("rejoin file: non-finite values"));
    }
    Ok(m)
}
