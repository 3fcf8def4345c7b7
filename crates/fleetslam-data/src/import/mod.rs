//! Dataset importers: turn public SLAM datasets into a fleetslam observation log
//! ([`Log`]), ground truth ([`Truth`]) and an [`ImportReport`] that says what the import
//! found and changed.
//!
//! - [`mrclam`]: the UTIAS Multi-Robot Cooperative Localization and Mapping dataset
//!   (K. Y. K. Leung, Y. Halpern, T. D. Barfoot and H. H. T. Liu, "The UTIAS multi-robot
//!   cooperative localization and mapping dataset", IJRR 30(8):969-974, 2011): five robots,
//!   velocity commands, range-bearing readings of barcoded landmarks and of each other.
//! - [`victoria`]: Victoria Park (J. Guivant, E. Nebot and S. Baiker, "Autonomous
//!   navigation and map building using laser range sensors in outdoor applications",
//!   Journal of Robotic Systems 17(10):565-583, 2000): one car, Ackermann inputs, tree
//!   detections without ids, GPS as approximate truth.
//!
//! Both importers share the same record scheme. Each robot gets one record per distinct
//! measurement timestamp (every measurement of that instant in one record) plus
//! motion-only records so that no robot goes longer than `max_record_interval` without a
//! record (a longer gap is split into equal parts). A record's motion covers exactly the
//! time since the robot's previous record (or its start): each control sample holds until
//! the next one, the last command holds over gaps in the control stream, a robot is still
//! before its first sample, and samples that repeat a timestamp are collapsed (the last
//! one wins). Runs of equal commands are merged into one segment.
//!
//! [`Imported::write`] stores the result as `OUT/log.ndjson`, `OUT/truth/` (see
//! [`Truth::write_dir`]) and `OUT/import_report.json`.
//!
//! Bad input never panics: a missing file is [`ImportError::Io`] naming the file, an
//! unreadable line is [`ImportError::Parse`] naming the file and line, and recoverable
//! oddities (misread barcodes, detections out of range, ...) are dropped and counted in the
//! report.

pub mod mrclam;
pub mod victoria;

pub use mrclam::{
    MrclamOptions, NO_IDS_LANDMARK_SEPARATION, SUGGESTED_ODOMETRY_DELAY, import_mrclam,
};
pub use victoria::{VictoriaOptions, import_victoria_park};

use crate::formats::Truth;
use fleetslam_core::log::{LandmarkObservation, Log, Record, RobotSighting, SensorRange};
use fleetslam_core::motion::Motion;
use serde::Serialize;
use std::collections::BTreeMap;
use std::fmt;
use std::path::{Path, PathBuf};

/// A gap between consecutive control samples longer than this (s) is reported as a gap
/// (the last command is held over it either way).
pub const CONTROL_GAP_THRESHOLD: f64 = 0.5;

/// Times closer than this (s) are treated as equal when scheduling records.
const TIME_TOL: f64 = 1e-6;

/// An imported dataset: the log to replay, its ground truth, and what the import found.
#[derive(Debug, Clone)]
pub struct Imported {
    pub log: Log,
    pub truth: Truth,
    pub report: ImportReport,
}

impl Imported {
    /// Writes `out/log.ndjson`, `out/truth/` and `out/import_report.json`, creating `out`.
    pub fn write(&self, out: &Path) -> Result<(), ImportError> {
        std::fs::create_dir_all(out).map_err(|e| ImportError::io(out, e))?;
        let log_path = out.join("log.ndjson");
        self.log
            .write_path(&log_path)
            .map_err(|e| ImportError::io(&log_path, e))?;
        let truth_dir = out.join("truth");
        self.truth
            .write_dir(&truth_dir)
            .map_err(|e| ImportError::io(&truth_dir, e))?;
        let report_path = out.join("import_report.json");
        let write_report = || -> std::io::Result<()> {
            let f = std::fs::File::create(&report_path)?;
            let mut w = std::io::BufWriter::new(f);
            serde_json::to_writer_pretty(&mut w, &self.report)?;
            std::io::Write::write_all(&mut w, b"\n")?;
            std::io::Write::flush(&mut w)
        };
        write_report().map_err(|e| ImportError::io(&report_path, e))
    }
}

/// Per-robot figures of an import.
#[derive(Debug, Clone, Default, Serialize)]
pub struct RobotImportStats {
    /// Time of the robot's start pose (s).
    pub t0: f64,
    /// Time of the robot's last record (s).
    pub t_end: f64,
    pub records: usize,
    /// Records that carry motion only (inserted every `max_record_interval` at most).
    pub motion_only_records: usize,
    pub landmark_observations: usize,
    pub robot_sightings: usize,
    pub misread_barcodes: usize,
    /// Gaps in the control stream longer than [`CONTROL_GAP_THRESHOLD`].
    pub control_gaps: usize,
    /// Longest gap between consecutive control samples (s).
    pub longest_control_gap: f64,
    /// Control samples that repeat the previous sample's timestamp.
    pub repeated_timestamps: usize,
    /// Seconds from the start pose to the first control sample, during which the robot is
    /// taken to be still.
    pub still_before_first_control: f64,
    /// Seconds of data after the ground truth ends (0 when truth covers the run).
    pub truth_ends_early: f64,
}

/// What an import found: counts, dropped data and warnings. Serialised as
/// `import_report.json`; [`fmt::Display`] gives a short human summary.
#[derive(Debug, Clone, Default, Serialize)]
pub struct ImportReport {
    /// Name of the data set.
    pub dataset: String,
    /// Robots imported.
    pub robots: Vec<String>,
    /// Earliest start time (s).
    pub t_start: f64,
    /// Latest record time (s).
    pub t_end: f64,
    /// Records in the log.
    pub records: usize,
    /// Records without measurements.
    pub motion_only_records: usize,
    pub landmark_observations: usize,
    pub robot_sightings: usize,
    /// Readings whose barcode is in no row of `Barcodes.dat` (rejected).
    pub misread_barcodes: usize,
    /// Gaps in the control streams (odometry, inputs) longer than
    /// [`CONTROL_GAP_THRESHOLD`]; the last command is held over them.
    pub control_gaps: usize,
    /// Longest gap between consecutive control samples (s).
    pub longest_control_gap: f64,
    /// Control samples that repeat the previous sample's timestamp (collapsed; the last
    /// sample of a timestamp wins).
    pub repeated_timestamps: usize,
    /// Robots whose ground truth ends before their data does: seconds without truth.
    pub truth_ends_early: BTreeMap<String, f64>,
    /// Detections dropped, by reason (misread barcodes are counted separately).
    pub detections_dropped: BTreeMap<String, usize>,
    /// The sensor range written to the header (measured from the data for MRCLAM).
    pub sensor_range: Option<SensorRange>,
    /// Details per robot.
    pub per_robot: BTreeMap<String, RobotImportStats>,
    /// Facts checked during the import (time units, start frame, ...).
    pub notes: Vec<String>,
    /// Anything odd that the user should know about.
    pub warnings: Vec<String>,
}

impl ImportReport {
    /// Counts a dropped detection under `reason`.
    pub(crate) fn drop_detection(&mut self, reason: &str) {
        *self
            .detections_dropped
            .entry(reason.to_string())
            .or_default() += 1;
    }

    /// Fills the totals from the per-robot figures and the records.
    pub(crate) fn finish(&mut self, records: &[Record]) {
        self.records = records.len();
        self.motion_only_records = records
            .iter()
            .filter(|r| r.landmarks.is_empty() && r.robots.is_empty())
            .count();
        self.landmark_observations = records.iter().map(|r| r.landmarks.len()).sum();
        self.robot_sightings = records.iter().map(|r| r.robots.len()).sum();
        let per = self.per_robot.values();
        self.misread_barcodes = per.clone().map(|s| s.misread_barcodes).sum();
        self.control_gaps = per.clone().map(|s| s.control_gaps).sum();
        self.longest_control_gap = per
            .clone()
            .map(|s| s.longest_control_gap)
            .fold(0.0, f64::max);
        self.repeated_timestamps = per.clone().map(|s| s.repeated_timestamps).sum();
        self.truth_ends_early = self
            .per_robot
            .iter()
            .filter(|(_, s)| s.truth_ends_early > 0.0)
            .map(|(r, s)| (r.clone(), s.truth_ends_early))
            .collect();
        self.robots = self.per_robot.keys().cloned().collect();
        self.t_start = per.clone().map(|s| s.t0).fold(f64::INFINITY, f64::min);
        self.t_end = per.map(|s| s.t_end).fold(f64::NEG_INFINITY, f64::max);
        if self.per_robot.is_empty() {
            self.t_start = 0.0;
            self.t_end = 0.0;
        }
    }
}

impl fmt::Display for ImportReport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(
            f,
            "{}: {} robot(s), {} records ({} motion-only) over {:.1} s",
            self.dataset,
            self.robots.len(),
            self.records,
            self.motion_only_records,
            self.t_end - self.t_start
        )?;
        writeln!(
            f,
            "  observations: {} of landmarks, {} of robots; {} misread barcode(s) rejected",
            self.landmark_observations, self.robot_sightings, self.misread_barcodes
        )?;
        writeln!(
            f,
            "  controls: {} gap(s) > {CONTROL_GAP_THRESHOLD} s held (longest {:.2} s), {} repeated timestamp(s)",
            self.control_gaps, self.longest_control_gap, self.repeated_timestamps
        )?;
        if let Some(s) = &self.sensor_range {
            writeln!(
                f,
                "  sensor range: {:.2} m, field of view {:.3} rad ({:.1} deg)",
                s.max_range,
                s.fov,
                s.fov.to_degrees()
            )?;
        }
        for (robot, secs) in &self.truth_ends_early {
            writeln!(
                f,
                "  truth of robot {robot} ends {secs:.1} s before its data"
            )?;
        }
        for (reason, n) in &self.detections_dropped {
            writeln!(f, "  dropped {n} detection(s): {reason}")?;
        }
        for n in &self.notes {
            writeln!(f, "  note: {n}")?;
        }
        for w in &self.warnings {
            writeln!(f, "  warning: {w}")?;
        }
        Ok(())
    }
}

/// Errors of an import. Each names the file (and line) at fault.
#[derive(Debug, thiserror::Error)]
pub enum ImportError {
    #[error("{}: {source}", path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{}, line {line}: {message}", path.display())]
    Parse {
        path: PathBuf,
        line: usize,
        message: String,
    },
    #[error("missing data: {0}")]
    Missing(String),
    #[error("invalid import option: {0}")]
    InvalidOption(String),
    /// The files disagree with each other or with physics (e.g. a run spanning years).
    #[error("inconsistent data: {0}")]
    Inconsistent(String),
}

impl ImportError {
    pub(crate) fn io(path: &Path, source: std::io::Error) -> Self {
        ImportError::Io {
            path: path.to_path_buf(),
            source,
        }
    }
}

/// One data line of a table: its 1-based line number and its numbers.
pub(crate) type Row<const N: usize> = (usize, [f64; N]);

/// Reads a whitespace-separated table of exactly `N` finite numbers per line. Blank lines
/// and lines starting with `#` are skipped.
pub(crate) fn read_table<const N: usize>(
    path: &Path,
    columns: [&str; N],
) -> Result<Vec<Row<N>>, ImportError> {
    let text = std::fs::read_to_string(path).map_err(|e| ImportError::io(path, e))?;
    let mut rows = Vec::with_capacity(text.len() / 32);
    for (i, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let parse_err = |message: String| ImportError::Parse {
            path: path.to_path_buf(),
            line: i + 1,
            message,
        };
        let mut v = [0.0; N];
        let mut fields = line.split_whitespace();
        for (k, slot) in v.iter_mut().enumerate() {
            let s = fields.next().ok_or_else(|| {
                parse_err(format!(
                    "expected {N} columns ({}), found {k}",
                    columns.join(", ")
                ))
            })?;
            let x: f64 = s.parse().map_err(|_| {
                parse_err(format!(
                    "column {} ({}): {s:?} is not a number",
                    k + 1,
                    columns[k]
                ))
            })?;
            if !x.is_finite() {
                return Err(parse_err(format!(
                    "column {} ({}): {s:?} is not a finite number",
                    k + 1,
                    columns[k]
                )));
            }
            *slot = x;
        }
        if fields.next().is_some() {
            return Err(parse_err(format!(
                "expected {N} columns ({}), found more",
                columns.join(", ")
            )));
        }
        rows.push((i + 1, v));
    }
    Ok(rows)
}

/// Sorts rows by time (column 0), stably, and returns how many rows were out of order.
pub(crate) fn sort_by_time<const N: usize>(rows: &mut [Row<N>]) -> usize {
    let out_of_order = rows.windows(2).filter(|w| w[1].1[0] < w[0].1[0]).count();
    if out_of_order > 0 {
        rows.sort_by(|a, b| a.1[0].total_cmp(&b.1[0]));
    }
    out_of_order
}

/// A stream of two-component control samples `(t, [a, b])`, each holding until the next.
#[derive(Debug, Clone, Default)]
pub(crate) struct ControlTrack {
    times: Vec<f64>,
    cmds: Vec<[f64; 2]>,
}

impl ControlTrack {
    /// Builds a track from samples in time order, collapsing samples that share a
    /// timestamp (the last one wins). Returns the track and the number of collapsed samples.
    pub(crate) fn new(samples: impl IntoIterator<Item = (f64, [f64; 2])>) -> (Self, usize) {
        let mut track = ControlTrack::default();
        let mut repeated = 0;
        for (t, c) in samples {
            match (track.times.last(), track.cmds.last_mut()) {
                (Some(&last), Some(cmd)) if last == t => {
                    *cmd = c;
                    repeated += 1;
                }
                _ => {
                    track.times.push(t);
                    track.cmds.push(c);
                }
            }
        }
        (track, repeated)
    }

    pub(crate) fn first_time(&self) -> Option<f64> {
        self.times.first().copied()
    }

    pub(crate) fn last_time(&self) -> Option<f64> {
        self.times.last().copied()
    }

    /// The command active at `t` (`[0, 0]` before the first sample).
    pub(crate) fn command_at(&self, t: f64) -> [f64; 2] {
        let k = self.times.partition_point(|&s| s <= t);
        k.checked_sub(1).map_or([0.0, 0.0], |i| self.cmds[i])
    }

    /// Piecewise-constant segments `[a, b, dt]` covering exactly `(from, to]`. Before the
    /// first sample the command is `[0, 0]`; after the last one the last command holds.
    /// Consecutive equal commands are merged. Empty when `to <= from`.
    pub(crate) fn segments(&self, from: f64, to: f64) -> Vec<[f64; 3]> {
        let mut out: Vec<([f64; 2], f64, f64)> = Vec::new();
        if to <= from {
            return Vec::new();
        }
        // Index of the first sample after `from`; the active one is just before it.
        let mut k = self.times.partition_point(|&t| t <= from);
        let mut cmd = if k == 0 { [0.0, 0.0] } else { self.cmds[k - 1] };
        let mut cur = from;
        loop {
            let next = self.times.get(k).map_or(to, |&t| t.min(to));
            match out.last_mut() {
                Some(last) if last.0 == cmd => last.2 = next,
                _ => out.push((cmd, cur, next)),
            }
            if next >= to {
                break;
            }
            cur = next;
            cmd = self.cmds[k];
            k += 1;
        }
        out.into_iter()
            .map(|(c, a, b)| [c[0], c[1], b - a])
            .collect()
    }

    /// Number of intervals between consecutive samples inside `[from, to]` that are longer
    /// than `threshold`, and the longest such interval.
    pub(crate) fn gaps(&self, from: f64, to: f64, threshold: f64) -> (usize, f64) {
        let lo = self.times.partition_point(|&t| t < from);
        let hi = self.times.partition_point(|&t| t <= to);
        let inside = self.times.get(lo..hi).unwrap_or(&[]);
        inside
            .windows(2)
            .map(|w| w[1] - w[0])
            .fold((0, 0.0), |(n, longest), d| {
                (n + usize::from(d > threshold), f64::max(longest, d))
            })
    }
}

/// One measurement of a robot, before grouping.
#[derive(Debug, Clone)]
pub(crate) enum Observation {
    Landmark(LandmarkObservation),
    Robot(RobotSighting),
}

/// The measurements of one instant.
#[derive(Debug, Clone, Default)]
pub(crate) struct Group {
    pub t: f64,
    pub landmarks: Vec<LandmarkObservation>,
    pub robots: Vec<RobotSighting>,
}

/// Groups time-sorted observations by exact timestamp.
pub(crate) fn group_by_time(obs: Vec<(f64, Observation)>) -> Vec<Group> {
    let mut groups: Vec<Group> = Vec::new();
    for (t, o) in obs {
        if groups.last().is_none_or(|g| g.t != t) {
            groups.push(Group {
                t,
                ..Group::default()
            });
        }
        if let Some(group) = groups.last_mut() {
            match o {
                Observation::Landmark(l) => group.landmarks.push(l),
                Observation::Robot(r) => group.robots.push(r),
            }
        }
    }
    groups
}

/// Times strictly between `from` and `to` that split the gap into equal parts of at most
/// `max_interval` (none when the gap already fits).
fn fill_times(from: f64, to: f64, max_interval: f64) -> Vec<f64> {
    let gap = to - from;
    if gap <= max_interval + TIME_TOL {
        return Vec::new();
    }
    let n = (gap / max_interval - TIME_TOL).ceil().max(1.0) as usize;
    (1..n).map(|k| from + gap * k as f64 / n as f64).collect()
}

/// Builds a robot's records from its start at `t0` to `t_end`: one per measurement group
/// (groups must be time-sorted and inside `[t0, t_end]`), motion-only records so that no
/// two records are more than `max_interval` apart, and a last record at `t_end`. `wrap`
/// turns the control segments into the run's motion type.
pub(crate) fn build_records(
    robot: &str,
    track: &ControlTrack,
    groups: Vec<Group>,
    t0: f64,
    t_end: f64,
    max_interval: f64,
    wrap: fn(Vec<[f64; 3]>) -> Motion,
) -> Vec<Record> {
    let mut records: Vec<Record> = Vec::new();
    let push = |records: &mut Vec<Record>, t: f64, group: Option<Group>| {
        let prev = records.last().map_or(t0, |r| r.t);
        let (landmarks, robots) =
            group.map_or((Vec::new(), Vec::new()), |g| (g.landmarks, g.robots));
        records.push(Record {
            robot: robot.to_string(),
            seq: records.len() as u64,
            t,
            motion: Some(wrap(track.segments(prev, t))),
            landmarks,
            robots,
        });
    };
    for g in groups {
        let prev = records.last().map_or(t0, |r| r.t);
        for t in fill_times(prev, g.t, max_interval) {
            push(&mut records, t, None);
        }
        push(&mut records, g.t, Some(g));
    }
    let last = records.last().map_or(t0, |r| r.t);
    if t_end - last > TIME_TOL {
        for t in fill_times(last, t_end, max_interval) {
            push(&mut records, t, None);
        }
        push(&mut records, t_end, None);
    }
    records
}

/// The `p`-quantile (0..=1, nearest rank) of `values`; `None` when empty.
pub(crate) fn quantile(values: &[f64], p: f64) -> Option<f64> {
    if values.is_empty() {
        return None;
    }
    let mut v = values.to_vec();
    v.sort_by(f64::total_cmp);
    let rank = ((p * v.len() as f64).ceil() as usize).clamp(1, v.len());
    Some(v[rank - 1])
}

/// Keeps at most one point per `min_dt` seconds (always the first and the last).
pub(crate) fn downsample<T: Copy>(points: &[T], time: impl Fn(&T) -> f64, min_dt: f64) -> Vec<T> {
    let mut out: Vec<T> = Vec::with_capacity(points.len());
    for (i, p) in points.iter().enumerate() {
        let keep = match out.last() {
            None => true,
            Some(last) => time(p) - time(last) >= min_dt - TIME_TOL || i + 1 == points.len(),
        };
        if keep {
            out.push(*p);
        }
    }
    out
}

/// Last directory component of `dir`, or `fallback`.
pub(crate) fn dir_name(dir: &Path, fallback: &str) -> String {
    let canonical = dir.canonicalize().ok();
    canonical
        .as_deref()
        .unwrap_or(dir)
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .filter(|n| !n.is_empty())
        .unwrap_or_else(|| fallback.to_string())
}

/// Longest run accepted (s): a longer one means a corrupt timestamp, and would otherwise
/// produce billions of motion-only records.
pub const MAX_RUN_SECONDS: f64 = 1e6;

/// Refuses a robot whose records would span more than [`MAX_RUN_SECONDS`].
pub(crate) fn check_span(robot: &str, t0: f64, t_end: f64) -> Result<(), ImportError> {
    if t_end - t0 > MAX_RUN_SECONDS {
        return Err(ImportError::Inconsistent(format!(
            "robot {robot}'s data runs from t = {t0} s to t = {t_end} s, longer than \
             {MAX_RUN_SECONDS} s: check the timestamps"
        )));
    }
    Ok(())
}

/// Checks the options shared by both importers.
pub(crate) fn check_common_options(
    duration: Option<f64>,
    max_record_interval: f64,
) -> Result<(), ImportError> {
    if let Some(d) = duration
        && !(d.is_finite() && d >= 0.0)
    {
        return Err(ImportError::InvalidOption(format!(
            "duration must be a finite number of seconds >= 0, got {d}"
        )));
    }
    if !(max_record_interval.is_finite() && max_record_interval >= 1e-3) {
        return Err(ImportError::InvalidOption(format!(
            "max_record_interval must be a finite number of seconds >= 0.001, got {max_record_interval}"
        )));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn track(samples: &[(f64, [f64; 2])]) -> ControlTrack {
        ControlTrack::new(samples.iter().copied()).0
    }

    #[test]
    fn segments_hold_and_start_still() {
        let tr = track(&[(1.0, [0.5, 0.1]), (2.0, [0.4, 0.0]), (5.0, [0.0, 0.0])]);
        // Still before the first sample, then each command holds until the next.
        assert_eq!(
            tr.segments(0.0, 2.5),
            vec![[0.0, 0.0, 1.0], [0.5, 0.1, 1.0], [0.4, 0.0, 0.5]]
        );
        // A gap holds the last command; after the last sample its command holds.
        assert_eq!(tr.segments(2.5, 4.0), vec![[0.4, 0.0, 1.5]]);
        assert_eq!(tr.segments(5.0, 6.0), vec![[0.0, 0.0, 1.0]]);
        // A sample exactly at the start of the interval is active from there on.
        assert_eq!(tr.segments(1.0, 1.5), vec![[0.5, 0.1, 0.5]]);
        assert!(tr.segments(3.0, 3.0).is_empty());
        assert_eq!(tr.command_at(0.5), [0.0, 0.0]);
        assert_eq!(tr.command_at(2.0), [0.4, 0.0]);
        assert_eq!(tr.command_at(9.0), [0.0, 0.0]);
    }

    #[test]
    fn equal_commands_merge_and_repeats_collapse() {
        let (tr, repeated) = ControlTrack::new([
            (0.0, [1.0, 0.0]),
            (0.1, [1.0, 0.0]),
            (0.1, [2.0, 0.0]),
            (0.2, [2.0, 0.0]),
        ]);
        assert_eq!(repeated, 1);
        assert_eq!(
            tr.segments(0.0, 0.3),
            vec![[1.0, 0.0, 0.1], [2.0, 0.0, 0.3 - 0.1]]
        );
        assert_eq!(tr.gaps(0.0, 0.3, 0.05), (2, 0.1));
    }

    #[test]
    fn records_fill_gaps_evenly_and_cover_time() {
        let tr = track(&[(0.0, [1.0, 0.0])]);
        let groups = vec![
            Group {
                t: 0.1,
                landmarks: vec![LandmarkObservation {
                    id: Some(7),
                    z: vec![1.0, 0.0],
                }],
                robots: vec![],
            },
            Group {
                t: 0.6,
                ..Group::default()
            },
        ];
        let recs = build_records("r", &tr, groups, 0.0, 1.0, 0.2, Motion::Velocity);
        let times: Vec<f64> = recs.iter().map(|r| r.t).collect();
        // 0.1 -> 0.6 is split in three; 0.6 -> 1.0 in two, ending at t_end.
        let expect = [0.1, 0.1 + 0.5 / 3.0, 0.1 + 1.0 / 3.0, 0.6, 0.8, 1.0];
        assert_eq!(times.len(), expect.len());
        for (a, b) in times.iter().zip(expect) {
            assert!((a - b).abs() < 1e-12, "{times:?}");
        }
        let mut prev = 0.0;
        for (i, r) in recs.iter().enumerate() {
            assert_eq!(r.seq, i as u64);
            let d = r.motion.as_ref().map_or(0.0, |m| m.duration());
            assert!((d - (r.t - prev)).abs() < 1e-12);
            prev = r.t;
        }
    }

    #[test]
    fn table_errors_name_file_and_line() {
        let dir = tempfile::TempDir::new().unwrap();
        let p = dir.path().join("t.dat");
        std::fs::write(&p, "# header\n1 2\n\n3 x\n").unwrap();
        let e = read_table(&p, ["a", "b"]).unwrap_err().to_string();
        assert!(
            e.contains("t.dat") && e.contains("line 4") && e.contains("(b)"),
            "{e}"
        );
        std::fs::write(&p, "1 2 3\n").unwrap();
        let e = read_table(&p, ["a", "b"]).unwrap_err().to_string();
        assert!(e.contains("line 1") && e.contains("more"), "{e}");
        std::fs::write(&p, "1 nan\n").unwrap();
        assert!(read_table(&p, ["a", "b"]).is_err());
        std::fs::write(&p, "1\n").unwrap();
        assert!(read_table(&p, ["a", "b"]).is_err());
        let missing = dir.path().join("none.dat");
        let e = read_table(&missing, ["a"]).unwrap_err();
        assert!(matches!(e, ImportError::Io { .. }) && e.to_string().contains("none.dat"));
    }

    #[test]
    fn quantile_and_downsample() {
        assert_eq!(quantile(&[3.0, 1.0, 2.0, 4.0], 0.5), Some(2.0));
        assert_eq!(quantile(&[3.0, 1.0], 1.0), Some(3.0));
        assert_eq!(quantile(&[], 0.5), None);
        let t: Vec<f64> = (0..=100).map(|i| i as f64 * 0.01).collect();
        let d = downsample(&t, |x| *x, 0.05);
        assert_eq!(d.len(), 21);
        assert_eq!(d.last(), Some(&1.0));
    }
}
