//! Pose-Gaussian math shared by the filter's steps: sampling and the symmetric-matrix packing
//! of pose covariances. The measurement models' math lives in
//! [`crate::sensor::MeasurementModel`].

use crate::pose::{Pose2, wrap_angle};
use crate::rng::Stream;
use nalgebra::{Matrix3, Vector3};
use rand::Rng;
use rand_distr::StandardNormal;

#[inline]
pub(super) fn normal3(rng: &mut Stream) -> Vector3<f64> {
    Vector3::new(
        rng.sample(StandardNormal),
        rng.sample(StandardNormal),
        rng.sample(StandardNormal),
    )
}

/// Lower Cholesky factor of a symmetric positive semi-definite matrix (with a tiny jitter
/// for semi-definite ones).
pub(super) fn cholesky_psd(m: &Matrix3<f64>) -> Option<Matrix3<f64>> {
    if let Some(c) = m.cholesky() {
        return Some(c.l());
    }
    let jitter = 1e-12 * (1.0 + m.trace().abs());
    (m + Matrix3::identity() * jitter).cholesky().map(|c| c.l())
}

/// A symmetric 3x3 matrix from its upper triangle (xx, xy, xθ, yy, yθ, θθ).
#[inline]
pub(super) fn sym3(c: &[f64; 6]) -> Matrix3<f64> {
    Matrix3::new(c[0], c[1], c[2], c[1], c[3], c[4], c[2], c[4], c[5])
}

/// The upper triangle of a 3x3 matrix, symmetrised.
#[inline]
pub(super) fn upper3(m: &Matrix3<f64>) -> [f64; 6] {
    let s = |i: usize, j: usize| 0.5 * (m[(i, j)] + m[(j, i)]);
    [m[(0, 0)], s(0, 1), s(0, 2), m[(1, 1)], s(1, 2), m[(2, 2)]]
}

/// Jacobian of `prev ⊕ inc` with respect to `prev`, given `prev.theta.sin_cos()`.
#[inline]
pub(super) fn compose_jacobian((s, c): (f64, f64), inc: &Pose2) -> Matrix3<f64> {
    Matrix3::new(
        1.0,
        0.0,
        -s * inc.x - c * inc.y,
        0.0,
        1.0,
        c * inc.x - s * inc.y,
        0.0,
        0.0,
        1.0,
    )
}

/// A sample of `N(mean, cov)` (the mean itself when `cov` has no Cholesky factor, which
/// only a covariance with a non-finite entry lacks after the jitter).
pub(super) fn sample_gaussian(mean: &Pose2, cov: &Matrix3<f64>, rng: &mut Stream) -> Pose2 {
    match cholesky_psd(cov) {
        Some(l) => {
            let e = l * normal3(rng);
            Pose2::new(mean.x + e[0], mean.y + e[1], wrap_angle(mean.theta + e[2]))
        }
        None => *mean,
    }
}
