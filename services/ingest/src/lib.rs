//! The ingest stage: RGB-D frames and object masks in, Observations out.
//!
//! Per object ([`prepare`], then [`Prepared::write_payload`] straight into
//! the output buffer): the mask's box grown to a padded square and
//! resampled to S×S, normalised; the P×P token mask of patches the mask
//! touches; mask pixels behind a nearer mask pixel (background past the
//! outline) dropped; masked depth back-projected with the intrinsics, thinned,
//! cleaned of outliers, farthest-point sampled to N (resampled with
//! replacement, and flagged, when fewer), centred on its mean, which the
//! header keeps so poses can be mapped back to the camera frame.
//!
//! Frames come from [`sources`]: a BOP dataset directory or the renderer
//! as a live synthetic camera.

mod crop;
mod edges;
mod error;
mod frame_message;
mod jitter;
mod observe;
mod params;
mod points;
pub mod shard;
pub mod sources;
pub mod stage;
pub mod truth_prior;

pub use crop::{CropBox, Normalisation, write_crop, write_token_mask};
pub use edges::EdgeFilter;
pub use error::IngestError;
pub use frame_message::{FrameLayout, frame_message, read_frame};
pub use jitter::MaskJitter;
pub use observe::{ObjectMask, Prepared, RgbdFrame, check_frame, prepare};
pub use params::IngestParams;
pub use points::{OutlierFilter, back_project, centre, remove_outliers, sample_fixed, thin};

/// The stages of this crate, by the executable names graph files give them:
/// `frame-source` (Frames from a BOP dataset or the renderer), `ingest`
/// (Frame in, Observation out) and `truth-prior` (Observation in, the
/// perturbed ground truth out as an Estimate).
pub fn registrations() -> Vec<poseflow_runtime::Registration> {
    use poseflow_runtime::Registration;
    vec![
        Registration::source("frame-source", |wiring| {
            stage::frame_source(&wiring.params).map(stage::FrameSourceStage::new)
        }),
        Registration::transform("ingest", |wiring| {
            IngestParams::from_json(&wiring.params).map(stage::IngestStage::new)
        }),
        Registration::transform("truth-prior", |wiring| {
            truth_prior::TruthPriorParams::from_json(&wiring.params).and_then(truth_prior::TruthPriorStage::new)
        }),
    ]
}
