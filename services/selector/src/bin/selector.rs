//! The selector stage process: `exe = "selector"` in a graph file (see
//! [`poseflow_selector::registrations`]).

fn main() -> std::process::ExitCode {
    poseflow_runtime::run_registered(poseflow_selector::registrations(), "selector")
}
