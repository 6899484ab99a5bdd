//! The supervisor: injects faults, watches its children's liveness (waitpid, then
//! iceoryx2's dead nodes), restarts them per [`super::policy`] and tells the hub each
//! process's state; its typed event log; and the fault reports built from that log and the
//! trace.

use super::policy::{run_state, Decision, Injection, Life, Policy, RunState, State};
use super::recorder::Progress;
use super::spawn::{ChildProc, Spawn};
use crate::common::BusClock;
use crate::faults::{signal, FaultKind};
use anyhow::Result;
use drivelab_runtime::bus;
use drivelab_runtime::config::Scenario;
use drivelab_runtime::service::TopologyPlan;
use drivelab_runtime::stage::TopicId;
use drivelab_runtime::trace::TraceRow;
use serde::Serialize;
use std::collections::BTreeMap;
use std::process::ExitStatus;
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

/// What happened, with what it concerns.
#[derive(Debug, Clone, PartialEq)]
pub enum EventKind {
    /// A fault was injected (the process was signalled).
    Inject {
        /// Kill or stop.
        fault: FaultKind,
        /// How long a stop lasts, s.
        duration_s: f64,
        /// The monitor that asked for it; none for a planned fault.
        monitor_pid: Option<u32>,
    },
    /// A fault was not injected: the request was invalid or the clock does not allow it.
    InjectRefused {
        /// Why.
        reason: String,
    },
    /// A fault was not injected: its process was not running.
    InjectSkipped {
        /// What it was instead: "frozen by an earlier stop", "dead, to be restarted", ...
        why: &'static str,
    },
    /// Lockstep and in process: a kill or stop simulated by the stage hosts at its sample
    /// (no signal, no wall time: `t_wall_s` is 0).
    Simulated {
        /// The fault, as on the command line.
        spec: String,
    },
    /// A stopped process was resumed (SIGCONT).
    Resume,
    /// A process exited with a failure.
    Exited {
        /// Its exit status.
        status: ExitStatus,
        /// Not the death of an injected kill: a crash (`summary.json` → `crashes`).
        crash: bool,
    },
    /// The stale resources of dead iceoryx2 nodes were removed.
    Reaped {
        /// The nodes.
        nodes: Vec<String>,
    },
    /// A process was started again.
    Restarted {
        /// Its restarts so far, this one included.
        restart: u32,
        /// The new pid.
        pid: u32,
    },
    /// A restarted process is ready.
    Ready {
        /// Its pid.
        pid: u32,
    },
    /// The standby twin of a process that died took over: it is the process now.
    TakenOver {
        /// The twin's pid.
        pid: u32,
    },
    /// A (new) standby twin of a process was started.
    StandbyStarted {
        /// Its pid.
        pid: u32,
    },
    /// A standby twin is ready to take over.
    StandbyReady {
        /// Its pid.
        pid: u32,
    },
    /// A standby twin died (it is started again as a restart would be).
    StandbyExited {
        /// Its exit status.
        status: ExitStatus,
    },
    /// A stage of the process panicked (its host said so before it exited): a bug of the
    /// stage, which fails the run even when the restart made up for it.
    Panicked {
        /// The stage, call and sample it panicked in (or the process's stages), the panic's
        /// message and place.
        what: String,
    },
    /// A hog (a competing SCHED_FIFO busy loop, `crate::faults::hog`) was started.
    Hog {
        /// What it does.
        hog: crate::faults::hog::Hog,
        /// Its pid.
        pid: u32,
    },
}

impl EventKind {
    /// The name in `summary.json` and the monitor's log.
    pub fn name(&self) -> &'static str {
        match self {
            Self::Inject { .. } => "inject",
            Self::InjectRefused { .. } => "inject-refused",
            Self::InjectSkipped { .. } => "inject-skipped",
            Self::Simulated { .. } => "inject-simulated",
            Self::Resume => "resume",
            Self::Exited { .. } => "exited",
            Self::Panicked { .. } => "panicked",
            Self::Reaped { .. } => "reaped",
            Self::Restarted { .. } => "restarted",
            Self::Ready { .. } => "ready",
            Self::Hog { .. } => "hog",
            Self::TakenOver { .. } => "taken-over",
            Self::StandbyStarted { .. } => "standby-started",
            Self::StandbyReady { .. } => "standby-ready",
            Self::StandbyExited { .. } => "standby-exited",
        }
    }

    /// The details as text.
    pub fn detail(&self) -> String {
        match self {
            Self::Inject {
                fault,
                duration_s,
                monitor_pid,
            } => {
                let mut s = crate::faults::kind_name(*fault).to_string();
                if *fault == FaultKind::Stop {
                    s += &format!(" for {duration_s} s");
                }
                if let Some(pid) = monitor_pid {
                    s += &format!(" (requested by pid {pid})");
                }
                s
            }
            Self::InjectRefused { reason } => reason.clone(),
            Self::InjectSkipped { why } => format!("its process is not running: {why}"),
            Self::Simulated { spec } => format!("{spec}, simulated at its sample"),
            Self::Resume => "SIGCONT".into(),
            Self::Exited { status, crash } => {
                let how = outside_stop(*status)
                    .map(|sig| format!(" ({sig} from another process than the launcher)"))
                    .unwrap_or_default();
                format!("{status}{how}{}", if *crash { NOT_INJECTED } else { "" })
            }
            Self::Panicked { what } => what.clone(),
            Self::Reaped { nodes } => {
                format!("dead iceoryx2 nodes cleaned: {}", nodes.join(", "))
            }
            Self::Restarted { restart, pid } => format!("restart #{restart}, pid {pid}"),
            Self::Ready { pid } => format!("pid {pid}"),
            Self::Hog { hog, pid } => format!("{} (pid {pid})", hog.describe()),
            Self::TakenOver { pid } => format!("its standby twin (pid {pid}) is the process now"),
            Self::StandbyStarted { pid } | Self::StandbyReady { pid } => format!("pid {pid}"),
            Self::StandbyExited { status } => format!("{status}"),
        }
    }
}

/// One supervisor event.
#[derive(Debug, Clone, PartialEq)]
pub struct SupEvent {
    /// Wall time since the start signal, s.
    pub t_wall_s: f64,
    /// Newest sample the recorder had seen (k + 1), i.e. the drive's progress.
    pub k: u64,
    /// What happened.
    pub kind: EventKind,
    /// Stage (inject, resume) or process (exited, restarted, ready); "-" for the bus.
    pub service: String,
    /// The process concerned; "-" for the bus.
    pub process: String,
}

/// How the detail of an `exited` event that was a crash ends.
pub const NOT_INJECTED: &str = ", not injected";

/// The stop signal that ended a stage host from outside its drive, if that is how it ended
/// (its exit status is then 128 + the signal).
pub fn outside_stop(st: ExitStatus) -> Option<&'static str> {
    let code = st.code()?;
    drivelab_runtime::service::stop_signals()
        .find(|(sig, _)| i32::from(drivelab_runtime::service::outside_stop_status(*sig)) == code)
        .map(|(_, name)| name)
}

/// A stage host that a stop signal from another process ended: the same sender may be
/// stopping the whole drive (`timeout`, `kill -- -PGID` and service managers signal every
/// process at once), the launcher a moment later. True when the launcher's own stop comes
/// within 50 ms: the exit is the drive's stop, not a crash.
fn stopping_with_the_drive(st: ExitStatus) -> bool {
    if outside_stop(st).is_none() {
        return false;
    }
    let t = Instant::now();
    while t.elapsed() < Duration::from_millis(50) {
        if crate::common::stop_requested() {
            return true;
        }
        std::thread::sleep(Duration::from_millis(1));
    }
    crate::common::stop_requested()
}

/// Process exits in `events` that were not the death of an injected kill: crashes.
pub fn crashes(events: &[SupEvent]) -> usize {
    events
        .iter()
        .filter(|e| matches!(e.kind, EventKind::Exited { crash: true, .. }))
        .count()
}

/// A [`SupEvent`] as written to `summary.json` → `supervisor_events`.
#[derive(Debug, Serialize)]
struct EventRecord<'a> {
    t_wall_s: f64,
    k: u64,
    event: &'static str,
    service: &'a str,
    process: &'a str,
    detail: String,
}

impl SupEvent {
    /// The event's name (inject, inject-refused, inject-skipped, resume, exited, reaped,
    /// restarted, ready).
    pub fn name(&self) -> &'static str {
        self.kind.name()
    }

    /// Its details as text.
    pub fn detail(&self) -> String {
        self.kind.detail()
    }
}

impl Serialize for SupEvent {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        EventRecord {
            t_wall_s: self.t_wall_s,
            k: self.k,
            event: self.name(),
            service: &self.service,
            process: &self.process,
            detail: self.detail(),
        }
        .serialize(s)
    }
}

/// Notes a fault of the run's plan that was not made, with why (`Progress::not_made`).
fn not_made(progress: &Progress, why: String) {
    if let Ok(mut v) = progress.not_made.lock() {
        v.push(why);
    }
}

/// Lockstep and in process: an `inject-simulated` event for each kill and stop of the
/// scenario's schedule, at its sample (docs/architecture.md, "Fault model").
pub fn simulated_events(sc: &Scenario, topo: &TopologyPlan) -> Vec<SupEvent> {
    sc.inject
        .iter()
        .filter(|i| i.kind.downs_stage())
        .map(|i| SupEvent {
            t_wall_s: 0.0,
            k: (i.at_s * sc.rates.sample_hz).round() as u64,
            kind: EventKind::Simulated { spec: i.spec() },
            service: i.target.clone(),
            process: topo
                .process_of(&i.target)
                .map_or_else(|| "-".to_string(), |p| topo.processes[p].name.clone()),
        })
        .collect()
}

/// One child process under supervision.
pub(super) struct Supervised {
    /// The process.
    pub proc: ChildProc,
    /// Its life under the policy.
    life: Life,
    /// Its standby twin (`standby = true` in the topology, real time), ready or starting.
    pub standby: Option<ChildProc>,
    /// The twin has not said READY yet.
    standby_starting: bool,
    /// When to start a new twin (after a takeover, or after the twin died).
    standby_due: Option<Instant>,
}

impl Supervised {
    /// A child that has passed the start-up handshake, with its twin if it has one.
    pub fn new(proc: ChildProc, standby: Option<ChildProc>) -> Self {
        let life = Life::new(proc.source);
        Self {
            proc,
            life,
            standby,
            standby_starting: false,
            standby_due: None,
        }
    }

    /// Its standby twin is alive (and has not exited unnoticed).
    fn twin_alive(&mut self) -> bool {
        self.standby
            .as_mut()
            .is_some_and(|t| matches!(t.child.try_wait(), Ok(None)))
    }
}

/// The supervisor: injects the planned faults when the drive reaches their sample, notices
/// dead services (waitpid, then iceoryx2's node liveness, whose stale resources it removes),
/// restarts them per policy with `--rejoin`, and records every event. Returns a failure
/// message when the run cannot go on.
pub(super) fn supervise(
    hub: &mut crate::hub::Hub,
    bar: &indicatif::ProgressBar,
    children: &mut [Supervised],
    plan: &[crate::faults::Fault],
    hogs: &[crate::faults::hog::Hog],
    // `hogs`, armed; killed and reaped when this function returns, however it returns.
    mut running: crate::faults::hog::Running,
    events: &mut Vec<SupEvent>,
    progress: &Progress,
    sc: &Scenario,
    sp: &Spawn,
    started: Instant,
    limit: Duration,
    link: &mut dyn FnMut() -> Option<String>,
) -> Result<Option<String>> {
    let (bus_id, clock, out) = (sp.bus_id, sp.clock, sp.out);
    let policy = Policy::new(sp.o.restart, clock == BusClock::Lockstep);
    let fs = sc.rates.sample_hz;
    let mut next_fault = 0;
    let mut next_hog = 0;
    let log = |events: &mut Vec<SupEvent>, kind: EventKind, service: &str, process: &str| {
        events.push(SupEvent {
            t_wall_s: started.elapsed().as_secs_f64(),
            k: progress.next_k.load(Ordering::Relaxed),
            kind,
            service: service.into(),
            process: process.into(),
        });
    };
    // The hosts' data segments, held so that a dead process's are freed here, on the
    // launcher's CPUs, and not in the loop of the host that drops them last.
    let mut segments = bus::SegmentKeeper::new(bus_id);
    segments.hold_new();
    'run: loop {
        if crate::common::stop_requested() {
            // The hosts are asked to stop before the launcher takes anything of its own off
            // the bus: what they do from then on is the stop's (the system-call audit stops
            // counting), not a peer vanishing under a running loop.
            for c in children.iter_mut() {
                super::spawn::ask_to_stop(&mut c.proc);
                if let Some(t) = c.standby.as_mut() {
                    super::spawn::ask_to_stop(t);
                }
            }
            return Ok(Some(super::interrupted()));
        }
        // A recorder that failed, or a split drive whose other machine is gone (`Bridge::lost`).
        if let Some(why) = link() {
            return Ok(Some(why));
        }
        if started.elapsed() > limit {
            return Ok(Some(format!("the drive did not finish within {limit:?}")));
        }
        let now = Instant::now();
        let k_now = progress.next_k.load(Ordering::Relaxed);
        bar.set_position(k_now);
        // Faults due at this point of the run (in samples, so lockstep and realtime agree),
        // then those a monitor asked for, with the monitor's pid.
        let mut due: Vec<(crate::faults::Fault, Option<u32>)> = Vec::new();
        while next_fault < plan.len() && k_now as f64 >= plan[next_fault].at_s * fs {
            due.push((plan[next_fault].clone(), None));
            next_fault += 1;
        }
        for r in hub.poll(events, k_now, &progress.tail)? {
            match crate::hub::to_fault(&r, k_now as f64 / fs, hub.stages()) {
                Ok(f) => due.push((f, Some(r.pid))),
                Err(e) => log(
                    events,
                    EventKind::InjectRefused {
                        reason: format!("{e:#}"),
                    },
                    "-",
                    "-",
                ),
            }
        }
        while next_hog < hogs.len() && k_now as f64 >= hogs[next_hog].at_s * fs {
            let h = &hogs[next_hog];
            let k_start = plant_sample_now(progress, sc.rates.ts_ns());
            let kind = match running.start(next_hog, h) {
                Ok(pid) => EventKind::Hog {
                    hog: h.clone(),
                    pid,
                },
                Err(e) => {
                    let reason = format!("{}: {e:#}", h.describe());
                    not_made(progress, reason.clone());
                    EventKind::InjectRefused { reason }
                }
            };
            next_hog += 1;
            log(events, kind, &format!("cpu{}", h.cpu), "hog");
            if let (Some(e), Some(k)) = (events.last_mut(), k_start) {
                e.k = e.k.max(k);
            }
        }
        for (pid, st) in running.poll(now) {
            let reason = format!("the hog (pid {pid}) failed: {st}");
            log(events, EventKind::InjectRefused { reason }, "-", "hog");
        }
        for (f, monitor_pid) in due {
            // A stage's fault hits the whole process that hosts it.
            let Some(c) = children
                .iter_mut()
                .find(|c| c.proc.stages.contains(&f.service))
            else {
                continue;
            };
            // The plant's sample when the signal goes out: the recorder's progress lags it.
            let k_signal = plant_sample_now(progress, sc.rates.ts_ns());
            let stop = match f.kind {
                FaultKind::Stop => Duration::from_secs_f64(f.duration_s),
                FaultKind::Kill => Duration::ZERO,
            };
            let kind = match c
                .life
                .inject(f.kind, stop, now, clock == BusClock::Realtime)
            {
                // Only a monitor's request can get here: a plan is refused before the start.
                Injection::Refused => EventKind::InjectRefused {
                    reason: "faults need --clock realtime".into(),
                },
                Injection::Skipped(why) => EventKind::InjectSkipped { why },
                Injection::Signal(sig) => {
                    signal(c.proc.host_pid(), sig)?;
                    EventKind::Inject {
                        fault: f.kind,
                        duration_s: f.duration_s,
                        monitor_pid,
                    }
                }
            };
            let injected = matches!(kind, EventKind::Inject { .. });
            if !injected && monitor_pid.is_none() {
                not_made(
                    progress,
                    format!(
                        "{}: not injected: {} (process {})",
                        f.spec(),
                        kind.detail(),
                        c.proc.name
                    ),
                );
            }
            log(events, kind, &f.service, &c.proc.name);
            if let (true, Some(e), Some(k)) = (injected, events.last_mut(), k_signal) {
                e.k = e.k.max(k);
            }
        }
        for c in children.iter_mut() {
            if c.life.resume_due(now) {
                let _ = signal(c.proc.host_pid(), libc::SIGCONT);
                log(events, EventKind::Resume, &c.proc.name, &c.proc.name);
            }
        }
        // Liveness: our own children first (waitpid), then iceoryx2's view of the bus.
        let mut any_dead = false;
        // Twins: ready, or dead (then started again as a restart would be).
        for c in children.iter_mut() {
            let n = c.proc.name.clone();
            let Some(t) = c.standby.as_mut() else {
                continue;
            };
            if c.standby_starting && t.poll_ready() {
                c.standby_starting = false;
                segments.hold_new();
                log(events, EventKind::StandbyReady { pid: t.pid() }, &n, &n);
            }
            // A twin that ended with the drive stays listed (the summary names it).
            if let Some(st) = t.child.try_wait()?.filter(|st| !st.success()) {
                if stopping_with_the_drive(st) {
                    return Ok(Some(super::interrupted()));
                }
                // A twin's panic is its stage's bug as much as the process's own would be.
                let panic = t.panic_after_exit(st);
                c.standby = None;
                any_dead = true;
                log(events, EventKind::StandbyExited { status: st }, &n, &n);
                if let Some(what) = panic {
                    let what = format!("(its standby twin) {what}");
                    log(events, EventKind::Panicked { what }, &n, &n);
                }
                c.standby_due = Some(now + Duration::from_millis(100));
            }
        }
        for c in children.iter_mut() {
            if !c.life.state.alive() {
                continue;
            }
            if c.life.state.awaiting_ready() && c.proc.poll_ready() {
                c.life.ready();
                segments.hold_new();
                let kind = EventKind::Ready {
                    pid: c.proc.host_pid(),
                };
                log(events, kind, &c.proc.name, &c.proc.name);
            }
            let Some(st) = c.proc.child.try_wait()? else {
                continue;
            };
            if !st.success() && stopping_with_the_drive(st) {
                return Ok(Some(super::interrupted()));
            }
            any_dead |= !st.success();
            let n = c.proc.name.clone();
            let panic = c.proc.panic_after_exit(st);
            if !st.success() {
                let crash = !c.life.kill_pending();
                log(events, EventKind::Exited { status: st, crash }, &n, &n);
            }
            if let Some(what) = panic.clone() {
                log(events, EventKind::Panicked { what }, &n, &n);
            }
            // A ready twin has taken over already (it watches the dead one's lease): it is
            // the process now, and a new twin is started when the policy would restart. A
            // twin still starting is stopped: the process restarts as it would without one.
            let promote = !st.success() && !c.standby_starting && c.twin_alive();
            if !st.success() && !promote {
                if let Some(mut t) = c.standby.take() {
                    let _ = t.child.kill();
                    let _ = t.child.wait();
                    c.standby_starting = false;
                    c.standby_due = Some(now + Duration::from_millis(200));
                }
            }
            match c.life.exited(st.success(), &policy, now) {
                // A panic is named as such, in the words of a real-time run's error.
                Some(Decision::FailRun) => {
                    return Ok(Some(match panic {
                        Some(p) => format!("process {n} panicked: {p}"),
                        None => format!("process {n} failed ({st})"),
                    }));
                }
                Some(Decision::StopDrive) => break 'run,
                Some(d) if promote => {
                    let mut twin = c.standby.take().expect("alive above");
                    twin.standby = false;
                    let pid = twin.pid();
                    c.proc = twin;
                    c.life.ready();
                    if let Decision::RestartAt(at) = d {
                        c.standby_due = Some(at);
                    }
                    log(events, EventKind::TakenOver { pid }, &n, &n);
                }
                _ => {}
            }
        }
        if any_dead {
            // Before the dead node's files are removed: hold what a host made since.
            segments.hold_new();
            let nodes = bus::reap_dead_nodes(bus_id)?;
            log(events, EventKind::Reaped { nodes }, "-", "-");
        }
        let starting = children
            .iter()
            .any(|c| c.life.state.coming_up() || c.standby_starting);
        segments.release_removed(now, starting);
        for c in children.iter_mut() {
            let due = c.standby_due.is_some_and(|at| now >= at);
            if due && c.standby.is_none() && c.life.state.alive() {
                // After the reaping above: the dead instance's ports are gone, so the new
                // twin gets their publisher slots.
                c.standby_due = None;
                let t = c.proc.respawn_standby(sp)?;
                let n = c.proc.name.clone();
                log(events, EventKind::StandbyStarted { pid: t.pid() }, &n, &n);
                c.standby = Some(t);
                c.standby_starting = true;
            }
            if !c.life.restart_due(now) {
                continue;
            }
            let name = c.proc.name.clone();
            let rejoin_file = out.join(format!("rejoin-{name}.json"));
            // What the restarted process takes over from, as the recorder saw it: the
            // plant's true state, and the own last output of a stage that reads it back
            // (docs/architecture.md, "Bumpless rejoin").
            let mut state = serde_json::Map::new();
            if c.proc.source {
                let last = progress.last.lock().ok().and_then(|l| *l);
                let Some(last) = last else {
                    return Ok(Some(
                        "plant died before its first sample; cannot resume".into(),
                    ));
                };
                if !drivelab_runtime::messages::Finite::is_finite(&last) {
                    return Ok(Some(format!(
                        "plant cannot resume: its last true state (sample {}) is not a finite number",
                        last.hdr.k
                    )));
                }
                // The plant resumes from this state as the file gives it back: keep that.
                let text = serde_json::to_vec(&crate::common::truth_to_json(&last))?;
                let file: serde_json::Value = serde_json::from_slice(&text)?;
                let given = drivelab_runtime::service::truth_from_json(&file)?;
                if let Ok(mut r) = progress.rejoins.lock() {
                    r.push(given);
                }
                if let serde_json::Value::Object(m) = file {
                    state = m;
                }
            }
            let own = sp.plan.own_rejoin_topics(&c.proc.stages);
            if own.contains(&TopicId::Wref) {
                // None when the loop died before the recorder saw an output of it: it then
                // counts from where the drive is, as at the start.
                if let Some(w) = progress.last_wref.lock().ok().and_then(|l| *l) {
                    state.insert(
                        TopicId::Wref.name().into(),
                        drivelab_runtime::service::speed_ref_to_json(&w),
                    );
                }
            }
            let file = if state.is_empty() {
                None
            } else {
                let text = serde_json::to_vec(&serde_json::Value::Object(state))?;
                drivelab_runtime::files::write(&rejoin_file, &text)?;
                Some(rejoin_file.as_path())
            };
            c.proc = c.proc.respawn(sp, file)?;
            let kind = EventKind::Restarted {
                restart: c.life.restarted(),
                pid: c.proc.host_pid(),
            };
            log(events, kind, &name, &name);
        }
        for c in children.iter() {
            let state = c.life.state.proc_state();
            for st in &c.proc.stages {
                hub.set_process(st, state, c.proc.host_pid(), c.life.history.restarts);
            }
        }
        match run_state(children.iter().map(|c| &c.life)) {
            RunState::Going => {}
            RunState::Over => break 'run,
            RunState::PlantFinished => {
                // A process still stopped by a fault could not end with the drive.
                for c in children.iter_mut() {
                    if c.life.resume_at_end() {
                        let _ = signal(c.proc.host_pid(), libc::SIGCONT);
                        log(events, EventKind::Resume, &c.proc.name, &c.proc.name);
                    }
                }
                // Anyone not done within 2 s is stopped by the caller.
                let t = Instant::now();
                while t.elapsed() < Duration::from_secs(2) {
                    if children.iter_mut().all(|c| {
                        c.life.state == State::Finished
                            || matches!(c.proc.child.try_wait(), Ok(Some(_)))
                    }) {
                        break;
                    }
                    std::thread::sleep(Duration::from_millis(5));
                }
                break 'run;
            }
        }
        std::thread::sleep(Duration::from_millis(1));
    }
    // The drive ended before some planned faults were due (it stopped early, or the
    // recorder, whose progress times them, was behind): each is named, not dropped.
    let k_end = progress.next_k.load(Ordering::Relaxed);
    let late = plan[next_fault..]
        .iter()
        .map(|f| (f.spec(), f.at_s))
        .chain(hogs[next_hog..].iter().map(|h| (h.spec(), h.at_s)));
    for (spec, at_s) in late {
        let reason = super::ended_before(&spec, k_end, (at_s * fs).round() as u64);
        not_made(progress, reason.clone());
        log(events, EventKind::InjectRefused { reason }, "-", "-");
    }
    Ok(None)
}

/// The sample the real-time plant is at now: the first one it has not published yet, from
/// its truth messages counted since the recorder's newest read. Without that count (iceoryx2
/// wake-ups) the schedule's estimate: the newest sample the recorder has read plus the sample
/// periods since its instant, which runs ahead of a plant that is late. None in lockstep,
/// which has no schedule.
fn plant_sample_now(progress: &Progress, ts_ns: u64) -> Option<u64> {
    let last = progress.last.lock().ok().and_then(|l| *l)?;
    let t = last.hdr.t_sample_ns;
    if t == 0 || ts_ns == 0 {
        return None;
    }
    let mark = progress.truth_mark.lock().ok().and_then(|m| *m);
    Some(match (mark, progress.truth_count.get()) {
        (Some(mark), Some(count)) => mark.next_sample(count.get()),
        _ => last.hdr.k + drivelab_runtime::rt::now_ns().saturating_sub(t) / ts_ns,
    })
}

/// One entry of `summary.json` → `faults`. Times are in ms from the injection.
#[derive(Debug, Clone, Default, Serialize)]
pub struct FaultReport {
    /// kill or stop (with its duration).
    pub fault: String,
    /// Target stage.
    pub service: String,
    /// The process that was signalled (it hosts the stage, perhaps with others).
    pub process: String,
    /// Injection: sample index (the first sample the plant had not published when the signal
    /// went out, so also for a plant that ran behind its schedule; for a kill of the plant's
    /// own process, the first sample it did not produce).
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
    /// The plant's downtime: samples rebuilt (plant_flags 64) in the fault's window, and the
    /// peak |i_dq| (A) and |ω_m| (mechanical rad/s) over them. None when no sample was
    /// rebuilt (not a plant fault, or the plant did not come back).
    pub plant_down: Option<PlantDown>,
    /// What the fault did to the commands, sample by sample, over its span.
    #[serde(flatten)]
    pub samples: SampleCounts,
    /// A bus fault's own figures (delay, drop, corrupt), beside the ones above.
    #[serde(flatten)]
    pub bus: Option<crate::bus_faults::BusFigures>,
    /// Hog and sensor faults: the trace before the fault against during it.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub window: Option<crate::faults::window::FaultWindow>,
    /// Why a figure above is null, where the figure's name alone does not say (the run
    /// ended before a recovery could be told): figure → reason. Absent when empty.
    #[serde(skip_serializing_if = "BTreeMap::is_empty")]
    pub why_null: BTreeMap<&'static str, String>,
}

/// The motor while the plant's process was down (see [`FaultReport::plant_down`]).
#[derive(Debug, Clone, Copy, Default, Serialize)]
pub struct PlantDown {
    /// Samples rebuilt.
    pub samples: u64,
    /// Peak current magnitude |i_dq|, A.
    pub peak_current_a: f64,
    /// Peak speed magnitude, mechanical rad/s.
    pub peak_speed_rad_s: f64,
}

impl PlantDown {
    /// The rows of `rows` flagged `plant_down`, or None when there are none.
    pub fn of<'a>(rows: impl Iterator<Item = &'a TraceRow>) -> Option<Self> {
        use drivelab_runtime::messages::FLAG_PLANT_DOWN;
        let down: Vec<&TraceRow> = rows
            .filter(|r| r.plant_flags & FLAG_PLANT_DOWN != 0)
            .collect();
        (!down.is_empty()).then(|| PlantDown {
            samples: down.len() as u64,
            peak_current_a: down.iter().map(|r| r.i_d.hypot(r.i_q)).fold(0.0, f64::max),
            peak_speed_rad_s: down.iter().map(|r| r.omega_m.abs()).fold(0.0, f64::max),
        })
    }
}

/// What a fault did to the commands, counted over its span: from its first sample to the
/// speed's recovery (or to fresh outputs again where the speed did not recover, or 0.2 s on
/// where neither came; a trip: to the end of the run), the same for every kind of fault.
#[derive(Debug, Clone, Copy, Default, Serialize, PartialEq)]
pub struct SampleCounts {
    /// Samples at which the plant had no fresh command: it held one or applied its safe state
    /// (`plant_flags` 2, `miss` = 1).
    pub stale_command_samples: u64,
    /// Samples in the inverter's safe state (`plant_flags` 4).
    pub safe_state_samples: u64,
    /// Samples with no usable command recorded (`ctrl_flags` 32).
    pub missing_command_samples: u64,
    /// Samples whose command was made from a stale input or a fallback (`ctrl_flags` 8: a
    /// held estimate or reference).
    pub stale_input_samples: u64,
}

impl SampleCounts {
    /// The counts of the rows of a fault's span.
    pub fn of<'a>(span: impl IntoIterator<Item = &'a TraceRow>) -> Self {
        use drivelab_runtime::messages::{
            FLAG_MISSING, FLAG_SAFE_STATE, FLAG_STALE_CMD, FLAG_STALE_INPUT,
        };
        let mut c = Self::default();
        for r in span {
            let plant = |f: u32| u64::from(r.plant_flags & f != 0);
            let ctrl = |f: u32| u64::from(r.ctrl_flags & f != 0);
            c.stale_command_samples += plant(FLAG_STALE_CMD);
            c.safe_state_samples += plant(FLAG_SAFE_STATE);
            c.missing_command_samples += ctrl(FLAG_MISSING);
            c.stale_input_samples += ctrl(FLAG_STALE_INPUT);
        }
        c
    }
}

/// The speed's recovery band: within ±2 % of its reference, for 10 ms (samples).
fn speed_band(sc: &Scenario) -> (impl Fn(&TraceRow) -> bool + '_, usize) {
    let hold = (0.01 * sc.rates.sample_hz).ceil() as usize;
    let within = |r: &TraceRow| {
        let w = drivelab_runtime::config::profile_at(&sc.reference.speed_rad_s, r.t);
        (r.omega_m - w).abs() <= 0.02 * w.abs().max(1e-9)
    };
    (within, hold)
}

/// The first sample of `tail` (rows in order) from which the speed stays within ±2 % of its
/// reference for 10 ms.
pub fn speed_recovered(sc: &Scenario, tail: &[&TraceRow]) -> Option<u64> {
    let (within, hold) = speed_band(sc);
    (0..tail.len())
        .find(|&i| tail[i..].iter().take(hold).all(|r| within(r)) && tail.len() - i >= hold)
        .map(|i| tail[i].k)
}

/// `FaultReport::why_null` of a report whose speed recovery over `tail` is `rec`: when the
/// run's end decided it (the speed back in its band for the run's last samples, fewer than
/// the 10 ms it must stay there), it says so; a speed that never came back needs no note.
pub fn recovery_notes(
    sc: &Scenario,
    tail: &[&TraceRow],
    rec: Option<u64>,
) -> BTreeMap<&'static str, String> {
    let (within, hold) = speed_band(sc);
    let back = tail.iter().rev().take_while(|r| within(r)).count();
    let mut notes = BTreeMap::new();
    if rec.is_none() && back > 0 && back < hold {
        notes.insert(
            "speed_recovered_ms",
            format!(
                "the run ended {} ms after the speed came back within ±2 % of its reference, before the 10 ms it must stay there",
                back as f64 * 1e3 / sc.rates.sample_hz
            ),
        );
    }
    notes
}

/// Builds the fault reports from the supervisor's events and the trace, and the windows to
/// shade on the plots.
pub fn fault_reports(
    sc: &Scenario,
    rows: &[TraceRow],
    events: &[SupEvent],
) -> (Vec<FaultReport>, Vec<(f64, f64, String)>) {
    use drivelab_runtime::messages::{
        FLAG_PLANT_DOWN, FLAG_SAFE_STATE, FLAG_STALE_CMD, FLAG_STALE_INPUT,
    };
    let fs = sc.rates.sample_hz;
    let ms = |dk: u64| dk as f64 * 1e3 / fs;
    let by_k: BTreeMap<u64, &TraceRow> = rows.iter().map(|r| (r.k, r)).collect();
    let mut out = Vec::new();
    let mut windows = Vec::new();
    let injects: Vec<&SupEvent> = events
        .iter()
        .filter(|e| matches!(e.kind, EventKind::Inject { .. } | EventKind::Hog { .. }))
        .collect();
    // Where each fault begins: the plant's next sample when the signal went out, counted from
    // its publishes (see `plant_sample_now`). A killed plant's rebuilt downtime says exactly
    // where it stopped, and the fault begins with it:
    // - Where only the schedule's estimate was there (iceoryx2 wake-ups), a plant killed while
    //   it ran late had produced fewer samples: its downtime begins before the estimate (but
    //   after the previous fault's sample).
    // - The count is exact to one message: a publish is a send and then a bump of the count,
    //   and the recorder's mark or the signal can fall between the two. A plant whose
    //   downtime begins one sample after the count's estimate published that sample.
    // - A plant that was catching up when its own process was killed (back to back, a few
    //   µs a sample) went on publishing while the signal was under way: the kill took hold
    //   where its downtime begins, the first rebuilt sample before the next fault.
    let down = |k: u64| {
        by_k.get(&k)
            .is_some_and(|r| r.plant_flags & FLAG_PLANT_DOWN != 0)
    };
    let plant_process = sc
        .topology()
        .into_iter()
        .find(|p| p.stages.iter().any(|s| s == "plant"))
        .map(|p| p.name);
    let kills_the_plant = |e: &SupEvent| {
        matches!(
            e.kind,
            EventKind::Inject {
                fault: FaultKind::Kill,
                ..
            }
        ) && plant_process.as_deref() == Some(e.process.as_str())
    };
    let mut starts: Vec<u64> = Vec::with_capacity(injects.len());
    for (n, inj) in injects.iter().enumerate() {
        let k_prev = n.checked_sub(1).map_or(0, |p| injects[p].k + 1);
        let k_next = injects.get(n + 1).map_or(u64::MAX, |e| e.k);
        let mut k0 = inj.k;
        while k0 > k_prev && down(k0 - 1) {
            k0 -= 1;
        }
        if !down(k0) && down(k0 + 1) {
            k0 += 1;
        } else if !down(k0) && kills_the_plant(inj) {
            if let Some((&k, _)) = by_k
                .range(k0..k_next)
                .find(|(_, r)| r.plant_flags & FLAG_PLANT_DOWN != 0)
            {
                k0 = k;
            }
        }
        starts.push(k0);
    }
    for (n, inj) in injects.iter().enumerate() {
        let k0 = starts[n];
        let k_end_window = starts.get(n + 1).copied().unwrap_or(u64::MAX);
        let after = || by_k.range(k0..k_end_window).map(|(_, r)| *r);
        // Data-path detection: the first stale flag, or the first sample the plant did not produce.
        let mut det = None;
        for (expect, r) in (k0..).zip(after()) {
            if r.k != expect {
                det = Some((expect, "recorder (plant produced no sample)".to_string()));
                break;
            }
            // A rebuilt sample of the plant's downtime: the inverter's own watchdog saw the
            // commands stop.
            if r.plant_flags & FLAG_PLANT_DOWN != 0 {
                det = Some((r.k, "inverter (plant process down)".into()));
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
        let sup = events
            .iter()
            .find(|e| {
                matches!(e.kind, EventKind::Exited { .. })
                    && e.process == inj.process
                    && e.t_wall_s >= inj.t_wall_s
            })
            .map(|e| (e.t_wall_s - inj.t_wall_s) * 1e3);
        // Fresh again: the first sample after the detection with no stale flag at all.
        let k_det = det.as_ref().map(|d| d.0).unwrap_or(k0);
        let fresh = after()
            .filter(|r| r.k > k_det)
            .find(|r| r.plant_flags & (FLAG_STALE_CMD | FLAG_SAFE_STATE) == 0 && r.ctrl_flags == 0)
            .map(|r| r.k);
        let tail: Vec<&TraceRow> = after()
            .filter(|r| fresh.is_some_and(|f| r.k >= f))
            .collect();
        let rec = speed_recovered(sc, &tail);
        let k_rec = rec
            .or(fresh)
            .unwrap_or(k_end_window.min(k0 + (0.2 * fs) as u64));
        // The safe state this fault caused: reached before the drive had recovered from it
        // (a later one, after a burst of deadline misses say, is not this fault's).
        let safe = after()
            .take_while(|r| r.k <= k_rec)
            .find(|r| r.plant_flags & FLAG_SAFE_STATE != 0)
            .map(|r| ms(r.k - k0));
        let peak = after()
            .filter(|r| r.k <= k_rec)
            .map(|r| (r.i_d * r.i_d + r.i_q * r.i_q).sqrt())
            .fold(0.0, f64::max);
        windows.push((
            k0 as f64 / fs,
            k_rec as f64 / fs,
            format!("{} {}", inj.detail(), inj.service),
        ));
        let plant_down = PlantDown::of(after().filter(|r| r.k <= k_rec));
        let samples = SampleCounts::of(after().take_while(|r| r.k <= k_rec));
        let window = match &inj.kind {
            EventKind::Hog { hog, .. } => Some(crate::faults::hog::window(hog, rows, k0, fs)),
            _ => None,
        };
        let why_null = {
            let mut notes = recovery_notes(sc, &tail, rec);
            // A fault's figures end where the next one begins: a recovery that had not
            // come by then was cut, not missed.
            if let Some(next) = injects.get(n + 1) {
                let cut = format!(
                    "the next fault ({} {}) came {} ms after this one, before",
                    next.detail(),
                    next.service,
                    ms(k_end_window.saturating_sub(k0))
                );
                if fresh.is_none() {
                    notes.insert("republished_ms", format!("{cut} fresh outputs"));
                }
                if rec.is_none() {
                    notes.insert(
                        "speed_recovered_ms",
                        format!("{cut} the speed was back within ±2 % of its reference for 10 ms"),
                    );
                }
            }
            notes
        };
        out.push(FaultReport {
            fault: inj.detail(),
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
            plant_down,
            samples,
            bus: None,
            window,
            why_null,
        });
    }
    (out, windows)
}

#[cfg(test)]
mod tests {
    use super::*;
    use drivelab_runtime::config::Step;
    use drivelab_runtime::messages::{FLAG_SAFE_STATE, FLAG_STALE_CMD, FLAG_STALE_INPUT};
    use std::os::unix::process::ExitStatusExt;

    /// A scenario at 1 kHz (one sample per ms) with a constant speed reference of 100 rad/s.
    fn scenario() -> Scenario {
        let (mut sc, _) = Scenario::load("kyslan-pi").unwrap();
        sc.rates.sample_hz = 1000.0;
        sc.reference.speed_rad_s = vec![Step {
            t_s: 0.0,
            value: 100.0,
        }];
        sc
    }

    /// Rows `ks` on the reference with 1 A of q current.
    fn rows(ks: impl Iterator<Item = u64>) -> Vec<TraceRow> {
        ks.map(|k| TraceRow {
            k,
            t: k as f64 * 1e-3,
            omega_ref: 100.0,
            omega_m: 100.0,
            i_q: 1.0,
            ..Default::default()
        })
        .collect()
    }

    fn at(rows: &mut [TraceRow], ks: std::ops::RangeInclusive<u64>, f: impl Fn(&mut TraceRow)) {
        rows.iter_mut().filter(|r| ks.contains(&r.k)).for_each(f);
    }

    fn ev(t_wall_s: f64, k: u64, kind: EventKind, service: &str, process: &str) -> SupEvent {
        SupEvent {
            t_wall_s,
            k,
            kind,
            service: service.into(),
            process: process.into(),
        }
    }

    fn kill() -> EventKind {
        EventKind::Inject {
            fault: FaultKind::Kill,
            duration_s: 0.0,
            monitor_pid: None,
        }
    }

    #[test]
    fn a_kill_detected_by_the_plant_goes_safe_republishes_and_recovers() {
        let sc = scenario();
        let mut tr = rows(0..60);
        at(&mut tr, 12..=13, |r| r.plant_flags = FLAG_STALE_CMD);
        at(&mut tr, 14..=16, |r| {
            r.plant_flags = FLAG_STALE_CMD | FLAG_SAFE_STATE
        });
        at(&mut tr, 15..=15, |r| r.i_d = 3.0);
        at(&mut tr, 15..=15, |r| r.i_q = 4.0);
        // Fresh from 17, but 10 % slow up to 24.
        at(&mut tr, 17..=24, |r| r.omega_m = 90.0);
        let cl = "current-loop";
        let events = [
            ev(1.0, 10, kill(), cl, cl),
            ev(
                1.0,
                10,
                EventKind::InjectSkipped { why: "finished" },
                "plant",
                "plant",
            ),
            ev(
                1.003,
                13,
                EventKind::Exited {
                    status: ExitStatus::from_raw(9),
                    crash: false,
                },
                cl,
                cl,
            ),
            ev(
                1.02,
                30,
                EventKind::Restarted { restart: 1, pid: 7 },
                cl,
                cl,
            ),
            ev(1.05, 33, EventKind::Ready { pid: 7 }, cl, cl),
        ];
        let (reports, windows) = fault_reports(&sc, &tr, &events);
        assert_eq!(reports.len(), 1);
        let f = &reports[0];
        assert_eq!(
            (f.fault.as_str(), f.service.as_str(), f.process.as_str()),
            ("kill", cl, cl)
        );
        assert_eq!((f.injected_k, f.injected_t_s), (10, 0.01));
        assert_eq!(f.detected_data_path_ms, Some(2.0));
        assert_eq!(f.detected_by.as_deref(), Some("plant"));
        assert!(
            (f.detected_supervisor_ms.unwrap() - 3.0).abs() < 1e-9,
            "{f:?}"
        );
        assert_eq!(f.safe_state_ms, Some(4.0));
        assert_eq!(f.republished_ms, Some(7.0));
        // Within ±2 % from 25 and for the 10 samples after.
        assert_eq!(f.speed_recovered_ms, Some(15.0));
        assert_eq!(f.peak_current_a, 5.0);
        assert_eq!(windows, [(0.01, 0.025, "kill current-loop".to_string())]);
    }

    #[test]
    fn a_recovery_the_next_fault_cut_says_so() {
        let sc = scenario();
        // The current loop is killed at 10; the speed is 10 % low from 12 on, and the
        // observer is killed at 20, before it came back.
        let mut tr = rows(0..80);
        at(&mut tr, 12..=79, |r| r.omega_m = 90.0);
        let (cl, ob) = ("current-loop", "observer");
        let (reports, _) = fault_reports(
            &sc,
            &tr,
            &[ev(1.0, 10, kill(), cl, cl), ev(1.01, 20, kill(), ob, ob)],
        );
        assert_eq!(reports.len(), 2);
        assert_eq!(reports[0].speed_recovered_ms, None);
        assert_eq!(
            reports[0].why_null["speed_recovered_ms"],
            "the next fault (kill observer) came 10 ms after this one, before the speed was back within ±2 % of its reference for 10 ms"
        );
        // The last fault has no next one: its null is the plain "never recovered".
        assert_eq!(reports[1].speed_recovered_ms, None);
        assert!(
            !reports[1].why_null.contains_key("speed_recovered_ms"),
            "{:?}",
            reports[1].why_null
        );
    }

    #[test]
    fn missing_samples_and_a_stale_input_are_detections_each_in_its_own_window() {
        let sc = scenario();
        // The plant is killed at 10 and produces nothing up to 14.
        let mut tr = rows((0..10).chain(15..80));
        // A monitor stops the observer at 40: the current loop falls back from 42 to 44.
        at(&mut tr, 42..=44, |r| r.ctrl_flags = FLAG_STALE_INPUT);
        let stop = EventKind::Inject {
            fault: FaultKind::Stop,
            duration_s: 0.02,
            monitor_pid: Some(4242),
        };
        let exited = EventKind::Exited {
            status: ExitStatus::from_raw(9),
            crash: false,
        };
        let events = [
            ev(1.0, 10, kill(), "plant", "plant"),
            ev(1.001, 10, exited.clone(), "plant", "plant"),
            ev(2.0, 40, stop, "observer", "observer"),
            // An exit of another process says nothing of this fault.
            ev(2.001, 41, exited, "plant", "plant"),
            ev(2.02, 60, EventKind::Resume, "observer", "observer"),
        ];
        let (reports, windows) = fault_reports(&sc, &tr, &events);
        assert_eq!(reports.len(), 2);
        let (p, o) = (&reports[0], &reports[1]);
        assert_eq!(p.detected_data_path_ms, Some(0.0));
        assert_eq!(
            p.detected_by.as_deref(),
            Some("recorder (plant produced no sample)")
        );
        assert_eq!(p.safe_state_ms, None);
        assert_eq!(p.republished_ms, Some(5.0));
        assert_eq!(p.speed_recovered_ms, Some(5.0));
        assert_eq!(o.fault, "stop for 0.02 s (requested by pid 4242)");
        assert_eq!((o.service.as_str(), o.injected_k), ("observer", 40));
        assert_eq!(o.detected_data_path_ms, Some(2.0));
        assert_eq!(o.detected_by.as_deref(), Some("current-loop"));
        assert_eq!(o.detected_supervisor_ms, None);
        assert_eq!(o.republished_ms, Some(5.0));
        assert_eq!(windows[0], (0.01, 0.015, "kill plant".to_string()));
        assert_eq!(
            windows[1].2,
            "stop for 0.02 s (requested by pid 4242) observer"
        );
    }

    #[test]
    fn a_safe_state_after_the_recovery_is_not_the_faults() {
        let sc = scenario();
        let mut tr = rows(0..300);
        // The speed loop is killed at 10; the current loop holds its reference (11-12),
        // fresh again from 13. Much later the plant misses deadlines and goes safe.
        at(&mut tr, 11..=12, |r| r.ctrl_flags = FLAG_STALE_INPUT);
        at(&mut tr, 150..=152, |r| {
            r.plant_flags = FLAG_STALE_CMD | FLAG_SAFE_STATE
        });
        let sl = "speed-loop";
        let (reports, _) = fault_reports(&sc, &tr, &[ev(1.0, 10, kill(), sl, sl)]);
        let f = &reports[0];
        assert_eq!(f.detected_data_path_ms, Some(1.0));
        assert_eq!(f.republished_ms, Some(3.0));
        assert_eq!(f.safe_state_ms, None, "{f:?}");
    }

    #[test]
    fn a_plant_killed_while_late_begins_with_its_first_rebuilt_sample() {
        use drivelab_runtime::messages::FLAG_PLANT_DOWN;
        let sc = scenario();
        let mut tr = rows(0..100);
        // The plant died after sample 9 (it was behind its schedule); the signal was
        // estimated at sample 12. Down from 10 to 19, safe from 13; back from 20.
        at(&mut tr, 10..=19, |r| {
            r.plant_flags = FLAG_PLANT_DOWN | FLAG_STALE_CMD;
            r.i_q = 0.5;
        });
        at(&mut tr, 13..=19, |r| r.plant_flags |= FLAG_SAFE_STATE);
        let (reports, _) = fault_reports(&sc, &tr, &[ev(1.0, 12, kill(), "plant", "plant")]);
        let f = &reports[0];
        assert_eq!(f.injected_k, 10);
        let pd = f.plant_down.as_ref().expect("plant down");
        assert_eq!(pd.samples, 10);
        assert_eq!(f.safe_state_ms, Some(3.0));
        assert_eq!(f.detected_data_path_ms, Some(0.0));
        assert_eq!(f.republished_ms, Some(10.0));
        // A second fault right after the first does not take the first one's samples.
        let (reports, _) = fault_reports(
            &sc,
            &tr,
            &[
                ev(1.0, 12, kill(), "plant", "plant"),
                ev(1.1, 15, kill(), "plant", "plant"),
            ],
        );
        assert_eq!((reports[0].injected_k, reports[1].injected_k), (10, 13));
        // A fault before the plant's kill ends where the kill's samples begin: the plant's
        // downtime is not reported twice.
        let (reports, _) = fault_reports(
            &sc,
            &tr,
            &[
                ev(0.9, 2, kill(), "observer", "observer"),
                ev(1.0, 12, kill(), "plant", "plant"),
            ],
        );
        assert!(reports[0].plant_down.is_none(), "{:?}", reports[0]);
        assert_eq!(reports[1].plant_down.as_ref().map(|p| p.samples), Some(10));
        // Dated by the count one sample before the plant stopped (it published sample 9
        // while the signal was under way): the fault begins with its downtime all the same.
        let (reports, _) = fault_reports(&sc, &tr, &[ev(1.0, 9, kill(), "plant", "plant")]);
        assert_eq!(reports[0].injected_k, 10, "{:?}", reports[0]);
        assert_eq!(reports[0].plant_down.as_ref().map(|p| p.samples), Some(10));
        // Two samples early: the plant published them while the signal was under way (it was
        // catching up), and the kill took hold where its downtime begins.
        let (reports, _) = fault_reports(&sc, &tr, &[ev(1.0, 8, kill(), "plant", "plant")]);
        assert_eq!(reports[0].injected_k, 10, "{:?}", reports[0]);
        assert_eq!(reports[0].plant_down.as_ref().map(|p| p.samples), Some(10));
        // Not so for a kill of another process, or a stop of the plant's: the downtime that
        // follows is not theirs, and their dating stands.
        let (reports, _) = fault_reports(
            &sc,
            &tr,
            &[ev(1.0, 5, kill(), "current-loop", "current-loop")],
        );
        assert_eq!(reports[0].injected_k, 5, "{:?}", reports[0]);
        let stop = EventKind::Inject {
            fault: FaultKind::Stop,
            duration_s: 0.01,
            monitor_pid: None,
        };
        let (reports, _) = fault_reports(&sc, &tr, &[ev(1.0, 8, stop, "plant", "plant")]);
        assert_eq!(reports[0].injected_k, 8, "{:?}", reports[0]);
    }

    #[test]
    fn no_recovery_within_the_window_reports_none() {
        let sc = scenario();
        let mut tr = rows(0..300);
        at(&mut tr, 5..=299, |r| r.plant_flags = FLAG_SAFE_STATE);
        let (reports, windows) = fault_reports(&sc, &tr, &[ev(1.0, 5, kill(), "plant", "plant")]);
        let f = &reports[0];
        assert_eq!(f.detected_data_path_ms, None);
        assert_eq!(f.safe_state_ms, Some(0.0));
        assert_eq!((f.republished_ms, f.speed_recovered_ms), (None, None));
        // The shaded window is 200 ms at the most.
        assert_eq!(windows[0].1, 0.205);
    }

    #[test]
    fn events_keep_their_json_shape() {
        let all = [
            (kill(), "inject", "kill"),
            (
                EventKind::InjectRefused {
                    reason: "faults need --clock realtime".into(),
                },
                "inject-refused",
                "faults need --clock realtime",
            ),
            (
                EventKind::InjectSkipped {
                    why: "frozen by an earlier stop",
                },
                "inject-skipped",
                "its process is not running: frozen by an earlier stop",
            ),
            (EventKind::Resume, "resume", "SIGCONT"),
            (
                EventKind::Exited {
                    status: ExitStatus::from_raw(9),
                    crash: false,
                },
                "exited",
                "signal: 9 (SIGKILL)",
            ),
            (
                EventKind::Exited {
                    status: ExitStatus::from_raw(11),
                    crash: true,
                },
                "exited",
                "signal: 11 (SIGSEGV), not injected",
            ),
            (
                EventKind::Reaped {
                    nodes: vec!["a".into(), "b".into()],
                },
                "reaped",
                "dead iceoryx2 nodes cleaned: a, b",
            ),
            (
                EventKind::Restarted { restart: 2, pid: 9 },
                "restarted",
                "restart #2, pid 9",
            ),
            (EventKind::Ready { pid: 9 }, "ready", "pid 9"),
        ];
        for (kind, name, detail) in all {
            let v = serde_json::to_value(ev(0.5, 3, kind, "plant", "p")).unwrap();
            assert_eq!(
                v,
                serde_json::json!({ "t_wall_s": 0.5, "k": 3, "event": name, "service": "plant", "process": "p", "detail": detail })
            );
        }
    }
}
