//! Scores of one object instance: the BOP and paper metrics of its
//! estimate against the ground truth.
//!
//! Conventions: poses are `camera_from_object` in metres, model points in
//! the object frame in metres, errors in degrees, centimetres and pixels.
//! Every accuracy is a share in [0, 1] of the *scored poses*: the selected
//! pose alone, or every hypothesis when there is no selection (the accuracy
//! of one random sample, the paper's "None" rows).

use nalgebra::Point3;
use poseflow_geometry::metrics::{DepthImages, NearestPoints, Pinhole, add, mspd, mssd, vsd};
use poseflow_geometry::{Pose, SymmetrySet};
use poseflow_scene::{Camera, Placed, RenderModel, object_depth};
use rand::seq::index::sample;

/// n°, m cm thresholds of the accuracy columns, in report order.
pub const ACCURACY_THRESHOLDS: [(f64, f64); 4] = [(5.0, 2.0), (5.0, 5.0), (10.0, 2.0), (10.0, 5.0)];
/// A hypothesis covers a symmetric twin of the truth within this (degrees, cm).
pub const MODE_THRESHOLD: (f64, f64) = (10.0, 2.0);
/// Coverage: some hypothesis within these (degrees, cm) of the truth,
/// symmetry-aware; in report order (`coverage_10deg_5cm`, `coverage_5deg_5cm`).
pub const COVERAGE_THRESHOLDS: [(f64, f64); 2] = [(10.0, 5.0), (5.0, 5.0)];
/// ADD(-S) passes below this share of the diameter.
pub const ADD_FRACTION: f64 = 0.1;
/// BOP19: MSSD thresholds are these shares of the diameter…
pub const MSSD_FRACTIONS: [f64; 10] = [0.05, 0.10, 0.15, 0.20, 0.25, 0.30, 0.35, 0.40, 0.45, 0.50];
/// …and MSPD thresholds these pixels at a 640-pixel-wide image (scaled by
/// width / 640).
pub const MSPD_PIXELS_AT_640: [f64; 10] = [5.0, 10.0, 15.0, 20.0, 25.0, 30.0, 35.0, 40.0, 45.0, 50.0];
/// BOP19 VSD: visibility tolerance δ (metres), misalignment tolerances τ
/// (shares of the diameter) and correctness thresholds θ on the error.
pub const VSD_DELTA: f64 = 0.015;
pub const VSD_TAU_FRACTIONS: [f64; 10] = MSSD_FRACTIONS;
pub const VSD_THRESHOLDS: [f64; 10] = [0.05, 0.10, 0.15, 0.20, 0.25, 0.30, 0.35, 0.40, 0.45, 0.50];
/// VSD renders the object at every scored pose, by far the costliest
/// metric: without selection it averages over a seeded random subset of
/// this many samples (an unbiased estimate of the per-sample mean; the
/// first samples are not: the selector orders them best cluster first.
/// Measured: all 50 samples made scoring 420 instances take 8 minutes).
pub const VSD_MAX_POSES: usize = 10;

/// What the metrics need of an object.
#[derive(Debug, Clone)]
pub struct ScoredObject {
    /// Model surface points, object frame, metres: every mesh vertex, as
    /// BOP scores against its full models.
    pub points: Vec<Point3<f64>>,
    /// The same points indexed for ADD-S's nearest-point search.
    pub nearest: NearestPoints,
    /// Metres.
    pub diameter: f64,
    /// BOP-discretised symmetries (identity only for an asymmetric object).
    pub symmetries: SymmetrySet,
    /// The mesh, rendered for VSD.
    pub model: RenderModel,
}

impl ScoredObject {
    pub fn is_symmetric(&self) -> bool {
        self.symmetries.transforms().len() > 1
    }
}

/// The camera of the image, for MSPD.
#[derive(Debug, Clone, Copy)]
pub struct ImageCamera {
    pub pinhole: Pinhole,
    pub width: u32,
}

/// The test image's sensor depth (row-major, metres, 0 = no measurement)
/// and the camera that took it, for VSD.
#[derive(Debug, Clone)]
pub struct TestDepth {
    pub camera: Camera,
    pub depth: Vec<f32>,
}

impl TestDepth {
    /// Recall over BOP19's τ × θ grid of the VSD errors of `pose` against
    /// the truth's rendered depth.
    fn vsd_recall(&self, object: &ScoredObject, pose: &Pose, truth_depth: &[f32]) -> f64 {
        let estimate = object_depth(&self.camera, &Placed { model: &object.model, pose });
        let images = DepthImages {
            pinhole: Pinhole { fx: self.camera.fx, fy: self.camera.fy, cx: self.camera.cx, cy: self.camera.cy },
            width: self.camera.width as usize,
            test: &self.depth,
            estimate: &estimate,
            truth: truth_depth,
        };
        let taus = VSD_TAU_FRACTIONS.map(|f| f * object.diameter);
        let errors = vsd(&images, VSD_DELTA, &taus);
        let passed: f64 = errors.iter().map(|&e| recall_over(e, VSD_THRESHOLDS.iter().copied())).sum();
        passed / errors.len() as f64
    }
}

/// One instance's scores.
#[derive(Debug, Clone, PartialEq)]
pub struct InstanceScore {
    /// Of the selected pose (symmetry-aware): degrees, centimetres.
    pub rotation_error_deg: f64,
    pub translation_error_cm: f64,
    /// Share of the scored poses within each of [`ACCURACY_THRESHOLDS`].
    pub accuracy: [f64; 4],
    /// Share of the scored poses with ADD (ADD-S for a symmetric object)
    /// below [`ADD_FRACTION`] × diameter.
    pub add_s: f64,
    /// BOP recall averaged over the thresholds, over the scored poses.
    pub mssd_recall: f64,
    pub mspd_recall: f64,
    /// With the test image's depth: VSD recall over the scored poses.
    pub vsd_recall: Option<f64>,
    /// For a symmetric object with hypotheses: share of its symmetric twins
    /// of the truth with a hypothesis within [`MODE_THRESHOLD`].
    pub mode_recall: Option<f64>,
    /// √trace of the rotational covariance the estimate reports, degrees
    /// (none for a method that reports no covariance).
    pub rotation_spread_deg: Option<f64>,
    /// Whether some hypothesis (the kept ones; the selected pose when
    /// there are none) lies within each of [`COVERAGE_THRESHOLDS`].
    pub covered: [bool; 2],
    /// The largest rotational standard deviation of the kept hypotheses,
    /// folded by the object's symmetries, degrees (none without
    /// hypotheses).
    pub rotation_spread_max_deg: Option<f64>,
}

/// What the graph estimated for one instance.
#[derive(Debug, Clone)]
pub struct EstimatedInstance<'a> {
    pub selected: Pose,
    /// Every hypothesis the selector scored (refined ones included), best
    /// first; empty for a method that gives one pose.
    pub hypotheses: &'a [Pose],
    /// How many of the first hypotheses the selector kept (every one
    /// without selection).
    pub kept: usize,
    /// Seeds the choice of the samples VSD renders.
    pub seed: u64,
    /// Trace of the rotational covariance, rad², when reported.
    pub rotation_trace: Option<f64>,
    /// No selection: score the hypotheses, not `selected`.
    pub score_every_hypothesis: bool,
}

fn within(rotation_deg: f64, translation_cm: f64, (deg, cm): (f64, f64)) -> bool {
    rotation_deg < deg && translation_cm < cm
}

fn share(count: usize, of: usize) -> f64 {
    if of == 0 { 0.0 } else { count as f64 / of as f64 }
}

/// Mean over `thresholds` of whether `error` is below each.
fn recall_over(error: f64, thresholds: impl Iterator<Item = f64>) -> f64 {
    let (mut passed, mut total) = (0usize, 0usize);
    for threshold in thresholds {
        passed += usize::from(error < threshold);
        total += 1;
    }
    share(passed, total)
}

/// The scores of `estimate` against `truth` (VSD when the test image's
/// depth is given).
pub fn score_instance(
    estimate: &EstimatedInstance<'_>,
    truth: &Pose,
    object: &ScoredObject,
    camera: &ImageCamera,
    depth: Option<&TestDepth>,
) -> InstanceScore {
    let selected_error = object.symmetries.pose_error(&estimate.selected, truth);
    let scored: &[Pose] = if estimate.score_every_hypothesis && !estimate.hypotheses.is_empty() {
        estimate.hypotheses
    } else {
        std::slice::from_ref(&estimate.selected)
    };
    let kept = &estimate.hypotheses[..estimate.kept.min(estimate.hypotheses.len())];
    let mut accuracy = [0usize; 4];
    let (mut add_passed, mut mssd_sum, mut mspd_sum) = (0usize, 0.0, 0.0);
    let pixel_scale = f64::from(camera.width) / 640.0;
    for pose in scored {
        let error = object.symmetries.pose_error(pose, truth);
        let (deg, cm) = (error.rotation.to_degrees(), error.translation * 100.0);
        for (count, &threshold) in accuracy.iter_mut().zip(&ACCURACY_THRESHOLDS) {
            *count += usize::from(within(deg, cm, threshold));
        }
        let add_error =
            if object.is_symmetric() { object.nearest.add_s(pose, truth) } else { add(&object.points, pose, truth) };
        add_passed += usize::from(add_error < ADD_FRACTION * object.diameter);
        let mssd_error = mssd(&object.points, pose, truth, &object.symmetries);
        mssd_sum += recall_over(mssd_error, MSSD_FRACTIONS.iter().map(|f| f * object.diameter));
        let mspd_error = mspd(&object.points, pose, truth, &object.symmetries, &camera.pinhole);
        mspd_sum += recall_over(mspd_error, MSPD_PIXELS_AT_640.iter().map(|p| p * pixel_scale));
    }
    let vsd_recall = depth.map(|depth| {
        let truth_depth = object_depth(&depth.camera, &Placed { model: &object.model, pose: truth });
        let subset = vsd_subset(scored.len(), estimate.seed);
        let sum: f64 = subset.iter().map(|&k| depth.vsd_recall(object, &scored[k], &truth_depth)).sum();
        sum / subset.len() as f64
    });
    let n = scored.len();
    InstanceScore {
        rotation_error_deg: selected_error.rotation.to_degrees(),
        translation_error_cm: selected_error.translation * 100.0,
        accuracy: accuracy.map(|count| share(count, n)),
        add_s: share(add_passed, n),
        mssd_recall: mssd_sum / n as f64,
        mspd_recall: mspd_sum / n as f64,
        vsd_recall,
        mode_recall: (object.is_symmetric() && !estimate.hypotheses.is_empty())
            .then(|| mode_recall(estimate.hypotheses, truth, &object.symmetries)),
        rotation_spread_deg: estimate.rotation_trace.map(|trace| trace.max(0.0).sqrt().to_degrees()),
        covered: coverage(if kept.is_empty() { std::slice::from_ref(&estimate.selected) } else { kept }, truth, object),
        rotation_spread_max_deg: rotation_spread_max_deg(kept, &estimate.selected, object),
    }
}

/// The indices of the scored poses VSD renders: all of them up to
/// [`VSD_MAX_POSES`], else a seeded random subset of that many.
fn vsd_subset(count: usize, seed: u64) -> Vec<usize> {
    if count <= VSD_MAX_POSES {
        return (0..count).collect();
    }
    let mut rng = poseflow_geometry::sampling::seeded_rng(seed);
    sample(&mut rng, count, VSD_MAX_POSES).into_vec()
}

/// Whether some hypothesis lies within each of [`COVERAGE_THRESHOLDS`] of
/// the truth (symmetry-aware).
fn coverage(hypotheses: &[Pose], truth: &Pose, object: &ScoredObject) -> [bool; 2] {
    let errors: Vec<(f64, f64)> = hypotheses
        .iter()
        .map(|h| {
            let error = object.symmetries.pose_error(h, truth);
            (error.rotation.to_degrees(), error.translation * 100.0)
        })
        .collect();
    COVERAGE_THRESHOLDS.map(|threshold| errors.iter().any(|&(deg, cm)| within(deg, cm, threshold)))
}

/// The largest rotational standard deviation of `kept`, each folded onto
/// its symmetric twin nearest the selected pose, in degrees; none without
/// hypotheses, or (logged) when the covariance cannot be decomposed.
fn rotation_spread_max_deg(kept: &[Pose], selected: &Pose, object: &ScoredObject) -> Option<f64> {
    if kept.is_empty() {
        return None;
    }
    let rotations: Vec<_> = kept.iter().map(|p| p.rotation).collect();
    match object.symmetries.folded_max_rotation_std(&rotations, &selected.rotation) {
        Ok(std) => Some(std.to_degrees()),
        Err(err) => {
            tracing::warn!(%err, "the kept hypotheses' rotational spread: no figure");
            None
        }
    }
}

/// Share of the symmetric twins `truth · S` that some hypothesis is within
/// [`MODE_THRESHOLD`] of (plain errors: each twin is one mode).
pub fn mode_recall(hypotheses: &[Pose], truth: &Pose, symmetries: &SymmetrySet) -> f64 {
    let identity = SymmetrySet::identity_only();
    let twins: Vec<Pose> = symmetries.equivalent_poses(truth).collect();
    let covered = twins
        .iter()
        .filter(|twin| {
            hypotheses.iter().any(|h| {
                let error = identity.pose_error(h, twin);
                within(error.rotation.to_degrees(), error.translation * 100.0, MODE_THRESHOLD)
            })
        })
        .count();
    share(covered, twins.len())
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Rotation3, Vector3};
    use poseflow_geometry::models_info::ModelInfo;
    use poseflow_scene::primitives::ClutterShape;

    /// A 10 cm × 4 cm × 2 cm box's corners and face centres.
    fn box_points() -> Vec<Point3<f64>> {
        let mut points = Vec::new();
        for x in [-0.05, 0.0, 0.05] {
            for y in [-0.02, 0.02] {
                for z in [-0.01, 0.01] {
                    points.push(Point3::new(x, y, z));
                }
            }
        }
        points
    }

    /// The box's mesh, centred like its points (only VSD sees the mesh).
    fn box_model() -> RenderModel {
        let shape = ClutterShape::Box { half_extents: nalgebra::Vector3::new(0.05, 0.02, 0.01) };
        let mut mesh = shape.mesh([200, 200, 200]);
        // The clutter shape stands on z = 0.
        mesh.vertices.iter_mut().for_each(|v| v.z -= 0.01);
        RenderModel::new(mesh).unwrap()
    }

    fn object(symmetries: SymmetrySet) -> ScoredObject {
        let points = box_points();
        ScoredObject { nearest: NearestPoints::new(&points), points, diameter: 0.11, symmetries, model: box_model() }
    }

    /// The sensor sees the box at the truth and nothing else.
    fn test_depth() -> TestDepth {
        let camera = Camera { fx: 572.4, fy: 573.6, cx: 325.3, cy: 242.0, width: 640, height: 480 };
        let depth = object_depth(&camera, &Placed { model: &box_model(), pose: &truth() });
        TestDepth { camera, depth }
    }

    /// The box is the same after a half-turn about its long axis.
    fn half_turn_about_x() -> SymmetrySet {
        let info = ModelInfo {
            diameter: 0.11,
            min: None,
            size: None,
            symmetries_discrete: vec![Pose::new(
                Rotation3::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI),
                Vector3::zeros(),
            )],
            symmetries_continuous: Vec::new(),
        };
        SymmetrySet::from_model_info(&info, poseflow_geometry::symmetry::BOP_MAX_SYMMETRY_STEP)
    }

    fn camera() -> ImageCamera {
        ImageCamera { pinhole: Pinhole { fx: 572.4, fy: 573.6, cx: 325.3, cy: 242.0 }, width: 640 }
    }

    fn truth() -> Pose {
        Pose::new(Rotation3::from_euler_angles(0.3, -0.2, 0.5), Vector3::new(0.05, -0.02, 0.8))
    }

    fn selected(pose: Pose) -> EstimatedInstance<'static> {
        EstimatedInstance {
            selected: pose,
            hypotheses: &[],
            kept: 0,
            seed: 0,
            rotation_trace: None,
            score_every_hypothesis: false,
        }
    }

    fn turned(pose: &Pose, degrees: f64) -> Pose {
        Pose::new(
            pose.rotation * Rotation3::from_axis_angle(&Vector3::z_axis(), degrees.to_radians()),
            pose.translation,
        )
    }

    fn shifted(pose: &Pose, metres: f64) -> Pose {
        Pose::new(pose.rotation, pose.translation + Vector3::new(metres, 0.0, 0.0))
    }

    #[test]
    fn a_perfect_estimate_passes_everything() {
        let score =
            score_instance(&selected(truth()), &truth(), &object(SymmetrySet::identity_only()), &camera(), None);
        assert!(score.rotation_error_deg < 1e-6 && score.translation_error_cm < 1e-6);
        assert_eq!(score.accuracy, [1.0; 4]);
        assert_eq!((score.add_s, score.mssd_recall, score.mspd_recall), (1.0, 1.0, 1.0));
        assert_eq!(score.mode_recall, None);
    }

    #[test]
    fn known_errors_fall_on_the_right_side_of_each_threshold() {
        let object = object(SymmetrySet::identity_only());
        // 7° and 3 cm: only 10°5cm passes.
        let estimate = shifted(&turned(&truth(), 7.0), 0.03);
        let score = score_instance(&selected(estimate), &truth(), &object, &camera(), None);
        assert!((score.rotation_error_deg - 7.0).abs() < 1e-6, "{score:?}");
        assert!((score.translation_error_cm - 3.0).abs() < 1e-6, "{score:?}");
        assert_eq!(score.accuracy, [0.0, 0.0, 0.0, 1.0]);
        // A pure 3 cm shift: ADD = 3 cm > 1.1 cm fails; MSSD = 3 cm passes the
        // thresholds from 0.30 × 11 cm = 3.3 cm up: 5 of 10.
        let score = score_instance(&selected(shifted(&truth(), 0.03)), &truth(), &object, &camera(), None);
        assert_eq!(score.add_s, 0.0);
        assert!((score.mssd_recall - 0.5).abs() < 1e-12, "{score:?}");
        // At 0.8 m a 3 cm sideways shift is fx·0.03/0.8 ≈ 21.5 px: MSPD passes
        // from 25 px: 6 of 10.
        assert!((score.mspd_recall - 0.6).abs() < 1e-12, "{score:?}");
    }

    #[test]
    fn a_symmetric_twin_scores_zero_error_and_an_asymmetric_object_does_not() {
        let twin = Pose::new(
            truth().rotation * Rotation3::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI),
            truth().translation,
        );
        let symmetric = score_instance(&selected(twin), &truth(), &object(half_turn_about_x()), &camera(), None);
        assert!(symmetric.rotation_error_deg < 1e-6, "{symmetric:?}");
        assert_eq!(symmetric.accuracy, [1.0; 4]);
        assert_eq!((symmetric.add_s, symmetric.mssd_recall, symmetric.mspd_recall), (1.0, 1.0, 1.0));
        let asymmetric =
            score_instance(&selected(twin), &truth(), &object(SymmetrySet::identity_only()), &camera(), None);
        assert!((asymmetric.rotation_error_deg - 180.0).abs() < 1e-6, "{asymmetric:?}");
        assert_eq!(asymmetric.accuracy, [0.0; 4]);
        assert_eq!(asymmetric.add_s, 0.0);
    }

    #[test]
    fn without_selection_accuracy_is_the_share_of_good_samples() {
        let hypotheses = [truth(), turned(&truth(), 3.0), turned(&truth(), 8.0), turned(&truth(), 40.0)];
        let estimate = EstimatedInstance {
            selected: turned(&truth(), 40.0),
            hypotheses: &hypotheses,
            kept: hypotheses.len(),
            seed: 0,
            rotation_trace: Some(0.01),
            score_every_hypothesis: true,
        };
        let score = score_instance(&estimate, &truth(), &object(SymmetrySet::identity_only()), &camera(), None);
        assert_eq!(score.accuracy, [0.5, 0.5, 0.75, 0.75]);
        assert_eq!(score.vsd_recall, None);
        assert!((score.rotation_error_deg - 40.0).abs() < 1e-6);
        assert!((score.rotation_spread_deg.unwrap() - 0.1f64.to_degrees()).abs() < 1e-9);
    }

    #[test]
    fn vsd_sees_the_visible_surface_only() {
        let depth = test_depth();
        let object = object(SymmetrySet::identity_only());
        let score = |pose: Pose| score_instance(&selected(pose), &truth(), &object, &camera(), Some(&depth));
        assert_eq!(score(truth()).vsd_recall, Some(1.0));
        // A half-turn about the box's long axis leaves the same surface: VSD
        // needs no symmetry list, though the other metrics here, given none,
        // call it 180° off.
        let turned_over = Pose::new(
            truth().rotation * Rotation3::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI),
            truth().translation,
        );
        let twin = score(turned_over);
        assert_eq!(twin.accuracy, [0.0; 4]);
        assert!(twin.vsd_recall.unwrap() > 0.99, "{twin:?}");
        // Sideways shifts: the overlap shrinks, so recall falls, to 0 once
        // less than half the visible surface overlaps.
        let recall = |metres| score(shifted(&truth(), metres)).vsd_recall.unwrap();
        let (near, far) = (recall(0.005), recall(0.01));
        assert!(0.0 < far && far < near && near < 1.0, "{near} {far}");
        assert_eq!(recall(0.03), 0.0);
        // Without selection VSD averages a random subset of the samples, not
        // the first ones (the selector puts its best cluster first): with
        // the good samples first and as many bad ones after them, the first
        // VSD_MAX_POSES alone would score 1.
        let mut samples = vec![truth(); VSD_MAX_POSES];
        samples.extend(vec![shifted(&truth(), 0.03); VSD_MAX_POSES]);
        let recall_with_seed = |seed| {
            let every = EstimatedInstance {
                selected: truth(),
                hypotheses: &samples,
                kept: samples.len(),
                seed,
                rotation_trace: None,
                score_every_hypothesis: true,
            };
            score_instance(&every, &truth(), &object, &camera(), Some(&depth)).vsd_recall.unwrap()
        };
        let recalls: Vec<f64> = (0..8).map(recall_with_seed).collect();
        let mean = recalls.iter().sum::<f64>() / recalls.len() as f64;
        assert!(recalls.iter().all(|&r| r < 1.0), "{recalls:?}");
        assert!((mean - 0.5).abs() < 0.15, "{recalls:?}");
        assert_eq!(recall_with_seed(3), recall_with_seed(3));
    }

    #[test]
    fn coverage_and_spread_come_from_the_kept_hypotheses() {
        let object = object(SymmetrySet::identity_only());
        // Kept: 30° and 40° off; scored but not kept: the truth itself.
        let hypotheses = [turned(&truth(), 30.0), turned(&truth(), 40.0), truth()];
        let estimate = |kept| EstimatedInstance {
            selected: turned(&truth(), 35.0),
            hypotheses: &hypotheses,
            kept,
            seed: 0,
            rotation_trace: None,
            score_every_hypothesis: false,
        };
        let score = score_instance(&estimate(2), &truth(), &object, &camera(), None);
        assert_eq!(score.covered, [false, false]);
        // ±5° about one axis around their mean: a largest std of 5°.
        assert!((score.rotation_spread_max_deg.unwrap() - 5.0).abs() < 1e-6, "{score:?}");
        let every = score_instance(&estimate(3), &truth(), &object, &camera(), None);
        assert_eq!(every.covered, [true, true]);
        assert!(every.rotation_spread_max_deg.unwrap() > 10.0, "{every:?}");
        // Without hypotheses the selected pose is the one hypothesis.
        let single = score_instance(&selected(turned(&truth(), 7.0)), &truth(), &object, &camera(), None);
        assert_eq!((single.covered, single.rotation_spread_max_deg), ([true, false], None));
    }

    #[test]
    fn a_symmetric_twin_among_the_kept_hypotheses_is_neither_spread_nor_a_miss() {
        let object = object(half_turn_about_x());
        let twin = |pose: Pose| {
            Pose::new(
                pose.rotation * Rotation3::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI),
                pose.translation,
            )
        };
        let hypotheses = [turned(&truth(), 2.0), twin(turned(&truth(), -2.0))];
        let estimate = EstimatedInstance {
            selected: truth(),
            hypotheses: &hypotheses,
            kept: 2,
            seed: 0,
            rotation_trace: None,
            score_every_hypothesis: false,
        };
        let score = score_instance(&estimate, &truth(), &object, &camera(), None);
        assert_eq!(score.covered, [true, true]);
        assert!((score.rotation_spread_max_deg.unwrap() - 2.0).abs() < 1e-6, "{score:?}");
    }

    #[test]
    fn mode_recall_counts_the_twins_with_a_sample_near_them() {
        let twin = Pose::new(
            truth().rotation * Rotation3::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI),
            truth().translation,
        );
        let symmetries = half_turn_about_x();
        assert_eq!(mode_recall(&[turned(&truth(), 4.0)], &truth(), &symmetries), 0.5);
        assert_eq!(mode_recall(&[turned(&truth(), 4.0), turned(&twin, -4.0)], &truth(), &symmetries), 1.0);
        // 3 cm off the twin is outside 2 cm.
        assert_eq!(mode_recall(&[shifted(&twin, 0.03)], &truth(), &symmetries), 0.0);
    }
}
