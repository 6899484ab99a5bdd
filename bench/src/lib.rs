//! drivelab latency/jitter benchmarks: the measurement back-ends of `drivelab bench`.
//!
//! * [`run_floor`]: a bare periodic `clock_nanosleep(TIMER_ABSTIME)` loop — what the timer
//!   alone costs on this machine (wake-up lateness, one per wake-up: after a late wake-up the
//!   deadlines that passed are skipped, as cyclictest does, and counted as misses);
//! * [`run_inprocess`]: the whole control chain ([`InProcessDrive::cycle`]) in one thread on the
//!   same kind of timer;
//! * [`cyclictest::run`]: cyclictest (rt-tests), when installed, as a cross-check of the
//!   floor;
//! * [`cache::after_sleep`]: how cold the plant's core leaves a task's memory over one
//!   sample's sleep (the host's share of every stage's step after its wake-up);
//! * [`idle::settle`]: before a variant measured without the CPU wake-up latency request, lets
//!   the core's idle governor stop the polling that the request left behind;
//! * [`hop::run`]: one process-to-process futex wake-up with nothing else in it (the
//!   kernel's part of every hop of the chain), or the bare chain: the timer and the default
//!   chain's two wake-ups, with no bus, messages or stage work;
//! * [`run_uds_chain`]: the four roles as four processes exchanging the bus messages over Unix
//!   domain sockets, with the same per-sample order and semantics as the iceoryx2 services
//!   (see [`uds`]).
//!
//! Every real-time loop preallocates its histograms and never allocates, locks or logs.
//!
//! A stop signal (`drivelab_runtime::service::stop_signals`, once the caller has installed
//! their handlers) ends every measurement early with [`Interrupted`]: the loops read the stop
//! flag (an atomic load per sample), the processes a measurement started are stopped and
//! reaped, and the bus files it made are removed.

use anyhow::{anyhow, bail, Result};
use drivelab_runtime::config::Scenario;
use drivelab_runtime::drive::InProcessDrive;
use drivelab_runtime::rt::{
    now_ns, setup_rt, sleep_until_ns, thread_cpu_ns, RtPolicy, RtReport, RtRequest,
};
use drivelab_runtime::timing::{CycleMonitor, LatencyHist, MissCounter};

pub mod cache;
pub mod catch_up;
mod children;
pub mod cyclictest;
pub mod hop;
pub mod idle;
pub mod uds;
pub mod wire;

pub use uds::{run_uds_chain, run_uds_node, UdsNodeArgs};

/// The error of a measurement that a stop signal cut short (its processes stopped, its bus
/// files removed). Displays as "interrupted (SIGINT)", naming the first stop signal.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Interrupted;

impl std::fmt::Display for Interrupted {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "interrupted ({})",
            drivelab_runtime::service::stop_signal_name()
        )
    }
}

impl std::error::Error for Interrupted {}

/// Whether a stop signal has arrived (one atomic load: real-time loops may ask every sample).
#[inline]
pub(crate) fn stopping() -> bool {
    drivelab_runtime::service::stop_requested()
}

/// Err([`Interrupted`]) once a stop signal has arrived.
pub fn check_stop() -> Result<()> {
    if stopping() {
        Err(Interrupted.into())
    } else {
        Ok(())
    }
}

/// Result of one measured variant.
#[derive(Debug, Clone)]
pub struct VariantResult {
    /// Cycle latency from the ideal sample instant t_k to the moment command k is available to
    /// the plant (for `floor`: the timer's wake-up lateness, i.e. wake − t_k).
    pub cycle: LatencyHist,
    /// Plant wake-up lateness (actual wake − scheduled) — for floor same as cycle.
    pub lateness: LatencyHist,
    /// Samples run.
    pub samples: u64,
    /// Deadline misses (command k not available by t_{k+1}; for the floor: wake-ups later than
    /// Ts) and longest run.
    pub misses: MissCounter,
    /// The floor: the measuring thread's time on the CPU over all its wake-ups (the kernel's
    /// timer path included), ns.
    pub cpu_run_ns: Option<u64>,
    /// The floor: its lateness at every deadline, one list per round (empty for the other
    /// variants, and for a round longer than [`MAX_DEADLINES_KEPT`]), for
    /// [`catch_up::misses`].
    pub deadline_lateness: Vec<catch_up::DeadlineLateness>,
    /// The system calls the variant's loops made at drivelab's own call sites
    /// (`drivelab_runtime::rt::syscalls`: sleeps, futex waits and wakes, socket sends and
    /// receives), all its processes together; None where they are not counted.
    pub syscalls: Option<u64>,
    /// The floor's stalls, wake-ups half a millisecond late or later, and how many
    /// consecutive ones end on a host's 100 ms throttling grid; for a drive's chain, its
    /// plant's (`summary.json → timing.stalls`). None for the other variants.
    pub stalls: Option<drivelab_runtime::timing::StallReport>,
}

impl VariantResult {
    /// Adds another measurement of the same variant (a later round): histograms and counts
    /// add, the longest miss run is the longest of either (runs do not span rounds).
    pub fn merge(&mut self, other: &VariantResult) -> anyhow::Result<()> {
        self.cycle.add(&other.cycle)?;
        self.lateness.add(&other.lateness)?;
        self.samples += other.samples;
        self.misses.misses += other.misses.misses;
        self.misses.longest_run = self.misses.longest_run.max(other.misses.longest_run);
        self.cpu_run_ns = match (self.cpu_run_ns, other.cpu_run_ns) {
            (Some(a), Some(b)) => Some(a + b),
            _ => None,
        };
        self.deadline_lateness
            .extend(other.deadline_lateness.iter().cloned());
        self.syscalls = self.syscalls.zip(other.syscalls).map(|(a, b)| a + b);
        self.stalls = match (self.stalls.take(), &other.stalls) {
            (Some(a), Some(b)) => Some(a.merged(b)),
            (a, b) => a.or_else(|| b.clone()),
        };
        Ok(())
    }
}

/// Placement of one node: core and SCHED_FIFO priority (None = unpinned / SCHED_OTHER).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct NodeSpec {
    /// CPU core to pin to.
    pub core: Option<usize>,
    /// SCHED_FIFO priority 1..=99.
    pub priority: Option<u8>,
}

/// What to measure for a chain variant.
#[derive(Debug, Clone)]
pub struct ChainSpec {
    /// The scenario (the caller sets `rates.sample_hz`). Its placement is ignored: the four
    /// [`NodeSpec`]s below decide.
    pub scenario: Scenario,
    /// Seconds of measurement: round(seconds × sample_hz) samples.
    pub seconds: f64,
    /// Plant (timing master).
    pub plant: NodeSpec,
    /// Observer.
    pub observer: NodeSpec,
    /// Current loop.
    pub current_loop: NodeSpec,
    /// Speed loop.
    pub speed_loop: NodeSpec,
}

/// The floor keeps its lateness at each deadline for rounds of up to this many deadlines
/// (16 MB: 200 s at 20 kHz).
pub const MAX_DEADLINES_KEPT: u64 = 1 << 22;

/// Stack bytes touched before a loop starts.
const PREFAULT_STACK: usize = 256 * 1024;

/// Applies a node's placement to the calling thread (warn on refusal) and prints the one-line
/// report to stderr. `lock_memory` is process-wide (`mlockall`): only node processes ask.
pub(crate) fn apply_rt(name: &str, node: &NodeSpec, lock_memory: bool) -> Result<RtReport> {
    let req = RtRequest {
        core: node.core,
        fifo_priority: node.priority,
        lock_memory,
        prefault_stack_bytes: PREFAULT_STACK,
    };
    let rep = setup_rt(&req, RtPolicy::Warn).map_err(|e| anyhow!("{name}: {e}"))?;
    eprintln!("{}", rep.one_line(name));
    Ok(rep)
}

/// Sleeps to the absolute deadline; with `spin_ns` > 0 sleeps to `spin_ns` before it and spins
/// the rest (the scenario's `timing.plant_spin_us`, as the iceoryx2 plant does).
#[inline]
pub(crate) fn wait_deadline(deadline: u64, spin_ns: u64) {
    if spin_ns > 0 {
        sleep_until_ns(deadline.saturating_sub(spin_ns));
        while now_ns() < deadline {
            std::hint::spin_loop();
        }
    } else {
        sleep_until_ns(deadline);
    }
}

/// Sample count and sample time (ns) for `seconds` at `hz`.
pub(crate) fn schedule(hz: f64, seconds: f64) -> Result<(u64, u64)> {
    if !(hz.is_finite() && hz > 0.0 && hz <= 1e6) {
        bail!("sample rate {hz} Hz must be in (0, 1e6]");
    }
    if !(seconds.is_finite() && seconds > 0.0 && seconds <= 86_400.0) {
        bail!("seconds = {seconds} must be in (0, 86400]");
    }
    let n = (seconds * hz).round() as u64;
    let ts_ns = (1e9 / hz).round() as u64;
    Ok((n, ts_ns))
}

/// Runs `f` in a fresh, named thread (its placement dies with it) and returns its result.
pub(crate) fn in_fresh_thread<T: Send + 'static>(
    name: &str,
    f: impl FnOnce() -> Result<T> + Send + 'static,
) -> Result<T> {
    std::thread::Builder::new()
        .name(name.into())
        .spawn(f)
        .map_err(|e| anyhow!("cannot start the {name} thread: {e}"))?
        .join()
        .map_err(|_| anyhow!("the {name} thread panicked"))?
}

/// The floor: a bare periodic clock_nanosleep(TIMER_ABSTIME) loop at `hz` for `seconds`, on
/// `node`'s core and SCHED_FIFO priority, in a fresh thread of this process (restore nothing:
/// the thread ends), its schedule started as the chains' is (`tick_aligned`). Records
/// lateness.
pub fn run_floor(
    hz: f64,
    seconds: f64,
    node: &NodeSpec,
    tick_aligned: bool,
) -> Result<VariantResult> {
    let (n, ts_ns) = schedule(hz, seconds)?;
    let node = *node;
    in_fresh_thread("bench-floor", move || {
        // The histogram first: locking memory populates it now, whereas memory allocated
        // after the lock is only locked page by page as the loop first touches it (a page
        // fault inside the loop, hundreds per run).
        let mut late = LatencyHist::new("lateness");
        let mut cycle = LatencyHist::new("cycle");
        let mut misses = MissCounter::default();
        let mut stalls =
            drivelab_runtime::timing::StallLog::new(drivelab_runtime::timing::STALL_LOG, ts_ns);
        let mut by_deadline =
            catch_up::DeadlineLateness::with_capacity(if n <= MAX_DEADLINES_KEPT {
                n as usize
            } else {
                0
            });
        // Like cyclictest: memory locked (process-wide, as the drive's hosts do).
        apply_rt("floor", &node, true)?;
        let t0 = drivelab_runtime::rt::schedule_start_ns(tick_aligned);
        sleep_until_ns(t0 - ts_ns);
        let cpu0 = thread_cpu_ns();
        let calls0 = drivelab_runtime::rt::syscalls();
        // ---- real-time loop: no allocation, no locks, no logging ----
        let mut k = 0;
        while k < n && !stopping() {
            let deadline = t0 + k * ts_ns;
            sleep_until_ns(deadline);
            let now = now_ns();
            late.record_ns(now as i64 - deadline as i64);
            stalls.record(deadline, now as i64 - deadline as i64);
            let missed = misses.misses;
            k = wake_up_covers(
                k,
                now,
                (t0, ts_ns, n),
                &mut cycle,
                &mut misses,
                &mut by_deadline,
            );
            stalls.misses_in_stall(misses.misses - missed);
        }
        // ---- end of the real-time loop ----
        if k < n {
            return Err(Interrupted.into());
        }
        let cpu_run_ns = Some(thread_cpu_ns().saturating_sub(cpu0));
        Ok(VariantResult {
            cycle,
            lateness: late,
            samples: n,
            misses,
            cpu_run_ns,
            deadline_lateness: if by_deadline.len() as u64 == n {
                vec![by_deadline]
            } else {
                Vec::new()
            },
            syscalls: Some(drivelab_runtime::rt::syscalls() - calls0),
            stalls: Some(drivelab_runtime::timing::StallReport::of(&stalls)),
        })
    })
}

/// The floor's bookkeeping after its wake-up for deadline `k` at `now` (deadline j is t0 +
/// j·ts_ns). The caller records one lateness per wake-up and does not sleep to the deadlines
/// that passed while it was late, as cyclictest does (a stall is one late wake-up). Every
/// deadline from `k` up to the next one ahead is handled by this wake-up, as a chain that
/// cost nothing would handle it: its lateness `now − t_j` goes into `cycle`, and it is a miss
/// when `now` is after the deadline that follows it (the chain's rule: command j later than
/// t_{j+1}). The lateness also goes into `by_deadline` while it has room (it never grows).
/// Returns the next deadline's index, at most `n`.
fn wake_up_covers(
    k: u64,
    now: u64,
    (t0, ts_ns, n): (u64, u64, u64),
    cycle: &mut LatencyHist,
    misses: &mut MissCounter,
    by_deadline: &mut catch_up::DeadlineLateness,
) -> u64 {
    let next = ((now.saturating_sub(t0) / ts_ns) + 1).clamp(k + 1, n.max(k + 1));
    for j in k..next {
        let late_ns = now as i64 - (t0 + j * ts_ns) as i64;
        cycle.record_ns(late_ns);
        misses.record(now > t0 + (j + 1) * ts_ns);
        if by_deadline.len() < by_deadline.capacity() {
            by_deadline.push(late_ns.clamp(0, u32::MAX as i64) as u32);
        }
    }
    next
}

/// In-process: the full control chain ([`InProcessDrive::cycle`]) in one thread on the same
/// timer, on the plant's core and priority; cycle latency = time the command of sample k is
/// ready − t_k (a miss when that is later than t_{k+1}).
pub fn run_inprocess(spec: &ChainSpec) -> Result<VariantResult> {
    let (n, ts_ns) = schedule(spec.scenario.rates.sample_hz, spec.seconds)?;
    let sc = spec.scenario.clone();
    let node = spec.plant;
    in_fresh_thread("bench-inprocess", move || {
        let mut drive = InProcessDrive::new(&sc);
        // Warm-up on a throw-away copy: code and data pages are touched before the clock starts.
        let mut warm = drive.clone();
        for k in 0..50 {
            std::hint::black_box(warm.cycle(k));
        }
        drop(warm);
        let spin_ns = (sc.timing.plant_spin_us * 1e3).round() as u64;
        apply_rt("inprocess", &node, false)?;
        let mut mon = CycleMonitor::new(ts_ns);
        let mut late = LatencyHist::new("lateness");
        let t0 = drivelab_runtime::rt::schedule_start_ns(sc.timing.tick_aligned);
        let calls0 = drivelab_runtime::rt::syscalls();
        // ---- real-time loop: no allocation, no locks, no logging ----
        let mut k = 0;
        while k < n && !stopping() {
            let deadline = t0 + k * ts_ns;
            wait_deadline(deadline, spin_ns);
            late.record_ns(now_ns() as i64 - deadline as i64);
            std::hint::black_box(drive.cycle(k));
            mon.at_deadline(deadline, Some(now_ns()));
            k += 1;
        }
        // ---- end of the real-time loop ----
        if k < n {
            return Err(Interrupted.into());
        }
        Ok(VariantResult {
            cycle: mon.cycle,
            lateness: late,
            samples: n,
            misses: mon.misses,
            cpu_run_ns: None,
            deadline_lateness: Vec::new(),
            syscalls: Some(drivelab_runtime::rt::syscalls() - calls0),
            stalls: None,
        })
    })
}

#[cfg(test)]
pub(crate) mod testutil {
    use drivelab_runtime::config::Scenario;

    /// The shipped kyslan-pi scenario at `hz`.
    pub fn kyslan(hz: f64) -> Scenario {
        let text = std::fs::read_to_string(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../scenarios/kyslan-pi.toml"
        ))
        .unwrap();
        let mut sc = Scenario::from_toml(&text, "kyslan-pi.toml").unwrap();
        sc.rates.sample_hz = hz;
        sc.rates.speed_divider = ((hz / 1000.0).round() as u32).max(1);
        sc.observer.speed_filter_tau_s = sc.observer.speed_filter_tau_s.max(1.0 / hz);
        sc.current_loop.tau_c_s = sc.current_loop.tau_c_s.max(2.0 / hz);
        sc.validate().unwrap();
        sc
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn floor_runs_the_expected_samples() {
        let r = run_floor(2000.0, 0.05, &NodeSpec::default(), true).unwrap();
        assert_eq!(r.samples, 100);
        // One lateness per wake-up (100 on time, fewer after a late one); one cycle entry
        // per deadline.
        assert!(
            (1..=100).contains(&r.lateness.len()),
            "{}",
            r.lateness.len()
        );
        assert_eq!(r.cycle.len(), 100);
        assert_eq!(r.cycle.name, "cycle");
        assert_eq!(r.lateness.name, "lateness");
        assert!(r.misses.misses <= r.samples);
    }

    #[test]
    fn a_late_wake_up_skips_the_deadlines_that_passed_and_misses_them() {
        let (t0, ts) = (1_000_000_000, 100_000);
        let mut m = MissCounter::default();
        let mut c = LatencyHist::new("cycle");
        let mut d = Vec::with_capacity(10);
        let at = (t0, ts, 10);
        // On time: the next deadline, no miss.
        assert_eq!(
            wake_up_covers(0, t0 + 30_000, at, &mut c, &mut m, &mut d),
            1
        );
        assert_eq!((m.misses, m.longest_run, c.len()), (0, 0, 1));
        // Woken for deadline 1 at t0 + 450 µs (3.5 periods late): deadlines 2, 3 and 4 have
        // passed and are not slept to; 1, 2 and 3 missed (t0 + 450 µs is after t_2, t_3, t_4),
        // 4 did not (its command is due at t_5 = t0 + 500 µs). Each is in the cycle
        // histogram with its own lateness: 350, 250, 150, 50 µs.
        assert_eq!(
            wake_up_covers(1, t0 + 450_000, at, &mut c, &mut m, &mut d),
            5
        );
        assert_eq!((m.misses, m.longest_run, c.len()), (3, 3, 5));
        // The same lateness per deadline, in order, for the catch-up model.
        assert_eq!(d, [30_000, 350_000, 250_000, 150_000, 50_000]);
        assert_eq!(
            (c.quantile_ns(1.0) / 1000, c.quantile_ns(0.0) / 1000),
            (350, 30)
        );
        // Exactly at the next deadline is not after it; the end of the run caps the skip.
        let mut m = MissCounter::default();
        assert_eq!(wake_up_covers(0, t0 + ts, at, &mut c, &mut m, &mut d), 2);
        assert_eq!(m.misses, 0);
        assert_eq!(
            wake_up_covers(8, t0 + 50 * ts, at, &mut c, &mut m, &mut d),
            10
        );
        assert_eq!(m.misses, 2);
    }

    #[test]
    fn inprocess_records_one_cycle_per_sample() {
        let spec = ChainSpec {
            scenario: testutil::kyslan(2000.0),
            seconds: 0.05,
            plant: NodeSpec::default(),
            observer: NodeSpec::default(),
            current_loop: NodeSpec::default(),
            speed_loop: NodeSpec::default(),
        };
        let r = run_inprocess(&spec).unwrap();
        assert_eq!(r.samples, 100);
        assert_eq!(r.cycle.len(), r.samples);
        assert_eq!(r.lateness.len(), r.samples);
        assert!(r.misses.misses <= r.samples);
    }

    #[test]
    fn bad_rates_and_durations_are_refused() {
        assert!(run_floor(0.0, 1.0, &NodeSpec::default(), true).is_err());
        assert!(run_floor(1000.0, f64::NAN, &NodeSpec::default(), true).is_err());
        assert!(run_floor(1000.0, -1.0, &NodeSpec::default(), true).is_err());
    }
}
