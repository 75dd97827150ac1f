use std::path::PathBuf;

use poseflow_graph::GraphError;
use poseflow_runtime::RuntimeError;
use poseflow_runtime::recording::RecordingError;
use poseflow_transport::TransportError;

/// Why a graph could not be launched or had to be stopped.
#[derive(Debug, thiserror::Error)]
pub enum LaunchError {
    #[error(transparent)]
    Graph(#[from] GraphError),

    #[error(transparent)]
    Transport(#[from] TransportError),

    #[error("stage `{stage}`: cannot start {}", exe.display())]
    Spawn {
        stage: String,
        exe: PathBuf,
        #[source]
        source: std::io::Error,
    },

    #[error("stage `{stage}`: cannot learn whether it exited")]
    Wait {
        stage: String,
        #[source]
        source: std::io::Error,
    },

    #[error("{}: cannot create the stage log", path.display())]
    StageLog {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },

    #[error("the launcher's iceoryx2 waitset")]
    WaitSet(#[source] Box<dyn std::error::Error + Send + Sync>),

    #[error(transparent)]
    Recording(#[from] RecordingError),

    #[error("--record-edges: `{edge}` is a request-response edge; only publish-subscribe edges are recorded")]
    RecordRequestResponse { edge: String },

    #[error("--record-edges: `{edge}` is not an edge of {} (edges: {edges:?})", file.display())]
    RecordUnknownEdge { edge: String, file: PathBuf, edges: Vec<String> },

    #[error("--host {host}: {} names no such host (its hosts: {hosts:?})", file.display())]
    UnknownHost { file: PathBuf, host: String, hosts: Vec<String> },

    #[error(
        "--host runs one host's stages as processes beside its Zenoh bridge; --in-process runs a whole graph on one machine"
    )]
    HostInProcess,

    #[error("--record-edges: `{edge}` is neither written nor read on host `{host}`; record it on a host that has it")]
    RecordElsewhere { edge: String, host: String },

    #[error("edge `{edge}`: message type `{message}` is not a contract message")]
    UnknownMessage { edge: String, message: String },

    #[error(
        "{}: stages `{first}` and `{second}` both write timestamp slot `{slot}` on one path, so one overwrites \
         the other's stamp; give one of them another `stamp` (or \"none\")",
        file.display()
    )]
    StampClash { file: PathBuf, slot: &'static str, first: String, second: String },

    #[error("the launcher thread panicked")]
    LauncherPanicked,

    #[error("the recorder thread {0}")]
    Recorder(&'static str),

    #[error(
        "{}: `stages.{stage}.exe`: {exe:?} cannot run in-process; the stages that can: {available}",
        file.display()
    )]
    NotInProcess { file: PathBuf, stage: String, exe: String, available: String },

    #[error("{}: in-process run", file.display())]
    InProcess {
        file: PathBuf,
        #[source]
        source: RuntimeError,
    },

    #[error("{}: stage `{stage}`", file.display())]
    Stage {
        file: PathBuf,
        stage: String,
        #[source]
        source: RuntimeError,
    },

    #[error("{}: edge `{edge}`: expected a publish-subscribe edge of {expected} messages, found {found}", file.display())]
    DrivenEdge { file: PathBuf, edge: String, expected: &'static str, found: String },

    #[error("{}: driven in-process", file.display())]
    Driven {
        file: PathBuf,
        #[source]
        source: Box<poseflow_runtime::DriveError>,
    },
}
