//! The generic stage host: runs the stages of one process in chain order over a
//! [`Transport`] (the iceoryx2 bus, or nothing at all in process), in real time or lockstep.
//!
//! What the host does for every stage, so that stages stay pure (docs/architecture.md,
//! "Stages and topologies"):
//! - pacing: the source stage (no trigger) runs on the clock: absolute deadlines in real
//!   time, "as soon as its delayed inputs are there" in lockstep;
//! - inputs: every message is checked (finite, index advancing) and kept per topic by index,
//!   so that a stage gets the value its sample expects (same sample, or the newest one of the
//!   producer's rate before k for a delayed input) and sees whether it is fresh;
//! - freshness: in real time a stale input is marked and the stage's own fallback applies;
//!   a trigger that stops coming is replaced by the clock (the source's samples) once it is
//!   `max_age` samples old; lockstep always waits (with a watchdog);
//! - catch-up: a stage that fell behind in real time skips to the newest trigger (a stage
//!   that needs every sample steps the older ones without publishing them);
//! - warm-up and end markers travel through every stage's outputs without a step;
//! - rejoin: after a restart each stage takes over from the newest inputs;
//! - counters and histograms per stage, preallocated.
//!
//! The loops make no allocation, take no lock, do no logging (the bus under a [`Transport`]
//! allocates one block inside iceoryx2 per message sent: docs/architecture.md, "Real-time
//! rules").

use crate::inject::{Armed, Inject, InjectKind, InjectObs};
use crate::messages::{
    Header, FLAG_ABSENT, FLAG_END, FLAG_PLANT_DOWN, FLAG_STALE_INPUT, FLAG_WARMUP,
};
use crate::rt::{now_ns, sleep_until_ns};
use crate::stage::*;
use crate::timing::{CycleMonitor, LatencyHist, MissCounter};
use anyhow::{anyhow, bail, Result};
use serde::Serialize;
use std::time::{Duration, Instant};

/// Poll period of waits that must also notice a stop request.
pub const WAIT_SLICE: Duration = Duration::from_millis(50);

/// In lockstep, how long a stage waits for an input before it gives up (the producing
/// process is considered gone).
pub const LOCKSTEP_WATCHDOG: Duration = Duration::from_secs(10);

/// Warm-up messages the source sends through the chain before sample 0.
pub const WARMUP_MESSAGES: u64 = 50;

/// Messages kept per topic, by index (a delayed input looks back at most one producer
/// period; catch-up looks at most this far).
const RING: usize = 64;

/// How a host moves messages between processes. In process, nothing crosses: the
/// transport only receives the outputs (for a recorder).
pub trait Transport {
    /// Publishes `msg` (and wakes whoever waits on its topic).
    fn send(&mut self, msg: &Msg) -> Result<()>;
    /// The next message of `topic` from another process, if any.
    fn try_recv(&mut self, topic: TopicId) -> Result<Option<Msg>>;
    /// True when a message of `topic` is waiting.
    fn pending(&mut self, topic: TopicId) -> Result<bool>;
    /// Blocks until a message of `topic` may be there, or `timeout`.
    fn wait(&mut self, topic: TopicId, timeout: Duration) -> Result<()>;
    /// Stops receiving `topic` for good and releases its subscription. A restarted stage
    /// calls it once, when its rejoin is done, for an input read only while rejoining: a
    /// subscription nobody drains would keep every dead publisher's segment mapped.
    fn close(&mut self, _topic: TopicId) {}
    /// When the sender of `topic`'s newest wake-up started to notify (CLOCK_MONOTONIC ns), if
    /// the transport stamps its wake-ups; 0 otherwise.
    fn notified_ns(&mut self, _topic: TopicId) -> u64 {
        0
    }
    /// Whether the process that produces `topic` is up (real time, from the bus's liveness
    /// words: a killed process is down until its restart or its twin holds its lease; a
    /// stopped one is up). True where nothing can die on its own: in process, in lockstep.
    fn producer_up(&self, _topic: TopicId) -> bool {
        true
    }
    /// A standby twin that has not taken over: the newest message the active instance of its
    /// process published on `topic`, one of its own outputs (what a stage that reads its
    /// output back rejoins from; docs/architecture.md, "Liveness words and standby twins").
    /// A twin that took over: the newest such message it had read before. None for any
    /// other instance.
    fn twin_newest(&mut self, _topic: TopicId) -> Result<Option<Msg>> {
        Ok(None)
    }
    /// A standby twin whose process's active instance lives. At the first call after that
    /// instance's death the twin takes over (as at an output) and is no longer standing by.
    /// False for any other instance.
    fn twin_standing_by(&mut self) -> Result<bool> {
        Ok(false)
    }
    /// Wakes the receivers of `topic` without a message (they check their inputs' age).
    fn poke(&mut self, _topic: TopicId) -> Result<()> {
        Ok(())
    }
    /// The recorder's progress (every sample below it is stored), for lockstep flow
    /// control; None when there is no recorder.
    fn recorder_progress(&mut self) -> Result<Option<u64>> {
        Ok(None)
    }
    /// Blocks until the recorder may have progressed, or `timeout`.
    fn wait_recorder(&mut self, _timeout: Duration) -> Result<()> {
        Ok(())
    }
    /// Live status of stage `i` at sample k (ten times per simulated second; `last`: now,
    /// whatever the tenth of a second, after the loop for the run's last part second).
    fn status(
        &mut self,
        _i: usize,
        _k: u64,
        _c: &Counters,
        _h: &StageHists,
        _cycle: Option<&CycleMonitor>,
        _last: bool,
    ) -> Result<()> {
        Ok(())
    }
}

/// A transport with no other process: outputs are kept for the caller.
#[derive(Debug, Default)]
pub struct Local {
    /// Every output, in order.
    pub sent: Vec<Msg>,
}

impl Transport for Local {
    fn send(&mut self, msg: &Msg) -> Result<()> {
        self.sent.push(*msg);
        Ok(())
    }
    fn try_recv(&mut self, _topic: TopicId) -> Result<Option<Msg>> {
        Ok(None)
    }
    fn pending(&mut self, _topic: TopicId) -> Result<bool> {
        Ok(false)
    }
    fn wait(&mut self, _topic: TopicId, _timeout: Duration) -> Result<()> {
        Ok(())
    }
}

/// Counters every stage keeps (plain integers: no allocation in the loop).
#[derive(Debug, Clone, Copy, Default, Serialize, PartialEq, Eq)]
pub struct Counters {
    /// Samples stepped.
    pub samples: u64,
    /// Inputs that were not there (or not the expected index) when needed.
    pub stale_inputs: u64,
    /// Inputs rejected as malformed: NaN/∞, an end marker before the last sample, or a
    /// sample index outside the window the drive can be at ([`IndexWindow`]).
    pub rejected_inputs: u64,
    /// Triggers that arrived after a newer one had been taken (index at or behind the last
    /// one seen): late, not malformed.
    pub late_inputs: u64,
    /// Source only: deadline misses, the samples whose command was not there at the next
    /// deadline t_{k+1} (the cycle monitor's count).
    pub deadline_misses: u64,
    /// Source only: longest run of consecutive misses.
    pub longest_miss_run: u64,
    /// Source only: delayed inputs that arrived after their deadline and were discarded.
    pub late_commands: u64,
    /// Inputs deliberately skipped to catch up after falling behind (real time only).
    pub skipped: u64,
    /// Source only: wall time from its first sample to the end marker, ns.
    pub loop_wall_ns: u64,
    /// Others: outputs published after the end of their sample period (t_k + T_s; real
    /// time only).
    pub late_outputs: u64,
    /// Others: longest run of consecutive late outputs.
    pub longest_late_run: u64,
    /// Samples stepped in a fallback (a stale trigger replaced by the clock).
    pub fallback_steps: u64,
    /// Samples at which the process producing one of the stage's inputs was down (real
    /// time: its liveness word; docs/architecture.md, "Liveness words and standby twins").
    pub producer_down_samples: u64,
}

/// Greatest common divisor (gcd(0, b) = b).
pub(crate) fn gcd(a: u64, b: u64) -> u64 {
    if b == 0 {
        a
    } else {
        gcd(b, a % b)
    }
}

/// Per-stage histograms, preallocated before the loop. For a stage woken by another
/// process, `wake` = `send` + `wakeup` sample by sample when the transport stamps its
/// wake-ups; with `exec`, the parts tile the sample's critical path (docs/architecture.md,
/// "Where the microseconds go").
#[derive(Debug)]
pub struct StageHists {
    /// Wake-up: for the source, release lateness (wake − deadline); for the others, the
    /// hop from the trigger's publication to the stage running.
    pub wake: LatencyHist,
    /// The trigger's sender from stamping the message to starting its notify (loan, copy,
    /// send): the part of the hop spent in the sender.
    pub send: LatencyHist,
    /// From the trigger's notify to this stage running (futex wake, scheduling, receive).
    pub wakeup: LatencyHist,
    /// Execution of the step: input taken (for the source: woken) → step returned. It
    /// excludes publishing, so no stage that this one wakes can be inside it.
    pub exec: LatencyHist,
    /// Age of the trigger when used, from its sample instant t_k (real time only).
    pub input_age: LatencyHist,
    /// Outputs published after t_k + T_s.
    pub late: MissCounter,
    ts_ns: u64,
}

impl StageHists {
    /// Histograms for a drive sampled every `ts_ns`.
    pub fn new(source: bool, ts_ns: u64) -> Self {
        Self {
            wake: LatencyHist::new(if source { "lateness" } else { "wake" }),
            send: LatencyHist::new("send"),
            wakeup: LatencyHist::new("wakeup"),
            exec: LatencyHist::new("exec"),
            input_age: LatencyHist::new("input_age"),
            late: MissCounter::default(),
            ts_ns,
        }
    }

    /// Every histogram, for writing out.
    pub fn all(&self) -> [&LatencyHist; 5] {
        [
            &self.wake,
            &self.send,
            &self.wakeup,
            &self.exec,
            &self.input_age,
        ]
    }

    /// A trigger published at `t_pub`, notified at `t_notify` (0: not stamped) for sample
    /// instant `t_sample`, taken at `t_in`.
    #[inline]
    fn input(&mut self, t_in: u64, t_pub: u64, t_notify: u64, t_sample: u64) {
        if t_pub != 0 {
            self.wake.record_ns(t_in as i64 - t_pub as i64);
            // A stamp outside [t_pub, t_in] belongs to another message (a later one).
            if (t_pub..=t_in).contains(&t_notify) {
                self.send.record_ns((t_notify - t_pub) as i64);
                self.wakeup.record_ns((t_in - t_notify) as i64);
            }
        }
        if t_sample != 0 {
            self.input_age.record_ns(t_in as i64 - t_sample as i64);
        }
    }

    /// The step taken at `t_in` returned at `t_end`.
    #[inline]
    fn stepped(&mut self, t_in: u64, t_end: u64) {
        self.exec.record_ns(t_end as i64 - t_in as i64);
    }

    /// Its outputs for sample instant `t_sample` are published.
    #[inline]
    fn published(&mut self, t_sample: u64) {
        self.late
            .record(t_sample != 0 && now_ns() > t_sample + self.ts_ns);
    }
}

/// What the source saw at one deadline, in real time: its wake-up's lateness, ns, and the
/// previous command (its index, its sample instant, when it was published, None: not there).
#[derive(Clone, Copy)]
struct Deadline {
    deadline: u64,
    wake_ns: Option<i64>,
    cmd: Option<(u64, u64, Option<u64>)>,
}

/// Where a stage's input comes from in this topology.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Origin {
    /// Produced by a stage of this process.
    Local,
    /// Produced by a stage of another process.
    External,
    /// No stage of the topology produces it: the input is never there.
    Absent,
}

/// A stage's input bound to the topology.
#[derive(Debug, Clone, Copy)]
pub struct Bound {
    /// The declaration.
    pub spec: InputSpec,
    /// The producer's rate divider.
    pub producer_divider: u64,
    /// Where it comes from.
    pub origin: Origin,
}

/// An external input the host reads from the bus: each topic once, its counts on the first
/// stage that reads it.
#[derive(Clone, Copy)]
struct Drain {
    /// The stage that owns its counts.
    owner: usize,
    /// That stage's binding.
    bound: Bound,
    /// The smallest delay among this process's readers of the topic: at sample k they read
    /// no message newer than the one due at k − delay. None when one of them reads the
    /// newest message there is (a rejoin-only input), so every waiting one is taken.
    stop_delay: Option<u64>,
}

/// A stage in a host, with its bindings and bookkeeping.
pub struct Hosted {
    /// The stage.
    pub stage: Box<dyn Stage>,
    /// Its inputs, bound.
    pub inputs: Vec<Bound>,
    /// Its counters.
    pub counters: Counters,
    /// Its histograms.
    pub hists: StageHists,
    /// What it saw of each injection of the schedule (same order as the scenario's).
    pub inject: Vec<InjectObs>,
    last_k: Option<u64>,
    /// Index of the newest trigger received (for gaps, order and staleness).
    last_seen: Option<u64>,
    in_fallback: bool,
    rejoining: bool,
    divider: u64,
    /// Lockstep: a simulated kill of this stage is scheduled (its rejoin-only inputs are
    /// kept drained and open, see [`Host::arm_spares`]).
    killable: bool,
}

impl Hosted {
    fn trigger(&self) -> Option<Bound> {
        self.inputs
            .iter()
            .copied()
            .find(|b| b.spec.role == Role::Trigger)
    }
}

/// How the host paces.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Pacing {
    /// Absolute deadlines; late inputs are stale.
    Realtime,
    /// Every input is waited for; no wall clock.
    Lockstep,
}

/// Settings of a host.
#[derive(Debug, Clone)]
pub struct HostConfig {
    /// Pacing.
    pub pacing: Pacing,
    /// Samples of the run (the source stops at n).
    pub samples: u64,
    /// Sample time, ns.
    pub ts_ns: u64,
    /// Source only, real time: sleep to this long before each deadline, then spin, ns.
    pub spin_ns: u64,
    /// Source only, real time: start the schedule on the scheduler tick's grid
    /// of its own CPU ([`crate::rt::schedule_start_ns`]).
    pub tick_aligned: bool,
    /// Restarted: take over a running drive.
    pub rejoin: bool,
    /// Rejoining: the last outputs as the recorder saw them (at most one per topic): the
    /// source's true state; the own last output of a stage that reads it back, for its
    /// own-output rejoin slot (docs/architecture.md, "Bumpless rejoin").
    pub rejoin_from: Vec<Msg>,
    /// Source only: send warm-up messages through the chain before sample 0.
    pub warm_up: bool,
    /// Topics that stages of other processes wait on (the source pokes them when its delayed
    /// input is missing, so that they check their inputs without a timer).
    pub poke: Vec<TopicId>,
    /// The topic that tells where the drive is (the source's output), for fallbacks.
    pub clock_topic: TopicId,
    /// The transport wakes this process at each message of the clock topic when it waits
    /// on it (futex wake words): a stage falling back on the clock then sleeps until the
    /// next sample is out instead of polling on a timer.
    pub clock_wakes: bool,
    /// Bus faults to inject by sample index (the scenario's `[[inject]]` tables).
    pub inject: Vec<Inject>,
    /// Sample rate, Hz (to turn the injections' times into sample indices).
    pub sample_hz: f64,
}

impl HostConfig {
    /// The settings for `samples` samples of scenario `sc` at `pacing`: its sample time and
    /// plant spin; no rejoin, warm-up on, no pokes, the measurement as the clock topic.
    pub fn for_scenario(sc: &crate::config::Scenario, pacing: Pacing, samples: u64) -> Self {
        Self {
            pacing,
            samples,
            ts_ns: sc.rates.ts_ns(),
            spin_ns: (sc.timing.plant_spin_us * 1e3).round() as u64,
            tick_aligned: sc.timing.tick_aligned,
            rejoin: false,
            rejoin_from: Vec::new(),
            warm_up: true,
            poke: Vec::new(),
            clock_topic: TopicId::Meas,
            clock_wakes: false,
            inject: sc.inject.clone(),
            sample_hz: sc.rates.sample_hz,
        }
    }
}

/// Lockstep: how far ahead of the newest index taken so far an input may be, samples. In
/// lockstep no stage runs ahead of the chain by more than the slowest stage's period, and no
/// process restarts, so a larger jump can only be a foreign or corrupted message.
const LOCKSTEP_WINDOW_MIN: u64 = 16;

/// Which sample indices a host takes from the bus. Every message of a drive carries the index
/// of the sample it belongs to, and sample k starts at t0 + k·T_s on the drive's schedule.
/// In real time an index is taken only if its sample has started by now (plus one sample of
/// slack): a message cannot come from the future, so a huge index is rejected however it
/// arrived. The schedule's origin t0 is learnt from the first message with a sample instant.
/// In lockstep (no wall clock) an index is taken within a window of the newest one taken.
/// A restarted producer, or a consumer that catches up after a freeze, stays inside both.
#[derive(Debug, Clone, Copy)]
struct IndexWindow {
    realtime: bool,
    ts_ns: u64,
    t0_ns: Option<u64>,
    newest: Option<u64>,
    window: u64,
}

impl IndexWindow {
    fn new(realtime: bool, ts_ns: u64, max_divider: u64) -> Self {
        Self {
            realtime,
            ts_ns: ts_ns.max(1),
            t0_ns: None,
            newest: None,
            window: LOCKSTEP_WINDOW_MIN.max(4 * max_divider),
        }
    }

    /// True when sample index `hdr.k` is one the drive can be at now (`now_ns`: the
    /// monotonic clock). Learns the schedule's origin or the newest index on the way.
    fn admits(&mut self, hdr: &crate::messages::Header, now_ns: u64) -> bool {
        if self.realtime {
            if let Some(t0) = self.t0_ns {
                // The sample that has started by now, plus one of slack.
                let k_now = now_ns.saturating_sub(t0) / self.ts_ns;
                return hdr.k <= k_now + 1;
            }
            if hdr.t_sample_ns != 0 {
                self.t0_ns = hdr
                    .k
                    .checked_mul(self.ts_ns)
                    .and_then(|x| hdr.t_sample_ns.checked_sub(x));
            }
            return true;
        }
        if self
            .newest
            .is_some_and(|n| hdr.k > n.saturating_add(self.window))
        {
            return false;
        }
        self.newest = Some(self.newest.map_or(hdr.k, |n| n.max(hdr.k)));
        true
    }
}

/// Per-topic store of the newest messages by index.
struct Store {
    ring: [[Option<Msg>; RING]; N_TOPICS],
    divider: [u64; N_TOPICS],
    newest: [Option<Msg>; N_TOPICS],
}

impl Store {
    fn new(divider: [u64; N_TOPICS]) -> Self {
        Self {
            ring: [[None; RING]; N_TOPICS],
            divider,
            newest: [None; N_TOPICS],
        }
    }

    fn slot_of(&self, t: TopicId, k: u64) -> usize {
        ((k / self.divider[t.index()].max(1)) % RING as u64) as usize
    }

    fn put(&mut self, msg: Msg) {
        let t = msg.topic();
        let k = msg.hdr().k;
        let s = self.slot_of(t, k);
        self.ring[t.index()][s] = Some(msg);
        if self.newest[t.index()].is_none_or(|n| k >= n.hdr().k) {
            self.newest[t.index()] = Some(msg);
        }
    }

    fn get(&self, t: TopicId, k: u64) -> Option<Msg> {
        self.ring[t.index()][self.slot_of(t, k)].filter(|m| m.hdr().k == k && !m.hdr().is_absent())
    }

    /// Marks message k of `t` absent: lockstep knows it will not come (a message already
    /// taken for k stays).
    fn put_absent(&mut self, t: TopicId, k: u64) {
        let s = self.slot_of(t, k);
        if self.get(t, k).is_none() {
            let hdr = Header {
                k,
                flags: FLAG_ABSENT,
                ..Default::default()
            };
            self.ring[t.index()][s] = Some(Msg::marker(t, hdr));
        }
    }

    /// True when message k of `t` is there or known to be absent.
    fn settled(&self, t: TopicId, k: u64) -> bool {
        self.ring[t.index()][self.slot_of(t, k)].is_some_and(|m| m.hdr().k == k)
    }

    fn newest_k(&self, t: TopicId) -> Option<u64> {
        self.newest[t.index()].map(|m| m.hdr().k)
    }
}

/// Which call of a stage its host makes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Call {
    /// [`Stage::step`].
    Step,
    /// [`Stage::after_publish`].
    AfterPublish,
    /// [`Stage::rejoin`].
    Rejoin,
}

impl Call {
    /// The method's name.
    pub fn name(self) -> &'static str {
        match self {
            Self::Step => "step",
            Self::AfterPublish => "after_publish",
            Self::Rejoin => "rejoin",
        }
    }
}

/// The stage call a host made last: stage `si` (chain order), `call`, of sample `k`. The
/// host writes it before each call (plain stores, nothing else on the real-time path),
/// so that a panic caught around [`Host::run`] can name the stage and the sample
/// (docs/architecture.md, "Fault model").
#[derive(Debug, Clone, Copy)]
struct Calling {
    si: usize,
    k: u64,
    call: Call,
}

/// The host of one process.
pub struct Host<T: Transport> {
    /// The stages, in chain order.
    pub stages: Vec<Hosted>,
    /// The transport.
    pub transport: T,
    cfg: HostConfig,
    store: Store,
    /// Source only: cycle latency and deadline misses.
    pub cycle: CycleMonitor,
    /// Source only, real time: its wake-ups that came half a millisecond late or later.
    pub stalls: crate::timing::StallLog,
    stop: Box<dyn Fn() -> bool + Send>,
    stop_without_end: Box<dyn Fn() -> bool + Send>,
    /// Called once, on the loop's thread, as the first sample begins (see
    /// [`Host::at_first_sample`]).
    first_sample: Option<Box<dyn FnOnce() -> Result<()> + Send>>,
    /// The external inputs to drain, each topic once.
    drains: Vec<Drain>,
    /// The sample indices taken from the bus.
    window: IndexWindow,
    /// The injection schedule bound to this host's stages and topics.
    armed: Vec<Armed>,
    /// Lockstep kills: per injection, the freshly built stage that replaces the killed one
    /// (built at set-up by [`Host::arm_spares`]; after the swap, the dead one until the end).
    spares: Vec<Option<Box<dyn Stage>>>,
    /// Per injection: the kill's swap is done.
    swapped: Vec<bool>,
    /// The stage call made last (None: none yet).
    calling: Option<Calling>,
}

impl<T: Transport> Host<T> {
    /// A host for `stages` (chain order) whose inputs are bound per `producers`: for every
    /// produced topic, the producer's divider and whether it is produced in this process (a
    /// topic not listed is produced nowhere).
    pub fn new(
        stages: Vec<Box<dyn Stage>>,
        producers: &[(TopicId, u64, bool)],
        transport: T,
        cfg: HostConfig,
    ) -> Self {
        let mut divider = [1u64; N_TOPICS];
        for (t, d, _) in producers {
            divider[t.index()] = *d;
        }
        let hosted = stages
            .into_iter()
            .enumerate()
            .map(|(i, stage)| {
                let inputs = stage
                    .inputs()
                    .iter()
                    .map(|spec| {
                        let p = producers.iter().find(|(t, _, _)| *t == spec.topic);
                        Bound {
                            spec: *spec,
                            producer_divider: p.map_or(1, |p| p.1),
                            origin: match p {
                                None => Origin::Absent,
                                Some((_, _, true)) => Origin::Local,
                                Some((_, _, false)) => Origin::External,
                            },
                        }
                    })
                    .collect();
                let divider = stage.divider().max(1);
                let source = i == 0 && trigger_of(stage.as_ref()).is_none();
                Hosted {
                    stage,
                    inputs,
                    counters: Counters::default(),
                    hists: StageHists::new(source, cfg.ts_ns),
                    inject: vec![InjectObs::default(); cfg.inject.len()],
                    last_k: None,
                    last_seen: None,
                    in_fallback: false,
                    rejoining: cfg.rejoin,
                    divider,
                    killable: false,
                }
            })
            .collect::<Vec<Hosted>>();
        let mut drains: Vec<Drain> = Vec::new();
        for (si, h) in hosted.iter().enumerate() {
            for b in &h.inputs {
                if b.origin != Origin::External {
                    continue;
                }
                let stop = (b.spec.role != Role::Rejoin).then_some(b.spec.delay);
                match drains
                    .iter_mut()
                    .find(|d| d.bound.spec.topic == b.spec.topic)
                {
                    None => drains.push(Drain {
                        owner: si,
                        bound: *b,
                        stop_delay: stop,
                    }),
                    Some(d) => d.stop_delay = d.stop_delay.zip(stop).map(|(a, b)| a.min(b)),
                }
            }
        }
        let max_divider = divider
            .iter()
            .copied()
            .chain(hosted.iter().map(|h| h.divider))
            .max()
            .unwrap_or(1);
        let names: Vec<&str> = hosted.iter().map(|h| h.stage.name()).collect();
        let armed: Vec<Armed> = cfg
            .inject
            .iter()
            .map(|i| Armed::bind(i, cfg.sample_hz, &names, |t| divider[t.index()]))
            .collect();
        let mut host = Self {
            spares: armed.iter().map(|_| None).collect(),
            swapped: vec![false; armed.len()],
            armed,
            window: IndexWindow::new(cfg.pacing == Pacing::Realtime, cfg.ts_ns, max_divider),
            stages: hosted,
            transport,
            store: Store::new(divider),
            cycle: CycleMonitor::new(cfg.ts_ns),
            // Empty, allocating nothing: only the source keeps its stalls (below).
            stalls: crate::timing::StallLog::new(0, cfg.ts_ns),
            cfg,
            stop: Box::new(|| false),
            stop_without_end: Box::new(|| false),
            first_sample: None,
            drains,
            calling: None,
        };
        if host.is_source() {
            host.stalls = crate::timing::StallLog::new(crate::timing::STALL_LOG, host.cfg.ts_ns);
        }
        host
    }

    /// Lockstep kills (docs/architecture.md, "Fault model"): builds, with `build` (a stage
    /// name → a fresh stage), the stage that replaces each killed stage of this host, at
    /// set-up rather than in the loop. An error when a kill targets a stage of this host that
    /// `build` cannot make, or when the run is not in lockstep.
    pub fn arm_spares(&mut self, build: impl Fn(&str) -> Option<Box<dyn Stage>>) -> Result<()> {
        for i in 0..self.armed.len() {
            let a = self.armed[i];
            let Some(si) = a.stage.filter(|_| a.kind == InjectKind::Kill) else {
                continue;
            };
            let name = self.stages[si].stage.name();
            if self.cfg.pacing != Pacing::Lockstep {
                bail!("kill of {name} by the injection schedule: lockstep only");
            }
            // The source (the plant) keeps its state: the motor keeps turning while its
            // process is down (see `run_source`).
            if si == 0 && self.is_source() {
                continue;
            }
            let fresh = build(name)
                .ok_or_else(|| anyhow!("kill of {name} in lockstep: no fresh {name} stage can be built to restart it (a stage this executable can build)"))?;
            self.spares[i] = Some(fresh);
            self.stages[si].killable = true;
        }
        Ok(())
    }

    /// Lockstep kill or stop of stage `si` (docs/architecture.md, "Fault model"): true when
    /// it is down at k (no step, its outputs absent). From a kill's first sample on, the
    /// stage is the fresh one built at set-up, marked rejoining: once the window is over it
    /// takes over through [`Stage::rejoin`] as a restarted process would. A stop keeps it.
    fn down(&mut self, si: usize, k: u64) -> bool {
        if self.cfg.pacing != Pacing::Lockstep {
            return false;
        }
        let mut down = false;
        for i in 0..self.armed.len() {
            let a = self.armed[i];
            if !a.kind.downs_stage() || a.stage != Some(si) || k < a.from_k {
                continue;
            }
            if a.kind == InjectKind::Kill && !self.swapped[i] {
                if let Some(fresh) = self.spares[i].as_mut() {
                    // The dead stage stays in the spare's place until the end: no drop here.
                    std::mem::swap(&mut self.stages[si].stage, fresh);
                    self.stages[si].rejoining = true;
                    self.stages[si].in_fallback = false;
                }
                self.swapped[i] = true;
            }
            down |= a.covers(k);
        }
        down
    }

    /// Lockstep: true when stage `si`, stopped (not killed) at sample k, steps k silently. A
    /// real stopped process keeps its topics' last [`crate::bus::HISTORY`] samples and, if
    /// it needs every sample ([`Stage::steps_every_sample`], the observer), steps them
    /// unpublished when it resumes, so its state has seen each of them; older ones are
    /// lost to it, as here.
    fn catches_up(&self, si: usize, k: u64) -> bool {
        self.stages[si].stage.steps_every_sample()
            && self.armed.iter().any(|a| {
                a.kind == InjectKind::Stop
                    && a.stage == Some(si)
                    && a.covers(k)
                    && k + crate::bus::HISTORY as u64 >= a.to_k
            })
    }

    /// Sets the function that says a stop was requested (SIGINT, SIGTERM, SIGHUP …).
    pub fn stop_when(&mut self, f: impl Fn() -> bool + Send + 'static) {
        self.stop = Box::new(f);
    }

    /// Sets a function to call once, on the loop's thread, as the first sample begins: the
    /// source's after its warm-up and its schedule's start, a triggered host's at its first
    /// trigger that is not a marker (its warm-up forwarded, when the iceoryx2 ports have
    /// mapped the segments of their peers). An error ends the run. The system-call audit
    /// arms itself here.
    pub fn at_first_sample(&mut self, f: impl FnOnce() -> Result<()> + Send + 'static) {
        self.first_sample = Some(Box::new(f));
    }

    /// Sets the function that says a stop ends this process only, not the drive: a source
    /// then forwards no END marker, and the rest of the drive sees it go as it sees a crash.
    pub fn stop_without_end_when(&mut self, f: impl Fn() -> bool + Send + 'static) {
        self.stop_without_end = Box::new(f);
    }

    fn stopping(&self) -> bool {
        (self.stop)()
    }

    /// True when message `m` from another process may be used: finite values and a sample
    /// index the drive can be at ([`IndexWindow`]). Else counted as rejected against stage
    /// `si`.
    fn admit(&mut self, si: usize, m: &Msg) -> bool {
        let plausible = self.window.admits(m.hdr(), now_ns());
        let ok = plausible && m.is_finite();
        if !ok {
            self.reject(si, m, plausible);
        }
        ok
    }

    /// Counts message `m` as rejected by stage `si`, and against the corrupt fault whose
    /// window it is in. In lockstep an unusable message of a `plausible` index is absent for
    /// its sample: nobody waits for it any more.
    fn reject(&mut self, si: usize, m: &Msg, plausible: bool) {
        let (t, k) = (m.topic(), m.hdr().k);
        self.stages[si].counters.rejected_inputs += 1;
        for i in 0..self.armed.len() {
            if self.armed[i].kind == InjectKind::Corrupt && self.armed[i].hits(t, k) {
                self.stages[si].inject[i].rejected += 1;
            }
        }
        if plausible && self.cfg.pacing == Pacing::Lockstep {
            self.store.put_absent(t, k);
        }
    }

    /// Lockstep: takes absent marker `hdr` of `t` (a sample the producer has no message
    /// for). False when its index is not one the drive can be at.
    fn take_absent(&mut self, t: TopicId, hdr: &Header) -> bool {
        let ok = self.window.admits(hdr, now_ns());
        if ok {
            self.store.put_absent(t, hdr.k);
        }
        ok
    }

    /// The first stage of this process that reads `t` from a stage of this process.
    fn local_reader(&self, t: TopicId) -> Option<usize> {
        self.stages.iter().position(|h| {
            h.inputs.iter().any(|b| {
                b.spec.topic == t && b.origin == Origin::Local && b.spec.role != Role::Rejoin
            })
        })
    }

    /// Publishes output `m` of this process, or what the injection schedule makes of it:
    /// nothing (drop; lockstep tells the consumers so) or a corrupt copy, which this
    /// process's own reader rejects as a peer's would.
    fn publish(&mut self, m: Msg) -> Result<()> {
        let (t, k) = (m.topic(), m.hdr().k);
        let hit = self
            .armed
            .iter()
            .position(|a| a.kind != InjectKind::Delay && a.hits(t, k));
        let Some(i) = hit else {
            self.store.put(m);
            return self.transport.send(&m);
        };
        let a = self.armed[i];
        if a.kind == InjectKind::Drop {
            return self.absent(t, k);
        }
        let mut c = m;
        crate::inject::corrupt(&mut c, a.nth(k));
        if let Some(r) = self.local_reader(t) {
            self.reject(r, &c, true);
        }
        self.transport.send(&c)
    }

    /// No message of `t` for sample k: in lockstep the consumers get an absent marker.
    fn absent(&mut self, t: TopicId, k: u64) -> Result<()> {
        self.store.put_absent(t, k);
        if self.cfg.pacing == Pacing::Lockstep {
            let hdr = Header {
                k,
                flags: FLAG_ABSENT,
                ..Default::default()
            };
            self.transport.send(&Msg::marker(t, hdr))?;
        }
        Ok(())
    }

    /// Lockstep: stage `si` cannot step at k (a required input is absent): its outputs of
    /// sample k are absent too, so that their consumers do not wait for them.
    fn absent_outputs(&mut self, si: usize, k: u64) -> Result<()> {
        if self.cfg.pacing != Pacing::Lockstep {
            return Ok(());
        }
        let outs = self.stages[si].stage.outputs();
        for &t in outs {
            self.absent(t, k)?;
        }
        Ok(())
    }

    /// Real time: the outputs of stage `si` for sample k wait out every delay fault that
    /// covers k (a slow computation): a spin on the monotonic clock (vDSO, no system call),
    /// no allocation.
    #[inline]
    fn delay(&self, si: usize, k: u64) {
        let lat = self
            .armed
            .iter()
            .filter(|a| a.kind == InjectKind::Delay && a.stage == Some(si) && a.covers(k))
            .map(|a| a.latency_ns)
            .max()
            .unwrap_or(0);
        if lat > 0 {
            let until = now_ns() + lat;
            while now_ns() < until {
                std::hint::spin_loop();
            }
        }
    }

    /// Source: records what a deadline showed (see [`Deadline`]).
    fn account_deadline(&mut self, seen: Deadline) {
        if let Some(w) = seen.wake_ns {
            self.stages[0].hists.wake.record_ns(w);
            self.stalls.record(seen.deadline, w);
        }
        if let Some((kc, t_k, avail)) = seen.cmd {
            let before = self.cycle.misses.misses;
            self.cycle.at_deadline(t_k, avail);
            self.stalls
                .misses_in_stall(self.cycle.misses.misses - before);
            self.observe_cycle(kc, t_k, avail, true);
        }
    }

    /// Source, real time: command `kc` (of sample instant `t_k`) was published at `avail`
    /// (None: not there at its deadline), for the delay faults whose window covers `kc`.
    /// `at_deadline`: seen at its deadline (counted) rather than arriving late.
    fn observe_cycle(&mut self, kc: u64, t_k: u64, avail: Option<u64>, at_deadline: bool) {
        let ts = self.cfg.ts_ns;
        for i in 0..self.armed.len() {
            let a = self.armed[i];
            if a.kind != InjectKind::Delay || !a.covers(kc) {
                continue;
            }
            let o = &mut self.stages[0].inject[i];
            let lat = avail.map(|t| t.saturating_sub(t_k));
            if let Some(l) = lat {
                o.cycle_max_ns = o.cycle_max_ns.max(l);
            }
            if at_deadline {
                o.cycles += 1;
                o.misses += u64::from(lat.is_none_or(|l| l > ts));
            }
        }
    }

    /// Notes the stage call about to be made (what a panic in it is named by).
    #[inline]
    fn calling(&mut self, si: usize, k: u64, call: Call) {
        self.calling = Some(Calling { si, k, call });
    }

    /// The stage call made last, as text: "stage NAME, CALL at sample k, t = k·T_s s";
    /// None before the first. For the line of a panic caught around [`Host::run`].
    pub fn last_call(&self) -> Option<String> {
        let c = self.calling?;
        let name = self.stages.get(c.si)?.stage.name();
        // k·T_s in ns, printed in seconds without trailing zeros.
        let t_ns = u128::from(c.k) * u128::from(self.cfg.ts_ns);
        let frac = format!("{:09}", t_ns % 1_000_000_000);
        let frac = frac.trim_end_matches('0');
        let t = format!(
            "{}{}{frac}",
            t_ns / 1_000_000_000,
            if frac.is_empty() { "" } else { "." }
        );
        Some(format!(
            "stage {name}, {} at sample {}, t = {t} s",
            c.call.name(),
            c.k
        ))
    }

    /// True when the first stage is the source (no trigger).
    pub fn is_source(&self) -> bool {
        self.stages.first().is_some_and(|h| h.trigger().is_none())
    }

    /// Runs until the end marker, a stop request or an error; then sends each stage's last
    /// status, so that the run's last second is reported too.
    pub fn run(&mut self) -> Result<()> {
        if self.is_source() {
            self.run_source()?;
        } else {
            self.run_triggered()?;
        }
        self.status(true)
    }

    // ---------------------------------------------------------------- inputs

    /// Takes the waiting messages of the external inputs (except `skip`, the trigger being
    /// consumed) into the store: all of them, or with `upto` = Some(k) only until the store
    /// holds what this process's stages read at sample k (each read that finds nothing costs
    /// about 0.1 µs on the critical path; the rest wait in the subscriber's buffer for a
    /// later sample). Malformed ones are rejected and counted against the owner. The
    /// source passes `expect_k`, its sample, to count commands that came too late.
    fn drain_external(
        &mut self,
        skip: Option<TopicId>,
        expect_k: Option<u64>,
        upto: Option<u64>,
    ) -> Result<()> {
        for di in 0..self.drains.len() {
            let Drain {
                owner: si,
                bound: b,
                stop_delay,
            } = self.drains[di];
            if Some(b.spec.topic) == skip
                || (b.spec.role == Role::Rejoin
                    && !self.stages[si].rejoining
                    && !self.stages[si].killable)
            {
                continue;
            }
            // The newest message its readers take at `upto`: nothing yet (k < delay), one the
            // store holds already, or one to read up to.
            let mut enough = None;
            if let Some((k, d)) = upto.zip(stop_delay) {
                match expected_index(k, d, b.producer_divider) {
                    None => continue,
                    Some(w) if self.store.settled(b.spec.topic, w) => continue,
                    Some(w) => enough = Some(w),
                }
            }
            while let Some(m) = self.transport.try_recv(b.spec.topic)? {
                let h = m.hdr();
                if h.is_warmup() || h.is_end() {
                    continue;
                }
                if h.is_absent() {
                    self.take_absent(b.spec.topic, h);
                    continue;
                }
                if !self.admit(si, &m) {
                    continue;
                }
                // Source: a delayed input older than the one this sample expects came
                // after its deadline.
                if let Some(want) =
                    expect_k.and_then(|k| expected_index(k, b.spec.delay, b.producer_divider))
                {
                    if b.spec.delay > 0 && h.k < want {
                        self.stages[si].counters.late_commands += 1;
                        if h.t_sample_ns != 0 {
                            self.cycle.late_command(h.t_sample_ns, h.t_pub_ns);
                            self.observe_cycle(h.k, h.t_sample_ns, Some(h.t_pub_ns), false);
                        }
                        continue;
                    }
                    if h.k > want {
                        self.stages[si].counters.rejected_inputs += 1;
                        continue;
                    }
                }
                self.store.put(m);
                if enough.is_some_and(|w| h.k >= w) {
                    break;
                }
            }
        }
        Ok(())
    }

    /// The inbox of stage `si` at sample k, and false when a required input is missing.
    fn inbox(&self, si: usize, k: u64) -> (Inbox, bool) {
        let mut ib = Inbox::default();
        let mut complete = true;
        for b in &self.stages[si].inputs {
            let t = b.spec.topic;
            if b.origin == Origin::Absent {
                continue;
            }
            let slot = &mut ib.slots[t.index()];
            slot.msg = self.store.newest[t.index()];
            if b.spec.role == Role::Rejoin {
                if slot.msg.is_none() && self.own_output(si, t) {
                    // A restarted process: its own last output as the recorder saw it.
                    slot.msg = self
                        .cfg
                        .rejoin_from
                        .iter()
                        .find(|m| m.topic() == t)
                        .copied();
                }
                slot.fresh = slot.msg.is_some();
                continue;
            }
            match expected_index(k, b.spec.delay, b.producer_divider) {
                None => {
                    // Nothing expected yet (k < delay): fresh, with no value.
                    slot.msg = None;
                    slot.fresh = true;
                }
                Some(want) => match self.store.get(t, want) {
                    // A fallback input whose producer's process is down is stale from the
                    // sample this host sees it down, even when its last message was the one
                    // expected: the stage takes its fallback at once (the plant starts its
                    // hold), not a producer period later.
                    Some(m)
                        if b.origin == Origin::External
                            && b.spec.on_stale == OnStale::Fallback
                            && !self.transport.producer_up(t) =>
                    {
                        slot.msg = Some(m);
                        slot.fresh = false;
                        slot.producer_down = true;
                    }
                    Some(m) => {
                        slot.msg = Some(m);
                        slot.fresh = true;
                    }
                    None => {
                        slot.fresh = false;
                        slot.producer_down =
                            b.origin == Origin::External && !self.transport.producer_up(t);
                        slot.age = match self.store.newest_k(t) {
                            Some(nk) if nk < want => (want - nk) / b.producer_divider.max(1),
                            _ => want / b.producer_divider.max(1) + 1,
                        };
                        if b.spec.on_stale == OnStale::Required {
                            complete = false;
                        }
                    }
                },
            }
        }
        (ib, complete)
    }

    /// Lockstep: waits until every external input stage `si` expects at k is there.
    fn wait_inputs(&mut self, si: usize, k: u64) -> Result<bool> {
        let started = Instant::now();
        // The process's trigger is taken only by its trigger loop: drained here, a trigger
        // that came early (the next sample's, from a producer on another core) would sit in
        // the store and never wake the chain.
        let trigger = self.stages[0]
            .trigger()
            .filter(|t| t.origin == Origin::External)
            .map(|t| t.spec.topic);
        loop {
            self.drain_external(trigger, None, None)?;
            let missing = self.stages[si].inputs.iter().copied().find(|b| {
                b.origin == Origin::External
                    && b.spec.role == Role::Latest
                    && expected_index(k, b.spec.delay, b.producer_divider)
                        .is_some_and(|w| !self.store.settled(b.spec.topic, w))
            });
            let Some(b) = missing else { return Ok(true) };
            if self.stopping() {
                return Ok(false);
            }
            self.transport.wait(b.spec.topic, WAIT_SLICE)?;
            if started.elapsed() > LOCKSTEP_WATCHDOG {
                let c = self.stages[si].counters;
                bail!(
                    "{}: no {} for sample {k} for {LOCKSTEP_WATCHDOG:?} (newest {}: {:?}; {} rejected, {} late)",
                    self.stages[si].stage.name(),
                    b.spec.topic.name(),
                    b.spec.topic.name(),
                    self.store.newest_k(b.spec.topic),
                    c.rejected_inputs,
                    c.late_inputs,
                );
            }
        }
    }

    // ---------------------------------------------------------------- steps

    /// Steps stage `si` at k with `ib` and publishes its outputs. `t_in` is when its input
    /// was taken; `fallback` marks every output as made from a stale input.
    fn step_publish(
        &mut self,
        si: usize,
        k: u64,
        ib: &Inbox,
        t_in: u64,
        fallback: bool,
    ) -> Result<()> {
        let mut out = Outbox::default();
        self.calling(si, k, Call::Step);
        let h = &mut self.stages[si];
        h.stage.step(k, ib, &mut out);
        let t_end = now_ns();
        // Its declared outputs, every one: the stages that read one would wait for it in
        // lockstep (and the drive would stop on another's time-out) or see it stale.
        if let Some(t) = h.stage.outputs().iter().find(|t| out.get(**t).is_none()) {
            bail!(
                "stage '{}' published no '{}' at sample {k}: a step publishes each of its declared outputs every time it runs",
                h.stage.name(),
                t.name()
            );
        }
        // And nothing else: a topic it did not declare has no publisher of its.
        if let Some(m) = out
            .msgs
            .iter()
            .flatten()
            .find(|m| !h.stage.outputs().contains(&m.topic()))
        {
            bail!(
                "stage '{}' published '{}' at sample {k}, which it does not declare among its outputs",
                h.stage.name(),
                m.topic().name()
            );
        }
        let t_sample = if self.cfg.pacing == Pacing::Realtime {
            ib.slots
                .iter()
                .filter_map(|s| s.msg)
                .map(|m| m.hdr().t_sample_ns)
                .find(|&t| t != 0)
                .unwrap_or(0)
        } else {
            0
        };
        let mut any = false;
        if self.cfg.pacing == Pacing::Realtime {
            self.delay(si, k);
        }
        // One instant for all of the sample's outputs, its first publish's: the first can
        // wake a stage of higher priority that preempts this one before the next publish (the
        // plant's truth would carry the time the plant got the core back, after the chain).
        let t_pub = now_ns();
        for mut m in out.drain() {
            any = true;
            let hd = m.hdr_mut();
            if fallback {
                hd.flags |= FLAG_STALE_INPUT;
            }
            hd.t_pub_ns = t_pub;
            self.publish(m)?;
        }
        let h = &mut self.stages[si];
        if any {
            h.counters.samples += 1;
            if fallback {
                h.counters.fallback_steps += 1;
            }
            h.hists.stepped(t_in, t_end);
            h.hists.published(t_sample);
        }
        h.last_k = Some(k);
        Ok(())
    }

    /// Runs stages `from..` of the chain at sample k (the trigger of stage `from` is in the
    /// store). Stages whose rate does not hit k are skipped.
    fn run_chain(&mut self, from: usize, k: u64, t_in: u64) -> Result<bool> {
        for si in from..self.stages.len() {
            if !k.is_multiple_of(self.stages[si].divider) {
                continue;
            }
            if self.stages[si].last_k.is_some_and(|l| k <= l) {
                continue;
            }
            if self.down(si, k) {
                // Lockstep: a stage that is down still waits for its inputs of k (unused), so
                // the chain keeps its pace. Without it the source would run on without the
                // stages this one waits for (the current loop down, the speed loop left
                // behind), and one the machine holds back would lose the inputs its buffers
                // cannot keep and wait for them until the watchdog.
                if self.cfg.pacing == Pacing::Lockstep && !self.wait_inputs(si, k)? {
                    return Ok(false);
                }
                if self.catches_up(si, k) {
                    // A stopped process that needs every sample steps its backlog silently
                    // when it resumes: here each sample as it comes, its outputs absent.
                    let (ib, complete) = self.inbox(si, k);
                    if complete {
                        let mut out = Outbox::default();
                        self.calling(si, k, Call::Step);
                        self.stages[si].stage.step(k, &ib, &mut out);
                    }
                }
                self.absent_outputs(si, k)?;
                self.stages[si].last_k = Some(k);
                continue;
            }
            // A trigger from another process than the one that ran this chain: wait for it;
            // in real time, a stage with a fallback runs without it after one sample.
            let mut fallback = false;
            if si > from {
                if let Some(tb) = self.stages[si].trigger() {
                    if tb.origin == Origin::External
                        && self.store.get(tb.spec.topic, k).is_none()
                        && !self.wait_trigger_k(si, tb.spec.topic, k)?
                    {
                        if self.stopping() {
                            continue;
                        }
                        if tb.spec.on_stale != OnStale::Fallback {
                            self.absent_outputs(si, k)?;
                            continue;
                        }
                        fallback = true;
                    }
                }
            }
            if self.cfg.pacing == Pacing::Lockstep && !self.wait_inputs(si, k)? {
                return Ok(false);
            }
            let (mut ib, complete) = self.inbox(si, k);
            self.count_inputs(si, &ib);
            if !complete {
                self.absent_outputs(si, k)?;
                continue;
            }
            let mut took_over = false;
            if self.stages[si].rejoining {
                if self.stages[si].killable {
                    // Lockstep: the rejoin-only inputs of sample k exactly, not whatever is
                    // newest (that would depend on how far the peers have run).
                    self.rejoin_inputs_at(si, k, &mut ib)?;
                }
                if !self.own_outputs_from_the_active_instance(si, &mut ib)? {
                    if self.transport.twin_standing_by()? {
                        // A twin that started after its active instance's newest output (its
                        // receivers get only later ones) waits for the next one, rather than
                        // rejoin without it; it publishes nothing meanwhile.
                        self.stages[si].last_k = Some(k);
                        continue;
                    }
                    // It has just taken over: what it read of its predecessor, if anything.
                    self.own_outputs_from_the_active_instance(si, &mut ib)?;
                }
                self.calling(si, k, Call::Rejoin);
                if self.stages[si].stage.rejoin(k, &ib) == Rejoin::NeedMore {
                    self.stages[si].last_k = Some(k);
                    // Lockstep: nothing of sample k will come from it.
                    self.absent_outputs(si, k)?;
                    continue;
                }
                self.stages[si].rejoining = false;
                took_over = true;
                // Re-read: rejoin may have consumed nothing, but keep the same inputs.
                ib = self.inbox(si, k).0;
            }
            self.stages[si].in_fallback = fallback;
            self.step_publish(si, k, &ib, t_in, fallback)?;
            // Closing a subscription unmaps segments (a bus call, once per restart): after
            // this sample's outputs are out, not before them.
            if took_over {
                self.close_rejoin_inputs(si);
            }
        }
        Ok(true)
    }

    /// Lockstep, a killed stage `si` rejoining at k: its rejoin-only inputs become the
    /// messages of sample k (waited for; None when absent), as the in-process chain order
    /// has them.
    fn rejoin_inputs_at(&mut self, si: usize, k: u64, ib: &mut Inbox) -> Result<()> {
        let started = Instant::now();
        for i in 0..self.stages[si].inputs.len() {
            let b = self.stages[si].inputs[i];
            if b.spec.role != Role::Rejoin || b.origin == Origin::Absent {
                continue;
            }
            let t = b.spec.topic;
            if self.own_output(si, t) {
                // Its own output: the killed instance's last one, which the store keeps as
                // the newest (the absent markers of the downtime do not replace it) and the
                // inbox holds already, as the recorder saw it.
                continue;
            }
            while !self.store.settled(t, k) && b.origin == Origin::External {
                if self.stopping() {
                    break;
                }
                if started.elapsed() > LOCKSTEP_WATCHDOG {
                    bail!(
                        "{}: no {} for sample {k} to rejoin from for {LOCKSTEP_WATCHDOG:?}",
                        self.stages[si].stage.name(),
                        t.name()
                    );
                }
                self.transport.wait(t, WAIT_SLICE)?;
                self.drain_external(None, None, None)?;
            }
            let slot = &mut ib.slots[t.index()];
            slot.msg = self.store.get(t, k);
            slot.fresh = slot.msg.is_some();
        }
        Ok(())
    }

    /// A standby twin's stage `si` rejoining: its rejoin-only inputs on its own outputs that
    /// `ib` has no message for take the newest one the active instance of the process
    /// published (it lives and steps on: a file written when the twin started would be
    /// behind it). A once-per-rejoin bus read. False when one of them is still without a
    /// message.
    fn own_outputs_from_the_active_instance(&mut self, si: usize, ib: &mut Inbox) -> Result<bool> {
        let mut all = true;
        for bi in 0..self.stages[si].inputs.len() {
            let b = self.stages[si].inputs[bi];
            let t = b.spec.topic;
            if b.spec.role != Role::Rejoin
                || !self.own_output(si, t)
                || ib.slots[t.index()].msg.is_some()
            {
                continue;
            }
            match self.transport.twin_newest(t)? {
                Some(m) => {
                    let slot = &mut ib.slots[t.index()];
                    slot.msg = Some(m);
                    slot.fresh = true;
                }
                None => all = false,
            }
        }
        Ok(all)
    }

    /// True when stage `si` publishes `t`: a rejoin-only input on it is the stage's own last
    /// output (docs/architecture.md, "Bumpless rejoin").
    fn own_output(&self, si: usize, t: TopicId) -> bool {
        self.stages[si].stage.outputs().contains(&t)
    }

    /// Stage `si` has taken over: see [`Self::close_rejoin_inputs`].
    fn end_rejoin(&mut self, si: usize) {
        self.stages[si].rejoining = false;
        self.close_rejoin_inputs(si);
    }

    /// Stage `si`, no longer rejoining, closes its rejoin-only inputs that no other stage
    /// here still reads (see [`Transport::close`]): once per restart, not per sample.
    fn close_rejoin_inputs(&mut self, si: usize) {
        for i in 0..self.stages[si].inputs.len() {
            let b = self.stages[si].inputs[i];
            if b.spec.role != Role::Rejoin
                || b.origin != Origin::External
                || self.stages[si].killable
            {
                continue;
            }
            let still_read = self.stages.iter().any(|h| {
                h.inputs.iter().any(|o| {
                    o.spec.topic == b.spec.topic
                        && o.origin == Origin::External
                        && (o.spec.role != Role::Rejoin || h.rejoining)
                })
            });
            if !still_read {
                self.transport.close(b.spec.topic);
            }
        }
    }

    /// Counts what `ib` says of stage `si`'s inputs: those it marks stale (rejoin-only and
    /// absent ones do not count; returned), and whether a producer's process is down.
    fn count_inputs(&mut self, si: usize, ib: &Inbox) -> u64 {
        let st = &mut self.stages[si];
        let stale = st
            .inputs
            .iter()
            .filter(|b| {
                b.spec.role != Role::Rejoin
                    && b.origin != Origin::Absent
                    && !ib.slot(b.spec.topic).fresh
            })
            .count() as u64;
        st.counters.stale_inputs += stale;
        st.counters.producer_down_samples += u64::from(ib.producer_down());
        stale
    }

    /// Waits (real time: briefly; lockstep: with the watchdog) for the trigger of stage `si`
    /// with index k from another process.
    fn wait_trigger_k(&mut self, si: usize, topic: TopicId, k: u64) -> Result<bool> {
        let started = Instant::now();
        loop {
            while let Some(m) = self.transport.try_recv(topic)? {
                if m.hdr().is_warmup() || m.hdr().is_end() {
                    continue;
                }
                if m.hdr().is_absent() {
                    self.take_absent(topic, m.hdr());
                    continue;
                }
                if self.admit(si, &m) {
                    self.store.put(m);
                }
            }
            if self.store.get(topic, k).is_some() {
                return Ok(true);
            }
            // Lockstep: known to be absent (dropped, or rejected as unusable).
            if self.store.settled(topic, k) {
                return Ok(false);
            }
            if self.stopping() {
                return Ok(false);
            }
            let limit = match self.cfg.pacing {
                Pacing::Lockstep => LOCKSTEP_WATCHDOG,
                Pacing::Realtime => Duration::from_nanos(self.cfg.ts_ns),
            };
            if started.elapsed() > limit {
                if self.cfg.pacing == Pacing::Lockstep {
                    bail!(
                        "{}: no {} for sample {k} for {LOCKSTEP_WATCHDOG:?}",
                        self.stages[si].stage.name(),
                        topic.name()
                    );
                }
                self.stages[si].counters.stale_inputs += 1;
                return Ok(false);
            }
            self.transport
                .wait(topic, Duration::from_nanos(self.cfg.ts_ns / 4))?;
        }
    }

    /// Sends a marker with header `hdr` on every output of stages `from..`.
    fn forward_marker(&mut self, from: usize, hdr: Header) -> Result<()> {
        for si in from..self.stages.len() {
            for &t in self.stages[si].stage.outputs() {
                self.transport.send(&Msg::marker(t, hdr))?;
            }
        }
        Ok(())
    }

    /// Each stage's status when due (`last`: now).
    fn status(&mut self, last: bool) -> Result<()> {
        for i in 0..self.stages.len() {
            let Some(k) = self.stages[i].last_k else {
                continue;
            };
            let cyc = (i == 0 && self.is_source()).then_some(&self.cycle);
            let h = &self.stages[i];
            self.transport
                .status(i, k, &h.counters, &h.hists, cyc, last)?;
        }
        Ok(())
    }

    // ---------------------------------------------------------------- the source

    fn warm_up(&mut self) -> Result<()> {
        let waits: Vec<TopicId> = self.stages[0]
            .inputs
            .iter()
            .filter(|b| b.origin == Origin::External && b.spec.role == Role::Latest)
            .map(|b| b.spec.topic)
            .collect();
        for i in 0..WARMUP_MESSAGES {
            let hdr = Header {
                k: i,
                flags: FLAG_WARMUP,
                t_pub_ns: now_ns(),
                ..Default::default()
            };
            self.forward_marker(0, hdr)?;
            for &t in &waits {
                let started = Instant::now();
                'wait: loop {
                    while let Some(m) = self.transport.try_recv(t)? {
                        if m.hdr().is_warmup() && m.hdr().k == i {
                            break 'wait;
                        }
                    }
                    if self.stopping() {
                        return Ok(());
                    }
                    self.transport.wait(t, WAIT_SLICE)?;
                    if started.elapsed() > LOCKSTEP_WATCHDOG {
                        bail!("warm-up message {i} did not come back through the chain on {} within {LOCKSTEP_WATCHDOG:?}", t.name());
                    }
                }
            }
        }
        Ok(())
    }

    fn run_source(&mut self) -> Result<()> {
        let ts_ns = self.cfg.ts_ns;
        let n = self.cfg.samples;
        let realtime = self.cfg.pacing == Pacing::Realtime;
        let (t0, k_start) = if self.cfg.rejoin {
            let last = self
                .cfg
                .rejoin_from
                .iter()
                .find(|m| m.topic() == TopicId::Truth)
                .copied()
                .ok_or_else(|| {
                    anyhow!("a restarted source needs its last output to rejoin from")
                })?;
            if !realtime || last.hdr().t_sample_ns == 0 {
                bail!("a plant can only rejoin a real-time drive");
            }
            let lk = last.hdr().k;
            let t0 = last.hdr().t_sample_ns - lk * ts_ns;
            // The source rejoins at a sample 2 ms ahead, after bringing its model through
            // the downtime (the plant integrates the motor up to it); if that took so long
            // that the sample has passed, it aims again (the result depends only on `last`
            // and the sample).
            let mut k = lk + 1;
            for _ in 0..8 {
                k = ((now_ns() + 2_000_000 - t0) / ts_ns + 1).max(lk + 1);
                let mut ib = Inbox::default();
                ib.put(last);
                self.calling(0, k, Call::Rejoin);
                self.stages[0].stage.rejoin(k, &ib);
                if t0 + k * ts_ns > now_ns() {
                    break;
                }
            }
            self.end_rejoin(0);
            (t0, k)
        } else {
            if self.cfg.warm_up {
                self.warm_up()?;
            }
            (
                crate::rt::schedule_start_ns(realtime && self.cfg.tick_aligned),
                0,
            )
        };
        let mut recorder_done = 0u64;
        let mut loop_start = 0u64;
        let mut t_woken = 0u64;
        // The first delayed input of the source is the command whose availability makes the
        // cycle (t_k → command k available).
        let cmd_topic = self.stages[0]
            .inputs
            .iter()
            .find(|b| b.spec.delay > 0 && b.spec.role == Role::Latest)
            .map(|b| b.spec.topic);
        if let Some(f) = self.first_sample.take() {
            f()?;
        }
        // ---- real-time loop: no allocation, no locks, no logging ----
        for k in k_start..=n {
            let deadline = t0 + k * ts_ns;
            if realtime {
                if self.cfg.spin_ns > 0 {
                    sleep_until_ns(deadline - self.cfg.spin_ns);
                    while now_ns() < deadline {
                        std::hint::spin_loop();
                    }
                } else {
                    sleep_until_ns(deadline);
                }
                t_woken = now_ns();
                self.drain_external(None, Some(k), Some(k))?;
            } else if k > 0 && !self.wait_inputs(0, k)? {
                break;
            }
            // What this deadline showed (the wake-up's lateness, whether command k − 1 was
            // there) is taken now and recorded once this sample's outputs are out: the
            // histograms stay off the critical path (docs/architecture.md, "Where the
            // microseconds go").
            let seen = Deadline {
                deadline,
                wake_ns: realtime.then(|| t_woken as i64 - deadline as i64),
                cmd: match cmd_topic {
                    Some(t) if realtime && (k > k_start || (k > 0 && !self.cfg.rejoin)) => {
                        let avail = self.store.get(t, k - 1).map(|m| m.hdr().t_pub_ns);
                        Some((k - 1, deadline - ts_ns, avail))
                    }
                    _ => None,
                },
            };
            if k == k_start {
                loop_start = now_ns();
            }
            // One read of the stop flag for both decisions: a stop signal from outside that
            // landed between two reads would have been taken for the drive's own stop, and
            // the end marker forwarded would have ended the whole drive (its sender is
            // stored before the flag, so a flag read as set has it).
            let stopping = self.stopping();
            if stopping && k < n && (self.stop_without_end)() {
                break;
            }
            if stopping || k == n {
                let hdr = Header {
                    k,
                    flags: FLAG_END,
                    t_pub_ns: now_ns(),
                    ..Default::default()
                };
                self.forward_marker(0, hdr)?;
                self.account_deadline(seen);
                break;
            }
            // The source's execution starts when it wakes: taking its inputs is part of it.
            let t_in = if realtime { t_woken } else { now_ns() };
            let (mut ib, _) = self.inbox(0, k);
            // Lockstep, the plant killed or stopped: no command reaches the inverter (held,
            // then its safe state), the motor is integrated on, the measurements are absent
            // and the true state is flagged `plant_down`, as a real-time downtime is rebuilt.
            let down = self.down(0, k);
            if down {
                for s in ib.slots.iter_mut() {
                    s.msg = None;
                    s.fresh = false;
                }
            }
            let stale = self.count_inputs(0, &ib);
            let mut out = Outbox::default();
            self.calling(0, k, Call::Step);
            self.stages[0].stage.step(k, &ib, &mut out);
            let t_end = now_ns();
            if realtime {
                self.delay(0, k);
            }
            // One instant for the sample's outputs, as a stage's (the truth after the
            // measurement would carry the time the plant got the core back from the chain).
            let t_pub = now_ns();
            for mut m in out.drain() {
                let t = m.topic();
                let hd = m.hdr_mut();
                hd.t_sample_ns = if realtime { deadline } else { 0 };
                hd.t_pub_ns = t_pub;
                if down {
                    if t != TopicId::Truth {
                        self.absent(t, k)?;
                        continue;
                    }
                    hd.flags |= FLAG_PLANT_DOWN;
                }
                self.publish(m)?;
            }
            // A missing input: wake the stages that should have produced it, after this
            // sample's outputs are out, so that a stage falling back on the clock computes
            // this sample's output in time for the next one.
            if stale > 0 && realtime {
                for i in 0..self.cfg.poke.len() {
                    let t = self.cfg.poke[i];
                    self.transport.poke(t)?;
                }
            }
            self.stages[0].hists.stepped(t_in, t_end);
            self.account_deadline(seen);
            self.stages[0].counters.samples += 1;
            self.stages[0].last_k = Some(k);
            // The rest of this process's chain, in order, on the source's outputs.
            if self.stages.len() > 1 && !self.run_chain(1, k, now_ns())? {
                break;
            }
            for si in 0..self.stages.len() {
                self.calling(si, k, Call::AfterPublish);
                self.stages[si].stage.after_publish();
            }
            // Take what the next sample reads if it is here already: on one core the chain
            // has published command k before the source runs again, and a read at the next
            // deadline would put the bus call on the critical path. What has not come yet is
            // read at the deadline as before, so the inputs and their counts do not change.
            if realtime {
                self.drain_external(None, Some(k + 1), Some(k + 1))?;
            }
            self.status(false)?;
            if !realtime {
                // Flow control: never run more than half a recorder buffer ahead.
                let started = Instant::now();
                loop {
                    match self.transport.recorder_progress()? {
                        None => break,
                        Some(done) => recorder_done = recorder_done.max(done),
                    }
                    if k < recorder_done + (crate::bus::MAX_BUFFER / 2) as u64 || self.stopping() {
                        break;
                    }
                    self.transport.wait_recorder(WAIT_SLICE)?;
                    if started.elapsed() > LOCKSTEP_WATCHDOG {
                        bail!("recorder stopped reading at sample {recorder_done}");
                    }
                }
            }
        }
        // ---- end of the real-time loop ----
        let c = &mut self.stages[0].counters;
        c.loop_wall_ns = now_ns().saturating_sub(loop_start);
        c.deadline_misses = self.cycle.misses.misses;
        c.longest_miss_run = self.cycle.misses.longest_run;
        Ok(())
    }

    // ---------------------------------------------------------------- triggered processes

    fn run_triggered(&mut self) -> Result<()> {
        let trig = self.stages[0].trigger().expect("not the source");
        let topic = trig.spec.topic;
        let realtime = self.cfg.pacing == Pacing::Realtime;
        let mut last_input = Instant::now();
        let every_sample = self.stages[0].stage.steps_every_sample();
        // The samples at which some stage of this process steps: multiples of this.
        let step_every = self
            .stages
            .iter()
            .map(|h| h.divider)
            .reduce(gcd)
            .unwrap_or(1);
        // Running on the clock (the trigger is lost): a process that steps every sample
        // sleeps until the next clock message if the transport wakes it for that (a
        // missing sample, the source dead, ends the sleep after two sample times);
        // otherwise it polls at half its own period.
        let on_clock = self.cfg.clock_wakes && step_every == 1;
        let (fallback_topic, fallback_wait) = if on_clock {
            (
                self.cfg.clock_topic,
                Duration::from_nanos(2 * self.cfg.ts_ns),
            )
        } else {
            (topic, Duration::from_nanos(self.cfg.ts_ns * step_every / 2))
        };
        // ---- real-time loop: no allocation, no locks, no logging ----
        'outer: while !self.stopping() {
            self.status(false)?;
            let in_fallback = self.stages.iter().any(|h| h.in_fallback);
            if in_fallback && realtime {
                self.transport.wait(fallback_topic, fallback_wait)?;
            } else {
                self.transport.wait(topic, WAIT_SLICE)?;
            }
            let mut got = false;
            while let Some(m) = self.transport.try_recv(topic)? {
                got = true;
                // Only lockstep's watchdog reads it: real time spares the clock read.
                if !realtime {
                    last_input = Instant::now();
                }
                let hdr = *m.hdr();
                // An end marker counts only at the run's last sample (the source sends it
                // there): a forged one cannot stop the drive.
                if hdr.is_end() && hdr.k < self.cfg.samples {
                    self.stages[0].counters.rejected_inputs += 1;
                    continue;
                }
                if hdr.is_warmup() || hdr.is_end() {
                    // The markers on the other inputs go too: a transport that delivers
                    // markers without loss (the bench's Unix sockets) blocks their sender
                    // while the receiver's queue is full.
                    self.drain_external(Some(topic), None, None)?;
                    self.forward_marker(0, hdr)?;
                    if hdr.is_end() {
                        break 'outer;
                    }
                    continue;
                }
                if let Some(f) = self.first_sample.take() {
                    f()?;
                }
                // Lockstep: an absent marker, or an unusable trigger, leaves the sample without
                // its trigger; the chain runs it as it would a stale one (docs/architecture.md,
                // "Fault model").
                let usable = if hdr.is_absent() {
                    if !self.take_absent(topic, &hdr) {
                        continue;
                    }
                    false
                } else if self.admit(0, &m) {
                    true
                } else if !realtime && self.store.settled(topic, hdr.k) {
                    false
                } else {
                    continue;
                };
                let h0 = &mut self.stages[0];
                if h0.last_seen.is_some_and(|l| hdr.k <= l) {
                    h0.counters.late_inputs += 1;
                    continue;
                }
                if let Some(l) = h0.last_seen {
                    h0.counters.stale_inputs += hdr.k - l - 1;
                }
                h0.last_seen = Some(hdr.k);
                if usable {
                    self.store.put(m);
                    // The trigger is back: the stages it triggers leave the clock (a sample
                    // the fallback already computed is not stepped again).
                    for h in self.stages.iter_mut() {
                        if h.trigger().is_some_and(|t| t.spec.topic == topic) {
                            h.in_fallback = false;
                        }
                    }
                }
                // A sample that no stage here steps (they run slower than their trigger)
                // only goes into the store: it is neither behind nor a wake-up.
                if !every_sample && !hdr.k.is_multiple_of(step_every) {
                    continue;
                }
                // The other inputs of this sample, once its trigger is in hand (without
                // it, `fallbacks` takes them all).
                self.drain_external(Some(topic), None, Some(hdr.k))?;
                // Behind: a newer trigger waits. For stages slower than their trigger, only
                // once the next sample they step is due: a waiting sample in between is none
                // of theirs (a vDSO clock read, no system call).
                let behind = realtime
                    && self.transport.pending(topic)?
                    && (step_every == 1
                        || now_ns()
                            >= hdr
                                .t_sample_ns
                                .saturating_add(step_every.saturating_mul(self.cfg.ts_ns)));
                if behind || (self.stages[0].rejoining && !every_sample) {
                    // Behind (a newer trigger is waiting), or rejoining: only the newest is
                    // published. A stage that needs every sample steps this one silently.
                    if every_sample && !self.stages[0].rejoining {
                        let (ib, complete) = self.inbox(0, hdr.k);
                        if complete {
                            let mut out = Outbox::default();
                            self.calling(0, hdr.k, Call::Step);
                            self.stages[0].stage.step(hdr.k, &ib, &mut out);
                        }
                    }
                    if behind {
                        self.stages[0].counters.skipped += 1;
                        self.stages[0].last_k = Some(hdr.k);
                        continue;
                    }
                }
                let t_in = now_ns();
                let t_notify = self.transport.notified_ns(topic);
                let more = self.run_chain(0, hdr.k, t_in)?;
                // Recorded once the chain's outputs are out, off the critical path.
                self.stages[0]
                    .hists
                    .input(t_in, hdr.t_pub_ns, t_notify, hdr.t_sample_ns);
                if !more {
                    break 'outer;
                }
            }
            if !realtime {
                if self.stages[0].last_k.is_some() && last_input.elapsed() > LOCKSTEP_WATCHDOG {
                    let c = self.stages[0].counters;
                    bail!(
                        "{}: no {} for {LOCKSTEP_WATCHDOG:?} (last stepped: {:?}; {} rejected, {} late)",
                        self.stages[0].stage.name(),
                        topic.name(),
                        self.stages[0].last_k,
                        c.rejected_inputs,
                        c.late_inputs,
                    );
                }
                continue;
            }
            if got {
                continue;
            }
            self.fallbacks()?;
        }
        // ---- end of the real-time loop ----
        Ok(())
    }

    /// Real time, woken without a trigger: every stage whose trigger is from another process
    /// and has fallen `max_age` samples behind the drive (the newest sample of the clock
    /// topic) runs on the clock instead, with its trigger marked stale.
    fn fallbacks(&mut self) -> Result<()> {
        let clock = self.cfg.clock_topic;
        self.drain_external(None, None, None)?;
        while let Some(m) = self.transport.try_recv(clock)? {
            let h = m.hdr();
            if !h.is_warmup() && !h.is_end() && !h.is_absent() && m.is_finite() {
                self.store.put(m);
            }
        }
        let Some(kn) = self.store.newest_k(clock) else {
            return Ok(());
        };
        for si in 0..self.stages.len() {
            let Some(tb) = self.stages[si].trigger() else {
                continue;
            };
            if tb.origin != Origin::External || tb.spec.on_stale != OnStale::Fallback {
                continue;
            }
            let Some(last) = self.stages[si].last_seen.or(self.stages[si].last_k) else {
                continue;
            };
            let lag = if self.stages[si].in_fallback {
                1
            } else {
                tb.spec.max_age
            };
            if kn < last + lag {
                continue;
            }
            let d = self.stages[si].divider;
            let j = kn / d * d;
            if self.stages[si].last_k.is_some_and(|l| j <= l) || self.stages[si].rejoining {
                continue;
            }
            let (mut ib, complete) = self.inbox(si, j);
            ib.set_stale(
                tb.spec.topic,
                j - self.store.newest_k(tb.spec.topic).unwrap_or(0).min(j),
            );
            if !complete {
                continue;
            }
            self.stages[si].in_fallback = true;
            self.stages[si].counters.stale_inputs += 1;
            self.stages[si].counters.producer_down_samples += u64::from(ib.producer_down());
            let t_in = now_ns();
            self.step_publish(si, j, &ib, t_in, true)?;
        }
        Ok(())
    }

    /// Names and values of each stage's diagnostics (after the run).
    pub fn diagnostics(&self) -> Vec<(&'static str, Vec<(&'static str, u64)>)> {
        self.stages
            .iter()
            .map(|h| {
                let names = h.stage.diagnostic_names();
                let mut vals = vec![0u64; names.len()];
                h.stage.diagnostics(&mut vals);
                (h.stage.name(), names.iter().copied().zip(vals).collect())
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    //! The host's own policies (catch-up, the clock fallback, end forwarding) on a scripted
    //! transport: no bus, no clock.
    use super::*;
    use crate::config::Scenario;
    use crate::messages::*;
    use crate::stages::{CurrentLoopStage, ObserverStage, PlantStage, SpeedLoopStage};
    use std::collections::VecDeque;

    fn scenario() -> Scenario {
        let path = format!(
            "{}/../../scenarios/kyslan-pi.toml",
            env!("CARGO_MANIFEST_DIR")
        );
        Scenario::from_toml(&std::fs::read_to_string(&path).unwrap(), &path).unwrap()
    }

    /// Delivers queued messages per topic; on the n-th wait, runs a scripted action.
    #[derive(Default)]
    struct Script {
        queues: [VecDeque<Msg>; N_TOPICS],
        sent: Vec<Msg>,
        waits: usize,
        on_wait: Vec<(usize, Msg)>,
        /// Each closed topic, with how many messages had been sent when it was closed.
        closed: Vec<(TopicId, usize)>,
        /// From this wait on, the producer of this topic is down.
        down_from: Option<(usize, TopicId)>,
        /// A standby twin: its active instance dies at this wait, and the newest output of
        /// that instance it has read is this message from that wait on.
        twin: Option<(usize, usize, Msg)>,
    }

    impl Transport for Script {
        fn send(&mut self, msg: &Msg) -> Result<()> {
            self.sent.push(*msg);
            Ok(())
        }
        fn try_recv(&mut self, topic: TopicId) -> Result<Option<Msg>> {
            Ok(self.queues[topic.index()].pop_front())
        }
        fn pending(&mut self, topic: TopicId) -> Result<bool> {
            Ok(!self.queues[topic.index()].is_empty())
        }
        fn close(&mut self, topic: TopicId) {
            self.closed.push((topic, self.sent.len()));
        }
        fn twin_newest(&mut self, _topic: TopicId) -> Result<Option<Msg>> {
            Ok(self
                .twin
                .and_then(|(_, from, m)| (self.waits >= from).then_some(m)))
        }
        fn twin_standing_by(&mut self) -> Result<bool> {
            Ok(self.twin.is_some_and(|(dies, _, _)| self.waits < dies))
        }
        fn producer_up(&self, topic: TopicId) -> bool {
            !self
                .down_from
                .is_some_and(|(w, t)| t == topic && self.waits >= w)
        }
        fn wait(&mut self, _topic: TopicId, _timeout: Duration) -> Result<()> {
            self.waits += 1;
            let n = self.waits;
            // Watchdog against hangs: a host that never stops fails the test instead.
            assert!(
                n < 100_000,
                "the host is still waiting after the script ended"
            );
            for (w, m) in self.on_wait.iter().filter(|(w, _)| *w == n) {
                let _ = w;
                self.queues[m.topic().index()].push_back(*m);
            }
            Ok(())
        }
    }

    fn meas(k: u64, theta: f64) -> Msg {
        meas_at(k, theta, 1_000_000 + k * 100_000)
    }

    /// The messages of `topic` among `sent`, its end marker left out.
    fn published(sent: &[Msg], topic: TopicId) -> impl Iterator<Item = &Msg> {
        sent.iter()
            .filter(move |m| m.topic() == topic && !m.hdr().is_end())
    }

    /// Measurement k with encoder angle `theta` and deadline `t_sample_ns`.
    fn meas_at(k: u64, theta: f64, t_sample_ns: u64) -> Msg {
        Msg::Meas(Measurement {
            hdr: Header {
                k,
                t_sample_ns,
                ..Default::default()
            },
            theta_m_enc: theta,
            ..Default::default()
        })
    }

    fn end(topic: TopicId, k: u64) -> Msg {
        Msg::marker(
            topic,
            Header {
                k,
                flags: FLAG_END,
                ..Default::default()
            },
        )
    }

    fn config(sc: &Scenario) -> HostConfig {
        HostConfig {
            spin_ns: 0,
            warm_up: false,
            ..HostConfig::for_scenario(sc, Pacing::Realtime, 100)
        }
    }

    fn est(k: u64, omega_m: f64) -> Msg {
        Msg::Est(Estimate {
            hdr: Header {
                k,
                t_sample_ns: 1_000_000 + k * 100_000,
                ..Default::default()
            },
            omega_m,
            ..Default::default()
        })
    }

    #[test]
    fn a_restarted_speed_loop_closes_its_rejoin_only_input_once_it_has_taken_over() {
        let sc = scenario();
        let run = |rejoin: bool| {
            let mut tr = Script::default();
            let cmd = Msg::Cmd(VoltageCommand {
                hdr: header(0, 1_000_000),
                ..Default::default()
            });
            tr.queues[TopicId::Est.index()].push_back(est(0, 10.0));
            tr.queues[TopicId::Cmd.index()].push_back(cmd);
            for k in 1..=20 {
                tr.on_wait.push((k as usize + 1, est(k, 10.0)));
            }
            tr.on_wait.push((22, end(TopicId::Est, 100)));
            let stages: Vec<Box<dyn Stage>> = vec![Box::new(SpeedLoopStage::new(&sc))];
            let producers = [
                (TopicId::Est, 1, false),
                (TopicId::Cmd, 1, false),
                (TopicId::Iref, 1, true),
            ];
            let cfg = HostConfig {
                rejoin,
                ..config(&sc)
            };
            let mut host = Host::new(stages, &producers, tr, cfg);
            host.run().unwrap();
            let sent = &host.transport.sent;
            let steps = published(sent, TopicId::Iref).count();
            // What had been published on the speed loop's output when each topic was closed.
            let closed: Vec<(TopicId, usize)> = host
                .transport
                .closed
                .iter()
                .map(|&(t, n)| (t, published(&sent[..n], TopicId::Iref).count()))
                .collect();
            (closed, steps)
        };
        // Restarted: the command topic is read while rejoining, then released, once, after
        // the output of the sample it took over at is out (closing unmaps segments); the
        // stage then steps as usual (samples 0, 10 and 20 of the 10-sample speed period).
        assert_eq!(run(true), (vec![(TopicId::Cmd, 1)], 3));
        // A first start never subscribed to it, and closes nothing.
        assert_eq!(run(false), (vec![], 3));
    }

    /// An outer loop that reads its own last output back while it rejoins and publishes
    /// the position it found there (−1 without one).
    struct ReadsItsOwnOutput {
        found: f64,
    }

    impl Stage for ReadsItsOwnOutput {
        fn name(&self) -> &'static str {
            "outer"
        }
        fn inputs(&self) -> &'static [InputSpec] {
            const INPUTS: &[InputSpec] = &[
                InputSpec::trigger(TopicId::Meas, 1, OnStale::Required),
                InputSpec::rejoin(TopicId::Wref),
            ];
            INPUTS
        }
        fn outputs(&self) -> &'static [TopicId] {
            &[TopicId::Wref]
        }
        fn step(&mut self, k: u64, _inputs: &Inbox, out: &mut Outbox) {
            out.push(Msg::Wref(crate::messages::SpeedRef {
                hdr: header(k, 0),
                theta_m: self.found,
                ..Default::default()
            }));
        }
        fn rejoin(&mut self, _k: u64, inputs: &Inbox) -> Rejoin {
            self.found = inputs.newest_wref().map_or(-1.0, |w| w.theta_m);
            Rejoin::Done
        }
    }

    #[test]
    fn a_restarted_process_hands_a_stage_its_own_last_output_from_the_rejoin_file() {
        let run = |rejoin_from: Vec<Msg>| {
            let mut tr = Script::default();
            tr.queues[TopicId::Meas.index()].push_back(meas(0, 1.0));
            tr.on_wait.push((2, end(TopicId::Meas, 100)));
            own_output_found(tr, rejoin_from).first().unwrap().1
        };
        let last = Msg::Wref(crate::messages::SpeedRef {
            hdr: header(30, 0),
            theta_m: 7.5,
            ..Default::default()
        });
        // Another topic's message (the plant's state) fills no slot of it.
        let truth = Msg::Truth(PlantTruth::default());
        assert_eq!(run(vec![truth, last]), 7.5);
        // Without one (it died before the recorder saw an output of it): nothing there.
        assert_eq!(run(vec![truth]), -1.0);
    }

    /// The positions a standby twin's stage publishes (what it found while rejoining),
    /// with their samples: measurements 0 to 5 come at waits 0 to 5; its active instance
    /// dies at wait `dies`, and the newest output of it the twin has read is θ 7.5 from wait
    /// `seen` on.
    fn twin_rejoins(dies: usize, seen: usize) -> Vec<(u64, f64)> {
        let mut tr = Script::default();
        tr.queues[TopicId::Meas.index()].push_back(meas(0, 1.0));
        for k in 1..6 {
            tr.on_wait.push((k, meas(k as u64, 1.0)));
        }
        tr.on_wait.push((6, end(TopicId::Meas, 100)));
        let last = Msg::Wref(crate::messages::SpeedRef {
            hdr: header(0, 0),
            theta_m: 7.5,
            ..Default::default()
        });
        tr.twin = Some((dies, seen, last));
        own_output_found(tr, Vec::new())
    }

    /// Runs [`ReadsItsOwnOutput`] restarted on `tr`: the positions it published, with their
    /// samples.
    fn own_output_found(tr: Script, rejoin_from: Vec<Msg>) -> Vec<(u64, f64)> {
        let sc = scenario();
        let stages: Vec<Box<dyn Stage>> = vec![Box::new(ReadsItsOwnOutput { found: 0.0 })];
        let producers = [(TopicId::Meas, 1, false), (TopicId::Wref, 1, true)];
        let cfg = HostConfig {
            rejoin: true,
            rejoin_from,
            ..config(&sc)
        };
        let mut host = Host::new(stages, &producers, tr, cfg);
        host.run().unwrap();
        published(&host.transport.sent, TopicId::Wref)
            .filter_map(|m| match m {
                Msg::Wref(w) => Some((w.hdr.k, w.theta_m)),
                _ => None,
            })
            .collect()
    }

    #[test]
    fn a_standby_twin_waits_for_its_active_instances_output_before_it_rejoins() {
        // Started after the active instance's newest output, the twin has read none of it
        // at first: it rejoins at the first sample it has one, and finds it (it had rejoined
        // at sample 0 without one, and counted a position loop's turns from 0).
        let sent = twin_rejoins(100, 3);
        assert_eq!(sent.first().copied(), Some((3, 7.5)), "{sent:?}");
        assert!(sent.iter().all(|&(_, th)| th == 7.5), "{sent:?}");
        // Its active instance died before the twin read an output of it: the twin takes
        // over at its next sample and rejoins without one (as a restarted process that
        // died before it published), instead of waiting for an output that cannot come.
        let sent = twin_rejoins(2, 100);
        assert_eq!(sent.first().copied(), Some((2, -1.0)), "{sent:?}");
        // A restarted process (no twin) rejoins at once, with or without one.
        let first = |sent: Vec<(u64, f64)>| sent.first().map(|s| s.1);
        assert_eq!(first(twin_rejoins(0, 0)), Some(7.5));
        assert_eq!(first(twin_rejoins(0, 100)), Some(-1.0));
    }

    #[test]
    fn the_injection_schedule_on_the_publish_path_is_applied_by_index_without_allocating() {
        use crate::inject::{Inject, InjectKind};
        let mut sc = scenario();
        let at = |kind, target: &str, at_s, count| Inject {
            kind,
            target: target.into(),
            at_s,
            duration_s: 0.0,
            latency_us: 0.0,
            count,
        };
        // 10 kHz: commands 10 and 11 dropped, 20 and 21 corrupt, 30..40 published 1 µs late.
        sc.inject = vec![
            at(InjectKind::Drop, "cmd", 0.001, 2),
            at(InjectKind::Corrupt, "cmd", 0.002, 2),
            Inject {
                duration_s: 0.001,
                latency_us: 1.0,
                ..at(InjectKind::Delay, "current-loop", 0.003, 0)
            },
        ];
        let stages: Vec<Box<dyn Stage>> = vec![Box::new(CurrentLoopStage::new(&sc))];
        let cfg = HostConfig::for_scenario(&sc, Pacing::Lockstep, 100);
        // Room for every message beforehand: pushing within it does not allocate.
        let local = Local {
            sent: Vec::with_capacity(64),
        };
        let mut host = Host::new(stages, &[(TopicId::Cmd, 1, true)], local, cfg);
        let cmd = |k| {
            Msg::Cmd(VoltageCommand {
                hdr: Header {
                    k,
                    ..Default::default()
                },
                ..Default::default()
            })
        };
        let ((), allocations) = crate::alloc_count::allocations_during(|| {
            for k in 0..40 {
                host.delay(0, k);
                host.publish(cmd(k)).unwrap();
            }
            host.observe_cycle(35, 1_000, Some(200_000), true);
        });
        assert_eq!(allocations, 0);
        let sent = &host.transport.sent;
        let ks = |f: fn(&Msg) -> bool| -> Vec<u64> {
            sent.iter().filter(|m| f(m)).map(|m| m.hdr().k).collect()
        };
        // Lockstep: an absent marker in place of each dropped command.
        assert_eq!(sent.len(), 40);
        assert_eq!(ks(|m| m.hdr().is_absent()), [10, 11]);
        assert_eq!(ks(|m| !m.is_finite()), [20, 21]);
        for k in [10, 11, 20, 21] {
            assert!(host.store.get(TopicId::Cmd, k).is_none(), "{k}");
        }
        assert!(host.store.settled(TopicId::Cmd, 10) && host.store.get(TopicId::Cmd, 12).is_some());
        let o = host.stages[0].inject[2];
        assert_eq!((o.cycles, o.misses, o.cycle_max_ns), (1, 1, 199_000));
    }

    #[test]
    fn an_index_far_ahead_is_rejected_and_a_repeated_one_is_counted_late() {
        let sc = scenario();
        // Real time: the drive's sample 0 started 1 ms ago (the run has 100 samples of
        // 100 µs, so the drive is at sample 10 now).
        let t0 = now_ns() - 1_000_000;
        let at = |k: u64| {
            let Msg::Meas(mut m) = meas(k, k as f64 * 0.01) else {
                unreachable!()
            };
            m.hdr.t_sample_ns = t0 + k * 100_000;
            Msg::Meas(m)
        };
        let mut tr = Script::default();
        tr.queues[TopicId::Meas.index()].push_back(at(0));
        tr.on_wait.push((2, at(1)));
        // Forged: far beyond any sample the drive can be at; then a repeat of sample 1.
        tr.on_wait.push((3, at(1_000_000)));
        tr.on_wait.push((4, at(1)));
        tr.on_wait.push((5, at(2)));
        tr.on_wait.push((6, end(TopicId::Meas, 100)));
        let stages: Vec<Box<dyn Stage>> = vec![Box::new(ObserverStage::new(&sc))];
        let producers = [(TopicId::Meas, 1, false), (TopicId::Est, 1, true)];
        let mut host = Host::new(stages, &producers, tr, config(&sc));
        host.run().unwrap();
        let sent: Vec<u64> = host
            .transport
            .sent
            .iter()
            .filter(|m| m.topic() == TopicId::Est)
            .map(|m| m.hdr().k)
            .collect();
        assert_eq!(sent, vec![0, 1, 2, 100]);
        let c = host.stages[0].counters;
        assert_eq!((c.rejected_inputs, c.late_inputs), (1, 1));
    }

    fn header(k: u64, t_sample_ns: u64) -> crate::messages::Header {
        crate::messages::Header {
            k,
            t_sample_ns,
            ..Default::default()
        }
    }

    #[test]
    fn in_real_time_an_index_is_taken_only_once_its_sample_has_started() {
        // 10 kHz; the drive's sample 0 started at t = 1 ms.
        let ts = 100_000;
        let mut w = IndexWindow::new(true, ts, 10);
        // The first message teaches the schedule: sample 5 at 1.5 ms.
        assert!(w.admits(&header(5, 1_500_000), 1_520_000));
        // At 2.0 ms the drive is at sample 10: 10 and 11 (one sample of slack) are taken,
        // 12 is in the future.
        let now = 2_000_000;
        assert!(w.admits(&header(10, 0), now));
        assert!(w.admits(&header(11, 0), now));
        assert!(!w.admits(&header(12, 0), now));
        assert!(!w.admits(&header(u64::MAX, u64::MAX), now));
        // A producer back after 1 s of downtime is taken at once.
        assert!(w.admits(&header(10_009, 0), now + 1_000_000_000));
        // A first message whose instant does not fit its index teaches nothing.
        let mut w = IndexWindow::new(true, ts, 1);
        assert!(w.admits(&header(u64::MAX, 7), now));
        assert_eq!(w.t0_ns, None);
    }

    #[test]
    fn in_lockstep_an_index_is_taken_within_the_window_of_the_newest() {
        // The slowest stage runs every 10 samples: a window of 40.
        let mut w = IndexWindow::new(false, 100_000, 10);
        assert!(w.admits(&header(0, 0), 0));
        assert!(w.admits(&header(40, 0), 0));
        assert!(!w.admits(&header(81, 0), 0));
        assert!(w.admits(&header(80, 0), 0));
        // Older indices are for the caller to judge (late), not the window.
        assert!(w.admits(&header(3, 0), 0));
        assert!(!w.admits(&header(u64::MAX, 0), 0));
        // The window is never narrower than 16 samples.
        let mut w = IndexWindow::new(false, 100_000, 1);
        assert!(w.admits(&header(0, 0), 0));
        assert!(w.admits(&header(16, 0), 0));
        assert!(!w.admits(&header(33, 0), 0));
    }

    #[test]
    fn an_end_marker_before_the_last_sample_is_rejected_and_the_stage_goes_on() {
        let sc = scenario();
        let mut tr = Script::default();
        tr.queues[TopicId::Meas.index()].push_back(meas(0, 0.0));
        // Forged: the run (config) has 100 samples, the source ends at sample 100.
        tr.on_wait.push((2, end(TopicId::Meas, 1)));
        tr.on_wait.push((3, meas(1, 0.01)));
        tr.on_wait.push((4, end(TopicId::Meas, 100)));
        let stages: Vec<Box<dyn Stage>> = vec![Box::new(ObserverStage::new(&sc))];
        let producers = [(TopicId::Meas, 1, false), (TopicId::Est, 1, true)];
        let mut host = Host::new(stages, &producers, tr, config(&sc));
        host.run().unwrap();
        let sent: Vec<(u64, bool)> = host
            .transport
            .sent
            .iter()
            .filter(|m| m.topic() == TopicId::Est)
            .map(|m| (m.hdr().k, m.hdr().is_end()))
            .collect();
        assert_eq!(sent, vec![(0, false), (1, false), (100, true)]);
        assert_eq!(host.stages[0].counters.rejected_inputs, 1);
    }

    /// The observer under another name, its step followed by `after` (which may change its
    /// outputs): a stage that breaks the rules of its declaration.
    struct Unruly {
        observer: ObserverStage,
        after: fn(u64, &mut Outbox),
    }

    impl Stage for Unruly {
        fn name(&self) -> &'static str {
            "unruly"
        }
        fn inputs(&self) -> &'static [InputSpec] {
            self.observer.inputs()
        }
        fn outputs(&self) -> &'static [TopicId] {
            self.observer.outputs()
        }
        fn step(&mut self, k: u64, inputs: &Inbox, out: &mut Outbox) {
            self.observer.step(k, inputs, out);
            (self.after)(k, out);
        }
    }

    /// Runs `unruly` on measurements 0 and 1; the host's error and the samples it published.
    fn run_unruly(after: fn(u64, &mut Outbox)) -> (String, Vec<u64>) {
        let sc = scenario();
        let mut tr = Script::default();
        tr.queues[TopicId::Meas.index()].push_back(meas(0, 0.0));
        tr.on_wait.push((2, meas(1, 0.01)));
        let observer = ObserverStage::new(&sc);
        let stages: Vec<Box<dyn Stage>> = vec![Box::new(Unruly { observer, after })];
        let producers = [(TopicId::Meas, 1, false), (TopicId::Est, 1, true)];
        let mut host = Host::new(stages, &producers, tr, config(&sc));
        let e = host.run().unwrap_err().to_string();
        (e, host.transport.sent.iter().map(|m| m.hdr().k).collect())
    }

    #[test]
    fn a_stage_that_leaves_out_a_declared_output_stops_its_host_naming_it() {
        // Its estimate dropped from sample 1 on.
        let (e, sent) = run_unruly(|k, out| {
            if k >= 1 {
                out.msgs[TopicId::Est.index()] = None;
            }
        });
        assert_eq!(
            e,
            "stage 'unruly' published no 'est' at sample 1: a step publishes each of its declared outputs every time it runs"
        );
        assert_eq!(sent, [0]);
    }

    #[test]
    fn a_stage_that_publishes_a_topic_it_did_not_declare_stops_its_host_naming_it() {
        // A speed reference of its own at sample 1.
        let (e, sent) = run_unruly(|k, out| {
            if k == 1 {
                out.push(Msg::Wref(crate::messages::SpeedRef::default()));
            }
        });
        assert_eq!(
            e,
            "stage 'unruly' published 'wref' at sample 1, which it does not declare among its outputs"
        );
        assert_eq!(sent, [0]);
    }

    #[test]
    fn a_stage_that_fell_behind_publishes_only_the_newest_but_its_filter_sees_every_sample() {
        let sc = scenario();
        let mut tr = Script::default();
        for k in 0..5 {
            tr.queues[TopicId::Meas.index()].push_back(meas(k, 0.01 * k as f64));
        }
        // The end comes later (a pending END would also count as "a newer message waits").
        tr.on_wait.push((2, end(TopicId::Meas, 100)));
        let stages: Vec<Box<dyn Stage>> = vec![Box::new(ObserverStage::new(&sc))];
        let producers = [(TopicId::Meas, 1, false), (TopicId::Est, 1, true)];
        let mut host = Host::new(stages, &producers, tr, config(&sc));
        host.run().unwrap();
        let est: Vec<Estimate> = host
            .transport
            .sent
            .iter()
            .filter_map(|m| match m {
                Msg::Est(e) if !e.hdr.is_end() => Some(*e),
                _ => None,
            })
            .collect();
        // Samples 0-4 were all waiting: 0-3 are skipped (counted), only the newest, 4, is
        // published, and the END marker is forwarded.
        assert_eq!(est.iter().map(|e| e.hdr.k).collect::<Vec<_>>(), vec![4]);
        assert_eq!(host.stages[0].counters.skipped, 4);
        assert!(host
            .transport
            .sent
            .iter()
            .any(|m| m.topic() == TopicId::Est && m.hdr().is_end()));
        // The filter stepped through 0-3 silently: estimate 4 equals direct stepping.
        let mut direct = crate::drive::ObserverStep::new(&sc);
        let mut last = Estimate::default();
        for k in 0..5 {
            if let Msg::Meas(m) = meas(k, 0.01 * k as f64) {
                last = direct.step(&m);
            }
        }
        assert_eq!(est[0].omega_m, last.omega_m);
        assert_eq!(est[0].theta_e, last.theta_e);
    }

    /// A stage at a tenth of its trigger's rate that publishes the index of each sample it
    /// steps.
    struct EveryTenth;

    impl Stage for EveryTenth {
        fn name(&self) -> &'static str {
            "tenth"
        }
        fn inputs(&self) -> &'static [InputSpec] {
            const INPUTS: &[InputSpec] = &[InputSpec::trigger(TopicId::Meas, 1, OnStale::Required)];
            INPUTS
        }
        fn outputs(&self) -> &'static [TopicId] {
            &[TopicId::Wref]
        }
        fn divider(&self) -> u64 {
            10
        }
        fn step(&mut self, k: u64, _inputs: &Inbox, out: &mut Outbox) {
            out.push(Msg::Wref(crate::messages::SpeedRef {
                hdr: header(k, 0),
                ..Default::default()
            }));
        }
    }

    #[test]
    fn a_stage_slower_than_its_trigger_is_behind_only_once_its_next_sample_is_due() {
        let sc = scenario();
        // Samples 0-3 wait when the host wakes; their deadlines lie `ahead_ns` from now.
        let run = |ahead_ns: i64| {
            let mut tr = Script::default();
            let t0 = (now_ns() as i64 + ahead_ns) as u64;
            for k in 0..4 {
                tr.queues[TopicId::Meas.index()].push_back(meas_at(k, 0.0, t0 + k * 100_000));
            }
            tr.on_wait.push((2, end(TopicId::Meas, 100)));
            let stages: Vec<Box<dyn Stage>> = vec![Box::new(EveryTenth)];
            let producers = [(TopicId::Meas, 1, false), (TopicId::Wref, 10, true)];
            let mut host = Host::new(stages, &producers, tr, config(&sc));
            host.run().unwrap();
            let sent: Vec<u64> = published(&host.transport.sent, TopicId::Wref)
                .map(|m| m.hdr().k)
                .collect();
            (sent, host.stages[0].counters.skipped)
        };
        // Sample 10, the next it steps, is not due for a second: samples 1-3 waiting behind
        // sample 0 are none of its own, and it steps sample 0 (it skipped it, publishing
        // nothing for the period, when any waiting sample counted).
        assert_eq!(run(1_000_000_000), (vec![0], 0));
        // Sample 10 was due 10 ms ago: behind, it skips sample 0 for the newer ones.
        assert_eq!(run(-11_000_000), (vec![], 1));
    }

    /// A current loop of `sc` (speed loop at a tenth of the rate, in another process) on
    /// the script, not yet run.
    fn current_loop_host<T: Transport>(sc: &Scenario, tr: T) -> Host<T> {
        let stages: Vec<Box<dyn Stage>> = vec![Box::new(CurrentLoopStage::new(sc))];
        let producers = [
            (TopicId::Meas, 1, false),
            (TopicId::Est, 1, false),
            (TopicId::Iref, 10, false),
            (TopicId::Cmd, 1, true),
        ];
        Host::new(stages, &producers, tr, config(sc))
    }

    /// A host of the plant alone (the source) on transport `tr`.
    fn plant_host<T: Transport>(sc: &Scenario, tr: T, cfg: HostConfig) -> Host<T> {
        let stages: Vec<Box<dyn Stage>> = vec![Box::new(PlantStage::new(sc))];
        let producers = [
            (TopicId::Cmd, 1, false),
            (TopicId::Meas, 1, true),
            (TopicId::Truth, 1, true),
        ];
        Host::new(stages, &producers, tr, cfg)
    }

    /// [`current_loop_host`] run on the script to its end.
    fn run_current_loop<T: Transport>(sc: &Scenario, tr: T) -> Host<T> {
        let mut host = current_loop_host(sc, tr);
        host.run().unwrap();
        host
    }

    /// The speed loop's reference of sample 0: 50 rad/s, i_q* 0.5 A.
    fn iref0() -> Msg {
        Msg::Iref(CurrentRef {
            hdr: Header {
                k: 0,
                ..Default::default()
            },
            omega_ref: 50.0,
            i_d_ref: 0.0,
            i_q_ref: 0.5,
        })
    }

    /// The commands among `sent` (end marker left out): each sample index and whether it
    /// was flagged as made from a stale input.
    fn commands(sent: &[Msg]) -> Vec<(u64, bool)> {
        sent.iter()
            .filter_map(|m| match m {
                Msg::Cmd(c) if !c.hdr.is_end() => {
                    Some((c.hdr.k, c.hdr.flags & FLAG_STALE_INPUT != 0))
                }
                _ => None,
            })
            .collect()
    }

    /// A process reads an input only as far as the sample it runs: with measurement k waiting
    /// beside estimate k it reads the measurement topic once per sample (not a second time to
    /// find it empty), and the speed loop's topic only when a new reference is due (samples
    /// 1, 11 and 21 of its 10-sample period); every command is made from fresh inputs. (A
    /// host that read each input until it was empty read the measurements 51 times.)
    #[test]
    fn a_process_reads_each_input_only_as_far_as_the_sample_it_runs() {
        struct Counting(Script, [usize; N_TOPICS]);
        impl Transport for Counting {
            fn send(&mut self, msg: &Msg) -> Result<()> {
                self.0.send(msg)
            }
            fn try_recv(&mut self, topic: TopicId) -> Result<Option<Msg>> {
                self.1[topic.index()] += 1;
                self.0.try_recv(topic)
            }
            fn pending(&mut self, topic: TopicId) -> Result<bool> {
                self.0.pending(topic)
            }
            fn wait(&mut self, topic: TopicId, timeout: Duration) -> Result<()> {
                self.0.wait(topic, timeout)
            }
        }
        let sc = scenario();
        let iref = |k: u64| {
            Msg::Iref(CurrentRef {
                hdr: header(k, 1_000_000 + k * 100_000),
                omega_ref: 50.0,
                i_d_ref: 0.0,
                i_q_ref: 0.5,
            })
        };
        let mut tr = Script::default();
        tr.queues[TopicId::Est.index()].push_back(est(0, 7.0));
        tr.queues[TopicId::Meas.index()].push_back(meas(0, 0.2));
        tr.queues[TopicId::Iref.index()].push_back(iref(0));
        // Sample k's messages come at the (k+1)-th wait (the first finds sample 0's).
        for k in 1..25u64 {
            let w = k as usize + 1;
            tr.on_wait.push((w, meas(k, 0.2)));
            tr.on_wait.push((w, est(k, 7.0)));
            if k % 10 == 0 {
                tr.on_wait.push((w, iref(k)));
            }
        }
        tr.on_wait.push((26, end(TopicId::Est, 100)));
        let host = run_current_loop(&sc, Counting(tr, [0; N_TOPICS]));
        assert_eq!(
            commands(&host.transport.0.sent),
            (0..25).map(|k| (k, false)).collect::<Vec<_>>()
        );
        assert_eq!(host.stages[0].counters.stale_inputs, 0);
        let reads = host.transport.1;
        // One more read of each at the end marker, which takes whatever waits.
        assert_eq!(reads[TopicId::Meas.index()], 25 + 1, "{reads:?}");
        assert_eq!(reads[TopicId::Iref.index()], 3 + 1, "{reads:?}");
    }

    /// What a [`Chain`] saw: a command read, a status reported (each with its sample).
    #[derive(Debug, PartialEq)]
    enum Event {
        Read(u64),
        Status(u64),
    }
    /// A chain on the source's core: it answers measurement k with command k at once. With
    /// `stall` (k, d) the machine holds it for d before it answers measurement k.
    #[derive(Default)]
    struct Chain {
        cmds: VecDeque<Msg>,
        events: Vec<Event>,
        stall: Option<(u64, Duration)>,
    }
    impl Transport for Chain {
        fn send(&mut self, msg: &Msg) -> Result<()> {
            if let Msg::Meas(m) = msg {
                if self.stall.is_some_and(|(k, _)| k == m.hdr.k) {
                    std::thread::sleep(self.stall.unwrap().1);
                }
                if !m.hdr.is_end() {
                    self.cmds.push_back(Msg::Cmd(VoltageCommand {
                        hdr: header(m.hdr.k, m.hdr.t_sample_ns),
                        ..Default::default()
                    }));
                }
            }
            Ok(())
        }
        fn try_recv(&mut self, topic: TopicId) -> Result<Option<Msg>> {
            assert_eq!(topic, TopicId::Cmd, "the plant reads only commands");
            let m = self.cmds.pop_front();
            if let Some(m) = &m {
                self.events.push(Event::Read(m.hdr().k));
            }
            Ok(m)
        }
        fn pending(&mut self, _topic: TopicId) -> Result<bool> {
            Ok(!self.cmds.is_empty())
        }
        fn wait(&mut self, _topic: TopicId, _timeout: Duration) -> Result<()> {
            panic!("a real-time source sleeps to its deadlines, it does not wait")
        }
        fn status(
            &mut self,
            _i: usize,
            k: u64,
            _c: &Counters,
            _h: &StageHists,
            _cycle: Option<&CycleMonitor>,
            last: bool,
        ) -> Result<()> {
            if !last {
                self.events.push(Event::Status(k));
            }
            Ok(())
        }
    }
    impl Chain {
        /// A chain with room for `n` samples' commands and events: it allocates nothing
        /// while a host runs.
        fn with_room(n: usize) -> Self {
            Self {
                cmds: VecDeque::with_capacity(n + 8),
                events: Vec::with_capacity(2 * n + 8),
                stall: None,
            }
        }
    }

    /// A real-time source takes the command its next sample reads as soon as the chain has
    /// published it, after its own sample's work and before it sleeps to the next deadline,
    /// not after that deadline: the transport answers measurement k with command k at once
    /// (a chain on the source's core), and every command is read once, before the source's
    /// status report of the sample that made it. (A source that read its command only at
    /// the deadline read command k after that report.) Every sample but the first is made
    /// from its fresh command and none counts as late.
    #[test]
    fn a_source_takes_its_next_command_before_it_sleeps() {
        let sc = scenario();
        let n = 40;
        let cfg = HostConfig {
            samples: n,
            ..config(&sc)
        };
        let mut host = plant_host(&sc, Chain::default(), cfg);
        host.run().unwrap();
        let events = &host.transport.events;
        let at = |e: Event| {
            events
                .iter()
                .position(|x| *x == e)
                .unwrap_or_else(|| panic!("no {e:?} in {events:?}"))
        };
        for k in 0..n - 1 {
            assert!(
                at(Event::Read(k)) < at(Event::Status(k)),
                "command {k} read after the report of sample {k}: {events:?}"
            );
        }
        let reads = events
            .iter()
            .filter(|e| matches!(e, Event::Read(_)))
            .count();
        assert_eq!(reads as u64, n, "each command once: {events:?}");
        let c = &host.stages[0].counters;
        assert_eq!((c.samples, c.late_commands, c.stale_inputs), (n, 0, 0));
    }

    /// The plant's host run for `n` samples in real time on `chain` under the allocation
    /// counter: the host and its allocations.
    fn source_counted(sc: &Scenario, chain: Chain, n: u64) -> (Host<Chain>, u64) {
        let cfg = HostConfig {
            samples: n,
            ..config(sc)
        };
        let mut host = plant_host(sc, chain, cfg);
        let (r, allocations) = crate::alloc_count::allocations_during(|| host.run());
        r.unwrap();
        (host, allocations)
    }

    /// A real-time source (the plant, sleeping to its deadlines, reading each command
    /// ahead) makes as many allocations in a run of 40 samples as in one of 20: none per
    /// sample. What it allocates once, before its first sample, is its own business
    /// (docs/architecture.md, "Real-time rules").
    #[test]
    fn a_real_time_source_allocates_nothing_per_sample() {
        let sc = scenario();
        let count = |n: u64| {
            let (host, allocations) = source_counted(&sc, Chain::with_room(n as usize), n);
            let c = &host.stages[0].counters;
            assert_eq!((c.samples, c.late_commands), (n, 0), "{n} samples");
            allocations
        };
        let (a20, a40) = (count(20), count(40));
        assert_eq!(a20, a40, "allocations in 20 samples and in 40");
    }

    /// A real-time source that catches up after a stall (the machine holds it for 2 ms, 20
    /// samples, at sample 5: it runs the late samples back to back and logs the stall)
    /// makes as many allocations in a run of 60 samples as in one of 40.
    #[test]
    fn a_real_time_source_catching_up_after_a_stall_allocates_nothing_per_sample() {
        let sc = scenario();
        let count = |n: u64| {
            let chain = Chain {
                stall: Some((5, Duration::from_millis(2))),
                ..Chain::with_room(n as usize)
            };
            let (host, allocations) = source_counted(&sc, chain, n);
            assert_eq!(host.stages[0].counters.samples, n, "{n} samples");
            assert!(host.stalls.count >= 1, "{n} samples: no stall logged");
            allocations
        };
        let (a40, a60) = (count(40), count(60));
        assert_eq!(a40, a60, "allocations in 40 samples and in 60");
    }

    /// A stop signal from outside (`stop_without_end`) that lands while the source is
    /// deciding at a deadline: the stop flag is read once there, so the source never takes
    /// it for the drive's own stop and forwards no end marker (which would end the whole
    /// drive). Here the flag turns set right after its first read.
    #[test]
    fn a_stop_from_outside_that_lands_at_a_deadline_sends_no_end_marker() {
        use std::sync::atomic::{AtomicUsize, Ordering};
        use std::sync::Arc;
        let sc = scenario();
        let mut host = plant_host(&sc, Script::default(), config(&sc));
        let reads = Arc::new(AtomicUsize::new(0));
        let r = reads.clone();
        host.stop_when(move || r.fetch_add(1, Ordering::SeqCst) >= 1);
        host.stop_without_end_when(|| true);
        host.run().unwrap();
        assert!(
            reads.load(Ordering::SeqCst) >= 2,
            "the flag was read once only"
        );
        let ends: Vec<(TopicId, u64)> = host
            .transport
            .sent
            .iter()
            .filter(|m| m.hdr().is_end())
            .map(|m| (m.topic(), m.hdr().k))
            .collect();
        assert!(ends.is_empty(), "end markers sent: {ends:?}");
    }

    /// A script with room for `n` messages per queue, `2 n` sent and `n` scripted actions
    /// (plus a few): it allocates nothing while a host runs.
    fn script_with_room(n: usize) -> Script {
        let mut tr = Script::default();
        for q in tr.queues.iter_mut() {
            q.reserve(n + 16);
        }
        tr.sent.reserve(2 * n + 16);
        tr.on_wait.reserve(n + 16);
        tr
    }

    /// Asserts that `count(n)`, the allocations of a run of n wake-ups, is 0 for 20 and 40.
    fn none_in_20_or_40_wake_ups(count: impl Fn(u64) -> u64) {
        assert_eq!(
            (count(20), count(40)),
            (0, 0),
            "allocations in 20 and 40 wake-ups"
        );
    }

    /// The current loop's host run on `tr` under the allocation counter: the host and its
    /// allocations.
    fn current_loop_counted(sc: &Scenario, tr: Script) -> (Host<Script>, u64) {
        let mut host = current_loop_host(sc, tr);
        let (r, allocations) = crate::alloc_count::allocations_during(|| host.run());
        r.unwrap();
        (host, allocations)
    }

    /// A triggered host (the current loop, in real time, one estimate a wake-up) allocates
    /// nothing in its run, set-up included (its buffers are made in `Host::new`), for 20
    /// samples or for 40.
    #[test]
    fn a_triggered_host_allocates_nothing_per_sample() {
        let sc = scenario();
        let count = |n: u64| {
            let mut tr = script_with_room(n as usize);
            tr.queues[TopicId::Est.index()].push_back(est(0, 7.0));
            for k in 0..n {
                tr.queues[TopicId::Meas.index()].push_back(meas(k, 0.2));
            }
            tr.queues[TopicId::Iref.index()].push_back(iref0());
            for k in 1..n {
                tr.on_wait.push((k as usize + 1, est(k, 7.0)));
            }
            tr.on_wait.push((n as usize + 1, end(TopicId::Est, 100)));
            let (host, allocations) = current_loop_counted(&sc, tr);
            assert_eq!(commands(&host.transport.sent).len() as u64, n);
            allocations
        };
        none_in_20_or_40_wake_ups(count);
    }

    /// Catching up (two estimates at each wake-up: the older skipped, the newer stepped) and
    /// an input whose producer is down (the speed loop's, from the 4th wake-up on: each
    /// command made from the reference held, flagged) allocate nothing either: none in a run
    /// of 20 wake-ups, none in one of 40.
    #[test]
    fn catching_up_and_a_producer_down_allocate_nothing() {
        let sc = scenario();
        let count = |n: u64| {
            let mut tr = script_with_room(2 * n as usize);
            for k in 0..2 * n {
                tr.queues[TopicId::Meas.index()].push_back(meas(k, 0.2));
            }
            tr.queues[TopicId::Est.index()].push_back(est(0, 7.0));
            tr.queues[TopicId::Iref.index()].push_back(iref0());
            for j in 1..n {
                let w = j as usize + 1;
                tr.on_wait.push((w, est(2 * j - 1, 7.0)));
                tr.on_wait.push((w, est(2 * j, 7.0)));
            }
            tr.on_wait.push((n as usize + 1, end(TopicId::Est, 1000)));
            tr.down_from = Some((4, TopicId::Iref));
            let (host, allocations) = current_loop_counted(&sc, tr);
            let c = &host.stages[0].counters;
            assert_eq!((c.samples, c.skipped), (n, n - 1), "{n} wake-ups");
            assert!(c.producer_down_samples > 0, "{n} wake-ups: {c:?}");
            allocations
        };
        none_in_20_or_40_wake_ups(count);
    }

    /// The clock's fallback (the observer stops after estimate 1; from the 3rd wake-up on
    /// the current loop steps on each new measurement's encoder angle) allocates nothing:
    /// none in a run of 20 wake-ups, none in one of 40.
    #[test]
    fn stepping_on_the_clock_without_a_trigger_allocates_nothing() {
        let sc = scenario();
        let count = |n: u64| {
            let n = n as usize;
            let mut tr = script_with_room(n);
            tr.queues[TopicId::Est.index()].push_back(est(0, 7.0));
            tr.on_wait.push((2, est(1, 7.0)));
            for k in 0..6 {
                tr.queues[TopicId::Meas.index()].push_back(meas(k, 0.2));
            }
            for w in 3..=n {
                tr.on_wait.push((w, meas(w as u64 + 3, 0.2)));
            }
            tr.on_wait.push((n + 1, end(TopicId::Est, 1000)));
            tr.queues[TopicId::Iref.index()].push_back(iref0());
            let (host, allocations) = current_loop_counted(&sc, tr);
            let steps = host.stages[0].counters.fallback_steps;
            assert!(steps + 3 >= n as u64, "{n} wake-ups, {steps} on the clock");
            allocations
        };
        none_in_20_or_40_wake_ups(count);
    }

    /// The first-sample hook of a triggered host runs once, after the warm-up marker is
    /// forwarded and before the first step; an error from it ends the run there.
    #[test]
    fn a_triggered_hosts_first_sample_hook_runs_once_after_the_warm_up() {
        use std::sync::atomic::{AtomicUsize, Ordering};
        use std::sync::Arc;
        let sc = scenario();
        let script = || {
            let mut tr = Script::default();
            let warm = Msg::marker(
                TopicId::Est,
                Header {
                    k: 0,
                    flags: FLAG_WARMUP,
                    ..Default::default()
                },
            );
            tr.queues[TopicId::Est.index()].push_back(warm);
            tr.queues[TopicId::Est.index()].push_back(est(0, 7.0));
            for k in 0..3 {
                tr.queues[TopicId::Meas.index()].push_back(meas(k, 0.2));
            }
            tr.queues[TopicId::Iref.index()].push_back(iref0());
            for k in 1..3 {
                tr.on_wait.push((k as usize + 1, est(k, 7.0)));
            }
            tr.on_wait.push((4, end(TopicId::Est, 100)));
            tr
        };
        // Refused: the marker went out, no command did.
        let mut host = current_loop_host(&sc, script());
        host.at_first_sample(|| Err(anyhow!("refused at the first sample")));
        let e = host.run().unwrap_err();
        assert!(e.to_string().contains("refused at the first sample"), "{e}");
        let sent = &host.transport.sent;
        assert!(
            !sent.is_empty() && sent.iter().all(|m| m.hdr().is_warmup()),
            "the warm-up marker alone goes out before the hook: {sent:?}"
        );
        // Accepted: called once, every command made.
        let calls = Arc::new(AtomicUsize::new(0));
        let c = calls.clone();
        let mut host = current_loop_host(&sc, script());
        host.at_first_sample(move || {
            c.fetch_add(1, Ordering::SeqCst);
            Ok(())
        });
        host.run().unwrap();
        assert_eq!(calls.load(Ordering::SeqCst), 1);
        let made: Vec<u64> = host
            .transport
            .sent
            .iter()
            .filter(|m| !m.hdr().is_warmup() && !m.hdr().is_end())
            .map(|m| m.hdr().k)
            .collect();
        assert_eq!(made, [0, 1, 2]);
    }

    /// The source's first-sample hook runs before its first measurement goes out.
    #[test]
    fn the_sources_first_sample_hook_runs_before_its_first_output() {
        let sc = scenario();
        let mut host = plant_host(&sc, Script::default(), config(&sc));
        host.at_first_sample(|| Err(anyhow!("refused at the first sample")));
        let e = host.run().unwrap_err();
        assert!(e.to_string().contains("refused at the first sample"), "{e}");
        assert!(host.transport.sent.is_empty(), "{:?}", host.transport.sent);
    }

    /// The speed loop's reference of sample 0 is the one the current loop expects up to
    /// sample 9; when the speed loop's process goes down after command 2, commands 3 and 4
    /// are made from a stale reference (flagged) at once, not from sample 10 on.
    #[test]
    fn an_input_whose_producer_is_down_is_stale_at_once() {
        let sc = scenario();
        let mut tr = Script::default();
        tr.queues[TopicId::Est.index()].push_back(est(0, 7.0));
        for k in 0..6 {
            tr.queues[TopicId::Meas.index()].push_back(meas(k, 0.2));
        }
        tr.queues[TopicId::Iref.index()].push_back(iref0());
        // Estimate k comes at the (k+1)-th wait (the first steps on estimate 0).
        for k in 1..5 {
            tr.on_wait.push((k as usize + 1, est(k, 7.0)));
        }
        tr.on_wait.push((6, end(TopicId::Est, 100)));
        tr.down_from = Some((4, TopicId::Iref));
        let host = run_current_loop(&sc, tr);
        assert_eq!(
            commands(&host.transport.sent),
            vec![(0, false), (1, false), (2, false), (3, true), (4, true)]
        );
        assert_eq!(host.stages[0].counters.producer_down_samples, 2);
        // The reference it held is the one it had: only the flag says the speed loop is gone.
        let Some(Msg::Cmd(c)) = host.transport.sent.iter().rev().nth(1) else {
            panic!("no command 4")
        };
        assert_eq!((c.i_dq_ref, c.omega_ref), ([0.0, 0.5], 50.0));
    }

    #[test]
    fn a_trigger_that_stops_is_replaced_by_the_clock_after_max_age_samples() {
        let sc = scenario();
        let mut tr = Script::default();
        let est = |k: u64| {
            Msg::Est(Estimate {
                hdr: Header {
                    k,
                    t_sample_ns: 1_000_000 + k * 100_000,
                    ..Default::default()
                },
                theta_e: 0.1,
                omega_m: 7.0,
            })
        };
        // Estimates 0 and 1 come one wake-up apart, then the observer stops; the plant goes on
        // to sample 5 (its measurements are there). The 4th wake-up brings the end.
        tr.queues[TopicId::Est.index()].push_back(est(0));
        tr.on_wait.push((2, est(1)));
        for k in 0..6 {
            tr.queues[TopicId::Meas.index()].push_back(meas(k, 0.2));
        }
        tr.on_wait.push((4, end(TopicId::Est, 100)));
        // The speed loop's reference of sample 0, which commands 1 and 5 are due to use.
        tr.queues[TopicId::Iref.index()].push_back(Msg::Iref(CurrentRef {
            hdr: Header {
                k: 0,
                t_sample_ns: 1_000_000,
                ..Default::default()
            },
            omega_ref: 50.0,
            i_d_ref: 0.0,
            i_q_ref: 0.5,
        }));
        let host = run_current_loop(&sc, tr);
        let cmds: Vec<VoltageCommand> = host
            .transport
            .sent
            .iter()
            .filter_map(|m| match m {
                Msg::Cmd(c) if !c.hdr.is_end() => Some(*c),
                _ => None,
            })
            .collect();
        // 0 and 1 from their estimates; then, woken (3rd) without one, the newest measurement
        // is 5 ≥ 1 + EST_MAX_AGE: command 5 on the encoder angle, flagged.
        let ks: Vec<u64> = cmds.iter().map(|c| c.hdr.k).collect();
        assert_eq!(ks, vec![0, 1, 5], "{cmds:?}");
        assert_eq!(cmds[1].hdr.flags & FLAG_STALE_INPUT, 0);
        assert_ne!(cmds[2].hdr.flags & FLAG_STALE_INPUT, 0);
        let p = sc.motor_params().p();
        assert!((cmds[2].theta_hat - drivelab_control::motor::wrap_2pi(p * 0.2)).abs() < 1e-12);
        assert_eq!(host.stages[0].counters.fallback_steps, 1);
        // The END marker on the trigger is forwarded on the stage's output.
        assert!(host
            .transport
            .sent
            .last()
            .is_some_and(|m| m.topic() == TopicId::Cmd && m.hdr().is_end()));
    }
}
