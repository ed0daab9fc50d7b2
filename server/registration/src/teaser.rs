//! A TEASER++-class robust registration solver.
//!
//! Pipeline (after Yang, Shi and Carlone, "TEASER: Fast and Certifiable Point Cloud Registration"):
//! 1. Pairwise invariants: for correspondences i, j the distances |s_i - s_j| and |d_i - d_j| agree
//!    within `2 * noise_bound * sqrt(cbar2)` when both are inliers, whatever the rotation and
//!    translation. Consistent pairs are the edges of a graph.
//! 2. The maximum clique of that graph keeps mutually consistent correspondences ([`crate::clique`]).
//! 3. Rotation by graduated non-convexity with a truncated least squares cost (GNC-TLS) on the
//!    translation-invariant measurements (TIMs) d_j - d_i = R (s_j - s_i) of the clique.
//! 4. Translation per axis by adaptive voting: the largest set of d - R s values within the noise bound.
//! 5. Inliers: correspondences whose residual is within `noise_bound * sqrt(cbar2)`; a final
//!    least-squares fit on them polishes the estimate (TEASER++ stops at 4; the polish removes the
//!    voting's quantisation at no risk, because only certified-consistent inliers enter it).
//!
//! Validity: the result is invalid when fewer than `min_inliers` correspondences agree (a few
//! mutually consistent pairs arise by chance among hundreds of outliers) or when the inliers are
//! degenerate (coincident or collinear, leaving a rotation undetermined).

use std::time::Duration;

use nalgebra::{Rotation3, Vector3};

use crate::clique::{max_clique, Budget, Graph};
use crate::kabsch::{principal_spreads, weighted_kabsch, weighted_rotation};
use crate::Rigid;

/// Default node budget of the clique search. Sized on the searches of `pntr eval` over two synthetic
/// apartments with out-of-map queries and robot effects (14,230 searches, BENCHMARKS.md, "The clique
/// search's budget in nodes"): the largest that finished within the former 10 ms budget visited
/// 4,539 nodes, at 0.3-0.4 nodes a microsecond on one 2 vCPU EPYC core; 8,192 keeps each of them and
/// bounds a search at about 25 ms there.
pub const CLIQUE_NODES: u64 = 8192;

/// Solver parameters.
#[derive(Debug, Clone, PartialEq)]
pub struct TeaserParams {
    /// Bound on an inlier's residual |d - (R s + t)|, metres. Default 0.05: depth from an RGB-D camera
    /// up to 10 m, back-projected at keypoints localised to about a pixel, lands within a few
    /// centimetres indoors (the HPointLoc reference uses the same 5 cm).
    pub noise_bound: f64,
    /// Squared multiple of the noise bound for the truncation (TEASER's c-bar squared). Default 1.
    pub cbar2: f64,
    /// GNC continuation factor (TEASER++: 1.4).
    pub gnc_factor: f64,
    /// Maximum GNC iterations (TEASER++: 100).
    pub max_iterations: usize,
    /// GNC stops when the cost changes less than this (TEASER++: 1e-12).
    pub cost_threshold: f64,
    /// Branch-and-bound nodes the exact maximum clique search may visit before the best clique found
    /// so far is used ([`crate::clique::Budget`]). A count, not a time, so a registration answers
    /// the same on a machine at rest and under load.
    pub clique_nodes: u64,
    /// Wall-clock safety net of the clique search: a search stops here even within its node budget
    /// (a machine many times slower than the node budget was sized on).
    pub clique_budget: Duration,
    /// Fewest inliers for a valid result. Default 10: among a few hundred random correspondences,
    /// chance alone produces consistent sets of 4 or 5.
    pub min_inliers: usize,
}

impl Default for TeaserParams {
    fn default() -> Self {
        Self {
            noise_bound: 0.05,
            cbar2: 1.0,
            gnc_factor: 1.4,
            max_iterations: 100,
            cost_threshold: 1e-12,
            clique_nodes: CLIQUE_NODES,
            clique_budget: Duration::from_millis(50),
            min_inliers: 10,
        }
    }
}

/// What the solver found.
#[derive(Debug, Clone, PartialEq)]
pub struct TeaserResult {
    /// `dst = rotation * src + translation` (identity when invalid).
    pub transform: Rigid,
    /// Indices of the correspondences consistent with `transform`.
    pub inliers: Vec<usize>,
    /// Size of the maximum clique of the consistency graph.
    pub clique_size: usize,
    /// Whether the clique is proven maximum (false when the node budget, or the time limit, cut the
    /// search).
    pub clique_exact: bool,
    /// Whether the estimate can be trusted.
    pub valid: bool,
    /// Why the result is invalid, when it is.
    pub reason: Option<String>,
}

impl TeaserResult {
    fn invalid(reason: impl Into<String>, clique_size: usize, clique_exact: bool) -> Self {
        Self {
            transform: Rigid::identity(),
            inliers: Vec::new(),
            clique_size,
            clique_exact,
            valid: false,
            reason: Some(reason.into()),
        }
    }
}

/// Graduated non-convexity with truncated least squares for the rotation of `b = R a`.
/// `c2` is the squared residual bound of an inlier measurement.
pub fn gnc_tls_rotation(
    a: &[Vector3<f64>],
    b: &[Vector3<f64>],
    c2: f64,
    p: &TeaserParams,
) -> Option<Rotation3<f64>> {
    let n = a.len();
    let mut w = vec![1.0; n];
    let mut r = weighted_rotation(a, b, &w)?;
    let res2 = |r: &Rotation3<f64>, i: usize| (b[i] - r * a[i]).norm_squared();
    let max_r2 = (0..n).map(|i| res2(&r, i)).fold(0.0, f64::max);
    if max_r2 <= c2 {
        // Every measurement is an inlier of the least-squares solution: it is the TLS optimum.
        return Some(r);
    }
    let mut mu = 1.0 / (2.0 * max_r2 / c2 - 1.0);
    let mut prev_cost = f64::INFINITY;
    for _ in 0..p.max_iterations {
        let th1 = (mu + 1.0) / mu * c2;
        let th2 = mu / (mu + 1.0) * c2;
        let mut cost = 0.0;
        for (i, wi) in w.iter_mut().enumerate() {
            let e = res2(&r, i);
            *wi = if e >= th1 {
                0.0
            } else if e <= th2 {
                1.0
            } else {
                (c2 * mu * (mu + 1.0) / e).sqrt() - mu
            };
            cost += *wi * e;
        }
        r = weighted_rotation(a, b, &w)?;
        if (cost - prev_cost).abs() < p.cost_threshold || w.iter().all(|&x| x == 0.0 || x == 1.0) {
            break;
        }
        prev_cost = cost;
        mu *= p.gnc_factor;
    }
    Some(r)
}

/// Adaptive voting: the value with the most samples within their bound of it (`bounds[i]` for
/// `values[i]`), as the mean of that set weighted by `(bounds[0] / bound)^2` (the plain mean when
/// every bound is the same).
fn vote(values: &[f64], bounds: &[f64]) -> f64 {
    // Sweep the interval endpoints: the depth of overlap of [v - b, v + b] intervals.
    let mut ev: Vec<(f64, i32, f64)> = Vec::with_capacity(values.len() * 2);
    for (&v, &b) in values.iter().zip(bounds) {
        ev.push((v - b, 1, b));
        ev.push((v + b, -1, b));
    }
    ev.sort_by(|x, y| x.0.total_cmp(&y.0).then(y.1.cmp(&x.1)));
    let (mut depth, mut best, mut at) = (0, 0, values[0]);
    for (x, d, b) in ev {
        depth += d;
        if depth > best {
            best = depth;
            at = x + b;
        }
    }
    let (mut sum, mut total) = (0.0, 0.0);
    for (&v, &b) in values.iter().zip(bounds) {
        if (v - at).abs() <= b {
            let w = (bounds[0] / b).powi(2);
            sum += w * v;
            total += w;
        }
    }
    if total > 0.0 {
        sum / total
    } else {
        0.0
    }
}

fn tim_pairs(k: usize) -> Vec<(usize, usize)> {
    if k <= 120 {
        (0..k)
            .flat_map(|i| (i + 1..k).map(move |j| (i, j)))
            .collect()
    } else {
        // Enough TIMs for a well-determined rotation at bounded cost: each vertex with a few others
        // at different strides.
        let mut out = Vec::with_capacity(k * 4);
        for i in 0..k {
            for s in [1, 7, 31, k / 2] {
                let j = (i + s) % k;
                if j != i {
                    out.push((i.min(j), i.max(j)));
                }
            }
        }
        out.sort_unstable();
        out.dedup();
        out
    }
}

/// The graph whose edges join correspondences i, j with `| |s_i - s_j| - |d_i - d_j| | <= bound`.
///
/// Structure of arrays in f32 so the inner loop vectorises (the quadratic part of the solver: 2M pairs
/// for N = 2000); f32 resolves lengths of tens of metres to micrometres, far below any noise bound.
pub fn consistency_graph(
    src: &[Vector3<f64>],
    dst: &[Vector3<f64>],
    finite: &[bool],
    bound: f64,
) -> Graph {
    let bound = bound as f32;
    graph_within(src, dst, finite, |_, _| bound)
}

/// As [`consistency_graph`] with a bound per correspondence: i and j are joined when
/// `| |s_i - s_j| - |d_i - d_j| | <= beta[i] + beta[j]` (`beta`: each correspondence's residual
/// bound times `sqrt(cbar2)`, TEASER's beta_i, metres).
pub fn consistency_graph_bounded(
    src: &[Vector3<f64>],
    dst: &[Vector3<f64>],
    finite: &[bool],
    beta: &[f64],
) -> Graph {
    let beta: Vec<f32> = beta.iter().map(|&b| b as f32).collect();
    graph_within(src, dst, finite, |i, j| beta[i] + beta[j])
}

/// The consistency graph with `bound(i, j)` for the pair i < j (a constant keeps the inner loop
/// as vectorisable as a plain comparison).
fn graph_within(
    src: &[Vector3<f64>],
    dst: &[Vector3<f64>],
    finite: &[bool],
    bound: impl Fn(usize, usize) -> f32,
) -> Graph {
    let n = src.len();
    let soa = |pts: &[Vector3<f64>], k: usize| -> Vec<f32> {
        pts.iter()
            .zip(finite)
            .map(|(p, &ok)| if ok { p[k] as f32 } else { f32::NAN })
            .collect()
    };
    let (sx, sy, sz) = (soa(src, 0), soa(src, 1), soa(src, 2));
    let (dx, dy, dz) = (soa(dst, 0), soa(dst, 1), soa(dst, 2));
    let mut g = Graph::new(n);
    let mut diff = vec![0f32; n];
    for i in 0..n {
        if !finite[i] {
            continue;
        }
        let m = n - i - 1;
        let (a, b, c) = (&sx[i + 1..], &sy[i + 1..], &sz[i + 1..]);
        let (e, f, h) = (&dx[i + 1..], &dy[i + 1..], &dz[i + 1..]);
        for j in 0..m {
            let (u, v, w) = (a[j] - sx[i], b[j] - sy[i], c[j] - sz[i]);
            let (x, y, z) = (e[j] - dx[i], f[j] - dy[i], h[j] - dz[i]);
            let d = ((u * u + v * v + w * w).sqrt() - (x * x + y * y + z * z).sqrt()).abs();
            // Not above 0 when within the pair's bound; NaN (a non-finite partner) compares false.
            diff[j] = d - bound(i, i + 1 + j);
        }
        // 64 partners at a time, without a branch per pair (whether a pair agrees is close to
        // a coin toss among wrong matches).
        for (k, chunk) in diff[..m].chunks(64).enumerate() {
            let mask = chunk
                .iter()
                .enumerate()
                .fold(0u64, |acc, (b, &d)| acc | (((d <= 0.0) as u64) << b));
            g.add_edges_from(i, i + 1 + 64 * k, mask);
        }
    }
    g
}

/// Register `src` to `dst` (paired by index) robustly.
///
/// Both sets are first moved to their centroids (of the finite points), so coordinates far from the
/// origin (UTM-sized, 1e6 m) lose nothing in the single-precision consistency graph; the answer is
/// moved back: `dst = R (src - c_s) + t_c + c_d`.
pub fn solve(src: &[Vector3<f64>], dst: &[Vector3<f64>], p: &TeaserParams) -> TeaserResult {
    solve_with_bounds(src, dst, None, p)
}

/// [`solve`] with a residual bound per correspondence (metres, parallel to `src`), in place of
/// `p.noise_bound` for each: for a sensor whose noise depends on the point (depth noise growing
/// with range). Two correspondences are consistent when their distances agree within the sum of
/// their bounds times `sqrt(cbar2)`; the rotation's measurements are
/// normalised by their pairs' bounds, the translation is voted with each value's own bound, and
/// the polish weights each inlier by `(noise_bound / bound)^2`. `None` (or every bound equal to
/// `noise_bound`) is exactly [`solve`]. A bound that is not finite and positive, or a slice of
/// another length, gives an invalid result that says so.
pub fn solve_with_bounds(
    src: &[Vector3<f64>],
    dst: &[Vector3<f64>],
    bounds: Option<&[f64]>,
    p: &TeaserParams,
) -> TeaserResult {
    if let Some(b) = bounds {
        if b.len() != src.len() {
            return TeaserResult::invalid(
                format!("{} bounds for {} correspondences", b.len(), src.len()),
                0,
                true,
            );
        }
        if let Some(bad) = b.iter().find(|x| !(x.is_finite() && **x > 0.0)) {
            return TeaserResult::invalid(
                format!("a correspondence's noise bound is {bad} m; bounds must be positive"),
                0,
                true,
            );
        }
    }
    let centroid = |pts: &[Vector3<f64>]| {
        let finite: Vec<&Vector3<f64>> = pts
            .iter()
            .filter(|v| v.iter().all(|x| x.is_finite()))
            .collect();
        if finite.is_empty() {
            return Vector3::zeros();
        }
        finite.iter().copied().sum::<Vector3<f64>>() / finite.len() as f64
    };
    let (cs, cd) = (centroid(src), centroid(dst));
    let s: Vec<Vector3<f64>> = src.iter().map(|v| v - cs).collect();
    let d: Vec<Vector3<f64>> = dst.iter().map(|v| v - cd).collect();
    let mut r = solve_centred(&s, &d, bounds, p);
    if r.valid {
        r.transform.translation += cd - r.transform.rotation * cs;
    }
    r
}

/// [`solve`] on sets already near the origin.
fn solve_centred(
    src: &[Vector3<f64>],
    dst: &[Vector3<f64>],
    bounds: Option<&[f64]>,
    p: &TeaserParams,
) -> TeaserResult {
    if src.len() != dst.len() {
        return TeaserResult::invalid(
            format!(
                "{} source points but {} destination points",
                src.len(),
                dst.len()
            ),
            0,
            true,
        );
    }
    let n = src.len();
    if n < 3 {
        return TeaserResult::invalid(
            format!("{n} correspondences; at least 3 are needed"),
            0,
            true,
        );
    }
    let finite: Vec<bool> = (0..n)
        .map(|i| src[i].iter().chain(dst[i].iter()).all(|v| v.is_finite()))
        .collect();
    let sc = p.cbar2.sqrt();
    // Each correspondence's residual bound; a uniform one keeps the fast graph below.
    let uniform = bounds.is_none_or(|b| b.iter().all(|&x| x == p.noise_bound));
    let bound_of = |i: usize| match bounds {
        Some(b) if !uniform => b[i],
        _ => p.noise_bound,
    };
    // 1. Consistency graph of pairwise invariants.
    let g = if uniform {
        consistency_graph(src, dst, &finite, 2.0 * p.noise_bound * sc)
    } else {
        let beta: Vec<f64> = (0..n).map(|i| bound_of(i) * sc).collect();
        consistency_graph_bounded(src, dst, &finite, &beta)
    };
    // 2. Maximum clique.
    let clique = max_clique(
        &g,
        Budget {
            nodes: p.clique_nodes,
            time: p.clique_budget,
        },
    );
    let (k, exact) = (clique.vertices.len(), clique.exact);
    if k < p.min_inliers.max(3) {
        return TeaserResult::invalid(
            format!(
                "only {k} mutually consistent correspondences (need {})",
                p.min_inliers.max(3)
            ),
            k,
            exact,
        );
    }
    let cs: Vec<Vector3<f64>> = clique.vertices.iter().map(|&i| src[i]).collect();
    let cd: Vec<Vector3<f64>> = clique.vertices.iter().map(|&i| dst[i]).collect();
    let cb: Vec<f64> = clique.vertices.iter().map(|&i| bound_of(i)).collect();
    // 3. Rotation from TIMs, each scaled so that its pair's bound becomes the uniform one (a
    // factor of exactly 1 when the bounds are uniform).
    let pairs = tim_pairs(k);
    let scale = |i: usize, j: usize| 2.0 * p.noise_bound / (cb[i] + cb[j]);
    let ta: Vec<Vector3<f64>> = pairs
        .iter()
        .map(|&(i, j)| (cs[j] - cs[i]) * scale(i, j))
        .collect();
    let tb: Vec<Vector3<f64>> = pairs
        .iter()
        .map(|&(i, j)| (cd[j] - cd[i]) * scale(i, j))
        .collect();
    let tim_bound2 = p.cbar2 * (2.0 * p.noise_bound).powi(2);
    let Some(rotation) = gnc_tls_rotation(&ta, &tb, tim_bound2, p) else {
        return TeaserResult::invalid(
            "rotation estimation failed (no usable measurements)",
            k,
            exact,
        );
    };
    // 4. Translation by adaptive voting per axis.
    let vote_bounds: Vec<f64> = cb.iter().map(|b| b * sc).collect();
    let mut translation = Vector3::zeros();
    for axis in 0..3 {
        let vals: Vec<f64> = cs
            .iter()
            .zip(&cd)
            .map(|(s, d)| (d - rotation * s)[axis])
            .collect();
        translation[axis] = vote(&vals, &vote_bounds);
    }
    // 5. Inliers and a least-squares polish on them.
    let inliers_of = |t: &Rigid| -> Vec<usize> {
        (0..n)
            .filter(|&i| finite[i] && (dst[i] - t.apply(&src[i])).norm() <= bound_of(i) * sc)
            .collect()
    };
    let mut est = Rigid {
        rotation,
        translation,
    };
    let mut inliers = inliers_of(&est);
    if inliers.len() >= 3 {
        let s: Vec<_> = inliers.iter().map(|&i| src[i]).collect();
        let d: Vec<_> = inliers.iter().map(|&i| dst[i]).collect();
        let w: Vec<f64> = inliers
            .iter()
            .map(|&i| (p.noise_bound / bound_of(i)).powi(2))
            .collect();
        if let Some(polished) = weighted_kabsch(&s, &d, &w) {
            let again = inliers_of(&polished);
            if again.len() >= inliers.len() {
                est = polished;
                inliers = again;
            }
        }
    }
    if inliers.len() < p.min_inliers.max(3) {
        return TeaserResult::invalid(
            format!(
                "only {} inliers after estimation (need {})",
                inliers.len(),
                p.min_inliers.max(3)
            ),
            k,
            exact,
        );
    }
    if let Some(why) = degenerate(
        &inliers.iter().map(|&i| src[i]).collect::<Vec<_>>(),
        p.noise_bound,
    ) {
        return TeaserResult::invalid(why, k, exact);
    }
    TeaserResult {
        transform: est,
        inliers,
        clique_size: k,
        clique_exact: exact,
        valid: true,
        reason: None,
    }
}

/// Why a point set cannot fix a rotation: all points within the noise of one point, or of one line.
pub fn degenerate(points: &[Vector3<f64>], noise: f64) -> Option<String> {
    let ev = principal_spreads(points);
    // Spread (standard deviation) along the two main directions.
    let floor = 0.5 * noise;
    if ev[0] < floor {
        return Some("degenerate: the inlier points coincide".into());
    }
    if ev[1] < floor.max(1e-3 * ev[0]) {
        return Some("degenerate: the inlier points are collinear".into());
    }
    None
}
