//! Every built-in stage, by the executable name graph files give in `exe`.
//! A new service crate adds its `registrations()` here.

use poseflow_runtime::Registry;

/// The registry of the built-in stages.
pub fn registry() -> Registry {
    Registry::new()
        .with(poseflow_smoke::registrations())
        .with(poseflow_replay::registrations())
        .with(poseflow_ingest::registrations())
        .with(poseflow_detector::registrations())
        .with(poseflow_inference::registrations())
        .with(poseflow_sampler::registrations())
        .with(poseflow_selector::registrations())
        .with(poseflow_grasp::registrations())
        .with(poseflow_nbv::registrations())
        .with(poseflow_ros2::registrations())
}

#[cfg(test)]
mod tests {
    /// Every `services/*/src/bin/NAME.rs` is a stage binary, except the
    /// command line itself and the Zenoh bridge, which `poseflow run --host`
    /// starts beside a host's stages and no graph file names.
    #[test]
    fn every_stage_binary_of_the_workspace_is_registered() {
        let registry = super::registry();
        let services = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).parent().expect("services/");
        let mut binaries = Vec::new();
        for crate_dir in std::fs::read_dir(services).expect("services/ is readable") {
            let bin_dir = crate_dir.expect("a directory entry").path().join("src/bin");
            for file in std::fs::read_dir(&bin_dir).into_iter().flatten() {
                let path = file.expect("a directory entry").path();
                binaries.push(path.file_stem().and_then(|s| s.to_str()).expect("a UTF-8 name").to_string());
            }
        }
        assert!(binaries.len() >= 12, "found only {binaries:?}");
        for exe in binaries.iter().filter(|exe| exe.as_str() != poseflow_graph::BRIDGE_EXE) {
            assert!(registry.get(exe).is_some(), "stage binary {exe} is not in the registry");
        }
    }
}
