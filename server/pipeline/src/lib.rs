//! The heart of pntr: the map database and the PNTR localization pipeline.
//!
//! Why one crate for these: the map is exactly what the pipeline needs at query time (keypoints,
//! descriptors and their 3D points per database image, and the retrieval stage), and the file format
//! and the pipeline change together. Making and changing maps (building, keyframes, extension,
//! merging, a map's own calibration) lives above it in `pntr-mapping`, evaluation in `pntr-eval`; this
//! crate knows nothing of either.
//!
//! - [`preset`]: named combinations of stages (`fast`, `accurate`, `classical`, ICP variants).
//! - [`map`]: the map in memory (its images, header and retrieval stage); [`mapfile`]: the
//!   versioned, checksummed, atomically written file.
//! - [`camera`]: any query camera brought to the map's pixel scale (resampling, undistortion), with
//!   keypoints traced back to the query's own depth.
//! - [`depth_noise`]: how noisy a frame's depth is (`k` of `sigma = k z^2`), measured on the frame,
//!   which widens registration's bound with range for a real sensor's frame.
//! - [`pipeline`]: retrieve, re-rank by geometry, match, back-project, register, verify, compose.
//! - [`shortlist`]: the global ranking's top images re-ranked by a vote of their strongest keypoints,
//!   so look-alike rooms of a large map do not crowd the right one out of the candidates.
//! - [`alias`]: a registration locked onto a repeated texture one period off, found from the
//!   residuals of the other matches and moved when the dense checks prefer the copy they support.
//! - [`refine`]: a registered pose polished against the map view's whole depth (point-to-plane ICP
//!   with the keypoint inliers), the chosen one also against the neighbouring map views.
//! - [`verify`]: dense depth, free-space and colour checks of a pose against the map's thumbnails;
//!   [`calibration`]: the fitted model that turns them into the probability of a right pose.
//! - [`prior`]: a rough pose from the robot (odometry, the last fix) as a search region, and the
//!   spatial index over the map's camera positions that serves it.
//! - [`odometry`]: a stream's next frame registered against its keyframe (the last verified frame),
//!   anchored to a map fix, so a driving robot stays localized between views the map covers.

pub mod agreement;
pub mod alias;
pub mod calibration;
pub mod camera;
pub mod coverage;
pub mod depth_noise;
pub mod map;
pub mod mapfile;
pub mod odometry;
pub mod pipeline;
pub mod pose_check;
pub mod preset;
pub mod prior;
pub mod refine;
pub mod shortlist;
pub mod verify;

#[cfg(test)]
mod test_scenes;

use std::path::PathBuf;

/// Errors of the map and the pipeline.
#[derive(Debug, thiserror::Error)]
pub enum PipelineError {
    /// A configuration that cannot work (unknown preset, unfit stages, map/preset mismatch).
    #[error("configuration: {0}")]
    Config(String),
    /// A request that is well formed but cannot be done with these inputs (maps that do not
    /// overlap, a recording already in the map, nothing new to add); the message says why.
    #[error("{0}")]
    Refused(String),
    /// A query that cannot be localised as sent.
    #[error("invalid query: {0}")]
    Query(String),
    /// A map file that cannot be used.
    #[error("map file {path}: {message}")]
    MapFile {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
    /// An I/O failure.
    #[error("{path}: {message}")]
    Io {
        /// The file.
        path: PathBuf,
        /// What went wrong.
        message: String,
    },
    /// Reading the dataset failed.
    #[error(transparent)]
    Dataset(#[from] pntr_dataset::DatasetError),
    /// Feature extraction or matching failed.
    #[error(transparent)]
    Features(#[from] pntr_features::FeatureError),
    /// Retrieval failed.
    #[error(transparent)]
    Retrieval(#[from] pntr_retrieval::RetrievalError),
}
