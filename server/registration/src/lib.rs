//! Registration: turning matched keypoints with depth into a relative pose.
//!
//! Pure math on nalgebra with no I/O, so every solver is testable on generated data and usable from the
//! pipeline, the CLI and benchmarks alike.
//!
//! - [`teaser`]: certifiable-style robust 3D-3D registration in the manner of TEASER++ (Yang, Shi,
//!   Carlone 2020): pairwise-invariant pruning, maximum clique, GNC-TLS rotation, adaptive-voting TLS
//!   translation, then a least-squares polish on the inliers. Survives 95% outliers.
//! - [`icp`]: point-to-point ICP on matched pairs (trimmed) or on two clouds (nearest neighbours through
//!   a k-d tree), from identity or a prior.
//! - [`pnp`]: 2D-3D PnP with RANSAC over a six-point DLT and a Levenberg-Marquardt refinement of the
//!   reprojection error (the family the HPointLoc paper calls g2o).
//! - [`covariance`]: the 6x6 pose covariance of a 3D-3D registration from its inlier residuals.
//!
//! Convention everywhere: find `R`, `t` with `dst = R * src + t` (so the result is `dst_from_src`).

pub mod clique;
pub mod covariance;
pub mod icp;
mod kabsch;
mod kdtree;
pub mod pnp;
pub mod problems;
pub mod ransac;
pub mod teaser;

pub use kabsch::{kabsch, weighted_kabsch};
pub use teaser::{TeaserParams, TeaserResult};

use nalgebra::{Isometry3, Rotation3, Translation3, UnitQuaternion, Vector3};

/// A rigid transform as a rotation matrix and a translation: `dst = rotation * src + translation`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Rigid {
    /// Rotation.
    pub rotation: Rotation3<f64>,
    /// Translation, metres.
    pub translation: Vector3<f64>,
}

impl Rigid {
    /// The identity.
    pub fn identity() -> Self {
        Self {
            rotation: Rotation3::identity(),
            translation: Vector3::zeros(),
        }
    }

    /// As an isometry.
    pub fn to_isometry(&self) -> Isometry3<f64> {
        Isometry3::from_parts(
            Translation3::from(self.translation),
            UnitQuaternion::from_rotation_matrix(&self.rotation),
        )
    }

    /// From an isometry.
    pub fn from_isometry(iso: &Isometry3<f64>) -> Self {
        Self {
            rotation: iso.rotation.to_rotation_matrix(),
            translation: iso.translation.vector,
        }
    }

    /// Apply to a point.
    pub fn apply(&self, p: &Vector3<f64>) -> Vector3<f64> {
        self.rotation * p + self.translation
    }
}
