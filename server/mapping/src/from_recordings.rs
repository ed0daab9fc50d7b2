//! `build-db --sequence` and `--extend`, and a server's `ExtendMap`, as one call: keyframes of a
//! robot's recordings made into a new map or added to one ([`crate::recording_map`]), then the
//! check (frames the map was not built from, localized against it) and the map's own calibration
//! fitted on the same frames, the check's answers reused as the fit's in-map pass.

use std::collections::BTreeMap;
use std::time::Instant;

use pntr_pipeline::calibration::Calibration;
use pntr_pipeline::map::Map;
use pntr_pipeline::preset::Preset;
use pntr_pipeline::PipelineError;
use serde::Serialize;

use crate::keyframes::KeyframeParams;
use crate::own_calibration::{fitting_pipeline, refitted};
use crate::progress::{self, Progress};
use crate::recording_map::{self, BuildReport, CheckReport, Session};
use crate::selfcal::Answered;
use crate::stages::Stages;

/// What the recordings go into.
#[allow(clippy::large_enum_variant)] // made once per mapping job
pub enum Target {
    /// A new map.
    New {
        /// Its id (clients name it in requests).
        map_id: String,
        /// The preset it is built with.
        preset: Preset,
        /// The world's up axis (`y` or `z`); `None` infers it from the camera poses.
        up_axis: Option<String>,
    },
    /// An existing map of one scene, whose frame the recordings' poses are in; the result keeps
    /// its id, preset, axes and retrieval.
    Extend(Map),
}

/// The check of the finished map.
pub struct Check<'a> {
    /// Another recording of the same place, in the map's frame, to localize instead of the frames
    /// between keyframes (the easy case: each is near one).
    pub other: Option<Session<'a>>,
    /// Frames localized at most, evenly spaced (0: all).
    pub frames: usize,
}

/// What [`run`] is given besides the recordings.
pub struct Options<'a> {
    /// New map or extension.
    pub target: Target,
    /// How keyframes are chosen.
    pub keyframes: KeyframeParams,
    /// The check; `None` skips it.
    pub check: Option<Check<'a>>,
    /// Fit the map's own calibration. On the checked frames when there is a check, otherwise on
    /// at most `self_calibration_frames` frames between keyframes. A map of a single place, or
    /// frames that cannot make a fit, keep the shipped calibration ([`Report::calibration_note`]).
    pub self_calibrate: bool,
    /// Frames of the fit without a check (0: all).
    pub self_calibration_frames: usize,
    /// The calibration the fit starts from (the shipped one unless the user fitted their own).
    pub base_calibration: Calibration,
}

/// What [`run`] did.
#[derive(Debug, Serialize)]
pub struct Report {
    /// The keyframe selection and the build (frames read, left out by reason, places, axes,
    /// warnings, seconds per stage).
    #[serde(flatten)]
    pub build: BuildReport,
    /// The check, when it ran.
    pub check: Option<CheckReport>,
    /// Seconds the map's own calibration took (0 when it was not fitted).
    pub self_calibration_seconds: f64,
    /// Why the map keeps the calibration it had (a map of a single place, frames that cannot make
    /// a fit), when it was to be fitted.
    pub calibration_note: Option<String>,
    /// The fit's labelled answers, for studying the map's look-alikes.
    #[serde(skip)]
    pub answers: Vec<Answered>,
}

/// Make or extend a map from `sessions` (recordings whose poses share the map's frame), check it
/// and fit its own calibration as `opts` says, loading networks with `stages`. Progress through
/// `progress`: [`progress::KEYFRAMES`], [`progress::CHECKING`], then the self-calibration passes.
///
/// Errors: those of [`recording_map::build`] and [`recording_map::extend`] (no posed frame, a depth
/// in the wrong unit, recordings that contradict the map, nothing new to add), models that do not
/// load, a frame the pipeline fails on.
pub fn run(
    sessions: &[Session<'_>],
    opts: Options<'_>,
    stages: &Stages,
    progress: &mut Progress<'_>,
) -> Result<(Map, Report), PipelineError> {
    let (map, build, map_stage) = match opts.target {
        Target::Extend(base) => {
            let preset = base.header.preset.clone();
            let stage = stages.map_stage(&preset)?;
            let (map, report) = recording_map::extend(
                base,
                sessions,
                opts.keyframes,
                &preset,
                &stage,
                &mut progress::of(progress::KEYFRAMES, progress),
            )?;
            (map, report, stage)
        }
        Target::New {
            map_id,
            preset,
            up_axis,
        } => {
            let stage = stages.map_stage(&preset)?;
            let (map, report) = recording_map::build(
                &map_id,
                sessions,
                opts.keyframes,
                up_axis.as_deref(),
                &preset,
                &stage,
                &stages.models,
                &mut progress::of(progress::KEYFRAMES, progress),
            )?;
            (map, report, stage)
        }
    };
    let mut report = Report {
        build,
        check: None,
        self_calibration_seconds: 0.0,
        calibration_note: None,
        answers: Vec::new(),
    };
    if opts.check.is_none() && !opts.self_calibrate {
        return Ok((map, report));
    }
    let t_cal = Instant::now();
    let (pipeline, regions) =
        fitting_pipeline(map, &opts.base_calibration, stages, Some(map_stage))?;
    let regions = match regions {
        Ok(r) => Some(r).filter(|_| opts.self_calibrate),
        Err(why) => {
            if opts.self_calibrate {
                report.calibration_note = Some(why);
            }
            None
        }
    };
    let other = opts.check.as_ref().and_then(|c| c.other.as_ref());
    let (check_sessions, frames, kind): (&[Session<'_>], Vec<(usize, usize)>, &str) = match other {
        Some(o) => (
            std::slice::from_ref(o),
            (0..o.recording.len()).map(|i| (0, i)).collect(),
            "another recording",
        ),
        None => (
            sessions,
            report.build.left_out.clone(),
            "frames between keyframes (the easy case: each is near one)",
        ),
    };
    let mut used = recording_map::evenly(&frames, opts.self_calibration_frames);
    let mut in_map = None;
    if let Some(c) = &opts.check {
        let frames = recording_map::evenly(&frames, c.frames);
        let mut checked = recording_map::check(
            &pipeline,
            check_sessions,
            &frames,
            kind,
            regions.as_ref(),
            &mut progress::of(progress::CHECKING, progress),
        )?;
        // The check's answers are the fit's in-map pass of the same frames.
        in_map = regions
            .is_some()
            .then(|| std::mem::take(&mut checked.answers));
        report.check = Some(checked);
        used = frames;
    }
    let t_fit = Instant::now();
    let Some(regions) = regions else {
        return Ok((crate::selfcal::fitted_map(pipeline, None), report));
    };
    let fitted = recording_map::fit_own_calibration(
        &pipeline,
        &opts.base_calibration,
        &regions,
        check_sessions,
        &used,
        in_map,
        &mut progress::self_calibration(regions.count(), progress),
    )?;
    let done = refitted(pipeline, fitted.fit, fitted.answers, true, t_cal)?;
    report.self_calibration_seconds = t_fit.elapsed().as_secs_f64();
    report.calibration_note = done.kept_because;
    report.answers = done.answers;
    Ok((done.map, report))
}

/// Seconds per stage of `report` for people: the build's, then `check` and `self_calibration`
/// when they ran.
pub fn stage_seconds(report: &Report) -> BTreeMap<String, f64> {
    let mut s = report.build.stage_seconds.clone();
    if let Some(c) = &report.check {
        s.insert("check".into(), c.seconds);
    }
    if report.self_calibration_seconds > 0.0 {
        s.insert("self_calibration".into(), report.self_calibration_seconds);
    }
    s
}
