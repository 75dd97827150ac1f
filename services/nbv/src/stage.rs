//! The next-best-view stage: Estimate in, NextView out.

use poseflow_contracts::{CANDIDATE_LEN, EstimateHeader, NextViewHeader, Stage};
use poseflow_geometry::Pose;
use poseflow_runtime::{Emitter, Input, Transform};

use crate::{NbvError, NbvPlanner, NextViewPlan};

#[derive(Debug)]
pub struct NbvStage {
    planner: NbvPlanner,
}

impl NbvStage {
    pub fn new(planner: NbvPlanner) -> Self {
        Self { planner }
    }
}

/// The kept hypotheses of an Estimate (object-to-camera), best first.
pub fn kept_hypotheses(header: &EstimateHeader, payload: &[f32]) -> Result<Vec<Pose>, NbvError> {
    let (frame, object) = (header.header.frame_id, header.header.object_id);
    let in_frame = |detail: String| NbvError::Frame { frame, object, detail };
    let kept = header.kept_poses(payload).map_err(|e| in_frame(e.to_string()))?;
    kept.enumerate()
        .map(|(i, values)| Pose::from_f32_row_major(values).map_err(|e| in_frame(format!("hypothesis {i}: {e}"))))
        .collect()
}

/// The NextView header (without the common header) and payload of a plan.
pub fn next_view_message(plan: &NextViewPlan, current_trace: f32) -> (NextViewHeader, Vec<f32>) {
    let best = &plan.views[0];
    let header = NextViewHeader {
        chosen: best.camera_from_next.to_f32_row_major(),
        expected_rotation_trace: best.expected_trace as f32,
        current_rotation_trace: current_trace,
        candidate_count: plan.views.len() as u32,
        ..Default::default()
    };
    let mut payload = Vec::with_capacity(plan.views.len() * CANDIDATE_LEN);
    for view in &plan.views {
        payload.extend_from_slice(&view.camera_from_next.to_f32_row_major());
        payload.push(view.expected_trace as f32);
    }
    (header, payload)
}

impl Transform for NbvStage {
    type In = EstimateHeader;
    type Out = NextViewHeader;
    type Error = NbvError;
    const SLOT: Option<Stage> = Some(Stage::NextView);

    fn process(
        &mut self,
        input: Input<'_, EstimateHeader>,
        output: &mut dyn Emitter<NextViewHeader>,
    ) -> Result<(), NbvError> {
        let header = input.header;
        let (frame, object) = (header.header.frame_id, header.header.object_id);
        let _span = tracing::debug_span!("nbv", frame, object).entered();
        let hypotheses = kept_hypotheses(header, input.payload)?;
        let up = self.planner.params().up;
        let plan = self.planner.plan(frame, object, &hypotheses, &up)?;
        tracing::info!(
            frame,
            object,
            current = header.rotation_trace,
            expected = plan.views[0].expected_trace,
            views = plan.cost.views,
            wall_ms = plan.cost.wall_ms,
            "next view"
        );
        let (next, payload) = next_view_message(&plan, header.rotation_trace);
        let out = NextViewHeader { header: input.forward_header(), ..next };
        output.emit(out, payload.len(), &mut |buffer| buffer.copy_from_slice(&payload))?;
        Ok(())
    }
}
