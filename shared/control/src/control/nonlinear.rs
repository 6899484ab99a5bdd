//! Two-step linearising speed control of a salient-pole PMSM, Kyslan et al. 2015 (§3–§5).
//!
//! Step 1, direct compensation (eqs 9–10): the two speed–current products of eqs (1)–(2)
//! are cancelled by feed-forward voltages. Step 2, input–output linearisation (eqs 12–26):
//! the coordinates x_R = T(x) of eq. (20) turn the compensated model (11) into the linear
//! "dummy" system (26), controlled by integral state-space controllers (27) placed by pole
//! placement. Eqs (28)–(31) are that controller written back in motor quantities.
//!
//! # Notation
//!
//! State x = [x1, x2, x3] = [ω (mechanical rad/s), i_q, i_d], input u = [u1, u2] = [u_q, u_d],
//! disturbance z = T_L, as in eq. (6). From eqs (1)–(4) (amplitude-invariant dq, hence 3/2):
//!
//! | constant | value | | constant | value |
//! |---|---|---|---|---|
//! | a1 | 3pψ/(2J) | | a5 | pψ/L_q |
//! | a2 | 3p(L_d − L_q)/(2J) | | a6 | R/L_d |
//! | a3 | R/L_q | | a7 | pL_q/L_d |
//! | a4 | pL_d/L_q | | b21, b32, e | 1/L_q, 1/L_d, 1/J |
//!
//! # Readings of ambiguous or misprinted equations
//!
//! 1. Eq. (8): E is printed with two rows; it is E = [−e, 0, 0]ᵀ (the load acts on ω only).
//! 2. Eqs (21)–(22) drop the load: with it, ẋ_R1 = x_R2 − e·T_L. The load is therefore a
//!    disturbance at the input of the first integrator of (26), rejected by the integral
//!    action of v1 (27); it is not compensated.
//! 3. Eq. (25): the second row prints `r_2 x_R3`. We read **r3·x_R3**: eq. (26) has −r3 in
//!    the x_R3 row and eq. (29) has r3·x3, and only r3 makes the field subsystem's pole a
//!    free parameter.
//! 4. Eq. (28): v2 there is the virtual input v_R2 of (25)–(26) written back in current
//!    units, **v2 = v_R2/(a1 + a2 x3)** (the same substitution as w2 = w_R2/(a1 + a2 x3) of
//!    eq. 30); v3 = v_R3 because x_R3 = x3. Expanding M⁻¹ of eq. (24) in (25) gives (28)
//!    exactly under this reading (unit test `law_28_29_is_law_25_written_back`).
//! 5. Eq. (27), i = 2, is integrated in the transformed coordinates, as printed:
//!    v_R2 = K2∫(w_R2 − x_R2)dt. Integrating v2 = K2∫(w2 − x2)dt in motor units instead
//!    gives d/dt[(a1 + a2 x3)·v2] = K2(w_R2 − x_R2) + a2·ẋ3·v2: whenever i_d moves, the
//!    torque loop's integrator is kicked, i.e. the torque/flux decoupling is lost during an
//!    i_d step. v2 of (28) is then v_R2/(a1 + a2 x3) (reading 4).
//! 6. Eq. (31): the speed reference w1 does not appear; it **enters only through the
//!    integrator v1 = K1∫(w1 − x1)dt** of eq. (27) (i = 1). The speed controller is "I + state
//!    feedback": w_R2 = v1 − r11·x_R1 − r12·x_R2 − d12·v_R2, whose division by (a1 + a2 x3)
//!    (eq. 30) is eq. (31). The closed loop from w1 to ω has no zero, so no reference
//!    prefilter is needed (the PI cascade needs one). d12 multiplies v_R2 (the state of the
//!    inner integrator), r12 multiplies x_R2: eq. (31)'s `a1(r12 x2 + d12 v2) + a2(d12 v2 x3 +
//!    r12 x2 x3)` is (a1 + a2 x3)(r12 x2 + d12 v2) = r12 x_R2 + d12 v_R2.
//! 7. Eq. (19)'s k2 = b32(a1 + a2 x3) yields t2 = x3 only up to a constant factor; we take
//!    eq. (20) as printed: x_R3 = x3.
//! 8. Damping 0.6 (§6) is given to every pole pair: the field loop s² + r3 s + K3, the
//!    inner torque loop s² + r2 s + K2 and the two pairs of the speed subsystem's
//!    closed loop (see [`design_nonlinear`]).
//! 9. Friction (b_nms) is not in the paper's model; the law ignores it and the integral
//!    action of v1 rejects it like a load.
//! 10. ω in eqs (1)–(3) is the mechanical speed (it appears as p·ω in the voltage equations),
//!     so x1 and the speed set-point of 70 rad/s are mechanical.
//! 11. §6 loads the motor "in t = 0.02 s", the instant of the i_d step; we follow
//!     docs/architecture.md, "Paper conventions":
//!     i_d* = −1.6 A at 20 ms, nominal load at 40 ms.
//!
//! # Design ([`design_nonlinear`])
//!
//! Every pole pair gets damping 0.6. The field loop and the inner torque loop (the dummy
//! system's r2, K2 and r3, K3) get the natural frequency ω_i (chosen by the drive from the
//! current-loop time constant, see `drive::nonlinear_inner_frequency`). The speed subsystem
//! (four states: x_R1, x_R2, v_R2, v1) is placed at (s² + 2ζω_0 s + ω_0²)(s² + 2ζω_i s + ω_i²),
//! which gives the closed forms K1 = ω_0², r11 = 2ζω_0(ω_0 + ω_i)/ω_i, r12 = (ω_0/ω_i)²,
//! d12 = 2ζω_0/ω_i². ω_0 is solved by bisection so that the *sampled* design model
//! [`NlLoopModel`] (the drive's own discrete law and timing) first reaches the set-point at
//! the target, as the PI design is solved on its sampled cascade. The paper's continuous
//! dummy system with the same gains is reported beside it: the computation delay, the 1 kHz
//! speed law and the speed filter cost the sampled loop damping (≈ 28 % overshoot instead of
//! the ≈ 10 % of the continuous design for the Kyslan motor at 10 kHz; dominant pair at
//! damping 0.37 on the loop that runs).
//!
//! [`NlPlacement::Sampled`] (an option, not the paper's) places on the loop that runs
//! ([`NlLoopModel::lifted_matrix`]): the dominant pair at (ζ, ω_0) exactly through K1, r11
//! ([`place_dominant_pair`]), every other pole as fast as r12, d12 and the torque loop's
//! r2, K2 can make it ([`place_on_sampled_loop`]); the field loop keeps (ζ, ω_i).
//!
//! # Split across the processes (Fig. 2)
//!
//! The speed-loop process ([`NlSpeedLaw`], every N samples) runs the outer law: the integrator
//! v1, the speed feedback r11·x1, and eq. (30) at the flux-current set-point w3. It sends
//! the result as the q-current reference of `CurrentRef`, scaled to the q current it settles
//! to (so that the current limit i_q_max means the same as for the PI cascade):
//! `i_q_ref = (v1 − r11 x1)/(g·(a1 + a2 w3))`, with g = 1 + r12 + d12·r2 the steady-state gain
//! from (v1 − r11 x1) to x_R2 of the closed inner loop.
//!
//! The current-loop process ([`NlCurrentLaw`], every sample) recovers (v1 − r11 x1) =
//! i_q_ref·g·(a1 + a2 w3) exactly, adds the inner-state terms of eq. (31), −r12·x_R2 −
//! d12·v_R2, which feed back states of the current loop and must run at its rate, integrates
//! v_R2 and v3 (27), and computes u_q, u_d from (28)–(29) and (9)–(10). The trace's
//! i_q_ref is w2 of eq. (30), the reference the q integrator actually tracks.
//!
//! # Controllability (eq. 15)
//!
//! Everything divides by a1 + a2 x3, zero at i_d = −ψ/(L_d − L_q). [`KyslanModel::factor`]
//! flags a value below [`NEAR_SINGULAR`]·a1 (the torque per ampere of i_q has fallen to half
//! its PM value) and clamps it at [`GUARD`]·a1 > 0, so the law never divides by zero.

use crate::control::current::CurrentInput;
use crate::control::filter::Bessel2;
use crate::motor::{Mechanics, MotorInput, MotorParams, MotorState, Rk4};
use crate::observer::EncoderObserver;
use serde::{Deserialize, Serialize};

/// Damping of every pole pair (Kyslan §6: "damping coefficient d = 0.6").
pub const DAMPING: f64 = 0.6;
/// a1 + a2·x3 below this fraction of a1 counts as approaching the singularity of eq. (15).
pub const NEAR_SINGULAR: f64 = 0.5;
/// a1 + a2·x3 is never used below this fraction of a1 (no division by zero).
pub const GUARD: f64 = 0.1;

/// The constants of the state-space model (5)–(8).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct KyslanModel {
    /// 3pψ/(2J), rad/(s²·A).
    pub a1: f64,
    /// 3p(L_d − L_q)/(2J), rad/(s²·A²).
    pub a2: f64,
    /// R/L_q, 1/s.
    pub a3: f64,
    /// p·L_d/L_q.
    pub a4: f64,
    /// p·ψ/L_q, A/rad.
    pub a5: f64,
    /// R/L_d, 1/s.
    pub a6: f64,
    /// p·L_q/L_d.
    pub a7: f64,
    /// 1/L_q, 1/H.
    pub b21: f64,
    /// 1/L_d, 1/H.
    pub b32: f64,
    /// 1/J, 1/(kg·m²).
    pub e: f64,
}

/// a1 + a2·x3 after the controllability guard.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Factor {
    /// The value used (≥ GUARD·a1).
    pub value: f64,
    /// Below NEAR_SINGULAR·a1.
    pub near_singular: bool,
    /// Below GUARD·a1 and clamped.
    pub clamped: bool,
}

type V3 = [f64; 3];

impl KyslanModel {
    /// The constants of a motor.
    pub fn new(m: &MotorParams) -> Self {
        let p = m.p();
        Self {
            a1: 1.5 * p * m.psi_pm_wb / m.j_kgm2,
            a2: 1.5 * p * (m.l_d_h - m.l_q_h) / m.j_kgm2,
            a3: m.r_ohm / m.l_q_h,
            a4: p * m.l_d_h / m.l_q_h,
            a5: p * m.psi_pm_wb / m.l_q_h,
            a6: m.r_ohm / m.l_d_h,
            a7: p * m.l_q_h / m.l_d_h,
            b21: 1.0 / m.l_q_h,
            b32: 1.0 / m.l_d_h,
            e: 1.0 / m.j_kgm2,
        }
    }

    /// A(x), eq. (7).
    pub fn a(&self, x: V3) -> V3 {
        [
            self.a1 * x[1] + self.a2 * x[1] * x[2],
            -self.a3 * x[1] - self.a4 * x[0] * x[2] - self.a5 * x[0],
            -self.a6 * x[2] + self.a7 * x[0] * x[1],
        ]
    }

    /// ẋ = A(x) + B u + E T_L, eq. (5); u = [u_q, u_d].
    pub fn f(&self, x: V3, u: [f64; 2], t_load: f64) -> V3 {
        let a = self.a(x);
        [
            a[0] - self.e * t_load,
            a[1] + self.b21 * u[0],
            a[2] + self.b32 * u[1],
        ]
    }

    /// The direct compensation [u_com1, u_com2] of eq. (10).
    pub fn compensation(&self, x: V3) -> [f64; 2] {
        [
            self.a4 * x[0] * x[2] / self.b21,
            -self.a7 * x[0] * x[1] / self.b32,
        ]
    }

    /// Drift of the compensated model (11).
    pub fn a_compensated(&self, x: V3) -> V3 {
        [
            self.a1 * x[1] + self.a2 * x[1] * x[2],
            -self.a3 * x[1] - self.a5 * x[0],
            -self.a6 * x[2],
        ]
    }

    /// a1 + a2·x3: the factor of eq. (15) (zero ⇔ Q_R singular), unguarded.
    pub fn factor_raw(&self, x3: f64) -> f64 {
        self.a1 + self.a2 * x3
    }

    /// a1 + a2·x3 with the controllability guard.
    pub fn factor(&self, x3: f64) -> Factor {
        let raw = self.factor_raw(x3);
        let min = GUARD * self.a1;
        Factor {
            value: if raw < min { min } else { raw },
            near_singular: raw < NEAR_SINGULAR * self.a1,
            clamped: raw < min,
        }
    }

    /// The i_d of eq. (15) where the controllability matrix is singular, −ψ/(L_d − L_q), A;
    /// None for a non-salient motor.
    pub fn singular_i_d(&self) -> Option<f64> {
        (self.a2 != 0.0).then(|| -self.a1 / self.a2)
    }

    /// Controllability matrix Q_R of eq. (14): columns b1, N·b1, b2.
    pub fn controllability(&self, x: V3) -> [V3; 3] {
        let k = self.factor_raw(x[2]);
        [
            [0.0, self.b21 * k, 0.0],
            [self.b21, -self.a3 * self.b21, 0.0],
            [0.0, 0.0, self.b32],
        ]
    }

    /// x_R = T(x), eq. (20).
    pub fn transform(&self, x: V3) -> V3 {
        [x[0], self.factor_raw(x[2]) * x[1], x[2]]
    }

    /// A_R(x) = [x_R2, f_R2, f_R3], eq. (22).
    pub fn a_r(&self, x: V3) -> V3 {
        let k = self.factor_raw(x[2]);
        [
            k * x[1],
            k * (-self.a3 * x[1] - self.a5 * x[0]) - self.a2 * self.a6 * x[1] * x[2],
            -self.a6 * x[2],
        ]
    }

    /// B_R(x), eq. (23) (rows x_R1..x_R3, columns u10, u20).
    pub fn b_r(&self, x: V3) -> [[f64; 2]; 3] {
        let m = self.m(x);
        [[0.0, 0.0], m[0], m[1]]
    }

    /// M(x) of eq. (24), B_R = I_R·M.
    pub fn m(&self, x: V3) -> [[f64; 2]; 2] {
        [
            [self.b21 * self.factor_raw(x[2]), self.a2 * x[1] * self.b32],
            [0.0, self.b32],
        ]
    }

    /// Control law (25) (with reading 3: r3 on x_R3): [u10, u20] = M⁻¹ [−f_R2 + v_R2 −
    /// r2 x_R2, −f_R3 + v_R3 − r3 x_R3]. Unguarded (for the tests of the derivation).
    pub fn law_25(&self, x: V3, v_r2: f64, v_r3: f64, r2: f64, r3: f64) -> [f64; 2] {
        let ar = self.a_r(x);
        let xr = self.transform(x);
        let y2 = -ar[1] + v_r2 - r2 * xr[1];
        let y3 = -ar[2] + v_r3 - r3 * xr[2];
        let m = self.m(x);
        // Upper-triangular 2×2 solve.
        let u20 = y3 / m[1][1];
        let u10 = (y2 - m[0][1] * u20) / m[0][0];
        [u10, u20]
    }

    /// Control law (28)–(29) in motor quantities: [u10, u20] from v2, v3. `k` is a1 + a2 x3
    /// (pass the guarded value).
    pub fn law_28_29(&self, x: V3, v2: f64, v3: f64, r2: f64, r3: f64, k: f64) -> [f64; 2] {
        let u10 = (v2 - r2 * x[1]
            + self.a3 * x[1]
            + self.a5 * x[0]
            + self.a2 * x[1] * (r3 * x[2] - v3) / k)
            / self.b21;
        let u20 = (v3 - r3 * x[2] + self.a6 * x[2]) / self.b32;
        [u10, u20]
    }
}

/// Gains of the integral state-space controllers (27) and of eqs (28)–(31).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct NlGains {
    /// Eq. (25)/(26): pole of the x_R2 row, 1/s.
    pub r2: f64,
    /// Eq. (27) i = 2: integral gain of the torque loop, 1/s².
    pub k2: f64,
    /// Eq. (25)/(26): pole of the x_R3 row, 1/s.
    pub r3: f64,
    /// Eq. (27) i = 3: integral gain of the field loop, 1/s².
    pub k3: f64,
    /// Eq. (27) i = 1: integral gain of the speed loop, 1/s².
    pub k1: f64,
    /// Eq. (31): speed feedback, 1/s.
    pub r11: f64,
    /// Eq. (31): x_R2 feedback (dimensionless).
    pub r12: f64,
    /// Eq. (31): v_R2 feedback, s.
    pub d12: f64,
}

impl NlGains {
    /// Steady-state gain g = 1 + r12 + d12·r2 from (v1 − r11 x1) to x_R2 of the closed
    /// inner loop (26)–(27): at rest v_R2 = r2 x_R2 and w_R2 = x_R2.
    pub fn g_ss(&self) -> f64 {
        1.0 + self.r12 + self.d12 * self.r2
    }
}

/// Pole placement of the speed subsystem of the dummy system (26)–(27), (31).
///
/// States [x_R1, x_R2, v_R2, v1]: ẋ_R1 = x_R2, ẋ_R2 = −r2 x_R2 + v_R2,
/// v̇_R2 = K2(w_R2 − x_R2), v̇1 = K1(w1 − x_R1), w_R2 = v1 − r11 x_R1 − r12 x_R2 − d12 v_R2.
/// Characteristic polynomial:
/// s⁴ + (r2 + K2 d12) s³ + (r2 K2 d12 + K2 (1 + r12)) s² + K2 r11 s + K2 K1.
/// Given r2, K2 (the inner loop) and the wanted c3..c0, returns (K1, r11, r12, d12).
pub fn place_speed_poles(r2: f64, k2: f64, c: [f64; 4]) -> (f64, f64, f64, f64) {
    let [c3, c2, c1, c0] = c;
    let d12 = (c3 - r2) / k2;
    let r12 = (c2 - r2 * k2 * d12) / k2 - 1.0;
    let r11 = c1 / k2;
    let k1 = c0 / k2;
    (k1, r11, r12, d12)
}

/// Gains for inner natural frequency `w_i` and speed natural frequency `w_0`, damping ζ:
/// inner loops s² + 2ζω_i s + ω_i², speed subsystem (s² + 2ζω_0 s + ω_0²)(s² + 2ζω_i s + ω_i²).
pub fn gains_for(w_i: f64, w_0: f64, zeta: f64) -> NlGains {
    let r2 = 2.0 * zeta * w_i;
    let k2 = w_i * w_i;
    let (p1, q1) = (2.0 * zeta * w_0, w_0 * w_0);
    let (p2, q2) = (2.0 * zeta * w_i, w_i * w_i);
    let c = [p1 + p2, q1 + q2 + p1 * p2, p1 * q2 + p2 * q1, q1 * q2];
    let (k1, r11, r12, d12) = place_speed_poles(r2, k2, c);
    NlGains {
        r2,
        k2,
        r3: r2,
        k3: k2,
        k1,
        r11,
        r12,
        d12,
    }
}

/// The speed-loop half of the law (see the module doc): v1, r11·x1 and eq. (30) at the
/// flux-current set-point. Runs every N samples.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NlSpeedLaw {
    model: KyslanModel,
    k1: f64,
    r11: f64,
    g_ss: f64,
    tw: f64,
    i_q_max: f64,
    /// Integrator v1 of eq. (27), i = 1, rad/s².
    pub v1: f64,
}

/// Output of one speed-law step.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NlSpeedOut {
    /// q-current reference (the q current the demand settles to), A.
    pub i_q_ref: f64,
    /// The current limit was active.
    pub saturated: bool,
    /// The flux-current set-point approaches eq. (15).
    pub near_singular: bool,
}

impl NlSpeedLaw {
    /// Builds the law for speed-loop sample time `tw` and limit `i_q_max` on the settled i_q.
    pub fn new(m: &MotorParams, g: &NlGains, tw: f64, i_q_max: f64) -> Self {
        Self {
            model: KyslanModel::new(m),
            k1: g.k1,
            r11: g.r11,
            g_ss: g.g_ss(),
            tw,
            i_q_max,
            v1: 0.0,
        }
    }

    /// Speed reference w1, speed x1 (mechanical rad/s) and i_d set-point w3 (A) → i_q*.
    pub fn step(&mut self, w1: f64, x1: f64, w3: f64) -> NlSpeedOut {
        let k = self.model.factor(w3);
        let i = (self.v1 - self.r11 * x1) / (self.g_ss * k.value);
        let i_q_ref = i.clamp(-self.i_q_max, self.i_q_max);
        let e = w1 - x1;
        // Anti-windup: no integration further into the limit (k.value > 0, g > 0). An
        // integration that would overflow (an absurd but finite reference or speed) is not
        // taken either: an infinite v1 would meet an infinite r11·x1 later and make i_q* NaN.
        let winding = (i > self.i_q_max && e > 0.0) || (i < -self.i_q_max && e < 0.0);
        let v1 = self.v1 + self.k1 * self.tw * e;
        if !winding && v1.is_finite() {
            self.v1 = v1;
        }
        NlSpeedOut {
            i_q_ref,
            saturated: i_q_ref != i,
            near_singular: k.near_singular,
        }
    }
}

/// The current-loop half of the law: the inner-state terms of eq. (31), the integrators
/// v_R2, v3 of eq. (27), eqs (28)–(29) and the compensation (9)–(10). Runs every sample.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NlCurrentLaw {
    model: KyslanModel,
    g: NlGains,
    pole_pairs: f64,
    ts: f64,
    u_max: f64,
    /// Integrator v_R2 of eq. (27), i = 2, rad/s³.
    pub v_r2: f64,
    /// Integrator v3 (= v_R3) of eq. (27), i = 3, A/s.
    pub v3: f64,
    /// Samples with a1 + a2·i_d below NEAR_SINGULAR·a1.
    pub near_singular_samples: u64,
    /// Samples where a1 + a2·i_d was clamped at GUARD·a1.
    pub clamped_samples: u64,
}

/// Output of one current-law step.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct NlCurrentOut {
    /// d-axis voltage, V.
    pub u_d: f64,
    /// q-axis voltage, V.
    pub u_q: f64,
    /// w2 of eq. (30)–(31): the reference the q integrator tracks, A.
    pub w2: f64,
    /// The voltage vector was limited (integrators frozen).
    pub saturated: bool,
}

impl NlCurrentLaw {
    /// Builds the law for sample time `ts` and voltage-vector limit `u_max`.
    pub fn new(m: &MotorParams, g: &NlGains, ts: f64, u_max: f64) -> Self {
        Self {
            model: KyslanModel::new(m),
            g: *g,
            pole_pairs: m.p(),
            ts,
            u_max,
            v_r2: 0.0,
            v3: 0.0,
            near_singular_samples: 0,
            clamped_samples: 0,
        }
    }

    /// One step. `x.i_q_ref` is the speed law's output, `x.i_d_ref` = w3.
    pub fn step(&mut self, x: &CurrentInput) -> NlCurrentOut {
        let md = &self.model;
        let g = &self.g;
        let s: V3 = [x.omega_e / self.pole_pairs, x.i_q, x.i_d];
        let k = md.factor(s[2]);
        if k.near_singular {
            self.near_singular_samples += 1;
        }
        if k.clamped {
            self.clamped_samples += 1;
        }
        // (v1 − r11 x1) as sent by the speed loop, then eq. (31) × (a1 + a2 x3).
        let demand = x.i_q_ref * g.g_ss() * md.factor(x.i_d_ref).value;
        let x_r2 = k.value * s[1];
        let w_r2 = demand - g.r12 * x_r2 - g.d12 * self.v_r2;
        let w3 = x.i_d_ref;
        // Eq. (28)–(29) with v2 = v_R2/(a1 + a2 x3) (reading 4), then (9)–(10).
        let u0 = md.law_28_29(s, self.v_r2 / k.value, self.v3, g.r2, g.r3, k.value);
        let com = md.compensation(s);
        let (mut u_q, mut u_d) = (u0[0] + com[0], u0[1] + com[1]);
        // Voltage-vector limit, d axis first (as the PI path), integrators frozen if active.
        let mut saturated = false;
        if u_d.abs() > self.u_max {
            u_d = u_d.clamp(-self.u_max, self.u_max);
            saturated = true;
        }
        let u_q_max = (self.u_max * self.u_max - u_d * u_d).max(0.0).sqrt();
        if u_q.abs() > u_q_max {
            u_q = u_q.clamp(-u_q_max, u_q_max);
            saturated = true;
        }
        if !saturated {
            self.v_r2 += g.k2 * self.ts * (w_r2 - x_r2);
            self.v3 += g.k3 * self.ts * (w3 - s[2]);
        }
        NlCurrentOut {
            u_d,
            u_q,
            w2: w_r2 / k.value,
            saturated,
        }
    }
}

/// The sampled loop the nonlinear speed design is computed on: the drive's own discrete
/// law ([`NlSpeedLaw`], [`NlCurrentLaw`]) on the motor at i_d = 0 with ideal load-free
/// mechanics and no limits, with the drive's timing: encoder speed by backward difference
/// and the Bessel filter, speed law every N samples used from the next sample on, voltage
/// applied one sample after it was computed, zero-order hold.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct NlLoopModel {
    /// Current-loop sample time T_s, s.
    pub ts: f64,
    /// Speed-loop divider N.
    pub n: u32,
    /// Speed-filter group delay τ_f, s.
    pub tau_f_s: f64,
}

impl NlLoopModel {
    /// Response to a small speed step (linear range) over `t_end`: time to first reach the
    /// set-point and overshoot.
    pub fn step_response(&self, m: &MotorParams, g: &NlGains, t_end: f64) -> StepFigures {
        let n = u64::from(self.n.max(1));
        let tw = self.ts * n as f64;
        let mut sp = NlSpeedLaw::new(m, g, tw, f64::INFINITY);
        let mut cl = NlCurrentLaw::new(m, g, self.ts, f64::INFINITY);
        let mut obs = EncoderObserver::new(m.pole_pairs, self.ts, self.tau_f_s);
        let rk = Rk4 { substeps: 4 };
        let step = 1.0;
        let mut x = MotorState::default();
        let mut i_q_ref = 0.0;
        let mut u_prev = [0.0; 2];
        let mut f = StepFigures::new(t_end);
        let steps = (t_end / self.ts).ceil() as u64;
        for k in 0..steps {
            let est = obs.step(x.theta_m);
            let omega_e = m.p() * est.omega_m;
            let out = cl.step(&CurrentInput {
                i_d_ref: 0.0,
                i_q_ref,
                i_d: x.i_d,
                i_q: x.i_q,
                omega_e,
            });
            if k % n == 0 {
                i_q_ref = sp.step(step, est.omega_m, 0.0).i_q_ref;
            }
            x = rk.advance(
                m,
                Mechanics::Inertia,
                &x,
                &MotorInput {
                    u_d: u_prev[0],
                    u_q: u_prev[1],
                    t_load: 0.0,
                    ..Default::default()
                },
                self.ts,
            );
            u_prev = [out.u_d, out.u_q];
            if !f.sample((k + 1) as f64 * self.ts, x.omega_m / step) {
                break;
            }
        }
        f
    }
}

/// The q/speed part of the sampled loop of [`NlLoopModel`] as an explicit state, for its
/// linearisation: the motor (i_q, ω, θ), the encoder's last angle, the Bessel filter's
/// y(k−1), y(k−2), u(k−1), u(k−2), the integrators v_R2 and v1, the held i_q* and the
/// voltage u_q on its way. At i_d = 0 the field loop is decoupled from it to first order.
#[derive(Debug, Clone, Copy)]
struct LoopState {
    x: MotorState,
    last_theta: f64,
    filt: [f64; 4],
    cl: NlCurrentLaw,
    sp: NlSpeedLaw,
    i_q_ref: f64,
    u_q_prev: f64,
}

/// Number of states of [`LoopState`].
const LOOP_STATES: usize = 12;

impl LoopState {
    fn to_vec(self) -> [f64; LOOP_STATES] {
        let f = self.filt;
        [
            self.x.i_q,
            self.x.omega_m,
            self.x.theta_m,
            self.last_theta,
            f[0],
            f[1],
            f[2],
            f[3],
            self.cl.v_r2,
            self.sp.v1,
            self.i_q_ref,
            self.u_q_prev,
        ]
    }

    fn set(&mut self, v: &[f64; LOOP_STATES]) {
        self.x.i_q = v[0];
        self.x.omega_m = v[1];
        self.x.theta_m = v[2];
        self.last_theta = v[3];
        self.filt = [v[4], v[5], v[6], v[7]];
        self.cl.v_r2 = v[8];
        self.sp.v1 = v[9];
        self.i_q_ref = v[10];
        self.u_q_prev = v[11];
    }
}

impl NlLoopModel {
    /// One sample of the loop as it runs (the same order as [`Self::step_response`]), with
    /// the speed law at phase `k` of its divider, the encoder and filter unrolled so that
    /// their states are visible. No angle wrap (small signals about θ = 0).
    fn sample(&self, m: &MotorParams, f: &Bessel2, s: &mut LoopState, k: u64, w1: f64) {
        let n = u64::from(self.n.max(1));
        let raw = (s.x.theta_m - s.last_theta) / self.ts;
        s.last_theta = s.x.theta_m;
        let [y1, y2, u1, u2] = s.filt;
        let omega_hat = -f.a1 * y1 - f.a0 * y2 + f.b1 * u1 + f.b0 * u2;
        s.filt = [omega_hat, y1, raw, u1];
        let out = s.cl.step(&CurrentInput {
            i_d_ref: 0.0,
            i_q_ref: s.i_q_ref,
            i_d: s.x.i_d,
            i_q: s.x.i_q,
            omega_e: m.p() * omega_hat,
        });
        if k.is_multiple_of(n) {
            s.i_q_ref = s.sp.step(w1, omega_hat, 0.0).i_q_ref;
        }
        let th = s.x.theta_m;
        s.x = Rk4 { substeps: 4 }.advance(
            m,
            Mechanics::Inertia,
            &s.x,
            &MotorInput {
                u_d: 0.0,
                u_q: s.u_q_prev,
                t_load: 0.0,
                ..Default::default()
            },
            self.ts,
        );
        // Unwrapped angle (advance wraps to [0, 2π)).
        s.x.theta_m = th
            + ((s.x.theta_m - th + std::f64::consts::PI).rem_euclid(std::f64::consts::TAU)
                - std::f64::consts::PI);
        s.u_q_prev = out.u_q;
    }

    /// The loop's map over one speed period N·T_s (from just before a speed-law sample to
    /// the next), linearised at rest by central differences: the matrix Φ of
    /// X[j+1] = Φ X[j] with the states of [`LoopState`].
    pub fn lifted_matrix(&self, m: &MotorParams, g: &NlGains) -> nalgebra::DMatrix<f64> {
        let n = u64::from(self.n.max(1));
        let tw = self.ts * n as f64;
        let f = Bessel2::design(self.tau_f_s, self.ts);
        let base = LoopState {
            x: MotorState::default(),
            last_theta: 0.0,
            filt: [0.0; 4],
            cl: NlCurrentLaw::new(m, g, self.ts, f64::INFINITY),
            sp: NlSpeedLaw::new(m, g, tw, f64::INFINITY),
            i_q_ref: 0.0,
            u_q_prev: 0.0,
        };
        let run = |v: &[f64; LOOP_STATES]| {
            let mut s = base;
            s.set(v);
            for k in 0..n {
                self.sample(m, &f, &mut s, k, 0.0);
            }
            s.to_vec()
        };
        let mut phi = nalgebra::DMatrix::<f64>::zeros(LOOP_STATES, LOOP_STATES);
        // A step of the same small size in every state's own unit (1 A, 1 rad/s, the angle
        // of 1 rad/s over T_s, 1 V and the integrator values that make them): each column
        // then moves the angle well above its rounding (the plant keeps θ in [0, 2π), so a
        // tiny negative angle would lose its digits), and the products of eqs (9)-(10),
        // which enter at second order, cancel in the central difference.
        let md = KyslanModel::new(m);
        let unit: [f64; LOOP_STATES] = [
            1.0,
            1.0,
            self.ts,
            self.ts,
            1.0,
            1.0,
            1.0,
            1.0,
            md.a1 * md.b21,
            md.a1,
            1.0,
            1.0,
        ];
        for j in 0..LOOP_STATES {
            let h = 1e-3 * unit[j];
            let (mut p, mut q) = ([0.0; LOOP_STATES], [0.0; LOOP_STATES]);
            p[j] = h;
            q[j] = -h;
            let (a, b) = (run(&p), run(&q));
            for i in 0..LOOP_STATES {
                phi[(i, j)] = (a[i] - b[i]) / (2.0 * h);
            }
        }
        phi
    }

    /// The largest |z| of the sampled loop's poles (q axis and speed, linearised at rest over
    /// one speed period, [`Self::lifted_matrix`]), without the encoder angle's z = 1 (a shift
    /// of the angle and of its last value changes no speed). Above 1 the loop is unstable: its
    /// step response grows without bound, and a rise time or overshoot read off it is only
    /// what the simulated window happened to show.
    pub fn spectral_radius(&self, m: &MotorParams, g: &NlGains) -> f64 {
        let mut z = crate::math::eigenvalues(self.lifted_matrix(m, g));
        let one = nalgebra::Complex::new(1.0, 0.0);
        if let Some(i) = (0..z.len()).min_by(|&a, &b| {
            crate::math::cnorm(z[a] - one).total_cmp(&crate::math::cnorm(z[b] - one))
        }) {
            z.swap_remove(i);
        }
        crate::math::spectral_radius(z)
    }

    /// Poles of the sampled loop (q axis and speed), as ln(z)/(N·T_s) in rad/s, sorted by
    /// magnitude. Poles at z ≈ 0 (pure delays) are left out.
    pub fn sampled_poles(&self, m: &MotorParams, g: &NlGains) -> Vec<(f64, f64)> {
        let tw = self.ts * f64::from(self.n.max(1));
        let mut v: Vec<(f64, f64)> = crate::math::eigenvalues(self.lifted_matrix(m, g))
            .iter()
            .filter(|z| crate::math::cnorm(**z) > 1e-9)
            .map(|z| {
                let l = crate::math::cln(*z) / tw;
                (l.re, l.im)
            })
            .collect();
        v.sort_by(|p, q| libm::hypot(p.0, p.1).total_cmp(&libm::hypot(q.0, q.1)));
        v
    }
}

/// z = e^{s·N·T_s} of the pair s = −ζω ± jω√(1 − ζ²) (upper half).
fn pair_z(model: &NlLoopModel, zeta: f64, w: f64) -> nalgebra::Complex<f64> {
    let tw = model.ts * f64::from(model.n.max(1));
    crate::math::cexp(nalgebra::Complex::new(-zeta * w, w * (1.0 - zeta * zeta).sqrt()) * tw)
}

/// K1 and r11 that put a pole pair of the sampled loop at (ζ, ω_0), the other gains of `g`
/// kept, and the loop's matrix Φ with them. The speed law runs once per period and its
/// output enters the loop through one row (v1 − r11·ω̂, v1 += K1·T_w·(w1 − ω̂)), so
/// Φ = Φ_0 + K1·Φ_1 + r11·Φ_2 is affine in (K1, r11) (three linearisations give it) and
/// det(zI − Φ) = 0 at z_0 is solved by Newton's method on that affine Φ (two real equations,
/// two unknowns, 1e-12 of the residual at (0, 0)). None if singular.
pub fn place_dominant_pair(
    m: &MotorParams,
    model: &NlLoopModel,
    g: &NlGains,
    w_0: f64,
    zeta: f64,
) -> Option<(NlGains, nalgebra::DMatrix<f64>)> {
    use nalgebra::{Complex, DMatrix};
    let z0 = pair_z(model, zeta, w_0);
    let unit = gains_for(g.k2.sqrt(), w_0, zeta);
    let (s1, s2) = (unit.k1.abs().max(1e-9), unit.r11.abs().max(1e-9));
    let zero = NlGains {
        k1: 0.0,
        r11: 0.0,
        ..*g
    };
    let phi0 = model.lifted_matrix(m, &zero);
    let phi1 = (model.lifted_matrix(m, &NlGains { k1: s1, ..zero }) - &phi0) / s1;
    let phi2 = (model.lifted_matrix(m, &NlGains { r11: s2, ..zero }) - &phi0) / s2;
    let phi = |k1: f64, r11: f64| &phi0 + &phi1 * k1 + &phi2 * r11;
    let n = phi0.nrows();
    let det = |k1: f64, r11: f64| {
        (DMatrix::<Complex<f64>>::identity(n, n) * z0 - phi(k1, r11).map(|v| Complex::new(v, 0.0)))
            .determinant()
    };
    let (mut k1, mut r11) = (0.0, 0.0);
    let p_start = crate::math::cnorm(det(0.0, 0.0));
    for _ in 0..8 {
        let p0 = det(k1, r11);
        if crate::math::cnorm(p0) <= 1e-12 * p_start {
            break;
        }
        let p1 = det(k1 + s1, r11) - p0;
        let p2 = det(k1, r11 + s2) - p0;
        let a = nalgebra::Matrix2::new(p1.re, p2.re, p1.im, p2.im);
        let d = a.lu().solve(&nalgebra::Vector2::new(-p0.re, -p0.im))?;
        k1 += d[0] * s1;
        r11 += d[1] * s2;
    }
    (k1.is_finite() && r11.is_finite()).then(|| (NlGains { k1, r11, ..zero }, phi(k1, r11)))
}

/// The eigenvalues of Φ other than the encoder angle's z = 1 and the pair nearest to z_0 and
/// its conjugate, largest |z| first.
fn other_poles(
    phi: &nalgebra::DMatrix<f64>,
    z0: nalgebra::Complex<f64>,
) -> Vec<nalgebra::Complex<f64>> {
    let one = nalgebra::Complex::new(1.0, 0.0);
    let mut v: Vec<_> = crate::math::eigenvalues(phi.clone())
        .into_iter()
        .filter(|z| crate::math::cnorm(z - one) > 1e-6)
        .collect();
    for t in [z0, z0.conj()] {
        if let Some(i) = (0..v.len())
            .min_by(|&a, &b| crate::math::cnorm(v[a] - t).total_cmp(&crate::math::cnorm(v[b] - t)))
        {
            v.remove(i);
        }
    }
    v.sort_by(|a, b| crate::math::cnorm(*b).total_cmp(&crate::math::cnorm(*a)));
    v
}

/// Nelder–Mead minimisation of `f` from `x0` (initial simplex steps `step`), `iters`
/// iterations; returns the best point and value.
fn nelder_mead(f: &dyn Fn(&[f64]) -> f64, x0: &[f64], step: f64, iters: usize) -> (Vec<f64>, f64) {
    let n = x0.len();
    let mut s: Vec<(Vec<f64>, f64)> = (0..=n)
        .map(|i| {
            let mut x = x0.to_vec();
            if i > 0 {
                x[i - 1] += step;
            }
            let v = f(&x);
            (x, v)
        })
        .collect();
    for _ in 0..iters {
        s.sort_by(|a, b| a.1.total_cmp(&b.1));
        let c: Vec<f64> = (0..n)
            .map(|k| s[..n].iter().map(|p| p.0[k]).sum::<f64>() / n as f64)
            .collect();
        let pt = |t: f64| -> Vec<f64> { (0..n).map(|k| c[k] + t * (s[n].0[k] - c[k])).collect() };
        let xr = pt(-1.0);
        let fr = f(&xr);
        if fr < s[0].1 {
            let xe = pt(-2.0);
            let fe = f(&xe);
            s[n] = if fe < fr { (xe, fe) } else { (xr, fr) };
        } else if fr < s[n - 1].1 {
            s[n] = (xr, fr);
        } else {
            let xc = pt(0.5);
            let fc = f(&xc);
            if fc < s[n].1 {
                s[n] = (xc, fc);
            } else {
                let b = s[0].0.clone();
                for p in s.iter_mut().skip(1) {
                    p.0 = (0..n).map(|k| b[k] + 0.5 * (p.0[k] - b[k])).collect();
                    p.1 = f(&p.0);
                }
            }
        }
    }
    s.sort_by(|a, b| a.1.total_cmp(&b.1));
    s.swap_remove(0)
}

/// One placement on the sampled loop: the pair (ζ, ω_0) exactly ([`place_dominant_pair`]),
/// and r12, d12 of the speed subsystem and r2, K2 of the torque loop chosen so that the
/// largest |z| of the other poles is as small as they can make it (Nelder–Mead over their
/// logarithms relative to the continuous design at ω_0, from `start`, else from the
/// continuous design). The field loop (r3, K3) keeps (ζ, ω_i). Returns the gains and the
/// largest |z| of the other poles.
pub fn place_on_sampled_loop(
    m: &MotorParams,
    model: &NlLoopModel,
    w_i: f64,
    w_0: f64,
    zeta: f64,
    start: Option<&NlGains>,
) -> Option<(NlGains, f64)> {
    let base = gains_for(w_i, w_0, zeta);
    let z0 = pair_z(model, zeta, w_0);
    let from = |x: &[f64]| NlGains {
        r12: base.r12 * libm::exp(x[0]),
        d12: base.d12 * libm::exp(x[1]),
        r2: base.r2 * libm::exp(x[2]),
        k2: base.k2 * libm::exp(x[3]),
        ..base
    };
    let placed = |x: &[f64]| place_dominant_pair(m, model, &from(x), w_0, zeta);
    let cost = |x: &[f64]| -> f64 {
        placed(x)
            .map(|(_, phi)| {
                other_poles(&phi, z0)
                    .first()
                    .map_or(0.0, |z| crate::math::cnorm(*z))
            })
            .filter(|v| v.is_finite())
            .unwrap_or(f64::INFINITY)
    };
    let x0: Vec<f64> = match start {
        Some(s) => [
            s.r12 / base.r12,
            s.d12 / base.d12,
            s.r2 / base.r2,
            s.k2 / base.k2,
        ]
        .iter()
        .map(|v| libm::log(v.max(1e-12)))
        .collect(),
        None => vec![0.0; 4],
    };
    let (x, _) = nelder_mead(&cost, &x0, if start.is_some() { 0.1 } else { 1.0 }, 300);
    // Restarted once from its best point (Nelder–Mead's simplex can collapse early).
    let (x, rho) = nelder_mead(&cost, &x, 0.1, 150);
    let (g, _) = placed(&x)?;
    rho.is_finite().then_some((g, rho))
}

/// Inputs of the nonlinear design.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct NlSpec {
    /// Target time to first reach the speed set-point, s.
    pub rise_time_s: f64,
    /// Natural frequency of the inner (torque and field) loops ω_i, rad/s.
    pub omega_i_rad_s: f64,
    /// Damping of every pole pair.
    pub zeta: f64,
    /// Which loop the poles are placed on.
    #[serde(default)]
    pub placement: NlPlacement,
}

/// Which loop [`design_nonlinear`] places the poles on.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum NlPlacement {
    /// The paper's continuous dummy system (26)–(27); ω_0 solved for the rise time on the
    /// sampled model.
    #[default]
    Continuous,
    /// The sampled loop as it runs ([`NlLoopModel::lifted_matrix`]): its dominant pair at
    /// (ζ, ω_0) and every other pole as fast as the gains allow ([`place_on_sampled_loop`]),
    /// ω_0 the slowest that meets the rise time.
    Sampled,
}

impl NlPlacement {
    /// The paper's placement (the default).
    pub fn is_continuous(&self) -> bool {
        *self == Self::Continuous
    }
}

/// The placement on the sampled loop, when asked for ([`NlPlacement::Sampled`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct NlSampledPlacement {
    /// The poles of the sampled loop (q axis and speed) after placement, ln(z)/(N·T_s),
    /// (re, im) in rad/s, slowest first, without the encoder angle's z = 1.
    pub poles: Vec<(f64, f64)>,
    /// (ω_0, rise s, overshoot %) of every ω_0 the search placed, for the record.
    pub searched: Vec<(f64, f64, f64)>,
    /// ln|z|/(N·T_s) of the slowest pole other than the placed pair, rad/s (the decay rate
    /// the placement could give the poles of delay, filter and hold).
    pub others_slowest_rad_s: f64,
}

/// Result of the nonlinear design.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct NlDesign {
    /// Damping of every pole pair.
    pub zeta: f64,
    /// Inner-loop natural frequency ω_i, rad/s.
    pub omega_i_rad_s: f64,
    /// Natural frequency ω_0 of the speed pair, rad/s (solved for the rise time).
    pub omega_0_rad_s: f64,
    /// The gains.
    pub gains: NlGains,
    /// Steady-state gain g = 1 + r12 + d12·r2 (scales i_q* on the bus).
    pub g_ss: f64,
    /// Rise time of the sampled design model, s (None: it did not reach the set-point
    /// within `response_window_s`, or diverged first).
    pub predicted_rise_time_s: Option<f64>,
    /// Overshoot of the sampled design model, % (None: the response diverged).
    pub predicted_overshoot_pct: Option<f64>,
    /// Rise time of the continuous dummy system (26)–(27), s (the paper's design model;
    /// None as for the sampled model).
    pub continuous_rise_time_s: Option<f64>,
    /// Overshoot of the continuous dummy system, % (None: the response diverged).
    pub continuous_overshoot_pct: Option<f64>,
    /// How long both step responses were simulated, s ([`response_window`]).
    #[serde(default)]
    pub response_window_s: f64,
    /// i_d of eq. (15), A (None: non-salient).
    pub i_d_singular_a: Option<f64>,
    /// Set when the rise-time target could not be met; says why.
    pub warning: Option<String>,
    /// The placement on the sampled loop ([`NlPlacement::Sampled`] only).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sampled: Option<NlSampledPlacement>,
}

/// What the design reads off a unit-step response simulated over `window_s`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepFigures {
    /// Time to first reach the set-point, s; None when it did not within the window (or
    /// the response diverged first).
    pub rise_s: Option<f64>,
    /// Overshoot over the window, %; None when the response stopped being finite (the loop
    /// diverges, or the model is not sound at its sample time).
    pub overshoot_pct: Option<f64>,
    /// Simulated time, s.
    pub window_s: f64,
}

impl StepFigures {
    /// Nothing seen yet of a response simulated over `window_s`.
    fn new(window_s: f64) -> Self {
        Self {
            rise_s: None,
            overshoot_pct: Some(0.0),
            window_s,
        }
    }

    /// Takes the response `y` (1: the set-point) at time `t`; false once it is not finite
    /// (the simulation stops there).
    fn sample(&mut self, t: f64, y: f64) -> bool {
        if !y.is_finite() {
            self.overshoot_pct = None;
            return false;
        }
        if self.rise_s.is_none() && y >= 1.0 {
            self.rise_s = Some(t);
        }
        self.overshoot_pct = self.overshoot_pct.map(|os| os.max((y - 1.0) * 100.0));
        true
    }

    /// Why a figure is missing, in words: "diverged: not finite within 2.00 ms", "did not
    /// reach the set-point within 20.00 ms"; None when the response rose and stayed finite.
    pub fn failure(&self) -> Option<String> {
        let within = self.window_s * 1e3;
        match (self.rise_s, self.overshoot_pct) {
            (_, None) => Some(format!("diverged: not finite within {within:.2} ms")),
            (None, Some(_)) => Some(format!("did not reach the set-point within {within:.2} ms")),
            (Some(_), Some(_)) => None,
        }
    }
}

/// Longest step response the nonlinear design simulates, in loop samples (it bounds the
/// cost of a design whose speed pair is very slow).
pub const RESPONSE_SAMPLES_MAX: f64 = 1e6;

/// How long the nonlinear design simulates a step response of its speed pair at `w0`
/// (rad/s): 10 × the rise-time target, or 20/(ζ·ω_0) when that is longer (about 8 × the
/// pair's own rise time at ζ = 0.7: the rise and the overshoot of a pair slower than the
/// target are seen), but at most [`RESPONSE_SAMPLES_MAX`] samples of `ts`.
pub fn response_window(spec: &NlSpec, w0: f64, ts: f64) -> f64 {
    let pair = 20.0 / (spec.zeta * w0);
    (10.0 * spec.rise_time_s).max(pair.min(RESPONSE_SAMPLES_MAX * ts))
}

/// Unit-step response of the continuous dummy system (26)–(27), (31) over `t_end`: the
/// all-pole closed loop K2·K1/P(s) of [`place_speed_poles`]. Returns the time to first reach
/// 1 and the overshoot.
pub fn continuous_step_response(g: &NlGains, t_end: f64) -> StepFigures {
    let f = |s: [f64; 4]| -> [f64; 4] {
        let [x1, x2, v2, v1] = s;
        let w_r2 = v1 - g.r11 * x1 - g.r12 * x2 - g.d12 * v2;
        [x2, -g.r2 * x2 + v2, g.k2 * (w_r2 - x2), g.k1 * (1.0 - x1)]
    };
    let fastest = g.r2.max(g.k2.sqrt()).max(1.0 / t_end);
    let h = 0.02 / fastest;
    let (mut s, mut t) = ([0.0; 4], 0.0);
    let mut fig = StepFigures::new(t_end);
    let add = |a: [f64; 4], b: [f64; 4], c: f64| {
        [
            a[0] + c * b[0],
            a[1] + c * b[1],
            a[2] + c * b[2],
            a[3] + c * b[3],
        ]
    };
    while t < t_end {
        let k1 = f(s);
        let k2 = f(add(s, k1, 0.5 * h));
        let k3 = f(add(s, k2, 0.5 * h));
        let k4 = f(add(s, k3, h));
        for j in 0..4 {
            s[j] += h / 6.0 * (k1[j] + 2.0 * k2[j] + 2.0 * k3[j] + k4[j]);
        }
        t += h;
        if !fig.sample(t, s[0]) {
            break;
        }
    }
    fig
}

/// Designs the nonlinear controller: inner loops at (ω_i, ζ), the speed subsystem's
/// closed loop (s² + 2ζω_0 s + ω_0²)(s² + 2ζω_i s + ω_i²), and ω_0 solved by bisection so that
/// the sampled design model [`NlLoopModel`] first reaches the set-point at the target.
pub fn design_nonlinear(m: &MotorParams, spec: &NlSpec, model: &NlLoopModel) -> NlDesign {
    if spec.placement == NlPlacement::Sampled {
        return design_nonlinear_sampled(m, spec, model);
    }
    let target = spec.rise_time_s;
    // Whether ω_0 is fast enough: a response that has not risen by the target is too slow,
    // however long it takes after it.
    let t_end = 10.0 * target;
    let meets = |w0: f64| {
        model
            .step_response(m, &gains_for(spec.omega_i_rad_s, w0, spec.zeta), t_end)
            .rise_s
            .is_some_and(|r| r <= target)
    };
    // A second-order pair alone reaches the set-point at (π − acos ζ)/(ω√(1 − ζ²)).
    let w_nominal = (std::f64::consts::PI - libm::acos(spec.zeta))
        / (1.0 - spec.zeta * spec.zeta).sqrt()
        / target;
    let (mut lo, mut hi) = (0.2 * w_nominal, spec.omega_i_rad_s);
    let reachable = meets(hi);
    if reachable {
        for _ in 0..50 {
            let mid = 0.5 * (lo + hi);
            if meets(mid) {
                hi = mid;
            } else {
                lo = mid;
            }
        }
    } else {
        lo = hi;
    }
    let w0 = hi.max(lo);
    let g = gains_for(spec.omega_i_rad_s, w0, spec.zeta);
    let mut d = NlDesign::evaluate(m, spec, model, w0, g, None);
    if !reachable {
        // The design's response over its whole window, not only up to 10 × the target.
        let p = d.predicted();
        let got = p.failure().unwrap_or_else(|| {
            format!(
                "gives {:.2} ms{}",
                p.rise_s.unwrap_or(f64::NAN) * 1e3,
                overshoot_note(p.overshoot_pct)
            )
        });
        d.warning = Some(format!(
            "speed rise time {:.2} ms is not reachable with inner loops at ω_i = {:.0} rad/s (ω_0 = ω_i {got})",
            target * 1e3,
            spec.omega_i_rad_s,
        ));
    }
    d
}

impl NlDesign {
    /// The sampled design model's step response, as [`Self::evaluate`] found it.
    pub fn predicted(&self) -> StepFigures {
        StepFigures {
            rise_s: self.predicted_rise_time_s,
            overshoot_pct: self.predicted_overshoot_pct,
            window_s: self.response_window_s,
        }
    }

    /// The continuous dummy system's step response, as [`Self::evaluate`] found it.
    pub fn continuous(&self) -> StepFigures {
        StepFigures {
            rise_s: self.continuous_rise_time_s,
            overshoot_pct: self.continuous_overshoot_pct,
            window_s: self.response_window_s,
        }
    }

    /// The design record of gains `g` (speed pair at ω_0 = `w0`): the sampled model's and the
    /// continuous dummy system's step responses (the latter with the continuous design at
    /// the same ω_0).
    fn evaluate(
        m: &MotorParams,
        spec: &NlSpec,
        model: &NlLoopModel,
        w0: f64,
        g: NlGains,
        warning: Option<String>,
    ) -> Self {
        let t_end = response_window(spec, w0, model.ts);
        let p = model.step_response(m, &g, t_end);
        let c = continuous_step_response(&gains_for(spec.omega_i_rad_s, w0, spec.zeta), t_end);
        Self {
            zeta: spec.zeta,
            omega_i_rad_s: spec.omega_i_rad_s,
            omega_0_rad_s: w0,
            gains: g,
            g_ss: g.g_ss(),
            predicted_rise_time_s: p.rise_s,
            predicted_overshoot_pct: p.overshoot_pct,
            continuous_rise_time_s: c.rise_s,
            continuous_overshoot_pct: c.overshoot_pct,
            response_window_s: t_end,
            i_d_singular_a: KyslanModel::new(m).singular_i_d(),
            warning,
            sampled: None,
        }
    }
}

/// What a warning adds about a design's overshoot: its figure, and that a response which
/// overshoots by more than the step itself is no speed loop to run.
fn overshoot_note(overshoot_pct: Option<f64>) -> String {
    match overshoot_pct {
        Some(o) if o > 100.0 => format!(
            " with an overshoot of {o:.1} %, more than the step itself: do not run it, ask for a slower rise"
        ),
        Some(o) => format!(" with an overshoot of {o:.1} %"),
        None => String::new(),
    }
}

/// [`NlPlacement::Sampled`]: for ω_0 on a grid of ω_i/200 steps from the second-order
/// estimate (π − acos ζ)/(ω_0√(1 − ζ²)) = t_r up to ω_i/2, each placement started from the
/// previous one ([`place_on_sampled_loop`]); the slowest ω_0 whose sampled step response
/// first reaches the set-point by the target, else the fastest-rising one with a warning.
fn design_nonlinear_sampled(m: &MotorParams, spec: &NlSpec, model: &NlLoopModel) -> NlDesign {
    let (w_i, zeta, target) = (spec.omega_i_rad_s, spec.zeta, spec.rise_time_s);
    let w_nominal = (std::f64::consts::PI - libm::acos(zeta)) / (1.0 - zeta * zeta).sqrt() / target;
    let step = w_i / 200.0;
    let first = (w_nominal / step).floor().max(1.0) as u32;
    let mut placed: Vec<(f64, NlGains, f64)> = Vec::new();
    let mut searched = Vec::new();
    let mut start: Option<NlGains> = None;
    let mut meets = None;
    for k in first..=100 {
        let w0 = f64::from(k) * step;
        let Some((g, rho)) = place_on_sampled_loop(m, model, w_i, w0, zeta, start.as_ref())
            .or_else(|| place_on_sampled_loop(m, model, w_i, w0, zeta, None))
        else {
            continue;
        };
        start = Some(g);
        let f = model.step_response(m, &g, response_window(spec, w0, model.ts));
        // NaN: not reached within the window (or the response diverged).
        let r = f.rise_s.unwrap_or(f64::NAN);
        searched.push((w0, r, f.overshoot_pct.unwrap_or(f64::NAN)));
        placed.push((w0, g, rho));
        if r <= target {
            meets = Some(placed.len() - 1);
            break;
        }
    }
    let best = searched
        .iter()
        .enumerate()
        .filter(|(_, s)| s.1.is_finite())
        .min_by(|a, b| a.1 .1.total_cmp(&b.1 .1))
        .map(|(i, _)| i);
    let Some(i) = meets.or(best) else {
        let mut d = design_nonlinear(
            m,
            &NlSpec {
                placement: NlPlacement::Continuous,
                ..*spec
            },
            model,
        );
        let why = if placed.is_empty() {
            "no placement on the sampled loop succeeded: the continuous design is used"
        } else {
            "no placement on the sampled loop reached the set-point: the continuous design is used"
        };
        // The continuous design's own warning (a target it cannot reach) still holds.
        d.warning = Some(match d.warning.take() {
            Some(w) => format!("{why}; {w}"),
            None => why.to_string(),
        });
        return d;
    };
    let (w0, g, rho) = placed[i];
    let tw = model.ts * f64::from(model.n.max(1));
    let mut warning = meets.is_none().then(|| {
        format!(
            "speed rise time {:.2} ms is not reachable with the sampled loop's dominant pair at damping {zeta}: the fastest placed design (ω_0 = {w0:.0} rad/s) first reaches the set-point at {:.2} ms{}",
            target * 1e3,
            searched[i].1 * 1e3,
            overshoot_note(Some(searched[i].2).filter(|o| o.is_finite()))
        )
    });
    let z0 = pair_z(model, zeta, w0);
    if rho >= crate::math::cnorm(z0) {
        warning = Some(format!(
            "the placed pair (ζ = {zeta}, ω_0 = {w0:.0} rad/s) is not the slowest pole of the sampled loop (another at |z| = {rho:.3})"
        ));
    }
    let poles = model
        .sampled_poles(m, &g)
        .into_iter()
        .filter(|p| libm::hypot(p.0, p.1) > 1e-3)
        .collect();
    NlDesign {
        sampled: Some(NlSampledPlacement {
            poles,
            searched,
            others_slowest_rad_s: libm::log(rho) / tw,
        }),
        ..NlDesign::evaluate(m, spec, model, w0, g, warning)
    }
}

#[cfg(test)]
// The tests' own reference values come from std's maths: they never reach a trace.
#[allow(clippy::disallowed_methods)]
mod tests {
    use super::*;
    use nalgebra::Matrix4;

    /// Operating points (ω, i_q, i_d) spread over the motor's range, both signs.
    const POINTS: [V3; 5] = [
        [70.0, 0.8, -1.6],
        [-150.0, -1.2, 0.4],
        [300.0, 1.5, -0.3],
        [5.0, 0.0, 0.0],
        [120.0, -0.7, -1.1],
    ];
    const INPUTS: [[f64; 2]; 3] = [[30.0, -12.0], [-80.0, 45.0], [0.0, 0.0]];

    fn motors() -> [MotorParams; 2] {
        [MotorParams::kyslan2015(), MotorParams::kyslan2015_sal618()]
    }

    /// Central-difference Jacobian ∂f/∂x (rows: outputs).
    fn jacobian(f: impl Fn(V3) -> V3, x: V3) -> [V3; 3] {
        let mut j = [[0.0; 3]; 3];
        for c in 0..3 {
            let h = 1e-6 * x[c].abs().max(1.0);
            let (mut xp, mut xm) = (x, x);
            xp[c] += h;
            xm[c] -= h;
            let (fp, fm) = (f(xp), f(xm));
            for r in 0..3 {
                j[r][c] = (fp[r] - fm[r]) / (2.0 * h);
            }
        }
        j
    }

    fn mul(j: &[V3; 3], v: V3) -> V3 {
        [0, 1, 2].map(|r| j[r][0] * v[0] + j[r][1] * v[1] + j[r][2] * v[2])
    }

    fn close(a: V3, b: V3, what: &str) {
        for i in 0..3 {
            let scale = a[i].abs().max(b[i].abs()).max(1.0);
            assert!(
                (a[i] - b[i]).abs() <= 1e-6 * scale,
                "{what}: component {i}: {a:?} vs {b:?}"
            );
        }
    }

    fn compensated_rhs(md: &KyslanModel, x: V3, u0: [f64; 2]) -> V3 {
        let a = md.a_compensated(x);
        [a[0], a[1] + md.b21 * u0[0], a[2] + md.b32 * u0[1]]
    }

    #[test]
    fn constants_reproduce_equations_1_to_4() {
        for m in motors() {
            let md = KyslanModel::new(&m);
            for x in POINTS {
                for u in INPUTS {
                    let s = MotorState {
                        omega_m: x[0],
                        i_q: x[1],
                        i_d: x[2],
                        theta_m: 0.0,
                    };
                    let d = crate::motor::derivative(
                        &m,
                        Mechanics::Inertia,
                        &s,
                        &MotorInput {
                            u_d: u[1],
                            u_q: u[0],
                            t_load: 0.2,
                            ..Default::default()
                        },
                    );
                    close(
                        md.f(x, u, 0.2),
                        [d.omega_m, d.i_q, d.i_d],
                        "eq. (5) vs motor model",
                    );
                }
            }
        }
    }

    #[test]
    fn compensation_9_10_turns_model_5_into_11() {
        for m in motors() {
            let md = KyslanModel::new(&m);
            for x in POINTS {
                for u0 in INPUTS {
                    let c = md.compensation(x);
                    let full = md.f(x, [u0[0] + c[0], u0[1] + c[1]], 0.3);
                    let mut simplified = compensated_rhs(&md, x, u0);
                    simplified[0] -= md.e * 0.3;
                    close(full, simplified, "eq. (11)");
                }
            }
        }
    }

    #[test]
    fn controllability_matrix_14_from_numerical_jacobian() {
        for m in motors() {
            let md = KyslanModel::new(&m);
            for x in POINTS {
                // Eq. (13): N b = ∂A/∂x · b, for the compensated drift of (11).
                let ja = jacobian(|x| md.a_compensated(x), x);
                let b1 = [0.0, md.b21, 0.0];
                let b2 = [0.0, 0.0, md.b32];
                let nb1 = mul(&ja, b1);
                let q = md.controllability(x);
                for r in 0..3 {
                    close(
                        [q[r][0], q[r][1], q[r][2]],
                        [b1[r], nb1[r], b2[r]],
                        "eq. (14)",
                    );
                }
                // Eq. (17)-(20): the second row of T is N t1 = ∂t1/∂x · A(x).
                let jt = jacobian(|x| md.transform(x), x);
                let nt1: f64 = (0..3).map(|c| jt[0][c] * md.a_compensated(x)[c]).sum();
                assert!((nt1 - md.transform(x)[1]).abs() < 1e-6 * nt1.abs().max(1.0));
            }
            // Eq. (15): singular exactly at i_d = −ψ/(L_d − L_q).
            let sing = md.singular_i_d().unwrap();
            assert!((sing + m.psi_pm_wb / (m.l_d_h - m.l_q_h)).abs() < 1e-12);
            let det3 = |q: [V3; 3]| {
                q[0][0] * (q[1][1] * q[2][2] - q[1][2] * q[2][1])
                    - q[0][1] * (q[1][0] * q[2][2] - q[1][2] * q[2][0])
                    + q[0][2] * (q[1][0] * q[2][1] - q[1][1] * q[2][0])
            };
            let scale = md.b21 * md.b21 * md.b32 * md.a1;
            assert!(det3(md.controllability([50.0, 1.0, sing])).abs() < 1e-9 * scale);
            assert!(det3(md.controllability([50.0, 1.0, -1.6])).abs() > 0.5 * scale);
        }
        assert_eq!(
            KyslanModel::new(&MotorParams::low1998()).singular_i_d(),
            None
        );
    }

    #[test]
    fn transformed_system_20_to_23_matches_numerical_jacobian() {
        for m in motors() {
            let md = KyslanModel::new(&m);
            for x in POINTS {
                let jt = jacobian(|x| md.transform(x), x);
                for u0 in INPUTS {
                    // Eq. (21): ẋ_R = ∂T/∂x · (A(x) + B u), against eqs (22)-(23).
                    let lhs = mul(&jt, compensated_rhs(&md, x, u0));
                    let ar = md.a_r(x);
                    let br = md.b_r(x);
                    let rhs = [0, 1, 2].map(|r| ar[r] + br[r][0] * u0[0] + br[r][1] * u0[1]);
                    close(lhs, rhs, "eqs (21)-(23)");
                }
                // Eq. (24): B_R = I_R·M.
                let (br, mm) = (md.b_r(x), md.m(x));
                assert_eq!(br, [[0.0, 0.0], mm[0], mm[1]]);
                // First row of (22) is x_R2: the chain of integrators.
                assert!((md.a_r(x)[0] - md.transform(x)[1]).abs() < 1e-12);
            }
        }
    }

    #[test]
    fn law_25_makes_the_transformed_system_linear_26() {
        let (r2, r3, v_r2, v_r3) = (2400.0, 2000.0, 3.0e5, -1500.0);
        for m in motors() {
            let md = KyslanModel::new(&m);
            for x in POINTS {
                let u0 = md.law_25(x, v_r2, v_r3, r2, r3);
                let jt = jacobian(|x| md.transform(x), x);
                let xr_dot = mul(&jt, compensated_rhs(&md, x, u0));
                let xr = md.transform(x);
                close(
                    xr_dot,
                    [xr[1], -r2 * xr[1] + v_r2, -r3 * xr[2] + v_r3],
                    "eq. (26)",
                );
            }
        }
    }

    #[test]
    fn law_28_29_is_law_25_written_back() {
        let (r2, r3) = (2400.0, 2000.0);
        for m in motors() {
            let md = KyslanModel::new(&m);
            for x in POINTS {
                for (v_r2, v3) in [(3.0e5, -1500.0), (-2.0e4, 800.0)] {
                    let k = md.factor_raw(x[2]);
                    let a = md.law_25(x, v_r2, v3, r2, r3);
                    let b = md.law_28_29(x, v_r2 / k, v3, r2, r3, k);
                    close([a[0], a[1], 0.0], [b[0], b[1], 0.0], "eq. (28)-(29)");
                }
            }
        }
    }

    #[test]
    fn whole_two_step_linearisation_on_model_5_with_load() {
        // Compensation (9)-(10) + law (28)-(29) on the full model (5): ẋ_R is (26) plus the
        // load on the first integrator (reading 2).
        let (r2, r3, v_r2, v3, tl) = (2400.0, 2000.0, 1.0e5, 700.0, 0.5);
        for m in motors() {
            let md = KyslanModel::new(&m);
            for x in POINTS {
                let k = md.factor_raw(x[2]);
                let u0 = md.law_28_29(x, v_r2 / k, v3, r2, r3, k);
                let c = md.compensation(x);
                let xdot = md.f(x, [u0[0] + c[0], u0[1] + c[1]], tl);
                let jt = jacobian(|x| md.transform(x), x);
                let xr = md.transform(x);
                close(
                    mul(&jt, xdot),
                    [xr[1] - md.e * tl, -r2 * xr[1] + v_r2, -r3 * xr[2] + v3],
                    "two-step linearisation",
                );
            }
        }
    }

    #[test]
    fn pole_placement_puts_the_speed_subsystem_poles_where_asked() {
        let (zeta, w0, wi) = (DAMPING, 300.0, 2000.0);
        let g = gains_for(wi, w0, zeta);
        // Closed loop of the dummy system, states [x_R1, x_R2, v_R2, v1].
        let a = Matrix4::new(
            0.0,
            1.0,
            0.0,
            0.0, //
            0.0,
            -g.r2,
            1.0,
            0.0, //
            -g.k2 * g.r11,
            -g.k2 * (1.0 + g.r12),
            -g.k2 * g.d12,
            g.k2, //
            -g.k1,
            0.0,
            0.0,
            0.0,
        );
        let mut got: Vec<(f64, f64)> = a
            .complex_eigenvalues()
            .iter()
            .map(|c| (c.re, c.im.abs()))
            .collect();
        got.sort_by(|p, q| p.0.total_cmp(&q.0).then(p.1.total_cmp(&q.1)));
        let pair = |w: f64| (-zeta * w, w * (1.0 - zeta * zeta).sqrt());
        let mut want = vec![pair(wi), pair(wi), pair(w0), pair(w0)];
        want.sort_by(|p, q| p.0.total_cmp(&q.0).then(p.1.total_cmp(&q.1)));
        for (g, w) in got.iter().zip(&want) {
            assert!(
                (g.0 - w.0).abs() < 1e-6 * wi && (g.1 - w.1).abs() < 1e-6 * wi,
                "{got:?} vs {want:?}"
            );
        }
        // Closed forms printed by `drivelab design`.
        assert!((g.k1 - w0 * w0).abs() < 1e-9 * w0 * w0);
        assert!((g.r11 - 2.0 * zeta * w0 * (w0 + wi) / wi).abs() < 1e-9 * g.r11);
        assert!((g.r12 - libm::pow(w0 / wi, 2.0)).abs() < 1e-12);
        assert!((g.d12 - 2.0 * zeta * w0 / (wi * wi)).abs() < 1e-15);
        assert_eq!(
            (g.r2, g.k2, g.r3, g.k3),
            (2.0 * zeta * wi, wi * wi, 2.0 * zeta * wi, wi * wi)
        );
        // Steady state of the closed loop: x_R1 = 1 for w1 = 1, and x_R2 = demand / g.
        let g_ss = g.g_ss();
        assert!((g_ss - (1.0 + g.r12 + g.d12 * g.r2)).abs() < 1e-15);
    }

    #[test]
    fn sampled_design_model_tends_to_the_continuous_dummy_system() {
        // With fast sampling, no speed-loop divider and a negligible filter, the drive's
        // discrete law on the motor behaves like the dummy system (26)-(27).
        let m = MotorParams::kyslan2015();
        let g = gains_for(2000.0, 300.0, DAMPING);
        let fine = NlLoopModel {
            ts: 2e-6,
            n: 1,
            tau_f_s: 2e-6,
        };
        let (s, c) = (
            fine.step_response(&m, &g, 0.04),
            continuous_step_response(&g, 0.04),
        );
        let (r_s, os_s) = (s.rise_s.unwrap(), s.overshoot_pct.unwrap());
        let (r_c, os_c) = (c.rise_s.unwrap(), c.overshoot_pct.unwrap());
        assert!((r_s - r_c).abs() < 0.02 * r_c, "{r_s} vs {r_c}");
        assert!((os_s - os_c).abs() < 1.0, "{os_s} vs {os_c}");
    }

    #[test]
    fn design_meets_the_rise_time_target_on_the_sampled_model() {
        let model = NlLoopModel {
            ts: 1e-4,
            n: 10,
            tau_f_s: 1e-4,
        };
        for m in motors() {
            let d = design_nonlinear(
                &m,
                &NlSpec {
                    rise_time_s: 8e-3,
                    omega_i_rad_s: 2000.0,
                    zeta: DAMPING,
                    placement: NlPlacement::Continuous,
                },
                &model,
            );
            assert!(d.warning.is_none(), "{d:?}");
            assert!(
                (d.predicted_rise_time_s.unwrap() - 8e-3).abs() <= model.ts + 1e-12,
                "{d:?}"
            );
            assert!(d.omega_0_rad_s < d.omega_i_rad_s);
        }
        // A target the inner loops cannot support is reported, not silently missed.
        let d = design_nonlinear(
            &MotorParams::kyslan2015(),
            &NlSpec {
                rise_time_s: 0.5e-3,
                omega_i_rad_s: 2000.0,
                zeta: DAMPING,
                placement: NlPlacement::Continuous,
            },
            &model,
        );
        assert!(d.warning.unwrap().contains("not reachable"));
    }

    #[test]
    fn a_target_the_inner_loops_cannot_meet_still_reports_the_rise_time_they_give() {
        // 0.2 ms: even ω_0 = ω_i first reaches the set-point long after 10 × the target
        // (2 ms); the design reports when it does, and its overshoot, instead of NaN.
        let model = NlLoopModel {
            ts: 1e-4,
            n: 10,
            tau_f_s: 1e-4,
        };
        for placement in [NlPlacement::Continuous, NlPlacement::Sampled] {
            let spec = NlSpec {
                rise_time_s: 0.2e-3,
                omega_i_rad_s: 2000.0,
                zeta: DAMPING,
                placement,
            };
            let d = design_nonlinear(&MotorParams::kyslan2015(), &spec, &model);
            let w = d.warning.clone().unwrap();
            assert!(!w.contains("NaN"), "{placement:?}: {w}");
            assert!(w.contains("with an overshoot of "), "{placement:?}: {w}");
            for f in [d.predicted(), d.continuous()] {
                assert_eq!(f.failure(), None, "{placement:?}: {d:?}");
                let r = f.rise_s.unwrap();
                assert!(
                    r > 10.0 * spec.rise_time_s && r < f.window_s,
                    "{placement:?}: {f:?}"
                );
                assert!(f.overshoot_pct.unwrap().is_finite(), "{placement:?}: {f:?}");
            }
            let r = d.predicted_rise_time_s.unwrap();
            if placement == NlPlacement::Continuous {
                assert!(
                    w.contains(&format!(
                        "(ω_0 = ω_i gives {:.2} ms with an overshoot of {:.1} %",
                        r * 1e3,
                        d.predicted_overshoot_pct.unwrap()
                    )),
                    "{w}"
                );
            }
        }
    }

    #[test]
    fn a_response_that_does_not_rise_or_diverges_says_so_instead_of_a_figure() {
        let mut slow = StepFigures::new(0.02);
        for k in 1..=200 {
            assert!(slow.sample(f64::from(k) * 1e-4, 0.5));
        }
        assert_eq!((slow.rise_s, slow.overshoot_pct), (None, Some(0.0)));
        assert_eq!(
            slow.failure().unwrap(),
            "did not reach the set-point within 20.00 ms"
        );
        let mut wild = StepFigures::new(0.002);
        assert!(wild.sample(1e-4, 3.0));
        assert!(!wild.sample(2e-4, f64::NAN));
        assert_eq!((wild.rise_s, wild.overshoot_pct), (Some(1e-4), None));
        assert_eq!(
            wild.failure().unwrap(),
            "diverged: not finite within 2.00 ms"
        );
        let mut fine = StepFigures::new(0.01);
        assert!(fine.sample(1e-3, 0.9) && fine.sample(2e-3, 1.1) && fine.sample(3e-3, 1.0));
        assert_eq!(fine.rise_s, Some(2e-3));
        assert!((fine.overshoot_pct.unwrap() - 10.0).abs() < 1e-9);
        assert_eq!(fine.failure(), None);
    }

    /// The loop the drive runs, written out by hand as a linear map per current-loop sample
    /// (at rest, i_d = 0, no limits), independently of [`NlLoopModel`]: the q axis and
    /// mechanics of eqs (2)-(3) under a zero-order hold (exact matrix exponential), the
    /// encoder's backward difference and the Bessel filter, the current law (28) with
    /// (31)'s inner terms, the speed law every N samples, the voltage applied one sample
    /// late. States: i_q, ω, θ, θ(k−1), y(k−1), y(k−2), u(k−1), u(k−2), v_R2, v1, the held
    /// demand v1 − r11·ω̂, the voltage on its way. Returns the eigenvalues of the map over
    /// one speed period as ln(z)/(N·T_s), rad/s.
    fn closed_loop_poles_by_hand(
        m: &MotorParams,
        g: &NlGains,
        ts: f64,
        n: usize,
        tau_f: f64,
    ) -> Vec<nalgebra::Complex<f64>> {
        use nalgebra::{DMatrix, Matrix4};
        let p = f64::from(m.pole_pairs);
        let (r, lq, psi, j) = (m.r_ohm, m.l_q_h, m.psi_pm_wb, m.j_kgm2);
        let a1 = 1.5 * p * psi / j;
        // Motor: d/dt [i_q, ω, θ] = A x + B u_q, ZOH over T_s.
        let c = Matrix4::new(
            -r / lq,
            -p * psi / lq,
            0.0,
            1.0 / lq,
            a1,
            -m.b_nms / j,
            0.0,
            0.0,
            0.0,
            1.0,
            0.0,
            0.0,
            0.0,
            0.0,
            0.0,
            0.0,
        ) * ts;
        let e = c.exp();
        let f = Bessel2::design(tau_f, ts);
        let (iq, w, th, thl, y1, y2, u1, u2, vr2, v1, dem, up) =
            (0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11);
        let step = |speed: bool| {
            let mut a = DMatrix::<f64>::zeros(12, 12);
            // ω̂ = −a1 y1 − a0 y2 + b1 u1 + b0 u2 (a row over the states).
            let mut omega_hat = [0.0; 12];
            omega_hat[y1] = -f.a1;
            omega_hat[y2] = -f.a0;
            omega_hat[u1] = f.b1;
            omega_hat[u2] = f.b0;
            // u_q of (28) at i_d = 0: (v_R2/a1 − r2 i_q + R/L_q i_q + pψ/L_q ω̂)·L_q.
            let mut u_q = [0.0; 12];
            u_q[vr2] = lq / a1;
            u_q[iq] = (r / lq - g.r2) * lq;
            for k in 0..12 {
                u_q[k] += p * psi * omega_hat[k];
            }
            // Motor from the voltage on its way.
            for (row, col) in [(iq, 0), (w, 1), (th, 2)] {
                a[(row, iq)] = e[(col, 0)];
                a[(row, w)] = e[(col, 1)];
                a[(row, th)] = e[(col, 2)];
                a[(row, up)] = e[(col, 3)];
            }
            a[(thl, th)] = 1.0;
            for k in 0..12 {
                a[(y1, k)] = omega_hat[k];
                a[(up, k)] = u_q[k];
            }
            a[(y2, y1)] = 1.0;
            a[(u1, th)] = 1.0 / ts;
            a[(u1, thl)] = -1.0 / ts;
            a[(u2, u1)] = 1.0;
            // v_R2 += K2 T_s (w_R2 − x_R2), w_R2 = demand − r12 x_R2 − d12 v_R2, x_R2 = a1 i_q.
            a[(vr2, vr2)] = 1.0 - g.k2 * ts * g.d12;
            a[(vr2, dem)] = g.k2 * ts;
            a[(vr2, iq)] = -g.k2 * ts * a1 * (1.0 + g.r12);
            if speed {
                let tw = ts * n as f64;
                for k in 0..12 {
                    a[(dem, k)] = -g.r11 * omega_hat[k];
                    a[(v1, k)] = -g.k1 * tw * omega_hat[k];
                }
                a[(dem, v1)] += 1.0;
                a[(v1, v1)] += 1.0;
            } else {
                a[(dem, dem)] = 1.0;
                a[(v1, v1)] = 1.0;
            }
            a
        };
        let mut phi = step(true);
        for _ in 1..n {
            phi = step(false) * phi;
        }
        let tw = ts * n as f64;
        phi.complex_eigenvalues()
            .iter()
            .filter(|z| z.norm() > 1e-9)
            .map(|z| z.ln() / tw)
            .collect()
    }

    /// The sampled placement: the pair (ζ = 0.6, ω_0) is a pole pair of the loop as it runs
    /// (its matrix derived by hand, not the design's linearisation), every other pole is
    /// faster and at least as damped, and the design model meets the rise time. The
    /// continuous placement's dominant pair on the same loop has damping ≈ 0.37.
    #[test]
    fn sampled_placement_puts_the_dominant_pair_on_the_loop_that_runs() {
        let model = NlLoopModel {
            ts: 1e-4,
            n: 10,
            tau_f_s: 1e-4,
        };
        let zeta_of = |s: &nalgebra::Complex<f64>| -s.re / s.norm();
        let spec = |placement| NlSpec {
            rise_time_s: 8e-3,
            omega_i_rad_s: 2000.0,
            zeta: DAMPING,
            placement,
        };
        for m in motors() {
            let cont = design_nonlinear(&m, &spec(NlPlacement::Continuous), &model);
            let poles = closed_loop_poles_by_hand(&m, &cont.gains, 1e-4, 10, 1e-4);
            let dom = poles
                .iter()
                .filter(|s| s.im > 1.0)
                .min_by(|a, b| a.norm().total_cmp(&b.norm()))
                .unwrap();
            assert!(zeta_of(dom) < 0.4, "{dom:?}");

            let d = design_nonlinear(&m, &spec(NlPlacement::Sampled), &model);
            assert!(d.warning.is_none(), "{:?}", d.warning);
            let w0 = d.omega_0_rad_s;
            let want = nalgebra::Complex::new(-DAMPING * w0, w0 * (1.0 - DAMPING * DAMPING).sqrt());
            let poles = closed_loop_poles_by_hand(&m, &d.gains, 1e-4, 10, 1e-4);
            // The angle's integrator (z = 1) aside.
            let poles: Vec<_> = poles.into_iter().filter(|s| s.norm() > 1e-6).collect();
            let (near, _) = poles
                .iter()
                .enumerate()
                .min_by(|a, b| (a.1 - want).norm().total_cmp(&(b.1 - want).norm()))
                .unwrap();
            assert!(
                (poles[near] - want).norm() < 1e-3 * w0,
                "{want} not in {poles:?}"
            );
            for (i, s) in poles.iter().enumerate() {
                if i == near || (s - want.conj()).norm() < 1e-3 * w0 {
                    continue;
                }
                assert!(
                    s.re < 2.0 * want.re,
                    "{s} not faster than twice the pair {want}"
                );
                assert!(zeta_of(s) >= DAMPING, "{s} less damped than {DAMPING}");
            }
            assert!(
                (d.predicted_rise_time_s.unwrap() - 8e-3).abs() <= model.ts + 1e-12,
                "{d:?}"
            );
        }
    }

    #[test]
    fn the_law_never_divides_by_zero_near_equation_15() {
        let m = MotorParams::kyslan2015_sal618();
        let md = KyslanModel::new(&m);
        let sing = md.singular_i_d().unwrap();
        let g = gains_for(2000.0, 300.0, DAMPING);
        for i_d in [0.6 * sing, sing, 1.5 * sing] {
            let f = md.factor(i_d);
            assert!(f.near_singular);
            assert!(f.value >= GUARD * md.a1);
            let mut sp = NlSpeedLaw::new(&m, &g, 1e-3, 1.6);
            let o = sp.step(70.0, 10.0, i_d);
            assert!(o.i_q_ref.is_finite() && o.near_singular);
            let mut cl = NlCurrentLaw::new(&m, &g, 1e-4, 180.0);
            for _ in 0..10 {
                let u = cl.step(&CurrentInput {
                    i_d_ref: i_d,
                    i_q_ref: o.i_q_ref,
                    i_d,
                    i_q: 0.5,
                    omega_e: 250.0,
                });
                assert!(u.u_d.is_finite() && u.u_q.is_finite() && u.w2.is_finite());
                assert!(libm::hypot(u.u_d, u.u_q) <= 180.0 + 1e-9);
            }
            assert_eq!(cl.near_singular_samples, 10);
            assert_eq!(cl.clamped_samples, if i_d == 0.6 * sing { 0 } else { 10 });
        }
        assert!(!md.factor(-1.6).near_singular);
    }

    #[test]
    fn speed_law_limits_the_settled_current_without_windup() {
        let m = MotorParams::kyslan2015();
        let g = gains_for(2000.0, 300.0, DAMPING);
        let mut sp = NlSpeedLaw::new(&m, &g, 1e-3, 1.6);
        let step = g.k1 * 1e-3 * 100.0; // one integration step for a 100 rad/s error
        for _ in 0..1000 {
            let o = sp.step(100.0, 0.0, -1.6);
            assert!(o.i_q_ref <= 1.6);
        }
        // No wind-up: the integrator stopped within one step of the limit.
        let limit_v1 = 1.6 * g.g_ss() * KyslanModel::new(&m).factor_raw(-1.6);
        assert!(sp.v1 <= limit_v1 + step, "{} vs {limit_v1}", sp.v1);
        // Reversing the error leaves the limit within two speed samples.
        sp.step(-100.0, 0.0, -1.6);
        assert!(sp.step(-100.0, 0.0, -1.6).i_q_ref < 1.6);
    }

    #[test]
    fn absurd_but_finite_speeds_keep_the_current_reference_finite_and_limited() {
        // An outer loop's reference of f64::MAX, then a speed estimate of f64::MAX (the
        // case a property test found): the integration of the first would overflow, and
        // the infinite integrator against the infinite r11·x1 of the second was NaN.
        let m = MotorParams::kyslan2015();
        let g = gains_for(2000.0, 300.0, DAMPING);
        let mut sp = NlSpeedLaw::new(&m, &g, 1e-3, 1.6);
        for (w1, x1) in [
            (f64::MAX, 0.0),
            (0.0, f64::MAX),
            (-f64::MAX, f64::MAX),
            (f64::MAX, -f64::MAX),
            (0.0, 0.0),
        ] {
            let o = sp.step(w1, x1, 0.0);
            assert!(
                o.i_q_ref.is_finite() && o.i_q_ref.abs() <= 1.6,
                "w1 {w1}, x1 {x1}: i_q* {}",
                o.i_q_ref
            );
            assert!(sp.v1.is_finite(), "w1 {w1}, x1 {x1}: v1 {}", sp.v1);
        }
    }
}
