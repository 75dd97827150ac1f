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
    let output = run_graph(&record, &graph).output_within(RUN_DEADLINE);
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
        let output = run_graph(&["--json", "--status-ms", "0"], &replay).output_within(RUN_DEADLINE);
        let replayed = summary(&output);
        assert!(output.status.success(), "{replayed}");
        eprintln!("replay at {speed} speed took {:.2} s", replayed["elapsed_s"].as_f64().unwrap());
        let seen: SinkReport = serde_json::from_str(&std::fs::read_to_string(&report).unwrap()).unwrap();
        // The recorded edge carries the relay's negated values and stamps.
        assert_eq!((seen.received, seen.intact, seen.relayed, seen.gaps), (300, 300, 300, 0), "{speed}: {seen:?}");
    }
}

/// A graph entry's `stamp` moves a stage to another timestamp slot, in
/// processes and in-process alike; a slot written twice on one path is
/// refused before anything starts.
#[test]
fn a_graph_stamp_key_chooses_the_slot_a_stage_writes() {
    use poseflow_contracts::{HypothesesHeader, MessageHeader, StampSlot};
    use poseflow_runtime::recording::{RecordingReader, header_from_bytes};

    let _serial = serial();
    let scratch = Scratch::new("stamp");
    let relay_stamped = |stamp: &str| {
        let path = scratch.graph(100, 0.0, "block");
        let text = std::fs::read_to_string(&path)
            .unwrap()
            .replace("exe = \"smoke-relay\"", &format!("exe = \"smoke-relay\"\nstamp = \"{stamp}\""));
        std::fs::write(&path, text).unwrap();
        path
    };
    for mode in [&[][..], &["--in-process"][..]] {
        let recording = scratch.dir.join("negated.rec");
        let graph = relay_stamped("grasp");
        let mut args = vec!["--json", "--status-ms", "0", "--record", recording.to_str().unwrap()];
        args.extend(["--record-edges", "negated"]);
        args.extend(mode);
        let output = run_graph(&args, &graph).output_within(RUN_DEADLINE);
        assert!(output.status.success(), "{mode:?}: {}", summary(&output));
        let mut reader = RecordingReader::open(&recording).unwrap();
        let mut seen = 0;
        while let Some(message) = reader.next_message().unwrap() {
            let header: HypothesesHeader = header_from_bytes(&message.header).unwrap();
            let stamps = &header.header().stamps;
            assert!(stamps.get(StampSlot::Source).is_some(), "{mode:?}: {stamps:?}");
            assert!(stamps.get(StampSlot::Grasp).is_some(), "{mode:?}: the relay's chosen slot: {stamps:?}");
            assert_eq!(stamps.get(StampSlot::Sampler), None, "{mode:?}: the relay's own default slot");
            seen += 1;
        }
        assert_eq!(seen, 100, "{mode:?}");
    }

    let clash = relay_stamped("source");
    for check in [&["--check"][..], &["--json"][..]] {
        let output = run_graph(check, &clash).output_within(RUN_DEADLINE);
        let stderr = String::from_utf8_lossy(&output.stderr);
        assert!(!output.status.success(), "{check:?}");
        assert!(
            stderr.contains("stages `relay` and `source` both write timestamp slot `source` on one path"),
            "{check:?}: {stderr}"
        );
    }
    let unknown = relay_stamped("detector");
    let output = run_graph(&["--check"], &unknown).output_within(RUN_DEADLINE);
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(stderr.contains("stages.relay.stamp") && stderr.contains("\"detector\""), "{stderr}");
}
