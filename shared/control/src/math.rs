//! Complex-number functions on the pure-Rust `libm` crate.
//!
//! `num_complex`'s `exp`, `ln`, `norm` and `arg` call std's `f64` functions, that is the
//! platform's libm, whose last bits differ between architectures; these give the same bits
//! on every architecture. (Real functions are called as `libm::sin(x)` etc. directly.)

use nalgebra::Complex;

/// e^z = e^re · (cos im + i sin im).
pub fn cexp(z: Complex<f64>) -> Complex<f64> {
    let r = libm::exp(z.re);
    let (s, c) = libm::sincos(z.im);
    Complex::new(r * c, r * s)
}

/// |z| (without overflow: `hypot`).
pub fn cnorm(z: Complex<f64>) -> f64 {
    libm::hypot(z.re, z.im)
}

/// arg z in (−π, π].
pub fn carg(z: Complex<f64>) -> f64 {
    libm::atan2(z.im, z.re)
}

/// The principal logarithm ln|z| + i arg z.
pub fn cln(z: Complex<f64>) -> Complex<f64> {
    Complex::new(libm::log(cnorm(z)), carg(z))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn complex_functions_agree_with_their_definitions() {
        let z = Complex::new(-0.3, 2.5);
        let e = cexp(z);
        assert!((cnorm(e) - libm::exp(-0.3)).abs() < 1e-15);
        assert!((carg(e) - 2.5).abs() < 1e-15);
        let l = cln(e);
        assert!((l - z).re.abs() < 1e-15 && (l - z).im.abs() < 1e-15);
        assert_eq!(carg(Complex::new(-1.0, 0.0)), std::f64::consts::PI);
        assert_eq!(cnorm(Complex::new(3.0, 4.0)), 5.0);
    }
}
