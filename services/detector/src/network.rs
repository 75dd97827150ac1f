//! The learned detector: a small RGB-D segmentation network (ONNX) that
//! labels each pixel of a downsampled frame with the object seen there.
//!
//! A model directory holds `detector.onnx` and `detector.json`:
//!
//! - input `rgbd`, float32 N × 5 × H × W, channels RGB / 255, depth in
//!   metres / `depth_scale_m` (0 = no measurement), and 1 where depth was
//!   measured; H × W is the frame sampled at the centre pixel of each
//!   `down` × `down` block (a 640 × 480 frame: 120 × 160 with `down` 4);
//! - output `probabilities`, float32 N × (1 + K) × H × W: class 0 is
//!   background, class k the k-th of `object_ids`.
//!
//! A network trained with class weights in its loss (background weighted
//! less, since most pixels are background) predicts each class as if it
//! were its weight times as likely as it is, which grows every mask by
//! its uncertain border. `detector.json`'s `class_weights` records them, and
//! the labels are taken from the probabilities divided by them.

use std::path::{Path, PathBuf};

use ort::session::Session;
use ort::value::{TensorElementType, TensorRef};
use poseflow_geometry::metrics::Pinhole;
use serde::Deserialize;

use crate::DetectorError;
use crate::instances::LabelMap;

/// The format `detector.json` must declare.
pub const FORMAT: &str = "poseflow-detector/1";

/// `detector.json`.
#[derive(Debug, Clone, Deserialize)]
pub struct DetectorMeta {
    pub format: String,
    pub object_ids: Vec<u32>,
    pub input: InputSpec,
    /// The loss weight of each class in training, background first (absent:
    /// all equal).
    #[serde(default)]
    pub class_weights: Option<Vec<f32>>,
}

impl DetectorMeta {
    /// Each class's weight, background first: `class_weights` or ones.
    pub fn weights(&self) -> Vec<f32> {
        self.class_weights.clone().unwrap_or_else(|| vec![1.0; self.object_ids.len() + 1])
    }
}

/// The network's input size and scaling.
#[derive(Debug, Clone, Copy, Deserialize, PartialEq)]
pub struct InputSpec {
    pub height: usize,
    pub width: usize,
    pub down: usize,
    pub depth_scale_m: f32,
}

/// One RGB-D frame as the Frame contract carries it: `rgb` 3·W·H
/// row-major interleaved 0–255, `depth` W·H metres (0 = none), and the
/// camera's intrinsics (pixels).
#[derive(Debug, Clone, Copy)]
pub struct ImageView<'a> {
    pub rgb: &'a [f32],
    pub depth: &'a [f32],
    pub width: usize,
    pub height: usize,
    pub camera: Pinhole,
}

/// The network's input for one frame, channel-major (5 × H × W). Each input
/// pixel is the frame pixel at the centre of its block, the frame stretched
/// to H × W when its size is not `down` times the input's. Depth is rounded
/// to whole millimetres, as the training data stores it. `out` is resized
/// and overwritten.
pub fn network_input(image: &ImageView<'_>, spec: &InputSpec, out: &mut Vec<f32>) {
    let (h, w) = (spec.height, spec.width);
    let plane = h * w;
    out.resize(5 * plane, 0.0);
    for y in 0..h {
        let v = ((2 * y + 1) * image.height / (2 * h)).min(image.height - 1);
        for x in 0..w {
            let u = ((2 * x + 1) * image.width / (2 * w)).min(image.width - 1);
            let pixel = v * image.width + u;
            let i = y * w + x;
            for c in 0..3 {
                out[c * plane + i] = image.rgb[3 * pixel + c] / 255.0;
            }
            let depth = image.depth[pixel];
            let depth_mm = if depth.is_finite() && depth > 0.0 { (depth * 1000.0).round().min(65535.0) } else { 0.0 };
            out[3 * plane + i] = depth_mm / (1000.0 * spec.depth_scale_m);
            out[4 * plane + i] = if depth_mm > 0.0 { 1.0 } else { 0.0 };
        }
    }
}

/// Each pixel's most probable class and its probability, from `N = 1`
/// probabilities of `weights.len()` planes divided by the classes'
/// training weights and normalised, with the depth the network saw in
/// `input` (its [`network_input`]). `posteriors` is overwritten with those
/// normalised probabilities, class-major like the network's output.
pub fn label_map(
    probabilities: &[f32],
    weights: &[f32],
    spec: &InputSpec,
    input: &[f32],
    posteriors: &mut Vec<f32>,
) -> LabelMap {
    let plane = spec.height * spec.width;
    let mut labels = vec![0u8; plane];
    let mut best = vec![f32::NEG_INFINITY; plane];
    let mut total = vec![0.0f32; plane];
    posteriors.resize(weights.len() * plane, 0.0);
    // Plane by plane, not pixel by pixel: every pass reads and writes
    // contiguous memory (a 240 × 320 map of 11 classes is 3.4 MB).
    for (c, weight) in weights.iter().enumerate() {
        let scaled = &mut posteriors[c * plane..(c + 1) * plane];
        for (((q, &p), (b, label)), t) in scaled
            .iter_mut()
            .zip(&probabilities[c * plane..(c + 1) * plane])
            .zip(best.iter_mut().zip(labels.iter_mut()))
            .zip(total.iter_mut())
        {
            *q = p / weight;
            *t += *q;
            if *q > *b {
                (*b, *label) = (*q, c as u8);
            }
        }
    }
    // The winner's share, in place: `best` becomes the confidence.
    for (b, &t) in best.iter_mut().zip(&total) {
        *b = if t > 0.0 { *b / t } else { 0.0 };
    }
    for class in posteriors.chunks_exact_mut(plane) {
        for (q, &t) in class.iter_mut().zip(&total) {
            *q = if t > 0.0 { *q / t } else { 0.0 };
        }
    }
    let depth = input[3 * plane..4 * plane].iter().map(|d| d * spec.depth_scale_m).collect();
    LabelMap { width: spec.width, height: spec.height, labels, confidence: best, depth, instances: Vec::new() }
}

/// A loaded detector network.
#[derive(Debug)]
pub struct SegmentationNetwork {
    session: Session,
    meta: DetectorMeta,
    /// [`DetectorMeta::weights`].
    weights: Vec<f32>,
    path: PathBuf,
    /// The input tensor, reused from frame to frame.
    input: Vec<f32>,
    /// The last frame's [`label_map`] posteriors.
    posteriors: Vec<f32>,
}

impl SegmentationNetwork {
    /// Loads `dir/detector.onnx` described by `dir/detector.json`, checking
    /// both against the contract above.
    pub fn load(dir: &Path, threads: usize) -> Result<Self, DetectorError> {
        let meta_path = dir.join("detector.json");
        let bad = |detail: String| DetectorError::Model { path: meta_path.clone(), detail };
        let text = std::fs::read_to_string(&meta_path).map_err(|e| {
            bad(format!("cannot read ({e}); a detector model directory holds detector.json and detector.onnx"))
        })?;
        let meta: DetectorMeta = serde_json::from_str(&text).map_err(|e| bad(e.to_string()))?;
        if meta.format != FORMAT {
            return Err(bad(format!("format is `{}`, expected `{FORMAT}`", meta.format)));
        }
        let classes = meta.object_ids.len() + 1;
        if meta.object_ids.is_empty() || classes > 256 {
            return Err(bad(format!("object_ids: expected 1 to 255 ids, found {}", meta.object_ids.len())));
        }
        if let Some(weights) = &meta.class_weights
            && (weights.len() != classes || !weights.iter().all(|w| w.is_finite() && *w > 0.0))
        {
            return Err(bad(format!(
                "class_weights: expected {classes} positive weights (background, then each object id), found {weights:?}"
            )));
        }
        let spec = meta.input;
        if spec.height == 0
            || spec.width == 0
            || spec.down == 0
            || spec.depth_scale_m.is_nan()
            || spec.depth_scale_m <= 0.0
        {
            return Err(bad(format!("input: expected positive height, width, down and depth_scale_m, found {spec:?}")));
        }
        let path = dir.join("detector.onnx");
        let session = poseflow_onnx::session(&path, threads, "the detector network beside detector.json")?;
        use TensorElementType::Float32 as F;
        let (h, w) = (spec.height as i64, spec.width as i64);
        poseflow_onnx::check_ports(
            &path,
            "inputs",
            session.inputs(),
            &[poseflow_onnx::port("rgbd", F, &[-1, 5, h, w])],
        )?;
        poseflow_onnx::check_ports(
            &path,
            "outputs",
            session.outputs(),
            &[poseflow_onnx::port("probabilities", F, &[-1, classes as i64, h, w])],
        )?;
        let weights = meta.weights();
        Ok(Self { session, meta, weights, path, input: Vec::new(), posteriors: Vec::new() })
    }

    pub fn meta(&self) -> &DetectorMeta {
        &self.meta
    }

    /// Labels every input pixel of one frame.
    pub fn segment(&mut self, image: &ImageView<'_>) -> Result<LabelMap, DetectorError> {
        let spec = self.meta.input;
        network_input(image, &spec, &mut self.input);
        let run_error = |e: ort::Error| DetectorError::Run { path: self.path.clone(), detail: e.to_string() };
        let tensor =
            TensorRef::from_array_view(([1, 5, spec.height, spec.width], &self.input[..])).map_err(run_error)?;
        let outputs = self.session.run(ort::inputs!["rgbd" => tensor]).map_err(run_error)?;
        let (_, probabilities) = outputs["probabilities"].try_extract_tensor::<f32>().map_err(run_error)?;
        Ok(label_map(probabilities, &self.weights, &spec, &self.input, &mut self.posteriors))
    }

    /// The last segmented frame's class probabilities per map cell, the
    /// training weights divided out: class-major, `(1 + K) × H × W`.
    pub fn posteriors(&self) -> &[f32] {
        &self.posteriors
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const SPEC: InputSpec = InputSpec { height: 2, width: 3, down: 2, depth_scale_m: 2.0 };

    #[test]
    fn the_input_takes_each_blocks_centre_pixel_and_scales_it() {
        // A 6 × 4 frame whose pixel (u, v) has red u, green v, blue 255 and
        // depth (u + 10v) mm, except pixel (3, 1) which has none.
        let (fw, fh) = (6, 4);
        let mut rgb = Vec::new();
        let mut depth = Vec::new();
        for v in 0..fh {
            for u in 0..fw {
                rgb.extend([u as f32, v as f32, 255.0]);
                depth.push(if (u, v) == (3, 1) { 0.0 } else { (u + 10 * v) as f32 / 1000.0 });
            }
        }
        let mut input = Vec::new();
        let camera = Pinhole { fx: 1.0, fy: 1.0, cx: 0.0, cy: 0.0 };
        network_input(&ImageView { rgb: &rgb, depth: &depth, width: fw, height: fh, camera }, &SPEC, &mut input);
        let plane = 6;
        // Input pixel (x, y) samples frame pixel (2x + 1, 2y + 1).
        assert_eq!(&input[..plane], &[1.0, 3.0, 5.0, 1.0, 3.0, 5.0].map(|u: f32| u / 255.0));
        assert_eq!(&input[plane..2 * plane], &[1.0, 1.0, 1.0, 3.0, 3.0, 3.0].map(|v: f32| v / 255.0));
        assert!(input[2 * plane..3 * plane].iter().all(|&b| b == 1.0));
        assert_eq!(input[3 * plane + 3], 31.0 / 2000.0);
        assert_eq!((input[3 * plane + 1], input[4 * plane + 1]), (0.0, 0.0), "no depth at (3, 1)");
        assert_eq!(input[4 * plane], 1.0);
    }

    #[test]
    fn labels_are_the_most_probable_class() {
        // Three classes over six pixels; pixel i's winner is i % 3.
        let mut probabilities = vec![0.1; 3 * 6];
        for i in 0..6 {
            probabilities[(i % 3) * 6 + i] = 0.8;
        }
        // Depth plane: 0.25 · (pixel index) in units of depth_scale_m.
        let mut input = vec![0.0; 5 * 6];
        for i in 0..6 {
            input[3 * 6 + i] = 0.25 * i as f32;
        }
        let map = label_map(&probabilities, &[1.0; 3], &SPEC, &input, &mut Vec::new());
        assert_eq!(map.labels, [0, 1, 2, 0, 1, 2]);
        assert!(map.confidence.iter().all(|&c| (c - 0.8).abs() < 1e-6));
        assert_eq!(map.depth, [0.0, 0.5, 1.0, 1.5, 2.0, 2.5], "metres, depth_scale_m being 2");
    }

    #[test]
    fn class_weights_of_training_are_divided_out() {
        // Background 0.4 against an object 0.6 from a network that weighted
        // background 0.2: really 2 : 0.6, so background at 0.4 / 0.2 /
        // (2 + 0.6) ≈ 0.77.
        let probabilities = [0.4, 0.9, 0.6, 0.1];
        let spec = InputSpec { height: 1, width: 2, down: 1, depth_scale_m: 1.0 };
        let mut posteriors = Vec::new();
        let map = label_map(&probabilities, &[0.2, 1.0], &spec, &[0.0; 10], &mut posteriors);
        assert_eq!(map.labels, [0, 0]);
        assert!((map.confidence[0] - 2.0 / 2.6).abs() < 1e-6, "{:?}", map.confidence);
        assert!((posteriors[0] - 2.0 / 2.6).abs() < 1e-6 && (posteriors[2] - 0.6 / 2.6).abs() < 1e-6);
        assert!((posteriors[1] + posteriors[3] - 1.0).abs() < 1e-6, "normalised: {posteriors:?}");
        let unweighted = label_map(&probabilities, &[1.0, 1.0], &spec, &[0.0; 10], &mut Vec::new());
        assert_eq!(unweighted.labels, [1, 0]);
    }

    proptest::proptest! {
        #[test]
        fn each_pixel_gets_its_largest_weighted_probability_normalised(
            probabilities in proptest::collection::vec(0.0f32..1.0, 4 * 6),
            weights in proptest::collection::vec(0.05f32..2.0, 4),
        ) {
            let mut posteriors = Vec::new();
            let map = label_map(&probabilities, &weights, &SPEC, &[0.0; 5 * 6], &mut posteriors);
            for i in 0..6 {
                let scaled: Vec<f32> = (0..4).map(|c| probabilities[c * 6 + i] / weights[c]).collect();
                let total: f32 = scaled.iter().sum();
                let winner = (0..4).fold(0, |w, c| if scaled[c] > scaled[w] { c } else { w });
                proptest::prop_assert_eq!(map.labels[i] as usize, winner);
                if total > 0.0 {
                    proptest::prop_assert!((map.confidence[i] - scaled[winner] / total).abs() < 1e-5);
                    let sum: f32 = (0..4).map(|c| posteriors[c * 6 + i]).sum();
                    proptest::prop_assert!((sum - 1.0).abs() < 1e-4, "pixel {} sums to {}", i, sum);
                } else {
                    proptest::prop_assert_eq!(map.confidence[i], 0.0);
                }
            }
        }
    }
}
