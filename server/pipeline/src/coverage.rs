//! Where the map reaches: the surfaces its images saw, kept as occupied voxels of the world frame,
//! and how much of a frame's depth, at a pose, lands on them.
//!
//! A stream tracked by odometry can carry its pose out of the mapped rooms (a mapping drive that
//! stopped before the last wing, a door the map never went through). There the pose may still be
//! right, but nothing the map holds confirms it, and a look-alike room the map does hold would be
//! the next map answer. [`Coverage::explained`] measures the share of the frame's depth (its
//! verification thumbnail, [`Thumb`]) that falls within a voxel of a surface some map image saw;
//! a tracked pose whose view the map barely explains is outside the mapped area
//! ([`crate::pipeline::Cause::OutsideMap`]).
//!
//! The voxels are made from the map images' thumbnails (their median-filtered depth, back-projected
//! at each image's pose), [`VOXEL_M`] a side, up to [`MAX_RANGE_M`] from the camera (far depth is
//! noisy and would mark space the map only glimpsed). A frame's point counts as explained when its
//! voxel or one of the 26 around it is occupied: a tolerance of one to two voxels, wider than
//! odometry drift over a few metres and the depth noise of real sensors at range.

use std::collections::HashSet;

use nalgebra::{Isometry3, Point3};
use pntr_core::pose::convert_axes;
use pntr_core::CameraAxes;

use crate::map::Map;
use crate::verify::Thumb;

/// Side of a coverage voxel, metres.
pub const VOXEL_M: f64 = 0.2;
/// Depth beyond this, metres, neither marks the map's surfaces nor is judged in a frame.
pub const MAX_RANGE_M: f64 = 6.0;
/// Fewest valid thumbnail depths a frame needs for [`Coverage::explained`] to judge it.
pub const MIN_POINTS: usize = 30;

/// The occupied voxels of a map's surfaces (world frame).
#[derive(Debug, Default)]
pub struct Coverage {
    cells: HashSet<[i32; 3]>,
}

fn cell(p: &Point3<f64>) -> [i32; 3] {
    [
        (p.x / VOXEL_M).floor() as i32,
        (p.y / VOXEL_M).floor() as i32,
        (p.z / VOXEL_M).floor() as i32,
    ]
}

/// The valid depths of `thumb` within [`MAX_RANGE_M`] as points of its OpenCV camera frame, every
/// `stride`-th pixel in each axis.
fn points(thumb: &Thumb, stride: usize) -> impl Iterator<Item = Point3<f64>> + '_ {
    let (w, h) = (thumb.width as usize, thumb.height as usize);
    (0..h).step_by(stride).flat_map(move |r| {
        (0..w).step_by(stride).filter_map(move |c| {
            let z = thumb.depth_mm[r * w + c] as f64 / 1000.0;
            (z > 0.0 && z <= MAX_RANGE_M)
                .then(|| thumb.intrinsics.backproject(c as f64, r as f64, z))
        })
    })
}

impl Coverage {
    /// The surfaces every image of `map` saw (`axes`: the map's camera axes). Time and memory grow
    /// with the map's images times their thumbnail pixels (a few hundred thousand voxels for a
    /// building): made once per map, when a stream first needs it.
    pub fn of_map(map: &Map, axes: CameraAxes) -> Self {
        let mut cells = HashSet::new();
        for im in &map.images {
            let world_from_camera = convert_axes(&im.world_from_camera, axes, CameraAxes::OpenCv);
            for p in points(&im.thumb, 1) {
                cells.insert(cell(&(world_from_camera * p)));
            }
        }
        Self { cells }
    }

    /// Occupied voxels.
    pub fn len(&self) -> usize {
        self.cells.len()
    }

    /// Whether no surface is known (an empty map).
    pub fn is_empty(&self) -> bool {
        self.cells.is_empty()
    }

    /// The share (0..1) of `thumb`'s valid depths that lie on a surface of the map when the camera
    /// is at `world_from_camera` (OpenCV camera axes, map world frame); `None` when the frame has
    /// fewer than [`MIN_POINTS`] valid depths within [`MAX_RANGE_M`] (nothing to judge by).
    pub fn explained(&self, thumb: &Thumb, world_from_camera: &Isometry3<f64>) -> Option<f64> {
        // About a thousand points are plenty for a share; a VGA frame's thumbnail holds ~5000.
        let n = thumb.width as usize * thumb.height as usize;
        let stride = ((n as f64 / 1200.0).sqrt().floor() as usize).max(1);
        let (mut seen, mut hit) = (0usize, 0usize);
        for p in points(thumb, stride) {
            seen += 1;
            let [x, y, z] = cell(&(world_from_camera * p));
            let near = (-1..=1).any(|dx| {
                (-1..=1).any(|dy| (-1..=1).any(|dz| self.cells.contains(&[x + dx, y + dy, z + dz])))
            });
            hit += near as usize;
        }
        (seen >= MIN_POINTS).then(|| hit as f64 / seen as f64)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion, Vector3};

    fn wall(depth_m: f64) -> Thumb {
        crate::test_scenes::wall(depth_m, false)
    }

    #[test]
    fn a_view_of_mapped_surfaces_is_explained_and_one_elsewhere_is_not() {
        let seen_from = Isometry3::identity();
        let mut c = Coverage::default();
        for p in points(&wall(2.0), 1) {
            c.cells.insert(cell(&(seen_from * p)));
        }
        // The same wall from 0.5 m to the side and 0.3 m nearer: mostly explained.
        let beside =
            Isometry3::from_parts(Translation3::new(0.5, 0.0, 0.3), UnitQuaternion::identity());
        let share = c.explained(&wall(1.7), &beside).unwrap();
        assert!(share > 0.6, "{share}");
        // Turned round to face the other way, 4 m off: a room the map never saw.
        let elsewhere = Isometry3::from_parts(
            Translation3::new(0.0, 0.0, -4.0),
            UnitQuaternion::from_axis_angle(&Vector3::y_axis(), std::f64::consts::PI),
        );
        let share = c.explained(&wall(2.0), &elsewhere).unwrap();
        assert!(share < 0.05, "{share}");
        // No depth: nothing to judge by.
        let mut blind = wall(2.0);
        blind.depth_mm.fill(0);
        assert!(c.explained(&blind, &seen_from).is_none());
    }
}
