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
    /// An unsure track: `tracking.prior_share` of the samples from the
    /// prior, the rest tracked from the previous estimate, so the selector
    /// can pick whichever explains the observation.
    Mixed(Pose),
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
        let groups = self.draw(handle, start, scale, centroid);
        for group in &groups {
            self.integrate(handle, group, field)?;
        }
        for pose in &mut self.poses {
            pose.translation = pose.translation * scale + centroid;
        }
        let steps = groups.iter().map(|g| g.steps).max().unwrap_or(0);
        Ok(Sampled { poses: &self.poses, steps })
    }

    /// Integrates the samples of `group` from its start time to t = 1 in
    /// its number of Euler steps.
    fn integrate(
        &mut self,
        handle: &ConditionHandle,
        group: &Group,
        field: &mut dyn VelocityField,
    ) -> Result<(), SamplerError> {
        let (frame, object) = (handle.header.frame_id, handle.header.object_id);
        let poses = &mut self.poses[group.samples.clone()];
        let n = poses.len();
        let dt = (1.0 - group.start_time) / group.steps as f64;
        for k in 0..group.steps {
            let t = group.start_time + k as f64 * dt;
            self.request.clear();
            self.request.extend(poses.iter().flat_map(|p| p.to_f32_row_major()));
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
                step_count: group.steps as u32,
            };
            field.velocities(&request, &self.request, &mut self.response).map_err(|source| SamplerError::Velocity {
                frame,
                object,
                step: k,
                source,
            })?;
            if let Some(bad) = self.response.iter().position(|v| !v.is_finite()) {
                let (component, sample) = (bad % VELOCITY_LEN, group.samples.start + bad / VELOCITY_LEN);
                return Err(SamplerError::NonFinite { frame, object, step: k, component, sample });
            }
            self.velocities.clear();
            self.velocities.extend(
                self.response.chunks_exact(VELOCITY_LEN).map(|v| Velocity::from_f32(v.try_into().expect("6 values"))),
            );
            euler_step(poses, &self.velocities, dt).map_err(|e| SamplerError::Geometry {
                frame,
                object,
                detail: e.to_string(),
            })?;
        }
        Ok(())
    }

    /// Fills `self.poses` with the start samples in the request frame; the
    /// groups that integrate from different start times.
    fn draw(&mut self, handle: &ConditionHandle, start: &Start, scale: f64, centroid: Vector3<f64>) -> Vec<Group> {
        let params = &self.params;
        let mut rng = seeded_rng(sample_seed(params.seed, handle.header.frame_id, handle.header.object_id));
        let n = params.samples;
        let (from_prior, previous) = match start {
            Start::Prior => (n, None),
            Start::Track(previous) => (0, Some(previous)),
            // At least one sample of each kind when there are two.
            Start::Mixed(previous) => {
                let share = (params.tracking.prior_share * n as f64).round() as usize;
                (share.clamp(1, n.saturating_sub(1).max(1)), Some(previous))
            }
        };
        self.poses.clear();
        let noise = TranslationNoise::Gaussian { std_dev: params.translation_noise_std / scale };
        self.poses.extend((0..from_prior).map(|_| initial_pose(&mut rng, &noise)));
        let mut groups = Vec::with_capacity(2);
        if from_prior > 0 {
            groups.push(Group { samples: 0..from_prior, start_time: 0.0, steps: params.steps });
        }
        if let Some(previous) = previous {
            let tracking = &params.tracking;
            let sigma_rot = tracking.rotation_noise_deg.to_radians();
            let centred = (previous.translation - centroid) / scale;
            self.poses.extend((from_prior..n).map(|_| {
                let turn = gaussian3(&mut rng, sigma_rot);
                let shift = gaussian3(&mut rng, tracking.translation_noise / scale);
                Pose::new(previous.rotation * so3::exp(&turn), centred + shift)
            }));
            // The previous estimate itself stays where it was: the last
            // tracked sample, outside the integrated group, and only beside
            // at least one sample of the flow.
            let integrated_end = if tracking.keep_previous && n - from_prior >= 2 {
                self.poses[n - 1] = Pose::new(previous.rotation, centred);
                n - 1
            } else {
                n
            };
            if from_prior < integrated_end {
                groups.push(Group {
                    samples: from_prior..integrated_end,
                    start_time: tracking.start_time,
                    steps: tracking.steps,
                });
            }
        }
        groups
    }
}

/// Samples that start at one flow time and take one number of steps.
#[derive(Debug, Clone)]
struct Group {
    samples: std::ops::Range<usize>,
    start_time: f64,
    steps: usize,
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
