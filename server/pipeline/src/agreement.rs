//! How well the map's own views agree with a frame placed at a given pose: the referee between two
//! poses of one stream frame (the track's and a map fix's), and the check that a tracked pose still
//! lies where the map says it can.
//!
//! Verification judges a map answer against the views of the image it matched. A pose that did not
//! come from matching (odometry carried it there) has no matched view, so the map images taken
//! nearby and looking the same way judge it instead: the frame's thumbnail is moved into each of
//! them ([`dense_check`]) and the depths compared. A pose 0.7 m off along a corridor keeps the side
//! walls but not the far wall; a right one agrees nearly everywhere the views overlap.

use nalgebra::{Isometry3, Vector3};
use pntr_core::{convert_axes, CameraAxes};

use crate::map::MapImage;
use crate::prior::{PoseIndex, Region};
use crate::verify::{dense_check, DenseCounts, Thumb};

/// Map images taken within this distance of the pose judge it, metres.
pub const VIEW_RADIUS_M: f64 = 2.5;
/// ... and looking within this angle of its optical axis, degrees.
pub const VIEW_MAX_DEG: f64 = 60.0;
/// At most this many of them (the nearest).
pub const MAX_VIEWS: usize = 6;
/// Fewest of the frame's samples that must land on a view's valid depth for it to judge.
pub const MIN_INSIDE: usize = 60;
/// Smallest share of those that must agree with the view or lie where it saw through.
pub const MIN_DECIDED: f64 = 0.3;

/// The views' judgement of a pose.
#[derive(Debug, Clone, PartialEq)]
pub struct Agreement {
    /// Each view's counts ([`dense_check`], frame into view), nearest view first.
    pub each: Vec<DenseCounts>,
}

impl Agreement {
    /// Whether a view's counts decide about the pose: at least [`MIN_INSIDE`] of the frame's samples
    /// land on its depth, and at least [`MIN_DECIDED`] of those agree with it or lie where it saw
    /// through (a view looking at a wall between it and the frame's surfaces, from the next room,
    /// sees neither).
    fn decides(c: &DenseCounts) -> bool {
        c.inside >= MIN_INSIDE && (c.agree + c.violate) as f64 >= MIN_DECIDED * c.inside as f64
    }

    /// The views that decide ([`Agreement::decides`]).
    pub fn deciding(&self) -> usize {
        self.each.iter().filter(|c| Self::decides(c)).count()
    }

    /// How strongly the map contradicts the pose, 0..1: over the deciding views, the smallest share
    /// of samples that lie where the view saw through among those the view decides (agreeing or
    /// seen through). A right pose has at least one view that agrees nearly everywhere it decides
    /// (on our drives with a robot's depth noise: at most 0.18); a pose 0.25 m or more off is seen
    /// through by every view that looks at the same surfaces (0.4 and more). `None` without a
    /// deciding view.
    pub fn contradiction(&self) -> Option<f64> {
        self.each
            .iter()
            .filter(|c| Self::decides(c))
            .map(|c| c.violate as f64 / (c.agree + c.violate) as f64)
            .min_by(f64::total_cmp)
    }
}

/// The agreement of the map's views (`images`) with the frame `thumb` at `world_from_camera` (map
/// frame, OpenCV camera axes): the counts of [`nearby_views`]. `None` when no view decides
/// ([`Agreement::deciding`]: the map has no view of what the frame sees from there, nothing to judge
/// by).
pub fn map_agreement(
    images: &[MapImage],
    index: &PoseIndex,
    axes: CameraAxes,
    thumb: &Thumb,
    world_from_camera: &Isometry3<f64>,
) -> Option<Agreement> {
    let a = Agreement {
        each: nearby_views(images, index, axes, thumb, world_from_camera),
    };
    (a.deciding() > 0).then_some(a)
}

/// The frame `thumb` at `world_from_camera` (map frame, OpenCV camera axes) moved into each of up to
/// [`MAX_VIEWS`] map images (`images`, `axes`: their camera axes, `index`: their camera positions)
/// within [`VIEW_RADIUS_M`] whose optical axis is within [`VIEW_MAX_DEG`] of the pose's, nearest
/// first: each one's [`dense_check`] counts.
pub fn nearby_views(
    images: &[MapImage],
    index: &PoseIndex,
    axes: CameraAxes,
    thumb: &Thumb,
    world_from_camera: &Isometry3<f64>,
) -> Vec<DenseCounts> {
    let Ok(region) = Region::new(world_from_camera.translation.vector, VIEW_RADIUS_M) else {
        return Vec::new();
    };
    let axis = world_from_camera.rotation * Vector3::z();
    let cos_max = VIEW_MAX_DEG.to_radians().cos();
    let mut each = Vec::new();
    for i in index.within(&region) {
        let Some(im) = images.get(i) else {
            continue;
        };
        let world_from_view = convert_axes(&im.world_from_camera, axes, CameraAxes::OpenCv);
        if (world_from_view.rotation * Vector3::z()).dot(&axis) < cos_max {
            continue;
        }
        each.push(dense_check(
            thumb,
            &im.thumb,
            &(world_from_view.inverse() * world_from_camera),
        ));
        if each.len() == MAX_VIEWS {
            break;
        }
    }
    each
}

#[cfg(test)]
mod tests {
    use super::*;

    fn wall(depth_m: f64) -> Thumb {
        crate::test_scenes::wall(depth_m, true)
    }

    fn judged(frame: &Thumb, views: &[(&Thumb, Isometry3<f64>)]) -> Agreement {
        Agreement {
            each: views
                .iter()
                .map(|(t, view_from_frame)| dense_check(frame, t, view_from_frame))
                .collect(),
        }
    }

    #[test]
    fn a_slipped_pose_is_contradicted_and_a_view_through_a_wall_decides_nothing() {
        let view = wall(2.0);
        // The frame where it was taken: the view agrees everywhere.
        let right = judged(&wall(2.0), &[(&view, Isometry3::identity())]);
        assert_eq!(right.deciding(), 1);
        assert!(right.contradiction().unwrap() < 0.05);
        // The same frame placed 0.5 m behind where it was taken: its wall lies 0.5 m in front of
        // the one the view saw, where the view saw through.
        let behind = Isometry3::translation(0.0, 0.0, -0.5);
        let slipped = judged(&wall(2.0), &[(&view, behind)]);
        assert!(slipped.contradiction().unwrap() > 0.9);
        // A view whose own wall stands 1 m before the frame's surfaces (the next room's) sees
        // neither agreement nor violation there: it does not decide, and it does not dilute the
        // view that does.
        let next_room = wall(1.0);
        let both = judged(
            &wall(2.0),
            &[(&next_room, Isometry3::identity()), (&view, behind)],
        );
        assert_eq!(both.deciding(), 1);
        assert!(both.contradiction().unwrap() > 0.9);
        let none = judged(&wall(2.0), &[(&next_room, Isometry3::identity())]);
        assert_eq!(none.deciding(), 0);
        assert!(none.contradiction().is_none());
    }
}
