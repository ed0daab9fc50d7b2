//! Whether a recording's poses agree with its own images, before its frames become map images.
//!
//! A pose source can fail while the camera records on: a publisher that stalls repeats its last
//! pose while the images move; a motion-capture dropout puts a few frames metres from where they
//! were taken. Either would put map images where they were not taken. Each posed frame is compared
//! with a reference frame of the same recording: its verification thumbnail, moved by the recorded
//! relative pose into the reference's view ([`crate::verify::dense_check_both`], both ways), must not
//! mostly disagree with the reference's depth; and the recorded motion since the reference must not
//! be faster than a robot or a hand moves a camera. The reference stays until the recorded pose has
//! moved [`REFERENCE_STEP_M`] or turned [`REFERENCE_STEP_DEG`] from it, so a frozen pose (which never
//! moves) keeps being compared with the same reference while the camera moves away from it; when
//! the two views no longer share enough of their surfaces, nothing can be said and the frame becomes
//! the reference.
//!
//! The rules are loose on purpose (people walking through, depth noise, a pose stream a few
//! milliseconds off the images must pass): a frame is refused only when most of what the two views
//! share disagrees and a good part of it lies where the other camera saw through.

use nalgebra::Isometry3;

use crate::verify::{dense_check_both, Thumb};

/// Fastest recorded motion a frame may show since its reference, metres a second (a walking person
/// carries a camera at about 1.5, a fast robot drives at 2-3).
pub const MAX_SPEED_M_S: f64 = 5.0;
/// Fastest recorded turn since the reference, degrees a second.
pub const MAX_TURN_DEG_S: f64 = 360.0;
/// Share of the samples that must land on the other view's valid depth for the views to judge each
/// other.
pub const MIN_OVERLAP: f64 = 0.3;
/// Below this share of agreeing samples (with [`MAX_VIOLATE`]) the pose disagrees with the images.
/// Right poses measured 0.81 at worst, 0.95-0.99 at the median (real Kinect frames of 7-Scenes
/// redkitchen 0-499 at 30 Hz, rendered robot drives with depth noise and dropouts); a pose stalled
/// for 0.2 s of a hand-held camera's motion falls to 0.7.
pub const MIN_AGREE: f64 = 0.65;
/// Above this share of samples in the other view's free space (with [`MIN_AGREE`]) the pose
/// disagrees with the images. Right poses measured 0.10 at worst, 0.00-0.02 at the median.
pub const MAX_VIOLATE: f64 = 0.15;
/// Recorded motion from the reference after which an agreeing frame becomes the reference, metres.
pub const REFERENCE_STEP_M: f64 = 0.1;
/// Recorded turn from the reference after which an agreeing frame becomes the reference, degrees.
pub const REFERENCE_STEP_DEG: f64 = 5.0;

/// What [`PoseCheck::judge`] found.
#[derive(Debug, Clone, PartialEq)]
pub enum Verdict {
    /// The pose agrees with the images (or there was nothing yet to compare with).
    Agrees,
    /// The views share too little to judge: the frame is taken as it is and becomes the reference.
    Undecided,
    /// The pose disagrees with the images: why, in words.
    Disagrees(String),
}

struct Reference {
    thumb: Thumb,
    world_from_camera: Isometry3<f64>,
    stamp: f64,
}

/// The check over one recording's frames in time order ([`PoseCheck::new_session`] between
/// recordings).
#[derive(Default)]
pub struct PoseCheck {
    reference: Option<Reference>,
}

impl PoseCheck {
    /// Forget the reference (a new recording starts).
    pub fn new_session(&mut self) {
        self.reference = None;
    }

    /// Judge the frame of `thumb` (its verification thumbnail: [`Thumb::new`]) recorded at
    /// `world_from_camera` (optical axes) at `stamp` seconds.
    pub fn judge(
        &mut self,
        thumb: Thumb,
        world_from_camera: &Isometry3<f64>,
        stamp: f64,
    ) -> Verdict {
        let new = |thumb| Reference {
            thumb,
            world_from_camera: *world_from_camera,
            stamp,
        };
        let Some(r) = &self.reference else {
            self.reference = Some(new(thumb));
            return Verdict::Agrees;
        };
        let dt = (stamp - r.stamp).abs().max(1e-3);
        let ref_from_frame = r.world_from_camera.inverse() * world_from_camera;
        let moved_m = ref_from_frame.translation.vector.norm();
        let turned_deg = ref_from_frame.rotation.angle().to_degrees();
        if moved_m / dt > MAX_SPEED_M_S || turned_deg / dt > MAX_TURN_DEG_S {
            return Verdict::Disagrees(format!(
                "the pose moved {moved_m:.2} m and turned {turned_deg:.0} deg in {dt:.3} s since the frame at {:.3} s, faster than a camera is carried",
                r.stamp
            ));
        }
        let c = dense_check_both(&thumb, &r.thumb, &ref_from_frame);
        tracing::debug!(
            stamp,
            reference = r.stamp,
            overlap = c.overlap(),
            agree = c.agree_share(),
            violate = c.violate_share(),
            "recorded pose against the reference frame"
        );
        if c.overlap() < MIN_OVERLAP {
            self.reference = Some(new(thumb));
            return Verdict::Undecided;
        }
        if c.agree_share() < MIN_AGREE && c.violate_share() > MAX_VIOLATE {
            return Verdict::Disagrees(format!(
                "moved by the recorded poses, its depth agrees with the frame at {:.3} s on {:.0}% of what both see and {:.0}% lies where that camera saw through (the poses moved {moved_m:.2} m, turned {turned_deg:.0} deg between them)",
                r.stamp,
                100.0 * c.agree_share(),
                100.0 * c.violate_share()
            ));
        }
        if moved_m > REFERENCE_STEP_M || turned_deg > REFERENCE_STEP_DEG {
            self.reference = Some(new(thumb));
        }
        Verdict::Agrees
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_scenes::{room_frame, CLUTTER};
    use nalgebra::{Translation3, UnitQuaternion, Vector3};
    use pntr_core::Intrinsics;

    /// A robot driving into a cluttered room at 0.3 m/s, 10 frames a second, turning at 20 deg/s.
    fn walk(k: usize) -> Isometry3<f64> {
        let s = k as f64 * 0.1;
        Isometry3::from_parts(
            Translation3::new(0.0, 0.0, -1.0 + 0.3 * s),
            UnitQuaternion::from_axis_angle(&Vector3::y_axis(), (20.0 * s - 30.0).to_radians()),
        )
    }

    /// What the camera at `pose` sees, with a depth sensor's noise.
    fn seen(pose: &Isometry3<f64>, seed: u64) -> Thumb {
        let k = Intrinsics::hpointloc();
        let (rgb, depth) = room_frame(pose, &k, 0.01, seed, &CLUTTER);
        Thumb::new(&rgb, &depth, &k)
    }

    fn run(recorded: impl Fn(usize) -> Isometry3<f64>) -> Vec<bool> {
        let mut check = PoseCheck::default();
        (0..30)
            .map(|k| {
                let v = check.judge(seen(&walk(k), k as u64), &recorded(k), k as f64 * 0.1);
                matches!(v, Verdict::Disagrees(_))
            })
            .collect()
    }

    #[test]
    fn right_poses_pass_and_stalled_or_jumping_ones_are_found() {
        // Right poses, with a depth sensor's noise: nothing disagrees.
        assert!(run(walk).iter().all(|d| !d), "{:?}", run(walk));
        // The pose source stalls at frame 10 while the camera walks on: once the camera is a
        // few tens of centimetres from the repeated pose, its frames disagree, and frames with
        // right poses again agree (the reference is the last frame that agreed).
        let stalled = run(|k| {
            if (10..20).contains(&k) {
                walk(10)
            } else {
                walk(k)
            }
        });
        assert!(stalled[..10].iter().all(|d| !d), "{stalled:?}");
        assert!(stalled[14..20].iter().all(|d| *d), "{stalled:?}");
        assert!(stalled[20..].iter().all(|d| !d), "{stalled:?}");
        // Three frames 5 m off (a motion-capture dropout): too fast to be carried.
        let jumped = run(|k| {
            if (15..18).contains(&k) {
                Isometry3::translation(5.0, 0.0, 0.0) * walk(k)
            } else {
                walk(k)
            }
        });
        let found: Vec<usize> = (0..30).filter(|&k| jumped[k]).collect();
        assert_eq!(found, vec![15, 16, 17]);
    }
}
