//! The plant process: timing master. Per sample k it takes command k−1, publishes
//! measurement k and integrates to t_{k+1} (docs/architecture.md, "The cycle").

use crate::common::*;
use anyhow::{anyhow, bail, Context, Result};
use drivelab_runtime::bus::{self, DriveTopics, Receiver, MAX_BUFFER};
use drivelab_runtime::drive::Plant;
use drivelab_runtime::messages::{
    Finite, Header, Measurement, VoltageCommand, FLAG_END, FLAG_WARMUP,
};
use drivelab_runtime::rt::{now_ns, sleep_until_ns};
use drivelab_runtime::timing::CycleMonitor;
use std::io::BufRead;
use std::time::Instant;

/// Takes every buffered command; returns command `want` if it is there. Older commands are
/// late (counted, and their latency still recorded), malformed ones rejected (counted).
fn take_command(
    rx: &Receiver<VoltageCommand>,
    want: u64,
    c: &mut Counters,
    mon: &mut CycleMonitor,
) -> Result<Option<VoltageCommand>> {
    let mut found = None;
    while let Some(cmd) = rx.try_recv()? {
        if cmd.hdr.is_warmup() {
            continue;
        }
        if !cmd.is_finite() || cmd.hdr.k > want {
            c.rejected_inputs += 1;
        } else if cmd.hdr.k == want {
            found = Some(cmd);
        } else {
            c.late_commands += 1;
            if cmd.hdr.t_sample_ns != 0 {
                mon.late_command(cmd.hdr.t_sample_ns, cmd.hdr.t_pub_ns);
            }
        }
    }
    Ok(found)
}

/// Warm-up messages sent through the chain before sample 0.
pub const WARMUP_MESSAGES: u64 = 50;

/// Sends [`WARMUP_MESSAGES`] flagged measurements through the chain and waits for each
/// flagged command, so that lazy port connections and first-touch page faults happen before
/// the clock starts. Controllers forward them without stepping; the recorder ignores them.
fn warm_up(meas_tx: &bus::Sender<Measurement>, cmd_rx: &Receiver<VoltageCommand>) -> Result<()> {
    for i in 0..WARMUP_MESSAGES {
        let hdr = Header {
            k: i,
            flags: FLAG_WARMUP,
            t_pub_ns: now_ns(),
            ..Default::default()
        };
        meas_tx.send(Measurement {
            hdr,
            ..Default::default()
        })?;
        let started = Instant::now();
        'wait: loop {
            while let Some(c) = cmd_rx.try_recv()? {
                if c.hdr.is_warmup() && c.hdr.k == i {
                    break 'wait;
                }
            }
            if stop_requested() {
                return Ok(());
            }
            cmd_rx.wait(WAIT_SLICE)?;
            if started.elapsed() > LOCKSTEP_WATCHDOG {
                bail!("warm-up message {i} did not come back through the chain within {LOCKSTEP_WATCHDOG:?}");
            }
        }
    }
    Ok(())
}

/// Runs the plant service.
pub fn run(args: ServiceArgs) -> Result<()> {
    let sc = load_scenario(&args)?;
    let node = bus::node(&args.bus, "plant")?;
    let topics = DriveTopics::open_with(&node, sc.timing.wake, &args.bus)?;
    let meas_tx = topics.meas.sender()?;
    // Wakes the controllers when a command is missing, so that they check their inputs.
    let est_poke = topics.est.poker()?;
    // Real time polls the command at the deadline; lockstep waits for it.
    let lockstep = args.clock == BusClock::Lockstep;
    let cmd_rx = if lockstep {
        topics.cmd.receiver(16)?
    } else {
        topics.cmd.polled_receiver(16)?
    };
    let rec_rx = if lockstep && args.recorder {
        Some(topics.rec.receiver(16)?)
    } else {
        None
    };
    // Opened before the RT set-up: mapping its segments is not real-time work.
    let mut status = StatusPublisher::new(&node, "plant", &sc)?;
    // Connect now (a restarted plant joins running peers), not at real-time priority.
    meas_tx.connect()?;
    cmd_rx.connect()?;
    let mut plant = Plant::new(&sc);
    let mut c = Counters::default();
    let n = sc.samples();
    let ts_ns = sc.rates.ts_ns();
    let mut h = ServiceHists::new(true, ts_ns);
    let mut mon = CycleMonitor::new(ts_ns);
    let spin_ns = (sc.timing.plant_spin_us * 1e3).round() as u64;
    // Last: everything above (controller design, histograms) is set-up work, not real-time.
    let report = apply_placement("plant", &sc, &args)?;
    ready()?;
    let (t0, k_start) = if args.rejoin {
        // Restarted by the supervisor: resume from the last measurement the recorder saw,
        // on the original schedule; the samples of the downtime are not produced.
        let path = args
            .rejoin_from
            .as_ref()
            .ok_or_else(|| anyhow!("--rejoin needs --rejoin-from FILE"))?;
        let text =
            std::fs::read_to_string(path).with_context(|| format!("read {}", path.display()))?;
        let last = measurement_from_json(&serde_json::from_str(&text)?)?;
        plant.restore(&last);
        if lockstep || last.hdr.t_sample_ns == 0 {
            bail!("a plant can only rejoin a real-time drive");
        }
        let t0 = last.hdr.t_sample_ns - last.hdr.k * ts_ns;
        let k = (now_ns() + 2_000_000 - t0) / ts_ns + 1;
        (t0, k.max(last.hdr.k + 1))
    } else {
        // Wait for the launcher's GO (everyone is subscribed by then).
        let mut line = String::new();
        std::io::stdin().lock().read_line(&mut line)?;
        if line.trim() != "GO" {
            bail!(
                "launcher did not say GO (got {:?}); not starting",
                line.trim()
            );
        }
        warm_up(&meas_tx, &cmd_rx)?;
        (now_ns() + 2_000_000, 0)
    };
    let mut recorder_done: u64 = 0;
    let mut loop_start = 0u64;
    // ---- real-time loop: no allocation, no locks, no logging ----
    for k in k_start..=n {
        let deadline = t0 + k * ts_ns;
        let mut cmd = None;
        if lockstep {
            if k > 0 {
                let started = Instant::now();
                loop {
                    cmd = take_command(&cmd_rx, k - 1, &mut c, &mut mon)?;
                    if cmd.is_some() || stop_requested() {
                        break;
                    }
                    cmd_rx.wait(WAIT_SLICE)?;
                    if started.elapsed() > LOCKSTEP_WATCHDOG {
                        return Err(anyhow!(
                            "no command {} from current-loop for {LOCKSTEP_WATCHDOG:?}",
                            k - 1
                        ));
                    }
                }
            }
        } else {
            if spin_ns > 0 {
                sleep_until_ns(deadline - spin_ns);
                while now_ns() < deadline {
                    std::hint::spin_loop();
                }
            } else {
                sleep_until_ns(deadline);
            }
            h.wake.record_ns(now_ns() as i64 - deadline as i64);
            if k > k_start || (k > 0 && !args.rejoin) {
                cmd = take_command(&cmd_rx, k - 1, &mut c, &mut mon)?;
                mon.at_deadline(deadline - ts_ns, cmd.map(|c| c.hdr.t_pub_ns));
            }
        }
        if k == k_start {
            loop_start = now_ns();
        }
        if stop_requested() || k == n {
            let hdr = Header {
                k,
                flags: FLAG_END,
                t_pub_ns: now_ns(),
                ..Default::default()
            };
            meas_tx.send(Measurement {
                hdr,
                ..Default::default()
            })?;
            break;
        }
        let t_in = now_ns();
        if k > 0 && cmd.is_none() {
            c.stale_inputs += 1;
            if !lockstep {
                est_poke.poke()?;
            }
        }
        let mut meas = plant.sample(k, cmd.as_ref());
        meas.hdr.t_sample_ns = if lockstep { 0 } else { deadline };
        meas.hdr.t_pub_ns = now_ns();
        meas_tx.send(meas)?;
        plant.advance();
        h.done(t_in, 0);
        c.samples += 1;
        status.tick(k, &c, &h, Some(&mon))?;
        if let Some(rx) = &rec_rx {
            // Flow control (lockstep only): never run more than half a buffer ahead.
            let started = Instant::now();
            loop {
                while let Some(done) = rx.try_recv()? {
                    recorder_done = recorder_done.max(done);
                }
                if k < recorder_done + (MAX_BUFFER / 2) as u64 || stop_requested() {
                    break;
                }
                rx.wait(WAIT_SLICE)?;
                if started.elapsed() > LOCKSTEP_WATCHDOG {
                    return Err(anyhow!(
                        "recorder stopped reading at sample {recorder_done}"
                    ));
                }
            }
        }
    }
    // ---- end of the real-time loop ----
    c.loop_wall_ns = now_ns().saturating_sub(loop_start);
    c.deadline_misses = mon.misses.misses;
    c.longest_miss_run = mon.misses.longest_run;
    write_stats(&args, "plant", &report, c, &h, &[&mon.cycle])
}
