//! Sampler ⇄ inference, request-response: the velocities of a batch of pose
//! samples at one flow time.

use iceoryx2_bb_derive_macros::ZeroCopySend;
use iceoryx2_bb_elementary_traits::zero_copy_send::ZeroCopySend;

use crate::message::{MessageHeader, POSE_LEN, VELOCITY_LEN, bounded, header_accessors, limits};
use crate::{ContractError, Header};

/// Most segments one [`VelocityRequest`] carries.
pub const MAX_SEGMENTS: usize = 16;

/// A run of consecutive samples of a [`VelocityRequest`] under one condition
/// at one flow time: one observation's samples (or, when tracking, one of
/// its start-time groups). 16 bytes, alignment 8.
///
/// | offset | size | field        | type | meaning |
/// |-------:|-----:|--------------|------|---------|
/// | 0      | 8    | condition_id | u64  | from the [`crate::ConditionHandle`] |
/// | 8      | 4    | sample_count | u32  | samples of this segment |
/// | 12     | 4    | t            | f32  | flow time in `[0, 1)` |
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Default, ZeroCopySend)]
#[type_name("poseflow/VelocitySegment/v1")]
pub struct VelocitySegment {
    pub condition_id: u64,
    pub sample_count: u32,
    pub t: f32,
}

/// User header of a VelocityRequest (360 bytes, alignment 8).
///
/// | offset | size | field         | type | meaning |
/// |-------:|-----:|---------------|------|---------|
/// | 0      | 80   | header        | [`Header`] | |
/// | 80     | 8    | request_id    | u64  | echoed in the response |
/// | 88     | 4    | segment_count | u32  | S, 1 ..= [`MAX_SEGMENTS`] |
/// | 92     | 4    | sample_count  | u32  | N, the sum of the segments' counts |
/// | 96     | 4    | step_index    | u32  | k of K (for logs) |
/// | 100    | 4    | step_count    | u32  | K, the most steps of any segment |
/// | 104    | 256  | segments      | [[`VelocitySegment`]; 16] | the first S are used, the rest zero |
///
/// Payload (`f32`): N poses × 12 (`R` row-major, `t`), the segments' samples
/// one segment after the other, each in its observation's network frame:
/// centred on its centroid and divided by its `point_scale`. One request
/// carries the samples of every object of a frame, so the inference stage
/// runs its velocity network once per Euler step for all of them.
/// (`VelocityRequest/v1` had one condition and one `t`.)
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Default, ZeroCopySend)]
#[type_name("poseflow/VelocityRequest/v2")]
pub struct VelocityRequest {
    pub header: Header,
    pub request_id: u64,
    pub segment_count: u32,
    pub sample_count: u32,
    pub step_index: u32,
    pub step_count: u32,
    pub segments: [VelocitySegment; MAX_SEGMENTS],
}

impl VelocityRequest {
    /// A request of one segment: `sample_count` samples under `condition_id` at `t`.
    pub fn single(header: Header, condition_id: u64, request_id: u64, sample_count: u32, t: f32) -> Self {
        let mut request = Self { header, request_id, step_count: 1, ..Default::default() };
        request.push(VelocitySegment { condition_id, sample_count, t });
        request
    }

    /// The used segments (at most [`MAX_SEGMENTS`], whatever `segment_count` says).
    pub fn segments(&self) -> &[VelocitySegment] {
        &self.segments[..(self.segment_count as usize).min(MAX_SEGMENTS)]
    }

    /// Appends a segment and counts its samples; false (nothing changed)
    /// when the request already holds [`MAX_SEGMENTS`].
    pub fn push(&mut self, segment: VelocitySegment) -> bool {
        let Some(slot) = self.segments.get_mut(self.segment_count as usize) else {
            return false;
        };
        *slot = segment;
        self.segment_count += 1;
        self.sample_count = self.sample_count.saturating_add(segment.sample_count);
        true
    }
}

impl MessageHeader for VelocityRequest {
    const NAME: &'static str = "VelocityRequest";

    header_accessors!();

    fn payload_len(&self) -> Result<usize, ContractError> {
        let n = bounded(Self::NAME, "sample_count", self.sample_count, 1, limits::MAX_SAMPLES, "1..=4096")?;
        bounded(Self::NAME, "segment_count", self.segment_count, 1, MAX_SEGMENTS as u32, "1..=16")?;
        let mut total = 0usize;
        for segment in self.segments() {
            total += bounded(
                Self::NAME,
                "segments[].sample_count",
                segment.sample_count,
                1,
                limits::MAX_SAMPLES,
                "1..=4096",
            )?;
            if !(0.0..1.0).contains(&segment.t) {
                return Err(ContractError::FieldOutOfRange {
                    message: Self::NAME,
                    field: "segments[].t",
                    value: u64::from(segment.t.to_bits()),
                    expected: "a flow time 0 <= t < 1 (value shown as f32 bits)",
                });
            }
        }
        if total != n {
            return Err(ContractError::FieldOutOfRange {
                message: Self::NAME,
                field: "sample_count",
                value: n as u64,
                expected: "the sum of the segments' sample counts",
            });
        }
        Ok(n * POSE_LEN)
    }
}

/// Outcome codes of a [`VelocityResponse`].
pub mod status {
    pub const OK: u32 = 0;
    /// The `condition_id` is not (or no longer) cached: re-send the Observation.
    pub const UNKNOWN_CONDITION: u32 = 1;
    /// The request failed validation; the payload is empty.
    pub const INVALID_REQUEST: u32 = 2;
    /// The network failed to run; the payload is empty.
    pub const INFERENCE_FAILED: u32 = 3;
}

/// User header of a VelocityResponse (96 bytes, alignment 8).
///
/// | offset | size | field        | type | meaning |
/// |-------:|-----:|--------------|------|---------|
/// | 0      | 80   | header       | [`Header`] | |
/// | 80     | 8    | request_id   | u64  | of the request answered |
/// | 88     | 4    | sample_count | u32  | N (0 unless `status` is OK) |
/// | 92     | 4    | status       | u32  | [`status`] code |
///
/// Payload (`f32`): N velocities × 6 (`v` then body-frame `ω`), in the
/// request's frame and order.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Default, ZeroCopySend)]
#[type_name("poseflow/VelocityResponse/v1")]
pub struct VelocityResponse {
    pub header: Header,
    pub request_id: u64,
    pub sample_count: u32,
    pub status: u32,
}

impl MessageHeader for VelocityResponse {
    const NAME: &'static str = "VelocityResponse";

    header_accessors!();

    fn payload_len(&self) -> Result<usize, ContractError> {
        let min = if self.status == status::OK { 1 } else { 0 };
        let max = if self.status == status::OK { limits::MAX_SAMPLES } else { 0 };
        let n = bounded(Self::NAME, "sample_count", self.sample_count, min, max, "1..=4096 when status is OK, else 0")?;
        Ok(n * VELOCITY_LEN)
    }
}
