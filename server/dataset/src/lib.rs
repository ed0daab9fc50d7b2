//! The HPointLoc dataset on disk: find scenes and Points, read and write their HDF5 files.
//!
//! Layout (see `shared/docs/hpointloc.md`): `<root>/HPointLoc_dataset/<scene>/<scene>_point<N>.hdf5`,
//! one file per Point, holding the Point's database views (`rgb_base`, `depth_base`, `semantic_base`,
//! `gps_base`, `quat_base`) and its queries (`rgb`, `depth`, `gps`, `quat`). HPointLoc has no camera
//! field; pntr stores a camera other than HPointLoc's in the extra fields `camera_base` and `camera`
//! (float64 `[fx, fy, cx, cy]` or `[fx, fy, cx, cy, k1, k2, p1, p2, k3]`), which readers of the real
//! dataset ignore; without them a role has HPointLoc's 90-degree camera at its image size. The two
//! roles may have different image sizes.
//!
//! Why it is built this way:
//! - The reader validates every field's presence, dtype and shape when a file is opened, and names the
//!   file and field in every error. HDF5 converts numeric types silently (a float dataset read as u8
//!   "works"), so dtypes are checked explicitly before any read.
//! - Views are read one at a time through hyperslab selections, so an evaluation over 76k queries never
//!   holds more than one frame per worker; [`PointReader::read_all`] exists for small scenes and tests.
//! - The writer produces what h5py produces by default (no "latest" file format), so the files open
//!   with h5py and with the HPointLoc code exactly like the real dataset, and it writes to a temporary
//!   name and renames, so an interrupted write never leaves a half file under the final name.
//! - Damaged files must be refused, not crash the process. HDF5 is linked statically at 2.2 (built from
//!   source by hdf5-metno): Debian's libhdf5 1.10.8 segfaulted on damaged files that 2.2 refuses with an
//!   error (found by fuzzing, RELIABILITY.md). The reader also checks each dataset's storage (sizes,
//!   chunk shapes and positions) before reading, and every HDF5 call runs with a note naming the file
//!   and field that a fatal-signal handler prints, so a crash that slips through still says which file
//!   to replace (`last_words`).
//! - Poses come out as `world_from_camera` in Habitat camera axes, exactly as stored; conversion to
//!   OpenCV axes is an explicit call into `pntr_core`.

pub mod bag;
pub mod bag_writer;
pub mod depth_alignment;
pub mod depth_camera;
mod error;
mod last_words;
pub mod layout;
pub mod queries;
mod reader;
pub mod recording;
pub mod sevenscenes;
pub mod tf;
pub mod tum;
pub mod write_guard;
mod writer;

pub use error::DatasetError;
pub use layout::{DatasetIndex, PointEntry, SceneEntry};
pub use reader::{PointReader, MAX_IMAGE_SIDE, MAX_VIEWS};
pub use writer::{write_point, WriteOptions};

use nalgebra::Isometry3;
use pntr_core::{DepthMap, Intrinsics, LabelMap, RgbImage};

/// Whether a view is one of a Point's database images or one of its queries.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Role {
    /// `*_base` fields: the map's images.
    Database,
    /// The plain fields: query images.
    Query,
}

impl Role {
    /// The HDF5 field name of `stem` (`rgb`, `depth`, `semantic`, `gps`, `quat`) for this role.
    pub fn field(self, stem: &str) -> String {
        match self {
            Role::Database => format!("{stem}_base"),
            Role::Query => stem.to_string(),
        }
    }
}

/// One RGB-D frame with its ground-truth pose.
#[derive(Debug, Clone, PartialEq)]
pub struct View {
    /// Camera-to-world pose, Habitat camera axes (as stored in the file).
    pub world_from_camera: Isometry3<f64>,
    /// The colour image.
    pub rgb: RgbImage,
    /// Planar depth in metres (0 = invalid).
    pub depth: DepthMap,
    /// Per-pixel instance ids, where the file has them (database views only in HPointLoc).
    pub semantic: Option<LabelMap>,
    /// The camera that took it (the `camera` / `camera_base` field, else HPointLoc's 90-degree one).
    pub intrinsics: Intrinsics,
}

/// The camera a role has when its file has no camera field: HPointLoc's 90-degree horizontal field
/// of view at the role's image size (exactly `Intrinsics::hpointloc()` for 256x256).
pub fn default_camera(width: u32, height: u32) -> Intrinsics {
    Intrinsics::from_fov(width, height, 90.0)
}

/// Everything one Point file holds.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct PointRecord {
    /// The database views (6 in HPointLoc: yaw 0, 60, ..., 300 degrees).
    pub db: Vec<View>,
    /// The query views taken near this Point.
    pub queries: Vec<View>,
    /// Category id (index into `pntr_core::categories::CATEGORIES`) of each instance id, where known.
    /// Stored as the extra field `semantic_category`, which readers of the real dataset ignore.
    pub instance_categories: Option<Vec<u8>>,
}
