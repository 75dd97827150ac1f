//! What the supervisor reports: live status lines and the final summary.

use std::collections::BTreeMap;
use std::time::Duration;

use poseflow_contracts::Heartbeat;
use poseflow_graph::Graph;
use serde_json::json;

#[derive(Debug, Clone, PartialEq)]
pub enum Outcome {
    Running,
    Restarting,
    /// Exited with status 0 and is not to be restarted.
    Finished,
    /// Stopped by the supervisor at shutdown.
    Stopped,
    /// Failed beyond its restart policy.
    Failed(String),
}

impl Outcome {
    fn label(&self) -> &str {
        match self {
            Outcome::Running => "running",
            Outcome::Restarting => "restarting",
            Outcome::Finished => "finished",
            Outcome::Stopped => "stopped",
            Outcome::Failed(_) => "failed",
        }
    }
}

#[derive(Debug, Clone)]
pub struct StageReport {
    pub name: String,
    pub pid: u32,
    pub outcome: Outcome,
    pub restarts: u32,
    pub hangs: u32,
    /// Still running `STOP_GRACE` after SIGTERM at shutdown: SIGKILLed.
    pub killed_at_stop: bool,
    /// From a death being noticed to the replacement being started.
    pub restart_latency_ms: Vec<f64>,
    /// The latest heartbeat of the current process.
    pub heartbeat: Option<Heartbeat>,
    /// Counters of the stage's earlier processes (restarted ones), as their
    /// last heartbeats had them: what a process did after its last
    /// heartbeat is not counted.
    pub earlier: Counters,
}

/// Frame counters summed over processes.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Counters {
    pub frames_in: u64,
    pub frames_out: u64,
    pub dropped: u64,
    pub errors: u64,
}

impl Counters {
    fn of(beat: &Heartbeat) -> Self {
        Self { frames_in: beat.frames_in, frames_out: beat.frames_out, dropped: beat.dropped, errors: beat.errors }
    }

    fn plus(self, other: Self) -> Self {
        Self {
            frames_in: self.frames_in + other.frames_in,
            frames_out: self.frames_out + other.frames_out,
            dropped: self.dropped + other.dropped,
            errors: self.errors + other.errors,
        }
    }
}

impl StageReport {
    pub fn new(name: &str) -> Self {
        Self {
            name: name.to_string(),
            pid: 0,
            outcome: Outcome::Running,
            restarts: 0,
            hangs: 0,
            killed_at_stop: false,
            restart_latency_ms: Vec::new(),
            heartbeat: None,
            earlier: Counters::default(),
        }
    }

    /// Takes a heartbeat; one from a new process first adds the previous
    /// process's last counters to [`Self::earlier`].
    pub fn beat(&mut self, beat: Heartbeat) {
        if let Some(previous) = self.heartbeat.filter(|p| p.pid != beat.pid) {
            self.earlier = self.earlier.plus(Counters::of(&previous));
        }
        self.heartbeat = Some(beat);
    }

    /// Counters over every process of the stage.
    pub fn total(&self) -> Counters {
        self.earlier.plus(self.heartbeat.as_ref().map(Counters::of).unwrap_or_default())
    }

    fn line(&self, width: usize) -> String {
        let beat = self.heartbeat.unwrap_or_default();
        format!(
            "  {:<width$} {:<10} pid {:>7}  in {:>8}  out {:>8}  drop {:>6}  err {:>4}  restarts {:>2}  p50 {:>7} µs  p99 {:>7} µs",
            self.name,
            self.outcome.label(),
            self.pid,
            beat.frames_in,
            beat.frames_out,
            beat.dropped,
            beat.errors,
            self.restarts,
            beat.latency_p50_us,
            beat.latency_p99_us,
        )
    }

    fn to_json(&self) -> serde_json::Value {
        let beat = self.heartbeat.unwrap_or_default();
        let total = self.total();
        json!({
            "outcome": self.outcome.label(),
            "failure": match &self.outcome { Outcome::Failed(why) => Some(why.as_str()), _ => None },
            "restarts": self.restarts,
            "hangs": self.hangs,
            "killed_at_stop": self.killed_at_stop,
            "restart_latency_ms": self.restart_latency_ms,
            "frames_in": beat.frames_in,
            "frames_out": beat.frames_out,
            "dropped": beat.dropped,
            "errors": beat.errors,
            "p50_us": beat.latency_p50_us,
            "p99_us": beat.latency_p99_us,
            "blocked_us": beat.blocked_us,
            "total": {
                "frames_in": total.frames_in,
                "frames_out": total.frames_out,
                "dropped": total.dropped,
                "errors": total.errors,
            },
        })
    }
}

pub fn status_lines<'a>(instance: &str, elapsed: Duration, stages: impl Iterator<Item = &'a StageReport>) -> String {
    let stages: Vec<_> = stages.collect();
    let width = stages.iter().map(|s| s.name.len()).max().unwrap_or(0);
    let mut out = format!("poseflow {instance} [{:.1} s]", elapsed.as_secs_f64());
    for s in stages {
        out.push('\n');
        out.push_str(&s.line(width));
    }
    out
}

/// Messages through one edge whose counts are attributable: its writer
/// has no other output and each reader reads it as its one main input
/// (side inputs are not counted in `frames_in`), so the writer's
/// `frames_out` all went into it and each reader's `frames_in` came from
/// it (totals over restarted processes).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct EdgeFlow {
    pub writer: String,
    pub sent: u64,
    pub received: BTreeMap<String, u64>,
}

impl EdgeFlow {
    /// Sent but not received by the reader that received least: dropped
    /// by a full drop-oldest queue, or lost with a dead process.
    pub fn lost(&self) -> u64 {
        self.received.values().map(|r| self.sent.saturating_sub(*r)).max().unwrap_or(0)
    }
}

/// The attributable edges of `graph` (see [`EdgeFlow`]).
pub fn edge_flows(graph: &Graph, stages: &BTreeMap<String, StageReport>) -> BTreeMap<String, EdgeFlow> {
    let total = |name: &str| stages.get(name).map(StageReport::total).unwrap_or_default();
    graph
        .edges
        .keys()
        .filter_map(|edge| {
            let mut writers = graph.stages.values().filter(|s| s.outputs.iter().any(|o| o == edge));
            let writer = writers.next().filter(|w| w.outputs.len() == 1)?;
            if writers.next().is_some() {
                return None;
            }
            let readers: Vec<_> = graph.stages.values().filter(|s| s.reads(edge)).collect();
            let attributable = !readers.is_empty() && readers.iter().all(|r| r.inputs == [edge.as_str()]);
            attributable.then(|| {
                let received = readers.iter().map(|r| (r.name.clone(), total(&r.name).frames_in)).collect();
                (edge.clone(), EdgeFlow { writer: writer.name.clone(), sent: total(&writer.name).frames_out, received })
            })
        })
        .collect()
}

#[derive(Debug)]
pub struct Report {
    pub graph: String,
    pub instance: String,
    pub elapsed: Duration,
    pub stale_nodes_removed_at_exit: usize,
    pub stages: BTreeMap<String, StageReport>,
    /// Counted flow through the attributable edges.
    pub edges: BTreeMap<String, EdgeFlow>,
    /// Messages recorded per edge, with `--record`.
    pub recording: Option<Vec<(String, u64)>>,
}

impl Report {
    pub fn failed(&self) -> bool {
        self.stages.values().any(|s| matches!(s.outcome, Outcome::Failed(_)))
    }

    pub fn table(&self) -> String {
        status_lines(&self.instance, self.elapsed, self.stages.values())
    }

    pub fn to_json(&self) -> serde_json::Value {
        json!({
            "graph": self.graph,
            "instance": self.instance,
            "elapsed_s": self.elapsed.as_secs_f64(),
            "failed": self.failed(),
            "stale_nodes_removed_at_exit": self.stale_nodes_removed_at_exit,
            "recorded": self.recording.as_ref().map(|edges| edges.iter().cloned().collect::<BTreeMap<_, _>>()),
            "stages": self.stages.iter().map(|(name, s)| (name.clone(), s.to_json())).collect::<serde_json::Map<_, _>>(),
            "edges": self
                .edges
                .iter()
                .map(|(name, e)| {
                    let flow = json!({"writer": e.writer, "sent": e.sent, "received": e.received, "lost": e.lost()});
                    (name.clone(), flow)
                })
                .collect::<serde_json::Map<_, _>>(),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn beat(pid: u32, frames_in: u64, frames_out: u64) -> Heartbeat {
        Heartbeat { pid, frames_in, frames_out, dropped: 1, ..Default::default() }
    }

    #[test]
    fn counters_add_up_over_restarted_processes() {
        let mut report = StageReport::new("relay");
        assert_eq!(report.total(), Counters::default());
        // The first process: later heartbeats replace earlier ones.
        report.beat(beat(10, 5, 5));
        report.beat(beat(10, 300, 299));
        assert_eq!(report.total(), Counters { frames_in: 300, frames_out: 299, dropped: 1, errors: 0 });
        // Its replacement starts from zero; the first one's last counts stay.
        report.beat(beat(11, 20, 20));
        report.beat(beat(11, 1000, 1000));
        assert_eq!(report.earlier, Counters { frames_in: 300, frames_out: 299, dropped: 1, errors: 0 });
        assert_eq!(report.total(), Counters { frames_in: 1300, frames_out: 1299, dropped: 2, errors: 0 });
        assert_eq!(report.to_json()["total"]["frames_out"], 1299);
        assert_eq!(report.to_json()["frames_out"], 1000);
    }

    /// The tracking graph: a reader's side inputs do not count in its
    /// `frames_in`, so an edge read as the main input of a stage with side
    /// inputs is attributable; an edge that someone reads as a side input
    /// is not.
    #[test]
    fn edges_read_as_main_inputs_are_attributable_whatever_the_side_inputs() {
        let file = std::path::Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/../../deploy/tracking.toml"));
        let graph = poseflow_graph::parse_in_process(&std::fs::read_to_string(file).unwrap(), file).unwrap();
        let mut stages = BTreeMap::new();
        for (name, frames_in, frames_out) in
            [("frames", 0, 30), ("ingest", 30, 90), ("inference", 90, 90), ("sampler", 88, 88), ("selector", 88, 88)]
        {
            let mut report = StageReport::new(name);
            report.beat(Heartbeat { pid: 1, frames_in, frames_out, ..Default::default() });
            stages.insert(name.to_string(), report);
        }
        let flows = edge_flows(&graph, &stages);
        assert_eq!(flows.keys().collect::<Vec<_>>(), ["conditions", "frames", "hypotheses"]);
        assert_eq!((flows["conditions"].writer.as_str(), flows["conditions"].lost()), ("inference", 2));
        assert_eq!(flows["hypotheses"].received, BTreeMap::from([("selector".to_string(), 88)]));
        assert_eq!(flows["hypotheses"].lost(), 0);
    }
}
