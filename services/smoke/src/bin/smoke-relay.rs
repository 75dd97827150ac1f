fn main() -> std::process::ExitCode {
    poseflow_runtime::run_transform(|_| Ok::<_, std::convert::Infallible>(poseflow_smoke::NegatingRelay))
}
