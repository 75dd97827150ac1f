//! BOP JSON files as the frame source and the model library read them:
//! scene_camera.json, scene_gt.json and models_info.json (with the
//! symmetries it lists). Every value is checked or a named error.
#![no_main]

use std::path::Path;

use libfuzzer_sys::fuzz_target;
use poseflow_geometry::SymmetrySet;
use poseflow_geometry::models_info::ModelsInfo;
use poseflow_scene::bop::{ByImage, CameraEntry, GtEntry};

/// The symmetry discretisation the selector uses for continuous symmetries.
const SYMMETRY_STEP_RAD: f64 = 0.2;

fuzz_target!(|bytes: &[u8]| {
    let file = Path::new("fuzz.json");
    if let Ok(cameras) = serde_json::from_slice::<ByImage<CameraEntry>>(bytes) {
        for (&im_id, entry) in &cameras {
            let _ = entry.camera(640, 480, file, im_id);
            let _ = entry.camera_from_world(file, im_id);
        }
    }
    if let Ok(truths) = serde_json::from_slice::<ByImage<Vec<GtEntry>>>(bytes) {
        for (&im_id, entries) in &truths {
            for (instance, entry) in entries.iter().enumerate() {
                let _ = entry.pose(file, im_id, instance);
            }
        }
    }
    if let Ok(text) = std::str::from_utf8(bytes)
        && let Ok(info) = ModelsInfo::from_json_str(text, file)
    {
        for model in info.objects.values() {
            let _ = SymmetrySet::from_model_info(model, SYMMETRY_STEP_RAD);
        }
    }
});
