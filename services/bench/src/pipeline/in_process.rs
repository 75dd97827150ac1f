//! The in-process baseline: the graph's pose stages as one
//! [`PosePipeline`] with the graph's parameters, frame after frame on one
//! thread (the same library code the stage processes run).

use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use poseflow_graph::Graph;
use poseflow_inference::stage::InferenceParams;
use poseflow_ingest::IngestParams;
use poseflow_ingest::sources::LoadedFrame;
use poseflow_pipeline::{PosePipeline, StageTimes};
use poseflow_sampler::SamplerParams;
use poseflow_selector::SelectorParams;

use super::FrameLatencies;

/// The parameters of the stage whose executable is `exe`.
fn params_of<'a>(graph: &'a Graph, exe: &str) -> anyhow::Result<&'a serde_json::Value> {
    let mut found = graph.stages.values().filter(|s| s.exe.file_name().is_some_and(|n| n == exe));
    match (found.next(), found.next()) {
        (Some(stage), None) => Ok(&stage.params),
        (None, _) => bail!("{}: no stage with exe = {exe:?}; the pipeline benchmark needs one", graph.file.display()),
        (Some(_), Some(_)) => bail!("{}: several stages with exe = {exe:?}; expected one", graph.file.display()),
    }
}

/// The graph's ingest, inference, sampler and selector as one pipeline.
pub(super) fn pipeline_of(graph: &Graph) -> anyhow::Result<PosePipeline> {
    let context = |stage: &str| format!("{}: stage `{stage}`", graph.file.display());
    let ingest = IngestParams::from_json(params_of(graph, "ingest")?).with_context(|| context("ingest"))?;
    let inference = InferenceParams::from_json(params_of(graph, "inference")?).with_context(|| context("inference"))?;
    let sampler = SamplerParams::from_json(params_of(graph, "sampler")?).with_context(|| context("sampler"))?;
    let selector = SelectorParams::from_json(params_of(graph, "selector")?).with_context(|| context("selector"))?;
    Ok(PosePipeline::new(ingest, &inference, sampler, selector)?)
}

/// What the in-process run measured, warm-up frames left out.
#[derive(Debug)]
pub(super) struct InProcess {
    pub frames: FrameLatencies,
    /// Per estimate, where its time went.
    pub stage_times: Vec<StageTimes>,
    pub wall: Duration,
}

/// Estimates every object of every frame in order, back to back or, with
/// `period`, one frame per period (as a paced frame source sends them);
/// frames before `warmup` are run but not counted.
pub(super) fn measure(
    pipeline: &mut PosePipeline,
    frames: &[LoadedFrame],
    warmup: usize,
    period: Option<Duration>,
) -> InProcess {
    let mut measured = InProcess { frames: FrameLatencies::default(), stage_times: Vec::new(), wall: Duration::ZERO };
    let first = Instant::now();
    for (index, loaded) in frames.iter().enumerate() {
        let _span = tracing::debug_span!("frame", id = loaded.frame.frame_id).entered();
        if let Some(period) = period {
            std::thread::sleep((first + period * index as u32).saturating_duration_since(Instant::now()));
        }
        let started = Instant::now();
        let mut estimated = 0;
        let mut times = Vec::new();
        for object in &loaded.objects {
            match pipeline.estimate(&loaded.frame, object) {
                Ok(estimate) => {
                    estimated += 1;
                    times.push(estimate.times);
                }
                Err(err) => tracing::warn!(object = object.obj_id, %err, "not estimated"),
            }
        }
        let latency = started.elapsed();
        if index < warmup {
            continue;
        }
        measured.wall += latency;
        measured.frames.record(loaded.frame.frame_id, estimated, latency);
        measured.stage_times.extend(times);
    }
    measured
}
