//! What a Kinect- or RealSense-class RGB-D camera does to a perfect render,
//! effect by effect. Each effect is switchable (`None` turns it off), seeded,
//! and draws from its own random stream, so turning one off leaves every
//! other effect's output unchanged.
//!
//! Images are row-major. Depth is metres (camera z), 0 = no measurement, as
//! in BOP; colour is 8-bit sRGB. The depth effects run in the order a sensor
//! makes them: what the projector cannot light (shadow), what the surface
//! does not return (dark, specular, grazing), mixed returns at depth edges
//! (flying pixels), noise and disparity quantisation of what is measured,
//! then the registration of the depth image to the colour camera.

use nalgebra::Vector3;
use poseflow_geometry::sampling::{SeededRng, seeded_rng};
use rand::Rng;
use rand_distr::{Distribution, StandardNormal};

use crate::{Camera, DepthNoise};

/// Which side of a foreground edge the projector's shadow falls on, seen in
/// the image.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ShadowSide {
    Left,
    Right,
}

/// The structured-light (or active-stereo) shadow: background just beside a
/// foreground edge is hidden from the projector, which sits `baseline`
/// metres beside the depth camera, so it has no depth. The band is
/// `fx · baseline · (1/z_front − 1/z_back)` pixels wide: the disparity
/// between the two surfaces.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Shadow {
    pub baseline: f64,
    pub side: ShadowSide,
}

/// Depth effects. The defaults imitate a Kinect v1 / RealSense D400 at
/// 0.4–1.5 m.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DepthEffects {
    /// Axial noise growing with z², dropout at depth edges, random holes.
    pub noise: Option<DepthNoise>,
    /// Disparity quantisation: depth is measured in steps of `q · z²`
    /// metres (Kinect v1: 1/8 px of disparity at f = 580 px, b = 7.5 cm
    /// gives q ≈ 2.9e-3 /m, 2.9 mm at 1 m, 6.5 mm at 1.5 m).
    pub quantisation: Option<f64>,
    /// Share of depth-edge pixels that return a mixture of the foreground
    /// and the background depth (flying pixels) instead of either.
    pub flying_pixels: Option<f64>,
    pub shadow: Option<Shadow>,
    /// Largest dropout probability on a black material (too little of the
    /// sensor's light returns); it falls linearly to 0 at albedo luminance
    /// [`DARK_LUMINANCE`].
    pub dark: Option<f64>,
    /// Largest dropout probability on a surface seen edge-on; it falls
    /// linearly to 0 at [`GRAZING_DEG`] from the line of sight's normal.
    pub grazing: Option<f64>,
    /// Dropout probability on a bright surface facing the camera (the
    /// projector's pattern saturates in the mirror reflection).
    pub specular: Option<f64>,
    /// The depth image is registered to the colour image up to this many
    /// pixels off, along x and y (calibration error, unsynchronised
    /// shutters).
    pub misregistration_px: Option<u32>,
}

/// Luminance (0–1) below which dark-surface dropout starts.
pub const DARK_LUMINANCE: f64 = 0.15;
/// Angle between the surface normal and the line of sight beyond which
/// grazing dropout starts.
pub const GRAZING_DEG: f64 = 70.0;
/// Side of the square patches in which material dropout is decided
/// together.
const HOLE_CELL_PX: usize = 4;
/// Luminance and facing angle of a specular return.
const SPECULAR_LUMINANCE: f64 = 0.8;
const SPECULAR_COS: f64 = 0.98;

impl Default for DepthEffects {
    fn default() -> Self {
        Self {
            noise: Some(DepthNoise::default()),
            quantisation: Some(2.9e-3),
            flying_pixels: Some(0.3),
            shadow: Some(Shadow { baseline: 0.075, side: ShadowSide::Left }),
            dark: Some(0.5),
            grazing: Some(0.6),
            specular: Some(0.3),
            misregistration_px: Some(1),
        }
    }
}

/// Colour effects, drawn per image within the ranges given.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ColourEffects {
    /// Exposure error, ± this many stops.
    pub exposure_ev: Option<f64>,
    /// White-balance error: each channel's gain within 1 ± this.
    pub white_balance: Option<f64>,
    /// Tone curve `v^(1/γ)` with γ in this range.
    pub gamma: Option<(f64, f64)>,
    /// Defocus: Gaussian blur with σ up to this many pixels.
    pub defocus_px: Option<f64>,
    /// Motion blur: a straight streak up to this many pixels long, any
    /// direction, in half the images.
    pub motion_blur_px: Option<f64>,
    /// Photon (shot) noise: variance `shot · I` in 8-bit levels.
    pub shot_noise: Option<f64>,
    /// Read noise: σ in 8-bit levels.
    pub read_noise: Option<f64>,
    /// Vignetting: brightness falls by up to this share at the corners.
    pub vignetting: Option<f64>,
    /// JPEG compression with quality in this range (a USB or network
    /// camera's stream).
    pub jpeg_quality: Option<(u8, u8)>,
}

impl Default for ColourEffects {
    fn default() -> Self {
        Self {
            exposure_ev: Some(0.5),
            white_balance: Some(0.1),
            gamma: Some((0.8, 1.25)),
            defocus_px: Some(1.0),
            motion_blur_px: Some(6.0),
            shot_noise: Some(0.6),
            read_noise: Some(2.0),
            vignetting: Some(0.3),
            jpeg_quality: Some((60, 95)),
        }
    }
}

/// A camera's effects on depth and colour.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct SensorModel {
    pub depth: DepthEffects,
    pub colour: ColourEffects,
}

/// The names `--without` accepts, one per switchable effect.
pub const EFFECT_NAMES: [&str; 17] = [
    "depth-noise",
    "quantisation",
    "flying-pixels",
    "shadow",
    "dark",
    "grazing",
    "specular",
    "misregistration",
    "exposure",
    "white-balance",
    "gamma",
    "defocus",
    "motion-blur",
    "shot-noise",
    "read-noise",
    "vignetting",
    "jpeg",
];

impl SensorModel {
    /// Turns off the effect called `name` (one of [`EFFECT_NAMES`]).
    pub fn without(mut self, name: &str) -> Result<Self, String> {
        let (d, c) = (&mut self.depth, &mut self.colour);
        match name {
            "depth-noise" => d.noise = None,
            "quantisation" => d.quantisation = None,
            "flying-pixels" => d.flying_pixels = None,
            "shadow" => d.shadow = None,
            "dark" => d.dark = None,
            "grazing" => d.grazing = None,
            "specular" => d.specular = None,
            "misregistration" => d.misregistration_px = None,
            "exposure" => c.exposure_ev = None,
            "white-balance" => c.white_balance = None,
            "gamma" => c.gamma = None,
            "defocus" => c.defocus_px = None,
            "motion-blur" => c.motion_blur_px = None,
            "shot-noise" => c.shot_noise = None,
            "read-noise" => c.read_noise = None,
            "vignetting" => c.vignetting = None,
            "jpeg" => c.jpeg_quality = None,
            other => return Err(format!("{other:?}: expected one of {}", EFFECT_NAMES.join(", "))),
        }
        Ok(self)
    }

    /// Applies every effect to one rendered image: returns the sensor's
    /// depth and changes `rgb` in place. `albedo` (the unshaded surface
    /// colour) tells dark and bright materials apart, as the sensor's own
    /// light sees them.
    pub fn apply<R: Rng + ?Sized>(
        &self,
        camera: &Camera,
        depth: &[f32],
        albedo: &[[u8; 3]],
        rgb: &mut [[u8; 3]],
        rng: &mut R,
    ) -> Vec<f32> {
        let base: u64 = rng.random();
        let stream = |effect: u64| seeded_rng(base ^ effect.wrapping_mul(0x9E37_79B9_7F4A_7C15));
        let depth = self.depth.apply(camera, depth, albedo, &stream);
        self.colour.apply(camera.width as usize, rgb, &stream);
        depth
    }
}

fn luminance(rgb: [u8; 3]) -> f64 {
    (0.2126 * f64::from(rgb[0]) + 0.7152 * f64::from(rgb[1]) + 0.0722 * f64::from(rgb[2])) / 255.0
}

impl DepthEffects {
    fn apply(&self, camera: &Camera, clean: &[f32], albedo: &[[u8; 3]], stream: &dyn Fn(u64) -> SeededRng) -> Vec<f32> {
        let (w, h) = (camera.width as usize, camera.height as usize);
        let mut depth = clean.to_vec();
        if let Some(shadow) = self.shadow {
            cast_shadow(&mut depth, clean, w, camera.fx, &shadow);
        }
        let (dark, grazing, specular) = (self.dark, self.grazing, self.specular);
        if dark.is_some() || grazing.is_some() || specular.is_some() {
            // Real holes are patches, not salt and pepper: one draw per cell.
            let draws = cell_draws(w, h, HOLE_CELL_PX, &mut stream(1));
            for v in 0..h {
                for u in 0..w {
                    let i = v * w + u;
                    let z = clean[i];
                    let draw = draws[i];
                    if z <= 0.0 {
                        continue;
                    }
                    let light = luminance(albedo[i]);
                    let facing = if grazing.is_some() || specular.is_some() {
                        facing_cosine(clean, w, h, u, v, camera)
                    } else {
                        None
                    };
                    let mut keep = 1.0;
                    if let Some(p) = dark {
                        keep *= 1.0 - p * ((DARK_LUMINANCE - light) / DARK_LUMINANCE).clamp(0.0, 1.0);
                    }
                    if let (Some(p), Some(cos)) = (grazing, facing) {
                        let limit = GRAZING_DEG.to_radians().cos();
                        keep *= 1.0 - p * ((limit - cos) / limit).clamp(0.0, 1.0);
                    }
                    if let (Some(p), Some(cos)) = (specular, facing)
                        && light > SPECULAR_LUMINANCE
                        && cos > SPECULAR_COS
                    {
                        keep *= 1.0 - p;
                    }
                    if draw >= keep {
                        depth[i] = 0.0;
                    }
                }
            }
        }
        if let Some(share) = self.flying_pixels {
            let edge_jump = self.noise.map_or(DepthNoise::default().edge_jump, |n| n.edge_jump);
            let mut rng = stream(2);
            for v in 0..h {
                for u in 0..w {
                    let i = v * w + u;
                    let (draw, mix): (f64, f32) = (rng.random(), rng.random());
                    let z = clean[i];
                    if z <= 0.0 || depth[i] <= 0.0 || draw >= share {
                        continue;
                    }
                    // The neighbour across the largest jump is the other surface.
                    let neighbours = [(u.wrapping_sub(1), v), (u + 1, v), (u, v.wrapping_sub(1)), (u, v + 1)];
                    let other = neighbours
                        .iter()
                        .filter(|&&(nu, nv)| nu < w && nv < h)
                        .map(|&(nu, nv)| clean[nv * w + nu])
                        .filter(|&n| n > 0.0)
                        .max_by(|a, b| (a - z).abs().total_cmp(&(b - z).abs()));
                    if let Some(other) = other.filter(|n| (n - z).abs() > edge_jump) {
                        depth[i] = z + mix * (other - z);
                    }
                }
            }
        }
        if let Some(noise) = &self.noise {
            let mut rng = stream(3);
            let noisy = noise.apply(&depth, w, &mut rng);
            depth = noisy;
        }
        if let Some(q) = self.quantisation {
            // Steps of q in inverse depth (disparity) are steps of q·z² in depth.
            for z in depth.iter_mut().filter(|z| **z > 0.0) {
                let disparity = (1.0 / f64::from(*z) / q).round().max(1.0) * q;
                *z = (1.0 / disparity) as f32;
            }
        }
        if let Some(reach) = self.misregistration_px {
            let mut rng = stream(4);
            let reach = i64::from(reach);
            let (dx, dy) = (rng.random_range(-reach..=reach), rng.random_range(-reach..=reach));
            depth = shifted(&depth, w, h, dx, dy);
        }
        depth
    }
}

/// One uniform draw per `cell × cell` patch of a grid laid at a random
/// offset, spread over the patch's pixels.
fn cell_draws<R: Rng + ?Sized>(w: usize, h: usize, cell: usize, rng: &mut R) -> Vec<f64> {
    let (ou, ov) = (rng.random_range(0..cell), rng.random_range(0..cell));
    let columns = (w + ou).div_ceil(cell);
    let cells: Vec<f64> = (0..columns * (h + ov).div_ceil(cell)).map(|_| rng.random()).collect();
    (0..w * h).map(|i| cells[((i / w + ov) / cell) * columns + (i % w + ou) / cell]).collect()
}

/// |cos| of the angle between the surface normal (from the depth image's
/// neighbours, back-projected) and the line of sight; `None` at a depth edge
/// or the image border.
fn facing_cosine(depth: &[f32], w: usize, h: usize, u: usize, v: usize, camera: &Camera) -> Option<f64> {
    if u == 0 || v == 0 || u + 1 >= w || v + 1 >= h {
        return None;
    }
    let point = |u: usize, v: usize| {
        let z = f64::from(depth[v * w + u]);
        (z > 0.0)
            .then(|| Vector3::new((u as f64 - camera.cx) / camera.fx * z, (v as f64 - camera.cy) / camera.fy * z, z))
    };
    let centre = point(u, v)?;
    let (right, left, down, up) = (point(u + 1, v)?, point(u - 1, v)?, point(u, v + 1)?, point(u, v - 1)?);
    let reach = 0.05 * centre.z;
    if [right, left, down, up].iter().any(|p| (p.z - centre.z).abs() > reach) {
        return None;
    }
    let normal = (right - left).cross(&(down - up)).try_normalize(1e-12)?;
    Some(normal.dot(&centre.normalize()).abs())
}

/// Removes the depth of background pixels the projector cannot see.
fn cast_shadow(depth: &mut [f32], clean: &[f32], w: usize, fx: f64, shadow: &Shadow) {
    const JUMP: f32 = 0.02;
    for row in 0..depth.len() / w.max(1) {
        let line = &clean[row * w..(row + 1) * w];
        for u in 0..w {
            let front = line[u];
            // The neighbour on the shadow side, farther back, starts a band.
            let step: isize = match shadow.side {
                ShadowSide::Left => -1,
                ShadowSide::Right => 1,
            };
            let Some(next) = u.checked_add_signed(step).filter(|&n| n < w) else { continue };
            let back = line[next];
            if front <= 0.0 || back <= front + JUMP {
                continue;
            }
            let width = (fx * shadow.baseline * (1.0 / f64::from(front) - 1.0 / f64::from(back))).round() as isize;
            for k in 1..=width {
                let Some(at) = u.checked_add_signed(step * k).filter(|&n| n < w) else { break };
                if line[at] <= front + JUMP {
                    break;
                }
                depth[row * w + at] = 0.0;
            }
        }
    }
}

/// The image moved by (dx, dy) pixels; uncovered pixels read 0.
fn shifted(depth: &[f32], w: usize, h: usize, dx: i64, dy: i64) -> Vec<f32> {
    let mut out = vec![0.0; depth.len()];
    for v in 0..h as i64 {
        for u in 0..w as i64 {
            let (su, sv) = (u - dx, v - dy);
            if (0..w as i64).contains(&su) && (0..h as i64).contains(&sv) {
                out[(v * w as i64 + u) as usize] = depth[(sv * w as i64 + su) as usize];
            }
        }
    }
    out
}

impl ColourEffects {
    fn apply(&self, w: usize, rgb: &mut [[u8; 3]], stream: &dyn Fn(u64) -> SeededRng) {
        let h = rgb.len() / w.max(1);
        let mut image: Vec<[f64; 3]> = rgb.iter().map(|p| p.map(|c| f64::from(c) / 255.0)).collect();
        let mut gain = [1.0f64; 3];
        if let Some(ev) = self.exposure_ev {
            let stops = stream(10).random_range(-ev..=ev);
            gain = gain.map(|g| g * 2f64.powf(stops));
        }
        if let Some(spread) = self.white_balance {
            let mut rng = stream(11);
            for g in &mut gain {
                *g *= rng.random_range(1.0 - spread..=1.0 + spread);
            }
        }
        if let Some(strength) = self.vignetting {
            let fall = stream(12).random_range(0.0..=strength);
            let (cu, cv) = ((w as f64 - 1.0) / 2.0, (h as f64 - 1.0) / 2.0);
            let corner2 = cu * cu + cv * cv;
            for (i, p) in image.iter_mut().enumerate() {
                let (du, dv) = ((i % w) as f64 - cu, (i / w) as f64 - cv);
                let factor = 1.0 - fall * (du * du + dv * dv) / corner2.max(1.0);
                *p = p.map(|c| c * factor);
            }
        }
        for p in &mut image {
            *p = [p[0] * gain[0], p[1] * gain[1], p[2] * gain[2]];
        }
        if let Some(max_sigma) = self.defocus_px {
            let sigma = stream(13).random_range(0.0..=max_sigma);
            gaussian_blur(&mut image, w, h, sigma);
        }
        if let Some(max_length) = self.motion_blur_px {
            let mut rng = stream(14);
            let (moving, length, angle): (bool, f64, f64) =
                (rng.random_bool(0.5), rng.random_range(0.0..=max_length), rng.random_range(0.0..std::f64::consts::PI));
            if moving {
                streak(&mut image, w, h, length, angle);
            }
        }
        if self.shot_noise.is_some() || self.read_noise.is_some() {
            let mut rng = stream(15);
            let (shot, read) = (self.shot_noise.unwrap_or(0.0), self.read_noise.unwrap_or(0.0));
            for c in image.as_flattened_mut() {
                let level = (*c * 255.0).max(0.0);
                let sigma = (shot * level + read * read).sqrt();
                let n: f64 = StandardNormal.sample(&mut rng);
                *c += n * sigma / 255.0;
            }
        }
        if let Some((low, high)) = self.gamma {
            let gamma = stream(16).random_range(low..=high);
            for c in image.as_flattened_mut() {
                *c = c.clamp(0.0, 1.0).powf(1.0 / gamma);
            }
        }
        for (out, p) in rgb.iter_mut().zip(&image) {
            *out = p.map(|c| (c * 255.0).round().clamp(0.0, 255.0) as u8);
        }
        if let Some((low, high)) = self.jpeg_quality {
            let quality = stream(17).random_range(low.min(high)..=high.max(low)).clamp(1, 100);
            jpeg_round_trip(rgb, w, h, quality);
        }
    }
}

fn gaussian_blur(image: &mut [[f64; 3]], w: usize, h: usize, sigma: f64) {
    if sigma < 0.3 {
        return;
    }
    let radius = (3.0 * sigma).ceil() as isize;
    let kernel: Vec<f64> = (-radius..=radius).map(|k| (-(k * k) as f64 / (2.0 * sigma * sigma)).exp()).collect();
    let total: f64 = kernel.iter().sum();
    let pass = |image: &[[f64; 3]], horizontal: bool| -> Vec<[f64; 3]> {
        (0..w * h)
            .map(|i| {
                let (u, v) = ((i % w) as isize, (i / w) as isize);
                let mut sum = [0.0; 3];
                for (j, weight) in kernel.iter().enumerate() {
                    let k = j as isize - radius;
                    let (su, sv) = if horizontal { (u + k, v) } else { (u, v + k) };
                    let (su, sv) = (su.clamp(0, w as isize - 1) as usize, sv.clamp(0, h as isize - 1) as usize);
                    let p = image[sv * w + su];
                    for c in 0..3 {
                        sum[c] += weight * p[c];
                    }
                }
                sum.map(|s| s / total)
            })
            .collect()
    };
    let rows = pass(image, true);
    let both = pass(&rows, false);
    image.copy_from_slice(&both);
}

/// Averages each pixel along a centred streak `length` pixels long.
fn streak(image: &mut [[f64; 3]], w: usize, h: usize, length: f64, angle: f64) {
    let taps = length.round() as isize;
    if taps < 2 {
        return;
    }
    let (du, dv) = (angle.cos(), angle.sin());
    let source = image.to_vec();
    for (i, out) in image.iter_mut().enumerate() {
        let (u, v) = ((i % w) as f64, (i / w) as f64);
        let mut sum = [0.0; 3];
        for k in 0..=taps {
            let t = k as f64 - taps as f64 / 2.0;
            let su = (u + t * du).round().clamp(0.0, w as f64 - 1.0) as usize;
            let sv = (v + t * dv).round().clamp(0.0, h as f64 - 1.0) as usize;
            let p = source[sv * w + su];
            for c in 0..3 {
                sum[c] += p[c];
            }
        }
        *out = sum.map(|s| s / (taps + 1) as f64);
    }
}

fn jpeg_round_trip(rgb: &mut [[u8; 3]], w: usize, h: usize, quality: u8) {
    use image::ImageEncoder;
    let mut bytes = Vec::new();
    let encoder = image::codecs::jpeg::JpegEncoder::new_with_quality(&mut bytes, quality);
    let written = encoder.write_image(rgb.as_flattened(), w as u32, h as u32, image::ExtendedColorType::Rgb8);
    // An in-memory encode of a valid image cannot fail; if it ever did, the
    // image is left uncompressed rather than lost.
    if written.is_err() {
        return;
    }
    if let Ok(decoded) = image::load_from_memory_with_format(&bytes, image::ImageFormat::Jpeg) {
        let decoded = decoded.to_rgb8();
        for (out, p) in rgb.iter_mut().zip(decoded.pixels()) {
            *out = p.0;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn camera(w: u32, h: u32) -> Camera {
        Camera { fx: 500.0, fy: 500.0, cx: f64::from(w) / 2.0, cy: f64::from(h) / 2.0, width: w, height: h }
    }

    /// A 0.5 m box in front of a 1 m wall: the box covers u in [20, 40).
    fn step_scene(w: usize, h: usize) -> Vec<f32> {
        (0..w * h).map(|i| if (20..40).contains(&(i % w)) { 0.5 } else { 1.0 }).collect()
    }

    fn only_depth(depth: DepthEffects) -> SensorModel {
        let none = ColourEffects {
            exposure_ev: None,
            white_balance: None,
            gamma: None,
            defocus_px: None,
            motion_blur_px: None,
            shot_noise: None,
            read_noise: None,
            vignetting: None,
            jpeg_quality: None,
        };
        SensorModel { depth, colour: none }
    }

    fn no_depth_effects() -> DepthEffects {
        DepthEffects {
            noise: None,
            quantisation: None,
            flying_pixels: None,
            shadow: None,
            dark: None,
            grazing: None,
            specular: None,
            misregistration_px: None,
        }
    }

    #[test]
    fn the_shadow_band_has_the_width_of_the_disparity_between_the_surfaces() {
        let (w, h) = (60, 4);
        let shadow = Shadow { baseline: 0.075, side: ShadowSide::Left };
        let model = only_depth(DepthEffects { shadow: Some(shadow), ..no_depth_effects() });
        let mut rgb = vec![[128; 3]; w * h];
        let depth = model.apply(&camera(60, 4), &step_scene(w, h), &rgb.clone(), &mut rgb, &mut seeded_rng(1));
        // 500 px · 0.075 m · (1/0.5 − 1/1) m⁻¹ = 37.5 → 38 px, clipped at the image edge.
        let row = &depth[..w];
        assert!(row[..20].iter().all(|&z| z == 0.0), "{row:?}");
        assert!(row[20..40].iter().all(|&z| z == 0.5) && row[40..].iter().all(|&z| z == 1.0), "{row:?}");
        let right = only_depth(DepthEffects {
            shadow: Some(Shadow { side: ShadowSide::Right, baseline: 0.01 }),
            ..no_depth_effects()
        });
        let depth = right.apply(&camera(60, 4), &step_scene(w, h), &rgb.clone(), &mut rgb, &mut seeded_rng(1));
        // 500 · 0.01 · 1 = 5 px to the right of the box.
        assert_eq!(depth[40..46], [0.0, 0.0, 0.0, 0.0, 0.0, 1.0]);
        assert!(depth[..20].iter().all(|&z| z == 1.0));
    }

    #[test]
    fn flying_pixels_lie_between_the_two_surfaces_and_only_at_edges() {
        let (w, h) = (60, 40);
        let model = only_depth(DepthEffects { flying_pixels: Some(1.0), ..no_depth_effects() });
        let clean = step_scene(w, h);
        let depth = model.apply(
            &camera(60, 40),
            &clean,
            &vec![[128; 3]; w * h],
            &mut vec![[128; 3]; w * h],
            &mut seeded_rng(2),
        );
        let mut mixed = 0;
        for (i, (&z, &c)) in depth.iter().zip(&clean).enumerate() {
            if z != c {
                mixed += 1;
                assert!([19, 20, 39, 40].contains(&(i % w)), "pixel {i} is no edge");
                assert!((0.5..=1.0).contains(&z), "{z}");
            }
        }
        assert!(mixed > 2 * h, "{mixed}");
    }

    #[test]
    fn quantisation_steps_grow_with_the_square_of_depth() {
        let model = only_depth(DepthEffects { quantisation: Some(2.9e-3), ..no_depth_effects() });
        let (w, h) = (200, 1);
        let clean: Vec<f32> = (0..w).map(|i| 1.0 + i as f32 * 1e-4).collect();
        let depth = model.apply(
            &camera(200, 1),
            &clean,
            &vec![[128; 3]; w * h],
            &mut vec![[128; 3]; w * h],
            &mut seeded_rng(3),
        );
        let mut levels: Vec<f32> = depth.clone();
        levels.dedup();
        // 2 cm of depth at ~1 m in 2.9 mm steps: about 7 levels.
        assert!((6..=9).contains(&levels.len()), "{levels:?}");
        for (z, c) in depth.iter().zip(&clean) {
            assert!((z - c).abs() <= 2.9e-3 * c * c / 2.0 + 1e-6);
        }
    }

    #[test]
    fn dark_and_grazing_surfaces_lose_depth_and_bright_frontal_ones_less() {
        let (w, h) = (160, 160);
        let cam = camera(160, 160);
        // A wall at 1 m facing the camera, and the same wall tilted 80°.
        let frontal = vec![1.0f32; w * h];
        let tilted: Vec<f32> = (0..w * h)
            .map(|i| {
                let x = ((i % w) as f64 - cam.cx) / cam.fx;
                // The plane z = 1 + tan(80°)·x, intersected with the ray.
                (1.0 / (1.0 - 80f64.to_radians().tan() * x)).clamp(0.0, 5.0) as f32
            })
            .collect();
        let holes = |model: &SensorModel, depth: &[f32], grey: u8| {
            let mut rgb = vec![[grey; 3]; w * h];
            let out = model.apply(&cam, depth, &rgb.clone(), &mut rgb, &mut seeded_rng(4));
            // Holes come in 4 px patches: 525 of them here.
            let valid: Vec<usize> = (10..150).flat_map(|v| (10..70).map(move |u| v * w + u)).collect();
            valid.iter().filter(|&&i| out[i] == 0.0).count() as f64 / valid.len() as f64
        };
        let dark = only_depth(DepthEffects { dark: Some(0.5), ..no_depth_effects() });
        assert!((holes(&dark, &frontal, 0) - 0.5).abs() < 0.1, "black: {}", holes(&dark, &frontal, 0));
        assert_eq!(holes(&dark, &frontal, 128), 0.0);
        let grazing = only_depth(DepthEffects { grazing: Some(0.6), ..no_depth_effects() });
        assert_eq!(holes(&grazing, &frontal, 128), 0.0);
        let tilted_holes = holes(&grazing, &tilted, 128);
        // 72–88° from the normal across the region: 0.6 · (cos 70° − cos θ) / cos 70° averages ~0.15.
        assert!((0.08..0.3).contains(&tilted_holes), "80° off the line of sight: {tilted_holes}");
        let specular = only_depth(DepthEffects { specular: Some(0.3), ..no_depth_effects() });
        assert!((holes(&specular, &frontal, 250) - 0.3).abs() < 0.1);
        assert_eq!(holes(&specular, &frontal, 128), 0.0);
    }

    #[test]
    fn misregistration_moves_the_whole_depth_image_by_at_most_its_reach() {
        let (w, h) = (60, 40);
        let model = only_depth(DepthEffects { misregistration_px: Some(2), ..no_depth_effects() });
        let clean = step_scene(w, h);
        let mut shifts = std::collections::BTreeSet::new();
        for seed in 0..30 {
            let depth = model.apply(
                &camera(60, 40),
                &clean,
                &vec![[0; 3]; w * h],
                &mut vec![[0; 3]; w * h],
                &mut seeded_rng(seed),
            );
            let row = &depth[20 * w..21 * w];
            let start = row.iter().position(|&z| z == 0.5).unwrap() as i64 - 20;
            assert!(start.abs() <= 2, "{start}");
            shifts.insert(start);
        }
        assert!(shifts.len() >= 3, "{shifts:?}");
    }

    #[test]
    fn turning_one_effect_off_leaves_the_others_unchanged() {
        let (w, h) = (64, 48);
        let cam = camera(64, 48);
        let clean = step_scene(w, h);
        let render: Vec<[u8; 3]> = (0..w * h).map(|i| [(i % 256) as u8, 90, 200]).collect();
        let run = |model: SensorModel| {
            let mut rgb = render.clone();
            let depth = model.apply(&cam, &clean, &render, &mut rgb, &mut seeded_rng(7));
            (depth, rgb)
        };
        let all = run(SensorModel::default());
        assert_eq!(all, run(SensorModel::default()), "the same seed gives the same image");
        let without_jpeg = run(SensorModel::default().without("jpeg").unwrap());
        assert_eq!(all.0, without_jpeg.0, "depth does not depend on the colour effects");
        assert_ne!(all.1, without_jpeg.1);
        let without_shadow = run(SensorModel::default().without("shadow").unwrap());
        assert_eq!(all.1, without_shadow.1, "colour does not depend on the depth effects");
        assert_ne!(all.0, without_shadow.0);
        let err = SensorModel::default().without("lens-flare").unwrap_err();
        assert!(err.contains("lens-flare") && err.contains("jpeg"), "{err}");
    }

    #[test]
    fn colour_effects_keep_a_grey_image_grey_on_average_within_their_ranges() {
        let (w, h) = (64, 48);
        let model = SensorModel { depth: no_depth_effects(), ..SensorModel::default() };
        for seed in 0..10 {
            let mut rgb = vec![[128u8; 3]; w * h];
            model.apply(&camera(64, 48), &vec![0.0; w * h], &rgb.clone(), &mut rgb, &mut seeded_rng(seed));
            let mean = rgb.iter().map(|p| f64::from(p[1])).sum::<f64>() / (w * h) as f64;
            // ±0.5 stop, ±10 % balance, γ 0.8–1.25 and 30 % vignetting keep a
            // mid grey between these bounds.
            assert!((40.0..=230.0).contains(&mean), "seed {seed}: {mean}");
        }
    }
}
