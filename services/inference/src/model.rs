//! The two ONNX networks of a PoseFlow model directory and their contract
//! (`training/poseflow_train/export.py`), for B observations of G samples
//! each (M = B·G samples; samples b·G … (b+1)·G − 1 belong to observation b):
//!
//! - `encoder.onnx`: `image` [B,3,S,S] f32, `token_mask` [B,P·P] f32,
//!   `points` [B,N,3] f32, `object_index` [B] i64 → `condition` [B,T,D],
//!   `condition_mask` [B,T], and from `poseflow-onnx/2` on `cross_kv`
//!   [B,L,T,2D] (the keys then values of each of the velocity network's L
//!   cross-attention blocks over the condition tokens);
//! - `velocity.onnx`: `condition` [B,T,D], `condition_mask` [B,T],
//!   (`poseflow-onnx/2`) `cross_kv` [B,L,T,2D], `rotation` [M,3,3],
//!   `translation` [M,3] (metres, relative to the observed points' mean),
//!   `t` [M] → `v_rot` [M,3] (body frame), `v_pos` [M,3].
//!
//! `poseflow-onnx/1` (still served) has no `cross_kv`, so its velocity
//! network recomputes the keys and values at every Euler step, and takes one
//! observation per run (B = 1): a batch of several runs one by one.
//!
//! Metadata (ONNX `metadata_props`, JSON values) gives S, P, N, the
//! normalisation, the translation scale and noise, and the object ids.
//!
//! A **category-level** model (same ports) also has `categories` (`{code:
//! name}`: its `object_ids` are category codes, REAL275's) and `size_values`
//! (`[first, end)`: where in the last condition token its predicted size
//! lies, as extents / `translation_scale`).

use std::path::{Path, PathBuf};

use ort::session::Session;
use ort::value::{TensorElementType, TensorRef};
pub(crate) use poseflow_onnx::{check_ports, port};

use crate::InferenceError;

/// The contract versions this crate serves, oldest first: `metadata`
/// `contract` of an encoder names one.
pub const CONTRACTS: [&str; 2] = ["poseflow-onnx/1", "poseflow-onnx/2"];

/// What a model says about itself in its metadata.
#[derive(Debug, Clone, PartialEq)]
pub struct ModelInfo {
    pub image_size: usize,
    pub patch_grid: usize,
    pub point_count: usize,
    pub normalisation_mean: [f32; 3],
    pub normalisation_std: [f32; 3],
    /// Standard deviation (metres) of the flow's initial translations.
    pub translation_noise_std: f64,
    /// BOP object ids, in the order of `object_index`.
    pub object_ids: Vec<u32>,
    /// Condition tokens T and their width D.
    pub tokens: usize,
    pub width: usize,
    /// The contract version (1 or 2) of [`CONTRACTS`].
    pub contract: u32,
    /// Cross-attention blocks L whose keys and values the encoder caches
    /// (`poseflow-onnx/2`); 0 under `poseflow-onnx/1`.
    pub cached_blocks: usize,
    /// A category-level model's categories and size output; None for an
    /// instance-level model.
    pub categories: Option<CategoryHead>,
}

/// What a category-level model adds to its metadata.
#[derive(Debug, Clone, PartialEq)]
pub struct CategoryHead {
    /// (code, name) of each category, in `object_ids` order.
    pub names: Vec<(u32, String)>,
    /// Values [first, end) of the last condition token holding the size
    /// (box extents x, y, z) divided by `translation_scale`.
    pub size_values: (usize, usize),
    /// Metres per network translation unit.
    pub translation_scale: f32,
}

impl CategoryHead {
    /// The code of a category name.
    pub fn code(&self, name: &str) -> Option<u32> {
        self.names.iter().find(|(_, n)| n == name).map(|(code, _)| *code)
    }

    /// The size (metres) an encoded condition carries.
    pub fn size(&self, condition: &Condition, tokens: usize, width: usize) -> [f32; 3] {
        let last = &condition.tokens[(tokens - 1) * width..tokens * width];
        let (first, _) = self.size_values;
        std::array::from_fn(|i| last[first + i] * self.translation_scale)
    }
}

/// One observation's encoded condition, kept by the inference stage and
/// reused for every velocity request of that observation.
#[derive(Debug, Clone, PartialEq)]
pub struct Condition {
    /// T·D values, row-major.
    pub tokens: Vec<f32>,
    /// T values, 1 = attend.
    pub mask: Vec<f32>,
    /// L·T·2D values, row-major: the velocity network's cross-attention
    /// keys and values (`poseflow-onnx/2`); empty under `poseflow-onnx/1`.
    pub cross_kv: Vec<f32>,
    /// Which encoding this is (numbered by the model from 1); lets a batch
    /// of the same conditions be gathered once for all its Euler steps.
    /// 0: made elsewhere, gathered every time.
    pub serial: u64,
}

/// Which files of a model directory are served: the exported FP32 networks
/// (`encoder.onnx`, `velocity.onnx`) or their dynamic INT8 quantisation
/// (`encoder.int8.onnx`, `velocity.int8.onnx`, `poseflow_train.quantize`):
/// the same contract, weights in 7 bits and matrix products in integers.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Deserialize, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Precision {
    #[default]
    Fp32,
    Int8,
}

impl Precision {
    pub const ALL: [Precision; 2] = [Precision::Fp32, Precision::Int8];

    /// The encoder's and the velocity network's file names.
    pub fn files(self) -> [&'static str; 2] {
        match self {
            Precision::Fp32 => ["encoder.onnx", "velocity.onnx"],
            Precision::Int8 => ["encoder.int8.onnx", "velocity.int8.onnx"],
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            Precision::Fp32 => "fp32",
            Precision::Int8 => "int8",
        }
    }
}

impl std::str::FromStr for Precision {
    type Err = String;

    fn from_str(text: &str) -> Result<Self, String> {
        Self::ALL
            .into_iter()
            .find(|p| p.name() == text)
            .ok_or_else(|| format!("{text:?}: expected \"fp32\" or \"int8\""))
    }
}

/// One observation's encoder inputs (payload sections of an Observation).
#[derive(Debug, Clone, Copy)]
pub struct EncoderInput<'a> {
    /// 3·S·S values, channel-major, normalised.
    pub image: &'a [f32],
    /// P·P values, 1 = the patch shows the object.
    pub token_mask: &'a [f32],
    /// N·3 values, centred, metres.
    pub points: &'a [f32],
    pub object_index: usize,
}

/// Velocities of a batch: `v_rot` and `v_pos`, M·3 values each.
#[derive(Debug, Clone, PartialEq)]
pub struct Velocities {
    pub rotation: Vec<f32>,
    pub translation: Vec<f32>,
}

#[derive(Debug)]
pub struct PoseFlowModel {
    pub dir: PathBuf,
    pub info: ModelInfo,
    /// The files loaded.
    pub precision: Precision,
    encoder: Session,
    velocity: Session,
    /// A batch's inputs, gathered (reused between runs).
    gathered: Gathered,
    encodings: u64,
}

#[derive(Debug, Default)]
struct Gathered {
    /// The serials of the conditions in `tokens`, `mask` and `cross_kv`.
    conditions: Vec<u64>,
    image: Vec<f32>,
    token_mask: Vec<f32>,
    points: Vec<f32>,
    object_index: Vec<i64>,
    tokens: Vec<f32>,
    mask: Vec<f32>,
    cross_kv: Vec<f32>,
}

pub(crate) fn session(path: &Path, threads: usize) -> Result<Session, InferenceError> {
    Ok(poseflow_onnx::session(
        path,
        threads,
        "a PoseFlow model directory holds encoder.onnx and velocity.onnx, a grasp flow model grasp_encoder.onnx and grasp_velocity.onnx",
    )?)
}

/// The fixed token count T of a velocity network's `condition` input
/// (dimension 1), which the condition buffers are sized by.
pub(crate) fn condition_tokens(velocity: &Session, path: &Path) -> Result<i64, InferenceError> {
    velocity
        .inputs()
        .iter()
        .find(|o| o.name() == "condition")
        .and_then(|o| o.dtype().tensor_shape().and_then(|s| s.get(1).copied()))
        .filter(|&tokens| tokens > 0)
        .ok_or_else(|| InferenceError::Model {
            path: path.to_path_buf(),
            detail: "input `condition` needs a fixed token count (dimension 1)".into(),
        })
}

/// The two outputs every velocity network has: `v_rot` and `v_pos`, M × 3.
pub(crate) fn check_velocity_outputs(velocity: &Session, path: &Path) -> Result<(), InferenceError> {
    use TensorElementType::Float32 as F;
    Ok(check_ports(path, "outputs", velocity.outputs(), &[port("v_rot", F, &[-1, 3]), port("v_pos", F, &[-1, 3])])?)
}

/// A metadata value parsed as JSON into `T`.
pub(crate) fn meta<T: serde::de::DeserializeOwned>(
    session: &Session,
    path: &Path,
    key: &str,
) -> Result<T, InferenceError> {
    let bad = |detail: String| InferenceError::Model { path: path.to_path_buf(), detail };
    let metadata = session.metadata().map_err(|e| bad(e.to_string()))?;
    let text = metadata.custom(key).ok_or_else(|| bad(format!("metadata has no `{key}`")))?;
    serde_json::from_str(&text)
        .or_else(|_| serde_json::from_value(serde_json::Value::String(text.clone())))
        .map_err(|e| bad(format!("metadata `{key}` = {text:?}: {e}")))
}

/// A metadata value that may be absent.
fn optional_meta<T: serde::de::DeserializeOwned>(
    session: &Session,
    path: &Path,
    key: &str,
) -> Result<Option<T>, InferenceError> {
    let metadata =
        session.metadata().map_err(|e| InferenceError::Model { path: path.to_path_buf(), detail: e.to_string() })?;
    if metadata.custom(key).is_none() {
        return Ok(None);
    }
    meta(session, path, key).map(Some)
}

/// The category head a model's metadata declares, checked against its
/// object ids and token width.
fn category_head(
    encoder: &Session,
    path: &Path,
    object_ids: &[u32],
    width: usize,
) -> Result<Option<CategoryHead>, InferenceError> {
    let bad = |detail: String| InferenceError::Model { path: path.to_path_buf(), detail };
    let Some(names) = optional_meta::<std::collections::BTreeMap<String, String>>(encoder, path, "categories")? else {
        return Ok(None);
    };
    let mut pairs = Vec::new();
    for id in object_ids {
        let name = names
            .get(&id.to_string())
            .ok_or_else(|| bad(format!("metadata `categories` names no category for object id (code) {id}")))?;
        pairs.push((*id, name.clone()));
    }
    let (first, end): (usize, usize) = optional_meta(encoder, path, "size_values")?
        .ok_or_else(|| bad("metadata has `categories` but no `size_values`".into()))?;
    if end != first + 3 || end > width {
        return Err(bad(format!(
            "metadata `size_values` = [{first}, {end}): expected 3 values within the token width {width}"
        )));
    }
    let translation_scale: f32 = meta(encoder, path, "translation_scale")?;
    Ok(Some(CategoryHead { names: pairs, size_values: (first, end), translation_scale }))
}

/// An encoder and a velocity session from one model directory.
pub(crate) struct SessionPair {
    pub encoder: Session,
    pub encoder_path: PathBuf,
    pub velocity: Session,
    pub velocity_path: PathBuf,
}

/// Opens `<dir>/<files[0]>` (encoder) and `<dir>/<files[1]>` (velocity)
/// and checks that the encoder's metadata declares one of `contracts`;
/// returns the pair and the index of the declared contract.
pub(crate) fn open_pair(
    dir: &Path,
    files: [&str; 2],
    threads: usize,
    contracts: &[&str],
) -> Result<(SessionPair, usize), InferenceError> {
    let (encoder_path, velocity_path) = (dir.join(files[0]), dir.join(files[1]));
    let encoder = session(&encoder_path, threads)?;
    let velocity = session(&velocity_path, threads)?;
    let declared: String = meta(&encoder, &encoder_path, "contract")?;
    let Some(version) = contracts.iter().position(|&c| c == declared) else {
        return Err(InferenceError::Model {
            path: encoder_path,
            detail: format!("metadata `contract` = {declared:?}, this build serves {contracts:?}"),
        });
    };
    Ok((SessionPair { encoder, encoder_path, velocity, velocity_path }, version))
}

impl PoseFlowModel {
    /// Loads and checks `<dir>/encoder.onnx` and `<dir>/velocity.onnx`.
    pub fn load(dir: &Path, threads: usize) -> Result<Self, InferenceError> {
        Self::load_as(dir, threads, Precision::Fp32)
    }

    /// Loads and checks the networks of `precision` in `dir`.
    pub fn load_as(dir: &Path, threads: usize, precision: Precision) -> Result<Self, InferenceError> {
        let (SessionPair { encoder, encoder_path, velocity, velocity_path }, version) =
            open_pair(dir, precision.files(), threads, &CONTRACTS)?;
        let contract = version as u32 + 1;
        let (s, p, n): (i64, i64, i64) = (
            meta(&encoder, &encoder_path, "image_size")?,
            meta(&encoder, &encoder_path, "patch_grid")?,
            meta(&encoder, &encoder_path, "point_count")?,
        );
        let width: i64 = meta(&encoder, &encoder_path, "width")?;
        use TensorElementType::{Float32 as F, Int64 as I};
        check_ports(
            &encoder_path,
            "inputs",
            encoder.inputs(),
            &[
                port("image", F, &[-1, 3, s, s]),
                port("token_mask", F, &[-1, p * p]),
                port("points", F, &[-1, n, 3]),
                port("object_index", I, &[-1]),
            ],
        )?;
        let mut encoder_outputs = vec![port("condition", F, &[-1, -1, width]), port("condition_mask", F, &[-1, -1])];
        if contract >= 2 {
            encoder_outputs.push(port("cross_kv", F, &[-1, -1, -1, 2 * width]));
        }
        check_ports(&encoder_path, "outputs", encoder.outputs(), &encoder_outputs)?;
        let t_dim = condition_tokens(&velocity, &velocity_path)?;
        let cached_blocks = if contract >= 2 { cross_kv_blocks(&velocity, &velocity_path)? } else { 0 };
        let observations = if contract >= 2 { -1 } else { 1 };
        let mut velocity_inputs = vec![
            port("condition", F, &[observations, t_dim, width]),
            port("condition_mask", F, &[observations, t_dim]),
        ];
        if contract >= 2 {
            velocity_inputs.push(port("cross_kv", F, &[-1, cached_blocks as i64, t_dim, 2 * width]));
        }
        velocity_inputs.extend([
            port("rotation", F, &[-1, 3, 3]),
            port("translation", F, &[-1, 3]),
            port("t", F, &[-1]),
        ]);
        check_ports(&velocity_path, "inputs", velocity.inputs(), &velocity_inputs)?;
        check_velocity_outputs(&velocity, &velocity_path)?;
        let object_ids: Vec<u32> = meta(&encoder, &encoder_path, "object_ids")?;
        let categories = category_head(&encoder, &encoder_path, &object_ids, width as usize)?;
        let info = ModelInfo {
            image_size: s as usize,
            patch_grid: p as usize,
            point_count: n as usize,
            normalisation_mean: meta(&encoder, &encoder_path, "normalisation_mean")?,
            normalisation_std: meta(&encoder, &encoder_path, "normalisation_std")?,
            translation_noise_std: meta(&encoder, &encoder_path, "translation_noise_std")?,
            object_ids,
            tokens: t_dim as usize,
            width: width as usize,
            contract,
            cached_blocks,
            categories,
        };
        Ok(Self {
            dir: dir.to_path_buf(),
            info,
            precision,
            encoder,
            velocity,
            gathered: Gathered::default(),
            encodings: 0,
        })
    }

    /// Index of a BOP object id for `object_index`.
    pub fn object_index(&self, obj_id: u32) -> Option<usize> {
        self.info.object_ids.iter().position(|&id| id == obj_id)
    }

    /// Encodes one observation (payload sections of an Observation).
    pub fn encode(
        &mut self,
        image: &[f32],
        token_mask: &[f32],
        points: &[f32],
        object_index: usize,
    ) -> Result<Condition, InferenceError> {
        let mut conditions = self.encode_batch(&[EncoderInput { image, token_mask, points, object_index }])?;
        Ok(conditions.pop().expect("one condition per input"))
    }

    /// Encodes several observations in one run of the encoder (batch B);
    /// each condition equals the one its observation gets alone.
    pub fn encode_batch(&mut self, inputs: &[EncoderInput<'_>]) -> Result<Vec<Condition>, InferenceError> {
        let (s, p, n) = (self.info.image_size, self.info.patch_grid, self.info.point_count);
        let b = inputs.len();
        if b == 0 {
            return Ok(Vec::new());
        }
        let run_error = |e: ort::Error| InferenceError::Run { model: "encoder", detail: e.to_string() };
        let g = &mut self.gathered;
        g.image.clear();
        g.token_mask.clear();
        g.points.clear();
        g.object_index.clear();
        for input in inputs {
            g.image.extend_from_slice(input.image);
            g.token_mask.extend_from_slice(input.token_mask);
            g.points.extend_from_slice(input.points);
            g.object_index.push(input.object_index as i64);
        }
        let outputs = self
            .encoder
            .run(ort::inputs![
                "image" => TensorRef::from_array_view(([b, 3, s, s], &g.image[..])).map_err(run_error)?,
                "token_mask" => TensorRef::from_array_view(([b, p * p], &g.token_mask[..])).map_err(run_error)?,
                "points" => TensorRef::from_array_view(([b, n, 3], &g.points[..])).map_err(run_error)?,
                "object_index" => TensorRef::from_array_view(([b], &g.object_index[..])).map_err(run_error)?,
            ])
            .map_err(run_error)?;
        let (_, tokens) = outputs["condition"].try_extract_tensor::<f32>().map_err(run_error)?;
        let (_, mask) = outputs["condition_mask"].try_extract_tensor::<f32>().map_err(run_error)?;
        let cross_kv = match self.info.contract {
            1 => &[][..],
            _ => outputs["cross_kv"].try_extract_tensor::<f32>().map_err(run_error)?.1,
        };
        let per = |values: &[f32]| values.len() / b;
        let (tokens_per, mask_per, kv_per) = (per(tokens), per(mask), per(cross_kv));
        let first = self.encodings + 1;
        self.encodings += b as u64;
        Ok((0..b)
            .map(|i| Condition {
                tokens: tokens[i * tokens_per..(i + 1) * tokens_per].to_vec(),
                mask: mask[i * mask_per..(i + 1) * mask_per].to_vec(),
                cross_kv: cross_kv[i * kv_per..(i + 1) * kv_per].to_vec(),
                serial: first + i as u64,
            })
            .collect())
    }

    /// Velocities for M poses (`rotations` M·9 row-major, `translations` M·3,
    /// `t` M) under one condition.
    pub fn velocity(
        &mut self,
        condition: &Condition,
        rotations: &[f32],
        translations: &[f32],
        t: &[f32],
    ) -> Result<Velocities, InferenceError> {
        self.velocity_batch(&[condition], rotations, translations, t)
    }

    /// Velocities for the samples of several observations in one run of
    /// the velocity network (`poseflow-onnx/2`; one run per observation
    /// under `poseflow-onnx/1`): M = B·G poses, the G samples of
    /// `conditions[b]` at rows b·G … (b+1)·G − 1, as in [`Self::velocity`].
    pub fn velocity_batch(
        &mut self,
        conditions: &[&Condition],
        rotations: &[f32],
        translations: &[f32],
        t: &[f32],
    ) -> Result<Velocities, InferenceError> {
        let (b, m) = (conditions.len(), t.len());
        if b == 0 || m % b != 0 || rotations.len() != 9 * m || translations.len() != 3 * m {
            return Err(InferenceError::Run {
                model: "velocity",
                detail: format!(
                    "{b} conditions, {} rotation, {} translation and {m} time values: expected B × G samples (9, 3 and 1 values each) for B ≥ 1 conditions",
                    rotations.len(),
                    translations.len()
                ),
            });
        }
        if self.info.contract == 1 && b > 1 {
            let g = m / b;
            let mut all = Velocities { rotation: Vec::with_capacity(3 * m), translation: Vec::with_capacity(3 * m) };
            for (i, condition) in conditions.iter().enumerate() {
                let part = self.velocity_batch(
                    &[condition],
                    &rotations[9 * g * i..9 * g * (i + 1)],
                    &translations[3 * g * i..3 * g * (i + 1)],
                    &t[g * i..g * (i + 1)],
                )?;
                all.rotation.extend(part.rotation);
                all.translation.extend(part.translation);
            }
            return Ok(all);
        }
        let (tk, d, l) = (self.info.tokens, self.info.width, self.info.cached_blocks);
        let run_error = |e: ort::Error| InferenceError::Run { model: "velocity", detail: e.to_string() };
        // One condition is read in place; several are gathered, once for
        // all the Euler steps of the same batch.
        let (tokens, mask, cross_kv) = match conditions {
            [one] => (&one.tokens[..], &one.mask[..], &one.cross_kv[..]),
            _ => {
                let g = &mut self.gathered;
                let same = conditions.iter().all(|c| c.serial != 0)
                    && g.conditions.iter().copied().eq(conditions.iter().map(|c| c.serial));
                if !same {
                    g.conditions.clear();
                    g.tokens.clear();
                    g.mask.clear();
                    g.cross_kv.clear();
                    for condition in conditions {
                        g.conditions.push(condition.serial);
                        g.tokens.extend_from_slice(&condition.tokens);
                        g.mask.extend_from_slice(&condition.mask);
                        g.cross_kv.extend_from_slice(&condition.cross_kv);
                    }
                }
                (&g.tokens[..], &g.mask[..], &g.cross_kv[..])
            }
        };
        let sizes = [(tokens.len(), b * tk * d), (mask.len(), b * tk), (cross_kv.len(), b * l * tk * 2 * d)];
        if sizes.iter().any(|&(found, expected)| found != expected) {
            return Err(InferenceError::Run {
                model: "velocity",
                detail: format!(
                    "conditions hold {} token, {} mask and {} cross_kv values, expected {} (B = {b} of T = {tk}, D = {d}, L = {l})",
                    tokens.len(),
                    mask.len(),
                    cross_kv.len(),
                    b * tk * d
                ),
            });
        }
        let mut inputs = ort::inputs![
            "condition" => TensorRef::from_array_view(([b, tk, d], tokens)).map_err(run_error)?,
            "condition_mask" => TensorRef::from_array_view(([b, tk], mask)).map_err(run_error)?,
            "rotation" => TensorRef::from_array_view(([m, 3, 3], rotations)).map_err(run_error)?,
            "translation" => TensorRef::from_array_view(([m, 3], translations)).map_err(run_error)?,
            "t" => TensorRef::from_array_view(([m], t)).map_err(run_error)?,
        ];
        if self.info.contract >= 2 {
            inputs.push((
                "cross_kv".into(),
                TensorRef::from_array_view(([b, l, tk, 2 * d], cross_kv)).map_err(run_error)?.into(),
            ));
        }
        let outputs = self.velocity.run(inputs).map_err(run_error)?;
        let (_, rotation) = outputs["v_rot"].try_extract_tensor::<f32>().map_err(run_error)?;
        let (_, translation) = outputs["v_pos"].try_extract_tensor::<f32>().map_err(run_error)?;
        Ok(Velocities { rotation: rotation.to_vec(), translation: translation.to_vec() })
    }
}

impl PoseFlowModel {
    /// Velocities for runs of samples of different lengths, each under its
    /// condition (`segments`: the condition and its sample count, in the
    /// order of the samples): one network run for all of them, shorter runs
    /// padded to the longest with identity poses whose velocities are
    /// dropped (a sample attends only to its own tokens and its
    /// observation's condition, so padding changes no other sample).
    pub fn velocity_segments(
        &mut self,
        segments: &[(&Condition, usize)],
        rotations: &[f32],
        translations: &[f32],
        t: &[f32],
    ) -> Result<Velocities, InferenceError> {
        let m: usize = segments.iter().map(|&(_, count)| count).sum();
        let longest = segments.iter().map(|&(_, count)| count).max().unwrap_or(0);
        if m != t.len() || rotations.len() != 9 * m || translations.len() != 3 * m || longest == 0 {
            return Err(InferenceError::Run {
                model: "velocity",
                detail: format!(
                    "segments of {m} samples in all, {} rotation, {} translation and {} time values: expected 9, 3 and 1 per sample, at least one sample",
                    rotations.len(),
                    translations.len(),
                    t.len()
                ),
            });
        }
        let conditions: Vec<&Condition> = segments.iter().map(|&(condition, _)| condition).collect();
        if segments.iter().all(|&(_, count)| count == longest) {
            return self.velocity_batch(&conditions, rotations, translations, t);
        }
        let (mut r, mut p, mut times) = (Vec::new(), Vec::new(), Vec::new());
        let mut start = 0;
        for &(_, count) in segments {
            let samples = start..start + count;
            r.extend_from_slice(&rotations[9 * samples.start..9 * samples.end]);
            p.extend_from_slice(&translations[3 * samples.start..3 * samples.end]);
            times.extend_from_slice(&t[samples]);
            let padding = longest - count;
            r.extend((0..padding).flat_map(|_| [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]));
            p.extend(std::iter::repeat_n(0.0, 3 * padding));
            times.extend(std::iter::repeat_n(0.0, padding));
            start += count;
        }
        let padded = self.velocity_batch(&conditions, &r, &p, &times)?;
        let mut out = Velocities { rotation: Vec::with_capacity(3 * m), translation: Vec::with_capacity(3 * m) };
        for (i, &(_, count)) in segments.iter().enumerate() {
            let rows = 3 * i * longest..3 * (i * longest + count);
            out.rotation.extend_from_slice(&padded.rotation[rows.clone()]);
            out.translation.extend_from_slice(&padded.translation[rows]);
        }
        Ok(out)
    }
}

/// The block count L of a `poseflow-onnx/2` velocity network's `cross_kv`
/// input (dimension 1).
fn cross_kv_blocks(velocity: &Session, path: &Path) -> Result<usize, InferenceError> {
    velocity
        .inputs()
        .iter()
        .find(|o| o.name() == "cross_kv")
        .and_then(|o| o.dtype().tensor_shape().and_then(|s| s.get(1).copied()))
        .filter(|&blocks| blocks > 0)
        .map(|blocks| blocks as usize)
        .ok_or_else(|| InferenceError::Model {
            path: path.to_path_buf(),
            detail: "poseflow-onnx/2: input `cross_kv` [B, L, T, 2D] needs a fixed block count L (dimension 1)".into(),
        })
}
