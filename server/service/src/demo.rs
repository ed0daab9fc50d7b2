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
use pntr_pipeline::map::cache_path;
use pntr_pipeline::preset::{Preset, DEFAULT_PRESET};
use pntr_pipeline::{map, mapfile};
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
    let stage = preset
        .feature_config(models.to_path_buf())
        .build()
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
    let m = pntr_mapping::build::build(&scene, &[entry], &preset, &stage, models, &mut |_, _| {})
        .map_err(|e| e.to_string())?;
    log("fitting the demo map's own calibration on its scene's queries");
    let m = with_own_calibration(m, entry, stage, preset)?;
    mapfile::save(&m, &path).map_err(|e| e.to_string())?;
    Ok(path)
}

/// `map` with its own calibration fitted on [`pntr_mapping::recording_map::SELF_CALIBRATION_FRAMES`]
/// queries of `scene` (the dataset it was built from), as `pntr build-db --dataset` does.
fn with_own_calibration(
    map: map::Map,
    scene: &pntr_dataset::SceneEntry,
    stage: pntr_features::config::FeatureStage,
    preset: Preset,
) -> Result<map::Map, String> {
    use pntr_mapping::selfcal;
    let base = pntr_pipeline::calibration::Calibration::embedded();
    let p = selfcal::fitting_pipeline(map, stage, preset, &base).map_err(|e| e.to_string())?;
    let regions = selfcal::Regions::of_map(&p.map).map_err(|e| e.to_string())?;
    let fitted = pntr_mapping::own_calibration::fit_on_dataset(
        &p,
        &base,
        &regions,
        &[scene],
        pntr_mapping::recording_map::SELF_CALIBRATION_FRAMES,
        &mut |_, _, _| {},
    )
    .map_err(|e| format!("fitting the demo map's own calibration: {e}"))?;
    let calibration = fitted
        .fit
        .map_err(|e| format!("fitting the demo map's own calibration: {e}"))?;
    Ok(selfcal::fitted_map(p, Some(calibration)))
}
