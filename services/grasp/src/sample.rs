//! Grasp data: antipodal proposals on an object mesh, each kept only when
//! [`check_grasp`] says it holds, and the object's surface cloud.

use nalgebra::{Isometry3, Matrix3, Point3, Rotation3, Translation3, UnitQuaternion, Vector3};
use parry3d::query::{Ray, RayCast};
use parry3d::shape::TriMesh;
use poseflow_scene::surface_points;
use rand::Rng;

use crate::check::{GraspOutcome, check_grasp};
use crate::gripper::Gripper;

/// A grasp on an object: grasp frame to object frame, and the width the
/// pads close to (m).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ObjectGrasp {
    pub object_from_grasp: Isometry3<f32>,
    pub width: f32,
}

/// A unit vector within `half_angle` of `axis`, uniform on that cap.
fn within_cone<R: Rng + ?Sized>(axis: &Vector3<f32>, half_angle: f32, rng: &mut R) -> Vector3<f32> {
    let cos_theta = 1.0 - rng.random::<f32>() * (1.0 - half_angle.cos());
    let sin_theta = (1.0 - cos_theta * cos_theta).max(0.0).sqrt();
    let phi = rng.random::<f32>() * std::f32::consts::TAU;
    let (u, v) = perpendiculars(axis);
    axis * cos_theta + (u * phi.cos() + v * phi.sin()) * sin_theta
}

/// Two unit vectors completing `axis` (unit) to a right-handed basis.
fn perpendiculars(axis: &Vector3<f32>) -> (Vector3<f32>, Vector3<f32>) {
    let helper = if axis.x.abs() < 0.9 { Vector3::x() } else { Vector3::y() };
    let u = axis.cross(&helper).normalize();
    (u, axis.cross(&u))
}

/// One antipodal proposal from a surface point: a closing direction inside
/// the friction cone there, through the object to where it leaves it, a
/// random approach direction about that axis, the contact line through the
/// middle of the two contacts. `None` when the object is too wide there.
fn propose<R: Rng + ?Sized>(
    mesh: &TriMesh,
    gripper: &Gripper,
    (entry, normal): (Point3<f32>, Vector3<f32>),
    rng: &mut R,
) -> Option<Isometry3<f32>> {
    let closing = within_cone(&-normal, gripper.friction_angle(), rng);
    let start = entry + closing * 1e-4;
    let exit = mesh.cast_local_ray(&Ray::new(start, closing), gripper.max_opening, false)?;
    let centre = start + closing * exit / 2.0;
    let (u, v) = perpendiculars(&closing);
    let angle = rng.random::<f32>() * std::f32::consts::TAU;
    let approach = u * angle.cos() + v * angle.sin();
    let rotation =
        Rotation3::from_matrix_unchecked(Matrix3::from_columns(&[closing, approach.cross(&closing), approach]));
    let origin = centre + approach * gripper.contact_depth;
    Some(Isometry3::from_parts(Translation3::from(origin.coords), UnitQuaternion::from_rotation_matrix(&rotation)))
}

/// What [`sample_grasps`] found.
#[derive(Debug, Clone, PartialEq)]
pub struct SampledGrasps {
    pub grasps: Vec<ObjectGrasp>,
    /// Proposals made (each from a fresh surface point).
    pub proposals: usize,
}

/// Up to `wanted` grasps that hold on `mesh`, from at most `max_proposals`
/// antipodal proposals.
pub fn sample_grasps<R: Rng + ?Sized>(
    mesh: &TriMesh,
    gripper: &Gripper,
    wanted: usize,
    max_proposals: usize,
    rng: &mut R,
) -> SampledGrasps {
    let mut grasps = Vec::with_capacity(wanted);
    let mut proposals = 0;
    while grasps.len() < wanted && proposals < max_proposals {
        proposals += 1;
        let surface = surface_points(mesh, 1, rng)[0];
        let Some(object_from_grasp) = propose(mesh, gripper, surface, rng) else {
            continue;
        };
        if let GraspOutcome::Holds { width, .. } = check_grasp(mesh, gripper, &object_from_grasp) {
            grasps.push(ObjectGrasp { object_from_grasp, width });
        }
    }
    SampledGrasps { grasps, proposals }
}

#[cfg(test)]
mod tests {
    use poseflow_geometry::sampling::seeded_rng;

    use super::*;
    use crate::check::tests::box_mesh;

    #[test]
    fn surface_points_lie_on_the_faces_in_proportion_to_their_area() {
        let mesh = box_mesh([0.01, 0.02, 0.04]);
        let points = surface_points(&mesh, 4000, &mut seeded_rng(1));
        let on_z_faces = points.iter().filter(|(p, _)| (p.z.abs() - 0.04).abs() < 1e-6).count();
        for (p, n) in &points {
            // On the surface, with the normal of the face it lies on.
            let face = [p.x.abs() / 0.01, p.y.abs() / 0.02, p.z.abs() / 0.04];
            let axis = (0..3).max_by(|&a, &b| face[a].total_cmp(&face[b])).unwrap();
            assert!((face[axis] - 1.0).abs() < 1e-5, "{p}");
            assert!((n[axis] - p[axis].signum()).abs() < 1e-5, "{p} {n}");
        }
        // The z faces are 2·(0.02·0.04) of 2·(0.02·0.04 + 0.02·0.08 + 0.04·0.08) = 1/7 of the area.
        let share = on_z_faces as f64 / points.len() as f64;
        assert!((share - 1.0 / 7.0).abs() < 0.02, "{share}");
    }

    #[test]
    fn every_sampled_grasp_holds_and_closes_to_the_width_it_grips() {
        let gripper = Gripper::default();
        // 2 × 6 × 12 cm: only the 2 cm and 6 cm directions fit the 8 cm stroke.
        let mesh = box_mesh([0.01, 0.03, 0.06]);
        let sampled = sample_grasps(&mesh, &gripper, 200, 20_000, &mut seeded_rng(2));
        assert_eq!(sampled.grasps.len(), 200, "after {} proposals", sampled.proposals);
        for grasp in &sampled.grasps {
            assert!(check_grasp(&mesh, &gripper, &grasp.object_from_grasp).holds());
            // Across a face pair within the friction cone: between the box's
            // thickness and the thickness over cos(cone).
            let closing = grasp.object_from_grasp.rotation * Vector3::x();
            let axis = (0..3).max_by(|&a, &b| closing[a].abs().total_cmp(&closing[b].abs())).unwrap();
            assert!(axis < 2, "no grasp fits across the 12 cm length: {closing}");
            let thickness = [0.02, 0.06][axis];
            assert!(grasp.width >= thickness - 1e-4 && grasp.width <= thickness / 0.89 + 1e-4, "{}", grasp.width);
        }
    }

    #[test]
    fn an_object_wider_than_the_stroke_everywhere_has_no_grasp() {
        let mesh = box_mesh([0.05, 0.05, 0.05]);
        let sampled = sample_grasps(&mesh, &Gripper::default(), 10, 2000, &mut seeded_rng(3));
        assert!(sampled.grasps.is_empty());
        assert_eq!(sampled.proposals, 2000);
    }
}
