//! Views chosen by what the camera sees of one part of an object: the
//! ambiguous views of a pose benchmark (a mug whose handle is hidden has a
//! whole arc of poses that explain the image; one whose handle is in view
//! has one).
//!
//! A part is the object-frame points beyond a plane, `axis · x > beyond`
//! (metres). Pixels are counted on the noiseless render at 640×480 and
//! scaled with the image area for other sizes.

use nalgebra::{Point3, Unit, Vector3};

use crate::Camera;
use crate::scene::{Scene, View};

/// Draws of camera and light tried per image, by default, before a
/// condition is called unsatisfiable for the scene's arrangement.
pub const MAX_VIEW_ATTEMPTS: usize = 400;
/// At most this many part pixels (at 640×480) for the part to be hidden.
pub const HIDDEN_MAX_PIXELS: f64 = 10.0;
/// At least this many part pixels (at 640×480) for the part to be visible.
pub const VISIBLE_MIN_PIXELS: f64 = 150.0;
/// Share of the object's silhouette that must be visible either way, so
/// that "hidden" means the part, not the whole object.
pub const MIN_OBJECT_VISIB_FRACT: f64 = 0.5;

/// The object-frame points `axis · x > beyond` of object `obj_id`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ObjectPart {
    pub obj_id: u32,
    pub axis: Unit<Vector3<f64>>,
    /// Metres along `axis`.
    pub beyond: f64,
}

impl ObjectPart {
    /// The YCB-V mug's handle (BOP YCB-V id 14, `025_mug`): its body is a
    /// 4.65 cm-radius cylinder about object z, the handle points along +x.
    pub fn ycbv_mug_handle() -> Self {
        Self { obj_id: 14, axis: Vector3::x_axis(), beyond: 0.05 }
    }

    /// Whether an object-frame point (metres) lies on the part.
    pub fn contains(&self, object_point: &Point3<f64>) -> bool {
        self.axis.dot(&object_point.coords) > self.beyond
    }

    /// Pixels where instance `instance` of the view (label `instance + 1`)
    /// is visible and its (noiseless) surface point lies on the part.
    pub fn visible_pixels(&self, view: &View, camera: &Camera, instance: usize) -> usize {
        let object_from_camera = view.object_poses[instance].inverse();
        let width = camera.width as usize;
        view.frame
            .depth
            .iter()
            .zip(&view.frame.label)
            .enumerate()
            .filter(|(_, (z, l))| usize::from(**l) == instance + 1 && **z > 0.0)
            .filter(|(i, (z, _))| {
                let (u, v) = ((i % width) as f64 + 0.5, (i / width) as f64 + 0.5);
                let ray = camera.ray_direction(u, v);
                let point = Point3::from(ray * (f64::from(**z) / ray.z));
                self.contains(&object_from_camera.transform_point(&point))
            })
            .count()
    }
}

/// Whether the part must be seen or not.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PartVisibility {
    Hidden,
    Visible,
}

/// Views in which every instance of the part's object is at least
/// [`MIN_OBJECT_VISIB_FRACT`] visible and shows its part as `visibility`
/// says: hidden (≤ [`HIDDEN_MAX_PIXELS`]) or in view (≥ [`VISIBLE_MIN_PIXELS`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ViewCondition {
    pub part: ObjectPart,
    pub visibility: PartVisibility,
    /// Camera and light draws per image before the scene's arrangement is
    /// given up on ([`MAX_VIEW_ATTEMPTS`] unless a test wants fewer).
    pub view_attempts: usize,
}

impl ViewCondition {
    /// The condition with the default [`MAX_VIEW_ATTEMPTS`].
    pub fn new(part: ObjectPart, visibility: PartVisibility) -> Self {
        Self { part, visibility, view_attempts: MAX_VIEW_ATTEMPTS }
    }

    /// Whether `view` of `scene` meets the condition; false when the scene
    /// has no instance of the part's object.
    pub fn accepts(&self, scene: &Scene, view: &View, camera: &Camera) -> bool {
        let area_scale = f64::from(camera.width) * f64::from(camera.height) / (640.0 * 480.0);
        let mut instances = scene.objects.iter().enumerate().filter(|(_, o)| o.obj_id == self.part.obj_id).peekable();
        instances.peek().is_some()
            && instances.all(|(k, _)| {
                let all = view.silhouettes[k].iter().filter(|&&inside| inside).count();
                let visible = view.frame.label.iter().filter(|&&l| usize::from(l) == k + 1).count();
                if all == 0 || (visible as f64) < MIN_OBJECT_VISIB_FRACT * all as f64 {
                    return false;
                }
                let pixels = self.part.visible_pixels(view, camera, k) as f64;
                match self.visibility {
                    PartVisibility::Hidden => pixels <= HIDDEN_MAX_PIXELS * area_scale,
                    PartVisibility::Visible => pixels >= VISIBLE_MIN_PIXELS * area_scale,
                }
            })
    }
}

impl std::fmt::Display for ViewCondition {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let a = self.part.axis;
        write!(
            f,
            "object {} at least {:.0} % visible with its part ({:.2}, {:.2}, {:.2}) · x > {} m {}",
            self.part.obj_id,
            100.0 * MIN_OBJECT_VISIB_FRACT,
            a.x,
            a.y,
            a.z,
            self.part.beyond,
            match self.visibility {
                PartVisibility::Hidden => "hidden",
                PartVisibility::Visible => "in view",
            }
        )
    }
}
