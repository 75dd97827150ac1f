//! The ROS 2 messages PoseFlow speaks, as plain structs with their CDR
//! encoding, and what rmw_zenoh needs to name their types.
//!
//! Field lists follow the ROS 2 Jazzy interface definitions (the `.msg`
//! files are vendored for the tests in `tests/data/ros2-msgs/`). Type
//! hashes are RIHS01 hashes of those definitions; the values for `Time`,
//! `Header`, `Point`, `Image`, `CameraInfo` and `PoseWithCovarianceStamped`
//! equal the ones ROS 2 Jazzy reports, and the e2e tests check every one
//! against an independent implementation (`zenoh-ros2-sdk`).

use crate::cdr::{CdrError, CdrReader, CdrWriter};

/// How a ROS 2 message type is named on the wire.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RosType {
    /// `package/msg/Name`.
    pub name: &'static str,
    /// `package::msg::dds_::Name_`, the name in rmw_zenoh key expressions.
    pub dds_name: &'static str,
    /// `RIHS01_<sha256>`.
    pub hash: &'static str,
}

pub const POSE_WITH_COVARIANCE_STAMPED: RosType = RosType {
    name: "geometry_msgs/msg/PoseWithCovarianceStamped",
    dds_name: "geometry_msgs::msg::dds_::PoseWithCovarianceStamped_",
    hash: "RIHS01_26432f9803e43727d3c8f668d1fdb3c630f548af631e2f4e31382371bfea3b6e",
};

pub const POSE_ARRAY: RosType = RosType {
    name: "geometry_msgs/msg/PoseArray",
    dds_name: "geometry_msgs::msg::dds_::PoseArray_",
    hash: "RIHS01_af0cc36d190e104d546d168d6b39df04fa4b4ccecf59cb4c9ed328d3d5004aa0",
};

pub const IMAGE: RosType = RosType {
    name: "sensor_msgs/msg/Image",
    dds_name: "sensor_msgs::msg::dds_::Image_",
    hash: "RIHS01_d31d41a9a4c4bc8eae9be757b0beed306564f7526c88ea6a4588fb9582527d47",
};

pub const CAMERA_INFO: RosType = RosType {
    name: "sensor_msgs/msg/CameraInfo",
    dds_name: "sensor_msgs::msg::dds_::CameraInfo_",
    hash: "RIHS01_b3dfd68ff46c9d56c80fd3bd4ed22c7a4ddce8c8348f2f59c299e73118e7e275",
};

/// `builtin_interfaces/msg/Time`: seconds and nanoseconds since the UNIX
/// epoch (or the simulation's clock).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, PartialOrd, Ord)]
pub struct Time {
    pub sec: i32,
    pub nanosec: u32,
}

impl Time {
    /// From nanoseconds since the epoch (the stamps' clock,
    /// [`poseflow_contracts::stamp_clock_ns`]).
    pub fn from_ns(ns: u64) -> Self {
        Self { sec: (ns / 1_000_000_000).min(i32::MAX as u64) as i32, nanosec: (ns % 1_000_000_000) as u32 }
    }

    /// Nanoseconds since the epoch; a time before it is 0.
    pub fn as_ns(&self) -> u64 {
        u64::try_from(self.sec).map_or(0, |sec| sec * 1_000_000_000 + u64::from(self.nanosec))
    }
}

/// `std_msgs/msg/Header`.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct RosHeader {
    pub stamp: Time,
    pub frame_id: String,
}

impl RosHeader {
    fn write(&self, w: &mut CdrWriter) {
        w.i32(self.stamp.sec);
        w.u32(self.stamp.nanosec);
        w.string(&self.frame_id);
    }

    fn read(r: &mut CdrReader<'_>) -> Result<Self, CdrError> {
        let sec = r.i32("header.stamp.sec")?;
        let nanosec = r.u32("header.stamp.nanosec")?;
        Ok(Self { stamp: Time { sec, nanosec }, frame_id: r.string("header.frame_id")? })
    }
}

/// `geometry_msgs/msg/Pose`: a position (metres) and an orientation as a
/// unit quaternion `x, y, z, w`.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct RosPose {
    pub position: [f64; 3],
    pub orientation: [f64; 4],
}

impl RosPose {
    fn write(&self, w: &mut CdrWriter) {
        for value in self.position.iter().chain(&self.orientation) {
            w.f64(*value);
        }
    }

    fn read(r: &mut CdrReader<'_>, field: &'static str) -> Result<Self, CdrError> {
        Ok(Self { position: r.f64_array(field)?, orientation: r.f64_array(field)? })
    }
}

/// `geometry_msgs/msg/PoseWithCovarianceStamped`. `covariance` is 6×6
/// row-major over `x, y, z` and rotations about the fixed `X, Y, Z` axes.
#[derive(Debug, Clone, PartialEq)]
pub struct PoseWithCovarianceStamped {
    pub header: RosHeader,
    pub pose: RosPose,
    pub covariance: [f64; 36],
}

impl PoseWithCovarianceStamped {
    pub fn encode(&self) -> Vec<u8> {
        let mut w = CdrWriter::new();
        self.header.write(&mut w);
        self.pose.write(&mut w);
        for value in &self.covariance {
            w.f64(*value);
        }
        w.finish()
    }

    pub fn decode(bytes: &[u8]) -> Result<Self, CdrError> {
        let mut r = CdrReader::new(bytes)?;
        Ok(Self {
            header: RosHeader::read(&mut r)?,
            pose: RosPose::read(&mut r, "pose.pose")?,
            covariance: r.f64_array("pose.covariance")?,
        })
    }
}

/// `geometry_msgs/msg/PoseArray`.
#[derive(Debug, Clone, PartialEq)]
pub struct PoseArray {
    pub header: RosHeader,
    pub poses: Vec<RosPose>,
}

impl PoseArray {
    pub fn encode(&self) -> Vec<u8> {
        let mut w = CdrWriter::new();
        self.header.write(&mut w);
        w.count(self.poses.len());
        for pose in &self.poses {
            pose.write(&mut w);
        }
        w.finish()
    }

    pub fn decode(bytes: &[u8]) -> Result<Self, CdrError> {
        let mut r = CdrReader::new(bytes)?;
        let header = RosHeader::read(&mut r)?;
        let count = r.count("poses", 56)?;
        let poses = (0..count).map(|_| RosPose::read(&mut r, "poses")).collect::<Result<_, _>>()?;
        Ok(Self { header, poses })
    }
}

/// `sensor_msgs/msg/Image`, borrowing its pixels from the message.
#[derive(Debug, Clone, PartialEq)]
pub struct Image<'a> {
    pub header: RosHeader,
    pub height: u32,
    pub width: u32,
    pub encoding: String,
    pub is_bigendian: u8,
    /// Bytes per row.
    pub step: u32,
    pub data: std::borrow::Cow<'a, [u8]>,
}

impl<'a> Image<'a> {
    pub fn encode(&self) -> Vec<u8> {
        let mut w = CdrWriter::new();
        self.header.write(&mut w);
        w.u32(self.height);
        w.u32(self.width);
        w.string(&self.encoding);
        w.u8(self.is_bigendian);
        w.u32(self.step);
        w.byte_sequence(&self.data);
        w.finish()
    }

    pub fn decode(bytes: &'a [u8]) -> Result<Self, CdrError> {
        let mut r = CdrReader::new(bytes)?;
        Ok(Self {
            header: RosHeader::read(&mut r)?,
            height: r.u32("height")?,
            width: r.u32("width")?,
            encoding: r.string("encoding")?,
            is_bigendian: r.u8("is_bigendian")?,
            step: r.u32("step")?,
            data: std::borrow::Cow::Borrowed(r.byte_sequence("data")?),
        })
    }
}

/// `sensor_msgs/msg/CameraInfo` (the fields PoseFlow reads; the rest is
/// written as zeros and skipped when read).
#[derive(Debug, Clone, PartialEq)]
pub struct CameraInfo {
    pub header: RosHeader,
    pub height: u32,
    pub width: u32,
    pub distortion_model: String,
    pub d: Vec<f64>,
    /// 3×3 row-major intrinsic matrix `[fx 0 cx; 0 fy cy; 0 0 1]`.
    pub k: [f64; 9],
}

impl CameraInfo {
    pub fn encode(&self) -> Vec<u8> {
        let mut w = CdrWriter::new();
        self.header.write(&mut w);
        w.u32(self.height);
        w.u32(self.width);
        w.string(&self.distortion_model);
        w.count(self.d.len());
        for value in self.d.iter().chain(&self.k) {
            w.f64(*value);
        }
        let identity = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0];
        let [fx, _, cx, _, fy, cy, ..] = self.k;
        let projection = [fx, 0.0, cx, 0.0, 0.0, fy, cy, 0.0, 0.0, 0.0, 1.0, 0.0];
        for value in identity.iter().chain(&projection) {
            w.f64(*value);
        }
        for _ in 0..2 {
            w.u32(0); // binning
        }
        for _ in 0..4 {
            w.u32(0); // roi
        }
        w.u8(0);
        w.finish()
    }

    pub fn decode(bytes: &[u8]) -> Result<Self, CdrError> {
        let mut r = CdrReader::new(bytes)?;
        Ok(Self {
            header: RosHeader::read(&mut r)?,
            height: r.u32("height")?,
            width: r.u32("width")?,
            distortion_model: r.string("distortion_model")?,
            d: r.f64_sequence("d")?,
            k: r.f64_array("k")?,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn header() -> RosHeader {
        RosHeader { stamp: Time { sec: 1_700_000_000, nanosec: 123_456_789 }, frame_id: "camera_optical".into() }
    }

    #[test]
    fn messages_survive_their_round_trip() {
        let pose = RosPose { position: [0.1, -0.2, 0.9], orientation: [0.0, 0.0, 0.6, 0.8] };
        let stamped =
            PoseWithCovarianceStamped { header: header(), pose, covariance: std::array::from_fn(|i| i as f64) };
        assert_eq!(PoseWithCovarianceStamped::decode(&stamped.encode()).unwrap(), stamped);
        let array = PoseArray { header: header(), poses: vec![pose; 3] };
        assert_eq!(PoseArray::decode(&array.encode()).unwrap(), array);
        let image = Image {
            header: header(),
            height: 2,
            width: 3,
            encoding: "rgb8".into(),
            is_bigendian: 0,
            step: 9,
            data: (0..18u8).collect::<Vec<_>>().into(),
        };
        assert_eq!(Image::decode(&image.encode()).unwrap(), image);
        let info = CameraInfo {
            header: header(),
            height: 480,
            width: 640,
            distortion_model: "plumb_bob".into(),
            d: vec![0.0; 5],
            k: [572.4, 0.0, 325.3, 0.0, 573.6, 242.0, 0.0, 0.0, 1.0],
        };
        assert_eq!(CameraInfo::decode(&info.encode()).unwrap(), info);
    }

    /// PoseWithCovarianceStamped has a fixed layout once the frame id is
    /// known: header (4 + 4 + 4 + len + NUL, padded to 8), then 7 + 36
    /// doubles.
    #[test]
    fn a_pose_with_covariance_has_the_size_ros_gives_it() {
        let stamped = PoseWithCovarianceStamped { header: header(), pose: RosPose::default(), covariance: [0.0; 36] };
        // "camera_optical" is 14 bytes: 8 + 4 + 15 = 27, padded to 32.
        assert_eq!(stamped.encode().len(), 4 + 32 + 43 * 8);
    }

    #[test]
    fn times_convert_to_and_from_nanoseconds() {
        let t = Time::from_ns(1_700_000_000_123_456_789);
        assert_eq!(t, Time { sec: 1_700_000_000, nanosec: 123_456_789 });
        assert_eq!(t.as_ns(), 1_700_000_000_123_456_789);
        assert_eq!(Time { sec: -1, nanosec: 0 }.as_ns(), 0);
    }

    #[test]
    fn truncated_images_name_the_field() {
        let image = Image {
            header: header(),
            height: 1,
            width: 1,
            encoding: "mono8".into(),
            is_bigendian: 0,
            step: 1,
            data: vec![7u8; 100].into(),
        };
        let bytes = image.encode();
        let err = Image::decode(&bytes[..bytes.len() - 10]).unwrap_err().to_string();
        assert!(err.contains("data"), "{err}");
    }
}
