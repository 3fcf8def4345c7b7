//! [`MlpUpdater`]: the learned landmark update, in plain batched Rust (no burn at run time).
//!
//! What the network predicts and what is derived (see the crate docs for why):
//!
//! | output | `line_of_sight` (default preset) | `paper` preset |
//! |---|---|---|
//! | posterior mean | network (correction in the measurement frame) | network (world coordinates) |
//! | posterior covariance | network (Cholesky factor: always positive definite), or the closed form with `covariance: closed_form` | EKF closed form `Σ − Σ S⁻¹ Σ` (the paper's single covariance element cannot form a covariance) |
//! | log-likelihood (particle weight) | closed form `ln N(ν; 0, Σ + Q)` | same |
//! | squared Mahalanobis distance (gating) | closed form `νᵀ (Σ + Q)⁻¹ ν` | same |
//! | new landmark | inverse measurement with the model's noise (as the EKF) | same |

use crate::LearnedError;
use crate::frame::{Frame, InputLayout, frame2, frame3, paper_features};
use crate::model::{CovarianceSource, MAX_IO, MlpModel};
use fleetslam_core::config::FilterConfig;
use fleetslam_core::ekf::EkfUpdater;
use fleetslam_core::pose::Pose2;
use fleetslam_core::sensor::LandmarkKind;
use fleetslam_core::updater::{LandmarkGaussian, LandmarkUpdater, UpdateInput, UpdateOutput};
use nalgebra::SVector;

/// Relative difference allowed between a model's sensor noise and a run's.
pub const NOISE_TOLERANCE: f64 = 0.05;

/// The learned updater. `name()` is the model id.
#[derive(Debug, Clone)]
pub struct MlpUpdater {
    model: MlpModel,
    init: EkfUpdater,
    n_in: usize,
    n_out: usize,
}

impl MlpUpdater {
    /// Validates the model (format, layout version, shapes) and builds the updater.
    pub fn new(model: MlpModel) -> Result<Self, LearnedError> {
        model.validate()?;
        let (n_in, n_out) = model.layout.dims(model.kind);
        Ok(Self {
            init: EkfUpdater::new(model.kind, &model.noise),
            model,
            n_in,
            n_out,
        })
    }

    /// As [`MlpUpdater::new`], refusing a model trained for another landmark kind than
    /// `kind`.
    pub fn for_kind(model: MlpModel, kind: LandmarkKind) -> Result<Self, LearnedError> {
        if model.kind != kind {
            return Err(LearnedError::KindMismatch {
                model: model.kind,
                expected: kind,
                id: model.id,
            });
        }
        Self::new(model)
    }

    /// For a run: refuses a model of another landmark kind than the run's, whose id is not
    /// the run's `updater`, or whose sensor noise differs from the run's by more than
    /// [`NOISE_TOLERANCE`] (the network's features are scaled by it and the particle weights
    /// use it). Within the tolerance the run's noise is used, so that the weights are exactly
    /// those the run's configuration implies.
    pub fn for_run(mut model: MlpModel, config: &FilterConfig) -> Result<Self, LearnedError> {
        if model.id != config.updater {
            return Err(LearnedError::Config(format!(
                "the run names updater {:?} but the model's id is {:?}",
                config.updater, model.id
            )));
        }
        if model.kind != config.landmark_kind {
            return Err(LearnedError::KindMismatch {
                model: model.kind,
                expected: config.landmark_kind,
                id: model.id,
            });
        }
        let (m, r) = (&model.noise, &config.sensor_noise);
        let pairs: Vec<(f64, f64)> = match config.landmark_kind {
            LandmarkKind::RangeBearing2d => vec![(m.range, r.range), (m.bearing, r.bearing)],
            LandmarkKind::Point3d => (0..3).map(|k| (m.xyz[k], r.xyz[k])).collect(),
        };
        if pairs
            .iter()
            .any(|(a, b)| (a - b).abs() > NOISE_TOLERANCE * b.abs())
        {
            return Err(LearnedError::Config(format!(
                "model {:?} was trained with sensor noise {:?} but the run uses {:?}: train it on \
                 updates logged with the run's noise",
                model.id, model.noise, config.sensor_noise
            )));
        }
        model.noise = config.sensor_noise;
        Self::for_kind(model, config.landmark_kind)
    }

    pub fn model(&self) -> &MlpModel {
        &self.model
    }

    #[inline]
    fn update_frame<const D: usize>(&self, inp: &UpdateInput, f: &Frame<D>) -> UpdateOutput {
        let Some(inn) = f.innovation() else {
            return rejected(&inp.prior);
        };
        let mut feats = [0f64; MAX_IO];
        let mut out = [0f64; MAX_IO];
        let posterior = match self.model.layout {
            InputLayout::LineOfSight => {
                f.los_features(&mut feats[..self.n_in]);
                self.model
                    .predict(&feats[..self.n_in], &mut out[..self.n_out]);
                let (corr, cov) = f.los_decode(&out[..self.n_out]);
                match self.model.covariance {
                    CovarianceSource::Network => f.world_posterior(&inp.prior.mean, &corr, &cov),
                    CovarianceSource::ClosedForm => {
                        f.world_posterior(&inp.prior.mean, &corr, &f.closed_form_cov(&inn))
                    }
                }
            }
            InputLayout::Paper => {
                paper_features(self.model.kind, inp, &mut feats[..self.n_in]);
                self.model
                    .predict(&feats[..self.n_in], &mut out[..self.n_out]);
                let cov = f.closed_form_cov(&inn);
                let mut post =
                    f.world_posterior(&inp.prior.mean, &SVector::<f64, D>::zeros(), &cov);
                post.mean[..D].copy_from_slice(&out[..D]);
                post
            }
        };
        let o = UpdateOutput {
            posterior,
            log_likelihood: inn.log_likelihood,
            mahalanobis2: inn.mahalanobis2,
        };
        if o.posterior.is_finite() && o.log_likelihood.is_finite() {
            o
        } else {
            rejected(&inp.prior)
        }
    }
}

/// As the EKF: an update that can't be computed keeps the prior and is infinitely unlikely.
fn rejected(prior: &LandmarkGaussian) -> UpdateOutput {
    UpdateOutput {
        posterior: *prior,
        log_likelihood: f64::NEG_INFINITY,
        mahalanobis2: f64::INFINITY,
    }
}

impl LandmarkUpdater for MlpUpdater {
    fn name(&self) -> &str {
        &self.model.id
    }

    fn kind(&self) -> LandmarkKind {
        self.model.kind
    }

    fn initialize(&self, pose: &Pose2, z: &[f64; 3]) -> LandmarkGaussian {
        self.init.initialize(pose, z)
    }

    fn update_batch(&self, inputs: &[UpdateInput], outputs: &mut [UpdateOutput]) {
        debug_assert_eq!(inputs.len(), outputs.len());
        let noise = &self.model.noise;
        match self.model.kind {
            LandmarkKind::RangeBearing2d => {
                for (i, o) in inputs.iter().zip(outputs.iter_mut()) {
                    *o = match frame2(i, noise) {
                        Some(f) => self.update_frame(i, &f),
                        None => rejected(&i.prior),
                    };
                }
            }
            LandmarkKind::Point3d => {
                for (i, o) in inputs.iter().zip(outputs.iter_mut()) {
                    *o = self.update_frame(i, &frame3(i, noise));
                }
            }
        }
    }
}

/// The EKF's update recomputed in the measurement frame (checks the frame's algebra).
#[cfg(test)]
pub(crate) fn closed_form_update<const D: usize>(
    f: &Frame<D>,
    prior_mean: &[f64; 3],
) -> Option<(LandmarkGaussian, f64, f64)> {
    let inn = f.innovation()?;
    let k: nalgebra::SMatrix<f64, D, D> = f.sigma * inn.s_inv;
    let corr = k * f.nu;
    let cov = f.closed_form_cov(&inn);
    Some((
        f.world_posterior(prior_mean, &corr, &cov),
        inn.log_likelihood,
        inn.mahalanobis2,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use fleetslam_core::sensor::SensorNoise;
    use rand::{Rng, SeedableRng};

    fn noise() -> SensorNoise {
        SensorNoise {
            range: 0.1,
            bearing: 0.03,
            xyz: [0.05, 0.08, 0.1],
        }
    }

    /// The measurement-frame update is the EKF's update: same posterior, likelihood and
    /// Mahalanobis distance, for both kinds, over random geometry.
    #[test]
    fn measurement_frame_reproduces_the_ekf() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        for kind in [LandmarkKind::RangeBearing2d, LandmarkKind::Point3d] {
            let ekf = EkfUpdater::new(kind, &noise());
            for _ in 0..500 {
                let pose = Pose2::new(
                    rng.random_range(-5.0..5.0),
                    rng.random_range(-5.0..5.0),
                    rng.random_range(-3.0..3.0),
                );
                let r = rng.random_range(0.5..8.0);
                let b: f64 = rng.random_range(-1.5..1.5);
                let z0 = match kind {
                    LandmarkKind::RangeBearing2d => [r, b, 0.0],
                    LandmarkKind::Point3d => {
                        [r * b.cos(), r * b.sin(), rng.random_range(-1.0..1.0)]
                    }
                };
                let mut prior = ekf.initialize(&pose, &z0);
                let s = rng.random_range(0.05..3.0);
                prior.cov.iter_mut().for_each(|c| *c *= s);
                let z = [
                    z0[0] + rng.random_range(-0.2..0.2),
                    z0[1] + rng.random_range(-0.05..0.05),
                    z0[2] + rng.random_range(-0.2..0.2),
                ];
                let inp = UpdateInput { prior, pose, z };
                let want = ekf.update(&inp);
                let got = match kind {
                    LandmarkKind::RangeBearing2d => {
                        closed_form_update(&frame2(&inp, &noise()).unwrap(), &prior.mean)
                    }
                    LandmarkKind::Point3d => {
                        closed_form_update(&frame3(&inp, &noise()), &prior.mean)
                    }
                }
                .unwrap();
                for (g, w) in got.0.mean.iter().zip(&want.posterior.mean) {
                    assert!((g - w).abs() < 1e-9);
                }
                for (k, (g, w)) in got.0.cov.iter().zip(&want.posterior.cov).enumerate() {
                    let tol = 1e-9 * (1.0 + w.abs());
                    assert!((g - w).abs() < tol, "{kind:?} cov {k}");
                }
                assert!((got.1 - want.log_likelihood).abs() < 1e-8, "{kind:?} ll");
                assert!((got.2 - want.mahalanobis2).abs() < 1e-8);
            }
        }
    }
}
