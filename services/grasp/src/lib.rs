//! Grasps under pose uncertainty (paper, "Robotic Grasping").
//!
//! - [`gripper`]: the parallel-jaw gripper and the grasp frame;
//! - [`check_grasp`]: antipodal and collision-free on an object mesh, the
//!   single test behind the grasp data, the valid shares and the simulated
//!   evaluation;
//! - [`sample_grasps`]: antipodal grasp data for training the grasp flow,
//!   written per object as a [`data::GraspSet`];
//! - [`marginal_grasps`]: grasps integrated in the grasp flow's velocity
//!   averaged over the pose hypotheses (the paper's mean field);
//! - [`GraspPlanner`]: objects + grasp flow: an Estimate's hypotheses to
//!   grasps ranked by the share of hypotheses they hold under; the same
//!   code runs in-process and as the stage ([`stage::GraspStage`]).

mod check;
pub mod data;
mod error;
pub mod gripper;
mod marginal;
mod params;
mod planner;
mod sample;
pub mod stage;

pub use check::{GraspOutcome, check_grasp};
pub use error::GraspError;
pub use gripper::{Gripper, GripperError};
pub use marginal::{GraspField, MeanFieldError, MeanFieldParams, marginal_grasps};
pub use params::GraspParams;
pub use planner::{GraspObject, GraspObjects, GraspPlanner, OnnxGraspField, PlannedGrasp, isometry, judge};
pub use sample::{ObjectGrasp, SampledGrasps, sample_grasps};

/// The stage of this crate: `grasp` (Estimate in, Grasps out).
pub fn registrations() -> Vec<poseflow_runtime::Registration> {
    vec![poseflow_runtime::Registration::transform("grasp", |wiring| {
        let planner = GraspPlanner::load(GraspParams::from_json(&wiring.params)?)?;
        tracing::info!(
            model = %planner.params().model.display(),
            objects = ?planner.objects().ids(),
            hypotheses = planner.params().hypotheses,
            "grasp stage ready"
        );
        Ok::<_, poseflow_runtime::BuildError>(stage::GraspStage::new(planner))
    })]
}
