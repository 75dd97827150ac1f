//! The sampler against velocity fields with known flows.

use nalgebra::Vector3;
use poseflow_contracts::{ConditionHandle, Header, VelocityRequest, flags};
use poseflow_geometry::flow::target_velocity;
use poseflow_geometry::{Pose, so3};
use poseflow_runtime::{EmitError, Emitter, Input, Transform};
use poseflow_sampler::stage::SamplerStage;
use poseflow_sampler::{FieldError, FlowSampler, SamplerParams, Start, TrackingParams};

fn handle(frame: u64) -> ConditionHandle {
    ConditionHandle {
        header: Header::new(frame, 5),
        condition_id: 42,
        centroid: [0.1, -0.05, 0.7],
        point_scale: 0.5,
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
    let scale = f64::from(handle.point_scale);
    let centroid = Vector3::from(handle.centroid.map(f64::from));
    let goal = Pose::new(target().rotation, (target().translation - centroid) / scale);
    move |request, poses, out| {
        times.push(request.t);
        for (pose, velocity) in poses.chunks_exact(12).zip(out.chunks_exact_mut(6)) {
            let current = Pose::from_f32_row_major(pose.try_into().unwrap()).map_err(|e| FieldError::Call(e.into()))?;
            let v = target_velocity(&current, &goal, f64::from(request.t)).map_err(|e| FieldError::Call(e.into()))?;
            velocity.copy_from_slice(&v.to_f32());
        }
        Ok(())
    }
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
    // 3 of 10 from the prior in 4 steps from t = 0, then 6 tracked in one
    // step from t = 0.8 beside the previous estimate itself.
    assert_eq!(counts, vec![3, 3, 3, 3, 6]);
    assert_eq!(times, vec![0.0, 0.25, 0.5, 0.75, 0.8]);
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
    stage.process(Input { header: &restarted, payload: &[] }, &mut out).unwrap();
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
    stage.process(Input { header: &first, payload: &[] }, &mut out).unwrap();
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
    let err = poseflow_runtime::error_chain(&stage.process(Input { header: &h, payload: &[] }, &mut out).unwrap_err());
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
    stage.process(Input { header: &h, payload: &[] }, &mut out).unwrap();
    let (header, payload) = &out.0[0];
    assert_eq!((header.sample_count, header.step_count, header.header.frame_id), (4, 5, 2));
    let poses: Vec<Pose> =
        payload.chunks_exact(12).map(|c| Pose::from_f32_row_major(c.try_into().unwrap()).unwrap()).collect();
    assert_near_target(&poses, 1e-3, 1e-5);
}

#[test]
fn bad_parameters_are_named() {
    for (json, expected) in [
        (serde_json::json!({"samples": 0}), "samples"),
        (serde_json::json!({"steps": 0}), "steps"),
        (serde_json::json!({"tracking": {"start_time": 1.0}}), "tracking.start_time"),
        (serde_json::json!({"tracking": {"enable": true}}), "unknown field `enable`"),
        (serde_json::json!({"translation_noise_std": -1.0}), "translation_noise_std"),
    ] {
        let err = SamplerParams::from_json(&json).unwrap_err().to_string();
        assert!(err.contains(expected), "{json}: {err}");
    }
}
