//! Weighted Karcher (Fréchet) means and tangent-space covariances.
//!
//! Poses are averaged on the product manifold SO(3) × ℝ³, whose metric is the
//! one behind [`crate::PoseMetric`]: the rotation part is the Riemannian
//! (geodesic) Karcher mean, the translation part the weighted arithmetic
//! mean. Tangent vectors at the mean are `[t − t̄; log(R̄ᵀ R)]`.

use nalgebra::{Matrix3, Matrix6, Quaternion, Rotation3, UnitQuaternion, Vector3, Vector6};

use crate::eigen::{SymmetricEigen, symmetric_eigen};
use crate::{GeometryError, Pose, so3};

/// Stopping rule of the Karcher iteration.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct KarcherOptions {
    /// Stop when the update's rotation angle falls below this (radians).
    pub tolerance: f64,
    /// Stop after this many updates even if not converged.
    pub max_iterations: usize,
}

impl Default for KarcherOptions {
    fn default() -> Self {
        Self { tolerance: 1e-10, max_iterations: 50 }
    }
}

/// A mean and how the iteration that produced it ended.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct KarcherMean<T> {
    pub mean: T,
    pub iterations: usize,
    /// False when `max_iterations` was reached first (samples spread over
    /// more than a hemisphere of SO(3) have no unique mean).
    pub converged: bool,
}

/// Weights normalised to sum 1; uniform when `weights` is `None`.
fn normalised_weights(count: usize, weights: Option<&[f64]>) -> Result<Vec<f64>, GeometryError> {
    if count == 0 {
        return Err(GeometryError::Empty { what: "samples to average" });
    }
    let Some(weights) = weights else {
        return Ok(vec![1.0 / count as f64; count]);
    };
    if weights.len() != count {
        return Err(GeometryError::LengthMismatch {
            what: "weights (one per sample)",
            expected: count,
            actual: weights.len(),
        });
    }
    let sum: f64 = weights.iter().sum();
    let all_valid = weights.iter().all(|w| w.is_finite() && *w >= 0.0);
    if !all_valid || !sum.is_finite() || sum <= 0.0 {
        return Err(GeometryError::InvalidWeights { detail: format!("{weights:?}") });
    }
    Ok(weights.iter().map(|w| w / sum).collect())
}

/// A starting point near the mean: the weighted quaternion sum with signs
/// aligned to the heaviest sample (the chordal mean), which leaves the
/// geodesic iteration only a few steps to go.
fn chordal_start(rotations: &[Rotation3<f64>], weights: &[f64]) -> Rotation3<f64> {
    let heaviest = weights.iter().enumerate().max_by(|a, b| a.1.total_cmp(b.1)).map_or(0, |(i, _)| i);
    let quaternions: Vec<UnitQuaternion<f64>> =
        rotations.iter().map(|r| so3::quaternion_from_matrix(r.matrix())).collect();
    let reference = quaternions[heaviest].coords;
    let mut sum = Quaternion::identity().coords * 0.0;
    for (q, w) in quaternions.iter().zip(weights) {
        let sign = if q.coords.dot(&reference) < 0.0 { -1.0 } else { 1.0 };
        sum += q.coords * (sign * w);
    }
    if sum.norm() < 1e-9 {
        return rotations[heaviest];
    }
    UnitQuaternion::from_quaternion(Quaternion::from(sum)).to_rotation_matrix()
}

/// The weighted Karcher mean of rotations: the minimiser of
/// `Σ wᵢ θ(R, Rᵢ)²`, by the fixed-point iteration `R ← R exp(Σ wᵢ log(Rᵀ Rᵢ))`.
pub fn karcher_mean_rotations(
    rotations: &[Rotation3<f64>],
    weights: Option<&[f64]>,
    options: &KarcherOptions,
) -> Result<KarcherMean<Rotation3<f64>>, GeometryError> {
    let weights = normalised_weights(rotations.len(), weights)?;
    let mut mean = chordal_start(rotations, &weights);
    for iteration in 1..=options.max_iterations {
        let mean_inverse = mean.inverse();
        let step: Vector3<f64> = rotations.iter().zip(&weights).map(|(r, w)| so3::log(&(mean_inverse * r)) * *w).sum();
        mean *= so3::exp(&step);
        if step.norm() < options.tolerance {
            return Ok(KarcherMean { mean, iterations: iteration, converged: true });
        }
    }
    Ok(KarcherMean { mean, iterations: options.max_iterations, converged: false })
}

/// The weighted Karcher mean of poses on SO(3) × ℝ³ (see the module docs).
pub fn karcher_mean_poses(
    poses: &[Pose],
    weights: Option<&[f64]>,
    options: &KarcherOptions,
) -> Result<KarcherMean<Pose>, GeometryError> {
    let rotations: Vec<_> = poses.iter().map(|p| p.rotation).collect();
    let rotation = karcher_mean_rotations(&rotations, weights, options)?;
    let weights = normalised_weights(poses.len(), weights)?;
    let translation: Vector3<f64> = poses.iter().zip(&weights).map(|(p, w)| p.translation * *w).sum();
    Ok(KarcherMean {
        mean: Pose::new(rotation.mean, translation),
        iterations: rotation.iterations,
        converged: rotation.converged,
    })
}

/// Mean and spread of a set of pose samples.
///
/// `covariance` is the weighted second moment of the tangent vectors
/// `[t − t̄; log(R̄ᵀ R)]` at the mean (metres², radians²; rows/columns 0–2
/// translation, 3–5 rotation in the mean's body frame). It is the maximum
/// likelihood (biased) estimate, `Σ wᵢ ξᵢ ξᵢᵀ` with `Σ wᵢ = 1`.
#[derive(Debug, Clone, PartialEq)]
pub struct PoseStatistics {
    pub mean: KarcherMean<Pose>,
    pub covariance: Matrix6<f64>,
}

impl PoseStatistics {
    pub fn compute(poses: &[Pose], weights: Option<&[f64]>, options: &KarcherOptions) -> Result<Self, GeometryError> {
        let mean = karcher_mean_poses(poses, weights, options)?;
        let weights = normalised_weights(poses.len(), weights)?;
        let mean_inverse = mean.mean.rotation.inverse();
        let mut covariance = Matrix6::zeros();
        for (pose, w) in poses.iter().zip(&weights) {
            let dt = pose.translation - mean.mean.translation;
            let dr = so3::log(&(mean_inverse * pose.rotation));
            let xi = Vector6::new(dt.x, dt.y, dt.z, dr.x, dr.y, dr.z);
            covariance += xi * xi.transpose() * *w;
        }
        Ok(Self { mean, covariance })
    }

    /// The 3×3 rotational block `Σ_R` (radians²); its trace is the paper's
    /// next-best-view objective.
    pub fn rotation_covariance(&self) -> Matrix3<f64> {
        self.covariance.fixed_view::<3, 3>(3, 3).into_owned()
    }

    pub fn translation_covariance(&self) -> Matrix3<f64> {
        self.covariance.fixed_view::<3, 3>(0, 0).into_owned()
    }

    /// Principal axes of the full 6×6 covariance.
    pub fn eigen(&self) -> Result<SymmetricEigen<6>, GeometryError> {
        symmetric_eigen(&self.covariance)
    }

    /// Principal axes of rotational uncertainty.
    pub fn rotation_eigen(&self) -> Result<SymmetricEigen<3>, GeometryError> {
        symmetric_eigen(&self.rotation_covariance())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mean_of_two_rotations_about_an_axis_is_the_midpoint() {
        let a = so3::exp(&Vector3::new(0.0, 0.0, 0.2));
        let b = so3::exp(&Vector3::new(0.0, 0.0, 1.0));
        let m = karcher_mean_rotations(&[a, b], None, &KarcherOptions::default()).unwrap();
        assert!(m.converged);
        assert!((so3::log(&m.mean) - Vector3::new(0.0, 0.0, 0.6)).norm() < 1e-12);
    }

    #[test]
    fn weights_pull_the_mean() {
        let a = so3::exp(&Vector3::new(0.0, 0.0, 0.0));
        let b = so3::exp(&Vector3::new(0.0, 0.0, 1.0));
        let m = karcher_mean_rotations(&[a, b], Some(&[3.0, 1.0]), &KarcherOptions::default()).unwrap();
        assert!((so3::log(&m.mean) - Vector3::new(0.0, 0.0, 0.25)).norm() < 1e-12);
    }

    #[test]
    fn bad_weights_are_rejected_with_a_reason() {
        let r = [Rotation3::identity(); 2];
        let opts = KarcherOptions::default();
        assert!(karcher_mean_rotations(&[], None, &opts).is_err());
        assert!(karcher_mean_rotations(&r, Some(&[1.0]), &opts).is_err());
        let err = karcher_mean_rotations(&r, Some(&[1.0, -1.0]), &opts).unwrap_err();
        assert!(err.to_string().contains("non-negative"), "{err}");
        assert!(karcher_mean_rotations(&r, Some(&[0.0, 0.0]), &opts).is_err());
        assert!(karcher_mean_rotations(&r, Some(&[f64::NAN, 1.0]), &opts).is_err());
    }

    #[test]
    fn covariance_of_a_known_spread() {
        // Rotations ±σ about x and translations ±s along y, each half the weight:
        // the covariance is diag(0, s², 0, σ², 0, 0) with zero cross terms.
        let (sigma, s) = (0.1, 0.02);
        let poses = [
            Pose::new(so3::exp(&Vector3::new(sigma, 0.0, 0.0)), Vector3::new(0.0, s, 0.0)),
            Pose::new(so3::exp(&Vector3::new(-sigma, 0.0, 0.0)), Vector3::new(0.0, -s, 0.0)),
        ];
        let stats = PoseStatistics::compute(&poses, None, &KarcherOptions::default()).unwrap();
        let mut expected = Matrix6::zeros();
        expected[(1, 1)] = s * s;
        expected[(3, 3)] = sigma * sigma;
        expected[(1, 3)] = s * sigma;
        expected[(3, 1)] = s * sigma;
        assert!((stats.covariance - expected).abs().max() < 1e-14, "{}", stats.covariance);
        assert!((stats.rotation_covariance().trace() - sigma * sigma).abs() < 1e-14);
        let eig = stats.rotation_eigen().unwrap();
        assert!((eig.values[2] - sigma * sigma).abs() < 1e-14);
        assert!(eig.values[0].abs() < 1e-14);
        // One principal direction carries all the 6-D variance.
        let full = stats.eigen().unwrap();
        assert!((full.values[5] - (s * s + sigma * sigma)).abs() < 1e-14);
    }
}
