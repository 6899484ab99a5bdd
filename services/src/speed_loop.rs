//! The speed-loop process: every N-th estimate → current reference.

use crate::common::*;
use anyhow::{anyhow, Result};
use drivelab::bus::{self, DriveTopics};
use drivelab::drive::{DriveDesign, SpeedLoopStep};
use drivelab::messages::{CurrentRef, Finite};
use drivelab::rt::now_ns;
use std::time::Instant;

/// Runs the speed-loop service.
pub fn run(args: ServiceArgs) -> Result<()> {
    let sc = load_scenario(&args)?;
    let node = bus::node(&args.bus, "speed-loop")?;
    let topics = DriveTopics::open_with(&node, sc.timing.wake, &args.bus)?;
    let est_rx = topics.est.receiver(64)?;
    let iref_tx = topics.iref.sender()?;
    let report = apply_placement("speed-loop", &sc, &args)?;
    let mut ctrl = SpeedLoopStep::new(&sc);
    for w in DriveDesign::from_scenario(&sc).warnings {
        eprintln!("speed-loop: warning: {w}");
    }
    let mut c = Counters::default();
    let mut h = ServiceHists::new(false);
    let mut last_k: Option<u64> = None;
    let mut last_input = Instant::now();
    ready()?;
    // ---- real-time loop: no allocation, no locks, no logging ----
    'outer: while !stop_requested() {
        est_rx.wait(WAIT_SLICE)?;
        while let Some(e) = est_rx.try_recv()? {
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
            let t_in = h.input(e.hdr.t_pub_ns, e.hdr.t_sample_ns);
            if let Some(mut r) = ctrl.step(&e) {
                r.hdr.t_pub_ns = now_ns();
                iref_tx.send(r)?;
                c.samples += 1;
            }
            h.done(t_in);
        }
        if args.clock == BusClock::Lockstep
            && last_k.is_some()
            && last_input.elapsed() > LOCKSTEP_WATCHDOG
        {
            return Err(anyhow!(
                "no estimate from observer for {LOCKSTEP_WATCHDOG:?}"
            ));
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
