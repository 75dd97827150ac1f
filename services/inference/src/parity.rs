//! The parity vectors an export stores beside a model (`parity.json`, an
//! index of named tensors, and `parity.bin`, their little-endian values),
//! and how far a model's INT8 networks move from the FP32 outputs stored
//! there: quantised products that overflow on a CPU (ONNX Runtime's u8 × s8
//! kernels on x86 without VNNI, for full 8-bit weights) move them by far
//! more than quantisation does.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use crate::{Condition, EncoderInput, InferenceError, PoseFlowModel};

#[derive(serde::Deserialize)]
struct Entry {
    shape: Vec<usize>,
    dtype: String,
    offset: usize,
}

/// Named tensors of a model directory's `parity.bin`, as `f32` (`i64`
/// values converted), row-major in the shapes `parity.json` gives.
#[derive(Debug, Clone)]
pub struct ParityVectors {
    tensors: BTreeMap<String, Vec<f32>>,
    index: PathBuf,
}

impl ParityVectors {
    /// Reads `<dir>/parity.json` and `<dir>/parity.bin`; `None` when the
    /// directory has no `parity.json`.
    pub fn read(dir: &Path) -> Result<Option<Self>, InferenceError> {
        let index = dir.join("parity.json");
        if !index.is_file() {
            return Ok(None);
        }
        let bad = |path: &Path, detail: String| InferenceError::Model { path: path.to_path_buf(), detail };
        let text = std::fs::read_to_string(&index).map_err(|e| bad(&index, e.to_string()))?;
        let entries: BTreeMap<String, Entry> = serde_json::from_str(&text)
            .map_err(|e| bad(&index, format!("{e}: expected {{name: {{shape, dtype, offset}}}}")))?;
        let blob_path = dir.join("parity.bin");
        let blob = std::fs::read(&blob_path).map_err(|e| bad(&blob_path, e.to_string()))?;
        let mut tensors = BTreeMap::new();
        for (name, entry) in entries {
            let count: usize = entry.shape.iter().product();
            let width = match entry.dtype.as_str() {
                "f32" => 4,
                "i64" => 8,
                other => return Err(bad(&index, format!("`{name}`.dtype = {other:?}, expected \"f32\" or \"i64\""))),
            };
            let bytes =
                entry.offset.checked_add(width * count).and_then(|end| blob.get(entry.offset..end)).ok_or_else(
                    || {
                        bad(
                            &index,
                            format!(
                                "`{name}` ({count} values from byte {}) lies beyond parity.bin's {} bytes",
                                entry.offset,
                                blob.len()
                            ),
                        )
                    },
                )?;
            let values = match width {
                4 => bytes.chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect(),
                _ => bytes
                    .chunks_exact(8)
                    .map(|b| i64::from_le_bytes([b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]]) as f32)
                    .collect(),
            };
            tensors.insert(name, values);
        }
        Ok(Some(Self { tensors, index }))
    }

    /// The tensor `name`, or an error naming `parity.json` and the tensor.
    pub fn get(&self, name: &str) -> Result<&[f32], InferenceError> {
        self.tensors
            .get(name)
            .map(Vec::as_slice)
            .ok_or_else(|| InferenceError::Model { path: self.index.clone(), detail: format!("no tensor `{name}`") })
    }

    pub fn into_map(self) -> BTreeMap<String, Vec<f32>> {
        self.tensors
    }
}

/// How far a model's outputs are from the stored FP32 ones: for each
/// output, the largest absolute difference as a share of the largest
/// stored magnitude (scale-free, so an untrained fixture and a trained
/// model share one limit).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OutputDrift {
    /// Encoder: condition tokens.
    pub tokens: f32,
    /// Velocity network: angular velocity.
    pub v_rot: f32,
    /// Velocity network: linear velocity.
    pub v_pos: f32,
}

impl OutputDrift {
    /// Dynamic quantisation with 7-bit weights moves the shipped models'
    /// outputs by at most about 3 % of their range; the 8-bit files that
    /// overflowed on a CPU without VNNI moved them by 9–20 %.
    pub const INT8_LIMITS: OutputDrift = OutputDrift { tokens: 0.05, v_rot: 0.05, v_pos: 0.05 };

    pub fn within(&self, limits: &OutputDrift) -> bool {
        self.tokens < limits.tokens && self.v_rot < limits.v_rot && self.v_pos < limits.v_pos
    }
}

/// `max |a − reference|` over `max |reference|`; infinite for a length mismatch.
fn relative_difference(a: &[f32], reference: &[f32]) -> f32 {
    if a.len() != reference.len() {
        return f32::INFINITY;
    }
    let largest = reference.iter().fold(0.0f32, |m, x| m.max(x.abs())).max(f32::MIN_POSITIVE);
    a.iter().zip(reference).map(|(x, y)| (x - y).abs()).fold(0.0, f32::max) / largest
}

/// How far `model`'s outputs are from the stored ones: the encoder on the
/// stored observations (B of them, encoded as one batch), the velocity
/// network on the stored condition tokens with the encoder's cached keys
/// and values, for the stored poses (B × G of them).
pub fn output_drift(model: &mut PoseFlowModel, parity: &ParityVectors) -> Result<OutputDrift, InferenceError> {
    let object_index = parity.get("object_index")?;
    let b = object_index.len();
    let part = |name: &str, i: usize| -> Result<&[f32], InferenceError> {
        let values = parity.get(name)?;
        let per = values.len() / b.max(1);
        Ok(&values[i * per..(i + 1) * per])
    };
    let inputs = (0..b)
        .map(|i| {
            Ok(EncoderInput {
                image: part("image", i)?,
                token_mask: part("token_mask", i)?,
                points: part("points", i)?,
                object_index: object_index[i] as usize,
            })
        })
        .collect::<Result<Vec<_>, InferenceError>>()?;
    let conditions = model.encode_batch(&inputs)?;
    let tokens: Vec<f32> = conditions.iter().flat_map(|c| c.tokens.iter().copied()).collect();
    let stored = (0..b)
        .map(|i| {
            Ok(Condition {
                tokens: part("condition", i)?.to_vec(),
                mask: part("condition_mask", i)?.to_vec(),
                cross_kv: conditions[i].cross_kv.clone(),
                serial: 0,
            })
        })
        .collect::<Result<Vec<_>, InferenceError>>()?;
    let all: Vec<&Condition> = stored.iter().collect();
    let out = model.velocity_batch(&all, parity.get("rotation")?, parity.get("translation")?, parity.get("t")?)?;
    Ok(OutputDrift {
        tokens: relative_difference(&tokens, parity.get("condition")?),
        v_rot: relative_difference(&out.rotation, parity.get("v_rot")?),
        v_pos: relative_difference(&out.translation, parity.get("v_pos")?),
    })
}
