//! Next-best-view planning (paper, "Active Perception"): the viewpoint
//! expected to leave the least rotational uncertainty,
//! v* = argmin_v E[tr(Σ_R | v)], approximated by sampling.
//!
//! - [`candidate_views`]: cameras on a sphere around the object, within an
//!   elevation band, looking at its centre;
//! - [`simulate::simulated_view`]: the object rendered at a hypothesis from
//!   a candidate, with sensor noise, hidden where the current frame's
//!   observed surface ([`Occluders`]) lies in front of it;
//! - [`NbvPlanner`]: for every candidate, the pose stages (their own
//!   registrations, in-process: [`ESTIMATION_GRAPH`]) on the views simulated under a few of the
//!   Estimate's hypotheses, ranked by the mean trace they leave; the same
//!   code runs in-process and as the stage ([`stage::NbvStage`]).

mod candidates;
mod error;
mod occluders;
mod params;
mod planner;
mod pose_stages;
pub mod simulate;
pub mod stage;

pub use candidates::candidate_views;
pub use error::NbvError;
pub use occluders::Occluders;
pub use params::{ESTIMATION_GRAPH, NbvParams, ViewSphere};
pub use planner::{NbvPlanner, NextViewPlan, PlanCost, ScoredView, UNIFORM_ROTATION_TRACE, spread_evenly};
pub use pose_stages::{PoseStages, PoseStagesError};

/// The stage of this crate: `nbv` (Estimate in, NextView out; the Frames as
/// a side input let it judge what hides the object from each candidate).
pub fn registrations() -> Vec<poseflow_runtime::Registration> {
    vec![poseflow_runtime::Registration::transform_or_joined("nbv", |wiring| {
        let planner = NbvPlanner::load(NbvParams::from_json(&wiring.params)?)?;
        let params = planner.params();
        tracing::info!(
            model = %params.estimation.stages["inference"].params["model"],
            objects = ?planner.object_ids(),
            candidates = params.sphere.candidates,
            hypotheses = params.hypotheses,
            workers = params.workers,
            occluders = !wiring.side_inputs.is_empty(),
            "next-best-view stage ready"
        );
        Ok::<_, poseflow_runtime::BuildError>(stage::NbvStage::new(planner))
    })]
}
