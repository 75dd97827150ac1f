fn main() -> std::process::ExitCode {
    poseflow_runtime::run_sink(poseflow_smoke::CheckingSink::from_wiring)
}
