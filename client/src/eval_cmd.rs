//! `pntr eval`: the pipeline over a dataset's queries with the HPointLoc protocol and honest
//! metrics, in this process, through a server it starts, or through a running one.

use std::path::PathBuf;
use std::sync::Arc;

use anyhow::{Context, Result};
use pntr_dataset::DatasetIndex;
use pntr_eval::{self as eval, EvalOptions, EvalReport};
use pntr_pipeline::pipeline::Pipeline;
use pntr_pipeline::preset::{Preset, DEFAULT_PRESET};

use crate::evaluation::{
    evaluate_in_process, evaluate_remote, finish_recording, stability_table, start_recording,
};
use crate::loading::{
    build_map, calibrated, effects, feature_stage, load_map, models_dir, negative_scenes,
    select_scenes,
};
use crate::output::{write_json, write_text};

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
    /// `position_m`, `world_from_camera` (the ground truth) and `estimate_world_from_camera` (the
    /// best pose found, or null), each [tx, ty, tz, qx, qy, qz, qw] in the dataset's Habitat axes,
    /// `error` (of the LOCALIZED pose), `estimate_error` (of the best pose found),
    /// `estimate_offset_camera_m` (where that pose lies in the true camera's axes),
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
