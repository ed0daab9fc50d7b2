//! Progress of a long mapping job, reported through a callback: the command line turns each stage
//! into a progress bar, the server into log lines.

/// How far one stage of a mapping job is: `done` of `total` items (frames, images, queries).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Step<'a> {
    /// What is being done, for people (`choosing keyframes`, `checking the map`, ...). A new value
    /// starts a new stage.
    pub stage: &'a str,
    /// Items done.
    pub done: usize,
    /// Items in all (may grow while the stage runs).
    pub total: usize,
}

/// The callback an entry point reports through; `&mut |_| {}` ignores it.
pub type Progress<'p> = dyn FnMut(Step<'_>) + 'p;

/// Stage: database images described ([`crate::from_dataset`]).
pub const DESCRIBING: &str = "extracting database features";
/// Stage: a recording's frames read and judged ([`crate::from_recordings`]).
pub const KEYFRAMES: &str = "choosing keyframes";
/// Stage: frames the map was not built from localized against it ([`crate::from_recordings`]).
pub const CHECKING: &str = "checking the map";
/// Stage: the map's own calibration, frames against the whole map.
pub const SELF_CALIBRATION_IN_MAP: &str = "self-calibration: frames against the whole map";

/// Stage: the map's own calibration, frames against the map without their region.
pub fn self_calibration_held_out(regions: usize) -> String {
    format!("self-calibration: frames against the map without their region ({regions} regions)")
}

/// A self-calibration pass's `(held_out, done, total)` callback as steps of `progress`.
pub(crate) fn self_calibration<'a, 'p: 'a>(
    regions: usize,
    progress: &'a mut Progress<'p>,
) -> impl FnMut(bool, usize, usize) + use<'a, 'p> {
    let held_out_stage = self_calibration_held_out(regions);
    move |held_out, done, total| {
        let stage = if held_out {
            held_out_stage.as_str()
        } else {
            SELF_CALIBRATION_IN_MAP
        };
        progress(Step { stage, done, total })
    }
}

/// A `(done, total)` callback as steps of `stage`.
pub(crate) fn of<'a, 'p: 'a>(
    stage: &'a str,
    progress: &'a mut Progress<'p>,
) -> impl FnMut(usize, usize) + use<'a, 'p> {
    move |done, total| progress(Step { stage, done, total })
}
