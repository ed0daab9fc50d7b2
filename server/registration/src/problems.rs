//! Generated registration problems with a known answer, for tests and benchmarks.

use nalgebra::{Rotation3, Unit, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal, UnitSphere};

use crate::Rigid;

/// A correspondence problem: `dst[i] = truth(src[i]) + noise` for inliers, random for outliers.
#[derive(Debug, Clone)]
pub struct Problem {
    /// Source points.
    pub src: Vec<Vector3<f64>>,
    /// Destination points.
    pub dst: Vec<Vector3<f64>>,
    /// The transform that generated the inliers.
    pub truth: Rigid,
    /// Which correspondences are inliers.
    pub is_inlier: Vec<bool>,
}

fn indoor_point(rng: &mut ChaCha8Rng) -> Vector3<f64> {
    Vector3::new(
        rng.gen_range(-4.0..4.0),
        rng.gen_range(-1.5..1.5),
        rng.gen_range(0.5..8.0),
    )
}

/// `n` correspondences in an indoor-sized volume (8 x 3 x 7.5 m), a random rotation and translation,
/// Gaussian noise of `sigma_m` on inlier destinations, and the first `round(n * outlier_ratio)`
/// correspondences replaced by random destinations in the same volume.
pub fn generate(seed: u64, n: usize, outlier_ratio: f64, sigma_m: f64) -> Problem {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let axis: [f64; 3] = UnitSphere.sample(&mut rng);
    let angle = rng.gen_range(0.0..std::f64::consts::PI);
    let truth = Rigid {
        rotation: Rotation3::from_axis_angle(&Unit::new_normalize(Vector3::from(axis)), angle),
        translation: Vector3::new(
            rng.gen_range(-5.0..5.0),
            rng.gen_range(-2.0..2.0),
            rng.gen_range(-5.0..5.0),
        ),
    };
    let noise = Normal::new(0.0, sigma_m.max(0.0)).expect("finite sigma");
    let n_out = (n as f64 * outlier_ratio.clamp(0.0, 1.0)).round() as usize;
    let mut p = Problem {
        src: Vec::with_capacity(n),
        dst: Vec::with_capacity(n),
        truth,
        is_inlier: Vec::with_capacity(n),
    };
    for i in 0..n {
        let s = indoor_point(&mut rng);
        let d = if i < n_out {
            truth.apply(&indoor_point(&mut rng))
        } else {
            truth.apply(&s)
                + Vector3::new(
                    noise.sample(&mut rng),
                    noise.sample(&mut rng),
                    noise.sample(&mut rng),
                )
        };
        p.src.push(s);
        p.dst.push(d);
        p.is_inlier.push(i >= n_out);
    }
    p
}

/// Rotation error (degrees, geodesic) and translation error (metres) of `est` against `truth`.
///
/// The angle comes from the chordal distance, `|R1 - R2|_F = 2 sqrt(2) sin(theta / 2)`, which stays
/// finite and accurate for tiny angles where `acos` of the trace rounds past 1 and gives NaN.
pub fn errors(est: &Rigid, truth: &Rigid) -> (f64, f64) {
    let chord = (est.rotation.matrix() - truth.rotation.matrix()).norm();
    let angle = 2.0 * (chord / (2.0 * 2f64.sqrt())).clamp(0.0, 1.0).asin();
    (
        angle.to_degrees(),
        (est.translation - truth.translation).norm(),
    )
}
