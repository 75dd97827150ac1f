//! The graph types ([`Graph`], [`Edge`], [`Stage`]) and the checks that turn
//! a parsed file into a graph known to be runnable.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::time::Duration;

use crate::hosts::{
    BRIDGE_EXE, HostEndpoints, ZenohMode, ZenohSettings, check_placement, endpoint_problem, key_prefix_problem,
};
use crate::spec::{EdgePattern, EdgeSpec, GraphFile, HostSpec, OverflowPolicy, RestartPolicy, StageSpec, ZenohSpec};
use crate::stamp::Stamp;
use crate::wiring::{EdgeWiring, StageWiring};
use crate::{GraphError, PUBLISH_SUBSCRIBE_MESSAGES, REQUEST_RESPONSE_MESSAGES, resolve_executable};

/// Heartbeat periods a started process may miss before it counts as
/// frozen: one late beat on a loaded machine is not a hang.
const SILENT_HEARTBEATS: u64 = 5;

/// A validated graph.
#[derive(Debug, Clone)]
pub struct Graph {
    pub file: PathBuf,
    pub name: String,
    pub description: String,
    pub heartbeat: Duration,
    /// Longest time a process may be busy in one message, or take to send
    /// its first heartbeat.
    pub heartbeat_timeout: Duration,
    /// Longest gap between heartbeats once they started. The heartbeat
    /// thread beats whatever the stage's own code does, so only a frozen
    /// process falls silent: it gets a deadline of a few periods instead of
    /// the busy deadline.
    pub silence_timeout: Duration,
    pub edges: BTreeMap<String, Edge>,
    pub stages: BTreeMap<String, Stage>,
    /// How hosts reach each other (used only when `hosts` is not empty).
    pub zenoh: ZenohSettings,
    /// The machines the stages are placed on; empty: one machine.
    pub hosts: BTreeMap<String, HostEndpoints>,
    /// The bridge executable that carries edges between hosts, found when
    /// the graph names hosts.
    pub bridge_exe: Option<PathBuf>,
}

#[derive(Debug, Clone, PartialEq)]
pub struct Edge {
    pub name: String,
    pub message: String,
    pub pattern: EdgePattern,
    pub queue: usize,
    pub overflow: OverflowPolicy,
    pub max_payload_len: usize,
}

#[derive(Debug, Clone, PartialEq)]
pub struct Restart {
    pub policy: RestartPolicy,
    /// Delay before the first restart; doubles after each, up to `max_backoff`.
    pub backoff: Duration,
    pub max_backoff: Duration,
    /// Restarts allowed before the stage counts as failed for good.
    pub max_restarts: u32,
}

impl Default for Restart {
    /// The graph file's defaults.
    fn default() -> Self {
        Self {
            policy: RestartPolicy::OnFailure,
            backoff: Duration::from_millis(100),
            max_backoff: Duration::from_millis(5000),
            max_restarts: 10,
        }
    }
}

#[derive(Debug, Clone, PartialEq)]
pub struct Stage {
    pub name: String,
    pub exe: PathBuf,
    pub args: Vec<String>,
    /// The host that runs it, in a graph that names hosts.
    pub host: Option<String>,
    pub inputs: Vec<String>,
    pub outputs: Vec<String>,
    /// Read beside the input, never waited on (see the graph file's
    /// `side_inputs`); exempt from the cycle check.
    pub side_inputs: Vec<String>,
    pub serves: Vec<String>,
    pub calls: Vec<String>,
    pub params: serde_json::Value,
    /// The timestamp slot it writes; `None`: its registration's default.
    pub stamp: Option<Stamp>,
    pub restart: Restart,
}

impl Stage {
    /// Whether the stage subscribes to `edge` (as its input or a side input).
    pub fn reads(&self, edge: &str) -> bool {
        self.inputs.iter().chain(&self.side_inputs).any(|e| e == edge)
    }

    /// The executable's file name: what a stage registry knows it by.
    pub fn exe_name(&self) -> &str {
        self.exe.file_name().and_then(|n| n.to_str()).unwrap_or_default()
    }
}

/// Reads and validates a graph file. `search_path` is where bare executable
/// names are looked up before `PATH`.
pub fn load(file: &Path, search_path: &[PathBuf]) -> Result<Graph, GraphError> {
    let text = std::fs::read_to_string(file).map_err(|source| GraphError::Read { file: file.to_path_buf(), source })?;
    parse(&text, file, search_path)
}

/// Validates file contents; `file` names the source in errors and anchors
/// relative paths.
pub fn parse(text: &str, file: &Path, search_path: &[PathBuf]) -> Result<Graph, GraphError> {
    let spec: GraphFile = toml::from_str(text)
        .map_err(|e| GraphError::Syntax { file: file.to_path_buf(), message: e.to_string().trim_end().to_string() })?;
    Checker { file, resolve_exes: true }.graph(spec, search_path)
}

/// Validates file contents for an in-process launch, where stages are
/// found by executable name in a stage registry: `exe` names are kept as
/// written, not looked up on disk.
pub fn parse_in_process(text: &str, file: &Path) -> Result<Graph, GraphError> {
    let spec: GraphFile = toml::from_str(text)
        .map_err(|e| GraphError::Syntax { file: file.to_path_buf(), message: e.to_string().trim_end().to_string() })?;
    Checker { file, resolve_exes: false }.graph(spec, &[])
}

struct Checker<'a> {
    file: &'a Path,
    resolve_exes: bool,
}

impl Checker<'_> {
    fn invalid(&self, key: impl Into<String>, expected: impl Into<String>, found: impl Into<String>) -> GraphError {
        GraphError::Invalid {
            file: self.file.to_path_buf(),
            key: key.into(),
            expected: expected.into(),
            found: found.into(),
        }
    }

    fn name(&self, key: &str, kind: &'static str, name: &str) -> Result<(), GraphError> {
        poseflow_transport::validate_name(kind, name)
            .map_err(|_| self.invalid(key, "1-64 characters of A-Z, a-z, 0-9, '-' or '_'", format!("{name:?}")))
    }

    fn graph(&self, spec: GraphFile, search_path: &[PathBuf]) -> Result<Graph, GraphError> {
        self.name("graph.name", "graph", &spec.graph.name)?;
        if spec.graph.heartbeat_ms < 10 {
            return Err(self.invalid(
                "graph.heartbeat_ms",
                "at least 10 (milliseconds)",
                spec.graph.heartbeat_ms.to_string(),
            ));
        }
        if spec.graph.heartbeat_timeout_ms <= spec.graph.heartbeat_ms {
            return Err(self.invalid(
                "graph.heartbeat_timeout_ms",
                format!("more than graph.heartbeat_ms ({})", spec.graph.heartbeat_ms),
                spec.graph.heartbeat_timeout_ms.to_string(),
            ));
        }
        let silence_timeout_ms = spec.graph.silence_timeout_ms.unwrap_or(SILENT_HEARTBEATS * spec.graph.heartbeat_ms);
        if silence_timeout_ms <= spec.graph.heartbeat_ms {
            return Err(self.invalid(
                "graph.silence_timeout_ms",
                format!("more than graph.heartbeat_ms ({})", spec.graph.heartbeat_ms),
                silence_timeout_ms.to_string(),
            ));
        }
        if spec.stages.is_empty() {
            return Err(self.invalid("stages", "at least one [stages.<name>] table", "none"));
        }
        let edges = spec
            .edges
            .into_iter()
            .map(|(name, edge)| Ok((name.clone(), self.edge(name, edge)?)))
            .collect::<Result<BTreeMap<_, _>, GraphError>>()?;
        let graph_dir = self.file.parent().unwrap_or(Path::new("."));
        let stages = spec
            .stages
            .into_iter()
            .map(|(name, stage)| Ok((name.clone(), self.stage(name, stage, graph_dir, search_path, &edges)?)))
            .collect::<Result<BTreeMap<_, _>, GraphError>>()?;
        self.connections(&edges, &stages)?;
        self.acyclic(&stages)?;
        let zenoh = self.zenoh(spec.zenoh, &spec.graph.name)?;
        let hosts = spec
            .hosts
            .into_iter()
            .map(|(name, host)| Ok((name.clone(), self.host(name, host)?)))
            .collect::<Result<BTreeMap<_, _>, GraphError>>()?;
        let bridge_exe = match (hosts.is_empty(), self.resolve_exes) {
            (true, _) => None,
            (false, false) => Some(PathBuf::from(BRIDGE_EXE)),
            (false, true) => Some(resolve_executable(BRIDGE_EXE, graph_dir, search_path).map_err(|searched| {
                let places: Vec<String> = searched.iter().map(|p| p.display().to_string()).collect();
                self.invalid(
                    "hosts",
                    format!(
                        "the `{BRIDGE_EXE}` executable, which carries edges between hosts; looked in: {}",
                        places.join(", ")
                    ),
                    "none",
                )
            })?),
        };
        let graph = Graph {
            file: self.file.to_path_buf(),
            name: spec.graph.name,
            description: spec.graph.description,
            heartbeat: Duration::from_millis(spec.graph.heartbeat_ms),
            heartbeat_timeout: Duration::from_millis(spec.graph.heartbeat_timeout_ms),
            silence_timeout: Duration::from_millis(silence_timeout_ms),
            edges,
            stages,
            zenoh,
            hosts,
            bridge_exe,
        };
        check_placement(&graph)?;
        Ok(graph)
    }

    fn zenoh(&self, spec: ZenohSpec, graph_name: &str) -> Result<ZenohSettings, GraphError> {
        let mode = match spec.mode.as_deref() {
            None | Some("peer") => ZenohMode::Peer,
            Some("client") => ZenohMode::Client,
            Some(other) => return Err(self.invalid("zenoh.mode", "\"peer\" or \"client\"", format!("{other:?}"))),
        };
        if let Some(problem) = spec.router.as_deref().and_then(endpoint_problem) {
            return Err(self.invalid("zenoh.router", "a Zenoh endpoint such as \"tcp/10.0.0.1:7447\"", problem));
        }
        if mode == ZenohMode::Client && spec.router.is_none() {
            return Err(self.invalid("zenoh.router", "a router endpoint in client mode", "none"));
        }
        let key_prefix = spec.key_prefix.unwrap_or_else(|| format!("poseflow/{graph_name}"));
        if let Some(problem) = key_prefix_problem(&key_prefix) {
            return Err(self.invalid("zenoh.key_prefix", "chunks separated by '/', without wildcards", problem));
        }
        Ok(ZenohSettings { mode, router: spec.router, multicast_scouting: spec.multicast_scouting, key_prefix })
    }

    fn host(&self, name: String, spec: HostSpec) -> Result<HostEndpoints, GraphError> {
        let key = format!("hosts.{name}");
        self.name(&key, "host", &name)?;
        for (field, endpoints) in [("listen", &spec.listen), ("connect", &spec.connect)] {
            if let Some(problem) = endpoints.iter().find_map(|e| endpoint_problem(e)) {
                return Err(self.invalid(
                    format!("{key}.{field}"),
                    "Zenoh endpoints such as \"tcp/10.0.0.1:7447\"",
                    problem,
                ));
            }
        }
        Ok(HostEndpoints { listen: spec.listen, connect: spec.connect })
    }

    fn edge(&self, name: String, spec: EdgeSpec) -> Result<Edge, GraphError> {
        let key = format!("edges.{name}");
        self.name(&key, "edge", &name)?;
        let known: &[&str] = match spec.pattern {
            EdgePattern::PublishSubscribe => &PUBLISH_SUBSCRIBE_MESSAGES,
            EdgePattern::RequestResponse => &REQUEST_RESPONSE_MESSAGES,
        };
        if !known.contains(&spec.message.as_str()) {
            return Err(self.invalid(
                format!("{key}.message"),
                format!("one of {known:?} for this pattern"),
                format!("{:?}", spec.message),
            ));
        }
        if !(1..=1024).contains(&spec.queue) {
            return Err(self.invalid(format!("{key}.queue"), "1..=1024 messages", spec.queue.to_string()));
        }
        if !(1..=(1 << 26)).contains(&spec.max_payload_len) {
            return Err(self.invalid(
                format!("{key}.max_payload_len"),
                "1..=67108864 f32 values",
                spec.max_payload_len.to_string(),
            ));
        }
        Ok(Edge {
            name,
            message: spec.message,
            pattern: spec.pattern,
            queue: spec.queue,
            overflow: spec.overflow,
            max_payload_len: spec.max_payload_len,
        })
    }

    fn stage(
        &self,
        name: String,
        spec: StageSpec,
        graph_dir: &Path,
        search_path: &[PathBuf],
        edges: &BTreeMap<String, Edge>,
    ) -> Result<Stage, GraphError> {
        let key = format!("stages.{name}");
        self.name(&key, "stage", &name)?;
        let resolved = match self.resolve_exes {
            true => resolve_executable(&spec.exe, graph_dir, search_path),
            false => Ok(PathBuf::from(&spec.exe)),
        };
        let exe = resolved.map_err(|searched| {
            let places: Vec<String> = searched.iter().map(|p| p.display().to_string()).collect();
            self.invalid(
                format!("{key}.exe"),
                format!("an executable file; looked in: {}", places.join(", ")),
                format!("{:?}", spec.exe),
            )
        })?;
        for (field, list, pattern) in [
            ("inputs", &spec.inputs, EdgePattern::PublishSubscribe),
            ("outputs", &spec.outputs, EdgePattern::PublishSubscribe),
            ("side_inputs", &spec.side_inputs, EdgePattern::PublishSubscribe),
            ("serves", &spec.serves, EdgePattern::RequestResponse),
            ("calls", &spec.calls, EdgePattern::RequestResponse),
        ] {
            let mut seen = BTreeSet::new();
            for edge in list {
                let field_key = format!("{key}.{field}");
                match edges.get(edge) {
                    None => {
                        return Err(self.invalid(
                            field_key,
                            "edges declared in an [edges.<name>] table",
                            format!("{edge:?}"),
                        ));
                    }
                    Some(e) if e.pattern != pattern => {
                        return Err(self.invalid(
                            field_key,
                            format!("{pattern:?} edges only"),
                            format!("{edge:?}, a {:?} edge", e.pattern),
                        ));
                    }
                    Some(_) if !seen.insert(edge) => {
                        return Err(self.invalid(field_key, "each edge once", format!("{edge:?} twice")));
                    }
                    Some(_) => {}
                }
            }
        }
        if let Some(edge) = spec.side_inputs.iter().find(|e| spec.inputs.contains(e) || spec.outputs.contains(e)) {
            return Err(self.invalid(
                format!("{key}.side_inputs"),
                "edges that are not also the stage's inputs or outputs",
                format!("{edge:?}"),
            ));
        }
        let stamp = match spec.stamp.as_deref() {
            None => None,
            Some(text) => Some(
                Stamp::parse(text)
                    .ok_or_else(|| self.invalid(format!("{key}.stamp"), Stamp::expected(), format!("{text:?}")))?,
            ),
        };
        let params = self.params(&key, spec.config.as_deref(), spec.params, graph_dir)?;
        if spec.backoff_ms == 0 || spec.max_backoff_ms < spec.backoff_ms {
            return Err(self.invalid(
                format!("{key}.backoff_ms"),
                "1 <= backoff_ms <= max_backoff_ms",
                format!("backoff_ms = {}, max_backoff_ms = {}", spec.backoff_ms, spec.max_backoff_ms),
            ));
        }
        Ok(Stage {
            name,
            exe,
            args: spec.args,
            host: spec.host,
            inputs: spec.inputs,
            outputs: spec.outputs,
            side_inputs: spec.side_inputs,
            serves: spec.serves,
            calls: spec.calls,
            params,
            stamp,
            restart: Restart {
                policy: spec.restart,
                backoff: Duration::from_millis(spec.backoff_ms),
                max_backoff: Duration::from_millis(spec.max_backoff_ms),
                max_restarts: spec.max_restarts,
            },
        })
    }

    /// The config file's table with the inline `params` laid over it.
    fn params(
        &self,
        key: &str,
        config: Option<&str>,
        inline: toml::Table,
        graph_dir: &Path,
    ) -> Result<serde_json::Value, GraphError> {
        let mut merged = match config {
            None => toml::Table::new(),
            Some(relative) => {
                let path = graph_dir.join(relative);
                let text = std::fs::read_to_string(&path).map_err(|e| {
                    self.invalid(
                        format!("{key}.config"),
                        "a readable TOML file, relative to the graph file",
                        format!("{} ({e})", path.display()),
                    )
                })?;
                toml::from_str::<toml::Table>(&text).map_err(|e| {
                    self.invalid(
                        format!("{key}.config"),
                        "a TOML table of parameters",
                        format!("{}: {}", path.display(), e.to_string().trim_end()),
                    )
                })?
            }
        };
        merged.extend(inline);
        serde_json::to_value(&merged)
            .map_err(|e| self.invalid(format!("{key}.params"), "parameters representable as JSON", e.to_string()))
    }

    fn connections(&self, edges: &BTreeMap<String, Edge>, stages: &BTreeMap<String, Stage>) -> Result<(), GraphError> {
        for edge in edges.values() {
            let (producers, consumers): (Vec<&str>, Vec<&str>) = match edge.pattern {
                EdgePattern::PublishSubscribe => (
                    stages.values().filter(|s| s.outputs.contains(&edge.name)).map(|s| s.name.as_str()).collect(),
                    stages.values().filter(|s| s.reads(&edge.name)).map(|s| s.name.as_str()).collect(),
                ),
                EdgePattern::RequestResponse => (
                    stages.values().filter(|s| s.serves.contains(&edge.name)).map(|s| s.name.as_str()).collect(),
                    stages.values().filter(|s| s.calls.contains(&edge.name)).map(|s| s.name.as_str()).collect(),
                ),
            };
            let (produce, consume) = match edge.pattern {
                EdgePattern::PublishSubscribe => ("outputs", "inputs"),
                EdgePattern::RequestResponse => ("serves", "calls"),
            };
            match (producers.as_slice(), consumers.as_slice()) {
                ([], []) => {
                    return Err(self.invalid(
                        format!("edges.{}", edge.name),
                        "an edge some stage uses",
                        "no stage lists it",
                    ));
                }
                ([], [consumer, ..]) => {
                    return Err(self.invalid(
                        format!("stages.{consumer}.{consume}"),
                        format!("an edge listed in some stage's `{produce}` (unconnected input)"),
                        format!("{:?}, which no stage produces", edge.name),
                    ));
                }
                ([_, _, ..], _) => {
                    return Err(self.invalid(
                        format!("edges.{}", edge.name),
                        format!("exactly one stage listing it in `{produce}`"),
                        format!("{producers:?}"),
                    ));
                }
                _ => {}
            }
        }
        Ok(())
    }

    /// Publish-subscribe edges must form a DAG; request-response edges (the
    /// sampler ⇄ inference velocity loop) are calls, not data flow, and are
    /// exempt.
    fn acyclic(&self, stages: &BTreeMap<String, Stage>) -> Result<(), GraphError> {
        let downstream = |stage: &Stage| -> Vec<&str> {
            stages
                .values()
                .filter(|other| other.inputs.iter().any(|e| stage.outputs.contains(e)))
                .map(|s| s.name.as_str())
                .collect()
        };
        #[derive(Clone, Copy, PartialEq)]
        enum Mark {
            Unvisited,
            OnPath,
            Done,
        }
        let mut marks: BTreeMap<&str, Mark> = stages.keys().map(|k| (k.as_str(), Mark::Unvisited)).collect();
        fn visit<'a>(
            name: &'a str,
            path: &mut Vec<&'a str>,
            marks: &mut BTreeMap<&'a str, Mark>,
            stages: &'a BTreeMap<String, Stage>,
            downstream: &dyn Fn(&'a Stage) -> Vec<&'a str>,
        ) -> Option<Vec<&'a str>> {
            marks.insert(name, Mark::OnPath);
            path.push(name);
            for next in downstream(&stages[name]) {
                match marks[next] {
                    Mark::OnPath => {
                        let start = path.iter().position(|n| *n == next).unwrap_or(0);
                        let mut cycle = path[start..].to_vec();
                        cycle.push(next);
                        return Some(cycle);
                    }
                    Mark::Unvisited => {
                        if let Some(cycle) = visit(next, path, marks, stages, downstream) {
                            return Some(cycle);
                        }
                    }
                    Mark::Done => {}
                }
            }
            path.pop();
            marks.insert(name, Mark::Done);
            None
        }
        for name in stages.keys() {
            if marks[name.as_str()] != Mark::Unvisited {
                continue;
            }
            if let Some(cycle) = visit(name, &mut Vec::new(), &mut marks, stages, &downstream) {
                return Err(self.invalid(
                    "stages",
                    "publish-subscribe edges without cycles (only request-response edges, such as sampler <-> inference, may loop)",
                    format!("the cycle {}", cycle.join(" -> ")),
                ));
            }
        }
        Ok(())
    }
}

impl Edge {
    /// The transport settings of this edge.
    pub fn options(&self) -> poseflow_transport::EdgeOptions {
        poseflow_transport::EdgeOptions {
            queue: self.queue,
            overflow: self.overflow.into(),
            max_payload_len: self.max_payload_len,
        }
    }
}

impl Graph {
    /// The wiring handed to `stage` when the whole graph runs on this
    /// machine as `instance`.
    pub fn wiring(&self, stage: &Stage, instance: &str) -> Result<StageWiring, GraphError> {
        self.wiring_on(stage, instance, None)
    }

    /// The wiring handed to `stage` when `poseflow run --host host` runs
    /// its part of the graph (`None`: every stage here): outputs wait for
    /// the readers on this host only.
    pub fn wiring_on(&self, stage: &Stage, instance: &str, host: Option<&str>) -> Result<StageWiring, GraphError> {
        let invalid_instance = |_| GraphError::Invalid {
            file: self.file.clone(),
            key: "--instance".to_string(),
            expected: "1-64 characters of A-Z, a-z, 0-9, '-' or '_'".to_string(),
            found: format!("{instance:?}"),
        };
        let wire = |names: &[String]| -> Result<Vec<EdgeWiring>, GraphError> {
            names
                .iter()
                .map(|name| {
                    let edge = &self.edges[name];
                    Ok(EdgeWiring {
                        edge: name.clone(),
                        service: poseflow_transport::edge_service_name(instance, name).map_err(invalid_instance)?,
                        message: edge.message.clone(),
                        queue: edge.queue,
                        overflow: edge.overflow,
                        max_payload_len: edge.max_payload_len,
                        readers: self.local_readers(name, host),
                    })
                })
                .collect()
        };
        Ok(StageWiring {
            instance: instance.to_string(),
            stage: stage.name.clone(),
            inputs: wire(&stage.inputs)?,
            outputs: wire(&stage.outputs)?,
            side_inputs: wire(&stage.side_inputs)?,
            serves: wire(&stage.serves)?,
            calls: wire(&stage.calls)?,
            heartbeat_service: poseflow_transport::heartbeat_service_name(instance, &stage.name)
                .map_err(invalid_instance)?,
            heartbeat_ms: self.heartbeat.as_millis() as u64,
            params: stage.params.clone(),
            stamp: stage.stamp,
            incarnation: 0,
        })
    }
}
