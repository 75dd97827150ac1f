//! The ingest stage process: `exe = "ingest"` in a graph file; Frame in,
//! Observation out.

fn main() -> std::process::ExitCode {
    poseflow_runtime::run_registered(poseflow_ingest::registrations(), "ingest")
}
