//! Live telemetry for `drivelab monitor`, kept off the real-time path's connections.
//!
//! Every service publishes a [`ServiceStatus`] ten times per simulated second on
//! [`TOPIC_STATUS`]. Its only subscriber is the supervisor in `drivelab run`, which exists
//! before the services start, so no connection is ever set up inside a real-time loop. The
//! supervisor aggregates the statuses, its own view of the processes and a decimated trace
//! into a [`DriveView`] on [`TOPIC_VIEW`], and its event log into [`EventEntry`]s on
//! [`TOPIC_EVENTS`]. A monitor subscribes to those two (published by a non-real-time thread)
//! and asks for faults on [`TOPIC_FAULT_REQ`]; attaching or detaching a monitor therefore
//! never touches a real-time process.
//!
//! The status histograms are [`CompactHist`]s: 4 logarithmic buckets per octave (a bucket
//! spans at most 19 % of its value), fixed size, so that recording is a few instructions and
//! the message is a plain copy.

use crate::messages::Header;
use anyhow::{anyhow, Result};
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::*;

/// Services → supervisor: one [`ServiceStatus`] per service ten times per simulated second.
pub const TOPIC_STATUS: &str = "drivelab/status";
/// Supervisor → monitors: the aggregated [`DriveView`], about ten times per wall second.
pub const TOPIC_VIEW: &str = "drivelab/view";
/// Supervisor → monitors: the event log, one [`EventEntry`] per event.
pub const TOPIC_EVENTS: &str = "drivelab/events";
/// Monitors → supervisor: fault requests ([`FaultRequest`]).
pub const TOPIC_FAULT_REQ: &str = "drivelab/fault-request";

/// Buckets of a [`CompactHist`].
pub const BUCKETS: usize = 112;
const SUB_BITS: u32 = 2;
const SUB: u32 = 1 << SUB_BITS;
/// Values below 2^MIN_OCTAVE ns share bucket 0.
const MIN_OCTAVE: u32 = 6;

/// Bucket of a value in ns.
#[inline]
pub fn bucket(v: u64) -> usize {
    if v < (1 << MIN_OCTAVE) {
        return 0;
    }
    let e = 63 - v.leading_zeros();
    let sub = ((v >> (e - SUB_BITS)) as u32) & (SUB - 1);
    ((1 + (e - MIN_OCTAVE) * SUB + sub) as usize).min(BUCKETS - 1)
}

/// Exclusive upper edge of bucket `b`, ns.
pub fn bucket_upper_ns(b: usize) -> u64 {
    if b == 0 {
        return 1 << MIN_OCTAVE;
    }
    let i = (b - 1) as u32;
    let e = MIN_OCTAVE + i / SUB;
    let sub = u64::from(i % SUB);
    (1u64 << e) + ((sub + 1) << (e - SUB_BITS))
}

/// A fixed-size logarithmic histogram of ns values with an exact maximum.
#[derive(Debug, Clone, Copy, PartialEq, ZeroCopySend)]
#[repr(C)]
pub struct CompactHist {
    /// Values recorded.
    pub count: u64,
    /// Largest value, ns.
    pub max_ns: u64,
    /// Counts per bucket (see [`bucket`]).
    pub counts: [u32; BUCKETS],
}

impl Default for CompactHist {
    fn default() -> Self {
        Self {
            count: 0,
            max_ns: 0,
            counts: [0; BUCKETS],
        }
    }
}

impl CompactHist {
    /// Records one value in ns (negative values as 0). No allocation, no branch on the data
    /// beyond the bucket computation.
    #[inline]
    pub fn record_ns(&mut self, v: i64) {
        let v = v.max(0) as u64;
        self.count += 1;
        self.max_ns = self.max_ns.max(v);
        let b = bucket(v);
        self.counts[b] = self.counts[b].saturating_add(1);
    }

    /// Adds `other`'s values to these.
    pub fn add(&mut self, other: &CompactHist) {
        self.count += other.count;
        self.max_ns = self.max_ns.max(other.max_ns);
        for (a, b) in self.counts.iter_mut().zip(other.counts.iter()) {
            *a = a.saturating_add(*b);
        }
    }

    /// Upper bound of quantile `q` (0..1), ns: the upper edge of the bucket holding it,
    /// never above the maximum. 0 when empty.
    pub fn quantile_ns(&self, q: f64) -> u64 {
        if self.count == 0 {
            return 0;
        }
        let want = ((q.clamp(0.0, 1.0) * self.count as f64).ceil() as u64).max(1);
        let mut seen = 0u64;
        for (b, &c) in self.counts.iter().enumerate() {
            seen += u64::from(c);
            if seen >= want {
                return bucket_upper_ns(b).min(self.max_ns);
            }
        }
        self.max_ns
    }
}

/// Service → supervisor: counters and histograms since the service started.
#[derive(Debug, Clone, Copy, PartialEq, Default, ZeroCopySend)]
#[repr(C)]
pub struct ServiceStatus {
    /// `k`: newest sample handled; `t_pub_ns`: when this status was published.
    pub hdr: Header,
    /// Index of the stage in the drive's topology (the order of `topology.json`).
    pub service: u32,
    /// Process id.
    pub pid: u32,
    /// Samples processed.
    pub samples: u64,
    /// Deadline misses: for the plant, samples that used a held or safe command; for the
    /// controllers, outputs published after the end of their sample period (real time only).
    pub misses: u64,
    /// Longest run of consecutive misses.
    pub longest_miss_run: u64,
    /// Inputs that were not there when needed.
    pub stale_inputs: u64,
    /// Inputs rejected (NaN/∞, index going backwards).
    pub rejected_inputs: u64,
    /// Inputs skipped to catch up.
    pub skipped: u64,
    /// Plant: release lateness; controllers: bus hop (wake − input published).
    pub wake: CompactHist,
    /// Execution time of the step.
    pub exec: CompactHist,
    /// Plant only: cycle latency (t_k → command k available).
    pub cycle: CompactHist,
}

/// Process state as the supervisor sees it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[repr(u32)]
pub enum ProcState {
    /// Spawned, not ready yet.
    Starting = 0,
    /// Running.
    Alive = 1,
    /// Frozen by a stop fault (SIGSTOP).
    Frozen = 2,
    /// Dead, not (yet) restarted.
    Dead = 3,
    /// Dead and waiting for its restart, or restarted and not ready yet.
    Restarting = 4,
    /// Exited normally at the end of the run.
    Finished = 5,
}

impl ProcState {
    /// From the wire value.
    pub fn from_u32(v: u32) -> Self {
        match v {
            1 => Self::Alive,
            2 => Self::Frozen,
            3 => Self::Dead,
            4 => Self::Restarting,
            5 => Self::Finished,
            _ => Self::Starting,
        }
    }

    /// Display name.
    pub fn name(self) -> &'static str {
        match self {
            Self::Starting => "starting",
            Self::Alive => "alive",
            Self::Frozen => "frozen",
            Self::Dead => "dead",
            Self::Restarting => "restarting",
            Self::Finished => "finished",
        }
    }
}

/// One service in the [`DriveView`].
#[derive(Debug, Clone, Copy, PartialEq, Default, ZeroCopySend)]
#[repr(C)]
pub struct ServiceView {
    /// The newest status the service published (all zero before the first).
    pub status: ServiceStatus,
    /// [`ProcState`] as u32.
    pub state: u32,
    /// Process id of the current instance.
    pub pid: u32,
    /// Restarts so far.
    pub restarts: u32,
    /// 1 once a status has arrived.
    pub has_status: u32,
    /// Samples per wall second over the last two statuses.
    pub rate_hz: f64,
}

/// One decimated trace point.
#[derive(Debug, Clone, Copy, PartialEq, Default, ZeroCopySend)]
#[repr(C)]
pub struct TracePoint {
    /// Sample index.
    pub k: u64,
    /// Speed, mechanical rad/s.
    pub omega: f64,
    /// Speed reference, rad/s (from the newest command).
    pub omega_ref: f64,
    /// d-axis current, A.
    pub i_d: f64,
    /// q-axis current, A.
    pub i_q: f64,
    /// d-axis current reference, A.
    pub i_d_ref: f64,
    /// q-axis current reference, A.
    pub i_q_ref: f64,
}

/// Trace points in a [`DriveView`].
pub const VIEW_POINTS: usize = 256;
/// Length of the scenario name field.
pub const NAME_LEN: usize = 48;
/// Stages a [`DriveView`] can show.
pub const MAX_STAGES: usize = 8;
/// Length of a stage name field.
pub const STAGE_NAME_LEN: usize = 32;

/// Supervisor → monitors: everything a monitor draws.
#[derive(Debug, Clone, Copy, PartialEq, ZeroCopySend)]
#[repr(C)]
pub struct DriveView {
    /// `k`: drive progress (newest measurement + 1); flags: `FLAG_END` on the last view.
    pub hdr: Header,
    /// Sample rate, Hz.
    pub sample_hz: f64,
    /// Samples in the run.
    pub n_samples: u64,
    /// 1 in lockstep, 0 in real time.
    pub lockstep: u32,
    /// Valid entries of `points`, oldest first.
    pub n_points: u32,
    /// Samples between trace points.
    pub decimation: u64,
    /// Cores the scenario pins real-time services to (bit i = CPU i); a monitor keeps off
    /// them.
    pub rt_cores: u64,
    /// Scenario name, NUL-padded UTF-8.
    pub scenario: [u8; NAME_LEN],
    /// Valid entries of `stage_names` and `services`.
    pub n_stages: u32,
    /// Padding made explicit (zero): the view has no hidden bytes, so the Zenoh bridge can
    /// send it as it is in memory.
    pub reserved: u32,
    /// Stage names in the topology's order (process, then chain), NUL-padded UTF-8.
    pub stage_names: [[u8; STAGE_NAME_LEN]; MAX_STAGES],
    /// Per stage, in `stage_names` order.
    pub services: [ServiceView; MAX_STAGES],
    /// Decimated trace, oldest first.
    pub points: [TracePoint; VIEW_POINTS],
}

impl DriveView {
    /// Name of stage `i`.
    pub fn stage_name(&self, i: usize) -> &str {
        self.stage_names.get(i).map_or("?", |n| get_str(n))
    }

    /// Number of stages shown.
    pub fn stages(&self) -> usize {
        (self.n_stages as usize).min(MAX_STAGES)
    }
}

impl Default for DriveView {
    fn default() -> Self {
        Self {
            hdr: Header::default(),
            sample_hz: 0.0,
            n_samples: 0,
            lockstep: 0,
            n_points: 0,
            decimation: 1,
            rt_cores: 0,
            scenario: [0; NAME_LEN],
            n_stages: 0,
            reserved: 0,
            stage_names: [[0; STAGE_NAME_LEN]; MAX_STAGES],
            services: [ServiceView::default(); MAX_STAGES],
            points: [TracePoint::default(); VIEW_POINTS],
        }
    }
}

/// Length of an event's text.
pub const EVENT_TEXT: usize = 120;

/// Supervisor → monitors: one event of the supervisor's log.
#[derive(Debug, Clone, Copy, PartialEq, ZeroCopySend)]
#[repr(C)]
pub struct EventEntry {
    /// Wall time since the start, s.
    pub t_wall_s: f64,
    /// Drive progress when it happened (sample index).
    pub k: u64,
    /// Sequence number (0, 1, ...).
    pub seq: u64,
    /// "event service: detail", NUL-padded UTF-8 (cut at a character boundary).
    pub text: [u8; EVENT_TEXT],
}

impl EventEntry {
    /// Builds an entry, cutting `text` to fit.
    pub fn new(t_wall_s: f64, k: u64, seq: u64, text: &str) -> Self {
        let mut e = Self {
            t_wall_s,
            k,
            seq,
            text: [0; EVENT_TEXT],
        };
        put_str(&mut e.text, text);
        e
    }

    /// The text.
    pub fn text(&self) -> &str {
        get_str(&self.text)
    }
}

/// Copies `s` into a NUL-padded buffer, cut at a character boundary.
pub fn put_str(buf: &mut [u8], s: &str) {
    let mut end = s.len().min(buf.len());
    while !s.is_char_boundary(end) {
        end -= 1;
    }
    buf[..end].copy_from_slice(&s.as_bytes()[..end]);
    buf[end..].fill(0);
}

/// Reads a NUL-padded buffer written by [`put_str`].
pub fn get_str(buf: &[u8]) -> &str {
    let end = buf.iter().position(|&b| b == 0).unwrap_or(buf.len());
    std::str::from_utf8(&buf[..end]).unwrap_or("?")
}

/// Fault kinds a monitor can ask for.
pub const FAULT_KILL: u32 = 1;
/// SIGSTOP for `stop_ms`, then SIGCONT.
pub const FAULT_STOP: u32 = 2;

/// Monitor → supervisor: inject a fault now.
#[derive(Debug, Clone, Copy, PartialEq, Default, ZeroCopySend)]
#[repr(C)]
pub struct FaultRequest {
    /// [`FAULT_KILL`] or [`FAULT_STOP`].
    pub kind: u32,
    /// Index of the stage in the drive's topology, as in [`DriveView::stage_names`].
    pub service: u32,
    /// Freeze time of a stop, ms.
    pub stop_ms: u32,
    /// Requesting process.
    pub pid: u32,
}

/// A publish-subscribe service without wake-ups (telemetry is polled).
pub type Plain<T> =
    iceoryx2::service::port_factory::publish_subscribe::PortFactory<ipc::Service, T, ()>;

/// Opens or creates a polled telemetry topic.
pub fn open_plain<T: std::fmt::Debug + ZeroCopySend + Copy + 'static>(
    node: &Node<ipc::Service>,
    topic: &str,
    buffer: usize,
    history: usize,
) -> Result<Plain<T>> {
    let name = ServiceName::new(topic).map_err(|e| anyhow!("service name {topic}: {e:?}"))?;
    node.service_builder(&name)
        .publish_subscribe::<T>()
        .max_publishers(8)
        .max_subscribers(8)
        .max_nodes(16)
        .subscriber_max_buffer_size(buffer)
        .history_size(history)
        .enable_safe_overflow(true)
        .open_or_create()
        .map_err(|e| anyhow!("cannot open topic {topic}: {e:?}"))
}

/// Opens an existing telemetry topic (for a monitor: fails when no drive is on the bus).
pub fn open_existing<T: std::fmt::Debug + ZeroCopySend + Copy + 'static>(
    node: &Node<ipc::Service>,
    topic: &str,
) -> Result<Plain<T>> {
    let name = ServiceName::new(topic).map_err(|e| anyhow!("service name {topic}: {e:?}"))?;
    node.service_builder(&name)
        .publish_subscribe::<T>()
        .open()
        .map_err(|e| anyhow!("cannot open topic {topic}: {e:?}"))
}

/// A publisher of a telemetry topic.
pub struct PlainSender<T: std::fmt::Debug + ZeroCopySend + Copy + 'static>(
    Publisher<ipc::Service, T, ()>,
);

impl<T: std::fmt::Debug + ZeroCopySend + Copy + 'static> PlainSender<T> {
    /// Creates the publisher and connects it to the subscribers that exist now.
    pub fn new(topic: &Plain<T>) -> Result<Self> {
        use iceoryx2::port::update_connections::UpdateConnections;
        let p = topic
            .publisher_builder()
            .max_loaned_samples(2)
            .create()
            .map_err(|e| anyhow!("publisher: {e:?}"))?;
        p.update_connections()
            .map_err(|e| anyhow!("update connections: {e:?}"))?;
        Ok(Self(p))
    }

    /// Connects to subscribers that appeared since the last send (and hands them the
    /// history), without sending.
    pub fn connect(&self) -> Result<()> {
        use iceoryx2::port::update_connections::UpdateConnections;
        self.0
            .update_connections()
            .map_err(|e| anyhow!("update connections: {e:?}"))
    }

    /// Copies `msg` into a loaned sample and sends it (no wake-up; the loan makes iceoryx2's
    /// one allocation per message, docs/architecture.md, "Real-time rules").
    #[inline]
    pub fn send(&self, msg: &T) -> Result<()> {
        let s = self.0.loan_uninit().map_err(|e| anyhow!("loan: {e:?}"))?;
        s.write_payload(*msg)
            .send()
            .map_err(|e| anyhow!("send: {e:?}"))?;
        Ok(())
    }
}

/// A polled subscriber of a telemetry topic.
pub struct PlainReceiver<T: std::fmt::Debug + ZeroCopySend + Copy + 'static>(
    Subscriber<ipc::Service, T, ()>,
);

impl<T: std::fmt::Debug + ZeroCopySend + Copy + 'static> PlainReceiver<T> {
    /// Creates the subscriber with a buffer of `buffer` samples.
    pub fn new(topic: &Plain<T>, buffer: usize) -> Result<Self> {
        Ok(Self(
            topic
                .subscriber_builder()
                .buffer_size(buffer)
                .create()
                .map_err(|e| anyhow!("subscriber: {e:?}"))?,
        ))
    }

    /// Next buffered message, oldest first.
    pub fn try_recv(&self) -> Result<Option<T>> {
        match self.0.receive() {
            Ok(Some(s)) => Ok(Some(*s)),
            Ok(None) => Ok(None),
            Err(e) => Err(anyhow!("receive: {e:?}")),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn buckets_are_monotonic_and_contain_their_values() {
        let mut last = 0;
        for v in (0..40u32).flat_map(|e| {
            let base = 1u64 << e;
            [base, base + base / 3, base + base / 2, 2 * base - 1]
        }) {
            let b = bucket(v);
            assert!(b >= last, "bucket({v}) = {b} < {last}");
            last = b;
            if b < BUCKETS - 1 {
                assert!(v < bucket_upper_ns(b), "{v} not below upper edge of {b}");
                if b > 0 {
                    assert!(v >= bucket_upper_ns(b - 1), "{v} below lower edge of {b}");
                }
            }
        }
        // A bucket spans at most a quarter octave.
        for b in 2..BUCKETS {
            let lo = bucket_upper_ns(b - 1) as f64;
            let hi = bucket_upper_ns(b) as f64;
            assert!(hi / lo <= 1.26, "bucket {b} spans {lo}..{hi}");
        }
    }

    #[test]
    fn quantiles_bound_the_exact_ones() {
        let mut h = CompactHist::default();
        // 990 values of 10 µs and 10 of 500 µs: p99 is 10 µs, p99.9 500 µs.
        for _ in 0..990 {
            h.record_ns(10_000);
        }
        for _ in 0..10 {
            h.record_ns(500_000);
        }
        let p99 = h.quantile_ns(0.99);
        assert!((10_000..=10_000 * 126 / 100).contains(&p99), "p99 {p99}");
        assert_eq!(h.quantile_ns(0.999), 500_000, "clamped to the max");
        assert_eq!(h.max_ns, 500_000);
        assert_eq!(h.count, 1000);
        assert_eq!(CompactHist::default().quantile_ns(0.99), 0);
        h.record_ns(-5);
        assert_eq!(h.counts[0], 1);
    }

    #[test]
    fn event_text_is_cut_at_a_character_boundary() {
        let long = "é".repeat(100);
        let e = EventEntry::new(0.0, 0, 0, &long);
        assert_eq!(e.text().len(), EVENT_TEXT);
        assert!(e.text().chars().all(|c| c == 'é'));
        assert_eq!(
            EventEntry::new(0.0, 0, 0, "kill plant").text(),
            "kill plant"
        );
    }
}
