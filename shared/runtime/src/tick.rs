//! The kernel's scheduler tick as `/proc/timer_list` shows it (root reads it): where each
//! CPU's tick falls, so that a real-time schedule can start on its own CPU's tick and `drivelab
//! doctor` can say where the ticks are (docs/architecture.md, "The tick and the samples").
//!
//! A CPU's tick expires on a fixed grid of CLOCK_MONOTONIC for the whole uptime: every period
//! (1 / CONFIG_HZ) from a start that is the same on every CPU, or offset per CPU by
//! `skew_tick=1`. A tick stopped on an idle CPU restarts on the same grid. So one expiry, the
//! next one or the last before it stopped, gives the CPU's phase.

use std::path::Path;

/// The grid a tick-aligned schedule starts on: a millisecond. Every tick period of whole
/// milliseconds (CONFIG_HZ 1000, 250, 100) is a multiple of it.
pub const GRID_NS: u64 = 1_000_000;

/// Where the kernel shows its timers.
pub const TIMER_LIST: &str = "/proc/timer_list";

/// One CPU's scheduler tick as `/proc/timer_list` shows it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct CpuTick {
    /// The CPU.
    pub cpu: usize,
    /// Its next expiry, ns of CLOCK_MONOTONIC; None where its tick is not armed (stopped while
    /// the CPU idles).
    pub next_ns: Option<u64>,
    /// Its last expiry before it stopped (`.last_tick`), ns; None where not shown.
    pub last_ns: Option<u64>,
}

impl CpuTick {
    /// Where the tick falls past a whole millisecond, ns (0: on whole milliseconds): from its
    /// next expiry, or from its last one while it is stopped.
    pub fn phase_ns(&self) -> Option<u64> {
        self.next_ns.or(self.last_ns).map(|t| t % GRID_NS)
    }
}

/// Each CPU's tick in `/proc/timer_list`'s text: the first `tick_nohz_handler` timer
/// (`tick_sched_timer` before Linux 6.8) of its hrtimer bases and its `.last_tick`. The clock
/// event devices listed after "Tick Device:" repeat "cpu: N" and are not read.
pub fn parse(text: &str) -> Vec<CpuTick> {
    let mut out: Vec<CpuTick> = Vec::new();
    let mut tick_next = false;
    for line in text.lines() {
        let l = line.trim();
        if let Some(cpu) = l.strip_prefix("cpu: ").and_then(|c| c.trim().parse().ok()) {
            out.push(CpuTick {
                cpu,
                next_ns: None,
                last_ns: None,
            });
            tick_next = false;
        } else if l.contains(", tick_nohz_handler,") || l.contains(", tick_sched_timer,") {
            tick_next = out.last().is_some_and(|t| t.next_ns.is_none());
        } else if tick_next {
            tick_next = false;
            let soft = l
                .strip_prefix("# expires at ")
                .and_then(|r| r.split('-').next())
                .and_then(|v| v.trim().parse().ok());
            if let (Some(last), Some(ns)) = (out.last_mut(), soft) {
                last.next_ns = Some(ns);
            }
        } else if let Some(v) = l.strip_prefix(".last_tick") {
            let ns = v
                .trim_start_matches([' ', ':'])
                .split_whitespace()
                .next()
                .and_then(|v| v.parse::<u64>().ok())
                .filter(|ns| *ns > 0);
            if let Some(last) = out.last_mut() {
                last.last_ns = ns;
            }
        } else if l.starts_with("Tick Device:") {
            break;
        }
    }
    out
}

/// Where `cpu`'s tick falls past a whole millisecond, ns, read from `timer_list`; one line
/// that names the problem where it cannot be read.
pub fn phase_at(timer_list: &Path, cpu: usize) -> Result<u64, String> {
    let text = std::fs::read_to_string(timer_list)
        .map_err(|e| format!("cannot read {}: {e}", timer_list.display()))?;
    parse(&text)
        .iter()
        .find(|t| t.cpu == cpu)
        .and_then(CpuTick::phase_ns)
        .ok_or_else(|| format!("no tick of cpu{cpu} in {}", timer_list.display()))
}

/// Where `cpu`'s tick falls past a whole millisecond, ns ([`phase_at`] the kernel's list).
pub fn phase_of(cpu: usize) -> Result<u64, String> {
    phase_at(Path::new(TIMER_LIST), cpu)
}

/// The CPU the calling thread runs on now (its own, once pinned to one).
pub fn this_cpu() -> Option<usize> {
    // SAFETY: sched_getcpu takes no arguments and only returns a number (-1 on error).
    let c = unsafe { libc::sched_getcpu() };
    usize::try_from(c).ok()
}

/// The first instant at or after `earliest_ns` that is `phase_ns` past a whole millisecond: a
/// schedule that starts there, at a period that divides a millisecond, has a deadline at
/// every expiry of a tick of that phase and a period of whole milliseconds, which its own
/// timer interrupt then serves.
pub fn on_grid(earliest_ns: u64, phase_ns: u64) -> u64 {
    let phase = phase_ns % GRID_NS;
    phase + earliest_ns.saturating_sub(phase).div_ceil(GRID_NS) * GRID_NS
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `/proc/timer_list` as Linux 6.18 writes it, cut down: CPU 0's tick armed at `cpu0`
    /// (with another timer before it), CPU 1's at `cpu1` or not armed (`None`: idle), its
    /// last tick at `last1` (0: not shown).
    fn timer_list(cpu0: u64, cpu1: Option<u64>, last1: u64) -> String {
        let mut t = String::from(
            "Timer List Version: v0.10\nHRTIMER_MAX_CLOCK_BASES: 8\nnow at 98577976528 nsecs\n\n\
             cpu: 0\n clock 0:\n  .index:      0\nactive timers:\n \
             #0: <00000000aa>, hrtimer_wakeup, S:01\n \
             # expires at 98570000000-98570050000 nsecs [in 1 to 2 nsecs]\n",
        );
        t += &format!(
            " #1: <000000000c>, tick_nohz_handler, S:01\n # expires at {cpu0}-{cpu0} nsecs [in 2023472 to 2023472 nsecs]\n"
        );
        t += " #2: <000000004a>, watchdog_timer_fn, S:01\n # expires at 100240535679-100240535679 nsecs [in 1 to 1 nsecs]\n";
        t += "  .expires_next   : 98580000000 nsecs\n  .last_tick      : 98576000000 nsecs\n  .tick_stopped   : 0\n\n";
        t += "cpu: 1\n clock 0:\nactive timers:\n";
        if let Some(e) = cpu1 {
            t += &format!(" #0: <000000001b>, tick_nohz_handler, S:01\n # expires at {e}-{e} nsecs [in 1 to 1 nsecs]\n");
        }
        t += " #1: <0000000055>, dl_task_timer, S:01\n # expires at 99514017905-99514017905 nsecs [in 1 to 1 nsecs]\n";
        t += &format!("  .last_tick      : {last1} nsecs\n  .tick_stopped   : 1\n\n");
        // The clock event devices repeat "cpu: N" lines; they are not ticks.
        t += "Tick Device: mode:     1\nPer CPU device: 0\nClock Event Device: lapic-deadline\n \
              next_event:     98580000000 nsecs\n\ncpu: 0\n #0: <01>, tick_nohz_handler, S:01\n \
              # expires at 1-1 nsecs\n  .last_tick      : 7 nsecs\n";
        t
    }

    #[test]
    fn each_cpus_tick_is_read_with_its_last_expiry() {
        let ticks = parse(&timer_list(
            98_580_000_000,
            Some(98_584_500_000),
            98_000_500_000,
        ));
        assert_eq!(
            ticks,
            vec![
                CpuTick {
                    cpu: 0,
                    next_ns: Some(98_580_000_000),
                    last_ns: Some(98_576_000_000)
                },
                CpuTick {
                    cpu: 1,
                    next_ns: Some(98_584_500_000),
                    last_ns: Some(98_000_500_000)
                }
            ]
        );
        assert_eq!(ticks[0].phase_ns(), Some(0));
        assert_eq!(ticks[1].phase_ns(), Some(500_000));
        // Stopped on an idle CPU: its last tick gives the phase (it restarts on its grid).
        let idle = parse(&timer_list(98_580_000_000, None, 98_000_250_000));
        assert_eq!(idle[1].next_ns, None);
        assert_eq!(idle[1].phase_ns(), Some(250_000));
        // Before Linux 6.8 the tick's handler was tick_sched_timer.
        let old = timer_list(4_000_000, None, 0).replace("tick_nohz_handler", "tick_sched_timer");
        let old = parse(&old);
        assert_eq!(old[0].next_ns, Some(4_000_000));
        assert_eq!(old[1].phase_ns(), None, "no tick and no last one shown");
        assert_eq!(parse("cpu: x\n"), vec![]);
    }

    #[test]
    fn a_cpus_phase_is_read_from_the_file_or_the_reason_is_given() {
        let dir = std::env::temp_dir().join(format!("drivelab-tick-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let f = dir.join("timer_list");
        std::fs::write(&f, timer_list(98_580_000_000, Some(98_582_500_000), 0)).unwrap();
        assert_eq!(phase_at(&f, 0), Ok(0));
        assert_eq!(phase_at(&f, 1), Ok(500_000));
        assert_eq!(
            phase_at(&f, 2),
            Err(format!("no tick of cpu2 in {}", f.display()))
        );
        let missing = dir.join("none");
        assert!(phase_at(&missing, 0)
            .unwrap_err()
            .starts_with(&format!("cannot read {}: ", missing.display())));
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn a_schedule_on_the_grid_starts_at_the_ticks_phase() {
        assert_eq!(on_grid(0, 0), 0);
        assert_eq!(on_grid(1, 0), 1_000_000);
        assert_eq!(on_grid(1_000_000, 0), 1_000_000);
        assert_eq!(on_grid(4_597_988_000_001, 0), 4_597_989_000_000);
        // Half a millisecond past (skew_tick=1, CPU 1 of 4 at 250 Hz).
        assert_eq!(on_grid(4_597_988_000_001, 500_000), 4_597_988_500_000);
        assert_eq!(on_grid(4_597_988_500_000, 500_000), 4_597_988_500_000);
        assert_eq!(on_grid(4_597_988_500_001, 500_000), 4_597_989_500_000);
        assert_eq!(on_grid(3, 500_000), 500_000, "before the first: the first");
        assert_eq!(
            on_grid(3, 1_500_000),
            500_000,
            "a phase is within a millisecond"
        );
        // Every tick of a 4 ms period at that phase is then a deadline at 10 and 20 kHz,
        // where a schedule on whole milliseconds would meet none of them (skew_tick=1 at
        // 1000 Hz on 8 CPUs puts CPU 1's tick 62.5 µs past, CPU 2's 125 µs, CPU 4's 250 µs).
        for (phase, ts) in [(125_000, 100_000u64), (250_000, 100_000), (62_500, 50_000)] {
            let earliest = 98_577_976_528;
            let tick0 = 98_576_000_000 + phase; // a tick of that phase before the start
            let ticks = (1..20).map(|m| tick0 + m * 4_000_000);
            let meets = |t0: u64| {
                ticks
                    .clone()
                    .filter(|tick| *tick >= t0)
                    .all(|tick| (tick - t0).is_multiple_of(ts))
            };
            assert!(meets(on_grid(earliest, phase)), "{phase} {ts}");
            assert!(!meets(on_grid(earliest, 0)), "{phase} {ts}");
        }
    }
}
