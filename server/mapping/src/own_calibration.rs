//! A dataset map's own confidence calibration, fitted on the queries of the dataset it was built
//! from: what `pntr build-db --dataset` runs and what the embedded demo map carries.
//!
//! Every second query goes through a robot camera's effects ([`pntr_synth::effects::RobotEffects`],
//! seeded by its place in the list), so the fit sees the captures robots bring; each is localized
//! against the whole map and again with its region held out ([`pntr_pipeline::selfcal`]). It lives
//! here rather than in the pipeline crate because the effects come from `pntr-synth`, which the
//! pipeline only uses in its tests. Maps from recordings are fitted by
//! [`pntr_pipeline::recording_map::fit_own_calibration`] on their own frames.

use pntr_core::{convert_axes, CameraAxes};
use pntr_dataset::queries::{query_list, QueryViews};
use pntr_dataset::SceneEntry;
use pntr_pipeline::calibration::Calibration;
use pntr_pipeline::pipeline::{Pipeline, Query};

use crate::fit::today;
use crate::recording_map::FittedCalibration;
use crate::selfcal::{self, PosedFrame, Regions};
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
