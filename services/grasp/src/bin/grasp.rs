//! The grasp stage process: `exe = "grasp"` in a graph file; Estimate in,
//! Grasps out.

use std::process::ExitCode;

use poseflow_grasp::stage::GraspStage;
use poseflow_grasp::{GraspParams, GraspPlanner};

fn main() -> ExitCode {
    poseflow_runtime::run_transform(|wiring| -> Result<_, poseflow_runtime::BuildError> {
        let params = GraspParams::from_json(&wiring.params)?;
        let planner = GraspPlanner::load(params)?;
        tracing::info!(
            model = %planner.params().model.display(),
            objects = ?planner.objects().ids(),
            hypotheses = planner.params().hypotheses,
            "grasp stage ready"
        );
        Ok(GraspStage::new(planner))
    })
}
