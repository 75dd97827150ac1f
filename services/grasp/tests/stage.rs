//! The grasp stage's message side (its integration tests also make cargo
//! build the `grasp` binary the end-to-end graph tests launch).

use poseflow_contracts::{EstimateHeader, GRASP_LEN, Header, POSE_LEN, WEIGHTED_POSE_LEN};
use poseflow_geometry::Pose;
use poseflow_grasp::stage::{grasp_values, kept_hypotheses};
use poseflow_grasp::{Gripper, PlannedGrasp};

fn estimate(kept: u32, hypotheses: &[Pose]) -> (EstimateHeader, Vec<f32>) {
    let header = EstimateHeader {
        header: Header::new(7, 14),
        hypothesis_count: hypotheses.len() as u32,
        kept_count: kept,
        ..Default::default()
    };
    let payload = hypotheses
        .iter()
        .enumerate()
        .flat_map(|(i, pose)| pose.to_f32_row_major().into_iter().chain([i as f32]))
        .collect();
    (header, payload)
}

#[test]
fn the_kept_hypotheses_are_read_in_order_and_a_bad_payload_names_the_frame() {
    let poses: Vec<Pose> = (0..4)
        .map(|i| Pose::new(nalgebra::Rotation3::identity(), nalgebra::Vector3::new(0.01 * f64::from(i), 0.0, 0.5)))
        .collect();
    let (header, payload) = estimate(3, &poses);
    assert_eq!(payload.len(), 4 * WEIGHTED_POSE_LEN);
    let kept = kept_hypotheses(&header, &payload).unwrap();
    assert_eq!(kept.len(), 3);
    for (read, written) in kept.iter().zip(&poses) {
        assert!((read.translation - written.translation).norm() < 1e-6);
    }
    let err = kept_hypotheses(&header, &payload[..payload.len() - 1]).unwrap_err().to_string();
    assert!(err.starts_with("frame 7 object 14:"), "{err}");
}

#[test]
fn a_grasp_is_written_as_pose_width_share_and_score() {
    let pose = Pose::new(nalgebra::Rotation3::identity(), nalgebra::Vector3::new(0.1, 0.2, 0.3));
    let gripper = Gripper::default();
    // Half the friction cone left: the score is the share plus 0.01 × 0.5.
    let margin = gripper.friction_angle() / 2.0;
    let grasp = PlannedGrasp { camera_from_grasp: pose, width: 0.03, valid_share: 0.75, margin };
    let values = grasp_values(&grasp, &gripper);
    assert_eq!(values.len(), GRASP_LEN);
    assert_eq!(&values[..POSE_LEN], &pose.to_f32_row_major());
    assert_eq!(&values[POSE_LEN..], &[0.03, 0.75, 0.755]);
}
