//! `poseflow demo --track`: the tracking graph over a rendered video,
//! scored frame by frame against the ground truth.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::{Context, bail};
use poseflow_contracts::{StampSlot, flags};
use poseflow_geometry::Pose;
use poseflow_scene::ModelLibrary;
use serde::Serialize;

use poseflow_scene::bop::{GtEntry, GtInfoEntry, SceneDir, read_json};
use poseflow_scene::video::EventRecord;

use super::pictures::{ErrorSeries, error_plot};
use super::{DemoArgs, ground_truth, print_report, read_recording, symmetries};
use crate::recovery::{EventOutcome, PROMPT_IMAGES, REAPPEARED_VISIBLE, outcomes};
use poseflow_runtime::timing::Timing;

/// Accuracy thresholds of the report: (degrees, metres).
const TIGHT: (f64, f64) = (5.0, 0.05);
const LOOSE: (f64, f64) = (10.0, 0.05);

/// One object over the video.
#[derive(Debug, Serialize)]
struct TrackedObject {
    obj_id: u32,
    /// Images the object is annotated in, and those with an estimate.
    frames: u32,
    estimated: u32,
    /// Estimates whose samples started from the previous estimate.
    tracked: u32,
    /// Estimates the selector's track check flagged `LOST`, `UNSURE`,
    /// `REINITIALISED` (0 without the check).
    lost: u32,
    unsure: u32,
    reinitialised: u32,
    /// Percent of the annotated images whose estimate is within 5°/5 cm
    /// (resp. 10°/5 cm) of the truth; an image without an estimate counts
    /// as a miss.
    acc_5deg_5cm: f64,
    acc_10deg_5cm: f64,
    median_rotation_error_deg: f64,
    max_rotation_error_deg: f64,
    median_translation_error_cm: f64,
    /// From the frame source's stamp to the selector's.
    latency: Timing,
}

#[derive(Debug, Serialize)]
struct TrackingReport {
    out: PathBuf,
    frames: u32,
    orbit_step_deg: f64,
    rate_hz: f64,
    /// Over every object and image.
    acc_5deg_5cm: f64,
    acc_10deg_5cm: f64,
    objects: Vec<TrackedObject>,
    /// The video's occlusions and teleports (`--occlusions`, `--teleports`)
    /// and how soon each object was back within 10°5cm.
    events: Vec<EventOutcome>,
    /// Percent of the events after which the estimate was back within
    /// 10°5cm at most 2 images after the object reappeared or moved.
    events_prompt_pct: f64,
    /// Every estimate: image, object, errors and track flags (CSV).
    table: PathBuf,
    plot: PathBuf,
}

fn median(mut values: Vec<f64>) -> f64 {
    values.sort_by(f64::total_cmp);
    values.get(values.len() / 2).copied().unwrap_or(f64::NAN)
}

fn percent(count: usize, of: usize) -> f64 {
    100.0 * count as f64 / of.max(1) as f64
}

fn within((degrees, metres): (f64, f64), (rotation_deg, translation_m): (f64, f64)) -> bool {
    rotation_deg < degrees && translation_m < metres
}

/// Scores the recorded estimates of the video against its ground truth,
/// prints the report and draws the error plot.
pub fn report(args: &DemoArgs, library: &ModelLibrary, recording: &Path) -> anyhow::Result<()> {
    let truths = ground_truth(&args.out.join("scene"))?;
    // One scene whose every image is a target: frame k is image k.
    let mut by_object: BTreeMap<u32, Vec<(u32, f64, f64)>> = BTreeMap::new();
    let mut latencies: BTreeMap<u32, Vec<Duration>> = BTreeMap::new();
    let mut tracked: BTreeMap<u32, u32> = BTreeMap::new();
    // Per object: [LOST, UNSURE, REINITIALISED] counts, and the LOST images.
    let mut track_flags: BTreeMap<u32, [u32; 3]> = BTreeMap::new();
    let mut lost_images: BTreeMap<u32, Vec<u32>> = BTreeMap::new();
    let mut per_image = String::from("image,object,rotation_error_deg,translation_error_cm,flags\n");
    // Built once per object: a continuous symmetry is hundreds of transforms.
    let mut symmetry_sets = BTreeMap::new();
    for entry in read_recording(recording)? {
        let header = &entry.estimate.header;
        let Ok(im_id) = u32::try_from(header.frame_id) else { continue };
        let Some(truth) = truths.get(&im_id).and_then(|t| t.iter().find(|(id, _)| *id == header.object_id)) else {
            continue;
        };
        let best = Pose::from_f32_row_major(&entry.estimate.best)?;
        let symmetries = match symmetry_sets.entry(header.object_id) {
            std::collections::btree_map::Entry::Occupied(set) => set.into_mut(),
            std::collections::btree_map::Entry::Vacant(slot) => slot.insert(symmetries(library, header.object_id)?),
        };
        let error = symmetries.pose_error(&best, &truth.1);
        by_object.entry(header.object_id).or_default().push((im_id, error.rotation.to_degrees(), error.translation));
        per_image.push_str(&format!(
            "{im_id},{},{:.3},{:.3},{}\n",
            header.object_id,
            error.rotation.to_degrees(),
            error.translation * 100.0,
            flag_names(header.flags)
        ));
        if let Some(ns) = header.stamps.elapsed_ns(StampSlot::Source, StampSlot::Selector) {
            latencies.entry(header.object_id).or_default().push(Duration::from_nanos(ns));
        }
        if header.flags & flags::TRACKING != 0 {
            *tracked.entry(header.object_id).or_default() += 1;
        }
        let counts = track_flags.entry(header.object_id).or_default();
        for (count, bit) in counts.iter_mut().zip([flags::LOST, flags::UNSURE, flags::REINITIALISED]) {
            *count += u32::from(header.flags & bit != 0);
        }
        if header.flags & flags::LOST != 0 {
            lost_images.entry(header.object_id).or_default().push(im_id);
        }
    }
    if by_object.is_empty() {
        bail!("the tracking graph produced no estimate for the video's objects (see {})", recording.display());
    }
    let mut annotated: BTreeMap<u32, u32> = BTreeMap::new();
    for (obj_id, _) in truths.values().flatten() {
        *annotated.entry(*obj_id).or_default() += 1;
    }
    let (mut tight_all, mut loose_all, mut frames_all) = (0, 0, 0);
    let mut objects = Vec::new();
    for (obj_id, frames) in &annotated {
        let errors = by_object.get(obj_id).map_or(&[][..], Vec::as_slice);
        let tight = errors.iter().filter(|e| within(TIGHT, (e.1, e.2))).count();
        let loose = errors.iter().filter(|e| within(LOOSE, (e.1, e.2))).count();
        (tight_all, loose_all, frames_all) = (tight_all + tight, loose_all + loose, frames_all + *frames as usize);
        objects.push(TrackedObject {
            obj_id: *obj_id,
            frames: *frames,
            estimated: errors.len() as u32,
            tracked: tracked.get(obj_id).copied().unwrap_or(0),
            lost: track_flags.get(obj_id).map_or(0, |c| c[0]),
            unsure: track_flags.get(obj_id).map_or(0, |c| c[1]),
            reinitialised: track_flags.get(obj_id).map_or(0, |c| c[2]),
            acc_5deg_5cm: percent(tight, *frames as usize),
            acc_10deg_5cm: percent(loose, *frames as usize),
            median_rotation_error_deg: median(errors.iter().map(|e| e.1).collect()),
            max_rotation_error_deg: errors.iter().map(|e| e.1).fold(0.0, f64::max),
            median_translation_error_cm: median(errors.iter().map(|e| e.2 * 100.0).collect()),
            latency: Timing::of(latencies.remove(obj_id).unwrap_or_default()),
        });
    }
    let within_loose: BTreeMap<(u32, u32), bool> = by_object
        .iter()
        .flat_map(|(obj_id, errors)| errors.iter().map(move |e| ((e.0, *obj_id), within(LOOSE, (e.1, e.2)))))
        .collect();
    let events = event_outcomes(&args.out.join("scene"), &within_loose, args.frames)?;
    let table = args.out.join("tracking.csv");
    std::fs::write(&table, per_image).with_context(|| format!("writing {}", table.display()))?;
    let plot = args.out.join("tracking.png");
    let series: Vec<ErrorSeries> = by_object
        .iter()
        .map(|(obj_id, errors)| ErrorSeries {
            obj_id: *obj_id,
            points: errors.iter().map(|e| (e.0, e.1)).collect(),
            lost: lost_images.remove(obj_id).unwrap_or_default(),
        })
        .collect();
    error_plot(&series, args.frames, &plot)?;
    let report = TrackingReport {
        out: args.out.clone(),
        frames: args.frames,
        orbit_step_deg: args.orbit_step_deg,
        rate_hz: args.rate_hz,
        acc_5deg_5cm: percent(tight_all, frames_all),
        acc_10deg_5cm: percent(loose_all, frames_all),
        objects,
        events_prompt_pct: percent(events.iter().filter(|e| e.prompt()).count(), events.len()),
        events,
        table,
        plot,
    };
    print_report(&report, args.json, print_table)
}

/// The outcomes of the rendered video's events, if it has any.
fn event_outcomes(
    dataset: &Path,
    within: &BTreeMap<(u32, u32), bool>,
    frames: u32,
) -> anyhow::Result<Vec<EventOutcome>> {
    let scene = SceneDir::new(&dataset.join("test"), 0);
    if !scene.video_events().is_file() {
        return Ok(Vec::new());
    }
    let events: Vec<EventRecord> = read_json(&scene.video_events())?;
    let gt: BTreeMap<u32, Vec<GtEntry>> = read_json(&scene.scene_gt())?;
    let info: BTreeMap<u32, Vec<GtInfoEntry>> = read_json(&scene.scene_gt_info())?;
    let visible = gt
        .iter()
        .flat_map(|(im_id, entries)| {
            let shares = info.get(im_id).map_or(&[][..], Vec::as_slice);
            entries.iter().zip(shares).map(move |(entry, share)| ((*im_id, entry.obj_id), share.visib_fract))
        })
        .collect();
    Ok(outcomes(&events, &visible, within, frames))
}

/// The track flags of an Estimate header, `|`-separated (`-` for none).
fn flag_names(bits: u32) -> String {
    let names: Vec<&str> = [
        (flags::TRACKING, "tracking"),
        (flags::LOST, "lost"),
        (flags::UNSURE, "unsure"),
        (flags::REINITIALISED, "reinitialised"),
    ]
    .into_iter()
    .filter(|(bit, _)| bits & bit != 0)
    .map(|(_, name)| name)
    .collect();
    if names.is_empty() { "-".into() } else { names.join("|") }
}

fn print_table(report: &TrackingReport) {
    println!(
        "tracking over {} images (camera orbit {}°/image at {} Hz): 5°5cm {:.1} %, 10°5cm {:.1} % of object-images",
        report.frames, report.orbit_step_deg, report.rate_hz, report.acc_5deg_5cm, report.acc_10deg_5cm
    );
    println!(
        "object  estimated  tracked  lost  unsure  reinit  5°5cm %  10°5cm %  median rot °  max rot °  median trans cm  latency p50/p99 ms"
    );
    for o in &report.objects {
        println!(
            "{:>6}  {:>4}/{:<4}  {:>7}  {:>4}  {:>6}  {:>6}  {:>7.1}  {:>8.1}  {:>12.2}  {:>9.1}  {:>15.2}  {:>8.1}/{:.1}",
            o.obj_id,
            o.estimated,
            o.frames,
            o.tracked,
            o.lost,
            o.unsure,
            o.reinitialised,
            o.acc_5deg_5cm,
            o.acc_10deg_5cm,
            o.median_rotation_error_deg,
            o.max_rotation_error_deg,
            o.median_translation_error_cm,
            o.latency.p50_ms,
            o.latency.p99_ms
        );
    }
    if !report.events.is_empty() {
        println!(
            "events: {} of {} back within 10°5cm at most {PROMPT_IMAGES} images after the object reappeared (≥ {:.0} % visible) or moved ({:.1} %)",
            report.events.iter().filter(|e| e.prompt()).count(),
            report.events.len(),
            REAPPEARED_VISIBLE * 100.0,
            report.events_prompt_pct
        );
        for e in &report.events {
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
    println!("per image: {}", report.table.display());
    println!(
        "plot: {} (rotation error per image, one colour per object; grey lines at 5° and 10°; crosses: LOST)",
        report.plot.display()
    );
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn thresholds_are_strict_and_misses_count_against_accuracy() {
        assert!(within(TIGHT, (4.99, 0.049)));
        assert!(!within(TIGHT, (5.0, 0.01)));
        assert!(!within(LOOSE, (1.0, 0.05)));
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
    }
}
