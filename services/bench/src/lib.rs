//! `poseflow bench`: latency and throughput measurements.

mod graph_run;
mod ingest;
mod ipc;
mod model;
mod pipeline;
mod soak;

pub use model::NetworkWorkload;

use std::process::ExitCode;

use clap::{Args, Subcommand};

#[derive(Debug, Args)]
pub struct BenchArgs {
    #[command(subcommand)]
    pub what: BenchCommand,
}

#[derive(Debug, Subcommand)]
pub enum BenchCommand {
    /// One-way per-hop latency of iceoryx2 (zero-copy, event wake-up), an
    /// in-process channel and a Unix socket carrying bincode, for 4 KiB to
    /// 4 MiB payloads.
    Ipc(ipc::IpcArgs),
    /// Observations per second on one core: crop, token mask and point
    /// cloud of every object of a BOP dataset's frames (held in memory).
    Ingest(ingest::IngestArgs),
    /// Latency of a model's encoder (per observation) and velocity network
    /// (per batch of samples) through ONNX Runtime.
    Model(model::ModelArgs),
    /// Frames per second and per-frame latency of the estimation and
    /// tracking graphs through processes and in one process, with each
    /// stage's process time, on the default model and a rendered sequence.
    Pipeline(pipeline::PipelineArgs),
    /// A graph run for minutes (`poseflow run`) while its stages are
    /// SIGKILLed in turn: frames, restarts, drops, corrupted estimates,
    /// leaked shared memory and every process's resident memory over time.
    /// The frame source must last the whole soak (e.g. `--set
    /// frames.frames_per_scene=100000`).
    Soak(soak::SoakArgs),
    /// Internal: the receiving process of `bench ipc`.
    #[command(hide = true)]
    IpcReceive(ipc::ReceiveArgs),
}

pub fn run(args: BenchArgs) -> anyhow::Result<ExitCode> {
    match args.what {
        BenchCommand::Ipc(args) => ipc::run(&args).map(|()| ExitCode::SUCCESS),
        BenchCommand::Ingest(args) => ingest::run(&args).map(|()| ExitCode::SUCCESS),
        BenchCommand::Model(args) => model::run(&args).map(|()| ExitCode::SUCCESS),
        BenchCommand::Soak(args) => soak::run(&args).map(|()| ExitCode::SUCCESS),
        BenchCommand::IpcReceive(args) => ipc::receive(&args).map(|()| ExitCode::SUCCESS),
        BenchCommand::Pipeline(args) => pipeline::run(&args).map(|()| ExitCode::SUCCESS),
    }
}
