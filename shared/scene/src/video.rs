//! Events in a rendered video (an orbit camera path), for tracking
//! benchmarks: an object hidden by an occluder sliding across its line of
//! sight, and an object moved between two images (a teleport). Each scene's
//! schedule follows from the seed, the scene and the video's length.
//!
//! Frames as in [`crate::scene`]: world z up, metres.

use nalgebra::{Point3, Rotation3, Vector2, Vector3};
use poseflow_geometry::Pose;
use rand::Rng;

use crate::library::ModelLibrary;
use crate::primitives::ClutterShape;
use crate::render::RenderModel;
use crate::scene::Scene;

/// Images before the first event: the tracker has settled.
const LEAD_IN: u32 = 10;
/// Images after an event before the next may start: the tracker can
/// recover in between, so each event is measured on its own.
const SETTLE: u32 = 12;
/// Fully hidden images per occlusion event.
pub const HIDDEN_IMAGES: (u32, u32) = (5, 20);
/// The occluder's angular half-width, in units of the hidden object's
/// angular radius (its bounding sphere).
const OCCLUDER_WIDTH: f64 = 2.5;
/// Where the occluder stands between the object (0) and the camera (1).
const OCCLUDER_PLACE: f64 = 0.4;
/// A teleport turns the object about the vertical by this much (degrees)
/// and shifts it on the table by at most this much (metres).
const TELEPORT_TURN_DEG: (f64, f64) = (90.0, 180.0);
const TELEPORT_SHIFT: f64 = 0.05;

/// How many events each scene of a video gets.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct VideoEvents {
    /// An object fully hidden for 5–20 images by a box sliding across its
    /// line of sight.
    pub occlusions: u32,
    /// An object turned about the vertical by 90–180° and shifted up to
    /// 5 cm between two images.
    pub teleports: u32,
}

impl VideoEvents {
    pub fn is_empty(&self) -> bool {
        self.occlusions == 0 && self.teleports == 0
    }
}

/// One scheduled event; objects by index into [`Scene::objects`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Event {
    /// The occluder crosses during images `start .. start + span(hidden)`,
    /// hiding the object wholly for about `hidden` of them in the middle.
    Occlusion { object: usize, start: u32, hidden: u32 },
    /// From image `at` on, the object stands turned and shifted.
    Teleport { object: usize, at: u32, turn_deg: f64, shift: Vector2<f64> },
}

/// An event as `video_events.json` lists it, by BOP object id.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(tag = "kind", rename_all = "kebab-case")]
pub enum EventRecord {
    /// The occluder crosses the object during images `start..end`; about
    /// `hidden` of them in the middle show none of it.
    Occlusion { obj_id: u32, start: u32, end: u32, hidden: u32 },
    /// The object stands turned by `turn_deg` about the vertical and shifted
    /// by `shift_m` (world x, y) from image `at` on.
    Teleport { obj_id: u32, at: u32, turn_deg: f64, shift_m: [f64; 2] },
}

impl EventRecord {
    pub fn new(event: &Event, scene: &Scene) -> Self {
        match *event {
            Event::Occlusion { object, start, hidden } => {
                Self::Occlusion { obj_id: scene.objects[object].obj_id, start, end: event.end(), hidden }
            }
            Event::Teleport { object, at, turn_deg, shift } => {
                Self::Teleport { obj_id: scene.objects[object].obj_id, at, turn_deg, shift_m: [shift.x, shift.y] }
            }
        }
    }
}

/// Images an occlusion of `hidden` fully hidden images spans: the occluder
/// travels from touching the object's silhouette on one side to the other.
pub fn occlusion_span(hidden: u32) -> u32 {
    let (wide, narrow) = (OCCLUDER_WIDTH + 1.0, OCCLUDER_WIDTH - 1.0);
    (f64::from(hidden) * wide / narrow).ceil() as u32
}

impl Event {
    /// The first image after the event.
    pub fn end(&self) -> u32 {
        match *self {
            Self::Occlusion { start, hidden, .. } => start + occlusion_span(hidden),
            Self::Teleport { at, .. } => at + 1,
        }
    }
}

/// The events of one scene of `frames` images with `objects` objects, in
/// time order, apart by at least [`SETTLE`] images. Events that do not fit
/// in the video are left out (the caller can count them).
pub fn schedule<R: Rng + ?Sized>(events: &VideoEvents, objects: usize, frames: u32, rng: &mut R) -> Vec<Event> {
    if objects == 0 {
        return Vec::new();
    }
    let mut kinds: Vec<bool> =
        (0..events.occlusions).map(|_| true).chain((0..events.teleports).map(|_| false)).collect();
    // Occlusions and teleports interleaved in a seeded order.
    for i in (1..kinds.len()).rev() {
        kinds.swap(i, rng.random_range(0..=i));
    }
    let mut cursor = LEAD_IN;
    let mut scheduled = Vec::new();
    for (k, occlusion) in kinds.into_iter().enumerate() {
        let object = (k + rng.random_range(0..objects)) % objects;
        let start = cursor + rng.random_range(0..=4);
        let event = if occlusion {
            Event::Occlusion { object, start, hidden: rng.random_range(HIDDEN_IMAGES.0..=HIDDEN_IMAGES.1) }
        } else {
            let turn_deg = rng.random_range(TELEPORT_TURN_DEG.0..=TELEPORT_TURN_DEG.1)
                * if rng.random_bool(0.5) { 1.0 } else { -1.0 };
            let angle = rng.random_range(0.0..std::f64::consts::TAU);
            let shift = Vector2::new(angle.cos(), angle.sin()) * rng.random_range(0.0..=TELEPORT_SHIFT);
            Event::Teleport { object, at: start, turn_deg, shift }
        };
        if event.end() > frames {
            break;
        }
        cursor = event.end() + SETTLE;
        scheduled.push(event);
    }
    scheduled
}

/// `scene` as image `im_id` shows it: teleported objects moved, and the
/// occluder of an occlusion under way placed for the camera at
/// `camera_from_world`.
pub fn scene_at(
    scene: &Scene,
    library: &ModelLibrary,
    events: &[Event],
    im_id: u32,
    camera_from_world: &Pose,
) -> Scene {
    let mut shown = scene.clone();
    for event in events {
        match *event {
            Event::Teleport { object, at, turn_deg, shift } if at <= im_id => {
                let placed = &mut shown.objects[object].world_from_object;
                let turn = Rotation3::from_axis_angle(&Vector3::z_axis(), turn_deg.to_radians());
                *placed = Pose::new(turn * placed.rotation, placed.translation + Vector3::new(shift.x, shift.y, 0.0));
            }
            _ => {}
        }
    }
    for event in events {
        if let Event::Occlusion { object, start, hidden } = *event
            && (start..event.end()).contains(&im_id)
        {
            let target = &shown.objects[object];
            let radius = library.objects[target.library_index].info.diameter / 2.0;
            let travelled = (f64::from(im_id - start) + 0.5) / f64::from(occlusion_span(hidden));
            shown.clutter.push(occluder(
                &target.world_from_object.translation.into(),
                radius,
                camera_from_world,
                travelled,
            ));
        }
    }
    shown
}

/// The occluder for an object at `centre` (bounding radius `radius`), seen
/// from `camera_from_world`, `travelled` (0–1) of the way across: a thin
/// grey box facing the camera, sliding along the image's x axis.
fn occluder(centre: &Point3<f64>, radius: f64, camera_from_world: &Pose, travelled: f64) -> (RenderModel, Pose) {
    let world_from_camera = camera_from_world.inverse();
    let eye = world_from_camera.translation;
    let to_camera = eye - centre.coords;
    let distance = to_camera.norm();
    let at = centre.coords + to_camera * OCCLUDER_PLACE;
    let box_distance = distance * (1.0 - OCCLUDER_PLACE);
    // Angular units of the object's radius, converted to metres at the box.
    let angular_radius = radius / distance;
    let reach = (OCCLUDER_WIDTH + 1.0) * angular_radius;
    let offset = (-reach + 2.0 * reach * travelled) * box_distance;
    let half_width = (OCCLUDER_WIDTH * angular_radius * box_distance) as f32;
    let image_x = world_from_camera.rotation * Vector3::x();
    let shape = ClutterShape::Box { half_extents: Vector3::new(half_width, half_width, 0.01) };
    let model = RenderModel::new(shape.mesh([120, 118, 112])).expect("a box is a valid mesh");
    (model, Pose::new(world_from_camera.rotation, at + image_x * offset))
}

#[cfg(test)]
mod tests {
    use super::*;
    use poseflow_geometry::sampling::seeded_rng;

    #[test]
    fn events_fit_the_video_in_order_and_apart() {
        let wanted = VideoEvents { occlusions: 3, teleports: 3 };
        for seed in 0..50 {
            let events = schedule(&wanted, 3, 300, &mut seeded_rng(seed));
            assert!(!events.is_empty());
            for pair in events.windows(2) {
                let next_start = match pair[1] {
                    Event::Occlusion { start, .. } => start,
                    Event::Teleport { at, .. } => at,
                };
                assert!(next_start >= pair[0].end() + SETTLE, "{pair:?}");
            }
            for event in &events {
                assert!(event.end() <= 300);
                match *event {
                    Event::Occlusion { object, hidden, .. } => {
                        assert!(object < 3 && (HIDDEN_IMAGES.0..=HIDDEN_IMAGES.1).contains(&hidden));
                    }
                    Event::Teleport { object, turn_deg, shift, .. } => {
                        assert!(object < 3 && (90.0..=180.0).contains(&turn_deg.abs()) && shift.norm() <= 0.05);
                    }
                }
            }
        }
        // A short video holds fewer events; none without objects.
        assert!(schedule(&wanted, 3, 40, &mut seeded_rng(1)).len() < 6);
        assert!(schedule(&wanted, 0, 300, &mut seeded_rng(1)).is_empty());
    }

    #[test]
    fn the_span_covers_the_hidden_images_and_both_crossings() {
        assert_eq!(occlusion_span(6), 14);
        assert!(occlusion_span(20) > 20);
    }
}
