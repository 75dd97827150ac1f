/// Why the grasp stage cannot start or plan a frame; each names the
/// parameter, file, frame or object concerned.
#[derive(Debug, thiserror::Error)]
pub enum GraspError {
    #[error("param `{key}`: {detail}")]
    Params { key: &'static str, detail: String },

    #[error("the grasp stage's params")]
    ParamsJson(#[source] serde_json::Error),

    #[error("param `gripper`")]
    Gripper(#[source] crate::GripperError),

    #[error(transparent)]
    ObjectModels(#[from] poseflow_scene::SceneError),

    #[error(transparent)]
    Model(#[from] poseflow_inference::InferenceError),

    #[error("frame {frame} object {object}: {detail}")]
    Frame { frame: u64, object: u32, detail: String },

    #[error("frame {frame} object {object}: no grasps planned")]
    Plan {
        frame: u64,
        object: u32,
        #[source]
        source: crate::MeanFieldError,
    },

    #[error(transparent)]
    Emit(#[from] poseflow_runtime::EmitError),
}
