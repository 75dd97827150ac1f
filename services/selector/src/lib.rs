//! Pose selection (paper, "Pose selection"): from N flow samples to one
//! Estimate — the selected pose, the mean and tangent covariance of the
//! kept hypotheses, the modes, and every hypothesis with its score.
//!
//! - model-free: DBSCAN with the paper's thresholds, the largest cluster,
//!   its Karcher mean ([`cluster`]);
//! - model-based: how well the observed points fit the object under each
//!   hypothesis, by exact point-to-mesh distance (Chamfer) or by a signed
//!   distance grid precomputed once per object
//!   ([`poseflow_scene::sdf`], [`score`]);
//! - refinement (beyond the paper): Levenberg-Marquardt on SE(3) pulling
//!   the kept hypotheses onto the observed points through the same grid
//!   ([`poseflow_scene::sdf_refine`]).
//!
//! [`select`] is the plain function; [`stage::SelectorStage`] the stage.

pub mod cluster;
mod error;
mod params;
pub mod score;
mod select;
pub mod stage;
pub mod track;
pub mod visibility;

pub use error::SelectorError;
pub use params::{Distribution, Method, SelectorParams, Turns};
pub use select::{Observed, Selection, select};

/// The stage of this crate: `selector` (Hypotheses in, Estimate out; the
/// model-based methods and refinement read the Observations as a side
/// input).
pub fn registrations() -> Vec<poseflow_runtime::Registration> {
    vec![poseflow_runtime::Registration::transform_or_joined("selector", stage::from_wiring)]
}
