//! The minimal-order position observer of Low, Deng & Guo 1998 (§IV, eqs 11–17): sin θ_e and
//! cos θ_e estimated in the stationary αβ frame from the measured currents and the applied
//! voltages, θ̂_e = atan2 (eq. 17), and a speed estimate that closes the loop.
//!
//! # Model (eq. 11)
//!
//! Surface PMSM (L_d = L_q = L), X = [i_α, i_β, sin θ_e, cos θ_e]ᵀ, U = [u_α, u_β]ᵀ, Y = [i_α, i_β]ᵀ:
//!
//! ```text
//! L di_α/dt = u_α − r i_α + k_e ω_m sin θ_e        d sin θ_e/dt =  ω_e cos θ_e
//! L di_β/dt = u_β − r i_β − k_e ω_m cos θ_e        d cos θ_e/dt = −ω_e sin θ_e
//! ```
//!
//! with k_e = p·ψ (V·s/rad mechanical) and ω_e = p·ω_m: the back-EMF of the amplitude-invariant
//! αβ frame is e_αβ = ω_e ψ [−sin θ_e, cos θ_e]. The blocks of eq. (15) are
//! A11 = −r/L·I, A12 = k_e ω_m/L·diag(1, −1), A21 = 0, A22 = ω_e [[0, 1], [−1, 0]], B1 = I/L,
//! B2 = 0.
//!
//! # Discretisation (eqs 12–14)
//!
//! * [`Discretisation::Truncated`] (the paper, eq. 13): A(k) = I + A(ω_m)·T_s, B(k) = B·T_s.
//! * [`Discretisation::Exact`]: A(k) = e^{A(ω_m) T_s}, B(k) = ∫₀^{T_s} e^{Aτ} dτ·B (zero-order
//!   hold of u_αβ), in closed form.
//!
//! The difference: the truncated model takes the back-EMF at the start of the interval, the
//! current really integrates it over the interval, during which it turns by ω_e T_s. The
//! observer therefore lines its estimate up with the EMF at about the middle of the interval:
//! θ̂ leads θ by somewhat less than ω_e T_s/2 in steady state (2.23° at 1200 rpm and no load,
//! T_s = 0.2 ms, τ_o = 1 ms, where ω_e T_s/2 = 2.9°; [`predicted_angle_error`] gives the figure
//! for any operating point, and the drive settles to it within 0.001°). The exact model
//! removes this bias; what is left is the inverter's hold in the rotor frame (u_dq constant
//! over the sample, hence u_αβ turning), which no αβ model with a held u_αβ describes
//! (−0.008° at 1200 rpm). The
//! relative truncation error ζ of eq. (14) ([`truncation_error`]) is the design figure of the
//! paper's Fig. 3 (`drivelab observer-error`).
//!
//! # Observer (eq. 16)
//!
//! With the partition of eq. (15) and gain V2 = G:
//!
//! ```text
//! X̂_B(k) = A22 X̂_B(k−1) + G·[Y(k) − A11 Y(k−1) − B1 U(k−1) − A12 X̂_B(k−1)]
//! ```
//!
//! which is eq. (16) with Ẑ(k) = X̂_B(k) − V2·Y(k), D = A22 − G A12, E = D·G + A21 − G A11,
//! G_u = B2 − G B1 ([`ObserverMatrices`]; a unit test checks both forms give the same
//! estimate). Written on X̂_B as above, rescheduling G with the speed does not bump the
//! estimate. The estimation error obeys e(k) = D·e(k−1); G is chosen so that
//! D = λ·I, λ = e^{−T_s/τ_o} (τ_o: `observer.pole_tau_s`, default 1 ms), i.e.
//! G = (A22 − λ I)·A12⁻¹, recomputed every sample from the speed estimate ("rescheduled").
//! A12 is proportional to ω_m: at standstill the back-EMF vanishes and the position is not
//! observable. The gains use |ω̂| ≥ [`OMEGA_MIN_FRACTION`]·ω_rated.
//!
//! All 2×2 blocks commute with the 90° rotation, so the observer is computed in complex
//! arithmetic (i = i_α + j i_β, w = cos θ_e + j sin θ_e); this is the same linear map.
//!
//! # Speed estimate
//!
//! ω̂_m closes the loop twice: it sets the observer's model and gains at the next sample, and
//! it is the speed loop's input. It is the backward difference of an angle, divided by p·T_s,
//! through the Bessel filter of eq. (10) (group delay `observer.speed_filter_tau_s`), as the
//! paper does with position data — but of the angle of the *measured back-EMF increment*
//! ν_m(k) = Y(k) − A11·Y(k−1) − B1·U(k−1) (the measured part of the innovation, = A12·X_B(k−1)
//! by the model; A11 and B1 do not depend on ω), not of θ̂_e. Differencing θ̂_e feeds the
//! observer's own convergence back into its gains: correcting a 90° error within a few τ_o
//! reads as a speed error of about −(π/2)/(p·τ_o) ≈ −400 rad/s, the rescheduled model then
//! turns the estimate the wrong way and the estimate never settles (seen in the drive: 50 ms
//! of oscillation and divergence from a 90° start). The back-EMF vector turns at ω_e
//! whatever the estimate does, so that loop is cut. Below [`EMF_GATE_FRACTION`] of the
//! back-EMF at the scheduling floor its direction is noise and the estimate's own rotation
//! (backward difference of θ̂_e) is used instead.
//!
//! # Limits
//!
//! At standstill the back-EMF vanishes and the position is unobservable: a sensorless start
//! from rest needs the initial angle (the scenarios start aligned at θ_e = 0, as after a
//! d-axis alignment pulse); a wrong initial angle at rest is not recovered. From speed (a
//! flying start, `mechanics.initial_speed_rad_s`) any initial error converges in a few τ_o.
//!
//! # Timing
//!
//! Measurement k carries the currents at t_k and the voltage the inverter applies on
//! [t_k, t_{k+1}); the prediction from k−1 to k uses the voltage of measurement k−1, kept in
//! the observer's state.

use crate::control::filter::Bessel2;
use crate::motor::{wrap_2pi, MotorParams};
use crate::observer::PosSpeed;
use nalgebra::{Complex, Matrix4};
use serde::{Deserialize, Serialize};
use std::f64::consts::{PI, TAU};

/// Where the drive's position and speed come from (`observer.mode`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ObserverMode {
    /// Encoder angle, backward-difference speed through the Bessel filter.
    #[default]
    Encoder,
    /// The minimal-order αβ observer (this module): no position sensor.
    Sensorless,
    /// The controllers use the encoder; the αβ observer runs beside it and its angle is the
    /// trace's `theta_hat` (estimator tests on a sensored drive, e.g. on a dynamometer).
    /// `omega_hat` stays the encoder speed (the speed loop's input).
    Monitor,
}

/// Discretisation of the observer's model (`observer.discretisation`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Discretisation {
    /// A(k) = I + A·T_s, B(k) = B·T_s (Low eq. 13).
    #[default]
    Truncated,
    /// A(k) = e^{A T_s}, B(k) = ∫ e^{Aτ}dτ·B.
    Exact,
}

/// The observer's gains use a speed of at least this fraction of the rated speed.
pub const OMEGA_MIN_FRACTION: f64 = 0.05;

/// The direction of the measured back-EMF increment is trusted for the speed estimate when
/// its magnitude exceeds this fraction of its value at [`OMEGA_MIN_FRACTION`]·ω_rated.
pub const EMF_GATE_FRACTION: f64 = 0.25;

/// The continuous A(ω_m) of eq. (11), state [i_α, i_β, sin θ_e, cos θ_e].
pub fn continuous_a(m: &MotorParams, omega_m: f64) -> Matrix4<f64> {
    let l = m.l_d_h;
    let kappa = m.p() * m.psi_pm_wb * omega_m / l;
    let we = m.p() * omega_m;
    let a = -m.r_ohm / l;
    Matrix4::new(
        a, 0.0, kappa, 0.0, //
        0.0, a, 0.0, -kappa, //
        0.0, 0.0, 0.0, we, //
        0.0, 0.0, -we, 0.0,
    )
}

/// Relative truncation error ζ of eq. (14):
/// ‖e^{A T_s} − (I + A T_s)‖_F / ‖e^{A T_s}‖_F at mechanical speed `omega_m` (rad/s).
pub fn truncation_error(m: &MotorParams, ts: f64, omega_m: f64) -> f64 {
    let at = continuous_a(m, omega_m) * ts;
    let e = at.exp();
    let trunc = Matrix4::identity() + at;
    (e - trunc).norm() / e.norm()
}

/// The discretised blocks of eq. (15) as complex scalars (A21 = 0, B2 = 0): i(k+1) =
/// a11·i(k) + a12·w(k) + b1·u(k), w(k+1) = a22·w(k).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DiscreteModel {
    /// A11 (real scalar times I).
    pub a11: f64,
    /// A12.
    pub a12: Complex<f64>,
    /// A22.
    pub a22: Complex<f64>,
    /// B1 (real scalar times I).
    pub b1: f64,
}

impl DiscreteModel {
    /// The model at mechanical speed `omega_m`.
    pub fn new(m: &MotorParams, ts: f64, omega_m: f64, disc: Discretisation) -> Self {
        let l = m.l_d_h;
        let alpha = m.r_ohm / l;
        let kappa = m.p() * m.psi_pm_wb * omega_m / l;
        let we = m.p() * omega_m;
        let j = Complex::new(0.0, 1.0);
        match disc {
            Discretisation::Truncated => Self {
                a11: 1.0 - alpha * ts,
                a12: -j * kappa * ts,
                a22: Complex::new(1.0, we * ts),
                b1: ts / l,
            },
            Discretisation::Exact => {
                let ea = libm::exp(-alpha * ts);
                let rot = crate::math::cexp(Complex::new(0.0, we * ts));
                Self {
                    a11: ea,
                    a12: -j * kappa * (rot - ea) / Complex::new(alpha, we),
                    a22: rot,
                    b1: (1.0 - ea) / m.r_ohm,
                }
            }
        }
    }

    /// Observer gain G = (A22 − λI)·A12⁻¹: error dynamics D = A22 − G·A12 = λ·I.
    pub fn gain(&self, lambda: f64) -> Complex<f64> {
        (self.a22 - lambda) / self.a12
    }
}

/// Real 2×2 matrix, row-major.
pub type M2 = [[f64; 2]; 2];

/// A complex scalar acting on w = [sin, cos] (ordered as X_B) → the same ordering.
fn m_ww(c: Complex<f64>) -> M2 {
    [[c.re, c.im], [-c.im, c.re]]
}

/// A complex scalar mapping i = [α, β] to w = [sin, cos].
fn m_wi(c: Complex<f64>) -> M2 {
    [[c.im, c.re], [c.re, -c.im]]
}

/// The design matrices of eq. (16) at one speed.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct ObserverMatrices {
    /// D = A22 − G A12 (= λ I).
    pub d: M2,
    /// E = D G + A21 − G A11.
    pub e: M2,
    /// G_u = B2 − G B1 (the paper's G(k)).
    pub g_u: M2,
    /// V2 = G.
    pub v2: M2,
}

/// Eq. (16)'s matrices for `model` and pole `lambda`.
pub fn observer_matrices(model: &DiscreteModel, lambda: f64) -> ObserverMatrices {
    let g = model.gain(lambda);
    let d = model.a22 - g * model.a12;
    ObserverMatrices {
        d: m_ww(d),
        e: m_wi(d * g - g * model.a11),
        g_u: m_wi(-g * model.b1),
        v2: m_wi(g),
    }
}

/// Steady-state angle error θ̂_e − θ_e (rad) the observer settles to at constant speed
/// `omega_m` with constant rotor-frame currents (i_d, i_q), on this drive's plant: currents
/// constant in dq, the voltage held constant in the rotor frame over each sample and reported
/// as u_αβ at the mid-sample angle. From X̂_B(k) = ρ·X_B(k) in eq. (16):
/// ρ·(e^{jω_e T_s} − λ) = G·ν, ν the innovation per unit X_B(k−1).
pub fn predicted_angle_error(
    m: &MotorParams,
    ts: f64,
    omega_m: f64,
    i_d: f64,
    i_q: f64,
    pole_tau_s: f64,
    disc: Discretisation,
) -> f64 {
    let we = m.p() * omega_m;
    let phi = we * ts;
    let i = Complex::new(i_d, i_q);
    let u = Complex::new(
        m.r_ohm * i_d - we * m.l_q_h * i_q,
        m.r_ohm * i_q + we * (m.l_d_h * i_d + m.psi_pm_wb),
    );
    let model = DiscreteModel::new(m, ts, omega_m, disc);
    let lambda = libm::exp(-ts / pole_tau_s);
    let rot = crate::math::cexp(Complex::new(0.0, phi));
    let half = crate::math::cexp(Complex::new(0.0, 0.5 * phi));
    let nu = i * rot - i * model.a11 - u * half * model.b1;
    let rho = model.gain(lambda) * nu / (rot - lambda);
    crate::math::carg(rho)
}

/// Settings of the sensorless observer.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SensorlessSettings {
    /// Sample time T_s, s.
    pub ts: f64,
    /// Observer time constant τ_o, s (pole λ = e^{−T_s/τ_o}).
    pub pole_tau_s: f64,
    /// Discretisation of the model.
    pub discretisation: Discretisation,
    /// Group delay of the Bessel speed filter, s.
    pub speed_filter_tau_s: f64,
    /// Initial estimate θ̂_e(0), rad (the plant starts at θ_e = 0, so this is the initial error).
    pub initial_angle_rad: f64,
}

/// The minimal-order observer with its speed estimate. Fixed-size state; `step` does not
/// allocate.
#[derive(Debug, Clone, Copy)]
pub struct SensorlessObserver {
    m: MotorParams,
    s: SensorlessSettings,
    lambda: f64,
    omega_min: f64,
    /// X̂_B as w = cos θ̂ + j sin θ̂ (not normalised).
    w: Complex<f64>,
    y_prev: Complex<f64>,
    u_prev: Complex<f64>,
    started: bool,
    theta_prev: f64,
    omega_hat: f64,
    filter: Bessel2,
    /// The measured back-EMF increment of the previous sample (speed estimate).
    emf_prev: Complex<f64>,
    /// Below this |EMF increment| its direction is not trusted (see [`EMF_GATE_FRACTION`]).
    emf_gate: f64,
}

impl SensorlessObserver {
    /// A new observer at θ̂_e = `initial_angle_rad`, ω̂ = 0.
    pub fn new(m: &MotorParams, s: SensorlessSettings) -> Self {
        let (sin, cos) = libm::sincos(s.initial_angle_rad);
        Self {
            m: *m,
            s,
            lambda: libm::exp(-s.ts / s.pole_tau_s),
            omega_min: OMEGA_MIN_FRACTION * m.omega_rated_rad_s,
            w: Complex::new(cos, sin),
            y_prev: Complex::new(0.0, 0.0),
            u_prev: Complex::new(0.0, 0.0),
            started: false,
            theta_prev: wrap_2pi(s.initial_angle_rad),
            omega_hat: 0.0,
            filter: Bessel2::design(s.speed_filter_tau_s, s.ts),
            emf_prev: Complex::new(0.0, 0.0),
            emf_gate: EMF_GATE_FRACTION
                * m.p()
                * m.psi_pm_wb
                * OMEGA_MIN_FRACTION
                * m.omega_rated_rad_s
                * s.ts
                / m.l_d_h,
        }
    }

    /// The speed the model and gains use: ω̂ with |ω̂| ≥ ω_min.
    pub fn scheduling_speed(&self) -> f64 {
        let w = self.omega_hat;
        if w.abs() >= self.omega_min {
            w
        } else if w < 0.0 {
            -self.omega_min
        } else {
            self.omega_min
        }
    }

    /// Measurement k: currents i_αβ(k) and the voltage applied on [t_k, t_{k+1}) → θ̂_e(k),
    /// ω̂_m(k).
    pub fn step(&mut self, i_alpha: f64, i_beta: f64, u_ab_applied: [f64; 2]) -> PosSpeed {
        let y = Complex::new(i_alpha, i_beta);
        let mut emf = Complex::new(0.0, 0.0);
        if self.started {
            let model = DiscreteModel::new(
                &self.m,
                self.s.ts,
                self.scheduling_speed(),
                self.s.discretisation,
            );
            let g = model.gain(self.lambda);
            // The measured part of the innovation: the current change the R-L model does not
            // explain, A12·X_B(k−1) by the model (A11 and B1 do not depend on ω).
            emf = y - self.y_prev * model.a11 - self.u_prev * model.b1;
            let nu = emf - model.a12 * self.w;
            self.w = model.a22 * self.w + g * nu;
        }
        self.started = true;
        self.y_prev = y;
        self.u_prev = Complex::new(u_ab_applied[0], u_ab_applied[1]);
        // Eq. (17).
        let theta = wrap_2pi(libm::atan2(self.w.im, self.w.re));
        let dtheta = if crate::math::cnorm(emf) > self.emf_gate
            && crate::math::cnorm(self.emf_prev) > self.emf_gate
        {
            // Rotation of the measured back-EMF vector over one sample.
            crate::math::carg(emf * self.emf_prev.conj())
        } else {
            // Too little back-EMF to trust its direction: the estimate's own rotation.
            (theta - self.theta_prev + PI).rem_euclid(TAU) - PI
        };
        let raw = dtheta / (self.m.p() * self.s.ts);
        self.theta_prev = theta;
        self.emf_prev = emf;
        self.omega_hat = self.filter.step(raw);
        PosSpeed {
            theta_e: theta,
            omega_m: self.omega_hat,
        }
    }

    /// The estimate X̂_B = [sin θ̂_e, cos θ̂_e] (not normalised).
    pub fn x_b(&self) -> [f64; 2] {
        [self.w.im, self.w.re]
    }

    /// Bumpless start at a known electrical angle and mechanical speed; the next step starts
    /// a fresh prediction.
    pub fn preset(&mut self, theta_e: f64, omega_m: f64) {
        let (s, c) = libm::sincos(theta_e);
        self.w = Complex::new(c, s);
        self.theta_prev = wrap_2pi(theta_e);
        self.omega_hat = omega_m;
        self.filter.preset(omega_m);
        self.started = false;
        self.emf_prev = Complex::new(0.0, 0.0);
    }
}

/// The sensorless observer's settings as recorded in `summary.json` → `design.observer`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct ObserverDesign {
    /// "sensorless" or "monitor".
    pub mode: ObserverMode,
    /// "truncated" or "exact".
    pub discretisation: Discretisation,
    /// Observer time constant τ_o, s.
    pub pole_tau_s: f64,
    /// Observer pole λ = e^{−T_s/τ_o} (both estimation-error modes).
    pub lambda: f64,
    /// Gains are scheduled at |ω̂| of at least this, rad/s.
    pub omega_min_rad_s: f64,
    /// Initial estimate θ̂_e(0) − θ_e(0), degrees.
    pub initial_angle_error_deg: f64,
    /// ζ of eq. (14) at rated speed, for this T_s.
    pub zeta_at_rated_speed: f64,
}

/// A plain-text printout of the observer of a scenario: pole, gains of eq. (16) at 1200 rpm
/// and rated speed, ζ and the predicted steady-state angle error.
pub fn render_design(d: &ObserverDesign, m: &MotorParams, ts: f64) -> String {
    use std::fmt::Write;
    let mut o = String::new();
    let _ = writeln!(
        o,
        "minimal-order αβ observer (Low et al. 1998 eqs 11-17), mode {:?}, {:?} model: τ_o = {} ms, D = λI with λ = e^(-T_s/τ_o) = {:.5}, gains scheduled at |ω̂| ≥ {:.1} rad/s",
        d.mode, d.discretisation, d.pole_tau_s * 1e3, d.lambda, d.omega_min_rad_s
    );
    for (label, w) in [
        ("1200 rpm", 1200.0 * PI / 30.0),
        ("rated speed", m.omega_rated_rad_s),
    ] {
        let model = DiscreteModel::new(m, ts, w, d.discretisation);
        let mx = observer_matrices(&model, d.lambda);
        let f = |a: &M2| {
            format!(
                "[[{:.4}, {:.4}], [{:.4}, {:.4}]]",
                a[0][0], a[0][1], a[1][0], a[1][1]
            )
        };
        let _ = writeln!(
            o,
            "  at {label} ({w:.1} rad/s): V2 = G = {}, E = {}, G_u = {}; ζ = {:.3} %, predicted steady-state θ̂ − θ at no load {:.3}° ({:.3}° with the other discretisation)",
            f(&mx.v2),
            f(&mx.e),
            f(&mx.g_u),
            100.0 * truncation_error(m, ts, w),
            predicted_angle_error(m, ts, w, 0.0, 0.0, d.pole_tau_s, d.discretisation).to_degrees(),
            predicted_angle_error(
                m,
                ts,
                w,
                0.0,
                0.0,
                d.pole_tau_s,
                match d.discretisation {
                    Discretisation::Truncated => Discretisation::Exact,
                    Discretisation::Exact => Discretisation::Truncated,
                }
            )
            .to_degrees()
        );
    }
    o
}

#[cfg(test)]
// The tests' own reference values come from std's maths: they never reach a trace.
#[allow(clippy::disallowed_methods)]
mod tests {
    use super::*;
    use crate::motor::{Mechanics, MotorInput, MotorState, Rk4};
    use crate::transforms::{inverse_park, park, AlphaBeta, Dq};

    const TS: f64 = 2e-4;

    fn rpm(n: f64) -> f64 {
        n * PI / 30.0
    }

    #[test]
    fn zeta_is_about_2_percent_at_1200_rpm_and_0_2_ms() {
        // Low et al.: "ζ is smaller than 2 % at a speed of 1200 rpm with 0.2 ms".
        let m = MotorParams::low1998();
        let z = truncation_error(&m, TS, rpm(1200.0));
        assert!(z < 0.02, "ζ = {z}");
        // ζ grows with speed and with T_s.
        assert!(truncation_error(&m, TS, rpm(2400.0)) > z);
        assert!(truncation_error(&m, 2.0 * TS, rpm(1200.0)) > z);
        // At standstill A·T_s = diag(x, x, 0, 0) with x = −R·T_s/L, so
        // ζ = √2·|e^x − 1 − x| / √(2·e^{2x} + 2). The difference e^{A·T} − (I + A·T) loses
        // four of its digits (|x| = 0.017); 1e-9 of ζ leaves room for that.
        let x = -m.r_ohm * TS / m.l_d_h;
        let z0 = 2f64.sqrt() * (x.exp() - 1.0 - x).abs() / (2.0 * (2.0 * x).exp() + 2.0).sqrt();
        let got = truncation_error(&m, TS, 0.0);
        assert!(
            (got - z0).abs() <= 1e-9 * z0,
            "ζ(0) = {got}, closed form {z0}"
        );
    }

    #[test]
    fn exact_model_is_the_matrix_exponential() {
        let m = MotorParams::low1998();
        let w = rpm(1500.0);
        let e = (continuous_a(&m, w) * TS).exp();
        let d = DiscreteModel::new(&m, TS, w, Discretisation::Exact);
        // Column of sin θ (index 2) in rows i_α, i_β: A12 acting on X_B = [1, 0].
        let a12 = m_wi(d.a12);
        let _ = a12;
        // A12 maps w (as [sin, cos]) to i = [α, β]: i = a12·w with w = cos + j sin.
        let w_sin = Complex::new(0.0, 1.0); // sin = 1, cos = 0
        let i = d.a12 * w_sin;
        assert!((i.re - e[(0, 2)]).abs() < 1e-12 && (i.im - e[(1, 2)]).abs() < 1e-12);
        let w_cos = Complex::new(1.0, 0.0);
        let i = d.a12 * w_cos;
        assert!((i.re - e[(0, 3)]).abs() < 1e-12 && (i.im - e[(1, 3)]).abs() < 1e-12);
        assert!((d.a11 - e[(0, 0)]).abs() < 1e-15);
        let r = d.a22 * w_sin; // new [sin, cos] = [r.im, r.re]
        assert!((r.im - e[(2, 2)]).abs() < 1e-12 && (r.re - e[(3, 2)]).abs() < 1e-12);
    }

    #[test]
    fn eq16_form_with_z_gives_the_same_estimate() {
        // Constant speed: run eq. (16) literally with real matrices and compare.
        let m = MotorParams::low1998();
        let w = rpm(900.0);
        let s = SensorlessSettings {
            ts: TS,
            pole_tau_s: 1e-3,
            discretisation: Discretisation::Truncated,
            speed_filter_tau_s: 1e-3,
            initial_angle_rad: 1.0,
        };
        let mut o = SensorlessObserver::new(&m, s);
        o.omega_hat = w;
        o.filter.preset(w);
        let model = DiscreteModel::new(&m, TS, w, s.discretisation);
        let mx = observer_matrices(&model, o.lambda);
        // D = λ I.
        assert!((mx.d[0][0] - o.lambda).abs() < 1e-12 && mx.d[0][1].abs() < 1e-12);
        let mv = |a: &M2, x: [f64; 2]| {
            [
                a[0][0] * x[0] + a[0][1] * x[1],
                a[1][0] * x[0] + a[1][1] * x[1],
            ]
        };
        let mut xb = [libm::sin(1f64), libm::cos(1f64)];
        let mut z = [0.0; 2];
        let mut first = true;
        for k in 0..200 {
            let th = w * 4.0 * k as f64 * TS;
            let y = [
                0.3 * libm::cos(th) - 1.0 * libm::sin(th),
                0.3 * libm::sin(th) + libm::cos(th),
            ];
            let u = [40.0 * libm::cos(th + 0.2), 40.0 * libm::sin(th + 0.2)];
            if first {
                let v = mv(&mx.v2, y);
                z = [xb[0] - v[0], xb[1] - v[1]];
                first = false;
            }
            let v = mv(&mx.v2, y);
            xb = [z[0] + v[0], z[1] + v[1]];
            let _ = o.step(y[0], y[1], u);
            if k > 0 {
                let got = o.x_b();
                assert!(
                    (got[0] - xb[0]).abs() < 1e-9 && (got[1] - xb[1]).abs() < 1e-9,
                    "k = {k}: {got:?} vs {xb:?}"
                );
            }
            // z(k+1) = D z + E y + G_u u.
            let (a, b, c) = (mv(&mx.d, z), mv(&mx.e, y), mv(&mx.g_u, u));
            z = [a[0] + b[0] + c[0], a[1] + b[1] + c[1]];
            // Keep the speed estimate at w so that the gains stay those of `mx`.
            o.omega_hat = w;
        }
    }

    /// Runs the observer on the plant model at a prescribed speed with a fixed dq voltage
    /// chosen for currents (i_d, i_q); returns the angle errors (deg) per sample.
    fn run_on_plant(disc: Discretisation, init_err_deg: f64, n: usize) -> Vec<f64> {
        let m = MotorParams::low1998();
        let w = rpm(1200.0);
        let we = m.p() * w;
        let (id, iq) = (0.0, 1.0);
        let u = Dq {
            d: m.r_ohm * id - we * m.l_q_h * iq,
            q: m.r_ohm * iq + we * (m.l_d_h * id + m.psi_pm_wb),
        };
        let mut x = MotorState {
            i_d: id,
            i_q: iq,
            omega_m: w,
            theta_m: 0.0,
        };
        let rk = Rk4 { substeps: 8 };
        let mut o = SensorlessObserver::new(
            &m,
            SensorlessSettings {
                ts: TS,
                pole_tau_s: 1e-3,
                discretisation: disc,
                speed_filter_tau_s: 1e-3,
                initial_angle_rad: init_err_deg.to_radians(),
            },
        );
        let mut errs = Vec::new();
        for _ in 0..n {
            let th = x.theta_e(&m);
            let i_ab = inverse_park(Dq { d: x.i_d, q: x.i_q }, th);
            let u_ab: AlphaBeta = inverse_park(u, th + 0.5 * we * TS);
            let est = o.step(i_ab.alpha, i_ab.beta, [u_ab.alpha, u_ab.beta]);
            errs.push(((est.theta_e - th + PI).rem_euclid(TAU) - PI).to_degrees());
            let ud = park(u_ab, th + 0.5 * we * TS);
            x = rk.advance(
                &m,
                Mechanics::PrescribedSpeed(w),
                &x,
                &MotorInput {
                    u_d: ud.d,
                    u_q: ud.q,
                    t_load: 0.0,
                    ..Default::default()
                },
                TS,
            );
        }
        errs
    }

    #[test]
    fn converges_from_90_degrees_to_the_predicted_truncation_bias() {
        let m = MotorParams::low1998();
        for disc in [Discretisation::Truncated, Discretisation::Exact] {
            let e = run_on_plant(disc, 90.0, 2000);
            let ss = e[1900..].iter().sum::<f64>() / 100.0;
            let pred =
                predicted_angle_error(&m, TS, rpm(1200.0), 0.0, 1.0, 1e-3, disc).to_degrees();
            let conv = e.iter().rposition(|x| (x - ss).abs() > 1.0).unwrap() as f64 * TS;
            eprintln!(
                "{disc:?}: steady state {ss:.4}°, predicted {pred:.4}°, within 1° after {:.2} ms",
                conv * 1e3
            );
            assert!((ss - pred).abs() < 0.01, "{disc:?}: {ss} vs {pred}");
            assert!(conv < 0.05, "{disc:?}: converged after {conv} s");
        }
        let t = predicted_angle_error(
            &m,
            TS,
            rpm(1200.0),
            0.0,
            1.0,
            1e-3,
            Discretisation::Truncated,
        )
        .to_degrees();
        let x = predicted_angle_error(&m, TS, rpm(1200.0), 0.0, 1.0, 1e-3, Discretisation::Exact)
            .to_degrees();
        // The truncated model leads by about half a sample of rotation; the exact one does not.
        let half = (m.p() * rpm(1200.0) * TS / 2.0).to_degrees();
        assert!(t > 0.5 * half && t < 1.5 * half, "{t} vs {half}");
        assert!(x.abs() < 0.1 * t.abs(), "{x}");
    }
}
