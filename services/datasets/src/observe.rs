//! `poseflow observe`: a BOP dataset's observations with their ground
//! truth, as a training shard (`services/ingest/src/shard.rs`).

use std::path::PathBuf;

use anyhow::Context;
use clap::Args;
use poseflow_detector::{Detector, DetectorParams, ImageView};
use poseflow_geometry::metrics::Pinhole;
use poseflow_ingest::shard::{ShardInfo, record_bytes, write_shard};
use poseflow_ingest::sources::{BopFrames, FrameSource, LoadedFrame, Masks};
use poseflow_ingest::{IngestError, IngestParams, MaskJitter};

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
    /// Training data: each annotated object that this detector finds (a detection of the object at mask IoU
    /// ≥ 0.5) takes the detector's mask, as the detect graphs hand it to the pose stages; the others keep their
    /// annotated masks. The detector's model directory, e.g. models/detector-lmo10 (config/detector.toml's
    /// defaults).
    #[arg(long, value_name = "DIR")]
    pub detector_masks: Option<PathBuf>,
    /// Print the counts as JSON.
    #[arg(long)]
    pub json: bool,
}

/// A detection stands for an annotated object from this mask IoU on, as
/// `poseflow eval --detect` counts an object found.
const MIN_DETECTOR_IOU: f64 = 0.5;

/// Frames whose annotated masks are swapped for the detector's where it
/// finds the object (with a detector), counting both.
#[derive(Debug)]
struct ObservedFrames<S> {
    frames: S,
    detector: Option<Detector>,
    swapped: u64,
    kept: u64,
}

impl<S: FrameSource> FrameSource for ObservedFrames<S> {
    fn next_frame(&mut self) -> Option<Result<LoadedFrame, IngestError>> {
        let loaded = self.frames.next_frame()?;
        let Some(detector) = self.detector.as_mut() else { return Some(loaded) };
        Some(loaded.and_then(|mut loaded| {
            let (swapped, kept) = swap_masks(detector, &mut loaded)?;
            self.swapped += swapped;
            self.kept += kept;
            Ok(loaded)
        }))
    }
}

/// Replaces the mask of each object of `loaded` that the detector finds by
/// its best detection's; how many were swapped and how many kept.
fn swap_masks(detector: &mut Detector, loaded: &mut LoadedFrame) -> Result<(u64, u64), IngestError> {
    let frame = &loaded.frame;
    let (width, height) = (frame.rgb.width as usize, frame.rgb.height as usize);
    let rgb: Vec<f32> = frame.rgb.pixels.iter().flat_map(|p| p.map(f32::from)).collect();
    let c = &frame.camera;
    let camera = Pinhole { fx: c.fx, fy: c.fy, cx: c.cx, cy: c.cy };
    let image = ImageView { rgb: &rgb, depth: &frame.depth.pixels, width, height, camera };
    let found = detector
        .detect(&image)
        .map_err(|e| IngestError::Frame { frame: frame.label.clone(), detail: format!("--detector-masks: {e}") })?;
    let (mut swapped, mut kept) = (0, 0);
    for object in &mut loaded.objects {
        let best = found
            .objects
            .iter()
            .filter(|d| d.obj_id == object.obj_id)
            .map(|d| (d.iou(&object.mask.pixels, width), d))
            .max_by(|a, b| a.0.total_cmp(&b.0));
        match best {
            Some((iou, detection)) if iou >= MIN_DETECTOR_IOU => {
                object.mask.pixels = detection.frame_mask(width, height);
                swapped += 1;
            }
            _ => kept += 1,
        }
    }
    Ok((swapped, kept))
}

/// What `observe` wrote, as `--json` prints it.
#[derive(Debug, serde::Serialize)]
struct ObserveCounts {
    #[serde(flatten)]
    shard: poseflow_ingest::shard::ShardCounts,
    /// With --detector-masks: objects given the detector's mask, and the
    /// ones it did not find (annotated mask kept).
    #[serde(skip_serializing_if = "Option::is_none")]
    detector_masks: Option<u64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    annotated_masks: Option<u64>,
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
    let bop = BopFrames::open(&args.dataset, &args.split, &[], None, Masks::GroundTruth)
        .with_context(|| format!("--dataset {}", args.dataset.display()))?;
    let total = bop.len() as u64;
    let detector = match &args.detector_masks {
        Some(dir) => {
            let params = DetectorParams::from_json(&serde_json::json!({ "model": dir }))
                .with_context(|| format!("--detector-masks {}", dir.display()))?;
            Some(Detector::new(params).with_context(|| format!("--detector-masks {}", dir.display()))?)
        }
        None => None,
    };
    let mut frames = ObservedFrames { frames: bop, detector, swapped: 0, kept: 0 };
    let info = ShardInfo {
        image_size: params.image_size,
        patch_grid: params.patch_grid,
        point_count: params.point_count,
        normalisation: params.normalisation,
        record_bytes: record_bytes(&params),
        dataset: args.dataset.display().to_string(),
        split: args.split.clone(),
    };
    let mut progress = Progress::new("observe", total);
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
    let shard = write_shard(&mut frames, &split_dir, &params, &jitter, &info, &args.out, |c| {
        progress.update(c.frames, &format!("{} observations", c.records))
    })
    .with_context(|| format!("--out {}", args.out.display()))?;
    let counts = ObserveCounts {
        shard,
        detector_masks: frames.detector.is_some().then_some(frames.swapped),
        annotated_masks: frames.detector.is_some().then_some(frames.kept),
    };
    if args.json {
        println!("{}", serde_json::to_string(&counts)?);
    } else {
        let shard = &counts.shard;
        println!(
            "wrote {} observations of {} frames to {} ({} rejected, {} bytes each)",
            shard.records,
            shard.frames,
            args.out.display(),
            shard.rejected,
            info.record_bytes
        );
        if let (Some(swapped), Some(kept)) = (counts.detector_masks, counts.annotated_masks) {
            println!("detector masks: {swapped} objects; annotated masks kept: {kept} objects the detector missed");
        }
    }
    Ok(())
}
