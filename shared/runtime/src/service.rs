//! A stage host process on the iceoryx2 bus: arguments, signals, the bus transport, RT
//! set-up, the start handshake with the launcher, live status and the statistics files.
//!
//! `drivelab-host` is [`host_main`] with the built-in stages; a user's stage crate is the
//! same `main` with its own stages added (see `examples/position-loop`).

use crate::bus::{self, DriveTopics, Poker, Receiver, Sender};
use crate::config::Scenario;
use crate::host::{Counters, Host, HostConfig, Pacing, StageHists, Transport};
use crate::lease::{Lease, Life, Role as LifeRole};
use crate::messages::*;
use crate::rt::{setup_rt, RtPolicy, RtReport, RtRequest};
use crate::stage::{Msg, Role, Stage, TopicId, N_TOPICS};
use crate::telemetry::{open_plain, Plain, PlainSender, ServiceStatus, TOPIC_STATUS};
use crate::timing::{CycleMonitor, LatencyHist};
use crate::topology::{ProcessSpec, Producer, StageInfo};
use anyhow::{anyhow, bail, Context, Result};
use clap::{Parser, ValueEnum};
use serde::{Deserialize, Serialize};
use std::io::{BufRead, Write};
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

/// How the source paces the samples.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum BusClock {
    /// The source sleeps to absolute deadlines; a late command is a deadline miss.
    Realtime,
    /// The source waits for each command; no wall clock; reproducible bit for bit.
    Lockstep,
}

/// Arguments of a stage host (normally given by `drivelab run`).
#[derive(Debug, Parser)]
#[command(about = "drivelab stage host: runs the stages of one process of a drive's topology")]
pub struct HostArgs {
    /// Resolved scenario file (TOML), as written by `drivelab run` into the run folder.
    #[arg(long, required_unless_present = "check_rt")]
    pub scenario: Option<PathBuf>,
    /// Resolved topology (JSON), as written by `drivelab run` into the run folder.
    #[arg(long, required_unless_present_any = ["describe", "check_rt"])]
    pub topology: Option<PathBuf>,
    /// Name of the process of the topology that this host runs.
    #[arg(long, required_unless_present_any = ["describe", "check_rt"])]
    pub process: Option<String>,
    /// The stages this process hosts, comma-separated (as the topology says; lets tools such
    /// as `drivelab fault` find a stage's process from its command line).
    #[arg(long, value_name = "STAGES")]
    pub hosts: Option<String>,
    /// Bus id: isolates this drive's shared memory (1-24 characters of A-Z, a-z, 0-9, _).
    #[arg(long, required_unless_present_any = ["describe", "check_rt"])]
    pub bus: Option<String>,
    /// Pacing of the cycle.
    #[arg(long, value_enum, default_value_t = BusClock::Realtime)]
    pub clock: BusClock,
    /// Fail instead of warning when a core, SCHED_FIFO priority or mlock is refused.
    #[arg(long)]
    pub rt_strict: bool,
    /// Skip pinning, SCHED_FIFO and mlock entirely.
    #[arg(long)]
    pub no_rt: bool,
    /// Count every system call the loop makes from its first sample on beyond its wait and
    /// wakes (`futex`, `clock_nanosleep`, `clock_gettime`, `restart_syscall`, `rt_sigreturn`),
    /// by name, up to a stop request, into `<stage>.stats.json → stray_syscalls` (a seccomp
    /// filter on the loop's thread; docs/architecture.md, "Real-time rules").
    #[arg(long)]
    pub audit_syscalls: bool,
    /// Folder for the statistics files (`<stage>.stats.json`, histograms).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Source only: in lockstep, do not run more than half a recorder buffer ahead of the
    /// recorder (so that it never loses a sample).
    #[arg(long)]
    pub recorder: bool,
    /// Restarted by the supervisor: skip the start handshake and take over from the running
    /// drive.
    #[arg(long)]
    pub rejoin: bool,
    /// With --rejoin: JSON file with what the recorder saw last: the plant's true state (the
    /// source needs it) and the own last output of a stage that reads it back (`wref`).
    #[arg(long, value_name = "FILE", requires = "rejoin")]
    pub rejoin_from: Option<PathBuf>,
    /// Print the declarations of the stages this executable can host (JSON) and exit.
    #[arg(long)]
    pub describe: bool,
    /// Run as the process's standby twin: step on the same inputs, publish nothing, and take
    /// over when the active instance dies (see docs/architecture.md, "Liveness words and
    /// standby twins").
    #[arg(long)]
    pub standby: bool,
    /// Ask for a real-time placement as --rt-strict would (memory lock, and --cpu and
    /// --priority when given), then exit: 0 if every part was granted, else 1 with the
    /// refusal in one line. `drivelab run --rt-strict` asks each process's executable before
    /// the drive starts.
    #[arg(long, conflicts_with_all = ["describe", "topology", "process", "bus"])]
    pub check_rt: bool,
    /// With --check-rt: the CPU to pin to.
    #[arg(long, requires = "check_rt", value_name = "CPU")]
    pub cpu: Option<usize>,
    /// With --check-rt: the SCHED_FIFO priority (1-99).
    #[arg(long, requires = "check_rt", value_name = "PRIORITY")]
    pub priority: Option<u8>,
    /// With --check-rt: how many stages the process will host (what it locks grows with
    /// them).
    #[arg(long, requires = "check_rt", value_name = "N", default_value_t = 1,
          value_parser = clap::value_parser!(u16).range(1..=1024))]
    pub stages: u16,
}

/// A resolved topology as the launcher hands it to the hosts.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct TopologyPlan {
    /// Processes with their stages in chain order.
    pub processes: Vec<ProcessSpec>,
    /// Every produced topic.
    pub producers: Vec<Producer>,
    /// Every stage's declaration, in process and chain order.
    pub stages: Vec<StageInfo>,
    /// Processes that run on the other machine of a split drive (indices into
    /// `processes`): their topics reach this bus through the Zenoh bridge, whose process
    /// stands in for them, so their liveness words here are not read.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub away: Vec<usize>,
    /// Built-in stages that a user's stage replaces, each with the executable hosting it.
    #[serde(default, skip_serializing_if = "std::collections::BTreeMap::is_empty")]
    pub replaced: std::collections::BTreeMap<String, String>,
    /// What resolving the topology found worth a note line (not kept in topology.json): a
    /// process whose `exec` runs a built-in stage that could have been replaced.
    #[serde(skip)]
    pub notes: Vec<String>,
}

impl TopologyPlan {
    /// From a resolved topology.
    pub fn from_resolved(r: &crate::topology::Resolved) -> Self {
        Self {
            processes: r.processes.iter().map(|(p, _)| p.clone()).collect(),
            producers: r.producers.clone(),
            stages: r
                .processes
                .iter()
                .flat_map(|(_, s)| s.iter().cloned())
                .collect(),
            away: Vec::new(),
            replaced: Default::default(),
            notes: Vec::new(),
        }
    }

    /// Index of the process that hosts `stage`.
    pub fn process_of(&self, stage: &str) -> Option<usize> {
        self.processes
            .iter()
            .position(|p| p.stages.iter().any(|s| s == stage))
    }

    /// One line per stage that waits in real time for a trigger from another process after
    /// its own process's first stage has run (`{plant, current-loop}` beside `{observer,
    /// speed-loop}`): its host waits for that trigger with a timeout of a quarter sample, a
    /// timer every sample, where the other waits have none (docs/architecture.md,
    /// "Real-time rules"). No shipped topology has one.
    pub fn timed_waits(&self) -> Vec<String> {
        let mut lines = Vec::new();
        for (pi, p) in self.processes.iter().enumerate() {
            for name in p.stages.iter().skip(1) {
                let Some(st) = self.stages.iter().find(|s| &s.name == name) else {
                    continue;
                };
                for i in st.inputs.iter().filter(|i| i.role == Role::Trigger) {
                    let Some(src) = self.producers.iter().find(|x| x.topic == i.topic) else {
                        continue;
                    };
                    if src.process != pi {
                        lines.push(format!(
                            "process '{}': stage '{name}' is triggered by '{}' from process '{}' after '{}' has run: in real time it waits for it with a timer every sample; host it with '{}' or first in a process of its own",
                            p.name,
                            i.topic.name(),
                            self.processes[src.process].name,
                            p.stages[0],
                            src.stage
                        ));
                    }
                }
            }
        }
        lines
    }

    /// The topics that the stages `stages` publish and read back while they rejoin (their
    /// own-output rejoin slots, docs/architecture.md, "Bumpless rejoin"), each once.
    pub fn own_rejoin_topics(&self, stages: &[String]) -> Vec<TopicId> {
        let mut topics = Vec::new();
        for st in self.stages.iter().filter(|s| stages.contains(&s.name)) {
            for i in &st.inputs {
                if i.role == Role::Rejoin
                    && st.outputs.contains(&i.topic)
                    && !topics.contains(&i.topic)
                {
                    topics.push(i.topic);
                }
            }
        }
        topics
    }
}

/// Builds a user stage from the scenario.
pub type StageFactory = fn(&Scenario) -> Result<Box<dyn Stage>>;

static STOP: AtomicBool = AtomicBool::new(false);
static STOP_SIGNAL: std::sync::atomic::AtomicI32 = std::sync::atomic::AtomicI32::new(0);

/// The signals that stop a drive cleanly (its trace and summary written, its bus removed):
/// Ctrl-C, a stop request, a closed terminal, Ctrl-\, the two user signals, and every other
/// standard signal whose default would end the process on the spot (timers, a CPU time
/// limit, power failure, I/O readiness). SIGPIPE and SIGXFSZ are ignored instead (a failed
/// write says why). [`stop_signals`] adds the real-time signals.
pub const STOP_SIGNALS: [(libc::c_int, &str); 13] = [
    (libc::SIGINT, "SIGINT"),
    (libc::SIGTERM, "SIGTERM"),
    (libc::SIGHUP, "SIGHUP"),
    (libc::SIGQUIT, "SIGQUIT"),
    (libc::SIGUSR1, "SIGUSR1"),
    (libc::SIGUSR2, "SIGUSR2"),
    (libc::SIGALRM, "SIGALRM"),
    (libc::SIGVTALRM, "SIGVTALRM"),
    (libc::SIGPROF, "SIGPROF"),
    (libc::SIGXCPU, "SIGXCPU"),
    (libc::SIGPWR, "SIGPWR"),
    (libc::SIGIO, "SIGIO"),
    (libc::SIGSTKFLT, "SIGSTKFLT"),
];

/// Names of the real-time signals from SIGRTMIN up (the C library keeps the kernel's first
/// two or three for itself; at most 33 remain).
const RT_SIGNAL_NAMES: [&str; 33] = [
    "SIGRTMIN",
    "SIGRTMIN+1",
    "SIGRTMIN+2",
    "SIGRTMIN+3",
    "SIGRTMIN+4",
    "SIGRTMIN+5",
    "SIGRTMIN+6",
    "SIGRTMIN+7",
    "SIGRTMIN+8",
    "SIGRTMIN+9",
    "SIGRTMIN+10",
    "SIGRTMIN+11",
    "SIGRTMIN+12",
    "SIGRTMIN+13",
    "SIGRTMIN+14",
    "SIGRTMIN+15",
    "SIGRTMIN+16",
    "SIGRTMIN+17",
    "SIGRTMIN+18",
    "SIGRTMIN+19",
    "SIGRTMIN+20",
    "SIGRTMIN+21",
    "SIGRTMIN+22",
    "SIGRTMIN+23",
    "SIGRTMIN+24",
    "SIGRTMIN+25",
    "SIGRTMIN+26",
    "SIGRTMIN+27",
    "SIGRTMIN+28",
    "SIGRTMIN+29",
    "SIGRTMIN+30",
    "SIGRTMIN+31",
    "SIGRTMIN+32",
];

/// Every signal that stops a drive cleanly: the [`STOP_SIGNALS`] and the real-time signals
/// (SIGRTMIN … SIGRTMAX), whose default also ends a process on the spot.
pub fn stop_signals() -> impl Iterator<Item = (libc::c_int, &'static str)> {
    STOP_SIGNALS
        .into_iter()
        .chain((libc::SIGRTMIN()..=libc::SIGRTMAX()).zip(RT_SIGNAL_NAMES))
}

/// The pid of the process that sent the first stop signal when that was neither this
/// process's parent (its launcher) nor the kernel (a terminal's Ctrl-C or hang-up); else 0.
static STOP_SENDER_OUTSIDE: std::sync::atomic::AtomicI32 = std::sync::atomic::AtomicI32::new(0);

/// This process's parent (its launcher) when the handlers were installed: the handler reads
/// it instead of asking the kernel, so that it makes no system call inside a loop it
/// interrupts (the system-call audit counts the loop's calls up to the stop).
static PARENT: std::sync::atomic::AtomicI32 = std::sync::atomic::AtomicI32::new(0);

extern "C" fn on_signal(sig: libc::c_int, info: *mut libc::siginfo_t, _: *mut libc::c_void) {
    let parent = PARENT.load(Ordering::SeqCst);
    // SAFETY: the kernel hands an SA_SIGINFO handler a valid siginfo_t (checked for null
    // all the same); si_code and si_pid are plain reads.
    let outside = unsafe {
        match info.as_ref() {
            // si_code ≤ 0: sent by a process (kill, sigqueue, tgkill), which si_pid names.
            Some(i) if i.si_code <= 0 && i.si_pid() != parent => i.si_pid(),
            _ => 0,
        }
    };
    // The first signal names the stop (stored before the flag, which the loops read).
    if STOP_SIGNAL
        .compare_exchange(0, sig, Ordering::SeqCst, Ordering::SeqCst)
        .is_ok()
    {
        STOP_SENDER_OUTSIDE.store(outside, Ordering::SeqCst);
    }
    STOP.store(true, Ordering::SeqCst);
}

/// Installs handlers of the [`stop_signals`] that set the stop flag (iceoryx2's own handling
/// is off).
pub fn install_signal_handlers() -> Result<()> {
    // SAFETY: getppid takes no argument and cannot fail.
    PARENT.store(unsafe { libc::getppid() }, Ordering::SeqCst);
    for (sig, _) in stop_signals() {
        // SAFETY: `sigaction` is given a zero-initialised struct whose handler is an
        // `extern "C"` function that only stores to an atomic, which is async-signal-safe.
        let rc = unsafe {
            let mut sa: libc::sigaction = std::mem::zeroed();
            sa.sa_sigaction = on_signal as *const () as libc::sighandler_t;
            sa.sa_flags = libc::SA_SIGINFO;
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
    // A process may start with some of them blocked, so that one sent before its handlers
    // were in place waits for them (a bench's hop receiver: its parent-death SIGTERM); now
    // they can come.
    // SAFETY: a zero-initialised sigset_t filled by sigemptyset/sigaddset, passed by valid
    // pointer; the old mask is not asked for (null).
    let rc = unsafe {
        let mut set: libc::sigset_t = std::mem::zeroed();
        libc::sigemptyset(&mut set);
        for (sig, _) in stop_signals() {
            libc::sigaddset(&mut set, sig);
        }
        libc::pthread_sigmask(libc::SIG_UNBLOCK, &set, std::ptr::null_mut())
    };
    if rc != 0 {
        return Err(anyhow!(
            "cannot unblock the stop signals: {}",
            std::io::Error::from_raw_os_error(rc)
        ));
    }
    Ok(())
}

/// The flag the handlers of [`install_signal_handlers`] set (no SA_RESTART: a blocked
/// receive returns EINTR, so a loop sees it at once).
pub fn stop_flag() -> &'static AtomicBool {
    &STOP
}

/// True once one of the [`stop_signals`] arrived.
pub fn stop_requested() -> bool {
    STOP.load(Ordering::Relaxed)
}

/// The name of the first stop signal that arrived ("SIGINT" …), or "a stop signal" before
/// any.
pub fn stop_signal_name() -> &'static str {
    let sig = STOP_SIGNAL.load(Ordering::Relaxed);
    stop_signals()
        .find(|(s, _)| *s == sig)
        .map_or("a stop signal", |(_, n)| n)
}

/// A file size limit (`ulimit -f`) then makes the write that passes it fail with EFBIG,
/// which the writer reports in one line, instead of killing the process with SIGXFSZ on the
/// spot (a launcher killed so leaves its bus behind). Every `main` calls this first.
pub fn file_size_limit_as_error() {
    // SAFETY: signal(2) with SIG_IGN changes only this process's disposition of SIGXFSZ.
    unsafe {
        libc::signal(libc::SIGXFSZ, libc::SIG_IGN);
    }
}

/// The first stop signal and its sender, when a process other than this one's parent sent
/// it: for a stage host, a stop that is not its launcher's (`kill PID` from a shell).
pub fn stopped_from_outside() -> Option<(libc::c_int, libc::pid_t)> {
    let pid = STOP_SENDER_OUTSIDE.load(Ordering::SeqCst);
    (pid != 0 && pid != std::process::id() as libc::pid_t)
        .then(|| (STOP_SIGNAL.load(Ordering::SeqCst), pid))
}

/// The exit status of a stage host that a stop signal from outside its drive ended: 128 +
/// the signal, as a shell reports a process that the signal killed. The launcher counts it
/// as a crash unless it is stopping the drive too (`timeout`, `kill -- -PGID` and service
/// managers signal every process of a drive at once).
pub fn outside_stop_status(sig: libc::c_int) -> u8 {
    u8::try_from(128 + sig).unwrap_or(1)
}

/// Writes one protocol line to stdout (to the launcher) and flushes it.
pub fn protocol_line(line: &str) -> Result<()> {
    let mut out = std::io::stdout().lock();
    writeln!(out, "{line}")?;
    out.flush()?;
    Ok(())
}

/// Builds stage `name`: a built-in one or one of `user`.
pub fn make_stage(
    name: &str,
    sc: &Scenario,
    user: &[(&str, StageFactory)],
) -> Result<Box<dyn Stage>> {
    if let Some((_, f)) = user.iter().find(|(n, _)| *n == name) {
        // A user's stage is a controller or an observer: it sees the controller's model.
        let s = f(&sc.controller_view()).with_context(|| format!("stage '{name}'"))?;
        // The launcher knows a stage by what `--describe` says, `Stage::name`; this host
        // builds it by the name it was registered under.
        if s.name() != name {
            bail!(
                "the user's stage registered as '{name}' calls itself '{}' (Stage::name): the two must be the same",
                s.name()
            );
        }
        return Ok(s);
    }
    crate::stages::builtin(name, sc).ok_or_else(|| {
        let mut known: Vec<&str> = crate::stages::BUILTIN.to_vec();
        known.extend(user.iter().map(|(n, _)| *n));
        anyhow!(
            "this executable hosts no stage '{name}' (it hosts: {})",
            known.join(", ")
        )
    })
}

/// The user's stages must not take the plant's name (a built-in stage that cannot be
/// replaced; the others can: [`crate::stages::REPLACEABLE`]), nor one name twice.
fn check_user_names(user: &[(&'static str, StageFactory)]) -> Result<()> {
    for (i, (n, _)) in user.iter().enumerate() {
        if crate::stages::BUILTIN.contains(n) && !crate::stages::REPLACEABLE.contains(n) {
            anyhow::bail!(
                "a user's stage may not be called '{n}': the built-in {n} cannot be replaced (a user's stage may replace {}); give it another name",
                crate::stages::REPLACEABLE.join(", ")
            );
        }
        if user[..i].iter().any(|(m, _)| m == n) {
            anyhow::bail!("the user's stage '{n}' is registered twice");
        }
    }
    Ok(())
}

/// The `main` of a stage host: the built-in stages plus `user`. Prints a one-line error and
/// exits 1 on failure.
pub fn host_main(user: &[(&'static str, StageFactory)]) -> std::process::ExitCode {
    crate::bus::quiet_iceoryx2_log();
    file_size_limit_as_error();
    // A stage that panics prints its message (and, with RUST_BACKTRACE, symbolizes its
    // backtrace: milliseconds of work) off the real-time priority, so that the stages below
    // it on its core are not held up while it dies.
    let report = std::panic::take_hook();
    std::panic::set_hook(Box::new(move |info| {
        let _ = crate::rt::set_scheduler(libc::SCHED_OTHER, 0);
        report(info);
        let msg = info
            .payload()
            .downcast_ref::<&str>()
            .map(|s| s.to_string())
            .or_else(|| info.payload().downcast_ref::<String>().cloned())
            .unwrap_or_else(|| "(no message)".into());
        let at = info
            .location()
            .map(|l| format!(" (at {}:{})", l.file(), l.line()))
            .unwrap_or_default();
        if let Ok(mut p) = PANIC.lock() {
            p.get_or_insert(crate::text::one_line(&format!("{msg}{at}")));
        }
    }));
    let args = HostArgs::parse();
    if args.check_rt {
        return check_rt(&args);
    }
    let name = args.process.clone().unwrap_or_else(|| "host".into());
    let stages = args.hosts.clone().unwrap_or_else(|| name.clone());
    // A panic (a stage's bug) ends the process with PANIC_STATUS, after one line naming it
    // on stderr and a `PANIC` line telling the launcher what it was.
    let result = install_signal_handlers().and_then(|_| {
        std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| run_host(args, user)))
            .unwrap_or_else(|_| Err(anyhow!(Panicked { during: None })))
    });
    if let Some(p) = result
        .as_ref()
        .err()
        .and_then(|e| e.downcast_ref::<Panicked>())
    {
        let what = PANIC
            .lock()
            .ok()
            .and_then(|p| p.clone())
            .unwrap_or_else(|| "(no message)".into());
        // The stage call it panicked in, with its sample; outside the drive's loop (set-up,
        // the end), the process's stages.
        let during = p
            .during
            .clone()
            .unwrap_or_else(|| format!("stages {stages}"));
        crate::errln!(
            "{name}: error: a stage panicked ({during}): {what}; exit status {PANIC_STATUS}"
        );
        let _ = protocol_line(&format!("PANIC {during}: {what}"));
        return std::process::ExitCode::from(PANIC_STATUS);
    }
    // A stop signal that another process sent (not the launcher, not the terminal) ends
    // the process, not the drive: the source forwards no end of the run, and the exit
    // status says which signal it was (the launcher names it; docs/architecture.md,
    // "Stopping a drive").
    if let Some((sig, _)) = stopped_from_outside() {
        return std::process::ExitCode::from(outside_stop_status(sig));
    }
    if let Err(e) = result {
        // A host told to stop (SIGTERM from a launcher whose start failed elsewhere, or
        // Ctrl-C) fails in whatever it was doing; the launcher says why, once.
        if !stop_requested() {
            crate::errln!("{name}: error: {}", crate::text::error_text(&e));
        }
        return std::process::ExitCode::from(1);
    }
    std::process::ExitCode::SUCCESS
}

/// The exit status of a stage host whose stage panicked (Rust's own for a panic that ends a
/// program). Before it exits the host prints one line naming the panic and sends the
/// launcher `PANIC <what>` on its stdout.
pub const PANIC_STATUS: u8 = 101;

/// The first panic's message and place, as the panic hook saw it.
static PANIC: std::sync::Mutex<Option<String>> = std::sync::Mutex::new(None);

/// The error `host_main` turns a caught panic into: `during`, the stage call of the drive's
/// loop it was caught in ([`Host::last_call`]), if it was.
#[derive(Debug)]
struct Panicked {
    during: Option<String>,
}

impl std::fmt::Display for Panicked {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("a stage panicked")
    }
}

/// `--check-rt`: the placement a real-time host asks for, strictly; the process exits
/// straight after, and the kernel drops all of it.
fn check_rt(args: &HostArgs) -> std::process::ExitCode {
    let placement = RtRequest {
        core: args.cpu,
        fifo_priority: args.priority,
        lock_memory: false,
        prefault_stack_bytes: 0,
    };
    // The priority again: a request without one would move the thread back to SCHED_OTHER.
    let lock = RtRequest {
        core: None,
        lock_memory: true,
        ..placement
    };
    // The core and the priority, then whether the memory lock's limit leaves room for what
    // a host locks once its bus is open (far more than this process), then the lock itself.
    let checked = setup_rt(&placement, RtPolicy::Strict)
        .and_then(|_| {
            crate::rt::check_lock_headroom(crate::rt::host_locked_bytes(args.stages.into()))
        })
        .and_then(|_| setup_rt(&lock, RtPolicy::Strict));
    match checked {
        Ok(_) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            crate::errln!("{}", crate::text::error_text(&e));
            std::process::ExitCode::from(1)
        }
    }
}

fn load_scenario(path: &std::path::Path) -> Result<Scenario> {
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("cannot read scenario {}", path.display()))?;
    Scenario::from_toml(&text, &path.display().to_string()).map_err(|e| anyhow!(e))
}

fn run_host(args: HostArgs, user: &[(&'static str, StageFactory)]) -> Result<()> {
    // Start-up phases, ms: where a restarted process spends its time before READY.
    let mut phase_start = std::time::Instant::now();
    let mut startup: Vec<(&'static str, f64)> = Vec::with_capacity(8);
    let mut phase = |name: &'static str| {
        let now = std::time::Instant::now();
        startup.push((name, (now - phase_start).as_secs_f64() * 1e3));
        phase_start = now;
    };
    check_user_names(user)?;
    let sc = load_scenario(args.scenario.as_deref().expect("required by clap"))?;
    phase("scenario");
    if args.describe {
        let mut infos = Vec::new();
        for (n, _) in user {
            let s = make_stage(n, &sc, user)?;
            infos.push(StageInfo {
                name: s.name().to_string(),
                inputs: s.inputs().to_vec(),
                outputs: s.outputs().to_vec(),
                divider: s.divider(),
            });
        }
        protocol_line(&serde_json::to_string(&infos)?)?;
        return Ok(());
    }
    let topo_path = args.topology.as_ref().expect("required by clap");
    let plan: TopologyPlan = serde_json::from_str(
        &std::fs::read_to_string(topo_path)
            .with_context(|| format!("cannot read topology {}", topo_path.display()))?,
    )
    .with_context(|| format!("topology {}", topo_path.display()))?;
    let pname = args.process.clone().expect("required by clap");
    let bus_id = args.bus.clone().expect("required by clap");
    let pi = plan
        .processes
        .iter()
        .position(|p| p.name == pname)
        .ok_or_else(|| anyhow!("the topology has no process '{pname}'"))?;
    let proc = plan.processes[pi].clone();
    if let Some(h) = &args.hosts {
        if *h != proc.stages.join(",") {
            bail!(
                "--hosts {h} differs from the topology's stages of process '{pname}': {}",
                proc.stages.join(",")
            );
        }
    }
    let stages: Vec<Box<dyn Stage>> = proc
        .stages
        .iter()
        .map(|s| make_stage(s, &sc, user))
        .collect::<Result<_>>()?;
    phase("stages");
    // The launcher planned the drive on the stages' declarations as `--describe` gave them:
    // a stage that runs at another rate than declared would wait for samples never coming.
    for s in &stages {
        if let Some(p) = plan
            .stages
            .iter()
            .find(|p| p.name == s.name() && p.divider != s.divider())
        {
            bail!(
                "stage '{}' runs every {} sample(s), but the drive was planned on every {} (its executable's --describe answer): the answer and the stage differ",
                s.name(),
                s.divider(),
                p.divider
            );
        }
    }
    for s in &stages {
        for w in s.warnings() {
            crate::errln!("{}: warning: {w}", s.name());
        }
    }
    let bindings: Vec<(TopicId, u64, bool)> = plan
        .producers
        .iter()
        .map(|p| (p.topic, p.divider, p.process == pi))
        .collect();
    let source = pi == 0;
    let lockstep = args.clock == BusClock::Lockstep;
    if args.standby && (lockstep || !proc.standby) {
        bail!("--standby: process '{pname}' has no standby twin in a real-time drive");
    }
    let node = bus::node(
        &bus_id,
        &if args.standby {
            format!("{pname}-standby")
        } else {
            pname.clone()
        },
    )?;
    phase("node");
    let topics = DriveTopics::open_for(
        &node,
        sc.timing.wake,
        &bus_id,
        publishers_per_topic(&plan, lockstep),
    )?;
    phase("topics");
    // Which topics this process receives, sends, waits on and pokes.
    let decim = decimation(&plan);
    let mut decimated = [true; N_TOPICS];
    let mut waited = [false; N_TOPICS];
    let mut polled = [false; N_TOPICS];
    let mut sent = [false; N_TOPICS];
    let external = |t: TopicId| bindings.iter().any(|(x, _, local)| *x == t && !*local);
    // A stage killed by the lockstep schedule rejoins later: it keeps its rejoin inputs.
    let killed = |name: &str| {
        sc.inject
            .iter()
            .any(|i| i.kind == crate::inject::InjectKind::Kill && i.target == name)
    };
    for s in &stages {
        for &t in s.outputs() {
            sent[t.index()] = true;
        }
        for i in s.inputs() {
            if !external(i.topic) {
                continue;
            }
            // A trigger this process's stages step on only every d-th time can be slept
            // through in between, unless some other wait here needs every one.
            let producer_divider = bindings
                .iter()
                .find(|(x, _, _)| *x == i.topic)
                .map_or(1, |b| b.1);
            let waits = i.role == Role::Trigger || (lockstep && i.role == Role::Latest);
            let slower = i.role == Role::Trigger && s.divider() > producer_divider;
            if waits && (!slower || decim[i.topic.index()] == 0) {
                decimated[i.topic.index()] = false;
            }
            match i.role {
                Role::Trigger => waited[i.topic.index()] = true,
                Role::Latest if lockstep => waited[i.topic.index()] = true,
                Role::Latest => polled[i.topic.index()] = true,
                Role::Rejoin if args.rejoin || (lockstep && killed(s.name())) => {
                    polled[i.topic.index()] = true
                }
                Role::Rejoin => {}
            }
        }
    }
    // Not the source, in real time: the source's output tells where the drive is. With
    // futex wake words, waiting on it costs the source nothing while nobody sleeps there
    // (a stage falls back on it only while its trigger is lost); an iceoryx2 listener
    // would cost the source a syscall per sample, so with events it is only polled.
    let clock_wakes = !source && !lockstep && sc.timing.wake == crate::bus::WakeKind::Futex;
    if clock_wakes {
        waited[TopicId::Meas.index()] = true;
        decimated[TopicId::Meas.index()] = false;
    } else if !source && !lockstep {
        polled[TopicId::Meas.index()] = true;
    }
    // The source pokes the triggers of the other processes when its delayed input is
    // missing, so that they check their inputs' age without a timer of their own.
    let mut poke = Vec::new();
    if source {
        // Every stage outside this (the source's) process.
        for st in plan
            .stages
            .iter()
            .filter(|s| !plan.processes[0].stages.contains(&s.name))
        {
            for inp in &st.inputs {
                if inp.role == Role::Trigger
                    && !sent[inp.topic.index()]
                    && !poke.contains(&inp.topic)
                {
                    poke.push(inp.topic);
                }
            }
        }
    }
    let wait: [Wait; N_TOPICS] = std::array::from_fn(|i| match (waited[i], polled[i]) {
        (true, _) if decimated[i] => Wait::Decimated,
        (true, _) => Wait::Woken,
        (false, true) => Wait::Polled,
        (false, false) => Wait::None,
    });
    let mut tr = BusTransport::open(
        &topics,
        &wait,
        &sent,
        &poke,
        lockstep && source && args.recorder,
    )?;
    tr.decim = decim;
    if !lockstep {
        // Liveness (docs/architecture.md, "Liveness words and standby twins"): this instance
        // holds its process's lease, or as a twin its standby mutex, from here to its end;
        // each input from another process goes stale the moment its producer is down.
        let life = std::sync::Arc::new(Life::open(&bus_id, plan.processes.len())?);
        if args.standby {
            let mut own = life.lease(pi, LifeRole::Standby)?;
            own.hold()?;
            let lease = life.lease(pi, LifeRole::Active)?;
            tr.shadow = Some(Shadow::new(lease, own, &topics, &sent)?);
        } else {
            let mut lease = life.lease(pi, LifeRole::Active)?;
            lease.hold()?;
            tr.lease = Some(lease);
        }
        for b in &plan.producers {
            if b.process != pi && !plan.away.contains(&b.process) {
                tr.producer[b.topic.index()] = Some(b.process);
            }
        }
        tr.life = Some(life);
    }
    tr.status = stages
        .iter()
        .map(|s| {
            let idx = plan.stages.iter().position(|x| x.name == s.name());
            StatusPublisher::new(&node, idx, &sc)
        })
        .collect::<Result<_>>()?;
    phase("ports");
    // Connect now (a restarted process joins running peers), not at real-time priority.
    tr.connect()?;
    phase("connect");
    let rejoin_from = match &args.rejoin_from {
        Some(path) if args.rejoin => {
            rejoin_state(path, source, &plan.own_rejoin_topics(&proc.stages))?
        }
        _ if args.rejoin && source => bail!("--rejoin of the source needs --rejoin-from FILE"),
        _ => Vec::new(),
    };
    let mut host = Host::new(
        stages,
        &bindings,
        tr,
        HostConfig {
            rejoin: args.rejoin,
            rejoin_from,
            poke,
            clock_wakes,
            ..HostConfig::for_scenario(
                &sc,
                if lockstep {
                    Pacing::Lockstep
                } else {
                    Pacing::Realtime
                },
                // Lockstep: up to a kill of the plant for good, where the drive ends.
                if lockstep {
                    sc.samples_made()
                } else {
                    sc.samples()
                },
            )
        },
    );
    host.arm_spares(|name| make_stage(name, &sc, user).ok())?;
    host.stop_when(stop_requested);
    host.stop_without_end_when(|| stopped_from_outside().is_some());
    // Last: everything above (designs, histograms, ports) is set-up work, not real-time.
    let label = if args.standby {
        format!("{pname} (standby)")
    } else {
        pname.clone()
    };
    // The audit's supervisor is a normal task: started before the placement it would inherit.
    let audit = args
        .audit_syscalls
        .then(|| crate::audit::Audit::start(stop_requested))
        .transpose()?;
    if let Some(a) = &audit {
        let a = a.clone();
        host.at_first_sample(move || a.arm());
    }
    let report = apply_placement(&label, &proc, &args)?;
    phase("rt");
    // The launcher signals this pid (faults): it is its child's unless a wrapper script
    // started this host without `exec`.
    protocol_line(&format!("PID {}", std::process::id()))?;
    protocol_line("READY")?;
    if source && !args.rejoin {
        // Wait for the launcher's GO (everyone is subscribed by then).
        let mut line = String::new();
        std::io::stdin().lock().read_line(&mut line)?;
        if line.is_empty() && stop_requested() {
            // Stopped during the start-up: the launcher closed our stdin after its signal.
            // The drive never ran; there is nothing to report.
            return Ok(());
        }
        if line.trim() != "GO" {
            bail!(
                "launcher did not say GO (got {:?}); not starting",
                line.trim()
            );
        }
    }
    // What the set-up cost is not the run's: its figures start here.
    let at_run = usage(libc::RUSAGE_SELF);
    // A panic in a stage call is caught here, where the host can still say which call of
    // which stage at which sample it was (docs/architecture.md, "Fault model").
    let ran = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| host.run())).unwrap_or_else(
        |_| {
            Err(anyhow!(Panicked {
                during: host.last_call()
            }))
        },
    );
    let stray = audit.as_ref().map(|a| a.disarm());
    ran?;
    if host.transport.shadow.is_some() {
        // A twin that never took over: the active instance's statistics are the process's.
        return Ok(());
    }
    for h in &host.stages {
        for w in h.stage.exit_warnings() {
            crate::errln!("{}: warning: {w}", h.stage.name());
        }
    }
    write_stats(
        &args,
        &pname,
        &report,
        &host,
        &startup,
        at_run,
        stray.as_ref(),
    )
}

/// Publishers per drive topic: 1, or 2 when a process of a real-time drive has a standby
/// twin (its publishers are made at its set-up). Every node of the bus opens the topics with
/// this number, the launcher's recorder first.
pub fn publishers_per_topic(plan: &TopologyPlan, lockstep: bool) -> usize {
    if !lockstep && plan.processes.iter().any(|p| p.standby) {
        2
    } else {
        1
    }
}

/// Set (by the launcher of a campaign's run): a host does not print its real-time set-up
/// line; the launcher has the report from the `RT` line and puts it in summary.json.
pub const QUIET_RT_LINE: &str = "DRIVELAB_QUIET_RT_LINE";

/// Applies the process's placement and prints the one-line report to stderr (unless
/// [`QUIET_RT_LINE`] is set); also sends
/// `RT <json>` on stdout for the launcher.
fn apply_placement(process: &str, p: &ProcessSpec, args: &HostArgs) -> Result<RtReport> {
    let req = if args.no_rt {
        RtRequest {
            core: None,
            fifo_priority: None,
            lock_memory: false,
            prefault_stack_bytes: 0,
        }
    } else {
        RtRequest {
            core: p.cpu,
            // The twin runs right after the active instance on its core (docs/architecture.md,
            // "Liveness words and standby twins"). Lockstep has no deadline to keep: its
            // processes keep their cores but run as normal tasks, so that a long simulation
            // does not hold a core at real-time priority for minutes (docs/architecture.md,
            // "Clocks").
            fifo_priority: p
                .priority
                .filter(|_| args.clock == BusClock::Realtime)
                .map(|pr| {
                    if args.standby {
                        pr.saturating_sub(1).max(1)
                    } else {
                        pr
                    }
                }),
            lock_memory: true,
            prefault_stack_bytes: 256 * 1024,
        }
    };
    let policy = if args.rt_strict {
        RtPolicy::Strict
    } else {
        RtPolicy::Warn
    };
    let report = setup_rt(&req, policy).map_err(|e| anyhow!("{process}: {e}"))?;
    if std::env::var_os(QUIET_RT_LINE).is_none() {
        crate::errln!("{}", report.one_line(process));
    }
    protocol_line(&format!("RT {}", serde_json::to_string(&report)?))?;
    Ok(report)
}

// ------------------------------------------------------------------ the bus transport

enum Rx {
    Meas(Receiver<Measurement>),
    Est(Receiver<Estimate>),
    Iref(Receiver<CurrentRef>),
    Cmd(Receiver<VoltageCommand>),
    Wref(Receiver<SpeedRef>),
    Truth(Receiver<PlantTruth>),
}

enum Tx {
    Meas(Sender<Measurement>),
    Est(Sender<Estimate>),
    Iref(Sender<CurrentRef>),
    Cmd(Sender<VoltageCommand>),
    Wref(Sender<SpeedRef>),
    Truth(Sender<PlantTruth>),
}

/// How a process receives a topic.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Wait {
    /// Not at all.
    None,
    /// Read when needed; never woken by it.
    Polled,
    /// Woken by every message.
    Woken,
    /// Woken only at the samples its stages step (see [`decimation`]).
    Decimated,
}

impl Wait {
    fn receiver<T: std::fmt::Debug + iceoryx2::prelude::ZeroCopySend + Copy + 'static>(
        self,
        topic: &bus::Topic<T>,
        buffer: usize,
    ) -> Result<Receiver<T>> {
        match self {
            Wait::Decimated => topic.decimated_receiver(buffer),
            Wait::Woken => topic.receiver(buffer),
            Wait::Polled | Wait::None => topic.polled_receiver(buffer),
        }
    }
}

/// A receiver of topic `t` that waits per `w`, with a buffer of `buf` samples.
fn rx_of(topics: &DriveTopics, t: TopicId, w: Wait, buf: usize) -> Result<Rx> {
    Ok(match t {
        TopicId::Meas => Rx::Meas(w.receiver(&topics.meas, buf)?),
        TopicId::Est => Rx::Est(w.receiver(&topics.est, buf)?),
        TopicId::Iref => Rx::Iref(w.receiver(&topics.iref, buf)?),
        TopicId::Cmd => Rx::Cmd(w.receiver(&topics.cmd, buf)?),
        TopicId::Wref => Rx::Wref(w.receiver(&topics.wref, buf)?),
        TopicId::Truth => Rx::Truth(w.receiver(&topics.truth, buf)?),
    })
}

/// [`Sender::wake`] on whichever topic `t` sends.
fn wake_tx(t: &Tx, decimated: bool) -> Result<()> {
    match t {
        Tx::Meas(t) => t.wake(decimated),
        Tx::Est(t) => t.wake(decimated),
        Tx::Iref(t) => t.wake(decimated),
        Tx::Cmd(t) => t.wake(decimated),
        Tx::Wref(t) => t.wake(decimated),
        Tx::Truth(t) => t.wake(decimated),
    }
}

/// The next message of `r`, if one is there.
#[inline]
fn recv_rx(r: &Rx) -> Result<Option<Msg>> {
    Ok(match r {
        Rx::Meas(r) => r.try_recv()?.map(Msg::Meas),
        Rx::Est(r) => r.try_recv()?.map(Msg::Est),
        Rx::Iref(r) => r.try_recv()?.map(Msg::Iref),
        Rx::Cmd(r) => r.try_recv()?.map(Msg::Cmd),
        Rx::Wref(r) => r.try_recv()?.map(Msg::Wref),
        Rx::Truth(r) => r.try_recv()?.map(Msg::Truth),
    })
}

/// Per topic, the rate below its producer's at which some stage of another process steps
/// on it as its trigger: the gcd of those stages' dividers (0: none). Such stages sleep on
/// the topic's decimated wake word, which the producer bumps only at multiples of it, so a
/// 1 kHz speed loop is not woken at 10 kHz to do nothing nine times out of ten.
pub fn decimation(plan: &TopologyPlan) -> [u64; N_TOPICS] {
    let mut d = [0u64; N_TOPICS];
    for s in &plan.stages {
        let Some(t) = s.inputs.iter().find(|i| i.role == Role::Trigger) else {
            continue;
        };
        let Some(p) = plan.producers.iter().find(|p| p.topic == t.topic) else {
            continue;
        };
        if plan.process_of(&s.name) != Some(p.process) && s.divider > p.divider {
            d[t.topic.index()] = crate::host::gcd(d[t.topic.index()], s.divider);
        }
    }
    d
}

/// The iceoryx2 bus as a [`Transport`]: one receiver per input topic (waitable for
/// triggers, and in lockstep for every input; only polled otherwise, so that senders pay no
/// wake-up for it), one sender per output topic.
pub struct BusTransport {
    /// Per topic: its decimated receivers step every this many samples (0: none).
    decim: [u64; N_TOPICS],
    rx: [Option<Rx>; N_TOPICS],
    tx: [Option<Tx>; N_TOPICS],
    pokers: Vec<(TopicId, Poker)>,
    rec: Option<Receiver<u64>>,
    status: Vec<StatusPublisher>,
    /// A standby twin that has not taken over: it publishes nothing (see [`Shadow`]).
    shadow: Option<Shadow>,
    /// The lease this instance holds (its process's; a twin's once it has taken over). Kept
    /// until the process ends. None in lockstep.
    lease: Option<Lease>,
    /// The bus's liveness segment (real time).
    life: Option<std::sync::Arc<Life>>,
    /// Per topic, the process that produces it when that is another process.
    producer: [Option<usize>; N_TOPICS],
    /// Per topic: the newest index the instance before this one published (a twin that
    /// took over sends only later ones).
    before: [Option<u64>; N_TOPICS],
    /// A twin that took over: its watching receivers, kept (never read) until the end.
    retired: Option<[Option<Rx>; N_TOPICS]>,
    /// A twin that took over: per output topic, the newest message its predecessor
    /// published that it read (what a stage still rejoining reads back).
    inherited: [Option<Msg>; N_TOPICS],
}

/// A standby twin before it takes over: it steps on the same inputs as the active instance
/// and publishes nothing. It tries the lease at every output; once the active instance has
/// died the lease is its, it reads which samples its predecessor had published, and from
/// then on it is the process.
pub struct Shadow {
    /// The process's lease, taken at the takeover.
    lease: Lease,
    /// The twin's own standby mutex, held while it waits (its process reads up while it
    /// lives), given up at the takeover for the next twin.
    own: Lease,
    /// Per output topic, a polled receiver of the active instance's messages (read at the
    /// takeover for their newest index, and by a stage's rejoin for its own last output).
    watch: [Option<Rx>; N_TOPICS],
    /// Per output topic, the newest message read from `watch` before the takeover.
    newest: [Option<Msg>; N_TOPICS],
}

/// Reads what watching receiver `w` holds of the active instance's messages, noting the
/// newest index in `before` (published already: a twin that takes over sends only later
/// ones), and hands each to `each`.
fn read_watch(w: &Rx, before: &mut Option<u64>, mut each: impl FnMut(Msg)) -> Result<()> {
    while let Some(m) = recv_rx(w)? {
        let k = m.hdr().k;
        *before = Some(before.map_or(k, |b| b.max(k)));
        each(m);
    }
    Ok(())
}

/// Keeps `m` in `newest` when it is a message (not a marker) at least as new.
fn keep_newest(newest: &mut Option<Msg>, m: Msg) {
    let h = m.hdr();
    let marker = h.is_warmup() || h.is_end() || h.is_absent();
    if !marker && newest.is_none_or(|n| h.k >= n.hdr().k) {
        *newest = Some(m);
    }
}

impl Shadow {
    fn new(
        lease: Lease,
        own: Lease,
        topics: &DriveTopics,
        sent: &[bool; N_TOPICS],
    ) -> Result<Self> {
        let mut watch: [Option<Rx>; N_TOPICS] = Default::default();
        for t in TopicId::ALL {
            if sent[t.index()] {
                watch[t.index()] = Some(rx_of(topics, t, Wait::Polled, 4)?);
            }
        }
        Ok(Self {
            lease,
            own,
            watch,
            newest: [None; N_TOPICS],
        })
    }
}

impl BusTransport {
    fn open(
        topics: &DriveTopics,
        wait: &[Wait; N_TOPICS],
        sent: &[bool; N_TOPICS],
        poke: &[TopicId],
        recorder: bool,
    ) -> Result<Self> {
        const BUF: usize = 64;
        let mut rx: [Option<Rx>; N_TOPICS] = Default::default();
        let mut tx: [Option<Tx>; N_TOPICS] = Default::default();
        for t in TopicId::ALL {
            let i = t.index();
            let w = wait[i];
            if w != Wait::None {
                let buf = match t {
                    TopicId::Meas | TopicId::Est => BUF,
                    _ => 16,
                };
                rx[i] = Some(rx_of(topics, t, w, buf)?);
            }
            if sent[i] {
                tx[i] = Some(match t {
                    TopicId::Meas => Tx::Meas(topics.meas.sender()?),
                    TopicId::Est => Tx::Est(topics.est.sender()?),
                    TopicId::Iref => Tx::Iref(topics.iref.sender()?),
                    TopicId::Cmd => Tx::Cmd(topics.cmd.sender()?),
                    TopicId::Wref => Tx::Wref(topics.wref.sender()?),
                    TopicId::Truth => Tx::Truth(topics.truth.sender()?),
                });
            }
        }
        let mut pokers = Vec::new();
        for &t in poke {
            pokers.push((
                t,
                match t {
                    TopicId::Meas => topics.meas.poker()?,
                    TopicId::Est => topics.est.poker()?,
                    TopicId::Iref => topics.iref.poker()?,
                    TopicId::Cmd => topics.cmd.poker()?,
                    TopicId::Wref => topics.wref.poker()?,
                    TopicId::Truth => topics.truth.poker()?,
                },
            ));
        }
        let rec = if recorder {
            Some(topics.rec.receiver(16)?)
        } else {
            None
        };
        Ok(Self {
            decim: [0; N_TOPICS],
            rx,
            tx,
            pokers,
            rec,
            status: Vec::new(),
            shadow: None,
            lease: None,
            life: None,
            producer: [None; N_TOPICS],
            before: [None; N_TOPICS],
            retired: None,
            inherited: [None; N_TOPICS],
        })
    }

    /// A standby twin's check at each output: false while the active instance lives. At the
    /// first call after its death the twin takes the lease, notes the newest index its
    /// predecessor published per topic, and drops its watching receivers (a bus call, once
    /// per takeover, as a rejoin's `close`).
    #[inline]
    fn active(&mut self) -> Result<bool> {
        let Some(sh) = self.shadow.as_mut() else {
            return Ok(true);
        };
        if !sh.lease.try_take() {
            return Ok(false);
        }
        let Shadow {
            lease,
            mut own,
            watch,
            mut newest,
        } = self.shadow.take().expect("checked above");
        own.release();
        for (i, w) in watch.iter().enumerate() {
            if let Some(w) = w {
                read_watch(w, &mut self.before[i], |m| keep_newest(&mut newest[i], m))?;
            }
        }
        self.inherited = newest;
        // A predecessor killed between a send and its wake-up left that message unannounced:
        // its readers would sleep through it (a decimated reader for a whole period). Wake
        // them for the newest message it sent; a reader that already has it drains nothing.
        for (i, b) in self.before.iter().enumerate() {
            if let (Some(b), Some(t)) = (b, &self.tx[i]) {
                wake_tx(t, self.wakes_decimated(i, *b))?;
            }
        }
        // The watching receivers stay until the host ends: dropping a subscriber unmaps its
        // publishers' segments, about half a millisecond here at the drive's priority, in the
        // sample of the takeover. Each costs the publisher one more delivery per message.
        self.retired = Some(watch);
        self.lease = Some(lease);
        Ok(true)
    }

    /// Whether sample `k` of topic `i` wakes its decimated receivers: it is one they step.
    #[inline]
    fn wakes_decimated(&self, i: usize, k: u64) -> bool {
        self.decim[i] > 0 && k.is_multiple_of(self.decim[i])
    }

    fn connect(&self) -> Result<()> {
        let watched = self.shadow.iter().flat_map(|s| s.watch.iter().flatten());
        for r in self.rx.iter().flatten().chain(watched) {
            match r {
                Rx::Meas(r) => r.connect()?,
                Rx::Est(r) => r.connect()?,
                Rx::Iref(r) => r.connect()?,
                Rx::Cmd(r) => r.connect()?,
                Rx::Wref(r) => r.connect()?,
                Rx::Truth(r) => r.connect()?,
            }
        }
        for t in self.tx.iter().flatten() {
            match t {
                Tx::Meas(t) => t.connect()?,
                Tx::Est(t) => t.connect()?,
                Tx::Iref(t) => t.connect()?,
                Tx::Cmd(t) => t.connect()?,
                Tx::Wref(t) => t.connect()?,
                Tx::Truth(t) => t.connect()?,
            }
        }
        Ok(())
    }
}

impl Transport for BusTransport {
    #[inline]
    fn send(&mut self, msg: &Msg) -> Result<()> {
        let i = msg.topic().index();
        let h = msg.hdr();
        if !self.active()? || self.before[i].is_some_and(|b| h.k <= b) {
            return Ok(());
        }
        // The decimated receivers wake at the samples they step and at every marker.
        let d =
            self.wakes_decimated(i, h.k) || (self.decim[i] > 0 && (h.is_end() || h.is_warmup()));
        match (&self.tx[i], msg) {
            (Some(Tx::Meas(t)), Msg::Meas(m)) => t.send_waking(*m, d),
            (Some(Tx::Est(t)), Msg::Est(m)) => t.send_waking(*m, d),
            (Some(Tx::Iref(t)), Msg::Iref(m)) => t.send_waking(*m, d),
            (Some(Tx::Cmd(t)), Msg::Cmd(m)) => t.send_waking(*m, d),
            (Some(Tx::Wref(t)), Msg::Wref(m)) => t.send_waking(*m, d),
            (Some(Tx::Truth(t)), Msg::Truth(m)) => t.send_waking(*m, d),
            _ => Ok(()),
        }
    }

    #[inline]
    fn try_recv(&mut self, topic: TopicId) -> Result<Option<Msg>> {
        match &self.rx[topic.index()] {
            Some(r) => recv_rx(r),
            None => Ok(None),
        }
    }

    fn close(&mut self, topic: TopicId) {
        // Dropping the subscriber unmaps its publishers' segments and removes its port: a
        // bus call, made once per restart (see `Transport::close`).
        self.rx[topic.index()] = None;
    }

    #[inline]
    fn notified_ns(&mut self, topic: TopicId) -> u64 {
        match &self.rx[topic.index()] {
            Some(Rx::Meas(r)) => r.notified_ns(),
            Some(Rx::Est(r)) => r.notified_ns(),
            Some(Rx::Iref(r)) => r.notified_ns(),
            Some(Rx::Cmd(r)) => r.notified_ns(),
            Some(Rx::Wref(r)) => r.notified_ns(),
            Some(Rx::Truth(r)) => r.notified_ns(),
            None => 0,
        }
    }

    #[inline]
    fn pending(&mut self, topic: TopicId) -> Result<bool> {
        Ok(match &self.rx[topic.index()] {
            Some(Rx::Meas(r)) => !r.is_empty()?,
            Some(Rx::Est(r)) => !r.is_empty()?,
            Some(Rx::Iref(r)) => !r.is_empty()?,
            Some(Rx::Cmd(r)) => !r.is_empty()?,
            Some(Rx::Wref(r)) => !r.is_empty()?,
            Some(Rx::Truth(r)) => !r.is_empty()?,
            None => false,
        })
    }

    #[inline]
    fn wait(&mut self, topic: TopicId, timeout: Duration) -> Result<()> {
        match &self.rx[topic.index()] {
            Some(Rx::Meas(r)) => r.wait(timeout),
            Some(Rx::Est(r)) => r.wait(timeout),
            Some(Rx::Iref(r)) => r.wait(timeout),
            Some(Rx::Cmd(r)) => r.wait(timeout),
            Some(Rx::Wref(r)) => r.wait(timeout),
            Some(Rx::Truth(r)) => r.wait(timeout),
            None => {
                std::thread::sleep(timeout.min(bus::POLL_SLEEP));
                Ok(())
            }
        }
    }

    #[inline]
    fn producer_up(&self, topic: TopicId) -> bool {
        match (&self.life, self.producer[topic.index()]) {
            (Some(life), Some(p)) => life.up(p),
            _ => true,
        }
    }

    fn twin_newest(&mut self, topic: TopicId) -> Result<Option<Msg>> {
        let i = topic.index();
        let Some(sh) = self.shadow.as_mut() else {
            return Ok(self.inherited[i]);
        };
        if let Some(w) = &sh.watch[i] {
            let newest = &mut sh.newest[i];
            read_watch(w, &mut self.before[i], |m| keep_newest(newest, m))?;
        }
        Ok(sh.newest[i])
    }

    fn twin_standing_by(&mut self) -> Result<bool> {
        Ok(self.shadow.is_some() && !self.active()?)
    }

    fn poke(&mut self, topic: TopicId) -> Result<()> {
        if self.shadow.is_some() {
            return Ok(());
        }
        for (t, p) in &self.pokers {
            if *t == topic {
                p.poke()?;
            }
        }
        Ok(())
    }

    fn recorder_progress(&mut self) -> Result<Option<u64>> {
        let Some(rx) = &self.rec else { return Ok(None) };
        let mut newest = 0;
        while let Some(d) = rx.try_recv()? {
            newest = newest.max(d);
        }
        Ok(Some(newest))
    }

    fn wait_recorder(&mut self, timeout: Duration) -> Result<()> {
        match &self.rec {
            Some(rx) => rx.wait(timeout),
            None => Ok(()),
        }
    }

    #[inline]
    fn status(
        &mut self,
        i: usize,
        k: u64,
        c: &Counters,
        h: &StageHists,
        cycle: Option<&CycleMonitor>,
        last: bool,
    ) -> Result<()> {
        if self.shadow.is_some() {
            return Ok(());
        }
        match self.status.get_mut(i) {
            Some(s) => s.tick(k, c, h, cycle, last),
            None => Ok(()),
        }
    }
}

// ------------------------------------------------------------------ status and statistics

/// Live status for the supervisor (and through it `drivelab monitor`), published ten times
/// per simulated second. The supervisor subscribes before the hosts start and the publisher
/// connects before the loop, so the loop only copies a message into a loaned sample.
pub struct StatusPublisher {
    _topic: Plain<ServiceStatus>,
    tx: PlainSender<ServiceStatus>,
    st: ServiceStatus,
    every: u64,
    next_k: u64,
}

impl StatusPublisher {
    /// Opens the status topic for the stage at index `stage` of the topology (None: the
    /// view has no row for it, nothing is published) of scenario `sc`.
    pub fn new(
        node: &iceoryx2::prelude::Node<iceoryx2::prelude::ipc::Service>,
        stage: Option<usize>,
        sc: &Scenario,
    ) -> Result<Self> {
        let topic = open_plain::<ServiceStatus>(node, TOPIC_STATUS, 16, 0)?;
        let tx = PlainSender::new(&topic)?;
        let idx = stage
            .filter(|&i| i < crate::telemetry::MAX_STAGES)
            .map_or(u32::MAX, |i| i as u32);
        let st = ServiceStatus {
            service: idx,
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

    /// Publishes a status if sample `k` has reached the next tenth of a simulated second,
    /// or `now`.
    #[inline]
    pub fn tick(
        &mut self,
        k: u64,
        c: &Counters,
        h: &StageHists,
        cycle: Option<&CycleMonitor>,
        now: bool,
    ) -> Result<()> {
        if (k < self.next_k && !now) || self.st.service == u32::MAX {
            return Ok(());
        }
        self.next_k = (k / self.every + 1) * self.every;
        let st = &mut self.st;
        st.hdr.k = k;
        st.hdr.t_pub_ns = crate::rt::now_ns();
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

/// Statistics file of one stage.
#[derive(Debug, Serialize)]
pub struct StageStats<'a> {
    /// Stage name.
    pub service: &'a str,
    /// The process that hosted it.
    pub process: &'a str,
    /// Process id.
    pub pid: u32,
    /// RT setup report of the process.
    pub rt: &'a RtReport,
    /// CPU time (user + system) of the whole process at its end, s.
    pub process_cpu_s: f64,
    /// Context switches of the whole process at its end: voluntary (it waited) and
    /// involuntary (it was preempted), the scheduler's view of its wake-ups.
    pub process_context_switches: ContextSwitches,
    /// CPU time (user + system) of the whole process from the start of its run (after its
    /// set-up and the launcher's GO) to its end, s.
    pub run_cpu_s: f64,
    /// Context switches of the whole process over the same span.
    pub run_context_switches: ContextSwitches,
    /// The system calls the process's loop made at drivelab's own call sites, from its start
    /// to its end (`rt::syscalls`: its sleeps, futex waits and wakes; not iceoryx2's own).
    pub process_syscalls: u64,
    /// With `--audit-syscalls`: the system calls the process's loop made beyond its wait and
    /// wakes, by name (empty: none).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub stray_syscalls: Option<&'a std::collections::BTreeMap<String, u64>>,
    /// Counters.
    pub counters: Counters,
    /// The stage's own diagnostics.
    pub diagnostics: std::collections::BTreeMap<&'static str, u64>,
    /// What the stage saw of each `[[inject]]` fault, in the scenario's order (empty without
    /// any). A restarted process starts these again from zero.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub inject: Vec<crate::inject::InjectObs>,
    /// Tail summary of each histogram, µs, keyed `<stage>.<metric>` (and `cycle`).
    pub latency_us: std::collections::BTreeMap<String, crate::timing::Percentiles>,
    /// What the stage warned about, as the host printed it: its configuration
    /// ([`Stage::warnings`], before the run) and its run ([`Stage::exit_warnings`]).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub warnings: Vec<String>,
    /// Source only, real time: its wake-ups at least half a millisecond late, as
    /// [deadline, lateness] in ns on CLOCK_MONOTONIC (the first 4096), and how many there
    /// were in all (`timing::StallLog`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub stalls: Option<Stalls<'a>>,
    /// The process's start-up, ms per phase in order (scenario, stages, node, topics,
    /// ports, connect, rt), from its `main` to READY.
    pub startup_ms: &'a [(&'static str, f64)],
}

/// The source's stalls in its `stats.json`.
#[derive(Debug, Serialize)]
pub struct Stalls<'a> {
    /// Every stall.
    pub count: u64,
    /// The first of them, [deadline, lateness] ns.
    pub log: &'a [(u64, u64)],
    /// Deadline misses decided at a wake-up inside a stall.
    pub misses: u64,
}

/// Writes `<out>/<stage>.stats.json` and one `<key>.hdr` per non-empty histogram for every
/// stage of the host.
fn write_stats<T: Transport>(
    args: &HostArgs,
    process: &str,
    rt: &RtReport,
    host: &Host<T>,
    startup_ms: &[(&'static str, f64)],
    at_run: (f64, ContextSwitches),
    stray_syscalls: Option<&std::collections::BTreeMap<String, u64>>,
) -> Result<()> {
    let Some(dir) = &args.out else { return Ok(()) };
    let diags = host.diagnostics();
    let (process_cpu_s, process_context_switches) = usage(libc::RUSAGE_SELF);
    let run_cpu_s = (process_cpu_s - at_run.0).max(0.0);
    let run_context_switches = process_context_switches.since(at_run.1);
    for (i, h) in host.stages.iter().enumerate() {
        let name = h.stage.name();
        let source = i == 0 && host.is_source();
        let mut counters = h.counters;
        if !source {
            counters.late_outputs = h.hists.late.misses;
            counters.longest_late_run = h.hists.late.longest_run;
        }
        let mut latency_us = std::collections::BTreeMap::new();
        let cycle: Option<&LatencyHist> = source.then_some(&host.cycle.cycle);
        for hist in h.hists.all().into_iter().chain(cycle) {
            if hist.is_empty() {
                continue;
            }
            let key = if hist.name == "cycle" {
                "cycle".to_string()
            } else {
                format!("{name}.{}", hist.name)
            };
            hist.write_v2(&dir.join(format!("{key}.hdr")))?;
            latency_us.insert(key, hist.percentiles());
        }
        let stats = StageStats {
            service: name,
            process,
            pid: std::process::id(),
            rt,
            process_cpu_s,
            process_context_switches,
            run_cpu_s,
            run_context_switches,
            process_syscalls: crate::rt::syscalls(),
            stray_syscalls,
            counters,
            diagnostics: diags[i].1.iter().copied().collect(),
            inject: h.inject.clone(),
            latency_us,
            warnings: h
                .stage
                .warnings()
                .into_iter()
                .chain(h.stage.exit_warnings())
                .collect(),
            stalls: (source && args.clock == BusClock::Realtime).then(|| Stalls {
                count: host.stalls.count,
                log: host.stalls.entries(),
                misses: host.stalls.misses,
            }),
            startup_ms,
        };
        let p = dir.join(format!("{name}.stats.json"));
        crate::files::write(&p, serde_json::to_vec_pretty(&stats)?)
            .with_context(|| format!("write {}", p.display()))?;
    }
    Ok(())
}

/// Context switches of a process (getrusage).
#[derive(Debug, Clone, Copy, Serialize)]
pub struct ContextSwitches {
    /// It gave up the CPU (waited).
    pub voluntary: u64,
    /// It was preempted.
    pub involuntary: u64,
}

impl ContextSwitches {
    /// The switches since `earlier` (a reading of the same process).
    fn since(self, earlier: Self) -> Self {
        Self {
            voluntary: self.voluntary.saturating_sub(earlier.voluntary),
            involuntary: self.involuntary.saturating_sub(earlier.involuntary),
        }
    }
}

/// CPU time (user + system, s) and context switches so far of this process (`who` =
/// `libc::RUSAGE_SELF`) or of all its children that have ended and been reaped
/// (`libc::RUSAGE_CHILDREN`).
pub fn usage(who: libc::c_int) -> (f64, ContextSwitches) {
    // SAFETY: getrusage writes into the zero-initialised struct we pass; an invalid `who`
    // makes it fail with EINVAL and leave the struct zero.
    let ru = unsafe {
        let mut ru: libc::rusage = std::mem::zeroed();
        libc::getrusage(who, &mut ru);
        ru
    };
    let tv = |t: libc::timeval| t.tv_sec as f64 + t.tv_usec as f64 * 1e-6;
    (
        tv(ru.ru_utime) + tv(ru.ru_stime),
        ContextSwitches {
            voluntary: ru.ru_nvcsw.max(0) as u64,
            involuntary: ru.ru_nivcsw.max(0) as u64,
        },
    )
}

/// Reads a rejoin file (`--rejoin-from`): the source's true state (required when `source`)
/// and the own last output on each topic of `own` that the file has (a stage that finds none
/// starts fresh). A key this process has no use for is an error: the file is not its own.
fn rejoin_state(path: &std::path::Path, source: bool, own: &[TopicId]) -> Result<Vec<Msg>> {
    let text = std::fs::read_to_string(path).with_context(|| format!("read {}", path.display()))?;
    let v: serde_json::Value = serde_json::from_str(&text)
        .with_context(|| format!("rejoin file {}: not JSON", path.display()))?;
    let Some(obj) = v.as_object() else {
        bail!("rejoin file {}: not a JSON object", path.display());
    };
    let mut msgs = Vec::new();
    if source {
        msgs.push(Msg::Truth(truth_from_json(&v)?));
    }
    for (key, val) in obj {
        if key == TopicId::Wref.name() && own.contains(&TopicId::Wref) {
            msgs.push(Msg::Wref(speed_ref_from_json(val)?));
        } else if !source {
            bail!(
                "rejoin file {}: '{key}' is not the own output of a stage of this process that reads it back",
                path.display()
            );
        }
    }
    Ok(msgs)
}

/// An outer loop's speed reference as JSON (the supervisor hands the last one to the
/// restarted loop: its own-output rejoin slot).
pub fn speed_ref_to_json(w: &SpeedRef) -> serde_json::Value {
    serde_json::json!({
        "k": w.hdr.k, "t_sample_ns": w.hdr.t_sample_ns,
        "omega_ref": w.omega_ref, "theta_m_ref": w.theta_m_ref, "theta_m": w.theta_m,
    })
}

/// A number of a rejoin file's message `what` ("" for the plant's state, "wref: " for an
/// outer loop's reference).
fn json_number(v: &serde_json::Value, what: &str, key: &str) -> Result<f64> {
    v[key]
        .as_f64()
        .ok_or_else(|| anyhow!("rejoin file: {what}'{key}' missing or not a number"))
}

/// The header (`k`, `t_sample_ns`) of a rejoin file's message `what` (as [`json_number`]).
fn json_header(v: &serde_json::Value, what: &str) -> Result<Header> {
    Ok(Header {
        k: v["k"]
            .as_u64()
            .ok_or_else(|| anyhow!("rejoin file: {what}'k' missing"))?,
        t_sample_ns: v["t_sample_ns"].as_u64().unwrap_or(0),
        ..Default::default()
    })
}

/// Reads a speed reference written by [`speed_ref_to_json`].
pub fn speed_ref_from_json(v: &serde_json::Value) -> Result<SpeedRef> {
    let f = |key: &str| json_number(v, "wref: ", key);
    let mut w = SpeedRef {
        hdr: json_header(v, "wref: ")?,
        ..Default::default()
    };
    w.omega_ref = f("omega_ref")?;
    w.theta_m_ref = f("theta_m_ref")?;
    w.theta_m = f("theta_m")?;
    if !w.is_finite() {
        bail!("rejoin file: wref: non-finite values");
    }
    Ok(w)
}

/// The plant's last true state as JSON (the supervisor hands it to a restarted source).
pub fn truth_to_json(m: &PlantTruth) -> serde_json::Value {
    serde_json::json!({
        "k": m.hdr.k, "t_sample_ns": m.hdr.t_sample_ns,
        "i_dq": m.i_dq, "omega_m": m.omega_m, "theta_e": m.theta_e, "theta_m": m.theta_m,
        "u_dq_applied": m.u_dq_applied, "u_ab_applied": m.u_ab_applied, "t_load": m.t_load,
        "theta_m_enc": m.theta_m_enc,
    })
}

/// Reads a state written by [`truth_to_json`].
pub fn truth_from_json(v: &serde_json::Value) -> Result<PlantTruth> {
    let f = |key: &str| json_number(v, "", key);
    let a2 = |key: &str| -> Result<[f64; 2]> {
        match v[key]
            .as_array()
            .map(|a| a.iter().map(|x| x.as_f64()).collect::<Vec<_>>())
        {
            Some(a) if a.len() == 2 && a.iter().all(Option::is_some) => {
                Ok([a[0].unwrap_or_default(), a[1].unwrap_or_default()])
            }
            _ => Err(anyhow!("rejoin file: '{key}' must be two numbers")),
        }
    };
    let mut m = PlantTruth {
        hdr: json_header(v, "")?,
        ..Default::default()
    };
    m.i_dq = a2("i_dq")?;
    m.omega_m = f("omega_m")?;
    m.theta_e = f("theta_e")?;
    m.theta_m = f("theta_m")?;
    m.u_dq_applied = a2("u_dq_applied")?;
    m.u_ab_applied = a2("u_ab_applied")?;
    m.t_load = f("t_load")?;
    m.theta_m_enc = f("theta_m_enc")?;
    if !m.is_finite() {
        return Err(anyhow!("rejoin file: non-finite values"));
    }
    Ok(m)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_rejoin_file_gives_an_outer_loop_its_own_last_output_and_nothing_else() {
        let dir = std::env::temp_dir().join(format!("drivelab-rejoin-file-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let file = |name: &str, text: &str| {
            let p = dir.join(name);
            std::fs::write(&p, text).unwrap();
            p
        };
        let w = SpeedRef {
            hdr: Header {
                k: 990,
                t_sample_ns: 5,
                ..Default::default()
            },
            omega_ref: 100.0,
            theta_m_ref: 12.5,
            theta_m: 8.6,
        };
        let text = serde_json::json!({ "wref": speed_ref_to_json(&w) }).to_string();
        let ok = file("ok.json", &text);
        assert_eq!(
            rejoin_state(&ok, false, &[TopicId::Wref]).unwrap(),
            [Msg::Wref(w)]
        );
        // A process whose stages do not read `wref` back: not its file.
        let e = rejoin_state(&ok, false, &[]).unwrap_err().to_string();
        assert!(
            e.ends_with(
                "'wref' is not the own output of a stage of this process that reads it back"
            ),
            "{e}"
        );
        for (text, want) in [
            ("[1]", "not a JSON object"),
            ("{", "not JSON"),
            (
                r#"{"wref": {"k": 1, "omega_ref": 1.0, "theta_m_ref": 0.0}}"#,
                "rejoin file: wref: 'theta_m' missing or not a number",
            ),
        ] {
            let p = file("bad.json", text);
            let e = rejoin_state(&p, false, &[TopicId::Wref]).unwrap_err();
            let e = crate::text::error_text(&e);
            assert!(e.contains(want) && !e.contains('\n'), "{text}: {e}");
        }
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn a_users_stage_may_not_take_the_plants_name_nor_one_twice() {
        fn any(sc: &Scenario) -> Result<Box<dyn Stage>> {
            crate::stages::builtin("speed-loop", sc).ok_or_else(|| anyhow!("none"))
        }
        check_user_names(&[("ramp-ref", any as StageFactory)]).unwrap();
        // A replacement of a built-in stage other than the plant.
        check_user_names(&[("ramp-ref", any as StageFactory), ("speed-loop", any)]).unwrap();
        let e = check_user_names(&[("ramp-ref", any as StageFactory), ("plant", any)])
            .unwrap_err()
            .to_string();
        assert_eq!(
            e,
            "a user's stage may not be called 'plant': the built-in plant cannot be replaced (a user's stage may replace observer, current-loop, speed-loop); give it another name"
        );
        let e = check_user_names(&[("mine", any as StageFactory), ("mine", any)])
            .unwrap_err()
            .to_string();
        assert_eq!(e, "the user's stage 'mine' is registered twice");
        // Registered under one name, calling itself by another: the launcher would take it
        // for the built-in of that name (or for none).
        let e = make_stage(
            "ramp-ref",
            &kyslan_pi(),
            &[("ramp-ref", any as StageFactory)],
        )
        .err()
        .unwrap()
        .to_string();
        assert_eq!(
            e,
            "the user's stage registered as 'ramp-ref' calls itself 'speed-loop' (Stage::name): the two must be the same"
        );
    }

    /// The shipped kyslan-pi scenario.
    fn kyslan_pi() -> Scenario {
        let text = std::fs::read_to_string(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../../scenarios/kyslan-pi.toml"
        ))
        .unwrap();
        Scenario::from_toml(&text, "kyslan-pi.toml").unwrap()
    }

    fn plan(topology: &str) -> TopologyPlan {
        let sc = kyslan_pi();
        let (file, _) = crate::topology::load(topology).unwrap();
        let r = crate::topology::resolve(&file.process, &mut |_, stage| {
            crate::topology::builtin_info(&sc, stage).ok_or_else(|| stage.to_string())
        })
        .unwrap();
        TopologyPlan::from_resolved(&r)
    }

    /// The active instance dies between sending estimate 10 and waking its readers (a
    /// thread that sends without waking and ends holding the lease, as a SIGKILL between
    /// the two would leave it). Its twin takes the lease at its first output and wakes the
    /// readers for that estimate, the decimated ones too (10 is a multiple of the speed
    /// loop's divider): without it the speed loop would sleep through sample 10.
    #[test]
    fn a_twin_that_takes_over_wakes_the_readers_its_dead_predecessor_did_not() {
        let bus = format!("svtw{}", std::process::id());
        let _cleanup = bus::CleanupOnDrop(bus.clone());
        let life = std::sync::Arc::new(Life::create(&bus, 1).unwrap());
        let node = bus::node(&bus, "twin").unwrap();
        let topics = DriveTopics::open_for(&node, bus::WakeKind::Futex, &bus, 2).unwrap();
        let reader = topics.est.receiver(8).unwrap();
        let slow_reader = topics.est.decimated_receiver(8).unwrap();
        // The twin as `serve` sets it up: it sends estimates and watches its own topic.
        let mut sent = [false; N_TOPICS];
        sent[TopicId::Est.index()] = true;
        let mut tr =
            BusTransport::open(&topics, &[Wait::None; N_TOPICS], &sent, &[], false).unwrap();
        tr.decim[TopicId::Est.index()] = 10;
        let mut own = life.lease(0, LifeRole::Standby).unwrap();
        own.hold().unwrap();
        let lease = life.lease(0, LifeRole::Active).unwrap();
        tr.shadow = Some(Shadow::new(lease, own, &topics, &sent).unwrap());
        tr.connect().unwrap();
        let (life2, bus2) = (life.clone(), bus.clone());
        std::thread::spawn(move || {
            let node = bus::node(&bus2, "active").unwrap();
            let topics = DriveTopics::open_for(&node, bus::WakeKind::Futex, &bus2, 2).unwrap();
            let mut lease = life2.lease(0, LifeRole::Active).unwrap();
            lease.hold().unwrap();
            let tx = topics.est.sender().unwrap();
            tx.connect().unwrap();
            let mut est = Estimate::default();
            est.hdr.k = 10;
            tx.publish(est).unwrap();
            // Dies here: no wake-up, the lease still held, nothing dropped.
            std::mem::forget((lease, tx, topics, node));
        })
        .join()
        .unwrap();
        assert!(!reader.is_empty().unwrap(), "estimate 10 did not arrive");
        assert_eq!(
            (reader.notified_ns(), slow_reader.notified_ns()),
            (0, 0),
            "woken before the takeover"
        );
        assert!(
            tr.active().unwrap(),
            "the twin did not take over from a dead holder"
        );
        assert_eq!(tr.before[TopicId::Est.index()], Some(10));
        assert_ne!(reader.notified_ns(), 0, "readers not woken at the takeover");
        assert_ne!(
            slow_reader.notified_ns(),
            0,
            "decimated readers not woken for sample 10"
        );
    }

    #[test]
    fn only_a_slower_stage_of_another_process_sleeps_through_samples() {
        // kyslan-pi: the speed loop steps every 10th estimate, in its own process.
        let d = decimation(&plan("four-process"));
        let mut want = [0u64; N_TOPICS];
        want[TopicId::Est.index()] = 10;
        assert_eq!(d, want);
        // With the observer in its process, nothing crosses at a lower rate.
        assert_eq!(decimation(&plan("two-process")), [0; N_TOPICS]);
        assert_eq!(decimation(&plan("one-process")), [0; N_TOPICS]);
    }

    /// The bus side of the real-time loop allocates one block per message it sends and
    /// nothing else: the iceoryx2 ports and futex words that a plant and a controller use
    /// every sample (send and wake, wait, drain, the pokes, the status for the supervisor),
    /// 200 samples after a warm-up, over a real bus of this process's own. The block is
    /// iceoryx2 0.10's own: each loan of a sample makes a reference count for it (`Rc`, 48
    /// bytes), freed when that sample is sent; no call of ours allocates. Every block is
    /// freed within the window, so the heap does not grow (docs/architecture.md, "Real-time
    /// rules"). The host around the bus is counted in `host::tests`.
    #[test]
    fn the_bus_side_allocates_one_block_per_message_sent_and_frees_it() {
        let bus = format!("bal{}", std::process::id());
        let _cleanup = bus::CleanupOnDrop(bus.clone());
        // A status every 20 samples (a tenth of a simulated second), ten in the count.
        let mut sc = kyslan_pi();
        sc.rates.sample_hz = 200.0;
        let node = bus::node(&bus, "alloc").unwrap();
        let topics = DriveTopics::open_with(&node, bus::WakeKind::Futex, &bus).unwrap();
        let waits = |on: &[(TopicId, Wait)]| {
            let mut w = [Wait::None; N_TOPICS];
            for &(t, how) in on {
                w[t.index()] = how;
            }
            w
        };
        let sends = |on: &[TopicId]| {
            let mut s = [false; N_TOPICS];
            for t in on {
                s[t.index()] = true;
            }
            s
        };
        // The plant: sends measurements and the truth, polls commands, pokes the observer's
        // trigger. The controller: woken by measurements, sends commands.
        let mut plant = BusTransport::open(
            &topics,
            &waits(&[(TopicId::Cmd, Wait::Polled)]),
            &sends(&[TopicId::Meas, TopicId::Truth]),
            &[TopicId::Meas],
            false,
        )
        .unwrap();
        plant
            .status
            .push(StatusPublisher::new(&node, Some(0), &sc).unwrap());
        let mut ctrl = BusTransport::open(
            &topics,
            &waits(&[(TopicId::Meas, Wait::Woken)]),
            &sends(&[TopicId::Cmd]),
            &[],
            false,
        )
        .unwrap();
        ctrl.status
            .push(StatusPublisher::new(&node, Some(1), &sc).unwrap());
        let status_topic = open_plain::<ServiceStatus>(&node, TOPIC_STATUS, 16, 0).unwrap();
        let supervisor = crate::telemetry::PlainReceiver::new(&status_topic, 16).unwrap();
        plant.connect().unwrap();
        ctrl.connect().unwrap();
        let counters = Counters::default();
        let hists = StageHists::new(true, 100_000);
        let hdr = |k: u64| Header {
            k,
            t_sample_ns: k * 100_000,
            ..Default::default()
        };
        let mut sample = |k: u64| {
            let (got, allocations, frees) =
                crate::alloc_count::allocations_and_frees_during(|| {
                    plant
                        .send(&Msg::Meas(Measurement {
                            hdr: hdr(k),
                            ..Default::default()
                        }))
                        .unwrap();
                    plant
                        .send(&Msg::Truth(PlantTruth {
                            hdr: hdr(k),
                            ..Default::default()
                        }))
                        .unwrap();
                    ctrl.wait(TopicId::Meas, Duration::from_millis(50)).unwrap();
                    let _ = ctrl.notified_ns(TopicId::Meas);
                    let mut got = None;
                    while ctrl.pending(TopicId::Meas).unwrap() {
                        got = ctrl.try_recv(TopicId::Meas).unwrap().map(|m| m.hdr().k);
                    }
                    ctrl.send(&Msg::Cmd(VoltageCommand {
                        hdr: hdr(k),
                        ..Default::default()
                    }))
                    .unwrap();
                    ctrl.status(0, k, &counters, &hists, None, false).unwrap();
                    let cmd = plant.try_recv(TopicId::Cmd).unwrap().map(|m| m.hdr().k);
                    if k.is_multiple_of(10) {
                        plant.poke(TopicId::Meas).unwrap();
                    }
                    plant.status(0, k, &counters, &hists, None, false).unwrap();
                    (got, cmd)
                });
            // The supervisor's side, in its own thread in a drive: not counted.
            let mut statuses = 0;
            while supervisor.try_recv().unwrap().is_some() {
                statuses += 1;
            }
            assert_eq!(
                got,
                (Some(k), Some(k)),
                "sample {k}: measurement and command"
            );
            [allocations, frees, statuses]
        };
        for k in 0..50 {
            sample(k);
        }
        let [allocations, frees, statuses] = (50..250)
            .map(&mut sample)
            .fold([0; 3], |a, d| [a[0] + d[0], a[1] + d[1], a[2] + d[2]]);
        assert_eq!(statuses, 20, "two stages' statuses every 20 samples");
        // Three messages a sample (measurement, truth, command) and the statuses.
        let sent = 3 * 200 + statuses;
        assert_eq!(
            (allocations, frees),
            (sent, sent),
            "allocations and frees in 200 samples on the bus, {sent} messages sent"
        );
        drop((plant, ctrl, supervisor, status_topic, topics, node));
    }
}
