//! The hop floor: what one process-to-process wake-up costs on the chain's core, with nothing
//! else in it. A sender thread (the plant's place: core, priority, timer) wakes every sample,
//! stamps the moment and notifies a futex word of a wake segment; a receiver process (the
//! observer's place) waits on that word and records notify → running. This is the kernel's
//! part of every hop of the iceoryx2 chain (a futex wake and a switch to another address
//! space), so the chain's median can not come closer to the floor than its number of hops
//! times this.

use crate::uds::log_tail;
use crate::{apply_rt, in_fresh_thread, schedule, NodeSpec, VariantResult};
use anyhow::{anyhow, bail, Context, Result};
use drivelab_runtime::futex::WakeSegment;
use drivelab_runtime::rt::{now_ns, sleep_until_ns};
use drivelab_runtime::timing::{LatencyHist, MissCounter};
use std::path::Path;
use std::process::Stdio;
use std::time::{Duration, Instant};

/// Wake word of the samples.
const SAMPLE: usize = 0;
/// Wake word the receiver bumps once it is ready (placed, waiting).
const READY: usize = 1;
/// The receiver gives up after this long without a notify.
const SENDER_GONE: Duration = Duration::from_secs(5);

/// Runs round(seconds × hz) hops: this process sends from a fresh thread placed at
/// `sender`, `exe bench-node hop` receives placed at `receiver`. The wake segment is bus
/// `bus`'s and is removed afterwards.
pub fn run(
    exe: &Path,
    hz: f64,
    seconds: f64,
    sender: &NodeSpec,
    receiver: &NodeSpec,
    bus: &str,
    work: &Path,
) -> Result<VariantResult> {
    let (n, ts_ns) = schedule(hz, seconds)?;
    std::fs::create_dir_all(work)?;
    let out = work.join("hop.wakeup.hdr");
    let _ = std::fs::remove_file(&out);
    let seg = WakeSegment::open(bus)?;
    let result = (|| {
        // Through DRIVELAB_RUNNER when set (an aarch64 build under qemu-user).
        let mut cmd = drivelab_runtime::runner::env_command(exe).map_err(|e| anyhow!(e))?;
        cmd.args(["bench-node", "hop", "--bus", bus, "--samples"])
            .arg(n.to_string())
            .arg("--out")
            .arg(&out);
        if let Some(c) = receiver.core {
            cmd.arg("--core").arg(c.to_string());
        }
        if let Some(p) = receiver.priority {
            cmd.arg("--priority").arg(p.to_string());
        }
        let log = work.join("hop-receiver.log");
        let f = std::fs::File::create(&log)?;
        let mut child = cmd
            .stdin(Stdio::null())
            .stdout(f.try_clone()?)
            .stderr(f)
            .spawn()
            .with_context(|| format!("cannot start {} for the hop receiver", exe.display()))?;
        let watchdog = Duration::from_secs_f64(seconds * 3.0 + 10.0);
        let started = Instant::now();
        while seg.seq(READY) == 0 {
            if child.try_wait()?.is_some() || started.elapsed() > watchdog {
                let _ = child.kill();
                let _ = child.wait();
                bail!("hop receiver did not get ready: {}", log_tail(&log));
            }
            std::thread::sleep(Duration::from_millis(1));
        }
        let seg = WakeSegment::open(bus)?;
        let node = *sender;
        let lateness = in_fresh_thread("bench-hop", move || {
            // Allocated before the memory lock populates it (as the floor does).
            let mut late = LatencyHist::new("lateness");
            apply_rt("hop sender", &node, true)?;
            let t0 = now_ns() + 2_000_000;
            // ---- real-time loop: no allocation, no locks, no logging ----
            for k in 0..n {
                let deadline = t0 + k * ts_ns;
                sleep_until_ns(deadline);
                let t = now_ns();
                late.record_ns(t as i64 - deadline as i64);
                seg.notify_stamped(SAMPLE, t);
            }
            // ---- end of the real-time loop ----
            Ok(late)
        })?;
        loop {
            if let Some(s) = child.try_wait()? {
                if !s.success() {
                    bail!("hop receiver exited with {s}: {}", log_tail(&log));
                }
                break;
            }
            if started.elapsed() > watchdog {
                let _ = child.kill();
                let _ = child.wait();
                bail!("hop receiver still running after {watchdog:?}; killed");
            }
            std::thread::sleep(Duration::from_millis(5));
        }
        let wakeup = LatencyHist::read_v2("cycle", &out)?;
        let mut misses = MissCounter::default();
        // Hops the receiver did not see one by one (it woke after two or more notifies).
        misses.misses = n.saturating_sub(wakeup.len());
        Ok(VariantResult {
            cycle: wakeup,
            lateness,
            samples: n,
            misses,
            cpu_run_ns: None,
        })
    })();
    drop(seg);
    drivelab_runtime::bus::cleanup(bus)?;
    result
}

/// The receiver (`drivelab bench-node hop`): opens bus `bus`'s wake segment, takes its
/// placement, says it is ready and records, for each notify it sees, stamp → running, until
/// `samples` notifies were sent; writes the histogram to `out`.
pub fn receive(bus: &str, samples: u64, node: &NodeSpec, out: &Path) -> Result<()> {
    let seg = WakeSegment::open(bus)?;
    let mut h = LatencyHist::new("wakeup");
    apply_rt("hop receiver", node, true)?;
    let mut seen = seg.seq(SAMPLE);
    seg.notify(READY);
    let mut last = Instant::now();
    // ---- real-time loop: no allocation, no locks, no logging ----
    while u64::from(seen) < samples {
        let now = seg.wait(SAMPLE, seen, Duration::from_millis(100));
        if now == seen {
            // The sender is gone (its bench was killed): do not outlive it.
            if last.elapsed() > SENDER_GONE {
                return Err(anyhow!("hop receiver: no notify for {SENDER_GONE:?}"));
            }
            continue;
        }
        last = Instant::now();
        let t = now_ns();
        // Only a single step is one hop; after a jump the stamp is the newest notify's.
        if now == seen.wrapping_add(1) {
            h.record_ns(t as i64 - seg.stamp(SAMPLE) as i64);
        }
        seen = now;
    }
    // ---- end of the real-time loop ----
    h.write_v2(out)
}
