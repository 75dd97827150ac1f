//! The grasp flow's two ONNX networks and their contract
//! (`training/poseflow_train/grasp.py`, `export`):
//!
//! - `grasp_encoder.onnx`: `points` [B,P,3] f32 (a zero-mean object cloud,
//!   metres) → `condition` [B,T,D];
//! - `grasp_velocity.onnx`: `condition` [B,T,D], `rotation` [B·G,3,3],
//!   `translation` [B·G,3] (metres, relative to the cloud's mean), `t`
//!   [B·G] → `v_rot` [B·G,3] (body frame), `v_pos` [B·G,3]; the G grasps
//!   of each cloud in a row.
//!
//! Metadata: `contract`, `point_count`, `translation_noise_std`, `gripper`
//! (the gripper the training grasps were checked with, JSON).

use std::path::{Path, PathBuf};

use ort::session::Session;
use ort::value::{TensorElementType, TensorRef};

use crate::InferenceError;
use crate::model::{SessionPair, check_ports, check_velocity_outputs, condition_tokens, meta, open_pair, port};

/// The grasp contract version this crate serves.
pub const GRASP_CONTRACT: &str = "poseflow-grasp-onnx/1";

/// What a grasp flow model says about itself.
#[derive(Debug, Clone, PartialEq)]
pub struct GraspModelInfo {
    /// Points P of each cloud.
    pub point_count: usize,
    /// Standard deviation (metres) of the flow's initial grasp positions.
    pub translation_noise_std: f64,
    /// The gripper of the training data, as JSON.
    pub gripper: serde_json::Value,
    /// Condition tokens T and their width D.
    pub tokens: usize,
    pub width: usize,
}

#[derive(Debug)]
pub struct GraspFlowModel {
    pub dir: PathBuf,
    pub info: GraspModelInfo,
    encoder: Session,
    velocity: Session,
}

impl GraspFlowModel {
    /// Loads and checks `<dir>/grasp_encoder.onnx` and `<dir>/grasp_velocity.onnx`.
    pub fn load(dir: &Path, threads: usize) -> Result<Self, InferenceError> {
        let SessionPair { encoder, encoder_path, velocity, velocity_path } =
            open_pair(dir, ["grasp_encoder.onnx", "grasp_velocity.onnx"], threads, &[GRASP_CONTRACT])?.0;
        let n: i64 = meta(&encoder, &encoder_path, "point_count")?;
        let width: i64 = meta(&encoder, &encoder_path, "width")?;
        use TensorElementType::Float32 as F;
        check_ports(&encoder_path, "inputs", encoder.inputs(), &[port("points", F, &[-1, n, 3])])?;
        check_ports(&encoder_path, "outputs", encoder.outputs(), &[port("condition", F, &[-1, -1, width])])?;
        let tokens = condition_tokens(&velocity, &velocity_path)?;
        check_ports(
            &velocity_path,
            "inputs",
            velocity.inputs(),
            &[
                port("condition", F, &[-1, tokens, width]),
                port("rotation", F, &[-1, 3, 3]),
                port("translation", F, &[-1, 3]),
                port("t", F, &[-1]),
            ],
        )?;
        check_velocity_outputs(&velocity, &velocity_path)?;
        let info = GraspModelInfo {
            point_count: n as usize,
            translation_noise_std: meta(&encoder, &encoder_path, "translation_noise_std")?,
            gripper: meta(&encoder, &encoder_path, "gripper")?,
            tokens: tokens as usize,
            width: width as usize,
        };
        Ok(Self { dir: dir.to_path_buf(), info, encoder, velocity })
    }

    /// Encodes B zero-mean clouds (`points` B·P·3): B·T·D condition values.
    pub fn encode(&mut self, points: &[f32]) -> Result<Vec<f32>, InferenceError> {
        let n = self.info.point_count;
        let clouds = points.len() / (3 * n);
        if clouds == 0 || points.len() != clouds * n * 3 {
            return Err(InferenceError::Run {
                model: "grasp encoder",
                detail: format!("{} point values: expected a positive multiple of {n} × 3", points.len()),
            });
        }
        let run_error = |e: ort::Error| InferenceError::Run { model: "grasp encoder", detail: e.to_string() };
        let outputs = self
            .encoder
            .run(ort::inputs!["points" => TensorRef::from_array_view(([clouds, n, 3], points)).map_err(run_error)?])
            .map_err(run_error)?;
        let (_, condition) = outputs["condition"].try_extract_tensor::<f32>().map_err(run_error)?;
        Ok(condition.to_vec())
    }

    /// Velocities of B·G grasps (`rotations` B·G·9 row-major, `translations`
    /// B·G·3, `t` B·G), the G grasps of each of the B conditions in a row.
    pub fn velocity(
        &mut self,
        condition: &[f32],
        rotations: &[f32],
        translations: &[f32],
        t: &[f32],
    ) -> Result<crate::Velocities, InferenceError> {
        let (tk, d, m) = (self.info.tokens, self.info.width, t.len());
        let clouds = condition.len() / (tk * d);
        let run_error = |e: ort::Error| InferenceError::Run { model: "grasp velocity", detail: e.to_string() };
        if clouds == 0 || condition.len() != clouds * tk * d || m % clouds != 0 {
            return Err(InferenceError::Run {
                model: "grasp velocity",
                detail: format!(
                    "{} condition values and {m} grasps: expected B × {tk} × {d} values and B × G grasps",
                    condition.len()
                ),
            });
        }
        let outputs = self
            .velocity
            .run(ort::inputs![
                "condition" => TensorRef::from_array_view(([clouds, tk, d], condition)).map_err(run_error)?,
                "rotation" => TensorRef::from_array_view(([m, 3, 3], rotations)).map_err(run_error)?,
                "translation" => TensorRef::from_array_view(([m, 3], translations)).map_err(run_error)?,
                "t" => TensorRef::from_array_view(([m], t)).map_err(run_error)?,
            ])
            .map_err(run_error)?;
        let (_, rotation) = outputs["v_rot"].try_extract_tensor::<f32>().map_err(run_error)?;
        let (_, translation) = outputs["v_pos"].try_extract_tensor::<f32>().map_err(run_error)?;
        Ok(crate::Velocities { rotation: rotation.to_vec(), translation: translation.to_vec() })
    }
}
