//! What the commands load: the models folder and its networks, maps, calibrations, datasets'
//! scenes, and the robot camera effects `--effects` names.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use anyhow::{Context, Result};
use pntr_dataset::{DatasetIndex, SceneEntry};
use pntr_features::runtime::RuntimeOptions;
use pntr_mapping::stages::Stages;
use pntr_pipeline::calibration::Calibration;
use pntr_pipeline::map::Map;
use pntr_pipeline::mapfile;
use pntr_pipeline::pipeline::Pipeline;
use pntr_pipeline::preset::Preset;
use pntr_retrieval::onnx_global::OnnxGlobal;

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

/// The networks of the models folder `models` with `threads` ONNX Runtime threads.
pub fn stages(models: &Path, threads: usize) -> Stages {
    Stages::new(models, threads)
}

/// The feature stage that describes `preset`'s queries.
pub fn feature_stage(
    preset: &Preset,
    models: &Path,
    threads: usize,
) -> Result<pntr_features::config::FeatureStage> {
    Ok(stages(models, threads).query_stage(preset)?)
}

/// Build a map of `scenes` in memory (no own calibration), with a progress bar.
pub fn build_map(
    map_id: &str,
    scenes: &[&SceneEntry],
    preset: &Preset,
    models: &Path,
    threads: usize,
) -> Result<Map> {
    let opts = pntr_mapping::from_dataset::Options {
        map_id: map_id.to_string(),
        preset: preset.clone(),
        self_calibration: None,
    };
    let (map, _) = pntr_mapping::from_dataset::run(
        scenes,
        opts,
        &stages(models, threads),
        &mut crate::output::bars(),
    )?;
    Ok(map)
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
