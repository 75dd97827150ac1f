//! ROS 2 in and out, checked by an independent ROS 2 client: the PyPI
//! `zenoh-ros2-sdk` (rmw_zenoh's key expressions, type hashes computed from
//! the vendored `.msg` files, CDR through `rosbags`) runs as a peer
//! (`tests/ros2/ros2_peer.py`) that the graphs' ROS 2 stages connect to on
//! loopback.

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};

use poseflow_contracts::{EstimateHeader, StampSlot};
use poseflow_e2e::harness::*;
use poseflow_e2e::plugin_python;
use poseflow_e2e::recordings::recorded_messages;
use poseflow_geometry::Pose;
use poseflow_runtime::recording::{RecordingReader, header_from_bytes};
use poseflow_transport::shared_memory_files;

fn repository() -> PathBuf {
    PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/.."))
}

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port()
}

/// deploy/ros2.toml with its ROS 2 stages connecting to `endpoint` and
/// the camera stage's table replaced by `camera` (when given); written
/// into `scratch` with absolute config paths.
fn ros2_graph(scratch: &Scratch, name: &str, endpoint: &str, camera: Option<&str>) -> PathBuf {
    let mut text = std::fs::read_to_string(repository().join("deploy/ros2.toml")).unwrap();
    let config = repository().join("config");
    text = text.replace("\"../config/", &format!("\"{}/", config.display()));
    text = text.replace("connect = [\"tcp/localhost:7447\"]", &format!("connect = [\"{endpoint}\"]"));
    if let Some(camera) = camera {
        let (start, end) = (text.find("[stages.camera]").unwrap(), text.find("[stages.ingest]").unwrap());
        text.replace_range(start..end, &format!("[stages.camera]\n{camera}\n\n"));
    }
    let graph = scratch.dir.join(name);
    std::fs::write(&graph, text).unwrap();
    graph
}

/// The ROS 2 peer, listening on `endpoint`, started and subscribed.
fn start_peer(endpoint: &str, out: &Path, extra: &[&str]) -> Child {
    let mut command = Command::new(plugin_python());
    command
        .arg(repository().join("tests/ros2/ros2_peer.py"))
        .args(["--endpoint", endpoint, "--out", out.to_str().unwrap(), "--timeout", "240"])
        .arg("--msgs")
        .arg(repository().join("tests/data/ros2-msgs"))
        .args(extra)
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit());
    let mut peer = command.spawn().unwrap();
    let mut line = String::new();
    BufReader::new(peer.stdout.as_mut().unwrap()).read_line(&mut line).unwrap();
    assert_eq!(line.trim(), "ready", "the ROS 2 peer did not start");
    peer
}

/// What the peer received, once it exited.
fn peer_report(peer: Child, out: &Path) -> serde_json::Value {
    let output = wait_within(peer, RUN_DEADLINE);
    assert!(output.status.success(), "ROS 2 peer: {}", String::from_utf8_lossy(&output.stdout));
    serde_json::from_str(&std::fs::read_to_string(out).unwrap()).unwrap()
}

/// The Estimates of a recording.
fn estimates(recording: &Path) -> Vec<(EstimateHeader, Vec<f32>)> {
    let mut reader = RecordingReader::open(recording).unwrap();
    let mut out = Vec::new();
    while let Some(message) = reader.next_message().unwrap() {
        out.push((header_from_bytes(&message.header).unwrap(), message.payload));
    }
    out
}

fn run_recorded(graph: &Path, recording: &Path, extra: &[&str]) -> serde_json::Value {
    let mut args =
        vec!["--json", "--status-ms", "0", "--record", recording.to_str().unwrap(), "--record-edges", "estimates"];
    args.extend_from_slice(extra);
    let output = run_graph(&args, graph).current_dir(repository()).output_within(RUN_DEADLINE);
    let result = summary(&output);
    assert!(output.status.success(), "{result}\n{}", String::from_utf8_lossy(&output.stderr));
    result
}

/// Less work for the unoptimised test build.
const COARSE: [&str; 2] = ["--set", "selector.sdf_resolution=16"];

/// Every Estimate of a rendered scene reaches the ROS 2 client as the
/// object's PoseWithCovarianceStamped (pose, stamp from the frame, the
/// covariance of the kept hypotheses in ROS's convention) and PoseArray.
#[test]
fn a_ros2_client_receives_every_estimate_as_pose_and_hypotheses() {
    let _serial = serial();
    let before = shared_memory_files();
    let scratch = Scratch::new("ros2-poses");
    let endpoint = format!("tcp/127.0.0.1:{}", free_port());
    let frames = r#"exe = "frame-source"
outputs = ["frames"]
params = { source = "synthetic", models = "objects/lmo", objects = [1, 11], frames_per_scene = 2, width = 320, height = 240 }"#;
    let graph = ros2_graph(&scratch, "poses.toml", &endpoint, Some(frames));
    let out = scratch.dir.join("peer.json");
    let peer = start_peer(&endpoint, &out, &["--objects", "1,11", "--expect", "4"]);
    let recording = scratch.dir.join("estimates.rec");
    let summary = run_recorded(&graph, &recording, &COARSE);
    assert_eq!(summary["stages"]["poses"]["total"]["errors"], 0, "{summary}");
    let report = peer_report(peer, &out);

    let recorded = estimates(&recording);
    assert_eq!(recorded.len(), 4, "two objects in two frames");
    let poses = report["poses"].as_array().unwrap();
    let arrays = report["arrays"].as_array().unwrap();
    assert_eq!((poses.len(), arrays.len()), (recorded.len(), recorded.len()), "{report}");
    for (header, payload) in &recorded {
        let stamp = header.header.stamps.get(StampSlot::Source).unwrap();
        let topic = format!("/poseflow/obj_{:06}/pose", header.header.object_id);
        let pose = poses
            .iter()
            .find(|p| p["topic"] == topic.as_str() && p["stamp_ns"] == stamp)
            .unwrap_or_else(|| panic!("no {topic} stamped {stamp}: {report}"));
        assert_eq!(pose["frame_id"], "camera_color_optical_frame");
        let best = Pose::from_f32_row_major(&header.best).unwrap();
        let position: Vec<f64> = serde_json::from_value(pose["position"].clone()).unwrap();
        for (a, b) in position.iter().zip(best.translation.iter()) {
            assert!((a - b).abs() < 1e-12, "position {position:?} vs {:?}", best.translation);
        }
        let q: Vec<f64> = serde_json::from_value(pose["orientation"].clone()).unwrap();
        let rotation = poseflow_geometry::nalgebra::UnitQuaternion::from_quaternion(
            poseflow_geometry::nalgebra::Quaternion::new(q[3], q[0], q[1], q[2]),
        );
        let angle = poseflow_geometry::so3::geodesic_angle(&rotation.to_rotation_matrix(), &best.rotation);
        assert!(angle < 1e-9, "orientation {q:?}: {angle} rad from the Estimate's");
        let kept: Vec<Pose> =
            header.kept_poses(payload).unwrap().map(|p| Pose::from_f32_row_major(p).unwrap()).collect();
        let expected = poseflow_ros2::poses::ros_covariance(&best, &kept);
        let covariance: Vec<f64> = serde_json::from_value(pose["covariance"].clone()).unwrap();
        for (a, b) in covariance.iter().zip(&expected) {
            // The JSON between the client and this test keeps ~16 digits.
            assert!((a - b).abs() <= 1e-12 * b.abs(), "covariance of object {}: {a} vs {b}", header.header.object_id);
        }
        assert!(covariance[0] > 0.0 && covariance[35] > 0.0, "{covariance:?}");
        let topic = format!("/poseflow/obj_{:06}/hypotheses", header.header.object_id);
        let array = arrays.iter().find(|a| a["topic"] == topic.as_str() && a["stamp_ns"] == stamp).unwrap();
        assert_eq!(array["poses"].as_array().unwrap().len(), kept.len());
    }
    drop(scratch);
    assert_nothing_leaked(&before);
}

/// A rendered BOP sequence played as a ROS 2 camera (colour, 32FC1 depth,
/// CameraInfo, a label image) gives the Estimates of the BOP frame source
/// on the same files, bit for bit, and the poses come back on ROS 2 with
/// the images' own stamps.
#[test]
fn a_ros2_camera_gives_the_bop_frame_source_estimates() {
    let _serial = serial();
    let before = shared_memory_files();
    let scratch = Scratch::new("ros2-camera");
    let dataset = scratch.dir.join("bop");
    let rendered = poseflow()
        .args(["render", "--models", "objects/lmo", "--objects", "1,11", "--frames-per-scene", "2"])
        .args(["--width", "320", "--height", "240", "--out", dataset.to_str().unwrap()])
        .current_dir(repository())
        .output_within(RUN_DEADLINE);
    assert!(rendered.status.success(), "{}", String::from_utf8_lossy(&rendered.stderr));

    let endpoint = format!("tcp/127.0.0.1:{}", free_port());
    let bop = format!(
        "exe = \"frame-source\"\noutputs = [\"frames\"]\nparams = {{ source = \"bop\", dataset = \"{}\", split = \"train\" }}",
        dataset.display()
    );
    let reference = scratch.dir.join("bop.rec");
    run_recorded(&ros2_graph(&scratch, "bop.toml", &endpoint, Some(&bop)), &reference, &COARSE);

    let graph = ros2_graph(&scratch, "camera.toml", &endpoint, None);
    let out = scratch.dir.join("peer.json");
    let split = dataset.join("train");
    let peer = start_peer(&endpoint, &out, &["--objects", "1,11", "--expect", "4", "--play", split.to_str().unwrap()]);
    let recording = scratch.dir.join("camera.rec");
    let stop = ["--set", "camera.max_frames=2", "--set", "camera.queue=8"];
    let summary = run_recorded(&graph, &recording, &[&COARSE[..], &stop].concat());
    assert_eq!(summary["stages"]["camera"]["total"]["errors"], 0, "unpaired or refused messages: {summary}");
    let report = peer_report(peer, &out);

    let (reference, camera) = (recorded_messages(&reference), recorded_messages(&recording));
    let (reference, camera) = (&reference["estimates"], &camera["estimates"]);
    assert_eq!(reference.len(), 4, "two objects in two frames");
    assert_eq!(camera.len(), reference.len());
    for (i, (a, b)) in reference.iter().zip(camera).enumerate() {
        assert!(a == b, "estimate {i} differs between the BOP frame source and the ROS 2 camera");
    }
    let published: Vec<u64> = serde_json::from_value(report["published"].clone()).unwrap();
    let mut stamps: Vec<u64> =
        report["poses"].as_array().unwrap().iter().map(|p| p["stamp_ns"].as_u64().unwrap()).collect();
    stamps.sort_unstable();
    stamps.dedup();
    assert_eq!(stamps, published, "poses stamped with their images' stamps");
    drop(scratch);
    assert_nothing_leaked(&before);
}
