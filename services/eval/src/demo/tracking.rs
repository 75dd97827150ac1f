//! `poseflow demo --track`: the tracking graph over a rendered video,
//! scored frame by frame against the ground truth ([`crate::tracking`]).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::{Context, bail};
use poseflow_contracts::{StampSlot, flags};
use poseflow_geometry::{Pose, SymmetrySet};
use serde::Serialize;

use super::pictures::{ErrorSeries, error_plot};
use super::{DemoArgs, ground_truth, print_report, read_recording, symmetries_note};
use crate::SymmetriesArg;
use crate::tracking::{TrackedImage, VideoSummary, print_video, summarise_video, write_per_image};

#[derive(Debug, Serialize)]
struct TrackingReport {
    out: PathBuf,
    orbit_step_deg: f64,
    rate_hz: f64,
    /// The symmetries the errors were scored up to.
    symmetries: SymmetriesArg,
    #[serde(flatten)]
    video: VideoSummary,
    /// Every estimate: image, object, errors and track flags (CSV).
    table: PathBuf,
    plot: PathBuf,
}

/// Scores the tracking graph's `recording` against the video's ground
/// truth, up to `symmetries` (read from `source`), and prints the report.
pub fn report(
    args: &DemoArgs,
    symmetries: &BTreeMap<u32, SymmetrySet>,
    source: SymmetriesArg,
    recording: &Path,
) -> anyhow::Result<()> {
    let truths = ground_truth(&args.out.join("scene"))?;
    // One scene whose every image is a target: frame k is image k.
    let mut images = Vec::new();
    for entry in read_recording(recording)? {
        let header = &entry.estimate.header;
        let Ok(im_id) = u32::try_from(header.frame_id) else { continue };
        let Some(truth) = truths.get(&im_id).and_then(|t| t.iter().find(|(id, _)| *id == header.object_id)) else {
            continue;
        };
        let best = Pose::from_f32_row_major(&entry.estimate.best)?;
        let symmetries = symmetries.get(&header.object_id).context("an object of the video")?;
        let error = symmetries.pose_error(&best, &truth.1);
        images.push(TrackedImage {
            im_id,
            obj_id: header.object_id,
            rotation_error_deg: error.rotation.to_degrees(),
            translation_error_m: error.translation,
            flags: header.flags,
            latency: header.stamps.elapsed_ns(StampSlot::Source, StampSlot::Selector).map(Duration::from_nanos),
        });
    }
    if images.is_empty() {
        bail!("the tracking graph produced no estimate for the video's objects (see {})", recording.display());
    }
    let video = summarise_video(&args.out.join("scene").join("test"), 0, args.frames, &images)?;
    let table = args.out.join("tracking.csv");
    write_per_image(&table, &[(0, &images)])?;
    let plot = args.out.join("tracking.png");
    let mut series: BTreeMap<u32, ErrorSeries> = BTreeMap::new();
    for image in &images {
        let s = series.entry(image.obj_id).or_insert_with(|| ErrorSeries {
            obj_id: image.obj_id,
            points: Vec::new(),
            lost: Vec::new(),
        });
        s.points.push((image.im_id, image.rotation_error_deg));
        if image.flags & flags::LOST != 0 {
            s.lost.push(image.im_id);
        }
    }
    error_plot(&series.into_values().collect::<Vec<_>>(), args.frames, &plot)?;
    let report = TrackingReport {
        out: args.out.clone(),
        orbit_step_deg: args.orbit_step_deg,
        rate_hz: args.rate_hz,
        symmetries: source,
        video,
        table,
        plot,
    };
    print_report(&report, args.json, print_table)
}

fn print_table(report: &TrackingReport) {
    println!(
        "tracking over {} images (camera orbit {}°/image at {} Hz): 5°5cm {:.1} %, 10°5cm {:.1} % of object-images, \
         up to the objects' symmetries{}",
        report.video.frames,
        report.orbit_step_deg,
        report.rate_hz,
        report.video.acc_5deg_5cm,
        report.video.acc_10deg_5cm,
        symmetries_note(report.symmetries)
    );
    print_video(&report.video);
    println!("per image: {}", report.table.display());
    println!(
        "plot: {} (rotation error per image, one colour per object; grey lines at 5° and 10°; crosses: LOST)",
        report.plot.display()
    );
}
