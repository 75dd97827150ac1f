use std::path::PathBuf;

/// A mesh, model directory or dataset file that cannot be used, named with
/// where and why.
#[derive(Debug, thiserror::Error)]
pub enum SceneError {
    #[error("{path}: cannot read")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },

    #[error("{path}: cannot write")]
    Write {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },

    #[error("{path}: cannot build a triangle mesh of the model")]
    TriMesh {
        path: PathBuf,
        #[source]
        source: parry3d::shape::TriMeshBuilderError,
    },

    #[error("{path}: {location}: {detail}")]
    Malformed { path: PathBuf, location: String, detail: String },

    #[error("{path}: cannot read the objects' information")]
    ModelsInfo {
        path: PathBuf,
        #[source]
        source: Box<poseflow_geometry::GeometryError>,
    },

    #[error("{path}: {detail}")]
    NoModels { path: PathBuf, detail: String },

    #[error("{path}: unknown mesh format (expected a .ply or .obj file)")]
    UnknownFormat { path: PathBuf },

    #[error("{path}: {detail}")]
    Image { path: PathBuf, detail: String },

    #[error("{0}")]
    Invalid(String),

    #[error("scene {scene_id} image {im_id}: no view in {attempts} random cameras shows {condition}")]
    NoView { scene_id: u32, im_id: u32, attempts: usize, condition: String },
}

impl SceneError {
    pub(crate) fn malformed(path: &std::path::Path, location: impl Into<String>, detail: impl Into<String>) -> Self {
        Self::Malformed { path: path.to_path_buf(), location: location.into(), detail: detail.into() }
    }
}
