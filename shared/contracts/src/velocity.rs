//! Sampler ⇄ inference, request-response: the velocities of a batch of pose
//! samples at one flow time.

use iceoryx2_bb_derive_macros::ZeroCopySend;
use iceoryx2_bb_elementary_traits::zero_copy_send::ZeroCopySend;

use crate::message::{MessageHeader, POSE_LEN, VELOCITY_LEN, bounded, header_accessors, limits};
use crate::{ContractError, Header};

/// User header of a VelocityRequest (112 bytes, alignment 8).
///
/// | offset | size | field        | type | meaning |
/// |-------:|-----:|--------------|------|---------|
/// | 0      | 80   | header       | [`Header`] | |
/// | 80     | 8    | condition_id | u64  | from the [`crate::ConditionHandle`] |
/// | 88     | 8    | request_id   | u64  | echoed in the response |
/// | 96     | 4    | sample_count | u32  | N |
/// | 100    | 4    | t            | f32  | flow time in `[0, 1)`, shared by all N samples |
/// | 104    | 4    | step_index   | u32  | k of K (for logs) |
/// | 108    | 4    | step_count   | u32  | K |
///
/// Payload (`f32`): N poses × 12 (`R` row-major, `t`) in the network's frame:
/// centred on the observation's centroid and divided by its `point_scale`.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Default, ZeroCopySend)]
#[type_name("poseflow/VelocityRequest/v1")]
pub struct VelocityRequest {
    pub header: Header,
    pub condition_id: u64,
    pub request_id: u64,
    pub sample_count: u32,
    pub t: f32,
    pub step_index: u32,
    pub step_count: u32,
}

impl MessageHeader for VelocityRequest {
    const NAME: &'static str = "VelocityRequest";

    header_accessors!();

    fn payload_len(&self) -> Result<usize, ContractError> {
        let n = bounded(Self::NAME, "sample_count", self.sample_count, 1, limits::MAX_SAMPLES, "1..=4096")?;
        if !(0.0..1.0).contains(&self.t) {
            return Err(ContractError::FieldOutOfRange {
                message: Self::NAME,
                field: "t",
                value: u64::from(self.t.to_bits()),
                expected: "a flow time 0 <= t < 1 (value shown as f32 bits)",
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
