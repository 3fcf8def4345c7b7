//! FastSLAM 2.0's proposal ([`super::proposal::propose`]) for [`LANES`] particles at once,
//! 2D range-bearing: the particles go through the record's observations in lockstep, each
//! number of the pose Gaussian's refinement (the prediction, `H_m`, `Hₓ`, `S` and its
//! inverse, the gain, the mean, the covariance) one vector of the four particles' values.
//!
//! Every lane performs the scalar proposal's operations in the same order (the products of
//! [`crate::linalg`] term by term, `atan` and the angles' wrap of [`crate::ekf_lanes`]), so a
//! lane's pose Gaussian has the scalar proposal's bits; what each particle does with an
//! observation (its landmark lookup, clutter terms, the mixture term, the outlier gate) stays
//! scalar, lane by lane, and a lane takes an observation's refinement only where the scalar
//! proposal would. A lane whose numbers leave the common path of the vector `atan` or wrap
//! is redone whole by the scalar proposal. The test `the_instruction_set_changes_no_bit`
//! (`tests/determinism.rs`) compares whole runs with the baseline (scalar) path.

use super::proposal::matched_landmark;
use super::{Action, StepCtx};
use crate::ekf_lanes::{F, LANES, M, atan2_lanes, wrap_lanes};
use crate::map::LandmarkMap;
use crate::pose::Pose2;
use crate::stats::MixtureLogSum;
use nalgebra::{Matrix2, Matrix3, Vector3};
use pulp::Simd;

/// A lane's proposal before the sightings and the draw ([`super::proposal::finish_proposal`]).
pub(super) enum LaneProposal {
    /// The refined pose Gaussian `N(mu, pc)`, the log-weight increment of the unmatched
    /// observations and the matched ones' mixture terms.
    Refined {
        mu: Vector3<f64>,
        pc: Matrix3<f64>,
        dw: f64,
        matched: MixtureLogSum,
    },
    /// Left to the scalar proposal; its actions may have changed part way: the caller
    /// associates the record again before it.
    Scalar,
}

/// Lanes as a mask.
#[inline(always)]
fn mask<S: Simd>(s: S, b: [bool; LANES]) -> M<S> {
    F::load(s, b.map(|v| if v { 1.0 } else { 0.0 })).gt(F::splat(s, 0.0))
}

/// The proposal of `LANES` particles (their maps, predicted pose Gaussians `mean0[l] =
/// (mean, covariance)`, actions and best likelihoods by observation) with the observations' noises
/// `q`, in vectors of `simd` (which must hold [`LANES`] f64 lanes). Actions change as in
/// the scalar proposal (a lane left to the scalar proposal needs its association again).
#[allow(clippy::too_many_arguments)]
#[inline(always)]
pub(super) fn propose_lanes<S: Simd>(
    simd: S,
    ctx: &StepCtx<'_>,
    q: &[Matrix2<f64>],
    maps: [&LandmarkMap; LANES],
    mean0: &[(Pose2, Matrix3<f64>); LANES],
    acts: &mut [&mut [Action]; LANES],
    best_ll: [&[f64]; LANES],
) -> [LaneProposal; LANES] {
    let outlier = ctx.cfg.association_params.outlier;
    let zero = F::splat(simd, 0.0);
    let mut mu = [zero; 3];
    let mut pc = [[zero; 3]; 3];
    {
        let mut m = [[0.0; LANES]; 3];
        let mut p = [[[0.0; LANES]; 3]; 3];
        for (l, (pose, cov)) in mean0.iter().enumerate() {
            m[0][l] = pose.x;
            m[1][l] = pose.y;
            m[2][l] = pose.theta;
            for i in 0..3 {
                for c in 0..3 {
                    p[i][c][l] = cov[(i, c)];
                }
            }
        }
        for i in 0..3 {
            mu[i] = F::load(simd, m[i]);
            for c in 0..3 {
                pc[i][c] = F::load(simd, p[i][c]);
            }
        }
    }
    let mut dw = [0.0; LANES];
    let mut matched = [MixtureLogSum::default(); LANES];
    let mut scalar = [false; LANES];
    for (j, o) in ctx.obs.iter().enumerate() {
        // What each lane does with the observation, and the landmarks of those it refines.
        let mut active = [false; LANES];
        let mut lm = [[0.0; 5]; LANES];
        for l in 0..LANES {
            if scalar[l] {
                continue;
            }
            if let Some(m) = matched_landmark(
                maps[l],
                &mut acts[l][j],
                best_ll[l][j],
                o.clutter,
                &mut dw[l],
            ) {
                let (g, c) = (&m.gaussian.mean, &m.gaussian.cov);
                lm[l] = [g[0], g[1], c[0], c[1], c[3]];
                active[l] = true;
            }
        }
        if !active.contains(&true) {
            continue;
        }
        let mut cols = [[0.0; LANES]; 5];
        for (l, v) in lm.iter().enumerate() {
            for (col, x) in cols.iter_mut().zip(v) {
                col[l] = *x;
            }
        }
        let (mx, my) = (F::load(simd, cols[0]), F::load(simd, cols[1]));
        let (c0, c1, c3) = (
            F::load(simd, cols[2]),
            F::load(simd, cols[3]),
            F::load(simd, cols[4]),
        );
        // `range_bearing_predict` at the pose `mu`.
        let dx = mx - mu[0];
        let dy = my - mu[1];
        let qq = dx * dx + dy * dy;
        let r = qq.sqrt();
        let (b, atan_ok) = atan2_lanes(dy, dx);
        let (zb, zb_ok) = wrap_lanes(b - mu[2]);
        let hm = [[dx / r, dy / r], [-dy / qq, dx / qq]];
        let hx = [
            [-dx / r, -dy / r, zero],
            [dy / qq, -dx / qq, F::splat(simd, -1.0)],
        ];
        // `sandwich(H_m, Σ) + Q_j`, the left product first.
        let cov = [[c0, c1], [c1, c3]];
        let qo = &q[j];
        let mut a = [[zero; 2]; 2];
        for i in 0..2 {
            for c in 0..2 {
                a[i][c] = hm[i][0] * cov[0][c] + hm[i][1] * cov[1][c];
            }
        }
        let mut qj = [[zero; 2]; 2];
        for i in 0..2 {
            for c in 0..2 {
                qj[i][c] = (a[i][0] * hm[c][0] + a[i][1] * hm[c][1]) + qo[(i, c)];
            }
        }
        // `mul_t(pc, Hₓ)` (3x2) and `mul(Hₓ, pht) + (sandwich + Q_j)`.
        let mut pht = [[zero; 2]; 3];
        for i in 0..3 {
            for c in 0..2 {
                pht[i][c] = (pc[i][0] * hx[c][0] + pc[i][1] * hx[c][1]) + pc[i][2] * hx[c][2];
            }
        }
        let mut s = [[zero; 2]; 2];
        for i in 0..2 {
            for c in 0..2 {
                s[i][c] = ((hx[i][0] * pht[0][c] + hx[i][1] * pht[1][c]) + hx[i][2] * pht[2][c])
                    + qj[i][c];
            }
        }
        let det = s[0][0] * s[1][1] - s[0][1] * s[1][0];
        let inv_ok = det.gt(zero).and(det.finite()).and(s[0][0].gt(zero));
        let inv = [
            [s[1][1] / det, -s[0][1] / det],
            [-s[1][0] / det, s[0][0] / det],
        ];
        let z0 = F::splat(simd, o.z[0]);
        let z1 = F::splat(simd, o.z[1]);
        let nu0 = z0 - r;
        let (nu1, nu_ok) = wrap_lanes(z1 - zb);
        let m2 =
            nu0 * (inv[0][0] * nu0 + inv[0][1] * nu1) + nu1 * (inv[1][0] * nu0 + inv[1][1] * nu1);
        let mut k = [[zero; 2]; 3];
        let mut next = [zero; 3];
        for i in 0..3 {
            for c in 0..2 {
                k[i][c] = pht[i][0] * inv[0][c] + pht[i][1] * inv[1][c];
            }
            next[i] = mu[i] + (k[i][0] * nu0 + k[i][1] * nu1);
        }
        let (theta, theta_ok) = wrap_lanes(next[2]);
        // What the scalar proposal does with each lane's numbers.
        let predicted = qq.ge(qq.c(1e-12)).get();
        let (atan_ok, zb_ok, inv_ok, nu_ok, theta_ok) = (
            atan_ok.get(),
            zb_ok.get(),
            inv_ok.get(),
            nu_ok.get(),
            theta_ok.get(),
        );
        let (m2v, detv) = (m2.get(), det.get());
        let mut refine = [false; LANES];
        for l in 0..LANES {
            if !active[l] {
                continue;
            }
            if !predicted[l] {
                acts[l][j] = Action::Outlier;
                dw[l] += o.clutter;
            } else if !(atan_ok[l] && zb_ok[l]) {
                scalar[l] = true;
            } else if !inv_ok[l] {
                acts[l][j] = Action::Outlier;
                dw[l] += o.clutter;
            } else if !nu_ok[l] {
                scalar[l] = true;
            } else {
                matched[l].add_gaussian(m2v[l], detv[l], 2, o.clutter);
                if outlier.is_some_and(|b| m2v[l].is_nan() || m2v[l] > b) {
                    acts[l][j] = Action::Outlier;
                } else if theta_ok[l] {
                    refine[l] = true;
                } else {
                    scalar[l] = true;
                }
            }
        }
        if !refine.contains(&true) {
            continue;
        }
        let take = mask(simd, refine);
        // `kalman_posterior_cov(pc, k, pht)`: the upper triangle, mirrored.
        let mut out = pc;
        for i in 0..3 {
            for c in i..3 {
                let v = pc[i][c] - (k[i][0] * pht[c][0] + k[i][1] * pht[c][1]);
                out[i][c] = v;
                out[c][i] = v;
            }
        }
        for i in 0..3 {
            for c in 0..3 {
                pc[i][c] = take.pick(out[i][c], pc[i][c]);
            }
        }
        mu = [
            take.pick(next[0], mu[0]),
            take.pick(next[1], mu[1]),
            take.pick(theta, mu[2]),
        ];
    }
    let muv = [mu[0].get(), mu[1].get(), mu[2].get()];
    let mut pcv = [[[0.0; LANES]; 3]; 3];
    for i in 0..3 {
        for c in 0..3 {
            pcv[i][c] = pc[i][c].get();
        }
    }
    std::array::from_fn(|l| {
        if scalar[l] {
            return LaneProposal::Scalar;
        }
        LaneProposal::Refined {
            mu: Vector3::new(muv[0][l], muv[1][l], muv[2][l]),
            pc: Matrix3::from_fn(|i, c| pcv[i][c][l]),
            dw: dw[l],
            matched: matched[l],
        }
    })
}
