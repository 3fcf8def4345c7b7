//! A deterministic multi-robot simulator that writes observation logs with their ground truth.
//!
//! Robots drive smooth paths in a rectangular arena `[0, W] x [0, H]` (by default the
//! 17 m x 10.5 m environment of the FastSLAM-MLP paper) among point landmarks, and report
//! what a real robot would post to the server: the commands they executed, the landmarks
//! they saw and the robots they sighted.
//!
//! # Paths
//!
//! Each robot starts at a known pose (an exact [`RobotStart`] at `t0 = 0`): robot `i`
//! (0-based) starts at the `i`-th point of the R2 low-discrepancy sequence,
//!
//! ```text
//! (u, v) = frac(0.5 + i / g, 0.5 + i / g^2),  g = 1.3247... (the plastic number)
//! ```
//!
//! mapped into the arena minus a margin, facing the arena's centre, so robots are spread
//! out whatever their number. It then follows random waypoints (drawn inside the margin)
//! with a proportional heading controller evaluated every `control_period`:
//!
//! ```text
//! e = wrap(atan2(wy - y, wx - x) - theta)
//! w = clamp(1.5 e, -0.8, 0.8) rad/s
//! v = speed (0.2 + 0.4 (1 + cos e))
//! ```
//!
//! which bounds the turn rate and slows down for sharp turns, keeping turning radii well
//! below the 1 m margin at the default speed.
//!
//! # Motion and its noise
//!
//! Within one record of `record_period` seconds the commands form `n` segments
//! `(v, w, dt)` with `n = ceil(record_period / control_period)` and `dt = record_period / n`;
//! the log reports them as [`Motion::Velocity`] (or, for the odometry model, their
//! composed increment as [`Motion::Odometry`]). The robot's TRUE motion follows the filter's
//! noise model exactly (see [`fleetslam_core::motion`]): with `inc` the deterministic
//! increment of the commands in the robot frame,
//!
//! ```text
//! x_k = x_{k-1} ⊕ (inc + e),   e ~ N(0, diag(var_long, var_lat, var_theta))
//! ```
//!
//! with the variances of [`MotionNoise::variances`]`(inc, record_period)` for
//! `true_motion_noise`, so the log's commands plus that noise model are statistically right.
//!
//! # Observations
//!
//! At each record time a robot observes every landmark inside its sensor wedge (planar
//! distance `<= max_range` and `|bearing| <= fov / 2`, judged on the true poses):
//!
//! ```text
//! range_bearing_2d:  z = [r + N(0, s_r^2), wrap(b + N(0, s_b^2))]
//! point3d:           z = [dx, dy, dz] + N(0, diag(s_x^2, s_y^2, s_z^2))   (robot frame)
//! ```
//!
//! and sights every other robot within `sighting_range` and the same field of view, as a
//! range-bearing measurement with the range and bearing noise of `true_sensor_noise`. A
//! noisy range that comes out `<= 0` (only possible with huge noise) drops the observation.
//!
//! # Determinism
//!
//! The same config gives the same log byte for byte. All randomness comes from
//! [`ChaCha8Rng`] seeded with `seed`, on separate streams: stream 0 places landmarks and,
//! for robot `i`, streams `1 + 4i + {0, 1, 2, 3}` draw its waypoints, its motion noise, its
//! landmark measurement noise and its sighting noise. Adding a robot therefore leaves the
//! other robots' paths, motion and landmark measurements unchanged (only the sightings
//! change, since there is one more robot to see).

use crate::formats::{LandmarkRow, TrajectoryPoint, Truth};
use fleetslam_core::log::{
    LOG_VERSION, LandmarkObservation, Log, LogHeader, Record, RobotSighting, RobotStart,
    SensorRange, record_order,
};
use fleetslam_core::math;
use fleetslam_core::motion::{
    AckermannParams, Motion, MotionModel, MotionNoise, scale_increment, velocity_increment,
};
use fleetslam_core::pose::{Pose2, PoseGaussian, wrap_angle};
use fleetslam_core::rng::StandardNormal;
use fleetslam_core::sensor::{LandmarkKind, SensorNoise};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use std::f64::consts::PI;

/// Maximum turn rate of the waypoint controller (rad/s).
const MAX_TURN_RATE: f64 = 0.8;
/// Proportional gain of the heading controller (1/s).
const HEADING_GAIN: f64 = 1.5;
/// A waypoint closer than this is reached (m).
const WAYPOINT_REACHED: f64 = 0.5;
/// Waypoints are drawn at least this far from the robot when possible (m).
const MIN_WAYPOINT_DISTANCE: f64 = 2.0;
/// A waypoint not reached after this long is replaced (s).
const WAYPOINT_TIMEOUT: f64 = 60.0;
/// Smallest suggested measurement noise written to the header (std in m or rad), so that a
/// noise-free simulation still gives the filter a valid model.
const MIN_SUGGESTED_SENSOR_STD: f64 = 1e-3;
/// Upper bounds that keep a mistyped config from allocating the machine away.
const MAX_ROBOTS: usize = 10_000;
const MAX_LANDMARKS: usize = 1_000_000;
const MAX_RECORDS: f64 = 10_000_000.0;
const MAX_SEGMENTS: f64 = 100_000_000.0;

/// What to simulate. Every field has a default (see [`SimConfig::default`]), so a JSON
/// config only needs the fields it changes.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SimConfig {
    /// Number of robots, named "1", "2", ... Default 3.
    pub robots: usize,
    /// Number of randomly placed landmarks (ignored when `landmark_positions` is set).
    /// Default 20.
    pub landmarks: usize,
    /// Kind of landmark and measurement. Default range-bearing 2D.
    pub kind: LandmarkKind,
    /// Velocity segments or odometry increments (Ackermann is not simulated).
    /// Default velocity.
    pub motion_model: MotionModel,
    /// Length of the run (s). Default 60.
    pub duration: f64,
    /// Time between two records of a robot (s). Default 0.2.
    pub record_period: f64,
    /// Time between two velocity commands within a record (s), shortened if needed so that
    /// a whole number of segments fills each record. Default 0.05.
    pub control_period: f64,
    /// Arena size `[W, H]` (m): the arena is `[0, W] x [0, H]`. Default `[17.0, 10.5]`.
    pub arena: [f64; 2],
    /// Cruise speed (m/s). Default 0.4.
    pub speed: f64,
    /// Noise of the true motion around the commands. Default [`MotionNoise::default`].
    pub true_motion_noise: MotionNoise,
    /// Noise of landmark measurements and robot sightings (standard deviations >= 0).
    /// Default [`SensorNoise::default`].
    pub true_sensor_noise: SensorNoise,
    /// The sensor's wedge. Default 6 m and 180 degrees (the paper's stereo camera).
    pub sensor_range: SensorRange,
    /// Robots sight each other within this range and the field of view (m); 0 disables
    /// sightings. Default 5.
    pub sighting_range: f64,
    /// Whether observations carry landmark ids. Default true.
    pub with_ids: bool,
    /// Seed of every random draw. Default 1.
    pub seed: u64,
    /// Explicit landmark positions `[x, y, z]` (z is ignored in 2D); they override random
    /// placement. Default none.
    pub landmark_positions: Option<Vec<[f64; 3]>>,
    /// Range of landmark heights `[z_min, z_max]` for random 3D landmarks (m).
    /// Default `[0.2, 2.0]`.
    pub landmark_height: [f64; 2],
    /// Systematic odometry error `[distance, rotation]`: the robot truly moves
    /// `(d·dx, d·dy, r·dθ)` of each commanded increment (worn wheels, a track width off its
    /// nominal value), before the noise; the log keeps the commands. Default `[1, 1]`.
    pub odometry_scale: [f64; 2],
    /// The smallest distance between distinct landmarks that the log's header suggests to
    /// the filter (`LogHeader::landmark_separation`; unknown association). Default none
    /// (the filter's default).
    pub landmark_separation: Option<f64>,
}

impl Default for SimConfig {
    fn default() -> Self {
        Self {
            robots: 3,
            landmarks: 20,
            kind: LandmarkKind::RangeBearing2d,
            motion_model: MotionModel::Velocity,
            duration: 60.0,
            record_period: 0.2,
            control_period: 0.05,
            arena: [17.0, 10.5],
            speed: 0.4,
            true_motion_noise: MotionNoise::default(),
            true_sensor_noise: SensorNoise::default(),
            sensor_range: SensorRange {
                max_range: 6.0,
                fov: PI,
            },
            sighting_range: 5.0,
            with_ids: true,
            seed: 1,
            landmark_positions: None,
            landmark_height: [0.2, 2.0],
            odometry_scale: [1.0, 1.0],
            landmark_separation: None,
        }
    }
}

impl SimConfig {
    /// The high-control-noise scenario of the FastSLAM 2.0 consistency check: one robot among
    /// 38 landmarks that it sees all at once (20 m range, all around), records at 10 Hz with
    /// one control each, speed noise 0.5 m/s and turn-rate noise 10 deg/s (as random walks
    /// of 0.5·√0.1 m/√s and 10°·√0.1 /√s over each 0.1 s record), and an accurate sensor
    /// (0.3 m, 2 deg).
    pub fn high_control_noise(seed: u64, duration: f64) -> SimConfig {
        let dt: f64 = 0.1;
        SimConfig {
            robots: 1,
            landmarks: 38,
            duration,
            record_period: dt,
            control_period: dt,
            true_motion_noise: MotionNoise {
                trans_per_m: 0.0,
                lateral_per_m: 0.0,
                rot_per_rad: 0.0,
                rot_per_m: 0.0,
                trans_per_sqrt_s: 0.5 * dt.sqrt(),
                rot_per_sqrt_s: 10f64.to_radians() * dt.sqrt(),
                random_walk_max_dt: 1.0,
            },
            true_sensor_noise: SensorNoise {
                range: 0.3,
                bearing: 2f64.to_radians(),
                ..SensorNoise::default()
            },
            sensor_range: SensorRange {
                max_range: 20.0,
                fov: 2.0 * PI,
            },
            sighting_range: 0.0,
            seed,
            ..SimConfig::default()
        }
    }
}

/// An invalid simulator configuration.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SimError {
    #[error("invalid simulator config: {0}")]
    Config(String),
}

fn config_error(message: impl Into<String>) -> SimError {
    SimError::Config(message.into())
}

fn check(ok: bool, message: impl FnOnce() -> String) -> Result<(), SimError> {
    if ok {
        Ok(())
    } else {
        Err(SimError::Config(message()))
    }
}

impl SimConfig {
    /// Checks every field; the message names the field and the accepted values.
    pub fn validate(&self) -> Result<(), SimError> {
        check((1..=MAX_ROBOTS).contains(&self.robots), || {
            format!(
                "robots must be between 1 and {MAX_ROBOTS}, got {}",
                self.robots
            )
        })?;
        if self.motion_model == MotionModel::Ackermann {
            return Err(config_error(
                "motion_model \"ackermann\" is not simulated: use \"velocity\" or \"odometry\"",
            ));
        }
        let positive = |name: &str, v: f64| {
            check(v.is_finite() && v > 0.0, || {
                format!("{name} must be a finite number > 0, got {v}")
            })
        };
        positive("duration", self.duration)?;
        positive("record_period", self.record_period)?;
        positive("control_period", self.control_period)?;
        positive("arena[0]", self.arena[0])?;
        positive("arena[1]", self.arena[1])?;
        positive("sensor_range.max_range", self.sensor_range.max_range)?;
        check(self.record_period <= self.duration, || {
            format!(
                "record_period ({}) must not exceed duration ({}): the log would be empty",
                self.record_period, self.duration
            )
        })?;
        check(self.control_period <= self.record_period, || {
            format!(
                "control_period ({}) must not exceed record_period ({})",
                self.control_period, self.record_period
            )
        })?;
        let records = self.robots as f64 * (self.duration / self.record_period);
        check(records <= MAX_RECORDS, || {
            format!(
                "robots * duration / record_period = {records:.0} records is more than \
                 {MAX_RECORDS}: raise record_period or shorten duration"
            )
        })?;
        let segments = records * (self.record_period / self.control_period);
        check(segments <= MAX_SEGMENTS, || {
            format!(
                "robots * duration / control_period = {segments:.0} velocity segments is more \
                 than {MAX_SEGMENTS}: raise control_period"
            )
        })?;
        check(self.speed.is_finite() && self.speed >= 0.0, || {
            format!("speed must be a finite number >= 0, got {}", self.speed)
        })?;
        let fov = self.sensor_range.fov;
        check(fov.is_finite() && fov > 0.0 && fov <= 2.0 * PI, || {
            format!("sensor_range.fov must be in (0, 2 pi] radians, got {fov}")
        })?;
        check(
            self.sighting_range.is_finite() && self.sighting_range >= 0.0,
            || {
                format!(
                    "sighting_range must be a finite number >= 0 (0 disables sightings), got {}",
                    self.sighting_range
                )
            },
        )?;
        self.true_motion_noise
            .validate()
            .map_err(|e| config_error(format!("true_{e}")))?;
        check(
            self.odometry_scale
                .iter()
                .all(|s| s.is_finite() && (0.5..=1.5).contains(s)),
            || {
                format!(
                    "odometry_scale must hold two factors between 0.5 and 1.5, got {:?}",
                    self.odometry_scale
                )
            },
        )?;
        if let Some(s) = self.landmark_separation {
            check(s.is_finite() && s >= 0.0, || {
                format!("landmark_separation must be a finite distance >= 0 (m), got {s}")
            })?;
        }
        let n = &self.true_sensor_noise;
        for (name, v) in [
            ("range", n.range),
            ("bearing", n.bearing),
            ("xyz[0]", n.xyz[0]),
            ("xyz[1]", n.xyz[1]),
            ("xyz[2]", n.xyz[2]),
            ("range_per_m", n.range_per_m),
        ] {
            check(v.is_finite() && v >= 0.0, || {
                format!("true_sensor_noise.{name} must be a finite number >= 0, got {v}")
            })?;
        }
        let [lo, hi] = self.landmark_height;
        check(lo.is_finite() && hi.is_finite() && lo <= hi, || {
            format!("landmark_height must be finite with min <= max, got [{lo}, {hi}]")
        })?;
        if let Some(p) = &self.landmark_positions {
            check(p.len() <= MAX_LANDMARKS, || {
                format!(
                    "landmark_positions has {} entries, more than {MAX_LANDMARKS}",
                    p.len()
                )
            })?;
            if let Some(i) = p.iter().position(|m| m.iter().any(|v| !v.is_finite())) {
                return Err(config_error(format!(
                    "landmark_positions[{i}] = {:?} has a non-finite number",
                    p[i]
                )));
            }
        } else {
            check(self.landmarks <= MAX_LANDMARKS, || {
                format!(
                    "landmarks must be at most {MAX_LANDMARKS}, got {}",
                    self.landmarks
                )
            })?;
        }
        Ok(())
    }

    /// Number of records per robot: `floor(duration / record_period)`.
    pub fn records_per_robot(&self) -> usize {
        (self.duration / self.record_period + 1e-9).floor() as usize
    }

    /// Number of velocity segments per record: `ceil(record_period / control_period)`.
    pub fn segments_per_record(&self) -> usize {
        ((self.record_period / self.control_period - 1e-9).ceil() as usize).max(1)
    }

    /// The id of robot `i` (0-based) in the log and the truth.
    pub fn robot_id(i: usize) -> String {
        (i + 1).to_string()
    }

    /// The margin kept between waypoints (and start poses) and the arena's walls (m).
    pub fn margin(&self) -> f64 {
        (0.1 * self.arena[0].min(self.arena[1])).min(1.0)
    }
}

/// A simulated run: the log the robots post and the ground truth to evaluate against.
#[derive(Debug, Clone, PartialEq)]
pub struct Simulated {
    pub log: Log,
    pub truth: Truth,
}

/// A generator on its own ChaCha8 stream of `seed`.
fn stream(seed: u64, stream: u64) -> ChaCha8Rng {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    rng.set_stream(stream);
    rng
}

/// Which stream robot `robot` (0-based) uses for `purpose` (0 path, 1 motion, 2 landmarks,
/// 3 sightings).
fn robot_stream(seed: u64, robot: usize, purpose: u64) -> ChaCha8Rng {
    stream(seed, 1 + 4 * robot as u64 + purpose)
}

fn normal(rng: &mut ChaCha8Rng) -> f64 {
    rng.sample::<f64, _>(StandardNormal)
}

/// `n` landmarks placed uniformly in the arena `[0, W] x [0, H]` with heights uniform in
/// `[height[0], height[1]]`, drawn from stream 0 of `seed` (the stream [`simulate`] uses).
pub fn random_landmarks(n: usize, arena: [f64; 2], height: [f64; 2], seed: u64) -> Vec<[f64; 3]> {
    let mut rng = stream(seed, 0);
    (0..n)
        .map(|_| {
            let x = rng.random::<f64>() * arena[0];
            let y = rng.random::<f64>() * arena[1];
            let z = height[0] + rng.random::<f64>() * (height[1] - height[0]);
            [x, y, z]
        })
        .collect()
}

/// The start pose of robot `i` (0-based): the R2 sequence in the arena minus the margin,
/// facing the arena's centre.
fn start_pose(cfg: &SimConfig, i: usize) -> Pose2 {
    const G: f64 = 1.324_717_957_244_746; // the plastic number
    let (a1, a2) = (1.0 / G, 1.0 / (G * G));
    let u = (0.5 + a1 * i as f64).fract();
    let v = (0.5 + a2 * i as f64).fract();
    let m = cfg.margin();
    let x = m + u * (cfg.arena[0] - 2.0 * m);
    let y = m + v * (cfg.arena[1] - 2.0 * m);
    let (cx, cy) = (0.5 * cfg.arena[0], 0.5 * cfg.arena[1]);
    let theta = if math::hypot(cx - x, cy - y) < 1e-9 {
        0.0
    } else {
        math::atan2(cy - y, cx - x)
    };
    Pose2::new(x, y, theta)
}

/// Waypoint follower of one robot.
struct Driver {
    rng: ChaCha8Rng,
    lo: [f64; 2],
    hi: [f64; 2],
    speed: f64,
    waypoint: [f64; 2],
    since: f64,
}

impl Driver {
    fn new(cfg: &SimConfig, robot: usize, start: &Pose2) -> Self {
        let m = cfg.margin();
        let mut d = Driver {
            rng: robot_stream(cfg.seed, robot, 0),
            lo: [m, m],
            hi: [cfg.arena[0] - m, cfg.arena[1] - m],
            speed: cfg.speed,
            waypoint: [start.x, start.y],
            since: 0.0,
        };
        d.next_waypoint(start);
        d
    }

    /// Draws a waypoint inside the margin, at least [`MIN_WAYPOINT_DISTANCE`] away when the
    /// arena allows it (a bounded number of tries keeps tiny arenas working).
    fn next_waypoint(&mut self, from: &Pose2) {
        let min_dist = MIN_WAYPOINT_DISTANCE
            .min(0.5 * math::hypot(self.hi[0] - self.lo[0], self.hi[1] - self.lo[1]));
        for _ in 0..32 {
            let x = self.lo[0] + self.rng.random::<f64>() * (self.hi[0] - self.lo[0]);
            let y = self.lo[1] + self.rng.random::<f64>() * (self.hi[1] - self.lo[1]);
            self.waypoint = [x, y];
            if math::hypot(x - from.x, y - from.y) >= min_dist {
                break;
            }
        }
        self.since = 0.0;
    }

    /// The command `(v, w)` for the next `dt` seconds from `pose`.
    fn command(&mut self, pose: &Pose2, dt: f64) -> (f64, f64) {
        let reached =
            math::hypot(self.waypoint[0] - pose.x, self.waypoint[1] - pose.y) < WAYPOINT_REACHED;
        if reached || self.since > WAYPOINT_TIMEOUT {
            self.next_waypoint(pose);
        }
        self.since += dt;
        let bearing = math::atan2(self.waypoint[1] - pose.y, self.waypoint[0] - pose.x);
        let e = wrap_angle(bearing - pose.theta);
        let w = (HEADING_GAIN * e).clamp(-MAX_TURN_RATE, MAX_TURN_RATE);
        let v = self.speed * (0.2 + 0.4 * (1.0 + math::cos(e)));
        (v, w)
    }
}

/// One robot's true poses at `t0` and every record time, with the motion it reported.
struct RobotRun {
    id: String,
    poses: Vec<Pose2>,
    motions: Vec<Motion>,
}

fn drive(cfg: &SimConfig, robot: usize) -> RobotRun {
    let n_rec = cfg.records_per_robot();
    let n_seg = cfg.segments_per_record();
    let seg_dt = cfg.record_period / n_seg as f64;
    let start = start_pose(cfg, robot);
    let mut driver = Driver::new(cfg, robot, &start);
    let mut noise_rng = robot_stream(cfg.seed, robot, 1);
    let mut poses = Vec::with_capacity(n_rec + 1);
    let mut motions = Vec::with_capacity(n_rec);
    poses.push(start);
    let mut pose = start;
    for _ in 0..n_rec {
        // The controller acts on the nominal path from the current true pose.
        let mut nominal = pose;
        let mut segments = Vec::with_capacity(n_seg);
        for _ in 0..n_seg {
            let (v, w) = driver.command(&nominal, seg_dt);
            segments.push([v, w, seg_dt]);
            nominal = nominal.compose(&velocity_increment(v, w, seg_dt));
        }
        let velocity = Motion::Velocity(segments);
        let inc = velocity.increment(&AckermannParams::default());
        let var = cfg.true_motion_noise.variances(&inc, cfg.record_period);
        // Always three draws, so the stream stays aligned whatever the noise levels.
        let e: [f64; 3] = std::array::from_fn(|k| var[k].sqrt() * normal(&mut noise_rng));
        let true_inc = scale_increment(&inc, cfg.odometry_scale);
        pose = pose.compose(&Pose2::new(
            true_inc.x + e[0],
            true_inc.y + e[1],
            true_inc.theta + e[2],
        ));
        motions.push(match cfg.motion_model {
            MotionModel::Odometry => Motion::Odometry([inc.x, inc.y, inc.theta]),
            _ => velocity,
        });
        poses.push(pose);
    }
    RobotRun {
        id: SimConfig::robot_id(robot),
        poses,
        motions,
    }
}

/// Planar range and bearing of `(x, y)` from `pose`, when inside the wedge.
fn in_wedge(pose: &Pose2, x: f64, y: f64, max_range: f64, fov: f64) -> Option<(f64, f64)> {
    let r = math::hypot(x - pose.x, y - pose.y);
    if !(r > 1e-6 && r <= max_range) {
        return None;
    }
    let b = wrap_angle(math::atan2(y - pose.y, x - pose.x) - pose.theta);
    (b.abs() <= 0.5 * fov).then_some((r, b))
}

fn observe_landmarks(
    cfg: &SimConfig,
    pose: &Pose2,
    landmarks: &[[f64; 3]],
    rng: &mut ChaCha8Rng,
) -> Vec<LandmarkObservation> {
    let noise = &cfg.true_sensor_noise;
    let SensorRange { max_range, fov } = cfg.sensor_range;
    let mut out = Vec::new();
    for (i, m) in landmarks.iter().enumerate() {
        let Some((r, b)) = in_wedge(pose, m[0], m[1], max_range, fov) else {
            continue;
        };
        let z = match cfg.kind {
            LandmarkKind::RangeBearing2d => {
                let r = r + noise.range_std_at(r) * normal(rng);
                let b = wrap_angle(b + noise.bearing * normal(rng));
                if r <= 0.0 {
                    continue;
                }
                vec![r, b]
            }
            LandmarkKind::Point3d => {
                let (s, c) = math::sin_cos(pose.theta);
                let (dx, dy) = (m[0] - pose.x, m[1] - pose.y);
                let local = [c * dx + s * dy, -s * dx + c * dy, m[2]];
                local
                    .iter()
                    .zip(noise.xyz)
                    .map(|(v, sd)| v + sd * normal(rng))
                    .collect()
            }
        };
        out.push(LandmarkObservation {
            id: cfg.with_ids.then_some(i as u32 + 1),
            z,
        });
    }
    out
}

fn sight_robots(
    cfg: &SimConfig,
    me: usize,
    k: usize,
    runs: &[RobotRun],
    rng: &mut ChaCha8Rng,
) -> Vec<RobotSighting> {
    if cfg.sighting_range <= 0.0 {
        return Vec::new();
    }
    let pose = runs[me].poses[k];
    let noise = &cfg.true_sensor_noise;
    let mut out = Vec::new();
    for (j, other) in runs.iter().enumerate() {
        if j == me {
            continue;
        }
        let p = other.poses[k];
        let Some((r, b)) = in_wedge(&pose, p.x, p.y, cfg.sighting_range, cfg.sensor_range.fov)
        else {
            continue;
        };
        let r = r + noise.range * normal(rng);
        let b = wrap_angle(b + noise.bearing * normal(rng));
        if r > 0.0 {
            out.push(RobotSighting {
                robot: other.id.clone(),
                z: vec![r, b],
            });
        }
    }
    out
}

/// The header's suggested sensor noise: the true noise, floored so that it validates.
fn suggested(noise: &SensorNoise) -> SensorNoise {
    let f = |v: f64| v.max(MIN_SUGGESTED_SENSOR_STD);
    SensorNoise {
        range: f(noise.range),
        bearing: f(noise.bearing),
        xyz: noise.xyz.map(f),
        range_per_m: noise.range_per_m,
    }
}

/// Simulates a run. The log's records are in [`record_order`] with `seq` from 0 per robot;
/// the truth holds every robot's true pose at `t0 = 0` and at each record time, and the
/// landmarks with ids `1..=n` (the ids the log uses when `with_ids`).
pub fn simulate(cfg: &SimConfig) -> Result<Simulated, SimError> {
    cfg.validate()?;
    let mut landmarks = match &cfg.landmark_positions {
        Some(p) => p.clone(),
        None => random_landmarks(cfg.landmarks, cfg.arena, cfg.landmark_height, cfg.seed),
    };
    if cfg.kind == LandmarkKind::RangeBearing2d {
        for m in &mut landmarks {
            m[2] = 0.0;
        }
    }

    let runs: Vec<RobotRun> = (0..cfg.robots).map(|i| drive(cfg, i)).collect();
    let n_rec = cfg.records_per_robot();
    // Record times are rounded to the nanosecond so that logs read 0.6, not 0.6000000000000001.
    let time = |k: usize| (k as f64 * cfg.record_period * 1e9).round() / 1e9;

    let mut records = Vec::with_capacity(cfg.robots * n_rec);
    for (i, run) in runs.iter().enumerate() {
        let mut lm_rng = robot_stream(cfg.seed, i, 2);
        let mut sight_rng = robot_stream(cfg.seed, i, 3);
        for (k, motion) in run.motions.iter().enumerate() {
            let pose = run.poses[k + 1];
            records.push(Record {
                robot: run.id.clone(),
                seq: k as u64,
                t: time(k + 1),
                motion: Some(motion.clone()),
                landmarks: observe_landmarks(cfg, &pose, &landmarks, &mut lm_rng),
                robots: sight_robots(cfg, i, k + 1, &runs, &mut sight_rng),
            });
        }
    }
    records.sort_by(record_order);

    let sensor_noise = suggested(&cfg.true_sensor_noise);
    let header = LogHeader {
        fleetslam_log: LOG_VERSION,
        name: Some("sim".into()),
        landmark_kind: cfg.kind,
        motion_model: cfg.motion_model,
        ackermann: None,
        motion_noise: Some(cfg.true_motion_noise),
        odometry_calibration: None,
        sensor_noise: Some(sensor_noise),
        sighting_noise: (cfg.sighting_range > 0.0).then_some(sensor_noise),
        sensor_range: Some(cfg.sensor_range),
        landmark_separation: cfg.landmark_separation,
        landmark_ids: cfg.with_ids,
        truth_frame: true,
        robots: runs
            .iter()
            .map(|r| RobotStart {
                id: r.id.clone(),
                start: Some(PoseGaussian::exact(r.poses[0])),
                t0: Some(0.0),
            })
            .collect(),
    };

    let truth = Truth {
        trajectories: runs
            .iter()
            .map(|r| {
                let pts = r
                    .poses
                    .iter()
                    .enumerate()
                    .map(|(k, &pose)| TrajectoryPoint { t: time(k), pose })
                    .collect();
                (r.id.clone(), pts)
            })
            .collect(),
        landmarks: landmarks
            .iter()
            .enumerate()
            .map(|(i, &mean)| LandmarkRow {
                id: Some(i as u32 + 1),
                mean,
                cov: [0.0; 6],
            })
            .collect(),
    };
    Ok(Simulated {
        log: Log { header, records },
        truth,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn quiet() -> SimConfig {
        SimConfig {
            duration: 20.0,
            ..SimConfig::default()
        }
    }

    fn bytes(s: &Simulated) -> Vec<u8> {
        let mut buf = Vec::new();
        s.log.write(&mut buf).unwrap();
        buf
    }

    #[test]
    fn deterministic_by_seed() {
        let cfg = quiet();
        let a = simulate(&cfg).unwrap();
        let b = simulate(&cfg).unwrap();
        assert_eq!(bytes(&a), bytes(&b));
        assert_eq!(a.truth, b.truth);
        let c = simulate(&SimConfig { seed: 2, ..cfg }).unwrap();
        assert_ne!(bytes(&a), bytes(&c));
    }

    #[test]
    fn adding_a_robot_keeps_the_others() {
        let a = simulate(&quiet()).unwrap();
        let b = simulate(&SimConfig {
            robots: 4,
            ..quiet()
        })
        .unwrap();
        for id in ["1", "2", "3"] {
            assert_eq!(a.truth.trajectories[id], b.truth.trajectories[id]);
            let lm = |s: &Simulated| -> Vec<Vec<LandmarkObservation>> {
                s.log
                    .records
                    .iter()
                    .filter(|r| r.robot == id)
                    .map(|r| r.landmarks.clone())
                    .collect()
            };
            assert_eq!(lm(&a), lm(&b));
        }
    }

    #[test]
    fn records_validate_and_are_ordered() {
        for (kind, model) in [
            (LandmarkKind::RangeBearing2d, MotionModel::Velocity),
            (LandmarkKind::Point3d, MotionModel::Odometry),
        ] {
            let cfg = SimConfig {
                kind,
                motion_model: model,
                ..quiet()
            };
            let s = simulate(&cfg).unwrap();
            let h = &s.log.header;
            assert_eq!((h.landmark_kind, h.motion_model), (kind, model));
            assert_eq!(h.robots.len(), 3);
            assert_eq!(s.log.records.len(), 3 * 100);
            for r in &s.log.records {
                r.validate(h.landmark_kind, h.motion_model).unwrap();
            }
            assert!(
                s.log
                    .records
                    .windows(2)
                    .all(|w| record_order(&w[0], &w[1]).is_lt())
            );
            for id in ["1", "2", "3"] {
                let seqs: Vec<u64> = s
                    .log
                    .records
                    .iter()
                    .filter(|r| r.robot == id)
                    .map(|r| r.seq)
                    .collect();
                assert_eq!(seqs, (0..100).collect::<Vec<_>>());
            }
            // The log survives its own reader (serde_json may round floats by an ulp).
            let mut buf = Vec::new();
            s.log.write(&mut buf).unwrap();
            let back = Log::read(&buf[..]).unwrap();
            for (a, b) in back.header.robots.iter().zip(&h.robots) {
                let (a, b) = (a.start.unwrap().mean, b.start.unwrap().mean);
                assert!(a.distance(&b) < 1e-12);
            }
            assert_eq!(back.header.motion_noise, h.motion_noise);
            assert_eq!(back.records.len(), s.log.records.len());
            h.sensor_noise.unwrap().validate("sensor_noise").unwrap();
        }
    }

    #[test]
    fn point3d_measurements_have_three_numbers() {
        let s = simulate(&SimConfig {
            kind: LandmarkKind::Point3d,
            ..quiet()
        })
        .unwrap();
        let obs: Vec<_> = s.log.records.iter().flat_map(|r| &r.landmarks).collect();
        assert!(!obs.is_empty());
        assert!(obs.iter().all(|o| o.z.len() == 3));
        // Heights are the landmarks' (plus noise) and lie in the configured range.
        assert!(obs.iter().all(|o| o.z[2] > 0.0 && o.z[2] < 2.5));
        assert!(
            s.truth
                .landmarks
                .iter()
                .all(|l| (0.2..=2.0).contains(&l.mean[2]))
        );
    }

    /// Integrates each robot's logged commands from its start, each increment `(dx, dy, dθ)`
    /// taken as `(d dx, d dy, r dθ)` for `scale = [d, r]`, and checks every record's pose
    /// against the truth within `tol`; returns the distance each robot's commands cover.
    fn check_commands_against_truth(
        s: &Simulated,
        scale: [f64; 2],
        tol: f64,
        label: &str,
    ) -> Vec<f64> {
        let mut moved = Vec::new();
        for start in &s.log.header.robots {
            let truth = &s.truth.trajectories[&start.id];
            let mut pose = start.start.unwrap().mean;
            assert_eq!(pose, truth[0].pose);
            let mut distance = 0.0;
            for r in s.log.records.iter().filter(|r| r.robot == start.id) {
                let inc = r
                    .motion
                    .as_ref()
                    .unwrap()
                    .increment(&AckermannParams::default());
                pose = pose.compose(&Pose2::new(
                    scale[0] * inc.x,
                    scale[0] * inc.y,
                    scale[1] * inc.theta,
                ));
                distance += math::hypot(inc.x, inc.y);
                let k = r.seq as usize + 1;
                assert!((truth[k].t - r.t).abs() < 1e-12);
                let err = pose.distance(&truth[k].pose);
                assert!(err < tol, "{label} robot {} at t={}: {err}", start.id, r.t);
            }
            moved.push(distance);
        }
        moved
    }

    /// Integrating the logged commands without noise from the start stays near the truth;
    /// with zero true noise it lands exactly on it.
    #[test]
    fn commands_agree_with_truth() {
        for model in [MotionModel::Velocity, MotionModel::Odometry] {
            for (noise, tol) in [(MotionNoise::default(), 0.3), (zero_motion_noise(), 1e-9)] {
                let cfg = SimConfig {
                    motion_model: model,
                    true_motion_noise: noise,
                    duration: 10.0,
                    ..SimConfig::default()
                };
                let s = simulate(&cfg).unwrap();
                check_commands_against_truth(&s, [1.0, 1.0], tol, &format!("{model:?}"));
            }
        }
    }

    /// With an odometry scale the robot truly moves the scaled increments of its logged
    /// commands (exactly, without noise), and the log keeps the commands.
    #[test]
    fn odometry_scale_scales_the_true_motion() {
        let scale = [0.9, 1.1];
        let cfg = SimConfig {
            true_motion_noise: zero_motion_noise(),
            duration: 10.0,
            odometry_scale: scale,
            ..SimConfig::default()
        };
        let s = simulate(&cfg).unwrap();
        let plain = simulate(&SimConfig {
            odometry_scale: [1.0, 1.0],
            ..cfg.clone()
        })
        .unwrap();
        let moved = check_commands_against_truth(&s, scale, 1e-9, "scaled");
        assert!(moved.iter().all(|&d| d > 1.0), "{moved:?}");
        // The controller steers from the true pose, so the commands differ from the
        // unscaled run's, but the first record's do not.
        assert_eq!(s.log.records[0].motion, plain.log.records[0].motion);
    }

    /// The true motion and measurements scatter around the logged commands and the truth
    /// exactly as the filter's models say: normalised squared errors average to their
    /// dimension.
    #[test]
    fn noise_matches_the_filter_models() {
        let s = simulate(&SimConfig {
            duration: 60.0,
            ..SimConfig::default()
        })
        .unwrap();
        let noise = s.log.header.motion_noise.unwrap();
        let (mut motion_nees, mut n_motion) = (0.0, 0);
        let (mut sensor_nees, mut n_sensor) = (0.0, 0);
        for r in &s.log.records {
            let truth = &s.truth.trajectories[&r.robot];
            let (prev, pose) = (truth[r.seq as usize].pose, truth[r.seq as usize + 1].pose);
            let inc = r
                .motion
                .as_ref()
                .unwrap()
                .increment(&AckermannParams::default());
            let actual = pose.relative_to(&prev);
            let var = noise.variances(&inc, 0.2);
            let e = [
                actual.x - inc.x,
                actual.y - inc.y,
                wrap_angle(actual.theta - inc.theta),
            ];
            motion_nees += (0..3).map(|k| e[k] * e[k] / var[k]).sum::<f64>();
            n_motion += 1;
            for o in &r.landmarks {
                let m = s.truth.landmarks[o.id.unwrap() as usize - 1].mean;
                let (range, bearing) =
                    in_wedge(&pose, m[0], m[1], f64::INFINITY, 2.0 * PI).unwrap();
                let sn = &s.log.header.sensor_noise.unwrap();
                sensor_nees += ((o.z[0] - range) / sn.range).powi(2)
                    + (wrap_angle(o.z[1] - bearing) / sn.bearing).powi(2);
                n_sensor += 1;
            }
        }
        let motion_nees = motion_nees / n_motion as f64;
        let sensor_nees = sensor_nees / n_sensor as f64;
        // 900 motion samples: the mean of a chi-square(3) has std sqrt(6 / 900) = 0.08.
        assert!(
            (motion_nees - 3.0).abs() < 0.35,
            "motion NEES {motion_nees}"
        );
        assert!(
            (sensor_nees - 2.0).abs() < 0.15,
            "sensor NEES {sensor_nees} over {n_sensor}"
        );
    }

    fn zero_motion_noise() -> MotionNoise {
        MotionNoise {
            trans_per_m: 0.0,
            lateral_per_m: 0.0,
            rot_per_rad: 0.0,
            rot_per_m: 0.0,
            trans_per_sqrt_s: 0.0,
            rot_per_sqrt_s: 0.0,
            random_walk_max_dt: 0.0,
        }
    }

    #[test]
    fn landmarks_observed_only_inside_the_wedge() {
        let cfg = SimConfig {
            sensor_range: SensorRange {
                max_range: 3.0,
                fov: PI / 2.0,
            },
            ..quiet()
        };
        let s = simulate(&cfg).unwrap();
        let mut seen = 0;
        for r in &s.log.records {
            let pose = s.truth.trajectories[&r.robot][r.seq as usize + 1].pose;
            for o in &r.landmarks {
                let m = s.truth.landmarks[o.id.unwrap() as usize - 1].mean;
                let (range, bearing) =
                    in_wedge(&pose, m[0], m[1], f64::INFINITY, 2.0 * PI).unwrap();
                assert!(
                    range <= 3.0 && bearing.abs() <= PI / 4.0,
                    "{range} {bearing}"
                );
                seen += 1;
            }
            // And every landmark inside the wedge was observed.
            let inside = s
                .truth
                .landmarks
                .iter()
                .filter(|l| in_wedge(&pose, l.mean[0], l.mean[1], 3.0, PI / 2.0).is_some())
                .count();
            assert_eq!(inside, r.landmarks.len());
        }
        assert!(seen > 0);
    }

    #[test]
    fn robots_stay_in_the_arena() {
        let s = simulate(&SimConfig {
            duration: 120.0,
            ..SimConfig::default()
        })
        .unwrap();
        for pts in s.truth.trajectories.values() {
            for p in pts {
                assert!((0.0..=17.0).contains(&p.pose.x) && (0.0..=10.5).contains(&p.pose.y));
            }
            // And they do move around.
            let far = pts
                .iter()
                .map(|p| p.pose.distance(&pts[0].pose))
                .fold(0.0, f64::max);
            assert!(far > 2.0);
        }
    }

    #[test]
    fn close_robots_sight_each_other() {
        // Two robots whose sightings reach across the whole arena see each other whenever
        // the other is in front.
        let cfg = SimConfig {
            robots: 2,
            sighting_range: 100.0,
            sensor_range: SensorRange {
                max_range: 6.0,
                fov: 2.0 * PI,
            },
            ..quiet()
        };
        let s = simulate(&cfg).unwrap();
        for r in &s.log.records {
            assert_eq!(r.robots.len(), 1, "{r:?}");
            let other = &r.robots[0];
            assert_ne!(other.robot, r.robot);
            let a = s.truth.trajectories[&r.robot][r.seq as usize + 1].pose;
            let b = s.truth.trajectories[&other.robot][r.seq as usize + 1].pose;
            assert!((other.z[0] - a.distance(&b)).abs() < 0.6);
        }
        assert!(s.log.header.sighting_noise.is_some());
        // Disabled sightings produce none.
        let s = simulate(&SimConfig {
            sighting_range: 0.0,
            ..cfg
        })
        .unwrap();
        assert!(s.log.records.iter().all(|r| r.robots.is_empty()));
        assert!(s.log.header.sighting_noise.is_none());
    }

    #[test]
    fn header_and_truth_describe_the_run() {
        let cfg = SimConfig {
            with_ids: false,
            landmark_positions: Some(vec![[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]),
            ..quiet()
        };
        let s = simulate(&cfg).unwrap();
        let h = &s.log.header;
        assert_eq!(h.name.as_deref(), Some("sim"));
        assert!(!h.landmark_ids);
        assert_eq!(h.motion_noise, Some(cfg.true_motion_noise));
        assert_eq!(h.sensor_range, Some(cfg.sensor_range));
        for r in &h.robots {
            assert_eq!(r.t0, Some(0.0));
            assert_eq!(r.start.unwrap().cov, [[0.0; 3]; 3]);
        }
        assert!(
            s.log
                .records
                .iter()
                .flat_map(|r| &r.landmarks)
                .all(|o| o.id.is_none())
        );
        // Explicit positions are used as given (z dropped in 2D), with ids 1..=n.
        let lm: Vec<_> = s.truth.landmarks.iter().map(|l| (l.id, l.mean)).collect();
        assert_eq!(
            lm,
            vec![(Some(1), [1.0, 2.0, 0.0]), (Some(2), [4.0, 5.0, 0.0])]
        );
        for pts in s.truth.trajectories.values() {
            assert_eq!(pts.len(), 101);
            assert_eq!(pts[0].t, 0.0);
        }
    }

    #[test]
    fn random_landmarks_fill_the_arena() {
        let a = random_landmarks(200, [17.0, 10.5], [0.2, 2.0], 7);
        assert_eq!(a, random_landmarks(200, [17.0, 10.5], [0.2, 2.0], 7));
        assert_ne!(a, random_landmarks(200, [17.0, 10.5], [0.2, 2.0], 8));
        assert!(a.iter().all(|m| (0.0..=17.0).contains(&m[0])
            && (0.0..=10.5).contains(&m[1])
            && (0.2..=2.0).contains(&m[2])));
        assert!(a.iter().any(|m| m[0] > 12.0) && a.iter().any(|m| m[0] < 5.0));
    }

    #[test]
    fn bad_configs_are_refused_with_the_field_name() {
        let bad = [
            (
                SimConfig {
                    robots: 0,
                    ..quiet()
                },
                "robots",
            ),
            (
                SimConfig {
                    duration: f64::NAN,
                    ..quiet()
                },
                "duration",
            ),
            (
                SimConfig {
                    record_period: 0.0,
                    ..quiet()
                },
                "record_period",
            ),
            (
                SimConfig {
                    control_period: 1.0,
                    ..quiet()
                },
                "control_period",
            ),
            (
                SimConfig {
                    duration: 0.1,
                    ..quiet()
                },
                "empty",
            ),
            (
                SimConfig {
                    duration: 1e9,
                    ..quiet()
                },
                "records",
            ),
            (
                SimConfig {
                    control_period: 1e-8,
                    ..quiet()
                },
                "segments",
            ),
            (
                SimConfig {
                    landmarks: usize::MAX,
                    ..quiet()
                },
                "landmarks",
            ),
            (
                SimConfig {
                    arena: [17.0, -1.0],
                    ..quiet()
                },
                "arena[1]",
            ),
            (
                SimConfig {
                    speed: -1.0,
                    ..quiet()
                },
                "speed",
            ),
            (
                SimConfig {
                    sighting_range: -1.0,
                    ..quiet()
                },
                "sighting_range",
            ),
            (
                SimConfig {
                    landmark_height: [2.0, 1.0],
                    ..quiet()
                },
                "landmark_height",
            ),
            (
                SimConfig {
                    motion_model: MotionModel::Ackermann,
                    ..quiet()
                },
                "ackermann",
            ),
            (
                SimConfig {
                    landmark_positions: Some(vec![[0.0, f64::INFINITY, 0.0]]),
                    ..quiet()
                },
                "landmark_positions[0]",
            ),
            (
                SimConfig {
                    true_motion_noise: MotionNoise {
                        trans_per_m: -1.0,
                        ..MotionNoise::default()
                    },
                    ..quiet()
                },
                "true_motion_noise.trans_per_m",
            ),
            (
                SimConfig {
                    odometry_scale: [1.0, 0.0],
                    ..quiet()
                },
                "odometry_scale",
            ),
            (
                SimConfig {
                    true_sensor_noise: SensorNoise {
                        range: f64::NAN,
                        ..SensorNoise::default()
                    },
                    ..quiet()
                },
                "true_sensor_noise.range",
            ),
            (
                SimConfig {
                    sensor_range: SensorRange {
                        max_range: 6.0,
                        fov: 7.0,
                    },
                    ..quiet()
                },
                "fov",
            ),
        ];
        for (cfg, needle) in bad {
            let e = simulate(&cfg).unwrap_err().to_string();
            assert!(e.contains(needle), "{needle}: {e}");
        }
    }

    #[test]
    fn config_json_accepts_partial_configs() {
        let cfg: SimConfig =
            serde_json::from_str(r#"{"robots":2,"kind":"point3d","seed":9}"#).unwrap();
        assert_eq!(cfg.robots, 2);
        assert_eq!(cfg.kind, LandmarkKind::Point3d);
        assert_eq!(cfg.arena, [17.0, 10.5]);
        assert!(serde_json::from_str::<SimConfig>(r#"{"robot":2}"#).is_err());
        let back: SimConfig = serde_json::from_str(&serde_json::to_string(&cfg).unwrap()).unwrap();
        assert_eq!(back, cfg);
    }
}
