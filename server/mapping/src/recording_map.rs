//! Maps from a robot's own recordings: keyframes of one or more drives (TUM folders, ROS 2 bags) that
//! share one world frame become the map's images, and the frames left out tell where the map works.
//!
//! Frames are read one at a time, in time order ([`pntr_dataset::recording::Recording`]); a frame is
//! judged by [`crate::keyframes::Selector`] and only kept frames are described (features, 3D points,
//! thumbnail), so memory grows with the map, not with the recording. A distorted camera's frames are
//! undistorted as they are read ([`pntr_pipeline::camera::to_map_scale`] at the camera's own scale), so maps
//! hold rectified images. The map keeps the recordings' conventions: optical camera axes, and the
//! world's up axis as given or as the camera poses show it (the mean of the cameras' "down" axes).
//!
//! [`check`] localizes frames the map was not built from against it (the frames between keyframes,
//! or another recording) and compares with the recording's poses.

use std::collections::BTreeMap;
use std::time::Instant;

use nalgebra::{Isometry3, Vector3};
use pntr_core::{CameraAxes, DepthMap, Intrinsics, RgbImage};
use pntr_dataset::recording::{depth_unit_hint, Recording};
use pntr_features::config::FeatureStage;
use serde::Serialize;

use crate::build::{MapBuilder, NewImage};
use crate::keyframes::{KeyframeParams, Selector, Skip};
use pntr_pipeline::map::{Map, SessionRecord};
use pntr_pipeline::pipeline::{Pipeline, Query};
use pntr_pipeline::preset::Preset;
use pntr_pipeline::prior::LocalizeOptions;
use pntr_pipeline::verify::Thumb;
use pntr_pipeline::PipelineError;

/// Frames of each recording whose depth outlines are checked against their colour edges
/// ([`pntr_dataset::depth_alignment`]; at most about 12 ms each at 640x480), evenly spread.
pub const ALIGNMENT_FRAMES: usize = 8;

/// One recording to build from, with the camera its frames are read with.
pub struct Session<'a> {
    /// The recording.
    pub recording: &'a Recording,
    /// Its camera (from the recording, or the user's `--intrinsics`).
    pub camera: Intrinsics,
}

/// What [`build`] did.
#[derive(Debug, Clone, Default, Serialize)]
pub struct BuildReport {
    /// Frames read, over every session.
    pub frames: usize,
    /// Frames left out, by reason ([`Skip::name`]).
    pub skipped: BTreeMap<String, usize>,
    /// Seconds per stage: `read` (decoding frames), `select` (quality and keyframe tests),
    /// `describe` (features of kept frames), `index` (retrieval training and indexing).
    pub stage_seconds: BTreeMap<String, f64>,
    /// Places (the map's Points).
    pub places: usize,
    /// The world's up axis the map records, and whether it was inferred from the poses.
    pub up_axis: String,
    /// True when `up_axis` came from the camera poses rather than the caller.
    pub up_axis_inferred: bool,
    /// (session, frame) of every frame that had a pose and was readable but was not kept: what
    /// [`check`] localizes by default.
    #[serde(skip)]
    pub left_out: Vec<(usize, usize)>,
    /// Warnings for the user (unreadable frames, a world whose up axis is unusual).
    pub warnings: Vec<String>,
    /// Images the map had before ([`extend`]); 0 for a new map.
    pub base_images: usize,
}

/// The frame as the map describes it, and its camera: undistorted when `camera` is distorted (same
/// focal length), and resampled to `max_pixels` pixels (aspect ratio kept) when it has more
/// ([`Preset::max_image_pixels`]; 0 keeps every size).
fn rectified(
    rgb: RgbImage,
    depth: DepthMap,
    camera: &Intrinsics,
    max_pixels: usize,
) -> (RgbImage, DepthMap, Intrinsics) {
    let pixels = camera.width as f64 * camera.height as f64;
    let scale = if max_pixels > 0 && pixels > max_pixels as f64 {
        (max_pixels as f64 / pixels).sqrt()
    } else {
        1.0
    };
    if !camera.is_distorted() && scale == 1.0 {
        return (rgb, depth, *camera);
    }
    let q = Query {
        rgb,
        depth,
        intrinsics: *camera,
    };
    let focal = (camera.fx * camera.fy).sqrt() * scale;
    let r = pntr_pipeline::camera::to_map_scale(&q, focal, pixels * scale * scale)
        .query
        .into_owned();
    (r.rgb, r.depth, r.intrinsics)
}

/// The world's up axis the cameras show: the opposite of their mean "down" (optical +y) axis, as the
/// nearest of `y` and `z`, with a warning when it points the other way or is not clear.
fn infer_up(down_sum: &Vector3<f64>, n: usize) -> (String, Option<String>) {
    if n == 0 || down_sum.norm() < 1e-9 {
        return ("y".into(), None);
    }
    let up = -down_sum / n as f64;
    let (axis, v) = if up.z.abs() > up.y.abs() {
        ("z", up.z)
    } else {
        ("y", up.y)
    };
    let warning = if v < 0.0 {
        Some(format!(
            "the cameras' down axes point along +{axis} on average: the world is upside down for pntr's up = +{axis}; give --up-axis if that is wrong"
        ))
    } else if v.abs() < 0.7 * up.norm().max(1e-9) {
        Some(format!(
            "the cameras' mean up direction ({:.2}, {:.2}, {:.2}) is not close to the y or z axis; up recorded as {axis}. Are the poses of the optical frame (x right, y down, z forward)? A body frame such as camera_link or base_link (x forward, z up) gives this: check --camera-frame or --pose-topic (or give --up-axis if the poses are right)",
            up.x, up.y, up.z
        ))
    } else {
        None
    };
    (axis.to_string(), warning)
}

/// Build a map of `sessions` (one world frame) with `preset`, describing kept frames with `stage`
/// ([`Preset::map_feature_config`]). `up_axis`: `y` or `z`, or `None` to infer it. Image ids are
/// `<recording name>/place<P>/<stamp>`. `progress(frames done, frames in all)` after every frame.
///
/// Errors: no session frame has a pose (name the recording and what to give), a depth whose median
/// is not an indoor range (the likely unit mistake, and `--depth-scale`), no frame kept, and what the
/// map builder refuses.
#[allow(clippy::too_many_arguments)]
pub fn build(
    map_id: &str,
    sessions: &[Session<'_>],
    params: KeyframeParams,
    up_axis: Option<&str>,
    preset: &Preset,
    stage: &FeatureStage,
    models_dir: &std::path::Path,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<(Map, BuildReport), PipelineError> {
    let mut builder = MapBuilder::new(preset, stage)?;
    let mut selector = Selector::new(params);
    let mut report = BuildReport::default();
    let (seconds, down_sum, posed) = collect(
        &mut builder,
        &mut selector,
        sessions,
        (CameraAxes::OpenCv, preset.max_image_pixels),
        &mut report,
        progress,
    )?;
    let (up, warning) = match up_axis {
        Some(a) => (a.to_string(), None),
        None => infer_up(&down_sum, posed),
    };
    report.up_axis_inferred = up_axis.is_none();
    report.warnings.extend(warning);
    report.up_axis = up.clone();
    report.places = selector.places();
    let t = Instant::now();
    let mut map = builder.finish(
        map_id,
        vec![map_id.to_string()],
        CameraAxes::OpenCv,
        &up,
        models_dir,
    )?;
    map.header.sessions = sessions.iter().map(|s| record_of(s.recording)).collect();
    record_seconds(&mut report, seconds, t.elapsed().as_secs_f64());
    Ok((map, report))
}

/// What a map remembers of a recording it holds.
fn record_of(rec: &Recording) -> SessionRecord {
    let n = rec.len();
    SessionRecord {
        name: rec.name(),
        frames: n,
        first_stamp: if n > 0 { rec.timestamp(0) } else { f64::NAN },
        last_stamp: if n > 0 {
            rec.timestamp(n - 1)
        } else {
            f64::NAN
        },
    }
}

/// Add the keyframes of `sessions` (poses in `base`'s frame) to map `base`, which keeps its id,
/// header, camera axes, up axis and learned retrieval (its index grows; [`MapBuilder::extending`]).
/// Frames the map already covers are left out by the keyframe rule, as between a recording's own
/// frames; new keyframes join the map's places within [`crate::keyframes::PLACE_RADIUS_M`] or start
/// new ones. Describe with `stage` built from the base's preset.
///
/// Errors: a map of several scenes (several world frames: which one would the recording be in?),
/// those of [`build`], and no new frame kept (the recording adds nothing the map does not have).
pub fn extend(
    base: Map,
    sessions: &[Session<'_>],
    params: KeyframeParams,
    preset: &Preset,
    stage: &FeatureStage,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<(Map, BuildReport), PipelineError> {
    if base.header.scenes.len() > 1 {
        return Err(PipelineError::Refused(format!(
            "map `{}` holds {} scenes, each in its own world frame: extend a map of one scene (build-db --dataset ... --scene NAME)",
            base.header.map_id,
            base.header.scenes.len()
        )));
    }
    for s in sessions {
        let r = record_of(s.recording);
        // The same frames, whatever the folder is called now (a copy, a renamed bag).
        let same = |o: &SessionRecord| {
            o.frames == r.frames && o.first_stamp == r.first_stamp && o.last_stamp == r.last_stamp
        };
        if base.header.sessions.iter().any(same) {
            return Err(PipelineError::Refused(format!(
                "{} is already in map `{}` ({} frames from {:.3} s to {:.3} s): it was built or extended with it",
                s.recording.path.display(),
                base.header.map_id,
                r.frames,
                r.first_stamp,
                r.last_stamp
            )));
        }
    }
    let added: Vec<SessionRecord> = sessions.iter().map(|s| record_of(s.recording)).collect();
    let axes = base.header.axes();
    refuse_turned_world(&base, axes, sessions)?;
    let mut selector = Selector::new(params);
    selector.seed(base.images.iter().map(|im| {
        (
            pntr_core::pose::convert_axes(&im.world_from_camera, axes, CameraAxes::OpenCv),
            im.camera,
            im.point,
            im.thumb.clone(),
        )
    }));
    let mut report = BuildReport {
        base_images: base.images.len(),
        up_axis: base.header.up_axis.clone(),
        ..BuildReport::default()
    };
    // The map's own working resolution, so the new images share its scale.
    let max_pixels = base.header.preset.max_image_pixels;
    let mut builder = MapBuilder::extending(base, preset, stage)?;
    let (seconds, _, _) = collect(
        &mut builder,
        &mut selector,
        sessions,
        (axes, max_pixels),
        &mut report,
        progress,
    )?;
    if builder.len() == builder.base_len() {
        return Err(PipelineError::Refused(format!(
            "no frame was added: the map already covers every usable frame ({} read; left out: {:?})",
            report.frames, report.skipped
        )));
    }
    refuse_contradicted(builder.images(), builder.base_len(), axes, sessions)?;
    report.places = selector.places();
    let t = Instant::now();
    let mut map = builder.finish_extension()?;
    map.header.sessions.extend(added);
    record_seconds(&mut report, seconds, t.elapsed().as_secs_f64());
    Ok((map, report))
}

/// Largest angle, degrees, between the cameras' mean down direction (optical +y) in a map and in a
/// recording that extends it. Cameras carried by a robot or a person keep their down axis near the
/// world's down (a mean within 30 degrees of it, whatever the route); a recording whose world is
/// another convention's (y-up against z-up: 90 degrees; y-down against y-up: 180) is far beyond.
pub const MAX_DOWN_ANGLE_DEG: f64 = 60.0;
/// The mean down direction must be at least this long (of unit vectors) to say anything: cameras
/// looking every way (a survey of a ceiling and a floor) have no common down.
pub const MIN_DOWN_CONSISTENCY: f64 = 0.5;

/// Refuse an extension whose recording's world is turned against the map's (another up axis, or
/// upside down), from the cameras' mean down directions, before any frame is described. The map's
/// own views cannot judge such poses (they lie where no map camera sees).
fn refuse_turned_world(
    base: &Map,
    axes: CameraAxes,
    sessions: &[Session<'_>],
) -> Result<(), PipelineError> {
    let mean = |downs: &mut dyn Iterator<Item = Vector3<f64>>| {
        let (sum, n) = downs.fold((Vector3::zeros(), 0usize), |(s, n), d| (s + d, n + 1));
        (n > 0).then(|| sum / n as f64)
    };
    let Some(map_down) = mean(&mut base.images.iter().map(|im| {
        pntr_core::pose::convert_axes(&im.world_from_camera, axes, CameraAxes::OpenCv).rotation
            * Vector3::y()
    })) else {
        return Ok(());
    };
    for s in sessions {
        let rec = s.recording;
        let Some(rec_down) = mean(
            &mut (0..rec.len())
                .filter_map(|i| rec.world_from_camera(i))
                .map(|p| p.rotation * Vector3::y()),
        ) else {
            continue;
        };
        if map_down.norm() < MIN_DOWN_CONSISTENCY || rec_down.norm() < MIN_DOWN_CONSISTENCY {
            continue;
        }
        let angle = map_down.angle(&rec_down).to_degrees();
        if angle > MAX_DOWN_ANGLE_DEG {
            let show = |v: &Vector3<f64>| {
                let u = v.normalize();
                format!("({:.2}, {:.2}, {:.2})", u.x, u.y, u.z)
            };
            return Err(PipelineError::Refused(format!(
                "{}: its poses are in another frame than map `{}`'s: its cameras' mean down direction {} is {angle:.0} deg from the map's {} (map up axis {}), as when one world is y-up and the other z-up (a REP 103 bag against a y-up render or TUM folder) or upside down. Give the recording's poses in the map's frame, or build a map of it and join the two with `pntr maps merge`; nothing was written",
                rec.path.display(),
                base.header.map_id,
                show(&rec_down),
                show(&map_down),
                base.header.up_axis
            )));
        }
    }
    Ok(())
}

/// Share of an extension's new images that the map's own views may contradict before the
/// extension is refused (among those the views can judge).
pub const MAX_CONTRADICTED_SHARE: f64 = 0.5;
/// Fewest new images the map's views must judge before an extension can be refused.
pub const MIN_JUDGED: usize = 3;
/// A new image is contradicted when even the map view that agrees best with it agrees on less than
/// this share of the samples that land on its depth. Measured (the best view's share, per judged
/// image): right sessions 0.55-0.99, median 0.70 (a rendered apartment's other route under other
/// lighting) and 0.85-0.96 (real Kinect, 7-Scenes redkitchen 250-499 onto 0-249); other apartments
/// with overlapping coordinates median 0.07, 0.25 and 0.42 (rendered seeds 45, 9 and 5 onto 44's).
pub const MIN_BEST_AGREEMENT: f64 = 0.5;

/// Refuse an extension whose new images (`images[base_len..]`) the map's own images
/// (`images[..base_len]`) contradict where they see the same places: a drive of another building
/// whose poses happen to overlap the map's coordinates, or poses in another frame. Each new image's
/// thumbnail is moved into the map's images near its pose and looking its way (those of
/// [`pntr_pipeline::agreement::map_agreement`]); a view judges when at least a third of the image's samples
/// land on its depth, and the image is contradicted when even the best of them agrees on less than
/// [`MIN_BEST_AGREEMENT`] of those. Images the map has no view of (a new wing) are not judged; depth
/// does not change with the lighting, so a session under other lighting agrees.
fn refuse_contradicted(
    images: &[pntr_pipeline::map::MapImage],
    base_len: usize,
    axes: CameraAxes,
    sessions: &[Session<'_>],
) -> Result<(), PipelineError> {
    let (base, new) = images.split_at(base_len);
    let index = pntr_pipeline::prior::PoseIndex::new(
        base.iter()
            .map(|im| im.world_from_camera.translation.vector)
            .collect(),
    );
    let mut judged = 0usize;
    let mut contradicted = Vec::new();
    for im in new {
        let pose = pntr_core::pose::convert_axes(&im.world_from_camera, axes, CameraAxes::OpenCv);
        let views = pntr_pipeline::agreement::nearby_views(base, &index, axes, &im.thumb, &pose);
        let best = views
            .iter()
            .filter(|c| {
                c.inside >= pntr_pipeline::agreement::MIN_INSIDE && c.overlap() >= 1.0 / 3.0
            })
            .map(|c| c.agree_share())
            .max_by(f64::total_cmp);
        tracing::debug!(id = %im.id, ?best, "a new image against the map's views");
        let Some(best) = best else {
            continue;
        };
        judged += 1;
        if best < MIN_BEST_AGREEMENT {
            contradicted.push(im.id.as_str());
        }
    }
    tracing::debug!(
        judged,
        contradicted = contradicted.len(),
        "new images against the map's views"
    );
    if judged >= MIN_JUDGED && contradicted.len() as f64 > MAX_CONTRADICTED_SHARE * judged as f64 {
        let names: Vec<String> = sessions
            .iter()
            .map(|s| s.recording.path.display().to_string())
            .collect();
        return Err(PipelineError::Refused(format!(
            "{} of the {judged} new images the map's own views can judge ({:.0}%) are contradicted by them: where both see, their depth disagrees with the map's (first: {}): {} is not of this map's place in this map's frame (another building, or poses in another frame: `pntr maps merge` joins a session in another frame); nothing was written",
            contradicted.len(),
            100.0 * contradicted.len() as f64 / judged as f64,
            contradicted[..contradicted.len().min(3)].join(", "),
            names.join(", ")
        )));
    }
    Ok(())
}

fn record_seconds(report: &mut BuildReport, seconds: [f64; 3], index_s: f64) {
    for (k, v) in [
        ("read", seconds[0]),
        ("select", seconds[1]),
        ("describe", seconds[2]),
        ("index", index_s),
    ] {
        report.stage_seconds.insert(k.into(), v);
    }
}

/// Read every session's frames in order, judge them, and describe the kept ones into `builder`
/// with poses in the map's camera axes `axes` (recordings give optical ones). Returns the seconds
/// spent reading, selecting and describing, the sum of the cameras' down axes and how many posed
/// frames were read (for the up axis).
fn collect(
    builder: &mut MapBuilder<'_>,
    selector: &mut Selector,
    sessions: &[Session<'_>],
    (axes, max_pixels): (CameraAxes, usize),
    report: &mut BuildReport,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<([f64; 3], Vector3<f64>, usize), PipelineError> {
    let total: usize = sessions.iter().map(|s| s.recording.len()).sum();
    let known: std::collections::HashSet<String> =
        builder.images().iter().map(|im| im.id.clone()).collect();
    let mut seconds = [0.0f64; 3];
    let mut down_sum = Vector3::zeros();
    let mut posed = 0usize;
    let mut unreadable_logged = 0;
    let mut pose_check = pntr_pipeline::pose_check::PoseCheck::default();
    for (si, s) in sessions.iter().enumerate() {
        selector.new_session();
        pose_check.new_session();
        // Frames whose recorded pose their images contradict: (frame, stamp, why).
        let mut disagreeing: Vec<(usize, f64, String)> = Vec::new();
        let rec = s.recording;
        for w in rec.warnings() {
            report.warnings.push(format!("{}: {w}", rec.path.display()));
        }
        let name = rec.name();
        let mut unit_checked = false;
        // Depth outlines against colour edges on a few frames spread over the recording
        // ([`pntr_dataset::depth_alignment`]): unregistered depth is named, not only mapped badly.
        let align_every = (rec.len() / ALIGNMENT_FRAMES).max(1);
        let mut alignments = Vec::new();
        let mut session_posed = 0usize;
        for i in 0..rec.len() {
            report.frames += 1;
            progress(report.frames, total);
            let Some(pose) = rec.world_from_camera(i) else {
                *report
                    .skipped
                    .entry(Skip::NoPose.name().into())
                    .or_default() += 1;
                continue;
            };
            session_posed += 1;
            let t = Instant::now();
            let frame = rec.load(i);
            seconds[0] += t.elapsed().as_secs_f64();
            let (rgb, depth) = match frame {
                Ok(f) => f,
                Err(e) => {
                    *report
                        .skipped
                        .entry(Skip::Unreadable.name().into())
                        .or_default() += 1;
                    if unreadable_logged < 5 {
                        tracing::warn!("{}: frame {i} skipped: {e}", rec.path.display());
                        report
                            .warnings
                            .push(format!("{}: frame {i} skipped: {e}", rec.path.display()));
                        unreadable_logged += 1;
                    }
                    continue;
                }
            };
            if (rgb.width, rgb.height) != (s.camera.width, s.camera.height) {
                return Err(PipelineError::Config(format!(
                    "{}: frame {i} is {}x{} but the camera is {}x{}: the calibration describes another resolution (give --intrinsics for the recorded size)",
                    rec.path.display(),
                    rgb.width,
                    rgb.height,
                    s.camera.width,
                    s.camera.height
                )));
            }
            if !unit_checked && depth.valid_count() > 0 {
                if let Some(hint) = depth_unit_hint(&depth, rec.depth_units_per_m()) {
                    return Err(PipelineError::Config(format!(
                        "{}: frame {i}: {hint}",
                        rec.path.display()
                    )));
                }
                unit_checked = true;
            }
            if i % align_every == 0 && alignments.len() < ALIGNMENT_FRAMES {
                alignments.push(pntr_dataset::depth_alignment::measure(&rgb, &depth));
            }
            down_sum += pose.rotation * Vector3::y();
            posed += 1;
            let t = Instant::now();
            let (rgb, depth, camera) = rectified(rgb, depth, &s.camera, max_pixels);
            let stamp = rec.timestamp(i);
            if let pntr_pipeline::pose_check::Verdict::Disagrees(why) =
                pose_check.judge(Thumb::new(&rgb, &depth, &camera), &pose, stamp)
            {
                seconds[1] += t.elapsed().as_secs_f64();
                *report
                    .skipped
                    .entry(Skip::PoseDisagrees.name().into())
                    .or_default() += 1;
                disagreeing.push((i, stamp, why));
                continue;
            }
            let verdict = selector.judge(&rgb, &depth, &camera, &pose);
            seconds[1] += t.elapsed().as_secs_f64();
            match verdict {
                Err(skip) => {
                    *report.skipped.entry(skip.name().into()).or_default() += 1;
                    report.left_out.push((si, i));
                }
                Ok(place) => {
                    let t = Instant::now();
                    let id = format!("{name}/place{place}/{stamp:.6}");
                    if known.contains(&id) {
                        // The same frame of the same recording, already in the map.
                        *report
                            .skipped
                            .entry(Skip::Covered.name().into())
                            .or_default() += 1;
                        continue;
                    }
                    builder.add(NewImage {
                        id,
                        scene: 0,
                        point: place,
                        world_from_camera: pntr_core::pose::convert_axes(
                            &pose,
                            CameraAxes::OpenCv,
                            axes,
                        ),
                        stamp: Some(stamp),
                        rgb: &rgb,
                        depth: &depth,
                        labels: None,
                        camera,
                    })?;
                    seconds[2] += t.elapsed().as_secs_f64();
                }
            }
        }
        if let Some((first, first_stamp, why)) = disagreeing.first() {
            let n = disagreeing.len();
            let frames: Vec<String> = disagreeing
                .iter()
                .take(8)
                .map(|(i, _, _)| i.to_string())
                .collect();
            let said = format!(
                "{n} of {session_posed} posed frames' poses disagree with their own images (frames {}{}; the first, frame {first} at {first_stamp:.3} s: {why}): a pose source that stalled or jumped, or poses of another frame than the camera's",
                frames.join(", "),
                if n > frames.len() { ", ..." } else { "" }
            );
            if n >= 10 && 2 * n > session_posed {
                return Err(PipelineError::Config(format!(
                    "{}: {said}; refused, since most frames disagree (check --camera-frame, --pose-topic or the trajectory's time base)",
                    rec.path.display()
                )));
            }
            report
                .warnings
                .push(format!("{}: {said}; they are left out", rec.path.display()));
        }
        tracing::debug!(
            "{}: depth outlines against colour edges: {alignments:?}",
            rec.path.display()
        );
        if let Some(hint) = pntr_dataset::depth_alignment::misregistration_hint(&alignments) {
            report
                .warnings
                .push(format!("{}: {hint}", rec.path.display()));
        }
        if session_posed == 0 {
            let why = rec
                .pose_problem()
                .map(|p| format!(": {p}"))
                .unwrap_or_default();
            return Err(PipelineError::Config(format!(
                "{}: no frame has a pose{why} (give --trajectory FILE.txt with the SLAM's poses, or for a bag --pose-topic, or --map-frame and --camera-frame for TF)",
                rec.path.display()
            )));
        }
    }
    if builder.is_empty() {
        return Err(PipelineError::Config(format!(
            "no frame was kept as a map image ({} read; left out: {:?})",
            report.frames, report.skipped
        )));
    }
    Ok((seconds, down_sum, posed))
}

/// One frame localized by [`check`].
#[derive(Debug, Clone, Serialize)]
pub struct CheckedFrame {
    /// The recording's position of the frame, map frame, metres.
    pub position_m: [f64; 3],
    /// Position error of the answer, metres, when LOCALIZED.
    pub error_m: Option<f64>,
    /// The map's surfaces explain less than [`pntr_pipeline::pipeline::MIN_EXPLAINED`] of the frame's depth
    /// at its recorded pose ([`pntr_pipeline::coverage::Coverage::explained`]): a part of the drive the map
    /// does not cover, where a stream answers OUTSIDE_MAP.
    pub outside_map: bool,
}

/// How frames the map was not built from localize against it.
#[derive(Debug, Clone, Default, Serialize)]
pub struct CheckReport {
    /// Frames localized.
    pub frames: usize,
    /// Share of them LOCALIZED.
    pub localized_share: f64,
    /// RMSE of the LOCALIZED frames' positions against the recording's, metres (in the map's own
    /// frame, no alignment; NaN when none).
    pub ate_rmse_m: f64,
    /// LOCALIZED frames more than 1 m off.
    pub frames_over_1m: usize,
    /// LOCALIZED frames more than 10 degrees off.
    pub frames_over_10deg: usize,
    /// Frames whose view, at the recording's pose, the map's surfaces do not explain
    /// ([`CheckedFrame::outside_map`]): the parts of the drive the map does not cover.
    pub frames_outside_map: usize,
    /// What the frames were: `between keyframes` (the easy case) or `another recording`.
    pub kind: String,
    /// Seconds the check took.
    pub seconds: f64,
    /// Every frame, for pictures.
    #[serde(skip)]
    pub per_frame: Vec<CheckedFrame>,
    /// Every frame's verified candidates, labelled, for the map's own calibration (only when
    /// [`check`] was given the map's regions).
    #[serde(skip)]
    pub answers: Vec<crate::selfcal::Answered>,
}

/// Localize `frames` ((recording, frame) of `sessions`) against `pipeline`'s map, one at a time and
/// globally (no prior, no tracking), and compare with the recordings' poses. Unreadable frames and
/// frames without a pose are passed over. With `regions`, each frame's answer is also kept
/// ([`CheckReport::answers`]) as the in-map pass of the map's own calibration. `progress(done,
/// total)` after every frame.
pub fn check(
    pipeline: &Pipeline,
    sessions: &[Session<'_>],
    frames: &[(usize, usize)],
    kind: &str,
    regions: Option<&crate::selfcal::Regions>,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<CheckReport, PipelineError> {
    let t0 = Instant::now();
    let mut out = CheckReport {
        kind: kind.into(),
        ..Default::default()
    };
    let (mut localized, mut sq) = (0usize, 0.0f64);
    for (n, &(si, i)) in frames.iter().enumerate() {
        progress(n + 1, frames.len());
        let s = &sessions[si];
        let Some(truth) = s.recording.world_from_camera(i) else {
            continue;
        };
        let Ok((rgb, depth)) = s.recording.load(i) else {
            continue;
        };
        let q = Query {
            rgb,
            depth,
            intrinsics: s.camera,
        };
        // Recordings' poses are of the optical camera, in the map's world frame.
        let thumb = pntr_pipeline::verify::Thumb::new(&q.rgb, &q.depth, &q.intrinsics);
        let outside_map = pipeline
            .coverage()
            .explained(&thumb, &truth)
            .is_some_and(|share| share < pntr_pipeline::pipeline::MIN_EXPLAINED);
        out.frames_outside_map += outside_map as usize;
        let loc = pipeline.localize_with(&q, &LocalizeOptions::default())?;
        let position = truth.translation.vector;
        if let Some(r) = regions.and_then(|r| r.of_position(&pipeline.map, 0, &position)) {
            out.answers
                .push(crate::selfcal::answered(&loc, &truth, r, false));
        }
        out.frames += 1;
        let error_m = loc.pose.map(|p: Isometry3<f64>| {
            let d = (p.translation.vector - truth.translation.vector).norm();
            localized += 1;
            sq += d * d;
            out.frames_over_1m += (d > 1.0) as usize;
            out.frames_over_10deg +=
                (p.rotation.angle_to(&truth.rotation).to_degrees() > 10.0) as usize;
            d
        });
        out.per_frame.push(CheckedFrame {
            position_m: truth.translation.vector.into(),
            error_m,
            outside_map,
        });
    }
    out.localized_share = localized as f64 / out.frames.max(1) as f64;
    out.ate_rmse_m = if localized > 0 {
        (sq / localized as f64).sqrt()
    } else {
        f64::NAN
    };
    out.seconds = t0.elapsed().as_secs_f64();
    Ok(out)
}

/// Frames of a recording map's own calibration by default: evenly spaced over what there is, each
/// localized twice (against the whole map, and with its region held out).
pub const SELF_CALIBRATION_FRAMES: usize = 300;

/// Frame `i` of `frames` ((session, frame) of `sessions`) as a posed query for the map's own
/// calibration: its images and camera, and its recorded `world_from_camera` (the map's frame).
/// `None` for a frame without a pose or whose images cannot be read.
pub fn posed_frame(
    sessions: &[Session<'_>],
    frames: &[(usize, usize)],
    i: usize,
) -> Option<crate::selfcal::PosedFrame> {
    let (si, fi) = frames[i];
    let s = &sessions[si];
    let truth = s.recording.world_from_camera(fi)?;
    let (rgb, depth) = s.recording.load(fi).ok()?;
    Some(crate::selfcal::PosedFrame {
        query: Query {
            rgb,
            depth,
            intrinsics: s.camera,
        },
        world_from_camera: truth,
        scene: 0,
    })
}

/// The own calibration of the map `pipeline` serves (with `base`'s weights), fitted on `frames` of
/// `sessions` (recordings whose poses are in the map's frame): every frame localized against the
/// whole map (or `in_map`, those answers when [`check`] already made them) and again with its
/// region of `regions` held out ([`crate::selfcal::pass`]), then [`crate::selfcal::fit`] from
/// `base`, dated today. What `pntr build-db` and `pntr calibrate --sequence` run, and a server's
/// `ExtendMap` on the frames it was given. Returns the fit (`Err(PipelineError::Refused)` when
/// these frames cannot calibrate the map, saying why) and every frame's answers. `progress(held_out,
/// done, total)` after each frame. Errors: a frame the pipeline fails on.
pub fn fit_own_calibration(
    pipeline: &Pipeline,
    base: &pntr_pipeline::calibration::Calibration,
    regions: &crate::selfcal::Regions,
    sessions: &[Session<'_>],
    frames: &[(usize, usize)],
    in_map: Option<Vec<crate::selfcal::Answered>>,
    progress: &mut dyn FnMut(bool, usize, usize),
) -> Result<FittedCalibration, PipelineError> {
    let mut frame = |i: usize| Ok(posed_frame(sessions, frames, i));
    let n = frames.len();
    let mut answers = match in_map {
        Some(a) => a,
        None => crate::selfcal::pass(pipeline, regions, n, false, &mut frame, &mut |d, n| {
            progress(false, d, n)
        })?,
    };
    answers.extend(crate::selfcal::pass(
        pipeline,
        regions,
        n,
        true,
        &mut frame,
        &mut |d, n| progress(true, d, n),
    )?);
    let fit = crate::selfcal::fit(base, &pipeline.map, regions, &answers, &crate::fit::today());
    Ok(FittedCalibration { fit, answers })
}

/// What [`fit_own_calibration`] made.
pub struct FittedCalibration {
    /// The map's own calibration, or why these frames could not make one
    /// (`PipelineError::Refused`).
    pub fit: Result<pntr_pipeline::calibration::MapCalibration, PipelineError>,
    /// Every frame's answers (against the whole map, then held out).
    pub answers: Vec<crate::selfcal::Answered>,
}

/// At most `max` of `frames`, evenly spaced (all when `max` is 0 or there are fewer).
pub fn evenly(frames: &[(usize, usize)], max: usize) -> Vec<(usize, usize)> {
    if max == 0 || frames.len() <= max {
        return frames.to_vec();
    }
    (0..max).map(|k| frames[k * frames.len() / max]).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn up_is_read_from_the_cameras_down_axes() {
        // Level optical cameras in a y-up world look down along -y; in a z-up world along -z.
        assert_eq!(
            infer_up(&Vector3::new(0.0, -10.0, 0.5), 10),
            ("y".into(), None)
        );
        assert_eq!(infer_up(&Vector3::new(0.3, 0.0, -9.0), 10).0, "z");
        let (axis, warning) = infer_up(&Vector3::new(0.0, 0.0, 9.0), 10);
        assert_eq!(axis, "z");
        assert!(warning.unwrap().contains("upside down"));
        assert_eq!(
            evenly(&[(0, 1), (0, 2), (0, 3), (0, 4)], 2),
            vec![(0, 1), (0, 3)]
        );
    }
}
