//! The in-process baseline: the graph's stages between its frames and its
//! estimates as threads of this process ([`DrivenGraph`], built by the
//! same registrations as the processes), one frame at a time: no transport
//! and no pipelining across frames.

use std::collections::BTreeMap;
use std::time::{Duration, Instant};

use poseflow_contracts::{EstimateHeader, FrameHeader, monotonic_ns};
use poseflow_graph::Graph;
use poseflow_ingest::frame_message;
use poseflow_ingest::sources::LoadedFrame;
use poseflow_launch::DrivenGraph;

use super::FrameLatencies;
use super::graph::{StampOwners, path_intervals};

pub(super) type InProcessGraph = DrivenGraph<FrameHeader, EstimateHeader>;

/// The graph's stages from `frames` to `estimates`, started.
pub(super) fn start(graph: &Graph, frames: &str, estimates: &str) -> anyhow::Result<InProcessGraph> {
    Ok(DrivenGraph::start(graph, &poseflow_stages::registry(), frames, estimates)?)
}

/// What the in-process run measured, warm-up frames left out.
#[derive(Debug)]
pub(super) struct InProcess {
    pub frames: FrameLatencies,
    /// Per estimate, the intervals between the stamps of its path (as the
    /// graph's are measured).
    pub path: BTreeMap<String, Vec<Duration>>,
    pub wall: Duration,
}

/// Estimates every object of every frame in order, back to back or, with
/// `period`, one frame per period (as a paced frame source sends them);
/// frames before `warmup` are run but not counted.
pub(super) fn measure(
    graph: &mut InProcessGraph,
    frames: &[LoadedFrame],
    warmup: usize,
    period: Option<Duration>,
    owners: &StampOwners,
) -> anyhow::Result<InProcess> {
    let mut measured = InProcess { frames: FrameLatencies::default(), path: BTreeMap::new(), wall: Duration::ZERO };
    let first = Instant::now();
    for (index, loaded) in frames.iter().enumerate() {
        let _span = tracing::debug_span!("frame", id = loaded.frame.frame_id).entered();
        if let Some(period) = period {
            std::thread::sleep((first + period * index as u32).saturating_duration_since(Instant::now()));
        }
        let started = Instant::now();
        let (header, payload) = frame_message(loaded);
        let estimates = graph.process(header, payload)?;
        let (latency, received) = (started.elapsed(), monotonic_ns());
        if index < warmup {
            continue;
        }
        measured.wall += latency;
        measured.frames.record(loaded.frame.frame_id, estimates.len(), latency);
        for (estimate, _) in &estimates {
            for (interval, duration) in path_intervals(estimate, received, owners) {
                measured.path.entry(interval).or_default().push(duration);
            }
        }
    }
    Ok(measured)
}
