//! The inference stage process: `exe = "inference"` in a graph file;
//! Observation in, Condition handle out, velocity requests served.

use std::process::ExitCode;

use poseflow_inference::stage::{InferenceParams, InferenceStage};

fn main() -> ExitCode {
    poseflow_runtime::init_logging();
    poseflow_runtime::run_server(|wiring| {
        let params = InferenceParams::from_json(&wiring.params).map_err(|e| e.to_string())?;
        let stage = InferenceStage::new(&params).map_err(|e| e.to_string())?;
        tracing::info!(model = %stage.model_dir().display(), threads = params.threads, "model loaded");
        Ok(stage)
    })
}
