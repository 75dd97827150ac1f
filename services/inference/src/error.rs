use std::path::PathBuf;

/// Why a model cannot be loaded or run; each names the file, input or
/// output and what was expected.
#[derive(Debug, thiserror::Error)]
pub enum InferenceError {
    #[error(
        "ONNX Runtime not found. Set ORT_DYLIB_PATH to libonnxruntime.so (1.17 or newer), or install the Python \
         package into the project's environment: `deploy/setup` (pip install onnxruntime==1.32.0 into \
         target/python-venv). Searched: {searched}"
    )]
    RuntimeMissing { searched: String },

    #[error("{path}: cannot load ONNX Runtime: {detail}")]
    RuntimeLoad { path: PathBuf, detail: String },

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
