//! Symmetry-aware pose errors.
//!
//! A symmetric object has a set of object-frame transforms `S` under which it
//! looks the same, so the poses `T` and `T · S` are equally correct. Errors
//! are the minimum over that set, with continuous symmetries discretised as
//! the BOP toolkit does (`bop_toolkit_lib.misc.get_symmetry_transformations`).

use nalgebra::{Rotation3, Vector3};

use crate::models_info::ModelInfo;
use crate::{GeometryError, KarcherOptions, Pose, PoseStatistics, so3};

/// The BOP toolkit's default `max_sym_disc_step`: the largest distance a
/// surface point may move between two discretised symmetry rotations, as a
/// fraction of the object diameter. It gives ⌈π / 0.01⌉ = 315 rotations
/// (1.14° apart) per continuous axis.
pub const BOP_MAX_SYMMETRY_STEP: f64 = 0.01;

/// All transforms `S` (object frame, metres) with `T ≅ T · S`, identity first.
#[derive(Debug, Clone, PartialEq)]
pub struct SymmetrySet {
    transforms: Vec<Pose>,
}

/// The error of an estimate against the closest symmetric twin of the truth.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SymmetricError {
    /// Geodesic angle in radians, minimised over the symmetry set.
    pub rotation: f64,
    /// Translation error in metres against the twin that minimises `rotation`.
    pub translation: f64,
    /// Index into [`SymmetrySet::transforms`] of that twin.
    pub symmetry_index: usize,
}

impl Default for SymmetrySet {
    fn default() -> Self {
        Self::identity_only()
    }
}

impl SymmetrySet {
    /// An asymmetric object: only the identity.
    pub fn identity_only() -> Self {
        Self { transforms: vec![Pose::identity()] }
    }

    /// The BOP discretisation: each continuous symmetry becomes
    /// `n = ⌈π / max_step⌉` rotations by `i · 2π/n` about its axis through its
    /// offset, combined with every discrete symmetry (and the identity).
    ///
    /// Unlike older bop_toolkit releases, the rotation `i = 0` is kept, so the
    /// identity is always a member and a perfect estimate has error exactly 0.
    pub fn from_model_info(info: &ModelInfo, max_step: f64) -> Self {
        let mut discrete = vec![Pose::identity()];
        discrete.extend(info.symmetries_discrete.iter().copied());

        let steps = (std::f64::consts::PI / max_step).ceil().max(1.0) as usize;
        let continuous: Vec<Pose> = info
            .symmetries_continuous
            .iter()
            .flat_map(|sym| {
                (0..steps).map(move |i| {
                    let angle = i as f64 * std::f64::consts::TAU / steps as f64;
                    let rotation = so3::exp(&(sym.axis.into_inner() * angle));
                    // Rotation about the axis through `offset`, not the origin.
                    Pose::new(rotation, sym.offset - rotation * sym.offset)
                })
            })
            .collect();

        let transforms = if continuous.is_empty() {
            discrete
        } else {
            discrete.iter().flat_map(|d| continuous.iter().map(move |c| *c * *d)).collect()
        };
        Self { transforms }
    }

    pub fn transforms(&self) -> &[Pose] {
        &self.transforms
    }

    /// The poses equivalent to `truth`: `truth · S` for every `S`.
    pub fn equivalent_poses<'a>(&'a self, truth: &'a Pose) -> impl Iterator<Item = Pose> + 'a {
        self.transforms.iter().map(move |s| *truth * *s)
    }

    /// `min_S θ(R_est, R_truth · R_S)` in radians.
    pub fn rotation_error(&self, estimate: &Rotation3<f64>, truth: &Rotation3<f64>) -> f64 {
        self.transforms
            .iter()
            .map(|s| so3::geodesic_angle(estimate, &(truth * s.rotation)))
            .fold(f64::INFINITY, f64::min)
    }

    /// The spread of `rotations` modulo the symmetries (rad²): the mean
    /// squared angle from their medoid (the rotation whose sum of squared
    /// symmetric distances to the others is least) to each rotation's twin
    /// nearest it. For an asymmetric object it is tr Σ_R about the medoid,
    /// for a symmetric one it does not count the symmetry as uncertainty.
    /// 0 for no rotations.
    pub fn folded_rotation_spread(&self, rotations: &[Rotation3<f64>]) -> f64 {
        let squared_from =
            |centre: &Rotation3<f64>| -> f64 { rotations.iter().map(|r| self.rotation_error(r, centre).powi(2)).sum() };
        let least = rotations.iter().map(squared_from).fold(f64::INFINITY, f64::min);
        if rotations.is_empty() { 0.0 } else { least / rotations.len() as f64 }
    }

    /// The twin `pose · S` whose rotation is nearest `reference`: a
    /// hypothesis expressed in the same symmetric "branch" as the reference,
    /// so spreads and means do not count the symmetry as uncertainty.
    pub fn nearest_twin(&self, pose: &Pose, reference: &Rotation3<f64>) -> Pose {
        let mut best = (f64::INFINITY, *pose);
        for twin in self.equivalent_poses(pose) {
            let angle = so3::geodesic_angle(&twin.rotation, reference);
            if angle < best.0 {
                best = (angle, twin);
            }
        }
        best.1
    }

    /// Each of `poses` replaced by its twin whose rotation is nearest
    /// `reference` ([`Self::nearest_twin`]): a set of hypotheses in one
    /// symmetric branch, whose statistics then measure doubt about the pose
    /// rather than the symmetry.
    pub fn fold_onto(&self, poses: &[Pose], reference: &Rotation3<f64>) -> Vec<Pose> {
        poses.iter().map(|pose| self.nearest_twin(pose, reference)).collect()
    }

    /// Whether the set holds more than the identity.
    pub fn is_symmetric(&self) -> bool {
        self.transforms.len() > 1
    }

    /// The largest rotational standard deviation of `rotations` modulo the
    /// symmetries (radians): each rotation is replaced by its twin nearest
    /// `reference`, and the result is the square root of the largest
    /// eigenvalue of their tangent covariance about their Karcher mean.
    /// 0 for fewer than two rotations.
    pub fn folded_max_rotation_std(
        &self,
        rotations: &[Rotation3<f64>],
        reference: &Rotation3<f64>,
    ) -> Result<f64, GeometryError> {
        if rotations.len() < 2 {
            return Ok(0.0);
        }
        let poses: Vec<Pose> = rotations.iter().map(|r| Pose::new(*r, Vector3::zeros())).collect();
        let statistics = PoseStatistics::compute(&self.fold_onto(&poses, reference), None, &KarcherOptions::default())?;
        let largest = statistics.rotation_eigen()?.values.max();
        Ok(largest.max(0.0).sqrt())
    }

    /// Rotation error minimised over the set, and the translation error
    /// against the same twin (`t_truth + R_truth t_S`).
    pub fn pose_error(&self, estimate: &Pose, truth: &Pose) -> SymmetricError {
        let mut best = SymmetricError { rotation: f64::INFINITY, translation: f64::INFINITY, symmetry_index: 0 };
        for (index, twin) in self.equivalent_poses(truth).enumerate() {
            let rotation = so3::geodesic_angle(&estimate.rotation, &twin.rotation);
            if rotation < best.rotation {
                best = SymmetricError {
                    rotation,
                    translation: (estimate.translation - twin.translation).norm(),
                    symmetry_index: index,
                };
            }
        }
        best
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::models_info::{ContinuousSymmetry, ModelInfo};
    use nalgebra::{Unit, Vector3};

    fn info(discrete: Vec<Pose>, continuous: Vec<ContinuousSymmetry>) -> ModelInfo {
        ModelInfo {
            diameter: 0.1,
            min: None,
            size: None,
            symmetries_discrete: discrete,
            symmetries_continuous: continuous,
        }
    }

    #[test]
    fn asymmetric_object_has_plain_error() {
        let set = SymmetrySet::from_model_info(&info(vec![], vec![]), BOP_MAX_SYMMETRY_STEP);
        assert_eq!(set.transforms().len(), 1);
        let truth = Pose::identity();
        let est = Pose::new(so3::exp(&Vector3::new(0.0, 0.0, 0.3)), Vector3::new(0.01, 0.0, 0.0));
        let err = set.pose_error(&est, &truth);
        assert!((err.rotation - 0.3).abs() < 1e-14);
        assert!((err.translation - 0.01).abs() < 1e-15);
    }

    #[test]
    fn flipped_box_has_zero_error_under_its_discrete_symmetry() {
        // 180° about z through the point (0.01, 0, 0): S = (R_z(π), t = 2·(0.01, 0, 0)).
        let flip = Pose::new(so3::exp(&Vector3::new(0.0, 0.0, std::f64::consts::PI)), Vector3::new(0.02, 0.0, 0.0));
        let set = SymmetrySet::from_model_info(&info(vec![flip], vec![]), BOP_MAX_SYMMETRY_STEP);
        let truth = Pose::new(so3::exp(&Vector3::new(0.4, -0.2, 1.0)), Vector3::new(0.1, 0.2, 0.8));
        let twin = truth * flip;
        let err = set.pose_error(&twin, &truth);
        assert!(err.rotation < 1e-7 && err.translation < 1e-12, "{err:?}");
        assert_eq!(err.symmetry_index, 1);
        // Without the symmetry the same estimate is 180° off.
        let plain = SymmetrySet::identity_only().pose_error(&twin, &truth);
        assert!((plain.rotation - std::f64::consts::PI).abs() < 1e-7);
    }

    #[test]
    fn continuous_axis_uses_bop_step_count_and_keeps_identity() {
        let cylinder = ContinuousSymmetry { axis: Unit::new_normalize(Vector3::z()), offset: Vector3::zeros() };
        let set = SymmetrySet::from_model_info(&info(vec![], vec![cylinder]), BOP_MAX_SYMMETRY_STEP);
        assert_eq!(set.transforms().len(), 315);
        assert_eq!(set.transforms()[0], Pose::identity());
        // Any spin about z is within half a step (π/315 rad) of a member.
        let truth = Pose::identity();
        let spun = Pose::new(so3::exp(&Vector3::new(0.0, 0.0, 1.2345)), Vector3::zeros());
        assert!(set.rotation_error(&spun.rotation, &truth.rotation) <= std::f64::consts::PI / 315.0 + 1e-12);
        // A tilt off the axis is not forgiven.
        let tilted = so3::exp(&Vector3::new(0.2, 0.0, 0.0));
        assert!((set.rotation_error(&tilted, &truth.rotation) - 0.2).abs() < 1e-12);
    }

    #[test]
    fn discrete_and_continuous_combine() {
        let flip = Pose::new(so3::exp(&Vector3::new(std::f64::consts::PI, 0.0, 0.0)), Vector3::zeros());
        let cylinder = ContinuousSymmetry { axis: Unit::new_normalize(Vector3::z()), offset: Vector3::zeros() };
        let set = SymmetrySet::from_model_info(&info(vec![flip], vec![cylinder]), 0.1);
        assert_eq!(set.transforms().len(), 2 * 32);
    }

    #[test]
    fn folded_max_std_is_the_spread_along_the_widest_axis() {
        let about = |axis: Vector3<f64>, deg: f64| so3::exp(&(axis * deg.to_radians()));
        let plain = SymmetrySet::identity_only();
        // ±σ about x (and nothing about y, z): the largest std is σ exactly
        // (the Karcher mean is the identity, the covariance diag(σ², 0, 0)).
        let fan = [about(Vector3::x(), 12.0), about(Vector3::x(), -12.0)];
        let std = plain.folded_max_rotation_std(&fan, &Rotation3::identity()).unwrap();
        assert!((std - 12f64.to_radians()).abs() < 1e-9, "{}", std.to_degrees());
        // A second, narrower axis does not change the largest one.
        let cross = [fan[0], fan[1], about(Vector3::y(), 3.0), about(Vector3::y(), -3.0)];
        let std = plain.folded_max_rotation_std(&cross, &Rotation3::identity()).unwrap();
        assert!((std - 12f64.to_radians() / 2f64.sqrt()).abs() < 1e-6, "{}", std.to_degrees());
        assert_eq!(plain.folded_max_rotation_std(&fan[..1], &Rotation3::identity()).unwrap(), 0.0);
    }

    #[test]
    fn folded_max_std_does_not_count_a_symmetry_as_spread() {
        let half_turn = Pose::new(so3::exp(&Vector3::new(0.0, 0.0, std::f64::consts::PI)), Vector3::zeros());
        let twofold = SymmetrySet::from_model_info(&info(vec![half_turn], vec![]), BOP_MAX_SYMMETRY_STEP);
        let tilt = |deg: f64| so3::exp(&Vector3::new(deg.to_radians(), 0.0, 0.0));
        // Half the samples in the other symmetric branch: 90° apart unfolded,
        // 5° folded.
        let samples = [tilt(5.0), tilt(-5.0), tilt(5.0) * half_turn.rotation, tilt(-5.0) * half_turn.rotation];
        let folded = twofold.folded_max_rotation_std(&samples, &Rotation3::identity()).unwrap();
        assert!((folded - 5f64.to_radians()).abs() < 1e-9, "{}", folded.to_degrees());
        let unfolded = SymmetrySet::identity_only().folded_max_rotation_std(&samples, &Rotation3::identity()).unwrap();
        assert!(unfolded.to_degrees() > 60.0, "{}", unfolded.to_degrees());
        // The twin nearest a reference in the other branch is that branch's.
        let twin = twofold.nearest_twin(&Pose::new(tilt(5.0), Vector3::zeros()), &half_turn.rotation);
        assert!(so3::geodesic_angle(&twin.rotation, &(tilt(5.0) * half_turn.rotation)) < 1e-12);
    }

    #[test]
    fn folded_spread_ignores_the_symmetry_and_measures_the_rest() {
        let half_turn = Rotation3::from_axis_angle(&Vector3::z_axis(), std::f64::consts::PI);
        let tilt = |deg: f64| Rotation3::from_axis_angle(&Vector3::x_axis(), deg.to_radians());
        let plain = SymmetrySet::identity_only();
        let twofold = SymmetrySet::from_model_info(&info(vec![Pose::new(half_turn, Vector3::zeros())], vec![]), 0.01);
        assert_eq!(plain.folded_rotation_spread(&[]), 0.0);
        assert_eq!(plain.folded_rotation_spread(&[tilt(30.0)]), 0.0);
        // Two rotations a half turn apart: π²/2 about either as medoid,
        // nothing for an object with that half turn as its symmetry.
        let pair = [Rotation3::identity(), half_turn];
        let half = std::f64::consts::PI.powi(2) / 2.0;
        assert!((plain.folded_rotation_spread(&pair) - half).abs() < 1e-9);
        assert!(twofold.folded_rotation_spread(&pair) < 1e-12);
        // 0°, 10°, 20° about x: the medoid is 10°, spread (2·(10°)²)/3 —
        // and the same when one of them is replaced by its twin.
        let fan = [tilt(0.0), tilt(10.0), tilt(20.0)];
        let expected = 2.0 * 10f64.to_radians().powi(2) / 3.0;
        assert!((plain.folded_rotation_spread(&fan) - expected).abs() < 1e-9);
        let twinned = [fan[0], fan[1] * half_turn, fan[2]];
        assert!((twofold.folded_rotation_spread(&twinned) - expected).abs() < 1e-9);
    }
}
