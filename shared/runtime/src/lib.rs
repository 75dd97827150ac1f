//! The stage runtime.
//!
//! A stage is a library implementing [`Transform`], [`Server`], [`Joined`], [`Source`] or [`Sink`]:
//! plain functions from messages to messages. This crate runs it as a
//! process of a graph ([`run_transform`], [`run_server`], [`run_joined`], [`run_source`], [`run_sink`]):
//! it reads the stage's wiring from the environment, connects to its
//! iceoryx2 services, sleeps in a WaitSet until data or a timer wakes it,
//! validates every message against its contract, stamps per-stage
//! timestamps, counts drops and errors, publishes a heartbeat, propagates
//! end-of-stream, and exits cleanly on SIGINT/SIGTERM.

mod call;
mod error;
mod heartbeat;
mod liveness;
mod local;
mod logging;
mod process;
pub mod progress;
pub mod recording;
mod registry;
mod stage;
pub mod timing;

pub use call::{Call, CallError, connect};
pub use error::{BuildError, RuntimeError, error_chain};
pub use heartbeat::ProcessHeartbeat;
pub use local::{Collector, DriveError, Feed, LocalGraph, LocalGraphError, LocalOverflow, LocalReport, RunningGraph};
pub use logging::init_logging;
pub use process::{run_joined, run_server, run_sink, run_source, run_transform, run_transform_or_joined};
pub use registry::{Registration, Registry, StageKind, run_registered};
pub use stage::{EmitError, Emitter, Flush, FrameBatches, Input, Joined, Server, Sink, Source, SourceStep, Transform};
