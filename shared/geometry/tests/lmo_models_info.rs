//! The real LM-O `models_info.json` (vendored under `tests/data`).

use std::path::Path;

use nalgebra::Vector3;
use poseflow_geometry::models_info::ModelsInfo;
use poseflow_geometry::symmetry::{BOP_MAX_SYMMETRY_STEP, SymmetrySet};
use poseflow_geometry::{Pose, so3};

const PATH: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../../objects/lmo/models_info.json");

#[test]
fn lmo_objects_diameters_and_symmetries() {
    let info = ModelsInfo::from_path(Path::new(PATH)).unwrap();
    let ids: Vec<u32> = info.objects.keys().copied().collect();
    assert_eq!(ids, [1, 5, 6, 8, 9, 10, 11, 12]);
    assert!((info.get(1).unwrap().diameter - 0.102099).abs() < 1e-9);
    let symmetric: Vec<u32> = info.objects.iter().filter(|(_, m)| m.is_symmetric()).map(|(id, _)| *id).collect();
    assert_eq!(symmetric, [10, 11], "eggbox and glue");

    // The eggbox symmetry is a half turn about (nearly) the z axis.
    let eggbox = info.get(10).unwrap();
    let flip = eggbox.symmetries_discrete[0];
    let axis = so3::log(&flip.rotation);
    assert!((axis.norm() - std::f64::consts::PI).abs() < 0.02, "{axis}");
    assert!(axis.normalize().z.abs() > 0.99, "{axis}");

    // An estimate equal to the flipped ground truth scores as correct.
    let set = SymmetrySet::from_model_info(eggbox, BOP_MAX_SYMMETRY_STEP);
    let truth = Pose::new(so3::exp(&Vector3::new(0.3, 1.0, -0.4)), Vector3::new(0.05, -0.02, 0.9));
    let err = set.pose_error(&(truth * flip), &truth);
    assert!(err.rotation < 1e-9 && err.translation < 1e-12);
}

#[test]
fn missing_file_error_names_the_path() {
    let err = ModelsInfo::from_path(Path::new("/nonexistent/models_info.json")).unwrap_err();
    assert!(err.to_string().starts_with("/nonexistent/models_info.json"), "{err}");
}
