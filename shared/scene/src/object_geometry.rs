//! The object models the model-based scores and the refinement need: the
//! triangle mesh (exact distances) and, built on first use, its signed
//! distance grid.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;
use std::time::Instant;

use nalgebra::{Point3, Rotation3, Vector3};
use parry3d::shape::{TriMesh, TriMeshBuilderError};
use poseflow_geometry::SymmetrySet;
use poseflow_geometry::models_info::ModelsInfo;
use poseflow_geometry::sampling::seeded_rng;

use crate::import::SHAPE_SYMMETRIES_FILE;
use crate::sdf::SignedDistanceGrid;
use crate::symmetry::principal_axes;
use crate::{SceneError, load_bop_model, model_file_name, oriented_trimesh, surface_points};

/// Surface points per object for the silhouette check: a few per cell of
/// its grid even where the object is thin.
const SURFACE_POINTS: usize = 2000;

/// The largest step, as a share of the diameter, between the rotations a
/// continuous symmetry is discretised into for [`ObjectGeometry::symmetries`]
/// (BOP's `max_sym_disc_step` form): 158 rotations 2.3° apart, so a pose's
/// nearest twin is found to within 1.2°, far below what the track check
/// calls a jump, at an eighth of the evaluation's 315.
const TRACK_SYMMETRY_STEP: f64 = 0.02;

/// One object model, model frame, metres.
#[derive(Debug)]
pub struct ObjectGeometry {
    pub obj_id: u32,
    pub mesh: TriMesh,
    resolution: usize,
    grid: OnceLock<SignedDistanceGrid>,
    surface: OnceLock<Vec<Point3<f64>>>,
    half_turns: OnceLock<[(Rotation3<f64>, Vector3<f64>); 3]>,
    quarter_turns: OnceLock<[(Rotation3<f64>, Vector3<f64>); 9]>,
    symmetries: SymmetrySet,
}

impl ObjectGeometry {
    /// The model of a closed triangle mesh (model frame, metres), see
    /// [`oriented_trimesh`].
    pub fn from_mesh(
        obj_id: u32,
        vertices: Vec<Point3<f32>>,
        triangles: Vec<[u32; 3]>,
        resolution: usize,
    ) -> Result<Self, TriMeshBuilderError> {
        let mesh = oriented_trimesh(vertices, triangles)?;
        Ok(Self {
            obj_id,
            mesh,
            resolution,
            grid: OnceLock::new(),
            surface: OnceLock::new(),
            half_turns: OnceLock::new(),
            quarter_turns: OnceLock::new(),
            symmetries: SymmetrySet::identity_only(),
        })
    }

    /// The same model with the transforms `S` (model frame) under which
    /// its shape looks the same.
    pub fn with_symmetries(self, symmetries: SymmetrySet) -> Self {
        Self { symmetries, ..self }
    }

    /// The transforms under which the shape looks the same, identity first
    /// (only the identity unless [`Self::with_symmetries`] set them): the
    /// poses `T` and `T · S` fit any observation equally well.
    pub fn symmetries(&self) -> &SymmetrySet {
        &self.symmetries
    }

    /// Points spread over the whole surface (model frame), uniform by area
    /// and the same on every run: what the silhouette check projects.
    pub fn surface(&self) -> &[Point3<f64>] {
        self.surface.get_or_init(|| {
            surface_points(&self.mesh, SURFACE_POINTS, &mut seeded_rng(u64::from(self.obj_id)))
                .into_iter()
                .map(|(p, _)| p.cast::<f64>())
                .collect()
        })
    }

    /// Half turns about the principal axes of the surface (through its
    /// centroid), as rigid motions of the model frame `y ↦ F y + s`: the
    /// poses a depth fit confuses most, a box or a figure seen from one
    /// side turned over.
    pub fn half_turns(&self) -> &[(Rotation3<f64>, Vector3<f64>); 3] {
        self.half_turns.get_or_init(|| self.principal_turns([std::f64::consts::PI]).map(|[turn]| turn))
    }

    /// Quarter, half and three-quarter turns about each principal axis of
    /// the surface (through its centroid), as [`Self::half_turns`]: also
    /// the confusions of a box seen on one face, whose neighbouring faces
    /// fit a partial view as well once turned by a quarter.
    pub fn quarter_turns(&self) -> &[(Rotation3<f64>, Vector3<f64>); 9] {
        use std::f64::consts::{FRAC_PI_2, PI};
        self.quarter_turns.get_or_init(|| {
            let by_axis = self.principal_turns([FRAC_PI_2, PI, 3.0 * FRAC_PI_2]);
            std::array::from_fn(|i| by_axis[i / 3][i % 3])
        })
    }

    /// The turns by each of `angles` about each principal axis through the
    /// surface's centroid, axis by axis.
    fn principal_turns<const N: usize>(&self, angles: [f64; N]) -> [[(Rotation3<f64>, Vector3<f64>); N]; 3] {
        let surface = self.surface();
        let centroid =
            Point3::from(surface.iter().fold(Vector3::zeros(), |sum, p| sum + p.coords) / surface.len().max(1) as f64);
        principal_axes(surface, &centroid).map(|axis| {
            angles.map(|angle| {
                let turn = Rotation3::from_axis_angle(&axis, angle);
                (turn, centroid.coords - turn * centroid.coords)
            })
        })
    }

    /// A sphere holding the whole object (model frame): the box's centre
    /// and half diagonal.
    pub fn bounding_sphere(&self) -> (Point3<f64>, f64) {
        let aabb = self.mesh.local_aabb();
        (aabb.center().cast::<f64>(), f64::from(aabb.half_extents().norm()))
    }

    /// The largest side of the model's bounding box, metres.
    pub fn extent(&self) -> f64 {
        f64::from(self.mesh.local_aabb().extents().max())
    }

    /// The signed distance grid, computed on first use (about a second for
    /// a 64-cell grid; logged).
    pub fn grid(&self) -> &SignedDistanceGrid {
        self.grid.get_or_init(|| {
            let started = Instant::now();
            // A margin of a few cells, so points a little off the surface
            // still interpolate inside the grid.
            let extent = self.mesh.local_aabb().extents().max() as f64;
            let grid = SignedDistanceGrid::build(&self.mesh, self.resolution, 4.0 * extent / self.resolution as f64);
            tracing::info!(
                object = self.obj_id,
                dims = ?grid.dims(),
                ms = started.elapsed().as_millis() as u64,
                "signed distance grid built"
            );
            grid
        })
    }
}

/// The objects of a BOP models directory.
#[derive(Debug)]
pub struct ObjectLibrary {
    pub dir: PathBuf,
    objects: BTreeMap<u32, ObjectGeometry>,
}

impl ObjectLibrary {
    /// Loads every object of `dir/models_info.json` that has a model file,
    /// with the symmetries of its shape: its entry in
    /// [`SHAPE_SYMMETRIES_FILE`] when the directory has one (what depth can
    /// show), else those of `models_info.json`.
    pub fn load(dir: &Path, sdf_resolution: usize) -> Result<Self, SceneError> {
        let read = |path: PathBuf| {
            ModelsInfo::from_path(&path).map_err(|source| SceneError::ModelsInfo { path, source: Box::new(source) })
        };
        let info = read(dir.join("models_info.json"))?;
        let shape_path = dir.join(SHAPE_SYMMETRIES_FILE);
        let shape = if shape_path.is_file() { Some(read(shape_path)?) } else { None };
        let mut objects = BTreeMap::new();
        for (&obj_id, entry) in &info.objects {
            let path = dir.join(model_file_name(obj_id));
            if !path.is_file() {
                continue;
            }
            let mesh = load_bop_model(&path, entry.diameter)?;
            let symmetric_as = shape.as_ref().and_then(|shape| shape.get(obj_id)).unwrap_or(entry);
            let object = ObjectGeometry::from_mesh(obj_id, mesh.vertices, mesh.triangles, sdf_resolution)
                .map_err(|source| SceneError::TriMesh { path: path.clone(), source })?
                .with_symmetries(SymmetrySet::from_model_info(symmetric_as, TRACK_SYMMETRY_STEP));
            objects.insert(obj_id, object);
        }
        if objects.is_empty() {
            return Err(SceneError::NoModels {
                path: dir.to_path_buf(),
                detail: "no object of models_info.json has a model file (expected obj_NNNNNN.ply beside it)".into(),
            });
        }
        Ok(Self { dir: dir.to_path_buf(), objects })
    }

    pub fn get(&self, obj_id: u32) -> Option<&ObjectGeometry> {
        self.objects.get(&obj_id)
    }

    /// Computes every object's signed distance grid now.
    pub fn build_grids(&self) {
        for object in self.objects.values() {
            object.grid();
        }
    }

    /// Every object, in ascending id.
    pub fn objects(&self) -> impl Iterator<Item = &ObjectGeometry> {
        self.objects.values()
    }

    pub fn ids(&self) -> Vec<u32> {
        self.objects.keys().copied().collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_library_takes_the_shapes_symmetries_over_the_printed_objects() {
        let lmo = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../objects/lmo");
        let dir = std::env::temp_dir().join(format!("poseflow-object-library-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        for file in ["models_info.json", "obj_000001.ply", "obj_000010.ply"] {
            std::fs::copy(lmo.join(file), dir.join(file)).unwrap();
        }
        let counts = |library: &ObjectLibrary| {
            library.objects().map(|o| (o.obj_id, o.symmetries().transforms().len())).collect::<Vec<_>>()
        };
        // models_info.json: the eggbox's half turn, the ape asymmetric.
        assert_eq!(counts(&ObjectLibrary::load(&dir, 16).unwrap()), [(1, 1), (10, 2)]);

        // A shape file with a continuous axis for the ape wins over it.
        let shape = r#"{"1": {"diameter": 102.099, "symmetries_continuous": [{"axis": [0, 0, 1], "offset": [0, 0, 0]}]},
                        "10": {"diameter": 164.628}}"#;
        std::fs::write(dir.join(SHAPE_SYMMETRIES_FILE), shape).unwrap();
        let library = ObjectLibrary::load(&dir, 16).unwrap();
        let steps = (std::f64::consts::PI / TRACK_SYMMETRY_STEP).ceil() as usize;
        assert_eq!(counts(&library), [(1, steps), (10, 1)]);

        std::fs::write(dir.join(SHAPE_SYMMETRIES_FILE), "{").unwrap();
        let error = ObjectLibrary::load(&dir, 16).unwrap_err().to_string();
        assert!(error.contains(SHAPE_SYMMETRIES_FILE), "the broken file is named: {error}");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
