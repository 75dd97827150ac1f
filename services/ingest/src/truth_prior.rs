//! The `truth-prior` stage: for each Observation of a BOP dataset, the
//! ground-truth pose of its object perturbed by a random rotation and
//! translation, published as an Estimate. Wired into the sampler's side
//! input it replaces the previous frame's estimate, so tracking can be
//! measured from a known start (the evaluation's "tracking from a perturbed
//! ground truth"; `evaluation/graphs/tracking-from-truth.toml`).
//!
//! Parameters (graph `params`):
//!
//! | key | meaning | default |
//! |---|---|---|
//! | `dataset`, `split`, `targets` | as the frame source's: the same dataset, so frame ids name the same images | split `test` |
//! | `max_rotation_deg` | the perturbation's angle is uniform in [0, this], about a uniform random axis | 20 |
//! | `max_translation` | its length is uniform in [0, this], in a uniform random direction, metres | 0.05 |
//! | `seed` | the perturbation of (frame, object) depends only on it | 0 |

use std::collections::BTreeMap;
use std::path::PathBuf;

use nalgebra::{Rotation3, Unit, Vector3};
use poseflow_contracts::{EstimateHeader, ObservationHeader, POSE_LEN, SelectionMethod, StampSlot, WEIGHTED_POSE_LEN};
use poseflow_geometry::Pose;
use poseflow_geometry::sampling::seeded_rng;
use poseflow_runtime::{Emitter, Input, Transform};
use poseflow_scene::bop::{ByImage, GtEntry, SceneDir, read_json};
use rand::Rng;
use serde::Deserialize;

use crate::IngestError;
use crate::sources::{BopFrames, Masks};

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TruthPriorParams {
    pub dataset: PathBuf,
    #[serde(default = "default_split")]
    pub split: String,
    pub targets: Option<PathBuf>,
    #[serde(default = "default_max_rotation")]
    pub max_rotation_deg: f64,
    #[serde(default = "default_max_translation")]
    pub max_translation: f64,
    #[serde(default)]
    pub seed: u64,
}

fn default_split() -> String {
    "test".into()
}
fn default_max_rotation() -> f64 {
    20.0
}
fn default_max_translation() -> f64 {
    0.05
}

impl TruthPriorParams {
    pub fn from_json(value: &serde_json::Value) -> Result<Self, IngestError> {
        let params: Self = serde_json::from_value(value.clone())
            .map_err(|err| IngestError::Params { key: "truth-prior".into(), detail: err.to_string() })?;
        let bad = |key: &str, value: f64, expected: &str| IngestError::Params {
            key: key.into(),
            detail: format!("{value}: expected {expected}"),
        };
        if !(0.0..=180.0).contains(&params.max_rotation_deg) {
            return Err(bad("max_rotation_deg", params.max_rotation_deg, "degrees in 0..=180"));
        }
        if !(params.max_translation.is_finite() && params.max_translation >= 0.0) {
            return Err(bad("max_translation", params.max_translation, "metres >= 0"));
        }
        Ok(params)
    }
}

/// `truth · δ` for a perturbation `δ` drawn from (seed, frame, object):
/// rotation about a uniform axis by an angle uniform in [0, max], applied in
/// the object frame; translation uniform in direction and length.
pub fn perturbed(truth: &Pose, params: &TruthPriorParams, frame_id: u64, object_id: u32) -> Pose {
    let mut rng = seeded_rng(params.seed ^ frame_id.wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ u64::from(object_id) << 48);
    let mut direction = || loop {
        let v = Vector3::new(rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0));
        if (1e-6..=1.0).contains(&v.norm_squared()) {
            return Unit::new_normalize(v);
        }
    };
    let (axis, shift) = (direction(), direction());
    let angle = rng.random_range(0.0..=params.max_rotation_deg.to_radians());
    let length = rng.random_range(0.0..=params.max_translation);
    Pose::new(
        truth.rotation * Rotation3::from_axis_angle(&axis, angle),
        truth.translation + shift.into_inner() * length,
    )
}

/// The stage: frame ids mapped to dataset images, their ground truth read
/// once per scene.
#[derive(Debug)]
pub struct TruthPriorStage {
    params: TruthPriorParams,
    images: Vec<(u32, u32)>,
    scenes: BTreeMap<u32, ByImage<Vec<GtEntry>>>,
}

impl TruthPriorStage {
    pub fn new(params: TruthPriorParams) -> Result<Self, IngestError> {
        let frames =
            BopFrames::open(&params.dataset, &params.split, &[], params.targets.as_deref(), Masks::GroundTruth)?;
        let images = frames.images().map(|(scene, im, _)| (scene, im)).collect();
        Ok(Self { params, images, scenes: BTreeMap::new() })
    }

    /// The ground truth of the observed instance: the object's instance in
    /// the frame's image nearest the observed points' centroid.
    fn truth(&mut self, header: &ObservationHeader) -> Result<Pose, IngestError> {
        let (frame, object) = (header.header.frame_id, header.header.object_id);
        let missing = |detail: String| IngestError::Frame { frame: format!("frame {frame} object {object}"), detail };
        let &(scene_id, im_id) = usize::try_from(frame)
            .ok()
            .and_then(|i| self.images.get(i))
            .ok_or_else(|| missing(format!("the dataset has {} images", self.images.len())))?;
        let dir = SceneDir::new(&self.params.dataset.join(&self.params.split), scene_id);
        let scene = match self.scenes.entry(scene_id) {
            std::collections::btree_map::Entry::Occupied(entry) => entry.into_mut(),
            std::collections::btree_map::Entry::Vacant(entry) => entry.insert(read_json(&dir.scene_gt())?),
        };
        let entries =
            scene.get(&im_id).ok_or_else(|| missing(format!("{} has no image {im_id}", dir.scene_gt().display())))?;
        let centroid = Vector3::from(header.centroid.map(f64::from));
        let mut best: Option<(f64, Pose)> = None;
        for (index, entry) in entries.iter().enumerate().filter(|(_, e)| e.obj_id == object) {
            let pose = entry.pose(&dir.scene_gt(), im_id, index)?;
            let distance = (pose.translation - centroid).norm();
            if best.is_none_or(|(d, _)| distance < d) {
                best = Some((distance, pose));
            }
        }
        best.map(|(_, pose)| pose)
            .ok_or_else(|| missing(format!("scene {scene_id} image {im_id} has no instance of object {object}")))
    }
}

/// An Estimate holding the single pose `pose` (no selection, no spread).
pub fn single_pose_estimate(header: poseflow_contracts::Header, pose: &Pose) -> EstimateHeader {
    let values = pose.to_f32_row_major();
    EstimateHeader {
        header,
        best: values,
        mean: values,
        selection: SelectionMethod::None as u32,
        hypothesis_count: 1,
        kept_count: 1,
        ..EstimateHeader::default()
    }
}

impl Transform for TruthPriorStage {
    type In = ObservationHeader;
    type Out = EstimateHeader;
    type Error = IngestError;
    const SLOT: Option<StampSlot> = None;

    fn process(
        &mut self,
        input: Input<'_, ObservationHeader>,
        output: &mut dyn Emitter<EstimateHeader>,
    ) -> Result<(), IngestError> {
        let header = input.header;
        let truth = self.truth(header)?;
        let prior = perturbed(&truth, &self.params, header.header.frame_id, header.header.object_id);
        let values = prior.to_f32_row_major();
        output.emit(single_pose_estimate(input.forward_header(), &prior), WEIGHTED_POSE_LEN, &mut |out| {
            out[..POSE_LEN].copy_from_slice(&values);
            out[POSE_LEN] = 0.0;
        })?;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn params(max_rotation_deg: f64, max_translation: f64, seed: u64) -> TruthPriorParams {
        TruthPriorParams {
            dataset: PathBuf::new(),
            split: "test".into(),
            targets: None,
            max_rotation_deg,
            max_translation,
            seed,
        }
    }

    #[test]
    fn perturbations_stay_within_their_bounds_and_follow_the_seed() {
        let truth = Pose::new(Rotation3::from_euler_angles(0.4, -1.0, 2.0), Vector3::new(0.1, 0.0, 0.9));
        let p = params(20.0, 0.05, 7);
        let (mut largest_angle, mut largest_shift) = (0.0f64, 0.0f64);
        for frame in 0..500 {
            let prior = perturbed(&truth, &p, frame, 5);
            let angle = prior.rotation.angle_to(&truth.rotation).to_degrees();
            let shift = (prior.translation - truth.translation).norm();
            assert!(angle <= 20.0 + 1e-9 && shift <= 0.05 + 1e-12, "{angle} {shift}");
            (largest_angle, largest_shift) = (largest_angle.max(angle), largest_shift.max(shift));
            assert_eq!(prior, perturbed(&truth, &p, frame, 5), "same seed, frame and object: same prior");
        }
        // The whole range is used.
        assert!(largest_angle > 19.0 && largest_shift > 0.049, "{largest_angle} {largest_shift}");
        assert_ne!(perturbed(&truth, &p, 3, 5), perturbed(&truth, &p, 3, 6));
        assert_ne!(perturbed(&truth, &p, 3, 5), perturbed(&truth, &params(20.0, 0.05, 8), 3, 5));
        // No perturbation asked for: the truth.
        let exact = perturbed(&truth, &params(0.0, 0.0, 7), 3, 5);
        assert!(exact.rotation.angle_to(&truth.rotation) < 1e-12 && exact.translation == truth.translation);
    }

    #[test]
    fn bad_parameters_are_named() {
        let err = |value: serde_json::Value| TruthPriorParams::from_json(&value).unwrap_err().to_string();
        assert!(err(serde_json::json!({"dataset": "d", "max_rotation_deg": 200.0})).contains("max_rotation_deg"));
        assert!(err(serde_json::json!({"dataset": "d", "max_translation": -1.0})).contains("max_translation"));
        assert!(err(serde_json::json!({"dataset": "d", "spread": 1})).contains("spread"));
        assert!(err(serde_json::json!({})).contains("dataset"));
    }
}
