//! A map's own confidence calibration: the LOCALIZED threshold (and, with enough samples, the
//! weights) fitted on frames with known poses, each localized against the whole map and again with
//! its region held out ([`crate::selfcal`]). Two sources of frames: the queries of the dataset a map
//! was built from ([`on_dataset`]: what `pntr build-db --dataset`, `pntr calibrate --db --dataset`
//! and the embedded demo map run; every second query through a robot camera's effects,
//! [`pntr_synth::effects::RobotEffects`], seeded by its place in the list, so the fit sees the
//! captures robots bring), and recordings whose poses are in the map's frame ([`on_recordings`]:
//! `pntr calibrate --db --sequence`, `pntr maps merge --sequence`; maps built or extended from
//! recordings are fitted on their own frames by [`crate::from_recordings`]).

use pntr_core::{convert_axes, CameraAxes};
use pntr_dataset::queries::{query_list, QueryViews};
use pntr_dataset::SceneEntry;
use pntr_pipeline::calibration::Calibration;
use pntr_pipeline::calibration::MapCalibration;
use pntr_pipeline::map::Map;
use pntr_pipeline::pipeline::{Pipeline, Query};

use crate::fit::today;
use crate::progress::Progress;
use crate::recording_map::{FittedCalibration, Session};
use crate::selfcal::Answered;
use crate::selfcal::{self, PosedFrame, Regions};
use crate::stages::Stages;
use pntr_pipeline::PipelineError;
use pntr_synth::effects::RobotEffects;

/// The own calibration of the map `pipeline` serves (with `base`'s weights), fitted on at most
/// `max_frames` queries (0: all) of `scenes`, the dataset the map was built from (its scenes, any
/// order; queries of other scenes are skipped), evenly spaced: both passes of
/// [`selfcal::pass`], then [`selfcal::fit`] from `base`, dated today. Returns the fit
/// (`Err(PipelineError::Refused)` when these queries cannot calibrate the map, saying why) and
/// every query's answers. `progress(held_out, done, total)` after each query. Errors: a query that
/// cannot be read, or that the pipeline fails on.
pub fn fit_on_dataset(
    pipeline: &Pipeline,
    base: &Calibration,
    regions: &Regions,
    scenes: &[&SceneEntry],
    max_frames: usize,
    progress: &mut dyn FnMut(bool, usize, usize),
) -> Result<FittedCalibration, PipelineError> {
    let names = pipeline.map.header.scenes.clone();
    let list = query_list(scenes.iter().copied(), max_frames)?;
    let fx = RobotEffects::default();
    let axes = pipeline.map.header.axes();
    let mut views = QueryViews::default();
    let mut frame = |i: usize| -> Result<Option<PosedFrame>, PipelineError> {
        let (entry, qi) = &list[i];
        let Some(scene) = names.iter().position(|s| *s == entry.scene) else {
            return Ok(None);
        };
        let v = views.view(entry, *qi)?;
        let mut query = Query {
            rgb: v.rgb,
            depth: v.depth,
            intrinsics: v.intrinsics,
        };
        if i % 2 == 1 {
            fx.apply(&mut query.rgb, &mut query.depth, i as u64 + 1);
        }
        Ok(Some(PosedFrame {
            query,
            // Habitat camera axes in the dataset, the map's in the answers.
            world_from_camera: convert_axes(&v.world_from_camera, CameraAxes::Habitat, axes),
            scene: scene as u32,
        }))
    };
    let n = list.len();
    let mut answers = Vec::with_capacity(2 * n);
    for held_out in [false, true] {
        answers.extend(selfcal::pass(
            pipeline,
            regions,
            n,
            held_out,
            &mut frame,
            &mut |d, n| progress(held_out, d, n),
        )?);
    }
    let fit = selfcal::fit(base, &pipeline.map, regions, &answers, &today());
    Ok(FittedCalibration { fit, answers })
}

/// What fitting a map's own calibration is given besides the map and its frames.
#[derive(Debug, Clone)]
pub struct FitOptions {
    /// Frames used at most, evenly spaced over what there is (0: all); each is localized twice.
    pub max_frames: usize,
    /// The calibration the fit starts from (its weights, and the lowest threshold it may choose):
    /// the shipped one unless the user fitted their own.
    pub base: Calibration,
    /// When the map cannot be calibrated from these frames (a map of a single place, frames that
    /// cannot make a fit): keep the map as it was and say why ([`Refitted::kept_because`]) rather
    /// than fail.
    pub keep_on_refusal: bool,
}

impl FitOptions {
    /// From the shipped calibration, at most `max_frames` frames, keeping the map on a refusal.
    pub fn shipped(max_frames: usize) -> Self {
        Self {
            max_frames,
            base: Calibration::embedded(),
            keep_on_refusal: true,
        }
    }
}

/// A map with its own calibration (re)fitted, and what the fit saw.
pub struct Refitted {
    /// The map: with the fitted calibration, or as it was when `kept_because` says why not.
    pub map: Map,
    /// Every frame's labelled answers (against the whole map, then held out), for studying the
    /// map's look-alikes (`--self-calibration-samples`).
    pub answers: Vec<Answered>,
    /// Why the map kept the calibration it had (only with [`FitOptions::keep_on_refusal`]).
    pub kept_because: Option<String>,
    /// Seconds the fit took, both passes.
    pub seconds: f64,
}

/// A pipeline over `map` with `base`'s weights for fitting (its threshold does not matter: every
/// frame's candidates are kept and scored again), describing queries with `stages`' query network
/// for the map's preset (or `map_stage` when that is the same network), and the map's regions or
/// why it has none.
pub fn fitting_pipeline(
    map: Map,
    base: &Calibration,
    stages: &Stages,
    map_stage: Option<pntr_features::config::FeatureStage>,
) -> Result<(Pipeline, Result<Regions, String>), PipelineError> {
    let preset = map.header.preset.clone();
    let stage = match map_stage {
        Some(s) => stages.query_stage_or(&preset, s)?,
        None => stages.query_stage(&preset)?,
    };
    let p = selfcal::fitting_pipeline(map, stage, preset, base)?;
    let regions = match Regions::of_map(&p.map) {
        Ok(r) => Ok(r),
        Err(PipelineError::Refused(why)) => Err(why),
        Err(e) => return Err(e),
    };
    Ok((p, regions))
}

/// The map back from `p` with `fit` when it was made; a refusal keeps the map as it was when
/// `keep_on_refusal`, saying why.
pub fn refitted(
    p: Pipeline,
    fit: Result<MapCalibration, PipelineError>,
    answers: Vec<Answered>,
    keep_on_refusal: bool,
    t0: std::time::Instant,
) -> Result<Refitted, PipelineError> {
    let (calibration, kept_because) = match fit {
        Ok(c) => (Some(c), None),
        Err(PipelineError::Refused(why)) if keep_on_refusal => (None, Some(why)),
        Err(e) => return Err(e),
    };
    let map = selfcal::fitted_map(p, calibration);
    Ok(Refitted {
        map,
        answers,
        kept_because,
        seconds: t0.elapsed().as_secs_f64(),
    })
}

/// A fitting pipeline over `map` ([`fitting_pipeline`]), `fit` run on it and its regions, and the
/// map back with the result ([`refitted`]); a map without regions is refused (kept when
/// `opts.keep_on_refusal`).
fn refit_with(
    map: Map,
    opts: &FitOptions,
    stages: &Stages,
    map_stage: Option<pntr_features::config::FeatureStage>,
    fit: impl FnOnce(&Pipeline, &Regions) -> Result<FittedCalibration, PipelineError>,
) -> Result<Refitted, PipelineError> {
    let t0 = std::time::Instant::now();
    let (p, regions) = fitting_pipeline(map, &opts.base, stages, map_stage)?;
    let fitted = match regions {
        Ok(regions) => fit(&p, &regions)?,
        Err(why) => FittedCalibration {
            fit: Err(PipelineError::Refused(why)),
            answers: Vec::new(),
        },
    };
    refitted(p, fitted.fit, fitted.answers, opts.keep_on_refusal, t0)
}

/// `map` with its own calibration fitted on the queries of `scenes` (the dataset it was built
/// from: its scenes; queries of other scenes are skipped), at most `opts.max_frames` of them
/// ([`fit_on_dataset`]). Errors: `Refused` for a map of a single place or queries that cannot
/// calibrate it (unless `opts.keep_on_refusal`), a query that cannot be read or that the pipeline
/// fails on, models that do not load.
pub fn on_dataset(
    map: Map,
    scenes: &[&SceneEntry],
    opts: &FitOptions,
    stages: &Stages,
    map_stage: Option<pntr_features::config::FeatureStage>,
    progress: &mut Progress<'_>,
) -> Result<Refitted, PipelineError> {
    refit_with(map, opts, stages, map_stage, |p, regions| {
        fit_on_dataset(
            p,
            &opts.base,
            regions,
            scenes,
            opts.max_frames,
            &mut crate::progress::self_calibration(regions.count(), progress),
        )
    })
}

/// The posed frames of `sessions` that are not `map`'s own images (they would be answered by
/// themselves), evenly spaced, at most `max` (0: all), as (session, frame). A frame is a map image
/// when an image has its stamp and its position (within 1 mm): two sessions' clocks both start at
/// 0 in rendered drives, so the stamp alone would leave out another session's frames that share
/// one. Errors: `Refused` when there is none.
pub fn recording_frames(
    map: &Map,
    sessions: &[Session<'_>],
    max: usize,
) -> Result<Vec<(usize, usize)>, PipelineError> {
    let stamped: Vec<(f64, nalgebra::Vector3<f64>)> = map
        .images
        .iter()
        .filter_map(|im| Some((im.stamp?, im.world_from_camera.translation.vector)))
        .collect();
    let is_map_image = |t: f64, at: nalgebra::Vector3<f64>| {
        stamped
            .iter()
            .any(|(s, p)| (s - t).abs() < 1e-6 && (p - at).norm() < 1e-3)
    };
    let frames: Vec<(usize, usize)> = sessions
        .iter()
        .enumerate()
        .flat_map(|(si, s)| {
            (0..s.recording.len())
                .filter(|&i| {
                    s.recording.world_from_camera(i).is_some_and(|pose| {
                        !is_map_image(s.recording.timestamp(i), pose.translation.vector)
                    })
                })
                .map(move |i| (si, i))
        })
        .collect();
    if frames.is_empty() {
        return Err(PipelineError::Refused(
            "the recordings have no posed frame that is not already a map image".into(),
        ));
    }
    Ok(crate::recording_map::evenly(&frames, max))
}

/// `map` with its own calibration fitted on `frames` ((session, frame) of `sessions`, recordings
/// whose poses are in the map's frame; [`recording_frames`] picks them) with
/// [`crate::recording_map::fit_own_calibration`]. Errors: as [`on_dataset`].
pub fn on_recordings(
    map: Map,
    sessions: &[Session<'_>],
    frames: &[(usize, usize)],
    opts: &FitOptions,
    stages: &Stages,
    map_stage: Option<pntr_features::config::FeatureStage>,
    progress: &mut Progress<'_>,
) -> Result<Refitted, PipelineError> {
    refit_with(map, opts, stages, map_stage, |p, regions| {
        crate::recording_map::fit_own_calibration(
            p,
            &opts.base,
            regions,
            sessions,
            frames,
            None,
            &mut crate::progress::self_calibration(regions.count(), progress),
        )
    })
}
