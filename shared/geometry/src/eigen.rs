//! Symmetric eigen-decomposition of small fixed-size matrices through faer.

use nalgebra::{SMatrix, SVector};

use crate::GeometryError;

/// `A = V diag(λ) Vᵀ` of a symmetric `A`. `values` are ascending; column `k`
/// of `vectors` (unit length) belongs to `values[k]`.
#[derive(Debug, Clone, PartialEq)]
pub struct SymmetricEigen<const N: usize> {
    pub values: SVector<f64, N>,
    pub vectors: SMatrix<f64, N, N>,
}

/// Decomposes `m`, reading only its lower triangle (so a covariance that is
/// symmetric up to rounding needs no clean-up).
pub fn symmetric_eigen<const N: usize>(m: &SMatrix<f64, N, N>) -> Result<SymmetricEigen<N>, GeometryError> {
    let dense = faer::Mat::<f64>::from_fn(N, N, |i, j| m[(i, j)]);
    let evd = dense.self_adjoint_eigen(faer::Side::Lower).map_err(|_| GeometryError::EigenNoConvergence { size: N })?;
    let values = evd.S().column_vector();
    let vectors = evd.U();
    Ok(SymmetricEigen { values: SVector::from_fn(|i, _| values[i]), vectors: SMatrix::from_fn(|i, j| vectors[(i, j)]) })
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Matrix3, Vector3};

    #[test]
    fn diagonal_matrix_gives_sorted_values() {
        let eig = symmetric_eigen(&Matrix3::from_diagonal(&Vector3::new(3.0, 1.0, 2.0))).unwrap();
        assert_eq!(eig.values, Vector3::new(1.0, 2.0, 3.0));
        assert!((eig.vectors.column(0).abs() - Vector3::y()).norm() < 1e-15);
    }

    #[test]
    fn reconstructs_a_full_symmetric_matrix() {
        let a = Matrix3::new(4.0, 1.0, -2.0, 1.0, 2.0, 0.5, -2.0, 0.5, 3.0);
        let eig = symmetric_eigen(&a).unwrap();
        let back = eig.vectors * Matrix3::from_diagonal(&eig.values) * eig.vectors.transpose();
        assert!((back - a).abs().max() < 1e-13);
        assert!(eig.values[0] <= eig.values[1] && eig.values[1] <= eig.values[2]);
    }
}
