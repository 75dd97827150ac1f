//! Candidate viewpoints: cameras on a sphere around the object centre,
//! looking at it, with the world's up direction upwards in the image.
//!
//! Frames: everything is in the current camera's frame (OpenCV axes,
//! metres). A candidate is `camera_from_next`, the pose of the next camera
//! in the current one (`x_current = R x_next + t`), the convention of
//! NextView's `chosen`.

use nalgebra::{Point3, Vector3};
use poseflow_geometry::Pose;
use poseflow_scene::scene::look_at_up;

use crate::params::ViewSphere;

/// The golden angle: successive azimuths spread evenly around the circle
/// for any count.
const GOLDEN_ANGLE: f64 = 2.399_963_229_728_653;

/// `sphere.candidates` viewpoints around `centre`: equal-area steps through
/// the elevation band (measured above the plane through `centre`
/// perpendicular to `up`), azimuths on a golden-angle spiral starting at
/// the current camera's side. The radius is `sphere.radius`, else the
/// current camera's distance. `up` must be a unit vector.
pub fn candidate_views(centre: &Point3<f64>, up: &Vector3<f64>, sphere: &ViewSphere) -> Vec<Pose> {
    let to_camera = -centre.coords;
    let radius = sphere.radius.unwrap_or_else(|| to_camera.norm());
    // Azimuth 0: towards the current camera, projected onto the horizontal
    // plane (any horizontal direction when the camera is straight above).
    let level = to_camera - up * up.dot(&to_camera);
    let forward = if level.norm() > 1e-9 * radius.max(1e-9) {
        level.normalize()
    } else {
        let any = if up.x.abs() < 0.9 { Vector3::x() } else { Vector3::y() };
        (any - up * up.dot(&any)).normalize()
    };
    let side = up.cross(&forward);
    let [low, high] = sphere.elevation.map(f64::sin);
    (0..sphere.candidates)
        .map(|i| {
            let height = low + (i as f64 + 0.5) / sphere.candidates as f64 * (high - low);
            let azimuth = i as f64 * GOLDEN_ANGLE;
            let across = (1.0 - height * height).sqrt();
            let direction = across * (azimuth.cos() * forward + azimuth.sin() * side) + height * up;
            let eye = centre + radius * direction;
            look_at_up(&eye, centre, up, 0.0).inverse()
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use poseflow_geometry::so3::geodesic_angle;
    use proptest::prelude::*;

    use super::*;

    fn sphere(candidates: usize, low_deg: f64, high_deg: f64, radius: Option<f64>) -> ViewSphere {
        ViewSphere { candidates, elevation: [low_deg.to_radians(), high_deg.to_radians()], radius }
    }

    /// Elevation of a candidate's eye above the plane through `centre`.
    fn elevation(view: &Pose, centre: &Point3<f64>, up: &Vector3<f64>) -> f64 {
        (view.translation - centre.coords).normalize().dot(up).asin()
    }

    #[test]
    fn a_camera_level_with_the_object_gets_a_ring_around_it() {
        // Object 0.5 m ahead, world up = image up: one candidate at
        // elevation 0 (band [0, 0.001]) and azimuth 0 is the current camera.
        let centre = Point3::new(0.0, 0.0, 0.5);
        let up = Vector3::new(0.0, -1.0, 0.0);
        let views = candidate_views(&centre, &up, &sphere(1, 0.0, 0.001, None));
        let here = &views[0];
        assert!(here.translation.norm() < 1e-5, "{}", here.translation);
        assert!(geodesic_angle(&here.rotation, &nalgebra::Rotation3::identity()) < 1e-5);
        // Two candidates on a level ring with radius 0.3: both 0.3 m from
        // the centre, the second a golden angle further round.
        let views = candidate_views(&centre, &up, &sphere(2, 0.0, 0.0001, Some(0.3)));
        for view in &views {
            assert!(((view.translation - centre.coords).norm() - 0.3).abs() < 1e-12);
        }
        let a = views[0].translation - centre.coords;
        let b = views[1].translation - centre.coords;
        assert!((a.angle(&b) - GOLDEN_ANGLE).abs() < 1e-5, "{}", a.angle(&b));
    }

    #[test]
    fn a_camera_straight_above_still_gets_candidates() {
        // Looking straight down the world's up axis (camera −z is up).
        let centre = Point3::new(0.0, 0.0, 0.4);
        let up = Vector3::new(0.0, 0.0, -1.0);
        let views = candidate_views(&centre, &up, &sphere(6, 20.0, 50.0, None));
        assert_eq!(views.len(), 6);
        for view in &views {
            assert!(view.translation.iter().all(|v| v.is_finite()));
            assert!(((view.translation - centre.coords).norm() - 0.4).abs() < 1e-12);
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(500))]
        /// Every candidate sits on the sphere within the band, looks at the
        /// centre, and keeps the world's up direction upwards in its image.
        #[test]
        fn candidates_look_at_the_centre_from_within_the_band(
            cx in -0.3f64..0.3, cy in -0.3f64..0.3, cz in 0.2f64..1.5,
            ux in -1.0f64..1.0, uy in -1.0f64..1.0, uz in -1.0f64..1.0,
            low in -60.0f64..60.0, width in 1.0f64..25.0, count in 1usize..40,
        ) {
            let up = Vector3::new(ux, uy, uz);
            prop_assume!(up.norm() > 0.1);
            let up = up.normalize();
            let centre = Point3::new(cx, cy, cz);
            let band = sphere(count, low, low + width, Some(0.5));
            let views = candidate_views(&centre, &up, &band);
            prop_assert_eq!(views.len(), count);
            for view in &views {
                prop_assert!(((view.translation - centre.coords).norm() - 0.5).abs() < 1e-9);
                let e = elevation(view, &centre, &up).to_degrees();
                prop_assert!(e >= low - 1e-6 && e <= low + width + 1e-6, "{e} outside [{low}, {}]", low + width);
                // The centre on the next camera's optical axis, in front.
                let seen = view.inverse().transform_point(&centre);
                prop_assert!(seen.x.abs() < 1e-9 && seen.y.abs() < 1e-9 && seen.z > 0.0, "{seen}");
                // Up points up in the image (negative y), not sideways.
                let up_in_next = view.rotation.inverse() * up;
                prop_assert!(up_in_next.x.abs() < 1e-9 && up_in_next.y < 0.0, "{up_in_next}");
            }
        }
    }
}
