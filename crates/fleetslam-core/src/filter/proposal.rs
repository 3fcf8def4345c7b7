//! How a particle's pose moves: FastSLAM 2.0's proposal (the motion prediction refined by
//! the matched observations), robot sightings as Kalman updates of a deferred pose
//! Gaussian, FastSLAM 1.0's motion sample, and the odometry scales' draws and walk.

use super::gauss::{cholesky_psd, normal3, sym3};
use super::{Action, StepCtx};
use crate::config::OdometryCalibration;
use crate::linalg::{kalman_posterior_cov, mul, mul_t, sandwich};
use crate::map::{Landmark, LandmarkMap};
use crate::math;
use crate::motion::scale_increment;
use crate::pose::{Pose2, wrap_angle};
use crate::rng::StandardNormal;
use crate::rng::{LANE_CALIBRATION, Stream, stream};
use crate::sensor::{MeasurementModel, RangeBearingModel};
use crate::stats::{MixtureLogSum, gaussian_log_density, log_add_exp};
use nalgebra::{Matrix2, Matrix2x3, Matrix3, SMatrix, Vector2, Vector3};
use rand::Rng;

/// Log-likelihood of a sighting `z` (range, bearing) of robot `other` from `pose` (pose
/// covariance `pr`) in the particle of index `particle`, where `other` stands at its pose
/// there with its pose covariance's position block, with sighting noise `qs`; and the
/// Kalman gain and innovation that update `pose`'s Gaussian with it: the marginal over both
/// robots' pose Gaussians (a point pose has a zero covariance). `None` for a degenerate
/// geometry, or for the stepping robot itself (whose sightings are refused before a step).
#[allow(clippy::type_complexity, clippy::too_many_arguments)]
#[inline(always)]
pub(super) fn sighting_marginal(
    ctx: &StepCtx<'_>,
    particle: usize,
    other: usize,
    pose: &Pose2,
    pr: &Matrix3<f64>,
    qs: &Matrix2<f64>,
    z: &[f64; 2],
) -> Option<(f64, Matrix2x3<f64>, Matrix2<f64>, Vector2<f64>)> {
    let (target, target_cov) = ctx.others.get(other, particle)?;
    let pt = sym3(target_cov);
    let (zhat, hm, hx) = RangeBearingModel::predict(pose, &[target.x, target.y, 0.0])?;
    let ptp = pt.fixed_view::<2, 2>(0, 0).into_owned();
    let s = qs + sandwich(&hm, &ptp) + sandwich(&hx, pr);
    let (s_inv, det) = RangeBearingModel::inverse_det(&s)?;
    let nu = RangeBearingModel::innovation(&[z[0], z[1], 0.0], &zhat);
    let ll = gaussian_log_density(nu.dot(&mul(&s_inv, &nu)), math::ln(det), 2);
    ll.is_finite().then_some((ll, hx, s_inv, nu))
}

/// The landmark of `map` that the proposal refines a pose by for an observation the
/// association gave action `act`, or `None` with the observation's term of the log-weight
/// added to `dw`: clutter (density `clutter`) for a new landmark or an outlier, the mixture
/// of its best likelihood `best_ll` and clutter for an ambiguous one or one the association
/// made new. With known ids the association leaves the lookup to the proposal: an id the map
/// does not hold yet starts a landmark (`act` becomes `New`, weighed as clutter). The scalar
/// proposal and the lanes' ([`super::proposal_lanes`]) share it.
#[inline(always)]
pub(super) fn matched_landmark<'m>(
    map: &'m LandmarkMap,
    act: &mut Action,
    best_ll: f64,
    clutter: f64,
    dw: &mut f64,
) -> Option<&'m Landmark> {
    match *act {
        Action::Update(s) => {
            let lm = map.get(s);
            if lm.is_none() {
                *act = Action::New(Some(s));
                *dw += clutter;
            }
            lm
        }
        Action::New(Some(_)) | Action::Outlier => {
            *dw += clutter;
            None
        }
        Action::New(None) | Action::Ignore => {
            *dw += log_add_exp(best_ll, clutter);
            None
        }
    }
}

/// FastSLAM 2.0's proposal for the particle of index `particle`, whose map is `map`: the motion prediction `N(mean0, pc)` refined by
/// each observation the association matched, and with `sightings_in_proposal` each sighting
/// of another robot (a Kalman update of the pose per observation), then sampled. Returns the sampled pose and the particle's log-weight increment, the sum of
/// each observation's mixture likelihood (its proposal marginal for the matched ones), or
/// `None` when the proposal is degenerate (non-finite, or a covariance without a Cholesky
/// factor): the caller then falls back to 1.0's proposal for this particle. Matched
/// observations whose prediction fails, or beyond the `outlier` bound, become `Outlier`;
/// with known ids (`acts` holds `Update` for every observation with an id) an id the map
/// does not hold becomes `New`.
#[allow(clippy::too_many_arguments)]
#[inline(always)]
pub(super) fn propose<const D: usize, M: MeasurementModel<D>>(
    ctx: &StepCtx<'_>,
    q: &[SMatrix<f64, D, D>],
    map: &LandmarkMap,
    particle: usize,
    mean0: &Pose2,
    pc0: &Matrix3<f64>,
    acts: &mut [Action],
    best_ll: &[f64],
    rng: &mut Stream,
) -> Option<(Pose2, f64)> {
    let outlier = ctx.cfg.association_params.outlier;
    let mut mu = Vector3::new(mean0.x, mean0.y, mean0.theta);
    let mut pc = *pc0;
    let mut dw = 0.0;
    // The matched observations' mixture terms, with one logarithm for the record.
    let mut matched = MixtureLogSum::default();
    for (j, o) in ctx.obs.iter().enumerate() {
        let Some(lm) = matched_landmark(map, &mut acts[j], best_ll[j], o.clutter, &mut dw) else {
            continue;
        };
        let pose = Pose2::new(mu[0], mu[1], mu[2]);
        let Some((zhat, hm, hx)) = M::predict(&pose, &lm.gaussian.mean) else {
            acts[j] = Action::Outlier;
            dw += o.clutter;
            continue;
        };
        let qj = sandwich(&hm, &M::cov(&lm.gaussian)) + q[j];
        let pht = mul_t(&pc, &hx);
        let s = mul(&hx, &pht) + qj;
        let Some((s_inv, det)) = M::inverse_det(&s) else {
            acts[j] = Action::Outlier;
            dw += o.clutter;
            continue;
        };
        let nu = M::innovation(&o.z, &zhat);
        let m2 = nu.dot(&mul(&s_inv, &nu));
        matched.add_gaussian(m2, det, D, o.clutter);
        if outlier.is_some_and(|b| m2.is_nan() || m2 > b) {
            acts[j] = Action::Outlier;
            continue;
        }
        let k = mul(&pht, &s_inv);
        mu += mul(&k, &nu);
        mu[2] = wrap_angle(mu[2]);
        pc = kalman_posterior_cov(&pc, &k, &pht);
    }
    finish_proposal(ctx, particle, mu, pc, dw, matched, rng)
}

/// The end of FastSLAM 2.0's proposal for the particle of index `particle` after its
/// matched observations (`N(mu, pc)`, the log-weight increment `dw` of the others and the
/// `matched` ones' mixture terms): the sightings' refinement, the checks, the draw.
#[inline(always)]
pub(super) fn finish_proposal(
    ctx: &StepCtx<'_>,
    particle: usize,
    mut mu: Vector3<f64>,
    mut pc: Matrix3<f64>,
    mut dw: f64,
    matched: MixtureLogSum,
    rng: &mut Stream,
) -> Option<(Pose2, f64)> {
    // With `sightings_in_proposal` (by default with unknown association), sightings of
    // other robots refine the proposal too: the other robot's position is a landmark whose
    // covariance is its pose covariance's position block.
    let sightings = if ctx.cfg.sightings_refine_proposal() {
        ctx.sightings
    } else {
        &[]
    };
    for s in sightings {
        let pose = Pose2::new(mu[0], mu[1], mu[2]);
        let Some((ll, next, next_pc)) =
            sighting_step(ctx, particle, s.robot, &s.z, &s.q, &pose, &pc)
        else {
            dw += s.clutter;
            continue;
        };
        dw += log_add_exp(ll, s.clutter);
        mu = Vector3::new(next.x, next.y, next.theta);
        pc = next_pc;
    }
    if !(mu.iter().all(|v| v.is_finite()) && pc.iter().all(|v| v.is_finite())) {
        return None;
    }
    dw += matched.value();
    // A zero covariance (no motion noise) is a point proposal, not a failure.
    let e = if pc.iter().all(|v| *v == 0.0) {
        Vector3::zeros()
    } else {
        mul(&cholesky_psd(&pc)?, &normal3(rng))
    };
    Some((
        Pose2::new(mu[0] + e[0], mu[1] + e[1], wrap_angle(mu[2] + e[2])),
        dw,
    ))
}

/// The deferred path of FastSLAM 2.0 for a record without landmark observations, in
/// the particle of index `particle`: the robot's predicted pose Gaussian `N(mean0, pc0)` updated by each of
/// its sightings of other robots (an EKF update, marginal over the other robot's pose
/// Gaussian), and the log-weight increment, each sighting's mixture likelihood.
#[inline(always)]
pub(super) fn sighting_update(
    ctx: &StepCtx<'_>,
    particle: usize,
    mean0: Pose2,
    pc0: Matrix3<f64>,
) -> (Pose2, Matrix3<f64>, f64) {
    let (mut mu, mut pc, mut dw) = (mean0, pc0, 0.0);
    for s in ctx.sightings {
        let Some((ll, next, next_pc)) = sighting_step(ctx, particle, s.robot, &s.z, &s.q, &mu, &pc)
        else {
            dw += s.clutter;
            continue;
        };
        dw += log_add_exp(ll, s.clutter);
        if next.is_finite() && next_pc.iter().all(|v| v.is_finite()) {
            mu = next;
            pc = next_pc;
        }
    }
    (mu, pc, dw)
}

/// One sighting `z` of robot `other` (its pose Gaussian in the particle of index `particle`) as an EKF update
/// of the pose Gaussian `N(mu, pc)` of the robot that saw it: the sighting's log-likelihood,
/// marginal over both Gaussians ([`sighting_marginal`]), and the updated mean and
/// covariance. `None` for a degenerate geometry.
#[inline(always)]
pub(super) fn sighting_step(
    ctx: &StepCtx<'_>,
    particle: usize,
    other: usize,
    z: &[f64; 2],
    qs: &Matrix2<f64>,
    mu: &Pose2,
    pc: &Matrix3<f64>,
) -> Option<(f64, Pose2, Matrix3<f64>)> {
    let (ll, hx, s_inv, nu) = sighting_marginal(ctx, particle, other, mu, pc, qs, z)?;
    let pht = mul_t(pc, &hx);
    let k = mul(&pht, &s_inv);
    let d = mul(&k, &nu);
    let next = Pose2::new(mu.x + d[0], mu.y + d[1], wrap_angle(mu.theta + d[2]));
    Some((ll, next, kalman_posterior_cov(pc, &k, &pht)))
}

/// A sample of the motion model (FastSLAM 1.0's proposal).
pub(super) fn sample_motion(
    ctx: &StepCtx<'_>,
    prev: &Pose2,
    inc: &Pose2,
    rng: &mut Stream,
) -> Pose2 {
    let e = Pose2::new(
        ctx.std[0] * rng.sample::<f64, _>(StandardNormal),
        ctx.std[1] * rng.sample::<f64, _>(StandardNormal),
        ctx.std[2] * rng.sample::<f64, _>(StandardNormal),
    );
    let noisy = Pose2::new(inc.x + e.x, inc.y + e.y, inc.theta + e.theta);
    prev.compose(&noisy)
}

/// A new robot's odometry scales in particle `i`: `[1, 1]` without calibration (nothing
/// drawn), else `1 + std · N(0, 1)` each, from the particle's calibration stream.
pub(super) fn draw_scales(cal: &OdometryCalibration, seed: u64, step: u64, i: usize) -> [f64; 2] {
    if !cal.enabled() {
        return [1.0; 2];
    }
    let mut rng = stream(seed, step, LANE_CALIBRATION + i as u64);
    let mut draw = |std: f64| 1.0 + std * rng.sample::<f64, _>(StandardNormal);
    [draw(cal.distance_std), draw(cal.rotation_std)]
}

/// The record's increment as a particle's odometry scales `s` of the robot see it, after
/// their random walk over the motion's duration (which draws from `rng` only when
/// calibration walks).
pub(super) fn scaled_increment(ctx: &StepCtx<'_>, s: &mut [f64; 2], rng: &mut Stream) -> Pose2 {
    if let Some([distance, rotation]) = ctx.scale_walk {
        s[0] += distance * rng.sample::<f64, _>(StandardNormal);
        s[1] += rotation * rng.sample::<f64, _>(StandardNormal);
    }
    scale_increment(&ctx.inc, *s)
}

/// The standard deviations (distance, rotation) of the odometry scales' random walk over a
/// motion of `dt` seconds, `None` where it does not move them (no walk, or no time).
pub(super) fn scale_walk(cal: &OdometryCalibration, dt: f64) -> Option<[f64; 2]> {
    (cal.walks() && dt > 0.0).then(|| {
        let sq = dt.sqrt();
        [
            cal.distance_walk_per_sqrt_s * sq,
            cal.rotation_walk_per_sqrt_s * sq,
        ]
    })
}
