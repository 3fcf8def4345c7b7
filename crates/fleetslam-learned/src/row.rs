//! The training row: one logged landmark update (inputs and the EKF's outputs), one JSON
//! object per row. The store keeps rows as JSON strings; offline runs write NDJSON files.

use crate::LearnedError;
use fleetslam_core::Pose2;
use fleetslam_core::sensor::LandmarkKind;
use fleetslam_core::updater::{LandmarkGaussian, UpdateInput, UpdateOutput};
use serde::{Deserialize, Serialize};
use std::io::{BufRead, Write};
use std::path::Path;

/// One landmark update as logged from a run: what went in and what the (EKF) updater
/// returned. Rows of rejected updates (non-finite outputs) are never logged: JSON has no
/// infinities and such an update teaches nothing.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TrainingRow {
    /// The landmark kind of the run that logged the row.
    pub kind: LandmarkKind,
    /// Prior mean `[x, y, z]` [m] (z = 0 in 2D).
    pub prior_mean: [f64; 3],
    /// Prior covariance, upper triangle `[xx, xy, xz, yy, yz, zz]` [m²].
    pub prior_cov: [f64; 6],
    /// Robot pose `[x, y, theta]` [m, m, rad].
    pub pose: [f64; 3],
    /// Measurement: `[range, bearing, 0]` or `[dx, dy, dz]` in the robot frame.
    pub z: [f64; 3],
    /// Posterior mean [m].
    pub post_mean: [f64; 3],
    /// Posterior covariance, upper triangle [m²].
    pub post_cov: [f64; 6],
    /// ln p(z | prior, pose).
    pub log_likelihood: f64,
    /// Squared Mahalanobis distance of the innovation.
    pub mahalanobis2: f64,
    /// The landmark's true position as seen from the row's pose [m]: placed from `pose` by
    /// the noise-free measurement (from the robot's true pose to the landmark's true
    /// position), when the run has ground truth and the row was labelled
    /// ([`crate::truth::label_rows`], which says why not the absolute position); the target
    /// of models trained against truth.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub truth: Option<[f64; 3]>,
}

impl TrainingRow {
    /// A row from an update; `None` when the output is not finite (a rejected update).
    pub fn new(kind: LandmarkKind, input: &UpdateInput, output: &UpdateOutput) -> Option<Self> {
        let row = Self {
            kind,
            prior_mean: input.prior.mean,
            prior_cov: input.prior.cov,
            pose: [input.pose.x, input.pose.y, input.pose.theta],
            z: input.z,
            post_mean: output.posterior.mean,
            post_cov: output.posterior.cov,
            log_likelihood: output.log_likelihood,
            mahalanobis2: output.mahalanobis2,
            truth: None,
        };
        row.is_finite().then_some(row)
    }

    pub fn is_finite(&self) -> bool {
        self.prior_mean
            .iter()
            .chain(&self.prior_cov)
            .chain(&self.pose)
            .chain(&self.z)
            .chain(&self.post_mean)
            .chain(&self.post_cov)
            .chain([&self.log_likelihood, &self.mahalanobis2])
            .chain(self.truth.iter().flatten())
            .all(|v| v.is_finite())
    }

    /// The updater input this row logged.
    pub fn input(&self) -> UpdateInput {
        UpdateInput {
            prior: LandmarkGaussian {
                mean: self.prior_mean,
                cov: self.prior_cov,
            },
            pose: Pose2::new(self.pose[0], self.pose[1], self.pose[2]),
            z: self.z,
        }
    }

    /// The updater output this row logged.
    pub fn output(&self) -> UpdateOutput {
        UpdateOutput {
            posterior: LandmarkGaussian {
                mean: self.post_mean,
                cov: self.post_cov,
            },
            log_likelihood: self.log_likelihood,
            mahalanobis2: self.mahalanobis2,
        }
    }

    /// One JSON object (no newline).
    pub fn to_json(&self) -> String {
        serde_json::to_string(self).expect("a finite row always serialises")
    }

    pub fn from_json(s: &str) -> Result<Self, LearnedError> {
        let row: Self = serde_json::from_str(s).map_err(|e| LearnedError::Row(e.to_string()))?;
        if !row.is_finite() {
            return Err(LearnedError::Row("a value is not finite".into()));
        }
        Ok(row)
    }
}

/// Writes rows as NDJSON (one object per line).
pub fn write_ndjson<W: Write>(mut w: W, rows: &[TrainingRow]) -> std::io::Result<()> {
    for r in rows {
        w.write_all(r.to_json().as_bytes())?;
        w.write_all(b"\n")?;
    }
    w.flush()
}

/// Writes rows to an NDJSON file.
pub fn write_ndjson_path(path: &Path, rows: &[TrainingRow]) -> Result<(), LearnedError> {
    let f = std::fs::File::create(path).map_err(|e| LearnedError::io(path, e))?;
    write_ndjson(std::io::BufWriter::new(f), rows).map_err(|e| LearnedError::io(path, e))
}

/// Reads an NDJSON file of rows; blank lines are skipped, a bad line is an error naming it.
pub fn read_ndjson_path(path: &Path) -> Result<Vec<TrainingRow>, LearnedError> {
    let f = std::fs::File::open(path).map_err(|e| LearnedError::io(path, e))?;
    let mut rows = Vec::new();
    for (i, line) in std::io::BufReader::new(f).lines().enumerate() {
        let line = line.map_err(|e| LearnedError::io(path, e))?;
        if line.trim().is_empty() {
            continue;
        }
        let row = TrainingRow::from_json(&line)
            .map_err(|e| LearnedError::Row(format!("{} line {}: {e}", path.display(), i + 1)))?;
        rows.push(row);
    }
    Ok(rows)
}
