//! Plug-in stages in Python: a relay in place of a Rust one, messages whose
//! lengths disagree with their headers, a detector between the frame source
//! and ingest. Whole graphs of real processes over real iceoryx2 shared
//! memory, launched by `poseflow run`.

use poseflow_e2e::harness::*;
use poseflow_e2e::plugin_python;
use poseflow_transport::shared_memory_files;

#[test]
fn a_python_stage_replaces_a_rust_one() {
    let _serial = serial();
    let before = shared_memory_files();
    let scratch = Scratch::new("python");
    let graph = scratch.graph(500, 0.0, "block");
    let plugin = concat!(env!("CARGO_MANIFEST_DIR"), "/../plugins/python/examples/negating_relay.py");
    let text = std::fs::read_to_string(&graph)
        .unwrap()
        .replace("exe = \"smoke-relay\"", &format!("exe = \"{}\"\nargs = [\"{plugin}\"]", plugin_python().display()));
    std::fs::write(&graph, text).unwrap();
    let output = run_graph(&["--json", "--status-ms", "0"], &graph).output_within(RUN_DEADLINE);
    let summary = summary(&output);
    assert!(output.status.success(), "{summary}\n{}", String::from_utf8_lossy(&output.stderr));
    assert_eq!(summary["stages"]["relay"]["frames_in"], 500, "{summary}");

    // The Rust sink checks the Python relay's output value by value.
    let report = scratch.report();
    assert_eq!((report.received, report.intact, report.relayed), (500, 500, 500), "{report:?}");
    assert_nothing_leaked(&before);
}

/// A foreign stage sending messages whose header and payload disagree (a
/// Python relay garbling every 50th frame): the Rust sink rejects exactly
/// those, names the contract broken, and everything else arrives intact.
#[test]
fn messages_with_inconsistent_lengths_are_rejected_and_the_rest_flows() {
    let _serial = serial();
    let before = shared_memory_files();
    let scratch = Scratch::new("garble");
    let graph = scratch.graph(500, 0.0, "block");
    let plugin = concat!(env!("CARGO_MANIFEST_DIR"), "/stages/garbling_relay.py");
    let text = std::fs::read_to_string(&graph).unwrap().replace(
        "exe = \"smoke-relay\"",
        &format!("exe = \"{}\"\nargs = [\"{plugin}\", \"50\"]", plugin_python().display()),
    );
    std::fs::write(&graph, text).unwrap();
    let (summary, stderr) = run_to_end(&graph);
    for stage in ["source", "relay", "sink"] {
        assert_eq!(summary["stages"][stage]["outcome"], "finished", "{summary}");
    }
    assert_eq!(summary["stages"]["sink"]["errors"], 10, "{summary}");
    assert!(
        stderr.contains("message rejected")
            && stderr.contains("Hypotheses: payload holds 48 f32 values, the header announces 60"),
        "{stderr}"
    );
    let report = scratch.report();
    // Frames 49, 99, …, 499 rejected: 9 gaps between received frames, and
    // the last one received is 498.
    assert_eq!((report.received, report.intact, report.corrupted, report.gaps), (490, 490, 0, 9), "{report:?}");
    assert_eq!(report.last_frame, Some(498), "{report:?}");
    assert_nothing_leaked(&before);
}

/// A detector written in Python sits between the frame source and ingest
/// and decides which objects are observed.
#[test]
fn a_python_detector_plugs_in_between_frames_and_ingest() {
    let _serial = serial();
    let before = shared_memory_files();
    let scratch = Scratch::new("detector");
    let plugin = concat!(env!("CARGO_MANIFEST_DIR"), "/../plugins/python/examples/detector_template.py");
    let graph = ingest_graph(&scratch, "detector.toml", &corpus_frames(), Some((plugin, "{ min_area = 150 }")));
    let recording = scratch.dir.join("observations.rec");
    let (result, stderr) = run_recording(&graph, "observations", &recording);
    assert_eq!(result["stages"]["detector"]["outcome"], "finished", "{result}");
    // Image 0 has objects of 153, 442 and 130 visible pixels: the detector
    // keeps the first two. It drops image 5's empty and 3-pixel masks, so
    // ingest only rejects image 6's two remaining objects (no depth).
    assert_eq!(recorded_observations(&recording), [(0, 1), (0, 10)], "{result}\n{stderr}");
    assert_eq!(result["stages"]["ingest"]["errors"], 2, "{result}\n{stderr}");
    drop(scratch);
    assert_nothing_leaked(&before);
}
