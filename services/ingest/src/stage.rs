//! The two stage processes of this crate.
//!
//! `frame-source` ([`FrameSourceStage`]) publishes Frame messages from a
//! BOP dataset or the renderer. Parameters (graph `params` over its
//! `config`, e.g. `config/frame-source.toml`):
//!
//! | key | meaning |
//! |---|---|
//! | `source` | `"bop"` (a dataset directory) or `"synthetic"` (the renderer) |
//! | `dataset`, `split`, `scenes`, `mask_dir`, `targets` | bop: dataset root, split folder (default `test`), scene ids (default all), masks from files instead of the ground truth ([`Masks::Files`]), a BOP19 targets file instead of the dataset's `test_targets_bop19.json` |
//! | `models`, `objects`, `scenes`, `frames_per_scene`, `seed`, `occlusion`, `width`, `height`, `orbit_step_deg` | synthetic: as `poseflow render` |
//! | `rate_hz` | frames per second (read by the runtime; default as fast as the output accepts) |
//! | `preload` | `true`: read (or render) every frame before publishing the first, so a benchmark measures the pipeline rather than PNG decoding or rendering (memory: ~2.5 MB per 640×480 frame) |
//!
//! `ingest` ([`IngestStage`]) turns each detection of a Frame into an
//! Observation; its parameters are [`IngestParams`] (`config/ingest.toml`).

use std::path::PathBuf;

use poseflow_contracts::{FrameHeader, MessageHeader, ObservationHeader, StampSlot, flags};
use poseflow_geometry::sampling::{SeededRng, seeded_rng};
use poseflow_runtime::{Emitter, Input, Source, SourceStep, Transform};
use poseflow_scene::camera_path::CameraPath;
use poseflow_scene::dataset::{RenderSpec, lmo_camera};
use poseflow_scene::scene::{Occlusion, ViewRange};
use poseflow_scene::{DepthNoise, ModelLibrary};
use serde::Deserialize;

use crate::sources::{BopFrames, FrameSource, Masks, PreloadedFrames, SyntheticFrames};
use crate::{FrameLayout, IngestError, IngestParams, check_frame, prepare, read_frame};

#[derive(Debug, Deserialize)]
#[serde(tag = "source", rename_all = "snake_case", deny_unknown_fields)]
enum SourceParams {
    Bop {
        dataset: PathBuf,
        #[serde(default = "default_split")]
        split: String,
        #[serde(default)]
        scenes: Vec<u32>,
        /// Masks from files (`<dir>/<scene:06>/<im:06>_obj<obj:06>.png`)
        /// instead of the ground truth.
        mask_dir: Option<PathBuf>,
        /// A BOP19 targets file instead of the dataset's own.
        targets: Option<PathBuf>,
    },
    Synthetic {
        models: PathBuf,
        #[serde(default)]
        objects: Vec<u32>,
        #[serde(default = "one")]
        scenes: u32,
        #[serde(default = "ten")]
        frames_per_scene: u32,
        #[serde(default)]
        seed: u64,
        #[serde(default)]
        occlusion: OcclusionParam,
        #[serde(default = "default_width")]
        width: u32,
        #[serde(default = "default_height")]
        height: u32,
        /// Degrees of azimuth per image of an orbiting camera (a video);
        /// absent: independent random views.
        orbit_step_deg: Option<f64>,
    },
}

#[derive(Debug, Default, Deserialize)]
#[serde(rename_all = "snake_case")]
enum OcclusionParam {
    Low,
    #[default]
    Medium,
    High,
}

fn default_split() -> String {
    "test".into()
}
fn one() -> u32 {
    1
}
fn ten() -> u32 {
    10
}
fn default_width() -> u32 {
    640
}
fn default_height() -> u32 {
    480
}

fn params_error(err: impl std::fmt::Display) -> IngestError {
    IngestError::Params { key: "source".into(), detail: err.to_string() }
}

/// Builds a frame source from the `frame-source` parameters (module docs).
pub fn frame_source(value: &serde_json::Value) -> Result<Box<dyn FrameSource>, IngestError> {
    let mut value = value.clone();
    // The runtime paces sources by `rate_hz`; `preload` wraps any source;
    // the rest chooses and configures the source.
    let mut preload = serde_json::Value::Bool(false);
    if let Some(table) = value.as_object_mut() {
        table.remove("rate_hz");
        preload = table.remove("preload").unwrap_or(preload);
    }
    let preload = preload.as_bool().ok_or_else(|| IngestError::Params {
        key: "preload".into(),
        detail: format!("{preload}: expected true or false"),
    })?;
    let source = source_from(value)?;
    Ok(if preload { Box::new(PreloadedFrames::read_all(source)) } else { source })
}

fn source_from(value: serde_json::Value) -> Result<Box<dyn FrameSource>, IngestError> {
    Ok(match serde_json::from_value(value).map_err(params_error)? {
        SourceParams::Bop { dataset, split, scenes, mask_dir, targets } => {
            let masks = mask_dir.map_or(Masks::GroundTruth, Masks::Files);
            Box::new(BopFrames::open(&dataset, &split, &scenes, targets.as_deref(), masks)?)
        }
        SourceParams::Synthetic {
            models,
            objects,
            scenes,
            frames_per_scene,
            seed,
            occlusion,
            width,
            height,
            orbit_step_deg,
        } => {
            let library = ModelLibrary::load(&models, &objects)?;
            let spec = RenderSpec {
                split: String::new(),
                first_scene: 0,
                scenes,
                frames_per_scene,
                seed,
                occlusion: match occlusion {
                    OcclusionParam::Low => Occlusion::Low,
                    OcclusionParam::Medium => Occlusion::Medium,
                    OcclusionParam::High => Occlusion::High,
                },
                camera: lmo_camera(width, height),
                views: ViewRange::default(),
                path: orbit_step_deg
                    .map_or(CameraPath::Random, |step_deg| CameraPath::Orbit { step_deg, events: Default::default() }),
                depth_noise: Some(DepthNoise::default()),
                rgb_noise: 2.0,
                sensor: None,
                style: Default::default(),
                condition: None,
            };
            Box::new(SyntheticFrames::new(library, spec))
        }
    })
}

/// Publishes every frame of a [`FrameSource`] as a Frame message.
#[derive(Debug)]
pub struct FrameSourceStage {
    frames: Box<dyn FrameSource>,
    rejected: u64,
    /// The scene of the previous frame, to flag the first of each sequence.
    scene: Option<u32>,
}

impl FrameSourceStage {
    pub fn new(frames: Box<dyn FrameSource>) -> Self {
        Self { frames, rejected: 0, scene: None }
    }
}

impl Source for FrameSourceStage {
    type Out = FrameHeader;
    type Error = IngestError;
    const SLOT: Option<StampSlot> = Some(StampSlot::Source);

    fn next(&mut self, output: &mut dyn Emitter<FrameHeader>) -> Result<SourceStep, IngestError> {
        if !self.frames.wait_ready() {
            return Ok(SourceStep::Idle);
        }
        let Some(loaded) = self.frames.next_frame() else {
            return Ok(SourceStep::Finished);
        };
        // A frame that cannot be read is one error (its objects are unknown).
        let loaded = loaded?;
        check_frame(&loaded.frame)?;
        let _span = tracing::info_span!("frame", id = loaded.frame.frame_id).entered();
        for err in &loaded.skipped {
            tracing::warn!(%err, "object skipped");
        }
        self.rejected += loaded.skipped.len() as u64;
        let mut layout = FrameLayout::of(&loaded);
        if self.scene.replace(loaded.scene_id) != Some(loaded.scene_id) {
            layout.header.header.flags |= flags::SEQUENCE_START;
        }
        output.emit(layout.header, layout.payload_len(), &mut |out| layout.write(&loaded, out))?;
        Ok(SourceStep::Continue)
    }

    fn take_rejected(&mut self) -> u64 {
        std::mem::take(&mut self.rejected) + self.frames.take_dropped()
    }
}

/// Frames in, one Observation per detection out.
#[derive(Debug)]
pub struct IngestStage {
    params: IngestParams,
    rejected: u64,
}

impl IngestStage {
    pub fn new(params: IngestParams) -> Self {
        Self { params, rejected: 0 }
    }

    /// Draws for resampling small point sets, seeded by the frame so a frame
    /// gives the same observation however the stream was started.
    fn rng(frame_id: u64) -> SeededRng {
        seeded_rng(frame_id.wrapping_mul(0x9E37_79B9_7F4A_7C15))
    }
}

impl Transform for IngestStage {
    type In = FrameHeader;
    type Out = ObservationHeader;
    type Error = IngestError;
    const SLOT: Option<StampSlot> = Some(StampSlot::Ingest);

    fn process(
        &mut self,
        input: Input<'_, FrameHeader>,
        output: &mut dyn Emitter<ObservationHeader>,
    ) -> Result<(), IngestError> {
        let (frame, objects) = read_frame(input.header, input.payload)?;
        let _span = tracing::info_span!("frame", id = frame.frame_id).entered();
        // A frame whose intrinsics are unusable rejects all of its objects.
        if let Err(err) = check_frame(&frame) {
            self.rejected += objects.len() as u64;
            return Err(err);
        }
        let mut rng = Self::rng(frame.frame_id);
        let mut observed = Vec::with_capacity(objects.len());
        for object in &objects {
            match prepare(&frame, object, &self.params, &mut rng) {
                Ok(prepared) => {
                    let mut header = prepared.header(frame.frame_id, &frame.camera, &self.params);
                    header.header.stamps = input.header.header.stamps;
                    header.header.flags |= input.header.header.flags & !flags::MORE_IN_FRAME;
                    // Validated parameters always give a valid header; a
                    // failure here names the frame rather than a parameter.
                    let len = header
                        .payload_len()
                        .map_err(|err| IngestError::Frame { frame: frame.label.clone(), detail: err.to_string() })?;
                    observed.push((header, len, prepared, object));
                }
                Err(err) => {
                    tracing::warn!(%err, "object skipped");
                    self.rejected += 1;
                }
            }
        }
        // Sent together once all are ready, each but the last marked: the
        // inference stage encodes them as one batch.
        let count = observed.len();
        for (header, _, _, _) in observed.iter_mut().take(count.saturating_sub(1)) {
            header.header.flags |= flags::MORE_IN_FRAME;
        }
        for (header, len, prepared, object) in observed {
            output.emit(header, len, &mut |out| prepared.write_payload(&frame, object, &self.params, out))?;
        }
        Ok(())
    }

    fn take_rejected(&mut self) -> u64 {
        std::mem::take(&mut self.rejected)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bad_source_parameters_are_named() {
        let err = frame_source(&serde_json::json!({ "source": "camera" })).unwrap_err().to_string();
        assert!(err.contains("param `source`") && err.contains("camera") && err.contains("bop"), "{err}");
        let err =
            frame_source(&serde_json::json!({ "source": "bop", "dataset": "/nonexistent" })).unwrap_err().to_string();
        assert!(err.contains("/nonexistent/test"), "{err}");
        let err = frame_source(&serde_json::json!({ "source": "bop", "datset": "x" })).unwrap_err().to_string();
        assert!(err.contains("datset"), "{err}");
        let err = frame_source(&serde_json::json!({ "source": "bop", "preload": "yes" })).unwrap_err().to_string();
        assert!(err.contains("preload") && err.contains("\"yes\"") && err.contains("true or false"), "{err}");
    }

    #[test]
    fn the_first_frame_of_each_scene_starts_a_sequence() {
        struct Flags(Vec<u32>);
        impl Emitter<FrameHeader> for Flags {
            fn emit(
                &mut self,
                header: FrameHeader,
                len: usize,
                fill: &mut dyn FnMut(&mut [f32]),
            ) -> Result<(), poseflow_runtime::EmitError> {
                fill(&mut vec![0.0; len]);
                self.0.push(header.header.flags);
                Ok(())
            }
        }
        let models = concat!(env!("CARGO_MANIFEST_DIR"), "/../../objects/lmo");
        let params = serde_json::json!({ "source": "synthetic", "models": models, "objects": [1], "scenes": 2,
            "frames_per_scene": 2, "width": 64, "height": 48, "orbit_step_deg": 5.0 });
        let mut stage = FrameSourceStage::new(frame_source(&params).expect("valid params"));
        let mut emitted = Flags(Vec::new());
        while let SourceStep::Continue = stage.next(&mut emitted).expect("rendered") {}
        let starts: Vec<bool> = emitted.0.iter().map(|f| f & flags::SEQUENCE_START != 0).collect();
        assert_eq!(starts, [true, false, true, false]);
    }

    #[test]
    fn preloaded_frames_are_the_source_frames_in_order() {
        let models = concat!(env!("CARGO_MANIFEST_DIR"), "/../../objects/lmo");
        let params = |preload: bool| {
            serde_json::json!({ "source": "synthetic", "models": models, "objects": [1], "frames_per_scene": 3,
                "width": 64, "height": 48, "orbit_step_deg": 5.0, "preload": preload, "rate_hz": 10.0 })
        };
        let drain = |mut source: Box<dyn FrameSource>| -> Vec<(u64, Vec<[u8; 3]>, Vec<f32>)> {
            std::iter::from_fn(|| source.next_frame())
                .map(|f| f.expect("rendered"))
                .map(|f| (f.frame.frame_id, f.frame.rgb.pixels, f.frame.depth.pixels))
                .collect()
        };
        let live = drain(frame_source(&params(false)).expect("valid params"));
        let preloaded = drain(frame_source(&params(true)).expect("valid params"));
        assert_eq!(live.len(), 3);
        assert_eq!(live.iter().map(|f| f.0).collect::<Vec<_>>(), [0, 1, 2]);
        assert!(live == preloaded, "a preloaded source hands out the live source's frames");
    }
}
