use std::path::PathBuf;

/// Why a model cannot be loaded or run; each names the file, input or
/// output and what was expected.
#[derive(Debug, thiserror::Error)]
pub enum InferenceError {
    #[error(transparent)]
    Onnx(#[from] poseflow_onnx::OnnxError),

    #[error("{path}: {detail}")]
    Model { path: PathBuf, detail: String },

    #[error("{model}: {detail}")]
    Run { model: &'static str, detail: String },

    #[error("param `{key}`: {detail}")]
    Params { key: String, detail: String },

    #[error("frame {frame}: observation rejected: {detail}")]
    Observation { frame: u64, detail: String },

    #[error(transparent)]
    Emit(#[from] poseflow_runtime::EmitError),
}
