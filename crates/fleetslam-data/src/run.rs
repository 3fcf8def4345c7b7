//! Runs a log through the filter offline and collects what `fleetslam run` writes:
//! per-robot trajectories, the final landmarks and timing metrics.
//!
//! [`run_log`] applies the records of robots with a known start and skips the others;
//! [`run_log_joining`] localizes robots without a known start against the run's map and
//! merges them when localized ([`fleetslam_localize::LateJoinSlam`]). For a log whose robots
//! all have known starts the two give bit-identical filters.

use crate::formats::{LandmarkRow, TrajectoryPoint, Truth};
use fleetslam_core::filter::{Estimate, FastSlam, FilterError};
use fleetslam_core::log::{Log, record_order};
use fleetslam_localize::localizer::LocalizerStatus;
use fleetslam_localize::{LateJoinSlam, LocalizeConfig, LocalizeError};
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
    /// Landmarks merged into a neighbour closer than the minimum separation (unknown ids).
    #[serde(default)]
    pub landmarks_merged: u64,
    pub outliers: u64,
    /// FastSLAM 2.0 particle steps whose proposal was degenerate and fell back to 1.0's.
    #[serde(default)]
    pub proposal_fallbacks: u64,
    pub final_ess: f64,
    /// Records of robots without a known start pose, not applied.
    pub skipped_records: u64,
    /// True when every robot started at a known pose given in the ground truth's frame:
    /// evaluation then needs no alignment.
    pub shared_frame: bool,
    pub threads: usize,
    /// Wall time of the run per particle and record: `wall_time_s / (particles × steps)`
    /// [ns]. The cost every record pays for every particle (motion, weights, resampling).
    #[serde(default)]
    pub ns_per_particle_record: f64,
    /// Wall time of the run per particle and landmark observation: `wall_time_s /
    /// (particles × observations)` [ns]; 0 for a run without observations.
    #[serde(default)]
    pub ns_per_particle_observation: f64,
    /// Robots that joined at an unknown pose ([`run_log_joining`]); absent otherwise.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub joiners: Vec<JoinerMetrics>,
}

/// What happened to a robot that joined at an unknown pose.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct JoinerMetrics {
    pub id: String,
    /// Time it entered the filter [s]; `None` if it never localized.
    pub joined_at: Option<f64>,
    /// Its records dropped before `join_at`.
    pub dropped_before_join: u64,
    /// The localizer's final state and counters.
    pub localization: LocalizerStatus,
}

/// How [`run_log_joining`] treats robots without a known start.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct JoinOptions {
    /// Robots whose start pose is forgotten, so that they are localized, besides those the
    /// header gives no start.
    pub unknown: Vec<String>,
    /// The `unknown` robots' records before this time are dropped: they join the run then
    /// (as if switched on at that time).
    pub join_at: Option<f64>,
    /// Localization of the joining robots.
    pub localize: LocalizeConfig,
}

/// The result of a run.
#[derive(Debug, Clone)]
pub struct RunOutput {
    pub estimate: Truth,
    pub metrics: RunMetrics,
    pub final_estimate: Estimate,
}

/// Start time of a robot: its header's `t0`, or else the time of its first record (its
/// clock starts there, so that its first record's random walk covers no silence before it;
/// 0 for a robot without records). Trajectories get a start point only from a header's `t0`.
fn start_time(log: &Log, r: &fleetslam_core::log::RobotStart) -> f64 {
    if let Some(t) = r.t0 {
        return t;
    }
    let first = log
        .records
        .iter()
        .filter(|rec| rec.robot == r.id)
        .map(|rec| rec.t)
        .fold(f64::INFINITY, f64::min);
    if first.is_finite() { first } else { 0.0 }
}

/// The pose a trajectory records for robot `r`.
fn pose_of(slam: &FastSlam, which: TrajectoryEstimate, r: usize) -> fleetslam_core::Pose2 {
    match which {
        TrajectoryEstimate::Mean => slam.mean_pose(r),
        TrajectoryEstimate::Best => slam.robot_particles()[r].poses[slam.best_index()],
    }
}

/// Adds the header's robots with known start poses to the filter; returns whether every
/// robot had one, in the ground truth's frame.
pub fn add_header_robots(slam: &mut FastSlam, log: &Log) -> Result<bool, FilterError> {
    let mut all_known = true;
    for r in &log.header.robots {
        match &r.start {
            Some(start) => {
                slam.add_robot(&r.id, start, start_time(log, r))?;
            }
            None => all_known = false,
        }
    }
    Ok(all_known && log.header.truth_frame)
}

/// Applies every record of `log` in the deterministic order (time, robot, sequence).
/// `progress(done, total)` is called now and then.
///
/// The loop runs on a thread of rayon's pool (`rayon::scope`), so that each step's parallel
/// part starts and joins from inside the pool instead of waking it from outside and
/// blocking the caller: on MRCLAM Dataset 6 that took the context switches from 96,000 to
/// 14,000 (README, session 17). Results do not depend on it.
pub fn run_log(
    slam: &mut FastSlam,
    log: &Log,
    which: TrajectoryEstimate,
    mut progress: impl FnMut(usize, usize) + Send,
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
        if log
            .header
            .robots
            .iter()
            .any(|h| h.id == r.id && h.t0.is_some())
        {
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
    rayon::scope(|_| -> Result<(), FilterError> {
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
        Ok(())
    })?;
    progress(total, total);
    let wall = start.elapsed().as_secs_f64();
    Ok(finish(
        slam,
        trajectories,
        step_ns,
        wall,
        skipped,
        shared_frame,
    ))
}

/// The output of a run from the filter's final state and the per-step timings.
/// `wall` seconds per particle and per `count` (steps or observations), in ns; 0 when
/// there was nothing to count.
pub fn per_particle_ns(wall: f64, particles: usize, count: u64) -> f64 {
    if count == 0 || particles == 0 {
        return 0.0;
    }
    wall * 1e9 / (particles as f64 * count as f64)
}

fn finish(
    slam: &FastSlam,
    trajectories: std::collections::BTreeMap<String, Vec<TrajectoryPoint>>,
    mut step_ns: Vec<u64>,
    wall: f64,
    skipped: u64,
    shared_frame: bool,
) -> RunOutput {
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
        landmarks_merged: stats.landmarks_merged,
        outliers: stats.outliers,
        proposal_fallbacks: stats.proposal_fallbacks,
        final_ess: est.ess,
        skipped_records: skipped,
        shared_frame,
        threads: rayon::current_num_threads(),
        ns_per_particle_record: per_particle_ns(wall, slam.config().particles, stats.steps),
        ns_per_particle_observation: per_particle_ns(
            wall,
            slam.config().particles,
            stats.observations,
        ),
        joiners: Vec::new(),
    };
    let landmarks = landmark_rows(&est);
    RunOutput {
        estimate: Truth {
            trajectories,
            landmarks,
        },
        metrics,
        final_estimate: est,
    }
}

/// [`run_log`] with late joiners: robots of the header without a start pose, and those
/// named in `opts.unknown`, are registered as unknown; their records are localized against
/// the run's best map until they converge, and from then on they map
/// ([`LateJoinSlam`]). Their trajectories start when they join. Records of the `unknown`
/// robots before `opts.join_at` are dropped. At least one robot needs a known start, or
/// there is no map to localize in. For a log without such robots the filter ends
/// bit-identical to [`run_log`]'s.
pub fn run_log_joining(
    run: &mut LateJoinSlam,
    log: &Log,
    which: TrajectoryEstimate,
    opts: &JoinOptions,
    mut progress: impl FnMut(usize, usize) + Send,
) -> Result<RunOutput, LocalizeError> {
    for u in &opts.unknown {
        if !log.header.robots.iter().any(|r| &r.id == u) {
            return Err(LocalizeError::Robot(format!(
                "--unknown {u:?}: the log has no such robot (it has {:?})",
                log.header.robots.iter().map(|r| &r.id).collect::<Vec<_>>()
            )));
        }
    }
    let is_unknown = |id: &str| opts.unknown.iter().any(|u| u == id);
    let mut any_known = false;
    for r in &log.header.robots {
        match &r.start {
            Some(start) if !is_unknown(&r.id) => {
                run.add_robot(&r.id, start, start_time(log, r))?;
                any_known = true;
            }
            _ => run.add_unknown_robot(&r.id)?,
        }
    }
    // Joiners are localized in the map, hence in the frame of the robots with known starts.
    let shared_frame = any_known && log.header.truth_frame;
    let mut order: Vec<usize> = (0..log.records.len()).collect();
    order.sort_by(|&a, &b| record_order(&log.records[a], &log.records[b]));
    let mut trajectories: std::collections::BTreeMap<String, Vec<TrajectoryPoint>> = run
        .slam()
        .robots()
        .iter()
        .map(|r| (r.id.clone(), Vec::new()))
        .collect();
    for r in run.slam().robots() {
        if log
            .header
            .robots
            .iter()
            .any(|h| h.id == r.id && h.t0.is_some())
        {
            let i = run.slam().robot_index(&r.id).expect("robot just added");
            let pose = pose_of(run.slam(), which, i);
            trajectories
                .entry(r.id.clone())
                .or_default()
                .push(TrajectoryPoint { t: r.last_t, pose });
        }
    }
    let mut dropped: std::collections::BTreeMap<String, u64> = Default::default();
    let mut step_ns = Vec::with_capacity(order.len());
    let start = Instant::now();
    let total = order.len();
    // On a thread of rayon's pool, as in `run_log`.
    rayon::scope(|_| -> Result<(), LocalizeError> {
        for (k, &i) in order.iter().enumerate() {
            let rec = &log.records[i];
            if is_unknown(&rec.robot) && opts.join_at.is_some_and(|t| rec.t < t) {
                *dropped.entry(rec.robot.clone()).or_insert(0) += 1;
                continue;
            }
            let t0 = Instant::now();
            let step = run.step(rec)?;
            step_ns.push(t0.elapsed().as_nanos() as u64);
            if step.phase == fleetslam_localize::Phase::Mapping {
                let r = run
                    .slam()
                    .robot_index(&rec.robot)
                    .expect("a mapping robot is in the filter");
                let pose = pose_of(run.slam(), which, r);
                trajectories
                    .entry(rec.robot.clone())
                    .or_default()
                    .push(TrajectoryPoint { t: rec.t, pose });
            }
            if k % 256 == 0 {
                progress(k, total);
            }
        }
        Ok(())
    })?;
    progress(total, total);
    let wall = start.elapsed().as_secs_f64();
    let mut out = finish(run.slam(), trajectories, step_ns, wall, 0, shared_frame);
    out.metrics.joiners = run
        .phases()
        .into_iter()
        .filter_map(|p| {
            p.localization.map(|l| JoinerMetrics {
                dropped_before_join: dropped.get(&p.id).copied().unwrap_or(0),
                id: p.id,
                joined_at: p.joined_at,
                localization: l,
            })
        })
        .collect();
    Ok(out)
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
