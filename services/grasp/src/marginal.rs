//! The paper's mean field (eq. "meanfield_canonical"): one set of grasps
//! integrated with the grasp flow's velocity averaged over the pose
//! hypotheses.
//!
//! Frames: grasps live in the camera frame (grasp-to-camera poses, metres).
//! Hypothesis k places the object model cloud M in the camera frame,
//! `M_k = R_k M + t_k`; the network sees it centred, `M̃_k = M_k − c_k`
//! (camera axes, origin at its centroid `c_k`), and a grasp `(R, p)` as
//! `(R, p − c_k)`. Its velocities (body-frame ω, and v) are the same in
//! both frames, so they average directly: `v̄ = (1/K) Σ_k v_θ(M̃_k, ·)`.

use nalgebra::{Point3, Vector3};
use poseflow_geometry::flow::{Velocity, euler_step, euler_times};
use poseflow_geometry::sampling::{SeededRng, TranslationNoise, initial_pose};
use poseflow_geometry::{GeometryError, Pose};

/// Where the grasp velocities come from: the grasp flow model (the stage),
/// or a closed-form field (tests).
pub trait GraspField {
    /// Why the field could not answer.
    type Error: std::error::Error + Send + Sync + 'static;

    /// Points per cloud the field takes.
    fn point_count(&self) -> usize;

    /// Encodes B zero-mean clouds (B·P·3 values, metres) into a condition.
    fn encode(&mut self, clouds: &[f32]) -> Result<Vec<f32>, Self::Error>;

    /// Velocities of B·G grasps (rotations B·G·9 row-major, translations
    /// B·G·3 relative to each cloud's mean, `t` B·G; the G grasps of each
    /// cloud in a row): (ω body frame, v), B·G·3 values each.
    fn velocity(
        &mut self,
        condition: &[f32],
        rotations: &[f32],
        translations: &[f32],
        t: &[f32],
    ) -> Result<(Vec<f32>, Vec<f32>), Self::Error>;
}

/// How many grasps, how many Euler steps, and the initial positions'
/// spread about the hypotheses' mean centroid.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MeanFieldParams {
    pub grasps: usize,
    pub steps: usize,
    pub noise: TranslationNoise,
}

/// Why grasps could not be sampled.
#[derive(Debug, thiserror::Error)]
pub enum MeanFieldError {
    #[error("no pose hypothesis to grasp under")]
    NoHypotheses,
    #[error("the object cloud has {found} points, the grasp flow takes {expected}")]
    CloudSize { found: usize, expected: usize },
    #[error("the grasp flow failed")]
    Field(#[source] Box<dyn std::error::Error + Send + Sync>),
    #[error("the grasp flow answered {rotation} and {translation} velocity values for {grasps} grasps")]
    VelocityCount { rotation: usize, translation: usize, grasps: usize },
    #[error("the grasp flow's velocity value {index} is not finite (t = {t})")]
    NonFinite { index: usize, t: f64 },
    #[error(transparent)]
    Geometry(#[from] GeometryError),
}

/// G grasp-to-camera poses integrated in the mean field of `hypotheses`
/// (object-to-camera) over the object's `cloud` (object frame, the
/// field's point count, farthest-point order). One hypothesis gives the
/// single-hypothesis baseline.
pub fn marginal_grasps<F: GraspField + ?Sized>(
    field: &mut F,
    cloud: &[Point3<f32>],
    hypotheses: &[Pose],
    params: &MeanFieldParams,
    rng: &mut SeededRng,
) -> Result<Vec<Pose>, MeanFieldError> {
    if hypotheses.is_empty() {
        return Err(MeanFieldError::NoHypotheses);
    }
    if cloud.len() != field.point_count() {
        return Err(MeanFieldError::CloudSize { found: cloud.len(), expected: field.point_count() });
    }
    let (clouds, centroids) = centred_clouds(cloud, hypotheses);
    let failed = |e: F::Error| MeanFieldError::Field(Box::new(e));
    let condition = field.encode(&clouds).map_err(failed)?;
    let mean_centroid = centroids.iter().sum::<Vector3<f64>>() / centroids.len() as f64;
    let mut grasps: Vec<Pose> = (0..params.grasps)
        .map(|_| {
            let start = initial_pose(rng, &params.noise);
            Pose::new(start.rotation, start.translation + mean_centroid)
        })
        .collect();
    let (k, g) = (hypotheses.len(), params.grasps);
    let (mut rotations, mut translations) = (Vec::with_capacity(k * g * 9), Vec::with_capacity(k * g * 3));
    for t in euler_times(params.steps) {
        rotations.clear();
        translations.clear();
        for centroid in &centroids {
            for grasp in &grasps {
                rotations.extend(grasp.rotation.matrix().transpose().iter().map(|&x| x as f32));
                translations.extend((grasp.translation - centroid).iter().map(|&x| x as f32));
            }
        }
        let times = vec![t as f32; k * g];
        let (omega, v) = field.velocity(&condition, &rotations, &translations, &times).map_err(failed)?;
        if omega.len() != k * g * 3 || v.len() != k * g * 3 {
            return Err(MeanFieldError::VelocityCount { rotation: omega.len(), translation: v.len(), grasps: k * g });
        }
        if let Some(index) = omega.iter().chain(&v).position(|x| !x.is_finite()) {
            return Err(MeanFieldError::NonFinite { index, t });
        }
        let mean = |values: &[f32], i: usize| {
            (0..k).map(|h| Vector3::from_fn(|a, _| f64::from(values[(h * g + i) * 3 + a]))).sum::<Vector3<f64>>()
                / k as f64
        };
        let velocities: Vec<Velocity> =
            (0..g).map(|i| Velocity { linear: mean(&v, i), angular: mean(&omega, i) }).collect();
        euler_step(&mut grasps, &velocities, 1.0 / params.steps as f64)?;
    }
    Ok(grasps)
}

/// Each hypothesis' cloud in the camera frame, centred (K·P·3 values), and
/// its centroid.
fn centred_clouds(cloud: &[Point3<f32>], hypotheses: &[Pose]) -> (Vec<f32>, Vec<Vector3<f64>>) {
    let mut values = Vec::with_capacity(hypotheses.len() * cloud.len() * 3);
    let mut centroids = Vec::with_capacity(hypotheses.len());
    for pose in hypotheses {
        let placed: Vec<Vector3<f64>> = cloud.iter().map(|p| pose.transform_point(&p.cast::<f64>()).coords).collect();
        let centroid = placed.iter().sum::<Vector3<f64>>() / placed.len() as f64;
        values.extend(placed.iter().flat_map(|p| (p - centroid).iter().map(|&x| x as f32).collect::<Vec<_>>()));
        centroids.push(centroid);
    }
    (values, centroids)
}

#[cfg(test)]
mod tests {
    use nalgebra::Rotation3;
    use poseflow_geometry::sampling::seeded_rng;
    use poseflow_geometry::so3;

    use super::*;

    /// A field whose flow ends at one grasp fixed to the object: for each
    /// cloud it reads the object's orientation from the cloud (the test
    /// cloud's first point is the object's +x axis tip) and steers every
    /// grasp to `target` (object frame) at t = 1.
    struct PointAtTarget {
        target: Pose,
        points: usize,
        encoded: Vec<usize>,
    }

    impl GraspField for PointAtTarget {
        type Error = std::convert::Infallible;

        fn point_count(&self) -> usize {
            self.points
        }

        fn encode(&mut self, clouds: &[f32]) -> Result<Vec<f32>, Self::Error> {
            self.encoded.push(clouds.len() / (3 * self.points));
            Ok(clouds.to_vec())
        }

        fn velocity(
            &mut self,
            condition: &[f32],
            rotations: &[f32],
            translations: &[f32],
            t: &[f32],
        ) -> Result<(Vec<f32>, Vec<f32>), Self::Error> {
            let per_cloud = 3 * self.points;
            let clouds = condition.len() / per_cloud;
            let g = t.len() / clouds;
            let (mut omega, mut v) = (Vec::new(), Vec::new());
            for i in 0..t.len() {
                let c = &condition[(i / g) * per_cloud..];
                // The test cloud is three orthogonal axis tips about the origin
                // plus their negatives: columns of the object's rotation.
                let axis =
                    |j: usize| Vector3::new(c[3 * j] as f64, c[3 * j + 1] as f64, c[3 * j + 2] as f64).normalize();
                let object =
                    Rotation3::from_matrix_unchecked(nalgebra::Matrix3::from_columns(&[axis(0), axis(1), axis(2)]));
                let r = Rotation3::from_matrix_unchecked(nalgebra::Matrix3::from_row_slice(
                    &rotations[9 * i..9 * i + 9].iter().map(|&x| x as f64).collect::<Vec<_>>(),
                ));
                let p = Vector3::new(
                    translations[3 * i] as f64,
                    translations[3 * i + 1] as f64,
                    translations[3 * i + 2] as f64,
                );
                let goal_r = object * self.target.rotation;
                let goal_p = object * self.target.translation;
                let remaining = 1.0 - t[i] as f64;
                omega.extend(so3::log(&(r.inverse() * goal_r)).iter().map(|&x| (x / remaining) as f32));
                v.extend(((goal_p - p) / remaining).iter().map(|&x| x as f32));
            }
            Ok((omega, v))
        }
    }

    fn axis_cloud() -> Vec<Point3<f32>> {
        let tips = [Vector3::x(), Vector3::y(), Vector3::z()].map(|a| a * 0.05);
        tips.iter().map(|&a| Point3::from(a)).chain(tips.iter().map(|&a| Point3::from(-a))).collect()
    }

    fn params() -> MeanFieldParams {
        MeanFieldParams { grasps: 8, steps: 10, noise: TranslationNoise::Gaussian { std_dev: 0.05 } }
    }

    /// A field that cannot answer.
    struct Broken;

    impl GraspField for Broken {
        type Error = std::io::Error;

        fn point_count(&self) -> usize {
            6
        }

        fn encode(&mut self, _: &[f32]) -> Result<Vec<f32>, Self::Error> {
            Err(std::io::Error::other("the network failed"))
        }

        fn velocity(
            &mut self,
            _: &[f32],
            _: &[f32],
            _: &[f32],
            _: &[f32],
        ) -> Result<(Vec<f32>, Vec<f32>), Self::Error> {
            Err(std::io::Error::other("not reached"))
        }
    }

    #[test]
    fn a_failing_field_keeps_its_cause_as_the_source() {
        let object = Pose::new(Rotation3::identity(), Vector3::new(0.0, 0.0, 0.6));
        let err = marginal_grasps(&mut Broken, &axis_cloud(), &[object], &params(), &mut seeded_rng(1)).unwrap_err();
        assert!(matches!(err, MeanFieldError::Field(_)), "{err:?}");
        assert_eq!(poseflow_runtime::error_chain(&err), "the grasp flow failed: the network failed");
    }

    #[test]
    fn one_hypothesis_reaches_the_grasp_the_field_points_at() {
        let target = Pose::new(so3::exp(&Vector3::new(0.3, -0.2, 1.0)), Vector3::new(0.02, 0.0, 0.06));
        let mut field = PointAtTarget { target, points: 6, encoded: Vec::new() };
        let object = Pose::new(so3::exp(&Vector3::new(-0.5, 1.2, 0.1)), Vector3::new(0.1, -0.05, 0.7));
        let grasps = marginal_grasps(&mut field, &axis_cloud(), &[object], &params(), &mut seeded_rng(1)).unwrap();
        // The cloud is symmetric about the object origin: the centroid is
        // the object's position, and the grasp ends at object ∘ target.
        let expected = object * target;
        for grasp in &grasps {
            assert!(so3::geodesic_angle(&grasp.rotation, &expected.rotation) < 1e-6);
            assert!((grasp.translation - expected.translation).norm() < 1e-6);
        }
        assert_eq!(field.encoded, [1]);
    }

    #[test]
    fn two_hypotheses_average_their_velocities() {
        // Two hypotheses differing by a shift: their fields point at grasps
        // 4 cm apart, and the mean field ends midway between them.
        let target = Pose::new(Rotation3::identity(), Vector3::new(0.0, 0.0, 0.05));
        let mut field = PointAtTarget { target, points: 6, encoded: Vec::new() };
        let a = Pose::new(Rotation3::identity(), Vector3::new(-0.02, 0.0, 0.6));
        let b = Pose::new(Rotation3::identity(), Vector3::new(0.02, 0.0, 0.6));
        let grasps = marginal_grasps(&mut field, &axis_cloud(), &[a, b], &params(), &mut seeded_rng(2)).unwrap();
        for grasp in &grasps {
            assert!((grasp.translation - Vector3::new(0.0, 0.0, 0.65)).norm() < 1e-6, "{}", grasp.translation);
        }
        assert_eq!(field.encoded, [2]);
    }

    #[test]
    fn bad_inputs_are_named() {
        let mut field = PointAtTarget { target: Pose::identity(), points: 6, encoded: Vec::new() };
        let err = marginal_grasps(&mut field, &axis_cloud(), &[], &params(), &mut seeded_rng(3)).unwrap_err();
        assert!(matches!(err, MeanFieldError::NoHypotheses));
        let err = marginal_grasps(&mut field, &axis_cloud()[..4], &[Pose::identity()], &params(), &mut seeded_rng(3))
            .unwrap_err();
        assert!(err.to_string().contains("4 points") && err.to_string().contains("takes 6"), "{err}");
    }
}
