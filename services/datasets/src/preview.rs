//! `poseflow preview`: one BOP image's RGB, depth and visible masks side by
//! side in a PNG, to look at what a dataset holds.

use std::path::{Path, PathBuf};

use anyhow::{Context, bail};
use clap::Args;
use poseflow_scene::bop::{self, ByImage, CameraEntry, GtEntry, Raster, SceneDir};

#[derive(Debug, Args)]
pub struct PreviewArgs {
    /// A BOP scene directory (<dataset>/<split>/<scene_id:06>).
    #[arg(long)]
    pub scene: PathBuf,
    /// Image id within the scene.
    #[arg(long, default_value_t = 0)]
    pub image: u32,
    /// PNG to write: RGB | depth (near = bright, no measurement = black) | visible masks.
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

/// Depth as grey: the nearest valid depth white, the farthest dark grey.
fn depth_panel(depth: &Raster<f32>) -> Vec<[u8; 3]> {
    let valid = || depth.pixels.iter().copied().filter(|&z| z > 0.0);
    let near = valid().fold(f32::INFINITY, f32::min);
    let far = valid().fold(0.0f32, f32::max);
    let range = (far - near).max(1e-6);
    depth
        .pixels
        .iter()
        .map(|&z| if z > 0.0 { [(255.0 - 191.0 * (z - near) / range).round() as u8; 3] } else { [0; 3] })
        .collect()
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
    let mut masks: Vec<[u8; 3]> = rgb.pixels.iter().map(|p| p.map(|c| c / 3)).collect();
    for (k, color) in (0..instances).zip(PALETTE.iter().cycle()) {
        let mask = bop::read_mask_png(&dir.mask_visib(args.image, k))?;
        for (pixel, _) in masks.iter_mut().zip(&mask.pixels).filter(|(_, inside)| **inside) {
            *pixel = *color;
        }
    }
    let depth = depth_panel(&depth);
    let w = rgb.width as usize;
    let mut sheet = Vec::with_capacity(3 * rgb.pixels.len());
    for row in 0..rgb.height as usize {
        for panel in [&rgb.pixels, &depth, &masks] {
            sheet.extend_from_slice(&panel[row * w..(row + 1) * w]);
        }
    }
    bop::write_rgb_png(&args.out, 3 * rgb.width, rgb.height, &sheet)?;
    println!("wrote {} ({} instances)", args.out.display(), instances);
    Ok(())
}
