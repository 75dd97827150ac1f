//! The pose stages of a graph in this process, one frame at a time: what
//! the planner estimates simulated views with, and what the simulations
//! estimate with. The stages are built by their own registrations, as in
//! every graph.

use poseflow_contracts::{EstimateHeader, FrameHeader};
use poseflow_graph::Graph;
use poseflow_ingest::sources::LoadedFrame;
use poseflow_ingest::{ObjectMask, RgbdFrame, frame_message};
use poseflow_launch::{DrivenGraph, LaunchError};
use poseflow_runtime::Registry;

/// Why a frame got no Estimate for a reason other than showing too little.
#[derive(Debug, thiserror::Error)]
pub enum PoseStagesError {
    #[error(transparent)]
    Launch(#[from] LaunchError),

    #[error("the ingest stage observed the object but no Estimate came out (the stages' log says why)")]
    NoEstimate,
}

/// A graph's stages from its `frames` edge to its `estimates` edge,
/// in-process: a frame with one object mask in, that object's Estimate out.
#[derive(Debug)]
pub struct PoseStages {
    graph: DrivenGraph<FrameHeader, EstimateHeader>,
    /// Observations the ingest stage has sent so far.
    observed: u64,
}

impl PoseStages {
    /// The registrations of the pose stages (ingest, inference, sampler,
    /// selector).
    pub fn registry() -> Registry {
        Registry::new()
            .with(poseflow_ingest::registrations())
            .with(poseflow_inference::registrations())
            .with(poseflow_sampler::registrations())
            .with(poseflow_selector::registrations())
    }

    /// Starts the stages of `graph` between `frames` and `estimates` and
    /// waits until each is built.
    pub fn start(graph: &Graph, registry: &Registry) -> Result<Self, LaunchError> {
        Ok(Self { graph: DrivenGraph::start(graph, registry, "frames", "estimates")?, observed: 0 })
    }

    /// The Estimate of `object` in `frame`; `None` when the ingest stage
    /// rejected it (too few points: its log line says so).
    pub fn estimate(
        &mut self,
        frame: &RgbdFrame,
        object: &ObjectMask,
    ) -> Result<Option<(EstimateHeader, Vec<f32>)>, PoseStagesError> {
        let view = LoadedFrame {
            frame: frame.clone(),
            objects: vec![object.clone()],
            skipped: Vec::new(),
            scene_id: 0,
            image_id: 0,
            captured_ns: None,
        };
        let (header, payload) = frame_message(&view);
        let mut estimates = self.graph.process(header, payload)?;
        let observed = self.graph.counters().get("ingest").map_or(0, |beat| beat.frames_out);
        let was_observed = std::mem::replace(&mut self.observed, observed) < observed;
        match estimates.pop() {
            Some(estimate) => Ok(Some(estimate)),
            None if was_observed => Err(PoseStagesError::NoEstimate),
            None => Ok(None),
        }
    }
}
