//! What the current frame says about occlusion: the observed surface
//! (every other object, clutter, the table) as points that may hide the
//! target from a candidate camera. Unobserved space counts as free, so a
//! view is judged optimistically behind what the camera has not seen.
//!
//! Frames: points in the current camera frame (OpenCV axes, metres).

use nalgebra::Point3;
use poseflow_geometry::Pose;
use poseflow_ingest::{ObjectMask, RgbdFrame};
use poseflow_scene::Camera;

/// A rendered object pixel counts as hidden when an observed surface lies
/// this much (metres) in front of it: more than depth noise, less than a
/// thin object.
const HIDING_MARGIN: f32 = 0.01;

/// Largest splat half-width (pixels) of one observed point.
const MAX_SPLAT: i64 = 24;

/// Neighbouring samples farther apart than this (metres) lie on different
/// surfaces (a depth edge), not on one patch.
const MAX_PATCH: f64 = 0.05;

/// Observed surface points and the patch of surface each stands for.
#[derive(Debug, Clone, Default)]
pub struct Occluders {
    /// Current camera frame, metres.
    points: Vec<Point3<f64>>,
    /// Side (metres) of the surface patch each point stands for: the
    /// distance to its next samples along the row and the column, so a
    /// surface seen at a grazing angle from here has no holes when seen
    /// face-on from a candidate.
    patches: Vec<f64>,
}

impl Occluders {
    /// Every `stride`-th pixel (both ways) of `frame`'s depth with a
    /// measurement, outside `target`'s mask (the object does not hide
    /// itself: the renderer does that).
    pub fn from_depth(frame: &RgbdFrame, target: &ObjectMask, stride: usize) -> Self {
        let stride = stride.max(1);
        let (width, height) = (frame.depth.width as usize, frame.depth.height as usize);
        let camera = &frame.camera;
        let point = |u: usize, v: usize| -> Option<Point3<f64>> {
            let z = f64::from(*frame.depth.pixels.get(v * width + u)?);
            (z > 0.0).then(|| {
                let ray = camera.ray_direction(u as f64 + 0.5, v as f64 + 0.5);
                Point3::from(ray * (z / ray.z))
            })
        };
        let mut occluders = Self::default();
        for v in (0..height).step_by(stride) {
            for u in (0..width).step_by(stride) {
                if target.mask.pixels.get(v * width + u).copied().unwrap_or(false) {
                    continue;
                }
                let Some(here) = point(u, v) else { continue };
                let nominal = stride as f64 * here.z / camera.fx;
                let gaps = [
                    (u + stride < width).then(|| point(u + stride, v)),
                    (v + stride < height).then(|| point(u, v + stride)),
                ];
                let patch = gaps
                    .into_iter()
                    .flatten()
                    .flatten()
                    .map(|next| (next - here).norm())
                    .filter(|gap| *gap < MAX_PATCH)
                    .fold(nominal, f64::max);
                occluders.points.push(here);
                occluders.patches.push(patch);
            }
        }
        occluders
    }

    pub fn len(&self) -> usize {
        self.points.len()
    }

    pub fn is_empty(&self) -> bool {
        self.points.is_empty()
    }

    /// Hides the rendered object's pixels (`depth`, metres; `mask`) that an
    /// observed surface covers from `camera` at `next_from_current`; such a
    /// pixel takes the surface's depth. Returns how many it hid.
    pub fn hide(&self, camera: &Camera, next_from_current: &Pose, depth: &mut [f32], mask: &mut [bool]) -> usize {
        let (width, height) = (camera.width as i64, camera.height as i64);
        let mut nearest = vec![f32::INFINITY; depth.len()];
        for (point, patch) in self.points.iter().zip(&self.patches) {
            let p = next_from_current.transform_point(point);
            if p.z <= 1e-3 {
                continue;
            }
            let (u, v) = ((camera.fx * p.x / p.z + camera.cx) as i64, (camera.fy * p.y / p.z + camera.cy) as i64);
            // The patch the point stands for, as seen from the candidate:
            // `size` pixels across, covered by a square 2·half + 1 wide.
            let size = patch * camera.fx / p.z;
            let half = ((size / 2.0).floor() as i64).clamp(0, MAX_SPLAT);
            for y in (v - half).max(0)..=(v + half).min(height - 1) {
                for x in (u - half).max(0)..=(u + half).min(width - 1) {
                    let i = (y * width + x) as usize;
                    nearest[i] = nearest[i].min(p.z as f32);
                }
            }
        }
        let mut hidden = 0;
        for ((z, seen), front) in depth.iter_mut().zip(mask.iter_mut()).zip(&nearest) {
            if *seen && *front < *z - HIDING_MARGIN {
                *seen = false;
                *z = *front;
                hidden += 1;
            }
        }
        hidden
    }
}

#[cfg(test)]
mod tests {
    use nalgebra::{Rotation3, Vector3};
    use poseflow_scene::bop::Raster;
    use poseflow_scene::dataset::lmo_camera;

    use super::*;

    /// A 64×48 frame whose depth is `wall` metres everywhere, with
    /// `target` pixels (a centred 16×16 square) at 0.6 m.
    fn frame(wall: f32) -> (RgbdFrame, ObjectMask) {
        let camera = lmo_camera(64, 48);
        let target: Vec<bool> =
            (0..64 * 48).map(|i| (24..40).contains(&(i % 64)) && (16..32).contains(&(i / 64))).collect();
        let depth = target.iter().map(|&t| if t { 0.6 } else { wall }).collect();
        let raster = |pixels| Raster { width: 64, height: 48, pixels };
        let frame = RgbdFrame {
            frame_id: 1,
            label: "test".into(),
            camera,
            rgb: raster(vec![[0u8; 3]; 64 * 48]),
            depth: Raster { width: 64, height: 48, pixels: depth },
        };
        (frame, ObjectMask { obj_id: 1, instance: 0, mask: Raster { width: 64, height: 48, pixels: target } })
    }

    #[test]
    fn the_target_is_left_out_and_points_lie_on_their_rays() {
        let (frame, target) = frame(1.0);
        let occluders = Occluders::from_depth(&frame, &target, 2);
        // 32 × 24 samples, minus the target's 8 × 8.
        assert_eq!(occluders.len(), 32 * 24 - 64);
        assert!(occluders.points.iter().all(|p| (p.z - 1.0).abs() < 1e-6));
        assert!(Occluders::from_depth(&frame, &target, 1).len() > occluders.len());
    }

    #[test]
    fn a_surface_in_front_hides_the_object_and_one_behind_does_not() {
        let camera = lmo_camera(64, 48);
        // The object rendered at 0.6 m over the whole image.
        let rendered = || (vec![0.6f32; 64 * 48], vec![true; 64 * 48]);
        let same_camera = Pose::identity();

        // A wall at 0.4 m covers everything but where the target was seen.
        let (in_front, target) = frame(0.4);
        let (mut depth, mut mask) = rendered();
        let hidden = Occluders::from_depth(&in_front, &target, 1).hide(&camera, &same_camera, &mut depth, &mut mask);
        assert_eq!(hidden, 64 * 48 - 256);
        assert_eq!(mask.iter().filter(|&&m| m).count(), 256);
        assert!(depth.iter().zip(&mask).all(|(z, m)| if *m { *z == 0.6 } else { (*z - 0.4).abs() < 1e-6 }));

        // A wall behind the object, or within the margin, hides nothing.
        for wall in [1.0, 0.595] {
            let (behind, target) = frame(wall);
            let (mut depth, mut mask) = rendered();
            assert_eq!(
                Occluders::from_depth(&behind, &target, 1).hide(&camera, &same_camera, &mut depth, &mut mask),
                0
            );
            assert!(mask.iter().all(|&m| m));
        }

        // Seen from a camera turned half-way round (looking back at the
        // wall from beyond it), the wall is behind that camera: nothing
        // hidden.
        let (in_front, target) = frame(0.4);
        let turned = Pose::new(
            Rotation3::from_axis_angle(&Vector3::y_axis(), std::f64::consts::PI),
            Vector3::new(0.0, 0.0, 0.1),
        );
        let (mut depth, mut mask) = rendered();
        assert_eq!(Occluders::from_depth(&in_front, &target, 1).hide(&camera, &turned, &mut depth, &mut mask), 0);
    }
}
