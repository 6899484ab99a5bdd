//! Bus faults injected by the stage hosts themselves, by sample index: a stage's outputs
//! published late (`delay`), messages of a topic not published (`drop`) or published with
//! unusable values (`corrupt`). The schedule travels in the scenario (`[[inject]]` tables,
//! written by the launcher from `--fault delay:…`, `drop:…`, `corrupt:…`), so every process,
//! a restarted one included, applies the same schedule, and a lockstep run with drop or
//! corrupt faults gives the same trace every time. See docs/architecture.md, "Fault model".

use crate::stage::{Msg, TopicId};
use serde::{Deserialize, Serialize};

/// Most `[[inject]]` entries in one scenario (the hosts keep them in preallocated tables).
pub const MAX_INJECT: usize = 16;
/// Shortest delay window, s (as a `stop`).
pub const DELAY_MIN_S: f64 = 0.001;
/// Longest delay window, s (as a `stop`).
pub const DELAY_MAX_S: f64 = 60.0;
/// Smallest added latency, µs.
pub const LATENCY_MIN_US: f64 = 1.0;
/// Shortest simulated restart of a killed stage in lockstep, s.
pub const RESTART_MIN_S: f64 = 0.001;
/// Longest simulated restart of a killed stage in lockstep, s.
pub const RESTART_MAX_S: f64 = 10.0;
/// Default simulated restart of a killed stage in lockstep, ms: close to the restart time
/// measured in real time (docs/architecture.md, "Fault model").
pub const RESTART_DEFAULT_MS: f64 = 40.0;
/// Largest added latency, µs (100 ms).
pub const LATENCY_MAX_US: f64 = 100_000.0;
/// Most messages one drop or corrupt fault removes or spoils.
pub const COUNT_MAX: u64 = 100_000;
/// The absurd but finite value every other corrupt message carries (the others carry NaN),
/// so that both checks of a receiver, finite and plausible magnitude, are exercised.
pub const CORRUPT_HUGE: f64 = 1e30;

/// Kinds of bus fault.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum InjectKind {
    /// The target stage's outputs are published `latency_us` late (real time only).
    Delay,
    /// The producer of the target topic does not publish `count` consecutive messages.
    Drop,
    /// `count` consecutive messages of the target topic carry NaN and 1e30 alternately.
    Corrupt,
    /// Lockstep only (written by the launcher from `--fault kill:…`): the target stage dies
    /// at `at_s`, its outputs are absent for `duration_s` (the simulated restart time), and
    /// a freshly built stage rejoins; `duration_s` 0 (or absent): it is never restarted
    /// ([`Inject::never_restarted`]).
    Kill,
    /// Lockstep only (from `--fault stop:…`): the target stage's outputs are absent for
    /// `duration_s`, then it resumes with its old state.
    Stop,
}

impl InjectKind {
    /// `delay`, `drop` or `corrupt`.
    pub fn name(self) -> &'static str {
        match self {
            InjectKind::Delay => "delay",
            InjectKind::Drop => "drop",
            InjectKind::Corrupt => "corrupt",
            InjectKind::Kill => "kill",
            InjectKind::Stop => "stop",
        }
    }

    /// True for the kinds that name a stage (delay, kill, stop) rather than a topic.
    pub fn on_stage(self) -> bool {
        matches!(
            self,
            InjectKind::Delay | InjectKind::Kill | InjectKind::Stop
        )
    }

    /// True for a lockstep kill or stop: the stage is down (outputs absent) in the window.
    pub fn downs_stage(self) -> bool {
        matches!(self, InjectKind::Kill | InjectKind::Stop)
    }
}

/// One `[[inject]]` table of a scenario.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Inject {
    /// `delay`, `drop` or `corrupt`.
    pub kind: InjectKind,
    /// `delay`, `kill`, `stop`: a stage name; `drop`, `corrupt`: a topic name (meas, est,
    /// iref, cmd, wref).
    pub target: String,
    /// First affected sample, as simulated seconds after sample 0 (rounded to a sample).
    pub at_s: f64,
    /// `delay`, `stop`: how long the window lasts, s; `kill`: the simulated restart time, s
    /// (0: never restarted).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub duration_s: f64,
    /// `delay`: the added latency before each output is published, µs.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub latency_us: f64,
    /// `drop`, `corrupt`: consecutive messages of the topic affected.
    #[serde(default, skip_serializing_if = "is_zero_u64")]
    pub count: u64,
}

fn is_zero(x: &f64) -> bool {
    *x == 0.0
}

fn is_zero_u64(x: &u64) -> bool {
    *x == 0
}

/// The topics a drop or corrupt fault may name: those a stage reads. `truth` feeds only the
/// recorder, which takes a hole in it for a plant downtime.
pub const TOPICS: [TopicId; 5] = [
    TopicId::Meas,
    TopicId::Est,
    TopicId::Iref,
    TopicId::Cmd,
    TopicId::Wref,
];

/// The topic named `name`, or a one-line error listing the valid ones.
pub fn topic(name: &str) -> Result<TopicId, String> {
    TOPICS
        .iter()
        .copied()
        .find(|t| t.name() == name)
        .ok_or_else(|| {
            format!(
                "unknown topic '{name}' (topics a stage reads: {})",
                TOPICS.map(|t| t.name()).join(", ")
            )
        })
}

/// The longest simulated restart a run of `duration_s` takes: [`RESTART_MAX_S`], or the
/// run's length in a longer run (a restart after the end).
pub fn restart_max_s(duration_s: f64) -> f64 {
    RESTART_MAX_S.max(duration_s)
}

impl Inject {
    /// A kill whose stage is never restarted: a restart time of 0 (`--restart never`).
    pub fn never_restarted(&self) -> bool {
        self.kind == InjectKind::Kill && self.duration_s == 0.0
    }

    /// `kind:target@at_s[:...]`, as on the command line.
    pub fn spec(&self) -> String {
        match self.kind {
            InjectKind::Delay => format!(
                "delay:{}@{}:{}:{}us",
                self.target, self.at_s, self.duration_s, self.latency_us
            ),
            InjectKind::Kill => format!("kill:{}@{}", self.target, self.at_s),
            InjectKind::Stop => format!("stop:{}@{}:{}", self.target, self.at_s, self.duration_s),
            k => format!("{}:{}@{}:{}", k.name(), self.target, self.at_s, self.count),
        }
    }

    /// Checks the entry's numbers and target form against a run of `duration_s`.
    pub fn validate(&self, duration_s: f64) -> Result<(), String> {
        let what = self.spec();
        if !(self.at_s.is_finite() && self.at_s >= 0.0 && self.at_s < duration_s) {
            return Err(format!(
                "inject {what}: at_s must be within [0, duration_s = {duration_s})"
            ));
        }
        if self.kind.on_stage() {
            let stage_form = !self.target.is_empty()
                && self
                    .target
                    .chars()
                    .all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == '-');
            if !stage_form {
                return Err(format!("inject {what}: '{}' is no stage name", self.target));
            }
        }
        match self.kind {
            InjectKind::Kill | InjectKind::Stop => {
                // A stage that is not restarted (`restart = "never"`) stays down for the
                // run's duration, however long the run.
                let (lo, hi, name, never) = if self.kind == InjectKind::Kill {
                    (
                        RESTART_MIN_S,
                        restart_max_s(duration_s),
                        "the simulated restart",
                        " (0: never restarted)",
                    )
                } else {
                    (DELAY_MIN_S, DELAY_MAX_S, "a stop", "")
                };
                if !(self.never_restarted() || (lo..=hi).contains(&self.duration_s)) {
                    return Err(format!("inject {what}: {name} lasts {lo} to {hi} s{never}"));
                }
                if self.count != 0 || self.latency_us != 0.0 {
                    return Err(format!(
                        "inject {what}: a {} takes no count or latency",
                        self.kind.name()
                    ));
                }
            }
            InjectKind::Delay => {
                if !(DELAY_MIN_S..=DELAY_MAX_S).contains(&self.duration_s) {
                    return Err(format!(
                        "inject {what}: a delay lasts {DELAY_MIN_S} to {DELAY_MAX_S} s"
                    ));
                }
                if !(LATENCY_MIN_US..=LATENCY_MAX_US).contains(&self.latency_us) {
                    return Err(format!(
                        "inject {what}: the latency must be {LATENCY_MIN_US} µs to 100 ms"
                    ));
                }
                if self.count != 0 {
                    return Err(format!("inject {what}: a delay takes no count"));
                }
            }
            InjectKind::Drop | InjectKind::Corrupt => {
                topic(&self.target).map_err(|e| format!("inject {what}: {e}"))?;
                if !(1..=COUNT_MAX).contains(&self.count) {
                    return Err(format!("inject {what}: count must be in 1..={COUNT_MAX}"));
                }
                if self.duration_s != 0.0 || self.latency_us != 0.0 {
                    return Err(format!(
                        "inject {what}: duration_s and latency_us are for delay only"
                    ));
                }
            }
        }
        Ok(())
    }
}

/// Checks every `[[inject]]` table of a scenario of `duration_s`.
pub fn validate(all: &[Inject], duration_s: f64) -> Result<(), String> {
    if all.len() > MAX_INJECT {
        return Err(format!(
            "{} [[inject]] tables: at most {MAX_INJECT}",
            all.len()
        ));
    }
    all.iter().try_for_each(|i| i.validate(duration_s))
}

/// An injection bound to a host: the sample indices it covers, [from_k, to_k).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Armed {
    /// Kind.
    pub kind: InjectKind,
    /// drop/corrupt: the topic.
    pub topic: Option<TopicId>,
    /// delay: the index of the stage in this host (None: not hosted here).
    pub stage: Option<usize>,
    /// First index covered.
    pub from_k: u64,
    /// First index after the window.
    pub to_k: u64,
    /// The producer's rate divider (drop/corrupt: messages are `divider` samples apart).
    pub divider: u64,
    /// delay: added latency, ns.
    pub latency_ns: u64,
}

impl Armed {
    /// Binds `i` for a host sampled at `sample_hz` whose stages are `stages` (names, chain
    /// order), with `divider(topic)` the producer's rate divider. drop/corrupt: the window
    /// starts at the first message of the topic at or after the sample of `at_s` and covers
    /// `count` messages.
    pub fn bind(
        i: &Inject,
        sample_hz: f64,
        stages: &[&str],
        divider: impl Fn(TopicId) -> u64,
    ) -> Self {
        let k0 = (i.at_s * sample_hz).round() as u64;
        match i.kind {
            InjectKind::Delay | InjectKind::Kill | InjectKind::Stop => Self {
                kind: i.kind,
                topic: None,
                stage: stages.iter().position(|s| *s == i.target),
                from_k: k0,
                to_k: if i.never_restarted() {
                    u64::MAX
                } else {
                    k0 + ((i.duration_s * sample_hz).round() as u64).max(1)
                },
                divider: 1,
                latency_ns: (i.latency_us * 1e3).round() as u64,
            },
            InjectKind::Drop | InjectKind::Corrupt => {
                let t = topic(&i.target).ok();
                let d = t.map_or(1, &divider).max(1);
                let from_k = k0.div_ceil(d) * d;
                Self {
                    kind: i.kind,
                    topic: t,
                    stage: None,
                    from_k,
                    to_k: from_k.saturating_add(i.count.saturating_mul(d)),
                    divider: d,
                    latency_ns: 0,
                }
            }
        }
    }

    /// True when sample index k is in the window.
    #[inline]
    pub fn covers(&self, k: u64) -> bool {
        (self.from_k..self.to_k).contains(&k)
    }

    /// True when message k of `topic` is one this drop or corrupt fault hits.
    #[inline]
    pub fn hits(&self, topic: TopicId, k: u64) -> bool {
        self.topic == Some(topic) && self.covers(k) && k.is_multiple_of(self.divider)
    }

    /// For a corrupt fault: the position of message k in the window (0, 1, ...).
    #[inline]
    pub fn nth(&self, k: u64) -> u64 {
        (k - self.from_k) / self.divider
    }
}

/// What a host saw of injection i (per stage; written to its statistics file).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize)]
pub struct InjectObs {
    /// Messages of the fault's topic and window this stage rejected (corrupt).
    pub rejected: u64,
    /// Source only, delay: commands of the window's samples that the source waited for.
    pub cycles: u64,
    /// Source only, delay: of those, commands not there at their deadline.
    pub misses: u64,
    /// Source only, delay: the longest cycle latency (t_k to command k published), ns.
    pub cycle_max_ns: u64,
}

/// Spoils message `m` for the `nth` message of a corrupt fault: every floating-point field
/// becomes NaN (even n) or [`CORRUPT_HUGE`] (odd n). The header is kept.
pub fn corrupt(m: &mut Msg, nth: u64) {
    let v = if nth.is_multiple_of(2) {
        f64::NAN
    } else {
        CORRUPT_HUGE
    };
    match m {
        Msg::Meas(x) => {
            x.i_abc = [v; 3];
            x.theta_m_enc = v;
            x.u_ab_applied = [v; 2];
        }
        Msg::Est(x) => {
            x.theta_e = v;
            x.omega_m = v;
        }
        Msg::Iref(x) => {
            x.omega_ref = v;
            x.i_d_ref = v;
            x.i_q_ref = v;
        }
        Msg::Cmd(x) => {
            x.u_ab = [v; 2];
            x.u_dq = [v; 2];
            x.i_dq_ref = [v; 2];
            x.omega_ref = v;
            x.omega_hat = v;
            x.theta_hat = v;
        }
        Msg::Wref(x) => {
            x.omega_ref = v;
            x.theta_m_ref = v;
            x.theta_m = v;
        }
        Msg::Truth(x) => {
            x.i_dq = [v; 2];
            x.omega_m = v;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::messages::VoltageCommand;

    fn drop_cmd(at_s: f64, count: u64) -> Inject {
        Inject {
            kind: InjectKind::Drop,
            target: "cmd".into(),
            at_s,
            duration_s: 0.0,
            latency_us: 0.0,
            count,
        }
    }

    #[test]
    fn windows_follow_the_producer_rate_and_round_to_a_sample() {
        // iref every 10 samples: 3 messages from the first multiple of 10 at or after 1234.
        let i = Inject {
            target: "iref".into(),
            ..drop_cmd(0.1234, 3)
        };
        let a = Armed::bind(&i, 10_000.0, &[], |_| 10);
        assert_eq!((a.from_k, a.to_k), (1240, 1270));
        assert!(a.hits(TopicId::Iref, 1260) && !a.hits(TopicId::Iref, 1265));
        assert!(!a.hits(TopicId::Iref, 1270) && !a.hits(TopicId::Cmd, 1240));
        assert_eq!(a.nth(1260), 2);
        let d = Inject {
            kind: InjectKind::Delay,
            target: "observer".into(),
            at_s: 0.5,
            duration_s: 0.01,
            latency_us: 300.0,
            count: 0,
        };
        let a = Armed::bind(&d, 10_000.0, &["plant", "observer"], |_| 1);
        assert_eq!(
            (a.stage, a.from_k, a.to_k, a.latency_ns),
            (Some(1), 5000, 5100, 300_000)
        );
        assert_eq!(Armed::bind(&d, 10_000.0, &["plant"], |_| 1).stage, None);
    }

    #[test]
    fn corrupt_messages_alternate_nan_and_huge_and_are_refused_by_the_check() {
        use crate::messages::Finite;
        let mut a = Msg::Cmd(VoltageCommand::default());
        let mut b = a;
        corrupt(&mut a, 0);
        corrupt(&mut b, 1);
        let (Msg::Cmd(a), Msg::Cmd(b)) = (a, b) else {
            unreachable!()
        };
        assert!(a.u_dq[0].is_nan() && b.u_dq[0] == CORRUPT_HUGE);
        assert!(!a.is_finite() && !b.is_finite());
    }

    #[test]
    fn bounds_are_one_line_errors() {
        assert!(validate(&[drop_cmd(0.1, 1)], 1.0).is_ok());
        let cases = [
            (drop_cmd(0.1, 0), "count must be in 1..=100000"),
            (drop_cmd(0.1, 100_001), "count must be in 1..=100000"),
            (drop_cmd(1.0, 1), "at_s must be within [0, duration_s = 1)"),
            (drop_cmd(f64::NAN, 1), "at_s must be within"),
            (
                Inject {
                    target: "truth".into(),
                    ..drop_cmd(0.1, 1)
                },
                "unknown topic 'truth' (topics a stage reads: meas, est, iref, cmd, wref)",
            ),
            (
                Inject {
                    kind: InjectKind::Delay,
                    target: "plant".into(),
                    duration_s: 0.5,
                    latency_us: 100_001.0,
                    ..drop_cmd(0.1, 0)
                },
                "the latency must be 1 µs to 100 ms",
            ),
            (
                Inject {
                    kind: InjectKind::Delay,
                    target: "plant".into(),
                    duration_s: 61.0,
                    latency_us: 10.0,
                    ..drop_cmd(0.1, 0)
                },
                "a delay lasts 0.001 to 60 s",
            ),
        ];
        for (i, want) in cases {
            let e = validate(&[i], 1.0).unwrap_err();
            assert!(e.contains(want) && !e.contains('\n'), "{e}");
        }
        // In a scenario file: checked with the rest, unknown keys refused.
        let path = concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../../scenarios/kyslan-pi.toml"
        );
        let text = std::fs::read_to_string(path).unwrap();
        let with = |t: &str| crate::config::Scenario::from_toml(&format!("{text}\n{t}"), path);
        let ok = with("[[inject]]\nkind = \"corrupt\"\ntarget = \"est\"\nat_s = 0.05\ncount = 3\n");
        assert_eq!(ok.unwrap().inject[0].spec(), "corrupt:est@0.05:3");
        for (bad, want) in [
            (
                "kind = \"drop\"\ntarget = \"cmd\"\nat_s = 0.05\ncount = 0",
                "count must be in",
            ),
            (
                "kind = \"drop\"\ntarget = \"cmd\"\nat_s = 0.05\nn = 3",
                "unknown field",
            ),
            (
                "kind = \"melt\"\ntarget = \"cmd\"\nat_s = 0.05",
                "unknown variant",
            ),
        ] {
            let e = with(&format!("[[inject]]\n{bad}\n")).unwrap_err();
            assert!(e.contains(want), "{bad}: {e}");
        }
        let down = |kind, duration_s| Inject {
            kind,
            target: "observer".into(),
            duration_s,
            ..drop_cmd(0.1, 0)
        };
        assert!(validate(
            &[down(InjectKind::Kill, 0.04), down(InjectKind::Stop, 60.0)],
            1.0
        )
        .is_ok());
        for (i, want) in [
            (
                down(InjectKind::Kill, 0.0005),
                "the simulated restart lasts 0.001 to 10 s",
            ),
            (
                down(InjectKind::Kill, 10.5),
                "the simulated restart lasts 0.001 to 10 s",
            ),
            (down(InjectKind::Stop, 61.0), "a stop lasts 0.001 to 60 s"),
            (
                Inject {
                    count: 3,
                    ..down(InjectKind::Stop, 0.01)
                },
                "a stop takes no count or latency",
            ),
            (
                Inject {
                    target: "Obs erver".into(),
                    ..down(InjectKind::Kill, 0.04)
                },
                "is no stage name",
            ),
        ] {
            let e = validate(&[i], 1.0).unwrap_err();
            assert!(e.contains(want) && !e.contains('\n'), "{e}");
        }
        let many = vec![drop_cmd(0.1, 1); MAX_INJECT + 1];
        assert!(validate(&many, 1.0).unwrap_err().contains("at most 16"));
    }
}
