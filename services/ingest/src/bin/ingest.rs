//! The ingest stage process: `exe = "ingest"` in a graph file; Frame in,
//! Observation out.

use std::process::ExitCode;

use poseflow_ingest::IngestParams;
use poseflow_ingest::stage::IngestStage;

fn main() -> ExitCode {
    poseflow_runtime::init_logging();
    poseflow_runtime::run_transform(|wiring| -> Result<_, poseflow_runtime::BuildError> {
        IngestParams::from_json(&wiring.params).map(IngestStage::new).map_err(Into::into)
    })
}
