//! Recordings of graph traffic: the messages of chosen edges with the time
//! they were received, so a stage can be developed and benchmarked against
//! a real stream without the stages upstream of it.
//!
//! # File format (version 3)
//!
//! ```text
//! "POSEFLOW-REC"  12 bytes magic
//! version         u32 little-endian (3: Condition/v2, Hypotheses/v2, Estimate/v3 headers)
//! frames          each: u64 little-endian length, then that many bytes of
//!                 bincode 2 (standard config, serde): first a
//!                 RecordingInfo, then one RecordedMessage per message
//! ```
//!
//! A message's header is stored as the raw bytes of its `#[repr(C)]`
//! contract header, so the recording is exact and type-agnostic; the
//! version changes with any contract layout change.

use std::io::{BufReader, BufWriter, Read, Write};
use std::path::{Path, PathBuf};

/// Recordings store headers as raw bytes (re-exported for their readers).
pub use poseflow_contracts::{header_bytes, header_from_bytes};
use serde::{Deserialize, Serialize};

pub const MAGIC: &[u8; 12] = b"POSEFLOW-REC";
pub const VERSION: u32 = 3;
/// A frame larger than this is a corrupt file, not a message.
const MAX_FRAME_BYTES: u64 = 1 << 30;

#[derive(Debug, thiserror::Error)]
pub enum RecordingError {
    #[error("{path}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{path}: {detail}")]
    Format { path: PathBuf, detail: String },
}

/// What the recording holds.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RecordingInfo {
    pub graph: String,
    pub instance: String,
    pub edges: Vec<RecordedEdge>,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RecordedEdge {
    pub edge: String,
    /// Contract message name (e.g. `Observation`).
    pub message: String,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RecordedMessage {
    pub edge: String,
    /// When the recorder received it, on the stamps' clock
    /// ([`poseflow_contracts::stamp_clock_ns`]).
    pub received_ns: u64,
    /// Raw bytes of the contract header.
    pub header: Vec<u8>,
    pub payload: Vec<f32>,
}

fn config() -> bincode::config::Configuration {
    bincode::config::standard()
}

#[derive(Debug)]
pub struct RecordingWriter {
    path: PathBuf,
    out: BufWriter<std::fs::File>,
}

impl RecordingWriter {
    pub fn create(path: &Path, info: &RecordingInfo) -> Result<Self, RecordingError> {
        let io = |source| RecordingError::Io { path: path.to_path_buf(), source };
        let mut out = BufWriter::new(std::fs::File::create(path).map_err(io)?);
        out.write_all(MAGIC).map_err(io)?;
        out.write_all(&VERSION.to_le_bytes()).map_err(io)?;
        let mut writer = Self { path: path.to_path_buf(), out };
        writer.frame(info)?;
        Ok(writer)
    }

    pub fn write(&mut self, message: &RecordedMessage) -> Result<(), RecordingError> {
        self.frame(message)
    }

    fn frame<T: Serialize>(&mut self, value: &T) -> Result<(), RecordingError> {
        let bytes = bincode::serde::encode_to_vec(value, config())
            .map_err(|e| RecordingError::Format { path: self.path.clone(), detail: e.to_string() })?;
        let io = |source| RecordingError::Io { path: self.path.clone(), source };
        self.out.write_all(&(bytes.len() as u64).to_le_bytes()).map_err(io)?;
        self.out.write_all(&bytes).map_err(io)
    }

    pub fn finish(mut self) -> Result<(), RecordingError> {
        self.out.flush().map_err(|source| RecordingError::Io { path: self.path.clone(), source })
    }
}

#[derive(Debug)]
pub struct RecordingReader {
    path: PathBuf,
    input: BufReader<std::fs::File>,
    pub info: RecordingInfo,
}

impl RecordingReader {
    pub fn open(path: &Path) -> Result<Self, RecordingError> {
        let format = |detail: String| RecordingError::Format { path: path.to_path_buf(), detail };
        let file =
            std::fs::File::open(path).map_err(|source| RecordingError::Io { path: path.to_path_buf(), source })?;
        let mut input = BufReader::new(file);
        let mut magic = [0u8; 12];
        let mut version = [0u8; 4];
        if input.read_exact(&mut magic).is_err() || &magic != MAGIC {
            return Err(format("not a PoseFlow recording (expected the magic bytes \"POSEFLOW-REC\")".into()));
        }
        input.read_exact(&mut version).map_err(|_| format("truncated after the magic bytes".into()))?;
        let version = u32::from_le_bytes(version);
        if version != VERSION {
            return Err(format(format!("recording format version {version}, this build reads version {VERSION}")));
        }
        let mut reader = Self {
            path: path.to_path_buf(),
            input,
            info: RecordingInfo { graph: String::new(), instance: String::new(), edges: Vec::new() },
        };
        reader.info = reader.frame()?.ok_or_else(|| format("no recording info after the header".into()))?;
        Ok(reader)
    }

    /// The next recorded message, `None` at the end of the file.
    pub fn next_message(&mut self) -> Result<Option<RecordedMessage>, RecordingError> {
        self.frame()
    }

    fn frame<T: serde::de::DeserializeOwned>(&mut self) -> Result<Option<T>, RecordingError> {
        let format = |detail: String| RecordingError::Format { path: self.path.clone(), detail };
        let mut len = [0u8; 8];
        match self.input.read_exact(&mut len) {
            Ok(()) => {}
            Err(e) if e.kind() == std::io::ErrorKind::UnexpectedEof => return Ok(None),
            Err(source) => return Err(RecordingError::Io { path: self.path.clone(), source }),
        }
        let len = u64::from_le_bytes(len);
        if len > MAX_FRAME_BYTES {
            return Err(format(format!("frame of {len} bytes exceeds the limit of {MAX_FRAME_BYTES}: corrupt file")));
        }
        let mut bytes = vec![0u8; len as usize];
        self.input.read_exact(&mut bytes).map_err(|_| format(format!("truncated frame of {len} bytes")))?;
        bincode::serde::decode_from_slice(&bytes, config()).map(|(v, _)| Some(v)).map_err(|e| format(e.to_string()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use poseflow_contracts::{Header, HypothesesHeader};

    #[test]
    fn messages_round_trip_exactly() {
        let path = std::env::temp_dir().join(format!("poseflow-rec-test-{}.rec", std::process::id()));
        let info = RecordingInfo {
            graph: "g".into(),
            instance: "i".into(),
            edges: vec![RecordedEdge { edge: "e".into(), message: "Hypotheses".into() }],
        };
        let header =
            HypothesesHeader { header: Header::new(42, 7), sample_count: 1, step_count: 5, ..Default::default() };
        let message = RecordedMessage {
            edge: "e".into(),
            received_ns: 123,
            header: header_bytes(&header),
            payload: (0..12).map(|i| i as f32 * 0.5).collect(),
        };
        let mut writer = RecordingWriter::create(&path, &info).unwrap();
        writer.write(&message).unwrap();
        writer.finish().unwrap();

        let mut reader = RecordingReader::open(&path).unwrap();
        assert_eq!(reader.info, info);
        let back = reader.next_message().unwrap().unwrap();
        assert_eq!(back, message);
        assert_eq!(header_from_bytes::<HypothesesHeader>(&back.header), Some(header));
        assert!(header_from_bytes::<HypothesesHeader>(&back.header[1..]).is_none());
        assert!(reader.next_message().unwrap().is_none());

        // Truncation and foreign files are named errors, not panics.
        let bytes = std::fs::read(&path).unwrap();
        std::fs::write(&path, &bytes[..bytes.len() - 3]).unwrap();
        let mut reader = RecordingReader::open(&path).unwrap();
        assert!(reader.next_message().unwrap_err().to_string().contains("truncated"));
        std::fs::write(&path, b"PNG....").unwrap();
        assert!(RecordingReader::open(&path).unwrap_err().to_string().contains("not a PoseFlow recording"));
        std::fs::remove_file(&path).unwrap();
    }
}
