//! How well the observed points fit the object under a pose: each observed
//! point (camera frame) is taken into the model frame, `y = Rᵀ(x − t)`, and
//! its distance to the surface is a residual. Residuals are truncated at
//! `outlier_distance` (points of occluders or mask bleed) and turned into a
//! Gaussian log-likelihood per point:
//! `score = −(1/n) Σ min(r², τ²) / (2σ²)`. Higher is better; 0 is a perfect fit.
//!
//! With the crop's depth at hand ([`Scorer`]), a pose that puts the object
//! where the camera saw past it loses `w · τ²/(2σ²) · share` more: each
//! violated line of sight counts like an outlier point, per cell of object
//! seen ([`crate::visibility::free_space`]), times the weight `w`. Among
//! several poses it is added only while it can change the best
//! ([`Scorer::scores`]).

use nalgebra::Point3;
use parry3d::query::PointQuery;
use poseflow_geometry::Pose;
use poseflow_geometry::metrics::Pinhole;
use poseflow_scene::ObjectGeometry;
use poseflow_scene::sdf_refine::Likelihood;

use crate::visibility::{DepthGrid, FreeSpace, FreeSpaceSettings, free_space};

/// Where residuals come from.
#[derive(Debug, Clone, Copy)]
pub enum Residuals<'a> {
    /// One-sided Chamfer: the exact distance from each observed point to
    /// the posed mesh (parry point projection).
    Chamfer(&'a ObjectGeometry),
    /// The signed distance grid, trilinear.
    Sdf(&'a ObjectGeometry),
}

impl<'a> Residuals<'a> {
    pub fn object(&self) -> &'a ObjectGeometry {
        match *self {
            Self::Chamfer(object) | Self::Sdf(object) => object,
        }
    }

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

/// The free-space term of a [`Scorer`]: the crop's depth grid, the camera
/// it was seen with, and how much a violation costs.
#[derive(Debug, Clone, Copy)]
pub struct FreeSpaceTerm<'a> {
    pub grid: &'a DepthGrid,
    pub camera: &'a Pinhole,
    pub settings: FreeSpaceSettings,
    /// `w`: 1 counts a violated line of sight like an outlier point.
    pub weight: f64,
}

/// Scores poses of one object against one observation: the points'
/// log-likelihood and, with a [`FreeSpaceTerm`], the free-space penalty.
#[derive(Debug, Clone, Copy)]
pub struct Scorer<'a> {
    pub residuals: Residuals<'a>,
    pub points: &'a [Point3<f64>],
    pub likelihood: Likelihood,
    pub free_space: Option<FreeSpaceTerm<'a>>,
}

impl Scorer<'_> {
    /// The points' log-likelihood alone.
    pub fn fit(&self, pose: &Pose) -> f64 {
        self.residuals.score(pose, self.points, &self.likelihood)
    }

    /// The scores of `poses` from their `fits`: the free-space penalty added
    /// in order of fit for as long as it can change which pose is best.
    /// A penalty only lowers a score, so once the best score found (or
    /// `floor`, the best of poses scored earlier) is at least the next fit,
    /// no later pose can win, and the rest keep their fit (an upper bound)
    /// without the cost of their lines of sight.
    pub fn scores(&self, poses: &[Pose], fits: &[f64], floor: f64) -> Vec<f64> {
        let mut scores = fits.to_vec();
        let Some(term) = self.free_space.filter(|term| term.weight > 0.0) else { return scores };
        let mut order: Vec<usize> = (0..poses.len()).collect();
        order.sort_by(|&a, &b| fits[b].total_cmp(&fits[a]));
        let mut best = floor;
        for i in order {
            if fits[i] <= best {
                break;
            }
            let share = self.free_space(&poses[i]).map_or(0.0, |found| found.share());
            scores[i] = fits[i] + term.weight * self.likelihood.outlier_score() * share;
            best = best.max(scores[i]);
        }
        scores
    }

    /// What the free-space test finds at `pose`, whatever the term's
    /// weight; `None` without a depth grid.
    pub fn free_space(&self, pose: &Pose) -> Option<FreeSpace> {
        let term = self.free_space?;
        let object = self.residuals.object();
        Some(free_space(pose, term.grid, term.camera, object.bounding_sphere(), &term.settings, |y| {
            object.grid().value(y)
        }))
    }
}
