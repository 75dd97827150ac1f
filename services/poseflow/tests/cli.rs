//! The `poseflow` binary as a user meets it.

use std::process::{Command, Output};

fn poseflow(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_poseflow"))
        .args(args)
        .env_remove("RUST_LOG")
        .output()
        .expect("poseflow binary runs")
}

const SUBCOMMANDS: [&str; 5] = ["demo", "run", "render", "eval", "bench"];

#[test]
fn help_lists_every_subcommand() {
    let out = poseflow(&["--help"]);
    assert!(out.status.success());
    let help = String::from_utf8(out.stdout).unwrap();
    for sub in SUBCOMMANDS {
        assert!(help.lines().any(|l| l.trim_start().starts_with(sub)), "`{sub}` missing from:\n{help}");
    }
    assert!(help.contains("--log-format"));
}

#[test]
fn unavailable_subcommands_say_so_and_exit_2() {
    for sub in ["demo", "render", "eval", "bench pipeline"] {
        let args: Vec<&str> = sub.split(' ').collect();
        let out = poseflow(&args);
        assert_eq!(out.status.code(), Some(2), "{sub}");
        let stderr = String::from_utf8(out.stderr).unwrap();
        assert!(stderr.contains(&format!("`poseflow {sub}` is not available yet")), "{stderr}");
    }
}

#[test]
fn json_logs_are_one_object_per_line() {
    let out = poseflow(&["--log-format", "json", "demo"]);
    let stderr = String::from_utf8(out.stderr).unwrap();
    let line = stderr.lines().next().expect("one log line");
    let value: serde_json::Value = serde_json::from_str(line).expect("log line is JSON");
    assert_eq!(value["level"], "ERROR");
    assert_eq!(value["fields"]["subcommand"], "demo");
}

#[test]
fn unknown_log_format_is_rejected_with_the_choices() {
    let out = poseflow(&["--log-format", "xml", "demo"]);
    assert_eq!(out.status.code(), Some(2));
    let stderr = String::from_utf8(out.stderr).unwrap();
    assert!(stderr.contains("pretty") && stderr.contains("json"), "{stderr}");
}

#[test]
fn bench_ipc_reports_every_transport_and_payload() {
    let out = poseflow(&["bench", "ipc", "--json", "--samples", "20", "--warmup", "5", "--period-us", "200"]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let report: serde_json::Value = serde_json::from_slice(&out.stdout).expect("one JSON object");
    for transport in ["iceoryx2", "in_process", "unix_socket_bincode"] {
        for bytes in ["4096", "65536", "1048576", "4194304"] {
            let cell = &report[transport][bytes];
            assert_eq!(cell["samples"], 20, "{transport} {bytes}: {cell}");
            let (p50, p99, max) =
                (cell["p50_us"].as_f64().unwrap(), cell["p99_us"].as_f64().unwrap(), cell["max_us"].as_f64().unwrap());
            assert!(0.0 < p50 && p50 <= p99 && p99 <= max, "{transport} {bytes}: {cell}");
        }
    }
}
