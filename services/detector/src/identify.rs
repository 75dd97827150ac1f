//! The identifier: which object of the set (or none) each region of the
//! segmentation is, from a crop around the whole region.
//!
//! The segmentation network labels each pixel from what a fraction of the
//! object shows, and most of the objects it misses on the development
//! renders are found whole and labelled as another object. The identifier
//! (`identify.onnx` beside `detector.onnx`, trained by
//! `training/poseflow_train/identify.py`) sees a region at a fixed size with
//! its depth relief and metric size, like the second stage of a two-stage
//! detector; each region then takes the object that its answer and the
//! segmentation's agree on best (see [`Identifier::relabel`]).
//!
//! Its input is built on the frame's grid of every other pixel, cell
//! (x, y) being frame pixel (2x + 1, 2y + 1), whatever the segmentation's
//! own resolution:
//!
//! - a square of `side = context · max(box columns, box rows) + 2` cells
//!   centred on the region's box, sampled `crop × crop` times, sample i at
//!   cell ⌊centre − side/2 + (i + ½)·side/crop⌋ (zeros outside the frame);
//! - channels R, G, B / 255; (z − z₀) / `relief_m` clamped to ±1 where
//!   depth was measured (z₀ the region's median depth, z in whole
//!   millimetres), else 0; 1 where depth was measured; 1 on the region; the
//!   side in metres (side · 2 · z₀ / fx) / `size_m` on every sample.
//!
//! Output `probabilities`, N × (1 + K): class 0 is "none of the objects",
//! class k the k-th of `object_ids` (the segmentation's order).

use std::path::{Path, PathBuf};

use ort::session::Session;
use ort::value::{TensorElementType, TensorRef};
use serde::Deserialize;

use crate::DetectorError;
use crate::instances::{LabelMap, Region, regions};
use crate::network::ImageView;

/// The format `identify.json` must declare.
pub const FORMAT: &str = "poseflow-identify/1";

/// The frame pixels per grid cell along each axis.
const GRID_DOWN: usize = 2;
const CHANNELS: usize = 7;

/// `identify.json`.
#[derive(Debug, Clone, Deserialize)]
pub struct IdentifyMeta {
    pub format: String,
    pub object_ids: Vec<u32>,
    pub crop: usize,
    pub context: f64,
    pub relief_m: f32,
    pub size_m: f32,
    pub grid_down: usize,
}

/// What [`Identifier::relabel`] did to one frame's regions.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Relabelled {
    /// Regions the identifier saw.
    pub regions: usize,
    /// Of those, the ones that took another object's label.
    pub changed: usize,
}

/// A loaded identifier.
#[derive(Debug)]
pub struct Identifier {
    session: Session,
    meta: IdentifyMeta,
    path: PathBuf,
    input: Vec<f32>,
}

impl Identifier {
    /// Loads `dir/identify.onnx` described by `dir/identify.json`, or
    /// `None` when the directory has no `identify.json`. Its objects must
    /// be `object_ids`, in that order.
    pub fn load(dir: &Path, threads: usize, object_ids: &[u32]) -> Result<Option<Self>, DetectorError> {
        let meta_path = dir.join("identify.json");
        if !meta_path.exists() {
            return Ok(None);
        }
        let bad = |detail: String| DetectorError::Model { path: meta_path.clone(), detail };
        let text = std::fs::read_to_string(&meta_path).map_err(|e| bad(format!("cannot read ({e})")))?;
        let meta: IdentifyMeta = serde_json::from_str(&text).map_err(|e| bad(e.to_string()))?;
        if meta.format != FORMAT {
            return Err(bad(format!("format is `{}`, expected `{FORMAT}`", meta.format)));
        }
        if meta.object_ids != object_ids {
            return Err(bad(format!(
                "object_ids {:?} differ from the segmentation network's {object_ids:?} (detector.json)",
                meta.object_ids
            )));
        }
        if meta.grid_down != GRID_DOWN {
            return Err(bad(format!("grid_down: expected {GRID_DOWN}, found {}", meta.grid_down)));
        }
        let positive = |x: f64| x.is_finite() && x > 0.0;
        if meta.crop == 0
            || !positive(meta.context)
            || !positive(f64::from(meta.relief_m))
            || !positive(f64::from(meta.size_m))
        {
            return Err(bad(format!(
                "expected a positive crop, context, relief_m and size_m, found {}, {}, {}, {}",
                meta.crop, meta.context, meta.relief_m, meta.size_m
            )));
        }
        let path = dir.join("identify.onnx");
        let session = poseflow_onnx::session(&path, threads, "the identifier beside identify.json")?;
        use TensorElementType::Float32 as F;
        let crop = meta.crop as i64;
        let classes = object_ids.len() as i64 + 1;
        poseflow_onnx::check_ports(
            &path,
            "inputs",
            session.inputs(),
            &[poseflow_onnx::port("crops", F, &[-1, CHANNELS as i64, crop, crop])],
        )?;
        poseflow_onnx::check_ports(
            &path,
            "outputs",
            session.outputs(),
            &[poseflow_onnx::port("probabilities", F, &[-1, classes])],
        )?;
        Ok(Some(Self { session, meta, path, input: Vec::new() }))
    }

    /// Relabels each region of `map` of at least `min_cells` map cells and
    /// sets its cells' confidence. The identifier's probabilities are
    /// multiplied by the region's mean `posteriors` (the segmentation's
    /// per-cell class probabilities, class-major, background first), when
    /// given, as two independent opinions; the region takes the most
    /// probable object and that object's share of the product. A region
    /// that both call background or none of the objects keeps a label but a
    /// low confidence, which `min_score` then drops.
    pub fn relabel(
        &mut self,
        map: &mut LabelMap,
        image: &ImageView<'_>,
        min_cells: usize,
        posteriors: Option<&[f32]>,
    ) -> Result<Relabelled, DetectorError> {
        let (grid_width, grid_height) = grid_size(image);
        if grid_width == 0 || grid_height == 0 {
            // A frame under two pixels wide or high has no grid to crop from.
            return Ok(Relabelled::default());
        }
        let found: Vec<Region> = regions(map).into_iter().filter(|r| r.cells.len() >= min_cells.max(1)).collect();
        let mut done = Relabelled { regions: found.len(), ..Relabelled::default() };
        if found.is_empty() {
            return Ok(done);
        }
        let classes = self.meta.object_ids.len() + 1;
        let plane = map.width * map.height;
        if let Some(p) = posteriors
            && p.len() != classes * plane
        {
            return Err(DetectorError::Run {
                path: self.path.clone(),
                detail: format!("expected {classes} × {plane} segmentation posteriors, got {}", p.len()),
            });
        }
        let size = CHANNELS * self.meta.crop * self.meta.crop;
        self.input.clear();
        self.input.resize(found.len() * size, 0.0);
        // One membership raster for the frame: each region's cells are
        // marked for its crop and cleared after, not a raster per region.
        let mut inside = vec![false; plane];
        for (region, out) in found.iter().zip(self.input.chunks_exact_mut(size)) {
            region.cells.iter().for_each(|&c| inside[c] = true);
            crop_input(map, region, &inside, image, &self.meta, out);
            region.cells.iter().for_each(|&c| inside[c] = false);
        }
        let run_error = |e: ort::Error| DetectorError::Run { path: self.path.clone(), detail: e.to_string() };
        let crop = self.meta.crop;
        let tensor =
            TensorRef::from_array_view(([found.len(), CHANNELS, crop, crop], &self.input[..])).map_err(run_error)?;
        let outputs = self.session.run(ort::inputs!["crops" => tensor]).map_err(run_error)?;
        let (_, probabilities) = outputs["probabilities"].try_extract_tensor::<f32>().map_err(run_error)?;
        for (region, identified) in found.iter().zip(probabilities.chunks_exact(classes)) {
            let mut joint = identified.to_vec();
            if let Some(p) = posteriors {
                for (c, q) in joint.iter_mut().enumerate() {
                    let mean = region.cells.iter().map(|&i| p[c * plane + i]).sum::<f32>() / region.cells.len() as f32;
                    *q *= mean;
                }
            }
            let total: f32 = joint.iter().sum();
            let (object, share) = most_probable(&joint[1..]);
            let label = object + 1;
            let confidence = if total > 0.0 { share / total } else { 0.0 };
            done.changed += usize::from(label != usize::from(region.class));
            for &c in &region.cells {
                map.labels[c] = label as u8;
                map.confidence[c] = confidence;
            }
        }
        Ok(done)
    }
}

/// The index and value of the largest probability (the first of equals).
fn most_probable(p: &[f32]) -> (usize, f32) {
    p.iter().copied().enumerate().fold((0, f32::NEG_INFINITY), |best, (k, q)| if q > best.1 { (k, q) } else { best })
}

/// The grid's size for a frame: every other pixel.
fn grid_size(image: &ImageView<'_>) -> (usize, usize) {
    (image.width / GRID_DOWN, image.height / GRID_DOWN)
}

/// The grid cells whose map cells lie in `c0..=c1`: those whose
/// `floor(g·cells/grid)` does.
fn grid_span(c0: usize, c1: usize, cells: usize, grid: usize) -> (usize, usize) {
    let first = |cell: usize| (cell * grid).div_ceil(cells);
    (first(c0), first(c1 + 1).min(grid).saturating_sub(1).max(first(c0)))
}

/// Writes one region's `CHANNELS × crop × crop` input (the module's
/// contract) into `out`; `inside` marks the region's map cells.
pub(crate) fn crop_input(
    map: &LabelMap,
    region: &Region,
    inside: &[bool],
    image: &ImageView<'_>,
    meta: &IdentifyMeta,
    out: &mut [f32],
) {
    let (gw, gh) = grid_size(image);
    let (mw, mh) = (map.width, map.height);
    let in_region = |gx: usize, gy: usize| inside[(gy * mh / gh) * mw + gx * mw / gw];
    let pixel = |gx: usize, gy: usize| (GRID_DOWN * gy + 1) * image.width + GRID_DOWN * gx + 1;
    let depth_m = |gx: usize, gy: usize| {
        let d = image.depth[pixel(gx, gy)];
        if d.is_finite() && d > 0.0 { (d * 1000.0).round() / 1000.0 } else { 0.0 }
    };
    let [cx0, cy0, cx1, cy1] = region.bounds;
    let (x0, x1) = grid_span(cx0, cx1, mw, gw);
    let (y0, y1) = grid_span(cy0, cy1, mh, gh);
    let mut measured: Vec<f32> = (y0..=y1)
        .flat_map(|gy| (x0..=x1).map(move |gx| (gx, gy)))
        .filter(|&(gx, gy)| in_region(gx, gy))
        .map(|(gx, gy)| depth_m(gx, gy))
        .filter(|&d| d > 0.0)
        .collect();
    measured.sort_by(f32::total_cmp);
    let z0 = measured.get(measured.len().saturating_sub(1) / 2).copied().unwrap_or(0.0);
    let (cx, cy) = ((x0 + x1 + 1) as f64 / 2.0, (y0 + y1 + 1) as f64 / 2.0);
    let side = meta.context * ((x1 - x0 + 1).max(y1 - y0 + 1)) as f64 + 2.0;
    let crop = meta.crop;
    let at = |centre: f64, i: usize| (centre - side / 2.0 + (i as f64 + 0.5) * side / crop as f64).floor();
    let scale = (side * GRID_DOWN as f64 * f64::from(z0) / image.camera.fx / f64::from(meta.size_m)) as f32;
    let plane = crop * crop;
    for i in 0..crop {
        let gy = at(cy, i);
        for j in 0..crop {
            let gx = at(cx, j);
            let k = i * crop + j;
            out[6 * plane + k] = scale;
            if gx < 0.0 || gy < 0.0 || gx >= gw as f64 || gy >= gh as f64 {
                for c in 0..6 {
                    out[c * plane + k] = 0.0;
                }
                continue;
            }
            let (gx, gy) = (gx as usize, gy as usize);
            let p = pixel(gx, gy);
            for c in 0..3 {
                out[c * plane + k] = image.rgb[3 * p + c] / 255.0;
            }
            let z = depth_m(gx, gy);
            out[3 * plane + k] = if z > 0.0 && z0 > 0.0 { ((z - z0) / meta.relief_m).clamp(-1.0, 1.0) } else { 0.0 };
            out[4 * plane + k] = if z > 0.0 { 1.0 } else { 0.0 };
            out[5 * plane + k] = if in_region(gx, gy) { 1.0 } else { 0.0 };
        }
    }
}

#[cfg(test)]
mod tests {
    use poseflow_geometry::metrics::Pinhole;

    use super::*;
    use crate::instances::membership;

    fn meta(crop: usize, context: f64) -> IdentifyMeta {
        IdentifyMeta {
            format: FORMAT.into(),
            object_ids: vec![7],
            crop,
            context,
            relief_m: 0.1,
            size_m: 0.5,
            grid_down: GRID_DOWN,
        }
    }

    /// An 8 × 8 frame (a 4 × 4 grid): pixel (u, v) has red u, green v, blue
    /// 9, and depth 1 m + (u + v) cm except where `hole` says none.
    fn frame(hole: (usize, usize)) -> (Vec<f32>, Vec<f32>) {
        let mut rgb = Vec::new();
        let mut depth = Vec::new();
        for v in 0..8 {
            for u in 0..8 {
                rgb.extend([u as f32, v as f32, 9.0]);
                depth.push(if (u, v) == hole { 0.0 } else { 1.0 + (u + v) as f32 / 100.0 });
            }
        }
        (rgb, depth)
    }

    fn map(width: usize, height: usize, cells: &[usize]) -> LabelMap {
        let mut labels = vec![0; width * height];
        for &c in cells {
            labels[c] = 1;
        }
        LabelMap {
            width,
            height,
            labels,
            confidence: vec![1.0; width * height],
            depth: Vec::new(),
            instances: Vec::new(),
        }
    }

    #[test]
    fn a_crop_as_wide_as_the_grid_samples_every_cell_once() {
        let (rgb, depth) = frame((3, 3));
        let camera = Pinhole { fx: 400.0, fy: 400.0, cx: 4.0, cy: 4.0 };
        let image = ImageView { rgb: &rgb, depth: &depth, width: 8, height: 8, camera };
        // The middle 2 × 2 cells; context 1: side 2 + 2 = 4 cells around
        // centre (2, 2), so sample i is cell i.
        let labels = map(4, 4, &[5, 6, 9, 10]);
        let region = regions(&labels).remove(0);
        let mut out = vec![f32::NAN; CHANNELS * 16];
        crop_input(&labels, &region, &membership(&labels, &region), &image, &meta(4, 1.0), &mut out);
        let plane = |c: usize| &out[c * 16..(c + 1) * 16];
        // Cell (x, y) is pixel (2x + 1, 2y + 1).
        let expected_red: Vec<f32> = (0..16).map(|k| (2 * (k % 4) + 1) as f32 / 255.0).collect();
        let expected_green: Vec<f32> = (0..16).map(|k| (2 * (k / 4) + 1) as f32 / 255.0).collect();
        assert_eq!(plane(0), &expected_red[..]);
        assert_eq!(plane(1), &expected_green[..]);
        assert!(plane(2).iter().all(|&b| b == 9.0 / 255.0));
        // Region depths: cells (1,1) (2,1) (1,2) (2,2) are pixels whose
        // u + v is 6, 8, 8, 10 cm over 1 m, but pixel (3, 3) has none: the
        // median of 1.08, 1.08, 1.10 is 1.08.
        let z0 = 1.08f32;
        for k in 0..16 {
            let (u, v) = (2 * (k % 4) + 1, 2 * (k / 4) + 1);
            let z = if (u, v) == (3, 3) { 0.0 } else { 1.0 + (u + v) as f32 / 100.0 };
            let relief = if z > 0.0 { ((z - z0) / 0.1).clamp(-1.0, 1.0) } else { 0.0 };
            assert!((plane(3)[k] - relief).abs() < 1e-5, "relief at {k}: {} against {relief}", plane(3)[k]);
            assert_eq!(plane(4)[k], if z > 0.0 { 1.0 } else { 0.0 });
        }
        let inside: Vec<f32> = (0..16).map(|k| if [5, 6, 9, 10].contains(&k) { 1.0 } else { 0.0 }).collect();
        assert_eq!(plane(5), &inside[..]);
        // 4 cells of 2 pixels at 1.08 m over fx 400: 0.0432 m, over size_m 0.5.
        let size = (4.0 * 2.0 * 1.08 / 400.0 / 0.5) as f32;
        assert!(plane(6).iter().all(|&s| (s - size).abs() < 1e-6), "{:?}", plane(6));
    }

    #[test]
    fn samples_beyond_the_frame_are_zero_and_a_coarser_map_is_read_through_the_grid() {
        let (rgb, depth) = frame((99, 99));
        let camera = Pinhole { fx: 400.0, fy: 400.0, cx: 4.0, cy: 4.0 };
        let image = ImageView { rgb: &rgb, depth: &depth, width: 8, height: 8, camera };
        // A 2 × 2 map (each cell 2 × 2 grid cells): its top-left cell is
        // grid cells 0..=1 along each axis. Context 1: side 2 + 2 = 4 around
        // centre (1, 1), so sample i is cell i − 1.
        let labels = map(2, 2, &[0]);
        let region = regions(&labels).remove(0);
        let mut out = vec![f32::NAN; CHANNELS * 16];
        crop_input(&labels, &region, &membership(&labels, &region), &image, &meta(4, 1.0), &mut out);
        for k in 0..16 {
            let (i, j) = (k / 4, k % 4);
            let outside = i == 0 || j == 0;
            let inside = (1..=2).contains(&i) && (1..=2).contains(&j);
            for c in 0..6 {
                if outside {
                    assert_eq!(out[c * 16 + k], 0.0, "channel {c} sample ({j}, {i})");
                }
            }
            assert_eq!(out[5 * 16 + k], if inside { 1.0 } else { 0.0 }, "region at sample ({j}, {i})");
            assert!(out[6 * 16 + k] > 0.0, "the size channel fills the crop");
        }
        assert_eq!(out[16 + 5], 1.0 / 255.0, "sample (1, 1) is cell (0, 0), pixel (1, 1)");
    }

    #[test]
    fn the_most_probable_class_wins_and_ties_keep_the_first() {
        assert_eq!(most_probable(&[0.1, 0.7, 0.2]), (1, 0.7));
        assert_eq!(most_probable(&[0.5, 0.5]), (0, 0.5));
    }
}
