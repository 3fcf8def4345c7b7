//! Log-space weights and low-variance (systematic) resampling.

use rand::Rng;

/// Normalises log-weights in place so that `Σ exp(w) = 1` and returns the effective sample
/// size `1 / Σ w²`. Non-finite weights count as impossible and become `f64::MIN` (finite, so
/// that they serialise); if every weight is impossible the weights are reset to uniform (and
/// the ESS is N). The filter never produces NaN.
pub fn normalize_log_weights(log_w: &mut [f64]) -> f64 {
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
        let u = -(n as f64).ln();
        log_w.iter_mut().for_each(|w| *w = u);
        return n as f64;
    }
    let sum: f64 = log_w
        .iter()
        .map(|&w| if w.is_finite() { (w - max).exp() } else { 0.0 })
        .sum();
    let lse = max + sum.ln();
    let mut sq = 0.0;
    for w in log_w.iter_mut() {
        *w = if w.is_finite() {
            (*w - lse).max(f64::MIN)
        } else {
            f64::MIN
        };
        let p = w.exp();
        sq += p * p;
    }
    1.0 / sq
}

/// Systematic resampling: one uniform draw, N evenly spaced pointers into the cumulative
/// weights (Thrun, Burgard, Fox, Probabilistic Robotics, table 4.4). `log_w` must be
/// normalised. Returns the index of the parent of each new particle, in order.
pub fn systematic(log_w: &[f64], rng: &mut impl Rng) -> Vec<usize> {
    let n = log_w.len();
    let mut out = Vec::with_capacity(n);
    if n == 0 {
        return out;
    }
    let step = 1.0 / n as f64;
    let mut u = rng.random::<f64>() * step;
    let mut c = log_w[0].exp();
    let mut i = 0;
    for _ in 0..n {
        while u > c && i + 1 < n {
            i += 1;
            c += log_w[i].exp();
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
        let mut w: Vec<f64> = [0.5f64, 0.25, 0.25, 0.0].iter().map(|p| p.ln()).collect();
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
            let s: f64 = w.iter().map(|w| w.exp()).sum();
            prop_assert!((s - 1.0).abs() < 1e-9);
            prop_assert!(ess >= 1.0 - 1e-9 && ess <= w.len() as f64 + 1e-9);
            let idx = systematic(&w, &mut crate::rng::stream(1, 2, 3));
            prop_assert_eq!(idx.len(), w.len());
            prop_assert!(idx.windows(2).all(|p| p[0] <= p[1]));
        }
    }
}
