//! The drive's side of the bridge: `drivelab bridge`, started by `drivelab run
//! --zenoh-listen` (docs/architecture.md, "Across machines (Zenoh)").
//!
//! It is not real-time. It moves itself off the drive's cores at nice 10 before Zenoh starts
//! its threads, reads the chosen topics with polled subscribers (a real-time sender pays one
//! more queue write per message and no wake-up; the buffers overflow safely, so a stalled
//! bridge never blocks a stage), and every millisecond puts what arrived as one frame per
//! topic on `drivelab/<bus>/<topic>`. It answers queries on `drivelab/<bus>/q/...`: the
//! scenario, the event history, the newest view, the history of truth, cmd and wref (for a
//! recorder that joins late) and fault requests, which go onto the bus only when the drive
//! was started with `--allow-remote-faults`.
//!
//! The launcher talks to it by lines on its stdin/stdout: it prints `ready` once listening,
//! answers `detach` (let go of the bus before its files are removed) with `detached STATS`,
//! and `summary PATH` (publish the run's summary, then exit) with `done`. End of input
//! (the launcher died) ends it too.

use crate::codec::{self, Wire};
use crate::link::{self, Side};
use crate::split;
use anyhow::{anyhow, bail, Context, Result};
use drivelab_runtime::bus::{self, DriveTopics, MAX_BUFFER};
use drivelab_runtime::config::Scenario;
use drivelab_runtime::telemetry::{self as tm, DriveView, EventEntry, FaultRequest};
use iceoryx2::prelude::*;
use std::collections::VecDeque;
use std::io::{BufRead, Write};
use std::path::PathBuf;
use std::sync::mpsc;
use std::time::{Duration, Instant};
use zenoh::Wait;

/// Samples of truth, cmd and wref kept for a recorder that joins late: 6.5 s at 10 kHz,
/// about 15 MB.
pub const HISTORY_MAX: usize = 1 << 16;
/// Events kept for a monitor that joins late (as the supervisor's hub).
pub const EVENTS_KEPT: usize = 64;
/// SCHED_FIFO priority of a split drive's bridge (below the stages' 70 and up).
pub const LINK_PRIORITY: i32 = 60;
/// How long the bridge sleeps when nothing arrived.
pub const POLL: Duration = Duration::from_millis(1);

/// Options of `drivelab bridge`.
#[derive(Debug, Clone)]
pub struct ServeOptions {
    /// Bus id of the drive.
    pub bus: String,
    /// Endpoint to listen on (checked by [`link::check_endpoint`]).
    pub listen: String,
    /// Zenoh configuration file (TLS, access control).
    pub config: Option<PathBuf>,
    /// Take fault requests from the network.
    pub allow_remote_faults: bool,
    /// Short names of the topics to forward.
    pub topics: Vec<String>,
    /// The run folder (its scenario.toml describes the drive).
    pub run_dir: PathBuf,
    /// Connect to `listen` (a Zenoh client) instead of listening there: the side of a split
    /// drive that joins the other.
    pub connect: bool,
    /// This machine of a split drive, and the drive's clock (`realtime` or `lockstep`): the
    /// bridge carries the topics that cross to the other machine ([`crate::split`]).
    pub split: Option<(String, String)>,
    /// A split drive: how long the joining side retries its connection and each side waits
    /// for the other to be ready.
    pub wait: Duration,
}

/// What a listening side of a split drive tells the joining side (`q/split`).
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
pub struct SplitInfo {
    /// The listening machine.
    pub machine: String,
    /// The drive's clock.
    pub clock: String,
    /// The resolved scenario (both sides must run the same).
    pub scenario: String,
}

/// What the bridge did, reported on `detach` and in `summary.json → bridge`.
#[derive(Debug, Default, Clone, serde::Serialize)]
pub struct Stats {
    /// Endpoint it listened on.
    pub listen: String,
    /// Messages put on Zenoh, per topic.
    pub forwarded: std::collections::BTreeMap<String, u64>,
    /// Frames put on Zenoh (each holds the messages of one topic since the last poll).
    pub frames: u64,
    /// Fault requests passed to the supervisor.
    pub faults_forwarded: u64,
    /// Fault requests refused: the drive does not allow remote faults.
    pub faults_refused: u64,
    /// Inbound frames rejected as foreign or malformed (see `codec::Reject`).
    pub rejected: u64,
    /// Bus messages not forwarded because the other side would reject them (NaN, ∞).
    pub implausible: u64,
    /// Queries answered.
    pub queries: u64,
    /// Replies that could not be sent (the client had gone).
    pub failed_replies: u64,
    /// CPU time the bridge process used (user + system, all its threads), s.
    pub cpu_s: f64,
    /// The scheduling policies of the bridge process's threads (its own and Zenoh's), read
    /// back from the kernel when it detached: policy name → threads.
    pub thread_policies: std::collections::BTreeMap<String, u64>,
    /// The split link's counters (a drive split across machines).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub split: Option<serde_json::Value>,
}

/// CPU time of this process so far (user + system), s.
fn cpu_s() -> f64 {
    // SAFETY: getrusage fills the zeroed struct we own; RUSAGE_SELF covers all threads.
    let ru = unsafe {
        let mut ru: libc::rusage = std::mem::zeroed();
        libc::getrusage(libc::RUSAGE_SELF, &mut ru);
        ru
    };
    let t = |tv: libc::timeval| tv.tv_sec as f64 + tv.tv_usec as f64 * 1e-6;
    t(ru.ru_utime) + t(ru.ru_stime)
}

/// The scheduling policy of each thread of this process, counted by name.
fn thread_policies() -> std::collections::BTreeMap<String, u64> {
    let mut m = std::collections::BTreeMap::new();
    let Ok(tasks) = std::fs::read_dir("/proc/self/task") else {
        return m;
    };
    for tid in tasks
        .flatten()
        .filter_map(|e| e.file_name().to_str()?.parse().ok())
    {
        // SAFETY: sched_getscheduler reads the policy of a thread id; no memory is passed.
        let policy = unsafe { libc::sched_getscheduler(tid) };
        let name = match policy {
            libc::SCHED_OTHER => "SCHED_OTHER",
            libc::SCHED_FIFO => "SCHED_FIFO",
            libc::SCHED_RR => "SCHED_RR",
            libc::SCHED_BATCH => "SCHED_BATCH",
            libc::SCHED_IDLE => "SCHED_IDLE",
            // The thread ended since it was listed.
            -1 => continue,
            _ => "other",
        };
        *m.entry(name.to_string()).or_insert(0) += 1;
    }
    m
}

/// A bus subscriber the bridge drains.
trait Drain<T> {
    fn next(&self) -> Result<Option<T>>;
}

impl<T: std::fmt::Debug + ZeroCopySend + Copy + 'static> Drain<T> for bus::Receiver<T> {
    fn next(&self) -> Result<Option<T>> {
        self.try_recv()
    }
}

impl<T: std::fmt::Debug + ZeroCopySend + Copy + 'static> Drain<T> for tm::PlainReceiver<T> {
    fn next(&self) -> Result<Option<T>> {
        self.try_recv()
    }
}

/// One forwarded topic.
trait Pump {
    /// Drains the bus subscriber and puts what arrived; returns the messages forwarded.
    fn pump(&mut self, stats: &mut Stats) -> Result<usize>;
    /// Frames of the kept history (for `q/history/NAME` and `q/events`), oldest first.
    fn history_frames(&self) -> Vec<Vec<u8>>;
    /// The topic's short name.
    fn name(&self) -> &'static str;
}

struct Forward<T: Wire, R: Drain<T>> {
    /// None once `ends` saw the last message (the view's END): the subscriber is gone, so
    /// the supervisor does not wait for the bridge to detach as it waits for monitors.
    rx: Option<R>,
    ends: fn(&T) -> bool,
    publisher: zenoh::pubsub::Publisher<'static>,
    batch: Vec<T>,
    buf: Vec<u8>,
    /// Kept messages (0: none), newest last.
    keep: usize,
    kept: VecDeque<T>,
    /// Forward only the newest message of each poll (the view).
    newest_only: bool,
}

impl<T: Wire, R: Drain<T>> Pump for Forward<T, R> {
    fn pump(&mut self, stats: &mut Stats) -> Result<usize> {
        let mut total = 0;
        loop {
            self.batch.clear();
            let Some(rx) = &self.rx else {
                return Ok(total);
            };
            while self.batch.len() < codec::MAX_COUNT {
                match rx.next()? {
                    // What the receiving side would reject (a `corrupt` fault's NaN) is not
                    // sent: that sample goes missing there, as it does in a local trace.
                    Some(m) if !m.plausible() => stats.implausible += 1,
                    Some(m) if self.newest_only => {
                        self.batch.clear();
                        self.batch.push(m);
                    }
                    Some(m) => self.batch.push(m),
                    None => break,
                }
            }
            if self.batch.is_empty() {
                return Ok(total);
            }
            if self.batch.iter().any(self.ends) {
                self.rx = None;
            }
            if self.keep > 0 {
                for m in &self.batch {
                    if self.kept.len() == self.keep {
                        self.kept.pop_front();
                    }
                    self.kept.push_back(*m);
                }
            }
            codec::encode_into(&self.batch, &mut self.buf);
            self.publisher
                .put(self.buf.clone())
                .wait()
                .map_err(|e| anyhow!("zenoh put {}: {e}", T::NAME))?;
            stats.frames += 1;
            *stats.forwarded.entry(T::NAME.to_string()).or_default() += self.batch.len() as u64;
            total += self.batch.len();
            if self.batch.len() < codec::MAX_COUNT {
                return Ok(total);
            }
        }
    }

    fn history_frames(&self) -> Vec<Vec<u8>> {
        let all: Vec<T> = self.kept.iter().copied().collect();
        all.chunks(codec::MAX_COUNT).map(codec::encode).collect()
    }

    fn name(&self) -> &'static str {
        T::NAME
    }
}

/// Why a fault request from the network does not reach the supervisor.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Refusal {
    /// The drive was not started with `--allow-remote-faults`.
    NotAllowed,
    /// The request is no valid frame of one [`FaultRequest`].
    Malformed(String),
}

impl std::fmt::Display for Refusal {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Refusal::NotAllowed => write!(
                f,
                "remote faults are not allowed on this drive (start it with --allow-remote-faults)"
            ),
            Refusal::Malformed(why) => write!(f, "malformed fault request: {why}"),
        }
    }
}

/// Checks a fault request from the network: one well-formed [`FaultRequest`], and a drive
/// that allows remote faults. Counts a refusal in `stats`.
pub fn check_fault(
    payload: &[u8],
    allow: bool,
    stats: &mut Stats,
) -> Result<FaultRequest, Refusal> {
    let reqs = match codec::decode::<FaultRequest>(payload) {
        Ok(r) if r.len() == 1 => r,
        Ok(r) => {
            stats.rejected += 1;
            return Err(Refusal::Malformed(format!(
                "{} requests in one frame",
                r.len()
            )));
        }
        Err(e) => {
            stats.rejected += 1;
            return Err(Refusal::Malformed(e.to_string()));
        }
    };
    if !allow {
        stats.faults_refused += 1;
        return Err(Refusal::NotAllowed);
    }
    Ok(reqs[0])
}

/// The bridge's bus side: dropped on `detach`.
struct BusSide {
    pumps: Vec<Box<dyn Pump>>,
    fault_tx: tm::PlainSender<FaultRequest>,
    _fault_topic: tm::Plain<FaultRequest>,
    _plain: Vec<Box<dyn std::any::Any>>,
    _topics: DriveTopics,
    _node: Node<ipc::Service>,
}

fn forward<T: Wire, R: Drain<T> + 'static>(
    session: &zenoh::Session,
    bus_id: &str,
    rx: R,
    keep: usize,
    newest_only: bool,
    ends: fn(&T) -> bool,
) -> Result<Box<dyn Pump>> {
    let publisher = session
        .declare_publisher(crate::key(bus_id, T::NAME))
        // The bridge is not real-time: it waits for a slow network rather than drop, and
        // its own bus buffer absorbs (or, safely, overflows) meanwhile.
        .congestion_control(zenoh::qos::CongestionControl::Block)
        .wait()
        .map_err(|e| anyhow!("zenoh publisher {}: {e}", T::NAME))?;
    Ok(Box::new(Forward {
        rx: Some(rx),
        ends,
        publisher,
        batch: Vec::with_capacity(codec::MAX_COUNT),
        buf: Vec::new(),
        keep,
        kept: VecDeque::new(),
        newest_only,
    }))
}

fn never<T>(_: &T) -> bool {
    false
}

fn attach(o: &ServeOptions, sc: &Scenario, session: &zenoh::Session) -> Result<BusSide> {
    let node = bus::node(&o.bus, "zenoh-bridge")?;
    let topics = DriveTopics::open_with(&node, sc.timing.wake, &o.bus)?;
    let mut pumps: Vec<Box<dyn Pump>> = Vec::new();
    let mut plain: Vec<Box<dyn std::any::Any>> = Vec::new();
    let want = |t: &str| o.topics.iter().any(|x| x == t);
    let b = o.bus.as_str();
    // Polled receivers only: a listener would cost the real-time senders a wake-up. The
    // plant's truth and the command (the trace's parts) and the outer reference keep a
    // history for a late recorder; the rest only their live stream.
    macro_rules! drive_topic {
        ($name:literal, $field:ident, $keep:expr) => {
            if want($name) {
                let rx = topics.$field.polled_receiver(MAX_BUFFER)?;
                pumps.push(forward(session, b, rx, $keep, false, never)?);
            }
        };
    }
    drive_topic!("meas", meas, 0);
    drive_topic!("truth", truth, HISTORY_MAX);
    drive_topic!("est", est, 0);
    drive_topic!("iref", iref, 0);
    drive_topic!("cmd", cmd, HISTORY_MAX);
    drive_topic!("wref", wref, HISTORY_MAX);
    // The supervisor's telemetry exists before the bridge starts (the launcher made it).
    if want("view") {
        let t = tm::open_existing::<DriveView>(&node, tm::TOPIC_VIEW)?;
        let rx = tm::PlainReceiver::new(&t, 4)?;
        plain.push(Box::new(t));
        pumps.push(forward(session, b, rx, 1, true, |v: &DriveView| {
            v.hdr.is_end()
        })?);
    }
    if want("events") {
        let t = tm::open_existing::<EventEntry>(&node, tm::TOPIC_EVENTS)?;
        let rx = tm::PlainReceiver::new(&t, EVENTS_KEPT)?;
        plain.push(Box::new(t));
        pumps.push(forward(session, b, rx, EVENTS_KEPT, false, never)?);
    }
    let fault_topic = tm::open_existing::<FaultRequest>(&node, tm::TOPIC_FAULT_REQ)?;
    Ok(BusSide {
        pumps,
        fault_tx: tm::PlainSender::new(&fault_topic)?,
        _fault_topic: fault_topic,
        _plain: plain,
        _topics: topics,
        _node: node,
    })
}

/// Answers one query on `drivelab/<bus>/q/...`.
fn answer(
    q: &zenoh::query::Query,
    o: &ServeOptions,
    scenario_toml: &str,
    side: Option<&BusSide>,
    summary: Option<&str>,
    stats: &mut Stats,
) -> Result<()> {
    stats.queries += 1;
    // The query's key may name this bus or a wildcard (`drivelab/*/q/scenario` finds the
    // drives); the reply names this bus.
    let asked = q.key_expr().as_str().to_string();
    let what = asked
        .splitn(4, '/')
        .nth(3)
        .filter(|_| asked.split('/').nth(2) == Some("q"))
        .unwrap_or("")
        .to_string();
    let key = crate::query_key(&o.bus, &what);
    let reply = |bytes: Vec<u8>| {
        q.reply(key.as_str(), bytes)
            .wait()
            .map_err(|e| anyhow!("zenoh reply: {e}"))
    };
    let reply_err = |text: String| {
        q.reply_err(text.into_bytes())
            .wait()
            .map_err(|e| anyhow!("zenoh reply: {e}"))
    };
    match what.as_str() {
        "scenario" => reply(scenario_toml.as_bytes().to_vec()),
        // Read when asked (a recorder asks once): written beside scenario.toml before the
        // bridge starts.
        "topology" => match std::fs::read(o.run_dir.join("topology.json")) {
            Ok(t) => reply(t),
            Err(e) => reply_err(format!("the drive's topology.json: {e}")),
        },
        "split" => match (&o.split, o.connect) {
            (Some((machine, clock)), false) => reply(serde_json::to_vec(&SplitInfo {
                machine: machine.clone(),
                clock: clock.clone(),
                scenario: scenario_toml.to_string(),
            })?),
            _ => reply_err("this drive is not the listening side of a split drive".into()),
        },
        "summary" => match summary {
            Some(s) => reply(s.as_bytes().to_vec()),
            None => reply_err("the drive has not ended yet".into()),
        },
        "fault" => {
            let payload = q
                .payload()
                .map(|p| p.to_bytes().into_owned())
                .unwrap_or_default();
            match check_fault(&payload, o.allow_remote_faults, stats) {
                Err(r) => {
                    drivelab_runtime::errln!("drivelab bridge: refused a fault request: {r}");
                    reply_err(r.to_string())
                }
                Ok(req) => match side {
                    None => reply_err("the drive has ended; no fault to inject".into()),
                    Some(s) => {
                        s.fault_tx.send(&req)?;
                        stats.faults_forwarded += 1;
                        reply(b"forwarded to the supervisor".to_vec())
                    }
                },
            }
        }
        other => {
            let name = other.strip_prefix("history/").unwrap_or(other);
            let pump = side.and_then(|s| s.pumps.iter().find(|p| p.name() == name));
            match pump {
                Some(p) => {
                    for f in p.history_frames() {
                        reply(f)?;
                    }
                    Ok(())
                }
                None => reply_err(format!("nothing to answer for '{other}'")),
            }
        }
    }
}

/// Runs the bridge until the launcher says `summary` or goes away.
pub fn serve(o: &ServeOptions) -> Result<()> {
    bus::check_bus_id(&o.bus)?;
    link::check_endpoint(&o.listen, !o.connect).map_err(|e| anyhow!(e))?;
    let sc_path = o.run_dir.join("scenario.toml");
    let scenario_toml = std::fs::read_to_string(&sc_path)
        .with_context(|| format!("cannot read {}", sc_path.display()))?;
    let sc = Scenario::from_toml(&scenario_toml, &sc_path.display().to_string())
        .map_err(|e| anyhow!(e))?;
    let rt_cores = drivelab_runtime::topology::cores(&sc.topology());
    // Before Zenoh starts its threads, so that they inherit the placement.
    let mut placed = drivelab_runtime::rt::keep_off(rt_cores, "zenoh bridge");
    // A split drive's link is on its data path: the bridge and Zenoh's threads (they
    // inherit the policy) run at SCHED_FIFO, below every stage, still off the drive's cores.
    // Not in lockstep, whose processes run as normal tasks (docs/architecture.md, "Clocks"):
    // with no deadline to keep, a long simulation must not hold a core at real-time priority.
    if o.split
        .as_ref()
        .is_some_and(|(_, clock)| clock == "lockstep")
    {
        placed = format!("{placed}; link at SCHED_OTHER (lockstep)");
    } else if o.split.is_some() {
        match drivelab_runtime::rt::set_scheduler(libc::SCHED_FIFO, LINK_PRIORITY) {
            Ok(()) => placed = format!("{placed}; link at SCHED_FIFO {LINK_PRIORITY}"),
            Err(e) => {
                placed = format!(
                    "{placed}; link not real-time ({})",
                    drivelab_runtime::rt::os_error_text(&e)
                )
            }
        }
    }
    let side_of_link = if o.connect {
        Side::Connect
    } else {
        Side::Listen
    };
    let session = open_session(side_of_link, o)?;
    let queries = session
        .declare_queryable(crate::query_key(&o.bus, "**"))
        .wait()
        .map_err(|e| anyhow!("zenoh queryable: {e}"))?;
    let summary_pub = session
        .declare_publisher(crate::key(&o.bus, "summary"))
        .congestion_control(zenoh::qos::CongestionControl::Block)
        .wait()
        .map_err(|e| anyhow!("zenoh publisher summary: {e}"))?;
    let mut split = match &o.split {
        Some((machine, clock)) => Some(start_split(
            o,
            &sc,
            &scenario_toml,
            machine,
            clock,
            &session,
        )?),
        None => None,
    };
    // Set when the launcher says `peer`: until when the other machine may take to join.
    let mut meeting: Option<Instant> = None;
    let mut side = Some(attach(o, &sc, &session)?);
    let mut stats = Stats {
        listen: o.listen.clone(),
        ..Default::default()
    };
    let (tx, commands) = mpsc::channel::<String>();
    std::thread::Builder::new()
        .name("bridge-stdin".into())
        .spawn(move || {
            for line in std::io::stdin().lock().lines() {
                let Ok(line) = line else { break };
                if tx.send(line).is_err() {
                    break;
                }
            }
        })?;
    say(&format!("ready {placed}"))?;
    let mut summary: Option<String> = None;
    loop {
        let mut moved = 0;
        if let Some(s) = side.as_mut() {
            for p in s.pumps.iter_mut() {
                moved += p.pump(&mut stats)?;
            }
        }
        while let Ok(Some(q)) = queries.try_recv() {
            // A client that left before its answer is no reason to stop the bridge.
            if let Err(e) = answer(
                &q,
                o,
                &scenario_toml,
                side.as_ref(),
                summary.as_deref(),
                &mut stats,
            ) {
                stats.failed_replies += 1;
                drivelab_runtime::errln!("drivelab bridge: {e:#}");
            }
        }
        if let Some(sp) = split.as_mut() {
            if let Some(until) = meeting {
                if sp.met()? {
                    meeting = None;
                    say("peer")?;
                } else if Instant::now() > until {
                    bail!(
                        "machine '{}' did not join within {} s (start its side with --machine {} {})",
                        sp.there(),
                        o.wait.as_secs(),
                        sp.there(),
                        if o.connect {
                            "--zenoh-listen ENDPOINT"
                        } else {
                            "--zenoh-connect ENDPOINT"
                        }
                    );
                }
            } else {
                sp.check()?;
                if sp.left()? {
                    say(&format!(
                        "lost machine '{}' left the split link",
                        sp.there()
                    ))?;
                }
            }
        }
        match commands.try_recv() {
            Ok(line) if line == "peer" => match split.as_mut() {
                Some(sp) => {
                    sp.announce(&session)?;
                    meeting = Some(Instant::now() + o.wait);
                }
                None => bail!("bridge: 'peer' without a split drive"),
            },
            Ok(line) if line == "detach" => {
                if let Some(sp) = split.take() {
                    stats.split = Some(sp.finish()?);
                }
                if let Some(mut s) = side.take() {
                    for p in s.pumps.iter_mut() {
                        p.pump(&mut stats)?;
                    }
                }
                stats.cpu_s = cpu_s();
                stats.thread_policies = thread_policies();
                say(&format!("detached {}", serde_json::to_string(&stats)?))?;
            }
            Ok(line) if line.starts_with("summary ") => {
                let path = line.trim_start_matches("summary ");
                let text =
                    std::fs::read_to_string(path).with_context(|| format!("cannot read {path}"))?;
                summary_pub
                    .put(text.clone().into_bytes())
                    .wait()
                    .map_err(|e| anyhow!("zenoh put summary: {e}"))?;
                summary = Some(text);
                // Recorders leave once they have it; answer their queries meanwhile.
                let t = Instant::now();
                while t.elapsed() < Duration::from_secs(2) && subscribed(&summary_pub) {
                    while let Ok(Some(q)) = queries.try_recv() {
                        if answer(&q, o, &scenario_toml, None, summary.as_deref(), &mut stats)
                            .is_err()
                        {
                            stats.failed_replies += 1;
                        }
                    }
                    std::thread::sleep(Duration::from_millis(10));
                }
                say("done")?;
                break;
            }
            Ok(other) => bail!("bridge: unknown command '{other}'"),
            Err(mpsc::TryRecvError::Disconnected) => break,
            Err(mpsc::TryRecvError::Empty) => {}
        }
        if moved == 0 {
            std::thread::sleep(POLL);
        }
    }
    drop(side);
    session
        .close()
        .wait()
        .map_err(|e| anyhow!("zenoh close: {e}"))?;
    Ok(())
}

fn open_session(side: Side, o: &ServeOptions) -> Result<zenoh::Session> {
    if side == Side::Listen {
        return link::open(side, &o.listen, o.config.as_deref());
    }
    let t = Instant::now();
    loop {
        match link::open(side, &o.listen, o.config.as_deref()) {
            Ok(s) => return Ok(s),
            Err(e) if t.elapsed() >= o.wait => return Err(e),
            Err(_) => std::thread::sleep(Duration::from_millis(200)),
        }
    }
}

/// The split link of machine `machine`: the listening side names it by its own bus; the
/// joining side asks the listener (`q/split`) and checks that both run the same scenario
/// with the same clock.
fn start_split(
    o: &ServeOptions,
    sc: &Scenario,
    scenario_toml: &str,
    machine: &str,
    clock: &str,
    session: &zenoh::Session,
) -> Result<split::Split> {
    let topo_path = o.run_dir.join("topology.json");
    let plan: drivelab_runtime::service::TopologyPlan = serde_json::from_slice(
        &std::fs::read(&topo_path)
            .with_context(|| format!("cannot read {}", topo_path.display()))?,
    )?;
    let sp = split::SplitPlan::new(&plan, machine).map_err(|e| anyhow!(e))?;
    let link = if o.connect {
        join(session, o, scenario_toml, &sp.there, clock)?
    } else {
        o.bus.clone()
    };
    let publishers = drivelab_runtime::service::publishers_per_topic(&plan, clock == "lockstep");
    split::Split::start(session, sp, &link, &o.bus, sc.timing.wake, publishers)
}

/// Finds the listening machine `there` and checks it runs `scenario_toml` on `clock`;
/// returns the link's name.
fn join(
    session: &zenoh::Session,
    o: &ServeOptions,
    scenario_toml: &str,
    there: &str,
    clock: &str,
) -> Result<String> {
    let t = Instant::now();
    loop {
        let replies = session
            .get(crate::query_key("*", "split"))
            .timeout(Duration::from_secs(5))
            .wait()
            .map_err(|e| anyhow!("zenoh query: {e}"))?;
        let mut found: Vec<(String, SplitInfo)> = Vec::new();
        while let Ok(reply) = replies.recv() {
            let Ok(s) = reply.result() else { continue };
            let bus = s
                .key_expr()
                .as_str()
                .split('/')
                .nth(1)
                .unwrap_or("")
                .to_string();
            if let Ok(info) = serde_json::from_slice::<SplitInfo>(&s.payload().to_bytes()) {
                if info.machine == there {
                    found.push((bus, info));
                }
            }
        }
        match found.len() {
            0 if t.elapsed() < o.wait => std::thread::sleep(Duration::from_millis(200)),
            0 => bail!(
                "no split drive with machine '{there}' answers at {} (start it first with --machine {there} --zenoh-listen)",
                o.listen
            ),
            1 => {
                let (bus, info) = found.remove(0);
                if info.clock != clock {
                    bail!(
                        "machine '{there}' runs the {} clock and this one {clock}: start both with the same --clock",
                        info.clock
                    );
                }
                if info.scenario != scenario_toml {
                    let (here, theirs): (Vec<&str>, Vec<&str>) =
                        (scenario_toml.lines().collect(), info.scenario.lines().collect());
                    let n = (0..here.len().max(theirs.len()))
                        .find(|&i| here.get(i) != theirs.get(i))
                        .unwrap_or(0);
                    bail!(
                        "machine '{there}' runs another scenario (line {}: '{}' there, '{}' here): give both sides the same scenario, topology and options",
                        n + 1,
                        theirs.get(n).unwrap_or(&""),
                        here.get(n).unwrap_or(&"")
                    );
                }
                return Ok(bus);
            }
            n => bail!("{n} split drives with machine '{there}' answer at {}", o.listen),
        }
    }
}

/// True while a remote subscriber matches `p`.
fn subscribed(p: &zenoh::pubsub::Publisher<'_>) -> bool {
    p.matching_status().wait().is_ok_and(|m| m.matching())
}

fn say(line: &str) -> Result<()> {
    let mut out = std::io::stdout().lock();
    writeln!(out, "{line}")?;
    out.flush()?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use drivelab_runtime::telemetry::{FAULT_KILL, FAULT_STOP};

    #[test]
    fn a_fault_request_needs_permission_and_a_well_formed_frame_and_refusals_are_counted() {
        let req = FaultRequest {
            kind: FAULT_STOP,
            service: 1,
            stop_ms: 50,
            pid: 9,
        };
        let mut st = Stats::default();
        assert_eq!(check_fault(&codec::encode(&[req]), true, &mut st), Ok(req));
        assert_eq!(
            check_fault(&codec::encode(&[req]), false, &mut st),
            Err(Refusal::NotAllowed)
        );
        assert_eq!((st.faults_refused, st.rejected), (1, 0));
        // Foreign bytes, two requests in one frame, an unknown kind: rejected and counted,
        // whatever the permission.
        let two = codec::encode(&[
            req,
            FaultRequest {
                kind: FAULT_KILL,
                ..req
            },
        ]);
        let forged = codec::encode(&[FaultRequest { kind: 99, ..req }]);
        for (bytes, why) in [
            (
                b"please kill the plant".to_vec(),
                "not a drivelab frame (bad magic)",
            ),
            (two, "2 requests in one frame"),
            (forged, "a message with implausible values"),
        ] {
            assert_eq!(
                check_fault(&bytes, true, &mut st),
                Err(Refusal::Malformed(why.into()))
            );
        }
        assert_eq!(st.rejected, 3);
        assert_eq!(
            Refusal::NotAllowed.to_string(),
            "remote faults are not allowed on this drive (start it with --allow-remote-faults)"
        );
    }
}
