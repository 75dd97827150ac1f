//! `poseflow`: the command line of the PoseFlow runtime. It parses the
//! arguments and calls the libraries: the launcher (`run`), the demo and
//! evaluation, the data commands, the benchmarks and the simulations.

mod cli;
mod logging;
mod run;

use std::process::ExitCode;

use clap::Parser;

fn main() -> ExitCode {
    let cli = cli::Cli::parse();
    if let Err(err) = logging::init(cli.log_format) {
        eprintln!("poseflow: cannot set up logging: {err:#}");
        return ExitCode::FAILURE;
    }
    cli::run(cli.command, cli.log_format)
}
