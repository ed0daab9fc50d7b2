//! Closed-form least-squares rotation (and translation) between point sets.

use nalgebra::{Matrix3, Rotation3, Vector3};

use crate::Rigid;

/// The rotation `R` minimising `sum w_i |b_i - R a_i|^2` for vectors without translation (as the
/// translation-invariant measurements are). Returns `None` when the weights sum to zero.
pub fn weighted_rotation(
    a: &[Vector3<f64>],
    b: &[Vector3<f64>],
    w: &[f64],
) -> Option<Rotation3<f64>> {
    let mut h = Matrix3::zeros();
    let mut total = 0.0;
    for ((ai, bi), &wi) in a.iter().zip(b).zip(w) {
        // Without a branch (GNC's weights switch between 0 and 1 unpredictably): a weight that
        // is not positive adds zeros, `h + 0 == h` to the bit (`h` never holds -0), so the sums
        // are those of the positive weights alone, whatever its measurement holds.
        let keep = wi > 0.0;
        let only = |v: f64| if keep { v } else { 0.0 };
        let (x, y, z) = (wi * bi.x, wi * bi.y, wi * bi.z);
        // `h += wi * bi * ai.transpose()`, entry by entry: (wi * b_r) * a_c.
        h[(0, 0)] += only(x * ai.x);
        h[(0, 1)] += only(x * ai.y);
        h[(0, 2)] += only(x * ai.z);
        h[(1, 0)] += only(y * ai.x);
        h[(1, 1)] += only(y * ai.y);
        h[(1, 2)] += only(y * ai.z);
        h[(2, 0)] += only(z * ai.x);
        h[(2, 1)] += only(z * ai.y);
        h[(2, 2)] += only(z * ai.z);
        total += only(wi);
    }
    if total <= 0.0 {
        return None;
    }
    Some(rotation_from_cross_covariance(&h))
}

/// Nearest rotation to the cross-covariance `H = sum b a^T` (SVD with the reflection fixed).
fn rotation_from_cross_covariance(h: &Matrix3<f64>) -> Rotation3<f64> {
    let svd = h.svd(true, true);
    let (u, v_t) = (svd.u.expect("computed"), svd.v_t.expect("computed"));
    let d = (u * v_t).determinant().signum();
    let s = Matrix3::from_diagonal(&Vector3::new(1.0, 1.0, if d == 0.0 { 1.0 } else { d }));
    Rotation3::from_matrix_unchecked(u * s * v_t)
}

/// Weighted least-squares rigid transform with `dst ~ R src + t` (Kabsch/Umeyama without scale).
/// Returns `None` when the weights sum to zero.
pub fn weighted_kabsch(src: &[Vector3<f64>], dst: &[Vector3<f64>], w: &[f64]) -> Option<Rigid> {
    let total: f64 = w.iter().filter(|&&x| x > 0.0).sum();
    if total <= 0.0 || src.len() != dst.len() || src.len() != w.len() {
        return None;
    }
    let mut cs = Vector3::zeros();
    let mut cd = Vector3::zeros();
    for ((s, d), &wi) in src.iter().zip(dst).zip(w) {
        if wi > 0.0 {
            cs += wi * s;
            cd += wi * d;
        }
    }
    cs /= total;
    cd /= total;
    let mut h = Matrix3::zeros();
    for ((s, d), &wi) in src.iter().zip(dst).zip(w) {
        if wi > 0.0 {
            h += wi * (d - cd) * (s - cs).transpose();
        }
    }
    let rotation = rotation_from_cross_covariance(&h);
    Some(Rigid {
        rotation,
        translation: cd - rotation * cs,
    })
}

/// Standard deviations of `points` along their principal axes, largest first (all zero when empty).
pub(crate) fn principal_spreads(points: &[Vector3<f64>]) -> [f64; 3] {
    if points.is_empty() {
        return [0.0; 3];
    }
    let n = points.len() as f64;
    let c = points.iter().sum::<Vector3<f64>>() / n;
    let mut cov = Matrix3::zeros();
    for p in points {
        cov += (p - c) * (p - c).transpose();
    }
    cov /= n;
    let mut ev: Vec<f64> = cov
        .symmetric_eigenvalues()
        .iter()
        .map(|v| v.max(0.0).sqrt())
        .collect();
    ev.sort_by(|a, b| b.total_cmp(a));
    [ev[0], ev[1], ev[2]]
}

/// Unweighted least-squares rigid transform; `None` for empty or mismatched input.
pub fn kabsch(src: &[Vector3<f64>], dst: &[Vector3<f64>]) -> Option<Rigid> {
    weighted_kabsch(src, dst, &vec![1.0; src.len()])
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector3;

    #[test]
    fn recovers_an_exact_transform_and_never_a_reflection() {
        let r = Rotation3::from_euler_angles(0.3, -1.1, 2.0);
        let t = Vector3::new(1.0, -2.0, 0.5);
        let src: Vec<_> = (0..10)
            .map(|i| Vector3::new(i as f64, (i * i) as f64 * 0.1, (i as f64).sin()))
            .collect();
        let dst: Vec<_> = src.iter().map(|p| r * p + t).collect();
        let est = kabsch(&src, &dst).unwrap();
        assert!(est.rotation.angle_to(&r) < 1e-9);
        assert!((est.translation - t).norm() < 1e-9);
        // A mirrored target still yields a proper rotation.
        let mirrored: Vec<_> = src.iter().map(|p| Vector3::new(-p.x, p.y, p.z)).collect();
        let est = kabsch(&src, &mirrored).unwrap();
        assert!((est.rotation.matrix().determinant() - 1.0).abs() < 1e-9);
        assert!(kabsch(&[], &[]).is_none());
    }
}
