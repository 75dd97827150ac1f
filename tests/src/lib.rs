//! What the end-to-end tests and their test stages share.

pub mod deadline;
pub mod harness;
pub mod recordings;

use poseflow_geometry::sampling::{seeded_rng, uniform_rotation};

/// `count` poses (R row-major, t in metres within 5 cm) fixed by the frame
/// and object: the test stage that calls the inference stage and the test
/// that checks its answers in-process use the same ones.
pub fn probe_poses(frame: u64, object: u32, count: usize) -> Vec<f32> {
    let mut rng = seeded_rng(frame * 1000 + u64::from(object));
    let mut poses = Vec::with_capacity(12 * count);
    for k in 0..count {
        let rotation = uniform_rotation(&mut rng);
        let m = rotation.matrix();
        for i in 0..3 {
            for j in 0..3 {
                poses.push(m[(i, j)] as f32);
            }
        }
        let s = k as f32 / count as f32 - 0.5;
        poses.extend([0.1 * s, -0.05 * s, 0.02]);
    }
    poses
}

/// The Python interpreter with iceoryx2's bindings that `deploy/setup`
/// installs (override with POSEFLOW_PYTHON).
pub fn plugin_python() -> std::path::PathBuf {
    let python = std::env::var_os("POSEFLOW_PYTHON").map(std::path::PathBuf::from).unwrap_or_else(|| {
        std::path::PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/../target/python-venv/bin/python"))
    });
    assert!(python.exists(), "{} missing: run deploy/setup first", python.display());
    python
}
