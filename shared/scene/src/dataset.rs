//! Rendering a BOP-format dataset of random scenes, reproducible bit for bit
//! from a seed.
//!
//! Layout written under the output directory:
//! `camera.json`, `models/` (the model files used and `models_info.json`),
//! `poseflow_render.json` (the parameters, for provenance) and
//! `<split>/<scene_id:06>/` with `scene_camera.json`, `scene_gt.json`,
//! `scene_gt_info.json`, `rgb/`, `depth/`, `mask/`, `mask_visib/`. A `test`
//! split also gets `test_targets_bop19.json` at the root.
//!
//! Every scene and every frame draws from its own random stream, derived
//! from `(seed, scene_id)` and `(seed, scene_id, im_id)`, so any scene can
//! be re-rendered alone and comes out identical. Under a view condition a
//! scene whose arrangement no camera can show it in is arranged again from
//! its own further streams (`rearranged_scenes` in `poseflow_render.json`).

use std::path::Path;
use std::time::{Duration, Instant};

use poseflow_geometry::Pose;
use poseflow_geometry::sampling::seeded_rng;
use rand::Rng;
use rand_distr::{Distribution, StandardNormal};
use serde::Serialize;

use crate::bop::{
    ByImage, CameraEntry, DatasetCamera, GtEntry, GtInfoEntry, SceneDir, write_by_image, write_depth_png, write_json,
    write_mask_png, write_rgb_png,
};
use crate::camera_path::{CameraPath, Orbit};
use crate::part::ViewCondition;
use crate::scene::{Occlusion, Scene, SceneStyle, View, ViewRange, compose_styled_scene, random_light, render_view};
use crate::sensor::SensorModel;
use crate::video::{self, VideoEvents};
use crate::{Camera, DepthNoise, ModelLibrary, SceneError, model_file_name};

/// Depth PNG unit: 0.1 mm, so 16 bits reach 6.5 m.
pub const DEPTH_SCALE: f64 = 0.1;

/// The YCB-Video camera's intrinsics at 640×480 (BOP YCB-V), scaled to
/// another image size: a narrower view than LM-O's (fx 1067 px).
pub fn ycbv_camera(width: u32, height: u32) -> Camera {
    let (sx, sy) = (f64::from(width) / 640.0, f64::from(height) / 480.0);
    Camera { fx: 1066.778 * sx, fy: 1067.487 * sy, cx: 312.9869 * sx, cy: 241.3109 * sy, width, height }
}

/// Camera distances (metres) for [`ycbv_camera`]: about the LM-O range's
/// image scales at 1.9× its focal length, clipped to a tabletop's reach.
pub const YCBV_DISTANCE: (f64, f64) = (0.6, 1.6);

/// The LM-O (Kinect v1) intrinsics at 640×480, scaled to another image size.
pub fn lmo_camera(width: u32, height: u32) -> Camera {
    let (sx, sy) = (f64::from(width) / 640.0, f64::from(height) / 480.0);
    Camera { fx: 572.4114 * sx, fy: 573.57043 * sy, cx: 325.2611 * sx, cy: 242.04899 * sy, width, height }
}

/// What to render.
#[derive(Debug, Clone, PartialEq)]
pub struct RenderSpec {
    pub split: String,
    pub first_scene: u32,
    pub scenes: u32,
    pub frames_per_scene: u32,
    pub seed: u64,
    pub occlusion: Occlusion,
    pub camera: Camera,
    pub views: ViewRange,
    /// How the camera moves from image to image within a scene.
    pub path: CameraPath,
    /// `None` writes the ray-cast depth as is.
    pub depth_noise: Option<DepthNoise>,
    /// Standard deviation of per-channel RGB noise, 8-bit levels.
    pub rgb_noise: f64,
    /// A camera's effects on depth and colour (`crate::sensor`); when set,
    /// they replace `depth_noise` and `rgb_noise`.
    pub sensor: Option<SensorModel>,
    /// Patterns and distractors (the library's `distractors`).
    pub style: SceneStyle,
    /// Keep drawing each image's camera and light until the view meets this
    /// (random camera paths only).
    pub condition: Option<ViewCondition>,
}

/// Progress after each written frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FrameDone {
    pub scene_id: u32,
    pub im_id: u32,
    /// Frames written so far, and in all.
    pub done: u64,
    pub total: u64,
    /// Scene composition (amortised into the first frame), ray casting and
    /// noise.
    pub render: Duration,
    /// PNG encoding and file writes.
    pub write: Duration,
}

fn is_zero(value: &u32) -> bool {
    *value == 0
}

/// The parameters as written to `poseflow_render.json`.
#[derive(Serialize)]
struct Provenance<'a> {
    generator: &'static str,
    version: &'static str,
    split: &'a str,
    first_scene: u32,
    scenes: u32,
    frames_per_scene: u32,
    seed: u64,
    occlusion: String,
    /// `random`, or `orbit <step>°/image`.
    camera_path: String,
    objects: Vec<u32>,
    depth_noise: bool,
    rgb_noise: f64,
    /// The sensor effects, when they replace the two above.
    #[serde(skip_serializing_if = "Option::is_none")]
    sensor: Option<String>,
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    textured: bool,
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    upright: bool,
    #[serde(skip_serializing_if = "is_zero")]
    objects_per_scene: u32,
    /// Up to this many distractors per scene, drawn from these objects.
    #[serde(skip_serializing_if = "Option::is_none")]
    distractors: Option<(u32, Vec<u32>)>,
    #[serde(skip_serializing_if = "Option::is_none")]
    view_condition: Option<String>,
    /// Scenes drawn again because no view of their first arrangement met
    /// `view_condition`.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    rearranged_scenes: Vec<u32>,
}

/// Folds `parts` into one 64-bit seed (SplitMix64 finaliser on each step),
/// so nearby seeds and ids give unrelated streams.
fn stream_seed(parts: &[u64]) -> u64 {
    parts.iter().fold(0x9E37_79B9_7F4A_7C15u64, |acc, &part| {
        let mut z = acc.wrapping_add(part).wrapping_add(0x9E37_79B9_7F4A_7C15);
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    })
}

/// `[x, y, width, height]` of the true pixels, `[-1; 4]` when there are none.
fn bounding_box(mask: &[bool], width: u32) -> [i32; 4] {
    let w = width as usize;
    let mut bounds: Option<[usize; 4]> = None;
    for (i, _) in mask.iter().enumerate().filter(|(_, inside)| **inside) {
        let (u, v) = (i % w, i / w);
        bounds = Some(match bounds {
            None => [u, v, u, v],
            Some([u0, v0, u1, v1]) => [u0.min(u), v0.min(v), u1.max(u), v1.max(v)],
        });
    }
    bounds.map_or([-1; 4], |[u0, v0, u1, v1]| [u0 as i32, v0 as i32, (u1 - u0 + 1) as i32, (v1 - v0 + 1) as i32])
}

fn add_rgb_noise<R: Rng + ?Sized>(rgb: &mut [[u8; 3]], sigma: f64, rng: &mut R) {
    if sigma <= 0.0 {
        return;
    }
    for channel in rgb.as_flattened_mut() {
        let n: f64 = StandardNormal.sample(rng);
        *channel = (f64::from(*channel) + n * sigma).round().clamp(0.0, 255.0) as u8;
    }
}

fn same_file(a: &Path, b: &Path) -> bool {
    a.canonicalize().ok().zip(b.canonicalize().ok()).is_some_and(|(a, b)| a == b)
}

fn copy_models(library: &ModelLibrary, out: &Path) -> Result<(), SceneError> {
    let models = out.join("models");
    std::fs::create_dir_all(&models).map_err(|source| SceneError::Write { path: models.clone(), source })?;
    let info = library.dir.join("models_info.json");
    let files = library.objects.iter().map(|o| (o.path.clone(), models.join(model_file_name(o.obj_id))));
    // The shape's symmetries go along: the rendered objects are one-coloured,
    // so the training data is ambiguous up to them.
    let shape = library.dir.join(crate::import::SHAPE_SYMMETRIES_FILE);
    let shape = shape.is_file().then(|| (shape, models.join(crate::import::SHAPE_SYMMETRIES_FILE)));
    for (from, to) in files.chain([(info, models.join("models_info.json"))]).chain(shape) {
        if !same_file(&from, &to) {
            std::fs::copy(&from, &to).map_err(|source| SceneError::Write { path: to.clone(), source })?;
        }
    }
    // The rendered objects' categories and canonical frames go along, for
    // `poseflow eval --category` on the dataset.
    let categories = library.dir.join(crate::category::CATEGORIES_FILE);
    let copied = models.join(crate::category::CATEGORIES_FILE);
    if categories.is_file() && !same_file(&categories, &copied) {
        let mut table: serde_json::Map<String, serde_json::Value> = crate::bop::read_json(&categories)?;
        table.retain(|key, _| library.objects.iter().any(|o| o.obj_id.to_string() == *key));
        if !table.is_empty() {
            crate::bop::write_json(&copied, &table)?;
        }
    }
    Ok(())
}

/// Arrangements a scene may go through before a view condition that none of
/// them can meet is reported.
pub const MAX_ARRANGEMENTS: u32 = 8;

/// The arrangement of scene `scene_id`: the same for the same seed, however
/// many scenes are rendered and in which order.
pub fn scene(library: &ModelLibrary, spec: &RenderSpec, scene_id: u32) -> Scene {
    arrangement(library, spec, scene_id, 0)
}

/// Arrangement `k` of scene `scene_id`: 0 is [`scene`]; the later ones are
/// what [`write_dataset`] falls back to when no view of the earlier ones
/// meets `spec.condition`.
pub fn arrangement(library: &ModelLibrary, spec: &RenderSpec, scene_id: u32, k: u32) -> Scene {
    let stream = match k {
        0 => stream_seed(&[spec.seed, scene_id.into()]),
        k => stream_seed(&[spec.seed, scene_id.into(), 0, k.into()]),
    };
    compose_styled_scene(library, spec.occlusion, &spec.style, &mut seeded_rng(stream))
}

/// One frame as it goes into the dataset, in memory.
#[derive(Debug, Clone)]
pub struct RenderedFrame {
    pub camera_from_world: Pose,
    /// The render; its RGB is the camera's (with `spec.rgb_noise` or
    /// `spec.sensor`), its depth the noiseless one.
    pub view: View,
    /// The depth image as written: with sensor noise when `spec.depth_noise`
    /// or `spec.sensor` is set. Metres, 0 = no measurement.
    pub depth: Vec<f32>,
}

/// Renders image `im_id` of `scene` (scene `scene_id`): the camera and
/// light of `spec.path`, sensor noise. With `spec.condition` (random
/// cameras), cameras and lights are drawn until the view meets it; after
/// its `view_attempts` draws [`SceneError::NoView`] reports the scene as
/// unable to.
pub fn frame(
    library: &ModelLibrary,
    spec: &RenderSpec,
    scene: &Scene,
    scene_id: u32,
    im_id: u32,
) -> Result<RenderedFrame, SceneError> {
    if let Some(condition) = &spec.condition
        && !scene.objects.iter().any(|o| o.obj_id == condition.part.obj_id)
    {
        return Err(SceneError::Invalid(format!(
            "scene {scene_id} image {im_id}: no view can show {condition}: the scene has no object {}",
            condition.part.obj_id
        )));
    }
    let mut rng = seeded_rng(stream_seed(&[spec.seed, scene_id.into(), 1 + u64::from(im_id)]));
    let (camera_from_world, mut view) = match spec.path {
        CameraPath::Random => {
            let mut attempts = 0;
            loop {
                let camera_from_world = spec.views.sample(scene, &mut rng);
                let light = random_light(&mut rng);
                let view = render_view(library, scene, &spec.camera, &camera_from_world, &light);
                match &spec.condition {
                    Some(condition) if !condition.accepts(scene, &view, &spec.camera) => {
                        attempts += 1;
                        if attempts >= condition.view_attempts {
                            return Err(SceneError::NoView {
                                scene_id,
                                im_id,
                                attempts,
                                condition: condition.to_string(),
                            });
                        }
                    }
                    _ => break (camera_from_world, view),
                }
            }
        }
        CameraPath::Orbit { step_deg, events } => {
            // Stream 0 of the scene: the same orbit for all of its images.
            let orbit = Orbit::draw(&spec.views, &mut seeded_rng(stream_seed(&[spec.seed, scene_id.into(), 0])));
            let camera_from_world = orbit.camera_from_world(&scene.centre, step_deg * f64::from(im_id));
            let view = if events.is_empty() {
                render_view(library, scene, &spec.camera, &camera_from_world, &orbit.light)
            } else {
                let schedule = video_schedule(spec, scene, scene_id, &events);
                let shown = video::scene_at(scene, library, &schedule, im_id, &camera_from_world);
                render_view(library, &shown, &spec.camera, &camera_from_world, &orbit.light)
            };
            (camera_from_world, view)
        }
    };
    let depth = match (&spec.sensor, &spec.depth_noise) {
        (Some(sensor), _) => {
            sensor.apply(&spec.camera, &view.frame.depth, &view.frame.albedo, &mut view.frame.rgb, &mut rng)
        }
        (None, Some(noise)) => noise.apply(&view.frame.depth, spec.camera.width as usize, &mut rng),
        (None, None) => view.frame.depth.clone(),
    };
    if spec.sensor.is_none() {
        add_rgb_noise(&mut view.frame.rgb, spec.rgb_noise, &mut rng);
    }
    Ok(RenderedFrame { camera_from_world, view, depth })
}

/// The video events of scene `scene_id` (stream 2 of the scene: the same
/// schedule for every image).
pub fn video_schedule(spec: &RenderSpec, scene: &Scene, scene_id: u32, events: &VideoEvents) -> Vec<video::Event> {
    let mut rng = seeded_rng(stream_seed(&[spec.seed, scene_id.into(), 2]));
    video::schedule(events, scene.objects.len(), spec.frames_per_scene, &mut rng)
}

/// Renders `spec` with every object of `library` in every scene, writing
/// the dataset under `out` and calling `on_frame` after each frame.
pub fn write_dataset(
    library: &ModelLibrary,
    spec: &RenderSpec,
    out: &Path,
    mut on_frame: impl FnMut(&FrameDone),
) -> Result<(), SceneError> {
    let split_dir = out.join(&spec.split);
    std::fs::create_dir_all(&split_dir).map_err(|source| SceneError::Write { path: split_dir.clone(), source })?;
    copy_models(library, out)?;
    write_json(&out.join("camera.json"), &DatasetCamera::new(&spec.camera, DEPTH_SCALE))?;
    let total = u64::from(spec.scenes) * u64::from(spec.frames_per_scene);
    let mut done = 0;
    let mut targets = Vec::new();
    let mut rearranged_scenes = Vec::new();
    for scene_id in spec.first_scene..spec.first_scene + spec.scenes {
        let done_before = done;
        let mut k = 0;
        let written = loop {
            let started = Instant::now();
            let scene = arrangement(library, spec, scene_id, k);
            let progress = Progress { done: &mut done, total, compose_time: started.elapsed() };
            match write_scene(library, spec, &split_dir, scene_id, &scene, progress, &mut on_frame) {
                Err(SceneError::NoView { im_id, condition, .. }) if k + 1 < MAX_ARRANGEMENTS => {
                    tracing::warn!(scene_id, im_id, arrangement = k, %condition, "no view meets the condition: scene arranged again");
                    done = done_before;
                    k += 1;
                }
                result => break result?,
            }
        };
        if k > 0 {
            rearranged_scenes.push(scene_id);
        }
        targets.extend(written);
    }
    write_json(
        &out.join("poseflow_render.json"),
        &Provenance {
            generator: "poseflow render",
            version: env!("CARGO_PKG_VERSION"),
            split: &spec.split,
            first_scene: spec.first_scene,
            scenes: spec.scenes,
            frames_per_scene: spec.frames_per_scene,
            seed: spec.seed,
            occlusion: format!("{:?}", spec.occlusion).to_lowercase(),
            camera_path: match spec.path {
                CameraPath::Random => "random".into(),
                CameraPath::Orbit { step_deg, events } if events.is_empty() => format!("orbit {step_deg}°/image"),
                CameraPath::Orbit { step_deg, events } => format!(
                    "orbit {step_deg}°/image, {} occlusion(s) and {} teleport(s) per scene wanted",
                    events.occlusions, events.teleports
                ),
            },
            objects: library.objects.iter().map(|o| o.obj_id).collect(),
            depth_noise: spec.depth_noise.is_some(),
            rgb_noise: spec.rgb_noise,
            sensor: spec.sensor.map(|sensor| format!("{sensor:?}")),
            textured: spec.style.textured,
            upright: spec.style.upright,
            objects_per_scene: spec.style.objects_per_scene,
            distractors: (spec.style.distractors > 0)
                .then(|| (spec.style.distractors, library.distractors.iter().map(|o| o.obj_id).collect())),
            view_condition: spec.condition.map(|c| c.to_string()),
            rearranged_scenes,
        },
    )?;
    if spec.split == "test" {
        write_json(&out.join("test_targets_bop19.json"), &targets)?;
    }
    Ok(())
}

/// Frames written so far (rewound when a scene is arranged again), and the
/// scene's composition time, counted into its first frame.
struct Progress<'a> {
    done: &'a mut u64,
    total: u64,
    compose_time: Duration,
}

/// Renders and writes every image of one scene arrangement; returns its
/// BOP19 targets.
fn write_scene(
    library: &ModelLibrary,
    spec: &RenderSpec,
    split_dir: &Path,
    scene_id: u32,
    scene: &Scene,
    progress: Progress<'_>,
    on_frame: &mut impl FnMut(&FrameDone),
) -> Result<Vec<Target>, SceneError> {
    let Progress { done, total, mut compose_time } = progress;
    let mut targets = Vec::new();
    let dir = SceneDir::new(split_dir, scene_id);
    dir.create()?;
    let (mut cameras, mut gts, mut infos) = (ByImage::new(), ByImage::new(), ByImage::new());
    for im_id in 0..spec.frames_per_scene {
        let started = Instant::now();
        let RenderedFrame { camera_from_world, view, depth } = frame(library, spec, scene, scene_id, im_id)?;
        let render_time = started.elapsed() + std::mem::take(&mut compose_time);

        let started = Instant::now();
        let (w, h) = (spec.camera.width, spec.camera.height);
        write_rgb_png(&dir.rgb(im_id), w, h, &view.frame.rgb)?;
        write_depth_png(&dir.depth(im_id), w, h, &depth, DEPTH_SCALE)?;
        let mut gt = Vec::with_capacity(scene.objects.len());
        let mut info = Vec::with_capacity(scene.objects.len());
        for (k, (object, pose)) in scene.objects.iter().zip(&view.object_poses).enumerate() {
            let full = &view.silhouettes[k];
            let visible: Vec<bool> = view.frame.label.iter().map(|&l| usize::from(l) == k + 1).collect();
            write_mask_png(&dir.mask(im_id, k), w, h, full)?;
            write_mask_png(&dir.mask_visib(im_id, k), w, h, &visible)?;
            // As BOP counts it: with the part the image border cuts off.
            let px_count_all = full.iter().filter(|&&inside| inside).count() as u64 + view.truncated[k];
            let px_count_visib = visible.iter().filter(|&&inside| inside).count() as u64;
            info.push(GtInfoEntry {
                bbox_obj: bounding_box(full, w),
                bbox_visib: bounding_box(&visible, w),
                px_count_all,
                px_count_valid: full.iter().zip(&depth).filter(|&(&inside, &z)| inside && z > 0.0).count() as u64,
                px_count_visib,
                visib_fract: if px_count_all > 0 { px_count_visib as f64 / px_count_all as f64 } else { 0.0 },
            });
            gt.push(GtEntry::new(object.obj_id, pose));
        }
        for obj_id in scene.objects.iter().map(|o| o.obj_id) {
            targets.push(Target { im_id, inst_count: 1, obj_id, scene_id });
        }
        cameras.insert(im_id, CameraEntry::new(&spec.camera, DEPTH_SCALE, Some(&camera_from_world)));
        gts.insert(im_id, gt);
        infos.insert(im_id, info);
        *done += 1;
        on_frame(&FrameDone { scene_id, im_id, done: *done, total, render: render_time, write: started.elapsed() });
    }
    if let CameraPath::Orbit { events, .. } = spec.path
        && !events.is_empty()
    {
        let schedule = video_schedule(spec, scene, scene_id, &events);
        let records: Vec<video::EventRecord> = schedule.iter().map(|e| video::EventRecord::new(e, scene)).collect();
        write_json(&dir.video_events(), &records)?;
    }
    write_by_image(&dir.scene_camera(), &cameras)?;
    write_by_image(&dir.scene_gt(), &gts)?;
    write_by_image(&dir.scene_gt_info(), &infos)?;
    Ok(targets)
}

/// One entry of BOP's `test_targets_bop19.json`.
#[derive(Serialize)]
struct Target {
    im_id: u32,
    inst_count: u32,
    obj_id: u32,
    scene_id: u32,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bounding_boxes_are_inclusive_and_empty_is_minus_one() {
        let mut mask = vec![false; 6 * 4];
        assert_eq!(bounding_box(&mask, 6), [-1; 4]);
        mask[6 + 2] = true;
        assert_eq!(bounding_box(&mask, 6), [2, 1, 1, 1]);
        mask[3 * 6 + 4] = true;
        assert_eq!(bounding_box(&mask, 6), [2, 1, 3, 3]);
    }

    #[test]
    fn stream_seeds_differ_for_neighbouring_ids() {
        let seeds =
            [stream_seed(&[0, 0, 1]), stream_seed(&[0, 0, 2]), stream_seed(&[0, 1, 1]), stream_seed(&[1, 0, 1])];
        for (i, a) in seeds.iter().enumerate() {
            for b in &seeds[i + 1..] {
                assert_ne!(a, b);
            }
        }
        assert_eq!(stream_seed(&[7, 3]), stream_seed(&[7, 3]));
    }

    #[test]
    fn lmo_camera_scales_with_the_image() {
        let half = lmo_camera(320, 240);
        assert!((half.fx - 286.2057).abs() < 1e-9 && (half.cy - 121.024495).abs() < 1e-9);
    }
}
