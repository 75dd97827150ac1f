//! Camera → detector → ingest: one RGB-D image with the object masks to
//! observe in it.
//!
//! A frame source (dataset reader, renderer, camera driver) publishes
//! Frames, with ground-truth or file masks or none; a detector (Mask R-CNN,
//! CNOS, SAM, …) is a stage that takes Frames and publishes them again with
//! its own detections; ingest turns each detection into an Observation.

use iceoryx2_bb_derive_macros::ZeroCopySend;
use iceoryx2_bb_elementary_traits::zero_copy_send::ZeroCopySend;

use crate::message::{MessageHeader, bounded, header_accessors, limits, sections};
use crate::{CameraIntrinsics, ContractError, Header};

/// `f32` values of one detection record: `obj_id, instance, score, x, y,
/// width, height, mask_offset` (integers stored exactly as `f32`).
pub const DETECTION_LEN: usize = 8;

/// User header of a Frame (120 bytes, alignment 8).
///
/// | offset | size | field           | type     | meaning |
/// |-------:|-----:|-----------------|----------|---------|
/// | 0      | 80   | header          | [`Header`] | frame id; `object_id` unused (0) |
/// | 80     | 24   | intrinsics      | [`CameraIntrinsics`] | W = width, H = height |
/// | 104    | 4    | scene_id        | u32      | dataset scene (0 for a live camera) |
/// | 108    | 4    | image_id        | u32      | dataset image id (or a camera's frame counter) |
/// | 112    | 4    | detection_count | u32      | M |
/// | 116    | 4    | mask_len        | u32      | L = Σ widthₖ·heightₖ |
///
/// Payload (`f32`): `rgb` 3·W·H (row-major, RGB interleaved, 0–255) ‖
/// `depth` W·H (metres along the optical axis, 0 = no measurement) ‖
/// `detections` M·[`DETECTION_LEN`] ‖ `masks` L (1 inside, 0 outside). The
/// mask of detection k covers its box `[x, x + width) × [y, y + height)`
/// row-major and starts at `mask_offset` in `masks`; offsets follow each
/// other without gaps.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Default, ZeroCopySend)]
#[type_name("poseflow/Frame/v1")]
pub struct FrameHeader {
    pub header: Header,
    pub intrinsics: CameraIntrinsics,
    pub scene_id: u32,
    pub image_id: u32,
    pub detection_count: u32,
    pub mask_len: u32,
}

/// One detection of a [`FrameView`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Detection<'a> {
    pub obj_id: u32,
    pub instance: u32,
    pub score: f32,
    /// `x, y, width, height` in pixels.
    pub bbox: [u32; 4],
    /// `width · height` values, row-major over the box.
    pub mask: &'a [f32],
}

/// The sections of a Frame payload.
#[derive(Debug, Clone, Copy)]
pub struct FrameView<'a> {
    pub rgb: &'a [f32],
    pub depth: &'a [f32],
    detections: &'a [f32],
    masks: &'a [f32],
}

impl FrameHeader {
    fn section_lengths(&self) -> Result<[usize; 4], ContractError> {
        let w = bounded(Self::NAME, "intrinsics.width", self.intrinsics.width, 1, limits::MAX_FRAME_SIDE, "1..=8192")?;
        let h =
            bounded(Self::NAME, "intrinsics.height", self.intrinsics.height, 1, limits::MAX_FRAME_SIDE, "1..=8192")?;
        let m = bounded(Self::NAME, "detection_count", self.detection_count, 0, limits::MAX_DETECTIONS, "0..=256")?;
        let max_mask = (m * w * h).min(u32::MAX as usize) as u32;
        let l = bounded(Self::NAME, "mask_len", self.mask_len, 0, max_mask, "at most detection_count · W · H")?;
        Ok([3 * w * h, w * h, m * DETECTION_LEN, l])
    }

    /// Splits a payload that [`MessageHeader::check_payload`] accepts and
    /// checks every detection record against the image and the mask section.
    pub fn view<'a>(&self, payload: &'a [f32]) -> Result<FrameView<'a>, ContractError> {
        self.check_payload(payload)?;
        let [rgb, depth, detections, masks] = sections(payload, self.section_lengths()?);
        let view = FrameView { rgb, depth, detections, masks };
        let mut expected_offset = 0usize;
        for k in 0..self.detection_count as usize {
            let d = view.detection_unchecked(k, self)?;
            let offset = view.detections[k * DETECTION_LEN + 7] as usize;
            if offset != expected_offset {
                return Err(ContractError::FieldOutOfRange {
                    message: Self::NAME,
                    field: "detections.mask_offset",
                    value: offset as u64,
                    expected: "the sum of the previous detections' box areas",
                });
            }
            expected_offset += d.mask.len();
        }
        if expected_offset != masks.len() {
            return Err(ContractError::FieldOutOfRange {
                message: Self::NAME,
                field: "mask_len",
                value: u64::from(self.mask_len),
                expected: "the sum of the detections' box areas",
            });
        }
        Ok(view)
    }
}

/// An `f32` that must hold a non-negative integer up to `max`.
fn integer(value: f32, field: &'static str, max: u32, expected: &'static str) -> Result<u32, ContractError> {
    if value.is_finite() && value >= 0.0 && value.fract() == 0.0 && value <= max as f32 {
        Ok(value as u32)
    } else {
        Err(ContractError::FieldOutOfRange {
            message: FrameHeader::NAME,
            field,
            value: if value.is_finite() && value >= 0.0 { value as u64 } else { u64::MAX },
            expected,
        })
    }
}

impl<'a> FrameView<'a> {
    /// Number of detections.
    pub fn detection_count(&self) -> usize {
        self.detections.len() / DETECTION_LEN
    }

    /// Detection `k` of a view made by [`FrameHeader::view`] (which checked
    /// every record).
    pub fn detection(&self, k: usize, header: &FrameHeader) -> Detection<'a> {
        self.detection_unchecked(k, header).expect("FrameHeader::view checked every detection")
    }

    fn detection_unchecked(&self, k: usize, header: &FrameHeader) -> Result<Detection<'a>, ContractError> {
        let r = &self.detections[k * DETECTION_LEN..(k + 1) * DETECTION_LEN];
        let (w, h) = (header.intrinsics.width, header.intrinsics.height);
        let obj_id = integer(r[0], "detections.obj_id", u32::MAX, "a non-negative integer")?;
        let instance = integer(r[1], "detections.instance", limits::MAX_DETECTIONS, "an integer 0..=256")?;
        if !r[2].is_finite() {
            return Err(ContractError::FieldOutOfRange {
                message: FrameHeader::NAME,
                field: "detections.score",
                value: u64::MAX,
                expected: "a finite number",
            });
        }
        let x = integer(r[3], "detections.x", w - 1, "a column inside the image")?;
        let y = integer(r[4], "detections.y", h - 1, "a row inside the image")?;
        let bw = integer(r[5], "detections.width", w - x, "1..=W − x")?;
        let bh = integer(r[6], "detections.height", h - y, "1..=H − y")?;
        let offset = integer(r[7], "detections.mask_offset", header.mask_len, "an offset inside the mask section")?;
        let area = bw as usize * bh as usize;
        let mask = self.masks.get(offset as usize..offset as usize + area).filter(|_| area > 0).ok_or(
            ContractError::FieldOutOfRange {
                message: FrameHeader::NAME,
                field: "detections.width",
                value: u64::from(bw),
                expected: "a non-empty box whose mask fits in the mask section",
            },
        )?;
        Ok(Detection { obj_id, instance, score: r[2], bbox: [x, y, bw, bh], mask })
    }
}

impl MessageHeader for FrameHeader {
    const NAME: &'static str = "Frame";

    header_accessors!();

    fn payload_len(&self) -> Result<usize, ContractError> {
        Ok(self.section_lengths()?.iter().sum())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame(detections: &[[f32; 7]]) -> (FrameHeader, Vec<f32>) {
        let (w, h) = (4u32, 3u32);
        let mut header = FrameHeader {
            intrinsics: CameraIntrinsics { fx: 1.0, fy: 1.0, cx: 2.0, cy: 1.0, width: w, height: h },
            detection_count: detections.len() as u32,
            ..FrameHeader::default()
        };
        let mut payload = vec![0.5f32; 4 * (w * h) as usize];
        let mut masks = Vec::new();
        for d in detections {
            payload.extend_from_slice(d);
            payload.push(masks.len() as f32);
            masks.extend(std::iter::repeat_n(1.0, (d[5] * d[6]) as usize));
        }
        header.mask_len = masks.len() as u32;
        payload.extend(masks);
        (header, payload)
    }

    #[test]
    fn detections_read_back_with_their_masks() {
        let (header, payload) = frame(&[[1.0, 0.0, 0.9, 1.0, 1.0, 2.0, 2.0], [10.0, 1.0, 0.5, 0.0, 0.0, 4.0, 3.0]]);
        let view = header.view(&payload).unwrap();
        assert_eq!(view.detection_count(), 2);
        let second = view.detection(1, &header);
        assert_eq!((second.obj_id, second.instance, second.bbox, second.mask.len()), (10, 1, [0, 0, 4, 3], 12));
        assert_eq!(view.rgb.len(), 36);
    }

    #[test]
    fn boxes_outside_the_image_and_bad_offsets_are_rejected() {
        let (header, payload) = frame(&[[1.0, 0.0, 0.9, 3.0, 0.0, 2.0, 1.0]]);
        let err = header.view(&payload).unwrap_err().to_string();
        assert!(err.contains("detections.width") && err.contains("W − x"), "{err}");
        let (header, mut payload) = frame(&[[1.0, 0.0, 0.9, 0.0, 0.0, 1.0, 1.0], [2.0, 1.0, 0.9, 0.0, 0.0, 1.0, 1.0]]);
        payload[48 + DETECTION_LEN + 7] = 0.0; // second mask said to start where the first does
        let err = header.view(&payload).unwrap_err().to_string();
        assert!(err.contains("mask_offset"), "{err}");
        let (mut header, payload) = frame(&[]);
        header.intrinsics.width = 0;
        assert!(header.view(&payload).unwrap_err().to_string().contains("intrinsics.width"));
    }
}
