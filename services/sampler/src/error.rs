/// Why a frame could not be sampled; each names the frame, object or
/// parameter concerned.
#[derive(Debug, thiserror::Error)]
pub enum SamplerError {
    #[error("param `{key}`: {detail}")]
    Params { key: &'static str, detail: String },

    #[error("frame {frame} object {object}: velocity request at step {step}: {detail}")]
    Velocity { frame: u64, object: u32, step: usize, detail: String },

    #[error("frame {frame} object {object}: {detail}")]
    Geometry { frame: u64, object: u32, detail: String },

    #[error(transparent)]
    Emit(#[from] poseflow_runtime::EmitError),
}
