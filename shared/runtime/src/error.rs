/// Why a stage's `make` function could not build it: any error (a typed one
/// from the stage's library, or a message: `Err("...".into())`).
pub type BuildError = Box<dyn std::error::Error + Send + Sync + 'static>;

/// Why a stage process could not start or had to stop.
#[derive(Debug, thiserror::Error)]
pub enum RuntimeError {
    #[error(transparent)]
    Wiring(#[from] poseflow_graph::WiringError),

    #[error("stage `{stage}`: expected {expected}, the graph gives {found}")]
    Shape { stage: String, expected: &'static str, found: String },

    #[error("stage `{stage}`: cannot build from its parameters")]
    Build {
        stage: String,
        #[source]
        source: BuildError,
    },

    #[error(transparent)]
    Transport(#[from] poseflow_transport::TransportError),

    #[error("the stage's iceoryx2 waitset")]
    WaitSet(#[source] Box<dyn std::error::Error + Send + Sync>),

    #[error("cannot start the heartbeat thread")]
    HeartbeatThread(#[source] std::io::Error),

    #[error("the heartbeat thread ended during start-up")]
    HeartbeatThreadDied,

    #[error("stage `{stage}`: a {kind} stage cannot run in-process yet; run the graph as processes")]
    NotInProcess { stage: String, kind: &'static str },

    #[error(transparent)]
    Local(#[from] crate::local::LocalGraphError),
}

/// `err` and each of its sources, joined by ": " (a log line that keeps the
/// whole chain).
pub fn error_chain(err: &dyn std::error::Error) -> String {
    let mut text = err.to_string();
    let mut source = err.source();
    while let Some(cause) = source {
        text.push_str(": ");
        text.push_str(&cause.to_string());
        source = cause.source();
    }
    text
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_build_error_keeps_its_cause_in_the_chain() {
        let cause: BuildError = "model directory `m` has no encoder.onnx".into();
        let err = RuntimeError::Build { stage: "inference".into(), source: cause };
        assert_eq!(
            error_chain(&err),
            "stage `inference`: cannot build from its parameters: model directory `m` has no encoder.onnx"
        );
    }
}
