//! The flow sampler: turns a Condition handle into N pose hypotheses by
//! integrating the learned velocity field on SE(3) (paper, "Inference"),
//! asking the inference stage for the velocities of all N samples at once
//! per Euler step.
//!
//! The heart is [`FlowSampler::sample`], a plain function of a handle, a
//! start ([`Start`]) and a [`VelocityField`]; the same code runs in-process
//! (the field is the inference stage's library) and as a process (the field
//! is an iceoryx2 request-response client, [`stage::RemoteField`]).

mod error;
mod flow;
mod params;
pub mod stage;

pub use error::{FieldError, SamplerError};
pub use flow::{FlowSampler, Start, VelocityField};
pub use params::{SamplerParams, TrackingParams};

/// The stage of this crate: `sampler` (Condition handles in, Hypotheses
/// out; velocities asked of the inference stage over the request-response
/// edge in `calls`; with the selector's Estimates as a side input it
/// tracks).
pub fn registrations() -> Vec<poseflow_runtime::Registration> {
    vec![poseflow_runtime::Registration::transform_or_joined("sampler", stage::from_wiring)]
}
