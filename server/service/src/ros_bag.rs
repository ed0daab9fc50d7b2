//! What `pntr replay --record-bag` writes: the answered frames as a ROS 2 bag (a rosbag2 folder of
//! MCAP with ROS 2 message types, [`pntr_dataset::bag_writer`]), in ROS conventions (z-up `map`, the
//! camera's optical frame `camera_optical`), with the topics `pntr-ros` publishes on a robot, so
//! `ros2 bag play` feeds a recorded run to rviz or to the nodes that consume pntr-ros:
//! - `/pntr/pose` (geometry_msgs/PoseWithCovarianceStamped): the camera's pose in `map` with its
//!   covariance (ROS order), LOCALIZED frames only;
//! - `/tf` (tf2_msgs/TFMessage): `map -> camera_optical` for every LOCALIZED answer (there is no
//!   odometry in a replay, so the camera's frame itself);
//! - `/diagnostics` (diagnostic_msgs/DiagnosticArray): one status a frame, OK when LOCALIZED, WARN
//!   with the reason when not, with the confidence, inliers, mode, cause and matched image;
//! - `/pntr/ground_truth` (geometry_msgs/PoseStamped): the true pose, when known;
//! - `/camera/color/image_raw/compressed` (sensor_msgs/CompressedImage, PNG) and
//!   `/camera/color/camera_info` (sensor_msgs/CameraInfo): the frame as it was sent.

use std::path::{Path, PathBuf};
use std::sync::Mutex;

use nalgebra::Isometry3;
use pntr_dataset::bag::{
    CameraInfo, CompressedImage, Header, Point, Pose, PoseStamped, RosQuaternion, RosVector3,
    TfMessage, Time, Transform, TransformStamped,
};
use pntr_dataset::bag_writer::{
    BagWriter, Covariance, DiagnosticArray, DiagnosticStatus, KeyValue, MessageType,
    PoseWithCovariance, PoseWithCovarianceStamped,
};

use crate::visual::{Observation, Picture, FRAME_CAMERA, FRAME_MAP};

/// The topics of a bag.
pub mod topics {
    /// The answered pose.
    pub const POSE: &str = "/pntr/pose";
    /// `map -> camera_optical`.
    pub const TF: &str = "/tf";
    /// One status a frame.
    pub const DIAGNOSTICS: &str = "/diagnostics";
    /// The true pose.
    pub const TRUTH: &str = "/pntr/ground_truth";
    /// The frame's colour image.
    pub const IMAGE: &str = "/camera/color/image_raw/compressed";
    /// The frame's camera.
    pub const CAMERA_INFO: &str = "/camera/color/camera_info";
}

/// A ROS 2 bag being written from answered frames; [`BagRecording::finish`] completes it.
pub struct BagRecording {
    writer: Mutex<BagWriter>,
}

fn nanos(time_s: f64) -> u64 {
    (time_s.max(0.0) * 1e9).round() as u64
}

fn header(time_s: f64, frame: &str) -> Header {
    Header {
        stamp: Time::from_seconds(time_s.max(0.0)),
        frame_id: frame.into(),
    }
}

fn pose(p: &Isometry3<f64>) -> Pose {
    let q = pntr_core::pose::canonical_wxyz(&p.rotation);
    Pose {
        position: Point {
            x: p.translation.x,
            y: p.translation.y,
            z: p.translation.z,
        },
        orientation: RosQuaternion {
            x: q[1],
            y: q[2],
            z: q[3],
            w: q[0],
        },
    }
}

impl BagRecording {
    /// Start the bag folder `out` (it must not exist). Errors name the folder.
    pub fn create(out: &Path) -> Result<Self, String> {
        Ok(Self {
            writer: Mutex::new(BagWriter::create(out).map_err(|e| e.to_string())?),
        })
    }

    /// Write one answered frame.
    pub fn observe(&self, o: &Observation<'_>) -> Result<(), String> {
        let mut w = self.writer.lock().unwrap_or_else(|e| e.into_inner());
        let t = nanos(o.time_s);
        let err = |e: pntr_dataset::DatasetError| e.to_string();
        if let Some((picture, k)) = &o.picture {
            let (data, format) = match picture {
                Picture::Encoded { data, format } => (data.to_vec(), *format),
                Picture::Raw(rgb) => (
                    crate::wire::encode_png(
                        rgb.width,
                        rgb.height,
                        png::ColorType::Rgb,
                        png::BitDepth::Eight,
                        &rgb.data,
                    )
                    .map_err(|e| format!("encoding a frame as PNG: {e}"))?,
                    "png",
                ),
            };
            let image = CompressedImage {
                header: header(o.time_s, FRAME_CAMERA),
                format: format!("rgb8; {format} compressed rgb8"),
                data,
            };
            w.write(topics::IMAGE, MessageType::CompressedImage, t, &image)
                .map_err(err)?;
            w.write(
                topics::CAMERA_INFO,
                MessageType::CameraInfo,
                t,
                &CameraInfo::of(k, header(o.time_s, FRAME_CAMERA)),
            )
            .map_err(err)?;
        }
        if let Some(p) = &o.pose {
            let mut covariance = [0.0; 36];
            if o.covariance.len() == 36 {
                covariance.copy_from_slice(o.covariance);
            }
            let m = PoseWithCovarianceStamped {
                header: header(o.time_s, FRAME_MAP),
                pose: PoseWithCovariance {
                    pose: pose(p),
                    covariance: Covariance(covariance),
                },
            };
            w.write(topics::POSE, MessageType::PoseWithCovarianceStamped, t, &m)
                .map_err(err)?;
            let q = pose(p);
            let tf = TfMessage {
                transforms: vec![TransformStamped {
                    header: header(o.time_s, FRAME_MAP),
                    child_frame_id: FRAME_CAMERA.into(),
                    transform: Transform {
                        translation: RosVector3 {
                            x: q.position.x,
                            y: q.position.y,
                            z: q.position.z,
                        },
                        rotation: q.orientation,
                    },
                }],
            };
            w.write(topics::TF, MessageType::TfMessage, t, &tf)
                .map_err(err)?;
        }
        if let Some(g) = &o.truth {
            let m = PoseStamped {
                header: header(o.time_s, FRAME_MAP),
                pose: pose(g),
            };
            w.write(topics::TRUTH, MessageType::PoseStamped, t, &m)
                .map_err(err)?;
        }
        let kv = |k: &str, v: String| KeyValue {
            key: k.into(),
            value: v,
        };
        let localized = o.pose.is_some();
        let diagnostics = DiagnosticArray {
            header: header(o.time_s, ""),
            status: vec![DiagnosticStatus {
                level: if localized { 0 } else { 1 },
                name: "pntr: localization".into(),
                message: if localized {
                    "localized".into()
                } else {
                    format!("not localized: {}", o.reason)
                },
                hardware_id: o.map_id.into(),
                values: vec![
                    kv("status", o.status.into()),
                    kv("reason", o.reason.into()),
                    kv("confidence", format!("{:.4}", o.confidence)),
                    kv("inliers", o.inliers.to_string()),
                    kv("mode", o.mode.into()),
                    kv("matched_image_id", o.matched_image_id.into()),
                    kv("map_version", o.map_version.into()),
                    kv("request_id", o.request_id.into()),
                ],
            }],
        };
        w.write(
            topics::DIAGNOSTICS,
            MessageType::DiagnosticArray,
            t,
            &diagnostics,
        )
        .map_err(err)
    }

    /// Close the bag and move it to its name.
    pub fn finish(self) -> Result<PathBuf, String> {
        self.writer
            .into_inner()
            .unwrap_or_else(|e| e.into_inner())
            .finish()
            .map_err(|e| e.to_string())
    }
}

/// Where `--record` writes: a Foxglove MCAP file (a path ending in `.mcap`) or a ROS 2 bag (any
/// other path: a new rosbag2 folder).
pub enum Recorder {
    /// Foxglove's schemas, one MCAP file ([`crate::visual::Recording`]).
    Foxglove(crate::visual::Recording),
    /// ROS 2 message types, a rosbag2 folder ([`BagRecording`]).
    RosBag(Box<BagRecording>),
}

impl Recorder {
    /// Start `out`: a Foxglove MCAP file when it ends in `.mcap`, else a ROS 2 bag folder (which
    /// must not exist). Errors name the path.
    pub fn create(out: &Path) -> Result<Self, String> {
        let mcap = out
            .extension()
            .is_some_and(|e| e.eq_ignore_ascii_case("mcap"));
        Ok(if mcap {
            Self::Foxglove(crate::visual::Recording::create(out)?)
        } else {
            Self::RosBag(Box::new(BagRecording::create(out)?))
        })
    }

    /// Write one answered frame.
    pub fn observe(&self, o: &Observation<'_>) -> Result<(), String> {
        match self {
            Self::Foxglove(r) => {
                r.view().observe(o);
                r.error().map_or(Ok(()), Err)
            }
            Self::RosBag(b) => b.observe(o),
        }
    }

    /// The poses of a map's images (`map_from_camera_optical`, z-up), at `time_s`: shown in a
    /// Foxglove file; a ROS 2 bag has no standard message for them and leaves them out.
    pub fn map_cameras(&self, time_s: f64, poses: impl IntoIterator<Item = Isometry3<f64>>) {
        if let Self::Foxglove(r) = self {
            r.view().map_cameras(time_s, poses);
        }
    }

    /// Close it and move it to its name.
    pub fn finish(self) -> Result<PathBuf, String> {
        match self {
            Self::Foxglove(r) => r.finish(),
            Self::RosBag(b) => b.finish(),
        }
    }
}
