fn main() -> std::process::ExitCode {
    poseflow_runtime::run_transform(|_| Ok(poseflow_smoke::NegatingRelay))
}
