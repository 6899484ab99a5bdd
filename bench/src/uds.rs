//! The Unix-socket chain: plant, observer, current loop and speed loop as four processes that
//! exchange the bus messages ([`drivelab_runtime::messages`], sent as their bytes) over Unix
//! domain datagram sockets in a private directory. Each process runs its built-in stage on
//! the same generic host as the iceoryx2 drive (`drivelab_runtime::host::Host`, the
//! four-process topology); only the transport differs ([`UdsTransport`]), so the two chains
//! differ in nothing but how a message travels.
//!
//! Sockets (one per receiver and input, so a receiver can wait on exactly the input that wakes
//! it, as with iceoryx2's notified vs polled subscribers):
//!
//! | socket | bound by | written by |
//! |---|---|---|
//! | `plant.cmd` | plant | current loop |
//! | `observer.meas` | observer | plant |
//! | `current-loop.meas` | current loop | plant |
//! | `current-loop.est` | current loop | observer |
//! | `current-loop.iref` | current loop | speed loop |
//! | `speed-loop.est` | speed loop | observer |
//!
//! Start-up: every node binds its sockets, then connects to its peers (retrying until they
//! exist), sets up real time and prints `READY`. The host of the plant then sends its warm-up
//! messages through the whole chain before t_0, so the clock starts only when every socket
//! of the chain is bound and connected; at the end it sends the end marker, which every host
//! forwards before it exits. SIGTERM/SIGINT stop a node (the plant still sends the end marker
//! and writes its results).

use crate::children::{log_tail, Kids};
use crate::wire::{Recv, Rx, Sent, Tx, Wire};
use crate::{apply_rt, schedule, NodeSpec};
use crate::{ChainSpec, VariantResult};
use anyhow::{anyhow, bail, Context, Result};
use drivelab_runtime::config::Scenario;
use drivelab_runtime::drive::trace_row;
use drivelab_runtime::host::{Host, HostConfig, Pacing, Transport};
use drivelab_runtime::messages::{
    CurrentRef, Estimate, Measurement, PlantTruth, VoltageCommand, FLAG_SAFE_STATE, FLAG_STALE_CMD,
    FLAG_STALE_INPUT,
};
use drivelab_runtime::service::{install_signal_handlers, stop_flag};
use drivelab_runtime::stage::{Msg, TopicId, N_TOPICS};
use drivelab_runtime::timing::{LatencyHist, MissCounter};
use drivelab_runtime::trace::TraceRow;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};

/// Socket names (files in the socket directory).
const PLANT_CMD: &str = "plant.cmd";
const OBS_MEAS: &str = "observer.meas";
const CL_MEAS: &str = "current-loop.meas";
const CL_EST: &str = "current-loop.est";
const CL_IREF: &str = "current-loop.iref";
const SL_EST: &str = "speed-loop.est";

/// Warm-up messages sent through the chain before sample 0 (as the iceoryx2 plant does).
pub const WARMUP_MESSAGES: u64 = 50;
/// How long a node waits for a peer's socket to appear.
const CONNECT_TIMEOUT: Duration = Duration::from_secs(10);
/// How long a control message (warm-up, end) may wait for room in a full queue.
const CONTROL_TIMEOUT: Duration = Duration::from_secs(1);
/// After the plant has exited, how long the other nodes get to finish before they are killed.
const STRAGGLER_GRACE: Duration = Duration::from_secs(5);

/// The four roles.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Role {
    Plant,
    Observer,
    CurrentLoop,
    SpeedLoop,
}

/// Every role, in start order (downstream first; the plant waits for its peers' sockets).
const ROLES: [Role; 4] = [
    Role::Observer,
    Role::CurrentLoop,
    Role::SpeedLoop,
    Role::Plant,
];

impl Role {
    /// Command-line name.
    pub(crate) fn name(self) -> &'static str {
        match self {
            Role::Plant => "plant",
            Role::Observer => "observer",
            Role::CurrentLoop => "current-loop",
            Role::SpeedLoop => "speed-loop",
        }
    }

    /// Parses a command-line name.
    pub(crate) fn parse(s: &str) -> Result<Self> {
        Ok(match s {
            "plant" => Role::Plant,
            "observer" => Role::Observer,
            "current-loop" => Role::CurrentLoop,
            "speed-loop" => Role::SpeedLoop,
            other => bail!(
                "unknown role '{other}' (expected plant, observer, current-loop or speed-loop)"
            ),
        })
    }
}

/// Counters a node keeps (plain integers: no allocation in the loop).
#[derive(Debug, Clone, Copy, Default, Serialize, Deserialize, PartialEq, Eq)]
pub(crate) struct Counters {
    /// Samples processed (plant: samples run).
    pub samples: u64,
    /// Inputs that were not there (or not the expected index) when needed.
    pub stale_inputs: u64,
    /// Inputs rejected: wrong size, NaN/∞, or an index that went backwards.
    pub rejected_inputs: u64,
    /// Plant: commands that arrived after their deadline (discarded, latency recorded).
    pub late_commands: u64,
    /// Plant: commands flagged by the current loop as computed with a stale reference.
    pub stale_input_commands: u64,
    /// Messages dropped because the receiver's queue was full.
    pub dropped_sends: u64,
    /// Messages not delivered because the receiver was gone.
    pub peer_gone: u64,
}

/// Sends a control message (forwarded warm-up/end marker), waiting a little for room; a gone
/// peer is not an error (it may have finished already).
fn send_control<T: Wire>(tx: &Tx, m: &T) -> Result<()> {
    match tx.send_patiently(m, CONTROL_TIMEOUT) {
        Sent::Ok | Sent::PeerGone | Sent::Full => Ok(()),
        Sent::Err(e) => Err(anyhow!(
            "send to {}: {}",
            tx.peer,
            std::io::Error::from_raw_os_error(e)
        )),
    }
}

fn recv_error(sock: &str, e: i32) -> anyhow::Error {
    anyhow!(
        "receive on {sock}: {}",
        std::io::Error::from_raw_os_error(e)
    )
}

/// Everything one role needs to run (in a process or, in tests, in a thread).
pub(crate) struct RoleCtx<'a> {
    pub role: Role,
    /// Socket directory.
    pub dir: &'a Path,
    pub sc: &'a Scenario,
    /// Plant: seconds of measurement.
    pub seconds: f64,
    pub node: NodeSpec,
    /// `mlockall` (process-wide: only in node processes).
    pub lock_memory: bool,
    pub stop: &'static AtomicBool,
    /// Print `READY` on stdout once bound and connected (node processes).
    pub announce: bool,
    /// Plant: keep the trace rows (tests: determinism across transports).
    pub keep_trace: bool,
    /// Realtime (the bench) or lockstep (tests: every row, whatever the machine's load).
    pub pacing: Pacing,
}

impl RoleCtx<'_> {
    fn stopped(&self) -> bool {
        self.stop.load(Ordering::Relaxed)
    }

    fn bind(&self, name: &str) -> Result<Rx> {
        Rx::bind(&self.dir.join(name)).with_context(|| format!("{}: bind {name}", self.role.name()))
    }

    fn connect(&self, name: &'static str) -> Result<Tx> {
        Tx::connect(&self.dir.join(name), name, CONNECT_TIMEOUT, || {
            self.stopped()
        })
        .with_context(|| self.role.name())
    }

    fn ready(&self) -> Result<String> {
        let rep = apply_rt(self.role.name(), &self.node, self.lock_memory)?;
        if self.announce {
            use std::io::Write;
            let mut out = std::io::stdout().lock();
            writeln!(out, "READY")?;
            out.flush()?;
        }
        Ok(rep.one_line(self.role.name()))
    }
}

/// What the plant measured.
#[derive(Debug)]
pub(crate) struct PlantOutcome {
    pub result: VariantResult,
    pub counters: Counters,
    /// Trace rows k = 0.. up to the first miss or stale-input command (only with keep_trace).
    #[cfg_attr(not(test), allow(dead_code))]
    pub trace: Vec<TraceRow>,
    /// The plant's RT report line.
    pub rt: String,
}

/// Runs one role to its end on the same stage host as the iceoryx2 drive
/// (`drivelab_runtime::host`), over [`UdsTransport`]. The plant returns its measurements,
/// the others None.
pub(crate) fn run_role(ctx: &RoleCtx) -> Result<Option<PlantOutcome>> {
    let name = ctx.role.name();
    let stage = drivelab_runtime::stages::builtin(name, ctx.sc)
        .ok_or_else(|| anyhow!("no built-in stage '{name}'"))?;
    // Every stage in its own process, as in the four-process topology.
    let producers: Vec<(TopicId, u64, bool)> = drivelab_runtime::stages::BUILTIN
        .iter()
        .filter_map(|n| drivelab_runtime::stages::builtin(n, ctx.sc))
        .flat_map(|s| {
            let local = s.name() == name;
            let d = s.divider();
            s.outputs()
                .iter()
                .map(move |t| (*t, d, local))
                .collect::<Vec<_>>()
        })
        .collect();
    let mut tr = UdsTransport::open(ctx)?;
    let source = ctx.role == Role::Plant;
    let n = (ctx.seconds * ctx.sc.rates.sample_hz).round() as u64;
    if source && ctx.keep_trace {
        tr.truths.reserve(n as usize + 1);
        tr.cmds.reserve(n as usize + 1);
    }
    let mut host = Host::new(
        vec![stage],
        &producers,
        tr,
        HostConfig::for_scenario(ctx.sc, ctx.pacing, n),
    );
    let stop = ctx.stop;
    host.stop_when(move || stop.load(Ordering::Relaxed));
    let rt = ctx.ready()?;
    host.run().with_context(|| name)?;
    let h = &host.stages[0];
    let mut c = Counters {
        samples: h.counters.samples,
        stale_inputs: h.counters.stale_inputs,
        rejected_inputs: h.counters.rejected_inputs,
        late_commands: h.counters.late_commands,
        stale_input_commands: host.transport.stale_input_commands,
        dropped_sends: host.transport.dropped_sends,
        peer_gone: host.transport.peer_gone,
    };
    eprintln!(
        "{name}: {} samples, {} stale inputs, {} rejected, {} dropped sends, {} to a gone peer",
        c.samples, c.stale_inputs, c.rejected_inputs, c.dropped_sends, c.peer_gone
    );
    if !source {
        return Ok(None);
    }
    c.samples = host.stages[0].counters.samples;
    let trace = host.transport.trace(ctx.sc.rates.ts());
    let cycle = host.cycle.clone();
    Ok(Some(PlantOutcome {
        result: VariantResult {
            cycle: cycle.cycle,
            lateness: std::mem::replace(
                &mut host.stages[0].hists.wake,
                LatencyHist::new("lateness"),
            ),
            samples: c.samples,
            misses: cycle.misses,
            cpu_run_ns: None,
            deadline_lateness: Vec::new(),
            // This role's own calls; the chain runner adds the other roles'.
            syscalls: Some(drivelab_runtime::rt::syscalls()),
            stalls: None,
        },
        counters: c,
        trace,
        rt,
    }))
}

/// The Unix datagram sockets as a [`Transport`]: one bound socket per (receiving role,
/// input topic), one connected sender per (topic, receiver). A blocking wait keeps the
/// message it received for the next `try_recv`.
pub(crate) struct UdsTransport {
    rx: [Option<(Rx, &'static str)>; N_TOPICS],
    peeked: [Option<Msg>; N_TOPICS],
    tx: [Vec<Tx>; N_TOPICS],
    stale_input_commands: u64,
    dropped_sends: u64,
    peer_gone: u64,
    keep_trace: bool,
    truths: Vec<PlantTruth>,
    cmds: Vec<VoltageCommand>,
}

impl UdsTransport {
    /// Binds the role's input sockets, then connects to its peers' (retrying until they
    /// exist).
    fn open(ctx: &RoleCtx) -> Result<Self> {
        let mut t = Self {
            rx: Default::default(),
            peeked: [None; N_TOPICS],
            tx: Default::default(),
            stale_input_commands: 0,
            dropped_sends: 0,
            peer_gone: 0,
            keep_trace: ctx.keep_trace,
            truths: Vec::new(),
            cmds: Vec::new(),
        };
        let inputs: &[(TopicId, &'static str)] = match ctx.role {
            Role::Plant => &[(TopicId::Cmd, PLANT_CMD)],
            Role::Observer => &[(TopicId::Meas, OBS_MEAS)],
            Role::CurrentLoop => &[
                (TopicId::Meas, CL_MEAS),
                (TopicId::Est, CL_EST),
                (TopicId::Iref, CL_IREF),
            ],
            Role::SpeedLoop => &[(TopicId::Est, SL_EST)],
        };
        for &(topic, sock) in inputs {
            t.rx[topic.index()] = Some((ctx.bind(sock)?, sock));
        }
        let outputs: &[(TopicId, &'static str)] = match ctx.role {
            Role::Plant => &[(TopicId::Meas, CL_MEAS), (TopicId::Meas, OBS_MEAS)],
            Role::Observer => &[(TopicId::Est, CL_EST), (TopicId::Est, SL_EST)],
            Role::CurrentLoop => &[(TopicId::Cmd, PLANT_CMD)],
            Role::SpeedLoop => &[(TopicId::Iref, CL_IREF)],
        };
        for &(topic, sock) in outputs {
            t.tx[topic.index()].push(ctx.connect(sock)?);
        }
        Ok(t)
    }

    fn recv_one(&mut self, topic: TopicId, block: bool) -> Result<Option<Msg>> {
        let Some((rx, sock)) = &self.rx[topic.index()] else {
            return Ok(None);
        };
        macro_rules! take {
            ($ty:ty, $variant:ident) => {
                match rx.recv::<$ty>(block) {
                    Recv::Msg(m) => Some(Msg::$variant(m)),
                    Recv::Empty => None,
                    // A wrong-size datagram: skipped here (the host counts what it rejects).
                    Recv::Malformed => None,
                    Recv::Err(e) => return Err(recv_error(sock, e)),
                }
            };
        }
        let m = match topic {
            TopicId::Meas => take!(Measurement, Meas),
            TopicId::Est => take!(Estimate, Est),
            TopicId::Iref => take!(CurrentRef, Iref),
            TopicId::Cmd => take!(VoltageCommand, Cmd),
            TopicId::Wref | TopicId::Truth => None,
        };
        if let Some(Msg::Cmd(c)) = &m {
            if !c.hdr.is_warmup() && !c.hdr.is_end() {
                if c.hdr.flags & FLAG_STALE_INPUT != 0 {
                    self.stale_input_commands += 1;
                }
                if self.keep_trace && self.cmds.len() < self.cmds.capacity() {
                    self.cmds.push(*c);
                }
            }
        }
        Ok(m)
    }

    /// The trace the plant saw: truth k joined with command k, up to the first sample whose
    /// command was missing (the plant held or went safe) or made from a stale input.
    fn trace(&self, ts: f64) -> Vec<TraceRow> {
        let mut rows = Vec::new();
        for (t, c) in self.truths.iter().zip(&self.cmds) {
            if t.hdr.k != c.hdr.k
                || t.hdr.flags & (FLAG_STALE_CMD | FLAG_SAFE_STATE) != 0
                || c.hdr.flags & FLAG_STALE_INPUT != 0
            {
                break;
            }
            rows.push(trace_row(ts, t, c));
        }
        rows
    }
}

impl Transport for UdsTransport {
    fn send(&mut self, msg: &Msg) -> Result<()> {
        if let Msg::Truth(t) = msg {
            if self.keep_trace
                && !t.hdr.is_end()
                && !t.hdr.is_warmup()
                && self.truths.len() < self.truths.capacity()
            {
                self.truths.push(*t);
            }
            return Ok(());
        }
        let marker = msg.hdr().is_warmup() || msg.hdr().is_end();
        for tx in &self.tx[msg.topic().index()] {
            let sent = match msg {
                Msg::Meas(m) if marker => send_control(tx, m).map(|_| Sent::Ok)?,
                Msg::Est(m) if marker => send_control(tx, m).map(|_| Sent::Ok)?,
                Msg::Iref(m) if marker => send_control(tx, m).map(|_| Sent::Ok)?,
                Msg::Cmd(m) if marker => send_control(tx, m).map(|_| Sent::Ok)?,
                Msg::Meas(m) => tx.send(m),
                Msg::Est(m) => tx.send(m),
                Msg::Iref(m) => tx.send(m),
                Msg::Cmd(m) => tx.send(m),
                Msg::Wref(_) | Msg::Truth(_) => Sent::Ok,
            };
            match sent {
                Sent::Ok => {}
                Sent::Full => self.dropped_sends += 1,
                Sent::PeerGone => self.peer_gone += 1,
                Sent::Err(e) => {
                    return Err(anyhow!(
                        "send to {}: {}",
                        tx.peer,
                        std::io::Error::from_raw_os_error(e)
                    ))
                }
            }
        }
        Ok(())
    }

    fn try_recv(&mut self, topic: TopicId) -> Result<Option<Msg>> {
        if let Some(m) = self.peeked[topic.index()].take() {
            return Ok(Some(m));
        }
        self.recv_one(topic, false)
    }

    fn pending(&mut self, topic: TopicId) -> Result<bool> {
        if self.peeked[topic.index()].is_none() {
            self.peeked[topic.index()] = self.recv_one(topic, false)?;
        }
        Ok(self.peeked[topic.index()].is_some())
    }

    fn wait(&mut self, topic: TopicId, _timeout: Duration) -> Result<()> {
        // A blocking receive returns at the latest after RECV_SLICE (or on a signal).
        if self.peeked[topic.index()].is_none() {
            self.peeked[topic.index()] = self.recv_one(topic, true)?;
        }
        Ok(())
    }
}

// ------------------------------------------------------------------------------------------
// Node process entry point
// ------------------------------------------------------------------------------------------

/// Entry point arguments of `drivelab bench-node uds ...`.
#[derive(Debug, Clone)]
pub struct UdsNodeArgs {
    /// plant, observer, current-loop or speed-loop.
    pub role: String,
    /// Socket directory (shared by the four nodes).
    pub dir: PathBuf,
    /// Scenario file (TOML).
    pub scenario: PathBuf,
    /// Seconds of measurement (the plant's run length; the others run until the end marker).
    pub seconds: f64,
    /// CPU core.
    pub core: Option<usize>,
    /// SCHED_FIFO priority.
    pub priority: Option<u8>,
    /// Result file (JSON). The plant's: its measurements, with its histograms beside it as
    /// `<out>.cycle.hdr`, `<out>.lateness.hdr`; another role's: its system-call count.
    pub out: Option<PathBuf>,
}

/// The plant's result file.
#[derive(Debug, Serialize, Deserialize)]
struct PlantFile {
    samples: u64,
    misses: u64,
    longest_miss_run: u64,
    counters: Counters,
    cycle_clamped: u64,
    lateness_clamped: u64,
    cycle_hdr: PathBuf,
    lateness_hdr: PathBuf,
    rt: String,
    /// The plant's system calls at drivelab's call sites (`rt::syscalls`).
    syscalls: u64,
}

/// The result file of a role other than the plant.
#[derive(Debug, Serialize, Deserialize)]
struct NodeFile {
    role: String,
    /// Its system calls at drivelab's call sites (`rt::syscalls`).
    syscalls: u64,
}

fn sibling(out: &Path, suffix: &str) -> PathBuf {
    let mut s = out.as_os_str().to_os_string();
    s.push(suffix);
    PathBuf::from(s)
}

fn write_plant_file(out: &Path, p: &PlantOutcome) -> Result<()> {
    let cycle_hdr = sibling(out, ".cycle.hdr");
    let lateness_hdr = sibling(out, ".lateness.hdr");
    p.result.cycle.write_v2(&cycle_hdr)?;
    p.result.lateness.write_v2(&lateness_hdr)?;
    let f = PlantFile {
        samples: p.result.samples,
        misses: p.result.misses.misses,
        longest_miss_run: p.result.misses.longest_run,
        counters: p.counters,
        cycle_clamped: p.result.cycle.clamped,
        lateness_clamped: p.result.lateness.clamped,
        cycle_hdr,
        lateness_hdr,
        rt: p.rt.clone(),
        syscalls: p.result.syscalls.unwrap_or(0),
    };
    drivelab_runtime::files::write(out, serde_json::to_vec_pretty(&f)?)
        .with_context(|| format!("write {}", out.display()))
}

fn read_plant_file(out: &Path) -> Result<VariantResult> {
    let text = std::fs::read(out)
        .with_context(|| format!("the UDS plant wrote no result file {}", out.display()))?;
    let f: PlantFile = serde_json::from_slice(&text)
        .with_context(|| format!("{}: not a UDS plant result", out.display()))?;
    let mut cycle = LatencyHist::read_v2("cycle", &f.cycle_hdr)?;
    cycle.clamped = f.cycle_clamped;
    let mut lateness = LatencyHist::read_v2("lateness", &f.lateness_hdr)?;
    lateness.clamped = f.lateness_clamped;
    let mut misses = MissCounter::default();
    misses.misses = f.misses;
    misses.longest_run = f.longest_miss_run;
    Ok(VariantResult {
        cycle,
        lateness,
        samples: f.samples,
        misses,
        cpu_run_ns: None,
        deadline_lateness: Vec::new(),
        syscalls: Some(f.syscalls),
        stalls: None,
    })
}

/// The system calls a role other than the plant counted, from its result file; None when it
/// wrote none (killed as a straggler).
fn read_node_syscalls(out: &Path) -> Option<u64> {
    let f: NodeFile = serde_json::from_slice(&std::fs::read(out).ok()?).ok()?;
    Some(f.syscalls)
}

/// Entry point for `drivelab bench-node uds ...`: runs one role of the Unix-socket chain in
/// this process until the end marker (or SIGTERM/SIGINT). The plant writes its results to
/// `out`.
pub fn run_uds_node(args: &UdsNodeArgs) -> Result<()> {
    let role = Role::parse(&args.role)?;
    if !(args.seconds.is_finite() && args.seconds > 0.0) {
        bail!("--seconds must be a positive number, got {}", args.seconds);
    }
    install_signal_handlers()?;
    let text = std::fs::read_to_string(&args.scenario)
        .with_context(|| format!("cannot read scenario {}", args.scenario.display()))?;
    let sc =
        Scenario::from_toml(&text, &args.scenario.display().to_string()).map_err(|e| anyhow!(e))?;
    let ctx = RoleCtx {
        role,
        dir: &args.dir,
        sc: &sc,
        seconds: args.seconds,
        node: NodeSpec {
            core: args.core,
            priority: args.priority,
        },
        lock_memory: true,
        stop: stop_flag(),
        announce: true,
        keep_trace: false,
        pacing: Pacing::Realtime,
    };
    let out = run_role(&ctx).with_context(|| format!("bench-node uds {}", role.name()))?;
    match (out, &args.out) {
        (Some(p), Some(path)) => write_plant_file(path, &p)?,
        (None, Some(path)) => {
            let f = NodeFile {
                role: role.name().into(),
                syscalls: drivelab_runtime::rt::syscalls(),
            };
            drivelab_runtime::files::write(path, serde_json::to_vec_pretty(&f)?)
                .with_context(|| format!("write {}", path.display()))?;
        }
        (_, None) => {}
    }
    Ok(())
}

// ------------------------------------------------------------------------------------------
// The chain runner
// ------------------------------------------------------------------------------------------

/// A private socket directory (mode 0700), removed with its contents on drop.
#[derive(Debug)]
pub(crate) struct SockDir {
    pub path: PathBuf,
}

impl SockDir {
    /// Creates a fresh directory named `<prefix>-<pid>-<seq>` in the temp dir (or /tmp when
    /// the temp dir's path would make socket paths too long).
    pub(crate) fn create(prefix: &str) -> Result<Self> {
        use std::os::unix::fs::DirBuilderExt;
        static SEQ: AtomicU64 = AtomicU64::new(0);
        let mut base = std::env::temp_dir();
        // Longest socket name is 17 bytes; sun_path holds 107.
        if base.as_os_str().len() > 60 {
            base = PathBuf::from("/tmp");
        }
        for _ in 0..100 {
            let seq = SEQ.fetch_add(1, Ordering::Relaxed);
            let path = base.join(format!("{prefix}-{}-{seq}", std::process::id()));
            match std::fs::DirBuilder::new().mode(0o700).create(&path) {
                Ok(()) => return Ok(Self { path }),
                Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => continue,
                Err(e) => bail!("cannot create socket directory {}: {e}", path.display()),
            }
        }
        bail!(
            "cannot create a fresh socket directory in {}",
            base.display()
        )
    }
}

impl Drop for SockDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.path);
    }
}

/// Unix-socket chain: the same four roles as four processes exchanging the same message
/// structs over Unix domain datagram sockets in a private temp dir (removed afterwards). The
/// processes are started as `exe bench-node uds --role <role> --dir <sockdir> --scenario
/// <file> --seconds S [--core C] [--priority P] --out <file>`; the scenario file, each
/// node's result file (`uds-<role>.json`: the plant's measurements, the others' system-call
/// counts) and one log per node (`uds-<role>.log`, stdout and stderr) go to `workdir`.
/// Watchdog: seconds × 3 + 20 s; a stop signal ends it with [`crate::Interrupted`]; no
/// process is left behind on any path.
pub fn run_uds_chain(spec: &ChainSpec, exe: &Path, workdir: &Path) -> Result<VariantResult> {
    schedule(spec.scenario.rates.sample_hz, spec.seconds)?;
    std::fs::create_dir_all(workdir)
        .with_context(|| format!("cannot create {}", workdir.display()))?;
    let scenario = workdir.join("uds-scenario.toml");
    drivelab_runtime::files::write(&scenario, toml::to_string(&spec.scenario)?)
        .with_context(|| format!("write {}", scenario.display()))?;
    let out_of = |role: Role| workdir.join(format!("uds-{}.json", role.name()));
    let out = out_of(Role::Plant);
    for p in [sibling(&out, ".cycle.hdr"), sibling(&out, ".lateness.hdr")]
        .into_iter()
        .chain(ROLES.map(out_of))
    {
        let _ = std::fs::remove_file(p);
    }
    // Declared before the processes so that it is dropped (removed) after they are reaped.
    let sock = SockDir::create("drivelab-uds")?;
    let mut kids = Kids::default();
    for role in ROLES {
        let node = match role {
            Role::Plant => spec.plant,
            Role::Observer => spec.observer,
            Role::CurrentLoop => spec.current_loop,
            Role::SpeedLoop => spec.speed_loop,
        };
        let log = workdir.join(format!("uds-{}.log", role.name()));
        // Through DRIVELAB_RUNNER when set (an aarch64 build under qemu-user).
        let mut cmd = drivelab_runtime::runner::env_command(exe).map_err(|e| anyhow!(e))?;
        cmd.args(["bench-node", "uds", "--role", role.name(), "--dir"])
            .arg(&sock.path)
            .arg("--scenario")
            .arg(&scenario)
            .arg("--seconds")
            .arg(spec.seconds.to_string());
        if let Some(c) = node.core {
            cmd.arg("--core").arg(c.to_string());
        }
        if let Some(p) = node.priority {
            cmd.arg("--priority").arg(p.to_string());
        }
        cmd.arg("--out").arg(out_of(role));
        kids.spawn(role, &mut cmd, log, &format!("the {}", role.name()))?;
    }
    let watchdog = Duration::from_secs_f64(spec.seconds * 3.0 + 20.0);
    let started = Instant::now();
    let mut plant_done: Option<Instant> = None;
    loop {
        let all = kids.poll();
        for k in &kids.0 {
            if let Some(s) = k.status {
                if !s.success() {
                    bail!(
                        "UDS chain: {} exited with {s}: {}",
                        k.what.name(),
                        log_tail(&k.log)
                    );
                }
                if k.what == Role::Plant && plant_done.is_none() {
                    plant_done = Some(Instant::now());
                }
            }
        }
        // A stop signal: the guard stops the nodes.
        crate::check_stop()?;
        if all {
            break;
        }
        if plant_done.is_some_and(|t| t.elapsed() > STRAGGLER_GRACE) {
            break; // stragglers are killed below
        }
        if started.elapsed() > watchdog {
            let running: Vec<&str> = kids
                .0
                .iter()
                .filter(|k| k.status.is_none())
                .map(|k| k.what.name())
                .collect();
            bail!(
                "UDS chain watchdog: {} still running after {watchdog:?}; killed",
                running.join(", ")
            );
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    kids.terminate();
    drop(kids);
    drop(sock);
    let mut r = read_plant_file(&out)?;
    // Every role's calls, or none when one of them wrote no count.
    for role in ROLES.into_iter().filter(|r| *r != Role::Plant) {
        r.syscalls = r
            .syscalls
            .zip(read_node_syscalls(&out_of(role)))
            .map(|(a, b)| a + b);
    }
    Ok(r)
}

/// SCHED_FIFO priority of the threads of [`run_chain_threads`].
#[cfg(test)]
const THREAD_CHAIN_PRIORITY: u8 = 50;

/// Runs the four roles as threads of this process over the same sockets (tests; SCHED_FIFO
/// where allowed, not pinned).
#[cfg(test)]
pub(crate) fn run_chain_threads(
    sc: &Scenario,
    seconds: f64,
    keep_trace: bool,
    pacing: Pacing,
) -> Result<PlantOutcome> {
    let sock = SockDir::create("drivelab-udst")?;
    // The hosts' stop condition must outlive them: one flag per run, leaked (tests only).
    let stop: &'static AtomicBool = Box::leak(Box::new(AtomicBool::new(false)));
    // SCHED_FIFO where this user may have it (a warning where not): the chain's rows compare
    // only up to its first miss, and threads that a busy machine (a parallel build, the other
    // tests) preempts for a sample time miss early.
    let node = NodeSpec {
        core: None,
        priority: Some(THREAD_CHAIN_PRIORITY),
    };
    let ctx = |role| RoleCtx {
        role,
        dir: &sock.path,
        sc,
        seconds,
        node,
        lock_memory: false,
        stop,
        announce: false,
        keep_trace,
        pacing,
    };
    std::thread::scope(|s| {
        let run = |role| {
            let c = ctx(role);
            s.spawn(move || {
                let r = run_role(&c);
                if r.is_err() {
                    stop.store(true, Ordering::SeqCst);
                }
                r
            })
        };
        let others = [
            run(Role::Observer),
            run(Role::CurrentLoop),
            run(Role::SpeedLoop),
        ];
        let plant = run(Role::Plant)
            .join()
            .map_err(|_| anyhow!("plant thread panicked"))?;
        let t = Instant::now();
        while others.iter().any(|h| !h.is_finished()) && t.elapsed() < STRAGGLER_GRACE {
            std::thread::sleep(Duration::from_millis(5));
        }
        stop.store(true, Ordering::SeqCst);
        for h in others {
            h.join().map_err(|_| anyhow!("node thread panicked"))??;
        }
        plant?.ok_or_else(|| anyhow!("plant returned no outcome"))
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::children::Kid;
    use crate::testutil::kyslan;
    use drivelab_runtime::drive::InProcessDrive;
    use std::process::{Command, Stdio};

    #[test]
    fn unknown_role_is_a_one_line_error() {
        let args = UdsNodeArgs {
            role: "recorder".into(),
            dir: "/nonexistent".into(),
            scenario: "/nonexistent.toml".into(),
            seconds: 1.0,
            core: None,
            priority: None,
            out: None,
        };
        let e = format!("{:#}", run_uds_node(&args).unwrap_err());
        assert_eq!(
            e,
            "unknown role 'recorder' (expected plant, observer, current-loop or speed-loop)"
        );
    }

    #[test]
    fn scenario_survives_the_toml_round_trip() {
        let sc = kyslan(5000.0);
        let back = Scenario::from_toml(&toml::to_string(&sc).unwrap(), "x").unwrap();
        assert_eq!(back, sc);
    }

    /// The in-process chain's first `n` trace rows of `sc`: what every transport must give.
    fn inprocess_rows(sc: &Scenario, n: u64) -> Vec<TraceRow> {
        let mut d = InProcessDrive::new(sc);
        (0..n).map(|k| d.cycle(k)).collect()
    }

    #[test]
    fn thread_chain_in_lockstep_matches_the_inprocess_trace_row_for_row() {
        // Determinism across transports: in lockstep every input is waited for, so the
        // chain over Unix sockets must give the in-process chain's trace bit for bit, every
        // row, however loaded the machine is.
        let sc = kyslan(1000.0);
        let reference = inprocess_rows(&sc, 200);
        let p = run_chain_threads(&sc, 0.2, true, Pacing::Lockstep).unwrap();
        assert_eq!(p.result.samples, 200);
        assert_eq!(p.result.misses.misses, 0);
        assert_eq!(p.counters.stale_input_commands, 0);
        assert_eq!(p.trace.len(), 200);
        assert!(
            p.trace == reference,
            "the lockstep trace differs from the in-process one"
        );
    }

    #[test]
    fn thread_chain_in_real_time_matches_the_inprocess_trace_up_to_its_first_miss() {
        // 1 kHz: the threads run unpinned at SCHED_FIFO 50, below the drives that other
        // tests run at the same time. A thread preempted for more than a sample time makes a
        // miss, after which the rows legitimately differ (the plant held its command); how
        // soon that happens depends on the machine, so this checks the rows before it and
        // the run's accounting, and the lockstep test above checks every row. Misses are
        // rare at 1 kHz, so of up to three runs the longest must compare at least half of
        // its rows: a chain that flagged its commands stale from the start compares none.
        let sc = kyslan(1000.0);
        let reference = inprocess_rows(&sc, 100);
        let mut longest = 0;
        for _ in 0..3 {
            let p = run_chain_threads(&sc, 0.1, true, Pacing::Realtime).unwrap();
            assert_eq!(p.result.samples, 100);
            // One wake-up per sample plus the one that takes the last command.
            assert_eq!(p.result.lateness.len(), 101);
            assert!(!p.result.cycle.is_empty());
            assert_eq!(p.counters.samples, 100);
            eprintln!(
                "uds threads: {} misses, {} stale-input commands, {} rows compared, cycle {:?}",
                p.result.misses.misses,
                p.counters.stale_input_commands,
                p.trace.len(),
                p.result.cycle.percentiles()
            );
            assert!(
                p.trace[..] == reference[..p.trace.len()],
                "a row before the first miss differs"
            );
            longest = longest.max(p.trace.len());
            if p.result.misses.misses == 0 && p.counters.stale_input_commands == 0 {
                assert_eq!(p.trace.len(), 100);
                break;
            }
        }
        assert!(
            longest >= 50,
            "at most {longest} rows before a miss in three runs"
        );
    }

    /// Not a test: the entry point of a `bench-node uds` node process that [`fake_drivelab`]
    /// starts (this test binary, run with `--ignored --exact` on this name). Ignored, so that
    /// it is never counted as a passing test; run without the node's arguments it fails.
    #[test]
    #[ignore = "the node process of the process-chain tests (fake_drivelab runs it), not a test"]
    fn node_trampoline() {
        let a = std::env::var("DRIVELAB_BENCH_UDS_NODE_ARGS").expect(
            "node_trampoline runs only as a node process started by fake_drivelab \
             (DRIVELAB_BENCH_UDS_NODE_ARGS is not set)",
        );
        let v: Vec<&str> = a.lines().collect();
        let mut args = UdsNodeArgs {
            role: String::new(),
            dir: PathBuf::new(),
            scenario: PathBuf::new(),
            seconds: 0.0,
            core: None,
            priority: None,
            out: None,
        };
        for pair in v.chunks(2) {
            let val = pair.get(1).copied().unwrap_or_default();
            match pair[0] {
                "--role" => args.role = val.into(),
                "--dir" => args.dir = val.into(),
                "--scenario" => args.scenario = val.into(),
                "--seconds" => args.seconds = val.parse().unwrap(),
                "--core" => args.core = Some(val.parse().unwrap()),
                "--priority" => args.priority = Some(val.parse().unwrap()),
                "--out" => args.out = Some(val.into()),
                other => {
                    eprintln!("unexpected argument {other}");
                    std::process::exit(2);
                }
            }
        }
        match run_uds_node(&args) {
            Ok(()) => std::process::exit(0),
            Err(e) => {
                eprintln!("bench-node uds: error: {e:#}");
                std::process::exit(1);
            }
        }
    }

    /// Serialises the tests that spawn processes (they check for leftover children).
    static PROCESS_TESTS: std::sync::Mutex<()> = std::sync::Mutex::new(());

    fn children_of_this_process() -> Vec<u32> {
        let me = std::process::id().to_string();
        let mut v = Vec::new();
        for e in std::fs::read_dir("/proc").unwrap().flatten() {
            let Ok(pid) = e.file_name().to_string_lossy().parse::<u32>() else {
                continue;
            };
            let Ok(st) = std::fs::read_to_string(format!("/proc/{pid}/status")) else {
                continue;
            };
            if st
                .lines()
                .any(|l| l.strip_prefix("PPid:").map(str::trim) == Some(me.as_str()))
            {
                v.push(pid);
            }
        }
        v
    }

    fn leftover_sock_dirs() -> Vec<PathBuf> {
        let prefix = format!("drivelab-uds-{}-", std::process::id());
        let mut v = Vec::new();
        for base in [std::env::temp_dir(), PathBuf::from("/tmp")] {
            for e in std::fs::read_dir(base).unwrap().flatten() {
                if e.file_name().to_string_lossy().starts_with(&prefix) {
                    v.push(e.path());
                }
            }
        }
        v
    }

    /// A shell script standing in for `drivelab`: it maps `bench-node uds ARGS` onto
    /// [`node_trampoline`] in this test binary.
    fn fake_drivelab(work: &Path) -> PathBuf {
        let me = std::env::current_exe().unwrap();
        let script = work.join("fake-drivelab");
        std::fs::write(
            &script,
            format!(
                "#!/bin/sh\n[ \"$1\" = bench-node ] && [ \"$2\" = uds ] || {{ echo \"bad args: $*\" >&2; exit 2; }}\n\
                 shift 2\nDRIVELAB_BENCH_UDS_NODE_ARGS=$(printf '%s\\n' \"$@\")\nexport DRIVELAB_BENCH_UDS_NODE_ARGS\n\
                 exec '{}' --ignored --exact uds::tests::node_trampoline --nocapture --test-threads=1 -q\n",
                me.display()
            ),
        )
        .unwrap();
        use std::os::unix::fs::PermissionsExt;
        std::fs::set_permissions(&script, std::fs::Permissions::from_mode(0o755)).unwrap();
        script
    }

    /// The whole process chain through [`fake_drivelab`].
    /// (Both process tests in one function: they check for leftovers of this process.)
    #[test]
    fn process_chain_end_to_end_and_failure_paths() {
        let _serial = PROCESS_TESTS.lock().unwrap_or_else(|e| e.into_inner());
        let work = std::env::temp_dir().join(format!("drivelab-bench-e2e-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&work);
        std::fs::create_dir_all(&work).unwrap();
        let script = fake_drivelab(&work);
        let spec = ChainSpec {
            scenario: kyslan(2000.0),
            seconds: 0.05,
            plant: NodeSpec::default(),
            observer: NodeSpec::default(),
            current_loop: NodeSpec::default(),
            speed_loop: NodeSpec::default(),
        };
        let t = Instant::now();
        let r = run_uds_chain(&spec, &script, &work.join("ok")).unwrap();
        eprintln!(
            "uds processes: {} samples, {} misses, cycle {:?}, lateness {:?}, in {:?}",
            r.samples,
            r.misses.misses,
            r.cycle.percentiles(),
            r.lateness.percentiles(),
            t.elapsed()
        );
        assert_eq!(r.samples, 100);
        assert_eq!(r.lateness.len(), 101);
        assert!(!r.cycle.is_empty());
        assert!(children_of_this_process().is_empty());
        assert!(
            leftover_sock_dirs().is_empty(),
            "{:?}",
            leftover_sock_dirs()
        );
        let log = std::fs::read_to_string(work.join("ok/uds-plant.log")).unwrap();
        assert!(log.contains("READY") && log.contains("plant: cpu"), "{log}");

        // A node that cannot start: a clear error naming it, nothing left behind.
        let e = run_uds_chain(&spec, Path::new("/bin/false"), &work.join("bad"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("exited with exit status: 1"), "{e}");
        assert!(children_of_this_process().is_empty());
        assert!(leftover_sock_dirs().is_empty());

        // A missing executable.
        let e = run_uds_chain(&spec, &work.join("missing"), &work.join("bad2"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("cannot start"), "{e}");
        assert!(leftover_sock_dirs().is_empty());
        std::fs::remove_dir_all(&work).unwrap();
    }

    /// SIGTERM stops every node at once: a downstream node just exits, the plant sends the end
    /// marker and writes its (partial) results.
    #[test]
    fn nodes_stop_on_sigterm() {
        let _serial = PROCESS_TESTS.lock().unwrap_or_else(|e| e.into_inner());
        let work = std::env::temp_dir().join(format!("drivelab-bench-term-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&work);
        std::fs::create_dir_all(&work).unwrap();
        let script = fake_drivelab(&work);
        let sock = SockDir::create("drivelab-udsterm").unwrap();
        let scen = work.join("sc.toml");
        std::fs::write(&scen, toml::to_string(&kyslan(2000.0)).unwrap()).unwrap();
        let out = work.join("plant.json");
        let spawn = |role: &str| {
            let mut c = Command::new(&script);
            c.args(["bench-node", "uds", "--role", role, "--dir"])
                .arg(&sock.path)
                .args(["--scenario"])
                .arg(&scen)
                .args(["--seconds", "60"])
                .stdout(Stdio::null());
            if role == "plant" {
                c.arg("--out").arg(&out);
            }
            c.spawn().unwrap()
        };
        // In their guard: any node still running when the test ends, or fails, is stopped
        // and reaped.
        let mut kids = Kids::default();
        for role in [
            Role::Observer,
            Role::CurrentLoop,
            Role::SpeedLoop,
            Role::Plant,
        ] {
            kids.0.push(Kid {
                what: role,
                child: spawn(role.name()),
                log: PathBuf::new(),
                status: None,
            });
        }
        let term_and_wait = |k: &mut Kid<Role>| {
            // SAFETY: kill(2) on our own unreaped child.
            unsafe { libc::kill(k.child.id() as libc::pid_t, libc::SIGTERM) };
            let t = Instant::now();
            loop {
                if let Some(s) = k.child.try_wait().unwrap() {
                    k.status = Some(s);
                    return (s, t.elapsed());
                }
                assert!(
                    t.elapsed() < Duration::from_secs(3),
                    "no exit after SIGTERM"
                );
                std::thread::sleep(Duration::from_millis(5));
            }
        };
        // Let the chain run: wait until the plant samples, as the scheduler sees it (the UDS
        // nodes publish no progress of their own): its voluntary context switches rise by at
        // least 70 in each of two consecutive 50 ms windows. Sampling at 2 kHz sleeps 100
        // times per window; before it, the plant's connect retries (1 ms apart) make at most
        // 50 per window, and its 50 warm-up round trips end within one. A plain count (200)
        // was reached by connect retries alone when the peers started slowly.
        let plant_pid = kids.0[3].child.id();
        let switches = || -> u64 {
            // Over every thread of the process.
            std::fs::read_dir(format!("/proc/{plant_pid}/task"))
                .into_iter()
                .flatten()
                .flatten()
                .filter_map(|t| std::fs::read_to_string(t.path().join("status")).ok())
                .filter_map(|t| {
                    t.lines()
                        .find_map(|l| l.strip_prefix("voluntary_ctxt_switches:"))
                        .and_then(|v| v.trim().parse::<u64>().ok())
                })
                .sum()
        };
        let t = Instant::now();
        let (mut last, mut fast_windows) = (switches(), 0);
        while fast_windows < 2 {
            assert!(
                t.elapsed() < Duration::from_secs(20),
                "watchdog: the plant did not start sampling within 20 s"
            );
            std::thread::sleep(Duration::from_millis(50));
            let now = switches();
            fast_windows = if now >= last + 70 {
                fast_windows + 1
            } else {
                0
            };
            last = now;
        }
        for k in &mut kids.0 {
            assert!(
                k.child.try_wait().unwrap().is_none(),
                "a node ended early: {}",
                k.what.name()
            );
        }
        // A downstream node first, then the plant, then the rest.
        for i in [0usize, 3, 1, 2] {
            let k = &mut kids.0[i];
            let role = k.what.name();
            let (s, dt) = term_and_wait(k);
            assert!(s.success(), "{role}: {s}");
            eprintln!("{role} stopped {dt:?} after SIGTERM");
            if i == 0 {
                // Let the plant run without its observer for a while.
                std::thread::sleep(Duration::from_millis(50));
            }
        }
        let r = read_plant_file(&out).unwrap();
        assert!(r.samples > 0 && r.samples < 120_000, "{}", r.samples);
        // The observer was gone for a while: the plant saw misses.
        assert!(r.misses.misses > 0);
        drop(sock);
        std::fs::remove_dir_all(&work).unwrap();
    }
}
