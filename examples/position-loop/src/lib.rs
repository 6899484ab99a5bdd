//! A user-written stage: a position loop on top of the built-in speed loop.
//!
//! `PositionLoop` is triggered by the plant's measurement (topic `meas`), unwraps the encoder
//! angle and publishes a speed reference (topic `wref`) that the speed loop follows instead
//! of the scenario's speed profile. It uses the public stage API only; its host is
//! `src/main.rs`, one call to `drivelab_runtime::service::host_main`.

use drivelab_runtime::config::Scenario;
use drivelab_runtime::messages::{Header, SpeedRef, MAX_ABS_VALUE};
use drivelab_runtime::stage::{
    Diagnostics, Inbox, InputSpec, Msg, OnStale, Outbox, Rejoin, Stage, TopicId,
};
use std::f64::consts::{PI, TAU};

/// The stage's name, as in `[[process]] stages` and `[stages.position-loop]`.
pub const NAME: &str = "position-loop";

/// The parameters `[stages.position-loop]` accepts.
pub const KEYS: [&str; 5] = [
    "step_rad",
    "step_at_s",
    "rate_hz",
    "omega_max_rad_s",
    "kp_per_s",
];

/// A bad `[stages.position-loop]` parameter (one line).
#[derive(Debug, Clone, PartialEq)]
pub struct ParamError(pub String);

impl std::fmt::Display for ParamError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for ParamError {}

/// Position P controller with a speed limit: ω* = clamp(K_p·(θ* − θ), ±ω_max), θ* a step
/// from 0 to `step_rad` at `step_at_s`, θ the unwrapped encoder angle.
///
/// Gain: the speed loop is designed for a rise time t_r (`speed_loop.rise_time_s`), i.e. a
/// closed-loop bandwidth of roughly 2/t_r. The default K_p = 1/(4·t_r) puts the position
/// loop's crossover (≈ K_p) about 8× below it, so the speed loop looks like a unity gain to
/// the position loop and the P loop settles like a first-order lag of time constant 1/K_p
/// (32 ms for t_r = 8 ms), without overshoot from the cascade.
///
/// Unwrapping takes the shortest way between two runs of the stage, so it needs
/// |ω|·(divider·T_s) < π (3141 rad/s at 1 kHz). A host that has fallen behind in real time
/// publishes only the newest sample; so that the unwrapping still sees every measurement it
/// holds, the stage steps every sample ([`Stage::steps_every_sample`]): without it, a
/// standby twin one priority below, behind on a busy core, went 80 ms without a step while
/// the motor turned 7.6 rad, and counted one turn too few.
///
/// Restart: the encoder gives the angle within a turn only, so a fresh instance would count
/// its turns from 0 and drive the missing ones again. Each output carries the unwrapped
/// position θ it measured (`SpeedRef::theta_m`); a restarted instance reads its own last
/// output (a rejoin-only input on `wref`, its own output topic) and takes the turn count
/// that puts the encoder angle nearest to it ([`turns_from`]).
#[derive(Debug, Clone)]
pub struct PositionLoop {
    divider: u64,
    ts: f64,
    /// Position gain K_p, 1/s.
    pub kp: f64,
    /// Speed limit ω_max, mechanical rad/s.
    pub omega_max: f64,
    step_rad: f64,
    step_at_s: f64,
    omega_rated: f64,
    /// The run's length, s: a step at or after it is never taken.
    duration_s: f64,
    last_enc: Option<f64>,
    theta: f64,
    /// Rejoins whose turn count was ambiguous (the encoder angle about half a turn from the
    /// last published position).
    ambiguous_rejoins: u64,
}

const INPUTS: &[InputSpec] = &[
    InputSpec::trigger(TopicId::Meas, 1, OnStale::Required),
    // Read while rejoining only: this stage's own last output, as the recorder saw it.
    InputSpec::rejoin(TopicId::Wref),
];

/// A rejoin's turn count is ambiguous when the encoder angle is within this of half a turn
/// from the last published position, rad.
pub const AMBIGUOUS_WITHIN_RAD: f64 = 0.1 * PI;

/// The unwrapped position nearest to `last` whose angle within a turn is `enc` (in
/// [0, 2π)): 2π·n + enc for the turn count n that puts it nearest to `last`, and whether
/// that choice is ambiguous (`enc` within [`AMBIGUOUS_WITHIN_RAD`] of half a turn from
/// `last`). Right while the motor turned less than half a turn (π) between the two
/// readings, i.e. during the downtime: the speed loop brings the drive to a standstill once
/// `wref` is lost for 2 periods, so that holds unless the drive ran fast (at the Kyslan
/// motor's rated 366.5 rad/s, half a turn takes 8.6 ms).
pub fn turns_from(last: f64, enc: f64) -> (f64, bool) {
    let n = ((last - enc) / TAU).round();
    let theta = n * TAU + enc;
    (theta, (theta - last).abs() > PI - AMBIGUOUS_WITHIN_RAD)
}

/// Which values a parameter may take (beyond being a finite number).
#[derive(Debug, Clone, Copy, PartialEq)]
enum Sign {
    Any,
    NotNegative,
    Positive,
}

impl PositionLoop {
    /// From `[stages.position-loop]` of `sc` (every parameter optional).
    pub fn new(sc: &Scenario) -> Result<Self, ParamError> {
        let table = sc.stages.get(NAME);
        if let Some(k) = table.and_then(|t| t.keys().find(|k| !KEYS.contains(&k.as_str()))) {
            return Err(ParamError(format!(
                "stages.{NAME}.{k}: unknown parameter (known: {})",
                KEYS.join(", ")
            )));
        }
        let get = |key: &str, default: f64, sign: Sign| -> Result<f64, ParamError> {
            let Some(v) = table.and_then(|t| t.get(key)) else {
                return Ok(default);
            };
            let x = v.as_float().or_else(|| v.as_integer().map(|i| i as f64));
            let bad = |why: &str| {
                let text = format!("stages.{NAME}.{key} = {v} {why}");
                Err(ParamError(
                    drivelab_runtime::text::readable_numbers(&text).into_owned(),
                ))
            };
            match x {
                None => bad("must be a number"),
                Some(x) if !x.is_finite() => bad("must be finite"),
                // Larger values would make messages every peer rejects: a drive that runs
                // and does nothing.
                Some(x) if x.abs() > MAX_ABS_VALUE => {
                    bad("must be at most 1e12 in magnitude (the largest value a message carries)")
                }
                Some(x) if sign != Sign::Any && x < 0.0 => bad("must not be negative"),
                Some(x) if sign == Sign::Positive && x == 0.0 => bad("must be greater than 0"),
                Some(x) => Ok(x),
            }
        };
        let omega_rated = sc.motor_params().omega_rated_rad_s;
        Ok(Self {
            // rate_hz is checked by the scenario (it must divide the sample rate).
            divider: sc
                .stage_divider(NAME)
                .unwrap_or(u64::from(sc.rates.speed_divider)),
            ts: sc.rates.ts(),
            kp: get(
                "kp_per_s",
                1.0 / (4.0 * sc.speed_loop.rise_time_s),
                Sign::Positive,
            )?,
            omega_max: get("omega_max_rad_s", 0.25 * omega_rated, Sign::Positive)?,
            // A step either way: the loop and its unwrapping are the same for both signs.
            step_rad: get("step_rad", 0.0, Sign::Any)?,
            step_at_s: get("step_at_s", 0.0, Sign::NotNegative)?,
            omega_rated,
            duration_s: sc.duration_s,
            last_enc: None,
            theta: 0.0,
            ambiguous_rejoins: 0,
        })
    }

    /// The position reference θ* at sample k, rad.
    pub fn theta_ref(&self, k: u64) -> f64 {
        if k as f64 * self.ts + 1e-12 >= self.step_at_s {
            self.step_rad
        } else {
            0.0
        }
    }

    /// The unwrapped position θ after the last step, rad.
    pub fn theta(&self) -> f64 {
        self.theta
    }
}

impl Stage for PositionLoop {
    fn name(&self) -> &'static str {
        NAME
    }
    fn inputs(&self) -> &'static [InputSpec] {
        INPUTS
    }
    fn outputs(&self) -> &'static [TopicId] {
        &[TopicId::Wref]
    }
    fn divider(&self) -> u64 {
        self.divider
    }
    fn steps_every_sample(&self) -> bool {
        // The unwrapping needs each measurement: see the type's documentation.
        true
    }
    fn step(&mut self, k: u64, inputs: &Inbox, out: &mut Outbox) {
        let Some(m) = inputs.meas() else { return };
        let enc = m.theta_m_enc;
        // Unwrap: add the shortest angle from the previous reading.
        if let Some(prev) = self.last_enc {
            self.theta += (enc - prev + PI).rem_euclid(TAU) - PI;
        } else {
            self.theta = enc;
        }
        self.last_enc = Some(enc);
        let theta_m_ref = self.theta_ref(k);
        let omega_ref =
            (self.kp * (theta_m_ref - self.theta)).clamp(-self.omega_max, self.omega_max);
        out.push(Msg::Wref(SpeedRef {
            hdr: Header {
                k,
                t_sample_ns: m.hdr.t_sample_ns,
                ..Default::default()
            },
            omega_ref,
            theta_m_ref,
            theta_m: self.theta,
        }));
    }
    fn rejoin(&mut self, _k: u64, inputs: &Inbox) -> Rejoin {
        // Its own last output: the turn count from the position it measured then. Without
        // one (it died before it published), the turns are counted from 0, as at the start.
        if let (Some(m), Some(w)) = (inputs.meas(), inputs.newest_wref()) {
            let (theta, ambiguous) = turns_from(w.theta_m, m.theta_m_enc);
            self.ambiguous_rejoins += u64::from(ambiguous);
            // step() unwraps from here: the first reading adds nothing.
            self.theta = theta;
            self.last_enc = Some(m.theta_m_enc);
        }
        Rejoin::Done
    }
    fn diagnostic_names(&self) -> Diagnostics {
        &["ambiguous_rejoins"]
    }
    fn diagnostics(&self, values: &mut [u64]) {
        values[0] = self.ambiguous_rejoins;
    }
    fn warnings(&self) -> Vec<String> {
        let mut w = Vec::new();
        if self.omega_max > self.omega_rated {
            w.push(format!(
                "stages.{NAME}.omega_max_rad_s = {} exceeds the motor's rated speed {:.1} rad/s",
                self.omega_max, self.omega_rated
            ));
        }
        if self.step_rad != 0.0 && self.step_at_s >= self.duration_s {
            w.push(format!(
                "stages.{NAME}.step_at_s = {} s is at or after the run's end ({} s): the position step is not taken",
                self.step_at_s, self.duration_s
            ));
        }
        w
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use drivelab_runtime::messages::Measurement;

    fn scenario(params: &str) -> Scenario {
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/position-step.toml");
        let mut sc = Scenario::from_toml(&std::fs::read_to_string(path).unwrap(), path).unwrap();
        sc.stages
            .insert(NAME.into(), params.parse::<toml::Table>().unwrap());
        sc
    }

    fn step(s: &mut PositionLoop, k: u64, enc: f64) -> SpeedRef {
        let mut ib = Inbox::default();
        ib.put(Msg::Meas(Measurement {
            hdr: Header {
                k,
                ..Default::default()
            },
            theta_m_enc: enc,
            ..Default::default()
        }));
        let mut out = Outbox::default();
        s.step(k, &ib, &mut out);
        match out.get(TopicId::Wref) {
            Some(Msg::Wref(w)) => *w,
            other => panic!("no wref: {other:?}"),
        }
    }

    #[test]
    fn a_step_at_or_after_the_run_s_end_is_named_in_a_warning() {
        let end = scenario("").duration_s;
        let warned = |params: &str| PositionLoop::new(&scenario(params)).unwrap().warnings();
        let late = warned(&format!("step_rad = 1.0\nstep_at_s = {end}"));
        assert_eq!(
            late,
            [format!(
                "stages.{NAME}.step_at_s = {end} s is at or after the run's end ({end} s): the position step is not taken"
            )]
        );
        assert_eq!(
            warned(&format!("step_rad = 1.0\nstep_at_s = {}", end * 0.5)),
            Vec::<String>::new()
        );
        // No step to take: nothing to warn about.
        assert_eq!(warned(&format!("step_at_s = {end}")), Vec::<String>::new());
    }

    #[test]
    fn unwraps_across_two_pi_both_ways() {
        let mut s = PositionLoop::new(&scenario("step_rad = 20.0")).unwrap();
        step(&mut s, 0, 6.2);
        step(&mut s, 10, 0.1);
        assert!((s.theta() - (TAU + 0.1)).abs() < 1e-12, "{}", s.theta());
        step(&mut s, 20, 6.0);
        assert!((s.theta() - 6.0).abs() < 1e-12, "{}", s.theta());
        // Many turns forward, 1 rad per run.
        let mut enc = 6.0;
        for i in 0..30 {
            enc = (enc + 1.0f64).rem_euclid(TAU);
            step(&mut s, 30 + 10 * i, enc);
        }
        assert!((s.theta() - 36.0).abs() < 1e-9, "{}", s.theta());
    }

    #[test]
    fn speed_reference_is_p_times_error_clamped() {
        let mut s = PositionLoop::new(&scenario(
            "step_rad = 6.0\nomega_max_rad_s = 50\nkp_per_s = 10.0",
        ))
        .unwrap();
        // Error 6 rad: 60 rad/s, clamped to 50.
        assert_eq!(step(&mut s, 0, 0.0).omega_ref, 50.0);
        // Error 3.5 rad: 35 rad/s; error 1 rad: 10 rad/s (readings less than π apart).
        let w = step(&mut s, 10, 2.5);
        assert!((w.omega_ref - 35.0).abs() < 1e-12, "{w:?}");
        let w = step(&mut s, 20, 5.0);
        assert!((w.omega_ref - 10.0).abs() < 1e-12, "{w:?}");
        assert_eq!(w.theta_m_ref, 6.0);
        assert_eq!(w.hdr.k, 20);
        // Past the target across 2π: at 10 rad, −40 rad/s; at 16 rad, clamped to −50.
        step(&mut s, 30, 7.5f64.rem_euclid(TAU));
        let w = step(&mut s, 40, 10f64.rem_euclid(TAU));
        assert!((w.omega_ref + 40.0).abs() < 1e-9, "{w:?}");
        step(&mut s, 50, 13f64.rem_euclid(TAU));
        let w = step(&mut s, 60, 16f64.rem_euclid(TAU));
        assert_eq!(w.omega_ref, -50.0);
    }

    #[test]
    fn a_rejoin_takes_the_turn_count_nearest_to_the_last_published_position() {
        // Last published 2 turns + 1 rad; the motor moved a little either way since.
        for (last, enc, want) in [
            (2.0 * TAU + 1.0, 1.2, 2.0 * TAU + 1.2),
            (2.0 * TAU + 1.0, 0.8, 2.0 * TAU + 0.8),
            // Across a turn boundary, forward and back.
            (2.0 * TAU + 6.2, 0.1, 3.0 * TAU + 0.1),
            (3.0 * TAU + 0.1, 6.2, 2.0 * TAU + 6.2),
            // Below 0.
            (-TAU + 0.5, 0.4, -TAU + 0.4),
            (0.0, 6.0, 6.0 - TAU),
        ] {
            let (theta, ambiguous) = turns_from(last, enc);
            assert!((theta - want).abs() < 1e-12, "{last} {enc}: {theta}");
            assert!(!ambiguous, "{last} {enc}");
        }
        // Half a turn away: either count is as near, so the choice is flagged.
        assert!(turns_from(TAU + 0.1, 0.1 + PI).1);
        assert!(turns_from(TAU + 0.1, 0.1 + PI - 0.05).1);
        assert!(!turns_from(TAU + 0.1, 0.1 + PI - 0.5).1);
    }

    #[test]
    fn a_restarted_loop_takes_over_from_its_last_output_not_from_turn_zero() {
        let sc = scenario("step_rad = 12.566370614359172\nkp_per_s = 10.0");
        let mut s = PositionLoop::new(&sc).unwrap();
        let mut ib = Inbox::default();
        ib.put(Msg::Meas(Measurement {
            theta_m_enc: 1.0,
            ..Default::default()
        }));
        ib.put(Msg::Wref(SpeedRef {
            theta_m: TAU + 0.9,
            ..Default::default()
        }));
        assert_eq!(s.rejoin(100, &ib), Rejoin::Done);
        let w = step(&mut s, 100, 1.0);
        assert!((s.theta() - (TAU + 1.0)).abs() < 1e-12, "{}", s.theta());
        assert!((w.theta_m - (TAU + 1.0)).abs() < 1e-12, "{w:?}");
        assert!(
            (w.omega_ref - 10.0 * (2.0 * TAU - (TAU + 1.0))).abs() < 1e-9,
            "{w:?}"
        );
        let mut d = [9];
        s.diagnostics(&mut d);
        assert_eq!(d, [0]);
        // Without an output of its own to go by (it died before it published): from the
        // encoder angle, as at the start.
        let mut s = PositionLoop::new(&sc).unwrap();
        let mut ib = Inbox::default();
        ib.put(Msg::Meas(Measurement {
            theta_m_enc: 1.0,
            ..Default::default()
        }));
        assert_eq!(s.rejoin(100, &ib), Rejoin::Done);
        step(&mut s, 100, 1.0);
        assert_eq!(s.theta(), 1.0);
        // Half a turn from the last output: counted.
        let mut s = PositionLoop::new(&sc).unwrap();
        ib.put(Msg::Wref(SpeedRef {
            theta_m: 1.0 + PI,
            ..Default::default()
        }));
        s.rejoin(100, &ib);
        s.diagnostics(&mut d);
        assert_eq!(d, [1]);
    }

    #[test]
    fn the_step_comes_at_step_at_s() {
        // T_s = 100 µs: 10 ms is sample 100.
        let mut s = PositionLoop::new(&scenario("step_rad = 1.0\nstep_at_s = 0.01")).unwrap();
        assert_eq!(step(&mut s, 90, 0.0).theta_m_ref, 0.0);
        assert_eq!(step(&mut s, 90, 0.0).omega_ref, 0.0);
        assert_eq!(s.theta_ref(99), 0.0);
        let w = step(&mut s, 100, 0.0);
        assert_eq!(w.theta_m_ref, 1.0);
        assert!((w.omega_ref - s.kp).abs() < 1e-12, "{w:?}");
    }

    #[test]
    fn a_negative_step_drives_backwards_across_zero() {
        let mut s = PositionLoop::new(&scenario(
            "step_rad = -10.0\nomega_max_rad_s = 50\nkp_per_s = 10.0",
        ))
        .unwrap();
        assert_eq!(s.theta_ref(0), -10.0);
        // Error −10 rad: −100 rad/s, clamped to −50.
        assert_eq!(step(&mut s, 0, 0.0).omega_ref, -50.0);
        // Below 0 the encoder reads 2π − 2.5: unwrapped to −2.5 rad, error −7.5 rad.
        let w = step(&mut s, 10, TAU - 2.5);
        assert!((s.theta() + 2.5).abs() < 1e-12, "{}", s.theta());
        assert_eq!(w.omega_ref, -50.0);
        // Two turns down, near the target: −9.5 rad, error −0.5 rad: −5 rad/s.
        step(&mut s, 20, (-5.0f64).rem_euclid(TAU));
        step(&mut s, 30, (-7.5f64).rem_euclid(TAU));
        let w = step(&mut s, 40, (-9.5f64).rem_euclid(TAU));
        assert!((w.theta_m + 9.5).abs() < 1e-9, "{w:?}");
        assert!((w.omega_ref + 5.0).abs() < 1e-9, "{w:?}");
        assert_eq!(w.theta_m_ref, -10.0);
    }

    #[test]
    fn defaults_follow_the_speed_loop() {
        let mut sc = scenario("");
        sc.stages.clear();
        let s = PositionLoop::new(&sc).unwrap();
        assert!((s.kp - 1.0 / (4.0 * 0.008)).abs() < 1e-9);
        assert_eq!(s.divider(), u64::from(sc.rates.speed_divider));
        assert!(s.omega_max > 0.0 && s.omega_max < sc.motor_params().omega_rated_rad_s);
        assert_eq!(s.theta_ref(1_000_000), 0.0);
        let s = PositionLoop::new(&scenario("rate_hz = 2000")).unwrap();
        assert_eq!(s.divider(), 5);
    }

    #[test]
    fn bad_parameters_are_one_line_errors() {
        for (p, msg) in [
            (
                "step_rad = \"x\"",
                "stages.position-loop.step_rad = \"x\" must be a number",
            ),
            (
                "step_at_s = nan",
                "stages.position-loop.step_at_s = nan must be finite",
            ),
            (
                "kp_per_s = -2.0",
                "stages.position-loop.kp_per_s = -2.0 must not be negative",
            ),
            (
                "step_at_s = -0.5",
                "stages.position-loop.step_at_s = -0.5 must not be negative",
            ),
            (
                "omega_max_rad_s = 0",
                "stages.position-loop.omega_max_rad_s = 0 must be greater than 0",
            ),
            (
                "stepp_rad = 1.0",
                "stages.position-loop.stepp_rad: unknown parameter",
            ),
            (
                "step_rad = 1e308",
                "stages.position-loop.step_rad = 1e308 must be at most 1e12 in magnitude (the largest value a message carries)",
            ),
            (
                "omega_max_rad_s = 2e12",
                "stages.position-loop.omega_max_rad_s = 2000000000000.0 must be at most 1e12",
            ),
        ] {
            let e = PositionLoop::new(&scenario(p)).unwrap_err().to_string();
            assert!(e.starts_with(msg), "{p}: {e}");
            assert!(!e.contains('\n'), "{e}");
        }
    }
}
