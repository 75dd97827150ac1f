fn main() -> std::process::ExitCode {
    poseflow_runtime::run_registered(poseflow_smoke::registrations(), "smoke-relay")
}
