//! The four services' step functions and the in-process runner.
//!
//! Per sample k (DESIGN.md "The cycle"):
//! 1. plant: take command k−1 (or hold / safe state), publish measurement k, integrate to t_{k+1};
//! 2. observer: measurement k → estimate k;
//! 3. current loop: measurement k + estimate k + the current reference computed at the last
//!    speed sample before k → command k (applied by the plant from t_{k+1});
//! 4. speed loop, when k mod N = 0: estimate k → current reference k (used from k+1 on).
//!
//! The in-process runner, the lockstep bus and the real-time bus all call these same functions
//! in this order, so their traces are bit-identical when no deadline is missed.

use crate::config::{profile_at, SafeState, Scenario, Step};
use crate::control::current::{CurrentInput, CurrentPiDesign, PiCurrentController, VoltageDq};
use crate::control::speed::{
    design_symmetrical_optimum, sum_of_small_time_constants, SoDesign, SoSpec, SpeedLoopModel,
    SpeedPi,
};
use crate::messages::*;
use crate::motor::{wrap_2pi, Mechanics, MotorInput, MotorParams, MotorState, Rk4};
use crate::observer::EncoderObserver;
use crate::trace::TraceRow;
use crate::transforms::{clarke, inverse_clarke, inverse_park, park, AlphaBeta, Dq};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use serde::Serialize;

/// Controller designs derived from a scenario (never hand-tuned per scenario).
#[derive(Debug, Clone, Serialize)]
pub struct DriveDesign {
    /// Current PI design.
    pub current: CurrentPiDesign,
    /// Speed PI design.
    pub speed: SoDesign,
}

impl DriveDesign {
    /// Designs the controllers from the scenario's motor, rates and targets.
    pub fn from_scenario(sc: &Scenario) -> Self {
        let m = sc.motor_params();
        let ts = sc.rates.ts();
        let current = CurrentPiDesign::new(&m, sc.current_loop.tau_c_s);
        let t_sigma = sum_of_small_time_constants(
            sc.current_loop.tau_c_s,
            ts,
            sc.observer.speed_filter_tau_s,
            sc.rates.speed_divider,
        );
        let model = SpeedLoopModel {
            ts,
            n: sc.rates.speed_divider,
            tau_c_s: sc.current_loop.tau_c_s,
            tau_f_s: sc.observer.speed_filter_tau_s,
        };
        let speed = design_symmetrical_optimum(
            &m,
            &SoSpec {
                t_sigma_s: t_sigma,
                rise_time_s: sc.speed_loop.rise_time_s,
            },
            &model,
        );
        Self { current, speed }
    }
}

/// Plant: PMSM model, inverter (DC-bus limit, hold and safe state) and sensors.
#[derive(Debug, Clone)]
pub struct Plant {
    m: MotorParams,
    mech: Mechanics,
    rk: Rk4,
    ts: f64,
    /// State at t_k.
    pub x: MotorState,
    u_max: f64,
    hold_samples: u32,
    safe_state: SafeState,
    load: Vec<Step>,
    encoder_counts: u32,
    noise: Option<(ChaCha8Rng, Normal<f64>)>,
    last_u_ab: [f64; 2],
    /// Consecutive samples without a fresh command.
    pub stale_run: u32,
    u_dq_applied: Dq,
    t_load: f64,
}

impl Plant {
    /// Builds the plant at rest (or at the prescribed speed).
    pub fn new(sc: &Scenario) -> Self {
        let m = sc.motor_params();
        let mech = match sc.mechanics.prescribed_speed_rad_s {
            Some(w) => Mechanics::PrescribedSpeed(w),
            None => Mechanics::Inertia,
        };
        let x = MotorState {
            omega_m: sc.mechanics.prescribed_speed_rad_s.unwrap_or(0.0),
            ..Default::default()
        };
        let noise = (sc.sensors.current_noise_a > 0.0).then(|| {
            (
                ChaCha8Rng::seed_from_u64(sc.sensors.seed),
                Normal::new(0.0, sc.sensors.current_noise_a).expect("validated std dev"),
            )
        });
        Self {
            m,
            mech,
            rk: Rk4 {
                substeps: sc.rates.plant_substeps,
            },
            ts: sc.rates.ts(),
            x,
            u_max: sc.u_max(),
            hold_samples: sc.inverter.hold_samples,
            safe_state: sc.inverter.safe_state,
            load: sc.load.torque_nm.clone(),
            encoder_counts: sc.sensors.encoder_counts_per_rev,
            noise,
            last_u_ab: [0.0; 2],
            stale_run: 0,
            u_dq_applied: Dq::default(),
            t_load: 0.0,
        }
    }

    /// Sample k: applies command k−1 (`None` if it did not arrive in time) on [t_k, t_{k+1}) and
    /// returns measurement k. For k = 0 pass `None`; it is not a miss.
    pub fn sample(&mut self, k: u64, cmd: Option<&VoltageCommand>) -> Measurement {
        let mut flags = 0;
        match cmd {
            Some(c) => {
                self.last_u_ab = c.u_ab;
                self.stale_run = 0;
            }
            None if k == 0 => {}
            None => {
                self.stale_run = self.stale_run.saturating_add(1);
                flags |= FLAG_STALE_CMD;
                if self.stale_run > self.hold_samples {
                    flags |= FLAG_SAFE_STATE;
                    match self.safe_state {
                        SafeState::ZeroVector => self.last_u_ab = [0.0; 2],
                    }
                }
            }
        }
        // Inverter: limit the voltage vector to the linear SVPWM range V_dc/√3.
        let mut u = AlphaBeta {
            alpha: self.last_u_ab[0],
            beta: self.last_u_ab[1],
        };
        let mag = (u.alpha * u.alpha + u.beta * u.beta).sqrt();
        if mag > self.u_max {
            u.alpha *= self.u_max / mag;
            u.beta *= self.u_max / mag;
        }
        let t = k as f64 * self.ts;
        self.t_load = profile_at(&self.load, t);
        let theta_e = self.x.theta_e(&self.m);
        // Zero-order hold in the rotor frame: the αβ vector is rotated with the mid-sample angle.
        let omega_e = self.m.p() * self.x.omega_m;
        self.u_dq_applied = park(u, theta_e + 0.5 * omega_e * self.ts);
        let i_ab = inverse_park(
            Dq {
                d: self.x.i_d,
                q: self.x.i_q,
            },
            theta_e,
        );
        let (mut ia, mut ib, mut ic) = inverse_clarke(i_ab);
        if let Some((rng, n)) = self.noise.as_mut() {
            ia += n.sample(rng);
            ib += n.sample(rng);
            ic += n.sample(rng);
        }
        let theta_m_enc = if self.encoder_counts > 0 {
            let step = std::f64::consts::TAU / f64::from(self.encoder_counts);
            (self.x.theta_m / step).floor() * step
        } else {
            self.x.theta_m
        };
        Measurement {
            hdr: Header {
                k,
                flags,
                ..Default::default()
            },
            i_abc: [ia, ib, ic],
            theta_m_enc,
            u_ab_applied: [u.alpha, u.beta],
            i_dq_true: [self.x.i_d, self.x.i_q],
            omega_m_true: self.x.omega_m,
            theta_e_true: theta_e,
            u_dq_applied: [self.u_dq_applied.d, self.u_dq_applied.q],
            t_load: self.t_load,
        }
    }

    /// Integrates the model from t_k to t_{k+1} with the voltage chosen by [`Plant::sample`].
    pub fn advance(&mut self) {
        let u = MotorInput {
            u_d: self.u_dq_applied.d,
            u_q: self.u_dq_applied.q,
            t_load: self.t_load,
        };
        self.x = self.rk.advance(&self.m, self.mech, &self.x, &u, self.ts);
    }
}

/// Observer service step (encoder mode).
#[derive(Debug, Clone)]
pub struct ObserverStep {
    enc: EncoderObserver,
}

impl ObserverStep {
    /// Builds the observer.
    pub fn new(sc: &Scenario) -> Self {
        let m = sc.motor_params();
        Self {
            enc: EncoderObserver::new(m.pole_pairs, sc.rates.ts(), sc.observer.speed_filter_tau_s),
        }
    }

    /// Measurement k → estimate k.
    pub fn step(&mut self, meas: &Measurement) -> Estimate {
        let e = self.enc.step(meas.theta_m_enc);
        Estimate {
            hdr: Header {
                k: meas.hdr.k,
                t_sample_ns: meas.hdr.t_sample_ns,
                ..Default::default()
            },
            theta_e: e.theta_e,
            omega_m: e.omega_m,
        }
    }
}

/// Speed-loop service step.
#[derive(Debug, Clone)]
pub struct SpeedLoopStep {
    ctrl: SpeedPi,
    divider: u64,
    ts: f64,
    speed_ref: Vec<Step>,
    i_d_ref: Vec<Step>,
}

impl SpeedLoopStep {
    /// Builds the speed loop from the scenario's design.
    pub fn new(sc: &Scenario) -> Self {
        let d = DriveDesign::from_scenario(sc);
        let n = sc.rates.speed_divider;
        Self {
            ctrl: SpeedPi::new(&d.speed, f64::from(n) * sc.rates.ts(), sc.i_q_max()),
            divider: u64::from(n),
            ts: sc.rates.ts(),
            speed_ref: sc.reference.speed_rad_s.clone(),
            i_d_ref: sc.reference.i_d_a.clone(),
        }
    }

    /// True when the speed loop runs at sample k.
    pub fn runs_at(&self, k: u64) -> bool {
        k % self.divider == 0
    }

    /// Estimate k → current reference k when k mod N = 0, else None.
    pub fn step(&mut self, est: &Estimate) -> Option<CurrentRef> {
        let k = est.hdr.k;
        if !self.runs_at(k) {
            return None;
        }
        let t = k as f64 * self.ts;
        let omega_ref = profile_at(&self.speed_ref, t);
        let i_q_ref = self.ctrl.step(omega_ref, est.omega_m);
        Some(CurrentRef {
            hdr: Header {
                k,
                t_sample_ns: est.hdr.t_sample_ns,
                ..Default::default()
            },
            omega_ref,
            i_d_ref: profile_at(&self.i_d_ref, t),
            i_q_ref,
        })
    }
}

/// Current-loop service step.
#[derive(Debug, Clone)]
pub struct CurrentLoopStep {
    ctrl: PiCurrentController,
    pole_pairs: f64,
    ts: f64,
    divider: u64,
}

impl CurrentLoopStep {
    /// Builds the current loop from the scenario's design.
    pub fn new(sc: &Scenario) -> Self {
        let m = sc.motor_params();
        let d = DriveDesign::from_scenario(sc);
        Self {
            ctrl: PiCurrentController::new(
                &m,
                &d.current,
                sc.rates.ts(),
                sc.u_max(),
                sc.current_loop.decoupling,
            ),
            pole_pairs: m.p(),
            ts: sc.rates.ts(),
            divider: u64::from(sc.rates.speed_divider),
        }
    }

    /// Index of the current reference the current loop must use at sample k: the one computed
    /// at the last speed sample strictly before k. None for k = 0 (zero references).
    pub fn expected_ref_index(&self, k: u64) -> Option<u64> {
        (k > 0).then(|| (k - 1) / self.divider * self.divider)
    }

    /// Measurement k + estimate k + current reference → command k.
    pub fn step(
        &mut self,
        meas: &Measurement,
        est: &Estimate,
        iref: &CurrentRef,
    ) -> VoltageCommand {
        let i_ab = clarke(meas.i_abc[0], meas.i_abc[1], meas.i_abc[2]);
        let i = park(i_ab, est.theta_e);
        let omega_e = self.pole_pairs * est.omega_m;
        let u: VoltageDq = self.ctrl.step(&CurrentInput {
            i_d_ref: iref.i_d_ref,
            i_q_ref: iref.i_q_ref,
            i_d: i.d,
            i_q: i.q,
            omega_e,
        });
        // The command acts on [t_{k+1}, t_{k+2}); the plant rotates it with the mid-sample
        // angle, so compensate 1.5 samples of rotation.
        let u_ab = inverse_park(
            Dq { d: u.u_d, q: u.u_q },
            est.theta_e + 1.5 * omega_e * self.ts,
        );
        VoltageCommand {
            hdr: Header {
                k: meas.hdr.k,
                t_sample_ns: meas.hdr.t_sample_ns,
                ..Default::default()
            },
            u_ab: [u_ab.alpha, u_ab.beta],
            u_dq: [u.u_d, u.u_q],
            i_dq_ref: [iref.i_d_ref, iref.i_q_ref],
            omega_ref: iref.omega_ref,
            omega_hat: est.omega_m,
            theta_hat: wrap_2pi(est.theta_e),
        }
    }
}

/// One trace row from measurement k and command k.
pub fn trace_row(ts: f64, meas: &Measurement, cmd: &VoltageCommand) -> TraceRow {
    TraceRow {
        k: meas.hdr.k,
        t: meas.hdr.k as f64 * ts,
        omega_ref: cmd.omega_ref,
        omega_m: meas.omega_m_true,
        omega_hat: cmd.omega_hat,
        theta_e: meas.theta_e_true,
        theta_hat: cmd.theta_hat,
        i_d_ref: cmd.i_dq_ref[0],
        i_q_ref: cmd.i_dq_ref[1],
        i_d: meas.i_dq_true[0],
        i_q: meas.i_dq_true[1],
        u_d: meas.u_dq_applied[0],
        u_q: meas.u_dq_applied[1],
        t_load: meas.t_load,
        miss: u8::from(meas.hdr.flags & (FLAG_STALE_CMD | FLAG_SAFE_STATE) != 0),
    }
}

/// The four step functions in one thread, in the cycle's order (the `inprocess` clock).
#[derive(Debug, Clone)]
pub struct InProcessDrive {
    /// Plant.
    pub plant: Plant,
    /// Observer.
    pub observer: ObserverStep,
    /// Current loop.
    pub current: CurrentLoopStep,
    /// Speed loop.
    pub speed: SpeedLoopStep,
    iref: CurrentRef,
    cmd: Option<VoltageCommand>,
    ts: f64,
}

impl InProcessDrive {
    /// Builds the drive.
    pub fn new(sc: &Scenario) -> Self {
        Self {
            plant: Plant::new(sc),
            observer: ObserverStep::new(sc),
            current: CurrentLoopStep::new(sc),
            speed: SpeedLoopStep::new(sc),
            iref: CurrentRef::default(),
            cmd: None,
            ts: sc.rates.ts(),
        }
    }

    /// Runs sample k and returns its trace row.
    pub fn cycle(&mut self, k: u64) -> TraceRow {
        let meas = self.plant.sample(k, self.cmd.as_ref());
        let est = self.observer.step(&meas);
        let cmd = self.current.step(&meas, &est, &self.iref);
        if let Some(r) = self.speed.step(&est) {
            self.iref = r;
        }
        self.plant.advance();
        self.cmd = Some(cmd);
        trace_row(self.ts, &meas, &cmd)
    }
}

/// Runs a whole scenario in process and returns the trace.
pub fn run_inprocess(sc: &Scenario) -> Vec<TraceRow> {
    let n = sc.samples();
    let mut d = InProcessDrive::new(sc);
    let mut rows = Vec::with_capacity(n as usize);
    for k in 0..n {
        rows.push(d.cycle(k));
    }
    rows
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::Scenario;

    fn kyslan() -> Scenario {
        let text = std::fs::read_to_string(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../scenarios/kyslan-pi.toml"
        ))
        .unwrap();
        Scenario::from_toml(&text, "kyslan-pi.toml").unwrap()
    }

    #[test]
    fn kyslan_pi_inprocess_metrics() {
        let sc = kyslan();
        let rows = run_inprocess(&sc);
        let m = crate::metrics::speed_metrics(&sc, &rows);
        eprintln!("{m:?} design {:?}", DriveDesign::from_scenario(&sc));
        let r = m.rise_time_ms.unwrap();
        assert!((r - 8.0).abs() <= 0.8, "rise {r} ms");
    }
}
