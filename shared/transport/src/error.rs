/// Failures of the iceoryx2 transport. Each names the service or port and
/// the operation that failed.
#[derive(Debug, thiserror::Error)]
pub enum TransportError {
    #[error("invalid name {name:?}: {detail}")]
    Name { name: String, detail: String },

    #[error("{operation} `{target}` failed: {detail}")]
    Iceoryx { operation: &'static str, target: String, detail: String },

    #[error("payload of {len} f32 values exceeds the edge's max_payload_len of {max}")]
    PayloadTooLarge { len: usize, max: usize },

    #[error("no {operation} on `{target}` within {after:?}")]
    Timeout { operation: &'static str, target: String, after: std::time::Duration },

    #[error("no server holds the request on `{target}`: none was running, or it stopped or restarted before answering")]
    NoServer { target: String },

    #[error("{operation} on `{target}` abandoned: the process was asked to stop")]
    Interrupted { operation: &'static str, target: String },

    #[error("a {message} header has {expected} bytes, found {found}")]
    HeaderSize { message: &'static str, expected: usize, found: usize },

    #[error("{message:?} is not a contract message")]
    UnknownMessage { message: String },

    #[error(transparent)]
    Contract(#[from] poseflow_contracts::ContractError),
}

impl TransportError {
    pub(crate) fn iceoryx(operation: &'static str, target: &str, err: impl std::fmt::Debug) -> Self {
        Self::Iceoryx { operation, target: target.to_string(), detail: format!("{err:?}") }
    }
}
