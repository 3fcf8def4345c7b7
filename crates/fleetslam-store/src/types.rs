//! The rows the store takes and gives back.

use serde::{Deserialize, Serialize};
use serde_json::Value;

/// The status a new run starts in.
pub const STATUS_ACTIVE: &str = "active";
/// The status of a run that ended normally.
pub const STATUS_ENDED: &str = "ended";
/// The status of a run that was stopped by an error.
pub const STATUS_FAILED: &str = "failed";
/// Every status a run can have.
pub const STATUSES: [&str; 3] = [STATUS_ACTIVE, STATUS_ENDED, STATUS_FAILED];

/// A run to create.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct NewRun {
    /// The run's id, chosen by the caller (unique, not empty).
    pub id: String,
    /// An optional human-readable name.
    pub name: Option<String>,
    /// The run's filter configuration.
    pub config: Value,
    /// The observation-log header the run was started with, if any.
    pub header: Option<Value>,
}

/// A stored run with its counts.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RunRow {
    /// The run's id.
    pub id: String,
    /// Its human-readable name.
    pub name: Option<String>,
    /// `"active"`, `"ended"` or `"failed"`.
    pub status: String,
    /// The filter configuration it was created with.
    pub config: Value,
    /// The observation-log header it was created with.
    pub header: Option<Value>,
    /// The summary set when its status last changed with one.
    pub summary: Option<Value>,
    /// Creation time, unix milliseconds.
    pub created_at: i64,
    /// When it ended or failed, unix milliseconds.
    pub ended_at: Option<i64>,
    /// Why it failed (status `"failed"`), when known.
    #[serde(default)]
    pub reason: Option<String>,
    /// How many robots it has.
    pub robots: i64,
    /// How many observation records it holds (also its highest arrival number).
    pub records: i64,
}

/// Which runs [`Store::list_runs`](crate::Store::list_runs) returns, newest first.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(default)]
pub struct RunFilter {
    /// Only runs with this status.
    pub status: Option<String>,
    /// Only runs created at or after this time (unix ms).
    pub created_after: Option<i64>,
    /// Only runs created strictly before this time (unix ms).
    pub created_before: Option<i64>,
    /// Page size, at most [`RunFilter::MAX_LIMIT`].
    pub limit: i64,
    /// How many matching runs to skip.
    pub offset: i64,
}

impl RunFilter {
    /// The default page size.
    pub const DEFAULT_LIMIT: i64 = 50;
    /// The largest page size accepted.
    pub const MAX_LIMIT: i64 = 1000;
}

impl Default for RunFilter {
    fn default() -> Self {
        RunFilter {
            status: None,
            created_after: None,
            created_before: None,
            limit: Self::DEFAULT_LIMIT,
            offset: 0,
        }
    }
}

/// A robot joining a run.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct NewRobot {
    /// The robot's id, unique within the run.
    pub robot_id: String,
    /// Its start pose (mean and covariance) when known.
    pub start: Option<Value>,
    /// The hash of its access token (the server hashes; the store never sees the token).
    pub token_hash: String,
    /// Its clock's origin, seconds.
    pub t0: Option<f64>,
}

/// A stored robot.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RobotRow {
    /// The run it belongs to.
    pub run_id: String,
    /// Its id within the run.
    pub robot_id: String,
    /// Its start pose, when known.
    pub start: Option<Value>,
    /// The hash of its access token; never serialized, so a row can be shown as is.
    #[serde(skip_serializing, default)]
    pub token_hash: String,
    /// Its clock's origin, seconds.
    pub t0: Option<f64>,
    /// When it joined, unix milliseconds.
    pub added_at: i64,
}

/// One observation record to append.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct NewObservation {
    /// The robot that sent it.
    pub robot_id: String,
    /// The robot's sequence number for it (from 0); `(run, robot, seq)` identifies it.
    pub seq: i64,
    /// Its time, seconds.
    pub t: f64,
    /// The record's JSON text, stored byte for byte.
    pub body: String,
}

/// What happened to one appended record.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Appended {
    /// The robot that sent it.
    pub robot_id: String,
    /// Its sequence number.
    pub seq: i64,
    /// Its arrival number in the run (1, 2, 3, ...): new, or the stored one of a repeat.
    pub arrival: i64,
    /// True when `(run, robot, seq)` was already stored: nothing was inserted.
    pub duplicate: bool,
}

/// The answer to [`Store::append`](crate::Store::append): one item per input record, in
/// input order. Every item is committed (durable) when this is returned.
#[derive(Debug, Clone, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct AppendOutcome {
    /// One per input record, in input order.
    pub items: Vec<Appended>,
}

impl AppendOutcome {
    /// How many records were newly inserted.
    pub fn inserted(&self) -> usize {
        self.items.iter().filter(|a| !a.duplicate).count()
    }
}

/// A stored observation record.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StoredObservation {
    /// Its arrival number in the run.
    pub arrival: i64,
    /// The robot that sent it.
    pub robot_id: String,
    /// The robot's sequence number.
    pub seq: i64,
    /// Its time, seconds.
    pub t: f64,
    /// The record's JSON text, as appended.
    pub body: String,
    /// Why it was quarantined ([`Store::quarantine`](crate::Store::quarantine)): the
    /// filter failed or panicked on it, or its body cannot be parsed. `None` for a record in
    /// good standing.
    #[serde(default)]
    pub rejected: Option<String>,
}

/// A filter snapshot to store.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct NewSnapshot {
    /// How many records had been applied (a watermark opaque to the store; the key of the
    /// snapshot within its run: storing the same value again replaces it).
    pub applied: i64,
    /// The filter time of the snapshot, seconds.
    pub t: f64,
    /// The serialized filter.
    pub data: Vec<u8>,
}

/// A stored filter snapshot.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SnapshotRow {
    /// The run it belongs to.
    pub run_id: String,
    /// The watermark it was stored with.
    pub applied: i64,
    /// Its filter time, seconds.
    pub t: f64,
    /// The serialized filter.
    pub data: Vec<u8>,
    /// When it was stored, unix milliseconds.
    pub created_at: i64,
}

/// A piece of a robot's trajectory, stored with a snapshot
/// ([`Store::put_trajectory_chunks`](crate::Store::put_trajectory_chunks)).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TrajectoryChunk {
    /// The robot whose trajectory it is.
    pub robot_id: String,
    /// The index of its first point in the robot's trajectory.
    pub first: i64,
    /// The points, as the caller encoded them (JSON text), stored as given.
    pub points: String,
}

/// A learned model to store.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct NewModel {
    /// Its id (storing the same id again replaces the model).
    pub id: String,
    /// What kind of model it is (e.g. `"mlp_updater"`).
    pub kind: String,
    /// Its architecture and training configuration.
    pub config: Value,
    /// Its evaluation metrics.
    pub metrics: Value,
    /// The serialized weights.
    pub weights: Vec<u8>,
}

/// A stored model with its weights.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ModelRow {
    /// Its id.
    pub id: String,
    /// Its kind.
    pub kind: String,
    /// Its configuration.
    pub config: Value,
    /// Its metrics.
    pub metrics: Value,
    /// The serialized weights.
    pub weights: Vec<u8>,
    /// When it was stored, unix milliseconds.
    pub created_at: i64,
}

/// A stored model without its weights, as listed by
/// [`Store::list_models`](crate::Store::list_models).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ModelInfo {
    /// Its id.
    pub id: String,
    /// Its kind.
    pub kind: String,
    /// Its configuration.
    pub config: Value,
    /// Its metrics.
    pub metrics: Value,
    /// The size of its weights in bytes.
    pub weights_len: i64,
    /// When it was stored, unix milliseconds.
    pub created_at: i64,
}

/// Counters of the group-commit writer, for measurements and tests.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct WriterStats {
    /// Append transactions committed.
    pub commits: u64,
    /// Append calls answered successfully.
    pub appends: u64,
    /// Records inserted (repeats not counted).
    pub records: u64,
}
