//! A signed distance grid of an object model, computed once per object
//! with parry (distance to the mesh, inside/outside from its angle-weighted
//! pseudo-normals) and read by trilinear interpolation: the exact
//! counterpart of the paper's learned SDF.
//!
//! Frame and units: the model frame, metres. Values are negative inside.
//! Layout: `values[(z * ny + y) * nx + x]` for the grid node at
//! `origin + cell * (x, y, z)`.

use nalgebra::{Point3, Vector3};
use parry3d::query::PointQueryWithLocation;
use parry3d::shape::TriMesh;

#[derive(Debug, Clone)]
pub struct SignedDistanceGrid {
    origin: Vector3<f64>,
    cell: f64,
    dims: [usize; 3],
    values: Vec<f32>,
}

impl SignedDistanceGrid {
    /// Samples `mesh` (built with `TriMeshFlags::ORIENTED`) on a grid with
    /// `resolution` cells along the longest side of its bounding box, padded
    /// by `margin` metres on every side.
    pub fn build(mesh: &TriMesh, resolution: usize, margin: f64) -> Self {
        let aabb = mesh.local_aabb();
        let (min, max) = (aabb.mins.coords.cast::<f64>(), aabb.maxs.coords.cast::<f64>());
        let extent = (max - min).max();
        let cell = extent / resolution as f64;
        let origin = min - Vector3::repeat(margin);
        let span = max - min + Vector3::repeat(2.0 * margin);
        let dims = [0, 1, 2].map(|k| (span[k] / cell).ceil() as usize + 1);
        let mut values = Vec::with_capacity(dims[0] * dims[1] * dims[2]);
        for z in 0..dims[2] {
            for y in 0..dims[1] {
                for x in 0..dims[0] {
                    let p = origin + Vector3::new(x as f64, y as f64, z as f64) * cell;
                    let query = Point3::from(p.cast::<f32>());
                    // Projected onto the surface (not solid), with the
                    // inside flag from the pseudo-normals.
                    let (projection, _) = mesh.project_local_point_and_get_location(&query, false);
                    let distance = (projection.point - query).norm();
                    values.push(if projection.is_inside { -distance } else { distance });
                }
            }
        }
        Self { origin, cell, dims, values }
    }

    pub fn cell(&self) -> f64 {
        self.cell
    }

    pub fn dims(&self) -> [usize; 3] {
        self.dims
    }

    fn at(&self, x: usize, y: usize, z: usize) -> f64 {
        f64::from(self.values[(z * self.dims[1] + y) * self.dims[0] + x])
    }

    /// The interpolated signed distance at `p` and its gradient. Outside the
    /// grid the value at the nearest grid point plus the distance to it (an
    /// upper bound), with the gradient pointing away from the grid.
    pub fn value_and_gradient(&self, p: &Point3<f64>) -> (f64, Vector3<f64>) {
        let local = (p.coords - self.origin) / self.cell;
        let upper = Vector3::from_fn(|k, _| (self.dims[k] - 1) as f64);
        let clamped = local.zip_map(&upper, |v, u| v.clamp(0.0, u));
        let outside = (local - clamped) * self.cell;
        let index = clamped.map(|v| v.floor()).zip_map(&upper, |v, u| v.min(u - 1.0).max(0.0));
        let f = clamped - index;
        let [x, y, z] = [0, 1, 2].map(|k| index[k] as usize);
        let c = |dx: usize, dy: usize, dz: usize| self.at(x + dx, y + dy, z + dz);
        let (c000, c100, c010, c110) = (c(0, 0, 0), c(1, 0, 0), c(0, 1, 0), c(1, 1, 0));
        let (c001, c101, c011, c111) = (c(0, 0, 1), c(1, 0, 1), c(0, 1, 1), c(1, 1, 1));
        let lerp = |a: f64, b: f64, t: f64| a + (b - a) * t;
        let (c00, c10) = (lerp(c000, c100, f.x), lerp(c010, c110, f.x));
        let (c01, c11) = (lerp(c001, c101, f.x), lerp(c011, c111, f.x));
        let (c0, c1) = (lerp(c00, c10, f.y), lerp(c01, c11, f.y));
        let value = lerp(c0, c1, f.z);
        let dx = lerp(lerp(c100 - c000, c110 - c010, f.y), lerp(c101 - c001, c111 - c011, f.y), f.z);
        let dy = lerp(lerp(c010 - c000, c110 - c100, f.x), lerp(c011 - c001, c111 - c101, f.x), f.z);
        let dz = c1 - c0;
        let gradient = Vector3::new(dx, dy, dz) / self.cell;
        let away = outside.norm();
        if away > 0.0 { (value + away, gradient + outside / away) } else { (value, gradient) }
    }

    pub fn value(&self, p: &Point3<f64>) -> f64 {
        self.value_and_gradient(p).0
    }
}
