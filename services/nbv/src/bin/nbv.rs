//! The next-best-view stage process: `exe = "nbv"` in a graph file (see
//! [`poseflow_nbv::registrations`]).

fn main() -> std::process::ExitCode {
    poseflow_runtime::run_registered(poseflow_nbv::registrations(), "nbv")
}
