//! The track check: in a tracking graph, whether each selected pose still
//! explains its observation, decided per object with hysteresis, so the
//! sampler knows when to start an object afresh from the prior.
//!
//! Evidence per estimate (all from what the selector already has):
//! - the valid depth points the Observation had;
//! - the share of scored points within `inlier_distance` of the object's
//!   surface at the selected pose (needs the object model);
//! - the rotational spread of the kept hypotheses, √trace of their
//!   rotational covariance;
//! - the jump of the selected pose from where the motion so far predicts
//!   it (constant velocity over the last two accepted estimates).
//!
//! Spread and jump are only meaningful while tracking: an estimate from the
//! prior of a symmetric object spreads over its symmetric poses, and an
//! object being re-acquired has no motion to compare with. An estimate made
//! while the object is unsure or lost is judged by its points and its fit.
//!
//! | state      | passes                       | soft failure                    | hard failure |
//! |------------|------------------------------|---------------------------------|--------------|
//! | acquiring  | tracking                     | lost                            | lost         |
//! | tracking   | tracking                     | unsure (1)                      | lost         |
//! | unsure (n) | tracking                     | unsure (n+1), lost at `lost_after` | lost      |
//! | lost       | tracking, `REINITIALISED`    | lost                            | lost         |

use std::collections::{HashMap, VecDeque};

use nalgebra::Point3;
use poseflow_contracts::flags;
use poseflow_geometry::{Pose, so3};
use serde::Deserialize;

use crate::SelectorError;

/// The selector's `tracking` parameters.
///
/// | key | meaning | default |
/// |---|---|---|
/// | `check` | judge every estimate and flag `LOST`, `UNSURE`, `REINITIALISED` | false |
/// | `min_points` | fewer valid depth points than this cannot confirm a pose (hard) | 24 |
/// | `inlier_distance` | a scored point within this of the surface is an inlier, metres | 0.01 |
/// | `min_inlier_share` | a smaller share of inliers is a poor fit (soft) | 0.6 |
/// | `lost_inlier_share` | a smaller share is a lost fit (hard) | 0.3 |
/// | `max_spread_deg` | tracking: a wider rotational spread of the kept hypotheses is unsure (soft) | 45 |
/// | `max_jump_deg` | tracking: a larger turn away from the predicted pose is a jump (soft) | 30 |
/// | `max_jump_m` | tracking: a larger shift away from the predicted position is a jump (soft) | 0.05 |
/// | `lost_after` | consecutive soft failures that declare the object lost | 2 |
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TrackCheckParams {
    #[serde(default)]
    pub check: bool,
    #[serde(default = "default_min_points")]
    pub min_points: usize,
    #[serde(default = "default_inlier_distance")]
    pub inlier_distance: f64,
    #[serde(default = "default_min_inlier_share")]
    pub min_inlier_share: f64,
    #[serde(default = "default_lost_inlier_share")]
    pub lost_inlier_share: f64,
    #[serde(default = "default_max_spread_deg")]
    pub max_spread_deg: f64,
    #[serde(default = "default_max_jump_deg")]
    pub max_jump_deg: f64,
    #[serde(default = "default_max_jump_m")]
    pub max_jump_m: f64,
    #[serde(default = "default_lost_after")]
    pub lost_after: u32,
}

fn default_min_points() -> usize {
    24
}
fn default_inlier_distance() -> f64 {
    0.01
}
fn default_min_inlier_share() -> f64 {
    0.6
}
fn default_lost_inlier_share() -> f64 {
    0.3
}
fn default_max_spread_deg() -> f64 {
    45.0
}
fn default_max_jump_deg() -> f64 {
    30.0
}
fn default_max_jump_m() -> f64 {
    0.05
}
fn default_lost_after() -> u32 {
    2
}

impl Default for TrackCheckParams {
    fn default() -> Self {
        serde_json::from_value(serde_json::json!({})).expect("every field has a default")
    }
}

impl TrackCheckParams {
    pub fn validate(&self) -> Result<(), SelectorError> {
        let positive = |x: f64| x.is_finite() && x > 0.0;
        let share = |x: f64| (0.0..=1.0).contains(&x);
        let checks: [(&'static str, bool, String); 6] = [
            (
                "tracking.inlier_distance",
                positive(self.inlier_distance),
                format!("{}: expected metres > 0", self.inlier_distance),
            ),
            (
                "tracking.min_inlier_share / lost_inlier_share",
                share(self.min_inlier_share)
                    && share(self.lost_inlier_share)
                    && self.lost_inlier_share <= self.min_inlier_share,
                format!(
                    "{} / {}: expected shares in [0, 1], the lost one at most the minimum",
                    self.min_inlier_share, self.lost_inlier_share
                ),
            ),
            (
                "tracking.max_spread_deg",
                positive(self.max_spread_deg),
                format!("{}: expected degrees > 0", self.max_spread_deg),
            ),
            (
                "tracking.max_jump_deg",
                positive(self.max_jump_deg) && self.max_jump_deg <= 180.0,
                format!("{}: expected degrees in (0, 180]", self.max_jump_deg),
            ),
            ("tracking.max_jump_m", positive(self.max_jump_m), format!("{}: expected metres > 0", self.max_jump_m)),
            ("tracking.lost_after", self.lost_after >= 1, format!("{}: expected at least 1", self.lost_after)),
        ];
        match checks.into_iter().find(|(_, ok, _)| !ok) {
            Some((key, _, detail)) => Err(SelectorError::Params { key, detail }),
            None => Ok(()),
        }
    }
}

/// What one estimate is judged on.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Evidence {
    pub frame_id: u64,
    /// Valid depth points of the Observation.
    pub observed_points: usize,
    /// Share of the scored points on the surface at `pose`; `None` without
    /// an object model.
    pub inlier_share: Option<f64>,
    /// √trace of the kept hypotheses' rotational covariance, degrees.
    pub spread_deg: f64,
    /// The selected pose (camera frame).
    pub pose: Pose,
}

/// Why an estimate failed the check.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Failure {
    TooFewPoints { points: usize },
    LostFit { inlier_share: f64 },
    PoorFit { inlier_share: f64 },
    Spread { degrees: f64 },
    Jump { degrees: f64, metres: f64 },
}

impl Failure {
    /// A hard failure declares the object lost at once.
    pub fn is_hard(&self) -> bool {
        matches!(self, Self::TooFewPoints { .. } | Self::LostFit { .. })
    }
}

impl std::fmt::Display for Failure {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::TooFewPoints { points } => write!(f, "{points} valid points (below tracking.min_points)"),
            Self::LostFit { inlier_share } => {
                write!(f, "{:.0} % of points on the surface (below tracking.lost_inlier_share)", inlier_share * 100.0)
            }
            Self::PoorFit { inlier_share } => {
                write!(f, "{:.0} % of points on the surface (below tracking.min_inlier_share)", inlier_share * 100.0)
            }
            Self::Spread { degrees } => write!(f, "hypotheses spread {degrees:.1}° (over tracking.max_spread_deg)"),
            Self::Jump { degrees, metres } => write!(
                f,
                "jumped {degrees:.1}° / {:.1} cm from the predicted pose (over tracking.max_jump_deg / max_jump_m)",
                metres * 100.0
            ),
        }
    }
}

/// Where an object's track stands.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TrackState {
    /// No estimate has passed yet.
    Acquiring,
    Tracking,
    /// This many consecutive soft failures.
    Unsure(u32),
    Lost,
}

/// The check's outcome for one estimate.
#[derive(Debug, Clone, PartialEq)]
pub struct Verdict {
    pub before: TrackState,
    pub after: TrackState,
    pub failures: Vec<Failure>,
    /// The turn (degrees) and shift (metres) from the predicted pose, when
    /// the jump was measured.
    pub jump: Option<(f64, f64)>,
}

impl Verdict {
    /// The Estimate header's bits for this verdict ([`flags::LOST`],
    /// [`flags::UNSURE`], [`flags::REINITIALISED`]).
    pub fn flags(&self) -> u32 {
        match (self.before, self.after) {
            (_, TrackState::Lost) => flags::LOST,
            (_, TrackState::Unsure(_)) => flags::UNSURE,
            (TrackState::Lost, TrackState::Tracking) => flags::REINITIALISED,
            _ => 0,
        }
    }
}

/// One object's track.
#[derive(Debug, Clone)]
struct Track {
    state: TrackState,
    /// The last two estimates that passed, oldest first.
    accepted: VecDeque<(u64, Pose)>,
    last_frame: u64,
}

/// The per-object state machine (module docs).
#[derive(Debug, Clone)]
pub struct TrackMonitor {
    params: TrackCheckParams,
    tracks: HashMap<u32, Track>,
}

impl TrackMonitor {
    pub fn new(params: TrackCheckParams) -> Self {
        Self { params, tracks: HashMap::new() }
    }

    pub fn params(&self) -> &TrackCheckParams {
        &self.params
    }

    /// Forgets every track (an upstream restart: the same ids may show
    /// another scene).
    pub fn reset(&mut self) {
        self.tracks.clear();
    }

    /// Judges one estimate of `object` and moves its track on.
    pub fn check(&mut self, object: u32, evidence: &Evidence) -> Verdict {
        let fresh = Track { state: TrackState::Acquiring, accepted: VecDeque::new(), last_frame: evidence.frame_id };
        let track = self.tracks.entry(object).or_insert_with(|| fresh.clone());
        if evidence.frame_id < track.last_frame {
            // The source numbered from the start again: another run.
            *track = fresh;
        }
        track.last_frame = evidence.frame_id;
        let before = track.state;
        let params = &self.params;
        let mut failures = Vec::new();
        if evidence.observed_points < params.min_points {
            failures.push(Failure::TooFewPoints { points: evidence.observed_points });
        }
        if let Some(inlier_share) = evidence.inlier_share {
            if inlier_share < params.lost_inlier_share {
                failures.push(Failure::LostFit { inlier_share });
            } else if inlier_share < params.min_inlier_share {
                failures.push(Failure::PoorFit { inlier_share });
            }
        }
        let mut jump = None;
        if before == TrackState::Tracking {
            if evidence.spread_deg > params.max_spread_deg {
                failures.push(Failure::Spread { degrees: evidence.spread_deg });
            }
            if let Some(predicted) = predict(&track.accepted, evidence.frame_id) {
                let degrees = so3::geodesic_angle(&predicted.rotation, &evidence.pose.rotation).to_degrees();
                let metres = (predicted.translation - evidence.pose.translation).norm();
                jump = Some((degrees, metres));
                if degrees > params.max_jump_deg || metres > params.max_jump_m {
                    failures.push(Failure::Jump { degrees, metres });
                }
            }
        }
        let after = if failures.iter().any(Failure::is_hard) {
            TrackState::Lost
        } else if failures.is_empty() {
            TrackState::Tracking
        } else {
            match before {
                TrackState::Tracking => TrackState::Unsure(1),
                TrackState::Unsure(n) if n + 1 < params.lost_after => TrackState::Unsure(n + 1),
                _ => TrackState::Lost,
            }
        };
        // A lost object's motion history no longer says where it is.
        if after == TrackState::Lost {
            track.accepted.clear();
        }
        if after == TrackState::Tracking {
            if before != TrackState::Tracking {
                track.accepted.clear();
            }
            track.accepted.push_back((evidence.frame_id, evidence.pose));
            if track.accepted.len() > 2 {
                track.accepted.pop_front();
            }
        }
        track.state = after;
        Verdict { before, after, failures, jump }
    }
}

/// Where constant velocity over the accepted estimates puts the object at
/// `frame`: the last pose moved on by the last per-frame motion (camera
/// frame), or the last pose when there is only one.
fn predict(accepted: &VecDeque<(u64, Pose)>, frame: u64) -> Option<Pose> {
    let &(last_frame, last) = accepted.back()?;
    let Some(&(first_frame, first)) = accepted.iter().rev().nth(1) else { return Some(last) };
    let (gap, ahead) = (last_frame.saturating_sub(first_frame), frame.saturating_sub(last_frame));
    if gap == 0 {
        return Some(last);
    }
    let scale = ahead as f64 / gap as f64;
    let turn = so3::log(&(last.rotation * first.rotation.inverse())) * scale;
    let shift = (last.translation - first.translation) * scale;
    Some(Pose::new(so3::exp(&turn) * last.rotation, last.translation + shift))
}

/// Share of `points` (camera frame) within `distance` of the surface at
/// `pose`, by `residual` of model-frame points.
pub fn inlier_share(pose: &Pose, points: &[Point3<f64>], distance: f64, residual: impl Fn(&Point3<f64>) -> f64) -> f64 {
    if points.is_empty() {
        return 0.0;
    }
    let inverse = pose.inverse();
    let inliers = points.iter().filter(|x| residual(&inverse.transform_point(x)).abs() <= distance).count();
    inliers as f64 / points.len() as f64
}

/// Share of the inliers (points within `distance` of the surface at
/// `pose`) whose surface there faces the camera (at the origin), by the
/// gradient of `signed` at model-frame points. Recorded, not yet judged:
/// a pose that fits the points onto the object's far side would show here.
pub fn facing_share(
    pose: &Pose,
    points: &[Point3<f64>],
    distance: f64,
    signed: impl Fn(&Point3<f64>) -> (f64, nalgebra::Vector3<f64>),
) -> f64 {
    let inverse = pose.inverse();
    let (mut inliers, mut facing) = (0usize, 0usize);
    for x in points {
        let (value, gradient) = signed(&inverse.transform_point(x));
        if value.abs() <= distance {
            inliers += 1;
            facing += usize::from((pose.rotation * gradient).dot(&-x.coords) > 0.0);
        }
    }
    if inliers == 0 { 0.0 } else { facing as f64 / inliers as f64 }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Rotation3, Vector3};
    use proptest::prelude::*;

    fn evidence(frame_id: u64, inlier_share: f64, pose: Pose) -> Evidence {
        Evidence { frame_id, observed_points: 500, inlier_share: Some(inlier_share), spread_deg: 3.0, pose }
    }

    fn turned(degrees: f64) -> Pose {
        Pose::new(Rotation3::from_axis_angle(&Vector3::z_axis(), degrees.to_radians()), Vector3::new(0.0, 0.0, 0.8))
    }

    fn monitor() -> TrackMonitor {
        TrackMonitor::new(TrackCheckParams { check: true, ..Default::default() })
    }

    #[test]
    fn a_good_track_stays_tracking_without_flags() {
        let mut monitor = monitor();
        for frame in 0..20 {
            let verdict = monitor.check(1, &evidence(frame, 0.95, turned(frame as f64 * 2.0)));
            assert_eq!(verdict.after, TrackState::Tracking, "{verdict:?}");
            assert_eq!(verdict.flags(), 0);
        }
    }

    #[test]
    fn one_poor_frame_is_unsure_and_two_are_lost_then_a_good_one_reinitialises() {
        let mut monitor = monitor();
        monitor.check(1, &evidence(0, 0.9, turned(0.0)));
        let unsure = monitor.check(1, &evidence(1, 0.5, turned(0.0)));
        assert_eq!((unsure.after, unsure.flags()), (TrackState::Unsure(1), flags::UNSURE));
        // Hysteresis: a good frame after one poor one carries on.
        assert_eq!(monitor.check(1, &evidence(2, 0.9, turned(0.0))).flags(), 0);
        monitor.check(1, &evidence(3, 0.5, turned(0.0)));
        let lost = monitor.check(1, &evidence(4, 0.5, turned(0.0)));
        assert_eq!((lost.after, lost.flags()), (TrackState::Lost, flags::LOST));
        let back = monitor.check(1, &evidence(5, 0.9, turned(90.0)));
        assert_eq!((back.after, back.flags()), (TrackState::Tracking, flags::REINITIALISED));
        // Re-acquired far from the old pose: its motion history starts again.
        assert_eq!(monitor.check(1, &evidence(6, 0.9, turned(91.0))).flags(), 0);
    }

    #[test]
    fn a_lost_fit_or_too_few_points_lose_the_object_at_once() {
        let mut monitor = monitor();
        monitor.check(1, &evidence(0, 0.9, turned(0.0)));
        assert_eq!(monitor.check(1, &evidence(1, 0.1, turned(0.0))).flags(), flags::LOST);
        let mut hidden = evidence(2, 0.9, turned(0.0));
        hidden.observed_points = 3;
        let verdict = monitor.check(1, &hidden);
        assert_eq!(verdict.failures, vec![Failure::TooFewPoints { points: 3 }]);
        assert_eq!(verdict.flags(), flags::LOST);
    }

    #[test]
    fn the_jump_is_measured_from_constant_velocity() {
        let mut monitor = monitor();
        // 10° per frame is motion, not a jump.
        for frame in 0..5 {
            let verdict = monitor.check(1, &evidence(frame, 0.9, turned(frame as f64 * 10.0)));
            assert_eq!(verdict.flags(), 0, "{verdict:?}");
            if frame >= 2 {
                let (degrees, _) = verdict.jump.unwrap();
                assert!(degrees < 1e-6, "{degrees}");
            }
        }
        // Frame 6 after a skipped frame: predicted at 60°.
        let verdict = monitor.check(1, &evidence(6, 0.9, turned(60.0)));
        assert!(verdict.jump.unwrap().0 < 1e-6, "{verdict:?}");
        // A flip that fits well is still a jump.
        let flipped = monitor.check(1, &evidence(7, 0.95, turned(70.0 + 117.0)));
        assert!(matches!(flipped.failures[..], [Failure::Jump { .. }]), "{flipped:?}");
        assert_eq!(flipped.flags(), flags::UNSURE);
    }

    #[test]
    fn spread_and_jump_are_not_held_against_an_estimate_from_the_prior() {
        let mut monitor = monitor();
        let mut first = evidence(0, 0.9, turned(0.0));
        first.spread_deg = 120.0;
        assert_eq!(monitor.check(1, &first).after, TrackState::Tracking);
        let mut wide = evidence(1, 0.9, turned(0.0));
        wide.spread_deg = 120.0;
        assert!(matches!(monitor.check(1, &wide).failures[..], [Failure::Spread { .. }]));
    }

    #[test]
    fn objects_and_runs_are_tracked_apart() {
        let mut monitor = monitor();
        monitor.check(1, &evidence(5, 0.9, turned(0.0)));
        assert_eq!(monitor.check(2, &evidence(5, 0.1, turned(0.0))).flags(), flags::LOST);
        assert_eq!(monitor.check(1, &evidence(6, 0.9, turned(1.0))).flags(), 0);
        // Frame ids from the start again: a new run, acquired afresh.
        let again = monitor.check(1, &evidence(0, 0.9, turned(150.0)));
        assert_eq!((again.before, again.after), (TrackState::Acquiring, TrackState::Tracking));
    }

    #[test]
    fn inlier_share_counts_points_on_the_surface() {
        // A unit sphere's surface distance; points at radius 1 and 1.5.
        let sphere = |y: &Point3<f64>| y.coords.norm() - 1.0;
        let pose = Pose::new(Rotation3::identity(), Vector3::new(0.0, 0.0, 2.0));
        let points: Vec<Point3<f64>> =
            [1.0, 1.0, 1.0, 1.5].iter().map(|r| pose.transform_point(&Point3::new(*r, 0.0, 0.0))).collect();
        assert_eq!(inlier_share(&pose, &points, 0.01, sphere), 0.75);
        assert_eq!(inlier_share(&pose, &[], 0.01, sphere), 0.0);
    }

    #[test]
    fn facing_share_tells_the_near_side_from_the_far_side() {
        // A unit sphere 3 m in front of the camera: its near cap faces the
        // camera, its far cap faces away.
        let sphere = |y: &Point3<f64>| (y.coords.norm() - 1.0, y.coords.normalize());
        let pose = Pose::new(Rotation3::identity(), Vector3::new(0.0, 0.0, 3.0));
        let near = [Point3::new(0.0, 0.0, 2.0), Point3::new(0.1, 0.0, 2.005)];
        let far = [Point3::new(0.0, 0.0, 4.0)];
        assert_eq!(facing_share(&pose, &near, 0.01, sphere), 1.0);
        assert_eq!(facing_share(&pose, &far, 0.01, sphere), 0.0);
        assert_eq!(facing_share(&pose, &[near[0], far[0]], 0.01, sphere), 0.5);
    }

    #[test]
    fn bad_parameters_are_named() {
        let mut params = TrackCheckParams { lost_inlier_share: 0.8, ..Default::default() };
        let err = params.validate().unwrap_err().to_string();
        assert!(err.contains("tracking.min_inlier_share / lost_inlier_share"), "{err}");
        params = TrackCheckParams { lost_after: 0, ..Default::default() };
        assert!(params.validate().unwrap_err().to_string().contains("tracking.lost_after"));
    }

    proptest! {
        /// Whatever the evidence, the flags are one of the four outcomes and
        /// agree with the state: LOST exactly when lost, REINITIALISED only
        /// out of lost, and a hard failure always loses the object.
        #[test]
        fn flags_follow_the_state(
            steps in proptest::collection::vec((0usize..600, 0.0f64..1.0, 0.0f64..90.0, -180.0f64..180.0), 1..40),
        ) {
            let mut monitor = monitor();
            for (frame, (points, share, spread, angle)) in steps.into_iter().enumerate() {
                let mut e = evidence(frame as u64, share, turned(angle));
                e.observed_points = points;
                e.spread_deg = spread;
                let verdict = monitor.check(7, &e);
                let flags = verdict.flags();
                prop_assert!([0, flags::LOST, flags::UNSURE, flags::REINITIALISED].contains(&flags));
                prop_assert_eq!(flags == flags::LOST, verdict.after == TrackState::Lost);
                if flags == flags::REINITIALISED {
                    prop_assert_eq!(verdict.before, TrackState::Lost);
                }
                if verdict.failures.iter().any(Failure::is_hard) {
                    prop_assert_eq!(verdict.after, TrackState::Lost);
                }
                if verdict.failures.is_empty() {
                    prop_assert_eq!(verdict.after, TrackState::Tracking);
                }
            }
        }
    }
}
