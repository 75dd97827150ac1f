//! The `ros2-bridge` stage process (see the crate docs).

fn main() -> std::process::ExitCode {
    poseflow_runtime::run_registered(poseflow_ros2::registrations(), "ros2-bridge")
}
