//! Perspective-n-point with RANSAC: the camera pose from 3D points and the pixels where they appear.
//!
//! Hypotheses come from a six-point direct linear transform on normalised image coordinates (with the
//! 3D points centred and scaled for conditioning); samples whose points are nearly coplanar are
//! skipped, since the DLT is degenerate there. The best hypothesis is refit on its inliers and refined
//! by Levenberg-Marquardt on the reprojection error in pixels (numeric Jacobian over a rotation vector
//! and the translation), the g2o-style refinement of the HPointLoc paper's PnP baselines.

use nalgebra::{DMatrix, Matrix3x4, Point2, Rotation3, SMatrix, SVector, Vector3};
use pntr_core::Intrinsics;
use rand::seq::index::sample;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use crate::kabsch::principal_spreads;
use crate::Rigid;

/// PnP-RANSAC parameters.
#[derive(Debug, Clone, PartialEq)]
pub struct PnpParams {
    /// Reprojection error of an inlier, pixels. Default 4.
    pub inlier_px: f64,
    /// RANSAC iteration cap. Default 2000.
    pub max_iterations: usize,
    /// Probability of drawing at least one all-inlier sample, for the adaptive stop. Default 0.999.
    pub confidence: f64,
    /// Fewest inliers for a valid result. Default 12.
    pub min_inliers: usize,
    /// Seed of the sampler (results are reproducible).
    pub seed: u64,
}

impl Default for PnpParams {
    fn default() -> Self {
        Self {
            inlier_px: 4.0,
            max_iterations: 2000,
            confidence: 0.999,
            min_inliers: 12,
            seed: 0,
        }
    }
}

/// The result of PnP.
#[derive(Debug, Clone, PartialEq)]
pub struct PnpResult {
    /// Maps points into the camera frame (OpenCV axes): `p_cam = R p + t`.
    pub camera_from_points: Rigid,
    /// Indices of the inliers.
    pub inliers: Vec<usize>,
    /// Whether the result can be used.
    pub valid: bool,
    /// Why not, when it cannot.
    pub reason: Option<String>,
}

fn normalised(k: &Intrinsics, uv: &Point2<f64>) -> (f64, f64) {
    ((uv.x - k.cx) / k.fx, (uv.y - k.cy) / k.fy)
}

/// Squared reprojection error in pixels, or infinity behind the camera.
fn reproj2(k: &Intrinsics, t: &Rigid, p: &Vector3<f64>, uv: &Point2<f64>) -> f64 {
    let c = t.apply(p);
    if c.z <= 1e-6 {
        return f64::INFINITY;
    }
    let du = k.fx * c.x / c.z + k.cx - uv.x;
    let dv = k.fy * c.y / c.z + k.cy - uv.y;
    du * du + dv * dv
}

fn spread_ok(pts: &[Vector3<f64>]) -> bool {
    let ev = principal_spreads(pts);
    ev[0] > 1e-9 && ev[2] > 0.05 * ev[0]
}

/// Direct linear transform from at least six non-coplanar points.
fn dlt(k: &Intrinsics, pts: &[Vector3<f64>], px: &[Point2<f64>]) -> Option<Rigid> {
    let n = pts.len();
    if n < 6 {
        return None;
    }
    let c = pts.iter().sum::<Vector3<f64>>() / n as f64;
    let s = (pts.iter().map(|p| (p - c).norm()).sum::<f64>() / n as f64).max(1e-12);
    let mut a = DMatrix::<f64>::zeros(2 * n, 12);
    for (i, (p, uv)) in pts.iter().zip(px).enumerate() {
        let q = (p - c) / s;
        let (x, y) = normalised(k, uv);
        let xh = [q.x, q.y, q.z, 1.0];
        for j in 0..4 {
            a[(2 * i, j)] = xh[j];
            a[(2 * i, 8 + j)] = -x * xh[j];
            a[(2 * i + 1, 4 + j)] = xh[j];
            a[(2 * i + 1, 8 + j)] = -y * xh[j];
        }
    }
    let ata = a.transpose() * &a;
    let eig = ata.symmetric_eigen();
    let (imin, _) = eig
        .eigenvalues
        .iter()
        .enumerate()
        .min_by(|x, y| x.1.total_cmp(y.1))?;
    let v = eig.eigenvectors.column(imin);
    let mut pn = Matrix3x4::from_fn(|r, col| v[r * 4 + col]);
    // Undo the normalisation: P = P' T with T = [I/s, -c/s; 0 1].
    let m = pn.fixed_view::<3, 3>(0, 0).into_owned() / s;
    let tcol = pn.column(3).into_owned() - m * c;
    pn.fixed_view_mut::<3, 3>(0, 0).copy_from(&m);
    pn.set_column(3, &tcol);
    let mut m = pn.fixed_view::<3, 3>(0, 0).into_owned();
    let mut tv = pn.column(3).into_owned();
    if m.determinant() < 0.0 {
        m = -m;
        tv = -tv;
    }
    let svd = m.svd(true, true);
    let (u, vt) = (svd.u?, svd.v_t?);
    let scale = svd.singular_values.mean();
    if scale <= 1e-12 {
        return None;
    }
    Some(Rigid {
        rotation: Rotation3::from_matrix_unchecked(u * vt),
        translation: tv / scale,
    })
}

fn residuals(
    k: &Intrinsics,
    t: &Rigid,
    pts: &[Vector3<f64>],
    px: &[Point2<f64>],
    out: &mut Vec<f64>,
) {
    out.clear();
    for (p, uv) in pts.iter().zip(px) {
        let c = t.apply(p);
        let z = c.z.max(1e-6);
        out.push(k.fx * c.x / z + k.cx - uv.x);
        out.push(k.fy * c.y / z + k.cy - uv.y);
    }
}

fn perturb(t: &Rigid, d: &SVector<f64, 6>) -> Rigid {
    Rigid {
        rotation: Rotation3::new(Vector3::new(d[0], d[1], d[2])) * t.rotation,
        translation: t.translation + Vector3::new(d[3], d[4], d[5]),
    }
}

/// Levenberg-Marquardt on the reprojection error of all given pairs.
pub fn refine_lm(k: &Intrinsics, init: Rigid, pts: &[Vector3<f64>], px: &[Point2<f64>]) -> Rigid {
    let mut est = init;
    let mut lambda = 1e-3;
    let mut r = Vec::new();
    let mut rp = Vec::new();
    residuals(k, &est, pts, px, &mut r);
    let mut cost: f64 = r.iter().map(|v| v * v).sum();
    for _ in 0..30 {
        // Numeric Jacobian, 6 columns.
        let n = r.len();
        let mut jtj = SMatrix::<f64, 6, 6>::zeros();
        let mut jtr = SVector::<f64, 6>::zeros();
        let mut cols: Vec<Vec<f64>> = Vec::with_capacity(6);
        for j in 0..6 {
            let h = if j < 3 {
                1e-6
            } else {
                1e-6 * (1.0 + est.translation.norm())
            };
            let mut d = SVector::<f64, 6>::zeros();
            d[j] = h;
            residuals(k, &perturb(&est, &d), pts, px, &mut rp);
            cols.push((0..n).map(|i| (rp[i] - r[i]) / h).collect());
        }
        for a in 0..6 {
            for b in a..6 {
                let v: f64 = cols[a].iter().zip(&cols[b]).map(|(x, y)| x * y).sum();
                jtj[(a, b)] = v;
                jtj[(b, a)] = v;
            }
            jtr[a] = cols[a].iter().zip(&r).map(|(x, y)| x * y).sum();
        }
        let mut improved = false;
        for _ in 0..8 {
            let mut h = jtj;
            for d in 0..6 {
                h[(d, d)] *= 1.0 + lambda;
            }
            let Some(step) = h.cholesky().map(|c| c.solve(&(-jtr))) else {
                lambda *= 10.0;
                continue;
            };
            let cand = perturb(&est, &step);
            residuals(k, &cand, pts, px, &mut rp);
            let c: f64 = rp.iter().map(|v| v * v).sum();
            if c < cost {
                est = cand;
                std::mem::swap(&mut r, &mut rp);
                let rel = (cost - c) / cost.max(1e-30);
                cost = c;
                lambda = (lambda * 0.3).max(1e-9);
                improved = rel > 1e-12;
                break;
            }
            lambda *= 10.0;
        }
        if !improved {
            break;
        }
    }
    est
}

/// Estimate the camera pose from 3D points (any frame) and their pixels (OpenCV convention).
pub fn pnp_ransac(
    k: &Intrinsics,
    pts: &[Vector3<f64>],
    px: &[Point2<f64>],
    p: &PnpParams,
) -> PnpResult {
    let fail = |reason: String| PnpResult {
        camera_from_points: Rigid::identity(),
        inliers: Vec::new(),
        valid: false,
        reason: Some(reason),
    };
    let n = pts.len();
    if n != px.len() {
        return fail(format!("{n} points but {} pixels", px.len()));
    }
    if n < 6 {
        return fail(format!("{n} correspondences; PnP needs at least 6"));
    }
    let th2 = p.inlier_px * p.inlier_px;
    let inliers_of = |t: &Rigid| -> Vec<usize> {
        (0..n)
            .filter(|&i| reproj2(k, t, &pts[i], &px[i]) <= th2)
            .collect()
    };
    let mut rng = ChaCha8Rng::seed_from_u64(p.seed);
    let mut best: Option<(Rigid, Vec<usize>)> = None;
    let mut needed = p.max_iterations;
    let mut it = 0;
    while it < needed.min(p.max_iterations) {
        it += 1;
        let idx = sample(&mut rng, n, 6).into_vec();
        let sp: Vec<_> = idx.iter().map(|&i| pts[i]).collect();
        if !spread_ok(&sp) {
            continue;
        }
        let su: Vec<_> = idx.iter().map(|&i| px[i]).collect();
        let Some(h) = dlt(k, &sp, &su) else { continue };
        let inl = inliers_of(&h);
        if inl.len() > best.as_ref().map_or(5, |b| b.1.len()) {
            let w = inl.len() as f64 / n as f64;
            let denom = (1.0 - w.powi(6)).max(1e-12).ln();
            needed = if denom < 0.0 {
                ((1.0 - p.confidence).ln() / denom).ceil() as usize
            } else {
                1
            };
            best = Some((h, inl));
        }
    }
    let Some((mut est, mut inl)) = best else {
        return fail("no hypothesis: every sample was degenerate (near-coplanar points)".into());
    };
    for _ in 0..2 {
        let ip: Vec<_> = inl.iter().map(|&i| pts[i]).collect();
        let iu: Vec<_> = inl.iter().map(|&i| px[i]).collect();
        est = refine_lm(k, est, &ip, &iu);
        let again = inliers_of(&est);
        if again.len() < inl.len() {
            break;
        }
        inl = again;
    }
    if inl.len() < p.min_inliers {
        return PnpResult {
            camera_from_points: est,
            reason: Some(format!(
                "only {} inliers (need {})",
                inl.len(),
                p.min_inliers
            )),
            inliers: inl,
            valid: false,
        };
    }
    PnpResult {
        camera_from_points: est,
        inliers: inl,
        valid: true,
        reason: None,
    }
}
