//! The observation log: one JSON format that robots post to the server as-is and that
//! log files store one record per line (NDJSON), opened by a header.
//!
//! ```text
//! {"fleetslam_log":1,"landmark_kind":"range_bearing_2d","motion_model":"velocity","robots":[{"id":"1","start":{"mean":{"x":0,"y":0,"theta":0}},"t0":0.0}]}
//! {"robot":"1","seq":0,"t":0.5,"motion":{"velocity":[[0.2,0.0,0.5]]},"landmarks":[{"id":7,"z":[2.1,0.3]}]}
//! {"robot":"1","seq":1,"t":1.0,"motion":{"velocity":[[0.2,0.1,0.5]]},"robots":[{"robot":"2","z":[1.5,-0.2]}]}
//! ```

use crate::motion::{AckermannParams, Motion, MotionModel, MotionNoise};
use crate::pose::PoseGaussian;
use crate::sensor::{LandmarkKind, SensorNoise, validate_measurement};
use serde::{Deserialize, Serialize};
use std::io::{BufRead, Write};

/// Current version of the log format.
pub const LOG_VERSION: u32 = 1;

/// First line of a log: the run's models, suggested noise, and its robots.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LogHeader {
    /// Format version; always [`LOG_VERSION`].
    pub fleetslam_log: u32,
    /// Free-form name of the data set.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub name: Option<String>,
    pub landmark_kind: LandmarkKind,
    pub motion_model: MotionModel,
    /// Vehicle constants for the Ackermann model.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ackermann: Option<AckermannParams>,
    /// Suggested motion noise.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub motion_noise: Option<MotionNoise>,
    /// Suggested online odometry calibration (each robot's odometry scales estimated by
    /// the filter).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub odometry_calibration: Option<crate::config::OdometryCalibration>,
    /// Suggested landmark measurement noise.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sensor_noise: Option<SensorNoise>,
    /// Suggested robot-sighting noise (range-bearing).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sighting_noise: Option<SensorNoise>,
    /// The sensor's field of view, used to decide which landmarks should have been seen.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sensor_range: Option<SensorRange>,
    /// Suggested smallest distance between two distinct landmarks of the environment (m,
    /// in the ground plane), for unknown association
    /// (`association_params.min_separation`): features closer than this count as one
    /// landmark, and an observation that matches no landmark but lies this close to one
    /// starts none. A property of the place the robots map (how densely its landmarks
    /// stand), which its integrator knows.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub landmark_separation: Option<f64>,
    /// Whether observations carry landmark ids.
    #[serde(default = "default_true")]
    pub landmark_ids: bool,
    /// Whether the robots' start poses are given in the ground truth's frame (MRCLAM: yes,
    /// Vicon's; Victoria Park: no, the car starts at the origin and GPS has its own frame).
    /// Evaluation aligns trajectories only when they are not.
    #[serde(default = "default_true")]
    pub truth_frame: bool,
    pub robots: Vec<RobotStart>,
}

fn default_true() -> bool {
    true
}

/// Where a sensor can see: landmarks inside this wedge should be observed.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SensorRange {
    /// Maximum range [m].
    pub max_range: f64,
    /// Full field of view [rad], centred on the robot's heading.
    pub fov: f64,
}

/// A robot of the log, with its start pose when known.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RobotStart {
    pub id: String,
    /// Start pose; `None` when unknown (the robot must be localized first).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub start: Option<PoseGaussian>,
    /// Time of the start pose [s].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub t0: Option<f64>,
}

/// One observation of a landmark.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LandmarkObservation {
    /// The landmark's id, or `None` when data association is unknown.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub id: Option<u32>,
    /// `[range, bearing]` or `[dx, dy, dz]`, by the run's landmark kind.
    pub z: Vec<f64>,
}

/// One sighting of another robot, as range and bearing.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RobotSighting {
    pub robot: String,
    /// `[range, bearing]`.
    pub z: Vec<f64>,
}

/// One record: what a robot did and saw since its previous record.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Record {
    pub robot: String,
    /// Per-robot sequence number, increasing by one per record.
    pub seq: u64,
    /// Time of the record [s].
    pub t: f64,
    /// Motion since the robot's previous record (or its start).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub motion: Option<Motion>,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub landmarks: Vec<LandmarkObservation>,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub robots: Vec<RobotSighting>,
}

impl Record {
    /// Checks numbers and shapes against the run's models. The message says what was wrong.
    pub fn validate(&self, kind: LandmarkKind, model: MotionModel) -> Result<(), String> {
        if self.robot.is_empty() {
            return Err("robot must be a non-empty id".into());
        }
        if !self.t.is_finite() || self.t.abs() > 1e12 {
            return Err(format!(
                "t must be a finite time in seconds, got {}",
                self.t
            ));
        }
        if let Some(m) = &self.motion {
            if m.model() != model {
                return Err(format!(
                    "motion is {:?} but the run's motion model is {:?}",
                    m.model(),
                    model
                ));
            }
            m.validate()?;
        }
        for (i, o) in self.landmarks.iter().enumerate() {
            validate_measurement(kind, &o.z).map_err(|e| format!("landmarks[{i}]: {e}"))?;
        }
        for (i, s) in self.robots.iter().enumerate() {
            validate_measurement(LandmarkKind::RangeBearing2d, &s.z)
                .map_err(|e| format!("robots[{i}]: {e}"))?;
            if s.robot == self.robot {
                return Err(format!("robots[{i}]: a robot cannot sight itself"));
            }
        }
        Ok(())
    }

    /// The deterministic order in which records are applied: time, then robot, then sequence.
    pub fn order_key(&self) -> (f64, &str, u64) {
        (self.t, self.robot.as_str(), self.seq)
    }
}

/// Total order of [`Record::order_key`] (times compare with `total_cmp`).
pub fn record_order(a: &Record, b: &Record) -> std::cmp::Ordering {
    a.t.total_cmp(&b.t)
        .then_with(|| a.robot.cmp(&b.robot))
        .then_with(|| a.seq.cmp(&b.seq))
}

/// Errors reading a log.
#[derive(Debug, thiserror::Error)]
pub enum LogError {
    #[error("reading the log: {0}")]
    Io(#[from] std::io::Error),
    #[error("line {line}: {message}")]
    Parse { line: usize, message: String },
    #[error("the log is empty: its first line must be a header")]
    Empty,
}

/// A whole log in memory.
#[derive(Debug, Clone, PartialEq)]
pub struct Log {
    pub header: LogHeader,
    pub records: Vec<Record>,
}

impl Log {
    /// Reads and validates an NDJSON log. Blank lines are skipped.
    pub fn read(reader: impl BufRead) -> Result<Log, LogError> {
        let mut header: Option<LogHeader> = None;
        let mut records = Vec::new();
        for (i, line) in reader.lines().enumerate() {
            let line = line?;
            let trimmed = line.trim();
            if trimmed.is_empty() {
                continue;
            }
            let n = i + 1;
            match &header {
                None => {
                    let h: LogHeader =
                        serde_json::from_str(trimmed).map_err(|e| LogError::Parse {
                            line: n,
                            message: format!("expected the header: {e}"),
                        })?;
                    if h.fleetslam_log != LOG_VERSION {
                        return Err(LogError::Parse {
                            line: n,
                            message: format!(
                                "log version {} is not supported (this build reads {LOG_VERSION})",
                                h.fleetslam_log
                            ),
                        });
                    }
                    header = Some(h);
                }
                Some(h) => {
                    let r: Record = serde_json::from_str(trimmed).map_err(|e| LogError::Parse {
                        line: n,
                        message: e.to_string(),
                    })?;
                    r.validate(h.landmark_kind, h.motion_model)
                        .map_err(|message| LogError::Parse { line: n, message })?;
                    records.push(r);
                }
            }
        }
        Ok(Log {
            header: header.ok_or(LogError::Empty)?,
            records,
        })
    }

    pub fn read_path(path: impl AsRef<std::path::Path>) -> Result<Log, LogError> {
        let f = std::fs::File::open(path)?;
        Log::read(std::io::BufReader::new(f))
    }

    /// Writes the header and records as NDJSON.
    pub fn write(&self, mut w: impl Write) -> std::io::Result<()> {
        serde_json::to_writer(&mut w, &self.header)?;
        w.write_all(b"\n")?;
        for r in &self.records {
            serde_json::to_writer(&mut w, r)?;
            w.write_all(b"\n")?;
        }
        w.flush()
    }

    pub fn write_path(&self, path: impl AsRef<std::path::Path>) -> std::io::Result<()> {
        let f = std::fs::File::create(path)?;
        self.write(std::io::BufWriter::new(f))
    }

    /// Sorts records into the deterministic apply order.
    pub fn sort(&mut self) {
        self.records.sort_by(record_order);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pose::Pose2;

    fn sample() -> Log {
        Log {
            header: LogHeader {
                fleetslam_log: LOG_VERSION,
                name: Some("t".into()),
                landmark_kind: LandmarkKind::RangeBearing2d,
                motion_model: MotionModel::Velocity,
                ackermann: None,
                motion_noise: Some(MotionNoise::default()),
                odometry_calibration: None,
                sensor_noise: None,
                sighting_noise: None,
                sensor_range: None,
                landmark_separation: None,
                landmark_ids: true,
                truth_frame: true,
                robots: vec![RobotStart {
                    id: "1".into(),
                    start: Some(PoseGaussian::exact(Pose2::new(1.0, 2.0, 0.5))),
                    t0: Some(0.0),
                }],
            },
            records: vec![Record {
                robot: "1".into(),
                seq: 0,
                t: 0.5,
                motion: Some(Motion::Velocity(vec![[0.2, 0.0, 0.5]])),
                landmarks: vec![LandmarkObservation {
                    id: Some(7),
                    z: vec![2.0, 0.1],
                }],
                robots: vec![],
            }],
        }
    }

    #[test]
    fn round_trip() {
        let log = sample();
        let mut buf = Vec::new();
        log.write(&mut buf).unwrap();
        let back = Log::read(&buf[..]).unwrap();
        assert_eq!(back, log);
    }

    #[test]
    fn errors_name_the_line() {
        let mut buf = Vec::new();
        sample().write(&mut buf).unwrap();
        buf.extend_from_slice(
            b"{\"robot\":\"1\",\"seq\":1,\"t\":1.0,\"landmarks\":[{\"z\":[1.0]}]}\n",
        );
        let e = Log::read(&buf[..]).unwrap_err().to_string();
        assert!(
            e.contains("line 3") && e.contains("[range, bearing]"),
            "{e}"
        );
        let e = Log::read(&b"{\"robot\":\"1\"}\n"[..])
            .unwrap_err()
            .to_string();
        assert!(e.contains("line 1") && e.contains("header"), "{e}");
        assert!(matches!(Log::read(&b"\n"[..]), Err(LogError::Empty)));
    }

    #[test]
    fn unknown_fields_are_refused() {
        let e = serde_json::from_str::<Record>(r#"{"robot":"1","seq":0,"t":0,"colour":1}"#)
            .unwrap_err()
            .to_string();
        assert!(e.contains("colour"), "{e}");
    }
}
