//! The selector stage: Hypotheses in, Estimate out; Observations as a side
//! input (their points, for the model-based scores and refinement).

use std::collections::VecDeque;

use nalgebra::{Point3, Vector3};
use poseflow_contracts::{
    EstimateHeader, Header, HypothesesHeader, ObservationHeader, POSE_LEN, SelectionMethod, StampSlot,
    WEIGHTED_POSE_LEN, flags,
};
use poseflow_geometry::Pose;
use poseflow_runtime::{Emitter, Input, Joined, Transform};
use poseflow_scene::category::{Category, template};
use poseflow_scene::{ObjectGeometry, ObjectLibrary};

use crate::select::{Observed, scorer};
use crate::track::{Evidence, TrackMonitor, Verdict};
use crate::visibility::{DepthGrid, FitSettings, INSIDE_DEPTH, point_fit, silhouette};
use crate::{Method, Selection, SelectorError, SelectorParams, select};
use poseflow_geometry::metrics::Pinhole;

/// One Observation's points (camera frame, metres) and depth grid, kept
/// until its Hypotheses come.
#[derive(Debug)]
struct Kept {
    frame_id: u64,
    object_id: u32,
    /// Valid depth points the Observation had (before subsampling).
    valid_points: usize,
    /// The Observation's valid points, farthest-point ordered (so that a
    /// prefix is an even subsample).
    points: Vec<Point3<f64>>,
    camera: Pinhole,
    depth: Option<DepthGrid>,
}

impl Kept {
    /// The points the scores use: the first `count`.
    fn scored(&self, count: usize) -> &[Point3<f64>] {
        &self.points[..count.min(self.points.len())]
    }

    /// What the scores compare poses with: the first `count` points, and
    /// the depth grid.
    fn observed(&self, count: usize) -> Observed<'_> {
        Observed { points: self.scored(count), depth: self.depth.as_ref().map(|grid| (grid, &self.camera)) }
    }
}

#[derive(Debug)]
pub struct SelectorStage {
    params: SelectorParams,
    library: Option<ObjectLibrary>,
    observations: VecDeque<Kept>,
    /// With `tracking.check`.
    monitor: Option<TrackMonitor>,
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
        let monitor = params.tracking.check.then(|| TrackMonitor::new(params.tracking.clone()));
        Ok(Self { params, library, observations: VecDeque::new(), monitor })
    }

    pub fn params(&self) -> &SelectorParams {
        &self.params
    }

    /// Keeps an Observation's valid points in the camera frame (the first
    /// `score_points`, or all of them for the track check's silhouette), and
    /// its depth grid when it has one.
    pub fn keep_observation(&mut self, header: &ObservationHeader, payload: &[f32]) -> Result<(), SelectorError> {
        let view = header.view(payload).map_err(|e| SelectorError::Frame {
            frame: header.header.frame_id,
            object: header.header.object_id,
            detail: e.to_string(),
        })?;
        let scale = f64::from(header.point_scale);
        let centroid = Vector3::from(header.centroid.map(f64::from));
        let valid = (header.valid_point_count as usize).clamp(1, header.point_count as usize);
        let silhouette = self.monitor.as_ref().is_some_and(|m| m.params().min_covered > 0.0);
        let kept = if silhouette { valid } else { valid.min(self.params.score_points) };
        let points = view
            .points
            .chunks_exact(3)
            .take(kept)
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
        let depth = match header.depth_grid {
            0 => None,
            cells => Some(depth_grid(header, cells as usize, view.depth, view.mask)?),
        };
        self.observations.push_back(Kept {
            frame_id: header.header.frame_id,
            object_id: header.header.object_id,
            valid_points: header.valid_point_count as usize,
            points,
            depth,
            camera: Pinhole {
                fx: f64::from(header.intrinsics.fx),
                fy: f64::from(header.intrinsics.fy),
                cx: f64::from(header.intrinsics.cx),
                cy: f64::from(header.intrinsics.cy),
            },
        });
        Ok(())
    }

    /// Selects from one Hypotheses message; with the track check on, also
    /// returns the header bits of its verdict ([`TrackMonitor`]).
    pub fn select_and_check(
        &mut self,
        header: &HypothesesHeader,
        payload: &[f32],
    ) -> Result<(Selection, u32), SelectorError> {
        let (mut selection, observed) = self.select_for(header, payload)?;
        let Some(monitor) = &mut self.monitor else { return Ok((selection, 0)) };
        if header.header.has_flag(flags::UPSTREAM_RESTARTED) {
            monitor.reset();
        }
        let (frame, object) = (header.header.frame_id, header.header.object_id);
        if header.header.has_flag(flags::SEQUENCE_START) {
            monitor.forget(object);
        }
        let seen = observed.as_ref().map_or(Observed::points(&[]), |o| o.observed(self.params.score_points));
        let points = seen.points;
        let model = self.library.as_ref().and_then(|library| library.get(object));
        if let Some(model) = model.filter(|_| monitor.params().half_turns && !monitor.is_tracking(object))
            && selection.search_half_turns(model, seen, &self.params, HALF_TURN_CANDIDATES)
        {
            tracing::debug!(frame, object, "a candidate turned half a turn fits better: selected");
        }
        if let Some(model) = model
            && let Some(predicted) = monitor.motion_candidate(object, frame)
            && selection.consider(&[predicted], model, seen, &self.params)
        {
            tracing::debug!(frame, object, "the pose the motion predicts fits better: selected");
        }
        let settings = FitSettings {
            inlier_distance: monitor.params().inlier_distance,
            hidden_depth: INSIDE_DEPTH,
            reach: model.map_or(0.0, ObjectGeometry::extent),
        };
        let evidence = Evidence {
            frame_id: frame,
            continued: header.header.has_flag(flags::TRACKING),
            observed_points: observed.as_ref().map_or(0, |o| o.valid_points),
            fit: model.and_then(|model| point_fit(&selection.best, points, &settings, |y| model.grid().value(y))),
            silhouette: match (model, &observed) {
                (Some(model), Some(o)) if monitor.params().min_covered > 0.0 => {
                    silhouette(&selection.best, model.surface(), &o.points, &o.camera, SILHOUETTE_CELLS)
                }
                _ => None,
            },
            free_space: model
                .and_then(|model| scorer(&self.params, model, seen))
                .and_then(|s| s.free_space(&selection.best)),
            spread_deg: selection.statistics.rotation_covariance().trace().max(0.0).sqrt().to_degrees(),
            pose: selection.best,
        };
        let verdict = monitor.check(object, &evidence);
        log_verdict(frame, object, &evidence, &verdict);
        Ok((selection, verdict.flags()))
    }

    /// Selects from one Hypotheses message; the Observation it used.
    fn select_for(
        &mut self,
        header: &HypothesesHeader,
        payload: &[f32],
    ) -> Result<(Selection, Option<Kept>), SelectorError> {
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
        let template = match self.params.category_templates {
            true => Some(template_geometry(header, self.params.sdf_resolution).map_err(in_frame)?),
            false => None,
        };
        let model = match (&self.library, &template) {
            (_, Some(template)) => Some(template),
            (Some(library), None) => Some(library.get(object).ok_or_else(|| {
                in_frame(format!(
                    "no model of object {object} in {} (objects there: {:?})",
                    library.dir.display(),
                    library.ids()
                ))
            })?),
            (None, None) => None,
        };
        let selection =
            select(&hypotheses, observed.as_ref().map(|o| o.observed(self.params.score_points)), model, &self.params)
                .map_err(|e| in_frame(e.to_string()))?;
        Ok((selection, observed))
    }
}

/// The template a category-level message is scored against: its
/// category's mean shape stretched to the predicted size. Built per message
/// (a mesh of about a thousand vertices; its SDF grid only if refinement or
/// the free-space test asks for it).
fn template_geometry(header: &HypothesesHeader, sdf_resolution: usize) -> Result<ObjectGeometry, String> {
    let category = &header.category;
    let kind = Category::from_code(category.code).ok_or_else(|| match category.code {
        0 => "category_templates: the Hypotheses carry no category (an instance-level model?)".to_string(),
        code => format!(
            "category_templates: no template for category code {code} (templates: {})",
            Category::ALL.map(|c| format!("{} {}", c.code(), c.name())).join(", ")
        ),
    })?;
    let mesh = template(kind, Vector3::from(category.size));
    ObjectGeometry::from_mesh(category.code, mesh.vertices, mesh.triangles, sdf_resolution)
        .map_err(|e| format!("the {} template at size {:?}: {e}", kind.name(), category.size))
}

/// The depth grid of an Observation: the crop scaled by `depth_span` about
/// its centre. A span or crop that is not a finite positive square is
/// refused, naming the field.
fn depth_grid(
    header: &ObservationHeader,
    cells: usize,
    depth: &[f32],
    mask: &[f32],
) -> Result<DepthGrid, SelectorError> {
    let bad = |detail: String| SelectorError::Frame {
        frame: header.header.frame_id,
        object: header.header.object_id,
        detail,
    };
    let [x0, y0, x1, _] = header.crop.map(f64::from);
    let (span, side) = (f64::from(header.depth_span), x1 - x0);
    if !(span.is_finite() && span > 0.0) {
        return Err(bad(format!("Observation depth_span {span}: expected a positive factor")));
    }
    if !(x0.is_finite() && y0.is_finite() && side.is_finite() && side > 0.0) {
        return Err(bad(format!("Observation crop {:?}: expected a square of positive side", header.crop)));
    }
    let grow = side * (span - 1.0) / 2.0;
    Ok(DepthGrid {
        x_min: x0 - grow,
        y_min: y0 - grow,
        side: side * span,
        cells,
        depth: depth.to_vec(),
        mask: mask.iter().map(|&m| m > 0.5).collect(),
    })
}

/// Candidates turned over while re-acquiring an object: the best two, so
/// that a second mode near the best is tried as well (six refinements).
const HALF_TURN_CANDIDATES: usize = 2;

/// Cells across the silhouette's larger side: with 1,024 points spread
/// over a fully visible mask, several points per cell.
const SILHOUETTE_CELLS: usize = 16;

/// Logs a track check: `info` when the state changes, `debug` otherwise,
/// with the evidence (rounded) and the failures.
fn log_verdict(frame: u64, object: u32, evidence: &Evidence, verdict: &Verdict) {
    let changed = verdict.before != verdict.after;
    if !changed && !tracing::enabled!(tracing::Level::DEBUG) {
        return;
    }
    let round = |v: f64| (v * 1e3).round() / 1e3;
    let fit = evidence.fit;
    let inlier_share = fit.map_or(f64::NAN, |f| round(f.inlier_share));
    let rms_mm = fit.map_or(f64::NAN, |f| round(f.rms_residual * 1e3));
    let hidden = fit.map_or(f64::NAN, |f| round(f.hidden_share));
    let covered = evidence.silhouette.map_or(f64::NAN, |s| round(s.covered));
    let seen_past = evidence.free_space.map_or(f64::NAN, |found| round(found.share()));
    let spread_deg = round(evidence.spread_deg);
    let jump_deg = verdict.jump.map_or(f64::NAN, |(degrees, _)| (degrees * 10.0).round() / 10.0);
    let failures = verdict.failures.iter().map(ToString::to_string).collect::<Vec<_>>().join("; ");
    let points = evidence.observed_points;
    if changed {
        tracing::info!(frame, object, from = ?verdict.before, to = ?verdict.after, points, inlier_share, rms_mm, hidden,
            covered, seen_past, spread_deg, jump_deg, failures, "track state changed");
    } else {
        tracing::debug!(frame, object, state = ?verdict.after, points, inlier_share, rms_mm, hidden, covered,
            seen_past, spread_deg, jump_deg, failures, "track check");
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
        category: Default::default(),
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
        let (selection, track_flags) = self.select_and_check(header, input.payload)?;
        let mut forwarded = input.forward_header();
        forwarded.flags |= track_flags;
        let estimate = EstimateHeader { category: header.category, ..estimate_header(&selection, forwarded) };
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
    if params.tracking.check && wiring.side_inputs.is_empty() {
        return Err(format!(
            "stage `{}`: the track check (`tracking.check`) counts the observed points: list the Observation edge in `side_inputs`",
            wiring.stage
        )
        .into());
    }
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

#[cfg(test)]
mod tests {
    use super::*;
    use poseflow_contracts::ObjectCategory;

    fn observation(crop: [f32; 4], depth_span: f32) -> ObservationHeader {
        ObservationHeader { header: Header::new(7, 3), crop, depth_grid: 2, depth_span, ..Default::default() }
    }

    /// An Observation of `points` (camera frame, metres) with a tiny
    /// image and no depth grid.
    fn observation_of(points: &[Point3<f64>]) -> (ObservationHeader, Vec<f32>) {
        let centroid = points.iter().fold(Vector3::zeros(), |sum, p| sum + p.coords) / points.len() as f64;
        let header = ObservationHeader {
            header: Header::new(7, 3),
            centroid: centroid.cast::<f32>().into(),
            point_scale: 1.0,
            image_size: 16,
            patch_grid: 2,
            point_count: points.len() as u32,
            valid_point_count: points.len() as u32,
            ..Default::default()
        };
        let mut payload = vec![0.0; 3 * 16 * 16 + 4];
        payload.extend(points.iter().flat_map(|p| (p.coords - centroid).cast::<f32>().data.0[0]));
        (header, payload)
    }

    #[test]
    fn category_templates_score_against_the_mean_shape_at_the_predicted_size() {
        // A can (not the mean one) seen from the front; hypotheses: the truth,
        // the truth 3 cm off, and the truth tipped 30° over.
        let can = poseflow_scene::category::generate(Category::Can, 11);
        let size = can.size;
        let geometry = ObjectGeometry::from_mesh(4, can.mesh.vertices.clone(), can.mesh.triangles.clone(), 32).unwrap();
        let truth = Pose::new(nalgebra::Rotation3::from_euler_angles(-1.2, 0.3, 0.2), Vector3::new(0.02, -0.01, 0.7));
        let points: Vec<Point3<f64>> = geometry
            .surface()
            .iter()
            .map(|p| truth.transform_point(p))
            .filter(|p| p.z < truth.translation.z)
            .take(300)
            .collect();
        let params = SelectorParams::from_json(&serde_json::json!({
            "method": "chamfer", "category_templates": true, "keep_fraction": 0.3, "keep_margin": 0.0
        }))
        .unwrap();
        let mut stage = SelectorStage::new(params).unwrap();
        let tipped =
            Pose::new(truth.rotation * nalgebra::Rotation3::from_euler_angles(0.52, 0.0, 0.0), truth.translation);
        let shifted = Pose::new(truth.rotation, truth.translation + Vector3::new(0.03, 0.0, 0.0));
        let hypotheses: Vec<f32> = [shifted, tipped, truth].iter().flat_map(|p| p.to_f32_row_major()).collect();
        let category = ObjectCategory { code: Category::Can.code(), size: size.into() };
        let header = HypothesesHeader { header: Header::new(7, 3), sample_count: 3, step_count: 5, category };
        let (observation, payload) = observation_of(&points);
        stage.keep_observation(&observation, &payload).unwrap();
        let (selection, _) = stage.select_and_check(&header, &hypotheses).unwrap();
        assert!(selection.best.translation.metric_distance(&truth.translation) < 1e-6, "{:?}", selection.best);
        assert_eq!(selection.kept, 1);

        // Without a category (an instance-level model), the template is refused by name.
        let instance = HypothesesHeader { category: ObjectCategory::default(), ..header };
        stage.keep_observation(&observation, &payload).unwrap();
        let error = stage.select_and_check(&instance, &hypotheses).unwrap_err().to_string();
        assert!(error.contains("frame 7") && error.contains("carry no category"), "{error}");
        // A category without a template (3: camera) is named.
        let camera = HypothesesHeader { category: ObjectCategory { code: 3, ..category }, ..header };
        stage.keep_observation(&observation, &payload).unwrap();
        let error = stage.select_and_check(&camera, &hypotheses).unwrap_err().to_string();
        assert!(error.contains("category code 3"), "{error}");
    }

    #[test]
    fn the_depth_grid_spans_the_crop_scaled_about_its_centre() {
        let grid =
            depth_grid(&observation([10.0, 20.0, 30.0, 40.0], 2.0), 2, &[0.5, 0.0, 1.0, 2.0], &[1.0, 0.0, 0.0, 1.0])
                .unwrap();
        assert_eq!((grid.x_min, grid.y_min, grid.side, grid.cells), (0.0, 10.0, 40.0, 2));
        assert_eq!(grid.mask, [true, false, false, true]);
        assert_eq!(grid.depth, [0.5, 0.0, 1.0, 2.0]);
    }

    #[test]
    fn a_bad_span_or_crop_is_refused_by_name() {
        for (crop, span, field) in [
            ([10.0, 20.0, 30.0, 40.0], f32::NAN, "depth_span NaN"),
            ([10.0, 20.0, 30.0, 40.0], 0.0, "depth_span 0"),
            ([10.0, 20.0, 10.0, 40.0], 2.0, "crop"),
            ([f32::INFINITY, 20.0, 30.0, 40.0], 2.0, "crop"),
        ] {
            let err = depth_grid(&observation(crop, span), 2, &[0.0; 4], &[0.0; 4]).unwrap_err().to_string();
            assert!(err.contains(field) && err.contains("frame 7"), "{err}");
        }
    }
}
