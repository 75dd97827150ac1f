//! Command-line definition and dispatch.

use std::process::ExitCode;

use clap::{Parser, Subcommand};

use crate::logging::LogFormat;

/// Exit code of a subcommand that this build does not provide yet.
const NOT_AVAILABLE: u8 = 2;

#[derive(Debug, Parser)]
#[command(
    name = "poseflow",
    version,
    about = "6D object pose distributions from RGB-D: SE(3) flow matching as a zero-copy process graph",
    long_about = "6D object pose distributions from RGB-D: SE(3) flow matching as a zero-copy process graph.\n\n\
        Stages (ingest, inference, sampler, selector, grasp, next-best-view) run as separate processes \
        exchanging tensors over iceoryx2 shared memory.\n\n\
        Logging: RUST_LOG sets the filter (default: info), --log-format the output."
)]
pub struct Cli {
    /// Log output format (logs go to stderr).
    #[arg(long, value_enum, default_value_t = LogFormat::Pretty, global = true)]
    pub log_format: LogFormat,

    #[command(subcommand)]
    pub command: Command,
}

#[derive(Debug, Subcommand)]
pub enum Command {
    /// Run the end-to-end demo on the embedded default model and data.
    Demo(crate::demo::DemoArgs),
    /// Launch a process graph from a graph file (deploy/*.toml).
    Run(crate::run::RunArgs),
    /// Render a BOP-format dataset of random RGB-D tabletop scenes from object models.
    Render(crate::render::RenderArgs),
    /// Add an object from a PLY or OBJ mesh to a BOP models directory (model file + models_info.json entry).
    ImportModel(crate::import_model::ImportModelArgs),
    /// Write one dataset image's RGB, depth and visible masks side by side as a PNG.
    Preview(crate::preview::PreviewArgs),
    /// Write a BOP dataset's observations and ground truth as a training shard.
    Observe(crate::observe::ObserveArgs),
    /// Evaluate on a BOP-format dataset: accuracy, ADD(-S), calibration, runtime.
    Eval,
    /// Benchmark transport latency and end-to-end throughput.
    Bench(crate::bench::BenchArgs),
}

impl Command {
    fn name(&self) -> &'static str {
        match self {
            Command::Demo(_) => "demo",
            Command::Run(_) => "run",
            Command::Render(_) => "render",
            Command::ImportModel(_) => "import-model",
            Command::Preview(_) => "preview",
            Command::Observe(_) => "observe",
            Command::Eval => "eval",
            Command::Bench(_) => "bench",
        }
    }
}

fn report(result: anyhow::Result<ExitCode>) -> ExitCode {
    result.unwrap_or_else(|err| {
        tracing::error!("{err:#}");
        ExitCode::FAILURE
    })
}

pub fn run(command: Command, log_format: LogFormat) -> ExitCode {
    // What has to land before a subcommand works.
    let missing = match command {
        Command::Run(args) => return report(crate::run::run(args, log_format)),
        Command::Demo(args) => return report(crate::demo::run(&args).map(|()| ExitCode::SUCCESS)),
        Command::Bench(args) => return report(crate::bench::run(args)),
        Command::Render(args) => return report(crate::render::run(&args).map(|()| ExitCode::SUCCESS)),
        Command::ImportModel(args) => return report(crate::import_model::run(&args).map(|()| ExitCode::SUCCESS)),
        Command::Preview(args) => return report(crate::preview::run(&args).map(|()| ExitCode::SUCCESS)),
        Command::Observe(args) => return report(crate::observe::run(&args).map(|()| ExitCode::SUCCESS)),
        Command::Eval => "it needs the estimation graph and the BOP benchmark runner",
    };
    tracing::error!(
        subcommand = command.name(),
        "`poseflow {}` is not available yet in this build: {}",
        command.name(),
        missing
    );
    ExitCode::from(NOT_AVAILABLE)
}
