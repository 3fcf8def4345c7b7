//! Measurement models: 2D range-bearing and 3D relative points (the stereo landmarks of the
//! FastSLAM-MLP paper), with their Jacobians and inverses.
//!
//! Measurements travel as `[f64; 3]`: `[range, bearing, 0]` for range-bearing and
//! `[dx, dy, dz]` (robot frame, x forward, y left, z up) for points, so that batches of
//! updates are plain arrays whatever the kind. Landmark means are `[x, y, z]` with `z = 0`
//! in 2D.

use crate::pose::{Pose2, wrap_angle};
use nalgebra::{Matrix2, Matrix2x3, Matrix3, Vector2, Vector3};
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
}

impl Default for SensorNoise {
    fn default() -> Self {
        Self {
            range: 0.1,
            bearing: 0.02,
            xyz: [0.05; 3],
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
        Ok(())
    }

    pub fn q2(&self) -> Matrix2<f64> {
        Matrix2::new(
            self.range * self.range,
            0.0,
            0.0,
            self.bearing * self.bearing,
        )
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
#[inline]
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
    let z = Vector2::new(r, wrap_angle(dy.atan2(dx) - pose.theta));
    let hm = Matrix2::new(dx / r, dy / r, -dy / q, dx / q);
    let hx = Matrix2x3::new(-dx / r, -dy / r, 0.0, dy / q, -dx / q, -1.0);
    Some((z, hm, hx))
}

/// World position of a range-bearing measurement.
#[inline]
pub fn range_bearing_inverse(pose: &Pose2, range: f64, bearing: f64) -> (f64, f64) {
    let (s, c) = (pose.theta + bearing).sin_cos();
    (pose.x + range * c, pose.y + range * s)
}

/// Predicted relative point of landmark `m` from `pose`, with H_m (3x3, a rotation) and
/// H_x (3x3, last row zero).
#[inline]
pub fn point3_predict(pose: &Pose2, m: &[f64; 3]) -> (Vector3<f64>, Matrix3<f64>, Matrix3<f64>) {
    let (s, c) = pose.theta.sin_cos();
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
    let (s, c) = pose.theta.sin_cos();
    [
        pose.x + c * z[0] - s * z[1],
        pose.y + s * z[0] + c * z[1],
        z[2],
    ]
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
