//! A simulated observation: the object alone, rendered at one hypothesis
//! from one candidate camera, with the sensor's depth noise.

use poseflow_geometry::Pose;
use poseflow_geometry::sampling::SeededRng;
use poseflow_ingest::{ObjectMask, RgbdFrame};
use poseflow_scene::bop::Raster;
use poseflow_scene::{Camera, DepthNoise, Light, Placed, RenderModel, render};

use crate::Occluders;

/// Colour of pixels that see nothing: a neutral grey, as no scene behind
/// the object is known.
const BACKGROUND: [u8; 3] = [100, 100, 100];

/// Where the candidate camera is and what may hide the object from it.
#[derive(Debug, Clone, Copy)]
pub struct Viewpoint<'a> {
    pub camera: &'a Camera,
    /// The object in the candidate camera's frame.
    pub camera_from_object: Pose,
    /// The candidate camera's pose relative to the current one, and the
    /// current frame's observed surface.
    pub occluders: Option<(&'a Occluders, Pose)>,
}

/// The rendered frame and the object's mask, or `None` when fewer than
/// `min_pixels` object pixels are in view (after the occluders hid theirs).
pub fn simulated_view(
    model: &RenderModel,
    obj_id: u32,
    viewpoint: &Viewpoint<'_>,
    frame_id: u64,
    min_pixels: usize,
    rng: &mut SeededRng,
) -> Option<(RgbdFrame, ObjectMask)> {
    let camera = viewpoint.camera;
    let mut rendered = render(camera, &[Placed { model, pose: &viewpoint.camera_from_object }], &Light::default());
    let mut mask: Vec<bool> = rendered.label.iter().map(|&l| l == 1).collect();
    if let Some((occluders, next_from_current)) = &viewpoint.occluders {
        occluders.hide(camera, next_from_current, &mut rendered.depth, &mut mask);
    }
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
