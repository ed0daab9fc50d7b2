//! What pntr shows in Foxglove: the frames it localizes, the poses it answers (with covariance,
//! status and reason), the ground truth when there is one, and the map's cameras, with Foxglove's
//! own schemas, written to an MCAP file ([`Recording`]: `pntr replay --record`, `pntr eval
//! --record`) or streamed live over the Foxglove WebSocket protocol ([`Live`]: `pntr-server
//! --foxglove`). Both go through the Foxglove SDK, one [`View`] over one SDK context, so a file and
//! the live view hold the same channels.
//!
//! Everything is drawn in ROS conventions whatever the map's own axes, because that is what
//! Foxglove's 3D panel expects: the world frame `map` is z-up (REP 103) and the query camera's frame
//! `camera_optical` has optical axes (x right, y down, z forward), so the image lies in the camera's
//! frustum at the answered pose. Topics ([`topics`]):
//! - `/pntr/camera/image` (foxglove.CompressedImage, PNG) and `/pntr/camera/calibration`
//!   (foxglove.CameraCalibration): the frame as it was sent, in frame `camera_optical`;
//! - `/tf` (foxglove.FrameTransforms): `map -> camera_optical` for every LOCALIZED answer;
//! - `/pntr/pose` (foxglove.PoseInFrame): the answered pose, LOCALIZED frames only;
//! - `/pntr/ground_truth` (foxglove.PoseInFrame): the true pose, when the caller knows it;
//! - `/pntr/answer` (JSON, schema `pntr.Answer`): status, reason, confidence, inliers, mode, map and
//!   its version,
//!   matched image, the pose and its 6x6 covariance (ROS order, in the `map` frame), and the error
//!   against the ground truth;
//! - `/pntr/map/cameras` (foxglove.PosesInFrame): the poses of the map's images, in frame `map`.
//!
//! Images are encoded only while something listens (a file always does; a live view only while a
//! client subscribes), so an idle `--foxglove` costs the server nothing per frame.

use std::fs::File;
use std::io::{BufWriter, Write};
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use foxglove::messages::{
    CameraCalibration, CompressedImage, FrameTransform, FrameTransforms, Pose, PoseInFrame,
    PosesInFrame, Quaternion, Timestamp, Vector3,
};
use foxglove::{Channel, Context, McapWriterHandle, RawChannel, Schema, WebSocketServerHandle};
use nalgebra::Isometry3;
use pntr_core::{Intrinsics, RgbImage};
use pntr_dataset::write_guard::{FirstError, GuardedWriter};

/// The frame id of the world (z-up, REP 103).
pub const FRAME_MAP: &str = "map";
/// The frame id of the query camera (optical axes).
pub const FRAME_CAMERA: &str = "camera_optical";

/// The topics a [`View`] writes.
pub mod topics {
    /// foxglove.CompressedImage of each frame.
    pub const IMAGE: &str = "/pntr/camera/image";
    /// foxglove.CameraCalibration of each frame's camera.
    pub const CALIBRATION: &str = "/pntr/camera/calibration";
    /// foxglove.FrameTransforms, `map -> camera_optical` of LOCALIZED answers.
    pub const TF: &str = "/tf";
    /// foxglove.PoseInFrame of LOCALIZED answers.
    pub const POSE: &str = "/pntr/pose";
    /// foxglove.PoseInFrame of the ground truth.
    pub const TRUTH: &str = "/pntr/ground_truth";
    /// JSON `pntr.Answer` of every answer.
    pub const ANSWER: &str = "/pntr/answer";
    /// foxglove.PosesInFrame of the map's images.
    pub const MAP_CAMERAS: &str = "/pntr/map/cameras";
}

/// JSON schema of the `/pntr/answer` messages.
const ANSWER_SCHEMA: &str = r#"{
  "title": "pntr.Answer",
  "description": "One answer of pntr: poses in ROS conventions (z-up map frame, optical camera axes)",
  "type": "object",
  "properties": {
    "timestamp": {"type": "object", "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer"}}},
    "request_id": {"type": "string"},
    "map_id": {"type": "string"},
    "map_version": {"type": "string", "description": "the version of the map that answered: it changes when the map is replaced or extended while serving"},
    "status": {"type": "string", "enum": ["LOCALIZED", "NOT_LOCALIZED", "ERROR"]},
    "reason": {"type": "string"},
    "confidence": {"type": "number"},
    "inliers": {"type": "integer"},
    "mode": {"type": "string"},
    "track_state": {"type": "string", "description": "a stream's track after this frame: NONE, RE_ACQUIRING, ESTABLISHED or CARRIED; empty for single frames"},
    "matched_image_id": {"type": "string"},
    "pose": {"type": ["object", "null"], "properties": {
      "position": {"type": "array", "items": {"type": "number"}},
      "orientation_wxyz": {"type": "array", "items": {"type": "number"}}}},
    "covariance": {"type": "array", "items": {"type": "number"},
      "description": "6x6 row-major, x y z then rotation about x y z, map frame, m^2 and rad^2"},
    "position_sigma_m": {"type": ["number", "null"]},
    "truth_error_m": {"type": ["number", "null"]},
    "truth_error_deg": {"type": ["number", "null"]}
  }
}"#;

/// A frame's colour image as it can be shown.
pub enum Picture<'a> {
    /// An encoded file, shown as it is (`format` "png" or "jpeg").
    Encoded {
        /// The file's bytes.
        data: &'a [u8],
        /// "png" or "jpeg".
        format: &'static str,
    },
    /// Decoded pixels, encoded as PNG when someone listens.
    Raw(&'a RgbImage),
}

/// One localized (or refused) frame, everything in ROS conventions.
pub struct Observation<'a> {
    /// When the frame was taken (seconds since the Unix epoch, or since the start of a recording
    /// whose stamps are not absolute).
    pub time_s: f64,
    /// The frame's colour image and camera, when it is to be shown.
    pub picture: Option<(Picture<'a>, &'a Intrinsics)>,
    /// The caller's id of the frame.
    pub request_id: &'a str,
    /// The map that answered.
    pub map_id: &'a str,
    /// The version of that map that answered (it changes with a live replace or extend; empty
    /// where unknown).
    pub map_version: &'a str,
    /// LOCALIZED, NOT_LOCALIZED or ERROR.
    pub status: &'a str,
    /// Why it is not LOCALIZED (or the error).
    pub reason: &'a str,
    /// The calibrated confidence.
    pub confidence: f64,
    /// Registration inliers.
    pub inliers: u32,
    /// GLOBAL, PRIOR or TRACKING.
    pub mode: &'a str,
    /// A stream's track after this frame ([`crate::wire::track_state_label`]); empty for single
    /// frames.
    pub track_state: &'a str,
    /// The map image the pose was registered against.
    pub matched_image_id: &'a str,
    /// `map_from_camera_optical` (z-up map frame), LOCALIZED only.
    pub pose: Option<Isometry3<f64>>,
    /// 6x6 covariance of `pose` in the `map` frame (ROS order), or empty.
    pub covariance: &'a [f64],
    /// The true `map_from_camera_optical`, when known.
    pub truth: Option<Isometry3<f64>>,
}

/// The channels of one Foxglove context (a file or a live view).
pub struct View {
    image: Channel<CompressedImage>,
    calibration: Channel<CameraCalibration>,
    tf: Channel<FrameTransforms>,
    pose: Channel<PoseInFrame>,
    truth: Channel<PoseInFrame>,
    answer: Arc<RawChannel>,
    map_cameras: Channel<PosesInFrame>,
}

fn stamp(time_s: f64) -> Timestamp {
    Timestamp::saturating_from_epoch_secs_f64(time_s.max(0.0))
}

fn nanos(time_s: f64) -> u64 {
    stamp(time_s).total_nanos()
}

/// The Foxglove form of a rigid transform.
fn pose_message(p: &Isometry3<f64>) -> Pose {
    let t = p.translation.vector;
    let [w, x, y, z] = pntr_core::pose::canonical_wxyz(&p.rotation);
    Pose {
        position: Some(Vector3 {
            x: t.x,
            y: t.y,
            z: t.z,
        }),
        orientation: Some(Quaternion { x, y, z, w }),
    }
}

impl View {
    /// The channels, on `ctx`.
    pub fn new(ctx: &Arc<Context>) -> Self {
        let answer = ctx
            .channel_builder(topics::ANSWER)
            .message_encoding("json")
            .schema(Schema::new(
                "pntr.Answer",
                "jsonschema",
                ANSWER_SCHEMA.as_bytes().to_vec(),
            ))
            .build_raw()
            .expect("a message encoding is given");
        Self {
            image: ctx.channel_builder(topics::IMAGE).build(),
            calibration: ctx.channel_builder(topics::CALIBRATION).build(),
            tf: ctx.channel_builder(topics::TF).build(),
            pose: ctx.channel_builder(topics::POSE).build(),
            truth: ctx.channel_builder(topics::TRUTH).build(),
            answer,
            map_cameras: ctx.channel_builder(topics::MAP_CAMERAS).build(),
        }
    }

    /// True when something listens to any channel (a file, or a subscribed live client).
    pub fn wanted(&self) -> bool {
        self.answer.has_sinks()
            || self.image.has_sinks()
            || self.pose.has_sinks()
            || self.map_cameras.has_sinks()
    }

    /// True when the frames' images are listened to (encode them only then).
    pub fn wants_images(&self) -> bool {
        self.image.has_sinks()
    }

    /// Show one answered frame.
    pub fn observe(&self, o: &Observation<'_>) {
        let t = nanos(o.time_s);
        if let Some((picture, k)) = &o.picture {
            if self.image.has_sinks() {
                let (data, format) = match picture {
                    Picture::Encoded { data, format } => (data.to_vec(), *format),
                    Picture::Raw(rgb) => match crate::wire::encode_png(
                        rgb.width,
                        rgb.height,
                        png::ColorType::Rgb,
                        png::BitDepth::Eight,
                        &rgb.data,
                    ) {
                        Ok(d) => (d, "png"),
                        Err(e) => {
                            tracing::warn!(error = %e, "encoding a frame for Foxglove failed");
                            (Vec::new(), "png")
                        }
                    },
                };
                if !data.is_empty() {
                    self.image.log_with_time(
                        &CompressedImage {
                            timestamp: Some(stamp(o.time_s)),
                            frame_id: FRAME_CAMERA.into(),
                            data: data.into(),
                            format: format.into(),
                        },
                        t,
                    );
                }
            }
            self.calibration.log_with_time(&calibration(k, o.time_s), t);
        }
        if let Some(p) = &o.pose {
            let m = pose_message(p);
            self.tf.log_with_time(
                &FrameTransforms {
                    transforms: vec![FrameTransform {
                        timestamp: Some(stamp(o.time_s)),
                        parent_frame_id: FRAME_MAP.into(),
                        child_frame_id: FRAME_CAMERA.into(),
                        translation: m.position,
                        rotation: m.orientation,
                    }],
                },
                t,
            );
            self.pose.log_with_time(
                &PoseInFrame {
                    timestamp: Some(stamp(o.time_s)),
                    frame_id: FRAME_MAP.into(),
                    pose: Some(m),
                },
                t,
            );
        }
        if let Some(g) = &o.truth {
            self.truth.log_with_time(
                &PoseInFrame {
                    timestamp: Some(stamp(o.time_s)),
                    frame_id: FRAME_MAP.into(),
                    pose: Some(pose_message(g)),
                },
                t,
            );
        }
        if self.answer.has_sinks() {
            let ts = stamp(o.time_s);
            let errors = match (&o.pose, &o.truth) {
                (Some(p), Some(g)) => Some((
                    (p.translation.vector - g.translation.vector).norm(),
                    p.rotation.angle_to(&g.rotation).to_degrees(),
                )),
                _ => None,
            };
            let json = serde_json::json!({
                "timestamp": {"sec": ts.sec(), "nsec": ts.nsec()},
                "request_id": o.request_id,
                "map_id": o.map_id,
                "map_version": o.map_version,
                "status": o.status,
                "reason": o.reason,
                "confidence": o.confidence,
                "inliers": o.inliers,
                "mode": o.mode,
                "track_state": o.track_state,
                "matched_image_id": o.matched_image_id,
                "pose": o.pose.map(|p| serde_json::json!({
                    "position": [p.translation.x, p.translation.y, p.translation.z],
                    "orientation_wxyz": pntr_core::pose::canonical_wxyz(&p.rotation),
                })),
                "covariance": o.covariance,
                "position_sigma_m": (o.covariance.len() == 36)
                    .then(|| (o.covariance[0] + o.covariance[7] + o.covariance[14]).max(0.0).sqrt()),
                "truth_error_m": errors.map(|e| e.0),
                "truth_error_deg": errors.map(|e| e.1),
            });
            self.answer.log_with_meta(
                json.to_string().as_bytes(),
                foxglove::PartialMetadata::with_log_time(t),
            );
        }
    }

    /// Show the poses of a map's images (`map_from_camera_optical`, z-up), at `time_s`.
    pub fn map_cameras(&self, time_s: f64, poses: impl IntoIterator<Item = Isometry3<f64>>) {
        if !self.map_cameras.has_sinks() {
            return;
        }
        self.map_cameras.log_with_time(
            &PosesInFrame {
                timestamp: Some(stamp(time_s)),
                frame_id: FRAME_MAP.into(),
                poses: poses.into_iter().map(|p| pose_message(&p)).collect(),
            },
            nanos(time_s),
        );
    }
}

/// The ROS-style camera calibration of `k` (plumb_bob; K and P from the pinhole, R the identity).
fn calibration(k: &Intrinsics, time_s: f64) -> CameraCalibration {
    CameraCalibration {
        timestamp: Some(stamp(time_s)),
        frame_id: FRAME_CAMERA.into(),
        width: k.width,
        height: k.height,
        distortion_model: "plumb_bob".into(),
        d: k.distortion.to_vec(),
        k: vec![k.fx, 0.0, k.cx, 0.0, k.fy, k.cy, 0.0, 0.0, 1.0],
        r: vec![1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        p: vec![
            k.fx, 0.0, k.cx, 0.0, 0.0, k.fy, k.cy, 0.0, 0.0, 0.0, 1.0, 0.0,
        ],
    }
}

/// An MCAP file being written: [`Recording::finish`] closes it under its name; until then it is
/// `<name>.partial`, so an interrupted run never leaves a file that looks complete. The first write
/// that fails (a full disk, a file-size limit) is kept and reported once by [`Recording::error`];
/// the recording is dead from there (later writes are dropped, not retried and warned about one by
/// one), and a recording dropped or failed at its finish removes its partial file.
pub struct Recording {
    view: View,
    writer: Option<McapWriterHandle<GuardedWriter<BufWriter<File>>>>,
    _ctx: Arc<Context>,
    failed: FirstError,
    partial: PathBuf,
    out: PathBuf,
}

impl Recording {
    /// Start writing `out` (an existing file is replaced at [`Recording::finish`]). Errors name the
    /// file.
    pub fn create(out: &Path) -> Result<Self, String> {
        let mut partial = out.as_os_str().to_owned();
        partial.push(".partial");
        let partial = PathBuf::from(partial);
        let _ = std::fs::remove_file(&partial);
        let ctx = Context::new();
        let view = View::new(&ctx);
        let file = File::create_new(&partial).map_err(|e| format!("{}: {e}", partial.display()))?;
        let (file, failed) = GuardedWriter::new(BufWriter::new(file));
        let writer = ctx
            .mcap_writer()
            .create(file)
            .map_err(|e| format!("{}: {e}", partial.display()))?;
        Ok(Self {
            view,
            writer: Some(writer),
            _ctx: ctx,
            failed,
            partial,
            out: out.to_path_buf(),
        })
    }

    /// The channels to log to.
    pub fn view(&self) -> &View {
        &self.view
    }

    /// The first write that failed, as `<partial file>: <cause>`; `None` while all is well. Writes
    /// are buffered, so a failure shows some messages after the one that caused it.
    pub fn error(&self) -> Option<String> {
        self.failed.get().map(|e| {
            format!(
                "{} (written as {}): {e}",
                self.out.display(),
                self.partial.display()
            )
        })
    }

    /// Close the file and move it to its name. Errors (the first failed write, or the close) name
    /// the file and the cause; the partial file is removed then.
    pub fn finish(mut self) -> Result<PathBuf, String> {
        if let Some(w) = self.writer.take() {
            // The SDK's close writes the summary and footer but leaves them buffered: flushed and
            // synced here, through the guard, so a disk that fills at the very end is seen.
            let mut file = w
                .close()
                .map_err(|e| format!("{}: {e}", self.partial.display()))?;
            file.run(|b| b.flush().and_then(|()| b.get_ref().sync_all()));
        }
        if let Some(e) = self.error() {
            return Err(e);
        }
        std::fs::rename(&self.partial, &self.out)
            .map_err(|e| format!("{} -> {}: {e}", self.partial.display(), self.out.display()))?;
        Ok(self.out.clone())
    }
}

impl Drop for Recording {
    fn drop(&mut self) {
        // Unfinished or failed: close the writer, then remove what it wrote (after a successful
        // finish the partial file has its final name already and nothing is removed).
        if let Some(w) = self.writer.take() {
            drop(w.close());
        }
        let _ = std::fs::remove_file(&self.partial);
    }
}

/// Messages a live viewer may have queued before the oldest are dropped (the Foxglove SDK's
/// per-client backlog; its default, 1024, held about 45 MB per viewer that never read at 256x256
/// and far more at 640x480). 64 is about nine frames' messages: a viewer that falls behind sees the
/// newest frames, not a growing delay.
pub const LIVE_BACKLOG_MESSAGES: usize = 64;
/// Answered frames waiting for the live view's thread; a frame arriving while it is full is not
/// shown (counted in `pntr_live_view_frames_dropped_total`), so drawing never holds up an answer.
pub const LIVE_QUEUE_FRAMES: usize = 2;
/// Most camera images a second the live view shows, over all streams (every answer, pose and
/// transform is shown; only images are left out of the frames in between). Foxglove's image panel
/// shows no more to a person, and PNG-encoding every frame of a server answering 150 frames a
/// second took a fifth of its throughput on 2 cores (BENCHMARKS.md, "Slow Foxglove viewers").
pub const LIVE_MAX_IMAGES_PER_S: f64 = 15.0;

/// One answered frame as the live view shows it, owned, so the request goes on without it (the
/// borrowed form is [`Observation`]). Everything in ROS conventions.
#[derive(Debug, Clone)]
pub struct Shown {
    /// Seconds since the Unix epoch.
    pub time_s: f64,
    /// The frame's colour image, when it is to be shown ([`Live::claim_image`]).
    pub rgb: Option<RgbImage>,
    /// Its camera.
    pub intrinsics: Intrinsics,
    /// The caller's id of the frame.
    pub request_id: String,
    /// The map that answered.
    pub map_id: String,
    /// That map's version.
    pub map_version: String,
    /// LOCALIZED or NOT_LOCALIZED.
    pub status: &'static str,
    /// Why it is not LOCALIZED.
    pub reason: String,
    /// The calibrated confidence.
    pub confidence: f64,
    /// Registration inliers.
    pub inliers: u32,
    /// GLOBAL, PRIOR or TRACKING.
    pub mode: &'static str,
    /// A stream's track after this frame ([`crate::wire::track_state_label`]); empty for single
    /// frames.
    pub track_state: &'static str,
    /// The map image the pose was registered against.
    pub matched_image_id: String,
    /// `map_from_camera_optical` (z-up), LOCALIZED only.
    pub pose: Option<Isometry3<f64>>,
    /// 6x6 covariance of `pose` (ROS order), or empty.
    pub covariance: Vec<f64>,
}

impl Shown {
    /// The frame as a stream answered it (`r`, after the stream's state took it): its status,
    /// reason, cause and track state; the pose only when still LOCALIZED.
    pub fn as_answered(mut self, r: &crate::proto::LocalizeResponse) -> Self {
        let localized = r.status == crate::proto::Status::Localized as i32;
        self.status = if localized {
            "LOCALIZED"
        } else {
            "NOT_LOCALIZED"
        };
        self.reason = r.reason.clone();
        self.confidence = r.confidence;
        self.track_state = crate::wire::track_state_label(r.track_state);
        if !localized {
            self.pose = None;
            self.covariance.clear();
            self.matched_image_id.clear();
        }
        self
    }

    fn observation(&self) -> Observation<'_> {
        Observation {
            time_s: self.time_s,
            picture: self
                .rgb
                .as_ref()
                .map(|rgb| (Picture::Raw(rgb), &self.intrinsics)),
            request_id: &self.request_id,
            map_id: &self.map_id,
            map_version: &self.map_version,
            status: self.status,
            reason: &self.reason,
            confidence: self.confidence,
            inliers: self.inliers,
            mode: self.mode,
            track_state: self.track_state,
            matched_image_id: &self.matched_image_id,
            pose: self.pose,
            covariance: &self.covariance,
            truth: None,
        }
    }
}

/// The live Foxglove WebSocket view of a server (`pntr-server --foxglove ADDR`).
///
/// Viewers connect to `ADDR`, which hands each connection to the Foxglove SDK's server on an
/// ephemeral local port ([`crate::live_proxy`]: clients asking for the protocol's earlier name,
/// `foxglove.websocket.v1`, are served too). Frames are drawn (PNG-encoded, serialised) on a thread
/// of their own, fed by [`Live::show`] through a queue of [`LIVE_QUEUE_FRAMES`], images at most
/// [`LIVE_MAX_IMAGES_PER_S`] a second ([`Live::claim_image`]); each viewer's
/// backlog holds at most [`LIVE_BACKLOG_MESSAGES`], oldest dropped first. So a slow or stalled
/// viewer costs neither the robots' latency nor memory without bound.
pub struct Live {
    view: Arc<View>,
    handle: Option<WebSocketServerHandle>,
    addr: SocketAddr,
    frames: Option<std::sync::mpsc::SyncSender<Shown>>,
    /// When the last image was claimed for showing.
    last_image: std::sync::Mutex<Option<std::time::Instant>>,
    front: tokio::task::JoinHandle<()>,
    _ctx: Arc<Context>,
}

impl Live {
    /// Listen on `addr` (port 0: an ephemeral one; see [`Live::addr`]). Errors say why (the
    /// address is taken, say).
    pub async fn start(addr: SocketAddr) -> Result<Self, String> {
        let listener = tokio::net::TcpListener::bind(addr)
            .await
            .map_err(|e| format!("--foxglove {addr}: {e}"))?;
        let bound = listener
            .local_addr()
            .map_err(|e| format!("--foxglove {addr}: {e}"))?;
        let ctx = Context::new();
        let view = Arc::new(View::new(&ctx));
        let handle = foxglove::WebSocketServer::new()
            .name(format!("pntr-server {}", env!("CARGO_PKG_VERSION")))
            .context(&ctx)
            .message_backlog_size(LIVE_BACKLOG_MESSAGES)
            .bind("127.0.0.1", 0)
            .start()
            .await
            .map_err(|e| format!("--foxglove {addr}: the Foxglove server: {e}"))?;
        let (tx, rx) = std::sync::mpsc::sync_channel::<Shown>(LIVE_QUEUE_FRAMES);
        let drawn = view.clone();
        std::thread::Builder::new()
            .name("pntr-live-view".into())
            .spawn(move || {
                for shown in rx {
                    drawn.observe(&shown.observation());
                }
            })
            .map_err(|e| format!("--foxglove {addr}: starting its thread: {e}"))?;
        let inner = SocketAddr::from(([127, 0, 0, 1], handle.port()));
        let front = tokio::spawn(crate::live_proxy::serve(listener, inner));
        tracing::info!("live Foxglove view: viewers connect to ws://{bound}");
        Ok(Self {
            view,
            handle: Some(handle),
            addr: bound,
            frames: Some(tx),
            last_image: std::sync::Mutex::new(None),
            front,
            _ctx: ctx,
        })
    }

    /// The bound address.
    pub fn addr(&self) -> SocketAddr {
        self.addr
    }

    /// The channels to log to (for what is drawn rarely, such as the map's cameras; frames go
    /// through [`Live::show`]).
    pub fn view(&self) -> &View {
        &self.view
    }

    /// Whether this frame's image is to be shown: a viewer watches the images and none was claimed
    /// in the last 1 / [`LIVE_MAX_IMAGES_PER_S`] s (then this one is). Ask before copying the image.
    pub fn claim_image(&self) -> bool {
        if !self.view.wants_images() {
            return false;
        }
        let mut last = self.last_image.lock().unwrap_or_else(|e| e.into_inner());
        let now = std::time::Instant::now();
        let due =
            last.is_none_or(|t| now.duration_since(t).as_secs_f64() >= 1.0 / LIVE_MAX_IMAGES_PER_S);
        if due {
            *last = Some(now);
        }
        due
    }

    /// Hand an answered frame to the live view's thread, without waiting. False when it is not
    /// shown (counted as dropped): the thread is still drawing the frames before it.
    pub fn show(&self, shown: Shown) -> bool {
        let queued = self
            .frames
            .as_ref()
            .is_some_and(|tx| tx.try_send(shown).is_ok());
        if !queued {
            metrics::counter!(crate::telemetry::LIVE_VIEW_DROPPED).increment(1);
        }
        queued
    }

    /// Live clients connected now.
    pub fn clients(&self) -> usize {
        self.handle.as_ref().map_or(0, |h| h.client_count())
    }
}

impl std::fmt::Debug for Live {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Live(ws://{}, {} clients)", self.addr, self.clients())
    }
}

impl Drop for Live {
    fn drop(&mut self) {
        // The drawing thread ends with its queue; the front door stops accepting.
        self.frames.take();
        self.front.abort();
        if let Some(h) = self.handle.take() {
            // Closes the clients' connections.
            drop(h.stop());
        }
    }
}
