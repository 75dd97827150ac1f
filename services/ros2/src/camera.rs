//! A ROS 2 camera as a frame source: colour, aligned depth and camera
//! info (and optionally a label image for masks) over Zenoh, paired by
//! stamp ([`crate::pairing`]) and turned into frames exactly as the BOP
//! frame source makes them.
//!
//! Encodings: colour `rgb8` or `bgr8`; depth `16UC1` or `mono16` in
//! millimetres (as RealSense, Azure Kinect and Orbbec drivers publish it)
//! or `32FC1` in metres (ZED); labels `mono8`, `8UC1`, `mono16` or `16UC1`
//! with each pixel the BOP object id seen there (0 = none): one mask per
//! id present. The depth must be registered to the colour image (the
//! drivers' `aligned_depth_to_color` topics) and the images rectified:
//! PoseFlow's camera model is a pinhole without distortion.

use std::sync::{Arc, Condvar, Mutex};
use std::time::Duration;

use poseflow_ingest::sources::{FrameSource, LoadedFrame};
use poseflow_ingest::{IngestError, ObjectMask, RgbdFrame};
use poseflow_scene::Camera;
use poseflow_scene::bop::{MM_PER_M, Raster};
use serde::Deserialize;

use crate::Ros2Error;
use crate::msgs::{CAMERA_INFO, CameraInfo, IMAGE, Image};
use crate::pairing::{Pairing, Stamped};
use crate::session::{Connection, RosSession, RosSubscription};

/// Why a camera message could not become a frame.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum CameraError {
    #[error("{topic}: {detail}")]
    Message { topic: String, detail: String },
}

fn message_error(topic: &str, detail: impl Into<String>) -> CameraError {
    CameraError::Message { topic: topic.to_string(), detail: detail.into() }
}

/// The rows of an image's `data`, checked against its size and `step`.
fn rows<'a>(image: &'a Image<'_>, topic: &str, bytes_per_pixel: usize) -> Result<Vec<&'a [u8]>, CameraError> {
    let row = image.width as usize * bytes_per_pixel;
    let step = image.step as usize;
    if step < row {
        return Err(message_error(
            topic,
            format!("step {step} is shorter than a row ({} × {bytes_per_pixel} bytes)", image.width),
        ));
    }
    let needed = step * (image.height as usize).saturating_sub(1) + row;
    if image.height == 0 || image.width == 0 || image.data.len() < needed {
        return Err(message_error(
            topic,
            format!(
                "{} bytes of data for {}×{} at step {step}: expected {needed}",
                image.data.len(),
                image.width,
                image.height
            ),
        ));
    }
    Ok((0..image.height as usize).map(|v| &image.data[v * step..v * step + row]).collect())
}

/// Colour pixels of an `rgb8` or `bgr8` image.
pub fn colour_pixels(image: &Image<'_>, topic: &str) -> Result<Vec<[u8; 3]>, CameraError> {
    let swap = match image.encoding.as_str() {
        "rgb8" => false,
        "bgr8" => true,
        other => return Err(message_error(topic, format!("encoding {other:?}: expected \"rgb8\" or \"bgr8\""))),
    };
    let rows = rows(image, topic, 3)?;
    Ok(rows
        .into_iter()
        .flat_map(|row| row.chunks_exact(3))
        .map(|p| if swap { [p[2], p[1], p[0]] } else { [p[0], p[1], p[2]] })
        .collect())
}

/// A 16-bit sample of a row, honouring `is_bigendian`.
fn u16_at(row: &[u8], i: usize, big_endian: bool) -> u16 {
    let bytes = [row[2 * i], row[2 * i + 1]];
    if big_endian { u16::from_be_bytes(bytes) } else { u16::from_le_bytes(bytes) }
}

/// Depth in metres (0 = no measurement) of a `16UC1`/`mono16` (mm) or
/// `32FC1` (m) image; NaN, infinite and negative depths are no measurement.
pub fn depth_metres(image: &Image<'_>, topic: &str) -> Result<Vec<f32>, CameraError> {
    let big_endian = image.is_bigendian != 0;
    let width = image.width as usize;
    match image.encoding.as_str() {
        "16UC1" | "mono16" => {
            let scale = 1.0 / MM_PER_M;
            Ok(rows(image, topic, 2)?
                .into_iter()
                .flat_map(|row| (0..width).map(move |i| (f64::from(u16_at(row, i, big_endian)) * scale) as f32))
                .collect())
        }
        "32FC1" => Ok(rows(image, topic, 4)?
            .into_iter()
            .flat_map(|row| {
                row.chunks_exact(4).map(move |b| {
                    let b = [b[0], b[1], b[2], b[3]];
                    let z = if big_endian { f32::from_be_bytes(b) } else { f32::from_le_bytes(b) };
                    if z.is_finite() && z > 0.0 { z } else { 0.0 }
                })
            })
            .collect()),
        other => Err(message_error(
            topic,
            format!("encoding {other:?}: expected \"16UC1\" or \"mono16\" (mm), or \"32FC1\" (m)"),
        )),
    }
}

/// One mask per object id of a label image, by increasing id.
pub fn label_masks(image: &Image<'_>, topic: &str) -> Result<Vec<(u32, Raster<bool>)>, CameraError> {
    let big_endian = image.is_bigendian != 0;
    let width = image.width as usize;
    let labels: Vec<u32> = match image.encoding.as_str() {
        "mono8" | "8UC1" => {
            rows(image, topic, 1)?.into_iter().flat_map(|row| row.iter().map(|&v| u32::from(v))).collect()
        }
        "mono16" | "16UC1" => rows(image, topic, 2)?
            .into_iter()
            .flat_map(|row| (0..width).map(move |i| u32::from(u16_at(row, i, big_endian))))
            .collect(),
        other => {
            return Err(message_error(
                topic,
                format!("encoding {other:?}: expected \"mono8\", \"8UC1\", \"mono16\" or \"16UC1\" object ids"),
            ));
        }
    };
    let ids: std::collections::BTreeSet<u32> = labels.iter().copied().filter(|&id| id != 0).collect();
    Ok(ids
        .into_iter()
        .map(|id| {
            let pixels = labels.iter().map(|&l| l == id).collect();
            (id, Raster { width: image.width, height: image.height, pixels })
        })
        .collect())
}

/// The pinhole camera of a CameraInfo, for images of `width`×`height`.
pub fn camera_model(info: &CameraInfo, topic: &str, width: u32, height: u32) -> Result<Camera, CameraError> {
    if (info.width, info.height) != (width, height) {
        return Err(message_error(
            topic,
            format!("{}×{}: expected the colour image's size {width}×{height}", info.width, info.height),
        ));
    }
    let [fx, _, cx, _, fy, cy, ..] = info.k;
    if ![fx, fy, cx, cy].iter().all(|v| v.is_finite()) || fx <= 0.0 || fy <= 0.0 {
        return Err(message_error(topic, format!("k = {:?}: expected finite intrinsics with fx, fy > 0", info.k)));
    }
    Ok(Camera { fx, fy, cx, cy, width, height })
}

/// Names of a camera's topics.
#[derive(Debug, Clone, PartialEq)]
pub struct CameraTopics {
    pub color: String,
    pub depth: String,
    pub info: String,
    pub labels: Option<String>,
}

/// One frame from paired messages; `frame_id` as the frame source counts.
pub fn frame_from_messages(
    topics: &CameraTopics,
    frame_id: u64,
    color: &Image<'_>,
    depth: &Image<'_>,
    info: &CameraInfo,
    labels: Option<&Image<'_>>,
) -> Result<LoadedFrame, CameraError> {
    let (width, height) = (color.width, color.height);
    let camera = camera_model(info, &topics.info, width, height)?;
    let same_size = |image: &Image<'_>, topic: &str| {
        if (image.width, image.height) == (width, height) {
            Ok(())
        } else {
            Err(message_error(
                topic,
                format!(
                    "{}×{}: expected the colour image's size {width}×{height} (depth aligned to colour)",
                    image.width, image.height
                ),
            ))
        }
    };
    same_size(depth, &topics.depth)?;
    let rgb = colour_pixels(color, &topics.color)?;
    let depth = depth_metres(depth, &topics.depth)?;
    let objects = match (labels, &topics.labels) {
        (Some(labels), Some(topic)) => {
            same_size(labels, topic)?;
            label_masks(labels, topic)?
                .into_iter()
                .enumerate()
                .map(|(instance, (obj_id, mask))| ObjectMask { obj_id, instance, mask })
                .collect()
        }
        _ => Vec::new(),
    };
    let stamp = color.header.stamp;
    Ok(LoadedFrame {
        frame: RgbdFrame {
            frame_id,
            label: format!("{} at {}.{:09}", topics.color, stamp.sec, stamp.nanosec),
            camera,
            rgb: Raster { width, height, pixels: rgb },
            depth: Raster { width, height, pixels: depth },
        },
        objects,
        skipped: Vec::new(),
        scene_id: 0,
        image_id: frame_id.min(u64::from(u32::MAX)) as u32,
        captured_ns: Some(stamp.as_ns()),
    })
}

/// The `ros2-camera` stage's own parameters (besides [`Connection`]).
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraParams {
    /// Defaults: the topics of `realsense2_camera` (ROS 2 Humble and later)
    /// with `align_depth.enable:=true`.
    #[serde(default = "color_topic")]
    pub color_topic: String,
    #[serde(default = "depth_topic")]
    pub depth_topic: String,
    #[serde(default = "info_topic")]
    pub info_topic: String,
    /// A label image topic for masks; none: frames without detections (a
    /// detector stage downstream adds them).
    pub labels_topic: Option<String>,
    /// Largest stamp difference within a frame, milliseconds.
    #[serde(default = "tolerance_ms")]
    pub stamp_tolerance_ms: f64,
    /// Messages held per topic while waiting for their partners; when the
    /// pipeline is slower than the camera the oldest are dropped (counted).
    #[serde(default = "queue")]
    pub queue: usize,
    /// End the stream after this many frames (tests, recordings); none:
    /// run until stopped.
    pub max_frames: Option<u64>,
}

fn color_topic() -> String {
    "/camera/camera/color/image_raw".into()
}
fn depth_topic() -> String {
    "/camera/camera/aligned_depth_to_color/image_raw".into()
}
fn info_topic() -> String {
    "/camera/camera/color/camera_info".into()
}
fn tolerance_ms() -> f64 {
    10.0
}
fn queue() -> usize {
    4
}

impl CameraParams {
    pub fn from_json(value: serde_json::Value) -> Result<Self, Ros2Error> {
        serde_json::from_value(value)
            .map_err(|err| Ros2Error::Params { key: "ros2-camera".into(), detail: err.to_string() })
    }

    pub fn topics(&self) -> CameraTopics {
        CameraTopics {
            color: self.color_topic.clone(),
            depth: self.depth_topic.clone(),
            info: self.info_topic.clone(),
            labels: self.labels_topic.clone(),
        }
    }
}

/// A received image message, kept as its bytes.
#[derive(Debug)]
struct Received {
    stamp_ns: u64,
    bytes: Vec<u8>,
}

impl Stamped for Received {
    fn stamp_ns(&self) -> u64 {
        self.stamp_ns
    }
}

/// What the Zenoh threads hand to the stage.
#[derive(Debug)]
struct Inbox {
    pairing: Pairing<Received>,
    frames: std::collections::VecDeque<Vec<Received>>,
    info: Option<Vec<u8>>,
    /// Messages that did not decode.
    undecodable: u64,
    /// Paired frames dropped because the stage had not taken the older ones.
    behind: u64,
}

/// How long one wait for a frame lasts before the stage reports idle.
const WAIT: Duration = Duration::from_millis(50);

/// A ROS 2 camera: subscriptions to its topics and the frames paired so far.
pub struct RosCamera {
    topics: CameraTopics,
    inbox: Arc<(Mutex<Inbox>, Condvar)>,
    next_frame: u64,
    max_frames: Option<u64>,
    reported_unpaired: u64,
    /// Whether the camera's distortion has been reported.
    distortion_reported: bool,
    _subscriptions: Vec<RosSubscription>,
    _session: RosSession,
}

impl std::fmt::Debug for RosCamera {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RosCamera")
            .field("topics", &self.topics)
            .field("next_frame", &self.next_frame)
            .finish_non_exhaustive()
    }
}

impl RosCamera {
    /// Subscribes to the camera's topics.
    pub fn open(connection: &Connection, params: &CameraParams) -> Result<Self, Ros2Error> {
        let topics = params.topics();
        for (key, topic) in
            [("color_topic", &topics.color), ("depth_topic", &topics.depth), ("info_topic", &topics.info)]
                .into_iter()
                .chain(topics.labels.as_ref().map(|t| ("labels_topic", t)))
        {
            crate::rmw::check_topic(topic)
                .map_err(|detail| Ros2Error::Params { key: key.into(), detail: format!("{topic:?}: {detail}") })?;
        }
        if !(params.stamp_tolerance_ms.is_finite() && params.stamp_tolerance_ms >= 0.0) {
            return Err(Ros2Error::Params {
                key: "stamp_tolerance_ms".into(),
                detail: format!("{}: expected a non-negative number", params.stamp_tolerance_ms),
            });
        }
        let streams = 2 + usize::from(topics.labels.is_some());
        let tolerance_ns = (params.stamp_tolerance_ms * 1e6) as u64;
        let inbox = Arc::new((
            Mutex::new(Inbox {
                pairing: Pairing::new(streams, tolerance_ns, params.queue),
                frames: Default::default(),
                info: None,
                undecodable: 0,
                behind: 0,
            }),
            Condvar::new(),
        ));
        let mut session = RosSession::open(connection, "poseflow_camera")?;
        let mut subscriptions = Vec::new();
        let image_streams = [Some(&topics.color), Some(&topics.depth), topics.labels.as_ref()];
        for (stream, topic) in image_streams.into_iter().flatten().enumerate() {
            let (inbox, topic_name, queue) = (inbox.clone(), topic.clone(), params.queue);
            subscriptions.push(session.subscribe(topic, &IMAGE, move |bytes| {
                let (lock, ready) = &*inbox;
                let mut inbox = lock.lock().unwrap_or_else(|e| e.into_inner());
                match Image::decode(&bytes) {
                    Ok(image) => {
                        let stamp_ns = image.header.stamp.as_ns();
                        tracing::debug!(topic = %topic_name, stamp_ns, bytes = bytes.len(), "image received");
                        if let Some(frame) = inbox.pairing.push(stream, Received { stamp_ns, bytes }) {
                            // Frames the stage has not taken yet: the oldest go first.
                            if inbox.frames.len() == queue {
                                inbox.frames.pop_front();
                                inbox.behind += 1;
                                tracing::warn!(topic = %topic_name, "frame dropped: the pipeline is behind the camera");
                            }
                            inbox.frames.push_back(frame);
                            ready.notify_one();
                        }
                    }
                    Err(err) => {
                        inbox.undecodable += 1;
                        tracing::warn!(topic = %topic_name, %err, "message refused");
                    }
                }
            })?);
        }
        let info_inbox = inbox.clone();
        let info_topic = topics.info.clone();
        subscriptions.push(session.subscribe(&topics.info, &CAMERA_INFO, move |bytes| {
            let mut inbox = info_inbox.0.lock().unwrap_or_else(|e| e.into_inner());
            match CameraInfo::decode(&bytes) {
                Ok(_) => inbox.info = Some(bytes),
                Err(err) => {
                    inbox.undecodable += 1;
                    tracing::warn!(topic = %info_topic, %err, "message refused");
                }
            }
        })?);
        tracing::info!(color = %topics.color, depth = %topics.depth, info = %topics.info, labels = ?topics.labels, "waiting for the camera");
        Ok(Self {
            topics,
            inbox,
            next_frame: 0,
            max_frames: params.max_frames,
            reported_unpaired: 0,
            distortion_reported: false,
            _subscriptions: subscriptions,
            _session: session,
        })
    }

    fn ended(&self) -> bool {
        self.max_frames.is_some_and(|max| self.next_frame >= max)
    }

    /// Messages left unpaired or refused, and frames dropped behind the
    /// camera, since the last call.
    fn take_unpaired(&mut self) -> u64 {
        let inbox = self.inbox.0.lock().unwrap_or_else(|e| e.into_inner());
        let total = inbox.pairing.unpaired().iter().sum::<u64>() + inbox.undecodable + inbox.behind;
        let new = total - self.reported_unpaired;
        if new > 0 {
            tracing::warn!(
                unpaired = ?inbox.pairing.unpaired(),
                refused = inbox.undecodable,
                frames_behind = inbox.behind,
                "so far: camera messages left unpaired (colour, depth[, labels]), refused, and frames dropped behind the camera"
            );
        }
        self.reported_unpaired = total;
        new
    }
}

impl FrameSource for RosCamera {
    fn take_dropped(&mut self) -> u64 {
        self.take_unpaired()
    }

    fn wait_ready(&mut self) -> bool {
        if self.ended() {
            return true;
        }
        let (lock, ready) = &*self.inbox;
        let inbox = lock.lock().unwrap_or_else(|e| e.into_inner());
        let (inbox, _) = ready
            .wait_timeout_while(inbox, WAIT, |inbox| inbox.frames.is_empty() || inbox.info.is_none())
            .unwrap_or_else(|e| e.into_inner());
        !inbox.frames.is_empty() && inbox.info.is_some()
    }

    fn next_frame(&mut self) -> Option<Result<LoadedFrame, IngestError>> {
        if self.ended() {
            return None;
        }
        let (images, info) = {
            let mut inbox = self.inbox.0.lock().unwrap_or_else(|e| e.into_inner());
            (inbox.frames.pop_front()?, inbox.info.clone()?)
        };
        let frame_id = self.next_frame;
        self.next_frame += 1;
        let decoded = (|| {
            let info = CameraInfo::decode(&info).map_err(|err| message_error(&self.topics.info, err.to_string()))?;
            if !self.distortion_reported && info.d.iter().any(|d| *d != 0.0) {
                // Said once: PoseFlow back-projects through a pinhole.
                tracing::warn!(topic = %self.topics.info, d = ?info.d, model = %info.distortion_model,
                    "the camera reports lens distortion, which PoseFlow ignores: use its rectified image topics");
                self.distortion_reported = true;
            }
            let image = |k: usize, topic: &str| {
                Image::decode(&images[k].bytes).map_err(|err| message_error(topic, err.to_string()))
            };
            let color = image(0, &self.topics.color)?;
            let depth = image(1, &self.topics.depth)?;
            let labels = match &self.topics.labels {
                Some(topic) => Some(image(2, topic)?),
                None => None,
            };
            frame_from_messages(&self.topics, frame_id, &color, &depth, &info, labels.as_ref())
        })();
        Some(
            decoded.map_err(|err| IngestError::Frame {
                frame: format!("camera frame {frame_id}"),
                detail: err.to_string(),
            }),
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::msgs::{RosHeader, Time};

    fn image(encoding: &str, width: u32, height: u32, bytes_per_pixel: u32, data: Vec<u8>) -> Image<'static> {
        Image {
            header: RosHeader { stamp: Time { sec: 5, nanosec: 7 }, frame_id: "cam".into() },
            height,
            width,
            encoding: encoding.into(),
            is_bigendian: 0,
            step: width * bytes_per_pixel,
            data: data.into(),
        }
    }

    fn topics() -> CameraTopics {
        CameraTopics { color: "/c".into(), depth: "/d".into(), info: "/i".into(), labels: Some("/l".into()) }
    }

    fn info(width: u32, height: u32) -> CameraInfo {
        CameraInfo {
            header: RosHeader::default(),
            height,
            width,
            distortion_model: "plumb_bob".into(),
            d: vec![0.0; 5],
            k: [500.0, 0.0, 1.0, 0.0, 501.0, 0.5, 0.0, 0.0, 1.0],
        }
    }

    #[test]
    fn bgr_is_swapped_to_rgb_and_padded_rows_are_read() {
        let mut bgr = image("bgr8", 1, 2, 3, vec![1, 2, 3, 9, 4, 5, 6, 9]);
        bgr.step = 4;
        assert_eq!(colour_pixels(&bgr, "/c").unwrap(), [[3, 2, 1], [6, 5, 4]]);
        let err = colour_pixels(&image("rgba8", 1, 1, 4, vec![0; 4]), "/c").unwrap_err().to_string();
        assert_eq!(err, "/c: encoding \"rgba8\": expected \"rgb8\" or \"bgr8\"");
        let err = colour_pixels(&image("rgb8", 2, 2, 3, vec![0; 11]), "/c").unwrap_err().to_string();
        assert!(err.contains("11 bytes") && err.contains("expected 12"), "{err}");
    }

    #[test]
    fn depth_in_millimetres_and_metres_becomes_metres() {
        let mm = image("16UC1", 2, 1, 2, [1234u16, 0].iter().flat_map(|v| v.to_le_bytes()).collect());
        assert_eq!(depth_metres(&mm, "/d").unwrap(), [(1234.0f64 * (1.0 / 1000.0)) as f32, 0.0]);
        let mut big = image("mono16", 1, 1, 2, 1234u16.to_be_bytes().to_vec());
        big.is_bigendian = 1;
        assert_eq!(depth_metres(&big, "/d").unwrap(), [1.234]);
        let m = image("32FC1", 3, 1, 4, [0.8f32, f32::NAN, -1.0].iter().flat_map(|v| v.to_le_bytes()).collect());
        assert_eq!(depth_metres(&m, "/d").unwrap(), [0.8, 0.0, 0.0]);
        let err = depth_metres(&image("rgb8", 1, 1, 3, vec![0; 3]), "/d").unwrap_err().to_string();
        assert!(err.contains("/d") && err.contains("16UC1"), "{err}");
    }

    #[test]
    fn a_label_image_gives_one_mask_per_object_id() {
        let labels = image("mono8", 3, 1, 1, vec![5, 0, 2]);
        let masks = label_masks(&labels, "/l").unwrap();
        assert_eq!(masks.iter().map(|(id, _)| *id).collect::<Vec<_>>(), [2, 5]);
        assert_eq!(masks[1].1.pixels, [true, false, false]);
    }

    #[test]
    fn paired_messages_become_a_frame_stamped_by_the_camera() {
        let color = image("rgb8", 2, 1, 3, vec![10, 20, 30, 40, 50, 60]);
        let depth = image("16UC1", 2, 1, 2, [800u16, 900].iter().flat_map(|v| v.to_le_bytes()).collect());
        let labels = image("mono8", 2, 1, 1, vec![0, 7]);
        let frame = frame_from_messages(&topics(), 3, &color, &depth, &info(2, 1), Some(&labels)).unwrap();
        assert_eq!(frame.captured_ns, Some(5_000_000_007));
        assert_eq!((frame.frame.frame_id, frame.image_id), (3, 3));
        assert_eq!(frame.frame.rgb.pixels, [[10, 20, 30], [40, 50, 60]]);
        assert_eq!(frame.objects.len(), 1);
        assert_eq!((frame.objects[0].obj_id, frame.frame.camera.fy), (7, 501.0));

        let wide = image("rgb8", 640, 480, 3, vec![0; 640 * 480 * 3]);
        let narrow = image("16UC1", 320, 240, 2, vec![0; 320 * 240 * 2]);
        let defaults = CameraParams::from_json(serde_json::json!({})).unwrap().topics();
        let err = frame_from_messages(&defaults, 3, &wide, &narrow, &info(640, 480), None).unwrap_err().to_string();
        assert_eq!(
            err,
            "/camera/camera/aligned_depth_to_color/image_raw: 320×240: expected the colour image's size 640×480 \
             (depth aligned to colour)"
        );
        let small_depth = image("16UC1", 1, 1, 2, vec![0, 0]);
        let err = frame_from_messages(&topics(), 3, &color, &small_depth, &info(2, 1), None).unwrap_err().to_string();
        assert!(err.contains("/d") && err.contains("1×1") && err.contains("2×1"), "{err}");
        let err = frame_from_messages(&topics(), 3, &color, &depth, &info(4, 3), None).unwrap_err().to_string();
        assert!(err.contains("/i") && err.contains("4×3"), "{err}");
        let mut bad = info(2, 1);
        bad.k[0] = f64::NAN;
        let err = frame_from_messages(&topics(), 3, &color, &depth, &bad, None).unwrap_err().to_string();
        assert!(err.contains("fx, fy > 0"), "{err}");
    }
}
