//! Runs a log through the filter offline and collects what `fleetslam run` writes:
//! per-robot trajectories, the final landmarks and timing metrics.

use crate::formats::{LandmarkRow, TrajectoryPoint, Truth};
use fleetslam_core::filter::{Estimate, FastSlam, FilterError};
use fleetslam_core::log::{Log, record_order};
use serde::{Deserialize, Serialize};
use std::path::Path;
use std::time::Instant;

/// Which pose estimate a trajectory records after each of the robot's records.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TrajectoryEstimate {
    /// The weighted mean over particles (smooth; the default).
    #[default]
    Mean,
    /// The pose in the particle of highest weight.
    Best,
}

/// The metrics of a run, written as `metrics.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RunMetrics {
    pub wall_time_s: f64,
    pub steps: u64,
    pub step_ms_p50: f64,
    pub step_ms_p95: f64,
    pub step_ms_max: f64,
    pub landmark_updates: u64,
    /// Time inside the updater per landmark update, summed over threads.
    pub ns_per_landmark_update: f64,
    pub particles: usize,
    pub updater: String,
    pub seed: u64,
    pub resamples: u64,
    pub landmarks: usize,
    pub landmarks_created: u64,
    pub landmarks_removed: u64,
    pub outliers: u64,
    pub final_ess: f64,
    /// Records of robots without a known start pose, not applied.
    pub skipped_records: u64,
    /// True when every robot started at a known pose given in the ground truth's frame:
    /// evaluation then needs no alignment.
    pub shared_frame: bool,
    pub threads: usize,
}

/// The result of a run.
#[derive(Debug, Clone)]
pub struct RunOutput {
    pub estimate: Truth,
    pub metrics: RunMetrics,
    pub final_estimate: Estimate,
}

/// Start time of a robot whose header gives none: before any record. Trajectories get no
/// start point for it.
const UNKNOWN_T0: f64 = -1e12;

/// The pose a trajectory records for robot `r`.
fn pose_of(slam: &FastSlam, which: TrajectoryEstimate, r: usize) -> fleetslam_core::Pose2 {
    match which {
        TrajectoryEstimate::Mean => slam.mean_pose(r),
        TrajectoryEstimate::Best => slam.particles()[slam.best_index()].poses[r],
    }
}

/// Adds the header's robots with known start poses to the filter; returns whether every
/// robot had one, in the ground truth's frame.
pub fn add_header_robots(slam: &mut FastSlam, log: &Log) -> Result<bool, FilterError> {
    let mut all_known = true;
    for r in &log.header.robots {
        match &r.start {
            Some(start) => {
                let t0 = r.t0.map_or(UNKNOWN_T0, |t| t.max(UNKNOWN_T0));
                slam.add_robot(&r.id, start, t0)?;
            }
            None => all_known = false,
        }
    }
    Ok(all_known && log.header.truth_frame)
}

/// Applies every record of `log` in the deterministic order (time, robot, sequence).
/// `progress(done, total)` is called now and then.
pub fn run_log(
    slam: &mut FastSlam,
    log: &Log,
    which: TrajectoryEstimate,
    mut progress: impl FnMut(usize, usize),
) -> Result<RunOutput, FilterError> {
    let shared_frame = add_header_robots(slam, log)?;
    let mut order: Vec<usize> = (0..log.records.len()).collect();
    order.sort_by(|&a, &b| record_order(&log.records[a], &log.records[b]));
    let mut trajectories: std::collections::BTreeMap<String, Vec<TrajectoryPoint>> = slam
        .robots()
        .iter()
        .map(|r| (r.id.clone(), Vec::new()))
        .collect();
    for r in slam.robots() {
        if r.last_t > UNKNOWN_T0 {
            let i = slam.robot_index(&r.id).expect("robot just added");
            let pose = pose_of(slam, which, i);
            trajectories
                .get_mut(&r.id)
                .expect("inserted above")
                .push(TrajectoryPoint { t: r.last_t, pose });
        }
    }
    let mut step_ns = Vec::with_capacity(order.len());
    let mut skipped = 0u64;
    let start = Instant::now();
    let total = order.len();
    for (k, &i) in order.iter().enumerate() {
        let rec = &log.records[i];
        let Some(r) = slam.robot_index(&rec.robot) else {
            skipped += 1;
            continue;
        };
        let t0 = Instant::now();
        slam.step(rec)?;
        step_ns.push(t0.elapsed().as_nanos() as u64);
        let pose = pose_of(slam, which, r);
        trajectories
            .get_mut(&rec.robot)
            .expect("every robot in the filter has a trajectory")
            .push(TrajectoryPoint { t: rec.t, pose });
        if k % 256 == 0 {
            progress(k, total);
        }
    }
    progress(total, total);
    let wall = start.elapsed().as_secs_f64();
    step_ns.sort_unstable();
    let pct = |p: f64| -> f64 {
        if step_ns.is_empty() {
            return 0.0;
        }
        let idx = ((step_ns.len() - 1) as f64 * p).round() as usize;
        step_ns[idx] as f64 / 1e6
    };
    let est = slam.estimate();
    let stats = *slam.stats();
    let metrics = RunMetrics {
        wall_time_s: wall,
        steps: step_ns.len() as u64,
        step_ms_p50: pct(0.5),
        step_ms_p95: pct(0.95),
        step_ms_max: pct(1.0),
        landmark_updates: stats.landmark_updates,
        ns_per_landmark_update: if stats.landmark_updates > 0 {
            stats.update_nanos as f64 / stats.landmark_updates as f64
        } else {
            0.0
        },
        particles: slam.config().particles,
        updater: slam.updater().name().to_string(),
        seed: slam.config().seed,
        resamples: stats.resamples,
        landmarks: est.landmarks.len(),
        landmarks_created: stats.landmarks_created,
        landmarks_removed: stats.landmarks_removed,
        outliers: stats.outliers,
        final_ess: est.ess,
        skipped_records: skipped,
        shared_frame,
        threads: rayon::current_num_threads(),
    };
    let landmarks = landmark_rows(&est);
    Ok(RunOutput {
        estimate: Truth {
            trajectories,
            landmarks,
        },
        metrics,
        final_estimate: est,
    })
}

/// The best particle's landmarks as CSV rows.
pub fn landmark_rows(est: &Estimate) -> Vec<LandmarkRow> {
    est.landmarks
        .iter()
        .map(|l| LandmarkRow {
            id: l.id,
            mean: l.gaussian.mean,
            cov: l.gaussian.cov,
        })
        .collect()
}

impl RunOutput {
    /// Writes `trajectory_<robot>.tum`, `landmarks.csv` and `metrics.json` into `dir`.
    pub fn write(&self, dir: &Path) -> std::io::Result<()> {
        std::fs::create_dir_all(dir)?;
        self.estimate.write_dir(dir)?;
        if self.estimate.landmarks.is_empty() {
            crate::formats::write_landmarks_csv_path(&crate::formats::landmarks_file(dir), &[])?;
        }
        let f = std::fs::File::create(dir.join("metrics.json"))?;
        serde_json::to_writer_pretty(f, &self.metrics)?;
        Ok(())
    }
}
