//! Measurement models: 2D range-bearing and 3D relative points (the stereo landmarks of the
//! FastSLAM-MLP paper), with their Jacobians and inverses.
//!
//! Measurements travel as `[f64; 3]`: `[range, bearing, 0]` for range-bearing and
//! `[dx, dy, dz]` (robot frame, x forward, y left, z up) for points, so that batches of
//! updates are plain arrays whatever the kind. Landmark means are `[x, y, z]` with `z = 0`
//! in 2D.
//!
//! [`MeasurementModel`] gives each kind its statically sized math (a 2D measurement stays in
//! 2x2 matrices): prediction and Jacobians, innovation, noise, the innovation covariance's
//! inverse and log-determinant. The EKF, the filter's association and proposal, and the
//! localizer all compute with it, generic over the kind, and weigh with
//! [`crate::stats::gaussian_log_density`].

use crate::math;
use crate::pose::{Pose2, wrap_angle};
use crate::updater::LandmarkGaussian;
use nalgebra::{Matrix2, Matrix2x3, Matrix3, SMatrix, SVector, Vector2, Vector3};
use serde::{Deserialize, Serialize};

/// The kind of landmark a run maps. One run uses one kind.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum LandmarkKind {
    /// 2D landmarks observed as (range [m], bearing [rad]).
    #[serde(rename = "range_bearing_2d")]
    RangeBearing2d,
    /// 3D landmarks observed as a point (dx, dy, dz) [m] in the robot frame.
    #[serde(rename = "point3d")]
    Point3d,
}

impl LandmarkKind {
    pub const ALL: [&'static str; 2] = ["range_bearing_2d", "point3d"];

    /// Number of measurement components (2 or 3).
    pub fn dim(self) -> usize {
        match self {
            LandmarkKind::RangeBearing2d => 2,
            LandmarkKind::Point3d => 3,
        }
    }

    pub fn as_str(self) -> &'static str {
        match self {
            LandmarkKind::RangeBearing2d => "range_bearing_2d",
            LandmarkKind::Point3d => "point3d",
        }
    }
}

/// Measurement noise (standard deviations).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SensorNoise {
    /// Range std [m] (range-bearing). Default 0.1.
    pub range: f64,
    /// Bearing std [rad] (range-bearing). Default 0.02.
    pub bearing: f64,
    /// Per-axis std [m] of a 3D point (point3d). Default [0.05, 0.05, 0.05].
    pub xyz: [f64; 3],
    /// Range std per metre of measured range (range-bearing; dimensionless): the range
    /// variance of a measurement of range `r` is `range² + (range_per_m · r)²`. A camera
    /// that ranges a target by its apparent size errs in proportion to the range: MRCLAM's
    /// monocular barcode ranges err by a standard deviation of 0.07 m at 1-2 m, 0.11 m at
    /// 2-3 m, 0.16 m at 3-4 m and 0.19 m at 4-5 m against Vicon (`python3
    /// tools/mrclam_range_error.py`). The measured range, not the predicted one, sets it,
    /// so every particle weighs an observation with the same noise. Default 0 (constant).
    pub range_per_m: f64,
}

impl Default for SensorNoise {
    fn default() -> Self {
        Self {
            range: 0.1,
            bearing: 0.02,
            xyz: [0.05; 3],
            range_per_m: 0.0,
        }
    }
}

impl SensorNoise {
    pub fn validate(&self, prefix: &str) -> Result<(), String> {
        for (name, v) in [
            ("range", self.range),
            ("bearing", self.bearing),
            ("xyz[0]", self.xyz[0]),
            ("xyz[1]", self.xyz[1]),
            ("xyz[2]", self.xyz[2]),
        ] {
            if !(v.is_finite() && v > 0.0) {
                return Err(format!(
                    "{prefix}.{name} must be a finite number > 0, got {v}"
                ));
            }
        }
        if !(self.range_per_m.is_finite() && (0.0..=1.0).contains(&self.range_per_m)) {
            return Err(format!(
                "{prefix}.range_per_m must lie in [0, 1], got {}",
                self.range_per_m
            ));
        }
        Ok(())
    }

    /// The range-bearing noise covariance of a measurement whose range is not known (the
    /// constant part: `range_per_m` left out).
    pub fn q2(&self) -> Matrix2<f64> {
        self.q2_at(0.0)
    }

    /// The range-bearing noise covariance of a measurement of range `r` [m].
    #[inline]
    pub fn q2_at(&self, r: f64) -> Matrix2<f64> {
        let g = self.range_per_m * r;
        Matrix2::new(
            self.range * self.range + g * g,
            0.0,
            0.0,
            self.bearing * self.bearing,
        )
    }

    /// The range standard deviation of a measurement of range `r` [m]: `range` itself
    /// (the same bits) when `range_per_m` is 0.
    #[inline]
    pub fn range_std_at(&self, r: f64) -> f64 {
        if self.range_per_m == 0.0 {
            self.range
        } else {
            self.range_var_at(r).sqrt()
        }
    }

    /// The range variance of a measurement of range `r` [m].
    #[inline]
    pub fn range_var_at(&self, r: f64) -> f64 {
        let g = self.range_per_m * r;
        self.range * self.range + g * g
    }

    pub fn q3(&self) -> Matrix3<f64> {
        Matrix3::from_diagonal(&Vector3::new(
            self.xyz[0] * self.xyz[0],
            self.xyz[1] * self.xyz[1],
            self.xyz[2] * self.xyz[2],
        ))
    }
}

/// Predicted range-bearing measurement of `m` from `pose`, with the Jacobians with respect
/// to the landmark (H_m, 2x2) and the pose (H_x, 2x3). `None` when the landmark sits on the
/// robot (no bearing is defined).
#[inline(always)]
pub fn range_bearing_predict(
    pose: &Pose2,
    mx: f64,
    my: f64,
) -> Option<(Vector2<f64>, Matrix2<f64>, Matrix2x3<f64>)> {
    let dx = mx - pose.x;
    let dy = my - pose.y;
    let q = dx * dx + dy * dy;
    if q < 1e-12 {
        return None;
    }
    let r = q.sqrt();
    let z = Vector2::new(r, wrap_angle(bearing_atan2(dy, dx) - pose.theta));
    let hm = Matrix2::new(dx / r, dy / r, -dy / q, dx / q);
    let hx = Matrix2x3::new(-dx / r, -dy / r, 0.0, dy / q, -dx / q, -1.0);
    Some((z, hm, hx))
}

/// `atan2(y, x)` as the filter's predictions take it: the `libm` crate's (FreeBSD's
/// msun, error below one ulp), not the platform's C library's. It is the prediction's
/// largest single cost: glibc's `atan2` took about 147 instructions a call, 15 % of the
/// filter's instructions on the simulated speed log (two calls per particle and observation:
/// 2.0's proposal and the landmark update), `libm`'s takes about 104 (callgrind, README,
/// session 24). And it gives the same bits on every platform, whatever its C library.
///
/// Where `x` and `y` are normal and finite and their exponents differ by at most 64 (every
/// bearing the filter predicts), this takes libm's own path without its special cases
/// (zeros, infinities, NaN, `x = 1`, ratios beyond 2^±64): `atan(|y/x|)` placed in its
/// quadrant by the same operations, so the result has the same bits as `libm::atan2`'s
/// (test `bearing_atan2_is_libms_atan2`); everything else goes to `libm::atan2`. Skipping
/// those checks and the call saved 15-27 of the 104 instructions a bearing cost (callgrind,
/// README, session 27).
#[inline]
pub fn bearing_atan2(y: f64, x: f64) -> f64 {
    // The low 31 bits of the high word: exponent and leading mantissa bits.
    let high = |v: f64| ((v.to_bits() >> 32) as u32) & 0x7fff_ffff;
    let (ix, iy) = (high(x), high(y));
    // Normal and finite: exponent field neither 0 nor all ones.
    let normal = |i: u32| i.wrapping_sub(0x0010_0000) < 0x7fe0_0000;
    // libm's bounds on the ratio, as it tests them: exponents 64 apart in the high word.
    const RATIO: u32 = 64 << 20;
    if !(normal(ix) && normal(iy) && iy <= ix + RATIO && ix <= iy + RATIO) {
        return special_atan2(y, x);
    }
    const PI_LO: f64 = 1.224_646_799_147_353_2e-16;
    let z = libm::atan((y / x).abs());
    match (x < 0.0, y < 0.0) {
        (false, false) => z,
        (false, true) => -z,
        (true, false) => std::f64::consts::PI - (z - PI_LO),
        (true, true) => (z - PI_LO) - std::f64::consts::PI,
    }
}

/// [`bearing_atan2`]'s rare inputs, kept out of line so that the common path stays small
/// enough to inline into the predictions.
#[cold]
#[inline(never)]
fn special_atan2(y: f64, x: f64) -> f64 {
    libm::atan2(y, x)
}

/// World position of a range-bearing measurement.
#[inline]
pub fn range_bearing_inverse(pose: &Pose2, range: f64, bearing: f64) -> (f64, f64) {
    let (s, c) = math::sin_cos(pose.theta + bearing);
    (pose.x + range * c, pose.y + range * s)
}

/// Predicted relative point of landmark `m` from `pose`, with H_m (3x3, a rotation) and
/// H_x (3x3, last row zero).
#[inline]
pub fn point3_predict(pose: &Pose2, m: &[f64; 3]) -> (Vector3<f64>, Matrix3<f64>, Matrix3<f64>) {
    let (s, c) = math::sin_cos(pose.theta);
    let dxw = m[0] - pose.x;
    let dyw = m[1] - pose.y;
    let zx = c * dxw + s * dyw;
    let zy = -s * dxw + c * dyw;
    let z = Vector3::new(zx, zy, m[2]);
    let hm = Matrix3::new(c, s, 0.0, -s, c, 0.0, 0.0, 0.0, 1.0);
    let hx = Matrix3::new(-c, -s, zy, s, -c, -zx, 0.0, 0.0, 0.0);
    (z, hm, hx)
}

/// World position of a relative point.
#[inline]
pub fn point3_inverse(pose: &Pose2, z: &[f64; 3]) -> [f64; 3] {
    let (s, c) = math::sin_cos(pose.theta);
    [
        pose.x + c * z[0] - s * z[1],
        pose.y + s * z[0] + c * z[1],
        z[2],
    ]
}

/// The measurement model of one landmark kind, in matrices of its own dimension `D` (2 for
/// range-bearing, 3 for points). Code generic over it is compiled once per kind; the run's
/// kind picks the instance once per step, not once per observation.
pub trait MeasurementModel<const D: usize> {
    /// The kind this model serves.
    const KIND: LandmarkKind;

    /// The predicted measurement `ẑ = h(x, m)` of landmark mean `m` from `pose`, with the
    /// Jacobians with respect to the landmark (`H_m`, D x D) and the pose (`Hₓ`, D x 3).
    /// `None` where the model is undefined (a range-bearing landmark on the robot).
    #[allow(clippy::type_complexity)]
    fn predict(
        pose: &Pose2,
        m: &[f64; 3],
    ) -> Option<(SVector<f64, D>, SMatrix<f64, D, D>, SMatrix<f64, D, 3>)>;

    /// The innovation `z − ẑ` (the bearing wrapped to (−π, π] in 2D).
    fn innovation(z: &[f64; 3], zhat: &SVector<f64, D>) -> SVector<f64, D>;

    /// The measurement noise covariance `Q` of measurement `z`.
    fn noise(n: &SensorNoise, z: &[f64; 3]) -> SMatrix<f64, D, D>;

    /// A landmark Gaussian's mean in the model's dimension.
    fn mean(g: &LandmarkGaussian) -> SVector<f64, D>;

    /// A landmark Gaussian's covariance in the model's dimension.
    fn cov(g: &LandmarkGaussian) -> SMatrix<f64, D, D>;

    /// A landmark Gaussian from a mean and covariance of the model's dimension (symmetrised).
    fn gaussian(mean: &SVector<f64, D>, cov: &SMatrix<f64, D, D>) -> LandmarkGaussian;

    /// The inverse and the determinant of an innovation covariance `S`; `None` unless `S` is
    /// positive definite with a finite determinant. (The determinant, not its logarithm: an
    /// update that needs no likelihood takes no logarithm.)
    fn inverse_det(s: &SMatrix<f64, D, D>) -> Option<(SMatrix<f64, D, D>, f64)>;
}

/// [`LandmarkKind::RangeBearing2d`]'s model: `z = (range, bearing)`, 2x2 throughout.
#[derive(Debug, Clone, Copy)]
pub struct RangeBearingModel;

impl MeasurementModel<2> for RangeBearingModel {
    const KIND: LandmarkKind = LandmarkKind::RangeBearing2d;

    #[inline(always)]
    fn predict(pose: &Pose2, m: &[f64; 3]) -> Option<(Vector2<f64>, Matrix2<f64>, Matrix2x3<f64>)> {
        range_bearing_predict(pose, m[0], m[1])
    }

    #[inline(always)]
    fn innovation(z: &[f64; 3], zhat: &Vector2<f64>) -> Vector2<f64> {
        Vector2::new(z[0] - zhat[0], wrap_angle(z[1] - zhat[1]))
    }

    #[inline(always)]
    fn noise(n: &SensorNoise, z: &[f64; 3]) -> Matrix2<f64> {
        n.q2_at(z[0])
    }

    #[inline(always)]
    fn mean(g: &LandmarkGaussian) -> Vector2<f64> {
        Vector2::new(g.mean[0], g.mean[1])
    }

    #[inline(always)]
    fn cov(g: &LandmarkGaussian) -> Matrix2<f64> {
        g.cov2()
    }

    #[inline(always)]
    fn gaussian(mean: &Vector2<f64>, cov: &Matrix2<f64>) -> LandmarkGaussian {
        LandmarkGaussian::from_2d([mean[0], mean[1]], cov)
    }

    /// The closed-form 2x2 inverse (positive definite: a positive determinant and a positive
    /// first diagonal entry).
    #[inline(always)]
    fn inverse_det(s: &Matrix2<f64>) -> Option<(Matrix2<f64>, f64)> {
        let det = s[(0, 0)] * s[(1, 1)] - s[(0, 1)] * s[(1, 0)];
        if !(det > 0.0 && det.is_finite() && s[(0, 0)] > 0.0) {
            return None;
        }
        let inv = Matrix2::new(
            s[(1, 1)] / det,
            -s[(0, 1)] / det,
            -s[(1, 0)] / det,
            s[(0, 0)] / det,
        );
        Some((inv, det))
    }
}

/// [`LandmarkKind::Point3d`]'s model: `z = (dx, dy, dz)` in the robot frame, 3x3.
#[derive(Debug, Clone, Copy)]
pub struct Point3Model;

impl MeasurementModel<3> for Point3Model {
    const KIND: LandmarkKind = LandmarkKind::Point3d;

    #[inline(always)]
    fn predict(pose: &Pose2, m: &[f64; 3]) -> Option<(Vector3<f64>, Matrix3<f64>, Matrix3<f64>)> {
        Some(point3_predict(pose, m))
    }

    #[inline(always)]
    fn innovation(z: &[f64; 3], zhat: &Vector3<f64>) -> Vector3<f64> {
        Vector3::new(z[0] - zhat[0], z[1] - zhat[1], z[2] - zhat[2])
    }

    #[inline(always)]
    fn noise(n: &SensorNoise, _z: &[f64; 3]) -> Matrix3<f64> {
        n.q3()
    }

    #[inline(always)]
    fn mean(g: &LandmarkGaussian) -> Vector3<f64> {
        Vector3::from(g.mean)
    }

    #[inline(always)]
    fn cov(g: &LandmarkGaussian) -> Matrix3<f64> {
        g.cov3()
    }

    #[inline(always)]
    fn gaussian(mean: &Vector3<f64>, cov: &Matrix3<f64>) -> LandmarkGaussian {
        LandmarkGaussian::from_3d([mean[0], mean[1], mean[2]], cov)
    }

    /// Through the Cholesky factor.
    #[inline(always)]
    fn inverse_det(s: &Matrix3<f64>) -> Option<(Matrix3<f64>, f64)> {
        let c = s.cholesky()?;
        let det = c.determinant();
        (det > 0.0 && det.is_finite()).then(|| (c.inverse(), det))
    }
}

/// `true` when the measurement is finite and physically possible for the kind.
pub fn validate_measurement(kind: LandmarkKind, z: &[f64]) -> Result<(), String> {
    if z.len() != kind.dim() {
        return Err(format!(
            "a {} measurement has {} numbers ({}), got {}",
            kind.as_str(),
            kind.dim(),
            if kind == LandmarkKind::RangeBearing2d {
                "[range, bearing]"
            } else {
                "[dx, dy, dz]"
            },
            z.len()
        ));
    }
    if z.iter().any(|v| !v.is_finite()) {
        return Err(format!("measurement {z:?} has a non-finite number"));
    }
    if kind == LandmarkKind::RangeBearing2d && z[0] <= 0.0 {
        return Err(format!("range must be > 0, got {}", z[0]));
    }
    if z.iter().any(|v| v.abs() > 1e6) {
        return Err(format!(
            "measurement {z:?} is beyond 1e6 m: check its units"
        ));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// The same bits as `libm::atan2`, NaN as NaN.
    fn same_as_libm(y: f64, x: f64) -> Result<(), String> {
        let (a, b) = (bearing_atan2(y, x), libm::atan2(y, x));
        if a.to_bits() == b.to_bits() || (a.is_nan() && b.is_nan()) {
            Ok(())
        } else {
            Err(format!("atan2({y:e}, {x:e}): {a:e} against libm's {b:e}"))
        }
    }

    /// Every pair of special and boundary values: signed zeros, subnormals, the smallest
    /// normal, one, huge values, infinities, NaN, and ratios around libm's 2^±64 bounds, in
    /// all four quadrants.
    #[test]
    fn bearing_atan2_is_libms_atan2() {
        let mut values = vec![
            0.0,
            5e-324,
            1e-310,
            f64::MIN_POSITIVE,
            1e-300,
            1e-20,
            0.5,
            1.0,
            1.0 + f64::EPSILON,
            3.0,
            1e20,
            1e300,
            f64::MAX,
            f64::INFINITY,
            f64::NAN,
        ];
        for e in [-66, -65, -64, -63, 63, 64, 65, 66] {
            let p = 2f64.powi(e);
            values.extend([
                p,
                p * (1.0 - f64::EPSILON),
                p * (1.0 + 2.0 * f64::EPSILON),
                p * 1.5,
            ]);
        }
        let signed: Vec<f64> = values.iter().flat_map(|v| [*v, -*v]).collect();
        for &y in &signed {
            for &x in &signed {
                if let Err(e) = same_as_libm(y, x) {
                    panic!("{e}");
                }
            }
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(20_000))]
        /// Any two floats, from their bits (every exponent alike).
        #[test]
        fn bearing_atan2_is_libms_atan2_on_any_bits(a in any::<u64>(), b in any::<u64>()) {
            let r = same_as_libm(f64::from_bits(a), f64::from_bits(b));
            prop_assert!(r.is_ok(), "{}", r.unwrap_err());
        }

        /// Landmark offsets as the filter predicts them, and ratios near the 2^±64 bounds.
        #[test]
        fn bearing_atan2_is_libms_atan2_on_offsets(
            dy in -200.0..200.0f64,
            dx in -200.0..200.0f64,
            e in -70..70i32,
        ) {
            let r = same_as_libm(dy, dx);
            prop_assert!(r.is_ok(), "{}", r.unwrap_err());
            let r = same_as_libm(dy * 2f64.powi(e), dx);
            prop_assert!(r.is_ok(), "{}", r.unwrap_err());
        }
    }

    #[test]
    fn range_noise_grows_with_the_measured_range_when_asked() {
        let constant = SensorNoise::default();
        assert_eq!(constant.q2_at(7.0), constant.q2());
        assert_eq!(constant.range_std_at(7.0), constant.range);
        let grow = SensorNoise {
            range: 0.05,
            range_per_m: 0.04,
            ..SensorNoise::default()
        };
        // 0.05² + (0.04 · 3)² = 0.0025 + 0.0144.
        assert!((grow.range_var_at(3.0) - 0.0169).abs() < 1e-15);
        assert!((grow.range_std_at(3.0) - 0.13).abs() < 1e-15);
        let q = RangeBearingModel::noise(&grow, &[3.0, 0.2, 0.0]);
        assert_eq!(q, grow.q2_at(3.0));
        assert_eq!(q[(1, 1)], grow.bearing * grow.bearing);
        for bad in [-0.01, f64::NAN, f64::INFINITY, 1.5] {
            let n = SensorNoise {
                range_per_m: bad,
                ..SensorNoise::default()
            };
            let e = n.validate("sensor_noise").unwrap_err();
            assert!(e.contains("sensor_noise.range_per_m"), "{e}");
        }
        // Old configurations (no such field) read as constant noise.
        let old: SensorNoise =
            serde_json::from_str(r#"{"range":0.3,"bearing":0.04,"xyz":[0.1,0.1,0.1]}"#).unwrap();
        assert_eq!(old.range_per_m, 0.0);
    }

    #[test]
    fn range_bearing_hand_worked() {
        // Robot at (1, 1) facing +y; landmark at (1, 3): range 2, bearing 0.
        let pose = Pose2::new(1.0, 1.0, std::f64::consts::FRAC_PI_2);
        let (z, hm, hx) = range_bearing_predict(&pose, 1.0, 3.0).unwrap();
        assert!((z[0] - 2.0).abs() < 1e-12 && z[1].abs() < 1e-12);
        // dx = 0, dy = 2, q = 4, r = 2.
        assert!((hm - Matrix2::new(0.0, 1.0, -0.5, 0.0)).norm() < 1e-12);
        assert!((hx - Matrix2x3::new(0.0, -1.0, 0.0, 0.5, 0.0, -1.0)).norm() < 1e-12);
        let (x, y) = range_bearing_inverse(&pose, z[0], z[1]);
        assert!((x - 1.0).abs() < 1e-12 && (y - 3.0).abs() < 1e-12);
    }

    fn numeric_jacobian(f: impl Fn(&[f64]) -> Vec<f64>, at: &[f64]) -> Vec<Vec<f64>> {
        let f0 = f(at);
        let h = 1e-6;
        (0..f0.len())
            .map(|i| {
                (0..at.len())
                    .map(|j| {
                        let mut a = at.to_vec();
                        a[j] += h;
                        let mut d = f(&a)[i] - f0[i];
                        if d.abs() > 1.0 {
                            d = wrap_angle(d);
                        }
                        d / h
                    })
                    .collect()
            })
            .collect()
    }

    #[test]
    fn jacobians_match_finite_differences() {
        let pose = Pose2::new(0.3, -0.7, 2.5);
        let m = [2.0, 1.5, 0.8];
        let (_, hm, hx) = range_bearing_predict(&pose, m[0], m[1]).unwrap();
        let nm = numeric_jacobian(
            |a| {
                let (z, _, _) = range_bearing_predict(&pose, a[0], a[1]).unwrap();
                vec![z[0], z[1]]
            },
            &m[..2],
        );
        let nx = numeric_jacobian(
            |a| {
                let p = Pose2::new(a[0], a[1], a[2]);
                let (z, _, _) = range_bearing_predict(&p, m[0], m[1]).unwrap();
                vec![z[0], z[1]]
            },
            &[pose.x, pose.y, pose.theta],
        );
        for i in 0..2 {
            for j in 0..2 {
                assert!((hm[(i, j)] - nm[i][j]).abs() < 1e-5);
            }
            for j in 0..3 {
                assert!((hx[(i, j)] - nx[i][j]).abs() < 1e-5);
            }
        }
        let (z3, hm3, hx3) = point3_predict(&pose, &m);
        let back = point3_inverse(&pose, &[z3[0], z3[1], z3[2]]);
        for k in 0..3 {
            assert!((back[k] - m[k]).abs() < 1e-12);
        }
        let nm3 = numeric_jacobian(
            |a| {
                let (z, _, _) = point3_predict(&pose, &[a[0], a[1], a[2]]);
                z.iter().copied().collect()
            },
            &m,
        );
        let nx3 = numeric_jacobian(
            |a| {
                let (z, _, _) = point3_predict(&Pose2::new(a[0], a[1], a[2]), &m);
                z.iter().copied().collect()
            },
            &[pose.x, pose.y, pose.theta],
        );
        for i in 0..3 {
            for j in 0..3 {
                assert!((hm3[(i, j)] - nm3[i][j]).abs() < 1e-5);
                assert!((hx3[(i, j)] - nx3[i][j]).abs() < 1e-5);
            }
        }
    }

    /// Each model's inverse is the inverse and its determinant the determinant; a covariance
    /// that is not positive definite has none; a landmark Gaussian survives the model's
    /// reading and writing; and the models name their kinds.
    #[test]
    fn measurement_models_invert_and_round_trip() {
        fn check<const D: usize, M: MeasurementModel<D>>(s: SMatrix<f64, D, D>, want_det: f64) {
            let (inv, det) = M::inverse_det(&s).unwrap();
            assert!((inv * s - SMatrix::<f64, D, D>::identity()).norm() < 1e-12);
            assert!((det - want_det).abs() < 1e-12 * want_det);
            assert!(M::inverse_det(&(-s)).is_none());
            assert!(M::inverse_det(&SMatrix::<f64, D, D>::zeros()).is_none());
            let g = LandmarkGaussian {
                mean: [1.0, -2.0, if D == 3 { 0.5 } else { 0.0 }],
                cov: if D == 3 {
                    [0.3, 0.01, 0.02, 0.2, 0.03, 0.1]
                } else {
                    [0.3, 0.01, 0.0, 0.2, 0.0, 0.0]
                },
            };
            assert_eq!(M::gaussian(&M::mean(&g), &M::cov(&g)), g);
            assert_eq!(M::KIND.dim(), D);
        }
        let s2 = Matrix2::new(0.02, 0.001, 0.001, 0.005);
        check::<2, RangeBearingModel>(s2, s2.determinant());
        let s3 = Matrix3::new(0.02, 0.001, 0.0, 0.001, 0.005, 0.002, 0.0, 0.002, 0.03);
        check::<3, Point3Model>(s3, s3.determinant());
        // The models predict what the kinds' functions do, and wrap the bearing.
        let pose = Pose2::new(0.3, -0.7, 2.5);
        let m = [2.0, 1.5, 0.8];
        let (z, hm, hx) = RangeBearingModel::predict(&pose, &m).unwrap();
        assert_eq!(Some((z, hm, hx)), range_bearing_predict(&pose, m[0], m[1]));
        assert!(RangeBearingModel::predict(&pose, &[0.3, -0.7, 0.0]).is_none());
        let nu = RangeBearingModel::innovation(
            &[z[0] + 0.1, z[1] + 2.0 * std::f64::consts::PI, 0.0],
            &z,
        );
        assert!((nu[0] - 0.1).abs() < 1e-12 && nu[1].abs() < 1e-12);
        assert_eq!(
            Point3Model::predict(&pose, &m),
            Some(point3_predict(&pose, &m))
        );
    }

    #[test]
    fn kind_names() {
        for k in [LandmarkKind::RangeBearing2d, LandmarkKind::Point3d] {
            assert_eq!(
                serde_json::to_string(&k).unwrap(),
                format!("\"{}\"", k.as_str())
            );
            assert!(LandmarkKind::ALL.contains(&k.as_str()));
        }
    }

    #[test]
    fn measurement_validation() {
        let k = LandmarkKind::RangeBearing2d;
        assert!(validate_measurement(k, &[1.0, 0.1]).is_ok());
        assert!(validate_measurement(k, &[1.0]).is_err());
        assert!(validate_measurement(k, &[-1.0, 0.1]).is_err());
        assert!(validate_measurement(k, &[f64::INFINITY, 0.1]).is_err());
        assert!(validate_measurement(LandmarkKind::Point3d, &[1.0, 0.1, 1e9]).is_err());
    }
}
