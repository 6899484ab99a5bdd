//! Where the launcher sends what it records beside `trace.csv`: `trace.mcap`
//! ([`crate::trace_mcap`]) and the live Foxglove stream ([`crate::foxglove`]). The recorder
//! thread gives it the trace's rows, the supervisor thread the per-second service figures
//! and the events; both run in the launcher, never in a real-time process.

use crate::foxglove::{Live, Topic};
use crate::per_second::ServiceSecond;
use crate::trace_mcap::{LogMsg, McapTrace, WallClock, LOG_INFO};
use anyhow::{anyhow, Result};
use drivelab_runtime::trace::TraceRow;
use std::sync::{Arc, Mutex};

/// The recording's other outputs; clones share them.
#[derive(Clone)]
pub struct Sinks {
    /// `trace.mcap` while it is written (taken out to be finished).
    pub mcap: Arc<Mutex<Option<McapTrace>>>,
    /// The live stream, if asked for.
    pub live: Option<Arc<Live>>,
    /// This machine's monotonic → Unix offset (None: the samples come from another machine).
    wall: Option<WallClock>,
}

impl Sinks {
    /// Sinks writing `mcap` (if any) and streaming to `live` (if any).
    pub fn new(mcap: Option<McapTrace>, live: Option<Arc<Live>>) -> Self {
        Self {
            mcap: Arc::new(Mutex::new(mcap)),
            live,
            wall: Some(WallClock::now()),
        }
    }

    /// For samples stamped by another machine's clock: no wall time in `trace.mcap`.
    pub fn without_wall_time(mut self) -> Self {
        self.wall = None;
        self
    }

    /// No output at all (tests of the trace alone).
    pub fn none() -> Self {
        Self::new(None, None)
    }

    fn with_mcap(&self, f: impl FnOnce(&mut McapTrace) -> Result<()>) -> Result<()> {
        let mut m = self
            .mcap
            .lock()
            .map_err(|_| anyhow!("trace.mcap: a writer thread panicked"))?;
        match m.as_mut() {
            Some(m) => f(m),
            None => Ok(()),
        }
    }

    /// A row of the trace; `t_pub_ns`: when the plant published its sample (monotonic, 0:
    /// unknown, e.g. a rebuilt sample).
    pub fn row(&self, row: &TraceRow, t_pub_ns: u64) -> Result<()> {
        if let Some(l) = &self.live {
            l.row(row);
        }
        let wall = self.wall.and_then(|w| w.unix_ns(t_pub_ns));
        self.with_mcap(|m| m.row(row, wall))
    }

    /// A stage's second.
    pub fn second(&self, s: &ServiceSecond) -> Result<()> {
        if let Some(l) = &self.live {
            l.publish(Topic::Services, crate::trace_mcap::ns(s.t_s), s);
        }
        self.with_mcap(|m| m.second(s))
    }

    /// An event of the supervisor, live (`trace.mcap` gets the log from the summary).
    pub fn event(&self, t_ns: u64, text: &str) {
        if let Some(l) = &self.live {
            l.publish(
                Topic::Log,
                t_ns,
                &LogMsg::new(t_ns, LOG_INFO, "supervisor", text),
            );
        }
    }

    /// Takes the MCAP writer out to finish it.
    pub fn take_mcap(&self) -> Option<McapTrace> {
        self.mcap.lock().ok().and_then(|mut m| m.take())
    }
}
