//! `poseflow preview`: one BOP image's RGB, depth and visible masks side by
//! side in a PNG, to look at what a dataset holds.

use std::path::{Path, PathBuf};

use anyhow::{Context, bail};
use clap::Args;
use image::{Rgb, RgbImage};
use poseflow_figures::plotters::prelude::*;
use poseflow_figures::{colour_bar, image_panel, image_panel_size, legend, render};
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
    /// its scale in metres) | visible masks (legend: object ids), in pixel axes.
    #[arg(long)]
    pub out: PathBuf,
}

/// Distinct colours for instance masks, cycled.
const PALETTE: [[u8; 3]; 8] = [
    [230, 25, 75],
    [60, 180, 75],
    [255, 225, 25],
    [0, 130, 200],
    [245, 130, 48],
    [145, 30, 180],
    [70, 240, 240],
    [240, 50, 230],
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
    let mut masks = RgbImage::from_fn(rgb.width, rgb.height, |x, y| Rgb(rgb.pixels[pixel(x, y)].map(|c| c / 3)));
    let gt = entry(&gts, args.image, &dir.scene_gt())?;
    for (k, colour) in (0..instances).zip(PALETTE.iter().cycle()) {
        let mask = bop::read_mask_png(&dir.mask_visib(args.image, k))?;
        for (i, _) in mask.pixels.iter().enumerate().filter(|(_, inside)| **inside) {
            masks.put_pixel(i as u32 % rgb.width, i as u32 / rgb.width, Rgb(*colour));
        }
    }
    let (depth, (near, far)) = depth_panel(&depth);
    let (panel_width, panel_height) = image_panel_size(rgb.width, rgb.height);
    const SCALE_WIDTH: u32 = 150;
    render(&args.out, "preview", (3 * panel_width + SCALE_WIDTH, panel_height), |root| {
        let (panels, scale) = root.split_horizontally(3 * panel_width);
        let (left, rest) = panels.split_horizontally(panel_width);
        let (middle, right) = rest.split_horizontally(panel_width);
        image_panel(&left, &colour_image, &format!("RGB, image {}", args.image))?;
        image_panel(&middle, &depth, "depth (black: no measurement)")?;
        let mut chart = image_panel(&right, &masks, "visible masks")?;
        for (entry, colour) in gt.iter().zip(PALETTE.iter().cycle()) {
            let colour = RGBColor(colour[0], colour[1], colour[2]);
            chart
                .draw_series(std::iter::empty::<Rectangle<(i32, i32)>>())?
                .label(format!("object {}", entry.obj_id))
                .legend(move |(x, y)| Rectangle::new([(x, y - 5), (x + 14, y + 5)], colour.filled()));
        }
        legend(&mut chart, SeriesLabelPosition::UpperRight)?;
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
