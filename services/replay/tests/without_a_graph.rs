//! `replay-source` outside a graph, and with a recording that is not one.
//! (Being an integration test, this also makes `cargo test --workspace`
//! build the binary the end-to-end tests launch.)

use std::process::Command;

#[test]
fn replay_without_wiring_explains_how_to_start_it() {
    let out = Command::new(env!("CARGO_BIN_EXE_replay-source")).env_remove("POSEFLOW_STAGE").output().unwrap();
    assert_eq!(out.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&out.stderr).contains("POSEFLOW_STAGE is not set"));
}

#[test]
fn a_file_that_is_not_a_recording_is_named() {
    let path = std::env::temp_dir().join(format!("not-a-recording-{}.rec", std::process::id()));
    std::fs::write(&path, b"definitely not").unwrap();
    let wiring = format!(
        r#"{{"instance":"replay-test-{pid}","stage":"replay","inputs":[],"serves":[],"calls":[],
            "outputs":[{{"edge":"e","service":"poseflow/replay-test-{pid}/e","message":"Hypotheses","queue":4,
                        "overflow":"drop-oldest","max_payload_len":64,"readers":0}}],
            "heartbeat_service":"poseflow/replay-test-{pid}/_heartbeat/replay","heartbeat_ms":100,
            "params":{{"file":"{file}"}}}}"#,
        pid = std::process::id(),
        file = path.display()
    );
    let out = Command::new(env!("CARGO_BIN_EXE_replay-source")).env("POSEFLOW_STAGE", wiring).output().unwrap();
    std::fs::remove_file(&path).unwrap();
    assert_eq!(out.status.code(), Some(1));
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.contains("not a PoseFlow recording") && stderr.contains("not-a-recording"), "{stderr}");
}
