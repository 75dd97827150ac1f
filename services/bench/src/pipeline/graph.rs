//! One graph run of the pipeline benchmark: `poseflow run` with the
//! estimates edge recorded; per-frame latency from the frame source's
//! stamp to the recorder receiving the frame's last Estimate.

use std::collections::BTreeMap;
use std::path::Path;
use std::time::Duration;

use anyhow::{Context, bail};
use poseflow_contracts::{EstimateHeader, StampSlot};
use poseflow_runtime::recording::{RecordingReader, header_from_bytes};

use super::{FrameLatencies, VerdictCounts};
use crate::graph_run::GraphRun;

/// Process time per message of one stage, from its last heartbeat.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
pub(super) struct StageLatency {
    pub p50_us: u64,
    pub p99_us: u64,
}

/// What one graph run measured, warm-up frames left out.
#[derive(Debug)]
pub(super) struct GraphRunFigures {
    pub frames: FrameLatencies,
    /// Between the first and the last counted frame's last Estimate.
    pub span: Duration,
    pub stages: BTreeMap<String, StageLatency>,
    pub restarts: u64,
    pub errors: u64,
    /// Per counted estimate, the time between consecutive stamps of its
    /// path named by their stages (`frames→ingest`, …, `selector→received`): process time plus
    /// queueing and transport, where the time goes in the graph.
    pub path: BTreeMap<String, Vec<Duration>>,
    /// The counted estimates by the track check's verdict.
    pub verdicts: VerdictCounts,
}

/// Runs the graph to its end and reads what it recorded.
pub(super) fn measure(
    run: &GraphRun<'_>,
    log: &Path,
    warmup: u64,
    owners: &StampOwners,
) -> anyhow::Result<GraphRunFigures> {
    let summary = run.launch(log)?;
    let stages = summary["stages"].as_object().context("the run's summary has no `stages`")?;
    for (name, stage) in stages {
        if stage["outcome"] != "finished" {
            bail!(
                "{}: stage `{name}` ended {} ({}); its log: {}",
                run.graph.display(),
                stage["outcome"],
                stage["failure"],
                log.display()
            );
        }
    }
    let latency = |stage: &serde_json::Value| StageLatency {
        p50_us: stage["p50_us"].as_u64().unwrap_or(0),
        p99_us: stage["p99_us"].as_u64().unwrap_or(0),
    };
    let total = |key: &str| stages.values().filter_map(|s| s[key].as_u64()).sum::<u64>();
    let Recorded { frames, span, path, verdicts } = read_recording(run.record.0, run.record.1, warmup, owners)?;
    Ok(GraphRunFigures {
        frames,
        span,
        stages: stages.iter().map(|(name, s)| (name.clone(), latency(s))).collect(),
        restarts: total("restarts"),
        errors: stages.values().filter_map(|s| s["total"]["errors"].as_u64()).sum(),
        path,
        verdicts,
    })
}

/// Which graph stage writes each timestamp slot ([`poseflow_launch::stamp_owners`]).
pub(super) type StampOwners = BTreeMap<StampSlot, String>;

/// The intervals between consecutive stamps of an Estimate's path, in time
/// order, named by the stages that wrote them (`frames→ingest`, …), the
/// last ending when it was received (`received_ns`, the stamps' clock).
pub(super) fn path_intervals(
    header: &EstimateHeader,
    received_ns: u64,
    owners: &StampOwners,
) -> Vec<(String, Duration)> {
    let mut stamps: Vec<(u64, &str)> = StampSlot::ALL
        .iter()
        .filter_map(|slot| {
            let at = header.header.stamps.get(*slot)?;
            Some((at, owners.get(slot).map_or(slot.name(), String::as_str)))
        })
        .collect();
    stamps.sort_by_key(|&(at, _)| at);
    stamps.push((received_ns, "received"));
    stamps
        .windows(2)
        .map(|pair| (format!("{}→{}", pair[0].1, pair[1].1), Duration::from_nanos(pair[1].0.saturating_sub(pair[0].0))))
        .collect()
}

/// What a run's recording of its Estimates says, frames before `warmup`
/// left out.
struct Recorded {
    /// Per frame id: estimates, latency from the source's stamp to the
    /// last one received.
    frames: FrameLatencies,
    /// From the first counted frame's completion to the last's.
    span: Duration,
    /// The path's intervals per estimate.
    path: BTreeMap<String, Vec<Duration>>,
    verdicts: VerdictCounts,
}

fn read_recording(recording: &Path, edge: &str, warmup: u64, owners: &StampOwners) -> anyhow::Result<Recorded> {
    let mut reader = RecordingReader::open(recording).with_context(|| format!("{}", recording.display()))?;
    // frame id → (source stamp, last received, estimates)
    let mut frames: BTreeMap<u64, (u64, u64, usize)> = BTreeMap::new();
    let mut path: BTreeMap<String, Vec<Duration>> = BTreeMap::new();
    let mut verdicts = VerdictCounts::default();
    while let Some(message) = reader.next_message()? {
        if message.edge != edge {
            continue;
        }
        let header: EstimateHeader = header_from_bytes(&message.header)
            .with_context(|| format!("{}: a message on `{edge}` is not an Estimate", recording.display()))?;
        let frame = header.header.frame_id;
        let source = header.header.stamps.get(StampSlot::Source).with_context(|| {
            format!("{}: frame {frame}: the Estimate carries no frame-source stamp", recording.display())
        })?;
        let entry = frames.entry(frame).or_insert((source, 0, 0));
        entry.1 = entry.1.max(message.received_ns);
        entry.2 += 1;
        if frame >= warmup {
            verdicts.count(header.header.flags);
            for (interval, duration) in path_intervals(&header, message.received_ns, owners) {
                path.entry(interval).or_default().push(duration);
            }
        }
    }
    let mut latencies = FrameLatencies::default();
    let counted: Vec<_> = frames.range(warmup..).collect();
    for &(&frame, &(source, done, estimates)) in &counted {
        latencies.record(frame, estimates, Duration::from_nanos(done.saturating_sub(source)));
    }
    let done = |entry: Option<&(&u64, &(u64, u64, usize))>| entry.map_or(0, |(_, e)| e.1);
    let span = Duration::from_nanos(done(counted.last()).saturating_sub(done(counted.first())));
    Ok(Recorded { frames: latencies, span, path, verdicts })
}
