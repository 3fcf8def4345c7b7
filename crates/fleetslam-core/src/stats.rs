//! Small statistical helpers: the chi-square distribution's CDF and quantile, used for the
//! association gates (a squared Mahalanobis distance of a `d`-dimensional Gaussian innovation
//! is χ² with `d` degrees of freedom), and `ln(eˣ + eʸ)` without overflow.

use crate::math;

/// ln(2π), of every Gaussian log-density in the workspace (the EKF's and the learned
/// updater's likelihoods, the filter's proposal and association, the localizer's weights).
pub const LN_2PI: f64 = 1.837_877_066_409_345_3;

/// `ln N(ν; 0, S)` of a `dim`-dimensional Gaussian innovation from its squared Mahalanobis
/// distance `m2 = νᵀ S⁻¹ ν` and `logdet = ln |S|`: `−½ m2 − ½ (dim ln 2π + ln |S|)`. The one
/// formula of the EKF's and the learned updater's likelihoods, the filter's association,
/// proposal and sightings, and the localizer's weights.
#[inline(always)]
pub fn gaussian_log_density(m2: f64, logdet: f64, dim: usize) -> f64 {
    -0.5 * m2 - 0.5 * (dim as f64 * LN_2PI + logdet)
}

/// `ln Γ(a)` for `a = k / 2`, `k >= 1` (exact recursion from Γ(1) = 1 and Γ(½) = √π).
fn ln_gamma_half(k: u32) -> f64 {
    let mut a = if k.is_multiple_of(2) { 1.0 } else { 0.5 };
    let mut lg = if k.is_multiple_of(2) {
        0.0
    } else {
        0.5 * math::ln(std::f64::consts::PI)
    };
    while a < 0.5 * k as f64 - 1e-9 {
        lg += math::ln(a);
        a += 1.0;
    }
    lg
}

/// CDF of the chi-square distribution with `dof` degrees of freedom at `x`: the regularised
/// lower incomplete gamma function P(dof/2, x/2), by its power series (Numerical Recipes
/// 6.2.5), which converges for every x; accurate to about 1e-14 for the values the gates use.
pub fn chi2_cdf(x: f64, dof: u32) -> f64 {
    if x <= 0.0 || dof == 0 {
        return 0.0;
    }
    let a = 0.5 * dof as f64;
    let x = 0.5 * x;
    let mut term = 1.0 / a;
    let mut sum = term;
    let mut n = 1.0;
    while term > sum * 1e-16 {
        term *= x / (a + n);
        sum += term;
        n += 1.0;
        if n > 10_000.0 {
            break;
        }
    }
    let ln_p = a * math::ln(x) - x - ln_gamma_half(dof) + math::ln(sum);
    math::exp(ln_p).min(1.0)
}

/// The chi-square quantile: the x with `chi2_cdf(x, dof) = p`, by bisection (to 1e-12
/// relative). `p` must lie in (0, 1).
pub fn chi2_quantile(p: f64, dof: u32) -> f64 {
    debug_assert!(p > 0.0 && p < 1.0 && dof > 0);
    let (mut lo, mut hi) = (0.0, 1.0);
    while chi2_cdf(hi, dof) < p {
        hi *= 2.0;
    }
    while hi - lo > 1e-12 * hi {
        let mid = 0.5 * (lo + hi);
        if chi2_cdf(mid, dof) < p {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    0.5 * (lo + hi)
}

/// `ln(eᵃ + eᵇ)`, exact for infinite arguments.
#[inline]
pub fn log_add_exp(a: f64, b: f64) -> f64 {
    let (hi, lo) = if a >= b { (a, b) } else { (b, a) };
    if hi == f64::NEG_INFINITY {
        return hi;
    }
    hi + math::ln_1p(math::exp(lo - hi))
}

/// `e^ℓ / e^other` for the Gaussian log-density `ℓ` of `(m2, det, dim)`, without the
/// logarithm of `det`: `e^a / √det` with `a = −m2/2 − dim·ln(2π)/2 − other`.
#[inline]
fn density_ratio(m2: f64, det: f64, dim: usize, other: f64) -> f64 {
    math::exp(-0.5 * m2 - 0.5 * dim as f64 * LN_2PI - other) / det.sqrt()
}

/// A sum of terms `log_add_exp(ℓ, other)`, each for a Gaussian log-density `ℓ =
/// gaussian_log_density(m2, math::ln(det), dim)` (a non-finite `ℓ` taken as `−∞`) against another
/// log-density `other`, with one logarithm for the whole sum and none of `det`: a term is
/// `other + ln(1 + x)` with `x = e^a / √det`, `a = −m2/2 − dim·ln(2π)/2 − other`; it adds
/// `other` to a sum and multiplies `1 + x` into a product, whose logarithm
/// [`MixtureLogSum::value`] adds once. Where `x` is not finite (`ℓ` beyond `other` by more
/// than the `f64` range, or a NaN) the term is computed in the two steps. FastSLAM 2.0's
/// proposal weighs every matched observation of a record with such a term (the mixture of
/// its marginal and the clutter density): one `ln` a particle and record instead of one a
/// particle and observation. The product stays finite: a factor or a product above
/// [`MixtureLogSum::FLUSH`] is moved into the sum at once (`FLUSH²` is below `f64::MAX`).
/// Its value differs from the sum of the terms by rounding (one rounding a factor; `1 + x`
/// rounds an `x` below half an ulp of 1 away, an absolute error of at most 1.1e-16 a term).
#[derive(Debug, Clone, Copy)]
pub struct MixtureLogSum {
    sum: f64,
    product: f64,
}

impl Default for MixtureLogSum {
    fn default() -> Self {
        Self {
            sum: 0.0,
            product: 1.0,
        }
    }
}

impl MixtureLogSum {
    /// The largest product (and factor) kept out of the sum: 2⁵⁰⁰.
    pub const FLUSH: f64 = 3.273_390_607_896_142e150;

    /// Adds the term of `(m2, det, dim, other)`.
    #[inline]
    pub fn add_gaussian(&mut self, m2: f64, det: f64, dim: usize, other: f64) {
        let x = density_ratio(m2, det, dim, other);
        if !x.is_finite() {
            self.sum += gaussian_log_add_exp_in_two_steps(m2, det, dim, other);
            return;
        }
        self.sum += other;
        let f = 1.0 + x;
        if f > Self::FLUSH {
            self.sum += math::ln(f);
            return;
        }
        self.product *= f;
        if self.product > Self::FLUSH {
            self.sum += math::ln(self.product);
            self.product = 1.0;
        }
    }

    /// The sum of the terms added.
    #[inline]
    pub fn value(&self) -> f64 {
        self.sum + math::ln(self.product)
    }
}

/// A [`MixtureLogSum`] term as the two steps: the Gaussian's log-density
/// (`−∞` when not finite), then `log_add_exp`.
fn gaussian_log_add_exp_in_two_steps(m2: f64, det: f64, dim: usize, other: f64) -> f64 {
    let ll = gaussian_log_density(m2, math::ln(det), dim);
    log_add_exp(
        if ll.is_finite() {
            ll
        } else {
            f64::NEG_INFINITY
        },
        other,
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Terms from perfect to hopeless matches (and a NaN distance), clutter densities far
    /// above and below, and determinants across the sensors' range.
    fn mixture_terms() -> Vec<(f64, f64, usize, f64)> {
        let mut terms = Vec::new();
        for dim in [2, 3] {
            for m2 in [0.0, 1e-6, 0.3, 2.0, 9.21, 30.0, 200.0, 1e3, 1e5, f64::NAN] {
                for det in [1e-30, 1e-12, 1e-6, 1e-3, 0.5, 1.0, 40.0, 1e6] {
                    for other in [-1e3, -60.0, -8.0, -2.0, 0.0, 5.0, 40.0] {
                        terms.push((m2, det, dim, other));
                    }
                }
            }
        }
        terms
    }

    /// One term.
    fn one_term(m2: f64, det: f64, dim: usize, other: f64) -> f64 {
        let mut sum = MixtureLogSum::default();
        sum.add_gaussian(m2, det, dim, other);
        sum.value()
    }

    /// A term without the logarithm of `det` equals the two steps (the Gaussian's
    /// log-density, then `log_add_exp`) to rounding (within 1e-14 of the larger of its size
    /// and 1); non-finite inputs take the two steps' value.
    #[test]
    fn the_folded_mixture_is_the_two_steps() {
        let two_steps = gaussian_log_add_exp_in_two_steps;
        let mut worst = 0.0f64;
        for (m2, det, dim, other) in mixture_terms() {
            let (f, r) = (
                one_term(m2, det, dim, other),
                two_steps(m2, det, dim, other),
            );
            let err = (f - r).abs() / r.abs().max(1.0);
            assert!(
                err < 1e-14,
                "m2 {m2} det {det} dim {dim} other {other}: {f} vs {r}"
            );
            worst = worst.max(err);
        }
        assert!(worst > 0.0, "the fold is a different computation");
        // Beyond exp's range the two steps are taken: ℓ above `other` by about 1,000.
        let (m2, det, other) = (0.0, 1e-30, -1e3);
        assert!((-0.5 * m2 - LN_2PI - other) > 709.0);
        assert_eq!(one_term(m2, det, 2, other), two_steps(m2, det, 2, other));
        // A NaN or infinite distance weighs as the other term alone, as before.
        assert_eq!(one_term(f64::NAN, 1.0, 2, -3.0), -3.0);
        assert_eq!(one_term(f64::INFINITY, 1.0, 2, -3.0), -3.0);
    }

    /// The one-logarithm sum equals the sum of the two steps' terms to rounding (within 1e-14
    /// of the larger of its size and 1), over sequences of [`mixture_terms`] that keep
    /// the product below the flush, cross it, and hold single factors above it.
    #[test]
    fn the_mixture_sum_is_the_sum_of_the_terms() {
        let two_steps = gaussian_log_add_exp_in_two_steps;
        let terms = mixture_terms();
        let (mut flushed, mut worst) = (0, 0.0f64);
        for len in [1, 2, 7, 38, 200] {
            for chunk in terms.chunks(len) {
                let mut sum = MixtureLogSum::default();
                let mut reference = 0.0;
                for &(m2, det, dim, other) in chunk {
                    let before = sum.product;
                    sum.add_gaussian(m2, det, dim, other);
                    reference += two_steps(m2, det, dim, other);
                    // Every factor is at least 1: only a flush lowers the product.
                    if sum.product < before {
                        flushed += 1;
                    }
                }
                let err = (sum.value() - reference).abs() / reference.abs().max(1.0);
                assert!(err < 1e-14, "{chunk:?}: {} vs {reference}", sum.value());
                worst = worst.max(err);
            }
        }
        assert!(flushed > 0, "no sequence crossed the flush");
        assert!(worst > 0.0, "the product is a different computation");
        // A single factor above the flush goes to the sum at once.
        let (m2, det, other) = (1e3, 1.0, -1e3);
        assert!(density_ratio(m2, det, 2, other) > MixtureLogSum::FLUSH);
        let mut one = MixtureLogSum::default();
        one.add_gaussian(m2, det, 2, other);
        assert_eq!(one.product, 1.0);
        let r = two_steps(m2, det, 2, other);
        assert!(
            (one.value() - r).abs() < 1e-14 * r.abs(),
            "{} vs {r}",
            one.value()
        );
    }

    #[test]
    fn chi2_matches_tables() {
        // Closed form for 2 dof: CDF = 1 − e^(−x/2).
        for x in [0.1, 1.0, 5.0, 9.21, 20.0] {
            assert!((chi2_cdf(x, 2) - (1.0 - math::exp(-x / 2.0f64))).abs() < 1e-13);
        }
        // Published quantiles (99% and 99.9%).
        assert!((chi2_quantile(0.99, 2) - 9.2103).abs() < 1e-4);
        assert!((chi2_quantile(0.99, 3) - 11.3449).abs() < 1e-4);
        assert!((chi2_quantile(0.999, 2) - 13.8155).abs() < 1e-4);
        assert!((chi2_quantile(0.999, 3) - 16.2662).abs() < 1e-4);
        assert!((chi2_quantile(0.95, 1) - 3.8415).abs() < 1e-4);
    }

    #[test]
    fn gaussian_log_density_is_the_log_of_the_density() {
        // 1D: N(x; 0, σ²) = exp(−x²/2σ²) / √(2πσ²).
        let (x, var) = (0.7f64, 0.09f64);
        let pdf = math::exp(-x * x / (2.0 * var)) / (2.0 * std::f64::consts::PI * var).sqrt();
        assert!(
            (gaussian_log_density(x * x / var, math::ln(var), 1) - math::ln(pdf)).abs() < 1e-13
        );
        // Independent components: the 2D and 3D densities are sums of 1D ones.
        let one = |x: f64, var: f64| gaussian_log_density(x * x / var, math::ln(var), 1);
        let (y, vy, z, vz) = (-0.2f64, 0.01f64, 1.5f64, 4.0f64);
        let m2 = x * x / var + y * y / vy;
        let two = gaussian_log_density(m2, math::ln(var * vy), 2);
        assert!((two - (one(x, var) + one(y, vy))).abs() < 1e-12);
        let three = gaussian_log_density(m2 + z * z / vz, math::ln(var * vy * vz), 3);
        assert!((three - (two + one(z, vz))).abs() < 1e-12);
        // It falls as the Mahalanobis distance grows.
        assert!(gaussian_log_density(2.0, 0.0, 2) < gaussian_log_density(1.0, 0.0, 2));
    }

    #[test]
    fn log_add_exp_is_exact() {
        assert!((log_add_exp(0.0, 0.0) - math::ln(2f64)).abs() < 1e-15);
        assert_eq!(log_add_exp(f64::NEG_INFINITY, -3.0), -3.0);
        assert_eq!(
            log_add_exp(f64::NEG_INFINITY, f64::NEG_INFINITY),
            f64::NEG_INFINITY
        );
        assert!(
            (log_add_exp(-1000.0, -1001.0) - (-1000.0 + math::ln(1.0 + math::exp(-1.0f64)))).abs()
                < 1e-12
        );
    }
}
