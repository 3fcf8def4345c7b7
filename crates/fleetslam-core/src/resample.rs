//! Log-space weights and low-variance (systematic) resampling.

use crate::math;
use rand::Rng;
use rayon::prelude::*;

/// Fewest weights a thread takes in [`normalize_log_weights_keeping`]'s parallel passes:
/// below it the passes stay on one thread (each weight is one `exp`, some 20 ns, against a
/// few microseconds to hand work to another thread). No effect on results.
const PARALLEL_WEIGHTS_MIN: usize = 256;

/// Normalises log-weights in place so that `Σ exp(w) = 1` and returns the effective sample
/// size `1 / Σ w²`. Non-finite weights count as impossible and become `f64::MIN` (finite, so
/// that they serialise); if every weight is impossible the weights are reset to uniform (and
/// the ESS is N). The filter never produces NaN.
pub fn normalize_log_weights(log_w: &mut [f64]) -> f64 {
    normalize_log_weights_keeping(log_w, &mut Vec::new())
}

/// [`normalize_log_weights`], also writing each normalised weight `exp(w)` (bit for bit what
/// `math::exp(w)` gives afterwards) into `weights`, which is cleared first: the normalisation
/// computes them for the ESS anyway. Its two passes of `exp` run in parallel (rayon) and
/// their sums in order, so the results are the same bits on any number of threads (the
/// tests compare them with the sequential computation): a filter of 1,000 particles
/// normalises after every record that observes something, and the `exp`s were its longest
/// serial part.
pub fn normalize_log_weights_keeping(log_w: &mut [f64], weights: &mut Vec<f64>) -> f64 {
    weights.clear();
    let n = log_w.len();
    if n == 0 {
        return 0.0;
    }
    let max = log_w
        .iter()
        .copied()
        .filter(|w| w.is_finite())
        .fold(f64::NEG_INFINITY, f64::max);
    if !max.is_finite() {
        let u = -math::ln(n as f64);
        log_w.fill(u);
        weights.resize(n, math::exp(u));
        return n as f64;
    }
    weights.resize(n, 0.0);
    weights
        .par_iter_mut()
        .zip(log_w.par_iter())
        .with_min_len(PARALLEL_WEIGHTS_MIN)
        .for_each(|(e, &w)| {
            *e = if w.is_finite() {
                math::exp(w - max)
            } else {
                0.0
            }
        });
    let sum: f64 = weights.iter().sum();
    let lse = max + math::ln(sum);
    weights
        .par_iter_mut()
        .zip(log_w.par_iter_mut())
        .with_min_len(PARALLEL_WEIGHTS_MIN)
        .for_each(|(p, w)| {
            *w = if w.is_finite() {
                (*w - lse).max(f64::MIN)
            } else {
                f64::MIN
            };
            *p = math::exp(*w);
        });
    let mut sq = 0.0;
    for p in weights.iter() {
        sq += p * p;
    }
    1.0 / sq
}

/// Systematic resampling: one uniform draw, N evenly spaced pointers into the cumulative
/// weights (Thrun, Burgard, Fox, Probabilistic Robotics, table 4.4). `log_w` must be
/// normalised. Returns the index of the parent of each new particle, in order.
pub fn systematic(log_w: &[f64], rng: &mut impl Rng) -> Vec<usize> {
    let weights: Vec<f64> = log_w.iter().map(|&w| math::exp(w)).collect();
    systematic_weights(&weights, rng)
}

/// [`systematic`] given the normalised weights themselves (`exp` of the log-weights, as
/// [`normalize_log_weights_keeping`] keeps them): the same draw and the same parents.
pub fn systematic_weights(weights: &[f64], rng: &mut impl Rng) -> Vec<usize> {
    let n = weights.len();
    let mut out = Vec::with_capacity(n);
    if n == 0 {
        return out;
    }
    let step = 1.0 / n as f64;
    let mut u = rng.random::<f64>() * step;
    let mut c = weights[0];
    let mut i = 0;
    for _ in 0..n {
        while u > c && i + 1 < n {
            i += 1;
            c += weights[i];
        }
        out.push(i);
        u += step;
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// The normalisation computed on one thread, in order: the reference the parallel one
    /// must match bit for bit. Returns the ESS and the normalised weights.
    fn sequential(log_w: &mut [f64]) -> (f64, Vec<f64>) {
        let n = log_w.len();
        if n == 0 {
            return (0.0, Vec::new());
        }
        let max = log_w
            .iter()
            .copied()
            .filter(|w| w.is_finite())
            .fold(f64::NEG_INFINITY, f64::max);
        if !max.is_finite() {
            let u = -math::ln(n as f64);
            log_w.fill(u);
            return (n as f64, vec![math::exp(u); n]);
        }
        let sum: f64 = log_w
            .iter()
            .map(|&w| {
                if w.is_finite() {
                    math::exp(w - max)
                } else {
                    0.0
                }
            })
            .sum();
        let lse = max + math::ln(sum);
        let (mut sq, mut weights) = (0.0, Vec::with_capacity(n));
        for w in log_w.iter_mut() {
            *w = if w.is_finite() {
                (*w - lse).max(f64::MIN)
            } else {
                f64::MIN
            };
            let p = math::exp(*w);
            weights.push(p);
            sq += p * p;
        }
        (1.0 / sq, weights)
    }

    #[test]
    fn extreme_weights_never_nan() {
        let mut w = vec![-1e308, f64::NEG_INFINITY, f64::NAN, -1e300];
        let ess = normalize_log_weights(&mut w);
        assert!(ess.is_finite() && ess >= 1.0);
        assert!(w.iter().all(|w| w.is_finite()));
        let mut all_bad = vec![f64::NAN, f64::NEG_INFINITY];
        assert_eq!(normalize_log_weights(&mut all_bad), 2.0);
        assert!(all_bad.iter().all(|w| w.is_finite()));
    }

    #[test]
    fn systematic_keeps_proportions() {
        let mut w: Vec<f64> = [0.5f64, 0.25, 0.25, 0.0]
            .iter()
            .map(|&p| math::ln(p))
            .collect();
        normalize_log_weights(&mut w);
        let idx = systematic(&w, &mut crate::rng::stream(0, 0, 0));
        let count = |k| idx.iter().filter(|&&i| i == k).count();
        assert_eq!((count(0), count(1), count(2), count(3)), (2, 1, 1, 0));
    }

    proptest! {
        #[test]
        fn normalised_weights_sum_to_one(ws in proptest::collection::vec(-1e3f64..1e3, 1..200)) {
            let mut w = ws.clone();
            let ess = normalize_log_weights(&mut w);
            let s: f64 = w.iter().map(|&w| math::exp(w)).sum();
            prop_assert!((s - 1.0).abs() < 1e-9);
            prop_assert!(ess >= 1.0 - 1e-9 && ess <= w.len() as f64 + 1e-9);
            let idx = systematic(&w, &mut crate::rng::stream(1, 2, 3));
            prop_assert_eq!(idx.len(), w.len());
            prop_assert!(idx.windows(2).all(|p| p[0] <= p[1]));
        }

        /// The kept weights are `exp` of the normalised log-weights, bit for bit, and the
        /// log-weights, ESS and weights are those of the sequential computation (up to
        /// 2,000 weights: the parallel passes split); impossible weights too.
        #[test]
        fn kept_weights_are_the_exp_of_the_normalised_ones(
            ws in prop_oneof![
                proptest::collection::vec(prop_oneof![
                    8 => -1e3f64..1e3,
                    1 => Just(f64::NEG_INFINITY),
                    1 => Just(f64::NAN),
                ], 1..2000),
                // Weights of one scale: many terms of the sums count, so their order shows.
                proptest::collection::vec(prop_oneof![
                    8 => -5f64..0.0,
                    1 => Just(f64::NEG_INFINITY),
                ], 1..2000),
            ],
        ) {
            let (mut a, mut b) = (ws.clone(), ws.clone());
            let mut kept = vec![7.0; 3];
            let ess = normalize_log_weights_keeping(&mut a, &mut kept);
            let (want_ess, want_kept) = sequential(&mut b);
            prop_assert_eq!(ess.to_bits(), want_ess.to_bits());
            prop_assert_eq!(kept.len(), a.len());
            for (((w, k), v), p) in a.iter().zip(&kept).zip(&b).zip(&want_kept) {
                prop_assert_eq!(w.to_bits(), v.to_bits());
                prop_assert_eq!(k.to_bits(), math::exp(*w).to_bits());
                prop_assert_eq!(k.to_bits(), p.to_bits());
            }
            let mut c = ws.clone();
            prop_assert_eq!(normalize_log_weights(&mut c).to_bits(), ess.to_bits());
            prop_assert!(c.iter().zip(&a).all(|(x, y)| x.to_bits() == y.to_bits()));
            // Resampling from the kept weights draws the same parents.
            let rng = || crate::rng::stream(1, 2, 3);
            prop_assert_eq!(systematic_weights(&kept, &mut rng()), systematic(&a, &mut rng()));
        }
    }
}
