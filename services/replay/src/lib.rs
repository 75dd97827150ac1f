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

use poseflow_contracts::{MessageHeader, Stage};
use poseflow_graph::StageWiring;
use poseflow_runtime::recording::{RecordingError, RecordingReader, header_from_bytes};
use poseflow_runtime::{Emitter, Source, SourceStep};

#[derive(Debug, thiserror::Error)]
pub enum ReplayError {
    #[error(transparent)]
    Recording(#[from] RecordingError),
    #[error("{file}: message {index} of edge `{edge}`: header of {found} bytes, {message} headers have {expected}")]
    HeaderSize { file: PathBuf, index: u64, edge: String, message: &'static str, found: usize, expected: usize },
    #[error("{0}")]
    Emit(#[from] poseflow_runtime::EmitError),
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
    pub fn from_wiring(wiring: &StageWiring) -> Result<Self, String> {
        let params = &wiring.params;
        let file = PathBuf::from(
            params.get("file").and_then(|v| v.as_str()).ok_or("param `file`: expected the path of a recording")?,
        );
        let reader = RecordingReader::open(&file).map_err(|e| e.to_string())?;
        let edges = &reader.info.edges;
        let recorded = match params.get("edge").and_then(|v| v.as_str()) {
            Some(name) => edges.iter().find(|e| e.edge == name).ok_or_else(|| {
                format!(
                    "param `edge`: {name:?} is not in {} (it holds {:?})",
                    file.display(),
                    edges.iter().map(|e| &e.edge).collect::<Vec<_>>()
                )
            })?,
            None if edges.len() == 1 => &edges[0],
            None => {
                return Err(format!(
                    "param `edge`: {} holds several edges {:?}; name one",
                    file.display(),
                    edges.iter().map(|e| &e.edge).collect::<Vec<_>>()
                ));
            }
        };
        if recorded.message != H::NAME {
            return Err(format!(
                "{}: edge `{}` carries {}, the output edge carries {}",
                file.display(),
                recorded.edge,
                recorded.message,
                H::NAME
            ));
        }
        let speed = match params.get("speed").and_then(|v| v.as_str()) {
            None | Some("recorded") => Speed::Recorded,
            Some("max") => Speed::Max,
            Some(other) => return Err(format!("param `speed`: expected \"recorded\" or \"max\", got {other:?}")),
        };
        let edge = recorded.edge.clone();
        Ok(Self { file, reader, edge, speed, origin: None, replayed: 0, _message: PhantomData })
    }
}

impl<H: MessageHeader> Source for ReplaySource<H> {
    type Out = H;
    type Error = ReplayError;
    /// Recorded stamps are kept as they were.
    const SLOT: Option<Stage> = None;

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
