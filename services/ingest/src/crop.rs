//! The image half of an observation: a square crop around the object's
//! mask, resampled to the encoder's S×S input and normalised, and the token
//! mask saying which of the P×P patches the object touches.
//!
//! Image coordinates: pixel `(u, v)` has its centre at integer coordinates
//! and covers `[u − ½, u + ½] × [v − ½, v + ½]` (BOP / OpenCV). The crop is
//! the square `[x_min, x_min + side] × [y_min, y_min + side]` in those
//! coordinates; output pixel `(j, i)` samples the crop at
//! `(x_min + (j + ½)·side/S, y_min + (i + ½)·side/S)`. Outside the image the
//! crop is black.

use serde::{Deserialize, Serialize};

/// The square crop in full-image coordinates.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CropBox {
    pub x_min: f64,
    pub y_min: f64,
    pub side: f64,
}

impl CropBox {
    /// The square centred on the inclusive pixel box `[u0, u1] × [v0, v1]`,
    /// its side the longer box side times `1 + 2·padding`.
    pub fn around(u0: u32, v0: u32, u1: u32, v1: u32, padding: f64) -> Self {
        let (w, h) = (f64::from(u1 - u0 + 1), f64::from(v1 - v0 + 1));
        let side = w.max(h) * (1.0 + 2.0 * padding);
        let (cu, cv) = ((f64::from(u0) + f64::from(u1)) / 2.0, (f64::from(v0) + f64::from(v1)) / 2.0);
        Self { x_min: cu - side / 2.0, y_min: cv - side / 2.0, side }
    }

    /// The square scaled by `factor` about its centre.
    pub fn scaled(&self, factor: f64) -> Self {
        let side = self.side * factor;
        let grow = (side - self.side) / 2.0;
        Self { x_min: self.x_min - grow, y_min: self.y_min - grow, side }
    }

    /// `[x_min, y_min, x_max, y_max]`, as the Observation header carries it.
    pub fn corners(&self) -> [f32; 4] {
        [self.x_min as f32, self.y_min as f32, (self.x_min + self.side) as f32, (self.y_min + self.side) as f32]
    }
}

/// Per-channel normalisation `(value/255 − mean)/std` applied to the crop,
/// RGB order; the default is ImageNet's, which DINOv2 expects.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Normalisation {
    pub mean: [f32; 3],
    pub std: [f32; 3],
}

impl Default for Normalisation {
    fn default() -> Self {
        Self { mean: [0.485, 0.456, 0.406], std: [0.229, 0.224, 0.225] }
    }
}

/// Writes the crop into `out` (3·S·S values, CHW), bilinear, with `k × k`
/// sub-samples per output pixel when the crop is more than 1.5 times the
/// output size (to average rather than alias).
pub fn write_crop(
    rgb: &[[u8; 3]],
    width: u32,
    height: u32,
    crop: &CropBox,
    size: usize,
    norm: &Normalisation,
    out: &mut [f32],
) {
    let (w, h) = (width as usize, height as usize);
    let scale = crop.side / size as f64;
    let k = (scale / 1.5).ceil().clamp(1.0, 3.0) as usize;
    let plane = size * size;
    let at = |x: isize, y: isize| -> [f32; 3] {
        if x < 0 || y < 0 || x as usize >= w || y as usize >= h {
            [0.0; 3]
        } else {
            rgb[y as usize * w + x as usize].map(f32::from)
        }
    };
    let factors: [(f32, f32); 3] = std::array::from_fn(|c| (1.0 / (255.0 * norm.std[c]), norm.mean[c] / norm.std[c]));
    // A sub-sample's column depends only on (j, sj) and its row only on
    // (i, si): each pixel position and bilinear weight is computed once per
    // column and row of sub-samples, not once per sub-sample.
    let taps = |min: f64| -> Vec<(isize, f32)> {
        (0..size * k)
            .map(|n| {
                let (pixel, sub) = (n / k, n % k);
                let x = min + (pixel as f64 + (sub as f64 + 0.5) / k as f64) * scale;
                let x0 = x.floor();
                (x0 as isize, (x - x0) as f32)
            })
            .collect()
    };
    let (columns, rows) = (taps(crop.x_min), taps(crop.y_min));
    for i in 0..size {
        for j in 0..size {
            let mut sum = [0.0f32; 3];
            for &(y0, fy) in &rows[i * k..(i + 1) * k] {
                for &(x0, fx) in &columns[j * k..(j + 1) * k] {
                    let (a, b, c, d) = (at(x0, y0), at(x0 + 1, y0), at(x0, y0 + 1), at(x0 + 1, y0 + 1));
                    for ch in 0..3 {
                        let top = a[ch] + (b[ch] - a[ch]) * fx;
                        let bottom = c[ch] + (d[ch] - c[ch]) * fx;
                        sum[ch] += top + (bottom - top) * fy;
                    }
                }
            }
            let samples = (k * k) as f32;
            for ch in 0..3 {
                out[ch * plane + i * size + j] = sum[ch] / samples * factors[ch].0 - factors[ch].1;
            }
        }
    }
}

/// Writes the P×P token mask into `out`: 1 for every patch that some mask
/// pixel's square overlaps, 0 elsewhere; row-major over patch rows.
pub fn write_token_mask(mask: &[bool], width: u32, crop: &CropBox, grid: usize, out: &mut [f32]) {
    out.fill(0.0);
    let w = width as usize;
    if w == 0 {
        return;
    }
    // Patch coordinates of an image coordinate.
    let to_patch = |x: f64, min: f64| (x - min) / crop.side * grid as f64;
    // The patches a pixel's square overlaps along one axis, or none: the
    // open interval (a, b), so a pixel ending exactly on a patch border does
    // not enter the next patch.
    let span = |at: usize, min: f64| {
        let (a, b) = (to_patch(at as f64 - 0.5, min), to_patch(at as f64 + 0.5, min));
        (b > 0.0 && a < grid as f64)
            .then(|| a.floor().max(0.0) as usize..=(b.ceil() - 1.0).min(grid as f64 - 1.0) as usize)
    };
    // Each column's span once; each row's once, for the rows that hold
    // mask pixels.
    let columns: Vec<_> = (0..w).map(|u| span(u, crop.x_min)).collect();
    for (v, row) in mask.chunks(w).enumerate() {
        let Some(rows) = row.contains(&true).then(|| span(v, crop.y_min)).flatten() else { continue };
        for (_, columns) in row.iter().zip(&columns).filter(|(inside, _)| **inside) {
            for c in columns.iter().flat_map(|span| span.clone()) {
                for r in rows.clone() {
                    out[r * grid + c] = 1.0;
                }
            }
        }
    }
}

/// Writes the G×G depth and mask grids of the square `crop` (`depth_out`, `mask_out`,
/// G·G values each, row-major over grid rows): each cell takes the image
/// pixel nearest to its centre. Depth is in metres, 0 where it is missing,
/// beyond `max_depth` or outside the image; the mask is 1 or 0.
#[allow(clippy::too_many_arguments)]
pub fn write_depth_and_mask(
    depth: &[f32],
    mask: &[bool],
    width: u32,
    height: u32,
    crop: &CropBox,
    grid: usize,
    max_depth: f32,
    depth_out: &mut [f32],
    mask_out: &mut [f32],
) {
    let (w, h) = (i64::from(width), i64::from(height));
    let cell = crop.side / grid as f64;
    for i in 0..grid {
        for j in 0..grid {
            let u = (crop.x_min + (j as f64 + 0.5) * cell).round() as i64;
            let v = (crop.y_min + (i as f64 + 0.5) * cell).round() as i64;
            let pixel = ((0..w).contains(&u) && (0..h).contains(&v)).then(|| (v * w + u) as usize);
            let z = pixel.map_or(0.0, |k| depth[k]);
            depth_out[i * grid + j] = if z.is_finite() && z > 0.0 && z <= max_depth { z } else { 0.0 };
            mask_out[i * grid + j] = if pixel.is_some_and(|k| mask[k]) { 1.0 } else { 0.0 };
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tight_box_with_padding_is_centred_and_square() {
        let crop = CropBox::around(10, 20, 29, 29, 0.0);
        assert_eq!(crop, CropBox { x_min: 9.5, y_min: 14.5, side: 20.0 });
        assert_eq!(crop.scaled(2.0), CropBox { x_min: -0.5, y_min: 4.5, side: 40.0 });
        let padded = CropBox::around(10, 20, 29, 29, 0.25);
        assert_eq!(padded.side, 30.0);
        assert_eq!(padded.corners(), [4.5, 9.5, 34.5, 39.5]);
    }

    #[test]
    fn identity_crop_reproduces_the_pixels() {
        // A 4×4 image cropped exactly to itself at S = 4.
        let rgb: Vec<[u8; 3]> = (0..16).map(|i| [i as u8 * 10, 255 - i as u8, 7]).collect();
        let crop = CropBox::around(0, 0, 3, 3, 0.0);
        let plain = Normalisation { mean: [0.0; 3], std: [1.0 / 255.0; 3] };
        let mut out = vec![0.0; 48];
        write_crop(&rgb, 4, 4, &crop, 4, &plain, &mut out);
        for (i, pixel) in rgb.iter().enumerate() {
            for c in 0..3 {
                assert!((out[c * 16 + i] - f32::from(pixel[c])).abs() < 1e-3, "pixel {i} channel {c}");
            }
        }
    }

    #[test]
    fn outside_the_image_is_black_and_normalised() {
        let rgb = vec![[255u8; 3]; 4];
        let crop = CropBox { x_min: 10.0, y_min: 10.0, side: 2.0 };
        let norm = Normalisation::default();
        let mut out = vec![0.0; 12];
        write_crop(&rgb, 2, 2, &crop, 2, &norm, &mut out);
        assert!((out[0] + norm.mean[0] / norm.std[0]).abs() < 1e-6);
    }

    #[test]
    fn depth_and_mask_grids_take_the_pixel_nearest_each_cell_centre() {
        // A 4×4 image, depth = 1 + pixel index / 100 with one missing and one
        // too far, the mask its two left columns.
        let mut depth: Vec<f32> = (0..16).map(|i| 1.0 + i as f32 / 100.0).collect();
        depth[5] = 0.0;
        depth[13] = 9.0;
        let mask: Vec<bool> = (0..16).map(|i| i % 4 < 2).collect();
        let (mut d, mut m) = (vec![-1.0; 4], vec![-1.0; 4]);
        // The image on a 2×2 grid: cell centres at 0.5 and 2.5, nearest
        // pixels 1 and 3 (halves round away from zero).
        let whole = CropBox { x_min: -0.5, y_min: -0.5, side: 4.0 };
        write_depth_and_mask(&depth, &mask, 4, 4, &whole, 2, 6.0, &mut d, &mut m);
        assert_eq!(d, [0.0, 1.07, 0.0, 1.15]);
        assert_eq!(m, [1.0, 0.0, 1.0, 0.0]);
        // Shifted two pixels right: the right column of cells is outside.
        let shifted = CropBox { x_min: 1.5, ..whole };
        write_depth_and_mask(&depth, &mask, 4, 4, &shifted, 2, 6.0, &mut d, &mut m);
        assert_eq!(d, [1.07, 0.0, 1.15, 0.0]);
        assert_eq!(m, [0.0; 4]);
    }

    #[test]
    fn token_mask_marks_exactly_the_touched_patches() {
        // 8×8 image, crop = the image, 2×2 patches of 4×4 pixels.
        let crop = CropBox::around(0, 0, 7, 7, 0.0);
        let mut mask = vec![false; 64];
        mask[8 + 1] = true; // patch (0, 0)
        let mut out = vec![0.0; 4];
        write_token_mask(&mask, 8, &crop, 2, &mut out);
        assert_eq!(out, [1.0, 0.0, 0.0, 0.0]);
        mask[5 * 8 + 4] = true; // first pixel of patch (1, 1)
        write_token_mask(&mask, 8, &crop, 2, &mut out);
        assert_eq!(out, [1.0, 0.0, 0.0, 1.0]);
        // A pixel straddling a patch border in a coarser crop touches both.
        let half = CropBox { x_min: 0.0, y_min: -0.5, side: 8.0 };
        let mut one = vec![false; 64];
        one[3] = true; // u = 3 covers [2.5, 3.5], border at 4.0: only column 0
        write_token_mask(&one, 8, &half, 2, &mut out);
        assert_eq!(out, [1.0, 0.0, 0.0, 0.0]);
        one[3] = false;
        one[4] = true; // covers [3.5, 4.5]: both columns
        write_token_mask(&one, 8, &half, 2, &mut out);
        assert_eq!(out, [1.0, 1.0, 0.0, 0.0]);
    }
}
