//! Graphs across hosts: two network namespaces joined by a veth pair stand
//! in for two machines, each running its part of one graph file with
//! `poseflow run --host`, its edges crossing in the Zenoh bridges. The
//! tests skip, saying why, where namespaces cannot be created (they need
//! root and `ip`).

use std::path::{Path, PathBuf};
use std::process::{Child, Stdio};
use std::time::{Duration, Instant};

use poseflow_bridge::netns::{ADDRESS_A, HostPair};
use poseflow_e2e::harness::*;
use poseflow_e2e::recordings::recorded_messages;
use poseflow_transport::shared_memory_files;

fn repository() -> PathBuf {
    PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/.."))
}

/// Namespaces for this test, or `None` after saying why the test skips.
fn host_pair(tag: &str) -> Option<HostPair> {
    match HostPair::create(tag) {
        Ok(pair) => Some(pair),
        Err(reason) => {
            eprintln!("SKIPPED: two-host test needs network namespaces: {reason}");
            None
        }
    }
}

/// `poseflow run --host host` of `graph` inside `namespace`, started.
fn start_host(namespace: &str, graph: &Path, host: &str, instance: &str, extra: &[&str]) -> Child {
    let mut args = vec!["--json", "--status-ms", "0", "--host", host, "--instance", instance];
    args.extend_from_slice(extra);
    let mut command = run_graph(&args, graph);
    command.current_dir(repository());
    HostPair::inside(namespace, &command).stdout(Stdio::piped()).stderr(Stdio::piped()).spawn().unwrap()
}

/// Waits for a host's run; its summary, checking it succeeded.
fn finished(run: Child, host: &str) -> serde_json::Value {
    let output = wait_within(run, RUN_DEADLINE);
    let summary = summary(&output);
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(output.status.success(), "host {host}: {summary}\n{stderr}");
    let bridge = &summary["stages"]["zenoh-bridge"];
    assert_eq!(bridge["outcome"], "finished", "host {host}: {summary}\n{stderr}");
    assert_eq!(bridge["total"]["errors"], 0, "host {host}: refused messages: {summary}\n{stderr}");
    summary
}

/// The estimation graph split as deploy/two-hosts/estimation.toml places
/// it (frames and ingest on `robot`; inference, sampler and selector on
/// `compute`), in two namespaces: its Estimates equal, bit for bit
/// (timestamps aside), those of the same file run on one host.
#[test]
fn the_estimation_graph_split_across_two_hosts_gives_the_single_host_estimates() {
    let _serial = serial();
    let Some(pair) = host_pair("pfe") else { return };
    let before = shared_memory_files();
    let scratch = Scratch::new("two-hosts");
    let graph = repository().join("deploy/two-hosts/estimation.toml");
    // Less work for the unoptimised test build: three frames, coarse grids.
    let shorter = ["--set", "frames.frames_per_scene=3", "--set", "selector.sdf_resolution=16"];

    let single = scratch.dir.join("single.rec");
    let mut args =
        vec!["--json", "--status-ms", "0", "--record", single.to_str().unwrap(), "--record-edges", "estimates"];
    args.extend_from_slice(&shorter);
    let output = run_graph(&args, &graph).current_dir(repository()).output_within(RUN_DEADLINE);
    assert!(output.status.success(), "single host: {}", String::from_utf8_lossy(&output.stderr));

    let split = scratch.dir.join("split.rec");
    let id = std::process::id();
    let (robot_instance, compute_instance) = (format!("robot-{id}"), format!("compute-{id}"));
    let mut compute_args = vec!["--record", split.to_str().unwrap(), "--record-edges", "estimates"];
    compute_args.extend_from_slice(&shorter);
    let compute = start_host(&pair.b, &graph, "compute", &compute_instance, &compute_args);
    let robot = start_host(&pair.a, &graph, "robot", &robot_instance, &shorter);
    let compute = finished(compute, "compute");
    let robot = finished(robot, "robot");
    assert_eq!(
        robot["stages"]["zenoh-bridge"]["total"]["frames_out"],
        compute["stages"]["zenoh-bridge"]["total"]["frames_in"]
    );
    assert!(robot["stages"].get("inference").is_none() && compute["stages"].get("ingest").is_none());

    let (single, split) = (recorded_messages(&single), recorded_messages(&split));
    let estimates = &single["estimates"];
    assert!(!estimates.is_empty(), "the single-host run estimated nothing");
    assert_eq!(estimates.len(), split["estimates"].len(), "estimates per run");
    for (i, (a, b)) in estimates.iter().zip(&split["estimates"]).enumerate() {
        assert!(a == b, "estimate {i} of {} differs between one host and two", estimates.len());
    }
    eprintln!("{} estimates equal across one and two hosts", estimates.len());
    drop(scratch);
    drop(pair);
    assert_nothing_leaked(&before);
}

/// The relay graph with the source and sink on host `a` and the relay on
/// host `b`, so traffic crosses twice. Killing the relay: `b`'s supervisor
/// restarts it; on `a` nothing restarts, the sink sees no corrupted frame,
/// counts what was lost as gaps and gets the restart notice across hosts.
#[test]
fn a_stage_killed_on_one_host_is_restarted_there_and_the_other_host_counts_the_gap() {
    let _serial = serial();
    let Some(pair) = host_pair("pfk") else { return };
    let before = shared_memory_files();
    let scratch = Scratch::new("two-hosts-kill");
    // 1,500 frames at 500 Hz; drop-oldest so the source never waits for the dead relay.
    let graph = scratch.graph(1500, 500.0, "drop-oldest");
    let text = std::fs::read_to_string(&graph)
        .unwrap()
        .replace(
            "[edges.raw]",
            &format!(
                "[hosts.a]\nlisten = [\"tcp/{ADDRESS_A}:7447\"]\n\n[hosts.b]\nconnect = [\"tcp/{ADDRESS_A}:7447\"]\n\n[edges.raw]"
            ),
        )
        .replace("exe = \"smoke-source\"", "exe = \"smoke-source\"\nhost = \"a\"")
        .replace("exe = \"smoke-sink\"", "exe = \"smoke-sink\"\nhost = \"a\"")
        .replace("exe = \"smoke-relay\"", "exe = \"smoke-relay\"\nhost = \"b\"");
    std::fs::write(&graph, text).unwrap();
    let id = std::process::id();
    let (instance_a, instance_b) = (format!("kill-a-{id}"), format!("kill-b-{id}"));
    let run_b = start_host(&pair.b, &graph, "b", &instance_b, &[]);
    let run_a = start_host(&pair.a, &graph, "a", &instance_a, &[]);
    let deadline = Instant::now() + Duration::from_secs(60);
    let relay = loop {
        if let Some(pid) = find_stage_pid(&instance_b, "relay") {
            break pid;
        }
        assert!(Instant::now() < deadline, "the relay never started on host b");
        std::thread::sleep(Duration::from_millis(20));
    };
    // Let traffic flow across both hosts, then kill the relay mid-stream.
    std::thread::sleep(Duration::from_millis(1500));
    // SAFETY: signalling a process this test started (through poseflow).
    assert_eq!(unsafe { libc::kill(relay as i32, libc::SIGKILL) }, 0);

    let summary_b = finished(run_b, "b");
    let summary_a = finished(run_a, "a");
    assert_eq!(summary_b["stages"]["relay"]["restarts"], 1, "{summary_b}");
    for stage in ["source", "sink"] {
        assert_eq!(summary_a["stages"][stage]["restarts"], 0, "{summary_a}");
        assert_eq!(summary_a["stages"][stage]["outcome"], "finished", "{summary_a}");
    }
    let report = scratch.report();
    eprintln!("sink on host a: {report:?}");
    assert_eq!(report.corrupted, 0, "{report:?}");
    assert_eq!(report.intact, report.received, "{report:?}");
    assert_eq!(report.last_frame, Some(1499), "traffic did not resume: {report:?}");
    assert_eq!(report.received + report.gaps, 1500 - report.first_frame.unwrap(), "{report:?}");
    assert_eq!(report.restart_notices, 1, "the restart notice crossed hosts: {report:?}");
    drop(scratch);
    drop(pair);
    assert_nothing_leaked(&before);
}

/// `poseflow bench ipc --zenoh` measures the two-host hop (two bridges and
/// the link between two namespaces) beside the local transports, and the
/// ratios at 4 MiB.
#[test]
fn the_ipc_benchmark_measures_an_edge_between_two_hosts() {
    let _serial = serial();
    // The benchmark makes its own namespaces; skip where none can be made.
    let Some(probe) = host_pair("pfp") else { return };
    drop(probe);
    let before = shared_memory_files();
    let output = poseflow()
        .args(["bench", "ipc", "--zenoh", "--json", "--samples", "20", "--warmup", "5", "--period-us", "2000"])
        .output_within(RUN_DEADLINE);
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(output.status.success(), "{stderr}");
    let report: serde_json::Value = serde_json::from_slice(&output.stdout).expect("one JSON object");
    for bytes in ["4096", "65536", "1048576", "4194304"] {
        let cell = &report["zenoh_two_hosts"][bytes];
        assert_eq!(cell["samples"], 20, "{bytes}: {cell}\n{stderr}");
        // Two bridges and a network link cost more than one shared-memory hop.
        let local = report["iceoryx2"][bytes]["p50_us"].as_f64().unwrap();
        assert!(cell["p50_us"].as_f64().unwrap() > local, "{bytes}: {report}");
    }
    assert!(report["zenoh_4mib_p50_ratio"]["vs_unix_socket"].as_f64().unwrap() > 0.0, "{report}");
    assert_nothing_leaked(&before);
}

/// `--host` mistakes are refused before anything starts, naming what was
/// expected (no namespaces needed).
#[test]
fn host_mistakes_are_refused_before_anything_starts() {
    let graph = repository().join("deploy/two-hosts/estimation.toml");
    let scratch = Scratch::new("host-mistakes");
    let recording = scratch.dir.join("x.rec");
    for (args, expected) in [
        (vec!["--host", "lab"], "--host lab"),
        (vec!["--host", "robot", "--in-process"], "--in-process runs a whole graph on one machine"),
        (
            vec!["--host", "robot", "--record", recording.to_str().unwrap(), "--record-edges", "estimates"],
            "`estimates` is neither written nor read on host `robot`",
        ),
    ] {
        let output = run_graph(&args, &graph).current_dir(repository()).output_within(RUN_DEADLINE);
        let stderr = String::from_utf8_lossy(&output.stderr);
        assert!(!output.status.success(), "{args:?} ran");
        assert!(stderr.contains(expected), "{args:?}: {stderr}");
    }
    let output = run_graph(&["--host", "lab"], &graph).current_dir(repository()).output_within(RUN_DEADLINE);
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(stderr.contains("[\"compute\", \"robot\"]"), "the hosts it has: {stderr}");
    assert!(!recording.exists());
}
