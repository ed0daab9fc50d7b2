//! Pose covariance of a 3D-3D registration from its inlier residuals.
//!
//! Linearising `dst_i = exp([dθ]) R src_i + t + dp` around the estimate gives the Jacobian
//! `J_i = [I, -[R src_i]x]` of each inlier's residual with respect to (dp, dθ): a shift of the
//! position and a small rotation about the axes of the `dst` frame, centred on the position (the ROS
//! `PoseWithCovariance` order: x, y, z, rotation about x, y, z). With isotropic point noise of variance
//! σ² the Gauss-Newton covariance is `σ² (Σ J_iᵀ J_i)⁻¹`; σ² is estimated from the inlier residuals
//! (sum of squares over 3n - 6 degrees of freedom), floored at `min_sigma_m²` so that a handful of
//! lucky inliers never claims millimetre certainty. More inliers with the same spread shrink it as 1/n.
//! (Hartley & Zisserman, ch. 5: covariance of an ML estimate; Censi, ICRA 2007, for the ICP case.)

use nalgebra::{Matrix3, Matrix6, Vector3};

use crate::Rigid;

/// Covariance of `dst_from_src` over inlier pairs (`src[i]`, `dst[i]`), order (x, y, z, rx, ry, rz)
/// in the `dst` frame, metres² and radians². Symmetric positive definite for three or more inliers
/// that are not collinear; `None` otherwise.
pub fn point_to_point_covariance(
    src: &[Vector3<f64>],
    dst: &[Vector3<f64>],
    transform: &Rigid,
    min_sigma_m: f64,
) -> Option<Matrix6<f64>> {
    let n = src.len().min(dst.len());
    if n < 3 {
        return None;
    }
    let mut h = Matrix6::<f64>::zeros();
    let mut ss = 0.0;
    for (s, d) in src.iter().zip(dst) {
        let rs = transform.rotation * s;
        let r = d - (rs + transform.translation);
        ss += r.norm_squared();
        let skew = -rs.cross_matrix();
        let mut j = nalgebra::Matrix3x6::<f64>::zeros();
        j.fixed_view_mut::<3, 3>(0, 0)
            .copy_from(&Matrix3::identity());
        j.fixed_view_mut::<3, 3>(0, 3).copy_from(&skew);
        h += j.transpose() * j;
    }
    let dof = (3 * n).saturating_sub(6).max(1) as f64;
    let sigma2 = (ss / dof).max(min_sigma_m * min_sigma_m);
    let cov = h.try_inverse()? * sigma2;
    let cov = (cov + cov.transpose()) * 0.5;
    cov.cholesky().map(|_| cov)
}

/// Express a covariance of `b_from_c` (order x, y, z, rx, ry, rz in frame b) in frame a, for
/// `a_from_c = a_from_b * b_from_c`: both blocks rotate with `a_from_b`'s rotation (the position of c
/// moves rigidly with frame b, and a small rotation about b's axes is one about the rotated axes).
pub fn rotate_covariance(cov: &Matrix6<f64>, a_from_b: &nalgebra::Rotation3<f64>) -> Matrix6<f64> {
    let mut g = Matrix6::<f64>::zeros();
    g.fixed_view_mut::<3, 3>(0, 0).copy_from(a_from_b.matrix());
    g.fixed_view_mut::<3, 3>(3, 3).copy_from(a_from_b.matrix());
    g * cov * g.transpose()
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Rotation3;
    use rand::{Rng, SeedableRng};

    fn problem(n: usize, seed: u64) -> (Vec<Vector3<f64>>, Vec<Vector3<f64>>, Rigid) {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let t = Rigid {
            rotation: Rotation3::from_euler_angles(0.1, -0.2, 0.3),
            translation: Vector3::new(1.0, 2.0, -0.5),
        };
        let mut src = Vec::new();
        let mut dst = Vec::new();
        for _ in 0..n {
            let s = Vector3::new(
                rng.gen_range(-2.0..2.0),
                rng.gen_range(-1.0..1.0),
                rng.gen_range(1.0..4.0),
            );
            let noise = Vector3::new(
                rng.gen_range(-0.01..0.01),
                rng.gen_range(-0.01..0.01),
                rng.gen_range(-0.01..0.01),
            );
            dst.push(t.rotation * s + t.translation + noise);
            src.push(s);
        }
        (src, dst, t)
    }

    #[test]
    fn covariance_is_spd_and_shrinks_with_more_inliers() {
        let (s, d, t) = problem(20, 1);
        let few = point_to_point_covariance(&s, &d, &t, 0.002).unwrap();
        let (s, d, t) = problem(200, 1);
        let many = point_to_point_covariance(&s, &d, &t, 0.002).unwrap();
        for c in [&few, &many] {
            assert!((c - c.transpose()).abs().max() < 1e-15);
            assert!(c.symmetric_eigenvalues().min() > 0.0);
        }
        assert!(
            many.trace() < few.trace() / 4.0,
            "{} vs {}",
            many.trace(),
            few.trace()
        );
        let rotated = rotate_covariance(&many, &Rotation3::from_euler_angles(0.3, 0.2, 0.1));
        assert!((rotated.trace() - many.trace()).abs() < 1e-12);
        // Collinear points cannot fix the rotation about their line.
        let line: Vec<Vector3<f64>> = (0..10).map(|i| Vector3::new(i as f64, 0.0, 0.0)).collect();
        assert!(point_to_point_covariance(&line, &line, &Rigid::identity(), 0.01).is_none());
    }
}
