//! The two ROS 2 stages.
//!
//! `ros2-bridge` ([`PosePublisher`], a sink of Estimates) publishes each
//! Estimate as `geometry_msgs/msg/PoseWithCovarianceStamped` on
//! `<topic_prefix>/obj_<id:06>/pose` and its kept hypotheses as
//! `geometry_msgs/msg/PoseArray` on `<topic_prefix>/obj_<id:06>/hypotheses`.
//! Its parameters are a [`Connection`] plus:
//!
//! | key | default | meaning |
//! |---|---|---|
//! | `frame_id` | `"camera_color_optical_frame"` | the camera's optical frame (REP 103), the frame of every pose |
//! | `topic_prefix` | `"/poseflow"` | where the topics go |
//! | `publish_lost` | `false` | also publish estimates the tracker flagged `LOST` (skipped ones are counted) |
//!
//! `ros2-camera` ([`CameraStage`]) publishes Frames from a ROS 2 camera;
//! its parameters are a [`Connection`] plus [`CameraParams`].

use std::collections::BTreeMap;

use poseflow_contracts::{EstimateHeader, FrameHeader, StampSlot};
use poseflow_ingest::stage::FrameSourceStage;
use poseflow_runtime::{Emitter, Input, Sink, Source, SourceStep};
use serde::Deserialize;

use crate::Ros2Error;
use crate::camera::{CameraParams, RosCamera};
use crate::msgs::{POSE_ARRAY, POSE_WITH_COVARIANCE_STAMPED};
use crate::poses::{is_lost, pose_messages};
use crate::rmw::check_topic;
use crate::session::{Connection, RosPublisher, RosSession};

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PoseParams {
    #[serde(default = "optical_frame")]
    pub frame_id: String,
    #[serde(default = "prefix")]
    pub topic_prefix: String,
    #[serde(default)]
    pub publish_lost: bool,
}

fn optical_frame() -> String {
    "camera_color_optical_frame".into()
}
fn prefix() -> String {
    "/poseflow".into()
}

/// The topics of object `obj_id`: its pose and its hypotheses.
pub fn object_topics(prefix: &str, obj_id: u32) -> (String, String) {
    let base = format!("{}/obj_{obj_id:06}", prefix.trim_end_matches('/'));
    (format!("{base}/pose"), format!("{base}/hypotheses"))
}

/// Estimates in, ROS 2 poses out.
pub struct PosePublisher {
    params: PoseParams,
    session: RosSession,
    /// Per object id: its pose and hypotheses publishers, made on first use.
    publishers: BTreeMap<u32, (RosPublisher, RosPublisher)>,
    skipped_lost: u64,
}

impl std::fmt::Debug for PosePublisher {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("PosePublisher").field("params", &self.params).finish_non_exhaustive()
    }
}

impl PosePublisher {
    pub fn from_params(params: &serde_json::Value) -> Result<Self, Ros2Error> {
        let mut params = params.clone();
        let connection = Connection::take(&mut params)?;
        let params: PoseParams = serde_json::from_value(params)
            .map_err(|err| Ros2Error::Params { key: "ros2-bridge".into(), detail: err.to_string() })?;
        check_topic(&params.topic_prefix).map_err(|detail| Ros2Error::Params {
            key: "topic_prefix".into(),
            detail: format!("{:?}: {detail}", params.topic_prefix),
        })?;
        if params.frame_id.is_empty() {
            return Err(Ros2Error::Params {
                key: "frame_id".into(),
                detail: "expected the camera's optical frame, e.g. camera_color_optical_frame".into(),
            });
        }
        let session = RosSession::open(&connection, "poseflow")?;
        Ok(Self { params, session, publishers: BTreeMap::new(), skipped_lost: 0 })
    }
}

impl Sink for PosePublisher {
    type In = EstimateHeader;
    type Error = Ros2Error;

    fn consume(&mut self, input: Input<'_, EstimateHeader>) -> Result<(), Ros2Error> {
        let header = input.header;
        let _span = tracing::debug_span!("frame", id = header.header.frame_id).entered();
        if is_lost(header) && !self.params.publish_lost {
            self.skipped_lost += 1;
            tracing::info!(
                object = header.header.object_id,
                skipped = self.skipped_lost,
                "lost estimate not published"
            );
            return Ok(());
        }
        let messages =
            pose_messages(header, input.payload, &self.params.frame_id, poseflow_contracts::stamp_clock_ns())?;
        let obj_id = header.header.object_id;
        if !self.publishers.contains_key(&obj_id) {
            let (pose_topic, hypotheses_topic) = object_topics(&self.params.topic_prefix, obj_id);
            let pose = self.session.publisher(&pose_topic, &POSE_WITH_COVARIANCE_STAMPED)?;
            let hypotheses = self.session.publisher(&hypotheses_topic, &POSE_ARRAY)?;
            tracing::info!(object = obj_id, pose = %pose_topic, hypotheses = %hypotheses_topic, "publishing");
            self.publishers.insert(obj_id, (pose, hypotheses));
        }
        let (pose, hypotheses) = self.publishers.get_mut(&obj_id).expect("inserted above");
        pose.put(messages.pose.encode())?;
        hypotheses.put(messages.hypotheses.encode())?;
        Ok(())
    }

    fn finish(&mut self) -> Result<(), Ros2Error> {
        tracing::info!(objects = self.publishers.len(), skipped_lost = self.skipped_lost, "ROS 2 publishing done");
        Ok(())
    }
}

/// Frames from a ROS 2 camera: the frame source's stage over a
/// [`RosCamera`], stamping nothing itself (a frame's `Source` stamp is its
/// image's ROS stamp).
#[derive(Debug)]
pub struct CameraStage {
    frames: FrameSourceStage,
}

impl CameraStage {
    pub fn from_params(params: &serde_json::Value) -> Result<Self, Ros2Error> {
        let mut params = params.clone();
        let connection = Connection::take(&mut params)?;
        let params = CameraParams::from_json(params)?;
        let camera = RosCamera::open(&connection, &params)?;
        Ok(Self { frames: FrameSourceStage::new(Box::new(camera)) })
    }
}

impl Source for CameraStage {
    type Out = FrameHeader;
    type Error = poseflow_ingest::IngestError;
    const SLOT: Option<StampSlot> = None;

    fn next(&mut self, output: &mut dyn Emitter<FrameHeader>) -> Result<SourceStep, Self::Error> {
        self.frames.next(output)
    }

    fn take_rejected(&mut self) -> u64 {
        self.frames.take_rejected()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn object_topics_carry_the_id() {
        assert_eq!(
            object_topics("/poseflow/", 5),
            ("/poseflow/obj_000005/pose".to_string(), "/poseflow/obj_000005/hypotheses".to_string())
        );
    }

    #[test]
    fn bad_parameters_are_named_before_any_connection() {
        let err = PosePublisher::from_params(&serde_json::json!({ "topic_prefix": "poseflow" })).unwrap_err();
        assert!(err.to_string().contains("topic_prefix") && err.to_string().contains("absolute"), "{err}");
        let err = PosePublisher::from_params(&serde_json::json!({ "frame": "x" })).unwrap_err().to_string();
        assert!(err.contains("frame"), "{err}");
        let err = CameraStage::from_params(&serde_json::json!({ "color_topic": "/a b" })).unwrap_err().to_string();
        assert!(err.contains("color_topic"), "{err}");
        let err = CameraStage::from_params(&serde_json::json!({ "stamp_tolerance_ms": -1.0 })).unwrap_err().to_string();
        assert!(err.contains("stamp_tolerance_ms"), "{err}");
    }
}
