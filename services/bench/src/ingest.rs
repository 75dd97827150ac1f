//! `poseflow bench ingest`: observations per second on one core, for the
//! frames of a BOP dataset held in memory.

use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::Context;
use clap::Args;
use poseflow_contracts::MessageHeader;
use poseflow_geometry::sampling::seeded_rng;
use poseflow_ingest::sources::{BopFrames, FrameSource, Masks};
use poseflow_ingest::{IngestParams, prepare};
use serde::Serialize;

use poseflow_runtime::timing::Timing;

#[derive(Debug, Args)]
pub struct IngestArgs {
    /// BOP dataset root (e.g. written by `poseflow render`).
    #[arg(long)]
    pub dataset: PathBuf,
    /// Split folder.
    #[arg(long, default_value = "test")]
    pub split: String,
    /// Crop size S.
    #[arg(long, default_value_t = 224)]
    pub image_size: u32,
    /// Patch grid P.
    #[arg(long, default_value_t = 16)]
    pub patch_grid: u32,
    /// Points N per observation.
    #[arg(long, default_value_t = 1024)]
    pub points: usize,
    /// Passes over the frames.
    #[arg(long, default_value_t = 3)]
    pub repeat: u32,
    /// Print one JSON object instead of text.
    #[arg(long)]
    pub json: bool,
}

#[derive(Debug, Serialize)]
struct Report {
    frames: usize,
    observations: usize,
    rejected: usize,
    /// PNG decoding and checks per frame (not part of the observation rate).
    load_ms_per_frame: f64,
    observations_per_s_per_core: f64,
    /// Per observation.
    observe: Timing,
}

pub fn run(args: &IngestArgs) -> anyhow::Result<()> {
    let params = IngestParams {
        image_size: args.image_size,
        patch_grid: args.patch_grid,
        point_count: args.points,
        max_filter_points: IngestParams::default().max_filter_points.max(args.points),
        ..IngestParams::default()
    };
    params.validate()?;
    let started = Instant::now();
    let mut source = BopFrames::open(&args.dataset, &args.split, &[], None, Masks::GroundTruth)
        .with_context(|| format!("--dataset {}", args.dataset.display()))?;
    let mut frames = Vec::new();
    while let Some(loaded) = source.next_frame() {
        frames.push(loaded?);
    }
    let load = started.elapsed() / frames.len().max(1) as u32;
    let mut times: Vec<Duration> = Vec::new();
    let mut rejected = 0;
    let mut rng = seeded_rng(0);
    // One output buffer, as the stage writes into a reused shared-memory
    // sample: the timing is of the observation, not of the allocator.
    let mut payload: Vec<f32> = Vec::new();
    for _ in 0..args.repeat {
        for loaded in &frames {
            for object in &loaded.objects {
                let started = Instant::now();
                let Ok(prepared) = prepare(&loaded.frame, object, &params, &mut rng) else {
                    rejected += 1;
                    continue;
                };
                let header = prepared.header(loaded.frame.frame_id, &loaded.frame.camera, &params);
                payload.resize(header.payload_len()?, 0.0);
                prepared.write_payload(&loaded.frame, object, &params, &mut payload);
                std::hint::black_box(&payload);
                times.push(started.elapsed());
            }
        }
    }
    let observations = times.len();
    let timing = Timing::of(times);
    let report = Report {
        frames: frames.len(),
        observations,
        rejected,
        load_ms_per_frame: load.as_secs_f64() * 1e3,
        observations_per_s_per_core: 1e3 / timing.mean_ms,
        observe: timing,
    };
    if args.json {
        println!("{}", serde_json::to_string(&report)?);
    } else {
        println!(
            "{} observations of {} frames ({} rejected): {:.2} ms each (p50 {:.2}, p99 {:.2}) = {:.0} observations/s \
             on one core; reading a frame {:.1} ms",
            report.observations,
            report.frames,
            report.rejected,
            report.observe.mean_ms,
            report.observe.p50_ms,
            report.observe.p99_ms,
            report.observations_per_s_per_core,
            report.load_ms_per_frame
        );
    }
    Ok(())
}
