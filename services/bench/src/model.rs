//! `poseflow bench model`: latency of a model's encoder and velocity
//! network through ONNX Runtime, alone: the network-only bound a pipeline
//! is compared with. `--batch B` runs B observations per call (the
//! encoder on B observations, the velocity network on B × N samples), as
//! the inference stage does for the objects of one frame.

use std::path::PathBuf;
use std::time::{Duration, Instant};

use clap::Args;
use poseflow_inference::{Condition, EncoderInput, PoseFlowModel, Precision};
use serde::Serialize;

use poseflow_runtime::timing::Timing;

#[derive(Debug, Args)]
pub struct ModelArgs {
    /// Model directory (encoder.onnx, velocity.onnx).
    #[arg(long, default_value = "models/poseflow-lmo10")]
    pub model: PathBuf,
    /// Which files: int8 (encoder.int8.onnx, velocity.int8.onnx; the
    /// inference stage's default) or fp32 (encoder.onnx, velocity.onnx).
    #[arg(long, default_value = "int8")]
    pub precision: Precision,
    /// ONNX Runtime intra-op threads.
    #[arg(long, default_value_t = 2)]
    pub threads: usize,
    /// Samples per observation in a velocity call (N).
    #[arg(long, default_value_t = 50)]
    pub samples: usize,
    /// Observations per call (B): the encoder encodes B at once, the
    /// velocity network takes B × N samples.
    #[arg(long, default_value_t = 1)]
    pub batch: usize,
    /// Timed runs of each network (after 5 warm-up runs).
    #[arg(long, default_value_t = 50)]
    pub runs: usize,
    /// Print one JSON object instead of text.
    #[arg(long)]
    pub json: bool,
}

#[derive(Debug, Serialize)]
struct Report {
    model: PathBuf,
    precision: &'static str,
    contract: u32,
    threads: usize,
    samples: usize,
    batch: usize,
    /// Per call of B observations.
    encoder: Timing,
    /// Per call of B × N samples.
    velocity: Timing,
    encoder_per_observation_ms: f64,
    velocity_per_observation_ms: f64,
}

fn timed(runs: usize, mut f: impl FnMut() -> anyhow::Result<()>) -> anyhow::Result<Vec<Duration>> {
    for _ in 0..5 {
        f()?;
    }
    (0..runs)
        .map(|_| {
            let started = Instant::now();
            f().map(|()| started.elapsed())
        })
        .collect()
}

pub fn run(args: &ModelArgs) -> anyhow::Result<()> {
    if args.batch == 0 || args.samples == 0 || args.runs == 0 {
        anyhow::bail!(
            "--batch {}, --samples {}, --runs {}: expected at least 1 each",
            args.batch,
            args.samples,
            args.runs
        );
    }
    let mut model = PoseFlowModel::load_as(&args.model, args.threads, args.precision)?;
    let info = model.info.clone();
    let (s, p, n, b) = (info.image_size, info.patch_grid, info.point_count, args.batch);
    let image = vec![0.1f32; 3 * s * s];
    let token_mask = vec![1.0f32; p * p];
    let points: Vec<f32> = (0..3 * n).map(|i| ((i * 7919) % 101) as f32 * 1e-3 - 0.05).collect();
    let inputs: Vec<EncoderInput> = (0..b)
        .map(|i| EncoderInput {
            image: &image,
            token_mask: &token_mask,
            points: &points,
            object_index: i % info.object_ids.len(),
        })
        .collect();
    let mut conditions = Vec::new();
    let encoder = timed(args.runs, || {
        conditions = model.encode_batch(&inputs)?;
        Ok(())
    })?;
    let conditions: Vec<&Condition> = conditions.iter().collect();
    let m = args.samples * b;
    let rotations: Vec<f32> = (0..m).flat_map(|_| [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]).collect();
    let translations = vec![0.01f32; 3 * m];
    let t = vec![0.2f32; m];
    let velocity = timed(args.runs, || {
        model.velocity_batch(&conditions, &rotations, &translations, &t)?;
        Ok(())
    })?;
    let (encoder, velocity) = (Timing::of(encoder), Timing::of(velocity));
    let report = Report {
        model: args.model.clone(),
        precision: args.precision.name(),
        contract: info.contract,
        threads: args.threads,
        samples: args.samples,
        batch: b,
        encoder_per_observation_ms: encoder.p50_ms / b as f64,
        velocity_per_observation_ms: velocity.p50_ms / b as f64,
        encoder,
        velocity,
    };
    if args.json {
        println!("{}", serde_json::to_string(&report)?);
    } else {
        println!(
            "{} ({}, poseflow-onnx/{}): encoder {:.2} ms per call of {b} (p99 {:.2}; {:.2} per observation), velocity {:.2} ms per call of {b} × {} samples (p99 {:.2}; {:.2} per observation), {} threads",
            report.model.display(),
            report.precision,
            report.contract,
            report.encoder.p50_ms,
            report.encoder.p99_ms,
            report.encoder_per_observation_ms,
            report.velocity.p50_ms,
            args.samples,
            report.velocity.p99_ms,
            report.velocity_per_observation_ms,
            report.threads
        );
    }
    Ok(())
}
