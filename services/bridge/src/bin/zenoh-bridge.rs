//! The Zenoh bridge process. `poseflow run --graph G --host NAME` starts one
//! beside that host's stages when edges cross hosts; it is not named in
//! graph files.

fn main() -> std::process::ExitCode {
    poseflow_runtime::init_logging();
    match poseflow_bridge::run_from_env() {
        Ok(counts) => {
            tracing::info!(sent = counts.sent, received = counts.received, lost = counts.lost, "bridge finished");
            std::process::ExitCode::SUCCESS
        }
        Err(err) => {
            tracing::error!(err = %poseflow_runtime::error_chain(&err), "bridge failed");
            std::process::ExitCode::FAILURE
        }
    }
}
