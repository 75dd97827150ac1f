//! Training-time imitation of what real segmentation and a real RGB-D
//! sensor do to a rendered frame's perfect masks: a mask a few pixels too
//! wide or too narrow, and depth registered a pixel or two off the colour
//! image. Renders have neither, and a network trained only on perfect masks
//! learns the exact outline of the object's cloud (measured: masks 3 px
//! wider turned per-sample 10°5cm from 68 % to 9 %). Used by `poseflow
//! observe` when writing training shards, never by the running stage.
//! Rasters are row-major; shifts are in pixels, +x right, +y down.

use poseflow_scene::bop::Raster;
use rand::Rng;

use crate::{ObjectMask, RgbdFrame};

/// Each object's mask grown by up to `grow` or shrunk by up to `shrink`
/// pixels (uniform over −shrink..=grow, a square neighbourhood) and each
/// frame's depth moved by up to `shift` pixels along each axis. Like a
/// detector's, the outline may also be `ragged` (pixels within that many of
/// it flipped, in 2×2 patches, with probability one half) and, with
/// probability `cut`, a straight cut removes up to 40 % of the mask (a
/// detector that misses part of an object).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct MaskJitter {
    pub grow: u32,
    pub shrink: u32,
    pub shift: u32,
    pub ragged: u32,
    pub cut: f64,
}

/// The largest share of a mask a cut removes.
const MAX_CUT_SHARE: f64 = 0.4;

impl MaskJitter {
    /// Jitters one frame and its objects' masks in place.
    pub fn apply<R: Rng + ?Sized>(&self, frame: &mut RgbdFrame, objects: &mut [ObjectMask], rng: &mut R) {
        let reach = self.shift as i64;
        let (dx, dy) = (rng.random_range(-reach..=reach), rng.random_range(-reach..=reach));
        if (dx, dy) != (0, 0) {
            frame.depth = shifted(&frame.depth, dx, dy);
        }
        for object in objects {
            let by = rng.random_range(-(self.shrink as i64)..=self.grow as i64);
            if by > 0 {
                object.mask = dilated(&object.mask, by as usize);
            } else if by < 0 {
                object.mask = eroded(&object.mask, by.unsigned_abs() as usize);
            }
            // Drawn only when asked for, so shards written without them keep
            // their random stream.
            if self.ragged > 0 {
                object.mask = ragged(&object.mask, self.ragged as usize, rng);
            }
            if self.cut > 0.0 && rng.random_bool(self.cut.min(1.0)) {
                object.mask = cut(&object.mask, rng);
            }
        }
    }
}

/// The raster moved by (dx, dy); uncovered pixels read 0 (no depth).
fn shifted(depth: &Raster<f32>, dx: i64, dy: i64) -> Raster<f32> {
    let (w, h) = (depth.width as i64, depth.height as i64);
    let pixels = (0..h)
        .flat_map(|v| (0..w).map(move |u| (u - dx, v - dy)))
        .map(|(u, v)| if (0..w).contains(&u) && (0..h).contains(&v) { depth.pixels[(v * w + u) as usize] } else { 0.0 })
        .collect();
    Raster { width: depth.width, height: depth.height, pixels }
}

/// Pixels within `band` of the outline take a random value per 2×2 patch.
fn ragged<R: Rng + ?Sized>(mask: &Raster<bool>, band: usize, rng: &mut R) -> Raster<bool> {
    let (outer, inner) = (dilated(mask, band), eroded(mask, band));
    let columns = (mask.width as usize).div_ceil(2);
    let patches: Vec<bool> = (0..columns * (mask.height as usize).div_ceil(2)).map(|_| rng.random_bool(0.5)).collect();
    let pixels = (0..mask.pixels.len())
        .map(|i| {
            let (u, v) = (i % mask.width as usize, i / mask.width as usize);
            if outer.pixels[i] && !inner.pixels[i] { patches[(v / 2) * columns + u / 2] } else { mask.pixels[i] }
        })
        .collect();
    Raster { width: mask.width, height: mask.height, pixels }
}

/// The mask without the part beyond a random straight line that holds at
/// most [`MAX_CUT_SHARE`] of it.
fn cut<R: Rng + ?Sized>(mask: &Raster<bool>, rng: &mut R) -> Raster<bool> {
    let w = mask.width as usize;
    let inside: Vec<(f64, f64)> =
        mask.pixels.iter().enumerate().filter(|(_, p)| **p).map(|(i, _)| ((i % w) as f64, (i / w) as f64)).collect();
    let angle = rng.random_range(0.0..std::f64::consts::TAU);
    let share = rng.random_range(0.0..MAX_CUT_SHARE);
    if inside.is_empty() {
        return mask.clone();
    }
    let (c, s) = (angle.cos(), angle.sin());
    let mut along: Vec<f64> = inside.iter().map(|(u, v)| c * u + s * v).collect();
    along.sort_by(f64::total_cmp);
    let limit = along[((1.0 - share) * (along.len() - 1) as f64) as usize];
    let pixels =
        mask.pixels.iter().enumerate().map(|(i, &p)| p && c * (i % w) as f64 + s * (i / w) as f64 <= limit).collect();
    Raster { width: mask.width, height: mask.height, pixels }
}

/// Binary dilation by a (2·by+1)² square: a row pass, then a column pass.
fn dilated(mask: &Raster<bool>, by: usize) -> Raster<bool> {
    let (w, h) = (mask.width as usize, mask.height as usize);
    let any_within = |values: &[bool], count: usize, at: &dyn Fn(usize) -> usize, i: usize| {
        (i.saturating_sub(by)..=(i + by).min(count - 1)).any(|j| values[at(j)])
    };
    let mut rows = vec![false; w * h];
    for v in 0..h {
        for u in 0..w {
            rows[v * w + u] = any_within(&mask.pixels, w, &|j| v * w + j, u);
        }
    }
    let mut pixels = vec![false; w * h];
    for v in 0..h {
        for u in 0..w {
            pixels[v * w + u] = any_within(&rows, h, &|j| j * w + u, v);
        }
    }
    Raster { width: mask.width, height: mask.height, pixels }
}

/// Binary erosion: the complement of the complement's dilation.
fn eroded(mask: &Raster<bool>, by: usize) -> Raster<bool> {
    let inverse = Raster { width: mask.width, height: mask.height, pixels: mask.pixels.iter().map(|p| !p).collect() };
    let grown = dilated(&inverse, by);
    Raster { width: mask.width, height: mask.height, pixels: grown.pixels.iter().map(|p| !p).collect() }
}

#[cfg(test)]
mod tests {
    use super::*;
    use poseflow_geometry::sampling::seeded_rng;

    fn square(width: u32, height: u32, u0: u32, u1: u32) -> Raster<bool> {
        let pixels =
            (0..width * height).map(|i| (u0..=u1).contains(&(i % width)) && (u0..=u1).contains(&(i / width))).collect();
        Raster { width, height, pixels }
    }

    #[test]
    fn dilation_and_erosion_move_a_square_outline() {
        let mask = square(12, 12, 4, 7);
        assert_eq!(dilated(&mask, 2), square(12, 12, 2, 9));
        assert_eq!(eroded(&mask, 1), square(12, 12, 5, 6));
        // Eroded away entirely: an empty mask (prepare then rejects it).
        assert!(eroded(&mask, 2).pixels.iter().all(|p| !p));
    }

    #[test]
    fn a_shift_moves_depth_and_leaves_no_measurement_behind() {
        let depth = Raster { width: 3, height: 2, pixels: vec![1.0, 2.0, 3.0, 4.0, 5.0, 6.0] };
        assert_eq!(shifted(&depth, 1, 0).pixels, vec![0.0, 1.0, 2.0, 0.0, 4.0, 5.0]);
        assert_eq!(shifted(&depth, 0, -1).pixels, vec![4.0, 5.0, 6.0, 0.0, 0.0, 0.0]);
    }

    #[test]
    fn jitter_stays_within_its_bounds_and_none_changes_nothing() {
        let camera = poseflow_scene::Camera { fx: 500.0, fy: 500.0, cx: 6.0, cy: 6.0, width: 12, height: 12 };
        let frame = RgbdFrame {
            frame_id: 0,
            label: "test".into(),
            camera,
            rgb: Raster { width: 12, height: 12, pixels: vec![[0; 3]; 144] },
            depth: Raster { width: 12, height: 12, pixels: (0..144).map(|i| i as f32).collect() },
        };
        let object = ObjectMask { obj_id: 1, instance: 0, mask: square(12, 12, 4, 7) };
        let mut rng = seeded_rng(3);
        for _ in 0..50 {
            let (mut jittered, mut objects) = (frame.clone(), vec![object.clone()]);
            MaskJitter { grow: 2, shrink: 1, shift: 1, ..MaskJitter::default() }.apply(
                &mut jittered,
                &mut objects,
                &mut rng,
            );
            let inside = objects[0].mask.pixels.iter().filter(|p| **p).count();
            assert!([4, 16, 36, 64].contains(&inside), "a square of side 2..=8, got {inside} pixels");
            let moved = jittered.depth.pixels[5 * 12 + 5] - frame.depth.pixels[5 * 12 + 5];
            assert!([-13.0, -12.0, -11.0, -1.0, 0.0, 1.0, 11.0, 12.0, 13.0].contains(&moved), "{moved}");
        }
        let (mut same, mut objects) = (frame.clone(), vec![object.clone()]);
        MaskJitter::default().apply(&mut same, &mut objects, &mut rng);
        assert_eq!((same.depth.pixels, &objects[0].mask), (frame.depth.pixels, &object.mask));
    }

    #[test]
    fn ragged_outlines_change_only_the_band_and_cuts_keep_most_of_the_mask() {
        let mask = square(40, 40, 10, 29);
        let mut rng = seeded_rng(5);
        let frayed = ragged(&mask, 2, &mut rng);
        let (outer, inner) = (dilated(&mask, 2), eroded(&mask, 2));
        let mut changed = 0;
        for i in 0..mask.pixels.len() {
            if frayed.pixels[i] != mask.pixels[i] {
                changed += 1;
                assert!(outer.pixels[i] && !inner.pixels[i], "pixel {i} is off the band");
            }
        }
        assert!(changed > 50, "{changed}");
        let area = |m: &Raster<bool>| m.pixels.iter().filter(|p| **p).count();
        for _ in 0..30 {
            let kept = cut(&mask, &mut rng);
            assert!(kept.pixels.iter().zip(&mask.pixels).all(|(k, m)| !k || *m), "a cut only removes");
            assert!(area(&kept) as f64 >= 0.59 * area(&mask) as f64, "{} of {}", area(&kept), area(&mask));
        }
    }
}
