//! The embedded default: the demo synthetic scene and its map, generated once and cached on disk.
//!
//! `pntr-server` with no `--db` and `pntr demo` both call [`ensure_demo_map`], so a fresh machine
//! serves something real with no data at hand: a Val-sized procedural apartment in the HPointLoc layout
//! (`pntr synth` defaults) and a map of it built with the default preset, carrying its own confidence
//! calibration fitted on the scene's queries as `pntr build-db --dataset` fits it
//! ([`pntr_mapping::own_calibration`]). Both steps are skipped when their output is already there (the scene
//! folder appears only once complete; the map (`<cache>/<scene>-<preset>.pntrmap`) is written
//! atomically and must carry the expected preset and its own calibration, else it is rebuilt).

use std::path::{Path, PathBuf};

use pntr_dataset::DatasetIndex;
use pntr_mapping::from_dataset;
use pntr_mapping::own_calibration::FitOptions;
use pntr_pipeline::map::cache_path;
use pntr_pipeline::mapfile;
use pntr_pipeline::preset::{Preset, DEFAULT_PRESET};
use pntr_synth::SynthConfig;

/// Make sure the demo scene and its map exist under `cache`; return the map file. `log` receives
/// progress lines.
pub fn ensure_demo_map(
    cache: &Path,
    models: &Path,
    log: &mut dyn FnMut(&str),
) -> Result<PathBuf, String> {
    let cfg = SynthConfig::default();
    let scene = pntr_synth::scene_name(0);
    let path = cache_path(cache, &scene, DEFAULT_PRESET);
    let fresh = mapfile::read_header(&path)
        .map(|h| h.preset.name == DEFAULT_PRESET && h.map_id == scene && h.calibration.is_some())
        .unwrap_or(false);
    if fresh {
        return Ok(path);
    }
    // Models first: a missing model fails in a second, not after the scene is rendered.
    let preset = Preset::named(DEFAULT_PRESET).map_err(|e| e.to_string())?;
    pntr_mapping::build::model_identities(&preset, models)
        .map_err(|e| format!("loading the models from {}: {e}", models.display()))?;
    if !cache.join("HPointLoc_dataset").join(&scene).is_dir() {
        log(&format!(
            "generating the demo scene ({} Points, {} queries per Point, seed {}) in {}",
            cfg.points_per_scene,
            cfg.queries_per_point,
            cfg.seed,
            cache.display()
        ));
        let planned = pntr_synth::plan_all(&cfg);
        pntr_synth::synthesize(&cfg, cache, planned, &|| {})
            .map_err(|e| format!("generating the demo scene: {e}"))?;
    }
    log(&format!("building the demo map {}", path.display()));
    let index = DatasetIndex::open(cache).map_err(|e| e.to_string())?;
    let entry = index.scene(&scene).map_err(|e| e.to_string())?;
    // Its own calibration fitted on SELF_CALIBRATION_FRAMES of the scene's queries, as `pntr
    // build-db --dataset` does.
    let opts = from_dataset::Options {
        map_id: scene.clone(),
        preset,
        self_calibration: Some(FitOptions {
            keep_on_refusal: false,
            ..FitOptions::shipped(pntr_mapping::recording_map::SELF_CALIBRATION_FRAMES)
        }),
    };
    let stages = pntr_mapping::stages::Stages {
        models: models.to_path_buf(),
        runtime: Default::default(),
    };
    let mut stage = String::new();
    let (m, _) = from_dataset::run(&[entry], opts, &stages, &mut |s| {
        if s.stage != stage {
            log(s.stage);
            stage = s.stage.to_string();
        }
    })
    .map_err(|e| format!("building the demo map: {e}"))?;
    mapfile::save(&m, &path).map_err(|e| e.to_string())?;
    Ok(path)
}
