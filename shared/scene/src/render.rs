//! Ray-cast rendering of posed object meshes: depth, instance labels and
//! shaded colour per pixel.
//!
//! Camera frame as in BOP/OpenCV: x right, y down, z forward (metres);
//! pixel `(u, v)` has its centre at integer coordinates and sees the ray
//! through `((u − cx)/fx, (v − cy)/fy, 1)`. Depth is the z coordinate of
//! the first surface hit (not the distance along the ray), 0 where nothing
//! is hit. Rows are rendered in parallel.

use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};
use parry3d::query::{Ray, RayCast};
use parry3d::shape::{FeatureId, TriMesh};
use poseflow_geometry::Pose;
use rayon::prelude::*;

use crate::ObjectMesh;
use crate::primitives::Texture;

/// Pinhole intrinsics (pixels) and image size.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Camera {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    pub width: u32,
    pub height: u32,
}

impl Camera {
    /// The unit ray direction through pixel `(u, v)`.
    pub fn ray_direction(&self, u: f64, v: f64) -> Vector3<f64> {
        Vector3::new((u - self.cx) / self.fx, (v - self.cy) / self.fy, 1.0).normalize()
    }

    /// The pixel a camera-frame point projects to, if it is in front.
    pub fn project(&self, p: &Point3<f64>) -> Option<(f64, f64)> {
        (p.z > 0.0).then(|| (self.fx * p.x / p.z + self.cx, self.fy * p.y / p.z + self.cy))
    }
}

/// An object ready to render: its mesh and the parry mesh (with BVH) built
/// once.
#[derive(Debug, Clone)]
pub struct RenderModel {
    pub mesh: ObjectMesh,
    trimesh: TriMesh,
    /// A pattern on the object's xy plane that replaces the vertex colours.
    pub texture: Option<Texture>,
}

impl RenderModel {
    pub fn new(mesh: ObjectMesh) -> Result<Self, parry3d::shape::TriMeshBuilderError> {
        let trimesh = mesh.to_trimesh()?;
        Ok(Self { mesh, trimesh, texture: None })
    }

    /// The colour at a point of triangle `tri` (object frame): vertex colours
    /// interpolated barycentrically, or flat grey for meshes without colour.
    fn color_at(&self, tri: usize, p: &Point3<f32>) -> [f32; 3] {
        if let Some(texture) = &self.texture {
            return texture.colour_at(p.x, p.y);
        }
        let Some(colors) = &self.mesh.colors else {
            return [0.7, 0.7, 0.7];
        };
        let [a, b, c] = self.mesh.triangles[tri].map(|i| i as usize);
        let (pa, pb, pc) = (self.mesh.vertices[a], self.mesh.vertices[b], self.mesh.vertices[c]);
        let area = (pb - pa).cross(&(pc - pa));
        let norm2 = area.norm_squared().max(f32::MIN_POSITIVE);
        let wa = (pb - p).cross(&(pc - p)).dot(&area) / norm2;
        let wb = (pc - p).cross(&(pa - p)).dot(&area) / norm2;
        let wc = 1.0 - wa - wb;
        let mix = |k: usize| {
            (wa * f32::from(colors[a][k]) + wb * f32::from(colors[b][k]) + wc * f32::from(colors[c][k])) / 255.0
        };
        [mix(0), mix(1), mix(2)]
    }
}

/// An object placed in the camera frame (object-to-camera pose).
#[derive(Debug, Clone, Copy)]
pub struct Placed<'a> {
    pub model: &'a RenderModel,
    pub pose: &'a Pose,
}

/// A directional light: `direction` points from the scene towards the light
/// (camera frame); `ambient` is the share of light every surface gets.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Light {
    pub direction: Vector3<f64>,
    pub ambient: f64,
}

impl Default for Light {
    /// Light from behind the camera, slightly above.
    fn default() -> Self {
        Self { direction: Vector3::new(0.0, -0.3, -1.0).normalize(), ambient: 0.3 }
    }
}

/// One rendered image, row-major.
#[derive(Debug, Clone, PartialEq)]
pub struct Frame {
    pub width: u32,
    pub height: u32,
    /// Metres (z in the camera frame); 0 = no surface.
    pub depth: Vec<f32>,
    /// 0 = background, `k + 1` = the `k`-th object passed to [`render`].
    pub label: Vec<u16>,
    pub rgb: Vec<[u8; 3]>,
    /// The surface colour before shading (0 where nothing is hit): what an
    /// active depth sensor's own light sees, whatever the room's light.
    pub albedo: Vec<[u8; 3]>,
}

fn isometry(pose: &Pose) -> Isometry3<f32> {
    let q = UnitQuaternion::from_rotation_matrix(&pose.rotation.cast::<f32>());
    Isometry3::from_parts(Translation3::from(pose.translation.cast::<f32>()), q)
}

/// The nearest hit along one camera ray: `(object, ray parameter, normal in
/// camera frame, colour)`.
fn first_hit(
    placed: &[(Isometry3<f32>, &RenderModel)],
    direction: &Vector3<f32>,
) -> Option<(usize, f32, Vector3<f32>, [f32; 3])> {
    let mut best: Option<(usize, f32, Vector3<f32>, [f32; 3])> = None;
    for (k, (pose, model)) in placed.iter().enumerate() {
        let ray = Ray::new(Point3::origin(), *direction);
        let max = best.map_or(f32::MAX, |b| b.1);
        let Some(hit) = model.trimesh.cast_ray_and_get_normal(pose, &ray, max, false) else {
            continue;
        };
        if best.is_some_and(|b| hit.time_of_impact >= b.1) {
            continue;
        }
        let n_tri = model.mesh.triangles.len() as u32;
        let tri = match hit.feature {
            FeatureId::Face(f) => (f % n_tri) as usize,
            _ => 0,
        };
        let local = pose.inverse_transform_point(&ray.point_at(hit.time_of_impact));
        best = Some((k, hit.time_of_impact, hit.normal, model.color_at(tri, &local)));
    }
    best
}

/// Renders `objects` (mutually occluding) as seen by `camera`. Rays are
/// cast only inside the box the objects' projected boxes span (a lone
/// object costs its own pixels, not the image's).
pub fn render(camera: &Camera, objects: &[Placed<'_>], light: &Light) -> Frame {
    let placed: Vec<(Isometry3<f32>, &RenderModel)> = objects.iter().map(|o| (isometry(o.pose), o.model)).collect();
    let to_light = light.direction.normalize().cast::<f32>();
    let (w, h) = (camera.width as usize, camera.height as usize);
    let mut depth = vec![0.0f32; w * h];
    let mut label = vec![0u16; w * h];
    let mut rgb = vec![[0u8; 3]; w * h];
    let mut albedo = vec![[0u8; 3]; w * h];
    let window = objects
        .iter()
        .filter_map(|o| projected_box(camera, o))
        .reduce(|a, b| (a.0.min(b.0), a.1.min(b.1), a.2.max(b.2), a.3.max(b.3)));
    let Some((u0, v0, u1, v1)) = window else {
        return Frame { width: camera.width, height: camera.height, depth, label, rgb, albedo };
    };
    let rows = depth
        .par_chunks_mut(w)
        .zip(label.par_chunks_mut(w))
        .zip(rgb.par_chunks_mut(w))
        .zip(albedo.par_chunks_mut(w))
        .enumerate();
    rows.skip(v0).take(v1 + 1 - v0).for_each(|(v, (((depth_row, label_row), rgb_row), albedo_row))| {
        for u in u0..=u1 {
            let direction = camera.ray_direction(u as f64, v as f64).cast::<f32>();
            let Some((k, toi, normal, color)) = first_hit(&placed, &direction) else {
                continue;
            };
            depth_row[u] = toi * direction.z;
            label_row[u] = k as u16 + 1;
            // Two-sided Lambert: the normal is flipped to face the camera.
            let n = if normal.dot(&direction) > 0.0 { -normal } else { normal };
            let shade = light.ambient as f32 + (1.0 - light.ambient as f32) * n.dot(&to_light).max(0.0);
            rgb_row[u] = color.map(|c| (c * shade * 255.0).round().clamp(0.0, 255.0) as u8);
            albedo_row[u] = color.map(|c| (c * 255.0).round().clamp(0.0, 255.0) as u8);
        }
    });
    Frame { width: camera.width, height: camera.height, depth, label, rgb, albedo }
}

/// Each object's full silhouette, ignoring the others (BOP's `mask/`; the
/// visible masks, `mask_visib/`, are the labels of [`render`]).
pub fn silhouettes(camera: &Camera, objects: &[Placed<'_>]) -> Vec<Vec<bool>> {
    objects.iter().map(|object| object_depth(camera, object).iter().map(|&z| z > 0.0).collect()).collect()
}

/// The depth of `object` alone (row-major, metres, 0 where it is not seen),
/// as for BOP's VSD. Rays are cast only inside the box that the object's
/// projected vertices span.
pub fn object_depth(camera: &Camera, object: &Placed<'_>) -> Vec<f32> {
    let (w, h) = (camera.width as usize, camera.height as usize);
    let mut depth = vec![0.0f32; w * h];
    let Some((u0, v0, u1, v1)) = projected_box(camera, object) else {
        return depth;
    };
    let pose = isometry(object.pose);
    depth.par_chunks_mut(w).enumerate().skip(v0).take(v1 + 1 - v0).for_each(|(v, row)| {
        for (u, z) in row.iter_mut().enumerate().take(u1 + 1).skip(u0) {
            let direction = camera.ray_direction(u as f64, v as f64).cast::<f32>();
            let ray = Ray::new(Point3::origin(), direction);
            if let Some(toi) = object.model.trimesh.cast_ray(&pose, &ray, f32::MAX, false) {
                *z = toi * direction.z;
            }
        }
    });
    depth
}

/// The pixels of `object`'s silhouette that lie outside the image but
/// within one image width and height of it: BOP's `calc_gt_info` counts
/// the silhouette on a canvas three times the image's size, so that an
/// object the image border cuts off has a `visib_fract` below 1. The whole
/// silhouette's `px_count_all` is this plus its pixels in the image.
pub fn truncated_pixels(camera: &Camera, object: &Placed<'_>) -> u64 {
    let (w, h) = (i64::from(camera.width), i64::from(camera.height));
    let Some((u0, v0, u1, v1)) = projected_bounds(camera, object, (-w, -h, 2 * w - 1, 2 * h - 1)) else {
        return 0;
    };
    let pose = isometry(object.pose);
    (v0..=v1)
        .into_par_iter()
        .map(|v| {
            let in_image_row = (0..h).contains(&v);
            (u0..=u1)
                .filter(|u| !(in_image_row && (0..w).contains(u)))
                .filter(|&u| {
                    let direction = camera.ray_direction(u as f64, v as f64).cast::<f32>();
                    object.model.trimesh.intersects_ray(&pose, &Ray::new(Point3::origin(), direction), f32::MAX)
                })
                .count() as u64
        })
        .sum()
}

/// The inclusive pixel box `(u0, v0, u1, v1)` that may see `object`: the
/// bounds of its projected vertices, clipped to the image; the whole image
/// when a vertex is behind the camera, `None` when it is outside.
fn projected_box(camera: &Camera, object: &Placed<'_>) -> Option<(usize, usize, usize, usize)> {
    let (w, h) = (i64::from(camera.width), i64::from(camera.height));
    let (u0, v0, u1, v1) = projected_bounds(camera, object, (0, 0, w - 1, h - 1))?;
    Some((u0 as usize, v0 as usize, u1 as usize, v1 as usize))
}

/// The bounds of `object`'s projected vertices, clipped to the inclusive
/// pixel box `canvas`; all of `canvas` when a vertex is behind the camera,
/// `None` when the object is outside it.
fn projected_bounds(
    camera: &Camera,
    object: &Placed<'_>,
    canvas: (i64, i64, i64, i64),
) -> Option<(i64, i64, i64, i64)> {
    let (cu0, cv0, cu1, cv1) = (canvas.0 as f64, canvas.1 as f64, canvas.2 as f64, canvas.3 as f64);
    let mut bounds = (f64::INFINITY, f64::INFINITY, f64::NEG_INFINITY, f64::NEG_INFINITY);
    for vertex in &object.model.mesh.vertices {
        let Some((u, v)) = camera.project(&object.pose.transform_point(&vertex.cast::<f64>())) else {
            bounds = (cu0, cv0, cu1, cv1);
            break;
        };
        bounds = (bounds.0.min(u), bounds.1.min(v), bounds.2.max(u), bounds.3.max(v));
    }
    let (u0, v0) = (bounds.0.floor().max(cu0), bounds.1.floor().max(cv0));
    let (u1, v1) = (bounds.2.ceil().min(cu1), bounds.3.ceil().min(cv1));
    (u0 <= u1 && v0 <= v1).then_some((u0 as i64, v0 as i64, u1 as i64, v1 as i64))
}
