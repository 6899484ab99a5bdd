//! The current-loop process: measurement k + estimate k + current reference → command k.
//!
//! Freshness (real time): without an estimate for 2 samples the loop falls back to the
//! encoder angle of the newest measurement (and the last speed estimate), or, sensorless,
//! commands zero voltage; without a fresh
//! current reference for 2 speed periods it ramps i_q* to zero. Commands made that way carry
//! `FLAG_STALE_INPUT`. After a restart (`--rejoin`) it takes over bumplessly from the voltage
//! the plant is applying.

use crate::common::*;
use anyhow::{anyhow, Result};
use drivelab_runtime::bus::{self, DriveTopics, Receiver};
use drivelab_runtime::drive::CurrentLoopStep;
use drivelab_runtime::messages::{
    CurrentRef, Estimate, Finite, Header, Measurement, VoltageCommand, FLAG_STALE_INPUT,
};
use drivelab_runtime::rt::now_ns;
use std::time::{Duration, Instant};

const MEAS_RING: usize = 64;
const IREF_RING: usize = 4;

/// Inputs received but not yet used, indexed by sample (fixed-size rings, no allocation).
struct Inbox {
    meas: [Option<Measurement>; MEAS_RING],
    iref: [Option<CurrentRef>; IREF_RING],
    divider: u64,
    newest_meas: Option<u64>,
    newest_iref: Option<CurrentRef>,
}

impl Inbox {
    fn drain(
        &mut self,
        meas: &Receiver<Measurement>,
        iref: &Receiver<CurrentRef>,
        c: &mut Counters,
    ) -> Result<()> {
        while let Some(m) = meas.try_recv()? {
            if m.hdr.is_warmup() || m.hdr.is_end() {
                continue;
            }
            if m.is_finite() {
                self.meas[(m.hdr.k % MEAS_RING as u64) as usize] = Some(m);
                self.newest_meas = Some(self.newest_meas.map_or(m.hdr.k, |n| n.max(m.hdr.k)));
            } else {
                c.rejected_inputs += 1;
            }
        }
        while let Some(r) = iref.try_recv()? {
            if r.hdr.is_warmup() || r.hdr.is_end() {
                continue;
            }
            if r.is_finite() {
                self.iref[((r.hdr.k / self.divider) % IREF_RING as u64) as usize] = Some(r);
                if self.newest_iref.is_none_or(|n| r.hdr.k >= n.hdr.k) {
                    self.newest_iref = Some(r);
                }
            } else {
                c.rejected_inputs += 1;
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

/// Runs the current-loop service.
pub fn run(args: ServiceArgs) -> Result<()> {
    let sc = load_scenario(&args)?;
    let node = bus::node(&args.bus, "current-loop")?;
    let topics = DriveTopics::open_with(&node, sc.timing.wake, &args.bus)?;
    let meas_rx = topics.meas.polled_receiver(64)?;
    let est_rx = topics.est.receiver(64)?;
    let lockstep = args.clock == BusClock::Lockstep;
    // Only lockstep waits for a current reference; real time polls it.
    let iref_rx = if lockstep {
        topics.iref.receiver(16)?
    } else {
        topics.iref.polled_receiver(16)?
    };
    let cmd_tx = topics.cmd.sender()?;
    // Opened before the RT set-up: mapping its segments is not real-time work.
    let mut status = StatusPublisher::new(&node, "current-loop", &sc)?;
    // Connect now (a restarted current loop joins running peers), not at real-time priority.
    meas_rx.connect()?;
    est_rx.connect()?;
    iref_rx.connect()?;
    cmd_tx.connect()?;
    let mut ctrl = CurrentLoopStep::new(&sc);
    let m = sc.motor_params();
    let ts = sc.rates.ts();
    let divider = u64::from(sc.rates.speed_divider);
    let mut inbox = Inbox {
        meas: [None; MEAS_RING],
        iref: [None; IREF_RING],
        divider,
        newest_meas: None,
        newest_iref: None,
    };
    let mut c = Counters::default();
    let mut last_k: Option<u64> = None;
    let mut active_ref = CurrentRef::default();
    let mut last_est = Estimate::default();
    let mut stale_ref_samples: u64 = 0;
    // Ramp of i_q* to zero when the speed loop is lost: the full current limit in 20 ms.
    let iq_ramp_per_sample = sc.i_q_max() * ts / 0.02;
    let mut last_input = Instant::now();
    let mut h = ServiceHists::new(false, sc.rates.ts_ns());
    let mut rejoining = args.rejoin;
    // Real time, in fallback: wake every half sample.
    let fallback_poll = Duration::from_secs_f64(0.5 * ts);
    let mut in_fallback = false;
    let sensorless =
        sc.observer.mode == drivelab_control::observer_sensorless::ObserverMode::Sensorless;
    // Last: everything above (controller design, histograms) is set-up work, not real-time.
    let report = apply_placement("current-loop", &sc, &args)?;
    ready()?;
    // ---- real-time loop: no allocation, no locks, no logging ----
    'outer: while !stop_requested() {
        if let Some(k) = last_k {
            status.tick(k, &c, &h, None)?;
        }
        // No timer in the normal path (arming one costs ~15 µs on a VM): the plant pokes the
        // estimate topic when a command is missing. In fallback, poll every half sample (an
        // estimate that comes back still wakes the loop at once).
        est_rx.wait(if in_fallback && !lockstep {
            fallback_poll
        } else {
            WAIT_SLICE
        })?;
        let mut got_est = false;
        while let Some(mut e) = est_rx.try_recv()? {
            got_est = true;
            last_input = Instant::now();
            inbox.drain(&meas_rx, &iref_rx, &mut c)?;
            if e.hdr.is_warmup() || e.hdr.is_end() {
                cmd_tx.send(VoltageCommand {
                    hdr: e.hdr,
                    ..Default::default()
                })?;
                if e.hdr.is_end() {
                    break 'outer;
                }
                continue;
            }
            if !e.is_finite() || last_k.is_some_and(|l| e.hdr.k <= l) {
                c.rejected_inputs += 1;
                continue;
            }
            if rejoining || (!lockstep && !est_rx.is_empty()?) {
                // After a restart, or when behind in real time: only the newest estimate of
                // the batch is used (older ones are counted as skipped).
                if let Some(newer) = peek_newest(&est_rx, e.hdr.k, &mut c)? {
                    if newer.hdr.is_end() {
                        cmd_tx.send(VoltageCommand {
                            hdr: newer.hdr,
                            ..Default::default()
                        })?;
                        break 'outer;
                    }
                    c.skipped += 1;
                    e = newer;
                    inbox.drain(&meas_rx, &iref_rx, &mut c)?;
                }
            }
            let k = e.hdr.k;
            let t_in = h.input(e.hdr.t_pub_ns, e.hdr.t_sample_ns);
            if let Some(l) = last_k {
                c.stale_inputs += k - l - 1;
            }
            last_k = Some(k);
            in_fallback = false;
            last_est = e;
            let Some(meas) = inbox.meas(k) else {
                // The observer saw measurement k, so it was published; we lost it.
                c.stale_inputs += 1;
                continue;
            };
            let mut flags = 0;
            if let Some(j) = ctrl.expected_ref_index(k) {
                let started = Instant::now();
                loop {
                    if let Some(r) = inbox.iref(j) {
                        active_ref = r;
                        stale_ref_samples = 0;
                        break;
                    }
                    if !lockstep {
                        // Real time: hold the last reference; after 2 speed periods without a
                        // fresh one, ramp i_q* to zero.
                        c.stale_inputs += 1;
                        stale_ref_samples += 1;
                        if stale_ref_samples > 2 * divider {
                            flags |= FLAG_STALE_INPUT;
                            let q = active_ref.i_q_ref;
                            active_ref.i_q_ref = q - q.signum() * iq_ramp_per_sample.min(q.abs());
                        }
                        break;
                    }
                    iref_rx.wait(WAIT_SLICE)?;
                    inbox.drain(&meas_rx, &iref_rx, &mut c)?;
                    if stop_requested() {
                        break 'outer;
                    }
                    if started.elapsed() > LOCKSTEP_WATCHDOG {
                        return Err(anyhow!(
                            "no current reference {j} from speed-loop for {LOCKSTEP_WATCHDOG:?}"
                        ));
                    }
                }
            }
            if rejoining {
                if let Some(r) = inbox.newest_iref {
                    active_ref = r;
                }
                ctrl.preset(&meas, &e, &active_ref);
                rejoining = false;
            }
            let mut cmd = ctrl.step(&meas, &e, &active_ref);
            cmd.hdr.flags |= flags;
            cmd.hdr.t_pub_ns = now_ns();
            cmd_tx.send(cmd)?;
            h.done(t_in, e.hdr.t_sample_ns);
            c.samples += 1;
        }
        if lockstep {
            if last_k.is_some() && last_input.elapsed() > LOCKSTEP_WATCHDOG {
                return Err(anyhow!(
                    "no estimate from observer for {LOCKSTEP_WATCHDOG:?}"
                ));
            }
            continue;
        }
        if got_est || rejoining {
            continue;
        }
        // Real time, no estimate: if the plant has moved on, fall back to the encoder angle.
        inbox.drain(&meas_rx, &iref_rx, &mut c)?;
        // Enter the fallback only when the observer is 2 samples behind the plant (one sample
        // is its normal lag behind a measurement the plant has just published).
        let lag = if in_fallback { 1 } else { 2 };
        let Some(kn) = inbox
            .newest_meas
            .filter(|&kn| last_k.is_some_and(|l| kn >= l + lag))
        else {
            continue;
        };
        let Some(meas) = inbox.meas(kn) else { continue };
        in_fallback = true;
        c.stale_inputs += 1;
        let t_in = now_ns();
        let e = Estimate {
            hdr: Header {
                k: kn,
                t_sample_ns: meas.hdr.t_sample_ns,
                flags: FLAG_STALE_INPUT,
                ..Default::default()
            },
            theta_e: drivelab_control::motor::wrap_2pi(m.p() * meas.theta_m_enc),
            omega_m: last_est.omega_m,
        };
        if let Some(r) = inbox.newest_iref {
            active_ref = r;
        }
        let mut cmd = if sensorless {
            // No position sensor to fall back on: command zero voltage.
            VoltageCommand {
                hdr: e.hdr,
                i_dq_ref: [active_ref.i_d_ref, active_ref.i_q_ref],
                omega_ref: active_ref.omega_ref,
                omega_hat: last_est.omega_m,
                theta_hat: last_est.theta_e,
                ..Default::default()
            }
        } else {
            ctrl.step(&meas, &e, &active_ref)
        };
        cmd.hdr.flags |= FLAG_STALE_INPUT;
        cmd.hdr.t_pub_ns = now_ns();
        cmd_tx.send(cmd)?;
        h.done(t_in, e.hdr.t_sample_ns);
        last_k = Some(kn);
    }
    // ---- end of the real-time loop ----
    let (near, clamped) = ctrl.singularity_counts();
    if near > 0 {
        eprintln!(
            "current-loop: warning: for {near} samples the measured i_d approached the uncontrollable i_d of Kyslan eq. (15); a1 + a2*i_d was clamped in {clamped} of them"
        );
    }
    write_stats(&args, "current-loop", &report, c, &h, &[])
}

/// Drains the receiver and returns the newest valid estimate after sample `after`, if any;
/// malformed ones and ones whose index does not advance are rejected and counted.
fn peek_newest(rx: &Receiver<Estimate>, after: u64, c: &mut Counters) -> Result<Option<Estimate>> {
    let mut newest: Option<Estimate> = None;
    while let Some(e) = rx.try_recv()? {
        if e.hdr.is_end() {
            // The end of the run wins: the caller forwards it.
            return Ok(Some(e));
        }
        if e.hdr.is_warmup() {
            continue;
        }
        if e.is_finite() && e.hdr.k > newest.map_or(after, |n| n.hdr.k) {
            newest = Some(e);
        } else {
            c.rejected_inputs += 1;
        }
    }
    Ok(newest)
}
