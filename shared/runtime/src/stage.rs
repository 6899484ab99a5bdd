//! The stage API: what a computation of the drive is, apart from where and when it runs.
//!
//! A stage declares its inputs (a topic, the role of each: the [`Role::Trigger`] that wakes it
//! or a [`Role::Latest`] value it reads, a delay of 0 or 1 sample, a freshness limit in
//! samples and what happens when the input is stale), its outputs and its rate divider. Its
//! [`Stage::step`] turns the inputs of sample k into outputs and does no I/O. A host
//! (`crate::host`) runs one or more stages per process in chain order over a transport, and
//! does the rest: waiting, freshness, catch-up, warm-up, end forwarding, rejoin, histograms.
//! See docs/architecture.md, "Stages and topologies".
//!
//! Messages are the fixed-size `#[repr(C)]` types of [`crate::messages`]; [`Msg`] carries
//! any of them, keyed by [`TopicId`].

use crate::messages::*;
use serde::{Deserialize, Serialize};

/// The topics of a drive. Every topic has exactly one producing stage in a topology.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum TopicId {
    /// Plant → controllers: [`Measurement`] k.
    Meas,
    /// Observer → controllers: [`Estimate`] k.
    Est,
    /// Speed loop → current loop: [`CurrentRef`] computed at k.
    Iref,
    /// Current loop → plant: [`VoltageCommand`] k.
    Cmd,
    /// Outer loop → speed loop: [`SpeedRef`] computed at k (a position loop's ω*).
    Wref,
    /// Plant → recorder: [`PlantTruth`] k (the true state, for the trace only).
    Truth,
}

/// Number of topics.
pub const N_TOPICS: usize = 6;

impl TopicId {
    /// Every topic, in index order.
    pub const ALL: [TopicId; N_TOPICS] = [
        TopicId::Meas,
        TopicId::Est,
        TopicId::Iref,
        TopicId::Cmd,
        TopicId::Wref,
        TopicId::Truth,
    ];

    /// Index into per-topic arrays.
    pub const fn index(self) -> usize {
        self as usize
    }

    /// Short name, as in topology files and error messages.
    pub const fn name(self) -> &'static str {
        match self {
            TopicId::Meas => "meas",
            TopicId::Est => "est",
            TopicId::Iref => "iref",
            TopicId::Cmd => "cmd",
            TopicId::Wref => "wref",
            TopicId::Truth => "truth",
        }
    }
}

/// A message on any topic.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Msg {
    /// On [`TopicId::Meas`].
    Meas(Measurement),
    /// On [`TopicId::Est`].
    Est(Estimate),
    /// On [`TopicId::Iref`].
    Iref(CurrentRef),
    /// On [`TopicId::Cmd`].
    Cmd(VoltageCommand),
    /// On [`TopicId::Wref`].
    Wref(SpeedRef),
    /// On [`TopicId::Truth`].
    Truth(PlantTruth),
}

impl Msg {
    /// The topic this message travels on.
    pub fn topic(&self) -> TopicId {
        match self {
            Msg::Meas(_) => TopicId::Meas,
            Msg::Est(_) => TopicId::Est,
            Msg::Iref(_) => TopicId::Iref,
            Msg::Cmd(_) => TopicId::Cmd,
            Msg::Wref(_) => TopicId::Wref,
            Msg::Truth(_) => TopicId::Truth,
        }
    }

    /// The header.
    pub fn hdr(&self) -> &Header {
        match self {
            Msg::Meas(m) => &m.hdr,
            Msg::Est(m) => &m.hdr,
            Msg::Iref(m) => &m.hdr,
            Msg::Cmd(m) => &m.hdr,
            Msg::Wref(m) => &m.hdr,
            Msg::Truth(m) => &m.hdr,
        }
    }

    /// The header, mutable.
    pub fn hdr_mut(&mut self) -> &mut Header {
        match self {
            Msg::Meas(m) => &mut m.hdr,
            Msg::Est(m) => &mut m.hdr,
            Msg::Iref(m) => &mut m.hdr,
            Msg::Cmd(m) => &mut m.hdr,
            Msg::Wref(m) => &mut m.hdr,
            Msg::Truth(m) => &mut m.hdr,
        }
    }

    /// True when every floating-point field is finite.
    pub fn is_finite(&self) -> bool {
        match self {
            Msg::Meas(m) => m.is_finite(),
            Msg::Est(m) => m.is_finite(),
            Msg::Iref(m) => m.is_finite(),
            Msg::Cmd(m) => m.is_finite(),
            Msg::Wref(m) => m.is_finite(),
            Msg::Truth(m) => m.is_finite(),
        }
    }

    /// A message of `topic` that carries only header `hdr` (warm-up and end markers).
    pub fn marker(topic: TopicId, hdr: Header) -> Msg {
        match topic {
            TopicId::Meas => Msg::Meas(Measurement {
                hdr,
                ..Default::default()
            }),
            TopicId::Est => Msg::Est(Estimate {
                hdr,
                ..Default::default()
            }),
            TopicId::Iref => Msg::Iref(CurrentRef {
                hdr,
                ..Default::default()
            }),
            TopicId::Cmd => Msg::Cmd(VoltageCommand {
                hdr,
                ..Default::default()
            }),
            TopicId::Wref => Msg::Wref(SpeedRef {
                hdr,
                ..Default::default()
            }),
            TopicId::Truth => Msg::Truth(PlantTruth {
                hdr,
                ..Default::default()
            }),
        }
    }
}

/// How a stage receives an input.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Role {
    /// The input whose arrival runs the stage (one per stage; the source stage has none: the
    /// clock runs it).
    Trigger,
    /// The newest value is read when the stage runs; it never wakes the stage.
    Latest,
    /// Read only while the stage rejoins a running drive (e.g. the newest value of a topic
    /// that the stage's own output influenced).
    Rejoin,
}

/// What a stale input means.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum OnStale {
    /// The stage still runs; [`Stage::step`] sees the input as stale and applies its own
    /// fallback (hold, safe state, another sensor). For a trigger: the host runs the stage
    /// without it once the drive has moved `max_age` samples past it.
    Fallback,
    /// The stage needs the input: without it the stage does not run for that sample.
    Required,
}

/// One declared input of a stage.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct InputSpec {
    /// The topic.
    pub topic: TopicId,
    /// Trigger, latest value or rejoin-only.
    pub role: Role,
    /// 0: the input of the same sample k; 1: the newest one computed before k (the one-sample
    /// computation delay that breaks a loop in the data graph).
    pub delay: u64,
    /// Samples after which the input counts as stale (real time; lockstep always waits).
    pub max_age: u64,
    /// What a stale input means.
    pub on_stale: OnStale,
}

impl InputSpec {
    /// The trigger of the same sample.
    pub const fn trigger(topic: TopicId, max_age: u64, on_stale: OnStale) -> Self {
        Self {
            topic,
            role: Role::Trigger,
            delay: 0,
            max_age,
            on_stale,
        }
    }

    /// A latest value of the same sample (delay 0) or of the previous one (delay 1).
    pub const fn latest(topic: TopicId, delay: u64, max_age: u64, on_stale: OnStale) -> Self {
        Self {
            topic,
            role: Role::Latest,
            delay,
            max_age,
            on_stale,
        }
    }

    /// A value read only while rejoining.
    pub const fn rejoin(topic: TopicId) -> Self {
        Self {
            topic,
            role: Role::Rejoin,
            delay: 1,
            max_age: u64::MAX,
            on_stale: OnStale::Fallback,
        }
    }
}

/// The newest value of one input as the host hands it to a stage.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Slot {
    /// The newest value received (also when stale), if any ever came.
    pub msg: Option<Msg>,
    /// True when `msg` is the one this sample expects (index and rate match).
    pub fresh: bool,
    /// Samples since the expected index when stale (0 when fresh, and when the expected
    /// message came but its producer is down).
    pub age: u64,
    /// The process that produces it is down (real time; docs/architecture.md, "Liveness
    /// words and standby twins").
    pub producer_down: bool,
}

/// The inputs of one step, by topic.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Inbox {
    /// Per topic, see [`TopicId::index`].
    pub slots: [Slot; N_TOPICS],
}

macro_rules! typed_access {
    ($fresh:ident, $newest:ident, $variant:ident, $ty:ty) => {
        /// The input of this topic when it is fresh.
        pub fn $fresh(&self) -> Option<&$ty> {
            let s = &self.slots[TopicId::$variant.index()];
            match (&s.msg, s.fresh) {
                (Some(Msg::$variant(m)), true) => Some(m),
                _ => None,
            }
        }

        /// The newest input of this topic received so far, fresh or not.
        pub fn $newest(&self) -> Option<&$ty> {
            match &self.slots[TopicId::$variant.index()].msg {
                Some(Msg::$variant(m)) => Some(m),
                _ => None,
            }
        }
    };
}

impl Inbox {
    typed_access!(meas, newest_meas, Meas, Measurement);
    typed_access!(est, newest_est, Est, Estimate);
    typed_access!(iref, newest_iref, Iref, CurrentRef);
    typed_access!(cmd, newest_cmd, Cmd, VoltageCommand);
    typed_access!(wref, newest_wref, Wref, SpeedRef);
    typed_access!(truth, newest_truth, Truth, PlantTruth);

    /// The slot of `topic`.
    pub fn slot(&self, topic: TopicId) -> &Slot {
        &self.slots[topic.index()]
    }

    /// True when the process producing one of these inputs is down.
    pub fn producer_down(&self) -> bool {
        self.slots.iter().any(|s| s.producer_down)
    }

    /// Sets `msg` as the fresh input of its topic (tests and the in-process host).
    pub fn put(&mut self, msg: Msg) {
        self.slots[msg.topic().index()] = Slot {
            msg: Some(msg),
            fresh: true,
            ..Slot::default()
        };
    }

    /// Marks the input of `topic` stale by `age` samples (it keeps its newest value).
    pub fn set_stale(&mut self, topic: TopicId, age: u64) {
        let s = &mut self.slots[topic.index()];
        s.fresh = false;
        s.age = age;
    }
}

/// The outputs of one step (at most one message per topic).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Outbox {
    /// Per topic, see [`TopicId::index`].
    pub msgs: [Option<Msg>; N_TOPICS],
}

impl Outbox {
    /// Publishes `msg` on its topic.
    pub fn push(&mut self, msg: Msg) {
        self.msgs[msg.topic().index()] = Some(msg);
    }

    /// The output on `topic`, if any.
    pub fn get(&self, topic: TopicId) -> Option<&Msg> {
        self.msgs[topic.index()].as_ref()
    }

    /// Takes every output, in topic order.
    pub fn drain(&mut self) -> impl Iterator<Item = Msg> + '_ {
        self.msgs.iter_mut().filter_map(Option::take)
    }
}

/// A stage's diagnostics: plain named counters, printed by the host at exit and written to
/// the statistics file. Nothing law-specific is printed by the host itself.
pub type Diagnostics = &'static [&'static str];

/// What a stage's rejoin attempt needs next.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Rejoin {
    /// Taken over: from now on the host calls [`Stage::step`]. The step of this same sample
    /// still runs.
    Done,
    /// Needs another sample (e.g. a second measurement for a speed).
    NeedMore,
}

/// One computation of the drive. Only [`Stage::step`] runs on the real-time path; it must
/// not allocate, lock, log or make a syscall.
pub trait Stage {
    /// The stage's name (unique in a topology; used in faults, statistics and the monitor).
    fn name(&self) -> &'static str;

    /// Declared inputs. At most one has [`Role::Trigger`]; a stage without one is the source
    /// (the timing master) and runs on the clock.
    fn inputs(&self) -> &'static [InputSpec];

    /// Topics this stage publishes.
    fn outputs(&self) -> &'static [TopicId];

    /// The stage runs at samples k with k mod divider = 0.
    fn divider(&self) -> u64 {
        1
    }

    /// True when, having fallen behind in real time, the stage must still see every older
    /// trigger (a filter whose state needs every sample) rather than only the newest.
    fn steps_every_sample(&self) -> bool {
        false
    }

    /// Sample k: inputs → outputs. Pure: no I/O. A stale input is marked in its slot; the
    /// stage applies its own fallback.
    fn step(&mut self, k: u64, inputs: &Inbox, out: &mut Outbox);

    /// Work after the outputs have left (the plant integrates to t_{k+1} here).
    fn after_publish(&mut self) {}

    /// Takes over a running drive after a restart, from the newest inputs (and, for the
    /// source, its own last output as the recorder saw it, in the slot of its output topic).
    fn rejoin(&mut self, _k: u64, _inputs: &Inbox) -> Rejoin {
        Rejoin::Done
    }

    /// Names of the counters that [`Stage::diagnostics`] fills.
    fn diagnostic_names(&self) -> Diagnostics {
        &[]
    }

    /// The counters' values, in the order of [`Stage::diagnostic_names`].
    fn diagnostics(&self, _values: &mut [u64]) {}

    /// Warnings about the stage's configuration, printed once by the host before it runs.
    fn warnings(&self) -> Vec<String> {
        Vec::new()
    }

    /// Warnings about what happened during the run, printed once by the host at the end.
    fn exit_warnings(&self) -> Vec<String> {
        Vec::new()
    }
}

/// The input of `stage` with role trigger, if any.
pub fn trigger_of(stage: &dyn Stage) -> Option<InputSpec> {
    stage
        .inputs()
        .iter()
        .copied()
        .find(|i| i.role == Role::Trigger)
}

/// The index of the input a stage expects at sample k from a producer that runs every
/// `producer_divider` samples, with `delay` (0 or 1): the newest multiple of the divider
/// that is ≤ k − delay. None when there is none yet (k < delay).
pub fn expected_index(k: u64, delay: u64, producer_divider: u64) -> Option<u64> {
    let d = producer_divider.max(1);
    k.checked_sub(delay).map(|j| j / d * d)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn expected_index_follows_rate_and_delay() {
        // The current loop at k uses the reference of the last speed sample strictly before k.
        assert_eq!(expected_index(0, 1, 10), None);
        assert_eq!(expected_index(1, 1, 10), Some(0));
        assert_eq!(expected_index(10, 1, 10), Some(0));
        assert_eq!(expected_index(11, 1, 10), Some(10));
        // The plant at k uses command k − 1; the current loop at k uses estimate k.
        assert_eq!(expected_index(7, 1, 1), Some(6));
        assert_eq!(expected_index(7, 0, 1), Some(7));
    }

    #[test]
    fn inbox_gives_fresh_values_only_when_fresh() {
        let mut ib = Inbox::default();
        let e = Estimate {
            hdr: Header {
                k: 4,
                ..Default::default()
            },
            theta_e: 1.0,
            omega_m: 2.0,
        };
        ib.put(Msg::Est(e));
        assert_eq!(ib.est(), Some(&e));
        ib.set_stale(TopicId::Est, 3);
        assert_eq!(ib.est(), None);
        assert_eq!(ib.newest_est(), Some(&e));
        assert_eq!(ib.slot(TopicId::Est).age, 3);
        assert_eq!(ib.meas(), None);
    }

    #[test]
    fn outbox_keeps_one_message_per_topic() {
        let mut o = Outbox::default();
        let mut c = VoltageCommand::default();
        o.push(Msg::Cmd(c));
        c.hdr.k = 9;
        o.push(Msg::Cmd(c));
        let all: Vec<Msg> = o.drain().collect();
        assert_eq!(all, vec![Msg::Cmd(c)]);
        assert!(o.get(TopicId::Cmd).is_none());
    }
}
