//! Dense refinement: a registered pose polished against the map view's whole depth, not only the
//! matched keypoints.
//!
//! Registration fixes the pose from the inlier keypoints. When they are few or bunched in one part of
//! the image (a textured picture on an otherwise plain wall), the rotation is held by a short lever and
//! comes out a few degrees off although the translation is within centimetres: most answers that are
//! right within (1 m, 10 deg) but not within (0.25 m, 2 deg) are of this kind. The depth, though, sees
//! every wall, floor and piece of furniture in view. Here the query's thumbnail depth ([`Thumb`]) is
//! aligned with the map view's by point-to-plane ICP with projective association (Chen and Medioni,
//! 1992; the KinectFusion tracker, Newcombe et al., 2011), jointly with the keypoint inliers'
//! point-to-point residuals, which keep the directions that the planes leave free (sliding along one
//! wall). Gauss-Newton with Huber weights, a handful of iterations on every other sample of the
//! thumbnail (32 x 32 for HPointLoc's camera; at most 128 x 128 for any declared camera).
//!
//! The refinement is refused (the registration is kept) when it would move the pose by more than
//! [`MAX_MOVE_M`] or [`MAX_MOVE_DEG`], or when fewer samples agree with the map view's depth after it
//! than before, by more than the count's own noise ([`AGREEMENT_NOISE_SIGMAS`] standard deviations;
//! refusing any loss refused most refinements of frames with a robot's depth noise, BENCHMARKS.md,
//! "Dense refinement within the agreement's noise").

use nalgebra::{Isometry3, Matrix6, Point3, Translation3, UnitQuaternion, Vector3, Vector6};

use pntr_core::{DepthMap, Intrinsics, RgbImage};

use crate::verify::{depth_tolerance_m, poses_agree, Thumb};

/// How many standard deviations of the agreeing samples' count a refinement may lose
/// ([`keeps_agreement`]).
pub const AGREEMENT_NOISE_SIGMAS: f64 = 2.0;
/// Focal length, in pixels, of the finer depth the refinement aligns where the camera's is at least
/// twice that ([`fine_depth`]).
pub const FINE_FOCAL_PX: f64 = 128.0;
/// Largest side of that finer depth, pixels (bounds its cost and the map's size).
pub const FINE_MAX_SIDE: u32 = 160;
/// Largest move of the final polish ([`polish_views`]), metres.
pub const MAX_POLISH_M: f64 = 0.1;
/// Largest rotation of the final polish, degrees.
pub const MAX_POLISH_DEG: f64 = 3.0;
/// Gauss-Newton iterations at most.
pub const ITERATIONS: usize = 10;
/// Largest move of the camera the refinement may make, metres.
pub const MAX_MOVE_M: f64 = 0.3;
/// Largest rotation the refinement may make, degrees.
pub const MAX_MOVE_DEG: f64 = 10.0;
/// Noise of a keypoint's 3D position (both images' depth and keypoint localisation), metres at 1 m;
/// it grows linearly with range, from a floor of [`KEYPOINT_MIN_RANGE_M`].
const KEYPOINT_SIGMA_PER_M: f64 = 0.02;
/// Range below which a keypoint's noise stops shrinking, metres.
const KEYPOINT_MIN_RANGE_M: f64 = 0.5;
/// Neighbouring thumbnail samples are independent only in part: each dense residual's sigma is
/// inflated by this factor. The depth still carries most of the weight (hundreds of samples against
/// a few dozen keypoints); the keypoints hold the directions the surfaces leave free.
const DENSE_CORRELATION: f64 = 1.5;
/// Of the query's samples, every this many is associated with a neighbouring view of
/// [`refine_views`] (all with the first view).
const NEIGHBOUR_STRIDE: usize = 4;
/// Fewest query samples with depth, and fewest associated with the map view's surfaces in an
/// iteration, for the alignment to be attempted.
const MIN_SAMPLES: usize = 32;
const MIN_ASSOCIATED: usize = 16;

/// A surface sample of a map view: its point and unit normal (OpenCV camera frame).
type Surface = (Point3<f64>, Vector3<f64>);

/// The point and normal of a map view's thumbnail at pixel (`c`, `r`); `None` where the depth is
/// invalid or the neighbourhood is not one surface.
fn point_and_normal(t: &Thumb, c: u32, r: u32) -> Option<Surface> {
    let k = &t.intrinsics;
    let at = |c: u32, r: u32| -> Option<Point3<f64>> {
        t.depth_m(c, r)
            .map(|z| k.backproject(c as f64, r as f64, z))
    };
    let p = at(c, r)?;
    let tol = depth_tolerance_m(p.z);
    let near = |q: Option<Point3<f64>>| q.filter(|q| (q.z - p.z).abs() <= tol);
    // Forward differences, backward at the last column / row.
    let h = if c + 1 < t.width {
        near(at(c + 1, r)).map(|q| q - p)
    } else {
        near(c.checked_sub(1).and_then(|c0| at(c0, r))).map(|q| p - q)
    }?;
    let v = if r + 1 < t.height {
        near(at(c, r + 1)).map(|q| q - p)
    } else {
        near(r.checked_sub(1).and_then(|r0| at(c, r0))).map(|q| p - q)
    }?;
    let mut n = h.cross(&v);
    let len = n.norm();
    if len <= 1e-12 {
        return None;
    }
    n /= len;
    if n.dot(&p.coords) > 0.0 {
        n = -n;
    }
    Some((p, n))
}

/// The surfaces of a map view's thumbnail, each pixel's computed the first time a query sample
/// lands on it ([`point_and_normal`]): a neighbouring view of the polish is hit on part of its
/// pixels only, and computing all of a 160 x 120 view's normals up front was most of the polish's
/// time.
struct Surfaces<'a> {
    thumb: &'a Thumb,
    /// Per pixel, row-major: `None` until computed.
    cache: Vec<Option<Option<Surface>>>,
}

impl<'a> Surfaces<'a> {
    fn new(thumb: &'a Thumb) -> Self {
        Self {
            thumb,
            cache: vec![None; (thumb.width * thumb.height) as usize],
        }
    }

    /// The surface at pixel (`u`, `v`); `None` outside the thumbnail's samples too (a thumbnail
    /// whose declared intrinsics size disagrees with its samples).
    fn at(&mut self, u: u32, v: u32) -> Option<Surface> {
        if u >= self.thumb.width {
            return None;
        }
        let slot = self.cache.get_mut((v * self.thumb.width + u) as usize)?;
        *slot.get_or_insert_with(|| point_and_normal(self.thumb, u, v))
    }
}

/// The finer depth a camera's frame is refined with, when the verification thumbnail
/// ([`Thumb::new`], focal length [`crate::verify::THUMB_FOCAL_PX`]) would throw most of its detail
/// away: for a camera of focal length at least twice [`FINE_FOCAL_PX`] (a VGA camera's 525-615 px,
/// a 720p camera's 900-1000 px), the frame reduced by the block that brings the focal length nearest
/// to [`FINE_FOCAL_PX`], at most [`FINE_MAX_SIDE`] a side (160 x 120 for a VGA frame: blocks of 4
/// pixels, where the thumbnail's are 16). `None` for smaller cameras (HPointLoc's f = 128 among
/// them), whose thumbnail is fine enough and is what the refinement aligns.
///
/// Why: a structured-light or stereo sensor's depth is good to a centimetre or two at a few metres,
/// and a 16-pixel block is 7 cm wide at 2.5 m with a 525 px lens; aligned at that scale, real frames
/// landed 3-5 cm from the truth (BENCHMARKS.md, "Real recordings").
pub fn fine_depth(rgb: &RgbImage, depth: &DepthMap, k: &Intrinsics) -> Option<Thumb> {
    // (A NaN focal length, which validation refuses earlier, has no finer depth either.)
    if k.fx.is_nan() || k.fy.is_nan() || k.fx.min(k.fy) < 2.0 * FINE_FOCAL_PX {
        return None;
    }
    let by_focal = (k.fx.min(k.fy) / FINE_FOCAL_PX).round();
    let side = rgb.width.max(rgb.height).max(1);
    let s = (by_focal.min(side as f64) as u32).max(side.div_ceil(FINE_MAX_SIDE));
    Some(Thumb::reduced(rgb, depth, k, s))
}

/// Huber weight of a normalised residual (threshold 1).
fn huber(r: f64) -> f64 {
    let a = r.abs();
    if a <= 1.0 {
        1.0
    } else {
        1.0 / a
    }
}

/// Samples of `query` that land on `db`'s surfaces within the depth tolerance under `db_from_query`.
fn agreeing(query: &Thumb, db: &Thumb, db_from_query: &Isometry3<f64>) -> usize {
    crate::verify::dense_check(query, db, db_from_query).agree
}

/// Refine `db_from_query` (query camera to map view camera, OpenCV axes, metres) with the query's
/// thumbnail `query`, the map view's `db`, and the registration's inlier pairs (`src` in the query's
/// camera frame, `dst` in the map view's, parallel slices). Returns the refined pose, or `None` when
/// the refinement is refused (see the module docs) or has nothing to work with.
pub fn refine_dense(
    query: &Thumb,
    db: &Thumb,
    db_from_query: &Isometry3<f64>,
    src: &[Vector3<f64>],
    dst: &[Vector3<f64>],
) -> Option<Isometry3<f64>> {
    refine_views(query, &[View::matched(db)], db_from_query, src, dst)
}

/// One map view of a joint refinement ([`refine_views`]): its depth, and its camera from the
/// reference view's camera (OpenCV axes, metres; the identity for the reference view itself).
#[derive(Clone, Copy)]
pub struct View<'a> {
    /// The view's depth (a thumbnail or its finer depth).
    pub thumb: &'a Thumb,
    /// `view_from_ref`: the reference camera's coordinates into this view's.
    pub from_ref: Isometry3<f64>,
}

impl<'a> View<'a> {
    /// The matched view itself: the reference frame of [`refine_views`].
    pub fn matched(thumb: &'a Thumb) -> Self {
        Self {
            thumb,
            from_ref: Isometry3::identity(),
        }
    }
}

/// [`refine_dense`] against several map views at once: every query sample is associated with each
/// view's surfaces (point-to-plane, projective association, the same depth gate), the residuals of
/// all views summed into one Gauss-Newton step on `ref_from_query` (the pose in the first view's
/// camera, `views[0]`, which the keypoint pairs' `dst` are in). A query seen from 0.5-1 m beyond
/// the map view it matched shares only part of its view with it, and that part (one cabinet front,
/// a floor) can leave a direction to the noisy keypoints; the neighbouring map views see the rest.
/// Refused, as [`refine_dense`], when it would move the pose more than [`MAX_MOVE_M`] /
/// [`MAX_MOVE_DEG`] or loses more agreeing samples, summed over the views, than the count's noise.
pub fn refine_views(
    query: &Thumb,
    views: &[View<'_>],
    ref_from_query: &Isometry3<f64>,
    src: &[Vector3<f64>],
    dst: &[Vector3<f64>],
) -> Option<Isometry3<f64>> {
    if src.len() < 3 {
        return None;
    }
    align(query, views, ref_from_query, src, dst, None)
}

/// What a tracked pose already says of itself: its covariance, a Gaussian prior for
/// [`polish_track`].
#[derive(Debug, Clone, Copy)]
pub struct Prior {
    /// Inverse of the pose's 6x6 covariance in the reference view's frame, ROS order: the query
    /// camera's position (metres), then its rotation about the reference camera's axes (radians).
    pub information: Matrix6<f64>,
}

impl Prior {
    /// The prior of a pose whose covariance `world_cov` is given in the map frame, ROS order
    /// (position, then rotation about the world axes; metres² and radians², as
    /// [`crate::pipeline::Localization::covariance`]), seen from the reference camera
    /// `world_from_ref` (both position and rotation blocks turn by `ref_from_world`'s rotation).
    /// `None` when the covariance is not invertible.
    pub fn from_world(world_cov: &[f64; 36], world_from_ref: &Isometry3<f64>) -> Option<Self> {
        let r = world_from_ref.rotation.inverse().to_rotation_matrix();
        let mut b = Matrix6::<f64>::zeros();
        b.fixed_view_mut::<3, 3>(0, 0).copy_from(r.matrix());
        b.fixed_view_mut::<3, 3>(3, 3).copy_from(r.matrix());
        let cov = b * Matrix6::from_row_slice(world_cov) * b.transpose();
        let information = ((cov + cov.transpose()) * 0.5).try_inverse()?;
        information
            .iter()
            .all(|v| v.is_finite())
            .then_some(Self { information })
    }
}

/// A tracked pose (`ref_from_query`, odometry chained from a map fix) polished against the map
/// views near it ([`View`]s, `views[0]` the reference): the dense point-to-plane alignment of
/// [`refine_views`] with the pose's own covariance as a Gaussian prior in place of keypoint pairs
/// (a maximum a posteriori step: where the map's surfaces hold a direction they move the pose, where
/// they leave one free, sliding along a cabinet front, the track keeps it). Odometry's error grows
/// with the path (centimetres after half a metre through a part of a kitchen the map's images never
/// matched from, though their depth sees it); aligned to the map's depth the track stays on the
/// map. Kept only within [`MAX_POLISH_M`] and [`MAX_POLISH_DEG`] of the track and when the
/// agreement, summed over the views, keeps its noise; `None` otherwise, or when too few samples
/// land on the views.
pub fn polish_track(
    query: &Thumb,
    views: &[View<'_>],
    ref_from_query: &Isometry3<f64>,
    prior: &Prior,
) -> Option<Isometry3<f64>> {
    let r = align(query, views, ref_from_query, &[], &[], Some(prior))?;
    poses_agree(&r, ref_from_query, MAX_POLISH_M, MAX_POLISH_DEG).then_some(r)
}

/// The alignment behind [`refine_views`] and [`polish_track`]: keypoint pairs, a prior centred on
/// `ref_from_query`, or both.
fn align(
    query: &Thumb,
    views: &[View<'_>],
    ref_from_query: &Isometry3<f64>,
    src: &[Vector3<f64>],
    dst: &[Vector3<f64>],
    prior: Option<&Prior>,
) -> Option<Isometry3<f64>> {
    let mut surfaces: Vec<Surfaces<'_>> = views.iter().map(|v| Surfaces::new(v.thumb)).collect();
    // Each view's rotation back into the reference frame, for its normals.
    let to_ref: Vec<_> = views
        .iter()
        .map(|v| v.from_ref.rotation.inverse())
        .collect();
    let kq = &query.intrinsics;
    // Every other sample in each direction: a quarter of the work, still hundreds of samples.
    let samples: Vec<Point3<f64>> = (0..query.height)
        .step_by(2)
        .flat_map(|r| (0..query.width).step_by(2).map(move |c| (c, r)))
        .filter_map(|(c, r)| {
            query
                .depth_m(c, r)
                .map(|z| kq.backproject(c as f64, r as f64, z))
        })
        .collect();
    debug_assert_eq!(src.len(), dst.len(), "src and dst are parallel");
    if samples.len() < MIN_SAMPLES || views.is_empty() {
        return None;
    }
    let mut est = *ref_from_query;
    for _ in 0..ITERATIONS {
        // The normal equations' upper triangle, row-major (the matrix is symmetric: each term
        // `j_a j_b w` equals `j_b j_a w` to the bit, so the lower triangle is a copy).
        let mut upper = [0.0f64; 21];
        let mut g = Vector6::<f64>::zeros();
        let mut used = 0usize;
        let mut add = |j: Vector6<f64>, r: f64, sigma: f64| {
            let rn = r / sigma;
            let w = huber(rn) / (sigma * sigma);
            // `h += j * j.transpose() * w` term by term: `(j_a * j_b) * w`, in that order.
            let mut k = 0;
            for a in 0..6 {
                for b in a..6 {
                    upper[k] += (j[a] * j[b]) * w;
                    k += 1;
                }
            }
            g += j * (r * w);
        };
        for (i, ((view, surfaces), to_ref)) in views
            .iter()
            .zip(surfaces.iter_mut())
            .zip(&to_ref)
            .enumerate()
        {
            let kd = &view.thumb.intrinsics;
            // Neighbouring views see each sample's surface a second time: every fourth sample of
            // theirs (a quarter of the cost) keeps the matched view's the larger share.
            let stride = if i == 0 { 1 } else { NEIGHBOUR_STRIDE };
            for x in samples.iter().step_by(stride) {
                let q = est * x;
                let qv = view.from_ref * q;
                let Some(uv) = kd.project(&qv) else { continue };
                let Some((u, v)) = kd.pixel_of(&uv) else {
                    continue;
                };
                // `pixel_of` bounds (u, v) by the intrinsics' size; `at` keeps a thumbnail whose
                // declared size disagrees with its samples from indexing out of range.
                let Some((d, n)) = surfaces.at(u, v) else {
                    continue;
                };
                let tol = depth_tolerance_m(qv.z);
                if (d.z - qv.z).abs() > tol {
                    continue;
                }
                used += 1;
                let r = n.dot(&(qv - d));
                // The residual's gradient in the reference frame, where the pose is perturbed.
                let n_ref = to_ref * n;
                let qn = q.coords.cross(&n_ref);
                let j = Vector6::new(qn.x, qn.y, qn.z, n_ref.x, n_ref.y, n_ref.z);
                add(j, r, tol / 2.0 * DENSE_CORRELATION);
            }
        }
        for (s, d) in src.iter().zip(dst) {
            let q = est * Point3::from(*s);
            let e = q.coords - d;
            let sigma = KEYPOINT_SIGMA_PER_M * q.z.max(KEYPOINT_MIN_RANGE_M);
            for (axis, r) in e.iter().enumerate() {
                let mut unit = Vector3::zeros();
                unit[axis] = 1.0;
                let qa = q.coords.cross(&unit);
                add(
                    Vector6::new(qa.x, qa.y, qa.z, unit.x, unit.y, unit.z),
                    *r,
                    sigma,
                );
            }
        }
        if used < MIN_ASSOCIATED {
            return None;
        }
        let mut h = Matrix6::<f64>::zeros();
        let mut k = 0;
        for a in 0..6 {
            for b in a..6 {
                h[(a, b)] = upper[k];
                h[(b, a)] = upper[k];
                k += 1;
            }
        }
        if let Some(prior) = prior {
            // Residual: the camera's position and rotation vector against the prior's (ROS
            // order); the step is (rotation, translation) applied on the left, so the position
            // moves by `rotation x position + translation`.
            let t = est.translation.vector;
            let dr = (est.rotation * ref_from_query.rotation.inverse()).scaled_axis();
            let r = Vector6::new(
                t.x - ref_from_query.translation.x,
                t.y - ref_from_query.translation.y,
                t.z - ref_from_query.translation.z,
                dr.x,
                dr.y,
                dr.z,
            );
            let mut j = Matrix6::<f64>::zeros();
            j.fixed_view_mut::<3, 3>(0, 0)
                .copy_from(&(-t.cross_matrix()));
            j.fixed_view_mut::<3, 3>(0, 3)
                .copy_from(&nalgebra::Matrix3::identity());
            j.fixed_view_mut::<3, 3>(3, 0)
                .copy_from(&nalgebra::Matrix3::identity());
            let jt_info = j.transpose() * prior.information;
            h += jt_info * j;
            g += jt_info * r;
        }
        let damping = 1e-9 * h.trace().max(1e-12);
        for i in 0..6 {
            h[(i, i)] += damping;
        }
        let step = h.cholesky()?.solve(&(-g));
        let rotation = UnitQuaternion::from_scaled_axis(Vector3::new(step[0], step[1], step[2]));
        let translation = Translation3::new(step[3], step[4], step[5]);
        est = Isometry3::from_parts(translation, rotation) * est;
        if step.norm() < 1e-5 {
            break;
        }
    }
    // The query camera's centre in the reference view's frame is the translation.
    if !poses_agree(&est, ref_from_query, MAX_MOVE_M, MAX_MOVE_DEG) {
        return None;
    }
    let agreeing_all = |p: &Isometry3<f64>| -> usize {
        views
            .iter()
            .map(|v| agreeing(query, v.thumb, &(v.from_ref * p)))
            .sum()
    };
    keeps_agreement(agreeing_all(&est), agreeing_all(ref_from_query)).then_some(est)
}

/// The final polish of a verified pose: [`refine_views`] on the finer depth ([`fine_depth`]) of the
/// query and of the map views (`views[0]` the matched one, whose frame `ref_from_query` and the
/// pairs' `dst` are in; [`View::matched`] alone for one view), kept only when it moves the camera by
/// at most [`MAX_POLISH_M`] and [`MAX_POLISH_DEG`] (a verified pose is right within a few
/// centimetres or wrong; the polish does not move it to another place). Same `None` cases as
/// [`refine_views`].
pub fn polish_views(
    query: &Thumb,
    views: &[View<'_>],
    ref_from_query: &Isometry3<f64>,
    src: &[Vector3<f64>],
    dst: &[Vector3<f64>],
) -> Option<Isometry3<f64>> {
    let r = refine_views(query, views, ref_from_query, src, dst)?;
    poses_agree(&r, ref_from_query, MAX_POLISH_M, MAX_POLISH_DEG).then_some(r)
}

/// Whether a refinement whose pose has `after` thumbnail samples agreeing with the map view's depth
/// keeps the `before` of the registration's pose: it may lose no more than
/// [`AGREEMENT_NOISE_SIGMAS`] standard deviations of the count (`sqrt(before)`, a count's Poisson
/// noise). A sensor's depth noise moves samples across the agreement tolerance at every pose, so
/// on a robot's frames a right refinement often loses a few; one that loses more than the noise
/// moved the pose away from the surfaces.
fn keeps_agreement(after: usize, before: usize) -> bool {
    after as f64 >= before as f64 - AGREEMENT_NOISE_SIGMAS * (before as f64).sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_scenes::{noisy_room_view, room_frame, room_view, CLUTTER};

    /// Twelve keypoint pairs in a 4 x 3 block of `query`'s thumbnail from `corner` (column, row):
    /// their points in the query camera and, under `truth`, in the map view's with 1 cm noise.
    fn bunched_pairs(
        query: &Thumb,
        truth: &Isometry3<f64>,
        corner: (u32, u32),
    ) -> (Vec<Vector3<f64>>, Vec<Vector3<f64>>) {
        let k = query.intrinsics;
        (0..12u32)
            .map(|i| {
                let (c, r) = (corner.0 + i % 4, corner.1 + i / 4);
                let z = query.depth_m(c, r).unwrap();
                let p = k.backproject(c as f64, r as f64, z).coords;
                let noise = Vector3::new(0.01, -0.01, 0.005) * ((i % 3) as f64 - 1.0);
                (p, (truth * Point3::from(p)).coords + noise)
            })
            .unzip()
    }

    /// Keypoint pairs at `pixels` of `query` that have depth: their points in the query camera and,
    /// under `truth`, in the map view's, with `noise` times -1, 0 or 1 in turn.
    fn pairs_at(
        query: &Thumb,
        truth: &Isometry3<f64>,
        pixels: impl Iterator<Item = (u32, u32)>,
        noise: Vector3<f64>,
    ) -> (Vec<Vector3<f64>>, Vec<Vector3<f64>>) {
        pixels
            .enumerate()
            .filter_map(|(i, (c, r))| {
                let z = query.depth_m(c, r)?;
                let p = query.intrinsics.backproject(c as f64, r as f64, z).coords;
                let n = noise * ((i % 3) as f64 - 1.0);
                Some((p, (truth * Point3::from(p)).coords + n))
            })
            .unzip()
    }

    /// Position (m) and rotation (deg) error of `p` against `truth`.
    fn pose_error(p: &Isometry3<f64>, truth: &Isometry3<f64>) -> (f64, f64) {
        (
            (p.translation.vector - truth.translation.vector).norm(),
            p.rotation.angle_to(&truth.rotation).to_degrees(),
        )
    }

    /// A Kinect-like VGA camera (f = 525 px).
    fn vga() -> Intrinsics {
        Intrinsics {
            fx: 525.0,
            fy: 525.0,
            cx: 319.5,
            cy: 239.5,
            width: 640,
            height: 480,
            distortion: [0.0; 5],
        }
    }

    #[test]
    fn a_rotation_held_by_bunched_keypoints_is_corrected_by_the_depth() {
        let db_pose = Isometry3::identity();
        let truth = Isometry3::from_parts(
            Translation3::new(0.3, 0.0, 0.4),
            UnitQuaternion::from_euler_angles(0.0, 0.25, 0.05),
        );
        let db = room_view(&db_pose);
        let query = room_view(&truth);
        // Twelve keypoints bunched in one corner of the query image, their 3D pairs with 1 cm noise.
        let (src, dst) = bunched_pairs(&query, &truth, (40, 10));
        // The registration's answer: the right place, turned by 3 degrees.
        let off = UnitQuaternion::from_euler_angles(0.02, 0.045, -0.01);
        let init = Isometry3::from_parts(truth.translation, off * truth.rotation);
        let before = init.rotation.angle_to(&truth.rotation).to_degrees();
        let refined = refine_dense(&query, &db, &init, &src, &dst).expect("refined");
        let after = refined.rotation.angle_to(&truth.rotation).to_degrees();
        let moved = (refined.translation.vector - truth.translation.vector).norm();
        assert!(before > 2.5, "{before}");
        assert!(after < 1.0, "rotation error {before:.2} -> {after:.2} deg");
        assert!(moved < 0.1, "{moved} m");
    }

    #[test]
    fn a_rotation_six_degrees_off_is_corrected_too() {
        // A robot's depth noise leaves some registrations from a dozen inliers 5-10 degrees off with
        // the position right; the refinement pulls them back (refusing moves over 5 degrees kept
        // them). Keypoint pairs with 1 cm noise, bunched in one part of the image.
        let truth = Isometry3::from_parts(
            Translation3::new(-0.1, 0.0, 0.3),
            UnitQuaternion::from_euler_angles(0.0, -0.15, 0.02),
        );
        let db = room_view(&Isometry3::identity());
        let query = room_view(&truth);
        let (src, dst) = bunched_pairs(&query, &truth, (20, 40));
        let axis = Vector3::new(0.3, 1.0, -0.2).normalize();
        let off = UnitQuaternion::from_scaled_axis(axis * 6f64.to_radians());
        let init = Isometry3::from_parts(truth.translation, off * truth.rotation);
        let refined = refine_dense(&query, &db, &init, &src, &dst).expect("refined");
        let after = refined.rotation.angle_to(&truth.rotation).to_degrees();
        let moved = (refined.translation.vector - truth.translation.vector).norm();
        assert!(after < 1.0, "rotation error 6 -> {after:.2} deg");
        assert!(moved < 0.1, "{moved} m");
    }

    #[test]
    fn a_noisy_sensors_refinement_is_kept_when_it_loses_only_the_counts_noise() {
        // A noisy depth sensor (sigma = 0.02 z^2 per pixel, before the thumbnail's block median)
        // and a registration a degree off, from keypoints spread over the view. The refined pose
        // agrees with the map view as well as the registration's, within the count's noise: on
        // some draws a few samples fewer (refusing any loss refused 2 of these 30).
        let truth: Isometry3<f64> = Isometry3::from_parts(
            Translation3::new(0.2, 0.05, 0.3),
            UnitQuaternion::from_euler_angles(0.02, -0.3, 0.01),
        );
        let axis = Vector3::new(-0.6, 0.7, 0.5).normalize();
        let off = UnitQuaternion::from_scaled_axis(axis * 1f64.to_radians());
        let init = Isometry3::from_parts(truth.translation, off * truth.rotation);
        let db = room_view(&Isometry3::identity());
        for seed in 1..=30 {
            let query = noisy_room_view(&truth, 0.02, seed);
            let k = query.intrinsics;
            let (mut src, mut dst) = (Vec::new(), Vec::new());
            for i in 0..20u32 {
                let (c, r) = (6 + 6 * (i % 10), 12 + 20 * (i / 10));
                let Some(z) = query.depth_m(c, r) else {
                    continue;
                };
                let p = k.backproject(c as f64, r as f64, z).coords;
                src.push(p);
                dst.push((truth * Point3::from(p)).coords);
            }
            let refined = refine_dense(&query, &db, &init, &src, &dst)
                .unwrap_or_else(|| panic!("seed {seed}: refinement refused"));
            let after = refined.rotation.angle_to(&truth.rotation).to_degrees();
            assert!(after < 0.75, "seed {seed}: 1 -> {after:.2} deg");
        }
        // The rule itself: a loss within two standard deviations of the count is kept, more is not.
        assert!(keeps_agreement(940, 1000) && keeps_agreement(1000, 1000));
        assert!(!keeps_agreement(930, 1000));
    }

    #[test]
    fn a_vga_frame_is_polished_on_its_finer_depth_and_only_near_its_pose() {
        // A Kinect-like camera (640 x 480, f = 525, depth noise 0.0015 z^2 per pixel) in a room
        // with boxes about: the thumbnail keeps blocks of 16 pixels, the finer depth blocks of 4.
        let k = vga();
        assert!(fine_depth(
            &RgbImage::new(256, 256, vec![0; 256 * 256 * 3]).unwrap(),
            &DepthMap::from_metres(256, 256, vec![1.0; 256 * 256]).unwrap(),
            &Intrinsics::hpointloc()
        )
        .is_none());
        let truth = Isometry3::from_parts(
            Translation3::new(0.25, 0.05, 0.2),
            UnitQuaternion::from_euler_angles(0.03, -0.35, 0.01),
        );
        let (rgb, depth) = room_frame(&Isometry3::identity(), &k, 0.0015, 1, &CLUTTER);
        let db_coarse = Thumb::new(&rgb, &depth, &k);
        let db_fine = fine_depth(&rgb, &depth, &k).expect("a VGA camera has a finer depth");
        assert_eq!((db_fine.width, db_fine.height), (160, 120));
        assert_eq!((db_coarse.width, db_coarse.height), (40, 30));
        let (rgb, depth) = room_frame(&truth, &k, 0.0015, 2, &CLUTTER);
        let q_coarse = Thumb::new(&rgb, &depth, &k);
        let q_fine = fine_depth(&rgb, &depth, &k).unwrap();
        // Keypoint pairs spread over the view, with 2 cm noise in the map view's frame.
        let (src, dst) = pairs_at(
            &q_fine,
            &truth,
            (0..24u32).map(|i| (20 + 25 * (i % 6), 15 + 25 * (i / 6))),
            Vector3::new(0.02, -0.02, 0.01),
        );
        let error = |p: &Isometry3<f64>| pose_error(p, &truth);
        // A verified pose 4 cm and 0.8 degrees off.
        let axis = Vector3::new(0.2, 1.0, 0.3).normalize();
        let init = Isometry3::from_parts(
            Translation3::from(truth.translation.vector + Vector3::new(0.03, -0.02, 0.018)),
            UnitQuaternion::from_scaled_axis(axis * 0.8f64.to_radians()) * truth.rotation,
        );
        let coarse = refine_dense(&q_coarse, &db_coarse, &init, &src, &dst).unwrap_or(init);
        let polished = polish_views(&q_fine, &[View::matched(&db_fine)], &coarse, &src, &dst)
            .expect("polished");
        let (coarse_m, coarse_deg) = error(&coarse);
        let (fine_m, fine_deg) = error(&polished);
        assert!(
            fine_m < 0.01 && fine_deg < 0.3,
            "polished {fine_m:.4} m {fine_deg:.3} deg (thumbnails: {coarse_m:.4} m {coarse_deg:.3} deg)"
        );
        // Measured: 3.2 mm and 0.10 deg polished, 4.0 mm and 0.30 deg on the thumbnails.
        assert!(
            fine_m < coarse_m && fine_deg < coarse_deg / 2.0,
            "polished {fine_m} m {fine_deg} deg, thumbnails {coarse_m} m {coarse_deg} deg"
        );
        // A pose 0.25 m off is not the polish's to move: refused, though the room's planes would
        // pull it back.
        let far = Isometry3::from_parts(
            Translation3::from(truth.translation.vector + Vector3::new(0.2, 0.0, 0.15)),
            truth.rotation,
        );
        assert!(polish_views(&q_fine, &[View::matched(&db_fine)], &far, &src, &dst).is_none());
    }

    #[test]
    fn a_query_far_from_its_map_view_is_polished_better_with_the_neighbouring_views() {
        // A VGA camera (Kinect-like depth noise) in the cluttered room: the matched map view 0.8 m
        // and 60 degrees from the query sees part of what it sees; a neighbouring map view near
        // the query sees the rest. Keypoint pairs only in one corner, with 2 cm noise.
        let k = vga();
        let world_from_db = Isometry3::from_parts(
            Translation3::new(0.0, 0.0, 0.0),
            UnitQuaternion::from_euler_angles(0.0, -0.6, 0.0),
        );
        let world_from_near = Isometry3::from_parts(
            Translation3::new(0.7, 0.05, 0.3),
            UnitQuaternion::from_euler_angles(0.0, 0.35, 0.0),
        );
        let world_from_query = Isometry3::from_parts(
            Translation3::new(0.75, 0.0, 0.25),
            UnitQuaternion::from_euler_angles(0.02, 0.44, 0.01),
        );
        let fine_of = |pose: &Isometry3<f64>, seed: u64| {
            let (rgb, depth) = room_frame(pose, &k, 0.0015, seed, &CLUTTER);
            fine_depth(&rgb, &depth, &k).unwrap()
        };
        let (db, near, query) = (
            fine_of(&world_from_db, 1),
            fine_of(&world_from_near, 2),
            fine_of(&world_from_query, 3),
        );
        let truth = world_from_db.inverse() * world_from_query;
        let (src, dst) = pairs_at(
            &query,
            &truth,
            (0..12u32).map(|i| (10 + 4 * (i % 4), 10 + 4 * (i / 4))),
            Vector3::new(0.02, -0.015, 0.02),
        );
        assert!(src.len() >= 6, "the corner has depth");
        let init = Isometry3::from_parts(
            Translation3::from(truth.translation.vector + Vector3::new(0.03, -0.02, 0.02)),
            UnitQuaternion::from_scaled_axis(Vector3::new(0.2, 1.0, 0.3).normalize() * 0.015)
                * truth.rotation,
        );
        let error = |p: &Isometry3<f64>| pose_error(p, &truth);
        let alone = [View::matched(&db)];
        let both = [
            alone[0],
            View {
                thumb: &near,
                from_ref: world_from_near.inverse() * world_from_db,
            },
        ];
        let one = polish_views(&query, &alone, &init, &src, &dst).unwrap_or(init);
        let two = polish_views(&query, &both, &init, &src, &dst).expect("polished");
        let ((one_m, one_deg), (two_m, two_deg)) = (error(&one), error(&two));
        assert!(
            two_m < 0.01 && two_deg < 0.3,
            "two views: {two_m:.4} m {two_deg:.3} deg (one: {one_m:.4} m {one_deg:.3} deg)"
        );
        // Measured: 3.9 mm and 0.04 deg with both views; the matched view alone leaves the pose
        // 4.1 cm and 0.86 deg off (its polish refused or short).
        assert!(
            two_m < one_m / 2.0 && two_deg < one_deg / 2.0,
            "two views: {two_m:.4} m {two_deg:.3} deg, one: {one_m:.4} m {one_deg:.3} deg"
        );
        // The neighbour's surfaces alone (the matched view without depth) bring the pose there:
        // its residuals reach the matched view's frame through `from_ref`.
        let blank = Thumb {
            depth_mm: vec![0; db.depth_mm.len()],
            ..db.clone()
        };
        let via_near = [View::matched(&blank), both[1]];
        let moved = refine_views(&query, &via_near, &init, &src, &dst).expect("refined");
        let (near_m, near_deg) = error(&moved);
        assert!(
            near_m < 0.01 && near_deg < 0.3,
            "by the neighbour alone: {near_m:.4} m {near_deg:.3} deg"
        );
        // A neighbour placed 20 cm from where it was taken (a map whose poses disagree) cannot
        // pull the pose off: the polish is refused or stays within its bounds (measured: 8.7 cm
        // from the truth, the start 4.1 cm; a map's own poses agree to a centimetre or two).
        let wrong = [
            alone[0],
            View {
                thumb: &near,
                from_ref: Isometry3::translation(0.2, 0.0, 0.0)
                    * world_from_near.inverse()
                    * world_from_db,
            },
        ];
        let pulled = polish_views(&query, &wrong, &init, &src, &dst).unwrap_or(init);
        let (pulled_m, _) = error(&pulled);
        assert!(pulled_m < 0.1, "pulled {pulled_m:.3} m off");
    }

    /// A covariance with `pos_m` and `rot_deg` standard deviations on each axis, ROS order.
    fn diagonal_covariance(pos_m: f64, rot_deg: f64) -> [f64; 36] {
        let mut c = [0.0; 36];
        for i in 0..3 {
            c[i * 7] = pos_m * pos_m;
            c[(i + 3) * 7] = rot_deg.to_radians().powi(2);
        }
        c
    }

    #[test]
    fn a_tracked_pose_is_held_to_the_maps_depth_where_it_constrains_it() {
        // A VGA camera in the cluttered room, tracked 4 cm and 0.8 deg off (odometry's drift),
        // its covariance saying 4 cm and 1 deg; the map view 0.5 m away sees the same surfaces.
        // The frame's depth has a robot camera's noise (`synth --realism robot`: 0.003 z^2 a
        // pixel), the map view's none. No keypoint pairs: the prior and the depth alone.
        let k = vga();
        let world_from_db = Isometry3::from_parts(
            Translation3::new(0.3, -0.1, 0.4),
            UnitQuaternion::from_euler_angles(0.1, -0.3, 0.05),
        );
        let world_from_query = Isometry3::from_parts(
            Translation3::new(0.6, 0.0, 0.8),
            UnitQuaternion::from_euler_angles(0.02, 0.1, 0.01),
        );
        let fine_of = |pose: &Isometry3<f64>, noise: f64, seed: u64| {
            let (rgb, depth) = room_frame(pose, &k, noise, seed, &CLUTTER);
            fine_depth(&rgb, &depth, &k).unwrap()
        };
        let db = fine_of(&world_from_db, 0.0, 1);
        let query = fine_of(&world_from_query, 0.0015, 2);
        let tracked = Isometry3::from_parts(
            Translation3::from(
                world_from_query.translation.vector + Vector3::new(0.03, -0.02, 0.018),
            ),
            UnitQuaternion::from_scaled_axis(Vector3::new(0.2, 1.0, 0.3).normalize() * 0.014)
                * world_from_query.rotation,
        );
        let prior = Prior::from_world(&diagonal_covariance(0.04, 1.0), &world_from_db).unwrap();
        let ref_from = |p: &Isometry3<f64>| world_from_db.inverse() * p;
        // The track at `start` (world frame) after the polish against `view`, or as it was.
        let polished_from = |view: &Thumb, start: &Isometry3<f64>, prior: &Prior| {
            polish_track(&query, &[View::matched(view)], &ref_from(start), prior)
                .map_or(*start, |p| world_from_db * p)
        };
        // From the truth itself the polish stays.
        let stays = polished_from(&db, &world_from_query, &prior);
        let (stays_m, _) = pose_error(&stays, &world_from_query);
        assert!(stays_m < 0.006, "from the truth: moved {stays_m:.4} m");
        let polished = polish_track(&query, &[View::matched(&db)], &ref_from(&tracked), &prior)
            .expect("polished");
        let (m, deg) = pose_error(&(world_from_db * polished), &world_from_query);
        let (m0, deg0) = pose_error(&tracked, &world_from_query);
        // Measured: 2.7 cm and 0.20 deg from 4.0 cm and 0.80 deg (one polish a frame; on the
        // noiseless frame it reaches 2 mm).
        assert!(
            m < 0.75 * m0 && deg < 0.3,
            "polished {m:.4} m {deg:.3} deg, tracked {m0:.4} m {deg0:.3} deg"
        );
        // A map view with a sensor's independent per-pixel noise as well (its normals then share
        // each pixel's noise, which biases a prior-only alignment): the track is not pulled away
        // from the truth (measured: the polish is refused).
        let noisy_db = fine_of(&world_from_db, 0.0015, 3);
        let kept = polished_from(&noisy_db, &world_from_query, &prior);
        let (kept_m, _) = pose_error(&kept, &world_from_query);
        assert!(
            kept_m < 0.01,
            "a noisy map view pulled the track {kept_m:.4} m"
        );
        // A track certain to a millimetre is not moved by the map: the prior outweighs the depth.
        let firm = Prior::from_world(&diagonal_covariance(0.0005, 0.01), &world_from_db).unwrap();
        let (moved_m, _) = pose_error(&polished_from(&db, &tracked, &firm), &tracked);
        assert!(moved_m < 0.005, "a firm track moved {moved_m:.4} m");
        // A track 0.25 m off is not the polish's to move.
        let far = Isometry3::from_parts(
            Translation3::from(world_from_query.translation.vector + Vector3::new(0.2, 0.0, 0.15)),
            world_from_query.rotation,
        );
        let wide = Prior::from_world(&diagonal_covariance(0.3, 5.0), &world_from_db).unwrap();
        assert!(polish_track(&query, &[View::matched(&db)], &ref_from(&far), &wide).is_none());
    }

    #[test]
    fn a_tracked_pose_keeps_what_a_flat_wall_leaves_free() {
        // The camera 1.5 m from the bare back wall, looking at it: the depth holds the distance to
        // the wall and the tilt, not a slide along it. The track is 3 cm off along the wall and
        // 3 cm off toward it: the polish removes the second and leaves the first to the track.
        let k = vga();
        let world_from_query = Isometry3::translation(0.1, -0.2, 2.5);
        let world_from_db = Isometry3::translation(-0.2, -0.1, 2.2);
        let frame = |pose: &Isometry3<f64>, noise: f64, seed: u64| {
            let (rgb, depth) = room_frame(pose, &k, noise, seed, &[]);
            fine_depth(&rgb, &depth, &k).unwrap()
        };
        let (db, query) = (
            frame(&world_from_db, 0.0, 3),
            frame(&world_from_query, 0.003, 4),
        );
        let tracked = Isometry3::translation(0.13, -0.2, 2.53);
        let prior = Prior::from_world(&diagonal_covariance(0.04, 1.0), &world_from_db).unwrap();
        let polished = polish_track(
            &query,
            &[View::matched(&db)],
            &(world_from_db.inverse() * tracked),
            &prior,
        )
        .map(|p| world_from_db * p)
        .expect("polished");
        let t = polished.translation.vector - world_from_query.translation.vector;
        assert!(t.z.abs() < 0.008, "toward the wall: {:.4} m left", t.z);
        assert!(
            (t.x - 0.03).abs() < 0.008,
            "along the wall: {:.4} m (the track's 0.03)",
            t.x
        );
        assert!(t.y.abs() < 0.008, "{:.4} m", t.y);
    }

    #[test]
    fn a_prior_turns_with_the_reference_camera() {
        // 1 cm along the world's x and 5 cm along its z, seen from a camera turned 90 degrees about
        // y: the reference camera's z is the world's x (and its x the world's -z).
        let mut world = [0.0; 36];
        world[0] = 1e-4;
        world[14] = 25e-4;
        for i in 3..6 {
            world[i * 7] = 1e-6;
        }
        world[7] = 4e-4;
        let world_from_ref = Isometry3::from_parts(
            Translation3::new(1.0, 2.0, 3.0),
            UnitQuaternion::from_euler_angles(0.0, std::f64::consts::FRAC_PI_2, 0.0),
        );
        let prior = Prior::from_world(&world, &world_from_ref).unwrap();
        let cov = prior.information.try_inverse().unwrap();
        assert!((cov[(2, 2)] - 1e-4).abs() < 1e-9, "{cov}");
        assert!((cov[(0, 0)] - 25e-4).abs() < 1e-9, "{cov}");
        assert!((cov[(1, 1)] - 4e-4).abs() < 1e-9, "{cov}");
        assert!(Prior::from_world(&[0.0; 36], &world_from_ref).is_none());
    }

    #[test]
    fn the_right_pose_stays_and_a_query_without_depth_is_refused() {
        let db = room_view(&Isometry3::identity());
        let truth = Isometry3::from_parts(
            Translation3::new(-0.2, 0.1, 0.5),
            UnitQuaternion::from_euler_angles(0.03, -0.2, 0.0),
        );
        let query = room_view(&truth);
        let k = query.intrinsics;
        let (mut src, mut dst) = (Vec::new(), Vec::new());
        for i in 0..16u32 {
            let (c, r) = (8 + 3 * i, 30 + (i % 5));
            let z = query.depth_m(c, r).unwrap();
            let p = k.backproject(c as f64, r as f64, z).coords;
            src.push(p);
            dst.push((truth * Point3::from(p)).coords);
        }
        // The exact pose stays: refined, it moves by less than the thumbnails' resolution (or the
        // refinement is refused and the caller keeps it).
        let kept = refine_dense(&query, &db, &truth, &src, &dst).unwrap_or(truth);
        let moved_m = (kept.translation.vector - truth.translation.vector).norm();
        let moved_deg = kept.rotation.angle_to(&truth.rotation).to_degrees();
        assert!(
            moved_m < 0.01 && moved_deg < 0.1,
            "{moved_m} m, {moved_deg} deg"
        );
        // Without any valid depth there is nothing to refine with.
        let empty = Thumb {
            depth_mm: vec![0; query.depth_mm.len()],
            ..query.clone()
        };
        assert!(refine_dense(&empty, &db, &truth, &src, &dst).is_none());
    }
}
