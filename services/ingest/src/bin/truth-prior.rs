//! The truth-prior stage process: `exe = "truth-prior"` in a graph file;
//! Observation in, Estimate (the perturbed ground truth) out.

fn main() -> std::process::ExitCode {
    poseflow_runtime::run_registered(poseflow_ingest::registrations(), "truth-prior")
}
