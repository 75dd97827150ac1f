//! Euler integration of the learned flow for one observation.
//!
//! Frames: the network works in the request frame — camera axes, origin at
//! the observed points' centroid, lengths divided by the observation's
//! `point_scale`. Hypotheses leave in the camera frame (metres):
//! `t_cam = s · p + centroid`, `R` unchanged.

use nalgebra::Vector3;
use poseflow_contracts::{ConditionHandle, POSE_LEN, VELOCITY_LEN, VelocityRequest};
use poseflow_geometry::flow::euler_step;
use poseflow_geometry::sampling::{TranslationNoise, initial_pose, sample_seed, seeded_rng};
use poseflow_geometry::{Pose, Velocity, so3};
use rand::Rng;
use rand_distr::{Distribution, StandardNormal};

use crate::{FieldError, SamplerError, SamplerParams};

/// Where the velocities come from: the inference stage's library
/// in-process, or a request-response client ([`crate::stage::RemoteField`]).
pub trait VelocityField {
    /// Writes the velocities (`v` then body-frame `ω`, 6 per pose) of
    /// `poses` (12 per pose, request frame) into `out`.
    fn velocities(&mut self, request: &VelocityRequest, poses: &[f32], out: &mut [f32]) -> Result<(), FieldError>;
}

impl<F: FnMut(&VelocityRequest, &[f32], &mut [f32]) -> Result<(), FieldError>> VelocityField for F {
    fn velocities(&mut self, request: &VelocityRequest, poses: &[f32], out: &mut [f32]) -> Result<(), FieldError> {
        self(request, poses, out)
    }
}

/// Where the N samples start.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Start {
    /// The flow's prior: Haar-uniform rotations, Gaussian translations
    /// about the centroid, integrated from t = 0.
    Prior,
    /// Tracking: the previous estimate (camera frame), perturbed, placed at
    /// `tracking.start_time`.
    Track(Pose),
}

/// The sampler with its buffers (reused across frames).
#[derive(Debug)]
pub struct FlowSampler {
    params: SamplerParams,
    poses: Vec<Pose>,
    request: Vec<f32>,
    response: Vec<f32>,
    velocities: Vec<Velocity>,
    requests: u64,
}

/// What one call produced: camera-frame hypotheses and how many steps.
#[derive(Debug)]
pub struct Sampled<'a> {
    pub poses: &'a [Pose],
    pub steps: usize,
}

impl FlowSampler {
    pub fn new(params: SamplerParams) -> Self {
        Self {
            params,
            poses: Vec::new(),
            request: Vec::new(),
            response: Vec::new(),
            velocities: Vec::new(),
            requests: 0,
        }
    }

    pub fn params(&self) -> &SamplerParams {
        &self.params
    }

    /// N hypotheses for the observation behind `handle`.
    pub fn sample(
        &mut self,
        handle: &ConditionHandle,
        start: &Start,
        field: &mut dyn VelocityField,
    ) -> Result<Sampled<'_>, SamplerError> {
        let (frame, object) = (handle.header.frame_id, handle.header.object_id);
        let scale = f64::from(handle.point_scale);
        if !(scale.is_finite() && scale > 0.0) || handle.centroid.iter().any(|x| !x.is_finite()) {
            return Err(SamplerError::Geometry {
                frame,
                object,
                detail: format!(
                    "condition handle with point_scale {} and centroid {:?}: expected a positive scale and a finite centroid",
                    handle.point_scale, handle.centroid
                ),
            });
        }
        let centroid = Vector3::from(handle.centroid.map(f64::from));
        let (start_time, steps) = self.draw(handle, start, scale, centroid);
        let dt = (1.0 - start_time) / steps as f64;
        let n = self.poses.len();
        for k in 0..steps {
            let t = start_time + k as f64 * dt;
            self.request.clear();
            self.request.extend(self.poses.iter().flat_map(|p| p.to_f32_row_major()));
            self.response.clear();
            self.response.resize(n * VELOCITY_LEN, 0.0);
            self.requests += 1;
            let request = VelocityRequest {
                header: handle.header,
                condition_id: handle.condition_id,
                request_id: self.requests,
                sample_count: n as u32,
                t: t as f32,
                step_index: k as u32,
                step_count: steps as u32,
            };
            field.velocities(&request, &self.request, &mut self.response).map_err(|source| SamplerError::Velocity {
                frame,
                object,
                step: k,
                source,
            })?;
            if let Some(bad) = self.response.iter().position(|v| !v.is_finite()) {
                let (component, sample) = (bad % VELOCITY_LEN, bad / VELOCITY_LEN);
                return Err(SamplerError::NonFinite { frame, object, step: k, component, sample });
            }
            self.velocities.clear();
            self.velocities.extend(
                self.response.chunks_exact(VELOCITY_LEN).map(|v| Velocity::from_f32(v.try_into().expect("6 values"))),
            );
            euler_step(&mut self.poses, &self.velocities, dt).map_err(|e| SamplerError::Geometry {
                frame,
                object,
                detail: e.to_string(),
            })?;
        }
        for pose in &mut self.poses {
            pose.translation = pose.translation * scale + centroid;
        }
        Ok(Sampled { poses: &self.poses, steps })
    }

    /// Fills `self.poses` with the start samples in the request frame;
    /// returns the start time and the number of steps.
    fn draw(&mut self, handle: &ConditionHandle, start: &Start, scale: f64, centroid: Vector3<f64>) -> (f64, usize) {
        let params = &self.params;
        let mut rng = seeded_rng(sample_seed(params.seed, handle.header.frame_id, handle.header.object_id));
        self.poses.clear();
        match start {
            Start::Prior => {
                let noise = TranslationNoise::Gaussian { std_dev: params.translation_noise_std / scale };
                self.poses.extend((0..params.samples).map(|_| initial_pose(&mut rng, &noise)));
                (0.0, params.steps)
            }
            Start::Track(previous) => {
                let tracking = &params.tracking;
                let sigma_rot = tracking.rotation_noise_deg.to_radians();
                let centred = (previous.translation - centroid) / scale;
                self.poses.extend((0..params.samples).map(|_| {
                    let turn = gaussian3(&mut rng, sigma_rot);
                    let shift = gaussian3(&mut rng, tracking.translation_noise / scale);
                    Pose::new(previous.rotation * so3::exp(&turn), centred + shift)
                }));
                (tracking.start_time, tracking.steps)
            }
        }
    }
}

fn gaussian3<R: Rng + ?Sized>(rng: &mut R, sigma: f64) -> Vector3<f64> {
    Vector3::from_fn(|_, _| {
        let z: f64 = StandardNormal.sample(rng);
        z * sigma
    })
}

/// Camera-frame hypotheses as the Hypotheses payload (12 floats each).
pub(crate) fn write_poses(poses: &[Pose], out: &mut [f32]) {
    for (chunk, pose) in out.chunks_exact_mut(POSE_LEN).zip(poses) {
        chunk.copy_from_slice(&pose.to_f32_row_major());
    }
}
