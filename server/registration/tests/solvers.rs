//! Property tests of the solvers on generated problems with known answers.

use nalgebra::{Rotation3, Vector3};
use pntr_registration::icp::{icp_clouds, icp_matched, IcpParams};
use pntr_registration::problems::{errors, generate, Problem};
use pntr_registration::teaser::{solve, solve_with_bounds, TeaserParams};
use pntr_registration::Rigid;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};

const NOISE_SIGMA_M: f64 = 0.01;

fn problem(rng: &mut ChaCha8Rng, n: usize, outlier_ratio: f64) -> Problem {
    generate(rng.gen(), n, outlier_ratio, NOISE_SIGMA_M)
}

#[test]
fn teaser_survives_up_to_95_percent_outliers() {
    let p = TeaserParams::default();
    for (k, ratio) in [0.0, 0.5, 0.9, 0.95].into_iter().enumerate() {
        for seed in 0..4 {
            let mut rng = ChaCha8Rng::seed_from_u64(100 * k as u64 + seed);
            let Problem {
                src,
                dst,
                truth,
                is_inlier,
            } = problem(&mut rng, 500, ratio);
            let r = solve(&src, &dst, &p);
            assert!(r.valid, "ratio {ratio} seed {seed}: {:?}", r.reason);
            let (rot, trans) = errors(&r.transform, &truth);
            assert!(
                rot < 1.0,
                "ratio {ratio} seed {seed}: rotation error {rot} deg"
            );
            assert!(
                trans < 3.0 * NOISE_SIGMA_M,
                "ratio {ratio} seed {seed}: translation error {trans} m"
            );
            let true_inliers = is_inlier.iter().filter(|&&b| b).count();
            let found_true = r.inliers.iter().filter(|&&i| is_inlier[i]).count();
            assert!(
                found_true as f64 >= 0.9 * true_inliers as f64,
                "found {found_true} of {true_inliers} inliers"
            );
            assert!(
                r.inliers.len() <= true_inliers + 10,
                "{} inliers claimed",
                r.inliers.len()
            );
        }
    }
}

#[test]
fn teaser_refuses_degenerate_and_hopeless_input() {
    let p = TeaserParams::default();
    let pts = |v: &[(f64, f64, f64)]| {
        v.iter()
            .map(|&(x, y, z)| Vector3::new(x, y, z))
            .collect::<Vec<_>>()
    };
    // Fewer than three correspondences.
    let r = solve(
        &pts(&[(0.0, 0.0, 0.0), (1.0, 0.0, 0.0)]),
        &pts(&[(0.0, 0.0, 0.0), (1.0, 0.0, 0.0)]),
        &p,
    );
    assert!(!r.valid && r.reason.unwrap().contains("at least 3"));
    assert!(!solve(&[], &[], &p).valid);
    // Mismatched lengths.
    assert!(!solve(&pts(&[(0.0, 0.0, 0.0); 5]), &pts(&[(0.0, 0.0, 0.0); 4]), &p).valid);
    // All points identical.
    let same = vec![Vector3::new(1.0, 2.0, 3.0); 50];
    let r = solve(&same, &same, &p);
    assert!(
        !r.valid && r.reason.as_deref().unwrap().contains("coincide"),
        "{:?}",
        r.reason
    );
    // All points on one line: rotation about it is undetermined.
    let line: Vec<_> = (0..50)
        .map(|i| Vector3::new(0.1 * i as f64, 0.0, 1.0))
        .collect();
    let r = solve(&line, &line, &p);
    assert!(
        !r.valid && r.reason.as_deref().unwrap().contains("collinear"),
        "{:?}",
        r.reason
    );
    // Every correspondence an outlier.
    for seed in 0..5 {
        let mut rng = ChaCha8Rng::seed_from_u64(900 + seed);
        let Problem { src, dst, .. } = problem(&mut rng, 500, 1.0);
        let r = solve(&src, &dst, &p);
        assert!(
            !r.valid,
            "seed {seed}: all outliers accepted with {} inliers",
            r.inliers.len()
        );
    }
    // Non-finite values are ignored, not propagated.
    let mut rng = ChaCha8Rng::seed_from_u64(77);
    let Problem {
        mut src,
        dst,
        truth,
        ..
    } = problem(&mut rng, 200, 0.3);
    src[150].x = f64::NAN;
    let r = solve(&src, &dst, &p);
    assert!(r.valid && !r.inliers.contains(&150));
    assert!(errors(&r.transform, &truth).0 < 1.0);
}

#[test]
fn dense_low_outlier_problem_does_not_blow_up() {
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let Problem {
        src, dst, truth, ..
    } = problem(&mut rng, 2000, 0.0);
    let r = solve(&src, &dst, &TeaserParams::default());
    assert!(r.valid);
    assert!(r.clique_size > 1900, "{}", r.clique_size);
    assert!(errors(&r.transform, &truth).0 < 0.2);
}

/// Points on the walls, floor and ceiling of a 6 x 3 x 5 m room, as a depth camera would see them.
fn room_cloud(rng: &mut ChaCha8Rng, n: usize) -> Vec<Vector3<f64>> {
    (0..n)
        .map(|_| {
            let (u, v) = (rng.gen_range(0.0..1.0), rng.gen_range(0.0..1.0));
            match rng.gen_range(0..5) {
                0 => Vector3::new(-3.0 + 6.0 * u, -1.25 + 2.8 * v, 5.0),
                1 => Vector3::new(-3.0, -1.25 + 2.8 * v, 5.0 * u),
                2 => Vector3::new(3.0, -1.25 + 2.8 * v, 5.0 * u),
                3 => Vector3::new(-3.0 + 6.0 * u, -1.25, 5.0 * v),
                _ => Vector3::new(-3.0 + 6.0 * u, 1.55, 5.0 * v),
            }
        })
        .collect()
}

#[test]
fn icp_converges_from_ten_degrees_and_thirty_centimetres() {
    let mut rng = ChaCha8Rng::seed_from_u64(8);
    let dst = room_cloud(&mut rng, 4000);
    let truth = Rigid {
        rotation: Rotation3::from_axis_angle(&Vector3::y_axis(), 10f64.to_radians()),
        translation: Vector3::new(0.2, 0.05, -0.2),
    };
    // Source: a different sampling of the same room, seen from the perturbed pose.
    let inv = truth.to_isometry().inverse();
    let src: Vec<_> = room_cloud(&mut rng, 4000)
        .iter()
        .map(|p| inv.transform_vector(p) + inv.translation.vector)
        .collect();
    let r = icp_clouds(&src, &dst, Rigid::identity(), &IcpParams::default());
    assert!(r.valid && r.converged, "{r:?}");
    let (rot, trans) = errors(&r.transform, &truth);
    assert!(
        rot < 0.5 && trans < 0.03,
        "rotation {rot} deg, translation {trans} m"
    );

    // Matched pairs with 20% gross outliers: trimming removes them.
    let Problem {
        src, dst, truth, ..
    } = problem(&mut rng, 300, 0.0);
    let mut dst = dst;
    for d in dst.iter_mut().take(60) {
        *d += Vector3::new(2.0, -1.0, 1.5);
    }
    let prior = Rigid {
        rotation: truth.rotation * Rotation3::from_axis_angle(&Vector3::x_axis(), 0.1),
        translation: truth.translation + Vector3::new(0.1, 0.1, -0.1),
    };
    let r = icp_matched(
        &src,
        &dst,
        prior,
        &IcpParams {
            max_correspondence_m: 1.5,
            ..Default::default()
        },
    );
    assert!(r.valid);
    let (rot, trans) = errors(&r.transform, &truth);
    assert!(
        rot < 0.3 && trans < 0.02,
        "rotation {rot} deg, translation {trans} m"
    );
    assert!(r.inliers.iter().all(|&i| i >= 60), "outliers kept");
}

/// `n` points in front of a camera `camera_from_points`, in the points' frame, and their pixels in the
/// 256x256 image with Gaussian noise of `sigma_px`.
fn pnp_scene(
    rng: &mut ChaCha8Rng,
    k: &pntr_core::Intrinsics,
    camera_from_points: &Rigid,
    n: usize,
    sigma_px: f64,
) -> (Vec<Vector3<f64>>, Vec<nalgebra::Point2<f64>>) {
    let inv = camera_from_points.to_isometry().inverse();
    let noise = Normal::new(0.0, sigma_px).unwrap();
    let (mut pts, mut px) = (Vec::new(), Vec::new());
    while pts.len() < n {
        let c = Vector3::new(
            rng.gen_range(-3.0..3.0),
            rng.gen_range(-2.0..2.0),
            rng.gen_range(1.0..8.0),
        );
        let uv = k.project(&c.into()).unwrap();
        if uv.x < 0.0 || uv.y < 0.0 || uv.x > 255.0 || uv.y > 255.0 {
            continue;
        }
        pts.push(inv.transform_vector(&c) + inv.translation.vector);
        px.push(nalgebra::Point2::new(
            uv.x + noise.sample(rng),
            uv.y + noise.sample(rng),
        ));
    }
    (pts, px)
}

#[test]
fn pnp_recovers_a_known_pose_with_outliers() {
    use nalgebra::Point2;
    use pntr_registration::pnp::{pnp_ransac, PnpParams};
    let k = pntr_core::Intrinsics::hpointloc();
    let mut rng = ChaCha8Rng::seed_from_u64(21);
    let truth = Rigid {
        rotation: Rotation3::from_euler_angles(0.05, 0.7, -0.02),
        translation: Vector3::new(0.4, -0.1, 1.5),
    };
    let (pts, mut px) = pnp_scene(&mut rng, &k, &truth, 300, 0.5);
    for p in px.iter_mut().take(90) {
        *p = Point2::new(rng.gen_range(0.0..256.0), rng.gen_range(0.0..256.0));
    }
    let r = pnp_ransac(&k, &pts, &px, &PnpParams::default());
    assert!(r.valid, "{:?}", r.reason);
    let (rot, trans) = errors(&r.camera_from_points, &truth);
    assert!(
        rot < 0.5 && trans < 0.05,
        "rotation {rot} deg, translation {trans} m"
    );
    assert!(
        r.inliers.iter().filter(|&&i| i < 90).count() < 5,
        "outliers accepted"
    );
    // Too few points, or all on one plane, are refused rather than guessed.
    assert!(!pnp_ransac(&k, &pts[..5], &px[..5], &PnpParams::default()).valid);
    let planar: Vec<_> = pts.iter().map(|p| Vector3::new(p.x, p.y, 3.0)).collect();
    assert!(!pnp_ransac(&k, &planar, &px, &PnpParams::default()).valid);
}

/// `p` with the source moved by `os` and the destination by `od`, and the transform that now holds.
fn offset(
    p: &Problem,
    os: Vector3<f64>,
    od: Vector3<f64>,
) -> (Vec<Vector3<f64>>, Vec<Vector3<f64>>, Rigid) {
    let src = p.src.iter().map(|v| v + os).collect();
    let dst = p.dst.iter().map(|v| v + od).collect();
    let truth = Rigid {
        rotation: p.truth.rotation,
        translation: p.truth.translation + od - p.truth.rotation * os,
    };
    (src, dst, truth)
}

#[test]
fn every_solver_works_far_from_the_origin() {
    // UTM-sized coordinates (the case of geographic maps): 500 pairs around (500000, 5500000, 100)
    // with 60% outliers and 1 cm noise, and offsets of 1e6 m on every axis.
    let p = TeaserParams::default();
    for (k, (os, od)) in [
        (
            Vector3::new(5e5, 5.5e6, 100.0),
            Vector3::new(5e5, 5.5e6, 100.0),
        ),
        (Vector3::new(1e6, 1e6, 1e6), Vector3::new(-1e6, 1e6, -1e6)),
    ]
    .into_iter()
    .enumerate()
    {
        let problem = generate(40 + k as u64, 500, 0.6, NOISE_SIGMA_M);
        let near = solve(&problem.src, &problem.dst, &p);
        let (src, dst, truth) = offset(&problem, os, od);
        let r = solve(&src, &dst, &p);
        assert!(r.valid, "{:?}", r.reason);
        let true_inliers = problem.is_inlier.iter().filter(|&&b| b).count();
        assert!(
            r.clique_size as f64 >= 0.9 * true_inliers as f64
                && r.clique_size >= near.clique_size - 5,
            "clique {} of {true_inliers} true inliers (near the origin {})",
            r.clique_size,
            near.clique_size
        );
        // Far from the origin the translation vector mostly says where the origin went; what the
        // user relies on is where the points go.
        let at_points = |t: &Rigid| t.apply(&(os + Vector3::new(0.0, 0.0, 4.0)));
        let (rot, _) = errors(&r.transform, &truth);
        let trans = (at_points(&r.transform) - at_points(&truth)).norm();
        assert!(
            rot < 1.0 && trans < 3.0 * NOISE_SIGMA_M,
            "{rot} deg, {trans} m at the points"
        );

        // ICP on the inliers from a prior 0.1 rad and 10 cm off.
        let inl: Vec<usize> = (0..500).filter(|&i| problem.is_inlier[i]).collect();
        let (s, d): (Vec<_>, Vec<_>) = inl.iter().map(|&i| (src[i], dst[i])).unzip();
        // The prior is turned 0.1 rad about the points (not about the far origin) and moved 17 cm.
        let c = s.iter().sum::<Vector3<f64>>() / s.len() as f64;
        let turn = Rotation3::from_axis_angle(&Vector3::x_axis(), 0.1);
        let prior = Rigid {
            rotation: truth.rotation * turn,
            translation: truth.rotation * (c - turn * c)
                + truth.translation
                + Vector3::new(0.1, -0.1, 0.1),
        };
        let r = icp_matched(
            &s,
            &d,
            prior,
            &IcpParams {
                max_correspondence_m: 1.5,
                ..Default::default()
            },
        );
        assert!(r.valid);
        let (rot, _) = errors(&r.transform, &truth);
        let trans = (at_points(&r.transform) - at_points(&truth)).norm();
        assert!(rot < 0.3 && trans < 0.02, "ICP: {rot} deg, {trans} m");
    }

    // PnP with map points 1e6 m from the origin.
    use pntr_registration::pnp::{pnp_ransac, PnpParams};
    let k = pntr_core::Intrinsics::hpointloc();
    let mut rng = ChaCha8Rng::seed_from_u64(77);
    let truth = Rigid {
        rotation: Rotation3::from_euler_angles(0.05, 0.7, -0.02),
        translation: Vector3::new(4e5, -1e6, 2.5e6),
    };
    let (pts, px) = pnp_scene(&mut rng, &k, &truth, 200, 0.0);
    let r = pnp_ransac(&k, &pts, &px, &PnpParams::default());
    assert!(r.valid, "{:?}", r.reason);
    let (rot, _) = errors(&r.camera_from_points, &truth);
    // The camera's position in the map (what a robot uses), not the translation vector.
    let centre = |t: &Rigid| t.to_isometry().inverse().translation.vector;
    let trans = (centre(&r.camera_from_points) - centre(&truth)).norm();
    assert!(rot < 0.5 && trans < 0.05, "PnP: {rot} deg, {trans} m");
}

/// A robot's frame against a clean map view: query points at 0.5-6 m with depth noise `k z^2`
/// along each point's viewing ray, `outliers` of them replaced by random points.
fn noisy_depth_problem(seed: u64, n: usize, outliers: f64, k: f64) -> (Problem, Vec<f64>) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let truth = Rigid {
        rotation: Rotation3::from_euler_angles(0.1, -0.4, 0.2),
        translation: Vector3::new(0.5, -0.2, 0.8),
    };
    let (mut src, mut dst, mut is_inlier, mut z) = (vec![], vec![], vec![], vec![]);
    let unit = Normal::new(0.0, 1.0).unwrap();
    for _ in 0..n {
        let range = rng.gen_range(0.5..6.0);
        let ray = Vector3::new(rng.gen_range(-1.0..1.0), rng.gen_range(-1.0..1.0), 1.0);
        let clean = ray * range;
        let inlier = rng.gen::<f64>() >= outliers;
        let d = if inlier {
            truth.apply(&clean)
        } else {
            Vector3::new(
                rng.gen_range(-4.0..4.0),
                rng.gen_range(-4.0..4.0),
                rng.gen_range(0.0..8.0),
            )
        };
        // Depth noise moves the query point along its ray by k z^2.
        let noisy = ray * (range + k * range * range * unit.sample(&mut rng));
        src.push(noisy);
        dst.push(d);
        is_inlier.push(inlier);
        z.push(range);
    }
    (
        Problem {
            src,
            dst,
            truth,
            is_inlier,
        },
        z,
    )
}

#[test]
fn bounds_equal_to_the_noise_bound_are_exactly_the_plain_solver() {
    let p = TeaserParams::default();
    for seed in 0..3 {
        let Problem { src, dst, .. } = generate(seed, 300, 0.7, NOISE_SIGMA_M);
        let bounds = vec![p.noise_bound; src.len()];
        let plain = solve(&src, &dst, &p);
        let bounded = solve_with_bounds(&src, &dst, Some(&bounds), &p);
        assert_eq!(plain, bounded, "seed {seed}");
    }
}

#[test]
fn equal_bounds_other_than_the_noise_bound_act_as_that_noise_bound() {
    // Bounds of 8 cm for every pair go through the per-pair graph, scaled rotation measurements
    // and per-value vote; they must find what the plain solver finds with an 8 cm noise bound.
    let p = TeaserParams::default();
    let wide = TeaserParams {
        noise_bound: 0.08,
        ..p.clone()
    };
    for seed in 0..3 {
        let Problem { src, dst, .. } = generate(20 + seed, 300, 0.7, 0.02);
        let bounded = solve_with_bounds(&src, &dst, Some(&vec![0.08; src.len()]), &p);
        let plain = solve(&src, &dst, &wide);
        assert!(bounded.valid && plain.valid, "seed {seed}");
        assert_eq!(bounded.clique_size, plain.clique_size, "seed {seed}");
        assert_eq!(bounded.inliers, plain.inliers, "seed {seed}");
        let (rot, trans) = errors(&bounded.transform, &plain.transform);
        assert!(
            rot < 1e-6 && trans < 1e-9,
            "seed {seed}: {rot} deg, {trans} m apart"
        );
    }
}

#[test]
fn bounds_that_grow_with_range_keep_a_noisy_sensor_s_far_inliers() {
    // sigma = 0.003 z^2: 7.5 cm at 5 m. The fixed 5 cm bound drops most far points; bounds of
    // 5 cm and three sigmas in quadrature keep them and give a pose at least as accurate.
    let p = TeaserParams::default();
    let k = 0.003;
    let (mut fixed_found, mut bounded_found) = (0usize, 0usize);
    for seed in 0..6 {
        let (prob, z) = noisy_depth_problem(40 + seed, 300, 0.6, k);
        let bounds: Vec<f64> = z
            .iter()
            .map(|z| (p.noise_bound.powi(2) + (3.0 * k * z * z).powi(2)).sqrt())
            .collect();
        let fixed = solve(&prob.src, &prob.dst, &p);
        let bounded = solve_with_bounds(&prob.src, &prob.dst, Some(&bounds), &p);
        assert!(bounded.valid, "seed {seed}: {:?}", bounded.reason);
        let true_found = |r: &pntr_registration::TeaserResult| {
            r.inliers.iter().filter(|&&i| prob.is_inlier[i]).count()
        };
        let false_found = bounded.inliers.len() - true_found(&bounded);
        let true_inliers = prob.is_inlier.iter().filter(|&&b| b).count();
        assert!(
            true_found(&bounded) as f64 >= 0.85 * true_inliers as f64,
            "seed {seed}: {} of {true_inliers} inliers kept",
            true_found(&bounded)
        );
        assert!(
            false_found <= 5,
            "seed {seed}: {false_found} outliers taken"
        );
        let (rot, trans) = errors(&bounded.transform, &prob.truth);
        assert!(
            rot < 1.0 && trans < 0.05,
            "seed {seed}: {rot} deg, {trans} m"
        );
        if fixed.valid {
            let (frot, _) = errors(&fixed.transform, &prob.truth);
            assert!(rot <= frot + 0.25, "seed {seed}: {rot} deg against {frot}");
        }
        fixed_found += if fixed.valid { true_found(&fixed) } else { 0 };
        bounded_found += true_found(&bounded);
    }
    assert!(
        bounded_found as f64 >= 1.3 * fixed_found as f64,
        "inliers kept: {bounded_found} with bounds, {fixed_found} fixed"
    );
}

#[test]
fn bounds_of_another_length_or_not_positive_are_refused() {
    let p = TeaserParams::default();
    let Problem { src, dst, .. } = generate(7, 50, 0.0, NOISE_SIGMA_M);
    let short = vec![0.05; 49];
    let r = solve_with_bounds(&src, &dst, Some(&short), &p);
    assert!(!r.valid && r.reason.unwrap().contains("49 bounds for 50"));
    let mut bad = vec![0.05; 50];
    bad[3] = -1.0;
    let r = solve_with_bounds(&src, &dst, Some(&bad), &p);
    assert!(!r.valid && r.reason.unwrap().contains("positive"));
    bad[3] = f64::NAN;
    assert!(!solve_with_bounds(&src, &dst, Some(&bad), &p).valid);
}
