//! Making and changing maps, above the localization pipeline: a map from a dataset's Point files
//! ([`build`]) or from a robot's recordings ([`recording_map`], choosing keyframes with
//! [`keyframes`]), extending one with new recordings, joining two maps whose frames differ
//! ([`merge`]), the map's own confidence calibration fitted on its own frames with each region held
//! out ([`selfcal`], [`own_calibration`]; the logistic fit itself in [`fit`]), and the check of a map
//! against frames it was not built from ([`recording_map::check`]).
//!
//! The pipeline below (`pntr-pipeline`: retrieval, matching, registration, verification, the prior,
//! odometry, the map file) knows nothing of building; the command line (`pntr build-db`, `pntr
//! calibrate`, `pntr maps merge`) and the server (`ExtendMap`, the demo map) call the functions here
//! and turn their progress callbacks into bars or logs. Errors are the pipeline's
//! ([`pntr_pipeline::PipelineError`]), so the server maps them to gRPC status in one place.

pub mod build;
pub mod fit;
pub mod from_dataset;
pub mod from_recordings;
pub mod keyframes;
pub mod merge;
pub mod own_calibration;
pub mod progress;
pub mod recording_map;
pub mod selfcal;
pub mod stages;

pub use pntr_pipeline::PipelineError;
