//! The truth-prior stage process: `exe = "truth-prior"` in a graph file;
//! Observation in, Estimate (the perturbed ground truth) out.

use std::process::ExitCode;

use poseflow_ingest::truth_prior::{TruthPriorParams, TruthPriorStage};

fn main() -> ExitCode {
    poseflow_runtime::init_logging();
    poseflow_runtime::run_transform(|wiring| -> Result<_, poseflow_runtime::BuildError> {
        TruthPriorParams::from_json(&wiring.params).and_then(TruthPriorStage::new).map_err(Into::into)
    })
}
