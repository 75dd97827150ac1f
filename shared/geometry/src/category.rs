//! Category-level pose metrics as REAL275 (NOCS) reports them: rotation
//! and translation errors with the rotation about a symmetry axis ignored,
//! and the 3D IoU of the predicted and true bounding boxes.
//!
//! Conventions: poses are `camera_from_object` in metres; the object frame
//! is the category's canonical frame (y up the symmetry axis, the bounding
//! box centred on the origin); sizes are the box's extents along the
//! object's x, y, z in metres; angles in degrees.

use nalgebra::{Point3, Rotation3, Unit, Vector3};

use crate::Pose;

/// The canonical frame's symmetry axis: object y.
pub fn symmetry_axis() -> Unit<Vector3<f64>> {
    Vector3::y_axis()
}

/// Rotation error in degrees. With `about_axis_ignored` (bottles, bowls,
/// cans, and mugs whose handle is hidden) only where the y axis points
/// counts: the angle between the two poses' images of object y. Otherwise
/// the full geodesic angle.
pub fn rotation_error_deg(estimate: &Pose, truth: &Pose, about_axis_ignored: bool) -> f64 {
    if about_axis_ignored {
        let a = estimate.rotation * symmetry_axis().into_inner();
        let b = truth.rotation * symmetry_axis().into_inner();
        // atan2 of sine and cosine: acos loses precision near 0°.
        a.cross(&b).norm().atan2(a.dot(&b)).to_degrees()
    } else {
        (estimate.rotation.inverse() * truth.rotation).angle().to_degrees()
    }
}

/// How widely `samples` spread in their turn about the canonical y axis
/// relative to `reference`: the circular standard deviation, in degrees,
/// of each sample's twist about y (the swing–twist split of `Rᵣᵀ Rₛ`).
/// A few degrees for a peaked distribution; about 113° for 50 samples
/// drawn uniformly around the axis, as an axis-symmetric object (or a mug
/// whose handle is hidden) should give; at most 180°. None for fewer than
/// two samples.
pub fn axis_spread_deg(reference: &Rotation3<f64>, samples: &[Rotation3<f64>]) -> Option<f64> {
    if samples.len() < 2 {
        return None;
    }
    let (mut cos_sum, mut sin_sum) = (0.0, 0.0);
    for sample in samples {
        // The twist about y of q = (w, x, y, z) is 2·atan2(y, w).
        let relative = nalgebra::UnitQuaternion::from_rotation_matrix(&(reference.inverse() * sample));
        let twist = 2.0 * relative.j.atan2(relative.w);
        cos_sum += twist.cos();
        sin_sum += twist.sin();
    }
    let resultant = (cos_sum.hypot(sin_sum) / samples.len() as f64).clamp(1e-12, 1.0);
    // Capped: past a half turn the figure only says "all around".
    Some((-2.0 * resultant.ln()).sqrt().to_degrees().min(180.0))
}

/// Translation error in centimetres.
pub fn translation_error_cm(estimate: &Pose, truth: &Pose) -> f64 {
    (estimate.translation - truth.translation).norm() * 100.0
}

/// A box of extents `size` centred on the origin of its object frame,
/// placed by `pose`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PlacedBox {
    pub pose: Pose,
    /// Extents along object x, y, z, metres (each > 0).
    pub size: Vector3<f64>,
}

impl PlacedBox {
    pub fn volume(&self) -> f64 {
        self.size.x * self.size.y * self.size.z
    }

    /// Whether a point of this box's own frame lies in it.
    fn contains(&self, local: &Point3<f64>) -> bool {
        (0..3).all(|i| local[i].abs() <= 0.5 * self.size[i])
    }
}

/// Grid cells per box side when [`box_iou`] measures an overlap: 40³
/// cell centres put the overlap's volume within about 1 % of its share of
/// the box (measured against closed forms in the tests).
pub const IOU_GRID: usize = 40;

/// Intersection over union of two oriented boxes. The overlap is measured
/// by counting which of a regular `grid`³ lattice of cell centres of the
/// smaller box lie in the other (exact as `grid` grows; boxes in any
/// orientation, where NOCS's own code compares axis-aligned hulls).
pub fn box_iou(a: &PlacedBox, b: &PlacedBox, grid: usize) -> f64 {
    let (small, large) = if a.volume() <= b.volume() { (a, b) } else { (b, a) };
    if small.volume() <= 0.0 || grid == 0 {
        return 0.0;
    }
    let small_to_large = large.pose.inverse() * small.pose;
    let mut inside = 0usize;
    for i in 0..grid {
        for j in 0..grid {
            for k in 0..grid {
                let cell = |n: usize, extent: f64| ((n as f64 + 0.5) / grid as f64 - 0.5) * extent;
                let local = Point3::new(cell(i, small.size.x), cell(j, small.size.y), cell(k, small.size.z));
                if large.contains(&small_to_large.transform_point(&local)) {
                    inside += 1;
                }
            }
        }
    }
    let intersection = small.volume() * inside as f64 / (grid * grid * grid) as f64;
    intersection / (a.volume() + b.volume() - intersection)
}

/// Turns about y tried by [`category_iou`] for an object whose turn about
/// its axis is unknowable: every 5° of a quarter turn.
pub const AXIS_TURNS: usize = 18;

/// REAL275's 3D IoU: with `about_axis_ignored`, the best over turns of the
/// estimate's box about its y axis (its turn about the axis is not
/// scored); otherwise the boxes as placed.
pub fn category_iou(estimate: &PlacedBox, truth: &PlacedBox, about_axis_ignored: bool) -> f64 {
    if !about_axis_ignored {
        return box_iou(estimate, truth, IOU_GRID);
    }
    (0..AXIS_TURNS)
        .map(|k| {
            let turn = Rotation3::from_axis_angle(
                &symmetry_axis(),
                std::f64::consts::FRAC_PI_2 * k as f64 / AXIS_TURNS as f64,
            );
            let turned =
                PlacedBox { pose: Pose::new(estimate.pose.rotation * turn, estimate.pose.translation), ..*estimate };
            box_iou(&turned, truth, IOU_GRID)
        })
        .fold(0.0, f64::max)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn axis_spread_is_the_circular_deviation_of_the_twist_about_y() {
        let about_y = |deg: f64| Rotation3::from_axis_angle(&Vector3::y_axis(), deg.to_radians());
        let reference = Rotation3::from_euler_angles(0.4, -1.1, 2.0);
        let turned = |deg: f64| reference * about_y(deg);
        // Two samples at ±10°: mean resultant cos 10°, deviation √(−2 ln cos 10°).
        let two = axis_spread_deg(&reference, &[turned(10.0), turned(-10.0)]).unwrap();
        let expected = (-2.0 * 10f64.to_radians().cos().ln()).sqrt().to_degrees();
        assert!((two - expected).abs() < 1e-9, "{two} against {expected}");
        // The same turn for all: none; a tilt across the axis is not a twist.
        let tilt = Rotation3::from_axis_angle(&Vector3::x_axis(), 0.3);
        let same = axis_spread_deg(&reference, &[turned(30.0), turned(30.0) * tilt]).unwrap();
        assert!(same < 1e-6, "{same}");
        // Evenly around the axis: the resultant vanishes, the deviation is large.
        let even: Vec<_> = (0..50).map(|k| turned(7.2 * k as f64)).collect();
        assert_eq!(axis_spread_deg(&reference, &even), Some(180.0));
        assert_eq!(axis_spread_deg(&reference, &even[..1]), None);
    }
    use proptest::prelude::*;

    fn placed(rotation: Rotation3<f64>, translation: [f64; 3], size: [f64; 3]) -> PlacedBox {
        PlacedBox { pose: Pose::new(rotation, Vector3::from(translation)), size: Vector3::from(size) }
    }

    #[test]
    fn shifted_boxes_overlap_by_their_shared_slab() {
        // Two 10 cm cubes 5 cm apart along x share half of each: IoU = 0.5 / 1.5.
        let a = placed(Rotation3::identity(), [0.0, 0.0, 0.5], [0.1, 0.1, 0.1]);
        let b = placed(Rotation3::identity(), [0.05, 0.0, 0.5], [0.1, 0.1, 0.1]);
        assert!((box_iou(&a, &b, IOU_GRID) - 1.0 / 3.0).abs() < 0.01);
        // A box inside another: the volume ratio.
        let inner = placed(Rotation3::identity(), [0.0, 0.0, 0.5], [0.05, 0.1, 0.1]);
        assert!((box_iou(&a, &inner, IOU_GRID) - 0.5).abs() < 1e-9);
        // Apart: nothing.
        let far = placed(Rotation3::identity(), [0.3, 0.0, 0.5], [0.1, 0.1, 0.1]);
        assert_eq!(box_iou(&a, &far, IOU_GRID), 0.0);
    }

    #[test]
    fn a_square_turned_by_45_degrees_overlaps_as_the_octagon() {
        // Unit squares (x–z) sharing a centre, one turned 45° about y: their
        // overlap is the regular octagon of inradius 1/2, area 2(√2 − 1).
        let a = placed(Rotation3::identity(), [0.0, 0.0, 1.0], [1.0, 0.2, 1.0]);
        let b = placed(
            Rotation3::from_axis_angle(&Vector3::y_axis(), 45f64.to_radians()),
            [0.0, 0.0, 1.0],
            [1.0, 0.2, 1.0],
        );
        let octagon = 2.0 * (2f64.sqrt() - 1.0);
        let expected = octagon / (2.0 - octagon);
        assert!((box_iou(&a, &b, IOU_GRID) - expected).abs() < 0.01, "{}", box_iou(&a, &b, IOU_GRID));
        // Ignoring the turn about y, the best turn finds the square again.
        assert!((category_iou(&a, &b, true) - 1.0).abs() < 1e-9);
        assert!(category_iou(&a, &b, false) < 0.9);
    }

    #[test]
    fn the_axis_error_ignores_turns_about_y_only() {
        let truth = Pose::new(Rotation3::from_euler_angles(0.3, -0.2, 1.0), Vector3::new(0.0, 0.0, 0.6));
        let about_y =
            Pose::new(truth.rotation * Rotation3::from_axis_angle(&Vector3::y_axis(), 2.0), truth.translation);
        assert!(rotation_error_deg(&about_y, &truth, true) < 1e-6);
        assert!((rotation_error_deg(&about_y, &truth, false) - 2f64.to_degrees()).abs() < 1e-6);
        // A tilt of the axis by 20° counts in full either way.
        let tilted = Pose::new(
            truth.rotation * Rotation3::from_axis_angle(&Vector3::x_axis(), 20f64.to_radians()),
            truth.translation,
        );
        assert!((rotation_error_deg(&tilted, &truth, true) - 20.0).abs() < 1e-6);
        assert!((rotation_error_deg(&tilted, &truth, false) - 20.0).abs() < 1e-6);
        let moved = Pose::new(truth.rotation, truth.translation + Vector3::new(0.03, 0.04, 0.0));
        assert!((translation_error_cm(&moved, &truth) - 5.0).abs() < 1e-9);
    }

    proptest! {
        #[test]
        fn iou_is_symmetric_bounded_and_one_for_the_same_box(
            rx in -3.0f64..3.0, ry in -3.0f64..3.0, rz in -3.0f64..3.0,
            dx in -0.1f64..0.1, dz in -0.1f64..0.1,
            sx in 0.02f64..0.3, sy in 0.02f64..0.3, sz in 0.02f64..0.3,
        ) {
            let a = placed(Rotation3::from_euler_angles(rx, ry, rz), [0.0, 0.0, 0.8], [sx, sy, sz]);
            let b = placed(Rotation3::from_euler_angles(ry, rz, rx), [dx, 0.0, 0.8 + dz], [sy, sz, 0.7 * sx]);
            prop_assert!((box_iou(&a, &a, 10) - 1.0).abs() < 1e-9);
            let (ab, ba) = (box_iou(&a, &b, 10), box_iou(&b, &a, 10));
            prop_assert!((0.0..=1.0).contains(&ab));
            prop_assert!((ab - ba).abs() < 1e-12);
            // Ignoring the turn about y never scores worse than the box as placed.
            prop_assert!(category_iou(&a, &b, true) + 1e-12 >= category_iou(&a, &b, false));
        }
    }
}
