//! The inference stage process: `exe = "inference"` in a graph file;
//! Observation in, Condition handle out, velocity requests served.

use std::process::ExitCode;

use poseflow_inference::stage::{InferenceParams, InferenceStage};

fn main() -> ExitCode {
    poseflow_runtime::init_logging();
    poseflow_runtime::run_server(|wiring| -> Result<_, poseflow_runtime::BuildError> {
        let mut params = InferenceParams::from_json(&wiring.params)?;
        // A reader a full queue behind, with one handle in hand and one more
        // held for publishing, must still find its conditions cached.
        let in_flight = wiring.outputs.iter().map(|o| o.queue + 2).max().unwrap_or(0);
        if params.cache < in_flight {
            tracing::info!(cache = params.cache, in_flight, "cache raised to the conditions a reader can lag by");
            params.cache = in_flight;
        }
        let stage = InferenceStage::new(&params)?;
        tracing::info!(model = %stage.model_dir().display(), threads = params.threads, "model loaded");
        Ok(stage)
    })
}
