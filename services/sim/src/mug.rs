//! A mug standing alone on a table, seen with its handle in view or hidden
//! behind its body: the paper's grasping scenes.
//!
//! World frame: z up, the table top is `z = 0`, metres. The YCB-V mug's
//! handle points along its object +x (beyond the body's 4.65 cm radius);
//! its axis is object z.

use nalgebra::{Point3, Rotation3, Vector3};
use poseflow_geometry::Pose;
use poseflow_geometry::sampling::SeededRng;
use poseflow_ingest::{ObjectMask, RgbdFrame};
use poseflow_scene::dataset::lmo_camera;
use poseflow_scene::part::ObjectPart;
use poseflow_scene::primitives::support_plane;
use poseflow_scene::scene::{Scene, SceneObject, look_at, random_light, render_view};
use poseflow_scene::{ModelLibrary, RenderModel};
use rand::Rng;

use super::sensor_frame;

/// Where the handle points relative to the camera.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Handle {
    /// Turned 60–120° from the line of sight: seen from the side.
    Visible,
    /// Pointing away from the camera (within 15°): hidden behind the body.
    Occluded,
    /// Hidden behind the body but turned 25–70° from pointing away: a
    /// network that has learnt "a hidden handle points away" puts it in the
    /// wrong place, while every pose on the hidden arc explains the image.
    HiddenAside,
}

impl Handle {
    pub fn name(self) -> &'static str {
        match self {
            Self::Visible => "visible",
            Self::Occluded => "occluded",
            Self::HiddenAside => "hidden_aside",
        }
    }
}

/// One rendered view: the frame and mask the pipeline reads, the truth,
/// and how much of the handle the camera sees.
#[derive(Debug, Clone)]
pub struct MugView {
    pub frame: RgbdFrame,
    pub mask: ObjectMask,
    pub camera_from_object: Pose,
    pub camera_from_world: Pose,
    /// Visible mug pixels that lie on the handle.
    pub handle_pixels: usize,
}

/// The mug (library object 0) standing on `plane` (the table) with its
/// handle turned `yaw` radians from world +x.
fn mug_scene(library: &ModelLibrary, yaw: f64, plane: RenderModel) -> Scene {
    let mug = &library.objects[0];
    let (min, max) = mug.model.mesh.bounds();
    let world_from_object =
        Pose::new(Rotation3::from_axis_angle(&Vector3::z_axis(), yaw), Vector3::new(0.0, 0.0, -f64::from(min.z)));
    Scene {
        objects: vec![SceneObject { obj_id: mug.obj_id, library_index: 0, world_from_object }],
        clutter: Vec::new(),
        plane,
        centre: Point3::new(0.0, 0.0, f64::from(max.z - min.z) / 2.0),
        spread: 0.1,
        background: [90, 90, 100],
        backdrop: None,
    }
}

/// Renders the mug scene from `camera_from_world` (LM-O camera, random
/// light, depth noise).
pub fn view_mug(
    library: &ModelLibrary,
    scene: &Scene,
    camera_from_world: &Pose,
    frame_id: u64,
    rng: &mut SeededRng,
) -> MugView {
    view_mug_if(library, scene, camera_from_world, frame_id, rng, |_| true).expect("every view is wanted")
}

/// [`view_mug`] when `wanted(handle pixels)`; the depth noise is drawn only
/// then, so a rejected view costs the random stream its light alone.
fn view_mug_if(
    library: &ModelLibrary,
    scene: &Scene,
    camera_from_world: &Pose,
    frame_id: u64,
    rng: &mut SeededRng,
    wanted: impl Fn(usize) -> bool,
) -> Option<MugView> {
    let camera = lmo_camera(640, 480);
    let view = render_view(library, scene, &camera, camera_from_world, &random_light(rng));
    let camera_from_object = view.object_poses[0];
    let visible: Vec<bool> = view.frame.label.iter().map(|&l| l == 1).collect();
    let handle = ObjectPart { obj_id: scene.objects[0].obj_id, ..ObjectPart::ycbv_mug_handle() };
    let handle_pixels = handle.visible_pixels(&view, &camera, 0);
    if !wanted(handle_pixels) {
        return None;
    }
    let target = (scene.objects[0].obj_id, 0, visible);
    let (frame, mask) = sensor_frame(camera, frame_id, format!("mug trial {frame_id}"), view.frame, target, rng);
    Some(MugView { frame, mask, camera_from_object, camera_from_world: *camera_from_world, handle_pixels })
}

/// Draws a mug scene and a camera for `handle` until the handle's
/// visibility matches (hidden: at most 10 handle pixels; visible: at least
/// 150) and renders it.
pub fn render_mug(library: &ModelLibrary, handle: Handle, frame_id: u64, rng: &mut SeededRng) -> (Scene, MugView) {
    let plane = RenderModel::new(support_plane(1.0, 32, [150, 130, 110], rng)).expect("the plane is a valid mesh");
    loop {
        let azimuth = rng.random_range(0.0..std::f64::consts::TAU);
        let yaw = match handle {
            Handle::Occluded => azimuth + std::f64::consts::PI + rng.random_range(-15f64..=15.0).to_radians(),
            Handle::HiddenAside => {
                let side = if rng.random::<bool>() { 1.0 } else { -1.0 };
                azimuth + std::f64::consts::PI + side * rng.random_range(25f64..=70.0).to_radians()
            }
            Handle::Visible => {
                let side = if rng.random::<bool>() { 1.0 } else { -1.0 };
                azimuth + side * rng.random_range(60f64..=120.0).to_radians()
            }
        };
        let scene = mug_scene(library, yaw, plane.clone());
        let elevation = rng.random_range(15f64..=35.0).to_radians();
        let distance = rng.random_range(0.45..=0.65);
        let eye = scene.centre
            + distance
                * Vector3::new(elevation.cos() * azimuth.cos(), elevation.cos() * azimuth.sin(), elevation.sin());
        let camera_from_world = look_at(&eye, &scene.centre, 0.0);
        let wanted = |pixels: usize| match handle {
            Handle::Occluded | Handle::HiddenAside => pixels <= 10,
            Handle::Visible => pixels >= 150,
        };
        if let Some(view) = view_mug_if(library, &scene, &camera_from_world, frame_id, rng, wanted) {
            return (scene, view);
        }
    }
}
