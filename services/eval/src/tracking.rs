//! How a tracking graph did over a video (one scene whose images are
//! consecutive frames): per object, the images tracked, flagged lost,
//! unsure or re-initialised, the accuracy, and after each of the video's
//! events (`video_events.json`) how soon the estimate was right again.
//! `poseflow demo --track` and `poseflow eval` with a tracking graph both
//! report through [`summarise_video`].

use std::collections::BTreeMap;
use std::path::Path;
use std::time::Duration;

use anyhow::Context;
use poseflow_contracts::flags;
use poseflow_runtime::timing::Timing;
use poseflow_scene::bop::{GtEntry, GtInfoEntry, SceneDir, read_json};
use poseflow_scene::video::EventRecord;
use serde::Serialize;

use crate::dataset::MIN_VISIB_FRACT;
use crate::recovery::{EventOutcome, PROMPT_IMAGES, REAPPEARED_VISIBLE, outcomes};

/// Accuracy thresholds of the report: (degrees, metres).
pub const TIGHT: (f64, f64) = (5.0, 0.05);
pub const LOOSE: (f64, f64) = (10.0, 0.05);

/// One estimate of one object in one image of the video.
#[derive(Debug, Clone, Copy)]
pub struct TrackedImage {
    pub im_id: u32,
    pub obj_id: u32,
    /// Of the selected pose, symmetry-aware.
    pub rotation_error_deg: f64,
    pub translation_error_m: f64,
    /// The Estimate header's flags.
    pub flags: u32,
    /// From reading the image to the estimate.
    pub latency: Option<Duration>,
}

impl TrackedImage {
    fn within(&self, (degrees, metres): (f64, f64)) -> bool {
        self.rotation_error_deg < degrees && self.translation_error_m < metres
    }
}

/// One object over the video.
#[derive(Debug, Serialize)]
pub struct TrackedObject {
    pub obj_id: u32,
    /// Images the object is annotated in, and those with an estimate.
    pub frames: u32,
    pub estimated: u32,
    /// Estimates whose samples started from the previous estimate.
    pub tracked: u32,
    /// Estimates the selector's track check flagged `LOST`, `UNSURE`,
    /// `REINITIALISED` (0 without the check).
    pub lost: u32,
    pub unsure: u32,
    pub reinitialised: u32,
    /// Estimates placed without the networks: a held track between its
    /// network passes (the sampler's `tracking.network_every`).
    pub network_skipped: u32,
    /// Percent of the annotated images whose estimate is within 5°/5 cm
    /// (resp. 10°/5 cm) of the truth; an image without an estimate counts
    /// as a miss.
    pub acc_5deg_5cm: f64,
    pub acc_10deg_5cm: f64,
    /// Images in which the object is at least [`MIN_VISIB_FRACT`] visible
    /// (BOP's `visib_fract`, which counts the part beyond the image
    /// border): all annotated ones without `scene_gt_info.json`.
    pub visible_frames: u32,
    /// Percent of those images whose estimate is within 10°/5 cm: how the
    /// object was tracked while it could be seen.
    pub acc_10deg_5cm_visible: f64,
    pub median_rotation_error_deg: f64,
    pub max_rotation_error_deg: f64,
    pub median_translation_error_cm: f64,
    /// From the frame source's stamp to the selector's.
    pub latency: Timing,
}

/// A video's summary.
#[derive(Debug, Serialize)]
pub struct VideoSummary {
    pub scene_id: u32,
    pub frames: u32,
    /// Over every object and image.
    pub acc_5deg_5cm: f64,
    pub acc_10deg_5cm: f64,
    /// The objects at least [`MIN_VISIB_FRACT`] visible in some image (all
    /// annotated ones when the scene has no `scene_gt_info.json`).
    pub objects: Vec<TrackedObject>,
    /// Annotated objects never that visible: out of the camera's view the
    /// whole video, so not scored.
    pub objects_never_visible: Vec<u32>,
    /// The video's occlusions and teleports and how soon each object was
    /// back within 10°5cm.
    pub events: Vec<EventOutcome>,
    /// Percent of the events after which the estimate was back within
    /// 10°5cm at most 2 images after the object reappeared or moved.
    pub events_prompt_pct: f64,
}

fn median(mut values: Vec<f64>) -> f64 {
    values.sort_by(f64::total_cmp);
    if values.is_empty() { f64::NAN } else { values[values.len() / 2] }
}

fn percent(count: usize, of: usize) -> f64 {
    if of == 0 { 0.0 } else { 100.0 * count as f64 / of as f64 }
}

/// Summarises the estimates `images` of the video of `frames` images in
/// scene `scene_id` of the BOP split folder `split` (`scene_gt.json`,
/// `scene_gt_info.json`, and `video_events.json` when it has events).
pub fn summarise_video(
    split: &Path,
    scene_id: u32,
    frames: u32,
    images: &[TrackedImage],
) -> anyhow::Result<VideoSummary> {
    let scene = &SceneDir::new(split, scene_id);
    let gt: BTreeMap<u32, Vec<GtEntry>> = read_json(&scene.scene_gt())?;
    let mut annotated: BTreeMap<u32, u32> = BTreeMap::new();
    for entry in gt.values().flatten() {
        *annotated.entry(entry.obj_id).or_default() += 1;
    }
    let visibility = visible_fractions(scene, &gt)?;
    let objects_never_visible = never_visible(&gt, visibility.as_ref());
    annotated.retain(|obj_id, _| !objects_never_visible.contains(obj_id));
    let mut by_object: BTreeMap<u32, Vec<&TrackedImage>> = BTreeMap::new();
    for image in images {
        by_object.entry(image.obj_id).or_default().push(image);
    }
    let (mut tight_all, mut loose_all, mut frames_all) = (0, 0, 0);
    let mut objects = Vec::new();
    for (&obj_id, &annotated_frames) in &annotated {
        let estimates = by_object.get(&obj_id).map_or(&[][..], Vec::as_slice);
        let count = |bit: u32| estimates.iter().filter(|e| e.flags & bit != 0).count() as u32;
        let tight = estimates.iter().filter(|e| e.within(TIGHT)).count();
        let loose = estimates.iter().filter(|e| e.within(LOOSE)).count();
        let seen = |im_id: u32| {
            visibility.as_ref().is_none_or(|v| v.get(&(im_id, obj_id)).is_some_and(|&f| f >= MIN_VISIB_FRACT))
        };
        let visible_frames =
            gt.iter().filter(|(im_id, entries)| entries.iter().any(|e| e.obj_id == obj_id) && seen(**im_id)).count();
        let loose_visible = estimates.iter().filter(|e| e.within(LOOSE) && seen(e.im_id)).count();
        (tight_all, loose_all, frames_all) = (tight_all + tight, loose_all + loose, frames_all + annotated_frames);
        objects.push(TrackedObject {
            obj_id,
            frames: annotated_frames,
            estimated: estimates.len() as u32,
            tracked: count(flags::TRACKING),
            lost: count(flags::LOST),
            unsure: count(flags::UNSURE),
            reinitialised: count(flags::REINITIALISED),
            network_skipped: count(flags::NETWORK_SKIPPED),
            acc_5deg_5cm: percent(tight, annotated_frames as usize),
            acc_10deg_5cm: percent(loose, annotated_frames as usize),
            visible_frames: visible_frames as u32,
            acc_10deg_5cm_visible: percent(loose_visible, visible_frames),
            median_rotation_error_deg: median(estimates.iter().map(|e| e.rotation_error_deg).collect()),
            max_rotation_error_deg: estimates.iter().map(|e| e.rotation_error_deg).fold(0.0, f64::max),
            median_translation_error_cm: median(estimates.iter().map(|e| e.translation_error_m * 100.0).collect()),
            latency: Timing::of(estimates.iter().filter_map(|e| e.latency).collect()),
        });
    }
    let within: BTreeMap<(u32, u32), bool> = images.iter().map(|e| ((e.im_id, e.obj_id), e.within(LOOSE))).collect();
    let events = event_outcomes(scene, visibility.as_ref(), &within, frames)?;
    Ok(VideoSummary {
        scene_id,
        frames,
        acc_5deg_5cm: percent(tight_all, frames_all as usize),
        acc_10deg_5cm: percent(loose_all, frames_all as usize),
        objects,
        objects_never_visible,
        events_prompt_pct: percent(events.iter().filter(|e| e.prompt()).count(), events.len()),
        events,
    })
}

/// Each annotated object's visible fraction per image, keyed by (image,
/// object); `None` without `scene_gt_info.json`.
fn visible_fractions(
    scene: &SceneDir,
    gt: &BTreeMap<u32, Vec<GtEntry>>,
) -> anyhow::Result<Option<BTreeMap<(u32, u32), f64>>> {
    if !scene.scene_gt_info().is_file() {
        return Ok(None);
    }
    let info: BTreeMap<u32, Vec<GtInfoEntry>> = read_json(&scene.scene_gt_info())?;
    let mut fractions = BTreeMap::new();
    for (im_id, entries) in gt {
        let shares = info.get(im_id).map_or(&[][..], Vec::as_slice);
        for (entry, share) in entries.iter().zip(shares) {
            let fraction = fractions.entry((*im_id, entry.obj_id)).or_insert(0.0f64);
            *fraction = fraction.max(share.visib_fract);
        }
    }
    Ok(Some(fractions))
}

/// The annotated objects never at least [`MIN_VISIB_FRACT`] visible in
/// the video (none without visible fractions).
fn never_visible(gt: &BTreeMap<u32, Vec<GtEntry>>, visibility: Option<&BTreeMap<(u32, u32), f64>>) -> Vec<u32> {
    let Some(visibility) = visibility else { return Vec::new() };
    let mut seen: BTreeMap<u32, bool> = BTreeMap::new();
    for (im_id, entries) in gt {
        for entry in entries {
            let visible = visibility.get(&(*im_id, entry.obj_id)).is_some_and(|&f| f >= MIN_VISIB_FRACT);
            *seen.entry(entry.obj_id).or_default() |= visible;
        }
    }
    seen.into_iter().filter(|(_, visible)| !visible).map(|(obj_id, _)| obj_id).collect()
}

/// The outcomes of the video's events, if it has any.
fn event_outcomes(
    scene: &SceneDir,
    visibility: Option<&BTreeMap<(u32, u32), f64>>,
    within: &BTreeMap<(u32, u32), bool>,
    frames: u32,
) -> anyhow::Result<Vec<EventOutcome>> {
    if !scene.video_events().is_file() {
        return Ok(Vec::new());
    }
    let events: Vec<EventRecord> = read_json(&scene.video_events())?;
    let visibility = visibility
        .with_context(|| format!("{} has events but no {}", scene.path.display(), scene.scene_gt_info().display()))?;
    Ok(outcomes(&events, visibility, within, frames))
}

/// The track flags of an Estimate header, `|`-separated (`-` for none).
pub fn flag_names(bits: u32) -> String {
    let names: Vec<&str> = [
        (flags::TRACKING, "tracking"),
        (flags::LOST, "lost"),
        (flags::UNSURE, "unsure"),
        (flags::REINITIALISED, "reinitialised"),
        (flags::NETWORK_SKIPPED, "network_skipped"),
    ]
    .into_iter()
    .filter(|(bit, _)| bits & bit != 0)
    .map(|(_, name)| name)
    .collect();
    if names.is_empty() { "-".into() } else { names.join("|") }
}

/// Writes every estimate, in image order, as CSV: scene, image, object,
/// errors and track flags.
pub fn write_per_image(path: &Path, videos: &[(u32, &[TrackedImage])]) -> anyhow::Result<()> {
    let mut text = String::from("scene,image,object,rotation_error_deg,translation_error_cm,flags\n");
    for (scene_id, images) in videos {
        let mut sorted: Vec<&TrackedImage> = images.iter().collect();
        sorted.sort_by_key(|e| (e.im_id, e.obj_id));
        for e in sorted {
            text.push_str(&format!(
                "{scene_id},{},{},{:.3},{:.3},{}\n",
                e.im_id,
                e.obj_id,
                e.rotation_error_deg,
                e.translation_error_m * 100.0,
                flag_names(e.flags)
            ));
        }
    }
    std::fs::write(path, text).with_context(|| format!("writing {}", path.display()))
}

/// Prints the per-object table and the events.
pub fn print_video(video: &VideoSummary) {
    println!(
        "object  estimated  tracked  no net  lost  unsure  reinit  5°5cm %  10°5cm %  visible  10°5cm % of visible  median rot °  max rot °  median trans cm  latency p50/p99 ms"
    );
    for o in &video.objects {
        println!(
            "{:>6}  {:>4}/{:<4}  {:>7}  {:>6}  {:>4}  {:>6}  {:>6}  {:>7.1}  {:>8.1}  {:>7}  {:>19.1}  {:>12.2}  {:>9.1}  {:>15.2}  {:>8.1}/{:.1}",
            o.obj_id,
            o.estimated,
            o.frames,
            o.tracked,
            o.network_skipped,
            o.lost,
            o.unsure,
            o.reinitialised,
            o.acc_5deg_5cm,
            o.acc_10deg_5cm,
            o.visible_frames,
            o.acc_10deg_5cm_visible,
            o.median_rotation_error_deg,
            o.max_rotation_error_deg,
            o.median_translation_error_cm,
            o.latency.p50_ms,
            o.latency.p99_ms
        );
    }
    if !video.objects_never_visible.is_empty() {
        let ids: Vec<String> = video.objects_never_visible.iter().map(u32::to_string).collect();
        println!(
            "not scored: object(s) {} never ≥ {:.0} % visible in the video",
            ids.join(", "),
            MIN_VISIB_FRACT * 100.0
        );
    }
    if !video.events.is_empty() {
        println!(
            "events: {} of {} back within 10°5cm at most {PROMPT_IMAGES} images after the object reappeared (≥ {:.0} % visible) or moved ({:.1} %)",
            video.events.iter().filter(|e| e.prompt()).count(),
            video.events.len(),
            REAPPEARED_VISIBLE * 100.0,
            video.events_prompt_pct
        );
        for e in &video.events {
            let image = |v: Option<u32>| v.map_or("-".to_string(), |v| v.to_string());
            println!(
                "  {:<9} object {:>2}: from image {:>4}, back after {} images",
                e.kind,
                e.obj_id,
                image(e.reappeared),
                image(e.recovered_after)
            );
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn image(im_id: u32, rotation_error_deg: f64, flags: u32) -> TrackedImage {
        TrackedImage { im_id, obj_id: 1, rotation_error_deg, translation_error_m: 0.01, flags, latency: None }
    }

    #[test]
    fn thresholds_are_strict() {
        assert!(image(0, 4.99, 0).within(TIGHT));
        assert!(!image(0, 5.0, 0).within(TIGHT));
        assert!(!TrackedImage { translation_error_m: 0.05, ..image(0, 1.0, 0) }.within(LOOSE));
        assert_eq!(percent(3, 4), 75.0);
        assert_eq!(percent(0, 0), 0.0);
        assert_eq!(median(vec![3.0, 1.0, 2.0]), 2.0);
        assert!(median(Vec::new()).is_nan());
    }

    #[test]
    fn flags_are_named_in_the_per_image_table() {
        assert_eq!(flag_names(0), "-");
        assert_eq!(flag_names(flags::TRACKING | flags::UNSURE), "tracking|unsure");
        assert_eq!(flag_names(flags::LOST | flags::POINTS_RESAMPLED), "lost");
        assert_eq!(flag_names(flags::TRACKING | flags::NETWORK_SKIPPED), "tracking|network_skipped");
    }

    #[test]
    fn a_video_is_summarised_per_object_with_misses_counted() {
        let dir = std::env::temp_dir().join(format!("poseflow-tracking-summary-{}", std::process::id()));
        let scene = SceneDir::new(&dir, 0);
        std::fs::create_dir_all(&scene.path).unwrap();
        // Object 1 annotated in images 0–3, estimated in each.
        let entry = |_| serde_json::json!([{"obj_id": 1, "cam_R_m2c": [1,0,0,0,1,0,0,0,1], "cam_t_m2c": [0,0,500]}]);
        let gt: BTreeMap<String, serde_json::Value> = (0..4).map(|i| (i.to_string(), entry(i))).collect();
        std::fs::write(scene.scene_gt(), serde_json::to_string(&gt).unwrap()).unwrap();
        let images = [
            image(0, 1.0, flags::UNSURE),
            image(1, 20.0, flags::TRACKING | flags::LOST),
            image(2, 7.0, flags::TRACKING | flags::REINITIALISED),
            image(3, 2.0, flags::TRACKING | flags::NETWORK_SKIPPED),
        ];
        let video = summarise_video(&dir, 0, 4, &images).unwrap();
        let o = &video.objects[0];
        assert_eq!((o.frames, o.estimated, o.tracked, o.lost, o.unsure, o.reinitialised), (4, 4, 3, 1, 1, 1));
        assert_eq!(o.network_skipped, 1);
        assert_eq!((o.acc_5deg_5cm, o.acc_10deg_5cm), (50.0, 75.0));
        // Without visible fractions every annotated image counts as visible.
        assert_eq!((o.visible_frames, o.acc_10deg_5cm_visible), (4, 75.0));
        assert!(video.events.is_empty());
        assert!(video.objects_never_visible.is_empty());
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn an_object_never_in_view_is_named_and_not_scored() {
        let dir = std::env::temp_dir().join(format!("poseflow-tracking-unseen-{}", std::process::id()));
        let scene = SceneDir::new(&dir, 0);
        std::fs::create_dir_all(&scene.path).unwrap();
        // Objects 1 and 2 annotated in images 0–1; 1 is 5 % then 40 %
        // visible, 2 is 5 % then out of the image.
        let pose =
            |obj_id| serde_json::json!({"obj_id": obj_id, "cam_R_m2c": [1,0,0,0,1,0,0,0,1], "cam_t_m2c": [0,0,500]});
        let share = |visib_fract| {
            serde_json::json!({"bbox_obj": [0, 0, 1, 1], "bbox_visib": [0, 0, 1, 1], "px_count_all": 100,
                "px_count_valid": 100, "px_count_visib": 10, "visib_fract": visib_fract})
        };
        let gt = serde_json::json!({"0": [pose(1), pose(2)], "1": [pose(1), pose(2)]});
        let info = serde_json::json!({"0": [share(0.05), share(0.05)], "1": [share(0.4), share(0.0)]});
        std::fs::write(scene.scene_gt(), gt.to_string()).unwrap();
        std::fs::write(scene.scene_gt_info(), info.to_string()).unwrap();
        let video = summarise_video(&dir, 0, 2, &[image(1, 1.0, 0)]).unwrap();
        assert_eq!(video.objects.iter().map(|o| o.obj_id).collect::<Vec<_>>(), [1]);
        assert_eq!(video.objects_never_visible, [2]);
        // A hidden image of an object in the video is still a miss.
        assert_eq!((video.objects[0].frames, video.acc_10deg_5cm), (2, 50.0));
        // Of the images in which it could be seen, it was right in all.
        assert_eq!((video.objects[0].visible_frames, video.objects[0].acc_10deg_5cm_visible), (1, 100.0));
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
