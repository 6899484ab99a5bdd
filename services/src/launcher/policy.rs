//! The supervisor's policy as pure logic, apart from the processes: each child's life
//! ([`Life`]: its [`State`], what was injected into it, its restart [`History`]), the restart
//! decision on a failure ([`Policy`]: back-off, crash loop, restart limit) and when the run is
//! over ([`run_state`]). The supervisor feeds it what it saw (an injection asked for, a stop
//! that ran out, READY, an exit) and carries out what it answers (a signal, a restart).

use super::Restart;
use crate::faults::FaultKind;
use drivelab_runtime::telemetry::ProcState;
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

/// Where a child process is in its life.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum State {
    /// Running (and ready).
    Running,
    /// Restarted, not ready yet.
    AwaitingReady,
    /// Stopped by a fault until `until`; `awaiting_ready` when it was not ready yet.
    Frozen {
        /// When the stop ends.
        until: Instant,
        /// It had not said READY when it was stopped (and has not since).
        awaiting_ready: bool,
    },
    /// Dead, to be restarted at `at`.
    RestartPending {
        /// When.
        at: Instant,
    },
    /// Dead for good.
    Dead,
    /// Exited normally.
    Finished,
}

impl State {
    /// Its process exists (and may be waited for).
    pub fn alive(self) -> bool {
        matches!(
            self,
            Self::Running | Self::AwaitingReady | Self::Frozen { .. }
        )
    }

    /// It is coming up: to be restarted, or started and not READY yet (one dead for good
    /// or finished is not).
    pub fn coming_up(self) -> bool {
        matches!(self, Self::RestartPending { .. }) || self.awaiting_ready()
    }

    /// It has not said READY yet.
    pub fn awaiting_ready(self) -> bool {
        matches!(
            self,
            Self::AwaitingReady
                | Self::Frozen {
                    awaiting_ready: true,
                    ..
                }
        )
    }

    /// What the hub shows.
    pub fn proc_state(self) -> ProcState {
        match self {
            Self::Finished => ProcState::Finished,
            Self::Dead => ProcState::Dead,
            Self::RestartPending { .. } | Self::AwaitingReady => ProcState::Restarting,
            Self::Frozen {
                awaiting_ready: true,
                ..
            } => ProcState::Restarting,
            Self::Frozen { .. } => ProcState::Frozen,
            Self::Running => ProcState::Alive,
        }
    }
}

/// The answer to a fault asked for one child.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Injection {
    /// Not injected: faults need a real-time drive.
    Refused,
    /// Not injected: its process is not running, and what it is instead ("frozen by an
    /// earlier stop", "dead, to be restarted", "dead and not restarted", "finished").
    Skipped(&'static str),
    /// Send this signal to the process (SIGKILL or SIGSTOP).
    Signal(i32),
}

/// One child's life under the policy.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Life {
    /// Where it is.
    pub state: State,
    /// Its restarts and crashes.
    pub history: History,
    /// It hosts the source (the plant).
    pub source: bool,
    /// A fault was injected into it at some point.
    injected: bool,
    /// A kill was injected and its death not yet handled.
    kill_pending: bool,
}

impl Life {
    /// A child that has passed the start-up handshake.
    pub fn new(source: bool) -> Self {
        Self {
            state: State::Running,
            history: History::default(),
            source,
            injected: false,
            kill_pending: false,
        }
    }

    /// A fault of `kind` (a stop lasting `stop`) is asked for at `now`: whether to signal the
    /// process, and with what. Only a running (or restarted, not yet ready) process of a
    /// real-time drive is signalled; a stopped one is frozen until `now + stop`.
    pub fn inject(
        &mut self,
        kind: FaultKind,
        stop: Duration,
        now: Instant,
        realtime: bool,
    ) -> Injection {
        if !realtime {
            return Injection::Refused;
        }
        match self.state {
            State::Running | State::AwaitingReady => {}
            State::Frozen { .. } => return Injection::Skipped("frozen by an earlier stop"),
            State::RestartPending { .. } => return Injection::Skipped("dead, to be restarted"),
            State::Dead => return Injection::Skipped("dead and not restarted"),
            State::Finished => return Injection::Skipped("finished"),
        }
        if self.kill_pending {
            // Signalled already, its exit not reaped yet: one kill, one restart.
            return Injection::Skipped("killed by an earlier fault, its exit not seen yet");
        }
        self.injected = true;
        match kind {
            FaultKind::Kill => {
                self.kill_pending = true;
                Injection::Signal(libc::SIGKILL)
            }
            FaultKind::Stop => {
                self.state = State::Frozen {
                    until: now + stop,
                    awaiting_ready: self.state.awaiting_ready(),
                };
                Injection::Signal(libc::SIGSTOP)
            }
        }
    }

    /// True when a stop is over at `now` (its end included): the process is to be resumed
    /// (SIGCONT), and it is back where the stop found it (running or awaiting READY).
    pub fn resume_due(&mut self, now: Instant) -> bool {
        match self.state {
            State::Frozen {
                until,
                awaiting_ready,
            } if now >= until => {
                self.state = if awaiting_ready {
                    State::AwaitingReady
                } else {
                    State::Running
                };
                true
            }
            _ => false,
        }
    }

    /// The drive ended during a stop: true when it was stopped, and it is to be resumed now
    /// (SIGCONT) so that it ends with the drive instead of being killed frozen.
    pub fn resume_at_end(&mut self) -> bool {
        match self.state {
            State::Frozen { until, .. } => self.resume_due(until),
            _ => false,
        }
    }

    /// It said READY (also while stopped: it stays stopped, as ready).
    pub fn ready(&mut self) {
        self.state = match self.state {
            State::Frozen { until, .. } => State::Frozen {
                until,
                awaiting_ready: false,
            },
            _ => State::Running,
        };
    }

    /// Its process exited at `now`: a success finishes it (None); on a failure, the
    /// policy's decision, and it is dead for good or waits for its restart.
    pub fn exited(&mut self, success: bool, policy: &Policy, now: Instant) -> Option<Decision> {
        if success {
            self.state = State::Finished;
            return None;
        }
        let killed = std::mem::take(&mut self.kill_pending);
        let d = policy.on_failure(&mut self.history, self.injected, killed, self.source, now);
        match d {
            Decision::GiveUp => self.state = State::Dead,
            Decision::RestartAt(at) => self.state = State::RestartPending { at },
            Decision::FailRun | Decision::StopDrive => {}
        }
        Some(d)
    }

    /// A kill was injected and its death not yet handled: the next exit is that death.
    pub fn kill_pending(&self) -> bool {
        self.kill_pending
    }

    /// Its restart is due at `now` (its time included).
    pub fn restart_due(&self, now: Instant) -> bool {
        matches!(self.state, State::RestartPending { at } if now >= at)
    }

    /// It was started again: it awaits READY. Returns its restarts so far, this one included.
    pub fn restarted(&mut self) -> u32 {
        self.history.restarted();
        self.state = State::AwaitingReady;
        self.history.restarts
    }
}

/// Where the run stands after a pass of the supervisor.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RunState {
    /// Go on supervising.
    Going,
    /// Every process has finished or is dead for good: the drive is over.
    Over,
    /// The plant has finished and nobody waits for a restart: the rest get a grace period
    /// to finish (the caller stops whoever has not).
    PlantFinished,
}

/// Where the run stands, from its children's lives.
pub fn run_state<'a>(lives: impl Iterator<Item = &'a Life> + Clone) -> RunState {
    let mut all = lives.clone();
    if all.all(|l| matches!(l.state, State::Finished | State::Dead)) {
        return RunState::Over;
    }
    let restart_pending = lives
        .clone()
        .any(|l| matches!(l.state, State::RestartPending { .. }));
    let plant_done = lives
        .clone()
        .any(|l| l.source && l.state == State::Finished);
    if plant_done && !restart_pending {
        RunState::PlantFinished
    } else {
        RunState::Going
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

    #[test]
    fn a_childs_state_says_whether_it_lives_awaits_ready_and_what_the_hub_shows() {
        let t = Instant::now();
        let frozen = |awaiting_ready| State::Frozen {
            until: t,
            awaiting_ready,
        };
        // (state, alive, awaiting READY, shown as)
        let table = [
            (State::Running, true, false, ProcState::Alive),
            (State::AwaitingReady, true, true, ProcState::Restarting),
            (frozen(false), true, false, ProcState::Frozen),
            // Stopped before it said READY: still restarting for the hub.
            (frozen(true), true, true, ProcState::Restarting),
            (
                State::RestartPending { at: t },
                false,
                false,
                ProcState::Restarting,
            ),
            (State::Dead, false, false, ProcState::Dead),
            (State::Finished, false, false, ProcState::Finished),
        ];
        for (st, alive, awaiting, shown) in table {
            assert_eq!(
                (st.alive(), st.awaiting_ready(), st.proc_state()),
                (alive, awaiting, shown),
                "{st:?}"
            );
        }
    }

    /// What a [`Life`] is told in a synthetic event stream, at a time in ms.
    #[derive(Debug, Clone, Copy)]
    enum Ev {
        /// A fault asked for (a stop lasting the ms given).
        Kill,
        Stop(u64),
        /// The supervisor's pass: a stop that ran out, a restart that is due.
        Tick,
        Ready,
        Crash,
        ExitOk,
    }

    /// Plays `stream` on `life` from `t0` (times in ms) in a real-time drive and returns what
    /// the supervisor would do or see, one word each: signals, resumes, restarts with their
    /// back-off in ms, the decisions that end something, and the state the hub shows.
    fn play(p: &Policy, life: &mut Life, t0: Instant, stream: &[(u64, Ev)]) -> Vec<String> {
        let mut out = Vec::new();
        for &(t_ms, ev) in stream {
            let now = t0 + ms(t_ms);
            let said = match ev {
                Ev::Kill | Ev::Stop(_) => {
                    let (kind, stop) = match ev {
                        Ev::Stop(d) => (FaultKind::Stop, ms(d)),
                        _ => (FaultKind::Kill, Duration::ZERO),
                    };
                    match life.inject(kind, stop, now, true) {
                        Injection::Signal(libc::SIGKILL) => "SIGKILL".to_string(),
                        Injection::Signal(libc::SIGSTOP) => "SIGSTOP".into(),
                        other => format!("{other:?}"),
                    }
                }
                Ev::Tick => {
                    let mut w = Vec::new();
                    if life.resume_due(now) {
                        w.push("SIGCONT".to_string());
                    }
                    if life.restart_due(now) {
                        w.push(format!("restart #{}", life.restarted()));
                    }
                    w.join(" ")
                }
                Ev::Ready => {
                    assert!(life.state.awaiting_ready(), "READY unasked at {t_ms} ms");
                    life.ready();
                    String::new()
                }
                Ev::Crash | Ev::ExitOk => match life.exited(matches!(ev, Ev::ExitOk), p, now) {
                    None => "finished".into(),
                    Some(Decision::RestartAt(at)) => {
                        format!("restart in {} ms", at.duration_since(now).as_millis())
                    }
                    Some(d) => format!("{d:?}"),
                },
            };
            out.push(format!("{said}|{}", life.state.proc_state().name()));
        }
        out
    }

    #[test]
    fn a_stop_freezes_until_its_end_included_and_resumes_where_it_found_the_process() {
        let p = Policy::new(Restart::OnFailure, false);
        let (t0, mut life) = (Instant::now(), Life::new(false));
        let seen = play(
            &p,
            &mut life,
            t0,
            &[
                (0, Ev::Stop(20)),
                // A second fault while frozen is skipped; the stop is not over 1 ms early.
                (5, Ev::Kill),
                (19, Ev::Tick),
                (20, Ev::Tick),
                (21, Ev::Tick),
            ],
        );
        assert_eq!(
            seen,
            [
                "SIGSTOP|frozen",
                "Skipped(\"frozen by an earlier stop\")|frozen",
                "|frozen",
                "SIGCONT|alive",
                "|alive"
            ]
        );
        // Stopped after a restart, before READY: it shows as restarting, READY while stopped
        // leaves it stopped, and it resumes ready.
        let seen = play(
            &p,
            &mut life,
            t0,
            &[
                (30, Ev::Kill),
                (31, Ev::Crash),
                (31, Ev::Tick),
                (32, Ev::Stop(10)),
                (35, Ev::Ready),
                (42, Ev::Tick),
            ],
        );
        assert_eq!(
            seen,
            [
                "SIGKILL|alive",
                "restart in 0 ms|restarting",
                "restart #1|restarting",
                "SIGSTOP|restarting",
                "|frozen",
                "SIGCONT|alive"
            ]
        );
        // Stopped before READY and resumed before it: awaiting READY again.
        let seen = play(
            &p,
            &mut life,
            t0,
            &[
                (50, Ev::Kill),
                (51, Ev::Crash),
                (51, Ev::Tick),
                (52, Ev::Stop(1)),
                (53, Ev::Tick),
            ],
        );
        assert_eq!(seen[4], "SIGCONT|restarting");
        assert_eq!(life.state, State::AwaitingReady);
    }

    #[test]
    fn faults_reach_only_a_running_or_restarting_process_of_a_real_time_drive() {
        let t = Instant::now();
        let (p, mut life) = (Policy::new(Restart::Never, false), Life::new(false));
        // Lockstep: refused, and nothing is recorded (a later failure is not injected).
        assert_eq!(
            life.inject(FaultKind::Kill, Duration::ZERO, t, false),
            Injection::Refused
        );
        assert_eq!(life, Life::new(false));
        assert_eq!(life.exited(false, &p, t), Some(Decision::FailRun));
        // Dead, waiting for a restart, finished, frozen: skipped, saying which, and unchanged.
        for (state, why) in [
            (State::Dead, "dead and not restarted"),
            (State::RestartPending { at: t }, "dead, to be restarted"),
            (State::Finished, "finished"),
            (
                State::Frozen {
                    until: t + ms(50),
                    awaiting_ready: false,
                },
                "frozen by an earlier stop",
            ),
        ] {
            let mut life = Life::new(false);
            life.state = state;
            let before = life;
            assert_eq!(
                life.inject(FaultKind::Stop, ms(5), t, true),
                Injection::Skipped(why)
            );
            assert_eq!(life, before);
        }
        // What holds the launcher's removed segments: a process coming up, not one gone.
        for (state, up) in [
            (State::RestartPending { at: t }, true),
            (State::AwaitingReady, true),
            (State::Running, false),
            (State::Dead, false),
            (State::Finished, false),
        ] {
            assert_eq!(state.coming_up(), up, "{state:?}");
        }
        // Killed, its exit not reaped yet: a second kill or a stop is not sent to it.
        let mut life = Life::new(false);
        assert_eq!(
            life.inject(FaultKind::Kill, Duration::ZERO, t, true),
            Injection::Signal(libc::SIGKILL)
        );
        let before = life;
        for kind in [FaultKind::Kill, FaultKind::Stop] {
            assert_eq!(
                life.inject(kind, ms(5), t, true),
                Injection::Skipped("killed by an earlier fault, its exit not seen yet")
            );
            assert_eq!(life, before);
        }
    }

    #[test]
    fn an_injected_kill_restarts_at_once_and_a_crash_after_it_is_a_crash() {
        let p = Policy::new(Restart::OnFailure, false);
        let (t0, mut life) = (Instant::now(), Life::new(false));
        // Twenty kills 1 ms apart: each restarted at once (no crash loop).
        let mut stream = Vec::new();
        for i in 0..20 {
            stream.extend([(i, Ev::Kill), (i, Ev::Crash), (i, Ev::Tick), (i, Ev::Ready)]);
        }
        let seen = play(&p, &mut life, t0, &stream);
        assert!(
            seen.chunks(4).all(|c| c[1] == "restart in 0 ms|restarting"),
            "{seen:?}"
        );
        assert_eq!(seen.last().unwrap(), "|alive");
        // A kill is consumed by the death it caused: six crashes after it are a crash loop.
        let mut crashes: Vec<(u64, Ev)> = (0..5)
            .flat_map(|i| {
                [
                    (100 + i, Ev::Crash),
                    (100 + i, Ev::Tick),
                    (100 + i, Ev::Ready),
                ]
            })
            .collect();
        crashes.push((105, Ev::Crash));
        let seen = play(&p, &mut life, t0, &crashes);
        let restarts: Vec<&str> = seen.iter().step_by(3).map(|s| s.as_str()).collect();
        assert_eq!(
            restarts,
            [
                "restart in 0 ms|restarting",
                "restart in 0 ms|restarting",
                "restart in 0 ms|restarting",
                "restart in 0 ms|restarting",
                "restart in 0 ms|restarting",
                "restart in 100 ms|restarting"
            ]
        );
        // The sixth restart waits its back-off: not due 1 ms early, due at its time.
        let seen = play(&p, &mut life, t0, &[(204, Ev::Tick), (205, Ev::Tick)]);
        assert_eq!(seen, ["|restarting", "restart #26|restarting"]);
    }

    #[test]
    fn at_the_restart_limit_a_process_dies_for_good_and_the_plant_stops_the_drive() {
        let p = Policy {
            restart: Restart::OnFailure,
            max_restarts: 2,
            lockstep: false,
        };
        let t0 = Instant::now();
        let stream = [
            (0, Ev::Kill),
            (0, Ev::Crash),
            (0, Ev::Tick),
            (1, Ev::Kill),
            (1, Ev::Crash),
            (1, Ev::Tick),
            (2, Ev::Kill),
            (2, Ev::Crash),
        ];
        let mut stage = Life::new(false);
        let seen = play(&p, &mut stage, t0, &stream);
        assert_eq!(seen[7], "GiveUp|dead");
        assert_eq!(stage.history.restarts, 2);
        let mut plant = Life::new(true);
        let seen = play(&p, &mut plant, t0, &stream);
        // The plant is left as it was (restarted, not yet ready): the supervisor ends the
        // drive.
        assert_eq!(seen[7], "StopDrive|restarting");
        // A crash that was never injected, at the limit: the run fails.
        let mut plain = Life::new(false);
        plain.history.restarts = 2;
        assert_eq!(plain.exited(false, &p, t0), Some(Decision::FailRun));
    }

    #[test]
    fn the_run_is_over_when_all_are_finished_or_dead_and_waits_for_a_pending_restart() {
        let t = Instant::now();
        let life = |source, state| Life {
            state,
            ..Life::new(source)
        };
        use State::*;
        // (plant, the other process, where the run stands)
        let table = [
            (Running, Running, RunState::Going),
            (Finished, Finished, RunState::Over),
            (Finished, Dead, RunState::Over),
            (Dead, Dead, RunState::Over),
            // The plant is done, the other still running: a grace period, then stopped.
            (Finished, Running, RunState::PlantFinished),
            (
                Finished,
                Frozen {
                    until: t,
                    awaiting_ready: false,
                },
                RunState::PlantFinished,
            ),
            // ... unless a restart is pending.
            (Finished, RestartPending { at: t }, RunState::Going),
            // Another process finished first: the plant goes on.
            (Running, Finished, RunState::Going),
        ];
        for (plant, other, want) in table {
            let lives = [life(true, plant), life(false, other)];
            assert_eq!(run_state(lives.iter()), want, "{plant:?}, {other:?}");
        }
        // An exit with success finishes a process, whatever was injected before.
        let p = Policy::new(Restart::OnFailure, false);
        let mut l = Life::new(true);
        let seen = play(&p, &mut l, t, &[(0, Ev::Kill), (0, Ev::ExitOk)]);
        assert_eq!(seen, ["SIGKILL|alive", "finished|finished"]);
    }
}
