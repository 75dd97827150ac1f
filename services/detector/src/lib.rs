//! Detector stage: finds the known objects in an RGB-D frame and publishes
//! the frame again with its detections (object id, instance, score, box and
//! visible mask), the Frame contract that ingest reads. It stands between a
//! frame source that has no masks (a camera, a dataset without ground
//! truth) and ingest.
//!
//! `mode = "network"` (the default) runs a small RGB-D segmentation network
//! exported to ONNX ([`network`]), trained on the project's renders by
//! `training/poseflow_train/detector.py`. Each object's pixels become
//! detections by [`instances::detections`].
//!
//! `mode = "classical"` needs no training, only the objects' meshes: the
//! support plane removed, the depth clustered, and each cluster identified
//! by fitting the known objects to it ([`classical`]).

pub mod classical;
pub mod identify;
pub mod instances;
pub mod network;
pub mod stage;
pub mod tabletop;

mod error;

use std::path::PathBuf;

pub use classical::{ClassicalDetector, ClassicalParams};
pub use error::DetectorError;
pub use identify::{Identifier, Relabelled};
pub use instances::{Found, FrameGrid, InstanceRules, LabelMap};
pub use network::{ImageView, SegmentationNetwork};
use serde::Deserialize;

/// One detection in frame pixels.
#[derive(Debug, Clone, PartialEq)]
pub struct DetectedObject {
    pub obj_id: u32,
    /// 0 for an object's first instance (the most confident), 1 for its
    /// second, …
    pub instance: u32,
    /// Mean probability of the object over its mask, 0–1.
    pub score: f32,
    /// `x, y, width, height` in pixels.
    pub bbox: [u32; 4],
    /// `width · height` values, row-major over the box: whether the object
    /// is seen at that pixel.
    pub mask: Vec<bool>,
}

impl DetectedObject {
    /// How the mask overlaps a whole-frame mask `other` (row-major, `width`
    /// columns, covering the box): the mask's pixels and, of those, the ones
    /// also in `other`.
    pub fn overlap(&self, other: &[bool], width: usize) -> (usize, usize) {
        let [x, y, w, _] = self.bbox.map(|v| v as usize);
        let (mut mine, mut both) = (0, 0);
        for (row, line) in self.mask.chunks(w.max(1)).enumerate() {
            for (col, &inside) in line.iter().enumerate() {
                if inside {
                    mine += 1;
                    both += usize::from(other.get((y + row) * width + x + col).copied().unwrap_or(false));
                }
            }
        }
        (mine, both)
    }

    /// Intersection over union with a whole-frame mask `other` (`width`
    /// columns); 0 when both are empty.
    pub fn iou(&self, other: &[bool], width: usize) -> f64 {
        let (mine, both) = self.overlap(other, width);
        let union = mine + other.iter().filter(|&&inside| inside).count() - both;
        if union == 0 { 0.0 } else { both as f64 / union as f64 }
    }

    /// Grows the mask by `by` pixels: every pixel within `by` columns and
    /// `by` rows of a mask pixel joins it (a dilation by a (2·by + 1)²
    /// square). The box grows by `by` on each side, clipped to the
    /// `width × height` frame. A mask whose length is not its box's area
    /// is left as it is.
    pub fn grow(&mut self, by: usize, width: usize, height: usize) {
        let [x, y, w, h] = self.bbox.map(|v| v as usize);
        if by == 0 || w == 0 || h == 0 || self.mask.len() != w * h {
            return;
        }
        let (x0, y0) = (x.saturating_sub(by), y.saturating_sub(by));
        let (x1, y1) = ((x + w + by).min(width.max(x + w)), (y + h + by).min(height.max(y + h)));
        let (grown_w, grown_h) = (x1 - x0, y1 - y0);
        // Along the rows into the grown box's columns, then along its columns.
        let mut across = Vec::with_capacity(h * grown_w);
        for row in self.mask.chunks(w) {
            across.extend(within_reach(row.iter().copied(), x, x0, grown_w, by));
        }
        let mut grown = vec![false; grown_w * grown_h];
        for c in 0..grown_w {
            let column = across.iter().skip(c).step_by(grown_w).copied();
            for (g, inside) in within_reach(column, y, y0, grown_h, by).enumerate() {
                grown[g * grown_w + c] = inside;
            }
        }
        self.bbox = [x0, y0, grown_w, grown_h].map(|v| v as u32);
        self.mask = grown;
    }

    /// The mask over a whole `width × height` frame, row-major.
    pub fn frame_mask(&self, width: usize, height: usize) -> Vec<bool> {
        let mut frame = vec![false; width * height];
        let [x, y, w, _] = self.bbox.map(|v| v as usize);
        for (row, line) in self.mask.chunks(w.max(1)).enumerate() {
            for (col, &inside) in line.iter().enumerate() {
                if inside && x + col < width && y + row < height {
                    frame[(y + row) * width + x + col] = true;
                }
            }
        }
        frame
    }
}

/// For each frame position `first..first + count`: whether `line`, which
/// starts at frame position `origin`, holds a set value within `by` of it.
fn within_reach(
    line: impl Iterator<Item = bool>,
    origin: usize,
    first: usize,
    count: usize,
    by: usize,
) -> impl Iterator<Item = bool> {
    let mut prefix = vec![0usize];
    for inside in line {
        prefix.push(prefix[prefix.len() - 1] + usize::from(inside));
    }
    let len = prefix.len() - 1;
    (first..first + count).map(move |at| {
        // The window [at − by, at + by] within the line, as indices.
        let lo = (at.saturating_sub(by).max(origin) - origin).min(len);
        let hi = (at + by + 1).min(origin + len).saturating_sub(origin);
        hi > lo && prefix[hi] > prefix[lo]
    })
}

/// Parameters of the detector stage (`config/detector.toml` and a graph's
/// `params`).
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DetectorParams {
    /// `network`: the learned detector; `classical`: plane, clusters and
    /// model fits (the `classical` table).
    #[serde(default)]
    pub mode: Mode,
    /// Directory of the network (`detector.onnx`, `detector.json`, and
    /// optionally the identifier, `identify.onnx` and `identify.json`).
    #[serde(default = "default_model")]
    pub model: PathBuf,
    /// Relabel each region by the model directory's identifier, when it has
    /// one (`false`: the segmentation's labels as they are).
    #[serde(default = "yes")]
    pub identify: bool,
    /// ONNX Runtime threads (network), or threads fitting objects at
    /// once (classical).
    #[serde(default = "one")]
    pub threads: usize,
    /// Only these objects are reported (empty: every object the network
    /// knows).
    #[serde(default)]
    pub objects: Vec<u32>,
    /// Regions smaller than this many frame pixels are dropped.
    #[serde(default = "default_min_pixels")]
    pub min_pixels: usize,
    /// Regions of one object whose boxes are at most this many pixels apart
    /// are one instance (0: boxes that overlap).
    #[serde(default = "default_merge_gap")]
    pub merge_gap_px: usize,
    /// Instances reported per object, most confident first.
    #[serde(default = "one")]
    pub max_instances: usize,
    /// Instances whose mean probability is lower are dropped.
    #[serde(default = "default_min_score")]
    pub min_score: f32,
    /// Masks follow depth edges within a block: a neighbouring cell's vote
    /// for a pixel halves (e^-½) at this depth difference in metres. 0 scales
    /// the label map up block by block.
    #[serde(default = "default_edge_depth")]
    pub edge_depth_m: f32,
    /// Network masks grown by this many pixels (a dilation by a square),
    /// before the table is dropped: the pose model, trained on annotated
    /// masks, loses more on a mask too narrow than on one too wide.
    #[serde(default = "default_grow")]
    pub grow_px: usize,
    /// Mask pixels less than this many metres in front of the frame's
    /// support plane (or behind it) are dropped: the table around an
    /// object's foot. 0: masks keep them.
    #[serde(default = "default_support_plane")]
    pub support_plane_m: f64,
    /// Settings of `mode = "classical"`.
    #[serde(default)]
    pub classical: ClassicalParams,
}

#[derive(Debug, Clone, Copy, Default, PartialEq, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Mode {
    #[default]
    Network,
    Classical,
}

fn default_model() -> PathBuf {
    PathBuf::from("models/detector-lmo10")
}
fn one() -> usize {
    1
}
fn yes() -> bool {
    true
}
fn default_min_pixels() -> usize {
    64
}
fn default_merge_gap() -> usize {
    0
}
fn default_min_score() -> f32 {
    0.3
}
fn default_edge_depth() -> f32 {
    0.01
}
fn default_grow() -> usize {
    1
}
fn default_support_plane() -> f64 {
    0.005
}

impl DetectorParams {
    pub fn from_json(value: &serde_json::Value) -> Result<Self, DetectorError> {
        let params: Self =
            serde_json::from_value(value.clone()).map_err(|e| DetectorError::ParamsFormat(e.to_string()))?;
        let bad = |key: &str, detail: String| Err(DetectorError::Params { key: key.into(), detail });
        if !(1..=64).contains(&params.threads) {
            return bad("threads", format!("expected 1 to 64, got {}", params.threads));
        }
        if params.max_instances == 0 {
            return bad("max_instances", "expected at least 1".into());
        }
        if !(0.0..=1.0).contains(&params.min_score) {
            return bad("min_score", format!("expected a probability from 0 to 1, got {}", params.min_score));
        }
        if !(params.edge_depth_m.is_finite() && params.edge_depth_m >= 0.0) {
            return bad("edge_depth_m", format!("expected metres, 0 or more, got {}", params.edge_depth_m));
        }
        if params.grow_px > 16 {
            return bad("grow_px", format!("expected 0 to 16 pixels, got {}", params.grow_px));
        }
        if !(params.support_plane_m.is_finite() && params.support_plane_m >= 0.0) {
            return bad("support_plane_m", format!("expected metres, 0 or more, got {}", params.support_plane_m));
        }
        if params.mode == Mode::Classical {
            params.classical.check()?;
        }
        Ok(params)
    }

    pub fn rules(&self) -> InstanceRules {
        InstanceRules {
            min_pixels: self.min_pixels,
            merge_gap_px: self.merge_gap_px,
            max_instances: self.max_instances,
            min_score: self.min_score,
            edge_depth_m: self.edge_depth_m,
            // A region the identifier and the segmentation disagree on can be
            // larger than the object's own region and would win on size.
            most_confident_first: true,
        }
    }
}

/// What finds the objects' pixels.
#[derive(Debug)]
enum Backend {
    Network(Box<Learned>),
    Classical(Box<ClassicalDetector>),
}

/// The network mode's networks: the segmentation and, when the model
/// directory has one, the identifier.
#[derive(Debug)]
struct Learned {
    segmentation: SegmentationNetwork,
    identifier: Option<Identifier>,
}

/// A ready detector: the network (or the classical fits) and the rules that
/// turn its labels into detections.
#[derive(Debug)]
pub struct Detector {
    backend: Backend,
    params: DetectorParams,
}

impl Detector {
    pub fn new(params: DetectorParams) -> Result<Self, DetectorError> {
        let (backend, source) = match params.mode {
            Mode::Network => {
                let segmentation = SegmentationNetwork::load(&params.model, params.threads)?;
                let identifier = if params.identify {
                    Identifier::load(&params.model, params.threads, &segmentation.meta().object_ids)?
                } else {
                    None
                };
                (Backend::Network(Box::new(Learned { segmentation, identifier })), params.model.clone())
            }
            Mode::Classical => {
                let classical = ClassicalDetector::new(params.classical.clone(), &params.objects, params.threads)?;
                let dir = classical.models_dir().to_path_buf();
                (Backend::Classical(Box::new(classical)), dir)
            }
        };
        let known = match &backend {
            Backend::Network(learned) => learned.segmentation.meta().object_ids.clone(),
            Backend::Classical(classical) => classical.object_ids().to_vec(),
        };
        let unknown: Vec<u32> = params.objects.iter().copied().filter(|id| !known.contains(id)).collect();
        if !unknown.is_empty() {
            tracing::warn!(
                objects = ?unknown,
                model = %source.display(),
                known = ?known,
                "objects the detector does not know are never detected"
            );
        }
        let mut params = params;
        params.objects.retain(|id| known.contains(id));
        if params.objects.is_empty() && !unknown.is_empty() {
            return Err(DetectorError::Params {
                key: "objects".into(),
                detail: format!("none of {unknown:?} is known to the detector at {} ({known:?})", source.display()),
            });
        }
        let identifies = matches!(&backend, Backend::Network(learned) if learned.identifier.is_some());
        tracing::info!(mode = ?params.mode, model = %source.display(), objects = ?params.objects, identifies, "detector ready");
        Ok(Self { backend, params })
    }

    /// The objects of the label map, label k being the k-th.
    fn labelled_ids(&self) -> &[u32] {
        match &self.backend {
            Backend::Network(learned) => &learned.segmentation.meta().object_ids,
            Backend::Classical(classical) => classical.object_ids(),
        }
    }

    /// The objects this detector can report.
    pub fn object_ids(&self) -> Vec<u32> {
        if self.params.objects.is_empty() { self.labelled_ids().to_vec() } else { self.params.objects.clone() }
    }

    /// The detections of one frame: the heart of the stage.
    pub fn detect(&mut self, image: &ImageView<'_>) -> Result<Found, DetectorError> {
        let map = match &mut self.backend {
            Backend::Network(learned) => {
                let Learned { segmentation, identifier } = learned.as_mut();
                let mut map = segmentation.segment(image)?;
                if let Some(identifier) = identifier {
                    let cell_pixels = (image.width * image.height) as f64 / (map.width * map.height) as f64;
                    let min_cells = (self.params.min_pixels as f64 / cell_pixels).ceil() as usize;
                    let relabelled = identifier.relabel(&mut map, image, min_cells, Some(segmentation.posteriors()))?;
                    tracing::debug!(?relabelled, "regions identified");
                }
                map
            }
            Backend::Classical(classical) => classical.segment(image),
        };
        let frame = FrameGrid { width: image.width, height: image.height, depth: image.depth };
        let mut found = instances::detections(&map, self.labelled_ids(), &frame, &self.params.rules());
        if !self.params.objects.is_empty() {
            found.objects.retain(|o| self.params.objects.contains(&o.obj_id));
        }
        if matches!(self.backend, Backend::Network(_)) {
            for object in &mut found.objects {
                object.grow(self.params.grow_px, image.width, image.height);
            }
        }
        if self.params.support_plane_m > 0.0 {
            let removed = tabletop::drop_support_pixels(&mut found.objects, image, self.params.support_plane_m);
            tracing::debug!(pixels = removed, "table pixels removed from the masks");
        }
        Ok(found)
    }
}

/// The 4-neighbours of cell `i` in a row-major `width × height` grid.
pub(crate) fn grid_neighbours(i: usize, width: usize, height: usize) -> [Option<usize>; 4] {
    let (x, y) = (i % width, i / width);
    [
        (x > 0).then(|| i - 1),
        (x + 1 < width).then(|| i + 1),
        (y > 0).then(|| i - width),
        (y + 1 < height).then(|| i + width),
    ]
}

/// The stages of this crate, by executable name.
pub fn registrations() -> Vec<poseflow_runtime::Registration> {
    vec![poseflow_runtime::Registration::transform("detector", |wiring| {
        DetectorParams::from_json(&wiring.params).and_then(stage::DetectorStage::new)
    })]
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn square(x: u32, y: u32, side: u32) -> DetectedObject {
        let n = (side * side) as usize;
        DetectedObject { obj_id: 1, instance: 0, score: 1.0, bbox: [x, y, side, side], mask: vec![true; n] }
    }

    #[test]
    fn overlap_of_two_squares_is_their_closed_form() {
        // 4×4 at (2, 0) against 4×4 at (0, 0) in a 10 × 6 frame: 2·4 shared.
        let truth = square(0, 0, 4).frame_mask(10, 6);
        let detection = square(2, 0, 4);
        assert_eq!(detection.overlap(&truth, 10), (16, 8));
        assert!((detection.iou(&truth, 10) - 8.0 / 24.0).abs() < 1e-12);
        assert_eq!(detection.iou(&[false; 60], 10), 0.0);
    }

    proptest! {
        #[test]
        fn a_detection_covers_its_own_frame_mask_exactly(
            x in 0u32..8, y in 0u32..6, w in 1u32..6, h in 1u32..5, bits in proptest::collection::vec(any::<bool>(), 30)
        ) {
            let mask: Vec<bool> = (0..(w * h) as usize).map(|i| bits[i % bits.len()]).collect();
            let pixels = mask.iter().filter(|&&m| m).count();
            let detection = DetectedObject { obj_id: 3, instance: 0, score: 0.5, bbox: [x, y, w, h], mask };
            let frame = detection.frame_mask(16, 12);
            prop_assert_eq!(frame.iter().filter(|&&m| m).count(), pixels);
            prop_assert_eq!(detection.overlap(&frame, 16), (pixels, pixels));
            prop_assert_eq!(detection.iou(&frame, 16), if pixels == 0 { 0.0 } else { 1.0 });
        }
    }

    #[test]
    fn a_grown_pixel_is_a_square_clipped_at_the_frame() {
        let mut pixel = square(1, 4, 1);
        pixel.grow(2, 10, 6);
        // Columns 0..=3 (clipped at the left edge), rows 2..=5 (clipped below).
        assert_eq!(pixel.bbox, [0, 2, 4, 4]);
        assert!(pixel.mask.iter().all(|&m| m));
        let mut unchanged = square(3, 3, 2);
        unchanged.grow(0, 10, 6);
        assert_eq!(unchanged, square(3, 3, 2));
    }

    proptest! {
        #[test]
        fn growing_a_mask_is_the_dilation_by_a_square(
            x in 0u32..8, y in 0u32..6, w in 1u32..6, h in 1u32..5, by in 0usize..4,
            bits in proptest::collection::vec(any::<bool>(), 30)
        ) {
            let (width, height) = (14usize, 11usize);
            let mask: Vec<bool> = (0..(w * h) as usize).map(|i| bits[i % bits.len()]).collect();
            let mut detection = DetectedObject { obj_id: 3, instance: 0, score: 0.5, bbox: [x, y, w, h], mask };
            let before = detection.frame_mask(width, height);
            detection.grow(by, width, height);
            prop_assert_eq!(detection.mask.len(), (detection.bbox[2] * detection.bbox[3]) as usize);
            prop_assert!(detection.bbox[0] + detection.bbox[2] <= width as u32);
            prop_assert!(detection.bbox[1] + detection.bbox[3] <= height as u32);
            let near = |u: usize, v: usize| {
                (v.saturating_sub(by)..=(v + by).min(height - 1))
                    .any(|q| (u.saturating_sub(by)..=(u + by).min(width - 1)).any(|p| before[q * width + p]))
            };
            let expected: Vec<bool> = (0..width * height).map(|i| near(i % width, i / width)).collect();
            prop_assert_eq!(detection.frame_mask(width, height), expected);
        }
    }

    #[test]
    fn bad_parameters_are_refused_naming_the_key() {
        let refused = |json: serde_json::Value| DetectorParams::from_json(&json).unwrap_err().to_string();
        for (json, key) in [
            (serde_json::json!({ "threads": 0 }), "threads"),
            (serde_json::json!({ "max_instances": 0 }), "max_instances"),
            (serde_json::json!({ "min_score": 1.5 }), "min_score"),
            (serde_json::json!({ "edge_depth_m": -0.01 }), "edge_depth_m"),
            (serde_json::json!({ "support_plane_m": -0.005 }), "support_plane_m"),
            (serde_json::json!({ "grow_px": 17 }), "grow_px"),
            (serde_json::json!({ "edge_depth": 0.01 }), "edge_depth"),
        ] {
            let message = refused(json.clone());
            assert!(message.contains(key), "{json}: {message}");
        }
        let defaults = DetectorParams::from_json(&serde_json::json!({})).unwrap();
        assert_eq!(defaults.rules().edge_depth_m, 0.01);
    }
}
