//! The extended Kalman filter landmark update (Montemerlo et al. 2002), for 2D range-bearing
//! and 3D relative-point landmarks.
//!
//! With `h` the measurement model, `H` its Jacobian with respect to the landmark at the
//! prior mean, and `Q` the measurement noise:
//!
//! ```text
//! S  = H Σ Hᵀ + Q            innovation covariance
//! K  = Σ Hᵀ S⁻¹              gain
//! ν  = z − h(μ, x)           innovation (bearing wrapped to (−π, π])
//! μ' = μ + K ν
//! Σ' = Σ − K (Σ Hᵀ)ᵀ = Σ − Σ Hᵀ S⁻¹ H Σ   (computed symmetric: linalg::kalman_posterior_cov)
//! ln p(z) = −½ νᵀ S⁻¹ ν − ½ ln |2π S|
//! ```
//!
//! A new landmark is the inverse of the measurement with `Σ = H⁻¹ Q H⁻ᵀ`.

use crate::ekf_lanes::{self, LANES};
use crate::linalg::kalman_posterior_cov;
use crate::math;
use crate::pose::Pose2;
use crate::sensor::{
    LandmarkKind, MeasurementModel, Point3Model, RangeBearingModel, SensorNoise, point3_inverse,
    range_bearing_inverse,
};
use crate::stats::gaussian_log_density;
use crate::updater::{LandmarkGaussian, LandmarkUpdater, UpdateInput, UpdateNeeds, UpdateOutput};
use nalgebra::{Matrix2, Matrix3, SMatrix};

/// The EKF updater.
#[derive(Debug, Clone)]
pub struct EkfUpdater {
    kind: LandmarkKind,
    noise: SensorNoise,
    /// The noise when it does not depend on the reading (no `range_per_m`).
    q2: Matrix2<f64>,
    q3: Matrix3<f64>,
    /// The instruction set a batch is compiled for, detected at construction: AVX2 where
    /// the CPU has it, as the learned updater's passes (a fair comparison). Rust never fuses
    /// a multiply and an add on its own, so every instruction set gives the same bits.
    arch: pulp::Arch,
}

impl EkfUpdater {
    pub fn new(kind: LandmarkKind, noise: &SensorNoise) -> Self {
        Self {
            kind,
            noise: *noise,
            q2: noise.q2(),
            q3: noise.q3(),
            arch: pulp::Arch::new(),
        }
    }

    /// The same updater without runtime SIMD dispatch (the baseline instruction set).
    pub fn baseline_simd(mut self) -> Self {
        self.arch = pulp::Arch::Scalar;
        self
    }

    /// One 2D range-bearing update with the sensor's noise at the input's range.
    #[inline(always)]
    fn update_2d(&self, i: &UpdateInput, needs: UpdateNeeds) -> UpdateOutput {
        let rpm = self.noise.range_per_m;
        if rpm == 0.0 {
            // A constant noise is read, not built per update.
            return Self::update::<2, RangeBearingModel>(&self.q2, i, needs);
        }
        // `RangeBearingModel::noise` (`q2_at`), as an increment of the constant part: the
        // same sums, and an instruction mix valgrind decodes.
        let g = rpm * i.z[0];
        let mut q = self.q2;
        q[(0, 0)] += g * g;
        Self::update::<2, RangeBearingModel>(&q, i, needs)
    }

    /// One update in measurement model `M` with noise `q` (the 2D one in 2x2 matrices).
    #[inline(always)]
    pub(crate) fn update<const D: usize, M: MeasurementModel<D>>(
        q: &SMatrix<f64, D, D>,
        inp: &UpdateInput,
        needs: UpdateNeeds,
    ) -> UpdateOutput {
        let prior = &inp.prior;
        let Some((zhat, h, _)) = M::predict(&inp.pose, &prior.mean) else {
            return UpdateOutput::rejected(prior);
        };
        let sigma = M::cov(prior);
        let sht = sigma * h.transpose();
        let s = h * sht + q;
        let Some((s_inv, det)) = M::inverse_det(&s) else {
            return UpdateOutput::rejected(prior);
        };
        let k = sht * s_inv;
        let nu = M::innovation(&inp.z, &zhat);
        let mean = M::mean(prior) + k * nu;
        let cov = kalman_posterior_cov(&sigma, &k, &sht);
        finish(prior, M::gaussian(&mean, &cov), needs, || {
            let m2 = nu.dot(&(s_inv * nu));
            (gaussian_log_density(m2, math::ln(det), D), m2)
        })
    }
}

/// A batch as one [`pulp::WithSimd`] operation: `with_simd` (and the updates, all
/// `#[inline(always)]`) is compiled into the function `Arch::dispatch` builds for the detected
/// instruction set; a closure's body would stay a separate, baseline function.
struct Batch<'a> {
    ekf: &'a EkfUpdater,
    needs: UpdateNeeds,
    inputs: &'a [UpdateInput],
    outputs: &'a mut [UpdateOutput],
}

impl pulp::WithSimd for Batch<'_> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, simd: S) {
        let (u, needs) = (self.ekf, self.needs);
        match u.kind {
            // Blocks of `LANES` updates at once ([`crate::ekf_lanes`]: the scalar update's
            // bits), the lanes it leaves and the last few inputs one by one.
            LandmarkKind::RangeBearing2d => {
                let rpm = u.noise.range_per_m;
                let blocks = if S::F64_LANES == LANES {
                    self.inputs.len() / LANES * LANES
                } else {
                    0
                };
                let (head_in, tail_in) = self.inputs.split_at(blocks);
                let (head_out, tail_out) = self.outputs.split_at_mut(blocks);
                for (i, o) in head_in
                    .chunks_exact(LANES)
                    .zip(head_out.chunks_exact_mut(LANES))
                {
                    let scalar = ekf_lanes::update_range_bearing(simd, &u.q2, rpm, i, o, needs);
                    for l in (0..LANES).filter(|&l| scalar[l]) {
                        o[l] = u.update_2d(&i[l], needs);
                    }
                }
                for (i, o) in tail_in.iter().zip(tail_out.iter_mut()) {
                    *o = u.update_2d(i, needs);
                }
            }
            LandmarkKind::Point3d => {
                for (i, o) in self.inputs.iter().zip(self.outputs.iter_mut()) {
                    *o = EkfUpdater::update::<3, Point3Model>(&u.q3, i, needs);
                }
            }
        }
    }
}

/// The output of a computed update: the likelihood only when asked for; a posterior or a
/// likelihood that is not finite makes the update a rejected one.
#[inline(always)]
fn finish(
    prior: &LandmarkGaussian,
    posterior: LandmarkGaussian,
    needs: UpdateNeeds,
    likelihood: impl FnOnce() -> (f64, f64),
) -> UpdateOutput {
    if !posterior.is_finite() {
        return UpdateOutput::rejected(prior);
    }
    let (log_likelihood, mahalanobis2) = if needs.likelihood() {
        let (ll, m2) = likelihood();
        if !ll.is_finite() {
            return UpdateOutput::rejected(prior);
        }
        (ll, m2)
    } else {
        (f64::NAN, f64::NAN)
    };
    UpdateOutput {
        posterior,
        log_likelihood,
        mahalanobis2,
    }
}

impl LandmarkUpdater for EkfUpdater {
    fn name(&self) -> &str {
        "ekf"
    }

    fn kind(&self) -> LandmarkKind {
        self.kind
    }

    fn initialize(&self, pose: &Pose2, z: &[f64; 3]) -> LandmarkGaussian {
        match self.kind {
            LandmarkKind::RangeBearing2d => {
                let (x, y) = range_bearing_inverse(pose, z[0], z[1]);
                // H_m⁻¹ maps (range, bearing) noise to position: columns are the line of
                // sight and its normal scaled by the range.
                let (s, c) = math::sin_cos(pose.theta + z[1]);
                let hinv = Matrix2::new(c, -z[0] * s, s, z[0] * c);
                let cov = hinv * self.noise.q2_at(z[0]) * hinv.transpose();
                LandmarkGaussian::from_2d([x, y], &cov)
            }
            LandmarkKind::Point3d => {
                let m = point3_inverse(pose, z);
                let (s, c) = math::sin_cos(pose.theta);
                let r = Matrix3::new(c, -s, 0.0, s, c, 0.0, 0.0, 0.0, 1.0);
                LandmarkGaussian::from_3d(m, &(r * self.q3 * r.transpose()))
            }
        }
    }

    fn update_batch(
        &self,
        needs: UpdateNeeds,
        inputs: &[UpdateInput],
        outputs: &mut [UpdateOutput],
    ) {
        debug_assert_eq!(inputs.len(), outputs.len());
        self.arch.dispatch(Batch {
            ekf: self,
            needs,
            inputs,
            outputs,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sensor::range_bearing_predict;
    use crate::stats::LN_2PI;
    use proptest::prelude::*;

    fn noise() -> SensorNoise {
        SensorNoise {
            range: 0.1,
            bearing: 0.05,
            xyz: [0.1, 0.2, 0.3],
            range_per_m: 0.0,
        }
    }

    #[test]
    fn ekf_2d_hand_worked() {
        // Robot at origin facing +x, landmark prior at (2, 0) with covariance I * 0.01.
        // H = [[1, 0], [0, 0.5]] (dx = 2, dy = 0, r = 2, q = 4).
        // S = diag(0.01 + 0.01, 0.25 * 0.01 + 0.0025) = diag(0.02, 0.005).
        // K = Σ Hᵀ S⁻¹ = diag(0.01 / 0.02, 0.01 * 0.5 / 0.005) = diag(0.5, 1.0).
        // z = (2.2, 0.1): ν = (0.2, 0.1) → μ' = (2.1, 0.1).
        let u = EkfUpdater::new(LandmarkKind::RangeBearing2d, &noise());
        let prior = LandmarkGaussian {
            mean: [2.0, 0.0, 0.0],
            cov: [0.01, 0.0, 0.0, 0.01, 0.0, 0.0],
        };
        let out = u.update(&UpdateInput {
            prior,
            pose: Pose2::default(),
            z: [2.2, 0.1, 0.0],
        });
        assert!((out.posterior.mean[0] - 2.1).abs() < 1e-12);
        assert!((out.posterior.mean[1] - 0.1).abs() < 1e-12);
        // Σ' = (I − KH) Σ: diag(0.5 * 0.01, (1 − 0.5) * 0.01) = diag(0.005, 0.005).
        assert!((out.posterior.cov[0] - 0.005).abs() < 1e-12);
        assert!((out.posterior.cov[3] - 0.005).abs() < 1e-12);
        assert!(out.posterior.cov[1].abs() < 1e-12);
        // m² = 0.2² / 0.02 + 0.1² / 0.005 = 2 + 2 = 4.
        assert!((out.mahalanobis2 - 4.0).abs() < 1e-12);
        let ll = -2.0 - LN_2PI - 0.5 * math::ln(0.02f64 * 0.005);
        assert!((out.log_likelihood - ll).abs() < 1e-12);
    }

    #[test]
    fn range_noise_that_grows_with_range_is_the_constant_noise_at_that_range() {
        // range_per_m = 0.05: a reading of range r has range std √(0.1² + (0.05 r)²); the
        // update (and a new landmark) must equal the constant-noise EKF's at that std.
        let grow = SensorNoise {
            range_per_m: 0.05,
            ..noise()
        };
        let u = EkfUpdater::new(LandmarkKind::RangeBearing2d, &grow);
        let prior = LandmarkGaussian {
            mean: [4.0, 1.0, 0.0],
            cov: [0.04, 0.01, 0.0, 0.03, 0.0, 0.0],
        };
        let pose = Pose2::new(0.5, -0.2, 0.3);
        for z in [[1.0f64, 0.1, 0.0], [4.2, 0.02, 0.0], [9.0, -0.3, 0.0]] {
            let fixed = SensorNoise {
                range: (0.1f64.powi(2) + (0.05 * z[0]).powi(2)).sqrt(),
                ..noise()
            };
            let v = EkfUpdater::new(LandmarkKind::RangeBearing2d, &fixed);
            let (a, b) = (
                u.update(&UpdateInput { prior, pose, z }),
                v.update(&UpdateInput { prior, pose, z }),
            );
            let close = |x: f64, y: f64| (x - y).abs() <= 1e-12 * (1.0 + y.abs());
            for (x, y) in a.posterior.mean.iter().zip(&b.posterior.mean) {
                assert!(close(*x, *y), "z {z:?}: {a:?} against {b:?}");
            }
            for (x, y) in a.posterior.cov.iter().zip(&b.posterior.cov) {
                assert!(close(*x, *y), "z {z:?}: {a:?} against {b:?}");
            }
            assert!(close(a.log_likelihood, b.log_likelihood), "z {z:?}");
            assert!(close(a.mahalanobis2, b.mahalanobis2), "z {z:?}");
            let (na, nb) = (u.initialize(&pose, &z), v.initialize(&pose, &z));
            for (x, y) in na.cov.iter().zip(&nb.cov) {
                assert!(close(*x, *y), "z {z:?}: {na:?} against {nb:?}");
            }
        }
        // With it, a far reading moves the landmark less than the constant noise does.
        let z = [6.0, 0.3, 0.0];
        let (a, b) = (
            u.update(&UpdateInput { prior, pose, z }),
            EkfUpdater::new(LandmarkKind::RangeBearing2d, &noise()).update(&UpdateInput {
                prior,
                pose,
                z,
            }),
        );
        let moved = |o: &UpdateOutput| {
            math::hypot(
                o.posterior.mean[0] - prior.mean[0],
                o.posterior.mean[1] - prior.mean[1],
            )
        };
        assert!(moved(&a) < moved(&b), "{a:?} against {b:?}");
    }

    #[test]
    fn ekf_3d_hand_worked() {
        // Robot at origin facing +x: H = I, so each axis is a scalar Kalman update.
        let u = EkfUpdater::new(LandmarkKind::Point3d, &noise());
        let prior = LandmarkGaussian {
            mean: [1.0, 2.0, 3.0],
            cov: [0.01, 0.0, 0.0, 0.04, 0.0, 0.09],
        };
        let out = u.update(&UpdateInput {
            prior,
            pose: Pose2::default(),
            z: [1.2, 2.2, 3.2],
        });
        // Gains 0.01/0.02, 0.04/0.08, 0.09/0.18 = 0.5 each: every coordinate moves by 0.1.
        for (k, want) in [1.1, 2.1, 3.1].iter().enumerate() {
            assert!((out.posterior.mean[k] - want).abs() < 1e-12);
        }
        assert!((out.posterior.cov[0] - 0.005).abs() < 1e-12);
        assert!((out.posterior.cov[3] - 0.02).abs() < 1e-12);
        assert!((out.posterior.cov[5] - 0.045).abs() < 1e-12);
    }

    #[test]
    fn initialize_inverts_the_measurement() {
        let u = EkfUpdater::new(LandmarkKind::RangeBearing2d, &noise());
        let pose = Pose2::new(1.0, 2.0, 0.5);
        let g = u.initialize(&pose, &[3.0, -0.4, 0.0]);
        let (z, _, _) = range_bearing_predict(&pose, g.mean[0], g.mean[1]).unwrap();
        assert!((z[0] - 3.0).abs() < 1e-12 && (z[1] + 0.4).abs() < 1e-12);
        // Range noise lies along the line of sight, bearing noise across it, scaled by r.
        let c = g.cov2();
        let eig = c.symmetric_eigenvalues();
        let (lo, hi) = (eig.min(), eig.max());
        assert!((lo - 0.01).abs() < 1e-12 && (hi - (3.0f64 * 0.05).powi(2)).abs() < 1e-12);
    }

    #[test]
    fn degenerate_geometry_keeps_the_prior() {
        let u = EkfUpdater::new(LandmarkKind::RangeBearing2d, &noise());
        let prior = LandmarkGaussian {
            mean: [0.0, 0.0, 0.0],
            cov: [0.01, 0.0, 0.0, 0.01, 0.0, 0.0],
        };
        let out = u.update(&UpdateInput {
            prior,
            pose: Pose2::default(),
            z: [1.0, 0.0, 0.0],
        });
        assert_eq!(out.posterior, prior);
        assert_eq!(out.log_likelihood, f64::NEG_INFINITY);
    }

    fn is_spd(g: &LandmarkGaussian, kind: LandmarkKind) -> bool {
        match kind {
            LandmarkKind::RangeBearing2d => g.cov2().cholesky().is_some(),
            LandmarkKind::Point3d => g.cov3().cholesky().is_some(),
        }
    }

    proptest! {
        #[test]
        fn posterior_is_spd_and_tighter(
            px in -10.0f64..10.0, py in -10.0f64..10.0, th in -3.2f64..3.2,
            r in 0.3f64..20.0, b in -1.5f64..1.5, dz in -2.0f64..2.0,
            nr in -0.5f64..0.5, nb in -0.2f64..0.2, s in 0.001f64..4.0,
        ) {
            for kind in [LandmarkKind::RangeBearing2d, LandmarkKind::Point3d] {
                let u = EkfUpdater::new(kind, &noise());
                let pose = Pose2::new(px, py, th);
                let z0 = match kind {
                    LandmarkKind::RangeBearing2d => [r, b, 0.0],
                    LandmarkKind::Point3d => [r * math::cos(b), r * math::sin(b), dz],
                };
                let mut prior = u.initialize(&pose, &z0);
                for c in prior.cov.iter_mut() { *c *= s; }
                let z = [z0[0] + nr, z0[1] + nb, z0[2] + nr];
                let out = u.update(&UpdateInput { prior, pose, z });
                // Asking for the posterior only gives the same posterior, bit for bit.
                let mut only = [UpdateOutput::default()];
                u.update_batch(UpdateNeeds::Posterior, &[UpdateInput { prior, pose, z }], &mut only);
                prop_assert_eq!(only[0].posterior, out.posterior);
                prop_assert!(only[0].log_likelihood.is_nan());
                // So does the baseline instruction set.
                let base = u.clone().baseline_simd().update(&UpdateInput { prior, pose, z });
                prop_assert_eq!(base, out);
                prop_assert!(out.log_likelihood.is_finite());
                prop_assert!(out.mahalanobis2 >= 0.0);
                prop_assert!(is_spd(&out.posterior, kind));
                // An update never increases the variance along any axis.
                prop_assert!(out.posterior.cov[0] <= prior.cov[0] * (1.0 + 1e-9));
                prop_assert!(out.posterior.cov[3] <= prior.cov[3] * (1.0 + 1e-9));
            }
        }
    }
}
