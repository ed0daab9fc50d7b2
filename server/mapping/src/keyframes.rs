//! Which frames of a recording become map images: keyframe selection and frame quality.
//!
//! A frame is kept when it adds a view the map does not have yet: no kept frame is within
//! [`KeyframeParams::distance_m`] and [`KeyframeParams::angle_deg`] of it while also seeing at least
//! [`KeyframeParams::min_overlap`] of what it sees (its depth re-projected into that frame). So a robot
//! turning in place keeps a frame every `angle_deg`, one driving straight every `distance_m`, and one
//! moving past a near wall (little overlap) more often. Before that, a frame is left out when it is
//! blurred (the variance of its Laplacian under [`KeyframeParams::blur_ratio`] of the median of the
//! frames before it: motion blur is relative to the scene), badly exposed (mostly black or saturated)
//! or has too little valid depth ([`KeyframeParams::min_valid_depth`]). Kept frames are grouped into
//! places (the map's Points): a frame joins the first place whose first frame is within
//! [`PLACE_RADIUS_M`], else it starts a new one, so verification's "nearby views" and eval's per-Point
//! metrics keep their meaning.
//!
//! Poses are `world_from_camera` with the optical axes (OpenCV), as recordings give them.

use std::collections::VecDeque;

use nalgebra::{Isometry3, Point3, Vector3};
use pntr_core::{DepthMap, Intrinsics, RgbImage};

use pntr_pipeline::verify::{dense_check_both, Thumb};

/// Radius of a place, metres: kept frames whose camera is this near a place's first frame join it.
pub const PLACE_RADIUS_M: f64 = 1.0;
/// Frames whose sharpness makes the running median a blurred frame is compared with.
const SHARPNESS_HISTORY: usize = 15;
/// Distance (m) and angle (rad) within which a frame is at a threshold rather than past it: the
/// rounding of poses.
const TIE_M: f64 = 1e-6;
const TIE_RAD: f64 = 1e-6;
/// Pixels sampled per axis for the overlap between two frames.
const OVERLAP_GRID: (u32, u32) = (24, 18);

/// Thresholds of keyframe selection.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct KeyframeParams {
    /// A frame farther than this from every kept frame is kept, metres.
    pub distance_m: f64,
    /// A frame turned more than this from every near kept frame is kept, degrees (geodesic).
    pub angle_deg: f64,
    /// A frame of which no near kept frame sees at least this share is kept (0..1).
    pub min_overlap: f64,
    /// A frame with less valid depth than this share of its pixels is left out (0..1).
    pub min_valid_depth: f64,
    /// A frame whose sharpness is under this share of the recent median is left out as blurred.
    pub blur_ratio: f64,
    /// When a map is extended ([`Selector::seed`]), one of its images covers a frame only if their
    /// grey levels also correlate at least this much under the relative pose (Pearson, -1..1, on
    /// the verification thumbnails): the same place under other lighting is a view the map lacks.
    pub min_appearance: f64,
}

impl Default for KeyframeParams {
    fn default() -> Self {
        Self {
            distance_m: 0.3,
            angle_deg: 15.0,
            min_overlap: 0.6,
            min_valid_depth: 0.2,
            blur_ratio: 0.4,
            min_appearance: 0.8,
        }
    }
}

/// Why a frame is not a map image.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub enum Skip {
    /// A kept frame already has this view.
    Covered,
    /// Blurred against the frames before it.
    Blurred,
    /// Mostly black or saturated.
    BadExposure,
    /// Too little valid depth.
    LittleDepth,
    /// No pose at its stamp (outside the trajectory or in a gap).
    NoPose,
    /// Its data could not be decoded.
    Unreadable,
    /// Its recorded pose disagrees with its own images ([`pntr_pipeline::pose_check`]).
    PoseDisagrees,
}

impl Skip {
    /// The name reports use.
    pub fn name(self) -> &'static str {
        match self {
            Skip::Covered => "covered",
            Skip::Blurred => "blurred",
            Skip::BadExposure => "bad_exposure",
            Skip::LittleDepth => "little_depth",
            Skip::NoPose => "no_pose",
            Skip::Unreadable => "unreadable",
            Skip::PoseDisagrees => "pose_disagrees",
        }
    }
}

/// Measures of a frame's quality.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FrameQuality {
    /// Variance of the Laplacian of the grey image (0..255 scale), on every second pixel.
    pub sharpness: f64,
    /// Mean grey, 0..255.
    pub mean_grey: f64,
    /// Share of pixels at most 8 or at least 247 in grey.
    pub clipped_share: f64,
    /// Share of pixels with valid depth.
    pub valid_depth: f64,
}

/// Measure `rgb` and `depth` (same size).
pub fn quality(rgb: &RgbImage, depth: &DepthMap) -> FrameQuality {
    let grey = rgb.to_gray();
    let (w, h) = (rgb.width as usize, rgb.height as usize);
    let mut sum = 0.0f64;
    let mut clipped = 0usize;
    for &g in &grey {
        let v = g as f64;
        sum += v;
        clipped += (!(8.0..247.0).contains(&v)) as usize;
    }
    let n = grey.len().max(1) as f64;
    let (mut s1, mut s2, mut m) = (0.0f64, 0.0f64, 0usize);
    for r in (1..h.saturating_sub(1)).step_by(2) {
        for c in (1..w.saturating_sub(1)).step_by(2) {
            let at = |rr: usize, cc: usize| grey[rr * w + cc] as f64;
            let l = at(r - 1, c) + at(r + 1, c) + at(r, c - 1) + at(r, c + 1) - 4.0 * at(r, c);
            s1 += l;
            s2 += l * l;
            m += 1;
        }
    }
    let m = m.max(1) as f64;
    FrameQuality {
        sharpness: (s2 / m - (s1 / m).powi(2)).max(0.0),
        mean_grey: sum / n,
        clipped_share: clipped as f64 / n,
        valid_depth: depth.valid_count() as f64 / depth.data.len().max(1) as f64,
    }
}

struct Kept {
    world_from_camera: Isometry3<f64>,
    camera: Intrinsics,
    /// A seeded map image's thumbnail: it covers a frame only where their appearance agrees.
    thumb: Option<Thumb>,
}

/// Keyframe selection over one or more recordings in one world frame.
pub struct Selector {
    params: KeyframeParams,
    kept: Vec<Kept>,
    /// Each place's id and the position of its first frame.
    places: Vec<(u32, Vector3<f64>)>,
    sharpness: VecDeque<f64>,
}

impl Selector {
    /// A selector with no kept frame yet.
    pub fn new(params: KeyframeParams) -> Self {
        Self {
            params,
            kept: Vec::new(),
            places: Vec::new(),
            sharpness: VecDeque::new(),
        }
    }

    /// Places so far.
    pub fn places(&self) -> usize {
        self.places.len()
    }

    /// Start from a map's images (`world_from_camera` in optical axes, camera, place), as when a map
    /// is extended: frames they already cover are left out, new frames near one of their places
    /// join it (a place's position is its first image's), and new places take ids after theirs.
    /// Each image's thumbnail makes it cover only frames of the same appearance
    /// ([`KeyframeParams::min_appearance`]).
    pub fn seed(
        &mut self,
        images: impl IntoIterator<Item = (Isometry3<f64>, Intrinsics, u32, Thumb)>,
    ) {
        for (world_from_camera, camera, place, thumb) in images {
            if !self.places.iter().any(|(p, _)| *p == place) {
                self.places
                    .push((place, world_from_camera.translation.vector));
            }
            self.kept.push(Kept {
                world_from_camera,
                camera,
                thumb: Some(thumb),
            });
        }
    }

    /// Start of a new recording: the sharpness history of the last one does not apply.
    pub fn new_session(&mut self) {
        self.sharpness.clear();
    }

    /// Judge frame `rgb`/`depth` taken by `camera` at `world_from_camera` (optical axes): `Ok(place)`
    /// when it is kept (and is then remembered as kept), else why not.
    pub fn judge(
        &mut self,
        rgb: &RgbImage,
        depth: &DepthMap,
        camera: &Intrinsics,
        world_from_camera: &Isometry3<f64>,
    ) -> Result<u32, Skip> {
        let q = quality(rgb, depth);
        if q.clipped_share > 0.6 || !(10.0..=245.0).contains(&q.mean_grey) {
            return Err(Skip::BadExposure);
        }
        if q.valid_depth < self.params.min_valid_depth {
            return Err(Skip::LittleDepth);
        }
        let median = {
            let mut v: Vec<f64> = self.sharpness.iter().copied().collect();
            v.sort_by(f64::total_cmp);
            v.get(v.len() / 2).copied()
        };
        self.sharpness.push_back(q.sharpness);
        if self.sharpness.len() > SHARPNESS_HISTORY {
            self.sharpness.pop_front();
        }
        if median
            .is_some_and(|m| self.sharpness.len() > 3 && q.sharpness < self.params.blur_ratio * m)
        {
            return Err(Skip::Blurred);
        }
        if self.covered(rgb, depth, camera, world_from_camera) {
            return Err(Skip::Covered);
        }
        self.kept.push(Kept {
            world_from_camera: *world_from_camera,
            camera: *camera,
            thumb: None,
        });
        let at = world_from_camera.translation.vector;
        let place = match self
            .places
            .iter()
            .find(|(_, p)| (p - at).norm() <= PLACE_RADIUS_M)
        {
            Some((id, _)) => *id,
            None => {
                let id = self.places.iter().map(|(id, _)| id + 1).max().unwrap_or(0);
                self.places.push((id, at));
                id
            }
        };
        Ok(place)
    }

    /// Whether a kept frame is near enough, turned little enough and sees enough of this frame.
    fn covered(
        &self,
        rgb: &RgbImage,
        depth: &DepthMap,
        camera: &Intrinsics,
        world_from_camera: &Isometry3<f64>,
    ) -> bool {
        let p = &self.params;
        let at = world_from_camera.translation.vector;
        let mut samples: Option<Vec<Point3<f64>>> = None;
        let mut thumb: Option<Thumb> = None;
        for k in &self.kept {
            // Ties (a drive of exact steps) count as near whatever the rounding of the poses'
            // source (a TF chain, a text file), so the same drive gives the same keyframes.
            if (k.world_from_camera.translation.vector - at).norm() > p.distance_m + TIE_M
                || k.world_from_camera
                    .rotation
                    .angle_to(&world_from_camera.rotation)
                    > p.angle_deg.to_radians() + TIE_RAD
            {
                continue;
            }
            let pts = samples.get_or_insert_with(|| sample_points(depth, camera));
            if pts.is_empty() {
                return true;
            }
            let k_from_frame = k.world_from_camera.inverse() * world_from_camera;
            let seen = pts
                .iter()
                .filter(|x| {
                    let y = k_from_frame * *x;
                    y.z > 0.05
                        && k.camera
                            .project(&y)
                            .is_some_and(|uv| k.camera.pixel_of(&uv).is_some())
                })
                .count();
            if (seen as f64) < p.min_overlap * pts.len() as f64 {
                continue;
            }
            let Some(theirs) = &k.thumb else {
                return true;
            };
            let ours = thumb.get_or_insert_with(|| Thumb::new(rgb, depth, camera));
            let corr = dense_check_both(ours, theirs, &k_from_frame).gray_correlation();
            tracing::trace!(corr, "appearance against a map image");
            if corr >= p.min_appearance {
                return true;
            }
        }
        false
    }
}

/// A grid of the frame's pixels with valid depth, back-projected (optical camera frame, metres).
fn sample_points(depth: &DepthMap, camera: &Intrinsics) -> Vec<Point3<f64>> {
    let (gw, gh) = OVERLAP_GRID;
    let mut out = Vec::with_capacity((gw * gh) as usize);
    for j in 0..gh {
        for i in 0..gw {
            let c = ((i as f64 + 0.5) * depth.width as f64 / gw as f64) as u32;
            let r = ((j as f64 + 0.5) * depth.height as f64 / gh as f64) as u32;
            if let Some(z) = depth.get(c, r).filter(|z| z.is_finite() && *z > 0.0) {
                out.push(camera.backproject(c as f64, r as f64, z as f64));
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion};

    fn frame(shade: impl Fn(u32, u32) -> u8) -> (RgbImage, DepthMap) {
        let (w, h) = (64u32, 48u32);
        let data = (0..w * h)
            .flat_map(|i| {
                let v = shade(i % w, i / w);
                [v, v, v]
            })
            .collect();
        (
            RgbImage {
                width: w,
                height: h,
                data,
            },
            DepthMap {
                width: w,
                height: h,
                data: vec![2.0; (w * h) as usize],
            },
        )
    }

    fn pose(x: f64, yaw_deg: f64) -> Isometry3<f64> {
        // Optical axes: a turn in place is about the camera's y (down) axis.
        Isometry3::from_parts(
            Translation3::new(x, 0.0, 0.0),
            UnitQuaternion::from_euler_angles(0.0, yaw_deg.to_radians(), 0.0),
        )
    }

    #[test]
    fn a_turn_in_place_keeps_a_frame_every_few_degrees_and_standing_still_keeps_one() {
        let k = Intrinsics::from_fov(64, 48, 90.0);
        let (rgb, depth) = frame(|c, r| ((c * 7 + r * 13) % 200) as u8 + 20);
        let mut s = Selector::new(KeyframeParams::default());
        // Standing still for 20 frames: one keyframe.
        let kept = (0..20)
            .filter(|_| s.judge(&rgb, &depth, &k, &pose(0.0, 0.0)).is_ok())
            .count();
        assert_eq!(kept, 1);
        // A full turn in place in 3-degree steps: a keyframe about every 15 degrees, all one place.
        let kept = (1..=120)
            .filter(|i| {
                s.judge(&rgb, &depth, &k, &pose(0.0, 3.0 * *i as f64))
                    .is_ok()
            })
            .count();
        // (The last steps come back to the first keyframe's view.)
        assert!((18..=26).contains(&kept), "{kept} keyframes in a full turn");
        assert_eq!(s.places(), 1);
        // Driving 3 m straight in 5 cm steps: one about every 0.3 m; places every metre or so.
        let kept = (1..=60)
            .filter(|i| {
                s.judge(&rgb, &depth, &k, &pose(0.05 * *i as f64, 0.0))
                    .is_ok()
            })
            .count();
        assert!((8..=12).contains(&kept), "{kept} keyframes over 3 m");
        assert!((3..=4).contains(&s.places()), "{} places", s.places());
    }

    #[test]
    fn a_map_being_extended_covers_frames_that_look_as_its_images_do() {
        let k = Intrinsics::from_fov(64, 48, 90.0);
        let shade = |c: u32, r: u32| ((c * 7 + r * 13) % 200) as u8 + 20;
        let (rgb, depth) = frame(shade);
        // The same view under other lighting: the shading reversed.
        let (relit, _) = frame(|c, r| 240 - shade(c, r));
        let map_image = Thumb::new(&rgb, &depth, &k);
        let mut s = Selector::new(KeyframeParams::default());
        s.seed([(pose(0.0, 0.0), k, 7, map_image)]);
        assert_eq!(s.places(), 1);
        assert_eq!(
            s.judge(&rgb, &depth, &k, &pose(0.0, 0.0)),
            Err(Skip::Covered),
            "the map has this view"
        );
        assert_eq!(
            s.judge(&relit, &depth, &k, &pose(0.0, 0.0)),
            Ok(7),
            "the map lacks this view under this lighting; it joins the map's place"
        );
        // A new place takes an id after the map's.
        assert_eq!(s.judge(&rgb, &depth, &k, &pose(5.0, 0.0)), Ok(8));
    }

    #[test]
    fn blurred_dark_and_depthless_frames_are_left_out() {
        let k = Intrinsics::from_fov(64, 48, 90.0);
        let (sharp, depth) = frame(|c, r| if (c / 2 + r / 2) % 2 == 0 { 40 } else { 200 });
        let (smooth, _) = frame(|c, _| (60 + c * 2) as u8);
        let (dark, _) = frame(|_, _| 2);
        let mut s = Selector::new(KeyframeParams::default());
        for i in 0..6 {
            // Each far from the last, so every sharp frame is kept.
            assert!(s.judge(&sharp, &depth, &k, &pose(i as f64, 0.0)).is_ok());
        }
        assert_eq!(
            s.judge(&smooth, &depth, &k, &pose(10.0, 0.0)),
            Err(Skip::Blurred)
        );
        assert_eq!(
            s.judge(&dark, &depth, &k, &pose(11.0, 0.0)),
            Err(Skip::BadExposure)
        );
        let empty = DepthMap {
            data: vec![0.0; depth.data.len()],
            ..depth.clone()
        };
        assert_eq!(
            s.judge(&sharp, &empty, &k, &pose(12.0, 0.0)),
            Err(Skip::LittleDepth)
        );
    }
}
