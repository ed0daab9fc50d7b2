//! The PNTR pipeline on the demo scene with the stages that exist, and the same with an oracle.
//!
//! Map: XFeat features of every database view, a VLAD codebook (64 words) learned on them by faiss
//! k-means, their VLAD vectors in a faiss flat index. Per query: XFeat, VLAD, top-1 retrieval, LighterGlue
//! against the retrieved view, back-projection with both depth maps (pairs without valid depth on either
//! side are dropped together, so they stay aligned), TEASER, `world_from_query = world_from_db *
//! db_from_query`. The oracle row replaces retrieval by the database view of the query's own Point that
//! looks most nearly the same way according to the ground truth, which separates retrieval failures from
//! matching and registration failures. Errors are honest: geodesic rotation angle, and every query that
//! fails still counts in the denominator. Geometric re-ranking and the map file arrive with issues 5-6.

use std::path::Path;
use std::time::Instant;

use anyhow::{Context, Result};
use nalgebra::{Isometry3, Vector3};
use pntr_core::{convert_axes, CameraAxes, DepthMap, Intrinsics};
use pntr_dataset::{Role, SceneEntry, View};
use pntr_features::config::{FeatureConfig, FeatureStage};
use pntr_features::runtime::RuntimeOptions;
use pntr_features::Features;
use pntr_registration::teaser::{solve, TeaserParams};
use pntr_registration::Rigid;
use pntr_retrieval::index::{GlobalIndex, IndexKind};
use pntr_retrieval::vlad::Codebook;

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

/// What every localisation needs, and the time spent in matching and registration.
struct Localizer {
    stage: FeatureStage,
    k: Intrinsics,
    params: TeaserParams,
    t_match: f64,
    t_reg: f64,
}

/// Localise `q` (features `fq`) against database view `db` (features `fdb`): errors (metres, degrees)
/// and inlier count, or `None` when registration is not valid. `timed` adds to the stage timings.
fn localize(
    ctx: &mut Localizer,
    (q, fq): (&View, &Features),
    (db, fdb): (&View, &Features),
    timed: bool,
) -> Result<Option<(f64, f64, usize)>> {
    let (stage, k, params) = (&ctx.stage, &ctx.k, &ctx.params);
    let t1 = Instant::now();
    let m = stage.matcher.match_features(fq, fdb)?;
    let t2 = Instant::now();
    let (mut src, mut dst) = (Vec::new(), Vec::new());
    for &(a, b) in &m.pairs {
        if let (Some(s), Some(d)) = (
            point_at(k, &q.depth, fq.keypoints[a as usize]),
            point_at(k, &db.depth, fdb.keypoints[b as usize]),
        ) {
            src.push(s);
            dst.push(d);
        }
    }
    let res = solve(&src, &dst, params);
    if timed {
        ctx.t_match += (t2 - t1).as_secs_f64();
        ctx.t_reg += t2.elapsed().as_secs_f64();
    }
    if !res.valid {
        return Ok(None);
    }
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
    Ok(Some((dt, dr, res.inliers.len())))
}

fn print_table(title: &str, errors: &[Option<(f64, f64, usize)>]) {
    let n = errors.len() as f64;
    let ok: Vec<(f64, f64, usize)> = errors.iter().flatten().copied().collect();
    println!(
        "{title}: {} of {} localized, mean {:.0} inliers",
        ok.len(),
        errors.len(),
        ok.iter().map(|e| e.2 as f64).sum::<f64>() / ok.len().max(1) as f64
    );
    let header: Vec<String> = THRESHOLDS
        .iter()
        .map(|(m, d)| format!("({m}m,{d}deg)"))
        .collect();
    let header_t: Vec<String> = THRESHOLDS.iter().map(|(m, _)| format!("({m}m)")).collect();
    println!("{} {}", header.join(" "), header_t.join(" "));
    let cell = |c: usize, label: String| format!("{:>width$.3}", c as f64 / n, width = label.len());
    let both: Vec<String> = THRESHOLDS
        .iter()
        .map(|&(m, d)| {
            cell(
                ok.iter().filter(|e| e.0 <= m && e.1 <= d).count(),
                format!("({m}m,{d}deg)"),
            )
        })
        .collect();
    let trans: Vec<String> = THRESHOLDS
        .iter()
        .map(|&(m, _)| cell(ok.iter().filter(|e| e.0 <= m).count(), format!("({m}m)")))
        .collect();
    println!("{} {}", both.join(" "), trans.join(" "));
}

/// Build the demo map of `scene`, localise `max_queries` evenly spaced queries with retrieval and with
/// the oracle, and print both recall tables and the mean stage timings.
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
    let mut ctx = Localizer {
        stage,
        k: Intrinsics::hpointloc(),
        params: TeaserParams::default(),
        t_match: 0.0,
        t_reg: 0.0,
    };
    // The map: every database view with its features, a VLAD codebook and index.
    let t_map = Instant::now();
    let mut db: Vec<(usize, View, Features)> = Vec::new();
    let mut all = Vec::new();
    // Each Point file is opened (and validated) once; queries are read from these readers below.
    let readers = scene
        .points
        .iter()
        .map(|p| p.open())
        .collect::<Result<Vec<_>, _>>()?;
    for (pi, r) in readers.iter().enumerate() {
        for j in 0..r.count(Role::Database) {
            let v = r.view(Role::Database, j)?;
            let f = ctx.stage.extractor.extract(&v.rgb)?;
            db.push((pi, v, f));
        }
        for q in 0..r.count(Role::Query) {
            all.push((pi, q));
        }
    }
    let descs: Vec<f32> = db
        .iter()
        .flat_map(|(_, _, f)| f.descriptors.iter().copied())
        .collect();
    let book = Codebook::train(&descs, 64, 64, 1)?;
    let vecs: Vec<f32> = db
        .iter()
        .map(|(_, _, f)| book.vlad(&f.descriptors))
        .collect::<Result<Vec<_>, _>>()?
        .concat();
    let mut index = GlobalIndex::build(&vecs, book.vlad_dim(), IndexKind::Flat)?;
    println!(
        "map: {} database views, VLAD {} words x XFeat-64, built in {:.1} s",
        db.len(),
        book.k,
        t_map.elapsed().as_secs_f64()
    );
    let step = (all.len() as f64 / max_queries.max(1) as f64).max(1.0);
    let picked: Vec<(usize, usize)> = (0..all.len().min(max_queries))
        .map(|i| all[(i as f64 * step) as usize])
        .collect();
    let (mut t_ext, mut t_ret) = (0.0, 0.0);
    let (mut with_retrieval, mut with_oracle) = (Vec::new(), Vec::new());
    let mut right_point = 0;
    for &(pi, qi) in &picked {
        let q = readers[pi].view(Role::Query, qi)?;
        let t0 = Instant::now();
        let fq = ctx.stage.extractor.extract(&q.rgb)?;
        let t1 = Instant::now();
        let hit = index.search(&book.vlad(&fq.descriptors)?, 1)?[0].id;
        t_ext += (t1 - t0).as_secs_f64();
        t_ret += t1.elapsed().as_secs_f64();
        right_point += (db[hit].0 == pi) as usize;
        let fq_dir = forward(&q.world_from_camera);
        let oracle = (0..db.len())
            .filter(|&i| db[i].0 == pi)
            .max_by(|&a, &b| {
                forward(&db[a].1.world_from_camera)
                    .dot(&fq_dir)
                    .total_cmp(&forward(&db[b].1.world_from_camera).dot(&fq_dir))
            })
            .context("a Point without database views")?;
        let r = localize(&mut ctx, (&q, &fq), (&db[hit].1, &db[hit].2), true)?;
        with_retrieval.push(r);
        with_oracle.push(if oracle == hit {
            r
        } else {
            localize(&mut ctx, (&q, &fq), (&db[oracle].1, &db[oracle].2), false)?
        });
    }
    let n = picked.len() as f64;
    println!();
    println!(
        "{} of {} queries (evenly spaced), xfeat + lighterglue (top 512) + teaser; retrieval top-1 on the right Point: {:.3}",
        picked.len(),
        all.len(),
        right_point as f64 / n
    );
    print_table("with retrieval (VLAD top-1)", &with_retrieval);
    print_table(
        "oracle retrieval (database view picked from the ground truth)",
        &with_oracle,
    );
    println!(
        "mean per query: extraction {:.1} ms, retrieval {:.2} ms, matching {:.1} ms, registration {:.2} ms",
        1e3 * t_ext / n,
        1e3 * t_ret / n,
        1e3 * ctx.t_match / n,
        1e3 * ctx.t_reg / n
    );
    Ok(())
}
