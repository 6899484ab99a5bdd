//! Linear filters: the 2nd-order Bessel low-pass of Low et al. 1998 eq. (10).

use nalgebra::{Matrix3, Vector2};

/// Discrete 2nd-order low-pass `(b1 z + b0)/(z² + a1 z + a0)`, Low et al. eq. (10), obtained by
/// zero-order-hold discretisation of the continuous Bessel prototype
/// `H(s) = 3 / ((τ s)² + 3 τ s + 3)` whose low-frequency group delay is τ.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Bessel2 {
    /// Numerator coefficient of z.
    pub b1: f64,
    /// Numerator constant.
    pub b0: f64,
    /// Denominator coefficient of z.
    pub a1: f64,
    /// Denominator constant.
    pub a0: f64,
    /// y(k-1), y(k-2), u(k-1), u(k-2).
    y1: f64,
    y2: f64,
    u1: f64,
    u2: f64,
}

impl Bessel2 {
    /// Designs the filter for group delay `tau_s` (s) at sample time `ts` (s).
    pub fn design(tau_s: f64, ts: f64) -> Self {
        let w2 = 3.0 / (tau_s * tau_s);
        // Companion form: x' = A x + B u, y = x1.
        let a = [[0.0, 1.0], [-w2, -3.0 / tau_s]];
        let b = [0.0, w2];
        // ZOH via the augmented matrix exponential exp([[A B];[0 0]]·T).
        let m = Matrix3::new(
            a[0][0], a[0][1], b[0], //
            a[1][0], a[1][1], b[1], //
            0.0, 0.0, 0.0,
        ) * ts;
        let e = m.exp();
        let phi = nalgebra::Matrix2::new(e[(0, 0)], e[(0, 1)], e[(1, 0)], e[(1, 1)]);
        let gam = Vector2::new(e[(0, 2)], e[(1, 2)]);
        // Transfer function C (zI − Φ)^{-1} Γ with C = [1 0]:
        // denominator z² − tr(Φ) z + det(Φ); numerator Γ1 z + (Φ12 Γ2 − Φ22 Γ1).
        let a1 = -(phi[(0, 0)] + phi[(1, 1)]);
        let a0 = phi.determinant();
        let b1 = gam[0];
        let b0 = phi[(0, 1)] * gam[1] - phi[(1, 1)] * gam[0];
        Self {
            b1,
            b0,
            a1,
            a0,
            y1: 0.0,
            y2: 0.0,
            u1: 0.0,
            u2: 0.0,
        }
    }

    /// One step with input u(k); returns y(k) = −a1 y(k−1) − a0 y(k−2) + b1 u(k−1) + b0 u(k−2).
    pub fn step(&mut self, u: f64) -> f64 {
        let y = -self.a1 * self.y1 - self.a0 * self.y2 + self.b1 * self.u1 + self.b0 * self.u2;
        self.y2 = self.y1;
        self.y1 = y;
        self.u2 = self.u1;
        self.u1 = u;
        y
    }

    /// Sets the filter to steady state at `value` (bumpless start).
    pub fn preset(&mut self, value: f64) {
        let g = (self.b1 + self.b0) / (1.0 + self.a1 + self.a0);
        self.y1 = value;
        self.y2 = value;
        self.u1 = value / g;
        self.u2 = value / g;
    }

    /// The state y(k−1), y(k−2), u(k−1), u(k−2) (to linearise a loop that holds the filter).
    pub fn state(&self) -> [f64; 4] {
        [self.y1, self.y2, self.u1, self.u2]
    }

    /// Sets the state y(k−1), y(k−2), u(k−1), u(k−2), as [`Self::state`] gives it.
    pub fn set_state(&mut self, x: [f64; 4]) {
        [self.y1, self.y2, self.u1, self.u2] = x;
    }

    /// DC gain (1 for a correct design).
    pub fn dc_gain(&self) -> f64 {
        (self.b1 + self.b0) / (1.0 + self.a1 + self.a0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn unity_dc_gain_and_stable_poles() {
        let f = Bessel2::design(2e-4, 1e-4);
        assert!((f.dc_gain() - 1.0).abs() < 1e-12);
        // Poles of z² + a1 z + a0 inside the unit circle: |a0| < 1 and |a1| < 1 + a0.
        assert!(f.a0.abs() < 1.0 && f.a1.abs() < 1.0 + f.a0);
    }

    #[test]
    fn poles_are_the_mapped_bessel_poles() {
        // Continuous poles (−3 ± j√3)/(2τ) map to z = e^{sT}.
        let (tau, ts) = (3e-4, 1e-4);
        let f = Bessel2::design(tau, ts);
        let re = libm::exp(-1.5 / tau * ts);
        let ang = 3f64.sqrt() / 2.0 / tau * ts;
        let a1 = -2.0 * re * libm::cos(ang);
        let a0 = re * re;
        assert!((f.a1 - a1).abs() < 1e-12 && (f.a0 - a0).abs() < 1e-12);
    }

    #[test]
    fn ramp_lags_by_tau_plus_half_a_sample() {
        // A Bessel filter delays a ramp by its group delay τ; the zero-order hold of the
        // sampled input adds T/2: y(k) tracks u(k) − (τ + T/2)·slope.
        let (tau, ts) = (2e-4, 1e-4);
        let mut f = Bessel2::design(tau, ts);
        let mut y = 0.0;
        let mut u = 0.0;
        for k in 0..2000 {
            u = k as f64 * ts; // unit-slope ramp
            y = f.step(u);
        }
        let lag = u - y;
        assert!((lag - (tau + 0.5 * ts)).abs() < 1e-6, "lag {lag}");
    }
}
