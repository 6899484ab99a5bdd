//! Settling a CPU's idle governor before a measurement without the CPU wake-up latency
//! request.
//!
//! While a request of 0 µs is held, an idle CPU polls instead of halting. Some governors keep
//! polling after the request is released: haltpoll (the governor of KVM guests) sets a poll
//! window the first time the CPU polls, and shrinks it only after the CPU has halted. A
//! periodic thread whose idle gaps are shorter than that window (a 20 kHz timer loop) never
//! lets the window expire, so it polls for as long as it runs, exactly as if the request were
//! still held: the "without request" measurement would measure the request.
//!
//! [`settle`] undoes that before such a measurement: a thread on the CPU sleeps 2 ms at a time
//! (longer than any poll window: at most a sixteenth of a scheduler tick, 0.625 ms at 100 Hz),
//! so every sleep lets the window expire and the CPU halt, until the CPU has gone
//! [`QUIET_SLEEPS`] sleeps without entering its polling state. A CPU that still polls after
//! [`MAX_SLEEPS`] has a request held by some other process. Without a polling state (no
//! cpuidle driver, or a platform without one) there is nothing to settle. See
//! docs/architecture.md, "Real-time rules" ("A released request can outlive itself").

use anyhow::{anyhow, Result};
use drivelab_runtime::rt::{setup_rt, RtPolicy, RtRequest};
use std::time::Duration;

/// Consecutive sleeps without a poll that show the governor has stopped polling.
pub const QUIET_SLEEPS: u32 = 5;
/// Sleeps after which a CPU that still polls is reported as such.
pub const MAX_SLEEPS: u32 = 100;
/// One sleep: longer than any poll window of the kernel's idle polling.
pub const SLEEP: Duration = Duration::from_millis(2);

/// What [`settle`] found.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Settle {
    /// The CPU has no polling idle state to settle.
    NoPollState,
    /// The CPU stopped polling; `sleeps` sleeps were taken (the quiet ones included).
    Settled { sleeps: u32 },
    /// The CPU still entered its polling state after [`MAX_SLEEPS`] sleeps.
    StillPolling,
}

/// Settles `cpu`'s idle governor (see the module's text), from a thread of this process pinned
/// to `cpu` at normal priority. Call it only while this process holds no CPU latency request.
pub fn settle(cpu: usize) -> Result<Settle> {
    let Some(state) = poll_state_dir(cpu) else {
        return Ok(Settle::NoPollState);
    };
    crate::in_fresh_thread("bench-idle-settle", move || {
        let req = RtRequest {
            core: Some(cpu),
            fifo_priority: None,
            lock_memory: false,
            prefault_stack_bytes: 0,
        };
        setup_rt(&req, RtPolicy::Strict)
            .map_err(|e| anyhow!("settling cpu {cpu}'s idle governor: {e}"))?;
        let usage = format!("{state}/usage");
        let polls = || {
            std::fs::read_to_string(&usage)
                .ok()
                .and_then(|s| s.trim().parse().ok())
        };
        Ok(settle_with(
            polls,
            || std::thread::sleep(SLEEP),
            QUIET_SLEEPS,
            MAX_SLEEPS,
        ))
    })
}

/// The sysfs folder of `cpu`'s polling idle state (the one named `POLL`), if it has one.
fn poll_state_dir(cpu: usize) -> Option<String> {
    let base = format!("/sys/devices/system/cpu/cpu{cpu}/cpuidle");
    std::fs::read_dir(&base)
        .ok()?
        .filter_map(|e| e.ok())
        .map(|e| e.path())
        .find(|p| std::fs::read_to_string(p.join("name")).is_ok_and(|n| n.trim() == "POLL"))
        .map(|p| p.to_string_lossy().into_owned())
}

/// Sleeps until `quiet` consecutive sleeps pass without the poll count (`polls`, the polling
/// state's entries so far) growing, at most `max` sleeps. A count that cannot be read means
/// there is nothing to watch: [`Settle::NoPollState`].
fn settle_with(
    mut polls: impl FnMut() -> Option<u64>,
    mut sleep: impl FnMut(),
    quiet: u32,
    max: u32,
) -> Settle {
    let Some(mut last) = polls() else {
        return Settle::NoPollState;
    };
    let mut calm = 0;
    for sleeps in 1..=max {
        sleep();
        let Some(now) = polls() else {
            return Settle::NoPollState;
        };
        calm = if now == last { calm + 1 } else { 0 };
        last = now;
        if calm >= quiet {
            return Settle::Settled { sleeps };
        }
    }
    Settle::StillPolling
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::cell::Cell;

    /// A governor whose poll window halves at every sleep (every halt), as haltpoll's does
    /// after a request is released: it polls once per sleep until the window is gone.
    #[test]
    fn settles_once_the_cpu_sleeps_without_polling() {
        let window = Cell::new(62_500u64);
        let count = Cell::new(1_000u64);
        let polls = || Some(count.get());
        let sleep = || {
            if window.get() > 0 {
                count.set(count.get() + 1);
                window.set(window.get() / 2);
            }
        };
        // 62 500 ns halves to 0 in 16 sleeps, each with a poll; then 5 quiet ones.
        assert_eq!(
            settle_with(polls, sleep, 5, 100),
            Settle::Settled { sleeps: 21 }
        );
    }

    #[test]
    fn a_cpu_that_polls_at_every_sleep_is_reported() {
        let count = Cell::new(0u64);
        let polls = || Some(count.get());
        let sleep = || count.set(count.get() + 1);
        assert_eq!(settle_with(polls, sleep, 5, 100), Settle::StillPolling);
        assert_eq!(count.get(), 100, "it stops after the last sleep allowed");
    }

    #[test]
    fn a_poll_among_quiet_sleeps_starts_the_count_again() {
        // Polls at sleeps 3 and 7 only: quiet from sleep 8 on, settled after sleep 12.
        let n = Cell::new(0u32);
        let count = Cell::new(0u64);
        let sleep = || {
            n.set(n.get() + 1);
            if n.get() == 3 || n.get() == 7 {
                count.set(count.get() + 1);
            }
        };
        assert_eq!(
            settle_with(|| Some(count.get()), sleep, 5, 100),
            Settle::Settled { sleeps: 12 }
        );
    }

    #[test]
    fn without_a_readable_poll_count_there_is_nothing_to_settle() {
        let slept = Cell::new(0);
        assert_eq!(
            settle_with(|| None, || slept.set(slept.get() + 1), 5, 100),
            Settle::NoPollState
        );
        assert_eq!(slept.get(), 0);
    }
}
