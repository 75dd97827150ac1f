//! Procedural meshes for scenes: the support plane and clutter shapes.
//!
//! All in metres with the shape's base on `z = 0` (resting on the plane of
//! a z-up world frame) and its vertical axis through the origin.

use nalgebra::{Point3, Vector3};
use parry3d::shape::{Ball, Cuboid, Cylinder};
use rand::Rng;

use crate::ObjectMesh;

/// A square `2·half_extent` wide at `z = 0`, split into `cells × cells`
/// quads whose corner colours vary around `base`: a table top with a
/// low-frequency texture, so the background is not a flat colour the
/// network could learn to ignore trivially.
pub fn support_plane<R: Rng + ?Sized>(half_extent: f32, cells: u32, base: [u8; 3], rng: &mut R) -> ObjectMesh {
    let n = cells + 1;
    let step = 2.0 * half_extent / cells as f32;
    let mut vertices = Vec::with_capacity((n * n) as usize);
    let mut colors = Vec::with_capacity((n * n) as usize);
    for j in 0..n {
        for i in 0..n {
            vertices.push(Point3::new(-half_extent + i as f32 * step, -half_extent + j as f32 * step, 0.0));
            let shade: f32 = rng.random_range(0.8..1.2);
            colors.push(base.map(|c| (f32::from(c) * shade).round().clamp(0.0, 255.0) as u8));
        }
    }
    let mut triangles = Vec::with_capacity((2 * cells * cells) as usize);
    for j in 0..cells {
        for i in 0..cells {
            let a = j * n + i;
            triangles.push([a, a + 1, a + n + 1]);
            triangles.push([a, a + n + 1, a + n]);
        }
    }
    ObjectMesh { vertices, triangles, normals: Some(vec![Vector3::z(); (n * n) as usize]), colors: Some(colors) }
}

/// A distractor shape standing on the plane.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum ClutterShape {
    Box { half_extents: Vector3<f32> },
    Cylinder { radius: f32, height: f32 },
    Sphere { radius: f32 },
}

impl ClutterShape {
    /// A random shape whose largest dimension is at most `max_size`.
    pub fn random<R: Rng + ?Sized>(max_size: f32, rng: &mut R) -> Self {
        let kind = rng.random_range(0..3);
        let mut size = || rng.random_range(0.3 * max_size..=max_size);
        match kind {
            0 => Self::Box { half_extents: Vector3::new(size() / 2.0, size() / 2.0, size() / 2.0) },
            1 => Self::Cylinder { radius: size() / 2.0, height: size() },
            _ => Self::Sphere { radius: size() / 2.0 },
        }
    }

    /// The radius of the shape's footprint around its vertical axis.
    pub fn footprint_radius(&self) -> f32 {
        match *self {
            Self::Box { half_extents } => half_extents.xy().norm(),
            Self::Cylinder { radius, .. } | Self::Sphere { radius } => radius,
        }
    }

    /// The mesh in one flat colour, base on `z = 0`.
    pub fn mesh(&self, color: [u8; 3]) -> ObjectMesh {
        let (vertices, triangles) = match *self {
            Self::Box { half_extents } => lifted(Cuboid::new(half_extents).to_trimesh(), half_extents.z),
            Self::Cylinder { radius, height } => {
                // parry's cylinder axis is y; a quarter turn about x stands it up along z.
                let (vertices, triangles) = Cylinder::new(height / 2.0, radius).to_trimesh(24);
                let upright = vertices.into_iter().map(|p| Point3::new(p.x, -p.z, p.y)).collect();
                lifted((upright, triangles), height / 2.0)
            }
            Self::Sphere { radius } => lifted(Ball::new(radius).to_trimesh(12, 24), radius),
        };
        let colors = vec![color; vertices.len()];
        ObjectMesh { vertices, triangles, normals: None, colors: Some(colors) }
    }
}

fn lifted((vertices, triangles): (Vec<Point3<f32>>, Vec<[u32; 3]>), by: f32) -> (Vec<Point3<f32>>, Vec<[u32; 3]>) {
    (vertices.into_iter().map(|p| p + Vector3::z() * by).collect(), triangles)
}

#[cfg(test)]
mod tests {
    use super::*;
    use poseflow_geometry::sampling::seeded_rng;

    #[test]
    fn clutter_stands_on_the_plane_within_its_footprint() {
        let mut rng = seeded_rng(3);
        for _ in 0..30 {
            let shape = ClutterShape::random(0.1, &mut rng);
            let mesh = shape.mesh([10, 20, 30]);
            let (min, max) = mesh.bounds();
            assert!(min.z.abs() < 1e-6, "{shape:?} starts at z = {}", min.z);
            assert!(max.z <= 0.1 + 1e-6 && max.z > 0.0, "{shape:?} is {} tall", max.z);
            let widest = mesh.vertices.iter().map(|p| p.coords.xy().norm()).fold(0.0, f32::max);
            assert!(widest <= shape.footprint_radius() + 1e-5, "{shape:?}: {widest}");
        }
    }

    #[test]
    fn plane_is_flat_and_covers_the_square() {
        let plane = support_plane(0.5, 4, [100, 100, 100], &mut seeded_rng(1));
        assert_eq!((plane.vertices.len(), plane.triangles.len()), (25, 32));
        let (min, max) = plane.bounds();
        assert_eq!((min, max), (Point3::new(-0.5, -0.5, 0.0), Point3::new(0.5, 0.5, 0.0)));
    }
}
