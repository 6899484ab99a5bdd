//! The speed-loop process: every N-th estimate → current reference.
//!
//! Freshness (real time): without estimates it holds its output with the integrator frozen —
//! it keeps publishing the last reference, flagged `FLAG_STALE_INPUT`, at every speed sample
//! the plant reaches. After a restart (`--rejoin`) it takes over from the last reference the
//! drive used (the topic's history) at the present speed estimate.

use crate::common::*;
use anyhow::{anyhow, Result};
use drivelab_runtime::bus::{self, DriveTopics};
use drivelab_runtime::drive::SpeedLoopStep;
use drivelab_runtime::messages::{CurrentRef, Finite, FLAG_STALE_INPUT};
use drivelab_runtime::rt::now_ns;
use std::time::Instant;

/// Runs the speed-loop service.
pub fn run(args: ServiceArgs) -> Result<()> {
    let sc = load_scenario(&args)?;
    let node = bus::node(&args.bus, "speed-loop")?;
    let topics = DriveTopics::open_with(&node, sc.timing.wake, &args.bus)?;
    let est_rx = topics.est.receiver(64)?;
    let meas_rx = topics.meas.polled_receiver(64)?;
    // After a restart: the commands' history carries the last reference the current loop
    // used (its own output's history died with the old process), for a bumpless take-over.
    let own_rx = if args.rejoin {
        Some(topics.cmd.polled_receiver(16)?)
    } else {
        None
    };
    let iref_tx = topics.iref.sender()?;
    // Opened before the RT set-up: mapping its segments is not real-time work.
    let mut status = StatusPublisher::new(&node, "speed-loop", &sc)?;
    // Connect now (a restarted speed loop joins running peers), not at real-time priority.
    est_rx.connect()?;
    meas_rx.connect()?;
    iref_tx.connect()?;
    let mut ctrl = SpeedLoopStep::new(&sc);
    for w in drivelab_runtime::drive::DriveDesign::from_scenario(&sc).warnings {
        eprintln!("speed-loop: warning: {w}");
    }
    let mut c = Counters::default();
    let mut h = ServiceHists::new(false, sc.rates.ts_ns());
    let mut last_k: Option<u64> = None;
    let mut last_input = Instant::now();
    let lockstep = args.clock == BusClock::Lockstep;
    let n = u64::from(sc.rates.speed_divider);
    let mut last_out: Option<CurrentRef> = None;
    let mut rejoining = args.rejoin;
    // Last: everything above (controller design, histograms) is set-up work, not real-time.
    let report = apply_placement("speed-loop", &sc, &args)?;
    ready()?;
    // ---- real-time loop: no allocation, no locks, no logging ----
    'outer: while !stop_requested() {
        if let Some(k) = last_k {
            status.tick(k, &c, &h, None)?;
        }
        // No timer: the plant pokes the estimate topic when a command is missing.
        est_rx.wait(WAIT_SLICE)?;
        let mut got = false;
        while let Some(e) = est_rx.try_recv()? {
            got = true;
            last_input = Instant::now();
            if e.hdr.is_warmup() || e.hdr.is_end() {
                iref_tx.send(CurrentRef {
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
            if let Some(l) = last_k {
                c.stale_inputs += e.hdr.k - l - 1;
            }
            last_k = Some(e.hdr.k);
            if !ctrl.runs_at(e.hdr.k) {
                continue;
            }
            if rejoining {
                if let Some(rx) = &own_rx {
                    let mut newest = None;
                    while let Some(cmd) = rx.try_recv()? {
                        if !cmd.hdr.is_warmup() && !cmd.hdr.is_end() && cmd.is_finite() {
                            newest = Some(cmd.i_dq_ref[1]);
                        }
                    }
                    if let Some(i_q_ref) = newest {
                        ctrl.preset(e.omega_m, i_q_ref);
                    }
                }
                rejoining = false;
            }
            let t_in = h.input(e.hdr.t_pub_ns, e.hdr.t_sample_ns);
            if let Some(mut r) = ctrl.step(&e) {
                r.hdr.t_pub_ns = now_ns();
                iref_tx.send(r)?;
                last_out = Some(r);
                c.samples += 1;
            }
            h.done(t_in, e.hdr.t_sample_ns);
        }
        if lockstep {
            if last_k.is_some() && last_input.elapsed() > LOCKSTEP_WATCHDOG {
                return Err(anyhow!(
                    "no estimate from observer for {LOCKSTEP_WATCHDOG:?}"
                ));
            }
            continue;
        }
        if got {
            continue;
        }
        // Real time, no estimate: hold the output (integrator frozen) at each speed sample
        // the plant has reached.
        let mut newest_meas = None;
        while let Some(m) = meas_rx.try_recv()? {
            if !m.hdr.is_warmup() && !m.hdr.is_end() {
                newest_meas = Some(m.hdr.k);
            }
        }
        let (Some(km), Some(prev)) = (newest_meas, last_out) else {
            continue;
        };
        let j = km / n * n;
        if j > prev.hdr.k {
            let mut r = prev;
            r.hdr.k = j;
            r.hdr.flags |= FLAG_STALE_INPUT;
            r.hdr.t_pub_ns = now_ns();
            iref_tx.send(r)?;
            last_out = Some(r);
            c.stale_inputs += 1;
        }
    }
    // ---- end of the real-time loop ----
    if ctrl.near_singular_samples > 0 {
        eprintln!(
            "speed-loop: warning: {} speed samples had an i_d set-point near the uncontrollable i_d of Kyslan eq. (15)",
            ctrl.near_singular_samples
        );
    }
    write_stats(&args, "speed-loop", &report, c, &h, &[])
}
