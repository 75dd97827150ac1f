//! The next-best-view stage's message side and its planner on the default
//! model (these integration tests also make cargo build the `nbv` binary
//! the end-to-end graph tests launch).

use std::path::PathBuf;

use nalgebra::{Point3, Rotation3, Vector3};
use poseflow_contracts::{CANDIDATE_LEN, MessageHeader, NextViewHeader, POSE_LEN};
use poseflow_geometry::Pose;
use poseflow_nbv::stage::next_view_message;
use poseflow_nbv::{NbvParams, NbvPlanner, NextViewPlan, PlanCost, ScoredView, UNIFORM_ROTATION_TRACE};
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
        "models": root().join("objects/ycbv/models"),
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
    let plan = planner.score_views(1, 14, &views, &[truth]).unwrap();
    let hidden = plan.views.iter().find(|v| v.camera_from_next == views[0]).unwrap();
    assert_ne!(plan.views[0].camera_from_next, views[0], "{:?}", plan.views);
    assert!(plan.views[0].expected_trace < hidden.expected_trace, "{:?}", plan.views);
    assert!(plan.views.iter().all(|v| v.uninformative == 0 && v.expected_trace < UNIFORM_ROTATION_TRACE));
    assert_eq!(plan.cost.views, 3);

    let again = mug_planner(1).score_views(1, 14, &views, &[truth]).unwrap();
    assert_eq!(again.views, plan.views);
}

/// A view that shows too little of the object counts as a uniform
/// rotation; the plan still ranks every candidate, in candidate order on a
/// tie; an object without a model is an error naming it.
#[test]
fn uninformative_views_count_as_uniform_and_unknown_objects_are_named() {
    let params = NbvParams::from_json(&serde_json::json!({
        "models": root().join("objects/ycbv/models"),
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
    let plan = planner.plan(2, 14, &hypotheses, &up).unwrap();
    let candidates = planner.candidates(2, 14, &hypotheses, &up).unwrap();
    // The current viewpoint first, then the sphere's four.
    assert_eq!((plan.views.len(), candidates.len()), (5, 4));
    let expected = std::iter::once(Pose::identity()).chain(candidates);
    for (view, candidate) in plan.views.iter().zip(expected) {
        assert_eq!(view.camera_from_next, candidate);
        assert_eq!((view.expected_trace, view.uninformative), (UNIFORM_ROTATION_TRACE, 1));
    }
    let err = planner.plan(2, 99, &hypotheses, &up).unwrap_err().to_string();
    assert!(err.starts_with("frame 2 object 99: no model of object 99"), "{err}");
    let err = planner.plan(2, 14, &[], &up).unwrap_err().to_string();
    assert!(err.contains("no kept hypothesis"), "{err}");
}
