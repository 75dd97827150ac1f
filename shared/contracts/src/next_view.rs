//! Next-best-view stage → robot: where to move the camera.

use iceoryx2_bb_derive_macros::ZeroCopySend;
use iceoryx2_bb_elementary_traits::zero_copy_send::ZeroCopySend;

use crate::message::{MessageHeader, POSE_LEN, bounded, header_accessors, limits};
use crate::{ContractError, Header};

/// `f32` values per candidate view: camera pose (12), expected rotational
/// trace.
pub const CANDIDATE_LEN: usize = POSE_LEN + 1;

/// User header of a NextView (144 bytes, alignment 8).
///
/// | offset | size | field                   | type      | meaning |
/// |-------:|-----:|-------------------------|-----------|---------|
/// | 0      | 80   | header                  | [`Header`] | |
/// | 80     | 48   | chosen                  | [f32; 12] | pose of the next camera in the current camera frame (`x_current = R x_next + t`) |
/// | 128    | 4    | expected_rotation_trace | f32       | E[tr Σ_R] after moving there (rad²), as the stage measures it (its own cheaper pose stages; modulo the object's symmetries) |
/// | 132    | 4    | current_rotation_trace  | f32       | tr Σ_R now: the Estimate's `rotation_trace` (rad²) |
/// | 136    | 4    | candidate_count         | u32       | C |
/// | 140    | 4    | reserved                | u32       | 0 |
///
/// Payload (`f32`): C candidates × 13 (camera pose as `chosen`, expected
/// trace), sorted best (lowest expected trace) first, so the first is
/// `chosen`; the current viewpoint (the identity pose) is among them when
/// the stage scores it, so compare expected traces with each other.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Default, ZeroCopySend)]
#[type_name("poseflow/NextView/v1")]
pub struct NextViewHeader {
    pub header: Header,
    pub chosen: [f32; 12],
    pub expected_rotation_trace: f32,
    pub current_rotation_trace: f32,
    pub candidate_count: u32,
    pub reserved: u32,
}

impl MessageHeader for NextViewHeader {
    const NAME: &'static str = "NextView";

    header_accessors!();

    fn payload_len(&self) -> Result<usize, ContractError> {
        let c = bounded(Self::NAME, "candidate_count", self.candidate_count, 1, limits::MAX_CANDIDATES, "1..=4096")?;
        Ok(c * CANDIDATE_LEN)
    }
}
