//! A map that knows its own look-alikes: the LOCALIZED threshold fitted on the map's own frames, with
//! each region of the map held out in turn.
//!
//! The places that fool a map most are the other rooms of the same building, which no shipped
//! calibration has seen. So the map is cut into regions ([`Regions`]: its places grouped by position
//! within each scene, about [`PLACES_PER_REGION`] places a region, a whole scene being a region of
//! its own in a map of several), and frames with known poses (a dataset's queries, a recording's
//! frames between keyframes) are localized twice ([`pass`]): against the whole map (in-map answers,
//! mostly right) and against the map without their own region ([`LocalizeOptions::among`]). A
//! held-out frame the rest of the map places within (1 m, 10 deg) is right (it saw into a kept
//! region); every other one is what an out-of-map query in this building looks like, in this
//! building's style. [`fit`] starts from the base calibration: it raises the threshold until at
//! most [`MAX_FALSE_POSITIVE_RATE`] of those negatives stay LOCALIZED, never below the base
//! threshold and never at a cost of more than [`MAX_RECALL_COST`] of the frames answered right
//! (in-map and held out); when the map gives enough samples it also refits the weights towards the base's,
//! cross-fitted over regions so the threshold is chosen on answers the weights did not see, and
//! keeps whichever refuses more of the map's negatives. The result, with what it measured, is
//! stored in the map ([`pntr_pipeline::calibration::MapCalibration`]).

use std::collections::BTreeMap;
use std::sync::Arc;

use nalgebra::{Isometry3, Vector3};

use pntr_pipeline::calibration::{
    choose, ece, Calibration, FitInfo, MapCalibration, MAP_FORMAT, MAP_VERSION,
};
use pntr_pipeline::map::Map;
use pntr_pipeline::pipeline::{Localization, Pipeline, Query, Status};
use pntr_pipeline::prior::LocalizeOptions;
use pntr_pipeline::PipelineError;

use crate::fit::{refit_toward, QuerySamples};

/// Places a region holds, about (k-means over the places' positions within a scene).
pub const PLACES_PER_REGION: usize = 4;
/// Most regions one scene is cut into.
pub const MAX_REGIONS_PER_SCENE: usize = 12;
/// Share of the map's own negatives allowed to stay LOCALIZED at the fitted threshold. A map's own
/// held-out regions are harder negatives than other buildings (3-7 % LOCALIZED at the shipped
/// threshold against 0-3 %): at 0.5 % the threshold cost up to 1.6 points of recall on a map for the
/// same out-of-map answers as 1 % (BENCHMARKS.md, "A map's own calibration"; chosen after that run).
pub const MAX_FALSE_POSITIVE_RATE: f64 = 0.01;
/// Largest share of the frames (both passes) answered right that raising the threshold may give up.
pub const MAX_RECALL_COST: f64 = 0.01;
/// A pose within this distance and angle of the truth is right (the calibration's own labels).
pub const RIGHT_M: f64 = 1.0;
/// See [`RIGHT_M`].
pub const RIGHT_DEG: f64 = 10.0;

/// The map's images grouped into regions that can be held out one at a time.
#[derive(Debug, Clone)]
pub struct Regions {
    of_image: Vec<usize>,
    count: usize,
}

impl Regions {
    /// Cut `map` into regions: per scene, the places' mean camera positions clustered by k-means
    /// (deterministic farthest-point start) into round(places / [`PLACES_PER_REGION`]) regions, at
    /// least 1 and at most [`MAX_REGIONS_PER_SCENE`]; a map of one scene gets at least 2. Every
    /// image of a place is in its place's region, so holding a region out holds whole places out.
    ///
    /// Errors: `Refused` for a map of a single place (nothing to hold out against).
    pub fn of_map(map: &Map) -> Result<Self, PipelineError> {
        let mut places: BTreeMap<(u32, u32), (Vector3<f64>, usize)> = BTreeMap::new();
        for im in &map.images {
            let e = places
                .entry((im.scene, im.point))
                .or_insert((Vector3::zeros(), 0));
            e.0 += im.world_from_camera.translation.vector;
            e.1 += 1;
        }
        if places.len() < 2 {
            return Err(PipelineError::Refused(format!(
                "map `{}` has {} place(s): a map's own calibration holds regions out against the rest, which needs at least 2 places",
                map.header.map_id,
                places.len()
            )));
        }
        let scenes: Vec<u32> = {
            let mut s: Vec<u32> = places.keys().map(|k| k.0).collect();
            s.dedup();
            s
        };
        let mut region_of_place: BTreeMap<(u32, u32), usize> = BTreeMap::new();
        let mut count = 0;
        for &scene in &scenes {
            let keys: Vec<(u32, u32)> = places.keys().filter(|k| k.0 == scene).copied().collect();
            let centres: Vec<Vector3<f64>> = keys
                .iter()
                .map(|k| places[k].0 / places[k].1 as f64)
                .collect();
            let mut k = ((keys.len() as f64 / PLACES_PER_REGION as f64).round() as usize)
                .clamp(1, MAX_REGIONS_PER_SCENE);
            if scenes.len() == 1 {
                k = k.max(2);
            }
            let labels = kmeans(&centres, k.min(keys.len()));
            // Compact labels (an emptied cluster leaves a gap).
            let mut seen: BTreeMap<usize, usize> = BTreeMap::new();
            for (key, l) in keys.iter().zip(labels) {
                let next = count + seen.len();
                let r = *seen.entry(l).or_insert(next);
                region_of_place.insert(*key, r);
            }
            count += seen.len();
        }
        let of_image = map
            .images
            .iter()
            .map(|im| region_of_place[&(im.scene, im.point)])
            .collect();
        Ok(Self { of_image, count })
    }

    /// How many regions.
    pub fn count(&self) -> usize {
        self.count
    }

    /// The region of map image `i`.
    pub fn of_image(&self, i: usize) -> usize {
        self.of_image[i]
    }

    /// The region of a frame taken at `position` (map frame, metres) in `scene`: that of the map
    /// image of the scene nearest to it; `None` when the scene has no image.
    pub fn of_position(&self, map: &Map, scene: u32, position: &Vector3<f64>) -> Option<usize> {
        map.images
            .iter()
            .enumerate()
            .filter(|(_, im)| im.scene == scene)
            .min_by(|a, b| {
                let d = |im: &pntr_pipeline::map::MapImage| {
                    (im.world_from_camera.translation.vector - position).norm_squared()
                };
                d(a.1).total_cmp(&d(b.1))
            })
            .map(|(i, _)| self.of_image[i])
    }

    /// The map images outside region `r`, ascending: what a frame of `r` is localized against when
    /// its region is held out.
    pub fn outside(&self, r: usize) -> Arc<[usize]> {
        (0..self.of_image.len())
            .filter(|&i| self.of_image[i] != r)
            .collect()
    }
}

/// Lloyd's k-means of `points` into `k` clusters from a farthest-point start (the first point,
/// then repeatedly the point farthest from every chosen centre): deterministic. Labels per point.
fn kmeans(points: &[Vector3<f64>], k: usize) -> Vec<usize> {
    if k <= 1 || points.is_empty() {
        return vec![0; points.len()];
    }
    let mut centres = vec![points[0]];
    while centres.len() < k {
        let far = points
            .iter()
            .max_by(|a, b| {
                let d = |p: &Vector3<f64>| {
                    centres
                        .iter()
                        .map(|c| (p - c).norm_squared())
                        .fold(f64::INFINITY, f64::min)
                };
                d(a).total_cmp(&d(b))
            })
            .expect("points is not empty");
        centres.push(*far);
    }
    let nearest = |p: &Vector3<f64>, centres: &[Vector3<f64>]| {
        (0..centres.len())
            .min_by(|&a, &b| {
                (p - centres[a])
                    .norm_squared()
                    .total_cmp(&(p - centres[b]).norm_squared())
            })
            .expect("k >= 1")
    };
    let mut labels: Vec<usize> = points.iter().map(|p| nearest(p, &centres)).collect();
    for _ in 0..50 {
        for (c, centre) in centres.iter_mut().enumerate() {
            let members: Vec<&Vector3<f64>> = points
                .iter()
                .zip(&labels)
                .filter(|(_, &l)| l == c)
                .map(|(p, _)| p)
                .collect();
            if !members.is_empty() {
                *centre = members.iter().copied().sum::<Vector3<f64>>() / members.len() as f64;
            }
        }
        let next: Vec<usize> = points.iter().map(|p| nearest(p, &centres)).collect();
        if next == labels {
            break;
        }
        labels = next;
    }
    labels
}

/// A frame with its true pose, for [`pass`].
pub struct PosedFrame {
    /// The frame as a query.
    pub query: Query,
    /// Its true `world_from_camera`, map frame and map camera axes.
    pub world_from_camera: Isometry3<f64>,
    /// The map scene it was taken in (0 for a map of one scene).
    pub scene: u32,
}

/// One frame's answer, kept as its verified candidates so a threshold can be chosen afterwards
/// under any calibration.
#[derive(Debug, Clone)]
pub struct Answered {
    /// Every verified candidate's evidence and label (right within ([`RIGHT_M`], [`RIGHT_DEG`])).
    pub samples: QuerySamples,
    /// The frame's region.
    pub region: usize,
    /// Whether its own region was held out.
    pub held_out: bool,
}

/// The verified candidates of `loc` labelled against `truth` (map frame and axes; `None`: every
/// candidate is wrong, an out-of-map query), with each candidate's rivals as indices.
pub fn samples_of(loc: &Localization, truth: Option<&Isometry3<f64>>) -> QuerySamples {
    let mut out = QuerySamples::default();
    for c in &loc.verified {
        out.rivals.push(
            c.rivals
                .iter()
                .filter_map(|r| loc.verified.iter().position(|o| o.image == *r))
                .collect(),
        );
        let right = truth.is_some_and(|t| {
            let dt = (c.pose.translation.vector - t.translation.vector).norm();
            let dr = pntr_core::rotation_angle_deg(&c.pose.rotation, &t.rotation);
            dt <= RIGHT_M && dr <= RIGHT_DEG
        });
        out.candidates.push((c.evidence, right));
    }
    out
}

/// Localize `n` frames (`frame(i)`; `None` skips one) against `pipeline`'s map, globally: the whole
/// map, or with `held_out` the map without each frame's own region. `progress(done, n)` after
/// each frame.
pub fn pass(
    pipeline: &Pipeline,
    regions: &Regions,
    n: usize,
    held_out: bool,
    frame: &mut dyn FnMut(usize) -> Result<Option<PosedFrame>, PipelineError>,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<Vec<Answered>, PipelineError> {
    let mut out = Vec::with_capacity(n);
    let mut outside: BTreeMap<usize, Arc<[usize]>> = BTreeMap::new();
    for i in 0..n {
        progress(i + 1, n);
        let Some(f) = frame(i)? else { continue };
        let position = f.world_from_camera.translation.vector;
        let Some(region) = regions.of_position(&pipeline.map, f.scene, &position) else {
            continue;
        };
        let opts = LocalizeOptions {
            among: held_out.then(|| {
                outside
                    .entry(region)
                    .or_insert_with(|| regions.outside(region))
                    .clone()
            }),
            ..LocalizeOptions::default()
        };
        let loc = match pipeline.localize_with(&f.query, &opts) {
            Ok(l) => l,
            Err(PipelineError::Query(m)) => {
                tracing::warn!("self-calibration: frame {i} refused: {m}");
                continue;
            }
            Err(e) => return Err(e),
        };
        out.push(answered(&loc, &f.world_from_camera, region, held_out));
    }
    Ok(out)
}

/// A localization of a frame of `region` as an [`Answered`] (for callers that localized the frame
/// already, such as a recording map's check).
pub fn answered(
    loc: &Localization,
    truth: &Isometry3<f64>,
    region: usize,
    held_out: bool,
) -> Answered {
    debug_assert!(loc.status != Status::Localized || loc.pose.is_some());
    Answered {
        samples: samples_of(loc, Some(truth)),
        region,
        held_out,
    }
}

/// The answer a frame gets under `calibration`: (confidence, right), (0, false) without candidates.
fn scored(calibration: &Calibration, a: &Answered) -> (f64, bool) {
    let q = &a.samples;
    let p: Vec<f64> = q
        .candidates
        .iter()
        .map(|s| calibration.probability(&s.0))
        .collect();
    let inliers: Vec<usize> = q.candidates.iter().map(|s| s.0.inliers()).collect();
    match choose(&p, &inliers, &q.rivals) {
        Some((i, conf)) => (conf, q.candidates[i].1),
        None => (0.0, false),
    }
}

/// Fit `map`'s own calibration from its frames' answers, starting from `base` (the shipped
/// calibration unless the user gave another). Two candidates:
///
/// - `threshold`: `base`'s weights, the threshold raised ([`threshold`]);
/// - `weights+threshold`, when the map gives enough samples (at least [`MIN_REFIT_REGIONS`]
///   regions and [`MIN_REFIT_SAMPLES`] right and wrong candidates): the weights refitted towards
///   `base`'s ([`crate::fit::refit_toward`], penalty [`REFIT_L2`]), cross-fitted over two
///   folds of regions (even and odd), each fold's answers scored by the weights fitted on the
///   other, the threshold chosen on those scores; the stored weights are then fitted on all.
///
/// The one with fewer of the map's own negatives LOCALIZED wins (then the higher in-map recall,
/// then `threshold`). `date`: today, as text. Errors: `Refused` when no frame was answered.
pub fn fit(
    base: &Calibration,
    map: &Map,
    regions: &Regions,
    answers: &[Answered],
    date: &str,
) -> Result<MapCalibration, PipelineError> {
    if answers.is_empty() {
        return Err(PipelineError::Refused(
            "the map's own calibration needs frames with poses; none was localized".into(),
        ));
    }
    let score = |c: &Calibration, a: &Answered| {
        let (conf, right) = scored(c, a);
        (conf, right, a.held_out)
    };
    let base_scores: Vec<(f64, bool, bool)> = answers.iter().map(|a| score(base, a)).collect();
    // Frames that the whole map does not place are not its frames: the likely mistake is another
    // place's dataset or recording, or poses in another frame or camera axes.
    let in_map: Vec<&(f64, bool, bool)> = base_scores.iter().filter(|a| !a.2).collect();
    let placed = in_map.iter().filter(|a| a.1).count();
    if !in_map.is_empty() && (placed as f64) < MIN_IN_MAP_RIGHT * in_map.len() as f64 {
        return Err(PipelineError::Refused(format!(
            "only {placed} of {} frames localize right (within {RIGHT_M} m, {RIGHT_DEG} deg of their poses) against the whole map `{}`, fewer than {:.0} %: these frames are not of this map (another building's dataset or recording?) or their poses are in another frame or camera axes; the map was not changed",
            in_map.len(),
            map.header.map_id,
            100.0 * MIN_IN_MAP_RIGHT
        )));
    }
    let base_t = base.threshold;
    let reference = Outcome::of(&base_scores, base_t);
    // Threshold only.
    let t = threshold(base_t, &base_scores, reference.right_kept);
    let mut best = (
        Outcome::of(&base_scores, t),
        base_scores.clone(),
        Calibration {
            threshold: t,
            ..base.clone()
        },
        "threshold",
    );
    // Weights and threshold, cross-fitted, when the samples allow.
    let count = |f: &dyn Fn(&Answered) -> bool, right: bool| -> usize {
        answers
            .iter()
            .filter(|a| f(a))
            .map(|a| a.samples.candidates.iter().filter(|c| c.1 == right).count())
            .sum()
    };
    let fold = |a: &Answered| a.region % 2;
    let enough = regions.count() >= MIN_REFIT_REGIONS
        && (0..2).all(|f| {
            let out = |a: &Answered| fold(a) != f;
            count(&out, true) >= MIN_REFIT_SAMPLES && count(&out, false) >= MIN_REFIT_SAMPLES
        });
    if enough {
        let mut oof = vec![(0.0, false, false); answers.len()];
        for f in 0..2 {
            let train: Vec<QuerySamples> = answers
                .iter()
                .filter(|a| fold(a) != f)
                .map(|a| a.samples.clone())
                .collect();
            let c = refit_toward(base, &train, REFIT_L2);
            for (i, a) in answers.iter().enumerate() {
                if fold(a) == f {
                    oof[i] = score(&c, a);
                }
            }
        }
        let t = threshold(base_t, &oof, reference.right_kept);
        let outcome = Outcome::of(&oof, t);
        let better = (
            outcome.false_positives,
            std::cmp::Reverse(outcome.in_map_right),
        ) < (
            best.0.false_positives,
            std::cmp::Reverse(best.0.in_map_right),
        );
        if better {
            let all: Vec<QuerySamples> = answers.iter().map(|a| a.samples.clone()).collect();
            let c = Calibration {
                threshold: t,
                ..refit_toward(base, &all, REFIT_L2)
            };
            best = (outcome, oof, c, "weights+threshold");
        }
    }
    let (outcome, scores, mut calibration, method) = best;
    let held = answers.iter().filter(|a| a.held_out).count();
    let n_in = answers.len() - held;
    let probs: Vec<(f64, bool)> = scores.iter().map(|a| (a.0, a.1)).collect();
    let samples: usize = answers.iter().map(|a| a.samples.candidates.len()).sum();
    let positives: usize = answers
        .iter()
        .map(|a| a.samples.candidates.iter().filter(|c| c.1).count())
        .sum();
    calibration.fitted_on = FitInfo {
        samples,
        positives,
        queries: answers.len(),
        datasets: vec![format!(
            "map `{}`: {} regions, each held out once; {n_in} frames against the whole map, {held} against the rest; {method} from calibration {}",
            map.header.map_id,
            regions.count(),
            base.checksum
        )],
        ece: ece(&probs, 10).0,
        precision_at_threshold: outcome.precision,
        recall_at_threshold: outcome.right_kept as f64 / outcome.right.max(1) as f64,
        date: date.into(),
    };
    calibration.checksum = String::new();
    let n_in_f = n_in.max(1) as f64;
    Ok(MapCalibration {
        format: MAP_FORMAT.into(),
        version: MAP_VERSION,
        calibration,
        method: method.into(),
        base_threshold: base_t,
        base_checksum: base.checksum.clone(),
        regions: regions.count(),
        in_map_queries: n_in,
        held_out_queries: held,
        held_out_right: scores.iter().filter(|a| a.2 && a.1).count(),
        negatives: outcome.negatives,
        false_positives_base: reference.false_positives,
        false_positives: outcome.false_positives,
        in_map_recall_base: reference.in_map_right as f64 / n_in_f,
        in_map_recall: outcome.in_map_right as f64 / n_in_f,
        expected_precision: outcome.precision,
        images: map.images.len(),
        fingerprint: map.image_fingerprint(),
        checksum: String::new(),
    }
    .sealed())
}

/// Least share of the frames that must localize right against the whole map for them to count as
/// the map's own frames ([`fit`] refuses others).
pub const MIN_IN_MAP_RIGHT: f64 = 0.5;
/// Fewest regions for refitting weights (two folds of at least two regions each).
pub const MIN_REFIT_REGIONS: usize = 4;
/// Fewest right and fewest wrong candidates the weights of each fold are fitted on.
pub const MIN_REFIT_SAMPLES: usize = 100;
/// The penalty that pulls refitted weights towards the base calibration's (standardised inputs;
/// see [`crate::fit::refit_toward`]). Chosen on three maps of two apartments (BENCHMARKS.md,
/// "A map's own calibration"): 3 to 30 gave about the same held-out figures, 1 followed one map too
/// closely.
pub const REFIT_L2: f64 = 10.0;

/// What a threshold gives on scored answers (confidence, right, held out).
struct Outcome {
    negatives: usize,
    false_positives: usize,
    right: usize,
    right_kept: usize,
    in_map_right: usize,
    precision: f64,
}

impl Outcome {
    fn of(scores: &[(f64, bool, bool)], t: f64) -> Self {
        let kept = scores.iter().filter(|a| a.0 >= t).count();
        let right_kept = scores.iter().filter(|a| a.1 && a.0 >= t).count();
        Self {
            negatives: scores.iter().filter(|a| !a.1).count(),
            false_positives: scores.iter().filter(|a| !a.1 && a.0 >= t).count(),
            right: scores.iter().filter(|a| a.1).count(),
            right_kept,
            in_map_right: scores.iter().filter(|a| !a.2 && a.1 && a.0 >= t).count(),
            precision: if kept == 0 {
                1.0
            } else {
                right_kept as f64 / kept as f64
            },
        }
    }
}

/// The map's threshold from every frame's (confidence, right, held out): the smallest at or above
/// `floor` that leaves at most [`MAX_FALSE_POSITIVE_RATE`] of the answers that are not right
/// LOCALIZED (half way between the highest that must go and the next right answer), lowered again
/// so that at least `reference_right` (the frames the base calibration answers right) less
/// [`MAX_RECALL_COST`] of the frames stay LOCALIZED right.
///
/// Both passes count for that recall: a held-out frame the rest of the map places right was seen
/// from farther off than any map image, which is what a robot off the mapping path brings. Counting
/// only in-map frames held a drive's map (whose in-map frames lie between keyframes, the easy case)
/// to a threshold that cost 4 points of recall on queries off the drive (BENCHMARKS.md, "A map's
/// own calibration").
fn threshold(floor: f64, all: &[(f64, bool, bool)], reference_right: usize) -> f64 {
    let mut negatives: Vec<f64> = all.iter().filter(|a| !a.1).map(|a| a.0).collect();
    negatives.sort_by(|a, b| b.total_cmp(a));
    let allowed = (MAX_FALSE_POSITIVE_RATE * negatives.len() as f64).floor() as usize;
    let mut t = floor;
    if let Some(&worst) = negatives.get(allowed).filter(|&&c| c >= floor) {
        // Above the first negative that must go: half way to the next right answer (the widest
        // margin the samples allow), or to 1.
        let next_right = all
            .iter()
            .filter(|a| a.1 && a.0 > worst)
            .map(|a| a.0)
            .fold(1.0, f64::min);
        t = 0.5 * (worst + next_right);
        if t <= worst {
            t = next_up(worst);
        }
    }
    // The recall this may give up, capped.
    let cap = (MAX_RECALL_COST * all.len() as f64).floor() as usize;
    let need = reference_right.saturating_sub(cap);
    let mut kept: Vec<f64> = all
        .iter()
        .filter(|a| a.1 && a.0 >= floor)
        .map(|a| a.0)
        .collect();
    kept.sort_by(|a, b| b.total_cmp(a));
    if kept.iter().filter(|&&c| c >= t).count() < need {
        // The highest threshold that keeps `need` of them (the floor when even that cannot).
        t = match need.checked_sub(1).and_then(|i| kept.get(i)) {
            Some(&c) => c.max(floor),
            None => floor,
        };
    }
    t
}

/// The smallest f64 above `x` (for finite, non-negative `x`).
fn next_up(x: f64) -> f64 {
    f64::from_bits(x.to_bits() + 1)
}

/// A pipeline over `map` scored with `base`'s weights, for fitting the map's own calibration (the
/// threshold does not matter here: every frame's candidates are kept and scored again when
/// fitting). `stage` describes queries for `preset`. Errors: as [`Pipeline::new`].
pub fn fitting_pipeline(
    map: Map,
    stage: pntr_features::config::FeatureStage,
    preset: pntr_pipeline::preset::Preset,
    base: &Calibration,
) -> Result<Pipeline, PipelineError> {
    Ok(Pipeline::new(Arc::new(map), stage, preset)?.with_calibration(Arc::new(base.clone()), None))
}

/// The map back from a [`fitting_pipeline`] that was its only holder, with `calibration` in its
/// header when given (otherwise the header keeps what it had).
///
/// # Panics
/// When something else still holds the map (a caller's bug: the fitting pipeline is never shared).
pub fn fitted_map(p: Pipeline, calibration: Option<MapCalibration>) -> Map {
    let mut map = Arc::try_unwrap(p.map).unwrap_or_else(|shared| {
        panic!(
            "the self-calibration's pipeline is the map's only holder ({} holders)",
            Arc::strong_count(&shared)
        )
    });
    if let Some(c) = calibration {
        map.header.calibration = Some(c);
    }
    map
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn kmeans_separates_two_rooms() {
        let pts: Vec<Vector3<f64>> = (0..8)
            .map(|i| {
                Vector3::new(
                    if i < 4 { 0.0 } else { 10.0 } + (i % 4) as f64 * 0.5,
                    0.0,
                    0.0,
                )
            })
            .collect();
        let l = kmeans(&pts, 2);
        assert!(l[..4].iter().all(|&x| x == l[0]));
        assert!(l[4..].iter().all(|&x| x == l[4]));
        assert_ne!(l[0], l[4]);
        assert_eq!(kmeans(&pts, 1), vec![0; 8]);
    }

    #[test]
    fn the_threshold_refuses_the_maps_own_look_alikes_within_the_recall_cap() {
        // 300 in-map frames answered right with confidences spread over 0.62..0.99, 100 held-out
        // negatives mostly low but two confident look-alikes at 0.90 and 0.93.
        let mut all: Vec<(f64, bool, bool)> = (0..300)
            .map(|i| (0.62 + 0.37 * i as f64 / 299.0, true, false))
            .collect();
        all.extend((0..98).map(|i| (0.3 * i as f64 / 97.0, false, true)));
        all.extend([(0.90, false, true), (0.93, false, true)]);
        // Both look-alikes must go, but that would cost 84 % of the right answers; the cap of 1 %
        // of the 400 frames (4) keeps 296 of the 300 right.
        let t = threshold(0.61, &all, 300);
        let right_kept = all.iter().filter(|a| a.1 && a.0 >= t).count();
        assert_eq!(right_kept, 296, "threshold {t}");
        // Look-alikes below every right answer: the threshold goes half way between the negative
        // that must go (0.70) and the next right answer (0.75).
        let mut easy: Vec<(f64, bool, bool)> = (0..300)
            .map(|i| (0.75 + 0.24 * i as f64 / 299.0, true, false))
            .collect();
        easy.extend((0..98).map(|i| (0.3 * i as f64 / 97.0, false, true)));
        // 1 % of the 100 negatives (one) may stay LOCALIZED: the second-highest must go.
        easy.push((0.72, false, true));
        easy.push((0.70, false, true));
        let t = threshold(0.61, &easy, 300);
        assert!((t - 0.725).abs() < 1e-9, "{t}");
        assert_eq!(easy.iter().filter(|a| a.1 && a.0 >= t).count(), 300);
        // One negative above the base threshold is allowed: the base stays; never below it.
        easy.pop();
        easy.push((0.1, false, true));
        assert_eq!(threshold(0.61, &easy, 300), 0.61);
        // With 400 negatives, 1 % (4) may stay: two confident look-alikes are tolerated.
        let mut many = easy.clone();
        many.extend((0..300).map(|_| (0.1, false, true)));
        many.push((0.7, false, true));
        assert_eq!(threshold(0.61, &many, 300), 0.61);
    }
}
