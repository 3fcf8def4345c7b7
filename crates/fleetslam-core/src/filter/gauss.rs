//! Gaussian and measurement-model math shared by the filter's steps: sampling, the
//! symmetric-matrix packing of pose covariances, and the measurement prediction, innovation
//! and innovation-covariance inverse of the run's landmark kind.

use crate::config::FilterConfig;
use crate::pose::{Pose2, wrap_angle};
use crate::sensor::{LandmarkKind, point3_predict, range_bearing_predict};
use nalgebra::{Matrix3, Vector3};
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;

#[inline]
pub(super) fn normal3(rng: &mut ChaCha8Rng) -> Vector3<f64> {
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
pub(super) fn sample_gaussian(mean: &Pose2, cov: &Matrix3<f64>, rng: &mut ChaCha8Rng) -> Pose2 {
    match cholesky_psd(cov) {
        Some(l) => {
            let e = l * normal3(rng);
            Pose2::new(mean.x + e[0], mean.y + e[1], wrap_angle(mean.theta + e[2]))
        }
        None => *mean,
    }
}

/// Measurement prediction of a landmark from a pose, in the run's kind, as 3-vectors (the
/// third component unused in 2D): (ẑ, H_m, Hₓ).
#[inline]
pub(super) fn predict(
    kind: LandmarkKind,
    pose: &Pose2,
    m: &[f64; 3],
) -> Option<(Vector3<f64>, Matrix3<f64>, Matrix3<f64>)> {
    match kind {
        LandmarkKind::RangeBearing2d => {
            let (z, hm, hx) = range_bearing_predict(pose, m[0], m[1])?;
            let mut hm3 = Matrix3::zeros();
            hm3.fixed_view_mut::<2, 2>(0, 0).copy_from(&hm);
            let mut hx3 = Matrix3::zeros();
            hx3.fixed_view_mut::<2, 3>(0, 0).copy_from(&hx);
            Some((Vector3::new(z[0], z[1], 0.0), hm3, hx3))
        }
        LandmarkKind::Point3d => Some(point3_predict(pose, m)),
    }
}

/// Innovation, with the bearing wrapped in 2D.
#[inline]
pub(super) fn innovation(kind: LandmarkKind, z: &[f64; 3], zhat: &Vector3<f64>) -> Vector3<f64> {
    match kind {
        LandmarkKind::RangeBearing2d => {
            Vector3::new(z[0] - zhat[0], wrap_angle(z[1] - zhat[1]), 0.0)
        }
        LandmarkKind::Point3d => Vector3::new(z[0] - zhat[0], z[1] - zhat[1], z[2] - zhat[2]),
    }
}

/// Inverse, log-determinant of an innovation covariance of the run's dimension, embedded in
/// 3x3 (the unused block is zero in 2D).
#[inline]
pub(super) fn inv_logdet(kind: LandmarkKind, s: &Matrix3<f64>) -> Option<(Matrix3<f64>, f64)> {
    match kind {
        LandmarkKind::RangeBearing2d => {
            let det = s[(0, 0)] * s[(1, 1)] - s[(0, 1)] * s[(1, 0)];
            if !(det > 0.0 && det.is_finite()) {
                return None;
            }
            let mut inv = Matrix3::zeros();
            inv[(0, 0)] = s[(1, 1)] / det;
            inv[(0, 1)] = -s[(0, 1)] / det;
            inv[(1, 0)] = -s[(1, 0)] / det;
            inv[(1, 1)] = s[(0, 0)] / det;
            Some((inv, det.ln()))
        }
        LandmarkKind::Point3d => {
            let c = s.cholesky()?;
            let det = c.determinant();
            (det > 0.0 && det.is_finite()).then(|| (c.inverse(), det.ln()))
        }
    }
}

pub(super) fn q_matrix(cfg: &FilterConfig) -> Matrix3<f64> {
    match cfg.landmark_kind {
        LandmarkKind::RangeBearing2d => {
            let mut q = Matrix3::zeros();
            q.fixed_view_mut::<2, 2>(0, 0)
                .copy_from(&cfg.sensor_noise.q2());
            q
        }
        LandmarkKind::Point3d => cfg.sensor_noise.q3(),
    }
}
