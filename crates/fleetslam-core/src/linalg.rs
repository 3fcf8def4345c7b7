//! Products of the filter's small fixed-size matrices (2x2 to 3x3), written out.
//!
//! nalgebra's product of statically sized matrices goes through its generic `gemm`: one
//! call, with loops over strided columns, per product. The filter takes several of these
//! per particle and observation (2.0's proposal, the deferred pose Gaussian's motion
//! update): a profile of MRCLAM Dataset 6 put 4.3 % of its samples in that call alone
//! (README, session 22). These functions sum
//! each entry's products in the order of the inner index, first product first, exactly as
//! nalgebra's `gemm` does (its `y = a·x·c + 1·y` column updates, with `a = 1`), so they give
//! the same bits; the tests check that against nalgebra on random matrices.

use nalgebra::SMatrix;

/// `a · b`.
#[inline(always)]
pub fn mul<const R: usize, const K: usize, const C: usize>(
    a: &SMatrix<f64, R, K>,
    b: &SMatrix<f64, K, C>,
) -> SMatrix<f64, R, C> {
    SMatrix::from_fn(|i, j| {
        let mut s = a[(i, 0)] * b[(0, j)];
        for k in 1..K {
            s += a[(i, k)] * b[(k, j)];
        }
        s
    })
}

/// `a · bᵀ` (as `a * b.transpose()`).
#[inline(always)]
pub fn mul_t<const R: usize, const K: usize, const C: usize>(
    a: &SMatrix<f64, R, K>,
    b: &SMatrix<f64, C, K>,
) -> SMatrix<f64, R, C> {
    mul(a, &b.transpose())
}

/// `a · m · aᵀ` (as `a * m * a.transpose()`: the left product first).
#[inline(always)]
pub fn sandwich<const R: usize, const K: usize>(
    a: &SMatrix<f64, R, K>,
    m: &SMatrix<f64, K, K>,
) -> SMatrix<f64, R, R> {
    mul_t(&mul(a, m), a)
}

/// The covariance after a Kalman update of `N(·, p)` with the optimal gain `k = p Hᵀ S⁻¹`
/// and `pht = p Hᵀ` (`S = H p Hᵀ + Q`): `p − k phtᵀ = p − p Hᵀ S⁻¹ H p`, its upper triangle
/// computed and mirrored, so exactly symmetric.
///
/// In exact arithmetic the same matrix as the Joseph form `(I − K H) p (I − K H)ᵀ + K Q Kᵀ`,
/// in a fraction of its products (`N(N+1)/2 · D` multiplications, 12 for the pose and a
/// range-bearing reading against some 100). The Joseph form guards against a gain that is
/// not the optimal one and against cancellation; here the gain is always computed from `S`,
/// and `S` holds the measurement noise (`S ≥ Q`), so the subtracted term is bounded by `p`.
/// It cancels digits where `H p Hᵀ` dwarfs `Q` (a pose Gaussian deferred over a long blind
/// stretch): the two forms differ by at most 1e-13 of `p`'s size while `H p Hᵀ` stays within
/// 100 times `Q` (the test below), and by about 1e-11 at 10⁴ times, where neither form is the
/// exact one. On this project's comparison runs (README, session 24) they print the same
/// figures.
#[inline(always)]
pub fn kalman_posterior_cov<const N: usize, const D: usize>(
    p: &SMatrix<f64, N, N>,
    k: &SMatrix<f64, N, D>,
    pht: &SMatrix<f64, N, D>,
) -> SMatrix<f64, N, N> {
    let mut out = SMatrix::<f64, N, N>::zeros();
    for i in 0..N {
        for j in i..N {
            let mut s = k[(i, 0)] * pht[(j, 0)];
            for d in 1..D {
                s += k[(i, d)] * pht[(j, d)];
            }
            let v = p[(i, j)] - s;
            out[(i, j)] = v;
            out[(j, i)] = v;
        }
    }
    out
}

/// What the tests of products written out for a structure (here and in the filter) share.
#[cfg(test)]
pub(crate) mod testing {
    use proptest::prelude::*;

    /// Entries of every sign and scale, with exact zeros and ones (as in Jacobians).
    pub(crate) fn entry() -> impl Strategy<Value = f64> {
        prop_oneof![
            4 => -1e3..1e3f64,
            1 => -1e-6..1e-6f64,
            1 => Just(0.0),
            1 => Just(-0.0),
            1 => Just(1.0),
        ]
    }

    /// `a` and `b` are the same bits, or both zero (of either sign): what a product that
    /// skips the terms of an exact zero or one factor keeps of the full product.
    pub(crate) fn same_but_zero_sign(a: f64, b: f64) -> bool {
        a.to_bits() == b.to_bits() || (a == 0.0 && b == 0.0)
    }
}

#[cfg(test)]
mod tests {
    use super::testing::entry;
    use super::*;
    use nalgebra::{Matrix2, Matrix2x3, Matrix3, Matrix3x2, Vector2, Vector3};
    use proptest::prelude::*;

    fn m<const R: usize, const C: usize>() -> impl Strategy<Value = SMatrix<f64, R, C>> {
        proptest::collection::vec(entry(), R * C).prop_map(|v| SMatrix::from_column_slice(&v))
    }

    fn same_bits<const R: usize, const C: usize>(
        a: &SMatrix<f64, R, C>,
        b: &SMatrix<f64, R, C>,
    ) -> bool {
        a.iter()
            .zip(b.iter())
            .all(|(x, y)| x.to_bits() == y.to_bits())
    }

    /// A random symmetric positive definite matrix, `a aᵀ + c I`.
    fn spd<const N: usize>() -> impl Strategy<Value = SMatrix<f64, N, N>> {
        (proptest::collection::vec(-2.0..2.0f64, N * N), 1e-3..1.0f64).prop_map(|(v, c)| {
            let a = SMatrix::<f64, N, N>::from_column_slice(&v);
            a * a.transpose() + SMatrix::<f64, N, N>::identity() * c
        })
    }

    /// A measurement Jacobian: entries up to 2 (a range-bearing reading's at 0.5 m and more,
    /// a rotation's), with exact zeros and ones.
    fn jacobian<const R: usize, const C: usize>() -> impl Strategy<Value = SMatrix<f64, R, C>> {
        proptest::collection::vec(
            prop_oneof![4 => -2.0..2.0f64, 1 => Just(0.0), 1 => Just(-1.0)],
            R * C,
        )
        .prop_map(|v| SMatrix::from_column_slice(&v))
    }

    /// The symmetric form against the Joseph form for the optimal gain, and its symmetry,
    /// with `p` scaled into the filter's range: `H p Hᵀ` at most `RATIO` times `Q`'s smallest
    /// eigenvalue bound (`kalman_posterior_cov`'s docs; beyond it both forms lose digits to the
    /// cancellation, and neither is the reference).
    fn check_posterior<const N: usize, const D: usize>(
        p: &SMatrix<f64, N, N>,
        h: &SMatrix<f64, D, N>,
        q: &SMatrix<f64, D, D>,
    ) -> Result<(), TestCaseError> {
        const RATIO: f64 = 100.0;
        // A lower bound of the smallest eigenvalue: 1 / ‖Q⁻¹‖ (Frobenius).
        let q_min = q.try_inverse().unwrap().norm().recip();
        let hph = (h * p * h.transpose()).norm();
        let p = &(p * (RATIO * q_min / hph).min(1.0));
        let pht = p * h.transpose();
        let s = h * pht + q;
        let k = pht * s.try_inverse().unwrap();
        let ikh = SMatrix::<f64, N, N>::identity() - k * h;
        let joseph = ikh * p * ikh.transpose() + k * q * k.transpose();
        let ours = kalman_posterior_cov(p, &k, &pht);
        prop_assert_eq!(ours, ours.transpose());
        let scale = p.norm();
        prop_assert!(
            (ours - joseph).norm() <= 1e-13 * scale,
            "{ours} against {joseph}"
        );
        // Positive definite, as the posterior of a Gaussian with positive noise must be.
        prop_assert!(ours.cholesky().is_some());
        Ok(())
    }

    proptest! {
        #[test]
        fn the_symmetric_posterior_is_the_joseph_forms(
            p3 in spd::<3>(), q2 in spd::<2>(), h23 in jacobian::<2, 3>(),
            p2 in spd::<2>(), h22 in jacobian::<2, 2>(), q3 in spd::<3>(), h33 in jacobian::<3, 3>(),
        ) {
            check_posterior(&p3, &h23, &q2)?;
            check_posterior(&p2, &h22, &q2)?;
            check_posterior(&p3, &h33, &q3)?;
        }

        #[test]
        fn products_are_nalgebras_bit_for_bit(
            a33 in m::<3, 3>(), b33 in m::<3, 3>(), a23 in m::<2, 3>(), a32 in m::<3, 2>(),
            a22 in m::<2, 2>(), b22 in m::<2, 2>(), v3 in m::<3, 1>(), v2 in m::<2, 1>(),
        ) {
            let (a33, b33): (Matrix3<f64>, Matrix3<f64>) = (a33, b33);
            let (a23, a32): (Matrix2x3<f64>, Matrix3x2<f64>) = (a23, a32);
            let (a22, b22): (Matrix2<f64>, Matrix2<f64>) = (a22, b22);
            let (v3, v2): (Vector3<f64>, Vector2<f64>) = (v3, v2);
            prop_assert!(same_bits(&mul(&a33, &b33), &(a33 * b33)));
            prop_assert!(same_bits(&mul(&a33, &v3), &(a33 * v3)));
            prop_assert!(same_bits(&mul(&a23, &a32), &(a23 * a32)));
            prop_assert!(same_bits(&mul(&a32, &a23), &(a32 * a23)));
            prop_assert!(same_bits(&mul(&a32, &a22), &(a32 * a22)));
            prop_assert!(same_bits(&mul(&a22, &v2), &(a22 * v2)));
            prop_assert!(same_bits(&mul_t(&a33, &b33), &(a33 * b33.transpose())));
            prop_assert!(same_bits(&mul_t(&a33, &a23), &(a33 * a23.transpose())));
            prop_assert!(same_bits(&sandwich(&a33, &b33), &(a33 * b33 * a33.transpose())));
            prop_assert!(same_bits(&sandwich(&a23, &b33), &(a23 * b33 * a23.transpose())));
            prop_assert!(same_bits(&sandwich(&a32, &a22), &(a32 * a22 * a32.transpose())));
            prop_assert!(same_bits(&sandwich(&a22, &b22), &(a22 * b22 * a22.transpose())));
        }
    }
}
