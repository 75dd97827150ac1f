//! `poseflow eval --category`: category-level estimates (pose in the
//! category's canonical frame plus size) scored as REAL275 reports them:
//! 5°2cm, 5°5cm, 10°2cm, 10°5cm and 3D IoU at 25 % and 50 %, per category
//! and averaged over the categories.
//!
//! The turn about the symmetry axis (canonical y) is not scored for
//! bottles, bowls and cans, nor for a mug whose handle the image does not
//! show ([`handle_pixels`]); there the rotation error is the angle between
//! the true and the estimated axis, and the IoU is the best over turns of
//! the estimated box about its axis (`poseflow_geometry::category`).
//!
//! REAL275 reports mAP over detection scores; with ground-truth masks every
//! instance is detected once, so the figures here are shares of instances
//! (an instance without an estimate counts as a miss).

use std::collections::BTreeMap;
use std::path::Path;

use anyhow::Context;
use nalgebra::{Point3, Vector3};
use poseflow_geometry::Pose;
use poseflow_geometry::category::{PlacedBox, axis_spread_deg, category_iou, rotation_error_deg, translation_error_cm};
use poseflow_geometry::metrics::Pinhole;
use poseflow_scene::bop::{Raster, SceneDir, read_depth_png, read_mask_png};
use poseflow_scene::category::{Category, CategoryEntry};
use serde::Serialize;

use crate::dataset::TruthImage;
use crate::estimates::Estimated;

/// A mug's handle counts as visible when at least this many of its pixels
/// (at 640 × 480; scaled by the image's area) are in the instance's
/// visible mask with a depth that puts them on the handle.
pub const HANDLE_VISIBLE_PIXELS_AT_640X480: f64 = 50.0;

/// Thresholds of the accuracy columns (degrees, centimetres), in order.
pub const THRESHOLDS: [(f64, f64); 4] = [(5.0, 2.0), (5.0, 5.0), (10.0, 2.0), (10.0, 5.0)];
/// 3D IoU thresholds, in order.
pub const IOU_THRESHOLDS: [f64; 2] = [0.25, 0.5];

/// How far off one estimate is.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct CategoryErrors {
    pub rotation_deg: f64,
    pub translation_cm: f64,
    pub iou: f64,
    /// Mean over the three extents of |estimated − true| / true.
    pub size_error: f64,
    /// How widely the samples turn about the canonical axis around the
    /// selected pose (`axis_spread_deg`): wide where the turn is ambiguous
    /// (an axis-symmetric object, a mug whose handle is hidden), narrow
    /// where the image decides it. None without samples.
    pub axis_spread_deg: Option<f64>,
}

/// One scored instance.
#[derive(Debug, Clone, Serialize)]
pub struct CategoryOutcome {
    pub scene_id: u32,
    pub im_id: u32,
    pub obj_id: u32,
    pub category: &'static str,
    /// A mug's handle seen (None for the other categories).
    pub handle_visible: Option<bool>,
    /// Whether the turn about the axis went unscored.
    pub axis_ignored: bool,
    /// None: no estimate, or one without a size (an instance-level model).
    pub errors: Option<CategoryErrors>,
}

/// The pixels of a mug's visible mask whose depth, taken into the object
/// frame by the true pose, lies beyond `beyond_x` along canonical x: its
/// handle as the camera saw it.
pub fn handle_pixels(mask: &Raster<bool>, depth: &Raster<f32>, camera: &Pinhole, pose: &Pose, beyond_x: f64) -> usize {
    let inverse = pose.inverse();
    let mut count = 0;
    for (i, (&inside, &z)) in mask.pixels.iter().zip(&depth.pixels).enumerate() {
        if !inside || z <= 0.0 {
            continue;
        }
        let (u, v) = ((i % mask.width as usize) as f64, (i / mask.width as usize) as f64);
        let z = f64::from(z);
        let seen = Point3::new((u - camera.cx) / camera.fx * z, (v - camera.cy) / camera.fy * z, z);
        if inverse.transform_point(&seen).x > beyond_x {
            count += 1;
        }
    }
    count
}

/// Whether the image shows instance `index` of its scene's ground truth as
/// a mug with its handle in view.
fn handle_visible(
    split_dir: &Path,
    image: &TruthImage,
    index: usize,
    pose: &Pose,
    beyond_x: f64,
) -> anyhow::Result<bool> {
    let dir = SceneDir::new(split_dir, image.scene_id);
    let mask_path = dir.mask_visib(image.im_id, index);
    let mask = read_mask_png(&mask_path).with_context(|| format!("{}", mask_path.display()))?;
    let depth_file = image.depth.as_ref().with_context(|| {
        format!(
            "{}: --category needs the depth image to see whether a mug's handle is in view",
            dir.depth(image.im_id).display()
        )
    })?;
    let depth = read_depth_png(&depth_file.path, depth_file.depth_scale)
        .with_context(|| format!("{}", depth_file.path.display()))?;
    if (mask.width, mask.height) != (depth.width, depth.height) {
        anyhow::bail!(
            "{}: {}×{} pixels, the depth image is {}×{}",
            mask_path.display(),
            mask.width,
            mask.height,
            depth.width,
            depth.height
        );
    }
    let seen = handle_pixels(&mask, &depth, &image.camera.pinhole, pose, beyond_x);
    let area = f64::from(mask.width) * f64::from(mask.height) / (640.0 * 480.0);
    Ok(seen as f64 >= HANDLE_VISIBLE_PIXELS_AT_640X480 * area)
}

/// The estimates of annotated objects taken from their category's frame,
/// where the model estimates, to the objects' model frames, where the
/// dataset's poses, the BOP results file and the instance-level metrics
/// are.
pub fn to_model_frames(estimates: &mut [Estimated], categories: &BTreeMap<u32, CategoryEntry>) {
    for estimate in estimates {
        if let Some(entry) = categories.get(&estimate.obj_id) {
            for pose in std::iter::once(&mut estimate.selected).chain(&mut estimate.hypotheses) {
                *pose = *pose * entry.canonical_from_model;
            }
        }
    }
}

/// A BOP targets list (`test_targets_bop19.json` format) of the annotated
/// instances of `images` whose object has a category: what a category run
/// estimates, so that objects without one (a sugar box beside the cans of
/// a real frame) are not sent to a model that cannot place them.
pub fn targets(images: &[TruthImage], categories: &BTreeMap<u32, CategoryEntry>) -> Vec<serde_json::Value> {
    let mut counts: BTreeMap<(u32, u32, u32), u32> = BTreeMap::new();
    for image in images {
        for instance in image.instances.iter().filter(|i| categories.contains_key(&i.obj_id)) {
            *counts.entry((image.scene_id, image.im_id, instance.obj_id)).or_default() += 1;
        }
    }
    counts
        .into_iter()
        .map(|((scene_id, im_id, obj_id), inst_count)| {
            serde_json::json!({ "scene_id": scene_id, "im_id": im_id, "obj_id": obj_id, "inst_count": inst_count })
        })
        .collect()
}

/// Scores every scored ground-truth instance of `images` whose object has
/// an entry in `categories` against its estimate (matched by image and
/// object id; both poses of the model frame, compared in the category's).
pub fn score(
    split_dir: &Path,
    images: &[TruthImage],
    estimates: &[Estimated],
    categories: &BTreeMap<u32, CategoryEntry>,
) -> anyhow::Result<Vec<CategoryOutcome>> {
    let by_instance: BTreeMap<(u32, u32, u32), &Estimated> =
        estimates.iter().map(|e| ((e.scene_id, e.im_id, e.obj_id), e)).collect();
    let mut outcomes = Vec::new();
    for image in images {
        for instance in image.instances.iter().filter(|i| i.scored) {
            let Some(entry) = categories.get(&instance.obj_id) else { continue };
            // The truth in the category's frame, where the model estimates.
            let truth = instance.pose * entry.canonical_from_model.inverse();
            let handle_visible = match (entry.category, entry.handle_beyond_x) {
                (Category::Mug, Some(beyond_x)) => {
                    Some(handle_visible(split_dir, image, instance.gt_index, &truth, beyond_x)?)
                }
                _ => None,
            };
            let axis_ignored = entry.category.symmetric_about_y() || handle_visible == Some(false);
            let truth_box = PlacedBox { pose: truth, size: entry.size };
            let errors = by_instance.get(&(image.scene_id, image.im_id, instance.obj_id)).and_then(|estimate| {
                let size = Vector3::from(estimate.category?.size.map(f64::from));
                let to_canonical = entry.canonical_from_model.inverse();
                let estimated = estimate.selected * to_canonical;
                let samples: Vec<_> = estimate.hypotheses.iter().map(|h| (*h * to_canonical).rotation).collect();
                let estimated_box = PlacedBox { pose: estimated, size };
                Some(CategoryErrors {
                    rotation_deg: rotation_error_deg(&estimated, &truth, axis_ignored),
                    translation_cm: translation_error_cm(&estimated, &truth),
                    iou: category_iou(&estimated_box, &truth_box, axis_ignored),
                    size_error: (0..3).map(|i| (size[i] - entry.size[i]).abs() / entry.size[i]).sum::<f64>() / 3.0,
                    axis_spread_deg: axis_spread_deg(&estimated.rotation, &samples),
                })
            });
            outcomes.push(CategoryOutcome {
                scene_id: image.scene_id,
                im_id: image.im_id,
                obj_id: instance.obj_id,
                category: entry.category.name(),
                handle_visible,
                axis_ignored,
                errors,
            });
        }
    }
    Ok(outcomes)
}

/// Accuracies of a set of instances, in % of them.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct CategoryRow {
    pub instances: usize,
    pub estimated: usize,
    /// In the order of [`THRESHOLDS`].
    pub accuracy: [f64; 4],
    /// In the order of [`IOU_THRESHOLDS`].
    pub iou: [f64; 2],
    pub median_rotation_deg: Option<f64>,
    pub median_translation_cm: Option<f64>,
    pub median_size_error: Option<f64>,
    pub median_axis_spread_deg: Option<f64>,
}

fn median(mut values: Vec<f64>) -> Option<f64> {
    values.sort_by(f64::total_cmp);
    (!values.is_empty()).then(|| values[values.len() / 2])
}

impl CategoryRow {
    fn of(outcomes: &[&CategoryOutcome]) -> Self {
        let errors: Vec<CategoryErrors> = outcomes.iter().filter_map(|o| o.errors).collect();
        let share = |count: usize| 100.0 * count as f64 / outcomes.len().max(1) as f64;
        Self {
            instances: outcomes.len(),
            estimated: errors.len(),
            accuracy: THRESHOLDS.map(|(deg, cm)| {
                share(errors.iter().filter(|e| e.rotation_deg <= deg && e.translation_cm <= cm).count())
            }),
            iou: IOU_THRESHOLDS.map(|t| share(errors.iter().filter(|e| e.iou >= t).count())),
            median_rotation_deg: median(errors.iter().map(|e| e.rotation_deg).collect()),
            median_translation_cm: median(errors.iter().map(|e| e.translation_cm).collect()),
            median_size_error: median(errors.iter().map(|e| e.size_error).collect()),
            median_axis_spread_deg: median(errors.iter().filter_map(|e| e.axis_spread_deg).collect()),
        }
    }

    /// The unweighted mean of rows (REAL275 averages its categories).
    fn mean(rows: &[&CategoryRow]) -> Self {
        let n = rows.len().max(1) as f64;
        let mean_of = |f: &dyn Fn(&CategoryRow) -> f64| rows.iter().map(|r| f(r)).sum::<f64>() / n;
        Self {
            instances: rows.iter().map(|r| r.instances).sum(),
            estimated: rows.iter().map(|r| r.estimated).sum(),
            accuracy: std::array::from_fn(|i| mean_of(&|r| r.accuracy[i])),
            iou: std::array::from_fn(|i| mean_of(&|r| r.iou[i])),
            median_rotation_deg: None,
            median_translation_cm: None,
            median_size_error: None,
            median_axis_spread_deg: None,
        }
    }
}

/// Per category, their mean, and mugs by whether their handle was seen.
#[derive(Debug, Clone, Serialize)]
pub struct CategorySummary {
    pub per_category: BTreeMap<&'static str, CategoryRow>,
    pub mean: CategoryRow,
    pub mugs_handle_visible: Option<CategoryRow>,
    pub mugs_handle_hidden: Option<CategoryRow>,
}

pub fn summarise(outcomes: &[CategoryOutcome]) -> CategorySummary {
    let mut groups: BTreeMap<&'static str, Vec<&CategoryOutcome>> = BTreeMap::new();
    for outcome in outcomes {
        groups.entry(outcome.category).or_default().push(outcome);
    }
    let per_category: BTreeMap<&'static str, CategoryRow> =
        groups.iter().map(|(name, members)| (*name, CategoryRow::of(members))).collect();
    let mean = CategoryRow::mean(&per_category.values().collect::<Vec<_>>());
    let mugs = |visible: bool| {
        let members: Vec<&CategoryOutcome> = outcomes.iter().filter(|o| o.handle_visible == Some(visible)).collect();
        (!members.is_empty()).then(|| CategoryRow::of(&members))
    };
    CategorySummary { per_category, mean, mugs_handle_visible: mugs(true), mugs_handle_hidden: mugs(false) }
}

pub fn print(summary: &CategorySummary) {
    println!(
        "\ncategory-level (REAL275 protocol; turns about the axis ignored for bottles, bowls, cans and mugs whose handle is hidden; % of instances):"
    );
    println!(
        "category         instances  estimated  5°2cm  5°5cm  10°2cm  10°5cm  IoU25  IoU50  med rot °  med cm  med size err %  axis spread °"
    );
    let optional = |v: Option<f64>, scale: f64| v.map_or("-".to_string(), |v| format!("{:.1}", v * scale));
    let row = |label: &str, r: &CategoryRow| {
        println!(
            "{label:<15}  {:>9}  {:>9}  {:>5.1}  {:>5.1}  {:>6.1}  {:>6.1}  {:>5.1}  {:>5.1}  {:>9}  {:>6}  {:>14}  {:>13}",
            r.instances,
            r.estimated,
            r.accuracy[0],
            r.accuracy[1],
            r.accuracy[2],
            r.accuracy[3],
            r.iou[0],
            r.iou[1],
            optional(r.median_rotation_deg, 1.0),
            optional(r.median_translation_cm, 1.0),
            optional(r.median_size_error, 100.0),
            optional(r.median_axis_spread_deg, 1.0)
        );
    };
    for (name, r) in &summary.per_category {
        row(name, r);
    }
    if let Some(r) = &summary.mugs_handle_visible {
        row("mug, handle seen", r);
    }
    if let Some(r) = &summary.mugs_handle_hidden {
        row("mug, hidden", r);
    }
    row("mean", &summary.mean);
}

/// The per-instance CSV (`category.csv`).
pub fn instances_csv(outcomes: &[CategoryOutcome]) -> String {
    let mut out = String::from(
        "scene_id,im_id,obj_id,category,handle_visible,axis_ignored,rotation_deg,translation_cm,iou,size_error,axis_spread_deg\n",
    );
    for o in outcomes {
        let handle = o.handle_visible.map_or(String::new(), |v| v.to_string());
        let errors = o.errors.map_or(",,,,".to_string(), |e| {
            let spread = e.axis_spread_deg.map_or(String::new(), |d| format!("{d:.1}"));
            format!("{:.3},{:.3},{:.4},{:.4},{spread}", e.rotation_deg, e.translation_cm, e.iou, e.size_error)
        });
        out.push_str(&format!(
            "{},{},{},{},{handle},{},{errors}\n",
            o.scene_id, o.im_id, o.obj_id, o.category, o.axis_ignored
        ));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Rotation3;

    #[test]
    fn handle_pixels_are_those_beyond_the_body_in_the_object_frame() {
        // A 4×1 image of a plane 1 m away; the object frame is the camera's
        // shifted 1 m forward, so object x = camera x.
        let camera = Pinhole { fx: 50.0, fy: 50.0, cx: 1.5, cy: 0.0 };
        let mask = Raster { width: 4, height: 1, pixels: vec![true, true, true, false] };
        let depth = Raster { width: 4, height: 1, pixels: vec![1.0, 1.0, 1.0, 1.0] };
        let pose = Pose::new(Rotation3::identity(), Vector3::new(0.0, 0.0, 1.0));
        // x = (u − 1.5)/50: −0.03, −0.01, 0.01, 0.03; the fourth is outside the mask.
        assert_eq!(handle_pixels(&mask, &depth, &camera, &pose, 0.0), 1);
        assert_eq!(handle_pixels(&mask, &depth, &camera, &pose, -0.02), 2);
        // Pixels without depth are not seen.
        let holes = Raster { width: 4, height: 1, pixels: vec![1.0, 0.0, 0.0, 1.0] };
        assert_eq!(handle_pixels(&mask, &holes, &camera, &pose, -0.02), 0);
        // Turned half a turn about y, object x points the other way.
        let turned = Pose::new(Rotation3::from_axis_angle(&Vector3::y_axis(), std::f64::consts::PI), pose.translation);
        assert_eq!(handle_pixels(&mask, &depth, &camera, &turned, 0.0), 2);
        assert_eq!(handle_pixels(&mask, &depth, &camera, &turned, 0.02), 1);
    }

    #[test]
    fn a_scan_is_scored_in_its_category_frame_and_reported_in_its_model_frame() {
        // A can whose model frame stands it on z (a YCB can): canonical y
        // is model z, and the canonical origin sits 1 cm up the axis.
        let canonical_from_model = Pose::new(
            Rotation3::from_axis_angle(&Vector3::x_axis(), -std::f64::consts::FRAC_PI_2),
            Vector3::new(0.0, -0.01, 0.0),
        );
        let entry = CategoryEntry {
            category: Category::Can,
            size: Vector3::new(0.07, 0.1, 0.07),
            handle_beyond_x: None,
            canonical_from_model,
        };
        let categories = BTreeMap::from([(5, entry)]);
        let truth = Pose::new(Rotation3::from_euler_angles(0.3, -0.2, 1.0), Vector3::new(0.05, 0.0, 0.7));
        let image = image_of(&[(5, truth)]);
        // The model's estimate, in the canonical frame: the truth turned
        // 50° about the can's axis (not scored) and 3° across it.
        let canonical_truth = truth * canonical_from_model.inverse();
        let turn = Rotation3::from_axis_angle(&Vector3::y_axis(), 50f64.to_radians())
            * Rotation3::from_axis_angle(&Vector3::x_axis(), 3f64.to_radians());
        let estimate = Pose::new(canonical_truth.rotation * turn, canonical_truth.translation);
        let mut estimates = vec![Estimated {
            scene_id: 0,
            im_id: 0,
            obj_id: 5,
            selected: estimate,
            score: 1.0,
            hypotheses: vec![estimate],
            kept: 1,
            rotation_trace: None,
            service_time: None,
            latency: None,
            flags: 0,
            category: Some(poseflow_contracts::ObjectCategory { code: Category::Can.code(), size: [0.07, 0.1, 0.07] }),
        }];
        to_model_frames(&mut estimates, &categories);
        // Reported in the model frame: the canonical estimate carried back.
        let carried = estimates[0].selected * canonical_from_model.inverse();
        assert!((carried.to_homogeneous() - estimate.to_homogeneous()).abs().max() < 1e-12);
        assert!((estimates[0].selected.translation - truth.translation).norm() < 0.011);
        let outcome = &score(Path::new("unused"), &[image], &estimates, &categories).unwrap()[0];
        let errors = outcome.errors.as_ref().unwrap();
        assert!(outcome.axis_ignored);
        assert!((errors.rotation_deg - 3.0).abs() < 1e-6, "{errors:?}");
        assert!(errors.translation_cm < 1e-9 && errors.size_error < 1e-6, "{errors:?}");
        assert_eq!(errors.axis_spread_deg, None, "one sample has no spread");
        // Only the objects with a category are targets.
        let targets = targets(&[image_of(&[(5, truth), (3, truth), (5, truth)])], &categories);
        assert_eq!(targets, [serde_json::json!({"scene_id": 0, "im_id": 0, "obj_id": 5, "inst_count": 2})]);
    }

    fn image_of(instances: &[(u32, Pose)]) -> TruthImage {
        TruthImage {
            scene_id: 0,
            im_id: 0,
            camera: crate::score::ImageCamera {
                pinhole: Pinhole { fx: 500.0, fy: 500.0, cx: 320.0, cy: 240.0 },
                width: 640,
            },
            depth: None,
            instances: instances
                .iter()
                .enumerate()
                .map(|(gt_index, &(obj_id, pose))| crate::dataset::TruthInstance {
                    obj_id,
                    gt_index,
                    pose,
                    scored: true,
                    visib_fract: None,
                })
                .collect(),
        }
    }

    fn outcome(category: &'static str, rotation_deg: f64, translation_cm: f64, iou: f64) -> CategoryOutcome {
        CategoryOutcome {
            scene_id: 0,
            im_id: 0,
            obj_id: 1,
            category,
            handle_visible: None,
            axis_ignored: true,
            errors: Some(CategoryErrors { rotation_deg, translation_cm, iou, size_error: 0.1, axis_spread_deg: None }),
        }
    }

    #[test]
    fn rows_count_instances_within_each_threshold_and_the_mean_weighs_categories_equally() {
        let outcomes = vec![
            outcome("can", 3.0, 1.0, 0.8),
            outcome("can", 7.0, 4.0, 0.4),
            CategoryOutcome { errors: None, ..outcome("can", 0.0, 0.0, 0.0) },
            outcome("bowl", 20.0, 1.0, 0.6),
        ];
        let summary = summarise(&outcomes);
        let can = &summary.per_category["can"];
        assert_eq!((can.instances, can.estimated), (3, 2));
        let third: f64 = 100.0 / 3.0;
        assert_eq!(
            can.accuracy.map(|a| (a * 10.0).round()),
            [third, third, third, 2.0 * third].map(|a| (a * 10.0).round())
        );
        assert_eq!(can.iou.map(|a| (a * 10.0).round()), [2.0 * third, third].map(|a| (a * 10.0).round()));
        let bowl = &summary.per_category["bowl"];
        assert_eq!((bowl.accuracy, bowl.iou), ([0.0; 4], [100.0; 2]));
        // The mean is over the two categories, not the four instances.
        assert!((summary.mean.accuracy[3] - (2.0 * third) / 2.0).abs() < 1e-9);
        assert!((summary.mean.iou[1] - (third + 100.0) / 2.0).abs() < 1e-9);
        assert!(summary.mugs_handle_hidden.is_none());
    }
}
