//! [`MlpUpdater`]: the learned landmark update, in plain batched Rust (no burn at run time).
//!
//! A batch is processed [`LANES`] items at a time: the measurement frame and the features of
//! each item in f64, the network on all lanes at once in f32 ([`Kernel`]), the decoding back
//! per item. What the network predicts and what is derived (see the crate docs for why):
//!
//! | output | `line_of_sight` (default preset), `line_of_sight_range` (truth preset) | `gain` (structured preset) | `paper` preset |
//! |---|---|---|---|
//! | posterior mean | network (correction in the measurement frame) | `μ + K ν`, the gain `K` from the network | network (world coordinates) |
//! | posterior covariance | network (Cholesky factor: always positive definite), or the closed form with `covariance: closed_form` | as `line_of_sight` | EKF closed form `Σ − Σ S⁻¹ Σ` |
//! | log-likelihood (particle weight), when the filter asks | closed form `ln N(ν; 0, Σ + Q)` | same | same |
//! | squared Mahalanobis distance (gating), when asked | closed form `νᵀ (Σ + Q)⁻¹ ν` | same | same |
//! | new landmark | inverse measurement with the model's noise (as the EKF) | same | same |
//!
//! With [`UpdateNeeds::Posterior`] (FastSLAM 2.0) and the network's covariance, `S = Σ + Q`
//! is never formed: the update is the features, the network and the decoding.

use crate::LearnedError;
use crate::frame::{Frame, InputLayout, frame2, frame3, paper_features};
use crate::kernel::{Arch, Kernel, LANES, Lanes, Scratch};
use crate::model::{CovarianceSource, MAX_IO, MlpModel};
use fleetslam_core::config::FilterConfig;
use fleetslam_core::ekf::EkfUpdater;
use fleetslam_core::pose::Pose2;
use fleetslam_core::sensor::LandmarkKind;
use fleetslam_core::updater::{
    LandmarkGaussian, LandmarkUpdater, UpdateInput, UpdateNeeds, UpdateOutput,
};
use nalgebra::SVector;
use std::cell::RefCell;

/// Relative difference allowed between a model's sensor noise and a run's.
pub const NOISE_TOLERANCE: f64 = 0.05;

thread_local! {
    /// The kernel's hidden activations, one set per thread (taken once per batch).
    static SCRATCH: RefCell<Box<Scratch>> = RefCell::new(Box::default());
}

/// The learned updater. `name()` is the model id.
#[derive(Debug, Clone)]
pub struct MlpUpdater {
    model: MlpModel,
    kernel: Kernel,
    init: EkfUpdater,
    /// The instruction set the passes are compiled for (detected at construction).
    arch: Arch,
}

impl MlpUpdater {
    /// Validates the model (format, layout version, shapes) and builds the updater.
    pub fn new(model: MlpModel) -> Result<Self, LearnedError> {
        model.validate()?;
        Ok(Self {
            init: EkfUpdater::new(model.kind, &model.noise),
            kernel: Kernel::new(&model),
            model,
            arch: Arch::new(),
        })
    }

    /// The same updater without runtime SIMD dispatch (the baseline instruction set), for
    /// measuring what AVX2 buys and checking that it changes no bit.
    pub fn baseline_simd(mut self) -> Self {
        self.arch = Arch::Scalar;
        self
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
            LandmarkKind::RangeBearing2d => vec![
                (m.range, r.range),
                (m.bearing, r.bearing),
                (m.range_per_m, r.range_per_m),
            ],
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

    /// Updates `inputs` in passes of [`LANES`] items.
    fn run<const D: usize>(
        &self,
        needs: UpdateNeeds,
        inputs: &[UpdateInput],
        outputs: &mut [UpdateOutput],
        frame: impl Fn(&UpdateInput) -> Option<Frame<D>>,
    ) {
        SCRATCH.with(|scratch| {
            let mut scratch = scratch.borrow_mut();
            self.arch.dispatch(Passes {
                updater: self,
                needs,
                inputs,
                outputs,
                frame,
                scratch: &mut scratch,
            })
        })
    }

    #[inline(always)]
    fn pass<const D: usize>(
        &self,
        needs: UpdateNeeds,
        inputs: &[UpdateInput],
        outputs: &mut [UpdateOutput],
        frame: &impl Fn(&UpdateInput) -> Option<Frame<D>>,
        scratch: &mut Scratch,
    ) {
        let layout = self.model.layout;
        let mut frames: [Option<(Frame<D>, SVector<f64, D>)>; LANES] = [None; LANES];
        let mut x: [Lanes; MAX_IO] = [[0.0; LANES]; MAX_IO];
        let mut feats = [0f64; MAX_IO];
        for (lane, inp) in inputs.iter().enumerate() {
            let Some(f) = frame(inp) else { continue };
            let s = f.prior_std();
            match layout {
                InputLayout::LineOfSight => f.los_features(&s, &mut feats),
                InputLayout::LineOfSightRange => f.los_range_features(&s, &mut feats),
                InputLayout::Gain => {
                    f.prior_features(&s, &mut feats);
                }
                InputLayout::Paper => paper_features(self.model.kind, inp, &mut feats),
            }
            for (xi, v) in x.iter_mut().zip(&feats[..self.kernel.n_in()]) {
                xi[lane] = *v as f32;
            }
            frames[lane] = Some((f, s));
        }
        let mut y: [Lanes; MAX_IO] = [[0.0; LANES]; MAX_IO];
        self.kernel.forward(&x, &mut y, scratch);
        let mut raw = [0f64; MAX_IO];
        for (lane, (inp, o)) in inputs.iter().zip(outputs.iter_mut()).enumerate() {
            let Some((f, s)) = &frames[lane] else {
                *o = UpdateOutput::rejected(&inp.prior);
                continue;
            };
            for (r, yi) in raw.iter_mut().zip(&y[..self.kernel.n_out()]) {
                *r = yi[lane] as f64;
            }
            *o = self
                .decode(needs, inp, f, s, &raw)
                .unwrap_or_else(|| UpdateOutput::rejected(&inp.prior));
        }
    }

    /// One item's posterior (and likelihood when asked) from the network's raw outputs.
    #[inline(always)]
    fn decode<const D: usize>(
        &self,
        needs: UpdateNeeds,
        inp: &UpdateInput,
        f: &Frame<D>,
        s: &SVector<f64, D>,
        raw: &[f64],
    ) -> Option<UpdateOutput> {
        let closed_form = match self.model.layout {
            InputLayout::Paper => true,
            _ => self.model.covariance == CovarianceSource::ClosedForm,
        };
        let inn = if closed_form || needs.likelihood() {
            f.innovation(needs.likelihood())
        } else {
            None
        };
        if closed_form && inn.is_none() {
            return None;
        }
        let closed = |inn: &Option<_>| inn.as_ref().map(|i| f.closed_form_cov(i));
        let posterior = match self.model.layout {
            InputLayout::LineOfSight | InputLayout::LineOfSightRange | InputLayout::Gain => {
                let (corr, cov) = if self.model.layout == InputLayout::Gain {
                    f.gain_decode(s, raw)
                } else {
                    f.los_decode(s, raw)
                };
                let cov = if closed_form { closed(&inn)? } else { cov };
                f.world_posterior(&inp.prior.mean, &corr, &cov)
            }
            InputLayout::Paper => {
                let mut post =
                    f.world_posterior(&inp.prior.mean, &SVector::<f64, D>::zeros(), &closed(&inn)?);
                post.mean[..D].copy_from_slice(&raw[..D]);
                post
            }
        };
        if !posterior.is_finite() {
            return None;
        }
        // The posterior does not depend on what was asked; an innovation that cannot be
        // computed only makes the observation infinitely unlikely.
        let (log_likelihood, mahalanobis2) = match (&inn, needs.likelihood()) {
            (Some(i), true) if i.log_likelihood.is_finite() => (i.log_likelihood, i.mahalanobis2),
            (_, true) => (f64::NEG_INFINITY, f64::INFINITY),
            (_, false) => (f64::NAN, f64::NAN),
        };
        Some(UpdateOutput {
            posterior,
            log_likelihood,
            mahalanobis2,
        })
    }
}

/// A batch's passes, as one [`pulp::WithSimd`] operation: `with_simd` is inlined into the
/// function that `Arch::dispatch` compiles for the detected instruction set, and so are the
/// pass, the kernel and its layers (`#[inline(always)]`). (A closure would not be: its body
/// would stay a separate function compiled for the baseline.)
struct Passes<'a, F> {
    updater: &'a MlpUpdater,
    needs: UpdateNeeds,
    inputs: &'a [UpdateInput],
    outputs: &'a mut [UpdateOutput],
    frame: F,
    scratch: &'a mut Scratch,
}

impl<const D: usize, F: Fn(&UpdateInput) -> Option<Frame<D>>> pulp::WithSimd for Passes<'_, F> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _simd: S) {
        for (inp, out) in self
            .inputs
            .chunks(LANES)
            .zip(self.outputs.chunks_mut(LANES))
        {
            self.updater
                .pass(self.needs, inp, out, &self.frame, self.scratch);
        }
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

    fn update_batch(
        &self,
        needs: UpdateNeeds,
        inputs: &[UpdateInput],
        outputs: &mut [UpdateOutput],
    ) {
        debug_assert_eq!(inputs.len(), outputs.len());
        let noise = &self.model.noise;
        match self.model.kind {
            LandmarkKind::RangeBearing2d => {
                self.run::<2>(needs, inputs, outputs, |i| frame2(i, noise))
            }
            LandmarkKind::Point3d => {
                self.run::<3>(needs, inputs, outputs, |i| Some(frame3(i, noise)))
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
    let inn = f.innovation(true)?;
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
    use fleetslam_core::math;
    use fleetslam_core::sensor::SensorNoise;
    use rand::{Rng, SeedableRng};

    fn noise() -> SensorNoise {
        SensorNoise {
            range: 0.1,
            bearing: 0.03,
            xyz: [0.05, 0.08, 0.1],
            range_per_m: 0.0,
        }
    }

    fn gain_round_trip<const D: usize>(f: &Frame<D>, prior_mean: &[f64; 3]) -> LandmarkGaussian {
        let inn = f.innovation(false).unwrap();
        let cov = f.closed_form_cov(&inn);
        let mut t = [0.0; MAX_IO];
        f.gain_targets(&inn, &cov, &mut t).unwrap();
        let (corr, cov) = f.gain_decode(&f.prior_std(), &t);
        f.world_posterior(prior_mean, &corr, &cov)
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
                    LandmarkKind::Point3d => [
                        r * math::cos(b),
                        r * math::sin(b),
                        rng.random_range(-1.0..1.0),
                    ],
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
                // The gain layout's targets decode back to the EKF's update.
                let via_gain = match kind {
                    LandmarkKind::RangeBearing2d => {
                        gain_round_trip(&frame2(&inp, &noise()).unwrap(), &prior.mean)
                    }
                    LandmarkKind::Point3d => gain_round_trip(&frame3(&inp, &noise()), &prior.mean),
                };
                for (g, w) in via_gain.mean.iter().zip(&want.posterior.mean) {
                    assert!((g - w).abs() < 1e-9, "{kind:?} gain mean");
                }
                for (g, w) in via_gain.cov.iter().zip(&want.posterior.cov) {
                    assert!((g - w).abs() < 1e-9 * (1.0 + w.abs()), "{kind:?} gain cov");
                }
            }
        }
    }

    /// A decoded posterior covariance is never wider than the prior along a frame axis, and
    /// within that bound it is what the network said.
    #[test]
    fn decoded_covariance_never_exceeds_the_prior() {
        let ekf = EkfUpdater::new(LandmarkKind::RangeBearing2d, &noise());
        let pose = Pose2::new(0.3, -0.2, 0.4);
        let mut prior = ekf.initialize(&pose, &[3.0, 0.2, 0.0]);
        prior.cov[1] += 0.002;
        let f = frame2(
            &UpdateInput {
                prior,
                pose,
                z: [3.1, 0.21, 0.0],
            },
            &noise(),
        )
        .unwrap();
        let s = f.prior_std();
        // ln L = +3 on the diagonal and a large off-diagonal: far wider than the prior.
        let (_, wide) = f.los_decode(&s, &[0.0, 0.0, 3.0, 3.0, 5.0]);
        for i in 0..2 {
            assert!(wide[(i, i)] <= f.sigma[(i, i)] * (1.0 + 1e-12), "axis {i}");
        }
        assert!((wide[(0, 0)] - f.sigma[(0, 0)]).abs() < 1e-12 * f.sigma[(0, 0)]);
        // A narrower posterior passes unchanged: L = diag(e^-1, e^-2), L_ba = 0.1.
        let (_, narrow) = f.los_decode(&s, &[0.0, 0.0, -1.0, -2.0, 0.1]);
        let (a, b) = (math::exp(-1.0), math::exp(-2.0));
        assert!((narrow[(0, 0)] - a * a * s[0] * s[0]).abs() < 1e-15);
        assert!((narrow[(1, 1)] - (b * b + 0.01) * s[1] * s[1]).abs() < 1e-15);
        assert!((narrow[(1, 0)] - 0.1 * a * s[0] * s[1]).abs() < 1e-15);
    }
}
