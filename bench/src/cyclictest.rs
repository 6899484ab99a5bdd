//! cyclictest (rt-tests) as a cross-check of the floor: the reference tool measures the same
//! thing (a SCHED_FIFO thread's wake-up lateness from an absolute `clock_nanosleep`, memory
//! locked) on the same core, at the same priority and rate, in the same interleaved rounds.
//! If the floor and cyclictest disagree, the floor (and every "− floor" in the report) is
//! wrong, not the machine.
//!
//! cyclictest's main thread goes to another core (`--mainaffinity`) so that cyclictest, like
//! the floor, measures a lone timer thread. With `-a N` alone cyclictest pins its main
//! thread to core N too, and that thread wakes every 10 ms: on a machine whose idle vCPU
//! halts, that alone lowers the timer thread's wake-up lateness without the CPU wake-up
//! latency request (by about 3 µs at p50 on the VM of docs/measurements.md, where a C loop
//! with such a companion thread read as low as cyclictest and cyclictest with its main
//! thread moved read as high as the floor). A cyclictest without `--mainaffinity` (rt-tests
//! before 2.0) runs with its default layout.
//!
//! cyclictest writes a histogram of whole microseconds (it truncates); each bucket is
//! recorded at its middle (+0.5 µs). Wake-ups beyond the histogram's range
//! ([`HIST_MAX_US`]) are recorded at that range, so the maximum is a lower bound then.

use crate::children::{log_tail, Kids};
use crate::{schedule, NodeSpec, VariantResult};
use anyhow::{anyhow, bail, Context, Result};
use drivelab_runtime::timing::{LatencyHist, MissCounter};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Duration;

/// Range of cyclictest's histogram, µs.
pub const HIST_MAX_US: u64 = 10_000;

/// The cyclictest to run: `cmd` as given if it contains a '/', else found on PATH. Err says
/// why it cannot be used (for the bench's one-line skip message).
pub fn locate(cmd: &str) -> std::result::Result<PathBuf, String> {
    use drivelab_runtime::runner::Missing;
    drivelab_runtime::runner::locate(cmd).map_err(|m| match m {
        Missing::NotExecutable => format!("{cmd} is not an executable file"),
        Missing::NotOnPath => format!(
            "{cmd} is not on PATH (Debian: apt-get install rt-tests; scripts/setup.sh installs it)"
        ),
    })
}

/// Runs `exe` (cyclictest) for round(seconds × hz) wake-ups on `node`'s core at its
/// SCHED_FIFO priority, memory locked, with its CPU wake-up latency request at 0 µs when
/// `latency_request` (cyclictest's default) or without one (`--default-system`), its main
/// thread on `main_core` when given (see [`main_thread_core`]), its wake-ups from the next
/// full second on when `tick_aligned`, offset by where the tick of `node`'s core falls past
/// the millisecond (`--secaligned[=µs]`: on that tick, as the floor's schedule then starts;
/// on whole milliseconds where the tick cannot be read). The histogram file and its output (`cyclictest.log`) go to
/// `work`. A stop signal stops it and ends the run with [`crate::Interrupted`].
#[allow(clippy::too_many_arguments)]
pub fn run(
    exe: &Path,
    hz: f64,
    seconds: f64,
    node: &NodeSpec,
    main_core: Option<usize>,
    latency_request: bool,
    tick_aligned: bool,
    work: &Path,
) -> Result<VariantResult> {
    let (n, ts_ns) = schedule(hz, seconds)?;
    if ts_ns % 1000 != 0 {
        bail!("cyclictest takes whole microseconds: T_s = {ts_ns} ns at {hz} Hz is not");
    }
    std::fs::create_dir_all(work)?;
    let hist = work.join("cyclictest.hist");
    let mut c = Command::new(exe);
    c.args(arguments(
        ts_ns,
        n,
        node,
        main_core,
        latency_request,
        tick_aligned.then(|| tick_phase_us(node.core)),
        &hist,
    ));
    // In its guard: a stop signal (or any error) stops it; it is reaped on every path.
    let mut kids = Kids::default();
    kids.spawn((), &mut c, work.join("cyclictest.log"), "the cross-check")?;
    // Polled every 20 ms: few wake-ups of this process beside the measured thread.
    while !kids.poll() {
        crate::check_stop()?;
        std::thread::sleep(Duration::from_millis(20));
    }
    let k = &kids.0[0];
    if let Some(s) = k.status.filter(|s| !s.success()) {
        bail!("{} failed ({s}): {}", exe.display(), log_tail(&k.log));
    }
    let text = std::fs::read_to_string(&hist)
        .with_context(|| format!("cyclictest wrote no histogram at {}", hist.display()))?;
    let r = parse(&text, ts_ns)?;
    if r.samples != n {
        bail!(
            "cyclictest reported {} wake-ups, {n} were asked for",
            r.samples
        );
    }
    Ok(r)
}

/// Where the tick of `core` falls past a whole millisecond, in the whole µs cyclictest takes
/// (0 where it cannot be read or no core is given: whole milliseconds, as the floor assumes
/// there too).
fn tick_phase_us(core: Option<usize>) -> u64 {
    core.and_then(|c| drivelab_runtime::tick::phase_of(c).ok())
        .map_or(0, |ns| (ns + 500) / 1000)
}

/// cyclictest's arguments for [`run`]: one thread, memory locked, quiet, `n` wake-ups every
/// `ts_ns`, its histogram in µs to `hist`; its wake-ups from a full second on, offset by
/// `secaligned_us` when given.
fn arguments(
    ts_ns: u64,
    n: u64,
    node: &NodeSpec,
    main_core: Option<usize>,
    latency_request: bool,
    secaligned_us: Option<u64>,
    hist: &Path,
) -> Vec<String> {
    let mut a: Vec<String> = ["-m", "-q", "-t", "1"].map(String::from).to_vec();
    a.push(format!("--interval={}", ts_ns / 1000));
    a.push(format!("--loops={n}"));
    a.push(format!("--histogram={HIST_MAX_US}"));
    a.push(format!("--histfile={}", hist.display()));
    if let Some(cpu) = node.core {
        a.push(format!("--affinity={cpu}"));
    }
    if let Some(other) = main_core {
        a.push(format!("--mainaffinity={other}"));
    }
    if let Some(p) = node.priority {
        a.push(format!("--priority={p}"));
    }
    if !latency_request {
        a.push("--default-system".into());
    }
    match secaligned_us {
        Some(0) => a.push("--secaligned".into()),
        Some(us) => a.push(format!("--secaligned={us}")),
        None => {}
    }
    a
}

/// The core for cyclictest's main thread when its timer thread runs on `timer_core`: the
/// lowest core this thread may use other than `timer_core`. None when there is no such core
/// or when `exe` does not take `--mainaffinity` (its `--help` does not mention it).
pub fn main_thread_core(exe: &Path, timer_core: usize) -> Option<usize> {
    let other = drivelab_runtime::rt::affinity_cpus()?
        .into_iter()
        .find(|&c| c != timer_core)?;
    let help = Command::new(exe).arg("--help").output().ok()?;
    let text = [help.stdout, help.stderr].concat();
    String::from_utf8_lossy(&text)
        .contains("--mainaffinity")
        .then_some(other)
}

/// Reads cyclictest's histogram file (one thread): lines `BUCKET_US COUNT`, then `#` lines,
/// among them `# Histogram Overflows: N`. A wake-up counts as a miss when it is at least
/// T_s late (as the floor counts); cyclictest does not give the order of wake-ups, so the
/// longest run of misses is not known and stays 0.
pub fn parse(text: &str, ts_ns: u64) -> Result<VariantResult> {
    let mut late = LatencyHist::new("lateness");
    let mut misses = MissCounter::default();
    let mut samples = 0u64;
    let mut overflows = None;
    for line in text.lines() {
        let line = line.trim();
        if let Some(rest) = line.strip_prefix("# Histogram Overflows:") {
            let v = rest.split_whitespace().next().unwrap_or("");
            overflows = Some(
                v.parse::<u64>()
                    .map_err(|_| anyhow!("cyclictest histogram: bad overflow count '{v}'"))?,
            );
            continue;
        }
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let mut f = line.split_whitespace();
        let (Some(b), Some(c), None) = (f.next(), f.next(), f.next()) else {
            bail!("cyclictest histogram: unexpected line '{line}'");
        };
        let (Ok(bucket_us), Ok(count)) = (b.parse::<u64>(), c.parse::<u64>()) else {
            bail!("cyclictest histogram: unexpected line '{line}'");
        };
        record(&mut late, &mut misses, bucket_us * 1000 + 500, count, ts_ns);
        samples += count;
    }
    let overflows = overflows
        .ok_or_else(|| anyhow!("cyclictest histogram: no '# Histogram Overflows' line"))?;
    record(&mut late, &mut misses, HIST_MAX_US * 1000, overflows, ts_ns);
    samples += overflows;
    if samples == 0 {
        bail!("cyclictest histogram is empty");
    }
    let mut cycle = late.clone();
    cycle.name = "cycle";
    Ok(VariantResult {
        cycle,
        lateness: late,
        samples,
        misses,
        cpu_run_ns: None,
        deadline_lateness: Vec::new(),
        // cyclictest is not ours: its calls are not counted.
        syscalls: None,
        stalls: None,
    })
}

fn record(late: &mut LatencyHist, misses: &mut MissCounter, ns: u64, count: u64, ts_ns: u64) {
    for _ in 0..count {
        late.record_ns(ns as i64);
    }
    misses.misses += if ns >= ts_ns { count } else { 0 };
}

#[cfg(test)]
mod tests {
    use super::*;

    const HIST: &str = "# Histogram\n000014 000002\n000015 000005\n000100 000001\n000250 000002\n# Total: 000000010\n# Min Latencies: 00014\n# Histogram Overflows: 00001\n# Histogram Overflow at cycle number:\n# Thread 0: 00007\n";

    #[test]
    fn its_arguments_follow_the_floor_request_and_alignment() {
        let node = NodeSpec {
            core: Some(1),
            priority: Some(70),
        };
        let hist = Path::new("/w/cyclictest.hist");
        let a = arguments(100_000, 300_000, &node, Some(0), true, Some(0), hist);
        assert_eq!(
            a,
            [
                "-m",
                "-q",
                "-t",
                "1",
                "--interval=100",
                "--loops=300000",
                "--histogram=10000",
                "--histfile=/w/cyclictest.hist",
                "--affinity=1",
                "--mainaffinity=0",
                "--priority=70",
                "--secaligned",
            ]
        );
        // A core whose tick falls 125 µs past the millisecond: a full second plus that.
        let c = arguments(100_000, 300_000, &node, Some(0), true, Some(125), hist);
        assert_eq!(c.last().map(String::as_str), Some("--secaligned=125"));
        // Without the request it runs as the system is (its default holds one at 0 µs), and a
        // schedule that starts anywhere is not second-aligned; no node: no pinning or priority.
        let b = arguments(50_000, 10, &NodeSpec::default(), None, false, None, hist);
        assert_eq!(
            &b[4..],
            [
                "--interval=50",
                "--loops=10",
                "--histogram=10000",
                "--histfile=/w/cyclictest.hist",
                "--default-system"
            ]
        );
    }

    #[test]
    fn buckets_are_recorded_at_their_middle_and_overflows_at_the_range() {
        let r = parse(HIST, 100_000).unwrap();
        assert_eq!(r.samples, 11);
        assert_eq!(r.cycle.len(), 11);
        // 2 × 14.5, 5 × 15.5 µs: the median is 15.5 µs (within the histogram's precision).
        let p = r.cycle.percentiles();
        assert!((p.p50 - 15.5).abs() < 0.02, "{p:?}");
        assert!((p.max - HIST_MAX_US as f64).abs() / (HIST_MAX_US as f64) < 1e-3);
        // At least T_s = 100 µs late: the 100.5, the two 250.5 and the overflow.
        assert_eq!(r.misses.misses, 4);
    }

    #[test]
    fn a_malformed_histogram_is_an_error_that_says_what() {
        let e = parse("000014 x\n", 100_000).unwrap_err().to_string();
        assert!(e.contains("unexpected line '000014 x'"), "{e}");
        let e = parse("000014 000002\n", 100_000).unwrap_err().to_string();
        assert!(e.contains("Histogram Overflows"), "{e}");
        let e = parse("# Histogram Overflows: 00000\n", 100_000)
            .unwrap_err()
            .to_string();
        assert!(e.contains("empty"), "{e}");
    }

    #[test]
    fn a_missing_tool_says_how_to_get_it() {
        let e = locate("/nonexistent/cyclictest").unwrap_err();
        assert!(
            e.contains("/nonexistent/cyclictest is not an executable file"),
            "{e}"
        );
        let e = locate("no-such-tool-drivelab").unwrap_err();
        assert!(e.contains("not on PATH") && e.contains("rt-tests"), "{e}");
    }
}
