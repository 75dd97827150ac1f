//! The next-best-view stage process: `exe = "nbv"` in a graph file;
//! Estimate in, NextView out.

use std::process::ExitCode;

use poseflow_nbv::stage::NbvStage;
use poseflow_nbv::{NbvParams, NbvPlanner};

fn main() -> ExitCode {
    poseflow_runtime::run_transform(|wiring| {
        let params = NbvParams::from_json(&wiring.params).map_err(|e| e.to_string())?;
        let planner = NbvPlanner::load(params).map_err(|e| e.to_string())?;
        let params = planner.params();
        tracing::info!(
            model = %params.inference.model.display(),
            objects = ?planner.object_ids(),
            candidates = params.sphere.candidates,
            hypotheses = params.hypotheses,
            workers = params.workers,
            "next-best-view stage ready"
        );
        Ok(NbvStage::new(planner))
    })
}
