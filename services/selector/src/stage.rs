//! The selector stage: Hypotheses in, Estimate out; Observations as a side
//! input (their points, for the model-based scores and refinement).

use std::collections::VecDeque;

use nalgebra::{Point3, Vector3};
use poseflow_contracts::{
    EstimateHeader, Header, HypothesesHeader, ObservationHeader, POSE_LEN, SelectionMethod, StampSlot,
    WEIGHTED_POSE_LEN,
};
use poseflow_geometry::Pose;
use poseflow_runtime::{Emitter, Input, Joined, Transform};

use crate::{Method, ObjectLibrary, Selection, SelectorError, SelectorParams, select};

/// One Observation's points (camera frame, metres), kept until its
/// Hypotheses come.
#[derive(Debug)]
struct Observed {
    frame_id: u64,
    object_id: u32,
    points: Vec<Point3<f64>>,
}

#[derive(Debug)]
pub struct SelectorStage {
    params: SelectorParams,
    library: Option<ObjectLibrary>,
    observations: VecDeque<Observed>,
}

impl SelectorStage {
    /// Loads the object models when the parameters need them.
    pub fn new(params: SelectorParams) -> Result<Self, SelectorError> {
        params.validate()?;
        let library = match (&params.models, params.needs_models()) {
            (Some(dir), true) => Some(ObjectLibrary::load(dir, params.sdf_resolution)?),
            _ => None,
        };
        // The grids are built now rather than on an object's first frame,
        // whose latency they would otherwise take.
        if let (Some(library), true) = (&library, params.method == Method::Sdf || params.refine) {
            library.build_grids();
        }
        Ok(Self { params, library, observations: VecDeque::new() })
    }

    pub fn params(&self) -> &SelectorParams {
        &self.params
    }

    /// Keeps the first `score_points` points of an Observation (a prefix of
    /// the farthest-point order: an even subsample) in the camera frame.
    pub fn keep_observation(&mut self, header: &ObservationHeader, payload: &[f32]) -> Result<(), SelectorError> {
        let view = header.view(payload).map_err(|e| SelectorError::Frame {
            frame: header.header.frame_id,
            object: header.header.object_id,
            detail: e.to_string(),
        })?;
        let scale = f64::from(header.point_scale);
        let centroid = Vector3::from(header.centroid.map(f64::from));
        let valid = (header.valid_point_count as usize).clamp(1, header.point_count as usize);
        let points = view
            .points
            .chunks_exact(3)
            .take(valid.min(self.params.score_points))
            .map(|p| Point3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2])) * scale + centroid)
            .collect();
        if self.observations.len() == self.params.observations {
            let old = self.observations.pop_front().expect("not empty");
            tracing::warn!(
                frame = old.frame_id,
                object = old.object_id,
                "observation evicted before its hypotheses came"
            );
        }
        self.observations.push_back(Observed {
            frame_id: header.header.frame_id,
            object_id: header.header.object_id,
            points,
        });
        Ok(())
    }

    /// Selects from one Hypotheses message.
    pub fn select_for(&mut self, header: &HypothesesHeader, payload: &[f32]) -> Result<Selection, SelectorError> {
        let (frame, object) = (header.header.frame_id, header.header.object_id);
        let in_frame = |detail: String| SelectorError::Frame { frame, object, detail };
        let hypotheses = payload
            .chunks_exact(POSE_LEN)
            .enumerate()
            .map(|(i, chunk)| {
                Pose::from_f32_row_major(chunk.try_into().expect("12 values"))
                    .map_err(|e| in_frame(format!("hypothesis {i}: {e}")))
            })
            .collect::<Result<Vec<_>, _>>()?;
        let observed = self
            .observations
            .iter()
            .position(|o| o.frame_id == frame && o.object_id == object)
            .and_then(|i| self.observations.remove(i));
        let model = match &self.library {
            Some(library) => Some(library.get(object).ok_or_else(|| {
                in_frame(format!(
                    "no model of object {object} in {} (objects there: {:?})",
                    library.dir.display(),
                    library.ids()
                ))
            })?),
            None => None,
        };
        select(&hypotheses, observed.as_ref().map(|o| o.points.as_slice()), model, &self.params)
            .map_err(|e| in_frame(e.to_string()))
    }
}

/// The Estimate header for `selection`, published under `header`.
pub fn estimate_header(selection: &Selection, header: Header) -> EstimateHeader {
    let covariance = &selection.statistics.covariance;
    EstimateHeader {
        header,
        best: selection.best.to_f32_row_major(),
        mean: selection.statistics.mean.mean.to_f32_row_major(),
        covariance: std::array::from_fn(|i| covariance[(i / 6, i % 6)] as f32),
        rotation_trace: selection.statistics.rotation_covariance().trace() as f32,
        selection: match selection.method {
            Method::None => SelectionMethod::None,
            Method::ModelFree => SelectionMethod::ModelFree,
            Method::Chamfer => SelectionMethod::Chamfer,
            Method::Sdf => SelectionMethod::Sdf,
        } as u32,
        mode_count: selection.modes.len() as u32,
        hypothesis_count: selection.scored.len() as u32,
        kept_count: selection.kept as u32,
        refined: u32::from(selection.refined),
    }
}

/// Writes the Estimate payload: modes, then every hypothesis with its score.
pub fn write_estimate_payload(selection: &Selection, out: &mut [f32]) {
    let entries = selection.modes.iter().chain(&selection.scored);
    for (chunk, (pose, value)) in out.chunks_exact_mut(WEIGHTED_POSE_LEN).zip(entries) {
        chunk[..POSE_LEN].copy_from_slice(&pose.to_f32_row_major());
        chunk[POSE_LEN] = *value as f32;
    }
}

/// Floats in the Estimate payload of `selection`.
pub fn estimate_payload_len(selection: &Selection) -> usize {
    (selection.modes.len() + selection.scored.len()) * WEIGHTED_POSE_LEN
}

impl Transform for SelectorStage {
    type In = HypothesesHeader;
    type Out = EstimateHeader;
    type Error = SelectorError;
    const SLOT: Option<StampSlot> = Some(StampSlot::Selector);

    fn process(
        &mut self,
        input: Input<'_, HypothesesHeader>,
        output: &mut dyn Emitter<EstimateHeader>,
    ) -> Result<(), SelectorError> {
        let header = input.header;
        let _span =
            tracing::debug_span!("select", frame = header.header.frame_id, object = header.header.object_id).entered();
        let selection = self.select_for(header, input.payload)?;
        let estimate = estimate_header(&selection, input.forward_header());
        output.emit(estimate, estimate_payload_len(&selection), &mut |out| write_estimate_payload(&selection, out))?;
        Ok(())
    }
}

impl Joined for SelectorStage {
    type Side = ObservationHeader;

    fn side(&mut self, input: Input<'_, ObservationHeader>) -> Result<(), SelectorError> {
        self.keep_observation(input.header, input.payload)
    }
}

/// Builds the selector stage from its wiring; a method that scores the
/// observed points needs the Observation edge among the side inputs.
pub fn from_wiring(wiring: &poseflow_graph::StageWiring) -> Result<SelectorStage, poseflow_runtime::BuildError> {
    let params = SelectorParams::from_json(&wiring.params)?;
    if params.needs_models() && wiring.side_inputs.is_empty() {
        return Err(format!(
            "stage `{}`: method {:?}{} scores the observed points: list the Observation edge in `side_inputs`",
            wiring.stage,
            params.method,
            if params.refine { " with refine" } else { "" }
        )
        .into());
    }
    let stage = SelectorStage::new(params)?;
    tracing::info!(method = ?stage.params().method, refine = stage.params().refine, "selector ready");
    Ok(stage)
}
