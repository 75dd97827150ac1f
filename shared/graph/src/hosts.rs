//! Graphs that span machines: which host runs each stage, which edges
//! cross between hosts, and the plan each host's Zenoh bridge follows.
//!
//! A graph names its hosts in `[hosts.<name>]` tables and places every
//! stage on one (`stages.<name>.host`). `poseflow run --host NAME` runs
//! that host's stages plus one bridge process, which carries every edge
//! written on one host and read on another over Zenoh. Without `--host`
//! the same file runs every stage on this machine and no bridge.

use std::collections::{BTreeMap, BTreeSet};

use serde::{Deserialize, Serialize};

use crate::{EdgePattern, Graph, GraphError, Stage, StageWiring};

/// The bridge's stage name in reports and heartbeats; graph stages may not
/// use it when the graph names hosts.
pub const BRIDGE_STAGE: &str = "zenoh-bridge";
/// The bridge's executable, looked up like a stage's.
pub const BRIDGE_EXE: &str = "zenoh-bridge";

/// How a host's bridge joins the Zenoh network.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ZenohMode {
    /// Bridges connect to each other directly (and through a router if one
    /// is named).
    #[default]
    Peer,
    /// Bridges reach each other only through the router.
    Client,
}

/// The graph file's `[zenoh]` table.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct ZenohSettings {
    pub mode: ZenohMode,
    /// Endpoint of a Zenoh router, if the network has one.
    pub router: Option<String>,
    pub multicast_scouting: bool,
    /// Key expression prefix of this graph's traffic.
    pub key_prefix: String,
}

/// A `[hosts.<name>]` table: the Zenoh endpoints of that host's bridge.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct HostEndpoints {
    pub listen: Vec<String>,
    pub connect: Vec<String>,
}

/// What one host's bridge does; it travels to the bridge process as its
/// wiring's `params`. The edges' services and queue settings are the
/// wiring's `inputs` (edges this host sends) and `outputs` (edges it
/// receives).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BridgePlan {
    pub host: String,
    pub zenoh: ZenohSettings,
    pub endpoints: HostEndpoints,
    /// Per sent edge, the hosts that read it: the bridge forwards nothing
    /// on an edge until each of them is ready to receive.
    pub readers: BTreeMap<String, Vec<String>>,
}

/// The transports the bridge is built with.
const ENDPOINT_PROTOCOLS: [&str; 1] = ["tcp"];

/// Checks an endpoint such as `tcp/10.0.0.2:7447`; returns what is wrong.
pub(crate) fn endpoint_problem(endpoint: &str) -> Option<String> {
    let Some((protocol, address)) = endpoint.split_once('/') else {
        return Some(format!("{endpoint:?} has no `<protocol>/` prefix"));
    };
    if !ENDPOINT_PROTOCOLS.contains(&protocol) {
        return Some(format!("{endpoint:?}: the bridge is built with Zenoh's {ENDPOINT_PROTOCOLS:?} transports"));
    }
    match address.rsplit_once(':') {
        Some((host, port)) if !host.is_empty() && port.parse::<u16>().is_ok() => None,
        _ => Some(format!("{endpoint:?}: expected <address>:<port> after `{protocol}/`")),
    }
}

/// Checks a key expression prefix: plain chunks, no wildcards.
pub(crate) fn key_prefix_problem(prefix: &str) -> Option<String> {
    let bad_chunk = prefix.split('/').find(|chunk| {
        chunk.is_empty() || chunk.contains(['*', '$', '?', '#', '@']) || chunk.contains(char::is_whitespace)
    });
    bad_chunk.map(|chunk| format!("{prefix:?} (chunk {chunk:?})"))
}

impl Graph {
    /// Whether the graph places its stages on hosts.
    pub fn spans_hosts(&self) -> bool {
        !self.hosts.is_empty()
    }

    /// The stages `poseflow run --host host` runs; every stage without a host.
    pub fn stages_on<'g>(&'g self, host: Option<&'g str>) -> impl Iterator<Item = &'g Stage> + 'g {
        self.stages.values().filter(move |s| host.is_none() || s.host.as_deref() == host)
    }

    /// The host of the stage that writes (or serves) `edge`.
    fn writer_host(&self, edge: &str) -> Option<&str> {
        self.stages
            .values()
            .find(|s| s.outputs.iter().any(|o| o == edge) || s.serves.iter().any(|o| o == edge))
            .and_then(|s| s.host.as_deref())
    }

    /// Hosts other than `host` with a stage that reads `edge`.
    fn remote_reader_hosts(&self, edge: &str, host: &str) -> BTreeSet<&str> {
        self.stages
            .values()
            .filter(|s| s.reads(edge))
            .filter_map(|s| s.host.as_deref())
            .filter(|h| *h != host)
            .collect()
    }

    /// Edges written on `host` and read on another host.
    pub fn sent_from(&self, host: &str) -> Vec<&str> {
        self.edges
            .keys()
            .filter(|e| self.writer_host(e) == Some(host) && !self.remote_reader_hosts(e, host).is_empty())
            .map(String::as_str)
            .collect()
    }

    /// Edges written on another host and read on `host`.
    pub fn received_on(&self, host: &str) -> Vec<&str> {
        self.edges
            .keys()
            .filter(|e| {
                let writer = self.writer_host(e);
                writer.is_some() && writer != Some(host) && self.stages_on(Some(host)).any(|s| s.reads(e))
            })
            .map(String::as_str)
            .collect()
    }

    /// Edges whose messages exist on `host`: written there or received there.
    pub fn edges_on<'g>(&'g self, host: &'g str) -> Vec<&'g str> {
        let mut edges: Vec<&str> =
            self.stages_on(Some(host)).flat_map(|s| s.outputs.iter().map(String::as_str)).collect();
        edges.extend(self.received_on(host));
        edges.sort_unstable();
        edges.dedup();
        edges
    }

    /// Receivers of `edge` on `host` that its writer waits for: the stages
    /// there that read or call it, plus the bridge when the edge leaves
    /// the host. `None`: every stage runs here.
    pub(crate) fn local_readers(&self, edge: &str, host: Option<&str>) -> usize {
        let stages = self.stages_on(host).filter(|s| s.reads(edge) || s.calls.iter().any(|c| c == edge)).count();
        let bridge = host.is_some_and(|h| self.sent_from(h).contains(&edge));
        stages + usize::from(bridge)
    }

    /// The bridge `poseflow run --host host` starts beside its stages, as a
    /// stage (named [`BRIDGE_STAGE`]) and its wiring; `None` when no edge
    /// crosses to or from `host`.
    pub fn bridge(&self, host: &str, instance: &str) -> Result<Option<(Stage, StageWiring)>, GraphError> {
        let (sent, received) = (self.sent_from(host), self.received_on(host));
        if sent.is_empty() && received.is_empty() {
            return Ok(None);
        }
        let Some(exe) = self.bridge_exe.clone() else {
            return Err(GraphError::Invalid {
                file: self.file.clone(),
                key: "hosts".into(),
                expected: format!("the `{BRIDGE_EXE}` executable for the edges crossing hosts"),
                found: "no bridge executable".into(),
            });
        };
        let plan = BridgePlan {
            host: host.to_string(),
            zenoh: self.zenoh.clone(),
            endpoints: self.hosts.get(host).cloned().unwrap_or_default(),
            readers: sent
                .iter()
                .map(|e| (e.to_string(), self.remote_reader_hosts(e, host).into_iter().map(String::from).collect()))
                .collect(),
        };
        let params = serde_json::to_value(&plan).expect("a bridge plan is plain data");
        let stage = Stage {
            name: BRIDGE_STAGE.to_string(),
            exe,
            args: Vec::new(),
            host: Some(host.to_string()),
            inputs: sent.iter().map(|e| e.to_string()).collect(),
            outputs: received.iter().map(|e| e.to_string()).collect(),
            side_inputs: Vec::new(),
            serves: Vec::new(),
            calls: Vec::new(),
            params,
            stamp: None,
            restart: crate::Restart::default(),
        };
        let wiring = self.wiring_on(&stage, instance, Some(host))?;
        Ok(Some((stage, wiring)))
    }
}

/// The checks a graph that names hosts must pass (after its stages and
/// edges are valid on their own).
pub(crate) fn check_placement(graph: &Graph) -> Result<(), GraphError> {
    let invalid = |key: String, expected: String, found: String| GraphError::Invalid {
        file: graph.file.clone(),
        key,
        expected,
        found,
    };
    let known = || graph.hosts.keys().cloned().collect::<Vec<_>>().join(", ");
    for stage in graph.stages.values() {
        match (&stage.host, graph.spans_hosts()) {
            (Some(host), false) => {
                return Err(invalid(
                    format!("stages.{}.host", stage.name),
                    "a host declared in a [hosts.<name>] table".into(),
                    format!("{host:?}, and the graph declares no hosts"),
                ));
            }
            (Some(host), true) if !graph.hosts.contains_key(host) => {
                return Err(invalid(
                    format!("stages.{}.host", stage.name),
                    format!("one of the graph's hosts ({})", known()),
                    format!("{host:?}"),
                ));
            }
            (None, true) => {
                return Err(invalid(
                    format!("stages.{}.host", stage.name),
                    format!("a host for every stage of a graph that names hosts ({})", known()),
                    "none".into(),
                ));
            }
            _ => {}
        }
        if graph.spans_hosts() && stage.name == BRIDGE_STAGE {
            return Err(invalid(
                format!("stages.{}", stage.name),
                "a stage name other than the bridge's own".into(),
                format!("{BRIDGE_STAGE:?}"),
            ));
        }
    }
    // Request-response is a call per flow step: across a network each Euler
    // step would pay a round trip, and the bridge carries published messages
    // only, so server and callers share a host.
    for edge in graph.edges.values().filter(|e| e.pattern == EdgePattern::RequestResponse) {
        let on = |s: &Stage| format!("{} (host {})", s.name, s.host.as_deref().unwrap_or("-"));
        let server = graph.stages.values().find(|s| s.serves.contains(&edge.name));
        for caller in graph.stages.values().filter(|s| s.calls.contains(&edge.name)) {
            if let Some(server) = server
                && server.host != caller.host
            {
                return Err(invalid(
                    format!("edges.{}", edge.name),
                    "a request-response edge's server and callers on one host (requests are not carried between hosts)"
                        .into(),
                    format!("{} serves it and {} calls it", on(server), on(caller)),
                ));
            }
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn endpoints_need_a_known_protocol_an_address_and_a_port() {
        assert_eq!(endpoint_problem("tcp/10.0.0.2:7447"), None);
        assert_eq!(endpoint_problem("tcp/[::1]:7447"), None);
        assert!(endpoint_problem("10.0.0.2:7447").unwrap().contains("prefix"));
        assert!(endpoint_problem("quic/10.0.0.2:7447").unwrap().contains("tcp"));
        assert!(endpoint_problem("tcp/10.0.0.2").unwrap().contains("port"));
        assert!(endpoint_problem("tcp/10.0.0.2:99999").unwrap().contains("port"));
    }

    #[test]
    fn key_prefixes_are_plain_chunks() {
        assert_eq!(key_prefix_problem("poseflow/estimation"), None);
        assert!(key_prefix_problem("poseflow/*").is_some());
        assert!(key_prefix_problem("poseflow//x").is_some());
        assert!(key_prefix_problem("/poseflow").is_some());
        assert!(key_prefix_problem("").is_some());
    }
}
