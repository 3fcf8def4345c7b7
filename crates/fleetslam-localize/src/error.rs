//! The crate's one error type.

use fleetslam_core::filter::FilterError;

/// Errors of localization and of the late-joiner wrapper; each says what was wrong.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum LocalizeError {
    /// A configuration field is out of range; the message names it and the allowed values.
    #[error("invalid localization configuration: {0}")]
    Config(String),
    /// The fixed map cannot be used (empty, or a non-finite or non-positive-definite entry).
    #[error("invalid map: {0}")]
    Map(String),
    /// A record does not fit the localizer's models, or goes back in time.
    #[error("invalid record: {0}")]
    Record(String),
    /// The SLAM filter refused an operation.
    #[error(transparent)]
    Filter(#[from] FilterError),
    /// A robot is unknown to the wrapper, or registered twice.
    #[error("{0}")]
    Robot(String),
    /// A snapshot is inconsistent.
    #[error("invalid snapshot: {0}")]
    Snapshot(String),
    /// Writing experiment output failed.
    #[error("writing {path}: {message}")]
    Io { path: String, message: String },
}
