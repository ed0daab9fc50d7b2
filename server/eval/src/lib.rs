//! Evaluation with the HPointLoc protocol and honest metrics.
//!
//! Recall is the fraction of ALL queries under a threshold: a query that was not localised, or whose
//! request failed, stays in the denominator. Rotation error is the geodesic angle between estimate and
//! ground truth, both in the dataset's camera axes. `legacy` reproduces the published code instead: the
//! estimate left in OpenCV axes against a Habitat ground truth, and the angle folded with
//! `|90 - |a - 90||` (so 180 degrees counts as 0) — labelled as such in the report, only for comparing
//! with the paper. The retrieval-only row answers every query with the pose of its top-1 database image.

use std::collections::BTreeMap;
use std::time::Instant;

use nalgebra::{Isometry3, Point3, Vector3};
use pntr_core::{convert_axes, CameraAxes, DepthMap, Intrinsics};
use pntr_dataset::queries::{evenly_spaced, query_list, QueryViews};
use pntr_dataset::{Role, SceneEntry};
use serde::Serialize;

use pntr_pipeline::pipeline::{Query, StageTimes, Status};
use pntr_pipeline::prior::{Mode, Region};
use pntr_pipeline::PipelineError;

/// (metres, degrees) thresholds of the protocol.
pub const THRESHOLDS: [(f64, f64); 4] = [(5.0, 20.0), (1.0, 10.0), (0.5, 5.0), (0.25, 2.0)];

/// The 8 recall keys, in table order.
pub const RECALL_KEYS: [&str; 8] = [
    "5m_20deg",
    "1m_10deg",
    "0.5m_5deg",
    "0.25m_2deg",
    "5m",
    "1m",
    "0.5m",
    "0.25m",
];

/// What a localiser (in-process or remote) answered for one query.
#[derive(Debug, Clone, Default)]
pub struct Answer {
    /// LOCALIZED or not (`None` when the request itself failed).
    pub status: Option<Status>,
    /// The estimated `world_from_camera` (dataset camera axes), when localized.
    pub pose: Option<Isometry3<f64>>,
    /// Ids of the retrieved database images, best first.
    pub retrieved: Vec<String>,
    /// Id of the database image the pose came from.
    pub matched: Option<String>,
    /// Stage timings.
    pub times: StageTimes,
    /// The calibrated confidence of the best pose found (LOCALIZED or not).
    pub confidence: f64,
    /// The best pose found even when it was not LOCALIZED (in-process only; remote answers carry the
    /// pose of LOCALIZED frames only), for the precision/recall curve over the threshold.
    pub estimate: Option<Isometry3<f64>>,
    /// The LOCALIZED threshold the localiser reported, when it reports one (the server does).
    pub threshold: Option<f64>,
    /// Which path answered (`None` when unknown: an old server, a failed request).
    pub mode: Option<Mode>,
    /// The 6x6 covariance of `pose` (map frame, ROS order, row-major), when LOCALIZED with one.
    pub covariance: Option<[f64; 36]>,
    /// Why the frame is NOT_LOCALIZED (the check that failed), when it is not.
    pub reason: Option<String>,
}

impl Answer {
    /// The answer of the in-process pipeline, with map indices turned into image ids and poses
    /// turned from the map's camera axes into the dataset's (Habitat).
    pub fn of(l: &pntr_pipeline::pipeline::Localization, map: &pntr_pipeline::map::Map) -> Self {
        let axes = map.header.axes();
        let to_dataset = |p: Isometry3<f64>| convert_axes(&p, axes, CameraAxes::Habitat);
        Self {
            status: Some(l.status),
            pose: l.pose.map(to_dataset),
            retrieved: l
                .retrieved
                .iter()
                .map(|h| map.images[h.id].id.clone())
                .collect(),
            matched: l.image.map(|i| map.images[i].id.clone()),
            times: l.times,
            confidence: l.confidence,
            estimate: l.estimate.or(l.pose).map(to_dataset),
            threshold: None,
            mode: Some(l.mode),
            covariance: l.pose.and(l.covariance.as_deref().copied()),
            reason: l.reason.clone(),
        }
    }
}

/// Translation (m) and rotation (deg) error of `est` against `gt`, both `world_from_camera` in Habitat
/// axes. `legacy`: the published code's folded angle with the axes mismatch.
pub fn pose_error(est: &Isometry3<f64>, gt: &Isometry3<f64>, legacy: bool) -> (f64, f64) {
    let dt = (est.translation.vector - gt.translation.vector).norm();
    if legacy {
        let est_cv = convert_axes(est, CameraAxes::Habitat, CameraAxes::OpenCv);
        let a = est_cv.rotation.angle_to(&gt.rotation).to_degrees();
        (dt, (90.0 - (a - 90.0).abs()).abs())
    } else {
        (
            dt,
            pntr_core::rotation_angle_deg(&est.rotation, &gt.rotation),
        )
    }
}

/// The 8 recalls of a list of per-query errors (`None` = failed, counted in the denominator).
pub fn recall(errors: &[Option<(f64, f64)>]) -> BTreeMap<String, f64> {
    let n = errors.len().max(1) as f64;
    let ok: Vec<(f64, f64)> = errors.iter().flatten().copied().collect();
    let mut out = BTreeMap::new();
    for (i, &(m, d)) in THRESHOLDS.iter().enumerate() {
        let both = ok.iter().filter(|e| e.0 <= m && e.1 <= d).count();
        let trans = ok.iter().filter(|e| e.0 <= m).count();
        out.insert(RECALL_KEYS[i].to_string(), both as f64 / n);
        out.insert(RECALL_KEYS[i + 4].to_string(), trans as f64 / n);
    }
    out
}

/// Retrieval quality against the ground truth. Every value is NaN (null in JSON) when the map's images
/// are none of the dataset's views (a map built from a recording): its places are not the Points.
#[derive(Debug, Clone, Default, Serialize)]
pub struct RetrievalRecall {
    /// A top-1 image of the query's own Point.
    pub point_at_1: f64,
    /// Some top-5 image of the query's own Point.
    pub point_at_5: f64,
    /// Top-1 is the database view that overlaps the query most.
    pub view_at_1: f64,
    /// The best-overlapping view is among the top 5.
    pub view_at_5: f64,
    /// After geometric re-ranking: the image the pose came from is of the query's Point (top-1
    /// retrieval when the answer names none).
    pub reranked_point_at_1: f64,
    /// After geometric re-ranking: the image the pose came from is the best-overlapping view.
    pub reranked_view_at_1: f64,
}

/// The report `pntr eval --json` writes (keys fixed by issue 6; more may be added).
#[derive(Debug, Clone, Serialize)]
pub struct EvalReport {
    /// Queries evaluated.
    pub queries: usize,
    /// Queries answered LOCALIZED.
    pub localized: usize,
    /// Recall of the pipeline's poses.
    pub recall: BTreeMap<String, f64>,
    /// Recall of the top-1 database pose used as the answer.
    pub retrieval_only: BTreeMap<String, f64>,
    /// Mean milliseconds per stage.
    pub stage_ms: BTreeMap<String, f64>,
    /// Queries per second over the whole run (wall clock).
    pub fps: f64,
    /// `geodesic` or `legacy-folded (published code; not a correct metric)`.
    pub metric: String,
    /// Retrieval recall of the right Point and of the best-overlapping view.
    pub retrieval: RetrievalRecall,
    /// Queries whose request failed (they count as not localized).
    pub failed_requests: usize,
    /// The preset, when known.
    pub preset: String,
    /// Share of LOCALIZED answers within each threshold (`1m_10deg`, `5m_20deg`); NaN (null) when none.
    pub precision: BTreeMap<String, f64>,
    /// LOCALIZED answers more than (5 m, 20 deg) off: the confident wrong poses.
    pub localized_wrong: usize,
    /// Of those, the ones with confidence above 0.9 (issue 41's worst failure).
    pub localized_wrong_above_0_9: usize,
    /// Out-of-map queries (`--negatives`), when given.
    pub negatives: Option<NegativesReport>,
    /// Calibration of `confidence` against "within (1 m, 10 deg)" over every answer with a pose
    /// estimate (in-map and out-of-map).
    pub calibration: CalibrationReport,
    /// Precision and recall as the LOCALIZED threshold on the confidence varies.
    pub precision_recall: Vec<CurvePoint>,
    /// The LOCALIZED threshold the localiser used (NaN when unknown, e.g. remote).
    pub min_confidence: f64,
    /// The radius of the prior sent with each in-map query (`--prior-radius`), when one was.
    pub prior_radius_m: Option<f64>,
    /// Answers by the path that produced them (`GLOBAL`, `PRIOR`, `TRACKING`; `UNKNOWN` for failed
    /// requests and servers that do not say).
    pub modes: BTreeMap<String, usize>,
    /// How well the reported covariances describe the position errors of the in-map LOCALIZED
    /// answers that carry one.
    pub covariance: CovarianceReport,
    /// Each in-map query's outcome, in evaluation order (for plots; not in the JSON).
    #[serde(skip)]
    pub per_query: Vec<QueryOutcome>,
    /// (scene, position in metres) of every camera of the map in the evaluated scenes: the dataset's
    /// database views it holds, and with an empty scene name its images from recordings, which lie
    /// in the dataset's world frame (for plots; not in the JSON).
    #[serde(skip)]
    pub map_positions_m: Vec<(String, [f64; 3])>,
}

/// Consistency of the reported covariances with the true position errors (the NEES test of
/// estimation theory, Bar-Shalom et al., 2001, restricted to position).
#[derive(Debug, Clone, Default, Serialize)]
pub struct CovarianceReport {
    /// In-map LOCALIZED answers with a covariance.
    pub answers: usize,
    /// Share of them whose position error lies inside the covariance's 99% ellipsoid (squared
    /// Mahalanobis distance at most 11.34, the chi-square quantile for 3 dof); 0.99 when consistent,
    /// NaN (null) with no answer. Covariances that are not positive definite are left out.
    pub within_99: f64,
    /// Median Mahalanobis distance of the position errors (about 1.54 when consistent).
    pub median_mahalanobis: f64,
    /// Median position standard deviation, sqrt(trace / 3), metres.
    pub median_sigma_m: f64,
}

/// Chi-square 0.99 quantile for 3 degrees of freedom.
const CHI2_3_99: f64 = 11.345;

/// [`CovarianceReport`] of (position error in the map frame, metres; 6x6 covariance) pairs.
pub fn covariance_report(answers: &[(nalgebra::Vector3<f64>, [f64; 36])]) -> CovarianceReport {
    let mut d: Vec<f64> = Vec::new();
    let mut sigma: Vec<f64> = Vec::new();
    for (e, c) in answers {
        let m = nalgebra::Matrix3::from_fn(|r, k| c[r * 6 + k]);
        // A covariance that is not finite or not positive definite (a remote server's, say)
        // describes nothing: such answers are left out rather than counted as inside.
        let Some(chol) = nalgebra::Cholesky::new(m) else {
            continue;
        };
        let q = e.dot(&chol.solve(e));
        if !q.is_finite() {
            continue;
        }
        d.push(q.sqrt());
        sigma.push((m.trace() / 3.0).sqrt());
    }
    let median = |v: &mut Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v.get(v.len() / 2).copied().unwrap_or(f64::NAN)
    };
    let median_mahalanobis = median(&mut d);
    CovarianceReport {
        answers: d.len(),
        within_99: if d.is_empty() {
            f64::NAN
        } else {
            d.iter().filter(|&&x| x * x <= CHI2_3_99).count() as f64 / d.len() as f64
        },
        median_mahalanobis,
        median_sigma_m: median(&mut sigma),
    }
}

/// How often an answer changes under a small perturbation of its query (issue 41, `pntr eval
/// --stability`), per perturbation. Errors are against the ground truth; an out-of-map query has
/// none, and every LOCALIZED answer to it is wrong.
#[derive(Debug, Clone, Default, Serialize)]
pub struct StabilityCounts {
    /// Query pairs compared (the query as rendered and perturbed).
    pub queries: usize,
    /// The status changed (LOCALIZED <-> NOT_LOCALIZED).
    pub status_changed: usize,
    /// Both LOCALIZED, and the poses differ by more than 0.25 m or 2 degrees.
    pub pose_moved: usize,
    /// The query was NOT_LOCALIZED or right (within 1 m and 10 degrees), its perturbed copy
    /// LOCALIZED and wrong: the failure a robot must never see.
    pub became_wrong: usize,
    /// Perturbed answers LOCALIZED more than 5 m or 20 degrees off with confidence above 0.9.
    pub confident_wrong: usize,
    /// Of those, the ones whose query as rendered was not such an answer: a perturbation moved it
    /// to a confident wrong pose (issue 41's criterion).
    pub became_confident_wrong: usize,
}

impl StabilityCounts {
    /// Count one pair: `base` the answer to the query, `perturbed` to its perturbed copy, `truth`
    /// the query's world_from_camera (dataset frame and axes, as the answers' poses), `None` for an
    /// out-of-map query.
    pub fn add(&mut self, base: &Answer, perturbed: &Answer, truth: Option<&Isometry3<f64>>) {
        let localized = |a: &Answer| a.status == Some(Status::Localized) && a.pose.is_some();
        let error = |a: &Answer| match (truth, a.pose) {
            (Some(g), Some(p)) => Some(pose_error(&p, g, false)),
            _ => None,
        };
        let wrong = |a: &Answer| localized(a) && error(a).is_none_or(|(m, d)| m > 1.0 || d > 10.0);
        self.queries += 1;
        self.status_changed += (localized(base) != localized(perturbed)) as usize;
        if let (true, true, Some(p), Some(q)) = (
            localized(base),
            localized(perturbed),
            base.pose,
            perturbed.pose,
        ) {
            let (m, d) = pose_error(&p, &q, false);
            self.pose_moved += (m > 0.25 || d > 2.0) as usize;
        }
        self.became_wrong += (!wrong(base) && wrong(perturbed)) as usize;
        let confident_wrong = |a: &Answer| {
            localized(a) && a.confidence > 0.9 && error(a).is_none_or(|(m, d)| m > 5.0 || d > 20.0)
        };
        self.confident_wrong += confident_wrong(perturbed) as usize;
        self.became_confident_wrong +=
            (confident_wrong(perturbed) && !confident_wrong(base)) as usize;
    }
}

/// One in-map query's outcome.
#[derive(Debug, Clone, Serialize)]
pub struct QueryOutcome {
    /// Query id (`scene/pointN/qI`).
    pub id: String,
    /// Ground-truth camera position, map frame, metres.
    pub position_m: [f64; 3],
    /// The ground-truth pose `world_from_camera` (map frame, camera axes of the dataset: Habitat's
    /// x right, y up, z backward) as `[tx, ty, tz, qx, qy, qz, qw]`, metres (TUM order).
    pub world_from_camera: [f64; 7],
    /// The best pose found (LOCALIZED or not) in the same form; `None` without an estimate. With
    /// the ground truth, it lets a failure be rendered or plotted where the localiser put it.
    pub estimate_world_from_camera: Option<[f64; 7]>,
    /// (metres, degrees) error of the LOCALIZED pose; `None` when not localized.
    pub error: Option<(f64, f64)>,
    /// (metres, degrees) error of the best pose found, LOCALIZED or not.
    pub estimate_error: Option<(f64, f64)>,
    /// Where the best pose found lies from the true camera, metres, in the true camera's own axes
    /// (Habitat: x right, y up, z backward); `None` without an estimate. Errors that run along one
    /// axis by a fixed length (a texture's period, a room's symmetry) show here.
    pub estimate_offset_camera_m: Option<[f64; 3]>,
    /// (metres, degrees) error of the top retrieved database pose used as the answer.
    pub retrieval_error: Option<(f64, f64)>,
    /// The calibrated confidence.
    pub confidence: f64,
    /// Position (0 = first) of the first retrieved image of the query's own Point among the
    /// candidates retrieval gave the matcher; `None` when none of them is.
    pub right_point_rank: Option<usize>,
    /// Why the query is NOT_LOCALIZED, as the localiser said.
    pub reason: Option<String>,
}

/// How a localiser answered queries from places the map does not cover.
#[derive(Debug, Clone, Default, Serialize)]
pub struct NegativesReport {
    /// Out-of-map queries sent.
    pub queries: usize,
    /// Of which answered LOCALIZED (every one is a false positive).
    pub localized: usize,
    /// `localized / queries`.
    pub false_positive_rate: f64,
}

/// Expected calibration error and the reliability bins.
#[derive(Debug, Clone, Default, Serialize)]
pub struct CalibrationReport {
    /// Expected calibration error (10 equal-width bins).
    pub ece: f64,
    /// Answers scored.
    pub answers: usize,
    /// The bins.
    pub bins: Vec<pntr_pipeline::calibration::Bin>,
}

/// One point of the precision/recall curve.
#[derive(Debug, Clone, Default, Serialize)]
pub struct CurvePoint {
    /// Threshold on the confidence.
    pub threshold: f64,
    /// In-map queries whose estimate would be LOCALIZED at this threshold, over all in-map queries.
    pub localized_share: f64,
    /// Share of those within (1 m, 10 deg).
    pub precision_1m_10deg: f64,
    /// In-map queries LOCALIZED within (1 m, 10 deg), over all in-map queries.
    pub recall_1m_10deg: f64,
    /// In-map queries LOCALIZED within (0.25 m, 2 deg), over all in-map queries.
    pub recall_0_25m_2deg: f64,
    /// Out-of-map queries that would be LOCALIZED, over all out-of-map queries.
    pub false_positive_rate: f64,
}

/// Share of a grid of query pixels that reappear in `db` at a consistent depth: the ground-truth
/// overlap used to name the best database view of a query. `cameras` are the query's and the
/// database view's (distortion is ignored: a grid sample, not a measurement).
pub fn overlap(
    cameras: (&Intrinsics, &Intrinsics),
    q_pose: &Isometry3<f64>,
    q_depth: &DepthMap,
    db_pose: &Isometry3<f64>,
    db_depth: &DepthMap,
) -> f64 {
    let (kq, kd) = cameras;
    let world_from_q = convert_axes(q_pose, CameraAxes::Habitat, CameraAxes::OpenCv);
    let db_from_world = convert_axes(db_pose, CameraAxes::Habitat, CameraAxes::OpenCv).inverse();
    let (mut seen, mut valid) = (0usize, 0usize);
    // About 16x16 samples whatever the query's resolution.
    let step = (q_depth.width.max(q_depth.height) / 16).max(1);
    for r in (step / 2..q_depth.height).step_by(step as usize) {
        for c in (step / 2..q_depth.width).step_by(step as usize) {
            let Some(z) = q_depth.get(c, r) else { continue };
            valid += 1;
            let p: Point3<f64> =
                db_from_world * (world_from_q * kq.backproject(c as f64, r as f64, z as f64));
            if let Some(px) = kd.project(&p) {
                let (uc, vr) = (px.x.round(), px.y.round());
                if uc >= 0.0 && vr >= 0.0 {
                    if let Some(d) = db_depth.get(uc as u32, vr as u32) {
                        seen += ((d as f64 - p.z).abs() < 0.05 + 0.02 * p.z) as usize;
                    }
                }
            }
        }
    }
    seen as f64 / valid.max(1) as f64
}

/// Options of [`run`].
#[derive(Debug, Clone, Default)]
pub struct EvalOptions {
    /// Use the published (flawed) metric.
    pub legacy: bool,
    /// Evaluate at most this many queries, evenly spaced (0 = all).
    pub max_queries: usize,
    /// Preset name for the report.
    pub preset: String,
    /// Scenes the map does not cover: their queries are sent too, and every LOCALIZED answer is false.
    pub negatives: Vec<SceneEntry>,
    /// Evaluate at most this many negative queries, evenly spaced (0 = all).
    pub max_negatives: usize,
    /// The localiser's LOCALIZED threshold, for the report (else the one answers report, else NaN).
    pub min_confidence: Option<f64>,
    /// Send each in-map query a prior of this radius, metres, whose centre lies half the radius
    /// from the true position in a direction that varies from query to query (a robot's odometry is
    /// off by about that much). Out-of-map queries get none (there is no true position to be near).
    pub prior_radius_m: Option<f64>,
    /// The map images' own poses by id (`world_from_camera`, Habitat axes), for maps whose images
    /// are not the dataset's database views (a map built from a recording of the same place): the
    /// retrieval rows then use them (the Point rows cannot, as the map's places are not the
    /// dataset's Points).
    pub map_images: Vec<(String, Isometry3<f64>)>,
}

/// The prior [`run`] sends query number `n` at true position `truth_m`: a region of `radius_m` whose
/// centre is half the radius away along a direction of the golden-angle spiral (deterministic, evenly
/// spread over the sphere).
pub fn prior_around(
    truth_m: &Vector3<f64>,
    radius_m: f64,
    n: usize,
) -> Result<Region, PipelineError> {
    let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
    let k = (n % 64) as f64;
    let z = 1.0 - (2.0 * k + 1.0) / 64.0;
    let r = (1.0 - z * z).sqrt();
    let dir = Vector3::new(r * (golden * k).cos(), z, r * (golden * k).sin());
    Region::new(truth_m + dir * (0.5 * radius_m), radius_m)
}

/// What [`run`] localises with: a query and the prior to send with it (`--prior-radius`), to an
/// answer.
pub type Localizer<'a> = dyn FnMut(&Query, Option<&Region>) -> Result<Answer, PipelineError> + 'a;

/// What [`run_observed`] shows each answered query to: the query, its ground truth
/// (`world_from_camera`, dataset frame and Habitat axes; `None` for an out-of-map query) and the
/// answer (a failed request as a default answer).
pub type Observer<'a> = dyn FnMut(&Query, Option<&Isometry3<f64>>, &Answer) + 'a;

/// Localise every query of `scenes` with `localize` and score the answers.
pub fn run(
    scenes: &[&SceneEntry],
    opts: &EvalOptions,
    localize: &mut Localizer<'_>,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<EvalReport, PipelineError> {
    run_observed(scenes, opts, localize, progress, &mut |_, _, _| {})
}

/// [`run`], showing every query and its answer to `observe` as it goes (a recording).
pub fn run_observed(
    scenes: &[&SceneEntry],
    opts: &EvalOptions,
    localize: &mut Localizer<'_>,
    progress: &mut dyn FnMut(usize, usize),
    observe: &mut Observer<'_>,
) -> Result<EvalReport, PipelineError> {
    // Every database pose by id, for the retrieval-only row.
    let mut db_pose: BTreeMap<String, (Isometry3<f64>, String, u32)> = BTreeMap::new();
    let mut all = Vec::new();
    let mut readers = Vec::new();
    for s in scenes {
        for p in &s.points {
            let r = p.open()?;
            for (j, pose) in r.poses(Role::Database).iter().enumerate() {
                db_pose.insert(p.db_image_id(j), (*pose, p.scene.clone(), p.index));
            }
            for qi in 0..r.count(Role::Query) {
                all.push((readers.len(), qi));
            }
            readers.push((p.clone(), r));
        }
    }
    // A map whose images are none of the dataset's views (built from a recording): its places are
    // not the dataset's Points, so the Point and view rows do not apply.
    let foreign_map = !opts.map_images.is_empty()
        && opts
            .map_images
            .iter()
            .all(|(id, _)| !db_pose.contains_key(id));
    for (id, pose) in &opts.map_images {
        db_pose
            .entry(id.clone())
            .or_insert_with(|| (*pose, String::new(), u32::MAX));
    }
    let picked = evenly_spaced(all, opts.max_queries);
    let (mut errors, mut retrieval_errors) = (Vec::new(), Vec::new());
    let (mut localized, mut failed) = (0, 0);
    let mut sums = StageTimes::default();
    let mut rr = RetrievalRecall::default();
    let mut db_depths: BTreeMap<usize, Vec<DepthMap>> = BTreeMap::new();
    // (confidence, error of the best estimate, localized) per in-map query.
    let mut scored: Vec<Scored> = Vec::new();
    let mut reported_threshold = None;
    let mut modes: BTreeMap<String, usize> = BTreeMap::new();
    let mut per_query: Vec<QueryOutcome> = Vec::new();
    let mut covariances: Vec<(nalgebra::Vector3<f64>, [f64; 36])> = Vec::new();
    let t0 = Instant::now();
    for (n, &(pi, qi)) in picked.iter().enumerate() {
        let (entry, reader) = &readers[pi];
        let v = reader.view(Role::Query, qi)?;
        let gt = v.world_from_camera;
        if let std::collections::btree_map::Entry::Vacant(e) = db_depths.entry(pi) {
            let d = (0..reader.count(Role::Database))
                .map(|j| reader.view(Role::Database, j).map(|v| v.depth))
                .collect::<Result<Vec<_>, _>>()?;
            // Keep the depths of recent Points only: queries come Point by Point.
            e.insert(d);
        }
        db_depths.retain(|&key, _| key + 2 > pi);
        let best_view = db_depths[&pi]
            .iter()
            .enumerate()
            .map(|(j, d)| {
                (
                    j,
                    overlap(
                        (&v.intrinsics, &reader.camera(Role::Database)),
                        &gt,
                        &v.depth,
                        &reader.poses(Role::Database)[j],
                        d,
                    ),
                )
            })
            .max_by(|a, b| a.1.total_cmp(&b.1))
            .map(|(j, _)| entry.db_image_id(j));
        let q = Query {
            rgb: v.rgb,
            depth: v.depth,
            intrinsics: v.intrinsics,
        };
        let prior = match opts.prior_radius_m {
            Some(r) => Some(prior_around(&gt.translation.vector, r, n)?),
            None => None,
        };
        let a = match localize(&q, prior.as_ref()) {
            Ok(a) => a,
            Err(e) => {
                tracing::warn!("query {}: {e}", entry.query_id(qi));
                failed += 1;
                Answer::default()
            }
        };
        observe(&q, Some(&gt), &a);
        if a.status == Some(Status::Localized) {
            localized += 1;
        }
        *modes
            .entry(a.mode.map_or("UNKNOWN", |m| m.name()).to_string())
            .or_default() += 1;
        errors.push(a.pose.map(|p| pose_error(&p, &gt, opts.legacy)));
        if let (Some(p), Some(c)) = (a.pose, a.covariance) {
            covariances.push((p.translation.vector - gt.translation.vector, c));
        }
        reported_threshold = a.threshold.or(reported_threshold);
        scored.push((
            a.confidence,
            a.estimate.or(a.pose).map(|p| pose_error(&p, &gt, false)),
            a.status == Some(Status::Localized),
        ));
        per_query.push(QueryOutcome {
            id: entry.query_id(qi),
            position_m: gt.translation.vector.into(),
            world_from_camera: tum_pose(&gt),
            estimate_world_from_camera: a.estimate.or(a.pose).map(|p| tum_pose(&p)),
            error: *errors.last().expect("pushed above"),
            estimate_error: scored.last().and_then(|s| s.1),
            estimate_offset_camera_m: a.estimate.or(a.pose).map(|p| {
                (gt.rotation.inverse() * (p.translation.vector - gt.translation.vector)).into()
            }),
            retrieval_error: None,
            confidence: a.confidence,
            right_point_rank: None,
            reason: a.reason.clone(),
        });
        let same_point = |id: &String| {
            db_pose
                .get(id)
                .is_some_and(|(_, s, pt)| *s == entry.scene && *pt == entry.index)
        };
        retrieval_errors.push(
            a.retrieved
                .first()
                .and_then(|id| db_pose.get(id))
                .map(|(p, _, _)| pose_error(p, &gt, opts.legacy)),
        );
        if let Some(last) = per_query.last_mut() {
            last.retrieval_error = *retrieval_errors.last().expect("pushed above");
            last.right_point_rank = a.retrieved.iter().position(same_point);
        }
        rr.point_at_1 += a.retrieved.first().is_some_and(same_point) as usize as f64;
        let chosen = a.matched.as_ref().or(a.retrieved.first());
        rr.reranked_point_at_1 += chosen.is_some_and(same_point) as usize as f64;
        rr.point_at_5 += a.retrieved.iter().take(5).any(same_point) as usize as f64;
        if let Some(b) = &best_view {
            rr.view_at_1 += (a.retrieved.first() == Some(b)) as usize as f64;
            rr.reranked_view_at_1 += (chosen == Some(b)) as usize as f64;
            rr.view_at_5 += a.retrieved.iter().take(5).any(|x| x == b) as usize as f64;
        }
        sums.resampling += a.times.resampling;
        sums.extraction += a.times.extraction;
        sums.retrieval += a.times.retrieval;
        sums.matching += a.times.matching;
        sums.registration += a.times.registration;
        sums.verification += a.times.verification;
        sums.total += a.times.total;
        progress(n + 1, picked.len());
    }
    let wall = t0.elapsed().as_secs_f64();
    // Out-of-map queries: nothing they return can be right.
    let mut negatives: Vec<(f64, bool)> = Vec::new();
    if !opts.negatives.is_empty() {
        let mut views = QueryViews::default();
        for (p, qi) in &query_list(&opts.negatives, opts.max_negatives)? {
            let v = views.view(p, *qi)?;
            let q = Query {
                rgb: v.rgb,
                depth: v.depth,
                intrinsics: v.intrinsics,
            };
            match localize(&q, None) {
                Ok(a) => {
                    observe(&q, None, &a);
                    negatives.push((a.confidence, a.status == Some(Status::Localized)))
                }
                Err(e) => {
                    tracing::warn!("negative query {}: {e}", p.query_id(*qi));
                    negatives.push((0.0, false));
                }
            }
        }
    }
    let nq = picked.len().max(1) as f64;
    for x in [
        &mut rr.point_at_1,
        &mut rr.point_at_5,
        &mut rr.view_at_1,
        &mut rr.view_at_5,
        &mut rr.reranked_point_at_1,
        &mut rr.reranked_view_at_1,
    ] {
        *x = if foreign_map { f64::NAN } else { *x / nq };
    }
    let stage_ms = [
        ("resampling", sums.resampling),
        ("extraction", sums.extraction),
        ("retrieval", sums.retrieval),
        ("matching", sums.matching),
        ("registration", sums.registration),
        ("verification", sums.verification),
        ("total", sums.total),
    ]
    .into_iter()
    .map(|(k, s)| (k.to_string(), 1e3 * s / nq))
    .collect();
    Ok(EvalReport {
        queries: picked.len(),
        localized,
        recall: recall(&errors),
        retrieval_only: recall(&retrieval_errors),
        stage_ms,
        fps: picked.len() as f64 / wall.max(1e-9),
        metric: if opts.legacy {
            "legacy-folded (published code; not a correct metric)".into()
        } else {
            "geodesic".into()
        },
        retrieval: rr,
        failed_requests: failed,
        preset: opts.preset.clone(),
        precision: precision(&errors),
        localized_wrong: errors
            .iter()
            .flatten()
            .filter(|e| !(e.0 <= 5.0 && e.1 <= 20.0))
            .count(),
        localized_wrong_above_0_9: scored
            .iter()
            .filter(|s| s.2 && s.0 > 0.9)
            .filter(|s| s.1.is_some_and(|e| !(e.0 <= 5.0 && e.1 <= 20.0)))
            .count(),
        negatives: (!opts.negatives.is_empty()).then(|| NegativesReport {
            queries: negatives.len(),
            localized: negatives.iter().filter(|n| n.1).count(),
            false_positive_rate: negatives.iter().filter(|n| n.1).count() as f64
                / negatives.len().max(1) as f64,
        }),
        calibration: {
            let labelled: Vec<(f64, bool)> = scored
                .iter()
                .filter(|s| s.1.is_some())
                .map(|s| (s.0, s.1.is_some_and(|e| e.0 <= 1.0 && e.1 <= 10.0)))
                .chain(negatives.iter().filter(|n| n.0 > 0.0).map(|n| (n.0, false)))
                .collect();
            let (ece, bins) = pntr_pipeline::calibration::ece(&labelled, 10);
            CalibrationReport {
                ece,
                answers: labelled.len(),
                bins,
            }
        },
        precision_recall: curve(
            &scored,
            &negatives,
            opts.min_confidence.or(reported_threshold),
        ),
        min_confidence: opts
            .min_confidence
            .or(reported_threshold)
            .unwrap_or(f64::NAN),
        prior_radius_m: opts.prior_radius_m,
        modes,
        covariance: covariance_report(&covariances),
        per_query,
        // The cameras the map holds: its own images when it names them (a map from recordings, a
        // map extended by them, one of some of the dataset's views), every database view otherwise.
        map_positions_m: {
            let held: std::collections::HashSet<&str> =
                opts.map_images.iter().map(|(id, _)| id.as_str()).collect();
            db_pose
                .iter()
                .filter(|(id, _)| held.is_empty() || held.contains(id.as_str()))
                .map(|(_, (p, scene, _))| (scene.clone(), p.translation.vector.into()))
                .collect()
        },
    })
}

/// Share of LOCALIZED answers (`Some` errors) within (1 m, 10 deg) and (5 m, 20 deg); NaN (null in
/// JSON) when nothing was LOCALIZED.
pub fn precision(errors: &[Option<(f64, f64)>]) -> BTreeMap<String, f64> {
    let ok: Vec<&(f64, f64)> = errors.iter().flatten().collect();
    let share = |m: f64, d: f64| {
        if ok.is_empty() {
            f64::NAN
        } else {
            ok.iter().filter(|e| e.0 <= m && e.1 <= d).count() as f64 / ok.len() as f64
        }
    };
    BTreeMap::from([
        ("1m_10deg".to_string(), share(1.0, 10.0)),
        ("5m_20deg".to_string(), share(5.0, 20.0)),
    ])
}

/// One in-map answer for the curve: confidence, error of the best estimate, LOCALIZED.
type Scored = (f64, Option<(f64, f64)>, bool);

fn curve(scored: &[Scored], negatives: &[(f64, bool)], used: Option<f64>) -> Vec<CurvePoint> {
    let mut thresholds: Vec<f64> = (0..20).map(|i| i as f64 * 0.05).collect();
    thresholds.extend([0.97, 0.99]);
    thresholds.extend(used);
    thresholds.sort_by(f64::total_cmp);
    thresholds.dedup();
    let n = scored.len().max(1) as f64;
    thresholds
        .into_iter()
        .map(|t| {
            let kept: Vec<&(f64, f64)> = scored
                .iter()
                .filter(|s| s.0 >= t && s.0 > 0.0)
                .filter_map(|s| s.1.as_ref())
                .collect();
            let right = kept.iter().filter(|e| e.0 <= 1.0 && e.1 <= 10.0).count();
            let fine = kept.iter().filter(|e| e.0 <= 0.25 && e.1 <= 2.0).count();
            CurvePoint {
                threshold: t,
                localized_share: kept.len() as f64 / n,
                precision_1m_10deg: if kept.is_empty() {
                    1.0
                } else {
                    right as f64 / kept.len() as f64
                },
                recall_1m_10deg: right as f64 / n,
                recall_0_25m_2deg: fine as f64 / n,
                false_positive_rate: negatives.iter().filter(|x| x.0 >= t && x.0 > 0.0).count()
                    as f64
                    / negatives.len().max(1) as f64,
            }
        })
        .collect()
}

/// The recall rows as a text table (for the CLI).
pub fn table(report: &EvalReport) -> String {
    let mut s = format!(
        "{} queries, {} localized, metric {}\n",
        report.queries, report.localized, report.metric
    );
    s += &format!("{:<16}", "");
    for k in RECALL_KEYS {
        s += &format!("{k:>11}");
    }
    s.push('\n');
    for (name, row) in [
        ("pipeline", &report.recall),
        ("retrieval only", &report.retrieval_only),
    ] {
        s += &format!("{name:<16}");
        for k in RECALL_KEYS {
            s += &format!("{:>11.3}", row[k]);
        }
        s.push('\n');
    }
    let r = &report.retrieval;
    if r.point_at_1.is_nan() {
        s += "retrieval: right Point and best-overlap view n/a (the map's images are not the dataset's views)\n";
    } else {
        s += &format!(
            "retrieval: right Point @1 {:.3} @5 {:.3}; best-overlap view @1 {:.3} @5 {:.3}; after re-ranking: Point {:.3}, view {:.3}\n",
            r.point_at_1, r.point_at_5, r.view_at_1, r.view_at_5, r.reranked_point_at_1, r.reranked_view_at_1
        );
    }
    s += &format!(
        "precision of LOCALIZED answers: (1m, 10deg) {:.4} (5m, 20deg) {:.4}; {} LOCALIZED more than 5 m / 20 deg off ({} with confidence above 0.9)\n",
        report.precision["1m_10deg"], report.precision["5m_20deg"], report.localized_wrong, report.localized_wrong_above_0_9
    );
    if let Some(n) = &report.negatives {
        s += &format!(
            "out-of-map queries: {} sent, {} LOCALIZED (false-positive rate {:.4})\n",
            n.queries, n.localized, n.false_positive_rate
        );
    }
    if let Some(r) = report.prior_radius_m {
        let by_mode: Vec<String> = report
            .modes
            .iter()
            .map(|(m, n)| format!("{m} {n}"))
            .collect();
        s += &format!(
            "prior of {r} m radius sent with each query; answered by: {}\n",
            by_mode.join(", ")
        );
    }
    s += &format!(
        "confidence: expected calibration error {:.3} over {} answers; LOCALIZED threshold {:.2}\n",
        report.calibration.ece, report.calibration.answers, report.min_confidence
    );
    let c = &report.covariance;
    if c.answers > 0 {
        s += &format!(
            "covariance: position error inside its 99% ellipsoid for {:.3} of {} LOCALIZED answers (0.99 if consistent); median Mahalanobis distance {:.2} (1.54 if consistent), median sigma {:.3} m\n",
            c.within_99, c.answers, c.median_mahalanobis, c.median_sigma_m
        );
    }
    s += "mean ms per query:";
    for k in [
        "resampling",
        "extraction",
        "retrieval",
        "matching",
        "registration",
        "verification",
        "total",
    ] {
        // Resampling is listed only when queries came from another camera than the map's.
        let ms = report.stage_ms.get(k).copied().unwrap_or(0.0);
        if k != "resampling" || ms >= 0.05 {
            s += &format!(" {k} {ms:.1}");
        }
    }
    s += &format!("; {:.2} queries/s\n", report.fps);
    if report.stage_ms.get("matching").is_some_and(|&m| m < 0.05) {
        s += MATCHING_NOTE;
        s.push('\n');
    }
    s
}

/// Why `matching` reads 0.0 ms for MNN presets, printed wherever that figure is.
pub const MATCHING_NOTE: &str = "(matching 0.0 ms: with an MNN matcher the candidates are matched inside retrieval's keypoint vote, so their time is in retrieval)";

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion, Vector3};

    #[test]
    fn stability_counts_flips_moves_and_confident_wrong_answers() {
        let truth = Isometry3::identity();
        let at = |x: f64, deg: f64, localized: bool, confidence: f64| Answer {
            status: Some(if localized {
                Status::Localized
            } else {
                Status::NotLocalized
            }),
            pose: localized.then(|| {
                Isometry3::from_parts(
                    Translation3::new(x, 0.0, 0.0),
                    UnitQuaternion::from_axis_angle(&Vector3::y_axis(), deg.to_radians()),
                )
            }),
            confidence,
            ..Answer::default()
        };
        let mut c = StabilityCounts::default();
        // Right and steady: nothing counted but the pair.
        c.add(
            &at(0.01, 0.2, true, 0.99),
            &at(0.02, 0.3, true, 0.99),
            Some(&truth),
        );
        // Right, then moved 0.3 m but still right.
        c.add(
            &at(0.01, 0.2, true, 0.99),
            &at(0.31, 0.2, true, 0.99),
            Some(&truth),
        );
        // Refused, then LOCALIZED 8 m off with confidence 0.97: the worst flip.
        c.add(
            &at(0.0, 0.0, false, 0.2),
            &at(8.0, 0.0, true, 0.97),
            Some(&truth),
        );
        // Out of the map: any LOCALIZED answer is wrong.
        c.add(&at(0.0, 0.0, false, 0.1), &at(0.0, 0.0, true, 0.95), None);
        // Confidently wrong already as rendered: counted, but not as a perturbation's doing.
        c.add(
            &at(9.0, 0.0, true, 0.96),
            &at(9.0, 0.1, true, 0.97),
            Some(&truth),
        );
        assert_eq!(c.queries, 5);
        assert_eq!(c.status_changed, 2);
        assert_eq!(c.pose_moved, 1);
        assert_eq!(c.became_wrong, 2);
        assert_eq!(c.confident_wrong, 3);
        assert_eq!(c.became_confident_wrong, 2);
    }

    #[test]
    fn failures_stay_in_the_denominator_and_the_angle_is_geodesic() {
        let gt = Isometry3::identity();
        let turned = Isometry3::from_parts(
            Translation3::new(0.1, 0.0, 0.0),
            UnitQuaternion::from_axis_angle(&Vector3::y_axis(), 170f64.to_radians()),
        );
        let (dt, dr) = pose_error(&turned, &gt, false);
        assert!((dt - 0.1).abs() < 1e-9 && (dr - 170.0).abs() < 1e-6);
        // The folded legacy angle hides a yaw error near 180 degrees once the axes flip is applied.
        let (_, legacy) = pose_error(&gt, &gt, true);
        assert!(legacy < 1e-6, "identity in flipped axes folds to {legacy}");
        let r = recall(&[Some((0.1, 1.0)), None, Some((2.0, 30.0)), None]);
        assert_eq!(r["0.25m_2deg"], 0.25);
        assert_eq!(r["5m_20deg"], 0.25);
        assert_eq!(r["5m"], 0.5);
        assert_eq!(r.len(), 8);
    }
}

/// Errors of an estimated trajectory against the ground truth, both in the map frame (absolute
/// localization: no alignment is fitted, unlike a SLAM evaluation).
#[derive(Debug, Clone, Copy, Default, Serialize)]
pub struct TrajectoryErrors {
    /// Frames with an estimate and a ground-truth pose.
    pub compared: usize,
    /// Absolute trajectory error: RMSE of the position errors, metres.
    pub ate_rmse_m: f64,
    /// Largest position error, metres.
    pub max_error_m: f64,
    /// Frames whose position is more than 1 m off.
    pub over_1m: usize,
    /// Relative pose error between consecutive estimated frames (both estimated): RMSE of the
    /// translation part, metres.
    pub rpe_trans_rmse_m: f64,
    /// ... and of the rotation angle, degrees.
    pub rpe_rot_rmse_deg: f64,
    /// Consecutive pairs the relative error is measured on.
    pub rpe_pairs: usize,
}

/// One frame of a trajectory: the estimate (`None` when not localized) and the ground truth (`None`
/// when unknown), both `world_from_camera`.
pub type EstimateAndTruth = (Option<Isometry3<f64>>, Option<Isometry3<f64>>);

/// ATE and RPE (Sturm et al., the TUM RGB-D benchmark) of `frames`: per frame in time order, the
/// estimate (`None` when not localized) and the ground truth (`None` when unknown). NaN when nothing
/// can be compared.
pub fn trajectory_errors(frames: &[EstimateAndTruth]) -> TrajectoryErrors {
    let mut sq = 0.0;
    let mut out = TrajectoryErrors::default();
    for (est, gt) in frames {
        if let (Some(e), Some(g)) = (est, gt) {
            let d = (e.translation.vector - g.translation.vector).norm();
            sq += d * d;
            out.compared += 1;
            out.max_error_m = out.max_error_m.max(d);
            out.over_1m += (d > 1.0) as usize;
        }
    }
    out.ate_rmse_m = (sq / out.compared as f64).sqrt();
    let (mut st, mut sr) = (0.0, 0.0);
    for w in frames.windows(2) {
        if let ((Some(e0), Some(g0)), (Some(e1), Some(g1))) = (w[0], w[1]) {
            let delta = (g0.inverse() * g1).inverse() * (e0.inverse() * e1);
            st += delta.translation.vector.norm_squared();
            sr += delta.rotation.angle().to_degrees().powi(2);
            out.rpe_pairs += 1;
        }
    }
    out.rpe_trans_rmse_m = (st / out.rpe_pairs as f64).sqrt();
    out.rpe_rot_rmse_deg = (sr / out.rpe_pairs as f64).sqrt();
    if out.compared == 0 {
        out.max_error_m = f64::NAN;
    }
    out
}

#[cfg(test)]
mod trajectory_tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion};

    #[test]
    fn ate_and_rpe_of_known_offsets() {
        let gt = |i: usize| {
            Isometry3::from_parts(
                Translation3::new(0.05 * i as f64, 1.25, 0.0),
                UnitQuaternion::from_euler_angles(0.0, 0.01 * i as f64, 0.0),
            )
        };
        // A constant 3 cm offset along x: ATE 0.03, no relative error; one frame lost, one 2 m off.
        let mut frames: Vec<_> = (0..10)
            .map(|i| {
                let mut e = gt(i);
                e.translation.vector.x += 0.03;
                (Some(e), Some(gt(i)))
            })
            .collect();
        let t = trajectory_errors(&frames);
        assert!((t.ate_rmse_m - 0.03).abs() < 1e-12, "{t:?}");
        assert!(
            t.rpe_trans_rmse_m < 1e-9 && t.rpe_rot_rmse_deg < 1e-6,
            "{t:?}"
        );
        assert_eq!((t.compared, t.rpe_pairs, t.over_1m), (10, 9, 0));
        frames[4].0 = None;
        frames[7].0.as_mut().unwrap().translation.vector.z += 2.0;
        let t = trajectory_errors(&frames);
        assert_eq!((t.compared, t.rpe_pairs, t.over_1m), (9, 7, 1));
        assert!(t.max_error_m > 2.0 && t.ate_rmse_m > 0.6, "{t:?}");
        assert!(t.rpe_trans_rmse_m > 0.5, "{t:?}");
        let none = trajectory_errors(&[(None, Some(gt(0)))]);
        assert!(none.ate_rmse_m.is_nan() && none.max_error_m.is_nan());
    }
}

/// `pose` as `[tx, ty, tz, qx, qy, qz, qw]` (TUM order; the quaternion's sign chosen with qw >= 0).
fn tum_pose(pose: &Isometry3<f64>) -> [f64; 7] {
    let t = pose.translation.vector;
    let [w, x, y, z] = pntr_core::pose::canonical_wxyz(&pose.rotation);
    [t.x, t.y, t.z, x, y, z, w]
}
