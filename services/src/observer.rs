//! The observer process: measurement k → estimate k.

use crate::common::*;
use anyhow::{anyhow, Result};
use drivelab_runtime::bus::{self, DriveTopics};
use drivelab_runtime::drive::ObserverStep;
use drivelab_runtime::messages::{Estimate, Finite, Measurement};
use drivelab_runtime::rt::now_ns;
use std::f64::consts::{PI, TAU};
use std::time::Instant;

/// Runs the observer service.
pub fn run(args: ServiceArgs) -> Result<()> {
    let sc = load_scenario(&args)?;
    let node = bus::node(&args.bus, "observer")?;
    let topics = DriveTopics::open_with(&node, sc.timing.wake, &args.bus)?;
    let meas_rx = topics.meas.receiver(64)?;
    let est_tx = topics.est.sender()?;
    // Opened before the RT set-up: mapping its segments is not real-time work.
    let mut status = StatusPublisher::new(&node, "observer", &sc)?;
    // Connect now (a restarted observer joins running peers), not at real-time priority.
    meas_rx.connect()?;
    est_tx.connect()?;
    let mut obs = ObserverStep::new(&sc);
    let mut c = Counters::default();
    let mut h = ServiceHists::new(false, sc.rates.ts_ns());
    let mut last_k: Option<u64> = None;
    let mut last_input = Instant::now();
    let ts = sc.rates.ts();
    let realtime = args.clock == BusClock::Realtime;
    // After a restart: skip the publisher's history, seed the angle from the newest
    // measurement, take the speed from the backward difference to the next one, go on.
    let mut rejoining = args.rejoin;
    let mut seed: Option<Measurement> = None;
    // Last: everything above (controller design, histograms) is set-up work, not real-time.
    let report = apply_placement("observer", &sc, &args)?;
    ready()?;
    // ---- real-time loop: no allocation, no locks, no logging ----
    'outer: while !stop_requested() {
        if let Some(k) = last_k {
            status.tick(k, &c, &h, None)?;
        }
        meas_rx.wait(WAIT_SLICE)?;
        if rejoining {
            let mut newest = None;
            while let Some(m) = meas_rx.try_recv()? {
                if m.hdr.is_end() {
                    est_tx.send(Estimate {
                        hdr: m.hdr,
                        ..Default::default()
                    })?;
                    break 'outer;
                }
                if !m.hdr.is_warmup() && m.is_finite() {
                    newest = Some(m);
                }
            }
            let Some(m) = newest else { continue };
            match seed {
                Some(s) if m.hdr.k == s.hdr.k + 1 => {
                    let d = (m.theta_m_enc - s.theta_m_enc + PI).rem_euclid(TAU) - PI;
                    obs.preset(s.theta_m_enc, d / ts);
                    rejoining = false;
                    // m is processed below as the first estimate after the restart.
                    process(&mut obs, &m, &est_tx, &mut h, &mut c)?;
                    last_k = Some(m.hdr.k);
                }
                _ => seed = Some(m),
            }
            continue;
        }
        while let Some(m) = meas_rx.try_recv()? {
            last_input = Instant::now();
            if m.hdr.is_warmup() || m.hdr.is_end() {
                est_tx.send(Estimate {
                    hdr: m.hdr,
                    ..Default::default()
                })?;
                if m.hdr.is_end() {
                    break 'outer;
                }
                continue;
            }
            if !m.is_finite() || last_k.is_some_and(|l| m.hdr.k <= l) {
                c.rejected_inputs += 1;
                continue;
            }
            if let Some(l) = last_k {
                c.stale_inputs += m.hdr.k - l - 1;
            }
            last_k = Some(m.hdr.k);
            if realtime && !meas_rx.is_empty()? {
                // Behind (a newer measurement is waiting): update the estimator's state but
                // publish only the newest, so that a late observer catches up instead of
                // feeding the chain old estimates.
                obs.step(&m);
                c.skipped += 1;
                continue;
            }
            process(&mut obs, &m, &est_tx, &mut h, &mut c)?;
        }
        if args.clock == BusClock::Lockstep
            && last_k.is_some()
            && last_input.elapsed() > LOCKSTEP_WATCHDOG
        {
            return Err(anyhow!(
                "no measurement from plant for {LOCKSTEP_WATCHDOG:?}"
            ));
        }
    }
    // ---- end of the real-time loop ----
    write_stats(&args, "observer", &report, c, &h, &[])
}

#[inline]
fn process(
    obs: &mut ObserverStep,
    m: &Measurement,
    est_tx: &bus::Sender<Estimate>,
    h: &mut ServiceHists,
    c: &mut Counters,
) -> Result<()> {
    let t_in = h.input(m.hdr.t_pub_ns, m.hdr.t_sample_ns);
    let mut est = obs.step(m);
    est.hdr.t_pub_ns = now_ns();
    est_tx.send(est)?;
    h.done(t_in, m.hdr.t_sample_ns);
    c.samples += 1;
    Ok(())
}
