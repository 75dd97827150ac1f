//! An in-process launch: the graph's stages as threads of this process,
//! each built by its registration in the stage registry.

use std::collections::BTreeMap;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use poseflow_graph::{Graph, OverflowPolicy};
use poseflow_runtime::{LocalGraph, LocalOverflow, Registry};

use crate::LaunchError;
use crate::status::{Outcome, Report, StageReport, edge_flows};

pub fn run(graph: &Graph, instance: &str, registry: &Registry) -> Result<Report, LaunchError> {
    let mut local = LocalGraph::new();
    for edge in graph.edges.values() {
        let overflow = match edge.overflow {
            OverflowPolicy::DropOldest => LocalOverflow::DropOldest,
            OverflowPolicy::Block => LocalOverflow::Block,
        };
        local.edge(&edge.name, edge.queue, overflow);
    }
    for stage in graph.stages.values() {
        let exe = stage.exe.file_name().and_then(|n| n.to_str()).unwrap_or_default();
        let registration =
            registry.get(exe).filter(|r| r.runs_in_process()).ok_or_else(|| LaunchError::NotInProcess {
                file: graph.file.clone(),
                stage: stage.name.clone(),
                exe: exe.to_string(),
                available: registry.in_process_names().join(", "),
            })?;
        let wiring = graph.wiring(stage, instance)?;
        registration.add_to(&mut local, &wiring).map_err(|source| LaunchError::Stage {
            file: graph.file.clone(),
            stage: stage.name.clone(),
            source,
        })?;
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
