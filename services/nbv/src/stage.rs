//! The next-best-view stage: Estimate in, NextView out; the Frames as an
//! optional side input tell it what may hide the object from a candidate.

use std::collections::VecDeque;

use poseflow_contracts::{CANDIDATE_LEN, EstimateHeader, FrameHeader, NextViewHeader, StampSlot};
use poseflow_geometry::Pose;
use poseflow_ingest::{ObjectMask, RgbdFrame, read_frame};
use poseflow_runtime::{Emitter, Input, Joined, Transform};

use crate::{NbvError, NbvPlanner, NextViewPlan, Occluders};

#[derive(Debug)]
pub struct NbvStage {
    planner: NbvPlanner,
    /// The latest frames (depth and object masks; the colours dropped),
    /// oldest first.
    frames: VecDeque<(RgbdFrame, Vec<ObjectMask>)>,
    /// Estimates planned without their frame (no side input, or the frame
    /// was no longer kept).
    without_frame: u64,
}

impl NbvStage {
    pub fn new(planner: NbvPlanner) -> Self {
        Self { planner, frames: VecDeque::new(), without_frame: 0 }
    }

    /// Keeps a frame for the Estimates of its objects.
    pub fn keep_frame(&mut self, header: &FrameHeader, payload: &[f32]) -> Result<(), NbvError> {
        let frame = header.header.frame_id;
        let (mut rgbd, masks) =
            read_frame(header, payload).map_err(|e| NbvError::SideFrame { frame, detail: e.to_string() })?;
        rgbd.rgb.pixels = Vec::new();
        if self.frames.len() == self.planner.params().frames {
            self.frames.pop_front();
        }
        self.frames.push_back((rgbd, masks));
        Ok(())
    }

    /// The NextView (header without the common header, payload) of an
    /// Estimate, with the occluders of its frame when that is kept.
    pub fn next_view(
        &mut self,
        header: &EstimateHeader,
        payload: &[f32],
    ) -> Result<(NextViewHeader, Vec<f32>), NbvError> {
        let (frame, object) = (header.header.frame_id, header.header.object_id);
        let hypotheses = kept_hypotheses(header, payload)?;
        let up = self.planner.params().up;
        let occluders = self.occluders(frame, object);
        if occluders.is_none() {
            self.without_frame += 1;
            if self.without_frame == 1 {
                tracing::warn!(
                    frame,
                    object,
                    "no frame for this Estimate (is `frames` a side input?): planning without occluders; counted as without_frame"
                );
            }
        }
        let plan = self.planner.plan(frame, object, &hypotheses, &up, occluders.as_ref())?;
        tracing::info!(
            frame,
            object,
            current = header.rotation_trace,
            expected = plan.views[0].expected_trace,
            views = plan.cost.views,
            wall_ms = plan.cost.wall_ms,
            render_ms = plan.cost.render_ms,
            estimate_ms = plan.cost.estimate_ms,
            occluders = occluders.as_ref().map_or(0, Occluders::len),
            without_frame = self.without_frame,
            "next view"
        );
        Ok(next_view_message(&plan, header.rotation_trace))
    }

    /// The observed surface of `frame` around `object`, when the frame is
    /// kept and shows the object.
    pub fn occluders(&self, frame: u64, object: u32) -> Option<Occluders> {
        let (rgbd, masks) = self.frames.iter().find(|(f, _)| f.frame_id == frame)?;
        let target = masks.iter().find(|m| m.obj_id == object)?;
        Some(Occluders::from_depth(rgbd, target, self.planner.params().occluder_stride))
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
    const SLOT: Option<StampSlot> = Some(StampSlot::NextView);

    fn process(
        &mut self,
        input: Input<'_, EstimateHeader>,
        output: &mut dyn Emitter<NextViewHeader>,
    ) -> Result<(), NbvError> {
        let header = input.header;
        let _span =
            tracing::debug_span!("nbv", frame = header.header.frame_id, object = header.header.object_id).entered();
        let (next, payload) = self.next_view(header, input.payload)?;
        let out = NextViewHeader { header: input.forward_header(), ..next };
        output.emit(out, payload.len(), &mut |buffer| buffer.copy_from_slice(&payload))?;
        Ok(())
    }
}

impl Joined for NbvStage {
    type Side = FrameHeader;

    fn side(&mut self, input: Input<'_, FrameHeader>) -> Result<(), NbvError> {
        self.keep_frame(input.header, input.payload)
    }
}
