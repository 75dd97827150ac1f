//! A graph's stages in this process, driven one message at a time: what a
//! simulation, a planner or the in-process benchmark baseline runs. The
//! stages are built by the same registrations as in any other launch.

use std::collections::{BTreeSet, VecDeque};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::Duration;

use poseflow_contracts::MessageHeader;
use poseflow_graph::{EdgePattern, Graph};
use poseflow_runtime::{Collector, DriveError, Feed, LocalReport, Registry, RunningGraph};

use crate::LaunchError;

/// How long one message may take through the whole graph before the
/// graph counts as stuck (a first message also waits for the stages to
/// load their models).
const SETTLE_TIMEOUT: Duration = Duration::from_secs(600);

/// The stages between `input` and `output`: every stage `output` depends
/// on (through inputs, side inputs and request-response calls), except the
/// publisher of `input`, which the caller replaces.
pub fn stages_between(graph: &Graph, input: &str, output: &str) -> BTreeSet<String> {
    let publisher_of = |edge: &str| {
        graph.stages.values().find(|s| s.outputs.iter().any(|e| e == edge) || s.serves.iter().any(|e| e == edge))
    };
    let mut kept = BTreeSet::new();
    let mut edges: VecDeque<String> = VecDeque::from([output.to_string()]);
    while let Some(edge) = edges.pop_front() {
        if edge == input {
            continue;
        }
        let Some(stage) = publisher_of(&edge) else { continue };
        if kept.insert(stage.name.clone()) {
            edges.extend(stage.inputs.iter().chain(&stage.side_inputs).chain(&stage.calls).cloned());
        }
    }
    kept
}

/// A unique instance name per driven graph of this process: in-process
/// request-response services are found by name.
fn driven_instance(graph: &Graph) -> String {
    static NEXT: AtomicU64 = AtomicU64::new(0);
    let name: String = graph.name.chars().take(32).collect();
    format!("{name}-{}-d{}", std::process::id(), NEXT.fetch_add(1, Ordering::Relaxed))
}

/// The stages of a graph between an input edge (`I` messages, fed by the
/// caller) and an output edge (`O` messages, returned to the caller), as
/// threads of this process.
pub struct DrivenGraph<I, O> {
    file: std::path::PathBuf,
    feed: Option<Feed<I>>,
    collected: Collector<O>,
    running: Option<RunningGraph>,
}

impl<I, O> std::fmt::Debug for DrivenGraph<I, O> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("DrivenGraph").field("file", &self.file).finish()
    }
}

impl<I, O> DrivenGraph<I, O>
where
    I: MessageHeader + Send + 'static,
    O: MessageHeader + Send + 'static,
{
    /// Starts [`stages_between`] `input` and `output` of `graph` and waits
    /// until each is built. Both edges must be publish-subscribe edges of
    /// the graph carrying `I` and `O`.
    pub fn start(graph: &Graph, registry: &Registry, input: &str, output: &str) -> Result<Self, LaunchError> {
        for (edge, message) in [(input, I::NAME), (output, O::NAME)] {
            match graph.edges.get(edge) {
                Some(e) if e.message == message && e.pattern == EdgePattern::PublishSubscribe => {}
                found => {
                    return Err(LaunchError::DrivenEdge {
                        file: graph.file.clone(),
                        edge: edge.to_string(),
                        expected: message,
                        found: found.map_or("no such edge".to_string(), |e| format!("{} ({:?})", e.message, e.pattern)),
                    });
                }
            }
        }
        let kept = stages_between(graph, input, output);
        let instance = driven_instance(graph);
        let mut local = crate::local::build(graph, &instance, registry, |stage| kept.contains(&stage.name))?;
        let in_process = |source: poseflow_runtime::LocalGraphError| LaunchError::InProcess {
            file: graph.file.clone(),
            source: source.into(),
        };
        let feed = local.feed::<I>(input).map_err(in_process)?;
        let collected = local.collect::<O>(output).map_err(in_process)?;
        tracing::debug!(graph = %graph.name, %instance, stages = ?kept, "driven graph starting");
        let mut running = local.start(Arc::new(AtomicBool::new(false)));
        running
            .wait_built(SETTLE_TIMEOUT)
            .map_err(|source| LaunchError::Driven { file: graph.file.clone(), source: Box::new(source) })?;
        Ok(Self { file: graph.file.clone(), feed: Some(feed), collected, running: Some(running) })
    }

    fn running(&mut self) -> &mut RunningGraph {
        self.running.as_mut().expect("a driven graph runs until finished")
    }

    /// Sends one message and returns every output it caused, once the
    /// graph has handled it completely (none, when a stage dropped or
    /// rejected it: see [`Self::counters`]).
    pub fn process(&mut self, header: I, payload: Vec<f32>) -> Result<Vec<(O, Vec<f32>)>, LaunchError> {
        let driven =
            |file: &std::path::Path, source| LaunchError::Driven { file: file.to_path_buf(), source: Box::new(source) };
        let feed = self.feed.as_ref().expect("a driven graph keeps its feed until finished");
        feed.send(header, payload).map_err(|source| driven(&self.file, source))?;
        self.running().settle(SETTLE_TIMEOUT).map_err(|source: DriveError| driven(&self.file, source))?;
        Ok(self.collected.drain())
    }

    /// Every stage's counters now (messages in and out, errors, rejects).
    pub fn counters(&self) -> LocalReport {
        self.running.as_ref().map(RunningGraph::counters).unwrap_or_default()
    }

    /// Ends the input stream, waits for the stages to finish and returns
    /// their final counters.
    pub fn finish(mut self) -> Result<LocalReport, LaunchError> {
        drop(self.feed.take());
        let running = self.running.take().expect("a driven graph runs until finished");
        running.finish().map_err(|source| LaunchError::InProcess { file: self.file.clone(), source })
    }
}
