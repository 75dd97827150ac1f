//! `poseflow`: the command line of the PoseFlow runtime.

mod bench;
mod cli;
mod demo;
mod eval;
mod grasp_data;
mod import_model;
mod logging;
mod observe;
mod preview;
mod progress;
mod render;
mod run;
mod sim;
mod timing;

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
