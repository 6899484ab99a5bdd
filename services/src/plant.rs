//! The plant process: timing master. Per sample k it takes command k−1, publishes
//! measurement k and integrates to t_{k+1} (DESIGN.md "The cycle").

use crate::common::*;
use anyhow::{anyhow, bail, Result};
use drivelab::bus::{self, DriveTopics, Receiver, MAX_BUFFER};
use drivelab::drive::Plant;
use drivelab::messages::{Finite, Header, Measurement, VoltageCommand, FLAG_END};
use drivelab::rt::{now_ns, sleep_until_ns};
use std::io::BufRead;
use std::time::Instant;

/// Takes every buffered command; returns command `want` if it is there. Older commands are
/// late (counted), malformed ones rejected (counted).
fn take_command(
    rx: &Receiver<VoltageCommand>,
    want: u64,
    c: &mut Counters,
) -> Result<Option<VoltageCommand>> {
    let mut found = None;
    while let Some(cmd) = rx.try_recv()? {
        if !cmd.is_finite() || cmd.hdr.k > want {
            c.rejected_inputs += 1;
        } else if cmd.hdr.k == want {
            found = Some(cmd);
        } else {
            c.late_commands += 1;
        }
    }
    Ok(found)
}

/// Runs the plant service.
pub fn run(args: ServiceArgs) -> Result<()> {
    let sc = load_scenario(&args)?;
    let node = bus::node(&args.bus, "plant")?;
    let topics = DriveTopics::open(&node)?;
    let meas_tx = topics.meas.sender()?;
    let cmd_rx = topics.cmd.receiver(16)?;
    let lockstep = args.clock == BusClock::Lockstep;
    let rec_rx = if lockstep && args.recorder {
        Some(topics.rec.receiver(16)?)
    } else {
        None
    };
    let report = apply_placement("plant", &sc, &args)?;
    let mut plant = Plant::new(&sc);
    let mut c = Counters::default();
    ready()?;
    // Wait for the launcher's GO (everyone is subscribed by then).
    let mut line = String::new();
    std::io::stdin().lock().read_line(&mut line)?;
    if line.trim() != "GO" {
        bail!(
            "launcher did not say GO (got {:?}); not starting",
            line.trim()
        );
    }

    let n = sc.samples();
    let ts_ns = (1e9 / sc.rates.sample_hz).round() as u64;
    let t0 = now_ns() + 2_000_000;
    let mut recorder_done: u64 = 0;
    let mut miss_run: u64 = 0;
    // ---- real-time loop: no allocation, no locks, no logging ----
    for k in 0..=n {
        let deadline = t0 + k * ts_ns;
        let mut cmd = None;
        if lockstep {
            if k > 0 {
                let started = Instant::now();
                loop {
                    cmd = take_command(&cmd_rx, k - 1, &mut c)?;
                    if cmd.is_some() || stop_requested() {
                        break;
                    }
                    cmd_rx.wait(WAIT_SLICE)?;
                    if started.elapsed() > LOCKSTEP_WATCHDOG {
                        return Err(anyhow!(
                            "no command {} from current-loop for {:?}",
                            k - 1,
                            LOCKSTEP_WATCHDOG
                        ));
                    }
                }
            }
        } else {
            sleep_until_ns(deadline);
            if k > 0 {
                cmd = take_command(&cmd_rx, k - 1, &mut c)?;
            }
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
        if k > 0 && cmd.is_none() {
            c.deadline_misses += 1;
            miss_run += 1;
            c.longest_miss_run = c.longest_miss_run.max(miss_run);
        } else {
            miss_run = 0;
        }
        let mut meas = plant.sample(k, cmd.as_ref());
        meas.hdr.t_sample_ns = if lockstep { 0 } else { deadline };
        meas.hdr.t_pub_ns = now_ns();
        meas_tx.send(meas)?;
        plant.advance();
        c.samples += 1;
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
    write_stats(
        &args,
        &ServiceStats {
            service: "plant",
            pid: std::process::id(),
            rt: &report,
            counters: c,
        },
    )
}
