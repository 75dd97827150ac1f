//! The grasp stage process: `exe = "grasp"` in a graph file (see
//! [`poseflow_grasp::registrations`]).

fn main() -> std::process::ExitCode {
    poseflow_runtime::run_registered(poseflow_grasp::registrations(), "grasp")
}
