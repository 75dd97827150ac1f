//! The pose stages as processes: the ingest stage on the bad-input corpus,
//! the inference stage serving velocities, and every graph in `deploy/` as
//! processes against the same graph in-process, bit for bit. Whole graphs
//! of real processes over real iceoryx2 shared memory, launched by
//! `poseflow run`.

use std::path::{Path, PathBuf};

use poseflow_e2e::harness::*;
use poseflow_e2e::recordings::recorded_messages;
use poseflow_transport::shared_memory_files;

/// The ingest stage reads the bad-input corpus as its own process: broken
/// frames and objects are counted as errors, the good ones arrive intact
/// over shared memory, and the stream runs to its end.
#[test]
fn the_ingest_stage_survives_the_bad_input_corpus() {
    let _serial = serial();
    let before = shared_memory_files();
    let scratch = Scratch::new("ingest");
    let graph = ingest_graph(&scratch, "ingest.toml", &corpus_frames(), None);
    let recording = scratch.dir.join("observations.rec");
    let (result, stderr) = run_recording(&graph, "observations", &recording);
    let (frames, ingest) = (&result["stages"]["frames"], &result["stages"]["ingest"]);
    assert_eq!((&frames["outcome"], &ingest["outcome"]), (&"finished".into(), &"finished".into()), "{result}");
    // The frame source cannot read images 1, 2, 3, 4 (depth size), 7 and
    // scene 1, nor one mask of image 5; ingest rejects the other two objects
    // of image 5 and the three of image 6 (no depth). Image 0's three
    // objects arrive.
    assert_eq!(frames["errors"], 7, "{result}\n{stderr}");
    assert_eq!((&frames["frames_out"], &ingest["frames_in"]), (&3.into(), &3.into()), "{result}");
    assert_eq!(ingest["errors"], 5, "{result}\n{stderr}");
    assert_eq!(result["recorded"]["observations"], 3, "{result}\n{stderr}");
    for expected in ["rgb/000001.png", "expected a 16-bit single-channel depth PNG", "mask has 3 pixels", "cam_K"] {
        assert!(stderr.contains(expected), "no `{expected}` in:\n{stderr}");
    }
    assert_eq!(recorded_observations(&recording), [(0, 1), (0, 10), (0, 11)]);

    // The recorded frames replay into ingest without the frame source and
    // give the same observations.
    let frames_recording = scratch.dir.join("frames.rec");
    run_recording(&graph, "frames", &frames_recording);
    let replay =
        format!("exe = \"replay-source\"\nparams = {{ file = \"{}\", speed = \"max\" }}", frames_recording.display());
    let replay_graph = ingest_graph(&scratch, "replay.toml", &replay, None);
    run_recording(&replay_graph, "observations", &recording);
    assert_eq!(recorded_observations(&recording), [(0, 1), (0, 10), (0, 11)]);
    drop(scratch);
    assert_nothing_leaked(&before);
}

/// The corpus frames → ingest (112/8/1024) → inference (`model`, one
/// thread), with the `conditions` edge and the `velocities` request-response
/// edge (up to 50 samples) for the stages a test adds.
fn encoding_graph(name: &str, model: &Path) -> String {
    graph_head(name, 43_000)
        + &format!(
            r#"
[edges.conditions]
message = "Condition"
# One slot: the inference stage often waits on a full queue while the
# sampler waits for its answers, which it must keep giving.
queue = 1
overflow = "block"

[edges.velocities]
message = "Velocity"
pattern = "request-response"
max_payload_len = 600

[stages.frames]
outputs = ["frames"]
{frames}

[stages.ingest]
exe = "ingest"
inputs = ["frames"]
outputs = ["observations"]
params = {{ image_size = 112, patch_grid = 8, point_count = 1024 }}

[stages.inference]
exe = "inference"
inputs = ["observations"]
outputs = ["conditions"]
serves = ["velocities"]
params = {{ model = "{model}", threads = 1 }}
"#,
            frames = corpus_frames(),
            model = model.display(),
        )
}

/// frames → ingest → inference ⇄ velocity-probe: the inference stage, as its
/// own process, encodes each observation once and answers velocity requests
/// over iceoryx2 request-response with exactly what the same stage computes
/// in-process, and answers an unknown condition with its status code.
#[test]
fn the_inference_stage_answers_velocity_requests_over_shared_memory() {
    use poseflow_contracts::{MessageHeader, ObservationHeader, VelocityRequest, status};
    use poseflow_inference::PoseFlowModel;
    use poseflow_inference::stage::InferenceStage;
    use poseflow_runtime::recording::{RecordingReader, header_from_bytes};

    let _serial = serial();
    let before = shared_memory_files();
    let scratch = Scratch::new("inference");
    let model = PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/../models/test-tiny"));
    let report = scratch.dir.join("velocities.jsonl");
    let graph = scratch.dir.join("inference.toml");
    std::fs::write(
        &graph,
        encoding_graph("inference-e2e", &model)
            + &format!(
                r#"
[stages.probe]
exe = "velocity-probe"
inputs = ["conditions"]
calls = ["velocities"]
params = {{ report = "{report}" }}
"#,
                report = report.display(),
            ),
    )
    .unwrap();
    let recording = scratch.dir.join("observations.rec");
    let (result, stderr) = run_recording(&graph, "observations", &recording);
    // The inference stage counts the requests it could not serve.
    for (stage, errors) in [("inference", 3), ("probe", 0)] {
        assert_eq!(result["stages"][stage]["outcome"], "finished", "{result}\n{stderr}");
        assert_eq!(result["stages"][stage]["errors"], errors, "{result}\n{stderr}");
    }
    let lines: Vec<serde_json::Value> =
        std::fs::read_to_string(&report).unwrap().lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    // Image 0's three objects, each asked once with its condition and once
    // with an unknown one.
    assert_eq!(lines.len(), 6, "{lines:?}");

    let mut stage = InferenceStage::with_model(PoseFlowModel::load(&model, 1).unwrap(), 8);
    let mut reader = RecordingReader::open(&recording).unwrap();
    let mut answered = 0;
    while let Some(message) = reader.next_message().unwrap() {
        let header: ObservationHeader = header_from_bytes(&message.header).unwrap();
        header.check_payload(&message.payload).unwrap();
        let handle = stage.encode(&header, &message.payload).unwrap();
        let (frame, object) = (header.header.frame_id, header.header.object_id);
        let known = &lines[2 * answered];
        let unknown = &lines[2 * answered + 1];
        assert_eq!((known["frame"].as_u64(), known["object"].as_u64()), (Some(frame), Some(u64::from(object))));
        assert_eq!(known["status"], status::OK, "{known}");
        assert_eq!(unknown["status"], status::UNKNOWN_CONDITION, "{unknown}");
        assert_eq!(unknown["velocities"].as_array().map(Vec::len), Some(0));
        let poses = poseflow_e2e::probe_poses(frame, object, 50);
        let request = VelocityRequest::single(header.header, handle.condition_id, 0, 50, 0.2);
        let mut expected = vec![0.0f32; 50 * 6];
        stage.velocities(&request, &poses, &mut expected).unwrap();
        let served: Vec<f32> =
            known["velocities"].as_array().unwrap().iter().map(|v| v.as_f64().unwrap() as f32).collect();
        assert_eq!(served, expected, "frame {frame} object {object}");
        answered += 1;
    }
    assert_eq!(answered, 3);
    drop(scratch);
    assert_nothing_leaked(&before);
}

/// Every graph in `deploy/`, built through the stage registry once as
/// processes over iceoryx2 and once as threads of one process: every edge
/// carries the same messages, bit for bit (timestamps aside). Where the
/// graph is not deterministic the comparison says what still must agree:
/// on drop-oldest edges the messages both runs kept; in the tracking graph
/// (whose prior is whichever estimate arrived first) the counts, and the
/// messages upstream of the sampler.
#[test]
fn every_deploy_graph_gives_the_same_messages_as_processes_and_in_process() {
    let _serial = serial();
    let before = shared_memory_files();
    let scratch = Scratch::new("equivalence");
    let root = PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/.."));
    let mut graphs: Vec<PathBuf> = std::fs::read_dir(root.join("deploy"))
        .unwrap()
        .map(|entry| entry.unwrap().path())
        .filter(|path| path.extension().is_some_and(|e| e == "toml"))
        // A live ROS 2 camera has no frames without a ROS 2 peer; its graph
        // runs against one in tests/e2e/ros2.rs.
        .filter(|path| !std::fs::read_to_string(path).unwrap().contains("exe = \"ros2-camera\""))
        .collect();
    graphs.sort();
    assert!(graphs.len() >= 6, "{graphs:?}");
    // And the estimation graph with a one-slot conditions queue: the
    // inference stage must answer the sampler while its output is full.
    let one_slot = scratch.dir.join("estimation-one-slot.toml");
    let estimation = std::fs::read_to_string(root.join("deploy/estimation.toml")).unwrap();
    let narrowed = estimation
        .replace(
            "[edges.conditions]\nmessage = \"Condition\"\nqueue = 8",
            "[edges.conditions]\nmessage = \"Condition\"\nqueue = 1",
        )
        .replace("\"../config/", &format!("\"{}/config/", root.display()));
    assert_ne!(narrowed, estimation);
    std::fs::write(&one_slot, narrowed).unwrap();
    graphs.push(one_slot);
    for graph in &graphs {
        let name = graph.file_stem().unwrap().to_str().unwrap();
        // Less work for the unoptimised test build (what is compared is each
        // message, not their number or the defaults' accuracy): two frames,
        // coarse signed-distance grids, few next-best-view candidates and grasps.
        let text = std::fs::read_to_string(graph).unwrap();
        let mut shorter: Vec<&str> = Vec::new();
        for (stage, assignment) in [
            ("frames", "frames.frames_per_scene=2"),
            ("selector", "selector.sdf_resolution=16"),
            ("nbv", "nbv.candidates=3"),
            ("nbv", "nbv.hypotheses=1"),
            ("grasp", "grasp.grasps=8"),
            ("grasp", "grasp.hypotheses=2"),
        ] {
            if text.contains(&format!("[stages.{stage}]")) {
                shorter.extend(["--set", assignment]);
            }
        }
        let mut runs = Vec::new();
        for mode in ["processes", "in-process"] {
            let recording = scratch.dir.join(format!("{name}-{mode}.rec"));
            let mut args = vec!["--json", "--status-ms", "0", "--record", recording.to_str().unwrap()];
            args.extend_from_slice(&shorter);
            if mode == "in-process" {
                args.push("--in-process");
            }
            let output = run_graph(&args, graph).current_dir(&root).output_within(RUN_DEADLINE);
            let summary = summary(&output);
            let stderr = String::from_utf8_lossy(&output.stderr);
            assert!(output.status.success(), "{name} ({mode}): {summary}\n{stderr}");
            // A restarted stage flags its first output and may lose frames.
            for (stage, report) in summary["stages"].as_object().unwrap() {
                assert_eq!(report["restarts"], 0, "{name} ({mode}): stage `{stage}` restarted: {summary}\n{stderr}");
            }
            runs.push(recorded_messages(&recording));
        }
        let (processes, in_process) = (&runs[0], &runs[1]);
        assert!(!processes.is_empty(), "{name}: nothing recorded");
        // A drop-oldest edge loses what timing decides, so there only the
        // messages both runs kept are compared, matched by frame and object.
        let drops = text.contains("drop-oldest");
        if !drops {
            assert_eq!(
                processes.iter().map(|(edge, messages)| (edge, messages.len())).collect::<Vec<_>>(),
                in_process.iter().map(|(edge, messages)| (edge, messages.len())).collect::<Vec<_>>(),
                "{name}: messages per edge"
            );
        }
        let mut differences = Vec::new();
        for (edge, messages) in processes {
            // Downstream of the tracking sampler the prior is whichever
            // estimate arrived first.
            if name.starts_with("tracking")
                && !["frames", "detected", "observations", "conditions"].contains(&edge.as_str())
            {
                continue;
            }
            let theirs: std::collections::BTreeMap<&[u8], &(Vec<u8>, Vec<u32>)> =
                in_process[edge].iter().map(|m| (&m.0[..12], m)).collect();
            let mut compared = 0;
            for (i, a) in messages.iter().enumerate() {
                let b = if drops { theirs.get(&a.0[..12]).copied() } else { in_process[edge].get(i) };
                let Some(b) = b else { continue };
                compared += 1;
                if a != b {
                    let header_byte = a.0.iter().zip(&b.0).position(|(x, y)| x != y);
                    let value = a.1.iter().zip(&b.1).position(|(x, y)| x != y);
                    differences.push(format!(
                        "edge `{edge}`, message {i} of {}: first difference at header byte {header_byte:?}, \
                         payload value {value:?}",
                        messages.len()
                    ));
                    break;
                }
            }
            assert!(compared > 0, "{name}: edge `{edge}`: no message in both runs");
        }
        assert!(differences.is_empty(), "{name}: processes and in-process differ:\n{}", differences.join("\n"));
    }
    drop(scratch);
    assert_nothing_leaked(&before);
}

/// The tracking demo's graph (deploy/tracking.toml, the default model, real
/// processes) over a video in which an occluder hides one object for longer
/// than the sampler keeps estimates (development seed 5: object 10, 20
/// images). Its estimates carry `LOST` when it is seen again (the samples
/// came from the prior: the track was broken), then `REINITIALISED` once a
/// second estimate confirms the new one, and the last estimate is within
/// 10°5cm again.
#[test]
fn an_occluded_object_is_flagged_lost_then_reinitialised_and_recovered() {
    let _serial = serial();
    let scratch = Scratch::new("track-occlusion");
    let out = scratch.dir.join("demo");
    let output = poseflow()
        .args(["demo", "--track", "--json", "--frames", "60", "--occlusions", "1", "--seed", "5"])
        .args(["--out", out.to_str().unwrap()])
        .current_dir(concat!(env!("CARGO_MANIFEST_DIR"), "/.."))
        .output_within(RUN_DEADLINE);
    assert!(output.status.success(), "{}", String::from_utf8_lossy(&output.stderr));
    let report: serde_json::Value = serde_json::from_slice(&output.stdout).unwrap();
    let event = &report["events"][0];
    assert_eq!(event["kind"], "occlusion", "{report}");
    let occluded = event["obj_id"].as_u64().unwrap();
    // scene,image,object,rotation_error_deg,translation_error_cm,flags
    let table = std::fs::read_to_string(out.join("tracking.csv")).unwrap();
    let rows: Vec<Vec<&str>> = table.lines().skip(1).map(|l| l.split(',').collect()).collect();
    let of_object: Vec<&Vec<&str>> = rows.iter().filter(|r| r[2].parse::<u64>().unwrap() == occluded).collect();
    let flagged = |flag: &str| of_object.iter().position(|r| r[5].split('|').any(|f| f == flag));
    let lost = flagged("lost").unwrap_or_else(|| panic!("object {occluded} never flagged lost:\n{table}"));
    let reinitialised =
        of_object[lost..].iter().position(|r| r[5].split('|').any(|f| f == "reinitialised")).unwrap_or_else(|| {
            panic!("object {occluded} never reinitialised after image {}:\n{table}", of_object[lost][1])
        });
    assert!(reinitialised > 0, "{table}");
    let last = of_object.last().unwrap();
    let (rotation, translation_cm): (f64, f64) = (last[3].parse().unwrap(), last[4].parse().unwrap());
    assert!(rotation < 10.0 && translation_cm < 5.0, "last estimate {last:?}\n{table}");
}

/// `poseflow demo --detect`: the estimation graph with the detector stage
/// (deploy/estimation-detect.toml, real processes) on a rendered scene of
/// the three vendored objects, no ground-truth mask anywhere in the graph.
/// The detector's masks must lead the pose stages to most of the objects:
/// an untrained detector finds none and the demo fails.
#[test]
fn the_detect_graph_estimates_rendered_objects_without_ground_truth_masks() {
    let _serial = serial();
    let scratch = Scratch::new("demo-detect");
    let out = scratch.dir.join("demo");
    let output = poseflow()
        .args(["demo", "--detect", "--json", "--out", out.to_str().unwrap()])
        .current_dir(concat!(env!("CARGO_MANIFEST_DIR"), "/.."))
        .output_within(RUN_DEADLINE);
    assert!(output.status.success(), "{}", String::from_utf8_lossy(&output.stderr));
    let report: serde_json::Value = serde_json::from_slice(&output.stdout).unwrap();
    let graph = std::fs::read_to_string(out.join("estimation-detect.toml")).unwrap();
    assert!(graph.contains("[stages.detector]"), "{graph}");
    let objects = report["objects"].as_array().unwrap();
    let within: Vec<u64> = objects
        .iter()
        .filter(|o| {
            o["rotation_error_deg"].as_f64().unwrap() < 10.0 && o["translation_error_cm"].as_f64().unwrap() < 5.0
        })
        .map(|o| o["obj_id"].as_u64().unwrap())
        .collect();
    assert!(within.len() >= 2, "objects within 10°5cm: {within:?} of {report}");
}

/// `poseflow demo --detect --detector-mode classical`: the detector stage
/// with no network, only the objects' meshes, in the same process graph.
/// Each of the three rendered objects must be found and named, and its
/// estimate must be within 10°5cm, among clutter shapes that parts of the
/// objects fit.
#[test]
fn the_classical_detector_finds_and_names_the_rendered_objects_in_the_graph() {
    let _serial = serial();
    let scratch = Scratch::new("demo-classical");
    let out = scratch.dir.join("demo");
    let output = poseflow()
        .args(["demo", "--detect", "--detector-mode", "classical", "--json", "--out", out.to_str().unwrap()])
        .current_dir(concat!(env!("CARGO_MANIFEST_DIR"), "/.."))
        .output_within(RUN_DEADLINE);
    assert!(output.status.success(), "{}", String::from_utf8_lossy(&output.stderr));
    let report: serde_json::Value = serde_json::from_slice(&output.stdout).unwrap();
    let graph = std::fs::read_to_string(out.join("estimation-detect.toml")).unwrap();
    assert!(graph.contains("mode = \"classical\""), "{graph}");
    let mut placed: Vec<(u64, f64, f64)> = report["objects"]
        .as_array()
        .unwrap()
        .iter()
        .map(|o| {
            let error = |key: &str| o[key].as_f64().unwrap();
            (o["obj_id"].as_u64().unwrap(), error("rotation_error_deg"), error("translation_error_cm"))
        })
        .collect();
    placed.sort_by_key(|&(id, _, _)| id);
    let ids: Vec<u64> = placed.iter().map(|&(id, _, _)| id).collect();
    assert_eq!(ids, [1, 10, 11], "{report}");
    assert!(placed.iter().all(|&(_, deg, cm)| deg < 10.0 && cm < 5.0), "errors (°, cm): {placed:?}");
}
