//! The two ONNX networks of a PoseFlow model directory and their contract
//! (`training/poseflow_train/export.py`):
//!
//! - `encoder.onnx`: `image` [B,3,S,S] f32, `token_mask` [B,P·P] f32,
//!   `points` [B,N,3] f32, `object_index` [B] i64 → `condition` [B,T,D],
//!   `condition_mask` [B,T];
//! - `velocity.onnx`: `condition` [1,T,D], `condition_mask` [1,T],
//!   `rotation` [M,3,3], `translation` [M,3] (metres, relative to the
//!   observed points' mean), `t` [M] → `v_rot` [M,3] (body frame),
//!   `v_pos` [M,3].
//!
//! Metadata (ONNX `metadata_props`, JSON values) gives S, P, N, the
//! normalisation, the translation scale and noise, and the object ids.

use std::path::{Path, PathBuf};

use ort::session::Session;
use ort::session::builder::GraphOptimizationLevel;
use ort::value::{TensorElementType, TensorRef, ValueType};

use crate::InferenceError;

/// The contract version this crate serves.
pub const CONTRACT: &str = "poseflow-onnx/1";

/// What a model says about itself in its metadata.
#[derive(Debug, Clone, PartialEq)]
pub struct ModelInfo {
    pub image_size: usize,
    pub patch_grid: usize,
    pub point_count: usize,
    pub normalisation_mean: [f32; 3],
    pub normalisation_std: [f32; 3],
    /// Standard deviation (metres) of the flow's initial translations.
    pub translation_noise_std: f64,
    /// BOP object ids, in the order of `object_index`.
    pub object_ids: Vec<u32>,
    /// Condition tokens T and their width D.
    pub tokens: usize,
    pub width: usize,
}

/// One observation's encoded condition, kept by the inference stage and
/// reused for every velocity request of that observation.
#[derive(Debug, Clone, PartialEq)]
pub struct Condition {
    /// T·D values, row-major.
    pub tokens: Vec<f32>,
    /// T values, 1 = attend.
    pub mask: Vec<f32>,
}

/// Velocities of a batch: `v_rot` and `v_pos`, M·3 values each.
#[derive(Debug, Clone, PartialEq)]
pub struct Velocities {
    pub rotation: Vec<f32>,
    pub translation: Vec<f32>,
}

#[derive(Debug)]
pub struct PoseFlowModel {
    pub dir: PathBuf,
    pub info: ModelInfo,
    encoder: Session,
    velocity: Session,
}

/// An expected input or output: name, element type, dimensions (-1 = any).
pub(crate) struct Port {
    name: &'static str,
    ty: TensorElementType,
    dims: Vec<i64>,
}

pub(crate) fn port(name: &'static str, ty: TensorElementType, dims: &[i64]) -> Port {
    Port { name, ty, dims: dims.to_vec() }
}

/// Checks a session's inputs or outputs against the contract.
pub(crate) fn check_ports(
    path: &Path,
    what: &str,
    found: &[ort::value::Outlet],
    expected: &[Port],
) -> Result<(), InferenceError> {
    let bad = |detail: String| InferenceError::Model { path: path.to_path_buf(), detail };
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

pub(crate) fn session(path: &Path, threads: usize) -> Result<Session, InferenceError> {
    let model_error = |detail: String| InferenceError::Model { path: path.to_path_buf(), detail };
    if !path.is_file() {
        return Err(model_error(
            "no such file (a PoseFlow model directory holds encoder.onnx and velocity.onnx, a grasp flow model grasp_encoder.onnx and grasp_velocity.onnx)".into(),
        ));
    }
    let environment = crate::onnx_library::environment()?;
    Session::builder(environment)
        .and_then(|b| b.with_optimization_level(GraphOptimizationLevel::Level3).map_err(Into::into))
        .and_then(|b| b.with_intra_threads(threads).map_err(Into::into))
        // Idle pool threads sleep instead of spinning: a spinning pool of
        // the encoder steals a core from the velocity network and from the
        // other stages (2 cores: tracking 15.6 → 28.1 frames/s in-process,
        // 23.0 → 30.5 through the graph; `poseflow bench pipeline`).
        .and_then(|b| b.with_intra_op_spinning(false).map_err(Into::into))
        .and_then(|b| b.with_inter_op_spinning(false).map_err(Into::into))
        .and_then(|mut b| b.commit_from_file(path))
        .map_err(|e| model_error(e.to_string()))
}

/// The fixed token count T of a velocity network's `condition` input
/// (dimension 1), which the condition buffers are sized by.
pub(crate) fn condition_tokens(velocity: &Session, path: &Path) -> Result<i64, InferenceError> {
    velocity
        .inputs()
        .iter()
        .find(|o| o.name() == "condition")
        .and_then(|o| o.dtype().tensor_shape().and_then(|s| s.get(1).copied()))
        .filter(|&tokens| tokens > 0)
        .ok_or_else(|| InferenceError::Model {
            path: path.to_path_buf(),
            detail: "input `condition` needs a fixed token count (dimension 1)".into(),
        })
}

/// The two outputs every velocity network has: `v_rot` and `v_pos`, M × 3.
pub(crate) fn check_velocity_outputs(velocity: &Session, path: &Path) -> Result<(), InferenceError> {
    use TensorElementType::Float32 as F;
    check_ports(path, "outputs", velocity.outputs(), &[port("v_rot", F, &[-1, 3]), port("v_pos", F, &[-1, 3])])
}

/// A metadata value parsed as JSON into `T`.
pub(crate) fn meta<T: serde::de::DeserializeOwned>(
    session: &Session,
    path: &Path,
    key: &str,
) -> Result<T, InferenceError> {
    let bad = |detail: String| InferenceError::Model { path: path.to_path_buf(), detail };
    let metadata = session.metadata().map_err(|e| bad(e.to_string()))?;
    let text = metadata.custom(key).ok_or_else(|| bad(format!("metadata has no `{key}`")))?;
    serde_json::from_str(&text)
        .or_else(|_| serde_json::from_value(serde_json::Value::String(text.clone())))
        .map_err(|e| bad(format!("metadata `{key}` = {text:?}: {e}")))
}

/// An encoder and a velocity session from one model directory.
pub(crate) struct SessionPair {
    pub encoder: Session,
    pub encoder_path: PathBuf,
    pub velocity: Session,
    pub velocity_path: PathBuf,
}

/// Opens `<dir>/<files[0]>` (encoder) and `<dir>/<files[1]>` (velocity)
/// and checks that the encoder's metadata declares `contract`.
pub(crate) fn open_pair(
    dir: &Path,
    files: [&str; 2],
    threads: usize,
    contract: &str,
) -> Result<SessionPair, InferenceError> {
    let (encoder_path, velocity_path) = (dir.join(files[0]), dir.join(files[1]));
    let encoder = session(&encoder_path, threads)?;
    let velocity = session(&velocity_path, threads)?;
    let declared: String = meta(&encoder, &encoder_path, "contract")?;
    if declared != contract {
        return Err(InferenceError::Model {
            path: encoder_path,
            detail: format!("metadata `contract` = {declared:?}, this build serves {contract:?}"),
        });
    }
    Ok(SessionPair { encoder, encoder_path, velocity, velocity_path })
}

impl PoseFlowModel {
    /// Loads and checks `<dir>/encoder.onnx` and `<dir>/velocity.onnx`.
    pub fn load(dir: &Path, threads: usize) -> Result<Self, InferenceError> {
        let SessionPair { encoder, encoder_path, velocity, velocity_path } =
            open_pair(dir, ["encoder.onnx", "velocity.onnx"], threads, CONTRACT)?;
        let (s, p, n): (i64, i64, i64) = (
            meta(&encoder, &encoder_path, "image_size")?,
            meta(&encoder, &encoder_path, "patch_grid")?,
            meta(&encoder, &encoder_path, "point_count")?,
        );
        let width: i64 = meta(&encoder, &encoder_path, "width")?;
        use TensorElementType::{Float32 as F, Int64 as I};
        check_ports(
            &encoder_path,
            "inputs",
            encoder.inputs(),
            &[
                port("image", F, &[-1, 3, s, s]),
                port("token_mask", F, &[-1, p * p]),
                port("points", F, &[-1, n, 3]),
                port("object_index", I, &[-1]),
            ],
        )?;
        check_ports(
            &encoder_path,
            "outputs",
            encoder.outputs(),
            &[port("condition", F, &[-1, -1, width]), port("condition_mask", F, &[-1, -1])],
        )?;
        let t_dim = condition_tokens(&velocity, &velocity_path)?;
        check_ports(
            &velocity_path,
            "inputs",
            velocity.inputs(),
            &[
                port("condition", F, &[1, t_dim, width]),
                port("condition_mask", F, &[1, t_dim]),
                port("rotation", F, &[-1, 3, 3]),
                port("translation", F, &[-1, 3]),
                port("t", F, &[-1]),
            ],
        )?;
        check_velocity_outputs(&velocity, &velocity_path)?;
        let info = ModelInfo {
            image_size: s as usize,
            patch_grid: p as usize,
            point_count: n as usize,
            normalisation_mean: meta(&encoder, &encoder_path, "normalisation_mean")?,
            normalisation_std: meta(&encoder, &encoder_path, "normalisation_std")?,
            translation_noise_std: meta(&encoder, &encoder_path, "translation_noise_std")?,
            object_ids: meta(&encoder, &encoder_path, "object_ids")?,
            tokens: t_dim as usize,
            width: width as usize,
        };
        Ok(Self { dir: dir.to_path_buf(), info, encoder, velocity })
    }

    /// Index of a BOP object id for `object_index`.
    pub fn object_index(&self, obj_id: u32) -> Option<usize> {
        self.info.object_ids.iter().position(|&id| id == obj_id)
    }

    /// Encodes one observation (payload sections of an Observation).
    pub fn encode(
        &mut self,
        image: &[f32],
        token_mask: &[f32],
        points: &[f32],
        object_index: usize,
    ) -> Result<Condition, InferenceError> {
        let (s, p, n) = (self.info.image_size, self.info.patch_grid, self.info.point_count);
        let run_error = |e: ort::Error| InferenceError::Run { model: "encoder", detail: e.to_string() };
        let index = [object_index as i64];
        let outputs = self
            .encoder
            .run(ort::inputs![
                "image" => TensorRef::from_array_view(([1usize, 3, s, s], image)).map_err(run_error)?,
                "token_mask" => TensorRef::from_array_view(([1usize, p * p], token_mask)).map_err(run_error)?,
                "points" => TensorRef::from_array_view(([1usize, n, 3], points)).map_err(run_error)?,
                "object_index" => TensorRef::from_array_view(([1usize], &index[..])).map_err(run_error)?,
            ])
            .map_err(run_error)?;
        let (_, tokens) = outputs["condition"].try_extract_tensor::<f32>().map_err(run_error)?;
        let (_, mask) = outputs["condition_mask"].try_extract_tensor::<f32>().map_err(run_error)?;
        Ok(Condition { tokens: tokens.to_vec(), mask: mask.to_vec() })
    }

    /// Velocities for M poses (`rotations` M·9 row-major, `translations` M·3,
    /// `t` M) under one condition.
    pub fn velocity(
        &mut self,
        condition: &Condition,
        rotations: &[f32],
        translations: &[f32],
        t: &[f32],
    ) -> Result<Velocities, InferenceError> {
        let (tk, d, m) = (self.info.tokens, self.info.width, t.len());
        let run_error = |e: ort::Error| InferenceError::Run { model: "velocity", detail: e.to_string() };
        let outputs = self
            .velocity
            .run(ort::inputs![
                "condition" => TensorRef::from_array_view(([1usize, tk, d], &condition.tokens[..])).map_err(run_error)?,
                "condition_mask" => TensorRef::from_array_view(([1usize, tk], &condition.mask[..])).map_err(run_error)?,
                "rotation" => TensorRef::from_array_view(([m, 3, 3], rotations)).map_err(run_error)?,
                "translation" => TensorRef::from_array_view(([m, 3], translations)).map_err(run_error)?,
                "t" => TensorRef::from_array_view(([m], t)).map_err(run_error)?,
            ])
            .map_err(run_error)?;
        let (_, rotation) = outputs["v_rot"].try_extract_tensor::<f32>().map_err(run_error)?;
        let (_, translation) = outputs["v_pos"].try_extract_tensor::<f32>().map_err(run_error)?;
        Ok(Velocities { rotation: rotation.to_vec(), translation: translation.to_vec() })
    }
}
