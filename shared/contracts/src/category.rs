//! What a category-level model says of an object beyond its pose.

use iceoryx2_bb_derive_macros::ZeroCopySend;
use iceoryx2_bb_elementary_traits::zero_copy_send::ZeroCopySend;

use crate::ContractError;

/// An object's category and size, carried from the inference stage (a
/// category-level model predicts them) through the sampler to the
/// selector's Estimate. All zero for an instance-level model, whose object
/// id names the exact object and whose mesh gives its size.
///
/// | offset | size | field | type     | meaning |
/// |-------:|-----:|-------|----------|---------|
/// | 0      | 4    | code  | u32      | the model's category code (REAL275's: 1 bottle, 2 bowl, 3 camera, 4 can, 5 laptop, 6 mug); 0 = none |
/// | 4      | 12   | size  | [f32; 3] | extents of the object's bounding box along its canonical x, y, z, metres |
///
/// The canonical frame is NOCS's: y up the symmetry axis, a mug's handle
/// towards +x, the bounding box centred on the origin; the pose in the
/// same message maps that frame to the camera.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Default, ZeroCopySend)]
#[type_name("poseflow/ObjectCategory/v1")]
pub struct ObjectCategory {
    pub code: u32,
    pub size: [f32; 3],
}

impl ObjectCategory {
    /// Whether a category-level model filled it in.
    pub fn is_set(&self) -> bool {
        self.code != 0
    }

    /// Checks a filled-in category: finite, positive extents.
    pub fn check(&self, message: &'static str) -> Result<(), ContractError> {
        if self.is_set() && !self.size.iter().all(|s| s.is_finite() && *s > 0.0) {
            return Err(ContractError::InvalidField {
                message,
                field: "category.size",
                value: format!("{:?}", self.size),
                expected: "finite extents > 0 m when category.code is set",
            });
        }
        Ok(())
    }
}
