//! `build-db --dataset` and the embedded demo map as one call: a map of a dataset's scenes
//! ([`crate::build::build`]), then its own calibration fitted on the same scenes' queries
//! ([`crate::own_calibration::on_dataset`]).

use pntr_dataset::SceneEntry;
use pntr_pipeline::map::Map;
use pntr_pipeline::preset::Preset;
use pntr_pipeline::PipelineError;
use serde::Serialize;

use crate::own_calibration::{self, FitOptions};
use crate::progress::{self, Progress};
use crate::selfcal::Answered;
use crate::stages::Stages;

/// What [`run`] is given besides the scenes.
pub struct Options {
    /// The map's id (clients name it in requests).
    pub map_id: String,
    /// The preset it is built with.
    pub preset: Preset,
    /// Fit the map's own calibration on the scenes' queries; `None` leaves the shipped one.
    pub self_calibration: Option<FitOptions>,
}

/// What [`run`] did besides the map.
#[derive(Debug, Serialize)]
pub struct Report {
    /// Seconds the map's own calibration took (0 when it was not fitted).
    pub self_calibration_seconds: f64,
    /// Why the map keeps the shipped calibration, when it was to be fitted and could not be.
    pub calibration_note: Option<String>,
    /// The fit's labelled answers, for studying the map's look-alikes.
    #[serde(skip)]
    pub answers: Vec<Answered>,
}

/// Build a map of `scenes` (HPointLoc-layout Point files) and fit its own calibration as `opts`
/// says, loading networks with `stages`. Progress: [`progress::DESCRIBING`], then the
/// self-calibration passes. Errors: those of [`crate::build::build`] and
/// [`own_calibration::on_dataset`].
pub fn run(
    scenes: &[&SceneEntry],
    opts: Options,
    stages: &Stages,
    progress: &mut Progress<'_>,
) -> Result<(Map, Report), PipelineError> {
    let stage = stages.map_stage(&opts.preset)?;
    let map = crate::build::build(
        &opts.map_id,
        scenes,
        &opts.preset,
        &stage,
        &stages.models,
        &mut progress::of(progress::DESCRIBING, progress),
    )?;
    let mut report = Report {
        self_calibration_seconds: 0.0,
        calibration_note: None,
        answers: Vec::new(),
    };
    let Some(fit) = &opts.self_calibration else {
        return Ok((map, report));
    };
    let done = own_calibration::on_dataset(map, scenes, fit, stages, Some(stage), progress)?;
    report.self_calibration_seconds = done.seconds;
    report.calibration_note = done.kept_because;
    report.answers = done.answers;
    Ok((done.map, report))
}
