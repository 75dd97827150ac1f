fn main() -> std::process::ExitCode {
    poseflow_runtime::run_source(poseflow_smoke::CountingSource::from_wiring)
}
