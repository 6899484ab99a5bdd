//! Speed controller: PI designed by the symmetrical optimum (SO) with a reference prefilter,
//! anti-windup and the current limit (Kyslan §5 "PI cascade").

use super::pi::Pi;
use crate::motor::MotorParams;
use serde::{Deserialize, Serialize};

/// Inputs of the symmetrical-optimum design.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct SoSpec {
    /// Sum of the small time constants of the speed loop T_σ, s (see [`sum_of_small_time_constants`]).
    pub t_sigma_s: f64,
    /// Target time to first reach the set-point after a step (0–100 % rise time), s.
    pub rise_time_s: f64,
}

/// Result of the design.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SoDesign {
    /// SO parameter a (a = 2 is the classic symmetrical optimum).
    pub a: f64,
    /// Equivalent small time constant used by the design, s (≥ the physical T_σ).
    pub t_eq_s: f64,
    /// Physical T_σ, s.
    pub t_sigma_s: f64,
    /// Proportional gain K_p = J/(a·k_t·T_eq), A·s/rad.
    pub k_p: f64,
    /// Integral time T_i = a²·T_eq, s.
    pub t_i_s: f64,
    /// Prefilter time constant (= T_i), s.
    pub t_prefilter_s: f64,
    /// Rise time predicted by the reduced model, s.
    pub predicted_rise_time_s: f64,
    /// Overshoot predicted by the reduced model, %.
    pub predicted_overshoot_pct: f64,
    /// Set when the target could not be met within a ∈ [A_MIN, 2]; says why.
    pub warning: Option<String>,
    /// The largest |z| of the sampled cascade's poles ([`SpeedLoopModel::spectral_radius`]):
    /// above 1 the loop is unstable and the figures are only those of the simulated window.
    #[serde(default)]
    pub spectral_radius: f64,
}

/// Smallest SO parameter we accept (below it the loop is poorly damped).
pub const A_MIN: f64 = 1.4;

/// T_σ of the cascade: the closed current loop τ_c, its computation and PWM delay (1.5·T_s),
/// the speed-filter group delay τ_f plus half a sample for the backward difference, the
/// one-sample hand-over of the current reference, and the zero-order hold of a speed loop
/// running every N samples (N·T_s/2).
pub fn sum_of_small_time_constants(tau_c: f64, ts: f64, tau_f: f64, n: u32) -> f64 {
    tau_c + 1.5 * ts + tau_f + 0.5 * ts + ts + 0.5 * f64::from(n) * ts
}

/// Step response of the reduced SO loop (plant k_t/(J s) behind a lag 1/(1 + T s), PI, and a
/// prefilter 1/(1 + T_i s)), normalised: returns (first time y ≥ 1, overshoot %). Independent
/// of J and k_t because K_p absorbs them.
pub fn reduced_step_response(a: f64, t_eq: f64) -> (f64, f64) {
    let ti = a * a * t_eq;
    // Normalised: K = K_p k_t/J = 1/(a T).
    let kk = 1.0 / (a * t_eq);
    // States: r_f (prefilter), x_i (integral of e), i (lag), y (speed).
    let f = |s: [f64; 4]| -> [f64; 4] {
        let (rf, xi, i, y) = (s[0], s[1], s[2], s[3]);
        let e = rf - y;
        let u = kk * (e + xi / ti);
        [(1.0 - rf) / ti, e, (u - i) / t_eq, i]
    };
    let h = t_eq / 200.0;
    let mut s = [0.0; 4];
    let mut t = 0.0;
    let mut rise = f64::NAN;
    let mut peak: f64 = 0.0;
    let t_end = 40.0 * ti.max(t_eq);
    while t < t_end {
        let k1 = f(s);
        let add = |s: [f64; 4], k: [f64; 4], c: f64| {
            [
                s[0] + c * k[0],
                s[1] + c * k[1],
                s[2] + c * k[2],
                s[3] + c * k[3],
            ]
        };
        let k2 = f(add(s, k1, 0.5 * h));
        let k3 = f(add(s, k2, 0.5 * h));
        let k4 = f(add(s, k3, h));
        for j in 0..4 {
            s[j] += h / 6.0 * (k1[j] + 2.0 * k2[j] + 2.0 * k3[j] + k4[j]);
        }
        t += h;
        if rise.is_nan() && s[3] >= 1.0 {
            rise = t;
        }
        peak = peak.max(s[3]);
    }
    (rise, (peak - 1.0).max(0.0) * 100.0)
}

/// The sampled cascade the speed PI is designed on (linear, no saturation, no saliency):
/// the closed current loop as a first-order lag τ_c behind a one-sample computation delay,
/// the rigid shaft k_t/(J s), the backward-difference speed with the Bessel filter of eq. (10),
/// and the PI with its prefilter running every N samples, its output used from the next
/// sample on — i.e. the same timing as the drive.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct SpeedLoopModel {
    /// Current-loop sample time T_s, s.
    pub ts: f64,
    /// Speed-loop divider N.
    pub n: u32,
    /// Closed current-loop time constant τ_c, s.
    pub tau_c_s: f64,
    /// Speed-filter group delay τ_f, s.
    pub tau_f_s: f64,
}

/// The states of [`SpeedLoopModel`]'s loop: the prefilter, the integrator, the reference
/// computed and the one in use, the current, the speed and its last value, and the speed
/// filter's four.
const SPEED_LOOP_STATES: usize = 11;

/// One state of [`SpeedLoopModel`]'s loop at a sample (normalised: K_p·k_t/J folded in).
#[derive(Debug, Clone, Copy)]
struct SpeedLoopState {
    rf: f64,
    xi: f64,
    iq_cmd: f64,
    iq_cmd_prev: f64,
    iq: f64,
    w: f64,
    w_prev: f64,
    filt: super::filter::Bessel2,
}

impl SpeedLoopState {
    /// The loop's own states, in the order of [`SPEED_LOOP_STATES`]'s first seven.
    fn own(&mut self) -> [&mut f64; 7] {
        [
            &mut self.rf,
            &mut self.xi,
            &mut self.iq_cmd,
            &mut self.iq_cmd_prev,
            &mut self.iq,
            &mut self.w,
            &mut self.w_prev,
        ]
    }

    fn vector(mut self) -> [f64; SPEED_LOOP_STATES] {
        let mut v = [0.0; SPEED_LOOP_STATES];
        v[7..].copy_from_slice(&self.filt.state());
        for (x, s) in v.iter_mut().zip(self.own()) {
            *x = *s;
        }
        v
    }

    fn set(&mut self, v: &[f64; SPEED_LOOP_STATES]) {
        for (s, x) in self.own().into_iter().zip(v) {
            *s = *x;
        }
        self.filt.set_state([v[7], v[8], v[9], v[10]]);
    }
}

impl SpeedLoopModel {
    /// The loop at rest with the SO parameters (a, T_eq): its state and the sample step with
    /// reference `r` at phase `k` of the divider.
    fn at_rest(
        &self,
        a: f64,
        t_eq: f64,
    ) -> (SpeedLoopState, impl Fn(&mut SpeedLoopState, u64, f64)) {
        let ts = self.ts;
        let n = u64::from(self.n.max(1));
        let tw = ts * n as f64;
        let ti = a * a * t_eq;
        let kk = 1.0 / (a * t_eq); // K_p·k_t/J
        let pole = libm::exp(-tw / ti);
        let lag = 1.0 - libm::exp(-ts / self.tau_c_s);
        let s = SpeedLoopState {
            rf: 0.0,
            xi: 0.0,
            iq_cmd: 0.0,
            iq_cmd_prev: 0.0,
            iq: 0.0,
            w: 0.0,
            w_prev: 0.0,
            filt: super::filter::Bessel2::design(self.tau_f_s, ts),
        };
        let sample = move |s: &mut SpeedLoopState, k: u64, r: f64| {
            // Sample k: speed measured as the backward difference, then filtered.
            let w_hat = s.filt.step(0.5 * (s.w + s.w_prev));
            let used = s.iq_cmd; // reference computed at the last speed sample before k
            if k.is_multiple_of(n) {
                s.rf = pole * s.rf + (1.0 - pole) * r;
                let e = s.rf - w_hat;
                let y = kk * e + s.xi;
                s.xi += kk / ti * tw * e;
                s.iq_cmd = y;
            }
            // Current loop: command k acts from t_{k+1} (one-sample delay), first-order lag.
            let iq_next = s.iq + lag * (s.iq_cmd_prev - s.iq);
            s.iq_cmd_prev = used;
            s.w_prev = s.w;
            s.w += ts * 0.5 * (s.iq + iq_next); // k_t/J folded into kk
            s.iq = iq_next;
        };
        (s, sample)
    }

    /// Unit-step response of the model with the SO parameters (a, T_eq): returns
    /// (time to first reach the set-point, overshoot %). K_p·k_t/J = 1/(a·T_eq) makes the
    /// response independent of J and k_t.
    pub fn step_response(&self, a: f64, t_eq: f64) -> (f64, f64) {
        let (mut s, sample) = self.at_rest(a, t_eq);
        let mut rise = f64::NAN;
        let mut peak: f64 = 0.0;
        for k in 0..self.response_samples(a, t_eq) {
            sample(&mut s, k, 1.0);
            let t = (k + 1) as f64 * self.ts;
            if rise.is_nan() && s.w >= 1.0 {
                rise = t;
            }
            peak = peak.max(s.w);
        }
        (rise, (peak - 1.0).max(0.0) * 100.0)
    }

    /// How many samples [`Self::step_response`] simulates: 60 × the slower of T_i and T_eq,
    /// and 10 speed periods.
    fn response_samples(&self, a: f64, t_eq: f64) -> u64 {
        let ti = a * a * t_eq;
        ((60.0 * ti.max(t_eq)) / self.ts).ceil() as u64 + 10 * u64::from(self.n.max(1))
    }

    /// How long [`Self::step_response`] simulates, s.
    pub fn response_window_s(&self, a: f64, t_eq: f64) -> f64 {
        self.response_samples(a, t_eq) as f64 * self.ts
    }

    /// The largest |z| of the loop's poles with the SO parameters (a, T_eq): the eigenvalues
    /// of its map over one speed period N·T_s, X[j+1] = Φ X[j] (the loop is linear, so Φ's
    /// columns are its responses to each state alone, reference 0). Above 1 the loop is
    /// unstable: its step response grows without bound, and a rise time or overshoot read
    /// off it is only what the simulated window happened to show.
    pub fn spectral_radius(&self, a: f64, t_eq: f64) -> f64 {
        let n = u64::from(self.n.max(1));
        let (base, sample) = self.at_rest(a, t_eq);
        let mut phi = nalgebra::DMatrix::<f64>::zeros(SPEED_LOOP_STATES, SPEED_LOOP_STATES);
        for j in 0..SPEED_LOOP_STATES {
            let mut v = [0.0; SPEED_LOOP_STATES];
            v[j] = 1.0;
            let mut s = base;
            s.set(&v);
            for k in 0..n {
                sample(&mut s, k, 0.0);
            }
            for (i, x) in s.vector().into_iter().enumerate() {
                phi[(i, j)] = x;
            }
        }
        crate::math::spectral_radius(crate::math::eigenvalues(phi))
    }
}

/// Designs the speed PI for a rise-time target on the sampled cascade `model`.
///
/// Prefers the classic a = 2 and slows the loop (T_eq > T_σ) if the target allows it. If even
/// a = 2 with T_eq = T_σ is too slow, a is lowered towards [`A_MIN`] (less damping) to meet the
/// target; if that is not enough, the design keeps a = A_MIN and says so in `warning`.
pub fn design_symmetrical_optimum(
    m: &MotorParams,
    spec: &SoSpec,
    model: &SpeedLoopModel,
) -> SoDesign {
    let t_sigma = spec.t_sigma_s;
    let target = spec.rise_time_s;
    let rise = |a: f64, t: f64| model.step_response(a, t).0;
    let bisect = |lo: f64, hi: f64, f: &dyn Fn(f64) -> f64| {
        let (mut lo, mut hi) = (lo, hi);
        for _ in 0..60 {
            let mid = 0.5 * (lo + hi);
            // NaN (never reaches) counts as too slow.
            if f(mid) <= target {
                lo = mid;
            } else {
                hi = mid;
            }
        }
        lo
    };
    let (a, t_eq, warning) = if rise(2.0, t_sigma) <= target {
        (
            2.0,
            bisect(t_sigma, 100.0 * target, &|t| rise(2.0, t)),
            None,
        )
    } else if rise(A_MIN, t_sigma) > target || rise(A_MIN, t_sigma).is_nan() {
        let best = rise(A_MIN, t_sigma);
        (
            A_MIN,
            t_sigma,
            Some(format!(
                "speed rise time {:.2} ms is not reachable with T_sigma = {:.3} ms (best {:.2} ms at a = {A_MIN})",
                target * 1e3,
                t_sigma * 1e3,
                best * 1e3
            )),
        )
    } else {
        (bisect(A_MIN, 2.0, &|a| rise(a, t_sigma)), t_sigma, None)
    };
    let (rise_t, os) = model.step_response(a, t_eq);
    let t_i = a * a * t_eq;
    SoDesign {
        a,
        t_eq_s: t_eq,
        t_sigma_s: t_sigma,
        k_p: m.j_kgm2 / (a * m.k_t() * t_eq),
        t_i_s: t_i,
        t_prefilter_s: t_i,
        predicted_rise_time_s: rise_t,
        predicted_overshoot_pct: os,
        warning,
        spectral_radius: model.spectral_radius(a, t_eq),
    }
}

/// Discrete speed controller: first-order reference prefilter, PI, and the current limit on
/// i_q* with conditional-integration anti-windup. Runs at T_w = N·T_s.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SpeedPi {
    /// The PI on the speed error (output i_q*, A).
    pub pi: Pi,
    /// Prefilter state (filtered reference), rad/s.
    pub r_f: f64,
    /// Prefilter pole e^{−T_w/T_f}.
    pub prefilter_pole: f64,
}

impl SpeedPi {
    /// Builds the controller for sample time `t_w` and current limit `i_max`.
    pub fn new(d: &SoDesign, t_w: f64, i_max: f64) -> Self {
        Self {
            pi: Pi::new(d.k_p, d.k_p / d.t_i_s, t_w, i_max),
            r_f: 0.0,
            prefilter_pole: libm::exp(-t_w / d.t_prefilter_s),
        }
    }

    /// One step: speed reference and measured speed (mechanical rad/s) → i_q* (A).
    pub fn step(&mut self, omega_ref: f64, omega: f64) -> f64 {
        // Exact discretisation of 1/(1 + T_f s) with the reference held over the sample.
        self.r_f = self.prefilter_pole * self.r_f + (1.0 - self.prefilter_pole) * omega_ref;
        self.pi.step(self.r_f - omega, 0.0).y
    }

    /// Holds the output: returns the last output without integrating (stale input).
    pub fn hold(&self, omega: f64) -> f64 {
        (self.pi.k_p * (self.r_f - omega) + self.pi.x_i).clamp(self.pi.y_min, self.pi.y_max)
    }

    /// Bumpless take-over at speed `omega` and current `i_q`.
    pub fn preset(&mut self, omega: f64, i_q: f64) {
        self.r_f = omega;
        self.pi.preset_output(i_q, 0.0);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const MODEL: SpeedLoopModel = SpeedLoopModel {
        ts: 1e-4,
        n: 10,
        tau_c_s: 2.5e-4,
        tau_f_s: 1e-4,
    };

    #[test]
    fn sampled_model_approaches_the_continuous_one_for_fast_sampling() {
        // With tiny sample time and delays the sampled cascade is the textbook SO loop with a
        // lag of τ_c: same rise time within a few %.
        let fast = SpeedLoopModel {
            ts: 1e-6,
            n: 1,
            tau_c_s: 1e-4,
            tau_f_s: 1e-6,
        };
        let (r_d, os_d) = fast.step_response(2.0, 1.02e-4);
        let (r_c, os_c) = reduced_step_response(2.0, 1.02e-4);
        assert!((r_d - r_c).abs() < 0.03 * r_c, "{r_d} vs {r_c}");
        assert!((os_d - os_c).abs() < 1.0, "{os_d} vs {os_c}");
    }

    #[test]
    fn classic_so_a2_has_about_8_percent_overshoot_with_prefilter() {
        // Textbook: SO with a = 2 and prefilter 1/(1 + 4T s): overshoot ≈ 8.1 %, rise ≈ 7.6 T.
        let (rise, os) = reduced_step_response(2.0, 1.0);
        assert!((os - 8.1).abs() < 0.3, "overshoot {os}");
        assert!((rise - 7.6).abs() < 0.2, "rise {rise}");
    }

    #[test]
    fn design_meets_the_rise_time_target() {
        let m = MotorParams::kyslan2015();
        for (t_sigma, target) in [(1.0e-3, 8e-3), (1.2e-3, 8e-3), (0.5e-3, 8e-3)] {
            let d = design_symmetrical_optimum(
                &m,
                &SoSpec {
                    t_sigma_s: t_sigma,
                    rise_time_s: target,
                },
                &MODEL,
            );
            assert!(d.warning.is_none());
            assert!(
                (d.predicted_rise_time_s - target).abs() <= MODEL.ts + 1e-12,
                "{d:?}"
            );
            assert!(d.a >= A_MIN && d.a <= 2.0);
            assert!(d.t_eq_s >= t_sigma);
        }
    }

    #[test]
    fn unreachable_target_warns() {
        let m = MotorParams::kyslan2015();
        let d = design_symmetrical_optimum(
            &m,
            &SoSpec {
                t_sigma_s: 5e-3,
                rise_time_s: 8e-3,
            },
            &MODEL,
        );
        assert!(d.warning.unwrap().contains("not reachable"));
    }

    #[test]
    fn gains_follow_so_formulas() {
        let m = MotorParams::kyslan2015();
        let d = design_symmetrical_optimum(
            &m,
            &SoSpec {
                t_sigma_s: 0.5e-3,
                rise_time_s: 8e-3,
            },
            &MODEL,
        );
        assert!((d.k_p - m.j_kgm2 / (d.a * m.k_t() * d.t_eq_s)).abs() < 1e-15);
        assert!((d.t_i_s - d.a * d.a * d.t_eq_s).abs() < 1e-15);
    }

    #[test]
    fn current_limit_and_anti_windup() {
        let m = MotorParams::kyslan2015();
        let d = design_symmetrical_optimum(
            &m,
            &SoSpec {
                t_sigma_s: 1e-3,
                rise_time_s: 8e-3,
            },
            &MODEL,
        );
        let mut c = SpeedPi::new(&d, 1e-3, 1.6);
        for _ in 0..100 {
            let i = c.step(1000.0, 0.0);
            assert!(i <= 1.6);
        }
        assert!(c.pi.x_i <= 1.6 + 1e-12);
    }
}
