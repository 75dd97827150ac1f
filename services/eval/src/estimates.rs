//! The estimates an evaluation scores, whatever produced them: the
//! graph's recording, or another method's BOP19 results file.

use std::collections::BTreeMap;
use std::path::Path;
use std::time::Duration;

use anyhow::Context;
use poseflow_contracts::{EstimateHeader, ObjectCategory, StampSlot, WEIGHTED_POSE_LEN};
use poseflow_geometry::Pose;
use poseflow_runtime::recording::{RecordingReader, header_from_bytes};

use super::bop_csv::{self, BopRow};
use super::dataset::TruthImage;

/// One estimate of one object in one image, from the graph or a results
/// file.
#[derive(Debug)]
pub struct Estimated {
    pub scene_id: u32,
    pub im_id: u32,
    pub obj_id: u32,
    pub selected: Pose,
    pub score: f64,
    /// Every scored hypothesis, best first (none from a results file).
    pub hypotheses: Vec<Pose>,
    /// How many of the first `hypotheses` the selector kept.
    pub kept: usize,
    /// Trace of the rotational covariance, rad², when reported.
    pub rotation_trace: Option<f64>,
    /// The method's time on this object.
    pub service_time: Option<Duration>,
    /// From reading the image to the estimate.
    pub latency: Option<Duration>,
    /// The Estimate header's flags (0 from a results file; `TRACKING`: the
    /// samples started from an earlier estimate or a prior).
    pub flags: u32,
    /// A category-level model's category and size (none from a results
    /// file or an instance-level model).
    pub category: Option<ObjectCategory>,
}

/// The graph's estimates in a recording, placed in their images (the frame
/// id is the image's position in the frame source's stream). The service
/// time of an estimate is the interval since the previous one left the
/// selector: the graph is kept saturated, so this is the cost of one more
/// object (its mean is the inverse of the throughput); the first estimate,
/// which also waited for the graph to start, has none.
/// An Estimate's hypotheses with their scores, best first (the kept ones
/// are the first `kept_count`).
pub fn scored_hypotheses(header: &EstimateHeader, payload: &[f32]) -> anyhow::Result<Vec<(Pose, f64)>> {
    let view = header.view(payload).context("estimate payload")?;
    view.hypotheses
        .chunks_exact(WEIGHTED_POSE_LEN)
        .map(|c| Ok((Pose::from_f32_row_major(c[..12].try_into().expect("12 values"))?, f64::from(c[12]))))
        .collect()
}

pub fn read_recording(path: &Path, images: &[TruthImage]) -> anyhow::Result<Vec<Estimated>> {
    let mut reader = RecordingReader::open(path).with_context(|| format!("{}", path.display()))?;
    let mut estimates = Vec::new();
    while let Some(message) = reader.next_message()? {
        if message.edge != "estimates" {
            continue;
        }
        let header: EstimateHeader = header_from_bytes(&message.header).context("estimate header")?;
        let scored = scored_hypotheses(&header, &message.payload)?;
        let frame = header.header.frame_id;
        let image = usize::try_from(frame).ok().and_then(|i| images.get(i)).with_context(|| {
            format!("{}: an estimate of frame {frame}, but the dataset has {} images", path.display(), images.len())
        })?;
        estimates.push((
            (header.header.stamps.get(StampSlot::Selector), frame),
            Estimated {
                scene_id: image.scene_id,
                im_id: image.im_id,
                obj_id: header.header.object_id,
                selected: Pose::from_f32_row_major(&header.best)?,
                score: scored.first().map_or(0.0, |h| h.1),
                hypotheses: scored.into_iter().map(|h| h.0).collect(),
                kept: header.kept_count as usize,
                rotation_trace: Some(f64::from(header.rotation_trace)),
                service_time: None,
                latency: header
                    .header
                    .stamps
                    .elapsed_ns(StampSlot::Source, StampSlot::Selector)
                    .map(Duration::from_nanos),
                flags: header.header.flags,
                category: header.category.is_set().then_some(header.category),
            },
        ));
    }
    estimates.sort_by_key(|((departure, _), _)| *departure);
    let departures: Vec<(Option<u64>, u64)> = estimates.iter().map(|(departure, _)| *departure).collect();
    for (i, time) in service_times(&departures).into_iter().enumerate() {
        estimates[i].1.service_time = time;
    }
    Ok(estimates.into_iter().map(|(_, estimate)| estimate).collect())
}

/// Each estimate's share of the selector's time: `departures` are
/// (selector stamp, frame id) in departure order. The selector publishes a
/// frame's objects together, so the interval from the previous frame's
/// last estimate to this frame's last is split evenly among the frame's
/// estimates; the first frame, and a frame next to one without a stamp,
/// has none.
fn service_times(departures: &[(Option<u64>, u64)]) -> Vec<Option<Duration>> {
    let mut times = vec![None; departures.len()];
    let mut previous_end: Option<u64> = None;
    let mut start = 0;
    while start < departures.len() {
        let frame = departures[start].1;
        let end = start + departures[start..].iter().take_while(|(_, f)| *f == frame).count();
        let stamps: Option<Vec<u64>> = departures[start..end].iter().map(|(stamp, _)| *stamp).collect();
        let last = stamps.as_ref().and_then(|stamps| stamps.iter().max().copied());
        if let (Some(previous), Some(last)) = (previous_end, last) {
            let share = Duration::from_nanos(last.saturating_sub(previous)) / (end - start) as u32;
            times[start..end].fill(Some(share));
        }
        previous_end = last;
        start = end;
    }
    times
}

/// Estimates counted so far in a recording being written (a partly
/// written last message ends the count).
pub fn count_estimates(path: &Path) -> u64 {
    let Ok(mut reader) = RecordingReader::open(path) else { return 0 };
    let mut count = 0;
    while let Ok(Some(message)) = reader.next_message() {
        count += u64::from(message.edge == "estimates");
    }
    count
}

/// Another method's estimates from a BOP19 results file; its time per
/// image is shared evenly by the image's estimates.
pub fn read_results(path: &Path) -> anyhow::Result<Vec<Estimated>> {
    let text = std::fs::read_to_string(path).with_context(|| format!("--results {}", path.display()))?;
    let rows = bop_csv::parse(&text, path)?;
    let mut per_image: BTreeMap<(u32, u32), u32> = BTreeMap::new();
    for row in &rows {
        *per_image.entry((row.scene_id, row.im_id)).or_default() += 1;
    }
    Ok(rows
        .iter()
        .map(|row| Estimated {
            scene_id: row.scene_id,
            im_id: row.im_id,
            obj_id: row.obj_id,
            selected: row.pose,
            score: row.score,
            hypotheses: Vec::new(),
            kept: 0,
            rotation_trace: None,
            service_time: row
                .time_s
                .map(|s| Duration::from_secs_f64(s / f64::from(per_image[&(row.scene_id, row.im_id)]))),
            latency: row.time_s.map(Duration::from_secs_f64),
            flags: 0,
            category: None,
        })
        .collect())
}

/// The graph's estimates as BOP19 rows; an image's time is what the graph
/// spent on its objects.
pub fn bop_rows(estimates: &[Estimated]) -> Vec<BopRow> {
    let mut image_time: BTreeMap<(u32, u32), Option<Duration>> = BTreeMap::new();
    for e in estimates {
        let time = image_time.entry((e.scene_id, e.im_id)).or_insert(Some(Duration::ZERO));
        *time = time.zip(e.service_time).map(|(a, b)| a + b);
    }
    estimates
        .iter()
        .map(|e| BopRow {
            scene_id: e.scene_id,
            im_id: e.im_id,
            obj_id: e.obj_id,
            score: e.score,
            pose: e.selected,
            time_s: image_time[&(e.scene_id, e.im_id)].map(|d| d.as_secs_f64()),
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_frame_published_together_shares_the_interval_since_the_frame_before() {
        // Frame 0 at 10 ms; frame 1's three objects at 40 ms (a few µs
        // apart); frame 2's one object at 55 ms.
        let ms = |x: f64| Some((x * 1e6) as u64);
        let departures = [(ms(10.0), 0), (ms(40.0), 1), (ms(40.001), 1), (ms(40.002), 1), (ms(55.0), 2)];
        let times: Vec<Option<f64>> =
            service_times(&departures).into_iter().map(|t| t.map(|t| t.as_secs_f64() * 1e3)).collect();
        assert_eq!(times[0], None);
        for t in &times[1..4] {
            assert!((t.unwrap() - 30.002 / 3.0).abs() < 1e-6, "{times:?}");
        }
        assert!((times[4].unwrap() - 14.998).abs() < 1e-6, "{times:?}");
        // A frame without a stamp breaks the chain on both sides.
        let gap = [(ms(10.0), 0), (None, 1), (ms(30.0), 2)];
        assert_eq!(service_times(&gap), vec![None, None, None]);
    }
}
