//! The learned landmark updater of fleetslam: a small multilayer perceptron in place of the
//! EKF's per-landmark update, after Vidal & Rosa (2015), "FastSLAM com múltiplos robôs e
//! atualização de marcos por rede neural" (`shared/papers/fastslam-mlp-landmark-update-*`).
//!
//! - [`RecordingUpdater`] wraps any updater and keeps a deterministic sample of its updates as
//!   [`TrainingRow`]s (JSON objects; NDJSON files offline, JSON strings in the store).
//! - [`MlpModel`] is the model file (plain JSON weights, normalisation, landmark kind, input
//!   layout and version, preset, sensor noise); [`MlpUpdater`] runs it in plain batched Rust:
//!   [`kernel::Kernel`] evaluates the network in f32 on eight items at once, with the
//!   normalisation folded into the first and last layers.
//! - With the `train` feature, [`training`] trains models with burn (flex backend, autodiff)
//!   and saves burn's burnpack record beside the plain model.
//!
//! # What the network predicts, and what stays closed form
//!
//! A FastSLAM particle needs three things from a landmark update: the posterior mean, the
//! posterior covariance (the next update's prior), and, in FastSLAM 1.0 or with an outlier
//! gate, the observation likelihood (the particle's weight; the filter says whether it needs
//! it, [`fleetslam_core::updater::UpdateNeeds`]). The likelihood is never learned: it is the Gaussian innovation
//! likelihood `N(ν; 0, Σ + Q)` from the prior and the sensor noise, computed in a frame where
//! the EKF's Jacobian is the identity (see [`frame`]), so particle weights and outlier gating
//! are exactly the EKF's. The network predicts the posterior mean; the `default` preset's
//! network also predicts the posterior covariance as a Cholesky factor (always positive
//! definite); the `structured` preset's network predicts the gain (so the mean is exactly
//! linear in the innovation) and the covariance factor from the prior and the noise alone;
//! the `paper` preset's network predicts the mean, and its covariance is the EKF's closed
//! form `Σ − Σ (Σ + Q)⁻¹ Σ`. The `truth` preset's network learns the posterior mean from the
//! landmarks' true positions ([`truth::label_rows`] labels logged rows against a data set's
//! ground truth) instead of from the EKF, and so can learn a real sensor's biases.
//!
//! ```no_run
//! use fleetslam_learned::{MlpModel, MlpUpdater};
//! use fleetslam_core::sensor::LandmarkKind;
//! let bytes = std::fs::read("model.json").unwrap();
//! let model = MlpModel::from_json(&bytes).unwrap();
//! let updater = MlpUpdater::for_kind(model, LandmarkKind::RangeBearing2d).unwrap();
//! ```

pub mod dataset;
pub mod frame;
pub mod inference;
pub mod kernel;
pub mod model;
pub mod recorder;
pub mod row;
#[cfg(feature = "train")]
pub mod training;
pub mod truth;

pub use dataset::{
    RunSplit, TrainTarget, TruthError, UpdaterError, estimate_noise, split_runs, updater_error,
};
pub use frame::InputLayout;
pub use inference::MlpUpdater;
pub use model::{Activation, CovarianceSource, MlpModel, STORE_MODEL_KIND};
pub use recorder::{RecordingConfig, RecordingUpdater};
pub use row::TrainingRow;
pub use truth::{LabelStats, label_rows};

use fleetslam_core::sensor::LandmarkKind;

/// Errors of the learned updater crate.
#[derive(Debug, thiserror::Error)]
pub enum LearnedError {
    #[error("{path}: {source}")]
    Io {
        path: String,
        #[source]
        source: std::io::Error,
    },
    #[error("bad training row: {0}")]
    Row(String),
    #[error("bad model file: {0}")]
    Model(String),
    #[error(
        "model {id:?} was trained for {} landmarks but this run maps {} landmarks: train one on {} data",
        model.as_str(), expected.as_str(), expected.as_str()
    )]
    KindMismatch {
        id: String,
        model: LandmarkKind,
        expected: LandmarkKind,
    },
    #[error(
        "model input layout mismatch: the model has {model}, this build expects {expected}; retrain the model with this build"
    )]
    LayoutMismatch { model: String, expected: String },
    #[error("{0}")]
    Config(String),
    #[error("training data: {0}")]
    Data(String),
    #[error("burn: {0}")]
    Burn(String),
}

impl LearnedError {
    pub(crate) fn io(path: &std::path::Path, source: std::io::Error) -> Self {
        LearnedError::Io {
            path: path.display().to_string(),
            source,
        }
    }
}
