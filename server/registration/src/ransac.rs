//! Adaptive RANSAC for 3D-3D correspondences with a high inlier ratio (consecutive RGB-D frames).
//!
//! When most pairs are right, as between two frames a tenth of a second apart, a handful of random
//! minimal samples finds the transform: with an inlier share `w`, `k` samples of 3 miss every
//! all-inlier sample with probability `(1 - w³)^k`, about 1e-3 after 18 samples at `w = 0.7`. That is
//! far cheaper than a maximum clique over a dense consistency graph ([`crate::teaser`]), which is
//! built for the opposite case (few inliers among many outliers). Fischler and Bolles' RANSAC with
//! the adaptive stopping rule of Hartley and Zisserman (Multiple View Geometry, 4.7.1), minimal
//! samples solved by [`crate::kabsch`] and the best consensus refined by least squares on its
//! inliers until the set stops changing. Samples come from a fixed-seed generator: the same input
//! gives the same answer.

use nalgebra::Vector3;

use crate::kabsch::kabsch;
use crate::Rigid;

/// RANSAC settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RansacParams {
    /// Largest residual |dst - (R src + t)| of an inlier, metres.
    pub noise_bound: f64,
    /// Most minimal samples drawn.
    pub max_samples: usize,
    /// Accepted probability of never drawing an all-inlier sample.
    pub miss_probability: f64,
    /// Fewest inliers for a valid result.
    pub min_inliers: usize,
}

impl Default for RansacParams {
    fn default() -> Self {
        Self {
            noise_bound: 0.05,
            max_samples: 500,
            miss_probability: 1e-3,
            min_inliers: 10,
        }
    }
}

/// What RANSAC found.
#[derive(Debug, Clone, PartialEq)]
pub struct RansacResult {
    /// `dst = rotation * src + translation`, refined on the inliers (identity when invalid).
    pub transform: Rigid,
    /// Indices of the pairs within the noise bound of `transform`, ascending.
    pub inliers: Vec<usize>,
    /// Minimal samples drawn.
    pub samples: usize,
    /// At least `min_inliers` inliers.
    pub valid: bool,
}

fn inliers_of(t: &Rigid, src: &[Vector3<f64>], dst: &[Vector3<f64>], bound2: f64) -> Vec<usize> {
    (0..src.len())
        .filter(|&i| (dst[i] - t.apply(&src[i])).norm_squared() <= bound2)
        .collect()
}

/// Estimate the rigid transform taking `src[i]` to `dst[i]` (same length; extra elements of the
/// longer list are ignored). Invalid with fewer than 3 pairs or fewer than `min_inliers` inliers.
pub fn ransac_rigid(src: &[Vector3<f64>], dst: &[Vector3<f64>], p: &RansacParams) -> RansacResult {
    let n = src.len().min(dst.len());
    let invalid = |samples| RansacResult {
        transform: Rigid::identity(),
        inliers: Vec::new(),
        samples,
        valid: false,
    };
    if n < 3 {
        return invalid(0);
    }
    let bound2 = p.noise_bound * p.noise_bound;
    // SplitMix64 with a fixed seed: deterministic, and independent of any global generator.
    let mut state = 0x9E37_79B9_7F4A_7C15u64 ^ n as u64;
    let mut next = |m: usize| {
        state = state.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = state;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        ((z ^ (z >> 31)) % m as u64) as usize
    };
    let mut best: Vec<usize> = Vec::new();
    let mut needed = p.max_samples;
    let mut samples = 0;
    while samples < needed.min(p.max_samples) {
        samples += 1;
        let a = next(n);
        let b = next(n);
        let c = next(n);
        if a == b || b == c || a == c {
            continue;
        }
        // A sample whose three points are almost collinear fixes no rotation.
        let (s0, s1, s2) = (src[a], src[b], src[c]);
        if (s1 - s0).cross(&(s2 - s0)).norm() < 1e-4 {
            continue;
        }
        let Some(t) = kabsch(&[s0, s1, s2], &[dst[a], dst[b], dst[c]]) else {
            continue;
        };
        let found = inliers_of(&t, &src[..n], &dst[..n], bound2);
        if found.len() > best.len() {
            best = found;
            let w = best.len() as f64 / n as f64;
            let miss_one = 1.0 - w * w * w;
            needed = if miss_one <= 0.0 {
                samples
            } else {
                (p.miss_probability.ln() / miss_one.ln()).ceil().max(1.0) as usize
            };
        }
    }
    if best.len() < p.min_inliers.max(3) {
        return invalid(samples);
    }
    // Least squares on the consensus, until the inlier set stops changing (a few rounds).
    let mut transform = Rigid::identity();
    for _ in 0..5 {
        let s: Vec<_> = best.iter().map(|&i| src[i]).collect();
        let d: Vec<_> = best.iter().map(|&i| dst[i]).collect();
        let Some(t) = kabsch(&s, &d) else {
            return invalid(samples);
        };
        transform = t;
        let again = inliers_of(&transform, &src[..n], &dst[..n], bound2);
        if again == best || again.len() < p.min_inliers.max(3) {
            break;
        }
        best = again;
    }
    RansacResult {
        transform,
        valid: best.len() >= p.min_inliers.max(3),
        inliers: best,
        samples,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Rotation3;

    fn scene(
        n: usize,
        outliers: f64,
        offset: Vector3<f64>,
    ) -> (Vec<Vector3<f64>>, Vec<Vector3<f64>>, Rigid) {
        let mut s = 7u64;
        let mut r = || {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (s >> 11) as f64 / (1u64 << 53) as f64
        };
        let rotation = Rotation3::from_euler_angles(0.05, -0.2, 0.1);
        let truth = Rigid {
            rotation,
            translation: Vector3::new(0.3, -0.05, 0.12),
        };
        let (mut src, mut dst) = (Vec::new(), Vec::new());
        for i in 0..n {
            let p = offset + Vector3::new(4.0 * r() - 2.0, 2.0 * r(), 1.0 + 4.0 * r());
            src.push(p);
            if (i as f64) < outliers * n as f64 {
                dst.push(offset + Vector3::new(4.0 * r() - 2.0, 2.0 * r(), 1.0 + 4.0 * r()));
            } else {
                let noise = Vector3::new(r() - 0.5, r() - 0.5, r() - 0.5) * 0.01;
                dst.push(truth.apply(&p) + noise);
            }
        }
        (src, dst, truth)
    }

    #[test]
    fn finds_the_transform_and_the_inliers_with_few_samples() {
        for (outliers, offset) in [(0.0, 0.0), (0.3, 0.0), (0.5, 0.0), (0.3, 1e6)] {
            let (src, dst, truth) = scene(300, outliers, Vector3::repeat(offset));
            let r = ransac_rigid(&src, &dst, &RansacParams::default());
            assert!(r.valid, "outliers {outliers}");
            let inliers = (300.0 * (1.0 - outliers)) as usize;
            // Every true pair, and at most a chance outlier or two.
            assert!((0..300).filter(|i| *i >= 300 - inliers).count() <= r.inliers.len());
            assert!(
                r.inliers.len() <= inliers + 2,
                "{} of {inliers}",
                r.inliers.len()
            );
            let angle_deg = (r.transform.rotation.inverse() * truth.rotation)
                .angle()
                .to_degrees();
            assert!(angle_deg < 0.2, "{angle_deg} deg");
            let at = Vector3::repeat(offset);
            let moved = (r.transform.apply(&at) - truth.apply(&at)).norm();
            assert!(moved < 0.01, "{moved} m");
            assert!(r.samples <= 120, "{} samples at {outliers}", r.samples);
        }
    }

    #[test]
    fn refuses_pure_noise_and_tiny_inputs() {
        let (src, dst, _) = scene(200, 1.0, Vector3::zeros());
        let r = ransac_rigid(&src, &dst, &RansacParams::default());
        assert!(!r.valid || r.inliers.len() < 20, "{}", r.inliers.len());
        let r = ransac_rigid(&src[..2], &dst[..2], &RansacParams::default());
        assert!(!r.valid && r.samples == 0);
        assert_eq!(
            ransac_rigid(&src, &dst, &RansacParams::default()),
            ransac_rigid(&src, &dst, &RansacParams::default()),
            "deterministic"
        );
    }
}
