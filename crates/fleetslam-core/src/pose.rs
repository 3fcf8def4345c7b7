//! Planar robot poses and the angle arithmetic every model shares.

use crate::math;
use serde::{Deserialize, Serialize};
use std::f64::consts::PI;

/// Wraps an angle to (-pi, pi].
#[inline]
pub fn wrap_angle(a: f64) -> f64 {
    if a > -PI && a <= PI {
        return a;
    }
    let mut r = a.rem_euclid(2.0 * PI);
    if r > PI {
        r -= 2.0 * PI;
    }
    r
}

/// A robot pose in the plane: position in metres, heading in radians (CCW from +x).
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct Pose2 {
    pub x: f64,
    pub y: f64,
    pub theta: f64,
}

impl Pose2 {
    pub const fn new(x: f64, y: f64, theta: f64) -> Self {
        Self { x, y, theta }
    }

    /// `self ⊕ delta`: applies an increment expressed in this pose's frame.
    #[inline]
    pub fn compose(&self, delta: &Pose2) -> Pose2 {
        self.compose_sc(delta, math::sin_cos(self.theta))
    }

    /// [`Pose2::compose`] given `math::sin_cos(self.theta)`, for callers that need it anyway.
    #[inline]
    pub fn compose_sc(&self, delta: &Pose2, (s, c): (f64, f64)) -> Pose2 {
        Pose2 {
            x: self.x + c * delta.x - s * delta.y,
            y: self.y + s * delta.x + c * delta.y,
            theta: wrap_angle(self.theta + delta.theta),
        }
    }

    /// `self ⊖ other`: the increment that takes `other` to `self`, in `other`'s frame.
    #[inline]
    pub fn relative_to(&self, other: &Pose2) -> Pose2 {
        let (s, c) = math::sin_cos(other.theta);
        let dx = self.x - other.x;
        let dy = self.y - other.y;
        Pose2 {
            x: c * dx + s * dy,
            y: -s * dx + c * dy,
            theta: wrap_angle(self.theta - other.theta),
        }
    }

    /// Euclidean distance between the positions.
    pub fn distance(&self, other: &Pose2) -> f64 {
        math::hypot(self.x - other.x, self.y - other.y)
    }

    pub fn is_finite(&self) -> bool {
        self.x.is_finite() && self.y.is_finite() && self.theta.is_finite()
    }
}

/// A Gaussian over a pose: mean and 3x3 covariance (x, y, theta), row-major.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PoseGaussian {
    pub mean: Pose2,
    /// Row-major 3x3 covariance of (x, y, theta). Zero means the pose is known exactly.
    #[serde(default)]
    pub cov: [[f64; 3]; 3],
}

impl PoseGaussian {
    pub fn exact(mean: Pose2) -> Self {
        Self {
            mean,
            cov: [[0.0; 3]; 3],
        }
    }

    pub fn diagonal(mean: Pose2, sx: f64, sy: f64, stheta: f64) -> Self {
        let mut cov = [[0.0; 3]; 3];
        cov[0][0] = sx * sx;
        cov[1][1] = sy * sy;
        cov[2][2] = stheta * stheta;
        Self { mean, cov }
    }
}

/// A pose's position and its heading's `(sin θ, cos θ)`: what a weighted mean of poses
/// reads, kept side by side so that the mean reads contiguous memory. Its `sin` and `cos`
/// are always those of its `theta` (the default is the zero pose's).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PositionHeading {
    pub x: f64,
    pub y: f64,
    /// `θ`, whose sine and cosine these are.
    pub theta: f64,
    /// `sin θ`.
    pub sin: f64,
    /// `cos θ`.
    pub cos: f64,
}

impl Default for PositionHeading {
    fn default() -> Self {
        Self::of(&Pose2::default())
    }
}

impl PositionHeading {
    #[inline]
    pub fn of(p: &Pose2) -> Self {
        let (sin, cos) = math::sin_cos(p.theta);
        Self {
            x: p.x,
            y: p.y,
            theta: p.theta,
            sin,
            cos,
        }
    }

    /// Becomes [`PositionHeading::of`] `p`, computing the sine and cosine only when the
    /// heading changed (bit for bit): a robot that drives straight or stands keeps its
    /// heading exactly, as 9,963 of MRCLAM's 21,962 records without landmarks do
    /// (`filter_seeds -- speed` counts them).
    #[inline]
    pub fn move_to(&mut self, p: &Pose2) {
        if p.theta.to_bits() == self.theta.to_bits() {
            self.x = p.x;
            self.y = p.y;
        } else {
            *self = Self::of(p);
        }
    }

    /// `(sin θ, cos θ)`.
    #[inline]
    pub fn sc(&self) -> (f64, f64) {
        (self.sin, self.cos)
    }
}

/// Weighted circular/linear mean of poses. Weights need not be normalised.
pub fn weighted_mean_pose<'a>(items: impl Iterator<Item = (&'a Pose2, f64)>) -> Pose2 {
    weighted_mean_pose_sc(items.map(|(p, w)| (PositionHeading::of(p), w)))
}

/// [`weighted_mean_pose`] of poses given as [`PositionHeading`]s, computed once by the
/// caller.
pub fn weighted_mean_pose_sc(items: impl Iterator<Item = (PositionHeading, f64)>) -> Pose2 {
    let (mut sw, mut sx, mut sy, mut ss, mut sc) = (0.0, 0.0, 0.0, 0.0, 0.0);
    for (p, w) in items {
        sw += w;
        sx += w * p.x;
        sy += w * p.y;
        ss += w * p.sin;
        sc += w * p.cos;
    }
    if sw <= 0.0 {
        return Pose2::default();
    }
    Pose2::new(sx / sw, sy / sw, math::atan2(ss, sc))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_moved_heading_is_the_moved_poses() {
        let mut h = PositionHeading::default();
        assert_eq!(h, PositionHeading::of(&Pose2::default()));
        for p in [
            Pose2::new(1.0, 2.0, 0.0),
            Pose2::new(3.0, -1.0, 0.5),
            Pose2::new(4.0, 0.0, 0.5),
            Pose2::new(4.0, 0.0, -0.0),
            Pose2::new(-2.0, 7.0, PI),
        ] {
            h.move_to(&p);
            let want = PositionHeading::of(&p);
            assert_eq!(
                [h.x, h.y, h.theta, h.sin, h.cos].map(f64::to_bits),
                [want.x, want.y, want.theta, want.sin, want.cos].map(f64::to_bits)
            );
        }
    }

    #[test]
    fn wrap_angle_range() {
        for a in [-10.0, -PI, -3.0, 0.0, 3.0, PI, 10.0, 1e6] {
            let w = wrap_angle(a);
            assert!(w > -PI && w <= PI, "{a} -> {w}");
            assert!(((w - a) / (2.0 * PI)).round() * 2.0 * PI - (w - a) < 1e-6);
        }
        assert_eq!(wrap_angle(-PI), PI);
    }

    #[test]
    fn compose_and_relative_are_inverse() {
        let a = Pose2::new(1.0, -2.0, 0.7);
        let d = Pose2::new(0.3, 0.1, -0.2);
        let b = a.compose(&d);
        let back = b.relative_to(&a);
        assert!((back.x - d.x).abs() < 1e-12);
        assert!((back.y - d.y).abs() < 1e-12);
        assert!((back.theta - d.theta).abs() < 1e-12);
    }

    #[test]
    fn compose_hand_worked() {
        // Facing +y, moving 1 m forward lands at (0, 1).
        let a = Pose2::new(0.0, 0.0, PI / 2.0);
        let b = a.compose(&Pose2::new(1.0, 0.0, 0.0));
        assert!(b.x.abs() < 1e-12 && (b.y - 1.0).abs() < 1e-12);
    }
}
