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

    proptest! {
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
