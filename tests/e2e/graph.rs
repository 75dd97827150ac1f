//! Whole graphs of real processes over real iceoryx2 shared memory, launched
//! by `poseflow run`.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::sync::Mutex;
use std::time::{Duration, Instant};

use poseflow_e2e::plugin_python;
use poseflow_smoke::SinkReport;
use poseflow_transport::shared_memory_files;

/// Tests here compare shared-memory listings before and after, so they must
/// not overlap.
static SERIAL: Mutex<()> = Mutex::new(());

/// Where cargo put the workspace's binaries: this test runs from
/// `target/<profile>/deps/`.
fn bin_dir() -> PathBuf {
    let exe = std::env::current_exe().unwrap();
    exe.parent().and_then(|deps| deps.parent()).unwrap().to_path_buf()
}

/// `poseflow` and the smoke stages are built by `cargo test --workspace`.
fn poseflow() -> Command {
    let exe = bin_dir().join("poseflow");
    assert!(exe.exists(), "{} missing: run the tests with `cargo test --workspace`", exe.display());
    let mut command = Command::new(exe);
    command.env_remove("RUST_LOG");
    command
}

/// `poseflow run ARGS --graph GRAPH` with the workspace's stages on the
/// stage path.
fn run_graph(args: &[&str], graph: &Path) -> Command {
    let mut command = poseflow();
    command.arg("run").args(args).arg("--graph").arg(graph).arg("--stage-path").arg(bin_dir());
    command
}

/// `poseflow bench ARGS --json` from the repository root with the
/// workspace's stages; its report (the test fails with its log if it fails).
fn bench_report(args: &[&str]) -> serde_json::Value {
    let repository = Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/.."));
    let output = poseflow()
        .current_dir(repository)
        .arg("bench")
        .args(args)
        .arg("--json")
        .arg("--stage-path")
        .arg(bin_dir())
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(output.status.success(), "{stderr}");
    serde_json::from_slice(&output.stdout).unwrap()
}

/// Fails if a run left iceoryx2 files behind that were not there `before`.
fn assert_nothing_leaked(before: &BTreeSet<PathBuf>) {
    let leaked: Vec<_> = shared_memory_files().difference(before).cloned().collect();
    assert!(leaked.is_empty(), "stale iceoryx2 files: {leaked:?}");
}

struct Scratch {
    dir: PathBuf,
}

impl Scratch {
    fn new(name: &str) -> Self {
        let dir = std::env::temp_dir().join(format!("poseflow-e2e-{name}-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        Self { dir }
    }

    /// The relay graph with this test's parameters.
    fn graph(&self, frames: u64, rate_hz: f64, overflow: &str) -> PathBuf {
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
    fn fault_graph(
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

    fn report_path(&self) -> PathBuf {
        self.dir.join("sink-report.json")
    }

    fn report(&self) -> SinkReport {
        serde_json::from_str(&std::fs::read_to_string(self.report_path()).expect("sink wrote its report")).unwrap()
    }
}

impl Drop for Scratch {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}

fn summary(output: &Output) -> serde_json::Value {
    let stdout = String::from_utf8_lossy(&output.stdout);
    serde_json::from_str(&stdout).unwrap_or_else(|e| {
        panic!("summary is not JSON ({e}):\n{stdout}\nstderr:\n{}", String::from_utf8_lossy(&output.stderr))
    })
}

#[test]
fn three_processes_pass_every_frame_intact() {
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let before = shared_memory_files();
    let scratch = Scratch::new("intact");
    let graph = scratch.graph(1000, 0.0, "block");
    let output = run_graph(&["--json", "--status-ms", "0"], &graph).output().unwrap();
    let summary = summary(&output);
    assert!(output.status.success(), "{summary}");
    for stage in ["source", "relay", "sink"] {
        assert_eq!(summary["stages"][stage]["outcome"], "finished", "{summary}");
        assert_eq!(summary["stages"][stage]["restarts"], 0, "{summary}");
    }
    assert_eq!(summary["stages"]["relay"]["frames_in"], 1000, "{summary}");
    for edge in ["raw", "negated"] {
        let flow = &summary["edges"][edge];
        assert_eq!((flow["sent"].as_u64(), flow["lost"].as_u64()), (Some(1000), Some(0)), "{summary}");
    }

    // Back-pressure ("block") loses nothing: every frame, intact, in order.
    let report = scratch.report();
    assert_eq!(report.received, 1000, "{report:?}");
    assert_eq!(report.intact, 1000);
    assert_eq!(report.relayed, 1000);
    assert_eq!((report.first_frame, report.last_frame, report.gaps), (Some(0), Some(999), 0));

    assert_nothing_leaked(&before);
}

/// Starts `graph` as `instance` in the background and waits until its
/// stage `stage` is running; returns the launcher and the stage's pid.
fn start_and_wait_for(graph: &Path, instance: &str, stage: &str) -> (std::process::Child, u32) {
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
fn find_stage_pid(instance: &str, stage: &str) -> Option<u32> {
    let needle = format!("\"instance\":\"{instance}\",\"stage\":\"{stage}\"");
    std::fs::read_dir("/proc").ok()?.flatten().find_map(|entry| {
        let pid: u32 = entry.file_name().to_str()?.parse().ok()?;
        let environ = std::fs::read(entry.path().join("environ")).ok()?;
        String::from_utf8_lossy(&environ).contains(&needle).then_some(pid)
    })
}

#[test]
fn a_killed_stage_is_restarted_and_traffic_resumes() {
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let before = shared_memory_files();
    let scratch = Scratch::new("kill");
    // 1,500 frames at 500 Hz: three seconds of traffic; drop-oldest so the
    // source never waits for the dead relay.
    let graph = scratch.graph(1500, 500.0, "drop-oldest");
    let instance = format!("kill-{}", std::process::id());
    let (run, relay) = start_and_wait_for(&graph, &instance, "relay");
    // Let traffic flow for a moment, then kill the relay mid-stream.
    std::thread::sleep(Duration::from_millis(800));
    // SAFETY: signalling a process this test started (through poseflow).
    assert_eq!(unsafe { libc::kill(relay as i32, libc::SIGKILL) }, 0);

    let output = run.wait_with_output().unwrap();
    let summary = summary(&output);
    assert!(output.status.success(), "{summary}\n{}", String::from_utf8_lossy(&output.stderr));
    let relay_summary = &summary["stages"]["relay"];
    assert_eq!(relay_summary["restarts"], 1, "{summary}");
    let latency = relay_summary["restart_latency_ms"][0].as_f64().unwrap();
    eprintln!("relay restarted {latency:.0} ms after its death was noticed");
    for stage in ["source", "relay", "sink"] {
        assert_eq!(summary["stages"][stage]["outcome"], "finished", "{summary}");
    }

    // Nothing corrupted; what was lost while the relay was down is counted;
    // traffic resumed up to the last frame.
    let report = scratch.report();
    assert_eq!(report.corrupted, 0, "{report:?}");
    assert_eq!(report.intact, report.received);
    assert_eq!(report.last_frame, Some(1499), "traffic did not resume: {report:?}");
    let first = report.first_frame.unwrap();
    assert_eq!(report.received + report.gaps, 1500 - first, "{report:?}");
    assert_eq!(report.restart_notices, 1, "the sink was told of the restart: {report:?}");
    eprintln!("sink: {report:?}");

    assert_nothing_leaked(&before);
}

/// Runs a graph to its end; its JSON summary and stderr, checking it
/// succeeded.
fn run_to_end(graph: &Path) -> (serde_json::Value, String) {
    let output = run_graph(&["--json", "--status-ms", "0"], graph).output().unwrap();
    let summary = summary(&output);
    let stderr = String::from_utf8_lossy(&output.stderr).into_owned();
    assert!(output.status.success(), "{summary}\n{stderr}");
    (summary, stderr)
}

/// The fault-injection relay's checks common to the tests where it
/// recovers: every stage finished, the sink saw nothing corrupted, traffic
/// resumed to the last frame, what was lost is counted as gaps, and each
/// restart of the relay reached the sink as one `UPSTREAM_RESTARTED` frame.
fn assert_recovered(summary: &serde_json::Value, report: &SinkReport, frames: u64) {
    for stage in ["source", "relay", "sink"] {
        assert_eq!(summary["stages"][stage]["outcome"], "finished", "{summary}");
    }
    assert_eq!(Some(report.restart_notices), summary["stages"]["relay"]["restarts"].as_u64(), "{report:?}");
    assert_eq!(report.corrupted, 0, "{report:?}");
    assert_eq!(report.intact, report.received, "{report:?}");
    assert_eq!(report.last_frame, Some(frames - 1), "traffic did not resume: {report:?}");
    assert_eq!(report.received + report.gaps, frames - report.first_frame.unwrap(), "{report:?}");
}

/// A relay that panics in the middle of a frame (input taken, nothing
/// emitted) is restarted with backoff; the sink sees no corrupted frame.
#[test]
fn a_stage_crashing_mid_frame_is_restarted_and_nothing_corrupted_passes() {
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let before = shared_memory_files();
    let scratch = Scratch::new("crash");
    let (summary, stderr) = run_to_end(&scratch.fault_graph((1500, 500.0), "crash", 300, "", 3000));
    assert!(stderr.contains("injected crash at frame 300"), "{stderr}");
    assert_eq!(summary["stages"]["relay"]["restarts"], 1, "{summary}");
    let report = scratch.report();
    assert_recovered(&summary, &report, 1500);
    // The summary counts the relay's frames over both its processes: the
    // restarted one alone did not send all the sink received; with the
    // first one's counts (up to its last heartbeat, 100 ms = 50 frames
    // before the crash) they account for it.
    let relay = &summary["stages"]["relay"];
    let (all_out, last_out) = (relay["total"]["frames_out"].as_u64().unwrap(), relay["frames_out"].as_u64().unwrap());
    assert!(last_out < report.received && last_out < all_out, "{summary}\n{report:?}");
    assert!(report.received <= all_out + 100, "{summary}\n{report:?}");
    eprintln!("crash: {report:?}, restart latency {} ms", summary["stages"]["relay"]["restart_latency_ms"][0]);
    assert_nothing_leaked(&before);
}

/// A relay stuck in one frame is found by its heartbeat deadline
/// (`heartbeat_timeout_ms`), killed and restarted; traffic resumes.
#[test]
fn a_hung_stage_is_killed_at_its_heartbeat_deadline_and_restarted() {
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let before = shared_memory_files();
    let scratch = Scratch::new("hang");
    let (summary, stderr) = run_to_end(&scratch.fault_graph((2500, 500.0), "hang", 300, "", 1000));
    let relay = &summary["stages"]["relay"];
    assert_eq!((relay["hangs"].as_u64(), relay["restarts"].as_u64()), (Some(1), Some(1)), "{summary}");
    assert!(stderr.contains("busy in one message longer than graph.heartbeat_timeout_ms"), "{stderr}");
    let report = scratch.report();
    assert_recovered(&summary, &report, 2500);
    assert!(report.gaps > 0, "frames were lost while the relay hung: {report:?}");
    eprintln!("hang: {report:?}, restart latency {} ms", relay["restart_latency_ms"][0]);
    assert_nothing_leaked(&before);
}

/// As above with blocking queues: the source is held back by the hung
/// relay's full queue when the relay is killed; once the supervisor has
/// removed the dead reader's port, the source's send stops waiting for it
/// and traffic resumes through the restarted relay.
#[test]
fn a_writer_blocked_on_a_killed_reader_carries_on() {
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let before = shared_memory_files();
    let scratch = Scratch::new("hang-block");
    let graph = scratch.fault_graph((1500, 500.0), "hang", 300, "", 1000);
    let text = std::fs::read_to_string(&graph).unwrap().replace("\"drop-oldest\"", "\"block\"");
    std::fs::write(&graph, text).unwrap();
    let (summary, stderr) = run_to_end(&graph);
    assert_eq!(summary["stages"]["relay"]["hangs"], 1, "{summary}");
    assert!(stderr.contains("busy in one message longer than graph.heartbeat_timeout_ms"), "{stderr}");
    let report = scratch.report();
    assert_recovered(&summary, &report, 1500);
    eprintln!("blocked writer: {report:?}");
    assert_nothing_leaked(&before);
}

/// At shutdown, a stage that ignores SIGTERM (and is stuck) is SIGKILLed
/// after the grace period, reported as such, and leaves nothing behind;
/// the others stop normally.
#[test]
fn a_stage_ignoring_sigterm_is_killed_after_the_grace_period() {
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let before = shared_memory_files();
    let scratch = Scratch::new("sigterm");
    // A long stream and a generous heartbeat deadline: only shutdown ends
    // the stuck relay.
    let graph = scratch.fault_graph((1_000_000, 200.0), "ignore-sigterm", 50, "", 60_000);
    let instance = format!("sigterm-{}", std::process::id());
    let (run, _) = start_and_wait_for(&graph, &instance, "sink");
    let marker = scratch.dir.join("fault-marker");
    let waiting = Instant::now();
    while !marker.exists() && waiting.elapsed() < Duration::from_secs(20) {
        std::thread::sleep(Duration::from_millis(50));
    }
    assert!(marker.exists(), "the relay never reached its faulty frame");
    std::thread::sleep(Duration::from_millis(300));
    let stopping = Instant::now();
    // SAFETY: signalling the poseflow process this test started.
    assert_eq!(unsafe { libc::kill(run.id() as i32, libc::SIGINT) }, 0);
    let output = run.wait_with_output().unwrap();
    let stopped_after = stopping.elapsed();
    let summary = summary(&output);
    assert!(output.status.success(), "{summary}");
    assert_eq!(summary["stages"]["relay"]["killed_at_stop"], true, "{summary}");
    for stage in ["source", "sink"] {
        assert_eq!(summary["stages"][stage]["killed_at_stop"], false, "{summary}");
    }
    for stage in ["source", "relay", "sink"] {
        assert_eq!(summary["stages"][stage]["outcome"], "stopped", "{summary}");
        assert!(find_stage_pid(&instance, stage).is_none(), "{stage} still running");
    }
    // The grace period (5 s) passed before the SIGKILL.
    assert!(stopped_after >= Duration::from_secs(5), "{stopped_after:?}");
    eprintln!("sigterm ignored: the graph stopped {stopped_after:?} after SIGINT");
    assert_eq!(scratch.report().corrupted, 0);
    assert_nothing_leaked(&before);
}

/// A relay that floods its bounded, drop-oldest output queue (100 copies of
/// every frame from frame 100 on): the queue stays bounded, the sink
/// receives fewer messages than were sent (the difference is counted: the
/// relay's frames out minus the sink's frames in) and none corrupted.
#[test]
fn a_flooding_stage_overflows_a_bounded_queue_with_counted_losses() {
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let before = shared_memory_files();
    let scratch = Scratch::new("flood");
    let (summary, _) = run_to_end(&scratch.fault_graph((400, 200.0), "flood", 100, ", copies = 100", 3000));
    let relay_out = summary["stages"]["relay"]["frames_out"].as_u64().unwrap();
    let sink_in = summary["stages"]["sink"]["frames_in"].as_u64().unwrap();
    // Frames 0–99 once, 100–399 a hundred times each.
    assert_eq!(relay_out, 100 + 300 * 100, "{summary}");
    let report = scratch.report();
    assert_eq!(report.received, sink_in, "{summary}");
    assert!(sink_in < relay_out, "nothing overflowed: {summary}");
    // The launcher counts the loss on the edge.
    let negated = &summary["edges"]["negated"];
    assert_eq!(
        (negated["sent"].as_u64(), negated["lost"].as_u64()),
        (Some(relay_out), Some(relay_out - sink_in)),
        "{summary}"
    );
    eprintln!("flood: relay sent {relay_out}, sink received {sink_in}, {} lost in the queue", relay_out - sink_in);
    assert_eq!((report.corrupted, report.last_frame), (0, Some(399)), "{report:?}");
    assert_nothing_leaked(&before);
}

#[test]
fn an_invalid_graph_is_rejected_before_anything_starts() {
    let scratch = Scratch::new("invalid");
    let graph = scratch.graph(10, 0.0, "block");
    let text =
        std::fs::read_to_string(&graph).unwrap().replace("inputs = [\"raw\"]", "inputs = [\"raw\", \"missing\"]");
    std::fs::write(&graph, text).unwrap();
    let output = run_graph(&[], &graph).output().unwrap();
    assert!(!output.status.success());
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(
        stderr.contains("relay.toml") && stderr.contains("`stages.relay.inputs`") && stderr.contains("\"missing\""),
        "{stderr}"
    );
}

#[test]
fn a_python_stage_replaces_a_rust_one() {
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let before = shared_memory_files();
    let scratch = Scratch::new("python");
    let graph = scratch.graph(500, 0.0, "block");
    let plugin = concat!(env!("CARGO_MANIFEST_DIR"), "/../plugins/python/negating_relay.py");
    let text = std::fs::read_to_string(&graph)
        .unwrap()
        .replace("exe = \"smoke-relay\"", &format!("exe = \"{}\"\nargs = [\"{plugin}\"]", plugin_python().display()));
    std::fs::write(&graph, text).unwrap();
    let output = run_graph(&["--json", "--status-ms", "0"], &graph).output().unwrap();
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
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
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

#[test]
fn ctrl_c_stops_every_stage_and_leaves_nothing_behind() {
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let before = shared_memory_files();
    let scratch = Scratch::new("sigint");
    // A stream far longer than the test: only SIGINT ends it.
    let graph = scratch.graph(1_000_000, 200.0, "drop-oldest");
    let instance = format!("sigint-{}", std::process::id());
    let (run, _) = start_and_wait_for(&graph, &instance, "sink");
    std::thread::sleep(Duration::from_millis(500));
    // SAFETY: signalling the poseflow process this test started.
    assert_eq!(unsafe { libc::kill(run.id() as i32, libc::SIGINT) }, 0);

    let output = run.wait_with_output().unwrap();
    let summary = summary(&output);
    assert!(output.status.success(), "{summary}");
    for stage in ["source", "relay", "sink"] {
        assert_eq!(summary["stages"][stage]["outcome"], "stopped", "{summary}");
        assert!(find_stage_pid(&instance, stage).is_none(), "{stage} still running");
    }
    // The sink finished normally on SIGTERM and wrote what it had seen.
    let report = scratch.report();
    assert!(report.received > 0 && report.corrupted == 0, "{report:?}");
    assert_nothing_leaked(&before);
}

#[test]
fn a_stage_failing_beyond_its_restart_policy_fails_the_graph() {
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let before = shared_memory_files();
    let scratch = Scratch::new("failing");
    let graph = scratch.graph(1_000_000, 200.0, "drop-oldest");
    // A "relay" that dies at once, every time.
    let text = std::fs::read_to_string(&graph)
        .unwrap()
        .replace("exe = \"smoke-relay\"", "exe = \"/bin/false\"\nmax_restarts = 2")
        .replace("backoff_ms = 100", "backoff_ms = 10");
    std::fs::write(&graph, text).unwrap();
    let output = run_graph(&["--json", "--status-ms", "0"], &graph).output().unwrap();
    assert_eq!(output.status.code(), Some(1));
    let summary = summary(&output);
    assert_eq!(summary["failed"], true);
    let relay = &summary["stages"]["relay"];
    assert_eq!(relay["outcome"], "failed", "{summary}");
    assert_eq!(relay["restarts"], 2, "{summary}");
    assert!(relay["failure"].as_str().unwrap().contains("max_restarts"), "{summary}");
    assert_eq!(summary["stages"]["source"]["outcome"], "stopped", "{summary}");
    assert_nothing_leaked(&before);
}

/// Every graph shipped in deploy/ validates, and the smoke graph runs clean.
#[test]
fn deploy_graphs_are_valid_and_the_smoke_graph_runs() {
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let deploy = Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/../deploy"));
    for entry in std::fs::read_dir(deploy).unwrap().flatten() {
        let path = entry.path();
        if path.extension().is_some_and(|e| e == "toml") {
            let output = run_graph(&["--check"], &path).output().unwrap();
            assert!(output.status.success(), "{}: {}", path.display(), String::from_utf8_lossy(&output.stderr));
        }
    }
    let before = shared_memory_files();
    let output = run_graph(&["--json", "--status-ms", "0"], &deploy.join("smoke.toml")).output().unwrap();
    let summary = summary(&output);
    assert!(output.status.success(), "{summary}");
    assert_eq!(summary["stages"]["source"]["frames_out"], 3000, "{summary}");
    assert_eq!(summary["stages"]["sink"]["errors"], 0, "{summary}");
    assert_nothing_leaked(&before);
}

/// `poseflow bench soak`, short: the tracking graph on the default model
/// with every stage SIGKILLed once; each comes back, no estimate is
/// corrupted, nothing is left in shared memory, and the report has memory
/// samples of every process.
#[test]
fn a_short_soak_of_the_tracking_graph_survives_a_kill_of_every_stage() {
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let scratch = Scratch::new("soak");
    let out = scratch.dir.to_str().unwrap();
    let report = bench_report(&[
        "soak",
        "--out",
        out,
        "--duration-s",
        "42",
        "--kill-every-s",
        "6",
        "--sample-every-s",
        "3",
        // The selector twice: its restart once deadlocked the tracking loop
        // (the sampler blocked on the selector's full queue, the restarted
        // selector waiting for the sampler's handshake before reading).
        "--kill",
        "selector,sampler,selector,inference,ingest,frames",
        "--warmup-s",
        "5",
        "--set",
        "frames.frames_per_scene=100000",
        "--set",
        "frames.orbit_step_deg=2",
    ]);
    assert_eq!(report["ended_early"], serde_json::Value::Null, "{report}");
    let stages = ["frames", "inference", "ingest", "sampler", "selector"];
    let killed: Vec<&str> = report["kills"].as_array().unwrap().iter().map(|k| k["stage"].as_str().unwrap()).collect();
    assert_eq!(killed, ["selector", "sampler", "selector", "inference", "ingest", "frames"], "in --kill order");
    for stage in stages {
        let kills = if stage == "selector" { 2 } else { 1 };
        assert_eq!(report["stages"][stage]["restarts"], kills, "{stage}: {report}");
    }
    let estimates = &report["estimates"];
    assert_eq!(estimates["corrupted"], 0, "{report}");
    assert!(estimates["checked"].as_u64().unwrap() > 0 && estimates["tracked"].as_u64().unwrap() > 0, "{report}");
    assert!(estimates["restart_notices"].as_u64().unwrap() > 0, "downstream was told: {report}");
    // Estimates kept coming after every kill.
    let between = estimates["between_kills"].as_array().unwrap();
    assert_eq!(between.len(), 7, "{report}");
    if !between.iter().all(|n| n.as_u64().unwrap() > 0) {
        // The stages' own account of the stall, for a failure seen only in CI.
        let log = std::fs::read_to_string(scratch.dir.join("run.log")).unwrap_or_default();
        let warnings: Vec<&str> = log.lines().filter(|l| !l.contains(" DEBUG ") && !l.contains(" TRACE ")).collect();
        panic!("the graph stalled: {report}\nthe run's log:\n{}", warnings.join("\n"));
    }
    assert_eq!(report["leaked_shared_memory_files"], 0, "{report}");
    let samples = report["rss_mib"]["samples"].as_array().unwrap();
    assert!(samples.len() >= 10, "{report}");
    let last = samples.last().unwrap();
    for process in stages.iter().chain(&["supervisor"]) {
        assert!(last[process].as_f64().is_some_and(|mib| mib > 1.0), "{process}: {last}");
    }
    eprintln!("{}", serde_json::to_string_pretty(&report["stages"]).unwrap());
}

/// `poseflow bench pipeline`: both graphs through processes and in one
/// process on a short rendered sequence; every figure the issue asks for is
/// there and every counted frame was estimated, by both.
#[test]
fn the_pipeline_benchmark_measures_both_graphs_through_processes_and_in_process() {
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let before = shared_memory_files();
    let report = bench_report(&["pipeline", "--frames", "8", "--warmup", "2"]);
    for key in ["estimation", "tracking", "estimation_in_process", "tracking_in_process"] {
        let figures = &report[key];
        let (fps, p50, p99) = (&figures["fps"], &figures["p50_ms"], &figures["p99_ms"]);
        assert!(fps.as_f64().is_some_and(|f| f > 0.0), "{key}: {figures}");
        assert!(p50.as_f64().is_some_and(|p| p > 0.0 && p <= p99.as_f64().unwrap()), "{key}: {figures}");
        assert_eq!((&figures["frames"], &figures["expected_frames"]), (&6.into(), &6.into()), "{key}: {figures}");
    }
    for mode in ["estimation", "tracking"] {
        assert_eq!((&report[format!("{mode}_restarts")], &report[format!("{mode}_errors")]), (&0.into(), &0.into()));
        let path = &report[format!("{mode}_path")];
        assert!(path["source→ingest"]["p50_ms"].as_f64().is_some_and(|ms| ms > 0.0), "{path}");
        assert!(path["selector→received"]["p50_ms"].as_f64().is_some(), "{path}");
        let in_process = &report[format!("{mode}_in_process_stages")];
        assert!(in_process["encode"]["p50_ms"].as_f64().is_some_and(|ms| ms > 0.0), "{in_process}");
    }
    for stage in ["frames", "ingest", "inference", "sampler", "selector"] {
        let latency = &report["stages"][stage];
        assert!(latency["p50_us"].as_u64().is_some_and(|us| us > 0), "{stage}: {latency}");
    }
    assert_nothing_leaked(&before);

    let output = poseflow().args(["bench", "pipeline", "--frames", "3", "--warmup", "5"]).output().unwrap();
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(!output.status.success() && stderr.contains("--frames 3") && stderr.contains("--warmup"), "{stderr}");
}

/// `--in-process`: the same stage libraries as threads, same results.
#[test]
fn the_same_graph_runs_in_process() {
    let scratch = Scratch::new("in-process");
    let graph = scratch.graph(1000, 0.0, "block");
    let output = run_graph(&["--in-process", "--json"], &graph).output().unwrap();
    let summary = summary(&output);
    assert!(output.status.success(), "{summary}");
    assert_eq!(summary["stages"]["relay"]["frames_in"], 1000, "{summary}");
    let report = scratch.report();
    assert_eq!((report.received, report.intact, report.relayed, report.gaps), (1000, 1000, 1000, 0), "{report:?}");

    // A stage without an in-process build is named, with the alternatives.
    let text = std::fs::read_to_string(&graph).unwrap().replace("exe = \"smoke-relay\"", "exe = \"/bin/true\"");
    std::fs::write(&graph, text).unwrap();
    let output = run_graph(&["--in-process"], &graph).output().unwrap();
    assert!(!output.status.success());
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(stderr.contains("`stages.relay.exe`") && stderr.contains("smoke-relay"), "{stderr}");
}

/// `--record` captures an edge; `replay-source` plays it back into a sink
/// without the stages that produced it.
#[test]
fn a_recorded_edge_replays_into_a_sink() {
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
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

/// The `frames` stage reading the bad-input corpus.
fn corpus_frames() -> String {
    let corpus = concat!(env!("CARGO_MANIFEST_DIR"), "/corpus/ingest");
    format!("exe = \"frame-source\"\nparams = {{ source = \"bop\", dataset = \"{corpus}\", split = \"test\" }}")
}

/// The `[graph]` table and the frames and observations edges of a test
/// graph whose observations hold up to `observation_payload` values.
fn graph_head(name: &str, observation_payload: usize) -> String {
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
fn ingest_graph(scratch: &Scratch, name: &str, frames: &str, detector: Option<(&str, &str)>) -> PathBuf {
    let mut text = graph_head("ingest-corpus", 10_000);
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
fn run_recording(graph: &Path, edge: &str, recording: &Path) -> (serde_json::Value, String) {
    let args = ["--json", "--status-ms", "0", "--record", recording.to_str().unwrap(), "--record-edges", edge];
    let output = run_graph(&args, graph).output().unwrap();
    let result = summary(&output);
    let stderr = String::from_utf8_lossy(&output.stderr).into_owned();
    assert!(output.status.success(), "{result}\n{stderr}");
    (result, stderr)
}

/// Observation object ids of a recording, checking every message.
fn recorded_observations(recording: &Path) -> Vec<(u64, u32)> {
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

/// A detector written in Python sits between the frame source and ingest
/// and decides which objects are observed.
#[test]
fn a_python_detector_plugs_in_between_frames_and_ingest() {
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let before = shared_memory_files();
    let scratch = Scratch::new("detector");
    let plugin = concat!(env!("CARGO_MANIFEST_DIR"), "/../plugins/python/detector_template.py");
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

/// The ingest stage reads the bad-input corpus as its own process: broken
/// frames and objects are counted as errors, the good ones arrive intact
/// over shared memory, and the stream runs to its end.
#[test]
fn the_ingest_stage_survives_the_bad_input_corpus() {
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
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

    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
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

    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
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
