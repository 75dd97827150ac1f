//! The frame source process: `exe = "frame-source"` in a graph file;
//! publishes Frame messages from a BOP dataset or the renderer.

use std::process::ExitCode;

use poseflow_ingest::stage::{FrameSourceStage, frame_source};

fn main() -> ExitCode {
    poseflow_runtime::init_logging();
    poseflow_runtime::run_source(|wiring| -> Result<_, poseflow_runtime::BuildError> {
        frame_source(&wiring.params).map(FrameSourceStage::new).map_err(Into::into)
    })
}
