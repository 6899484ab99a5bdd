//! Position and speed estimation from the encoder: electrical angle, backward-difference
//! speed and the 2nd-order Bessel low-pass of Low et al. 1998 eq. (10).

use crate::control::filter::Bessel2;
use crate::motor::wrap_2pi;
use std::f64::consts::{PI, TAU};

/// Estimate produced each sample.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct PosSpeed {
    /// Electrical angle θ̂_e, rad in [0, 2π).
    pub theta_e: f64,
    /// Mechanical speed ω̂_m, rad/s.
    pub omega_m: f64,
}

/// Encoder-based observer.
#[derive(Debug, Clone, Copy)]
pub struct EncoderObserver {
    pole_pairs: f64,
    ts: f64,
    filter: Bessel2,
    last_theta_m: Option<f64>,
}

impl EncoderObserver {
    /// `tau_f_s`: group delay of the Bessel speed filter.
    pub fn new(pole_pairs: u32, ts: f64, tau_f_s: f64) -> Self {
        Self {
            pole_pairs: f64::from(pole_pairs),
            ts,
            filter: Bessel2::design(tau_f_s, ts),
            last_theta_m: None,
        }
    }

    /// One step with the encoder's mechanical angle (rad, [0, 2π)).
    pub fn step(&mut self, theta_m: f64) -> PosSpeed {
        let raw = match self.last_theta_m {
            // Backward difference with the angle difference wrapped to [−π, π).
            Some(prev) => ((theta_m - prev + PI).rem_euclid(TAU) - PI) / self.ts,
            None => 0.0,
        };
        self.last_theta_m = Some(theta_m);
        PosSpeed {
            theta_e: wrap_2pi(self.pole_pairs * theta_m),
            omega_m: self.filter.step(raw),
        }
    }

    /// Bumpless start at a known angle and speed.
    pub fn preset(&mut self, theta_m: f64, omega_m: f64) {
        self.last_theta_m = Some(theta_m);
        self.filter.preset(omega_m);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn constant_speed_is_recovered_across_wraps() {
        let ts = 1e-4;
        let w = 300.0;
        let mut o = EncoderObserver::new(5, ts, 2e-4);
        let mut est = PosSpeed::default();
        for k in 0..2000 {
            let th = wrap_2pi(w * k as f64 * ts);
            est = o.step(th);
        }
        assert!((est.omega_m - w).abs() < 1e-6, "{}", est.omega_m);
        let th_m = wrap_2pi(w * 1999.0 * ts);
        assert!((est.theta_e - wrap_2pi(5.0 * th_m)).abs() < 1e-9);
    }

    #[test]
    fn negative_speed() {
        let ts = 1e-4;
        let mut o = EncoderObserver::new(4, ts, 2e-4);
        let mut est = PosSpeed::default();
        for k in 0..2000 {
            est = o.step(wrap_2pi(-150.0 * k as f64 * ts));
        }
        assert!((est.omega_m + 150.0).abs() < 1e-6);
    }
}
