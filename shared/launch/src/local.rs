//! An in-process launch: the graph's stages as threads of this process,
//! each built by its registration in the stage registry.

use std::collections::BTreeMap;
use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use poseflow_contracts::{MessageHeader, MessageVisitor, stamp_clock_ns, visit_message};
use poseflow_graph::{Graph, OverflowPolicy};
use poseflow_runtime::recording::{RecordedMessage, RecordingError, RecordingWriter};
use poseflow_runtime::{BuildError, Input, LocalGraph, LocalOverflow, Registry, Sink};

use crate::LaunchError;
use crate::status::{Outcome, Report, StageReport, edge_flows};

/// The stage-name prefix of the recorder's taps (one reader per recorded
/// edge); they are not graph stages and are left out of the report.
const TAP: &str = "_record/";

/// One recorded edge's reader: writes every message it receives.
struct Tap<H> {
    edge: String,
    writer: Arc<Mutex<RecordingWriter>>,
    _message: std::marker::PhantomData<fn() -> H>,
}

impl<H: MessageHeader> Sink for Tap<H> {
    type In = H;
    type Error = RecordingError;

    fn consume(&mut self, input: Input<'_, H>) -> Result<(), RecordingError> {
        let message = RecordedMessage {
            edge: self.edge.clone(),
            received_ns: stamp_clock_ns(),
            header: poseflow_runtime::recording::header_bytes(input.header),
            payload: input.payload.to_vec(),
        };
        self.writer.lock().unwrap_or_else(|e| e.into_inner()).write(&message)
    }

    fn finish(&mut self) -> Result<(), RecordingError> {
        Ok(())
    }
}

/// Adds a tap of the edge's message type.
struct AddTap<'a> {
    local: &'a mut LocalGraph,
    edge: &'a str,
    writer: &'a Arc<Mutex<RecordingWriter>>,
}

impl MessageVisitor for AddTap<'_> {
    type Output = Result<(), poseflow_runtime::LocalGraphError>;

    fn visit<H: MessageHeader + Send + 'static>(self) -> Self::Output {
        let tap = Tap::<H> { edge: self.edge.to_string(), writer: self.writer.clone(), _message: Default::default() };
        self.local.add_sink(&format!("{TAP}{}", self.edge), move || Ok::<_, BuildError>(tap), self.edge)
    }
}

/// Taps `edges` of `local` into a recording at `path`.
fn add_taps(
    local: &mut LocalGraph,
    graph: &Graph,
    instance: &str,
    path: &Path,
    edges: &[String],
) -> Result<Arc<Mutex<RecordingWriter>>, LaunchError> {
    let info = crate::record::recording_info(graph, instance, edges);
    let writer = Arc::new(Mutex::new(RecordingWriter::create(path, &info)?));
    for edge in &info.edges {
        let unknown = || LaunchError::UnknownMessage { edge: edge.edge.clone(), message: edge.message.clone() };
        visit_message(&edge.message, AddTap { local, edge: &edge.edge, writer: &writer })
            .ok_or_else(unknown)?
            .map_err(|source| LaunchError::InProcess { file: graph.file.clone(), source: source.into() })?;
    }
    Ok(writer)
}

/// The stages of `graph` that `keep` selects, each built by its
/// registration, in a new [`LocalGraph`] with every edge declared.
pub(crate) fn build(
    graph: &Graph,
    instance: &str,
    registry: &Registry,
    keep: impl Fn(&poseflow_graph::Stage) -> bool,
) -> Result<LocalGraph, LaunchError> {
    let mut local = LocalGraph::new();
    for edge in graph.edges.values() {
        let overflow = match edge.overflow {
            OverflowPolicy::DropOldest => LocalOverflow::DropOldest,
            OverflowPolicy::Block => LocalOverflow::Block,
        };
        local.edge(&edge.name, edge.queue, overflow);
    }
    for stage in graph.stages.values().filter(|stage| keep(stage)) {
        let exe = stage.exe_name();
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
    Ok(local)
}

pub fn run(
    graph: &Graph,
    instance: &str,
    registry: &Registry,
    record: Option<&(std::path::PathBuf, Vec<String>)>,
) -> Result<Report, LaunchError> {
    let mut local = build(graph, instance, registry, |_| true)?;
    let writer = match record {
        Some((path, edges)) => Some(add_taps(&mut local, graph, instance, path, edges)?),
        None => None,
    };
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
    let mut finals = finals.map_err(|source| LaunchError::InProcess { file: graph.file.clone(), source })?;
    let recording = match writer {
        Some(writer) => {
            let taps: Vec<String> = finals.keys().filter(|name| name.starts_with(TAP)).cloned().collect();
            let counts = taps
                .into_iter()
                .filter_map(|name| finals.remove(&name).map(|beat| (name[TAP.len()..].to_string(), beat.frames_in)))
                .collect();
            let writer = Arc::into_inner(writer).ok_or(LaunchError::Recorder("still in use"))?;
            writer.into_inner().unwrap_or_else(|e| e.into_inner()).finish()?;
            Some(counts)
        }
        None => None,
    };
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
        recording,
    })
}
