//! The ingest stage as a graph source: frames from a configured source,
//! one Observation per object, written straight into the output buffer.
//!
//! Parameters (graph file `params`, merged over its `config` file, e.g.
//! `config/ingest.toml`):
//!
//! | key | meaning |
//! |---|---|
//! | `source` | `"bop"` (a dataset directory) or `"synthetic"` (the renderer) |
//! | `dataset`, `split`, `scenes` | bop: dataset root, split folder (default `test`), scene ids (default all) |
//! | `models`, `objects`, `scenes`, `frames_per_scene`, `seed`, `occlusion`, `width`, `height` | synthetic: as `poseflow render` |
//! | `observation` | crop, token and point parameters ([`IngestParams`]) |
//! | `rate_hz` | frames per second (read by the runtime; default as fast as the output accepts) |

use std::path::PathBuf;

use poseflow_contracts::{MessageHeader, ObservationHeader, Stage};
use poseflow_geometry::sampling::{SeededRng, seeded_rng};
use poseflow_runtime::{Emitter, Source, SourceStep};
use poseflow_scene::dataset::{RenderSpec, lmo_camera};
use poseflow_scene::scene::{Occlusion, ViewRange};
use poseflow_scene::{DepthNoise, ModelLibrary};
use serde::Deserialize;

use crate::sources::{BopFrames, FrameSource, SyntheticFrames};
use crate::{IngestError, IngestParams, check_frame, prepare};

#[derive(Debug, Deserialize)]
#[serde(tag = "source", rename_all = "snake_case", deny_unknown_fields)]
enum SourceParams {
    Bop {
        dataset: PathBuf,
        #[serde(default = "default_split")]
        split: String,
        #[serde(default)]
        scenes: Vec<u32>,
        #[serde(default)]
        observation: serde_json::Value,
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
        #[serde(default)]
        observation: serde_json::Value,
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

/// The stage: a frame source and the observation parameters.
pub struct IngestSource {
    frames: Box<dyn FrameSource>,
    params: IngestParams,
    /// Draws for resampling small point sets; reseeded per frame so a frame
    /// gives the same observation however the stream was started.
    rng_seed: u64,
    rejected: u64,
    observations: u64,
}

impl std::fmt::Debug for IngestSource {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("IngestSource").field("params", &self.params).field("rejected", &self.rejected).finish()
    }
}

fn params_error(err: impl std::fmt::Display) -> IngestError {
    IngestError::Params { key: "source".into(), detail: err.to_string() }
}

impl IngestSource {
    pub fn new(frames: Box<dyn FrameSource>, params: IngestParams) -> Self {
        Self { frames, params, rng_seed: 0, rejected: 0, observations: 0 }
    }

    /// Builds the stage from its parameters (see the module docs).
    pub fn from_params(value: &serde_json::Value) -> Result<Self, IngestError> {
        let mut value = value.clone();
        // The runtime paces sources by `rate_hz`; the rest is ours.
        if let Some(table) = value.as_object_mut() {
            table.remove("rate_hz");
        }
        let source: SourceParams = serde_json::from_value(value).map_err(params_error)?;
        let (frames, observation): (Box<dyn FrameSource>, _) = match source {
            SourceParams::Bop { dataset, split, scenes, observation, .. } => {
                (Box::new(BopFrames::open(&dataset, &split, &scenes)?), observation)
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
                observation,
                ..
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
                    depth_noise: Some(DepthNoise::default()),
                    rgb_noise: 2.0,
                };
                (Box::new(SyntheticFrames::new(library, spec)), observation)
            }
        };
        let params =
            if observation.is_null() { IngestParams::default() } else { IngestParams::from_json(&observation)? };
        params.validate()?;
        Ok(Self::new(frames, params))
    }

    fn rng(&self, frame_id: u64) -> SeededRng {
        seeded_rng(self.rng_seed ^ frame_id.wrapping_mul(0x9E37_79B9_7F4A_7C15))
    }
}

impl Source for IngestSource {
    type Out = ObservationHeader;
    type Error = IngestError;
    const SLOT: Option<Stage> = Some(Stage::Ingest);

    fn next(&mut self, output: &mut dyn Emitter<ObservationHeader>) -> Result<SourceStep, IngestError> {
        let Some(loaded) = self.frames.next_frame() else {
            tracing::info!(observations = self.observations, rejected = self.rejected, "frame source finished");
            return Ok(SourceStep::Finished);
        };
        let loaded = loaded?;
        let frame = &loaded.frame;
        let _span = tracing::info_span!("frame", id = frame.frame_id).entered();
        for err in &loaded.skipped {
            tracing::warn!(%err, "object skipped");
        }
        self.rejected += loaded.skipped.len() as u64;
        // A frame that cannot be read at all is one error (its objects are
        // unknown); otherwise every object not observed counts once.
        if let Err(err) = check_frame(frame) {
            tracing::warn!(%err, objects = loaded.objects.len(), "frame skipped");
            self.rejected += loaded.objects.len() as u64;
            return Ok(SourceStep::Continue);
        }
        let mut rng = self.rng(frame.frame_id);
        for object in &loaded.objects {
            match prepare(frame, object, &self.params, &mut rng) {
                Ok(prepared) => {
                    let mut header = prepared.header(frame.frame_id, &frame.camera, &self.params);
                    header.header.stamps.stamp(Stage::Source);
                    let len = header.payload_len().map_err(params_error)?;
                    output.emit(header, len, &mut |out| prepared.write_payload(frame, object, &self.params, out))?;
                    self.observations += 1;
                }
                Err(err) => {
                    tracing::warn!(%err, "object skipped");
                    self.rejected += 1;
                }
            }
        }
        Ok(SourceStep::Continue)
    }

    fn take_rejected(&mut self) -> u64 {
        std::mem::take(&mut self.rejected)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bad_stage_parameters_are_named() {
        let err = IngestSource::from_params(&serde_json::json!({ "source": "camera" })).unwrap_err().to_string();
        assert!(err.contains("param `source`") && err.contains("camera") && err.contains("bop"), "{err}");
        let err = IngestSource::from_params(&serde_json::json!({ "source": "bop", "dataset": "/nonexistent" }))
            .unwrap_err()
            .to_string();
        assert!(err.contains("/nonexistent/test"), "{err}");
    }
}
