//! Association of a record's observations with one particle's map (unknown ids: greedy by
//! likelihood with mutual exclusion, through the map's spatial index).

use super::{Action, StepCtx};
use crate::config::{Association, FilterConfig};
use crate::linalg::{mul, sandwich};
use crate::map::{INDEX_WIDE_TRACE, LandmarkMap};
use crate::math;
use crate::pose::Pose2;
use crate::sensor::{LandmarkKind, MeasurementModel, range_bearing_inverse};
use crate::stats::gaussian_log_density;
use crate::updater::LandmarkGaussian;
use nalgebra::{Matrix3, SMatrix};

/// A radius a little beyond `√d2`, so that a spatial query of it surely holds every point
/// whose squared distance is at most `d2` despite the rounding of the root and of the
/// query's cell bounds.
#[inline]
pub(super) fn covering_radius(d2: f64) -> f64 {
    d2.sqrt() * (1.0 + 1e-9) + 1e-9
}

/// The association pre-check compares the squared world distance between an observation's
/// point and a landmark with `new_landmark` times this slack times the trace of a world-frame
/// bound of the innovation covariance: a landmark that fails it has a squared Mahalanobis
/// distance beyond `new_landmark` (the world-frame bound linearises the bearing noise, hence
/// the slack), so skipping it changes no association and the weight by less than the
/// Gaussian density at that distance. A pure speed-up.
pub(super) const PRECHECK_SLACK: f64 = 1.5;

/// The observation's point in the world and a world-frame variance bound of the sensor noise,
/// for the association pre-check.
pub(super) fn world_point<const D: usize>(
    cfg: &FilterConfig,
    q: &SMatrix<f64, D, D>,
    pose: &Pose2,
    z: &[f64; 3],
) -> (f64, f64, f64) {
    match cfg.landmark_kind {
        LandmarkKind::RangeBearing2d => {
            let (x, y) = range_bearing_inverse(pose, z[0], z[1]);
            let n = &cfg.sensor_noise;
            (x, y, q[(0, 0)] + (z[0] * n.bearing).powi(2))
        }
        LandmarkKind::Point3d => {
            let w = crate::sensor::point3_inverse(pose, z);
            (w[0], w[1], q.trace())
        }
    }
}

/// Squared Mahalanobis distance and Gaussian log-likelihood of observation `z` of a landmark
/// `g` from `pose` with pose covariance `p`, in measurement model `M` with noise `q`; `None`
/// for a degenerate geometry.
#[inline]
pub(super) fn match_ll<const D: usize, M: MeasurementModel<D>>(
    q: &SMatrix<f64, D, D>,
    g: &LandmarkGaussian,
    pose: &Pose2,
    p: &Matrix3<f64>,
    z: &[f64; 3],
) -> Option<(f64, f64)> {
    let (zhat, hm, hx) = M::predict(pose, &g.mean)?;
    let s = sandwich(&hm, &M::cov(g)) + q + sandwich(&hx, p);
    let (s_inv, det) = M::inverse_det(&s)?;
    let nu = M::innovation(z, &zhat);
    let m2 = nu.dot(&mul(&s_inv, &nu));
    let ll = gaussian_log_density(m2, math::ln(det), D);
    (m2.is_finite() && ll.is_finite()).then_some((m2, ll))
}

/// The association of a whole record in one particle, with mutual exclusion: each landmark
/// explains at most one observation of the record and each observation at most one
/// landmark. Writes each observation's action and the Gaussian log-likelihood of the
/// landmark that explains it best (its match, or the best landmark left free by the others;
/// `-inf` if none) into `acts` and `best_ll`. `p` is the pose covariance (zero in 1.0),
/// `q[j]` observation `j`'s measurement noise.
///
/// Unknown association is greedy by likelihood: the pairs within the gate are taken best
/// first. An observation left without a landmark starts one if it lies beyond `new_landmark`
/// from every landmark of the map and from the landmarks started earlier in the same record;
/// otherwise it is ambiguous (`Ignore`).
#[allow(clippy::too_many_arguments)]
#[inline(always)]
pub(super) fn associate_record<const D: usize, M: MeasurementModel<D>>(
    ctx: &StepCtx<'_>,
    q: &[SMatrix<f64, D, D>],
    map: &LandmarkMap,
    pose: &Pose2,
    p: &Matrix3<f64>,
    acts: &mut [Action],
    best_ll: &mut [f64],
) {
    let cfg = ctx.cfg;
    best_ll.fill(f64::NEG_INFINITY);
    if cfg.association == Association::Known {
        // Every id is an `Update` of its slot, not looked up here: the proposal (2.0) and the
        // landmark update (1.0) read the landmark anyway, and take an id their map does not
        // hold yet as new.
        for (a, o) in acts.iter_mut().zip(ctx.obs) {
            *a = o.slot.map_or(Action::Ignore, Action::Update);
        }
        return;
    }
    let pose_term = p[(0, 0)] + p[(1, 1)];
    // Every computed (observation, slot, m², ll); the gated ones are the candidates.
    let mut pairs: Vec<(usize, usize, f64, f64)> = Vec::new();
    let mut nearest_m2 = vec![f64::INFINITY; ctx.obs.len()];
    // Squared ground-plane distance from each observation's point to the nearest landmark.
    let mut nearest_d2 = vec![f64::INFINITY; ctx.obs.len()];
    let mut points = Vec::with_capacity(ctx.obs.len());
    let sep2 = cfg.association_params.min_separation.powi(2);
    for (j, o) in ctx.obs.iter().enumerate() {
        let q = &q[j];
        let (wx, wy, q_world) = world_point(cfg, q, pose, &o.z);
        points.push((wx, wy));
        let pose_term = pose_term + p[(2, 2)] * (o.z[0] * o.z[0] + o.z[1] * o.z[1]);
        // Every landmark that can pass the pre-check below or lie within the minimum
        // separation is within this distance, unless its variance exceeds the index's
        // bound (those the index always visits).
        let reach2 = (ctx.new_landmark
            * ((INDEX_WIDE_TRACE + q_world + pose_term) * PRECHECK_SLACK))
            .max(sep2);
        map.for_each_near(wx, wy, covering_radius(reach2), |slot, lm| {
            let g = &lm.gaussian;
            let d2 = (g.mean[0] - wx).powi(2) + (g.mean[1] - wy).powi(2);
            nearest_d2[j] = nearest_d2[j].min(d2);
            let bound = (g.cov[0] + g.cov[3] + q_world + pose_term) * PRECHECK_SLACK;
            if d2 > ctx.new_landmark * bound {
                return;
            }
            if let Some((m2, ll)) = match_ll::<D, M>(q, g, pose, p, &o.z) {
                nearest_m2[j] = nearest_m2[j].min(m2);
                pairs.push((j, slot, m2, ll));
            }
        });
    }
    let mut cands: Vec<&(usize, usize, f64, f64)> =
        pairs.iter().filter(|c| c.2 < ctx.gate).collect();
    cands.sort_by(|a, b| b.3.total_cmp(&a.3).then(a.0.cmp(&b.0)).then(a.1.cmp(&b.1)));
    let mut taken: Vec<usize> = Vec::new();
    for a in acts.iter_mut() {
        *a = Action::Ignore;
    }
    let mut assigned = vec![false; ctx.obs.len()];
    for &&(j, slot, _, ll) in &cands {
        if assigned[j] || taken.contains(&slot) {
            continue;
        }
        assigned[j] = true;
        taken.push(slot);
        acts[j] = Action::Update(slot);
        best_ll[j] = ll;
    }
    let mut fresh: Vec<LandmarkGaussian> = Vec::new();
    for (j, o) in ctx.obs.iter().enumerate() {
        if assigned[j] {
            continue;
        }
        best_ll[j] = pairs
            .iter()
            .filter(|c| c.0 == j && !taken.contains(&c.1))
            .map(|c| c.3)
            .fold(f64::NEG_INFINITY, f64::max);
        if nearest_m2[j] <= ctx.new_landmark || nearest_d2[j] < sep2 {
            continue;
        }
        // Not near any landmark of the map: new, unless a landmark started by an earlier
        // observation of this record explains it or lies within the minimum separation.
        let (wx, wy) = points[j];
        let near_fresh = fresh.iter().any(|g| {
            (g.mean[0] - wx).powi(2) + (g.mean[1] - wy).powi(2) < sep2
                || match_ll::<D, M>(&q[j], g, pose, p, &o.z)
                    .is_none_or(|(m2, _)| m2 <= ctx.new_landmark)
        });
        if !near_fresh {
            fresh.push(ctx.updater.initialize(pose, &o.z));
            acts[j] = Action::New(None);
        }
    }
}
