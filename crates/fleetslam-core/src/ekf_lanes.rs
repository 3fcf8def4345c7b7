//! The 2D range-bearing EKF update ([`crate::ekf`]) of [`LANES`] inputs at once, each
//! number of the update one SIMD vector of lanes: where the batch is dispatched to AVX2,
//! each vector instruction computes a step of four updates instead of one.
//!
//! Every lane performs exactly the scalar update's operations in the same order (Rust
//! never fuses a multiply and an add, and vector division and square root round as the
//! scalar ones do), so a lane's result has the scalar update's bits: the test
//! `lanes_are_the_scalar_update_bit_for_bit` checks it on arbitrary inputs. `atan` is
//! FreeBSD msun's algorithm as the `libm` crate implements it (the scalar
//! [`crate::sensor::bearing_atan2`] calls it): its five argument reductions become one
//! division whose numerator and denominator take per-lane constants that reproduce each
//! reduction's operations exactly (`1·t − 0`, `0·t − 1`, `1 + 0·t`, ...). A lane whose
//! numbers leave the common path (a landmark on the robot, a bearing ratio beyond 2^±60,
//! an angle at least 4π away from the wrapped interval) is left to the scalar update.

use crate::math;
use crate::stats::gaussian_log_density;
use crate::updater::{LandmarkGaussian, UpdateInput, UpdateNeeds, UpdateOutput};
use nalgebra::Matrix2;
use pulp::Simd;
use std::f64::consts::PI;
use std::ops::{Add, Div, Mul, Neg, Sub};

/// Updates computed together: the f64 lanes of an AVX2 vector. A batch dispatched to an
/// instruction set with another lane count takes the scalar update.
pub(crate) const LANES: usize = 4;

/// One number of [`LANES`] updates.
#[derive(Clone, Copy)]
pub(crate) struct F<S: Simd>(S, S::f64s);

/// Which lanes hold a condition.
#[derive(Clone, Copy)]
pub(crate) struct M<S: Simd>(S, S::m64s);

impl<S: Simd> F<S> {
    #[inline(always)]
    pub(crate) fn load(s: S, v: [f64; LANES]) -> Self {
        F(s, pulp::bytemuck::cast(v))
    }
    #[inline(always)]
    pub(crate) fn splat(s: S, v: f64) -> Self {
        F(s, s.splat_f64s(v))
    }
    #[inline(always)]
    pub(crate) fn get(self) -> [f64; LANES] {
        pulp::bytemuck::cast(self.1)
    }
    #[inline(always)]
    pub(crate) fn c(self, v: f64) -> Self {
        Self::splat(self.0, v)
    }
    #[inline(always)]
    pub(crate) fn sqrt(self) -> Self {
        F(self.0, self.0.sqrt_f64s(self.1))
    }
    /// `|v|` for `v` not `-0` (which stays `-0`), by a comparison and a subtraction: pulp's
    /// `abs` and `neg` go through mask operations that the compiler does not always inline
    /// into the dispatched code (then a call each).
    #[inline(always)]
    pub(crate) fn abs_nonzero(self) -> Self {
        let zero = self.c(0.0);
        self.lt(zero).pick(zero - self, self)
    }
    /// `lo < v < hi`.
    #[inline(always)]
    pub(crate) fn within(self, lo: f64, hi: f64) -> M<S> {
        self.gt(self.c(lo)).and(self.lt(self.c(hi)))
    }
    #[inline(always)]
    pub(crate) fn lt(self, o: Self) -> M<S> {
        M(self.0, self.0.less_than_f64s(self.1, o.1))
    }
    #[inline(always)]
    pub(crate) fn le(self, o: Self) -> M<S> {
        M(self.0, self.0.less_than_or_equal_f64s(self.1, o.1))
    }
    #[inline(always)]
    pub(crate) fn gt(self, o: Self) -> M<S> {
        M(self.0, self.0.greater_than_f64s(self.1, o.1))
    }
    #[inline(always)]
    pub(crate) fn ge(self, o: Self) -> M<S> {
        M(self.0, self.0.greater_than_or_equal_f64s(self.1, o.1))
    }
    /// Normal and finite.
    #[inline(always)]
    pub(crate) fn normal(self) -> M<S> {
        let (lo, hi) = (self.c(f64::MIN_POSITIVE), self.c(f64::MAX));
        let positive = self.ge(lo).and(self.le(hi));
        let negative = self.le(-lo).and(self.ge(-hi));
        positive.or(negative)
    }
    /// Finite: `-f64::MAX <= v <= f64::MAX` (false for NaN).
    #[inline(always)]
    pub(crate) fn finite(self) -> M<S> {
        self.le(self.c(f64::MAX)).and(self.ge(self.c(-f64::MAX)))
    }
}

impl<S: Simd> M<S> {
    /// `if self { t } else { f }`, lane by lane.
    #[inline(always)]
    pub(crate) fn pick(self, t: F<S>, f: F<S>) -> F<S> {
        F(self.0, self.0.select_f64s(self.1, t.1, f.1))
    }
    #[inline(always)]
    pub(crate) fn and(self, o: Self) -> Self {
        M(self.0, self.0.and_m64s(self.1, o.1))
    }
    #[inline(always)]
    pub(crate) fn or(self, o: Self) -> Self {
        M(self.0, self.0.or_m64s(self.1, o.1))
    }
    #[inline(always)]
    pub(crate) fn get(self) -> [bool; LANES] {
        let v: [u64; LANES] = pulp::bytemuck::cast(self.1);
        v.map(|b| b != 0)
    }
}

macro_rules! binop {
    ($tr:ident, $f:ident, $op:ident) => {
        impl<S: Simd> $tr for F<S> {
            type Output = Self;
            #[inline(always)]
            fn $f(self, o: Self) -> Self {
                F(self.0, self.0.$op(self.1, o.1))
            }
        }
        impl<S: Simd> $tr<f64> for F<S> {
            type Output = Self;
            #[inline(always)]
            fn $f(self, o: f64) -> Self {
                F(self.0, self.0.$op(self.1, self.0.splat_f64s(o)))
            }
        }
        impl<S: Simd> $tr<F<S>> for f64 {
            type Output = F<S>;
            #[inline(always)]
            fn $f(self, o: F<S>) -> F<S> {
                F(o.0, o.0.$op(o.0.splat_f64s(self), o.1))
            }
        }
    };
}
binop!(Add, add, add_f64s);
binop!(Sub, sub, sub_f64s);
binop!(Mul, mul, mul_f64s);
binop!(Div, div, div_f64s);

impl<S: Simd> Neg for F<S> {
    type Output = Self;
    /// The sign flipped, as the scalar `-v`: `v · (−1)` is exact for every `v` (zeros
    /// included), and a plain product is inlined where pulp's `neg` may not be.
    #[inline(always)]
    fn neg(self) -> Self {
        self * -1.0
    }
}

/// `libm::atan`'s polynomial coefficients (msun `s_atan.c`), by their bits.
const AT: [f64; 11] = [
    f64::from_bits(0x3FD5_5555_5555_550D),
    f64::from_bits(0xBFC9_9999_9998_EBC4),
    f64::from_bits(0x3FC2_4924_9200_83FF),
    f64::from_bits(0xBFBC_71C6_FE23_1671),
    f64::from_bits(0x3FB7_45CD_C54C_206E),
    f64::from_bits(0xBFB3_B0F2_AF74_9A6D),
    f64::from_bits(0x3FB1_0D66_A0D0_3D51),
    f64::from_bits(0xBFAD_DE2D_52DE_FD9A),
    f64::from_bits(0x3FA9_7B4B_2476_0DEB),
    f64::from_bits(0xBFA2_B444_2C6A_6C2F),
    f64::from_bits(0x3F90_AD3A_E322_DA11),
];

/// `atan(0.5)`, `atan(1)`, `atan(1.5)`, `atan(∞)`: high and low parts (msun `s_atan.c`).
const ATAN_HI: [f64; 4] = [
    f64::from_bits(0x3FDD_AC67_0561_BB4F),
    f64::from_bits(0x3FE9_21FB_5444_2D18),
    f64::from_bits(0x3FEF_730B_D281_F69B),
    f64::from_bits(0x3FF9_21FB_5444_2D18),
];
const ATAN_LO: [f64; 4] = [
    f64::from_bits(0x3C7A_2B7F_222F_65E2),
    f64::from_bits(0x3C81_A626_3314_5C07),
    f64::from_bits(0x3C70_0788_7AF0_CBBD),
    f64::from_bits(0x3C91_A626_3314_5C07),
];

/// msun's interval bounds on the high word of `|x|` (`0x3e400000`, `0x3fdc0000`,
/// `0x3fe60000`, `0x3ff30000`, `0x40038000`) as numbers: for a non-negative `a`, `high(a) <
/// h` exactly when `a < f64::from_bits(h << 32)`.
const TINY: f64 = f64::from_bits(0x3e40_0000 << 32);
const BOUNDS: [f64; 4] = [
    f64::from_bits(0x3fdc_0000 << 32),
    f64::from_bits(0x3fe6_0000 << 32),
    f64::from_bits(0x3ff3_0000 << 32),
    f64::from_bits(0x4003_8000 << 32),
];

/// `v[k]` in the lanes whose argument lies in interval `k`, `ins[k]` marking the lanes
/// below its upper bound (the last interval has none).
#[inline(always)]
fn by_interval<S: Simd>(a: F<S>, ins: [M<S>; 4], v: [f64; 5]) -> F<S> {
    let [below, i0, i1, i2] = ins;
    below.pick(
        a.c(v[0]),
        i0.pick(a.c(v[1]), i1.pick(a.c(v[2]), i2.pick(a.c(v[3]), a.c(v[4])))),
    )
}

/// `libm::atan(a)` for `0 <= a < 2^66`, lane by lane. The reduction of msun's
/// `[7/16, 11/16)`, `[11/16, 19/16)`, `[19/16, 39/16)` and `[39/16, ∞)` intervals is
/// `(n·a − m) / (n + m·a)` with `(n, m)` `(2, 1)`, `(1, 1)`, `(1, 1.5)` and `(0, 1)`, and
/// below `7/16` `(1, 0)` (no reduction): the same operations on the same numbers as each
/// interval's own formula (`(2a − 1) / (2 + a)`, `(a − 1) / (a + 1)`, `(a − 1.5) / (1 +
/// 1.5a)`, `−1 / a`, `a`).
#[inline(always)]
fn atan_lanes<S: Simd>(a: F<S>) -> F<S> {
    let below = a.lt(a.c(BOUNDS[0]));
    let i0 = a.lt(a.c(BOUNDS[1]));
    let i1 = a.lt(a.c(BOUNDS[2]));
    let i2 = a.lt(a.c(BOUNDS[3]));
    // Per interval: below, [7/16, 11/16), [11/16, 19/16), [19/16, 39/16), beyond.
    let ins = [below, i0, i1, i2];
    let n = by_interval(a, ins, [1.0, 2.0, 1.0, 1.0, 0.0]);
    let m = by_interval(a, ins, [0.0, 1.0, 1.0, 1.5, 1.0]);
    let hi = by_interval(
        a,
        ins,
        [0.0, ATAN_HI[0], ATAN_HI[1], ATAN_HI[2], ATAN_HI[3]],
    );
    let lo = by_interval(
        a,
        ins,
        [0.0, ATAN_LO[0], ATAN_LO[1], ATAN_LO[2], ATAN_LO[3]],
    );
    let t = (n * a - m) / (n + m * a);
    let z = t * t;
    let w = z * z;
    let s1 = z * (AT[0] + w * (AT[2] + w * (AT[4] + w * (AT[6] + w * (AT[8] + w * AT[10])))));
    let s2 = w * (AT[1] + w * (AT[3] + w * (AT[5] + w * (AT[7] + w * AT[9]))));
    let u = t * (s1 + s2);
    // msun returns arguments below 2^-27 as they are.
    a.lt(a.c(TINY))
        .pick(a, below.pick(t - u, hi - (u - lo - t)))
}

/// [`crate::sensor::bearing_atan2`]`(y, x)` lane by lane, and the lanes where that is
/// sure to take its common path (`x` and `y` normal and finite, `|y/x|` within 2^±60,
/// inside its bound of exponents at most 64 apart); the others' results are meaningless.
#[inline(always)]
pub(crate) fn atan2_lanes<S: Simd>(y: F<S>, x: F<S>) -> (F<S>, M<S>) {
    const PI_LO: f64 = 1.224_646_799_147_353_2e-16;
    const RATIO: f64 = f64::from_bits((1023 + 60) << 52); // 2^60
    // `|y/x|`; a zero ratio (its sign kept) fails the bound below.
    let a = (y / x).abs_nonzero();
    let ok = x
        .normal()
        .and(y.normal())
        .and(a.le(a.c(RATIO)))
        .and(a.ge(a.c(1.0 / RATIO)));
    let z = atan_lanes(a);
    let zero = x.c(0.0);
    let (x_neg, y_neg) = (x.lt(zero), y.lt(zero));
    let r = x_neg.pick(
        y_neg.pick((z - PI_LO) - PI, PI - (z - PI_LO)),
        y_neg.pick(-z, z),
    );
    (r, ok)
}

/// [`crate::pose::wrap_angle`] lane by lane for `|a| < 4π` (`a` not `±2π`), where
/// `a.rem_euclid(2π)`'s remainder is `a`, or `a ∓ 2π` (exact: Sterbenz), and which lanes
/// were in that domain.
#[inline(always)]
pub(crate) fn wrap_lanes<S: Simd>(a: F<S>) -> (F<S>, M<S>) {
    const TAU: f64 = 2.0 * PI;
    // |a| < 4π but not 2π: three open intervals.
    let below_tau = a.within(-TAU, TAU);
    let ok = below_tau
        .or(a.within(TAU, 2.0 * TAU))
        .or(a.within(-2.0 * TAU, -TAU));
    let inside = a.gt(a.c(-PI)).and(a.le(a.c(PI)));
    let r = below_tau.pick(a, a.gt(a.c(0.0)).pick(a - TAU, a + TAU));
    let r = r.lt(a.c(0.0)).pick(r + TAU, r);
    let r = r.gt(a.c(PI)).pick(r - TAU, r);
    (inside.pick(a, r), ok)
}

/// One number of each of the inputs, as a vector.
#[inline(always)]
fn gather<S: Simd>(simd: S, inp: &[UpdateInput; LANES], f: impl Fn(&UpdateInput) -> f64) -> F<S> {
    F::load(simd, [f(&inp[0]), f(&inp[1]), f(&inp[2]), f(&inp[3])])
}

/// The 2D range-bearing EKF update of `inputs` (exactly [`LANES`] of them) with noise `q`
/// plus, on the range's variance, `(range_per_m · range)²` (0 for a constant noise: the
/// same bits as without it) into `outputs`, in vectors of `simd` (which must hold
/// [`LANES`] f64 lanes). Returns the lanes left to the scalar update (their outputs are
/// not written).
#[inline(always)]
pub(crate) fn update_range_bearing<S: Simd>(
    simd: S,
    q: &Matrix2<f64>,
    range_per_m: f64,
    inputs: &[UpdateInput],
    outputs: &mut [UpdateOutput],
    needs: UpdateNeeds,
) -> [bool; LANES] {
    let inp: &[UpdateInput; LANES] = inputs.try_into().expect("a block of LANES inputs");
    let (mx, my) = (
        gather(simd, inp, |i| i.prior.mean[0]),
        gather(simd, inp, |i| i.prior.mean[1]),
    );
    let (c0, c1, c3) = (
        gather(simd, inp, |i| i.prior.cov[0]),
        gather(simd, inp, |i| i.prior.cov[1]),
        gather(simd, inp, |i| i.prior.cov[3]),
    );
    let (px, py, th) = (
        gather(simd, inp, |i| i.pose.x),
        gather(simd, inp, |i| i.pose.y),
        gather(simd, inp, |i| i.pose.theta),
    );
    let (z0, z1) = (gather(simd, inp, |i| i.z[0]), gather(simd, inp, |i| i.z[1]));
    // The prediction (`range_bearing_predict`).
    let dx = mx - px;
    let dy = my - py;
    let qq = dx * dx + dy * dy;
    let r = qq.sqrt();
    let (b, atan_ok) = atan2_lanes(dy, dx);
    let (zb, wrap_ok) = wrap_lanes(b - th);
    // H_m, row by row.
    let (h00, h01, h10, h11) = (dx / r, dy / r, -dy / qq, dx / qq);
    // Σ Hᵀ.
    let t00 = c0 * h00 + c1 * h01;
    let t01 = c0 * h10 + c1 * h11;
    let t10 = c1 * h00 + c3 * h01;
    let t11 = c1 * h10 + c3 * h11;
    // S = H Σ Hᵀ + Q, Q's range variance grown with the measured range.
    let g = range_per_m * z0;
    let q00 = q[(0, 0)] + g * g;
    let s00 = (h00 * t00 + h01 * t10) + q00;
    let s01 = (h00 * t01 + h01 * t11) + q[(0, 1)];
    let s10 = (h10 * t00 + h11 * t10) + q[(1, 0)];
    let s11 = (h10 * t01 + h11 * t11) + q[(1, 1)];
    let det = s00 * s11 - s01 * s10;
    let zero = det.c(0.0);
    let inv_ok = det.gt(zero).and(det.finite()).and(s00.gt(zero));
    let (i00, i01, i10, i11) = (s11 / det, -s01 / det, -s10 / det, s00 / det);
    // K = Σ Hᵀ S⁻¹.
    let k00 = t00 * i00 + t01 * i10;
    let k01 = t00 * i01 + t01 * i11;
    let k10 = t10 * i00 + t11 * i10;
    let k11 = t10 * i01 + t11 * i11;
    let nu0 = z0 - r;
    let (nu1, nu_ok) = wrap_lanes(z1 - zb);
    let m0 = mx + (k00 * nu0 + k01 * nu1);
    let m1 = my + (k10 * nu0 + k11 * nu1);
    // Σ' = Σ − K (Σ Hᵀ)ᵀ, its upper triangle (`kalman_posterior_cov`), the off-diagonal
    // symmetrised as `LandmarkGaussian::from_2d` does.
    let p00 = c0 - (k00 * t00 + k01 * t01);
    let p01 = c1 - (k00 * t10 + k01 * t11);
    let p11 = c3 - (k10 * t10 + k11 * t11);
    let pxy = 0.5 * (p01 + p01);
    let finite = m0
        .finite()
        .and(m1.finite())
        .and(p00.finite())
        .and(pxy.finite())
        .and(p11.finite());
    // νᵀ S⁻¹ ν.
    let m2 = nu0 * (i00 * nu0 + i01 * nu1) + nu1 * (i10 * nu0 + i11 * nu1);
    let common = qq.ge(qq.c(1e-12)).and(atan_ok).and(wrap_ok).and(nu_ok);
    let (common, inv_ok, finite) = (common.get(), inv_ok.get(), finite.get());
    let (m0, m1, p00, pxy, p11, m2, det) = (
        m0.get(),
        m1.get(),
        p00.get(),
        pxy.get(),
        p11.get(),
        m2.get(),
        det.get(),
    );
    for l in 0..LANES {
        if !common[l] {
            continue;
        }
        let prior = &inp[l].prior;
        outputs[l] = if !(inv_ok[l] && finite[l]) {
            UpdateOutput::rejected(prior)
        } else {
            let posterior = LandmarkGaussian {
                mean: [m0[l], m1[l], 0.0],
                cov: [p00[l], pxy[l], 0.0, p11[l], 0.0, 0.0],
            };
            if needs.likelihood() {
                let ll = gaussian_log_density(m2[l], math::ln(det[l]), 2);
                if ll.is_finite() {
                    UpdateOutput {
                        posterior,
                        log_likelihood: ll,
                        mahalanobis2: m2[l],
                    }
                } else {
                    UpdateOutput::rejected(prior)
                }
            } else {
                UpdateOutput {
                    posterior,
                    log_likelihood: f64::NAN,
                    mahalanobis2: f64::NAN,
                }
            }
        };
    }
    common.map(|c| !c)
}

/// The lanes need a 4-lane instruction set: on x86-64 AVX2 (the machines the suite runs on
/// have it; `tests/determinism.rs` asserts it too).
#[cfg(all(test, target_arch = "x86_64"))]
mod tests {
    use super::*;
    use crate::pose::Pose2;
    use pulp::x86::V3;

    fn v3() -> V3 {
        V3::try_new().expect("this machine has AVX2")
    }
    use crate::ekf::EkfUpdater;
    use crate::pose::wrap_angle;
    use crate::sensor::{RangeBearingModel, bearing_atan2};
    use proptest::prelude::*;

    /// One input: the robot at `(x, y, θ)`, a landmark at range `r` and bearing `b` from it
    /// with covariance `[[vx, c √(vx vy)], [.., vy]]`, read with errors `(er, eb)`.
    #[allow(clippy::too_many_arguments)]
    fn input(pose: [f64; 3], r: f64, b: f64, v: [f64; 3], e: [f64; 2]) -> UpdateInput {
        let (x, y, th) = (pose[0], pose[1], pose[2]);
        let [vx, vy, c] = v;
        UpdateInput {
            prior: LandmarkGaussian {
                mean: [x + r * math::cos(th + b), y + r * math::sin(th + b), 0.0],
                cov: [vx, c * (vx * vy).sqrt(), 0.0, vy, 0.0, 0.0],
            },
            pose: Pose2::new(x, y, th),
            z: [r + e[0], b + e[1], 0.0],
        }
    }

    fn same(a: &UpdateOutput, b: &UpdateOutput) -> bool {
        let bits = |o: &UpdateOutput| {
            let mut v: Vec<u64> = o.posterior.mean.iter().map(|x| x.to_bits()).collect();
            v.extend(o.posterior.cov.iter().map(|x| x.to_bits()));
            v.push(o.log_likelihood.to_bits());
            v.push(o.mahalanobis2.to_bits());
            v
        };
        bits(a) == bits(b)
    }

    fn an_input() -> impl Strategy<Value = UpdateInput> {
        (
            (-50.0..50.0f64, -50.0..50.0f64, -PI..PI),
            0.01..30.0f64,
            -PI..PI,
            (1e-6..4.0f64, 1e-6..4.0f64, -0.99..0.99f64),
            (-1.0..1.0f64, -0.5..0.5f64),
        )
            .prop_map(|((x, y, th), r, b, (vx, vy, c), (er, eb))| {
                input([x, y, th], r, b, [vx, vy, c], [er, eb])
            })
    }

    proptest! {
        /// Every lane of a block is the scalar update, bit for bit, with a constant noise
        /// and with one that grows with the range, asked for the likelihood or not; and on
        /// these common inputs no lane is left to the scalar update (which would make the
        /// comparison one of the scalar update with itself).
        #[test]
        fn lanes_are_the_scalar_update_bit_for_bit(
            inputs in prop::array::uniform4(an_input()),
            rpm in prop_oneof![Just(0.0), 0.0..0.1f64],
            likelihood: bool,
        ) {
            let needs = if likelihood {
                UpdateNeeds::PosteriorAndLikelihood
            } else {
                UpdateNeeds::Posterior
            };
            let q = Matrix2::new(0.3f64.powi(2), 0.0, 0.0, 0.04f64.powi(2));
            let mut out = [UpdateOutput::default(); LANES];
            let scalar = update_range_bearing(v3(), &q, rpm, &inputs, &mut out, needs);
            for l in 0..LANES {
                prop_assert!(!scalar[l], "lane {l} left to the scalar update: {:?}", inputs[l]);
                let mut ql = q;
                let g = rpm * inputs[l].z[0];
                ql[(0, 0)] += g * g;
                let want = EkfUpdater::update::<2, RangeBearingModel>(&ql, &inputs[l], needs);
                prop_assert!(same(&out[l], &want), "lane {l}: {:?} against {:?}", out[l], want);
            }
        }

        /// The lanes' `atan` is `libm::atan` on any non-negative number below 2^66.
        #[test]
        fn atan_lanes_is_libms_atan(bits in prop::array::uniform4(0u64..0x4410_0000_0000_0000)) {
            let a = bits.map(f64::from_bits);
            let got = atan_lanes(F::load(v3(), a)).get();
            for l in 0..LANES {
                prop_assert_eq!(got[l].to_bits(), libm::atan(a[l]).to_bits(), "atan({})", a[l]);
            }
        }

        /// `atan2` and the angle's wrap lane by lane are `bearing_atan2` and `wrap_angle`
        /// wherever they report their common path, which holds for every bearing of
        /// coordinates of magnitudes between 1e-15 and 1e3 and every angle within 4π.
        #[test]
        fn atan2_and_wrap_lanes_are_the_scalar_ones(
            y in prop::array::uniform4(-1e3..1e3f64),
            x in prop::array::uniform4(-1e3..1e3f64),
            angle in prop::array::uniform4(-12.5..12.5f64),
        ) {
            let (got, ok) = atan2_lanes(F::load(v3(), y), F::load(v3(), x));
            let (got, ok) = (got.get(), ok.get());
            let (wrapped, wrap_ok) = wrap_lanes(F::load(v3(), angle));
            let (wrapped, wrap_ok) = (wrapped.get(), wrap_ok.get());
            for l in 0..LANES {
                if y[l].abs() > 1e-15 && x[l].abs() > 1e-15 {
                    prop_assert!(ok[l]);
                }
                if ok[l] {
                    prop_assert_eq!(got[l].to_bits(), bearing_atan2(y[l], x[l]).to_bits());
                }
                prop_assert!(wrap_ok[l]);
                prop_assert_eq!(wrapped[l].to_bits(), wrap_angle(angle[l]).to_bits());
            }
        }
    }

    /// Each of msun's intervals and their bounds, and the special lanes: a landmark on the
    /// robot and a ratio beyond 2^64 go to the scalar update, whose rejection or result the
    /// batch then holds.
    #[test]
    fn interval_bounds_and_special_lanes() {
        let bounds: [f64; 9] = [
            0.0, 1e-300, 7.0e-9, 0.437_5, 0.687_5, 1.187_5, 2.437_5, 1e10, 3.0e19,
        ];
        for &v in &bounds {
            for a in [
                v,
                f64::from_bits(v.to_bits().saturating_sub(1)),
                f64::from_bits(v.to_bits() + 1),
            ] {
                assert_eq!(
                    atan_lanes(F::load(v3(), [a; LANES])).get()[0].to_bits(),
                    libm::atan(a).to_bits(),
                    "{a}"
                );
            }
        }
        let q = Matrix2::new(0.09, 0.0, 0.0, 0.0016);
        let good = input([1.0, 2.0, 0.3], 4.0, 0.5, [0.1, 0.2, 0.3], [0.05, -0.01]);
        let mut on_robot = good;
        on_robot.prior.mean = [1.0, 2.0, 0.0];
        let mut far_ratio = good;
        far_ratio.prior.mean = [1.0 + 1e-25, 2.0 + 5.0, 0.0];
        let inputs = [good, on_robot, far_ratio, good];
        let mut out = [UpdateOutput::default(); LANES];
        let scalar = update_range_bearing(v3(), &q, 0.0, &inputs, &mut out, UpdateNeeds::Posterior);
        assert_eq!(scalar, [false, true, true, false]);
        let ekf = EkfUpdater::new(
            crate::sensor::LandmarkKind::RangeBearing2d,
            &crate::sensor::SensorNoise {
                range: 0.3,
                bearing: 0.04,
                xyz: [0.1; 3],
                range_per_m: 0.0,
            },
        );
        use crate::updater::LandmarkUpdater;
        let mut batch = [UpdateOutput::default(); LANES + 1];
        let mut five = inputs.to_vec();
        five.push(good);
        ekf.update_batch(UpdateNeeds::PosteriorAndLikelihood, &five, &mut batch);
        for (i, o) in five.iter().zip(&batch) {
            let want = EkfUpdater::update::<2, RangeBearingModel>(
                &q,
                i,
                UpdateNeeds::PosteriorAndLikelihood,
            );
            assert!(same(o, &want), "{o:?} against {want:?}");
        }
        assert_eq!(
            batch[1].log_likelihood,
            f64::NEG_INFINITY,
            "a landmark on the robot"
        );
        assert!(batch[2].log_likelihood.is_finite());
    }
}
