use std::path::PathBuf;

/// A mesh file that cannot be used, named with where and why.
#[derive(Debug, thiserror::Error)]
pub enum MeshError {
    #[error("{path}: cannot read: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },

    #[error("{path}: {location}: {detail}")]
    Malformed { path: PathBuf, location: String, detail: String },

    #[error("{path}: unknown mesh format (expected a .ply or .obj file)")]
    UnknownFormat { path: PathBuf },
}
