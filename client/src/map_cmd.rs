//! `pntr build-db` and `pntr eval`: build a map from a dataset, evaluate the pipeline on its queries.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use anyhow::{Context, Result};
use indicatif::{ProgressBar, ProgressStyle};
use pntr_dataset::{DatasetIndex, SceneEntry};
use pntr_eval::{self as eval, Answer, EvalOptions, EvalReport};
use pntr_features::runtime::RuntimeOptions;
use pntr_pipeline::calibration::Calibration;
use pntr_pipeline::map::Map;
use pntr_pipeline::mapfile;
use pntr_pipeline::pipeline::Pipeline;
use pntr_pipeline::preset::{Preset, DEFAULT_PRESET};
use pntr_pipeline::prior::LocalizeOptions;
use pntr_retrieval::onnx_global::OnnxGlobal;

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
    pub topics: crate::replay_cmd::TopicArgs,
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
    #[arg(long, default_value_t = crate::selfcal_cmd::DEFAULT_FRAMES, value_name = "N")]
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

/// Arguments of `pntr eval`.
#[derive(clap::Args, Debug)]
pub struct EvalArgs {
    /// Dataset root (holding HPointLoc_dataset).
    #[arg(long)]
    pub dataset: PathBuf,
    /// Only this scene.
    #[arg(long)]
    pub scene: Option<String>,
    /// A map file from `pntr build-db`; without it (and without --remote) the map is built from the
    /// dataset first.
    #[arg(long, conflicts_with = "remote")]
    pub db: Option<PathBuf>,
    /// Send every query to a running pntr-server at this address instead of running the pipeline here.
    #[arg(long)]
    pub remote: Option<String>,
    /// Map id sent with --remote (empty: the server's only map).
    #[arg(long, default_value = "")]
    pub map_id: String,
    /// Bearer token for --remote (or PNTR_TOKEN).
    #[arg(long, env = "PNTR_TOKEN", hide_env_values = true)]
    pub token: Option<String>,
    /// CA certificate (PEM) for a TLS --remote.
    #[arg(long)]
    pub tls_ca: Option<PathBuf>,
    /// Preset: fast, fast-norerank, fast-icp, accurate, accurate-icp, classical, xfeat-mnn,
    /// xfeat-mnn-int8, xfeat-mnn-bf16, xfeat-mnn-qvga, xfeat-mnn-bf16-qvga (default: the map's own,
    /// or `xfeat-mnn` when building).
    #[arg(long)]
    pub preset: Option<String>,
    /// Reproduce the published evaluation's folded, convention-mismatched angle (labelled in the output).
    #[arg(long)]
    pub legacy_metric: bool,
    /// Evaluate at most this many queries, evenly spaced (0 = all).
    #[arg(long, default_value_t = 0)]
    pub queries: usize,
    /// Folder of the ONNX models.
    /// (default: `PNTR_MODELS`, `./models`, next to the executable, `../share/pntr/models`).
    #[arg(long)]
    pub models: Option<PathBuf>,
    /// Threads for ONNX Runtime.
    #[arg(long, default_value_t = 2)]
    pub threads: usize,
    /// Also write the JSON report here (the table goes to stdout either way).
    #[arg(long)]
    pub json: Option<PathBuf>,
    /// Also localize two perturbed copies of every query (JPEG at quality 90; colour and depth
    /// shifted by one pixel) and report how often the answer changes: status, pose, and answers that
    /// become LOCALIZED and wrong (in process only; three localizations a query).
    #[arg(long)]
    pub stability: bool,
    /// With --stability: also localize every query through this preset (one describing images as
    /// the map does, e.g. `xfeat-mnn-bf16` for an `xfeat-mnn` map) and count how its answers differ.
    #[arg(long, requires = "stability", value_name = "PRESET")]
    pub stability_preset: Option<String>,
    /// Also write every query to this MCAP file with Foxglove's schemas (open it in Foxglove): its
    /// image and camera, the answer (pose with covariance, status, reason), the ground truth and the
    /// map's cameras (in process), in ROS conventions (z-up `map`, optical `camera_optical`). A path
    /// not ending in `.mcap` is a ROS 2 bag folder instead (the topics of `replay --record-bag`; queries
    /// stamped 0.1 s apart).
    #[arg(long, value_name = "OUT.mcap|OUT_DIR")]
    pub record: Option<PathBuf>,
    /// A dataset of places the map does not cover: its queries are sent too and every LOCALIZED answer
    /// counts as a false positive (`negatives` in the report).
    #[arg(long)]
    pub negatives: Option<PathBuf>,
    /// Evaluate at most this many negative queries, evenly spaced (0 = all).
    #[arg(long, default_value_t = 0)]
    pub negative_queries: usize,
    /// Camera effects applied to every query before it is localized: `none`, `robot` (exposure,
    /// gamma, white balance, blur, noise, JPEG, depth noise and dropouts; seeded per query), or a
    /// comma-separated list of the groups `exposure`, `blur`, `noise`, `jpeg`, `depth`.
    #[arg(long, default_value = "none")]
    pub effects: String,
    /// Calibration file for the confidence, for this evaluation (default: the map's own, fitted by
    /// `build-db`; the one shipped in models/ for a map without one).
    #[arg(long)]
    pub calibration: Option<PathBuf>,
    /// LOCALIZED threshold on the calibrated confidence (default: the calibration's own).
    #[arg(long)]
    pub min_confidence: Option<f64>,
    /// Send each query a prior (a robot's rough position) of this radius, metres, centred half the
    /// radius away from the true position; retrieval then looks inside it first.
    #[arg(long, value_name = "METRES")]
    pub prior_radius: Option<f64>,
    /// Also draw pictures into this folder, PNG and SVG: error distributions (pipeline and retrieval
    /// only), precision/recall over the confidence threshold, and a top-down map per scene.
    #[arg(long, value_name = "DIR")]
    pub plot: Option<PathBuf>,
    /// Also write each in-map query's outcome to this file, one JSON object a line (`id`,
    /// `position_m`, `error` (of the LOCALIZED pose), `estimate_error` (of the best pose found),
    /// `retrieval_error` (of the top image's pose), each [metres, degrees] or null, `confidence`,
    /// `right_point_rank` (where the query's own Point first appears among the candidates, or null)
    /// and `reason` (why it is NOT_LOCALIZED, or null)): which queries failed, and at which stage.
    #[arg(long, value_name = "FILE.jsonl")]
    pub per_query: Option<PathBuf>,
}

/// Write the `--per-query` lines and draw the `--plot` pictures of `report`, and say where they went.
fn extra_outputs(args: &EvalArgs, report: &EvalReport, what: &str) -> Result<()> {
    if let Some(path) = &args.per_query {
        let mut text = String::new();
        for q in &report.per_query {
            text.push_str(&serde_json::to_string(q)?);
            text.push('\n');
        }
        write_text(path, &text).with_context(|| format!("--per-query {}", path.display()))?;
        eprintln!(
            "{} query outcomes written to {}",
            report.per_query.len(),
            path.display()
        );
    }
    let Some(dir) = &args.plot else {
        return Ok(());
    };
    let title = format!(
        "{what}: {} queries of {}",
        report.queries,
        args.dataset.display()
    );
    let files = crate::plot::eval_plots(report, dir, &title)?;
    eprintln!("{} pictures written to {}", files.len(), dir.display());
    Ok(())
}

/// The eval report as JSON with `"effects"`: what `--effects` put on the queries.
fn with_effects(report: &EvalReport, effects: &str) -> Result<serde_json::Value> {
    let mut json = serde_json::to_value(report)?;
    if let Some(o) = json.as_object_mut() {
        o.insert("effects".into(), effects.into());
    }
    Ok(json)
}

/// The query transformation `--effects` names: `none`, `robot` (every frame effect), or a
/// comma-separated list of frame effect groups (`exposure`, `blur`, `noise`, `jpeg`, `depth`).
pub fn effects(name: &str) -> Result<Option<pntr_synth::effects::RobotEffects>> {
    match name {
        "none" => Ok(None),
        "robot" => Ok(Some(pntr_synth::effects::RobotEffects::default())),
        list => {
            let groups: Vec<&str> = list.split(',').map(str::trim).collect();
            if groups.contains(&"lighting") {
                anyhow::bail!(
                    "--effects {list}: lighting needs the scene rendered again; use `pntr synth --realism lighting`"
                );
            }
            pntr_synth::effects::RobotEffects::only(&groups)
                .map(Some)
                .map_err(|_| {
                    anyhow::anyhow!(
                        "--effects {list}: not none, robot, or a comma-separated list of exposure, blur, noise, jpeg, depth"
                    )
                })
        }
    }
}

/// The calibration `--calibration` names (the embedded default without it).
pub fn calibration(path: Option<&Path>) -> Result<Arc<Calibration>> {
    Ok(Arc::new(match path {
        Some(p) => Calibration::load(p)?,
        None => Calibration::embedded(),
    }))
}

/// `pipeline` with the calibration `--calibration` names, or the one it has (the map's own, else
/// the shipped one), and `--min-confidence` when given.
pub fn calibrated(
    pipeline: Pipeline,
    path: Option<&Path>,
    min_confidence: Option<f64>,
) -> Result<Pipeline> {
    Ok(match path {
        Some(_) => pipeline.with_calibration(calibration(path)?, min_confidence),
        None => pipeline.with_min_confidence(min_confidence),
    })
}

/// The scenes of a `--negatives` dataset.
pub fn negative_scenes(path: Option<&Path>) -> Result<Vec<SceneEntry>> {
    match path {
        None => Ok(Vec::new()),
        Some(p) => Ok(DatasetIndex::open(p)
            .with_context(|| format!("--negatives {}", p.display()))?
            .scenes),
    }
}

pub(crate) fn bar(total: usize, what: &str) -> ProgressBar {
    let bar = ProgressBar::new(total as u64);
    bar.set_style(
        ProgressStyle::with_template("{msg} [{bar:40}] {pos}/{len} ({per_sec}, eta {eta})")
            .expect("valid template")
            .progress_chars("=> "),
    );
    bar.set_message(what.to_string());
    bar
}

/// The scenes a command covers and the map id that goes with them.
pub fn select_scenes<'a>(
    index: &'a DatasetIndex,
    scene: Option<&str>,
) -> Result<(String, Vec<&'a SceneEntry>)> {
    Ok(match scene {
        Some(name) => (name.to_string(), vec![index.scene(name)?]),
        None => ("all".to_string(), index.scenes.iter().collect()),
    })
}

fn runtime(threads: usize) -> RuntimeOptions {
    RuntimeOptions {
        threads,
        ..RuntimeOptions::default()
    }
}

/// The models folder: `--models`, else found as [`pntr_features::models_dir::locate`] says. A wrong
/// `--models` or `PNTR_MODELS` is an error; when nothing is found anywhere the places looked at are
/// printed as a warning and `models` is used (presets without ONNX models, `classical`, need none;
/// the others then fail naming the file).
pub fn models_dir(arg: Option<&Path>) -> Result<PathBuf> {
    match pntr_features::models_dir::locate(arg) {
        Ok(dir) => Ok(dir),
        Err(e) if arg.is_none() && std::env::var_os(pntr_features::models_dir::ENV).is_none() => {
            tracing::warn!("{e}");
            Ok(PathBuf::from("models"))
        }
        Err(e) => Err(anyhow::anyhow!(e)),
    }
}

/// Build a map of `scenes` in memory.
pub fn build_map(
    map_id: &str,
    scenes: &[&SceneEntry],
    preset: &Preset,
    models: &Path,
    threads: usize,
) -> Result<Map> {
    let stage = map_feature_stage(preset, models, threads)?;
    let total: usize = scenes.iter().map(|s| s.points.len()).sum();
    let pb = bar(total * 6, "extracting database features");
    let map = pntr_mapping::build::build(
        map_id,
        scenes,
        preset,
        &stage,
        models,
        &mut |done, total| {
            pb.set_length(total as u64);
            pb.set_position(done as u64);
        },
    )?;
    pb.finish_and_clear();
    Ok(map)
}

pub(crate) fn feature_stage(
    preset: &Preset,
    models: &Path,
    threads: usize,
) -> Result<pntr_features::config::FeatureStage> {
    build_stage(
        preset.feature_config(models.to_path_buf()),
        preset,
        models,
        threads,
    )
}

/// The feature stage that describes a preset's map images ([`Preset::map_extractor`]).
pub(crate) fn map_feature_stage(
    preset: &Preset,
    models: &Path,
    threads: usize,
) -> Result<pntr_features::config::FeatureStage> {
    build_stage(
        preset.map_feature_config(models.to_path_buf()),
        preset,
        models,
        threads,
    )
}

fn build_stage(
    config: pntr_features::config::FeatureConfig,
    preset: &Preset,
    models: &Path,
    threads: usize,
) -> Result<pntr_features::config::FeatureStage> {
    let cfg = pntr_features::config::FeatureConfig {
        runtime: runtime(threads),
        ..config
    };
    cfg.build().with_context(|| {
        format!(
            "loading the models of preset {} from {}",
            preset.name,
            models.display()
        )
    })
}

/// Load a map file, loading the ONNX global model it names when it has one.
pub fn load_map(path: &Path, threads: usize) -> Result<Map> {
    let header = mapfile::read_header(path)?;
    let model = header.preset.global_model.clone();
    Ok(mapfile::load(path, |dim| {
        let p = model.ok_or_else(|| {
            pntr_retrieval::RetrievalError::Model(
                "the map uses an onnx global model but names none".into(),
            )
        })?;
        OnnxGlobal::load(&p, &runtime(threads), None, Some(dim))
    })?)
}

/// The preset `build-db` builds with (`--global-model` switching retrieval to it).
pub(crate) fn build_preset(args: &BuildArgs) -> Result<Preset> {
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
        return crate::build_cmd::build_from_recordings(args);
    };
    let index = DatasetIndex::open(dataset)?;
    let (scene_id, scenes) = select_scenes(&index, args.scene.as_deref())?;
    let map_id = args.map_id.clone().unwrap_or(scene_id);
    let preset = build_preset(args)?;
    let models = models_dir(args.models.as_deref())?;
    let map = build_map(&map_id, &scenes, &preset, &models, args.threads)?;
    let out = args.out.as_deref().context("--out is required")?;
    let t_cal = std::time::Instant::now();
    let map = if args.no_self_calibration {
        map
    } else {
        let opts = crate::selfcal_cmd::Options::of_build(args, &models);
        crate::selfcal_cmd::with_dataset(map, &scenes, &opts)
            .context("fitting the map's own calibration (--no-self-calibration skips it)")?
    };
    let self_calibration_s = t_cal.elapsed().as_secs_f64();
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
        "calibration": crate::selfcal_cmd::summary(map.header.calibration.as_ref(), false),
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
            crate::selfcal_cmd::line(map.header.calibration.as_ref(), false)
        );
    }
    Ok(())
}

/// Start a recording (`--record`) at `out` (a Foxglove MCAP file, or a ROS 2 bag folder when `out`
/// does not end in `.mcap`); with `db`, the map's cameras go in first, stamped
/// `time_s`.
pub fn start_recording(
    out: &Path,
    db: Option<&Path>,
    time_s: f64,
) -> Result<pntr_service::ros_bag::Recorder> {
    let rec = pntr_service::ros_bag::Recorder::create(out)
        .map_err(|e| anyhow::anyhow!("--record {e}"))?;
    if let Some(path) = db {
        let map = load_map(path, 1).with_context(|| format!("--db {}", path.display()))?;
        show_map_cameras(&rec, &map, time_s);
    }
    Ok(rec)
}

/// Write a map's image poses into a recording, in ROS conventions.
fn show_map_cameras(rec: &pntr_service::ros_bag::Recorder, map: &Map, time_s: f64) {
    let frames = pntr_service::wire::MapFrames::of(&map.header);
    rec.map_cameras(
        time_s,
        map.images
            .iter()
            .map(|im| frames.pose_to_ros(&im.world_from_camera)),
    );
}

/// Show one evaluated query in a recording: its image and camera, the answer and the ground truth,
/// in ROS conventions (the dataset's frame is y-up with Habitat camera axes). Queries are stamped
/// 0.1 s apart from the Unix epoch (datasets carry no time).
fn record_query(
    rec: &pntr_service::ros_bag::Recorder,
    n: &mut usize,
    q: &pntr_pipeline::pipeline::Query,
    truth: Option<&nalgebra::Isometry3<f64>>,
    a: &Answer,
) -> Result<()> {
    // Evaluation answers are in the dataset's frames: y up, Habitat axes.
    let frames = pntr_service::wire::MapFrames::default();
    let to_ros = |p: &nalgebra::Isometry3<f64>| frames.pose_to_ros(p);
    let covariance = a
        .covariance
        .map(|c| frames.covariance_to_ros(&c))
        .unwrap_or_default();
    let id = format!("query-{n}");
    let status = match a.status {
        Some(pntr_pipeline::pipeline::Status::Localized) => "LOCALIZED",
        Some(_) => "NOT_LOCALIZED",
        None => "ERROR",
    };
    rec.observe(&pntr_service::visual::Observation {
        time_s: *n as f64 * 0.1,
        picture: Some((pntr_service::visual::Picture::Raw(&q.rgb), &q.intrinsics)),
        request_id: &id,
        map_id: "",
        map_version: "",
        status,
        reason: a.reason.as_deref().unwrap_or(""),
        confidence: a.confidence,
        inliers: 0,
        mode: a.mode.map_or("UNKNOWN", |m| m.name()),
        matched_image_id: a.matched.as_deref().unwrap_or(""),
        pose: a.pose.as_ref().map(to_ros),
        covariance: &covariance,
        truth: truth.map(to_ros),
    })
    .map_err(|e| anyhow::anyhow!("--record: {e}"))?;
    *n += 1;
    Ok(())
}

/// Close a recording under its name and say where it is.
fn finish_recording(record: Option<pntr_service::ros_bag::Recorder>) -> Result<()> {
    if let Some(rec) = record {
        let path = rec.finish().map_err(|e| anyhow::anyhow!("--record {e}"))?;
        eprintln!("recording written to {}", path.display());
    }
    Ok(())
}

/// Run the in-process pipeline over the queries of `scenes`.
pub fn evaluate_in_process(
    pipeline: &Pipeline,
    scenes: &[&SceneEntry],
    opts: &EvalOptions,
    effects: Option<pntr_synth::effects::RobotEffects>,
    record: Option<&pntr_service::ros_bag::Recorder>,
    stability: bool,
    variant: Option<&Pipeline>,
) -> Result<(EvalReport, Stability)> {
    use pntr_synth::effects::Perturbation;
    let map = pipeline.map.clone();
    // With --stability, the answers to each query's perturbed copies (made in the localizer, which
    // sees the frame as localized), counted in the observer (which knows the truth).
    let pending: std::cell::RefCell<Vec<(String, Answer)>> = Default::default();
    let mut counts = Stability::new();
    let total: usize = scenes.iter().map(|s| s.points.len()).sum();
    let pb = bar(total, "localizing queries");
    let mut seed = 0u64;
    if let Some(rec) = record {
        show_map_cameras(rec, &map, 0.0);
    }
    let mut n = 0usize;
    // The first error writing --record: recording stops there and the run fails after it.
    let mut failed: Option<anyhow::Error> = None;
    let report = eval::run_observed(
        scenes,
        opts,
        &mut |q, prior| {
            seed += 1;
            let opts = prior
                .copied()
                .map(LocalizeOptions::prior)
                .unwrap_or_default();
            let mut q = q.clone();
            if let Some(fx) = &effects {
                fx.apply(&mut q.rgb, &mut q.depth, seed);
            }
            if stability {
                for kind in Perturbation::ALL {
                    let mut p = q.clone();
                    kind.apply(&mut p.rgb, &mut p.depth);
                    let a = pipeline
                        .localize_with(&p, &opts)
                        .map(|l| Answer::of(&l, &map));
                    pending
                        .borrow_mut()
                        .push((kind.name().to_string(), a.unwrap_or_default()));
                }
                // The same frame through another preset of the same descriptors (bf16 against
                // float, say).
                if let Some(v) = variant {
                    let a = v.localize_with(&q, &opts).map(|l| Answer::of(&l, &map));
                    pending
                        .borrow_mut()
                        .push((format!("preset:{}", v.preset.name), a.unwrap_or_default()));
                }
            }
            Ok(Answer::of(&pipeline.localize_with(&q, &opts)?, &map))
        },
        &mut |done, total| {
            pb.set_length(total as u64);
            pb.set_position(done as u64);
        },
        &mut |q, truth, a| {
            if let (Some(rec), None) = (record, &failed) {
                failed = record_query(rec, &mut n, q, truth, a).err();
            }
            for (kind, perturbed) in pending.borrow_mut().drain(..) {
                let side = if truth.is_some() {
                    "in_map"
                } else {
                    "out_of_map"
                };
                counts
                    .entry(format!("{kind}/{side}"))
                    .or_default()
                    .add(a, &perturbed, truth);
            }
        },
    )?;
    pb.finish_and_clear();
    if let Some(e) = failed {
        return Err(e);
    }
    Ok((report, counts))
}

/// `--stability` counts by `perturbation/in_map` or `perturbation/out_of_map`.
pub type Stability = std::collections::BTreeMap<String, eval::StabilityCounts>;

/// The stability lines of the eval table.
fn stability_table(s: &Stability) -> String {
    let mut out = String::from(
        "stability (answers to perturbed copies of each query: changed status, pose moved > 0.25 m / 2 deg, became LOCALIZED and wrong, confident (> 0.9) and > 5 m / 20 deg off):\n",
    );
    for (k, c) in s {
        out += &format!(
            "  {k:<22} {:>5} queries: status changed {}, pose moved {}, became wrong {}, confident wrong {} (became so {})\n",
            c.queries, c.status_changed, c.pose_moved, c.became_wrong, c.confident_wrong, c.became_confident_wrong
        );
    }
    out
}

/// Write `value` as pretty JSON to `path` atomically.
pub fn write_json(path: &Path, value: &impl serde::Serialize) -> Result<()> {
    write_text(path, &serde_json::to_string_pretty(value)?)
}

/// Write `text` to `path` atomically.
pub fn write_text(path: &Path, text: &str) -> Result<()> {
    let tmp = PathBuf::from(format!("{}.partial-{}", path.display(), std::process::id()));
    let written = std::fs::write(&tmp, text)
        .with_context(|| format!("writing {}", tmp.display()))
        .and_then(|()| {
            std::fs::rename(&tmp, path).with_context(|| format!("writing {}", path.display()))
        });
    if written.is_err() {
        // A full disk: no half-written file left beside the one asked for.
        let _ = std::fs::remove_file(&tmp);
    }
    written
}

/// Localise queries of `scenes` through `remote`.
pub fn evaluate_remote(
    remote: &mut crate::remote::Remote,
    scenes: &[&SceneEntry],
    opts: &EvalOptions,
    record: Option<&pntr_service::ros_bag::Recorder>,
) -> Result<EvalReport> {
    let total: usize = scenes.iter().map(|s| s.points.len()).sum();
    let pb = bar(total, "localizing queries through the server");
    let mut n = 0usize;
    // The first error writing --record: recording stops there and the run fails after it.
    let mut failed: Option<anyhow::Error> = None;
    let report = eval::run_observed(
        scenes,
        opts,
        &mut |q, prior| remote.answer(q, prior),
        &mut |done, total| {
            pb.set_length(total as u64);
            pb.set_position(done as u64);
        },
        &mut |q, truth, a| {
            if let (Some(rec), None) = (record, &failed) {
                failed = record_query(rec, &mut n, q, truth, a).err();
            }
        },
    )?;
    pb.finish_and_clear();
    if let Some(e) = failed {
        return Err(e);
    }
    Ok(report)
}

/// Start a pntr-server on 127.0.0.1 (ephemeral port) serving `map`, localise up to `queries` queries of
/// `scenes` through it, print the recall table and stage timings, and shut it down gracefully.
pub fn serve_and_evaluate(
    map: &Path,
    models: &Path,
    scenes: &[&SceneEntry],
    queries: usize,
) -> Result<()> {
    use pntr_service::tokio;
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()?;
    let settings =
        pntr_service::config::Settings::local(vec![map.to_path_buf()], models.to_path_buf());
    let mut running = rt.block_on(async {
        let r = pntr_service::start(settings).await?;
        r.ready().await?;
        Ok::<_, pntr_service::ServerError>(r)
    })?;
    println!(
        "pntr-server serving {} on {} (Prometheus metrics on http://{}/metrics)",
        map.display(),
        running.addr,
        running.metrics_addr
    );
    let mut remote = crate::remote::Remote::connect(&crate::remote::ConnectArgs {
        addr: running.addr.to_string(),
        ..Default::default()
    })?;
    let header = mapfile::read_header(map)?;
    let opts = EvalOptions {
        max_queries: queries,
        preset: header.preset.name.clone(),
        ..EvalOptions::default()
    };
    let report = evaluate_remote(&mut remote, scenes, &opts, None);
    drop(remote);
    running.shutdown();
    rt.block_on(running.wait())?;
    let report = report?;
    println!(
        "preset {}: {} + {} + {} + {:?}, {} retrieval candidates re-ranked by geometry",
        header.preset.name,
        header.preset.global,
        header.preset.extractor,
        header.preset.matcher,
        header.preset.solver,
        header.preset.candidates
    );
    print!("{}", eval::table(&report));
    println!("(stage times as the server reports them; queries/s measured at the client, one request at a time)");
    Ok(())
}

/// `pntr eval`.
pub fn eval(args: &EvalArgs) -> Result<()> {
    let index = DatasetIndex::open(&args.dataset)?;
    let (map_id, scenes) = select_scenes(&index, args.scene.as_deref())?;
    if let Some(r) = args.prior_radius {
        if !(r.is_finite() && r > 0.0 && r <= pntr_pipeline::prior::MAX_RADIUS_M) {
            anyhow::bail!(
                "--prior-radius {r}: must be in (0, {}] metres",
                pntr_pipeline::prior::MAX_RADIUS_M
            );
        }
    }
    if args.remote.is_some()
        && (args.effects != "none"
            || args.calibration.is_some()
            || args.min_confidence.is_some()
            || args.stability)
    {
        anyhow::bail!("--effects, --calibration, --min-confidence and --stability work in process only (the server applies its own calibration and threshold)");
    }
    if let Some(addr) = &args.remote {
        let mut remote = crate::remote::Remote::connect(&crate::remote::ConnectArgs {
            addr: addr.clone(),
            map_id: args.map_id.clone(),
            token: args.token.clone(),
            tls_ca: args.tls_ca.clone(),
            tls_domain: None,
        })?;
        let opts = EvalOptions {
            legacy: args.legacy_metric,
            max_queries: args.queries,
            preset: "remote".into(),
            negatives: negative_scenes(args.negatives.as_deref())?,
            max_negatives: args.negative_queries,
            min_confidence: None,
            prior_radius_m: args.prior_radius,
            map_images: Vec::new(),
        };
        let record = match &args.record {
            Some(p) => Some(start_recording(p, None, 0.0)?),
            None => None,
        };
        let report = evaluate_remote(&mut remote, &scenes, &opts, record.as_ref())?;
        finish_recording(record)?;
        print!("{}", eval::table(&report));
        if let Some(path) = &args.json {
            write_json(path, &with_effects(&report, &args.effects)?)?;
            eprintln!("report written to {}", path.display());
        }
        return extra_outputs(args, &report, &format!("pntr-server at {addr}"));
    }
    let models = models_dir(args.models.as_deref())?;
    let map = match &args.db {
        Some(p) => {
            let t = std::time::Instant::now();
            let map =
                load_map(p, args.threads).with_context(|| format!("loading {}", p.display()))?;
            eprintln!(
                "map {} loaded in {:.2} s: {} images, {:.1} MB in memory",
                p.display(),
                t.elapsed().as_secs_f64(),
                map.images.len(),
                map.heap_bytes() as f64 / 1e6
            );
            map
        }
        None => {
            let preset = Preset::named(args.preset.as_deref().unwrap_or(DEFAULT_PRESET))?;
            build_map(&map_id, &scenes, &preset, &models, args.threads)?
        }
    };
    let preset = match &args.preset {
        Some(name) => Preset::named(name)?,
        None => map.header.preset.clone(),
    };
    let stage = feature_stage(&preset, &models, args.threads)?;
    let fx = effects(&args.effects)?;
    if let Some(c) = args.min_confidence {
        if !(0.0..=1.0).contains(&c) {
            anyhow::bail!("--min-confidence must be between 0 and 1, not {c}");
        }
    }
    let axes = map.header.axes();
    let map_images = map
        .images
        .iter()
        .map(|im| {
            let pose = pntr_core::convert_axes(
                &im.world_from_camera,
                axes,
                pntr_core::CameraAxes::Habitat,
            );
            (im.id.clone(), pose)
        })
        .collect();
    let pipeline = calibrated(
        Pipeline::new(Arc::new(map), stage, preset.clone())?,
        args.calibration.as_deref(),
        args.min_confidence,
    )?;
    let source = match pipeline.calibration().1 {
        pntr_pipeline::calibration::CalibrationSource::Map => "the map's own".to_string(),
        pntr_pipeline::calibration::CalibrationSource::Shipped => "the shipped one".to_string(),
        pntr_pipeline::calibration::CalibrationSource::File => args
            .calibration
            .as_deref()
            .map_or_else(|| "a file".into(), |p| p.display().to_string()),
    };
    eprintln!(
        "calibration: {source}, LOCALIZED threshold {:.3}",
        pipeline.min_confidence()
    );
    let opts = EvalOptions {
        legacy: args.legacy_metric,
        max_queries: args.queries,
        preset: preset.name.clone(),
        negatives: negative_scenes(args.negatives.as_deref())?,
        max_negatives: args.negative_queries,
        min_confidence: Some(pipeline.min_confidence()),
        prior_radius_m: args.prior_radius,
        map_images,
    };
    let record = match &args.record {
        Some(p) => Some(start_recording(p, None, 0.0)?),
        None => None,
    };
    let variant = match &args.stability_preset {
        Some(name) => {
            let p = Preset::named(name)?;
            let st = feature_stage(&p, &models, args.threads)?;
            Some(calibrated(
                Pipeline::new(pipeline.map.clone(), st, p)?,
                args.calibration.as_deref(),
                args.min_confidence,
            )?)
        }
        None => None,
    };
    let (report, stability) = evaluate_in_process(
        &pipeline,
        &scenes,
        &opts,
        fx,
        record.as_ref(),
        args.stability,
        variant.as_ref(),
    )?;
    finish_recording(record)?;
    print!("{}", eval::table(&report));
    if args.stability {
        print!("{}", stability_table(&stability));
    }
    if let Some(path) = &args.json {
        let mut json = with_effects(&report, &args.effects)?;
        if args.stability {
            json["stability"] = serde_json::to_value(&stability)?;
        }
        write_json(path, &json)?;
        eprintln!("report written to {}", path.display());
    }
    extra_outputs(args, &report, &format!("preset {}", preset.name))
}

/// Every image of the map at `path`: id, place, stamp (seconds or null) and `world_from_camera`
/// (translation, rotation w x y z with w >= 0) in the map's frame and camera axes.
/// Also the map's version (build time and content checksum), which needs the whole file.
fn image_list(path: &Path) -> Result<(Vec<serde_json::Value>, String)> {
    let map = load_map(path, 1).with_context(|| format!("loading {}", path.display()))?;
    let version = pntr_service::engine::MapVersion::of(&map).label;
    let list = map
        .images
        .iter()
        .map(|im| {
            let t = im.world_from_camera.translation.vector;
            let q = im.world_from_camera.rotation.quaternion();
            let s = if q.w < 0.0 { -1.0 } else { 1.0 };
            serde_json::json!({
                "id": im.id,
                "place": im.point,
                "stamp": im.stamp,
                "translation": [t.x, t.y, t.z],
                "rotation_wxyz": [s * q.w, s * q.i, s * q.j, s * q.k],
            })
        })
        .collect();
    Ok((list, version))
}

/// `pntr info --db FILE [--images]`: what a map file says about itself, from its header and its
/// images' ids (fast on maps of any size; the ids say whether the map's own calibration is stale),
/// and with `images` every image's id, place, stamp and pose. Errors name the file and what is
/// wrong with it.
pub fn info(path: &Path, as_json: bool, images: bool) -> Result<()> {
    let header = mapfile::read_header(path)?;
    let list = if images {
        Some(image_list(path)?)
    } else {
        None
    };
    // Whether the map changed since its own calibration was fitted shows in its image ids (read
    // from the records' starts: fast on maps of any size).
    let stale = match &header.calibration {
        Some(c) => c.is_stale_for(mapfile::read_image_ids(path)?.iter().map(String::as_str)),
        None => false,
    };
    if as_json {
        let mut v = serde_json::to_value(&header)?;
        // `calibration.source`, `.stale` and `.threshold`, as `pntr info --addr --json` says them.
        let (calibration, source, threshold) = match &header.calibration {
            Some(own) => (v["calibration"].clone(), "map", own.calibration.threshold),
            None => (
                crate::selfcal_cmd::summary(None, false),
                "shipped",
                Calibration::embedded().threshold,
            ),
        };
        if let (Some(o), serde_json::Value::Object(mut c)) = (v.as_object_mut(), calibration) {
            c.insert("source".into(), source.into());
            c.insert("stale".into(), stale.into());
            c.insert("threshold".into(), threshold.into());
            o.insert("calibration".into(), c.into());
        }
        if let (Some(o), Some((list, version))) = (v.as_object_mut(), list) {
            o.insert("image_list".into(), list.into());
            o.insert("version".into(), version.into());
        }
        println!("{}", serde_json::to_string_pretty(&v)?);
        return Ok(());
    }
    let p = &header.preset;
    println!(
        "map {} ({}), built by {} in {:.1} s",
        header.map_id,
        path.display(),
        header.built_by,
        header.build_seconds
    );
    let keypoints = if p.extractor_top_k() > p.keypoints {
        format!(
            "{} keypoints (up to {} on larger images)",
            p.keypoints,
            p.extractor_top_k()
        )
    } else {
        format!("{} keypoints", p.keypoints)
    };
    println!(
        "preset {}: {} ({} words) + {}, index {}, {keypoints}, {} candidates, matcher {}, solver {:?}",
        p.name, p.global, p.vlad_words, p.extractor, p.index, p.candidates, p.matcher, p.solver
    );
    if p.map_extractor() != p.extractor {
        println!(
            "map images described by {}, queries by {}",
            p.map_extractor(),
            p.extractor
        );
    }
    for m in &header.models {
        println!(
            "model {}: {} ({}, checksum {})",
            m.role,
            m.name,
            m.file.as_deref().unwrap_or("no file"),
            m.checksum.as_deref().unwrap_or("-")
        );
    }
    let k = &header.intrinsics;
    println!(
        "camera (first image): fx {:.2} fy {:.2} cx {:.2} cy {:.2}, axes {}",
        k.fx, k.fy, k.cx, k.cy, header.camera_axes
    );
    println!(
        "scenes ({}): {}; world up axis {}",
        header.scenes.len(),
        header.scenes.join(", "),
        header.up_axis
    );
    if let Some(at) = header.built_at_unix_s.filter(|s| s.is_finite()) {
        let when = time::OffsetDateTime::from_unix_timestamp(at.floor() as i64)
            .ok()
            .and_then(|t| {
                t.format(&time::format_description::well_known::Rfc3339)
                    .ok()
            })
            .unwrap_or_else(|| format!("{at:.0} s since the Unix epoch"));
        println!("built (or last extended) at {when}");
    }
    for r in &header.sessions {
        println!(
            "session {}: {} frames, stamps {:.3} .. {:.3} s",
            r.name, r.frames, r.first_stamp, r.last_stamp
        );
    }
    println!(
        "{}",
        crate::selfcal_cmd::line(header.calibration.as_ref(), stale)
    );
    if let Some((_, version)) = &list {
        println!("version {version}");
    }
    for im in list.iter().flat_map(|(l, _)| l) {
        println!(
            "{} place {} stamp {} t {} q(wxyz) {}",
            im["id"].as_str().unwrap_or(""),
            im["place"],
            im["stamp"],
            im["translation"],
            im["rotation_wxyz"]
        );
    }
    Ok(())
}
