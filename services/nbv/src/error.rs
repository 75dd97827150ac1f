use std::path::PathBuf;

/// Why the next-best-view stage cannot start or plan a frame; each names
/// the parameter, file, frame or object concerned.
#[derive(Debug, thiserror::Error)]
pub enum NbvError {
    #[error("param `{key}`: {detail}")]
    Params { key: String, detail: String },

    #[error("{path}: {detail}")]
    Objects { path: PathBuf, detail: String },

    #[error("the pose stages that score views")]
    Estimation(#[source] Box<poseflow_launch::LaunchError>),

    #[error("frame {frame} object {object}: a simulated view")]
    View {
        frame: u64,
        object: u32,
        #[source]
        source: Box<crate::PoseStagesError>,
    },

    #[error("frame {frame} object {object}: {detail}")]
    Frame { frame: u64, object: u32, detail: String },

    #[error("frame {frame} (side input): {detail}; planning without its occluders")]
    SideFrame { frame: u64, detail: String },

    #[error(transparent)]
    Emit(#[from] poseflow_runtime::EmitError),
}

impl From<poseflow_launch::LaunchError> for NbvError {
    fn from(err: poseflow_launch::LaunchError) -> Self {
        NbvError::Estimation(Box::new(err))
    }
}
