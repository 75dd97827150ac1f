//! A BOP models directory loaded for rendering: `models_info.json` plus one
//! `obj_NNNNNN.ply` (millimetres) per object.

use std::path::{Path, PathBuf};

use poseflow_geometry::Pose;
use poseflow_geometry::models_info::{ModelInfo, ModelsInfo};

use crate::{ObjectMesh, RenderModel, SceneError, load_mesh};

/// BOP model files are in millimetres.
const BOP_MODEL_SCALE: f32 = 1e-3;

/// One object of a [`ModelLibrary`].
#[derive(Debug, Clone)]
pub struct LibraryObject {
    pub obj_id: u32,
    pub path: PathBuf,
    pub info: ModelInfo,
    pub model: RenderModel,
    /// Its category's canonical frame, from the directory's
    /// `categories.json` (identity without one): how an upright scene
    /// stands it on its base.
    pub canonical_from_model: Pose,
}

/// The objects a dataset is rendered from, in ascending `obj_id`.
#[derive(Debug, Clone)]
pub struct ModelLibrary {
    pub dir: PathBuf,
    pub objects: Vec<LibraryObject>,
    /// Other objects' meshes that scenes may show as unannotated
    /// distractors (`scene::SceneStyle::distractors`); none after [`load`].
    ///
    /// [`load`]: ModelLibrary::load
    pub distractors: Vec<LibraryObject>,
}

/// Loads a BOP model file (millimetres) and checks it against its
/// `models_info.json` diameter (metres): a file written in metres, or a
/// diameter given in metres, is off by a factor of 1000 and would place
/// every point in the wrong spot, so it is refused with the factor named.
pub fn load_bop_model(path: &Path, diameter: f64) -> Result<ObjectMesh, SceneError> {
    let mesh = load_mesh(path, BOP_MODEL_SCALE)?;
    let (min, max) = mesh.bounds();
    let box_diagonal = f64::from((max - min).norm());
    // The diameter lies between the largest box extent and the box diagonal
    // (at most √3 times the extent); a factor of 3 either way is units.
    let ratio = box_diagonal / diameter;
    if diameter > 0.0 && !(1.0 / 3.0..=3.0).contains(&ratio) {
        let hint = if ratio < 0.01 {
            "the model file looks like metres; BOP model files are millimetres (poseflow import-model --units m \
             converts one)"
        } else if ratio > 100.0 {
            "the diameter looks like metres; models_info.json gives millimetres"
        } else {
            "the model and its models_info.json entry describe different objects"
        };
        return Err(SceneError::Malformed {
            path: path.to_path_buf(),
            location: "vertices".into(),
            detail: format!(
                "they span a box {:.1} mm across, but models_info.json gives diameter {:.1} mm: {hint}",
                box_diagonal * 1e3,
                diameter * 1e3
            ),
        });
    }
    Ok(mesh)
}

/// The BOP file name of an object model.
pub fn model_file_name(obj_id: u32) -> String {
    format!("obj_{obj_id:06}.ply")
}

impl ModelLibrary {
    /// Loads `ids` (every object that has a model file when `ids` is empty)
    /// from a BOP models directory.
    pub fn load(dir: &Path, ids: &[u32]) -> Result<Self, SceneError> {
        let info_path = dir.join("models_info.json");
        let info = ModelsInfo::from_path(&info_path)
            .map_err(|err| SceneError::Invalid(format!("{}: {err}", info_path.display())))?;
        let wanted: Vec<u32> = if ids.is_empty() {
            info.objects.keys().copied().filter(|&id| dir.join(model_file_name(id)).is_file()).collect()
        } else {
            ids.to_vec()
        };
        if wanted.is_empty() {
            return Err(SceneError::Invalid(format!(
                "{}: no object has a model file (expected obj_NNNNNN.ply next to models_info.json)",
                dir.display()
            )));
        }
        let categories = if dir.join(crate::category::CATEGORIES_FILE).is_file() {
            crate::category::read_categories(dir)?
        } else {
            Default::default()
        };
        let mut objects = Vec::with_capacity(wanted.len());
        for obj_id in wanted {
            let info = info.get(obj_id).cloned().ok_or_else(|| {
                SceneError::Invalid(format!(
                    "{}: object {obj_id} is not listed (listed: {:?})",
                    info_path.display(),
                    info.objects.keys().collect::<Vec<_>>()
                ))
            })?;
            let path = dir.join(model_file_name(obj_id));
            let mesh = load_bop_model(&path, info.diameter)?;
            let model = RenderModel::new(mesh).map_err(|source| SceneError::TriMesh { path: path.clone(), source })?;
            let canonical_from_model = categories.get(&obj_id).map_or(Pose::identity(), |c| c.canonical_from_model);
            objects.push(LibraryObject { obj_id, path, info, model, canonical_from_model });
        }
        objects.sort_by_key(|o| o.obj_id);
        objects.dedup_by_key(|o| o.obj_id);
        Ok(Self { dir: dir.to_path_buf(), objects, distractors: Vec::new() })
    }

    /// Adds every object of the models directory `dir` whose id is not one
    /// of this library's targets as a distractor.
    pub fn with_distractors(mut self, dir: &Path) -> Result<Self, SceneError> {
        let others = Self::load(dir, &[])?;
        let same_dir = dir.canonicalize().ok() == self.dir.canonicalize().ok();
        let targets: Vec<u32> = self.objects.iter().map(|o| o.obj_id).collect();
        self.distractors = others.objects.into_iter().filter(|o| !(same_dir && targets.contains(&o.obj_id))).collect();
        if self.distractors.is_empty() {
            return Err(SceneError::Invalid(format!(
                "{}: no object is left to be a distractor (every one is a target)",
                dir.display()
            )));
        }
        Ok(self)
    }
}
