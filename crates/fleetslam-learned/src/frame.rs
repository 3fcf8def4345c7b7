//! The measurement frame, and the two input layouts built on it.
//!
//! Both landmark kinds have a frame in which the EKF's measurement Jacobian is the identity:
//!
//! - 3D points: the robot frame. `z = Rᵀ(m − p)` with `R` the heading rotation, so `H = Rᵀ`
//!   and the update is a linear Kalman update of the rotated landmark with noise
//!   `diag(σx², σy², σz²)`.
//! - 2D range-bearing: the line-of-sight frame at the prior mean, in metres (along the line
//!   of sight, across it). `H = diag(1, 1/r) R(φ)ᵀ`, so with the bearing innovation scaled by
//!   the range `r` the update is again linear with `H = I` and noise `diag(σr², r² σb²)`.
//!
//! In that frame the innovation covariance is `S = Σ + Q`, the gain `K = Σ S⁻¹`, the
//! correction `K ν` and the posterior covariance `Σ − K Σ` — exactly the EKF's update
//! (which computes the same posterior as `Σ − K (Σ Hᵀ)ᵀ` in the world frame). The innovation
//! likelihood the particle weight needs is `ln N(ν; 0, S)` (for range-bearing corrected by
//! `ln r`, the Jacobian of the bearing scaling), again exactly the EKF's.
//!
//! The learned updater computes that likelihood in closed form (it is the particle weight:
//! FastSLAM stays a proper particle filter whatever the network predicts), and lets the
//! network predict the landmark's posterior.

use fleetslam_core::math;
use fleetslam_core::pose::wrap_angle;
use fleetslam_core::sensor::{LandmarkKind, SensorNoise, bearing_atan2};
use fleetslam_core::updater::{LandmarkGaussian, UpdateInput};
use nalgebra::{SMatrix, SVector};
use serde::{Deserialize, Serialize};

use fleetslam_core::stats::gaussian_log_density;

/// How a model's inputs and outputs are laid out. A model trained for one layout can't be run
/// with another: the updater refuses it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum InputLayout {
    /// The paper's layout (Vidal & Rosa 2015, Fig. 1): inputs are the landmark's previous
    /// world coordinates, the robot pose `(x, y, α)` and the observation (9 inputs for the 3D
    /// stereo case, 7 for range-bearing); outputs are the landmark's new world coordinates.
    /// The paper's network also outputs one element `P_ii` of the covariance; one element
    /// cannot form a covariance (the updater takes the closed form), so it is not trained
    /// here: it would only compete with the coordinates for the two hidden neurons.
    Paper,
    /// Our layout: everything in the measurement frame, whitened by the sensor noise.
    /// Inputs `ln(σᵢ/qᵢ)`, the prior's correlations, and the innovation over its standard
    /// deviation; outputs the correction over the prior standard deviation and the Cholesky
    /// factor of the posterior covariance scaled by the prior standard deviations (log
    /// diagonal, raw off-diagonal), so that any output is a valid covariance.
    LineOfSight,
    /// The structured layout: the network sees only the prior and the noise (`ln(σᵢ/qᵢ)` and
    /// the prior's correlations, no innovation) and predicts the gain scaled by the prior and
    /// innovation standard deviations (`K̃ᵢⱼ = Kᵢⱼ uⱼ/sᵢ`, row-major) and the posterior's scaled
    /// Cholesky factor (as `line_of_sight`). The posterior mean `μ + K ν` is then exactly
    /// linear in the innovation, as the EKF's is, whatever the network's error.
    Gain,
    /// `line_of_sight` plus one input: the log of the distance from the robot to the prior
    /// mean (the range for range-bearing, the point's distance for 3D points). The whitened
    /// inputs hide the distance (they are ratios), yet a real sensor's error depends on it:
    /// on MRCLAM the range error's mean moves from +1 cm at 1-2 m to −5 cm at 4-5 m and its
    /// spread from 0.07 to 0.19 m (`python3 tools/mrclam_range_error.py`). For models
    /// trained against ground truth (the `truth` preset), which can learn that dependence;
    /// outputs as `line_of_sight`.
    LineOfSightRange,
}

impl InputLayout {
    /// The version of the feature definitions; bump it when they change so that old models
    /// are refused instead of silently misread.
    /// Version 2: the paper layout lost its `P_ii` output and `gain` was added.
    pub const VERSION: u32 = 2;

    pub fn as_str(self) -> &'static str {
        match self {
            InputLayout::Paper => "paper",
            InputLayout::LineOfSight => "line_of_sight",
            InputLayout::Gain => "gain",
            InputLayout::LineOfSightRange => "line_of_sight_range",
        }
    }

    /// (inputs, outputs) of a network for this layout and kind.
    pub fn dims(self, kind: LandmarkKind) -> (usize, usize) {
        let d = kind.dim();
        match self {
            InputLayout::Paper => (2 * d + 3, d),
            InputLayout::LineOfSight => (2 * d + d * (d - 1) / 2, 2 * d + d * (d - 1) / 2),
            InputLayout::LineOfSightRange => (2 * d + d * (d - 1) / 2 + 1, 2 * d + d * (d - 1) / 2),
            InputLayout::Gain => (d + d * (d - 1) / 2, d * d + d + d * (d - 1) / 2),
        }
    }

    /// Names of the outputs, for reports.
    pub fn output_names(self, kind: LandmarkKind) -> Vec<String> {
        let d = kind.dim();
        let ax = ["a", "b", "c"];
        match self {
            InputLayout::Paper => ["x_t", "y_t", "z_t"][..d]
                .iter()
                .map(|s| s.to_string())
                .collect(),
            InputLayout::LineOfSight | InputLayout::LineOfSightRange | InputLayout::Gain => {
                let mut v: Vec<String> = if self == InputLayout::Gain {
                    (0..d)
                        .flat_map(|i| (0..d).map(move |j| format!("K_{}{}", ax[i], ax[j])))
                        .collect()
                } else {
                    (0..d).map(|i| format!("dmean_{}", ax[i])).collect()
                };
                v.extend((0..d).map(|i| format!("ln_L_{}{}", ax[i], ax[i])));
                for i in 0..d {
                    for j in 0..i {
                        v.push(format!("L_{}{}", ax[i], ax[j]));
                    }
                }
                v
            }
        }
    }
}

/// The smallest distance [m] the `line_of_sight_range` layout's `ln d` input takes (a prior
/// mean on the robot would give `−∞`).
pub const MIN_FEATURE_DISTANCE: f64 = 1e-3;

/// One update seen in its measurement frame.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Frame<const D: usize> {
    /// World → frame rotation (rows are the frame's axes in world coordinates).
    pub t: SMatrix<f64, D, D>,
    /// Prior covariance in the frame.
    pub sigma: SMatrix<f64, D, D>,
    /// Noise variances in the frame.
    pub q: SVector<f64, D>,
    /// Innovation in the frame.
    pub nu: SVector<f64, D>,
    /// `ln ll_scale` added to the frame's log-likelihood gives the likelihood in measurement
    /// units (the range for range-bearing, 1 for 3D points).
    pub ll_scale: f64,
    /// Distance from the robot to the prior mean [m].
    pub dist: f64,
}

#[inline]
fn cov2(c: &[f64; 6]) -> SMatrix<f64, 2, 2> {
    SMatrix::<f64, 2, 2>::new(c[0], c[1], c[1], c[3])
}

#[inline]
fn cov3(c: &[f64; 6]) -> SMatrix<f64, 3, 3> {
    SMatrix::<f64, 3, 3>::new(c[0], c[1], c[2], c[1], c[3], c[4], c[2], c[4], c[5])
}

/// The range-bearing frame; `None` when the prior mean sits on the robot.
#[inline]
pub(crate) fn frame2(inp: &UpdateInput, noise: &SensorNoise) -> Option<Frame<2>> {
    let dx = inp.prior.mean[0] - inp.pose.x;
    let dy = inp.prior.mean[1] - inp.pose.y;
    let q = dx * dx + dy * dy;
    if q.is_nan() || q < 1e-12 {
        return None;
    }
    let r = q.sqrt();
    let (c, s) = (dx / r, dy / r);
    let t = SMatrix::<f64, 2, 2>::new(c, s, -s, c);
    let sigma = t * cov2(&inp.prior.cov) * t.transpose();
    let bearing = wrap_angle(bearing_atan2(dy, dx) - inp.pose.theta);
    let nu = SVector::<f64, 2>::new(inp.z[0] - r, r * wrap_angle(inp.z[1] - bearing));
    Some(Frame {
        t,
        sigma,
        q: SVector::<f64, 2>::new(
            noise.range_var_at(inp.z[0]),
            q * noise.bearing * noise.bearing,
        ),
        nu,
        ll_scale: r,
        dist: r,
    })
}

/// The 3D point frame (the robot frame).
#[inline]
pub(crate) fn frame3(inp: &UpdateInput, noise: &SensorNoise) -> Frame<3> {
    let (s, c) = math::sin_cos(inp.pose.theta);
    let t = SMatrix::<f64, 3, 3>::new(c, s, 0.0, -s, c, 0.0, 0.0, 0.0, 1.0);
    let sigma = t * cov3(&inp.prior.cov) * t.transpose();
    let m = &inp.prior.mean;
    let d = SVector::<f64, 3>::new(m[0] - inp.pose.x, m[1] - inp.pose.y, m[2]);
    let zhat = t * d;
    let dist = d.norm();
    let nu = SVector::<f64, 3>::new(inp.z[0], inp.z[1], inp.z[2]) - zhat;
    let x = &noise.xyz;
    Frame {
        t,
        sigma,
        q: SVector::<f64, 3>::new(x[0] * x[0], x[1] * x[1], x[2] * x[2]),
        nu,
        ll_scale: 1.0,
        dist,
    }
}

/// The innovation statistics: `S = Σ + Q`, its inverse, `ln p(z)` and the squared Mahalanobis
/// distance. `None` when `S` is not positive definite.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Innovation<const D: usize> {
    pub s_inv: SMatrix<f64, D, D>,
    pub log_likelihood: f64,
    pub mahalanobis2: f64,
}

impl<const D: usize> Frame<D> {
    /// `S = Σ + Q` and its inverse; the likelihood and Mahalanobis distance only when
    /// `likelihood` (NaN otherwise). `None` when `S` is not positive definite.
    #[inline]
    pub fn innovation(&self, likelihood: bool) -> Option<Innovation<D>> {
        let s = self.sigma + SMatrix::<f64, D, D>::from_diagonal(&self.q);
        let chol = s.cholesky()?;
        let s_inv = chol.inverse();
        let (ll, m2) = if likelihood {
            let det = chol.determinant();
            let m2 = self.nu.dot(&(s_inv * self.nu));
            let ll = gaussian_log_density(m2, math::ln(det), D) + math::ln(self.ll_scale);
            (ll, m2)
        } else {
            (f64::NAN, f64::NAN)
        };
        Some(Innovation {
            s_inv,
            log_likelihood: ll,
            mahalanobis2: m2,
        })
    }

    /// The EKF posterior covariance in the frame, `Σ − Σ S⁻¹ Σ`, symmetrised.
    #[inline]
    pub fn closed_form_cov(&self, inn: &Innovation<D>) -> SMatrix<f64, D, D> {
        let c = self.sigma - self.sigma * inn.s_inv * self.sigma;
        (c + c.transpose()) * 0.5
    }

    /// A frame correction and covariance back in the world.
    #[inline]
    pub fn world_posterior(
        &self,
        prior_mean: &[f64; 3],
        corr: &SVector<f64, D>,
        cov: &SMatrix<f64, D, D>,
    ) -> LandmarkGaussian {
        let dw = self.t.transpose() * corr;
        let cw = self.t.transpose() * cov * self.t;
        let mut mean = *prior_mean;
        for (m, d) in mean.iter_mut().zip(dw.iter()) {
            *m += d;
        }
        if D == 2 {
            LandmarkGaussian::from_2d(
                [mean[0], mean[1]],
                &nalgebra::Matrix2::new(cw[(0, 0)], cw[(0, 1)], cw[(1, 0)], cw[(1, 1)]),
            )
        } else {
            let m3 = nalgebra::Matrix3::from_fn(|i, j| cw[(i, j)]);
            LandmarkGaussian::from_3d(mean, &m3)
        }
    }

    /// A world posterior in the frame: (correction, covariance).
    #[inline]
    pub fn frame_posterior(
        &self,
        prior_mean: &[f64; 3],
        post: &LandmarkGaussian,
    ) -> (SVector<f64, D>, SMatrix<f64, D, D>) {
        let dw = SVector::<f64, D>::from_fn(|i, _| post.mean[i] - prior_mean[i]);
        let cw = if D == 2 {
            let c = cov2(&post.cov);
            SMatrix::<f64, D, D>::from_fn(|i, j| c[(i, j)])
        } else {
            let c = cov3(&post.cov);
            SMatrix::<f64, D, D>::from_fn(|i, j| c[(i, j)])
        };
        (self.t * dw, self.t * cw * self.t.transpose())
    }

    /// The innovation's standard deviations in the frame, `sqrt(σᵢᵢ + qᵢ)`.
    #[inline]
    pub fn innovation_std(&self) -> SVector<f64, D> {
        SVector::<f64, D>::from_fn(|i, _| (self.sigma[(i, i)] + self.q[i]).sqrt())
    }

    /// Prior standard deviations in the frame.
    #[inline]
    pub fn prior_std(&self) -> SVector<f64, D> {
        SVector::<f64, D>::from_fn(|i, _| self.sigma[(i, i)].max(1e-300).sqrt())
    }

    /// The prior features: `ln(σᵢ/qᵢ)` and the correlations `ρᵢⱼ` (i > j); returns how many
    /// were written (`D + D(D−1)/2`).
    #[inline]
    pub fn prior_features(&self, s: &SVector<f64, D>, out: &mut [f64]) -> usize {
        let mut k = 0;
        for i in 0..D {
            out[k] = 0.5 * math::ln(self.sigma[(i, i)].max(1e-300) / self.q[i]);
            k += 1;
        }
        for i in 0..D {
            for j in 0..i {
                out[k] = self.sigma[(i, j)] / (s[i] * s[j]);
                k += 1;
            }
        }
        k
    }

    /// The line-of-sight features: the prior features, then `νᵢ / sqrt(σᵢ² + qᵢ²)`.
    #[inline]
    pub fn los_features(&self, s: &SVector<f64, D>, out: &mut [f64]) {
        let k = self.prior_features(s, out);
        let u = self.innovation_std();
        for (i, o) in out[k..k + D].iter_mut().enumerate() {
            *o = self.nu[i] / u[i];
        }
    }

    /// The `line_of_sight_range` features: the line-of-sight features, then `ln d` (`d` the
    /// distance to the prior mean, floored at 1 mm).
    #[inline]
    pub fn los_range_features(&self, s: &SVector<f64, D>, out: &mut [f64]) {
        self.los_features(s, out);
        let k = D + D * (D - 1) / 2 + D;
        out[k] = math::ln(self.dist.max(MIN_FEATURE_DISTANCE));
    }

    /// The gain targets: `K̃ᵢⱼ = Kᵢⱼ uⱼ/sᵢ` of `K = Σ S⁻¹` (row-major; `s` the prior standard
    /// deviations, `u` the innovation's, `sqrt(σⱼⱼ + qⱼ)`), then the scaled Cholesky factor of
    /// the posterior `cov`. The correction is `sᵢ Σⱼ K̃ᵢⱼ (νⱼ/uⱼ)`: an error in `K̃` moves the
    /// landmark by a fraction of its prior standard deviation per standard deviation of
    /// innovation, whatever the ratio of the frame's axes (`K̃ᵢᵢ = sqrt(σᵢᵢ/(σᵢᵢ + qᵢ))` when
    /// uncorrelated). `None` when the posterior is not positive definite.
    pub fn gain_targets(
        &self,
        inn: &Innovation<D>,
        cov: &SMatrix<f64, D, D>,
        out: &mut [f64],
    ) -> Option<()> {
        let s = self.prior_std();
        let u = self.innovation_std();
        let k = self.sigma * inn.s_inv;
        for i in 0..D {
            for j in 0..D {
                out[i * D + j] = k[(i, j)] * u[j] / s[i];
            }
        }
        scaled_cholesky_targets(&s, cov, &mut out[D * D..])
    }

    /// Inverse of [`Frame::gain_targets`]: the correction `K ν` and the covariance.
    #[inline]
    pub fn gain_decode(
        &self,
        s: &SVector<f64, D>,
        out: &[f64],
    ) -> (SVector<f64, D>, SMatrix<f64, D, D>) {
        let u = self.innovation_std();
        let corr = SVector::<f64, D>::from_fn(|i, _| {
            (0..D)
                .map(|j| out[i * D + j] * self.nu[j] / u[j])
                .sum::<f64>()
                * s[i]
        });
        (corr, scaled_cholesky_decode(s, &out[D * D..]))
    }

    /// The line-of-sight targets of a known posterior (frame correction and covariance):
    /// the correction over the prior standard deviation, then the scaled Cholesky factor.
    /// `None` when the posterior is not positive definite.
    pub fn los_targets(
        &self,
        corr: &SVector<f64, D>,
        cov: &SMatrix<f64, D, D>,
        out: &mut [f64],
    ) -> Option<()> {
        let s = self.prior_std();
        for i in 0..D {
            out[i] = corr[i] / s[i];
        }
        scaled_cholesky_targets(&s, cov, &mut out[D..])
    }

    /// Inverse of [`Frame::los_targets`].
    #[inline]
    pub fn los_decode(
        &self,
        s: &SVector<f64, D>,
        out: &[f64],
    ) -> (SVector<f64, D>, SMatrix<f64, D, D>) {
        let corr = SVector::<f64, D>::from_fn(|i, _| out[i] * s[i]);
        (corr, scaled_cholesky_decode(s, &out[D..]))
    }
}

/// The Cholesky factor `L` of `S⁻¹ Σ' S⁻¹` (`S` the prior standard deviations): `ln Lᵢᵢ`,
/// then `Lᵢⱼ` (i > j). `None` when `Σ'` is not positive definite.
fn scaled_cholesky_targets<const D: usize>(
    s: &SVector<f64, D>,
    cov: &SMatrix<f64, D, D>,
    out: &mut [f64],
) -> Option<()> {
    let scaled = SMatrix::<f64, D, D>::from_fn(|i, j| cov[(i, j)] / (s[i] * s[j]));
    let l = scaled.cholesky()?.l();
    let mut k = 0;
    for i in 0..D {
        out[k] = math::ln(l[(i, i)]);
        k += 1;
    }
    for i in 0..D {
        for j in 0..i {
            out[k] = l[(i, j)];
            k += 1;
        }
    }
    Some(())
}

/// Inverse of [`scaled_cholesky_targets`]: always positive definite (the log diagonal is
/// clamped to ±20 so that `exp` stays finite), and never wider than the prior along a frame
/// axis. In the measurement frame the EKF's posterior is `Σ − Σ S⁻¹ Σ` with `Σ S⁻¹ Σ` positive
/// semi-definite, so `Σ'ᵢᵢ ≤ Σᵢᵢ`: in the scaled factor, each row's squared norm (`Σ'ᵢᵢ/Σᵢᵢ`)
/// is at most 1. A network's row that exceeds it is scaled back to norm 1; otherwise a
/// landmark updated thousands of times could see its covariance grow without bound.
#[inline]
fn scaled_cholesky_decode<const D: usize>(s: &SVector<f64, D>, out: &[f64]) -> SMatrix<f64, D, D> {
    let mut l = SMatrix::<f64, D, D>::zeros();
    for i in 0..D {
        l[(i, i)] = math::exp(out[i].clamp(-20.0, 20.0));
    }
    let mut k = D;
    for i in 0..D {
        for j in 0..i {
            l[(i, j)] = out[k];
            k += 1;
        }
    }
    for i in 0..D {
        let n2: f64 = (0..=i).map(|j| l[(i, j)] * l[(i, j)]).sum();
        let scale = if n2 > 1.0 { n2.sqrt().recip() } else { 1.0 };
        for j in 0..=i {
            l[(i, j)] *= scale * s[i];
        }
    }
    l * l.transpose()
}

/// The paper's inputs: prior mean (d), pose (3), observation (d).
#[inline]
pub(crate) fn paper_features(kind: LandmarkKind, inp: &UpdateInput, out: &mut [f64]) {
    let d = kind.dim();
    out[..d].copy_from_slice(&inp.prior.mean[..d]);
    out[d] = inp.pose.x;
    out[d + 1] = inp.pose.y;
    out[d + 2] = inp.pose.theta;
    out[d + 3..2 * d + 3].copy_from_slice(&inp.z[..d]);
}

/// The paper's targets: the posterior mean.
pub(crate) fn paper_targets(kind: LandmarkKind, post: &LandmarkGaussian, out: &mut [f64]) {
    let d = kind.dim();
    out[..d].copy_from_slice(&post.mean[..d]);
}
