//! How cold a core's caches are when a task wakes on it: the host's share of a stage's step.
//!
//! A stage's step right after its wake-up reads its state, its inputs and its code from the
//! caches it left behind a sample earlier. Whether they are still there is up to the machine:
//! on a shared host another tenant may run on the same physical core while this one sleeps,
//! and every step then starts on cold caches (on a 2-vCPU VM the same build's steps ran 2.5–3.7
//! times slower in such hours; docs/measurements.md, "The same VM three hours later").
//!
//! [`after_sleep`] measures that directly: a periodic SCHED_FIFO timer on the plant's core
//! wakes every [`PERIOD_NS`], reads one byte on each of [`LINES`] pages (one cache line per
//! page), timed, and reads the same lines again at once (warm). The difference per line is
//! what the sleep cost the caches. A few ns per line means the core's caches were cleared
//! while it slept; a fraction of a ns means they held ([`CacheState`] says which).

use anyhow::Result;
use drivelab_runtime::rt::{now_ns, sleep_until_ns};
use serde::Serialize;

use crate::{apply_rt, in_fresh_thread, NodeSpec};

/// Lines read after each wake-up, one per page.
pub const LINES: usize = 64;
/// Distance between two lines read: a page and a line, so that they fall into different
/// cache sets as well as different pages.
const STRIDE: usize = 4096 + 64;
/// The timer's period, ns (a sample at 10 kHz).
pub const PERIOD_NS: u64 = 100_000;
/// Wake-ups per probe (0.2 s).
pub const WAKEUPS: usize = 2_000;

/// Below this many ns a line after a sleep, the caches held: the warm hours measured on this
/// VM type read +0.2 to +1.2 ns a line (docs/measurements.md, "The same VM three hours later"
/// and the VMs after it).
pub const HELD_BELOW_NS_PER_LINE: f64 = 1.5;
/// From this many ns a line, the lines came from memory: the cold hours read +6.6 to +7.4 ns
/// a line, and two probes in between (+1.6, +3.0) came with steps only partly slower.
pub const CLEARED_FROM_NS_PER_LINE: f64 = 5.0;

/// What a sleep did to the core's caches, by [`CacheProbe::extra_ns_per_line`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CacheState {
    /// Under [`HELD_BELOW_NS_PER_LINE`].
    Held,
    /// Between the two bounds.
    Partly,
    /// [`CLEARED_FROM_NS_PER_LINE`] or more.
    Cleared,
}

impl CacheState {
    /// The report's words for it.
    pub fn words(self) -> &'static str {
        match self {
            CacheState::Held => "the caches held while the core slept",
            CacheState::Partly => {
                "some lines came from memory: the caches were partly cleared while the core slept"
            }
            CacheState::Cleared => {
                "the lines came from memory: the host cleared the core's caches while it slept, \
                 and each stage then reads its own memory from there after its wake-up"
            }
        }
    }
}

/// What [`after_sleep`] found, ns for all [`LINES`] lines at the median wake-up.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct CacheProbe {
    /// The core measured.
    pub cpu: Option<usize>,
    /// Lines read per wake-up.
    pub lines: usize,
    /// Wake-ups measured.
    pub wakeups: usize,
    /// The first read after each sleep, p50, ns.
    pub after_sleep_ns: u64,
    /// The second read straight after it, p50, ns.
    pub warm_ns: u64,
}

impl CacheProbe {
    /// What the sleep added per line read, ns (negative within the clock's resolution).
    pub fn extra_ns_per_line(&self) -> f64 {
        (self.after_sleep_ns as f64 - self.warm_ns as f64) / self.lines as f64
    }

    /// Whether the caches held over the sleep, by the bounds above.
    pub fn state(&self) -> CacheState {
        let extra = self.extra_ns_per_line();
        if extra < HELD_BELOW_NS_PER_LINE {
            CacheState::Held
        } else if extra < CLEARED_FROM_NS_PER_LINE {
            CacheState::Partly
        } else {
            CacheState::Cleared
        }
    }

    /// One clause for the report, e.g. "41 ns against 30 ns warm (+0.2 ns a line)".
    pub fn clause(&self) -> String {
        format!(
            "{} ns against {} ns warm ({:+.1} ns a line)",
            self.after_sleep_ns,
            self.warm_ns,
            self.extra_ns_per_line()
        )
    }
}

/// The probe on `node`'s core at its SCHED_FIFO priority, memory locked, in a fresh thread
/// of this process (it restores nothing: the thread ends). Holds no CPU wake-up latency
/// request of its own: it measures under whatever the caller holds.
pub fn after_sleep(node: &NodeSpec) -> Result<CacheProbe> {
    let node = *node;
    in_fresh_thread("bench-cache", move || {
        let buf = vec![1u8; LINES * STRIDE];
        let mut after = vec![0u64; WAKEUPS];
        let mut warm = vec![0u64; WAKEUPS];
        apply_rt("cache probe", &node, true)?;
        let base = buf.as_ptr();
        let read_all = || {
            let mut sum = 0u8;
            for j in 0..LINES {
                // SAFETY: j * STRIDE < LINES * STRIDE = buf's length, and `buf` outlives
                // the closure; a volatile read so that every line is really read.
                sum = sum.wrapping_add(unsafe { std::ptr::read_volatile(base.add(j * STRIDE)) });
            }
            sum
        };
        let t0 = now_ns() + 1_000_000;
        let mut sum = 0u8;
        for i in 0..WAKEUPS {
            sleep_until_ns(t0 + i as u64 * PERIOD_NS);
            let a = now_ns();
            sum = sum.wrapping_add(read_all());
            let b = now_ns();
            sum = sum.wrapping_add(read_all());
            let c = now_ns();
            after[i] = b - a;
            warm[i] = c - b;
        }
        std::hint::black_box(sum);
        after.sort_unstable();
        warm.sort_unstable();
        Ok(CacheProbe {
            cpu: node.core,
            lines: LINES,
            wakeups: WAKEUPS,
            after_sleep_ns: after[WAKEUPS / 2],
            warm_ns: warm[WAKEUPS / 2],
        })
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_clause_gives_both_reads_and_the_difference_per_line() {
        let p = CacheProbe {
            cpu: Some(1),
            lines: 64,
            wakeups: 2000,
            after_sleep_ns: 326,
            warm_ns: 32,
        };
        assert_eq!(p.extra_ns_per_line(), 294.0 / 64.0);
        assert_eq!(p.clause(), "326 ns against 32 ns warm (+4.6 ns a line)");
        let warm = CacheProbe {
            after_sleep_ns: 30,
            warm_ns: 33,
            ..p
        };
        assert_eq!(warm.clause(), "30 ns against 33 ns warm (-0.0 ns a line)");
    }

    #[test]
    fn the_state_follows_the_extra_per_line_across_both_bounds() {
        let probe = |after_sleep_ns| CacheProbe {
            cpu: Some(1),
            lines: 64,
            wakeups: 2000,
            after_sleep_ns,
            warm_ns: 30,
        };
        // Probes measured on these VMs: +0.5 (warm), +3.0 (between), +7.2 (cold) ns a line.
        assert_eq!(probe(62).state(), CacheState::Held);
        assert_eq!(probe(222).state(), CacheState::Partly);
        assert_eq!(probe(491).state(), CacheState::Cleared);
        // At the bounds: 1.5 ns a line is 96 ns over 64 lines, 5.0 is 320 ns.
        assert_eq!(probe(30 + 95).state(), CacheState::Held);
        assert_eq!(probe(30 + 96).state(), CacheState::Partly);
        assert_eq!(probe(30 + 319).state(), CacheState::Partly);
        assert_eq!(probe(30 + 320).state(), CacheState::Cleared);
        // Faster after the sleep than warm (the clock's resolution): held.
        assert_eq!(probe(20).state(), CacheState::Held);
    }

    #[test]
    fn the_probe_measures_every_wake_up_without_real_time_settings() {
        // No core, no priority: it runs anywhere as a normal thread. How long the reads take
        // is the machine's (no bound is asserted), but both medians are of reads that took
        // place: reading 64 lines takes some nanoseconds, warm or not, and a wake-up left
        // unmeasured would count as 0 ns and, with half of them so, make the median 0.
        let p = after_sleep(&NodeSpec {
            core: None,
            priority: None,
        })
        .unwrap();
        assert_eq!(p.cpu, None);
        assert!(p.after_sleep_ns > 0 && p.warm_ns > 0, "{p:?}");
    }
}
