//! Clarke and Park transforms (amplitude-invariant).

/// Two-axis stationary-frame quantity.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct AlphaBeta {
    /// α component.
    pub alpha: f64,
    /// β component.
    pub beta: f64,
}

/// Rotor-frame quantity.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Dq {
    /// d component.
    pub d: f64,
    /// q component.
    pub q: f64,
}

/// Clarke: phase quantities (a, b, c) → αβ, amplitude-invariant (a + b + c = 0 not assumed).
pub fn clarke(a: f64, b: f64, c: f64) -> AlphaBeta {
    AlphaBeta {
        alpha: (2.0 * a - b - c) / 3.0,
        beta: (b - c) / 3f64.sqrt(),
    }
}

/// Inverse Clarke: αβ → (a, b, c).
pub fn inverse_clarke(x: AlphaBeta) -> (f64, f64, f64) {
    let s3 = 3f64.sqrt() / 2.0;
    (
        x.alpha,
        -0.5 * x.alpha + s3 * x.beta,
        -0.5 * x.alpha - s3 * x.beta,
    )
}

/// Park: αβ → dq at electrical angle θ_e.
pub fn park(x: AlphaBeta, theta_e: f64) -> Dq {
    let (s, c) = libm::sincos(theta_e);
    Dq {
        d: c * x.alpha + s * x.beta,
        q: -s * x.alpha + c * x.beta,
    }
}

/// Inverse Park: dq → αβ at electrical angle θ_e.
pub fn inverse_park(x: Dq, theta_e: f64) -> AlphaBeta {
    let (s, c) = libm::sincos(theta_e);
    AlphaBeta {
        alpha: c * x.d - s * x.q,
        beta: s * x.d + c * x.q,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn balanced_three_phase_maps_to_constant_dq() {
        // i_a = I cos(θ + φ) … a balanced set at angle θ gives d = I cos φ, q = I sin φ.
        let (amp, phi) = (2.0f64, 0.4f64);
        for th in [0.0, 0.7, 2.0, 4.5, -1.0] {
            let a = amp * libm::cos(th + phi);
            let b = amp * libm::cos(th + phi - 2.0 * std::f64::consts::PI / 3.0);
            let c = amp * libm::cos(th + phi + 2.0 * std::f64::consts::PI / 3.0);
            let dq = park(clarke(a, b, c), th);
            assert!((dq.d - amp * libm::cos(phi)).abs() < 1e-12);
            assert!((dq.q - amp * libm::sin(phi)).abs() < 1e-12);
        }
    }

    #[test]
    fn round_trips() {
        let x = AlphaBeta {
            alpha: 0.3,
            beta: -1.7,
        };
        let (a, b, c) = inverse_clarke(x);
        assert!((a + b + c).abs() < 1e-12);
        let y = clarke(a, b, c);
        assert!((y.alpha - x.alpha).abs() < 1e-12 && (y.beta - x.beta).abs() < 1e-12);
        let z = inverse_park(park(x, 1.234), 1.234);
        assert!((z.alpha - x.alpha).abs() < 1e-12 && (z.beta - x.beta).abs() < 1e-12);
    }

    #[test]
    fn park_preserves_magnitude() {
        let x = AlphaBeta {
            alpha: 3.0,
            beta: 4.0,
        };
        let d = park(x, 0.9);
        assert!(((d.d * d.d + d.q * d.q).sqrt() - 5.0).abs() < 1e-12);
    }
}
