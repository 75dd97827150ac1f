//! Graphs that place their stages on hosts: what each host runs, which
//! edges cross, how many readers each writer waits for, and the placements
//! refused before anything starts.

use std::path::{Path, PathBuf};

use poseflow_graph::{BRIDGE_STAGE, BridgePlan, GraphError, ZenohMode, parse, parse_in_process};

const FILE: &str = "/deploy/two-hosts.toml";

/// frames → ingest on `robot`; inference ⇄ sampler → selector (which also
/// reads the observations) on `compute`.
const SPLIT: &str = r#"
[graph]
name = "split"

[zenoh]
mode = "peer"

[hosts.robot]
listen = ["tcp/10.0.0.1:7447"]

[hosts.compute]
connect = ["tcp/10.0.0.1:7447"]

[edges.frames]
message = "Frame"
[edges.observations]
message = "Observation"
[edges.conditions]
message = "Condition"
[edges.velocities]
message = "Velocity"
pattern = "request-response"
[edges.hypotheses]
message = "Hypotheses"
[edges.estimates]
message = "Estimate"

[stages.frames]
exe = "frame-source"
host = "robot"
outputs = ["frames"]
[stages.ingest]
exe = "ingest"
host = "robot"
inputs = ["frames"]
outputs = ["observations"]
[stages.inference]
exe = "inference"
host = "compute"
inputs = ["observations"]
outputs = ["conditions"]
serves = ["velocities"]
[stages.sampler]
exe = "sampler"
host = "compute"
inputs = ["conditions"]
calls = ["velocities"]
outputs = ["hypotheses"]
[stages.selector]
exe = "selector"
host = "compute"
inputs = ["hypotheses"]
side_inputs = ["observations"]
outputs = ["estimates"]
"#;

fn check(text: &str) -> Result<poseflow_graph::Graph, GraphError> {
    parse_in_process(text, Path::new(FILE))
}

fn error(text: &str) -> String {
    check(text).unwrap_err().to_string()
}

#[test]
fn each_host_runs_its_stages_and_its_bridge_carries_the_crossing_edges() {
    let graph = check(SPLIT).unwrap();
    assert!(graph.spans_hosts());
    assert_eq!(graph.zenoh.mode, ZenohMode::Peer);
    assert_eq!(graph.zenoh.key_prefix, "poseflow/split");
    let names = |host| graph.stages_on(Some(host)).map(|s| s.name.as_str()).collect::<Vec<_>>();
    assert_eq!(names("robot"), ["frames", "ingest"]);
    assert_eq!(names("compute"), ["inference", "sampler", "selector"]);
    assert_eq!(graph.stages_on(None).count(), 5);
    assert_eq!(graph.sent_from("robot"), ["observations"]);
    assert!(graph.received_on("robot").is_empty());
    assert_eq!(graph.received_on("compute"), ["observations"]);
    assert!(graph.sent_from("compute").is_empty());
    assert_eq!(graph.edges_on("robot"), ["frames", "observations"]);

    // On the robot, ingest waits for the bridge alone; on one machine, for
    // the inference stage and the selector.
    let ingest = &graph.stages["ingest"];
    assert_eq!(graph.wiring_on(ingest, "r", Some("robot")).unwrap().outputs[0].readers, 1);
    assert_eq!(graph.wiring(ingest, "r").unwrap().outputs[0].readers, 2);

    let (stage, wiring) = graph.bridge("robot", "r").unwrap().unwrap();
    assert_eq!(stage.name, BRIDGE_STAGE);
    assert_eq!(wiring.inputs.iter().map(|e| e.service.as_str()).collect::<Vec<_>>(), ["poseflow/r/observations"]);
    assert!(wiring.outputs.is_empty());
    let plan: BridgePlan = serde_json::from_value(wiring.params).unwrap();
    assert_eq!(plan.readers["observations"], ["compute"]);
    assert_eq!(plan.endpoints.listen, ["tcp/10.0.0.1:7447"]);

    // The compute host's bridge publishes the observations for two readers.
    let (_, wiring) = graph.bridge("compute", "c").unwrap().unwrap();
    assert_eq!(wiring.outputs[0].edge, "observations");
    assert_eq!(wiring.outputs[0].readers, 2);
}

#[test]
fn placements_that_cannot_run_are_refused_with_the_key() {
    // Inference and sampler call each other once per flow step: not across hosts.
    let err = error(&SPLIT.replace("exe = \"sampler\"\nhost = \"compute\"", "exe = \"sampler\"\nhost = \"robot\""));
    assert!(err.contains("`edges.velocities`") && err.contains("inference (host compute) serves it"), "{err}");
    let err = error(&SPLIT.replace("host = \"robot\"\ninputs", "host = \"lab\"\ninputs"));
    assert!(err.contains("`stages.ingest.host`") && err.contains("\"lab\""), "{err}");
    let err = error(&SPLIT.replace("exe = \"selector\"\nhost = \"compute\"\n", "exe = \"selector\"\n"));
    assert!(err.contains("`stages.selector.host`") && err.contains("found none"), "{err}");
    let err = error(&SPLIT.replace("tcp/10.0.0.1:7447\"]\n\n[hosts.compute]", "udp/10.0.0.1\"]\n\n[hosts.compute]"));
    assert!(err.contains("`hosts.robot.listen`"), "{err}");
    let err = error(&SPLIT.replace("mode = \"peer\"", "mode = \"router\""));
    assert!(err.contains("`zenoh.mode`"), "{err}");
    let err = error(&SPLIT.replace("mode = \"peer\"", "mode = \"client\""));
    assert!(err.contains("`zenoh.router`") && err.contains("client mode"), "{err}");
    let err = error(&SPLIT.replace("mode = \"peer\"", "key_prefix = \"poseflow/**\""));
    assert!(err.contains("`zenoh.key_prefix`"), "{err}");
    let err = error(&SPLIT.replace("[stages.frames]", "[stages.zenoh-bridge]"));
    assert!(err.contains("`stages.zenoh-bridge`"), "{err}");
    // A host named by a graph that declares none.
    let single = SPLIT.split("[edges.frames]").nth(1).unwrap();
    let err = error(&format!("[graph]\nname = \"one\"\n[edges.frames]{single}"));
    assert!(err.contains("`stages.") && err.contains("declares no hosts"), "{err}");
}

#[test]
fn a_graph_with_hosts_needs_the_bridge_executable() {
    // Every stage runs `true`, which exists; the bridge does not.
    let text = ["frame-source", "ingest", "inference", "sampler", "selector"]
        .iter()
        .fold(SPLIT.to_string(), |text, exe| text.replace(&format!("exe = \"{exe}\""), "exe = \"true\""));
    let err = parse(&text, Path::new(FILE), &[PathBuf::from("/bin")]).unwrap_err().to_string();
    assert!(err.contains("`hosts`") && err.contains("zenoh-bridge"), "{err}");
}
