//! A cluttered table (the vendored LM-O objects among distractors, heavy
//! occlusion) seen so that one target object is mostly hidden: the
//! occluded starts of the next-best-view simulation.
//!
//! World frame: z up, the table top is `z = 0`, metres.

use poseflow_geometry::Pose;
use poseflow_geometry::sampling::SeededRng;
use poseflow_ingest::{ObjectMask, RgbdFrame};
use poseflow_scene::ModelLibrary;
use poseflow_scene::dataset::lmo_camera;
use poseflow_scene::scene::{Occlusion, Scene, ViewRange, compose_scene, random_light, render_view};

use super::sensor_frame;

/// One rendered view of the target: the frame and its visible mask, the
/// truth, and how much of the target's silhouette is in view.
#[derive(Debug, Clone)]
pub struct ClutterView {
    pub frame: RgbdFrame,
    pub mask: ObjectMask,
    pub camera_from_object: Pose,
    pub camera_from_world: Pose,
    /// Visible pixels of the target over its full silhouette (0 when the
    /// silhouette is empty).
    pub visible_share: f64,
    pub visible_pixels: usize,
}

/// Renders `scene` from `camera_from_world` and observes library object
/// `target` (LM-O camera, random light, depth noise).
pub fn view_clutter(
    library: &ModelLibrary,
    scene: &Scene,
    target: usize,
    camera_from_world: &Pose,
    frame_id: u64,
    rng: &mut SeededRng,
) -> ClutterView {
    let camera = lmo_camera(640, 480);
    let view = render_view(library, scene, &camera, camera_from_world, &random_light(rng));
    let label = u16::try_from(target + 1).expect("fewer than 65535 objects");
    let visible: Vec<bool> = view.frame.label.iter().map(|&l| l == label).collect();
    let visible_pixels = visible.iter().filter(|&&v| v).count();
    let silhouette = view.silhouettes[target].iter().filter(|&&s| s).count();
    let camera_from_object = view.object_poses[target];
    let observed = (scene.objects[target].obj_id, target, visible);
    let (frame, mask) = sensor_frame(camera, frame_id, format!("clutter view {frame_id}"), view.frame, observed, rng);
    ClutterView {
        frame,
        mask,
        camera_from_object,
        camera_from_world: *camera_from_world,
        visible_share: if silhouette == 0 { 0.0 } else { visible_pixels as f64 / silhouette as f64 },
        visible_pixels,
    }
}

/// Draws crowded scenes of every library object and cameras around them
/// until `target` is heavily occluded yet observable: in view, 15–45 % of
/// its silhouette visible, at least 300 pixels.
pub fn render_occluded(
    library: &ModelLibrary,
    target: usize,
    frame_id: u64,
    rng: &mut SeededRng,
) -> (Scene, ClutterView) {
    // Closer than the dataset's views, so the target is large enough to
    // estimate once it is uncovered.
    let range = ViewRange { distance: (0.4, 0.8), elevation_deg: (15.0, 50.0), max_in_plane_deg: 0.0 };
    loop {
        let scene = compose_scene(library, Occlusion::High, rng);
        for _ in 0..50 {
            let camera_from_world = range.sample(&scene, rng);
            let view = view_clutter(library, &scene, target, &camera_from_world, frame_id, rng);
            if (0.15..=0.45).contains(&view.visible_share) && view.visible_pixels >= 300 {
                return (scene, view);
            }
        }
    }
}
