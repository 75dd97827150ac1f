//! `poseflow eval --detect`, the detector's half: the detector run over
//! every image of a BOP split, its masks scored against the visible masks
//! of the annotated instances.
//!
//! A detection matches the unmatched instance of its object with the
//! highest mask IoU; at IoU ≥ 0.5 it is a true positive (AP50), else a
//! false positive. Instances under 10 % visible (BOP19's threshold) are
//! ignored: a detection matching one is neither. AP is the area under the
//! precision–recall curve with precision made monotone (all points, as
//! PASCAL VOC 2010+). Mask IoU per object is the mean over its instances
//! of the best IoU any detection of the object reached with it (0 when
//! none overlaps): how well the masks fit, misses included.

use std::collections::BTreeMap;
use std::path::Path;

use anyhow::Context;
use poseflow_detector::{DetectedObject, Detector, ImageView};
use poseflow_scene::bop::{
    ByImage, CameraEntry, GtEntry, GtInfoEntry, SceneDir, read_depth_png, read_json, read_mask_png, read_rgb_png,
};
use serde::Serialize;

use crate::dataset::MIN_VISIB_FRACT;

/// The mask IoU at which a detection is a true positive (AP50).
pub const MATCH_IOU: f64 = 0.5;

/// One annotated instance's visible mask over the whole image.
#[derive(Debug, Clone)]
pub struct TruthMask {
    pub obj_id: u32,
    pub mask: Vec<bool>,
    /// Pixels inside `mask`.
    pub area: usize,
    /// Under [`MIN_VISIB_FRACT`] visible: neither hit nor missed.
    pub ignored: bool,
}

/// IoU of a detection (its box and mask) with a truth's whole-image mask of
/// `width` columns.
pub fn mask_iou(detection: &DetectedObject, truth: &TruthMask, width: usize) -> f64 {
    BestMatch::of(detection, truth, width).iou
}

/// An instance's best-overlapping detection of its object.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct BestMatch {
    /// 0 when no detection overlaps.
    pub iou: f64,
    /// Pixels of that detection's mask, and of those the ones on the
    /// instance (0 and 0 without one).
    pub detected_pixels: usize,
    pub overlap_pixels: usize,
}

impl BestMatch {
    /// How `detection` overlaps a truth's whole-image mask of `width`
    /// columns.
    fn of(detection: &DetectedObject, truth: &TruthMask, width: usize) -> Self {
        let (detected, both) = detection.overlap(&truth.mask, width);
        let union = detected + truth.area - both;
        let iou = if union == 0 { 0.0 } else { both as f64 / union as f64 };
        Self { iou, detected_pixels: detected, overlap_pixels: both }
    }
}

/// Per object: detections as (score, true positive), instances counted and
/// the IoU of each counted instance with its match (0 if missed).
#[derive(Debug, Clone, Default)]
pub struct ObjectTally {
    pub detections: Vec<(f32, bool)>,
    pub instances: usize,
    pub ious: Vec<f64>,
}

/// Matches one image's detections against its instances and adds them to
/// `tallies`; each instance's best match among the detections of its
/// object, in the order of `truths`.
pub fn tally_image(
    detections: &[DetectedObject],
    truths: &[TruthMask],
    width: usize,
    tallies: &mut BTreeMap<u32, ObjectTally>,
) -> Vec<BestMatch> {
    let mut order: Vec<usize> = (0..detections.len()).collect();
    order.sort_by(|&a, &b| detections[b].score.total_cmp(&detections[a].score));
    let mut best = vec![BestMatch::default(); truths.len()];
    let mut taken = vec![false; truths.len()];
    for truth in truths.iter().filter(|t| !t.ignored) {
        tallies.entry(truth.obj_id).or_default().instances += 1;
    }
    for i in order {
        let detection = &detections[i];
        let candidate = truths
            .iter()
            .enumerate()
            .filter(|(k, t)| t.obj_id == detection.obj_id && !taken[*k])
            .map(|(k, t)| (k, BestMatch::of(detection, t, width)))
            .max_by(|a, b| a.1.iou.total_cmp(&b.1.iou));
        let tally = tallies.entry(detection.obj_id).or_default();
        match candidate {
            Some((k, found)) if found.iou >= MATCH_IOU => {
                taken[k] = true;
                best[k] = found;
                if !truths[k].ignored {
                    tally.detections.push((detection.score, true));
                }
            }
            Some((k, _)) if truths[k].ignored => {}
            _ => tally.detections.push((detection.score, false)),
        }
        if let Some((k, found)) = candidate
            && !taken[k]
            && found.iou > best[k].iou
        {
            best[k] = found;
        }
    }
    for (k, truth) in truths.iter().enumerate().filter(|(_, t)| !t.ignored) {
        tallies.entry(truth.obj_id).or_default().ious.push(best[k].iou);
    }
    best
}

/// Average precision of detections `(score, true positive)` over
/// `positives` instances; `None` when there are none to find.
pub fn average_precision(detections: &[(f32, bool)], positives: usize) -> Option<f64> {
    if positives == 0 {
        return None;
    }
    let mut sorted = detections.to_vec();
    sorted.sort_by(|a, b| b.0.total_cmp(&a.0));
    let (mut tp, mut fp) = (0usize, 0usize);
    let mut curve = Vec::with_capacity(sorted.len());
    for (_, hit) in sorted {
        if hit {
            tp += 1
        } else {
            fp += 1
        }
        curve.push((tp as f64 / positives as f64, tp as f64 / (tp + fp) as f64));
    }
    // Precision made monotone from the right, then summed over recall steps.
    for i in (0..curve.len().saturating_sub(1)).rev() {
        curve[i].1 = curve[i].1.max(curve[i + 1].1);
    }
    let mut ap = 0.0;
    let mut last_recall = 0.0;
    for (recall, precision) in curve {
        ap += (recall - last_recall) * precision;
        last_recall = recall;
    }
    Some(ap)
}

#[derive(Debug, Clone, Serialize)]
pub struct ObjectDetection {
    pub instances: usize,
    pub detections: usize,
    /// AP at mask IoU 0.5, %.
    pub ap50: Option<f64>,
    /// Mean over the instances of the best IoU of a detection with it
    /// (0 when none overlaps), %.
    pub mask_iou: Option<f64>,
    /// Instances a detection of their object covers at mask IoU ≥ 0.5
    /// (found and named), %.
    pub found: Option<f64>,
}

#[derive(Debug, Clone, Serialize)]
pub struct DetectionSummary {
    pub images: usize,
    pub per_object: BTreeMap<u32, ObjectDetection>,
    /// Means over the objects with instances, %.
    pub ap50: Option<f64>,
    pub mask_iou: Option<f64>,
    /// Of every object's instances together, those found (see
    /// [`ObjectDetection::found`]), %.
    pub found: Option<f64>,
    /// Detector milliseconds per image, median and 99th percentile (this
    /// process, one image at a time).
    pub ms_p50: f64,
    pub ms_p99: f64,
    /// Every annotated instance of a known object, for `detections.csv`.
    #[serde(skip)]
    pub instances: Vec<InstanceDetection>,
}

/// How well one annotated instance was detected.
#[derive(Debug, Clone, PartialEq)]
pub struct InstanceDetection {
    pub scene_id: u32,
    pub im_id: u32,
    /// Its index among the image's ground-truth entries.
    pub gt_index: usize,
    pub obj_id: u32,
    pub visib_fract: f64,
    /// Pixels of its visible mask.
    pub truth_pixels: usize,
    /// Its best-overlapping detection.
    pub best: BestMatch,
    /// Under [`MIN_VISIB_FRACT`] visible: left out of AP and mean IoU.
    pub ignored: bool,
}

/// `detections.csv`: one row per instance of [`DetectionSummary::instances`].
pub fn instances_csv(instances: &[InstanceDetection]) -> String {
    let mut csv = String::from(
        "scene_id,im_id,gt_index,obj_id,visib_fract,ignored,mask_iou,truth_pixels,detected_pixels,overlap_pixels\n",
    );
    for i in instances {
        csv.push_str(&format!(
            "{},{},{},{},{:.4},{},{:.4},{},{},{}\n",
            i.scene_id,
            i.im_id,
            i.gt_index,
            i.obj_id,
            i.visib_fract,
            u8::from(i.ignored),
            i.best.iou,
            i.truth_pixels,
            i.best.detected_pixels,
            i.best.overlap_pixels,
        ));
    }
    csv
}

/// The share of instances whose best IoU is a true positive, %.
fn share_found(best_ious: &[f64]) -> Option<f64> {
    (!best_ious.is_empty())
        .then(|| 100.0 * best_ious.iter().filter(|&&iou| iou >= MATCH_IOU).count() as f64 / best_ious.len() as f64)
}

pub fn summarise(
    tallies: &BTreeMap<u32, ObjectTally>,
    images: usize,
    mut times_ms: Vec<f64>,
    instances: Vec<InstanceDetection>,
) -> DetectionSummary {
    let per_object: BTreeMap<u32, ObjectDetection> = tallies
        .iter()
        .map(|(&obj, t)| {
            let mask_iou = (!t.ious.is_empty()).then(|| 100.0 * t.ious.iter().sum::<f64>() / t.ious.len() as f64);
            let ap50 = average_precision(&t.detections, t.instances).map(|ap| 100.0 * ap);
            let found = share_found(&t.ious);
            (obj, ObjectDetection { instances: t.instances, detections: t.detections.len(), ap50, mask_iou, found })
        })
        .collect();
    let all_ious: Vec<f64> = tallies.values().flat_map(|t| t.ious.iter().copied()).collect();
    let mean = |values: Vec<f64>| (!values.is_empty()).then(|| values.iter().sum::<f64>() / values.len() as f64);
    times_ms.sort_by(f64::total_cmp);
    let quantile = |q: f64| times_ms.get(((times_ms.len() as f64 - 1.0) * q).round() as usize).copied().unwrap_or(0.0);
    DetectionSummary {
        images,
        ap50: mean(per_object.values().filter_map(|o| o.ap50).collect()),
        mask_iou: mean(per_object.values().filter_map(|o| o.mask_iou).collect()),
        found: share_found(&all_ious),
        ms_p50: quantile(0.5),
        ms_p99: quantile(0.99),
        per_object,
        instances,
    }
}

/// Runs `detector` over every image of `split_dir` (a BOP split) and scores
/// it against the annotated visible masks of the objects it knows.
pub fn evaluate_split(split_dir: &Path, detector: &mut Detector) -> anyhow::Result<DetectionSummary> {
    let known = detector.object_ids();
    let mut scenes: Vec<u32> = std::fs::read_dir(split_dir)
        .with_context(|| format!("{}: cannot list the split", split_dir.display()))?
        .flatten()
        .filter_map(|e| e.file_name().to_str().and_then(|n| n.parse().ok()))
        .collect();
    scenes.sort_unstable();
    let mut tallies = BTreeMap::new();
    let mut times = Vec::new();
    let mut instances = Vec::new();
    for scene_id in scenes {
        let scene = SceneDir::new(split_dir, scene_id);
        let cameras: ByImage<CameraEntry> = read_json(&scene.scene_camera())?;
        let gts: ByImage<Vec<GtEntry>> = read_json(&scene.scene_gt())?;
        let infos: ByImage<Vec<GtInfoEntry>> = read_json(&scene.scene_gt_info())?;
        for (&im_id, camera) in &cameras {
            let _frame = tracing::debug_span!("detect", scene = scene_id, image = im_id).entered();
            let rgb = read_rgb_png(&scene.rgb(im_id))?;
            let depth = read_depth_png(&scene.depth(im_id), camera.depth_scale)?;
            let (width, height) = (rgb.width as usize, rgb.height as usize);
            let rgb_f32: Vec<f32> = rgb.pixels.iter().flat_map(|p| p.map(f32::from)).collect();
            let image = ImageView { rgb: &rgb_f32, depth: &depth.pixels, width, height, camera: camera.pinhole() };
            let started = std::time::Instant::now();
            let found = detector.detect(&image)?;
            times.push(started.elapsed().as_secs_f64() * 1e3);
            let mut truths = Vec::new();
            let mut indices = Vec::new();
            for (k, gt) in gts.get(&im_id).into_iter().flatten().enumerate() {
                if !known.contains(&gt.obj_id) {
                    continue;
                }
                let visible = infos.get(&im_id).and_then(|i| i.get(k)).map_or(1.0, |i| i.visib_fract);
                indices.push((k, visible));
                let mask = read_mask_png(&scene.mask_visib(im_id, k))?;
                let area = mask.pixels.iter().filter(|&&inside| inside).count();
                truths.push(TruthMask {
                    obj_id: gt.obj_id,
                    mask: mask.pixels,
                    area,
                    ignored: visible < MIN_VISIB_FRACT,
                });
            }
            let matches = tally_image(&found.objects, &truths, width, &mut tallies);
            for ((truth, (gt_index, visib_fract)), best) in truths.iter().zip(indices).zip(matches) {
                instances.push(InstanceDetection {
                    scene_id,
                    im_id,
                    gt_index,
                    obj_id: truth.obj_id,
                    visib_fract,
                    truth_pixels: truth.area,
                    best,
                    ignored: truth.ignored,
                });
            }
        }
    }
    Ok(summarise(&tallies, times.len(), times, instances))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn detection(obj_id: u32, score: f32, bbox: [u32; 4]) -> DetectedObject {
        DetectedObject { obj_id, instance: 0, score, bbox, mask: vec![true; (bbox[2] * bbox[3]) as usize] }
    }

    fn truth(obj_id: u32, width: usize, height: usize, bbox: [usize; 4], ignored: bool) -> TruthMask {
        let mut mask = vec![false; width * height];
        for y in bbox[1]..bbox[1] + bbox[3] {
            for x in bbox[0]..bbox[0] + bbox[2] {
                mask[y * width + x] = true;
            }
        }
        TruthMask { obj_id, area: mask.iter().filter(|&&m| m).count(), mask, ignored }
    }

    #[test]
    fn mask_iou_of_overlapping_squares_is_their_closed_form() {
        // 4×4 squares offset by 2 columns: 8 shared pixels of 24.
        let t = truth(1, 10, 10, [0, 0, 4, 4], false);
        assert!((mask_iou(&detection(1, 1.0, [2, 0, 4, 4]), &t, 10) - 8.0 / 24.0).abs() < 1e-12);
        assert_eq!(mask_iou(&detection(1, 1.0, [0, 0, 4, 4]), &t, 10), 1.0);
    }

    #[test]
    fn average_precision_of_known_rankings() {
        // All found before any false alarm: 1.
        assert_eq!(average_precision(&[(0.9, true), (0.8, true), (0.1, false)], 2), Some(1.0));
        // Half the instances found, first: 0.5.
        assert_eq!(average_precision(&[(0.9, true)], 2), Some(0.5));
        // A false alarm first, then both hits: precision 2/3 at recall 1
        // carried back to recall 0.5: 2/3.
        let ap = average_precision(&[(0.9, false), (0.8, true), (0.7, true)], 2).unwrap();
        assert!((ap - 2.0 / 3.0).abs() < 1e-12);
        assert_eq!(average_precision(&[], 0), None);
        assert_eq!(average_precision(&[(0.5, false)], 3), Some(0.0));
    }

    #[test]
    fn matching_counts_hits_misses_false_alarms_and_ignores_the_barely_visible() {
        let (w, h) = (20, 10);
        let truths = [
            truth(1, w, h, [0, 0, 4, 4], false),
            truth(2, w, h, [10, 0, 4, 4], false),
            truth(3, w, h, [15, 5, 2, 2], true),
        ];
        let detections = [
            detection(1, 0.9, [0, 0, 4, 4]),  // hit, IoU 1
            detection(1, 0.8, [0, 5, 4, 4]),  // the same object again: a false alarm
            detection(3, 0.7, [15, 5, 2, 2]), // an ignored instance: neither
            detection(2, 0.6, [12, 0, 4, 4]), // IoU 1/3: a false alarm; the instance missed
        ];
        let mut tallies = BTreeMap::new();
        let matches = tally_image(&detections, &truths, w, &mut tallies);
        let best = |iou, detected_pixels, overlap_pixels| BestMatch { iou, detected_pixels, overlap_pixels };
        assert_eq!(
            matches,
            [best(1.0, 16, 16), best(8.0 / 24.0, 16, 8), best(1.0, 4, 4)],
            "each instance's best match"
        );
        let summary = summarise(&tallies, 1, vec![1.0], Vec::new());
        let one = &summary.per_object[&1];
        assert_eq!((one.instances, one.detections, one.ap50, one.mask_iou), (1, 2, Some(100.0), Some(100.0)));
        let two = &summary.per_object[&2];
        assert_eq!((two.instances, two.ap50), (1, Some(0.0)));
        assert!((two.mask_iou.unwrap() - 100.0 / 3.0).abs() < 1e-9, "a near miss keeps its IoU");
        let three = &summary.per_object[&3];
        assert_eq!((three.instances, three.detections, three.ap50), (0, 0, None));
        assert_eq!(summary.ap50, Some(50.0));
        assert_eq!((one.found, two.found, three.found), (Some(100.0), Some(0.0), None));
        assert_eq!(summary.found, Some(50.0), "one of the two counted instances");
    }
}
