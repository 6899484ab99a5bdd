//! The hop floor: what the chain's process-to-process wake-ups cost on its core, with nothing
//! else in them. A sender thread (the plant's place: core, priority, timer) wakes every
//! sample, stamps it and notifies a futex word of a wake segment; receiver processes (the
//! places of the stages downstream) each wait on their word and, but the last, pass the
//! stamp on to the next one's word. Two measurements use it:
//!
//! * [`Measure::Wakeup`], one receiver: notify → running, the kernel's part of every hop of
//!   the iceoryx2 chain (a futex wake and a switch to another process), so the chain's median
//!   can not come closer to the floor than its number of hops times this;
//! * [`Measure::Cycle`], as many receivers as the chain has processes after the plant on its
//!   critical path: deadline → the last receiver running, the bare chain. It is the iceoryx2
//!   chain's cycle without the bus, the messages and the stages' work, so it says how much of
//!   the chain's distance to the floor the machine's wake-ups take and how much is drivelab's.

use crate::children::{log_tail, Kids};
use crate::{apply_rt, in_fresh_thread, schedule, stopping, Interrupted, NodeSpec, VariantResult};
use anyhow::{anyhow, bail, Context, Result};
use drivelab_runtime::futex::WakeSegment;
use drivelab_runtime::rt::{now_ns, sleep_until_ns};
use drivelab_runtime::timing::{CycleMonitor, LatencyHist, MissCounter};
use std::path::Path;
use std::time::{Duration, Instant};

/// Wake word of the samples (the first receiver's input).
const SAMPLE: usize = 0;
/// Wake word every receiver bumps once it is ready (placed, waiting).
const READY: usize = 1;
/// Most receivers in one chain (wake words 2..=MAX_RECEIVERS are the later receivers' inputs).
pub const MAX_RECEIVERS: usize = 8;
/// The stamp that ends the run: the sender's last notify, passed along the chain.
const END: u64 = u64::MAX;
/// A receiver gives up after this long without a notify.
const SENDER_GONE: Duration = Duration::from_secs(5);

/// What the sender stamps and the last receiver records.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Measure {
    /// The sender stamps the moment it notifies; the receiver records notify → running for
    /// each notify it sees one by one.
    Wakeup,
    /// The sender stamps the sample's deadline; the last receiver records deadline → running
    /// for each sample that reaches it. A sample misses when it reaches the last receiver
    /// more than a period after its deadline (the plant would not have its command), or not
    /// at all (it coalesced with a later one on the way).
    Cycle,
}

impl Measure {
    /// The name on `drivelab bench-node hop --measure`.
    pub fn name(self) -> &'static str {
        match self {
            Measure::Wakeup => "wakeup",
            Measure::Cycle => "cycle",
        }
    }
}

impl std::str::FromStr for Measure {
    type Err = anyhow::Error;
    fn from_str(s: &str) -> Result<Self> {
        match s {
            "wakeup" => Ok(Measure::Wakeup),
            "cycle" => Ok(Measure::Cycle),
            other => bail!("unknown hop measure '{other}' (known: wakeup, cycle)"),
        }
    }
}

/// The wake word receiver `position` (1-based) waits on.
fn input_word(position: usize) -> usize {
    if position == 1 {
        SAMPLE
    } else {
        position
    }
}

/// Runs round(seconds × hz) samples: this process sends from a fresh thread placed at
/// `sender`; `exe bench-node hop` receives, once per entry of `receivers` (1 to
/// [`MAX_RECEIVERS`]), each placed there. The wake segment is bus `bus`'s and is removed
/// afterwards. The sender's schedule starts on the scheduler tick's grid when
/// `tick_aligned`, as the drive's plant does. The result's cycle is what `measure` says; its
/// lateness is the sender's. A stop signal ends it with [`Interrupted`], its receivers
/// stopped and its bus files removed.
#[allow(clippy::too_many_arguments)]
pub fn run(
    exe: &Path,
    hz: f64,
    seconds: f64,
    tick_aligned: bool,
    sender: &NodeSpec,
    receivers: &[NodeSpec],
    measure: Measure,
    bus: &str,
    work: &Path,
) -> Result<VariantResult> {
    if receivers.is_empty() || receivers.len() > MAX_RECEIVERS {
        bail!(
            "a hop chain has 1 to {MAX_RECEIVERS} receivers, not {}",
            receivers.len()
        );
    }
    let (n, ts_ns) = schedule(hz, seconds)?;
    std::fs::create_dir_all(work)?;
    let out = work.join(format!("hop-{}.hdr", measure.name()));
    let _ = std::fs::remove_file(&out);
    let _ = std::fs::remove_file(misses_file(&out));
    let result = (|| {
        // Dropped at the end of this closure, whatever ends it: no receiver outlives the run
        // (and each is gone before the bus files are removed below).
        let mut kids = Kids::default();
        let hops = receivers.len();
        // A segment of this name can only be a dead bench's (the name carries the bench's
        // pid, which the kernel reuses): its READY count would start this run before its
        // receivers are there.
        if WakeSegment::remove(bus)? {
            eprintln!("hop: removed a stale wake segment of bus {bus} (a bench that died)");
        }
        for (i, node) in receivers.iter().enumerate() {
            let position = i + 1;
            // Through DRIVELAB_RUNNER when set (an aarch64 build under qemu-user).
            let mut cmd = drivelab_runtime::runner::env_command(exe).map_err(|e| anyhow!(e))?;
            cmd.args([
                "bench-node",
                "hop",
                "--bus",
                bus,
                "--measure",
                measure.name(),
            ])
            .arg("--period-ns")
            .arg(ts_ns.to_string())
            .arg("--position")
            .arg(position.to_string())
            .arg("--hops")
            .arg(hops.to_string())
            .arg("--out")
            .arg(&out);
            if let Some(c) = node.core {
                cmd.arg("--core").arg(c.to_string());
            }
            if let Some(p) = node.priority {
                cmd.arg("--priority").arg(p.to_string());
            }
            let log = work.join(format!("hop-receiver-{position}.log"));
            kids.spawn_holding_term(position, &mut cmd, log, &format!("hop receiver {position}"))?;
        }
        // Made only now that the receivers run: a bench killed from here on leaves receivers
        // that remove the segment (they may make it themselves if they open it first).
        let seg = WakeSegment::open(bus)?;
        let watchdog = Duration::from_secs_f64(seconds * 3.0 + 10.0);
        let started = Instant::now();
        while (seg.seq(READY) as usize) < hops {
            kids.poll();
            if let Some(k) = kids.0.iter().find(|k| k.status.is_some()) {
                bail!(
                    "hop receiver {} exited before it was ready: {}",
                    k.what,
                    log_tail(&k.log)
                );
            }
            crate::check_stop()?;
            if started.elapsed() > watchdog {
                bail!("the hop receivers did not get ready within {watchdog:?}");
            }
            std::thread::sleep(Duration::from_millis(1));
        }
        let node = *sender;
        let lateness = in_fresh_thread("bench-hop", move || {
            // Allocated before the memory lock populates it (as the floor does).
            let mut late = LatencyHist::new("lateness");
            apply_rt("hop sender", &node, true)?;
            let t0 = drivelab_runtime::rt::schedule_start_ns(tick_aligned);
            // ---- real-time loop: no allocation, no locks, no logging ----
            let mut k = 0;
            while k < n && !stopping() {
                let deadline = t0 + k * ts_ns;
                sleep_until_ns(deadline);
                let t = now_ns();
                late.record_ns(t as i64 - deadline as i64);
                let stamp = match measure {
                    Measure::Wakeup => t,
                    Measure::Cycle => deadline,
                };
                seg.notify_stamped(SAMPLE, stamp);
                k += 1;
            }
            // ---- end of the real-time loop ----
            seg.notify_stamped(SAMPLE, END);
            if k < n {
                return Err(Interrupted.into());
            }
            Ok(late)
        })?;
        loop {
            let all = kids.poll();
            let failed = kids
                .0
                .iter()
                .find_map(|k| k.status.filter(|s| !s.success()).map(|s| (k, s)));
            if let Some((k, s)) = failed {
                bail!(
                    "hop receiver {} exited with {s}: {}",
                    k.what,
                    log_tail(&k.log)
                );
            }
            if all {
                break;
            }
            crate::check_stop()?;
            if started.elapsed() > watchdog {
                bail!("a hop receiver was still running after {watchdog:?}");
            }
            std::thread::sleep(Duration::from_millis(5));
        }
        let cycle = LatencyHist::read_v2("cycle", &out)?;
        let misses = match measure {
            // Hops the receiver did not see one by one.
            Measure::Wakeup => {
                let mut m = MissCounter::default();
                m.misses = n.saturating_sub(cycle.len());
                m
            }
            Measure::Cycle => {
                let (mut m, counted) = read_misses(&misses_file(&out))?;
                // Samples before the first that reached the last receiver.
                m.misses += n.saturating_sub(counted);
                m
            }
        };
        Ok(VariantResult {
            cycle,
            lateness,
            samples: n,
            misses,
            cpu_run_ns: None,
            deadline_lateness: Vec::new(),
            syscalls: None,
            stalls: None,
        })
    })();
    drivelab_runtime::bus::cleanup(bus)?;
    result
}

/// Accounts for one arrival at the last receiver of a [`Measure::Cycle`] chain in `mon`
/// (samples `period_ns` apart, the plant's cycle rule), in sample order: the samples between
/// the previous arrival's deadline and this one's never arrived (misses), and this one is
/// recorded as `deadline` → `arrived`. Returns how many samples it accounted for.
#[inline]
fn account(
    mon: &mut CycleMonitor,
    prev_deadline: Option<u64>,
    deadline: u64,
    arrived: u64,
    period_ns: u64,
) -> u64 {
    let skipped = prev_deadline.map_or(0, |p| {
        (deadline.saturating_sub(p) / period_ns).saturating_sub(1)
    });
    for j in 1..=skipped {
        mon.at_deadline(deadline - j * period_ns, None);
    }
    mon.at_deadline(deadline, Some(arrived));
    skipped + 1
}

/// Where the last receiver of a [`Measure::Cycle`] chain writes its misses, beside `out`.
fn misses_file(out: &Path) -> std::path::PathBuf {
    out.with_extension("misses")
}

/// Misses, longest run of misses and samples accounted for, as the last receiver wrote them.
fn read_misses(path: &Path) -> Result<(MissCounter, u64)> {
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("cannot read the bare chain's misses {}", path.display()))?;
    let v: Vec<u64> = text
        .split_whitespace()
        .map(str::parse)
        .collect::<std::result::Result<_, _>>()
        .with_context(|| format!("malformed misses file {}", path.display()))?;
    match v[..] {
        [misses, longest_run, counted] => {
            let mut m = MissCounter::default();
            m.misses = misses;
            m.longest_run = longest_run;
            Ok((m, counted))
        }
        _ => bail!("malformed misses file {}: want 3 numbers", path.display()),
    }
}

/// Receiver `position` of `hops` (`drivelab bench-node hop`): opens bus `bus`'s wake segment,
/// takes its placement, says it is ready, then for each notify on its word passes the stamp
/// on to the next receiver or, the last, records it as `measure` says (samples `period_ns`
/// apart), until the sender's end stamp; the last writes its histogram to `out` (and, for
/// [`Measure::Cycle`], its misses beside it).
pub fn receive(
    bus: &str,
    position: usize,
    hops: usize,
    measure: Measure,
    period_ns: u64,
    node: &NodeSpec,
    out: &Path,
) -> Result<()> {
    if hops == 0 || hops > MAX_RECEIVERS || position == 0 || position > hops {
        bail!("hop receiver {position} of {hops}: the position must be in 1..={hops} and the receivers 1 to {MAX_RECEIVERS}");
    }
    if measure == Measure::Cycle && period_ns == 0 {
        bail!("hop receiver {position}: --period-ns must be positive to measure a cycle");
    }
    // The wake-up or cycle histogram, and (cycle) the misses by the plant's rule.
    let mut mon = CycleMonitor::new(period_ns);
    let mut counted = 0u64;
    let mut prev_deadline: Option<u64> = None;
    // A stop signal (the bench's parent-death SIGTERM among them) ends the futex wait at
    // once (the handlers do not restart it), and notifies no longer come once the bench is
    // gone, so the loop below sees it without a notify.
    drivelab_runtime::service::install_signal_handlers()?;
    let seg = WakeSegment::open(bus)?;
    let input = input_word(position);
    let next = (position < hops).then(|| input_word(position + 1));
    apply_rt("hop receiver", node, true)?;
    let mut seen = seg.seq(input);
    seg.notify(READY);
    let mut last_ns = now_ns();
    // ---- real-time loop: no allocation, no locks, no logging ----
    loop {
        let now = seg.wait(input, seen, Duration::from_millis(100));
        if now == seen {
            // The sender is gone (its bench was killed: the kernel's parent-death SIGTERM, or
            // no notify for a while): do not outlive it, and do not leave its wake segment
            // behind either (a bench that was SIGKILLed cannot remove it).
            let why = if drivelab_runtime::service::stop_requested() {
                Some(drivelab_runtime::service::stop_signal_name().to_string())
            } else if now_ns().saturating_sub(last_ns) > SENDER_GONE.as_nanos() as u64 {
                Some(format!("no notify for {SENDER_GONE:?}"))
            } else {
                None
            };
            if let Some(why) = why {
                let removed = match WakeSegment::remove(bus) {
                    Ok(true) => "; removed its wake segment".to_string(),
                    Ok(false) => String::new(),
                    Err(e) => format!("; its wake segment stays: {e}"),
                };
                return Err(anyhow!("hop receiver {position} stopped ({why}){removed}"));
            }
            continue;
        }
        let t = now_ns();
        last_ns = t;
        // Read after the word: at least as new as the notify that bumped it.
        let stamp = seg.stamp(input);
        let single = now == seen.wrapping_add(1);
        seen = now;
        if let Some(w) = next {
            seg.notify_stamped(w, stamp);
        }
        if stamp == END {
            break;
        }
        if next.is_some() {
            continue;
        }
        match measure {
            // Only a single step is one hop (after a jump the stamp is the newest notify's).
            Measure::Wakeup if single => mon.cycle.record_ns(t as i64 - stamp as i64),
            Measure::Wakeup => {}
            // The stamp is the newest sample's deadline; the ones between it and the last
            // seen never arrived.
            Measure::Cycle => {
                counted += account(&mut mon, prev_deadline, stamp, t, period_ns);
                prev_deadline = Some(stamp);
            }
        }
    }
    // ---- end of the real-time loop ----
    if next.is_none() {
        mon.cycle.write_v2(out)?;
        if measure == Measure::Cycle {
            let path = misses_file(out);
            drivelab_runtime::files::write(
                &path,
                format!(
                    "{} {} {counted}\n",
                    mon.misses.misses, mon.misses.longest_run
                ),
            )
            .with_context(|| format!("cannot write {}", path.display()))?;
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_dead_benchs_wake_segment_does_not_start_the_sender_before_its_receivers() {
        // What a bench and its receivers, all SIGKILLed, would leave on a bus name that a
        // later bench gets again (the name carries the pid): two receivers counted ready.
        let bus = format!("hopstale{}", std::process::id());
        let work = std::env::temp_dir().join(format!("drivelab-hop-stale-{}", std::process::id()));
        // Removes the segment and the folder also when an assertion below fails.
        struct Leftovers<'a>(&'a str, &'a Path);
        impl Drop for Leftovers<'_> {
            fn drop(&mut self) {
                let _ = WakeSegment::remove(self.0);
                let _ = std::fs::remove_dir_all(self.1);
            }
        }
        let _leftovers = Leftovers(&bus, &work);
        let stale = WakeSegment::open(&bus).unwrap();
        stale.notify(READY);
        stale.notify(READY);
        drop(stale);
        // Receivers that never get ready: the sender must wait for them, not for the count
        // the dead bench left (it would send its samples and report how they exited).
        let e = run(
            Path::new("/bin/false"),
            1000.0,
            0.1,
            true,
            &NodeSpec::default(),
            &[NodeSpec::default(), NodeSpec::default()],
            Measure::Wakeup,
            &bus,
            &work,
        )
        .unwrap_err()
        .to_string();
        assert!(e.starts_with("hop receiver "), "{e}");
        assert!(e.contains(" exited before it was ready"), "{e}");
        assert!(
            !WakeSegment::remove(&bus).unwrap(),
            "the run left its segment"
        );
        std::fs::remove_dir_all(&work).unwrap();
    }

    #[test]
    fn the_bare_chain_counts_skipped_and_late_samples_as_misses_in_order() {
        let mut mon = CycleMonitor::new(1_000);
        // The first arrival, 400 ns after its deadline: in time.
        assert_eq!(account(&mut mon, None, 1_000, 1_400, 1_000), 1);
        assert_eq!((mon.misses.misses, mon.misses.longest_run), (0, 0));
        // Two samples coalesced on the way (deadlines 2 000 and 3 000), the third arrives in
        // time: three accounted for, two misses in a row.
        assert_eq!(account(&mut mon, Some(1_000), 4_000, 4_900, 1_000), 3);
        assert_eq!((mon.misses.misses, mon.misses.longest_run), (2, 2));
        // Exactly a period late still has its command at the next deadline; one ns more not.
        assert_eq!(account(&mut mon, Some(4_000), 5_000, 6_000, 1_000), 1);
        assert_eq!(mon.misses.misses, 2);
        assert_eq!(account(&mut mon, Some(5_000), 6_000, 7_001, 1_000), 1);
        assert_eq!((mon.misses.misses, mon.misses.longest_run), (3, 2));
    }

    #[test]
    fn measures_are_named_and_unknown_ones_are_refused() {
        for m in [Measure::Wakeup, Measure::Cycle] {
            assert_eq!(m.name().parse::<Measure>().unwrap(), m);
        }
        let e = "deadline".parse::<Measure>().unwrap_err().to_string();
        assert_eq!(e, "unknown hop measure 'deadline' (known: wakeup, cycle)");
    }

    #[test]
    fn a_malformed_misses_file_is_an_error_that_names_it() {
        let dir = std::env::temp_dir().join(format!("drivelab-hop-misses-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("hop-cycle.misses");
        std::fs::write(&path, "3 2 2000\n").unwrap();
        let (m, counted) = read_misses(&path).unwrap();
        assert_eq!((m.misses, m.longest_run, counted), (3, 2, 2000));
        std::fs::write(&path, "3 2\n").unwrap();
        let e = read_misses(&path).unwrap_err().to_string();
        assert!(
            e.starts_with("malformed misses file ") && e.ends_with("want 3 numbers"),
            "{e}"
        );
        std::fs::write(&path, "3 x 1\n").unwrap();
        let e = read_misses(&path).unwrap_err().to_string();
        assert!(e.starts_with("malformed misses file "), "{e}");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
