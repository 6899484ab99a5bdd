//! Complex-number functions on the pure-Rust `libm` crate.
//!
//! `num_complex`'s `exp`, `ln`, `norm` and `arg` call std's `f64` functions, that is the
//! platform's libm, whose last bits differ between architectures; these give the same bits
//! on every architecture. (Real functions are called as `libm::sin(x)` etc. directly.)

use nalgebra::Complex;

/// The eigenvalues of square matrix `m`, as nalgebra's `complex_eigenvalues` gives them;
/// every one NaN when an entry of `m` is not a finite number or the QR iteration has not
/// converged within 1 000 sweeps a row. (`complex_eigenvalues` iterates without a limit:
/// for ever on such a matrix, which a motor's out-of-scale values can make.)
pub fn eigenvalues(m: nalgebra::DMatrix<f64>) -> Vec<Complex<f64>> {
    let n = m.nrows();
    let nan = vec![Complex::new(f64::NAN, f64::NAN); n];
    if !m.iter().all(|x| x.is_finite()) {
        return nan;
    }
    // Schur with its Q computed does the same arithmetic on T as `complex_eigenvalues`.
    nalgebra::linalg::Schur::try_new(m, f64::EPSILON, 1000 * n.max(1))
        .map_or(nan, |s| s.complex_eigenvalues().iter().copied().collect())
}

/// The largest |z| of `z`: NaN when one is NaN (`f64::max` would pass over it).
pub fn spectral_radius(z: impl IntoIterator<Item = Complex<f64>>) -> f64 {
    z.into_iter().map(cnorm).fold(0.0, |r, x| {
        if r.is_nan() || x.is_nan() {
            f64::NAN
        } else {
            r.max(x)
        }
    })
}

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

    /// On a finite matrix the same bits as nalgebra's own eigenvalues; on one with NaN or ∞
    /// (where nalgebra's loops for ever) NaN at once, and a spectral radius of NaN.
    #[test]
    fn eigenvalues_match_nalgebras_and_end_on_a_matrix_that_is_not_finite() {
        let m = nalgebra::DMatrix::from_row_slice(
            3,
            3,
            &[0.9, -0.2, 0.05, 0.3, 0.7, -0.1, 0.0, 0.25, 0.95],
        );
        let theirs: Vec<Complex<f64>> = m.complex_eigenvalues().iter().copied().collect();
        assert_eq!(eigenvalues(m.clone()), theirs);
        assert!(spectral_radius(theirs.iter().copied()) < 1.0);
        for bad in [f64::NAN, f64::INFINITY] {
            let mut b = m.clone();
            b[(1, 2)] = bad;
            let z = eigenvalues(b);
            assert_eq!(z.len(), 3);
            assert!(z.iter().all(|z| z.re.is_nan() && z.im.is_nan()), "{z:?}");
            assert!(spectral_radius(z).is_nan());
        }
        // One NaN among finite poles is not passed over.
        let z = [Complex::new(0.5, 0.0), Complex::new(f64::NAN, 0.0)];
        assert!(spectral_radius(z).is_nan());
    }
}
