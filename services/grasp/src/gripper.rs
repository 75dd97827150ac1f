//! The parallel-jaw gripper: its shape and the grasp frame.
//!
//! Grasp frame (the Grasps contract): origin midway between the fingertips,
//! z along the approach direction (from the hand towards the object), x
//! along the closing direction, y = z × x. The fingers are boxes whose tips
//! lie in the plane z = 0 and whose inner faces are `opening / 2` either
//! side of the origin along x; the palm is a box behind them. Contacts are
//! made on the line y = 0, z = -`contact_depth` (the middle of the finger
//! pads). Metres.

use nalgebra::{Isometry3, Translation3, Vector3};
use parry3d::shape::Cuboid;
use serde::{Deserialize, Serialize};

/// A parallel-jaw gripper shaped like the Franka Panda hand (defaults:
/// 8 cm stroke, 2 cm wide fingers 4.5 cm long, a 20 × 6 × 6 cm hand).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Gripper {
    /// Largest distance between the finger pads (m).
    pub max_opening: f32,
    /// One finger's size along x (thickness), y (width), z (length) (m).
    pub finger: [f32; 3],
    /// The hand's size along x, y, z (m), behind the fingers.
    pub palm: [f32; 3],
    /// How far behind the fingertips the contact line lies (m).
    pub contact_depth: f32,
    /// Coulomb friction coefficient: a contact holds when the surface
    /// normal is within `atan(friction)` of the closing axis.
    pub friction: f32,
}

impl Default for Gripper {
    fn default() -> Self {
        Self {
            max_opening: 0.08,
            finger: [0.01, 0.02, 0.045],
            palm: [0.2, 0.06, 0.06],
            contact_depth: 0.01,
            friction: 0.5,
        }
    }
}

/// A box of the gripper: its half-extents and pose in the grasp frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GripperPart {
    pub shape: Cuboid,
    pub pose: Isometry3<f32>,
}

/// A gripper whose sizes cannot describe a real one.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum GripperError {
    #[error("gripper `{key}`: expected a positive size, found {value}")]
    NotPositive { key: &'static str, value: f32 },
    #[error("gripper `contact_depth` {depth}: expected less than the finger length {finger_length}")]
    ContactBeyondFinger { depth: f32, finger_length: f32 },
}

impl Gripper {
    /// Checks that every size is positive and the contact line lies on the
    /// finger pads.
    pub fn validate(&self) -> Result<(), GripperError> {
        let sizes =
            [("max_opening", self.max_opening), ("contact_depth", self.contact_depth), ("friction", self.friction)];
        let boxes = self.finger.iter().chain(&self.palm).map(|&v| ("finger/palm", v));
        if let Some((key, value)) = sizes.into_iter().chain(boxes).find(|(_, v)| !(v.is_finite() && *v > 0.0)) {
            return Err(GripperError::NotPositive { key, value });
        }
        if self.contact_depth >= self.finger[2] {
            return Err(GripperError::ContactBeyondFinger { depth: self.contact_depth, finger_length: self.finger[2] });
        }
        Ok(())
    }

    /// Half-angle of the friction cone (radians).
    pub fn friction_angle(&self) -> f32 {
        self.friction.atan()
    }

    /// The two fingers (opened to `opening`) and the palm, grasp frame.
    pub fn parts(&self, opening: f32) -> [GripperPart; 3] {
        let [fx, fy, fz] = self.finger;
        let finger = |side: f32| GripperPart {
            shape: Cuboid::new(Vector3::new(fx, fy, fz) / 2.0),
            pose: Translation3::new(side * (opening + fx) / 2.0, 0.0, -fz / 2.0).into(),
        };
        let [px, py, pz] = self.palm;
        let palm = GripperPart {
            shape: Cuboid::new(Vector3::new(px, py, pz) / 2.0),
            pose: Translation3::new(0.0, 0.0, -fz - pz / 2.0).into(),
        };
        [finger(-1.0), finger(1.0), palm]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_fingers_frame_the_opening_and_the_palm_sits_behind_them() {
        let gripper = Gripper::default();
        let [left, right, palm] = gripper.parts(0.08);
        // Inner faces at ±4 cm, tips at z = 0.
        assert!((left.pose.translation.x + left.shape.half_extents.x + 0.04).abs() < 1e-6);
        assert!((right.pose.translation.x - right.shape.half_extents.x - 0.04).abs() < 1e-6);
        assert!((left.pose.translation.z + left.shape.half_extents.z).abs() < 1e-6);
        // The palm's front face is where the fingers end.
        assert!((palm.pose.translation.z + palm.shape.half_extents.z + gripper.finger[2]).abs() < 1e-6);
        assert!(gripper.validate().is_ok());
    }

    #[test]
    fn bad_sizes_are_named() {
        let bad = Gripper { max_opening: -0.01, ..Gripper::default() };
        assert_eq!(bad.validate(), Err(GripperError::NotPositive { key: "max_opening", value: -0.01 }));
        let deep = Gripper { contact_depth: 0.05, ..Gripper::default() };
        let err = deep.validate().unwrap_err();
        assert!(matches!(err, GripperError::ContactBeyondFinger { .. }), "{err}");
        assert!(err.to_string().contains("contact_depth"), "{err}");
    }
}
