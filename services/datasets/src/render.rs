//! `poseflow render`: a BOP-format dataset of random tabletop scenes.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, bail};
use clap::{Args, ValueEnum};
use poseflow_scene::camera_path::CameraPath;
use poseflow_scene::dataset::{RenderSpec, YCBV_DISTANCE, lmo_camera, write_dataset, ycbv_camera};
use poseflow_scene::part::{ObjectPart, PartVisibility, ViewCondition};
use poseflow_scene::scene::{Occlusion, SceneStyle, ViewRange};
use poseflow_scene::sensor::SensorModel;
use poseflow_scene::video::VideoEvents;
use poseflow_scene::{DepthNoise, ModelLibrary};
use serde::Serialize;

use poseflow_runtime::progress::Progress;
use poseflow_runtime::timing::Timing;

/// Largest image side accepted: beyond it a typo, not a camera.
const MAX_IMAGE_SIDE: u32 = 8192;
/// Largest orbit step: beyond it consecutive images are not a video.
const MAX_ORBIT_STEP_DEG: f64 = 90.0;
/// Per-channel RGB noise of the default (realistic) render, 8-bit levels.
const RGB_NOISE: f64 = 2.0;

#[derive(Debug, Args)]
#[command(after_help = "Example:\n  poseflow render --models objects/lmo --out data/lmo-synth --scenes 20 \
    --frames-per-scene 50 --seed 1 --occlusion high\n  \
    poseflow render --models objects/lmo --out data/lmo-orbit --split test --frames-per-scene 120 \
    --orbit-step-deg 1   (a 120-image video for tracking)\n  \
    poseflow render --models objects/ycbv/models --objects 14 --out data/mug-hidden --split test --scenes 10 \
    --frames-per-scene 5 --mug-handle hidden   (mug views whose handle is out of sight)\n  \
    poseflow render --models objects/ycbv/models --out data/ycbv-synth --camera ycbv --sensor realistic \
    --without jpeg   (a real camera's effects but JPEG)\n\n\
    Writes <out>/camera.json, <out>/models/, <out>/poseflow_render.json and <out>/<split>/<scene:06>/ with \
    scene_camera.json, scene_gt.json, scene_gt_info.json, rgb/, depth/ (16-bit, depth_scale 0.1 mm), mask/, \
    mask_visib/. The same arguments give the same files, bit for bit.")]
pub struct RenderArgs {
    /// BOP models directory: models_info.json and obj_NNNNNN.ply files (millimetres).
    #[arg(long)]
    pub models: PathBuf,
    /// Dataset root to write (created if missing; existing scenes are overwritten).
    #[arg(long)]
    pub out: PathBuf,
    /// Number of scenes (object arrangements).
    #[arg(long, default_value_t = 1)]
    pub scenes: u32,
    /// Camera views per scene.
    #[arg(long, default_value_t = 10)]
    pub frames_per_scene: u32,
    /// Seed of every random draw.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Object ids to place in every scene, comma-separated (default: every model in --models).
    #[arg(long, value_delimiter = ',')]
    pub objects: Vec<u32>,
    /// How crowded scenes are: clutter shapes and spacing between objects.
    #[arg(long, value_enum, default_value_t = OcclusionArg::Medium)]
    pub occlusion: OcclusionArg,
    /// Camera intrinsics (scaled from 640×480 to --width × --height): LM-O's Kinect (fx 572 px) or YCB-V's
    /// (fx 1067 px, a narrower view).
    #[arg(long, value_enum, default_value_t = CameraArg::Lmo)]
    pub camera: CameraArg,
    /// Camera distance range to the scene centre, metres "MIN,MAX" (default: 0.35,1.5 with --camera lmo, as
    /// LM-O's; 0.6,1.6 with --camera ycbv, whose narrower view needs more distance for the same scene).
    #[arg(long, value_parser = parse_range, value_name = "MIN,MAX")]
    pub distance: Option<(f64, f64)>,
    /// Image width in pixels.
    #[arg(long, default_value_t = 640)]
    pub width: u32,
    /// Image height in pixels.
    #[arg(long, default_value_t = 480)]
    pub height: u32,
    /// Split folder under --out (train, val, test; test also writes test_targets_bop19.json).
    #[arg(long, default_value = "train")]
    pub split: String,
    /// Id of the first scene (to add scenes to an existing dataset).
    #[arg(long, default_value_t = 0)]
    pub first_scene: u32,
    /// Render each scene as a video: the camera orbits the scene centre by this many degrees of azimuth per
    /// image (elevation, distance and roll drift smoothly; one light per scene). Default: independent views.
    #[arg(long, value_name = "DEG")]
    pub orbit_step_deg: Option<f64>,
    /// With --orbit-step-deg: occlusion events per scene, each an object fully hidden for 5-20 images by a box
    /// sliding across its line of sight (listed in each scene's video_events.json).
    #[arg(long, default_value_t = 0, value_name = "N")]
    pub occlusions: u32,
    /// With --orbit-step-deg: teleports per scene, each an object turned 90-180° about the vertical and shifted up
    /// to 5 cm between two images (listed in video_events.json).
    #[arg(long, default_value_t = 0, value_name = "N")]
    pub teleports: u32,
    /// What the camera does to the render: `basic` (axial depth noise, dropout at depth edges, RGB noise),
    /// `realistic` (docs/datasets.md: depth quantisation, flying pixels, projector shadow, dropout on dark,
    /// specular and grazing surfaces, depth-to-colour misregistration; exposure, white balance, gamma, blur, shot
    /// and read noise, vignetting, JPEG) or `clean` (the exact render).
    #[arg(long, value_enum, default_value_t = SensorArg::Basic)]
    pub sensor: SensorArg,
    /// Same as --sensor clean.
    #[arg(long, conflicts_with = "sensor")]
    pub clean: bool,
    /// With --sensor realistic: effects to turn off, comma-separated (depth-noise, quantisation,
    /// flying-pixels, shadow, dark, grazing, specular, misregistration, exposure, white-balance, gamma, defocus,
    /// motion-blur, shot-noise, read-noise, vignetting, jpeg).
    #[arg(long, value_delimiter = ',', value_name = "EFFECT")]
    pub without: Vec<String>,
    /// Keep only views in which the YCB-V mug (object 14: its handle is object x > 5 cm) is at least half
    /// visible and shows its handle (`visible`: ≥ 150 handle pixels at 640×480) or hides it behind its body or
    /// clutter (`hidden`: ≤ 10): the ambiguity benchmark's views. Random cameras only.
    #[arg(long, value_enum, value_name = "VISIBILITY")]
    pub mug_handle: Option<HandleArg>,
    /// Pattern the table, the clutter and the backdrop (checker, stripes, blotches, wood grain) instead of plain
    /// colours.
    #[arg(long)]
    pub textured: bool,
    /// Stand every target with its object +y axis up at a random yaw (the canonical frame of
    /// `generate-objects`: mugs, bowls, bottles and cans on their base) instead of on a random face of its box.
    #[arg(long)]
    pub upright: bool,
    /// Each scene holds this many of the objects, drawn anew per scene (0: all of them); for libraries of many
    /// generated instances.
    #[arg(long, default_value_t = 0, value_name = "K")]
    pub objects_per_scene: u32,
    /// Stand up to this many unannotated distractor objects among the targets in each scene, drawn from
    /// --distractor-models.
    #[arg(long, default_value_t = 0, value_name = "N")]
    pub distractors: u32,
    /// BOP models directory the distractors come from (default: --models, the objects not in --objects).
    #[arg(long, value_name = "DIR")]
    pub distractor_models: Option<PathBuf>,
    /// Print a JSON summary on stdout instead of the text line.
    #[arg(long)]
    pub json: bool,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum HandleArg {
    Hidden,
    Visible,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum CameraArg {
    Lmo,
    Ycbv,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum SensorArg {
    Basic,
    Realistic,
    Clean,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum OcclusionArg {
    Low,
    Medium,
    High,
}

impl From<OcclusionArg> for Occlusion {
    fn from(value: OcclusionArg) -> Self {
        match value {
            OcclusionArg::Low => Occlusion::Low,
            OcclusionArg::Medium => Occlusion::Medium,
            OcclusionArg::High => Occlusion::High,
        }
    }
}

#[derive(Debug, Serialize)]
struct Summary {
    out: PathBuf,
    scenes: u32,
    frames: u64,
    objects: Vec<u32>,
    width: u32,
    height: u32,
    /// Scene set-up, ray casting and noise per frame.
    render: Timing,
    /// PNG encoding and writing per frame.
    write: Timing,
    total_s: f64,
}

fn parse_range(text: &str) -> Result<(f64, f64), String> {
    let parts: Vec<f64> = text
        .split(',')
        .map(|p| p.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .map_err(|_| format!("{text:?}: expected two distances in metres separated by a comma, e.g. 0.6,1.6"))?;
    match parts[..] {
        [low, high] if low > 0.05 && low <= high && high <= 20.0 => Ok((low, high)),
        _ => Err(format!("{text:?}: expected MIN,MAX with 0.05 m < MIN ≤ MAX ≤ 20 m")),
    }
}

fn check(args: &RenderArgs) -> anyhow::Result<()> {
    for (name, side) in [("--width", args.width), ("--height", args.height)] {
        if side == 0 || side > MAX_IMAGE_SIDE {
            bail!("{name} {side}: expected 1 to {MAX_IMAGE_SIDE} pixels");
        }
    }
    if args.scenes == 0 || args.frames_per_scene == 0 {
        bail!("--scenes {} --frames-per-scene {}: expected at least 1 of each", args.scenes, args.frames_per_scene);
    }
    if let Some(step) = args.orbit_step_deg
        && !(step.is_finite() && step.abs() <= MAX_ORBIT_STEP_DEG)
    {
        bail!("--orbit-step-deg {step}: expected degrees per image within ±{MAX_ORBIT_STEP_DEG}");
    }
    if (args.occlusions > 0 || args.teleports > 0) && args.orbit_step_deg.is_none() {
        bail!(
            "--occlusions {} --teleports {}: events happen in videos; add --orbit-step-deg",
            args.occlusions,
            args.teleports
        );
    }
    if args.mug_handle.is_some() && args.orbit_step_deg.is_some() {
        bail!("--mug-handle with --orbit-step-deg: views are chosen by drawing random cameras, an orbit has none");
    }
    if !args.without.is_empty() && args.sensor != SensorArg::Realistic {
        bail!("--without {}: effects are turned off only with --sensor realistic", args.without.join(","));
    }
    if args.split.is_empty() || args.split.contains(['/', '\\']) || args.split.starts_with('.') {
        bail!("--split {:?}: expected a plain folder name such as train, val or test", args.split);
    }
    Ok(())
}

pub fn run(args: &RenderArgs) -> anyhow::Result<()> {
    check(args)?;
    let sensor_kind = if args.clean { SensorArg::Clean } else { args.sensor };
    let sensor = match sensor_kind {
        SensorArg::Realistic => Some(
            args.without
                .iter()
                .try_fold(SensorModel::default(), |model, name| model.without(name))
                .map_err(|detail| anyhow::anyhow!("--without {detail}"))?,
        ),
        SensorArg::Basic | SensorArg::Clean => None,
    };
    let (camera, default_distance) = match args.camera {
        CameraArg::Lmo => (lmo_camera(args.width, args.height), ViewRange::default().distance),
        CameraArg::Ycbv => (ycbv_camera(args.width, args.height), YCBV_DISTANCE),
    };
    let views = ViewRange { distance: args.distance.unwrap_or(default_distance), ..ViewRange::default() };
    let mut library = ModelLibrary::load(&args.models, &args.objects)
        .with_context(|| format!("--models {}: cannot load the object models", args.models.display()))?;
    if args.distractors > 0 {
        let dir = args.distractor_models.as_ref().unwrap_or(&args.models);
        library = library
            .with_distractors(dir)
            .with_context(|| format!("--distractor-models {}: cannot load distractors", dir.display()))?;
    } else if let Some(dir) = &args.distractor_models {
        bail!("--distractor-models {}: needs --distractors N (how many per scene)", dir.display());
    }
    let condition = args.mug_handle.map(|handle| {
        let visibility = match handle {
            HandleArg::Hidden => PartVisibility::Hidden,
            HandleArg::Visible => PartVisibility::Visible,
        };
        ViewCondition::new(ObjectPart::ycbv_mug_handle(), visibility)
    });
    if let Some(condition) = condition
        && !library.objects.iter().any(|o| o.obj_id == condition.part.obj_id)
    {
        bail!(
            "--mug-handle: the scenes have no object {} (the YCB-V mug); --models {} --objects {:?}",
            condition.part.obj_id,
            args.models.display(),
            args.objects
        );
    }
    let spec = RenderSpec {
        split: args.split.clone(),
        first_scene: args.first_scene,
        scenes: args.scenes,
        frames_per_scene: args.frames_per_scene,
        seed: args.seed,
        occlusion: args.occlusion.into(),
        camera,
        views,
        path: args.orbit_step_deg.map_or(CameraPath::Random, |step_deg| CameraPath::Orbit {
            step_deg,
            events: VideoEvents { occlusions: args.occlusions, teleports: args.teleports },
        }),
        depth_noise: (sensor_kind == SensorArg::Basic).then(DepthNoise::default),
        rgb_noise: if sensor_kind == SensorArg::Basic { RGB_NOISE } else { 0.0 },
        sensor,
        style: SceneStyle {
            textured: args.textured,
            distractors: args.distractors,
            upright: args.upright,
            objects_per_scene: args.objects_per_scene,
        },
        condition,
    };
    let started = Instant::now();
    let total = u64::from(args.scenes) * u64::from(args.frames_per_scene);
    let mut progress = Progress::new("render", total);
    let (mut render_times, mut write_times) = (Vec::new(), Vec::new());
    write_dataset(&library, &spec, &args.out, |frame| {
        render_times.push(frame.render);
        write_times.push(frame.write);
        progress.update(frame.done, &format!("scene {} image {}", frame.scene_id, frame.im_id));
    })
    .with_context(|| format!("--out {}: cannot write the dataset", args.out.display()))?;
    let summary = Summary {
        out: args.out.clone(),
        scenes: args.scenes,
        frames: total,
        objects: library.objects.iter().map(|o| o.obj_id).collect(),
        width: args.width,
        height: args.height,
        render: Timing::of(render_times),
        write: Timing::of(write_times),
        total_s: started.elapsed().as_secs_f64(),
    };
    if args.json {
        println!("{}", serde_json::to_string(&summary)?);
    } else {
        // A library of generated instances holds thousands of ids.
        let objects = match summary.objects.as_slice() {
            [first, .., last] if summary.objects.len() > 20 => {
                format!("{} objects, ids {first}–{last}", summary.objects.len())
            }
            ids => format!("objects {ids:?}"),
        };
        let per_scene = match args.objects_per_scene {
            0 => String::new(),
            k => format!(", {k} a scene"),
        };
        println!(
            "rendered {} frames ({} scenes, {objects}{per_scene}, {}×{}) to {} in {:.1} s: render {:.1} ms/frame \
             (p50 {:.1}, max {:.1}), write {:.1} ms/frame",
            summary.frames,
            summary.scenes,
            summary.width,
            summary.height,
            summary.out.display(),
            summary.total_s,
            summary.render.mean_ms,
            summary.render.p50_ms,
            summary.render.max_ms,
            summary.write.mean_ms,
        );
    }
    Ok(())
}
