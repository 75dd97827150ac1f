//! The ingest stage process: `exe = "ingest"` in a graph file.

use std::process::ExitCode;

use poseflow_ingest::stage::IngestSource;

fn main() -> ExitCode {
    poseflow_runtime::init_logging();
    poseflow_runtime::run_source(|wiring| IngestSource::from_params(&wiring.params).map_err(|e| e.to_string()))
}
