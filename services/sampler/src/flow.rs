//! Euler integration of the learned flow, for one observation or for the
//! several observations of a frame in lockstep (one velocity request per
//! Euler step for all of them).
//!
//! Frames: the network works in the request frame — camera axes, origin at
//! the observed points' centroid, lengths divided by the observation's
//! `point_scale`. Hypotheses leave in the camera frame (metres):
//! `t_cam = s · p + centroid`, `R` unchanged.

use std::ops::Range;

use nalgebra::Vector3;
use poseflow_contracts::{
    ConditionHandle, MAX_SEGMENTS, POSE_LEN, VELOCITY_LEN, VelocityRequest, VelocitySegment, limits,
};
use poseflow_geometry::flow::{TimeGrid, euler_step};
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
    /// A held track between network passes: the previous estimate
    /// perturbed as for `Track`, not integrated (no velocity request), for
    /// the selector's fit to place.
    Hold(Pose),
}

/// The sampler with its buffers (reused across frames).
#[derive(Debug)]
pub struct FlowSampler {
    params: SamplerParams,
    /// Every job's samples, one job after the other.
    poses: Vec<Pose>,
    request: Vec<f32>,
    response: Vec<f32>,
    velocities: Vec<Velocity>,
    requests: u64,
    /// Most samples one velocity request may carry (the request-response
    /// edge's payload capacity).
    request_capacity: usize,
}

/// What one call produced: camera-frame hypotheses and how many steps.
#[derive(Debug)]
pub struct Sampled<'a> {
    pub poses: &'a [Pose],
    pub steps: usize,
}

/// One job of [`FlowSampler::sample_batch`]: where its hypotheses are in
/// [`FlowSampler::poses`] and how many steps they took.
#[derive(Debug, Clone, PartialEq)]
pub struct Batched {
    pub samples: Range<usize>,
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
            request_capacity: limits::MAX_SAMPLES as usize,
        }
    }

    /// Caps the samples of one velocity request (at most the contract's
    /// 4096): a batch is split into more requests rather than overflow the
    /// edge. One observation's group of samples is never split.
    pub fn set_request_capacity(&mut self, samples: usize) {
        self.request_capacity = samples.clamp(1, limits::MAX_SAMPLES as usize);
    }

    pub fn params(&self) -> &SamplerParams {
        &self.params
    }

    /// The samples of the last call (camera frame, metres).
    pub fn poses(&self) -> &[Pose] {
        &self.poses
    }

    /// N hypotheses for the observation behind `handle`.
    pub fn sample(
        &mut self,
        handle: &ConditionHandle,
        start: &Start,
        field: &mut dyn VelocityField,
    ) -> Result<Sampled<'_>, SamplerError> {
        let mut batch = self.sample_batch(&[(*handle, *start)], field)?;
        let Batched { samples, steps } = batch.pop().expect("one job")?;
        Ok(Sampled { poses: &self.poses[samples], steps })
    }

    /// N hypotheses for each job's observation, integrated in lockstep: at
    /// each Euler step one velocity request carries every job's samples
    /// that still move (in requests of at most [`MAX_SEGMENTS`] segments).
    /// A job whose handle is unusable fails alone (inner `Err`); a velocity
    /// request that fails fails the whole batch (outer `Err`). Each job's
    /// samples equal what [`Self::sample`] gives it alone.
    pub fn sample_batch(
        &mut self,
        jobs: &[(ConditionHandle, Start)],
        field: &mut dyn VelocityField,
    ) -> Result<Vec<Result<Batched, SamplerError>>, SamplerError> {
        self.poses.clear();
        let mut results = Vec::with_capacity(jobs.len());
        let mut groups = Vec::new();
        for (job, (handle, start)) in jobs.iter().enumerate() {
            let (frame, object) = (handle.header.frame_id, handle.header.object_id);
            let scale = f64::from(handle.point_scale);
            if !(scale.is_finite() && scale > 0.0) || handle.centroid.iter().any(|x| !x.is_finite()) {
                results.push(Err(SamplerError::Geometry {
                    frame,
                    object,
                    detail: format!(
                        "condition handle with point_scale {} and centroid {:?}: expected a positive scale and a finite centroid",
                        handle.point_scale, handle.centroid
                    ),
                }));
                continue;
            }
            let centroid = Vector3::from(handle.centroid.map(f64::from));
            let first = self.poses.len();
            let drawn = self.draw(handle, start, scale, centroid);
            let steps = drawn.iter().map(|g| g.steps).max().unwrap_or(0);
            groups.extend(drawn.into_iter().map(|mut group| {
                group.within_job = group.samples.start;
                group.samples = first + group.samples.start..first + group.samples.end;
                group.job = job;
                group
            }));
            results.push(Ok(Batched { samples: first..self.poses.len(), steps }));
        }
        let most_steps = groups.iter().map(|g| g.steps).max().unwrap_or(0);
        for k in 0..most_steps {
            let moving: Vec<&Group> = groups.iter().filter(|g| k < g.steps).collect();
            for request in requests_of(&moving, self.request_capacity) {
                self.step(jobs, request, k, most_steps, field)?;
            }
        }
        for (result, (handle, _)) in results.iter().zip(jobs) {
            if let Ok(batched) = result {
                let scale = f64::from(handle.point_scale);
                let centroid = Vector3::from(handle.centroid.map(f64::from));
                for pose in &mut self.poses[batched.samples.clone()] {
                    pose.translation = pose.translation * scale + centroid;
                }
            }
        }
        Ok(results)
    }

    /// Euler step `k` of `groups`: one velocity request for all of them.
    fn step(
        &mut self,
        jobs: &[(ConditionHandle, Start)],
        groups: &[&Group],
        k: usize,
        step_count: usize,
        field: &mut dyn VelocityField,
    ) -> Result<(), SamplerError> {
        let first = &jobs[groups[0].job].0;
        let (frame, object) = (first.header.frame_id, first.header.object_id);
        self.requests += 1;
        let mut request = VelocityRequest {
            header: first.header,
            request_id: self.requests,
            step_index: k as u32,
            step_count: step_count as u32,
            ..Default::default()
        };
        self.request.clear();
        for group in groups {
            let handle = &jobs[group.job].0;
            let t = group.time(k);
            request.push(VelocitySegment {
                condition_id: handle.condition_id,
                sample_count: group.samples.len() as u32,
                t: t as f32,
            });
            self.request.extend(self.poses[group.samples.clone()].iter().flat_map(|p| p.to_f32_row_major()));
        }
        self.response.clear();
        self.response.resize(request.sample_count as usize * VELOCITY_LEN, 0.0);
        field.velocities(&request, &self.request, &mut self.response).map_err(|source| SamplerError::Velocity {
            frame,
            object,
            step: k,
            source,
        })?;
        let mut offset = 0;
        for group in groups {
            let handle = &jobs[group.job].0;
            let (frame, object) = (handle.header.frame_id, handle.header.object_id);
            let values = &self.response[offset * VELOCITY_LEN..(offset + group.samples.len()) * VELOCITY_LEN];
            offset += group.samples.len();
            if let Some(bad) = values.iter().position(|v| !v.is_finite()) {
                let (component, sample) = (bad % VELOCITY_LEN, group.within_job + bad / VELOCITY_LEN);
                return Err(SamplerError::NonFinite { frame, object, step: k, component, sample });
            }
            self.velocities.clear();
            self.velocities
                .extend(values.chunks_exact(VELOCITY_LEN).map(|v| Velocity::from_f32(v.try_into().expect("6 values"))));
            euler_step(&mut self.poses[group.samples.clone()], &self.velocities, group.step(k))
                .map_err(|e| SamplerError::Geometry { frame, object, detail: e.to_string() })?;
        }
        Ok(())
    }

    /// Appends the start samples of one job to `self.poses` (request
    /// frame); the groups that integrate from different start times, with
    /// sample ranges relative to the job's first sample.
    fn draw(&mut self, handle: &ConditionHandle, start: &Start, scale: f64, centroid: Vector3<f64>) -> Vec<Group> {
        let params = &self.params;
        let mut rng = seeded_rng(sample_seed(params.seed, handle.header.frame_id, handle.header.object_id));
        let n = params.samples;
        let (from_prior, previous) = match start {
            Start::Prior => (n, None),
            Start::Track(previous) | Start::Hold(previous) => (0, Some(previous)),
            // At least one sample of each kind when there are two.
            Start::Mixed(previous) => {
                let share = (params.tracking.prior_share * n as f64).round() as usize;
                (share.clamp(1, n.saturating_sub(1).max(1)), Some(previous))
            }
        };
        let base = self.poses.len();
        let noise = TranslationNoise::Gaussian { std_dev: params.translation_noise_std / scale };
        self.poses.extend((0..from_prior).map(|_| initial_pose(&mut rng, &noise)));
        let mut groups = Vec::with_capacity(2);
        if from_prior > 0 {
            groups.push(Group {
                job: 0,
                within_job: 0,
                samples: 0..from_prior,
                start_time: 0.0,
                steps: params.steps,
                grid: params.time_grid,
            });
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
                self.poses[base + n - 1] = Pose::new(previous.rotation, centred);
                n - 1
            } else {
                n
            };
            if from_prior < integrated_end && !matches!(start, Start::Hold(_)) {
                groups.push(Group {
                    job: 0,
                    within_job: from_prior,
                    samples: from_prior..integrated_end,
                    start_time: tracking.start_time,
                    steps: tracking.steps,
                    grid: params.time_grid,
                });
            }
        }
        groups
    }
}

/// `groups` split into runs that one request can carry: at most
/// [`MAX_SEGMENTS`] segments and `capacity` samples each (a group larger
/// than that goes alone).
fn requests_of<'a, 'g>(groups: &'a [&'g Group], capacity: usize) -> Vec<&'a [&'g Group]> {
    let mut requests = Vec::new();
    let (mut start, mut samples) = (0, 0);
    for (i, group) in groups.iter().enumerate() {
        let full = i - start == MAX_SEGMENTS || samples + group.samples.len() > capacity;
        if full && i > start {
            requests.push(&groups[start..i]);
            (start, samples) = (i, 0);
        }
        samples += group.samples.len();
    }
    if start < groups.len() {
        requests.push(&groups[start..]);
    }
    requests
}

/// Samples of one job that start at one flow time and take one number of
/// steps.
#[derive(Debug, Clone)]
struct Group {
    job: usize,
    /// Where the group's samples start among its job's.
    within_job: usize,
    samples: Range<usize>,
    start_time: f64,
    steps: usize,
    grid: TimeGrid,
}

impl Group {
    /// The flow time of step `k`'s velocity.
    fn time(&self, k: usize) -> f64 {
        self.grid.time(self.start_time, k, self.steps)
    }

    /// The length of step `k`.
    fn step(&self, k: usize) -> f64 {
        self.grid.step(self.start_time, k, self.steps)
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
