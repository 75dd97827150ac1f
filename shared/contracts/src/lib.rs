//! Message layouts exchanged by PoseFlow stages over iceoryx2 shared memory.
//!
//! # Wire format
//!
//! Every message is an iceoryx2 publish-subscribe (or request-response)
//! sample made of
//!
//! 1. a **user header**: one of the `#[repr(C)]` structs below, fixed size,
//!    alignment 8, little-endian, no implicit padding; its first 80 bytes are
//!    always the common [`Header`] (frame id, object id, flags, per-stage
//!    timestamps);
//! 2. a **payload**: a flat slice of `f32` (little-endian IEEE-754) whose
//!    length the header determines, split into consecutive sections with no
//!    gaps ([`MessageHeader::payload_len`]).
//!
//! Each header's documentation has its byte-by-byte table; compile-time
//! assertions in this crate keep the tables true. The iceoryx2 type name of
//! each header (`type_name`, e.g. `poseflow/Observation/v2`) is stable and
//! versioned: a layout change gets a new version suffix. A Python or C++
//! stage reproduces a header as a C struct with the same fields in the same
//! order and registers it with the same type name.
//!
//! # Conventions
//!
//! - metres and radians; poses are object-to-camera (`x_cam = R x_obj + t`)
//!   as 12 `f32`: `R` row-major (9) then `t` (3);
//! - angular velocities are body-frame (`R ← R exp(dt ω)`);
//! - 6-vectors and 6×6 covariances are ordered translation first, rotation
//!   second;
//! - message timestamps are `CLOCK_REALTIME` nanoseconds since the UNIX
//!   epoch ([`stamp_clock_ns`]), the clock of ROS 2 stamps.
//!
//! | message | header | payload (`f32`) | from → to |
//! |---|---|---|---|
//! | Frame | [`FrameHeader`] | rgb 3·W·H ‖ depth W·H ‖ detections M·8 ‖ masks L | camera → detector → ingest |
//! | Observation | [`ObservationHeader`] | image 3·S·S ‖ token mask P·P ‖ points N·3 ‖ depth G·G ‖ mask G·G | ingest → inference, selector |
//! | Condition | [`ConditionHandle`] | none | inference → sampler |
//! | VelocityRequest | [`VelocityRequest`] | poses N·12 | sampler → inference |
//! | VelocityResponse | [`VelocityResponse`] | velocities N·6 | inference → sampler |
//! | Hypotheses | [`HypothesesHeader`] | poses N·12 | sampler → selector |
//! | Estimate | [`EstimateHeader`] | modes M·13 ‖ scored hypotheses N·13 | selector → grasp, nbv, robot |
//! | Grasps | [`GraspsHeader`] | grasps G·15 | grasp → robot |
//! | NextView | [`NextViewHeader`] | candidates C·13 | nbv → robot |
//! | Heartbeat | [`Heartbeat`] | none | every stage → supervisor |
//! | Tensor | [`TensorHeader`] | values ∏shape | plug-ins, benchmarks |

mod bytes;
mod category;
mod condition;
mod error;
mod estimate;
mod frame;
mod grasps;
mod header;
mod heartbeat;
mod message;
mod next_view;
mod observation;
mod tensor;
mod velocity;
mod visit;

#[cfg(test)]
mod tests;

pub use bytes::{header_bytes, header_from_bytes};
pub use category::ObjectCategory;
pub use condition::ConditionHandle;
pub use error::ContractError;
pub use estimate::{EstimateHeader, EstimateView, HypothesesHeader, SelectionMethod, WEIGHTED_POSE_LEN};
pub use frame::{DETECTION_LEN, Detection, FrameHeader, FrameView};
pub use grasps::{GRASP_LEN, GraspsHeader};
pub use header::{Header, STAGE_SLOTS, StageStamps, StampSlot, flags, monotonic_ns, stamp_clock_ns};
pub use heartbeat::{Heartbeat, StageState};
pub use message::{MessageHeader, POSE_LEN, VELOCITY_LEN, limits};
pub use next_view::{CANDIDATE_LEN, NextViewHeader};
pub use observation::{CameraIntrinsics, ObservationHeader, ObservationView};
pub use tensor::{MAX_TENSOR_LEN, TensorHeader};
pub use velocity::{MAX_SEGMENTS, VelocityRequest, VelocityResponse, VelocitySegment, status};
pub use visit::{MessageVisitor, PUBLISH_SUBSCRIBE_MESSAGES, REQUEST_RESPONSE_MESSAGES, visit_message};

/// The layout tables in the docs, checked by the compiler.
mod layout {
    use super::*;
    use core::mem::{align_of, offset_of, size_of};

    macro_rules! assert_layout {
        ($t:ty, size $size:expr, align $align:expr $(, $field:ident @ $offset:expr)*) => {
            const _: () = assert!(size_of::<$t>() == $size);
            const _: () = assert!(align_of::<$t>() == $align);
            $(const _: () = assert!(offset_of!($t, $field) == $offset);)*
        };
    }

    assert_layout!(StageStamps, size 64, align 8);
    assert_layout!(Header, size 80, align 8, frame_id @ 0, object_id @ 8, flags @ 12, stamps @ 16);
    assert_layout!(CameraIntrinsics, size 24, align 4, fx @ 0, fy @ 4, cx @ 8, cy @ 12, width @ 16, height @ 20);
    assert_layout!(FrameHeader, size 120, align 8,
        header @ 0, intrinsics @ 80, scene_id @ 104, image_id @ 108, detection_count @ 112, mask_len @ 116);
    assert_layout!(ObservationHeader, size 160, align 8,
        header @ 0, intrinsics @ 80, centroid @ 104, point_scale @ 116, crop @ 120,
        image_size @ 136, patch_grid @ 140, point_count @ 144, valid_point_count @ 148, depth_grid @ 152,
        depth_span @ 156);
    assert_layout!(ConditionHandle, size 136, align 8,
        header @ 0, condition_id @ 80, image_tokens @ 88, point_tokens @ 92,
        active_image_tokens @ 96, model_width @ 100, centroid @ 104, point_scale @ 116, category @ 120);
    assert_layout!(VelocitySegment, size 16, align 8, condition_id @ 0, sample_count @ 8, t @ 12);
    assert_layout!(VelocityRequest, size 360, align 8,
        header @ 0, request_id @ 80, segment_count @ 88, sample_count @ 92, step_index @ 96,
        step_count @ 100, segments @ 104);
    assert_layout!(VelocityResponse, size 96, align 8,
        header @ 0, request_id @ 80, sample_count @ 88, status @ 92);
    assert_layout!(ObjectCategory, size 16, align 4, code @ 0, size @ 4);
    assert_layout!(HypothesesHeader, size 104, align 8, header @ 0, sample_count @ 80, step_count @ 84, category @ 88);
    assert_layout!(EstimateHeader, size 360, align 8,
        header @ 0, best @ 80, mean @ 128, covariance @ 176, rotation_trace @ 320,
        selection @ 324, mode_count @ 328, hypothesis_count @ 332, kept_count @ 336, refined @ 340, category @ 344);
    assert_layout!(GraspsHeader, size 88, align 8, header @ 0, grasp_count @ 80, hypothesis_count @ 84);
    assert_layout!(Heartbeat, size 136, align 8,
        header @ 0, pid @ 80, state @ 84, frames_in @ 88, frames_out @ 96, dropped @ 104,
        errors @ 112, latency_p50_us @ 120, latency_p99_us @ 124, busy_us @ 128, blocked_us @ 132);
    assert_layout!(TensorHeader, size 104, align 8, header @ 0, shape @ 80, rank @ 96, reserved @ 100);
    assert_layout!(NextViewHeader, size 144, align 8,
        header @ 0, chosen @ 80, expected_rotation_trace @ 128, current_rotation_trace @ 132,
        candidate_count @ 136, reserved @ 140);
}
