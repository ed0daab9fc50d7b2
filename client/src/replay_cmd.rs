//! `pntr replay`: stream a recorded drive through a running server's `LocalizeStream`, as a robot
//! would, and measure the trajectory it gets back (ATE, RPE), the share localized and by which path,
//! and the latency.
//!
//! Frames go one at a time, each after the previous answer, at the sequence's own pace (`--rate`
//! to change it): the server tracks from the stream's last LOCALIZED pose. `--no-prior` asks for
//! global localization of every frame (`relocalize`), the baseline; `--prior-radius M` also sends
//! each frame an explicit prior of M metres around the previous answer (a robot's odometry).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use indicatif::{ProgressBar, ProgressStyle};
use nalgebra::Isometry3;
use pntr_dataset::recording::{Recording, RecordingOptions};
use pntr_dataset::tum::ground_truth_line;
use pntr_eval::trajectory_errors;
use pntr_pipeline::prior::Region;
use pntr_service::proto;
use pntr_service::tokio;
use pntr_service::wire;
use serde_json::json;

use crate::remote::{authorized, channel, client, ConnectArgs};

/// Arguments of `pntr replay`.
#[derive(clap::Args, Debug)]
pub struct ReplayArgs {
    /// Where the server is, and how to authenticate.
    #[command(flatten)]
    pub connect: ConnectArgs,
    /// The recorded drive: a folder in the TUM RGB-D layout (rgb.txt, depth.txt, optional
    /// groundtruth.txt and calibration.txt), a ROS 2 bag (a folder with metadata.yaml, or `.mcap`),
    /// or a folder in the 7-Scenes layout (frame-NNNNNN.color|depth|pose files).
    #[arg(long)]
    pub sequence: PathBuf,
    /// ROS 2 bag topics.
    #[command(flatten)]
    pub topics: crate::recordings::TopicArgs,
    /// Depth units per metre, replacing what the recording's format says (TUM PNGs 5000, ROS 16UC1
    /// 1000): e.g. 1000 for a folder of millimetre PNGs, 4000 for a sensor with 0.25 mm units.
    #[arg(long, value_name = "UNITS_PER_M")]
    pub depth_scale: Option<f64>,
    /// Frames per second to send at (default: the sequence's own timestamps). Each frame still
    /// carries its recorded stamp (`stamp_s`), so the server judges the camera's motion by the
    /// recording's time at any rate.
    #[arg(long)]
    pub rate: Option<f64>,
    /// Send the frames without their recorded stamps (`LocalizeRequest.stamp_s`): the server then
    /// judges the camera's motion by when the frames arrive, as for a client that sends none (with
    /// `--rate`, as if the camera moved at the rate's pace).
    #[arg(long)]
    pub no_stamps: bool,
    /// Localize every frame globally (the stream keeps no tracking region): the baseline.
    #[arg(long)]
    pub no_prior: bool,
    /// Also send each frame an explicit prior of this radius, metres, around the previous answer.
    #[arg(long, value_name = "METRES", conflicts_with = "no_prior")]
    pub prior_radius: Option<f64>,
    /// The colour camera as `fx,fy,cx,cy[,k1,k2,p1,p2[,k3]]` when the sequence names none (no
    /// calibration.txt or camera info; a 7-Scenes folder never does: 525,525,320,240 for its Kinect).
    #[arg(long, value_name = "FX,FY,CX,CY")]
    pub intrinsics: Option<String>,
    /// Camera effects applied to every frame before it is sent: `none`, `robot` (exposure, gamma,
    /// white balance, blur, noise, JPEG, depth noise growing with range, dropouts and lost edges), or
    /// a comma-separated list of the groups `exposure`, `blur`, `noise`, `jpeg`, `depth`. Exposure
    /// drifts smoothly over 3 s (30 frames), as an auto exposure does; the others are drawn for each
    /// frame from its index, so a run is repeatable.
    #[arg(long, default_value = "none")]
    pub effects: String,
    /// Replay at most this many frames (0 = all).
    #[arg(long, default_value_t = 0)]
    pub frames: usize,
    /// Send only every Nth frame of the recording (with its recorded stamp): a sparse stream, as a
    /// camera at a lower rate sends it (`--every 6` of a 30 Hz recording: 5 Hz; `--every 30`: 1
    /// Hz). `--frames` counts the recording's frames, before this.
    #[arg(long, value_name = "N", default_value_t = 1)]
    pub every: usize,
    /// The robot's odometry as a TUM trajectory file (`timestamp tx ty tz qx qy qz qw`,
    /// odom_from_camera with optical axes, on the recording's clock): each frame sends its pose at
    /// the frame's stamp (`LocalizeRequest.odometry`), so the stream carries its pose by it where the
    /// map gives no fix. Frames outside the trajectory send none.
    #[arg(long, value_name = "TRAJECTORY.txt")]
    pub odometry: Option<PathBuf>,
    /// Write the estimated trajectory in TUM format (`timestamp tx ty tz qx qy qz qw`), LOCALIZED
    /// frames only, to this file.
    #[arg(long)]
    pub trajectory: Option<PathBuf>,
    /// Write the JSON report (the summary line's figures and more: recalls, median errors, stage
    /// times, modes) to this file.
    #[arg(long)]
    pub json: Option<PathBuf>,
    /// Also draw both trajectories from above over the map's camera positions (PNG and SVG) into
    /// this folder.
    #[arg(long, value_name = "DIR")]
    pub plot: Option<PathBuf>,
    /// Also write one JSON line per frame (frame index in the drive's order, timestamp, status, mode,
    /// reason, cause, confidence, inliers, matched image, position and rotation standard deviations
    /// from the covariance, the map version that answered, latency, and with ground truth the
    /// translation and rotation errors): what answered each frame, and why a frame was not
    /// localized.
    #[arg(long, value_name = "OUT.jsonl")]
    pub frames_log: Option<PathBuf>,
    /// Also write what happened to this MCAP file, with Foxglove's schemas (open it in Foxglove):
    /// every frame's image and camera, the answered poses with their covariance, status and reason,
    /// the ground truth, and with --db the map's cameras; poses in ROS conventions (z-up `map`,
    /// optical `camera_optical`). A path not ending in `.mcap` is a ROS 2 bag folder instead, as
    /// `--record-bag` writes.
    #[arg(long, value_name = "OUT.mcap|OUT_DIR")]
    pub record: Option<PathBuf>,
    /// Also write what happened as a ROS 2 bag (a new rosbag2 folder: MCAP with ROS 2 message types
    /// and metadata.yaml, for `ros2 bag play` and rviz), with the topics pntr-ros publishes:
    /// `/pntr/pose` (PoseWithCovarianceStamped), `/tf` (`map -> camera_optical`), `/diagnostics`,
    /// `/pntr/ground_truth`, and the frames on `/camera/color/image_raw/compressed` and
    /// `/camera/color/camera_info`; ROS conventions (z-up `map`).
    #[arg(long, value_name = "OUT_DIR")]
    pub record_bag: Option<PathBuf>,
    /// The map file the server serves, read here for its cameras' poses (--record).
    #[arg(long, value_name = "MAP.pntrmap")]
    pub db: Option<PathBuf>,
}

/// Largest gap between two frames' stamps that replay waits through, seconds (a camera runs at 1 Hz
/// or faster; a longer gap is a clock jump).
const MAX_FRAME_GAP_S: f64 = 2.0;

/// The recorded drive `--sequence` names, with the bag topics and depth unit the flags give.
fn open_recording(args: &ReplayArgs) -> Result<Recording> {
    let (depth_intrinsics, colour_from_depth) = args.topics.depth_camera()?;
    let opts = RecordingOptions {
        topics: args.topics.topics(),
        trajectory: None,
        depth_units_per_m: args.depth_scale,
        depth_intrinsics,
        colour_from_depth,
    };
    Ok(Recording::open(&args.sequence, &opts)?)
}

/// One answered frame.
struct Answered {
    /// Index of the frame in the drive's own order (0 = its first frame).
    frame: usize,
    timestamp: f64,
    estimate: Option<Isometry3<f64>>,
    truth: Option<Isometry3<f64>>,
    mode: String,
    status: String,
    reason: String,
    cause: &'static str,
    /// The stream's track after this frame (`LocalizeResponse.track_state`, without its prefix).
    track_state: &'static str,
    confidence: f64,
    inliers: u32,
    matched_image_id: String,
    position_sigma_m: Option<f64>,
    rotation_sigma_deg: Option<f64>,
    map_version: String,
    latency_ms: f64,
    stages: Vec<(String, f64)>,
}

/// Thresholds of the pose recalls replay reports: (metres, degrees) and their JSON keys. (5 cm, 5 deg)
/// and (10 cm, 5 deg) are what 7-Scenes and 12-Scenes papers report; (0.25 m, 2 deg) HPointLoc's.
const RECALL_BOUNDS: [(&str, f64, f64); 3] = [
    ("5cm_5deg", 0.05, 5.0),
    ("10cm_5deg", 0.10, 5.0),
    ("25cm_2deg", 0.25, 2.0),
];

/// Recalls over the frames with ground truth (a frame not LOCALIZED counts as a miss), median errors
/// of the LOCALIZED ones, and how many of those are more than 0.5 m or 10 deg off (wrong).
fn pose_accuracy(out: &[Answered]) -> serde_json::Value {
    let with_truth = out.iter().filter(|a| a.truth.is_some()).count();
    let errors: Vec<(f64, f64)> = out
        .iter()
        .filter_map(|a| {
            let (e, t) = (a.estimate?, a.truth?);
            Some((
                (e.translation.vector - t.translation.vector).norm(),
                e.rotation.angle_to(&t.rotation).to_degrees(),
            ))
        })
        .collect();
    let recall: serde_json::Map<String, serde_json::Value> = RECALL_BOUNDS
        .iter()
        .map(|&(key, m, deg)| {
            let n = errors.iter().filter(|&&(e, d)| e <= m && d <= deg).count();
            (key.to_string(), json!(n as f64 / with_truth.max(1) as f64))
        })
        .collect();
    let median = |mut v: Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v.get(v.len() / 2).copied()
    };
    json!({
        "recall": recall,
        "median_error_m": median(errors.iter().map(|e| e.0).collect()),
        "median_error_deg": median(errors.iter().map(|e| e.1).collect()),
        "localized_over_0_5m_or_10deg": errors.iter().filter(|&&(e, d)| e > 0.5 || d > 10.0).count(),
        "frames_with_ground_truth": with_truth,
    })
}

/// The accuracy part of the report ([`pose_accuracy`]) in one line for the terminal: the recalls
/// and median errors against the ground truth; `None` without ground truth.
fn accuracy_line(accuracy: &serde_json::Value) -> Option<String> {
    let n = accuracy["frames_with_ground_truth"]
        .as_u64()
        .filter(|&n| n > 0)?;
    let recall = |key: &str| accuracy["recall"][key].as_f64().unwrap_or(0.0);
    let median = match (
        accuracy["median_error_m"].as_f64(),
        accuracy["median_error_deg"].as_f64(),
    ) {
        (Some(m), Some(deg)) => format!("{:.1} cm, {deg:.2} deg", 100.0 * m),
        _ => "none localized".to_string(),
    };
    Some(format!(
        "against the ground truth of {n} frames (not LOCALIZED counts as a miss): recall (5 cm, 5 deg) {:.3}, (10 cm, 5 deg) {:.3}, (0.25 m, 2 deg) {:.3}; median error {median}; LOCALIZED more than 0.5 m or 10 deg off: {}",
        recall("5cm_5deg"),
        recall("10cm_5deg"),
        recall("25cm_2deg"),
        accuracy["localized_over_0_5m_or_10deg"].as_u64().unwrap_or(0)
    ))
}

/// One JSON line per answered frame; errors are geodesic (rotation) and Euclidean (translation)
/// against the ground truth, for LOCALIZED frames that have one.
fn frames_log(out: &[Answered]) -> String {
    let mut text = String::new();
    for a in out {
        let (error_m, error_deg) = match (a.estimate, a.truth) {
            (Some(e), Some(t)) => (
                Some((e.translation.vector - t.translation.vector).norm()),
                Some(e.rotation.angle_to(&t.rotation).to_degrees()),
            ),
            _ => (None, None),
        };
        let line = json!({
            "frame": a.frame,
            "timestamp": a.timestamp,
            "status": a.status,
            "mode": a.mode,
            "reason": a.reason,
            "cause": a.cause,
            "track_state": a.track_state,
            "confidence": a.confidence,
            "inliers": a.inliers,
            "matched_image_id": a.matched_image_id,
            "position_sigma_m": a.position_sigma_m,
            "rotation_sigma_deg": a.rotation_sigma_deg,
            "map_version": a.map_version,
            "latency_ms": a.latency_ms,
            "error_m": error_m,
            "error_deg": error_deg,
        });
        text += &line.to_string();
        text.push('\n');
    }
    text
}

fn percentile(sorted: &[f64], p: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    sorted[((p / 100.0) * (sorted.len() - 1) as f64).round() as usize]
}

/// The database camera positions of the sequence's scene when it sits in a `pntr synth` output
/// (`ROOT/sequences/<scene>` beside `ROOT/HPointLoc_dataset/<scene>`); empty otherwise.
fn map_positions(sequence: &Path) -> Vec<[f64; 3]> {
    let (Some(scene), Some(root)) = (
        sequence
            .file_name()
            .map(|s| s.to_string_lossy().to_string()),
        sequence.parent().and_then(Path::parent),
    ) else {
        return Vec::new();
    };
    let Ok(index) = pntr_dataset::DatasetIndex::open(root) else {
        return Vec::new();
    };
    let mut out = Vec::new();
    for s in index.scenes.iter().filter(|s| s.name == scene) {
        for p in &s.points {
            if let Ok(r) = p.open() {
                out.extend(
                    r.poses(pntr_dataset::Role::Database)
                        .iter()
                        .map(|pose| -> [f64; 3] { pose.translation.vector.into() }),
                );
            }
        }
    }
    out
}

/// `pntr replay`.
pub fn run(args: &ReplayArgs) -> Result<()> {
    if args.every == 0 {
        bail!("--every must be at least 1 (every frame)");
    }
    if let Some(r) = args.rate {
        if !(r.is_finite() && r > 0.0) {
            bail!("--rate must be a positive number of frames per second, not {r}");
        }
    }
    if let Some(r) = args.prior_radius {
        if !(r.is_finite() && r > 0.0 && r <= pntr_pipeline::prior::MAX_RADIUS_M) {
            bail!(
                "--prior-radius must be in (0, {}] metres, not {r}",
                pntr_pipeline::prior::MAX_RADIUS_M
            );
        }
    }
    let effects = crate::loading::effects(&args.effects)?;
    let mut seq =
        open_recording(args).with_context(|| format!("--sequence {}", args.sequence.display()))?;
    let camera = match (&args.intrinsics, seq.intrinsics()) {
        (Some(s), _) => crate::recordings::parse_intrinsics(std::slice::from_ref(s))?,
        (None, Some(k)) => wire::intrinsics_message(&k),
        (None, None) => bail!(
            "{}: {}; pass the camera with --intrinsics fx,fy,cx,cy[,k1,k2,p1,p2,k3]",
            args.sequence.display(),
            seq.camera_problem()
                .unwrap_or_else(|| "no calibration.txt or camera info".into())
        ),
    };
    if seq.has_depth_camera() {
        let (width, height) = seq.image_size().with_context(|| {
            format!(
                "{}: none of the first frames could be read",
                args.sequence.display()
            )
        })?;
        let k = pntr_service::decode::intrinsics(Some(&camera), width, height)
            .map_err(|e| anyhow::anyhow!("--intrinsics: {}", e.message()))?;
        seq.set_colour_camera(k);
    }
    for w in seq.warnings() {
        eprintln!("warning: {w}");
    }
    let n = if args.frames == 0 {
        seq.len()
    } else {
        args.frames.min(seq.len())
    };
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()?;
    let mut c = client(rt.block_on(channel(&args.connect))?);
    let bar = ProgressBar::new(n.div_ceil(args.every.max(1)) as u64);
    bar.set_style(
        ProgressStyle::with_template("{msg} [{bar:30}] {pos}/{len} frames ({per_sec}, eta {eta})")
            .expect("valid template")
            .progress_chars("=> "),
    );
    let (tx, rx) = tokio::sync::mpsc::channel::<proto::LocalizeRequest>(1);
    let mut request = authorized(
        &args.connect,
        pntr_service::tokio_stream::wrappers::ReceiverStream::new(rx),
    )?;
    request.set_timeout(Duration::from_secs(3600 * 24));
    // Answers come in the map's camera axes; recordings (TUM, ROS) hold optical axes.
    let info = rt
        .block_on(c.get_map_info(authorized(
            &args.connect,
            proto::GetMapInfoRequest {
                map_id: args.connect.map_id.clone(),
            },
        )?))
        .ok()
        .map(|i| i.into_inner());
    let map_frames = info
        .as_ref()
        .map(wire::MapFrames::of_info)
        .unwrap_or_default();
    let map_axes = map_frames.camera;
    // The estimates and the truth below are in the map's frame with optical axes.
    let optical = wire::MapFrames {
        camera: pntr_core::CameraAxes::OpenCv,
        ..map_frames
    };
    let to_ros = |p: &Isometry3<f64>| optical.pose_to_ros(p);
    let mut record_errors: Vec<String> = Vec::new();
    let mut recording = match &args.record {
        Some(path) => Some(crate::evaluation::start_recording(
            path,
            args.db.as_deref(),
            seq.timestamp(0),
        )?),
        None => None,
    };
    let mut bag = match &args.record_bag {
        Some(path) => Some(
            pntr_service::ros_bag::BagRecording::create(path)
                .map_err(|e| anyhow::anyhow!("--record-bag {e}"))?,
        ),
        None => None,
    };
    let mut answers = rt
        .block_on(c.localize_stream(request))
        .context("opening LocalizeStream")?
        .into_inner();
    let odometry = match &args.odometry {
        Some(path) => Some(
            pntr_dataset::tum::Trajectory::read(path)
                .map_err(|e| anyhow::anyhow!("--odometry {e}"))?,
        ),
        None => None,
    };
    let mut odometry_frames = 0usize;
    let t0 = seq.timestamp(0);
    if !args.no_stamps && !(0.0..pntr_service::decode::MAX_STAMP_S).contains(&t0) {
        bail!(
            "{}: the first frame's stamp is {t0}, not seconds the server takes as a capture time (>= 0, < 1e11): give --no-stamps",
            args.sequence.display()
        );
    }
    let (mut skew, mut jumps, mut unreadable) = (0.0f64, 0usize, 0usize);
    let mut checked = false;
    let start = Instant::now();
    let mut out: Vec<Answered> = Vec::with_capacity(n);
    let mut last: Option<Isometry3<f64>> = None;
    let mut localized = 0usize;
    for (sent_k, i) in (0..n).step_by(args.every).enumerate() {
        let timestamp = seq.timestamp(i);
        // A stamp jump (a clock correction, stamps in another unit) is not slept through, nor
        // sent as a gap: the timeline moves on from the frame after it.
        if i > 0 {
            let gap = timestamp - seq.timestamp(i - args.every);
            if gap > MAX_FRAME_GAP_S * args.every as f64 {
                skew += gap;
                jumps += 1;
                if jumps == 1 && args.rate.is_none() {
                    eprintln!(
                        "warning: the stamps jump by {gap:.3} s between frames {} and {i}: sent without waiting (more jumps are counted in the report)",
                        i - 1
                    );
                }
            }
        }
        let due = match args.rate {
            Some(r) => sent_k as f64 / r,
            None => timestamp - t0 - skew,
        };
        let wait = due - start.elapsed().as_secs_f64();
        if wait > 0.0 {
            std::thread::sleep(Duration::from_secs_f64(wait));
        }
        let (mut rgb, mut depth) = match seq.load(i) {
            Ok(f) => f,
            Err(e) => {
                unreadable += 1;
                if unreadable <= 5 {
                    eprintln!("warning: frame {i} skipped: {e}");
                }
                bar.inc(1);
                continue;
            }
        };
        if !checked {
            // The likely integration mistakes, named before a drive localizes nothing.
            if let Some(k) = seq.intrinsics().filter(|_| args.intrinsics.is_none()) {
                if (k.width, k.height) != (rgb.width, rgb.height) {
                    bail!(
                        "{}: the frames are {}x{} but the camera info describes {}x{}: give --intrinsics for the recorded size",
                        args.sequence.display(),
                        rgb.width,
                        rgb.height,
                        k.width,
                        k.height
                    );
                }
            }
            if let Some(hint) = pntr_dataset::recording::depth_unit_hint(&depth, args.depth_scale) {
                bail!("{}: frame {i}: {hint}", args.sequence.display());
            }
            checked = depth.valid_count() > 0;
        }
        if let Some(fx) = &effects {
            let look = fx.drifting_look(0, i);
            fx.apply_with(&mut rgb, &mut depth, &look, i as u64);
        }
        let mut req = wire::raw_request(&rgb, &depth, None);
        req.intrinsics = Some(camera.clone());
        req.map_id = args.connect.map_id.clone();
        req.request_id = format!("{:.6}", timestamp);
        req.relocalize = args.no_prior;
        req.stamp_s = (!args.no_stamps).then_some(timestamp - skew);
        // Optical axes, as TUM trajectories hold them: converted to the map's camera axes, the
        // convention this request uses.
        let odometry_pose = odometry.as_ref().and_then(|o| o.at(timestamp));
        odometry_frames += odometry_pose.is_some() as usize;
        req.odometry = odometry_pose.map(|p| {
            wire::to_proto_pose(&pntr_core::convert_axes(
                &p,
                pntr_core::CameraAxes::OpenCv,
                map_axes,
            ))
        });
        // The recording's ground truth and the prior below are in the map's frame.
        req.frame_convention = proto::FrameConvention::Map as i32;
        // Only the prior's position is sent, which the camera axes do not change.
        if let (Some(r), Some(p)) = (args.prior_radius, last) {
            req.prior = Some(wire::prior_message(&Region::new(p.translation.vector, r)?));
        }
        let sent = Instant::now();
        rt.block_on(tx.send(req))
            .map_err(|_| anyhow::anyhow!("the server closed the stream"))?;
        let r = rt
            .block_on(answers.message())
            .with_context(|| format!("frame {i} (t = {:.6})", timestamp))?
            .with_context(|| format!("the server ended the stream before frame {i}"))?;
        let latency_ms = sent.elapsed().as_secs_f64() * 1e3;
        let estimate = (r.status == proto::Status::Localized as i32)
            .then(|| wire::pose(r.pose.as_ref()))
            .flatten()
            .map(|p| pntr_core::convert_axes(&p, map_axes, pntr_core::CameraAxes::OpenCv));
        if estimate.is_some() {
            localized += 1;
            last = estimate;
        }
        if recording.is_some() || bag.is_some() {
            let k = pntr_service::decode::intrinsics(Some(&camera), rgb.width, rgb.height)
                .map_err(|s| anyhow::anyhow!("the camera: {}", s.message()))?;
            let covariance = optical.covariance_to_ros(&r.covariance);
            let observation = pntr_service::visual::Observation {
                time_s: timestamp,
                picture: Some((pntr_service::visual::Picture::Raw(&rgb), &k)),
                request_id: &r.request_id,
                map_id: &r.map_id,
                map_version: &r.map_version,
                status: proto::Status::try_from(r.status).map_or("UNKNOWN", |s| s.as_str_name()),
                reason: &r.reason,
                confidence: r.confidence,
                inliers: r.inliers,
                mode: proto::Mode::try_from(r.mode).map_or("UNKNOWN", |m| m.as_str_name()),
                track_state: pntr_service::wire::track_state_label(r.track_state),
                matched_image_id: &r.matched_image_id,
                pose: estimate.as_ref().map(to_ros),
                covariance: &covariance,
                truth: seq.world_from_camera(i).as_ref().map(to_ros),
            };
            // A recording that cannot be written (a full disk) is abandoned at its first error,
            // said once; the replay goes on, its report is written, and the run fails at the end.
            if let Some(Err(e)) = recording.as_ref().map(|r| r.observe(&observation)) {
                recording = None;
                abandon_recording("--record", e, &mut record_errors);
                eprintln!("the replay goes on without it");
            }
            if let Some(Err(e)) = bag.as_ref().map(|b| b.observe(&observation)) {
                bag = None;
                abandon_recording("--record-bag", e, &mut record_errors);
                eprintln!("the replay goes on without it");
            }
        }
        out.push(Answered {
            frame: i,
            timestamp,
            estimate,
            truth: seq.world_from_camera(i),
            mode: proto::Mode::try_from(r.mode)
                .map(|m| m.as_str_name().to_string())
                .unwrap_or_else(|_| "UNKNOWN".into()),
            status: proto::Status::try_from(r.status)
                .map(|m| m.as_str_name().to_string())
                .unwrap_or_else(|_| "UNKNOWN".into()),
            reason: r.reason.clone(),
            cause: pntr_service::wire::cause_label(r.cause),
            track_state: pntr_service::wire::track_state_label(r.track_state),
            confidence: r.confidence,
            inliers: r.inliers,
            matched_image_id: r.matched_image_id.clone(),
            position_sigma_m: (r.covariance.len() == 36)
                .then(|| (r.covariance[0] + r.covariance[7] + r.covariance[14]).sqrt()),
            rotation_sigma_deg: (r.covariance.len() == 36).then(|| {
                (r.covariance[21] + r.covariance[28] + r.covariance[35])
                    .sqrt()
                    .to_degrees()
            }),
            map_version: r.map_version.clone(),
            latency_ms,
            stages: crate::remote::stage_seconds(&r),
        });
        bar.set_message(format!(
            "{:.1}% localized",
            100.0 * localized as f64 / (sent_k + 1) as f64
        ));
        bar.inc(1);
    }
    drop(tx);
    let wall = start.elapsed().as_secs_f64();
    if let Some(path) = args
        .odometry
        .as_ref()
        .filter(|_| odometry_frames < out.len())
    {
        eprintln!(
            "warning: --odometry {}: {odometry_frames} of {} frames had an odometry pose at their stamp (the trajectory must cover the recording's stamps, in seconds on its clock)",
            path.display(),
            out.len()
        );
    }
    bar.finish_and_clear();

    let mut traj = String::from("# estimated trajectory (world_from_camera, optical camera axes), LOCALIZED frames\n# timestamp tx ty tz qx qy qz qw\n");
    for a in &out {
        if let Some(e) = &a.estimate {
            traj += &ground_truth_line(a.timestamp, e);
            traj.push('\n');
        }
    }
    if let Some(path) = &args.trajectory {
        crate::output::write_text(path, &traj)?;
    }
    if let Some(b) = bag {
        match b.finish() {
            Ok(path) => eprintln!("ROS 2 bag written to {}", path.display()),
            Err(e) => abandon_recording("--record-bag", e, &mut record_errors),
        }
    }
    if let Some(rec) = recording {
        match rec.finish() {
            Ok(path) => eprintln!("recording written to {}", path.display()),
            Err(e) => abandon_recording("--record", e, &mut record_errors),
        }
    }
    if let Some(path) = &args.frames_log {
        crate::output::write_text(path, &frames_log(&out))?;
    }
    let pairs: Vec<_> = out.iter().map(|a| (a.estimate, a.truth)).collect();
    let errors = trajectory_errors(&pairs);
    let mut lat: Vec<f64> = out.iter().map(|a| a.latency_ms).collect();
    lat.sort_by(f64::total_cmp);
    let mut modes: BTreeMap<String, usize> = BTreeMap::new();
    for a in &out {
        *modes.entry(a.mode.clone()).or_default() += 1;
    }
    let mut stage_sums: BTreeMap<String, f64> = BTreeMap::new();
    for a in &out {
        for (s, v) in &a.stages {
            *stage_sums.entry(s.clone()).or_default() += v * 1e3;
        }
    }
    let stage_ms: BTreeMap<String, f64> = stage_sums
        .into_iter()
        .map(|(k, v)| (k, v / out.len().max(1) as f64))
        .collect();
    let tracked = out
        .iter()
        .filter(|a| a.estimate.is_some() && (a.mode == "TRACKING" || a.mode == "PRIOR"))
        .count();
    let frames = out.len().max(1) as f64;
    let report = json!({
        "frames": out.len(),
        "frames_unreadable": unreadable,
        "stamp_jumps": jumps,
        "stamps_sent": !args.no_stamps,
        "every": args.every,
        "odometry_sent": args.odometry.is_some(),
        "odometry_frames": odometry_frames,
        "localized_share": localized as f64 / frames,
        "tracking_share": tracked as f64 / frames,
        "ate_rmse_m": errors.ate_rmse_m,
        "rpe_trans_rmse_m": errors.rpe_trans_rmse_m,
        "rpe_rot_rmse_deg": errors.rpe_rot_rmse_deg,
        "fps": out.len() as f64 / wall.max(1e-9),
        "latency_ms": {"p50": percentile(&lat, 50.0), "p90": percentile(&lat, 90.0), "p99": percentile(&lat, 99.0)},
        "stage_ms": stage_ms,
        "max_error_m": errors.max_error_m,
        "frames_over_1m": errors.over_1m,
        "frames_with_ground_truth": errors.compared,
        "accuracy": pose_accuracy(&out),
        "modes": modes,
        "prior": if args.no_prior { "none (relocalize every frame)".to_string() }
            else if let Some(r) = args.prior_radius { format!("previous answer, {r} m radius, and the stream's tracking") }
            else { "the stream's tracking".to_string() },
        "sequence": args.sequence.display().to_string(),
        "effects": args.effects,
        "record_errors": record_errors,
    });
    if let Some(path) = &args.json {
        crate::output::write_json(path, &report)?;
    }
    println!(
        "{} frames: {:.1}% localized ({:.1}% by tracking or prior), ATE {:.3} m, RPE {:.3} m / {:.2} deg, max error {:.3} m ({} over 1 m); latency p50 {:.1} ms p90 {:.1} ms p99 {:.1} ms; {:.1} frames/s",
        out.len(),
        100.0 * localized as f64 / frames,
        100.0 * tracked as f64 / frames,
        errors.ate_rmse_m,
        errors.rpe_trans_rmse_m,
        errors.rpe_rot_rmse_deg,
        errors.max_error_m,
        errors.over_1m,
        percentile(&lat, 50.0),
        percentile(&lat, 90.0),
        percentile(&lat, 99.0),
        out.len() as f64 / wall.max(1e-9)
    );
    if let Some(line) = accuracy_line(&report["accuracy"]) {
        println!("{line}");
    }
    let written: Vec<String> = [("trajectory", &args.trajectory), ("report", &args.json)]
        .into_iter()
        .filter_map(|(what, path)| {
            path.as_ref()
                .map(|p| format!("{what} written to {}", p.display()))
        })
        .collect();
    if !written.is_empty() {
        eprintln!("{}", written.join(", "));
    }
    if let Some(dir) = &args.plot {
        let truth: Vec<[f64; 3]> = out
            .iter()
            .filter_map(|a| a.truth.map(|t| t.translation.vector.into()))
            .collect();
        let est: Vec<[f64; 3]> = out
            .iter()
            .filter_map(|a| a.estimate.map(|t| t.translation.vector.into()))
            .collect();
        let title = format!(
            "{}: {} frames, {:.1}% localized, ATE {:.3} m",
            args.sequence.display(),
            out.len(),
            100.0 * localized as f64 / frames,
            errors.ate_rmse_m
        );
        let files = crate::plot::trajectory_plot(
            &map_positions(&args.sequence),
            &truth,
            &est,
            dir,
            &title,
        )?;
        eprintln!("{} pictures written to {}", files.len(), dir.display());
    }
    if !record_errors.is_empty() {
        anyhow::bail!(
            "the replay ran and its report is written, but {}",
            record_errors.join("; ")
        );
    }
    Ok(())
}

/// Say once that a recording (`flag`: `--record` or `--record-bag`) could not be written and is
/// abandoned (its partial file or folder is removed when it is dropped), and keep the error for the
/// report and the exit status.
fn abandon_recording(flag: &str, error: String, errors: &mut Vec<String>) {
    let message = format!("{flag} {error}: nothing recorded (the partial output is removed)");
    eprintln!("error: {message}");
    errors.push(message);
}
