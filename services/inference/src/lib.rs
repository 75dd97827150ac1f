//! The inference stage's core: ONNX Runtime found and loaded at run time
//! ([`runtime`]), the PoseFlow encoder and velocity networks checked
//! against their contract at load ([`PoseFlowModel`]), and the stage that
//! serves them ([`stage::InferenceStage`]).

mod error;
mod model;
pub mod runtime;
pub mod stage;

pub use error::InferenceError;
pub use model::{CONTRACT, Condition, ModelInfo, PoseFlowModel, Velocities};
