//! The restart policy as pure logic: given a child's history, whether the failure was
//! injected, whether it hosts the source, and the time, what the supervisor does.

use super::Restart;
use std::time::{Duration, Instant};

/// Restarts of one process after which the supervisor gives up on it.
pub const MAX_RESTARTS: u32 = 1000;
/// A process that crashed more than [`CRASH_LOOP_RESTARTS`] times within this window is in
/// a crash loop; until then a dead process is restarted at once. A death by an injected kill
/// is no crash: it never counts.
pub const CRASH_LOOP_WINDOW: Duration = Duration::from_secs(10);
/// Crashes within [`CRASH_LOOP_WINDOW`] that a process may have without a back-off.
pub const CRASH_LOOP_RESTARTS: usize = 5;
/// The first back-off of a crash loop; it doubles per further restart in the loop.
pub const BACKOFF_MIN: Duration = Duration::from_millis(100);
/// The longest back-off.
pub const BACKOFF_MAX: Duration = Duration::from_millis(1000);

/// What the policy knows of one child.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct History {
    /// Restarts so far.
    pub restarts: u32,
    /// The last [`CRASH_LOOP_RESTARTS`] crashes (deaths not caused by an injected kill),
    /// newest first.
    pub recent_crashes: [Option<Instant>; CRASH_LOOP_RESTARTS],
    /// Crashes in the present crash loop beyond the first (0 outside a loop).
    pub loop_depth: u32,
}

/// The policy's answer to a failure (an exit other than success).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Decision {
    /// Start it again (with `--rejoin`) at this time.
    RestartAt(Instant),
    /// Leave it dead; the rest of the drive goes on in its degraded mode.
    GiveUp,
    /// Without the source (the plant) there is no drive: stop the rest, not a failure.
    StopDrive,
    /// A failure that was not injected, and not restarted: the run fails.
    FailRun,
}

/// The supervisor's restart policy.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Policy {
    /// `--restart`.
    pub restart: Restart,
    /// Restarts of one process at the most.
    pub max_restarts: u32,
    /// A lockstep drive: a process that dies without an injected fault ends the run (it
    /// would die again at the same sample: a lockstep run is deterministic).
    pub lockstep: bool,
}

impl Policy {
    /// The policy of `--restart restart`, with [`MAX_RESTARTS`].
    pub fn new(restart: Restart, lockstep: bool) -> Self {
        Self {
            restart,
            max_restarts: MAX_RESTARTS,
            lockstep,
        }
    }

    /// Decides on a failure of a child with history `h` at `now`; `injected` when a fault was
    /// ever injected into it, `killed` when this death is an injected kill, `source` when it
    /// hosts the plant. A process is restarted at once, unless it is in a crash loop (more
    /// than [`CRASH_LOOP_RESTARTS`] crashes within [`CRASH_LOOP_WINDOW`]): then after a
    /// back-off of [`BACKOFF_MIN`], doubled per further crash in the loop, up to
    /// [`BACKOFF_MAX`].
    pub fn on_failure(
        &self,
        h: &mut History,
        injected: bool,
        killed: bool,
        source: bool,
        now: Instant,
    ) -> Decision {
        if self.lockstep && !injected {
            return Decision::FailRun;
        }
        if self.restart == Restart::Never || h.restarts >= self.max_restarts {
            return if !injected {
                Decision::FailRun
            } else if source {
                Decision::StopDrive
            } else {
                Decision::GiveUp
            };
        }
        if killed {
            return Decision::RestartAt(now);
        }
        let crash_loop = h.recent_crashes[CRASH_LOOP_RESTARTS - 1]
            .is_some_and(|t| now.duration_since(t) <= CRASH_LOOP_WINDOW);
        h.recent_crashes.rotate_right(1);
        h.recent_crashes[0] = Some(now);
        if !crash_loop {
            h.loop_depth = 0;
            return Decision::RestartAt(now);
        }
        let backoff = BACKOFF_MIN
            .saturating_mul(1 << h.loop_depth.min(7))
            .min(BACKOFF_MAX);
        h.loop_depth += 1;
        Decision::RestartAt(now + backoff)
    }
}

impl History {
    /// Records a restart.
    pub fn restarted(&mut self) {
        self.restarts += 1;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ms(n: u64) -> Duration {
        Duration::from_millis(n)
    }

    /// Crashes and restarts a child `n` times, each `gap` after the last restart; returns
    /// the back-offs, in ms.
    fn backoffs(p: &Policy, h: &mut History, t: &mut Instant, n: usize, gap: Duration) -> Vec<u64> {
        deaths(p, h, t, n, gap, false)
    }

    /// Like [`backoffs`], for deaths by an injected kill when `killed`.
    fn deaths(
        p: &Policy,
        h: &mut History,
        t: &mut Instant,
        n: usize,
        gap: Duration,
        killed: bool,
    ) -> Vec<u64> {
        (0..n)
            .map(|_| {
                *t += gap;
                let Decision::RestartAt(at) = p.on_failure(h, true, killed, false, *t) else {
                    panic!("no restart");
                };
                h.restarted();
                let b = at.duration_since(*t);
                *t = at;
                b.as_millis() as u64
            })
            .collect()
    }

    #[test]
    fn a_dead_process_restarts_at_once_until_a_crash_loop_then_backs_off_up_to_one_second() {
        let p = Policy::new(Restart::OnFailure, false);
        let (mut h, mut t) = (History::default(), Instant::now());
        // Five restarts in quick succession are no loop yet; the sixth within 10 s is.
        assert_eq!(
            backoffs(&p, &mut h, &mut t, 11, ms(5)),
            [0, 0, 0, 0, 0, 100, 200, 400, 800, 1000, 1000]
        );
        assert_eq!(h.restarts, 11);
        // Uninjected failures are restarted the same way.
        let mut h = History::default();
        assert_eq!(
            p.on_failure(&mut h, false, false, true, t),
            Decision::RestartAt(t)
        );
    }

    #[test]
    fn injected_kills_are_no_crashes_and_never_back_off() {
        let p = Policy::new(Restart::OnFailure, false);
        let (mut h, mut t) = (History::default(), Instant::now());
        assert!(deaths(&p, &mut h, &mut t, 50, ms(5), true)
            .iter()
            .all(|&b| b == 0));
        // Nor do they count towards a crash loop.
        assert_eq!(backoffs(&p, &mut h, &mut t, 6, ms(5)), [0, 0, 0, 0, 0, 100]);
    }

    #[test]
    fn the_loop_ends_when_the_fifth_last_restart_is_more_than_ten_seconds_old() {
        let p = Policy::new(Restart::OnFailure, false);
        let (mut h, mut t) = (History::default(), Instant::now());
        assert_eq!(
            backoffs(&p, &mut h, &mut t, 7, ms(1)),
            [0, 0, 0, 0, 0, 100, 200]
        );
        // 10 s after the last restart the fifth-last is older than the window: at once.
        assert_eq!(
            backoffs(&p, &mut h, &mut t, 1, CRASH_LOOP_WINDOW + ms(1)),
            [0]
        );
        // Kills 2.5 s apart (100 in 60 s of a random run) never make a loop: 5 in 10 s.
        let (mut h, mut t) = (History::default(), Instant::now());
        assert!(backoffs(&p, &mut h, &mut t, 20, ms(2500))
            .iter()
            .all(|&b| b == 0));
        // The fifth-last restart exactly 10 s ago: still inside the window; 1 ms later: out.
        let (mut h, mut t) = (History::default(), Instant::now());
        backoffs(&p, &mut h, &mut t, 5, ms(2500));
        assert_eq!(backoffs(&p, &mut h, &mut t, 1, ms(0)), [100]);
        let (mut h, mut t) = (History::default(), Instant::now());
        backoffs(&p, &mut h, &mut t, 5, ms(2500));
        assert_eq!(backoffs(&p, &mut h, &mut t, 1, ms(1)), [0]);
    }

    /// The decisions on one failure each of (injected ever, killed now, source), at `t`,
    /// each with a fresh history.
    fn decisions(p: &Policy, t: Instant, cases: &[(bool, bool, bool)]) -> Vec<Decision> {
        cases
            .iter()
            .map(|&(injected, killed, source)| {
                p.on_failure(&mut History::default(), injected, killed, source, t)
            })
            .collect()
    }

    #[test]
    fn never_restarts_and_only_an_injected_failure_is_not_a_failed_run() {
        let p = Policy::new(Restart::Never, false);
        let t = Instant::now();
        use Decision::*;
        assert_eq!(
            decisions(
                &p,
                t,
                &[
                    (false, false, false),
                    (false, false, true),
                    (true, true, false),
                    (true, true, true)
                ]
            ),
            // Without the plant there is no drive.
            [FailRun, FailRun, GiveUp, StopDrive]
        );
    }

    #[test]
    fn in_lockstep_a_death_that_was_not_injected_ends_the_run() {
        let p = Policy::new(Restart::OnFailure, true);
        let t = Instant::now();
        // An injected kill is restarted as in real time.
        assert_eq!(
            decisions(
                &p,
                t,
                &[
                    (false, false, false),
                    (false, false, true),
                    (true, true, false)
                ]
            ),
            [Decision::FailRun, Decision::FailRun, Decision::RestartAt(t)]
        );
    }

    #[test]
    fn after_max_restarts_the_policy_is_that_of_never() {
        let p = Policy {
            restart: Restart::OnFailure,
            max_restarts: 3,
            lockstep: false,
        };
        let (mut h, mut t) = (History::default(), Instant::now());
        assert_eq!(backoffs(&p, &mut h, &mut t, 3, ms(1)), [0, 0, 0]);
        let before = h;
        assert_eq!(p.on_failure(&mut h, true, true, false, t), Decision::GiveUp);
        assert_eq!(
            p.on_failure(&mut h, true, true, true, t),
            Decision::StopDrive
        );
        assert_eq!(
            p.on_failure(&mut h, false, false, false, t),
            Decision::FailRun
        );
        assert_eq!(h, before);
        assert_eq!(Policy::new(Restart::OnFailure, false).max_restarts, 1000);
    }
}
