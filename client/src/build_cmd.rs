//! `pntr build-db`: a map from a dataset (`--dataset`) or from a robot's own recordings
//! (`--sequence`, `--extend`), with the check of where it works and the map's own calibration
//! ([`pntr_mapping::from_dataset`], [`pntr_mapping::from_recordings`]); the map written, a summary
//! printed.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use pntr_core::Intrinsics;
use pntr_dataset::recording::Recording;
use pntr_dataset::DatasetIndex;
use pntr_mapping::from_recordings::{self, Check, Options, Target};
use pntr_mapping::keyframes::KeyframeParams;
use pntr_mapping::own_calibration::FitOptions;
use pntr_mapping::recording_map::Session;
use pntr_pipeline::calibration::Calibration;
use pntr_pipeline::mapfile;
use pntr_pipeline::preset::{Preset, DEFAULT_PRESET};
use serde_json::json;

use crate::loading::{load_map, models_dir, select_scenes, stages};
use crate::recordings::{as_sessions, open_recording};

/// Arguments of `pntr build-db`.
#[derive(clap::Args, Debug)]
pub struct BuildArgs {
    /// Dataset root (holding HPointLoc_dataset).
    #[arg(
        long,
        required_unless_present = "sequence",
        conflicts_with = "sequence"
    )]
    pub dataset: Option<PathBuf>,
    /// A robot's recording to build the map from instead: a TUM RGB-D folder (rgb.txt, depth.txt,
    /// groundtruth.txt, calibration.txt) or a ROS 2 bag (a rosbag2 folder with metadata.yaml and its
    /// split .mcap files, or one `.mcap`) or a 7-Scenes folder (frame-NNNNNN.color.png|jpg,
    /// .depth.png, .pose.txt; see --depth-to-colour). Repeat it for several sessions
    /// whose poses share one frame. Keyframes become the map's images; poses use the optical camera
    /// axes (the TUM and ROS convention) and the map keeps them.
    #[arg(long, value_name = "DIR|FILE.mcap")]
    pub sequence: Vec<PathBuf>,
    /// Poses of a `--sequence` from this TUM trajectory file (`timestamp tx ty tz qx qy qz qw`,
    /// world_from_camera, optical axes: the output of your SLAM) instead of the recording's own,
    /// interpolated at each frame's stamp. Give one per `--sequence`, in the same order.
    #[arg(long, value_name = "FILE.txt")]
    pub trajectory: Vec<PathBuf>,
    /// The camera as `fx,fy,cx,cy[,k1,k2,p1,p2[,k3]]`, replacing the recording's calibration.txt or
    /// CameraInfo (a distorted camera's frames are undistorted as they are read).
    #[arg(long, value_name = "FX,FY,CX,CY")]
    pub intrinsics: Option<String>,
    /// Depth units per metre, replacing what the recording's format says (TUM PNGs 5000, ROS 16UC1
    /// 1000): e.g. 1000 for a folder of millimetre PNGs, 4000 for a sensor with 0.25 mm units.
    #[arg(long, value_name = "UNITS_PER_M")]
    pub depth_scale: Option<f64>,
    /// ROS 2 bag topics of a `--sequence`.
    #[command(flatten)]
    pub topics: crate::recordings::TopicArgs,
    /// The map's id (what clients name in requests). Default: the scene name or `all` for a dataset,
    /// the first recording's name for `--sequence`.
    #[arg(long)]
    pub map_id: Option<String>,
    /// The world's up axis of a `--sequence` map, `y` or `z` (a ROS `map` frame is z-up). Default:
    /// read from the camera poses (the opposite of the cameras' mean "down" axis).
    #[arg(long, value_name = "y|z")]
    pub up_axis: Option<String>,
    /// Keyframes: a frame farther than this from every map image is kept, metres.
    #[arg(long, default_value_t = 0.3, value_name = "METRES")]
    pub keyframe_distance: f64,
    /// Keyframes: a frame turned more than this from every near map image is kept, degrees.
    #[arg(long, default_value_t = 15.0, value_name = "DEG")]
    pub keyframe_angle: f64,
    /// Keyframes: a frame of which no near map image sees this share is kept (0..1).
    #[arg(long, default_value_t = 0.6, value_name = "SHARE")]
    pub keyframe_overlap: f64,
    /// After building from `--sequence`, localize this other recording against the new map (a
    /// route the map was not built from) instead of the frames between keyframes.
    #[arg(long, value_name = "DIR|FILE.mcap")]
    pub check_sequence: Option<PathBuf>,
    /// Frames the check localizes, evenly spaced (0 = all; none with `--no-check`).
    #[arg(long, default_value_t = 300)]
    pub check_frames: usize,
    /// Skip the check after building from `--sequence`.
    #[arg(long)]
    pub no_check: bool,
    /// Keep the shipped confidence calibration instead of fitting the map's own. By default the
    /// map is cut into regions and frames with known poses (the dataset's queries, or the
    /// recording's frames the map was not built from) are localized against the whole map and with
    /// their own region held out; the LOCALIZED threshold is raised until at most 1 % of the map's
    /// own look-alikes (the held-out frames it places wrongly) stay LOCALIZED, as long as at most 1 %
    /// of the frames answered right are given up, and stored in the map.
    #[arg(long)]
    pub no_self_calibration: bool,
    /// Frames the map's own calibration localizes, evenly spaced (0 = all); each is localized
    /// twice. With a check, the check's frames are used instead and its answers reused.
    #[arg(long, default_value_t = pntr_mapping::recording_map::SELF_CALIBRATION_FRAMES, value_name = "N")]
    pub self_calibration_frames: usize,
    /// Also write every self-calibration frame's answer here (JSON lines: held out or not, its
    /// region, each verified candidate's evidence and whether it is right), to study the map's
    /// look-alikes.
    #[arg(long, value_name = "FILE.jsonl")]
    pub self_calibration_samples: Option<PathBuf>,
    /// Draw the map from above with each checked frame coloured by how it went (PNG and SVG) into
    /// this folder.
    #[arg(long, value_name = "DIR")]
    pub plot: Option<PathBuf>,
    /// Only this scene (map id = the scene name); without it, every scene in one map (map id `all`).
    #[arg(long)]
    pub scene: Option<String>,
    /// The map file to write (atomically: a temporary name, then renamed). With --extend, the
    /// extended map's file [default: the map given to --extend, replaced by its new version].
    #[arg(long, required_unless_present = "extend")]
    pub out: Option<PathBuf>,
    /// Add the keyframes of the --sequence recordings (poses in this map's frame) to this existing
    /// map instead of building a new one: frames the map already covers are left out, the map's
    /// id, preset, axes and retrieval codebook are kept, its index grows, and the file is rewritten
    /// atomically as a new version (or written to --out). Its preset is used; --preset is ignored.
    #[arg(
        long,
        value_name = "MAP.pntrmap",
        requires = "sequence",
        conflicts_with_all = ["dataset", "up_axis", "global_model"]
    )]
    pub extend: Option<PathBuf>,
    /// Preset (fast, fast-norerank, fast-icp, accurate, accurate-icp, classical, xfeat-mnn,
    /// xfeat-mnn-int8, xfeat-mnn-bf16, xfeat-mnn-qvga, xfeat-mnn-bf16-qvga). The `-qvga` ones
    /// describe a recording's frames at 320x240 (a 640x480 or 1280x720 camera then costs the
    /// server about what a 256x256 frame does, for some accuracy: docs/mapping.md).
    #[arg(long, default_value = DEFAULT_PRESET)]
    pub preset: String,
    /// Folder of the ONNX models.
    /// (default: `PNTR_MODELS`, `./models`, next to the executable, `../share/pntr/models`).
    #[arg(long)]
    pub models: Option<PathBuf>,
    /// ONNX global-descriptor model (switches retrieval to `onnx`).
    #[arg(long)]
    pub global_model: Option<PathBuf>,
    /// Threads for ONNX Runtime.
    #[arg(long, default_value_t = 2)]
    pub threads: usize,
    /// Print a JSON summary on stdout.
    #[arg(long)]
    pub json: bool,
}

/// The preset `build-db` builds with (`--global-model` switching retrieval to it).
fn build_preset(args: &BuildArgs) -> Result<Preset> {
    let mut preset = Preset::named(&args.preset)?;
    if let Some(m) = &args.global_model {
        preset.global = "onnx".into();
        preset.global_model = Some(m.clone());
    }
    Ok(preset)
}

/// `pntr build-db`.
pub fn build_db(args: &BuildArgs) -> Result<()> {
    if let Some(id) = &args.map_id {
        pntr_pipeline::map::check_map_id(id).map_err(|e| anyhow::anyhow!("--map-id: {e}"))?;
    }
    let Some(dataset) = &args.dataset else {
        return build_from_recordings(args);
    };
    let index = DatasetIndex::open(dataset)?;
    let (scene_id, scenes) = select_scenes(&index, args.scene.as_deref())?;
    let map_id = args.map_id.clone().unwrap_or(scene_id);
    let preset = build_preset(args)?;
    let models = models_dir(args.models.as_deref())?;
    let out = args.out.as_deref().context("--out is required")?;
    let opts = pntr_mapping::from_dataset::Options {
        map_id,
        preset: preset.clone(),
        self_calibration: (!args.no_self_calibration)
            .then(|| FitOptions::shipped(args.self_calibration_frames)),
    };
    let (map, report) = pntr_mapping::from_dataset::run(
        &scenes,
        opts,
        &stages(&models, args.threads),
        &mut crate::output::bars(),
    )
    .context("building the map (--no-self-calibration skips its own calibration)")?;
    if let Some(why) = &report.calibration_note {
        eprintln!("warning: the map keeps the shipped calibration: {why}");
    }
    if let Some(path) = &args.self_calibration_samples {
        crate::own_calibration::write_samples(path, &report.answers)?;
    }
    let self_calibration_s = report.self_calibration_seconds;
    let t = std::time::Instant::now();
    mapfile::save(&map, out).with_context(|| format!("writing {}", out.display()))?;
    let write_s = t.elapsed().as_secs_f64();
    let bytes = std::fs::metadata(out)?.len();
    let summary = serde_json::json!({
        "map_id": map.header.map_id,
        "preset": preset.name,
        "images": map.images.len(),
        "scenes": map.header.scenes,
        "file": out.display().to_string(),
        "file_bytes": bytes,
        "heap_bytes": map.heap_bytes(),
        "build_seconds": map.header.build_seconds,
        "write_seconds": write_s,
        "self_calibration_seconds": self_calibration_s,
        "calibration": crate::own_calibration::summary(map.header.calibration.as_ref(), false),
    });
    if args.json {
        println!("{}", serde_json::to_string_pretty(&summary)?);
    } else {
        println!(
            "map {} ({} preset): {} database images from {} scene(s) in {:.1} s; {} written in {:.2} s ({:.1} MB)",
            map.header.map_id,
            preset.name,
            map.images.len(),
            map.header.scenes.len(),
            map.header.build_seconds,
            out.display(),
            write_s,
            bytes as f64 / 1e6
        );
        println!(
            "{}",
            crate::own_calibration::line(map.header.calibration.as_ref(), false)
        );
    }
    Ok(())
}

fn keyframe_params(args: &BuildArgs) -> Result<KeyframeParams> {
    let p = KeyframeParams {
        distance_m: args.keyframe_distance,
        angle_deg: args.keyframe_angle,
        min_overlap: args.keyframe_overlap,
        ..KeyframeParams::default()
    };
    if !(p.distance_m.is_finite() && p.distance_m > 0.0) {
        bail!(
            "--keyframe-distance must be a positive number of metres, not {}",
            p.distance_m
        );
    }
    if !(p.angle_deg.is_finite() && p.angle_deg > 0.0 && p.angle_deg <= 180.0) {
        bail!(
            "--keyframe-angle must be within (0, 180] degrees, not {}",
            p.angle_deg
        );
    }
    if !(0.0..=1.0).contains(&p.min_overlap) {
        bail!(
            "--keyframe-overlap must be within 0..1, not {}",
            p.min_overlap
        );
    }
    Ok(p)
}

fn open(
    path: &Path,
    args: &BuildArgs,
    trajectory: Option<&Path>,
) -> Result<(Recording, Intrinsics)> {
    open_recording(
        path,
        trajectory,
        &args.topics,
        args.depth_scale,
        args.intrinsics.as_deref(),
    )
}

/// `pntr build-db --sequence ...` (and `--extend`): [`pntr_mapping::from_recordings::run`], then
/// the map written, the check's pictures drawn and the summary printed.
pub fn build_from_recordings(args: &BuildArgs) -> Result<()> {
    if !args.trajectory.is_empty() && args.trajectory.len() != args.sequence.len() {
        bail!(
            "--trajectory given {} times for {} --sequence: give one per sequence, in the same order",
            args.trajectory.len(),
            args.sequence.len()
        );
    }
    let up_axis = match args.up_axis.as_deref().map(str::to_ascii_lowercase) {
        None => None,
        Some(a) if a == "y" || a == "z" => Some(a),
        Some(a) => bail!("--up-axis {a}: give y or z"),
    };
    if args.scene.is_some() {
        bail!("--scene selects a scene of a --dataset; a --sequence map takes --map-id");
    }
    let params = keyframe_params(args)?;
    let recordings: Vec<(Recording, Intrinsics)> = args
        .sequence
        .iter()
        .enumerate()
        .map(|(i, p)| open(p, args, args.trajectory.get(i).map(|t| t.as_path())))
        .collect::<Result<_>>()?;
    let sessions = as_sessions(&recordings);
    let out = args
        .out
        .clone()
        .or_else(|| args.extend.clone())
        .context("--out is required")?;
    let models = models_dir(args.models.as_deref())?;
    let target = match &args.extend {
        Some(base_path) => {
            if let Some(id) = &args.map_id {
                bail!("--map-id {id}: an extended map keeps its own id (give --out for a copy)");
            }
            Target::Extend(
                load_map(base_path, args.threads)
                    .with_context(|| format!("--extend {}", base_path.display()))?,
            )
        }
        None => Target::New {
            map_id: args
                .map_id
                .clone()
                .unwrap_or_else(|| sessions[0].recording.name()),
            preset: build_preset(args)?,
            up_axis,
        },
    };
    let other = args
        .check_sequence
        .as_deref()
        .map(|p| open(p, args, None))
        .transpose()?;
    let check = (!args.no_check).then(|| Check {
        other: other.as_ref().map(|(recording, camera)| Session {
            recording,
            camera: *camera,
        }),
        frames: args.check_frames,
    });
    let opts = Options {
        target,
        keyframes: params,
        check,
        self_calibrate: !args.no_self_calibration,
        self_calibration_frames: args.self_calibration_frames,
        base_calibration: Calibration::embedded(),
    };
    let (map, report) = from_recordings::run(
        &sessions,
        opts,
        &stages(&models, args.threads),
        &mut crate::output::bars(),
    )
    .with_context(|| match &args.extend {
        Some(base) => format!("extending {}", base.display()),
        None => "building the map".into(),
    })?;
    for w in &report.build.warnings {
        eprintln!("warning: {w}");
    }
    if let Some(why) = &report.calibration_note {
        eprintln!("warning: the map keeps the shipped calibration: {why}");
    }
    if let Some(path) = &args.self_calibration_samples {
        crate::own_calibration::write_samples(path, &report.answers)?;
    }
    let check = &report.check;
    let preset = map.header.preset.clone();
    let self_calibration_s = report.self_calibration_seconds;
    let t = std::time::Instant::now();
    mapfile::save(&map, &out).with_context(|| format!("writing {}", out.display()))?;
    let write_s = t.elapsed().as_secs_f64();
    let bytes = std::fs::metadata(&out)?.len();
    let map_positions: Vec<[f64; 3]> = map
        .images
        .iter()
        .map(|im| im.world_from_camera.translation.vector.into())
        .collect();
    let images = map.images.len();
    let heap = map.heap_bytes();
    let stale = map.calibration_is_stale();
    let header = map.header.clone();
    if let (Some(dir), Some(c)) = (&args.plot, &check) {
        let frames: Vec<crate::plot::CheckedPoint> = c
            .per_frame
            .iter()
            .map(|f| (f.position_m, f.error_m, f.outside_map))
            .collect();
        let title = format!(
            "{}: {images} map images; {} frames checked ({}), {:.1}% localized",
            header.map_id,
            c.frames,
            c.kind,
            100.0 * c.localized_share
        );
        let files = crate::plot::check_plot(
            &map_positions,
            &frames,
            crate::plot::ground_of(&header.up_axis),
            dir,
            &title,
        )?;
        eprintln!("{} pictures written to {}", files.len(), dir.display());
    }
    let mut stage_seconds = from_recordings::stage_seconds(&report);
    stage_seconds.insert("write".into(), write_s);
    let summary = json!({
        "map_id": header.map_id,
        "preset": preset.name,
        "images": images,
        "scenes": header.scenes,
        "file": out.display().to_string(),
        "extended": args.extend.as_ref().map(|p| p.display().to_string()),
        "base_images": report.build.base_images,
        "images_added": images - report.build.base_images,
        "file_bytes": bytes,
        "heap_bytes": heap,
        "build_seconds": header.build_seconds,
        "write_seconds": write_s,
        "frames": report.build.frames,
        "skipped": report.build.skipped,
        "places": report.build.places,
        "camera_axes": header.camera_axes,
        "up_axis": header.up_axis,
        "up_axis_inferred": report.build.up_axis_inferred,
        "stage_seconds": stage_seconds,
        "self_calibration_seconds": self_calibration_s,
        "sequences": args.sequence.iter().map(|p| p.display().to_string()).collect::<Vec<_>>(),
        "check": check.as_ref().map(serde_json::to_value).transpose()?,
        "calibration": crate::own_calibration::summary(header.calibration.as_ref(), stale),
        "warnings": report.build.warnings,
    });
    if args.json {
        println!("{}", serde_json::to_string_pretty(&summary)?);
        return Ok(());
    }
    let kept = if args.extend.is_some() {
        format!(
            "{} keyframes added to its {} images ({images} now) from",
            images - report.build.base_images,
            report.build.base_images
        )
    } else {
        format!("{images} keyframes of")
    };
    println!(
        "map {} ({} preset): {kept} {} frames in {} places (left out: {}), axes {} with up {}; {} written ({:.1} MB)",
        header.map_id,
        preset.name,
        report.build.frames,
        report.build.places,
        report
            .build
            .skipped
            .iter()
            .map(|(k, v)| format!("{v} {k}"))
            .collect::<Vec<_>>()
            .join(", "),
        header.camera_axes,
        header.up_axis,
        out.display(),
        bytes as f64 / 1e6
    );
    if let Some(c) = &check {
        println!(
            "check ({}): {} frames, {:.1}% localized, ATE {:.3} m, {} more than 1 m off, {} outside what the map covers",
            c.kind,
            c.frames,
            100.0 * c.localized_share,
            c.ate_rmse_m,
            c.frames_over_1m,
            c.frames_outside_map
        );
    }
    println!(
        "{}",
        crate::own_calibration::line(header.calibration.as_ref(), stale)
    );
    Ok(())
}
