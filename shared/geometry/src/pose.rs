//! Rigid transforms (SE(3)) and their exponential / logarithm maps.

use nalgebra::{Matrix3, Matrix4, Point3, Rotation3, Vector3, Vector6};

use crate::{GeometryError, so3};

/// A rigid transform `x_to = R · x_from + t` (metres).
///
/// As an object pose it maps object coordinates to camera coordinates
/// (object-to-camera). Composition `a * b` applies `b` first.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pose {
    pub rotation: Rotation3<f64>,
    pub translation: Vector3<f64>,
}

/// An SE(3) twist `[ρ; φ]`: translation part first, then the rotation vector.
pub type Twist = Vector6<f64>;

impl Pose {
    pub fn new(rotation: Rotation3<f64>, translation: Vector3<f64>) -> Self {
        Self { rotation, translation }
    }

    pub fn identity() -> Self {
        Self::new(Rotation3::identity(), Vector3::zeros())
    }

    pub fn inverse(&self) -> Self {
        let r_inv = self.rotation.inverse();
        Self::new(r_inv, -(r_inv * self.translation))
    }

    pub fn transform_point(&self, p: &Point3<f64>) -> Point3<f64> {
        self.rotation * p + self.translation
    }

    /// The homogeneous 4×4 matrix `[R t; 0 1]`.
    pub fn to_homogeneous(&self) -> Matrix4<f64> {
        let mut m = Matrix4::identity();
        m.fixed_view_mut::<3, 3>(0, 0).copy_from(self.rotation.matrix());
        m.fixed_view_mut::<3, 1>(0, 3).copy_from(&self.translation);
        m
    }

    /// The SE(3) exponential: `R = exp(φ)`, `t = J(φ) ρ` with the left
    /// Jacobian `J` ([`so3::left_jacobian`]).
    pub fn exp(twist: &Twist) -> Self {
        let rho = twist.fixed_rows::<3>(0).into_owned();
        let phi = twist.fixed_rows::<3>(3).into_owned();
        Self::new(so3::exp(&phi), so3::left_jacobian(&phi) * rho)
    }

    /// The SE(3) logarithm, inverse of [`Pose::exp`], with `|φ| ∈ [0, π]`.
    pub fn log(&self) -> Twist {
        let phi = so3::log(&self.rotation);
        let rho = so3::left_jacobian_inverse(&phi) * self.translation;
        Twist::new(rho.x, rho.y, rho.z, phi.x, phi.y, phi.z)
    }

    /// Flattens to the message layout: `R` row-major (9 values), then `t`
    /// (3 values), as `f32`.
    pub fn to_f32_row_major(&self) -> [f32; 12] {
        let r = self.rotation.matrix();
        let mut out = [0.0f32; 12];
        for row in 0..3 {
            for col in 0..3 {
                out[row * 3 + col] = r[(row, col)] as f32;
            }
            out[9 + row] = self.translation[row] as f32;
        }
        out
    }

    /// Reads the message layout of [`Pose::to_f32_row_major`].
    ///
    /// `f32` rounding leaves `R` slightly off SO(3); it is projected back onto
    /// the nearest rotation. Rejects non-finite values and matrices that are
    /// not rotations within `1e-3` (a corrupted message, not rounding).
    pub fn from_f32_row_major(values: &[f32; 12]) -> Result<Self, GeometryError> {
        let as_f64: Vec<f64> = values.iter().map(|&v| f64::from(v)).collect();
        if as_f64.iter().any(|v| !v.is_finite()) {
            return Err(GeometryError::NonFinite { what: "pose (row-major R, t)", values: as_f64 });
        }
        let m = Matrix3::from_row_slice(&as_f64[..9]);
        let rotation = project_to_rotation(&m, "pose rotation", 1e-3)?;
        Ok(Self::new(rotation, Vector3::new(as_f64[9], as_f64[10], as_f64[11])))
    }
}

impl std::ops::Mul for Pose {
    type Output = Pose;
    fn mul(self, rhs: Pose) -> Pose {
        Pose::new(self.rotation * rhs.rotation, self.rotation * rhs.translation + self.translation)
    }
}

/// Projects an almost-orthonormal matrix onto SO(3) after checking that it is
/// within `tolerance` of one (max-abs of `MᵀM − I`, and `det M > 0`).
pub fn project_to_rotation(m: &Matrix3<f64>, what: &str, tolerance: f64) -> Result<Rotation3<f64>, GeometryError> {
    let orthogonality = (m.transpose() * m - Matrix3::identity()).abs().max();
    let det = m.determinant();
    // NaN entries make `orthogonality` NaN, which must fail too.
    let is_rotation = orthogonality.is_finite() && orthogonality <= tolerance && det > 0.0;
    if !is_rotation {
        return Err(GeometryError::NotARotation {
            what: what.to_string(),
            detail: format!("max |RᵀR − I| = {orthogonality:.3e}, det = {det:.6}"),
        });
    }
    Ok(so3::quaternion_from_matrix(m).to_rotation_matrix())
}

/// The rotation nearest `m` in the Frobenius norm (`U Vᵀ` of its SVD, with
/// the sign of the last singular direction flipped if that is a
/// reflection): exact for a scaled rotation, unlike reading a quaternion
/// off the matrix. For annotations that are only nearly orthonormal.
pub fn nearest_rotation(m: &Matrix3<f64>) -> Rotation3<f64> {
    let svd = m.svd(true, true);
    let (u, v_t) = (svd.u.expect("requested"), svd.v_t.expect("requested"));
    let mut correction = Matrix3::identity();
    correction[(2, 2)] = (u * v_t).determinant().signum();
    // SVD orders singular values descending; flipping the smallest one's
    // direction is the least change.
    Rotation3::from_matrix_unchecked(u * correction * v_t)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::PI;

    #[test]
    fn the_nearest_rotation_of_a_scaled_or_sheared_rotation() {
        let r = Rotation3::from_euler_angles(0.4, -1.1, 2.5);
        let back = nearest_rotation(&(r.matrix() * 1.003));
        assert!((back.matrix() - r.matrix()).abs().max() < 1e-12);
        // A small symmetric stretch R (I + εS) keeps R as its nearest rotation.
        let stretch = Matrix3::new(0.0, 1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.5) * 2e-3;
        let back = nearest_rotation(&(r.matrix() * (Matrix3::identity() + stretch)));
        assert!((back.matrix() - r.matrix()).abs().max() < 1e-12, "{back}");
        assert!((back.matrix().determinant() - 1.0).abs() < 1e-12);
    }

    #[test]
    fn exp_of_pure_translation_is_translation() {
        let pose = Pose::exp(&Twist::new(1.0, -2.0, 0.5, 0.0, 0.0, 0.0));
        assert_eq!(pose.rotation, Rotation3::identity());
        assert_eq!(pose.translation, Vector3::new(1.0, -2.0, 0.5));
    }

    #[test]
    fn exp_of_screw_motion_matches_closed_form() {
        // Rotation by θ about z with ρ along x: t = J(φ) ρ where for φ = θ ẑ,
        // J ρ = (sin θ/θ, (1 − cos θ)/θ, 0) for ρ = x̂.
        let theta = 1.2;
        let pose = Pose::exp(&Twist::new(1.0, 0.0, 0.0, 0.0, 0.0, theta));
        let expected = Vector3::new(theta.sin() / theta, (1.0 - theta.cos()) / theta, 0.0);
        assert!((pose.translation - expected).norm() < 1e-14);
    }

    #[test]
    fn log_at_pi_is_finite_and_inverts() {
        let twist = Twist::new(0.3, 0.1, -0.2, 0.0, PI, 0.0);
        let pose = Pose::exp(&twist);
        let back = Pose::exp(&pose.log());
        assert!((back.to_homogeneous() - pose.to_homogeneous()).abs().max() < 1e-12);
    }

    #[test]
    fn inverse_composes_to_identity() {
        let pose = Pose::exp(&Twist::new(0.3, 0.1, -0.2, 0.4, -1.0, 2.0));
        let id = pose * pose.inverse();
        assert!((id.to_homogeneous() - Matrix4::identity()).abs().max() < 1e-14);
    }

    #[test]
    fn f32_round_trip_is_close() {
        let pose = Pose::exp(&Twist::new(0.3, 0.1, -0.2, 0.4, -1.0, 2.0));
        let back = Pose::from_f32_row_major(&pose.to_f32_row_major()).unwrap();
        assert!((back.to_homogeneous() - pose.to_homogeneous()).abs().max() < 1e-6);
    }

    #[test]
    fn f32_reader_rejects_nan_and_non_rotations() {
        let mut values = Pose::identity().to_f32_row_major();
        values[4] = f32::NAN;
        let err = Pose::from_f32_row_major(&values).unwrap_err().to_string();
        assert!(err.contains("finite"), "{err}");

        let mut values = Pose::identity().to_f32_row_major();
        values[0] = 2.0;
        let err = Pose::from_f32_row_major(&values).unwrap_err().to_string();
        assert!(err.contains("rotation matrix"), "{err}");

        let mut reflection = Pose::identity().to_f32_row_major();
        reflection[8] = -1.0;
        assert!(Pose::from_f32_row_major(&reflection).is_err());
    }
}
