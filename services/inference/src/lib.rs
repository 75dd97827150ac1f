//! The inference stage's core: ONNX Runtime found and loaded at run time
//! ([`runtime`]), the PoseFlow encoder and velocity networks checked
//! against their contract at load ([`PoseFlowModel`]), the stage that
//! serves them ([`stage::InferenceStage`]), and the grasp flow's networks
//! ([`GraspFlowModel`]) for the grasp stage.

mod error;
mod grasp_model;
mod model;
pub mod onnx_library;
pub mod stage;

pub use error::InferenceError;
pub use grasp_model::{GRASP_CONTRACT, GraspFlowModel, GraspModelInfo};
pub use model::{CONTRACT, Condition, ModelInfo, PoseFlowModel, Velocities};
