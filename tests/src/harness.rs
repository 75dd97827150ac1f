//! What the end-to-end test files share: launching `poseflow` and graphs
//! with the workspace's binaries, scratch directories, summaries, the
//! shared-memory leak check and the ingest graphs.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::sync::{Mutex, MutexGuard};
use std::time::{Duration, Instant};

use poseflow_smoke::SinkReport;
use poseflow_transport::shared_memory_files;

pub use crate::deadline::{OutputWithin, RUN_DEADLINE, wait_within};
use crate::plugin_python;

static SERIAL: Mutex<()> = Mutex::new(());

/// Held by each test that compares shared-memory listings before and after,
/// so such tests never overlap.
pub fn serial() -> MutexGuard<'static, ()> {
    SERIAL.lock().unwrap_or_else(|e| e.into_inner())
}

/// Where cargo put the workspace's binaries: this test runs from
/// `target/<profile>/deps/`.
pub fn bin_dir() -> PathBuf {
    let exe = std::env::current_exe().unwrap();
    exe.parent().and_then(|deps| deps.parent()).unwrap().to_path_buf()
}

/// `poseflow` and the smoke stages are built by `cargo test --workspace`.
pub fn poseflow() -> Command {
    let exe = bin_dir().join("poseflow");
    assert!(exe.exists(), "{} missing: run the tests with `cargo test --workspace`", exe.display());
    let mut command = Command::new(exe);
    command.env_remove("RUST_LOG");
    command
}

/// `poseflow run ARGS --graph GRAPH` with the workspace's stages on the
/// stage path.
pub fn run_graph(args: &[&str], graph: &Path) -> Command {
    let mut command = poseflow();
    command.arg("run").args(args).arg("--graph").arg(graph).arg("--stage-path").arg(bin_dir());
    command
}

/// `poseflow bench ARGS --json` from the repository root with the
/// workspace's stages; its report (the test fails with its log if it fails).
pub fn bench_report(args: &[&str]) -> serde_json::Value {
    let repository = Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/.."));
    let output = poseflow()
        .current_dir(repository)
        .arg("bench")
        .args(args)
        .arg("--json")
        .arg("--stage-path")
        .arg(bin_dir())
        .output_within(RUN_DEADLINE);
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(output.status.success(), "{stderr}");
    serde_json::from_slice(&output.stdout).unwrap()
}

/// Fails if a run left iceoryx2 files behind that were not there `before`.
pub fn assert_nothing_leaked(before: &BTreeSet<PathBuf>) {
    let leaked: Vec<_> = shared_memory_files().difference(before).cloned().collect();
    assert!(leaked.is_empty(), "stale iceoryx2 files: {leaked:?}");
}

#[derive(Debug)]
pub struct Scratch {
    pub dir: PathBuf,
}

impl Scratch {
    pub fn new(name: &str) -> Self {
        let dir = std::env::temp_dir().join(format!("poseflow-e2e-{name}-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        Self { dir }
    }

    /// The relay graph with this test's parameters.
    pub fn graph(&self, frames: u64, rate_hz: f64, overflow: &str) -> PathBuf {
        let text = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/graphs/relay.toml"))
            .unwrap()
            .replace("frames = 1000", &format!("frames = {frames}"))
            .replace("rate_hz = 0.0", &format!("rate_hz = {rate_hz}"))
            .replace("overflow = \"block\"", &format!("overflow = \"{overflow}\""))
            .replace("report = \"sink-report.json\"", &format!("report = \"{}\"", self.report_path().display()));
        let path = self.dir.join("relay.toml");
        std::fs::write(&path, text).unwrap();
        path
    }

    /// The relay graph (drop-oldest queues, `rate_hz`) with
    /// `tests/stages/fault_relay.rs` as the relay, failing with `fault` once
    /// at frame `at_frame` (`extra`: more params), and this heartbeat
    /// deadline.
    pub fn fault_graph(
        &self,
        (frames, rate_hz): (u64, f64),
        fault: &str,
        at_frame: u64,
        extra: &str,
        deadline_ms: u64,
    ) -> PathBuf {
        let path = self.graph(frames, rate_hz, "drop-oldest");
        let params = format!(
            "params = {{ fault = \"{fault}\", at_frame = {at_frame}, marker = \"{}\"{extra} }}",
            self.dir.join("fault-marker").display()
        );
        let text = std::fs::read_to_string(&path)
            .unwrap()
            .replace("exe = \"smoke-relay\"", &format!("exe = \"fault-relay\"\n{params}"))
            .replace("heartbeat_timeout_ms = 3000", &format!("heartbeat_timeout_ms = {deadline_ms}"));
        std::fs::write(&path, text).unwrap();
        path
    }

    pub fn report_path(&self) -> PathBuf {
        self.dir.join("sink-report.json")
    }

    pub fn report(&self) -> SinkReport {
        serde_json::from_str(&std::fs::read_to_string(self.report_path()).expect("sink wrote its report")).unwrap()
    }
}

impl Drop for Scratch {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}

pub fn summary(output: &Output) -> serde_json::Value {
    let stdout = String::from_utf8_lossy(&output.stdout);
    serde_json::from_str(&stdout).unwrap_or_else(|e| {
        panic!("summary is not JSON ({e}):\n{stdout}\nstderr:\n{}", String::from_utf8_lossy(&output.stderr))
    })
}

/// Starts `graph` as `instance` in the background and waits until its
/// stage `stage` is running; returns the launcher and the stage's pid.
pub fn start_and_wait_for(graph: &Path, instance: &str, stage: &str) -> (std::process::Child, u32) {
    let run = run_graph(&["--json", "--status-ms", "0", "--instance", instance], graph)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut run = run;
    let deadline = Instant::now() + Duration::from_secs(20);
    while Instant::now() < deadline {
        if let Some(pid) = find_stage_pid(instance, stage) {
            return (run, pid);
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    let _ = run.kill();
    let _ = run.wait();
    panic!("{stage} never started");
}

/// Processes whose stage wiring names this stage of this instance.
pub fn find_stage_pid(instance: &str, stage: &str) -> Option<u32> {
    let needle = format!("\"instance\":\"{instance}\",\"stage\":\"{stage}\"");
    std::fs::read_dir("/proc").ok()?.flatten().find_map(|entry| {
        let pid: u32 = entry.file_name().to_str()?.parse().ok()?;
        let environ = std::fs::read(entry.path().join("environ")).ok()?;
        String::from_utf8_lossy(&environ).contains(&needle).then_some(pid)
    })
}

/// Runs a graph to its end; its JSON summary and stderr, checking it
/// succeeded.
pub fn run_to_end(graph: &Path) -> (serde_json::Value, String) {
    let output = run_graph(&["--json", "--status-ms", "0"], graph).output_within(RUN_DEADLINE);
    let summary = summary(&output);
    let stderr = String::from_utf8_lossy(&output.stderr).into_owned();
    assert!(output.status.success(), "{summary}\n{stderr}");
    (summary, stderr)
}

/// The fault-injection relay's checks common to the tests where it
/// recovers: every stage finished, the sink saw nothing corrupted, traffic
/// resumed to the last frame, what was lost is counted as gaps, and each
/// restart of the relay reached the sink as one `UPSTREAM_RESTARTED` frame.
pub fn assert_recovered(summary: &serde_json::Value, report: &SinkReport, frames: u64) {
    for stage in ["source", "relay", "sink"] {
        assert_eq!(summary["stages"][stage]["outcome"], "finished", "{summary}");
    }
    assert_eq!(Some(report.restart_notices), summary["stages"]["relay"]["restarts"].as_u64(), "{report:?}");
    assert_eq!(report.corrupted, 0, "{report:?}");
    assert_eq!(report.intact, report.received, "{report:?}");
    assert_eq!(report.last_frame, Some(frames - 1), "traffic did not resume: {report:?}");
    assert_eq!(report.received + report.gaps, frames - report.first_frame.unwrap(), "{report:?}");
}

/// The `frames` stage reading the bad-input corpus.
pub fn corpus_frames() -> String {
    let corpus = concat!(env!("CARGO_MANIFEST_DIR"), "/corpus/ingest");
    format!("exe = \"frame-source\"\nparams = {{ source = \"bop\", dataset = \"{corpus}\", split = \"test\" }}")
}

/// The `[graph]` table and the frames and observations edges of a test
/// graph whose observations hold up to `observation_payload` values.
pub fn graph_head(name: &str, observation_payload: usize) -> String {
    format!(
        r#"
[graph]
name = "{name}"
heartbeat_ms = 100

[edges.frames]
message = "Frame"
queue = 2
overflow = "block"
max_payload_len = 100000

[edges.observations]
message = "Observation"
queue = 4
overflow = "block"
max_payload_len = {observation_payload}
"#
    )
}

/// A graph `frames` → [detector →] ingest, with `frames` the body of the
/// frames stage (exe and params) and `detector` a Python detector plug-in
/// and its params.
pub fn ingest_graph(scratch: &Scratch, name: &str, frames: &str, detector: Option<(&str, &str)>) -> PathBuf {
    let mut text = graph_head("ingest-corpus", 12_000);
    text += &format!(
        r#"
[stages.frames]
outputs = ["frames"]
{frames}

[stages.ingest]
exe = "ingest"
inputs = ["{ingest_input}"]
outputs = ["observations"]
params = {{ image_size = 56, patch_grid = 4, point_count = 64 }}
"#,
        ingest_input = if detector.is_some() { "detected" } else { "frames" }
    );
    if let Some((plugin, params)) = detector {
        text += &format!(
            r#"
[edges.detected]
message = "Frame"
queue = 2
overflow = "block"
max_payload_len = 100000

[stages.detector]
exe = "{python}"
args = ["{plugin}"]
inputs = ["frames"]
outputs = ["detected"]
params = {params}
"#,
            python = plugin_python().display()
        );
    }
    let graph = scratch.dir.join(name);
    std::fs::write(&graph, text).unwrap();
    graph
}

/// Runs `graph` recording its edge `edge` into `recording`; returns the
/// summary and the launcher's stderr after checking that it succeeded.
pub fn run_recording(graph: &Path, edge: &str, recording: &Path) -> (serde_json::Value, String) {
    let args = ["--json", "--status-ms", "0", "--record", recording.to_str().unwrap(), "--record-edges", edge];
    let output = run_graph(&args, graph).output_within(RUN_DEADLINE);
    let result = summary(&output);
    let stderr = String::from_utf8_lossy(&output.stderr).into_owned();
    assert!(output.status.success(), "{result}\n{stderr}");
    (result, stderr)
}

/// Observation object ids of a recording, checking every message.
pub fn recorded_observations(recording: &Path) -> Vec<(u64, u32)> {
    use poseflow_contracts::ObservationHeader;
    use poseflow_runtime::recording::{RecordingReader, header_from_bytes};

    let mut reader = RecordingReader::open(recording).unwrap();
    let mut objects = Vec::new();
    while let Some(message) = reader.next_message().unwrap() {
        let header: ObservationHeader = header_from_bytes(&message.header).unwrap();
        let view = header.view(&message.payload).expect("payload matches its header");
        let mean_x = view.points.chunks_exact(3).map(|p| p[0]).sum::<f32>() / header.point_count as f32;
        assert!(mean_x.abs() < 1e-5, "points centred: {mean_x}");
        assert!(view.token_mask.contains(&1.0));
        objects.push((header.header.frame_id, header.header.object_id));
    }
    objects
}
