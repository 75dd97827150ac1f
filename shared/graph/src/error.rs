use std::path::PathBuf;

/// A graph file that cannot run. `key` is the dotted TOML path of the
/// offending entry (e.g. `stages.relay.inputs`).
#[derive(Debug, thiserror::Error)]
pub enum GraphError {
    #[error("{file}: cannot read")]
    Read {
        file: PathBuf,
        #[source]
        source: std::io::Error,
    },

    #[error("{file}: {message}")]
    Syntax { file: PathBuf, message: String },

    #[error("{file}: `{key}`: expected {expected}, found {found}")]
    Invalid { file: PathBuf, key: String, expected: String, found: String },
}
