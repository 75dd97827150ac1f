//! The BOP dataset format (<https://github.com/thodan/bop_toolkit>, `docs/
//! bop_datasets_format.md`): per-scene JSON files keyed by image id and PNG
//! images, read and written.
//!
//! Units as in BOP: translations in millimetres, rotations as row-major 3×3
//! matrices, depth PNGs 16-bit with `depth[mm] = value · depth_scale`,
//! masks 8-bit with 255 inside. Everything in this crate's API is metres;
//! the conversion happens here and only here.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use image::{ImageBuffer, Luma, Rgb};
use nalgebra::{Matrix3, Vector3};
use poseflow_geometry::Pose;
use poseflow_geometry::pose::{nearest_rotation, project_to_rotation};
use serde::de::DeserializeOwned;
use serde::{Deserialize, Serialize};

use crate::{Camera, SceneError};

/// BOP files give lengths in millimetres; PoseFlow works in metres.
pub const MM_PER_M: f64 = 1000.0;
/// Tolerance for rotation matrices read from JSON (max |RᵀR − I|). BOP
/// files print about eight digits, but real datasets' annotations are
/// orthonormal only to ~2e-3 (LM-O's `scene_gt.json`); those are projected
/// onto SO(3). Beyond this the file is broken, not imprecise.
const ROTATION_TOLERANCE: f64 = 1e-2;
/// Departures from orthonormality above this are logged (at debug level)
/// when projected.
const ROTATION_ROUNDING: f64 = 1e-6;

/// Per-image values of a scene file, keyed by image id.
pub type ByImage<T> = BTreeMap<u32, T>;

/// `camera.json` at the dataset root.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct DatasetCamera {
    pub cx: f64,
    pub cy: f64,
    pub depth_scale: f64,
    pub fx: f64,
    pub fy: f64,
    pub height: u32,
    pub width: u32,
}

impl DatasetCamera {
    pub fn new(camera: &Camera, depth_scale: f64) -> Self {
        Self {
            cx: camera.cx,
            cy: camera.cy,
            depth_scale,
            fx: camera.fx,
            fy: camera.fy,
            height: camera.height,
            width: camera.width,
        }
    }
}

/// One image's entry of `scene_camera.json`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct CameraEntry {
    /// Row-major intrinsics `[fx 0 cx; 0 fy cy; 0 0 1]`.
    #[serde(rename = "cam_K")]
    pub cam_k: [f64; 9],
    pub depth_scale: f64,
    #[serde(rename = "cam_R_w2c", default, skip_serializing_if = "Option::is_none")]
    pub cam_r_w2c: Option<[f64; 9]>,
    /// Millimetres.
    #[serde(rename = "cam_t_w2c", default, skip_serializing_if = "Option::is_none")]
    pub cam_t_w2c: Option<[f64; 3]>,
}

impl CameraEntry {
    pub fn new(camera: &Camera, depth_scale: f64, camera_from_world: Option<&Pose>) -> Self {
        let (cam_r_w2c, cam_t_w2c) = camera_from_world.map(pose_to_bop).unzip();
        Self {
            cam_k: [camera.fx, 0.0, camera.cx, 0.0, camera.fy, camera.cy, 0.0, 0.0, 1.0],
            depth_scale,
            cam_r_w2c,
            cam_t_w2c,
        }
    }

    /// The intrinsics of `cam_K` as they are (no checks; see [`Self::camera`]).
    pub fn pinhole(&self) -> poseflow_geometry::metrics::Pinhole {
        let k = &self.cam_k;
        poseflow_geometry::metrics::Pinhole { fx: k[0], fy: k[4], cx: k[2], cy: k[5] }
    }

    /// The pinhole camera for an image of the given size; rejects
    /// intrinsics that are not finite or not a pinhole matrix.
    pub fn camera(&self, width: u32, height: u32, file: &Path, im_id: u32) -> Result<Camera, SceneError> {
        let k = &self.cam_k;
        let location = format!("image {im_id}: cam_K");
        if k.iter().any(|v| !v.is_finite()) || k[0] <= 0.0 || k[4] <= 0.0 {
            return Err(SceneError::malformed(
                file,
                location,
                format!("expected finite intrinsics with fx, fy > 0, found {k:?}"),
            ));
        }
        if !self.depth_scale.is_finite() || self.depth_scale <= 0.0 {
            return Err(SceneError::malformed(
                file,
                format!("image {im_id}: depth_scale"),
                format!("expected a positive number, found {}", self.depth_scale),
            ));
        }
        Ok(Camera { fx: k[0], fy: k[4], cx: k[2], cy: k[5], width, height })
    }

    /// `camera_from_world`, when the file has it.
    pub fn camera_from_world(&self, file: &Path, im_id: u32) -> Result<Option<Pose>, SceneError> {
        match (&self.cam_r_w2c, &self.cam_t_w2c) {
            (Some(r), Some(t)) => pose_from_bop(r, t, file, &format!("image {im_id}: cam_R_w2c/cam_t_w2c")).map(Some),
            _ => Ok(None),
        }
    }
}

/// One object instance of `scene_gt.json`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct GtEntry {
    #[serde(rename = "cam_R_m2c")]
    pub cam_r_m2c: [f64; 9],
    /// Millimetres.
    #[serde(rename = "cam_t_m2c")]
    pub cam_t_m2c: [f64; 3],
    pub obj_id: u32,
}

impl GtEntry {
    pub fn new(obj_id: u32, camera_from_object: &Pose) -> Self {
        let (cam_r_m2c, cam_t_m2c) = pose_to_bop(camera_from_object);
        Self { cam_r_m2c, cam_t_m2c, obj_id }
    }

    /// `camera_from_object` in metres.
    pub fn pose(&self, file: &Path, im_id: u32, instance: usize) -> Result<Pose, SceneError> {
        pose_from_bop(&self.cam_r_m2c, &self.cam_t_m2c, file, &format!("image {im_id}, instance {instance}"))
    }
}

/// One object instance of `scene_gt_info.json`. Boxes are `[x, y, width,
/// height]` in pixels, `[-1, -1, -1, -1]` when empty.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct GtInfoEntry {
    pub bbox_obj: [i32; 4],
    pub bbox_visib: [i32; 4],
    /// Pixels of the full silhouette inside the image.
    pub px_count_all: u64,
    /// Pixels of the full silhouette with a depth measurement.
    pub px_count_valid: u64,
    /// Pixels where the object is visible.
    pub px_count_visib: u64,
    /// `px_count_visib / px_count_all`, 0 for an object outside the image.
    pub visib_fract: f64,
}

fn pose_to_bop(pose: &Pose) -> ([f64; 9], [f64; 3]) {
    let r = pose.rotation.matrix();
    let rotation = std::array::from_fn(|i| r[(i / 3, i % 3)]);
    let translation = std::array::from_fn(|i| pose.translation[i] * MM_PER_M);
    (rotation, translation)
}

fn pose_from_bop(r: &[f64; 9], t: &[f64; 3], file: &Path, location: &str) -> Result<Pose, SceneError> {
    if r.iter().chain(t).any(|v| !v.is_finite()) {
        return Err(SceneError::malformed(file, location, format!("expected finite values, found R {r:?}, t {t:?}")));
    }
    let matrix = Matrix3::from_row_slice(r);
    project_to_rotation(&matrix, "rotation", ROTATION_TOLERANCE)
        .map_err(|err| SceneError::malformed(file, location, format!("{err} (tolerance {ROTATION_TOLERANCE:e})")))?;
    let departure = (matrix.transpose() * matrix - Matrix3::identity()).abs().max();
    if departure > ROTATION_ROUNDING {
        tracing::debug!(file = %file.display(), location, departure, "rotation projected onto SO(3)");
    }
    let rotation = nearest_rotation(&matrix);
    Ok(Pose::new(rotation, Vector3::from_row_slice(t) / MM_PER_M))
}

/// The files of one BOP scene directory (`<split>/<scene_id:06>/`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SceneDir {
    pub path: PathBuf,
}

impl SceneDir {
    pub fn new(split_dir: &Path, scene_id: u32) -> Self {
        Self { path: split_dir.join(format!("{scene_id:06}")) }
    }

    pub fn scene_camera(&self) -> PathBuf {
        self.path.join("scene_camera.json")
    }
    pub fn scene_gt(&self) -> PathBuf {
        self.path.join("scene_gt.json")
    }
    pub fn scene_gt_info(&self) -> PathBuf {
        self.path.join("scene_gt_info.json")
    }
    /// A rendered video's events ([`crate::video::EventRecord`]); not BOP.
    pub fn video_events(&self) -> PathBuf {
        self.path.join("video_events.json")
    }
    pub fn rgb(&self, im_id: u32) -> PathBuf {
        self.path.join(format!("rgb/{im_id:06}.png"))
    }
    pub fn depth(&self, im_id: u32) -> PathBuf {
        self.path.join(format!("depth/{im_id:06}.png"))
    }
    pub fn mask(&self, im_id: u32, instance: usize) -> PathBuf {
        self.path.join(format!("mask/{im_id:06}_{instance:06}.png"))
    }
    pub fn mask_visib(&self, im_id: u32, instance: usize) -> PathBuf {
        self.path.join(format!("mask_visib/{im_id:06}_{instance:06}.png"))
    }

    /// Creates the directory and its image folders.
    pub fn create(&self) -> Result<(), SceneError> {
        for sub in ["rgb", "depth", "mask", "mask_visib"] {
            let dir = self.path.join(sub);
            std::fs::create_dir_all(&dir).map_err(|source| SceneError::Write { path: dir, source })?;
        }
        Ok(())
    }
}

/// Reads a JSON file into `T`, naming the file, line and column of any
/// mismatch.
pub fn read_json<T: DeserializeOwned>(path: &Path) -> Result<T, SceneError> {
    let text = std::fs::read_to_string(path).map_err(|source| SceneError::Io { path: path.to_path_buf(), source })?;
    serde_json::from_str(&text).map_err(|err| {
        SceneError::malformed(path, format!("line {} column {}", err.line(), err.column()), err.to_string())
    })
}

/// Writes a JSON value pretty-printed.
pub fn write_json<T: Serialize>(path: &Path, value: &T) -> Result<(), SceneError> {
    let text = serde_json::to_string_pretty(value).map_err(|err| SceneError::Invalid(err.to_string()))?;
    write_file(path, (text + "\n").as_bytes())
}

/// Writes a per-image scene file as BOP does: one line per image id, in
/// ascending order.
pub fn write_by_image<T: Serialize>(path: &Path, entries: &ByImage<T>) -> Result<(), SceneError> {
    let mut text = String::from("{\n");
    for (i, (im_id, value)) in entries.iter().enumerate() {
        let value = serde_json::to_string(value).map_err(|err| SceneError::Invalid(err.to_string()))?;
        let comma = if i + 1 < entries.len() { "," } else { "" };
        text.push_str(&format!("  \"{im_id}\": {value}{comma}\n"));
    }
    text.push_str("}\n");
    write_file(path, text.as_bytes())
}

fn write_file(path: &Path, bytes: &[u8]) -> Result<(), SceneError> {
    std::fs::write(path, bytes).map_err(|source| SceneError::Write { path: path.to_path_buf(), source })
}

/// A row-major image read from a file.
#[derive(Debug, Clone, PartialEq)]
pub struct Raster<T> {
    pub width: u32,
    pub height: u32,
    pub pixels: Vec<T>,
}

fn image_error(path: &Path, err: impl std::fmt::Display) -> SceneError {
    SceneError::Image { path: path.to_path_buf(), detail: err.to_string() }
}

fn save<P: image::Pixel<Subpixel = S> + image::PixelWithColorType, S: image::Primitive>(
    path: &Path,
    image: ImageBuffer<P, Vec<S>>,
) -> Result<(), SceneError>
where
    [S]: image::EncodableLayout,
{
    image.save_with_format(path, image::ImageFormat::Png).map_err(|err| image_error(path, err))
}

fn size_error(path: &Path, width: u32, height: u32, len: usize) -> SceneError {
    image_error(path, format!("{len} pixels do not make a {width}×{height} image"))
}

pub fn write_rgb_png(path: &Path, width: u32, height: u32, rgb: &[[u8; 3]]) -> Result<(), SceneError> {
    let image = ImageBuffer::<Rgb<u8>, _>::from_raw(width, height, rgb.as_flattened().to_vec())
        .ok_or_else(|| size_error(path, width, height, rgb.len()))?;
    save(path, image)
}

/// Depth in metres to a 16-bit PNG of `depth_scale` millimetre units;
/// depths beyond the format's range become 0 (no measurement).
pub fn write_depth_png(
    path: &Path,
    width: u32,
    height: u32,
    depth_m: &[f32],
    depth_scale: f64,
) -> Result<(), SceneError> {
    let units = depth_m
        .iter()
        .map(|&z| {
            let value = (f64::from(z) * MM_PER_M / depth_scale).round();
            if value.is_finite() && value > 0.0 && value <= f64::from(u16::MAX) { value as u16 } else { 0 }
        })
        .collect();
    let image = ImageBuffer::<Luma<u16>, _>::from_raw(width, height, units)
        .ok_or_else(|| size_error(path, width, height, depth_m.len()))?;
    save(path, image)
}

pub fn write_mask_png(path: &Path, width: u32, height: u32, mask: &[bool]) -> Result<(), SceneError> {
    let bytes = mask.iter().map(|&inside| if inside { 255 } else { 0 }).collect();
    let image = ImageBuffer::<Luma<u8>, _>::from_raw(width, height, bytes)
        .ok_or_else(|| size_error(path, width, height, mask.len()))?;
    save(path, image)
}

fn open(path: &Path) -> Result<image::DynamicImage, SceneError> {
    if !path.is_file() {
        return Err(SceneError::Io {
            path: path.to_path_buf(),
            source: std::io::Error::new(std::io::ErrorKind::NotFound, "no such file"),
        });
    }
    image::open(path).map_err(|err| image_error(path, err))
}

pub fn read_rgb_png(path: &Path) -> Result<Raster<[u8; 3]>, SceneError> {
    let image = open(path)?.into_rgb8();
    let (width, height) = image.dimensions();
    let pixels = image.into_raw().chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect();
    Ok(Raster { width, height, pixels })
}

/// A 16-bit depth PNG in metres (0 = no measurement). 8-bit images are
/// rejected: they cannot hold depth at millimetre resolution and are
/// usually an RGB or mask file in the wrong place.
pub fn read_depth_png(path: &Path, depth_scale: f64) -> Result<Raster<f32>, SceneError> {
    let image = match open(path)? {
        image::DynamicImage::ImageLuma16(image) => image,
        other => {
            return Err(image_error(
                path,
                format!("expected a 16-bit single-channel depth PNG, found {:?}", other.color()),
            ));
        }
    };
    let (width, height) = image.dimensions();
    let scale = depth_scale / MM_PER_M;
    let pixels = image.into_raw().into_iter().map(|v| (f64::from(v) * scale) as f32).collect();
    Ok(Raster { width, height, pixels })
}

/// A mask PNG: any non-zero pixel is inside.
pub fn read_mask_png(path: &Path) -> Result<Raster<bool>, SceneError> {
    let image = open(path)?.into_luma8();
    let (width, height) = image.dimensions();
    Ok(Raster { width, height, pixels: image.into_raw().into_iter().map(|v| v > 0).collect() })
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Rotation3;

    #[test]
    fn poses_survive_the_millimetre_round_trip() {
        let pose = Pose::new(Rotation3::from_euler_angles(0.3, -1.2, 2.9), Vector3::new(0.0123, -0.2, 0.9876));
        let entry = GtEntry::new(5, &pose);
        assert!((entry.cam_t_m2c[2] - 987.6).abs() < 1e-9);
        let text = serde_json::to_string(&entry).unwrap();
        assert!(text.contains("\"cam_R_m2c\"") && text.contains("\"obj_id\":5"), "{text}");
        let back: GtEntry = serde_json::from_str(&text).unwrap();
        let read = back.pose(Path::new("scene_gt.json"), 0, 0).unwrap();
        assert!((read.rotation.matrix() - pose.rotation.matrix()).abs().max() < 1e-12);
        assert!((read.translation - pose.translation).norm() < 1e-12);
    }

    #[test]
    fn bad_intrinsics_and_rotations_name_file_image_and_value() {
        let camera = Camera { fx: 500.0, fy: 500.0, cx: 320.0, cy: 240.0, width: 640, height: 480 };
        let mut entry = CameraEntry::new(&camera, 0.1, None);
        assert_eq!(entry.camera(640, 480, Path::new("c.json"), 3).unwrap(), camera);
        entry.cam_k[4] = f64::NAN;
        let err = entry.camera(640, 480, Path::new("c.json"), 3).unwrap_err().to_string();
        assert!(err.contains("c.json") && err.contains("image 3: cam_K") && err.contains("NaN"), "{err}");
        let gt = GtEntry { cam_r_m2c: [1.0, 0.0, 0.0, 0.0, 2.0, 0.0, 0.0, 0.0, 1.0], cam_t_m2c: [0.0; 3], obj_id: 1 };
        let err = gt.pose(Path::new("g.json"), 7, 2).unwrap_err().to_string();
        assert!(err.contains("g.json") && err.contains("image 7, instance 2"), "{err}");
    }

    #[test]
    fn nearly_orthonormal_ground_truth_is_projected_and_a_broken_one_refused() {
        // As LM-O's scene_gt.json has them: |RᵀR − I| about 2e-3.
        let rotation = Rotation3::from_euler_angles(0.4, -0.3, 1.1);
        let scaled = |factor: f64| -> [f64; 9] { std::array::from_fn(|i| factor * rotation.matrix()[(i / 3, i % 3)]) };
        // RᵀR = 1.001² I: 2e-3 off.
        let r = scaled(1.001);
        let gt = GtEntry { cam_r_m2c: r, cam_t_m2c: [10.0, 20.0, 800.0], obj_id: 1 };
        let pose = gt.pose(Path::new("scene_gt.json"), 0, 0).unwrap();
        let orthogonality =
            (pose.rotation.matrix().transpose() * pose.rotation.matrix() - Matrix3::identity()).abs().max();
        assert!(orthogonality < 1e-12, "{orthogonality}");
        let angle = poseflow_geometry::so3::geodesic_angle(&pose.rotation, &rotation);
        assert!(angle < 1e-6, "{angle}");
        // 6 % off is a broken file: refused, naming the tolerance.
        let gt = GtEntry { cam_r_m2c: scaled(1.03), ..gt };
        let err = gt.pose(Path::new("scene_gt.json"), 4, 1).unwrap_err().to_string();
        assert!(err.contains("image 4, instance 1") && err.contains("tolerance 1e-2"), "{err}");
    }
}
