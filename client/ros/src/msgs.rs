//! The ROS 2 messages pntr-ros reads and writes, as serde structs laid out field by field as their
//! `.msg` definitions (common_interfaces, geometry2), so that CDR (XCDR1, little endian) encodes them
//! byte for byte as rmw_fastrtps and rmw_cyclonedds do. Byte arrays (`uint8[]`) go through
//! `serde_bytes` (one length and one copy instead of an element at a time); fixed arrays of more
//! than 32 elements through `serde_big_array`.

use ros2_client::{Message, MessageTypeName};
use serde::{Deserialize, Serialize};
use serde_big_array::BigArray;

/// builtin_interfaces/Time: seconds and nanoseconds since the epoch of the ROS clock.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, PartialOrd, Ord, Serialize, Deserialize)]
pub struct Time {
    /// Seconds.
    pub sec: i32,
    /// Nanoseconds, 0 ..= 999 999 999.
    pub nanosec: u32,
}

impl Time {
    /// Nanoseconds since the epoch.
    pub fn nanos(self) -> i64 {
        i64::from(self.sec) * 1_000_000_000 + i64::from(self.nanosec)
    }

    /// The time `ns` nanoseconds after the epoch.
    pub fn from_nanos(ns: i64) -> Self {
        Self {
            sec: ns.div_euclid(1_000_000_000) as i32,
            nanosec: ns.rem_euclid(1_000_000_000) as u32,
        }
    }

    /// The wall clock now (the ROS clock without simulated time).
    pub fn now() -> Self {
        let d = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .unwrap_or_default();
        Self::from_nanos(d.as_nanos() as i64)
    }
}

/// std_msgs/Header.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Header {
    /// When the data was captured.
    pub stamp: Time,
    /// The frame the data is expressed in.
    pub frame_id: String,
}

/// sensor_msgs/Image.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct Image {
    /// Capture time and the camera's optical frame.
    pub header: Header,
    /// Rows.
    pub height: u32,
    /// Columns.
    pub width: u32,
    /// Pixel encoding: rgb8, bgr8, rgba8, bgra8, mono8, 16UC1, mono16, 32FC1...
    pub encoding: String,
    /// 1 when multi-byte pixels are big endian.
    pub is_bigendian: u8,
    /// Bytes per row (at least width times the pixel size).
    pub step: u32,
    /// Row-major pixels, `step * height` bytes.
    #[serde(with = "serde_bytes")]
    pub data: Vec<u8>,
}

/// sensor_msgs/CompressedImage (image_transport's `compressed` and `compressedDepth`).
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct CompressedImage {
    /// Capture time and the camera's optical frame.
    pub header: Header,
    /// For example `bgr8; jpeg compressed bgr8` or `16UC1; compressedDepth png`.
    pub format: String,
    /// The file (for compressedDepth after a 12-byte configuration header).
    #[serde(with = "serde_bytes")]
    pub data: Vec<u8>,
}

/// sensor_msgs/RegionOfInterest.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct RegionOfInterest {
    /// First column.
    pub x_offset: u32,
    /// First row.
    pub y_offset: u32,
    /// Rows.
    pub height: u32,
    /// Columns.
    pub width: u32,
    /// Whether the ROI is to be rectified.
    pub do_rectify: bool,
}

/// sensor_msgs/CameraInfo.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct CameraInfo {
    /// Capture time and the camera's optical frame.
    pub header: Header,
    /// Rows of the calibrated image.
    pub height: u32,
    /// Columns of the calibrated image.
    pub width: u32,
    /// `plumb_bob`, `rational_polynomial`, `equidistant`...
    pub distortion_model: String,
    /// Distortion coefficients.
    pub d: Vec<f64>,
    /// 3x3 intrinsic matrix, row-major, pixels.
    pub k: [f64; 9],
    /// 3x3 rectification rotation, row-major.
    pub r: [f64; 9],
    /// 3x4 projection matrix, row-major.
    pub p: [f64; 12],
    /// Horizontal binning (0 and 1: none).
    pub binning_x: u32,
    /// Vertical binning (0 and 1: none).
    pub binning_y: u32,
    /// Region of interest (all zero: the whole image).
    pub roi: RegionOfInterest,
}

/// geometry_msgs/Vector3 (also geometry_msgs/Point: the same layout).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Vector3 {
    /// x, metres.
    pub x: f64,
    /// y, metres.
    pub y: f64,
    /// z, metres.
    pub z: f64,
}

/// geometry_msgs/Quaternion.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Quaternion {
    /// x.
    pub x: f64,
    /// y.
    pub y: f64,
    /// z.
    pub z: f64,
    /// w.
    pub w: f64,
}

/// geometry_msgs/Transform: parent_from_child.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Transform {
    /// The child frame's origin in the parent frame, metres.
    pub translation: Vector3,
    /// The child frame's orientation in the parent frame.
    pub rotation: Quaternion,
}

/// geometry_msgs/TransformStamped: `header.frame_id` is the parent, `child_frame_id` the child.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct TransformStamped {
    /// Time and parent frame.
    pub header: Header,
    /// The child frame.
    pub child_frame_id: String,
    /// parent_from_child.
    pub transform: Transform,
}

/// tf2_msgs/TFMessage (`/tf`, `/tf_static`).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct TfMessage {
    /// The transforms.
    pub transforms: Vec<TransformStamped>,
}

/// geometry_msgs/Pose: position (a geometry_msgs/Point) and orientation.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Pose {
    /// Position, metres.
    pub position: Vector3,
    /// Orientation.
    pub orientation: Quaternion,
}

/// geometry_msgs/PoseWithCovariance.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct PoseWithCovariance {
    /// The pose.
    pub pose: Pose,
    /// 6x6 row-major, x y z then rotation about x y z (fixed axes), metres² and radians².
    #[serde(with = "BigArray")]
    pub covariance: [f64; 36],
}

/// geometry_msgs/PoseWithCovarianceStamped.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PoseWithCovarianceStamped {
    /// Time and the frame the pose is in.
    pub header: Header,
    /// Pose and covariance.
    pub pose: PoseWithCovariance,
}

/// diagnostic_msgs/KeyValue.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct KeyValue {
    /// Key.
    pub key: String,
    /// Value.
    pub value: String,
}

/// diagnostic_msgs/DiagnosticStatus.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct DiagnosticStatus {
    /// OK = 0, WARN = 1, ERROR = 2, STALE = 3.
    pub level: u8,
    /// What is reported on.
    pub name: String,
    /// One line of state.
    pub message: String,
    /// The hardware (here the server address).
    pub hardware_id: String,
    /// Figures.
    pub values: Vec<KeyValue>,
}

/// diagnostic_msgs/DiagnosticArray (`/diagnostics`).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct DiagnosticArray {
    /// When.
    pub header: Header,
    /// One status per reporting part.
    pub status: Vec<DiagnosticStatus>,
}

/// std_srvs/Trigger request (rosidl gives an empty request one placeholder byte).
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct TriggerRequest {
    /// Unused.
    pub structure_needs_at_least_one_member: u8,
}
impl Message for TriggerRequest {}

/// std_srvs/Trigger response.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct TriggerResponse {
    /// Whether the request was carried out.
    pub success: bool,
    /// What was done.
    pub message: String,
}
impl Message for TriggerResponse {}

/// The ROS type of each message (`pkg/msg/Name`, which ros2-client turns into `pkg::msg::dds_::Name_`).
pub mod types {
    use super::MessageTypeName;

    /// sensor_msgs/Image.
    pub fn image() -> MessageTypeName {
        MessageTypeName::new("sensor_msgs", "Image")
    }
    /// sensor_msgs/CompressedImage.
    pub fn compressed_image() -> MessageTypeName {
        MessageTypeName::new("sensor_msgs", "CompressedImage")
    }
    /// sensor_msgs/CameraInfo.
    pub fn camera_info() -> MessageTypeName {
        MessageTypeName::new("sensor_msgs", "CameraInfo")
    }
    /// tf2_msgs/TFMessage.
    pub fn tf_message() -> MessageTypeName {
        MessageTypeName::new("tf2_msgs", "TFMessage")
    }
    /// geometry_msgs/PoseWithCovarianceStamped.
    pub fn pose_with_covariance_stamped() -> MessageTypeName {
        MessageTypeName::new("geometry_msgs", "PoseWithCovarianceStamped")
    }
    /// diagnostic_msgs/DiagnosticArray.
    pub fn diagnostic_array() -> MessageTypeName {
        MessageTypeName::new("diagnostic_msgs", "DiagnosticArray")
    }
}
