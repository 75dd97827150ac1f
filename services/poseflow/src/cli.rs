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
    Demo(poseflow_eval::demo::DemoArgs),
    /// Launch a process graph from a graph file (deploy/*.toml).
    Run(crate::run::RunArgs),
    /// Render a BOP-format dataset of random RGB-D tabletop scenes from object models.
    Render(poseflow_datasets::render::RenderArgs),
    /// Add an object from a PLY or OBJ mesh to a BOP models directory (model file + models_info.json entry).
    ImportModel(poseflow_datasets::import_model::ImportModelArgs),
    /// Generate procedural mugs, bowls, bottles and cans (category-level objects) into a BOP models directory.
    GenerateObjects(poseflow_datasets::generate_objects::GenerateObjectsArgs),
    /// Record a model's category and canonical frame (categories.json), for category-level eval of meshes not
    /// made in that frame.
    AnnotateCategory(poseflow_datasets::annotate_category::AnnotateCategoryArgs),
    /// Sample antipodal, collision-free grasps on object models (the grasp flow's training data).
    GraspData(poseflow_datasets::grasp_data::GraspDataArgs),
    /// Write one dataset image's RGB, depth and visible masks side by side as a PNG.
    Preview(poseflow_datasets::preview::PreviewArgs),
    /// Write a BOP dataset's observations and ground truth as a training shard.
    Observe(poseflow_datasets::observe::ObserveArgs),
    /// Evaluate on a BOP-format dataset: accuracy, ADD(-S), calibration, runtime.
    Eval(poseflow_eval::EvalArgs),
    /// Benchmark transport latency and end-to-end throughput.
    Bench(poseflow_bench::BenchArgs),
    /// Closed-loop simulations on rendered scenes (grasping under pose uncertainty, next-best view).
    Sim(poseflow_sim::SimArgs),
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
        Command::Bench(args) => report(poseflow_bench::run(args)),
        Command::Demo(args) => done(poseflow_eval::demo::run(&args)),
        Command::Render(args) => done(poseflow_datasets::render::run(&args)),
        Command::ImportModel(args) => done(poseflow_datasets::import_model::run(&args)),
        Command::GenerateObjects(args) => done(poseflow_datasets::generate_objects::run(&args)),
        Command::AnnotateCategory(args) => done(poseflow_datasets::annotate_category::run(&args)),
        Command::Preview(args) => done(poseflow_datasets::preview::run(&args)),
        Command::GraspData(args) => done(poseflow_datasets::grasp_data::run(&args)),
        Command::Observe(args) => done(poseflow_datasets::observe::run(&args)),
        Command::Eval(args) => done(poseflow_eval::run(&args)),
        Command::Sim(args) => done(poseflow_sim::run(&args)),
    }
}
