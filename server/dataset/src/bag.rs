//! ROS 2 bags as `ros2 bag record` writes them: a folder (`metadata.yaml` and one or more, possibly
//! split, MCAP files) or one `.mcap` file, read with the `mcap` crate's streaming reader (zstd and lz4
//! chunks; a file cut short is read up to its last intact record, with a warning) and decoded from CDR
//! with the `cdr` crate, every vector bounded by the message's size.
//!
//! Messages read: colour as `sensor_msgs/msg/Image` (`rgb8`, `bgr8`, `rgba8`, `bgra8`) or
//! `sensor_msgs/msg/CompressedImage` (JPEG or PNG, the `/compressed` sibling taken when the raw topic
//! is absent); depth as `Image` (`16UC1` in millimetres or `32FC1` in metres, pixel-aligned with the
//! colour, e.g. a RealSense's `aligned_depth_to_color`) or the `compressedDepth` form (a 12-byte header
//! and a 16-bit PNG); `sensor_msgs/msg/CameraInfo` (K, and plumb_bob D; a model pntr cannot use or an
//! all-zero K leaves the camera to `--intrinsics`, said so); poses from `geometry_msgs/msg/PoseStamped`
//! (world_from_camera of the optical frame), `nav_msgs/msg/Odometry` (of the body, moved to the camera
//! by TF) or TF itself (`/tf`, `/tf_static`, [`crate::tf`]), each looked up at the image's stamp.
//! Frames are paired by header stamp within [`crate::tum::MAX_PAIR_GAP_S`] (receive times when a
//! driver leaves every header stamp zero, said so). A topic holding another message type than
//! expected is refused before anything is decoded.
//!
//! Memory: [`Bag::open`] streams the files once for the stamps, camera and poses (kept: a few numbers
//! a message); [`Bag::load`] streams them again forward, keeping only messages later frames need, so
//! a recording of any length is read in bounded memory.

use std::collections::{BTreeMap, HashMap};
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
    /// Poses: `geometry_msgs/PoseStamped` of the camera's optical frame or `nav_msgs/Odometry` of
    /// the body; without it poses come from TF.
    pub pose: Option<String>,
    /// TF: the world frame poses are given in (`map`).
    pub map_frame: String,
    /// TF: the camera's optical frame (default: the colour images' `header.frame_id`).
    pub camera_frame: Option<String>,
}

impl Default for Topics {
    fn default() -> Self {
        Self {
            rgb: "/camera/color/image_raw".into(),
            depth: "/camera/aligned_depth_to_color/image_raw".into(),
            info: "/camera/color/camera_info".into(),
            pose: None,
            map_frame: "map".into(),
            camera_frame: None,
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

impl CameraInfo {
    /// The CameraInfo of a pinhole camera with `plumb_bob` distortion (K, identity R, P = [K | 0]).
    pub fn of(k: &Intrinsics, header: Header) -> Self {
        Self {
            header,
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
        }
    }
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

fn bad(path: &Path, problem: impl Into<String>) -> DatasetError {
    DatasetError::Layout {
        path: path.to_path_buf(),
        problem: problem.into(),
    }
}

/// sensor_msgs/msg/CompressedImage.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct CompressedImage {
    /// Stamp and frame.
    pub header: Header,
    /// `rgb8; jpeg compressed bgr8`, `16UC1; compressedDepth png`, ...
    pub format: String,
    /// The encoded image (for compressedDepth, a 12-byte header first).
    #[serde(with = "serde_bytes")]
    pub data: Vec<u8>,
}

/// geometry_msgs/msg/Vector3.
#[derive(Debug, Clone, Copy, Serialize, Deserialize)]
pub struct RosVector3 {
    /// x.
    pub x: f64,
    /// y.
    pub y: f64,
    /// z.
    pub z: f64,
}

/// geometry_msgs/msg/Transform.
#[derive(Debug, Clone, Copy, Serialize, Deserialize)]
pub struct Transform {
    /// Translation.
    pub translation: RosVector3,
    /// Rotation.
    pub rotation: RosQuaternion,
}

/// geometry_msgs/msg/TransformStamped.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct TransformStamped {
    /// Stamp and parent frame.
    pub header: Header,
    /// Child frame.
    pub child_frame_id: String,
    /// parent_from_child.
    pub transform: Transform,
}

/// tf2_msgs/msg/TFMessage.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct TfMessage {
    /// Transforms.
    pub transforms: Vec<TransformStamped>,
}

/// The leading fields of nav_msgs/msg/Odometry (header, child frame, pose with covariance).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct OdometryPose {
    /// Stamp and the pose's frame (odom, map).
    pub header: Header,
    /// The body frame the pose is of (base_link).
    pub child_frame_id: String,
    /// The pose.
    pub pose: Pose,
}

/// How far a quaternion's squared norm may be from 1 before its transform is left out: tf2's
/// tolerance (`BufferCore::setTransform` ignores such a transform with `TF_DENORMALIZED_QUATERNION`).
pub const QUATERNION_NORM2_TOLERANCE: f64 = 1e-2;

/// A transform or pose as recorded, or why it is left out (as tf2 leaves it out): a value that is
/// not finite, or a quaternion whose squared norm is farther than [`QUATERNION_NORM2_TOLERANCE`]
/// from 1 (an all-zero one among them). Within the tolerance the quaternion is normalised.
fn isometry(t: [f64; 3], q: &RosQuaternion) -> Result<Isometry3<f64>, String> {
    let v = [t[0], t[1], t[2], q.x, q.y, q.z, q.w];
    if v.iter().any(|x| !x.is_finite()) {
        return Err(format!(
            "a value that is not finite (position {:?}, quaternion x y z w {:?})",
            t,
            [q.x, q.y, q.z, q.w]
        ));
    }
    let q = Quaternion::new(q.w, q.x, q.y, q.z);
    let n2 = q.norm_squared();
    if (n2 - 1.0).abs() > QUATERNION_NORM2_TOLERANCE {
        return Err(format!(
            "a quaternion of norm {:.4}, not a rotation",
            n2.sqrt()
        ));
    }
    Ok(Isometry3::from_parts(
        Translation3::new(t[0], t[1], t[2]),
        UnitQuaternion::from_quaternion(q),
    ))
}

/// Transforms and poses left out of a recording (not finite, not a rotation), per topic: how many,
/// and the first one's stamp, frame and reason, for one warning a topic.
#[derive(Default)]
struct LeftOut(BTreeMap<String, (usize, f64, String, String)>);

impl LeftOut {
    fn note(&mut self, topic: &str, stamp: f64, frame: &str, why: String) {
        let e = self
            .0
            .entry(topic.to_string())
            .or_insert_with(|| (0, stamp, frame.to_string(), why));
        e.0 += 1;
    }

    fn warnings(&self) -> impl Iterator<Item = String> + '_ {
        self.0.iter().map(|(topic, (n, t, frame, why))| {
            // tf2 itself reads only TF; a pose topic's poses are held to the same rule.
            let rule = if topic.starts_with("/tf") {
                "as tf2 leaves them out"
            } else {
                "by tf2's rule for transforms"
            };
            format!(
                "{topic}: {n} pose{} left out, {rule} (the first at {t:.6} s, {frame}: {why}); frames are posed from the samples around the gap{}",
                if *n == 1 { "" } else { "s" },
                if *n == 1 { "" } else { "s" }
            )
        })
    }
}

/// The MCAP files of a bag: the file itself, or a rosbag2 folder's `metadata.yaml` files in order
/// (split recordings), or a folder's `.mcap` files by name when it has no metadata. A `.db3` (the
/// sqlite3 storage) is refused naming the conversion.
pub fn bag_files(path: &Path) -> Result<Vec<PathBuf>, DatasetError> {
    let sqlite = |p: &Path| {
        bad(
            p,
            "a rosbag2 sqlite3 (.db3) bag: pntr reads MCAP storage; convert it with `ros2 bag convert` (storage_id: mcap)",
        )
    };
    if path.is_file() {
        if path
            .extension()
            .is_some_and(|e| e.eq_ignore_ascii_case("db3"))
        {
            return Err(sqlite(path));
        }
        return Ok(vec![path.to_path_buf()]);
    }
    if !path.is_dir() {
        return Err(DatasetError::Io {
            path: path.to_path_buf(),
            source: std::io::Error::new(std::io::ErrorKind::NotFound, "no such file or folder"),
        });
    }
    let meta = path.join("metadata.yaml");
    if meta.is_file() {
        let text = std::fs::read_to_string(&meta).map_err(|source| DatasetError::Io {
            path: meta.clone(),
            source,
        })?;
        let v: serde_yaml::Value =
            serde_yaml::from_str(&text).map_err(|e| bad(&meta, format!("not YAML: {e}")))?;
        let info = &v["rosbag2_bagfile_information"];
        let storage = info["storage_identifier"].as_str().unwrap_or("mcap");
        if storage == "sqlite3" {
            return Err(sqlite(&meta));
        }
        let files: Vec<PathBuf> = info["relative_file_paths"]
            .as_sequence()
            .map(|s| {
                s.iter()
                    .filter_map(|f| f.as_str())
                    .map(|f| path.join(f))
                    .collect()
            })
            .unwrap_or_default();
        if files.is_empty() {
            return Err(bad(
                &meta,
                "rosbag2_bagfile_information.relative_file_paths lists no file",
            ));
        }
        for f in &files {
            if !f.is_file() {
                return Err(bad(
                    f,
                    "listed in metadata.yaml but missing (a split file lost?)",
                ));
            }
        }
        return Ok(files);
    }
    let mut files: Vec<PathBuf> = std::fs::read_dir(path)
        .map_err(|source| DatasetError::Io {
            path: path.to_path_buf(),
            source,
        })?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            p.extension()
                .is_some_and(|e| e.eq_ignore_ascii_case("mcap"))
        })
        .collect();
    files.sort();
    if files.is_empty() {
        return Err(bad(
            path,
            "a folder without metadata.yaml or .mcap files (expected a ROS 2 bag folder or a TUM RGB-D sequence)",
        ));
    }
    Ok(files)
}

/// One message read from a bag.
struct Message {
    topic: std::sync::Arc<str>,
    schema: std::sync::Arc<str>,
    log_time_ns: u64,
    data: Vec<u8>,
}

/// The largest record read, bytes (an uncompressed 4K depth frame is 17 MB).
const RECORD_LIMIT: usize = 256 << 20;

/// Messages of a bag's files in order, streamed through a small buffer (MCAP's linear reader: zstd and
/// lz4 chunks; a file cut short ends at its last intact record, with a warning).
struct MessageReader {
    files: Vec<PathBuf>,
    next_file: usize,
    current: Option<(PathBuf, std::fs::File, mcap::sans_io::LinearReader)>,
    schemas: HashMap<u16, std::sync::Arc<str>>,
    channels: HashMap<u16, (std::sync::Arc<str>, std::sync::Arc<str>, bool)>,
    warnings: Vec<String>,
}

impl MessageReader {
    fn new(files: Vec<PathBuf>) -> Self {
        Self {
            files,
            next_file: 0,
            current: None,
            schemas: HashMap::new(),
            channels: HashMap::new(),
            warnings: Vec::new(),
        }
    }

    fn next(&mut self) -> Result<Option<Message>, DatasetError> {
        use std::io::Read;
        loop {
            if self.current.is_none() {
                let Some(f) = self.files.get(self.next_file) else {
                    return Ok(None);
                };
                self.next_file += 1;
                let file = std::fs::File::open(f).map_err(|source| DatasetError::Io {
                    path: f.clone(),
                    source,
                })?;
                let reader = mcap::sans_io::LinearReader::new_with_options(
                    mcap::sans_io::LinearReaderOptions::default()
                        .with_record_length_limit(RECORD_LIMIT),
                );
                self.schemas.clear();
                self.channels.clear();
                self.current = Some((f.clone(), file, reader));
            }
            let (path, file, reader) = self.current.as_mut().expect("set above");
            let event = match reader.next_event() {
                None => {
                    self.current = None;
                    continue;
                }
                Some(Err(mcap::McapError::UnexpectedEof)) => {
                    self.warnings.push(format!(
                        "{}: the file ends in the middle of a record (cut short, e.g. by a power loss): read up to its last intact record",
                        path.display()
                    ));
                    self.current = None;
                    continue;
                }
                Some(Err(e)) => {
                    return Err(bad(path, format!("damaged MCAP file: {e}")));
                }
                Some(Ok(e)) => e,
            };
            match event {
                mcap::sans_io::LinearReadEvent::ReadRequest(n) => {
                    let buf = reader.insert(n.clamp(4096, 1 << 20));
                    let got = file.read(buf).map_err(|source| DatasetError::Io {
                        path: path.clone(),
                        source,
                    })?;
                    reader.notify_read(got);
                }
                mcap::sans_io::LinearReadEvent::Record { data, opcode } => {
                    let record = mcap::parse_record(opcode, data)
                        .map_err(|e| bad(path, format!("damaged MCAP record: {e}")))?;
                    match record {
                        mcap::records::Record::Schema { header, .. } => {
                            self.schemas.insert(header.id, header.name.as_str().into());
                        }
                        mcap::records::Record::Channel(c) => {
                            let schema = self
                                .schemas
                                .get(&c.schema_id)
                                .cloned()
                                .unwrap_or_else(|| "".into());
                            self.channels.insert(
                                c.id,
                                (c.topic.as_str().into(), schema, c.message_encoding == "cdr"),
                            );
                        }
                        mcap::records::Record::Message { header, data } => {
                            let Some((topic, schema, cdr)) = self.channels.get(&header.channel_id)
                            else {
                                continue;
                            };
                            if !cdr {
                                continue;
                            }
                            return Ok(Some(Message {
                                topic: topic.clone(),
                                schema: schema.clone(),
                                log_time_ns: header.log_time,
                                data: data.into_owned(),
                            }));
                        }
                        _ => {}
                    }
                }
            }
        }
    }
}

/// Decode a CDR message whose vectors and strings cannot claim more than the message holds.
fn decode_bounded<T: serde::de::DeserializeOwned>(
    path: &Path,
    topic: &str,
    bytes: &[u8],
) -> Result<T, DatasetError> {
    let mut r = bytes;
    cdr::deserialize_from::<_, T, _>(&mut r, cdr::size::Bounded(bytes.len() as u64 * 2 + 64))
        .map_err(|e| {
            bad(
                path,
                format!("topic {topic}: cannot decode the CDR message: {e}"),
            )
        })
}

const IMAGE: &str = "sensor_msgs/msg/Image";
const COMPRESSED: &str = "sensor_msgs/msg/CompressedImage";

/// Where a stream of colour or depth messages is: its topic's ordinal of each message, by stamp.
#[derive(Debug, Clone, Default)]
struct Stamps {
    /// (stamp seconds, ordinal on the topic)
    list: Vec<(f64, usize)>,
}

/// A ROS 2 bag's drive: paired colour and depth messages in time order, with their poses.
pub struct Bag {
    /// The file or folder.
    pub path: PathBuf,
    files: Vec<PathBuf>,
    /// The camera (from the first CameraInfo; `None` when the bag has none or one pntr cannot use,
    /// then [`Bag::camera_problem`] says why).
    pub intrinsics: Option<Intrinsics>,
    /// Why the bag's CameraInfo cannot be used (give `--intrinsics`).
    pub camera_problem: Option<String>,
    rgb_topic: String,
    depth_topic: String,
    /// (stamp, colour ordinal, depth ordinal, pose) per frame.
    frames: Vec<(f64, usize, usize, Option<Isometry3<f64>>)>,
    /// Why frames have no pose (the first failed look-up), when some have none.
    pub pose_problem: Option<String>,
    /// Warnings for the user (cut-short files, stamps replaced).
    pub warnings: Vec<String>,
    /// Units per metre of integer (`16UC1`) depth: 1000 (REP 118's millimetres) unless the caller
    /// knows the sensor uses others (4000 for 0.25 mm). `32FC1` depth is metres whatever this says.
    pub depth_units_per_m: f64,
    cursor: std::sync::Mutex<Option<Cursor>>,
    /// Per stream (colour, depth): CompressedImage rather than Image.
    compressed: [bool; 2],
    /// Per stream (colour, depth): the last frame that uses each message ordinal.
    last_use: [HashMap<usize, usize>; 2],
}

impl std::fmt::Debug for Bag {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Bag")
            .field("path", &self.path)
            .field("frames", &self.frames.len())
            .finish()
    }
}

/// A message's schema name and CDR bytes.
type Raw = (std::sync::Arc<str>, Vec<u8>);

/// The second pass: messages streamed forward, those a later frame needs kept.
struct Cursor {
    reader: MessageReader,
    seen: [usize; 2],
    kept: [HashMap<usize, Raw>; 2],
}

impl Bag {
    /// Read a bag's index (stamps, camera, poses; not the images): a `.mcap` file or a rosbag2
    /// folder. Colour comes from `topics.rgb` (or its `/compressed` sibling when it is absent), depth
    /// from `topics.depth` (or `/compressedDepth`); poses from `topics.pose` (PoseStamped of the
    /// camera, or Odometry of the body, moved to the camera by the static transforms) or, without
    /// one, from TF (`topics.map_frame` to `topics.camera_frame`, default the colour images'
    /// frame). Errors name the file, the topic and the message.
    pub fn open(path: &Path, topics: &Topics) -> Result<Self, DatasetError> {
        let files = bag_files(path)?;
        let mut reader = MessageReader::new(files.clone());
        let (rgb_c, depth_c) = (
            format!("{}/compressed", topics.rgb),
            format!("{}/compressedDepth", topics.depth),
        );
        // [raw colour, compressed colour, raw depth, compressed depth]
        let mut stamps: [Vec<(f64, f64)>; 4] = Default::default();
        // The message type on each of the four topics, when its schema names one.
        let mut kinds: [Option<String>; 4] = Default::default();
        let mut camera_frame: Option<String> = None;
        let mut info: Option<Result<CameraInfo, DatasetError>> = None;
        let mut poses: Vec<(f64, Isometry3<f64>)> = Vec::new();
        let mut odometry_child: Option<String> = None;
        let mut tf = crate::tf::TfTree::default();
        let mut left_out = LeftOut::default();
        let mut seen: BTreeMap<String, String> = BTreeMap::new();
        while let Some(m) = reader.next()? {
            let topic: &str = &m.topic;
            seen.entry(topic.to_string())
                .or_insert_with(|| m.schema.to_string());
            let slot = [&topics.rgb, &rgb_c, &topics.depth, &depth_c]
                .iter()
                .position(|t| t.as_str() == topic);
            let log_s = m.log_time_ns as f64 * 1e-9;
            if let Some(k) = slot {
                if !m.schema.is_empty() && &*m.schema != IMAGE && &*m.schema != COMPRESSED {
                    return Err(bad(
                        path,
                        format!(
                            "topic {topic} holds {}, not {IMAGE} or {COMPRESSED}",
                            m.schema
                        ),
                    ));
                }
                if !m.schema.is_empty() {
                    kinds[k].get_or_insert_with(|| m.schema.to_string());
                }
                let h: ImageStamp = decode_bounded(path, topic, &m.data)?;
                if k < 2 && camera_frame.is_none() && !h.header.frame_id.is_empty() {
                    camera_frame = Some(h.header.frame_id.clone());
                }
                stamps[k].push((h.header.stamp.seconds(), log_s));
            } else if topic == topics.info {
                if info.is_none() {
                    info = Some(decode_bounded(path, topic, &m.data));
                }
            } else if topic == "/tf" || topic == "/tf_static" {
                let msg: TfMessage = decode_bounded(path, topic, &m.data)?;
                for t in msg.transforms {
                    let p = t.transform;
                    let stamp = t.header.stamp.seconds();
                    match isometry(
                        [p.translation.x, p.translation.y, p.translation.z],
                        &p.rotation,
                    ) {
                        Ok(pose) => tf.add(
                            &t.header.frame_id,
                            &t.child_frame_id,
                            stamp,
                            pose,
                            topic == "/tf_static",
                        ),
                        Err(why) => left_out.note(
                            topic,
                            stamp,
                            &format!("{} -> {}", t.header.frame_id, t.child_frame_id),
                            why,
                        ),
                    }
                }
            } else if Some(topic) == topics.pose.as_deref() {
                let (stamp, frame, pose) = match &*m.schema {
                    "nav_msgs/msg/Odometry" => {
                        let o: OdometryPose = decode_bounded(path, topic, &m.data)?;
                        odometry_child.get_or_insert(o.child_frame_id.clone());
                        let p = o.pose.position;
                        (o.header.stamp.seconds(), o.child_frame_id, isometry([p.x, p.y, p.z], &o.pose.orientation))
                    }
                    "geometry_msgs/msg/PoseStamped" | "" => {
                        let o: PoseStamped = decode_bounded(path, topic, &m.data)?;
                        let p = o.pose.position;
                        (o.header.stamp.seconds(), o.header.frame_id, isometry([p.x, p.y, p.z], &o.pose.orientation))
                    }
                    other => {
                        return Err(bad(
                            path,
                            format!("topic {topic} holds {other}: poses are read from geometry_msgs/msg/PoseStamped or nav_msgs/msg/Odometry"),
                        ))
                    }
                };
                match pose {
                    Ok(pose) => poses.push((stamp, pose)),
                    Err(why) => left_out.note(topic, stamp, &frame, why),
                }
            }
        }
        tf.seal();
        let listing = || {
            seen.iter()
                .map(|(t, s)| format!("{t} ({s})"))
                .collect::<Vec<_>>()
                .join(", ")
        };
        let pick = |raw: usize, what: &str, topic: &str, sibling: &str| {
            if !stamps[raw].is_empty() {
                Ok((raw, topic.to_string()))
            } else if !stamps[raw + 1].is_empty() {
                Ok((raw + 1, sibling.to_string()))
            } else {
                Err(bad(
                    path,
                    format!(
                        "no {what} images on {topic} or {sibling}; the bag has: {}",
                        listing()
                    ),
                ))
            }
        };
        let (rgb_k, rgb_topic) = pick(0, "colour", &topics.rgb, &rgb_c)?;
        let (depth_k, depth_topic) = pick(2, "depth", &topics.depth, &depth_c)?;
        let mut warnings = std::mem::take(&mut reader.warnings);
        warnings.extend(left_out.warnings());
        let mut streams = [Stamps::default(), Stamps::default()];
        // A driver that leaves header stamps zero: receive times for both streams (and for the
        // pose look-ups), so the two are never mixed.
        let all_zero = [rgb_k, depth_k]
            .iter()
            .any(|&k| stamps[k].iter().all(|(h, _)| *h == 0.0));
        if all_zero {
            warnings.push(format!(
                "{rgb_topic} or {depth_topic}: every header stamp is zero; the bag's receive times are used to pair the frames and to look up their poses"
            ));
        }
        for (s, k) in streams.iter_mut().zip([rgb_k, depth_k]) {
            s.list = stamps[k]
                .iter()
                .enumerate()
                .map(|(i, (h, l))| (if all_zero { *l } else { *h }, i))
                .collect();
            s.list.sort_by(|a, b| a.0.total_cmp(&b.0));
        }
        let compressed = [
            kinds[rgb_k]
                .as_deref()
                .map_or(rgb_k % 2 == 1, |s| s == COMPRESSED),
            kinds[depth_k]
                .as_deref()
                .map_or(depth_k % 2 == 1, |s| s == COMPRESSED),
        ];
        let (intrinsics, camera_problem) = match info {
            None => (None, Some(format!("no CameraInfo on {}", topics.info))),
            Some(Err(e)) => (None, Some(e.to_string())),
            Some(Ok(i)) => match (camera(path, &i), &camera_frame) {
                // A CameraInfo of another camera (the depth camera's, another lens) would build the
                // map with the wrong intrinsics, silently: refused, naming both frames (unless it
                // is of the frame the caller named as the camera's with --camera-frame).
                (Ok(_), Some(images))
                    if !i.header.frame_id.is_empty()
                        && i.header.frame_id.trim_start_matches('/')
                            != images.trim_start_matches('/')
                        && topics.camera_frame.as_deref().map(|f| f.trim_start_matches('/'))
                            != Some(i.header.frame_id.trim_start_matches('/')) =>
                {
                    (
                        None,
                        Some(format!(
                            "the CameraInfo on {} is of frame {} but the colour images on {rgb_topic} are of {images}: it describes another camera; name the colour camera's CameraInfo with --info-topic",
                            topics.info, i.header.frame_id
                        )),
                    )
                }
                (Ok(k), _) => (Some(k), None),
                (Err(e), _) => (None, Some(e.to_string())),
            },
        };
        for (child, parents) in tf.several_parents() {
            let used = tf
                .parent_towards(&child, &topics.map_frame)
                .unwrap_or_default()
                .to_string();
            let named: Vec<String> = parents
                .iter()
                .map(|(p, n)| format!("{p} ({n} transforms)"))
                .collect();
            warnings.push(format!(
                "TF: {child} is published under {} parents, {}, by different publishers (odometry and another localizer, say); poses follow {used}'s chain to {}, never a mix",
                parents.len(),
                named.join(" and "),
                topics.map_frame
            ));
        }
        // (Poses from a PoseStamped topic are the camera's as they are: TF is not asked then.)
        let poses_from_tf = topics.pose.is_none() || odometry_child.is_some();
        if let Some(given) = topics.camera_frame.as_ref().filter(|_| poses_from_tf) {
            let optical = |f: &str| f.contains("optical");
            if !optical(given) {
                // A body frame (x forward) whose child is the optical frame (z forward): poses of
                // it would turn the map on its side.
                let mut below = Vec::new();
                let mut todo = tf.children(given);
                while let Some(f) = todo.pop() {
                    if below.len() < 64 {
                        todo.extend(tf.children(&f));
                        below.push(f);
                    }
                }
                let mut optical_below: Vec<&String> = below.iter().filter(|f| optical(f)).collect();
                optical_below.sort_by_key(|f| Some(f.as_str()) != camera_frame.as_deref());
                if let Some(child) = optical_below.first() {
                    return Err(bad(
                        path,
                        format!(
                            "--camera-frame {given} is a body frame in TF (x forward), not an optical one (z forward, x right, y down, as images are): its optical child is {child}{}; give --camera-frame {child}, or leave the flag out",
                            if Some(child.as_str()) == camera_frame.as_deref() { ", which the colour images name" } else { "" }
                        ),
                    ));
                }
            }
        }
        if let (Some(given), Some(images)) = (&topics.camera_frame, &camera_frame) {
            if given.trim_start_matches('/') != images.trim_start_matches('/') {
                warnings.push(format!(
                    "the colour images' frame_id is {images} but poses are looked up for --camera-frame {given}: the map's poses must be those of the images' optical frame"
                ));
            }
        }
        let camera_frame = topics
            .camera_frame
            .clone()
            .or(camera_frame)
            .unwrap_or_else(|| "camera_color_optical_frame".into());
        let trajectory = (!poses.is_empty()).then(|| crate::tum::Trajectory::from_poses(poses));
        if topics.pose.is_some() && trajectory.is_none() {
            let topic = topics.pose.as_deref().unwrap_or("");
            // Every pose there left out: say why, rather than that the topic is empty.
            if let Some((n, t, frame, why)) = left_out.0.get(topic) {
                return Err(bad(
                    path,
                    format!("no usable poses on {topic}: all {n} are left out (the first at {t:.6} s, {frame}: {why})"),
                ));
            }
            return Err(bad(
                path,
                format!("no poses on {topic}; the bag has: {}", listing()),
            ));
        }
        let mut pose_problem = None;
        let mut pose_at = |t: f64| -> Option<Isometry3<f64>> {
            let r = match (&trajectory, &odometry_child) {
                (Some(traj), None) => traj.at(t).ok_or_else(|| {
                    format!(
                        "no pose on {} at {t:.6} s",
                        topics.pose.as_deref().unwrap_or("")
                    )
                }),
                (Some(traj), Some(child)) => traj
                    .at(t)
                    .ok_or_else(|| format!("no odometry at {t:.6} s"))
                    .and_then(|p| Ok(p * tf.lookup(child, &camera_frame, t)?)),
                (None, _) if tf.is_empty() => Err(format!(
                    "no poses: the bag has no /tf and no --pose-topic was given; the bag has: {}",
                    listing()
                )),
                (None, _) => tf.lookup(&topics.map_frame, &camera_frame, t),
            };
            r.map_err(|e| {
                pose_problem.get_or_insert(e);
            })
            .ok()
        };
        let frames: Vec<_> = streams[0]
            .list
            .iter()
            .filter_map(|&(t, c)| {
                let d = nearest(&streams[1].list, t)?;
                Some((t, c, streams[1].list[d].1, pose_at(t)))
            })
            .collect();
        if frames.is_empty() {
            return Err(bad(
                path,
                format!("no colour image on {rgb_topic} has a depth image on {depth_topic} within {MAX_PAIR_GAP_S} s"),
            ));
        }
        let mut last_use: [HashMap<usize, usize>; 2] = Default::default();
        for (f, (_, c, d, _)) in frames.iter().enumerate() {
            last_use[0].insert(*c, f);
            last_use[1].insert(*d, f);
        }
        Ok(Self {
            path: path.to_path_buf(),
            files,
            intrinsics,
            camera_problem,
            rgb_topic,
            depth_topic,
            frames,
            pose_problem,
            warnings,
            depth_units_per_m: 1000.0,
            cursor: std::sync::Mutex::new(None),
            last_use,
            compressed,
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

    /// `world_from_camera` of frame `i` (optical frame), from the pose topic or TF.
    pub fn ground_truth(&self, i: usize) -> Option<Isometry3<f64>> {
        self.frames[i].3
    }

    /// The colour and depth messages of frame `i`, streaming forward from the last frame read (a
    /// frame before it starts the stream again).
    fn messages(&self, i: usize) -> Result<[Raw; 2], DatasetError> {
        let (_, c, d, _) = self.frames[i];
        let want = [c, d];
        let mut guard = self.cursor.lock().unwrap_or_else(|p| p.into_inner());
        let restart = guard.as_ref().is_none_or(|cur| {
            (0..2).any(|k| want[k] < cur.seen[k] && !cur.kept[k].contains_key(&want[k]))
        });
        if restart {
            *guard = Some(Cursor {
                reader: MessageReader::new(self.files.clone()),
                seen: [0, 0],
                kept: Default::default(),
            });
        }
        let cur = guard.as_mut().expect("set above");
        while (0..2).any(|k| !cur.kept[k].contains_key(&want[k])) {
            let Some(m) = cur.reader.next()? else {
                return Err(bad(
                    &self.path,
                    format!("frame {i}: its messages were not found on a second read (the bag changed?)"),
                ));
            };
            let k = if *m.topic == *self.rgb_topic {
                0
            } else if *m.topic == *self.depth_topic {
                1
            } else {
                continue;
            };
            let ordinal = cur.seen[k];
            cur.seen[k] += 1;
            // Kept while this frame or a later one uses it.
            if self.last_use[k].get(&ordinal).is_some_and(|&f| f >= i) {
                cur.kept[k].insert(ordinal, (m.schema, m.data));
            }
        }
        let out = [
            cur.kept[0].get(&want[0]).cloned().expect("read above"),
            cur.kept[1].get(&want[1]).cloned().expect("read above"),
        ];
        // Keep only what frames after this one use.
        for k in 0..2 {
            let last = &self.last_use[k];
            cur.kept[k].retain(|o, _| last.get(o).is_some_and(|&f| f > i));
        }
        Ok(out)
    }

    /// Decode frame `i`: colour and depth in metres (0 = missing). Errors name the topic, the
    /// encoding or format, and the frame.
    pub fn load(&self, i: usize) -> Result<(RgbImage, DepthMap), DatasetError> {
        let [(_, c), (_, d)] = self.messages(i)?;
        let rgb = if self.compressed[0] {
            let m: CompressedImage = decode_bounded(&self.path, &self.rgb_topic, &c)?;
            compressed_rgb(&self.path, &self.rgb_topic, &m)?
        } else {
            let m: Image = decode_bounded(&self.path, &self.rgb_topic, &c)?;
            rgb_of(&self.path, &m)?
        };
        let depth = if self.compressed[1] {
            let m: CompressedImage = decode_bounded(&self.path, &self.depth_topic, &d)?;
            compressed_depth(&self.path, &self.depth_topic, &m, self.depth_units_per_m)?
        } else {
            let m: Image = decode_bounded(&self.path, &self.depth_topic, &d)?;
            depth_of(&self.path, &m, self.depth_units_per_m)?
        };
        if (depth.width, depth.height) != (rgb.width, rgb.height) {
            return Err(bad(
                &self.path,
                format!(
                    "frame {i}: depth is {}x{}, colour {}x{}: the depth topic must be aligned to the colour camera",
                    depth.width, depth.height, rgb.width, rgb.height
                ),
            ));
        }
        Ok((rgb, depth))
    }
}

/// A `CompressedImage` colour frame (JPEG or PNG, as image_transport's `compressed` plugin writes:
/// a whole image file whose colours a decoder reads the right way round).
fn compressed_rgb(path: &Path, topic: &str, m: &CompressedImage) -> Result<RgbImage, DatasetError> {
    if m.data.is_empty() {
        return Err(bad(
            path,
            format!("topic {topic}: an empty compressed image"),
        ));
    }
    let img = image::load_from_memory(&m.data)
        .map_err(|e| {
            bad(
                path,
                format!("topic {topic}: cannot decode the {:?} image: {e}", m.format),
            )
        })?
        .to_rgb8();
    let (w, h) = img.dimensions();
    Ok(RgbImage {
        width: w,
        height: h,
        data: img.into_raw(),
    })
}

/// A `compressedDepth` depth frame: a 12-byte header (format, two quantisation parameters used only
/// for 32FC1) and a 16-bit PNG in the sensor's units (`units_per_m`, REP 118's millimetres by default).
fn compressed_depth(
    path: &Path,
    topic: &str,
    m: &CompressedImage,
    units_per_m: f64,
) -> Result<DepthMap, DatasetError> {
    if m.format.contains("rvl") {
        return Err(bad(
            path,
            format!(
                "topic {topic}: compressedDepth in RVL ({:?}) is not read; record the png form",
                m.format
            ),
        ));
    }
    if m.format.starts_with("32FC1") {
        return Err(bad(
            path,
            format!("topic {topic}: compressedDepth of 32FC1 (quantised inverse depth) is not read; record 16UC1"),
        ));
    }
    let png = if m.format.contains("compressedDepth")
        && m.data.len() > 12
        && !m.data.starts_with(b"\x89PNG")
    {
        &m.data[12..]
    } else {
        &m.data[..]
    };
    let img = image::load_from_memory_with_format(png, image::ImageFormat::Png).map_err(|e| {
        bad(
            path,
            format!(
                "topic {topic}: cannot decode the depth PNG ({:?}): {e}",
                m.format
            ),
        )
    })?;
    let image::DynamicImage::ImageLuma16(d) = img else {
        return Err(bad(
            path,
            format!(
                "topic {topic}: the depth PNG is {:?}, not 16-bit single-channel",
                img.color()
            ),
        ));
    };
    let (w, h) = d.dimensions();
    let scale = (1.0 / units_per_m) as f32;
    Ok(DepthMap {
        width: w,
        height: h,
        data: d.into_raw().into_iter().map(|v| v as f32 * scale).collect(),
    })
}

/// Only the header of an Image (what pairing needs), without copying the pixels.
#[derive(Deserialize)]
struct ImageStamp {
    header: Header,
}

fn camera(path: &Path, i: &CameraInfo) -> Result<Intrinsics, DatasetError> {
    if i.k.iter().all(|v| *v == 0.0) {
        return Err(bad(
            path,
            "camera info: K is all zero (an uncalibrated camera); give --intrinsics fx,fy,cx,cy",
        ));
    }
    let mut k = Intrinsics {
        fx: i.k[0],
        fy: i.k[4],
        cx: i.k[2],
        cy: i.k[5],
        width: i.width,
        height: i.height,
        ..Intrinsics::hpointloc()
    };
    let d = &i.d;
    match i.distortion_model.as_str() {
        _ if d.iter().all(|v| *v == 0.0) => {}
        "plumb_bob" | "rational_polynomial" | "" if d.len() >= 5 && d[5..].iter().all(|v| *v == 0.0) => {
            k.distortion.copy_from_slice(&d[..5]);
        }
        "plumb_bob" if d.len() == 4 => k.distortion[..4].copy_from_slice(d),
        m => {
            return Err(bad(
                path,
                format!("camera info: distortion model {m:?} with {} coefficients {d:?} is not read (plumb_bob k1 k2 p1 p2 k3 is); give --intrinsics fx,fy,cx,cy[,k1,k2,p1,p2,k3] or record rectified images", d.len()),
            ))
        }
    }
    k.validate()
        .map_err(|e| bad(path, format!("camera info: {e}; give --intrinsics")))?;
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
    write_bag_with(path, frames, k, topics, Some(mcap::Compression::Zstd))
}

/// [`write_bag`] with the chunks compressed by `compression` (zstd, lz4 or none).
pub fn write_bag_with(
    path: &Path,
    frames: &[BagFrame<'_>],
    k: &Intrinsics,
    topics: &Topics,
    compression: Option<mcap::Compression>,
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
        .compression(compression)
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
        let info = CameraInfo::of(k, header.clone());
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
        // lz4 chunks (MCAP allows them) read the same.
        let lz4 = dir.path().join("lz4.mcap");
        write_bag_with(&lz4, &frames, &k, &topics, Some(mcap::Compression::Lz4)).unwrap();
        let b = Bag::open(&lz4, &topics).unwrap();
        for (i, want_rgb) in rgbs.iter().enumerate() {
            assert_eq!(b.load(i).unwrap().0.data, want_rgb.data);
        }
        // The same frame twice, and frames out of order: the stream starts again where needed.
        for i in [1, 1, 0, 2, 2, 1] {
            let (rgb, _) = bag.load(i).unwrap();
            assert_eq!(rgb.data, rgbs[i].data, "frame {i}");
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
