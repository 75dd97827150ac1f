//! The grasp stage's parameters (graph `params` over `config/grasp.toml`).

use std::path::PathBuf;

use serde::Deserialize;

use crate::{GraspError, Gripper};

/// | key | meaning | default |
/// |---|---|---|
/// | `model` | grasp flow model directory (`grasp_encoder.onnx`, `grasp_velocity.onnx`) | `models/grasp-flow` |
/// | `models` | BOP models directory of the objects to grasp | `objects/ycbv/mug-bowl` |
/// | `grasps` | grasps G sampled per Estimate | 32 |
/// | `steps` | Euler steps of the grasp flow | 10 |
/// | `hypotheses` | pose hypotheses averaged over (the first kept ones of the Estimate); 1 = the single-hypothesis baseline | 8 |
/// | `threads` | ONNX Runtime intra-op threads | 1 |
/// | `seed` | seed of the initial grasps (with the frame and object id) | 0 |
/// | `gripper` | the gripper grasps are checked with (table: `max_opening`, `finger`, `palm`, `contact_depth`, `friction`) | Panda-like |
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GraspParams {
    #[serde(default = "default_model")]
    pub model: PathBuf,
    #[serde(default = "default_models")]
    pub models: PathBuf,
    #[serde(default = "default_grasps")]
    pub grasps: usize,
    #[serde(default = "default_steps")]
    pub steps: usize,
    #[serde(default = "default_hypotheses")]
    pub hypotheses: usize,
    #[serde(default = "default_threads")]
    pub threads: usize,
    #[serde(default)]
    pub seed: u64,
    #[serde(default)]
    pub gripper: Gripper,
}

fn default_model() -> PathBuf {
    PathBuf::from("models/grasp-flow")
}
fn default_models() -> PathBuf {
    PathBuf::from("objects/ycbv/mug-bowl")
}
fn default_grasps() -> usize {
    32
}
fn default_steps() -> usize {
    10
}
fn default_hypotheses() -> usize {
    8
}
fn default_threads() -> usize {
    1
}

impl Default for GraspParams {
    fn default() -> Self {
        serde_json::from_value(serde_json::json!({})).expect("every field has a default")
    }
}

impl GraspParams {
    /// Reads the graph's `params`, naming the key that is wrong.
    pub fn from_json(value: &serde_json::Value) -> Result<Self, GraspError> {
        let params: Self = serde_json::from_value(value.clone()).map_err(GraspError::ParamsJson)?;
        params.validate()?;
        Ok(params)
    }

    pub fn validate(&self) -> Result<(), GraspError> {
        let checks: [(&'static str, bool, String); 4] = [
            ("grasps", (1..=4096).contains(&self.grasps), format!("{}: expected 1 to 4096", self.grasps)),
            ("steps", (1..=100).contains(&self.steps), format!("{}: expected 1 to 100", self.steps)),
            ("hypotheses", (1..=64).contains(&self.hypotheses), format!("{}: expected 1 to 64", self.hypotheses)),
            ("threads", (1..=64).contains(&self.threads), format!("{}: expected 1 to 64", self.threads)),
        ];
        if let Some((key, _, detail)) = checks.into_iter().find(|(_, ok, _)| !ok) {
            return Err(GraspError::Params { key, detail });
        }
        self.gripper.validate().map_err(GraspError::Gripper)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_and_overrides_parse_and_bad_values_are_named() {
        let params = GraspParams::from_json(&serde_json::json!({"grasps": 8, "gripper": {"friction": 0.3}})).unwrap();
        assert_eq!((params.grasps, params.steps, params.hypotheses), (8, 10, 8));
        assert_eq!(params.gripper.friction, 0.3);
        assert_eq!(params.gripper.max_opening, Gripper::default().max_opening);
        let err = GraspParams::from_json(&serde_json::json!({"hypotheses": 0})).unwrap_err().to_string();
        assert!(err.contains("`hypotheses`") && err.contains("1 to 64"), "{err}");
        let err =
            GraspParams::from_json(&serde_json::json!({"gripper": {"finger": [0.01, -0.02, 0.045]}})).unwrap_err();
        let chain = poseflow_runtime::error_chain(&err);
        assert!(chain.starts_with("param `gripper`: gripper `finger/palm`: expected a positive size"), "{chain}");
        let err = GraspParams::from_json(&serde_json::json!({"grasp": 3})).unwrap_err();
        let chain = poseflow_runtime::error_chain(&err);
        assert!(chain.contains("params: unknown field `grasp`"), "{chain}");
    }
}
