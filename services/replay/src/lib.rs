//! The replay source: plays one edge of a recording (`poseflow run
//! --record`) back into a graph, so a stage can be developed and benchmarked
//! against a real stream without the stages upstream of it.
//!
//! Parameters: `file` (the recording, required), `edge` (which recorded
//! edge; may be omitted when the recording holds one), `speed` (`"recorded"`,
//! the default, keeps the recorded inter-arrival times; `"max"` sends as
//! fast as the output accepts). The output edge's message type must be the
//! recorded edge's. Headers are replayed byte for byte, stamps included.

use std::marker::PhantomData;
use std::path::PathBuf;
use std::time::{Duration, Instant};

use poseflow_contracts::{MessageHeader, StampSlot};
use poseflow_graph::StageWiring;
use poseflow_runtime::recording::{RecordingError, RecordingReader, header_from_bytes};
use poseflow_runtime::{Emitter, Source, SourceStep};

#[derive(Debug, thiserror::Error)]
pub enum ReplayError {
    #[error(transparent)]
    Recording(#[from] RecordingError),
    #[error("{file}: message {index} of edge `{edge}`: header of {found} bytes, {message} headers have {expected}")]
    HeaderSize { file: PathBuf, index: u64, edge: String, message: &'static str, found: usize, expected: usize },
    #[error(transparent)]
    Emit(#[from] poseflow_runtime::EmitError),
    #[error("param `{key}`: expected {expected}, got {found}")]
    Param { key: &'static str, expected: String, found: String },
    #[error("{file}: edge `{edge}` carries {recorded}, the output edge carries {expected}")]
    MessageMismatch { file: PathBuf, edge: String, recorded: String, expected: &'static str },
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Speed {
    Recorded,
    Max,
}

#[derive(Debug)]
pub struct ReplaySource<H> {
    file: PathBuf,
    reader: RecordingReader,
    edge: String,
    speed: Speed,
    /// Recorded time and wall time of the first message replayed.
    origin: Option<(u64, Instant)>,
    replayed: u64,
    _message: PhantomData<fn() -> H>,
}

impl<H: MessageHeader> ReplaySource<H> {
    pub fn from_wiring(wiring: &StageWiring) -> Result<Self, ReplayError> {
        let params = &wiring.params;
        let file = PathBuf::from(params.get("file").and_then(|v| v.as_str()).ok_or_else(|| ReplayError::Param {
            key: "file",
            expected: "the path of a recording".into(),
            found: params.get("file").map_or("nothing".into(), ToString::to_string),
        })?);
        let reader = RecordingReader::open(&file)?;
        let edges = &reader.info.edges;
        let names = || format!("{:?}", edges.iter().map(|e| &e.edge).collect::<Vec<_>>());
        let recorded = match params.get("edge").and_then(|v| v.as_str()) {
            Some(name) => edges.iter().find(|e| e.edge == name).ok_or_else(|| ReplayError::Param {
                key: "edge",
                expected: format!("an edge of {} (it holds {})", file.display(), names()),
                found: format!("{name:?}"),
            })?,
            None if edges.len() == 1 => &edges[0],
            None => {
                return Err(ReplayError::Param {
                    key: "edge",
                    expected: format!("one of the edges {} holds ({}); it holds several", file.display(), names()),
                    found: "nothing".into(),
                });
            }
        };
        if recorded.message != H::NAME {
            return Err(ReplayError::MessageMismatch {
                file: file.clone(),
                edge: recorded.edge.clone(),
                recorded: recorded.message.clone(),
                expected: H::NAME,
            });
        }
        let speed = match params.get("speed").and_then(|v| v.as_str()) {
            None | Some("recorded") => Speed::Recorded,
            Some("max") => Speed::Max,
            Some(other) => {
                return Err(ReplayError::Param {
                    key: "speed",
                    expected: "\"recorded\" or \"max\"".into(),
                    found: format!("{other:?}"),
                });
            }
        };
        let edge = recorded.edge.clone();
        Ok(Self { file, reader, edge, speed, origin: None, replayed: 0, _message: PhantomData })
    }
}

impl<H: MessageHeader> Source for ReplaySource<H> {
    type Out = H;
    type Error = ReplayError;
    /// Recorded stamps are kept as they were.
    const SLOT: Option<StampSlot> = None;

    fn next(&mut self, output: &mut dyn Emitter<H>) -> Result<SourceStep, ReplayError> {
        let message = loop {
            match self.reader.next_message()? {
                None => {
                    tracing::info!(replayed = self.replayed, file = %self.file.display(), "recording finished");
                    return Ok(SourceStep::Finished);
                }
                Some(m) if m.edge == self.edge => break m,
                Some(_) => continue,
            }
        };
        let header = header_from_bytes::<H>(&message.header).ok_or_else(|| ReplayError::HeaderSize {
            file: self.file.clone(),
            index: self.replayed,
            edge: self.edge.clone(),
            message: H::NAME,
            found: message.header.len(),
            expected: std::mem::size_of::<H>(),
        })?;
        if self.speed == Speed::Recorded {
            let (recorded_origin, wall_origin) = *self.origin.get_or_insert((message.received_ns, Instant::now()));
            let due = wall_origin + Duration::from_nanos(message.received_ns.saturating_sub(recorded_origin));
            // Pacing a replay to its recorded timing; not on any data path.
            std::thread::sleep(due.saturating_duration_since(Instant::now()));
        }
        let payload = message.payload;
        output.emit(header, payload.len(), &mut |out| out.copy_from_slice(&payload))?;
        self.replayed += 1;
        Ok(SourceStep::Continue)
    }
}

/// The stage of this crate: `replay-source`, which replays a recording's
/// messages of the output edge's message type.
pub fn registrations() -> Vec<poseflow_runtime::Registration> {
    use poseflow_contracts::{MessageHeader, MessageVisitor, visit_message};
    use poseflow_runtime::Registration;

    struct Typed;
    impl MessageVisitor for Typed {
        type Output = Registration;
        fn visit<H: MessageHeader + Send + 'static>(self) -> Registration {
            Registration::source("replay-source", ReplaySource::<H>::from_wiring)
        }
    }
    vec![Registration::source_of_any_message("replay-source", |message| visit_message(message, Typed))]
}
