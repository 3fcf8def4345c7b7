//! A run as an MCAP file with Foxglove's schemas (the official `foxglove` crate), for
//! Foxglove and every other MCAP reader.
//!
//! | topic | schema | messages |
//! |---|---|---|
//! | `/tf` | `foxglove.FrameTransform` | `world` → `robot_<id>`, one per trajectory pose |
//! | `/robot/<id>/pose` | `foxglove.PoseInFrame` | the estimated pose, one per trajectory pose |
//! | `/landmarks` | `foxglove.SceneUpdate` | one, at the last pose's time: per landmark a flat cylinder spanning its 2-sigma ellipse and its id as text |
//! | `/robot/<id>/particles` | `foxglove.PosesInFrame` | the particle sample's poses at the last pose's time, when given |
//! | `/filter` | `fleetslam.FilterStats` (JSON) | the filter after each applied record: `ess`, `step_ms`, `landmarks` (for Foxglove's Plot panel), when given |
//! | `/truth/<id>/pose` | `foxglove.PoseInFrame` | ground truth, when given |
//! | `/truth/landmarks` | `foxglove.SceneUpdate` | the true landmarks, when given |
//!
//! The live server (`fleetslam serve --foxglove-bind`) streams the same messages through
//! [`RunChannels`], under `/run/<id>` (`/run/<id>/tf`, `/run/<id>/robot/<rid>/pose`, ...),
//! logged at the wall clock and refreshed at the server's state rate.
//!
//! Times are the run's own (seconds, as the log's records carry them) as nanoseconds since
//! the epoch; a run whose times are negative cannot be written (MCAP times are unsigned).

use crate::formats::{LandmarkRow, Truth};
use fleetslam_core::math;
use fleetslam_core::pose::Pose2;
use foxglove::schemas::{
    Color, CylinderPrimitive, FrameTransform, Pose, PoseInFrame, PosesInFrame, Quaternion,
    SceneEntity, SceneEntityDeletion, SceneUpdate, SpherePrimitive, TextPrimitive, Timestamp,
    Vector3, scene_entity_deletion,
};
use foxglove::{Channel, Context, McapWriter, PartialMetadata, RawChannel, Schema};
use std::collections::BTreeMap;
use std::io::Cursor;
use std::sync::Arc;

/// The frame every pose and landmark is given in.
pub const WORLD_FRAME: &str = "world";
/// Height [m] of the flat cylinder that draws a landmark's 2-sigma ellipse.
const ELLIPSE_HEIGHT: f64 = 0.02;
/// Diameter [m] of the spheres that mark true landmarks.
const TRUTH_MARKER: f64 = 0.08;

#[derive(Debug, thiserror::Error)]
pub enum McapError {
    #[error("time {0} s cannot be written to MCAP (times must be finite and >= 0)")]
    Time(f64),
    #[error("writing MCAP: {0}")]
    Write(String),
}

fn stamp(t: f64) -> Result<Timestamp, McapError> {
    Timestamp::try_from_epoch_secs_f64(t).map_err(|_| McapError::Time(t))
}

fn quaternion(yaw: f64) -> Quaternion {
    let (s, c) = math::sin_cos(0.5 * yaw);
    Quaternion {
        x: 0.0,
        y: 0.0,
        z: s,
        w: c,
    }
}

fn pose(x: f64, y: f64, z: f64, yaw: f64) -> Pose {
    Pose {
        position: Some(Vector3 { x, y, z }),
        orientation: Some(quaternion(yaw)),
    }
}

fn robot_pose(p: &Pose2) -> Pose {
    pose(p.x, p.y, 0.0, p.theta)
}

/// The 2-sigma ellipse of a landmark's ground-plane covariance: (diameters, heading of the
/// first axis).
fn ellipse(cov: &[f64; 6]) -> ([f64; 2], f64) {
    let (a, b, c) = (cov[0], cov[1], cov[3]);
    let mid = 0.5 * (a + c);
    let r = (0.25 * (a - c) * (a - c) + b * b).sqrt();
    let sd = |l: f64| l.max(0.0).sqrt();
    (
        [4.0 * sd(mid + r), 4.0 * sd(mid - r)],
        0.5 * math::atan2(2.0 * b, a - c),
    )
}

fn landmark_entity(t: Timestamp, k: usize, l: &LandmarkRow, color: Color) -> SceneEntity {
    let name = l.id.map_or(format!("#{k}"), |id| id.to_string());
    let ([d1, d2], heading) = ellipse(&l.cov);
    let [x, y, z] = l.mean;
    SceneEntity {
        timestamp: Some(t),
        frame_id: WORLD_FRAME.into(),
        id: format!("landmark-{name}"),
        cylinders: vec![CylinderPrimitive {
            pose: Some(pose(x, y, z, heading)),
            size: Some(Vector3 {
                x: d1,
                y: d2,
                z: ELLIPSE_HEIGHT,
            }),
            bottom_scale: 1.0,
            top_scale: 1.0,
            color: Some(color),
        }],
        texts: vec![TextPrimitive {
            pose: Some(pose(x, y, z + 0.1, 0.0)),
            billboard: true,
            font_size: 14.0,
            scale_invariant: true,
            color: Some(color),
            text: name,
        }],
        ..SceneEntity::default()
    }
}

fn truth_entity(t: Timestamp, k: usize, l: &LandmarkRow) -> SceneEntity {
    let name = l.id.map_or(format!("#{k}"), |id| id.to_string());
    let [x, y, z] = l.mean;
    SceneEntity {
        timestamp: Some(t),
        frame_id: WORLD_FRAME.into(),
        id: format!("truth-{name}"),
        spheres: vec![SpherePrimitive {
            pose: Some(pose(x, y, z, 0.0)),
            size: Some(Vector3 {
                x: TRUTH_MARKER,
                y: TRUTH_MARKER,
                z: TRUTH_MARKER,
            }),
            color: Some(Color {
                r: 0.1,
                g: 0.7,
                b: 0.2,
                a: 1.0,
            }),
        }],
        ..SceneEntity::default()
    }
}

/// The JSON schema of the `/filter` topic's messages.
const FILTER_STATS_SCHEMA: &str = r#"{
  "title": "fleetslam.FilterStats",
  "description": "The filter after an applied record",
  "type": "object",
  "properties": {
    "t": {"type": "number", "description": "data time [s]"},
    "ess": {"type": "number", "description": "effective sample size"},
    "step_ms": {"type": "number", "description": "wall time of the record's step [ms]"},
    "landmarks": {"type": "number", "description": "landmarks in the best particle"}
  }
}"#;

/// The time a message is logged at (its own `timestamp` is always the data time it
/// describes).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LogTime {
    /// The data time: a file, which readers play back in data time.
    Data,
    /// The wall clock when it is logged: a live view.
    Wall,
}

/// One run's channels in a Foxglove [`Context`], under a topic prefix (`""` in a file,
/// `/run/<id>` on the live server; see the module's doc for the topics). The MCAP export
/// and the live server (`serve --foxglove-bind`) log through it, so both carry the same
/// messages. A robot's channels are made when it is first logged.
#[derive(Debug)]
pub struct RunChannels {
    ctx: Arc<Context>,
    prefix: String,
    time: LogTime,
    tf: Channel<FrameTransform>,
    landmarks: Channel<SceneUpdate>,
    poses: BTreeMap<String, Channel<PoseInFrame>>,
    particles: BTreeMap<String, Channel<PosesInFrame>>,
    filter: Arc<RawChannel>,
}

impl RunChannels {
    pub fn new(ctx: &Arc<Context>, prefix: &str, time: LogTime) -> Result<Self, McapError> {
        let filter = ctx
            .channel_builder(format!("{prefix}/filter"))
            .message_encoding("json")
            .schema(Schema::new(
                "fleetslam.FilterStats",
                "jsonschema",
                FILTER_STATS_SCHEMA.as_bytes(),
            ))
            .build_raw()
            .map_err(|e| McapError::Write(e.to_string()))?;
        Ok(Self {
            ctx: ctx.clone(),
            prefix: prefix.to_string(),
            time,
            tf: ctx
                .channel_builder(format!("{prefix}/tf"))
                .build::<FrameTransform>(),
            landmarks: ctx
                .channel_builder(format!("{prefix}/landmarks"))
                .build::<SceneUpdate>(),
            poses: BTreeMap::new(),
            particles: BTreeMap::new(),
            filter,
        })
    }

    fn meta(&self, t: Timestamp) -> PartialMetadata {
        match self.time {
            LogTime::Data => PartialMetadata::with_log_time(t),
            LogTime::Wall => PartialMetadata::default(),
        }
    }

    /// Whether any sink (a file, a live client) takes any of the run's channels: a live
    /// server skips building messages nobody subscribed to.
    pub fn has_sinks(&self) -> bool {
        self.tf.has_sinks()
            || self.landmarks.has_sinks()
            || self.poses.values().any(Channel::has_sinks)
            || self.particles.values().any(Channel::has_sinks)
            || self.filter.has_sinks()
    }

    /// Makes a robot's channels (so that a live client sees them advertised) without
    /// logging.
    pub fn add_robot(&mut self, robot: &str) {
        // Called for every pose logged: a robot's channels are made together, once.
        if self.poses.contains_key(robot) {
            return;
        }
        let (ctx, prefix) = (&self.ctx, &self.prefix);
        self.poses.insert(
            robot.to_string(),
            ctx.channel_builder(format!("{prefix}/robot/{robot}/pose"))
                .build(),
        );
        self.particles.insert(
            robot.to_string(),
            ctx.channel_builder(format!("{prefix}/robot/{robot}/particles"))
                .build(),
        );
    }

    /// A robot's pose at `t`: `{prefix}/robot/<id>/pose` and the `world` → `robot_<id>`
    /// transform on `{prefix}/tf`.
    pub fn pose(&mut self, robot: &str, t: f64, p: &Pose2) -> Result<(), McapError> {
        let ts = stamp(t)?;
        self.add_robot(robot);
        let meta = self.meta(ts);
        self.poses[robot].log_with_meta(
            &PoseInFrame {
                timestamp: Some(ts),
                frame_id: WORLD_FRAME.into(),
                pose: Some(robot_pose(p)),
            },
            meta,
        );
        self.tf.log_with_meta(
            &FrameTransform {
                timestamp: Some(ts),
                parent_frame_id: WORLD_FRAME.into(),
                child_frame_id: format!("robot_{robot}"),
                translation: Some(Vector3 {
                    x: p.x,
                    y: p.y,
                    z: 0.0,
                }),
                rotation: Some(quaternion(p.theta)),
            },
            meta,
        );
        Ok(())
    }

    /// The map at `t` on `{prefix}/landmarks`: it replaces the map logged before (landmarks
    /// that were removed go), each landmark a flat cylinder spanning its 2-sigma ellipse
    /// and its id as text.
    pub fn landmarks(&self, t: f64, landmarks: &[LandmarkRow]) -> Result<(), McapError> {
        let ts = stamp(t)?;
        let color = Color {
            r: 0.9,
            g: 0.4,
            b: 0.1,
            a: 0.6,
        };
        self.landmarks.log_with_meta(
            &SceneUpdate {
                deletions: vec![SceneEntityDeletion {
                    timestamp: Some(ts),
                    r#type: scene_entity_deletion::Type::All as i32,
                    id: String::new(),
                }],
                entities: landmarks
                    .iter()
                    .enumerate()
                    .map(|(k, l)| landmark_entity(ts, k, l, color))
                    .collect(),
            },
            self.meta(ts),
        );
        Ok(())
    }

    /// A sample of a robot's particles at `t` (`[x, y, theta, weight]`) on
    /// `{prefix}/robot/<id>/particles`.
    pub fn particles(&mut self, robot: &str, t: f64, sample: &[[f64; 4]]) -> Result<(), McapError> {
        let ts = stamp(t)?;
        self.add_robot(robot);
        self.particles[robot].log_with_meta(
            &PosesInFrame {
                timestamp: Some(ts),
                frame_id: WORLD_FRAME.into(),
                poses: sample.iter().map(|p| pose(p[0], p[1], 0.0, p[2])).collect(),
            },
            self.meta(ts),
        );
        Ok(())
    }

    /// The filter after a record, `[t, ess, step_ms, landmarks]`, on `{prefix}/filter`
    /// (JSON, for Foxglove's Plot panel).
    pub fn filter(&self, p: [f64; 4]) -> Result<(), McapError> {
        let ts = stamp(p[0])?;
        let msg = serde_json::json!({"t": p[0], "ess": p[1], "step_ms": p[2], "landmarks": p[3]});
        self.filter
            .log_with_meta(msg.to_string().as_bytes(), self.meta(ts));
        Ok(())
    }

    /// Removes the run's channels from the context (a live client sees them go).
    pub fn close(self) {
        self.tf.close();
        self.landmarks.close();
        self.poses.values().for_each(Channel::close);
        self.particles.values().for_each(Channel::close);
        self.filter.close();
    }
}

/// What a run's MCAP file holds.
#[derive(Debug, Clone, Copy)]
pub struct McapRun<'a> {
    /// The run's trajectories and landmarks.
    pub estimate: &'a Truth,
    /// Its ground truth, when there is one.
    pub truth: Option<&'a Truth>,
    /// The filter after each applied record: `[t, ess, step_ms, landmarks]`.
    pub series: &'a [[f64; 4]],
    /// A sample of each robot's particles at the end: `[x, y, theta, weight]`.
    pub particles: &'a BTreeMap<String, Vec<[f64; 4]>>,
}

impl<'a> McapRun<'a> {
    /// A run's estimate alone.
    pub fn estimate(estimate: &'a Truth) -> Self {
        static NONE: BTreeMap<String, Vec<[f64; 4]>> = BTreeMap::new();
        Self {
            estimate,
            truth: None,
            series: &[],
            particles: &NONE,
        }
    }
}

/// The MCAP file of a run (see the module's doc for its topics).
pub fn write_mcap(run: &McapRun) -> Result<Vec<u8>, McapError> {
    let McapRun {
        estimate,
        truth,
        series,
        particles,
    } = *run;
    let ctx = Context::new();
    let writer = McapWriter::new()
        .context(&ctx)
        .create(Cursor::new(Vec::new()))
        .map_err(|e| McapError::Write(e.to_string()))?;
    let mut channels = RunChannels::new(&ctx, "", LogTime::Data)?;
    for (robot, pts) in &estimate.trajectories {
        for p in pts {
            channels.pose(robot, p.t, &p.pose)?;
        }
    }
    let end = estimate
        .trajectories
        .values()
        .filter_map(|pts| pts.last().map(|p| p.t))
        .fold(0.0, f64::max);
    channels.landmarks(end, &estimate.landmarks)?;
    for (robot, sample) in particles {
        channels.particles(robot, end, sample)?;
    }
    for p in series {
        channels.filter(*p)?;
    }
    if let Some(truth) = truth {
        for (robot, pts) in &truth.trajectories {
            let ch = ctx
                .channel_builder(format!("/truth/{robot}/pose"))
                .build::<PoseInFrame>();
            for p in pts {
                let t = stamp(p.t)?;
                ch.log_with_time(
                    &PoseInFrame {
                        timestamp: Some(t),
                        frame_id: WORLD_FRAME.into(),
                        pose: Some(robot_pose(&p.pose)),
                    },
                    t,
                );
            }
        }
        if !truth.landmarks.is_empty() {
            let t = stamp(end)?;
            let scene = ctx
                .channel_builder("/truth/landmarks")
                .build::<SceneUpdate>();
            scene.log_with_time(
                &SceneUpdate {
                    deletions: Vec::new(),
                    entities: truth
                        .landmarks
                        .iter()
                        .enumerate()
                        .map(|(k, l)| truth_entity(t, k, l))
                        .collect(),
                },
                t,
            );
        }
    }
    let out = writer
        .close()
        .map_err(|e| McapError::Write(e.to_string()))?;
    Ok(out.into_inner())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A landmark's ellipse has the covariance's principal axes, 2 sigma each way.
    #[test]
    fn ellipse_spans_two_sigma_along_the_principal_axes() {
        // Axis-aligned: sigma 0.5 along x, 0.25 along y.
        let ([a, b], h) = ellipse(&[0.25, 0.0, 0.0, 0.0625, 0.0, 0.0]);
        assert!((a - 2.0).abs() < 1e-12 && (b - 1.0).abs() < 1e-12 && h.abs() < 1e-12);
        // Rotated by 30 degrees.
        let (s, c) = math::sin_cos(30f64.to_radians());
        let (l1, l2) = (0.25, 0.0625);
        let cov = [
            c * c * l1 + s * s * l2,
            c * s * (l1 - l2),
            0.0,
            s * s * l1 + c * c * l2,
            0.0,
            0.0,
        ];
        let ([a, b], h) = ellipse(&cov);
        assert!((a - 2.0).abs() < 1e-12 && (b - 1.0).abs() < 1e-12);
        assert!((h - 30f64.to_radians()).abs() < 1e-12);
    }
}
