//! `tracing` set-up shared by every subcommand: filter from `RUST_LOG`
//! (default `info`), human or JSON lines on stderr.

use std::io::IsTerminal;

pub use poseflow_launch::LogFormat;
use tracing_subscriber::EnvFilter;

pub fn init(format: LogFormat) -> anyhow::Result<()> {
    // iceoryx2's own notes (which config file it read) are for stage logs,
    // not for the person at the command line; IOX2_LOG_LEVEL still wins.
    iceoryx2::prelude::set_log_level_from_env_or(iceoryx2::prelude::LogLevel::Warn);
    let filter = EnvFilter::try_from_default_env().or_else(|_| EnvFilter::try_new("info"))?;
    let builder = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        // Colour only for a person: a log file or pipe gets plain text.
        .with_ansi(std::io::stderr().is_terminal());
    match format {
        LogFormat::Pretty => builder.try_init(),
        LogFormat::Json => builder.json().try_init(),
    }
    .map_err(|err| anyhow::anyhow!(err))
}
