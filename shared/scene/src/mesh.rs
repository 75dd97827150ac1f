//! The in-memory object mesh and loading by file type.

use std::path::Path;

use nalgebra::{Point3, Vector3};
use parry3d::shape::{TriMesh, TriMeshFlags};
use rand::Rng;

use crate::SceneError;

/// A triangle mesh in the object frame, metres.
#[derive(Debug, Clone, PartialEq)]
pub struct ObjectMesh {
    pub vertices: Vec<Point3<f32>>,
    /// Vertex indices of each triangle, counter-clockwise seen from outside.
    pub triangles: Vec<[u32; 3]>,
    /// Unit normals per vertex, when the file has them.
    pub normals: Option<Vec<Vector3<f32>>>,
    /// sRGB colour per vertex, when the file has it.
    pub colors: Option<Vec<[u8; 3]>>,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MeshFormat {
    Ply,
    Obj,
}

impl MeshFormat {
    pub fn of(path: &Path) -> Option<Self> {
        match path.extension()?.to_str()?.to_ascii_lowercase().as_str() {
            "ply" => Some(Self::Ply),
            "obj" => Some(Self::Obj),
            _ => None,
        }
    }
}

/// Loads a PLY or OBJ mesh and multiplies coordinates by `scale` (BOP PLY
/// files are in millimetres: pass 0.001; YCB-V OBJ files are in metres: 1).
pub fn load_mesh(path: &Path, scale: f32) -> Result<ObjectMesh, SceneError> {
    let format = MeshFormat::of(path).ok_or_else(|| SceneError::UnknownFormat { path: path.to_path_buf() })?;
    let bytes = std::fs::read(path).map_err(|source| SceneError::Io { path: path.to_path_buf(), source })?;
    let mut mesh = parse_mesh(&bytes, format, path)?;
    for v in &mut mesh.vertices {
        *v *= scale;
    }
    Ok(mesh)
}

/// Parses and validates a mesh file's contents, in the file's units;
/// `path` names the file in errors.
pub fn parse_mesh(bytes: &[u8], format: MeshFormat, path: &Path) -> Result<ObjectMesh, SceneError> {
    let mesh = match format {
        MeshFormat::Ply => crate::ply::parse(bytes, path)?,
        MeshFormat::Obj => crate::obj::parse(bytes, path)?,
    };
    mesh.validate(path)?;
    Ok(mesh)
}

impl ObjectMesh {
    /// Rejects meshes no renderer or distance query can use.
    fn validate(&self, path: &Path) -> Result<(), SceneError> {
        let malformed = |location: &str, detail: String| SceneError::Malformed {
            path: path.to_path_buf(),
            location: location.to_string(),
            detail,
        };
        if self.vertices.is_empty() || self.triangles.is_empty() {
            return Err(malformed(
                "mesh",
                format!("expected vertices and triangles, found {} and {}", self.vertices.len(), self.triangles.len()),
            ));
        }
        if let Some(i) = self.vertices.iter().position(|v| !v.coords.iter().all(|c| c.is_finite())) {
            return Err(malformed(
                &format!("vertex {i}"),
                format!("expected finite coordinates, found {}", self.vertices[i]),
            ));
        }
        let n = self.vertices.len() as u32;
        if let Some(t) = self.triangles.iter().position(|t| t.iter().any(|&i| i >= n)) {
            return Err(malformed(
                &format!("face {t}"),
                format!("vertex index out of range: {:?} with {n} vertices", self.triangles[t]),
            ));
        }
        Ok(())
    }

    /// The volume the surface encloses ([`enclosed_volume`]).
    pub fn enclosed_volume(&self) -> f64 {
        enclosed_volume(&self.vertices, &self.triangles)
    }

    /// Axis-aligned bounds `(min, max)`.
    pub fn bounds(&self) -> (Point3<f32>, Point3<f32>) {
        let mut min = Point3::from(Vector3::repeat(f32::INFINITY));
        let mut max = Point3::from(Vector3::repeat(f32::NEG_INFINITY));
        for v in &self.vertices {
            min = min.inf(v);
            max = max.sup(v);
        }
        (min, max)
    }

    /// The largest distance between two vertices (BOP's object diameter),
    /// O(n²) over the vertices: meant for checks, not per frame.
    pub fn diameter(&self) -> f32 {
        let mut best = 0.0f32;
        for (i, a) in self.vertices.iter().enumerate() {
            for b in &self.vertices[i + 1..] {
                best = best.max((a - b).norm_squared());
            }
        }
        best.sqrt()
    }

    /// The parry triangle mesh (with its BVH) for ray casts and distance
    /// queries.
    pub fn to_trimesh(&self) -> Result<TriMesh, parry3d::shape::TriMeshBuilderError> {
        TriMesh::new(self.vertices.clone(), self.triangles.clone())
    }
}

/// The volume a closed surface encloses (divergence theorem over its
/// triangles), positive when they are wound with outward normals.
pub fn enclosed_volume(vertices: &[Point3<f32>], triangles: &[[u32; 3]]) -> f64 {
    triangles
        .iter()
        .map(|t| {
            let [a, b, c] = t.map(|i| vertices[i as usize].coords.cast::<f64>());
            a.dot(&b.cross(&c)) / 6.0
        })
        .sum()
}

/// The parry mesh of a closed surface with outward faces and pseudo-normals,
/// for inside/outside tests (signed distances, grippers inside an object)
/// and outward contact normals. Faces wound inwards (negative enclosed
/// volume) are flipped.
pub fn oriented_trimesh(
    vertices: Vec<Point3<f32>>,
    mut triangles: Vec<[u32; 3]>,
) -> Result<TriMesh, parry3d::shape::TriMeshBuilderError> {
    if enclosed_volume(&vertices, &triangles) < 0.0 {
        triangles.iter_mut().for_each(|t| t.swap(1, 2));
    }
    let flags = TriMeshFlags::ORIENTED | TriMeshFlags::MERGE_DUPLICATE_VERTICES;
    TriMesh::with_flags(vertices, triangles, flags)
}

/// `count` points on the surface, uniform by area, each with the outward
/// normal of its triangle (object frame).
pub fn surface_points<R: Rng + ?Sized>(mesh: &TriMesh, count: usize, rng: &mut R) -> Vec<(Point3<f32>, Vector3<f32>)> {
    let triangles: Vec<_> = (0..mesh.indices().len() as u32).map(|i| mesh.triangle(i)).collect();
    let mut cumulative = Vec::with_capacity(triangles.len());
    let mut total = 0.0f64;
    for t in &triangles {
        total += f64::from((t.b - t.a).cross(&(t.c - t.a)).norm() / 2.0);
        cumulative.push(total);
    }
    (0..count)
        .map(|_| {
            let pick = rng.random::<f64>() * total;
            let index = cumulative.partition_point(|&c| c < pick).min(triangles.len() - 1);
            let t = &triangles[index];
            // Uniform on the triangle: fold the unit square onto it.
            let (mut u, mut v) = (rng.random::<f32>(), rng.random::<f32>());
            if u + v > 1.0 {
                (u, v) = (1.0 - u, 1.0 - v);
            }
            let point = t.a + (t.b - t.a) * u + (t.c - t.a) * v;
            (point, t.normal().map_or_else(Vector3::z, |n| n.into_inner()))
        })
        .collect()
}
