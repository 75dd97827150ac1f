//! Adding an object to a BOP models directory from any PLY or OBJ mesh:
//! writes `obj_NNNNNN.ply` (ASCII, millimetres, normals and colours) and
//! the object's `models_info.json` entry (diameter, bounding box,
//! symmetries), so that `poseflow render` and the training data can use
//! objects that are not in a BOP dataset (the YCB-V mug and bowl, a user's
//! own parts).

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use nalgebra::{Point3, Vector3};
use serde_json::{Map, Value, json};

use crate::symmetry::{Symmetry, find_symmetries};
use crate::{ObjectMesh, SceneError, bop, load_mesh, model_file_name};

/// BOP writes millimetres.
const METRES_TO_BOP: f64 = 1e3;

/// What to import and how.
#[derive(Debug, Clone)]
pub struct ImportSpec {
    pub mesh: PathBuf,
    /// Metres per mesh unit (1 for YCB-V OBJ files, 0.001 for millimetres).
    pub scale: f32,
    pub obj_id: u32,
    /// sRGB colour for every vertex; the mesh's own colours (or mid grey)
    /// otherwise.
    pub colour: Option<[u8; 3]>,
    /// Axis (object frame) of a continuous rotational symmetry through the
    /// origin, as a bowl or a can has about z.
    pub symmetry_axis: Option<Vector3<f64>>,
    /// Search the mesh for its symmetries ([`find_symmetries`]) with this
    /// tolerance, a fraction of the diameter, and record what it finds.
    pub find_symmetries: Option<f64>,
    /// Search the mesh for the turns that move no surface point farther
    /// than this many millimetres from the surface, and record them in
    /// [`SHAPE_SYMMETRIES_FILE`]: what a render of the one-coloured mesh
    /// cannot tell apart, whatever the real object's print shows.
    pub shape_symmetries_mm: Option<f64>,
}

/// The models directory's second `models_info.json`: the same entries with
/// the symmetries of the shape alone (`ImportSpec::shape_symmetries_mm`).
/// `models_info.json` keeps the symmetries of the real, printed object, as
/// BOP records them; a model trained on one-coloured renders can only be
/// asked for a pose up to these.
pub const SHAPE_SYMMETRIES_FILE: &str = "models_info_shape.json";

/// The entry written for the imported object.
#[derive(Debug, Clone, PartialEq)]
pub struct Imported {
    pub model_path: PathBuf,
    pub vertices: usize,
    pub triangles: usize,
    /// Metres.
    pub diameter: f64,
    /// Metres.
    pub size: Vector3<f64>,
    /// The symmetries recorded in `models_info.json`.
    pub symmetries: Vec<Symmetry>,
    /// The shape's, when searched, as recorded in [`SHAPE_SYMMETRIES_FILE`].
    pub shape_symmetries: Option<Vec<Symmetry>>,
}

/// Writes the object into `models_dir` (created if missing), replacing an
/// earlier object with the same id and keeping every other entry.
pub fn import_model(spec: &ImportSpec, models_dir: &Path) -> Result<Imported, SceneError> {
    let mut mesh = load_mesh(&spec.mesh, spec.scale)?;
    if let Some(colour) = spec.colour {
        mesh.colors = Some(vec![colour; mesh.vertices.len()]);
    }
    let symmetry_axis = spec
        .symmetry_axis
        .map(|axis| {
            axis.try_normalize(1e-9)
                .ok_or_else(|| SceneError::Invalid(format!("symmetry axis {axis:?}: expected a non-zero vector")))
        })
        .transpose()?;
    let diameter = diameter(&mesh.vertices);
    let mut symmetries: Vec<Symmetry> = symmetry_axis
        .map(|axis| Symmetry::Continuous { axis: nalgebra::Unit::new_unchecked(axis), offset: Vector3::zeros() })
        .into_iter()
        .collect();
    if let Some(tolerance) = spec.find_symmetries {
        if !(tolerance.is_finite() && tolerance > 0.0 && tolerance < 0.5) {
            return Err(SceneError::Invalid(format!(
                "symmetry tolerance {tolerance}: expected a fraction of the diameter in (0, 0.5), e.g. 0.01"
            )));
        }
        symmetries.extend(find_symmetries(&mesh, diameter, tolerance)?);
    }
    let shape_symmetries = spec
        .shape_symmetries_mm
        .map(|mm| {
            if !(mm.is_finite() && mm > 0.0 && mm < 0.5 * diameter * METRES_TO_BOP) {
                return Err(SceneError::Invalid(format!(
                    "shape symmetry tolerance {mm} mm: expected millimetres in (0, {:.0}), half the diameter, e.g. 8",
                    0.5 * diameter * METRES_TO_BOP
                )));
            }
            find_symmetries(&mesh, diameter, mm / METRES_TO_BOP / diameter)
        })
        .transpose()?;
    let imported = write_model(&mesh, spec.obj_id, symmetries, models_dir)?;
    let shape_path = models_dir.join(SHAPE_SYMMETRIES_FILE);
    // Once a directory has the file, every object gets an entry, so the
    // file never silently lacks one: an object imported without a search
    // has the symmetries it was given.
    if shape_symmetries.is_some() || shape_path.exists() {
        let symmetries = shape_symmetries.as_deref().unwrap_or(&imported.symmetries);
        let mut shape: Map<String, Value> = if shape_path.exists() { bop::read_json(&shape_path)? } else { Map::new() };
        let (min, max) = bounding_box(&mesh.vertices);
        shape.insert(spec.obj_id.to_string(), info_entry(min, max, imported.diameter, symmetries));
        bop::write_json(&shape_path, &shape)?;
    }
    Ok(Imported { shape_symmetries, ..imported })
}

/// Writes `mesh` (metres, object frame) into `models_dir` (created if
/// missing) as object `obj_id` with these symmetries, replacing an earlier
/// object with the same id and keeping every other entry.
pub fn write_model(
    mesh: &ObjectMesh,
    obj_id: u32,
    symmetries: Vec<Symmetry>,
    models_dir: &Path,
) -> Result<Imported, SceneError> {
    std::fs::create_dir_all(models_dir)
        .map_err(|source| SceneError::Write { path: models_dir.to_path_buf(), source })?;
    let model_path = models_dir.join(model_file_name(obj_id));
    std::fs::write(&model_path, ascii_ply_mm(mesh))
        .map_err(|source| SceneError::Write { path: model_path.clone(), source })?;

    let (min, max) = bounding_box(&mesh.vertices);
    let diameter = diameter(&mesh.vertices);
    let info_path = models_dir.join("models_info.json");
    let mut info: Map<String, Value> = if info_path.exists() { bop::read_json(&info_path)? } else { Map::new() };
    info.insert(obj_id.to_string(), info_entry(min, max, diameter, &symmetries));
    bop::write_json(&info_path, &info)?;
    Ok(Imported {
        model_path,
        vertices: mesh.vertices.len(),
        triangles: mesh.triangles.len(),
        diameter,
        size: max - min,
        symmetries,
        shape_symmetries: None,
    })
}

/// The `models_info.json` entry of a mesh with this bounding box and
/// diameter (metres) and these symmetries, in BOP's millimetres.
fn info_entry(min: Vector3<f64>, max: Vector3<f64>, diameter: f64, symmetries: &[Symmetry]) -> Value {
    let mut entry = json!({
        "diameter": diameter * METRES_TO_BOP,
        "min_x": min.x * METRES_TO_BOP, "min_y": min.y * METRES_TO_BOP, "min_z": min.z * METRES_TO_BOP,
        "size_x": (max - min).x * METRES_TO_BOP, "size_y": (max - min).y * METRES_TO_BOP,
        "size_z": (max - min).z * METRES_TO_BOP,
    });
    let continuous: Vec<Value> = symmetries
        .iter()
        .filter_map(|s| match s {
            Symmetry::Continuous { axis, offset } => {
                let offset = offset * METRES_TO_BOP;
                Some(json!({ "axis": [axis.x, axis.y, axis.z], "offset": [offset.x, offset.y, offset.z] }))
            }
            Symmetry::Discrete(_) => None,
        })
        .collect();
    let discrete: Vec<Value> = symmetries
        .iter()
        .filter_map(|s| match s {
            // BOP: the 4×4 matrix row-major, translation in millimetres.
            Symmetry::Discrete(pose) => {
                let (r, t) = (pose.rotation.matrix(), pose.translation * METRES_TO_BOP);
                Some(json!([
                    r[(0, 0)],
                    r[(0, 1)],
                    r[(0, 2)],
                    t.x,
                    r[(1, 0)],
                    r[(1, 1)],
                    r[(1, 2)],
                    t.y,
                    r[(2, 0)],
                    r[(2, 1)],
                    r[(2, 2)],
                    t.z,
                    0.0,
                    0.0,
                    0.0,
                    1.0
                ]))
            }
            Symmetry::Continuous { .. } => None,
        })
        .collect();
    if !continuous.is_empty() {
        entry["symmetries_continuous"] = Value::Array(continuous);
    }
    if !discrete.is_empty() {
        entry["symmetries_discrete"] = Value::Array(discrete);
    }
    entry
}

fn bounding_box(vertices: &[Point3<f32>]) -> (Vector3<f64>, Vector3<f64>) {
    let mut min = Vector3::repeat(f64::INFINITY);
    let mut max = Vector3::repeat(f64::NEG_INFINITY);
    for v in vertices {
        let v = v.coords.cast::<f64>();
        min = min.inf(&v);
        max = max.sup(&v);
    }
    (min, max)
}

/// The largest distance between two vertices. The farthest pair lies on the
/// convex hull, so only hull points are compared pairwise.
fn diameter(vertices: &[Point3<f32>]) -> f64 {
    let (hull, _) = parry3d::transformation::convex_hull(vertices);
    let points = if hull.is_empty() { vertices } else { &hull };
    let mut best = 0.0f64;
    for (i, a) in points.iter().enumerate() {
        for b in &points[i + 1..] {
            best = best.max(f64::from((a - b).norm()));
        }
    }
    best
}

/// The mesh as an ASCII PLY in millimetres, the layout of BOP's models.
fn ascii_ply_mm(mesh: &ObjectMesh) -> String {
    let mut out = String::with_capacity(64 * mesh.vertices.len() + 24 * mesh.triangles.len());
    out.push_str("ply\nformat ascii 1.0\ncomment written by poseflow (millimetres)\n");
    let _ = writeln!(out, "element vertex {}", mesh.vertices.len());
    out.push_str("property float x\nproperty float y\nproperty float z\n");
    if mesh.normals.is_some() {
        out.push_str("property float nx\nproperty float ny\nproperty float nz\n");
    }
    if mesh.colors.is_some() {
        out.push_str("property uchar red\nproperty uchar green\nproperty uchar blue\n");
    }
    let _ = writeln!(out, "element face {}", mesh.triangles.len());
    out.push_str("property list uchar int vertex_indices\nend_header\n");
    for (i, v) in mesh.vertices.iter().enumerate() {
        let mm = v.coords.cast::<f64>() * METRES_TO_BOP;
        let _ = write!(out, "{} {} {}", mm.x as f32, mm.y as f32, mm.z as f32);
        if let Some(normals) = &mesh.normals {
            let n = normals[i];
            let _ = write!(out, " {} {} {}", n.x, n.y, n.z);
        }
        if let Some(colors) = &mesh.colors {
            let [r, g, b] = colors[i];
            let _ = write!(out, " {r} {g} {b}");
        }
        out.push('\n');
    }
    for [a, b, c] in &mesh.triangles {
        let _ = writeln!(out, "3 {a} {b} {c}");
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ModelLibrary;
    use poseflow_geometry::models_info::ModelsInfo;

    const CUBE_OBJ: &str = "v 0 0 0\nv 0.1 0 0\nv 0.1 0.1 0\nv 0 0.1 0\nv 0 0 0.1\nv 0.1 0 0.1\nv 0.1 0.1 0.1\nv 0 0.1 0.1\n\
        f 1 3 2\nf 1 4 3\nf 5 6 7\nf 5 7 8\nf 1 2 6\nf 1 6 5\nf 2 3 7\nf 2 7 6\nf 3 4 8\nf 3 8 7\nf 4 1 5\nf 4 5 8\n";

    fn scratch(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("poseflow-import-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        dir
    }

    #[test]
    fn an_imported_cube_loads_back_with_its_diameter_box_and_symmetry() {
        let dir = scratch("cube");
        let mesh = dir.join("cube.obj");
        std::fs::write(&mesh, CUBE_OBJ).unwrap();
        let models = dir.join("models");
        let spec = ImportSpec {
            mesh,
            scale: 1.0,
            obj_id: 14,
            colour: Some([200, 30, 30]),
            symmetry_axis: Some(Vector3::new(0.0, 0.0, 2.0)),
            find_symmetries: None,
            shape_symmetries_mm: None,
        };
        let imported = import_model(&spec, &models).unwrap();
        // Space diagonal of a 10 cm cube.
        assert!((imported.diameter - 0.1 * 3f64.sqrt()).abs() < 1e-6, "{imported:?}");
        assert!((imported.size - Vector3::repeat(0.1)).norm() < 1e-6);

        let library = ModelLibrary::load(&models, &[14]).unwrap();
        let object = &library.objects[0];
        assert!((object.info.diameter - imported.diameter).abs() < 1e-6);
        assert_eq!(object.info.symmetries_continuous.len(), 1);
        assert!((object.info.symmetries_continuous[0].axis.z - 1.0).abs() < 1e-12);
        let loaded = load_mesh(&imported.model_path, 1e-3).unwrap();
        assert_eq!(loaded.triangles.len(), 12);
        assert_eq!(loaded.colors.as_deref().map(|c| c[0]), Some([200, 30, 30]));
        for (a, b) in loaded.vertices.iter().zip(load_mesh(&spec.mesh, 1.0).unwrap().vertices.iter()) {
            assert!((a - b).norm() < 1e-6, "{a} vs {b}");
        }
    }

    #[test]
    fn importing_keeps_the_other_entries_and_replaces_the_same_id() {
        let dir = scratch("merge");
        let mesh = dir.join("cube.obj");
        std::fs::write(&mesh, CUBE_OBJ).unwrap();
        let models = dir.join("models");
        let spec = |obj_id, scale| ImportSpec {
            mesh: mesh.clone(),
            scale,
            obj_id,
            colour: None,
            symmetry_axis: None,
            find_symmetries: None,
            shape_symmetries_mm: None,
        };
        import_model(&spec(1, 1.0), &models).unwrap();
        import_model(&spec(2, 1.0), &models).unwrap();
        let again = import_model(&spec(1, 2.0), &models).unwrap();
        assert!((again.diameter - 0.2 * 3f64.sqrt()).abs() < 1e-6);
        let library = ModelLibrary::load(&models, &[]).unwrap();
        let ids: Vec<u32> = library.objects.iter().map(|o| o.obj_id).collect();
        assert_eq!(ids, [1, 2]);
        assert!((library.objects[0].info.diameter - again.diameter).abs() < 1e-6);
    }

    #[test]
    fn shape_symmetries_go_to_their_own_file_and_every_later_object_gets_an_entry() {
        let dir = scratch("shape");
        // A 10 × 6 × 4 cm box: three half turns as a shape, none recorded
        // for the printed object.
        let box_obj = CUBE_OBJ
            .lines()
            .map(|line| match line.strip_prefix("v ") {
                Some(v) => {
                    let c: Vec<f64> = v.split(' ').map(|x| x.parse().unwrap()).collect();
                    format!("v {} {} {}\n", c[0], c[1] * 0.6, c[2] * 0.4)
                }
                None => format!("{line}\n"),
            })
            .collect::<String>();
        let mesh = dir.join("box.obj");
        std::fs::write(&mesh, box_obj).unwrap();
        let cube = dir.join("cube.obj");
        std::fs::write(&cube, CUBE_OBJ).unwrap();
        let models = dir.join("models");
        let spec = |mesh: &PathBuf, obj_id, shape_symmetries_mm| ImportSpec {
            mesh: mesh.clone(),
            scale: 1.0,
            obj_id,
            colour: None,
            symmetry_axis: None,
            find_symmetries: None,
            shape_symmetries_mm,
        };
        let imported = import_model(&spec(&mesh, 1, Some(2.0)), &models).unwrap();
        assert!(imported.symmetries.is_empty());
        assert_eq!(imported.shape_symmetries.as_ref().map(Vec::len), Some(3), "{imported:?}");
        import_model(&spec(&cube, 2, None), &models).unwrap();

        let shape = ModelsInfo::from_path(&models.join(SHAPE_SYMMETRIES_FILE)).unwrap();
        let printed = ModelsInfo::from_path(&models.join("models_info.json")).unwrap();
        assert_eq!(shape.get(1).unwrap().symmetries_discrete.len(), 3);
        assert!(!printed.get(1).unwrap().is_symmetric());
        // Imported without a search: the entry is there, with no symmetry
        // it was not given.
        assert!(!shape.get(2).unwrap().is_symmetric());
        assert!((shape.get(2).unwrap().diameter - printed.get(2).unwrap().diameter).abs() < 1e-9);

        for mm in [0.0, -1.0, f64::NAN, 500.0] {
            let err = import_model(&spec(&mesh, 3, Some(mm)), &models).unwrap_err().to_string();
            assert!(err.contains("shape symmetry tolerance") && err.contains("mm"), "{err}");
        }
    }

    #[test]
    fn a_zero_symmetry_axis_is_refused() {
        let dir = scratch("axis");
        let mesh = dir.join("cube.obj");
        std::fs::write(&mesh, CUBE_OBJ).unwrap();
        let spec = ImportSpec {
            mesh,
            scale: 1.0,
            obj_id: 3,
            colour: None,
            symmetry_axis: Some(Vector3::zeros()),
            find_symmetries: None,
            shape_symmetries_mm: None,
        };
        let err = import_model(&spec, &dir.join("models")).unwrap_err().to_string();
        assert!(err.contains("symmetry axis") && err.contains("non-zero"), "{err}");
    }
}
