//! Estimates as ROS 2 messages: the selected pose with a covariance, and
//! the kept hypotheses.
//!
//! Frames (REP 103/105): every pose is the object's pose in the camera's
//! *optical* frame (x right, y down, z forward, the frame of PoseFlow's
//! camera model), so `frame_id` should name that frame, e.g.
//! `camera_color_optical_frame` for a RealSense driver; tf2 then carries it
//! to `base_link` or `map`.

use poseflow_contracts::{EstimateHeader, StampSlot, flags};
use poseflow_geometry::nalgebra::{Matrix6, Vector6};
use poseflow_geometry::{Pose, so3};

use crate::msgs::{PoseArray, PoseWithCovarianceStamped, RosHeader, RosPose, Time};

#[derive(Debug, thiserror::Error)]
pub enum PoseError {
    #[error("estimate of frame {frame} object {object}: {detail}")]
    Estimate { frame: u64, object: u32, detail: String },
}

/// What one Estimate becomes on ROS 2.
#[derive(Debug, Clone, PartialEq)]
pub struct PoseMessages {
    /// The selected pose and the covariance of the kept hypotheses about it.
    pub pose: PoseWithCovarianceStamped,
    /// The kept hypotheses, best first.
    pub hypotheses: PoseArray,
}

/// A pose as `geometry_msgs/Pose`: position in metres, orientation as a
/// unit quaternion `x, y, z, w` with `w ≥ 0`.
pub fn ros_pose(pose: &Pose) -> RosPose {
    let q = so3::quaternion_from_matrix(pose.rotation.matrix());
    let sign = if q.w < 0.0 { -1.0 } else { 1.0 };
    RosPose { position: pose.translation.into(), orientation: [sign * q.i, sign * q.j, sign * q.k, sign * q.w] }
}

/// The covariance ROS expects of a `PoseWithCovariance` at `at`: the
/// second moment of `[tᵢ − t; log(Rᵢ Rᵀ)]` over `samples`, 6×6 row-major,
/// rows `x, y, z` (m) then rotations about the parent frame's fixed
/// `X, Y, Z` axes (rad).
///
/// About the published pose, not the samples' own mean, so a selected
/// pose off the centre of its hypotheses reports that offset as
/// uncertainty; and in the fixed (camera) frame, where PoseFlow's own
/// covariances perturb rotations in the body frame. With fewer than two
/// samples nothing is known about the spread: element 0 is −1, the ROS
/// convention for an unknown covariance.
pub fn ros_covariance(at: &Pose, samples: &[Pose]) -> [f64; 36] {
    if samples.len() < 2 {
        let mut unknown = [0.0; 36];
        unknown[0] = -1.0;
        return unknown;
    }
    let inverse = at.rotation.inverse();
    let mut moment = Matrix6::zeros();
    for sample in samples {
        let dt = sample.translation - at.translation;
        let dr = so3::log(&(sample.rotation * inverse));
        let xi = Vector6::new(dt.x, dt.y, dt.z, dr.x, dr.y, dr.z);
        moment += xi * xi.transpose();
    }
    moment /= samples.len() as f64;
    std::array::from_fn(|i| moment[(i / 6, i % 6)])
}

/// The ROS 2 messages of one Estimate. Stamped with the frame's `Source`
/// stamp, the time its image was captured (a ROS 2 camera's own stamp);
/// `now_ns` when the frame carries none.
pub fn pose_messages(
    header: &EstimateHeader,
    payload: &[f32],
    frame_id: &str,
    now_ns: u64,
) -> Result<PoseMessages, PoseError> {
    let error =
        |detail: String| PoseError::Estimate { frame: header.header.frame_id, object: header.header.object_id, detail };
    let best = Pose::from_f32_row_major(&header.best).map_err(|err| error(format!("best: {err}")))?;
    let kept: Vec<Pose> = header
        .kept_poses(payload)
        .map_err(|err| error(err.to_string()))?
        .enumerate()
        .map(|(i, values)| Pose::from_f32_row_major(values).map_err(|err| error(format!("hypothesis {i}: {err}"))))
        .collect::<Result<_, _>>()?;
    let stamp = Time::from_ns(header.header.stamps.get(StampSlot::Source).unwrap_or(now_ns));
    let ros_header = RosHeader { stamp, frame_id: frame_id.to_string() };
    Ok(PoseMessages {
        pose: PoseWithCovarianceStamped {
            header: ros_header.clone(),
            pose: ros_pose(&best),
            covariance: ros_covariance(&best, &kept),
        },
        hypotheses: PoseArray { header: ros_header, poses: kept.iter().map(ros_pose).collect() },
    })
}

/// Whether the selector declared the estimate's object lost.
pub fn is_lost(header: &EstimateHeader) -> bool {
    header.header.has_flag(flags::LOST)
}

#[cfg(test)]
mod tests {
    use poseflow_contracts::{SelectionMethod, WEIGHTED_POSE_LEN};
    use poseflow_geometry::nalgebra::{Rotation3, Vector3};

    use super::*;

    fn pose(axis_angle: [f64; 3], t: [f64; 3]) -> Pose {
        Pose::new(Rotation3::new(Vector3::from(axis_angle)), Vector3::from(t))
    }

    #[test]
    fn quaternions_are_the_rotation_with_a_non_negative_w() {
        let p = pose([0.0, 0.0, std::f64::consts::FRAC_PI_2], [0.1, 0.2, 0.3]);
        let q = ros_pose(&p);
        let h = std::f64::consts::FRAC_1_SQRT_2;
        for (a, b) in q.orientation.iter().zip([0.0, 0.0, h, h]) {
            assert!((a - b).abs() < 1e-12, "{:?}", q.orientation);
        }
        assert_eq!(q.position, [0.1, 0.2, 0.3]);
        // 350° about x is −10°: w stays positive.
        let q = ros_pose(&pose([350f64.to_radians(), 0.0, 0.0], [0.0; 3]));
        assert!(q.orientation[3] > 0.0 && q.orientation[0] < 0.0, "{:?}", q.orientation);
    }

    /// Two samples ±a about the camera's z axis and ±d along x: the closed
    /// form is a², d² on the diagonal, and the rotation rows are about the
    /// fixed axes even when the published pose itself is rotated.
    #[test]
    fn the_covariance_is_the_closed_form_in_the_fixed_frame() {
        let (a, d) = (0.1, 0.02);
        let at = pose([std::f64::consts::FRAC_PI_2, 0.0, 0.0], [0.0, 0.0, 1.0]);
        let turn = |angle: f64, dx: f64| {
            Pose::new(Rotation3::new(Vector3::new(0.0, 0.0, angle)) * at.rotation, at.translation + Vector3::x() * dx)
        };
        let c = ros_covariance(&at, &[turn(a, d), turn(-a, -d)]);
        let expected = |row: usize, col: usize| match (row, col) {
            (0, 0) => d * d,
            (5, 5) => a * a,
            (0, 5) | (5, 0) => a * d,
            _ => 0.0,
        };
        for (i, value) in c.iter().enumerate() {
            assert!((value - expected(i / 6, i % 6)).abs() < 1e-12, "element {i}: {value}");
        }
        assert_eq!(ros_covariance(&at, &[at])[0], -1.0, "one sample: unknown");
    }

    #[test]
    fn an_estimate_becomes_its_pose_and_hypotheses_stamped_by_its_frame() {
        let best = pose([0.3, -0.2, 0.1], [0.05, -0.02, 0.8]);
        let other = pose([0.35, -0.2, 0.1], [0.06, -0.02, 0.8]);
        let mut header = EstimateHeader {
            best: best.to_f32_row_major(),
            selection: SelectionMethod::Sdf as u32,
            hypothesis_count: 3,
            kept_count: 2,
            ..Default::default()
        };
        header.header.frame_id = 4;
        header.header.stamps.ns[StampSlot::Source as usize] = 1_700_000_000_500_000_000;
        let mut payload = Vec::new();
        for p in [best, other, other] {
            payload.extend(p.to_f32_row_major());
            payload.push(0.0);
        }
        assert_eq!(payload.len(), 3 * WEIGHTED_POSE_LEN);
        let messages = pose_messages(&header, &payload, "camera_optical", 7).unwrap();
        assert_eq!(messages.pose.header.stamp, Time { sec: 1_700_000_000, nanosec: 500_000_000 });
        assert_eq!(messages.pose.header.frame_id, "camera_optical");
        assert_eq!(messages.hypotheses.poses.len(), 2, "the kept ones only");
        assert!(messages.pose.covariance[0] > 0.0 && messages.pose.covariance[21] > 0.0);
        header.header.stamps = Default::default();
        assert_eq!(pose_messages(&header, &payload, "c", 7).unwrap().pose.header.stamp, Time::from_ns(7));
        header.kept_count = 4;
        let err = pose_messages(&header, &payload, "c", 7).unwrap_err().to_string();
        assert!(err.contains("frame 4") && err.contains("kept_count"), "{err}");
    }
}
