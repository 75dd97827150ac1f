//! `poseflow preview`: one BOP image's RGB, depth and visible masks side by
//! side in a PNG, to look at what a dataset holds; with `--detect`, the
//! detector stage's masks beside the annotated ones, to see what the pose
//! stages would be handed.

use std::path::{Path, PathBuf};

use anyhow::{Context, bail};
use clap::Args;
use image::{Rgb, RgbImage};
use poseflow_detector::{DetectedObject, Detector, DetectorParams, ImageView};
use poseflow_figures::plotters::prelude::*;
use poseflow_figures::{Area, DrawError, colour_bar, image_panel, image_panel_size, legend, render};
use poseflow_scene::bop::{self, ByImage, CameraEntry, GtEntry, Raster, SceneDir};

#[derive(Debug, Args)]
pub struct PreviewArgs {
    /// A BOP scene directory (<dataset>/<split>/<scene_id:06>).
    #[arg(long)]
    pub scene: PathBuf,
    /// Image id within the scene.
    #[arg(long, default_value_t = 0)]
    pub image: u32,
    /// PNG to write: RGB | depth (near = bright, no measurement = black, with
    /// its scale in metres) | visible masks (legend: object ids) [| the
    /// detector's masks], in pixel axes.
    #[arg(long)]
    pub out: PathBuf,
    /// Also run the detector stage on the image: a fourth panel with its masks, and per detection its score and
    /// mask IoU with the annotated instance of its object printed.
    #[arg(long)]
    pub detect: bool,
    /// The detector stage's parameter file, with --detect (both modes; a graph's `config` for the stage).
    #[arg(long, default_value = "config/detector.toml", requires = "detect")]
    pub detector_config: PathBuf,
    /// The detector's model directory, with --detect: replaces the parameter file's `model`.
    #[arg(long, requires = "detect")]
    pub detector_model: Option<PathBuf>,
}

/// Distinct colours for objects' masks, cycled.
const PALETTE: [[u8; 3]; 12] = [
    [230, 25, 75],
    [60, 180, 75],
    [255, 225, 25],
    [0, 130, 200],
    [245, 130, 48],
    [145, 30, 180],
    [70, 240, 240],
    [240, 50, 230],
    [170, 110, 40],
    [128, 128, 0],
    [250, 190, 212],
    [0, 0, 128],
];

fn entry<'a, T>(by_image: &'a ByImage<T>, im_id: u32, file: &Path) -> anyhow::Result<&'a T> {
    by_image.get(&im_id).with_context(|| {
        format!("{}: no image {im_id} (has {:?})", file.display(), by_image.keys().take(10).collect::<Vec<_>>())
    })
}

/// Grey level of depth `z` between `near` (white) and `far` (dark grey).
fn depth_grey(z: f64, (near, far): (f64, f64)) -> u8 {
    (255.0 - 191.0 * (z - near) / (far - near).max(1e-6)).round().clamp(64.0, 255.0) as u8
}

/// Depth as grey (see [`depth_grey`]), no measurement black, and the
/// nearest and farthest valid depth (metres).
fn depth_panel(depth: &Raster<f32>) -> (RgbImage, (f64, f64)) {
    let valid = || depth.pixels.iter().copied().filter(|&z| z > 0.0);
    let near = f64::from(valid().fold(f32::INFINITY, f32::min));
    let far = f64::from(valid().fold(0.0f32, f32::max));
    let range = if near <= far { (near, far) } else { (0.0, 1.0) };
    let image = RgbImage::from_fn(depth.width, depth.height, |x, y| {
        let z = depth.pixels[(y * depth.width + x) as usize];
        Rgb([if z > 0.0 { depth_grey(f64::from(z), range) } else { 0 }; 3])
    });
    (image, range)
}

/// The detector stage as `--detector-config` (and `--detector-model`) set it up.
fn load_detector(args: &PreviewArgs) -> anyhow::Result<Detector> {
    let file = &args.detector_config;
    let text = std::fs::read_to_string(file).with_context(|| format!("--detector-config {}", file.display()))?;
    let mut table: toml::Table = toml::from_str(&text)
        .with_context(|| format!("{}: expected a TOML table of the detector's parameters", file.display()))?;
    if let Some(model) = &args.detector_model {
        let model = model.to_str().with_context(|| format!("--detector-model {}: not UTF-8", model.display()))?;
        table.insert("model".into(), toml::Value::String(model.into()));
    }
    let params = DetectorParams::from_json(&serde_json::to_value(&table)?)
        .with_context(|| format!("--detector-config {}", file.display()))?;
    Detector::new(params).with_context(|| format!("--detector-config {}", file.display()))
}

/// A detection with its best mask IoU with an annotated instance of its
/// object (0 when it overlaps none).
struct Scored {
    detection: DetectedObject,
    iou: f64,
}

/// The mask IoU at which a detection finds an instance (`eval --detect`'s
/// AP50 rule).
const FOUND_IOU: f64 = 0.5;

/// Runs the detector on one image and scores each detection against the
/// annotated visible masks (`(obj_id, whole-image mask)`), printing both.
fn detect(
    args: &PreviewArgs,
    rgb: &Raster<[u8; 3]>,
    depth: &Raster<f32>,
    camera: &CameraEntry,
    annotated: &[(u32, Vec<bool>)],
) -> anyhow::Result<Vec<Scored>> {
    let mut detector = load_detector(args)?;
    let width = rgb.width as usize;
    let rgb_f32: Vec<f32> = rgb.pixels.iter().flat_map(|p| p.map(f32::from)).collect();
    let camera = camera.pinhole();
    let image = ImageView { rgb: &rgb_f32, depth: &depth.pixels, width, height: rgb.height as usize, camera };
    let started = std::time::Instant::now();
    let found = detector.detect(&image).context("--detect")?;
    let ms = started.elapsed().as_secs_f64() * 1e3;
    let scored: Vec<Scored> = found
        .objects
        .into_iter()
        .map(|detection| {
            let iou = annotated
                .iter()
                .filter(|(obj_id, _)| *obj_id == detection.obj_id)
                .map(|(_, mask)| detection.iou(mask, width))
                .fold(0.0, f64::max);
            Scored { detection, iou }
        })
        .collect();
    println!(
        "detector ({}{}): {} detections in {ms:.1} ms (first run, model loading excluded); {} regions dropped",
        args.detector_config.display(),
        args.detector_model.as_ref().map_or(String::new(), |m| format!(", model {}", m.display())),
        scored.len(),
        found.dropped
    );
    println!("object  instance  score  pixels  box (x, y, w, h)      mask IoU with the annotation");
    for Scored { detection, iou } in &scored {
        let pixels = detection.mask.iter().filter(|&&inside| inside).count();
        let [x, y, w, h] = detection.bbox;
        let bbox = format!("{x}, {y}, {w}, {h}");
        println!(
            "{:>6}  {:>8}  {:>5.2}  {pixels:>6}  {bbox:<20}  {iou:.2}",
            detection.obj_id, detection.instance, detection.score
        );
    }
    let missed: Vec<String> = annotated
        .iter()
        .filter(|(obj_id, mask)| {
            !scored.iter().any(|s| s.detection.obj_id == *obj_id && s.detection.iou(mask, width) >= FOUND_IOU)
        })
        .map(|(obj_id, _)| obj_id.to_string())
        .collect();
    if !missed.is_empty() {
        println!("annotated, with no detection at mask IoU >= {FOUND_IOU}: object {}", missed.join(", "));
    }
    Ok(scored)
}

/// `masks` (object id, whole-image row-major mask of `image`'s size, legend
/// label) painted over `image` at a third of its brightness, each in its
/// object's colour.
fn masks_panel(
    area: &Area<'_>,
    image: &RgbImage,
    masks: &[(u32, Vec<bool>, String)],
    colour_of: impl Fn(u32) -> [u8; 3],
    title: &str,
) -> Result<(), DrawError> {
    let mut shown = image.clone();
    shown.pixels_mut().for_each(|p| p.0 = p.0.map(|c| c / 3));
    let width = shown.width();
    for (obj_id, mask, _) in masks {
        for (i, _) in mask.iter().enumerate().filter(|(_, inside)| **inside) {
            shown.put_pixel(i as u32 % width, i as u32 / width, Rgb(colour_of(*obj_id)));
        }
    }
    let mut chart = image_panel(area, &shown, title)?;
    for (obj_id, _, label) in masks {
        let [r, g, b] = colour_of(*obj_id);
        chart
            .draw_series(std::iter::empty::<Rectangle<(i32, i32)>>())?
            .label(label.as_str())
            .legend(move |(x, y)| Rectangle::new([(x, y - 5), (x + 14, y + 5)], RGBColor(r, g, b).filled()));
    }
    legend(&mut chart, SeriesLabelPosition::UpperRight)
}

pub fn run(args: &PreviewArgs) -> anyhow::Result<()> {
    let dir = SceneDir { path: args.scene.clone() };
    let cameras: ByImage<CameraEntry> = bop::read_json(&dir.scene_camera())?;
    let gts: ByImage<Vec<GtEntry>> = bop::read_json(&dir.scene_gt())?;
    let camera = entry(&cameras, args.image, &dir.scene_camera())?;
    let instances = entry(&gts, args.image, &dir.scene_gt())?.len();
    let rgb = bop::read_rgb_png(&dir.rgb(args.image))?;
    let depth = bop::read_depth_png(&dir.depth(args.image), camera.depth_scale)?;
    if (depth.width, depth.height) != (rgb.width, rgb.height) {
        bail!(
            "{}: {}×{} pixels, but the RGB image is {}×{}",
            dir.depth(args.image).display(),
            depth.width,
            depth.height,
            rgb.width,
            rgb.height
        );
    }
    let pixel = |x: u32, y: u32| (y * rgb.width + x) as usize;
    let colour_image = RgbImage::from_fn(rgb.width, rgb.height, |x, y| Rgb(rgb.pixels[pixel(x, y)]));
    let gt = entry(&gts, args.image, &dir.scene_gt())?;
    let mut annotated = Vec::with_capacity(instances);
    for (k, entry) in gt.iter().enumerate() {
        let mask = bop::read_mask_png(&dir.mask_visib(args.image, k))?;
        if (mask.width, mask.height) != (rgb.width, rgb.height) {
            bail!(
                "{}: {}×{} pixels, but the RGB image is {}×{}",
                dir.mask_visib(args.image, k).display(),
                mask.width,
                mask.height,
                rgb.width,
                rgb.height
            );
        }
        annotated.push((entry.obj_id, mask.pixels));
    }
    let detected = if args.detect { Some(detect(args, &rgb, &depth, camera, &annotated)?) } else { None };
    // One colour per object in both mask panels, so a detection and its
    // annotation look alike.
    let mut objects: Vec<u32> = annotated.iter().map(|(obj_id, _)| *obj_id).collect();
    let (width, height) = (rgb.width as usize, rgb.height as usize);
    let detector_masks: Vec<(u32, Vec<bool>, String)> = detected
        .iter()
        .flatten()
        .map(|s| {
            let label = format!("object {} ({:.2}, IoU {:.2})", s.detection.obj_id, s.detection.score, s.iou);
            (s.detection.obj_id, s.detection.frame_mask(width, height), label)
        })
        .collect();
    objects.extend(detector_masks.iter().map(|(obj_id, _, _)| *obj_id));
    objects.sort_unstable();
    objects.dedup();
    let colour_of = |obj_id: u32| PALETTE[objects.binary_search(&obj_id).unwrap_or(0) % PALETTE.len()];
    let annotated_masks: Vec<(u32, Vec<bool>, String)> =
        annotated.into_iter().map(|(obj_id, mask)| (obj_id, mask, format!("object {obj_id}"))).collect();
    let (depth, (near, far)) = depth_panel(&depth);
    let (panel_width, panel_height) = image_panel_size(rgb.width, rgb.height);
    const SCALE_WIDTH: u32 = 150;
    let panel_count = if detected.is_some() { 4 } else { 3 };
    render(&args.out, "preview", (panel_count * panel_width + SCALE_WIDTH, panel_height), |root| {
        let (panels, scale) = root.split_horizontally(panel_count * panel_width);
        let (left, rest) = panels.split_horizontally(panel_width);
        let (middle, rest) = rest.split_horizontally(panel_width);
        let (right, detector_area) = rest.split_horizontally(panel_width);
        image_panel(&left, &colour_image, &format!("RGB, image {}", args.image))?;
        image_panel(&middle, &depth, "depth (black: no measurement)")?;
        masks_panel(&right, &colour_image, &annotated_masks, colour_of, "visible masks")?;
        if detected.is_some() {
            masks_panel(&detector_area, &colour_image, &detector_masks, colour_of, "the detector's masks")?;
        }
        let grey = |z: f64| {
            let level = depth_grey(z, (near, far));
            RGBColor(level, level, level)
        };
        let ticks = [near, (near + far) / 2.0, far];
        colour_bar(&scale, "depth (m)", (near, far), &ticks, grey, |z| format!("{z:.2}"))
    })?;
    println!("wrote {} ({} instances)", args.out.display(), instances);
    Ok(())
}
