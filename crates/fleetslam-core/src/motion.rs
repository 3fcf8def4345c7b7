//! Motion models: velocity commands (MRCLAM), odometry increments, Ackermann steering
//! (Victoria Park), and one noise model shared by all three.
//!
//! Every model first turns its input into a deterministic increment `(dx, dy, dtheta)` in the
//! robot frame at the start of the motion (exact arc integration for velocity segments, RK4
//! for the Ackermann kinematics of Guivant and Nebot 2000). Noise is then added to that
//! increment in the same frame, with standard deviations that grow with distance, rotation
//! and (as a random walk) with elapsed time:
//!
//! ```text
//! var_long  = (trans_per_m * d)^2              + trans_per_sqrt_s^2 * dt
//! var_lat   = (lateral_per_m * d)^2            + trans_per_sqrt_s^2 * dt
//! var_theta = (rot_per_rad * |dtheta|)^2 + (rot_per_m * d)^2 + rot_per_sqrt_s^2 * dt
//! ```
//!
//! Because the noisy pose is `prev ⊕ (increment + e)`, which is linear in `e`, the world-frame
//! covariance that FastSLAM 2.0's proposal needs is exact: `R = J diag(var) J^T`.

use crate::math;
use crate::pose::Pose2;
use nalgebra::Matrix3;
use serde::{Deserialize, Serialize};

/// Which motion model a run uses.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum MotionModel {
    /// Segments of (forward velocity v [m/s], angular velocity w [rad/s], duration dt [s]).
    Velocity,
    /// One increment (dx [m], dy [m], dtheta [rad]) in the robot frame.
    Odometry,
    /// Segments of (encoder speed [m/s], steering angle [rad], duration dt [s]).
    Ackermann,
}

impl MotionModel {
    pub const ALL: [&'static str; 3] = ["velocity", "odometry", "ackermann"];
}

/// The motion of one robot since its previous record, as posted by the robot.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", deny_unknown_fields)]
pub enum Motion {
    /// `[[v, w, dt], ...]`.
    Velocity(Vec<[f64; 3]>),
    /// `[dx, dy, dtheta]` in the robot frame at the previous record.
    Odometry([f64; 3]),
    /// `[[speed, steering, dt], ...]`.
    Ackermann(Vec<[f64; 3]>),
}

impl Motion {
    pub fn model(&self) -> MotionModel {
        match self {
            Motion::Velocity(_) => MotionModel::Velocity,
            Motion::Odometry(_) => MotionModel::Odometry,
            Motion::Ackermann(_) => MotionModel::Ackermann,
        }
    }

    /// Checks that every number is finite and every duration non-negative.
    pub fn validate(&self) -> Result<(), String> {
        let segs: &[[f64; 3]] = match self {
            Motion::Velocity(s) | Motion::Ackermann(s) => s,
            Motion::Odometry(d) => std::slice::from_ref(d),
        };
        for (i, s) in segs.iter().enumerate() {
            if s.iter().any(|v| !v.is_finite()) {
                return Err(format!("motion segment {i} has a non-finite number: {s:?}"));
            }
            if !matches!(self, Motion::Odometry(_)) && s[2] < 0.0 {
                return Err(format!(
                    "motion segment {i} has a negative duration {}",
                    s[2]
                ));
            }
        }
        Ok(())
    }

    /// Total duration of the segments (0 for an odometry increment, whose duration is the
    /// gap between records).
    pub fn duration(&self) -> f64 {
        match self {
            Motion::Velocity(s) | Motion::Ackermann(s) => s.iter().map(|s| s[2]).sum(),
            Motion::Odometry(_) => 0.0,
        }
    }

    /// The deterministic increment in the robot frame.
    pub fn increment(&self, ackermann: &AckermannParams) -> Pose2 {
        match self {
            Motion::Odometry(d) => Pose2::new(d[0], d[1], d[2]),
            Motion::Velocity(segs) => segs.iter().fold(Pose2::default(), |acc, s| {
                acc.compose(&velocity_increment(s[0], s[1], s[2]))
            }),
            Motion::Ackermann(segs) => segs.iter().fold(Pose2::default(), |acc, s| {
                acc.compose(&ackermann.increment(s[0], s[1], s[2]))
            }),
        }
    }
}

/// Exact integration of constant (v, w) over dt, from the origin.
#[inline]
pub fn velocity_increment(v: f64, w: f64, dt: f64) -> Pose2 {
    let th = w * dt;
    if th.abs() < 1e-9 {
        // Second order in th keeps the chord direction right for tiny turns.
        let d = v * dt;
        Pose2::new(d * (1.0 - th * th / 6.0), d * th / 2.0, th)
    } else {
        let r = v / w;
        Pose2::new(r * math::sin(th), r * (1.0 - math::cos(th)), th)
    }
}

/// An increment as odometry scales `[distance, rotation]` see it: `(d dx, d dy, r dθ)`,
/// first order in the scale error of an arc. The filter's odometry calibration and the
/// simulator's biased odometry both use it.
#[inline]
pub fn scale_increment(inc: &Pose2, [d, r]: [f64; 2]) -> Pose2 {
    Pose2::new(d * inc.x, d * inc.y, r * inc.theta)
}

/// Vehicle constants of the Ackermann model. Defaults are the Victoria Park utility car
/// (Guivant and Nebot 2000): the pose tracked is the laser's position.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AckermannParams {
    /// Wheel base L [m]. Default 2.83.
    pub wheel_base: f64,
    /// Lateral offset H of the speed encoder from the centre line [m]. Default 0.76.
    pub encoder_offset: f64,
    /// Laser position ahead of the rear axle a [m]. Default 3.78.
    pub sensor_forward: f64,
    /// Laser position left of the centre line b [m]. Default 0.50.
    pub sensor_left: f64,
}

impl Default for AckermannParams {
    fn default() -> Self {
        Self::VICTORIA_PARK
    }
}

impl AckermannParams {
    pub const VICTORIA_PARK: AckermannParams = AckermannParams {
        wheel_base: 2.83,
        encoder_offset: 0.76,
        sensor_forward: 3.78,
        sensor_left: 0.50,
    };

    fn derivative(&self, vc: f64, tan_s: f64, phi: f64) -> [f64; 3] {
        let (s, c) = math::sin_cos(phi);
        let k = tan_s / self.wheel_base;
        [
            vc * (c - k * (self.sensor_forward * s + self.sensor_left * c)),
            vc * (s + k * (self.sensor_forward * c - self.sensor_left * s)),
            vc * k,
        ]
    }

    /// Integrates one segment (encoder speed, steering, dt) from the origin with RK4.
    pub fn increment(&self, speed: f64, steering: f64, dt: f64) -> Pose2 {
        let tan_s = math::tan(steering);
        let vc = speed / (1.0 - tan_s * self.encoder_offset / self.wheel_base);
        let (mut x, mut y, mut phi) = (0.0, 0.0, 0.0);
        // Steps of at most 50 ms keep RK4 far below the sensor noise.
        let n = ((dt / 0.05).ceil() as usize).max(1);
        let h = dt / n as f64;
        for _ in 0..n {
            let k1 = self.derivative(vc, tan_s, phi);
            let k2 = self.derivative(vc, tan_s, phi + 0.5 * h * k1[2]);
            let k3 = self.derivative(vc, tan_s, phi + 0.5 * h * k2[2]);
            let k4 = self.derivative(vc, tan_s, phi + h * k3[2]);
            x += h / 6.0 * (k1[0] + 2.0 * k2[0] + 2.0 * k3[0] + k4[0]);
            y += h / 6.0 * (k1[1] + 2.0 * k2[1] + 2.0 * k3[1] + k4[1]);
            phi += h / 6.0 * (k1[2] + 2.0 * k2[2] + 2.0 * k3[2] + k4[2]);
        }
        Pose2::new(x, y, phi)
    }
}

/// Motion noise, as standard deviations that scale with distance, rotation and time.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct MotionNoise {
    /// Longitudinal std per metre travelled [m/m]. Default 0.05. Raise for slipping wheels.
    pub trans_per_m: f64,
    /// Lateral std per metre travelled [m/m]. Default 0.02.
    pub lateral_per_m: f64,
    /// Heading std per radian turned [rad/rad]. Default 0.05.
    pub rot_per_rad: f64,
    /// Heading std per metre travelled [rad/m]. Default 0.02.
    pub rot_per_m: f64,
    /// Position random walk [m/sqrt(s)]. Default 0.01. Covers time-stamping jitter and slip.
    pub trans_per_sqrt_s: f64,
    /// Heading random walk [rad/sqrt(s)]. Default 0.01.
    pub rot_per_sqrt_s: f64,
    /// Longest time [s] one record's random walk covers. Default 1.0. A record that follows
    /// a long silence (a paused robot, a gap in the log, the first record long after the
    /// run's start) adds at most this much random-walk noise: the walk models jitter and
    /// slip while moving, which the record's own motion bounds, not the length of the gap.
    pub random_walk_max_dt: f64,
}

impl Default for MotionNoise {
    fn default() -> Self {
        Self {
            trans_per_m: 0.05,
            lateral_per_m: 0.02,
            rot_per_rad: 0.05,
            rot_per_m: 0.02,
            trans_per_sqrt_s: 0.01,
            rot_per_sqrt_s: 0.01,
            random_walk_max_dt: 1.0,
        }
    }
}

impl MotionNoise {
    pub fn validate(&self) -> Result<(), String> {
        let fields = [
            ("trans_per_m", self.trans_per_m),
            ("lateral_per_m", self.lateral_per_m),
            ("rot_per_rad", self.rot_per_rad),
            ("rot_per_m", self.rot_per_m),
            ("trans_per_sqrt_s", self.trans_per_sqrt_s),
            ("rot_per_sqrt_s", self.rot_per_sqrt_s),
            ("random_walk_max_dt", self.random_walk_max_dt),
        ];
        for (name, v) in fields {
            if !(v.is_finite() && v >= 0.0) {
                return Err(format!(
                    "motion_noise.{name} must be a finite number >= 0, got {v}"
                ));
            }
        }
        Ok(())
    }

    /// Variances of (longitudinal, lateral, heading) noise of `inc` over `dt` seconds (the
    /// random walk over at most `random_walk_max_dt` of them).
    #[inline]
    pub fn variances(&self, inc: &Pose2, dt: f64) -> [f64; 3] {
        let d = math::hypot(inc.x, inc.y);
        let dt = dt.clamp(0.0, self.random_walk_max_dt);
        let rw_t = self.trans_per_sqrt_s * self.trans_per_sqrt_s * dt;
        [
            (self.trans_per_m * d).powi(2) + rw_t,
            (self.lateral_per_m * d).powi(2) + rw_t,
            (self.rot_per_rad * inc.theta).powi(2)
                + (self.rot_per_m * d).powi(2)
                + self.rot_per_sqrt_s * self.rot_per_sqrt_s * dt,
        ]
    }

    /// World-frame covariance of the new pose `prev ⊕ (inc + e)`.
    pub fn world_covariance(&self, prev: &Pose2, inc: &Pose2, dt: f64) -> Matrix3<f64> {
        covariance_in_world(prev, &self.variances(inc, dt))
    }
}

/// `J diag(var) Jᵀ`: the world-frame covariance of `prev ⊕ (inc + e)` for increment noise
/// `e` with the given (longitudinal, lateral, heading) variances.
#[inline]
pub fn covariance_in_world(prev: &Pose2, var: &[f64; 3]) -> Matrix3<f64> {
    covariance_in_world_sc(math::sin_cos(prev.theta), var)
}

/// [`covariance_in_world`] given the sine and cosine of the previous heading.
///
/// `J D Jᵀ` for the rotation `J = [[c, -s, 0], [s, c, 0], [0, 0, 1]]` and `D = diag(var)`,
/// written out: [`crate::linalg::sandwich`]'s products in its order without those by the
/// exact zeros and ones of `J` and `D` (a filter takes one per particle and record), so the
/// same value; only the sign of an entry that is zero may differ (the zero entries are +0).
#[inline]
pub fn covariance_in_world_sc((s, c): (f64, f64), var: &[f64; 3]) -> Matrix3<f64> {
    // The rows of J·D.
    let (a0, a1) = (c * var[0], -s * var[1]);
    let (b0, b1) = (s * var[0], c * var[1]);
    Matrix3::new(
        a0 * c + a1 * -s,
        a0 * s + a1 * c,
        0.0,
        b0 * c + b1 * -s,
        b0 * s + b1 * c,
        0.0,
        0.0,
        0.0,
        var[2],
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::linalg::testing::{entry, same_but_zero_sign};
    use nalgebra::Vector3;
    use proptest::prelude::*;
    use std::f64::consts::PI;

    proptest! {
        /// The written-out `J D Jᵀ` is the generic product's value, entry for entry.
        #[test]
        fn covariance_in_world_is_the_full_product(
            theta in prop_oneof![Just(0.0), -4.0..4.0f64], var in proptest::array::uniform3(entry()),
        ) {
            let (s, c) = math::sin_cos(theta);
            let j = Matrix3::new(c, -s, 0.0, s, c, 0.0, 0.0, 0.0, 1.0);
            let full = crate::linalg::sandwich(&j, &Matrix3::from_diagonal(&Vector3::from(var)));
            let got = covariance_in_world_sc((s, c), &var);
            for (x, y) in full.iter().zip(got.iter()) {
                prop_assert!(same_but_zero_sign(*x, *y), "{full} against {got}");
            }
        }
    }

    #[test]
    fn velocity_straight_and_quarter_circle() {
        let p = velocity_increment(1.0, 0.0, 2.0);
        assert!((p.x - 2.0).abs() < 1e-12 && p.y.abs() < 1e-12 && p.theta == 0.0);
        // Quarter circle of radius 1: v = 1, w = 1, dt = pi/2 ends at (1, 1), facing +y.
        let q = velocity_increment(1.0, 1.0, PI / 2.0);
        assert!((q.x - 1.0).abs() < 1e-12 && (q.y - 1.0).abs() < 1e-12);
        assert!((q.theta - PI / 2.0).abs() < 1e-12);
    }

    #[test]
    fn velocity_segments_compose() {
        let m = Motion::Velocity(vec![[1.0, 1.0, PI / 4.0], [1.0, 1.0, PI / 4.0]]);
        let q = m.increment(&AckermannParams::default());
        assert!((q.x - 1.0).abs() < 1e-12 && (q.y - 1.0).abs() < 1e-12);
    }

    #[test]
    fn tiny_turn_is_continuous() {
        let a = velocity_increment(1.0, 1e-10, 1.0);
        let b = velocity_increment(1.0, 1e-6, 1.0);
        assert!((a.x - b.x).abs() < 1e-9 && (a.y - b.y).abs() < 1e-6);
    }

    #[test]
    fn ackermann_straight_and_turn() {
        let p = AckermannParams::VICTORIA_PARK;
        let s = p.increment(2.0, 0.0, 3.0);
        assert!((s.x - 6.0).abs() < 1e-9 && s.y.abs() < 1e-12 && s.theta == 0.0);
        // Heading rate is v_c / L * tan(steer), with v_c = v_e / (1 - tan(steer) H / L).
        let steer: f64 = 0.1;
        let t = p.increment(2.0, steer, 1.0);
        let vc = 2.0 / (1.0 - math::tan(steer) * 0.76 / 2.83);
        assert!((t.theta - vc / 2.83 * math::tan(steer)).abs() < 1e-9);
        // Turning left moves the laser (ahead of the axle) to the left.
        assert!(t.y > 0.0);
    }

    #[test]
    fn random_walk_is_capped_per_record() {
        let n = MotionNoise::default();
        let inc = Pose2::new(0.1, 0.0, 0.0);
        assert_eq!(
            n.variances(&inc, 1e12),
            n.variances(&inc, n.random_walk_max_dt)
        );
        assert!(n.variances(&inc, 0.5)[0] < n.variances(&inc, 1.0)[0]);
    }

    #[test]
    fn noise_grows_with_distance_and_time() {
        let n = MotionNoise::default();
        let z = n.variances(&Pose2::default(), 0.0);
        assert_eq!(z, [0.0, 0.0, 0.0]);
        let a = n.variances(&Pose2::new(1.0, 0.0, 0.0), 0.0);
        let b = n.variances(&Pose2::new(2.0, 0.0, 0.0), 1.0);
        assert!(b.iter().zip(a.iter()).all(|(b, a)| b > a));
        let r = n.world_covariance(
            &Pose2::new(0.0, 0.0, PI / 2.0),
            &Pose2::new(1.0, 0.0, 0.0),
            0.0,
        );
        // Facing +y the longitudinal variance lands on y.
        assert!((r[(1, 1)] - a[0]).abs() < 1e-12 && (r[(0, 0)] - a[1]).abs() < 1e-12);
    }

    #[test]
    fn motion_validation() {
        assert!(
            Motion::Velocity(vec![[1.0, f64::NAN, 0.1]])
                .validate()
                .is_err()
        );
        assert!(Motion::Velocity(vec![[1.0, 0.0, -0.1]]).validate().is_err());
        assert!(Motion::Odometry([1.0, 0.0, -0.1]).validate().is_ok());
    }
}
