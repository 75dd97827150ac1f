//! The paper's rectified linear flow on SE(3) ≅ SO(3) × ℝ³ and its Euler
//! integration.
//!
//! Path from a noise sample `(R₀, p₀)` (t = 0) to the target `(R₁, p₁)` (t = 1):
//!
//! ```text
//! p_t = (1 − t) p₀ + t p₁            R_t = R₀ exp(t log(R₀ᵀ R₁))
//! ṗ_t = (p₁ − p_t) / (1 − t)         ṙ_t = log(R_tᵀ R₁) / (1 − t)
//! ```
//!
//! `ṙ_t` is a body-frame angular velocity: `R_{t+dt} ≈ R_t exp(dt ṙ_t)`.

use nalgebra::Vector3;

use crate::{GeometryError, Pose, so3};

/// A velocity on SO(3) × ℝ³: `linear` is `ṗ` (in the frame of `p`),
/// `angular` is the body-frame `ω` (right perturbation of `R`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Velocity {
    pub linear: Vector3<f64>,
    pub angular: Vector3<f64>,
}

impl Velocity {
    /// The message layout: `[v_x, v_y, v_z, ω_x, ω_y, ω_z]` as `f32`.
    pub fn to_f32(&self) -> [f32; 6] {
        let (v, w) = (self.linear, self.angular);
        [v.x, v.y, v.z, w.x, w.y, w.z].map(|x| x as f32)
    }

    pub fn from_f32(values: &[f32; 6]) -> Self {
        let v = values.map(f64::from);
        Self { linear: Vector3::new(v[0], v[1], v[2]), angular: Vector3::new(v[3], v[4], v[5]) }
    }
}

/// The point at time `t ∈ [0, 1]` on the path from `start` to `target`.
pub fn interpolate(start: &Pose, target: &Pose, t: f64) -> Pose {
    let relative = so3::log(&(start.rotation.inverse() * target.rotation));
    Pose::new(start.rotation * so3::exp(&(relative * t)), start.translation * (1.0 - t) + target.translation * t)
}

/// The conditional target velocity at `current` = the path point at time `t`,
/// `t ∈ [0, 1)`: the regression target of flow matching.
pub fn target_velocity(current: &Pose, target: &Pose, t: f64) -> Result<Velocity, GeometryError> {
    if !(0.0..1.0).contains(&t) {
        return Err(GeometryError::FlowTimeOutOfRange { t });
    }
    let remaining = 1.0 - t;
    Ok(Velocity {
        linear: (target.translation - current.translation) / remaining,
        angular: so3::log(&(current.rotation.inverse() * target.rotation)) / remaining,
    })
}

/// One explicit Euler step for a batch: `R ← R exp(dt ω)`, `p ← p + dt v`.
pub fn euler_step(poses: &mut [Pose], velocities: &[Velocity], dt: f64) -> Result<(), GeometryError> {
    if poses.len() != velocities.len() {
        return Err(GeometryError::LengthMismatch {
            what: "velocities for an Euler step (one per pose)",
            expected: poses.len(),
            actual: velocities.len(),
        });
    }
    for (pose, velocity) in poses.iter_mut().zip(velocities) {
        pose.rotation *= so3::exp(&(velocity.angular * dt));
        pose.translation += velocity.linear * dt;
    }
    Ok(())
}

/// The flow times of a `steps`-step Euler integration from 0 to 1:
/// `0, 1/K, …, (K−1)/K`. The velocity is evaluated at these times; the last
/// is `(K−1)/K < 1`, which is why training should sample `t` in that range.
pub fn euler_times(steps: usize) -> impl Iterator<Item = f64> {
    (0..steps).map(move |k| k as f64 / steps as f64)
}

/// Where a K-step Euler integration from flow time `s` to 1 asks for the
/// velocity: times `t_0 = s < t_1 < … < t_K = 1`, step `k` going from `t_k`
/// to `t_{k+1}`.
///
/// With a network trained on the clean pose, the last step lands on its
/// prediction at `t_{K−1}`, so a grid whose last time is nearer 1 ends on a
/// prediction made from a less noisy sample, at the same number of network
/// calls (docs/distributions.md, "Time grid").
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Deserialize, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum TimeGrid {
    /// `t_k = s + (1 − s) k / K`: the paper's.
    #[default]
    Uniform,
    /// `t_k = 1 − (1 − s)(1 − k / K)²`: steps shrink towards t = 1 (for
    /// s = 0, K = 5: 0, 0.36, 0.64, 0.84, 0.96).
    Quadratic,
}

impl TimeGrid {
    /// `t_k` of a `steps`-step integration from `start` (`k` = `steps`
    /// gives 1).
    pub fn time(self, start: f64, k: usize, steps: usize) -> f64 {
        match self {
            // Exactly `start + k dt`: results recorded with the uniform
            // sampler then reproduce bit for bit.
            TimeGrid::Uniform => start + k as f64 * self.step(start, k, steps),
            TimeGrid::Quadratic => 1.0 - (1.0 - start) * (1.0 - k as f64 / steps as f64).powi(2),
        }
    }

    /// `t_{k+1} − t_k`.
    pub fn step(self, start: f64, k: usize, steps: usize) -> f64 {
        match self {
            TimeGrid::Uniform => (1.0 - start) / steps as f64,
            TimeGrid::Quadratic => self.time(start, k + 1, steps) - self.time(start, k, steps),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pose::Twist;

    #[test]
    fn time_grids_closed_forms() {
        let quadratic: Vec<f64> = (0..=5).map(|k| TimeGrid::Quadratic.time(0.0, k, 5)).collect();
        for (got, want) in quadratic.iter().zip([0.0, 0.36, 0.64, 0.84, 0.96, 1.0]) {
            assert!((got - want).abs() < 1e-12, "{quadratic:?}");
        }
        for (k, t) in euler_times(5).enumerate() {
            assert!((TimeGrid::Uniform.time(0.0, k, 5) - t).abs() < 1e-15);
        }
        assert!((TimeGrid::Uniform.step(0.8, 0, 2) - 0.1).abs() < 1e-12);
        assert!((TimeGrid::Quadratic.time(0.8, 1, 2) - 0.95).abs() < 1e-12);
        // One step is the same whatever the grid.
        assert_eq!(TimeGrid::Quadratic.step(0.8, 0, 1), TimeGrid::Uniform.step(0.8, 0, 1));
    }

    fn sample_pair() -> (Pose, Pose) {
        (Pose::exp(&Twist::new(0.1, 0.2, 0.3, 0.5, -1.0, 0.7)), Pose::exp(&Twist::new(-0.3, 0.0, 0.9, -1.2, 0.4, 0.2)))
    }

    #[test]
    fn euler_with_exact_velocities_lands_on_target() {
        // Along the rectified path the exact velocity is constant in t, so
        // Euler integration is exact for any number of steps.
        let (start, target) = sample_pair();
        for steps in [1, 2, 5] {
            let mut poses = [start];
            for t in euler_times(steps) {
                let v = target_velocity(&poses[0], &target, t).unwrap();
                euler_step(&mut poses, &[v], 1.0 / steps as f64).unwrap();
            }
            let err = (poses[0].to_homogeneous() - target.to_homogeneous()).abs().max();
            assert!(err < 1e-12, "steps {steps}: {err}");
        }
    }

    #[test]
    fn velocity_at_t1_is_an_error() {
        let (start, target) = sample_pair();
        let err = target_velocity(&start, &target, 1.0).unwrap_err().to_string();
        assert!(err.contains("t = 1"), "{err}");
        assert!(target_velocity(&start, &target, f64::NAN).is_err());
    }

    #[test]
    fn euler_rejects_length_mismatch() {
        let mut poses = [Pose::identity(); 3];
        let v = Velocity { linear: Vector3::zeros(), angular: Vector3::zeros() };
        assert!(euler_step(&mut poses, &[v; 2], 0.1).is_err());
    }

    #[test]
    fn interpolation_midpoint_about_one_axis() {
        let start = Pose::identity();
        let target = Pose::new(so3::exp(&Vector3::new(0.0, 0.0, 1.0)), Vector3::new(2.0, 0.0, 0.0));
        let mid = interpolate(&start, &target, 0.5);
        assert!((so3::log(&mid.rotation) - Vector3::new(0.0, 0.0, 0.5)).norm() < 1e-15);
        assert_eq!(mid.translation, Vector3::new(1.0, 0.0, 0.0));
    }
}
