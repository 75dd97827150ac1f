//! `poseflow observe`: a BOP dataset's observations with their ground
//! truth, as a training shard (`services/ingest/src/shard.rs`).

use std::path::PathBuf;

use anyhow::Context;
use clap::Args;
use poseflow_ingest::shard::{ShardInfo, record_bytes, write_shard};
use poseflow_ingest::sources::{BopFrames, Masks};
use poseflow_ingest::{IngestParams, MaskJitter};

use poseflow_runtime::progress::Progress;

#[derive(Debug, Args)]
#[command(
    after_help = "Example:\n  poseflow observe --dataset data/lmo-synth --split train --out data/lmo-synth/train.obs \
    --image-size 112 --patch-grid 8\n  poseflow observe --dataset data/lmo-synth --split train --out data/lmo-synth/train-jittered.obs \
    --image-size 112 --patch-grid 8 --grow-masks 4 --shrink-masks 2 --shift-depth 2\n\nThe crops, token masks and points are made by the ingest stage's own code, so \
    a network trained on them sees exactly what the running graph feeds it."
)]
pub struct ObserveArgs {
    /// BOP dataset root (ground-truth masks and poses are read from it).
    #[arg(long)]
    pub dataset: PathBuf,
    /// Split folder.
    #[arg(long, default_value = "train")]
    pub split: String,
    /// Shard file to write.
    #[arg(long)]
    pub out: PathBuf,
    /// Ingest parameters (TOML, as config/ingest.toml); the flags below override it.
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Crop size S.
    #[arg(long)]
    pub image_size: Option<u32>,
    /// Patch grid P.
    #[arg(long)]
    pub patch_grid: Option<u32>,
    /// Points N.
    #[arg(long)]
    pub points: Option<usize>,
    /// Training data: grow each object's mask by up to this many pixels (uniform with --shrink-masks), as a
    /// detector's mask or depth misregistration puts background into it.
    #[arg(long, default_value_t = 0, value_name = "PX")]
    pub grow_masks: u32,
    /// Training data: shrink each object's mask by up to this many pixels.
    #[arg(long, default_value_t = 0, value_name = "PX")]
    pub shrink_masks: u32,
    /// Training data: move each frame's depth image by up to this many pixels along x and y against the colour
    /// image and masks (a sensor's depth-to-colour registration error).
    #[arg(long, default_value_t = 0, value_name = "PX")]
    pub shift_depth: u32,
    /// Training data: pixels within this many of each mask's outline take random values (in 2×2 patches), as a
    /// detector's ragged outline.
    #[arg(long, default_value_t = 0, value_name = "PX")]
    pub ragged_masks: u32,
    /// Training data: with this probability a straight cut removes up to 40 % of an object's mask, as a detector
    /// that misses part of an object.
    #[arg(long, default_value_t = 0.0, value_name = "P")]
    pub cut_masks: f64,
    /// Print the counts as JSON.
    #[arg(long)]
    pub json: bool,
}

pub fn run(args: &ObserveArgs) -> anyhow::Result<()> {
    let mut params = match &args.config {
        Some(path) => {
            let text = std::fs::read_to_string(path).with_context(|| format!("--config {}", path.display()))?;
            let table: toml::Table = toml::from_str(&text).with_context(|| format!("--config {}", path.display()))?;
            IngestParams::from_json(&serde_json::to_value(table)?)
                .with_context(|| format!("--config {}", path.display()))?
        }
        None => IngestParams::default(),
    };
    params.image_size = args.image_size.unwrap_or(params.image_size);
    params.patch_grid = args.patch_grid.unwrap_or(params.patch_grid);
    params.point_count = args.points.unwrap_or(params.point_count);
    params.max_filter_points = params.max_filter_points.max(params.point_count);
    params.validate()?;
    let mut frames = BopFrames::open(&args.dataset, &args.split, &[], None, Masks::GroundTruth)
        .with_context(|| format!("--dataset {}", args.dataset.display()))?;
    let info = ShardInfo {
        image_size: params.image_size,
        patch_grid: params.patch_grid,
        point_count: params.point_count,
        normalisation: params.normalisation,
        record_bytes: record_bytes(&params),
        dataset: args.dataset.display().to_string(),
        split: args.split.clone(),
    };
    let mut progress = Progress::new("observe", frames.len() as u64);
    let split_dir = args.dataset.join(&args.split);
    if !(0.0..=1.0).contains(&args.cut_masks) {
        anyhow::bail!("--cut-masks {}: expected a probability in [0, 1]", args.cut_masks);
    }
    let jitter = MaskJitter {
        grow: args.grow_masks,
        shrink: args.shrink_masks,
        shift: args.shift_depth,
        ragged: args.ragged_masks,
        cut: args.cut_masks,
    };
    let counts = write_shard(&mut frames, &split_dir, &params, &jitter, &info, &args.out, |c| {
        progress.update(c.frames, &format!("{} observations", c.records))
    })
    .with_context(|| format!("--out {}", args.out.display()))?;
    if args.json {
        println!("{}", serde_json::to_string(&counts)?);
    } else {
        println!(
            "wrote {} observations of {} frames to {} ({} rejected, {} bytes each)",
            counts.records,
            counts.frames,
            args.out.display(),
            counts.rejected,
            info.record_bytes
        );
    }
    Ok(())
}
