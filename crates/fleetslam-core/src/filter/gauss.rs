//! Pose-Gaussian math shared by the filter's steps: sampling and the symmetric-matrix packing
//! of pose covariances. The measurement models' math lives in
//! [`crate::sensor::MeasurementModel`].

use crate::linalg::mul;
use crate::pose::{Pose2, wrap_angle};
use crate::rng::StandardNormal;
use crate::rng::Stream;
use nalgebra::{Matrix3, Vector3};
use rand::Rng;

#[inline]
pub(super) fn normal3(rng: &mut Stream) -> Vector3<f64> {
    Vector3::new(
        rng.sample(StandardNormal),
        rng.sample(StandardNormal),
        rng.sample(StandardNormal),
    )
}

/// Lower Cholesky factor of a symmetric positive semi-definite matrix (with a tiny jitter
/// for semi-definite ones).
pub(super) fn cholesky_psd(m: &Matrix3<f64>) -> Option<Matrix3<f64>> {
    if let Some(l) = cholesky3(m) {
        return Some(l);
    }
    let jitter = 1e-12 * (1.0 + m.trace().abs());
    cholesky3(&(m + Matrix3::identity() * jitter))
}

/// The lower Cholesky factor of a 3x3 matrix from its lower triangle, or `None` where a
/// pivot is zero, negative or NaN: nalgebra's `Matrix3::cholesky().map(|c| c.l())` unrolled,
/// the same operations in the same order (column by column, each column's updates by the
/// earlier columns in turn, then its division by the pivot), hence the same bits, without
/// the generic loops and views (the proposal factors one per particle and observation).
#[inline]
pub(super) fn cholesky3(m: &Matrix3<f64>) -> Option<Matrix3<f64>> {
    // nalgebra's pivot: a non-zero value whose square root exists (not NaN, not negative,
    // not ±0).
    let pivot = |v: f64| (v > 0.0).then(|| v.sqrt());
    let d0 = pivot(m[(0, 0)])?;
    let l10 = m[(1, 0)] / d0;
    let l20 = m[(2, 0)] / d0;
    let d1 = pivot(-l10 * l10 + m[(1, 1)])?;
    let l21 = (-l10 * l20 + m[(2, 1)]) / d1;
    let d2 = pivot(-l21 * l21 + (-l20 * l20 + m[(2, 2)]))?;
    Some(Matrix3::new(d0, 0.0, 0.0, l10, d1, 0.0, l20, l21, d2))
}

/// A symmetric 3x3 matrix from its upper triangle (xx, xy, xθ, yy, yθ, θθ).
#[inline]
pub(super) fn sym3(c: &[f64; 6]) -> Matrix3<f64> {
    Matrix3::new(c[0], c[1], c[2], c[1], c[3], c[4], c[2], c[4], c[5])
}

/// The upper triangle of a 3x3 matrix, symmetrised.
#[inline]
pub(super) fn upper3(m: &Matrix3<f64>) -> [f64; 6] {
    let s = |i: usize, j: usize| 0.5 * (m[(i, j)] + m[(j, i)]);
    [m[(0, 0)], s(0, 1), s(0, 2), m[(1, 1)], s(1, 2), m[(2, 2)]]
}

/// Jacobian of `prev ⊕ inc` with respect to `prev`, given `math::sin_cos(prev.theta)`.
#[inline]
pub(super) fn compose_jacobian((s, c): (f64, f64), inc: &Pose2) -> Matrix3<f64> {
    Matrix3::new(
        1.0,
        0.0,
        -s * inc.x - c * inc.y,
        0.0,
        1.0,
        c * inc.x - s * inc.y,
        0.0,
        0.0,
        1.0,
    )
}

/// `F P Fᵀ` for `F = compose_jacobian(sc, inc)` (the identity but for its last column's
/// `a = F[0,2]`, `b = F[1,2]`) and the symmetric `P` of upper triangle `p`: the deferred pose
/// Gaussian's covariance carried through a motion, once per particle and record. Written
/// out: [`crate::linalg::sandwich`]'s products in its order without those by `F`'s exact
/// zeros and ones, so the same value; only the sign of an entry that is zero may differ.
#[inline]
pub(super) fn compose_sandwich(sc: (f64, f64), inc: &Pose2, p: &[f64; 6]) -> Matrix3<f64> {
    let f = compose_jacobian(sc, inc);
    let (a, b) = (f[(0, 2)], f[(1, 2)]);
    let m = sym3(p);
    // F·P: rows 0 and 1 gain a and b times row 2.
    let g = Matrix3::from_fn(|i, j| match i {
        0 => m[(0, j)] + a * m[(2, j)],
        1 => m[(1, j)] + b * m[(2, j)],
        _ => m[(2, j)],
    });
    // (F·P)·Fᵀ: columns 0 and 1 gain a and b times column 2.
    Matrix3::from_fn(|i, j| match j {
        0 => g[(i, 0)] + g[(i, 2)] * a,
        1 => g[(i, 1)] + g[(i, 2)] * b,
        _ => g[(i, 2)],
    })
}

/// A sample of `N(mean, cov)` (the mean itself when `cov` has no Cholesky factor, which
/// only a covariance with a non-finite entry lacks after the jitter).
pub(super) fn sample_gaussian(mean: &Pose2, cov: &Matrix3<f64>, rng: &mut Stream) -> Pose2 {
    match cholesky_psd(cov) {
        Some(l) => {
            let e = mul(&l, &normal3(rng));
            Pose2::new(mean.x + e[0], mean.y + e[1], wrap_angle(mean.theta + e[2]))
        }
        None => *mean,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::linalg::sandwich;
    use crate::linalg::testing::{entry, same_but_zero_sign};
    use crate::math;
    use crate::rng::stream;
    use proptest::prelude::*;
    use rand::Rng;

    proptest! {
        /// The written-out `F P Fᵀ` is the generic product's value, entry for entry.
        #[test]
        fn compose_sandwich_is_the_full_product(
            theta in prop_oneof![Just(0.0), -4.0..4.0f64], inc in proptest::array::uniform3(entry()),
            p in proptest::array::uniform6(entry()),
        ) {
            let sc = math::sin_cos(theta);
            let inc = Pose2::new(inc[0], inc[1], inc[2]);
            let full = sandwich(&compose_jacobian(sc, &inc), &sym3(&p));
            let got = compose_sandwich(sc, &inc, &p);
            for (x, y) in full.iter().zip(got.iter()) {
                prop_assert!(same_but_zero_sign(*x, *y), "{full} against {got}");
            }
        }
    }

    /// The unrolled factor is nalgebra's bit for bit, and fails where nalgebra's fails:
    /// covariances (`A Aᵀ`, some nearly singular), indefinite symmetric matrices, and ones
    /// with a zero or NaN pivot.
    #[test]
    fn cholesky3_is_nalgebras_factor_bit_for_bit() {
        let mut rng = stream(3, 1, 4);
        let mut draw =
            |scale: f64| Matrix3::from_fn(|_, _| scale * rng.sample::<f64, _>(StandardNormal));
        let mut cases = vec![
            Matrix3::zeros(),
            Matrix3::identity(),
            Matrix3::from_diagonal(&Vector3::new(1.0, 0.0, 1.0)),
            Matrix3::from_diagonal(&Vector3::new(1.0, 1.0, f64::NAN)),
            Matrix3::from_diagonal(&Vector3::new(-1.0, 1.0, 1.0)),
        ];
        for k in 0..3000 {
            let a = draw(10f64.powi(k % 7 - 3));
            cases.push(a * a.transpose());
            // Rank 2: semi-definite, failing or passing on rounding.
            let mut b = a;
            b.set_column(2, &(a.column(0) + a.column(1)));
            cases.push(b * b.transpose());
            cases.push(a + a.transpose());
        }
        let (mut ok, mut failed) = (0, 0);
        for m in &cases {
            let want = m.cholesky().map(|c| c.l());
            let got = cholesky3(m);
            match (want, got) {
                (Some(w), Some(g)) => {
                    ok += 1;
                    for (x, y) in w.iter().zip(g.iter()) {
                        assert_eq!(x.to_bits(), y.to_bits(), "{m}: {w} against {g}");
                    }
                }
                (None, None) => failed += 1,
                (w, g) => panic!("{m}: nalgebra {w:?}, unrolled {g:?}"),
            }
        }
        // Both branches are exercised.
        assert!(
            ok > 3000 && failed > 1000,
            "{ok} factored, {failed} refused"
        );
    }
}
