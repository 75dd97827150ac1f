//! Supervision: stages killed, crashing, hanging, ignoring SIGTERM or
//! flooding their queues are restarted, killed or counted by `poseflow run`;
//! Ctrl-C and failing graphs; the deploy graphs; the in-process mode. Whole
//! graphs of real processes over real iceoryx2 shared memory, launched by
//! `poseflow run`.

use std::path::Path;
use std::time::{Duration, Instant};

use poseflow_e2e::harness::*;
use poseflow_transport::shared_memory_files;

#[test]
fn three_processes_pass_every_frame_intact() {
    let _serial = serial();
    let before = shared_memory_files();
    let scratch = Scratch::new("intact");
    let graph = scratch.graph(1000, 0.0, "block");
    let output = run_graph(&["--json", "--status-ms", "0"], &graph).output_within(RUN_DEADLINE);
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

#[test]
fn a_killed_stage_is_restarted_and_traffic_resumes() {
    let _serial = serial();
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

    let output = wait_within(run, RUN_DEADLINE);
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

/// A relay that panics in the middle of a frame (input taken, nothing
/// emitted) is restarted with backoff; the sink sees no corrupted frame.
#[test]
fn a_stage_crashing_mid_frame_is_restarted_and_nothing_corrupted_passes() {
    let _serial = serial();
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
    let _serial = serial();
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

/// Sends SIGSTOP to `pid`, the process of `stage`, and waits for another
/// process of that stage; how long that took.
fn stop_and_time_replacement(instance: &str, stage: &str, pid: u32) -> Duration {
    let stopped = Instant::now();
    // SAFETY: signalling a process this test started (through poseflow).
    assert_eq!(unsafe { libc::kill(pid as i32, libc::SIGSTOP) }, 0);
    loop {
        match find_stage_pid(instance, stage) {
            Some(new) if new != pid => return stopped.elapsed(),
            _ if stopped.elapsed() > Duration::from_secs(30) => panic!("the stopped {stage} was not replaced"),
            _ => std::thread::sleep(Duration::from_millis(10)),
        }
    }
}

/// A stopped process (SIGSTOP: its heartbeat thread stops with it) is told
/// from one busy in a long message by its heartbeats' silence, and replaced
/// after a few heartbeat periods, not at the busy deadline (20 s here, as in
/// deploy/tracking.toml).
#[test]
fn a_stopped_stage_is_replaced_within_a_few_heartbeats() {
    let _serial = serial();
    let before = shared_memory_files();
    let scratch = Scratch::new("sigstop");
    let graph = scratch.graph(2500, 500.0, "drop-oldest");
    let text = std::fs::read_to_string(&graph).unwrap();
    std::fs::write(&graph, text.replace("heartbeat_timeout_ms = 3000", "heartbeat_timeout_ms = 20000")).unwrap();
    let instance = format!("sigstop-{}", std::process::id());
    let (run, relay) = start_and_wait_for(&graph, &instance, "relay");
    std::thread::sleep(Duration::from_millis(800));
    let replaced = stop_and_time_replacement(&instance, "relay", relay);
    let output = wait_within(run, RUN_DEADLINE);
    let (summary, stderr) = (summary(&output), String::from_utf8_lossy(&output.stderr));
    assert!(output.status.success(), "{summary}\n{stderr}");
    eprintln!("stopped relay replaced {} ms after SIGSTOP", replaced.as_millis());
    // Heartbeats every 100 ms, silence deadline 5 of them, 100 ms backoff.
    assert!(replaced < Duration::from_millis(1500), "replaced after {replaced:?}");
    let relay = &summary["stages"]["relay"];
    assert_eq!((relay["hangs"].as_u64(), relay["restarts"].as_u64()), (Some(1), Some(1)), "{summary}");
    assert!(stderr.contains("heartbeats stopped for longer than graph.silence_timeout_ms"), "{stderr}");
    let report = scratch.report();
    assert_recovered(&summary, &report, 2500);
    assert_nothing_leaked(&before);
}

/// As above with blocking queues: the source is held back by the hung
/// relay's full queue when the relay is killed; once the supervisor has
/// removed the dead reader's port, the source's send stops waiting for it
/// and traffic resumes through the restarted relay.
#[test]
fn a_writer_blocked_on_a_killed_reader_carries_on() {
    let _serial = serial();
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
    let _serial = serial();
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
    let output = wait_within(run, RUN_DEADLINE);
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
    let _serial = serial();
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
    let output = run_graph(&[], &graph).output_within(RUN_DEADLINE);
    assert!(!output.status.success());
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(
        stderr.contains("relay.toml") && stderr.contains("`stages.relay.inputs`") && stderr.contains("\"missing\""),
        "{stderr}"
    );
}

#[test]
fn ctrl_c_stops_every_stage_and_leaves_nothing_behind() {
    let _serial = serial();
    let before = shared_memory_files();
    let scratch = Scratch::new("sigint");
    // A stream far longer than the test: only SIGINT ends it.
    let graph = scratch.graph(1_000_000, 200.0, "drop-oldest");
    let instance = format!("sigint-{}", std::process::id());
    let (run, _) = start_and_wait_for(&graph, &instance, "sink");
    std::thread::sleep(Duration::from_millis(500));
    // SAFETY: signalling the poseflow process this test started.
    assert_eq!(unsafe { libc::kill(run.id() as i32, libc::SIGINT) }, 0);

    let output = wait_within(run, RUN_DEADLINE);
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
    let _serial = serial();
    let before = shared_memory_files();
    let scratch = Scratch::new("failing");
    let graph = scratch.graph(1_000_000, 200.0, "drop-oldest");
    // A "relay" that dies at once, every time.
    let text = std::fs::read_to_string(&graph)
        .unwrap()
        .replace("exe = \"smoke-relay\"", "exe = \"/bin/false\"\nmax_restarts = 2")
        .replace("backoff_ms = 100", "backoff_ms = 10");
    std::fs::write(&graph, text).unwrap();
    let output = run_graph(&["--json", "--status-ms", "0"], &graph).output_within(RUN_DEADLINE);
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

/// Every graph shipped in deploy/ (and deploy/two-hosts/) validates, and
/// the smoke graph runs clean.
#[test]
fn deploy_graphs_are_valid_and_the_smoke_graph_runs() {
    let _serial = serial();
    let deploy = Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/../deploy"));
    for dir in [deploy.to_path_buf(), deploy.join("two-hosts")] {
        for entry in std::fs::read_dir(dir).unwrap().flatten() {
            let path = entry.path();
            if path.extension().is_some_and(|e| e == "toml") {
                let output = run_graph(&["--check"], &path).output_within(RUN_DEADLINE);
                assert!(output.status.success(), "{}: {}", path.display(), String::from_utf8_lossy(&output.stderr));
            }
        }
    }
    let output = run_graph(&["--check"], &deploy.join("two-hosts/estimation.toml")).output_within(RUN_DEADLINE);
    let stdout = String::from_utf8_lossy(&output.stdout);
    assert!(stdout.contains("host robot: stages frames, ingest; sends [\"observations\"]"), "{stdout}");
    let before = shared_memory_files();
    let output = run_graph(&["--json", "--status-ms", "0"], &deploy.join("smoke.toml")).output_within(RUN_DEADLINE);
    let summary = summary(&output);
    assert!(output.status.success(), "{summary}");
    assert_eq!(summary["stages"]["source"]["frames_out"], 3000, "{summary}");
    assert_eq!(summary["stages"]["sink"]["errors"], 0, "{summary}");
    assert_nothing_leaked(&before);
}

/// `--in-process`: the same stage libraries as threads, same results.
#[test]
fn the_same_graph_runs_in_process() {
    let scratch = Scratch::new("in-process");
    let graph = scratch.graph(1000, 0.0, "block");
    let output = run_graph(&["--in-process", "--json"], &graph).output_within(RUN_DEADLINE);
    let summary = summary(&output);
    assert!(output.status.success(), "{summary}");
    assert_eq!(summary["stages"]["relay"]["frames_in"], 1000, "{summary}");
    let report = scratch.report();
    assert_eq!((report.received, report.intact, report.relayed, report.gaps), (1000, 1000, 1000, 0), "{report:?}");

    // A stage without an in-process build is named, with the alternatives.
    let text = std::fs::read_to_string(&graph).unwrap().replace("exe = \"smoke-relay\"", "exe = \"/bin/true\"");
    std::fs::write(&graph, text).unwrap();
    let output = run_graph(&["--in-process"], &graph).output_within(RUN_DEADLINE);
    assert!(!output.status.success());
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(stderr.contains("`stages.relay.exe`") && stderr.contains("smoke-relay"), "{stderr}");
}

/// The tracking demo's graph (deploy/tracking.toml, the default model, real
/// processes) with its sampler stopped mid-video, as a user might try: the
/// frozen sampler is replaced within 1.5 s although the graph allows 20 s
/// for one busy message, and every object's estimates resume to the end.
#[test]
fn a_stopped_sampler_of_the_tracking_graph_is_replaced_and_every_object_tracked_again() {
    let _serial = serial();
    let scratch = Scratch::new("track-sigstop");
    let out = scratch.dir.join("demo");
    let frames = 30;
    let demo = poseflow()
        .args(["demo", "--track", "--json", "--samples", "12", "--steps", "3", "--rate-hz", "5"])
        .args(["--frames", &frames.to_string(), "--out", out.to_str().unwrap()])
        .current_dir(concat!(env!("CARGO_MANIFEST_DIR"), "/.."))
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let instance = format!("tracking-{}", demo.id());
    let waiting = Instant::now();
    let sampler = loop {
        if let Some(pid) = find_stage_pid(&instance, "sampler") {
            break pid;
        }
        assert!(waiting.elapsed() < Duration::from_secs(120), "the tracking graph's sampler never started");
        std::thread::sleep(Duration::from_millis(50));
    };
    // A few images into the video (5 Hz): every object is being tracked.
    std::thread::sleep(Duration::from_secs(3));
    let replaced = stop_and_time_replacement(&instance, "sampler", sampler);
    let output = wait_within(demo, RUN_DEADLINE);
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(output.status.success(), "{stderr}");
    eprintln!("stopped sampler replaced {} ms after SIGSTOP", replaced.as_millis());
    assert!(replaced < Duration::from_millis(1500), "replaced after {replaced:?}");
    let log = std::fs::read_to_string(out.join("graph.log")).unwrap();
    assert!(log.contains("heartbeats stopped for longer than graph.silence_timeout_ms"), "{log}");
    let report: serde_json::Value = serde_json::from_slice(&output.stdout).unwrap();
    let objects = report["objects"].as_array().unwrap();
    assert_eq!(objects.len(), 3, "{report}");
    let mut missing = 0;
    for o in objects {
        // What dies with the frozen sampler is lost: the image in its hands
        // and the two messages its input queue held. The sends after it
        // wait for its replacement (a `block` edge), and so do the queues
        // before them.
        assert!(o["estimated"].as_u64().unwrap() >= frames - 3, "{o}");
        assert!(o["acc_10deg_5cm"].as_f64().unwrap() >= 80.0, "{o}");
        missing += frames - o["estimated"].as_u64().unwrap();
    }
    // Each missing estimate is counted: the sampler's edges count what
    // was sent and not received (a dead process's counts are its last
    // heartbeat's, so the count may exceed what was really lost).
    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("run.json")).unwrap()).unwrap();
    let lost: u64 =
        ["frames", "conditions", "hypotheses"].iter().map(|e| summary["edges"][e]["lost"].as_u64().unwrap()).sum();
    assert!(lost >= missing, "{missing} estimates missing, {lost} counted lost: {summary}");
}
