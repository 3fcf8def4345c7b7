//! The elementary functions of the filter, with the same bits on every CPU.
//!
//! `f64::exp`, `f64::ln`, `f64::sin_cos` and their kin call the C library, and glibc picks
//! each function's implementation when the process starts, by the CPU it finds: on x86-64
//! a variant that uses FMA instructions where the CPU has them, another where it has not.
//! The two round differently for some arguments: over 200,000 random arguments, glibc's
//! `exp`, `log`, `sin`, `cos`, `atan2`, `pow`, `log1p` and more each gave different bits
//! with `GLIBC_TUNABLES=glibc.cpu.hwcaps=-AVX2,-FMA` than without (README, session 31).
//! One differing bit in a weight or a pose changes which particles a resample keeps, and
//! from there the whole run: the same seed and log gave different maps on two machines,
//! and a run recovered or taken over on another machine would not continue as it would
//! have on the first.
//!
//! These functions are the `libm` crate's (a Rust port of FreeBSD's msun), which compute
//! with plain IEEE-754 operations and give the same bits wherever they run. The crates that
//! compute the filter's results (this one, `fleetslam-data`, `fleetslam-localize`) call
//! these and never the standard library's: their `clippy.toml` disallows the `f64` methods,
//! and `tests/determinism.rs` runs a filter under the tunable above and compares its bits.
//! `sqrt`, `abs`, `mul_add`, `powi` and the arithmetic are exact or compiled inline, the
//! same everywhere, and stay the standard library's.

/// `eˣ`.
#[inline]
pub fn exp(x: f64) -> f64 {
    libm::exp(x)
}

/// The natural logarithm, `ln x`.
#[inline]
pub fn ln(x: f64) -> f64 {
    libm::log(x)
}

/// `ln(1 + x)`, accurate for small `x`.
#[inline]
pub fn ln_1p(x: f64) -> f64 {
    libm::log1p(x)
}

/// `sin x`.
#[inline]
pub fn sin(x: f64) -> f64 {
    libm::sin(x)
}

/// `cos x`.
#[inline]
pub fn cos(x: f64) -> f64 {
    libm::cos(x)
}

/// `(sin x, cos x)`, with the bits of [`sin`] and [`cos`].
#[inline]
pub fn sin_cos(x: f64) -> (f64, f64) {
    libm::sincos(x)
}

/// `tan x`.
#[inline]
pub fn tan(x: f64) -> f64 {
    libm::tan(x)
}

/// The angle of the point `(x, y)`, in `[-π, π]`.
#[inline]
pub fn atan2(y: f64, x: f64) -> f64 {
    libm::atan2(y, x)
}

/// `√(x² + y²)` without overflow or underflow on the way.
#[inline]
pub fn hypot(x: f64, y: f64) -> f64 {
    libm::hypot(x, y)
}

/// `xʸ`.
#[inline]
pub fn powf(x: f64, y: f64) -> f64 {
    libm::pow(x, y)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::{FRAC_PI_2, FRAC_PI_4, PI};

    /// Each function against values known exactly or to the last place.
    #[test]
    fn the_functions_are_the_ones_named() {
        let close = |a: f64, b: f64| (a - b).abs() <= 4.0 * f64::EPSILON * b.abs().max(1.0);
        assert_eq!(exp(0.0), 1.0);
        assert!(close(exp(1.0), std::f64::consts::E));
        assert!(close(exp(-745.0), 5e-324) && exp(710.0).is_infinite());
        assert_eq!(ln(1.0), 0.0);
        assert!(close(ln(std::f64::consts::E), 1.0));
        assert!(ln(0.0) == f64::NEG_INFINITY && ln(-1.0).is_nan());
        assert!(close(ln_1p(1e-18), 1e-18) && close(ln_1p(1.0), std::f64::consts::LN_2));
        assert!(close(sin(FRAC_PI_2), 1.0) && close(cos(PI), -1.0));
        assert!(close(tan(FRAC_PI_4), 1.0));
        assert!(close(atan2(1.0, -1.0), 3.0 * FRAC_PI_4) && close(atan2(-0.0, -1.0), -PI));
        assert_eq!(hypot(3.0, 4.0), 5.0);
        assert_eq!(hypot(3e300, 4e300), 5e300);
        assert!(close(powf(2.0, 0.5), std::f64::consts::SQRT_2));
    }

    /// `sin_cos` is `sin` and `cos`, bit for bit, over many turns.
    #[test]
    fn sin_cos_is_sin_and_cos() {
        for k in -20_000..20_000 {
            let x = k as f64 * 0.001_234_567;
            let (s, c) = sin_cos(x);
            assert_eq!(
                (s.to_bits(), c.to_bits()),
                (sin(x).to_bits(), cos(x).to_bits())
            );
        }
    }
}
