//! The file schema, exactly as written by users. Unknown keys are errors.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct GraphFile {
    pub graph: GraphSection,
    #[serde(default)]
    pub edges: BTreeMap<String, EdgeSpec>,
    pub stages: BTreeMap<String, StageSpec>,
    /// How the graph's hosts reach each other, when its stages span hosts.
    #[serde(default)]
    pub zenoh: ZenohSpec,
    /// The machines the stages are placed on (`stages.<name>.host`).
    #[serde(default)]
    pub hosts: BTreeMap<String, HostSpec>,
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct ZenohSpec {
    /// `peer` (default) or `client`.
    pub mode: Option<String>,
    /// A Zenoh router every host connects to (required in client mode).
    pub router: Option<String>,
    /// Find the other hosts by UDP multicast too (off by default: robot
    /// networks often block it, and the endpoints are explicit).
    #[serde(default)]
    pub multicast_scouting: bool,
    /// The key expression under which the graph's edges travel; default
    /// `poseflow/<graph name>`.
    pub key_prefix: Option<String>,
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct HostSpec {
    /// Zenoh endpoints this host's bridge listens on (`tcp/10.0.0.2:7447`).
    #[serde(default)]
    pub listen: Vec<String>,
    /// Zenoh endpoints this host's bridge connects to.
    #[serde(default)]
    pub connect: Vec<String>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct GraphSection {
    pub name: String,
    #[serde(default)]
    pub description: String,
    /// How often each stage publishes its heartbeat.
    #[serde(default = "default_heartbeat_ms")]
    pub heartbeat_ms: u64,
    /// A stage busy in one message this long, or without a first
    /// heartbeat this long after it started, is considered hung and is
    /// restarted.
    #[serde(default = "default_heartbeat_timeout_ms")]
    pub heartbeat_timeout_ms: u64,
    /// A stage whose heartbeats stop this long after they started is
    /// frozen (stopped, or every thread deadlocked) and is restarted;
    /// default 5 × `heartbeat_ms`.
    pub silence_timeout_ms: Option<u64>,
}

fn default_heartbeat_ms() -> u64 {
    200
}

fn default_heartbeat_timeout_ms() -> u64 {
    3000
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum EdgePattern {
    PublishSubscribe,
    RequestResponse,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum OverflowPolicy {
    /// A full queue replaces its oldest message (fresh data wins).
    DropOldest,
    /// The publisher waits for room (nothing is lost; upstream slows down).
    Block,
}

impl From<OverflowPolicy> for poseflow_transport::Overflow {
    fn from(policy: OverflowPolicy) -> Self {
        match policy {
            OverflowPolicy::DropOldest => Self::DropOldest,
            OverflowPolicy::Block => Self::Block,
        }
    }
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct EdgeSpec {
    pub message: String,
    #[serde(default = "default_pattern")]
    pub pattern: EdgePattern,
    #[serde(default = "default_queue")]
    pub queue: usize,
    #[serde(default = "default_overflow")]
    pub overflow: OverflowPolicy,
    /// Largest payload in f32 values; its shared memory is reserved up front.
    #[serde(default = "default_max_payload")]
    pub max_payload_len: usize,
}

fn default_pattern() -> EdgePattern {
    EdgePattern::PublishSubscribe
}
fn default_queue() -> usize {
    4
}
fn default_overflow() -> OverflowPolicy {
    OverflowPolicy::DropOldest
}
fn default_max_payload() -> usize {
    4096
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum RestartPolicy {
    Never,
    OnFailure,
    Always,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct StageSpec {
    pub exe: String,
    /// The host (a `[hosts.<name>]` table) whose `poseflow run --host`
    /// runs this stage.
    pub host: Option<String>,
    #[serde(default)]
    pub args: Vec<String>,
    #[serde(default)]
    pub inputs: Vec<String>,
    #[serde(default)]
    pub outputs: Vec<String>,
    /// Edges read beside the input, whose messages the stage keeps for
    /// later (the selector keeps each Observation until its Hypotheses
    /// come; a tracking sampler keeps the last Estimate). Never waited on,
    /// so one may close a loop.
    #[serde(default)]
    pub side_inputs: Vec<String>,
    /// Request-response edges this stage answers.
    #[serde(default)]
    pub serves: Vec<String>,
    /// Request-response edges this stage calls.
    #[serde(default)]
    pub calls: Vec<String>,
    /// The timestamp slot the stage writes (`Stamp::parse`); absent: its
    /// registration's default.
    pub stamp: Option<String>,
    /// A TOML file of parameters, relative to the graph file.
    pub config: Option<String>,
    /// Inline parameters; they override the config file's.
    #[serde(default)]
    pub params: toml::Table,
    #[serde(default = "default_restart")]
    pub restart: RestartPolicy,
    #[serde(default = "default_backoff_ms")]
    pub backoff_ms: u64,
    #[serde(default = "default_max_backoff_ms")]
    pub max_backoff_ms: u64,
    #[serde(default = "default_max_restarts")]
    pub max_restarts: u32,
}

fn default_restart() -> RestartPolicy {
    RestartPolicy::OnFailure
}
fn default_backoff_ms() -> u64 {
    100
}
fn default_max_backoff_ms() -> u64 {
    5000
}
fn default_max_restarts() -> u32 {
    10
}
