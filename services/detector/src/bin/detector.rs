//! The detector stage process: `exe = "detector"` in a graph file; Frame in,
//! Frame out with the detector's detections.

fn main() -> std::process::ExitCode {
    poseflow_runtime::run_registered(poseflow_detector::registrations(), "detector")
}
