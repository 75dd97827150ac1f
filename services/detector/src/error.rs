use std::path::PathBuf;

/// Why the detector cannot start or could not handle a frame; each names
/// the file, parameter or frame and what was expected.
#[derive(Debug, thiserror::Error)]
pub enum DetectorError {
    #[error("{path}: {detail}")]
    Model { path: PathBuf, detail: String },

    #[error("{path}: cannot load the objects' meshes")]
    Models {
        path: PathBuf,
        #[source]
        source: poseflow_scene::SceneError,
    },

    #[error(transparent)]
    Onnx(#[from] poseflow_onnx::OnnxError),

    #[error("{path}: running the network: {detail}")]
    Run { path: PathBuf, detail: String },

    #[error("detector parameters: {0}")]
    ParamsFormat(String),

    #[error("param `{key}`: {detail}")]
    Params { key: String, detail: String },

    #[error("frame {frame}: {detail}")]
    Frame { frame: u64, detail: String },

    #[error(transparent)]
    Emit(#[from] poseflow_runtime::EmitError),
}
