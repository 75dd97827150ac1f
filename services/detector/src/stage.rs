//! The detector as a graph stage: Frame in, the same Frame out with the
//! detector's detections in place of any it came with.

use poseflow_contracts::{DETECTION_LEN, FrameHeader, MessageHeader, StampSlot};
use poseflow_geometry::metrics::Pinhole;
use poseflow_runtime::{Emitter, Input, Transform};

use crate::{DetectedObject, Detector, DetectorError, DetectorParams, ImageView};

#[derive(Debug)]
pub struct DetectorStage {
    detector: Detector,
    /// Regions dropped (too small, unsure, beyond `max_instances`) so far.
    dropped_regions: u64,
}

impl DetectorStage {
    pub fn new(params: DetectorParams) -> Result<Self, DetectorError> {
        Ok(Self { detector: Detector::new(params)?, dropped_regions: 0 })
    }
}

impl Drop for DetectorStage {
    fn drop(&mut self) {
        tracing::info!(dropped_regions = self.dropped_regions, "detector finished");
    }
}

/// The header of `header`'s frame carrying `objects` as its detections.
pub fn frame_with_detections(header: &FrameHeader, objects: &[DetectedObject]) -> FrameHeader {
    FrameHeader {
        detection_count: objects.len() as u32,
        mask_len: objects.iter().map(|o| o.mask.len() as u32).sum(),
        ..*header
    }
}

/// Writes `rgb ‖ depth ‖ records ‖ masks` into `out`.
pub fn write_frame_payload(rgb: &[f32], depth: &[f32], objects: &[DetectedObject], out: &mut [f32]) {
    let (image, rest) = out.split_at_mut(rgb.len());
    image.copy_from_slice(rgb);
    let (depth_out, rest) = rest.split_at_mut(depth.len());
    depth_out.copy_from_slice(depth);
    let (records, masks) = rest.split_at_mut(objects.len() * DETECTION_LEN);
    let mut offset = 0usize;
    for (record, object) in records.chunks_exact_mut(DETECTION_LEN).zip(objects) {
        let [x, y, w, h] = object.bbox;
        record.copy_from_slice(&[
            object.obj_id as f32,
            object.instance as f32,
            object.score,
            x as f32,
            y as f32,
            w as f32,
            h as f32,
            offset as f32,
        ]);
        for (out, &inside) in masks[offset..offset + object.mask.len()].iter_mut().zip(&object.mask) {
            *out = if inside { 1.0 } else { 0.0 };
        }
        offset += object.mask.len();
    }
}

impl Transform for DetectorStage {
    type In = FrameHeader;
    type Out = FrameHeader;
    type Error = DetectorError;
    // No slot of its own: the frame keeps its capture stamp, and ingest's
    // stamp measures source-to-ingest including this stage.
    const SLOT: Option<StampSlot> = None;

    fn process(
        &mut self,
        input: Input<'_, FrameHeader>,
        output: &mut dyn Emitter<FrameHeader>,
    ) -> Result<(), DetectorError> {
        let header = input.header;
        let frame = header.header.frame_id;
        let _span = tracing::info_span!("frame", id = frame).entered();
        let view = header.view(input.payload).map_err(|e| DetectorError::Frame { frame, detail: e.to_string() })?;
        let image = ImageView {
            rgb: view.rgb,
            depth: view.depth,
            width: header.intrinsics.width as usize,
            height: header.intrinsics.height as usize,
            camera: Pinhole {
                fx: f64::from(header.intrinsics.fx),
                fy: f64::from(header.intrinsics.fy),
                cx: f64::from(header.intrinsics.cx),
                cy: f64::from(header.intrinsics.cy),
            },
        };
        let found = self.detector.detect(&image)?;
        self.dropped_regions += found.dropped as u64;
        tracing::debug!(detections = found.objects.len(), dropped = found.dropped, "detected");
        let out_header = frame_with_detections(header, &found.objects);
        let len = out_header.payload_len().map_err(|e| DetectorError::Frame { frame, detail: e.to_string() })?;
        output.emit(out_header, len, &mut |out| write_frame_payload(view.rgb, view.depth, &found.objects, out))?;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use poseflow_contracts::{CameraIntrinsics, Header};

    #[test]
    fn the_written_frame_reads_back_with_its_detections() {
        let header = FrameHeader {
            header: Header::new(7, 0),
            intrinsics: CameraIntrinsics { fx: 1.0, fy: 1.0, cx: 2.0, cy: 1.5, width: 4, height: 3 },
            ..Default::default()
        };
        let rgb: Vec<f32> = (0..36).map(|v| v as f32).collect();
        let depth = vec![0.5; 12];
        let objects = [
            DetectedObject {
                obj_id: 5,
                instance: 0,
                score: 0.75,
                bbox: [1, 0, 2, 2],
                mask: vec![true, false, true, true],
            },
            DetectedObject { obj_id: 9, instance: 1, score: 0.5, bbox: [0, 2, 1, 1], mask: vec![true] },
        ];
        let out_header = frame_with_detections(&header, &objects);
        let mut payload = vec![f32::NAN; out_header.payload_len().unwrap()];
        write_frame_payload(&rgb, &depth, &objects, &mut payload);
        let view = out_header.view(&payload).unwrap();
        assert_eq!((view.rgb, view.depth), (&rgb[..], &depth[..]));
        let first = view.detection(0, &out_header);
        assert_eq!((first.obj_id, first.instance, first.score, first.bbox), (5, 0, 0.75, [1, 0, 2, 2]));
        assert_eq!(first.mask, &[1.0, 0.0, 1.0, 1.0]);
        let second = view.detection(1, &out_header);
        assert_eq!((second.obj_id, second.instance, second.bbox, second.mask), (9, 1, [0, 2, 1, 1], &[1.0][..]));
    }
}
