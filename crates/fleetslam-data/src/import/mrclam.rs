//! Importer for the UTIAS Multi-Robot Cooperative Localization and Mapping dataset
//! (K. Y. K. Leung, Y. Halpern, T. D. Barfoot and H. H. T. Liu, "The UTIAS multi-robot
//! cooperative localization and mapping dataset", IJRR 30(8):969-974, 2011).
//!
//! # Format
//!
//! Tab-separated tables with `#` header lines, times in UNIX seconds on one clock:
//!
//! | file | columns |
//! |---|---|
//! | `RobotN_Odometry.dat` | time, forward velocity v (m/s), angular velocity w (rad/s); ~100 Hz |
//! | `RobotN_Measurement.dat` | time, barcode, range (m), bearing (rad) |
//! | `RobotN_Groundtruth.dat` | time, x, y, heading (Vicon, ~100 Hz) |
//! | `Landmark_Groundtruth.dat` | subject, x, y, std-dev x, std-dev y |
//! | `Barcodes.dat` | subject, barcode (subjects 1-5 are the robots, 6-20 the landmarks) |
//!
//! # Output
//!
//! Robots `"1"`..`"5"` with [`Motion::Velocity`] segments, landmark ids = subject numbers,
//! sightings of other robots as [`fleetslam_core::log::RobotSighting`]s, times kept in
//! UNIX seconds. Each robot starts at its first ground-truth pose and time (the shared
//! frame is Vicon's). The truth is each robot's Vicon trajectory (thinned to at most
//! 20 Hz) and the surveyed landmark positions.
//!
//! # Pitfalls handled
//!
//! - Ground truth starts 6-16 s before a robot's odometry (odometry starts when the robot
//!   starts moving): the robot starts at its first truth pose and is still until its first
//!   odometry sample.
//! - Odometry has gaps of 0.5-1.4 s while the robot keeps moving: the last command holds
//!   over a gap (gaps longer than [`super::CONTROL_GAP_THRESHOLD`] are counted).
//! - Some odometry timestamps repeat: the last sample of a timestamp wins (counted).
//! - Odometry is the commanded velocity and leads Vicon by about 0.15-0.2 s:
//!   [`MrclamOptions::odometry_delay`] shifts it (default [`SUGGESTED_ODOMETRY_DELAY`]).
//! - Up to 10 readings share a timestamp: they become one record.
//! - Barcodes in no row of `Barcodes.dat` are misreads: rejected and counted, never an error.
//! - Robot 1's ground truth ends about 130 s before its odometry: reported per robot in
//!   [`super::ImportReport::truth_ends_early`].
//! - The camera's field of view is narrow: the header's sensor range is measured from the
//!   readings (99th-percentile range, twice the largest |bearing|).

use super::{
    CONTROL_GAP_THRESHOLD, ControlTrack, ImportError, ImportReport, Imported, Observation,
    RobotImportStats, Row, build_records, check_common_options, check_span, dir_name, downsample,
    group_by_time, quantile, read_table, sort_by_time,
};
use crate::formats::{LandmarkRow, TrajectoryPoint, Truth};
use fleetslam_core::config::OdometryCalibration;
use fleetslam_core::log::{
    LOG_VERSION, LandmarkObservation, Log, LogHeader, RobotSighting, RobotStart, SensorRange,
    record_order,
};
use fleetslam_core::motion::{Motion, MotionModel, MotionNoise};
use fleetslam_core::pose::{Pose2, PoseGaussian, wrap_angle};
use fleetslam_core::sensor::{LandmarkKind, SensorNoise};
use std::collections::HashMap;
use std::path::Path;

/// The robots of an MRCLAM dataset (subjects 1-5).
pub const ROBOTS: [&str; 5] = ["1", "2", "3", "4", "5"];

/// Ground-truth trajectories are thinned to at most this rate (Hz).
pub const TRUTH_MAX_RATE_HZ: f64 = 20.0;

/// Quantile of landmark ranges used as the header's maximum range.
pub const RANGE_QUANTILE: f64 = 0.99;

/// Standard deviation of the start pose (m and rad): the first Vicon pose is near exact.
const START_SIGMA: f64 = 1e-3;

/// Ground truth that ends this many seconds (s) before a robot's data is reported.
const TRUTH_EARLY_THRESHOLD: f64 = 1.0;

/// Options of [`import_mrclam`].
#[derive(Debug, Clone, PartialEq)]
pub struct MrclamOptions {
    /// Drop landmark ids (data association left to the filter). Robot sightings keep
    /// their robot id.
    pub no_ids: bool,
    /// Keep only the first `duration` seconds after the earliest start (records and truth).
    pub duration: Option<f64>,
    /// Emit motion-only records so that a robot never goes longer than this (s) without
    /// a record. Default 0.2.
    pub max_record_interval: f64,
    /// Seconds added to odometry timestamps. Default [`SUGGESTED_ODOMETRY_DELAY`]; 0 keeps
    /// the data as recorded.
    pub odometry_delay: f64,
    /// Import only these robots (ids "1".."5"); all five when `None`.
    pub robots: Option<Vec<String>>,
    /// Skip the first `start` seconds after the earliest start: each robot then starts at its
    /// first ground-truth pose at or after that time, and records and truth begin there
    /// (a later time span of the same robots, as a run of its own). `duration` still counts
    /// from the earliest start, so the span kept is `[start, duration]`.
    pub start: Option<f64>,
}

impl Default for MrclamOptions {
    fn default() -> Self {
        Self {
            no_ids: false,
            duration: None,
            max_record_interval: 0.2,
            odometry_delay: SUGGESTED_ODOMETRY_DELAY,
            robots: None,
            start: None,
        }
    }
}

/// The default odometry delay (s). The data set's README measures that odometry, the
/// commanded velocity, leads the Vicon truth by about 0.15-0.2 s, and the camera's readings
/// are on Vicon's clock. Measured on Dataset 6 (all five robots, 500 particles, FastSLAM 2.0,
/// known ids, seeds 1-10, bearing noise 0.03 rad): team ATE mean 0.222 m (worst seed
/// 0.244 m) at 0.1 s, 0.211 m (0.234 m) at 0.15 s; 0.05 s and 0.2 s were worse on seeds 1-6
/// (`cargo run --release --example filter_seeds -- mrclam --odometry-delay D`).
pub const SUGGESTED_ODOMETRY_DELAY: f64 = 0.15;

/// Suggested motion noise: the README measures odometry errors of 0.035-0.047 rad/sqrt(s)
/// in heading and 0.012-0.026 m/sqrt(s) in distance, plus a distance under-report of
/// about 3%.
pub fn suggested_motion_noise() -> MotionNoise {
    MotionNoise {
        trans_per_m: 0.05,
        lateral_per_m: 0.02,
        rot_per_rad: 0.05,
        rot_per_m: 0.05,
        trans_per_sqrt_s: 0.03,
        rot_per_sqrt_s: 0.05,
        // Odometry gaps of up to 1.4 s while the robot keeps moving (see the README).
        random_walk_max_dt: 2.0,
    }
}

/// Suggested online odometry calibration, with ids only. Dataset 6's odometry over-reports
/// distance by 5-9 % and rotation by 3-6 % per robot (regression of the Vicon
/// displacement on the odometry's over 1-3 s windows): with each robot's scales estimated
/// (prior standard deviation 0.05, random walk 0.001/√s) the full run with ids (1,000
/// particles, seeds 1-10) gave team ATE mean 0.208 m (worst seed 0.231 m), against
/// 0.226 m (0.267 m) without; a prior of 0.03 gave 0.216 m and 0.08 gave 0.227 m (seeds
/// 1-5), and inflating the motion noise instead (0.071 per m and per rad) 0.239 m. Without
/// ids the scales' dimensions cost more than they give (first 300 s, 200 particles, seeds
/// 1-4: team ATE mean 0.383 m and 4-6 of the 6 groups, against 0.259 m and 6 of 6), so
/// the `--no-ids` header leaves calibration off
/// (`cargo run --release --example filter_seeds -- mrclam`, with
/// `FLEETSLAM_EXPERIMENT_CONFIG` setting `odometry_calibration`).
pub fn suggested_odometry_calibration() -> OdometryCalibration {
    OdometryCalibration {
        distance_std: 0.05,
        rotation_std: 0.05,
        distance_walk_per_sqrt_s: 0.001,
        rotation_walk_per_sqrt_s: 0.001,
    }
}

/// Suggested measurement noise without ids, and for the robots' sightings of each other
/// (with ids: [`suggested_sensor_noise_with_ids`]), for a FastSLAM: larger than the robust true noise
/// (range 0.07-0.18 m, bearing 0.005-0.02 rad), for the members of a barcode group (one
/// landmark without ids), the timing left after the odometry delay and the inflation a
/// sample set needs. Measured on the full data set (500 particles, FastSLAM 2.0 with
/// deferred sampling, odometry delay 0.15 s, seeds 1-10, `cargo run --release --example
/// filter_seeds -- mrclam` with `FLEETSLAM_EXPERIMENT_CONFIG` setting `sensor_noise`):
/// known ids, team ATE mean (worst seed) 0.215 m (0.240 m) at range 0.3 m / bearing
/// 0.04 rad, 0.211 m (0.234 m) at 0.03 rad, 0.218 m (0.249 m) at 0.02 rad, 0.220 m
/// (0.240 m) at 0.25 m / 0.03 rad; without ids (first 300 s, 200 particles, seeds 1-4)
/// 0.04 rad mapped each of the 6 landmark groups in every seed with at most 1 spurious
/// landmark, where 0.03 rad without the minimum separation (odometry delay 0.1 s) split
/// groups into their members (9-10 spurious). Before
/// deferred sampling, 0.08 rad was needed (0.03 rad lost robots).
pub fn suggested_sensor_noise() -> SensorNoise {
    SensorNoise {
        range: 0.3,
        bearing: 0.04,
        ..SensorNoise::default()
    }
}

/// Suggested landmark measurement noise with ids: a range noise that grows with the range,
/// as the camera's does. Against Vicon, the range error's standard deviation is 0.07 m at
/// 1-2 m, 0.11 m at 2-3 m, 0.16 m at 3-4 m and 0.19 m at 4-5 m (`python3
/// tools/mrclam_range_error.py`): about 4 % of the range. The filter is told twice that
/// growth on a small constant (0.05 m + 8 %: 0.13 m at 1 m, 0.33 m at 4 m; bearing
/// 0.04 rad as [`suggested_sensor_noise`]), where the constant 0.3 m weighed near
/// readings as little as far ones. Full run, 1,000 particles, FastSLAM 2.0 (`cargo run
/// --release --example filter_seeds -- mrclam --seeds 1-40` with `FLEETSLAM_EXPERIMENT_CONFIG`
/// setting `sensor_noise`): team ATE mean 0.212 m (worst seed 0.251 m) over seeds 1-10 and
/// 0.213 m (0.268 m) over seeds 11-40, against 0.225 m (0.304 m) and 0.217 m (0.279 m) with
/// the constant noise; 0.1 m + 6 % gave 0.225 m (0.253 m), 0.1 m + 8 % 0.217 m (0.251 m)
/// and the measured growth itself (0.05 m + 4 %) 0.247 m (0.276 m) over seeds 1-10. Without
/// ids a landmark is a group of barcodes 0.18-0.25 m apart, whose spread dominates the near
/// readings' error: there 0.05 m + 8 % mapped all 6 groups in 4 of seeds 1-10 (team ATE
/// mean 0.284 m), the constant noise in 7 (0.275 m), so the `--no-ids` header keeps
/// [`suggested_sensor_noise`], and so do the robots' sightings of each other.
pub fn suggested_sensor_noise_with_ids() -> SensorNoise {
    SensorNoise {
        range: 0.05,
        range_per_m: 0.08,
        bearing: 0.04,
        ..SensorNoise::default()
    }
}

/// The smallest distance between distinct landmarks that a `--no-ids` header suggests (m):
/// half the smallest distance between the centres of the 6 barcode groups (1.8 m in
/// `Landmark_Groundtruth.dat`; a group's members stand 0.18-0.25 m apart and count as one
/// landmark without ids), so that an observation that matches no landmark but lies closer
/// to one than halfway to the next group starts no landmark. With the filter's default
/// (0.45 m) a robot whose pose had drifted 0.5-1 m mapped a second, shifted copy of the
/// groups it saw and went on in that copy's frame: on the full run (1,000 particles,
/// seeds 1-10) team ATE mean 0.376 m (worst seed 0.524 m) with 3-6 of the 6 groups mapped
/// within 0.3 m and 1-5 spurious landmarks, against 0.263 m (0.317 m), 3-6 of 6 and 0-3
/// with 0.9 m (`cargo run --release --example filter_seeds -- mrclam --no-ids`).
pub const NO_IDS_LANDMARK_SEPARATION: f64 = 0.9;

/// One robot's files, parsed and sorted by time.
struct RobotFiles {
    id: String,
    truth: Vec<Row<4>>,
    odometry: Vec<Row<3>>,
    measurements: Vec<Row<4>>,
    out_of_order: [usize; 3],
}

fn load_robot(dir: &Path, id: &str) -> Result<RobotFiles, ImportError> {
    let mut truth = read_table(
        &dir.join(format!("Robot{id}_Groundtruth.dat")),
        ["time", "x", "y", "heading"],
    )?;
    let mut odometry = read_table(
        &dir.join(format!("Robot{id}_Odometry.dat")),
        ["time", "forward velocity", "angular velocity"],
    )?;
    let mut measurements = read_table(
        &dir.join(format!("Robot{id}_Measurement.dat")),
        ["time", "barcode", "range", "bearing"],
    )?;
    let out_of_order = [
        sort_by_time(&mut truth),
        sort_by_time(&mut odometry),
        sort_by_time(&mut measurements),
    ];
    Ok(RobotFiles {
        id: id.to_string(),
        truth,
        odometry,
        measurements,
        out_of_order,
    })
}

/// Reads a column that must hold a non-negative integer (subject, barcode).
fn integer(path: &Path, line: usize, column: &str, v: f64) -> Result<u32, ImportError> {
    if v.fract() == 0.0 && (0.0..=f64::from(u32::MAX)).contains(&v) {
        Ok(v as u32)
    } else {
        Err(ImportError::Parse {
            path: path.to_path_buf(),
            line,
            message: format!("{column} must be a non-negative integer, got {v}"),
        })
    }
}

/// Barcode -> subject, from `Barcodes.dat`.
fn read_barcodes(dir: &Path) -> Result<HashMap<u32, u32>, ImportError> {
    let path = dir.join("Barcodes.dat");
    let rows = read_table(&path, ["subject", "barcode"])?;
    let mut map = HashMap::with_capacity(rows.len());
    for (line, [subject, barcode]) in rows {
        let subject = integer(&path, line, "subject", subject)?;
        let barcode = integer(&path, line, "barcode", barcode)?;
        if subject == 0 {
            return Err(ImportError::Parse {
                path,
                line,
                message: "subjects are numbered from 1".into(),
            });
        }
        if let Some(other) = map.insert(barcode, subject)
            && other != subject
        {
            return Err(ImportError::Parse {
                path,
                line,
                message: format!("barcode {barcode} is given to subjects {other} and {subject}"),
            });
        }
    }
    if map.is_empty() {
        return Err(ImportError::Missing(format!(
            "{} has no rows",
            path.display()
        )));
    }
    Ok(map)
}

/// Landmark truth from `Landmark_Groundtruth.dat`.
fn read_landmarks(dir: &Path, report: &mut ImportReport) -> Result<Vec<LandmarkRow>, ImportError> {
    let path = dir.join("Landmark_Groundtruth.dat");
    let rows = read_table(&path, ["subject", "x", "y", "std-dev x", "std-dev y"])?;
    let mut out = Vec::with_capacity(rows.len());
    for (line, [subject, x, y, sx, sy]) in rows {
        let id = integer(&path, line, "subject", subject)?;
        if (1..=ROBOTS.len() as u32).contains(&id) {
            report.warnings.push(format!(
                "{} line {line}: subject {id} is a robot, not a landmark; skipped",
                path.display()
            ));
            continue;
        }
        out.push(LandmarkRow {
            id: Some(id),
            mean: [x, y, 0.0],
            cov: [sx * sx, 0.0, 0.0, sy * sy, 0.0, 0.0],
        });
    }
    Ok(out)
}

fn robot_list(opts: &MrclamOptions) -> Result<Vec<String>, ImportError> {
    let Some(wanted) = &opts.robots else {
        return Ok(ROBOTS.iter().map(|r| r.to_string()).collect());
    };
    let mut out: Vec<String> = Vec::with_capacity(wanted.len());
    for r in wanted {
        if !ROBOTS.contains(&r.as_str()) {
            return Err(ImportError::InvalidOption(format!(
                "robot {r:?} is not an MRCLAM robot (ids are \"1\" to \"5\")"
            )));
        }
        if !out.contains(r) {
            out.push(r.clone());
        }
    }
    if out.is_empty() {
        return Err(ImportError::InvalidOption(
            "the robot subset is empty".into(),
        ));
    }
    out.sort();
    Ok(out)
}

/// Imports an MRCLAM dataset directory (e.g. `MRCLAM_Dataset6`). See the module docs.
pub fn import_mrclam(dir: &Path, opts: &MrclamOptions) -> Result<Imported, ImportError> {
    check_common_options(opts.duration, opts.max_record_interval)?;
    if !opts.odometry_delay.is_finite() || opts.odometry_delay.abs() > 10.0 {
        return Err(ImportError::InvalidOption(format!(
            "odometry_delay must be a finite number of seconds within +-10, got {}",
            opts.odometry_delay
        )));
    }
    let robots = robot_list(opts)?;
    let name = dir_name(dir, "mrclam");
    let mut report = ImportReport {
        dataset: name.clone(),
        ..ImportReport::default()
    };
    let barcodes = read_barcodes(dir)?;
    let landmarks = read_landmarks(dir, &mut report)?;

    let files: Vec<RobotFiles> = std::thread::scope(|s| {
        let handles: Vec<_> = robots
            .iter()
            .map(|id| (id, s.spawn(move || load_robot(dir, id))))
            .collect();
        handles
            .into_iter()
            .map(|(id, h)| {
                h.join().unwrap_or_else(|_| {
                    Err(ImportError::io(
                        dir,
                        std::io::Error::other(format!("the reader of robot {id}'s files failed")),
                    ))
                })
            })
            .collect::<Result<_, _>>()
    })?;

    // Each robot starts at its first ground-truth pose.
    let mut starts = Vec::with_capacity(files.len());
    for f in &files {
        let Some((_, [t, x, y, th])) = f.truth.first() else {
            return Err(ImportError::Missing(format!(
                "{} has no data rows: the start pose of robot {} is its first ground-truth pose",
                dir.join(format!("Robot{}_Groundtruth.dat", f.id)).display(),
                f.id
            )));
        };
        starts.push((*t, Pose2::new(*x, *y, wrap_angle(*th))));
    }
    let t_start = starts.iter().map(|s| s.0).fold(f64::INFINITY, f64::min);
    let cutoff = opts.duration.map_or(f64::INFINITY, |d| t_start + d);
    if let Some(skip) = opts.start {
        if !(skip.is_finite() && skip >= 0.0) || opts.duration.is_some_and(|d| d <= skip) {
            return Err(ImportError::InvalidOption(format!(
                "start must be a finite number of seconds >= 0 and below the duration, got {skip}"
            )));
        }
        for (f, s) in files.iter().zip(starts.iter_mut()) {
            let from = (t_start + skip).max(s.0);
            let Some((_, [t, x, y, th])) = f.truth.iter().find(|(_, [t, ..])| *t >= from) else {
                return Err(ImportError::InvalidOption(format!(
                    "start {skip} s: robot {} has no ground truth from then on",
                    f.id
                )));
            };
            *s = (*t, Pose2::new(*x, *y, wrap_angle(*th)));
        }
    }

    let mut records = Vec::new();
    let mut truth = Truth {
        trajectories: Default::default(),
        landmarks,
    };
    let mut ranges = Vec::new();
    let mut bearings = Vec::new();
    let mut truth_rows = 0;
    let mut header_robots = Vec::with_capacity(files.len());
    for (f, &(t0, start)) in files.iter().zip(&starts) {
        let id = f.id.as_str();
        header_robots.push(RobotStart {
            id: id.to_string(),
            start: Some(PoseGaussian::diagonal(
                start,
                START_SIGMA,
                START_SIGMA,
                START_SIGMA,
            )),
            t0: Some(t0),
        });
        for (what, n) in ["ground truth", "odometry", "measurement"]
            .iter()
            .zip(f.out_of_order)
        {
            if n > 0 {
                report.warnings.push(format!(
                    "robot {id}: {n} {what} row(s) out of time order; sorted"
                ));
            }
        }
        let mut stats = RobotImportStats {
            t0,
            ..RobotImportStats::default()
        };

        // Odometry: (t + delay, [v, w]).
        let (track, repeated) = ControlTrack::new(
            f.odometry
                .iter()
                .map(|(_, [t, v, w])| (t + opts.odometry_delay, [*v, *w])),
        );
        stats.repeated_timestamps = repeated;

        // Measurements.
        let mut obs = Vec::with_capacity(f.measurements.len());
        let meas_path = dir.join(format!("Robot{id}_Measurement.dat"));
        for &(line, [t, barcode, range, bearing]) in &f.measurements {
            if t > cutoff {
                break;
            }
            let barcode = integer(&meas_path, line, "barcode", barcode)?;
            let Some(&subject) = barcodes.get(&barcode) else {
                stats.misread_barcodes += 1;
                continue;
            };
            if t < t0 {
                report.drop_detection(
                    "before the robot's start (its first ground-truth pose, or the start option)",
                );
                continue;
            }
            if range <= 0.0 {
                report.drop_detection("range not positive");
                continue;
            }
            let z = vec![range, wrap_angle(bearing)];
            if (1..=ROBOTS.len() as u32).contains(&subject) {
                let seen = subject.to_string();
                if seen == id {
                    report.drop_detection("robot sighting of itself");
                } else if !robots.contains(&seen) {
                    report.drop_detection("sighting of a robot not imported");
                } else {
                    obs.push((t, Observation::Robot(RobotSighting { robot: seen, z })));
                }
            } else {
                ranges.push(range);
                bearings.push(z[1].abs());
                let id = (!opts.no_ids).then_some(subject);
                obs.push((t, Observation::Landmark(LandmarkObservation { id, z })));
            }
        }
        let groups = group_by_time(obs);

        // The robot's data ends with its last odometry sample or measurement.
        let data_end = [track.last_time(), groups.last().map(|g| g.t)]
            .into_iter()
            .flatten()
            .fold(t0, f64::max);
        let t_end = data_end.min(cutoff).max(t0);
        stats.t_end = t_end;
        check_span(id, t0, t_end)?;
        let recs = build_records(
            id,
            &track,
            groups,
            t0,
            t_end,
            opts.max_record_interval,
            Motion::Velocity,
        );
        stats.records = recs.len();
        stats.motion_only_records = recs
            .iter()
            .filter(|r| r.landmarks.is_empty() && r.robots.is_empty())
            .count();
        stats.landmark_observations = recs.iter().map(|r| r.landmarks.len()).sum();
        stats.robot_sightings = recs.iter().map(|r| r.robots.len()).sum();
        (stats.control_gaps, stats.longest_control_gap) =
            track.gaps(t0, t_end, CONTROL_GAP_THRESHOLD);
        match track.first_time() {
            Some(first) => {
                stats.still_before_first_control = (first.min(t_end) - t0).max(0.0);
                if stats.still_before_first_control > 0.0 {
                    report.notes.push(format!(
                        "robot {id}: odometry starts {:.2} s after its start pose; still until then",
                        stats.still_before_first_control
                    ));
                }
            }
            None => report.warnings.push(format!(
                "robot {id}: no odometry; the robot is taken to be still"
            )),
        }
        if let Some(last) = track.last_time()
            && t_end - last > CONTROL_GAP_THRESHOLD
        {
            report.warnings.push(format!(
                "robot {id}: odometry ends {:.2} s before its last record; the last command holds",
                t_end - last
            ));
        }
        records.extend(recs);

        // Ground truth, cut at the cutoff and thinned.
        let points: Vec<TrajectoryPoint> = f
            .truth
            .iter()
            .skip_while(|(_, [t, ..])| *t < t0)
            .take_while(|(_, [t, ..])| *t <= cutoff)
            .map(|(_, [t, x, y, th])| TrajectoryPoint {
                t: *t,
                pose: Pose2::new(*x, *y, wrap_angle(*th)),
            })
            .collect();
        truth_rows += points.len();
        let points = downsample(&points, |p| p.t, 1.0 / TRUTH_MAX_RATE_HZ);
        let truth_end = points.last().map_or(t0, |p| p.t);
        if t_end - truth_end > TRUTH_EARLY_THRESHOLD {
            stats.truth_ends_early = t_end - truth_end;
            report.warnings.push(format!(
                "robot {id}: ground truth ends {:.1} s before its data; evaluate only where truth exists",
                stats.truth_ends_early
            ));
        }
        truth.trajectories.insert(id.to_string(), points);
        report.per_robot.insert(id.to_string(), stats);
    }
    records.sort_by(record_order);

    // Sensor range measured from the valid landmark readings.
    let sensor_range = match (
        quantile(&ranges, RANGE_QUANTILE),
        bearings.iter().copied().reduce(f64::max),
    ) {
        (Some(max_range), Some(max_bearing)) => {
            report.notes.push(format!(
                "sensor range measured over {} landmark readings: {:.0}th-percentile range {max_range:.3} m \
                 (largest {:.3} m), largest |bearing| {max_bearing:.3} rad",
                ranges.len(),
                RANGE_QUANTILE * 100.0,
                ranges.iter().copied().fold(0.0, f64::max)
            ));
            Some(SensorRange {
                max_range,
                fov: 2.0 * max_bearing,
            })
        }
        _ => {
            report
                .warnings
                .push("no valid landmark readings: the header has no sensor range".into());
            None
        }
    };
    report.sensor_range = sensor_range;
    let kept: usize = truth.trajectories.values().map(Vec::len).sum();
    report.notes.push(format!(
        "ground truth thinned from {truth_rows} to {kept} poses (at most {TRUTH_MAX_RATE_HZ} Hz)"
    ));
    if opts.odometry_delay != 0.0 {
        report.notes.push(format!(
            "odometry timestamps shifted by {:+.3} s",
            opts.odometry_delay
        ));
    }
    if opts.no_ids {
        report.notes.push(format!(
            "no ids: the header suggests a landmark separation of {NO_IDS_LANDMARK_SEPARATION} m \
             (half the smallest distance between the barcode groups; features closer count \
             as one landmark)"
        ));
    }
    report.finish(&records);

    let header = LogHeader {
        fleetslam_log: LOG_VERSION,
        name: Some(name),
        landmark_kind: LandmarkKind::RangeBearing2d,
        motion_model: MotionModel::Velocity,
        ackermann: None,
        motion_noise: Some(suggested_motion_noise()),
        odometry_calibration: (!opts.no_ids).then(suggested_odometry_calibration),
        sensor_noise: Some(if opts.no_ids {
            suggested_sensor_noise()
        } else {
            suggested_sensor_noise_with_ids()
        }),
        sighting_noise: Some(suggested_sensor_noise()),
        sensor_range,
        landmark_separation: opts.no_ids.then_some(NO_IDS_LANDMARK_SEPARATION),
        landmark_ids: !opts.no_ids,
        truth_frame: true,
        robots: header_robots,
    };
    Ok(Imported {
        log: Log { header, records },
        truth,
        report,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use fleetslam_core::math;
    use fleetslam_core::motion::AckermannParams;
    use std::sync::OnceLock;

    const DATA: &str = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../../shared/datasets/mrclam-dataset6"
    );

    fn data_dir() -> Option<&'static Path> {
        let p = Path::new(DATA);
        if p.is_dir() {
            Some(p)
        } else {
            assert!(
                !std::env::var("FLEETSLAM_REQUIRE_DATA").is_ok_and(|v| v == "1"),
                "{DATA} is missing and FLEETSLAM_REQUIRE_DATA=1"
            );
            println!("skipped: {DATA} is missing");
            None
        }
    }

    /// The first 60 s of Dataset 6, imported once for all tests.
    fn slice() -> Option<&'static Imported> {
        static SLICE: OnceLock<Option<Imported>> = OnceLock::new();
        SLICE
            .get_or_init(|| {
                let dir = data_dir()?;
                let opts = MrclamOptions {
                    duration: Some(60.0),
                    ..MrclamOptions::default()
                };
                Some(import_mrclam(dir, &opts).expect("the 60 s slice imports"))
            })
            .as_ref()
    }

    /// Linear interpolation of a trajectory's position at `t`.
    fn position_at(points: &[TrajectoryPoint], t: f64) -> Option<(f64, f64)> {
        let i = points.partition_point(|p| p.t <= t);
        let (a, b) = (points.get(i.checked_sub(1)?)?, points.get(i)?);
        let s = (t - a.t) / (b.t - a.t);
        Some((
            a.pose.x + s * (b.pose.x - a.pose.x),
            a.pose.y + s * (b.pose.y - a.pose.y),
        ))
    }

    #[test]
    fn slice_has_five_robots_sorted_contiguous_records() {
        let Some(imp) = slice() else { return };
        let log = &imp.log;
        assert_eq!(log.header.name.as_deref(), Some("mrclam-dataset6"));
        assert_eq!(log.header.robots.len(), 5);
        assert!(log.header.landmark_ids);
        assert_eq!(imp.truth.trajectories.len(), 5);
        assert_eq!(imp.truth.landmarks.len(), 15);
        assert!(
            log.records
                .windows(2)
                .all(|w| record_order(&w[0], &w[1]).is_lt())
        );
        let t_start = imp.report.t_start;
        for rs in &log.header.robots {
            let mine: Vec<_> = log.records.iter().filter(|r| r.robot == rs.id).collect();
            assert!(!mine.is_empty(), "robot {}", rs.id);
            let mut prev = rs.t0.expect("t0");
            for (i, r) in mine.iter().enumerate() {
                assert_eq!(r.seq, i as u64);
                let Some(Motion::Velocity(segs)) = &r.motion else {
                    panic!("velocity motion expected: {r:?}");
                };
                let d: f64 = segs.iter().map(|s| s[2]).sum();
                assert!(
                    (d - (r.t - prev)).abs() < 1e-9,
                    "robot {} seq {}",
                    r.robot,
                    r.seq
                );
                assert!(r.t - prev <= 0.2 + 1e-6);
                prev = r.t;
            }
            assert!(prev <= t_start + 60.0 + 1e-9);
            let truth = &imp.truth.trajectories[&rs.id];
            assert!(truth.last().is_some_and(|p| p.t <= t_start + 60.0));
            assert!(
                truth
                    .windows(2)
                    .all(|w| w[1].t - w[0].t >= 0.05 - 1e-6 || w[1].t == truth[truth.len() - 1].t)
            );
        }
        let rep = &imp.report;
        assert_eq!(rep.records, log.records.len());
        assert!(rep.landmark_observations > 0 && rep.robot_sightings > 0);
        let range = rep.sensor_range.expect("sensor range measured");
        assert!(
            range.fov > 0.5 && range.fov < 1.6 && range.max_range > 3.0 && range.max_range < 9.0
        );
        assert_eq!(log.header.sensor_range, Some(range));
        println!("{rep}");
    }

    #[test]
    fn slice_round_trips_through_the_log_format() {
        let Some(imp) = slice() else { return };
        let mut buf = Vec::new();
        imp.log.write(&mut buf).expect("write");
        let back = Log::read(&buf[..]).expect("read back");
        assert_eq!(back.header, imp.log.header);
        assert_eq!(back.records.len(), imp.log.records.len());
        for (a, b) in back.records.iter().zip(&imp.log.records) {
            assert_eq!(a, b);
        }
        let dir = tempfile::TempDir::new().expect("tempdir");
        imp.write(dir.path()).expect("write the import");
        for f in [
            "log.ndjson",
            "import_report.json",
            "truth/trajectory_1.tum",
            "truth/landmarks.csv",
        ] {
            assert!(dir.path().join(f).is_file(), "{f}");
        }
        let truth = Truth::read_dir(&dir.path().join("truth")).expect("truth reads back");
        assert_eq!(truth.trajectories.len(), 5);
        let report: serde_json::Value = serde_json::from_str(
            &std::fs::read_to_string(dir.path().join("import_report.json")).expect("report"),
        )
        .expect("report is JSON");
        assert_eq!(report["records"].as_u64(), Some(imp.report.records as u64));
    }

    #[test]
    fn robot_1_dead_reckoning_follows_truth_for_30_s() {
        let Some(imp) = slice() else { return };
        let start = &imp.log.header.robots[0];
        assert_eq!(start.id, "1");
        let stats = &imp.report.per_robot["1"];
        assert!(stats.still_before_first_control > 5.0, "{stats:?}");
        let until = stats.t0 + stats.still_before_first_control + 30.0;
        let mut pose = start.start.expect("start").mean;
        let mut t = stats.t0;
        for r in imp.log.records.iter().filter(|r| r.robot == "1") {
            if r.t > until {
                break;
            }
            let m = r.motion.as_ref().expect("motion");
            pose = pose.compose(&m.increment(&AckermannParams::default()));
            t = r.t;
        }
        assert!(until - t < 0.2 + 1e-6);
        let (x, y) = position_at(&imp.truth.trajectories["1"], t).expect("truth at t");
        let err = math::hypot(pose.x - x, pose.y - y);
        println!("robot 1 after 30 s of motion: dead reckoning is {err:.3} m from Vicon");
        assert!(
            err < 0.5,
            "dead reckoning is {err:.3} m off truth after 30 s"
        );
    }

    #[test]
    fn no_ids_strips_landmark_ids_only() {
        let Some(dir) = data_dir() else { return };
        let opts = MrclamOptions {
            no_ids: true,
            duration: Some(30.0),
            robots: Some(vec!["2".into(), "3".into()]),
            ..MrclamOptions::default()
        };
        let imp = import_mrclam(dir, &opts).expect("import");
        assert!(!imp.log.header.landmark_ids);
        assert_eq!(imp.log.header.robots.len(), 2);
        let lms = imp.log.records.iter().flat_map(|r| &r.landmarks);
        assert!(lms.clone().count() > 0 && lms.clone().all(|l| l.id.is_none()));
        // Sightings keep the robot id, and only of imported robots.
        for s in imp.log.records.iter().flat_map(|r| &r.robots) {
            assert!(s.robot == "2" || s.robot == "3", "{s:?}");
        }
        assert!(imp.report.robot_sightings > 0);
        assert!(imp.report.detections_dropped["sighting of a robot not imported"] > 0);
        // The header suggests the groups' separation, which the filter takes; with ids the
        // filter keeps its default.
        let h = &imp.log.header;
        assert_eq!(h.landmark_separation, Some(NO_IDS_LANDMARK_SEPARATION));
        assert!(
            imp.report
                .notes
                .iter()
                .any(|n| n.contains("landmark separation of 0.9 m")),
            "{:?}",
            imp.report.notes
        );
        let cfg = fleetslam_core::config::FilterConfig::from_header(h);
        assert_eq!(
            cfg.association_params.min_separation,
            NO_IDS_LANDMARK_SEPARATION
        );
        let with_ids = import_mrclam(
            dir,
            &MrclamOptions {
                no_ids: false,
                ..opts
            },
        )
        .unwrap();
        assert_eq!(with_ids.log.header.landmark_separation, None);
        // With ids the landmark range noise grows with the range; without ids (a landmark
        // is a group of barcodes) and for sightings it is constant.
        assert_eq!(h.sensor_noise, Some(suggested_sensor_noise()));
        assert_eq!(h.sighting_noise, Some(suggested_sensor_noise()));
        let wh = &with_ids.log.header;
        assert_eq!(wh.sensor_noise, Some(suggested_sensor_noise_with_ids()));
        assert!(suggested_sensor_noise_with_ids().range_per_m > 0.0);
        assert_eq!(wh.sighting_noise, Some(suggested_sensor_noise()));
        assert_eq!(suggested_sensor_noise().range_per_m, 0.0);
        let default = fleetslam_core::config::AssociationParams::default();
        assert_eq!(
            fleetslam_core::config::FilterConfig::from_header(&with_ids.log.header)
                .association_params
                .min_separation,
            default.min_separation
        );
    }

    #[test]
    fn full_dataset_report() {
        let Some(dir) = data_dir() else { return };
        let t = std::time::Instant::now();
        let imp = import_mrclam(dir, &MrclamOptions::default()).expect("import");
        println!(
            "full MRCLAM import in {:.2} s\n{}",
            t.elapsed().as_secs_f64(),
            imp.report
        );
        let rep = &imp.report;
        assert_eq!(rep.misread_barcodes, 6);
        assert_eq!(rep.repeated_timestamps, 23);
        assert!(rep.truth_ends_early.get("1").is_some_and(|s| *s > 100.0));
        assert_eq!(rep.truth_ends_early.len(), 1);
        assert_eq!(rep.per_robot["4"].control_gaps, 94);
        assert_eq!(
            rep.landmark_observations + rep.robot_sightings,
            // Every reading with a known barcode, minus none dropped.
            19_377 - rep.misread_barcodes - rep.detections_dropped.values().sum::<usize>()
        );
    }

    /// A small, valid two-robot directory.
    fn tiny(dir: &Path) {
        let w = |name: &str, text: &str| std::fs::write(dir.join(name), text).expect("write");
        w("Barcodes.dat", "# subject barcode\n1 5\n2 14\n6 63\n7 81\n");
        w(
            "Landmark_Groundtruth.dat",
            "6 1.0 0.0 0.001 0.002\n7 0.0 2.0 0.001 0.001\n",
        );
        for r in ["1", "2"] {
            w(
                &format!("Robot{r}_Groundtruth.dat"),
                "10.0 0 0 0\n10.5 0 0 0\n12.0 0.2 0 0\n",
            );
            w(
                &format!("Robot{r}_Odometry.dat"),
                "11.0 0.1 0.0\n11.0 0.2 0.0\n11.5 0.2 0.1\n",
            );
            w(
                &format!("Robot{r}_Measurement.dat"),
                "11.2 63 1.0 0.1\n11.2 14 2.0 -0.1\n11.3 99 1.0 0.0\n11.4 81 2.0 0.3\n",
            );
        }
    }

    /// Robots 1 and 2 of the tiny data, as recorded (no odometry delay).
    fn two_robots() -> MrclamOptions {
        MrclamOptions {
            robots: Some(vec!["1".into(), "2".into()]),
            odometry_delay: 0.0,
            ..MrclamOptions::default()
        }
    }

    #[test]
    fn tiny_directory_imports_and_counts_misreads() {
        let tmp = tempfile::TempDir::new().expect("tempdir");
        tiny(tmp.path());
        let imp = import_mrclam(tmp.path(), &two_robots()).expect("import");
        let rep = &imp.report;
        assert_eq!(rep.misread_barcodes, 2, "{rep}");
        assert_eq!(rep.repeated_timestamps, 2);
        assert_eq!(rep.detections_dropped["robot sighting of itself"], 1);
        assert_eq!(rep.landmark_observations, 4);
        assert_eq!(rep.robot_sightings, 1);
        let r1: Vec<_> = imp.log.records.iter().filter(|r| r.robot == "1").collect();
        // Still from 10.0 to 11.0, then v = 0.2 (the repeated 11.0 sample wins).
        let first = r1
            .iter()
            .find(|r| !r.landmarks.is_empty())
            .expect("a landmark record");
        assert!((first.t - 11.2).abs() < 1e-12);
        let segs: Vec<[f64; 3]> = r1
            .iter()
            .take_while(|r| r.t <= 11.2)
            .flat_map(|r| match &r.motion {
                Some(Motion::Velocity(s)) => s.clone(),
                _ => Vec::new(),
            })
            .collect();
        let moving: f64 = segs.iter().filter(|s| s[0] == 0.2).map(|s| s[2]).sum();
        let still: f64 = segs.iter().filter(|s| s[0] == 0.0).map(|s| s[2]).sum();
        assert!(
            (moving - 0.2).abs() < 1e-9 && (still - 1.0).abs() < 1e-9,
            "{segs:?}"
        );
        assert!(segs.iter().all(|s| s[0] != 0.1));
        // Records end with the last odometry sample.
        assert!(r1.last().is_some_and(|r| (r.t - 11.5).abs() < 1e-12));
        assert_eq!(imp.report.sensor_range.map(|s| s.max_range), Some(2.0));
    }

    #[test]
    fn odometry_delay_shifts_the_commands() {
        let tmp = tempfile::TempDir::new().expect("tempdir");
        tiny(tmp.path());
        let opts = MrclamOptions {
            odometry_delay: 0.1,
            ..two_robots()
        };
        let imp = import_mrclam(tmp.path(), &opts).expect("import");
        let stats = &imp.report.per_robot["1"];
        assert!(
            (stats.still_before_first_control - 1.1).abs() < 1e-9,
            "{stats:?}"
        );
        // The last odometry sample moves to 11.6, and so does the robot's last record.
        assert!((stats.t_end - 11.6).abs() < 1e-9);
    }

    #[test]
    fn broken_directories_error_clearly() {
        let tmp = tempfile::TempDir::new().expect("tempdir");
        let dir = tmp.path();
        let check = |want: &[&str]| {
            let e = import_mrclam(dir, &two_robots()).expect_err("must fail");
            let s = e.to_string();
            assert!(want.iter().all(|w| s.contains(w)), "{s}");
        };

        tiny(dir);
        std::fs::remove_file(dir.join("Robot2_Odometry.dat")).expect("rm");
        check(&["Robot2_Odometry.dat"]);

        tiny(dir);
        std::fs::write(
            dir.join("Robot1_Measurement.dat"),
            "# h\n11.2 63 1.0 0.1\n11.3 63 abc 0.1\n",
        )
        .expect("write");
        check(&["Robot1_Measurement.dat", "line 3", "range"]);

        tiny(dir);
        std::fs::write(dir.join("Robot1_Measurement.dat"), "11.2 6.5 1.0 0.1\n").expect("write");
        check(&["Robot1_Measurement.dat", "line 1", "barcode"]);

        tiny(dir);
        std::fs::write(dir.join("Robot2_Groundtruth.dat"), "# only a header\n").expect("write");
        check(&["Robot2_Groundtruth.dat", "no data rows"]);

        tiny(dir);
        std::fs::write(dir.join("Barcodes.dat"), "1 5\n2 5\n").expect("write");
        check(&["Barcodes.dat", "line 2", "barcode 5"]);

        tiny(dir);
        std::fs::write(dir.join("Robot1_Measurement.dat"), "1e10 63 1.0 0.1\n").expect("write");
        check(&["robot 1", "check the timestamps"]);

        tiny(dir);
        let bad = MrclamOptions {
            robots: Some(vec!["7".into()]),
            ..MrclamOptions::default()
        };
        assert!(matches!(
            import_mrclam(dir, &bad),
            Err(ImportError::InvalidOption(_))
        ));
        let bad = MrclamOptions {
            max_record_interval: 0.0,
            ..two_robots()
        };
        assert!(matches!(
            import_mrclam(dir, &bad),
            Err(ImportError::InvalidOption(_))
        ));
        assert!(import_mrclam(&dir.join("nowhere"), &two_robots()).is_err());
    }

    /// `start` keeps a later time span as a run of its own: each robot starts at its first
    /// truth pose at or after the start, no record or truth point lies before it, and the
    /// motion integrates the odometry from there.
    #[test]
    fn start_keeps_a_later_time_span() {
        let tmp = tempfile::TempDir::new().expect("tempdir");
        tiny(tmp.path());
        let opts = MrclamOptions {
            start: Some(0.3),
            ..two_robots()
        };
        let imp = import_mrclam(tmp.path(), &opts).expect("import");
        let whole = import_mrclam(tmp.path(), &two_robots()).expect("import");
        for rs in &imp.log.header.robots {
            // The truth row at 10.5 is the first at or after 10.0 + 0.3.
            assert_eq!(rs.t0, Some(10.5), "{rs:?}");
        }
        assert!(imp.log.records.iter().all(|r| r.t >= 10.5));
        // The landmark readings (all after 10.5) are kept; records start at seq 0.
        let seen = |l: &Log| l.records.iter().map(|r| r.landmarks.len()).sum::<usize>();
        assert_eq!(seen(&imp.log), seen(&whole.log));
        assert_eq!(imp.log.records.iter().filter(|r| r.seq == 0).count(), 2);
        for pts in imp.truth.trajectories.values() {
            assert_eq!(pts.first().map(|p| p.t), Some(10.5));
        }
        for bad in [Some(-1.0), Some(f64::NAN), Some(100.0)] {
            let opts = MrclamOptions {
                start: bad,
                ..two_robots()
            };
            assert!(
                matches!(
                    import_mrclam(tmp.path(), &opts),
                    Err(ImportError::InvalidOption(_))
                ),
                "{bad:?}"
            );
        }
    }
}
