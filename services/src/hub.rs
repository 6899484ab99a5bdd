//! The supervisor's side of live telemetry (see `drivelab_runtime::telemetry`): it collects the
//! services' statuses, adds its own view of the processes and a decimated trace, and
//! publishes them for `drivelab monitor`; it takes the monitors' fault requests.
//!
//! Everything here runs on the launcher's supervisor thread, never in a real-time process.
//! The status subscriber exists before the services start, so their publishers connect
//! outside their loops; monitors connect only to this hub's publishers.

use anyhow::{anyhow, bail, Result};
use drivelab_runtime::config::Scenario;
use drivelab_runtime::messages::FLAG_END;
use drivelab_runtime::telemetry::*;
use iceoryx2::prelude::*;
use iceoryx2::service::port_factory::PortFactory;
use std::collections::VecDeque;
use std::sync::Mutex;
use std::time::{Duration, Instant};

/// How often the view is published (wall time).
pub const VIEW_PERIOD: Duration = Duration::from_millis(100);
/// Events kept for a monitor that attaches late.
pub const EVENT_HISTORY: usize = 64;

/// The decimated trace the recorder fills for the hub.
#[derive(Debug, Default)]
pub struct TraceTail {
    /// Samples between points.
    pub decimation: u64,
    /// Newest [`VIEW_POINTS`] points, oldest first.
    pub points: Mutex<VecDeque<TracePoint>>,
}

impl TraceTail {
    /// A tail with one point per 10 ms of simulated time.
    pub fn new(sample_hz: f64) -> Self {
        Self {
            decimation: ((sample_hz * 0.01).round() as u64).max(1),
            points: Mutex::new(VecDeque::with_capacity(VIEW_POINTS)),
        }
    }

    /// Adds a point if `p.k` is on the decimation grid.
    pub fn offer(&self, p: TracePoint) {
        if !p.k.is_multiple_of(self.decimation) {
            return;
        }
        if let Ok(mut q) = self.points.lock() {
            if q.len() == VIEW_POINTS {
                q.pop_front();
            }
            q.push_back(p);
        }
    }
}

/// The CPUs of the drive's real-time processes (bit i = CPU i) in `sc`'s topology.
pub fn rt_cores(sc: &Scenario) -> u64 {
    drivelab_runtime::topology::cores(&sc.topology())
}

/// The hub's ports and state.
pub struct Hub {
    _node: Node<ipc::Service>,
    _status_topic: Plain<ServiceStatus>,
    view_topic: Plain<DriveView>,
    _events_topic: Plain<EventEntry>,
    _req_topic: Plain<FaultRequest>,
    status_rx: PlainReceiver<ServiceStatus>,
    view_tx: PlainSender<DriveView>,
    events_tx: PlainSender<EventEntry>,
    req_rx: PlainReceiver<FaultRequest>,
    view: Box<DriveView>,
    prev: [Option<(u64, u64)>; MAX_STAGES],
    stages: Vec<String>,
    last_view: Option<Instant>,
    events_sent: usize,
    /// Per-second figures of each stage, for `trace.mcap` and the live stream.
    per_second: crate::per_second::PerSecond,
    sinks: crate::launcher::sinks::Sinks,
    sample_hz: f64,
}

impl Hub {
    /// Creates the hub's node and topics on bus `bus_id` for a drive of `stages` (the
    /// topology's order); call before spawning the stage hosts.
    pub fn new(bus_id: &str, sc: &Scenario, lockstep: bool, stages: &[String]) -> Result<Self> {
        let node = drivelab_runtime::bus::node(bus_id, "supervisor")?;
        let status_topic = open_plain::<ServiceStatus>(&node, TOPIC_STATUS, 16, 0)?;
        let view_topic = open_plain::<DriveView>(&node, TOPIC_VIEW, 4, 1)?;
        let events_topic =
            open_plain::<EventEntry>(&node, TOPIC_EVENTS, EVENT_HISTORY, EVENT_HISTORY)?;
        let req_topic = open_plain::<FaultRequest>(&node, TOPIC_FAULT_REQ, 16, 0)?;
        // Four services, ten statuses per simulated second each; lockstep runs ~10x faster
        // than real time and the hub polls every millisecond: 256 is ample.
        let status_rx = PlainReceiver::new(&status_topic, 16)?;
        let view_tx = PlainSender::new(&view_topic)?;
        let events_tx = PlainSender::new(&events_topic)?;
        let req_rx = PlainReceiver::new(&req_topic, 16)?;
        let mut view = Box::<DriveView>::default();
        view.sample_hz = sc.rates.sample_hz;
        view.n_samples = sc.samples();
        view.lockstep = u32::from(lockstep);
        view.rt_cores = rt_cores(sc);
        view.n_stages = stages.len().min(MAX_STAGES) as u32;
        for (slot, name) in view.stage_names.iter_mut().zip(stages) {
            put_str(slot, name);
        }
        put_str(&mut view.scenario, &sc.name);
        Ok(Self {
            _node: node,
            _status_topic: status_topic,
            view_topic,
            _events_topic: events_topic,
            _req_topic: req_topic,
            status_rx,
            view_tx,
            events_tx,
            req_rx,
            view,
            prev: [None; MAX_STAGES],
            stages: stages.to_vec(),
            last_view: None,
            events_sent: 0,
            per_second: crate::per_second::PerSecond::new(stages.len(), sc.rates.sample_hz),
            sinks: crate::launcher::sinks::Sinks::none(),
            sample_hz: sc.rates.sample_hz,
        })
    }

    /// Sends each stage's per-second figures and the events to `sinks` too.
    pub fn set_sinks(&mut self, sinks: crate::launcher::sinks::Sinks) {
        self.sinks = sinks;
    }

    /// Sets what the supervisor knows of the process that hosts `stage`.
    pub fn set_process(&mut self, stage: &str, state: ProcState, pid: u32, restarts: u32) {
        let Some(i) = self
            .stages
            .iter()
            .position(|s| s == stage)
            .filter(|&i| i < MAX_STAGES)
        else {
            return;
        };
        let s = &mut self.view.services[i];
        s.state = state as u32;
        s.pid = pid;
        s.restarts = restarts;
    }

    /// The drive's stages, in the view's order.
    pub fn stages(&self) -> &[String] {
        &self.stages
    }

    /// Drains statuses and fault requests, publishes new events, and the view when due.
    /// `events` is the supervisor's whole log; `k_now` the drive's progress. Returns the
    /// fault requests that arrived.
    pub fn poll(
        &mut self,
        events: &[crate::launcher::SupEvent],
        k_now: u64,
        tail: &TraceTail,
    ) -> Result<Vec<FaultRequest>> {
        while let Some(st) = self.status_rx.try_recv()? {
            let i = st.service as usize;
            if i >= self.view.stages() {
                continue;
            }
            let s = &mut self.view.services[i];
            // A restarted service starts its counters again: rate from its own statuses.
            if let Some((samples, t)) = self.prev[i].filter(|_| s.status.pid == st.pid) {
                let dt = st.hdr.t_pub_ns.saturating_sub(t) as f64 * 1e-9;
                if dt > 0.0 && st.samples >= samples {
                    s.rate_hz = (st.samples - samples) as f64 / dt;
                }
            } else {
                s.rate_hz = 0.0;
            }
            self.prev[i] = Some((st.samples, st.hdr.t_pub_ns));
            if let Some(sec) = self.per_second.offer(&self.stages[i], &st) {
                self.sinks.second(&sec)?;
            }
            s.status = st;
            s.has_status = 1;
        }
        while self.events_sent < events.len() {
            let e = &events[self.events_sent];
            let text = format!("{} {}: {}", e.name(), e.service, e.detail());
            self.sinks
                .event(crate::trace_mcap::ns(e.k as f64 / self.sample_hz), &text);
            self.events_tx.send(&EventEntry::new(
                e.t_wall_s,
                e.k,
                self.events_sent as u64,
                &text,
            ))?;
            self.events_sent += 1;
        }
        let mut reqs = Vec::new();
        while let Some(r) = self.req_rx.try_recv()? {
            reqs.push(r);
        }
        if self.last_view.is_none_or(|t| t.elapsed() >= VIEW_PERIOD) {
            self.last_view = Some(Instant::now());
            // A monitor that attached late gets the event history now, not at the next event.
            self.events_tx.connect()?;
            self.publish(k_now, tail, 0)?;
        }
        Ok(reqs)
    }

    fn publish(&mut self, k_now: u64, tail: &TraceTail, flags: u32) -> Result<()> {
        let v = &mut self.view;
        v.hdr.k = k_now;
        v.hdr.flags = flags;
        v.hdr.t_pub_ns = drivelab_runtime::rt::now_ns();
        v.decimation = tail.decimation;
        if let Ok(q) = tail.points.lock() {
            v.n_points = q.len() as u32;
            for (slot, p) in v.points.iter_mut().zip(q.iter()) {
                *slot = *p;
            }
        }
        self.view_tx.send(v)
    }

    /// Takes the stages' last statuses and reports each one's last (part) second, then
    /// publishes the final view (END flag) and waits up to `wait` for the monitors to let go
    /// of the bus, so that its files can be removed.
    pub fn finish(&mut self, k_now: u64, tail: &TraceTail, wait: Duration) -> Result<()> {
        self.poll(&[], k_now, tail)?;
        for i in 0..self.view.stages() {
            let s = &self.view.services[i];
            if s.has_status == 0 {
                continue;
            }
            if let Some(sec) = self.per_second.close(&self.stages[i], &s.status) {
                self.sinks.second(&sec)?;
            }
        }
        self.publish(k_now, tail, FLAG_END)?;
        let t = Instant::now();
        while self.view_topic.dynamic_config().number_of_subscribers() > 0 && t.elapsed() < wait {
            std::thread::sleep(Duration::from_millis(5));
        }
        Ok(())
    }
}

/// A monitor's fault request as a fault due at `at_s` (simulated time) on one of `stages`,
/// validated.
pub fn to_fault(r: &FaultRequest, at_s: f64, stages: &[String]) -> Result<crate::faults::Fault> {
    use crate::faults::{Fault, FaultKind};
    let service = stages
        .get(r.service as usize)
        .ok_or_else(|| anyhow!("fault request for unknown stage #{}", r.service))?;
    let (kind, duration_s) = match r.kind {
        FAULT_KILL => (FaultKind::Kill, 0.0),
        FAULT_STOP if (1..=60_000).contains(&r.stop_ms) => {
            (FaultKind::Stop, f64::from(r.stop_ms) / 1000.0)
        }
        FAULT_STOP => bail!(
            "stop fault of {} ms is out of range (1..60000 ms)",
            r.stop_ms
        ),
        k => bail!("unknown fault kind {k}"),
    };
    Ok(Fault {
        kind,
        service: service.to_string(),
        at_s,
        duration_s,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::faults::{Fault, FaultKind};

    #[test]
    fn a_monitors_request_becomes_a_fault_within_its_bounds() {
        let stages: Vec<String> = ["plant", "observer"].map(String::from).to_vec();
        let req = |kind, service, stop_ms| FaultRequest {
            kind,
            service,
            stop_ms,
            pid: 7,
        };
        let fault = |kind, service: &str, duration_s| Fault {
            kind,
            service: service.into(),
            at_s: 0.25,
            duration_s,
        };
        let ok = |r| to_fault(&r, 0.25, &stages).unwrap();
        let err = |r| format!("{:#}", to_fault(&r, 0.25, &stages).unwrap_err());
        assert_eq!(
            ok(req(FAULT_KILL, 1, 0)),
            fault(FaultKind::Kill, "observer", 0.0)
        );
        // A stop lasts 1 ms to 60 s, both ends included.
        assert_eq!(
            ok(req(FAULT_STOP, 0, 1)),
            fault(FaultKind::Stop, "plant", 0.001)
        );
        assert_eq!(
            ok(req(FAULT_STOP, 0, 60_000)),
            fault(FaultKind::Stop, "plant", 60.0)
        );
        for ms in [0, 60_001] {
            assert!(
                err(req(FAULT_STOP, 0, ms)).contains("out of range"),
                "{ms} ms"
            );
        }
        assert!(err(req(FAULT_KILL, 2, 0)).contains("unknown stage #2"));
        assert!(err(req(9, 0, 0)).contains("unknown fault kind 9"));
    }
}
