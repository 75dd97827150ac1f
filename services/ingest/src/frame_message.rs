//! Frames as Frame messages and back: what a frame source publishes and
//! ingest (or a detector) reads. Masks travel as their bounding box and the
//! mask inside it.

use poseflow_contracts::{DETECTION_LEN, FrameHeader, Header, MessageHeader};
use poseflow_scene::bop::Raster;

use crate::observe::{camera, intrinsics, mask_box};
use crate::sources::LoadedFrame;
use crate::{IngestError, ObjectMask, RgbdFrame};

/// A frame ready to publish: its header and each mask's box `(x, y, w, h)`.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameLayout {
    pub header: FrameHeader,
    boxes: Vec<[u32; 4]>,
}

impl FrameLayout {
    /// The header of `loaded` as a Frame message. An empty mask is sent as
    /// a 1×1 box holding 0, so the receiver sees (and reports) it.
    pub fn of(loaded: &LoadedFrame) -> Self {
        let camera = &loaded.frame.camera;
        let boxes: Vec<[u32; 4]> = loaded
            .objects
            .iter()
            .map(|o| mask_box(&o.mask).0.map_or([0, 0, 1, 1], |(u0, v0, u1, v1)| [u0, v0, u1 - u0 + 1, v1 - v0 + 1]))
            .collect();
        let mut header = Header::new(loaded.frame.frame_id, 0);
        match loaded.captured_ns {
            Some(ns) => header.stamps.ns[poseflow_contracts::StampSlot::Source as usize] = ns,
            None => header.stamps.stamp(poseflow_contracts::StampSlot::Source),
        }
        let header = FrameHeader {
            header,
            intrinsics: intrinsics(camera),
            scene_id: loaded.scene_id,
            image_id: loaded.image_id,
            detection_count: boxes.len() as u32,
            mask_len: boxes.iter().map(|b| b[2] * b[3]).sum(),
        };
        Self { header, boxes }
    }

    pub fn payload_len(&self) -> usize {
        self.header.payload_len().expect("a checked frame fits the Frame contract")
    }

    /// Writes the payload of `loaded` into `out` (`payload_len()` values).
    pub fn write(&self, loaded: &LoadedFrame, out: &mut [f32]) {
        let frame = &loaded.frame;
        let pixels = frame.rgb.pixels.len();
        let (rgb, rest) = out.split_at_mut(3 * pixels);
        let (depth, rest) = rest.split_at_mut(pixels);
        let (records, masks) = rest.split_at_mut(self.boxes.len() * DETECTION_LEN);
        for (out, pixel) in rgb.chunks_exact_mut(3).zip(&frame.rgb.pixels) {
            out.copy_from_slice(&pixel.map(f32::from));
        }
        depth.copy_from_slice(&frame.depth.pixels);
        let width = frame.camera.width as usize;
        let mut offset = 0;
        for ((record, object), &[x, y, w, h]) in
            records.chunks_exact_mut(DETECTION_LEN).zip(&loaded.objects).zip(&self.boxes)
        {
            let values = [object.obj_id, object.instance as u32, 1, x, y, w, h, offset as u32];
            record.copy_from_slice(&values.map(|v| v as f32));
            for row in 0..h as usize {
                let start = (y as usize + row) * width + x as usize;
                let line = &object.mask.pixels[start..start + w as usize];
                for (out, &inside) in masks[offset..offset + w as usize].iter_mut().zip(line) {
                    *out = if inside { 1.0 } else { 0.0 };
                }
                offset += w as usize;
            }
        }
    }
}

/// `loaded` as a Frame message: its header and payload.
pub fn frame_message(loaded: &LoadedFrame) -> (FrameHeader, Vec<f32>) {
    let layout = FrameLayout::of(loaded);
    let mut payload = vec![0.0; layout.payload_len()];
    layout.write(loaded, &mut payload);
    (layout.header, payload)
}

/// The frame and object masks of a Frame message (checked against its
/// contract). Colours are rounded and clamped to 0–255; non-finite or
/// negative depths become 0 (no measurement).
pub fn read_frame(header: &FrameHeader, payload: &[f32]) -> Result<(RgbdFrame, Vec<ObjectMask>), IngestError> {
    let label = format!("frame {} (scene {} image {})", header.header.frame_id, header.scene_id, header.image_id);
    let view =
        header.view(payload).map_err(|err| IngestError::Frame { frame: label.clone(), detail: err.to_string() })?;
    let camera = camera(&header.intrinsics);
    let rgb = view.rgb.chunks_exact(3).map(|c| [colour(c[0]), colour(c[1]), colour(c[2])]).collect();
    let depth = view.depth.iter().map(|&z| if z.is_finite() && z > 0.0 { z } else { 0.0 }).collect();
    let width = camera.width as usize;
    let objects = (0..view.detection_count())
        .map(|k| {
            let detection = view.detection(k, header);
            let [x, y, w, h] = detection.bbox.map(|v| v as usize);
            let mut mask = vec![false; width * camera.height as usize];
            for (row, values) in detection.mask.chunks_exact(w).enumerate().take(h) {
                for (col, &value) in values.iter().enumerate() {
                    mask[(y + row) * width + x + col] = value > 0.5;
                }
            }
            let mask = Raster { width: camera.width, height: camera.height, pixels: mask };
            ObjectMask { obj_id: detection.obj_id, instance: detection.instance as usize, mask }
        })
        .collect();
    let frame = RgbdFrame {
        frame_id: header.header.frame_id,
        label,
        camera,
        rgb: Raster { width: camera.width, height: camera.height, pixels: rgb },
        depth: Raster { width: camera.width, height: camera.height, pixels: depth },
    };
    Ok((frame, objects))
}

/// A colour channel of a Frame as a byte: rounded half up, clamped; NaN is
/// 0. Not `f32::round`: a libm call per channel cost more than the rest of
/// reading the frame.
fn colour(value: f32) -> u8 {
    (value + 0.5).clamp(0.0, 255.0) as u8
}

#[cfg(test)]
mod tests {
    use super::*;
    use poseflow_scene::Camera;

    #[test]
    fn colours_round_half_up_and_clamp() {
        let cases = [(0.49, 0), (0.5, 1), (127.0, 127), (254.5, 255), (255.4, 255), (300.0, 255), (-3.0, 0)];
        for (value, byte) in cases {
            assert_eq!(colour(value), byte, "{value}");
        }
        assert_eq!(colour(f32::NAN), 0);
    }

    #[test]
    fn frames_survive_the_message_round_trip() {
        let camera = Camera { fx: 500.0, fy: 500.0, cx: 3.5, cy: 2.5, width: 8, height: 6 };
        let mut mask = vec![false; 48];
        for i in [9, 10, 17, 27] {
            mask[i] = true;
        }
        let loaded = LoadedFrame {
            frame: RgbdFrame {
                frame_id: 7,
                label: "test".into(),
                camera,
                rgb: Raster { width: 8, height: 6, pixels: (0..48).map(|i| [i as u8, 255 - i as u8, 3]).collect() },
                depth: Raster { width: 8, height: 6, pixels: (0..48).map(|i| i as f32 * 0.01).collect() },
            },
            objects: vec![
                ObjectMask { obj_id: 5, instance: 0, mask: Raster { width: 8, height: 6, pixels: mask.clone() } },
                ObjectMask { obj_id: 9, instance: 1, mask: Raster { width: 8, height: 6, pixels: vec![false; 48] } },
            ],
            skipped: Vec::new(),
            scene_id: 3,
            image_id: 11,
            captured_ns: None,
        };
        let layout = FrameLayout::of(&loaded);
        assert_eq!(layout.header.mask_len, 3 * 3 + 1);
        let mut payload = vec![f32::NAN; layout.payload_len()];
        layout.write(&loaded, &mut payload);
        let (frame, objects) = read_frame(&layout.header, &payload).unwrap();
        assert_eq!(
            (frame.frame_id, frame.camera, &frame.rgb, &frame.depth),
            (7, camera, &loaded.frame.rgb, &loaded.frame.depth)
        );
        assert_eq!(objects.len(), 2);
        assert_eq!((objects[0].obj_id, objects[0].instance, &objects[0].mask.pixels), (5, 0, &mask));
        assert!(objects[1].mask.pixels.iter().all(|&inside| !inside));

        // A camera driver sending NaN intrinsics: the frame reads, and the
        // check names the values.
        let mut broken = layout.header;
        broken.intrinsics.fx = f32::NAN;
        let (frame, _) = read_frame(&broken, &payload).unwrap();
        let err = crate::check_frame(&frame).unwrap_err().to_string();
        assert!(
            err.contains("frame 7 (scene 3 image 11)") && err.contains("NaN") && err.contains("fx, fy > 0"),
            "{err}"
        );
    }
}
