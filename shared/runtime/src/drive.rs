//! The four services' step functions and the in-process runner.
//!
//! Per sample k (docs/architecture.md, "The cycle"):
//! 1. plant: take command k−1 (or hold / safe state), publish measurement k, integrate to t_{k+1};
//! 2. observer: measurement k → estimate k;
//! 3. current loop: measurement k + estimate k + the current reference computed at the last
//!    speed sample before k → command k (applied by the plant from t_{k+1});
//! 4. speed loop, when k mod N = 0: estimate k → current reference k (used from k+1 on).
//!
//! The in-process runner, the lockstep bus and the real-time bus all call these same functions
//! in this order, so their traces are bit-identical when no deadline is missed.

#[cfg(test)]
mod drift_tests;
mod rejoin;
#[cfg(test)]
mod safe_state_tests;

use crate::config::{drift_at, profile_at, SafeState, Scenario, Step};
use crate::messages::*;
use crate::trace::TraceRow;
use drivelab_control::control::current::{
    CurrentInput, CurrentPiDesign, PiCurrentController, VoltageDq,
};
use drivelab_control::control::nonlinear::{
    self, design_nonlinear, KyslanModel, NlCurrentLaw, NlDesign, NlLoopModel, NlSpec, NlSpeedLaw,
};
use drivelab_control::control::speed::{
    design_symmetrical_optimum, sum_of_small_time_constants, SoDesign, SoSpec, SpeedLoopModel,
    SpeedPi,
};
use drivelab_control::motor::{wrap_2pi, Mechanics, MotorInput, MotorParams, MotorState, Rk4};
use drivelab_control::observer::EncoderObserver;
use drivelab_control::observer_sensorless::{ObserverMode, SensorlessObserver};
use drivelab_control::transforms::{clarke, inverse_clarke, inverse_park, park, AlphaBeta, Dq};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use serde::Serialize;

/// Controller designs derived from a scenario (never hand-tuned per scenario). Both the PI
/// cascade and the nonlinear controller are designed for every scenario (so that they can be
/// compared); `controller` says which one runs.
#[derive(Debug, Clone, Serialize)]
pub struct DriveDesign {
    /// "pi", "nonlinear" or "rst" (either loop selects the Low et al. RST).
    pub controller: &'static str,
    /// Current PI design.
    pub current: CurrentPiDesign,
    /// Speed PI design.
    pub speed: SoDesign,
    /// Kyslan et al. 2015 nonlinear controller design.
    pub nonlinear: NlDesign,
    /// Set-points of this scenario that approach the singularity of Kyslan eq. (15).
    pub warnings: Vec<String>,
    /// Low et al. 1998 RST designs (i_d, i_q, speed), when a loop selects "rst".
    #[serde(skip_serializing_if = "Option::is_none")]
    pub rst: Option<drivelab_control::control::rst::RstDriveDesign>,
    /// The sensorless observer's settings, when `observer.mode` is not "encoder".
    #[serde(skip_serializing_if = "Option::is_none")]
    pub observer: Option<drivelab_control::observer_sensorless::ObserverDesign>,
    /// Miyajima et al. polar current law (CDM / flux-weakening design), when selected.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub polar: Option<drivelab_control::control::polar::PolarDesign>,
}

/// Natural frequency ω_i of the nonlinear controller's inner (torque and field) loops, rad/s.
///
/// The paper gives no inner-loop dynamics. Both controllers take their current-loop speed
/// from the scenario's `current_loop.tau_c_s` (the PI loops close as 1/(τ_c s + 1)):
/// ω_i = 1/(2τ_c). At damping 0.6 the inner open loop (r s + K)/s² crosses over at ≈ 1.4·ω_i
/// = 0.7/τ_c, below the PI loops' 1/τ_c, because it starts with less phase margin (59°
/// against 90°) and the same 1.5-sample computation and PWM delay must be paid from it.
pub fn nonlinear_inner_frequency(sc: &Scenario) -> f64 {
    0.5 / sc.current_loop.tau_c_s
}

impl DriveDesign {
    /// Designs the controllers from the scenario's motor, rates and targets (every design,
    /// for the reports; a stage designs only what it runs, see [`speed_pi_design`] and
    /// [`nonlinear_design`]).
    pub fn from_scenario(sc: &Scenario) -> Self {
        let m = sc.motor_params();
        let current = CurrentPiDesign::new(&m, sc.current_loop.tau_c_s);
        let speed = speed_pi_design(sc);
        let nonlinear = nonlinear_design(sc);
        let warnings = if sc.nonlinear() {
            set_point_warnings(sc)
        } else {
            Vec::new()
        };
        let rst = crate::wiring::rst::uses_rst(sc)
            .then(|| crate::wiring::rst::design_from_scenario(sc).expect("validated"));
        Self {
            controller: if let Some(m) = crate::wiring::polar::mode_of(sc) {
                m.name()
            } else if rst.is_some() {
                "rst"
            } else if sc.nonlinear() {
                "nonlinear"
            } else {
                "pi"
            },
            current,
            speed,
            nonlinear,
            warnings,
            rst,
            observer: crate::wiring::observer_sensorless::design_from_scenario(sc),
            polar: crate::wiring::polar::spec_from_scenario(sc)
                .map(|p| drivelab_control::control::polar::PolarDesign::new(&p)),
        }
    }
}

/// The speed PI by the symmetrical optimum (an iterative design: milliseconds).
pub fn speed_pi_design(sc: &Scenario) -> SoDesign {
    let ts = sc.rates.ts();
    let t_sigma = sum_of_small_time_constants(
        sc.current_loop.tau_c_s,
        ts,
        sc.observer.speed_filter_tau_s,
        sc.rates.speed_divider,
    );
    design_symmetrical_optimum(
        &sc.motor_params(),
        &SoSpec {
            t_sigma_s: t_sigma,
            rise_time_s: sc.speed_loop.rise_time_s,
        },
        &speed_loop_model(sc),
    )
}

/// The sampled cascade the speed PI is designed on (its design model), with `sc`'s timing.
pub fn speed_loop_model(sc: &Scenario) -> SpeedLoopModel {
    SpeedLoopModel {
        ts: sc.rates.ts(),
        n: sc.rates.speed_divider,
        tau_c_s: sc.current_loop.tau_c_s,
        tau_f_s: sc.observer.speed_filter_tau_s,
    }
}

/// Kyslan et al.'s nonlinear controller design (an iterative design: milliseconds).
pub fn nonlinear_design(sc: &Scenario) -> NlDesign {
    design_nonlinear(
        &sc.motor_params(),
        &NlSpec {
            rise_time_s: sc.speed_loop.rise_time_s,
            omega_i_rad_s: nonlinear_inner_frequency(sc),
            zeta: nonlinear::DAMPING,
            placement: if sc.nonlinear() {
                sc.speed_loop.nl_poles
            } else {
                nonlinear::NlPlacement::Continuous
            },
        },
        &NlLoopModel {
            ts: sc.rates.ts(),
            n: sc.rates.speed_divider,
            tau_f_s: sc.observer.speed_filter_tau_s,
        },
    )
}

/// Kyslan eq. (15): the i_d set-points of `sc` at which a1 + a2·i_d falls below
/// [`nonlinear::NEAR_SINGULAR`]·a1 (the nonlinear law divides by it), one line each.
pub fn set_point_warnings(sc: &Scenario) -> Vec<String> {
    let km = KyslanModel::new(&sc.motor_params());
    let Some(sing) = km.singular_i_d() else {
        return Vec::new();
    };
    sc.reference
        .i_d_a
        .iter()
        .filter(|s| km.factor(s.value).near_singular)
        .map(|s| {
            format!(
                "i_d* = {} A at t = {} s approaches the uncontrollable i_d = -psi/(Ld - Lq) = {:.3} A of Kyslan eq. (15): torque per ampere of i_q is {:.0} % of the PM value{}",
                s.value,
                s.t_s,
                sing,
                100.0 * km.factor_raw(s.value) / km.a1,
                if km.factor(s.value).clamped {
                    "; the law clamps a1 + a2*i_d and loses its linearisation"
                } else {
                    ""
                }
            )
        })
        .collect()
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
    /// Overcurrent trip level (peak phase current), A.
    i_trip_a: Option<f64>,
    /// The overcurrent trip has fired (latched).
    pub tripped: bool,
    load: Vec<Step>,
    load_model: drivelab_control::motor::LoadModel,
    /// The nominal (t = 0, undrifted) motor; `m` is it with the drift of `[plant_drift]`.
    m_nominal: MotorParams,
    drift: crate::config::PlantDrift,
    encoder_counts: u32,
    noise: Option<(ChaCha8Rng, Normal<f64>)>,
    /// Sensor faults (`[[sensor_fault]]`): what the measurement shows, never the truth.
    sensor_faults: crate::sensor_faults::SensorModel,
    last_u_ab: [f64; 2],
    /// `[inverter] model = "switching"`: carrier PWM, dead time, drop, DC link.
    pwm: Option<drivelab_control::inverter::SwitchingInverter>,
    /// The limited αβ command of this sample (the modulator's reference).
    u_ab_cmd: AlphaBeta,
    /// This sample's inverter is pulse-blocked (the averaged coasting model applies).
    pulse_blocked: bool,
    /// Mean αβ voltage the inverter applied over the last integrated sample, V.
    pub mean_u_ab: [f64; 2],
    /// Static sensor errors (`[sensors]`): gain, offset, ADC, encoder delay.
    sensor_errors: crate::sensor_errors::SensorErrors,
    /// The ADC samples `adc_lead_s` before t_k; the state there (when > 0).
    adc_lead_s: f64,
    x_adc: MotorState,
    /// Consecutive samples without a fresh command.
    pub stale_run: u32,
    u_dq_applied: Dq,
    t_load: f64,
    /// Mechanical position counted from the start (the model's state wraps to [0, 2π)).
    theta_m_unwrapped: f64,
    truth: PlantTruth,
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
            omega_m: sc
                .mechanics
                .prescribed_speed_rad_s
                .or(sc.mechanics.initial_speed_rad_s)
                .unwrap_or(0.0),
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
            i_trip_a: sc.inverter.i_trip_a,
            tripped: false,
            load: sc.load.torque_nm.clone(),
            load_model: sc.load_model(),
            m_nominal: m,
            drift: sc.plant_drift.clone(),
            encoder_counts: sc.sensors.encoder_counts_per_rev,
            noise,
            sensor_faults: crate::sensor_faults::SensorModel::new(
                &sc.sensor_fault,
                sc.rates.sample_hz,
            ),
            last_u_ab: [0.0; 2],
            pwm: sc.inverter.pwm(sc.rates.sample_hz).map(|p| {
                drivelab_control::inverter::SwitchingInverter::new(
                    p,
                    sc.rates.ts(),
                    sc.rates.ts() / f64::from(sc.rates.plant_substeps),
                )
            }),
            u_ab_cmd: AlphaBeta::default(),
            pulse_blocked: false,
            mean_u_ab: [0.0; 2],
            sensor_errors: crate::sensor_errors::SensorErrors::new(&sc.sensors, sc.rates.ts()),
            adc_lead_s: sc.sensors.adc_lead_us * 1e-6,
            x_adc: x,
            stale_run: 0,
            u_dq_applied: Dq::default(),
            t_load: 0.0,
            theta_m_unwrapped: 0.0,
            truth: PlantTruth::default(),
        }
    }

    /// Sample k: applies command k−1 (`None` if it did not arrive in time) on [t_k, t_{k+1}) and
    /// returns measurement k. For k = 0 pass `None`; it is not a miss.
    pub fn sample(&mut self, k: u64, cmd: Option<&VoltageCommand>) -> Measurement {
        let mut flags = 0;
        let mut safe = false;
        match cmd {
            Some(c) => {
                self.last_u_ab = c.u_ab;
                self.stale_run = 0;
            }
            None if k == 0 => {}
            None => {
                self.stale_run = self.stale_run.saturating_add(1);
                flags |= FLAG_STALE_CMD;
                safe = self.stale_run > self.hold_samples;
            }
        }
        // Overcurrent trip: the phase currents at t_k against the trip level; latched.
        let theta_e = self.x.theta_e(&self.m);
        let (ia, ib, ic) = inverse_clarke(inverse_park(
            Dq {
                d: self.x.i_d,
                q: self.x.i_q,
            },
            theta_e,
        ));
        if let Some(i_trip) = self.i_trip_a {
            self.tripped |= ia.abs().max(ib.abs()).max(ic.abs()) > i_trip;
        }
        if self.tripped {
            flags |= FLAG_TRIPPED;
            safe = true;
        }
        let mut pulse_blocked = false;
        if safe {
            flags |= FLAG_SAFE_STATE;
            match self.safe_state {
                SafeState::ZeroVector => self.last_u_ab = [0.0; 2],
                SafeState::PulseBlock => pulse_blocked = true,
            }
        }
        // Inverter: limit the voltage vector to the linear SVPWM range V_dc/√3.
        let mut u = AlphaBeta {
            alpha: self.last_u_ab[0],
            beta: self.last_u_ab[1],
        };
        (u.alpha, u.beta) = limit_vector(u.alpha, u.beta, self.u_max);
        self.u_ab_cmd = u;
        self.pulse_blocked = pulse_blocked;
        let t = k as f64 * self.ts;
        self.t_load = profile_at(&self.load, t);
        if !self.drift.is_none() {
            // R and ψ drift (`[plant_drift]`): the profile at t_k, held over [t_k, t_{k+1}).
            self.m.r_ohm = self.m_nominal.r_ohm * drift_at(&self.drift.r_factor, t);
            self.m.psi_pm_wb = self.m_nominal.psi_pm_wb * drift_at(&self.drift.psi_factor, t);
        }
        // Zero-order hold in the rotor frame: the αβ vector is rotated with the mid-sample angle.
        let omega_e = self.m.p() * self.x.omega_m;
        self.u_dq_applied = park(u, theta_e + 0.5 * omega_e * self.ts);
        if pulse_blocked {
            // Coasting: the diode bridge lets the current decay. The voltage that drives the
            // dq currents to zero within one sample (forward Euler of eqs 1-2), clamped to
            // the DC link.
            let (m, x, ts) = (&self.m, &self.x, self.ts);
            let mut ud = m.r_ohm * x.i_d - omega_e * m.l_q_h * x.i_q - m.l_d_h * x.i_d / ts;
            let mut uq =
                m.r_ohm * x.i_q + omega_e * (m.l_d_h * x.i_d + m.psi_pm_wb) - m.l_q_h * x.i_q / ts;
            (ud, uq) = limit_vector(ud, uq, self.u_max);
            self.u_dq_applied = Dq { d: ud, q: uq };
            self.last_u_ab = [0.0; 2];
            u = inverse_park(self.u_dq_applied, theta_e + 0.5 * omega_e * self.ts);
        }
        let mut i_abc = if self.adc_lead_s > 0.0 {
            // The ADC's instant, adc_lead_s before t_k.
            drivelab_control::inverter::phase_currents(&self.m, &self.x_adc)
        } else {
            [ia, ib, ic]
        };
        self.sensor_errors.analog(&mut i_abc);
        if let Some((rng, n)) = self.noise.as_mut() {
            for i in &mut i_abc {
                *i += n.sample(rng);
            }
        }
        self.sensor_faults.currents(k, &mut i_abc);
        self.sensor_errors.digitise(&mut i_abc);
        let theta_m_seen = self.sensor_errors.encoder(self.x.theta_m);
        let theta_m_enc = if self.encoder_counts > 0 {
            let step = std::f64::consts::TAU / f64::from(self.encoder_counts);
            (theta_m_seen / step).floor() * step
        } else {
            theta_m_seen
        };
        let theta_m_enc = self.sensor_faults.encoder(k, theta_m_enc);
        let hdr = Header {
            k,
            flags,
            ..Default::default()
        };
        self.truth = PlantTruth {
            hdr,
            i_dq: [self.x.i_d, self.x.i_q],
            omega_m: self.x.omega_m,
            theta_e,
            theta_m: self.theta_m_unwrapped,
            u_dq_applied: [self.u_dq_applied.d, self.u_dq_applied.q],
            u_ab_applied: [u.alpha, u.beta],
            t_load: self.load_model.torque(self.t_load, self.x.omega_m),
            theta_m_enc,
        };
        Measurement {
            hdr,
            i_abc,
            theta_m_enc,
            u_ab_applied: [u.alpha, u.beta],
        }
    }

    /// The true state of the last [`Plant::sample`], for the trace.
    pub fn truth(&self) -> &PlantTruth {
        &self.truth
    }

    /// Integrates the model from t_k to t_{k+1} with the voltage chosen by [`Plant::sample`].
    pub fn advance(&mut self) {
        let u = MotorInput {
            u_d: self.u_dq_applied.d,
            u_q: self.u_dq_applied.q,
            t_load: self.t_load,
            load: self.load_model,
        };
        let before = self.x.theta_m;
        match self.pwm.as_mut().filter(|_| !self.pulse_blocked) {
            Some(inv) => {
                let o = inv.sample(
                    &self.m,
                    self.mech,
                    &self.x,
                    self.truth.hdr.k,
                    self.u_ab_cmd,
                    self.t_load,
                    self.load_model,
                    self.ts,
                    self.adc_lead_s,
                );
                self.x = o.x;
                self.x_adc = o.x_adc;
                self.mean_u_ab = [o.mean_u_ab.alpha, o.mean_u_ab.beta];
            }
            None if self.adc_lead_s > 0.0 => {
                self.x_adc =
                    self.rk
                        .advance(&self.m, self.mech, &self.x, &u, self.ts - self.adc_lead_s);
                self.x = self
                    .rk
                    .advance(&self.m, self.mech, &self.x_adc, &u, self.adc_lead_s);
                self.mean_u_ab = self.truth.u_ab_applied;
            }
            None => {
                self.x = self.rk.advance(&self.m, self.mech, &self.x, &u, self.ts);
                self.mean_u_ab = self.truth.u_ab_applied;
            }
        }
        // The model wraps θ_m; a sample moves it by far less than π.
        let d = (self.x.theta_m - before + std::f64::consts::PI).rem_euclid(std::f64::consts::TAU)
            - std::f64::consts::PI;
        self.theta_m_unwrapped += d;
    }
}

/// Observer service step: the encoder path, and per `observer.mode` the sensorless αβ
/// observer of Low et al. (`observer_sensorless`): "sensorless" sends its angle and speed,
/// "monitor" its angle with the encoder speed (the current loop then takes the angle for
/// control from the encoder itself, see [`CurrentLoopStep::step`]).
#[derive(Debug, Clone)]
pub struct ObserverStep {
    enc: EncoderObserver,
    sensorless: Option<SensorlessObserver>,
    mode: ObserverMode,
}

impl ObserverStep {
    /// Builds the observer.
    pub fn new(sc: &Scenario) -> Self {
        let m = sc.motor_params();
        let mut enc =
            EncoderObserver::new(m.pole_pairs, sc.rates.ts(), sc.observer.speed_filter_tau_s);
        if let Some(w) = running_start_speed(sc) {
            // The encoder speed is settled: the angle one sample before t_0 and the speed.
            enc.preset(wrap_2pi(-w * sc.rates.ts()), w);
        }
        Self {
            enc,
            // The sensorless observer always starts cold: θ̂ = the configured initial error,
            // ω̂ = 0.
            sensorless: crate::wiring::observer_sensorless::from_scenario(sc),
            mode: sc.observer.mode,
        }
    }

    /// Measurement k → estimate k.
    pub fn step(&mut self, meas: &Measurement) -> Estimate {
        let mut e = self.enc.step(meas.theta_m_enc);
        if let Some(o) = self.sensorless.as_mut() {
            let i = clarke(meas.i_abc[0], meas.i_abc[1], meas.i_abc[2]);
            let s = o.step(i.alpha, i.beta, meas.u_ab_applied);
            e.theta_e = s.theta_e;
            if self.mode == ObserverMode::Sensorless {
                e.omega_m = s.omega_m;
            }
        }
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

/// Speed of a rotor already turning at t_0 (`mechanics.prescribed_speed_rad_s` or
/// `initial_speed_rad_s`) when the drive has a position sensor (observer mode "encoder" or
/// "monitor"): the drive is then enabled in steady state, its encoder speed settled and its
/// speed law preset to that speed with i_q* = 0, so that a dynamometer test starts without a
/// start-up transient. A sensorless drive knows nothing at t_0 and starts cold.
pub fn running_start_speed(sc: &Scenario) -> Option<f64> {
    if sc.observer.mode == ObserverMode::Sensorless {
        return None;
    }
    sc.mechanics
        .prescribed_speed_rad_s
        .or(sc.mechanics.initial_speed_rad_s)
}

/// The speed law a scenario selects.
#[derive(Debug, Clone)]
enum SpeedLaw {
    Pi(SpeedPi),
    Nonlinear(NlSpeedLaw),
    Rst(Box<drivelab_control::control::rst::RstSpeed>),
    /// No speed control: i_q* from `reference.i_q_a`.
    CurrentReference,
}

/// Speed-loop service step.
#[derive(Debug, Clone)]
pub struct SpeedLoopStep {
    law: SpeedLaw,
    divider: u64,
    ts: f64,
    speed_ref: Vec<Step>,
    i_d_ref: Vec<Step>,
    i_q_ref: Vec<Step>,
    /// Speed samples whose i_d set-point approached Kyslan eq. (15) (nonlinear only).
    pub near_singular_samples: u64,
}

impl SpeedLoopStep {
    /// Builds the speed loop from the scenario's design.
    pub fn new(sc: &Scenario) -> Self {
        // Only the design of the law in use: a restarted speed loop is back sooner.
        let n = sc.rates.speed_divider;
        let tw = f64::from(n) * sc.rates.ts();
        let law = if sc.speed_loop.controller == crate::config::SpeedController::CurrentReference {
            SpeedLaw::CurrentReference
        } else if sc.speed_loop.controller == crate::config::SpeedController::Rst {
            let r = crate::wiring::rst::design_from_scenario(sc).expect("validated");
            SpeedLaw::Rst(Box::new(drivelab_control::control::rst::RstSpeed::new(
                &r.speed,
                sc.i_q_max(),
            )))
        } else if sc.nonlinear() {
            SpeedLaw::Nonlinear(NlSpeedLaw::new(
                &sc.motor_params(),
                &nonlinear_design(sc).gains,
                tw,
                sc.i_q_max(),
            ))
        } else {
            SpeedLaw::Pi(SpeedPi::new(&speed_pi_design(sc), tw, sc.i_q_max()))
        };
        let mut law = law;
        if let Some(w) = running_start_speed(sc) {
            match &mut law {
                SpeedLaw::Pi(c) => c.preset(w, 0.0),
                SpeedLaw::Rst(c) => c.preset(w, 0.0),
                SpeedLaw::Nonlinear(_) | SpeedLaw::CurrentReference => {}
            }
        }
        Self {
            law,
            divider: u64::from(n),
            ts: sc.rates.ts(),
            speed_ref: sc.reference.speed_rad_s.clone(),
            i_d_ref: sc.reference.i_d_a.clone(),
            i_q_ref: sc.reference.i_q_a.clone(),
            near_singular_samples: 0,
        }
    }

    /// True when the speed loop runs at sample k.
    pub fn runs_at(&self, k: u64) -> bool {
        k.is_multiple_of(self.divider)
    }

    /// Estimate k → current reference k when k mod N = 0, else None.
    pub fn step(&mut self, est: &Estimate) -> Option<CurrentRef> {
        self.step_with(est, None)
    }

    /// As [`SpeedLoopStep::step`], with the speed reference `omega_ref` (rad/s) of an outer
    /// loop instead of the scenario's profile when given.
    pub fn step_with(&mut self, est: &Estimate, omega_ref: Option<f64>) -> Option<CurrentRef> {
        let k = est.hdr.k;
        if !self.runs_at(k) {
            return None;
        }
        let t = k as f64 * self.ts;
        let omega_ref = omega_ref.unwrap_or_else(|| profile_at(&self.speed_ref, t));
        let i_d_ref = profile_at(&self.i_d_ref, t);
        let i_q_ref = match &mut self.law {
            SpeedLaw::Pi(c) => c.step(omega_ref, est.omega_m),
            SpeedLaw::Rst(c) => c.step(omega_ref, est.omega_m),
            SpeedLaw::CurrentReference => profile_at(&self.i_q_ref, t),
            SpeedLaw::Nonlinear(c) => {
                let o = c.step(omega_ref, est.omega_m, i_d_ref);
                if o.near_singular {
                    self.near_singular_samples += 1;
                }
                o.i_q_ref
            }
        };
        Some(CurrentRef {
            hdr: Header {
                k,
                t_sample_ns: est.hdr.t_sample_ns,
                ..Default::default()
            },
            omega_ref,
            i_d_ref,
            i_q_ref,
        })
    }
}

/// The current law a scenario selects.
#[derive(Debug, Clone)]
enum CurrentLaw {
    Pi(PiCurrentController),
    Nonlinear(NlCurrentLaw),
    Rst(Box<drivelab_control::control::rst::RstCurrentController>),
    Polar(drivelab_control::control::polar::PolarCurrentController),
}

/// (a, b) scaled to length `max` when it is longer. Its length is √(a² + b²) as long as
/// the squares are finite, and `hypot` (which cannot overflow) beyond, so that a huge vector
/// is limited instead of becoming zero or NaN.
pub fn limit_vector(a: f64, b: f64, max: f64) -> (f64, f64) {
    let sq = a * a + b * b;
    let mag = if sq.is_finite() {
        sq.sqrt()
    } else {
        libm::hypot(a, b)
    };
    if mag > max {
        (a * (max / mag), b * (max / mag))
    } else {
        (a, b)
    }
}

/// Current-loop service step.
#[derive(Debug, Clone)]
pub struct CurrentLoopStep {
    /// Limit of each current reference taken from the bus, A: the largest of the i_q* limit,
    /// the motor's rated current and the scenario's own reference steps.
    i_ref_max: f64,
    /// Voltage-vector limit, V.
    u_max: f64,
    /// Commands replaced by the zero vector because the law's output was not finite (its
    /// inputs were absurd though finite).
    pub zeroed_commands: u64,
    law: CurrentLaw,
    pole_pairs: f64,
    ts: f64,
    divider: u64,
    /// `observer.mode = "monitor"`: control on the encoder angle of the measurement, the
    /// estimate's angle (the sensorless observer's) only goes to the trace.
    monitor: bool,
    /// `current_loop.dead_time_comp`: the per-phase voltage added along each current's sign,
    /// t_d·f_sw·V_dc + v_drop, V.
    dead_time_comp_v: Option<f64>,
}

impl CurrentLoopStep {
    /// Builds the current loop from the scenario's design.
    pub fn new(sc: &Scenario) -> Self {
        let m = sc.motor_params();
        // Only the design of the law in use: a restarted current loop is back sooner.
        let law = if let Some(c) = crate::wiring::polar::controller_from_scenario(sc) {
            CurrentLaw::Polar(c)
        } else if sc.current_loop.controller == crate::config::CurrentController::Rst {
            CurrentLaw::Rst(Box::new(
                drivelab_control::control::rst::RstCurrentController::new(
                    &m,
                    &crate::wiring::rst::design_from_scenario(sc).expect("validated"),
                    sc.u_max(),
                    sc.current_loop.decoupling,
                ),
            ))
        } else if sc.nonlinear() {
            CurrentLaw::Nonlinear(NlCurrentLaw::new(
                &m,
                &nonlinear_design(sc).gains,
                sc.rates.ts(),
                sc.u_max(),
            ))
        } else {
            CurrentLaw::Pi(PiCurrentController::new(
                &m,
                &CurrentPiDesign::new(&m, sc.current_loop.tau_c_s),
                sc.rates.ts(),
                sc.u_max(),
                sc.current_loop.decoupling,
            ))
        };
        let i_ref_max = sc
            .reference
            .i_d_a
            .iter()
            .chain(&sc.reference.i_q_a)
            .map(|s| s.value.abs())
            .fold(sc.i_q_max().max(m.i_max_a), f64::max);
        Self {
            i_ref_max,
            u_max: sc.u_max(),
            zeroed_commands: 0,
            law,
            pole_pairs: m.p(),
            ts: sc.rates.ts(),
            divider: u64::from(sc.rates.speed_divider),
            monitor: sc.observer.mode == ObserverMode::Monitor,
            dead_time_comp_v: sc
                .current_loop
                .dead_time_comp
                .then(|| sc.inverter.pwm(sc.rates.sample_hz))
                .flatten()
                .map(|p| p.dead_time_error_v() + p.v_drop_v),
        }
    }

    /// Index of the current reference the current loop must use at sample k: the one computed
    /// at the last speed sample strictly before k. None for k = 0 (zero references).
    pub fn expected_ref_index(&self, k: u64) -> Option<u64> {
        (k > 0).then(|| (k - 1) / self.divider * self.divider)
    }

    /// Nonlinear law only: samples where the measured i_d approached Kyslan eq. (15), and
    /// samples where a1 + a2·i_d had to be clamped. (0, 0) for the PI cascade.
    pub fn singularity_counts(&self) -> (u64, u64) {
        match &self.law {
            CurrentLaw::Pi(_) | CurrentLaw::Rst(_) | CurrentLaw::Polar(_) => (0, 0),
            CurrentLaw::Nonlinear(c) => (c.near_singular_samples, c.clamped_samples),
        }
    }

    /// Miyajima polar laws only: samples where V_a was limited, where δ was limited, and where
    /// |V_ao| sat at its lower limit 0.001·V_amax (near the uncontrollable point V_a ≈ 0).
    pub fn polar_counts(&self) -> Option<(u64, u64, u64)> {
        match &self.law {
            CurrentLaw::Polar(c) => Some((
                c.v_a_limited_samples,
                c.delta_limited_samples,
                c.near_zero_amplitude_samples,
            )),
            _ => None,
        }
    }

    /// Measurement k + estimate k + current reference → command k.
    pub fn step(
        &mut self,
        meas: &Measurement,
        est: &Estimate,
        iref: &CurrentRef,
    ) -> VoltageCommand {
        let i_ab = clarke(meas.i_abc[0], meas.i_abc[1], meas.i_abc[2]);
        let theta = if self.monitor {
            wrap_2pi(self.pole_pairs * meas.theta_m_enc)
        } else {
            est.theta_e
        };
        let i = park(i_ab, theta);
        let omega_e = self.pole_pairs * est.omega_m;
        // A reference from the bus never asks for more than the drive's own limits.
        let lim = self.i_ref_max;
        let iref = &CurrentRef {
            i_d_ref: iref.i_d_ref.clamp(-lim, lim),
            i_q_ref: iref.i_q_ref.clamp(-lim, lim),
            ..*iref
        };
        let input = CurrentInput {
            i_d_ref: iref.i_d_ref,
            i_q_ref: iref.i_q_ref,
            i_d: i.d,
            i_q: i.q,
            omega_e,
        };
        // u and the q reference actually tracked (w2 of Kyslan eq. 30 for the nonlinear law).
        let (u, i_q_ref) = match &mut self.law {
            CurrentLaw::Pi(c) => (c.step(&input), iref.i_q_ref),
            CurrentLaw::Rst(c) => (c.step(&input), iref.i_q_ref),
            CurrentLaw::Polar(c) => (c.step(&input), iref.i_q_ref),
            CurrentLaw::Nonlinear(c) => {
                let o = c.step(&input);
                (
                    VoltageDq {
                        u_d: o.u_d,
                        u_q: o.u_q,
                        saturated: o.saturated,
                    },
                    o.w2,
                )
            }
        };
        // The command acts on [t_{k+1}, t_{k+2}); the plant rotates it with the mid-sample
        // angle, so compensate 1.5 samples of rotation.
        let theta_apply = theta + 1.5 * omega_e * self.ts;
        let mut u_ab = inverse_park(Dq { d: u.u_d, q: u.u_q }, theta_apply);
        if let Some(dv) = self.dead_time_comp_v {
            u_ab = dead_time_compensation(u_ab, i, theta_apply, dv);
        }
        // The laws limit |u| themselves; this catches what absurd (finite) inputs make of
        // them: a longer vector is limited, a non-finite one becomes the zero vector.
        let (a, b) = limit_vector(u_ab.alpha, u_ab.beta, self.u_max * (1.0 + 1e-12));
        let (u_ab, u) = if a.is_finite() && b.is_finite() {
            (AlphaBeta { alpha: a, beta: b }, u)
        } else {
            self.zeroed_commands += 1;
            (
                AlphaBeta::default(),
                VoltageDq {
                    u_d: 0.0,
                    u_q: 0.0,
                    saturated: true,
                },
            )
        };
        VoltageCommand {
            hdr: Header {
                k: meas.hdr.k,
                t_sample_ns: meas.hdr.t_sample_ns,
                ..Default::default()
            },
            u_ab: [u_ab.alpha, u_ab.beta],
            u_dq: [u.u_d, u.u_q],
            i_dq_ref: [iref.i_d_ref, i_q_ref],
            omega_ref: iref.omega_ref,
            omega_hat: est.omega_m,
            theta_hat: wrap_2pi(est.theta_e),
        }
    }
}

/// Dead-time compensation (docs/architecture.md, "Plant realism"): the inverter moves each
/// pole's mean voltage by −sign(i_x)·ΔV (ΔV = t_d·f_sw·V_dc, plus the device drop), so each
/// phase reference gets +sign(i_x)·ΔV. The signs are those of the measured dq current `i`
/// turned to the angle at which the command will act (`theta_apply`, mid-application), so
/// the 1.5 samples of delay do not put the switch-over late.
pub fn dead_time_compensation(u_ab: AlphaBeta, i: Dq, theta_apply: f64, dv: f64) -> AlphaBeta {
    let (ia, ib, ic) = inverse_clarke(inverse_park(i, theta_apply));
    let sgn = |x: f64| {
        if x > 0.0 {
            dv
        } else if x < 0.0 {
            -dv
        } else {
            0.0
        }
    };
    // The zero sequence of the three corrections drops out in Clarke.
    let c = clarke(sgn(ia), sgn(ib), sgn(ic));
    AlphaBeta {
        alpha: u_ab.alpha + c.alpha,
        beta: u_ab.beta + c.beta,
    }
}

/// The stand-in for a command that never came (or came unusable) for sample k: NaN in every
/// column, flagged [`FLAG_MISSING`](crate::messages::FLAG_MISSING).
pub fn missing_command(k: u64) -> VoltageCommand {
    let nan = f64::NAN;
    VoltageCommand {
        hdr: crate::messages::Header {
            k,
            flags: crate::messages::FLAG_MISSING,
            ..Default::default()
        },
        u_ab: [nan; 2],
        u_dq: [nan; 2],
        i_dq_ref: [nan; 2],
        omega_ref: nan,
        omega_hat: nan,
        theta_hat: nan,
    }
}

/// One trace row from measurement k and command k.
pub fn trace_row(ts: f64, truth: &PlantTruth, cmd: &VoltageCommand) -> TraceRow {
    TraceRow {
        k: truth.hdr.k,
        t: truth.hdr.k as f64 * ts,
        omega_ref: cmd.omega_ref,
        omega_m: truth.omega_m,
        omega_hat: cmd.omega_hat,
        theta_e: truth.theta_e,
        theta_hat: cmd.theta_hat,
        i_d_ref: cmd.i_dq_ref[0],
        i_q_ref: cmd.i_dq_ref[1],
        i_d: truth.i_dq[0],
        i_q: truth.i_dq[1],
        u_d: truth.u_dq_applied[0],
        u_q: truth.u_dq_applied[1],
        t_load: truth.t_load,
        plant_flags: truth.hdr.flags,
        ctrl_flags: cmd.hdr.flags,
        // The safe state after the hold comes only with a stale command; a tripped inverter
        // is safe with every command there (no miss).
        miss: u8::from(truth.hdr.flags & FLAG_STALE_CMD != 0),
        theta_m: truth.theta_m,
        theta_m_ref: None,
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
        let view = sc.controller_view();
        Self {
            plant: Plant::new(sc),
            observer: ObserverStep::new(&view),
            current: CurrentLoopStep::new(&view),
            speed: SpeedLoopStep::new(&view),
            iref: CurrentRef::default(),
            cmd: None,
            ts: sc.rates.ts(),
        }
    }

    /// The command of the last sample run (applied over the next one).
    pub fn command(&self) -> Option<&VoltageCommand> {
        self.cmd.as_ref()
    }

    /// Runs sample k and returns its trace row.
    pub fn cycle(&mut self, k: u64) -> TraceRow {
        let meas = self.plant.sample(k, self.cmd.as_ref());
        let est = self.observer.step(&meas);
        let cmd = self.current.step(&meas, &est, &self.iref);
        if let Some(r) = self.speed.step(&est) {
            self.iref = r;
        }
        let truth = *self.plant.truth();
        self.plant.advance();
        self.cmd = Some(cmd);
        trace_row(self.ts, &truth, &cmd)
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

    fn scenario(name: &str) -> Scenario {
        let path = format!("{}/../../scenarios/{name}.toml", env!("CARGO_MANIFEST_DIR"));
        Scenario::from_toml(&std::fs::read_to_string(&path).unwrap(), &path).unwrap()
    }

    /// The plant's step with the switching inverter, a DC link and every sensor error
    /// (docs/architecture.md, "Real-time rules"): no allocation per sample.
    #[test]
    fn the_switching_plant_with_sensor_errors_steps_without_allocating() {
        let mut sc = scenario("kyslan-pi-pwm");
        sc.inverter.v_drop_v = 1.0;
        sc.inverter.dc_link_c_uf = Some(100.0);
        sc.inverter.r_source_ohm = Some(2.0);
        sc.current_loop.dead_time_comp = true;
        sc.sensors.current_gain = [1.01, 1.0, 0.99];
        sc.sensors.adc_bits = Some(12);
        sc.sensors.adc_range_a = Some(5.0);
        sc.sensors.adc_lead_us = 10.0;
        sc.sensors.encoder_delay_us = 150.0;
        sc.sensors.current_noise_a = 0.01;
        sc.validate().unwrap();
        let mut d = InProcessDrive::new(&sc);
        d.cycle(0);
        let (_, allocations) = crate::alloc_count::allocations_during(|| {
            for k in 1..500 {
                d.cycle(k);
            }
        });
        assert_eq!(allocations, 0);
        assert!(d.plant.x.omega_m > 1.0, "the drive turns: {:?}", d.plant.x);
    }

    /// `[sensors]` in the plant's measurement, in order: the current at the ADC's instant,
    /// gain and offset per phase, then the ADC's rounding and saturation; the truth stays
    /// true.
    #[test]
    fn the_measurement_goes_through_gain_offset_and_the_adc() {
        let mut sc = scenario("kyslan-pi");
        sc.sensors.current_gain = [1.1, 1.0, 0.9];
        sc.sensors.current_offset_a = [0.0, 0.2, 0.0];
        sc.sensors.adc_bits = Some(8);
        sc.sensors.adc_range_a = Some(1.5);
        sc.validate().unwrap();
        let mut p = Plant::new(&sc);
        p.x.i_d = 1.0;
        p.x.i_q = 0.5;
        p.x.theta_m = 0.3;
        let m = p.sample(0, None);
        let (ia, ib, ic) = inverse_clarke(inverse_park(
            Dq { d: 1.0, q: 0.5 },
            p.x.theta_e(&sc.motor_params()),
        ));
        let adc = crate::sensor_errors::Adc::new(8, 1.5);
        let want = [adc.read(1.1 * ia), adc.read(ib + 0.2), adc.read(0.9 * ic)];
        assert_eq!(m.i_abc, want, "true ({ia}, {ib}, {ic})");
        // |i| = 1.12 A: every reading lies within ±1.5 A, so the ADC only rounds, by half
        // an LSB (1.5/128 A) at most.
        assert!((m.i_abc[0] - 1.1 * ia).abs() <= 0.5 * 1.5 / 128.0 + 1e-12);
        assert_eq!(p.truth().i_dq, [1.0, 0.5]);
    }

    #[test]
    fn mismatched_controllers_are_rejected() {
        let text = std::fs::read_to_string(format!(
            "{}/../../scenarios/kyslan-nl.toml",
            env!("CARGO_MANIFEST_DIR")
        ))
        .unwrap()
        .replacen("controller = \"nonlinear\"", "controller = \"pi\"", 1);
        let e = Scenario::from_toml(&text, "x.toml").unwrap_err();
        assert!(e.contains("must both be"), "{e}");
    }

    #[test]
    fn near_singular_i_d_set_point_is_warned() {
        let mut sc = scenario("kyslan-nl-sal618");
        assert!(set_point_warnings(&sc).is_empty());
        // Singular at −ψ/(L_d − L_q) = −5.01 A; −3 A leaves 40 % of the PM torque per ampere.
        sc.reference.i_d_a[0].value = -3.0;
        let w = set_point_warnings(&sc);
        assert_eq!(w.len(), 1);
        assert!(
            w[0].contains("eq. (15)") && w[0].contains("-5.012"),
            "{w:?}"
        );
        assert_eq!(DriveDesign::from_scenario(&sc).warnings, w);
    }
}
