use iceoryx2_bb_elementary_traits::zero_copy_send::ZeroCopySend;
use proptest::prelude::*;

use super::*;

fn type_name<T: ZeroCopySend>() -> &'static str {
    // SAFETY: reading the registered name has no preconditions; `unsafe` in
    // iceoryx2's trait marks the promise made by implementors, not callers.
    unsafe { <T as ZeroCopySend>::type_name() }
}

#[test]
fn type_names_are_stable_and_versioned() {
    assert_eq!(type_name::<Header>(), "poseflow/Header/v1");
    assert_eq!(type_name::<ObservationHeader>(), "poseflow/Observation/v2");
    assert_eq!(type_name::<ConditionHandle>(), "poseflow/Condition/v2");
    assert_eq!(type_name::<VelocityRequest>(), "poseflow/VelocityRequest/v2");
    assert_eq!(type_name::<VelocityResponse>(), "poseflow/VelocityResponse/v1");
    assert_eq!(type_name::<HypothesesHeader>(), "poseflow/Hypotheses/v2");
    assert_eq!(type_name::<EstimateHeader>(), "poseflow/Estimate/v3");
    assert_eq!(type_name::<GraspsHeader>(), "poseflow/Grasps/v1");
    assert_eq!(type_name::<NextViewHeader>(), "poseflow/NextView/v1");
    assert_eq!(type_name::<Heartbeat>(), "poseflow/Heartbeat/v1");
    assert_eq!(type_name::<TensorHeader>(), "poseflow/Tensor/v1");
}

fn observation(image_size: u32, patch_grid: u32, points: u32) -> ObservationHeader {
    ObservationHeader {
        header: Header::new(7, 1),
        image_size,
        patch_grid,
        point_count: points,
        valid_point_count: points,
        point_scale: 1.0,
        ..Default::default()
    }
}

#[test]
fn observation_payload_splits_into_its_sections() {
    let header = observation(4, 2, 3);
    // image 3·4·4 = 48, mask 2·2 = 4, points 3·3 = 9.
    assert_eq!(header.payload_len().unwrap(), 61);
    let payload: Vec<f32> = (0..61).map(|i| i as f32).collect();
    let view = header.view(&payload).unwrap();
    assert_eq!(view.image.len(), 48);
    assert_eq!(view.token_mask, &[48.0, 49.0, 50.0, 51.0]);
    assert_eq!(view.points[0], 52.0);
    assert_eq!(view.points.len(), 9);
    assert!(view.depth.is_empty() && view.mask.is_empty());

    let header = ObservationHeader { depth_grid: 2, ..header };
    // … then depth 2·2 and mask 2·2.
    assert_eq!(header.payload_len().unwrap(), 69);
    let payload: Vec<f32> = (0..69).map(|i| i as f32).collect();
    let view = header.view(&payload).unwrap();
    assert_eq!(view.depth, &[61.0, 62.0, 63.0, 64.0]);
    assert_eq!(view.mask, &[65.0, 66.0, 67.0, 68.0]);
}

#[test]
fn inconsistent_lengths_are_named() {
    let header = observation(4, 2, 3);
    let err = header.view(&[0.0; 60]).unwrap_err().to_string();
    assert_eq!(err, "Observation: payload holds 60 f32 values, the header announces 61");

    let err = observation(224, 15, 1024).payload_len().unwrap_err().to_string();
    assert!(err.contains("patch_grid") && err.contains("divisor"), "{err}");

    let err = observation(224, 16, 0).payload_len().unwrap_err().to_string();
    assert!(err.contains("`point_count` = 0"), "{err}");

    let mut resampled = observation(224, 16, 10);
    resampled.valid_point_count = 11;
    assert!(resampled.payload_len().unwrap_err().to_string().contains("valid_point_count"));

    let deep = ObservationHeader { depth_grid: 257, ..observation(4, 2, 3) };
    let err = deep.payload_len().unwrap_err().to_string();
    assert!(err.contains("depth_grid") && err.contains("257") && err.contains("0..=256"), "{err}");
}

#[test]
fn velocity_request_rejects_flow_time_outside_unit_interval() {
    let mut request = VelocityRequest::single(Header::new(7, 1), 3, 1, 50, 0.8);
    assert_eq!(request.payload_len().unwrap(), 50 * POSE_LEN);
    for t in [1.0, -0.1, f32::NAN] {
        request.segments[0].t = t;
        let err = request.payload_len().unwrap_err().to_string();
        assert!(err.contains("field `segments[].t`"), "{err}");
    }
}

#[test]
fn velocity_request_segments_add_up_to_its_samples() {
    let mut request = VelocityRequest::single(Header::new(7, 1), 3, 1, 50, 0.0);
    assert!(request.push(VelocitySegment { condition_id: 4, sample_count: 49, t: 0.6 }));
    assert_eq!((request.segment_count, request.sample_count), (2, 99));
    assert_eq!(request.payload_len().unwrap(), 99 * POSE_LEN);
    // A header whose total disagrees with its segments, or with no or too
    // many segments, or an empty segment, is refused by field name.
    let mut wrong = request;
    wrong.sample_count = 100;
    assert!(wrong.payload_len().unwrap_err().to_string().contains("the sum of the segments"));
    for (count, field) in [(0, "segment_count"), (17, "segment_count")] {
        let mut wrong = request;
        wrong.segment_count = count;
        assert!(wrong.payload_len().unwrap_err().to_string().contains(field), "{count}");
    }
    let mut empty = request;
    empty.segments[1].sample_count = 0;
    empty.sample_count = 50;
    assert!(empty.payload_len().unwrap_err().to_string().contains("segments[].sample_count"));
    // A full request takes no seventeenth segment.
    let mut full = VelocityRequest::default();
    for id in 0..MAX_SEGMENTS as u64 {
        assert!(full.push(VelocitySegment { condition_id: id, sample_count: 1, t: 0.0 }));
    }
    assert!(!full.push(VelocitySegment { condition_id: 99, sample_count: 1, t: 0.0 }));
    assert_eq!((full.segment_count, full.sample_count), (16, 16));
    assert_eq!(full.segments().len(), MAX_SEGMENTS);
}

#[test]
fn failed_velocity_response_has_no_payload() {
    let ok = VelocityResponse { sample_count: 50, status: status::OK, ..Default::default() };
    assert_eq!(ok.payload_len().unwrap(), 300);
    let failed = VelocityResponse { sample_count: 0, status: status::UNKNOWN_CONDITION, ..Default::default() };
    assert_eq!(failed.payload_len().unwrap(), 0);
    let inconsistent = VelocityResponse { sample_count: 50, status: status::INFERENCE_FAILED, ..Default::default() };
    assert!(inconsistent.payload_len().is_err());
}

#[test]
fn estimate_sections_and_selection_codes() {
    let header = EstimateHeader {
        selection: SelectionMethod::ModelFree as u32,
        mode_count: 2,
        hypothesis_count: 10,
        kept_count: 3,
        ..Default::default()
    };
    let payload = vec![0.5; (2 + 10) * WEIGHTED_POSE_LEN];
    let view = header.view(&payload).unwrap();
    assert_eq!(view.modes.len(), 26);
    assert_eq!(view.hypotheses.len(), 130);
    let bad = EstimateHeader { selection: 9, ..header };
    assert!(bad.payload_len().unwrap_err().to_string().contains("selection"));
    for kept in [0, 11] {
        let bad = EstimateHeader { kept_count: kept, ..header };
        assert!(bad.payload_len().unwrap_err().to_string().contains("kept_count"), "{kept}");
    }
    assert_eq!(SelectionMethod::from_code(3), Some(SelectionMethod::Sdf));
}

#[test]
fn a_category_needs_finite_positive_extents() {
    let mug = ObjectCategory { code: 6, size: [0.12, 0.1, 0.09] };
    let estimate = EstimateHeader { kept_count: 1, hypothesis_count: 1, category: mug, ..Default::default() };
    assert!(estimate.payload_len().is_ok());
    for size in [[0.0, 0.1, 0.1], [f32::NAN, 0.1, 0.1], [0.1, -0.1, 0.1], [0.1, 0.1, f32::INFINITY]] {
        let bad = EstimateHeader { category: ObjectCategory { size, ..mug }, ..estimate };
        let error = bad.payload_len().unwrap_err().to_string();
        assert!(error.contains("Estimate") && error.contains("category.size"), "{error}");
        let hypotheses =
            HypothesesHeader { sample_count: 1, category: ObjectCategory { size, ..mug }, ..Default::default() };
        assert!(hypotheses.payload_len().is_err());
        let condition = ConditionHandle { category: ObjectCategory { size, ..mug }, ..Default::default() };
        assert!(condition.payload_len().is_err());
    }
    // An instance-level model leaves it all zero.
    assert!(ConditionHandle::default().payload_len().is_ok());
}

#[test]
fn grasps_next_view_hypotheses_and_condition_lengths() {
    let grasps = GraspsHeader { grasp_count: 4, hypothesis_count: 10, ..Default::default() };
    assert_eq!(grasps.payload_len().unwrap(), 4 * GRASP_LEN);
    let view = NextViewHeader { candidate_count: 3, ..Default::default() };
    assert_eq!(view.payload_len().unwrap(), 3 * CANDIDATE_LEN);
    let hyps = HypothesesHeader { sample_count: 50, step_count: 5, ..Default::default() };
    assert_eq!(hyps.payload_len().unwrap(), 600);
    assert_eq!(ConditionHandle::default().payload_len().unwrap(), 0);
    assert!(HypothesesHeader { sample_count: 5000, ..hyps }.payload_len().is_err());
}

#[test]
fn tensor_length_is_the_product_of_its_shape() {
    let t = TensorHeader { shape: [3, 224, 224, 99], rank: 3, ..Default::default() };
    assert_eq!(t.payload_len().unwrap(), 3 * 224 * 224);
    assert_eq!(TensorHeader::vector(Header::new(0, 0), 7).payload_len().unwrap(), 7);
    let huge = TensorHeader { shape: [u32::MAX, u32::MAX, 2, 2], rank: 4, ..Default::default() };
    assert!(huge.payload_len().unwrap_err().to_string().contains("shape"));
    assert!(TensorHeader { rank: 0, ..t }.payload_len().is_err());
}

#[test]
fn header_flags() {
    let mut header = Header::new(1, 2);
    assert!(!header.has_flag(flags::TRACKING));
    header.flags |= flags::TRACKING | flags::POINTS_RESAMPLED;
    assert!(header.has_flag(flags::TRACKING) && !header.has_flag(flags::UPSTREAM_RESTARTED));
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 10_000, ..ProptestConfig::default() })]

    /// Garbage headers (as a crashed or hostile peer may publish) never panic
    /// or overflow, and any length they accept stays within the limits.
    #[test]
    fn arbitrary_observation_headers_are_checked_not_trusted(
        s in any::<u32>(), p in any::<u32>(), n in any::<u32>(), valid in any::<u32>(), g in any::<u32>(),
    ) {
        let mut header = observation(s, p, n);
        header.valid_point_count = valid;
        header.depth_grid = g % 512;
        if let Ok(len) = header.payload_len() {
            prop_assert!(len <= 3 * 1024 * 1024 + 1024 * 1024 + 3 * 65_536 + 2 * 256 * 256);
            let payload = vec![0.0; len];
            prop_assert!(header.view(&payload).is_ok());
            prop_assert!(header.view(&payload[..len - 1]).is_err());
        }
    }

    #[test]
    fn arbitrary_estimate_headers_are_checked_not_trusted(
        selection in any::<u32>(), modes in any::<u32>(), scored in any::<u32>(), kept in any::<u32>(),
    ) {
        let header = EstimateHeader {
            selection, mode_count: modes, hypothesis_count: scored, kept_count: kept, ..Default::default()
        };
        if let Ok(len) = header.payload_len() {
            prop_assert!(len <= (64 + 4096) * WEIGHTED_POSE_LEN);
            prop_assert!(header.view(&vec![0.0; len]).is_ok());
        }
    }
}

#[test]
fn message_names_resolve_to_their_header_types() {
    struct Size;
    impl MessageVisitor for Size {
        type Output = usize;
        fn visit<H: MessageHeader + Send + 'static>(self) -> usize {
            std::mem::size_of::<H>()
        }
    }
    assert_eq!(visit_message("Observation", Size), Some(160));
    assert_eq!(visit_message("Estimate", Size), Some(360));
    assert_eq!(visit_message("Tensor", Size), Some(104));
    assert_eq!(visit_message("Pose", Size), None);
}
