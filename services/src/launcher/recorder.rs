//! The recorder thread: subscribes to the plant's truth, the commands and the position
//! references with large buffers, streams every sample into the trace ([`TraceStream`]),
//! shares its progress with the supervisor; and [`attribute_gaps`], which names the fault
//! behind each missing sample.

use super::stream::{Middle, TraceStream};
use super::supervisor::{EventKind, FaultReport, SupEvent};
use anyhow::{anyhow, Result};
use drivelab_runtime::bus::{self, DriveTopics, MAX_BUFFER};
use drivelab_runtime::config::Scenario;
use drivelab_runtime::messages::{PlantTruth, SpeedRef, VoltageCommand};
use serde::Serialize;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc;
use std::sync::Arc;
use std::time::Duration;

/// A contiguous range of samples missing from the trace and why.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct Gap {
    /// First missing k.
    pub from: u64,
    /// Last missing k.
    pub to: u64,
    /// Which part is missing ("measurement", "command", or the whole [`ROW`]).
    pub part: &'static str,
    /// Why.
    pub cause: String,
}

/// The part of a gap whose rows were made but are not in `trace.csv` (it could not be
/// written).
pub const ROW: &str = "row";

/// Samples of `gaps` without their row in `trace.csv` (a command gap's row is there, with NaN
/// in its command columns).
pub fn samples_missing(gaps: &[Gap]) -> u64 {
    gaps.iter()
        .filter(|g| g.part != "command")
        .map(|g| g.to + 1 - g.from)
        .sum()
}

/// Adds sample k to `gaps`: it extends the last gap when that one ends at k − 1 with the same
/// part and cause, else it opens a new one (samples come in order).
pub(super) fn push_gap(gaps: &mut Vec<Gap>, k: u64, part: &'static str, cause: &str) {
    if let Some(g) = gaps.last_mut() {
        if g.part == part && g.to + 1 == k && g.cause == cause {
            g.to = k;
            return;
        }
    }
    gaps.push(Gap {
        from: k,
        to: k,
        part,
        cause: cause.into(),
    });
}

/// Why a sample's row has no command (NaN in its command columns, `ctrl_flags` 32).
pub(super) fn missing_command_cause(plant_down: bool) -> &'static str {
    if plant_down {
        "none reached the inverter: the plant was down (sample rebuilt, plant_flags 64)"
    } else {
        "current-loop produced no command for this sample"
    }
}

/// The command gaps of a finished trace: its rows without a command, each with its cause, as
/// the recorder lists them while it streams (the in-process drive has no recorder).
pub(super) fn command_gaps(rows: &[drivelab_runtime::trace::TraceRow]) -> Vec<Gap> {
    use drivelab_runtime::messages::{FLAG_MISSING, FLAG_PLANT_DOWN};
    let mut gaps = Vec::new();
    for r in rows.iter().filter(|r| r.ctrl_flags & FLAG_MISSING != 0) {
        let down = r.plant_flags & FLAG_PLANT_DOWN != 0;
        push_gap(&mut gaps, r.k, "command", missing_command_cause(down));
    }
    gaps
}

/// What the recorder shares with the supervisor while the drive runs.
#[derive(Default)]
pub(super) struct Progress {
    /// Newest measurement index seen + 1 (0 = none yet).
    pub next_k: std::sync::atomic::AtomicU64,
    /// The plant's newest true state (for a restarted plant to resume from).
    pub last: std::sync::Mutex<Option<PlantTruth>>,
    /// The states restarted plants were given to resume from, in order.
    pub rejoins: std::sync::Mutex<Vec<PlantTruth>>,
    /// An outer loop's newest speed reference (for a restarted outer loop to take its turn
    /// count from: docs/architecture.md, "Bumpless rejoin").
    pub last_wref: std::sync::Mutex<Option<SpeedRef>>,
    /// Decimated trace for `drivelab monitor`.
    pub tail: crate::hub::TraceTail,
    /// Cycle latencies around each hog's window (`crate::faults::hog`).
    pub hog_latency: std::sync::Mutex<Vec<crate::faults::hog::WindowLatency>>,
    /// The plant's truth messages counted by their wake word (futex wake-ups only), and the
    /// count at the recorder's newest read with the newest sample it read: the supervisor's
    /// view of the plant's real progress (`supervisor::plant_sample_now`).
    pub truth_count: std::sync::OnceLock<bus::PublishCount>,
    pub truth_mark: std::sync::Mutex<Option<TruthMark>>,
    /// The recorder stopped on an error (a trace it cannot write): the drive stops at once,
    /// instead of waiting for a reader that is gone.
    pub failed: std::sync::atomic::AtomicBool,
    /// The sample of the plant's end marker, once the recorder has it: the plant published
    /// every sample before it since its last start (a plant on another machine has no
    /// counters here to say so).
    pub plant_end: std::sync::OnceLock<u64>,
    /// The faults of the run's plan (not a monitor's requests) that were not made, each
    /// with why: the run fails with them, as it did not test what it was asked to.
    pub not_made: std::sync::Mutex<Vec<String>>,
}

/// The newest truth sample the recorder had read, and the truth topic's wake count taken
/// as soon as the read found no more.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) struct TruthMark {
    pub k: u64,
    pub count: u32,
}

impl TruthMark {
    /// The first sample the plant had not yet published when its wake count was `now`: one
    /// message per sample since the mark. A restart that resumed at a later sample since the
    /// mark is not seen (its next mark, within one poll, is).
    pub fn next_sample(self, now: u32) -> u64 {
        self.k + 1 + u64::from(now.wrapping_sub(self.count))
    }
}

/// Command `c` as the trace takes it: an unusable one (NaN, ∞ or an absurd magnitude, e.g.
/// from a `corrupt` fault) is never recorded; like an absent marker, it leaves its sample
/// without a command (docs/architecture.md, "Fault model").
fn usable(c: VoltageCommand) -> VoltageCommand {
    use drivelab_runtime::messages::{Finite, FLAG_ABSENT};
    if c.hdr.is_absent() || c.is_finite() {
        return c;
    }
    VoltageCommand {
        hdr: drivelab_runtime::messages::Header {
            k: c.hdr.k,
            flags: FLAG_ABSENT,
            ..Default::default()
        },
        ..Default::default()
    }
}

/// The recorder thread's body: reports on `ready` whether its subscriptions are in place, then
/// records samples `0..n` of scenario `sc` into `trace` (written to `trace.csv` as it goes)
/// until both streams ended or `stop` is set. It opens the drive's topics first, with
/// `publishers` publishers each (see `service::publishers_per_topic`).
pub(super) fn run_recorder(
    bus_id: String,
    sc: Scenario,
    mut trace: TraceStream,
    stop: Arc<AtomicBool>,
    progress: Arc<Progress>,
    ready: mpsc::Sender<Result<()>>,
    publishers: usize,
    realtime: bool,
) -> Result<TraceStream> {
    // How long the recorder sleeps when it found nothing. In real time a millisecond: each
    // wake-up costs a context switch, and 10–20 samples a wake-up are well within the
    // buffers (docs/architecture.md, "The recorder's cost"). In lockstep the source waits
    // for the recorder's progress, so it polls as every polled receiver does.
    let idle = if realtime {
        Duration::from_millis(1)
    } else {
        bus::POLL_SLEEP
    };
    let wake = sc.timing.wake;
    let n = sc.samples();
    let setup = (|| -> Result<_> {
        let node = bus::node(&bus_id, "recorder")?;
        let topics = DriveTopics::open_for(&node, wake, &bus_id, publishers)?;
        // Polled: a listener would cost the real-time senders a wake-up syscall per sample.
        // The trace is the plant's true state (its own topic), joined with the commands.
        let meas_rx = topics.truth.polled_receiver(MAX_BUFFER)?;
        let cmd_rx = topics.cmd.polled_receiver(MAX_BUFFER)?;
        let wref_rx = topics.wref.polled_receiver(MAX_BUFFER)?;
        let rec_tx = topics.rec.sender()?;
        if let Some(c) = topics.truth.publish_count() {
            let _ = progress.truth_count.set(c);
        }
        // The chain's middle outputs only for timing.csv: each subscriber costs its publisher
        // a delivery per sample.
        let mid_rx = if trace.times_the_chain() {
            Some((
                topics.est.polled_receiver(MAX_BUFFER)?,
                topics.iref.polled_receiver(MAX_BUFFER)?,
            ))
        } else {
            None
        };
        Ok((node, topics, meas_rx, cmd_rx, wref_rx, rec_tx, mid_rx))
    })();
    let (_node, _topics, meas_rx, cmd_rx, wref_rx, rec_tx, mid_rx) = match setup {
        Ok(v) => {
            let _ = ready.send(Ok(()));
            v
        }
        Err(e) => {
            let _ = ready.send(Err(anyhow!("{e:#}")));
            return Err(e);
        }
    };
    let rejoins = || {
        progress
            .rejoins
            .lock()
            .map(|r| r.clone())
            .unwrap_or_default()
    };
    // The outer reference of the samples (position control's θ_m_ref), and the newest one
    // for a restarted outer loop. An absent marker (lockstep: the loop is down) is no
    // reference.
    let take_wref = |trace: &mut TraceStream| -> Result<()> {
        use drivelab_runtime::messages::Finite;
        let mut newest: Option<SpeedRef> = None;
        while let Some(w) = wref_rx.try_recv()? {
            if !w.hdr.is_warmup() && !w.hdr.is_end() && !w.hdr.is_absent() && w.is_finite() {
                trace.wref(w.hdr.k, w.theta_m_ref);
                if newest.is_none_or(|n| w.hdr.k >= n.hdr.k) {
                    newest = Some(w);
                }
            }
        }
        if let (Some(w), Ok(mut last)) = (newest, progress.last_wref.lock()) {
            if last.is_none_or(|l| w.hdr.k >= l.hdr.k) {
                *last = Some(w);
            }
        }
        Ok(())
    };
    let (mut meas_end, mut cmd_end) = (false, false);
    // Every sample below `stored` is in the trace or waiting complete in its window.
    let mut stored = 0u64;
    let mut last_progress = 0u64;
    let mut last_cmd = VoltageCommand::default();
    let hogs = progress
        .hog_latency
        .lock()
        .map(|v| !v.is_empty())
        .unwrap_or(false);
    loop {
        let mut got = false;
        let mut newest = None;
        while let Some(m) = meas_rx.try_recv()? {
            got = true;
            if m.hdr.is_warmup() {
                continue;
            }
            if m.hdr.is_end() {
                meas_end = true;
                let _ = progress.plant_end.set(m.hdr.k);
                continue;
            }
            trace.meas(m, rejoins)?;
            if m.hdr.k < n {
                progress
                    .tail
                    .offer(drivelab_runtime::telemetry::TracePoint {
                        k: m.hdr.k,
                        omega: m.omega_m,
                        omega_ref: last_cmd.omega_ref,
                        i_d: m.i_dq[0],
                        i_q: m.i_dq[1],
                        i_d_ref: last_cmd.i_dq_ref[0],
                        i_q_ref: last_cmd.i_dq_ref[1],
                    });
                if m.hdr.k + 1 > progress.next_k.load(Ordering::Relaxed) {
                    progress.next_k.store(m.hdr.k + 1, Ordering::Relaxed);
                    if let Ok(mut l) = progress.last.lock() {
                        *l = Some(m);
                    }
                }
                newest = Some(m.hdr.k);
            }
        }
        // Straight after the read came up empty, the count is the read's, to within a
        // message published in between.
        if let (Some(k), Some(c)) = (newest, progress.truth_count.get()) {
            if let Ok(mut mark) = progress.truth_mark.lock() {
                *mark = Some(TruthMark { k, count: c.get() });
            }
        }
        while let Some(c) = cmd_rx.try_recv()? {
            got = true;
            if c.hdr.is_warmup() {
                continue;
            }
            if c.hdr.is_end() {
                cmd_end = true;
                continue;
            }
            let c = usable(c);
            trace.cmd(c)?;
            if !c.hdr.is_absent() {
                last_cmd = c;
                if hogs && c.hdr.t_sample_ns > 0 {
                    if let Ok(mut lat) = progress.hog_latency.lock() {
                        let ns = c.hdr.t_pub_ns as i64 - c.hdr.t_sample_ns as i64;
                        lat.iter_mut().for_each(|w| w.record(c.hdr.k, ns));
                    }
                }
            }
        }
        if let Some((est_rx, iref_rx)) = &mid_rx {
            // A sample's own output: not a warm-up, end or absence marker.
            let mut time = |which, h: &drivelab_runtime::messages::Header| {
                if !h.is_warmup() && !h.is_end() && !h.is_absent() {
                    trace.middle(which, h.k, h.t_pub_ns);
                }
            };
            while let Some(e) = est_rx.try_recv()? {
                time(Middle::Estimate, &e.hdr);
            }
            while let Some(r) = iref_rx.try_recv()? {
                time(Middle::CurrentRef, &r.hdr);
            }
        }
        take_wref(&mut trace)?;
        while stored < n && trace.complete(stored) {
            stored += 1;
        }
        if stored >= last_progress + 256 || (stored > last_progress && !got) {
            rec_tx.send(stored)?;
            last_progress = stored;
        }
        trace.advance()?;
        // An output that cannot be written stops the recording, and with it the drive, at
        // once; what was recorded and the rows not written are listed in the summary.
        if !trace.write_errors.is_empty() {
            return trace.finish();
        }
        if (meas_end && cmd_end) || stop.load(Ordering::SeqCst) {
            // Take what is still buffered, then stop.
            while let Some(m) = meas_rx.try_recv()? {
                if m.hdr.is_end() {
                    let _ = progress.plant_end.set(m.hdr.k);
                } else if !m.hdr.is_warmup() {
                    trace.meas(m, rejoins)?;
                }
            }
            while let Some(c) = cmd_rx.try_recv()? {
                if !c.hdr.is_end() && !c.hdr.is_warmup() {
                    trace.cmd(usable(c))?;
                }
            }
            // And the outer reference of the last samples (another machine's may come after
            // the commands' end).
            take_wref(&mut trace)?;
            return trace.finish();
        }
        if !got {
            std::thread::sleep(idle);
        }
    }
}

/// Without a recovery or a republished output, a fault's window lasts this long, ms.
pub const FAULT_WINDOW_MAX_MS: f64 = 200.0;

/// Names the fault behind each gap that starts inside a fault's window: from its injection to
/// the speed's recovery (else to the republished output, else [`FAULT_WINDOW_MAX_MS`]), both
/// ends included; the latest such fault wins. A plant's missing measurements are its
/// downtime; any other missing part happened during the fault. Gaps outside every window keep
/// the recorder's cause. `fs` is the sample rate, Hz.
pub(super) fn attribute_gaps(gaps: &mut [Gap], faults: &[FaultReport], fs: f64) {
    // Rows made and not written keep their cause: the fault did not take them.
    for g in gaps.iter_mut().filter(|g| g.part != ROW) {
        let in_window = |f: &&FaultReport| {
            let ms = f
                .speed_recovered_ms
                .or(f.republished_ms)
                .unwrap_or(FAULT_WINDOW_MAX_MS);
            let end = f.injected_k + (ms * 1e-3 * fs) as u64;
            f.injected_k <= g.from && g.from <= end
        };
        if let Some(f) = faults.iter().rev().find(in_window) {
            g.cause = match (g.part, f.service.as_str()) {
                ("measurement", "plant") => format!(
                    "plant {} at sample {} (fault); the plant had not come back yet",
                    f.fault, f.injected_k
                ),
                (part, svc) => format!(
                    "no {part} recorded during fault '{} {svc}' injected at sample {}",
                    f.fault, f.injected_k
                ),
            };
        }
    }
}

/// Why a measurement before the newest one received is missing when nothing else is known:
/// the recorder read too slowly and the bus's buffer dropped it.
pub(super) const LOST_IN_BUFFER: &str =
    "measurement lost between plant and recorder (recorder buffer overflow)";

/// Why a measurement after the newest one received is missing when nothing else is known.
pub(super) const PLANT_STOPPED: &str = "the plant stopped before this sample";

/// Names the crash in the measurement gaps left while the plant's process (`plant_process`)
/// was down after a crash nobody injected, which no fault report covers: from the
/// supervisor's `exited` event to the process's next `ready` or `taken-over` (or the run's
/// end), each at the drive's progress then. A restarted plant's downtime is rebuilt into the
/// trace where it can be; what is left was no buffer overflow, which is all the recorder
/// could tell. Run after [`attribute_gaps`]: an injected fault's name stays.
pub(super) fn attribute_crash_gaps(gaps: &mut [Gap], events: &[SupEvent], plant_process: &str) {
    let of_plant = |e: &SupEvent| e.process == plant_process;
    let downs: Vec<(u64, Option<u64>, String)> = events
        .iter()
        .enumerate()
        .filter(|(_, e)| of_plant(e) && matches!(e.kind, EventKind::Exited { crash: true, .. }))
        .map(|(i, e)| {
            let back = events[i + 1..]
                .iter()
                .find(|n| {
                    of_plant(n)
                        && matches!(
                            n.kind,
                            EventKind::Ready { .. } | EventKind::TakenOver { .. }
                        )
                })
                .map(|n| n.k);
            let how = e.kind.detail();
            let how = how
                .trim_end_matches(super::supervisor::NOT_INJECTED)
                .to_string();
            (e.k, back, how)
        })
        .collect();
    for g in gaps
        .iter_mut()
        .filter(|g| g.part == "measurement" && g.cause == LOST_IN_BUFFER)
    {
        if let Some((k, _, how)) = downs
            .iter()
            .rev()
            .find(|(k, back, _)| *k <= g.from && back.is_none_or(|b| g.from <= b))
        {
            g.cause = format!(
                "the plant's process '{plant_process}' crashed ({how}) at about sample {k} and was \
                 not back yet"
            );
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use drivelab_runtime::messages::{Header, FLAG_MISSING};
    use drivelab_runtime::trace::TraceRow;

    const TS: f64 = 1e-4;

    #[test]
    fn the_plants_next_sample_counts_its_publishes_since_the_mark_across_the_wrap() {
        let mark = TruthMark { k: 41, count: 7 };
        assert_eq!(mark.next_sample(7), 42);
        assert_eq!(mark.next_sample(10), 45);
        let wrapped = TruthMark {
            k: 1_000,
            count: u32::MAX - 1,
        };
        assert_eq!(wrapped.next_sample(3), 1_006);
    }

    const LOST: &str = LOST_IN_BUFFER;
    const STOPPED: &str = PLANT_STOPPED;

    /// Which samples were recorded: a measurement where `meas` says so and a command where
    /// `cmd` says so.
    struct Recording {
        meas: Vec<bool>,
        cmd: Vec<bool>,
        wref: Vec<(u64, f64)>,
        /// The outer loop's rate divider (`TraceStream::with_outer_divider`).
        outer: Option<u64>,
    }

    fn recording(meas: &[bool], cmd: &[bool]) -> Recording {
        Recording {
            meas: meas.to_vec(),
            cmd: cmd.to_vec(),
            wref: Vec::new(),
            outer: None,
        }
    }

    /// Streams the recording through a [`TraceStream`] of a scenario with that many samples
    /// (all measurements in order, then the commands, as the recorder may read them) and
    /// returns its rows and gaps.
    fn assemble(ts: f64, rec: &Recording) -> (Vec<TraceRow>, Vec<Gap>) {
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../scenarios/kyslan-pi.toml");
        let mut sc =
            Scenario::from_toml(&std::fs::read_to_string(path).unwrap(), "kyslan-pi.toml").unwrap();
        sc.rates.sample_hz = 1.0 / ts;
        sc.duration_s = rec.meas.len() as f64 * ts;
        assert_eq!(sc.samples(), rec.meas.len() as u64);
        let mut t = TraceStream::new(&sc, None)
            .unwrap()
            .with_outer_divider(rec.outer);
        let hdr = |k: usize| Header {
            k: k as u64,
            ..Default::default()
        };
        for (k, w) in &rec.wref {
            t.wref(*k, *w);
        }
        for k in (0..rec.meas.len()).filter(|&k| rec.meas[k]) {
            let m = PlantTruth {
                hdr: hdr(k),
                omega_m: k as f64,
                ..Default::default()
            };
            t.meas(m, Vec::new).unwrap();
        }
        for k in (0..rec.cmd.len()).filter(|&k| rec.cmd[k]) {
            let c = VoltageCommand {
                hdr: hdr(k),
                omega_ref: 10.0,
                ..Default::default()
            };
            t.cmd(c).unwrap();
        }
        let t = t.finish().unwrap();
        assert_eq!(t.stats.rows, t.kept.len() as u64);
        (t.kept, t.gaps)
    }

    fn gap(from: u64, to: u64, part: &'static str, cause: &str) -> Gap {
        Gap {
            from,
            to,
            part,
            cause: cause.into(),
        }
    }

    #[test]
    fn a_complete_recording_has_every_row_and_no_gap() {
        let (rows, gaps) = assemble(TS, &recording(&[true; 3], &[true; 3]));
        assert_eq!(rows.iter().map(|r| r.k).collect::<Vec<_>>(), [0, 1, 2]);
        assert_eq!(rows[2].t, 2.0 * TS);
        assert!(rows
            .iter()
            .all(|r| r.omega_ref == 10.0 && r.ctrl_flags == 0));
        assert!(gaps.is_empty());
    }

    #[test]
    fn a_missing_command_keeps_its_row_with_nan_and_one_gap() {
        let (rows, gaps) = assemble(TS, &recording(&[true; 4], &[true, true, false, true]));
        assert_eq!(rows.len(), 4);
        let r = &rows[2];
        assert_eq!((r.k, r.omega_m), (2, 2.0));
        assert!(r.omega_ref.is_nan() && r.omega_hat.is_nan() && r.i_q_ref.is_nan());
        assert_eq!(r.ctrl_flags, FLAG_MISSING);
        assert_eq!(rows[3].omega_ref, 10.0);
        assert_eq!(
            gaps,
            [gap(
                2,
                2,
                "command",
                "current-loop produced no command for this sample"
            )]
        );
    }

    #[test]
    fn a_missing_measurement_is_a_gap_with_its_cause() {
        // Lost in the middle (a later one arrived), then missing to the end (the plant stopped).
        let (rows, gaps) = assemble(
            TS,
            &recording(&[true, false, true, false, false], &[true; 5]),
        );
        assert_eq!(rows.iter().map(|r| r.k).collect::<Vec<_>>(), [0, 2]);
        assert_eq!(
            gaps,
            [
                gap(1, 1, "measurement", LOST),
                gap(3, 4, "measurement", STOPPED)
            ]
        );
        // No measurement at all: the plant stopped before every sample.
        let (rows, gaps) = assemble(TS, &recording(&[false; 3], &[true; 3]));
        assert!(rows.is_empty());
        assert_eq!(gaps, [gap(0, 2, "measurement", STOPPED)]);
    }

    #[test]
    fn adjacent_gaps_merge_only_with_the_same_part_and_cause() {
        let (_, gaps) = assemble(
            TS,
            &recording(
                &[true, true, true, false, false, true, false, false],
                &[true, false, false, true, true, false, true, true],
            ),
        );
        assert_eq!(
            gaps,
            [
                gap(
                    1,
                    2,
                    "command",
                    "current-loop produced no command for this sample"
                ),
                gap(3, 4, "measurement", LOST),
                gap(
                    5,
                    5,
                    "command",
                    "current-loop produced no command for this sample"
                ),
                gap(6, 7, "measurement", STOPPED),
            ]
        );
    }

    #[test]
    fn a_finished_traces_command_gaps_are_the_ones_the_stream_listed() {
        // Commands missing at 1-2, 5 and 7, measurements at 3-4 (no row: no command gap).
        let (rows, gaps) = assemble(
            TS,
            &recording(
                &[true, true, true, false, false, true, true, true],
                &[true, false, false, true, true, false, true, false],
            ),
        );
        let streamed: Vec<Gap> = gaps.into_iter().filter(|g| g.part == "command").collect();
        assert_eq!(streamed.len(), 3, "{streamed:?}");
        assert_eq!(command_gaps(&rows), streamed);
        // A rebuilt sample (the plant was down) has its own cause.
        let mut down = rows.clone();
        let r7 = down.iter_mut().find(|r| r.k == 7).unwrap();
        r7.plant_flags |= drivelab_runtime::messages::FLAG_PLANT_DOWN;
        let g = command_gaps(&down);
        assert_eq!(g.len(), 3, "{g:?}");
        assert_eq!(g[2].cause, missing_command_cause(true));
        assert_eq!(command_gaps(&[]), []);
    }

    fn report(
        service: &str,
        k: u64,
        republished: Option<f64>,
        recovered: Option<f64>,
    ) -> FaultReport {
        FaultReport {
            fault: "kill".into(),
            service: service.into(),
            process: service.into(),
            injected_k: k,
            injected_t_s: k as f64 / 1000.0,
            detected_data_path_ms: None,
            detected_by: None,
            detected_supervisor_ms: None,
            safe_state_ms: None,
            peak_current_a: 0.0,
            republished_ms: republished,
            speed_recovered_ms: recovered,
            plant_down: None,
            samples: Default::default(),
            bus: None,
            window: None,
            why_null: Default::default(),
        }
    }

    #[test]
    fn gaps_in_a_fault_window_name_the_fault_and_the_window_ends_are_included() {
        const CMD: &str = "current-loop produced no command for this sample";
        let plant = "plant kill at sample 10 (fault); the plant had not come back yet";
        let cl = "no command recorded during fault 'kill current-loop' injected at sample 100";
        // 1 kHz: one sample per ms. The plant's window is 10..=15 (recovered after 5 ms);
        // the current loop's 100..=102 (republished after 2.9 ms, no recovery: truncated).
        let faults = [
            report("plant", 10, Some(3.0), Some(5.0)),
            report("current-loop", 100, Some(2.9), None),
        ];
        let mut gaps = vec![
            gap(9, 9, "measurement", LOST),
            gap(10, 12, "measurement", LOST),
            gap(15, 15, "measurement", STOPPED),
            gap(16, 16, "measurement", LOST),
            gap(14, 14, "command", CMD),
            gap(102, 102, "command", CMD),
            gap(103, 103, "command", CMD),
            // A row made and not written keeps its cause inside a window too.
            gap(101, 101, ROW, "not in trace.csv: full"),
        ];
        attribute_gaps(&mut gaps, &faults, 1000.0);
        let causes: Vec<&str> = gaps.iter().map(|g| g.cause.as_str()).collect();
        assert_eq!(
            causes,
            [
                LOST,
                plant,
                plant,
                LOST,
                "no command recorded during fault 'kill plant' injected at sample 10",
                cl,
                CMD,
                "not in trace.csv: full"
            ]
        );
    }

    #[test]
    fn without_recovery_or_republishing_the_window_is_200_ms_and_the_latest_fault_wins() {
        let faults = [
            report("observer", 0, None, None),
            report("plant", 150, None, Some(1.0)),
        ];
        let mut gaps = vec![
            gap(100, 100, "measurement", LOST),
            gap(150, 151, "measurement", LOST),
            gap(200, 200, "measurement", LOST),
            gap(201, 201, "measurement", LOST),
        ];
        attribute_gaps(&mut gaps, &faults, 1000.0);
        let obs = "no measurement recorded during fault 'kill observer' injected at sample 0";
        let causes: Vec<&str> = gaps.iter().map(|g| g.cause.as_str()).collect();
        assert_eq!(
            causes,
            [
                obs,
                "plant kill at sample 150 (fault); the plant had not come back yet",
                obs,
                LOST
            ]
        );
    }

    #[test]
    fn gaps_while_a_crashed_plant_was_down_name_the_crash_not_the_buffer() {
        use std::os::unix::process::ExitStatusExt;
        let event = |k: u64, process: &str, kind: EventKind| SupEvent {
            t_wall_s: 0.0,
            k,
            kind,
            service: process.into(),
            process: process.into(),
        };
        let exited = |crash| EventKind::Exited {
            status: std::process::ExitStatus::from_raw(11),
            crash,
        };
        // The plant's process "p" crashed at about sample 50 and was ready at 80; the observer
        // crashed at 200 (not the plant's); "p" crashed again at 300 and never came back.
        let events = [
            event(50, "p", exited(true)),
            event(60, "p", EventKind::Restarted { restart: 1, pid: 7 }),
            event(80, "p", EventKind::Ready { pid: 7 }),
            event(200, "o", exited(true)),
            event(300, "p", exited(true)),
        ];
        let mut gaps = vec![
            gap(40, 40, "measurement", LOST),
            gap(50, 70, "measurement", LOST),
            gap(90, 90, "measurement", LOST),
            gap(200, 210, "measurement", LOST),
            gap(
                55,
                55,
                "command",
                "current-loop produced no command for this sample",
            ),
            gap(301, 400, "measurement", LOST),
            gap(401, 401, "measurement", "plant kill at sample 300 (fault)"),
        ];
        attribute_crash_gaps(&mut gaps, &events, "p");
        let crashed = |k: u64| {
            format!(
                "the plant's process 'p' crashed (signal: 11 (SIGSEGV)) at about \
                 sample {k} and was not back yet"
            )
        };
        let causes: Vec<String> = gaps.iter().map(|g| g.cause.clone()).collect();
        assert_eq!(
            causes,
            [
                LOST.to_string(),
                crashed(50),
                LOST.to_string(),
                LOST.to_string(),
                "current-loop produced no command for this sample".to_string(),
                crashed(300),
                "plant kill at sample 300 (fault)".to_string(),
            ]
        );
        // An injected kill's exit (no crash) leaves the cause to the fault's report.
        let mut gaps = vec![gap(50, 70, "measurement", LOST)];
        attribute_crash_gaps(&mut gaps, &[event(50, "p", exited(false))], "p");
        assert_eq!(gaps[0].cause, LOST);
    }

    #[test]
    fn the_position_reference_is_the_newest_computed_before_the_sample() {
        let mut rec = recording(&[true; 4], &[true; 4]);
        rec.wref = vec![(2, 0.5), (0, 0.25)];
        let (rows, _) = assemble(TS, &rec);
        let refs: Vec<_> = rows.iter().map(|r| r.theta_m_ref).collect();
        assert_eq!(refs, [None, Some(0.25), Some(0.25), Some(0.5)]);
    }

    #[test]
    fn the_position_reference_is_empty_while_the_speed_loop_does_not_follow_the_outer_loop() {
        // An outer loop every 2 samples publishes at 0, 2 and 4, is down, and is back at 12.
        // The speed loop follows a reference up to 2 periods older than the one it expects
        // (k − 1 rounded down to a multiple of 2): 4 is followed up to sample 10.
        let mut rec = recording(&[true; 14], &[true; 14]);
        rec.wref = vec![(0, 1.0), (2, 1.0), (4, 1.0), (12, 2.0)];
        rec.outer = Some(2);
        let (rows, _) = assemble(TS, &rec);
        let refs: Vec<_> = rows.iter().map(|r| r.theta_m_ref).collect();
        let mut want = vec![Some(1.0); 14];
        want[0] = None;
        want[11] = None;
        want[12] = None;
        want[13] = Some(2.0);
        assert_eq!(refs, want);
    }
}
