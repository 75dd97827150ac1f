//! Command-line definition and dispatch.

use std::process::ExitCode;

use clap::{Parser, Subcommand};

use crate::logging::LogFormat;

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
    /// Sample antipodal, collision-free grasps on object models (the grasp flow's training data).
    GraspData(crate::grasp_data::GraspDataArgs),
    /// Write one dataset image's RGB, depth and visible masks side by side as a PNG.
    Preview(crate::preview::PreviewArgs),
    /// Write a BOP dataset's observations and ground truth as a training shard.
    Observe(crate::observe::ObserveArgs),
    /// Evaluate on a BOP-format dataset: accuracy, ADD(-S), calibration, runtime.
    Eval(crate::eval::EvalArgs),
    /// Benchmark transport latency and end-to-end throughput.
    Bench(crate::bench::BenchArgs),
    /// Closed-loop simulations on rendered scenes (grasping under pose uncertainty, next-best view).
    Sim(crate::sim::SimArgs),
}

fn report(result: anyhow::Result<ExitCode>) -> ExitCode {
    result.unwrap_or_else(|err| {
        tracing::error!("{err:#}");
        ExitCode::FAILURE
    })
}

pub fn run(command: Command, log_format: LogFormat) -> ExitCode {
    let done = |result: anyhow::Result<()>| report(result.map(|()| ExitCode::SUCCESS));
    match command {
        Command::Run(args) => report(crate::run::run(args, log_format)),
        Command::Bench(args) => report(crate::bench::run(args)),
        Command::Demo(args) => done(crate::demo::run(&args)),
        Command::Render(args) => done(crate::render::run(&args)),
        Command::ImportModel(args) => done(crate::import_model::run(&args)),
        Command::Preview(args) => done(crate::preview::run(&args)),
        Command::GraspData(args) => done(crate::grasp_data::run(&args)),
        Command::Observe(args) => done(crate::observe::run(&args)),
        Command::Eval(args) => done(crate::eval::run(&args)),
        Command::Sim(args) => done(crate::sim::run(&args)),
    }
}
