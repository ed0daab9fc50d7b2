//! Domain types shared by every pntr crate, with no I/O and no heavy dependencies.
//!
//! Why a crate of its own: the dataset reader, the synthetic renderer, the registration solvers, the
//! map and the service all speak about the same things (a camera pose, the camera's axes, its
//! intrinsics, an RGB image, a depth map). Keeping them here, at the bottom of the dependency graph,
//! means there is exactly one definition of each convention and every other crate converts through it.
//!
//! Naming follows the "what maps to what" rule: an `Isometry3` called `world_from_camera` maps a point
//! from camera coordinates to world coordinates (`p_world = world_from_camera * p_camera`). Units are in
//! names where they are not metres/radians (`_deg`, `_secs`).
//!
//! Conventions, fixed here once:
//! - World frame: the dataset's own (HPointLoc / Habitat: y up).
//! - Camera axes: [`CameraAxes::Habitat`] (x right, y up, looks along -z) is how HPointLoc stores
//!   poses; [`CameraAxes::OpenCv`] (x right, y down, looks along +z) is how pixels are back-projected.
//!   [`convert_axes`] moves a `world_from_camera` between them.
//! - Pixels: OpenCV convention, the centre of pixel (col, row) is at (u, v) = (col, row).

pub mod bytes;
pub mod categories;
pub mod image;
pub mod intrinsics;
pub mod pose;

pub use image::{DepthMap, ImageError, LabelMap, RgbImage};
pub use intrinsics::{Intrinsics, IntrinsicsError};
pub use pose::{
    convert_axes, pose_from_hpointloc, pose_to_hpointloc, rotation_angle_deg, CameraAxes, PoseError,
};

/// HPointLoc stores depth normalised to 0..1 where 1.0 is this many metres.
pub const HPOINTLOC_DEPTH_SCALE_M: f32 = 10.0;
