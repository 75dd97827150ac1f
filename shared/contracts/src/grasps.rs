//! Grasp stage → robot: grasps that hold under the pose hypotheses.

use iceoryx2_bb_derive_macros::ZeroCopySend;
use iceoryx2_bb_elementary_traits::zero_copy_send::ZeroCopySend;

use crate::message::{MessageHeader, POSE_LEN, bounded, header_accessors, limits};
use crate::{ContractError, Header};

/// `f32` values per grasp: gripper pose (12), opening width, valid share,
/// score.
pub const GRASP_LEN: usize = POSE_LEN + 3;

/// User header of Grasps (88 bytes, alignment 8).
///
/// | offset | size | field            | type | meaning |
/// |-------:|-----:|------------------|------|---------|
/// | 0      | 80   | header           | [`Header`] | |
/// | 80     | 4    | grasp_count      | u32  | G |
/// | 84     | 4    | hypothesis_count | u32  | pose hypotheses the grasps were checked against |
///
/// Payload (`f32`): G grasps × 15: gripper-to-camera pose (12; gripper frame:
/// origin midway between the fingertips, z along the approach direction, x
/// along the closing direction), opening width (m), share of hypotheses
/// under which the grasp is valid (`[0, 1]`), score (higher is better).
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Default, ZeroCopySend)]
#[type_name("poseflow/Grasps/v1")]
pub struct GraspsHeader {
    pub header: Header,
    pub grasp_count: u32,
    pub hypothesis_count: u32,
}

impl MessageHeader for GraspsHeader {
    const NAME: &'static str = "Grasps";

    header_accessors!();

    fn payload_len(&self) -> Result<usize, ContractError> {
        bounded(Self::NAME, "hypothesis_count", self.hypothesis_count, 1, limits::MAX_SAMPLES, "1..=4096")?;
        let g = bounded(Self::NAME, "grasp_count", self.grasp_count, 0, limits::MAX_GRASPS, "0..=4096")?;
        Ok(g * GRASP_LEN)
    }
}
