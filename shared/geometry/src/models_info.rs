//! The BOP `models_info.json` file: per-object diameter, bounding box and
//! symmetries. BOP stores millimetres; everything here is converted to metres.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use nalgebra::{Matrix3, Unit, Vector3};
use serde::Deserialize;

use crate::{GeometryError, Pose, pose::project_to_rotation};

const MM_TO_M: f64 = 1e-3;

/// BOP's symmetry matrices are printed with ~6 significant digits, so their
/// rotation blocks are orthonormal only to about 1e-5; anything further off is
/// a broken file rather than rounding.
const SYMMETRY_ORTHONORMALITY_TOLERANCE: f64 = 1e-3;

/// A continuous rotational symmetry: the object looks the same after any
/// rotation about `axis` (object frame) through the point `offset` (metres).
#[derive(Debug, Clone, PartialEq)]
pub struct ContinuousSymmetry {
    pub axis: Unit<Vector3<f64>>,
    pub offset: Vector3<f64>,
}

/// One object's entry, in metres.
#[derive(Debug, Clone, PartialEq)]
pub struct ModelInfo {
    pub diameter: f64,
    /// Bounding-box corner with the smallest coordinates, when given.
    pub min: Option<Vector3<f64>>,
    /// Bounding-box extents, when given.
    pub size: Option<Vector3<f64>>,
    /// Object-frame transforms `S` under which the object looks the same:
    /// the poses `T` and `T · S` are indistinguishable. Identity not included.
    pub symmetries_discrete: Vec<Pose>,
    pub symmetries_continuous: Vec<ContinuousSymmetry>,
}

impl ModelInfo {
    pub fn is_symmetric(&self) -> bool {
        !self.symmetries_discrete.is_empty() || !self.symmetries_continuous.is_empty()
    }
}

/// All entries of a `models_info.json`, keyed by object id.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct ModelsInfo {
    pub objects: BTreeMap<u32, ModelInfo>,
}

#[derive(Deserialize)]
struct RawModelInfo {
    diameter: f64,
    min_x: Option<f64>,
    min_y: Option<f64>,
    min_z: Option<f64>,
    size_x: Option<f64>,
    size_y: Option<f64>,
    size_z: Option<f64>,
    #[serde(default)]
    symmetries_discrete: Vec<Vec<f64>>,
    #[serde(default)]
    symmetries_continuous: Vec<RawContinuousSymmetry>,
}

#[derive(Deserialize)]
struct RawContinuousSymmetry {
    axis: [f64; 3],
    offset: [f64; 3],
}

impl ModelsInfo {
    pub fn from_path(path: &Path) -> Result<Self, GeometryError> {
        let text =
            std::fs::read_to_string(path).map_err(|source| GeometryError::Io { path: path.to_path_buf(), source })?;
        Self::from_json_str(&text, path)
    }

    /// Parses file contents; `path` only names the source in errors.
    pub fn from_json_str(text: &str, path: &Path) -> Result<Self, GeometryError> {
        let json_error = |source| GeometryError::Json { path: path.to_path_buf(), source };
        let raw: BTreeMap<String, serde_json::Value> = serde_json::from_str(text).map_err(json_error)?;
        let mut objects = BTreeMap::new();
        for (key, value) in raw {
            let context = FieldContext { path: path.to_path_buf(), object: key.clone() };
            let id = key
                .parse::<u32>()
                .map_err(|_| context.error("(key)", "expected a non-negative integer object id", &key))?;
            let entry: RawModelInfo = serde_json::from_value(value).map_err(|source| {
                GeometryError::ModelInfoEntry { path: path.to_path_buf(), object: key.clone(), source }
            })?;
            objects.insert(id, entry.into_model_info(&context)?);
        }
        Ok(Self { objects })
    }

    pub fn get(&self, object_id: u32) -> Option<&ModelInfo> {
        self.objects.get(&object_id)
    }
}

struct FieldContext {
    path: PathBuf,
    object: String,
}

impl FieldContext {
    fn error(&self, field: &'static str, expected: &'static str, value: impl std::fmt::Debug) -> GeometryError {
        GeometryError::ModelInfoField {
            path: self.path.clone(),
            object: self.object.clone(),
            field,
            expected,
            value: format!("{value:?}"),
        }
    }

    fn finite(&self, field: &'static str, values: &[f64]) -> Result<(), GeometryError> {
        if values.iter().all(|v| v.is_finite()) {
            Ok(())
        } else {
            Err(self.error(field, "expected finite numbers", values))
        }
    }
}

fn optional_vector(x: Option<f64>, y: Option<f64>, z: Option<f64>) -> Option<Vector3<f64>> {
    Some(Vector3::new(x?, y?, z?) * MM_TO_M)
}

impl RawModelInfo {
    fn into_model_info(self, context: &FieldContext) -> Result<ModelInfo, GeometryError> {
        if !(self.diameter.is_finite() && self.diameter > 0.0) {
            return Err(context.error("diameter", "expected a positive number of millimetres", self.diameter));
        }
        let min = optional_vector(self.min_x, self.min_y, self.min_z);
        let size = optional_vector(self.size_x, self.size_y, self.size_z);
        for (field, v) in [("min_x/min_y/min_z", min), ("size_x/size_y/size_z", size)] {
            if let Some(v) = v {
                context.finite(field, v.as_slice())?;
            }
        }

        let mut symmetries_discrete = Vec::with_capacity(self.symmetries_discrete.len());
        for values in &self.symmetries_discrete {
            if values.len() != 16 {
                return Err(context.error(
                    "symmetries_discrete",
                    "expected 16 numbers (a row-major 4x4 transform)",
                    values,
                ));
            }
            context.finite("symmetries_discrete", values)?;
            let m = Matrix3::new(
                values[0], values[1], values[2], //
                values[4], values[5], values[6], //
                values[8], values[9], values[10],
            );
            let rotation =
                project_to_rotation(&m, "symmetries_discrete", SYMMETRY_ORTHONORMALITY_TOLERANCE).map_err(|_| {
                    context.error("symmetries_discrete", "expected a rotation in the upper-left 3x3 block", values)
                })?;
            let translation = Vector3::new(values[3], values[7], values[11]) * MM_TO_M;
            symmetries_discrete.push(Pose::new(rotation, translation));
        }

        let mut symmetries_continuous = Vec::with_capacity(self.symmetries_continuous.len());
        for sym in &self.symmetries_continuous {
            context.finite("symmetries_continuous.axis", &sym.axis)?;
            context.finite("symmetries_continuous.offset", &sym.offset)?;
            let axis = Unit::try_new(Vector3::from(sym.axis), 1e-9)
                .ok_or_else(|| context.error("symmetries_continuous.axis", "expected a non-zero axis", sym.axis))?;
            symmetries_continuous.push(ContinuousSymmetry { axis, offset: Vector3::from(sym.offset) * MM_TO_M });
        }

        Ok(ModelInfo { diameter: self.diameter * MM_TO_M, min, size, symmetries_discrete, symmetries_continuous })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(text: &str) -> Result<ModelsInfo, GeometryError> {
        ModelsInfo::from_json_str(text, Path::new("models_info.json"))
    }

    #[test]
    fn reads_discrete_and_continuous_symmetries_in_metres() {
        let info = parse(
            r#"{
              "1": {"diameter": 102.099, "min_x": -37.9, "min_y": -38.8, "min_z": -45.9,
                    "size_x": 75.9, "size_y": 77.6, "size_z": 91.8},
              "10": {"diameter": 164.628,
                     "symmetries_discrete": [[-1, 0, 0, 0.2, 0, -1, 0, 0.7, 0, 0, 1, -0.1, 0, 0, 0, 1]]},
              "13": {"diameter": 100, "symmetries_continuous": [{"axis": [0, 0, 2], "offset": [0, 0, 5]}]}
            }"#,
        )
        .unwrap();
        let ape = info.get(1).unwrap();
        assert!((ape.diameter - 0.102099).abs() < 1e-12);
        assert!(!ape.is_symmetric());
        assert!((ape.size.unwrap().z - 0.0918).abs() < 1e-12);
        let eggbox = info.get(10).unwrap();
        assert_eq!(eggbox.symmetries_discrete.len(), 1);
        assert!((eggbox.symmetries_discrete[0].translation - Vector3::new(0.2e-3, 0.7e-3, -0.1e-3)).norm() < 1e-15);
        let bowl = info.get(13).unwrap();
        assert_eq!(bowl.symmetries_continuous[0].axis.into_inner(), Vector3::z());
        assert!((bowl.symmetries_continuous[0].offset.z - 0.005).abs() < 1e-15);
    }

    /// The error and its sources, as a log line shows them.
    fn chain(err: &dyn std::error::Error) -> String {
        std::iter::successors(Some(err), |e| e.source()).map(ToString::to_string).collect::<Vec<_>>().join(": ")
    }

    #[test]
    fn errors_name_object_field_and_value() {
        let err = parse(r#"{"5": {"diameter": -3}}"#).map_err(|e| chain(&e)).unwrap_err();
        assert!(err.contains("object 5") && err.contains("diameter") && err.contains("-3"), "{err}");

        let err =
            parse(r#"{"5": {"diameter": 3, "symmetries_discrete": [[1, 0, 0]]}}"#).map_err(|e| chain(&e)).unwrap_err();
        assert!(err.contains("symmetries_discrete") && err.contains("16 numbers"), "{err}");

        let err = parse(r#"{"5": {"diameter": 3, "symmetries_discrete": [[2,0,0,0, 0,1,0,0, 0,0,1,0, 0,0,0,1]]}}"#)
            .map_err(|e| chain(&e))
            .unwrap_err();
        assert!(err.contains("rotation"), "{err}");

        let err = parse(r#"{"abc": {"diameter": 3}}"#).map_err(|e| chain(&e)).unwrap_err();
        assert!(err.contains("object id"), "{err}");

        let err = parse(r#"{"7": {"size_x": 3}}"#).map_err(|e| chain(&e)).unwrap_err();
        assert!(err.contains("models_info.json") && err.contains("object 7") && err.contains("diameter"), "{err}");

        let err = parse(r#"{"7": {"diameter": 3, "symmetries_continuous": [{"axis": [0,0,0], "offset": [0,0,0]}]}}"#)
            .map_err(|e| chain(&e))
            .unwrap_err();
        assert!(err.contains("non-zero axis"), "{err}");

        assert!(parse("not json").unwrap_err().to_string().contains("invalid JSON"));
    }
}
