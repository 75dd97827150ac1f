use std::path::PathBuf;

/// Why the next-best-view stage cannot start or plan a frame; each names
/// the parameter, file, frame or object concerned.
#[derive(Debug, thiserror::Error)]
pub enum NbvError {
    #[error("param `{key}`: {detail}")]
    Params { key: String, detail: String },

    #[error("{path}: {detail}")]
    Objects { path: PathBuf, detail: String },

    #[error(transparent)]
    Pipeline(#[from] poseflow_pipeline::PipelineError),

    #[error("frame {frame} object {object}: {detail}")]
    Frame { frame: u64, object: u32, detail: String },

    #[error("frame {frame} (side input): {detail}; planning without its occluders")]
    SideFrame { frame: u64, detail: String },

    #[error(transparent)]
    Emit(#[from] poseflow_runtime::EmitError),
}
