//! `poseflow bench model`: latency of a model's encoder (one observation)
//! and velocity network (a batch of samples) through ONNX Runtime.

use std::path::PathBuf;
use std::time::{Duration, Instant};

use clap::Args;
use poseflow_inference::PoseFlowModel;
use serde::Serialize;

use poseflow_runtime::timing::Timing;

#[derive(Debug, Args)]
pub struct ModelArgs {
    /// Model directory (encoder.onnx, velocity.onnx).
    #[arg(long, default_value = "models/test-tiny")]
    pub model: PathBuf,
    /// ONNX Runtime intra-op threads.
    #[arg(long, default_value_t = 2)]
    pub threads: usize,
    /// Samples per velocity batch (N).
    #[arg(long, default_value_t = 50)]
    pub samples: usize,
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
    threads: usize,
    samples: usize,
    encoder: Timing,
    velocity: Timing,
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
    let mut model = PoseFlowModel::load(&args.model, args.threads)?;
    let info = model.info.clone();
    let (s, p, n) = (info.image_size, info.patch_grid, info.point_count);
    let image = vec![0.1f32; 3 * s * s];
    let token_mask = vec![1.0f32; p * p];
    let points: Vec<f32> = (0..3 * n).map(|i| ((i * 7919) % 101) as f32 * 1e-3 - 0.05).collect();
    let mut condition = None;
    let encoder = timed(args.runs, || {
        condition = Some(model.encode(&image, &token_mask, &points, 0)?);
        Ok(())
    })?;
    let condition = condition.expect("encoded above");
    let m = args.samples;
    let rotations: Vec<f32> = (0..m).flat_map(|_| [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]).collect();
    let translations = vec![0.01f32; 3 * m];
    let t = vec![0.2f32; m];
    let velocity = timed(args.runs, || {
        model.velocity(&condition, &rotations, &translations, &t)?;
        Ok(())
    })?;
    let report = Report {
        model: args.model.clone(),
        threads: args.threads,
        samples: m,
        encoder: Timing::of(encoder),
        velocity: Timing::of(velocity),
    };
    if args.json {
        println!("{}", serde_json::to_string(&report)?);
    } else {
        println!(
            "{}: encoder {:.2} ms per observation (p99 {:.2}), velocity {:.2} ms per batch of {m} (p99 {:.2}), {} threads",
            report.model.display(),
            report.encoder.p50_ms,
            report.encoder.p99_ms,
            report.velocity.p50_ms,
            report.velocity.p99_ms,
            report.threads
        );
    }
    Ok(())
}
