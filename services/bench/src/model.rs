//! `poseflow bench model`: latency of a model's encoder and velocity
//! network through ONNX Runtime, alone: the network-only bound a pipeline
//! is compared with. `--batch B` runs B observations per call (the
//! encoder on B observations, the velocity network on B × N samples), as
//! the inference stage does for the objects of one frame.

use std::path::PathBuf;
use std::time::{Duration, Instant};

use clap::Args;
use poseflow_inference::{Condition, EncoderInput, InferenceError, PoseFlowModel, Precision};
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

/// One run of each network on synthetic inputs of the model's shapes: B
/// observations (objects in turn) for the encoder, N samples of each at
/// one flow time for the velocity network. What `bench model` and the
/// criterion benchmarks time.
#[derive(Debug)]
pub struct NetworkWorkload {
    image: Vec<f32>,
    token_mask: Vec<f32>,
    points: Vec<f32>,
    objects: Vec<usize>,
    rotations: Vec<f32>,
    translations: Vec<f32>,
    t: Vec<f32>,
}

impl NetworkWorkload {
    pub fn new(model: &PoseFlowModel, batch: usize, samples: usize) -> Self {
        let info = &model.info;
        let (s, p, n) = (info.image_size, info.patch_grid, info.point_count);
        let m = samples * batch;
        Self {
            image: vec![0.1; 3 * s * s],
            token_mask: vec![1.0; p * p],
            points: (0..3 * n).map(|i| ((i * 7919) % 101) as f32 * 1e-3 - 0.05).collect(),
            objects: (0..batch).map(|i| i % info.object_ids.len()).collect(),
            rotations: (0..m).flat_map(|_| [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]).collect(),
            translations: vec![0.01; 3 * m],
            t: vec![0.2; m],
        }
    }

    /// The B observations, for one encoder run
    /// ([`PoseFlowModel::encode_batch`]).
    pub fn inputs(&self) -> Vec<EncoderInput<'_>> {
        self.objects
            .iter()
            .map(|&object_index| EncoderInput {
                image: &self.image,
                token_mask: &self.token_mask,
                points: &self.points,
                object_index,
            })
            .collect()
    }

    /// Every sample of `conditions` (as many as the batch) in one velocity
    /// run.
    pub fn velocities(&self, model: &mut PoseFlowModel, conditions: &[&Condition]) -> Result<(), InferenceError> {
        model.velocity_batch(conditions, &self.rotations, &self.translations, &self.t).map(drop)
    }
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
    let contract = model.info.contract;
    let b = args.batch;
    let workload = NetworkWorkload::new(&model, b, args.samples);
    let inputs = workload.inputs();
    let mut conditions = Vec::new();
    let encoder = timed(args.runs, || {
        conditions = model.encode_batch(&inputs)?;
        Ok(())
    })?;
    let conditions: Vec<&Condition> = conditions.iter().collect();
    let velocity = timed(args.runs, || {
        workload.velocities(&mut model, &conditions)?;
        Ok(())
    })?;
    let (encoder, velocity) = (Timing::of(encoder), Timing::of(velocity));
    let report = Report {
        model: args.model.clone(),
        precision: args.precision.name(),
        contract,
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
