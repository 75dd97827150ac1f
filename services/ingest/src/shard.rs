//! Training shards: the observations of a BOP dataset with their ground
//! truth, written by the same code that serves them (so the network trains
//! on exactly what the ingest stage will feed it) and read by the training
//! code (`training/`).
//!
//! File layout: the line `POSEFLOW-OBS v1`, one line of JSON
//! ([`ShardInfo`]: sizes, normalisation, record layout), then fixed-size
//! little-endian records until the end of the file:
//!
//! | field | type | meaning |
//! |---|---|---|
//! | obj_id, scene_id, im_id, instance | 4 × u32 | BOP ids |
//! | rotation | 9 × f32 | GT `cam_R_m2c`, row-major |
//! | translation | 3 × f32 | GT `cam_t_m2c`, metres |
//! | centroid | 3 × f32 | subtracted from the points, camera frame, metres |
//! | crop | 4 × f32 | x_min, y_min, x_max, y_max (full-image pixels) |
//! | intrinsics | 4 × f32 | fx, fy, cx, cy |
//! | valid_point_count | u32 | distinct observed points among the N |
//! | visib_fract | f32 | from `scene_gt_info.json` |
//! | token_mask | P·P × u8 | 1 = patch touches the mask |
//! | image | 3·S·S × u8 | the crop before normalisation, CHW, RGB |
//! | points | N·3 × f32 | centred, metres |

use std::io::Write;
use std::path::Path;

use poseflow_geometry::Pose;
use poseflow_geometry::sampling::seeded_rng;
use poseflow_scene::SceneError;
use poseflow_scene::bop::Raster;
use poseflow_scene::bop::{self, ByImage, GtEntry, GtInfoEntry, SceneDir};
use serde::Serialize;

use crate::sources::{FrameSource, LoadedFrame};
use crate::{
    IngestError, IngestParams, MaskJitter, Normalisation, ObjectMask, Prepared, prepare, write_crop, write_token_mask,
};

pub const MAGIC: &str = "POSEFLOW-OBS v1";

/// Mixed into the frame id for the jitter's draws, so that they do not
/// repeat the point sampling's (seeded by the frame id alone).
const JITTER_SEED: u64 = 0x6a69_7474_6572;

/// The JSON line after the magic.
#[derive(Debug, Clone, Serialize)]
pub struct ShardInfo {
    pub image_size: u32,
    pub patch_grid: u32,
    pub point_count: usize,
    /// To apply to the stored `image` bytes: `(value/255 − mean)/std`.
    pub normalisation: Normalisation,
    pub record_bytes: usize,
    pub dataset: String,
    pub split: String,
}

/// Bytes of one record for these parameters.
pub fn record_bytes(params: &IngestParams) -> usize {
    let (s, p) = (params.image_size as usize, params.patch_grid as usize);
    4 * 4 + 4 * (9 + 3 + 3 + 4 + 4) + 4 + 4 + p * p + 3 * s * s + 4 * 3 * params.point_count
}

/// Counts of a shard written by [`write_shard`].
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize)]
pub struct ShardCounts {
    pub frames: u64,
    pub records: u64,
    /// Objects ingest rejected (tiny masks, no depth) or frames it could not read.
    pub rejected: u64,
}

fn push_f32s(out: &mut Vec<u8>, values: impl IntoIterator<Item = f32>) {
    for v in values {
        out.extend_from_slice(&v.to_le_bytes());
    }
}

fn push_u32s(out: &mut Vec<u8>, values: impl IntoIterator<Item = u32>) {
    for v in values {
        out.extend_from_slice(&v.to_le_bytes());
    }
}

/// One record; `truth` (camera from object, metres, projected onto SO(3)
/// as BOP's rounded rotations need) and `info` are the instance's ground
/// truth.
fn record(
    loaded: &LoadedFrame,
    prepared: &Prepared,
    object: &ObjectMask,
    truth: &Pose,
    info: &GtInfoEntry,
    params: &IngestParams,
) -> Vec<u8> {
    let (s, p) = (params.image_size as usize, params.patch_grid as usize);
    let mut out = Vec::with_capacity(record_bytes(params));
    push_u32s(&mut out, [object.obj_id, loaded.scene_id, loaded.image_id, object.instance as u32]);
    let r = truth.rotation.matrix();
    push_f32s(&mut out, (0..9).map(|i| r[(i / 3, i % 3)] as f32));
    push_f32s(&mut out, truth.translation.iter().map(|&v| v as f32));
    push_f32s(&mut out, prepared.centroid.coords.iter().copied());
    push_f32s(&mut out, prepared.crop.corners());
    let c = &loaded.frame.camera;
    push_f32s(&mut out, [c.fx, c.fy, c.cx, c.cy].map(|v| v as f32));
    push_u32s(&mut out, [prepared.valid_point_count as u32]);
    push_f32s(&mut out, [info.visib_fract as f32]);
    let mut tokens = vec![0.0f32; p * p];
    write_token_mask(&object.mask.pixels, object.mask.width, &prepared.crop, p, &mut tokens);
    out.extend(tokens.iter().map(|&t| t as u8));
    let raw = Normalisation { mean: [0.0; 3], std: [1.0 / 255.0; 3] };
    let mut image = vec![0.0f32; 3 * s * s];
    let rgb: &Raster<[u8; 3]> = &loaded.frame.rgb;
    write_crop(&rgb.pixels, rgb.width, rgb.height, &prepared.crop, s, &raw, &mut image);
    out.extend(image.iter().map(|&v| v.round().clamp(0.0, 255.0) as u8));
    push_f32s(&mut out, prepared.points.iter().flat_map(|q| [q.x, q.y, q.z]));
    debug_assert_eq!(out.len(), record_bytes(params));
    out
}

/// The ground truth of the scene being written.
struct SceneTruth {
    scene_id: u32,
    gts: ByImage<Vec<GtEntry>>,
    infos: ByImage<Vec<GtInfoEntry>>,
}

/// Writes the observations of every frame of `frames` (a BOP source with
/// ground-truth masks) and their ground truth to `out`, calling `progress`
/// after each frame. `jitter` imitates real masks and registration (its
/// draws are seeded by frame id, apart from the point sampling's).
pub fn write_shard(
    frames: &mut dyn FrameSource,
    split_dir: &Path,
    params: &IngestParams,
    jitter: &MaskJitter,
    info: &ShardInfo,
    out: &Path,
    mut progress: impl FnMut(&ShardCounts),
) -> Result<ShardCounts, IngestError> {
    let file = std::fs::File::create(out).map_err(|source| SceneError::Write { path: out.to_path_buf(), source })?;
    let mut writer = std::io::BufWriter::new(file);
    let write_error = |source| IngestError::File(SceneError::Write { path: out.to_path_buf(), source });
    writeln!(writer, "{MAGIC}").map_err(write_error)?;
    writeln!(writer, "{}", serde_json::to_string(info).expect("plain data")).map_err(write_error)?;
    let mut counts = ShardCounts::default();
    let mut truth: Option<SceneTruth> = None;
    while let Some(loaded) = frames.next_frame() {
        counts.frames += 1;
        let mut loaded = match loaded {
            Ok(loaded) => loaded,
            Err(err) => {
                tracing::warn!(%err, "frame skipped");
                counts.rejected += 1;
                continue;
            }
        };
        if truth.as_ref().is_none_or(|t| t.scene_id != loaded.scene_id) {
            let dir = SceneDir::new(split_dir, loaded.scene_id);
            truth = Some(SceneTruth {
                scene_id: loaded.scene_id,
                gts: bop::read_json(&dir.scene_gt())?,
                infos: bop::read_json(&dir.scene_gt_info())?,
            });
        }
        let SceneTruth { gts, infos, .. } = truth.as_ref().expect("read above");
        let mut jitter_rng = seeded_rng(loaded.frame.frame_id ^ JITTER_SEED);
        jitter.apply(&mut loaded.frame, &mut loaded.objects, &mut jitter_rng);
        let mut rng = seeded_rng(loaded.frame.frame_id);
        let scene_gt = SceneDir::new(split_dir, loaded.scene_id).scene_gt();
        for object in &loaded.objects {
            let gt = gts.get(&loaded.image_id).and_then(|g| g.get(object.instance));
            let info = infos.get(&loaded.image_id).and_then(|g| g.get(object.instance));
            let (Some(gt), Some(info)) = (gt, info) else {
                counts.rejected += 1;
                continue;
            };
            let gt = match gt.pose(&scene_gt, loaded.image_id, object.instance) {
                Ok(pose) => pose,
                Err(err) => {
                    tracing::warn!(%err, "object skipped");
                    counts.rejected += 1;
                    continue;
                }
            };
            match prepare(&loaded.frame, object, params, &mut rng) {
                Ok(prepared) => {
                    writer.write_all(&record(&loaded, &prepared, object, &gt, info, params)).map_err(write_error)?;
                    counts.records += 1;
                }
                Err(_) => counts.rejected += 1,
            }
        }
        progress(&counts);
    }
    writer.flush().map_err(write_error)?;
    Ok(counts)
}
