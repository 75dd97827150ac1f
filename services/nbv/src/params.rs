//! The next-best-view stage's parameters (graph `params` over
//! `config/nbv.toml`).

use std::path::{Path, PathBuf};

use poseflow_graph::Graph;
use poseflow_scene::Camera;
use poseflow_scene::dataset::lmo_camera;
use serde::Deserialize;

use crate::NbvError;

/// | key | meaning | default |
/// |---|---|---|
/// | `candidates` | C viewpoints on the sphere | 12 |
/// | `elevation_deg` | [min, max] elevation band (degrees above the plane through the object centre perpendicular to `up`) | [10, 60] |
/// | `radius` | sphere radius (m); 0 = the current camera's distance to the object | 0 |
/// | `up` | the world's up direction in the current camera frame (OpenCV axes: image up is −y) | [0, −1, 0] |
/// | `include_current` | also score the current viewpoint (the identity pose), so the ranking says whether moving pays | true |
/// | `hypotheses` | H hypotheses of the Estimate (spread evenly over its kept ones) rendered per candidate | 3 |
/// | `workers` | pose pipelines scoring simulated views in parallel (one ONNX session pair each) | 2 |
/// | `min_visible_pixels` | a simulated view showing fewer object pixels is uninformative (trace of a uniform rotation) | 200 |
/// | `frames` | Frames (side input) kept for the Estimates still to come | 16 |
/// | `occluder_stride` | every n-th depth pixel (both ways) of the frame becomes an occluder point | 4 |
/// | `seed` | seed of the simulated sensor noise (with the frame, candidate and hypothesis) | 0 |
/// | `models` | BOP models directory the views are rendered from | `objects/lmo` |
/// | `camera` | intrinsics of the camera that moves (`fx`, `fy`, `cx`, `cy`, `width`, `height`) | LM-O 640×480 |
/// | `ingest`, `inference`, `sampler`, `selector` | the pose stages run on each simulated view ([`ESTIMATION_GRAPH`], built through the stage registry): tables over those stages' defaults (fewer samples and steps than estimation) | 112 px / 8 patches; `models/poseflow-lmo10`, 1 thread; 16 samples, 3 steps; no selection |
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
struct Raw {
    #[serde(default = "default_candidates")]
    candidates: usize,
    #[serde(default = "default_elevation")]
    elevation_deg: [f64; 2],
    #[serde(default)]
    radius: f64,
    #[serde(default = "default_up")]
    up: [f64; 3],
    #[serde(default = "default_true")]
    include_current: bool,
    #[serde(default = "default_hypotheses")]
    hypotheses: usize,
    #[serde(default = "default_workers")]
    workers: usize,
    #[serde(default = "default_min_visible_pixels")]
    min_visible_pixels: usize,
    #[serde(default = "default_frames")]
    frames: usize,
    #[serde(default = "default_occluder_stride")]
    occluder_stride: usize,
    #[serde(default)]
    seed: u64,
    #[serde(default = "default_models")]
    models: PathBuf,
    #[serde(default)]
    camera: Option<CameraTable>,
    #[serde(default)]
    ingest: serde_json::Map<String, serde_json::Value>,
    #[serde(default)]
    inference: serde_json::Map<String, serde_json::Value>,
    #[serde(default)]
    sampler: serde_json::Map<String, serde_json::Value>,
    #[serde(default)]
    selector: serde_json::Map<String, serde_json::Value>,
}

#[derive(Debug, Clone, Copy, Deserialize)]
#[serde(deny_unknown_fields)]
struct CameraTable {
    fx: f64,
    fy: f64,
    cx: f64,
    cy: f64,
    width: u32,
    height: u32,
}

fn default_candidates() -> usize {
    12
}
fn default_elevation() -> [f64; 2] {
    [10.0, 60.0]
}
fn default_up() -> [f64; 3] {
    [0.0, -1.0, 0.0]
}
fn default_true() -> bool {
    true
}
fn default_hypotheses() -> usize {
    3
}
fn default_workers() -> usize {
    2
}
fn default_min_visible_pixels() -> usize {
    200
}
fn default_frames() -> usize {
    16
}
fn default_occluder_stride() -> usize {
    4
}
fn default_models() -> PathBuf {
    PathBuf::from("objects/lmo")
}

/// Where the candidate viewpoints lie.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ViewSphere {
    pub candidates: usize,
    /// Radians, min < max, both within (−90°, 90°).
    pub elevation: [f64; 2],
    /// Metres; `None`: the current camera's distance.
    pub radius: Option<f64>,
}

#[derive(Debug, Clone)]
pub struct NbvParams {
    pub sphere: ViewSphere,
    /// Unit vector, current camera frame.
    pub up: nalgebra::Vector3<f64>,
    pub include_current: bool,
    pub hypotheses: usize,
    pub workers: usize,
    pub min_visible_pixels: usize,
    pub frames: usize,
    pub occluder_stride: usize,
    pub seed: u64,
    pub models: PathBuf,
    pub camera: Camera,
    /// The pose stages run on each simulated view, `frames` in,
    /// `estimates` out ([`ESTIMATION_GRAPH`] with the stage tables).
    pub estimation: Graph,
}

/// The graph of the pose stages the planner runs on simulated views; the
/// stages' parameters are the `ingest`, `inference`, `sampler` and
/// `selector` tables laid over their defaults.
pub const ESTIMATION_GRAPH: &str = r#"
[graph]
name = "nbv-views"
description = "The next-best-view planner's pose estimation on simulated views"

[edges.frames]
message = "Frame"
queue = 1
max_payload_len = 67108864

[edges.observations]
message = "Observation"
queue = 2
max_payload_len = 67108864

[edges.conditions]
message = "Condition"
queue = 2

[edges.velocities]
message = "Velocity"
pattern = "request-response"
max_payload_len = 67108864

[edges.hypotheses]
message = "Hypotheses"
queue = 2
max_payload_len = 67108864

[edges.estimates]
message = "Estimate"
queue = 2
max_payload_len = 67108864

# The planner feeds the simulated views in its place.
[stages.views]
exe = "frame-source"
outputs = ["frames"]

[stages.ingest]
exe = "ingest"
inputs = ["frames"]
outputs = ["observations"]

[stages.inference]
exe = "inference"
inputs = ["observations"]
outputs = ["conditions"]
serves = ["velocities"]

[stages.sampler]
exe = "sampler"
inputs = ["conditions"]
calls = ["velocities"]
outputs = ["hypotheses"]

[stages.selector]
exe = "selector"
inputs = ["hypotheses"]
side_inputs = ["observations"]
outputs = ["estimates"]
"#;

/// [`ESTIMATION_GRAPH`] with each stage's parameters.
fn estimation_graph(tables: [(&str, serde_json::Value); 4]) -> Result<Graph, NbvError> {
    let mut graph = poseflow_graph::parse_in_process(ESTIMATION_GRAPH, Path::new("<nbv estimation graph>"))
        .map_err(|e| NbvError::Params { key: "estimation graph".into(), detail: e.to_string() })?;
    for (stage, params) in tables {
        if let Some(stage) = graph.stages.get_mut(stage) {
            stage.params = params;
        }
    }
    Ok(graph)
}

/// `overrides` laid over `defaults`, as a JSON object.
fn over(defaults: serde_json::Value, overrides: serde_json::Map<String, serde_json::Value>) -> serde_json::Value {
    let mut merged = defaults;
    if let Some(table) = merged.as_object_mut() {
        table.extend(overrides);
    }
    merged
}

impl NbvParams {
    /// Reads the graph's `params`, naming the key that is wrong.
    pub fn from_json(value: &serde_json::Value) -> Result<Self, NbvError> {
        let bad = |key: &str, detail: String| NbvError::Params { key: key.to_string(), detail };
        let raw: Raw = serde_json::from_value(value.clone()).map_err(|e| bad("nbv", e.to_string()))?;
        let [low, high] = raw.elevation_deg;
        let checks: [(&str, bool, String); 9] = [
            ("candidates", (1..=4096).contains(&raw.candidates), format!("{}: expected 1 to 4096", raw.candidates)),
            (
                "elevation_deg",
                -89.0 <= low && low < high && high <= 89.0,
                format!("[{low}, {high}]: expected min < max, both within −89 to 89"),
            ),
            ("radius", raw.radius.is_finite() && raw.radius >= 0.0, format!("{}: expected ≥ 0 metres", raw.radius)),
            (
                "up",
                raw.up.iter().all(|v| v.is_finite()) && nalgebra::Vector3::from(raw.up).norm() > 1e-6,
                format!("{:?}: expected a non-zero direction", raw.up),
            ),
            ("hypotheses", (1..=64).contains(&raw.hypotheses), format!("{}: expected 1 to 64", raw.hypotheses)),
            ("workers", (1..=16).contains(&raw.workers), format!("{}: expected 1 to 16", raw.workers)),
            ("frames", (1..=256).contains(&raw.frames), format!("{}: expected 1 to 256", raw.frames)),
            (
                "occluder_stride",
                (1..=64).contains(&raw.occluder_stride),
                format!("{}: expected 1 to 64", raw.occluder_stride),
            ),
            (
                "camera",
                raw.camera.is_none_or(|c| {
                    c.width > 0 && c.height > 0 && c.fx > 0.0 && c.fy > 0.0 && c.cx.is_finite() && c.cy.is_finite()
                }),
                "expected positive fx, fy, width and height".to_string(),
            ),
        ];
        if let Some((key, _, detail)) = checks.into_iter().find(|(_, ok, _)| !ok) {
            return Err(bad(key, detail));
        }
        let estimation = estimation_graph([
            ("ingest", over(serde_json::json!({"image_size": 112, "patch_grid": 8}), raw.ingest)),
            ("inference", over(serde_json::json!({"model": "models/poseflow-lmo10", "threads": 1}), raw.inference)),
            ("sampler", over(serde_json::json!({"samples": 16, "steps": 3}), raw.sampler)),
            ("selector", over(serde_json::json!({"method": "none"}), raw.selector)),
        ])?;
        let camera = raw.camera.map_or_else(
            || lmo_camera(640, 480),
            |c| Camera { fx: c.fx, fy: c.fy, cx: c.cx, cy: c.cy, width: c.width, height: c.height },
        );
        Ok(Self {
            sphere: ViewSphere {
                candidates: raw.candidates,
                elevation: [low.to_radians(), high.to_radians()],
                radius: (raw.radius > 0.0).then_some(raw.radius),
            },
            up: nalgebra::Vector3::from(raw.up).normalize(),
            include_current: raw.include_current,
            hypotheses: raw.hypotheses,
            workers: raw.workers,
            min_visible_pixels: raw.min_visible_pixels,
            frames: raw.frames,
            occluder_stride: raw.occluder_stride,
            seed: raw.seed,
            models: raw.models,
            camera,
            estimation,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_overrides_and_named_errors() {
        let params = NbvParams::from_json(&serde_json::json!({
            "candidates": 8, "radius": 0.5, "sampler": {"samples": 8}, "selector": {"method": "model-free"},
        }))
        .unwrap();
        assert_eq!(params.sphere.candidates, 8);
        assert_eq!(params.sphere.radius, Some(0.5));
        let stage = |name: &str| &params.estimation.stages[name].params;
        assert_eq!((&stage("sampler")["samples"], &stage("sampler")["steps"]), (&8.into(), &3.into()));
        assert_eq!((&stage("ingest")["image_size"], &stage("ingest")["patch_grid"]), (&112.into(), &8.into()));
        assert_eq!(stage("selector")["method"], "model-free");
        assert_eq!(params.up, nalgebra::Vector3::new(0.0, -1.0, 0.0));
        assert_eq!(params.camera.width, 640);
        assert!(NbvParams::from_json(&serde_json::json!({})).unwrap().sphere.radius.is_none());

        let error = |value: serde_json::Value| NbvParams::from_json(&value).unwrap_err().to_string();
        let err = error(serde_json::json!({"elevation_deg": [60.0, 10.0]}));
        assert!(err.contains("`elevation_deg`") && err.contains("min < max"), "{err}");
        let err = error(serde_json::json!({"up": [0.0, 0.0, 0.0]}));
        assert!(err.contains("`up`"), "{err}");
        let err = error(serde_json::json!({"candidate": 3}));
        assert!(err.contains("unknown field `candidate`"), "{err}");
        let err = error(
            serde_json::json!({"camera": {"fx": 500.0, "fy": 500.0, "cx": 1.0, "cy": 1.0, "width": 0, "height": 4}}),
        );
        assert!(err.contains("`camera`"), "{err}");
    }
}
