//! The heart of the stage: one RGB-D frame and one object mask in, one
//! observation out.

use nalgebra::Point3;
use poseflow_contracts::{CameraIntrinsics, Header, ObservationHeader, flags};
use poseflow_scene::Camera;
use poseflow_scene::bop::Raster;
use rand::Rng;

use crate::crop::{CropBox, write_crop, write_depth_and_mask, write_token_mask};
use crate::points::{back_project, centre, remove_outliers, sample_fixed, thin};
use crate::{IngestError, IngestParams};

/// One RGB-D image with its camera; rasters are row-major and as large as
/// the camera's image. Depth in metres, 0 = no measurement.
#[derive(Debug, Clone)]
pub struct RgbdFrame {
    /// Monotonic per source.
    pub frame_id: u64,
    /// Where the frame came from, for messages (e.g. `scene 3 image 17`).
    pub label: String,
    pub camera: Camera,
    pub rgb: Raster<[u8; 3]>,
    pub depth: Raster<f32>,
}

/// One object to observe in a frame.
#[derive(Debug, Clone)]
pub struct ObjectMask {
    pub obj_id: u32,
    /// Index among the frame's objects (BOP's instance index).
    pub instance: usize,
    pub mask: Raster<bool>,
}

/// An observation before it is written out: everything but the image
/// pixels, which go straight into the output buffer.
#[derive(Debug, Clone, PartialEq)]
pub struct Prepared {
    pub obj_id: u32,
    pub crop: CropBox,
    /// Centred points (camera axes, metres).
    pub points: Vec<Point3<f32>>,
    /// The camera-frame mean subtracted from them.
    pub centroid: Point3<f32>,
    /// Distinct observed points among `points` (less than N when resampled).
    pub valid_point_count: usize,
}

/// The inclusive pixel box `(u0, v0, u1, v1)` of a mask and its pixel count.
pub(crate) fn mask_box(mask: &Raster<bool>) -> (Option<(u32, u32, u32, u32)>, usize) {
    let w = (mask.width as usize).max(1);
    let mut bounds: Option<(u32, u32, u32, u32)> = None;
    let mut count = 0;
    // Row by row: counting a row's pixels vectorises, and only rows that
    // hold some are searched for their ends.
    for (v, row) in mask.pixels.chunks(w).enumerate() {
        let in_row = row.iter().filter(|&&inside| inside).count();
        if in_row == 0 {
            continue;
        }
        count += in_row;
        let first = row.iter().position(|&inside| inside).unwrap_or(0) as u32;
        let last = row.iter().rposition(|&inside| inside).unwrap_or(0) as u32;
        let v = v as u32;
        bounds = Some(bounds.map_or((first, v, last, v), |(u0, v0, u1, _)| (u0.min(first), v0, u1.max(last), v)));
    }
    (bounds, count)
}

/// The camera as message intrinsics (`f32`).
pub(crate) fn intrinsics(camera: &Camera) -> CameraIntrinsics {
    CameraIntrinsics {
        fx: camera.fx as f32,
        fy: camera.fy as f32,
        cx: camera.cx as f32,
        cy: camera.cy as f32,
        width: camera.width,
        height: camera.height,
    }
}

/// The camera of message intrinsics.
pub(crate) fn camera(intrinsics: &CameraIntrinsics) -> Camera {
    let i = intrinsics;
    Camera {
        fx: f64::from(i.fx),
        fy: f64::from(i.fy),
        cx: f64::from(i.cx),
        cy: f64::from(i.cy),
        width: i.width,
        height: i.height,
    }
}

/// Checks that a frame's rasters match its camera.
pub fn check_frame(frame: &RgbdFrame) -> Result<(), IngestError> {
    let camera = &frame.camera;
    let bad = |detail: String| Err(IngestError::Frame { frame: frame.label.clone(), detail });
    let intrinsics = [camera.fx, camera.fy, camera.cx, camera.cy];
    if intrinsics.iter().any(|v| !v.is_finite()) || camera.fx <= 0.0 || camera.fy <= 0.0 {
        return bad(format!("intrinsics fx, fy, cx, cy = {intrinsics:?}: expected finite values with fx, fy > 0"));
    }
    for (what, (w, h)) in
        [("RGB", (frame.rgb.width, frame.rgb.height)), ("depth", (frame.depth.width, frame.depth.height))]
    {
        if (w, h) != (camera.width, camera.height) {
            return bad(format!("{what} image is {w}×{h}, expected the camera's {}×{}", camera.width, camera.height));
        }
    }
    Ok(())
}

/// Turns one object of a checked frame into an observation: mask box and
/// crop, back-projected depth, outlier removal, N points, centring.
pub fn prepare<R: Rng + ?Sized>(
    frame: &RgbdFrame,
    object: &ObjectMask,
    params: &IngestParams,
    rng: &mut R,
) -> Result<Prepared, IngestError> {
    let reject = |detail: String| IngestError::Object {
        frame: frame.label.clone(),
        obj_id: object.obj_id,
        instance: object.instance,
        detail,
    };
    let camera = &frame.camera;
    if (object.mask.width, object.mask.height) != (camera.width, camera.height) {
        return Err(reject(format!(
            "mask is {}×{}, expected the camera's {}×{}",
            object.mask.width, object.mask.height, camera.width, camera.height
        )));
    }
    let (bounds, pixels) = mask_box(&object.mask);
    let Some((u0, v0, u1, v1)) = bounds.filter(|_| pixels >= params.min_mask_pixels) else {
        return Err(reject(format!("mask has {pixels} pixels, expected at least {}", params.min_mask_pixels)));
    };
    let mask = params.behind_edges.apply(
        &frame.depth.pixels,
        &object.mask.pixels,
        camera.width as usize,
        (u0, v0, u1, v1),
        params.max_depth,
    );
    let observed = back_project(&frame.depth.pixels, &mask, camera, (v0, v1), params.max_depth);
    if observed.len() < params.min_points {
        return Err(reject(format!(
            "{} of {pixels} mask pixels have a valid depth (0 < z ≤ {} m), expected at least {}",
            observed.len(),
            params.max_depth,
            params.min_points
        )));
    }
    let kept = remove_outliers(thin(observed, params.max_filter_points), &params.outliers);
    if kept.len() < params.min_points {
        return Err(reject(format!(
            "{} points left after outlier removal, expected at least {}",
            kept.len(),
            params.min_points
        )));
    }
    let (mut points, valid_point_count) = sample_fixed(&kept, params.point_count, rng);
    let centroid = centre(&mut points);
    Ok(Prepared {
        obj_id: object.obj_id,
        crop: CropBox::around(u0, v0, u1, v1, params.padding),
        points,
        centroid,
        valid_point_count,
    })
}

impl Prepared {
    /// The Observation header for this object in frame `frame_id`.
    pub fn header(&self, frame_id: u64, camera: &Camera, params: &IngestParams) -> ObservationHeader {
        let mut header = Header::new(frame_id, self.obj_id);
        if self.valid_point_count < self.points.len() {
            header.flags |= flags::POINTS_RESAMPLED;
        }
        ObservationHeader {
            header,
            intrinsics: intrinsics(camera),
            centroid: self.centroid.coords.into(),
            point_scale: 1.0,
            crop: self.crop.corners(),
            image_size: params.image_size,
            patch_grid: params.patch_grid,
            point_count: self.points.len() as u32,
            valid_point_count: self.valid_point_count as u32,
            depth_grid: params.depth_grid,
            depth_span: params.depth_span,
        }
    }

    /// Writes the payload (image ‖ token mask ‖ points ‖ depth ‖ mask) into
    /// `out`, which holds exactly `header(..).payload_len()` values.
    pub fn write_payload(&self, frame: &RgbdFrame, object: &ObjectMask, params: &IngestParams, out: &mut [f32]) {
        let (s, p, g) = (params.image_size as usize, params.patch_grid as usize, params.depth_grid as usize);
        let (image, rest) = out.split_at_mut(3 * s * s);
        let (token_mask, rest) = rest.split_at_mut(p * p);
        let (points, rest) = rest.split_at_mut(3 * self.points.len());
        let (depth, mask) = rest.split_at_mut(g * g);
        write_depth_and_mask(
            &frame.depth.pixels,
            &object.mask.pixels,
            frame.depth.width,
            frame.depth.height,
            &self.crop.scaled(f64::from(params.depth_span)),
            g,
            params.max_depth,
            depth,
            mask,
        );
        if params.rgb {
            write_crop(
                &frame.rgb.pixels,
                frame.rgb.width,
                frame.rgb.height,
                &self.crop,
                s,
                &params.normalisation,
                image,
            );
            write_token_mask(&object.mask.pixels, object.mask.width, &self.crop, p, token_mask);
        } else {
            // The normalised mean colour, and no token may be attended to.
            image.fill(0.0);
            token_mask.fill(0.0);
        }
        for (out, point) in points.chunks_exact_mut(3).zip(&self.points) {
            out.copy_from_slice(point.coords.as_slice());
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    proptest! {
        /// The row-by-row scan finds the box and count of the definition:
        /// the extremes of the mask's pixels and how many there are.
        #[test]
        fn the_mask_box_holds_exactly_the_mask_pixels(
            (width, pixels) in (1u32..40).prop_flat_map(|w| (Just(w), proptest::collection::vec(proptest::bool::weighted(0.1), (w as usize)..(w as usize * 30)))),
        ) {
            let height = pixels.len() as u32 / width;
            let pixels = pixels[..(width * height) as usize].to_vec();
            let inside: Vec<(u32, u32)> =
                (0..width * height).filter(|&i| pixels[i as usize]).map(|i| (i % width, i / width)).collect();
            let expected = inside.first().map(|_| {
                let (us, vs): (Vec<u32>, Vec<u32>) = inside.iter().copied().unzip();
                (*us.iter().min().unwrap(), *vs.iter().min().unwrap(), *us.iter().max().unwrap(), *vs.iter().max().unwrap())
            });
            let mask = Raster { width, height, pixels };
            prop_assert_eq!(mask_box(&mask), (expected, inside.len()));
        }
    }
}
