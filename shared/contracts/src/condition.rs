//! Inference → sampler: the encoded observation is cached inside the
//! inference process; the sampler refers to it by this handle.

use iceoryx2_bb_derive_macros::ZeroCopySend;
use iceoryx2_bb_elementary_traits::zero_copy_send::ZeroCopySend;

use crate::message::{MessageHeader, header_accessors};
use crate::{ContractError, Header, ObjectCategory};

/// User header of a Condition handle (136 bytes, alignment 8). No payload.
///
/// | offset | size | field               | type     | meaning |
/// |-------:|-----:|---------------------|----------|---------|
/// | 0      | 80   | header              | [`Header`] | |
/// | 80     | 8    | condition_id        | u64      | key of the cached tokens in the inference stage |
/// | 88     | 4    | image_tokens        | u32      | number of image tokens |
/// | 92     | 4    | point_tokens        | u32      | number of point tokens |
/// | 96     | 4    | active_image_tokens | u32      | image tokens left active by the mask |
/// | 100    | 4    | model_width         | u32      | token width of the network |
/// | 104    | 12   | centroid            | [f32; 3] | copied from the Observation, to map poses back |
/// | 116    | 4    | point_scale         | f32      | copied from the Observation |
/// | 120    | 16   | category            | [`ObjectCategory`] | a category-level model's category and predicted size; zeros otherwise |
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Default, ZeroCopySend)]
#[type_name("poseflow/Condition/v2")]
pub struct ConditionHandle {
    pub header: Header,
    pub condition_id: u64,
    pub image_tokens: u32,
    pub point_tokens: u32,
    pub active_image_tokens: u32,
    pub model_width: u32,
    pub centroid: [f32; 3],
    pub point_scale: f32,
    pub category: ObjectCategory,
}

impl MessageHeader for ConditionHandle {
    const NAME: &'static str = "Condition";

    header_accessors!();

    fn payload_len(&self) -> Result<usize, ContractError> {
        self.category.check(Self::NAME)?;
        Ok(0)
    }
}
