//! Property tests of the geometry core, 10,000 cases each.

use std::f64::consts::PI;

use nalgebra::{Rotation3, Unit, Vector3};
use poseflow_geometry::flow::{self, Velocity};
use poseflow_geometry::mean::{KarcherOptions, karcher_mean_poses};
use poseflow_geometry::models_info::{ContinuousSymmetry, ModelInfo};
use poseflow_geometry::pose::Twist;
use poseflow_geometry::symmetry::{BOP_MAX_SYMMETRY_STEP, SymmetrySet};
use poseflow_geometry::{Pose, PoseMetric, so3};
use proptest::prelude::*;

fn config() -> ProptestConfig {
    ProptestConfig { cases: 10_000, ..ProptestConfig::default() }
}

fn unit_axis() -> impl Strategy<Value = Vector3<f64>> {
    (-1.0..1.0f64, -1.0..1.0f64, -1.0..1.0f64)
        .prop_filter("axis must not vanish", |(x, y, z)| x * x + y * y + z * z > 1e-4)
        .prop_map(|(x, y, z)| Vector3::new(x, y, z).normalize())
}

/// Angles over the whole range, with a third of the draws within 1e-6 of 0
/// and a third within 1e-6 of π, where naive formulas break.
fn angle_including_extremes() -> impl Strategy<Value = f64> {
    prop_oneof![0.0..PI, 0.0..1e-6f64, (PI - 1e-6)..=PI]
}

/// Same, but strictly below π, where the rotation vector is unique.
fn angle_below_pi() -> impl Strategy<Value = f64> {
    prop_oneof![0.0..PI - 1e-6, 0.0..1e-6f64, (PI - 1e-6)..(PI - 1e-9)]
}

fn rotation() -> impl Strategy<Value = Rotation3<f64>> {
    (unit_axis(), angle_including_extremes()).prop_map(|(axis, angle)| so3::exp(&(axis * angle)))
}

fn translation(scale: f64) -> impl Strategy<Value = Vector3<f64>> {
    (-scale..scale, -scale..scale, -scale..scale).prop_map(|(x, y, z)| Vector3::new(x, y, z))
}

fn pose() -> impl Strategy<Value = Pose> {
    (rotation(), translation(2.0)).prop_map(|(r, t)| Pose::new(r, t))
}

fn max_abs_diff(a: &Pose, b: &Pose) -> f64 {
    (a.to_homogeneous() - b.to_homogeneous()).abs().max()
}

proptest! {
    #![proptest_config(config())]

    #[test]
    fn so3_exp_of_log_is_identity(r in rotation()) {
        let back = so3::exp(&so3::log(&r));
        prop_assert!((back.matrix() - r.matrix()).abs().max() < 1e-12);
    }

    #[test]
    fn so3_log_of_exp_is_identity(axis in unit_axis(), angle in angle_below_pi()) {
        let omega = axis * angle;
        let back = so3::log(&so3::exp(&omega));
        prop_assert!((back - omega).norm() < 1e-9, "{omega} -> {back}");
    }

    #[test]
    fn se3_exp_of_log_is_identity(p in pose()) {
        prop_assert!(max_abs_diff(&Pose::exp(&p.log()), &p) < 1e-11);
    }

    #[test]
    fn se3_log_of_exp_is_identity(axis in unit_axis(), angle in angle_below_pi(), rho in translation(2.0)) {
        let phi = axis * angle;
        let twist = Twist::new(rho.x, rho.y, rho.z, phi.x, phi.y, phi.z);
        let back = Pose::exp(&twist).log();
        prop_assert!((back - twist).norm() < 1e-8, "{twist} -> {back}");
    }

    #[test]
    fn distance_is_symmetric_and_zero_on_the_diagonal(a in pose(), b in pose()) {
        let metric = PoseMetric::default();
        prop_assert!((metric.distance(&a, &b) - metric.distance(&b, &a)).abs() < 1e-9);
        prop_assert!(metric.distance(&a, &a) < 1e-9);
    }

    #[test]
    fn distance_satisfies_the_triangle_inequality(a in pose(), b in pose(), c in pose()) {
        let metric = PoseMetric::default();
        let direct = metric.distance(&a, &c);
        let detour = metric.distance(&a, &b) + metric.distance(&b, &c);
        prop_assert!(direct <= detour + 1e-9, "{direct} > {detour}");
    }

    #[test]
    fn path_starts_and_ends_at_its_endpoints(start in pose(), target in pose()) {
        prop_assert!(max_abs_diff(&flow::interpolate(&start, &target, 0.0), &start) < 1e-12);
        prop_assert!(max_abs_diff(&flow::interpolate(&start, &target, 1.0), &target) < 1e-11);
    }

    #[test]
    fn path_derivative_matches_the_target_velocity(
        start in pose(),
        axis in unit_axis(),
        // Away from π the geodesic is unique, so the path is differentiable.
        angle in 0.0..(PI - 0.01),
        target_translation in translation(2.0),
        t in 0.0..0.99f64,
    ) {
        let target = Pose::new(start.rotation * so3::exp(&(axis * angle)), target_translation);
        let h = 1e-6;
        let here = flow::interpolate(&start, &target, t);
        let ahead = flow::interpolate(&start, &target, t + h);
        let fd_rot = so3::log(&(here.rotation.inverse() * ahead.rotation)) / h;
        let fd_pos = (ahead.translation - here.translation) / h;
        let v = flow::target_velocity(&here, &target, t).unwrap();
        prop_assert!((fd_rot - v.angular).norm() < 1e-5 * (1.0 + v.angular.norm()), "{fd_rot} vs {}", v.angular);
        prop_assert!((fd_pos - v.linear).norm() < 1e-5 * (1.0 + v.linear.norm()), "{fd_pos} vs {}", v.linear);
    }

    #[test]
    fn euler_with_target_velocities_reaches_the_target(
        start in pose(), axis in unit_axis(), angle in 0.0..(PI - 0.01), p1 in translation(2.0), steps in 1usize..8,
    ) {
        let target = Pose::new(start.rotation * so3::exp(&(axis * angle)), p1);
        let mut poses = [start];
        for t in flow::euler_times(steps) {
            let v: Velocity = flow::target_velocity(&poses[0], &target, t).unwrap();
            flow::euler_step(&mut poses, &[v], 1.0 / steps as f64).unwrap();
        }
        prop_assert!(max_abs_diff(&poses[0], &target) < 1e-9);
    }

    #[test]
    fn every_time_grid_rises_from_its_start_to_one_and_integrates_exactly(
        start in pose(), axis in unit_axis(), angle in 0.0..(PI - 0.01), p1 in translation(2.0), steps in 1usize..8,
        from in 0.0..0.95f64, quadratic in any::<bool>(),
    ) {
        let grid = if quadratic { flow::TimeGrid::Quadratic } else { flow::TimeGrid::Uniform };
        let target = Pose::new(start.rotation * so3::exp(&(axis * angle)), p1);
        let mut poses = [flow::interpolate(&start, &target, from)];
        prop_assert!((grid.time(from, 0, steps) - from).abs() < 1e-12);
        prop_assert!((grid.time(from, steps, steps) - 1.0).abs() < 1e-12);
        for k in 0..steps {
            prop_assert!(grid.step(from, k, steps) > 0.0);
            let v = flow::target_velocity(&poses[0], &target, grid.time(from, k, steps)).unwrap();
            flow::euler_step(&mut poses, &[v], grid.step(from, k, steps)).unwrap();
        }
        prop_assert!(max_abs_diff(&poses[0], &target) < 1e-9);
    }

    #[test]
    fn karcher_mean_of_a_symmetric_cluster_is_its_centre(
        centre in pose(),
        offsets in prop::collection::vec((unit_axis(), 0.0..1.2f64, translation(0.1), 0.1..2.0f64), 1..6),
    ) {
        // Each tangent offset appears with both signs and equal weight, so the
        // gradient of the Karcher cost vanishes exactly at the centre.
        let mut poses = Vec::new();
        let mut weights = Vec::new();
        for (axis, angle, dt, w) in &offsets {
            for sign in [1.0, -1.0] {
                poses.push(Pose::new(centre.rotation * so3::exp(&(axis * (*angle * sign))), centre.translation + dt * sign));
                weights.push(*w);
            }
        }
        let mean = karcher_mean_poses(&poses, Some(&weights), &KarcherOptions::default()).unwrap();
        prop_assert!(mean.converged);
        prop_assert!(so3::geodesic_angle(&mean.mean.rotation, &centre.rotation) < 1e-8);
        prop_assert!((mean.mean.translation - centre.translation).norm() < 1e-12);
    }

    #[test]
    fn symmetric_twin_has_zero_error(
        truth in pose(),
        discrete_axis in unit_axis(),
        order in 2usize..7,
        which in 0usize..7,
        continuous_axis in unit_axis(),
        offset in translation(0.05),
        spin_step in 0usize..315,
        use_continuous in any::<bool>(),
    ) {
        // A discrete n-fold symmetry (all its powers listed, as BOP files do)
        // and optionally a continuous axis through an offset point.
        let discrete: Vec<Pose> = (1..order)
            .map(|k| Pose::new(so3::exp(&(discrete_axis * (k as f64 * 2.0 * PI / order as f64))), Vector3::zeros()))
            .collect();
        let continuous = if use_continuous {
            vec![ContinuousSymmetry { axis: Unit::new_normalize(continuous_axis), offset }]
        } else {
            vec![]
        };
        let info = ModelInfo { diameter: 0.1, min: None, size: None, symmetries_discrete: discrete, symmetries_continuous: continuous };
        let set = SymmetrySet::from_model_info(&info, BOP_MAX_SYMMETRY_STEP);
        let members = set.transforms();
        let s = if use_continuous { members[(which * 315 + spin_step) % members.len()] } else { members[which % members.len()] };
        let twin = truth * s;
        let err = set.pose_error(&twin, &truth);
        prop_assert!(err.rotation < 1e-7, "{err:?}");
        prop_assert!(err.translation < 1e-9, "{err:?}");
        prop_assert!(set.rotation_error(&twin.rotation, &truth.rotation) < 1e-7);
    }
}
