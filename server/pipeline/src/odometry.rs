//! Frame-to-frame tracking for streams: the next frame registered against the stream's keyframe.
//!
//! A robot's frames at 10-30 Hz overlap by most of their view, far more than any frame overlaps a map
//! image taken from a Point a metre away and looking elsewhere. So while a stream is tracked, the
//! server keeps its last LOCALIZED frame (keypoints, descriptors, their 3D points, a thumbnail and the
//! pose) as a [`Keyframe`], and a new frame is first matched and registered against it:
//! `world_from_query = world_from_keyframe * keyframe_from_query`. This is RGB-D odometry chained to
//! the map, the tracking thread of keyframe SLAM systems (ORB-SLAM's reference keyframe) without the
//! map building:
//!
//! - A keyframe is born only from an answer verified against the map ([`Keyframe::anchored`]), and
//!   an odometry answer keeps the keyframe (no chaining frame to frame, so error is not added at
//!   every frame) until the overlap falls below [`REFRESH_OVERLAP`] or the inliers below
//!   [`REFRESH_INLIERS`]; then the frame itself becomes the next keyframe, one hop further from its
//!   map fix ([`Keyframe::hops`]). The keyframe also remembers the last frame tracked from it
//!   ([`Keyframe::latest`]): when a frame no longer registers with the keyframe (a turn or a doorway
//!   between two frames), it is registered against that one, which becomes the keyframe.
//! - The chain answers for at most [`MAX_PATH_M`] from its map fix (drift grows with the
//!   distance); where the map does not reach, it goes on beyond, not answered, so the stream keeps
//!   the camera's motion, with an uncertainty that grows with it ([`with_drift`]).
//! - An odometry pose is LOCALIZED only when the registration holds ([`MIN_INLIERS`],
//!   [`MIN_INLIER_RATIO`]), the dense depth and grey levels of the two frames agree
//!   ([`MIN_DEPTH_AGREE`], [`MIN_GRAY_CORRELATION`], at most [`MAX_FREE_SPACE_VIOLATION`] seen
//!   through) and the pose lies in the tracking region (a camera cannot jump). The stream (the
//!   service) stops using the keyframe when its map fix is too old, and asks for the map to be tried
//!   first again after a short while, so the chain is re-anchored; a map answer that disagrees with
//!   an accepted hop is taken for a look-alike (the pipeline's `settle`).
//! - Confidence and covariance come from the map fix: the fix's calibrated confidence, and its
//!   covariance plus the covariance of each hop's registration, rotated into the map frame (the
//!   first-order sum, ignoring the lever arm of rotation uncertainty).

use std::sync::Arc;

use nalgebra::{Isometry3, Matrix6, Translation3, UnitQuaternion, Vector3, Vector6};
use pntr_features::{Features, Matcher};
use pntr_registration::covariance::{point_to_point_covariance, rotate_covariance};
use pntr_registration::ransac::{ransac_rigid, RansacParams};
use pntr_registration::Rigid;

use crate::verify::{dense_evidence, Evidence, Thumb};

/// Fewest registration inliers for an odometry pose.
pub const MIN_INLIERS: usize = 30;
/// Smallest share of the matched pairs with depth that are inliers.
pub const MIN_INLIER_RATIO: f64 = 0.3;
/// Smallest dense depth agreement between the frame and its keyframe (0..1; right hops on our
/// synthetic drives: 0.94 and above).
pub const MIN_DEPTH_AGREE: f64 = 0.8;
/// Smallest grey-level correlation on the agreeing samples (-1..1; right hops: 0.91 and above). Depth
/// alone cannot see a camera sliding along a flat wall; the wall's texture can.
pub const MIN_GRAY_CORRELATION: f64 = 0.7;
/// Largest share of the frame's samples that see through the keyframe's surfaces.
pub const MAX_FREE_SPACE_VIOLATION: f64 = 0.1;
/// The frame becomes the next keyframe when it sees less of the keyframe than this share...
pub const REFRESH_OVERLAP: f64 = 0.7;
/// ... or registers with fewer inliers than this.
pub const REFRESH_INLIERS: usize = 80;
/// Longest chain of hops from a map fix, metres driven (the sum of the keyframes' steps and the
/// last hop). Odometry drifts with the distance travelled (RGB-D odometry: about 1-2% of it), so 10 m
/// keeps the drift under the 0.25 m of a right pose; a longer stretch without a map fix is answered
/// NOT_LOCALIZED until the map answers again.
pub const MAX_PATH_M: f64 = 10.0;
/// Floor of the point noise in a hop's covariance, metres.
const MIN_SIGMA_M: f64 = 0.01;

/// What a stream tracks from: one earlier frame with its verified pose.
#[derive(Clone)]
pub struct Keyframe {
    /// Keypoints and descriptors of the frame (at the map's pixel scale).
    pub features: Features,
    /// 3D point of each keypoint in the frame's OpenCV camera frame, metres (`None`: no depth).
    pub points: Vec<Option<Vector3<f64>>>,
    /// Thumbnail for the dense check.
    pub thumb: Thumb,
    /// `world_from_camera` of the frame, map frame, OpenCV camera axes.
    pub world_from_camera: Isometry3<f64>,
    /// 6x6 covariance of that pose, map frame, ROS order (metres², radians²).
    pub covariance: Option<[f64; 36]>,
    /// Calibrated confidence of the map fix the chain starts from.
    pub confidence: f64,
    /// Map index of the database image of that fix.
    pub image: Option<usize>,
    /// Keyframes between this one and its map fix (0: the fix itself).
    pub hops: u32,
    /// Distance along the chain from the map fix to this keyframe, metres.
    pub path_m: f64,
    /// The last frame tracked from this keyframe, as a keyframe one hop further: what the next
    /// frame is registered against when it no longer registers with this one (the camera has
    /// turned or passed a doorway between two frames, before the overlap fell below
    /// [`REFRESH_OVERLAP`]).
    pub latest: Option<Arc<Keyframe>>,
}

impl std::fmt::Debug for Keyframe {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "Keyframe({} keypoints, hops {}, at {:?})",
            self.features.keypoints.len(),
            self.hops,
            self.world_from_camera.translation.vector.as_slice()
        )
    }
}

impl Keyframe {
    /// A keyframe from a frame verified against the map.
    pub fn anchored(
        features: &Features,
        points: &[Option<Vector3<f64>>],
        thumb: Thumb,
        world_from_camera: Isometry3<f64>,
        covariance: Option<[f64; 36]>,
        confidence: f64,
        image: Option<usize>,
    ) -> Self {
        Self {
            features: features.clone(),
            points: points.to_vec(),
            thumb,
            world_from_camera,
            covariance,
            confidence,
            image,
            hops: 0,
            path_m: 0.0,
            latest: None,
        }
    }
}

/// An odometry registration of a frame against a keyframe.
#[derive(Debug, Clone)]
pub struct Hop {
    /// `world_from_camera` of the frame, map frame, OpenCV axes.
    pub world_from_query: Isometry3<f64>,
    /// Registration inliers.
    pub inliers: usize,
    /// Matched pairs with depth on both sides.
    pub pairs: usize,
    /// The dense check against the keyframe.
    pub evidence: Evidence,
    /// Covariance of the pose (the keyframe's plus this hop's), map frame, ROS order.
    pub covariance: Option<[f64; 36]>,
    /// Distance along the chain from the map fix to the frame, metres.
    pub path_m: f64,
    /// Why the hop is refused, `None` when it holds.
    pub refused: Option<String>,
}

impl Hop {
    /// True when the frame should replace its keyframe (it sees too little of it).
    pub fn refreshes(&self) -> bool {
        self.evidence.overlap < REFRESH_OVERLAP || self.inliers < REFRESH_INLIERS
    }

    /// Why the chain is too long to answer from ([`MAX_PATH_M`], drift), `None` when it is not.
    /// Such a hop still measures the camera's motion: where the map does not reach, a stream
    /// follows it (not LOCALIZED) to judge map fixes by.
    pub fn worn(&self) -> Option<String> {
        (self.path_m > MAX_PATH_M).then(|| {
            format!(
                "{:.1} m driven since the last map fix, more than {MAX_PATH_M} m (drift)",
                self.path_m
            )
        })
    }
}

/// Match the frame (`features`, back-projected `points`, `thumb`) against `key` with `matcher`,
/// register the 3D pairs (adaptive RANSAC, [`pntr_registration::ransac`]: consecutive frames share
/// most of their keypoints, the case where it needs only a few samples) and check the dense depth of
/// both frames. `None` when the registration fails outright; otherwise the hop, refused or not.
///
/// # Errors
/// The matcher's errors.
pub fn register(
    key: &Keyframe,
    features: &Features,
    points: &[Option<Vector3<f64>>],
    thumb: &Thumb,
    matcher: &dyn Matcher,
    noise_bound_m: f64,
) -> Result<Option<Hop>, pntr_features::FeatureError> {
    let m = matcher.match_features(features, &key.features)?;
    let (mut src, mut dst) = (Vec::new(), Vec::new());
    for &(a, b) in &m.pairs {
        let (Some(Some(s)), Some(Some(d))) = (points.get(a as usize), key.points.get(b as usize))
        else {
            continue;
        };
        src.push(*s);
        dst.push(*d);
    }
    let r = ransac_rigid(
        &src,
        &dst,
        &RansacParams {
            noise_bound: noise_bound_m,
            min_inliers: MIN_INLIERS,
            ..RansacParams::default()
        },
    );
    if !r.valid {
        return Ok(None);
    }
    let key_from_query = Rigid::to_isometry(&r.transform);
    let evidence = dense_evidence(thumb, &key.thumb, &key_from_query, &[]);
    let inliers = r.inliers.len();
    let ratio = inliers as f64 / src.len().max(1) as f64;
    let path_m = key.path_m + key_from_query.translation.vector.norm();
    let refused = if inliers < MIN_INLIERS {
        Some(format!("{inliers} inliers, fewer than {MIN_INLIERS}"))
    } else if ratio < MIN_INLIER_RATIO {
        Some(format!("inlier ratio {ratio:.2} below {MIN_INLIER_RATIO}"))
    } else if evidence.depth_agree < MIN_DEPTH_AGREE {
        Some(format!(
            "depth agreement {:.2} below {MIN_DEPTH_AGREE}",
            evidence.depth_agree
        ))
    } else if evidence.gray_correlation < MIN_GRAY_CORRELATION {
        Some(format!(
            "grey correlation {:.2} below {MIN_GRAY_CORRELATION}",
            evidence.gray_correlation
        ))
    } else if evidence.free_space_violation > MAX_FREE_SPACE_VIOLATION {
        Some(format!(
            "free-space violation {:.2} above {MAX_FREE_SPACE_VIOLATION}",
            evidence.free_space_violation
        ))
    } else {
        None
    };
    let inlier_src: Vec<_> = r.inliers.iter().map(|&i| src[i]).collect();
    let inlier_dst: Vec<_> = r.inliers.iter().map(|&i| dst[i]).collect();
    let covariance = key.covariance.and_then(|base| {
        let local = point_to_point_covariance(&inlier_src, &inlier_dst, &r.transform, MIN_SIGMA_M)?;
        let world = rotate_covariance(&local, &key.world_from_camera.rotation.to_rotation_matrix());
        let mut out = base;
        for (i, v) in out.iter_mut().enumerate() {
            *v += world[(i / 6, i % 6)];
        }
        Some(out)
    });
    Ok(Some(Hop {
        world_from_query: key.world_from_camera * key_from_query,
        inliers,
        pairs: src.len(),
        evidence,
        covariance,
        path_m,
        refused,
    }))
}

/// The keyframe after an accepted `hop` from `key` of the frame (`features`, `points`, `thumb`): the
/// frame itself one hop further when it [`Hop::refreshes`]; otherwise `key` again, remembering the
/// frame as its [`Keyframe::latest`].
pub fn next_keyframe(
    key: &Arc<Keyframe>,
    hop: &Hop,
    features: &Features,
    points: &[Option<Vector3<f64>>],
    thumb: Thumb,
) -> Arc<Keyframe> {
    let frame = Arc::new(Keyframe {
        features: features.clone(),
        points: points.to_vec(),
        thumb,
        world_from_camera: hop.world_from_query,
        covariance: hop.covariance,
        confidence: key.confidence,
        image: key.image,
        hops: key.hops + 1,
        path_m: hop.path_m,
        latest: None,
    });
    if hop.refreshes() {
        return frame;
    }
    Arc::new(Keyframe {
        features: key.features.clone(),
        points: key.points.clone(),
        thumb: key.thumb.clone(),
        latest: Some(frame),
        ..**key
    })
}

/// Position drift of odometry, metres per metre driven since the map fix.
pub const DRIFT_M_PER_M: f64 = 0.05;
/// Rotation drift of odometry, radians per metre driven since the map fix (1 degree).
pub const DRIFT_RAD_PER_M: f64 = 0.017_453_292_519_943_295;

/// A tracked pose's covariance `chain` (the map fix's plus each hop's registration, ROS order:
/// metres², radians²) widened by the drift of `path_m` metres of odometry since the fix: standard
/// deviations of [`DRIFT_M_PER_M`] and [`DRIFT_RAD_PER_M`] times the path, added on the diagonal
/// (drift grows with the path, not with its square root: the hops' errors are not independent).
/// The hops' registrations alone count only their keypoints' independent noise: they claimed a
/// centimetre after 0.6 m and 33 degrees of real Kinect frames through an unmapped part of a
/// kitchen, where the track was 6-7 cm off, so the map fixes met there moved it by a fraction of
/// that (BENCHMARKS.md, "Real recordings").
pub fn with_drift(chain: &[f64; 36], path_m: f64) -> [f64; 36] {
    let (p, r) = (DRIFT_M_PER_M * path_m, DRIFT_RAD_PER_M * path_m);
    let mut out = *chain;
    for i in 0..3 {
        out[i * 7] += p * p;
        out[(i + 3) * 7] += r * r;
    }
    out
}

/// Two estimates of one camera pose fused by their covariances (the information form of a Kalman
/// update): `a` and `b` (`world_from_camera`) with 6x6 covariances in the order of
/// [`Localization::covariance`](crate::pipeline::Localization) (position, then rotation about the
/// world axes, metres² and radians²). The pose `b` is expressed at `a` (its position difference and
/// the rotation vector of `b a⁻¹`), the two are weighed by the inverses of their covariances, and the
/// result is `a` moved by the weighted offset; its covariance is the inverse of the summed
/// information. `None` when a covariance is not invertible. Used where a tracked stream meets a map
/// fix that agrees with it: a fix with few inliers (a wide baseline, a partly shared view) moves the
/// track in proportion to its certainty instead of replacing it.
pub fn fuse(
    a: &Isometry3<f64>,
    cov_a: &[f64; 36],
    b: &Isometry3<f64>,
    cov_b: &[f64; 36],
) -> Option<(Isometry3<f64>, [f64; 36])> {
    let info_a = Matrix6::from_row_slice(cov_a).try_inverse()?;
    let info_b = Matrix6::from_row_slice(cov_b).try_inverse()?;
    let dt = b.translation.vector - a.translation.vector;
    let dr = (b.rotation * a.rotation.inverse()).scaled_axis();
    let xb = Vector6::new(dt.x, dt.y, dt.z, dr.x, dr.y, dr.z);
    let cov = (info_a + info_b).try_inverse()?;
    let cov = (cov + cov.transpose()) * 0.5;
    let x = cov * info_b * xb;
    if !x.iter().all(|v| v.is_finite()) {
        return None;
    }
    let pose = Isometry3::from_parts(
        Translation3::from(a.translation.vector + Vector3::new(x[0], x[1], x[2])),
        UnitQuaternion::from_scaled_axis(Vector3::new(x[3], x[4], x[5])) * a.rotation,
    );
    let mut out = [0.0; 36];
    for r in 0..6 {
        for c in 0..6 {
            out[r * 6 + c] = cov[(r, c)];
        }
    }
    Some((pose, out))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn drift_widens_a_track_with_its_path() {
        let mut chain = [0.0; 36];
        for i in 0..6 {
            chain[i * 7] = 1e-4;
        }
        // At the fix nothing is added; after 0.6 m, 3 cm and 0.6 degrees (standard deviations).
        assert_eq!(with_drift(&chain, 0.0), chain);
        let wide = with_drift(&chain, 0.6);
        for i in 0..3 {
            assert!((wide[i * 7] - (1e-4 + 0.03f64.powi(2))).abs() < 1e-12);
            let r = (0.6f64).to_radians();
            assert!((wide[(i + 3) * 7] - (1e-4 + r * r)).abs() < 1e-12);
        }
        // Off the diagonal, nothing changes.
        assert!(wide
            .iter()
            .enumerate()
            .all(|(i, v)| i % 7 == 0 || *v == chain[i]));
    }

    #[test]
    fn fusion_weighs_each_pose_by_its_certainty() {
        let diag = |p: f64, r: f64| {
            let mut c = [0.0; 36];
            for i in 0..3 {
                c[i * 7] = p * p;
                c[(i + 3) * 7] = r * r;
            }
            c
        };
        let a = Isometry3::translation(1.0, 0.0, 0.0);
        let b = Isometry3::from_parts(
            Translation3::new(1.2, 0.0, 0.0),
            UnitQuaternion::from_euler_angles(0.0, 0.02, 0.0),
        );
        // Equal certainty: half way, and the fused covariance halves.
        let (m, c) = fuse(&a, &diag(0.1, 0.01), &b, &diag(0.1, 0.01)).unwrap();
        assert!((m.translation.x - 1.1).abs() < 1e-9, "{m}");
        assert!((m.rotation.angle() - 0.01).abs() < 1e-6);
        assert!((c[0] - 0.005).abs() < 1e-9);
        // A fix 0.2 m off with a 0.2 m sigma against a track of 0.05 m: the track holds.
        let (m, _) = fuse(&b, &diag(0.2, 0.05), &a, &diag(0.05, 0.01)).unwrap();
        assert!((m.translation.x - (1.0 + 0.2 / 17.0)).abs() < 1e-9, "{m}");
        // Not invertible: no fusion.
        assert!(fuse(&a, &[0.0; 36], &b, &diag(0.1, 0.01)).is_none());
    }
}
