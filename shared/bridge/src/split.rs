//! The drive split across two machines (docs/architecture.md, "The drive split across
//! machines"): each machine runs its processes of a split topology on a bus of its own, and
//! the two bridges carry the topics that cross between them.
//!
//! - [`SplitPlan`] says, from the topology, what this machine sends and takes: every topic
//!   a stage on the other machine reads, and the trace's parts (truth, cmd, wref), so that
//!   each machine's recorder writes the whole trace.
//! - A topic a remote stage waits for is sent as soon as it is published: a thread sleeps on
//!   its wake word like any receiver (the producer pays the wake-up it pays a local
//!   consumer) and puts each message at once, express, blocking on congestion: nothing is
//!   dropped, so a lockstep drive gives the same trace as in one process. The recorder's
//!   parts are polled every millisecond.
//! - Taken topics arrive on a Zenoh subscriber; a thread checks each frame ([`codec`]) and
//!   publishes the messages on the local bus, waking its receivers as their producer would
//!   (the decimated word at the multiples its slower stages step on), stamped with the
//!   instant it was published here (`t_pub_ns`). The bridge's process
//!   stands in for the remote producer; only topics the other machine produces are
//!   subscribed, so the network cannot publish anything else here.
//! - Each side declares a liveliness token once its stage hosts are ready and waits for the
//!   other's before its drive starts, so no sample is sent before the far side listens.
//!
//! Keys: `drivelab/<link>/split/<machine>/<topic>` for the data, with `<machine>` the
//! producer's, and `drivelab/<link>/split/<machine>/ready` for the tokens; `<link>` is the
//! bus id of the listening side.

use crate::codec::{self, Wire};
use anyhow::{anyhow, bail, Result};
use drivelab_runtime::bus::{self, DriveTopics, Topic, WakeKind, MAX_BUFFER};
use drivelab_runtime::messages::{
    CurrentRef, Estimate, Header, Measurement, PlantTruth, SpeedRef, VoltageCommand,
};
use drivelab_runtime::service::{decimation, TopologyPlan};
use drivelab_runtime::stage::{TopicId, N_TOPICS};
use iceoryx2::prelude::ZeroCopySend;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{mpsc, Arc};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};
use zenoh::handlers::{FifoChannel, FifoChannelHandler};
use zenoh::qos::{CongestionControl, Priority};
use zenoh::sample::Sample;
use zenoh::Wait;

/// The topics each machine's recorder needs for the trace.
const TRACE_PARTS: [TopicId; 3] = [TopicId::Truth, TopicId::Cmd, TopicId::Wref];
/// How long a sending thread sleeps on a wake word before it looks at the stop flag.
const WAIT_SLICE: Duration = Duration::from_millis(20);
/// Polling period of the topics no remote stage waits for.
const POLL: Duration = Duration::from_millis(1);
/// Frames a taken topic's subscriber buffers.
const SUB_FRAMES: usize = 65_536;

/// What one machine of a split drive sends and takes.
#[derive(Debug, Clone, PartialEq)]
pub struct SplitPlan {
    /// This machine.
    pub here: String,
    /// The other machine.
    pub there: String,
    /// Topics produced here that the other machine needs, with true when a stage there waits
    /// for them (sent at once) rather than only the recorder (polled).
    pub sends: Vec<(TopicId, bool)>,
    /// Topics produced there that this machine needs.
    pub takes: Vec<TopicId>,
    /// Per topic: its decimated receivers step every this many samples (0: none).
    pub decim: [u64; N_TOPICS],
}

impl SplitPlan {
    /// The plan of machine `here` in the resolved topology `plan`; a one-line error when the
    /// topology is not split or `here` is none of its machines.
    pub fn new(plan: &TopologyPlan, here: &str) -> Result<Self, String> {
        let machines = drivelab_runtime::topology::machines(&plan.processes);
        if machines.is_empty() {
            return Err(format!(
                "--machine {here}: the topology names no machines (give its processes `machine = \"...\"`)"
            ));
        }
        let Some(there) = machines.iter().find(|m| *m != here) else {
            unreachable!("a split topology has two machines");
        };
        if !machines.iter().any(|m| m == here) {
            return Err(format!(
                "--machine {here}: the topology's machines are {}",
                machines.join(", ")
            ));
        }
        let machine_of = |process: usize| plan.processes[process].machine.as_deref();
        let read_on = |t: TopicId, m: &str| {
            plan.stages.iter().any(|s| {
                s.inputs.iter().any(|i| i.topic == t)
                    && plan.process_of(&s.name).and_then(machine_of) == Some(m)
            })
        };
        let mut sends = Vec::new();
        let mut takes = Vec::new();
        for p in &plan.producers {
            let from = machine_of(p.process).unwrap_or_default();
            let to = if from == here { there.as_str() } else { here };
            let staged = read_on(p.topic, to);
            if !staged && !TRACE_PARTS.contains(&p.topic) {
                continue;
            }
            if from == here {
                sends.push((p.topic, staged));
            } else {
                takes.push(p.topic);
            }
        }
        Ok(Self {
            here: here.to_string(),
            there: there.clone(),
            sends,
            takes,
            decim: decimation(plan),
        })
    }
}

/// Key of topic `topic` produced on `machine` of link `link`.
pub fn data_key(link: &str, machine: &str, topic: TopicId) -> String {
    format!("drivelab/{link}/split/{machine}/{}", topic.name())
}

/// Key of `machine`'s readiness token on link `link`.
pub fn ready_key(link: &str, machine: &str) -> String {
    format!("drivelab/{link}/split/{machine}/ready")
}

/// Counters of the split link, per topic.
#[derive(Debug, Default)]
pub struct Counters {
    /// Messages sent to the other machine.
    pub sent: [AtomicU64; N_TOPICS],
    /// Messages taken from the other machine onto the bus.
    pub taken: [AtomicU64; N_TOPICS],
    /// Frames from the other machine refused by the codec.
    pub rejected: AtomicU64,
    /// Messages not sent because the other side would refuse them (NaN, ∞).
    pub implausible: AtomicU64,
}

impl Counters {
    /// As JSON for `summary.json → bridge.split`.
    pub fn to_json(&self, plan: &SplitPlan) -> serde_json::Value {
        let per = |a: &[AtomicU64; N_TOPICS], ts: &mut dyn Iterator<Item = TopicId>| {
            ts.map(|t| {
                (
                    t.name().to_string(),
                    a[t.index()].load(Ordering::Relaxed).into(),
                )
            })
            .collect::<serde_json::Map<_, _>>()
        };
        serde_json::json!({
            "here": plan.here,
            "there": plan.there,
            "sent": per(&self.sent, &mut plan.sends.iter().map(|s| s.0)),
            "taken": per(&self.taken, &mut plan.takes.iter().copied()),
            "rejected": self.rejected.load(Ordering::Relaxed),
            "implausible": self.implausible.load(Ordering::Relaxed),
        })
    }
}

/// A drive message that crosses a split link.
trait Data: Wire + ZeroCopySend + std::fmt::Debug {
    const TOPIC: TopicId;
    fn hdr(&self) -> &Header;
    fn hdr_mut(&mut self) -> &mut Header;
    fn topic(t: &DriveTopics) -> &Topic<Self>;
}

macro_rules! data {
    ($t:ty, $id:expr, $field:ident) => {
        impl Data for $t {
            const TOPIC: TopicId = $id;
            fn hdr(&self) -> &Header {
                &self.hdr
            }
            fn hdr_mut(&mut self) -> &mut Header {
                &mut self.hdr
            }
            fn topic(t: &DriveTopics) -> &Topic<Self> {
                &t.$field
            }
        }
    };
}

data!(Measurement, TopicId::Meas, meas);
data!(Estimate, TopicId::Est, est);
data!(CurrentRef, TopicId::Iref, iref);
data!(VoltageCommand, TopicId::Cmd, cmd);
data!(SpeedRef, TopicId::Wref, wref);
data!(PlantTruth, TopicId::Truth, truth);

/// Where the threads find the bus.
#[derive(Debug, Clone)]
struct BusRef {
    id: String,
    wake: WakeKind,
    publishers: usize,
}

impl BusRef {
    fn open(
        &self,
        name: &str,
    ) -> Result<(
        iceoryx2::node::Node<iceoryx2::prelude::ipc::Service>,
        DriveTopics,
    )> {
        let node = bus::node(&self.id, name)?;
        let topics = DriveTopics::open_for(&node, self.wake, &self.id, self.publishers)?;
        Ok((node, topics))
    }
}

/// What every thread of the link shares: the bus, the stop flag, the counters and the channel
/// on which it reports its set-up.
type LinkShared<'a> = (
    &'a BusRef,
    &'a Arc<AtomicBool>,
    &'a Arc<Counters>,
    &'a mpsc::Sender<Result<()>>,
);

/// Starts thread `name` running `body` on its own handles of `shared`.
fn spawn_link<F>(name: String, shared: LinkShared, body: F) -> Result<JoinHandle<Result<()>>>
where
    F: FnOnce(BusRef, Arc<AtomicBool>, Arc<Counters>, mpsc::Sender<Result<()>>) -> Result<()>
        + Send
        + 'static,
{
    let (b, s, c, r) = shared;
    let (b, s, c, r) = (b.clone(), s.clone(), c.clone(), r.clone());
    Ok(std::thread::Builder::new()
        .name(name)
        .spawn(move || body(b, s, c, r))?)
}

/// The running link: its threads and counters.
pub struct Split {
    plan: SplitPlan,
    link: String,
    stop: Arc<AtomicBool>,
    threads: Vec<JoinHandle<Result<()>>>,
    counters: Arc<Counters>,
    token: Option<zenoh::liveliness::LivelinessToken>,
    peer: Option<zenoh::pubsub::Subscriber<FifoChannelHandler<Sample>>>,
}

impl Split {
    /// Starts the sending and taking threads on bus `bus` for link `link`; returns once
    /// every bus port and Zenoh subscriber exists, so nothing published from then on is
    /// missed.
    pub fn start(
        session: &zenoh::Session,
        plan: SplitPlan,
        link: &str,
        bus_id: &str,
        wake: WakeKind,
        publishers: usize,
    ) -> Result<Self> {
        let stop = Arc::new(AtomicBool::new(false));
        let counters = Arc::new(Counters::default());
        let bus = BusRef {
            id: bus_id.to_string(),
            wake,
            publishers,
        };
        let mut threads = Vec::new();
        let (ready_tx, ready) = mpsc::channel::<Result<()>>();
        macro_rules! each {
            ($t:expr, $f:ident, $($arg:expr),*) => {
                match $t {
                    TopicId::Meas => $f::<Measurement>($($arg),*),
                    TopicId::Est => $f::<Estimate>($($arg),*),
                    TopicId::Iref => $f::<CurrentRef>($($arg),*),
                    TopicId::Cmd => $f::<VoltageCommand>($($arg),*),
                    TopicId::Wref => $f::<SpeedRef>($($arg),*),
                    TopicId::Truth => $f::<PlantTruth>($($arg),*),
                }
            };
        }
        for &(t, woken) in &plan.sends {
            let key = data_key(link, &plan.here, t);
            let publisher = session
                .declare_publisher(key)
                .congestion_control(CongestionControl::Block)
                .priority(if woken {
                    Priority::RealTime
                } else {
                    Priority::Data
                })
                .express(woken)
                .wait()
                .map_err(|e| anyhow!("zenoh publisher {}: {e}", t.name()))?;
            threads.push(spawn_link(
                format!("send-{}", t.name()),
                (&bus, &stop, &counters, &ready_tx),
                move |b, s, c, r| each!(t, send, publisher, b, woken, s, c, r),
            )?);
        }
        for &t in &plan.takes {
            let sub = session
                .declare_subscriber(data_key(link, &plan.there, t))
                .with(FifoChannel::new(SUB_FRAMES))
                .wait()
                .map_err(|e| anyhow!("zenoh subscriber {}: {e}", t.name()))?;
            let d = plan.decim[t.index()];
            threads.push(spawn_link(
                format!("take-{}", t.name()),
                (&bus, &stop, &counters, &ready_tx),
                move |b, s, c, r| each!(t, take, sub, b, d, s, c, r),
            )?);
        }
        drop(ready_tx);
        let mut split = Self {
            plan,
            link: link.to_string(),
            stop,
            threads,
            counters,
            token: None,
            peer: None,
        };
        for _ in 0..split.threads.len() {
            match ready.recv() {
                Ok(Ok(())) => {}
                Ok(Err(e)) => {
                    let _ = split.halt();
                    return Err(e);
                }
                Err(_) => {
                    let _ = split.halt();
                    bail!("a split-link thread ended during its set-up");
                }
            }
        }
        Ok(split)
    }

    /// Declares this machine ready (its stage hosts are) and starts watching for the other
    /// machine's declaration ([`Split::met`]).
    pub fn announce(&mut self, session: &zenoh::Session) -> Result<()> {
        self.token = Some(
            session
                .liveliness()
                .declare_token(ready_key(&self.link, &self.plan.here))
                .wait()
                .map_err(|e| anyhow!("zenoh liveliness token: {e}"))?,
        );
        self.peer = Some(
            session
                .liveliness()
                .declare_subscriber(ready_key(&self.link, &self.plan.there))
                .history(true)
                .wait()
                .map_err(|e| anyhow!("zenoh liveliness subscriber: {e}"))?,
        );
        Ok(())
    }

    /// True once the other machine has declared itself ready (after [`Split::announce`]);
    /// the error of a thread that failed.
    pub fn met(&mut self) -> Result<bool> {
        self.check()?;
        self.peer_saw(zenoh::sample::SampleKind::Put)
    }

    /// True once the other machine, after [`Split::met`], has withdrawn its declaration: its
    /// bridge ended or the network between them failed (Zenoh's lease, about 10 s by
    /// default, when nothing closes the connection). Told once.
    pub fn left(&mut self) -> Result<bool> {
        let gone = self.peer_saw(zenoh::sample::SampleKind::Delete)?;
        if gone {
            self.peer = None;
        }
        Ok(gone)
    }

    /// True when the other machine's token has changed as `kind` since the last look.
    fn peer_saw(&self, kind: zenoh::sample::SampleKind) -> Result<bool> {
        let Some(sub) = &self.peer else {
            return Ok(false);
        };
        while let Some(s) = sub
            .try_recv()
            .map_err(|e| anyhow!("zenoh liveliness: {e}"))?
        {
            if s.kind() == kind {
                return Ok(true);
            }
        }
        Ok(false)
    }

    /// The other machine.
    pub fn there(&self) -> &str {
        &self.plan.there
    }

    /// The first error of a thread that has ended, if any.
    pub fn check(&mut self) -> Result<()> {
        if let Some(i) = self.threads.iter().position(|h| h.is_finished()) {
            let h = self.threads.remove(i);
            match h.join() {
                Ok(Ok(())) => {}
                Ok(Err(e)) => return Err(e),
                Err(_) => bail!("a split-link thread panicked"),
            }
        }
        Ok(())
    }

    /// Sends what is left, lets go of the bus and returns the counters.
    pub fn finish(mut self) -> Result<serde_json::Value> {
        let r = self.halt();
        r.map(|_| self.counters.to_json(&self.plan))
    }

    fn halt(&mut self) -> Result<()> {
        self.stop.store(true, Ordering::SeqCst);
        let mut first = Ok(());
        for h in self.threads.drain(..) {
            let r = h
                .join()
                .unwrap_or_else(|_| Err(anyhow!("a split-link thread panicked")));
            if first.is_ok() {
                first = r;
            }
        }
        // Only then is this machine gone for the other: its sending threads have sent what
        // was left, which the other side would otherwise wait for no longer.
        self.token = None;
        first
    }
}

impl Drop for Split {
    fn drop(&mut self) {
        let _ = self.halt();
    }
}

/// Tells [`Split::start`] how a thread's set-up went; its ports, if it succeeded.
fn report<V>(
    set_up: Result<V>,
    ready: &mpsc::Sender<Result<()>>,
    what: &str,
    topic: &str,
) -> Option<V> {
    let (answer, ports) = match set_up {
        Ok(v) => (Ok(()), Some(v)),
        Err(e) => (Err(anyhow!("split link, {what} {topic}: {e:#}")), None),
    };
    let _ = ready.send(answer);
    ports
}

/// Sends topic `T` of the bus to the other machine until stopped, then what is left.
fn send<T: Data>(
    publisher: zenoh::pubsub::Publisher<'static>,
    bus: BusRef,
    woken: bool,
    stop: Arc<AtomicBool>,
    counters: Arc<Counters>,
    ready: mpsc::Sender<Result<()>>,
) -> Result<()> {
    let set_up = (|| -> Result<_> {
        let (node, topics) = bus.open(&format!("zenoh-send-{}", T::TOPIC.name()))?;
        let t = T::topic(&topics);
        let rx = if woken {
            t.receiver(MAX_BUFFER)?
        } else {
            t.polled_receiver(MAX_BUFFER)?
        };
        rx.connect()?;
        Ok((node, topics, rx))
    })();
    let Some((_node, _topics, rx)) = report(set_up, &ready, "sending", T::NAME) else {
        return Ok(());
    };
    let mut batch: Vec<T> = Vec::with_capacity(codec::MAX_COUNT);
    let mut buf = Vec::new();
    loop {
        // The stop flag is read before the last drain: what was published before it is sent.
        let stopping = stop.load(Ordering::SeqCst);
        batch.clear();
        while batch.len() < codec::MAX_COUNT {
            match rx.try_recv()? {
                Some(m) if m.plausible() => batch.push(m),
                Some(_) => {
                    counters.implausible.fetch_add(1, Ordering::Relaxed);
                }
                None => break,
            }
        }
        if !batch.is_empty() {
            codec::encode_into(&batch, &mut buf);
            publisher
                .put(buf.clone())
                .wait()
                .map_err(|e| anyhow!("zenoh put {}: {e}", T::NAME))?;
            counters.sent[T::TOPIC.index()].fetch_add(batch.len() as u64, Ordering::Relaxed);
            continue;
        }
        if stopping {
            return Ok(());
        }
        if woken {
            rx.wait(WAIT_SLICE)?;
        } else {
            std::thread::sleep(POLL);
        }
    }
}

/// How long a receiving thread that was told to stop still publishes what its queue holds.
const DRAIN_LIMIT: Duration = Duration::from_millis(200);

/// Publishes topic `T` from the other machine on the bus until stopped.
fn take<T: Data>(
    sub: zenoh::pubsub::Subscriber<FifoChannelHandler<Sample>>,
    bus: BusRef,
    decim: u64,
    stop: Arc<AtomicBool>,
    counters: Arc<Counters>,
    ready: mpsc::Sender<Result<()>>,
) -> Result<()> {
    let set_up = (|| -> Result<_> {
        let (node, topics) = bus.open(&format!("zenoh-take-{}", T::TOPIC.name()))?;
        let tx = T::topic(&topics).sender()?;
        tx.connect()?;
        Ok((node, topics, tx))
    })();
    let Some((_node, _topics, tx)) = report(set_up, &ready, "taking", T::NAME) else {
        return Ok(());
    };
    let mut msgs: Vec<T> = Vec::with_capacity(codec::MAX_COUNT);
    let mut put_on_bus = |sample: Sample| -> Result<()> {
        if codec::decode_into::<T>(&sample.payload().to_bytes(), &mut msgs).is_err() {
            counters.rejected.fetch_add(1, Ordering::Relaxed);
            return Ok(());
        }
        for m in msgs.iter_mut() {
            // Published here now: the message is available on this machine from this
            // instant, so the plant's cycle latency includes the way back over the network
            // and is measured on one clock (this machine's).
            m.hdr_mut().t_pub_ns = drivelab_runtime::rt::now_ns();
            let h = m.hdr();
            // As the producer wakes them (see `BusTransport`): the decimated receivers at the
            // samples they step and at every marker.
            let decimated = decim > 0 && (h.k.is_multiple_of(decim) || h.is_end() || h.is_warmup());
            tx.send_waking(*m, decimated)?;
        }
        counters.taken[T::TOPIC.index()].fetch_add(msgs.len() as u64, Ordering::Relaxed);
        Ok(())
    };
    while !stop.load(Ordering::SeqCst) {
        if let Some(sample) = sub
            .recv_timeout(WAIT_SLICE)
            .map_err(|e| anyhow!("zenoh receive {}: {e}", T::NAME))?
        {
            put_on_bus(sample)?;
        }
    }
    // What arrived before the stop is still published (and counted), as the sending threads
    // send what was published before it; for at most DRAIN_LIMIT, against a peer that
    // keeps sending.
    let until = Instant::now() + DRAIN_LIMIT;
    while Instant::now() < until {
        match sub
            .try_recv()
            .map_err(|e| anyhow!("zenoh receive {}: {e}", T::NAME))?
        {
            Some(sample) => put_on_bus(sample)?,
            None => break,
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use drivelab_runtime::config::Scenario;

    fn plan(machines: &[(&str, &str)]) -> TopologyPlan {
        let text = std::fs::read_to_string(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../../scenarios/kyslan-pi.toml"
        ))
        .unwrap();
        let sc = Scenario::from_toml(&text, "kyslan-pi.toml").unwrap();
        let mut procs = sc.topology();
        for p in procs.iter_mut() {
            p.machine = machines
                .iter()
                .find(|(n, _)| *n == p.name)
                .map(|(_, m)| m.to_string());
        }
        let r = drivelab_runtime::topology::resolve(&procs, &mut |_, s| {
            drivelab_runtime::topology::builtin_info(&sc, s).ok_or_else(|| s.to_string())
        })
        .unwrap();
        TopologyPlan::from_resolved(&r)
    }

    #[test]
    fn each_machine_sends_what_the_other_reads_and_the_trace_parts() {
        let p = plan(&[
            ("plant", "bench"),
            ("observer", "board"),
            ("current-loop", "board"),
            ("speed-loop", "board"),
        ]);
        let bench = SplitPlan::new(&p, "bench").unwrap();
        assert_eq!(bench.there, "board");
        // The observer and both loops read the measurement; the recorder there needs truth.
        assert_eq!(
            bench.sends,
            [(TopicId::Meas, true), (TopicId::Truth, false)]
        );
        // The plant reads the command; est and iref stay on the board.
        assert_eq!(bench.takes, [TopicId::Cmd]);
        let board = SplitPlan::new(&p, "board").unwrap();
        assert_eq!(board.sends, [(TopicId::Cmd, true)]);
        assert_eq!(board.takes, [TopicId::Meas, TopicId::Truth]);
        assert_eq!(
            SplitPlan::new(&p, "desk").unwrap_err(),
            "--machine desk: the topology's machines are bench, board"
        );
        assert!(SplitPlan::new(&plan(&[]), "bench")
            .unwrap_err()
            .contains("the topology names no machines"));
    }

    #[test]
    fn an_observer_beside_the_plant_sends_its_estimate_across() {
        let p = plan(&[
            ("plant", "bench"),
            ("observer", "bench"),
            ("current-loop", "board"),
            ("speed-loop", "board"),
        ]);
        let bench = SplitPlan::new(&p, "bench").unwrap();
        assert!(bench.sends.contains(&(TopicId::Est, true)));
        assert!(bench.sends.contains(&(TopicId::Meas, true)));
        // The speed loop (1 kHz) steps on every tenth estimate: woken at those only.
        assert_eq!(bench.decim[TopicId::Est.index()], 10);
    }
}
