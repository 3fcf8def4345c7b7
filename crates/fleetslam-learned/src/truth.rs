//! Labels training rows with ground truth, for models trained against it
//! ([`crate::dataset::TrainTarget::Truth`]).
//!
//! **What a row's truth is.** A particle's map lives in the frame of its own poses: its
//! landmark estimates and its robot pose err together (the whole team drifts, and a
//! particle's pose is off by its own error). A landmark update cannot know or undo those
//! errors, and a target that carried them (the landmark's absolute true position) measured
//! 0.96 m RMS from the filter's estimates on MRCLAM, a hundred prior standard deviations
//! for a well-observed landmark, which swamps the centimetres a real sensor's biases are
//! worth. What an update *can* get right is where the landmark lies relative to the robot:
//! the row's truth is the landmark placed from the row's (particle's) pose by the noise-free
//! measurement, the one the sensor would have returned from the robot's true pose to the
//! landmark's true position. On simulated rows, whose pose is the true pose, that is the
//! landmark's true position.
//!
//! **Which landmark a row updated.** A row holds what the updater saw (prior, pose,
//! measurement), not which landmark it was: the updater contract carries no landmark id,
//! and the hot path should not carry one for training's sake. The measurement identifies
//! the observation instead: the filter passes a log's measurement to the updater unchanged,
//! so a row's `z` equals, bit for bit, the `z` of the observation in the log that produced
//! it, whose record gives the robot and time and whose id names the landmark. A measurement
//! that occurs in two observations of the log (on MRCLAM's millimetre and milliradian
//! resolution 96 of 15,383 landmark readings repeat a reading of another landmark, and a
//! robot standing still repeats its own: 3.7-4.5 % of the rows logged) is ambiguous and left
//! unlabelled, as is one without an id, a truth position or a true robot
//! pose at its time; [`LabelStats`] counts each case.

use crate::row::TrainingRow;
use fleetslam_core::log::Log;
use fleetslam_core::math;
use fleetslam_core::pose::{Pose2, wrap_angle};
use fleetslam_core::sensor::LandmarkKind;
use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, HashMap};

/// What [`label_rows`] did.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct LabelStats {
    pub rows: usize,
    /// Rows given a truth position.
    pub labelled: usize,
    /// Rows whose measurement occurs in more than one observation of the log (another
    /// robot, time or landmark).
    pub ambiguous: usize,
    /// Rows whose observation has no id, an id without a truth position, or a time at
    /// which the robot's true pose is not known.
    pub no_truth: usize,
    /// Rows whose measurement is in no observation of the log (rows from another log).
    pub not_in_log: usize,
}

/// The observation a measurement came from.
#[derive(Debug, Clone, PartialEq)]
enum Seen<'a> {
    Once {
        robot: &'a str,
        t: f64,
        id: Option<u32>,
    },
    Ambiguous,
}

fn key(kind: LandmarkKind, z: &[f64]) -> [u64; 3] {
    let mut k = [0u64; 3];
    for (slot, v) in k.iter_mut().zip(&z[..kind.dim().min(z.len())]) {
        *slot = v.to_bits();
    }
    k
}

/// The noise-free measurement of `m` from `pose`: `[range, bearing, 0]` or the point in the
/// robot frame.
fn measure(kind: LandmarkKind, pose: &Pose2, m: &[f64; 3]) -> [f64; 3] {
    let (dx, dy) = (m[0] - pose.x, m[1] - pose.y);
    match kind {
        LandmarkKind::RangeBearing2d => [
            math::hypot(dx, dy),
            wrap_angle(math::atan2(dy, dx) - pose.theta),
            0.0,
        ],
        LandmarkKind::Point3d => {
            let (s, c) = math::sin_cos(pose.theta);
            [c * dx + s * dy, -s * dx + c * dy, m[2]]
        }
    }
}

/// The landmark that measurement `z` places from `pose` (the inverse of [`measure`]).
fn place(kind: LandmarkKind, pose: &Pose2, z: &[f64; 3]) -> [f64; 3] {
    match kind {
        LandmarkKind::RangeBearing2d => {
            let (s, c) = math::sin_cos(pose.theta + z[1]);
            [pose.x + z[0] * c, pose.y + z[0] * s, 0.0]
        }
        LandmarkKind::Point3d => {
            let (s, c) = math::sin_cos(pose.theta);
            [
                pose.x + c * z[0] - s * z[1],
                pose.y + s * z[0] + c * z[1],
                z[2],
            ]
        }
    }
}

/// Sets `truth` of every row whose measurement identifies one observation of `log` of a
/// landmark with a position in `landmarks` (id → true position), made when
/// `true_pose(robot, t)` knows the robot's true pose; other rows get `None`.
pub fn label_rows(
    rows: &mut [TrainingRow],
    log: &Log,
    landmarks: &BTreeMap<u32, [f64; 3]>,
    true_pose: impl Fn(&str, f64) -> Option<Pose2>,
) -> LabelStats {
    let kind = log.header.landmark_kind;
    let mut by_z: HashMap<[u64; 3], Seen> = HashMap::new();
    for rec in &log.records {
        for obs in &rec.landmarks {
            let now = Seen::Once {
                robot: &rec.robot,
                t: rec.t,
                id: obs.id,
            };
            by_z.entry(key(kind, &obs.z))
                .and_modify(|s| {
                    // A reading repeated within one record (MRCLAM repeats some rows) is
                    // still one observation.
                    if *s != now {
                        *s = Seen::Ambiguous;
                    }
                })
                .or_insert(now);
        }
    }
    let mut stats = LabelStats {
        rows: rows.len(),
        ..LabelStats::default()
    };
    for row in rows.iter_mut() {
        row.truth = None;
        match by_z.get(&key(row.kind, &row.z)) {
            None => stats.not_in_log += 1,
            Some(Seen::Ambiguous) => stats.ambiguous += 1,
            Some(Seen::Once { robot, t, id }) => {
                let truth = id
                    .and_then(|id| landmarks.get(&id))
                    .zip(true_pose(robot, *t));
                match truth {
                    Some((m, x)) => {
                        let pose = Pose2::new(row.pose[0], row.pose[1], row.pose[2]);
                        row.truth = Some(place(row.kind, &pose, &measure(row.kind, &x, m)));
                        stats.labelled += 1;
                    }
                    None => stats.no_truth += 1,
                }
            }
        }
    }
    stats
}

/// The squared Mahalanobis distance of the row's truth under its prior, `(t − μ)ᵀ Σ⁻¹ (t − μ)`:
/// how plausible the truth is for the particle's belief. `None` without truth or with a
/// prior that is not positive definite.
pub fn truth_mahalanobis2(row: &TrainingRow) -> Option<f64> {
    let t = row.truth?;
    let prior = row.input().prior;
    let d: Vec<f64> = (0..row.kind.dim()).map(|i| t[i] - prior.mean[i]).collect();
    match row.kind {
        LandmarkKind::RangeBearing2d => {
            let v = nalgebra::Vector2::new(d[0], d[1]);
            let c = prior.cov2().cholesky()?;
            Some(v.dot(&c.solve(&v)))
        }
        LandmarkKind::Point3d => {
            let v = nalgebra::Vector3::new(d[0], d[1], d[2]);
            let c = prior.cov3().cholesky()?;
            Some(v.dot(&c.solve(&v)))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Placing a measurement inverts measuring it, for both kinds.
    #[test]
    fn place_inverts_measure() {
        let pose = Pose2::new(1.5, -2.0, 2.8);
        for (kind, m) in [
            (LandmarkKind::RangeBearing2d, [4.0, 1.0, 0.0]),
            (LandmarkKind::Point3d, [-3.0, 0.5, 1.2]),
        ] {
            let back = place(kind, &pose, &measure(kind, &pose, &m));
            for (a, b) in back.iter().zip(&m) {
                assert!((a - b).abs() < 1e-12, "{kind:?}: {back:?} vs {m:?}");
            }
        }
    }
}
