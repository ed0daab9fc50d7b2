//! Writing ROS 2 bags as `ros2 bag record` leaves them: a folder holding one MCAP file (`ros2`
//! profile, zstd chunks; each channel's schema the `ros2msg` definition of its type, each message CDR
//! little endian) and a `metadata.yaml` in rosbag2's format (version 5: topics with their type,
//! serialization format and message count, the file list, start and duration), so `ros2 bag play`,
//! the Python `rosbags` package and Foxglove open it. The folder is written under a temporary name
//! and renamed into place when finished: an interrupted run leaves no half bag under the name.

use crate::write_guard::{FirstError, GuardedWriter};
use std::collections::BTreeMap;
use std::io::Write;
use std::path::{Path, PathBuf};

use serde::{Serialize, Serializer};

use crate::bag::{Header, Pose};
use crate::DatasetError;

/// The message types a bag can hold, each with its `ros2msg` definition.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub enum MessageType {
    /// sensor_msgs/msg/CompressedImage.
    CompressedImage,
    /// sensor_msgs/msg/CameraInfo.
    CameraInfo,
    /// geometry_msgs/msg/PoseStamped.
    PoseStamped,
    /// geometry_msgs/msg/PoseWithCovarianceStamped.
    PoseWithCovarianceStamped,
    /// tf2_msgs/msg/TFMessage.
    TfMessage,
    /// diagnostic_msgs/msg/DiagnosticArray.
    DiagnosticArray,
}

const SEPARATOR: &str =
    "================================================================================\n";
const HEADER: &str = "MSG: std_msgs/Header\nbuiltin_interfaces/Time stamp\nstring frame_id\n";
const TIME: &str = "MSG: builtin_interfaces/Time\nint32 sec\nuint32 nanosec\n";
const POSE: &str = "MSG: geometry_msgs/Pose\nPoint position\nQuaternion orientation\n";
const POINT: &str = "MSG: geometry_msgs/Point\nfloat64 x\nfloat64 y\nfloat64 z\n";
const QUATERNION: &str =
    "MSG: geometry_msgs/Quaternion\nfloat64 x\nfloat64 y\nfloat64 z\nfloat64 w\n";

impl MessageType {
    /// The ROS type name (`pkg/msg/Name`).
    pub fn name(self) -> &'static str {
        match self {
            Self::CompressedImage => "sensor_msgs/msg/CompressedImage",
            Self::CameraInfo => "sensor_msgs/msg/CameraInfo",
            Self::PoseStamped => "geometry_msgs/msg/PoseStamped",
            Self::PoseWithCovarianceStamped => "geometry_msgs/msg/PoseWithCovarianceStamped",
            Self::TfMessage => "tf2_msgs/msg/TFMessage",
            Self::DiagnosticArray => "diagnostic_msgs/msg/DiagnosticArray",
        }
    }

    /// The `ros2msg` schema: the type's fields, then each type it uses after a separator line.
    pub fn definition(self) -> String {
        let (fields, uses): (&str, &[&str]) = match self {
            Self::CompressedImage => (
                "std_msgs/Header header\nstring format\nuint8[] data\n",
                &[HEADER, TIME],
            ),
            Self::CameraInfo => (
                "std_msgs/Header header\nuint32 height\nuint32 width\nstring distortion_model\nfloat64[] d\nfloat64[9] k\nfloat64[9] r\nfloat64[12] p\nuint32 binning_x\nuint32 binning_y\nsensor_msgs/RegionOfInterest roi\n",
                &[
                    HEADER,
                    TIME,
                    "MSG: sensor_msgs/RegionOfInterest\nuint32 x_offset\nuint32 y_offset\nuint32 height\nuint32 width\nbool do_rectify\n",
                ],
            ),
            Self::PoseStamped => (
                "std_msgs/Header header\ngeometry_msgs/Pose pose\n",
                &[HEADER, TIME, POSE, POINT, QUATERNION],
            ),
            Self::PoseWithCovarianceStamped => (
                "std_msgs/Header header\ngeometry_msgs/PoseWithCovariance pose\n",
                &[
                    HEADER,
                    TIME,
                    "MSG: geometry_msgs/PoseWithCovariance\nPose pose\nfloat64[36] covariance\n",
                    POSE,
                    POINT,
                    QUATERNION,
                ],
            ),
            Self::TfMessage => (
                "geometry_msgs/TransformStamped[] transforms\n",
                &[
                    "MSG: geometry_msgs/TransformStamped\nstd_msgs/Header header\nstring child_frame_id\nTransform transform\n",
                    HEADER,
                    TIME,
                    "MSG: geometry_msgs/Transform\nVector3 translation\nQuaternion rotation\n",
                    "MSG: geometry_msgs/Vector3\nfloat64 x\nfloat64 y\nfloat64 z\n",
                    QUATERNION,
                ],
            ),
            Self::DiagnosticArray => (
                "std_msgs/Header header\ndiagnostic_msgs/DiagnosticStatus[] status\n",
                &[
                    HEADER,
                    TIME,
                    "MSG: diagnostic_msgs/DiagnosticStatus\nbyte OK=0\nbyte WARN=1\nbyte ERROR=2\nbyte STALE=3\nbyte level\nstring name\nstring message\nstring hardware_id\nKeyValue[] values\n",
                    "MSG: diagnostic_msgs/KeyValue\nstring key\nstring value\n",
                ],
            ),
        };
        let mut text = fields.to_string();
        for u in uses {
            text.push_str(SEPARATOR);
            text.push_str(u);
        }
        text
    }
}

/// A 6x6 covariance, row-major (a `float64[36]`: serialized as 36 values without a length).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Covariance(pub [f64; 36]);

impl Serialize for Covariance {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        use serde::ser::SerializeTuple;
        let mut t = s.serialize_tuple(36)?;
        for v in &self.0 {
            t.serialize_element(v)?;
        }
        t.end()
    }
}

/// geometry_msgs/msg/PoseWithCovariance.
#[derive(Debug, Clone, Serialize)]
pub struct PoseWithCovariance {
    /// The pose.
    pub pose: Pose,
    /// Its covariance: x, y, z, rotation about x, y, z (fixed axes), m² and rad².
    pub covariance: Covariance,
}

/// geometry_msgs/msg/PoseWithCovarianceStamped.
#[derive(Debug, Clone, Serialize)]
pub struct PoseWithCovarianceStamped {
    /// Stamp and the frame of the pose.
    pub header: Header,
    /// Pose and covariance.
    pub pose: PoseWithCovariance,
}

/// diagnostic_msgs/msg/KeyValue.
#[derive(Debug, Clone, Serialize)]
pub struct KeyValue {
    /// Key.
    pub key: String,
    /// Value.
    pub value: String,
}

/// diagnostic_msgs/msg/DiagnosticStatus.
#[derive(Debug, Clone, Serialize)]
pub struct DiagnosticStatus {
    /// OK 0, WARN 1, ERROR 2, STALE 3.
    pub level: u8,
    /// The part reported on.
    pub name: String,
    /// One line of state.
    pub message: String,
    /// The hardware (or service) it concerns.
    pub hardware_id: String,
    /// Figures.
    pub values: Vec<KeyValue>,
}

/// diagnostic_msgs/msg/DiagnosticArray.
#[derive(Debug, Clone, Serialize)]
pub struct DiagnosticArray {
    /// Stamp.
    pub header: Header,
    /// Statuses.
    pub status: Vec<DiagnosticStatus>,
}

struct Topic {
    channel: u16,
    kind: MessageType,
    count: u64,
}

/// A ROS 2 bag being written; [`BagWriter::finish`] completes it.
pub struct BagWriter {
    dir: PathBuf,
    tmp: PathBuf,
    file_name: String,
    /// Open until [`BagWriter::finish`] takes it.
    writer: Option<mcap::Writer<GuardedWriter<std::io::BufWriter<std::fs::File>>>>,
    /// The file's first failed write (a full disk): the bag is abandoned at it.
    failed: FirstError,
    schemas: BTreeMap<MessageType, u16>,
    topics: BTreeMap<String, Topic>,
    first_ns: Option<u64>,
    last_ns: u64,
    sequence: u32,
}

fn io(path: &Path) -> impl Fn(std::io::Error) -> DatasetError + '_ {
    move |source| DatasetError::Io {
        path: path.to_path_buf(),
        source,
    }
}

fn layout(path: &Path, problem: String) -> DatasetError {
    DatasetError::Layout {
        path: path.to_path_buf(),
        problem,
    }
}

impl BagWriter {
    /// Start the bag folder `dir` (which must not exist yet: a bag is never written over).
    ///
    /// Errors: `dir` exists, or its parent cannot be written.
    pub fn create(dir: &Path) -> Result<Self, DatasetError> {
        if dir.exists() {
            return Err(layout(
                dir,
                "already exists: a ROS 2 bag is a new folder (remove it, or give another name)"
                    .into(),
            ));
        }
        let name = dir
            .file_name()
            .and_then(|n| n.to_str())
            .filter(|n| !n.is_empty())
            .ok_or_else(|| layout(dir, "a bag folder needs a name".into()))?
            .to_string();
        let tmp = dir.with_file_name(format!(".{name}.partial-{}", std::process::id()));
        // A stale folder of an earlier run under the same pid (containers repeat pids) goes first.
        let _ = std::fs::remove_dir_all(&tmp);
        std::fs::create_dir_all(&tmp).map_err(io(&tmp))?;
        let file_name = format!("{name}_0.mcap");
        let path = tmp.join(&file_name);
        let file = std::fs::File::create(&path).map_err(io(&path))?;
        let (file, failed) = GuardedWriter::new(std::io::BufWriter::new(file));
        let writer = mcap::WriteOptions::new()
            .profile("ros2")
            .compression(Some(mcap::Compression::Zstd))
            .create(file)
            .map_err(|e| layout(&path, format!("writing MCAP: {e}")))?;
        Ok(Self {
            dir: dir.to_path_buf(),
            tmp,
            file_name,
            writer: Some(writer),
            failed,
            schemas: BTreeMap::new(),
            topics: BTreeMap::new(),
            first_ns: None,
            last_ns: 0,
            sequence: 0,
        })
    }

    fn writer_mut(
        &mut self,
    ) -> &mut mcap::Writer<GuardedWriter<std::io::BufWriter<std::fs::File>>> {
        self.writer.as_mut().expect("open until finished")
    }

    /// Write `message` of type `kind` on `topic`, received at `stamp_ns` (ns since the epoch of
    /// the recording's clock). A topic keeps the type of its first message.
    ///
    /// Errors: the topic had another type, or the file could not be written.
    pub fn write<T: Serialize>(
        &mut self,
        topic: &str,
        kind: MessageType,
        stamp_ns: u64,
        message: &T,
    ) -> Result<(), DatasetError> {
        let path = self.tmp.join(&self.file_name);
        let mcap_err = |e: mcap::McapError| layout(&path, format!("writing MCAP: {e}"));
        let channel = match self.topics.get(topic) {
            Some(t) if t.kind != kind => {
                return Err(layout(
                    &self.dir,
                    format!("topic {topic} holds {}, not {}", t.kind.name(), kind.name()),
                ))
            }
            Some(t) => t.channel,
            None => {
                let schema = match self.schemas.get(&kind) {
                    Some(s) => *s,
                    None => {
                        let s = self
                            .writer_mut()
                            .add_schema(kind.name(), "ros2msg", kind.definition().as_bytes())
                            .map_err(mcap_err)?;
                        self.schemas.insert(kind, s);
                        s
                    }
                };
                let channel = self
                    .writer_mut()
                    .add_channel(schema, topic, "cdr", &BTreeMap::new())
                    .map_err(mcap_err)?;
                self.topics.insert(
                    topic.to_string(),
                    Topic {
                        channel,
                        kind,
                        count: 0,
                    },
                );
                channel
            }
        };
        let data = cdr::serialize::<_, _, cdr::CdrLe>(message, cdr::Infinite)
            .map_err(|e| layout(&path, format!("CDR encoding of a {}: {e}", kind.name())))?;
        let header = mcap::records::MessageHeader {
            channel_id: channel,
            sequence: self.sequence,
            log_time: stamp_ns,
            publish_time: stamp_ns,
        };
        self.writer_mut()
            .write_to_known_channel(&header, &data)
            .map_err(mcap_err)?;
        if let Some(e) = self.failed.get() {
            return Err(layout(&path, format!("writing MCAP: {e}")));
        }
        self.sequence = self.sequence.wrapping_add(1);
        if let Some(t) = self.topics.get_mut(topic) {
            t.count += 1;
        }
        self.first_ns = Some(self.first_ns.map_or(stamp_ns, |f| f.min(stamp_ns)));
        self.last_ns = self.last_ns.max(stamp_ns);
        Ok(())
    }

    /// Close the MCAP file, write `metadata.yaml` and move the folder into place; returns it.
    pub fn finish(mut self) -> Result<PathBuf, DatasetError> {
        let path = self.tmp.join(&self.file_name);
        let mut writer = self.writer.take().expect("open until finished");
        writer
            .finish()
            .map_err(|e| layout(&path, format!("writing MCAP: {e}")))?;
        // mcap's finish leaves the end of the file buffered: flushed and synced through the guard,
        // so a disk that fills at the very end is seen.
        let mut file = writer.into_inner();
        file.run(|b| b.flush().and_then(|()| b.get_ref().sync_all()));
        if let Some(e) = self.failed.get() {
            return Err(layout(&path, format!("writing MCAP: {e}")));
        }
        let start = self.first_ns.unwrap_or(0);
        let duration = self.last_ns.saturating_sub(start);
        let total: u64 = self.topics.values().map(|t| t.count).sum();
        let topics: Vec<serde_yaml::Value> = self
            .topics
            .iter()
            .map(|(name, t)| {
                serde_yaml::to_value(metadata_yaml::topic(name, t.kind.name(), t.count))
                    .expect("plain YAML")
            })
            .collect();
        let metadata = serde_yaml::to_value(metadata_yaml::metadata(
            start,
            duration,
            total,
            &self.file_name,
            topics,
        ))
        .expect("plain YAML");
        let text = serde_yaml::to_string(&metadata).expect("plain YAML");
        let meta = self.tmp.join("metadata.yaml");
        std::fs::write(&meta, text).map_err(io(&meta))?;
        std::fs::rename(&self.tmp, &self.dir).map_err(io(&self.dir))?;
        Ok(self.dir.clone())
    }
}

impl Drop for BagWriter {
    /// A bag not finished (its run failed: a full disk, an error elsewhere) leaves nothing behind:
    /// its hidden partial folder is removed. After [`BagWriter::finish`] the folder has its name
    /// already and nothing is removed.
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.tmp);
    }
}

/// rosbag2's `metadata.yaml` (version 5) as YAML values.
mod metadata_yaml {
    use serde_yaml::{Mapping, Value};

    fn map(entries: Vec<(&str, Value)>) -> Value {
        Value::Mapping(
            entries
                .into_iter()
                .map(|(k, v)| (Value::from(k), v))
                .collect::<Mapping>(),
        )
    }

    fn nanos(key: &str, ns: u64) -> Value {
        map(vec![(key, Value::from(ns))])
    }

    pub fn topic(name: &str, kind: &str, count: u64) -> Value {
        map(vec![
            (
                "topic_metadata",
                map(vec![
                    ("name", Value::from(name)),
                    ("type", Value::from(kind)),
                    ("serialization_format", Value::from("cdr")),
                    ("offered_qos_profiles", Value::from("")),
                ]),
            ),
            ("message_count", Value::from(count)),
        ])
    }

    pub fn metadata(
        start: u64,
        duration: u64,
        total: u64,
        file: &str,
        topics: Vec<Value>,
    ) -> Value {
        map(vec![(
            "rosbag2_bagfile_information",
            map(vec![
                ("version", Value::from(5)),
                ("storage_identifier", Value::from("mcap")),
                ("duration", nanos("nanoseconds", duration)),
                ("starting_time", nanos("nanoseconds_since_epoch", start)),
                ("message_count", Value::from(total)),
                ("topics_with_message_count", Value::Sequence(topics)),
                ("compression_format", Value::from("")),
                ("compression_mode", Value::from("")),
                (
                    "relative_file_paths",
                    Value::Sequence(vec![Value::from(file)]),
                ),
                (
                    "files",
                    Value::Sequence(vec![map(vec![
                        ("path", Value::from(file)),
                        ("starting_time", nanos("nanoseconds_since_epoch", start)),
                        ("duration", nanos("nanoseconds", duration)),
                        ("message_count", Value::from(total)),
                    ])]),
                ),
            ]),
        )])
    }
}
