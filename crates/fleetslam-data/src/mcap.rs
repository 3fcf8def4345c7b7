//! A run as an MCAP file with Foxglove's schemas (the official `foxglove` crate), for
//! Foxglove and every other MCAP reader.
//!
//! | topic | schema | messages |
//! |---|---|---|
//! | `/tf` | `foxglove.FrameTransform` | `world` → `robot_<id>`, one per trajectory pose |
//! | `/robot/<id>/pose` | `foxglove.PoseInFrame` | the estimated pose, one per trajectory pose |
//! | `/landmarks` | `foxglove.SceneUpdate` | one, at the last pose's time: per landmark a flat cylinder spanning its 2-sigma ellipse and its id as text |
//! | `/truth/<id>/pose` | `foxglove.PoseInFrame` | ground truth, when given |
//! | `/truth/landmarks` | `foxglove.SceneUpdate` | the true landmarks, when given |
//!
//! Times are the run's own (seconds, as the log's records carry them) as nanoseconds since
//! the epoch; a run whose times are negative cannot be written (MCAP times are unsigned).

use crate::formats::{LandmarkRow, TrajectoryPoint, Truth};
use fleetslam_core::pose::Pose2;
use foxglove::schemas::{
    Color, CylinderPrimitive, FrameTransform, Pose, PoseInFrame, Quaternion, SceneEntity,
    SceneUpdate, SpherePrimitive, TextPrimitive, Timestamp, Vector3,
};
use foxglove::{Channel, Context, McapWriter};
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
    let (s, c) = (0.5 * yaw).sin_cos();
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
        0.5 * (2.0 * b).atan2(a - c),
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

fn poses(
    ctx: &Arc<Context>,
    prefix: &str,
    trajectories: &BTreeMap<String, Vec<TrajectoryPoint>>,
    tf: Option<&Channel<FrameTransform>>,
) -> Result<(), McapError> {
    for (robot, pts) in trajectories {
        let ch = ctx
            .channel_builder(format!("/{prefix}/{robot}/pose"))
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
            if let Some(tf) = tf {
                tf.log_with_time(
                    &FrameTransform {
                        timestamp: Some(t),
                        parent_frame_id: WORLD_FRAME.into(),
                        child_frame_id: format!("robot_{robot}"),
                        translation: Some(Vector3 {
                            x: p.pose.x,
                            y: p.pose.y,
                            z: 0.0,
                        }),
                        rotation: Some(quaternion(p.pose.theta)),
                    },
                    t,
                );
            }
        }
    }
    Ok(())
}

/// The MCAP file of a run's estimate (trajectories and landmarks) and, when given, its
/// ground truth.
pub fn write_mcap(estimate: &Truth, truth: Option<&Truth>) -> Result<Vec<u8>, McapError> {
    let ctx = Context::new();
    let writer = McapWriter::new()
        .context(&ctx)
        .create(Cursor::new(Vec::new()))
        .map_err(|e| McapError::Write(e.to_string()))?;
    let tf = ctx.channel_builder("/tf").build::<FrameTransform>();
    poses(&ctx, "robot", &estimate.trajectories, Some(&tf))?;
    let end = estimate
        .trajectories
        .values()
        .filter_map(|pts| pts.last().map(|p| p.t))
        .fold(0.0, f64::max);
    let t = stamp(end)?;
    let estimate_color = Color {
        r: 0.9,
        g: 0.4,
        b: 0.1,
        a: 0.6,
    };
    let scene = ctx.channel_builder("/landmarks").build::<SceneUpdate>();
    scene.log_with_time(
        &SceneUpdate {
            deletions: Vec::new(),
            entities: estimate
                .landmarks
                .iter()
                .enumerate()
                .map(|(k, l)| landmark_entity(t, k, l, estimate_color))
                .collect(),
        },
        t,
    );
    if let Some(truth) = truth {
        poses(&ctx, "truth", &truth.trajectories, None)?;
        if !truth.landmarks.is_empty() {
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
        let (s, c) = 30f64.to_radians().sin_cos();
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
