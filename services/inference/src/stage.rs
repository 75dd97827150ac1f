//! The inference stage: Observation in, Condition handle out, velocity
//! requests answered.
//!
//! Each Observation is encoded once; its condition tokens stay in this
//! process under a `condition_id` that the handle carries to the sampler,
//! which then asks for the velocities of all its samples at each Euler step
//! by request-response. Only the handle and the poses cross shared memory,
//! never the tokens.
//!
//! Parameters (graph `params` over `config/inference.toml`):
//!
//! | key | meaning | default |
//! |---|---|---|
//! | `model` | directory with `encoder.onnx` and `velocity.onnx` | `models/poseflow-lmo10` |
//! | `precision` | `fp32` (`encoder.onnx`, `velocity.onnx`) or `int8` (`encoder.int8.onnx`, `velocity.int8.onnx`; FP32 is served instead, with a warning, when their outputs on `parity.bin` drift on this CPU) | `fp32` |
//! | `threads` | ONNX Runtime intra-op threads per network | 2 |
//! | `cache` | conditions kept (oldest dropped first); the process raises it to what a reader can hold (its queue, a batch, one in hand) | 8 |
//! | `batch` | most observations of one frame encoded in one run of the encoder | 1 |
//! | `encode` | `on-arrival`: each Observation is encoded when it comes; `on-request`: when the first velocity request names its handle, so one the sampler asks nothing for (a held track between network passes) costs no encoder run | `on-arrival` |
//!
//! Batching: the Observations of one frame (the ingest stage marks all but
//! the last `MORE_IN_FRAME`) are encoded in one run of the encoder, at most
//! `batch` at a time ([`FrameBatches`]). On request, the observations a
//! velocity request names that are not yet encoded are encoded in one run.

use std::collections::{BTreeMap, VecDeque};
use std::path::{Path, PathBuf};

use poseflow_contracts::status as velocity_status;
use poseflow_contracts::{
    ConditionHandle, Header, ObjectCategory, ObservationHeader, POSE_LEN, StampSlot, VELOCITY_LEN, VelocityRequest,
    VelocityResponse, VelocitySegment,
};
use poseflow_runtime::{Emitter, Flush, FrameBatches, Input, Server, Transform};
use serde::Deserialize;

use crate::parity::{OutputDrift, ParityVectors, output_drift};
use crate::{CategoryHead, Condition, EncoderInput, InferenceError, PoseFlowModel, Precision};

/// The stage's parameters.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct InferenceParams {
    #[serde(default = "default_model")]
    pub model: PathBuf,
    #[serde(default)]
    pub precision: Precision,
    #[serde(default = "default_threads")]
    pub threads: usize,
    #[serde(default = "default_cache")]
    pub cache: usize,
    #[serde(default = "default_batch")]
    pub batch: usize,
    /// A category-level model's class of each object id: a JSON file
    /// `{"<obj_id>": {"category": "<name>", ...}}` (the `categories.json` of
    /// `poseflow generate-objects`). Without it a category model reads each
    /// object id as a category code.
    #[serde(default)]
    pub classes: Option<PathBuf>,
    #[serde(default)]
    pub encode: EncodeWhen,
}

/// When an observation is encoded ([`InferenceParams::encode`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum EncodeWhen {
    /// As it arrives (in its frame's batch), before its handle is sent.
    #[default]
    OnArrival,
    /// At the first velocity request that names it: the handle goes out at
    /// once, and an observation nobody asks velocities for is never
    /// encoded. A category-level model cannot: its handle carries the
    /// encoder's predicted size.
    OnRequest,
}

fn default_model() -> PathBuf {
    PathBuf::from("models/poseflow-lmo10")
}
fn default_threads() -> usize {
    2
}
fn default_cache() -> usize {
    8
}
fn default_batch() -> usize {
    8
}

impl InferenceParams {
    /// Reads the graph's `params`, naming the key that is wrong.
    pub fn from_json(value: &serde_json::Value) -> Result<Self, InferenceError> {
        let params: Self = serde_json::from_value(value.clone())
            .map_err(|e| InferenceError::Params { key: "inference".into(), detail: e.to_string() })?;
        if !(1..=64).contains(&params.threads) {
            return Err(InferenceError::Params {
                key: "threads".into(),
                detail: format!("{}: expected 1 to 64", params.threads),
            });
        }
        if params.cache == 0 {
            return Err(InferenceError::Params { key: "cache".into(), detail: "0: expected at least 1".into() });
        }
        if !(1..=64).contains(&params.batch) {
            return Err(InferenceError::Params {
                key: "batch".into(),
                detail: format!("{}: expected 1 to 64", params.batch),
            });
        }
        Ok(params)
    }
}

/// A checked observation waiting to be encoded with those that arrived
/// with it.
#[derive(Debug)]
struct Held {
    header: ObservationHeader,
    image: Vec<f32>,
    token_mask: Vec<f32>,
    /// Metres (the network's unit).
    points: Vec<f32>,
    object_index: usize,
    /// The category code of a category-level model; 0 otherwise.
    code: u32,
    active_image_tokens: u32,
}

impl Held {
    fn input(&self) -> EncoderInput<'_> {
        EncoderInput {
            image: &self.image,
            token_mask: &self.token_mask,
            points: &self.points,
            object_index: self.object_index,
        }
    }
}

/// One observation, kept for its velocity requests.
#[derive(Debug)]
struct Cached {
    id: u64,
    condition: Encoding,
    point_scale: f32,
}

/// An observation's condition tokens, or the observation until they are
/// needed ([`EncodeWhen::OnRequest`]).
#[derive(Debug)]
enum Encoding {
    Done(Condition),
    Pending(Box<Held>),
}

/// The inference stage: the model, the condition cache and the buffers a
/// velocity request is unpacked into (reused, so the hot path does not
/// allocate once warm).
#[derive(Debug)]
pub struct InferenceStage {
    model: PoseFlowModel,
    capacity: usize,
    cache: VecDeque<Cached>,
    /// High 32 bits of every condition id: differs between runs, so a
    /// sampler holding an id from before a restart gets UNKNOWN_CONDITION
    /// instead of another observation's condition.
    run_nonce: u64,
    encoded: u64,
    /// When the held observations are encoded.
    batches: FrameBatches,
    held: Vec<Held>,
    /// One observation's points in metres (reused).
    points: Vec<f32>,
    rotations: Vec<f32>,
    translations: Vec<f32>,
    times: Vec<f32>,
    response: Vec<f32>,
    rejected: u64,
    /// Object id → category code (`InferenceParams::classes`).
    classes: Option<BTreeMap<u32, u32>>,
    encode_when: EncodeWhen,
    /// Observations encoded (each once, whenever that is).
    encoder_inputs: u64,
}

/// Reads a `classes` file into object id → the model's category code.
fn read_classes(path: &Path, head: &CategoryHead) -> Result<BTreeMap<u32, u32>, InferenceError> {
    let bad = |detail: String| InferenceError::Params {
        key: "classes".into(),
        detail: format!("{}: {detail}", path.display()),
    };
    let text = std::fs::read_to_string(path).map_err(|e| bad(e.to_string()))?;
    let entries: BTreeMap<String, serde_json::Value> = serde_json::from_str(&text)
        .map_err(|e| bad(format!("expected {{\"<obj_id>\": {{\"category\": name}}}}: {e}")))?;
    let mut classes = BTreeMap::new();
    for (key, entry) in entries {
        let id: u32 = key.parse().map_err(|_| bad(format!("key {key:?}: expected an object id")))?;
        let name = entry
            .get("category")
            .and_then(|c| c.as_str())
            .ok_or_else(|| bad(format!("object {id}: no \"category\" name")))?;
        let code = head.code(name).ok_or_else(|| {
            let known: Vec<&str> = head.names.iter().map(|(_, n)| n.as_str()).collect();
            bad(format!("object {id}: category {name:?} is not one of the model's {known:?}"))
        })?;
        classes.insert(id, code);
    }
    Ok(classes)
}

/// Image tokens left active by a token mask.
fn active_tokens(token_mask: &[f32]) -> u32 {
    token_mask.iter().filter(|&&m| m > 0.5).count() as u32
}

/// The networks of `params.precision`. INT8 networks whose outputs on the
/// model's stored parity inputs drift from the stored FP32 ones beyond
/// [`OutputDrift::INT8_LIMITS`] on this CPU (products that overflow, or a
/// stale file) are replaced by the FP32 ones, with a warning: a fast wrong
/// pose is worth less than a slower right one.
fn load_checked(params: &InferenceParams) -> Result<PoseFlowModel, InferenceError> {
    let mut model = PoseFlowModel::load_as(&params.model, params.threads, params.precision)?;
    if params.precision != Precision::Int8 {
        return Ok(model);
    }
    let Some(parity) = ParityVectors::read(&params.model)? else {
        tracing::info!(model = %params.model.display(), "no parity.json: INT8 outputs not checked against FP32");
        return Ok(model);
    };
    let drift = output_drift(&mut model, &parity)?;
    let limits = OutputDrift::INT8_LIMITS;
    if drift.within(&limits) {
        tracing::info!(
            tokens = drift.tokens,
            v_rot = drift.v_rot,
            v_pos = drift.v_pos,
            "INT8 outputs within quantisation noise of FP32"
        );
        return Ok(model);
    }
    tracing::warn!(
        model = %params.model.display(),
        tokens = drift.tokens,
        v_rot = drift.v_rot,
        v_pos = drift.v_pos,
        limits = ?limits,
        "INT8 networks drift from their FP32 outputs on this CPU beyond quantisation noise: serving the FP32 \
         networks instead (re-quantise with python -m poseflow_train.quantize, which keeps weights in 7 bits)"
    );
    PoseFlowModel::load_as(&params.model, params.threads, Precision::Fp32)
}

fn run_nonce() -> u64 {
    let mixed = poseflow_contracts::monotonic_ns() ^ (u64::from(std::process::id()) << 20);
    // splitmix64 finaliser: spreads nearby clock values over all bits.
    let mut z = mixed.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    ((z ^ (z >> 31)) & 0xFFFF_FFFF).max(1) << 32
}

impl InferenceStage {
    pub fn new(params: &InferenceParams) -> Result<Self, InferenceError> {
        let model = load_checked(params)?;
        let classes = match (&params.classes, &model.info.categories) {
            (None, _) => None,
            (Some(path), Some(head)) => Some(read_classes(path, head)?),
            (Some(_), None) => {
                return Err(InferenceError::Params {
                    key: "classes".into(),
                    detail: format!(
                        "the model in {} is instance-level (no `categories` in its metadata): it takes object ids as they are",
                        params.model.display()
                    ),
                });
            }
        };
        if params.encode == EncodeWhen::OnRequest && model.info.categories.is_some() {
            return Err(InferenceError::Params {
                key: "encode".into(),
                detail: format!(
                    "\"on-request\": the model in {} is category-level, and a Condition handle carries the size its encoder predicts (use \"on-arrival\")",
                    params.model.display()
                ),
            });
        }
        Ok(Self {
            batches: FrameBatches::new(params.batch),
            classes,
            encode_when: params.encode,
            ..Self::with_model(model, params.cache)
        })
    }

    pub fn with_model(model: PoseFlowModel, capacity: usize) -> Self {
        Self {
            model,
            capacity: capacity.max(1),
            cache: VecDeque::new(),
            run_nonce: run_nonce(),
            encoded: 0,
            batches: FrameBatches::new(default_batch()),
            held: Vec::new(),
            points: Vec::new(),
            rotations: Vec::new(),
            translations: Vec::new(),
            times: Vec::new(),
            response: Vec::new(),
            rejected: 0,
            classes: None,
            encode_when: EncodeWhen::OnArrival,
            encoder_inputs: 0,
        }
    }

    /// Observations encoded so far: fewer than arrived when some handles
    /// were never asked for (`encode = "on-request"`).
    pub fn encoder_inputs(&self) -> u64 {
        self.encoder_inputs
    }

    pub fn model_dir(&self) -> &Path {
        &self.model.dir
    }

    /// The networks served: `params.precision`, or FP32 where the INT8 ones
    /// drift on this CPU.
    pub fn precision(&self) -> Precision {
        self.model.precision
    }

    /// Encodes one observation and caches its condition; returns the handle.
    /// Reads the payload in place (only the points are rescaled).
    pub fn encode(&mut self, header: &ObservationHeader, payload: &[f32]) -> Result<ConditionHandle, InferenceError> {
        let (object_index, code, view) = self.check(header, payload)?;
        // The network takes metres.
        self.points.clear();
        self.points.extend(view.points.iter().map(|&x| x * header.point_scale));
        let input = EncoderInput { image: view.image, token_mask: view.token_mask, points: &self.points, object_index };
        let condition = self.model.encode_batch(&[input])?.pop().expect("one condition per input");
        self.encoder_inputs += 1;
        Ok(self.store(header, active_tokens(view.token_mask), code, Encoding::Done(condition)))
    }

    /// Checks an observation against the model and keeps a copy of it for
    /// the next [`Self::encode_held`].
    pub fn hold(&mut self, header: &ObservationHeader, payload: &[f32]) -> Result<(), InferenceError> {
        let held = self.checked_copy(header, payload)?;
        self.held.push(held);
        Ok(())
    }

    /// Checks an observation against the model and caches a copy of it,
    /// encoded at the first velocity request that names it; its handle.
    pub fn defer(&mut self, header: &ObservationHeader, payload: &[f32]) -> Result<ConditionHandle, InferenceError> {
        let held = self.checked_copy(header, payload)?;
        let (active, code) = (held.active_image_tokens, held.code);
        Ok(self.store(header, active, code, Encoding::Pending(Box::new(held))))
    }

    /// A checked copy of an observation, points in metres.
    fn checked_copy(&self, header: &ObservationHeader, payload: &[f32]) -> Result<Held, InferenceError> {
        let (object_index, code, view) = self.check(header, payload)?;
        Ok(Held {
            header: *header,
            image: view.image.to_vec(),
            token_mask: view.token_mask.to_vec(),
            // The network takes metres.
            points: view.points.iter().map(|&x| x * header.point_scale).collect(),
            object_index,
            code,
            active_image_tokens: active_tokens(view.token_mask),
        })
    }

    /// The observation's object index, category code (0 for an
    /// instance-level model) and payload sections, or why the model cannot
    /// take it.
    fn check<'p>(
        &self,
        header: &ObservationHeader,
        payload: &'p [f32],
    ) -> Result<(usize, u32, poseflow_contracts::ObservationView<'p>), InferenceError> {
        let frame = header.header.frame_id;
        let bad = |detail: String| InferenceError::Observation { frame, detail };
        let info = &self.model.info;
        let sizes = [
            ("image_size", header.image_size as usize, info.image_size),
            ("patch_grid", header.patch_grid as usize, info.patch_grid),
            ("point_count", header.point_count as usize, info.point_count),
        ];
        for (field, found, expected) in sizes {
            if found != expected {
                return Err(bad(format!(
                    "{field} {found}, but the model in {} expects {expected} (set the ingest stage's {field} to match)",
                    self.model.dir.display()
                )));
            }
        }
        let object = header.header.object_id;
        let key = match &self.classes {
            Some(classes) => *classes.get(&object).ok_or_else(|| {
                bad(format!("object {object} has no category in the inference stage's `classes` file"))
            })?,
            None => object,
        };
        let object_index = self.model.object_index(key).ok_or_else(|| match &info.categories {
            Some(head) => bad(format!(
                "object {object}: the category model takes category codes {:?} (set the inference stage's `classes` to map object ids to categories)",
                head.names
            )),
            None => bad(format!("object {object} is not one the model knows (its objects: {:?})", info.object_ids)),
        })?;
        let code = if info.categories.is_some() { key } else { 0 };
        if !(header.point_scale.is_finite() && header.point_scale > 0.0) {
            return Err(bad(format!("point_scale {}: expected a positive number", header.point_scale)));
        }
        let view = header.view(payload).map_err(|e| bad(e.to_string()))?;
        Ok((object_index, code, view))
    }

    /// Observations held and not yet encoded.
    pub fn held(&self) -> usize {
        self.held.len()
    }

    /// Encodes every held observation in one run of the encoder, caches
    /// their conditions and returns their handles, in arrival order.
    pub fn encode_held(&mut self) -> Result<Vec<ConditionHandle>, InferenceError> {
        let held = std::mem::take(&mut self.held);
        let inputs: Vec<EncoderInput> = held.iter().map(Held::input).collect();
        let conditions = self.model.encode_batch(&inputs)?;
        self.encoder_inputs += held.len() as u64;
        Ok(held
            .iter()
            .zip(conditions)
            .map(|(h, condition)| self.store(&h.header, h.active_image_tokens, h.code, Encoding::Done(condition)))
            .collect())
    }

    /// Encodes, in one run of the encoder, the cached observations that
    /// `segments` name and that wait for it ([`EncodeWhen::OnRequest`]).
    /// Err carries the velocity status code.
    fn encode_pending(&mut self, segments: &[VelocitySegment]) -> Result<(), u32> {
        let positions: Vec<usize> = segments
            .iter()
            .filter_map(|s| self.cache.iter().position(|c| c.id == s.condition_id))
            .filter(|&at| matches!(self.cache[at].condition, Encoding::Pending(_)))
            .collect();
        if positions.is_empty() {
            return Ok(());
        }
        let inputs: Vec<EncoderInput> = positions
            .iter()
            .map(|&at| match &self.cache[at].condition {
                Encoding::Pending(held) => held.input(),
                Encoding::Done(_) => unreachable!("only pending observations are picked"),
            })
            .collect();
        let conditions = self.model.encode_batch(&inputs).map_err(|err| {
            tracing::warn!(%err, "encoder failed on a velocity request's observations");
            velocity_status::INFERENCE_FAILED
        })?;
        self.encoder_inputs += positions.len() as u64;
        for (at, condition) in positions.into_iter().zip(conditions) {
            self.cache[at].condition = Encoding::Done(condition);
        }
        Ok(())
    }

    /// Caches an observation (encoded, or waiting to be) under a new id;
    /// its handle.
    fn store(
        &mut self,
        header: &ObservationHeader,
        active_image_tokens: u32,
        code: u32,
        condition: Encoding,
    ) -> ConditionHandle {
        let info = &self.model.info;
        let category = match (&info.categories, &condition) {
            (Some(head), Encoding::Done(condition)) => {
                ObjectCategory { code, size: head.size(condition, info.tokens, info.width) }
            }
            _ => ObjectCategory::default(),
        };
        self.encoded += 1;
        let id = self.run_nonce | (self.encoded & 0xFFFF_FFFF);
        let image_tokens = (self.model.info.patch_grid * self.model.info.patch_grid) as u32;
        if self.cache.len() == self.capacity {
            self.cache.pop_front();
        }
        self.cache.push_back(Cached { id, condition, point_scale: header.point_scale });
        ConditionHandle {
            header: header.header,
            condition_id: id,
            image_tokens,
            point_tokens: (self.model.info.tokens as u32).saturating_sub(image_tokens),
            active_image_tokens,
            model_width: self.model.info.width as u32,
            centroid: header.centroid,
            point_scale: header.point_scale,
            category,
        }
    }

    /// Velocities (`v` then `ω`, 6 per sample, each segment's network
    /// frame) of a request's samples, written into `out`: one run of the
    /// velocity network for all its segments. Err carries the status code.
    pub fn velocities(&mut self, request: &VelocityRequest, poses: &[f32], out: &mut [f32]) -> Result<(), u32> {
        let n = request.sample_count as usize;
        if poses.len() != n * POSE_LEN || out.len() != n * VELOCITY_LEN || poses.iter().any(|x| !x.is_finite()) {
            return Err(velocity_status::INVALID_REQUEST);
        }
        self.encode_pending(request.segments())?;
        let mut segments = Vec::with_capacity(request.segments().len());
        for segment in request.segments() {
            let Some(cached) = self.cache.iter().find(|c| c.id == segment.condition_id) else {
                return Err(velocity_status::UNKNOWN_CONDITION);
            };
            let Encoding::Done(condition) = &cached.condition else {
                unreachable!("encode_pending encoded every cached condition of the request")
            };
            segments.push((cached.point_scale, condition, segment.sample_count as usize, segment.t));
        }
        self.rotations.clear();
        self.translations.clear();
        self.times.clear();
        let mut samples = poses.chunks_exact(POSE_LEN);
        for &(point_scale, _, count, t) in &segments {
            for pose in samples.by_ref().take(count) {
                self.rotations.extend_from_slice(&pose[..9]);
                self.translations.extend(pose[9..].iter().map(|&x| x * point_scale));
            }
            self.times.extend(std::iter::repeat_n(t, count));
        }
        let runs: Vec<(&Condition, usize)> =
            segments.iter().map(|&(_, condition, count, _)| (condition, count)).collect();
        let velocities =
            self.model.velocity_segments(&runs, &self.rotations, &self.translations, &self.times).map_err(|err| {
                tracing::warn!(%err, "velocity network failed");
                velocity_status::INFERENCE_FAILED
            })?;
        let mut rows = out
            .chunks_exact_mut(VELOCITY_LEN)
            .zip(velocities.translation.chunks_exact(3))
            .zip(velocities.rotation.chunks_exact(3));
        for &(scale, _, count, _) in &segments {
            for ((o, v), w) in rows.by_ref().take(count) {
                o[0] = v[0] / scale;
                o[1] = v[1] / scale;
                o[2] = v[2] / scale;
                o[3..].copy_from_slice(w);
            }
        }
        Ok(())
    }

    /// Encodes the held observations and emits their handles.
    fn run_batch(&mut self, output: &mut dyn Emitter<ConditionHandle>) -> Result<(), InferenceError> {
        if self.held.is_empty() {
            return Ok(());
        }
        let frames: Vec<u64> = self.held.iter().map(|h| h.header.header.frame_id).collect();
        let handles = self.encode_held().inspect_err(|_| tracing::warn!(?frames, "observations not encoded"))?;
        tracing::debug!(observations = handles.len(), "encoded");
        for handle in handles {
            output.emit(handle, 0, &mut |_| {})?;
        }
        Ok(())
    }

    fn reply_status(
        header: Header,
        request_id: u64,
        status: u32,
        reply: &mut dyn Emitter<VelocityResponse>,
    ) -> Result<(), InferenceError> {
        let response = VelocityResponse { header, request_id, sample_count: 0, status };
        reply.emit(response, 0, &mut |_| {})?;
        Ok(())
    }

    /// Holds an observation until its batch is complete, or runs the batch
    /// it completes.
    fn hold_or_encode(
        &mut self,
        input: Input<'_, ObservationHeader>,
        output: &mut dyn Emitter<ConditionHandle>,
    ) -> Result<(), InferenceError> {
        if self.encode_when == EncodeWhen::OnRequest {
            let handle = self.defer(input.header, input.payload)?;
            output.emit(handle, 0, &mut |_| {})?;
            return Ok(());
        }
        if !self.batches.run_after(&input.header.header, self.held.len() + 1) {
            return self.hold(input.header, input.payload);
        }
        if !self.held.is_empty() {
            self.hold(input.header, input.payload)?;
            return self.run_batch(output);
        }
        // A batch of one (one object a frame, or `batch = 1`): encoded in
        // place, no copy.
        let handle = self.encode(input.header, input.payload)?;
        output.emit(handle, 0, &mut |_| {})?;
        Ok(())
    }
}

impl Transform for InferenceStage {
    type In = ObservationHeader;
    type Out = ConditionHandle;
    type Error = InferenceError;
    const SLOT: Option<StampSlot> = Some(StampSlot::Encode);

    fn process(
        &mut self,
        input: Input<'_, ObservationHeader>,
        output: &mut dyn Emitter<ConditionHandle>,
    ) -> Result<(), InferenceError> {
        let header = &input.header.header;
        let before = match self.batches.run_before(header, self.held.len()) {
            true => self.run_batch(output),
            false => Ok(()),
        };
        let this = self.hold_or_encode(input, output);
        FrameBatches::first_failure(before, this, &mut self.rejected)
    }

    fn flush(&mut self, output: &mut dyn Emitter<ConditionHandle>, reason: Flush) -> Result<(), InferenceError> {
        if self.batches.run_at(reason) { self.run_batch(output) } else { Ok(()) }
    }

    fn take_rejected(&mut self) -> u64 {
        std::mem::take(&mut self.rejected)
    }
}

impl Server for InferenceStage {
    type Request = VelocityRequest;
    type Response = VelocityResponse;

    fn answer(
        &mut self,
        request: Input<'_, VelocityRequest>,
        reply: &mut dyn Emitter<VelocityResponse>,
    ) -> Result<(), InferenceError> {
        let header = request.header;
        let n = header.sample_count as usize;
        // Computed before the response is loaned: its header (status and
        // length) must be known first; the copy into shared memory is N·6
        // floats.
        let mut velocities = std::mem::take(&mut self.response);
        velocities.resize(n * VELOCITY_LEN, 0.0);
        let result = self.velocities(header, request.payload, &mut velocities);
        let sent = match result {
            Ok(()) => {
                let response = VelocityResponse {
                    header: header.header,
                    request_id: header.request_id,
                    sample_count: header.sample_count,
                    status: velocity_status::OK,
                };
                reply.emit(response, velocities.len(), &mut |out| out.copy_from_slice(&velocities)).map_err(Into::into)
            }
            Err(status) => {
                self.rejected += 1;
                let conditions: Vec<u64> = header.segments().iter().map(|s| s.condition_id).collect();
                tracing::warn!(?conditions, status, "velocity request not served");
                Self::reply_status(header.header, header.request_id, status, reply)
            }
        };
        self.response = velocities;
        sent
    }

    fn answer_invalid(
        &mut self,
        request: &VelocityRequest,
        reply: &mut dyn Emitter<VelocityResponse>,
    ) -> Result<(), InferenceError> {
        Self::reply_status(request.header, request.request_id, velocity_status::INVALID_REQUEST, reply)
    }
}
