//! Is a grasp antipodal and collision-free on an object? The one test the
//! grasp data, the valid shares the stage reports and the simulated
//! evaluation all use.

use nalgebra::{Isometry3, Point3, Vector3};
use parry3d::query::{PointQuery, Ray, RayCast, intersection_test};
use parry3d::shape::{FeatureId, TriMesh};

use crate::gripper::Gripper;

/// What closing the gripper on an object does.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum GraspOutcome {
    /// Antipodal and collision-free: the pads close to `width` (m), and the
    /// steeper contact normal is `margin` (radians) inside the friction
    /// cone: how much pose error the contacts tolerate before slipping.
    Holds { width: f32, margin: f32 },
    /// The open gripper (fingers at `max_opening`, palm) meets the object.
    Collides,
    /// Nothing lies between the pads on the contact line.
    Empty,
    /// A contact normal lies outside the friction cone of its finger.
    Slips,
}

impl GraspOutcome {
    pub fn holds(&self) -> bool {
        matches!(self, Self::Holds { .. })
    }
}

/// Closes `gripper` at `object_from_grasp` (grasp frame to object frame,
/// metres) on `mesh` (object frame; built by
/// [`poseflow_scene::oriented_trimesh`] so faces point outwards and the
/// inside of the object is known).
///
/// Collision: each gripper box, opened fully, must neither cross the
/// surface nor sit inside the object. Contacts: each finger moves along the
/// contact line until it meets the surface; the outward normal there must
/// face the finger within the friction cone (`atan(friction)`). Contacts on
/// the pad's centre line only: a grasp that holds on that line and whose
/// open fingers are clear of the object is antipodal in the usual sense.
pub fn check_grasp(mesh: &TriMesh, gripper: &Gripper, object_from_grasp: &Isometry3<f32>) -> GraspOutcome {
    for part in gripper.parts(gripper.max_opening) {
        let pose = object_from_grasp * part.pose;
        let crosses = intersection_test(&pose, &part.shape, &Isometry3::identity(), mesh).unwrap_or(true);
        if crosses || mesh.contains_local_point(&Point3::from(pose.translation.vector)) {
            return GraspOutcome::Collides;
        }
    }
    let half = gripper.max_opening / 2.0;
    let cone = gripper.friction_angle();
    let mut travel = 0.0;
    let mut steepest = 0.0f32;
    for side in [-1.0f32, 1.0] {
        // The finger on `side` closes towards the other one.
        let origin = object_from_grasp * Point3::new(side * half, 0.0, -gripper.contact_depth);
        let direction = object_from_grasp * Vector3::new(-side, 0.0, 0.0);
        let Some(hit) = mesh.cast_local_ray_and_get_normal(&Ray::new(origin, direction), gripper.max_opening, false)
        else {
            return GraspOutcome::Empty;
        };
        let Some(normal) = outward_normal(mesh, hit.feature) else {
            return GraspOutcome::Slips;
        };
        let angle = normal.dot(&-direction).clamp(-1.0, 1.0).acos();
        if angle > cone {
            return GraspOutcome::Slips;
        }
        steepest = steepest.max(angle);
        travel += hit.time_of_impact;
    }
    GraspOutcome::Holds { width: (gripper.max_opening - travel).max(0.0), margin: cone - steepest }
}

/// The outward normal of the triangle a ray hit (parry numbers back-face
/// hits after the triangles; the face's own winding gives the side).
fn outward_normal(mesh: &TriMesh, feature: FeatureId) -> Option<Vector3<f32>> {
    let FeatureId::Face(index) = feature else {
        return None;
    };
    let triangles = mesh.indices().len() as u32;
    mesh.triangle(index % triangles).normal().map(|n| n.into_inner())
}

#[cfg(test)]
pub(crate) mod tests {
    use nalgebra::{Translation3, UnitQuaternion};
    use poseflow_scene::oriented_trimesh;

    use super::*;

    /// A closed axis-aligned box centred at the origin.
    pub(crate) fn box_mesh(half: [f32; 3]) -> TriMesh {
        let [x, y, z] = half;
        let vertices = (0..8)
            .map(|i| {
                let s = |bit: u32| if i & (1 << bit) != 0 { 1.0 } else { -1.0 };
                Point3::new(s(0) * x, s(1) * y, s(2) * z)
            })
            .collect();
        let quads = [[0, 2, 6, 4], [1, 5, 7, 3], [0, 4, 5, 1], [2, 3, 7, 6], [0, 1, 3, 2], [4, 6, 7, 5]];
        let triangles = quads.iter().flat_map(|[a, b, c, d]| [[*a, *b, *c], [*a, *c, *d]]).collect();
        oriented_trimesh(vertices, triangles).unwrap()
    }

    /// A grasp from above (grasp z = object −z), closing along object x
    /// (tilted by `tilt` about y), contact line at height `height`.
    fn top_grasp(gripper: &Gripper, height: f32, tilt: f32) -> Isometry3<f32> {
        let down = UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f32::consts::PI);
        let tilted = UnitQuaternion::from_axis_angle(&Vector3::y_axis(), tilt) * down;
        let origin = Vector3::new(0.0, 0.0, height) + tilted * Vector3::new(0.0, 0.0, gripper.contact_depth);
        Isometry3::from_parts(Translation3::from(origin), tilted)
    }

    #[test]
    fn a_box_narrower_than_the_stroke_is_held_across_its_width() {
        let gripper = Gripper::default();
        let mesh = box_mesh([0.02, 0.02, 0.05]);
        // Contact line 2 cm below the top face: fingertips 1 cm below it.
        let outcome = check_grasp(&mesh, &gripper, &top_grasp(&gripper, 0.03, 0.0));
        let GraspOutcome::Holds { width, margin } = outcome else { panic!("{outcome:?}") };
        assert!((width - 0.04).abs() < 1e-5, "{width}");
        // Both pads meet their faces square on: the whole cone is margin.
        assert!((margin - gripper.friction_angle()).abs() < 1e-3, "{margin}");
    }

    #[test]
    fn a_box_wider_than_the_stroke_collides() {
        let mesh = box_mesh([0.05, 0.02, 0.05]);
        let gripper = Gripper::default();
        assert_eq!(check_grasp(&mesh, &gripper, &top_grasp(&gripper, 0.03, 0.0)), GraspOutcome::Collides);
    }

    #[test]
    fn a_gripper_that_sinks_into_the_object_collides_and_one_above_it_grasps_air() {
        let gripper = Gripper::default();
        let mesh = box_mesh([0.02, 0.02, 0.05]);
        // The palm's front face 1 cm under the top face.
        let sunk = top_grasp(&gripper, 0.05 - gripper.finger[2] + gripper.contact_depth - 0.01, 0.0);
        assert_eq!(check_grasp(&mesh, &gripper, &sunk), GraspOutcome::Collides);
        assert_eq!(check_grasp(&mesh, &gripper, &top_grasp(&gripper, 0.08, 0.0)), GraspOutcome::Empty);
    }

    #[test]
    fn the_friction_cone_decides_how_far_the_closing_axis_may_tilt() {
        let gripper = Gripper::default();
        // Thin enough that the tilted fingers and palm stay clear of it.
        let mesh = box_mesh([0.01, 0.02, 0.05]);
        // Tilting about y turns the closing axis away from the face normals
        // (±x) by the tilt: inside the 26.6° cone it holds, outside it slips.
        let holds = check_grasp(&mesh, &gripper, &top_grasp(&gripper, 0.035, 20f32.to_radians()));
        let GraspOutcome::Holds { margin, .. } = holds else { panic!("{holds:?}") };
        // 0.5 friction: a 26.57° cone, 6.57° of it left after the tilt.
        assert!((margin.to_degrees() - (0.5f32.atan().to_degrees() - 20.0)).abs() < 0.01, "{}", margin.to_degrees());
        let slips = check_grasp(&mesh, &gripper, &top_grasp(&gripper, 0.035, 30f32.to_radians()));
        assert_eq!(slips, GraspOutcome::Slips);
    }

    #[test]
    fn inward_wound_faces_give_the_same_answer() {
        let gripper = Gripper::default();
        let outward = box_mesh([0.02, 0.02, 0.05]);
        let flipped: Vec<[u32; 3]> = outward.indices().iter().map(|[a, b, c]| [*a, *c, *b]).collect();
        let inward = oriented_trimesh(outward.vertices().to_vec(), flipped).unwrap();
        let grasp = top_grasp(&gripper, 0.03, 0.0);
        assert_eq!(check_grasp(&inward, &gripper, &grasp), check_grasp(&outward, &gripper, &grasp));
    }
}
