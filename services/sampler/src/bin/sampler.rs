//! The sampler stage process: `exe = "sampler"` in a graph file (see
//! [`poseflow_sampler::registrations`]).

fn main() -> std::process::ExitCode {
    poseflow_runtime::run_registered(poseflow_sampler::registrations(), "sampler")
}
