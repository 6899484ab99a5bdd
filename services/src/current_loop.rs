//! The current-loop process: measurement k + estimate k + current reference → command k.

use crate::common::*;
use anyhow::{anyhow, Result};
use drivelab::bus::{self, DriveTopics, Receiver};
use drivelab::drive::CurrentLoopStep;
use drivelab::messages::{CurrentRef, Finite, Measurement, VoltageCommand};
use drivelab::rt::now_ns;
use std::time::Instant;

const MEAS_RING: usize = 64;
const IREF_RING: usize = 4;

/// Inputs received but not yet used, indexed by sample (fixed-size rings, no allocation).
struct Inbox {
    meas: [Option<Measurement>; MEAS_RING],
    iref: [Option<CurrentRef>; IREF_RING],
    divider: u64,
}

impl Inbox {
    fn drain(
        &mut self,
        meas: &Receiver<Measurement>,
        iref: &Receiver<CurrentRef>,
        c: &mut Counters,
    ) -> Result<()> {
        while let Some(m) = meas.try_recv()? {
            if m.hdr.is_warmup() {
                continue;
            }
            if m.hdr.is_warmup() {
                continue;
            }
            if m.is_finite() || m.hdr.is_end() {
                self.meas[(m.hdr.k % MEAS_RING as u64) as usize] = Some(m);
            } else {
                c.rejected_inputs += 1;
            }
        }
        while let Some(r) = iref.try_recv()? {
            if r.hdr.is_warmup() {
                continue;
            }
            if r.hdr.is_warmup() {
                continue;
            }
            if r.is_finite() && !r.hdr.is_end() {
                self.iref[((r.hdr.k / self.divider) % IREF_RING as u64) as usize] = Some(r);
            } else if !r.hdr.is_end() {
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
    // Only lockstep waits for a current reference; real time polls it.
    let iref_rx = if args.clock == BusClock::Lockstep {
        topics.iref.receiver(16)?
    } else {
        topics.iref.polled_receiver(16)?
    };
    let cmd_tx = topics.cmd.sender()?;
    let report = apply_placement("current-loop", &sc, &args)?;
    let mut ctrl = CurrentLoopStep::new(&sc);
    let lockstep = args.clock == BusClock::Lockstep;
    let mut inbox = Inbox {
        meas: [None; MEAS_RING],
        iref: [None; IREF_RING],
        divider: u64::from(sc.rates.speed_divider),
    };
    let mut c = Counters::default();
    let mut last_k: Option<u64> = None;
    let mut active_ref = CurrentRef::default();
    let mut last_input = Instant::now();
    let mut h = ServiceHists::new(false);
    ready()?;
    // ---- real-time loop: no allocation, no locks, no logging ----
    'outer: while !stop_requested() {
        est_rx.wait(WAIT_SLICE)?;
        while let Some(e) = est_rx.try_recv()? {
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
            let k = e.hdr.k;
            let t_in = h.input(e.hdr.t_pub_ns, e.hdr.t_sample_ns);
            if let Some(l) = last_k {
                c.stale_inputs += k - l - 1;
            }
            last_k = Some(k);
            let Some(meas) = inbox.meas(k) else {
                // The observer saw measurement k, so it was published; we lost it.
                c.stale_inputs += 1;
                continue;
            };
            if let Some(j) = ctrl.expected_ref_index(k) {
                let started = Instant::now();
                loop {
                    if let Some(r) = inbox.iref(j) {
                        active_ref = r;
                        break;
                    }
                    if !lockstep {
                        // Real time: use the last reference we have, and count it.
                        c.stale_inputs += 1;
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
            let mut cmd = ctrl.step(&meas, &e, &active_ref);
            cmd.hdr.t_pub_ns = now_ns();
            cmd_tx.send(cmd)?;
            h.done(t_in);
            c.samples += 1;
        }
        if lockstep && last_k.is_some() && last_input.elapsed() > LOCKSTEP_WATCHDOG {
            return Err(anyhow!(
                "no estimate from observer for {LOCKSTEP_WATCHDOG:?}"
            ));
        }
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
