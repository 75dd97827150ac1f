//! The inference stage's core: ONNX Runtime found and loaded at run time
//! ([`runtime`]), the PoseFlow encoder and velocity networks checked
//! against their contract at load ([`PoseFlowModel`]), the stage that
//! serves them ([`stage::InferenceStage`]), and the grasp flow's networks
//! ([`GraspFlowModel`]) for the grasp stage.

mod error;
mod grasp_model;
mod model;
pub mod parity;
pub mod stage;

pub use error::InferenceError;
pub use grasp_model::{GRASP_CONTRACT, GraspFlowModel, GraspModelInfo};
pub use model::{CONTRACTS, CategoryHead, Condition, EncoderInput, ModelInfo, PoseFlowModel, Precision, Velocities};

/// The stage of this crate: `inference` (Observation in, Condition handle
/// out, velocity requests served).
pub fn registrations() -> Vec<poseflow_runtime::Registration> {
    vec![poseflow_runtime::Registration::server("inference", |wiring| {
        let mut params = stage::InferenceParams::from_json(&wiring.params)?;
        // A reader a full queue behind, with a batch of handles in hand,
        // while this stage holds a batch for publishing, must still find its
        // conditions cached.
        let in_flight = wiring
            .outputs
            .iter()
            .map(|o| o.queue + params.batch + poseflow_contracts::MAX_SEGMENTS + 1)
            .max()
            .unwrap_or(0);
        if params.cache < in_flight {
            tracing::info!(cache = params.cache, in_flight, "cache raised to the conditions a reader can lag by");
            params.cache = in_flight;
        }
        let stage = stage::InferenceStage::new(&params)?;
        tracing::info!(
            model = %stage.model_dir().display(),
            precision = stage.precision().name(),
            threads = params.threads,
            "model loaded"
        );
        Ok::<_, poseflow_runtime::BuildError>(stage)
    })]
}
