//! The ground truth an evaluation scores against: per image of the frame
//! source's stream, its camera and the targeted object instances.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::{Context, bail};
use poseflow_geometry::Pose;
use poseflow_ingest::sources::BopFrames;
use poseflow_scene::Camera;
use poseflow_scene::bop::{ByImage, CameraEntry, GtEntry, GtInfoEntry, SceneDir, read_depth_png, read_json};

use super::score::{ImageCamera, TestDepth};

/// BOP19 scores only instances with at least this much of their silhouette
/// visible.
pub const MIN_VISIB_FRACT: f64 = 0.1;

#[derive(Debug, Clone)]
pub struct TruthInstance {
    pub obj_id: u32,
    /// Its position in the image's `scene_gt.json` list (the instance
    /// number of its mask files).
    pub gt_index: usize,
    pub pose: Pose,
    /// Below [`MIN_VISIB_FRACT`] the instance is not scored (an estimate of
    /// it is neither a hit nor a miss).
    pub scored: bool,
    /// `scene_gt_info.json`'s visible fraction, when the dataset has it.
    pub visib_fract: Option<f64>,
}

#[derive(Debug, Clone)]
pub struct TruthImage {
    pub scene_id: u32,
    pub im_id: u32,
    pub camera: ImageCamera,
    /// The image's depth PNG, when the dataset has one (for VSD).
    pub depth: Option<DepthFile>,
    /// The targeted instances (every annotated one without targets).
    pub instances: Vec<TruthInstance>,
}

/// A depth PNG and what reading it needs.
#[derive(Debug, Clone)]
pub struct DepthFile {
    pub path: PathBuf,
    pub depth_scale: f64,
    pub camera: Camera,
}

impl DepthFile {
    pub fn read(&self) -> anyhow::Result<TestDepth> {
        let raster = read_depth_png(&self.path, self.depth_scale)?;
        if (raster.width, raster.height) != (self.camera.width, self.camera.height) {
            bail!(
                "{}: {}×{} pixels, the image's rgb is {}×{}",
                self.path.display(),
                raster.width,
                raster.height,
                self.camera.width,
                self.camera.height
            );
        }
        Ok(TestDepth { camera: self.camera, depth: raster.pixels })
    }
}

struct SceneFiles {
    cameras: ByImage<CameraEntry>,
    gts: ByImage<Vec<GtEntry>>,
    infos: Option<ByImage<Vec<GtInfoEntry>>>,
}

fn read_scene(dir: &SceneDir) -> anyhow::Result<SceneFiles> {
    let infos = dir.scene_gt_info().is_file().then(|| read_json(&dir.scene_gt_info())).transpose()?;
    Ok(SceneFiles { cameras: read_json(&dir.scene_camera())?, gts: read_json(&dir.scene_gt())?, infos })
}

/// The truth of every image `frames` will deliver, in frame-id order.
pub fn read_truth(split_dir: &Path, frames: &BopFrames) -> anyhow::Result<Vec<TruthImage>> {
    let mut scenes: BTreeMap<u32, SceneFiles> = BTreeMap::new();
    let mut images = Vec::with_capacity(frames.len());
    for (scene_id, im_id, wanted) in frames.images() {
        let dir = SceneDir::new(split_dir, scene_id);
        let files = match scenes.entry(scene_id) {
            std::collections::btree_map::Entry::Occupied(entry) => entry.into_mut(),
            std::collections::btree_map::Entry::Vacant(entry) => entry.insert(read_scene(&dir)?),
        };
        let missing = |file: &Path| format!("{}: no entry for image {im_id}", file.display());
        let entry = files.cameras.get(&im_id).with_context(|| missing(&dir.scene_camera()))?;
        let (width, height) = image::image_dimensions(dir.rgb(im_id))
            .with_context(|| format!("{}: cannot read the image size", dir.rgb(im_id).display()))?;
        let k = &entry.cam_k;
        let camera = ImageCamera { pinhole: entry.pinhole(), width };
        let depth = dir.depth(im_id).is_file().then(|| DepthFile {
            path: dir.depth(im_id),
            depth_scale: entry.depth_scale,
            camera: Camera { fx: k[0], fy: k[4], cx: k[2], cy: k[5], width, height },
        });
        let gts = files.gts.get(&im_id).with_context(|| missing(&dir.scene_gt()))?;
        let infos = files.infos.as_ref().and_then(|infos| infos.get(&im_id));
        let mut instances = Vec::new();
        for (index, gt) in gts.iter().enumerate() {
            if !wanted.is_empty() && !wanted.contains(&gt.obj_id) {
                continue;
            }
            let visib_fract = infos.and_then(|infos| infos.get(index)).map(|info| info.visib_fract);
            instances.push(TruthInstance {
                obj_id: gt.obj_id,
                gt_index: index,
                pose: gt.pose(&dir.scene_gt(), im_id, index)?,
                scored: visib_fract.unwrap_or(1.0) >= MIN_VISIB_FRACT,
                visib_fract,
            });
        }
        images.push(TruthImage { scene_id, im_id, camera, depth, instances });
    }
    Ok(images)
}
