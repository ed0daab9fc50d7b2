//! How noisy a frame's depth is, measured on the frame itself.
//!
//! Structured-light and stereo RGB-D cameras measure disparity, so their depth noise grows with the
//! square of the range: `sigma_z = k * z^2` (Khoshelham and Elberink, 2012, for the Kinect: k about
//! 1.4e-3 per metre; stereo cameras of robots are of the same order or worse). A fixed registration
//! bound that suits a clean map view then rejects the right matches of far surfaces in a robot's
//! frame. `k` is also the standard deviation of the inverse depth `w = 1 / z` (d(1/z) = -dz / z^2),
//! whatever the range, and on any plane `w` is an affine function of the pixel, so its second
//! differences along rows and columns vanish there and keep only the noise: for independent noise a
//! second difference `w[i-1] - 2 w[i] + w[i+1]` has standard deviation `sqrt(6) k`. Depth edges and
//! curved surfaces give large second differences too, but they are a minority of an indoor frame's
//! pixels, so the median absolute value (scaled to a standard deviation, 1.4826 MAD) ignores them.
//!
//! The estimate assumes noise independent from pixel to pixel. A sensor whose noise is correlated
//! between neighbours (a stereo matcher's smoothing, a structured-light pattern's speckle) measures
//! less than its true `k`, so the bounds grow less: the estimate errs toward the fixed bound, never
//! toward wider ones.
//!
//! A rendered or fused depth (HPointLoc's, a mapping run's) measures near 0, and
//! [`depth_noise_per_m2`] answers 0 below [`MIN_DEPTH_NOISE_PER_M2`], so such frames keep every
//! registration bound as it was.

use pntr_core::DepthMap;

/// Below this `k` (per metre; 0.2 mm of noise at 1 m, 1.8 mm at 3 m) a frame counts as noise-free.
pub const MIN_DEPTH_NOISE_PER_M2: f64 = 2e-4;
/// Fewest second differences for an estimate; fewer valid triples answer 0.
const MIN_SAMPLES: usize = 256;
/// Rows (for the differences along rows) and columns (for those along columns) are taken every
/// this many: about 40,000 differences for 256 x 256, a median within 1% of all of them.
const STRIDE: usize = 3;
/// Standard deviation of one second difference of unit-variance independent noise (1 + 4 + 1).
const SECOND_DIFFERENCE_SIGMA: f64 = 2.449_489_742_783_178;
/// 1 / Phi^-1(3/4): a median absolute deviation of normal samples times this is their sigma.
const MAD_TO_SIGMA: f64 = 1.482_602_218_505_602;

/// The `k` of `sigma_z = k * z^2` for `depth` (metres; 0 = invalid), in 1/m, from the second
/// differences of the inverse depth along rows and columns over every three consecutive valid
/// pixels, on every third row and column (see the module docs). 0 when the frame measures below
/// [`MIN_DEPTH_NOISE_PER_M2`], has fewer than a few hundred valid triples, or has samples that
/// disagree with its size. Cost: about 0.1 ms at
/// 256 x 256.
pub fn depth_noise_per_m2(depth: &DepthMap) -> f64 {
    let (w, h) = (depth.width as usize, depth.height as usize);
    if depth.data.len() != w * h {
        return 0.0;
    }
    let inv: Vec<f32> = depth
        .data
        .iter()
        .map(|&z| {
            if z.is_finite() && z > 0.0 {
                1.0 / z
            } else {
                0.0
            }
        })
        .collect();
    let mut diffs: Vec<f32> = Vec::with_capacity(2 * w * h / STRIDE + 1);
    let mut push = |a: f32, b: f32, c: f32| {
        if a > 0.0 && b > 0.0 && c > 0.0 {
            diffs.push((a - 2.0 * b + c).abs());
        }
    };
    for r in (0..h).step_by(STRIDE) {
        let row = &inv[r * w..(r + 1) * w];
        for t in row.windows(3) {
            push(t[0], t[1], t[2]);
        }
    }
    for r in 1..h.saturating_sub(1) {
        for c in (0..w).step_by(STRIDE) {
            push(inv[(r - 1) * w + c], inv[r * w + c], inv[(r + 1) * w + c]);
        }
    }
    if diffs.len() < MIN_SAMPLES {
        return 0.0;
    }
    let mid = diffs.len() / 2;
    let (_, median, _) = diffs.select_nth_unstable_by(mid, f32::total_cmp);
    let k = *median as f64 * MAD_TO_SIGMA / SECOND_DIFFERENCE_SIGMA;
    if k < MIN_DEPTH_NOISE_PER_M2 {
        0.0
    } else {
        k
    }
}

/// Residual bound for a correspondence whose query point lies at range `z_m`: the clean bound
/// `base_m` and `sigmas` standard deviations of the depth noise `k * z^2` added in quadrature,
/// metres. Exactly `base_m` when `k` is 0.
pub fn bound_at(base_m: f64, k_per_m2: f64, sigmas: f64, z_m: f64) -> f64 {
    if k_per_m2 <= 0.0 {
        return base_m;
    }
    let s = sigmas * k_per_m2 * z_m * z_m;
    (base_m * base_m + s * s).sqrt()
}

/// Registration bounds per keypoint of one query, measured only when first asked for: a frame
/// whose candidates all register with the fixed bound never pays for the estimate.
pub struct RangeBounds<'a> {
    depth: &'a DepthMap,
    /// Query keypoints' 3D points (camera frame, metres), `None` without depth.
    points: &'a [Option<nalgebra::Vector3<f64>>],
    base_m: f64,
    sigmas: f64,
    bounds: std::cell::OnceCell<Option<Vec<f64>>>,
}

impl<'a> RangeBounds<'a> {
    /// Bounds for `points` (parallel to the query's keypoints) from the noise of `depth` (the
    /// frame as sent), `sigmas` standard deviations in quadrature with `base_m`; `sigmas` 0 is off.
    pub fn new(
        depth: &'a DepthMap,
        points: &'a [Option<nalgebra::Vector3<f64>>],
        base_m: f64,
        sigmas: f64,
    ) -> Self {
        Self {
            depth,
            points,
            base_m,
            sigmas,
            bounds: std::cell::OnceCell::new(),
        }
    }

    /// Each keypoint's bound (metres, [`bound_at`] of its range; `base_m` for one without depth),
    /// or `None` when the frame's depth is clean or the widening is off.
    pub fn get(&self) -> Option<&[f64]> {
        self.bounds
            .get_or_init(|| {
                if self.sigmas <= 0.0 {
                    return None;
                }
                let k = depth_noise_per_m2(self.depth);
                (k > 0.0).then(|| {
                    self.points
                        .iter()
                        .map(|p| bound_at(self.base_m, k, self.sigmas, p.map_or(0.0, |p| p.z)))
                        .collect()
                })
            })
            .as_deref()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    /// A room corner seen from inside: a floor and two walls (planes), with a depth edge between
    /// a box and the wall behind it, and noise `k z^2` drawn for `seed`.
    fn frame(k: f64, seed: u64) -> DepthMap {
        let (w, h) = (256usize, 256usize);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let mut data = Vec::with_capacity(w * h);
        for r in 0..h {
            for c in 0..w {
                // Ray (x, y, 1) of a 90 degree camera; planes n . p = d.
                let (x, y) = ((c as f64 - 127.5) / 127.5, (r as f64 - 127.5) / 127.5);
                let mut z = f64::INFINITY;
                for (n, d) in [
                    ([0.0, 1.0, 0.0], 1.2),  // floor 1.2 m below
                    ([0.0, 0.0, 1.0], 4.5),  // back wall
                    ([1.0, 0.0, 0.3], 2.0),  // a side wall, slanted
                    ([-1.0, 0.0, 0.2], 2.5), // the other one
                ] {
                    let dot: f64 = n[0] * x + n[1] * y + n[2];
                    if dot > 1e-9 {
                        z = z.min(d / dot);
                    }
                }
                if (100..140).contains(&c) && (150..200).contains(&r) {
                    z = z.min(2.0); // a box in front
                }
                let noise: f64 = rng.sample(rand_distr::StandardNormal);
                data.push((z + k * z * z * noise) as f32);
            }
        }
        DepthMap::from_metres(w as u32, h as u32, data).unwrap()
    }

    #[test]
    fn the_noise_of_a_depth_sensor_is_measured_within_ten_percent() {
        for (k, seed) in [(0.003, 1), (0.0015, 2), (0.006, 3)] {
            let got = depth_noise_per_m2(&frame(k, seed));
            assert!((got - k).abs() < 0.1 * k, "k {k}: measured {got}");
        }
    }

    #[test]
    fn a_rendered_depth_is_noise_free_and_keeps_the_bound() {
        assert_eq!(depth_noise_per_m2(&frame(0.0, 4)), 0.0);
        assert_eq!(bound_at(0.05, 0.0, 3.0, 4.0), 0.05);
        let far = bound_at(0.05, 0.003, 3.0, 4.0);
        assert!((far - (0.05f64.powi(2) + 0.144f64.powi(2)).sqrt()).abs() < 1e-12);
    }

    #[test]
    fn dropouts_and_a_tiny_frame_do_not_break_the_estimate() {
        let mut d = frame(0.003, 5);
        for (i, z) in d.data.iter_mut().enumerate() {
            if i % 7 == 0 {
                *z = 0.0;
            }
        }
        let got = depth_noise_per_m2(&d);
        assert!((got - 0.003).abs() < 0.0006, "measured {got}");
        let tiny = DepthMap::from_metres(4, 4, vec![1.0; 16]).unwrap();
        assert_eq!(depth_noise_per_m2(&tiny), 0.0);
    }
}
