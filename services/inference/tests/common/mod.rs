//! The fixture model and its stored parity vectors, shared by the tests.

use std::collections::BTreeMap;
use std::path::PathBuf;

pub fn model_dir() -> PathBuf {
    PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/../../models/test-tiny"))
}

/// The stored tensors as f32 (i64 ones converted).
pub fn parity() -> BTreeMap<String, Vec<f32>> {
    parity_of(&model_dir())
}

/// The stored tensors of the model in `dir`.
pub fn parity_of(dir: &std::path::Path) -> BTreeMap<String, Vec<f32>> {
    poseflow_inference::parity::ParityVectors::read(dir).unwrap().expect("parity.json").into_map()
}

pub fn max_difference(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter().zip(b).map(|(x, y)| (x - y).abs()).fold(0.0, f32::max)
}
