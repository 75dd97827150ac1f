//! The frame source process: `exe = "frame-source"` in a graph file;
//! publishes Frame messages from a BOP dataset or the renderer.

fn main() -> std::process::ExitCode {
    poseflow_runtime::run_registered(poseflow_ingest::registrations(), "frame-source")
}
