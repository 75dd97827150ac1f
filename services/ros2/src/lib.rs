//! ROS 2 without a ROS installation: PoseFlow's poses published to, and
//! RGB-D frames read from, a ROS 2 system over Zenoh in rmw_zenoh's
//! conventions ([`rmw`]), so nodes running `rmw_zenoh_cpp` (ROS 2 Humble
//! and later) see ordinary topics.
//!
//! - `ros2-bridge` ([`stage::PosePublisher`]): Estimate in; each object's
//!   selected pose as `geometry_msgs/msg/PoseWithCovarianceStamped` (the
//!   covariance of the kept hypotheses about it, ROS's 6×6 row-major `x y z`
//!   then rotations about the fixed `X Y Z` axes) and its kept hypotheses as
//!   `geometry_msgs/msg/PoseArray` ([`poses`]).
//! - `ros2-camera` ([`stage::CameraStage`]): colour and aligned depth
//!   `sensor_msgs/msg/Image`s and `sensor_msgs/msg/CameraInfo` in, paired
//!   by stamp ([`pairing`]); Frames out, as the BOP frame source makes them
//!   ([`camera`]).
//!
//! Messages are CDR-encoded by hand ([`cdr`], [`msgs`]): five message
//! types do not justify a ROS interface generator.

pub mod camera;
pub mod cdr;
pub mod msgs;
pub mod pairing;
pub mod poses;
pub mod rmw;
pub mod session;
pub mod stage;

#[derive(Debug, thiserror::Error)]
pub enum Ros2Error {
    #[error("param `{key}`: {detail}")]
    Params { key: String, detail: String },
    #[error("zenoh: {operation} `{target}`: {detail}")]
    Zenoh { operation: &'static str, target: String, detail: String },
    #[error(transparent)]
    Pose(#[from] poses::PoseError),
}

/// The stages of this crate: `ros2-bridge` (Estimates to ROS 2 topics) and
/// `ros2-camera` (a ROS 2 camera's topics to Frames).
pub fn registrations() -> Vec<poseflow_runtime::Registration> {
    use poseflow_runtime::Registration;
    vec![
        Registration::sink("ros2-bridge", |wiring| stage::PosePublisher::from_params(&wiring.params)),
        Registration::source("ros2-camera", |wiring| stage::CameraStage::from_params(&wiring.params)),
    ]
}
