//! The rotation group SO(3): exponential and logarithm maps, the geodesic
//! angle, and the left Jacobian used by SE(3).
//!
//! Rotation vectors `ω` are axis × angle in radians. `exp` maps them to
//! rotation matrices by Rodrigues' formula; `log` inverts it through a unit
//! quaternion, which stays accurate near 0 *and* near π, where the usual
//! `acos((tr R − 1)/2)` formula loses all precision.

use nalgebra::{Matrix3, Rotation3, UnitQuaternion, Vector3};

/// Below this angle (radians) the trigonometric coefficients switch to Taylor
/// series; the truncated terms are O(θ⁶) < 1e-24 there.
const SMALL_ANGLE: f64 = 1e-4;

/// The skew-symmetric matrix `[ω]×` with `[ω]× x = ω × x`.
pub fn hat(omega: &Vector3<f64>) -> Matrix3<f64> {
    Matrix3::new(
        0.0, -omega.z, omega.y, //
        omega.z, 0.0, -omega.x, //
        -omega.y, omega.x, 0.0,
    )
}

/// The inverse of [`hat`]: reads `ω` from the skew-symmetric part of `m`.
pub fn vee(m: &Matrix3<f64>) -> Vector3<f64> {
    Vector3::new(0.5 * (m[(2, 1)] - m[(1, 2)]), 0.5 * (m[(0, 2)] - m[(2, 0)]), 0.5 * (m[(1, 0)] - m[(0, 1)]))
}

/// `sin θ / θ`, `(1 − cos θ)/θ²` and `(θ − sin θ)/θ³`, stable at θ → 0.
fn rodrigues_coefficients(theta: f64) -> (f64, f64, f64) {
    if theta < SMALL_ANGLE {
        let t2 = theta * theta;
        (1.0 - t2 / 6.0 + t2 * t2 / 120.0, 0.5 - t2 / 24.0 + t2 * t2 / 720.0, 1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0)
    } else {
        let half_sin = (0.5 * theta).sin();
        (
            theta.sin() / theta,
            // 2 sin²(θ/2) avoids the cancellation in 1 − cos θ.
            2.0 * half_sin * half_sin / (theta * theta),
            (theta - theta.sin()) / (theta * theta * theta),
        )
    }
}

/// The exponential map: the rotation by `|ω|` radians about `ω/|ω|`.
pub fn exp(omega: &Vector3<f64>) -> Rotation3<f64> {
    let theta = omega.norm();
    let (a, b, _) = rodrigues_coefficients(theta);
    let k = hat(omega);
    Rotation3::from_matrix_unchecked(Matrix3::identity() + k * a + k * k * b)
}

/// The unit quaternion of a rotation matrix by Shepperd's method (branch on
/// the largest diagonal term, so no division by a small number), with the
/// scalar part made non-negative.
///
/// The result is normalised, so a matrix that is only approximately
/// orthonormal (e.g. read from `f32`) yields the nearest valid rotation.
pub fn quaternion_from_matrix(m: &Matrix3<f64>) -> UnitQuaternion<f64> {
    let trace = m[(0, 0)] + m[(1, 1)] + m[(2, 2)];
    let (w, x, y, z);
    if trace >= m[(0, 0)] && trace >= m[(1, 1)] && trace >= m[(2, 2)] {
        let s = 2.0 * (1.0 + trace).max(0.0).sqrt();
        w = 0.25 * s;
        x = (m[(2, 1)] - m[(1, 2)]) / s;
        y = (m[(0, 2)] - m[(2, 0)]) / s;
        z = (m[(1, 0)] - m[(0, 1)]) / s;
    } else if m[(0, 0)] >= m[(1, 1)] && m[(0, 0)] >= m[(2, 2)] {
        let s = 2.0 * (1.0 + m[(0, 0)] - m[(1, 1)] - m[(2, 2)]).max(0.0).sqrt();
        w = (m[(2, 1)] - m[(1, 2)]) / s;
        x = 0.25 * s;
        y = (m[(0, 1)] + m[(1, 0)]) / s;
        z = (m[(0, 2)] + m[(2, 0)]) / s;
    } else if m[(1, 1)] >= m[(2, 2)] {
        let s = 2.0 * (1.0 - m[(0, 0)] + m[(1, 1)] - m[(2, 2)]).max(0.0).sqrt();
        w = (m[(0, 2)] - m[(2, 0)]) / s;
        x = (m[(0, 1)] + m[(1, 0)]) / s;
        y = 0.25 * s;
        z = (m[(1, 2)] + m[(2, 1)]) / s;
    } else {
        let s = 2.0 * (1.0 - m[(0, 0)] - m[(1, 1)] + m[(2, 2)]).max(0.0).sqrt();
        w = (m[(1, 0)] - m[(0, 1)]) / s;
        x = (m[(0, 2)] + m[(2, 0)]) / s;
        y = (m[(1, 2)] + m[(2, 1)]) / s;
        z = 0.25 * s;
    }
    let sign = if w < 0.0 { -1.0 } else { 1.0 };
    UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(sign * w, sign * x, sign * y, sign * z))
}

/// The rotation vector of a unit quaternion with non-negative scalar part;
/// its norm is in `[0, π]`.
fn log_quaternion(q: &UnitQuaternion<f64>) -> Vector3<f64> {
    let imag = q.imag();
    let n = imag.norm();
    let w = q.scalar();
    // θ = 2·atan2(|v|, w) is well conditioned for every angle; the ratio θ/|v|
    // tends to 2/w as |v| → 0.
    let scale = if n < 1e-12 { 2.0 / w } else { 2.0 * n.atan2(w) / n };
    imag * scale
}

/// The logarithm map: the rotation vector `ω` with `exp(ω) = R` and
/// `|ω| ∈ [0, π]`.
///
/// At exactly π the axis is defined up to sign; either sign is returned and
/// both are valid (`exp` of either is `R`). Never NaN for a rotation matrix.
pub fn log(r: &Rotation3<f64>) -> Vector3<f64> {
    log_quaternion(&quaternion_from_matrix(r.matrix()))
}

/// The geodesic (angular) distance between two rotations, `|log(R₁ᵀ R₂)|`,
/// in radians, in `[0, π]`.
pub fn geodesic_angle(r1: &Rotation3<f64>, r2: &Rotation3<f64>) -> f64 {
    let q = quaternion_from_matrix(&(r1.matrix().transpose() * r2.matrix()));
    2.0 * q.imag().norm().atan2(q.scalar())
}

/// The left Jacobian `J(φ)` of SO(3): `exp` of an SE(3) twist `[ρ; φ]` has
/// translation `J(φ) ρ`.
pub fn left_jacobian(phi: &Vector3<f64>) -> Matrix3<f64> {
    let theta = phi.norm();
    let (_, b, c) = rodrigues_coefficients(theta);
    let k = hat(phi);
    Matrix3::identity() + k * b + k * k * c
}

/// The inverse of [`left_jacobian`], valid for `|φ| < 2π` and in particular
/// at `|φ| = π` (where it uses `cot(θ/2)`, which is 0 there, not `0/0`).
pub fn left_jacobian_inverse(phi: &Vector3<f64>) -> Matrix3<f64> {
    let theta = phi.norm();
    let d = if theta < SMALL_ANGLE {
        let t2 = theta * theta;
        1.0 / 12.0 + t2 / 720.0 + t2 * t2 / 30240.0
    } else {
        let half = 0.5 * theta;
        (1.0 - half * half.cos() / half.sin()) / (theta * theta)
    };
    let k = hat(phi);
    Matrix3::identity() - k * 0.5 + k * k * d
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::PI;

    fn assert_mat_close(a: &Matrix3<f64>, b: &Matrix3<f64>, tol: f64) {
        assert!((a - b).abs().max() < tol, "\n{a}\n!=\n{b}");
    }

    #[test]
    fn exp_about_z_matches_closed_form() {
        for &theta in &[0.0, 1e-9, 1e-5, 0.3, 1.0, PI / 2.0, 3.0, PI] {
            let r = exp(&Vector3::new(0.0, 0.0, theta));
            let (s, c) = theta.sin_cos();
            let expected = Matrix3::new(c, -s, 0.0, s, c, 0.0, 0.0, 0.0, 1.0);
            assert_mat_close(r.matrix(), &expected, 1e-15);
        }
    }

    #[test]
    fn log_of_identity_is_zero() {
        assert_eq!(log(&Rotation3::identity()), Vector3::zeros());
    }

    #[test]
    fn log_at_pi_returns_a_valid_axis() {
        // Diagonal matrices with two −1 entries are rotations by exactly π.
        for axis in [Vector3::x(), Vector3::y(), Vector3::z()] {
            let r = Rotation3::from_matrix_unchecked(Matrix3::from_diagonal(&(axis * 2.0 - Vector3::repeat(1.0))));
            let omega = log(&r);
            assert!(omega.iter().all(|x| x.is_finite()));
            assert!((omega.norm() - PI).abs() < 1e-12);
            assert!((omega.normalize().dot(&axis).abs() - 1.0).abs() < 1e-12);
            assert_mat_close(exp(&omega).matrix(), r.matrix(), 1e-12);
        }
    }

    #[test]
    fn log_near_pi_keeps_precision() {
        // acos-based logs lose ~sqrt(eps) here; the quaternion route must not.
        let axis = Vector3::new(1.0, 2.0, -0.5).normalize();
        let omega = axis * (PI - 1e-7);
        assert!((log(&exp(&omega)) - omega).norm() < 1e-12);
    }

    #[test]
    fn geodesic_angle_of_known_pair() {
        let a = exp(&Vector3::new(0.0, 0.0, 0.25));
        let b = exp(&Vector3::new(0.0, 0.0, -0.5));
        assert!((geodesic_angle(&a, &b) - 0.75).abs() < 1e-14);
        assert!(geodesic_angle(&a, &a) < 1e-15);
    }

    #[test]
    fn jacobian_inverse_inverts_near_zero_and_pi() {
        for &theta in &[0.0, 1e-8, 1e-3, 1.0, 3.0, PI - 1e-7, PI] {
            let phi = Vector3::new(0.6, -0.8, 0.0) * theta;
            let product = left_jacobian(&phi) * left_jacobian_inverse(&phi);
            assert_mat_close(&product, &Matrix3::identity(), 1e-11);
        }
    }

    #[test]
    fn hat_vee_round_trip() {
        let w = Vector3::new(0.1, -2.0, 3.5);
        assert_eq!(vee(&hat(&w)), w);
        assert_eq!(hat(&w) * Vector3::new(1.0, 2.0, 3.0), w.cross(&Vector3::new(1.0, 2.0, 3.0)));
    }
}
