//! One object's grasp data as the training code reads it (JSON).

use nalgebra::Isometry3;
use serde::{Deserialize, Serialize};

use crate::gripper::Gripper;
use crate::sample::ObjectGrasp;

/// Grasps that hold on one object, the gripper they were checked with and
/// the object's surface cloud (object frame, metres).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GraspSet {
    pub obj_id: u32,
    pub gripper: Gripper,
    /// Antipodal proposals made to find these grasps.
    pub proposals: usize,
    /// Grasp frame to object frame: `R` row-major (9), then `t` (3).
    pub grasps: Vec<[f32; 12]>,
    /// Width each grasp closes to (m).
    pub widths: Vec<f32>,
    /// Surface points, uniform by area.
    pub cloud: Vec<[f32; 3]>,
}

/// `R` row-major then `t`: the layout of every pose in the contracts.
pub fn row_major(pose: &Isometry3<f32>) -> [f32; 12] {
    let r = pose.rotation.to_rotation_matrix();
    let m = r.matrix();
    let t = pose.translation.vector;
    [m[(0, 0)], m[(0, 1)], m[(0, 2)], m[(1, 0)], m[(1, 1)], m[(1, 2)], m[(2, 0)], m[(2, 1)], m[(2, 2)], t.x, t.y, t.z]
}

impl GraspSet {
    pub fn new(obj_id: u32, gripper: Gripper, proposals: usize, grasps: &[ObjectGrasp], cloud: Vec<[f32; 3]>) -> Self {
        Self {
            obj_id,
            gripper,
            proposals,
            grasps: grasps.iter().map(|g| row_major(&g.object_from_grasp)).collect(),
            widths: grasps.iter().map(|g| g.width).collect(),
            cloud,
        }
    }
}

#[cfg(test)]
mod tests {
    use nalgebra::{Translation3, UnitQuaternion, Vector3};

    use super::*;

    #[test]
    fn poses_are_written_rotation_row_major_then_translation() {
        let rotation = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), std::f32::consts::FRAC_PI_2);
        let pose = Isometry3::from_parts(Translation3::new(1.0, 2.0, 3.0), rotation);
        let values = row_major(&pose);
        // A quarter turn about z maps x to y: first column (0, 1, 0).
        let expected = [0.0, -1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 1.0, 2.0, 3.0];
        assert!(values.iter().zip(expected).all(|(a, b)| (a - b).abs() < 1e-6), "{values:?}");
    }

    #[test]
    fn a_grasp_set_round_trips_through_json() {
        let grasp = ObjectGrasp { object_from_grasp: Isometry3::translation(0.0, 0.0, 0.1), width: 0.03 };
        let set = GraspSet::new(14, Gripper::default(), 7, &[grasp], vec![[0.0, 0.01, 0.02]]);
        let text = serde_json::to_string(&set).unwrap();
        assert_eq!(serde_json::from_str::<GraspSet>(&text).unwrap(), set);
        let unknown = text.replacen("\"proposals\"", "\"proposal\"", 1);
        assert!(serde_json::from_str::<GraspSet>(&unknown).unwrap_err().to_string().contains("proposal"));
    }
}
