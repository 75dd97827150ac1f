//! How well the observed points fit the object under a pose: each observed
//! point (camera frame) is taken into the model frame, `y = Rᵀ(x − t)`, and
//! its distance to the surface is a residual. Residuals are truncated at
//! `outlier_distance` (points of occluders or mask bleed) and turned into a
//! Gaussian log-likelihood per point:
//! `score = −(1/n) Σ min(r², τ²) / (2σ²)`. Higher is better; 0 is a perfect fit.

use nalgebra::Point3;
use parry3d::query::PointQuery;
use poseflow_geometry::Pose;

use crate::ObjectGeometry;

/// Where residuals come from.
#[derive(Debug, Clone, Copy)]
pub enum Residuals<'a> {
    /// One-sided Chamfer: the exact distance from each observed point to
    /// the posed mesh (parry point projection).
    Chamfer(&'a ObjectGeometry),
    /// The signed distance grid, trilinear.
    Sdf(&'a ObjectGeometry),
}

/// Likelihood settings, metres.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Likelihood {
    pub noise_std: f64,
    pub outlier_distance: f64,
}

impl Residuals<'_> {
    /// The residual of one model-frame point.
    pub fn residual(&self, y: &Point3<f64>) -> f64 {
        match self {
            Self::Chamfer(object) => {
                let query = Point3::from(y.coords.cast::<f32>());
                f64::from(object.mesh.distance_to_local_point(&query, false))
            }
            Self::Sdf(object) => object.grid().value(y),
        }
    }

    /// The log-likelihood score of `pose` for `points` (camera frame).
    pub fn score(&self, pose: &Pose, points: &[Point3<f64>], likelihood: &Likelihood) -> f64 {
        let inverse = pose.inverse();
        let cap = likelihood.outlier_distance * likelihood.outlier_distance;
        let sum: f64 = points.iter().map(|x| self.residual(&inverse.transform_point(x)).powi(2).min(cap)).sum();
        -sum / (points.len().max(1) as f64 * 2.0 * likelihood.noise_std * likelihood.noise_std)
    }
}
