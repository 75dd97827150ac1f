//! The grasp stage's core: the objects it can grasp, the grasp flow, and
//! for one Estimate's hypotheses the grasps with the share of hypotheses
//! under which each holds.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion};
use parry3d::shape::TriMesh;
use poseflow_geometry::Pose;
use poseflow_geometry::sampling::{TranslationNoise, farthest_point_indices, sample_seed, seeded_rng};
use poseflow_inference::GraspFlowModel;
use poseflow_scene::{ModelLibrary, SceneError, oriented_trimesh, surface_points};

use crate::{GraspError, GraspField, GraspParams, Gripper, MeanFieldParams, check_grasp, marginal_grasps};

/// One object: its mesh (object frame, outward faces) and the cloud the
/// grasp flow sees (farthest-point ordered surface points).
#[derive(Debug)]
pub struct GraspObject {
    pub mesh: TriMesh,
    pub cloud: Vec<Point3<f32>>,
}

/// The objects of a BOP models directory.
#[derive(Debug)]
pub struct GraspObjects {
    pub dir: PathBuf,
    objects: BTreeMap<u32, GraspObject>,
}

impl GraspObjects {
    /// Loads every object with a model file; `cloud_points` per cloud.
    pub fn load(dir: &Path, cloud_points: usize) -> Result<Self, GraspError> {
        let library = ModelLibrary::load(dir, &[])?;
        let mut objects = BTreeMap::new();
        for object in library.objects {
            let mesh = oriented_trimesh(object.model.mesh.vertices, object.model.mesh.triangles)
                .map_err(|source| SceneError::TriMesh { path: object.path.clone(), source })?;
            // Deterministic per object, so every run grasps the same cloud.
            let surface: Vec<Point3<f32>> =
                surface_points(&mesh, 4 * cloud_points, &mut seeded_rng(u64::from(object.obj_id)))
                    .into_iter()
                    .map(|(p, _)| p)
                    .collect();
            let cloud = farthest_point_indices(&surface, cloud_points).into_iter().map(|i| surface[i]).collect();
            objects.insert(object.obj_id, GraspObject { mesh, cloud });
        }
        Ok(Self { dir: dir.to_path_buf(), objects })
    }

    pub fn get(&self, obj_id: u32) -> Option<&GraspObject> {
        self.objects.get(&obj_id)
    }

    pub fn ids(&self) -> Vec<u32> {
        self.objects.keys().copied().collect()
    }
}

/// A grasp in the camera frame and how it fares under the hypotheses.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PlannedGrasp {
    pub camera_from_grasp: Pose,
    /// Mean closing width (m) under the hypotheses where it holds, 0 if none.
    pub width: f32,
    /// Share of hypotheses under which it holds, `[0, 1]`.
    pub valid_share: f64,
    /// Smallest friction-cone margin (radians) over the hypotheses where it
    /// holds, 0 if none: contacts near the cone's edge slip under small
    /// pose errors the hypotheses do not show.
    pub margin: f32,
}

impl PlannedGrasp {
    /// What a robot should rank by: the valid share first, then the margin
    /// as a fraction of the friction cone. The margin term stays below
    /// 1/64 (the finest share step at the stage's 64 hypotheses at most),
    /// so it only breaks ties between equal shares.
    pub fn score(&self, gripper: &Gripper) -> f64 {
        self.valid_share + 0.01 * f64::from(self.margin / gripper.friction_angle()).clamp(0.0, 1.0)
    }
}

/// `camera_from_grasp` checked on the object placed at each hypothesis.
pub fn judge(mesh: &TriMesh, gripper: &Gripper, hypotheses: &[Pose], camera_from_grasp: &Pose) -> PlannedGrasp {
    let mut widths = Vec::with_capacity(hypotheses.len());
    let mut margin = f32::INFINITY;
    for hypothesis in hypotheses {
        let object_from_grasp = hypothesis.inverse() * *camera_from_grasp;
        if let crate::GraspOutcome::Holds { width, margin: here } =
            check_grasp(mesh, gripper, &isometry(&object_from_grasp))
        {
            widths.push(width);
            margin = margin.min(here);
        }
    }
    PlannedGrasp {
        camera_from_grasp: *camera_from_grasp,
        width: if widths.is_empty() { 0.0 } else { widths.iter().sum::<f32>() / widths.len() as f32 },
        valid_share: widths.len() as f64 / hypotheses.len().max(1) as f64,
        margin: if widths.is_empty() { 0.0 } else { margin },
    }
}

/// The parry form of a pose (`f32`).
pub fn isometry(pose: &Pose) -> Isometry3<f32> {
    let rotation = UnitQuaternion::from_rotation_matrix(&pose.rotation.cast::<f32>());
    Isometry3::from_parts(Translation3::from(pose.translation.cast::<f32>()), rotation)
}

/// The grasp flow model as a [`GraspField`].
#[derive(Debug)]
pub struct OnnxGraspField(pub GraspFlowModel);

impl GraspField for OnnxGraspField {
    type Error = poseflow_inference::InferenceError;

    fn point_count(&self) -> usize {
        self.0.info.point_count
    }

    fn encode(&mut self, clouds: &[f32]) -> Result<Vec<f32>, Self::Error> {
        self.0.encode(clouds)
    }

    fn velocity(
        &mut self,
        condition: &[f32],
        rotations: &[f32],
        translations: &[f32],
        t: &[f32],
    ) -> Result<(Vec<f32>, Vec<f32>), Self::Error> {
        let v = self.0.velocity(condition, rotations, translations, t)?;
        Ok((v.rotation, v.translation))
    }
}

/// Objects, a grasp field and the parameters: hypotheses in, grasps out.
#[derive(Debug)]
pub struct GraspPlanner<F: GraspField> {
    params: GraspParams,
    objects: GraspObjects,
    field: F,
    noise: TranslationNoise,
}

impl GraspPlanner<OnnxGraspField> {
    /// Loads the grasp flow model and the objects named by `params`.
    pub fn load(params: GraspParams) -> Result<Self, GraspError> {
        params.validate()?;
        let model = GraspFlowModel::load(&params.model, params.threads)?;
        let noise = TranslationNoise::Gaussian { std_dev: model.info.translation_noise_std };
        let objects = GraspObjects::load(&params.models, model.info.point_count)?;
        Ok(Self::new(params, objects, OnnxGraspField(model), noise))
    }
}

impl<F: GraspField> GraspPlanner<F> {
    pub fn new(params: GraspParams, objects: GraspObjects, field: F, noise: TranslationNoise) -> Self {
        Self { params, objects, field, noise }
    }

    pub fn params(&self) -> &GraspParams {
        &self.params
    }

    pub fn objects(&self) -> &GraspObjects {
        &self.objects
    }

    /// Grasps for `object` under the first `params.hypotheses` of
    /// `hypotheses` (object-to-camera), best [`PlannedGrasp::score`] first
    /// (ties keep the flow's order). The draws depend on (seed, frame,
    /// object) only.
    pub fn plan(&mut self, frame: u64, object: u32, hypotheses: &[Pose]) -> Result<Vec<PlannedGrasp>, GraspError> {
        let in_frame = |detail: String| GraspError::Frame { frame, object, detail };
        let target = self.objects.get(object).ok_or_else(|| {
            in_frame(format!(
                "no model of object {object} in {} (objects there: {:?})",
                self.objects.dir.display(),
                self.objects.ids()
            ))
        })?;
        let used = &hypotheses[..hypotheses.len().min(self.params.hypotheses)];
        let mean_field = MeanFieldParams { grasps: self.params.grasps, steps: self.params.steps, noise: self.noise };
        let mut rng = seeded_rng(sample_seed(self.params.seed, frame, object));
        let grasps = marginal_grasps(&mut self.field, &target.cloud, used, &mean_field, &mut rng)
            .map_err(|source| GraspError::Plan { frame, object, source })?;
        let mut planned: Vec<PlannedGrasp> =
            grasps.iter().map(|g| judge(&target.mesh, &self.params.gripper, used, g)).collect();
        let gripper = &self.params.gripper;
        planned.sort_by(|a, b| b.score(gripper).total_cmp(&a.score(gripper)));
        Ok(planned)
    }
}

#[cfg(test)]
mod tests {
    use nalgebra::{Rotation3, Vector3};

    use super::*;
    use crate::check::tests::box_mesh;

    /// A grasp from above closing along x, its contact line at `height`.
    fn from_above(gripper: &Gripper, height: f64) -> Pose {
        let down = Rotation3::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI);
        Pose::new(down, Vector3::new(0.0, 0.0, height - f64::from(gripper.contact_depth)))
    }

    #[test]
    fn the_valid_share_counts_the_hypotheses_a_grasp_holds_under() {
        let gripper = Gripper::default();
        // A 4 cm wide box; a grasp from above closing along x, its contact
        // line 2 cm below the top of the box placed at the origin.
        let mesh = box_mesh([0.02, 0.02, 0.05]);
        let grasp = from_above(&gripper, 0.03);
        let here = Pose::identity();
        // The same box 10 cm aside: the gripper closes on air.
        let aside = Pose::new(Rotation3::identity(), Vector3::new(0.1, 0.0, 0.0));
        // Turned a quarter about z: still 4 cm across, still held.
        let turned =
            Pose::new(Rotation3::from_axis_angle(&Vector3::z_axis(), std::f64::consts::FRAC_PI_2), Vector3::zeros());
        let judged = judge(&mesh, &gripper, &[here, aside, turned], &grasp);
        assert!((judged.valid_share - 2.0 / 3.0).abs() < 1e-12, "{judged:?}");
        assert!((judged.width - 0.04).abs() < 1e-3, "{judged:?}");
        // Both pads meet their faces square on: the whole cone is margin.
        assert!((judged.margin - gripper.friction_angle()).abs() < 1e-3, "{judged:?}");
        let none = judge(&mesh, &gripper, &[aside], &grasp);
        assert_eq!((none.valid_share, none.width, none.margin), (0.0, 0.0, 0.0));
    }
}
