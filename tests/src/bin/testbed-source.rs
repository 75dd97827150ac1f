fn main() -> std::process::ExitCode {
    poseflow_runtime::run_source(poseflow_e2e::CountingSource::from_wiring)
}
