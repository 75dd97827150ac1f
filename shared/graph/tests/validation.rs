//! Graph files are rejected before anything starts, with the file, the key
//! and the expectation in the message.

use std::path::{Path, PathBuf};

use poseflow_graph::{GraphError, StageWiring, parse};

const FILE: &str = "/deploy/test.toml";

fn check(text: &str) -> Result<poseflow_graph::Graph, GraphError> {
    parse(text, Path::new(FILE), &[PathBuf::from("/bin"), PathBuf::from("/usr/bin")])
}

fn error(text: &str) -> String {
    check(text).unwrap_err().to_string()
}

const CHAIN: &str = r#"
[graph]
name = "chain"

[edges.raw]
message = "Hypotheses"
queue = 8

[edges.out]
message = "Estimate"
overflow = "block"

[stages.source]
exe = "true"
outputs = ["raw"]

[stages.middle]
exe = "/bin/true"
inputs = ["raw"]
outputs = ["out"]
params = { factor = 2 }
restart = "always"

[stages.sink]
exe = "true"
inputs = ["out"]
restart = "never"
"#;

#[test]
fn a_valid_chain_loads_with_defaults() {
    let graph = check(CHAIN).unwrap();
    assert_eq!(graph.stages.len(), 3);
    assert_eq!(graph.edges["raw"].queue, 8);
    assert_eq!(graph.edges["out"].queue, 4);
    assert_eq!(graph.stages["source"].exe, Path::new("/bin/true"));
    assert_eq!(graph.stages["middle"].params["factor"], 2);
    let wiring = graph.wiring(&graph.stages["middle"], "g7").unwrap();
    assert_eq!(wiring.inputs[0].service, "poseflow/g7/raw");
    assert_eq!(wiring.heartbeat_service, "poseflow/g7/_heartbeat/middle");
    let back: StageWiring = serde_json::from_str(&wiring.to_json()).unwrap();
    assert_eq!(back, wiring);
    assert!(graph.wiring(&graph.stages["middle"], "bad/instance").is_err());
}

#[test]
fn unknown_keys_are_named() {
    let err = error(&CHAIN.replace("restart = \"never\"", "restart = \"never\"\nretsart = 3"));
    assert!(err.starts_with(FILE) && err.contains("retsart"), "{err}");
    let err = error(&CHAIN.replace("queue = 8", "queue = 8\nqueue_size = 3"));
    assert!(err.contains("queue_size"), "{err}");
}

#[test]
fn bad_values_name_key_and_expectation() {
    let err = error(&CHAIN.replace("restart = \"always\"", "restart = \"sometimes\""));
    assert!(err.contains("sometimes"), "{err}");
    let err = error(&CHAIN.replace("queue = 8", "queue = 0"));
    assert!(err.contains("`edges.raw.queue`") && err.contains("1..=1024"), "{err}");
    let err = error(&CHAIN.replace("message = \"Estimate\"", "message = \"Pose\""));
    assert!(err.contains("`edges.out.message`") && err.contains("\"Pose\""), "{err}");
    let err = error(&CHAIN.replace("name = \"chain\"", "name = \"my graph\""));
    assert!(err.contains("`graph.name`"), "{err}");
}

/// A frozen process is told from a busy one by its silent heartbeats: a
/// deadline of its own, 5 periods unless set, and more than one period.
#[test]
fn the_silence_deadline_defaults_to_five_heartbeats_and_is_checked() {
    use std::time::Duration;
    let graph = check(&CHAIN.replace("name = \"chain\"", "name = \"chain\"\nheartbeat_ms = 150")).unwrap();
    assert_eq!((graph.heartbeat, graph.silence_timeout), (Duration::from_millis(150), Duration::from_millis(750)));
    assert_eq!(graph.heartbeat_timeout, Duration::from_millis(3000));
    let set = CHAIN.replace("name = \"chain\"", "name = \"chain\"\nsilence_timeout_ms = 1200");
    assert_eq!(check(&set).unwrap().silence_timeout, Duration::from_millis(1200));
    let err = error(&CHAIN.replace("name = \"chain\"", "name = \"chain\"\nsilence_timeout_ms = 200"));
    assert!(err.contains("`graph.silence_timeout_ms`") && err.contains("more than graph.heartbeat_ms (200)"), "{err}");
}

#[test]
fn missing_executables_list_where_they_were_sought() {
    let err = error(&CHAIN.replace("exe = \"/bin/true\"", "exe = \"no-such-stage-binary\""));
    assert!(err.contains("`stages.middle.exe`") && err.contains("/bin/no-such-stage-binary"), "{err}");
    let err = error(&CHAIN.replace("exe = \"/bin/true\"", "exe = \"./missing.py\""));
    assert!(err.contains("/deploy/./missing.py"), "{err}");
}

#[test]
fn unconnected_inputs_and_undeclared_edges() {
    let err = error(&CHAIN.replace("outputs = [\"raw\"]", "outputs = []"));
    assert!(err.contains("`stages.middle.inputs`") && err.contains("unconnected input"), "{err}");
    let err = error(&CHAIN.replace("inputs = [\"out\"]", "inputs = [\"result\"]"));
    assert!(err.contains("`stages.sink.inputs`") && err.contains("\"result\""), "{err}");
    let err = error(&format!("{CHAIN}\n[edges.spare]\nmessage = \"Grasps\"\n"));
    assert!(err.contains("`edges.spare`") && err.contains("no stage lists it"), "{err}");
    let err = error(&CHAIN.replace("inputs = [\"out\"]", "inputs = [\"out\"]\noutputs = [\"raw\"]"));
    assert!(err.contains("`edges.raw`") && err.contains("exactly one"), "{err}");
}

#[test]
fn cycles_are_rejected_but_request_response_loops_are_not() {
    let cyclic = r#"
[graph]
name = "loop"
[edges.a]
message = "Hypotheses"
[edges.b]
message = "Estimate"
[stages.one]
exe = "true"
inputs = ["b"]
outputs = ["a"]
[stages.two]
exe = "true"
inputs = ["a"]
outputs = ["b"]
"#;
    let err = error(cyclic);
    assert!(err.contains("`stages`") && err.contains("one -> two -> one"), "{err}");

    let velocity_loop = r#"
[graph]
name = "estimation"
[edges.velocity]
message = "Velocity"
pattern = "request-response"
[edges.hyps]
message = "Hypotheses"
[stages.sampler]
exe = "true"
calls = ["velocity"]
outputs = ["hyps"]
[stages.inference]
exe = "true"
serves = ["velocity"]
[stages.selector]
exe = "true"
inputs = ["hyps"]
"#;
    check(velocity_loop).unwrap();
    let err = error(&velocity_loop.replace("calls = [\"velocity\"]", "inputs = [\"velocity\"]"));
    assert!(err.contains("`stages.sampler.inputs`") && err.contains("PublishSubscribe edges only"), "{err}");
}

#[test]
fn a_side_input_may_close_a_loop_and_counts_as_a_reader() {
    let tracking = r#"
[graph]
name = "tracking"
[edges.handles]
message = "Condition"
[edges.hyps]
message = "Hypotheses"
[edges.estimates]
message = "Estimate"
[stages.source]
exe = "true"
outputs = ["handles"]
[stages.sampler]
exe = "true"
inputs = ["handles"]
side_inputs = ["estimates"]
outputs = ["hyps"]
[stages.selector]
exe = "true"
inputs = ["hyps"]
outputs = ["estimates"]
[stages.sink]
exe = "true"
inputs = ["estimates"]
"#;
    let graph = check(tracking).unwrap();
    let selector = graph.wiring(&graph.stages["selector"], "t1").unwrap();
    assert_eq!(selector.outputs[0].readers, 2, "the sampler's side input and the sink");
    let sampler = graph.wiring(&graph.stages["sampler"], "t1").unwrap();
    assert_eq!(sampler.side_inputs.len(), 1);
    assert_eq!(sampler.side_inputs[0].edge, "estimates");

    // As a plain input the same edge is a cycle.
    let err = error(
        &tracking
            .replace("inputs = [\"handles\"]\nside_inputs = [\"estimates\"]", "inputs = [\"handles\", \"estimates\"]"),
    );
    assert!(err.contains("sampler -> selector -> sampler"), "{err}");
    let err = error(&tracking.replace("side_inputs = [\"estimates\"]", "side_inputs = [\"handles\"]"));
    assert!(err.contains("`stages.sampler.side_inputs`") && err.contains("\"handles\""), "{err}");
    let err = error(&tracking.replace("side_inputs = [\"estimates\"]", "side_inputs = [\"nowhere\"]"));
    assert!(err.contains("`stages.sampler.side_inputs`"), "{err}");
}

#[test]
fn parameter_files_are_read_relative_to_the_graph() {
    let dir = std::env::temp_dir().join(format!("poseflow-graph-test-{}", std::process::id()));
    std::fs::create_dir_all(dir.join("config")).unwrap();
    std::fs::write(dir.join("config/middle.toml"), "factor = 1\nname = \"from file\"\n").unwrap();
    let text = CHAIN.replace("params = { factor = 2 }", "config = \"config/middle.toml\"\nparams = { factor = 2 }");
    let graph = parse(&text, &dir.join("g.toml"), &[PathBuf::from("/bin")]).unwrap();
    assert_eq!(graph.stages["middle"].params["factor"], 2, "inline overrides the file");
    assert_eq!(graph.stages["middle"].params["name"], "from file");
    std::fs::write(dir.join("config/middle.toml"), "factor = \n").unwrap();
    let err = parse(&text, &dir.join("g.toml"), &[PathBuf::from("/bin")]).unwrap_err().to_string();
    assert!(err.contains("`stages.middle.config`") && err.contains("middle.toml"), "{err}");
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn set_changes_one_parameter_for_one_run() {
    let mut graph = check(CHAIN).unwrap();
    graph.set_param("middle.factor=3").unwrap();
    graph.set_param("middle.tracking.enabled=false").unwrap();
    graph.set_param("source.dataset=data/lmo test").unwrap();
    graph.set_param("source.scenes=[0, 2]").unwrap();
    assert_eq!(graph.stages["middle"].params["factor"], 3);
    assert_eq!(graph.stages["middle"].params["tracking"]["enabled"], false);
    assert_eq!(graph.stages["source"].params["dataset"], "data/lmo test", "not TOML: a plain string");
    assert_eq!(graph.stages["source"].params["scenes"], serde_json::json!([0, 2]));
    let wiring = graph.wiring(&graph.stages["middle"], "g7").unwrap();
    assert_eq!(wiring.params["factor"], 3, "the stage process is told");

    for (assignment, expected) in [
        ("middle.factor", "expected STAGE.KEY=VALUE, found no `=`"),
        ("middle=3", "expected STAGE.KEY=VALUE, found key path `middle`"),
        ("middle..x=3", "key path `middle..x`"),
        ("nowhere.x=1", "expected one of the graph's stages (middle, sink, source), found `nowhere`"),
        ("middle.factor.x=1", "`stages.middle.params.factor`: expected a table to set `x` in, found 3"),
    ] {
        let err = graph.set_param(assignment).unwrap_err().to_string();
        assert!(err.contains(expected) && err.starts_with(FILE), "{assignment}: {err}");
    }
}
