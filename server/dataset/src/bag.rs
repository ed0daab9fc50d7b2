//! ROS 2 bags in MCAP (rosbag2's default storage): colour, depth and camera info as a robot recorded
//! them, read with the `mcap` crate and decoded from CDR with the `cdr` crate.
//!
//! Messages read: `sensor_msgs/msg/Image` (colour `rgb8`, `bgr8`, `rgba8`, `bgra8`; depth `16UC1` in
//! millimetres or `32FC1` in metres, pixel-aligned with the colour, e.g. a RealSense's
//! `aligned_depth_to_color`), `sensor_msgs/msg/CameraInfo` (K and plumb_bob D) and, for ground truth,
//! `geometry_msgs/msg/PoseStamped` (world_from_camera of the optical frame, as ROS gives camera poses).
//! Frames are paired by header stamp within
//! [`crate::tum::MAX_PAIR_GAP_S`]. The whole file is read into memory (a bag of a few minutes of
//! 640x480 frames is a few GB: split long recordings).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion};
use pntr_core::{DepthMap, Intrinsics, RgbImage};
use serde::{Deserialize, Serialize};

use crate::tum::{nearest, MAX_PAIR_GAP_S};
use crate::DatasetError;

/// Topics of a bag (RealSense's names by default).
#[derive(Debug, Clone)]
pub struct Topics {
    /// Colour images.
    pub rgb: String,
    /// Depth images aligned to the colour camera.
    pub depth: String,
    /// The colour camera's calibration.
    pub info: String,
    /// Ground-truth poses (`world_from_camera`), optional.
    pub pose: Option<String>,
}

impl Default for Topics {
    fn default() -> Self {
        Self {
            rgb: "/camera/color/image_raw".into(),
            depth: "/camera/aligned_depth_to_color/image_raw".into(),
            info: "/camera/color/camera_info".into(),
            pose: None,
        }
    }
}

/// builtin_interfaces/msg/Time.
#[derive(Debug, Clone, Copy, Serialize, Deserialize, Default)]
pub struct Time {
    /// Seconds.
    pub sec: i32,
    /// Nanoseconds.
    pub nanosec: u32,
}

impl Time {
    fn seconds(&self) -> f64 {
        self.sec as f64 + self.nanosec as f64 * 1e-9
    }

    /// The stamp of `t` seconds (t >= 0).
    pub fn from_seconds(t: f64) -> Self {
        let sec = t.floor();
        Self {
            sec: sec as i32,
            nanosec: ((t - sec) * 1e9).round().min(999_999_999.0) as u32,
        }
    }
}

/// std_msgs/msg/Header.
#[derive(Debug, Clone, Serialize, Deserialize, Default)]
pub struct Header {
    /// Time of the data.
    pub stamp: Time,
    /// Coordinate frame.
    pub frame_id: String,
}

/// sensor_msgs/msg/Image.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Image {
    /// Stamp and frame.
    pub header: Header,
    /// Rows.
    pub height: u32,
    /// Columns.
    pub width: u32,
    /// Pixel encoding (`rgb8`, `16UC1`, ...).
    pub encoding: String,
    /// 1 when multi-byte values are big-endian.
    pub is_bigendian: u8,
    /// Bytes per row.
    pub step: u32,
    /// The pixels.
    #[serde(with = "serde_bytes")]
    pub data: Vec<u8>,
}

/// sensor_msgs/msg/RegionOfInterest.
#[derive(Debug, Clone, Serialize, Deserialize, Default)]
pub struct RegionOfInterest {
    /// Left.
    pub x_offset: u32,
    /// Top.
    pub y_offset: u32,
    /// Rows.
    pub height: u32,
    /// Columns.
    pub width: u32,
    /// Rectify the region.
    pub do_rectify: bool,
}

/// sensor_msgs/msg/CameraInfo.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct CameraInfo {
    /// Stamp and frame.
    pub header: Header,
    /// Rows.
    pub height: u32,
    /// Columns.
    pub width: u32,
    /// `plumb_bob` (or empty / `rational_polynomial`, ...).
    pub distortion_model: String,
    /// Distortion coefficients.
    pub d: Vec<f64>,
    /// Row-major 3x3 camera matrix.
    pub k: [f64; 9],
    /// Rectification rotation.
    pub r: [f64; 9],
    /// Row-major 3x4 projection matrix.
    pub p: [f64; 12],
    /// Horizontal binning.
    pub binning_x: u32,
    /// Vertical binning.
    pub binning_y: u32,
    /// Region of interest.
    pub roi: RegionOfInterest,
}

/// geometry_msgs/msg/Point (also used for the position of a pose).
#[derive(Debug, Clone, Copy, Serialize, Deserialize)]
pub struct Point {
    /// x.
    pub x: f64,
    /// y.
    pub y: f64,
    /// z.
    pub z: f64,
}

/// geometry_msgs/msg/Quaternion.
#[derive(Debug, Clone, Copy, Serialize, Deserialize)]
pub struct RosQuaternion {
    /// x.
    pub x: f64,
    /// y.
    pub y: f64,
    /// z.
    pub z: f64,
    /// w.
    pub w: f64,
}

/// geometry_msgs/msg/Pose.
#[derive(Debug, Clone, Copy, Serialize, Deserialize)]
pub struct Pose {
    /// Position.
    pub position: Point,
    /// Orientation.
    pub orientation: RosQuaternion,
}

/// geometry_msgs/msg/PoseStamped.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct PoseStamped {
    /// Stamp and frame.
    pub header: Header,
    /// The pose.
    pub pose: Pose,
}

/// A ROS 2 bag's drive: paired colour and depth messages, in time order.
#[derive(Debug, Clone)]
pub struct Bag {
    /// The file.
    pub path: PathBuf,
    /// The camera (from the first CameraInfo; `None` when the bag has none).
    pub intrinsics: Option<Intrinsics>,
    /// Paired frames.
    frames: Vec<PairedFrame>,
    /// Units per metre of integer (`16UC1`) depth: 1000 (REP 118's millimetres) unless the caller
    /// knows the sensor uses others (4000 for 0.25 mm). `32FC1` depth is metres whatever this says.
    pub depth_units_per_m: f64,
}

/// Stamp seconds, colour message (CDR), depth message (CDR), ground truth.
type PairedFrame = (f64, Vec<u8>, Vec<u8>, Option<Isometry3<f64>>);

fn bad(path: &Path, problem: impl Into<String>) -> DatasetError {
    DatasetError::Layout {
        path: path.to_path_buf(),
        problem: problem.into(),
    }
}

fn decode<'a, T: Deserialize<'a>>(
    path: &Path,
    topic: &str,
    bytes: &[u8],
) -> Result<T, DatasetError> {
    cdr::deserialize::<T>(bytes).map_err(|e| {
        bad(
            path,
            format!("topic {topic}: cannot decode the CDR message: {e}"),
        )
    })
}

impl Bag {
    /// Read a bag. Errors name the file and, for a missing topic, the topics the bag has.
    pub fn open(path: &Path, topics: &Topics) -> Result<Self, DatasetError> {
        let bytes = std::fs::read(path).map_err(|source| DatasetError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        let mut rgb: Vec<(f64, Vec<u8>)> = Vec::new();
        let mut depth: Vec<(f64, Vec<u8>)> = Vec::new();
        let mut poses: Vec<(f64, Isometry3<f64>)> = Vec::new();
        let mut info: Option<CameraInfo> = None;
        let mut seen: BTreeMap<String, String> = BTreeMap::new();
        let stream = mcap::MessageStream::new(&bytes)
            .map_err(|e| bad(path, format!("not an MCAP file: {e}")))?;
        for m in stream {
            let m = m.map_err(|e| bad(path, format!("damaged MCAP file: {e}")))?;
            let topic = &m.channel.topic;
            let schema = m
                .channel
                .schema
                .as_ref()
                .map(|s| s.name.clone())
                .unwrap_or_default();
            seen.entry(topic.clone()).or_insert(schema);
            if m.channel.message_encoding != "cdr" {
                continue;
            }
            if topic == &topics.rgb || topic == &topics.depth {
                let header: ImageStamp = decode(path, topic, &m.data)?;
                let list = if topic == &topics.rgb {
                    &mut rgb
                } else {
                    &mut depth
                };
                list.push((header.header.stamp.seconds(), m.data.into_owned()));
            } else if topic == &topics.info && info.is_none() {
                info = Some(decode(path, topic, &m.data)?);
            } else if Some(topic) == topics.pose.as_ref() {
                let p: PoseStamped = decode(path, topic, &m.data)?;
                let o = p.pose.orientation;
                poses.push((
                    p.header.stamp.seconds(),
                    Isometry3::from_parts(
                        Translation3::new(p.pose.position.x, p.pose.position.y, p.pose.position.z),
                        UnitQuaternion::from_quaternion(Quaternion::new(o.w, o.x, o.y, o.z)),
                    ),
                ));
            }
        }
        let listing = || {
            seen.iter()
                .map(|(t, s)| format!("{t} ({s})"))
                .collect::<Vec<_>>()
                .join(", ")
        };
        for (what, topic, n) in [
            ("colour", &topics.rgb, rgb.len()),
            ("depth", &topics.depth, depth.len()),
        ] {
            if n == 0 {
                return Err(bad(
                    path,
                    format!("no {what} images on {topic}; the bag has: {}", listing()),
                ));
            }
        }
        if let Some(t) = &topics.pose {
            if poses.is_empty() {
                return Err(bad(
                    path,
                    format!("no poses on {t}; the bag has: {}", listing()),
                ));
            }
        }
        for list in [&mut rgb, &mut depth] {
            list.sort_by(|a, b| a.0.total_cmp(&b.0));
        }
        poses.sort_by(|a, b| a.0.total_cmp(&b.0));
        let intrinsics = info.map(|i| camera(path, &i)).transpose()?;
        let frames: Vec<_> = rgb
            .into_iter()
            .filter_map(|(t, c)| {
                let d = nearest(&depth, t)?;
                Some((
                    t,
                    c,
                    depth[d].1.clone(),
                    nearest(&poses, t).map(|g| poses[g].1),
                ))
            })
            .collect();
        if frames.is_empty() {
            return Err(bad(
                path,
                format!("no colour image has a depth image within {MAX_PAIR_GAP_S} s"),
            ));
        }
        Ok(Self {
            path: path.to_path_buf(),
            intrinsics,
            frames,
            depth_units_per_m: 1000.0,
        })
    }

    /// Paired frames.
    pub fn len(&self) -> usize {
        self.frames.len()
    }

    /// True when there is no frame.
    pub fn is_empty(&self) -> bool {
        self.frames.is_empty()
    }

    /// Stamp of frame `i`, seconds.
    pub fn timestamp(&self, i: usize) -> f64 {
        self.frames[i].0
    }

    /// Ground truth of frame `i`, when the bag has a pose topic.
    pub fn ground_truth(&self, i: usize) -> Option<Isometry3<f64>> {
        self.frames[i].3
    }

    /// Decode frame `i`: colour and depth in metres (0 = missing). Errors name the encoding.
    pub fn load(&self, i: usize) -> Result<(RgbImage, DepthMap), DatasetError> {
        let (_, c, d, _) = &self.frames[i];
        let c: Image = decode(&self.path, "colour", c)?;
        let d: Image = decode(&self.path, "depth", d)?;
        let rgb = rgb_of(&self.path, &c)?;
        let depth = depth_of(&self.path, &d, self.depth_units_per_m)?;
        if (depth.width, depth.height) != (rgb.width, rgb.height) {
            return Err(bad(
                &self.path,
                format!(
                    "depth is {}x{}, colour {}x{}: the depth topic must be aligned to the colour camera",
                    depth.width, depth.height, rgb.width, rgb.height
                ),
            ));
        }
        Ok((rgb, depth))
    }
}

/// Only the header of an Image (what pairing needs), without copying the pixels.
#[derive(Deserialize)]
struct ImageStamp {
    header: Header,
}

fn camera(path: &Path, i: &CameraInfo) -> Result<Intrinsics, DatasetError> {
    let mut k = Intrinsics {
        fx: i.k[0],
        fy: i.k[4],
        cx: i.k[2],
        cy: i.k[5],
        width: i.width,
        height: i.height,
        ..Intrinsics::hpointloc()
    };
    match (i.distortion_model.as_str(), i.d.len()) {
        (_, 0) => {}
        ("plumb_bob", 5) => k.distortion.copy_from_slice(&i.d),
        (m, n) => {
            return Err(bad(
                path,
                format!("camera info: distortion model {m:?} with {n} coefficients; plumb_bob with 5 is supported"),
            ))
        }
    }
    k.validate()
        .map_err(|e| bad(path, format!("camera info: {e}")))?;
    Ok(k)
}

fn rows<'a>(
    path: &Path,
    m: &'a Image,
    bytes_per_pixel: usize,
) -> Result<Vec<&'a [u8]>, DatasetError> {
    let row = m.width as usize * bytes_per_pixel;
    let step = m.step as usize;
    if step < row || m.data.len() < step * m.height as usize {
        return Err(bad(
            path,
            format!(
                "{} image {}x{}: step {} and {} bytes do not hold the pixels",
                m.encoding,
                m.width,
                m.height,
                m.step,
                m.data.len()
            ),
        ));
    }
    Ok((0..m.height as usize)
        .map(|r| &m.data[r * step..r * step + row])
        .collect())
}

fn rgb_of(path: &Path, m: &Image) -> Result<RgbImage, DatasetError> {
    let (bpp, order): (usize, [usize; 3]) = match m.encoding.as_str() {
        "rgb8" => (3, [0, 1, 2]),
        "bgr8" => (3, [2, 1, 0]),
        "rgba8" => (4, [0, 1, 2]),
        "bgra8" => (4, [2, 1, 0]),
        other => {
            return Err(bad(
                path,
                format!("colour encoding {other:?}: rgb8, bgr8, rgba8 and bgra8 are read"),
            ))
        }
    };
    let mut data = Vec::with_capacity(m.width as usize * m.height as usize * 3);
    for row in rows(path, m, bpp)? {
        for px in row.chunks_exact(bpp) {
            data.extend(order.iter().map(|&c| px[c]));
        }
    }
    Ok(RgbImage {
        width: m.width,
        height: m.height,
        data,
    })
}

fn depth_of(path: &Path, m: &Image, units_per_m: f64) -> Result<DepthMap, DatasetError> {
    let scale = (1.0 / units_per_m) as f32;
    let big = m.is_bigendian != 0;
    let data: Vec<f32> = match m.encoding.as_str() {
        "16UC1" | "mono16" => rows(path, m, 2)?
            .into_iter()
            .flat_map(|r| r.chunks_exact(2))
            .map(|b| {
                let v = if big {
                    u16::from_be_bytes([b[0], b[1]])
                } else {
                    u16::from_le_bytes([b[0], b[1]])
                };
                v as f32 * scale
            })
            .collect(),
        "32FC1" => rows(path, m, 4)?
            .into_iter()
            .flat_map(|r| r.chunks_exact(4))
            .map(|b| {
                let a = [b[0], b[1], b[2], b[3]];
                let v = if big {
                    f32::from_be_bytes(a)
                } else {
                    f32::from_le_bytes(a)
                };
                if v.is_finite() && v > 0.0 {
                    v
                } else {
                    0.0
                }
            })
            .collect(),
        other => {
            return Err(bad(
                path,
                format!(
                    "depth encoding {other:?}: 16UC1 (millimetres) and 32FC1 (metres) are read"
                ),
            ))
        }
    };
    Ok(DepthMap {
        width: m.width,
        height: m.height,
        data,
    })
}

/// Minimal ROS 2 message definitions (the `ros2msg` schema text) of what [`write_bag`] writes.
const IMAGE_DEF: &str = "std_msgs/Header header\nuint32 height\nuint32 width\nstring encoding\nuint8 is_bigendian\nuint32 step\nuint8[] data\n================================================================================\nMSG: std_msgs/Header\nbuiltin_interfaces/Time stamp\nstring frame_id\n================================================================================\nMSG: builtin_interfaces/Time\nint32 sec\nuint32 nanosec\n";
const INFO_DEF: &str = "std_msgs/Header header\nuint32 height\nuint32 width\nstring distortion_model\nfloat64[] d\nfloat64[9] k\nfloat64[9] r\nfloat64[12] p\nuint32 binning_x\nuint32 binning_y\nsensor_msgs/RegionOfInterest roi\n================================================================================\nMSG: std_msgs/Header\nbuiltin_interfaces/Time stamp\nstring frame_id\n================================================================================\nMSG: builtin_interfaces/Time\nint32 sec\nuint32 nanosec\n================================================================================\nMSG: sensor_msgs/RegionOfInterest\nuint32 x_offset\nuint32 y_offset\nuint32 height\nuint32 width\nbool do_rectify\n";
const POSE_DEF: &str = "std_msgs/Header header\ngeometry_msgs/Pose pose\n================================================================================\nMSG: std_msgs/Header\nbuiltin_interfaces/Time stamp\nstring frame_id\n================================================================================\nMSG: builtin_interfaces/Time\nint32 sec\nuint32 nanosec\n================================================================================\nMSG: geometry_msgs/Pose\nPoint position\nQuaternion orientation\n================================================================================\nMSG: geometry_msgs/Point\nfloat64 x\nfloat64 y\nfloat64 z\n================================================================================\nMSG: geometry_msgs/Quaternion\nfloat64 x\nfloat64 y\nfloat64 z\nfloat64 w\n";

/// One frame for [`write_bag`]: time, colour, depth (metres) and the ground truth.
pub type BagFrame<'a> = (f64, &'a RgbImage, &'a DepthMap, Option<Isometry3<f64>>);

/// Write frames as a ROS 2 bag (MCAP, zstd chunks): colour as `rgb8`, depth as `16UC1` millimetres,
/// one CameraInfo per frame, and PoseStamped ground truth on `topics.pose` when given. Through a
/// temporary name renamed into place.
pub fn write_bag(
    path: &Path,
    frames: &[BagFrame<'_>],
    k: &Intrinsics,
    topics: &Topics,
) -> Result<(), DatasetError> {
    let tmp = PathBuf::from(format!("{}.partial-{}", path.display(), std::process::id()));
    let io = |e: std::io::Error| DatasetError::Io {
        path: tmp.clone(),
        source: e,
    };
    let mcap_err = |e: mcap::McapError| bad(&tmp, format!("writing MCAP: {e}"));
    let file = std::io::BufWriter::new(std::fs::File::create(&tmp).map_err(io)?);
    let mut w = mcap::WriteOptions::new()
        .profile("ros2")
        .create(file)
        .map_err(mcap_err)?;
    let no_meta = BTreeMap::new();
    let image_schema = w
        .add_schema("sensor_msgs/msg/Image", "ros2msg", IMAGE_DEF.as_bytes())
        .map_err(mcap_err)?;
    let info_schema = w
        .add_schema("sensor_msgs/msg/CameraInfo", "ros2msg", INFO_DEF.as_bytes())
        .map_err(mcap_err)?;
    let rgb_ch = w
        .add_channel(image_schema, &topics.rgb, "cdr", &no_meta)
        .map_err(mcap_err)?;
    let depth_ch = w
        .add_channel(image_schema, &topics.depth, "cdr", &no_meta)
        .map_err(mcap_err)?;
    let info_ch = w
        .add_channel(info_schema, &topics.info, "cdr", &no_meta)
        .map_err(mcap_err)?;
    let pose_ch = match &topics.pose {
        Some(t) => {
            let s = w
                .add_schema(
                    "geometry_msgs/msg/PoseStamped",
                    "ros2msg",
                    POSE_DEF.as_bytes(),
                )
                .map_err(mcap_err)?;
            Some(w.add_channel(s, t, "cdr", &no_meta).map_err(mcap_err)?)
        }
        None => None,
    };
    let ser = |v: &dyn erased::Cdr| v.cdr().map_err(|e| bad(&tmp, format!("CDR encoding: {e}")));
    for (seq, (t, rgb, depth, gt)) in frames.iter().enumerate() {
        let header = Header {
            stamp: Time::from_seconds(*t),
            frame_id: "camera_color_optical_frame".into(),
        };
        let ns = (*t * 1e9).round() as u64;
        let mut put = |channel_id: u16, data: Vec<u8>| {
            w.write_to_known_channel(
                &mcap::records::MessageHeader {
                    channel_id,
                    sequence: seq as u32,
                    log_time: ns,
                    publish_time: ns,
                },
                &data,
            )
        };
        let colour = Image {
            header: header.clone(),
            height: rgb.height,
            width: rgb.width,
            encoding: "rgb8".into(),
            is_bigendian: 0,
            step: rgb.width * 3,
            data: rgb.data.clone(),
        };
        put(rgb_ch, ser(&colour)?).map_err(mcap_err)?;
        let mm: Vec<u8> = depth
            .to_millimetres()
            .into_iter()
            .flat_map(u16::to_le_bytes)
            .collect();
        let d = Image {
            header: header.clone(),
            height: depth.height,
            width: depth.width,
            encoding: "16UC1".into(),
            is_bigendian: 0,
            step: depth.width * 2,
            data: mm,
        };
        put(depth_ch, ser(&d)?).map_err(mcap_err)?;
        let info = CameraInfo {
            header: header.clone(),
            height: k.height,
            width: k.width,
            distortion_model: "plumb_bob".into(),
            d: k.distortion.to_vec(),
            k: [k.fx, 0.0, k.cx, 0.0, k.fy, k.cy, 0.0, 0.0, 1.0],
            r: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
            p: [
                k.fx, 0.0, k.cx, 0.0, 0.0, k.fy, k.cy, 0.0, 0.0, 0.0, 1.0, 0.0,
            ],
            binning_x: 0,
            binning_y: 0,
            roi: RegionOfInterest::default(),
        };
        put(info_ch, ser(&info)?).map_err(mcap_err)?;
        if let (Some(ch), Some(g)) = (pose_ch, gt) {
            let q = g.rotation.quaternion();
            let p = PoseStamped {
                header: Header {
                    frame_id: "map".into(),
                    ..header.clone()
                },
                pose: Pose {
                    position: Point {
                        x: g.translation.x,
                        y: g.translation.y,
                        z: g.translation.z,
                    },
                    orientation: RosQuaternion {
                        x: q.i,
                        y: q.j,
                        z: q.k,
                        w: q.w,
                    },
                },
            };
            put(ch, ser(&p)?).map_err(mcap_err)?;
        }
    }
    w.finish().map_err(mcap_err)?;
    drop(w);
    std::fs::rename(&tmp, path).map_err(|source| DatasetError::Io {
        path: path.to_path_buf(),
        source,
    })
}

/// CDR encoding of the message types behind one object-safe call.
mod erased {
    pub trait Cdr {
        fn cdr(&self) -> Result<Vec<u8>, cdr::Error>;
    }
    impl<T: serde::Serialize> Cdr for T {
        fn cdr(&self) -> Result<Vec<u8>, cdr::Error> {
            cdr::serialize::<_, _, cdr::CdrLe>(self, cdr::Infinite)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_written_bag_reads_back_and_mistakes_are_named() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("drive.mcap");
        let k = Intrinsics::from_fov(4, 2, 90.0);
        let rgbs: Vec<RgbImage> = (0..3u8)
            .map(|i| RgbImage {
                width: 4,
                height: 2,
                data: (0..24).map(|j| j * 10 + i).collect(),
            })
            .collect();
        let depth = DepthMap {
            width: 4,
            height: 2,
            data: vec![0.0, 1.0, 2.5, 10.0, 0.0004, f32::NAN, -1.0, 70.0],
        };
        let gt = |t: f64| {
            Isometry3::from_parts(
                Translation3::new(1.0 + t, 1.25, -2.0),
                UnitQuaternion::from_euler_angles(0.1, t, 0.0),
            )
        };
        let frames: Vec<BagFrame<'_>> = (0..3)
            .map(|i| {
                (
                    0.1 * i as f64 + 1.0,
                    &rgbs[i],
                    &depth,
                    Some(gt(0.1 * i as f64)),
                )
            })
            .collect();
        let topics = Topics {
            pose: Some("/ground_truth".into()),
            ..Topics::default()
        };
        write_bag(&path, &frames, &k, &topics).unwrap();
        let bag = Bag::open(&path, &topics).unwrap();
        assert_eq!(bag.len(), 3);
        let back = bag.intrinsics.unwrap();
        assert_eq!((back.fx, back.cx, back.width), (k.fx, k.cx, 4));
        for (i, want_rgb) in rgbs.iter().enumerate() {
            let (rgb, d) = bag.load(i).unwrap();
            assert_eq!(rgb.data, want_rgb.data);
            // Millimetres: invalid values become 0, 70 m saturates at 65.535 m.
            let want = [0.0, 1.0, 2.5, 10.0, 0.0, 0.0, 0.0, 65.535];
            for (a, b) in d.data.iter().zip(want) {
                assert!((a - b).abs() < 1e-3, "{a} vs {b}");
            }
            assert!((bag.timestamp(i) - (1.0 + 0.1 * i as f64)).abs() < 1e-6);
            let g = bag.ground_truth(i).unwrap();
            let w = gt(0.1 * i as f64);
            assert!((g.translation.vector - w.translation.vector).norm() < 1e-9);
            assert!(g.rotation.angle_to(&w.rotation) < 1e-9);
        }
        // A wrong topic names the topics the bag has.
        let e = Bag::open(
            &path,
            &Topics {
                rgb: "/camera/rgb".into(),
                ..topics.clone()
            },
        )
        .unwrap_err()
        .to_string();
        assert!(
            e.contains("/camera/rgb")
                && e.contains("/camera/color/image_raw (sensor_msgs/msg/Image)"),
            "{e}"
        );
        std::fs::write(dir.path().join("x.mcap"), b"not a bag").unwrap();
        let e = Bag::open(&dir.path().join("x.mcap"), &topics)
            .unwrap_err()
            .to_string();
        assert!(e.contains("x.mcap") && e.contains("MCAP"), "{e}");
    }
}
