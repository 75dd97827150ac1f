//! The grasp stage: Estimate in, Grasps out.

use poseflow_contracts::{EstimateHeader, GRASP_LEN, GraspsHeader, POSE_LEN, StampSlot};
use poseflow_geometry::Pose;
use poseflow_runtime::{Emitter, Input, Transform};

use crate::{GraspError, GraspField, GraspPlanner, Gripper, PlannedGrasp};

#[derive(Debug)]
pub struct GraspStage<F: GraspField> {
    planner: GraspPlanner<F>,
}

impl<F: GraspField> GraspStage<F> {
    pub fn new(planner: GraspPlanner<F>) -> Self {
        Self { planner }
    }
}

/// The kept hypotheses of an Estimate (object-to-camera), best first.
pub fn kept_hypotheses(header: &EstimateHeader, payload: &[f32]) -> Result<Vec<Pose>, GraspError> {
    let (frame, object) = (header.header.frame_id, header.header.object_id);
    let in_frame = |detail: String| GraspError::Frame { frame, object, detail };
    let kept = header.kept_poses(payload).map_err(|e| in_frame(e.to_string()))?;
    kept.enumerate()
        .map(|(i, values)| Pose::from_f32_row_major(values).map_err(|e| in_frame(format!("hypothesis {i}: {e}"))))
        .collect()
}

/// One grasp as the Grasps payload holds it: pose, width, valid share,
/// score ([`PlannedGrasp::score`]: what a robot should rank by).
pub fn grasp_values(grasp: &PlannedGrasp, gripper: &Gripper) -> [f32; GRASP_LEN] {
    let mut values = [0.0; GRASP_LEN];
    values[..POSE_LEN].copy_from_slice(&grasp.camera_from_grasp.to_f32_row_major());
    values[POSE_LEN] = grasp.width;
    values[POSE_LEN + 1] = grasp.valid_share as f32;
    values[POSE_LEN + 2] = grasp.score(gripper) as f32;
    values
}

impl<F: GraspField> Transform for GraspStage<F> {
    type In = EstimateHeader;
    type Out = GraspsHeader;
    type Error = GraspError;
    const SLOT: Option<StampSlot> = Some(StampSlot::Grasp);

    fn process(
        &mut self,
        input: Input<'_, EstimateHeader>,
        output: &mut dyn Emitter<GraspsHeader>,
    ) -> Result<(), GraspError> {
        let header = input.header;
        let (frame, object) = (header.header.frame_id, header.header.object_id);
        let _span = tracing::debug_span!("grasp", frame, object).entered();
        let hypotheses = kept_hypotheses(header, input.payload)?;
        let grasps = self.planner.plan(frame, object, &hypotheses)?;
        let params = self.planner.params();
        let used = hypotheses.len().min(params.hypotheses);
        let out = GraspsHeader {
            header: input.forward_header(),
            grasp_count: grasps.len() as u32,
            hypothesis_count: used as u32,
        };
        output.emit(out, grasps.len() * GRASP_LEN, &mut |payload| {
            for (chunk, grasp) in payload.chunks_exact_mut(GRASP_LEN).zip(&grasps) {
                chunk.copy_from_slice(&grasp_values(grasp, &params.gripper));
            }
        })?;
        Ok(())
    }
}
