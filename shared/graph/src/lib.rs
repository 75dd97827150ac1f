//! Graph files (`deploy/*.toml`): which stages run, which executable runs
//! each, how they are connected, and how they are restarted.
//!
//! [`load`] parses and validates a file before anything starts; every error
//! names the file, the key and what was expected. The launcher then hands
//! each stage process its [`StageWiring`] (service names, queue settings,
//! parameters) in the environment variable [`WIRING_ENV`].

mod error;
mod graph;
mod hosts;
mod overrides;
mod resolve;
mod spec;
mod stamp;
mod wiring;
mod write;

pub use error::GraphError;
pub use graph::{Edge, Graph, Restart, Stage, load, parse, parse_in_process};
pub use hosts::{BRIDGE_EXE, BRIDGE_STAGE, BridgePlan, HostEndpoints, ZenohMode, ZenohSettings};
pub use resolve::resolve_executable;
pub use spec::{EdgePattern, OverflowPolicy, RestartPolicy};
pub use stamp::Stamp;
pub use wiring::{EdgeWiring, StageWiring, WIRING_ENV, WiringError};

/// Message types an edge may carry, as named in graph files (defined with
/// the contracts).
pub use poseflow_contracts::{PUBLISH_SUBSCRIBE_MESSAGES, REQUEST_RESPONSE_MESSAGES};
