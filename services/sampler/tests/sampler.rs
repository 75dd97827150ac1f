//! The sampler against velocity fields with known flows.

use nalgebra::Vector3;
use poseflow_contracts::{ConditionHandle, Header, ObjectCategory, VelocityRequest, flags};
use poseflow_geometry::flow::target_velocity;
use poseflow_geometry::{Pose, so3};
use poseflow_runtime::{EmitError, Emitter, Flush, Input, Transform};
use poseflow_sampler::stage::SamplerStage;
use poseflow_sampler::{FieldError, FlowSampler, SamplerParams, Start, TrackingParams};

/// A category-level model's handle (a can and its size), which the
/// Hypotheses must carry on.
fn handle(frame: u64) -> ConditionHandle {
    ConditionHandle {
        header: Header::new(frame, 5),
        condition_id: 42,
        centroid: [0.1, -0.05, 0.7],
        point_scale: 0.5,
        category: ObjectCategory { code: 4, size: [0.08, 0.11, 0.08] },
        ..Default::default()
    }
}

/// The camera-frame pose every flow should reach.
fn target() -> Pose {
    Pose::new(so3::exp(&Vector3::new(0.3, 2.0, -0.4)), Vector3::new(0.12, -0.03, 0.72))
}

/// The exact velocity toward `target` (the paper's conditional velocity),
/// in the request frame of `handle`; records the times it was asked at.
fn toward_target<'a>(
    handle: &ConditionHandle,
    times: &'a mut Vec<f32>,
) -> impl FnMut(&VelocityRequest, &[f32], &mut [f32]) -> Result<(), FieldError> + 'a {
    toward_targets_recording(vec![*handle], move |request| times.extend(request.segments().iter().map(|s| s.t)))
}

/// As [`toward_target`] for several handles (the request frame of each
/// segment is its condition's); records each request's segments as
/// (condition, samples, t).
fn toward_targets<'a>(
    handles: Vec<ConditionHandle>,
    requests: &'a mut Vec<Vec<(u64, u32, f32)>>,
) -> impl FnMut(&VelocityRequest, &[f32], &mut [f32]) -> Result<(), FieldError> + 'a {
    toward_targets_recording(handles, move |request| {
        requests.push(request.segments().iter().map(|s| (s.condition_id, s.sample_count, s.t)).collect())
    })
}

/// As [`toward_targets`], handing every request to `record`.
fn toward_targets_recording<'a>(
    handles: Vec<ConditionHandle>,
    mut record: impl FnMut(&VelocityRequest) + 'a,
) -> impl FnMut(&VelocityRequest, &[f32], &mut [f32]) -> Result<(), FieldError> + 'a {
    move |request, poses, out| {
        record(request);
        let mut rows = poses.chunks_exact(12).zip(out.chunks_exact_mut(6));
        for segment in request.segments() {
            let handle = handles.iter().find(|h| h.condition_id == segment.condition_id).expect("a known condition");
            let scale = f64::from(handle.point_scale);
            let centroid = Vector3::from(handle.centroid.map(f64::from));
            let goal = Pose::new(target().rotation, (target().translation - centroid) / scale);
            for (pose, velocity) in rows.by_ref().take(segment.sample_count as usize) {
                let current =
                    Pose::from_f32_row_major(pose.try_into().unwrap()).map_err(|e| FieldError::Call(e.into()))?;
                let v =
                    target_velocity(&current, &goal, f64::from(segment.t)).map_err(|e| FieldError::Call(e.into()))?;
                velocity.copy_from_slice(&v.to_f32());
            }
        }
        Ok(())
    }
}

/// The handle marked as not its frame's last.
fn more_follow(handle: &ConditionHandle) -> ConditionHandle {
    let mut marked = *handle;
    marked.header.flags |= flags::MORE_IN_FRAME;
    marked
}

/// What the runtime does with one input: process it, then (the queue being
/// empty) flush.
fn run<F: poseflow_sampler::VelocityField>(
    stage: &mut SamplerStage<F>,
    handle: &ConditionHandle,
    out: &mut Collect,
) -> Result<(), poseflow_sampler::SamplerError> {
    stage.process(Input { header: handle, payload: &[] }, out)?;
    stage.flush(out, Flush::Idle)
}

fn assert_near_target(poses: &[Pose], degrees: f64, metres: f64) {
    for pose in poses {
        let angle = so3::geodesic_angle(&pose.rotation, &target().rotation).to_degrees();
        let offset = (pose.translation - target().translation).norm();
        assert!(angle < degrees && offset < metres, "{angle} deg, {offset} m");
    }
}

#[test]
fn the_exact_flow_carries_every_sample_to_the_target_in_the_camera_frame() {
    let handle = handle(3);
    let mut times = Vec::new();
    let mut sampler = FlowSampler::new(SamplerParams { samples: 20, steps: 5, ..Default::default() });
    let sampled = sampler.sample(&handle, &Start::Prior, &mut toward_target(&handle, &mut times)).unwrap();
    assert_eq!((sampled.poses.len(), sampled.steps), (20, 5));
    // f32 poses in the requests: micro-degree and sub-micrometre rounding.
    assert_near_target(sampled.poses, 1e-3, 1e-5);
    assert_eq!(times, vec![0.0, 0.2, 0.4, 0.6, 0.8]);
}

#[test]
fn a_quadratic_time_grid_asks_nearer_one_and_still_lands_on_the_target() {
    let handle = handle(3);
    let mut times = Vec::new();
    let params = SamplerParams::from_json(&serde_json::json!({"samples": 20, "time_grid": "quadratic"})).unwrap();
    let mut sampler = FlowSampler::new(params);
    let sampled = sampler.sample(&handle, &Start::Prior, &mut toward_target(&handle, &mut times)).unwrap();
    assert_near_target(sampled.poses, 1e-3, 1e-5);
    let expected = [0.0, 0.36, 0.64, 0.84, 0.96];
    assert!(times.iter().zip(expected).all(|(t, e)| (f64::from(*t) - e).abs() < 1e-6), "{times:?}");
    assert_eq!(times.len(), expected.len());
}

#[test]
fn draws_depend_on_seed_frame_and_object_only() {
    let zero = |_: &VelocityRequest, _: &[f32], out: &mut [f32]| -> Result<(), FieldError> {
        out.fill(0.0);
        Ok(())
    };
    let draw = |params: SamplerParams, handle: &ConditionHandle| -> Vec<Pose> {
        let mut field = zero;
        FlowSampler::new(params).sample(handle, &Start::Prior, &mut field).unwrap().poses.to_vec()
    };
    let params = SamplerParams { samples: 8, ..Default::default() };
    let a = draw(params.clone(), &handle(3));
    assert_eq!(a, draw(params.clone(), &handle(3)));
    assert_ne!(a, draw(params.clone(), &handle(4)));
    assert_ne!(a, draw(SamplerParams { seed: 1, ..params.clone() }, &handle(3)));
    // The prior: rotations spread, translations about the centroid with
    // the configured spread (0.05 m).
    let spread = a.iter().map(|p| (p.translation - Vector3::new(0.1, -0.05, 0.7)).norm()).fold(0.0, f64::max);
    assert!(spread > 0.01 && spread < 0.4, "{spread}");
}

#[test]
fn tracking_starts_from_the_previous_estimate_late_in_the_flow() {
    let params = SamplerParams {
        samples: 10,
        tracking: TrackingParams { enabled: true, steps: 2, ..Default::default() },
        ..Default::default()
    };
    let mut times = Vec::new();
    {
        let first = handle(10);
        let field = toward_target(&first, &mut times);
        let mut stage = SamplerStage::new(params, field);
        assert_eq!(stage.start_for(&first), Start::Prior);
        stage.remember(10, 5, target(), 0);
        let next = handle(11);
        assert_eq!(stage.start_for(&next), Start::Track(target()));
        let (header, poses) = stage.hypotheses(&next).unwrap();
        assert!(header.header.has_flag(flags::TRACKING));
        assert_eq!(header.step_count, 2);
        assert_eq!(header.category, next.category);
        assert_near_target(poses, 1e-3, 1e-5);
        // Too old an estimate is not used.
        assert_eq!(stage.start_for(&handle(17)), Start::Prior);
        // An estimate of the frame itself (a prior from elsewhere) is; one of
        // a later frame is not.
        let other = Pose::new(target().rotation, target().translation + Vector3::new(0.0, 0.0, 0.1));
        stage.remember(17, 5, other, 0);
        assert_eq!(stage.start_for(&handle(17)), Start::Track(other));
        assert_eq!(stage.start_for(&handle(16)), Start::Prior);
        // A side input running ahead (frame 19's estimate already in) does
        // not hide frame 17's from frame 18.
        stage.remember(19, 5, target(), 0);
        assert_eq!(stage.start_for(&handle(18)), Start::Track(other));
    }
    assert_eq!(times.len(), 2);
    assert!((times[0] - 0.8).abs() < 1e-6 && (times[1] - 0.9).abs() < 1e-6, "{times:?}");
}

/// The previous estimate itself is one of the tracked samples: neither
/// perturbed nor integrated, so the selector can keep a track that still
/// fits even where the flow pulls every sample elsewhere.
#[test]
fn tracking_keeps_the_previous_estimate_itself_beside_the_flows_samples() {
    let handle = handle(8);
    let previous = Pose::new(so3::exp(&Vector3::new(0.1, 2.3, -0.2)), Vector3::new(0.1, -0.02, 0.7));
    let sample = |keep_previous: bool, samples: usize| {
        let params = SamplerParams {
            samples,
            tracking: TrackingParams { enabled: true, keep_previous, ..Default::default() },
            ..Default::default()
        };
        let mut asked = Vec::new();
        let mut times = Vec::new();
        let mut exact = toward_target(&handle, &mut times);
        let mut field = |request: &VelocityRequest, poses: &[f32], out: &mut [f32]| {
            asked.push(request.sample_count);
            exact(request, poses, out)
        };
        let poses =
            FlowSampler::new(params).sample(&handle, &Start::Track(previous), &mut field).unwrap().poses.to_vec();
        (poses, asked)
    };
    let same = |a: &Pose, b: &Pose| {
        so3::geodesic_angle(&a.rotation, &b.rotation) < 1e-9 && (a.translation - b.translation).norm() < 1e-9
    };

    let (kept, asked) = sample(true, 8);
    assert_eq!(asked, vec![7], "the previous estimate is not integrated");
    assert!(same(&kept[7], &previous));
    assert!(kept[..7].iter().all(|pose| !same(pose, &previous)));
    assert_near_target(&kept[..7], 1e-3, 1e-5);

    let (flowed, asked) = sample(false, 8);
    assert_eq!(asked, vec![8]);
    assert!(flowed.iter().all(|pose| !same(pose, &previous)));

    // One sample is the flow's: a tracker must still track.
    let (single, asked) = sample(true, 1);
    assert_eq!(asked, vec![1]);
    assert_near_target(&single, 1e-3, 1e-5);
}

/// The selector's track check steers the next frame: after `LOST` every
/// sample starts from the prior (K steps from t = 0); after `UNSURE`
/// `prior_share` of them do and the rest are tracked (late in the flow), each
/// group integrated from its own start time.
#[test]
fn lost_and_unsure_estimates_start_from_the_prior_wholly_or_in_part() {
    let params = SamplerParams {
        samples: 10,
        steps: 4,
        tracking: TrackingParams { enabled: true, steps: 1, prior_share: 0.3, ..Default::default() },
        ..Default::default()
    };
    let mut times = Vec::new();
    let mut counts = Vec::new();
    {
        let next = handle(11);
        let mut exact = toward_target(&next, &mut times);
        let field = |request: &VelocityRequest, poses: &[f32], out: &mut [f32]| {
            counts.push(request.sample_count);
            exact(request, poses, out)
        };
        let mut stage = SamplerStage::new(params, field);
        stage.remember(10, 5, target(), flags::LOST);
        assert_eq!(stage.start_for(&next), Start::Prior);
        stage.remember(10, 5, target(), flags::UNSURE);
        assert_eq!(stage.start_for(&next), Start::Mixed(target()));
        let (header, poses) = stage.hypotheses(&next).unwrap();
        assert!(header.header.has_flag(flags::TRACKING));
        assert_eq!((poses.len(), header.step_count), (10, 4));
        assert_near_target(poses, 1e-3, 1e-5);
        // REINITIALISED (or any other bit) tracks as usual.
        stage.remember(10, 5, target(), flags::REINITIALISED);
        assert_eq!(stage.start_for(&next), Start::Track(target()));
    }
    // 3 of 10 from the prior in 4 steps from t = 0 and, in the first step's
    // request beside them, 6 tracked in one step from t = 0.8 beside the
    // previous estimate itself.
    assert_eq!(counts, vec![9, 3, 3, 3]);
    assert_eq!(times, vec![0.0, 0.8, 0.25, 0.5, 0.75]);
}

/// With `network_every = 3` a held track asks for velocities on one frame
/// in three (staggered by the object id); in between its samples are the
/// previous estimate perturbed, unintegrated, flagged `NETWORK_SKIPPED`. A
/// flagged or just re-acquired track asks the networks every frame.
#[test]
fn a_held_track_skips_the_networks_between_its_network_frames() {
    let params = SamplerParams {
        samples: 6,
        tracking: TrackingParams { enabled: true, network_every: 3, ..Default::default() },
        ..Default::default()
    };
    let previous = Pose::new(so3::exp(&Vector3::new(0.1, 2.3, -0.2)), Vector3::new(0.1, -0.02, 0.7));
    let mut counts = Vec::new();
    let mut times = Vec::new();
    let mut skipped = Vec::new();
    {
        let mut exact = toward_target(&handle(0), &mut times);
        let field = |request: &VelocityRequest, poses: &[f32], out: &mut [f32]| {
            counts.push((request.header.frame_id, request.sample_count));
            exact(request, poses, out)
        };
        let mut stage = SamplerStage::new(params.clone(), field);
        // Object 5: frames 10 (10 + 5 = 15) and 13 run the networks.
        for frame in 10..=14 {
            stage.remember(frame - 1, 5, previous, 0);
            let next = handle(frame);
            let start = stage.start_for(&next);
            let (header, poses) = stage.hypotheses(&next).unwrap();
            assert!(header.header.has_flag(flags::TRACKING));
            if header.header.has_flag(flags::NETWORK_SKIPPED) {
                assert_eq!(start, Start::Hold(previous));
                assert_eq!(header.step_count, 0);
                let angles: Vec<f64> =
                    poses.iter().map(|p| so3::geodesic_angle(&p.rotation, &previous.rotation).to_degrees()).collect();
                // The last is the previous estimate itself, the rest about it.
                assert!(angles[5] < 1e-9 && angles[..5].iter().all(|&a| a > 1e-6 && a < 30.0), "{angles:?}");
                skipped.push(frame);
            } else {
                assert_near_target(&poses[..5], 1e-3, 1e-5);
            }
        }
        // Flagged or just re-acquired estimates never skip.
        for flag in [flags::UNSURE, flags::LOST, flags::REINITIALISED] {
            stage.remember(13, 5, previous, flag);
            assert!(!matches!(stage.start_for(&handle(14)), Start::Hold(_)), "{flag}");
        }
    }
    assert_eq!(skipped, vec![11, 12, 14]);
    assert_eq!(counts, vec![(10, 5), (13, 5)]);
    // Every frame, the default.
    let mut every = SamplerStage::new(
        SamplerParams { tracking: TrackingParams { network_every: 1, ..params.tracking }, ..params },
        |_: &VelocityRequest, _: &[f32], _: &mut [f32]| Ok(()),
    );
    every.remember(10, 5, previous, 0);
    assert_eq!(every.start_for(&handle(11)), Start::Track(previous));
}

/// A tracking sampler of 2 samples whose field never moves them.
fn tracking_stage_without_flow() -> SamplerStage<impl poseflow_sampler::VelocityField> {
    let params = SamplerParams {
        samples: 2,
        tracking: TrackingParams { enabled: true, ..Default::default() },
        ..Default::default()
    };
    let zero = |_: &VelocityRequest, _: &[f32], out: &mut [f32]| -> Result<(), FieldError> {
        out.fill(0.0);
        Ok(())
    };
    SamplerStage::new(params, zero)
}

/// A tracking sampler waits, before a frame that would start from the
/// prior, for its object's estimate of the frame it sent last; a frame
/// that can start from an older estimate goes on.
#[test]
fn a_frame_that_would_start_from_the_prior_awaits_the_estimate_on_its_way() {
    use poseflow_contracts::EstimateHeader;
    use poseflow_runtime::Joined;
    let estimate = |frame: u64, object: u32, flags: u32| {
        let mut header = Header::new(frame, object);
        header.flags |= flags;
        EstimateHeader { header, best: target().to_f32_row_major(), ..Default::default() }
    };
    let of_object = |frame: u64, object: u32| {
        let mut handle = handle(frame);
        handle.header.object_id = object;
        handle
    };
    let mut stage = tracking_stage_without_flow();
    let mut out = Collect(Vec::new());
    assert_eq!(stage.awaits_side(&handle(7)), None, "nothing sent yet");
    run(&mut stage, &handle(7), &mut out).unwrap();
    assert_eq!(stage.awaits_side(&handle(7)), None, "the same frame again");
    assert_eq!(stage.awaits_side(&of_object(8, 6)), None, "another object");
    assert_eq!(stage.awaits_side(&handle(8)), Some(std::time::Duration::from_millis(1000)), "the default wait");
    // An estimate of an earlier frame is not the one awaited.
    stage.side(Input { header: &estimate(6, 5, flags::LOST), payload: &[] }).unwrap();
    assert!(stage.awaits_side(&handle(8)).is_some(), "a lost object starts from the prior");
    stage.side(Input { header: &estimate(7, 5, 0), payload: &[] }).unwrap();
    assert_eq!(stage.awaits_side(&handle(8)), None);
    let sent = Pose::from_f32_row_major(&target().to_f32_row_major()).unwrap();
    assert_eq!(stage.start_for(&handle(8)), Start::Track(sent));

    // A held track goes on from its older estimate while the newer is on its way.
    run(&mut stage, &handle(8), &mut out).unwrap();
    assert_eq!(stage.start_for(&handle(9)), Start::Track(sent));
    assert_eq!(stage.awaits_side(&handle(9)), None);

    // Two objects sent, neither with an estimate: the second's is awaited
    // too, but not long after the first of its frame came (the selector
    // made none for it).
    let mut stage = tracking_stage_without_flow();
    run(&mut stage, &of_object(9, 5), &mut out).unwrap();
    run(&mut stage, &of_object(9, 6), &mut out).unwrap();
    stage.side(Input { header: &estimate(9, 5, 0), payload: &[] }).unwrap();
    assert!(stage.awaits_side(&of_object(10, 6)).is_some(), "object 6's estimate of frame 9 is on its way");
    std::thread::sleep(std::time::Duration::from_millis(25));
    assert_eq!(stage.awaits_side(&of_object(10, 6)), None, "20 ms after the frame's first estimate, no more");
    // An estimate of a later frame ends the wait at once.
    run(&mut stage, &of_object(10, 6), &mut out).unwrap();
    stage.side(Input { header: &estimate(11, 5, 0), payload: &[] }).unwrap();
    assert_eq!(stage.awaits_side(&of_object(12, 6)), None);

    // Switched off, or not tracking: never waits.
    for tracking in [
        TrackingParams { enabled: true, await_estimate_ms: 0, ..Default::default() },
        TrackingParams { enabled: false, ..Default::default() },
    ] {
        let zero = |_: &VelocityRequest, _: &[f32], out: &mut [f32]| -> Result<(), FieldError> {
            out.fill(0.0);
            Ok(())
        };
        let mut stage = SamplerStage::new(SamplerParams { samples: 2, tracking, ..Default::default() }, zero);
        run(&mut stage, &handle(7), &mut out).unwrap();
        assert_eq!(stage.awaits_side(&handle(8)), None);
    }
    let err = SamplerParams::from_json(&serde_json::json!({ "tracking": { "await_estimate_ms": 60001 } }))
        .unwrap_err()
        .to_string();
    assert!(err.contains("tracking.await_estimate_ms"), "{err}");
}

/// A restarted source numbers its frames from 0 again and may show another
/// scene: its restart notice drops every track, and estimates of the old
/// numbering never seed the new frames.
#[test]
fn an_upstream_restart_drops_the_tracks() {
    let mut stage = tracking_stage_without_flow();
    let mut out = Collect(Vec::new());
    stage.remember(500, 5, target(), 0);
    assert_eq!(stage.start_for(&handle(501)), Start::Track(target()));

    let mut restarted = handle(0);
    restarted.header.flags |= flags::UPSTREAM_RESTARTED;
    run(&mut stage, &restarted, &mut out).unwrap();
    let (first, _) = &out.0[0];
    assert!(!first.header.has_flag(flags::TRACKING), "started from the prior");
    assert!(first.header.has_flag(flags::UPSTREAM_RESTARTED), "the notice travels on");
    assert_eq!(stage.start_for(&handle(501)), Start::Prior, "the old track is gone");

    // An estimate of the old numbering still in flight, then the new frame 0's:
    // the lower id wins and the old one is forgotten.
    stage.remember(502, 5, target(), 0);
    let other = Pose::new(target().rotation, target().translation + Vector3::new(0.0, 0.1, 0.0));
    stage.remember(0, 5, other, 0);
    assert_eq!(stage.start_for(&handle(1)), Start::Track(other));
    assert_eq!(stage.start_for(&handle(503)), Start::Prior);
}

/// The first frame of a new sequence (another scene) starts its object
/// from the prior, and an estimate of the old scene still on its way
/// afterwards does not seed the new one.
#[test]
fn a_sequence_start_drops_the_object_track_and_late_estimates_of_the_old_scene() {
    let mut stage = tracking_stage_without_flow();
    let mut out = Collect(Vec::new());
    stage.remember(39, 5, target(), 0);
    // A prior for the new sequence's first frame, fed ahead of it, stays.
    let fed_ahead = Pose::new(target().rotation, target().translation + Vector3::new(0.0, 0.0, 0.1));
    stage.remember(41, 5, fed_ahead, 0);
    let mut first = handle(40);
    first.header.flags |= flags::SEQUENCE_START;
    run(&mut stage, &first, &mut out).unwrap();
    assert!(!out.0[0].0.header.has_flag(flags::TRACKING), "started from the prior");
    stage.remember(39, 5, target(), 0);
    assert_eq!(stage.start_for(&handle(41)), Start::Track(fed_ahead), "the old scene's estimate is ignored");
    let other = Pose::new(target().rotation, target().translation + Vector3::new(0.0, 0.1, 0.0));
    stage.remember(42, 5, other, 0);
    assert_eq!(stage.start_for(&handle(42)), Start::Track(other));
}

struct Collect(Vec<(poseflow_contracts::HypothesesHeader, Vec<f32>)>);

impl Emitter<poseflow_contracts::HypothesesHeader> for Collect {
    fn emit(
        &mut self,
        header: poseflow_contracts::HypothesesHeader,
        len: usize,
        fill: &mut dyn FnMut(&mut [f32]),
    ) -> Result<(), EmitError> {
        let mut payload = vec![0.0; len];
        fill(&mut payload);
        self.0.push((header, payload));
        Ok(())
    }
}

#[test]
fn failed_or_non_finite_velocities_fail_the_frame_with_its_ids() {
    let failing = |_: &VelocityRequest, _: &[f32], _: &mut [f32]| -> Result<(), FieldError> {
        Err(FieldError::Call("timed out".into()))
    };
    let mut stage = SamplerStage::new(SamplerParams::default(), failing);
    let h = handle(9);
    let mut out = Collect(Vec::new());
    // The cause travels as the error's source, as the runtime logs it.
    let err = poseflow_runtime::error_chain(&run(&mut stage, &h, &mut out).unwrap_err());
    assert!(err.contains("frame 9 object 5") && err.contains("step 0") && err.contains("timed out"), "{err}");
    assert!(out.0.is_empty());

    let nan = |_: &VelocityRequest, _: &[f32], out: &mut [f32]| -> Result<(), FieldError> {
        out.fill(f32::NAN);
        Ok(())
    };
    let err = SamplerStage::new(SamplerParams::default(), nan).hypotheses(&h).unwrap_err().to_string();
    assert!(err.contains("not finite"), "{err}");

    let bad_scale = ConditionHandle { point_scale: 0.0, ..h };
    let zero = |_: &VelocityRequest, _: &[f32], out: &mut [f32]| -> Result<(), FieldError> {
        out.fill(0.0);
        Ok(())
    };
    let err = SamplerStage::new(SamplerParams::default(), zero).hypotheses(&bad_scale).unwrap_err().to_string();
    assert!(err.contains("point_scale 0"), "{err}");
}

#[test]
fn the_stage_publishes_camera_frame_poses() {
    let h = handle(2);
    let mut times = Vec::new();
    let mut stage =
        SamplerStage::new(SamplerParams { samples: 4, ..Default::default() }, toward_target(&h, &mut times));
    let mut out = Collect(Vec::new());
    run(&mut stage, &h, &mut out).unwrap();
    let (header, payload) = &out.0[0];
    assert_eq!((header.sample_count, header.step_count, header.header.frame_id), (4, 5, 2));
    let poses: Vec<Pose> =
        payload.chunks_exact(12).map(|c| Pose::from_f32_row_major(c.try_into().unwrap()).unwrap()).collect();
    assert_near_target(&poses, 1e-3, 1e-5);
}

/// Three objects of a frame that arrived together are sampled in lockstep:
/// one velocity request per Euler step carries all three, and each gets
/// exactly the hypotheses it gets alone. A fourth handle of an object
/// already held starts a new batch (it may track from the first's estimate).
#[test]
fn objects_that_arrive_together_share_one_request_per_step() {
    let handles: Vec<ConditionHandle> = (0..3)
        .map(|k| ConditionHandle {
            header: Header::new(8, 5 + k),
            condition_id: 40 + u64::from(k),
            centroid: [0.1 * k as f32, -0.05, 0.7],
            point_scale: 0.5 + 0.1 * k as f32,
            ..Default::default()
        })
        .collect();
    let params = SamplerParams { samples: 6, batch: 8, ..Default::default() };
    let mut requests = Vec::new();
    let mut stage = SamplerStage::new(params.clone(), toward_targets(handles.clone(), &mut requests));
    let mut out = Collect(Vec::new());
    for h in &handles[..2] {
        stage.process(Input { header: &more_follow(h), payload: &[] }, &mut out).unwrap();
    }
    stage.flush(&mut out, Flush::Idle).unwrap();
    assert!(out.0.is_empty(), "held until the frame's last handle");
    stage.process(Input { header: &handles[2], payload: &[] }, &mut out).unwrap();
    assert_eq!(out.0.len(), 3, "the frame's last handle runs the batch");
    let again = ConditionHandle { header: Header::new(9, 5), ..handles[0] };
    stage.process(Input { header: &more_follow(&again), payload: &[] }, &mut out).unwrap();
    let later = ConditionHandle { header: Header::new(9, 5), ..handles[0] };
    stage.process(Input { header: &later, payload: &[] }, &mut out).unwrap();
    assert_eq!(out.0.len(), 5, "a second handle of an object runs the first");
    drop(stage);
    assert_eq!(requests.len(), 5 + 5 + 5, "one request per step and batch");
    for (k, request) in requests[..5].iter().enumerate() {
        let expected: Vec<(u64, u32, f32)> = (40..43).map(|id| (id, 6, 0.2 * k as f32)).collect();
        assert_eq!(request, &expected);
    }
    for (h, (header, payload)) in handles.iter().zip(&out.0) {
        let mut alone_requests = Vec::new();
        let mut alone = SamplerStage::new(params.clone(), toward_targets(vec![*h], &mut alone_requests));
        let (alone_header, alone_poses) = alone.hypotheses(h).unwrap();
        assert_eq!(header.header.frame_id, alone_header.header.frame_id);
        assert_eq!(header.sample_count, alone_header.sample_count);
        let alone_payload: Vec<f32> = alone_poses.iter().flat_map(|p| p.to_f32_row_major()).collect();
        assert_eq!(payload, &alone_payload);
    }
}

/// A request never carries more samples than the edge holds: with room for
/// 8 samples, three objects of 6 samples each go in three requests a step,
/// with the same hypotheses.
#[test]
fn a_batch_larger_than_the_edge_is_split_into_requests() {
    let handles: Vec<ConditionHandle> = (0..3)
        .map(|k| ConditionHandle { header: Header::new(8, 5 + k), condition_id: 40 + u64::from(k), ..handle(8) })
        .collect();
    let params = SamplerParams { samples: 6, steps: 2, batch: 8, ..Default::default() };
    let sample = |capacity: usize| {
        let mut requests = Vec::new();
        let mut stage = SamplerStage::new(params.clone(), toward_targets(handles.clone(), &mut requests));
        stage.set_request_capacity(capacity);
        let mut out = Collect(Vec::new());
        for h in &handles {
            stage.process(Input { header: &more_follow(h), payload: &[] }, &mut out).unwrap();
        }
        stage.flush(&mut out, Flush::End).unwrap();
        drop(stage);
        (requests.iter().map(|r| r.iter().map(|s| s.1).sum::<u32>()).collect::<Vec<_>>(), out.0)
    };
    let (split, split_out) = sample(8);
    let (whole, whole_out) = sample(4096);
    assert_eq!(split, vec![6; 6]);
    assert_eq!(whole, vec![18; 2]);
    assert_eq!(split_out, whole_out);
}

/// A tracked object (one step from t = 0.8) and an object started from the
/// prior (five steps from 0) share the first request; the last four carry
/// the second alone.
#[test]
fn a_batch_of_tracked_and_new_objects_steps_each_at_its_own_times() {
    let tracked = handle(12);
    let fresh = ConditionHandle { header: Header::new(12, 6), condition_id: 43, ..tracked };
    let params = SamplerParams {
        samples: 4,
        batch: 8,
        tracking: TrackingParams { enabled: true, keep_previous: false, ..Default::default() },
        ..Default::default()
    };
    let mut requests = Vec::new();
    let mut stage = SamplerStage::new(params, toward_targets(vec![tracked, fresh], &mut requests));
    stage.remember(11, 5, target(), 0);
    let mut out = Collect(Vec::new());
    stage.process(Input { header: &more_follow(&tracked), payload: &[] }, &mut out).unwrap();
    stage.process(Input { header: &fresh, payload: &[] }, &mut out).unwrap();
    assert_eq!((out.0[0].0.step_count, out.0[1].0.step_count), (1, 5));
    assert!(out.0[0].0.header.has_flag(flags::TRACKING) && !out.0[1].0.header.has_flag(flags::TRACKING));
    drop(stage);
    assert_eq!(requests[0], vec![(43, 4, 0.0), (42, 4, 0.8)].into_iter().rev().collect::<Vec<_>>());
    for (k, request) in requests[1..].iter().enumerate() {
        assert_eq!(request, &vec![(43, 4, 0.2 * (k + 1) as f32)]);
    }
}

#[test]
fn bad_parameters_are_named() {
    for (json, expected) in [
        (serde_json::json!({"samples": 0}), "samples"),
        (serde_json::json!({"steps": 0}), "steps"),
        (serde_json::json!({"tracking": {"start_time": 1.0}}), "tracking.start_time"),
        (serde_json::json!({"tracking": {"enable": true}}), "unknown field `enable`"),
        (serde_json::json!({"translation_noise_std": -1.0}), "translation_noise_std"),
        (serde_json::json!({"time_grid": "cosine"}), "unknown variant `cosine`, expected `uniform` or `quadratic`"),
    ] {
        let err = SamplerParams::from_json(&json).unwrap_err().to_string();
        assert!(err.contains(expected), "{json}: {err}");
    }
}
