//! The restart policy as pure logic: given a child's history, whether the failure was
//! injected, whether it hosts the source, and the time, what the supervisor does.

use super::Restart;
use std::time::{Duration, Instant};

/// Restarts of one process after which the supervisor gives up on it.
pub const MAX_RESTARTS: u32 = 1000;
/// The first back-off; it doubles per restart in quick succession.
pub const BACKOFF_MIN: Duration = Duration::from_millis(10);
/// The longest back-off.
pub const BACKOFF_MAX: Duration = Duration::from_millis(1000);
/// Time from a restart after which a failure counts as a first one again (back-off reset);
/// the reset needs strictly more than this.
pub const HEALTHY_AFTER: Duration = Duration::from_secs(2);

/// What the policy knows of one child.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct History {
    /// Restarts so far.
    pub restarts: u32,
    /// Back-off level of the next restart: the back-off is `BACKOFF_MIN · 2^level`, capped.
    pub backoff_level: u32,
    /// When it was last restarted.
    pub last_restart: Option<Instant>,
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
}

impl Policy {
    /// The policy of `--restart restart`, with [`MAX_RESTARTS`].
    pub fn new(restart: Restart) -> Self {
        Self {
            restart,
            max_restarts: MAX_RESTARTS,
        }
    }

    /// Decides on a failure of a child with history `h` at `now`; `injected` when a fault was
    /// ever injected into it, `source` when it hosts the plant. A restart raises the history's
    /// back-off level (after resetting it when the last restart is more than
    /// [`HEALTHY_AFTER`] ago).
    pub fn on_failure(
        &self,
        h: &mut History,
        injected: bool,
        source: bool,
        now: Instant,
    ) -> Decision {
        if self.restart == Restart::Never || h.restarts >= self.max_restarts {
            return if !injected {
                Decision::FailRun
            } else if source {
                Decision::StopDrive
            } else {
                Decision::GiveUp
            };
        }
        if h.last_restart
            .is_some_and(|t| now.duration_since(t) > HEALTHY_AFTER)
        {
            h.backoff_level = 0;
        }
        let backoff = BACKOFF_MIN
            .saturating_mul(1 << h.backoff_level.min(7))
            .min(BACKOFF_MAX);
        h.backoff_level += 1;
        Decision::RestartAt(now + backoff)
    }
}

impl History {
    /// Records a restart at `now`.
    pub fn restarted(&mut self, now: Instant) {
        self.restarts += 1;
        self.last_restart = Some(now);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ms(n: u64) -> Duration {
        Duration::from_millis(n)
    }

    /// Fails and restarts a child at once, `n` times, each `gap` after the last restart;
    /// returns the back-offs, in ms.
    fn backoffs(p: &Policy, h: &mut History, t: &mut Instant, n: usize, gap: Duration) -> Vec<u64> {
        (0..n)
            .map(|_| {
                *t += gap;
                let Decision::RestartAt(at) = p.on_failure(h, true, false, *t) else {
                    panic!("no restart");
                };
                h.restarted(at);
                let b = at.duration_since(*t);
                *t = at;
                b.as_millis() as u64
            })
            .collect()
    }

    #[test]
    fn the_back_off_doubles_per_quick_repeat_up_to_one_second() {
        let p = Policy::new(Restart::OnFailure);
        let (mut h, mut t) = (History::default(), Instant::now());
        assert_eq!(
            backoffs(&p, &mut h, &mut t, 10, ms(5)),
            [10, 20, 40, 80, 160, 320, 640, 1000, 1000, 1000]
        );
        assert_eq!(h.restarts, 10);
        // Uninjected failures are restarted the same way.
        let mut h = History::default();
        assert_eq!(
            p.on_failure(&mut h, false, true, t),
            Decision::RestartAt(t + ms(10))
        );
    }

    #[test]
    fn the_back_off_resets_after_more_than_two_seconds_of_good_health() {
        let p = Policy::new(Restart::OnFailure);
        let (mut h, mut t) = (History::default(), Instant::now());
        assert_eq!(backoffs(&p, &mut h, &mut t, 3, ms(1)), [10, 20, 40]);
        // Exactly 2 s after the last restart: still a quick repeat.
        assert_eq!(backoffs(&p, &mut h, &mut t, 1, HEALTHY_AFTER), [80]);
        // Just over 2 s: a first failure again.
        assert_eq!(
            backoffs(
                &p,
                &mut h,
                &mut t,
                2,
                HEALTHY_AFTER + Duration::from_nanos(1)
            ),
            [10, 10]
        );
        assert_eq!(backoffs(&p, &mut h, &mut t, 2, ms(100)), [20, 40]);
        assert_eq!(h.restarts, 8);
    }

    #[test]
    fn never_restarts_and_only_an_injected_failure_is_not_a_failed_run() {
        let p = Policy::new(Restart::Never);
        let t = Instant::now();
        let mut h = History::default();
        assert_eq!(p.on_failure(&mut h, false, false, t), Decision::FailRun);
        assert_eq!(p.on_failure(&mut h, false, true, t), Decision::FailRun);
        assert_eq!(p.on_failure(&mut h, true, false, t), Decision::GiveUp);
        // Without the plant there is no drive.
        assert_eq!(p.on_failure(&mut h, true, true, t), Decision::StopDrive);
        assert_eq!(h, History::default());
    }

    #[test]
    fn after_max_restarts_the_policy_is_that_of_never() {
        let p = Policy {
            restart: Restart::OnFailure,
            max_restarts: 3,
        };
        let (mut h, mut t) = (History::default(), Instant::now());
        assert_eq!(backoffs(&p, &mut h, &mut t, 3, ms(1)), [10, 20, 40]);
        let before = h;
        assert_eq!(p.on_failure(&mut h, true, false, t), Decision::GiveUp);
        assert_eq!(p.on_failure(&mut h, true, true, t), Decision::StopDrive);
        assert_eq!(p.on_failure(&mut h, false, false, t), Decision::FailRun);
        assert_eq!(h, before);
        assert_eq!(Policy::new(Restart::OnFailure).max_restarts, 1000);
    }
}
