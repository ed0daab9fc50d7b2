//! A map's own calibration from the command line (`build-db`, `calibrate --db`): frames with poses
//! from a dataset (its queries) or from recordings (frames the map was not built from), localized
//! against the whole map and with their own region held out ([`pntr_mapping::selfcal`]), and the
//! fitted calibration put into the map's header.

use std::path::Path;

use anyhow::{Context, Result};
use pntr_dataset::SceneEntry;
use pntr_mapping::recording_map::{self, Session};
use pntr_mapping::selfcal::{self, Answered, Regions};
use pntr_pipeline::calibration::{Calibration, MapCalibration};
use pntr_pipeline::map::Map;
use pntr_pipeline::pipeline::Pipeline;
use pntr_pipeline::preset::Preset;
use pntr_pipeline::PipelineError;

use crate::map_cmd::{bar, feature_stage};

/// Frames used by default (evenly spaced over what there is); each is localized twice.
pub const DEFAULT_FRAMES: usize = recording_map::SELF_CALIBRATION_FRAMES;

/// What the self-calibration is given besides the map.
pub struct Options<'a> {
    /// Frames used at most (0: all).
    pub max_frames: usize,
    /// The base calibration (`--calibration`; the shipped one when `None`).
    pub base: Option<&'a Path>,
    /// Folder of the models.
    pub models: &'a Path,
    /// ONNX Runtime threads.
    pub threads: usize,
    /// Write every frame's answer here (JSON lines), to study the map's look-alikes.
    pub samples: Option<&'a Path>,
    /// When the map cannot be calibrated from these frames (a single place, frames that are not
    /// the map's): keep the map as it is with a warning (`build-db`) rather than fail (`calibrate`).
    pub keep_on_refusal: bool,
}

/// One JSON line per frame: `{"held_out", "region", "candidates": [{"right", "evidence"}],
/// "rivals"}`.
fn write_samples(path: &Path, answers: &[Answered]) -> Result<()> {
    let mut text = String::new();
    for a in answers {
        let line = serde_json::json!({
            "held_out": a.held_out,
            "region": a.region,
            "candidates": a.samples.candidates.iter().map(|(e, right)| serde_json::json!({"right": right, "evidence": e})).collect::<Vec<_>>(),
            "rivals": a.samples.rivals,
        });
        text += &format!("{line}\n");
    }
    crate::map_cmd::write_text(path, &text)
}

impl<'a> Options<'a> {
    /// What `build-db` gives: its `--self-calibration-*` arguments, the shipped base, and a
    /// refusal that keeps the map as built.
    pub fn of_build(args: &'a crate::map_cmd::BuildArgs, models: &'a Path) -> Self {
        Self {
            max_frames: args.self_calibration_frames,
            base: None,
            models,
            threads: args.threads,
            samples: args.self_calibration_samples.as_deref(),
            keep_on_refusal: true,
        }
    }
}

fn base_of(path: Option<&Path>) -> Result<Calibration> {
    Ok(match path {
        Some(p) => Calibration::load(p)?,
        None => Calibration::embedded(),
    })
}

/// A pipeline over `map` with `base`'s weights (its threshold does not matter here: every frame's
/// candidates are kept and scored again when fitting).
fn pipeline(map: Map, opts: &Options<'_>) -> Result<(Pipeline, Calibration)> {
    let base = base_of(opts.base)?;
    let preset: Preset = map.header.preset.clone();
    let stage = feature_stage(&preset, opts.models, opts.threads)?;
    let p = selfcal::fitting_pipeline(map, stage, preset, &base)?;
    Ok((p, base))
}

/// The map back from a pipeline that was its only holder ([`selfcal::fitted_map`]).
pub fn into_map(p: Pipeline) -> Map {
    selfcal::fitted_map(p, None)
}

/// Fit `map`'s own calibration on the queries of `scenes` (the dataset it was built from; every
/// second frame with a robot camera's effects, so the fit sees the captures robots bring) and
/// return the map with it. `scenes` must be the map's scenes, in its order.
pub fn with_dataset(map: Map, scenes: &[&SceneEntry], opts: &Options<'_>) -> Result<Map> {
    let (p, base) = pipeline(map, opts)?;
    let regions = match Regions::of_map(&p.map) {
        Ok(r) => r,
        Err(PipelineError::Refused(why)) if opts.keep_on_refusal => {
            eprintln!("warning: the map keeps the shipped calibration: {why}");
            return Ok(into_map(p));
        }
        Err(e) => return Err(e.into()),
    };
    let fitted = pntr_mapping::own_calibration::fit_on_dataset(
        &p,
        &base,
        &regions,
        scenes,
        opts.max_frames,
        &mut shown_progress(&regions),
    )?;
    kept(p, opts, fitted.fit, &fitted.answers)
}

/// Fit the own calibration of a map built from recordings on `frames` ((session, frame) of
/// `sessions`, poses in the map's frame), reusing `in_map`, the check's answers of the same frames
/// when it ran ([`recording_map::fit_own_calibration`], with progress bars). Returns the map with it.
pub fn with_recordings(
    p: Pipeline,
    opts: &Options<'_>,
    base: &Calibration,
    regions: &Regions,
    sessions: &[Session<'_>],
    frames: &[(usize, usize)],
    in_map: Option<Vec<Answered>>,
) -> Result<Map> {
    let fitted = recording_map::fit_own_calibration(
        &p,
        base,
        regions,
        sessions,
        frames,
        in_map,
        &mut shown_progress(regions),
    )?;
    kept(p, opts, fitted.fit, &fitted.answers)
}

/// What a self-calibration pass's progress bar says.
fn pass_label(held_out: bool, regions: &Regions) -> String {
    if held_out {
        format!(
            "self-calibration: frames against the map without their region ({} regions)",
            regions.count()
        )
    } else {
        "self-calibration: frames against the whole map".into()
    }
}

/// A progress callback `(held_out, done, total)` shown as one bar per pass, each cleared when the
/// next starts or the callback is dropped.
fn shown_progress(regions: &Regions) -> impl FnMut(bool, usize, usize) + '_ {
    let mut shown: Option<(bool, Bar)> = None;
    move |held_out, done, n| {
        if shown.as_ref().is_none_or(|(h, _)| *h != held_out) {
            shown = Some((held_out, Bar(bar(n, &pass_label(held_out, regions)))));
        }
        if let Some((_, pb)) = &shown {
            pb.0.set_position(done as u64);
        }
    }
}

/// A progress bar cleared when dropped.
struct Bar(indicatif::ProgressBar);

impl Drop for Bar {
    fn drop(&mut self) {
        self.0.finish_and_clear();
    }
}

/// The map back with `fit` (the samples written first when asked); a refusal keeps the map as it
/// is with a warning when `opts` says so.
fn kept(
    p: Pipeline,
    opts: &Options<'_>,
    fit: Result<MapCalibration, PipelineError>,
    answers: &[Answered],
) -> Result<Map> {
    if let Some(path) = opts.samples {
        write_samples(path, answers)?;
    }
    match fit {
        Ok(f) => Ok(selfcal::fitted_map(p, Some(f))),
        Err(PipelineError::Refused(why)) if opts.keep_on_refusal => {
            eprintln!("warning: the map keeps the shipped calibration: {why}");
            Ok(into_map(p))
        }
        Err(e) => Err(e.into()),
    }
}

/// A pipeline over a recording map for its check and self-calibration, the base calibration and
/// the map's regions (`None` when the map has a single place, with the warning why).
pub fn for_recordings(
    map: Map,
    opts: &Options<'_>,
) -> Result<(Pipeline, Calibration, Option<Regions>, Option<String>)> {
    let (p, base) = pipeline(map, opts)?;
    match Regions::of_map(&p.map) {
        Ok(r) => Ok((p, base, Some(r), None)),
        Err(PipelineError::Refused(why)) => Ok((p, base, None, Some(why))),
        Err(e) => Err(e).context("cutting the map into regions"),
    }
}

/// What `build-db --json`, `calibrate` and `info` say about a map's calibration: its source, the
/// threshold, what it was fitted on, what it measured and whether it is stale.
pub fn summary(map_calibration: Option<&MapCalibration>, stale: bool) -> serde_json::Value {
    match map_calibration {
        None => serde_json::json!({
            "source": "shipped",
            "threshold": Calibration::embedded().threshold,
            "fitted_on": Calibration::embedded().fitted_on.datasets,
        }),
        Some(c) => serde_json::json!({
            "source": "map",
            "method": c.method,
            "threshold": c.calibration.threshold,
            "base_threshold": c.base_threshold,
            "fitted_on": c.calibration.fitted_on.datasets,
            "date": c.calibration.fitted_on.date,
            "regions": c.regions,
            "in_map_frames": c.in_map_queries,
            "held_out_frames": c.held_out_queries,
            "held_out_right": c.held_out_right,
            "negatives": c.negatives,
            "false_positives_at_base_threshold": c.false_positives_base,
            "false_positives": c.false_positives,
            "in_map_recall_at_base_threshold": c.in_map_recall_base,
            "in_map_recall": c.in_map_recall,
            "expected_precision": c.expected_precision,
            "stale": stale,
        }),
    }
}

/// One line for people: where the calibration comes from and what it measured.
pub fn line(map_calibration: Option<&MapCalibration>, stale: bool) -> String {
    match map_calibration {
        None => format!(
            "calibration: shipped (threshold {:.3})",
            Calibration::embedded().threshold
        ),
        Some(c) => format!(
            "calibration: the map's own{} (threshold {:.3}, shipped {:.3}; {} regions held out, {} of {} own negatives LOCALIZED, {} at the shipped threshold; in-map recall {:.3}, {:.3} at the shipped threshold; expected precision {:.3})",
            if stale {
                ", STALE: the map changed since it was fitted (refit with `pntr calibrate --db`)"
            } else {
                ""
            },
            c.calibration.threshold,
            c.base_threshold,
            c.regions,
            c.false_positives,
            c.negatives,
            c.false_positives_base,
            c.in_map_recall,
            c.in_map_recall_base,
            c.expected_precision
        ),
    }
}
