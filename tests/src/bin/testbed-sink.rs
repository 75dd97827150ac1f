fn main() -> std::process::ExitCode {
    poseflow_runtime::run_sink(poseflow_e2e::CheckingSink::from_wiring)
}
