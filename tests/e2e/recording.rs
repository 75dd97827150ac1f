//! Record and replay: a recorded edge played back into a sink. Whole graphs
//! of real processes over real iceoryx2 shared memory, launched by `poseflow
//! run`.

use poseflow_e2e::harness::*;
use poseflow_smoke::SinkReport;

/// `--record` captures an edge; `replay-source` plays it back into a sink
/// without the stages that produced it.
#[test]
fn a_recorded_edge_replays_into_a_sink() {
    let _serial = serial();
    let scratch = Scratch::new("record");
    let recording = scratch.dir.join("negated.rec");
    let graph = scratch.graph(300, 500.0, "block");
    let record = ["--json", "--status-ms", "0", "--record", recording.to_str().unwrap(), "--record-edges", "negated"];
    let output = run_graph(&record, &graph).output().unwrap();
    let recorded = summary(&output);
    assert!(output.status.success(), "{recorded}");
    assert_eq!(recorded["recorded"]["negated"], 300, "{recorded}");

    for speed in ["max", "recorded"] {
        let report = scratch.dir.join(format!("replay-{speed}.json"));
        let replay = scratch.dir.join("replay.toml");
        let text = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/graphs/replay.toml"))
            .unwrap()
            .replace("file = \"recording.rec\"", &format!("file = \"{}\"", recording.display()))
            .replace("speed = \"max\"", &format!("speed = \"{speed}\""))
            .replace("report = \"sink-report.json\"", &format!("report = \"{}\"", report.display()));
        std::fs::write(&replay, text).unwrap();
        let output = run_graph(&["--json", "--status-ms", "0"], &replay).output().unwrap();
        let replayed = summary(&output);
        assert!(output.status.success(), "{replayed}");
        eprintln!("replay at {speed} speed took {:.2} s", replayed["elapsed_s"].as_f64().unwrap());
        let seen: SinkReport = serde_json::from_str(&std::fs::read_to_string(&report).unwrap()).unwrap();
        // The recorded edge carries the relay's negated values and stamps.
        assert_eq!((seen.received, seen.intact, seen.relayed, seen.gaps), (300, 300, 300, 0), "{speed}: {seen:?}");
    }
}
