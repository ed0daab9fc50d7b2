//! `pntr calibrate`: fit the confidence calibration on a user's own data.
//!
//! Every in-map query of `--dataset` is localised twice, as rendered and with robot camera effects,
//! and every out-of-map query of `--negatives` once; each candidate pose that verification scores
//! becomes one labelled sample (right = within (1 m, 10 deg) of the ground truth; anything from the
//! negatives is wrong). A logistic model is fitted on them ([`pntr_mapping::fit::fit`]) and
//! written atomically with its checksum; the threshold is the lowest that keeps the fitting set's
//! precision at `--target-precision`.

use std::path::PathBuf;
use std::sync::Arc;

use anyhow::{Context, Result};
use pntr_dataset::queries::query_list;
use pntr_dataset::{DatasetIndex, SceneEntry};
use pntr_mapping::fit::{self, QuerySamples};
use pntr_pipeline::calibration::Calibration;
use pntr_pipeline::pipeline::Pipeline;
use pntr_pipeline::preset::{Preset, DEFAULT_PRESET};
use pntr_pipeline::verify::EVIDENCE_NAMES;
use pntr_synth::effects::RobotEffects;

use crate::loading;
use crate::recordings::{as_sessions, open_recording};
use pntr_mapping::own_calibration::{self, FitOptions};

/// Arguments of `pntr calibrate`.
#[derive(clap::Args, Debug)]
pub struct CalibrateArgs {
    /// Dataset whose scenes the map covers (in-map queries with ground truth).
    #[arg(long, required_unless_present = "sequence")]
    pub dataset: Option<PathBuf>,
    /// Without `--negatives`, instead of --dataset: recordings whose poses are in `--db`'s frame
    /// (the map's own recordings), whose frames refit the map's own calibration. Repeatable.
    #[arg(long, value_name = "DIR|FILE.mcap", conflicts_with_all = ["dataset", "negatives"], requires = "db")]
    pub sequence: Vec<PathBuf>,
    /// Poses of each `--sequence` from this TUM trajectory instead of the recording's own (one per
    /// `--sequence`, in order).
    #[arg(long, value_name = "FILE.txt", requires = "sequence")]
    pub trajectory: Vec<PathBuf>,
    /// The camera of the `--sequence` recordings as `fx,fy,cx,cy[,k1,k2,p1,p2[,k3]]`.
    #[arg(long, value_name = "FX,FY,CX,CY", requires = "sequence")]
    pub intrinsics: Option<String>,
    /// Depth units per metre of the `--sequence` recordings, replacing what their format says.
    #[arg(long, value_name = "UNITS_PER_M", requires = "sequence")]
    pub depth_scale: Option<f64>,
    /// ROS 2 bag topics of a `--sequence`.
    #[command(flatten)]
    pub topics: crate::recordings::TopicArgs,
    /// Only this scene of --dataset.
    #[arg(long)]
    pub scene: Option<String>,
    /// More in-map datasets of the same places captured otherwise (`pntr synth` with the same seed and
    /// `--query-camera` for other cameras, or `--realism` for other lighting and a robot's camera
    /// effects): their queries join the fit, so confidence is calibrated for the captures robots
    /// bring, not only the map's. Repeatable.
    #[arg(long)]
    pub camera_dataset: Vec<PathBuf>,
    /// Dataset of places the map does not cover (out-of-map queries). Repeatable (for example the same
    /// places as rendered and with `--realism robot`). Without it, `--db` is given its own
    /// calibration instead (see `--db`).
    #[arg(long)]
    pub negatives: Vec<PathBuf>,
    /// Write the calibration here (JSON; written to a temporary name, then renamed). Without
    /// `--negatives`: the map with its own calibration [default: `--db`, rewritten atomically].
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// A map of --dataset from `pntr build-db`; without it the map is built first. Without
    /// `--negatives`, refit this map's own calibration: --dataset's queries are localized against
    /// the whole map and with their own region held out (what `build-db` does) and the map is
    /// rewritten with it (`--out` for a copy).
    #[arg(long)]
    pub db: Option<PathBuf>,
    /// Without `--negatives`: frames used, evenly spaced (0 = all); each is localized twice.
    #[arg(long, default_value_t = pntr_mapping::recording_map::SELF_CALIBRATION_FRAMES, value_name = "N")]
    pub self_calibration_frames: usize,
    /// Preset: fast, fast-norerank, fast-icp, accurate, accurate-icp, classical, xfeat-mnn,
    /// xfeat-mnn-int8, xfeat-mnn-bf16, xfeat-mnn-qvga, xfeat-mnn-bf16-qvga (default: the map's own,
    /// or `xfeat-mnn` when building).
    #[arg(long)]
    pub preset: Option<String>,
    /// In-map queries used, evenly spaced (0 = all).
    #[arg(long, default_value_t = 0)]
    pub queries: usize,
    /// Out-of-map queries used, evenly spaced (0 = all).
    #[arg(long, default_value_t = 0)]
    pub negative_queries: usize,
    /// Do not add the robot-effects copy of each in-map query.
    #[arg(long)]
    pub no_effects: bool,
    /// Precision (within 1 m, 10 deg) the recommended threshold must reach on the fitting set.
    #[arg(long, default_value_t = 0.995)]
    pub target_precision: f64,
    /// L2 penalty on the standardised weights.
    #[arg(long, default_value_t = 1.0)]
    pub l2: f64,
    /// Also write every labelled sample here, one JSON object a line (`{"query", "effects", "image",
    /// "chosen", "error_m", "error_deg", "confidence" (the candidate's own probability),
    /// "answer_confidence" (the query's answer), "rivals", "right", "negative", "evidence": {...}}`),
    /// to study the checks. Without --negatives: one line per frame (`{"held_out", "region",
    /// "candidates": [{"right", "evidence"}], "rivals"}`).
    #[arg(long)]
    pub samples: Option<PathBuf>,
    /// Calibration used while collecting (it picks among candidates and fills `confidence` in
    /// --samples; the fit itself does not depend on it) [default: the embedded one].
    #[arg(long)]
    pub calibration: Option<PathBuf>,
    /// Folder of the ONNX models.
    /// (default: `PNTR_MODELS`, `./models`, next to the executable, `../share/pntr/models`).
    #[arg(long)]
    pub models: Option<PathBuf>,
    /// Threads for ONNX Runtime.
    #[arg(long, default_value_t = 2)]
    pub threads: usize,
}

/// [`fit::labelled_samples`] with a progress bar saying `what`.
#[allow(clippy::too_many_arguments)]
fn collect(
    pipeline: &Pipeline,
    list: &[(pntr_dataset::PointEntry, usize)],
    effects: Option<&RobotEffects>,
    negative: bool,
    what: &str,
    out: &mut Vec<QuerySamples>,
    notes: &mut Vec<fit::CandidateNote>,
) -> Result<()> {
    let mut bars = crate::output::bars();
    Ok(fit::labelled_samples(
        pipeline,
        list,
        effects,
        negative,
        out,
        notes,
        &mut |done, total| {
            bars(pntr_mapping::progress::Step {
                stage: what,
                done,
                total,
            })
        },
    )?)
}

pub use pntr_mapping::fit::today;

/// `pntr calibrate`.
pub fn run(args: &CalibrateArgs) -> Result<()> {
    if !(args.target_precision > 0.0 && args.target_precision <= 1.0) {
        anyhow::bail!(
            "--target-precision must be in (0, 1], not {}",
            args.target_precision
        );
    }
    if !(args.l2.is_finite() && args.l2 >= 0.0) {
        anyhow::bail!("--l2 must be a finite number >= 0, not {}", args.l2);
    }
    if args.negatives.is_empty() {
        return own(args);
    }
    let Some(out) = &args.out else {
        anyhow::bail!("--out is required with --negatives (the calibration file to write)");
    };
    let Some(dataset) = &args.dataset else {
        anyhow::bail!("--dataset is required with --negatives (the places the map covers)");
    };
    for (flag, p) in [("--out", Some(out)), ("--samples", args.samples.as_ref())] {
        if let Some(dir) = p
            .and_then(|p| p.parent())
            .filter(|d| !d.as_os_str().is_empty())
        {
            if !dir.is_dir() {
                anyhow::bail!(
                    "{flag} {}: the folder {} does not exist",
                    p.expect("some").display(),
                    dir.display()
                );
            }
        }
    }
    let index = DatasetIndex::open(dataset)?;
    let (map_id, scenes) = loading::select_scenes(&index, args.scene.as_deref())?;
    let same = |a: &std::path::Path, b: &std::path::Path| matches!((a.canonicalize(), b.canonicalize()), (Ok(x), Ok(y)) if x == y);
    let mut neg_indexes = Vec::new();
    for (i, dir) in args.negatives.iter().enumerate() {
        if same(dataset, dir) {
            anyhow::bail!(
                "--negatives {} is --dataset itself: negatives must be places the map does not cover",
                dir.display()
            );
        }
        if args.negatives[..i].iter().any(|d| same(d, dir)) {
            anyhow::bail!(
                "--negatives {} is given twice (its queries would count twice in the fit)",
                dir.display()
            );
        }
        if args.camera_dataset.iter().any(|d| same(d, dir)) {
            anyhow::bail!(
                "--negatives {} is also a --camera-dataset: one folder cannot be in the map and outside it",
                dir.display()
            );
        }
        let idx =
            DatasetIndex::open(dir).with_context(|| format!("--negatives {}", dir.display()))?;
        neg_indexes.push((dir, idx));
    }
    let models = loading::models_dir(args.models.as_deref())?;
    let map = match &args.db {
        Some(p) => loading::load_map(p, args.threads)
            .with_context(|| format!("loading {}", p.display()))?,
        None => {
            let preset = Preset::named(args.preset.as_deref().unwrap_or(DEFAULT_PRESET))?;
            loading::build_map(&map_id, &scenes, &preset, &models, args.threads)?
        }
    };
    let preset = match &args.preset {
        Some(name) => Preset::named(name)?,
        None => map.header.preset.clone(),
    };
    let stage = loading::feature_stage(&preset, &models, args.threads)?;
    let pipeline = Pipeline::new(Arc::new(map), stage, preset.clone())?
        .with_calibration(loading::calibration(args.calibration.as_deref())?, None);
    let (mut samples, mut notes) = (Vec::new(), Vec::new());
    let inmap = query_list(scenes.iter().copied(), args.queries)?;
    collect(
        &pipeline,
        &inmap,
        None,
        false,
        "in-map queries",
        &mut samples,
        &mut notes,
    )?;
    if !args.no_effects {
        let fx = RobotEffects::default();
        collect(
            &pipeline,
            &inmap,
            Some(&fx),
            false,
            "in-map queries, robot effects",
            &mut samples,
            &mut notes,
        )?;
    }
    let mut other_cameras = Vec::new();
    for dir in &args.camera_dataset {
        let idx = DatasetIndex::open(dir)
            .with_context(|| format!("--camera-dataset {}", dir.display()))?;
        let (_, sc) = loading::select_scenes(&idx, args.scene.as_deref())?;
        let list = query_list(sc.iter().copied(), args.queries)?;
        collect(
            &pipeline,
            &list,
            None,
            false,
            &format!("in-map queries, {}", dir.display()),
            &mut samples,
            &mut notes,
        )?;
        other_cameras.push(format!(
            "in-map, also {} ({} queries)",
            dir.display(),
            list.len()
        ));
    }
    let n_inmap = samples.len();
    let mut negatives = Vec::new();
    for (dir, idx) in &neg_indexes {
        let scenes: Vec<&SceneEntry> = idx.scenes.iter().collect();
        let neg = query_list(scenes.iter().copied(), args.negative_queries)?;
        collect(
            &pipeline,
            &neg,
            None,
            true,
            &format!("out-of-map queries, {}", dir.display()),
            &mut samples,
            &mut notes,
        )?;
        negatives.push(format!(
            "out-of-map {} ({} queries)",
            dir.display(),
            neg.len()
        ));
    }
    if let Some(path) = &args.samples {
        let mut text = String::new();
        let flat = samples
            .iter()
            .enumerate()
            .flat_map(|(g, q)| q.candidates.iter().map(move |c| (g, c)));
        for (i, (g, (e, right))) in flat.enumerate() {
            let mut line = serde_json::to_value(&notes[i])?;
            line["right"] = serde_json::json!(right);
            line["negative"] = serde_json::json!(g >= n_inmap);
            line["evidence"] = serde_json::json!(e);
            text += &format!("{line}\n");
        }
        crate::output::write_text(path, &text)?;
    }
    let mut c = fit::fit(&samples, args.l2, args.target_precision, &preset.name)?;
    c.fitted_on.datasets = vec![format!(
        "in-map {} ({} queries)",
        dataset.display(),
        inmap.len()
    )];
    c.fitted_on.datasets.extend(negatives);
    c.fitted_on.datasets.extend(other_cameras);
    c.fitted_on.date = today();
    c.save(out)?;
    // Read it back: what was written is what the server will load.
    let c: Calibration = Calibration::load(out)?;
    let summary = serde_json::json!({
        "out": out,
        "samples": c.fitted_on.samples,
        "positives": c.fitted_on.positives,
        "threshold": c.threshold,
        "ece": c.fitted_on.ece,
        "precision_at_threshold": c.fitted_on.precision_at_threshold,
        "recall_at_threshold": c.fitted_on.recall_at_threshold,
        "weights": EVIDENCE_NAMES.iter().zip(&c.weights).map(|(n, w)| (n.to_string(), serde_json::json!(*w))).collect::<serde_json::Map<String, serde_json::Value>>(),
    });
    println!("{}", serde_json::to_string_pretty(&summary)?);
    Ok(())
}

/// `pntr calibrate --db MAP --dataset D` without `--negatives`: refit the map's own calibration on
/// D's queries and rewrite the map (or write `--out`).
fn own(args: &CalibrateArgs) -> Result<()> {
    let Some(db) = &args.db else {
        anyhow::bail!(
            "give --negatives (places the map does not cover) to fit a calibration file, or --db MAP to refit that map's own calibration from --dataset"
        );
    };
    if !args.camera_dataset.is_empty() {
        anyhow::bail!("--camera-dataset goes with --negatives (a calibration file)");
    }
    if let Some(scene) = &args.scene {
        anyhow::bail!(
            "--scene {scene} goes with --negatives: refitting a map's own calibration uses the map's own scenes"
        );
    }
    let out = args.out.clone().unwrap_or_else(|| db.clone());
    let models = loading::models_dir(args.models.as_deref())?;
    let map =
        loading::load_map(db, args.threads).with_context(|| format!("loading {}", db.display()))?;
    let opts = FitOptions {
        max_frames: args.self_calibration_frames,
        base: match &args.calibration {
            Some(p) => Calibration::load(p)?,
            None => Calibration::embedded(),
        },
        keep_on_refusal: false,
    };
    let stages = crate::loading::stages(&models, args.threads);
    let refitted = match &args.dataset {
        None => with_sequences(map, args, &opts, &stages)?,
        Some(dataset) => {
            let index = DatasetIndex::open(dataset)?;
            let scenes: Vec<&SceneEntry> = map
                .header
                .scenes
                .iter()
                .map(|name| {
                    index.scenes.iter().find(|s| s.name == *name).with_context(|| {
                        format!(
                            "--dataset {} has no scene `{name}`, which map {} holds: give the dataset the map was built from",
                            dataset.display(),
                            db.display()
                        )
                    })
                })
                .collect::<Result<_>>()?;
            own_calibration::on_dataset(
                map,
                &scenes,
                &opts,
                &stages,
                None,
                &mut crate::output::bars(),
            )?
        }
    };
    if let Some(path) = &args.samples {
        crate::own_calibration::write_samples(path, &refitted.answers)?;
    }
    finish_own(&refitted.map, &out)
}

/// The map's own calibration refitted on the frames of `--sequence` recordings (poses in the map's
/// frame) that are not map images, evenly spaced ([`own_calibration::recording_frames`]).
fn with_sequences(
    map: pntr_pipeline::map::Map,
    args: &CalibrateArgs,
    opts: &FitOptions,
    stages: &pntr_mapping::stages::Stages,
) -> Result<own_calibration::Refitted> {
    if !args.trajectory.is_empty() && args.trajectory.len() != args.sequence.len() {
        anyhow::bail!(
            "{} --trajectory for {} --sequence: give one per recording, in the same order",
            args.trajectory.len(),
            args.sequence.len()
        );
    }
    let recs = args
        .sequence
        .iter()
        .enumerate()
        .map(|(i, p)| {
            open_recording(
                p,
                args.trajectory.get(i).map(PathBuf::as_path),
                &args.topics,
                args.depth_scale,
                args.intrinsics.as_deref(),
            )
        })
        .collect::<Result<Vec<_>>>()?;
    let sessions = as_sessions(&recs);
    let frames = own_calibration::recording_frames(&map, &sessions, opts.max_frames)
        .context("--sequence")?;
    Ok(own_calibration::on_recordings(
        map,
        &sessions,
        &frames,
        opts,
        stages,
        None,
        &mut crate::output::bars(),
    )?)
}

/// Write the map with its refitted calibration and print what was fitted.
fn finish_own(map: &pntr_pipeline::map::Map, out: &std::path::Path) -> Result<()> {
    pntr_pipeline::mapfile::save(map, out).with_context(|| format!("writing {}", out.display()))?;
    let mut summary = crate::own_calibration::summary(map.header.calibration.as_ref(), false);
    summary["out"] = serde_json::json!(out);
    println!("{}", serde_json::to_string_pretty(&summary)?);
    eprintln!(
        "{}",
        crate::own_calibration::line(map.header.calibration.as_ref(), false)
    );
    Ok(())
}

#[cfg(test)]
mod tests {
    #[test]
    fn today_is_a_date() {
        let d = super::today();
        assert_eq!(d.len(), 10);
        assert!(d.starts_with("20"));
    }
}
