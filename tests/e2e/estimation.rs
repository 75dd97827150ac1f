//! The pose stages as processes: the ingest stage on the bad-input corpus,
//! the inference stage serving velocities, and the estimation graph (with
//! grasp and next-best-view) against the in-process run, bit for bit. Whole
//! graphs of real processes over real iceoryx2 shared memory, launched by
//! `poseflow run`.

use std::path::{Path, PathBuf};

use poseflow_e2e::harness::*;
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
    graph_head(name, 41_000)
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
        let request = VelocityRequest { header: header.header, sample_count: 50, t: 0.2, ..Default::default() };
        let request = VelocityRequest { condition_id: handle.condition_id, ..request };
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

/// frames → ingest → inference ⇄ sampler → selector (Observations as its
/// side input) → grasp and next-best view, each its own process: the
/// hypotheses, estimates, grasps and next views that cross shared memory
/// are bit for bit those of the same stages run in-process on the recorded
/// observations with the same seed.
#[test]
fn the_estimation_grasp_and_next_view_graph_matches_the_in_process_run_bit_for_bit() {
    use std::cell::RefCell;

    use poseflow_contracts::{
        CANDIDATE_LEN, EstimateHeader, GRASP_LEN, GraspsHeader, HypothesesHeader, MessageHeader, NextViewHeader,
        ObservationHeader,
    };
    use poseflow_grasp::stage::{grasp_values, kept_hypotheses};
    use poseflow_grasp::{GraspParams, GraspPlanner};
    use poseflow_inference::PoseFlowModel;
    use poseflow_inference::stage::InferenceStage;
    use poseflow_nbv::stage::NbvStage;
    use poseflow_nbv::{NbvParams, NbvPlanner};
    use poseflow_runtime::recording::{RecordingReader, header_from_bytes};
    use poseflow_sampler::SamplerParams;
    use poseflow_sampler::stage::SamplerStage;
    use poseflow_selector::SelectorParams;
    use poseflow_selector::stage::{SelectorStage, estimate_header, estimate_payload_len, write_estimate_payload};

    let _serial = serial();
    let before = shared_memory_files();
    let scratch = Scratch::new("estimation");
    let root = PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/.."));
    let model = root.join("models/test-tiny");
    let models = root.join("objects/lmo");
    let sampler_params = serde_json::json!({ "samples": 16, "steps": 3, "seed": 7 });
    let selector_params = serde_json::json!({
        "method": "sdf", "models": models, "refine": true, "score_points": 128, "sdf_resolution": 32,
    });
    let grasp_params = serde_json::json!({
        "model": root.join("models/grasp-flow"), "models": models, "grasps": 6, "steps": 3, "hypotheses": 3, "seed": 5,
    });
    let nbv_params = serde_json::json!({
        "models": models, "candidates": 3, "hypotheses": 2, "workers": 2,
        "inference": { "model": model }, "sampler": { "samples": 4, "steps": 2 },
    });
    let graph = scratch.dir.join("estimation.toml");
    std::fs::write(
        &graph,
        encoding_graph("estimation-e2e", &model)
            + &format!(
                r#"
[edges.hypotheses]
message = "Hypotheses"
queue = 4
overflow = "block"
max_payload_len = 600

[edges.estimates]
message = "Estimate"
queue = 4
overflow = "block"
max_payload_len = 2000

[stages.sampler]
exe = "sampler"
inputs = ["conditions"]
calls = ["velocities"]
outputs = ["hypotheses"]
params = {sampler_params}

[edges.grasps]
message = "Grasps"
queue = 4
overflow = "block"
max_payload_len = 200

[stages.selector]
exe = "selector"
inputs = ["hypotheses"]
side_inputs = ["observations"]
outputs = ["estimates"]
params = {selector_params}

[stages.grasp]
exe = "grasp"
inputs = ["estimates"]
outputs = ["grasps"]
params = {grasp_params}

[edges.next_views]
message = "NextView"
queue = 4
overflow = "block"
max_payload_len = 100

[stages.nbv]
exe = "nbv"
inputs = ["estimates"]
side_inputs = ["frames"]
outputs = ["next_views"]
params = {nbv_params}
"#,
                sampler_params = toml_inline(&sampler_params),
                selector_params = toml_inline(&selector_params),
                grasp_params = toml_inline(&grasp_params),
                nbv_params = toml_inline(&nbv_params),
            ),
    )
    .unwrap();
    let recording = scratch.dir.join("estimation.rec");
    let edges = "frames,observations,hypotheses,estimates,grasps,next_views";
    let (result, stderr) = run_recording(&graph, edges, &recording);
    for stage in ["ingest", "inference", "sampler", "selector", "grasp", "nbv"] {
        assert_eq!(result["stages"][stage]["outcome"], "finished", "{result}\n{stderr}");
    }
    for stage in ["inference", "sampler", "selector", "grasp", "nbv"] {
        assert_eq!(result["stages"][stage]["errors"], 0, "{stage}: {result}\n{stderr}");
        assert_eq!(result["stages"][stage]["dropped"], 0, "{stage}: {result}\n{stderr}");
    }

    let mut recorded: std::collections::BTreeMap<String, Vec<_>> = Default::default();
    let mut reader = RecordingReader::open(&recording).unwrap();
    while let Some(message) = reader.next_message().unwrap() {
        recorded.entry(message.edge.clone()).or_default().push(message);
    }
    let [frames, observations, hypotheses, estimates, grasps, next_views] =
        ["frames", "observations", "hypotheses", "estimates", "grasps", "next_views"]
            .map(|edge| recorded.remove(edge).unwrap_or_default());
    let counts = (observations.len(), hypotheses.len(), estimates.len(), grasps.len(), next_views.len());
    assert_eq!(counts, (3, 3, 3, 3, 3), "{result}");
    assert!(!frames.is_empty(), "{result}");

    let inference = RefCell::new(InferenceStage::with_model(PoseFlowModel::load(&model, 1).unwrap(), 8));
    let field = |request: &poseflow_contracts::VelocityRequest, poses: &[f32], out: &mut [f32]| {
        inference.borrow_mut().velocities(request, poses, out).map_err(|status| format!("status {status}"))
    };
    let mut sampler = SamplerStage::new(SamplerParams::from_json(&sampler_params).unwrap(), field);
    let mut selector = SelectorStage::new(SelectorParams::from_json(&selector_params).unwrap()).unwrap();
    let mut planner = GraspPlanner::load(GraspParams::from_json(&grasp_params).unwrap()).unwrap();
    // The nbv stage in-process, holding the recorded frames (its side
    // input) for their objects' occluders.
    let mut next_view_stage = NbvStage::new(NbvPlanner::load(NbvParams::from_json(&nbv_params).unwrap()).unwrap());
    for frame in &frames {
        let header: poseflow_contracts::FrameHeader = header_from_bytes(&frame.header).unwrap();
        next_view_stage.keep_frame(&header, &frame.payload).unwrap();
    }
    let served = observations.iter().zip(&hypotheses).zip(&estimates).zip(&grasps).zip(&next_views);
    for ((((observation, hypothesis), estimate), grasp), next_view) in served {
        let obs: ObservationHeader = header_from_bytes(&observation.header).unwrap();
        let handle = inference.borrow_mut().encode(&obs, &observation.payload).unwrap();
        let (expected_header, poses) = sampler.hypotheses(&handle).unwrap();
        let expected: Vec<f32> = poses.iter().flat_map(|p| p.to_f32_row_major()).collect();
        let served: HypothesesHeader = header_from_bytes(&hypothesis.header).unwrap();
        assert_eq!(served.header.frame_id, obs.header.frame_id);
        assert_eq!(served.header.object_id, obs.header.object_id);
        assert_eq!(
            (served.sample_count, served.step_count),
            (expected_header.sample_count, expected_header.step_count)
        );
        assert_eq!(
            hypothesis.payload, expected,
            "hypotheses of frame {} object {}",
            obs.header.frame_id, obs.header.object_id
        );

        selector.keep_observation(&obs, &observation.payload).unwrap();
        let selection = selector.select_for(&served, &hypothesis.payload).unwrap();
        let mut expected = vec![0.0; estimate_payload_len(&selection)];
        write_estimate_payload(&selection, &mut expected);
        let served: EstimateHeader = header_from_bytes(&estimate.header).unwrap();
        served.check_payload(&estimate.payload).unwrap();
        let local = estimate_header(&selection, served.header);
        assert_eq!(served, local, "estimate header of frame {}", obs.header.frame_id);
        assert_eq!(estimate.payload, expected, "estimate of frame {}", obs.header.frame_id);
        assert_eq!((served.kept_count, served.refined), (4, 1));

        // The grasp process: the same grasps as the planner in-process,
        // under the first three kept hypotheses.
        let kept = kept_hypotheses(&served, &estimate.payload).unwrap();
        let planned = planner.plan(served.header.frame_id, served.header.object_id, &kept).unwrap();
        let gripper = planner.params().gripper;
        let expected: Vec<f32> = planned.iter().flat_map(|g| grasp_values(g, &gripper)).collect();
        let grasps_header: GraspsHeader = header_from_bytes(&grasp.header).unwrap();
        grasps_header.check_payload(&grasp.payload).unwrap();
        assert_eq!((grasps_header.grasp_count, grasps_header.hypothesis_count), (6, 3));
        assert_eq!(grasps_header.header.frame_id, served.header.frame_id);
        assert_eq!(grasp.payload, expected, "grasps of frame {}", served.header.frame_id);
        for values in grasp.payload.chunks_exact(GRASP_LEN) {
            let share = values[GRASP_LEN - 2];
            assert!([0.0, 1.0 / 3.0, 2.0 / 3.0, 1.0].iter().any(|s| (s - share).abs() < 1e-6), "{share}");
        }

        // The next-best-view process: the same ranking as the stage
        // in-process (occluders from the frame), best first, chosen = first.
        let occluders = next_view_stage.occluders(served.header.frame_id, served.header.object_id);
        assert!(occluders.is_some_and(|o| !o.is_empty()), "frame {}", served.header.frame_id);
        let (expected_header, expected) = next_view_stage.next_view(&served, &estimate.payload).unwrap();
        let view: NextViewHeader = header_from_bytes(&next_view.header).unwrap();
        view.check_payload(&next_view.payload).unwrap();
        assert_eq!(view.header.frame_id, served.header.frame_id);
        assert_eq!(NextViewHeader { header: expected_header.header, ..view }, expected_header);
        assert_eq!(next_view.payload, expected, "next views of frame {}", served.header.frame_id);
        let traces: Vec<f32> = next_view.payload.chunks_exact(CANDIDATE_LEN).map(|c| c[CANDIDATE_LEN - 1]).collect();
        assert!(traces.windows(2).all(|w| w[0] <= w[1]), "{traces:?}");
        // The current viewpoint and the sphere's three.
        assert_eq!(view.candidate_count, 4);
    }
    drop(scratch);
    assert_nothing_leaked(&before);
}

/// A JSON object as a TOML inline table.
fn toml_inline(value: &serde_json::Value) -> String {
    let fields: Vec<String> = value
        .as_object()
        .unwrap()
        .iter()
        .map(|(k, v)| match v {
            serde_json::Value::String(s) => format!("{k} = {s:?}"),
            table @ serde_json::Value::Object(_) => format!("{k} = {}", toml_inline(table)),
            other => format!("{k} = {other}"),
        })
        .collect();
    format!("{{ {} }}", fields.join(", "))
}
