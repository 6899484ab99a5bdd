//! The Unix-socket chain: plant, observer, current loop and speed loop as four processes that
//! exchange the bus messages ([`drivelab_runtime::messages`], sent as their bytes) over Unix domain
//! datagram sockets in a private directory. It mirrors the iceoryx2 services in
//! `services/src/{plant,observer,current_loop,speed_loop}.rs`:
//!
//! * the plant is the timing master: it sleeps to t_k, takes command k−1 from its socket
//!   without waiting (absent = a deadline miss, the plant holds the previous command), and
//!   sends measurement k to the current loop and then to the observer;
//! * the observer blocks on its measurement socket and sends estimate k to the current loop
//!   and then to the speed loop;
//! * the current loop blocks on its estimate socket, drains its measurement and reference
//!   sockets, and uses the reference of the last speed sample before k
//!   ([`CurrentLoopStep::expected_ref_index`]; absent = it keeps the last one and flags the
//!   command [`FLAG_STALE_INPUT`]);
//! * the speed loop blocks on its estimate socket and runs every N samples.
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
//! exist), sets up real time and prints `READY`. The plant then sends 50 warm-up messages
//! ([`FLAG_WARMUP`]) through the whole chain, one at a time, before t_0 — so the clock starts
//! only when every socket of the chain is bound and connected. At the end the plant sends an
//! [`FLAG_END`] measurement that every node forwards before it exits. SIGTERM/SIGINT stop a
//! node (the plant still sends the end marker and writes its results).

use crate::wire::{Recv, Rx, Sent, Tx, Wire};
use crate::{apply_rt, schedule, wait_deadline, NodeSpec};
use crate::{ChainSpec, VariantResult};
use anyhow::{anyhow, bail, Context, Result};
use drivelab_runtime::config::Scenario;
use drivelab_runtime::drive::{trace_row, CurrentLoopStep, ObserverStep, Plant, SpeedLoopStep};
use drivelab_runtime::messages::{
    CurrentRef, Estimate, Finite, Header, Measurement, VoltageCommand, FLAG_END, FLAG_STALE_INPUT,
    FLAG_WARMUP,
};
use drivelab_runtime::rt::now_ns;
use drivelab_runtime::timing::{CycleMonitor, LatencyHist, MissCounter};
use drivelab_runtime::trace::TraceRow;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
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
/// How long the plant waits for one warm-up message to come back.
const WARMUP_TIMEOUT: Duration = Duration::from_secs(10);
/// A downstream node with no input for this long gives up (its upstream is gone).
const IDLE_LIMIT: Duration = Duration::from_secs(20);
/// How long a control message (warm-up, end) may wait for room in a full queue.
const CONTROL_TIMEOUT: Duration = Duration::from_secs(1);
/// After the plant has exited, how long the other nodes get to finish before they are killed.
const STRAGGLER_GRACE: Duration = Duration::from_secs(5);
/// How long a node gets to exit after SIGTERM before SIGKILL.
const TERM_GRACE: Duration = Duration::from_secs(2);

/// The four roles.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Role {
    Plant,
    Observer,
    CurrentLoop,
    SpeedLoop,
}

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

impl Counters {
    /// Sends a data message without blocking; a full queue or a gone peer is counted.
    #[inline]
    fn send<T: Wire>(&mut self, tx: &Tx, m: &T) -> Result<()> {
        match tx.send(m) {
            Sent::Ok => Ok(()),
            Sent::Full => {
                self.dropped_sends += 1;
                Ok(())
            }
            Sent::PeerGone => {
                self.peer_gone += 1;
                Ok(())
            }
            Sent::Err(e) => Err(anyhow!(
                "send to {}: {}",
                tx.peer,
                std::io::Error::from_raw_os_error(e)
            )),
        }
    }
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
    pub stop: &'a AtomicBool,
    /// Print `READY` on stdout once bound and connected (node processes).
    pub announce: bool,
    /// Plant: keep the trace rows (tests: determinism across transports).
    pub keep_trace: bool,
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

/// Runs one role to its end. The plant returns its measurements, the others None.
pub(crate) fn run_role(ctx: &RoleCtx) -> Result<Option<PlantOutcome>> {
    match ctx.role {
        Role::Plant => plant(ctx).map(Some),
        Role::Observer => observer(ctx).map(|_| None),
        Role::CurrentLoop => current_loop(ctx).map(|_| None),
        Role::SpeedLoop => speed_loop(ctx).map(|_| None),
    }
}

/// Takes every queued command; returns command `want` if it is there. Older commands are late
/// (counted, their latency still recorded), malformed or future ones rejected.
#[inline]
fn take_command(
    rx: &Rx,
    want: u64,
    c: &mut Counters,
    mon: &mut CycleMonitor,
) -> Result<Option<VoltageCommand>> {
    let mut found = None;
    loop {
        match rx.recv::<VoltageCommand>(false) {
            Recv::Msg(cmd) => {
                if cmd.hdr.is_warmup() {
                    continue;
                }
                if !cmd.is_finite() || cmd.hdr.k > want {
                    c.rejected_inputs += 1;
                } else if cmd.hdr.k == want {
                    found = Some(cmd);
                } else {
                    c.late_commands += 1;
                    if cmd.hdr.t_sample_ns != 0 {
                        mon.late_command(cmd.hdr.t_sample_ns, cmd.hdr.t_pub_ns);
                    }
                }
            }
            Recv::Empty => return Ok(found),
            Recv::Malformed => c.rejected_inputs += 1,
            Recv::Err(e) => return Err(recv_error(PLANT_CMD, e)),
        }
    }
}

/// Sends the warm-up messages through the chain, one at a time, each waiting for its flagged
/// command to come back.
fn warm_up(ctx: &RoleCtx, cmd_rx: &Rx, to_cl: &Tx, to_obs: &Tx) -> Result<()> {
    for i in 0..WARMUP_MESSAGES {
        let m = Measurement {
            hdr: Header {
                k: i,
                flags: FLAG_WARMUP,
                t_pub_ns: now_ns(),
                ..Default::default()
            },
            ..Default::default()
        };
        for tx in [to_cl, to_obs] {
            if let Sent::Err(e) = tx.send_patiently(&m, WARMUP_TIMEOUT) {
                bail!(
                    "warm-up: send to {}: {}",
                    tx.peer,
                    std::io::Error::from_raw_os_error(e)
                );
            }
        }
        let started = Instant::now();
        loop {
            match cmd_rx.recv::<VoltageCommand>(true) {
                Recv::Msg(c) if c.hdr.is_warmup() && c.hdr.k == i => break,
                Recv::Err(e) => return Err(recv_error(PLANT_CMD, e)),
                _ => {}
            }
            if ctx.stopped() {
                return Ok(());
            }
            if started.elapsed() > WARMUP_TIMEOUT {
                bail!(
                    "warm-up message {i} did not come back through the chain within \
                     {WARMUP_TIMEOUT:?}"
                );
            }
        }
    }
    Ok(())
}

/// The plant: timing master.
fn plant(ctx: &RoleCtx) -> Result<PlantOutcome> {
    let sc = ctx.sc;
    let (n, ts_ns) = schedule(sc.rates.sample_hz, ctx.seconds)?;
    let ts = sc.rates.ts();
    let cmd_rx = ctx.bind(PLANT_CMD)?;
    // The current loop first: it only polls its measurement socket, so the measurement must be
    // there before the observer (which wakes it) gets its copy.
    let to_cl = ctx.connect(CL_MEAS)?;
    let to_obs = ctx.connect(OBS_MEAS)?;
    let mut plant = Plant::new(sc);
    let mut mon = CycleMonitor::new(ts_ns);
    let mut lateness = LatencyHist::new("lateness");
    let mut c = Counters::default();
    let mut trace: Vec<TraceRow> = Vec::with_capacity(if ctx.keep_trace { n as usize } else { 0 });
    let mut tracing = ctx.keep_trace;
    let mut prev_truth = drivelab_runtime::messages::PlantTruth::default();
    let spin_ns = (sc.timing.plant_spin_us * 1e3).round() as u64;
    let rt = ctx.ready()?;
    warm_up(ctx, &cmd_rx, &to_cl, &to_obs)?;
    let t0 = now_ns() + 2_000_000;
    // ---- real-time loop: no allocation, no locks, no logging ----
    for k in 0..=n {
        let deadline = t0 + k * ts_ns;
        wait_deadline(deadline, spin_ns);
        lateness.record_ns(now_ns() as i64 - deadline as i64);
        let mut cmd = None;
        if k > 0 {
            cmd = take_command(&cmd_rx, k - 1, &mut c, &mut mon)?;
            mon.at_deadline(deadline - ts_ns, cmd.map(|c| c.hdr.t_pub_ns));
            match &cmd {
                Some(cm) => {
                    if cm.hdr.flags & FLAG_STALE_INPUT != 0 {
                        c.stale_input_commands += 1;
                        tracing = false;
                    }
                    if tracing {
                        // Capacity n was reserved: no allocation.
                        trace.push(trace_row(ts, &prev_truth, cm));
                    }
                }
                None => {
                    c.stale_inputs += 1;
                    tracing = false;
                }
            }
        }
        if ctx.stopped() || k == n {
            let end = Measurement {
                hdr: Header {
                    k,
                    flags: FLAG_END,
                    t_pub_ns: now_ns(),
                    ..Default::default()
                },
                ..Default::default()
            };
            send_control(&to_cl, &end)?;
            send_control(&to_obs, &end)?;
            break;
        }
        let mut meas = plant.sample(k, cmd.as_ref());
        meas.hdr.t_sample_ns = deadline;
        meas.hdr.t_pub_ns = now_ns();
        c.send(&to_cl, &meas)?;
        c.send(&to_obs, &meas)?;
        prev_truth = *plant.truth();
        plant.advance();
        c.samples += 1;
    }
    // ---- end of the real-time loop ----
    Ok(PlantOutcome {
        result: VariantResult {
            cycle: mon.cycle,
            lateness,
            samples: c.samples,
            misses: mon.misses,
        },
        counters: c,
        trace,
        rt,
    })
}

/// Gives up when no input came for [`IDLE_LIMIT`].
fn check_idle(ctx: &RoleCtx, last_input_ns: u64, what: &str) -> Result<()> {
    if now_ns().saturating_sub(last_input_ns) > IDLE_LIMIT.as_nanos() as u64 {
        bail!(
            "{}: no {what} for {IDLE_LIMIT:?}; giving up",
            ctx.role.name()
        );
    }
    Ok(())
}

fn summary(ctx: &RoleCtx, c: &Counters) {
    eprintln!(
        "{}: {} samples, {} stale inputs, {} rejected, {} dropped sends, {} to a gone peer",
        ctx.role.name(),
        c.samples,
        c.stale_inputs,
        c.rejected_inputs,
        c.dropped_sends,
        c.peer_gone
    );
}

/// The observer: measurement k → estimate k.
fn observer(ctx: &RoleCtx) -> Result<Counters> {
    let meas_rx = ctx.bind(OBS_MEAS)?;
    let to_cl = ctx.connect(CL_EST)?;
    let to_sl = ctx.connect(SL_EST)?;
    let mut obs = ObserverStep::new(ctx.sc);
    let mut c = Counters::default();
    let mut last_k: Option<u64> = None;
    ctx.ready()?;
    let mut last_input = now_ns();
    // ---- real-time loop: no allocation, no locks, no logging ----
    while !ctx.stopped() {
        let m = match meas_rx.recv::<Measurement>(true) {
            Recv::Msg(m) => m,
            Recv::Empty => {
                check_idle(ctx, last_input, "measurement from the plant")?;
                continue;
            }
            Recv::Malformed => {
                c.rejected_inputs += 1;
                continue;
            }
            Recv::Err(e) => return Err(recv_error(OBS_MEAS, e)),
        };
        last_input = now_ns();
        if m.hdr.is_warmup() || m.hdr.is_end() {
            let e = Estimate {
                hdr: m.hdr,
                ..Default::default()
            };
            send_control(&to_cl, &e)?;
            send_control(&to_sl, &e)?;
            if m.hdr.is_end() {
                break;
            }
            continue;
        }
        if !m.is_finite() || last_k.is_some_and(|l| m.hdr.k <= l) {
            c.rejected_inputs += 1;
            continue;
        }
        if let Some(l) = last_k {
            c.stale_inputs += m.hdr.k - l - 1;
        }
        last_k = Some(m.hdr.k);
        let mut est = obs.step(&m);
        est.hdr.t_pub_ns = now_ns();
        // The current loop (critical path) first.
        c.send(&to_cl, &est)?;
        c.send(&to_sl, &est)?;
        c.samples += 1;
    }
    // ---- end of the real-time loop ----
    summary(ctx, &c);
    Ok(c)
}

const MEAS_RING: usize = 64;
const IREF_RING: usize = 4;

/// Inputs received but not yet used, indexed by sample (fixed-size rings, no allocation).
struct Inbox {
    meas: [Option<Measurement>; MEAS_RING],
    iref: [Option<CurrentRef>; IREF_RING],
    divider: u64,
}

impl Inbox {
    #[inline]
    fn drain(&mut self, meas: &Rx, iref: &Rx, c: &mut Counters) -> Result<()> {
        loop {
            match meas.recv::<Measurement>(false) {
                Recv::Msg(m) => {
                    if m.hdr.is_warmup() {
                        continue;
                    }
                    if m.is_finite() || m.hdr.is_end() {
                        self.meas[(m.hdr.k % MEAS_RING as u64) as usize] = Some(m);
                    } else {
                        c.rejected_inputs += 1;
                    }
                }
                Recv::Empty => break,
                Recv::Malformed => c.rejected_inputs += 1,
                Recv::Err(e) => return Err(recv_error(CL_MEAS, e)),
            }
        }
        loop {
            match iref.recv::<CurrentRef>(false) {
                Recv::Msg(r) => {
                    if r.hdr.is_warmup() {
                        continue;
                    }
                    if r.is_finite() && !r.hdr.is_end() {
                        self.iref[((r.hdr.k / self.divider) % IREF_RING as u64) as usize] = Some(r);
                    } else if !r.hdr.is_end() {
                        c.rejected_inputs += 1;
                    }
                }
                Recv::Empty => break,
                Recv::Malformed => c.rejected_inputs += 1,
                Recv::Err(e) => return Err(recv_error(CL_IREF, e)),
            }
        }
        Ok(())
    }

    fn meas(&self, k: u64) -> Option<Measurement> {
        self.meas[(k % MEAS_RING as u64) as usize].filter(|m| m.hdr.k == k)
    }

    fn iref(&self, j: u64) -> Option<CurrentRef> {
        self.iref[((j / self.divider) % IREF_RING as u64) as usize].filter(|r| r.hdr.k == j)
    }
}

/// The current loop: measurement k + estimate k + current reference → command k.
fn current_loop(ctx: &RoleCtx) -> Result<Counters> {
    let meas_rx = ctx.bind(CL_MEAS)?;
    let est_rx = ctx.bind(CL_EST)?;
    let iref_rx = ctx.bind(CL_IREF)?;
    let to_plant = ctx.connect(PLANT_CMD)?;
    let mut ctrl = CurrentLoopStep::new(ctx.sc);
    let mut inbox = Inbox {
        meas: [None; MEAS_RING],
        iref: [None; IREF_RING],
        divider: u64::from(ctx.sc.rates.speed_divider),
    };
    let mut c = Counters::default();
    let mut last_k: Option<u64> = None;
    let mut active_ref = CurrentRef::default();
    ctx.ready()?;
    let mut last_input = now_ns();
    // ---- real-time loop: no allocation, no locks, no logging ----
    while !ctx.stopped() {
        let e = match est_rx.recv::<Estimate>(true) {
            Recv::Msg(e) => e,
            Recv::Empty => {
                check_idle(ctx, last_input, "estimate from the observer")?;
                continue;
            }
            Recv::Malformed => {
                c.rejected_inputs += 1;
                continue;
            }
            Recv::Err(e) => return Err(recv_error(CL_EST, e)),
        };
        last_input = now_ns();
        inbox.drain(&meas_rx, &iref_rx, &mut c)?;
        if e.hdr.is_warmup() || e.hdr.is_end() {
            send_control(
                &to_plant,
                &VoltageCommand {
                    hdr: e.hdr,
                    ..Default::default()
                },
            )?;
            if e.hdr.is_end() {
                break;
            }
            continue;
        }
        if !e.is_finite() || last_k.is_some_and(|l| e.hdr.k <= l) {
            c.rejected_inputs += 1;
            continue;
        }
        let k = e.hdr.k;
        if let Some(l) = last_k {
            c.stale_inputs += k - l - 1;
        }
        last_k = Some(k);
        let Some(meas) = inbox.meas(k) else {
            // The observer saw measurement k, so it was sent; we lost it.
            c.stale_inputs += 1;
            continue;
        };
        let mut stale_ref = false;
        if let Some(j) = ctrl.expected_ref_index(k) {
            match inbox.iref(j) {
                Some(r) => active_ref = r,
                None => {
                    // Real time: use the last reference we have, and count it.
                    c.stale_inputs += 1;
                    stale_ref = true;
                }
            }
        }
        let mut cmd = ctrl.step(&meas, &e, &active_ref);
        if stale_ref {
            cmd.hdr.flags |= FLAG_STALE_INPUT;
        }
        cmd.hdr.t_pub_ns = now_ns();
        c.send(&to_plant, &cmd)?;
        c.samples += 1;
    }
    // ---- end of the real-time loop ----
    summary(ctx, &c);
    Ok(c)
}

/// The speed loop: every N-th estimate → current reference.
fn speed_loop(ctx: &RoleCtx) -> Result<Counters> {
    let est_rx = ctx.bind(SL_EST)?;
    let to_cl = ctx.connect(CL_IREF)?;
    let mut ctrl = SpeedLoopStep::new(ctx.sc);
    let mut c = Counters::default();
    let mut last_k: Option<u64> = None;
    ctx.ready()?;
    let mut last_input = now_ns();
    // ---- real-time loop: no allocation, no locks, no logging ----
    while !ctx.stopped() {
        let e = match est_rx.recv::<Estimate>(true) {
            Recv::Msg(e) => e,
            Recv::Empty => {
                check_idle(ctx, last_input, "estimate from the observer")?;
                continue;
            }
            Recv::Malformed => {
                c.rejected_inputs += 1;
                continue;
            }
            Recv::Err(e) => return Err(recv_error(SL_EST, e)),
        };
        last_input = now_ns();
        if e.hdr.is_warmup() || e.hdr.is_end() {
            send_control(
                &to_cl,
                &CurrentRef {
                    hdr: e.hdr,
                    ..Default::default()
                },
            )?;
            if e.hdr.is_end() {
                break;
            }
            continue;
        }
        if !e.is_finite() || last_k.is_some_and(|l| e.hdr.k <= l) {
            c.rejected_inputs += 1;
            continue;
        }
        if let Some(l) = last_k {
            c.stale_inputs += e.hdr.k - l - 1;
        }
        last_k = Some(e.hdr.k);
        if let Some(mut r) = ctrl.step(&e) {
            r.hdr.t_pub_ns = now_ns();
            c.send(&to_cl, &r)?;
            c.samples += 1;
        }
    }
    // ---- end of the real-time loop ----
    summary(ctx, &c);
    Ok(c)
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
    /// Plant: result file (JSON; histograms beside it as `<out>.cycle.hdr`,
    /// `<out>.lateness.hdr`).
    pub out: Option<PathBuf>,
}

/// Set by SIGTERM/SIGINT in node processes.
static STOP: AtomicBool = AtomicBool::new(false);

extern "C" fn on_signal(_sig: libc::c_int) {
    STOP.store(true, Ordering::SeqCst);
}

fn install_signal_handlers() -> Result<()> {
    for sig in [libc::SIGINT, libc::SIGTERM] {
        // SAFETY: `sa` is zero-initialised and then filled in; its handler is an `extern "C"`
        // function that only stores to an atomic (async-signal-safe). No SA_RESTART: a blocked
        // recv returns EINTR and the loop sees the stop flag at once.
        let rc = unsafe {
            let mut sa: libc::sigaction = std::mem::zeroed();
            sa.sa_sigaction = on_signal as *const () as libc::sighandler_t;
            libc::sigemptyset(&mut sa.sa_mask);
            libc::sigaction(sig, &sa, std::ptr::null_mut())
        };
        if rc != 0 {
            bail!(
                "cannot install handler for signal {sig}: {}",
                std::io::Error::last_os_error()
            );
        }
    }
    Ok(())
}

/// Asks the kernel to send SIGTERM when the parent (the bench runner) dies, so that a node is
/// never left behind; stops at once if the parent is already gone.
fn stop_with_parent() {
    // SAFETY: prctl(PR_SET_PDEATHSIG) takes a signal number, no pointers.
    unsafe {
        libc::prctl(
            libc::PR_SET_PDEATHSIG,
            libc::SIGTERM as libc::c_ulong,
            0,
            0,
            0,
        )
    };
    // SAFETY: getppid has no arguments and cannot fail.
    if unsafe { libc::getppid() } == 1 {
        STOP.store(true, Ordering::SeqCst);
    }
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
    };
    std::fs::write(out, serde_json::to_vec_pretty(&f)?)
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
    })
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
    stop_with_parent();
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
        stop: &STOP,
        announce: true,
        keep_trace: false,
    };
    let out = run_role(&ctx).with_context(|| format!("bench-node uds {}", role.name()))?;
    if let (Some(p), Some(path)) = (out, &args.out) {
        write_plant_file(path, &p)?;
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

/// One node process.
struct Kid {
    role: Role,
    child: Child,
    log: PathBuf,
    status: Option<ExitStatus>,
}

/// The node processes; on drop every one still running gets SIGTERM, then SIGKILL after
/// [`TERM_GRACE`], and is reaped — on every path, errors and panics included.
#[derive(Default)]
struct Kids(Vec<Kid>);

impl Kids {
    /// Reaps whatever has exited; true when all have.
    fn poll(&mut self) -> bool {
        let mut all = true;
        for k in &mut self.0 {
            if k.status.is_none() {
                k.status = k.child.try_wait().ok().flatten();
            }
            all &= k.status.is_some();
        }
        all
    }

    fn terminate(&mut self) {
        for k in &mut self.0 {
            if k.status.is_none() {
                // The child has not been reaped, so its pid still names it (at worst a zombie).
                if let Ok(pid) = libc::pid_t::try_from(k.child.id()) {
                    // SAFETY: kill(2) on our own unreaped child; no pointers.
                    unsafe { libc::kill(pid, libc::SIGTERM) };
                }
            }
        }
        let started = Instant::now();
        while !self.poll() && started.elapsed() < TERM_GRACE {
            std::thread::sleep(Duration::from_millis(10));
        }
        for k in &mut self.0 {
            if k.status.is_none() {
                let _ = k.child.kill();
                k.status = k.child.wait().ok();
            }
        }
    }
}

impl Drop for Kids {
    fn drop(&mut self) {
        self.terminate();
    }
}

/// The last few lines of a node's log, for error messages.
fn log_tail(log: &Path) -> String {
    let text = std::fs::read_to_string(log).unwrap_or_default();
    let lines: Vec<&str> = text
        .lines()
        .map(str::trim)
        .filter(|l| !l.is_empty() && *l != "READY")
        .collect();
    let tail = &lines[lines.len().saturating_sub(3)..];
    if tail.is_empty() {
        format!("(no output; log {})", log.display())
    } else {
        format!("{} (log {})", tail.join(" | "), log.display())
    }
}

/// Unix-socket chain: the same four roles as four processes exchanging the same message
/// structs over Unix domain datagram sockets in a private temp dir (removed afterwards). The
/// processes are started as `exe bench-node uds --role <role> --dir <sockdir> --scenario
/// <file> --seconds S [--core C] [--priority P] [--out <file>]`; the scenario file, the
/// plant's result files and one log per node (`uds-<role>.log`, stdout and stderr) go to
/// `workdir`. Watchdog: seconds × 3 + 20 s; no process is left behind on any path.
pub fn run_uds_chain(spec: &ChainSpec, exe: &Path, workdir: &Path) -> Result<VariantResult> {
    schedule(spec.scenario.rates.sample_hz, spec.seconds)?;
    std::fs::create_dir_all(workdir)
        .with_context(|| format!("cannot create {}", workdir.display()))?;
    let scenario = workdir.join("uds-scenario.toml");
    std::fs::write(&scenario, toml::to_string(&spec.scenario)?)
        .with_context(|| format!("write {}", scenario.display()))?;
    let out = workdir.join("uds-plant.json");
    for p in [
        out.clone(),
        sibling(&out, ".cycle.hdr"),
        sibling(&out, ".lateness.hdr"),
    ] {
        let _ = std::fs::remove_file(p);
    }
    // Declared before the processes so that it is dropped (removed) after they are reaped.
    let sock = SockDir::create("drivelab-uds")?;
    let mut kids = Kids::default();
    // Downstream first; the plant waits for its peers' sockets anyway.
    for (role, node) in [
        (Role::Observer, spec.observer),
        (Role::CurrentLoop, spec.current_loop),
        (Role::SpeedLoop, spec.speed_loop),
        (Role::Plant, spec.plant),
    ] {
        let log = workdir.join(format!("uds-{}.log", role.name()));
        let f = std::fs::File::create(&log)
            .with_context(|| format!("cannot create {}", log.display()))?;
        let mut cmd = Command::new(exe);
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
        if role == Role::Plant {
            cmd.arg("--out").arg(&out);
        }
        cmd.stdin(Stdio::null()).stdout(f.try_clone()?).stderr(f);
        let child = cmd
            .spawn()
            .with_context(|| format!("cannot start {} for the {}", exe.display(), role.name()))?;
        kids.0.push(Kid {
            role,
            child,
            log,
            status: None,
        });
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
                        k.role.name(),
                        log_tail(&k.log)
                    );
                }
                if k.role == Role::Plant && plant_done.is_none() {
                    plant_done = Some(Instant::now());
                }
            }
        }
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
                .map(|k| k.role.name())
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
    read_plant_file(&out)
}

/// Runs the four roles as threads of this process over the same sockets (tests; no RT).
#[cfg(test)]
pub(crate) fn run_chain_threads(
    sc: &Scenario,
    seconds: f64,
    keep_trace: bool,
) -> Result<PlantOutcome> {
    let sock = SockDir::create("drivelab-udst")?;
    let stop = AtomicBool::new(false);
    let ctx = |role| RoleCtx {
        role,
        dir: &sock.path,
        sc,
        seconds,
        node: NodeSpec::default(),
        lock_memory: false,
        stop: &stop,
        announce: false,
        keep_trace,
    };
    std::thread::scope(|s| {
        let run = |role| {
            let c = ctx(role);
            let stop = &stop;
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
    use crate::testutil::kyslan;
    use drivelab_runtime::drive::InProcessDrive;

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

    #[test]
    fn thread_chain_matches_the_inprocess_trace() {
        let sc = kyslan(2000.0);
        let p = run_chain_threads(&sc, 0.05, true).unwrap();
        assert_eq!(p.result.samples, 100);
        // One wake-up per sample plus the one that takes the last command.
        assert_eq!(p.result.lateness.len(), 101);
        assert!(!p.result.cycle.is_empty());
        assert_eq!(p.counters.samples, 100);
        // Determinism across transports: every row up to the first miss (all of them when
        // nothing missed) is bit-identical to the in-process chain's.
        let mut d = InProcessDrive::new(&sc);
        let reference: Vec<TraceRow> = (0..100).map(|k| d.cycle(k)).collect();
        eprintln!(
            "uds threads: {} misses, {} stale-input commands, {} rows compared, cycle {:?}",
            p.result.misses.misses,
            p.counters.stale_input_commands,
            p.trace.len(),
            p.result.cycle.percentiles()
        );
        assert_eq!(p.trace[..], reference[..p.trace.len()]);
        if p.result.misses.misses == 0 && p.counters.stale_input_commands == 0 {
            assert_eq!(p.trace.len(), 100);
        }
    }

    /// In a `bench-node uds` trampoline process (see the end-to-end test) this runs the node;
    /// in a normal test run it does nothing.
    #[test]
    fn node_trampoline() {
        let Ok(a) = std::env::var("DRIVELAB_BENCH_UDS_NODE_ARGS") else {
            return;
        };
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
                 exec '{}' --exact uds::tests::node_trampoline --nocapture --test-threads=1 -q\n",
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
        let mut kids: Vec<(&str, Child)> = ["observer", "current-loop", "speed-loop", "plant"]
            .into_iter()
            .map(|r| (r, spawn(r)))
            .collect();
        let term_and_wait = |c: &mut Child| {
            // SAFETY: kill(2) on our own unreaped child.
            unsafe { libc::kill(c.id() as libc::pid_t, libc::SIGTERM) };
            let t = Instant::now();
            loop {
                if let Some(s) = c.try_wait().unwrap() {
                    return (s, t.elapsed());
                }
                assert!(
                    t.elapsed() < Duration::from_secs(3),
                    "no exit after SIGTERM"
                );
                std::thread::sleep(Duration::from_millis(5));
            }
        };
        // Let the chain run (warm-up done once the plant has measured something).
        std::thread::sleep(Duration::from_millis(600));
        for (_, c) in &mut kids {
            assert!(c.try_wait().unwrap().is_none(), "a node ended early");
        }
        // A downstream node first, then the plant, then the rest.
        for i in [0usize, 3, 1, 2] {
            let (role, c) = &mut kids[i];
            let (s, dt) = term_and_wait(c);
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

    /// Manual measurement (no assertions): `DRIVELAB_BENCH_SECONDS=2 cargo test -p
    /// drivelab-bench --release manual_measurement -- --ignored --nocapture`. Needs root
    /// for SCHED_FIFO; one-core placement on the last CPU, priorities as `drivelab bench`.
    #[test]
    #[ignore]
    fn manual_measurement() {
        let seconds: f64 = std::env::var("DRIVELAB_BENCH_SECONDS")
            .ok()
            .and_then(|s| s.parse().ok())
            .unwrap_or(2.0);
        let hz: f64 = std::env::var("DRIVELAB_BENCH_HZ")
            .ok()
            .and_then(|s| s.parse().ok())
            .unwrap_or(10_000.0);
        let core = drivelab_runtime::rt::online_cpus() - 1;
        let at = |p| NodeSpec {
            core: Some(core),
            priority: Some(p),
        };
        let work = std::env::temp_dir().join(format!("drivelab-bench-man-{}", std::process::id()));
        std::fs::create_dir_all(&work).unwrap();
        let spec = ChainSpec {
            scenario: kyslan(hz),
            seconds,
            plant: at(70),
            observer: at(72),
            current_loop: at(76),
            speed_loop: at(74),
        };
        let show = |name: &str, r: &VariantResult| {
            let c = r.cycle.percentiles();
            let l = r.lateness.percentiles();
            eprintln!(
                "{name:>9}: {} samples, cycle p50 {:.1} p99 {:.1} p99.9 {:.1} max {:.0} µs; \
                 lateness p50 {:.1} p99 {:.1} µs; misses {} (longest run {})",
                r.samples,
                c.p50,
                c.p99,
                c.p999,
                c.max,
                l.p50,
                l.p99,
                r.misses.misses,
                r.misses.longest_run
            );
        };
        show(
            "floor",
            &crate::run_floor(hz, seconds, &spec.plant).unwrap(),
        );
        show("inprocess", &crate::run_inprocess(&spec).unwrap());
        let script = fake_drivelab(&work);
        show(
            "uds",
            &run_uds_chain(&spec, &script, &work.join("uds")).unwrap(),
        );
        std::fs::remove_dir_all(&work).unwrap();
    }
}
