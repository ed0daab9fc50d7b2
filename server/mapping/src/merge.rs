//! Joining two maps of one building whose poses are in different frames: two mapping sessions whose
//! SLAM started at different places (each map is right in itself; between them lies an unknown
//! rigid transform).
//!
//! Map B's images are localized in map A from what B stores of them (keypoints, descriptors, the 3D
//! point of each keypoint, the verification thumbnail): A's global descriptor of B's features picks
//! A's candidate views, MNN matches and TEASER registers each pair, and the dense depth check of the
//! two thumbnails verifies the pose. Every verified image proposes a transform from B's frame to A's
//! (`world_A_from_camera * camera_from_world_B`). A wrong localization proposes a transform of its
//! own; the right ones all propose the same one. So the transform is the one most proposals agree
//! with, refused when too few do or when a second, different one has comparable support (a building
//! with two identical wings); it is then refitted by least squares to the 3D inlier pairs of the
//! agreeing images. Its covariance is the spread of the agreeing proposals around it (the standard
//! error of their mean, in the ROS order), which the per-image errors of the sessions' own poses
//! make larger than the point pairs alone would say.
//!
//! The merged map is A (its id, preset, axes, codebook) with B's images appended, their poses
//! carried into A's frame (and camera axes), their places renumbered after A's, and their global
//! descriptors computed with A's describer and added to A's index.

use std::collections::HashSet;

use nalgebra::{Isometry3, Matrix6, Vector3, Vector6};
use pntr_core::pose::convert_axes;
use pntr_core::CameraAxes;
use pntr_features::mnn::Mnn;
use pntr_features::Matcher;
use pntr_registration::teaser::{self, TeaserParams};
use rayon::prelude::*;
use serde::Serialize;

use pntr_pipeline::map::{unix_now_s, Map, MapImage};
use pntr_pipeline::verify::dense_evidence;
use pntr_pipeline::PipelineError;

/// Settings of [`merge`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MergeParams {
    /// B's images tried, evenly spaced (all when B has fewer).
    pub keyframes: usize,
    /// A's views tried per image of B (by A's global descriptor).
    pub candidates: usize,
    /// Fewest registration inliers of a verified image.
    pub min_inliers: usize,
    /// Fewest share of the thumbnails' depth that agrees under the pose.
    pub min_depth_agree: f64,
    /// Largest share of free-space violations under the pose.
    pub max_free_space_violation: f64,
    /// Two proposals agree when they move each other's camera by at most this, metres...
    pub agree_m: f64,
    /// ... and differ in rotation by at most this, degrees.
    pub agree_deg: f64,
    /// Fewest agreeing images for a transform (at least [`MIN_SUPPORT_FLOOR`]).
    pub min_support: usize,
    /// Fewest share of the images tried that must agree (sessions of one building agree in most
    /// of their overlap; a different building's chance agreements are a few per cent at most).
    pub min_support_share: f64,
}

/// The smallest `min_support` accepted: three chance agreements are too easy to meet.
pub const MIN_SUPPORT_FLOOR: usize = 4;

impl Default for MergeParams {
    fn default() -> Self {
        Self {
            keyframes: 300,
            candidates: 5,
            min_inliers: 20,
            min_depth_agree: 0.6,
            max_free_space_violation: 0.15,
            agree_m: 0.2,
            agree_deg: 2.0,
            min_support: 6,
            min_support_share: 0.05,
        }
    }
}

/// What [`merge`] found.
#[derive(Debug, Clone, Serialize)]
pub struct MergeReport {
    /// `a_from_b`: takes points of B's map frame into A's.
    #[serde(skip)]
    pub a_from_b: Isometry3<f64>,
    /// Its 6x6 covariance, row-major, ROS order (x, y, z, rotation about x, y, z) in A's frame,
    /// metres² and radians².
    pub covariance: Vec<f64>,
    /// Images of B whose localization in A agrees with the transform.
    pub supporting_keyframes: usize,
    /// Images of B tried.
    pub keyframes_tried: usize,
    /// Images of B verified in A (agreeing or not).
    pub keyframes_verified: usize,
    /// Images of the merged map.
    pub images: usize,
    /// Root mean square of the refit's 3D inlier residuals, metres.
    pub rms_m: f64,
    /// The merged map's own calibration fitted on recordings ([`run`] with [`Refit`]); `None`
    /// when none were given (the merged map keeps A's, stale).
    pub calibration_refit: Option<CalibrationRefit>,
}

/// How the merged map's own calibration was fitted ([`run`]).
#[derive(Debug, Clone, Serialize)]
pub struct CalibrationRefit {
    /// Frames of the recordings used (each localized twice).
    pub frames: usize,
    /// Seconds the fit took.
    pub seconds: f64,
    /// Why the merged map keeps A's calibration (stale) instead, when the frames could not make a
    /// fit.
    pub kept_because: Option<String>,
}

/// Recordings to fit the merged map's own calibration on, and how.
pub struct Refit<'a> {
    /// Recordings whose poses are in A's frame (the merged map's), such as the one A was built
    /// from; frames that are map images are left out.
    pub sessions: &'a [crate::recording_map::Session<'a>],
    /// At most how many frames, from which base, and whether a refusal keeps A's calibration.
    pub fit: crate::own_calibration::FitOptions,
}

/// One image of B verified in A: the transform it proposes and its 3D inlier pairs (B world, A
/// world, optical axes).
struct Proposal {
    a_from_b: Isometry3<f64>,
    /// The B image's camera centre in B's frame (where two proposals are compared).
    centre_b: Vector3<f64>,
    src: Vec<Vector3<f64>>,
    dst: Vec<Vector3<f64>>,
}

fn single_frame(m: &Map, which: &str) -> Result<(), PipelineError> {
    if m.header.scenes.len() > 1 {
        return Err(PipelineError::Refused(format!(
            "map {which} (`{}`) holds {} scenes, each in its own frame: merge maps of one scene",
            m.header.map_id,
            m.header.scenes.len()
        )));
    }
    Ok(())
}

/// Localize image `b_img` of B in A; the best verified registration's proposal.
fn localize(
    a: &Map,
    a_axes: CameraAxes,
    b_img: &MapImage,
    world_b_from_cam: &Isometry3<f64>,
    p: &MergeParams,
) -> Result<Option<Proposal>, PipelineError> {
    let features = b_img.features();
    let desc = a.retriever.describer.describe_features(&features)?;
    let hits = a.retriever.search(&desc, p.candidates)?;
    let mnn = Mnn::default();
    let solver = TeaserParams {
        min_inliers: p.min_inliers,
        ..TeaserParams::default()
    };
    let mut best: Option<(usize, Proposal)> = None;
    for h in hits {
        let a_img = &a.images[h.id];
        let m = mnn.match_features(&features, &a_img.features())?;
        let (mut src, mut dst) = (Vec::new(), Vec::new());
        for &(i, j) in &m.pairs {
            if let (Some(s), Some(d)) = (b_img.point(i as usize), a_img.point(j as usize)) {
                src.push(s);
                dst.push(d);
            }
        }
        if src.len() < p.min_inliers {
            continue;
        }
        let r = teaser::solve(&src, &dst, &solver);
        if !r.valid || r.inliers.len() < p.min_inliers {
            continue;
        }
        let a_cam_from_b_cam = r.transform.to_isometry();
        let e = dense_evidence(&b_img.thumb, &a_img.thumb, &a_cam_from_b_cam, &[]);
        if e.depth_agree < p.min_depth_agree || e.free_space_violation > p.max_free_space_violation
        {
            continue;
        }
        if best.as_ref().is_some_and(|(n, _)| *n >= r.inliers.len()) {
            continue;
        }
        let world_a_from_a_cam = convert_axes(&a_img.world_from_camera, a_axes, CameraAxes::OpenCv);
        let a_from_b = world_a_from_a_cam * a_cam_from_b_cam * world_b_from_cam.inverse();
        let proposal = Proposal {
            a_from_b,
            centre_b: world_b_from_cam.translation.vector,
            src: r
                .inliers
                .iter()
                .map(|&k| world_b_from_cam * nalgebra::Point3::from(src[k]))
                .map(|q| q.coords)
                .collect(),
            dst: r
                .inliers
                .iter()
                .map(|&k| world_a_from_a_cam * nalgebra::Point3::from(dst[k]))
                .map(|q| q.coords)
                .collect(),
        };
        best = Some((r.inliers.len(), proposal));
    }
    Ok(best.map(|(_, p)| p))
}

/// Whether two proposals agree: each moves the other's camera centre by at most `agree_m` and
/// their rotations differ by at most `agree_deg`.
fn agree(x: &Proposal, y: &Proposal, p: &MergeParams) -> bool {
    x.a_from_b
        .rotation
        .angle_to(&y.a_from_b.rotation)
        .to_degrees()
        <= p.agree_deg
        && [x.centre_b, y.centre_b].iter().all(|c| {
            let c = nalgebra::Point3::from(*c);
            (x.a_from_b * c - y.a_from_b * c).norm() <= p.agree_m
        })
}

/// The transform from `b`'s map frame into `a`'s, found by localizing `b`'s images in `a` (see the
/// module's documentation), and the map of both in `a`'s frame.
///
/// Errors: B mostly A's own images (the same map given twice); a map of several scenes; maps whose images are described differently (another extractor
/// or descriptor: rebuild B with A's preset); an ONNX global descriptor (it needs the images, which
/// maps do not keep); too few agreeing images (the message says how many were tried, verified and
/// agreed: sessions of different places, or too little overlap between them); two different
/// transforms with comparable support.
pub fn merge(a: Map, b: &Map, p: &MergeParams) -> Result<(Map, MergeReport), PipelineError> {
    single_frame(&a, "A")?;
    single_frame(b, "B")?;
    a.header.preset.serves(&b.header.preset).map_err(|e| {
        PipelineError::Refused(format!(
            "map B (`{}`, preset {}) describes images unlike map A (`{}`, preset {}): {e}; rebuild B with --preset {}",
            b.header.map_id,
            b.header.preset.name,
            a.header.map_id,
            a.header.preset.name,
            a.header.preset.name
        ))
    })?;
    if b.images.first().map(|im| im.dim) != a.images.first().map(|im| im.dim) {
        return Err(PipelineError::Refused(
            "the maps' descriptors differ in length: rebuild B with A's preset".into(),
        ));
    }
    // The same map or session given twice (`maps merge A A`) would hold every image twice.
    let in_a: std::collections::HashMap<&str, &pntr_pipeline::map::MapImage> =
        a.images.iter().map(|im| (im.id.as_str(), im)).collect();
    let twice = b
        .images
        .iter()
        .filter(|im| {
            in_a.get(im.id.as_str())
                .is_some_and(|x| x.keypoints == im.keypoints && x.descriptors == im.descriptors)
        })
        .count();
    if twice > 0 && twice == a.images.len() && b.images.len() > twice {
        // B grew from A (`build-db --extend` of A written as B): it is already the merge.
        return Err(PipelineError::Refused(format!(
            "map B holds every one of map A's {twice} images, unchanged, and {} more (B was extended from A): it is the merged map already; serve or replace with B instead of merging",
            b.images.len() - twice
        )));
    }
    if twice * 2 > b.images.len() {
        return Err(PipelineError::Refused(format!(
            "{twice} of map B's {} images are already in map A, unchanged (the same map or session given twice, as in `maps merge A A`): nothing to merge",
            b.images.len()
        )));
    }
    let (a_axes, b_axes) = (a.header.axes(), b.header.axes());
    let n = b.images.len();
    let tried: Vec<usize> = if p.keyframes == 0 || n <= p.keyframes {
        (0..n).collect()
    } else {
        (0..p.keyframes).map(|k| k * n / p.keyframes).collect()
    };
    let results: Vec<Result<Option<Proposal>, PipelineError>> = tried
        .par_iter()
        .map(|&i| {
            let im = &b.images[i];
            let world_b = convert_axes(&im.world_from_camera, b_axes, CameraAxes::OpenCv);
            localize(&a, a_axes, im, &world_b, p)
        })
        .collect();
    let mut proposals = Vec::new();
    for r in results {
        if let Some(x) = r? {
            proposals.push(x);
        }
    }
    let verified = proposals.len();
    // The proposal most others agree with; the support of the best one that disagrees with it.
    let support: Vec<Vec<usize>> = proposals
        .iter()
        .map(|x| {
            (0..proposals.len())
                .filter(|&j| agree(x, &proposals[j], p))
                .collect()
        })
        .collect();
    let Some(best) = (0..proposals.len()).max_by_key(|&i| (support[i].len(), usize::MAX - i))
    else {
        return Err(too_few(0, tried.len(), verified, p));
    };
    let chosen = &support[best];
    if chosen.len() < p.min_support.max(MIN_SUPPORT_FLOOR)
        || (chosen.len() as f64) < p.min_support_share * tried.len() as f64
    {
        return Err(too_few(chosen.len(), tried.len(), verified, p));
    }
    let in_chosen: HashSet<usize> = chosen.iter().copied().collect();
    let rival = (0..proposals.len())
        .filter(|j| !in_chosen.contains(j) && !agree(&proposals[best], &proposals[*j], p))
        .map(|j| support[j].iter().filter(|k| !in_chosen.contains(k)).count())
        .max()
        .unwrap_or(0);
    if rival * 2 >= chosen.len() && rival >= p.min_support {
        return Err(PipelineError::Refused(format!(
            "two different transforms are supported ({} and {rival} images of B agree with each): the building repeats itself; merge sessions that share a distinctive part",
            chosen.len()
        )));
    }
    // Refit to every inlier pair of the agreeing images, twice dropping pairs far off.
    let mut src: Vec<Vector3<f64>> = Vec::new();
    let mut dst: Vec<Vector3<f64>> = Vec::new();
    for &i in chosen {
        src.extend(&proposals[i].src);
        dst.extend(&proposals[i].dst);
    }
    let mut a_from_b = proposals[best].a_from_b;
    for _ in 0..3 {
        let keep: Vec<usize> = (0..src.len())
            .filter(|&k| {
                (a_from_b * nalgebra::Point3::from(src[k]) - nalgebra::Point3::from(dst[k])).norm()
                    <= 0.1
            })
            .collect();
        let s: Vec<_> = keep.iter().map(|&k| src[k]).collect();
        let d: Vec<_> = keep.iter().map(|&k| dst[k]).collect();
        if let Some(r) = pntr_registration::kabsch(&s, &d) {
            a_from_b = r.to_isometry();
        }
    }
    let residuals: Vec<f64> = src
        .iter()
        .zip(&dst)
        .map(|(s, d)| (a_from_b * nalgebra::Point3::from(*s) - nalgebra::Point3::from(*d)).norm())
        .filter(|r| *r <= 0.1)
        .collect();
    let rms_m =
        (residuals.iter().map(|r| r * r).sum::<f64>() / residuals.len().max(1) as f64).sqrt();
    // The spread of the agreeing proposals about the estimate: the standard error of their mean.
    let mut cov = Matrix6::<f64>::zeros();
    for &i in chosen {
        let d = proposals[i].a_from_b * a_from_b.inverse();
        let e = Vector6::new(
            d.translation.x,
            d.translation.y,
            d.translation.z,
            d.rotation.scaled_axis().x,
            d.rotation.scaled_axis().y,
            d.rotation.scaled_axis().z,
        );
        cov += e * e.transpose();
    }
    let k = chosen.len() as f64;
    cov /= k * (k - 1.0).max(1.0);
    let report_support = chosen.len();
    same_views(&a, b, &a_from_b)?;
    let merged = append(a, b, &a_from_b)?;
    let report = MergeReport {
        a_from_b,
        covariance: cov.transpose().iter().copied().collect(),
        supporting_keyframes: report_support,
        keyframes_tried: tried.len(),
        keyframes_verified: verified,
        images: merged.images.len(),
        rms_m,
        calibration_refit: None,
    };
    Ok((merged, report))
}

/// `pntr maps merge`: [`merge`], then with `refit` the merged map's own calibration fitted on its
/// recordings ([`crate::own_calibration::on_recordings`], the frames chosen by
/// [`crate::own_calibration::recording_frames`]), so the merged map is not served with A's
/// calibration, which was fitted on A's images alone. Networks from `stages`; progress through the
/// self-calibration passes. Errors: those of [`merge`], and of the fit (recordings without a posed
/// frame that is not a map image; a refusal unless `refit.fit.keep_on_refusal`).
pub fn run(
    a: Map,
    b: &Map,
    p: &MergeParams,
    refit: Option<Refit<'_>>,
    stages: &crate::stages::Stages,
    progress: &mut crate::progress::Progress<'_>,
) -> Result<(Map, MergeReport), PipelineError> {
    let (merged, mut report) = merge(a, b, p)?;
    let Some(refit) = refit else {
        return Ok((merged, report));
    };
    // The transform was found; what fails from here is the recordings given for the fit.
    let frames =
        crate::own_calibration::recording_frames(&merged, refit.sessions, refit.fit.max_frames)
            .map_err(for_fit)?;
    let done = crate::own_calibration::on_recordings(
        merged,
        refit.sessions,
        &frames,
        &refit.fit,
        stages,
        None,
        progress,
    )
    .map_err(for_fit)?;
    report.calibration_refit = Some(CalibrationRefit {
        frames: frames.len(),
        seconds: done.seconds,
        kept_because: done.kept_because,
    });
    Ok((done.map, report))
}

/// B's camera within this distance of one of A's, carried into A's frame, is the same view.
pub const SAME_VIEW_M: f64 = 0.05;
/// See [`SAME_VIEW_M`].
pub const SAME_VIEW_DEG: f64 = 2.0;

/// Refuse B when most of its images, carried into A's frame by `a_from_b`, stand where one of A's
/// cameras stands, looking the same way ([`SAME_VIEW_M`], [`SAME_VIEW_DEG`]): the same drive built
/// twice (from its TUM folder and from a bag of it, or with another trajectory's frame), which
/// the images' ids and bytes do not show and which would leave every view in the map twice. The
/// bounds leave room for the transform's own error (a few millimetres and tenths of a degree); two
/// drives of the same rooms choose their keyframes where their own motion put them, and only a
/// few of them fall that close to one another.
fn same_views(a: &Map, b: &Map, a_from_b: &Isometry3<f64>) -> Result<(), PipelineError> {
    let (a_axes, b_axes) = (a.header.axes(), b.header.axes());
    let cameras: Vec<Isometry3<f64>> = a
        .images
        .iter()
        .map(|im| convert_axes(&im.world_from_camera, a_axes, CameraAxes::OpenCv))
        .collect();
    let same = b
        .images
        .iter()
        .filter(|im| {
            let carried =
                a_from_b * convert_axes(&im.world_from_camera, b_axes, CameraAxes::OpenCv);
            cameras.iter().any(|c| {
                (c.translation.vector - carried.translation.vector).norm() <= SAME_VIEW_M
                    && c.rotation.angle_to(&carried.rotation).to_degrees() <= SAME_VIEW_DEG
            })
        })
        .count();
    if same * 2 > b.images.len() {
        return Err(PipelineError::Refused(format!(
            "{same} of map B's {} images, carried into A's frame, stand where one of A's cameras stands (within {:.0} cm and {SAME_VIEW_DEG} deg): B is the same drive as A (built again from another copy of the recording, or with another frame): nothing to merge",
            b.images.len(),
            100.0 * SAME_VIEW_M
        )));
    }
    Ok(())
}

/// A refusal of the merged map's calibration fit, saying that the merge itself succeeded.
fn for_fit(e: PipelineError) -> PipelineError {
    match e {
        PipelineError::Refused(why) => PipelineError::Refused(format!(
            "B's frame into A's was found, but the recordings given could not fit the merged map's own calibration (their poses must be in A's frame): {why}"
        )),
        e => e,
    }
}

fn too_few(agreeing: usize, tried: usize, verified: usize, p: &MergeParams) -> PipelineError {
    PipelineError::Refused(format!(
        "too few keyframes agree on a transform: of {tried} images of B tried, {verified} localized in A and at most {agreeing} agree on one transform (at least {} and {:.0}% of those tried must): are the two sessions of the same place, and do they overlap?",
        p.min_support.max(MIN_SUPPORT_FLOOR),
        100.0 * p.min_support_share
    ))
}

/// A with B's images appended, carried into A's frame and camera axes by `a_from_b`.
fn append(mut a: Map, b: &Map, a_from_b: &Isometry3<f64>) -> Result<Map, PipelineError> {
    let (a_axes, b_axes) = (a.header.axes(), b.header.axes());
    let ids: HashSet<String> = a.images.iter().map(|im| im.id.clone()).collect();
    let first_place = a.images.iter().map(|im| im.point + 1).max().unwrap_or(0);
    let mut descriptors = Vec::with_capacity(b.images.len());
    for im in &b.images {
        let mut im = im.clone();
        let world_b = convert_axes(&im.world_from_camera, b_axes, CameraAxes::OpenCv);
        im.world_from_camera = convert_axes(&(a_from_b * world_b), CameraAxes::OpenCv, a_axes);
        im.point += first_place;
        im.scene = 0;
        if ids.contains(&im.id) {
            im.id = format!("{}/{}", b.header.map_id, im.id);
        }
        descriptors.push(a.retriever.describer.describe_features(&im.features())?);
        a.images.push(im);
    }
    a.retriever.extend(descriptors)?;
    a.header.sessions.extend(b.header.sessions.iter().cloned());
    a.header.built_at_unix_s = Some(unix_now_s());
    a.checksum = 0;
    Ok(a)
}
