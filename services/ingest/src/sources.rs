//! Where frames come from: a BOP dataset directory, or the renderer as a
//! live synthetic camera. Each yields frames with the object masks to
//! observe; a frame that cannot be read is an error for that frame only.

use std::path::{Path, PathBuf};

use poseflow_scene::bop::{self, ByImage, CameraEntry, GtEntry, Raster, SceneDir};
use poseflow_scene::dataset::{RenderSpec, frame as render_frame, scene as render_scene};
use poseflow_scene::{ModelLibrary, SceneError};
use serde::Deserialize;

use crate::{IngestError, ObjectMask, RgbdFrame};

/// A frame and the objects to observe in it; objects whose mask could not
/// be read are in `skipped`.
#[derive(Debug)]
pub struct LoadedFrame {
    pub frame: RgbdFrame,
    pub objects: Vec<ObjectMask>,
    pub skipped: Vec<IngestError>,
    /// Where the frame came from in its dataset.
    pub scene_id: u32,
    pub image_id: u32,
    /// When a camera captured it (ns since the epoch, the stamps' clock),
    /// for the frame's `Source` stamp; `None`: when it is published.
    pub captured_ns: Option<u64>,
}

/// A stream of frames. `None` ends the stream.
pub trait FrameSource: Send + std::fmt::Debug {
    fn next_frame(&mut self) -> Option<Result<LoadedFrame, IngestError>>;

    /// A live source waits here, a short while at most, for its next frame;
    /// false when none came yet (the stage reports itself idle and asks
    /// again, so it stays responsive to signals). Files and the renderer are
    /// always ready.
    fn wait_ready(&mut self) -> bool {
        true
    }

    /// Input the source had to drop since the last call (a live camera's
    /// messages left unpaired or refused); the stage counts them with its
    /// rejected inputs.
    fn take_dropped(&mut self) -> u64 {
        0
    }
}

/// One image of a BOP dataset and the instances to observe in it.
#[derive(Debug, Clone, PartialEq)]
struct Target {
    scene_id: u32,
    im_id: u32,
    /// Object ids wanted in this image; empty = every annotated instance.
    obj_ids: Vec<u32>,
}

/// An entry of `test_targets_bop19.json`.
#[derive(Deserialize)]
struct TargetEntry {
    scene_id: u32,
    im_id: u32,
    obj_id: u32,
}

/// Where the object masks of a BOP frame come from.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Masks {
    /// The dataset's visible masks (`mask_visib/`) of the instances in
    /// `scene_gt.json`.
    GroundTruth,
    /// One PNG per detected object, `<dir>/<scene_id:06>/<im_id:06>_obj<obj_id:06>.png`
    /// (non-zero = object), e.g. written by a detector run offline; no
    /// ground truth needed.
    Files(PathBuf),
}

/// The mask file of object `obj_id` in image `im_id` of a [`Masks::Files`] directory.
pub fn mask_file(dir: &Path, scene_id: u32, im_id: u32, obj_id: u32) -> PathBuf {
    dir.join(format!("{scene_id:06}/{im_id:06}_obj{obj_id:06}.png"))
}

/// Frames of a BOP dataset split with their object masks, in scene and
/// image order; a test split (`test`, `test_primesense`, ...) is restricted to
/// the targets of `test_targets_bop19.json` when the dataset root has one
/// (or of the targets file given to [`BopFrames::open`]).
#[derive(Debug)]
pub struct BopFrames {
    split_dir: PathBuf,
    masks: Masks,
    targets: Vec<Target>,
    next: usize,
    loaded: Option<LoadedScene>,
}

/// The JSON files of the scene being read.
#[derive(Debug)]
struct LoadedScene {
    scene_id: u32,
    /// Camera entries stay JSON until used, so one broken entry spoils one
    /// image, not the scene.
    cameras: ByImage<serde_json::Value>,
    /// Only read with [`Masks::GroundTruth`].
    gts: Option<ByImage<Vec<GtEntry>>>,
}

fn scene_ids(split_dir: &Path) -> Result<Vec<u32>, IngestError> {
    let entries =
        std::fs::read_dir(split_dir).map_err(|source| SceneError::Io { path: split_dir.to_path_buf(), source })?;
    let mut ids: Vec<u32> = entries
        .filter_map(|e| e.ok())
        .filter(|e| e.path().is_dir())
        .filter_map(|e| e.file_name().to_str().and_then(|n| n.parse().ok()))
        .collect();
    ids.sort_unstable();
    Ok(ids)
}

impl BopFrames {
    /// `scenes` restricts the scenes (all when empty); `targets_file`, a
    /// BOP19 targets file, replaces the dataset's own for any split.
    pub fn open(
        root: &Path,
        split: &str,
        scenes: &[u32],
        targets_file: Option<&Path>,
        masks: Masks,
    ) -> Result<Self, IngestError> {
        let split_dir = root.join(split);
        let wanted = |scene_id: u32| scenes.is_empty() || scenes.contains(&scene_id);
        // BOP's targets name test images; training splits beside a test
        // split in the same root use all of their images.
        let dataset_targets = root.join("test_targets_bop19.json");
        let targets_file = match targets_file {
            Some(file) => Some(file.to_path_buf()),
            None => (split.starts_with("test") && dataset_targets.is_file()).then_some(dataset_targets),
        };
        let targets = if let Some(targets_file) = targets_file {
            let entries: Vec<TargetEntry> = bop::read_json(&targets_file)?;
            let mut targets: Vec<Target> = Vec::new();
            for entry in entries.into_iter().filter(|e| wanted(e.scene_id)) {
                match targets.last_mut() {
                    Some(t) if (t.scene_id, t.im_id) == (entry.scene_id, entry.im_id) => t.obj_ids.push(entry.obj_id),
                    _ => targets.push(Target {
                        scene_id: entry.scene_id,
                        im_id: entry.im_id,
                        obj_ids: vec![entry.obj_id],
                    }),
                }
            }
            targets
        } else {
            let mut targets = Vec::new();
            for scene_id in scene_ids(&split_dir)?.into_iter().filter(|&id| wanted(id)) {
                let dir = SceneDir::new(&split_dir, scene_id);
                let cameras: ByImage<serde_json::Value> = bop::read_json(&dir.scene_camera())?;
                targets.extend(cameras.keys().map(|&im_id| Target { scene_id, im_id, obj_ids: Vec::new() }));
            }
            targets
        };
        if targets.is_empty() {
            return Err(IngestError::Frame {
                frame: split_dir.display().to_string(),
                detail: format!("no images to read (scenes {scenes:?}); expected <scene_id:06>/scene_camera.json"),
            });
        }
        Ok(Self { split_dir, masks, targets, next: 0, loaded: None })
    }

    /// `(scene_id, im_id, obj_ids)` of every image the stream will
    /// deliver, in order (the frame id of an image is its position here);
    /// `obj_ids` are the targeted objects, empty for every annotated one.
    pub fn images(&self) -> impl Iterator<Item = (u32, u32, &[u32])> + '_ {
        self.targets.iter().map(|t| (t.scene_id, t.im_id, t.obj_ids.as_slice()))
    }

    /// Number of images the stream will deliver.
    pub fn len(&self) -> usize {
        self.targets.len()
    }

    pub fn is_empty(&self) -> bool {
        self.targets.is_empty()
    }

    fn load(&mut self, target: &Target, frame_id: u64) -> Result<LoadedFrame, IngestError> {
        let dir = SceneDir::new(&self.split_dir, target.scene_id);
        if self.loaded.as_ref().is_none_or(|scene| scene.scene_id != target.scene_id) {
            self.loaded = None;
            let cameras = bop::read_json(&dir.scene_camera())?;
            let gts = match self.masks {
                Masks::GroundTruth => Some(bop::read_json(&dir.scene_gt())?),
                Masks::Files(_) => None,
            };
            self.loaded = Some(LoadedScene { scene_id: target.scene_id, cameras, gts });
        }
        let LoadedScene { cameras, gts, .. } = self.loaded.as_ref().expect("loaded above");
        let label = format!("{} image {}", dir.path.display(), target.im_id);
        let missing = |file: PathBuf| IngestError::Frame {
            frame: label.clone(),
            detail: format!("{} has no entry for image {}", file.display(), target.im_id),
        };
        let entry = cameras.get(&target.im_id).ok_or_else(|| missing(dir.scene_camera()))?;
        let entry: CameraEntry = serde_json::from_value(entry.clone()).map_err(|err| IngestError::Frame {
            frame: label.clone(),
            detail: format!("{}: image {}: {err}", dir.scene_camera().display(), target.im_id),
        })?;
        let rgb = bop::read_rgb_png(&dir.rgb(target.im_id))?;
        let camera = entry.camera(rgb.width, rgb.height, &dir.scene_camera(), target.im_id)?;
        let depth = bop::read_depth_png(&dir.depth(target.im_id), entry.depth_scale)?;
        let wanted = |obj_id: u32| target.obj_ids.is_empty() || target.obj_ids.contains(&obj_id);
        // (object id, instance, mask file) of every mask to read.
        let files: Vec<(u32, usize, PathBuf)> = match &self.masks {
            Masks::GroundTruth => {
                let gts = gts.as_ref().expect("ground truth is loaded with ground-truth masks");
                let gt = gts.get(&target.im_id).ok_or_else(|| missing(dir.scene_gt()))?;
                gt.iter()
                    .enumerate()
                    .filter(|(_, gt)| wanted(gt.obj_id))
                    .map(|(instance, gt)| (gt.obj_id, instance, dir.mask_visib(target.im_id, instance)))
                    .collect()
            }
            Masks::Files(mask_dir) => mask_files(mask_dir, target.scene_id, target.im_id)?
                .into_iter()
                .filter(|(obj_id, _)| wanted(*obj_id))
                .enumerate()
                .map(|(instance, (obj_id, path))| (obj_id, instance, path))
                .collect(),
        };
        let (mut objects, mut skipped) = (Vec::new(), Vec::new());
        // BOP targets may name an object the image has no annotation of
        // (annotations left out, a target file from another release): each
        // such target is counted as skipped, not dropped in silence.
        if let (Masks::GroundTruth, Some(gts)) = (&self.masks, gts.as_ref())
            && let Some(gt) = gts.get(&target.im_id)
        {
            let mut unannotated: Vec<u32> =
                target.obj_ids.iter().copied().filter(|id| !gt.iter().any(|g| g.obj_id == *id)).collect();
            unannotated.dedup();
            skipped.extend(unannotated.into_iter().map(|obj_id| IngestError::Object {
                frame: label.clone(),
                obj_id,
                instance: 0,
                detail: format!(
                    "targeted, but {} has no annotation of it in image {}",
                    dir.scene_gt().display(),
                    target.im_id
                ),
            }));
        }
        for (obj_id, instance, path) in files {
            match bop::read_mask_png(&path) {
                Ok(mask) => objects.push(ObjectMask { obj_id, instance, mask }),
                Err(err) => skipped.push(IngestError::Object {
                    frame: label.clone(),
                    obj_id,
                    instance,
                    detail: err.to_string(),
                }),
            }
        }
        Ok(LoadedFrame {
            frame: RgbdFrame { frame_id, label, camera, rgb, depth },
            objects,
            skipped,
            scene_id: target.scene_id,
            image_id: target.im_id,
            captured_ns: None,
        })
    }
}

/// The `(obj_id, path)` of each mask file of one image, by object id.
fn mask_files(dir: &Path, scene_id: u32, im_id: u32) -> Result<Vec<(u32, PathBuf)>, IngestError> {
    let scene_dir = dir.join(format!("{scene_id:06}"));
    let entries = std::fs::read_dir(&scene_dir).map_err(|source| SceneError::Io { path: scene_dir.clone(), source })?;
    let prefix = format!("{im_id:06}_obj");
    let mut files: Vec<(u32, PathBuf)> = entries
        .filter_map(|e| e.ok())
        .filter_map(|e| {
            let name = e.file_name().into_string().ok()?;
            let obj_id = name.strip_prefix(&prefix)?.strip_suffix(".png")?.parse().ok()?;
            Some((obj_id, e.path()))
        })
        .collect();
    files.sort();
    Ok(files)
}

impl FrameSource for BopFrames {
    fn next_frame(&mut self) -> Option<Result<LoadedFrame, IngestError>> {
        let target = self.targets.get(self.next)?.clone();
        // Every image gets the next id, even one that fails to load, so the
        // gap shows downstream as a dropped frame.
        let frame_id = self.next as u64;
        self.next += 1;
        Some(self.load(&target, frame_id))
    }
}

/// The renderer as a camera: scenes of `spec` rendered on demand, with the
/// visible masks as object masks.
#[derive(Debug)]
pub struct SyntheticFrames {
    library: ModelLibrary,
    spec: RenderSpec,
    next: u64,
    scene: Option<(u32, poseflow_scene::scene::Scene)>,
}

impl SyntheticFrames {
    pub fn new(library: ModelLibrary, spec: RenderSpec) -> Self {
        Self { library, spec, next: 0, scene: None }
    }
}

impl FrameSource for SyntheticFrames {
    fn next_frame(&mut self) -> Option<Result<LoadedFrame, IngestError>> {
        let total = u64::from(self.spec.scenes) * u64::from(self.spec.frames_per_scene);
        if self.next >= total {
            return None;
        }
        let frame_id = self.next;
        self.next += 1;
        let per_scene = u64::from(self.spec.frames_per_scene);
        let scene_id = self.spec.first_scene + (frame_id / per_scene) as u32;
        let im_id = (frame_id % per_scene) as u32;
        if self.scene.as_ref().is_none_or(|(id, _)| *id != scene_id) {
            self.scene = Some((scene_id, render_scene(&self.library, &self.spec, scene_id)));
        }
        let (_, scene) = self.scene.as_ref().expect("composed above");
        let rendered = match render_frame(&self.library, &self.spec, scene, scene_id, im_id) {
            Ok(rendered) => rendered,
            Err(err) => return Some(Err(err.into())),
        };
        let camera = self.spec.camera;
        let objects = scene
            .objects
            .iter()
            .enumerate()
            .map(|(k, object)| ObjectMask {
                obj_id: object.obj_id,
                instance: k,
                mask: Raster {
                    width: camera.width,
                    height: camera.height,
                    pixels: rendered.view.frame.label.iter().map(|&l| usize::from(l) == k + 1).collect(),
                },
            })
            .collect();
        Some(Ok(LoadedFrame {
            frame: RgbdFrame {
                frame_id,
                label: format!("synthetic scene {scene_id} image {im_id}"),
                camera,
                rgb: Raster { width: camera.width, height: camera.height, pixels: rendered.view.frame.rgb },
                depth: Raster { width: camera.width, height: camera.height, pixels: rendered.depth },
            },
            objects,
            skipped: Vec::new(),
            scene_id,
            image_id: im_id,
            captured_ns: None,
        }))
    }
}

/// Every frame of another source, read before the first is handed out: a
/// stream whose pace depends on the pipeline only (benchmarks). Frames that
/// failed to read stay errors, in their place.
#[derive(Debug)]
pub struct PreloadedFrames {
    frames: std::collections::VecDeque<Result<LoadedFrame, IngestError>>,
}

impl PreloadedFrames {
    pub fn read_all(mut source: Box<dyn FrameSource>) -> Self {
        let started = std::time::Instant::now();
        let frames: std::collections::VecDeque<_> = std::iter::from_fn(|| source.next_frame()).collect();
        tracing::info!(frames = frames.len(), ms = started.elapsed().as_millis() as u64, "frames preloaded");
        Self { frames }
    }
}

impl FrameSource for PreloadedFrames {
    fn next_frame(&mut self) -> Option<Result<LoadedFrame, IngestError>> {
        self.frames.pop_front()
    }
}
