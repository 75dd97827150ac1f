/// Why a frame could not be sampled; each names the frame, object or
/// parameter concerned.
#[derive(Debug, thiserror::Error)]
pub enum SamplerError {
    #[error("param `{key}`: {detail}")]
    Params { key: &'static str, detail: String },

    #[error("frame {frame} object {object}: velocity request at step {step}")]
    Velocity {
        frame: u64,
        object: u32,
        step: usize,
        #[source]
        source: FieldError,
    },

    #[error("frame {frame} object {object}: velocity {component} of sample {sample} is not finite at step {step}")]
    NonFinite { frame: u64, object: u32, step: usize, component: usize, sample: usize },

    #[error("frame {frame} object {object}: {detail}")]
    Geometry { frame: u64, object: u32, detail: String },

    #[error(transparent)]
    Emit(#[from] poseflow_runtime::EmitError),
}

/// Why a [`crate::VelocityField`] gave no velocities.
#[derive(Debug, thiserror::Error)]
pub enum FieldError {
    /// The request-response call did not complete (no server, timeout,
    /// transport).
    #[error("the velocity call failed")]
    Call(#[source] Box<dyn std::error::Error + Send + Sync>),

    /// The inference stage answered with a failure status
    /// (`poseflow_contracts::velocity_status`).
    #[error("inference answered status {status}: {meaning}")]
    Status { status: u32, meaning: &'static str },

    /// The call completed without an answer.
    #[error("the velocity call returned no response")]
    NoResponse,

    /// An answer that does not belong to the request.
    #[error("answer to request {answered} with {values} values, expected request {expected} with {expected_values}")]
    Mismatch { answered: u64, values: usize, expected: u64, expected_values: usize },
}

impl FieldError {
    /// A velocity response's failure `status`, with what it means.
    pub fn status(status: u32) -> Self {
        use poseflow_contracts::status as velocity_status;
        let meaning = match status {
            velocity_status::UNKNOWN_CONDITION => "unknown condition (the inference stage restarted or evicted it)",
            velocity_status::INVALID_REQUEST => "invalid request",
            velocity_status::INFERENCE_FAILED => "the network failed",
            _ => "unknown status",
        };
        Self::Status { status, meaning }
    }
}
