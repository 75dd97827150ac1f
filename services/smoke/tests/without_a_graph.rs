//! A stage binary started by hand, outside `poseflow run`, says what to do
//! instead of panicking. (Being an integration test, this also makes
//! `cargo test --workspace` build the smoke binaries the end-to-end tests
//! launch.)

use std::process::Command;

#[test]
fn stages_started_without_wiring_explain_how_to_start_them() {
    for exe in [env!("CARGO_BIN_EXE_smoke-source"), env!("CARGO_BIN_EXE_smoke-relay"), env!("CARGO_BIN_EXE_smoke-sink")]
    {
        let out = Command::new(exe).env_remove("POSEFLOW_STAGE").env("NO_COLOR", "1").output().unwrap();
        assert_eq!(out.status.code(), Some(1), "{exe}");
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(
            stderr.contains("POSEFLOW_STAGE is not set") && stderr.contains("poseflow run --graph"),
            "{exe}: {stderr}"
        );
    }
}

#[test]
fn malformed_wiring_is_reported() {
    let out = Command::new(env!("CARGO_BIN_EXE_smoke-relay")).env("POSEFLOW_STAGE", "{not json").output().unwrap();
    assert_eq!(out.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&out.stderr).contains("invalid stage wiring"));
}
