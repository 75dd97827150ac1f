//! How a scene's camera moves from one image to the next: independent views
//! (a training set) or a smooth orbit (a video, for tracking).
//!
//! Same frames as [`crate::scene`]: world z up, metres, camera poses are
//! `camera_from_world` (OpenCV camera axes).

use nalgebra::Point3;
use poseflow_geometry::Pose;
use rand::Rng;

use crate::Light;
#[cfg(doc)]
use crate::scene::Scene;
use crate::scene::{ViewRange, look_at, random_light};
use crate::video::VideoEvents;

/// Relative swing of the orbit's distance about its mean.
const DISTANCE_SWING: f64 = 0.15;
/// Elevation swing about the orbit's mean, degrees.
const ELEVATION_SWING_DEG: f64 = 10.0;
/// Roll swing about the orbit's mean roll, degrees.
const ROLL_SWING_DEG: f64 = 10.0;
/// Degrees of azimuth over which elevation, distance and roll complete one
/// oscillation: slower than the azimuth, so the motion looks hand-held
/// rather than periodic.
const ELEVATION_PERIOD_DEG: f64 = 240.0;
const DISTANCE_PERIOD_DEG: f64 = 300.0;
const ROLL_PERIOD_DEG: f64 = 200.0;

/// The camera trajectory of every scene of a dataset.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub enum CameraPath {
    /// Every image from an independent random view and light.
    #[default]
    Random,
    /// A video: the camera circles the scene centre, `step_deg` degrees of
    /// azimuth per image, while its elevation, distance and roll drift
    /// smoothly; one light for the whole scene; `events` happen on the way
    /// ([`crate::video`]).
    Orbit { step_deg: f64, events: VideoEvents },
}

/// One scene's orbit, drawn once per scene.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Orbit {
    azimuth: f64,
    /// +1 counter-clockwise seen from above, −1 clockwise.
    direction: f64,
    elevation_deg: f64,
    distance: f64,
    roll_deg: f64,
    /// Phases of the three drifts, radians.
    phases: [f64; 3],
    pub light: Light,
}

/// A value drawn uniformly from `[lo, hi]` shrunk by `margin` at both ends
/// (the midpoint when the margins overlap).
fn inside<R: Rng + ?Sized>(lo: f64, hi: f64, margin_lo: f64, margin_hi: f64, rng: &mut R) -> f64 {
    let (a, b) = (lo + margin_lo, hi - margin_hi);
    if a < b { rng.random_range(a..=b) } else { (lo + hi) / 2.0 }
}

impl Orbit {
    /// Draws an orbit whose every view stays within `range`.
    pub fn draw<R: Rng + ?Sized>(range: &ViewRange, rng: &mut R) -> Self {
        let (near, far) = range.distance;
        let distance = inside(near, far, near * DISTANCE_SWING, far * DISTANCE_SWING, rng);
        let (low, high) = range.elevation_deg;
        let elevation_deg = inside(low, high, ELEVATION_SWING_DEG, ELEVATION_SWING_DEG, rng);
        let roll_limit = (range.max_in_plane_deg - ROLL_SWING_DEG).max(0.0);
        Self {
            azimuth: rng.random_range(0.0..std::f64::consts::TAU),
            direction: if rng.random_bool(0.5) { 1.0 } else { -1.0 },
            elevation_deg,
            distance,
            roll_deg: rng.random_range(-roll_limit..=roll_limit),
            phases: std::array::from_fn(|_| rng.random_range(0.0..std::f64::consts::TAU)),
            light: random_light(rng),
        }
    }

    /// The `camera_from_world` pose after `travelled_deg` degrees of azimuth,
    /// looking at `centre` (a scene's [`Scene::centre`]).
    pub fn camera_from_world(&self, centre: &Point3<f64>, travelled_deg: f64) -> Pose {
        let wave = |period: f64, phase: f64| (std::f64::consts::TAU * travelled_deg / period + phase).sin();
        let azimuth = self.azimuth + self.direction * travelled_deg.to_radians();
        let elevation =
            (self.elevation_deg + ELEVATION_SWING_DEG * wave(ELEVATION_PERIOD_DEG, self.phases[0])).to_radians();
        let distance = self.distance * (1.0 + DISTANCE_SWING * wave(DISTANCE_PERIOD_DEG, self.phases[1]));
        let roll = (self.roll_deg + ROLL_SWING_DEG * wave(ROLL_PERIOD_DEG, self.phases[2])).to_radians();
        let offset =
            nalgebra::Vector3::new(elevation.cos() * azimuth.cos(), elevation.cos() * azimuth.sin(), elevation.sin());
        look_at(&(centre + distance * offset), centre, roll)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const CENTRE: Point3<f64> = Point3::new(0.2, -0.1, 0.05);

    #[test]
    fn orbit_views_stay_in_range_and_move_smoothly() {
        let range = ViewRange::default();
        let mut rng = poseflow_geometry::sampling::seeded_rng(7);
        for _ in 0..20 {
            let orbit = Orbit::draw(&range, &mut rng);
            let mut previous: Option<Pose> = None;
            for k in 0..400 {
                let pose = orbit.camera_from_world(&CENTRE, f64::from(k));
                let eye = pose.inverse().translation;
                let from_centre = eye - CENTRE.coords;
                let distance = from_centre.norm();
                let elevation = (from_centre.z / distance).asin().to_degrees();
                assert!(distance >= range.distance.0 - 1e-9 && distance <= range.distance.1 + 1e-9, "{distance}");
                assert!(elevation >= range.elevation_deg.0 - 1e-9 && elevation <= range.elevation_deg.1 + 1e-9);
                // The centre stays on the optical axis.
                let seen = pose.transform_point(&CENTRE);
                assert!(seen.x.abs() < 1e-9 && seen.y.abs() < 1e-9 && seen.z > 0.0);
                if let Some(previous) = previous {
                    // One degree of azimuth moves the view by a few degrees at most.
                    let turn = (previous.rotation.inverse() * pose.rotation).angle().to_degrees();
                    assert!(turn < 3.0, "step {k}: {turn}°");
                }
                previous = Some(pose);
            }
        }
    }

    #[test]
    fn a_full_orbit_comes_back_around() {
        let orbit = Orbit::draw(&ViewRange::default(), &mut poseflow_geometry::sampling::seeded_rng(3));
        let start = orbit.camera_from_world(&CENTRE, 0.0).inverse().translation;
        let half = orbit.camera_from_world(&CENTRE, 180.0).inverse().translation;
        // Half an orbit puts the camera on the other side of the centre.
        let (a, b) = ((start - CENTRE.coords).xy(), (half - CENTRE.coords).xy());
        assert!(a.dot(&b) < 0.0, "{a} {b}");
    }
}
