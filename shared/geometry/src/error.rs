use std::path::PathBuf;

/// Everything that can go wrong in this crate. Messages name the input and
/// what was expected, so a user can fix a file without reading the source.
#[derive(Debug, thiserror::Error)]
pub enum GeometryError {
    #[error("{what}: expected at least one element, got none")]
    Empty { what: &'static str },

    #[error("{what}: expected {expected} elements, got {actual}")]
    LengthMismatch { what: &'static str, expected: usize, actual: usize },

    #[error("weights: expected finite, non-negative values with a positive sum, got {detail}")]
    InvalidWeights { detail: String },

    #[error("flow time t = {t}: expected 0 <= t < 1 (the velocity is undefined at t = 1)")]
    FlowTimeOutOfRange { t: f64 },

    #[error("{what}: expected finite values, got {values:?}")]
    NonFinite { what: &'static str, values: Vec<f64> },

    #[error("{what}: expected a rotation matrix (orthonormal, det +1), got {detail}")]
    NotARotation { what: String, detail: String },

    #[error("eigen-decomposition of a {size}x{size} covariance did not converge")]
    EigenNoConvergence { size: usize },

    #[error("{path}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },

    #[error("{path}: invalid JSON")]
    Json {
        path: PathBuf,
        #[source]
        source: serde_json::Error,
    },

    #[error("{path}: object {object}: expected a BOP models_info entry")]
    ModelInfoEntry {
        path: PathBuf,
        object: String,
        #[source]
        source: serde_json::Error,
    },

    #[error("{path}: object {object}: field `{field}`: {expected}, got {value}")]
    ModelInfoField { path: PathBuf, object: String, field: &'static str, expected: &'static str, value: String },
}
