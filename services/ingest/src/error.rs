/// Why a frame or an object was not turned into an observation. Every
/// variant names where (file, frame, object) and what was expected.
#[derive(Debug, thiserror::Error)]
pub enum IngestError {
    #[error("param `{key}`: {detail}")]
    Params { key: String, detail: String },

    #[error("params: {0}")]
    ParamsFormat(String),

    #[error(transparent)]
    File(#[from] poseflow_scene::SceneError),

    #[error("{frame}: {detail}")]
    Frame { frame: String, detail: String },

    #[error("{frame}, object {obj_id} (instance {instance}): {detail}; object skipped")]
    Object { frame: String, obj_id: u32, instance: usize, detail: String },

    #[error(transparent)]
    Emit(#[from] poseflow_runtime::EmitError),
}
