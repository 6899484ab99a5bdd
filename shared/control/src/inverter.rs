//! A switching two-level voltage-source inverter in front of the PMSM model: carrier-
//! comparison PWM, dead time, device voltage drop and an optional DC link (docs/architecture.md,
//! "Plant realism").
//!
//! **Modulator.** Sine-triangle comparison with min-max zero-sequence injection: the phase
//! references v_x* of the commanded αβ vector get v_0 = −(max v* + min v*)/2 added, which is
//! equivalent to space-vector PWM (the same switching instants, the same linear range
//! |u| ≤ V_dc/√3). The carrier is a symmetric triangle of frequency f_sw whose valleys and
//! peaks fall on the sample instants: t = 0 is a valley, and each sample interval holds
//! `2·f_sw·T_s` (a whole number ≥ 1) carrier half-periods. The duty cycles are computed once
//! per sample from the command and the DC-link voltage at the sample instant (the inverter's
//! own V_dc measurement), as a DSP updating its compare registers at the peak or valley.
//!
//! In a half-period T_h whose carrier rises from −1 to +1 the pole of phase x is high while
//! m_x = v_x/(V_dc/2) > carrier and falls at τ_x = T_h·(1 + m_x)/2; in a falling half it
//! rises at τ_x = T_h·(1 − m_x)/2. Over either half the pole is high for T_h·(1 + m_x)/2, so
//! the mean pole voltage is m_x·V_dc/2: without dead time and drops the mean αβ voltage over
//! a sample is exactly the command.
//!
//! **Dead time** t_d: at each edge the outgoing device turns off at τ_x and the incoming one
//! on at τ_x + t_d; in between the current chooses the pole through the free-wheeling diodes,
//! low for i_x > 0 and high for i_x < 0 (the sign taken at τ_x; at i_x = 0 the pole keeps its
//! outgoing state). One of the two edges of a carrier period is thus delayed by t_d, and the
//! mean pole voltage moves by −sign(i_x)·t_d·f_sw·V_dc. An edge within t_d of the end of its
//! half-period has its dead time cut at that end (the carrier's peak or valley); a phase at
//! full modulation (|m_x| = 1) does not switch and has none.
//!
//! **Device drop**: every conducting device (transistor or diode) drops `v_drop_v` along the
//! current: the pole voltage is (s_x − 1/2)·V_dc − sign(i_x)·v_drop (i_x at the start of the
//! piece).
//!
//! **DC link** (optional): a source V_src behind a resistance R_s feeds a capacitor C:
//! C·dv_dc/dt = (V_src − v_dc)/R_s − i_dc, with i_dc = Σ s_x·i_x the current of the upper
//! devices. Without it the link is stiff at V_src.
//!
//! **Integration.** Between two switching instants the pole states are constant, so the αβ
//! voltage is piecewise constant; the dq model (Kyslan eqs 1–4) is integrated over each piece
//! by classic RK4 with the voltage rotated into the rotor frame at every stage (a constant
//! stator-frame vector is not constant in dq while the rotor turns), in steps no longer than
//! `max_step_s`. No allocation: at most seven instants per half-period, sorted in place.

use crate::motor::{
    derivative, wrap_2pi, LoadModel, Mechanics, MotorInput, MotorParams, MotorState,
};
use crate::transforms::{inverse_park, park, AlphaBeta, Dq};

/// Most carrier half-periods per sample (2·f_sw·T_s): bounds the cost of a sample.
pub const MAX_HALF_PERIODS: u32 = 64;

/// The DC link behind the inverter.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DcLink {
    /// Capacitance, F.
    pub c_f: f64,
    /// Source resistance, Ω.
    pub r_source_ohm: f64,
}

/// Parameters of the switching inverter.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PwmSpec {
    /// Source (and, without a DC link, bus) voltage, V.
    pub v_dc_v: f64,
    /// Carrier frequency f_sw, Hz.
    pub f_sw_hz: f64,
    /// Dead time t_d, s.
    pub dead_time_s: f64,
    /// Forward drop of a conducting device, V.
    pub v_drop_v: f64,
    /// The DC link, if any (else stiff).
    pub dc_link: Option<DcLink>,
}

impl PwmSpec {
    /// Mean pole-voltage error of the dead time, t_d·f_sw·V_dc, V (with −sign(i_x)).
    pub fn dead_time_error_v(&self) -> f64 {
        self.dead_time_s * self.f_sw_hz * self.v_dc_v
    }
}

/// What one sample of the switching inverter and motor produced.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct PwmSample {
    /// Motor state at the end of the sample.
    pub x: MotorState,
    /// Motor state at the ADC instant (`lead_s` before the end), the end when `lead_s` is 0.
    pub x_adc: MotorState,
    /// Mean αβ voltage applied over the sample (volt-seconds / T_s), V.
    pub mean_u_ab: AlphaBeta,
    /// Mean dq current over the sample (trapezoidal over the RK4 steps, whose pieces are
    /// nearly straight: the steps are far shorter than L/R), A.
    pub mean_i_dq: Dq,
}

/// The switching inverter's state: the DC-link voltage and its carrier bookkeeping.
#[derive(Debug, Clone, Copy)]
pub struct SwitchingInverter {
    spec: PwmSpec,
    /// Carrier half-periods per sample.
    halves: u32,
    /// Longest RK4 step, s.
    max_step_s: f64,
    /// DC-link voltage, V.
    pub v_dc: f64,
}

/// Integration state: motor plus DC-link voltage.
#[derive(Debug, Clone, Copy)]
struct Xs {
    m: MotorState,
    v_dc: f64,
}

/// Everything constant over one piece: pole states, the drops' αβ vector, the load.
#[derive(Debug, Clone, Copy)]
struct Piece<'a> {
    motor: &'a MotorParams,
    mech: Mechanics,
    /// Clarke of the pole states (s_a, s_b, s_c) ∈ {0, 1}: u_ab = v_dc·s_ab + drop_ab.
    s_ab: AlphaBeta,
    drop_ab: AlphaBeta,
    s: [f64; 3],
    t_load: f64,
    load: LoadModel,
    link: Option<(DcLink, f64)>,
}

impl Piece<'_> {
    fn u_ab(&self, v_dc: f64) -> AlphaBeta {
        AlphaBeta {
            alpha: v_dc * self.s_ab.alpha + self.drop_ab.alpha,
            beta: v_dc * self.s_ab.beta + self.drop_ab.beta,
        }
    }

    /// d/dt of motor and link: Kyslan eqs (1)–(3) with u_dq = Park(u_ab, θ_e(t)).
    fn f(&self, x: &Xs) -> Xs {
        let theta_e = self.motor.p() * x.m.theta_m;
        let u = park(self.u_ab(x.v_dc), theta_e);
        let dm = derivative(
            self.motor,
            self.mech,
            &x.m,
            &MotorInput {
                u_d: u.d,
                u_q: u.q,
                t_load: self.t_load,
                load: self.load,
            },
        );
        let dv = match self.link {
            None => 0.0,
            Some((l, v_src)) => {
                let i = phase_currents(self.motor, &x.m);
                let i_dc = self.s[0] * i[0] + self.s[1] * i[1] + self.s[2] * i[2];
                ((v_src - x.v_dc) / l.r_source_ohm - i_dc) / l.c_f
            }
        };
        Xs { m: dm, v_dc: dv }
    }
}

fn axpy(x: &Xs, h: f64, d: &Xs) -> Xs {
    Xs {
        m: MotorState {
            i_d: x.m.i_d + h * d.m.i_d,
            i_q: x.m.i_q + h * d.m.i_q,
            omega_m: x.m.omega_m + h * d.m.omega_m,
            theta_m: x.m.theta_m + h * d.m.theta_m,
        },
        v_dc: x.v_dc + h * d.v_dc,
    }
}

/// One classic RK4 step of length h: x + h/6·(k1 + 2k2 + 2k3 + k4).
fn rk4(p: &Piece, x: &Xs, h: f64) -> Xs {
    let k1 = p.f(x);
    let k2 = p.f(&axpy(x, 0.5 * h, &k1));
    let k3 = p.f(&axpy(x, 0.5 * h, &k2));
    let k4 = p.f(&axpy(x, h, &k3));
    axpy(
        &axpy(&axpy(&axpy(x, h / 6.0, &k1), h / 3.0, &k2), h / 3.0, &k3),
        h / 6.0,
        &k4,
    )
}

/// The phase currents (a, b, c) of a motor state, A.
pub fn phase_currents(m: &MotorParams, x: &MotorState) -> [f64; 3] {
    let ab = inverse_park(Dq { d: x.i_d, q: x.i_q }, m.p() * x.theta_m);
    let s3 = 0.5 * 3f64.sqrt();
    [
        ab.alpha,
        -0.5 * ab.alpha + s3 * ab.beta,
        -0.5 * ab.alpha - s3 * ab.beta,
    ]
}

/// Sign of a current: −1, 0 or +1.
fn sign(i: f64) -> f64 {
    if i > 0.0 {
        1.0
    } else if i < 0.0 {
        -1.0
    } else {
        0.0
    }
}

/// Min-max (SVPWM-equivalent) modulation: the normalised phase references m_x ∈ [−1, 1] of
/// αβ command `u` on a bus of `v_dc` volts.
pub fn modulation(u: AlphaBeta, v_dc: f64) -> [f64; 3] {
    let s3 = 0.5 * 3f64.sqrt();
    let v = [
        u.alpha,
        -0.5 * u.alpha + s3 * u.beta,
        -0.5 * u.alpha - s3 * u.beta,
    ];
    let v0 = -0.5 * (v[0].max(v[1]).max(v[2]) + v[0].min(v[1]).min(v[2]));
    let half = 0.5 * v_dc;
    v.map(|vx| ((vx + v0) / half).clamp(-1.0, 1.0))
}

impl SwitchingInverter {
    /// The inverter of `spec` at sample time `ts_s`, with RK4 steps no longer than
    /// `max_step_s`. `spec` must have been checked ([`SwitchingInverter::check`]).
    pub fn new(spec: PwmSpec, ts_s: f64, max_step_s: f64) -> Self {
        Self {
            spec,
            halves: (2.0 * spec.f_sw_hz * ts_s).round() as u32,
            max_step_s,
            v_dc: spec.v_dc_v,
        }
    }

    /// The parameters.
    pub fn spec(&self) -> &PwmSpec {
        &self.spec
    }

    /// Carrier half-periods per sample.
    pub fn half_periods(&self) -> u32 {
        self.halves
    }

    /// Checks `spec` against sample time `ts_s`: a one-line error naming the field.
    pub fn check(spec: &PwmSpec, ts_s: f64) -> Result<(), String> {
        let f = spec.f_sw_hz;
        if !(f.is_finite() && f > 0.0) {
            return Err(format!("inverter.f_sw_hz = {f} must be a frequency > 0 Hz"));
        }
        let halves = 2.0 * f * ts_s;
        if (halves - halves.round()).abs() > 1e-9
            || halves.round() < 1.0
            || halves.round() > f64::from(MAX_HALF_PERIODS)
        {
            return Err(format!(
                "inverter.f_sw_hz = {f} must make 2·f_sw/f_s a whole number in 1..={MAX_HALF_PERIODS} (the samples fall on the carrier's peaks and valleys); f_s = {} Hz",
                1.0 / ts_s
            ));
        }
        let t_half = 0.5 / f;
        let td = spec.dead_time_s;
        if !(td.is_finite() && td >= 0.0 && td < t_half) {
            return Err(format!(
                "inverter.dead_time_us = {:.3} must be >= 0 and below half the switching period ({:.3} µs)",
                td * 1e6,
                t_half * 1e6
            ));
        }
        let vd = spec.v_drop_v;
        if !(vd.is_finite() && vd >= 0.0 && vd < 0.1 * spec.v_dc_v) {
            return Err(format!(
                "inverter.v_drop_v = {vd} must be >= 0 and below a tenth of v_dc_v"
            ));
        }
        if let Some(l) = spec.dc_link {
            if !(l.c_f.is_finite() && l.c_f > 0.0 && l.c_f <= 1.0) {
                return Err(format!(
                    "inverter.dc_link_c_uf = {:.3} must be in (0, 1e6] µF",
                    l.c_f * 1e6
                ));
            }
            if !(l.r_source_ohm.is_finite() && l.r_source_ohm > 0.0 && l.r_source_ohm <= 1e3) {
                return Err(format!(
                    "inverter.r_source_ohm = {} must be in (0, 1000] Ω",
                    l.r_source_ohm
                ));
            }
        }
        Ok(())
    }

    /// Integrates motor and DC link over sample k, [k·T_s, (k+1)·T_s), with the αβ command
    /// `u_ref` (already limited to the linear range) and returns the end state, the state
    /// `lead_s` before the end (the ADC instant, 0 ≤ lead_s < T_s) and the mean voltage.
    pub fn sample(
        &mut self,
        motor: &MotorParams,
        mech: Mechanics,
        x0: &MotorState,
        k: u64,
        u_ref: AlphaBeta,
        t_load: f64,
        load: LoadModel,
        ts_s: f64,
        lead_s: f64,
    ) -> PwmSample {
        let mut x = Xs {
            m: *x0,
            v_dc: self.v_dc,
        };
        if let Mechanics::PrescribedSpeed(w) = mech {
            x.m.omega_m = w;
        }
        let m = modulation(u_ref, x.v_dc);
        let t_half = ts_s / f64::from(self.halves);
        let td = self.spec.dead_time_s;
        let link = self.spec.dc_link.map(|l| (l, self.spec.v_dc_v));
        // The ADC instant as an offset into the sample (none: the end).
        let t_adc = ts_s - lead_s;
        let mut x_adc = None;
        let want_adc = lead_s > 0.0;
        let mut volt_s = AlphaBeta::default();
        let mut amp_s = Dq::default();
        for j in 0..self.halves {
            let t0 = f64::from(j) * t_half;
            // Half-period index from t = 0 (a valley): even halves rise.
            let rising = (k * u64::from(self.halves) + u64::from(j)).is_multiple_of(2);
            let (out_state, in_state) = if rising { (1.0, 0.0) } else { (0.0, 1.0) };
            let mut edge = [0.0; 3];
            for (e, mx) in edge.iter_mut().zip(m) {
                *e = t_half
                    * if rising {
                        0.5 * (1.0 + mx)
                    } else {
                        0.5 * (1.0 - mx)
                    };
            }
            // Instants of the half-period: the three edges, their dead-time ends, the ADC.
            let mut ev = [t_half; 7];
            for p in 0..3 {
                ev[2 * p] = edge[p];
                ev[2 * p + 1] = (edge[p] + td).min(t_half);
            }
            let adc_here = want_adc && x_adc.is_none() && t_adc >= t0 && t_adc < t0 + t_half;
            if adc_here {
                ev[6] = t_adc - t0;
            }
            ev.sort_unstable_by(f64::total_cmp);
            let mut diode: [Option<f64>; 3] = [None; 3];
            let mut t = 0.0;
            for &te in ev.iter().chain(std::iter::once(&t_half)) {
                if adc_here && x_adc.is_none() && t >= t_adc - t0 {
                    x_adc = Some(x.m);
                }
                let dt = te - t;
                if dt <= 0.0 {
                    continue;
                }
                let i = phase_currents(motor, &x.m);
                let mut s = [0.0; 3];
                let mut drop = [0.0; 3];
                for p in 0..3 {
                    s[p] = if t < edge[p] {
                        out_state
                    } else if t < edge[p] + td && edge[p] > 0.0 {
                        // Dead time: the diode the current chooses (sign at the edge).
                        *diode[p].get_or_insert(if i[p] > 0.0 {
                            0.0
                        } else if i[p] < 0.0 {
                            1.0
                        } else {
                            out_state
                        })
                    } else {
                        in_state
                    };
                    drop[p] = -sign(i[p]) * self.spec.v_drop_v;
                }
                let piece = Piece {
                    motor,
                    mech,
                    s_ab: clarke3(s),
                    drop_ab: clarke3(drop),
                    s,
                    t_load,
                    load,
                    link,
                };
                let u = piece.u_ab(x.v_dc);
                volt_s.alpha += u.alpha * dt;
                volt_s.beta += u.beta * dt;
                let n = (dt / self.max_step_s).ceil().max(1.0);
                let h = dt / n;
                for _ in 0..n as u32 {
                    let before = (x.m.i_d, x.m.i_q);
                    x = rk4(&piece, &x, h);
                    amp_s.d += 0.5 * h * (before.0 + x.m.i_d);
                    amp_s.q += 0.5 * h * (before.1 + x.m.i_q);
                }
                t = te;
            }
        }
        if let Mechanics::PrescribedSpeed(w) = mech {
            x.m.omega_m = w;
        }
        self.v_dc = x.v_dc;
        let mut end = x.m;
        end.theta_m = wrap_2pi(end.theta_m);
        let mut adc = x_adc.unwrap_or(x.m);
        adc.theta_m = wrap_2pi(adc.theta_m);
        PwmSample {
            x: end,
            x_adc: adc,
            mean_u_ab: AlphaBeta {
                alpha: volt_s.alpha / ts_s,
                beta: volt_s.beta / ts_s,
            },
            mean_i_dq: Dq {
                d: amp_s.d / ts_s,
                q: amp_s.q / ts_s,
            },
        }
    }
}

/// Amplitude-invariant Clarke of three phase quantities (the zero sequence drops out).
fn clarke3(v: [f64; 3]) -> AlphaBeta {
    crate::transforms::clarke(v[0], v[1], v[2])
}

#[cfg(test)]
mod tests {
    use super::*;

    const TS: f64 = 1e-4;

    fn spec(td: f64) -> PwmSpec {
        PwmSpec {
            v_dc_v: 470.0,
            f_sw_hz: 10_000.0,
            dead_time_s: td,
            v_drop_v: 0.0,
            dc_link: None,
        }
    }

    /// The locked rotor (ω = 0) of the low1998 motor with a fixed current direction: the
    /// phases' signs stay put, so the dead time's error per phase is exact.
    fn locked() -> (MotorParams, Mechanics) {
        (MotorParams::low1998(), Mechanics::PrescribedSpeed(0.0))
    }

    #[test]
    fn min_max_injection_reaches_the_svpwm_limit_and_no_further() {
        // On the circle |u| = V_dc/√3 the injected references are centred (max = −min) and
        // span at most the carrier: max − min is the largest line-to-line voltage over
        // V_dc/2, at most √3·|u|/(V_dc/2) = 2, reached where a line voltage peaks. Grid of
        // 0.5°: the peak is met within cos(0.25°) = 1 − 1e-5.
        let r = 470.0 / 3f64.sqrt();
        let mut top: f64 = 0.0;
        for k in 0..720 {
            let a = f64::from(k).to_radians() * 0.5;
            let m = modulation(
                AlphaBeta {
                    alpha: r * libm::cos(a),
                    beta: r * libm::sin(a),
                },
                470.0,
            );
            let (hi, lo) = (m[0].max(m[1]).max(m[2]), m[0].min(m[1]).min(m[2]));
            assert!((hi + lo).abs() < 1e-12 && hi <= 1.0 + 1e-12, "{a}: {m:?}");
            top = top.max(hi);
        }
        assert!(top > 1.0 - 1e-4, "{top}");
    }

    #[test]
    fn without_dead_time_the_mean_voltage_of_a_sample_is_the_command() {
        // The pole is high for T_h·(1 + m)/2 in every half-period (module doc), so the volt-
        // seconds are exact up to rounding (1e-12 relative of V_dc).
        let (mot, mech) = locked();
        for halves in [1u32, 2, 4] {
            let sp = PwmSpec {
                f_sw_hz: f64::from(halves) * 0.5 / TS,
                ..spec(0.0)
            };
            let mut inv = SwitchingInverter::new(sp, TS, TS / 4.0);
            let u = AlphaBeta {
                alpha: 120.0,
                beta: -200.0,
            };
            for k in 0..4 {
                let o = inv.sample(
                    &mot,
                    mech,
                    &MotorState::default(),
                    k,
                    u,
                    0.0,
                    LoadModel::Active,
                    TS,
                    0.0,
                );
                assert!(
                    (o.mean_u_ab.alpha - u.alpha).abs() < 1e-12 * 470.0,
                    "{halves}: {o:?}"
                );
                assert!(
                    (o.mean_u_ab.beta - u.beta).abs() < 1e-12 * 470.0,
                    "{halves}: {o:?}"
                );
            }
        }
    }

    /// One sample of a locked rotor with i along phase a (i_a = 2 A, i_b = i_c = −1 A) under
    /// the 5 V that holds it (R·i): the command and what `sp` made of it. The current moves by
    /// less than 1e-3 A in a sample, far from any zero crossing, so no sign changes.
    fn along_phase_a(sp: PwmSpec) -> (AlphaBeta, PwmSample) {
        let (mot, mech) = locked();
        let mut inv = SwitchingInverter::new(sp, TS, TS / 4.0);
        let x = MotorState {
            i_d: 2.0,
            ..Default::default()
        };
        let u = AlphaBeta {
            alpha: 5.0,
            beta: 0.0,
        };
        (
            u,
            inv.sample(&mot, mech, &x, 0, u, 0.0, LoadModel::Active, TS, 0.0),
        )
    }

    #[test]
    fn dead_time_moves_each_phase_by_td_fsw_vdc_against_its_current() {
        // The phase voltages' errors are the pole errors −sign(i_x)·t_d·f_sw·V_dc less their
        // mean, so the αβ error is Clarke(−1, +1, +1)·ΔV = (−4/3·ΔV, 0).
        let sp = spec(2e-6);
        let (u, o) = along_phase_a(sp);
        let dv = sp.dead_time_error_v();
        assert!((dv - 9.4).abs() < 1e-12);
        let err = o.mean_u_ab.alpha - u.alpha;
        assert!(
            (err + 4.0 / 3.0 * dv).abs() < 1e-9 * 470.0,
            "error {err} V vs {}",
            -4.0 / 3.0 * dv
        );
        assert!((o.mean_u_ab.beta).abs() < 1e-9 * 470.0, "{o:?}");
    }

    #[test]
    fn a_phase_at_full_modulation_does_not_switch_and_has_no_dead_time() {
        // |u| = V_dc/√3 at 30°: m_a = +1, m_b = 0, m_c = −1. Locked rotor, i along phase a
        // (i_a = 2 A, i_b = i_c = −1 A); the voltage drives the current along 30°, where
        // i_b's share is cos(−90°) = 0, so no sign changes within the sample. Only phase b
        // switches, so the error is Clarke(0, +ΔV, 0) = (−ΔV/3, ΔV/√3).
        let (mot, mech) = locked();
        let sp = spec(2e-6);
        let mut inv = SwitchingInverter::new(sp, TS, TS / 4.0);
        let r = 470.0 / 3f64.sqrt();
        let a = std::f64::consts::PI / 6.0;
        let u = AlphaBeta {
            alpha: r * libm::cos(a),
            beta: r * libm::sin(a),
        };
        let x = MotorState {
            i_d: 2.0,
            ..Default::default()
        };
        let o = inv.sample(&mot, mech, &x, 0, u, 0.0, LoadModel::Active, TS, 0.0);
        let dv = sp.dead_time_error_v();
        let (ea, eb) = (o.mean_u_ab.alpha - u.alpha, o.mean_u_ab.beta - u.beta);
        assert!((ea + dv / 3.0).abs() < 1e-9 * 470.0, "α error {ea} V");
        assert!(
            (eb - dv / 3f64.sqrt()).abs() < 1e-9 * 470.0,
            "β error {eb} V"
        );
    }

    #[test]
    fn the_device_drop_opposes_each_current() {
        let (u, o) = along_phase_a(PwmSpec {
            v_drop_v: 1.5,
            ..spec(0.0)
        });
        // Clarke(−1, +1, +1)·v_drop: −4/3·1.5 V on α.
        assert!((o.mean_u_ab.alpha - u.alpha + 2.0).abs() < 1e-9, "{o:?}");
    }

    #[test]
    fn the_dc_link_sags_by_the_load_current_times_the_source_resistance() {
        // A constant 2 A motoring current at a prescribed 50 rad/s draws a mean i_dc; once the
        // capacitor has settled, V_src − v_dc = R_s·mean(i_dc) and the power balance holds:
        // v_dc·mean(i_dc) = 3/2·(u_d·i_d + u_q·i_q) (ripple: a few ‰).
        let m = MotorParams::low1998();
        let mech = Mechanics::PrescribedSpeed(50.0);
        let link = DcLink {
            c_f: 200e-6,
            r_source_ohm: 1.0,
        };
        let sp = PwmSpec {
            dc_link: Some(link),
            ..spec(0.0)
        };
        let mut inv = SwitchingInverter::new(sp, TS, TS / 4.0);
        let we = m.p() * 50.0;
        let (i_d, i_q) = (0.0, 2.0);
        let u_dq = Dq {
            d: m.r_ohm * i_d - we * m.l_q_h * i_q,
            q: m.r_ohm * i_q + we * (m.l_d_h * i_d + m.psi_pm_wb),
        };
        let mut x = MotorState {
            i_d,
            i_q,
            omega_m: 50.0,
            theta_m: 0.0,
        };
        let mut p_sum = 0.0;
        let n = 3000;
        for k in 0..n {
            let u = inverse_park(u_dq, m.p() * (x.theta_m + 0.5 * 50.0 * TS));
            let o = inv.sample(&m, mech, &x, k, u, 0.0, LoadModel::Active, TS, 0.0);
            if k >= n - 1000 {
                let ud = park(o.mean_u_ab, m.p() * (x.theta_m + 0.5 * 50.0 * TS));
                p_sum += 1.5 * (ud.d * x.i_d + ud.q * x.i_q);
            }
            x = o.x;
        }
        let p = p_sum / 1000.0;
        let sag = 470.0 - inv.v_dc;
        // v·(V − v)/R_s = P: the sag that carries P through R_s.
        let expected = 470.0 - 0.5 * (470.0 + (470.0 * 470.0 - 4.0 * link.r_source_ohm * p).sqrt());
        assert!(
            sag > 0.0 && (sag - expected).abs() < 0.02 * expected,
            "sag {sag} V, expected {expected} V (P = {p} W)"
        );
    }

    /// Steady state at a prescribed speed under a constant dq command turned into αβ at the
    /// mid-sample angle (as the plant does), dead time 0, no drop, stiff link; the averaged
    /// model's steady state is the solution of u = R·i + jω_e·(L·i + ψ).
    fn steady(w: f64, lead_s: f64) -> (MotorParams, Dq, Vec<PwmSample>) {
        let m = MotorParams::low1998();
        let mech = Mechanics::PrescribedSpeed(w);
        let we = m.p() * w;
        let i_ss = Dq { d: -0.5, q: 2.0 };
        let u_dq = Dq {
            d: m.r_ohm * i_ss.d - we * m.l_q_h * i_ss.q,
            q: m.r_ohm * i_ss.q + we * (m.l_d_h * i_ss.d + m.psi_pm_wb),
        };
        let mut inv = SwitchingInverter::new(spec(0.0), TS, TS / 4.0);
        let mut x = MotorState {
            omega_m: w,
            ..Default::default()
        };
        let mut out = Vec::new();
        // 0.15 s = 12 L/R: the transient has decayed to e^-12 = 6e-6.
        for k in 0..1500u64 {
            let u = inverse_park(u_dq, m.p() * x.theta_m + 0.5 * we * TS);
            let o = inv.sample(&m, mech, &x, k, u, 0.0, LoadModel::Active, TS, lead_s);
            x = o.x;
            if k >= 1400 {
                out.push(o);
            }
        }
        (m, i_ss, out)
    }

    #[test]
    fn over_a_switching_period_the_switching_model_averages_to_the_averaged_model() {
        // Integrating L·di/dt = u − R·i − … over one period of the periodic steady state
        // (i(T) = i(0)) leaves R·mean(i) = mean(u) − …: the dq model is linear at a
        // prescribed speed, so the period's mean current is the averaged model's current,
        // up to the rotation of a stator-frame voltage within the period, (ω_e·T_s)²/24
        // = 2e-5 at 500 rpm, and the trapezoidal mean (≈ 1e-7). One carrier period per
        // sample here, so each sample's mean is a period's mean. Bound: 1e-3 (the check).
        for rpm in [0.0, 500.0] {
            let (_, i_ss, out) = steady(rpm * std::f64::consts::PI / 30.0, 0.0);
            let worst = out
                .iter()
                .map(|o| libm::hypot(o.mean_i_dq.d - i_ss.d, o.mean_i_dq.q - i_ss.q))
                .fold(0.0, f64::max)
                / libm::hypot(i_ss.d, i_ss.q);
            eprintln!(
                "{rpm} rpm: largest relative difference of a period's mean current {worst:.2e}"
            );
            assert!(worst < 1e-3, "{rpm} rpm: {worst}");
        }
    }

    #[test]
    fn the_adc_instant_sees_the_ripple_and_the_carrier_valley_its_midpoint() {
        // The current sampled at the carrier's valley (the sample instant) is the ripple's
        // midpoint, close to the period's mean; a quarter period earlier the ADC sees the
        // ripple's extreme, further away. Both on the same steady state. The midpoint's
        // error is second order in R·T_h/L = 4e-3 (and ω_e·T_s), the extreme's deviation is
        // first order: a ratio of the order of L/(R·T_h) = 240; the bound 10 leaves margin.
        let w = 500.0 * std::f64::consts::PI / 30.0;
        let (_, i_ss, at_valley) = steady(w, 0.0);
        let (_, _, early) = steady(w, 0.25 * TS);
        let dev = |v: &[PwmSample], adc: bool| {
            v.iter()
                .map(|o| {
                    let x = if adc { o.x_adc } else { o.x };
                    libm::hypot(x.i_d - i_ss.d, x.i_q - i_ss.q)
                })
                .fold(0.0, f64::max)
        };
        let (mid, quarter) = (dev(&at_valley, false), dev(&early, true));
        eprintln!("sampled current off the mean: at the valley {mid:.2e} A, a quarter period earlier {quarter:.2e} A");
        assert!(quarter > 10.0 * mid, "valley {mid}, quarter {quarter}");
    }

    #[test]
    fn bad_specs_are_named() {
        for (sp, needle) in [
            (
                PwmSpec {
                    f_sw_hz: 7_000.0,
                    ..spec(0.0)
                },
                "inverter.f_sw_hz = 7000",
            ),
            (
                PwmSpec {
                    f_sw_hz: 0.0,
                    ..spec(0.0)
                },
                "inverter.f_sw_hz = 0",
            ),
            (spec(50e-6), "inverter.dead_time_us = 50"),
            (spec(-1e-6), "inverter.dead_time_us = -1"),
            (
                PwmSpec {
                    v_drop_v: 100.0,
                    ..spec(0.0)
                },
                "inverter.v_drop_v = 100",
            ),
            (
                PwmSpec {
                    dc_link: Some(DcLink {
                        c_f: 1e-3,
                        r_source_ohm: 0.0,
                    }),
                    ..spec(0.0)
                },
                "inverter.r_source_ohm = 0",
            ),
        ] {
            let e = SwitchingInverter::check(&sp, TS).unwrap_err();
            assert!(e.contains(needle), "{e}");
        }
        SwitchingInverter::check(
            &PwmSpec {
                f_sw_hz: 5_000.0,
                ..spec(2e-6)
            },
            TS,
        )
        .unwrap();
    }
}
