//! The sampler stage: Condition handle in, Hypotheses out; velocities from
//! a [`VelocityField`] (over request-response in a process).

use std::collections::{BTreeMap, HashMap};
use std::time::{Duration, Instant};

use poseflow_contracts::{
    ConditionHandle, EstimateHeader, HypothesesHeader, POSE_LEN, StampSlot, VelocityRequest, VelocityResponse, flags,
    status as velocity_status,
};
use poseflow_geometry::Pose;
use poseflow_runtime::{Call, Emitter, Flush, FrameBatches, Input, Joined, Transform};

use crate::flow::write_poses;
use crate::{FieldError, FlowSampler, SamplerError, SamplerParams, Start, VelocityField};

/// The inference stage over its request-response edge (iceoryx2 between
/// processes, its thread in-process).
#[derive(Debug)]
pub struct RemoteField {
    client: Box<dyn Call<VelocityRequest, VelocityResponse>>,
    timeout: Duration,
}

impl RemoteField {
    pub fn new(client: Box<dyn Call<VelocityRequest, VelocityResponse>>, timeout: Duration) -> Self {
        Self { client, timeout }
    }
}

impl VelocityField for RemoteField {
    fn velocities(&mut self, request: &VelocityRequest, poses: &[f32], out: &mut [f32]) -> Result<(), FieldError> {
        let mut answer = Err(FieldError::NoResponse);
        self.client
            .call(*request, poses, self.timeout, &mut |response, payload| {
                answer = check_response(request, response, payload, out);
            })
            .map_err(|e| FieldError::Call(Box::new(e)))?;
        answer
    }
}

/// Copies a velocity response into `out` if it is the good answer to `request`.
fn check_response(
    request: &VelocityRequest,
    response: &VelocityResponse,
    payload: &[f32],
    out: &mut [f32],
) -> Result<(), FieldError> {
    if response.status != velocity_status::OK {
        return Err(FieldError::status(response.status));
    }
    if response.request_id != request.request_id || payload.len() != out.len() {
        return Err(FieldError::Mismatch {
            answered: response.request_id,
            values: payload.len(),
            expected: request.request_id,
            expected_values: out.len(),
        });
    }
    out.copy_from_slice(payload);
    Ok(())
}

/// Estimates kept per object: a side input may run ahead of the frames
/// (priors of later frames arriving before this frame is sampled).
const KEPT_ESTIMATES: usize = 32;

/// The stage: the sampler, its velocity field and, in tracking mode, the
/// latest estimates per object by frame id.
#[derive(Debug)]
pub struct SamplerStage<F> {
    sampler: FlowSampler,
    field: F,
    /// Handles of one frame, sampled together ([`FrameBatches`]).
    held: Vec<ConditionHandle>,
    batches: FrameBatches,
    /// Handles of a batch that could not be sampled beyond the first
    /// (which fails the flush), counted as rejected parts of it.
    rejected: u64,
    previous: HashMap<u32, BTreeMap<u64, Remembered>>,
    /// Per object, the first frame of its current sequence
    /// ([`flags::SEQUENCE_START`]): estimates of earlier frames still on
    /// their way belong to another scene.
    sequence_start: HashMap<u32, u64>,
    /// In tracking mode, the frame whose Hypotheses were sent last while
    /// its estimates have not all come back: a next frame that would start
    /// from the prior waits for them (`tracking.await_estimate_ms`,
    /// [`Joined::awaits_side`]).
    awaiting: Option<Awaited>,
}

/// The estimates a tracking sampler waits for.
#[derive(Debug, Clone)]
struct Awaited {
    frame: u64,
    /// Objects of `frame` whose estimate has not come.
    objects: Vec<u32>,
    /// When the first estimate of `frame` came.
    first_back: Option<Instant>,
}

/// The selector publishes a frame's estimates one after another: one that
/// has not come this long after the first was not made (the selector
/// counts and logs why), and is not waited for further.
const REST_OF_FRAME: Duration = Duration::from_millis(20);

/// An object's estimate as the sampler keeps it.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Remembered {
    pose: Pose,
    /// The Estimate's `LOST`, `UNSURE` and `REINITIALISED` bits.
    track_flags: u32,
}

impl<F: VelocityField> SamplerStage<F> {
    pub fn new(params: SamplerParams, field: F) -> Self {
        Self {
            batches: FrameBatches::new(params.batch),
            sampler: FlowSampler::new(params),
            field,
            held: Vec::new(),
            rejected: 0,
            previous: HashMap::new(),
            sequence_start: HashMap::new(),
            awaiting: None,
        }
    }

    /// Caps the samples of one velocity request ([`FlowSampler::set_request_capacity`]).
    pub fn set_request_capacity(&mut self, samples: usize) {
        self.sampler.set_request_capacity(samples);
    }

    /// Records an estimate (camera frame) that later frames of the object
    /// start from in tracking mode, with its Estimate header's flags (of
    /// which `LOST` and `UNSURE` matter). An id below the object's latest
    /// means the source restarted its numbering: the later ids are another
    /// run's.
    pub fn remember(&mut self, frame_id: u64, object_id: u32, pose: Pose, estimate_flags: u32) {
        if self.sequence_start.get(&object_id).is_some_and(|&start| frame_id < start) {
            return;
        }
        let estimates = self.previous.entry(object_id).or_default();
        estimates.split_off(&frame_id);
        let track_flags = estimate_flags & (flags::LOST | flags::UNSURE | flags::REINITIALISED);
        estimates.insert(frame_id, Remembered { pose, track_flags });
        while estimates.len() > KEPT_ESTIMATES {
            estimates.pop_first();
        }
    }

    /// Where the handle's frame starts: the object's latest estimate when
    /// tracking and recent enough (an earlier frame's, or one of this frame
    /// that arrived first), else the prior; an estimate flagged `LOST`
    /// means the prior, one flagged `UNSURE` a mix of both. A held track
    /// (unflagged, not just re-acquired) skips the networks except on every
    /// `network_every`-th frame, counted from a stagger of its object id so
    /// that the objects of a frame take turns.
    pub fn start_for(&self, handle: &ConditionHandle) -> Start {
        let tracking = &self.sampler.params().tracking;
        let frame = handle.header.frame_id;
        let recent = self
            .previous
            .get(&handle.header.object_id)
            .and_then(|estimates| estimates.range(..=frame).next_back())
            .filter(|&(&estimated, _)| frame - estimated <= tracking.max_age_frames);
        match recent {
            Some((_, remembered)) if tracking.enabled => match remembered.track_flags {
                f if f & flags::LOST != 0 => Start::Prior,
                f if f & flags::UNSURE != 0 => Start::Mixed(remembered.pose),
                f if f & flags::REINITIALISED == 0
                    && !(frame + u64::from(handle.header.object_id)).is_multiple_of(tracking.network_every) =>
                {
                    Start::Hold(remembered.pose)
                }
                _ => Start::Track(remembered.pose),
            },
            _ => Start::Prior,
        }
    }

    /// The sampled hypotheses of one handle (camera frame) and the header
    /// they are published under.
    pub fn hypotheses(&mut self, handle: &ConditionHandle) -> Result<(HypothesesHeader, &[Pose]), SamplerError> {
        let start = self.start_for(handle);
        let sampled = self.sampler.sample(handle, &start, &mut self.field)?;
        Ok((hypotheses_header(handle, &start, sampled.poses.len(), sampled.steps), sampled.poses))
    }

    /// Notes that the estimate of `object` in `frame` is on its way.
    fn await_estimate(&mut self, frame: u64, object: u32) {
        match &mut self.awaiting {
            Some(awaited) if awaited.frame == frame => awaited.objects.push(object),
            Some(awaited) if awaited.frame > frame => {}
            _ => self.awaiting = Some(Awaited { frame, objects: vec![object], first_back: None }),
        }
    }

    /// Samples every held handle together and emits each one's hypotheses;
    /// a handle that cannot be sampled is counted and the others go on.
    fn sample_held(&mut self, output: &mut dyn Emitter<HypothesesHeader>) -> Result<(), SamplerError> {
        let held = std::mem::take(&mut self.held);
        if held.is_empty() {
            return Ok(());
        }
        let jobs: Vec<(ConditionHandle, Start)> = held.iter().map(|h| (*h, self.start_for(h))).collect();
        let results = self.sampler.sample_batch(&jobs, &mut self.field).inspect_err(|_| {
            let frames: Vec<(u64, u32)> = held.iter().map(|h| (h.header.frame_id, h.header.object_id)).collect();
            tracing::warn!(?frames, "a velocity request failed: these (frame, object) pairs are not sampled");
        })?;
        let mut first_error = None;
        let tracking = &self.sampler.params().tracking;
        let awaits = tracking.enabled && tracking.await_estimate_ms > 0;
        for ((handle, start), result) in jobs.iter().zip(results) {
            match result {
                Ok(batched) => {
                    let poses = &self.sampler.poses()[batched.samples];
                    let header = hypotheses_header(handle, start, poses.len(), batched.steps);
                    output.emit(header, poses.len() * POSE_LEN, &mut |buffer| write_poses(poses, buffer))?;
                    if awaits {
                        self.await_estimate(handle.header.frame_id, handle.header.object_id);
                    }
                }
                Err(err) if first_error.is_none() => first_error = Some(err),
                Err(err) => {
                    self.rejected += 1;
                    tracing::warn!(err = %poseflow_runtime::error_chain(&err), "not sampled");
                }
            }
        }
        first_error.map_or(Ok(()), Err)
    }
}

/// The Hypotheses header of a handle's samples.
fn hypotheses_header(handle: &ConditionHandle, start: &Start, samples: usize, steps: usize) -> HypothesesHeader {
    let mut header = handle.header;
    if matches!(start, Start::Track(_) | Start::Mixed(_) | Start::Hold(_)) {
        header.flags |= flags::TRACKING;
    }
    if matches!(start, Start::Hold(_)) {
        header.flags |= flags::NETWORK_SKIPPED;
    }
    HypothesesHeader { header, sample_count: samples as u32, step_count: steps as u32, category: handle.category }
}

impl<F: VelocityField> Transform for SamplerStage<F> {
    type In = ConditionHandle;
    type Out = HypothesesHeader;
    type Error = SamplerError;
    const SLOT: Option<StampSlot> = Some(StampSlot::Sampler);

    fn process(
        &mut self,
        input: Input<'_, ConditionHandle>,
        output: &mut dyn Emitter<HypothesesHeader>,
    ) -> Result<(), SamplerError> {
        let handle = input.header;
        let _span =
            tracing::debug_span!("sample", frame = handle.header.frame_id, object = handle.header.object_id).entered();
        if handle.header.has_flag(flags::UPSTREAM_RESTARTED) && !self.previous.is_empty() {
            // A restarted source may show another scene under the same ids.
            tracing::info!("an upstream stage restarted: tracks start again from the prior");
            self.previous.clear();
        }
        if handle.header.has_flag(flags::SEQUENCE_START) {
            let (frame, object) = (handle.header.frame_id, handle.header.object_id);
            // An estimate of this frame or later (a prior fed ahead of its
            // frame) belongs to the new sequence.
            if let Some(estimates) = self.previous.get_mut(&object) {
                *estimates = estimates.split_off(&frame);
            }
            self.sequence_start.insert(object, frame);
        }
        // A batch holds one handle per object: a later frame of an object
        // starts from the estimate of the earlier one when tracking.
        let repeated = self.held.iter().any(|h| h.header.object_id == handle.header.object_id);
        let before = match repeated || self.batches.run_before(&handle.header, self.held.len()) {
            true => self.sample_held(output),
            false => Ok(()),
        };
        self.held.push(*handle);
        let after = match self.batches.run_after(&handle.header, self.held.len()) {
            true => self.sample_held(output),
            false => Ok(()),
        };
        FrameBatches::first_failure(before, after, &mut self.rejected)
    }

    fn flush(&mut self, output: &mut dyn Emitter<HypothesesHeader>, reason: Flush) -> Result<(), SamplerError> {
        if self.batches.run_at(reason) { self.sample_held(output) } else { Ok(()) }
    }

    fn take_rejected(&mut self) -> u64 {
        std::mem::take(&mut self.rejected)
    }
}

/// Tracking: the selector's Estimates as a side input (`side_inputs`), each
/// remembered as its object's previous pose.
impl<F: VelocityField> Joined for SamplerStage<F> {
    type Side = EstimateHeader;

    fn side(&mut self, input: Input<'_, EstimateHeader>) -> Result<(), SamplerError> {
        let header = &input.header.header;
        let best = Pose::from_f32_row_major(&input.header.best).map_err(|e| SamplerError::Geometry {
            frame: header.frame_id,
            object: header.object_id,
            detail: format!("estimate's best pose: {e}"),
        })?;
        self.remember(header.frame_id, header.object_id, best, header.flags);
        if let Some(awaited) = &mut self.awaiting
            && header.frame_id >= awaited.frame
        {
            awaited.objects.retain(|&object| object != header.object_id);
            awaited.first_back.get_or_insert_with(Instant::now);
            // An estimate of a later frame: the awaited frame's are all out.
            if awaited.objects.is_empty() || header.frame_id > awaited.frame {
                self.awaiting = None;
            }
        }
        Ok(())
    }

    /// Waits when `next` would start from the prior while its object's
    /// estimate of an earlier frame is on its way. A frame that can start
    /// from an older estimate goes on: waiting there would cost a saturated
    /// graph its overlap of sampler and selector for little.
    fn awaits_side(&self, next: &ConditionHandle) -> Option<Duration> {
        let awaited = self.awaiting.as_ref()?;
        let on_its_way = awaited.frame < next.header.frame_id && awaited.objects.contains(&next.header.object_id);
        let rest_of_frame_due = awaited.first_back.is_none_or(|first| first.elapsed() < REST_OF_FRAME);
        (on_its_way && rest_of_frame_due && self.start_for(next) == Start::Prior)
            .then(|| Duration::from_millis(self.sampler.params().tracking.await_estimate_ms))
    }
}

/// Builds the sampler stage from its wiring: parameters, and a client of
/// the one request-response edge in `calls`.
pub fn from_wiring(
    wiring: &poseflow_graph::StageWiring,
) -> Result<SamplerStage<RemoteField>, poseflow_runtime::BuildError> {
    let params = SamplerParams::from_json(&wiring.params)?;
    let [edge] = wiring.calls.as_slice() else {
        return Err(format!(
            "stage `{}`: expected exactly one request-response edge in `calls` (the inference stage's velocities), found {}",
            wiring.stage,
            wiring.calls.len()
        )
        .into());
    };
    let client = poseflow_runtime::connect(&wiring.stage, edge)?;
    let timeout = std::time::Duration::from_millis(params.velocity_timeout_ms);
    tracing::info!(samples = params.samples, steps = params.steps, tracking = params.tracking.enabled, "sampler ready");
    let mut stage = SamplerStage::new(params, RemoteField::new(client, timeout));
    stage.set_request_capacity(edge.max_payload_len / POSE_LEN);
    Ok(stage)
}
