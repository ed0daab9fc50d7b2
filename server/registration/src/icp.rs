//! Point-to-point ICP: on matched pairs (iteratively trimmed) or on two clouds (nearest neighbours).
//!
//! ICP is a local method: it refines a transform that is already close (a prior, or identity for
//! small motions). The HPointLoc paper uses it as a baseline after retrieval; pntr uses it the same way
//! and as an optional refinement of a robust estimate.

use nalgebra::Vector3;

use crate::kabsch::kabsch;
use crate::kdtree::KdTree;
use crate::Rigid;

/// ICP parameters.
#[derive(Debug, Clone, PartialEq)]
pub struct IcpParams {
    /// Pairs farther apart than this after applying the current estimate are ignored, metres.
    /// Default 0.5: large enough to capture a 10 degree / 0.3 m error at indoor ranges, small enough
    /// to keep pairs across different surfaces out.
    pub max_correspondence_m: f64,
    /// Iteration limit. Default 50.
    pub max_iterations: usize,
    /// Stop when an iteration moves the estimate by less than this (translation, metres, plus
    /// rotation, radians). Default 1e-6.
    pub tolerance: f64,
    /// The trimming distance shrinks toward this floor as ICP converges, metres. Default 0.05.
    pub min_correspondence_m: f64,
}

impl Default for IcpParams {
    fn default() -> Self {
        Self {
            max_correspondence_m: 0.5,
            max_iterations: 50,
            tolerance: 1e-6,
            min_correspondence_m: 0.05,
        }
    }
}

/// The result of ICP.
#[derive(Debug, Clone, PartialEq)]
pub struct IcpResult {
    /// `dst = R src + t`.
    pub transform: Rigid,
    /// Source indices used in the last iteration.
    pub inliers: Vec<usize>,
    /// Root mean square residual of those, metres.
    pub rmse: f64,
    /// Iterations run.
    pub iterations: usize,
    /// Whether the tolerance was reached before the iteration limit.
    pub converged: bool,
    /// Whether the result can be used (at least 3 correspondences, not degenerate).
    pub valid: bool,
}

/// How far two estimates are apart at `at` (the source's centroid: far from the origin the
/// translation vectors differ by the rotation change times the distance, which says nothing).
fn step_size(a: &Rigid, b: &Rigid, at: &Vector3<f64>) -> f64 {
    (a.apply(at) - b.apply(at)).norm() + a.rotation.angle_to(&b.rotation)
}

/// Shared loop: `pair` gives, for the current estimate, the (src index, dst point) pairs within `d`.
fn run<F>(src: &[Vector3<f64>], prior: Rigid, p: &IcpParams, mut pair: F) -> IcpResult
where
    F: FnMut(&Rigid, f64) -> Vec<(usize, Vector3<f64>)>,
{
    let finite: Vec<&Vector3<f64>> = src
        .iter()
        .filter(|v| v.iter().all(|x| x.is_finite()))
        .collect();
    let centroid = if finite.is_empty() {
        Vector3::zeros()
    } else {
        finite.iter().copied().sum::<Vector3<f64>>() / finite.len() as f64
    };
    let mut est = prior;
    let mut radius = p.max_correspondence_m;
    let mut last: Vec<(usize, Vector3<f64>)> = Vec::new();
    let mut converged = false;
    let mut iterations = 0;
    for it in 0..p.max_iterations {
        iterations = it + 1;
        let pairs = pair(&est, radius);
        if pairs.len() < 3 {
            break;
        }
        let s: Vec<_> = pairs.iter().map(|(i, _)| src[*i]).collect();
        let d: Vec<_> = pairs.iter().map(|(_, q)| *q).collect();
        let Some(next) = kabsch(&s, &d) else {
            break;
        };
        let step = step_size(&next, &est, &centroid);
        est = next;
        // Shrink the capture radius to three times the current residual spread, not below the floor.
        let rmse = (pairs
            .iter()
            .map(|(i, q)| (q - est.apply(&src[*i])).norm_squared())
            .sum::<f64>()
            / pairs.len() as f64)
            .sqrt();
        radius = (3.0 * rmse).clamp(p.min_correspondence_m, radius);
        last = pairs;
        if step < p.tolerance {
            converged = true;
            break;
        }
    }
    let rmse = if last.is_empty() {
        f64::INFINITY
    } else {
        (last
            .iter()
            .map(|(i, q)| (q - est.apply(&src[*i])).norm_squared())
            .sum::<f64>()
            / last.len() as f64)
            .sqrt()
    };
    let used: Vec<Vector3<f64>> = last.iter().map(|(i, _)| src[*i]).collect();
    let valid =
        used.len() >= 3 && crate::teaser::degenerate(&used, p.min_correspondence_m * 0.1).is_none();
    IcpResult {
        transform: est,
        inliers: last.iter().map(|(i, _)| *i).collect(),
        rmse,
        iterations,
        converged,
        valid,
    }
}

/// ICP with known pairing (`src[i]` pairs with `dst[i]`): each iteration drops the pairs farther
/// apart than the current radius and refits.
pub fn icp_matched(
    src: &[Vector3<f64>],
    dst: &[Vector3<f64>],
    prior: Rigid,
    p: &IcpParams,
) -> IcpResult {
    let n = src.len().min(dst.len());
    run(src, prior, p, |est, radius| {
        (0..n)
            .filter(|&i| (dst[i] - est.apply(&src[i])).norm() <= radius)
            .map(|i| (i, dst[i]))
            .collect()
    })
}

/// ICP between two clouds: each source point pairs with its nearest destination point.
pub fn icp_clouds(
    src: &[Vector3<f64>],
    dst: &[Vector3<f64>],
    prior: Rigid,
    p: &IcpParams,
) -> IcpResult {
    let tree = KdTree::new(dst);
    run(src, prior, p, |est, radius| {
        let r2 = radius * radius;
        src.iter()
            .enumerate()
            .filter_map(|(i, s)| tree.nearest(&est.apply(s), r2).map(|(j, _)| (i, dst[j])))
            .collect()
    })
}
