//! Recording (`poseflow run --record FILE`): a recorder thread in the launcher that
//! subscribes to chosen edges and writes their messages to a recording.

use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::thread::JoinHandle;
use std::time::Duration;

use iceoryx2::prelude::{CallbackProgression, SignalHandlingMode, WaitSetBuilder};
use poseflow_contracts::stamp_clock_ns;
use poseflow_graph::{EdgePattern, Graph};
use poseflow_runtime::recording::{RecordedEdge, RecordedMessage, RecordingInfo, RecordingWriter};
use poseflow_transport::{
    EdgeOptions, Ipc, TransportError, UntypedSubscriber, create_node, edge_service_name, untyped_subscriber,
};

use crate::LaunchError;

/// How often the recorder checks whether it should stop.
const STOP_POLL: Duration = Duration::from_millis(50);

/// One recorded edge, whatever its message type, and how many of its
/// messages were written.
#[derive(Debug)]
struct RecordedInput {
    edge: String,
    subscriber: Box<dyn UntypedSubscriber>,
    recorded: std::cell::Cell<u64>,
}

impl RecordedInput {
    /// Writes every queued message; returns whether END_OF_STREAM was seen.
    fn drain(&self, writer: &mut RecordingWriter) -> Result<bool, LaunchError> {
        let ended = self.subscriber.take_events()?;
        loop {
            let mut written = Ok(());
            let received = self.subscriber.receive_with(&mut |header, payload| {
                written = writer.write(&RecordedMessage {
                    edge: self.edge.clone(),
                    received_ns: stamp_clock_ns(),
                    header: header.to_vec(),
                    payload: payload.to_vec(),
                });
            })?;
            written?;
            if !received {
                return Ok(ended);
            }
            self.recorded.set(self.recorded.get() + 1);
        }
    }
}

/// What a recording of `edges` of `graph` says about itself.
pub(crate) fn recording_info(graph: &Graph, instance: &str, edges: &[String]) -> RecordingInfo {
    RecordingInfo {
        graph: graph.name.clone(),
        instance: instance.to_string(),
        edges: edges
            .iter()
            .map(|e| RecordedEdge { edge: e.clone(), message: graph.edges[e].message.clone() })
            .collect(),
    }
}

/// A running recorder; [`Recorder::finish`] stops it and reports counts.
#[derive(Debug)]
pub struct Recorder {
    stop: Arc<AtomicBool>,
    handle: JoinHandle<Result<Vec<(String, u64)>, LaunchError>>,
}

/// The edges `--record-edges` names, or every publish-subscribe edge.
pub fn chosen_edges(graph: &Graph, requested: &[String]) -> Result<Vec<String>, LaunchError> {
    if requested.is_empty() {
        return Ok(graph
            .edges
            .values()
            .filter(|e| e.pattern == EdgePattern::PublishSubscribe)
            .map(|e| e.name.clone())
            .collect());
    }
    for edge in requested {
        match graph.edges.get(edge) {
            Some(e) if e.pattern == EdgePattern::PublishSubscribe => {}
            Some(_) => return Err(LaunchError::RecordRequestResponse { edge: edge.clone() }),
            None => {
                return Err(LaunchError::RecordUnknownEdge {
                    edge: edge.clone(),
                    file: graph.file.clone(),
                    edges: graph.edges.keys().cloned().collect(),
                });
            }
        }
    }
    Ok(requested.to_vec())
}

impl Recorder {
    /// Subscribes to `edges` and starts writing `path`. Returns once the
    /// subscriptions exist, so the stages started next are all recorded.
    pub fn start(graph: &Graph, instance: &str, edges: &[String], path: PathBuf) -> Result<Self, LaunchError> {
        let info = recording_info(graph, instance, edges);
        let specs: Vec<(String, String, EdgeOptions)> = edges
            .iter()
            .map(|name| {
                let edge = &graph.edges[name];
                let options = edge.options();
                Ok((name.clone(), edge_service_name(instance, name)?, options))
            })
            .collect::<Result<_, LaunchError>>()?;
        let stop = Arc::new(AtomicBool::new(false));
        let (ready_tx, ready_rx) = std::sync::mpsc::channel();
        let handle = std::thread::spawn({
            let stop = stop.clone();
            move || -> Result<Vec<(String, u64)>, LaunchError> {
                let node = create_node("poseflow-recorder")?;
                let mut inputs = Vec::new();
                for (edge, service, options) in &specs {
                    let message = &info.edges.iter().find(|e| &e.edge == edge).expect("listed").message;
                    let subscriber = untyped_subscriber(&node, message, service, options).map_err(|err| match err {
                        TransportError::UnknownMessage { .. } => {
                            LaunchError::UnknownMessage { edge: edge.clone(), message: message.clone() }
                        }
                        other => other.into(),
                    })?;
                    inputs.push(RecordedInput { edge: edge.clone(), subscriber, recorded: Default::default() });
                }
                let mut writer = RecordingWriter::create(&path, &info)?;
                let _ = ready_tx.send(());
                record(&inputs, &mut writer, &stop)?;
                writer.finish()?;
                Ok(inputs.iter().map(|input| (input.edge.clone(), input.recorded.get())).collect())
            }
        });
        if ready_rx.recv().is_err() {
            // The thread ended before it was ready: report why.
            return Err(handle
                .join()
                .map_err(|_| LaunchError::Recorder("panicked"))?
                .err()
                .unwrap_or(LaunchError::Recorder("stopped before it was ready")));
        }
        Ok(Self { stop, handle })
    }

    /// Stops recording (after what is queued) and returns the number of
    /// messages written per edge.
    pub fn finish(self) -> Result<Vec<(String, u64)>, LaunchError> {
        self.stop.store(true, Ordering::Relaxed);
        self.handle.join().map_err(|_| LaunchError::Recorder("panicked"))?
    }
}

fn record(inputs: &[RecordedInput], writer: &mut RecordingWriter, stop: &AtomicBool) -> Result<(), LaunchError> {
    // SIGINT/SIGTERM belong to the supervisor's loop; this WaitSet must not
    // consume them.
    let waitset = WaitSetBuilder::new()
        .signal_handling_mode(SignalHandlingMode::Disabled)
        .create::<Ipc>()
        .map_err(waitset_error)?;
    let guards = inputs
        .iter()
        .map(|input| waitset.attach_notification(input.subscriber.as_ref()).map_err(waitset_error))
        .collect::<Result<Vec<_>, _>>()?;
    let tick = waitset.attach_interval(STOP_POLL).map_err(waitset_error)?;
    let mut ended = vec![false; inputs.len()];
    let mut failure = None;
    waitset
        .wait_and_process(|id| {
            for (i, guard) in guards.iter().enumerate() {
                if id.has_event_from(guard) {
                    let step = inputs[i].drain(writer).and_then(|end| {
                        if end && !ended[i] {
                            ended[i] = true;
                            inputs[i].subscriber.acknowledge_end()?;
                        }
                        Ok(())
                    });
                    if let Err(err) = step {
                        failure = Some(err);
                        return CallbackProgression::Stop;
                    }
                }
            }
            if id.has_event_from(&tick) && stop.load(Ordering::Relaxed) {
                return CallbackProgression::Stop;
            }
            if ended.iter().all(|e| *e) { CallbackProgression::Stop } else { CallbackProgression::Continue }
        })
        .map_err(waitset_error)?;
    if let Some(err) = failure {
        return Err(err);
    }
    // What arrived between the last wake-up and the stop.
    for input in inputs {
        input.drain(writer)?;
    }
    Ok(())
}

fn waitset_error(err: impl std::error::Error + Send + Sync + 'static) -> LaunchError {
    LaunchError::WaitSet(Box::new(err))
}
