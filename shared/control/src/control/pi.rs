//! Discrete PI controller with output limits and anti-windup by conditional integration.

/// Parallel-form discrete PI: y = K_p·e + x_I, x_I ← x_I + K_i·T_s·e (forward Euler),
/// with the output clamped to `[y_min, y_max]`. While the output is saturated and the error
/// would drive it further into the limit, the integrator is frozen (anti-windup).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pi {
    /// Proportional gain K_p.
    pub k_p: f64,
    /// Integral gain K_i (1/s × K_p/T_i).
    pub k_i: f64,
    /// Sample time T_s, s.
    pub ts: f64,
    /// Lower output limit.
    pub y_min: f64,
    /// Upper output limit.
    pub y_max: f64,
    /// Integrator state.
    pub x_i: f64,
}

/// Result of one PI step.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PiOut {
    /// Limited output.
    pub y: f64,
    /// True when the unlimited output was outside the limits.
    pub saturated: bool,
}

impl Pi {
    /// A PI with symmetric limits ±`limit` and a zero integrator.
    pub fn new(k_p: f64, k_i: f64, ts: f64, limit: f64) -> Self {
        Self {
            k_p,
            k_i,
            ts,
            y_min: -limit,
            y_max: limit,
            x_i: 0.0,
        }
    }

    /// One step. `feedforward` is added before limiting.
    pub fn step(&mut self, e: f64, feedforward: f64) -> PiOut {
        let v = self.k_p * e + self.x_i + feedforward;
        let y = v.clamp(self.y_min, self.y_max);
        let saturated = y != v;
        // Conditional integration: integrate unless saturated in the direction of e.
        let winding = (v > self.y_max && e > 0.0) || (v < self.y_min && e < 0.0);
        if !winding {
            self.x_i += self.k_i * self.ts * e;
        }
        PiOut { y, saturated }
    }

    /// Freezes nothing, resets the integrator so that the next output with zero error is `y0`
    /// (bumpless take-over).
    pub fn preset_output(&mut self, y0: f64, feedforward: f64) {
        self.x_i = (y0 - feedforward).clamp(self.y_min, self.y_max);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn integrates_constant_error() {
        let mut pi = Pi::new(2.0, 10.0, 0.01, 100.0);
        let a = pi.step(1.0, 0.0);
        assert_eq!(a.y, 2.0);
        let b = pi.step(1.0, 0.0);
        assert!((b.y - (2.0 + 0.1)).abs() < 1e-12);
    }

    #[test]
    fn anti_windup_freezes_integrator_while_saturated() {
        let mut pi = Pi::new(1.0, 100.0, 0.01, 1.0);
        for _ in 0..1000 {
            let o = pi.step(5.0, 0.0);
            assert!(o.y <= 1.0);
        }
        // The integrator did not wind up: it stopped once the output saturated.
        assert!(pi.x_i <= 1.0, "x_i = {}", pi.x_i);
        // Reversing the error leaves saturation immediately.
        let o = pi.step(-5.0, 0.0);
        assert!(o.y < 0.0, "y = {}", o.y);
    }

    #[test]
    fn preset_output_is_bumpless() {
        let mut pi = Pi::new(3.0, 50.0, 1e-3, 10.0);
        pi.preset_output(4.0, 1.0);
        assert_eq!(pi.step(0.0, 1.0).y, 4.0);
    }
}
