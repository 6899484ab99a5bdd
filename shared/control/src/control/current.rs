//! d/q current controllers: PI with decoupling and back-EMF feed-forward (Kyslan §5, the
//! "PI cascade" reference structure).

use super::pi::Pi;
use crate::motor::MotorParams;
use serde::{Deserialize, Serialize};

/// Design of the d/q current PIs by pole–zero cancellation: with decoupling the current
/// path is `1/(L s + R)`, and `K_p = L/τ_c`, `K_i = R/τ_c` give the closed loop `1/(τ_c s + 1)`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct CurrentPiDesign {
    /// Closed-loop time constant τ_c, s.
    pub tau_c_s: f64,
    /// d-axis K_p, V/A.
    pub k_p_d: f64,
    /// d-axis K_i, V/(A·s).
    pub k_i_d: f64,
    /// q-axis K_p, V/A.
    pub k_p_q: f64,
    /// q-axis K_i, V/(A·s).
    pub k_i_q: f64,
}

impl CurrentPiDesign {
    /// Pole–zero-cancellation design for closed-loop time constant `tau_c_s`.
    pub fn new(m: &MotorParams, tau_c_s: f64) -> Self {
        Self {
            tau_c_s,
            k_p_d: m.l_d_h / tau_c_s,
            k_i_d: m.r_ohm / tau_c_s,
            k_p_q: m.l_q_h / tau_c_s,
            k_i_q: m.r_ohm / tau_c_s,
        }
    }
}

/// Inputs of one current-control step, in the controller's (estimated) rotor frame.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct CurrentInput {
    /// d-axis current reference, A.
    pub i_d_ref: f64,
    /// q-axis current reference, A.
    pub i_q_ref: f64,
    /// Measured d-axis current, A.
    pub i_d: f64,
    /// Measured q-axis current, A.
    pub i_q: f64,
    /// Electrical speed used for decoupling, rad/s.
    pub omega_e: f64,
}

/// Output voltage command in the rotor frame.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct VoltageDq {
    /// d-axis voltage, V.
    pub u_d: f64,
    /// q-axis voltage, V.
    pub u_q: f64,
    /// True when the voltage vector was limited.
    pub saturated: bool,
}

/// PI current controller with decoupling (−ω_e L_q i_q on d, +ω_e L_d i_d on q) and back-EMF
/// feed-forward (+ω_e ψ_PM on q). The voltage vector is limited to `u_max` (circle), d first.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PiCurrentController {
    motor: MotorParams,
    /// d-axis PI.
    pub pi_d: Pi,
    /// q-axis PI.
    pub pi_q: Pi,
    /// Voltage vector limit, V.
    pub u_max: f64,
    /// Decoupling and back-EMF feed-forward on/off.
    pub decoupling: bool,
}

impl PiCurrentController {
    /// Builds the controller from a design, sample time and voltage limit.
    pub fn new(
        m: &MotorParams,
        d: &CurrentPiDesign,
        ts: f64,
        u_max: f64,
        decoupling: bool,
    ) -> Self {
        Self {
            motor: *m,
            pi_d: Pi::new(d.k_p_d, d.k_i_d, ts, u_max),
            pi_q: Pi::new(d.k_p_q, d.k_i_q, ts, u_max),
            u_max,
            decoupling,
        }
    }

    /// One control step.
    pub fn step(&mut self, x: &CurrentInput) -> VoltageDq {
        let m = &self.motor;
        let (ff_d, ff_q) = if self.decoupling {
            (
                -x.omega_e * m.l_q_h * x.i_q,
                x.omega_e * (m.l_d_h * x.i_d + m.psi_pm_wb),
            )
        } else {
            (0.0, 0.0)
        };
        // d axis gets priority for the voltage (flux control); q gets what is left.
        self.pi_d.y_min = -self.u_max;
        self.pi_d.y_max = self.u_max;
        let od = self.pi_d.step(x.i_d_ref - x.i_d, ff_d);
        let u_q_max = (self.u_max * self.u_max - od.y * od.y).max(0.0).sqrt();
        self.pi_q.y_min = -u_q_max;
        self.pi_q.y_max = u_q_max;
        let oq = self.pi_q.step(x.i_q_ref - x.i_q, ff_q);
        VoltageDq {
            u_d: od.y,
            u_q: oq.y,
            saturated: od.saturated || oq.saturated,
        }
    }

    /// Bumpless take-over: presets the integrators so that the next output equals `u`
    /// for zero error at the given operating point.
    pub fn preset(&mut self, u: VoltageDq, x: &CurrentInput) {
        let m = &self.motor;
        let ff_d = -x.omega_e * m.l_q_h * x.i_q;
        let ff_q = x.omega_e * (m.l_d_h * x.i_d + m.psi_pm_wb);
        let (ff_d, ff_q) = if self.decoupling {
            (ff_d, ff_q)
        } else {
            (0.0, 0.0)
        };
        self.pi_d.preset_output(u.u_d, ff_d);
        self.pi_q.preset_output(u.u_q, ff_q);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::motor::{Mechanics, MotorInput, MotorState, Rk4};

    /// Closed current loop on the model at a fixed speed (no computation delay): with
    /// decoupling the i_q step response is first order with time constant τ_c.
    #[test]
    fn closed_loop_is_first_order_with_tau_c() {
        let m = MotorParams::kyslan2015();
        let ts = 1e-5; // fine sampling so that the continuous design holds
        let tau = 5e-4;
        let d = CurrentPiDesign::new(&m, tau);
        let mut c = PiCurrentController::new(&m, &d, ts, 1e4, true);
        let w = 50.0;
        let mech = Mechanics::PrescribedSpeed(w);
        let mut x = MotorState {
            omega_m: w,
            ..Default::default()
        };
        let rk = Rk4 { substeps: 1 };
        let mut at_tau = None;
        for k in 0..((5.0 * tau / ts) as usize) {
            let inp = CurrentInput {
                i_d_ref: 0.0,
                i_q_ref: 1.0,
                i_d: x.i_d,
                i_q: x.i_q,
                omega_e: m.p() * w,
            };
            let u = c.step(&inp);
            x = rk.advance(
                &m,
                mech,
                &x,
                &MotorInput {
                    u_d: u.u_d,
                    u_q: u.u_q,
                    t_load: 0.0,
                    ..Default::default()
                },
                ts,
            );
            if k + 1 == (tau / ts) as usize {
                at_tau = Some(x.i_q);
            }
        }
        let v = at_tau.unwrap();
        // 1 − e^{−1} = 0.632 at t = τ_c (a few % off from the discrete forward-Euler integrator).
        assert!((v - 0.632).abs() < 0.02, "i_q(τ) = {v}");
        assert!((x.i_q - 1.0).abs() < 0.01, "final {}", x.i_q);
        assert!(x.i_d.abs() < 1e-3, "decoupled i_d = {}", x.i_d);
    }

    #[test]
    fn voltage_vector_is_limited_with_d_priority() {
        let m = MotorParams::kyslan2015();
        let d = CurrentPiDesign::new(&m, 5e-4);
        let mut c = PiCurrentController::new(&m, &d, 1e-4, 10.0, true);
        let u = c.step(&CurrentInput {
            i_d_ref: -100.0,
            i_q_ref: 100.0,
            ..Default::default()
        });
        assert!(u.saturated);
        assert!((u.u_d * u.u_d + u.u_q * u.u_q).sqrt() <= 10.0 + 1e-12);
        assert_eq!(u.u_d, -10.0);
    }
}
