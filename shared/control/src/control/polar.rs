//! Current control of a surface PMSM with the control inputs in polar coordinates,
//! Miyajima, Fujimoto and Fujitsuna ("Current Control Method with Control Inputs in Polar
//! Coordinates for SPMSM Based on Linearized Model").
//!
//! The input is u = (V_a, δ), the voltage amplitude and phase: v_d = −V_a sin δ,
//! v_q = V_a cos δ (eq. 1). Three current laws are selectable ([`PolarMode`]):
//!
//! * `polar` (section IV): C_21 drives i_q through V_a, C_12 drives i_d through δ, both PI,
//!   on top of the decoupling inputs V_ad, δ_d (eqs 14–16); gains by the coefficient diagram
//!   method (eqs 26–37, [`super::cdm`]) rescheduled every sample from the equilibrium of
//!   eqs (38)–(39). Options, off by default: the loops fed the currents predicted one sample
//!   ahead ([`super::cdm::CdmDelay::Predict`], [`SpmsmModel::predict`]) to compensate the
//!   computation delay; τ_21 other than eq. (36)'s 10·T_u; a weight β of i_q* in C_21's
//!   proportional term ([`PolarSpec`]). The design model is [`super::cdm::QLoop`].
//! * `voltage-phase` (section III, the conventional method): V_a held at V_amax, i_q
//!   controlled through δ by a (filtered) PID placed on the linearised model (2).
//! * `polar-fw` (section III, the proposed method): the same phase controller plus the
//!   voltage-amplitude controller C_v of eq. (11), a PID placed on ΔP_11, driving i_d to
//!   i_d* (= 0) through V_a (reading 6). In flux weakening V_a sits at V_amax and C_v's
//!   states are frozen; when the operating point leaves flux weakening C_v lowers V_a to
//!   stop flux strengthening (i_d > 0), without a mode switch.
//!
//! # Model (eqs 1–2)
//!
//! [`SpmsmModel`]: L = L_d = L_q, K_e = ψ_PM (Wb; the back-EMF is ω_e·K_e with ω_e the
//! electrical speed). Eq. (2) prints ΔA = [∂f/∂x]ᵀ, ΔB = [∂f/∂u]ᵀ; the matrices printed are the
//! Jacobians with rows = components of f (the ᵀ is the gradient-as-column convention), and
//! [`SpmsmModel::linearise`] returns them; a unit test checks them against central differences.
//!
//! # Readings of ambiguous or misprinted equations
//!
//! 1. **Eqs (14)–(15), decoupling.** (14), V_ad = ω_e·√(L²i_q² + (L i_d + K_e)²), is the
//!    amplitude of the speed voltage ω_e·ψ of (1), ψ = (L i_d + K_e, L i_q), and is used as
//!    printed (signed with ω_e, measured currents). (15) prints
//!    tan δ_d = ω_e L i_q/(ω_e L i_d + K_e), which adds a flux K_e to a voltage ω_e L i_d;
//!    we read K_e as ω_e K_e, the
//!    back-EMF, so that (15) is **the phase of the same vector as (14)**:
//!    δ_d = atan(L i_q/(L i_d + K_e)), and V_ad∠δ_d = −ω_e L i_q + j ω_e (L i_d + K_e) exactly
//!    cancels the speed voltage. Both drop R (C_21 is designed on 1/(L s + R), so its
//!    integrator carries R·i_q, and C_12's carries R·i_d). The reading is consistent (one
//!    vector), dimensionally right, independent of ω_e (continuous through standstill) and
//!    insensitive to current noise: |δ_d| ≈ L|i_q|/K_e ≈ 0.19 rad/A near zero current, where
//!    a reading that keeps R, atan2(ω_e L i_q − R i_d, ω_e(L i_d + K_e) + R i_q), becomes
//!    atan2(−R i_d, R i_q) at standstill and swings with the noise over ±90°. At standstill
//!    δ_d ≠ 0 turns C_21's output off the q axis by δ_d (21° at 2 A); C_12 brings i_d back.
//! 2. **Signed amplitude.** δ is limited to ±δ_max = ±π/2 (Fig. 7(d)) and V_a to ±V_amax
//!    (Fig. 7(c) draws ±M_max): the half plane v_q < 0 is reached with V_a < 0, not with
//!    |δ| > π/2. δ_d is folded into [−π/2, π/2] accordingly.
//! 3. **Eqs (38)–(39).** (38) prints δ_o[k] = δ_fb[k−1] + δ_a[k]; δ_a is read as δ_d, the
//!    decoupling phase of sample k. δ_fb[k−1] is what the previous (limited) output held
//!    beyond its decoupling part. V_ao[k] = V_a[k] (39) is the amplitude just computed by
//!    C_21 ("after the q-axis current controller calculation"). Both are limited as the
//!    paper says before any gain is computed: 0.001·V_amax ≤ |V_ao| ≤ V_amax (sign kept),
//!    |δ_o| ≤ 0.9·π/2 ([`super::cdm::limit_operating_point`]).
//! 4. **Eq. (37)** as printed: see [`super::cdm`].
//! 5. **Anti-windup.** An integrator is frozen while its output is limited and its increment
//!    would drive the output further into the limit (the gains of C_12 are negative for
//!    V_ao > 0, so the direction is taken from the increment K_I·e, not from e); the
//!    integrator is also kept within the output range (minus the decoupling feed-forward),
//!    so that the proportional term cannot hide a wound-up integrator.
//! 6. **Section III.** Our copy of the paper has lost the text of section III-A/B (eqs 3–10).
//!    What the remaining text fixes, and what we implement: the phase controller C_δ is
//!    designed on the linearised model (2); C_v is a PID placed on ΔP_11(s) (eq. 11, i_d from
//!    V_a) with all closed-loop poles assigned; C_v's states are not renewed while V_a is
//!    saturated ([`AntiWindup::Freeze`]); the equilibrium is V_ao = V_a[k−1] (V_amax in the
//!    conventional method) and δ_o comes from eq. (9); the real parts of all phase-loop poles
//!    are at −600 rad/s in both methods, of all amplitude-loop poles at −300 rad/s
//!    ([`SIGMA_DELTA_RAD_S`], [`SIGMA_V_RAD_S`], the defaults; a scenario may set others);
//!    at high speed the poles lie on the circle centred at the origin through the plant
//!    poles −R/L ± jω_e (eq. 12); δ is limited to ±π/2. Where we had to fill gaps:
//!    * eq. (9), [`SpmsmModel::fw_phase`]: the phase at which (1) settles with i_q = i_q* under
//!      the amplitude V_ao: V_ao·Z·cos(δ_o − φ) = Z²·i_q* + ω_e K_e R, Z = √(R² + ω_e²L²),
//!      φ = atan2(ω_e L, R); of the two roots the one with δ_o ≤ φ, where ∂i_q/∂δ > 0;
//!      clamped to φ when i_q* is out of reach. It is the design point of both controllers,
//!      not a feed-forward: their integrators carry the operating point;
//!    * both PIDs have a first-order filter on the derivative, C(s) = (q2 s² + q1 s + q0)/
//!      (s(s + f)): an ideal D term is not realisable at T_u with the drive's 1.5-sample delay.
//!      Plant (second order) and PID close to a fourth-order polynomial, and all four poles
//!      are placed ([`place_pid`], linear in f, q2, q1, q0);
//!    * the four poles ([`fw_poles`]): two pairs (s² + 2|σ|s + r²)² on the circle of radius
//!      r = max(|p_1|, |σ|), |p_1| = √((R/L)² + ω_e²); when |σ| > |p_1| the circle cannot
//!      carry real part σ and the four coincide at σ;
//!    * conventional method: the same C_δ with V_a ≡ V_amax and no amplitude controller.
//!
//!    On our motor (L = 30 mH, 800 rpm, V_dc = 100 V) this design does not reproduce the
//!    paper's Figs 2–3: ΔP_22 has a right-half-plane zero at ω_e cot δ_o − R/L (≈ 386 rad/s
//!    at 3 A), inside the −600 rad/s asked of the loop, and with the one-sample delay the
//!    sampled loop at 3 A is unstable ([`FwDesign`], `drivelab cdm-design --speed-rpm`,
//!    docs/paper-departures.md).
//! 7. **Negative speed.** The flux-weakening laws run in the mirrored frame
//!    (ω_e, i_q, V_a, δ) → (−ω_e, −i_q, −V_a, −δ), under which (1) is invariant, so the same
//!    branch of (9) applies in both directions.

use super::cdm;
use super::current::{CurrentInput, VoltageDq};
use crate::motor::MotorParams;
use serde::Serialize;
use std::f64::consts::FRAC_PI_2;

/// Output limit of the voltage phase, ±δ_max = ±π/2 (Fig. 7(d)).
pub const DELTA_MAX: f64 = FRAC_PI_2;
/// Default real part of the phase loop's poles, both methods (section III-C), rad/s.
pub const SIGMA_DELTA_RAD_S: f64 = -600.0;
/// Default real part of the amplitude loop's poles (section III-C), rad/s.
pub const SIGMA_V_RAD_S: f64 = -300.0;

/// Which of the paper's current laws runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum PolarMode {
    /// Section IV: C_21 (i_q via V_a) and C_12 (i_d via δ), CDM gains, decoupling (14)–(15).
    Polar,
    /// Section III, conventional: V_a = V_amax, i_q via δ only.
    VoltagePhase,
    /// Section III, proposed: the phase controller plus the amplitude controller C_v (eq. 11).
    PolarFw,
}

impl PolarMode {
    /// Name used in scenario files and printouts.
    pub fn name(self) -> &'static str {
        match self {
            Self::Polar => "polar",
            Self::VoltagePhase => "voltage-phase",
            Self::PolarFw => "polar-fw",
        }
    }
}

/// Surface PMSM of eq. (1): L = L_d = L_q, back-EMF constant K_e = ψ_PM.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct SpmsmModel {
    /// R, Ω.
    pub r_ohm: f64,
    /// L, H.
    pub l_h: f64,
    /// K_e, Wb (V·s per electrical rad).
    pub k_e_wb: f64,
}

/// Numerator and denominator of (b1 s + b0)/(s² + a1 s + a0).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct SecondOrder {
    /// s coefficient of the numerator.
    pub b1: f64,
    /// Constant of the numerator.
    pub b0: f64,
    /// s coefficient of the denominator.
    pub a1: f64,
    /// Constant of the denominator.
    pub a0: f64,
}

/// A PID with a filtered derivative, C(s) = (q2 s² + q1 s + q0)/(s·(s + f)): in parallel
/// form q2 + K_I/s + B/(s + f) with K_I = q0/f and B = q1 − q2·f − q0/f.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct PidGains {
    /// q2 (high-frequency gain).
    pub q2: f64,
    /// q1, per second.
    pub q1: f64,
    /// q0, per second².
    pub q0: f64,
    /// Pole of the derivative filter f > 0, rad/s.
    pub f: f64,
}

impl PidGains {
    /// Integral gain K_I = q0/f of the parallel form, per second.
    pub fn k_i(&self) -> f64 {
        self.q0 / self.f
    }

    /// Gain B of the filtered branch B/(s + f) of the parallel form, per second.
    pub fn b(&self) -> f64 {
        self.q1 - self.q2 * self.f - self.q0 / self.f
    }

    /// Proportional gain C(s)·s/(...) at low frequency: q1/f − q0/f² (K_P of the ideal
    /// PID the filtered one approximates below f).
    pub fn k_p(&self) -> f64 {
        self.q1 / self.f - self.q0 / (self.f * self.f)
    }
}

/// (V_a, δ) → (v_d, v_q) (eq. 1).
pub fn polar_to_dq(v_a: f64, delta: f64) -> (f64, f64) {
    let (s, c) = libm::sincos(delta);
    (-v_a * s, v_a * c)
}

/// (v_d, v_q) → (V_a, δ) with |δ| ≤ π/2 and V_a signed (reading 2), so that
/// [`polar_to_dq`] inverts it. (0, 0) → (0, 0).
pub fn dq_to_polar(v_d: f64, v_q: f64) -> (f64, f64) {
    let a = libm::atan2(-v_d, v_q);
    let d = fold_half_plane(a);
    let mag = libm::hypot(v_d, v_q);
    (if d == a { mag } else { -mag }, d)
}

/// Folds an angle in (−π, π] into [−π/2, π/2] (the direction of a signed amplitude).
fn fold_half_plane(a: f64) -> f64 {
    if a > FRAC_PI_2 {
        a - std::f64::consts::PI
    } else if a < -FRAC_PI_2 {
        a + std::f64::consts::PI
    } else {
        a
    }
}

impl SpmsmModel {
    /// The model of a surface motor (L = mean of L_d and L_q; the scenario checks they agree).
    pub fn from_motor(m: &MotorParams) -> Self {
        Self {
            r_ohm: m.r_ohm,
            l_h: 0.5 * (m.l_d_h + m.l_q_h),
            k_e_wb: m.psi_pm_wb,
        }
    }

    /// Eq. (1): f(x, u) = dx/dt for x = [i_d, i_q], u = [V_a, δ] at electrical speed ω_e.
    pub fn f(&self, x: [f64; 2], u: [f64; 2], omega_e: f64) -> [f64; 2] {
        let (v_d, v_q) = polar_to_dq(u[0], u[1]);
        let a = self.r_ohm / self.l_h;
        [
            -a * x[0] + omega_e * x[1] + v_d / self.l_h,
            -omega_e * x[0] - a * x[1] + (v_q - omega_e * self.k_e_wb) / self.l_h,
        ]
    }

    /// Eq. (2): the Jacobians (ΔA, ΔB) of (1) at input u_o (row i = component i of f).
    pub fn linearise(&self, u_o: [f64; 2], omega_e: f64) -> ([[f64; 2]; 2], [[f64; 2]; 2]) {
        let a = self.r_ohm / self.l_h;
        let l = self.l_h;
        let (s, c) = libm::sincos(u_o[1]);
        (
            [[-a, omega_e], [-omega_e, -a]],
            [[-s / l, -u_o[0] * c / l], [c / l, -u_o[0] * s / l]],
        )
    }

    /// Steady-state voltage (v_d, v_q) that holds the currents (i_d, i_q) at ω_e (f = 0).
    pub fn steady_voltage(&self, i_d: f64, i_q: f64, omega_e: f64) -> (f64, f64) {
        (
            self.r_ohm * i_d - omega_e * self.l_h * i_q,
            self.r_ohm * i_q + omega_e * (self.l_h * i_d + self.k_e_wb),
        )
    }

    /// Decoupling inputs (V_ad, δ_d), eqs (14)–(15) in the reading of the module docs: the
    /// amplitude and phase of the speed voltage ω_e·(L i_d + K_e, L i_q) of (1).
    pub fn decoupling(&self, i_d: f64, i_q: f64, omega_e: f64) -> (f64, f64) {
        let l = self.l_h;
        let v_ad = omega_e * libm::hypot(l * i_q, l * i_d + self.k_e_wb);
        (
            v_ad,
            fold_half_plane(libm::atan2(l * i_q, l * i_d + self.k_e_wb)),
        )
    }

    /// The currents one period `ts` after (i_d, i_q) under the constant voltage (u_d, u_q)
    /// at ω_e: the exact solution of (1), x(T) = e^{AT} x + A⁻¹(e^{AT} − I) b.
    pub fn predict(
        &self,
        i_d: f64,
        i_q: f64,
        u_d: f64,
        u_q: f64,
        omega_e: f64,
        ts: f64,
    ) -> (f64, f64) {
        let (a, w, l) = (self.r_ohm / self.l_h, omega_e, self.l_h);
        let (sn, cs) = libm::sincos(w * ts);
        let ea = libm::exp(-a * ts);
        // e^{AT} = e^{−aT}·[[cos, sin], [−sin, cos]].
        let (e11, e12, e21, e22) = (ea * cs, ea * sn, -ea * sn, ea * cs);
        let (b1, b2) = (u_d / l, (u_q - w * self.k_e_wb) / l);
        // A⁻¹ = [[−a, −ω], [ω, −a]]/(a² + ω²).
        let n = a * a + w * w;
        let (m1, m2) = ((e11 - 1.0) * b1 + e12 * b2, e21 * b1 + (e22 - 1.0) * b2);
        (
            e11 * i_d + e12 * i_q + (-a * m1 - w * m2) / n,
            e21 * i_d + e22 * i_q + (w * m1 - a * m2) / n,
        )
    }

    /// Eq. (9) (reconstructed, module docs reading 6): the equilibrium phase at amplitude
    /// `v_ao` ≥ 0 with i_q = `i_q` at ω_e ≥ 0, the root δ_o ≤ φ; φ when out of reach.
    pub fn fw_phase(&self, v_ao: f64, i_q: f64, omega_e: f64) -> f64 {
        let (r, l) = (self.r_ohm, self.l_h);
        let z = libm::hypot(r, omega_e * l);
        let phi = self.max_torque_phase(omega_e);
        let c = (z * z * i_q + omega_e * self.k_e_wb * r) / (v_ao * z);
        let c = if c.is_nan() { 1.0 } else { c.clamp(-1.0, 1.0) };
        phi - libm::acos(c)
    }

    /// ΔP_11(s) = Δi_d/ΔV_a of the full model (2) at (V_ao, δ_o, ω_e).
    pub fn plant_11(&self, delta_o: f64, omega_e: f64) -> SecondOrder {
        let a = self.r_ohm / self.l_h;
        let (s, c) = libm::sincos(delta_o);
        SecondOrder {
            b1: -s / self.l_h,
            b0: (omega_e * c - a * s) / self.l_h,
            a1: 2.0 * a,
            a0: a * a + omega_e * omega_e,
        }
    }

    /// ΔP_22(s) = Δi_q/Δδ of the full model (2) at (V_ao, δ_o, ω_e).
    pub fn plant_22(&self, v_ao: f64, delta_o: f64, omega_e: f64) -> SecondOrder {
        let p = self.plant_11(delta_o, omega_e);
        SecondOrder {
            b1: v_ao * p.b1,
            b0: v_ao * p.b0,
            ..p
        }
    }

    /// φ = atan2(ω_e L, R): the phase of the largest i_q at a given amplitude (the steady
    /// state of (1) gives i_q ∝ cos(δ − φ) + const).
    pub fn max_torque_phase(&self, omega_e: f64) -> f64 {
        libm::atan2(omega_e * self.l_h, self.r_ohm)
    }

    /// |p_1| = √((R/L)² + ω_e²): radius of the circle through the plant poles (eq. 12).
    pub fn pole_radius(&self, omega_e: f64) -> f64 {
        libm::hypot(self.r_ohm / self.l_h, omega_e)
    }
}

/// Coefficients (d3, d2, d1, d0) of s⁴ + d3 s³ + d2 s² + d1 s + d0 for the phase loop
/// (module docs reading 6): two pairs with real part `sigma` < 0 on the circle centred at
/// the origin of radius r = max(`rho`, |σ|): (s² + 2|σ| s + r²)². When ρ ≤ |σ| the four
/// poles coincide at σ.
pub fn fw_poles(sigma: f64, rho: f64) -> [f64; 4] {
    let s_ = sigma.abs();
    let r2 = libm::pow(rho.max(s_), 2.0);
    let (c1, c0) = (2.0 * s_, r2);
    [2.0 * c1, c1 * c1 + 2.0 * c0, 2.0 * c1 * c0, c0 * c0]
}

/// The filtered PID that places the closed loop of plant `p` at s⁴ + d3 s³ + d2 s² + d1 s + d0:
/// s(s + f)(s² + a1 s + a0) + (b1 s + b0)(q2 s² + q1 s + q0) is linear in (f, q2, q1, q0).
/// None when the plant's numerator and denominator share a root (no unique solution), or
/// the solution has f ≤ 0 (an unstable or integrating filter) or is not finite.
pub fn place_pid(p: &SecondOrder, d: [f64; 4]) -> Option<PidGains> {
    let [d3, d2, d1, d0] = d;
    let (b1, b0, a1, a0) = (p.b1, p.b0, p.a1, p.a0);
    if b0.abs() < 1e-12 * (a0.abs() + b1.abs() * a1.abs()).max(1e-300) {
        return None;
    }
    let q0 = d0 / b0;
    // Unknowns (f, q2, q1):  f + b1 q2 = d3 − a1;  a1 f + b0 q2 + b1 q1 = d2 − a0;
    // a0 f + b0 q1 = d1 − b1 q0.
    let m = [[1.0, b1, 0.0], [a1, b0, b1], [a0, 0.0, b0]];
    let rhs = [d3 - a1, d2 - a0, d1 - b1 * q0];
    let det3 = |m: &[[f64; 3]; 3]| {
        m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
            - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
            + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0])
    };
    let det = det3(&m);
    // det is the resultant of N and D (up to sign): zero when they share a root.
    let scale = b0.abs() * b0.abs().max(b1.abs() * a1.abs().max(a0.abs().sqrt()));
    if !(det.is_finite() && det.abs() > 1e-9 * scale) {
        return None;
    }
    let mut k = [0.0; 3];
    for (j, kj) in k.iter_mut().enumerate() {
        let mut mj = m;
        for (row, r) in mj.iter_mut().zip(rhs) {
            row[j] = r;
        }
        *kj = det3(&mj) / det;
    }
    let g = PidGains {
        f: k[0],
        q2: k[1],
        q1: k[2],
        q0,
    };
    let ok = g.f > 1e-9 && [g.f, g.q2, g.q1, g.q0].iter().all(|v| v.is_finite());
    ok.then_some(g)
}

/// The controller closing one loop of [`sampled_poles`], with the discretisation the law
/// runs it with: a PI as [`ScheduledPi`] (C_21, C_12 of section IV) or a filtered PID as
/// [`ScheduledPid`] (C_δ, C_v of section III).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum LoopController {
    /// K_P·e + x_I, the integrator by forward Euler.
    Pi {
        /// K_P.
        k_p: f64,
        /// K_I, per second.
        k_i: f64,
    },
    /// q2·e + x_I + z, the filter exact for e held over the sample.
    Pid(PidGains),
}

/// One loop of [`sampled_poles`]: its controller, the current it measures (0: i_d, 1: i_q)
/// and the input it writes (0: V_a, 1: δ).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SampledLoop {
    /// The controller.
    pub c: LoopController,
    /// Measured current: 0 i_d, 1 i_q.
    pub measured: usize,
    /// Written input: 0 V_a, 1 δ.
    pub input: usize,
    /// Added to the written input from the same sample's measured (i_d, i_q), per ampere:
    /// a static term the law adds beside the controller (section IV's phase δ_d,
    /// linearised); zero for none.
    pub direct: [f64; 2],
}

/// Closed-loop poles (z-plane) of current loops linearised at the input u_o = (V_ao, δ_o)
/// and ω_e as they run: plant (2) under a zero-order hold of T_u, the command of sample k
/// applied over [t_{k+1}, t_{k+2}) (one-sample computation delay), each of `loops` (at most
/// one per input) as its [`LoopController`] says, none limited. An input no loop writes is
/// held at u_o.
pub fn sampled_poles(
    md: &SpmsmModel,
    u_o: [f64; 2],
    omega_e: f64,
    ts: f64,
    loops: &[SampledLoop],
) -> Vec<nalgebra::Complex<f64>> {
    use nalgebra::{DMatrix, Matrix4};
    let (a, b) = md.linearise(u_o, omega_e);
    // Zero-order hold: exp([[A, B], [0, 0]]·T_u).
    let mut m = Matrix4::<f64>::zeros();
    for i in 0..2 {
        for j in 0..2 {
            m[(i, j)] = a[i][j] * ts;
            m[(i, j + 2)] = b[i][j] * ts;
        }
    }
    let e = m.exp();
    // States: i_d, i_q, the held input of each loop, then each loop's x_I (and z of a PID).
    let held = 2 + loops.len();
    let n = held
        + loops
            .iter()
            .map(|l| match l.c {
                LoopController::Pi { .. } => 1,
                LoopController::Pid(_) => 2,
            })
            .sum::<usize>();
    let mut c = DMatrix::<f64>::zeros(n, n);
    for i in 0..2 {
        for j in 0..2 {
            c[(i, j)] = e[(i, j)];
        }
        for (h, l) in loops.iter().enumerate() {
            c[(i, 2 + h)] = e[(i, 2 + l.input)];
        }
    }
    // A controller on measurement `y` (e = −y) writing the held input `u`, states from `k`.
    let mut k = held;
    for (h, l) in loops.iter().enumerate() {
        let (u, y) = (2 + h, l.measured);
        let (q2, k_i) = match l.c {
            LoopController::Pi { k_p, k_i } => (k_p, k_i),
            LoopController::Pid(g) => (g.q2, g.k_i()),
        };
        c[(u, y)] = -q2;
        for (j, g) in l.direct.iter().enumerate() {
            c[(u, j)] += g;
        }
        c[(u, k)] = 1.0;
        c[(k, k)] = 1.0;
        c[(k, y)] = -k_i * ts;
        k += 1;
        if let LoopController::Pid(g) = l.c {
            let phi = libm::exp(-g.f * ts);
            c[(u, k)] = 1.0;
            c[(k, k)] = phi;
            c[(k, y)] = -g.b() * (1.0 - phi) / g.f;
            k += 1;
        }
    }
    crate::math::eigenvalues(c)
}

/// Poles z of a loop sampled at `ts` as ln(z)/T_u (re, im), rad/s, sorted.
pub fn per_second(z: &[nalgebra::Complex<f64>], ts: f64) -> Vec<(f64, f64)> {
    sorted(
        z.iter()
            .map(|z| {
                let l = crate::math::cln(*z) / ts;
                (l.re, l.im)
            })
            .collect(),
    )
}

/// [`sampled_poles`] of the flux-weakening loops at (V_ao, δ_o, ω_e): C_δ on i_q writing δ
/// and, when `g_v` is given, C_v on i_d writing V_a (else V_a is held at V_ao).
pub fn fw_sampled_poles(
    md: &SpmsmModel,
    v_ao: f64,
    delta_o: f64,
    omega_e: f64,
    ts: f64,
    g_delta: &PidGains,
    g_v: Option<&PidGains>,
) -> Vec<nalgebra::Complex<f64>> {
    let mut loops = vec![SampledLoop {
        c: LoopController::Pid(*g_delta),
        measured: 1,
        input: 1,
        direct: [0.0; 2],
    }];
    if let Some(g) = g_v {
        loops.push(SampledLoop {
            c: LoopController::Pid(*g),
            measured: 0,
            input: 0,
            direct: [0.0; 2],
        });
    }
    sampled_poles(md, [v_ao, delta_o], omega_e, ts, &loops)
}

/// [`sampled_poles`] of the section IV design `d` at standstill (ω_e = 0) at its operating
/// point (V_ao, δ_o), for a motor of flux `k_e_wb`: C_21 on i_q writing V_a and C_12 on i_d
/// writing δ with the gains of eqs (28)–(31), the currents measured (no prediction). Of the
/// decoupling, V_ad is 0 at 0 rpm; its phase δ_d = atan2(L i_q, L i_d + K_e), which the law
/// adds to C_12's δ from the same sample's currents, enters linearised at the operating
/// point's currents (V_ao∠δ_o)/R. The gains' scheduling on δ_o does not enter: at the
/// equilibrium the errors they multiply are zero. As ln(z)/T_u, rad/s.
pub fn cdm_sampled_poles(d: &cdm::CdmDesign, k_e_wb: f64) -> Vec<(f64, f64)> {
    let md = SpmsmModel {
        r_ohm: d.r_ohm,
        l_h: d.l_h,
        k_e_wb: 0.0,
    };
    let loops = cdm_loops(d, delta_d_gains(d, k_e_wb));
    per_second(
        &sampled_poles(&md, [d.v_ao_v, d.delta_o_rad], 0.0, d.tu_s, &loops),
        d.tu_s,
    )
}

/// C_21 (i_q → V_a) and C_12 (i_d → δ, with `delta_d` added to its δ) of design `d`.
fn cdm_loops(d: &cdm::CdmDesign, delta_d: [f64; 2]) -> [SampledLoop; 2] {
    let pi = |k_p, k_i, measured, input, direct| SampledLoop {
        c: LoopController::Pi { k_p, k_i },
        measured,
        input,
        direct,
    };
    [
        pi(d.k_p21, d.k_i21, 1, 0, [0.0; 2]),
        pi(d.k_p12, d.k_i12, 0, 1, delta_d),
    ]
}

/// ∂δ_d/∂(i_d, i_q), rad/A, at the standstill currents of `d`'s operating point:
/// δ_d = atan2(Y, X) with X = L i_d + K_e, Y = L i_q gives (−L·Y, L·X)/(X² + Y²).
/// Zero where δ_d has no slope (no flux and no current).
fn delta_d_gains(d: &cdm::CdmDesign, k_e_wb: f64) -> [f64; 2] {
    let (u_d, u_q) = polar_to_dq(d.v_ao_v, d.delta_o_rad);
    let l = d.l_h;
    let (x, y) = (l * u_d / d.r_ohm + k_e_wb, l * u_q / d.r_ohm);
    let n = x * x + y * y;
    if n > 0.0 && n.is_finite() {
        [-l * y / n, l * x / n]
    } else {
        [0.0; 2]
    }
}

/// The section III design at one operating point, for printing and checking
/// (`drivelab cdm-design --speed-rpm`).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct FwDesign {
    /// ω_e, rad/s.
    pub omega_e: f64,
    /// V_ao after the limits, V.
    pub v_ao_v: f64,
    /// i_q* of the equilibrium, A.
    pub i_q_ref_a: f64,
    /// δ_o from (9), limited to 0.9·π/2, rad.
    pub delta_o_rad: f64,
    /// i_d of the equilibrium (V_ao, δ_o), A.
    pub i_d_o_a: f64,
    /// Radius of the circle through the plant poles −R/L ± jω_e (eq. 12), rad/s.
    pub rho_rad_s: f64,
    /// ΔP_22 = Δi_q/Δδ.
    pub p22: SecondOrder,
    /// ΔP_11 = Δi_d/ΔV_a.
    pub p11: SecondOrder,
    /// Zero of ΔP_22, rad/s (> 0: right half plane).
    pub zero_22_rad_s: f64,
    /// Zero of ΔP_11, rad/s.
    pub zero_11_rad_s: f64,
    /// Real part asked of the phase loop's poles, rad/s.
    pub sigma_delta_rad_s: f64,
    /// Real part asked of the amplitude loop's poles, rad/s.
    pub sigma_v_rad_s: f64,
    /// Placed poles of 1 + ΔP_22 C_δ (re, im), rad/s.
    pub poles_delta: Vec<(f64, f64)>,
    /// Placed poles of 1 + ΔP_11 C_v (re, im), rad/s (eq. 11).
    pub poles_v: Vec<(f64, f64)>,
    /// C_δ, or None when it cannot be placed.
    pub g_delta: Option<PidGains>,
    /// C_v, or None when it cannot be placed.
    pub g_v: Option<PidGains>,
    /// Sampled loop of C_δ alone (V_a = V_ao), poles as ln(z)/T_u (re, im), rad/s.
    pub sampled_delta: Vec<(f64, f64)>,
    /// Sampled loop of C_δ and C_v together, poles as ln(z)/T_u, rad/s.
    pub sampled_both: Vec<(f64, f64)>,
}

/// Roots of s⁴ + d3 s³ + d2 s² + d1 s + d0 as (re, im), sorted.
fn quartic_roots(d: [f64; 4]) -> Vec<(f64, f64)> {
    let m = nalgebra::DMatrix::from_row_slice(
        4,
        4,
        &[
            -d[0], -d[1], -d[2], -d[3], //
            1.0, 0.0, 0.0, 0.0, //
            0.0, 1.0, 0.0, 0.0, //
            0.0, 0.0, 1.0, 0.0,
        ],
    );
    sorted(
        crate::math::eigenvalues(m)
            .iter()
            .map(|c| (c.re, c.im))
            .collect(),
    )
}

fn sorted(mut v: Vec<(f64, f64)>) -> Vec<(f64, f64)> {
    v.sort_by(|p, q| p.0.total_cmp(&q.0).then(p.1.total_cmp(&q.1)));
    v
}

impl FwDesign {
    /// Both section III controllers at V_ao (limited), i_q*, ω_e ≥ 0, as [`PolarCurrentController`]
    /// designs them every sample.
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        md: &SpmsmModel,
        v_ao: f64,
        i_q_ref: f64,
        omega_e: f64,
        ts: f64,
        v_amax: f64,
        sigma_delta: f64,
        sigma_v: f64,
    ) -> Self {
        let (v_o, _) = cdm::limit_operating_point(v_ao, 0.0, v_amax);
        let d_o = md
            .fw_phase(v_o, i_q_ref, omega_e)
            .clamp(-cdm::DELTA_O_MAX, cdm::DELTA_O_MAX);
        let (vd, _) = polar_to_dq(v_o, d_o);
        let i_d_o = (vd + omega_e * md.l_h * i_q_ref) / md.r_ohm;
        let rho = md.pole_radius(omega_e);
        let (p22, p11) = (md.plant_22(v_o, d_o, omega_e), md.plant_11(d_o, omega_e));
        let (dd, dv) = (fw_poles(sigma_delta, rho), fw_poles(sigma_v, rho));
        let (g_delta, g_v) = (place_pid(&p22, dd), place_pid(&p11, dv));
        let to_s = |v: Vec<nalgebra::Complex<f64>>| per_second(&v, ts);
        let (sampled_delta, sampled_both) = match (&g_delta, &g_v) {
            (Some(gd), Some(gv)) => (
                to_s(fw_sampled_poles(md, v_o, d_o, omega_e, ts, gd, None)),
                to_s(fw_sampled_poles(md, v_o, d_o, omega_e, ts, gd, Some(gv))),
            ),
            (Some(gd), None) => (
                to_s(fw_sampled_poles(md, v_o, d_o, omega_e, ts, gd, None)),
                vec![],
            ),
            _ => (vec![], vec![]),
        };
        Self {
            omega_e,
            v_ao_v: v_o,
            i_q_ref_a: i_q_ref,
            delta_o_rad: d_o,
            i_d_o_a: i_d_o,
            rho_rad_s: rho,
            p22,
            p11,
            zero_22_rad_s: -p22.b0 / p22.b1,
            zero_11_rad_s: -p11.b0 / p11.b1,
            sigma_delta_rad_s: sigma_delta,
            sigma_v_rad_s: sigma_v,
            poles_delta: quartic_roots(dd),
            poles_v: quartic_roots(dv),
            g_delta,
            g_v,
            sampled_delta,
            sampled_both,
        }
    }
}

/// The filtered PID [`PidGains`] in parallel form with a feed-forward, output limits and
/// conditional integration. Gains are passed in every step (gain scheduling); both states
/// are in output units, so a gain change does not move them.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct ScheduledPid {
    /// Integrator state (output units).
    pub x_i: f64,
    /// State of the filtered branch B/(s + f) (output units).
    pub z: f64,
}

/// When [`ScheduledPid`] renews its states.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum AntiWindup {
    /// The filter always; the integrator unless the output is limited and its increment
    /// points further into the limit (C_δ).
    Conditional,
    /// Neither state while the output is limited (C_v, section III-B: "the state variables
    /// of the voltage amplitude controller is not renewed").
    Freeze,
}

impl ScheduledPid {
    /// One step: ff + q2·e + x_I + z limited to [lo, hi]. The filter is discretised exactly
    /// for e held over the sample; the integrator by forward Euler; `aw` says when they are
    /// renewed.
    #[allow(clippy::too_many_arguments)]
    pub fn step(
        &mut self,
        g: &PidGains,
        e: f64,
        ff: f64,
        lo: f64,
        hi: f64,
        ts: f64,
        aw: AntiWindup,
    ) -> (f64, bool) {
        let v = ff + g.q2 * e + self.x_i + self.z;
        let out = v.clamp(lo, hi);
        if aw == AntiWindup::Freeze && out != v {
            return (out, true);
        }
        let phi = libm::exp(-g.f * ts);
        let z = phi * self.z + g.b() * (1.0 - phi) / g.f * e;
        if z.is_finite() {
            self.z = z;
        }
        let inc = g.k_i() * ts * e;
        let winding = (v > hi && inc > 0.0) || (v < lo && inc < 0.0);
        if !winding && inc.is_finite() {
            // The integrator alone never leaves the output range either.
            self.x_i = (self.x_i + inc).clamp(lo, hi);
        }
        (out, out != v)
    }
}

/// A PI in parallel form with scheduled gains and conditional integration (the C_21 and
/// C_12 of eqs 24–25): the integrator is frozen while the output is limited and the
/// increment points further into the limit, and is kept within [lo − ff, hi − ff].
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct ScheduledPi {
    /// Integrator state (output units).
    pub x_i: f64,
}

impl ScheduledPi {
    /// One step: ff + K_P e + x_I limited to [lo, hi]; returns the output and whether it
    /// was limited.
    #[allow(clippy::too_many_arguments)]
    pub fn step(
        &mut self,
        k_p: f64,
        k_i: f64,
        e: f64,
        ff: f64,
        lo: f64,
        hi: f64,
        ts: f64,
    ) -> (f64, bool) {
        let v = ff + k_p * e + self.x_i;
        let out = v.clamp(lo, hi);
        let inc = k_i * ts * e;
        let winding = (v > hi && inc > 0.0) || (v < lo && inc < 0.0);
        if !winding && inc.is_finite() {
            // The integrator alone never drives the output beyond its range either.
            self.x_i = (self.x_i + inc).clamp(lo - ff, hi - ff);
        }
        (out, out != v)
    }
}

/// Settings of the polar current laws, all derived from the motor, T_u and V_amax.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct PolarSpec {
    /// Which law.
    pub mode: PolarMode,
    /// Plant model.
    pub model: SpmsmModel,
    /// Control period T_u, s.
    pub tu_s: f64,
    /// Voltage limit V_amax, V (V_dc/√3).
    pub v_amax_v: f64,
    /// Section III: real part of the phase loop's poles, rad/s (default −600).
    pub sigma_delta_rad_s: f64,
    /// Section III: real part of the amplitude loop's poles, rad/s (default −300).
    pub sigma_v_rad_s: f64,
    /// Section IV: how C_21 and C_12 treat the one-sample computation delay.
    pub cdm_delay: cdm::CdmDelay,
    /// Section IV: τ_21 in samples T_u (eq. 36: 10).
    pub cdm_tau21_samples: f64,
    /// Section IV: weight β of i_q* in C_21's proportional term, K_P21·(β·i_q* − i_q)
    /// (the paper: 1, a PI on the error).
    pub cdm_setpoint_weight: f64,
}

impl PolarSpec {
    /// The paper's design for `mode`: σ_δ = −600 rad/s, σ_v = −300 rad/s, CDM on the
    /// delay-free plant.
    pub fn paper(mode: PolarMode, model: SpmsmModel, tu_s: f64, v_amax_v: f64) -> Self {
        Self {
            mode,
            model,
            tu_s,
            v_amax_v,
            sigma_delta_rad_s: SIGMA_DELTA_RAD_S,
            sigma_v_rad_s: SIGMA_V_RAD_S,
            cdm_delay: cdm::CdmDelay::Paper,
            cdm_tau21_samples: cdm::TAU_SAMPLES,
            cdm_setpoint_weight: 1.0,
        }
    }
}

/// What a scenario's polar design looks like (`summary.json` → `design.polar`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct PolarDesign {
    /// The law and its inputs.
    pub spec: PolarSpec,
    /// CDM γ_1 (eqs 32, 34).
    pub gamma1: f64,
    /// τ_21 = 10·T_u, s.
    pub tau21_s: f64,
    /// a_1 of (26), 1/s.
    pub a1_21: f64,
    /// a_0 of (26), 1/s².
    pub a0_21: f64,
    /// K_P21 at δ_o = 0 (eq. 28), V/A.
    pub k_p21_at_0: f64,
    /// K_I21 at δ_o = 0 (eq. 29), V/(A·s).
    pub k_i21_at_0: f64,
    /// Lower limit of |V_ao|, V.
    pub v_ao_min_v: f64,
    /// Limit of |δ_o|, rad.
    pub delta_o_max_rad: f64,
    /// Output limit of |δ|, rad.
    pub delta_max_rad: f64,
    /// Real part of the phase loop's poles (section III), rad/s.
    pub sigma_delta_rad_s: f64,
    /// Real part of the amplitude loop's poles (section III), rad/s.
    pub sigma_v_rad_s: f64,
}

impl PolarDesign {
    /// The design summary for `spec`.
    pub fn new(spec: &PolarSpec) -> Self {
        let tau21 = spec.cdm_tau21_samples * spec.tu_s;
        let (a1, a0) = cdm::cdm_second_order(cdm::GAMMA1, tau21);
        let (kp, ki) = cdm::gains_21(spec.model.r_ohm, spec.model.l_h, a1, a0, 0.0);
        Self {
            spec: *spec,
            gamma1: cdm::GAMMA1,
            tau21_s: tau21,
            a1_21: a1,
            a0_21: a0,
            k_p21_at_0: kp,
            k_i21_at_0: ki,
            v_ao_min_v: cdm::V_AO_MIN_FRAC * spec.v_amax_v,
            delta_o_max_rad: cdm::DELTA_O_MAX,
            delta_max_rad: DELTA_MAX,
            sigma_delta_rad_s: spec.sigma_delta_rad_s,
            sigma_v_rad_s: spec.sigma_v_rad_s,
        }
    }
}

/// The polar current controller (all three modes). No allocation in [`Self::step`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PolarCurrentController {
    spec: PolarSpec,
    a1_21: f64,
    a0_21: f64,
    // Section IV.
    c21: ScheduledPi,
    c12: ScheduledPi,
    delta_fb_prev: f64,
    // Section III.
    c_delta: ScheduledPid,
    c_v: ScheduledPid,
    g_delta: PidGains,
    g_v: PidGains,
    v_a_prev: Option<f64>,
    started: bool,
    /// Last output (V_a, δ) in the motor's frame.
    pub last: (f64, f64),
    /// Samples where V_a was limited to ±V_amax.
    pub v_a_limited_samples: u64,
    /// Samples where δ was limited to ±δ_max.
    pub delta_limited_samples: u64,
    /// Samples where |V_ao| sat at its lower limit 0.001·V_amax (near the uncontrollable
    /// point V_a ≈ 0 of eq. 13).
    pub near_zero_amplitude_samples: u64,
    /// Samples where a flux-weakening PID could not be placed and kept its last gains.
    pub kept_gains_samples: u64,
}

impl PolarCurrentController {
    /// A controller for `spec`, at rest.
    pub fn new(spec: &PolarSpec) -> Self {
        let d = PolarDesign::new(spec);
        Self {
            spec: *spec,
            a1_21: d.a1_21,
            a0_21: d.a0_21,
            c21: ScheduledPi::default(),
            c12: ScheduledPi::default(),
            delta_fb_prev: 0.0,
            c_delta: ScheduledPid::default(),
            c_v: ScheduledPid::default(),
            g_delta: PidGains::default(),
            g_v: PidGains::default(),
            v_a_prev: None,
            started: false,
            last: (0.0, 0.0),
            v_a_limited_samples: 0,
            delta_limited_samples: 0,
            near_zero_amplitude_samples: 0,
            kept_gains_samples: 0,
        }
    }

    /// The settings.
    pub fn spec(&self) -> &PolarSpec {
        &self.spec
    }

    /// One control step: references, measured currents and ω_e → (v_d, v_q).
    pub fn step(&mut self, x: &CurrentInput) -> VoltageDq {
        let (v_a, delta, limited) = match self.spec.mode {
            PolarMode::Polar => self.step_polar(x),
            PolarMode::VoltagePhase | PolarMode::PolarFw => self.step_fw(x),
        };
        self.last = (v_a, delta);
        let (u_d, u_q) = polar_to_dq(v_a, delta);
        VoltageDq {
            u_d,
            u_q,
            saturated: limited,
        }
    }

    /// Section IV: eqs (14)–(16), (24)–(39).
    fn step_polar(&mut self, x: &CurrentInput) -> (f64, f64, bool) {
        let sp = self.spec;
        let (r, l, vmax, ts) = (sp.model.r_ohm, sp.model.l_h, sp.v_amax_v, sp.tu_s);
        // Delay compensation (option): the command of this sample acts from t_{k+1} on, so
        // the loops see the currents at t_{k+1}, predicted from the measurement under the
        // command already on its way (a Smith-type predictor of the model (1)).
        let predicted;
        let x = match sp.cdm_delay {
            cdm::CdmDelay::Paper => x,
            cdm::CdmDelay::Predict => {
                let (u_d, u_q) = polar_to_dq(self.last.0, self.last.1);
                let (i_d, i_q) = sp.model.predict(x.i_d, x.i_q, u_d, u_q, x.omega_e, ts);
                predicted = CurrentInput { i_d, i_q, ..*x };
                &predicted
            }
        };
        let (v_ad, delta_d) = sp.model.decoupling(x.i_d, x.i_q, x.omega_e);
        // (38): δ_o[k] = δ_fb[k−1] + δ_d[k], limited.
        let (_, d_o) = cdm::limit_operating_point(vmax, self.delta_fb_prev + delta_d, vmax);
        let (kp21, ki21) = cdm::gains_21(r, l, self.a1_21, self.a0_21, d_o);
        // Set-point weight (option): K_P21·(β i_q* − i_q) = K_P21·e − K_P21·(1 − β)·i_q*.
        let beta = sp.cdm_setpoint_weight;
        let ff = if beta == 1.0 {
            v_ad
        } else {
            v_ad - kp21 * (1.0 - beta) * x.i_q_ref
        };
        let (v_a, v_lim) = self
            .c21
            .step(kp21, ki21, x.i_q_ref - x.i_q, ff, -vmax, vmax, ts);
        // (39): V_ao[k] = V_a[k], limited; (37) and (30)–(31).
        let (v_o, d_o) = cdm::limit_operating_point(v_a, d_o, vmax);
        if v_o.abs() <= cdm::V_AO_MIN_FRAC * vmax {
            self.near_zero_amplitude_samples += 1;
        }
        let t12 = cdm::tau12(v_o, d_o, ts, vmax);
        let (a1, a0) = cdm::cdm_second_order(cdm::GAMMA1, t12);
        let (kp12, ki12) = cdm::gains_12(r, l, a1, a0, v_o, d_o);
        let (delta, d_lim) = self.c12.step(
            kp12,
            ki12,
            x.i_d_ref - x.i_d,
            delta_d,
            -DELTA_MAX,
            DELTA_MAX,
            ts,
        );
        self.delta_fb_prev = delta - delta_d;
        self.v_a_limited_samples += u64::from(v_lim);
        self.delta_limited_samples += u64::from(d_lim);
        (v_a, delta, v_lim || d_lim)
    }

    /// Section III: the phase controller, with V_a = V_amax (conventional) or from the
    /// amplitude controller C_v (proposed).
    fn step_fw(&mut self, x: &CurrentInput) -> (f64, f64, bool) {
        let sp = self.spec;
        let (vmax, ts, md) = (sp.v_amax_v, sp.tu_s, &sp.model);
        // Mirror to ω_e ≥ 0 (reading 7).
        let s = if x.omega_e < 0.0 { -1.0 } else { 1.0 };
        let w = s * x.omega_e;
        let (i_q, i_q_ref) = (s * x.i_q, s * x.i_q_ref);
        let rho = md.pole_radius(w);
        if !self.started {
            // Bumpless start at the equilibrium of the first references (reading 6: the
            // integrators carry the operating point).
            self.started = true;
            let (a, b) = md.steady_voltage(x.i_d_ref, i_q_ref, w);
            let v0 = match sp.mode {
                PolarMode::PolarFw => libm::hypot(a, b).min(vmax),
                _ => vmax,
            };
            let (v_o, _) = cdm::limit_operating_point(v0, 0.0, vmax);
            self.c_v.x_i = v0;
            self.c_delta.x_i = md.fw_phase(v_o, i_q_ref, w).clamp(-DELTA_MAX, DELTA_MAX);
            self.v_a_prev = Some(v0);
        }
        // Both controllers are designed at V_ao = V_a[k−1] (V_amax in the conventional
        // method) and δ_o from (9) (reading 6).
        let prev = match sp.mode {
            PolarMode::PolarFw => self.v_a_prev.unwrap_or(vmax),
            _ => vmax,
        };
        let (v_o, _) = cdm::limit_operating_point(prev, 0.0, vmax);
        if v_o <= cdm::V_AO_MIN_FRAC * vmax {
            self.near_zero_amplitude_samples += 1;
        }
        let d_o = md
            .fw_phase(v_o, i_q_ref, w)
            .clamp(-cdm::DELTA_O_MAX, cdm::DELTA_O_MAX);
        let mut v_lim = false;
        let v_a = match sp.mode {
            PolarMode::PolarFw => {
                // C_v: all four poles of 1 + ΔP_11 C_v = 0 (eq. 11) placed.
                match place_pid(&md.plant_11(d_o, w), fw_poles(sp.sigma_v_rad_s, rho)) {
                    Some(g) => self.g_v = g,
                    None => self.kept_gains_samples += 1,
                }
                let (v, lim) = self.c_v.step(
                    &self.g_v,
                    x.i_d_ref - x.i_d,
                    0.0,
                    0.0,
                    vmax,
                    ts,
                    AntiWindup::Freeze,
                );
                v_lim = lim;
                v
            }
            _ => vmax,
        };
        self.v_a_prev = Some(v_a);
        // C_δ: all four poles of 1 + ΔP_22 C_δ = 0 placed.
        match place_pid(
            &md.plant_22(v_o, d_o, w),
            fw_poles(sp.sigma_delta_rad_s, rho),
        ) {
            Some(g) => self.g_delta = g,
            None => self.kept_gains_samples += 1,
        }
        let (delta, d_lim) = self.c_delta.step(
            &self.g_delta,
            i_q_ref - i_q,
            0.0,
            -DELTA_MAX,
            DELTA_MAX,
            ts,
            AntiWindup::Conditional,
        );
        self.v_a_limited_samples += u64::from(v_lim || sp.mode == PolarMode::VoltagePhase);
        self.delta_limited_samples += u64::from(d_lim);
        (s * v_a, s * delta, v_lim || d_lim)
    }

    /// Bumpless take-over: presets the integrators so that the next output at zero error is
    /// the voltage `u` (e.g. the one the plant is applying), at operating point `x`.
    pub fn preset(&mut self, u: VoltageDq, x: &CurrentInput) {
        let (v_a, delta) = dq_to_polar(u.u_d, u.u_q);
        let md = self.spec.model;
        match self.spec.mode {
            PolarMode::Polar => {
                let (v_ad, delta_d) = md.decoupling(x.i_d, x.i_q, x.omega_e);
                self.c21.x_i = v_a - v_ad;
                self.c12.x_i = delta - delta_d;
                self.delta_fb_prev = delta - delta_d;
            }
            PolarMode::VoltagePhase | PolarMode::PolarFw => {
                let s = if x.omega_e < 0.0 { -1.0 } else { 1.0 };
                self.c_delta = ScheduledPid {
                    x_i: s * delta,
                    z: 0.0,
                };
                self.c_v = ScheduledPid {
                    x_i: s * v_a,
                    z: 0.0,
                };
                self.v_a_prev = Some(s * v_a);
                self.started = true;
            }
        }
        self.last = (v_a, delta);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::motor::{Mechanics, MotorInput, MotorState, Rk4};

    fn motor() -> MotorParams {
        MotorParams::low1998()
    }

    fn spec(mode: PolarMode, v_dc: f64) -> PolarSpec {
        PolarSpec::paper(
            mode,
            SpmsmModel::from_motor(&motor()),
            1e-4,
            v_dc / 3f64.sqrt(),
        )
    }

    /// Coefficients (d3, d2, d1, d0) of s(s + f)(s² + a1 s + a0) + (b1 s + b0)(q2 s² + q1 s + q0).
    fn closed_loop(p: &SecondOrder, g: &PidGains) -> [f64; 4] {
        [
            p.a1 + g.f + p.b1 * g.q2,
            p.a0 + g.f * p.a1 + p.b1 * g.q1 + p.b0 * g.q2,
            g.f * p.a0 + p.b1 * g.q0 + p.b0 * g.q1,
            p.b0 * g.q0,
        ]
    }

    /// Section IV at 0 rpm: the poles `cdm_sampled_poles` gives equal the eigenvalues of the
    /// running law's own one-sample map (the controller's step and the exact plant under a
    /// held command, one sample late), differentiated numerically at its equilibrium. At 2 A
    /// (V_ao = 5 V) the decoupling phase δ_d moves them: left out (as before), the poles
    /// differ from the law's by far more than the tolerance.
    #[test]
    fn the_section_iv_sampled_poles_are_those_of_the_running_law() {
        let sp = spec(PolarMode::Polar, 470.0);
        let md = sp.model;
        let (ts, vmax) = (sp.tu_s, sp.v_amax_v);
        for (v_ao, delta_o) in [(5.0, 0.0), (5.0, 0.3), (100.0, 0.0)] {
            let d = cdm::CdmDesign::new(md.r_ohm, md.l_h, ts, vmax, v_ao, delta_o, None);
            // The equilibrium at 0 rpm: i = u/R, the errors zero, V_a = x_I21 (V_ad = 0),
            // δ = δ_d + x_I12.
            let (u_d, u_q) = polar_to_dq(v_ao, delta_o);
            let i_o = [u_d / md.r_ohm, u_q / md.r_ohm];
            let (_, delta_d) = md.decoupling(i_o[0], i_o[1], 0.0);
            let x_o = [i_o[0], i_o[1], v_ao, delta_o, v_ao, delta_o - delta_d];
            // x = (i_d, i_q, held V_a, held δ, x_I21, x_I12) → the same one sample later.
            let step = |x: &[f64; 6]| -> [f64; 6] {
                let mut c = PolarCurrentController::new(&sp);
                c.c21.x_i = x[4];
                c.c12.x_i = x[5];
                c.delta_fb_prev = delta_o - delta_d;
                let cmd = c.step(&CurrentInput {
                    i_d_ref: i_o[0],
                    i_q_ref: i_o[1],
                    i_d: x[0],
                    i_q: x[1],
                    omega_e: 0.0,
                });
                let (hd, hq) = polar_to_dq(x[2], x[3]);
                let (i_d, i_q) = md.predict(x[0], x[1], hd, hq, 0.0, ts);
                let (v_a, delta) = c.last;
                assert!(cmd.u_d.is_finite() && cmd.u_q.is_finite());
                [i_d, i_q, v_a, delta, c.c21.x_i, c.c12.x_i]
            };
            let at = step(&x_o);
            for (a, b) in at.iter().zip(x_o) {
                assert!((a - b).abs() < 1e-9 * (1.0 + b.abs()), "{at:?} {x_o:?}");
            }
            let mut jac = nalgebra::DMatrix::<f64>::zeros(6, 6);
            for j in 0..6 {
                let h = 1e-6 * (1.0 + x_o[j].abs());
                let (mut up, mut dn) = (x_o, x_o);
                up[j] += h;
                dn[j] -= h;
                let (fu, fd) = (step(&up), step(&dn));
                for i in 0..6 {
                    jac[(i, j)] = (fu[i] - fd[i]) / (2.0 * h);
                }
            }
            let law: Vec<_> = jac.complex_eigenvalues().iter().copied().collect();
            let law = per_second(&law, ts);
            let near = |a: &[(f64, f64)], b: &[(f64, f64)]| {
                a.len() == b.len()
                    && a.iter().zip(b).all(|(p, q)| {
                        libm::hypot(p.0 - q.0, p.1 - q.1) < 1e-3 * (1.0 + libm::hypot(q.0, q.1))
                    })
            };
            let model = cdm_sampled_poles(&d, md.k_e_wb);
            assert!(
                near(&law, &model),
                "V_ao {v_ao}: law {law:?}, model {model:?}"
            );
            if v_ao == 5.0 {
                let loops = cdm_loops(&d, [0.0; 2]);
                let md0 = SpmsmModel { k_e_wb: 0.0, ..md };
                let z = sampled_poles(&md0, [v_ao, delta_o], 0.0, ts, &loops);
                let without = per_second(&z, ts);
                assert!(!near(&law, &without), "V_ao {v_ao}: {law:?} {without:?}");
            }
        }
    }

    /// Eq. (2) against central differences of eq. (1) at several equilibria and non-equilibria.
    #[test]
    fn linearisation_matches_a_numerical_jacobian() {
        let md = SpmsmModel::from_motor(&motor());
        for (x, u, w) in [
            ([0.0, 2.0], [5.0, 0.0], 0.0),
            ([-0.4, 2.0], [57.7, 0.6], 335.1),
            ([0.3, -1.0], [-20.0, -0.3], -167.5),
            ([1.0, 1.0], [100.0, 1.3], 50.0),
        ] {
            let (a, b) = md.linearise(u, w);
            for j in 0..2 {
                let h = 1e-6;
                let (mut xp, mut xm) = (x, x);
                xp[j] += h;
                xm[j] -= h;
                let (fp, fm) = (md.f(xp, u, w), md.f(xm, u, w));
                let (mut up, mut um) = (u, u);
                let hu = 1e-6 * u[j].abs().max(1.0);
                up[j] += hu;
                um[j] -= hu;
                let (gp, gm) = (md.f(x, up, w), md.f(x, um, w));
                for i in 0..2 {
                    let na = (fp[i] - fm[i]) / (2.0 * h);
                    let nb = (gp[i] - gm[i]) / (2.0 * hu);
                    assert!(
                        (na - a[i][j]).abs() <= 1e-6 * a[i][j].abs().max(1.0),
                        "A[{i}][{j}]"
                    );
                    assert!(
                        (nb - b[i][j]).abs() <= 1e-5 * b[i][j].abs().max(1.0),
                        "B[{i}][{j}] {nb} vs {}",
                        b[i][j]
                    );
                }
            }
        }
    }

    #[test]
    fn polar_and_dq_round_trip_with_a_signed_amplitude() {
        for (vd, vq) in [
            (3.0, 4.0),
            (-3.0, 4.0),
            (3.0, -4.0),
            (-3.0, -4.0),
            (0.0, 0.0),
            (-2.0, 0.0),
            (2.0, 0.0),
        ] {
            let (v, d) = dq_to_polar(vd, vq);
            assert!(d.abs() <= FRAC_PI_2 + 1e-15, "{d}");
            let (a, b) = polar_to_dq(v, d);
            assert!(
                (a - vd).abs() < 1e-12 && (b - vq).abs() < 1e-12,
                "({vd},{vq}) -> ({v},{d}) -> ({a},{b})"
            );
        }
    }

    #[test]
    fn decoupling_is_the_speed_voltage_in_polar_form() {
        let md = SpmsmModel::from_motor(&motor());
        let (l, k) = (md.l_h, md.k_e_wb);
        // Standstill: no amplitude; the phase is that of the flux vector, independent of ω_e,
        // and small at small currents (L/K_e ≈ 0.19 rad/A), whatever the noise.
        let (v, d) = md.decoupling(0.0, 2.0, 0.0);
        assert_eq!(v, 0.0);
        assert!((d - libm::atan2(l * 2.0, k)).abs() < 1e-15);
        let (_, d) = md.decoupling(0.003, -0.002, 0.0);
        assert!(d.abs() < l * 0.002 / (k - l * 0.003) * 1.001, "{d}");
        // At speed: V_ad∠δ_d is ω_e·(L i_d + K_e, L i_q), the speed voltage of (1):
        // v_d = −V_ad sin δ_d = −ω_e L i_q, v_q = V_ad cos δ_d = ω_e (L i_d + K_e).
        let w = 167.55;
        for (i_d, i_q) in [(0.0, 2.0), (-1.0, 1.5), (0.4, -0.7)] {
            let (v, d) = md.decoupling(i_d, i_q, w);
            let (vd, vq) = polar_to_dq(v, d);
            assert!((vd + w * l * i_q).abs() < 1e-9 && (vq - w * (l * i_d + k)).abs() < 1e-9);
            // Eq. (14) as printed.
            assert!((v - w * libm::hypot(l * i_q, l * i_d + k)).abs() < 1e-9);
        }
        // Negative speed: V_ad < 0, the same phase (signed amplitude, reading 2).
        let (v, d) = md.decoupling(0.0, 2.0, -w);
        let (_, d_pos) = md.decoupling(0.0, 2.0, w);
        assert!(v < 0.0 && d == d_pos);
    }

    #[test]
    fn fw_phase_is_the_equilibrium_of_eq_1() {
        let md = SpmsmModel::from_motor(&motor());
        let w = 4.0 * 800.0 * std::f64::consts::PI / 30.0;
        for (v, iq) in [(57.735, 0.0), (57.735, 2.0), (80.0, 1.0), (270.0, 3.0)] {
            let d = md.fw_phase(v, iq, w);
            // Solve f = 0 for i_d at this (V, δ): both rows must hold with i_q = iq.
            let (vd, _) = polar_to_dq(v, d);
            let i_d = (vd + w * md.l_h * iq) / md.r_ohm;
            let f = md.f([i_d, iq], [v, d], w);
            assert!(f[0].abs() < 1e-9 && f[1].abs() < 1e-6, "{v} {iq}: {f:?}");
            // The branch where more phase gives more i_q.
            let g = md.plant_22(v, d, w);
            assert!(g.b0 / g.a0 > 0.0, "{v} {iq}");
        }
        // Out of reach: clamped at φ, finite.
        let d = md.fw_phase(10.0, 5.0, w);
        assert!((d - libm::atan2(w * md.l_h, md.r_ohm)).abs() < 1e-12);
        assert!(md.fw_phase(0.0, 0.0, 0.0).is_finite());
    }

    #[test]
    fn pid_places_the_four_poles() {
        let md = SpmsmModel::from_motor(&motor());
        let w = 335.1;
        for (p, sigma) in [
            (md.plant_22(57.7, 0.6, w), -600.0),
            (md.plant_11(0.2, w), -300.0),
            (md.plant_22(270.0, 0.9, 167.5), -600.0),
        ] {
            let d = fw_poles(sigma, md.pole_radius(w));
            let g = place_pid(&p, d).unwrap();
            let got = closed_loop(&p, &g);
            for i in 0..4 {
                assert!(
                    (got[i] - d[i]).abs() < 1e-9 * d[i].abs(),
                    "{i}: {got:?} vs {d:?}"
                );
            }
            // Parallel form q2 + K_I/s + B/(s + f) is the same transfer function.
            let s0 = 700.0;
            let c1 = (g.q2 * s0 * s0 + g.q1 * s0 + g.q0) / (s0 * (s0 + g.f));
            let c2 = g.q2 + g.k_i() / s0 + g.b() / (s0 + g.f);
            assert!((c1 - c2).abs() < 1e-12 * c1.abs().max(1.0));
        }
        // Two pairs on the circle through the plant poles when it is larger than |σ|:
        // (s² + 600 s + 345²)².
        let d = fw_poles(-300.0, 345.0);
        let (c1, c0) = (600.0f64, 345.0f64 * 345.0);
        assert_eq!(d, [2.0 * c1, c1 * c1 + 2.0 * c0, 2.0 * c1 * c0, c0 * c0]);
        // Four poles at σ when the circle is smaller: (s + 600)⁴.
        let q = fw_poles(-600.0, 345.0);
        let want = [2400.0, 6.0 * 3.6e5, 4.0 * 2.16e8, 1.296e11];
        for i in 0..4 {
            assert!((q[i] - want[i]).abs() < 1e-9 * want[i], "{q:?}");
        }
        // Numerator and denominator sharing a root: none.
        let p = SecondOrder {
            b1: 1.0,
            b0: 2.0,
            a1: 3.0,
            a0: 2.0,
        }; // (s + 2)/((s + 1)(s + 2))
        assert!(place_pid(&p, d).is_none());
    }

    /// Section III at 800 rpm, V_dc = 100 V (the flux-weakening scenarios): both designs put
    /// their poles where asked, and the sampled loop shows why the paper's −600 rad/s fails.
    #[test]
    fn section_iii_designs_place_the_asked_poles() {
        let md = SpmsmModel::from_motor(&motor());
        let w = 4.0 * 800.0 * std::f64::consts::PI / 30.0;
        let vmax = 100.0 / 3f64.sqrt();
        let rho = md.pole_radius(w);
        assert!(rho > 300.0 && rho < 600.0, "{rho}");
        for iq in [0.5, 3.0] {
            let f = FwDesign::new(&md, vmax, iq, w, 1e-4, vmax, -600.0, -300.0);
            // C_v: real parts −300, on the circle through the plant poles (eq. 12), as a
            // double pair (fw_poles): roots of a double root are accurate to ~√ε relative.
            for &(re, im) in &f.poles_v {
                assert!((re + 300.0).abs() < 1e-6 * 300.0, "{:?}", f.poles_v);
                assert!(
                    (libm::hypot(re, im) - rho).abs() < 1e-6 * rho,
                    "{:?}",
                    f.poles_v
                );
            }
            // C_δ: |σ| = 600 > ρ, so all four at −600 (a quadruple root: ~ε^¼ ≈ 1e-4 relative).
            for &(re, im) in &f.poles_delta {
                assert!((re + 600.0).abs() < 1e-3 * 600.0 && im.abs() < 1e-3 * 600.0);
            }
            // The gains close the loops on exactly those polynomials.
            for (p, g, want) in [
                (f.p11, f.g_v.unwrap(), fw_poles(-300.0, rho)),
                (f.p22, f.g_delta.unwrap(), fw_poles(-600.0, rho)),
            ] {
                let got = closed_loop(&p, &g);
                for i in 0..4 {
                    assert!((got[i] - want[i]).abs() < 1e-9 * want[i].abs());
                }
            }
        }
        // The phase loop's zero: right half plane, inside |σ| = 600 at 3 A, beyond it at 0.5 A.
        let hi = FwDesign::new(&md, vmax, 3.0, w, 1e-4, vmax, -600.0, -300.0);
        let lo = FwDesign::new(&md, vmax, 0.5, w, 1e-4, vmax, -600.0, -300.0);
        assert!(hi.zero_22_rad_s > 0.0 && hi.zero_22_rad_s < 600.0);
        assert!(lo.zero_22_rad_s > 600.0);
        // As it runs (one-sample delay): unstable at 3 A, stable at 0.5 A.
        let unstable = |v: &[(f64, f64)]| v.iter().any(|p| p.0 > 0.0);
        assert!(unstable(&hi.sampled_delta) && unstable(&hi.sampled_both));
        assert!(!unstable(&lo.sampled_delta) && !unstable(&lo.sampled_both));
    }

    #[test]
    fn amplitude_controller_states_are_not_renewed_while_saturated() {
        let g = PidGains {
            q2: 2.0,
            q1: 900.0,
            q0: 2e5,
            f: 2000.0,
        };
        let mut c = ScheduledPid { x_i: 50.0, z: 1.0 };
        let (v, lim) = c.step(&g, 10.0, 0.0, 0.0, 57.7, 1e-4, AntiWindup::Freeze);
        assert!(lim && v == 57.7);
        assert_eq!((c.x_i, c.z), (50.0, 1.0));
        // Inside the limits both states move.
        let (_, lim) = c.step(&g, 0.1, 0.0, 0.0, 57.7, 1e-4, AntiWindup::Freeze);
        assert!(!lim && c.x_i != 50.0 && c.z != 1.0);
    }

    #[test]
    fn prediction_is_the_exact_solution_of_eq_1() {
        let md = SpmsmModel::from_motor(&motor());
        for (i_d, i_q, u_d, u_q, w) in [
            (0.0, 0.0, 0.0, 50.0, 0.0),
            (0.3, 1.5, -12.0, 40.0, 335.1),
            (-1.0, -2.0, 20.0, -70.0, -167.5),
        ] {
            let (pd, pq) = md.predict(i_d, i_q, u_d, u_q, w, 1e-4);
            // RK4 with 1000 steps of 0.1 µs: error ~h⁴, far below 1e-9 A.
            let mut x = [i_d, i_q];
            let (v_a, delta) = dq_to_polar(u_d, u_q);
            let h = 1e-7;
            for _ in 0..1000 {
                let k1 = md.f(x, [v_a, delta], w);
                let k2 = md.f(
                    [x[0] + 0.5 * h * k1[0], x[1] + 0.5 * h * k1[1]],
                    [v_a, delta],
                    w,
                );
                let k3 = md.f(
                    [x[0] + 0.5 * h * k2[0], x[1] + 0.5 * h * k2[1]],
                    [v_a, delta],
                    w,
                );
                let k4 = md.f([x[0] + h * k3[0], x[1] + h * k3[1]], [v_a, delta], w);
                for j in 0..2 {
                    x[j] += h / 6.0 * (k1[j] + 2.0 * k2[j] + 2.0 * k3[j] + k4[j]);
                }
            }
            assert!(
                (pd - x[0]).abs() < 1e-9 && (pq - x[1]).abs() < 1e-9,
                "{pd} {pq} {x:?}"
            );
        }
    }

    /// The drive's timing: command k applied on [t_{k+1}, t_{k+2}).
    fn simulate(
        c: &mut PolarCurrentController,
        w_m: f64,
        n: usize,
        iq_ref: impl Fn(usize) -> f64,
        noise: f64,
    ) -> Vec<(f64, f64, f64, f64)> {
        let m = motor();
        let rk = Rk4 { substeps: 4 };
        let mech = Mechanics::PrescribedSpeed(w_m);
        let mut x = MotorState {
            omega_m: w_m,
            ..Default::default()
        };
        let mut u_prev = (0.0, 0.0);
        let mut out = Vec::with_capacity(n);
        // Deterministic pseudo-noise (LCG), uniform in ±noise·√3 (σ = noise).
        let mut seed: u64 = 12345;
        let mut rnd = || {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((seed >> 11) as f64 / (1u64 << 53) as f64 - 0.5) * 2.0 * 3f64.sqrt() * noise
        };
        for k in 0..n {
            let inp = CurrentInput {
                i_d_ref: 0.0,
                i_q_ref: iq_ref(k),
                i_d: x.i_d + rnd(),
                i_q: x.i_q + rnd(),
                omega_e: m.p() * w_m,
            };
            let u = c.step(&inp);
            x = rk.advance(
                &m,
                mech,
                &x,
                &MotorInput {
                    u_d: u_prev.0,
                    u_q: u_prev.1,
                    t_load: 0.0,
                    ..Default::default()
                },
                1e-4,
            );
            u_prev = (u.u_d, u.u_q);
            out.push((x.i_d, x.i_q, c.last.0, c.last.1));
        }
        out
    }

    #[test]
    fn polar_law_reaches_the_step_without_steady_state_error() {
        for rpm in [0.0, 400.0] {
            let mut c = PolarCurrentController::new(&spec(PolarMode::Polar, 470.0));
            let r = simulate(
                &mut c,
                rpm * std::f64::consts::PI / 30.0,
                300,
                |k| if k >= 10 { 2.0 } else { 0.0 },
                0.0,
            );
            let (i_d, i_q, _, _) = *r.last().unwrap();
            assert!(
                (i_q - 2.0).abs() < 1e-3 && i_d.abs() < 1e-3,
                "{rpm} rpm: {i_d} {i_q}"
            );
        }
    }

    #[test]
    fn near_zero_amplitude_the_phase_stays_bounded() {
        // Standstill, zero references, noisy currents: V_a ≈ 0, where (13) loses rank.
        let mut c = PolarCurrentController::new(&spec(PolarMode::Polar, 470.0));
        let r = simulate(&mut c, 0.0, 20_000, |_| 0.0, 0.01);
        assert!(c.near_zero_amplitude_samples > 0);
        for &(i_d, i_q, v, d) in &r {
            assert!(i_d.is_finite() && i_q.is_finite() && v.is_finite() && d.is_finite());
            assert!(d.abs() <= DELTA_MAX && v.abs() <= 271.4);
        }
        // No runaway: the phase integrator holds no more than the limit.
        assert!(c.c12.x_i.abs() <= 2.0 * DELTA_MAX, "{}", c.c12.x_i);
    }
}
