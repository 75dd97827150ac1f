//! Scoring candidate views: v* = argmin_v E[tr Σ_R | v], the expectation
//! over hypotheses of the current pose distribution, each view simulated
//! by rendering the object at the hypothesis and running the pose stages
//! on the rendering. tr Σ_R is measured modulo the object's symmetries
//! ([`SymmetrySet::folded_rotation_spread`] of the simulated estimate's kept
//! hypotheses), so a symmetric object's twins do not count as uncertainty
//! no view could remove.

use std::time::Instant;

use nalgebra::{Point3, Vector3};
use poseflow_geometry::Pose;
use poseflow_geometry::sampling::{sample_seed, seeded_rng};
use poseflow_geometry::symmetry::{BOP_MAX_SYMMETRY_STEP, SymmetrySet};
use poseflow_scene::{ModelLibrary, RenderModel};

use crate::candidates::candidate_views;
use crate::pose_stages::PoseStages;
use crate::simulate::{Viewpoint, simulated_view};
use crate::{NbvError, NbvParams, Occluders};

/// tr Σ_R of the Haar-uniform rotation distribution, E[θ²] = π²/3 + 2
/// (rad²): the uncertainty a view that shows nothing leaves.
pub const UNIFORM_ROTATION_TRACE: f64 = std::f64::consts::PI * std::f64::consts::PI / 3.0 + 2.0;

/// One candidate and the uncertainty it is expected to leave.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ScoredView {
    /// Pose of the candidate camera in the current one (`x_current = R
    /// x_next + t`).
    pub camera_from_next: Pose,
    /// Mean over the simulated hypotheses of tr Σ_R modulo symmetries
    /// (rad²).
    pub expected_trace: f64,
    /// Simulated views that showed too little to estimate (counted at
    /// [`UNIFORM_ROTATION_TRACE`]).
    pub uninformative: usize,
}

/// What one plan cost.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct PlanCost {
    /// Simulated views (candidates × hypotheses).
    pub views: usize,
    /// Summed over workers: rendering and noise, and the pose stages.
    pub render_ms: f64,
    pub estimate_ms: f64,
    /// Wall time of the whole plan.
    pub wall_ms: f64,
}

#[derive(Debug, Clone)]
pub struct NextViewPlan {
    /// Every candidate, lowest expected trace first (ties: candidate order).
    pub views: Vec<ScoredView>,
    pub cost: PlanCost,
}

/// `count` of `kept` (best first) spread evenly over the list, so the
/// simulated hypotheses reach beyond the best-scored few.
pub fn spread_evenly(kept: &[Pose], count: usize) -> Vec<Pose> {
    let n = count.min(kept.len());
    (0..n).map(|i| kept[i * kept.len() / n]).collect()
}

/// One simulated view's job and result.
#[derive(Debug, Clone, Copy)]
struct Job {
    candidate: usize,
    hypothesis: usize,
    camera_from_object: Pose,
    next_from_current: Pose,
    trace: Option<f64>,
    render_ms: f64,
    estimate_ms: f64,
}

/// The object models and the pose stages that score views.
#[derive(Debug)]
pub struct NbvPlanner {
    params: NbvParams,
    library: ModelLibrary,
    /// Each library object's symmetries (BOP discretisation).
    symmetries: Vec<SymmetrySet>,
    estimators: Vec<PoseStages>,
}

impl NbvPlanner {
    pub fn load(params: NbvParams) -> Result<Self, NbvError> {
        let library = ModelLibrary::load(&params.models, &[])
            .map_err(|e| NbvError::Objects { path: params.models.clone(), detail: e.to_string() })?;
        let registry = PoseStages::registry();
        let estimators =
            (0..params.workers).map(|_| PoseStages::start(&params.estimation, &registry)).collect::<Result<_, _>>()?;
        let symmetries =
            library.objects.iter().map(|o| SymmetrySet::from_model_info(&o.info, BOP_MAX_SYMMETRY_STEP)).collect();
        Ok(Self { params, library, symmetries, estimators })
    }

    pub fn params(&self) -> &NbvParams {
        &self.params
    }

    pub fn object_ids(&self) -> Vec<u32> {
        self.library.objects.iter().map(|o| o.obj_id).collect()
    }

    /// The candidate views around the object at `hypotheses[0]` (the
    /// middle of its model's bounding box: BOP origins need not be).
    pub fn candidates(
        &self,
        frame: u64,
        obj_id: u32,
        hypotheses: &[Pose],
        up: &Vector3<f64>,
    ) -> Result<Vec<Pose>, NbvError> {
        let best = hypotheses.first().ok_or_else(|| NbvError::Frame {
            frame,
            object: obj_id,
            detail: "the Estimate has no kept hypothesis".into(),
        })?;
        let index = find_object(&self.library, &self.params, frame, obj_id)?;
        let (low, high) = self.library.objects[index].model.mesh.bounds();
        let centre = best.transform_point(&Point3::from((low.coords + high.coords).cast::<f64>() / 2.0));
        Ok(candidate_views(&centre, up, &self.params.sphere))
    }

    /// Ranks the candidate views around the object at `hypotheses[0]` (and
    /// the current viewpoint first, when `include_current`) for object
    /// `obj_id` seen in frame `frame`; `up` is the world's up direction in
    /// the current camera frame (unit); `occluders`, the frame's observed
    /// surface, when known.
    pub fn plan(
        &mut self,
        frame: u64,
        obj_id: u32,
        hypotheses: &[Pose],
        up: &Vector3<f64>,
        occluders: Option<&Occluders>,
    ) -> Result<NextViewPlan, NbvError> {
        let started = Instant::now();
        let mut views = self.candidates(frame, obj_id, hypotheses, up)?;
        if self.params.include_current {
            views.insert(0, Pose::identity());
        }
        let mut plan = self.score_views(frame, obj_id, &views, hypotheses, occluders)?;
        plan.cost.wall_ms = started.elapsed().as_secs_f64() * 1e3;
        tracing::debug!(
            frame,
            object = obj_id,
            views = plan.cost.views,
            wall_ms = plan.cost.wall_ms,
            "next view planned"
        );
        Ok(plan)
    }

    /// Scores `views` (poses of candidate cameras in the current one) by
    /// the mean tr Σ_R the pose stages leave on renderings under
    /// `hypotheses` (spread evenly over them), hidden where `occluders`
    /// cover them; lowest first.
    pub fn score_views(
        &mut self,
        frame: u64,
        obj_id: u32,
        views: &[Pose],
        hypotheses: &[Pose],
        occluders: Option<&Occluders>,
    ) -> Result<NextViewPlan, NbvError> {
        let started = Instant::now();
        let index = find_object(&self.library, &self.params, frame, obj_id)?;
        let (model, symmetries) = (&self.library.objects[index].model, &self.symmetries[index]);
        if hypotheses.is_empty() {
            let detail = "the Estimate has no kept hypothesis".to_string();
            return Err(NbvError::Frame { frame, object: obj_id, detail });
        }
        let simulated = spread_evenly(hypotheses, self.params.hypotheses);
        let mut jobs: Vec<Job> = views
            .iter()
            .enumerate()
            .flat_map(|(candidate, view)| {
                simulated.iter().enumerate().map(move |(hypothesis, pose)| Job {
                    candidate,
                    hypothesis,
                    camera_from_object: view.inverse() * *pose,
                    next_from_current: view.inverse(),
                    trace: None,
                    render_ms: 0.0,
                    estimate_ms: 0.0,
                })
            })
            .collect();

        // The jobs are dealt round-robin to the workers, each with its own
        // pose stages; a job's result depends on its inputs alone, so the
        // ranking does not depend on the worker count.
        let params = &self.params;
        let workers = self.estimators.len();
        let results: Vec<Result<(), NbvError>> = std::thread::scope(|scope| {
            let mut shares: Vec<Vec<&mut Job>> = (0..workers).map(|_| Vec::new()).collect();
            for (i, job) in jobs.iter_mut().enumerate() {
                shares[i % workers].push(job);
            }
            let handles: Vec<_> = self
                .estimators
                .iter_mut()
                .zip(shares)
                .map(|(estimator, share)| {
                    scope.spawn(move || {
                        for job in share {
                            run_job(estimator, params, (model, symmetries), (frame, obj_id), occluders, job)?;
                        }
                        Ok(())
                    })
                })
                .collect();
            handles
                .into_iter()
                .map(|h| {
                    h.join().unwrap_or_else(|_| {
                        Err(NbvError::Frame { frame, object: obj_id, detail: "a scoring worker panicked".into() })
                    })
                })
                .collect()
        });
        results.into_iter().collect::<Result<(), _>>()?;

        let hypotheses_per_view = simulated.len().max(1);
        let mut scored: Vec<ScoredView> = views
            .iter()
            .enumerate()
            .map(|(c, view)| {
                let traces = jobs.iter().filter(|j| j.candidate == c).map(|j| j.trace);
                let (sum, uninformative) = traces.fold((0.0, 0), |(sum, none), trace| match trace {
                    Some(t) => (sum + t, none),
                    None => (sum + UNIFORM_ROTATION_TRACE, none + 1),
                });
                ScoredView { camera_from_next: *view, expected_trace: sum / hypotheses_per_view as f64, uninformative }
            })
            .collect();
        scored.sort_by(|a, b| a.expected_trace.total_cmp(&b.expected_trace));
        let cost = PlanCost {
            views: jobs.len(),
            render_ms: jobs.iter().map(|j| j.render_ms).sum(),
            estimate_ms: jobs.iter().map(|j| j.estimate_ms).sum(),
            wall_ms: started.elapsed().as_secs_f64() * 1e3,
        };
        Ok(NextViewPlan { views: scored, cost })
    }
}

/// Index of `obj_id` in `library`.
fn find_object(library: &ModelLibrary, params: &NbvParams, frame: u64, obj_id: u32) -> Result<usize, NbvError> {
    library.objects.iter().position(|o| o.obj_id == obj_id).ok_or_else(|| NbvError::Frame {
        frame,
        object: obj_id,
        detail: format!("no model of object {obj_id} in {}", params.models.display()),
    })
}

/// Renders one job's view and estimates on it; a view the ingest rejects
/// (too few points) is uninformative, any other failure is the plan's.
fn run_job(
    estimator: &mut PoseStages,
    params: &NbvParams,
    (model, symmetries): (&RenderModel, &SymmetrySet),
    (frame, obj_id): (u64, u32),
    occluders: Option<&Occluders>,
    job: &mut Job,
) -> Result<(), NbvError> {
    let view_id = (frame << 20) | ((job.candidate as u64) << 8) | job.hypothesis as u64;
    let mut rng = seeded_rng(sample_seed(params.seed, view_id, obj_id));
    let started = Instant::now();
    let viewpoint = Viewpoint {
        camera: &params.camera,
        camera_from_object: job.camera_from_object,
        occluders: occluders.map(|o| (o, job.next_from_current)),
    };
    let simulated = simulated_view(model, obj_id, &viewpoint, view_id, params.min_visible_pixels, &mut rng);
    job.render_ms = started.elapsed().as_secs_f64() * 1e3;
    let Some((rgbd, mask)) = simulated else {
        return Ok(());
    };
    let started = Instant::now();
    let estimated = estimator.estimate(&rgbd, &mask);
    job.estimate_ms = started.elapsed().as_secs_f64() * 1e3;
    let failed =
        |detail: String| NbvError::Frame { frame, object: obj_id, detail: format!("simulated view: {detail}") };
    if let Some((header, payload)) =
        estimated.map_err(|source| NbvError::View { frame, object: obj_id, source: Box::new(source) })?
    {
        let kept = header.kept_poses(&payload).map_err(|e| failed(e.to_string()))?;
        let rotations = kept
            .map(|values| Pose::from_f32_row_major(values).map(|pose| pose.rotation))
            .collect::<Result<Vec<_>, _>>()
            .map_err(|e| failed(e.to_string()))?;
        job.trace = Some(symmetries.folded_rotation_spread(&rotations));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use nalgebra::{Rotation3, Vector3};
    use poseflow_geometry::sampling::{seeded_rng, uniform_rotation};
    use poseflow_geometry::so3::geodesic_angle;

    use super::*;

    #[test]
    fn the_uniform_trace_is_the_mean_squared_angle_of_haar_rotations() {
        // Simpson's rule on E[θ²] = ∫ θ² (1 − cos θ)/π dθ over [0, π].
        let n = 2000;
        let h = std::f64::consts::PI / n as f64;
        let f = |theta: f64| theta * theta * (1.0 - theta.cos()) / std::f64::consts::PI;
        let simpson: f64 = (0..=n)
            .map(|i| {
                let weight = if i == 0 || i == n {
                    1.0
                } else if i % 2 == 1 {
                    4.0
                } else {
                    2.0
                };
                weight * f(i as f64 * h)
            })
            .sum::<f64>()
            * h
            / 3.0;
        assert!((simpson - UNIFORM_ROTATION_TRACE).abs() < 1e-9, "{simpson}");
        // And by sampling: 100,000 Haar rotations' mean squared angle.
        let mut rng = seeded_rng(3);
        let samples = 100_000;
        let mean = (0..samples)
            .map(|_| geodesic_angle(&uniform_rotation(&mut rng), &Rotation3::identity()).powi(2))
            .sum::<f64>()
            / samples as f64;
        assert!((mean - UNIFORM_ROTATION_TRACE).abs() < 0.03, "{mean}");
    }

    #[test]
    fn hypotheses_are_spread_over_the_kept_list() {
        let kept: Vec<Pose> =
            (0..10).map(|i| Pose::new(Rotation3::identity(), Vector3::new(f64::from(i), 0.0, 0.0))).collect();
        let xs = |poses: Vec<Pose>| poses.iter().map(|p| p.translation.x).collect::<Vec<_>>();
        assert_eq!(xs(spread_evenly(&kept, 3)), [0.0, 3.0, 6.0]);
        assert_eq!(xs(spread_evenly(&kept, 1)), [0.0]);
        assert_eq!(xs(spread_evenly(&kept[..2], 3)), [0.0, 1.0]);
        assert!(spread_evenly(&[], 3).is_empty());
    }
}
