//! A user-written stage: a position loop on top of the built-in speed loop.
//!
//! `PositionLoop` is triggered by the plant's measurement (topic `meas`), unwraps the encoder
//! angle and publishes a speed reference (topic `wref`) that the speed loop follows instead
//! of the scenario's speed profile. It uses the public stage API only; its host is
//! `src/main.rs`, one call to `drivelab_runtime::service::host_main`.

use drivelab_runtime::config::Scenario;
use drivelab_runtime::messages::{Header, SpeedRef};
use drivelab_runtime::stage::{Inbox, InputSpec, Msg, OnStale, Outbox, Stage, TopicId};
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
/// |ω|·(divider·T_s) < π (3141 rad/s at 1 kHz).
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
    last_enc: Option<f64>,
    theta: f64,
}

const INPUTS: &[InputSpec] = &[InputSpec::trigger(TopicId::Meas, 1, OnStale::Required)];

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
        let get = |key: &str, default: f64, positive: bool| -> Result<f64, ParamError> {
            let Some(v) = table.and_then(|t| t.get(key)) else {
                return Ok(default);
            };
            let x = v.as_float().or_else(|| v.as_integer().map(|i| i as f64));
            let bad = |why: &str| Err(ParamError(format!("stages.{NAME}.{key} = {v} {why}")));
            match x {
                None => bad("must be a number"),
                Some(x) if !x.is_finite() => bad("must be finite"),
                Some(x) if x < 0.0 => bad("must not be negative"),
                Some(x) if positive && x == 0.0 => bad("must be greater than 0"),
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
            kp: get("kp_per_s", 1.0 / (4.0 * sc.speed_loop.rise_time_s), true)?,
            omega_max: get("omega_max_rad_s", 0.25 * omega_rated, true)?,
            step_rad: get("step_rad", 0.0, false)?,
            step_at_s: get("step_at_s", 0.0, false)?,
            omega_rated,
            last_enc: None,
            theta: 0.0,
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
        }));
    }
    fn warnings(&self) -> Vec<String> {
        if self.omega_max > self.omega_rated {
            vec![format!(
                "{NAME}: omega_max_rad_s = {} exceeds the motor's rated speed {:.1} rad/s",
                self.omega_max, self.omega_rated
            )]
        } else {
            Vec::new()
        }
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
                "omega_max_rad_s = 0",
                "stages.position-loop.omega_max_rad_s = 0 must be greater than 0",
            ),
            (
                "stepp_rad = 1.0",
                "stages.position-loop.stepp_rad: unknown parameter",
            ),
        ] {
            let e = PositionLoop::new(&scenario(p)).unwrap_err().to_string();
            assert!(e.starts_with(msg), "{p}: {e}");
            assert!(!e.contains('\n'), "{e}");
        }
    }
}
