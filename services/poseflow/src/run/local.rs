//! `poseflow run --in-process`: the graph's stages as threads of this
//! process, for the stages whose libraries are linked into `poseflow`.

use std::collections::BTreeMap;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use anyhow::bail;
use poseflow_graph::{Graph, OverflowPolicy, Stage};
use poseflow_runtime::{LocalGraph, LocalOverflow};
use poseflow_smoke::{CheckingSink, CountingSource, NegatingRelay};

use super::status::{Outcome, Report, StageReport, edge_flows};

/// Stages that can run in-process, by executable name.
const BUILT_IN: [&str; 3] = ["smoke-source", "smoke-relay", "smoke-sink"];

fn one<'a>(graph: &Graph, stage: &Stage, field: &str, edges: &'a [String]) -> anyhow::Result<&'a str> {
    match edges {
        [edge] => Ok(edge),
        _ => bail!(
            "{}: `stages.{}.{field}`: expected exactly one edge for this stage, found {edges:?}",
            graph.file.display(),
            stage.name
        ),
    }
}

fn add_stage(local: &mut LocalGraph, graph: &Graph, stage: &Stage, instance: &str) -> anyhow::Result<()> {
    let wiring = graph.wiring(stage, instance)?;
    let exe = stage.exe.file_name().and_then(|n| n.to_str()).unwrap_or_default();
    let name = stage.name.as_str();
    let added = match exe {
        "smoke-source" => {
            let rate_hz = wiring.params.get("rate_hz").and_then(|v| v.as_f64());
            let source = CountingSource::from_wiring(&wiring)?;
            local.add_source(name, source, one(graph, stage, "outputs", &stage.outputs)?, rate_hz)
        }
        "smoke-relay" => local.add_transform(
            name,
            NegatingRelay,
            one(graph, stage, "inputs", &stage.inputs)?,
            one(graph, stage, "outputs", &stage.outputs)?,
        ),
        "smoke-sink" => {
            let sink = CheckingSink::from_wiring(&wiring)?;
            local.add_sink(name, sink, one(graph, stage, "inputs", &stage.inputs)?)
        }
        other => bail!(
            "{}: `stages.{name}.exe`: {other:?} cannot run in-process; --in-process runs only the stages linked into poseflow: {}",
            graph.file.display(),
            BUILT_IN.join(", ")
        ),
    };
    added.map_err(|e| anyhow::anyhow!("{}: stage `{name}`: {e}", graph.file.display()))
}

pub fn run(graph: &Graph, instance: &str) -> anyhow::Result<Report> {
    let mut local = LocalGraph::new();
    for edge in graph.edges.values() {
        let overflow = match edge.overflow {
            OverflowPolicy::DropOldest => LocalOverflow::DropOldest,
            OverflowPolicy::Block => LocalOverflow::Block,
        };
        local.edge(&edge.name, edge.queue, overflow);
    }
    for stage in graph.stages.values() {
        add_stage(&mut local, graph, stage, instance)?;
    }
    let stop = Arc::new(AtomicBool::new(false));
    let done = Arc::new(AtomicBool::new(false));
    // Ctrl-C / SIGTERM: iceoryx2's handler records them; stages see `stop`.
    let watcher = std::thread::spawn({
        let (stop, done) = (stop.clone(), done.clone());
        move || {
            while !done.load(Ordering::Relaxed) {
                if iceoryx2_bb_posix::signal::SignalHandler::termination_requested() {
                    stop.store(true, Ordering::Relaxed);
                    break;
                }
                std::thread::sleep(Duration::from_millis(50));
            }
        }
    });
    tracing::info!(graph = %graph.name, stages = graph.stages.len(), "graph running in-process");
    let started = Instant::now();
    let finals = local.run(stop.clone());
    done.store(true, Ordering::Relaxed);
    let _ = watcher.join();
    let stopped = stop.load(Ordering::Relaxed);
    let stages: BTreeMap<String, StageReport> = finals
        .into_iter()
        .map(|(name, beat)| {
            let mut report = StageReport::new(&name);
            report.pid = beat.pid;
            report.outcome = if stopped { Outcome::Stopped } else { Outcome::Finished };
            report.heartbeat = Some(beat);
            (name, report)
        })
        .collect();
    Ok(Report {
        graph: graph.name.clone(),
        instance: instance.to_string(),
        elapsed: started.elapsed(),
        stale_nodes_removed_at_exit: 0,
        edges: edge_flows(graph, &stages),
        stages,
        recording: None,
    })
}
