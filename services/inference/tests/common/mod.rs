//! The fixture model and its stored parity vectors, shared by the tests.

use std::collections::BTreeMap;
use std::path::PathBuf;

pub fn model_dir() -> PathBuf {
    PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/../../models/test-tiny"))
}

#[derive(serde::Deserialize)]
struct Entry {
    shape: Vec<usize>,
    dtype: String,
    offset: usize,
}

/// The stored tensors as f32 (i64 ones converted).
pub fn parity() -> BTreeMap<String, Vec<f32>> {
    parity_of(&model_dir())
}

/// The stored tensors of the model in `dir`.
pub fn parity_of(dir: &std::path::Path) -> BTreeMap<String, Vec<f32>> {
    let index: BTreeMap<String, Entry> =
        serde_json::from_str(&std::fs::read_to_string(dir.join("parity.json")).unwrap()).unwrap();
    let blob = std::fs::read(dir.join("parity.bin")).unwrap();
    index
        .into_iter()
        .map(|(name, e)| {
            let count: usize = e.shape.iter().product();
            let values = match e.dtype.as_str() {
                "f32" => blob[e.offset..e.offset + 4 * count]
                    .chunks_exact(4)
                    .map(|b| f32::from_le_bytes(b.try_into().unwrap()))
                    .collect(),
                "i64" => blob[e.offset..e.offset + 8 * count]
                    .chunks_exact(8)
                    .map(|b| i64::from_le_bytes(b.try_into().unwrap()) as f32)
                    .collect(),
                other => panic!("dtype {other}"),
            };
            (name, values)
        })
        .collect()
}

pub fn max_difference(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter().zip(b).map(|(x, y)| (x - y).abs()).fold(0.0, f32::max)
}
