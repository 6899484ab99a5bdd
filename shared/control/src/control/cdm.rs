//! Coefficient diagram method (CDM, Manabe 1998) for the polar-coordinate current loops of
//! Miyajima, Fujimoto and Fujitsuna (eqs 26–37): the PI gains of C_21 (i_q through the
//! voltage amplitude V_a) and C_12 (i_d through the voltage phase δ) at an operating point
//! (V_ao, δ_o).
//!
//! With the low-speed approximation (18) the loops see the plants
//! ΔP_l21(s) = cos δ_o/(L s + R) and ΔP_l12(s) = −V_ao cos δ_o/(L s + R) (eqs 22, 21). A PI
//! C(s) = (K_P s + K_I)/s on b/(L s + R) closes to L s² + (R + b K_P) s + b K_I, so matching
//! s² + a_1 s + a_0 gives K_P = (a_1 L − R)/b and K_I = a_0 L/b: eqs (28)–(31). The CDM
//! standard form of a second-order polynomial has the stability index γ_1 = a_1²/a_0 and the
//! equivalent time constant τ = a_1/a_0 (eqs 32–35), hence a_1 = γ_1/τ and a_0 = γ_1/τ².
//!
//! Eq. (37) is read as printed: τ_12 = 10·T_u while |V_ao cos δ_o| ≥ 0.01·V_amax, else
//! τ_12 = 0.1·V_amax/|V_ao cos δ_o|·T_u (continuous at the switch, dimensionless ratio times
//! T_u). It slows the d loop where its plant gain V_ao cos δ_o vanishes. Before the gains are
//! computed V_ao and δ_o are limited as the paper says: 0.001·V_amax ≤ |V_ao| ≤ V_amax (the
//! sign of V_ao is kept; V_ao = 0 counts as positive) and |δ_o| ≤ 0.9·π/2.
//!
//! Near V_ao = 0 the d-loop gains stay bounded. On the second line of (37), with
//! g = V_ao cos δ_o: a_1 = 25·|g|/(V_amax T_u), so
//! K_P12 = −sgn(g)·(25·L/(V_amax T_u) − R/|g|) and K_I12 = −sgn(g)·250·L·|g|/(V_amax T_u)²:
//! the proportional gain is bounded by the limits on V_ao and δ_o (|g| ≥ 0.001·V_amax·
//! cos(0.45π)) and the integral gain vanishes with g — the "small gain d-axis current
//! controller when V_a ≃ 0" of section IV-C. (τ_12 can reach 0.1/(0.001·cos 0.45π)·T_u
//! ≈ 640·T_u, where a_1 L − R < 0: the placed poles are slower than the winding's own R/L.)

use serde::{Deserialize, Serialize};

/// How the polar CDM loops treat the drive's one-sample computation delay.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum CdmDelay {
    /// The paper's design: gains of eqs (28)–(31) on the delay-free plant, measured currents.
    #[default]
    Paper,
    /// The same gains, fed with the currents predicted one sample ahead by the model (1)
    /// under the voltage already commanded (a Smith-type predictor).
    Predict,
}

impl CdmDelay {
    /// The paper's design (the default).
    pub fn is_paper(&self) -> bool {
        *self == Self::Paper
    }
}

/// CDM stability index γ_1 of both loops (eqs 32, 34; γ_1 = 2.5 per docs/architecture.md,
/// "Paper conventions").
pub const GAMMA1: f64 = 2.5;
/// τ_21 = 10·T_u (eq. 36), and τ_12 away from V_ao cos δ_o ≈ 0 (eq. 37).
pub const TAU_SAMPLES: f64 = 10.0;
/// Lower limit of |V_ao| as a fraction of V_amax (section IV-B).
pub const V_AO_MIN_FRAC: f64 = 0.001;
/// Limit of |δ_o|, rad (0.9·π/2, section IV-B).
pub const DELTA_O_MAX: f64 = 0.9 * std::f64::consts::FRAC_PI_2;
/// Eq. (37): τ_12 switches when |V_ao cos δ_o| falls below this fraction of V_amax.
pub const TAU12_SWITCH_FRAC: f64 = 0.01;
/// Eq. (37): numerator of the slowed τ_12, as a fraction of V_amax.
pub const TAU12_SLOW_FRAC: f64 = 0.1;

/// Coefficients (a_1, a_0) of the CDM standard form s² + a_1 s + a_0 with stability index
/// `gamma1` and equivalent time constant `tau_s` (eqs 32–35).
pub fn cdm_second_order(gamma1: f64, tau_s: f64) -> (f64, f64) {
    (gamma1 / tau_s, gamma1 / (tau_s * tau_s))
}

/// The operating point after the paper's limits: 0.001·V_amax ≤ |V_ao| ≤ V_amax (sign kept)
/// and |δ_o| ≤ 0.9·π/2. Non-finite inputs fall back to (+0.001·V_amax, 0).
pub fn limit_operating_point(v_ao: f64, delta_o: f64, v_amax: f64) -> (f64, f64) {
    let v_min = V_AO_MIN_FRAC * v_amax;
    let v = if v_ao.is_finite() {
        let s = if v_ao < 0.0 { -1.0 } else { 1.0 };
        s * v_ao.abs().clamp(v_min, v_amax)
    } else {
        v_min
    };
    let d = if delta_o.is_finite() {
        delta_o.clamp(-DELTA_O_MAX, DELTA_O_MAX)
    } else {
        0.0
    };
    (v, d)
}

/// Eq. (37): τ_12 for a (limited) operating point, s.
pub fn tau12(v_ao: f64, delta_o: f64, tu_s: f64, v_amax: f64) -> f64 {
    let g = (v_ao * libm::cos(delta_o)).abs();
    if g >= TAU12_SWITCH_FRAC * v_amax {
        TAU_SAMPLES * tu_s
    } else {
        TAU12_SLOW_FRAC * v_amax / g * tu_s
    }
}

/// PI gains (K_P, K_I) placing b/(L s + R) in closed loop at s² + a_1 s + a_0.
pub fn pi_gains(r_ohm: f64, l_h: f64, a1: f64, a0: f64, b: f64) -> (f64, f64) {
    ((a1 * l_h - r_ohm) / b, a0 * l_h / b)
}

/// Gains of C_21 (eqs 28–29) at the (limited) phase δ_o: (K_P21 in V/A, K_I21 in V/(A·s)).
pub fn gains_21(r_ohm: f64, l_h: f64, a1: f64, a0: f64, delta_o: f64) -> (f64, f64) {
    pi_gains(r_ohm, l_h, a1, a0, libm::cos(delta_o))
}

/// Gains of C_12 (eqs 30–31) at the (limited) point (V_ao, δ_o): (K_P12 in rad/A,
/// K_I12 in rad/(A·s)).
pub fn gains_12(r_ohm: f64, l_h: f64, a1: f64, a0: f64, v_ao: f64, delta_o: f64) -> (f64, f64) {
    pi_gains(r_ohm, l_h, a1, a0, -v_ao * libm::cos(delta_o))
}

/// The whole CDM design at one operating point, for printing and checking by hand.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct CdmDesign {
    /// R, Ω.
    pub r_ohm: f64,
    /// L (= L_d = L_q), H.
    pub l_h: f64,
    /// Control period T_u, s.
    pub tu_s: f64,
    /// Voltage limit V_amax, V.
    pub v_amax_v: f64,
    /// V_ao as asked, V.
    pub v_ao_in_v: f64,
    /// δ_o as asked, rad.
    pub delta_o_in_rad: f64,
    /// V_ao after the limit 0.001·V_amax ≤ |V_ao| ≤ V_amax, V.
    pub v_ao_v: f64,
    /// δ_o after the limit |δ_o| ≤ 0.9·π/2, rad.
    pub delta_o_rad: f64,
    /// γ_1 of both loops.
    pub gamma1: f64,
    /// τ_21 = 10·T_u (eq. 36), s.
    pub tau21_s: f64,
    /// a_1 of (26), 1/s.
    pub a1_21: f64,
    /// a_0 of (26), 1/s².
    pub a0_21: f64,
    /// K_P21 (eq. 28), V/A.
    pub k_p21: f64,
    /// K_I21 (eq. 29), V/(A·s).
    pub k_i21: f64,
    /// |V_ao cos δ_o| (the switch of eq. 37), V.
    pub v_cos_v: f64,
    /// True when τ_12 came from the second line of eq. (37).
    pub tau12_slowed: bool,
    /// True when τ_12 was given instead of computed from eq. (37).
    pub tau12_given: bool,
    /// τ_12, s.
    pub tau12_s: f64,
    /// a_1 of (27), 1/s.
    pub a1_12: f64,
    /// a_0 of (27), 1/s².
    pub a0_12: f64,
    /// K_P12 (eq. 30), rad/A.
    pub k_p12: f64,
    /// K_I12 (eq. 31), rad/(A·s).
    pub k_i12: f64,
}

impl CdmDesign {
    /// Designs C_21 and C_12 for winding `r_ohm`, `l_h`, control period `tu_s` and voltage
    /// limit `v_amax_v` at the operating point (`v_ao_v`, `delta_o_rad`), limited first.
    /// `tau12_s` overrides eq. (37).
    pub fn new(
        r_ohm: f64,
        l_h: f64,
        tu_s: f64,
        v_amax_v: f64,
        v_ao_v: f64,
        delta_o_rad: f64,
        tau12_s: Option<f64>,
    ) -> Self {
        let (v, d) = limit_operating_point(v_ao_v, delta_o_rad, v_amax_v);
        let tau21 = TAU_SAMPLES * tu_s;
        let (a1_21, a0_21) = cdm_second_order(GAMMA1, tau21);
        let (k_p21, k_i21) = gains_21(r_ohm, l_h, a1_21, a0_21, d);
        let v_cos = (v * libm::cos(d)).abs();
        let t12 = tau12_s.unwrap_or_else(|| tau12(v, d, tu_s, v_amax_v));
        let (a1_12, a0_12) = cdm_second_order(GAMMA1, t12);
        let (k_p12, k_i12) = gains_12(r_ohm, l_h, a1_12, a0_12, v, d);
        Self {
            r_ohm,
            l_h,
            tu_s,
            v_amax_v,
            v_ao_in_v: v_ao_v,
            delta_o_in_rad: delta_o_rad,
            v_ao_v: v,
            delta_o_rad: d,
            gamma1: GAMMA1,
            tau21_s: tau21,
            a1_21,
            a0_21,
            k_p21,
            k_i21,
            v_cos_v: v_cos,
            tau12_slowed: tau12_s.is_none() && v_cos < TAU12_SWITCH_FRAC * v_amax_v,
            tau12_given: tau12_s.is_some(),
            tau12_s: t12,
            a1_12,
            a0_12,
            k_p12,
            k_i12,
        }
    }
}

/// CDM of a PI on the delayed plant (the design that includes the delay): the winding
/// 1/(L s + R) with the one-sample computation delay as a pole, 1/((L s + R)(T_u s + 1)),
/// closes to a_3 s³ + a_2 s² + a_1 s + a_0 with a_3 = L·T_u and a_2 = L + R·T_u fixed by the
/// plant and a_1 = R + K_P, a_0 = K_I (at δ_o = 0). Manabe's indices γ_1 = a_1²/(a_2 a_0) and
/// γ_2 = a_2²/(a_3 a_1) then fix both gains, and τ = a_1/a_0 follows (it is not free as
/// in eq. 36): a_1 = a_2²/(γ_2 a_3), a_0 = a_1²/(γ_1 a_2).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct DelayedPlantCdm {
    /// γ_1.
    pub gamma1: f64,
    /// γ_2.
    pub gamma2: f64,
    /// [a_3, a_2, a_1, a_0] of the closed-loop polynomial.
    pub a: [f64; 4],
    /// K_P21 at δ_o = 0, V/A.
    pub k_p: f64,
    /// K_I21 at δ_o = 0, V/(A·s).
    pub k_i: f64,
    /// The equivalent time constant τ = a_1/a_0 that follows, s.
    pub tau_s: f64,
}

impl DelayedPlantCdm {
    /// The design for winding `r_ohm`, `l_h` and delay `tu_s` with indices γ_1, γ_2.
    pub fn new(r_ohm: f64, l_h: f64, tu_s: f64, gamma1: f64, gamma2: f64) -> Self {
        let a3 = l_h * tu_s;
        let a2 = l_h + r_ohm * tu_s;
        let a1 = a2 * a2 / (gamma2 * a3);
        let a0 = a1 * a1 / (gamma1 * a2);
        Self {
            gamma1,
            gamma2,
            a: [a3, a2, a1, a0],
            k_p: a1 - r_ohm,
            k_i: a0,
            tau_s: a1 / a0,
        }
    }
}

/// The q loop of section IV at standstill as it runs, for a step of i_q*: the winding
/// 1/(L s + R) under a zero-order hold of T_u, the command of sample k applied over
/// [t_{k+1}, t_{k+2}), C_21 of eqs (28)–(29) at δ_o = 0 with γ_1 and τ_21 = `tau_samples`·T_u
/// (eq. 36: 10) and the set-point weight `beta` (the paper: 1), the integrator by forward
/// Euler as [`super::polar`] runs it, fed the measured current ([`CdmDelay::Paper`]) or the
/// current predicted one sample ahead ([`CdmDelay::Predict`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct QLoop {
    /// R, Ω.
    pub r_ohm: f64,
    /// L, H.
    pub l_h: f64,
    /// T_u, s.
    pub tu_s: f64,
    /// Delay treatment.
    pub delay: CdmDelay,
    /// τ_21 in samples.
    pub tau_samples: f64,
    /// Set-point weight β.
    pub beta: f64,
    /// C_21's gains (K_P, K_I) when not from γ_1 and τ_21 (e.g. [`DelayedPlantCdm`]).
    pub gains: Option<(f64, f64)>,
}

impl QLoop {
    /// The paper's loop (τ_21 = 10·T_u, β = 1) with `delay`.
    pub fn paper(r_ohm: f64, l_h: f64, tu_s: f64, delay: CdmDelay) -> Self {
        Self {
            r_ohm,
            l_h,
            tu_s,
            delay,
            tau_samples: TAU_SAMPLES,
            beta: 1.0,
            gains: None,
        }
    }

    /// C_21 designed on the delayed plant ([`DelayedPlantCdm`], γ_1 = 2.5, γ_2 = 2),
    /// measured currents.
    pub fn delayed_plant(r_ohm: f64, l_h: f64, tu_s: f64) -> Self {
        let d = DelayedPlantCdm::new(r_ohm, l_h, tu_s, GAMMA1, 2.0);
        Self {
            tau_samples: d.tau_s / tu_s,
            gains: Some((d.k_p, d.k_i)),
            ..Self::paper(r_ohm, l_h, tu_s, CdmDelay::Paper)
        }
    }

    /// (10–90 % rise time on the sample grid, s; overshoot, %) of the unit step.
    pub fn step(&self) -> (f64, f64) {
        let ys = self.response();
        let n = ys.len();
        let first = |f: f64| ys.iter().position(|&y| y >= f).unwrap_or(n);
        let rise = (first(0.9) - first(0.1)) as f64 * self.tu_s;
        let peak = ys.iter().copied().fold(0.0, f64::max);
        (rise, (peak - 1.0).max(0.0) * 100.0)
    }

    /// Over the γ_1 = 2.5 family of C_21 (τ_21 from 2 to 40 samples in quarter samples, this
    /// loop's delay treatment and β): the design with the least overshoot among those that
    /// rise within `rise_max_s`, as (τ_21 in samples, rise s, overshoot %).
    pub fn least_overshoot_within(&self, rise_max_s: f64) -> Option<(f64, f64, f64)> {
        (8..=160)
            .map(|q| f64::from(q) / 4.0)
            .map(|t| {
                let (r, os) = Self {
                    tau_samples: t,
                    gains: None,
                    ..*self
                }
                .step();
                (t, r, os)
            })
            .filter(|d| d.1 <= rise_max_s + 1e-12 && d.2.is_finite())
            .min_by(|a, b| a.2.total_cmp(&b.2))
    }

    /// The unit-step response, sample k+1 after the step at k = 0, for 200 samples.
    pub fn response(&self) -> Vec<f64> {
        let Self {
            r_ohm,
            l_h,
            tu_s,
            delay,
            tau_samples,
            beta,
            gains,
        } = *self;
        let (kp, ki) = gains.unwrap_or_else(|| {
            let (a1, a0) = cdm_second_order(GAMMA1, tau_samples * tu_s);
            gains_21(r_ohm, l_h, a1, a0, 0.0)
        });
        let p = libm::exp(-r_ohm / l_h * tu_s);
        let g = (1.0 - p) / r_ohm;
        let (mut i, mut x_i, mut u_prev) = (0.0, 0.0, 0.0);
        let n = 200;
        let mut ys = Vec::with_capacity(n);
        for _ in 0..n {
            let y = match delay {
                CdmDelay::Paper => i,
                CdmDelay::Predict => p * i + g * u_prev,
            };
            let e = 1.0 - y;
            let u = kp * (beta - y) + x_i;
            x_i += ki * tu_s * e;
            i = p * i + g * u_prev;
            u_prev = u;
            ys.push(i);
        }
        ys
    }
}

#[cfg(test)]
// The tests' own reference values come from std's maths: they never reach a trace.
#[allow(clippy::disallowed_methods)]
mod tests {
    use super::*;

    const R: f64 = 2.5;
    const L: f64 = 30e-3;
    const TU: f64 = 100e-6;
    const VMAX: f64 = 470.0 / 1.732_050_807_568_877_2;

    #[test]
    fn q_loop_model_shows_the_delay_and_its_compensation() {
        // The miyajima motor at T_u = 100 µs.
        let (paper, pred) = (
            QLoop::paper(2.5, 30e-3, 1e-4, CdmDelay::Paper).step(),
            QLoop::paper(2.5, 30e-3, 1e-4, CdmDelay::Predict).step(),
        );
        // The prediction removes the delay: the loop is the delay-free sampled design, whose
        // overshoot comes from the PI zero of the CDM polynomial alone (16.8 % on the
        // continuous model): less overshoot, slower rise.
        assert!(pred.1 < paper.1 && pred.0 > paper.0, "{paper:?} {pred:?}");
        eprintln!("paper {paper:?}, predict {pred:?}");
    }

    /// The design on the delayed plant has the asked indices: its closed-loop polynomial,
    /// multiplied out here from the plant, the delay pole and the PI, has γ_1 = 2.5,
    /// γ_2 = 2 and the roots of the CDM standard form with the τ it reports.
    #[test]
    fn delayed_plant_design_places_the_cdm_polynomial() {
        let d = DelayedPlantCdm::new(R, L, TU, 2.5, 2.0);
        // (L s + R)(T_u s + 1)·s + K_P s + K_I.
        let a = [L * TU, L + R * TU, R + d.k_p, d.k_i];
        let g1 = a[2] * a[2] / (a[1] * a[3]);
        let g2 = a[1] * a[1] / (a[0] * a[2]);
        assert!(
            (g1 - 2.5).abs() < 1e-12 && (g2 - 2.0).abs() < 1e-12,
            "{g1} {g2}"
        );
        // Manabe's standard form a_0·[(τs)³/(γ_1²γ_2) + (τs)²/γ_1 + τs + 1]: same roots.
        let t = d.tau_s;
        let b = [t * t * t / (2.5 * 2.5 * 2.0), t * t / 2.5, t, 1.0];
        let roots = |c: [f64; 4]| {
            let m = nalgebra::Matrix3::new(
                -c[1] / c[0],
                -c[2] / c[0],
                -c[3] / c[0],
                1.0,
                0.0,
                0.0,
                0.0,
                1.0,
                0.0,
            );
            let mut v: Vec<_> = m.complex_eigenvalues().iter().copied().collect();
            v.sort_by(|x, y| x.re.total_cmp(&y.re).then(x.im.total_cmp(&y.im)));
            v
        };
        for (x, y) in roots(a).iter().zip(roots(b)) {
            assert!((x - y).norm() < 1e-9 * y.norm(), "{x} vs {y}");
            assert!(x.re < 0.0);
        }
        // τ follows from the plant: 5·L·T_u/(L + R·T_u), about 5·T_u here.
        assert!((t - 5.0 * L * TU / (L + R * TU)).abs() < 1e-15, "{t}");
    }

    /// Section IV at 0 rpm, the target of docs/paper-departures.md: overshoot below 10 %
    /// with a rise no more than 1.5 times the paper's design's. No C_21 with γ_1 = 2.5 and the
    /// PI on the error meets it, whether the delay is compensated by prediction, by
    /// designing on the delayed plant, or by any τ_21: the PI's zero alone gives 16.8 %
    /// on the delay-free continuous model. The set-point weight moves that zero and does.
    #[test]
    fn no_gamma_2_5_pi_on_the_error_meets_the_0rpm_target() {
        let paper = QLoop::paper(R, L, TU, CdmDelay::Paper);
        let (rise0, os0) = paper.step();
        let rise_max = 1.5 * rise0;
        eprintln!("paper: rise {rise0} s, overshoot {os0} %");
        let dp = QLoop::delayed_plant(R, L, TU);
        let (r, os) = dp.step();
        eprintln!(
            "delayed plant (γ_2 = 2, τ = {} T_u): rise {r} s, overshoot {os} %",
            dp.tau_samples
        );
        assert!(os >= 10.0, "{os}");
        for delay in [CdmDelay::Paper, CdmDelay::Predict] {
            let best = QLoop::paper(R, L, TU, delay).least_overshoot_within(rise_max);
            eprintln!("{delay:?}: least overshoot within {rise_max} s: {best:?}");
            assert!(best.unwrap().2 >= 10.0, "{best:?}");
        }
        // The shipped option (miyajima-polar-0rpm-predict) keeps γ_1 = 2.5 and meets it.
        let (r, os) = QLoop {
            tau_samples: 5.0,
            beta: 0.6,
            ..QLoop::paper(R, L, TU, CdmDelay::Predict)
        }
        .step();
        assert!(os < 10.0 && r <= rise_max, "{r} {os}");
    }

    #[test]
    fn standard_form_has_the_asked_index_and_time_constant() {
        let (a1, a0) = cdm_second_order(2.5, 1e-3);
        assert!((a1 * a1 / a0 - 2.5).abs() < 1e-12);
        assert!((a1 / a0 - 1e-3).abs() < 1e-15);
        assert_eq!((a1, a0), (2500.0, 2.5e6));
    }

    /// Eqs (28)–(31) at a few operating points, written out by hand.
    #[test]
    fn gains_match_eqs_28_to_31() {
        for (v_ao, d_deg) in [(5.0, 0.0), (30.0, 20.0), (-12.0, -35.0), (200.0, 60.0)] {
            let d: f64 = f64::to_radians(d_deg);
            let g = CdmDesign::new(R, L, TU, VMAX, v_ao, d, None);
            // τ21 = 1 ms: a1 = 2.5/τ = 2500 1/s, a0 = 2.5/τ² = 2.5e6 1/s².
            let c = libm::cos(d);
            assert!((g.k_p21 - (2500.0 * L - R) / c).abs() < 1e-9);
            assert!((g.k_i21 - 2.5e6 * L / c).abs() < 1e-6);
            // All these points have |V_ao cos δ_o| ≥ 0.01·V_amax = 2.71 V: τ12 = 1 ms too.
            assert!(!g.tau12_slowed);
            assert!((g.k_p12 - (2500.0 * L - R) / (-v_ao * c)).abs() < 1e-9);
            assert!((g.k_i12 - 2.5e6 * L / (-v_ao * c)).abs() < 1e-6);
        }
        // Close to V_ao = 0: eq. (37)'s second line, τ12 = 0.1·V_amax/|V_ao cos δo|·T_u.
        let g = CdmDesign::new(R, L, TU, VMAX, 1.0, 0.0, None);
        assert!(g.tau12_slowed);
        let t12 = 0.1 * VMAX / 1.0 * TU;
        assert!((g.tau12_s - t12).abs() < 1e-15);
        let (a1, a0) = (2.5 / t12, 2.5 / (t12 * t12));
        assert!((g.k_p12 - (a1 * L - R) / -1.0).abs() < 1e-9);
        assert!((g.k_i12 - a0 * L / -1.0).abs() < 1e-6);
    }

    #[test]
    fn tau12_is_continuous_at_the_switch() {
        let v = TAU12_SWITCH_FRAC * VMAX;
        let a = tau12(v * (1.0 + 1e-9), 0.0, TU, VMAX);
        let b = tau12(v * (1.0 - 1e-9), 0.0, TU, VMAX);
        assert!((a - b).abs() < 1e-8 * a, "{a} {b}");
    }

    #[test]
    fn limits_keep_the_gains_bounded_near_zero_amplitude() {
        for v in [0.0, 1e-12, -1e-12, f64::NAN] {
            for d in [0.0, 1.5, -1.5, 3.0] {
                let g = CdmDesign::new(R, L, TU, VMAX, v, d, None);
                assert!(g.v_ao_v.abs() >= V_AO_MIN_FRAC * VMAX * (1.0 - 1e-12));
                assert!(g.delta_o_rad.abs() <= DELTA_O_MAX);
                for k in [g.k_p21, g.k_i21, g.k_p12, g.k_i12] {
                    assert!(k.is_finite(), "{g:?}");
                }
                // Bounded d controller: |K_P12| ≤ 25·L/(V_amax T_u) + R/|g|_min, K_I12 ∝ |g|.
                let g_min = V_AO_MIN_FRAC * VMAX * libm::cos(DELTA_O_MAX);
                let bound = 25.0 * L / (VMAX * TU) + R / g_min;
                assert!(g.k_p12.abs() <= bound * 1.0001, "{g:?}");
                let vc = (g.v_ao_v * libm::cos(g.delta_o_rad)).abs();
                let ki = 250.0 * L * vc / libm::pow(VMAX * TU, 2.0);
                assert!((g.k_i12.abs() - ki).abs() <= 1e-9 * ki, "{g:?}");
            }
        }
        let (v, d) = limit_operating_point(-1e-9, 0.0, VMAX);
        assert!(v < 0.0 && d == 0.0);
        let (v, _) = limit_operating_point(1e6, 0.0, VMAX);
        assert_eq!(v, VMAX);
    }
}
