//! Logging of stage processes: `RUST_LOG` filter (default `info`), pretty
//! or JSON lines on stderr (`POSEFLOW_LOG_FORMAT=json`, set by the launcher
//! from `--log-format`).

use std::io::IsTerminal;

use tracing_subscriber::EnvFilter;

/// The variable the launcher sets to pass `--log-format` on to stages.
pub const LOG_FORMAT_ENV: &str = "POSEFLOW_LOG_FORMAT";

/// Installs the subscriber; a second call is a no-op.
pub fn init_logging() {
    let filter = EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new("info"));
    let builder = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .with_ansi(std::io::stderr().is_terminal());
    let _ = if std::env::var(LOG_FORMAT_ENV).as_deref() == Ok("json") {
        builder.json().try_init()
    } else {
        builder.try_init()
    };
}
