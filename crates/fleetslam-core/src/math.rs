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
//! with plain IEEE-754 operations and give the same bits wherever they run; `exp`, the
//! filter's most frequent, is a table method of our own on the same operations. The
//! crates that compute the filter's results (this one, `fleetslam-data`,
//! `fleetslam-localize`, and `fleetslam-learned`, whose updater computes its measurement
//! frame in `f64`) call these and never the standard library's: their `clippy.toml`
//! disallows the `f64` methods, and `tests/determinism.rs` runs filters, with the EKF and
//! with the learned updater, under the tunable above and compares their bits. The learned
//! updater's network runs in `f32` with glibc's `tanhf`, which gave the same bits with and
//! without the tunable over 2,000,000 arguments in [-8, 8] (README, session 32).
//! `sqrt`, `abs`, `mul_add`, `powi` and the arithmetic are exact or compiled inline, the
//! same everywhere, and stay the standard library's.

/// Entries of [`exp`]'s table: `2^(j/N)` for `j < N`.
const EXP_TABLE_SIZE: usize = 128;

/// `2^(j/128)` for `j` in `0..128`, from `libm::exp2`.
static EXP_TABLE: std::sync::LazyLock<[f64; EXP_TABLE_SIZE]> = std::sync::LazyLock::new(|| {
    std::array::from_fn(|j| libm::exp2(j as f64 / EXP_TABLE_SIZE as f64))
});

/// Beyond this `|x|` [`exp`] is `libm::exp` (its result is near the overflow or the
/// subnormal range, where the scaling below would not hold).
const EXP_TABLE_RANGE: f64 = 700.0;

/// `eˣ`, within 1 ulp of `libm::exp`, by Tang's table method ("Table-driven
/// implementation of the exponential function in IEEE floating-point arithmetic", ACM TOMS
/// 15(2), 1989): `x = (k + j/N) ln 2 + r` with `|r| <= ln 2 / 2N`, `eˣ = 2ᵏ 2^(j/N) eʳ`,
/// `eʳ − 1` by its Taylor polynomial to `r⁵` (the next term, `r⁶/720`, is below 2⁻⁷⁷). No
/// division and no call: `libm::exp` divides once and calls its scaling, and took 2.2 times
/// as many of the filter's samples as glibc's `exp` (README, session 31).
#[inline]
pub fn exp(x: f64) -> f64 {
    if x.is_nan() || x.abs() > EXP_TABLE_RANGE {
        return libm::exp(x);
    }
    const N: f64 = EXP_TABLE_SIZE as f64;
    // Adding 1.5 · 2⁵² rounds x N / ln 2 to an integer held in the sum's low bits.
    const SHIFT: f64 = 6_755_399_441_055_744.0;
    // ln 2 / N in two parts (fdlibm's split of ln 2: the high part's low 21 bits are zero,
    // so `kd * LN2N_HI` is exact for |kd| < 2²¹).
    const LN2N_HI: f64 = 6.931_471_803_691_238e-1 / N;
    const LN2N_LO: f64 = 1.908_214_929_270_587_7e-10 / N;
    let shifted = x * (N / std::f64::consts::LN_2) + SHIFT;
    // The sum and SHIFT share their exponent: their bits differ by the integer k.
    let k = (shifted.to_bits() as i64).wrapping_sub(SHIFT.to_bits() as i64);
    let kd = shifted - SHIFT;
    let r = x - kd * LN2N_HI - kd * LN2N_LO;
    let r2 = r * r;
    let p = r + r2 * (0.5 + r * (1.0 / 6.0)) + r2 * r2 * (1.0 / 24.0 + r * (1.0 / 120.0));
    // k = N e + j: 2^(j/N) from the table, 2ᵉ by its bits (|e| <= 1,010 here).
    const BITS: u32 = EXP_TABLE_SIZE.trailing_zeros();
    let t = EXP_TABLE[(k & (EXP_TABLE_SIZE as i64 - 1)) as usize];
    let scale = f64::from_bits((((k >> BITS) + 1023) as u64) << 52);
    (t + t * p) * scale
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

    /// The table's `exp` is within 1 ulp of `libm::exp` over its range, and is `libm::exp`
    /// beyond it.
    #[test]
    fn exp_is_libms_within_an_ulp() {
        let mut worst = 0;
        for i in 0..2_000_000u64 {
            let x = -EXP_TABLE_RANGE
                + 2.0 * EXP_TABLE_RANGE * (i as f64 * 0.618_033_988_749_894_9).fract();
            for x in [x, x * 1e-3, x * 1e-6] {
                let d = (exp(x).to_bits() as i64 - libm::exp(x).to_bits() as i64).abs();
                worst = worst.max(d);
            }
        }
        assert!(worst <= 1, "{worst} ulps");
        for x in [
            0.0, -0.0, 1e-300, -1e-300, 700.0, -700.0, 700.1, -700.1, 709.7, 710.0, -745.0, -746.0,
        ] {
            assert_eq!(exp(x).to_bits(), libm::exp(x).to_bits(), "exp({x})");
        }
        assert!(exp(f64::NAN).is_nan() && exp(f64::INFINITY) == f64::INFINITY);
        assert_eq!(exp(f64::NEG_INFINITY), 0.0);
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
