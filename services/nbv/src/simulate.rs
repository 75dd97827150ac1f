//! A simulated observation: the object alone, rendered at one hypothesis
//! from one candidate camera, with the sensor's depth noise.

use poseflow_geometry::Pose;
use poseflow_geometry::sampling::SeededRng;
use poseflow_ingest::{ObjectMask, RgbdFrame};
use poseflow_scene::bop::Raster;
use poseflow_scene::{Camera, DepthNoise, Light, Placed, RenderModel, render};

/// Colour of pixels that see nothing: a neutral grey, as no scene behind
/// the object is known.
const BACKGROUND: [u8; 3] = [100, 100, 100];

/// The rendered frame and the object's mask, or `None` when fewer than
/// `min_pixels` object pixels are in view.
pub fn simulated_view(
    model: &RenderModel,
    obj_id: u32,
    camera: &Camera,
    camera_from_object: &Pose,
    frame_id: u64,
    min_pixels: usize,
    rng: &mut SeededRng,
) -> Option<(RgbdFrame, ObjectMask)> {
    let rendered = render(camera, &[Placed { model, pose: camera_from_object }], &Light::default());
    let mask: Vec<bool> = rendered.label.iter().map(|&l| l == 1).collect();
    if mask.iter().filter(|&&m| m).count() < min_pixels.max(1) {
        return None;
    }
    let rgb = rendered.rgb.iter().zip(&mask).map(|(&c, &m)| if m { c } else { BACKGROUND }).collect();
    let depth = DepthNoise::default().apply(&rendered.depth, camera.width as usize, rng);
    let (width, height) = (camera.width, camera.height);
    let frame = RgbdFrame {
        frame_id,
        label: format!("simulated view {frame_id:#x}"),
        camera: *camera,
        rgb: Raster { width, height, pixels: rgb },
        depth: Raster { width, height, pixels: depth },
    };
    Some((frame, ObjectMask { obj_id, instance: 0, mask: Raster { width, height, pixels: mask } }))
}
