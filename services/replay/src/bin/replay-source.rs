//! The replay source process: `exe = "replay-source"` in a graph file;
//! publishes a recording's messages of one edge.

fn main() -> std::process::ExitCode {
    poseflow_runtime::run_registered(poseflow_replay::registrations(), "replay-source")
}
