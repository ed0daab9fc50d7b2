//! The PNTR pipeline: one RGB-D query in, a pose out.
//!
//! extract the query's features once -> describe and retrieve the top database images -> (shortlist
//! the best k by a vote of their strongest keypoints, [`crate::shortlist`]; re-rank those by a cheap
//! geometric check: mutual nearest neighbours on the descriptors already in
//! hand, back-projected and registered, scored by inliers) -> run the configured matcher on the best
//! candidate(s) -> back-project matched keypoints with both depths (a pair is kept only when both
//! sides have valid depth, so the lists stay aligned) -> register -> verify the best registrations
//! densely ([`crate::verify`]) and turn the evidence into a calibrated probability
//! ([`crate::calibration`]); the most probable pose wins and is LOCALIZED only above the threshold ->
//! `world_from_query = world_from_db * db_from_query`, with its covariance from the inlier residuals.
//!
//! Poses: the map stores `world_from_camera` with its own camera axes (Habitat for HPointLoc, OpenCV's
//! optical axes for maps built from recordings: [`crate::map::MapHeader::camera_axes`]);
//! back-projection and registration work in OpenCV axes; the answer is converted back, so it is in the
//! same frame and axes as the map's own poses.

use std::collections::HashMap;
use std::sync::Arc;
use std::time::Instant;

use nalgebra::{Isometry3, Point2, Vector3};
use pntr_core::{convert_axes, CameraAxes, DepthMap, Intrinsics, RgbImage};
use pntr_features::config::FeatureStage;
use pntr_features::mnn::{Mnn, MnnParams};
use pntr_features::{Features, Matcher, Matches};
use pntr_registration::covariance::{point_to_point_covariance, rotate_covariance};
use pntr_registration::icp::{icp_matched, IcpParams};
use pntr_registration::pnp::{pnp_ransac, PnpParams};
use pntr_registration::teaser::{solve, solve_with_bounds, TeaserParams};
use pntr_registration::Rigid;
use pntr_retrieval::index::Hit;
use serde::Serialize;

use crate::agreement::{map_agreement, Agreement};
use crate::alias::resolve;
use crate::calibration::{choose, Calibration, CalibrationSource};
use crate::camera::to_map_scale;
use crate::coverage::Coverage;
use crate::depth_noise::RangeBounds;
use crate::map::Map;
use crate::odometry::{self, Keyframe};
use crate::preset::{Preset, Solver};
use crate::prior::{LocalizeOptions, Mode, PoseIndex, Region};
use crate::refine::{fine_depth, polish_track, polish_views, refine_dense, Prior, View};
use crate::shortlist::{automatic_depth, Shortlist, Shortlisted, FINAL_KEYPOINTS};

/// Nearest and farthest a map fix may lie from a tracked pose and still be fused with it, metres.
pub const FUSION_GATE_MIN_M: f64 = 0.1;
/// See [`FUSION_GATE_MIN_M`].
pub const FUSION_GATE_MAX_M: f64 = 0.5;

/// Map views the final polish aligns the query with at most, the matched one included
/// ([`Pipeline::polish`]).
pub const POLISH_VIEWS: usize = 4;
/// Radius around a verified camera in which the polish looks for neighbouring map views, metres.
pub const POLISH_RADIUS_M: f64 = 1.5;
/// Nearest map images (with a finer depth) the polish checks for shared surfaces.
pub const POLISH_NEIGHBOURS_SEARCHED: usize = 12;
/// Share of the query's valid thumbnail samples a neighbouring map view must agree with to join the
/// polish.
pub const POLISH_MIN_SHARED: f64 = 0.3;
/// The same share for the map views a tracked pose is polished against ([`Pipeline::polish_tracked`]).
/// Lower: the track's covariance holds what a small shared part leaves free, and where odometry
/// carries the camera beyond the map's matched views, the views still see 5-20% of the frame
/// (real Kinect frames of a kitchen, measured with the polished pose chained on: 0.3 kept 0.77 of
/// a stream within (5 cm, 5 deg), 0.1 kept 0.94, 0.05 kept 0.996; BENCHMARKS.md, "Tracks held to
/// the map's depth").
pub const TRACK_POLISH_MIN_SHARED: f64 = 0.05;

/// How far, metres, a map fix may lie from the tracked pose of the same frame and still be fused
/// with it ([`odometry::fuse`]): three times the track's RMS position error (the square root of
/// the trace of the position block of `track_covariance`, ROS order, with its drift:
/// [`odometry::with_drift`]; about 5 standard deviations of each axis), within
/// [`FUSION_GATE_MIN_M`] and [`FUSION_GATE_MAX_M`] (the latter also without a covariance). A fix
/// farther off is a challenger, not a correction: fused, a look-alike fix 0.44 m from a track
/// certain to 5 cm still moved it by 5.6 cm, and its neighbours stayed 4-7 cm off (real Kinect
/// frames, BENCHMARKS.md, "Real recordings").
pub fn fusion_gate_m(track_covariance: Option<&[f64; 36]>) -> f64 {
    track_covariance.map_or(FUSION_GATE_MAX_M, |c| {
        let sigma = (c[0] + c[7] + c[14]).max(0.0).sqrt();
        (3.0 * sigma).clamp(FUSION_GATE_MIN_M, FUSION_GATE_MAX_M)
    })
}

/// Why a pose cannot be a tracked camera's: it lies outside the region it can have reached, or,
/// with `turn` (an odometry hop, whose registration a turn beyond it would make suspect), it turned
/// more than it can have (`pose`: `world_from_camera`, map frame, map axes). A map answer is never
/// refused for its turn alone (issue 73: a sparse stream's frames 60 deg apart, each localized when
/// sent alone, were refused as "turned"); the stream judges its position against the camera's
/// motion.
fn off_track(pose: &Isometry3<f64>, opts: &LocalizeOptions, turn: bool) -> Option<String> {
    if opts.region_mode != Mode::Tracking {
        return None;
    }
    if let Some(region) = opts.region {
        let at = pose.translation.vector;
        if !region.contains(&at) {
            return Some(format!(
                "the pose is {:.1} m from where the stream's motion puts the camera, outside the {:.1} m it can have moved",
                (at - region.center_m).norm(),
                region.radius_m
            ));
        }
    }
    let heading = opts.heading.filter(|_| turn)?;
    let deg = heading.exceeded_by(&pose.rotation)?;
    Some(format!(
        "the pose is turned {deg:.0} deg from the stream's last pose, more than the {:.0} deg it can have turned",
        heading.max_deg
    ))
}
use crate::verify::{
    aliases, dense_check, dense_evidence, grid_coverage, poses_agree, vec3, Evidence, Thumb,
};
use crate::PipelineError;

/// Registered candidates verified per query (the most inliers first).
pub const VERIFY_CANDIDATES: usize = 5;
/// Map views besides the matched one that the dense check looks into.
pub const MAX_NEARBY_VIEWS: usize = 12;
/// Floor of the point noise in the covariance, metres (depth quantisation and keypoint jitter).
pub const COVARIANCE_MIN_SIGMA_M: f64 = 0.01;
/// MNN similarity floor of the second matching pass, run only when no candidate registered with
/// the preset's floor (0.82): 0.78 brings back right matches lost to blur, noise and other light
/// (BENCHMARKS.md, "The final matcher's similarity floor"), and as a fallback it cannot change an
/// answer the first pass gives.
pub const FALLBACK_MIN_SIMILARITY: f32 = 0.78;
/// Factor on the covariance from the inlier residuals. Those residuals understate the pose's error
/// (the inliers are the matches that fit within the noise bound, and they judge the pose they were
/// fitted to): on the calibration scenes (seed 11, as rendered and with the frame effects) the
/// position errors' median Mahalanobis distance was 1.93 and 2.47 against 1.54 for a consistent
/// 3-d covariance, so the variances are doubled (BENCHMARKS.md, "Covariance consistency").
pub const COVARIANCE_SCALE: f64 = 2.0;
/// Largest rotation standard deviation (degrees, the square root of the trace of the covariance's
/// rotation block) of a LOCALIZED answer: a pose whose own covariance leaves it this loosely held
/// could be 10 deg off (three standard deviations), where a wrong answer begins. On real Kinect
/// frames every answer more than 0.5 m or 10 deg off had 3.1-9.8 deg, and those within (5 cm, 5
/// deg) mostly less than 2 (BENCHMARKS.md, "Real recordings: more keypoints for larger frames").
/// Applied only against a map of a real camera's size, f >= 256 px (one that keeps a finer depth
/// per image, [`crate::refine::fine_depth`]): HPointLoc-camera answers (f = 128 px) this loosely
/// held were right, and refusing them cost 1 point of recall on clean rendered frames and 1.6 on
/// frames with a robot camera's effects. (The frame's measured depth noise does not tell the two
/// apart: the Kinect's correlated noise measures as clean.)
pub const MAX_ROTATION_SIGMA_DEG: f64 = 3.0;

/// The rotation standard deviation of a 6x6 covariance in the ROS order (x, y, z, then rotation
/// about x, y, z in radians): the square root of the rotation block's trace, in degrees.
pub fn rotation_sigma_deg(covariance: &[f64; 36]) -> f64 {
    (covariance[21] + covariance[28] + covariance[35])
        .max(0.0)
        .sqrt()
        .to_degrees()
}

/// A map view farther than this from the matched one (metres), or turned more (degrees), is an
/// independent view whose registration counts for the candidates' consensus.
pub const INDEPENDENT_VIEW_M: f64 = 1.0;
/// See [`INDEPENDENT_VIEW_M`].
pub const INDEPENDENT_VIEW_DEG: f64 = 20.0;

/// Map images tried for a LOCALIZED answer's turned look-alike ([`Pipeline::turned_views`]). With 2,
/// a query 1.9 m from a room that looks alike turned by 90 degrees was LOCALIZED there with
/// confidence 0.93: its own place's view was not among the 2 most alike; with 6 it is found and the
/// answer refused. Over 10,946 in-map queries, 6 against 2: LOCALIZED answers more than 5 m / 20
/// deg off 3 -> 1 (confidence above 0.9: 1 -> 0), recall -0.2 points, verification +0.5 ms a
/// query (BENCHMARKS.md, "Shape alone and more turned views").
pub const TURNED_CANDIDATES: usize = 6;
/// A map image counts as turned when its horizontal viewing direction differs from the answer's by
/// at least this, degrees (a room's 90 and 180 degree symmetries).
pub const TURNED_MIN_DEG: f64 = 60.0;
/// ... and when it was taken within this distance of the answer, metres (about a room).
pub const TURNED_RADIUS_M: f64 = 8.0;

/// What the search has seen of a query besides its features: its global descriptor, and the map
/// images it may use ([`LocalizeOptions::among`]).
struct Seen<'a> {
    desc: &'a pntr_retrieval::global::Descriptor,
    among: Option<&'a [usize]>,
}

/// Consensus counts only for a pose whose nearby map views agree with at least this share of the
/// query's samples ([`consensus_may_lift`]).
pub const CONSENSUS_MIN_VIEWS_AGREE: f64 = 0.6;
/// ... and that leaves at most this share of samples in space the matched or nearby views saw
/// through (each).
pub const CONSENSUS_MAX_VIOLATION: f64 = 0.1;

/// Whether other candidates' agreement may count for a pose with dense evidence `e`: only when the
/// dense checks support it on their own, its grey levels included
/// ([`shape_only`]: a box room matched by its shape alone agrees in depth
/// everywhere and in grey nowhere). Adjacent views of one wrong place register to the same
/// wrong pose, so their agreement lifted poses with free-space violations, low view agreement or
/// no grey agreement to confidences of 0.99 and above (issue 41; BENCHMARKS.md, "A map's own
/// calibration": of the out-of-map answers LOCALIZED against a drive's map, 7 of 75 before, 3
/// after, with no in-map answer lost on three maps' own frames).
pub fn consensus_may_lift(e: &Evidence) -> bool {
    e.views_agree >= CONSENSUS_MIN_VIEWS_AGREE
        && e.free_space_violation <= CONSENSUS_MAX_VIOLATION
        && e.views_violation <= CONSENSUS_MAX_VIOLATION
        && !shape_only(e)
}

/// Grey agreement within tiles ([`Evidence::local_gray`] with the matched view or
/// [`Evidence::views_local_gray`] with the nearby ones, whichever is higher) below which a pose is
/// supported by shape alone ([`shape_only`]).
pub const MIN_LOCAL_GRAY: f64 = 0.25;

/// The highest probability a candidate supported by shape alone is given, below every LOCALIZED
/// threshold calibrations choose (0.6 and up). Measured on six maps' own samples (three dataset
/// maps, three drives' maps; issue 41): of the candidates with grey agreement within tiles below
/// [`MIN_LOCAL_GRAY`] to which the logistic model gave 0.5 or more, 23 of 136 were right (0.17).
pub const SHAPE_ONLY_MAX_PROBABILITY: f64 = 0.3;

/// Whether a pose with evidence `e` is supported by shape alone: its depths agree with the map's
/// but its grey levels agree in no tile (or no tile has texture to compare). A room of another
/// building, or another room of the same one, with the query's shape (a wall at the same distance,
/// boxes of the same size) gives such poses, and depth and view agreement lift them to
/// probabilities they do not have (issue 41; BENCHMARKS.md, "Shape alone and more turned views").
pub fn shape_only(e: &Evidence) -> bool {
    e.best_local_gray() < MIN_LOCAL_GRAY
}

/// The probability the pipeline gives a verified candidate with evidence `e`: `calibration`'s, at
/// most [`SHAPE_ONLY_MAX_PROBABILITY`] for a pose supported by shape alone. Thresholds are fitted
/// on the calibration's own probabilities (`pntr_mapping::fit::fit`, `pntr_mapping::selfcal::fit`):
/// a map's own negatives that the cap removes still say how alike its places are, and a threshold
/// chosen after the cap fell to the base one and let 4 of 200 out-of-map queries through where it
/// had let 1 (seed 91's map; BENCHMARKS.md, "Shape alone and more turned views").
pub fn candidate_probability(calibration: &Calibration, e: &Evidence) -> f64 {
    let p = calibration.probability(e);
    if shape_only(e) {
        p.min(SHAPE_ONLY_MAX_PROBABILITY)
    } else {
        p
    }
}

/// One RGB-D query.
#[derive(Debug, Clone)]
pub struct Query {
    /// Colour image.
    pub rgb: RgbImage,
    /// Depth in metres (0, NaN, infinite or negative = missing), same size as `rgb`.
    pub depth: DepthMap,
    /// The query camera.
    pub intrinsics: Intrinsics,
}

/// Outcome of a localisation.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "SCREAMING_SNAKE_CASE")]
pub enum Status {
    /// A pose passed registration and verification.
    Localized,
    /// No pose passed: no valid registration, too few inliers, or verification below the threshold.
    NotLocalized,
}

/// Why a frame is NOT_LOCALIZED, as a bounded set a robot's supervisor can act on (the reason
/// says it in words): the proto's `NotLocalizedCause` and the `cause` label of the server's
/// NOT_LOCALIZED counter.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "SCREAMING_SNAKE_CASE")]
pub enum Cause {
    /// No candidate registered with enough inliers: nothing in view matched the map.
    NoMatch,
    /// A pose registered but its calibrated confidence stayed below the threshold.
    Unverified,
    /// A pose verified but another is as plausible: a look-alike place, the room turned round, or
    /// (in a stream) a map answer where the tracked camera cannot have gone.
    LookAlike,
    /// The camera is where the map does not reach (the reason begins with
    /// [`OUTSIDE_MAP_PREFIX`]).
    OutsideMap,
    /// The frame could not have been localized against any map: fewer keypoints on valid depth
    /// than a pose needs.
    BadInput,
}

impl Cause {
    /// The name used in the proto and as a metrics label (`NO_MATCH`, ...).
    pub fn name(self) -> &'static str {
        match self {
            Cause::NoMatch => "NO_MATCH",
            Cause::Unverified => "UNVERIFIED",
            Cause::LookAlike => "LOOK_ALIKE",
            Cause::OutsideMap => "OUTSIDE_MAP",
            Cause::BadInput => "BAD_INPUT",
        }
    }

    /// Every cause, in the proto's order.
    pub const ALL: [Cause; 5] = [
        Cause::NoMatch,
        Cause::Unverified,
        Cause::LookAlike,
        Cause::OutsideMap,
        Cause::BadInput,
    ];
}

/// A tracked pose whose view the map explains less than this share of ([`Coverage::explained`]) is
/// outside the mapped area.
pub const MIN_EXPLAINED: f64 = 0.2;

/// Largest contradiction of a tracked pose by the map's nearby views
/// ([`crate::agreement::Agreement::contradiction`]); beyond it the track is lost. Right tracked poses
/// on our drives: at most 0.18; a pose 0.25 m or more off: 0.4 and more.
pub const MAX_TRACK_CONTRADICTION: f64 = 0.3;

/// Farthest a re-anchoring map answer may lie from the frame's odometry pose, metres, for the map's
/// views to referee between the two ([`Pipeline::referee`]): both poses then see most of what the
/// map answer's views see. Farther apart, the answer challenges the track instead.
pub const SLIP_MAX_M: f64 = 1.0;
/// ... and the largest turn between them, degrees.
pub const SLIP_MAX_DEG: f64 = 15.0;
/// How much larger a share of the frame's samples that land on the map answer's views
/// ([`Evidence::views_agree`]) must agree with them at the map's pose than at the odometry pose
/// for the track to have slipped. Chosen on a robot drive along a striped wall whose odometry lost
/// a third of the camera's motion (seed 5, the map of the whole mapping drive, and its
/// database-view map): where the map answer was within 1 cm of the truth and the track 0.17-0.43 m
/// off, 0.99 agreed at the map's pose and 0.47-0.78 at the track's; one 0.12 m off (seed 3's
/// mapping drive, route 2) agreed on 0.96 and the right track on 0.93 (BENCHMARKS.md, "Tracks that
/// slip").
pub const SLIP_AGREE_MARGIN: f64 = 0.15;
/// ... and how much larger a share they must see through at the odometry pose
/// ([`Evidence::views_violation`]; the slipped tracks' poses 0.13-0.42, the map's 0.00-0.05).
pub const SLIP_VIOLATION_MARGIN: f64 = 0.05;

/// How the reason of a [`Cause::OutsideMap`] answer begins (a contract: supervisors match on it).
pub const OUTSIDE_MAP_PREFIX: &str = "outside the mapped area:";

/// Seconds spent in each stage of one query.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct StageTimes {
    /// Bringing a query from another camera to the map's pixel scale ([`crate::camera`]); 0 when
    /// the query already has the map's focal length and no distortion.
    pub resampling: f64,
    /// Feature extraction of the query.
    pub extraction: f64,
    /// Global descriptor and index search.
    pub retrieval: f64,
    /// Matching (cheap re-ranking matches and the final matcher).
    pub matching: f64,
    /// Back-projection and registration.
    pub registration: f64,
    /// Verification: dense checks of the best poses and the calibrated confidence.
    pub verification: f64,
    /// The whole localisation.
    pub total: f64,
}

/// The answer for one query.
#[derive(Debug, Clone)]
pub struct Localization {
    /// LOCALIZED or NOT_LOCALIZED.
    pub status: Status,
    /// Why it is NOT_LOCALIZED.
    pub reason: Option<String>,
    /// The reason's kind ([`Cause`]); `None` when LOCALIZED.
    pub cause: Option<Cause>,
    /// `world_from_camera` of the query (map frame, map camera axes); `None` unless localized.
    pub pose: Option<Isometry3<f64>>,
    /// The best pose found, even when verification rejected it (for evaluation and diagnostics).
    pub estimate: Option<Isometry3<f64>>,
    /// Calibrated confidence in 0..1 that `estimate` is within (1 m, 10 deg) of the truth: its
    /// candidate's probability times the chance that its strongest disagreeing rival is wrong, a
    /// rival with under half the candidate's inliers weighed in proportion
    /// ([`crate::calibration::choose`]); LOCALIZED needs at least the pipeline's threshold. 0 without
    /// an estimate.
    pub confidence: f64,
    /// What verification measured about `estimate`.
    pub evidence: Option<Evidence>,
    /// 6x6 covariance of `estimate`, row-major, order x, y, z, rotation about x, y, z in the map frame
    /// (metres², radians²; the ROS `PoseWithCovariance` convention), from the inlier residuals.
    pub covariance: Option<Box<[f64; 36]>>,
    /// Every candidate pose verification scored, in the order scored (the best is `estimate`).
    pub verified: Vec<Verified>,
    /// Registration inliers of the chosen candidate.
    pub inliers: usize,
    /// Matched pairs with valid depth given to registration.
    pub correspondences: usize,
    /// Map index of the chosen database image (of the top retrieval hit when not localized).
    pub image: Option<usize>,
    /// Retrieval hits (map indices and scores), best first.
    pub retrieved: Vec<Hit>,
    /// Stage timings.
    pub times: StageTimes,
    /// Which path answered: global retrieval, or the map images inside a prior or tracking region.
    pub mode: Mode,
    /// True when the pose came from registering the frame against the stream's keyframe
    /// ([`crate::odometry`]; `mode` is then [`Mode::Tracking`]).
    pub odometry: bool,
    /// A map answer that verified but lay outside the tracking region or turn bound, so it was
    /// refused, or a re-anchoring map answer that disagreed with the stream's odometry: its pose (map
    /// frame, the map's axes), calibrated confidence and registration inliers. The frame is then
    /// NOT_LOCALIZED, or answered by odometry. A stream weighs such answers against its track (the
    /// service's challenge rule).
    pub off_track: Option<(Isometry3<f64>, f64, usize)>,
    /// The keyframe the stream's next frame tracks from, when asked for
    /// ([`LocalizeOptions::want_keyframe`]) and LOCALIZED.
    pub keyframe: Option<Arc<Keyframe>>,
    /// The stream's track is lost: the map contradicted the pose its keyframe carried the frame to
    /// ([`MAX_TRACK_CONTRADICTION`]), so the frame was searched for over the whole map instead; the
    /// stream follows an established track on by [`Self::contradicted`], not answered, and drops
    /// one that is not established (an answer, LOCALIZED or not, is then a first fix).
    pub track_lost: bool,
    /// With [`Self::track_lost`]: where the frame's odometry carried the camera, which the map
    /// contradicted, and the keyframe its chain goes on with. Not an answer: the camera's motion,
    /// by which a stream still judges map fixes (issue 73: a right track the map contradicted in
    /// a doorway, where its views saw into another room, was dropped, and a copy of the mapped
    /// rooms beyond was taken once the time since allowed the distance).
    pub contradicted: Option<Contradicted>,
    /// For a map answer of a tracked frame whose keyframe also gave it a LOCALIZED pose (registered,
    /// on track, inside the mapped area): how far the map's pose lies from the frame's own odometry
    /// pose (metres, degrees), before they were fused; `None` otherwise. How
    /// a stream tells a fix that follows the camera's motion from one that merely lies near it.
    pub track_gap: Option<(f64, f64)>,
    /// For such a map answer that disagreed with the odometry pose beyond the fusion gate
    /// ([`fusion_gate_m`]): the map's views contradict the odometry pose where they agree with the
    /// map's ([`Pipeline::referee`], [`SLIP_AGREE_MARGIN`], [`SLIP_VIOLATION_MARGIN`]), so the
    /// track had slipped and this answer anchors it instead of challenging it; a stream whose track
    /// was established and answered within the last second keeps it established.
    pub track_slipped: bool,
}

/// What the map's views say of two poses of one tracked frame ([`Pipeline::referee`]).
#[derive(Debug, Clone, Copy)]
struct Slip {
    /// The dense evidence at the map answer's pose.
    map: Evidence,
    /// The same at the odometry pose.
    track: Evidence,
}

impl Slip {
    /// Whether the track slipped: at its pose the views agree with [`SLIP_AGREE_MARGIN`] less of
    /// the frame's depth than at the map's and see through [`SLIP_VIOLATION_MARGIN`] more of it. A
    /// paired test, like verification's between a pose and its turned rival, so it holds where no
    /// absolute floor does (the track's own contradiction check, [`MAX_TRACK_CONTRADICTION`], let
    /// a striped wall's slip reach 0.43 m).
    fn slipped(&self) -> bool {
        self.track.views_agree + SLIP_AGREE_MARGIN <= self.map.views_agree
            && self.track.views_violation >= self.map.views_violation + SLIP_VIOLATION_MARGIN
    }
}

/// A candidate pose that verification scored.
#[derive(Debug, Clone)]
pub struct Verified {
    /// Map index of the database image it was registered against.
    pub image: usize,
    /// `world_from_camera` (map frame, map camera axes).
    pub pose: Isometry3<f64>,
    /// What verification measured.
    pub evidence: Evidence,
    /// Its calibrated probability of being right (before its rivals are weighed).
    pub confidence: f64,
    /// Map indices of the verified candidates whose pose disagrees with it (0.5 m, 10 deg).
    pub rivals: Vec<usize>,
}

/// An accepted odometry hop: the keyframe it starts from, the hop, the pose (Habitat axes).
struct Tracked {
    key: Arc<Keyframe>,
    hop: odometry::Hop,
    pose: Isometry3<f64>,
}

/// Why the keyframe did not answer a tracked frame, and whether the track is lost with it (the map
/// contradicted the pose the hop gave: then the hop itself, [`Contradicted`]).
struct Refusal {
    why: String,
    lost: bool,
    contradicted: Option<Contradicted>,
}

/// The position uncertainty of a 6x6 pose covariance (ROS order, metres² first): the root of the
/// trace of its position block, metres.
pub fn position_sigma_m(covariance: &[f64; 36]) -> f64 {
    (covariance[0] + covariance[7] + covariance[14])
        .max(0.0)
        .sqrt()
}

/// A tracked frame's odometry pose that the map contradicted ([`Localization::contradicted`]).
#[derive(Debug, Clone)]
pub struct Contradicted {
    /// `world_from_camera`, map frame and axes.
    pub pose: Isometry3<f64>,
    /// Its position uncertainty by the chain's covariance and drift, metres (one standard
    /// deviation; `None` without a covariance).
    pub sigma_m: Option<f64>,
    /// The keyframe the chain goes on with (when the caller asked for keyframes).
    pub keyframe: Option<Arc<Keyframe>>,
}

/// The query as the tracking paths see it: features, back-projected keypoints (OpenCV query frame)
/// and the thumbnail (made only for streams).
struct Frame<'a> {
    /// The query at the map's pixel scale.
    query: &'a Query,
    features: &'a Features,
    points: &'a [Option<Vector3<f64>>],
    thumb: Option<&'a Thumb>,
}

/// How a candidate's matches are had: by a matcher, or already made (the shortlist's last vote,
/// with the same matcher on the whole features).
#[derive(Clone, Copy)]
enum Matched<'a> {
    By(&'a dyn Matcher),
    Known(&'a Matches),
}

/// Registration of one candidate.
#[derive(Debug, Clone)]
struct Candidate {
    image: usize,
    rank: usize,
    db_from_query: Option<Isometry3<f64>>,
    inliers: usize,
    pairs: usize,
    reason: Option<String>,
    /// Inlier pairs: query points (OpenCV query frame), database points, query pixels.
    inlier_src: Vec<Vector3<f64>>,
    inlier_dst: Vec<Vector3<f64>>,
    inlier_px: Vec<[f32; 2]>,
    /// Every matched pair with depth on both sides (the solver's input): query points, database
    /// points, query pixels. Empty for PnP.
    pair_src: Vec<Vector3<f64>>,
    pair_dst: Vec<Vector3<f64>>,
    pair_px: Vec<[f32; 2]>,
}

/// A map with the feature stage and solvers that run on it. Cheap to share: `localize` takes `&self`
/// and can run on many threads at once.
pub struct Pipeline {
    /// The map.
    pub map: Arc<Map>,
    /// Extractor and matcher.
    pub stage: FeatureStage,
    /// The preset in use.
    pub preset: Preset,
    /// TEASER settings.
    pub teaser: TeaserParams,
    /// ICP settings.
    pub icp: IcpParams,
    /// PnP settings.
    pub pnp: PnpParams,
    cheap: Mnn,
    /// MNN with [`FALLBACK_MIN_SIMILARITY`], for frames whose candidates all failed to register.
    fallback: Mnn,
    calibration: Arc<Calibration>,
    calibration_source: CalibrationSource,
    min_confidence: f64,
    /// Map indices of the images of each (scene, Point), for the nearby views of verification.
    point_views: HashMap<(u32, u32), Vec<usize>>,
    /// The focal length queries are resampled to: the median of the map images' cameras, pixels.
    map_focal_px: f64,
    /// Pixels of a map image (the median), what a query is compared with for coverage.
    map_pixels: f64,
    /// The map images' camera positions, for prior and tracking regions.
    pose_index: PoseIndex,
    /// The strongest keypoints of each map image, for the shortlist's vote.
    shortlist: Shortlist,
    /// Camera axes of the map's poses and of the answers ([`crate::map::MapHeader::axes`]).
    axes: CameraAxes,
    /// The map's surfaces, made once when first needed ([`Pipeline::coverage`]) and shared by the
    /// pipelines of one map ([`Pipeline::sharing_coverage`]).
    coverage: Arc<std::sync::OnceLock<Coverage>>,
}

impl std::fmt::Debug for Pipeline {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "Pipeline({}, {} images)",
            self.preset.name,
            self.map.images.len()
        )
    }
}

impl Pipeline {
    /// Put a map and a feature stage together. The preset must use the extractor the map was built
    /// with, or one with the same descriptors (`xfeat`, `xfeat-int8` and `xfeat-bf16`:
    /// [`pntr_features::config::same_descriptors`]); descriptors from another extractor mean nothing
    /// to the map.
    pub fn new(map: Arc<Map>, stage: FeatureStage, preset: Preset) -> Result<Self, PipelineError> {
        preset.validate()?;
        preset.serves(&map.header.preset)?;
        // The map's own calibration when it carries one (fitted on its own regions), else the
        // shipped one; `with_calibration` overrides either.
        let (calibration, calibration_source) = match &map.header.calibration {
            Some(own) => (Arc::new(own.calibration.clone()), CalibrationSource::Map),
            None => (
                Arc::new(Calibration::embedded()),
                CalibrationSource::Shipped,
            ),
        };
        let mut point_views: HashMap<(u32, u32), Vec<usize>> = HashMap::new();
        for (i, im) in map.images.iter().enumerate() {
            point_views.entry((im.scene, im.point)).or_default().push(i);
        }
        let map_focal_px = map.focal_px();
        let map_pixels = map.image_pixels();
        let pose_index = PoseIndex::new(
            map.images
                .iter()
                .map(|im| im.world_from_camera.translation.vector)
                .collect(),
        );
        let shortlist = Shortlist::new(&map.images, FINAL_KEYPOINTS);
        let axes = map.header.axes();
        Ok(Self {
            axes,
            map,
            stage,
            teaser: TeaserParams {
                min_inliers: preset.min_inliers.max(3),
                ..TeaserParams::default()
            },
            icp: IcpParams::default(),
            pnp: PnpParams {
                min_inliers: preset.min_inliers.max(4),
                ..PnpParams::default()
            },
            preset,
            cheap: Mnn::default(),
            fallback: Mnn {
                params: MnnParams {
                    min_similarity: FALLBACK_MIN_SIMILARITY,
                    ..MnnParams::default()
                },
            },
            min_confidence: calibration.threshold,
            calibration,
            calibration_source,
            point_views,
            map_focal_px,
            map_pixels,
            coverage: Arc::default(),
            pose_index,
            shortlist,
        })
    }

    /// Use `calibration` for confidence and LOCALIZED when the probability is at least `min_confidence`
    /// (the calibration's own recommended threshold when `None`).
    pub fn with_calibration(
        mut self,
        calibration: Arc<Calibration>,
        min_confidence: Option<f64>,
    ) -> Self {
        // A calibration fitted for another preset still loads: its probabilities then describe
        // another pipeline's evidence (refit it with `pntr calibrate --preset`).
        if calibration.preset != self.preset.name
            && calibration.preset != self.preset.calibration_preset()
        {
            tracing::warn!(
                calibration_preset = %calibration.preset,
                preset = %self.preset.name,
                "the confidence calibration was fitted for another preset; refit it with `pntr calibrate` for calibrated confidences"
            );
        }
        self.min_confidence = min_confidence.unwrap_or(calibration.threshold);
        self.calibration = calibration;
        self.calibration_source = CalibrationSource::File;
        self
    }

    /// LOCALIZED when the confidence is at least `min_confidence` instead of the calibration's own
    /// threshold (`None`: keep it).
    pub fn with_min_confidence(mut self, min_confidence: Option<f64>) -> Self {
        if let Some(m) = min_confidence {
            self.min_confidence = m;
        }
        self
    }

    /// The confidence calibration in use, and where it came from.
    pub fn calibration(&self) -> (&Calibration, CalibrationSource) {
        (&self.calibration, self.calibration_source)
    }

    /// The focal length, pixels, that queries from other cameras are resampled to.
    pub fn map_focal_px(&self) -> f64 {
        self.map_focal_px
    }

    /// The LOCALIZED threshold on the calibrated confidence.
    pub fn min_confidence(&self) -> f64 {
        self.min_confidence
    }

    /// Localise one query with global retrieval over the whole map.
    pub fn localize(&self, q: &Query) -> Result<Localization, PipelineError> {
        self.localize_with(q, &LocalizeOptions::default())
    }

    /// How many global candidates the shortlist's vote re-ranks to keep `keep`: the preset's
    /// `shortlist`, or by the map's size when that is 0; just `keep` when re-ranking is off.
    fn shortlist_depth(&self, keep: usize) -> usize {
        match (self.preset.rerank, self.preset.shortlist) {
            (false, _) => keep,
            (true, 0) => automatic_depth(self.map.images.len(), keep).max(keep),
            (true, d) => d.max(keep),
        }
    }

    /// The best `keep` of the global candidates `hits` by the shortlist's vote ([`Shortlist`]), or
    /// `hits` as they are when there are no more than `keep`; with the cheap matcher's matches of
    /// those the last vote compared whole.
    fn shortlisted(
        &self,
        fq: &Features,
        q_pts: &[Option<Vector3<f64>>],
        hits: Vec<Hit>,
        keep: usize,
    ) -> Result<Shortlisted, PipelineError> {
        if hits.len() <= keep {
            return Ok(Shortlisted::unmatched(hits));
        }
        self.shortlist.rerank_matched(
            &self.map.images,
            fq,
            q_pts,
            &hits,
            keep,
            &self.cheap,
            2.0 * self.teaser.noise_bound,
        )
    }

    /// How the map's views agree with the frame `thumb` at `pose` (`world_from_camera`, map frame,
    /// the map's camera axes): [`crate::agreement::map_agreement`].
    pub fn map_agreement(&self, thumb: &Thumb, pose: &Isometry3<f64>) -> Option<Agreement> {
        let world_from_camera = convert_axes(pose, self.axes, CameraAxes::OpenCv);
        map_agreement(
            &self.map.images,
            &self.pose_index,
            self.axes,
            thumb,
            &world_from_camera,
        )
    }

    /// The map images inside `region`, nearest first.
    pub fn images_within(&self, region: &Region) -> Vec<usize> {
        self.pose_index.within(region)
    }

    /// Localise one query, trying the map images inside `opts.region` first (a caller's prior or a
    /// stream's last pose): retrieval ranks only those images (`opts.region_candidates` of them),
    /// and the rest of the pipeline is the same. When the region holds no map image, or none of its
    /// candidates verifies, global retrieval over the whole map answers (the features are extracted
    /// once; the stage times add up both attempts); in tracking mode a global pose outside the
    /// region is refused (NOT_LOCALIZED: a tracked camera cannot jump). [`Localization::mode`] says
    /// which path produced the answer.
    ///
    /// With `opts.keyframe` (a stream's last verified frame) the frame is first registered against it
    /// ([`crate::odometry`]), and an accepted hop inside the region answers LOCALIZED in
    /// [`Mode::Tracking`] with [`Localization::odometry`] set, without retrieval; with
    /// `opts.map_first` the map answers and the hop only judges its answer (`settle`), or answers
    /// when the map does not. A hop the map's views contradict ([`MAX_TRACK_CONTRADICTION`]) loses
    /// the track: the frame is searched for over the whole map and [`Localization::track_lost`] is
    /// set. With `opts.want_keyframe` a LOCALIZED answer carries the keyframe for the next frame.
    pub fn localize_with(
        &self,
        q: &Query,
        opts: &LocalizeOptions,
    ) -> Result<Localization, PipelineError> {
        let t0 = Instant::now();
        check_query(q)?;
        let mut times = StageTimes::default();
        // Another camera's query is brought to the map's pixel scale; from here on `q` is the
        // resampled query and only the keypoints' depths come from the frame as sent.
        let resampled = to_map_scale(q, self.map_focal_px, self.map_pixels);
        let q_sent = q;
        let q: &Query = &resampled.query;
        let tr = Instant::now();
        times.resampling = (tr - t0).as_secs_f64();
        let pixels = q.rgb.width as usize * q.rgb.height as usize;
        let fq = self
            .stage
            .extractor
            .extract_at_most(&q.rgb, self.preset.keypoints_for(pixels))?;
        let t1 = Instant::now();
        times.extraction = (t1 - tr).as_secs_f64();
        // A query that sees less than a map image describes the place less surely: widen the
        // shortlist with its coverage deficit (at most twice the preset's).
        let shortlist = (self.preset.candidates as f64 * resampled.coverage_ratio.min(2.0)).round();
        let shortlist = shortlist as usize;
        let q_pts: Vec<Option<Vector3<f64>>> = resampled
            .keypoint_points(&fq.keypoints)
            .iter()
            .map(|p| p[0].is_finite().then(|| vec3(*p)))
            .collect();
        // Each keypoint's registration bound for a candidate the fixed bound cannot register: the
        // preset's, widened with range when the frame's depth is noisy (a real sensor's; measured
        // on the frame as sent, whose noise resampling would smooth, and only when first needed).
        let q_bounds = RangeBounds::new(
            &q_sent.depth,
            &q_pts,
            self.teaser.noise_bound,
            self.preset.depth_noise_sigmas,
        );
        let thumb = (opts.keyframe.is_some() || opts.want_keyframe)
            .then(|| Thumb::new(&q.rgb, &q.depth, &q.intrinsics));
        let frame = Frame {
            query: q,
            features: &fq,
            points: &q_pts,
            thumb: thumb.as_ref(),
        };
        // A tracked stream: the keyframe first. It answers unless its map fix is old enough to
        // re-anchor (`map_first`: the map answers, and the hop is the track's word on that answer).
        let mut odometry_refusal: Option<Refusal> = None;
        let mut hop = None;
        if let Some(key) = &opts.keyframe {
            match self.odometry_answer(key, &frame, opts, &mut times, t0)? {
                Ok(loc) if !opts.map_first => return Ok(loc),
                Ok(loc) => hop = Some(loc),
                Err(refusal) => odometry_refusal = Some(refusal),
            }
        }
        // The map contradicted where the keyframe carried the frame: the track is lost, and
        // the frame is searched for over the whole map, as a stream's first frame is (its tracking
        // region lies around a wrong pose, where a look-alike would be found again).
        let track_lost = odometry_refusal.as_ref().is_some_and(|r| r.lost);
        let contradicted = odometry_refusal
            .as_mut()
            .and_then(|r| r.contradicted.take());
        let untracked;
        let opts = if track_lost {
            untracked = LocalizeOptions {
                among: opts.among.clone(),
                want_keyframe: opts.want_keyframe,
                ..LocalizeOptions::default()
            };
            &untracked
        } else {
            opts
        };
        let odometry_refusal = odometry_refusal.map(|r| r.why);
        let td = Instant::now();
        let desc = self.map.retriever.describer.describe(&q.rgb, &fq)?;
        times.retrieval += td.elapsed().as_secs_f64();
        let inside = opts.region.map(|r| {
            let mut ids = self.images_within(&r);
            if let Some(among) = &opts.among {
                ids.retain(|i| among.binary_search(i).is_ok());
            }
            ids
        });
        if let Some(ids) = inside.filter(|ids| !ids.is_empty()) {
            let k = opts.region_candidates.unwrap_or(shortlist);
            let ts = Instant::now();
            // A caller's prior can hold many look-alike views: voted like global retrieval. A
            // tracking region holds the few views around the stream's last verified pose, ranked
            // by the global descriptor alone: its re-anchoring then keeps the views most like the
            // frame (voting there once re-anchored a clean drive on a view 0.3 m off).
            let hits = if opts.region_mode == Mode::Tracking {
                Shortlisted::unmatched(self.map.retriever.search_among(&desc, k, &ids)?)
            } else {
                let deep = self
                    .map
                    .retriever
                    .search_among(&desc, self.shortlist_depth(k), &ids)?;
                self.shortlisted(&fq, &q_pts, deep, k)?
            };
            times.retrieval += ts.elapsed().as_secs_f64();
            let seen = Seen {
                desc: &desc,
                among: opts.among.as_deref(),
            };
            let loc =
                self.answer_from_candidates(&fq, &q_pts, &q_bounds, q, hits, &seen, times, t0)?;
            let on_track = loc
                .pose
                .is_some_and(|p| off_track(&p, opts, false).is_none());
            if loc.status == Status::Localized && on_track {
                let loc = Localization {
                    mode: opts.region_mode,
                    ..loc
                };
                return Ok(self.settle(loc, &frame, opts, hop));
            }
            times = loc.times;
        }
        let t2 = Instant::now();
        let depth = self.shortlist_depth(shortlist);
        let hits = match &opts.among {
            Some(among) => self.map.retriever.search_among(&desc, depth, among)?,
            None => self.map.retriever.search(&desc, depth)?,
        };
        let hits = self.shortlisted(&fq, &q_pts, hits, shortlist)?;
        times.retrieval += t2.elapsed().as_secs_f64();
        let seen = Seen {
            desc: &desc,
            among: opts.among.as_deref(),
        };
        let loc = self.answer_from_candidates(&fq, &q_pts, &q_bounds, q, hits, &seen, times, t0)?;
        // A tracked camera cannot jump: a global answer outside the tracking region (where the
        // camera can be, given its last verified pose) is a look-alike, not the robot's position.
        let loc = match loc.pose.and_then(|p| off_track(&p, opts, false)) {
            Some(why) => Localization {
                status: Status::NotLocalized,
                reason: Some(format!(
                    "tracking: {why} (send relocalize to accept a jump)"
                )),
                cause: Some(Cause::LookAlike),
                pose: None,
                off_track: loc
                    .pose
                    .filter(|_| loc.status == Status::Localized)
                    .map(|p| (p, loc.confidence, loc.inliers)),
                ..loc
            },
            None => loc,
        };
        if loc.status == Status::Localized {
            let loc = Localization {
                track_lost,
                contradicted,
                ..loc
            };
            return Ok(self.settle(loc, &frame, opts, hop));
        }
        // The map did not answer: the keyframe's hop, when the map was tried first.
        let times = loc.times;
        if let Some(found) = hop {
            return Ok(Localization {
                off_track: loc.off_track,
                times,
                ..found
            });
        }
        let reason = match (loc.reason, odometry_refusal) {
            (Some(r), Some(o)) => Some(format!("{r}; odometry: {o}")),
            (r, o) => r.or(o.map(|o| format!("odometry: {o}"))),
        };
        Ok(Localization {
            reason,
            cause: loc.cause.or(Some(Cause::NoMatch)),
            times,
            track_lost,
            contradicted,
            ..loc
        })
    }

    /// Register the frame against a stream's keyframe ([`crate::odometry`]), and when that fails
    /// against the last frame tracked from it ([`Keyframe::latest`], which then becomes the
    /// keyframe): a TRACKING answer (NOT_LOCALIZED, OUTSIDE_MAP, where the map's surfaces do not
    /// explain the view), or why not: the keyframe's refusal, or the map's views contradicting the
    /// pose it gives ([`MAX_TRACK_CONTRADICTION`]; the refusal then says the track is lost). The
    /// hops' time counts as registration.
    fn odometry_answer(
        &self,
        key: &Arc<Keyframe>,
        frame: &Frame,
        opts: &LocalizeOptions,
        times: &mut StageTimes,
        t0: Instant,
    ) -> Result<Result<Localization, Refusal>, PipelineError> {
        let thumb = frame.thumb.expect("made when a keyframe is given");
        let mut found = self.hop(key, frame, thumb, opts, times)?;
        if let (Err(_), Some(latest)) = (&found, &key.latest) {
            if let Ok(hop) = self.hop(latest, frame, thumb, opts, times)? {
                found = Ok(hop);
            }
        }
        let Tracked { key, hop, pose } = match found {
            Ok(found) => found,
            Err(why) => {
                return Ok(Err(Refusal {
                    why,
                    lost: false,
                    contradicted: None,
                }))
            }
        };
        // A chain past its length answers nothing where the map reaches (drift: the map must
        // answer); beyond the map it goes on, not LOCALIZED, as the camera's motion (issue 73: a
        // stream whose chain ended 10 m into unmapped rooms had only the time since to judge
        // look-alikes by, and took a copy of the mapped rooms 7 m away once that time allowed).
        let explained = self
            .coverage()
            .explained(thumb, &convert_axes(&pose, self.axes, CameraAxes::OpenCv));
        let outside = explained.filter(|&share| share < MIN_EXPLAINED);
        if let Some(why) = hop.worn().filter(|_| outside.is_none()) {
            return Ok(Err(Refusal {
                why,
                lost: false,
                contradicted: None,
            }));
        }
        // Where the map has views of what the frame sees, they must not contradict the pose: a
        // track that slipped (odometry that lost the camera's motion along a striped corridor, a
        // look-alike room it was carried into) puts the frame's surfaces where the map saw
        // through. Right poses: at most 20% of the samples on our drives; slipped ones pass 30%
        // beyond about 0.3 m (BENCHMARKS.md, "Robots that leave the map").
        let agreement = self.map_agreement(thumb, &pose);
        let contradicted = agreement
            .as_ref()
            .and_then(|a| Some((a.contradiction()?, a.deciding())))
            .filter(|&(c, _)| c > MAX_TRACK_CONTRADICTION);
        let covariance = hop.covariance.map(|c| odometry::with_drift(&c, hop.path_m));
        if let Some((c, views)) = contradicted {
            times.total = t0.elapsed().as_secs_f64();
            let keyframe = opts.want_keyframe.then(|| {
                odometry::next_keyframe(&key, &hop, frame.features, frame.points, thumb.clone())
            });
            return Ok(Err(Refusal {
                contradicted: Some(Contradicted {
                    pose,
                    sigma_m: covariance.as_ref().map(position_sigma_m),
                    keyframe,
                }),
                why: format!(
                    "the map contradicts the tracked pose: each of the {views} nearby map views that look at what the frame sees saw through at least {:.0}% of it (at most {:.0}%), so the track may have slipped: it is not answered until a map fix agrees",
                    c * 100.0,
                    MAX_TRACK_CONTRADICTION * 100.0
                ),
                lost: true,
            }));
        }
        let keyframe = opts.want_keyframe.then(|| {
            odometry::next_keyframe(&key, &hop, frame.features, frame.points, thumb.clone())
        });
        // Odometry can carry the pose where the map does not reach (`outside`): there nothing
        // confirms it and a look-alike room is the next map answer, so the frame is not
        // LOCALIZED; the chain goes on (the keyframe) so the stream knows where the camera went
        // and when it comes back.
        // Odometry drifts where the map's images were never matched from, though their depth
        // still sees part of the frame's surfaces: the answer is held to them
        // ([`Self::polish_tracked`]). The chain goes on from odometry's own pose, so that a polish
        // cannot add its error to the frames after it.
        let tp = Instant::now();
        let pose = match (covariance, key.image, outside) {
            (Some(cov), Some(image), None) => self
                .polish_tracked(frame.query, thumb, &hop.world_from_query, &cov, image)
                .map_or(pose, |p| convert_axes(&p, CameraAxes::OpenCv, self.axes)),
            _ => pose,
        };
        times.verification += tp.elapsed().as_secs_f64();
        times.total = t0.elapsed().as_secs_f64();
        Ok(Ok(Localization {
            status: if outside.is_some() {
                Status::NotLocalized
            } else {
                Status::Localized
            },
            reason: outside.map(|share| {
                format!(
                    "{OUTSIDE_MAP_PREFIX} odometry carried the camera where the map's images did not see: {:.0}% of the view's depth lies on surfaces the map holds (at least {:.0}% needed); the stream keeps track of the camera and answers again when it is back in the mapped area",
                    share * 100.0,
                    MIN_EXPLAINED * 100.0
                )
            }),
            cause: outside.map(|_| Cause::OutsideMap),
            pose: outside.is_none().then_some(pose),
            estimate: Some(pose),
            confidence: key.confidence,
            evidence: Some(hop.evidence),
            covariance: covariance.map(Box::new),
            verified: Vec::new(),
            inliers: hop.inliers,
            correspondences: hop.pairs,
            image: key.image,
            retrieved: Vec::new(),
            times: *times,
            mode: Mode::Tracking,
            odometry: true,
            off_track: None,
            keyframe,
            track_lost: false,
            contradicted: None,
            track_gap: None,
            track_slipped: false,
        }))
    }

    /// One odometry hop of the frame from `key` when the registration holds and the pose is on
    /// track, otherwise why not.
    fn hop(
        &self,
        key: &Arc<Keyframe>,
        frame: &Frame,
        thumb: &Thumb,
        opts: &LocalizeOptions,
        times: &mut StageTimes,
    ) -> Result<Result<Tracked, String>, PipelineError> {
        let th = Instant::now();
        let hop = odometry::register(
            key,
            frame.features,
            frame.points,
            thumb,
            &self.cheap,
            self.teaser.noise_bound,
        )?;
        times.registration += th.elapsed().as_secs_f64();
        let Some(hop) = hop else {
            return Ok(Err("no valid registration with the keyframe".into()));
        };
        if let Some(why) = &hop.refused {
            return Ok(Err(why.clone()));
        }
        let pose = convert_axes(&hop.world_from_query, CameraAxes::OpenCv, self.axes);
        if let Some(why) = off_track(&pose, opts, true) {
            return Ok(Err(why));
        }
        Ok(Ok(Tracked {
            key: Arc::clone(key),
            hop,
            pose,
        }))
    }

    /// A LOCALIZED map answer `loc` of a tracked stream, and the keyframe's `hop` of the same frame
    /// when the map was tried first (a re-anchoring frame) and the hop held: when the two poses
    /// disagree (by more than [`fusion_gate_m`] or 10 deg), the camera cannot have jumped, so
    /// odometry answers and the map answer goes along as a challenger (`off_track`: two confident
    /// ones that agree move the track), unless the map's views say the track slipped
    /// ([`Self::referee`], [`Slip::slipped`]): then the map answer anchors the keyframe at its own
    /// pose ([`Localization::track_slipped`]); otherwise the map answer and the track are fused by
    /// their covariances ([`odometry::fuse`]) and the frame becomes the anchored keyframe at the
    /// fused pose. Either way [`Localization::track_gap`] says how far apart they were.
    fn settle(
        &self,
        mut loc: Localization,
        frame: &Frame,
        opts: &LocalizeOptions,
        hop: Option<Localization>,
    ) -> Localization {
        // A hop the map's surfaces do not explain cannot outweigh a verified map answer.
        let hop = hop.filter(|h| h.status == Status::Localized);
        let (Some(pose), Some(hop)) = (loc.pose, hop) else {
            return self.with_keyframe(loc, frame, opts);
        };
        let hop_pose = hop.pose.expect("LOCALIZED odometry answers have a pose");
        loc.track_gap = Some((
            (hop_pose.translation.vector - pose.translation.vector).norm(),
            hop_pose.rotation.angle_to(&pose.rotation).to_degrees(),
        ));
        if !poses_agree(
            &hop_pose,
            &pose,
            fusion_gate_m(hop.covariance.as_deref()),
            10.0,
        ) {
            // Near enough that both poses see what the map answer's views see: the views referee.
            // A track they contradict where the map's pose agrees has slipped (odometry that lost
            // the camera's motion along a striped wall): the map answer anchors the track.
            let referee = self.referee(&loc, &pose, frame, &hop_pose);
            let slipped = referee.is_some_and(|r| r.slipped());
            if let Some(r) = &referee {
                tracing::debug!(
                    gap_m = loc.track_gap.map(|g| g.0),
                    map_agree = r.map.views_agree,
                    map_violation = r.map.views_violation,
                    track_agree = r.track.views_agree,
                    track_violation = r.track.views_violation,
                    slipped,
                    "the map's views referee between a map answer and the track"
                );
            }
            if slipped {
                let loc = Localization {
                    track_slipped: true,
                    ..loc
                };
                return self.with_keyframe(loc, frame, opts);
            }
            // The refused map answer still challenges the track: a chain that slipped onto a
            // wrong pose is moved when confident map answers keep agreeing with each other
            // against it (the service's challenge rule).
            return Localization {
                off_track: Some((pose, loc.confidence, loc.inliers)),
                times: loc.times,
                track_gap: loc.track_gap,
                ..hop
            };
        }
        // The map fix and the track agree: each moves the other by its certainty
        // ([`odometry::fuse`]), so a fix with a handful of inliers (a wide baseline, a look-alike
        // part of the view) cannot drag a well-supported track by its own error (real Kinect
        // frames: BENCHMARKS.md, "Real recordings").
        let covs = (loc.covariance.as_deref(), hop.covariance.as_deref());
        if let (Some(cov), Some(track_cov)) = covs {
            if let Some((p, c)) = odometry::fuse(&pose, cov, &hop_pose, track_cov) {
                loc.pose = Some(p);
                loc.estimate = Some(p);
                loc.covariance = Some(Box::new(c));
            }
        }
        self.with_keyframe(loc, frame, opts)
    }

    /// What the map's views say of a LOCALIZED map answer `loc` (its pose `pose`) of a tracked
    /// frame and the frame's odometry pose `track_pose` (both map frame and axes), when the two lie
    /// within [`SLIP_MAX_M`] and [`SLIP_MAX_DEG`] of each other (`loc.track_gap`): both judged by
    /// the map answer's matched view and the other views of its Point ([`Self::evidence_at`], the
    /// same views for both poses). `None` farther apart, or without a thumbnail or a matched image.
    fn referee(
        &self,
        loc: &Localization,
        pose: &Isometry3<f64>,
        frame: &Frame,
        track_pose: &Isometry3<f64>,
    ) -> Option<Slip> {
        let (thumb, image) = (frame.thumb?, loc.image?);
        let (gap_m, gap_deg) = loc.track_gap?;
        if gap_m > SLIP_MAX_M || gap_deg > SLIP_MAX_DEG {
            return None;
        }
        let to_cv = |p: &Isometry3<f64>| convert_axes(p, self.axes, CameraAxes::OpenCv);
        Some(Slip {
            map: self.evidence_at(thumb, image, &to_cv(pose)),
            track: self.evidence_at(thumb, image, &to_cv(track_pose)),
        })
    }

    /// Dense evidence ([`dense_evidence`]) of a frame (`thumb`) at `world_from_query` (OpenCV
    /// axes, map frame) against map image `image` and up to [`MAX_NEARBY_VIEWS`] other views of
    /// its Point.
    fn evidence_at(
        &self,
        thumb: &Thumb,
        image: usize,
        world_from_query: &Isometry3<f64>,
    ) -> Evidence {
        let db_from_query = self.world_from_image(image).inverse() * world_from_query;
        let nearby = self.nearby_views(image, &[], world_from_query);
        dense_evidence(
            thumb,
            &self.map.images[image].thumb,
            &db_from_query,
            &nearby,
        )
    }

    /// The map views that judge a pose registered against map image `image` besides it: the other
    /// images of its Point, then the images among `hits` of its scene, at most
    /// [`MAX_NEARBY_VIEWS`], each with `view_from_query` for the query at `world_from_query`
    /// (OpenCV axes, map frame).
    fn nearby_views(
        &self,
        image: usize,
        hits: &[Hit],
        world_from_query: &Isometry3<f64>,
    ) -> Vec<(&Thumb, Isometry3<f64>)> {
        let db = &self.map.images[image];
        let mut views: Vec<usize> = self
            .point_views
            .get(&(db.scene, db.point))
            .cloned()
            .unwrap_or_default();
        for h in hits {
            if self.map.images[h.id].scene == db.scene && !views.contains(&h.id) {
                views.push(h.id);
            }
        }
        views.retain(|&i| i != image);
        views.truncate(MAX_NEARBY_VIEWS);
        views
            .iter()
            .map(|&i| {
                (
                    &self.map.images[i].thumb,
                    self.world_from_image(i).inverse() * world_from_query,
                )
            })
            .collect()
    }

    /// The map's surfaces ([`Coverage::of_map`]), made on first use (or by [`Self::coverage_maker`]).
    pub fn coverage(&self) -> &Coverage {
        self.coverage
            .get_or_init(|| Coverage::of_map(&self.map, self.axes))
    }

    /// This pipeline sharing `other`'s coverage (the same map's: one set of voxels, made once, for
    /// all the workers' pipelines).
    pub fn sharing_coverage(self, other: &Pipeline) -> Self {
        Self {
            coverage: Arc::clone(&other.coverage),
            ..self
        }
    }

    /// A job that makes the map's coverage ahead of its first use (time grows with the map: about
    /// 0.2 s for 550 images), for a background thread, so a stream's first tracked frame does not
    /// wait for it; a frame that needs it sooner waits for the job instead of repeating it.
    pub fn coverage_maker(&self) -> impl FnOnce() + Send + 'static {
        let (cell, map, axes) = (Arc::clone(&self.coverage), Arc::clone(&self.map), self.axes);
        move || {
            cell.get_or_init(|| Coverage::of_map(&map, axes));
        }
    }

    /// `loc` with the keyframe a stream tracks from next: this frame, at its verified map pose.
    fn with_keyframe(
        &self,
        loc: Localization,
        frame: &Frame,
        opts: &LocalizeOptions,
    ) -> Localization {
        let (Some(pose), Some(thumb), true) = (loc.pose, frame.thumb, opts.want_keyframe) else {
            return loc;
        };
        let keyframe = Keyframe::anchored(
            frame.features,
            frame.points,
            thumb.clone(),
            convert_axes(&pose, self.axes, CameraAxes::OpenCv),
            loc.covariance.as_deref().copied(),
            loc.confidence,
            loc.image,
        );
        Localization {
            keyframe: Some(Arc::new(keyframe)),
            ..loc
        }
    }

    /// Match, register and verify the retrieval candidates `hits` of the (resampled) query `q` with
    /// features `fq`, back-projected keypoints `q_pts` and their range-grown registration bounds
    /// `q_bounds` (for candidates the fixed bound cannot register); a GLOBAL answer.
    #[allow(clippy::too_many_arguments)]
    fn answer_from_candidates(
        &self,
        fq: &Features,
        q_pts: &[Option<Vector3<f64>>],
        q_bounds: &RangeBounds,
        q: &Query,
        shortlisted: Shortlisted,
        seen: &Seen<'_>,
        mut times: StageTimes,
        t0: Instant,
    ) -> Result<Localization, PipelineError> {
        let Shortlisted {
            hits,
            matches: known,
        } = shortlisted;
        let matcher_is_cheap = self.preset.matcher == "mnn";
        // One candidate of this frame matched (or its matches taken) and registered.
        let register = |id: usize, rank: usize, matched: Matched, times: &mut StageTimes| {
            self.candidate(fq, q_pts, q_bounds, q, id, rank, matched, times)
        };
        let mut finalists: Vec<(usize, usize)> =
            hits.iter().enumerate().map(|(r, h)| (h.id, r)).collect();
        let mut done: Vec<Candidate> = Vec::new();
        // Every registration seen (cheap pass and final), for the candidates' consensus.
        let mut pool: Vec<(usize, Isometry3<f64>, usize)> = Vec::new();
        if self.preset.rerank && hits.len() > 1 {
            let mut scored = Vec::with_capacity(hits.len());
            for &(id, rank) in &finalists {
                // The shortlist's last vote may have matched this pair already, with this matcher.
                let cheap = match known.get(rank) {
                    Some(Some(m)) => Matched::Known(m),
                    _ => Matched::By(&self.cheap),
                };
                let c = register(id, rank, cheap, &mut times)?;
                scored.push(c);
            }
            scored.sort_by(|a, b| b.inliers.cmp(&a.inliers).then(a.rank.cmp(&b.rank)));
            pool.extend(
                scored
                    .iter()
                    .filter_map(|c| Some((c.image, self.world_from_query(c)?, c.inliers))),
            );
            if matcher_is_cheap {
                done = scored;
            } else {
                scored.truncate(self.preset.final_candidates);
                finalists = scored.iter().map(|c| (c.image, c.rank)).collect();
            }
        }
        if done.is_empty() {
            for &(id, rank) in &finalists {
                let c = register(
                    id,
                    rank,
                    Matched::By(self.stage.matcher.as_ref()),
                    &mut times,
                )?;
                if let Some(w) = self.world_from_query(&c) {
                    pool.retain(|p| p.0 != c.image);
                    pool.push((c.image, w, c.inliers));
                }
                done.push(c);
            }
        }
        let (mut valid, mut fewest) = self.registered(done);
        // A second chance for a frame none of whose candidates registered (blur, sensor noise and
        // other light push right matches under the floor): MNN again with a lower floor. Only then,
        // so every answer the first pass gives stays as it was.
        if valid.is_empty() && matcher_is_cheap && fq.binary.is_empty() {
            pool.clear();
            let mut again = Vec::with_capacity(finalists.len());
            for &(id, rank) in &finalists {
                let c = register(id, rank, Matched::By(&self.fallback), &mut times)?;
                if let Some(w) = self.world_from_query(&c) {
                    pool.push((c.image, w, c.inliers));
                }
                again.push(c);
            }
            let (v, f) = self.registered(again);
            valid = v;
            fewest = f.or(fewest);
        }
        // Verification: dense checks of the best registrations; the calibrated probability chooses.
        let tv = Instant::now();
        let thumb = (!valid.is_empty()).then(|| Thumb::new(&q.rgb, &q.depth, &q.intrinsics));
        let thumb_ref = thumb.as_ref();
        // A registration one texture period off moved onto the copy its other matches support.
        if let Some(t) = thumb_ref {
            for c in valid.iter_mut() {
                if self.resolve_alias(c, t) {
                    if let Some(w) = self.world_from_query(c) {
                        pool.retain(|p| p.0 != c.image);
                        pool.push((c.image, w, c.inliers));
                    }
                }
            }
        }
        // Refined before verification, so the dense checks judge the refined poses. (`pool`, for the
        // candidates' consensus, keeps the registrations' poses, or the alias stage's: giving it the
        // refined poses instead changed one answer in 6,500 robot and clean queries, BENCHMARKS.md,
        // "Dense refinement up to 10 degrees".)
        if let Some(t) = thumb_ref {
            for c in valid.iter_mut() {
                let db = &self.map.images[c.image].thumb;
                let refined = c
                    .db_from_query
                    .and_then(|p| refine_dense(t, db, &p, &c.inlier_src, &c.inlier_dst));
                if refined.is_some() {
                    c.db_from_query = refined;
                }
            }
        }
        let mut scored: Vec<(Candidate, Evidence, Isometry3<f64>)> = valid
            .into_iter()
            .map(|c| {
                let e = self.evidence(
                    &c,
                    thumb_ref.expect("made when candidates exist"),
                    &pool,
                    &hits,
                    q,
                );
                let w = self.world_from_query(&c).expect("valid");
                (c, e, w)
            })
            .collect();
        let (mut probabilities, mut rivals, mut chosen) = self.decide(&mut scored);
        // A pose about to be LOCALIZED: is the same room, turned round, also a pose? Rooms that look
        // alike turned by 90 or 180 degrees gave the confident in-map errors (issue 41), and the
        // turned views rarely make the shortlist, whose ranking follows the look of the place.
        if let (Some((i, conf)), Some(t)) = (chosen, thumb_ref) {
            if conf >= self.min_confidence {
                let taken: Vec<usize> = scored.iter().map(|s| s.0.image).collect();
                let scene = self.map.images[scored[i].0.image].scene;
                let turned = self.turned_views(&scored[i].2, scene, seen, &taken)?;
                let before = scored.len();
                for (k, id) in turned.into_iter().enumerate() {
                    // Matched and registered as part of verification (its time counts there).
                    let matched = Matched::By(&self.cheap);
                    let mut part_of_verification = StageTimes::default();
                    let mut c = register(id, hits.len() + k, matched, &mut part_of_verification)?;
                    let Some(p) = c
                        .db_from_query
                        .filter(|_| c.inliers >= self.preset.min_inliers)
                    else {
                        continue;
                    };
                    let db = &self.map.images[c.image].thumb;
                    if let Some(r) = refine_dense(t, db, &p, &c.inlier_src, &c.inlier_dst) {
                        c.db_from_query = Some(r);
                    }
                    let w = self.world_from_query(&c).expect("valid");
                    pool.push((c.image, w, c.inliers));
                    let e = self.evidence(&c, t, &pool, &hits, q);
                    scored.push((c, e, w));
                }
                if scored.len() > before {
                    (probabilities, rivals, chosen) = self.decide(&mut scored);
                }
            }
        }
        // The strongest rival turned from the chosen pose by a room's symmetry, for the reason.
        let turned_rival = chosen.and_then(|(i, _)| {
            rivals[i]
                .iter()
                .map(|&j| {
                    let deg = scored[i]
                        .2
                        .rotation
                        .angle_to(&scored[j].2.rotation)
                        .to_degrees();
                    (deg, probabilities[j])
                })
                .filter(|&(deg, p)| deg >= TURNED_MIN_DEG && p >= 0.5)
                .max_by(|a, b| a.1.total_cmp(&b.1))
        });
        let verified: Vec<Verified> = scored
            .iter()
            .zip(&probabilities)
            .zip(&rivals)
            .map(|(((c, e, w), &p), r)| Verified {
                image: c.image,
                pose: convert_axes(w, CameraAxes::OpenCv, self.axes),
                evidence: *e,
                confidence: p,
                rivals: r.iter().map(|&j| scored[j].0.image).collect(),
            })
            .collect();
        // The answer's covariance is part of verification's work (its aliasing search).
        // The chosen pose's own probability, before its rivals were weighed.
        let own = chosen.map_or(0.0, |(i, _)| probabilities[i]);
        let best = chosen.map(|(i, conf)| {
            let (mut c, e, _) = scored.swap_remove(i);
            self.polish(q, &mut c, thumb_ref);
            let covariance = thumb_ref.and_then(|t| self.covariance(&c, t));
            (c, e, conf, covariance)
        });
        times.verification = tv.elapsed().as_secs_f64();
        times.total = t0.elapsed().as_secs_f64();
        let top = hits.first().map(|h| h.id);
        let Some((c, evidence, p, covariance)) = best else {
            // A frame with fewer keypoints on valid depth than a pose needs could not have been
            // localized against any map: say so, apart from a view the map does not match.
            let usable = q_pts.iter().filter(|p| p.is_some()).count();
            let starved = usable < self.preset.min_inliers && !hits.is_empty();
            return Ok(Localization {
                status: Status::NotLocalized,
                reason: Some(match fewest {
                    _ if starved => format!(
                        "input: only {usable} keypoints lie on valid depth, fewer than the {} a pose needs (a dark, blank or blurred image, or no depth under its texture)",
                        self.preset.min_inliers
                    ),
                    Some(n) => format!(
                        "registration: {n} inliers at best, fewer than {}",
                        self.preset.min_inliers
                    ),
                    None if hits.is_empty() => "the map is empty".into(),
                    None => "registration: no candidate gave a valid registration".into(),
                }),
                cause: Some(if starved {
                    Cause::BadInput
                } else {
                    Cause::NoMatch
                }),
                pose: None,
                estimate: None,
                confidence: 0.0,
                evidence: None,
                covariance: None,
                verified,
                inliers: 0,
                correspondences: 0,
                image: top,
                retrieved: hits,
                times,
                mode: Mode::Global,
                odometry: false,
                off_track: None,
                keyframe: None,
                track_lost: false,
                contradicted: None,
                track_gap: None,
                track_slipped: false,
            });
        };
        let world_from_query = self
            .world_from_query(&c)
            .expect("verified candidates are valid");
        let estimate = convert_axes(&world_from_query, CameraAxes::OpenCv, self.axes);
        // A pose its own inliers hold too loosely is not an answer, however sure the place is:
        // for a real camera's frame (a map that keeps finer depth, f >= 256 px) only; see
        // MAX_ROTATION_SIGMA_DEG for where it was measured.
        let loose = covariance.as_ref().map(rotation_sigma_deg).filter(|&deg| {
            deg > MAX_ROTATION_SIGMA_DEG
                && p >= self.min_confidence
                && self.map.images[c.image].fine.is_some()
        });
        let covariance = covariance.map(Box::new);
        let localized = p >= self.min_confidence && loose.is_none();
        Ok(Localization {
            status: if localized {
                Status::Localized
            } else {
                Status::NotLocalized
            },
            reason: (!localized).then(|| {
                if let Some(deg) = loose {
                    return format!(
                        "verification: the place verifies (confidence {p:.2}) but the pose is loosely held: rotation +-{deg:.1} deg (one standard deviation, {} inliers), more than the {MAX_ROTATION_SIGMA_DEG} deg a LOCALIZED answer may carry",
                        c.inliers
                    );
                }
                let turned = turned_rival.map_or(String::new(), |(deg, pr)| {
                    format!(
                        "; a pose turned by {deg:.0} deg also verifies (probability {pr:.2}): the room looks alike turned round and the map cannot tell the two apart"
                    )
                });
                let shape = if shape_only(&evidence) {
                    format!(
                        "; the pose fits the map's shape but not its look (grey agreement within tiles {:.2} at best over the matched and nearby views, below {:.2}): a place shaped alike, or a view with no texture to compare",
                        evidence.best_local_gray(),
                        MIN_LOCAL_GRAY
                    )
                } else {
                    String::new()
                };
                let (p, threshold) = apart(p, self.min_confidence);
                format!(
                    "verification: confidence {p} below the threshold {threshold} ({}){shape}{turned}",
                    evidence.summary()
                )
            }),
            // A pose that verified on its own but lost to a rival (a look-alike place, the room
            // turned round) is a look-alike; one that never verified is unverified.
            cause: (!localized).then_some(
                if loose.is_some() {
                    Cause::Unverified
                } else if turned_rival.is_some() || own >= self.min_confidence {
                    Cause::LookAlike
                } else {
                    Cause::Unverified
                },
            ),
            pose: localized.then_some(estimate),
            estimate: Some(estimate),
            confidence: p,
            evidence: Some(evidence),
            covariance,
            verified,
            inliers: c.inliers,
            correspondences: c.pairs,
            image: Some(c.image),
            retrieved: hits,
            times,
            mode: Mode::Global,
            odometry: false,
            off_track: None,
            keyframe: None,
            track_lost: false,
            contradicted: None,
            track_gap: None,
            track_slipped: false,
        })
    }

    /// Each verified candidate's rivalry (the best view agreement among the candidates whose pose
    /// disagrees, written into its evidence), calibrated probability and disagreeing rivals, and the
    /// choice among them ([`choose`]).
    #[allow(clippy::type_complexity)]
    fn decide(
        &self,
        scored: &mut [(Candidate, Evidence, Isometry3<f64>)],
    ) -> (Vec<f64>, Vec<Vec<usize>>, Option<(usize, f64)>) {
        // Ambiguity: the best rival that verifies well with a pose that disagrees (a symmetric room,
        // a repeated piece of furniture) lowers the confidence of each.
        let rival_agree: Vec<f64> = scored
            .iter()
            .map(|(_, _, w)| {
                scored
                    .iter()
                    .filter(|(_, _, o)| !poses_agree(o, w, 0.5, 10.0))
                    .map(|(_, e, _)| e.views_agree)
                    .fold(0.0, f64::max)
            })
            .collect();
        for ((_, e, _), r) in scored.iter_mut().zip(rival_agree) {
            e.rival_agree = r;
        }
        let probabilities: Vec<f64> = scored
            .iter()
            .map(|(_, e, _)| candidate_probability(&self.calibration, e))
            .collect();
        let rivals: Vec<Vec<usize>> = scored
            .iter()
            .map(|(_, _, w)| {
                (0..scored.len())
                    .filter(|&j| !poses_agree(&scored[j].2, w, 0.5, 10.0))
                    .collect()
            })
            .collect();
        let inliers: Vec<usize> = scored.iter().map(|(c, _, _)| c.inliers).collect();
        let chosen = choose(&probabilities, &inliers, &rivals);
        (probabilities, rivals, chosen)
    }

    /// Up to [`TURNED_CANDIDATES`] map images of `scene` (not in `taken`, within `seen.among`) that
    /// look at the room of `world_from_query` (OpenCV axes) from a direction turned by at least
    /// [`TURNED_MIN_DEG`] about the map's up axis, within [`TURNED_RADIUS_M`], the most alike
    /// (global descriptor) first: where the same room turned round would be seen from.
    fn turned_views(
        &self,
        world_from_query: &Isometry3<f64>,
        scene: u32,
        seen: &Seen<'_>,
        taken: &[usize],
    ) -> Result<Vec<usize>, PipelineError> {
        let up = self.map.header.up();
        let level = |r: &nalgebra::UnitQuaternion<f64>| {
            let f = r * Vector3::z();
            let h = f - up * f.dot(&up);
            (h.norm() > 0.3).then(|| h.normalize())
        };
        let Some(forward) = level(&world_from_query.rotation) else {
            return Ok(Vec::new());
        };
        let region = Region::new(world_from_query.translation.vector, TURNED_RADIUS_M)?;
        let min_cos = TURNED_MIN_DEG.to_radians().cos();
        let ids: Vec<usize> = self
            .images_within(&region)
            .into_iter()
            .filter(|&j| {
                let im = &self.map.images[j];
                im.scene == scene
                    && !taken.contains(&j)
                    && seen.among.is_none_or(|a| a.binary_search(&j).is_ok())
                    && level(
                        &convert_axes(&im.world_from_camera, self.axes, CameraAxes::OpenCv)
                            .rotation,
                    )
                    .is_some_and(|f| f.dot(&forward) <= min_cos)
            })
            .collect();
        if ids.is_empty() {
            return Ok(Vec::new());
        }
        let hits = self
            .map
            .retriever
            .search_among(seen.desc, TURNED_CANDIDATES, &ids)?;
        Ok(hits.into_iter().map(|h| h.id).collect())
    }

    /// The chosen candidate's pose polished with the finer depth of the query and of its map view,
    /// where the map has it ([`crate::map::MapImage::fine`], [`polish_views`]), jointly with up to
    /// [`POLISH_VIEWS`] - 1 neighbouring map views that see the same surfaces
    /// ([`Self::polish_neighbours`]). After the decision, so that which answers are LOCALIZED stays
    /// what verification decided on the thumbnails: aligned on the finer depth before verification,
    /// wrong wide-baseline registrations slid along a kitchen's cabinets into agreement and were
    /// LOCALIZED 0.3-0.5 m off (BENCHMARKS.md, "Real recordings").
    fn polish(&self, q: &Query, c: &mut Candidate, thumb: Option<&Thumb>) {
        let Some(db) = &self.map.images[c.image].fine else {
            return;
        };
        let Some(p) = c.db_from_query else { return };
        let Some(query) = fine_depth(&q.rgb, &q.depth, &q.intrinsics) else {
            return;
        };
        let mut views = vec![View::matched(db)];
        if let Some(t) = thumb {
            views.extend(self.polish_neighbours(c.image, &p, t));
        }
        if let Some(r) = polish_views(&query, &views, &p, &c.inlier_src, &c.inlier_dst) {
            c.db_from_query = Some(r);
        }
    }

    /// Map views near a verified pose (`db_from_query`, against map image `image`, OpenCV axes)
    /// that see what the query sees ([`Self::agreeing_views`], `image` left out), the most agreeing
    /// first, [`POLISH_VIEWS`] - 1 at most, each with its camera from `image`'s.
    fn polish_neighbours<'a>(
        &'a self,
        image: usize,
        db_from_query: &Isometry3<f64>,
        thumb: &Thumb,
    ) -> Vec<View<'a>> {
        let world_from_db = self.world_from_image(image);
        let world_from_query = world_from_db * db_from_query;
        let scene = self.map.images[image].scene;
        self.agreeing_views(
            &world_from_query,
            thumb,
            scene,
            Some(image),
            POLISH_MIN_SHARED,
        )
        .into_iter()
        .take(POLISH_VIEWS - 1)
        .map(|j| View {
            thumb: self.map.images[j]
                .fine
                .as_ref()
                .expect("views with a finer depth"),
            from_ref: self.world_from_image(j).inverse() * world_from_db,
        })
        .collect()
    }

    /// `world_from_camera` of map image `j`, OpenCV camera axes.
    fn world_from_image(&self, j: usize) -> Isometry3<f64> {
        convert_axes(
            &self.map.images[j].world_from_camera,
            self.axes,
            CameraAxes::OpenCv,
        )
    }

    /// Map images that see what a query camera at `world_from_query` (OpenCV axes) sees: of the
    /// [`POLISH_NEIGHBOURS_SEARCHED`] map images of `scene` nearest to it within
    /// [`POLISH_RADIUS_M`] that have a finer depth ([`crate::map::MapImage::fine`]; `except` left
    /// out), those whose thumbnail depth agrees with at least `min_shared` of the query's
    /// valid samples `thumb` under the pose, the most agreeing first: [`POLISH_MIN_SHARED`] for a
    /// verified map answer's neighbours, [`TRACK_POLISH_MIN_SHARED`] for a tracked pose's views.
    fn agreeing_views(
        &self,
        world_from_query: &Isometry3<f64>,
        thumb: &Thumb,
        scene: u32,
        except: Option<usize>,
        min_shared: f64,
    ) -> Vec<usize> {
        let Ok(region) = Region::new(world_from_query.translation.vector, POLISH_RADIUS_M) else {
            return Vec::new();
        };
        let mut found: Vec<(usize, usize)> = self
            .images_within(&region)
            .into_iter()
            .filter(|&j| Some(j) != except && self.map.images[j].scene == scene)
            .filter(|&j| self.map.images[j].fine.is_some())
            .take(POLISH_NEIGHBOURS_SEARCHED)
            .filter_map(|j| {
                let counts = dense_check(
                    thumb,
                    &self.map.images[j].thumb,
                    &(self.world_from_image(j).inverse() * world_from_query),
                );
                (counts.valid > 0 && counts.agree as f64 >= min_shared * counts.valid as f64)
                    .then_some((counts.agree, j))
            })
            .collect();
        found.sort_by_key(|f| std::cmp::Reverse(f.0));
        found.into_iter().map(|(_, j)| j).collect()
    }

    /// A tracked pose (`world_from_query`, OpenCV axes, with its covariance: map frame, ROS order)
    /// polished against the map views that see what the frame sees ([`Self::agreeing_views`] of the
    /// scene of the map fix the track started from, [`POLISH_VIEWS`] at most, the most agreeing the
    /// reference), with the pose's covariance as the prior ([`polish_track`]). `None` where the map
    /// keeps no finer depth (maps of cameras below 256 px of focal length: rendered HPointLoc maps
    /// among them), no view agrees, or the polish is refused.
    fn polish_tracked(
        &self,
        q: &Query,
        thumb: &Thumb,
        world_from_query: &Isometry3<f64>,
        covariance: &[f64; 36],
        image: usize,
    ) -> Option<Isometry3<f64>> {
        self.map.images[image].fine.as_ref()?;
        let scene = self.map.images[image].scene;
        let ids = self.agreeing_views(
            world_from_query,
            thumb,
            scene,
            None,
            TRACK_POLISH_MIN_SHARED,
        );

        let (&reference, _) = ids.split_first()?;
        let world_from_ref = self.world_from_image(reference);
        let views: Vec<View<'_>> = ids
            .iter()
            .take(POLISH_VIEWS)
            .map(|&j| View {
                thumb: self.map.images[j]
                    .fine
                    .as_ref()
                    .expect("views with a finer depth"),
                from_ref: self.world_from_image(j).inverse() * world_from_ref,
            })
            .collect();
        let query = fine_depth(&q.rgb, &q.depth, &q.intrinsics)?;
        let prior = Prior::from_world(covariance, &world_from_ref)?;
        let ref_from_query = world_from_ref.inverse() * world_from_query;
        polish_track(&query, &views, &ref_from_query, &prior).map(|p| world_from_ref * p)
    }

    /// The candidates with a registration, most inliers first, those with at least the preset's
    /// `min_inliers` (at most [`VERIFY_CANDIDATES`]), and the inliers of the weakest registration.
    fn registered(&self, done: Vec<Candidate>) -> (Vec<Candidate>, Option<usize>) {
        let mut valid: Vec<Candidate> = done
            .into_iter()
            .filter(|c| c.db_from_query.is_some())
            .collect();
        valid.sort_by(|a, b| b.inliers.cmp(&a.inliers).then(a.rank.cmp(&b.rank)));
        let fewest = valid.last().map(|c| c.inliers);
        valid.retain(|c| c.inliers >= self.preset.min_inliers);
        valid.truncate(VERIFY_CANDIDATES);
        (valid, fewest)
    }

    /// Move candidate `c`'s pose onto the rival its matches support when the dense checks prefer it
    /// ([`crate::alias::resolve`]; the rival needs the preset's `min_inliers`, as any registration);
    /// its inliers become the rival's. Returns whether it moved.
    fn resolve_alias(&self, c: &mut Candidate, thumb: &Thumb) -> bool {
        let Some(pose) = c.db_from_query else {
            return false;
        };
        let db = &self.map.images[c.image].thumb;
        let bound = self.teaser.noise_bound;
        let min = self.preset.min_inliers;
        let Some(r) = resolve(thumb, db, &pose, &c.pair_src, &c.pair_dst, bound, min) else {
            return false;
        };
        c.db_from_query = Some(r.db_from_query);
        c.inliers = r.inliers.len();
        c.inlier_src = r.inliers.iter().map(|&i| c.pair_src[i]).collect();
        c.inlier_dst = r.inliers.iter().map(|&i| c.pair_dst[i]).collect();
        c.inlier_px = r.inliers.iter().map(|&i| c.pair_px[i]).collect();
        true
    }

    /// `world_from_query` of a registered candidate, OpenCV camera axes.
    fn world_from_query(&self, c: &Candidate) -> Option<Isometry3<f64>> {
        Some(self.world_from_image(c.image) * c.db_from_query?)
    }

    /// What the dense checks, the inliers and the other candidates say about candidate `c`.
    fn evidence(
        &self,
        c: &Candidate,
        thumb: &Thumb,
        pool: &[(usize, Isometry3<f64>, usize)],
        hits: &[Hit],
        q: &Query,
    ) -> Evidence {
        let db = &self.map.images[c.image];
        let db_from_query = c.db_from_query.expect("valid");
        let world_from_query = self.world_from_query(c).expect("valid");
        // Nearby views: the matched image's Point and the other retrieved images of its scene.
        let nearby = self.nearby_views(c.image, hits, &world_from_query);
        let mut e = dense_evidence(thumb, &db.thumb, &db_from_query, &nearby);
        e.log_inliers = (1.0 + c.inliers as f64).ln();
        e.inlier_ratio = c.inliers as f64 / c.pairs.max(1) as f64;
        e.inlier_coverage = grid_coverage(&c.inlier_px, q.rgb.width, q.rgb.height, 4);
        let others: Vec<&(usize, Isometry3<f64>, usize)> =
            pool.iter().filter(|p| p.0 != c.image).collect();
        // Agreement counts only from views that are not near-copies of the matched one (within
        // 1 m and 20 deg of it): keyframes 0.3 m apart along a drive register a look-alike to the
        // same wrong pose as the matched one does, which is no second opinion (out-of-map answers
        // LOCALIZED against a drive's map: 0.12 with them, 0.047 without; BENCHMARKS.md, "Live
        // maps"). An HPointLoc Point's views differ in direction, so they all still count.
        let independent: Vec<&&(usize, Isometry3<f64>, usize)> = others
            .iter()
            .filter(|o| {
                let im = &self.map.images[o.0];
                (im.world_from_camera.translation.vector - db.world_from_camera.translation.vector)
                    .norm()
                    > INDEPENDENT_VIEW_M
                    || im
                        .world_from_camera
                        .rotation
                        .angle_to(&db.world_from_camera.rotation)
                        > INDEPENDENT_VIEW_DEG.to_radians()
            })
            .collect();
        let agreeing = independent
            .iter()
            .filter(|o| poses_agree(&o.1, &world_from_query, 0.5, 10.0))
            .count();
        // Other candidates agreeing is no evidence for a pose the dense checks do not support on
        // their own: views of one wrong place agree with each other (issue 41).
        e.consensus = if consensus_may_lift(&e) {
            agreeing as f64 / independent.len().max(1) as f64
        } else {
            0.0
        };
        e.rival_inliers = others
            .iter()
            .filter(|o| !poses_agree(&o.1, &world_from_query, 0.5, 10.0))
            .map(|o| o.2 as f64 / c.inliers.max(1) as f64)
            .fold(0.0, f64::max)
            .min(2.0);
        e
    }

    /// The 6x6 covariance of the answer in the map frame (ROS order), row-major.
    ///
    /// From the inlier residuals (times [`COVARIANCE_SCALE`]), widened along the query camera's image axes where the frame cannot
    /// tell the pose from one shifted by a texture period ([`aliases`]): the variance along such an
    /// axis grows by (shift / 2)², so the copy found lies at two standard deviations.
    fn covariance(&self, c: &Candidate, thumb: &Thumb) -> Option<[f64; 36]> {
        let db = &self.map.images[c.image];
        let world_from_db = self.world_from_image(c.image);
        let db_from_query = c.db_from_query?;
        let mut local = point_to_point_covariance(
            &c.inlier_src,
            &c.inlier_dst,
            &Rigid::from_isometry(&db_from_query),
            COVARIANCE_MIN_SIGMA_M,
        )? * COVARIANCE_SCALE;
        for (axis, shift) in aliases(thumb, &db.thumb, &db_from_query).iter().enumerate() {
            if *shift > 0.0 {
                let d = db_from_query.rotation * Vector3::ith(axis, 1.0);
                let widen = d * d.transpose() * (shift / 2.0).powi(2);
                let mut block = local.fixed_view_mut::<3, 3>(0, 0);
                block += widen;
            }
        }
        let world = rotate_covariance(&local, &world_from_db.rotation.to_rotation_matrix());
        let mut out = [0.0; 36];
        for r in 0..6 {
            for k in 0..6 {
                out[r * 6 + k] = world[(r, k)];
            }
        }
        Some(out)
    }

    /// Match the query against map image `id` (or take the matches already made) and register.
    #[allow(clippy::too_many_arguments)]
    fn candidate(
        &self,
        fq: &Features,
        q_pts: &[Option<Vector3<f64>>],
        q_bounds: &RangeBounds,
        q: &Query,
        id: usize,
        rank: usize,
        matched: Matched,
        times: &mut StageTimes,
    ) -> Result<Candidate, PipelineError> {
        let t0 = Instant::now();
        let db = &self.map.images[id];
        let made;
        let m = match matched {
            Matched::Known(m) => m,
            Matched::By(matcher) => {
                // The image's features widened into this thread's buffers, not allocated anew for
                // each candidate (the turned views match six a query).
                thread_local! {
                    static DB_FEATURES: std::cell::RefCell<Features> = Default::default();
                }
                made = DB_FEATURES.with(|f| {
                    let mut f = f.borrow_mut();
                    db.features_into(&mut f);
                    matcher.match_features(fq, &f)
                })?;
                &made
            }
        };
        let t1 = Instant::now();
        times.matching += (t1 - t0).as_secs_f64();
        let mut c = Candidate {
            image: id,
            rank,
            db_from_query: None,
            inliers: 0,
            pairs: 0,
            reason: None,
            inlier_src: Vec::new(),
            inlier_dst: Vec::new(),
            inlier_px: Vec::new(),
            pair_src: Vec::new(),
            pair_dst: Vec::new(),
            pair_px: Vec::new(),
        };
        match self.preset.solver {
            Solver::Pnp => {
                let (mut pts, mut px, mut qa) = (Vec::new(), Vec::new(), Vec::new());
                for &(a, b) in &m.pairs {
                    if let Some(p) = db.point(b as usize) {
                        let k = fq.keypoints[a as usize];
                        pts.push(p);
                        px.push(Point2::new(k[0] as f64, k[1] as f64));
                        qa.push(a as usize);
                    }
                }
                c.pairs = pts.len();
                let r = pnp_ransac(&q.intrinsics, &pts, &px, &self.pnp);
                if r.valid {
                    c.db_from_query = Some(r.camera_from_points.to_isometry().inverse());
                    c.inliers = r.inliers.len();
                    for &i in &r.inliers {
                        c.inlier_px.push(fq.keypoints[qa[i]]);
                        if let Some(s) = q_pts[qa[i]] {
                            c.inlier_src.push(s);
                            c.inlier_dst.push(pts[i]);
                        }
                    }
                } else {
                    c.reason = r.reason;
                }
            }
            Solver::Teaser | Solver::Icp => {
                let (mut src, mut dst, mut qa) = (Vec::new(), Vec::new(), Vec::new());
                for &(a, b) in &m.pairs {
                    if let (Some(s), Some(d)) = (q_pts[a as usize], db.point(b as usize)) {
                        src.push(s);
                        dst.push(d);
                        qa.push(a as usize);
                    }
                }
                c.pairs = src.len();
                let (transform, inliers) = if self.preset.solver == Solver::Teaser {
                    // The fixed bound first, so every registration it gives stays as it was (the
                    // calibration was fitted on those); the range-grown bounds of a noisy frame
                    // ([`crate::depth_noise`]) only for a candidate it cannot register, whose far
                    // surfaces' right matches the fixed bound drops.
                    let mut r = solve(&src, &dst, &self.teaser);
                    if let (false, Some(b)) = (r.valid, q_bounds.get()) {
                        let bounds: Vec<f64> = qa.iter().map(|&a| b[a]).collect();
                        let wide = solve_with_bounds(&src, &dst, Some(&bounds), &self.teaser);
                        if wide.valid {
                            r = wide;
                        } else if let (Some(fixed), Some(grown)) = (&r.reason, &wide.reason) {
                            r.reason = Some(format!(
                                "{fixed}; with bounds grown by the depth noise: {grown}"
                            ));
                        }
                    }
                    c.reason = r.reason;
                    (r.valid.then_some(r.transform), r.inliers)
                } else {
                    let r = icp_matched(&src, &dst, Rigid::identity(), &self.icp);
                    (r.valid.then_some(r.transform), r.inliers)
                };
                if let Some(t) = transform {
                    c.db_from_query = Some(Rigid::to_isometry(&t));
                    c.inliers = inliers.len();
                    for &i in &inliers {
                        c.inlier_src.push(src[i]);
                        c.inlier_dst.push(dst[i]);
                        c.inlier_px.push(fq.keypoints[qa[i]]);
                    }
                    c.pair_px = qa.iter().map(|&a| fq.keypoints[a]).collect();
                    c.pair_src = src;
                    c.pair_dst = dst;
                }
            }
        }
        times.registration += t1.elapsed().as_secs_f64();
        Ok(c)
    }
}

/// Refuse a query that cannot be localised at all (sizes that disagree, no valid depth).
pub fn check_query(q: &Query) -> Result<(), PipelineError> {
    let bad = |m: String| Err(PipelineError::Query(m));
    let (w, h) = (q.rgb.width, q.rgb.height);
    if w == 0 || h == 0 || q.rgb.data.len() != (w * h * 3) as usize {
        return bad(format!("rgb is {w}x{h} with {} bytes", q.rgb.data.len()));
    }
    if (q.depth.width, q.depth.height) != (w, h) || q.depth.data.len() != (w * h) as usize {
        return bad(format!(
            "depth is {}x{} but rgb is {w}x{h}",
            q.depth.width, q.depth.height
        ));
    }
    let k = &q.intrinsics;
    if !(k.fx > 0.0
        && k.fy > 0.0
        && k.fx.is_finite()
        && k.fy.is_finite()
        && k.cx.is_finite()
        && k.cy.is_finite())
    {
        return bad(format!(
            "intrinsics fx {} fy {} cx {} cy {}: focal lengths must be positive and finite",
            k.fx, k.fy, k.cx, k.cy
        ));
    }
    if !q.depth.data.iter().any(|d| d.is_finite() && *d > 0.0) {
        return bad("the depth image has no valid pixel".into());
    }
    Ok(())
}

/// `value` and `threshold` printed with two decimals, or with as many more (up to six) as it takes
/// for them to differ: "confidence 0.9996 below the threshold 0.9999", never "1.00 below 1.00".
fn apart(value: f64, threshold: f64) -> (String, String) {
    let mut digits = 2;
    while digits < 6 && format!("{value:.digits$}") == format!("{threshold:.digits$}") {
        digits += 1;
    }
    (format!("{value:.digits$}"), format!("{threshold:.digits$}"))
}

#[cfg(test)]
mod tests {
    #[test]
    fn a_refusal_never_prints_its_confidence_equal_to_the_threshold() {
        assert_eq!(apart(0.42, 0.61), ("0.42".into(), "0.61".into()));
        assert_eq!(apart(0.99963, 0.9999), ("0.9996".into(), "0.9999".into()));
        assert_eq!(apart(0.6049, 0.605), ("0.6049".into(), "0.6050".into()));
        // Equal to six decimals: six are printed.
        assert_eq!(
            apart(0.5, 0.5000001),
            ("0.500000".into(), "0.500000".into())
        );
    }

    #[test]
    fn a_slip_needs_both_margins() {
        let e = |agree: f64, violation: f64| Evidence {
            views_agree: agree,
            views_violation: violation,
            ..Default::default()
        };
        let slip = |track: Evidence| {
            Slip {
                map: e(0.99, 0.01),
                track,
            }
            .slipped()
        };
        // The striped wall's slip: far less agreement and more seen through at the track's pose.
        assert!(slip(e(0.66, 0.30)));
        assert!(slip(e(0.83, 0.07)), "both margins met");
        // One margin short: a challenger, not a slip.
        assert!(!slip(e(0.85, 0.30)), "agreement within the margin");
        assert!(!slip(e(0.50, 0.05)), "see-through within the margin");
        // The map answer the worse of the two (the track right): never a slip.
        let right_track = Slip {
            map: e(0.66, 0.30),
            track: e(0.99, 0.01),
        };
        assert!(!right_track.slipped());
    }

    use super::*;

    /// The gate's quantity on the covariance the pipeline computes from inliers: a real sensor's
    /// pose held by a dozen matches bunched on one patch at 2.5 m is loosely held, one held by
    /// matches spread over the view is not, with the same 1.5 cm of point noise.
    #[test]
    fn few_bunched_inliers_hold_a_rotation_loosely_and_spread_ones_tightly() {
        let mut state = 0x2545_f491_4f6c_dd1du64;
        let mut noise = move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (((state >> 11) as f64 / (1u64 << 53) as f64) - 0.5) * 0.05
        };
        let sigma = |src: Vec<Vector3<f64>>, noise: &mut dyn FnMut() -> f64| {
            let dst: Vec<Vector3<f64>> = src
                .iter()
                .map(|p| p + Vector3::new(noise(), noise(), noise()))
                .collect();
            let cov = point_to_point_covariance(
                &src,
                &dst,
                &Rigid::from_isometry(&Isometry3::identity()),
                COVARIANCE_MIN_SIGMA_M,
            )
            .unwrap()
                * COVARIANCE_SCALE;
            let mut c = [0.0; 36];
            for r in 0..6 {
                for k in 0..6 {
                    c[r * 6 + k] = cov[(r, k)];
                }
            }
            rotation_sigma_deg(&c)
        };
        let bunched: Vec<Vector3<f64>> = (0..12)
            .map(|i| Vector3::new(0.3 + 0.05 * (i % 4) as f64, 0.05 * (i / 4) as f64, 2.5))
            .collect();
        let spread: Vec<Vector3<f64>> = (0..40)
            .map(|i| {
                let (u, v) = ((i % 8) as f64 / 7.0 - 0.5, (i / 8) as f64 / 4.0 - 0.5);
                let z = 1.5 + (i % 3) as f64;
                Vector3::new(u * 1.6 * z, v * 1.2 * z, z)
            })
            .collect();
        let (loose, tight) = (sigma(bunched, &mut noise), sigma(spread, &mut noise));
        assert!(loose > MAX_ROTATION_SIGMA_DEG, "bunched: {loose:.2} deg");
        assert!(
            tight < MAX_ROTATION_SIGMA_DEG / 3.0,
            "spread: {tight:.2} deg"
        );
    }

    #[test]
    fn a_fix_is_fused_within_three_sigmas_of_the_track_and_its_bounds() {
        let isotropic = |sigma_m: f64| {
            let mut c = [0.0; 36];
            for i in 0..3 {
                c[i * 7] = sigma_m * sigma_m / 3.0;
            }
            c
        };
        // A track certain to a centimetre still fuses fixes 10 cm off; one widened by its drift
        // to 5 cm takes them to 15 cm; none beyond half a metre, as without a covariance.
        assert!((fusion_gate_m(Some(&isotropic(0.01))) - FUSION_GATE_MIN_M).abs() < 1e-12);
        assert!((fusion_gate_m(Some(&isotropic(0.05))) - 0.15).abs() < 1e-9);
        assert_eq!(fusion_gate_m(Some(&isotropic(1.0))), FUSION_GATE_MAX_M);
        assert_eq!(fusion_gate_m(None), FUSION_GATE_MAX_M);
        // The look-alike fix of the real kitchen: 0.44 m from a track of 5 cm is a challenger.
        let track = Isometry3::identity();
        let fix = Isometry3::translation(0.44, 0.0, 0.0);
        assert!(!poses_agree(
            &track,
            &fix,
            fusion_gate_m(Some(&isotropic(0.05))),
            10.0
        ));
    }

    /// A pose whose depths agree with the map everywhere but whose grey levels agree in no tile is
    /// capped below any threshold, whatever the model says; with grey agreement it keeps the
    /// model's probability, and consensus may lift it only then.
    #[test]
    fn a_pose_supported_by_shape_alone_is_capped() {
        let calibration = Calibration::embedded();
        let textured = Evidence {
            depth_agree: 0.99,
            overlap: 0.9,
            views_agree: 0.99,
            gray_correlation: 0.9,
            views_gray: 0.9,
            log_inliers: (1.0f64 + 60.0).ln(),
            inlier_ratio: 0.5,
            inlier_coverage: 0.8,
            consensus: 1.0,
            local_gray: 0.7,
            views_local_gray: 0.7,
            ..Evidence::default()
        };
        let shape = Evidence {
            local_gray: 0.1,
            views_local_gray: MIN_LOCAL_GRAY - 0.01,
            ..textured
        };
        assert!(!shape_only(&textured) && shape_only(&shape));
        assert!(
            calibration.probability(&shape) > 0.9,
            "the model alone is fooled"
        );
        assert_eq!(
            candidate_probability(&calibration, &shape),
            SHAPE_ONLY_MAX_PROBABILITY
        );
        assert_eq!(
            candidate_probability(&calibration, &textured),
            calibration.probability(&textured)
        );
        assert!(consensus_may_lift(&textured) && !consensus_may_lift(&shape));
    }
}
