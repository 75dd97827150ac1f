//! The next-best-view stage process: `exe = "nbv"` in a graph file;
//! Estimate in, NextView out; the Frames as a side input (`side_inputs`)
//! let it judge what hides the object from each candidate.

use std::process::ExitCode;

use poseflow_graph::StageWiring;
use poseflow_nbv::stage::NbvStage;
use poseflow_nbv::{NbvParams, NbvPlanner};
use poseflow_runtime::BuildError;

fn make(wiring: &StageWiring) -> Result<NbvStage, BuildError> {
    let params = NbvParams::from_json(&wiring.params)?;
    let planner = NbvPlanner::load(params)?;
    let params = planner.params();
    tracing::info!(
        model = %params.inference.model.display(),
        objects = ?planner.object_ids(),
        candidates = params.sphere.candidates,
        hypotheses = params.hypotheses,
        workers = params.workers,
        occluders = !wiring.side_inputs.is_empty(),
        "next-best-view stage ready"
    );
    Ok(NbvStage::new(planner))
}

fn main() -> ExitCode {
    poseflow_runtime::run_transform_or_joined(make)
}
