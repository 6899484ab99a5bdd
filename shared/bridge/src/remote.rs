//! The remote side of the bridge: what `drivelab monitor|fault|record --connect` use to
//! reach a drive's bridge over Zenoh (docs/architecture.md, "Across machines (Zenoh)").
//! Frames that fail the codec's checks are dropped and counted ([`Remote::rejected`]).

use crate::codec::{self, Wire};
use crate::link::{self, Side};
use anyhow::{anyhow, bail, Result};
use drivelab_runtime::telemetry::{DriveView, EventEntry, FaultRequest};
use std::cell::{Cell, RefCell};
use std::collections::VecDeque;
use std::path::Path;
use std::time::{Duration, Instant};
use zenoh::handlers::{FifoChannel, FifoChannelHandler};
use zenoh::query::ConsolidationMode;
use zenoh::sample::Sample;
use zenoh::Wait;

/// How long a query waits for the drive's answer.
pub const QUERY_TIMEOUT: Duration = Duration::from_secs(5);
/// Frames a subscription buffers between two reads (a frame holds up to one poll of the
/// bridge, about a millisecond of samples).
pub const SUB_FRAMES: usize = 16_384;

/// A session connected to a drive's bridge.
pub struct Remote {
    session: zenoh::Session,
    bus: String,
    endpoint: String,
    rejected: Cell<u64>,
}

/// A subscription to one topic of the drive, decoded.
pub struct Feed<T: Wire> {
    sub: zenoh::pubsub::Subscriber<FifoChannelHandler<Sample>>,
    pending: RefCell<VecDeque<T>>,
    scratch: RefCell<Vec<T>>,
}

impl Remote {
    /// Connects to the bridge at `endpoint` and finds its drive: the one of bus `bus`, or the
    /// only one there. Retries a refused connection until `wait` has passed (0: one try).
    pub fn connect(
        endpoint: &str,
        bus: Option<&str>,
        config: Option<&Path>,
        wait: Duration,
    ) -> Result<Self> {
        link::check_endpoint(endpoint, false).map_err(|e| anyhow!(e))?;
        if let Some(b) = bus {
            drivelab_runtime::bus::check_bus_id(b)?;
        }
        let t = Instant::now();
        let session = loop {
            match link::open(Side::Connect, endpoint, config) {
                Ok(s) => break s,
                Err(e) if t.elapsed() >= wait => return Err(e),
                Err(_) => std::thread::sleep(Duration::from_millis(200)),
            }
        };
        let mut r = Self {
            session,
            bus: String::new(),
            endpoint: endpoint.to_string(),
            rejected: Cell::new(0),
        };
        r.bus = r.find_bus(bus)?;
        Ok(r)
    }

    /// The drives the bridge answers for, or the one asked for.
    fn find_bus(&self, want: Option<&str>) -> Result<String> {
        let key = crate::query_key(want.unwrap_or("*"), "scenario");
        let mut buses: Vec<String> = Vec::new();
        for (k, _) in self.query(&key, None)? {
            if let Some(b) = k
                .strip_prefix("drivelab/")
                .and_then(|r| r.split('/').next())
            {
                if !buses.iter().any(|x| x == b) {
                    buses.push(b.to_string());
                }
            }
        }
        match (buses.len(), want) {
            (1, _) => Ok(buses.remove(0)),
            (0, Some(b)) => bail!("no drive on bus '{b}' at {}", self.endpoint),
            (0, None) => bail!("no drive answers at {}", self.endpoint),
            (_, _) => bail!(
                "{} drives answer at {} (buses {}): choose one with --bus",
                buses.len(),
                self.endpoint,
                buses.join(", ")
            ),
        }
    }

    /// Runs a query; returns (key, payload) of each good reply, or the first error reply.
    fn query(&self, key: &str, payload: Option<Vec<u8>>) -> Result<Vec<(String, Vec<u8>)>> {
        let mut get = self
            .session
            .get(key)
            .consolidation(ConsolidationMode::None)
            .timeout(QUERY_TIMEOUT);
        if let Some(p) = payload {
            get = get.payload(p);
        }
        let replies = get.wait().map_err(|e| anyhow!("zenoh query {key}: {e}"))?;
        let mut out = Vec::new();
        while let Ok(reply) = replies.recv() {
            match reply.result() {
                Ok(s) => out.push((
                    s.key_expr().as_str().to_string(),
                    s.payload().to_bytes().into_owned(),
                )),
                Err(e) => bail!("{}", String::from_utf8_lossy(&e.payload().to_bytes())),
            }
        }
        Ok(out)
    }

    /// The drive's bus id.
    pub fn bus(&self) -> &str {
        &self.bus
    }

    /// The endpoint connected to.
    pub fn endpoint(&self) -> &str {
        &self.endpoint
    }

    /// Frames dropped as foreign or malformed so far.
    pub fn rejected(&self) -> u64 {
        self.rejected.get()
    }

    /// The drive's resolved scenario (TOML).
    pub fn scenario_toml(&self) -> Result<String> {
        self.text("scenario")
    }

    /// The drive's resolved topology (its run folder's `topology.json`: processes, stages
    /// and each topic's producer with its rate divider).
    pub fn topology_json(&self) -> Result<String> {
        self.text("topology")
    }

    /// The drive's answer to query `what`, as text.
    fn text(&self, what: &str) -> Result<String> {
        let r = self.query(&crate::query_key(&self.bus, what), None)?;
        let (_, bytes) = r
            .into_iter()
            .next()
            .ok_or_else(|| anyhow!("the drive on bus '{}' sent no {what}", self.bus))?;
        String::from_utf8(bytes).map_err(|_| anyhow!("the drive's {what} is not UTF-8"))
    }

    /// Subscribes to topic `T::NAME` of the drive.
    pub fn feed<T: Wire>(&self) -> Result<Feed<T>> {
        let key = crate::key(&self.bus, T::NAME);
        let sub = self
            .session
            .declare_subscriber(key.as_str())
            .with(FifoChannel::new(SUB_FRAMES))
            .wait()
            .map_err(|e| anyhow!("zenoh subscriber {key}: {e}"))?;
        Ok(Feed {
            sub,
            pending: RefCell::new(VecDeque::new()),
            scratch: RefCell::new(Vec::new()),
        })
    }

    /// The kept history of topic `T::NAME` (truth, cmd, wref: the last samples of the
    /// drive; events: its last events), oldest first.
    pub fn history<T: Wire>(&self) -> Result<Vec<T>> {
        let what = if T::NAME == "events" {
            "events".to_string()
        } else {
            format!("history/{}", T::NAME)
        };
        let mut out = Vec::new();
        for (_, frame) in self.query(&crate::query_key(&self.bus, &what), None)? {
            match codec::decode::<T>(&frame) {
                Ok(v) => out.extend(v),
                Err(_) => self.rejected.set(self.rejected.get() + 1),
            }
        }
        Ok(out)
    }

    /// Decodes the next message of `feed`, if one has arrived.
    pub fn next<T: Wire>(&self, feed: &Feed<T>) -> Result<Option<T>> {
        loop {
            if let Some(m) = feed.pending.borrow_mut().pop_front() {
                return Ok(Some(m));
            }
            let Some(sample) = feed
                .sub
                .try_recv()
                .map_err(|e| anyhow!("zenoh receive: {e}"))?
            else {
                return Ok(None);
            };
            let mut v = feed.scratch.borrow_mut();
            match codec::decode_into::<T>(&sample.payload().to_bytes(), &mut v) {
                Ok(()) => feed.pending.borrow_mut().extend(v.drain(..)),
                Err(_) => self.rejected.set(self.rejected.get() + 1),
            }
        }
    }

    /// Asks the drive's supervisor for a fault; the error is the bridge's refusal.
    pub fn request_fault(&self, req: &FaultRequest) -> Result<()> {
        let answers = self
            .query(
                &crate::query_key(&self.bus, "fault"),
                Some(codec::encode(&[*req])),
            )
            .map_err(|e| anyhow!("the drive refused: {e:#}"))?;
        if answers.is_empty() {
            // Zenoh's access control drops a denied query without a word.
            bail!(
                "the drive's bridge did not answer the fault request within {QUERY_TIMEOUT:?} (denied by its access control?)"
            );
        }
        Ok(())
    }

    /// Subscribes to the run's summary (published once, when the drive has ended).
    pub fn summary_feed(&self) -> Result<zenoh::pubsub::Subscriber<FifoChannelHandler<Sample>>> {
        let key = crate::key(&self.bus, "summary");
        self.session
            .declare_subscriber(key.as_str())
            .wait()
            .map_err(|e| anyhow!("zenoh subscriber {key}: {e}"))
    }

    /// The summary from `feed`, if it has arrived.
    pub fn take_summary(
        feed: &zenoh::pubsub::Subscriber<FifoChannelHandler<Sample>>,
    ) -> Option<String> {
        feed.try_recv()
            .ok()
            .flatten()
            .and_then(|s| String::from_utf8(s.payload().to_bytes().into_owned()).ok())
    }

    /// The newest view and the event history, for a monitor that has just attached.
    pub fn catch_up(&self) -> Result<(Option<DriveView>, Vec<EventEntry>)> {
        let view = self.history::<DriveView>()?.pop();
        Ok((view, self.history::<EventEntry>()?))
    }

    /// Closes the session.
    pub fn close(self) -> Result<()> {
        self.session
            .close()
            .wait()
            .map_err(|e| anyhow!("zenoh close: {e}"))
    }
}
