//! The local half of PNTR on the demo scene, with the retrieval step replaced by an oracle.
//!
//! Retrieval (issue 5) is not built yet. To show what the stages that exist deliver, each query is
//! paired with the database view of its own Point that looks most nearly the same way according to the
//! ground truth (the oracle), then: XFeat + LighterGlue, back-projection with both depth maps (pairs
//! without valid depth on either side are dropped together, so they stay aligned), TEASER, and
//! `world_from_query = world_from_db * db_from_query`. Errors are honest: geodesic rotation angle, and
//! every query that fails still counts in the denominator. The table is labelled "oracle retrieval"
//! so it is not mistaken for the full pipeline's recall.

use std::collections::HashMap;
use std::path::Path;
use std::time::Instant;

use anyhow::{Context, Result};
use nalgebra::{Isometry3, Vector3};
use pntr_core::{convert_axes, CameraAxes, DepthMap, Intrinsics};
use pntr_dataset::{Role, SceneEntry, View};
use pntr_features::config::FeatureConfig;
use pntr_features::runtime::RuntimeOptions;
use pntr_features::Features;
use pntr_registration::teaser::{solve, TeaserParams};
use pntr_registration::Rigid;

/// Thresholds of the HPointLoc protocol: (metres, degrees).
const THRESHOLDS: [(f64, f64); 4] = [(5.0, 20.0), (1.0, 10.0), (0.5, 5.0), (0.25, 2.0)];

fn forward(p: &Isometry3<f64>) -> Vector3<f64> {
    p.rotation * Vector3::new(0.0, 0.0, -1.0)
}

/// 3D point (OpenCV camera frame) of keypoint `k`, where its pixel has a valid depth.
fn point_at(k: &Intrinsics, depth: &DepthMap, kp: [f32; 2]) -> Option<Vector3<f64>> {
    let (c, r) = (kp[0].round(), kp[1].round());
    if c < 0.0 || r < 0.0 {
        return None;
    }
    let z = depth.get(c as u32, r as u32)?;
    Some(k.backproject(kp[0] as f64, kp[1] as f64, z as f64).coords)
}

/// Run the oracle-retrieval localisation over `max_queries` queries of `scene`, evenly spaced, and print
/// the recall table and mean stage timings.
pub fn run(scene: &SceneEntry, models: &Path, max_queries: usize) -> Result<()> {
    let cfg = FeatureConfig {
        models_dir: models.to_path_buf(),
        top_k: 512,
        runtime: RuntimeOptions {
            threads: 2,
            ..RuntimeOptions::default()
        },
        ..FeatureConfig::default()
    };
    let stage = cfg
        .build()
        .with_context(|| format!("loading the feature models from {}", models.display()))?;
    let k = Intrinsics::hpointloc();
    let params = TeaserParams::default();
    // Every (Point, query) of the scene, then an even subsample.
    let mut all = Vec::new();
    for (pi, p) in scene.points.iter().enumerate() {
        let r = p.open()?;
        for q in 0..r.count(Role::Query) {
            all.push((pi, q));
        }
    }
    let step = (all.len() as f64 / max_queries.max(1) as f64).max(1.0);
    let picked: Vec<(usize, usize)> = (0..all.len().min(max_queries))
        .map(|i| all[(i as f64 * step) as usize])
        .collect();
    let mut db_cache: HashMap<(usize, usize), (View, Features)> = HashMap::new();
    let (mut t_ext, mut t_match, mut t_reg) = (0.0, 0.0, 0.0);
    let mut errors: Vec<Option<(f64, f64)>> = Vec::new();
    let mut inliers_sum = 0usize;
    for &(pi, qi) in &picked {
        let reader = scene.points[pi].open()?;
        let q = reader.view(Role::Query, qi)?;
        let fq_dir = forward(&q.world_from_camera);
        let (bj, _) = reader
            .poses(Role::Database)
            .iter()
            .enumerate()
            .map(|(j, p)| (j, forward(p).dot(&fq_dir)))
            .max_by(|a, b| a.1.total_cmp(&b.1))
            .context("a Point without database views")?;
        // Database features are computed once per view, as a map would store them.
        let (db, fdb) = match db_cache.entry((pi, bj)) {
            std::collections::hash_map::Entry::Occupied(e) => e.into_mut(),
            std::collections::hash_map::Entry::Vacant(e) => {
                let v = reader.view(Role::Database, bj)?;
                let f = stage.extractor.extract(&v.rgb)?;
                e.insert((v, f))
            }
        };
        let (db, fdb) = (&*db, &*fdb);
        let t0 = Instant::now();
        let fq = stage.extractor.extract(&q.rgb)?;
        let t1 = Instant::now();
        let m = stage.matcher.match_features(&fq, fdb)?;
        let t2 = Instant::now();
        let (mut src, mut dst) = (Vec::new(), Vec::new());
        for &(a, b) in &m.pairs {
            if let (Some(s), Some(d)) = (
                point_at(&k, &q.depth, fq.keypoints[a as usize]),
                point_at(&k, &db.depth, fdb.keypoints[b as usize]),
            ) {
                src.push(s);
                dst.push(d);
            }
        }
        let res = solve(&src, &dst, &params);
        let t3 = Instant::now();
        t_ext += (t1 - t0).as_secs_f64();
        t_match += (t2 - t1).as_secs_f64();
        t_reg += (t3 - t2).as_secs_f64();
        if !res.valid {
            errors.push(None);
            continue;
        }
        inliers_sum += res.inliers.len();
        let db_from_query = Rigid::to_isometry(&res.transform);
        let world_from_db = convert_axes(
            &db.world_from_camera,
            CameraAxes::Habitat,
            CameraAxes::OpenCv,
        );
        let est = convert_axes(
            &(world_from_db * db_from_query),
            CameraAxes::OpenCv,
            CameraAxes::Habitat,
        );
        let gt = q.world_from_camera;
        let dt = (est.translation.vector - gt.translation.vector).norm();
        let dr = est.rotation.angle_to(&gt.rotation).to_degrees();
        errors.push(Some((dt, dr)));
    }
    let n = errors.len() as f64;
    let localized = errors.iter().filter(|e| e.is_some()).count();
    println!();
    println!(
        "Oracle-retrieval localisation (the database view is picked from the ground truth; retrieval is not built yet):"
    );
    println!(
        "{} of {} queries (evenly spaced), xfeat + lighterglue (top 512) + teaser; {} localized, mean {:.0} inliers",
        errors.len(),
        all.len(),
        localized,
        inliers_sum as f64 / localized.max(1) as f64
    );
    let header: Vec<String> = THRESHOLDS
        .iter()
        .map(|(m, d)| format!("({m}m,{d}deg)"))
        .collect();
    let header_t: Vec<String> = THRESHOLDS.iter().map(|(m, _)| format!("({m}m)")).collect();
    println!("{:>14} {:>14}", header.join(" "), header_t.join(" "));
    let both: Vec<String> = THRESHOLDS
        .iter()
        .map(|&(m, d)| {
            let c = errors
                .iter()
                .flatten()
                .filter(|(dt, dr)| *dt <= m && *dr <= d)
                .count();
            format!(
                "{:>width$.3}",
                c as f64 / n,
                width = format!("({m}m,{d}deg)").len()
            )
        })
        .collect();
    let trans: Vec<String> = THRESHOLDS
        .iter()
        .map(|&(m, _)| {
            let c = errors.iter().flatten().filter(|(dt, _)| *dt <= m).count();
            format!(
                "{:>width$.3}",
                c as f64 / n,
                width = format!("({m}m)").len()
            )
        })
        .collect();
    println!("{} {}", both.join(" "), trans.join(" "));
    println!(
        "mean per query: extraction {:.1} ms, matching {:.1} ms, registration {:.2} ms",
        1e3 * t_ext / n,
        1e3 * t_match / n,
        1e3 * t_reg / n
    );
    Ok(())
}
