//! The next-best-view stage's message side and its planner on the default
//! model (these integration tests also make cargo build the `nbv` binary
//! the end-to-end graph tests launch).

use std::path::PathBuf;

use nalgebra::{Point3, Rotation3, Vector3};
use poseflow_contracts::{CANDIDATE_LEN, MessageHeader, NextViewHeader, POSE_LEN};
use poseflow_geometry::Pose;
use poseflow_ingest::{ObjectMask, RgbdFrame};
use poseflow_nbv::stage::next_view_message;
use poseflow_nbv::{NbvParams, NbvPlanner, NextViewPlan, Occluders, PlanCost, ScoredView, UNIFORM_ROTATION_TRACE};
use poseflow_scene::bop::Raster;
use poseflow_scene::dataset::lmo_camera;
use poseflow_scene::scene::look_at;

fn root() -> PathBuf {
    PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/../.."))
}

#[test]
fn a_plan_is_written_best_first_with_the_chosen_view_in_the_header() {
    let view = |x: f64, trace: f64| ScoredView {
        camera_from_next: Pose::new(Rotation3::from_axis_angle(&Vector3::y_axis(), x), Vector3::new(x, 0.0, 0.1)),
        expected_trace: trace,
        uninformative: 0,
    };
    let plan = NextViewPlan { views: vec![view(0.3, 0.01), view(-0.2, 0.5)], cost: PlanCost::default() };
    let (header, payload) = next_view_message(&plan, 0.25);
    assert_eq!(header.candidate_count, 2);
    assert_eq!(header.chosen, plan.views[0].camera_from_next.to_f32_row_major());
    assert_eq!((header.expected_rotation_trace, header.current_rotation_trace), (0.01, 0.25));
    header.check_payload(&payload).unwrap();
    assert_eq!(payload.len(), 2 * CANDIDATE_LEN);
    for (chunk, view) in payload.chunks_exact(CANDIDATE_LEN).zip(&plan.views) {
        assert_eq!(&chunk[..POSE_LEN], &view.camera_from_next.to_f32_row_major());
        assert_eq!(chunk[POSE_LEN], view.expected_trace as f32);
    }
    let bad = NextViewHeader { candidate_count: 3, ..header };
    assert!(bad.check_payload(&payload).is_err());
}

/// The YCB-V mug (handle along object +x) standing on a table at the world
/// origin, and cameras around it: world z up, metres.
struct MugWorld {
    world_from_object: Pose,
    centre: Point3<f64>,
}

impl MugWorld {
    fn new() -> Self {
        // The mug's base (object z = −3.65 cm in its model, 8.13 cm tall)
        // on the table.
        Self {
            world_from_object: Pose::new(Rotation3::identity(), Vector3::new(0.0, 0.0, 0.0365)),
            centre: Point3::new(0.0, 0.0, 0.041),
        }
    }

    /// `camera_from_world` of a camera 0.5 m away, 25° up, at `azimuth`
    /// (radians from world +x, the handle's direction).
    fn camera(&self, azimuth: f64) -> Pose {
        let e = 25f64.to_radians();
        let eye = self.centre + 0.5 * Vector3::new(e.cos() * azimuth.cos(), e.cos() * azimuth.sin(), e.sin());
        look_at(&eye, &self.centre, 0.0)
    }
}

fn mug_planner(workers: usize) -> NbvPlanner {
    let params = NbvParams::from_json(&serde_json::json!({
        "models": root().join("objects/ycbv/mug-bowl"),
        "hypotheses": 1,
        "workers": workers,
        "inference": {"model": root().join("models/poseflow-lmo10")},
        "sampler": {"samples": 16, "steps": 3},
    }))
    .unwrap();
    NbvPlanner::load(params).unwrap()
}

/// With the handle hidden behind the body, a view from the handle's side
/// leaves less rotational uncertainty than the view from behind the mug,
/// whatever the number of workers scoring them.
#[test]
fn seeing_the_handle_is_expected_to_leave_less_uncertainty_than_hiding_it() {
    let world = MugWorld::new();
    let current = world.camera(std::f64::consts::PI); // handle pointing away
    let truth = current * world.world_from_object;
    let next = |azimuth: f64| current * world.camera(azimuth).inverse();
    let views = [next(std::f64::consts::PI), next(std::f64::consts::FRAC_PI_2), next(-std::f64::consts::FRAC_PI_2)];
    let mut planner = mug_planner(2);
    let plan = planner.score_views(1, 14, &views, &[truth], None).unwrap();
    let hidden = plan.views.iter().find(|v| v.camera_from_next == views[0]).unwrap();
    assert_ne!(plan.views[0].camera_from_next, views[0], "{:?}", plan.views);
    assert!(plan.views[0].expected_trace < hidden.expected_trace, "{:?}", plan.views);
    assert!(plan.views.iter().all(|v| v.uninformative == 0 && v.expected_trace < UNIFORM_ROTATION_TRACE));
    assert_eq!(plan.cost.views, 3);

    let again = mug_planner(1).score_views(1, 14, &views, &[truth], None).unwrap();
    assert_eq!(again.views, plan.views);
}

/// The current camera's depth image of a wall (world plane y = `y`, 50 cm
/// wide, 35 cm tall, standing on the table) and an empty target mask.
fn wall_frame(camera_from_world: &Pose, y: f64) -> (RgbdFrame, ObjectMask) {
    let camera = lmo_camera(640, 480);
    let world_from_camera = camera_from_world.inverse();
    let eye = world_from_camera.translation;
    let depth: Vec<f32> = (0..640 * 480)
        .map(|i| {
            let ray = camera.ray_direction((i % 640) as f64 + 0.5, (i / 640) as f64 + 0.5);
            let direction = world_from_camera.rotation * ray;
            let s = (y - eye.y) / direction.y;
            let hit = eye + direction * s;
            let on_wall = s > 0.0 && hit.x.abs() < 0.25 && (0.0..0.35).contains(&hit.z);
            if on_wall { (ray.z * s) as f32 } else { 0.0 }
        })
        .collect();
    let raster = |pixels| Raster { width: 640, height: 480, pixels };
    let frame = RgbdFrame {
        frame_id: 3,
        label: "wall".into(),
        camera,
        rgb: raster(vec![[0u8; 3]; 640 * 480]),
        depth: Raster { width: 640, height: 480, pixels: depth },
    };
    (
        frame,
        ObjectMask {
            obj_id: 14,
            instance: 0,
            mask: Raster { width: 640, height: 480, pixels: vec![false; 640 * 480] },
        },
    )
}

/// A wall the current camera sees between the mug and one of the two
/// handle-side views makes that view uninformative (the rendering hidden
/// behind the observed surface), so the other side wins.
#[test]
fn an_observed_wall_hides_the_view_behind_it() {
    let world = MugWorld::new();
    let current = world.camera(std::f64::consts::PI);
    let truth = current * world.world_from_object;
    let next = |azimuth: f64| current * world.camera(azimuth).inverse();
    let (left, right) = (next(std::f64::consts::FRAC_PI_2), next(-std::f64::consts::FRAC_PI_2));
    let (frame, target) = wall_frame(&current, 0.12);
    let occluders = Occluders::from_depth(&frame, &target, 2);
    assert!(occluders.len() > 1000, "the camera sees the wall: {} points", occluders.len());
    let mut planner = mug_planner(2);
    let plan = planner.score_views(3, 14, &[left, right], &[truth], Some(&occluders)).unwrap();
    assert_eq!(plan.views[0].camera_from_next, right, "{:?}", plan.views);
    assert_eq!((plan.views[1].expected_trace, plan.views[1].uninformative), (UNIFORM_ROTATION_TRACE, 1));
    // Without the wall both sides show the mug.
    let open = planner.score_views(3, 14, &[left, right], &[truth], None).unwrap();
    assert!(open.views.iter().all(|v| v.uninformative == 0), "{:?}", open.views);
}

/// A view that shows too little of the object counts as a uniform
/// rotation; the plan still ranks every candidate, in candidate order on a
/// tie; an object without a model is an error naming it.
#[test]
fn uninformative_views_count_as_uniform_and_unknown_objects_are_named() {
    let params = NbvParams::from_json(&serde_json::json!({
        "models": root().join("objects/ycbv/mug-bowl"),
        "candidates": 4,
        "hypotheses": 2,
        "workers": 1,
        "min_visible_pixels": 10_000_000,
        "inference": {"model": root().join("models/poseflow-lmo10")},
    }))
    .unwrap();
    let mut planner = NbvPlanner::load(params).unwrap();
    let world = MugWorld::new();
    let current = world.camera(0.3);
    let hypotheses = [current * world.world_from_object];
    let up = current.rotation * Vector3::z();
    let plan = planner.plan(2, 14, &hypotheses, &up, None).unwrap();
    let candidates = planner.candidates(2, 14, &hypotheses, &up).unwrap();
    // The current viewpoint first, then the sphere's four.
    assert_eq!((plan.views.len(), candidates.len()), (5, 4));
    let candidates_again = candidates.clone();
    let expected = std::iter::once(Pose::identity()).chain(candidates);
    for (view, candidate) in plan.views.iter().zip(expected) {
        assert_eq!(view.camera_from_next, candidate);
        assert_eq!((view.expected_trace, view.uninformative), (UNIFORM_ROTATION_TRACE, 1));
    }
    let err = planner.plan(2, 99, &hypotheses, &up, None).unwrap_err().to_string();
    assert!(err.starts_with("frame 2 object 99: no model of object 99"), "{err}");
    let err = planner.plan(2, 14, &[], &up, None).unwrap_err().to_string();
    assert!(err.contains("no kept hypothesis"), "{err}");
    let err = planner.score_views(2, 14, &candidates_again, &[], None).unwrap_err().to_string();
    assert!(err.contains("no kept hypothesis"), "{err}");
}

/// A frame on the side input that does not match its header is an error
/// naming the frame; the stage keeps nothing from it and plans that
/// frame's objects without occluders.
#[test]
fn a_bad_side_frame_is_named_and_leaves_no_occluders() {
    use poseflow_contracts::{FrameHeader, Header};
    use poseflow_nbv::stage::NbvStage;

    let mut stage = NbvStage::new(mug_planner(1));
    let header = FrameHeader { header: Header::new(5, 0), detection_count: 1, ..Default::default() };
    let err = stage.keep_frame(&header, &[0.0; 7]).unwrap_err().to_string();
    assert!(err.starts_with("frame 5 (side input):") && err.contains("without its occluders"), "{err}");
    assert!(stage.occluders(5, 14).is_none());
}
