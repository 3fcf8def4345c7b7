//! The per-landmark update, behind a trait so that the EKF can be swapped for a learned one.
//!
//! An updater is a pure function of (landmark prior, robot pose, measurement): it returns
//! the landmark posterior and, when asked ([`UpdateNeeds`]), the observation's log-likelihood
//! (which weighs the particle in FastSLAM 1.0) and its squared Mahalanobis distance (which the
//! filter uses to reject outliers). FastSLAM 2.0 takes the particle's weight from its proposal
//! and needs only the posterior, so the filter says so and neither updater computes what
//! would be thrown away. An updater also creates a landmark from its first observation.
//! Updates come in batches (one item per particle), so an implementation can vectorise across
//! particles; the filter's results must not depend on how items are batched, so every item is
//! computed independently of the others, and the posterior is the same whatever was asked.

use crate::pose::Pose2;
use crate::sensor::LandmarkKind;
use serde::{Deserialize, Serialize};

/// A landmark's Gaussian: mean `[x, y, z]` (z = 0 in 2D) and the upper triangle of its
/// covariance `[xx, xy, xz, yy, yz, zz]` (the z entries are 0 in 2D).
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct LandmarkGaussian {
    pub mean: [f64; 3],
    pub cov: [f64; 6],
}

impl LandmarkGaussian {
    pub fn cov2(&self) -> nalgebra::Matrix2<f64> {
        let c = &self.cov;
        nalgebra::Matrix2::new(c[0], c[1], c[1], c[3])
    }

    pub fn cov3(&self) -> nalgebra::Matrix3<f64> {
        let c = &self.cov;
        nalgebra::Matrix3::new(c[0], c[1], c[2], c[1], c[3], c[4], c[2], c[4], c[5])
    }

    /// Builds from a 2x2 covariance, symmetrising it.
    pub fn from_2d(mean: [f64; 2], m: &nalgebra::Matrix2<f64>) -> Self {
        let xy = 0.5 * (m[(0, 1)] + m[(1, 0)]);
        Self {
            mean: [mean[0], mean[1], 0.0],
            cov: [m[(0, 0)], xy, 0.0, m[(1, 1)], 0.0, 0.0],
        }
    }

    /// Builds from a 3x3 covariance, symmetrising it.
    pub fn from_3d(mean: [f64; 3], m: &nalgebra::Matrix3<f64>) -> Self {
        let s = |i: usize, j: usize| 0.5 * (m[(i, j)] + m[(j, i)]);
        Self {
            mean,
            cov: [m[(0, 0)], s(0, 1), s(0, 2), m[(1, 1)], s(1, 2), m[(2, 2)]],
        }
    }

    /// Every number finite. A fold over each array without early exit (the compiler
    /// vectorises it): checked twice per landmark update, in the EKF and by the filter.
    #[inline]
    pub fn is_finite(&self) -> bool {
        let finite = |a: bool, v: &f64| a & v.is_finite();
        self.mean.iter().fold(true, finite) & self.cov.iter().fold(true, finite)
    }
}

/// One update to compute.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct UpdateInput {
    pub prior: LandmarkGaussian,
    pub pose: Pose2,
    /// `[range, bearing, 0]` or `[dx, dy, dz]`.
    pub z: [f64; 3],
}

/// What the filter needs from a batch of updates.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum UpdateNeeds {
    /// The posterior only (FastSLAM 2.0 without an outlier gate: the weight came from the
    /// proposal). `log_likelihood` and `mahalanobis2` of the outputs are unspecified (NaN).
    Posterior,
    /// The posterior, the log-likelihood and the squared Mahalanobis distance.
    PosteriorAndLikelihood,
}

impl UpdateNeeds {
    pub fn likelihood(self) -> bool {
        self == UpdateNeeds::PosteriorAndLikelihood
    }
}

/// The result of one update.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct UpdateOutput {
    pub posterior: LandmarkGaussian,
    /// ln p(z | prior, pose): the Gaussian innovation likelihood; −∞ for an update that
    /// could not be computed (the posterior is then the prior); NaN when not asked for.
    pub log_likelihood: f64,
    /// Squared Mahalanobis distance of the innovation (∞ for an update that could not be
    /// computed, NaN when not asked for).
    pub mahalanobis2: f64,
}

impl UpdateOutput {
    /// An update that could not be computed (degenerate geometry or numbers): the prior is
    /// kept and the observation counts as an infinitely unlikely one, which the filter floors.
    pub fn rejected(prior: &LandmarkGaussian) -> Self {
        Self {
            posterior: *prior,
            log_likelihood: f64::NEG_INFINITY,
            mahalanobis2: f64::INFINITY,
        }
    }
}

/// A per-landmark update. Implementations must be deterministic and item-independent.
pub trait LandmarkUpdater: Send + Sync + std::fmt::Debug {
    /// A short name for reports (`ekf`, a model id, ...).
    fn name(&self) -> &str;

    /// The landmark kind this updater serves; a run refuses an updater of another kind.
    fn kind(&self) -> LandmarkKind;

    /// A new landmark from its first observation.
    fn initialize(&self, pose: &Pose2, z: &[f64; 3]) -> LandmarkGaussian;

    /// Updates every input; `outputs.len() == inputs.len()`. The posteriors must not depend
    /// on `needs`; the likelihood fields are only meaningful when `needs` asks for them.
    fn update_batch(
        &self,
        needs: UpdateNeeds,
        inputs: &[UpdateInput],
        outputs: &mut [UpdateOutput],
    );

    /// One full update (a batch of one, posterior and likelihood).
    fn update(&self, input: &UpdateInput) -> UpdateOutput {
        let mut out = [UpdateOutput::default()];
        self.update_batch(
            UpdateNeeds::PosteriorAndLikelihood,
            std::slice::from_ref(input),
            &mut out,
        );
        out[0]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Finite only when every one of the nine numbers is, wherever the bad one sits.
    #[test]
    fn a_gaussian_is_finite_only_when_every_number_is() {
        let g = LandmarkGaussian {
            mean: [1.0, -2.0, 0.0],
            cov: [0.5, 0.1, 0.0, 0.4, 0.0, f64::MAX],
        };
        assert!(g.is_finite());
        for at in 0..9 {
            for bad in [f64::NAN, f64::INFINITY, f64::NEG_INFINITY] {
                let mut h = g;
                if at < 3 {
                    h.mean[at] = bad;
                } else {
                    h.cov[at - 3] = bad;
                }
                assert!(!h.is_finite(), "{bad} at {at}");
            }
        }
    }
}
