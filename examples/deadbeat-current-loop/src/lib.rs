//! A user-written stage that replaces a built-in one: a deadbeat predictive current loop in
//! the place of the built-in `current-loop`.
//!
//! `Deadbeat` registers under the built-in's name, declares the built-in's inputs and its one
//! output (topic `cmd`), and so takes its place in the chain: the plant, the observer and the
//! speed loop stay the built-in ones, and the trace, the faults and the histograms work as
//! for the built-in. Its fallbacks are the built-in's: without an estimate the encoder's
//! angle (sensorless: the zero voltage); without a fresh current reference the last one,
//! flagged, with i_q* ramped to zero after two speed periods; `observer.mode = "monitor"`
//! controls on the encoder's angle. It uses the public stage API only; its host is
//! `src/main.rs`, one call to `drivelab_runtime::service::host_main`.
//!
//! The law. The plant applies command k on [t_{k+1}, t_{k+2}), so a command cannot act on the
//! sample it was computed from. Per axis of the rotor frame (the estimated angle), with the
//! cross-coupling and back-EMF terms c frozen over a sample, the machine is the first-order
//! RL circuit L·di/dt = u − R·i + c, which is exact sampled as
//!
//! i_{k+1} = a·i_k + b·(u + c),  a = e^{−R·T_s/L},  b = (1 − a)/R,
//!
//! with c_d = ω_e·L_q·i_q and c_q = −ω_e·(L_d·i_d + ψ_pm). The loop first predicts i_{k+1}
//! from i_k and the command now being applied (its own last one), then solves the model for
//! the command that takes i_{k+2} to i_{k+1} + λ·(i* − i_{k+1}). With λ = 1 (deadbeat) a
//! reference step is reached two samples after the loop takes it; with λ < 1 the error is
//! multiplied by (1 − λ) each sample after that, which trades speed for tolerance of a wrong
//! model.
//! The voltage vector is limited to V_dc/√3; there is no integrator, so nothing winds up.
//! The model is the controllers' motor (`[model]`, or the plant's without one).

use drivelab_control::motor::wrap_2pi;
use drivelab_control::observer_sensorless::ObserverMode;
use drivelab_control::transforms::{clarke, inverse_park, park, Dq};
use drivelab_runtime::config::Scenario;
use drivelab_runtime::messages::{CurrentRef, Header, VoltageCommand, FLAG_STALE_INPUT};
use drivelab_runtime::stage::{
    Diagnostics, Inbox, InputSpec, Msg, OnStale, Outbox, Rejoin, Stage, TopicId,
};
use drivelab_runtime::stages::ReferenceHold;

/// The stage's name: the built-in stage it replaces.
pub const NAME: &str = "current-loop";

/// The parameters `[stages.current-loop]` accepts.
pub const KEYS: [&str; 1] = ["lambda"];

/// A bad `[stages.current-loop]` parameter (one line).
#[derive(Debug, Clone, PartialEq)]
pub struct ParamError(pub String);

impl std::fmt::Display for ParamError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for ParamError {}

/// The built-in current loop's inputs: triggered by the estimate (stale after two samples:
/// the encoder angle then), with the measurement of the same sample and the speed loop's
/// newest current reference.
const INPUTS: &[InputSpec] = &[
    InputSpec::trigger(
        TopicId::Est,
        drivelab_runtime::stages::EST_MAX_AGE,
        OnStale::Fallback,
    ),
    InputSpec::latest(TopicId::Meas, 0, 0, OnStale::Required),
    InputSpec::latest(TopicId::Iref, 1, 0, OnStale::Fallback),
];

/// One axis of the sampled RL model: i_{k+1} = a·i_k + b·(u + c).
#[derive(Debug, Clone, Copy)]
struct Axis {
    a: f64,
    b: f64,
}

impl Axis {
    fn new(r_ohm: f64, l_h: f64, ts: f64) -> Self {
        let a = (-r_ohm * ts / l_h).exp();
        Self {
            a,
            b: (1.0 - a) / r_ohm,
        }
    }
}

/// Deadbeat predictive current control in the estimated rotor frame (see the module's text).
#[derive(Debug, Clone)]
pub struct Deadbeat {
    /// Fraction of the predicted current error removed per sample, 0 < λ ≤ 1.
    pub lambda: f64,
    d: Axis,
    q: Axis,
    l_d: f64,
    l_q: f64,
    psi: f64,
    pole_pairs: f64,
    ts: f64,
    u_max: f64,
    i_ref_max: f64,
    mode: ObserverMode,
    /// The command being applied now (this loop's last one), d/q V.
    u_prev: Dq,
    /// The current reference in force: the built-in's hold and ramp of a missing one.
    reference: ReferenceHold,
    last_k: Option<u64>,
    omega_m: f64,
    saturated_samples: u64,
    fallback_samples: u64,
}

impl Deadbeat {
    /// From the scenario's controller model and `[stages.current-loop]` (every parameter
    /// optional).
    pub fn new(sc: &Scenario) -> Result<Self, ParamError> {
        let table = sc.stages.get(NAME);
        if let Some(k) = table.and_then(|t| t.keys().find(|k| !KEYS.contains(&k.as_str()))) {
            return Err(ParamError(format!(
                "stages.{NAME}.{k}: unknown parameter (known: {})",
                KEYS.join(", ")
            )));
        }
        let lambda = match table.and_then(|t| t.get("lambda")) {
            None => 1.0,
            Some(v) => {
                let x = v.as_float().or_else(|| v.as_integer().map(|i| i as f64));
                match x {
                    Some(x) if x > 0.0 && x <= 1.0 => x,
                    _ => {
                        return Err(ParamError(format!(
                            "stages.{NAME}.lambda = {v} must be a number in (0, 1] (1: deadbeat)"
                        )))
                    }
                }
            }
        };
        let m = sc.motor_params();
        let ts = sc.rates.ts();
        Ok(Self {
            lambda,
            d: Axis::new(m.r_ohm, m.l_d_h, ts),
            q: Axis::new(m.r_ohm, m.l_q_h, ts),
            l_d: m.l_d_h,
            l_q: m.l_q_h,
            psi: m.psi_pm_wb,
            pole_pairs: m.p(),
            ts,
            u_max: sc.u_max(),
            // A reference from the bus never asks for more than the drive's own limits (or
            // the scenario's own reference steps).
            i_ref_max: sc
                .reference
                .i_d_a
                .iter()
                .chain(&sc.reference.i_q_a)
                .map(|s| s.value.abs())
                .fold(sc.i_q_max().max(m.i_max_a), f64::max),
            mode: sc.observer.mode,
            u_prev: Dq::default(),
            reference: ReferenceHold::new(sc),
            last_k: None,
            omega_m: 0.0,
            saturated_samples: 0,
            fallback_samples: 0,
        })
    }

    /// The frozen cross-coupling and back-EMF terms (c_d, c_q) at current `i`, V.
    fn coupling(&self, i: Dq, omega_e: f64) -> (f64, f64) {
        (
            omega_e * self.l_q * i.q,
            -omega_e * (self.l_d * i.d + self.psi),
        )
    }

    /// The model's current one sample after current `i` under voltage `u` at electrical speed
    /// `omega_e` (rad/s).
    pub fn predict(&self, i: Dq, u: Dq, omega_e: f64) -> Dq {
        let (cd, cq) = self.coupling(i, omega_e);
        Dq {
            d: self.d.a * i.d + self.d.b * (u.d + cd),
            q: self.q.a * i.q + self.q.b * (u.q + cq),
        }
    }

    /// The voltage for measured current `i` and reference `i_ref` (both in the rotor frame):
    /// predicts the next current under the command being applied, then solves for the one
    /// after it. Limited to the voltage limit; remembered as the command being applied next.
    pub fn command(&mut self, i: Dq, i_ref: Dq, omega_e: f64) -> Dq {
        let next = self.predict(i, self.u_prev, omega_e);
        let target = Dq {
            d: next.d + self.lambda * (i_ref.d - next.d),
            q: next.q + self.lambda * (i_ref.q - next.q),
        };
        let (cd, cq) = self.coupling(next, omega_e);
        let mut u = Dq {
            d: (target.d - self.d.a * next.d) / self.d.b - cd,
            q: (target.q - self.q.a * next.q) / self.q.b - cq,
        };
        let mag = u.d.hypot(u.q);
        if mag > self.u_max {
            self.saturated_samples += 1;
            u.d *= self.u_max / mag;
            u.q *= self.u_max / mag;
        }
        if !(u.d.is_finite() && u.q.is_finite()) {
            u = Dq::default();
        }
        self.u_prev = u;
        u
    }

    /// Reference `r` within the drive's limits.
    fn limited(&self, r: &CurrentRef) -> CurrentRef {
        let lim = self.i_ref_max;
        CurrentRef {
            i_d_ref: r.i_d_ref.clamp(-lim, lim),
            i_q_ref: r.i_q_ref.clamp(-lim, lim),
            ..*r
        }
    }
}

impl Stage for Deadbeat {
    fn name(&self) -> &'static str {
        NAME
    }
    fn inputs(&self) -> &'static [InputSpec] {
        INPUTS
    }
    fn outputs(&self) -> &'static [TopicId] {
        &[TopicId::Cmd]
    }
    fn step(&mut self, k: u64, inputs: &Inbox, out: &mut Outbox) {
        let Some(meas) = inputs.meas() else { return };
        let elapsed = self.last_k.map_or(1, |l| k.saturating_sub(l).max(1));
        self.last_k = Some(k);
        // On the encoder fallback a stale reference is held, not ramped (as the built-in:
        // the speed loop, without estimates, holds its output too).
        let mut flags = self.reference.take(inputs, inputs.est().is_some(), elapsed);
        let encoder = wrap_2pi(self.pole_pairs * meas.theta_m_enc);
        // Without a fresh estimate: the encoder's angle and the last speed (sensorless, no
        // encoder to fall back on: the zero voltage). Monitor mode controls on the encoder.
        let theta = match inputs.est() {
            Some(e) => {
                self.omega_m = e.omega_m;
                if self.mode == ObserverMode::Monitor {
                    encoder
                } else {
                    e.theta_e
                }
            }
            None => {
                self.fallback_samples += 1;
                flags |= FLAG_STALE_INPUT;
                encoder
            }
        };
        let omega_e = self.pole_pairs * self.omega_m;
        let i = park(clarke(meas.i_abc[0], meas.i_abc[1], meas.i_abc[2]), theta);
        let r = self.limited(self.reference.active());
        let u = if inputs.est().is_none() && self.mode == ObserverMode::Sensorless {
            self.u_prev = Dq::default();
            Dq::default()
        } else {
            self.command(
                i,
                Dq {
                    d: r.i_d_ref,
                    q: r.i_q_ref,
                },
                omega_e,
            )
        };
        // The command acts on [t_{k+1}, t_{k+2}); the plant turns it with the angle in the
        // middle of that interval: 1.5 samples on.
        let u_ab = inverse_park(u, theta + 1.5 * omega_e * self.ts);
        out.push(Msg::Cmd(VoltageCommand {
            hdr: Header {
                k,
                t_sample_ns: meas.hdr.t_sample_ns,
                flags,
                ..Default::default()
            },
            u_ab: [u_ab.alpha, u_ab.beta],
            u_dq: [u.d, u.q],
            i_dq_ref: [r.i_d_ref, r.i_q_ref],
            omega_ref: r.omega_ref,
            omega_hat: self.omega_m,
            theta_hat: wrap_2pi(theta),
        }));
    }
    fn rejoin(&mut self, _k: u64, inputs: &Inbox) -> Rejoin {
        // After a restart: the voltage the plant is applying is the command being applied,
        // seen in the rotor frame in the middle of the sample.
        let (Some(meas), Some(e)) = (inputs.meas(), inputs.est()) else {
            return Rejoin::NeedMore;
        };
        self.omega_m = e.omega_m;
        let mid = e.theta_e + 0.5 * self.pole_pairs * e.omega_m * self.ts;
        let u = drivelab_control::transforms::AlphaBeta {
            alpha: meas.u_ab_applied[0],
            beta: meas.u_ab_applied[1],
        };
        self.u_prev = park(u, mid);
        if let Some(r) = inputs.newest_iref() {
            self.reference.set(*r);
        }
        Rejoin::Done
    }
    fn diagnostic_names(&self) -> Diagnostics {
        &["voltage_limited_samples", "encoder_fallback_samples"]
    }
    fn diagnostics(&self, v: &mut [u64]) {
        for (d, s) in v
            .iter_mut()
            .zip([self.saturated_samples, self.fallback_samples])
        {
            *d = s;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use drivelab_control::motor::{Mechanics, MotorInput, MotorParams, MotorState, Rk4};

    fn scenario(params: &str) -> Scenario {
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/deadbeat.toml");
        let mut sc = Scenario::from_toml(&std::fs::read_to_string(path).unwrap(), path).unwrap();
        sc.stages
            .insert(NAME.into(), params.parse::<toml::Table>().unwrap());
        sc
    }

    fn dq(d: f64, q: f64) -> Dq {
        Dq { d, q }
    }

    /// RK4 sub-steps of the motor per sample. Four keep a sample within 1e-6 of i_max of
    /// the exact solution at a harder operating point (drivelab-control's motor tests); the
    /// error falls as h⁴, so sixteen leave ~1e-8 A.
    const SUBSTEPS: u32 = 16;

    /// Slack for the motor's integration error and rounding: 100× the ~1e-8 A above.
    const INTEGRATION_A: f64 = 1e-6;

    /// The motor model (RK4, drivelab-control's `motor`, at the prescribed electrical speed
    /// `omega_e`) over one sample from current `i` under voltage `u`, held in the rotor frame
    /// as the plant holds it: the current at the sample's end and the largest change of each
    /// axis's current within the sample (at the sub-steps).
    fn motor_sample(m: &MotorParams, ts: f64, i: Dq, u: Dq, omega_e: f64) -> (Dq, Dq) {
        let omega_m = omega_e / m.p();
        let input = MotorInput {
            u_d: u.d,
            u_q: u.q,
            ..Default::default()
        };
        let mut x = MotorState {
            i_d: i.d,
            i_q: i.q,
            omega_m,
            theta_m: 0.0,
        };
        let mut moved = dq(0.0, 0.0);
        for _ in 0..SUBSTEPS {
            x = Rk4 { substeps: 1 }.advance(
                m,
                Mechanics::PrescribedSpeed(omega_m),
                &x,
                &input,
                ts / f64::from(SUBSTEPS),
            );
            moved.d = moved.d.max((x.i_d - i.d).abs());
            moved.q = moved.q.max((x.i_q - i.q).abs());
        }
        (dq(x.i_d, x.i_q), moved)
    }

    /// What the predictor neglects in a sample in which each axis's current moved by at most
    /// `moved`: it freezes c_d = ω_e·L_q·i_q and c_q = −ω_e·(L_d·i_d + ψ) at the sample's
    /// start, but they follow the other axis's current. The error δ in i_x obeys
    /// L_x·dδ/dt = −R·δ + c_x(t) − c_x(0), so |δ(T_s)| ≤ T_s/L_x·|ω_e|·L_y·max|i_y(t) − i_y(0)|
    /// (twice the error for a current that ramps linearly over the sample). At constant speed
    /// nothing else is neglected: the RL part and the ψ term are sampled exactly.
    fn neglected(s: &Deadbeat, omega_e: f64, moved: Dq) -> Dq {
        let w = omega_e.abs() * s.ts;
        dq(w * s.l_q / s.l_d * moved.q, w * s.l_d / s.l_q * moved.d)
    }

    /// Runs the loop from rest against the motor model at electrical speed `omega_e`, the
    /// plant applying each command one sample late (command k acts on [t_{k+1}, t_{k+2})):
    /// the currents at samples 0..=n, and for each sample k → k+1 the bound on what the
    /// predictor neglects in it.
    fn on_the_motor(s: &mut Deadbeat, i_ref: Dq, omega_e: f64, n: usize) -> (Vec<Dq>, Vec<Dq>) {
        let m = scenario("").motor_params();
        let mut i = dq(0.0, 0.0);
        let mut applied = dq(0.0, 0.0);
        let (mut v, mut eps) = (vec![i], Vec::with_capacity(n));
        for _ in 0..n {
            let u = s.command(i, i_ref, omega_e);
            let (next, moved) = motor_sample(&m, s.ts, i, applied, omega_e);
            eps.push(neglected(s, omega_e, moved));
            i = next;
            applied = u;
            v.push(i);
        }
        (v, eps)
    }

    /// The error E = i* − i obeys E_{k+2} = (1 − λ)·E_{k+1} + ((1 − λ)·I − J)·ε_k − ε_{k+1},
    /// with ε_k what the predictor missed over sample k → k+1 (bounded by [`neglected`]) and
    /// J its Jacobian: diagonal a_x ∈ (0, 1), so |1 − λ − a_x| < 1, and off-diagonal at most
    /// T_s·|ω_e|·L_y/L_x. Checks that on both axes from sample 2 on, within that bound plus
    /// the integration slack.
    fn assert_error_recursion(s: &Deadbeat, i_ref: Dq, omega_e: f64, i: &[Dq], eps: &[Dq]) {
        let w = omega_e.abs() * s.ts;
        for k in 0..i.len() - 2 {
            let (e, f) = (eps[k], eps[k + 1]);
            let tol_d = e.d + w * s.l_q / s.l_d * e.q + f.d + INTEGRATION_A;
            let tol_q = e.q + w * s.l_d / s.l_q * e.d + f.q + INTEGRATION_A;
            for (r, x1, x2, tol) in [
                (i_ref.d, i[k + 1].d, i[k + 2].d, tol_d),
                (i_ref.q, i[k + 1].q, i[k + 2].q, tol_q),
            ] {
                let (e1, e2) = (r - x1, r - x2);
                assert!(
                    (e2 - (1.0 - s.lambda) * e1).abs() <= tol,
                    "sample {}: {e1} -> {e2}, allowed ±{tol}: {i:?}",
                    k + 2
                );
            }
        }
    }

    /// Deadbeat on the motor model at 350 rad/s electrical (the scenario's 70 rad/s), where
    /// the back-EMF (36 V) and the coupling terms (1.4 and 3.1 V per A of the other axis) move
    /// the current by more per sample than the tolerance: a wrong coupling would show. The error
    /// from sample 2 on is only what the predictor neglects over the two samples before it
    /// (see [`assert_error_recursion`] with λ = 1), and it vanishes once the current settles.
    #[test]
    fn deadbeat_reaches_a_step_two_samples_after_taking_it() {
        let mut s = Deadbeat::new(&scenario("")).unwrap();
        assert_eq!(s.lambda, 1.0);
        // At speed, both axes stepped (each axis's coupling is driven by the other's
        // current), within the voltage limit.
        let (omega_e, i_ref) = (350.0, dq(-0.5, 1.0));
        let (i, eps) = on_the_motor(&mut s, i_ref, omega_e, 12);
        // Sample 1 still feels the command applied at the step (zero).
        assert!((i[1].q - i_ref.q).abs() > 0.5, "{:?}", i[1]);
        assert_error_recursion(&s, i_ref, omega_e, &i, &eps);
        // Settled: the last check's tolerance (over-estimated here) is below what one sample of
        // the coupling at the reference moves the current (b_x·|c_x|), so a coupling wrong by
        // its own size fails.
        let last = eps[eps.len() - 2..]
            .iter()
            .fold(INTEGRATION_A, |t, e| t + 2.0 * e.d.max(e.q));
        let (cd, cq) = s.coupling(i_ref, omega_e);
        assert!(last < (s.d.b * cd.abs()).min(s.q.b * cq.abs()), "{last}");
        assert_eq!(s.saturated_samples, 0);
    }

    /// λ = 0.5 on the motor model at the same speed: from sample 2 on each error is half the
    /// one before, up to what the predictor neglects over the two samples before it (see
    /// [`assert_error_recursion`]).
    #[test]
    fn lambda_removes_that_fraction_of_the_error_per_sample() {
        let mut s = Deadbeat::new(&scenario("lambda = 0.5")).unwrap();
        let (omega_e, i_ref) = (350.0, dq(-0.5, 1.0));
        let (i, eps) = on_the_motor(&mut s, i_ref, omega_e, 12);
        assert_error_recursion(&s, i_ref, omega_e, &i, &eps);
        assert_eq!(s.saturated_samples, 0);
    }

    /// The predictor against the motor model over one sample at 350 rad/s electrical. At a
    /// steady state (the voltage that holds the current) the coupling does not move, so it
    /// is exact up to the integration slack, where a coupling wrong by its own size would be
    /// off by b_x·|c_x| (15 mA on d, 0.8 A on q). Under a voltage step that moves the
    /// currents by about 1 A it is within what it neglects ([`neglected`]).
    #[test]
    fn the_predictor_is_the_motor_over_a_sample_up_to_the_frozen_coupling() {
        let s = Deadbeat::new(&scenario("")).unwrap();
        let m = scenario("").motor_params();
        let (omega_e, i) = (350.0, dq(-0.5, 1.0));
        let (cd, cq) = s.coupling(i, omega_e);
        let hold = dq(m.r_ohm * i.d - cd, m.r_ohm * i.q - cq);
        let (x, _) = motor_sample(&m, s.ts, i, hold, omega_e);
        let p = s.predict(i, hold, omega_e);
        for (a, b) in [(x.d, i.d), (x.q, i.q), (p.d, i.d), (p.q, i.q)] {
            assert!((a - b).abs() <= INTEGRATION_A, "{x:?}, {p:?} vs {i:?}");
        }
        let u = dq(hold.d + 60.0, hold.q - 40.0);
        let (x, moved) = motor_sample(&m, s.ts, i, u, omega_e);
        let p = s.predict(i, u, omega_e);
        assert!(moved.d > 0.5 && moved.q > 0.5, "{moved:?}");
        let tol = neglected(&s, omega_e, moved);
        assert!((x.d - p.d).abs() <= tol.d + INTEGRATION_A, "{x:?} vs {p:?}");
        assert!((x.q - p.q).abs() <= tol.q + INTEGRATION_A, "{x:?} vs {p:?}");
    }

    #[test]
    fn the_voltage_is_limited_to_the_linear_range() {
        let mut s = Deadbeat::new(&scenario("")).unwrap();
        let u = s.command(dq(0.0, 0.0), dq(0.0, 100.0), 0.0);
        assert!((u.d.hypot(u.q) - s.u_max).abs() < 1e-9, "{u:?}");
        assert_eq!(s.saturated_samples, 1);
        let u = s.command(dq(f64::NAN, 0.0), dq(0.0, 1.0), 0.0);
        assert_eq!((u.d, u.q), (0.0, 0.0));
    }

    /// One step at k with the current reference `iref` (fresh) or none (stale), and an
    /// estimate; the command.
    fn step_at(s: &mut Deadbeat, k: u64, iref: Option<f64>) -> VoltageCommand {
        use drivelab_runtime::messages::{Estimate, Measurement};
        let hdr = Header {
            k,
            ..Default::default()
        };
        let mut ib = Inbox::default();
        ib.put(Msg::Meas(Measurement {
            hdr,
            ..Default::default()
        }));
        ib.put(Msg::Est(Estimate {
            hdr,
            ..Default::default()
        }));
        match iref {
            Some(q) => ib.put(Msg::Iref(CurrentRef {
                hdr,
                i_q_ref: q,
                ..Default::default()
            })),
            None => ib.set_stale(TopicId::Iref, 1),
        }
        let mut out = Outbox::default();
        s.step(k, &ib, &mut out);
        match out.get(TopicId::Cmd) {
            Some(Msg::Cmd(c)) => *c,
            other => panic!("no command: {other:?}"),
        }
    }

    #[test]
    fn without_a_reference_i_q_is_held_two_speed_periods_then_ramped_to_zero() {
        let mut s = Deadbeat::new(&scenario("")).unwrap();
        assert_eq!(step_at(&mut s, 0, Some(1.0)).i_dq_ref[1], 1.0);
        // Held, flagged, for two speed periods (20 samples at 10 kHz and 1 kHz) …
        for k in 1..=20 {
            let c = step_at(&mut s, k, None);
            assert_eq!(c.i_dq_ref[1], 1.0, "{k}");
            assert_eq!(c.hdr.flags, FLAG_STALE_INPUT);
        }
        // … then down by the i_q* limit (1.6 A) in 20 ms: 0.008 A a sample.
        let c = step_at(&mut s, 21, None);
        assert!((c.i_dq_ref[1] - (1.0 - 0.008)).abs() < 1e-12, "{c:?}");
        let c = step_at(&mut s, 30, None);
        assert!(
            (c.i_dq_ref[1] - (1.0 - 10.0 * 0.008)).abs() < 1e-12,
            "{c:?}"
        );
        // A fresh reference ends it.
        assert_eq!(step_at(&mut s, 31, Some(0.5)).i_dq_ref[1], 0.5);
    }

    #[test]
    fn bad_parameters_are_one_line_errors() {
        for (p, msg) in [
            (
                "lambda = 0",
                "stages.current-loop.lambda = 0 must be a number in (0, 1]",
            ),
            (
                "lambda = 1.5",
                "stages.current-loop.lambda = 1.5 must be a number in (0, 1]",
            ),
            (
                "lambda = nan",
                "stages.current-loop.lambda = nan must be a number in (0, 1]",
            ),
            (
                "lambda = \"x\"",
                "stages.current-loop.lambda = \"x\" must be a number",
            ),
            (
                "gain = 1.0",
                "stages.current-loop.gain: unknown parameter (known: lambda)",
            ),
        ] {
            let e = Deadbeat::new(&scenario(p)).unwrap_err().to_string();
            assert!(e.starts_with(msg), "{p}: {e}");
            assert!(!e.contains('\n'), "{e}");
        }
    }
}
