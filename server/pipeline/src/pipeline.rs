//! The PNTR pipeline: one RGB-D query in, a pose out.
//!
//! extract the query's features once -> describe and retrieve the top-k database images -> (re-rank
//! the candidates by a cheap geometric check: mutual nearest neighbours on the descriptors already in
//! hand, back-projected and registered, scored by inliers) -> run the configured matcher on the best
//! candidate(s) -> back-project matched keypoints with both depths (a pair is kept only when both
//! sides have valid depth, so the lists stay aligned) -> register -> keep the candidate with the most
//! inliers -> `world_from_query = world_from_db * db_from_query`.
//!
//! Poses: the map stores `world_from_camera` with the dataset's camera axes (Habitat for HPointLoc);
//! back-projection and registration work in OpenCV axes; the answer is converted back, so it is in the
//! same frame and axes as the map's own poses.

use std::sync::Arc;
use std::time::Instant;

use nalgebra::{Isometry3, Point2, Vector3};
use pntr_core::{convert_axes, CameraAxes, DepthMap, Intrinsics, RgbImage};
use pntr_features::config::FeatureStage;
use pntr_features::mnn::Mnn;
use pntr_features::{Features, Matcher};
use pntr_registration::icp::{icp_matched, IcpParams};
use pntr_registration::pnp::{pnp_ransac, PnpParams};
use pntr_registration::teaser::{solve, TeaserParams};
use pntr_registration::Rigid;
use pntr_retrieval::index::Hit;
use serde::Serialize;

use crate::map::{keypoint_points, Map};
use crate::preset::{Preset, Solver};
use crate::PipelineError;

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
    /// A pose passed the checks.
    Localized,
    /// No candidate gave a valid registration with enough inliers.
    NotLocalized,
}

/// Seconds spent in each stage of one query.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct StageTimes {
    /// Feature extraction of the query.
    pub extraction: f64,
    /// Global descriptor and index search.
    pub retrieval: f64,
    /// Matching (cheap re-ranking matches and the final matcher).
    pub matching: f64,
    /// Back-projection and registration.
    pub registration: f64,
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
    /// `world_from_camera` of the query (map frame, map camera axes); `None` unless localized.
    pub pose: Option<Isometry3<f64>>,
    /// Heuristic confidence in 0..1: inlier ratio times a saturating inlier count (not calibrated).
    pub confidence: f64,
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
    /// with (descriptors from another extractor mean nothing to it).
    pub fn new(map: Arc<Map>, stage: FeatureStage, preset: Preset) -> Result<Self, PipelineError> {
        preset.validate()?;
        let built = &map.header.preset;
        if built.extractor != preset.extractor || built.global != preset.global {
            return Err(PipelineError::Config(format!(
                "the map was built with {} + {} (preset {}); preset {} uses {} + {}",
                built.global,
                built.extractor,
                built.name,
                preset.name,
                preset.global,
                preset.extractor
            )));
        }
        Ok(Self {
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
        })
    }

    /// Localise one query.
    pub fn localize(&self, q: &Query) -> Result<Localization, PipelineError> {
        let t0 = Instant::now();
        check_query(q)?;
        let mut times = StageTimes::default();
        let fq = self.stage.extractor.extract(&q.rgb)?;
        let t1 = Instant::now();
        times.extraction = (t1 - t0).as_secs_f64();
        let desc = self.map.retriever.describer.describe(&q.rgb, &fq)?;
        let hits = self.map.retriever.search(&desc, self.preset.candidates)?;
        times.retrieval = t1.elapsed().as_secs_f64();
        let (q_pts, _) = keypoint_points(&q.intrinsics, &q.depth, None, &fq.keypoints);
        let q_pts: Vec<Option<Vector3<f64>>> = q_pts
            .iter()
            .map(|p| {
                p[0].is_finite()
                    .then(|| Vector3::new(p[0] as f64, p[1] as f64, p[2] as f64))
            })
            .collect();

        let matcher_is_cheap = self.preset.matcher == "mnn";
        let mut finalists: Vec<(usize, usize)> =
            hits.iter().enumerate().map(|(r, h)| (h.id, r)).collect();
        let mut done: Vec<Candidate> = Vec::new();
        if self.preset.rerank && hits.len() > 1 {
            let mut scored = Vec::with_capacity(hits.len());
            for &(id, rank) in &finalists {
                let c = self.candidate(&fq, &q_pts, q, id, rank, &self.cheap, &mut times)?;
                scored.push(c);
            }
            scored.sort_by(|a, b| b.inliers.cmp(&a.inliers).then(a.rank.cmp(&b.rank)));
            scored.truncate(self.preset.final_candidates);
            if matcher_is_cheap {
                done = scored;
            } else {
                finalists = scored.iter().map(|c| (c.image, c.rank)).collect();
            }
        }
        if done.is_empty() {
            for &(id, rank) in &finalists {
                let c = self.candidate(
                    &fq,
                    &q_pts,
                    q,
                    id,
                    rank,
                    self.stage.matcher.as_ref(),
                    &mut times,
                )?;
                done.push(c);
            }
        }
        let best = done
            .into_iter()
            .filter(|c| c.db_from_query.is_some())
            .max_by(|a, b| a.inliers.cmp(&b.inliers).then(b.rank.cmp(&a.rank)));
        times.total = t0.elapsed().as_secs_f64();
        let top = hits.first().map(|h| h.id);
        Ok(match best {
            Some(c) if c.inliers >= self.preset.min_inliers => {
                let db = &self.map.images[c.image];
                let world_from_db = convert_axes(
                    &db.world_from_camera,
                    CameraAxes::Habitat,
                    CameraAxes::OpenCv,
                );
                let world_from_query = world_from_db * c.db_from_query.expect("filtered");
                let ratio = c.inliers as f64 / c.pairs.max(1) as f64;
                Localization {
                    status: Status::Localized,
                    reason: None,
                    pose: Some(convert_axes(
                        &world_from_query,
                        CameraAxes::OpenCv,
                        CameraAxes::Habitat,
                    )),
                    confidence: ratio * (1.0 - (-(c.inliers as f64) / 20.0).exp()),
                    inliers: c.inliers,
                    correspondences: c.pairs,
                    image: Some(c.image),
                    retrieved: hits,
                    times,
                }
            }
            other => Localization {
                status: Status::NotLocalized,
                reason: Some(match &other {
                    Some(c) => format!(
                        "{} inliers, fewer than {}",
                        c.inliers, self.preset.min_inliers
                    ),
                    None if hits.is_empty() => "the map is empty".into(),
                    None => "no candidate gave a valid registration".into(),
                }),
                pose: None,
                confidence: 0.0,
                inliers: other.as_ref().map_or(0, |c| c.inliers),
                correspondences: other.as_ref().map_or(0, |c| c.pairs),
                image: top,
                retrieved: hits,
                times,
            },
        })
    }

    /// Match the query against map image `id` and register.
    #[allow(clippy::too_many_arguments)]
    fn candidate(
        &self,
        fq: &Features,
        q_pts: &[Option<Vector3<f64>>],
        q: &Query,
        id: usize,
        rank: usize,
        matcher: &dyn Matcher,
        times: &mut StageTimes,
    ) -> Result<Candidate, PipelineError> {
        let t0 = Instant::now();
        let db = &self.map.images[id];
        let m = matcher.match_features(fq, &db.features())?;
        let t1 = Instant::now();
        times.matching += (t1 - t0).as_secs_f64();
        let mut c = Candidate {
            image: id,
            rank,
            db_from_query: None,
            inliers: 0,
            pairs: 0,
            reason: None,
        };
        match self.preset.solver {
            Solver::Pnp => {
                let (mut pts, mut px) = (Vec::new(), Vec::new());
                for &(a, b) in &m.pairs {
                    if let Some(p) = db.point(b as usize) {
                        let k = fq.keypoints[a as usize];
                        pts.push(p);
                        px.push(Point2::new(k[0] as f64, k[1] as f64));
                    }
                }
                c.pairs = pts.len();
                let r = pnp_ransac(&q.intrinsics, &pts, &px, &self.pnp);
                if r.valid {
                    c.db_from_query = Some(r.camera_from_points.to_isometry().inverse());
                    c.inliers = r.inliers.len();
                } else {
                    c.reason = r.reason;
                }
            }
            Solver::Teaser | Solver::Icp => {
                let (mut src, mut dst) = (Vec::new(), Vec::new());
                for &(a, b) in &m.pairs {
                    if let (Some(s), Some(d)) = (q_pts[a as usize], db.point(b as usize)) {
                        src.push(s);
                        dst.push(d);
                    }
                }
                c.pairs = src.len();
                if self.preset.solver == Solver::Teaser {
                    let r = solve(&src, &dst, &self.teaser);
                    if r.valid {
                        c.db_from_query = Some(Rigid::to_isometry(&r.transform));
                        c.inliers = r.inliers.len();
                    } else {
                        c.reason = r.reason;
                    }
                } else {
                    let r = icp_matched(&src, &dst, Rigid::identity(), &self.icp);
                    if r.valid {
                        c.db_from_query = Some(Rigid::to_isometry(&r.transform));
                        c.inliers = r.inliers.len();
                    }
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
