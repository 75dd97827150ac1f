//! What a stage process is told about its place in the graph.

use serde::{Deserialize, Serialize};

use poseflow_contracts::StampSlot;

use crate::Stamp;
use crate::spec::OverflowPolicy;

/// The environment variable holding a stage's wiring as JSON. Plug-in
/// stages in any language read it to find their services.
pub const WIRING_ENV: &str = "POSEFLOW_STAGE";

/// One edge as seen by one stage.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EdgeWiring {
    /// Edge name in the graph file.
    pub edge: String,
    /// iceoryx2 service name (`poseflow/<instance>/<edge>`).
    pub service: String,
    /// Contract message name (e.g. `Hypotheses`).
    pub message: String,
    pub queue: usize,
    pub overflow: OverflowPolicy,
    pub max_payload_len: usize,
    /// Stages reading this edge (for outputs: receivers to wait for at
    /// start-up).
    pub readers: usize,
}

impl EdgeWiring {
    /// The transport settings of this edge.
    pub fn options(&self) -> poseflow_transport::EdgeOptions {
        poseflow_transport::EdgeOptions {
            queue: self.queue,
            overflow: self.overflow.into(),
            max_payload_len: self.max_payload_len,
        }
    }
}

/// Everything a stage process needs to join its graph.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StageWiring {
    /// Graph instance name: the namespace of all services.
    pub instance: String,
    /// Stage name in the graph file.
    pub stage: String,
    pub inputs: Vec<EdgeWiring>,
    pub outputs: Vec<EdgeWiring>,
    /// Edges read beside the input (absent in wirings of older launchers).
    #[serde(default)]
    pub side_inputs: Vec<EdgeWiring>,
    pub serves: Vec<EdgeWiring>,
    pub calls: Vec<EdgeWiring>,
    /// iceoryx2 service on which the stage publishes its heartbeat.
    pub heartbeat_service: String,
    pub heartbeat_ms: u64,
    /// The stage's parameters (config file merged with inline params).
    pub params: serde_json::Value,
    /// How many processes of this stage ran before this one: 0 at the
    /// graph's start, n after the n-th restart. A restarted stage flags its
    /// first output `UPSTREAM_RESTARTED` so downstream caches are dropped.
    #[serde(default)]
    pub incarnation: u32,
    /// The graph's `stamp` for this stage; see [`Self::stamp_slot`]. Left
    /// out when absent, so stages built before the key read the wiring.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stamp: Option<Stamp>,
}

impl StageWiring {
    /// The timestamp slot the stage writes: the graph's `stamp`, else
    /// `default` (the stage type's own).
    pub fn stamp_slot(&self, default: Option<StampSlot>) -> Option<StampSlot> {
        Stamp::resolve(self.stamp, default)
    }

    pub fn to_json(&self) -> String {
        serde_json::to_string(self).expect("wiring is plain data")
    }

    /// Reads the wiring the launcher put in [`WIRING_ENV`].
    pub fn from_env() -> Result<Self, WiringError> {
        let text = std::env::var(WIRING_ENV).map_err(|_| WiringError::NotSet)?;
        serde_json::from_str(&text).map_err(WiringError::Invalid)
    }
}

/// Why a stage process has no wiring.
#[derive(Debug, thiserror::Error)]
pub enum WiringError {
    #[error("{WIRING_ENV} is not set: stages are started by `poseflow run --graph FILE`")]
    NotSet,

    #[error("{WIRING_ENV}: invalid stage wiring")]
    Invalid(#[source] serde_json::Error),
}
