//! BOP-style pose error metrics over model points.
//!
//! `points` are model surface points in the object frame (metres; e.g. the
//! mesh vertices); poses are `camera_from_object` (metres). Errors are in
//! metres, [`mspd`] in pixels. Symmetric objects: [`mssd`] and [`mspd`]
//! take the minimum over the [`SymmetrySet`], as the BOP toolkit does;
//! [`add_s`] needs no symmetries (closest-point matching). [`vsd`] compares
//! depth images and so needs no symmetries either.

use nalgebra::Point3;

use crate::{Pose, SymmetrySet};

/// Pinhole intrinsics for [`mspd`] (pixels; OpenCV convention).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pinhole {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
}

impl Pinhole {
    fn project(&self, p: &Point3<f64>) -> [f64; 2] {
        [self.fx * p.x / p.z + self.cx, self.fy * p.y / p.z + self.cy]
    }
}

/// ADD: mean distance between each point under the estimate and under the
/// truth. 0 for no points.
pub fn add(points: &[Point3<f64>], estimate: &Pose, truth: &Pose) -> f64 {
    let sum: f64 = points.iter().map(|p| (estimate.transform_point(p) - truth.transform_point(p)).norm()).sum();
    sum / points.len().max(1) as f64
}

/// ADD-S: mean distance from each point under the estimate to the closest
/// point under the truth (exhaustive search: O(n²), meant for a few
/// thousand points). 0 for no points.
pub fn add_s(points: &[Point3<f64>], estimate: &Pose, truth: &Pose) -> f64 {
    let targets: Vec<Point3<f64>> = points.iter().map(|p| truth.transform_point(p)).collect();
    let sum: f64 = points
        .iter()
        .map(|p| {
            let q = estimate.transform_point(p);
            targets.iter().map(|t| (q - t).norm_squared()).fold(f64::INFINITY, f64::min).sqrt()
        })
        .sum();
    if points.is_empty() { 0.0 } else { sum / points.len() as f64 }
}

/// The largest per-point error of `distance` under `truth · S`, minimised
/// over the symmetries `S`.
fn min_over_symmetries(
    points: &[Point3<f64>],
    symmetries: &SymmetrySet,
    truth: &Pose,
    distance: impl Fn(&Point3<f64>, &Pose) -> f64,
) -> f64 {
    symmetries
        .equivalent_poses(truth)
        .map(|twin| points.iter().map(|p| distance(p, &twin)).fold(0.0, f64::max))
        .fold(f64::INFINITY, f64::min)
}

/// MSSD (BOP): the maximum 3D point distance, minimised over symmetries.
pub fn mssd(points: &[Point3<f64>], estimate: &Pose, truth: &Pose, symmetries: &SymmetrySet) -> f64 {
    min_over_symmetries(points, symmetries, truth, |p, twin| {
        (estimate.transform_point(p) - twin.transform_point(p)).norm()
    })
}

/// MSPD (BOP): the maximum 2D distance of the projected points (pixels),
/// minimised over symmetries.
pub fn mspd(points: &[Point3<f64>], estimate: &Pose, truth: &Pose, symmetries: &SymmetrySet, camera: &Pinhole) -> f64 {
    min_over_symmetries(points, symmetries, truth, |p, twin| {
        let (a, b) = (camera.project(&estimate.transform_point(p)), camera.project(&twin.transform_point(p)));
        (a[0] - b[0]).hypot(a[1] - b[1])
    })
}

/// Depth images of one camera for [`vsd`]: row-major, `width` pixels per
/// row, metres of camera-frame z, 0 = no measurement / no surface.
#[derive(Debug, Clone, Copy)]
pub struct DepthImages<'a> {
    pub pinhole: Pinhole,
    pub width: usize,
    /// The sensor's depth of the test image.
    pub test: &'a [f32],
    /// The object alone rendered at the estimate and at the truth.
    pub estimate: &'a [f32],
    pub truth: &'a [f32],
}

/// Visible Surface Discrepancy (BOP19; Hodaň et al.), one error in [0, 1]
/// per misalignment tolerance in `taus` (metres): over the pixels where the
/// object is visible under the estimate or the truth, the share that is not
/// visible under both with distances within τ. Visibility as the BOP toolkit's
/// "bop19" mode: the rendered surface is at most `delta` metres behind the
/// test depth, or the test has no measurement there; a pixel visible under
/// the truth counts as visible under the estimate wherever the estimate has
/// a surface. Distances are along the ray, not z. An empty union gives 1.
/// Images of different sizes give 1 (nothing can be compared).
pub fn vsd(images: &DepthImages<'_>, delta: f64, taus: &[f64]) -> Vec<f64> {
    let n = images.test.len();
    if images.estimate.len() != n || images.truth.len() != n || images.width == 0 {
        return vec![1.0; taus.len()];
    }
    let Pinhole { fx, fy, cx, cy } = images.pinhole;
    let visible = |model: f64, test: f64| model > 0.0 && (test == 0.0 || model - test <= delta);
    let (mut union, mut only_one) = (0usize, 0usize);
    let mut both: Vec<f64> = Vec::new();
    for i in 0..n {
        // Neither model surface here: not visible under either (most of
        // the image, so skip the ray before computing it).
        if images.estimate[i] <= 0.0 && images.truth[i] <= 0.0 {
            continue;
        }
        let (u, v) = ((i % images.width) as f64, (i / images.width) as f64);
        let ray = ((u - cx) / fx).hypot((v - cy) / fy).hypot(1.0);
        let [test, estimate, truth] = [images.test[i], images.estimate[i], images.truth[i]].map(|z| f64::from(z) * ray);
        let in_truth = visible(truth, test);
        let in_estimate = visible(estimate, test) || (in_truth && estimate > 0.0);
        match (in_truth, in_estimate) {
            (true, true) => both.push((estimate - truth).abs()),
            (false, false) => continue,
            _ => only_one += 1,
        }
        union += 1;
    }
    taus.iter()
        .map(|&tau| {
            if union == 0 {
                return 1.0;
            }
            let misaligned = both.iter().filter(|&&d| d >= tau).count();
            (misaligned + only_one) as f64 / union as f64
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use nalgebra::{Rotation3, Vector3};

    use super::*;
    use crate::models_info::ModelInfo;

    /// Points on a circle of radius `r` about the object's z axis.
    fn ring(r: f64, n: usize) -> Vec<Point3<f64>> {
        (0..n)
            .map(|i| {
                let a = std::f64::consts::TAU * i as f64 / n as f64;
                Point3::new(r * a.cos(), r * a.sin(), 0.0)
            })
            .collect()
    }

    fn at_depth(rotation: Rotation3<f64>, x: f64) -> Pose {
        Pose::new(rotation, Vector3::new(x, 0.0, 0.5))
    }

    #[test]
    fn a_perfect_estimate_scores_zero_everywhere() {
        let points = ring(0.05, 36);
        let truth = at_depth(Rotation3::from_euler_angles(0.3, -0.2, 1.0), 0.02);
        let camera = Pinhole { fx: 572.0, fy: 573.0, cx: 320.0, cy: 240.0 };
        let none = SymmetrySet::identity_only();
        assert_eq!(add(&points, &truth, &truth), 0.0);
        assert_eq!(add_s(&points, &truth, &truth), 0.0);
        assert_eq!(mssd(&points, &truth, &truth, &none), 0.0);
        assert_eq!(mspd(&points, &truth, &truth, &none, &camera), 0.0);
    }

    #[test]
    fn known_errors_in_closed_form() {
        let (r, theta, shift) = (0.05, 0.4f64, 0.01);
        let points = ring(r, 360);
        let truth = at_depth(Rotation3::identity(), 0.0);
        // A turn by θ about the ring's axis moves every point by 2 r sin(θ/2).
        let turned = at_depth(Rotation3::from_axis_angle(&Vector3::z_axis(), theta), 0.0);
        let chord = 2.0 * r * (theta / 2.0).sin();
        assert!((add(&points, &turned, &truth) - chord).abs() < 1e-12);
        assert!((mssd(&points, &turned, &truth, &SymmetrySet::identity_only()) - chord).abs() < 1e-12);
        // ...but the ring maps onto itself: ADD-S sees only the sampling gap.
        assert!(add_s(&points, &turned, &truth) < r * std::f64::consts::TAU / 360.0);
        // A shift along x at depth z moves every projection by fx·d/z pixels.
        let shifted = at_depth(Rotation3::identity(), shift);
        let camera = Pinhole { fx: 600.0, fy: 600.0, cx: 320.0, cy: 240.0 };
        let pixels = mspd(&points, &shifted, &truth, &SymmetrySet::identity_only(), &camera);
        assert!((pixels - 600.0 * shift / 0.5).abs() < 1e-9, "{pixels}");
        assert!((add(&points, &shifted, &truth) - shift).abs() < 1e-12);
    }

    #[test]
    fn a_symmetric_twin_scores_zero_on_the_symmetry_aware_metrics() {
        // An object with a half-turn symmetry about z (an eggbox-like box).
        let half_turn =
            Pose::new(Rotation3::from_axis_angle(&Vector3::z_axis(), std::f64::consts::PI), Vector3::zeros());
        let info = ModelInfo {
            diameter: 0.1,
            min: None,
            size: None,
            symmetries_discrete: vec![half_turn],
            symmetries_continuous: Vec::new(),
        };
        let symmetries = SymmetrySet::from_model_info(&info, 0.01);
        let points =
            vec![Point3::new(0.05, 0.02, 0.01), Point3::new(-0.05, 0.02, -0.01), Point3::new(0.01, -0.02, 0.0)];
        let truth = at_depth(Rotation3::from_euler_angles(0.1, 0.2, 0.3), 0.0);
        let twin = truth * half_turn;
        let camera = Pinhole { fx: 572.0, fy: 573.0, cx: 320.0, cy: 240.0 };
        assert!(mssd(&points, &twin, &truth, &symmetries) < 1e-12);
        assert!(mspd(&points, &twin, &truth, &symmetries, &camera) < 1e-9);
        // Without its symmetries the twin is far off.
        assert!(mssd(&points, &twin, &truth, &SymmetrySet::identity_only()) > 0.05);
        assert!(add(&points, &twin, &truth) > 0.05);
    }

    /// A 4×3 camera with unit rays along the centre column's neighbours.
    fn depth_images<'a>(test: &'a [f32], estimate: &'a [f32], truth: &'a [f32]) -> DepthImages<'a> {
        DepthImages { pinhole: Pinhole { fx: 1e6, fy: 1e6, cx: 1.5, cy: 1.0 }, width: 4, test, estimate, truth }
    }

    #[test]
    fn vsd_in_closed_form() {
        let taus = [0.005, 0.02];
        // Truth covers 4 pixels, all seen by the sensor.
        let truth = [0.0, 0.5, 0.5, 0.0, 0.0, 0.5, 0.5, 0.0, 0.0, 0.0, 0.0, 0.0];
        let test = [0.8, 0.5, 0.5, 0.8, 0.8, 0.5, 0.5, 0.8, 0.8, 0.8, 0.8, 0.8];
        assert_eq!(vsd(&depth_images(&test, &truth, &truth), 0.015, &taus), vec![0.0, 0.0]);
        // The estimate 1 cm deeper: misaligned for τ = 5 mm, aligned for 2 cm.
        let deeper = truth.map(|z| if z > 0.0 { z + 0.01 } else { 0.0 });
        assert_eq!(vsd(&depth_images(&test, &deeper, &truth), 0.015, &taus), vec![1.0, 0.0]);
        // Shifted one column right: 2 pixels in both, 2 only in the truth,
        // 2 only in the estimate (in front of the background: visible).
        let shifted = [0.0, 0.0, 0.5, 0.5, 0.0, 0.0, 0.5, 0.5, 0.0, 0.0, 0.0, 0.0];
        assert_eq!(vsd(&depth_images(&test, &shifted, &truth), 0.015, &taus), vec![4.0 / 6.0, 4.0 / 6.0]);
        // No estimate at all: every truth pixel is unmatched.
        let nothing = [0.0; 12];
        assert_eq!(vsd(&depth_images(&test, &nothing, &truth), 0.015, &taus), vec![1.0, 1.0]);
        // An estimate hidden behind an occluder is not visible, so it is not
        // counted against the estimate: the occluded part of the truth...
        let occluded_test = [0.8, 0.3, 0.3, 0.8, 0.8, 0.5, 0.5, 0.8, 0.8, 0.8, 0.8, 0.8];
        let hidden_top = [0.0, 0.0, 0.0, 0.0, 0.0, 0.5, 0.5, 0.0, 0.0, 0.0, 0.0, 0.0];
        // ...is invisible under the truth as well, so hiding it costs nothing.
        assert_eq!(vsd(&depth_images(&occluded_test, &hidden_top, &truth), 0.015, &taus), vec![0.0, 0.0]);
        // Mismatched sizes compare nothing.
        assert_eq!(vsd(&depth_images(&test[..4], &truth, &truth), 0.015, &taus), vec![1.0, 1.0]);
    }
}
