/// Why a selection or the stage's set-up failed; each names the parameter,
/// file, frame or object concerned.
#[derive(Debug, thiserror::Error)]
pub enum SelectorError {
    #[error("param `{key}`: {detail}")]
    Params { key: &'static str, detail: String },

    #[error(transparent)]
    ObjectModel(#[from] poseflow_scene::SceneError),

    #[error("{detail}")]
    Selection { detail: String },

    #[error("frame {frame} object {object}: {detail}")]
    Frame { frame: u64, object: u32, detail: String },

    #[error(transparent)]
    Emit(#[from] poseflow_runtime::EmitError),
}
