//! The inference stage process: `exe = "inference"` in a graph file (see
//! [`poseflow_inference::registrations`]).

fn main() -> std::process::ExitCode {
    poseflow_runtime::run_registered(poseflow_inference::registrations(), "inference")
}
