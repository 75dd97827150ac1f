//! The pose stages in one process: ingest → encode → flow sampling →
//! selection, the same library code the graph's processes run. The
//! simulations, the next-best-view stage (which estimates on rendered
//! views) and the in-process baseline of `poseflow bench pipeline` use it;
//! `tests/e2e` checks that processes and libraries agree bit for bit.
//!
//! When the sampler's `tracking.enabled` is set, each estimate seeds the
//! next frames of its object, as the graph's estimates side input does.

use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, Instant};

use poseflow_contracts::{ContractError, EstimateHeader, MessageHeader, VelocityRequest};
use poseflow_geometry::Pose;
use poseflow_geometry::sampling::{sample_seed, seeded_rng};
use poseflow_inference::InferenceError;
use poseflow_inference::stage::{InferenceParams, InferenceStage};
use poseflow_ingest::{IngestError, IngestParams, ObjectMask, RgbdFrame, prepare};
use poseflow_sampler::stage::SamplerStage;
use poseflow_sampler::{SamplerError, SamplerParams, VelocityField};
use poseflow_selector::stage::{SelectorStage, estimate_header, estimate_payload_len, write_estimate_payload};
use poseflow_selector::{SelectorError, SelectorParams};

/// Why an object could not be estimated: the failing stage's own error.
#[derive(Debug, thiserror::Error)]
pub enum PipelineError {
    #[error(transparent)]
    Ingest(#[from] IngestError),
    #[error(transparent)]
    Inference(#[from] InferenceError),
    #[error(transparent)]
    Sampler(#[from] SamplerError),
    #[error(transparent)]
    Selector(#[from] SelectorError),
    #[error("the selector's own estimate: {0}")]
    Contract(#[from] ContractError),
    #[error("the selector's best pose: {0}")]
    Geometry(#[from] poseflow_geometry::GeometryError),
}

/// The inference stage shared by the pipeline (encoding) and the sampler's
/// velocity field, as the two talk over request-response in the graph. A
/// mutex rather than a `RefCell` so a pipeline can move to a worker thread;
/// it is never contended (one pipeline runs one object at a time).
#[derive(Debug, Clone)]
struct SharedField(Arc<Mutex<InferenceStage>>);

impl SharedField {
    fn stage(&self) -> std::sync::MutexGuard<'_, InferenceStage> {
        self.0.lock().unwrap_or_else(PoisonError::into_inner)
    }
}

impl VelocityField for SharedField {
    fn velocities(&mut self, request: &VelocityRequest, poses: &[f32], out: &mut [f32]) -> Result<(), String> {
        self.stage().velocities(request, poses, out).map_err(|status| format!("velocity request status {status}"))
    }
}

/// Where one estimate's time went, per stage of the graph.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct StageTimes {
    /// Crop, token mask, point cloud (the ingest stage).
    pub ingest: Duration,
    /// The encoder network (the inference stage's `process`).
    pub encode: Duration,
    /// The Euler steps, velocity network included (the sampler).
    pub sample: Duration,
    /// Scoring, clustering, refinement, statistics (the selector).
    pub select: Duration,
}

/// One object's Estimate: header and payload as the selector publishes them.
#[derive(Debug, Clone)]
pub struct Estimated {
    pub header: EstimateHeader,
    pub payload: Vec<f32>,
    pub times: StageTimes,
}

#[derive(Debug)]
pub struct PosePipeline {
    ingest: IngestParams,
    inference: SharedField,
    sampler: SamplerStage<SharedField>,
    selector: SelectorStage,
}

impl PosePipeline {
    pub fn new(
        ingest: IngestParams,
        inference: &InferenceParams,
        sampler: SamplerParams,
        selector: SelectorParams,
    ) -> Result<Self, PipelineError> {
        let inference = SharedField(Arc::new(Mutex::new(InferenceStage::new(inference)?)));
        Ok(Self {
            ingest,
            sampler: SamplerStage::new(sampler, inference.clone()),
            inference,
            selector: SelectorStage::new(selector)?,
        })
    }

    /// The Estimate of `object` in `frame` (frame id `frame.frame_id`).
    pub fn estimate(&mut self, frame: &RgbdFrame, object: &ObjectMask) -> Result<Estimated, PipelineError> {
        let (frame_id, obj_id) = (frame.frame_id, object.obj_id);
        let mut clock = Instant::now();
        let mut lap = || {
            let now = Instant::now();
            now - std::mem::replace(&mut clock, now)
        };
        let mut rng = seeded_rng(sample_seed(0, frame_id, obj_id));
        let prepared = prepare(frame, object, &self.ingest, &mut rng)?;
        let observation = prepared.header(frame_id, &frame.camera, &self.ingest);
        let mut payload = vec![0.0; observation.payload_len()?];
        prepared.write_payload(frame, object, &self.ingest, &mut payload);
        let ingest = lap();
        let handle = self.inference.stage().encode(&observation, &payload)?;
        let encode = lap();
        let (hypotheses, poses) = self.sampler.hypotheses(&handle)?;
        let poses: Vec<f32> = poses.iter().flat_map(|p| p.to_f32_row_major()).collect();
        let sample = lap();
        self.selector.keep_observation(&observation, &payload)?;
        let selection = self.selector.select_for(&hypotheses, &poses)?;
        let mut payload = vec![0.0; estimate_payload_len(&selection)];
        write_estimate_payload(&selection, &mut payload);
        let header = estimate_header(&selection, hypotheses.header);
        header.check_payload(&payload)?;
        // As the graph's sampler reads it from the Estimate (f32 values).
        let best = Pose::from_f32_row_major(&header.best)?;
        self.sampler.remember(frame_id, obj_id, best);
        let select = lap();
        Ok(Estimated { header, payload, times: StageTimes { ingest, encode, sample, select } })
    }
}
