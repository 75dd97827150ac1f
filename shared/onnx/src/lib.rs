//! ONNX Runtime for the stages that run networks (inference, detector):
//! one library loaded once per process, sessions built alike, and their
//! inputs and outputs checked against the contract a stage expects before
//! the first frame arrives.

use std::path::{Path, PathBuf};

use ort::session::Session;
use ort::session::builder::GraphOptimizationLevel;
use ort::value::{TensorElementType, ValueType};

mod library;

pub use library::{environment, find_library};

/// Why ONNX Runtime or a model cannot be loaded; each names the file and
/// what was expected.
#[derive(Debug, thiserror::Error)]
pub enum OnnxError {
    #[error(
        "ONNX Runtime not found. Set ORT_DYLIB_PATH to libonnxruntime.so (1.17 or newer), or install the Python \
         package into the project's environment: `deploy/setup` (pip install onnxruntime==1.32.0 into \
         target/python-venv). Searched: {searched}"
    )]
    RuntimeMissing { searched: String },

    #[error("{path}: cannot load ONNX Runtime: {detail}")]
    RuntimeLoad { path: PathBuf, detail: String },

    #[error("{path}: {detail}")]
    Model { path: PathBuf, detail: String },
}

/// A session on `path` with `threads` intra-op threads. `missing` says what
/// the file should have been, for the error when it is absent.
pub fn session(path: &Path, threads: usize, missing: &str) -> Result<Session, OnnxError> {
    let model_error = |detail: String| OnnxError::Model { path: path.to_path_buf(), detail };
    if !path.is_file() {
        return Err(model_error(format!("no such file ({missing})")));
    }
    let environment = environment()?;
    Session::builder(environment)
        .and_then(|b| b.with_optimization_level(GraphOptimizationLevel::Level3).map_err(Into::into))
        .and_then(|b| b.with_intra_threads(threads).map_err(Into::into))
        // Idle pool threads sleep instead of spinning: a spinning pool of
        // one network steals a core from the next one and from the other
        // stages (2 cores: tracking 15.6 → 28.1 frames/s in-process, 23.0 →
        // 30.5 through the graph; `poseflow bench pipeline`).
        .and_then(|b| b.with_intra_op_spinning(false).map_err(Into::into))
        .and_then(|b| b.with_inter_op_spinning(false).map_err(Into::into))
        .and_then(|mut b| b.commit_from_file(path))
        .map_err(|e| model_error(e.to_string()))
}

/// An expected input or output: name, element type, dimensions (-1 = any).
#[derive(Debug)]
pub struct Port {
    name: &'static str,
    ty: TensorElementType,
    dims: Vec<i64>,
}

pub fn port(name: &'static str, ty: TensorElementType, dims: &[i64]) -> Port {
    Port { name, ty, dims: dims.to_vec() }
}

/// Checks a session's inputs or outputs (`what`) against the contract.
pub fn check_ports(path: &Path, what: &str, found: &[ort::value::Outlet], expected: &[Port]) -> Result<(), OnnxError> {
    let bad = |detail: String| OnnxError::Model { path: path.to_path_buf(), detail };
    let names: Vec<&str> = found.iter().map(|o| o.name()).collect();
    if names.len() != expected.len() || expected.iter().any(|e| !names.contains(&e.name)) {
        return Err(bad(format!(
            "{what} are {names:?}, expected {:?}",
            expected.iter().map(|e| e.name).collect::<Vec<_>>()
        )));
    }
    for e in expected {
        let outlet = found.iter().find(|o| o.name() == e.name).expect("checked above");
        let ValueType::Tensor { ty, shape, .. } = outlet.dtype() else {
            return Err(bad(format!("{what} `{}` is not a tensor", e.name)));
        };
        let dims: Vec<i64> = shape.iter().copied().collect();
        let fits = *ty == e.ty
            && dims.len() == e.dims.len()
            && dims.iter().zip(&e.dims).all(|(&d, &want)| want < 0 || d < 0 || d == want);
        if !fits {
            return Err(bad(format!(
                "{what} `{}` is {ty:?} {dims:?}, expected {:?} {:?} (-1 = any)",
                e.name, e.ty, e.dims
            )));
        }
    }
    Ok(())
}
