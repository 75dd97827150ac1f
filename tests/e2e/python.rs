//! Python as a stage language (`plugins/python`): the module's ctypes
//! mirrors of the contracts against the Rust layouts (size, alignment,
//! every field's offset, and the iceoryx2 type name a service is opened
//! with: a mismatch would corrupt every message silently or keep the
//! Python side from opening the service), and the example source and
//! Estimate sink in real graphs, through the installed module.

use std::collections::BTreeMap;
use std::mem::{align_of, offset_of, size_of};
use std::process::Command;

use iceoryx2::prelude::ZeroCopySend;
use poseflow_contracts::{
    CameraIntrinsics, ConditionHandle, EstimateHeader, FrameHeader, GraspsHeader, Header, Heartbeat, HypothesesHeader,
    NextViewHeader, ObjectCategory, ObservationHeader, STAGE_SLOTS, StageStamps, StampSlot, TensorHeader,
    VelocityRequest, VelocityResponse, VelocitySegment,
};
use poseflow_e2e::harness::*;
use poseflow_e2e::plugin_python;
use poseflow_graph::Stamp;
use poseflow_runtime::recording::{RecordingReader, header_from_bytes};
use poseflow_transport::shared_memory_files;
use serde_json::{Value, json};

/// `{size, align, type_name, fields: {name: offset}}` of one Rust contract.
macro_rules! rust_layout {
    ($t:ty { $($field:ident),* $(,)? }) => {
        (
            stringify!($t),
            json!({
                "size": size_of::<$t>(),
                "align": align_of::<$t>(),
                // SAFETY: reading the name has no precondition; the trait is
                // unsafe for its implementors, who promise the layout.
                "type_name": unsafe { <$t as ZeroCopySend>::type_name() },
                "fields": { $(stringify!($field): offset_of!($t, $field)),* },
            }),
        )
    };
}

/// Contracts that only ever travel inside another header.
const NESTED: [&str; 5] = ["StageStamps", "Header", "CameraIntrinsics", "VelocitySegment", "ObjectCategory"];

const DUMP: &str = r#"
import ctypes, json, sys
sys.path.insert(0, sys.argv[1])
import poseflow_stage as p
print(json.dumps({c.__name__: {
    "size": ctypes.sizeof(c),
    "align": ctypes.alignment(c),
    "type_name": c.type_name() if hasattr(c, "type_name") else None,
    "fields": {name: getattr(c, name).offset for name, _ in c._fields_},
} for c in p.CONTRACTS}))
"#;

#[test]
fn every_python_contract_mirror_has_the_rust_layout_and_type_name() {
    let rust: BTreeMap<&str, Value> = [
        rust_layout!(StageStamps { ns }),
        rust_layout!(Header { frame_id, object_id, flags, stamps }),
        rust_layout!(CameraIntrinsics { fx, fy, cx, cy, width, height }),
        rust_layout!(ObjectCategory { code, size }),
        rust_layout!(FrameHeader { header, intrinsics, scene_id, image_id, detection_count, mask_len }),
        rust_layout!(ObservationHeader {
            header,
            intrinsics,
            centroid,
            point_scale,
            crop,
            image_size,
            patch_grid,
            point_count,
            valid_point_count,
            depth_grid,
            depth_span
        }),
        rust_layout!(ConditionHandle {
            header,
            condition_id,
            image_tokens,
            point_tokens,
            active_image_tokens,
            model_width,
            centroid,
            point_scale,
            category
        }),
        rust_layout!(VelocitySegment { condition_id, sample_count, t }),
        rust_layout!(VelocityRequest {
            header,
            request_id,
            segment_count,
            sample_count,
            step_index,
            step_count,
            segments
        }),
        rust_layout!(VelocityResponse { header, request_id, sample_count, status }),
        rust_layout!(HypothesesHeader { header, sample_count, step_count, category }),
        rust_layout!(EstimateHeader {
            header,
            best,
            mean,
            covariance,
            rotation_trace,
            selection,
            mode_count,
            hypothesis_count,
            kept_count,
            refined,
            category
        }),
        rust_layout!(GraspsHeader { header, grasp_count, hypothesis_count }),
        rust_layout!(Heartbeat {
            header,
            pid,
            state,
            frames_in,
            frames_out,
            dropped,
            errors,
            latency_p50_us,
            latency_p99_us,
            busy_us,
            blocked_us
        }),
        rust_layout!(TensorHeader { header, shape, rank, reserved }),
        rust_layout!(NextViewHeader {
            header,
            chosen,
            expected_rotation_trace,
            current_rotation_trace,
            candidate_count,
            reserved
        }),
    ]
    .into_iter()
    .collect();
    let plugins = concat!(env!("CARGO_MANIFEST_DIR"), "/../plugins/python");
    let output = Command::new(plugin_python()).args(["-c", DUMP, plugins]).output_within(RUN_DEADLINE);
    assert!(output.status.success(), "{}", String::from_utf8_lossy(&output.stderr));
    let python: BTreeMap<String, Value> = serde_json::from_slice(&output.stdout).unwrap();
    let names = |m: Vec<&str>| m.join(", ");
    assert_eq!(
        names(python.keys().map(String::as_str).collect()),
        names(rust.keys().copied().collect()),
        "a contract without its Python mirror, or the other way round"
    );
    for (name, expected) in &rust {
        let mirror = &python[*name];
        for key in ["size", "align", "fields"] {
            assert_eq!(
                mirror[key], expected[key],
                "{name}.{key}: Python {} against Rust {}",
                mirror[key], expected[key]
            );
        }
        // Structs nested in a header need no type name of their own in
        // Python: iceoryx2 matches only the header a service carries.
        if !mirror["type_name"].is_null() || !NESTED.contains(name) {
            assert_eq!(mirror["type_name"], expected["type_name"], "{name}: iceoryx2 type name");
        }
    }
}

/// The Python module's timestamp slots are the Rust `StampSlot`s: same
/// numbers, same names as graph files' `stamp` key; a Python stage writes
/// the slot its wiring's `stamp` names (as `StageWiring::stamp_slot`).
#[test]
fn the_python_timestamp_slots_are_the_rust_ones() {
    let plugins = concat!(env!("CARGO_MANIFEST_DIR"), "/../plugins/python");
    let dump = r#"
import json, sys
sys.path.insert(0, sys.argv[1])
import poseflow_stage as p
wired = lambda wire: type("Stage", (), {"wire": wire})()
chosen = [p._stamp_slot(wired(json.loads(w)), p.SLOT_SAMPLER) for w in sys.argv[2:]]
print(json.dumps([p.STAGE_SLOTS, list(p.SLOT_NAMES), [p.SLOT_SOURCE, p.SLOT_SAMPLER, p.SLOT_SINK], chosen]))
"#;
    let wirings = [json!({}), json!({"stamp": "grasp"}), json!({"stamp": "none"})];
    let mut args = vec!["-c".to_string(), dump.to_string(), plugins.to_string()];
    args.extend(wirings.iter().map(Value::to_string));
    let output = Command::new(plugin_python()).args(&args).output_within(RUN_DEADLINE);
    assert!(output.status.success(), "{}", String::from_utf8_lossy(&output.stderr));
    let python: Value = serde_json::from_slice(&output.stdout).unwrap();
    let names: Vec<&str> = StampSlot::ALL.iter().map(|slot| slot.name()).collect();
    let numbers = [StampSlot::Source, StampSlot::Sampler, StampSlot::Sink].map(|slot| slot as usize);
    // The same choices through the Rust wiring.
    let rust: Vec<Option<usize>> = wirings
        .iter()
        .map(|wire| {
            let stamp = wire.get("stamp").map(|s| serde_json::from_value::<Stamp>(s.clone()).unwrap());
            Stamp::resolve(stamp, Some(StampSlot::Sampler)).map(|slot| slot as usize)
        })
        .collect();
    assert_eq!(rust, [Some(3), Some(5), None]);
    assert_eq!(python, json!([STAGE_SLOTS, names, numbers, rust]));
}

/// The installed module (`pip install plugins/python`, as `deploy/setup`
/// does), not the file beside the examples: a script in `examples/` finds
/// only the installed copy.
fn example(name: &str) -> String {
    format!("{}/../plugins/python/examples/{name}", env!("CARGO_MANIFEST_DIR"))
}

/// A source written in Python feeds the Rust relay and checking sink,
/// which verifies all 500 frames value by value.
#[test]
fn a_python_source_feeds_rust_stages() {
    let _serial = serial();
    let before = shared_memory_files();
    let scratch = Scratch::new("python-source");
    let graph = scratch.graph(500, 0.0, "block");
    let text = std::fs::read_to_string(&graph).unwrap().replace(
        "exe = \"smoke-source\"",
        &format!("exe = \"{}\"\nargs = [\"{}\"]", plugin_python().display(), example("counting_source.py")),
    );
    std::fs::write(&graph, text).unwrap();
    let (summary, stderr) = run_to_end(&graph);
    for stage in ["source", "relay", "sink"] {
        assert_eq!(summary["stages"][stage]["outcome"], "finished", "{summary}\n{stderr}");
    }
    assert_eq!(summary["stages"]["source"]["frames_out"], 500, "{summary}");
    let report = scratch.report();
    assert_eq!((report.received, report.intact, report.gaps), (500, 500, 0), "{report:?}");
    assert_nothing_leaked(&before);
}

/// The Python Estimate sink on the estimation graph: one JSON line per
/// Estimate, each equal to the Estimate recorded on the same edge (frame,
/// object, best pose, modes and kept hypotheses, value for value).
#[test]
fn a_python_sink_reads_every_estimate_of_the_estimation_graph() {
    let _serial = serial();
    let before = shared_memory_files();
    let scratch = Scratch::new("python-sink");
    let root = std::path::PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/.."));
    let lines = scratch.dir.join("estimates.jsonl");
    let graph = scratch.dir.join("estimation-printed.toml");
    let text = std::fs::read_to_string(root.join("deploy/estimation.toml"))
        .unwrap()
        .replace("\"../config/", &format!("\"{}/config/", root.display()))
        + &format!(
            "\n[stages.printer]\nexe = \"{}\"\nargs = [\"{}\"]\ninputs = [\"estimates\"]\n\
             params = {{ format = \"json\", output = \"{}\" }}\n",
            plugin_python().display(),
            example("print_estimates.py"),
            lines.display()
        );
    std::fs::write(&graph, text).unwrap();
    let recording = scratch.dir.join("estimates.rec");
    let args = [
        "--json",
        "--status-ms",
        "0",
        "--record",
        recording.to_str().unwrap(),
        "--record-edges",
        "estimates",
        "--set",
        "frames.frames_per_scene=2",
        "--set",
        "selector.sdf_resolution=16",
    ];
    let output = run_graph(&args, &graph).current_dir(&root).output_within(RUN_DEADLINE);
    let summary = summary(&output);
    assert!(output.status.success(), "{summary}\n{}", String::from_utf8_lossy(&output.stderr));
    assert_eq!(summary["stages"]["printer"]["outcome"], "finished", "{summary}");

    let mut reader = RecordingReader::open(&recording).unwrap();
    let mut recorded = Vec::new();
    while let Some(message) = reader.next_message().unwrap() {
        let header: EstimateHeader = header_from_bytes(&message.header).unwrap();
        recorded.push((header, message.payload));
    }
    let printed: Vec<Value> =
        std::fs::read_to_string(&lines).unwrap().lines().map(|line| serde_json::from_str(line).unwrap()).collect();
    assert!(!recorded.is_empty());
    assert_eq!(printed.len(), recorded.len(), "one line per Estimate");
    let floats = |value: &Value| -> Vec<f32> {
        let pose = |p: &Value| -> Vec<f32> {
            let rows = p["R"].as_array().unwrap().iter().flat_map(|row| row.as_array().unwrap().clone());
            rows.chain(p["t"].as_array().unwrap().iter().cloned()).map(|v| v.as_f64().unwrap() as f32).collect()
        };
        match value.as_array() {
            Some(list) => list
                .iter()
                .flat_map(|item| {
                    let weight = item.get("weight").or(item.get("score")).unwrap();
                    pose(item).into_iter().chain([weight.as_f64().unwrap() as f32])
                })
                .collect(),
            None => pose(value),
        }
    };
    for ((header, payload), line) in recorded.iter().zip(&printed) {
        assert_eq!(line["frame"], header.header.frame_id, "{line}");
        assert_eq!(line["object"], header.header.object_id, "{line}");
        assert_eq!(floats(&line["best"]), header.best, "{line}");
        let modes = 13 * header.mode_count as usize;
        assert_eq!(floats(&line["modes"]), payload[..modes], "{line}");
        let kept = modes + 13 * header.kept_count as usize;
        assert_eq!(floats(&line["kept"]), payload[modes..kept], "{line}");
        assert_eq!(line["hypotheses"], header.hypothesis_count, "{line}");
    }
    drop(scratch);
    assert_nothing_leaked(&before);
}
