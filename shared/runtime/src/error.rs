/// Why a stage process could not start or had to stop.
#[derive(Debug, thiserror::Error)]
pub enum RuntimeError {
    #[error("{0}")]
    Wiring(String),

    #[error("stage `{stage}`: expected {expected}, the graph gives {found}")]
    Shape { stage: String, expected: &'static str, found: String },

    #[error("stage `{stage}`: cannot build from its parameters: {reason}")]
    Build { stage: String, reason: String },

    #[error(transparent)]
    Transport(#[from] poseflow_transport::TransportError),

    #[error("waitset: {0}")]
    WaitSet(String),
}
