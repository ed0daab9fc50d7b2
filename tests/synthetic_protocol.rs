//! The synthetic generator follows HPointLoc's protocol and conventions, checked on files it wrote.

use nalgebra::{Isometry3, Point3, Vector3};
use pntr_core::categories::category_id;
use pntr_core::{convert_axes, CameraAxes, DepthMap, Intrinsics};
use pntr_dataset::{DatasetIndex, PointReader, Role, View};
use pntr_synth::protocol::{CAMERA_HEIGHT_M, GRID_M, QUERY_CLEARANCE_M, QUERY_RADIUS_M};
use pntr_synth::{plan_scene, Scene, SynthConfig};

fn small_cfg(seed: u64) -> SynthConfig {
    SynthConfig {
        points_per_scene: 3,
        queries_per_point: 8,
        seed,
        ..SynthConfig::default()
    }
}

fn synthesize(cfg: &SynthConfig) -> (tempfile::TempDir, DatasetIndex) {
    let dir = tempfile::tempdir().unwrap();
    let planned = pntr_synth::plan_all(cfg);
    pntr_synth::synthesize(cfg, dir.path(), planned, &|| {}).unwrap();
    let index = DatasetIndex::open(dir.path()).unwrap();
    (dir, index)
}

/// Bilinear depth at sub-pixel (u, v), only where all four neighbours are valid.
fn bilinear(d: &DepthMap, u: f64, v: f64) -> Option<f64> {
    let (c0, r0) = (u.floor(), v.floor());
    if c0 < 0.0 || r0 < 0.0 {
        return None;
    }
    let (c, r) = (c0 as u32, r0 as u32);
    let (fu, fv) = (u - c0, v - r0);
    let a = d.get(c, r)? as f64;
    let b = d.get(c + 1, r)? as f64;
    let e = d.get(c, r + 1)? as f64;
    let f = d.get(c + 1, r + 1)? as f64;
    Some((a * (1.0 - fu) + b * fu) * (1.0 - fv) + (e * (1.0 - fu) + f * fu) * fv)
}

/// Back-project `src`'s depth, move it to the world with its pose, project into `dst`, and compare the
/// predicted depth with `dst`'s depth. Returns (co-visible pixels, median |disagreement| in metres).
/// `convert` = false skips the Habitat -> OpenCV axis conversion (to show the test can fail).
fn reprojection(src: &View, dst: &View, convert: bool) -> (usize, f64) {
    let k = Intrinsics::hpointloc();
    let to_cv = |p: &Isometry3<f64>| {
        if convert {
            convert_axes(p, CameraAxes::Habitat, CameraAxes::OpenCv)
        } else {
            *p
        }
    };
    let world_from_src = to_cv(&src.world_from_camera);
    let dst_from_world = to_cv(&dst.world_from_camera).inverse();
    let mut diffs = Vec::new();
    for row in (0..k.height).step_by(2) {
        for col in (0..k.width).step_by(2) {
            let Some(z) = src.depth.get(col, row) else {
                continue;
            };
            let p = k.backproject(col as f64, row as f64, z as f64);
            let q: Point3<f64> = dst_from_world * (world_from_src * p);
            let Some(uv) = k.project(&q) else { continue };
            if let Some(dz) = bilinear(&dst.depth, uv.x, uv.y) {
                diffs.push((dz - q.z).abs());
            }
        }
    }
    diffs.sort_by(f64::total_cmp);
    let median = diffs.get(diffs.len() / 2).copied().unwrap_or(f64::INFINITY);
    (diffs.len(), median)
}

#[test]
fn depth_poses_and_axes_agree_across_views() {
    let (_dir, index) = synthesize(&small_cfg(11));
    let r = index.scenes[0].points[0].open().unwrap();
    let db0 = r.view(Role::Database, 0).unwrap();
    let db1 = r.view(Role::Database, 1).unwrap();
    let (n, median) = reprojection(&db0, &db1, true);
    assert!(n > 500, "neighbouring database views share {n} pixels");
    assert!(
        median < 0.01,
        "median depth disagreement {median} m between db0 and db1"
    );
    let mut checked = 0;
    for i in 0..r.count(Role::Query) {
        let q = r.view(Role::Query, i).unwrap();
        // Every query shares view with at least one database view of its Point.
        let best = (0..6)
            .map(|j| reprojection(&r.view(Role::Database, j).unwrap(), &q, true))
            .max_by_key(|(n, _)| *n)
            .unwrap();
        assert!(
            best.0 > 500,
            "query {i} co-visible with only {} pixels",
            best.0
        );
        assert!(best.1 < 0.01, "query {i}: median disagreement {} m", best.1);
        checked += 1;
    }
    assert!(checked > 0);
    // The same check with the axis convention ignored fails: the test can tell right from wrong.
    let (n_wrong, median_wrong) = reprojection(&db0, &db1, false);
    assert!(
        n_wrong < 100 || median_wrong > 0.05,
        "ignoring the axis conversion should break reprojection ({n_wrong} px, median {median_wrong})"
    );
}

fn yaw_of(p: &Isometry3<f64>) -> f64 {
    // Habitat camera looks along -z; yaw measured about +y from world -z.
    let f = p.rotation * Vector3::new(0.0, 0.0, -1.0);
    (-f.x).atan2(-f.z)
}

#[test]
fn protocol_statistics_hold() {
    let cfg = small_cfg(5);
    let planned = plan_scene(&cfg, 0);
    let obstacles = planned.scene.obstacles();
    let (_dir, index) = synthesize(&cfg);
    let scene = &index.scenes[0];
    assert_eq!(scene.points.len(), 3);
    let mut keys = Vec::new();
    for entry in &scene.points {
        let r = entry.open().unwrap();
        assert_eq!(r.count(Role::Database), 6);
        let db = r.poses(Role::Database);
        let key = db[0].translation.vector;
        keys.push(key);
        assert!((key.y - CAMERA_HEIGHT_M).abs() < 1e-5);
        for (k, p) in db.iter().enumerate() {
            assert!(
                (p.translation.vector - key).norm() < 1e-5,
                "database views share the key position"
            );
            let up = p.rotation * Vector3::y();
            assert!(
                (up - Vector3::y()).norm() < 1e-5,
                "database views are level"
            );
            let rel = (yaw_of(p) - yaw_of(&db[0])).to_degrees().rem_euclid(360.0);
            assert!(
                (rel - 60.0 * k as f64).abs() < 1e-3,
                "view {k} at relative yaw {rel}"
            );
        }
        for (i, q) in r.poses(Role::Query).iter().enumerate() {
            let t = q.translation.vector;
            let horizontal = ((t.x - key.x).powi(2) + (t.z - key.z).powi(2)).sqrt();
            assert!(
                horizontal <= QUERY_RADIUS_M + 1e-5,
                "query {i} is {horizontal} m from its key"
            );
            assert!((t.y - CAMERA_HEIGHT_M).abs() < 1e-5);
            let tilt = (q.rotation * Vector3::y())
                .angle(&Vector3::y())
                .to_degrees();
            assert!(
                tilt <= 3.0 * cfg.tilt_sigma_deg * 1.5 + 1e-6,
                "query {i} tilted {tilt} deg"
            );
            let c = Scene::clearance(
                &obstacles,
                planned.scene.width_m,
                planned.scene.depth_m,
                t.x as f32,
                t.z as f32,
            );
            assert!(c >= QUERY_CLEARANCE_M, "query {i} only {c} m from geometry");
        }
        for role in [Role::Database, Role::Query] {
            for i in 0..r.count(role) {
                let v = r.view(role, i).unwrap();
                let valid: Vec<f32> = v.depth.data.iter().copied().filter(|&d| d > 0.0).collect();
                assert!(
                    valid.len() as f64 > 0.99 * v.depth.data.len() as f64,
                    "closed rooms: every ray hits"
                );
                let min = valid.iter().copied().fold(f32::INFINITY, f32::min);
                let max = valid.iter().copied().fold(0.0, f32::max);
                assert!(min > 0.1, "{role:?} {i}: camera {min} m from a surface");
                assert!(max < 10.0, "depth is clipped below 10 m");
            }
        }
    }
    // Key positions lie on one 2 m grid.
    for k in &keys {
        for axis in [0, 2] {
            let off = (k[axis] - keys[0][axis]) / GRID_M as f64;
            assert!((off - off.round()).abs() < 1e-4, "key {k:?} off the grid");
        }
    }
}

#[test]
fn instance_labels_carry_hpointloc_categories() {
    let (_dir, index) = synthesize(&small_cfg(7));
    let r: PointReader = index.scenes[0].points[1].open().unwrap();
    let table = r
        .instance_categories()
        .unwrap()
        .expect("synthetic files carry the category table");
    let mut seen = std::collections::HashSet::new();
    for i in 0..6 {
        let v = r.view(Role::Database, i).unwrap();
        let labels = v.semantic.expect("database views are labelled");
        for &l in &labels.data {
            assert!((l as usize) < table.len(), "label {l} has no category");
            seen.insert(table[l as usize]);
        }
    }
    for c in ["wall", "floor", "ceiling"] {
        assert!(
            seen.contains(&category_id(c).unwrap()),
            "no {c} seen around a Point"
        );
    }
}

#[test]
fn default_is_val_sized_and_generation_is_deterministic() {
    let cfg = SynthConfig::default();
    let a = plan_scene(&cfg, 0);
    assert_eq!(a.points.len(), 23);
    let queries: usize = a.points.iter().map(|p| p.queries.len()).sum();
    assert!((900..=1150).contains(&queries), "{queries} queries");
    let b = plan_scene(&cfg, 0);
    assert_eq!(a.points[5].queries, b.points[5].queries);
    let c = plan_scene(
        &SynthConfig {
            seed: 1,
            ..cfg.clone()
        },
        0,
    );
    assert_ne!(a.points[0].db[0], c.points[0].db[0]);

    let renderer = pntr_synth::Renderer::new(&a.scene);
    let k = Intrinsics::hpointloc();
    let f1 = renderer.render(&a.points[0].queries[0], &k, 9);
    let f2 = renderer.render(&a.points[0].queries[0], &k, 9);
    assert!(
        f1.rgb == f2.rgb && f1.depth == f2.depth,
        "same seed, same frame"
    );
    let brute = renderer.render_brute_force(&a.points[0].queries[0], &k, 9);
    assert!(
        f1.depth == brute.depth,
        "the hierarchy finds the same nearest surfaces"
    );
    // Labels may differ only where two coplanar faces tie exactly (back-to-back walls, corners).
    let same = f1
        .labels
        .data
        .iter()
        .zip(&brute.labels.data)
        .filter(|(a, b)| a == b)
        .count();
    assert!(
        same as f64 > 0.99 * f1.labels.data.len() as f64,
        "{same} labels agree"
    );
    // Sensor noise is there, with about the dataset's sigma (0.02 of full scale, about 5 levels).
    let f3 = renderer.render(&a.points[0].queries[0], &k, 10);
    let diffs: Vec<f64> = f1
        .rgb
        .data
        .iter()
        .zip(&f3.rgb.data)
        .map(|(&x, &y)| x as f64 - y as f64)
        .collect();
    let var = diffs.iter().map(|d| d * d).sum::<f64>() / diffs.len() as f64 / 2.0;
    assert!(
        (3.5..7.0).contains(&var.sqrt()),
        "noise sigma {}",
        var.sqrt()
    );
}

#[test]
fn realism_changes_queries_only_and_is_deterministic() {
    let clean = SynthConfig {
        points_per_scene: 2,
        queries_per_point: 3,
        ..small_cfg(21)
    };
    let robot = SynthConfig {
        realism: pntr_synth::effects::Realism::parse("robot").unwrap(),
        ..clean.clone()
    };
    let lit = SynthConfig {
        realism: pntr_synth::effects::Realism::parse("lighting").unwrap(),
        ..clean.clone()
    };
    let (_a, a) = synthesize(&clean);
    let (_b, b) = synthesize(&robot);
    let (_c, c) = synthesize(&robot);
    let (_d, d) = synthesize(&lit);
    let mean =
        |v: &View| v.rgb.data.iter().map(|&x| x as f64).sum::<f64>() / v.rgb.data.len() as f64;
    let mut brightness_changes = Vec::new();
    for p in 0..2 {
        let (ra, rb, rc, rd) = (
            a.scenes[0].points[p].open().unwrap(),
            b.scenes[0].points[p].open().unwrap(),
            c.scenes[0].points[p].open().unwrap(),
            d.scenes[0].points[p].open().unwrap(),
        );
        // The map's views are the mapping run's: clean whatever the queries' realism.
        let (da, db) = (
            ra.view(Role::Database, 0).unwrap(),
            rb.view(Role::Database, 0).unwrap(),
        );
        assert_eq!(da.rgb, db.rgb);
        assert_eq!(da.depth, db.depth);
        for q in 0..ra.count(Role::Query) {
            let (qa, qb, qc, qd) = (
                ra.view(Role::Query, q).unwrap(),
                rb.view(Role::Query, q).unwrap(),
                rc.view(Role::Query, q).unwrap(),
                rd.view(Role::Query, q).unwrap(),
            );
            assert_eq!(qa.world_from_camera, qb.world_from_camera, "same poses");
            assert_ne!(qa.rgb, qb.rgb);
            assert_eq!(
                (&qb.rgb, &qb.depth),
                (&qc.rgb, &qc.depth),
                "same seed, same frame"
            );
            // The robot's depth sensor loses pixels (dropouts, edges) the clean render has.
            let valid = |v: &View| v.depth.data.iter().filter(|&&z| z > 0.0).count();
            assert!(valid(&qb) < valid(&qa), "point {p} query {q}");
            // Lighting alone changes colour but not geometry.
            assert_eq!(qa.depth, qd.depth);
            brightness_changes.push((mean(&qd) - mean(&qa)).abs());
        }
    }
    assert!(
        brightness_changes.iter().any(|&m| m > 5.0),
        "lighting changes brightness: {brightness_changes:?}"
    );
}
