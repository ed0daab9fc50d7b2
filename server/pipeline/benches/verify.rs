//! Verification's dense work on one core: the thumbnail of a query frame, the dense evidence of a
//! candidate pose (both directions with the matched view and one direction with five nearby
//! views), right and wrong, and the dense refinement of a pose a few degrees off.
//!
//! Frames are rendered by `pntr-synth` (the first Point of scene 0 of the default configuration).
//! Compare two commits by running this bench on each, alternately; BENCHMARKS.md gives the ratios.
#![allow(missing_docs)] // criterion_group! generates undocumented functions

use criterion::{criterion_group, criterion_main, Criterion};
use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};
use pntr_core::pose::{convert_axes, CameraAxes};
use pntr_core::Intrinsics;
use pntr_pipeline::refine::refine_dense;
use pntr_pipeline::verify::{dense_evidence, Thumb};
use pntr_synth::{plan_scene, Renderer, SynthConfig};

fn bench(c: &mut Criterion) {
    let cfg = SynthConfig::default();
    let planned = plan_scene(&cfg, 0);
    let renderer = Renderer::new(&planned.scene);
    let k = Intrinsics::hpointloc();
    let point = &planned.points[0];
    let opencv = |p: &Isometry3<f64>| convert_axes(p, CameraAxes::Habitat, CameraAxes::OpenCv);
    let query_pose = point.queries[0];
    let query = renderer.render(&query_pose, &k, 1);
    let views: Vec<(Thumb, Isometry3<f64>)> = point
        .db
        .iter()
        .enumerate()
        .map(|(i, pose)| {
            let f = renderer.render(pose, &k, 10 + i as u64);
            (Thumb::new(&f.rgb, &f.depth, &k), opencv(pose))
        })
        .collect();
    let q = Thumb::new(&query.rgb, &query.depth, &k);
    let world_from_query = opencv(&query_pose);
    // A wrong pose: the query camera 0.8 m aside and turned by 25 degrees.
    let wrong = world_from_query
        * Isometry3::from_parts(
            Translation3::new(0.8, 0.0, 0.3),
            UnitQuaternion::from_euler_angles(0.0, 25f64.to_radians(), 0.0),
        );
    let evidence_at = |world_from_query: &Isometry3<f64>| {
        let (matched, world_from_matched) = &views[0];
        let db_from_query = world_from_matched.inverse() * world_from_query;
        let nearby: Vec<(&Thumb, Isometry3<f64>)> = views[1..]
            .iter()
            .map(|(t, w)| (t, w.inverse() * world_from_query))
            .collect();
        dense_evidence(&q, matched, &db_from_query, &nearby)
    };
    let mut g = c.benchmark_group("verify");
    g.sample_size(20);
    g.bench_function("thumbnail", |b| {
        b.iter(|| Thumb::new(&query.rgb, &query.depth, &k))
    });
    g.bench_function("dense_evidence_right", |b| {
        b.iter(|| evidence_at(&world_from_query))
    });
    g.bench_function("dense_evidence_wrong", |b| b.iter(|| evidence_at(&wrong)));
    // Refinement from a pose 3 degrees off, with 40 keypoint pairs spread over the query's view.
    let (matched, world_from_matched) = &views[0];
    let truth = world_from_matched.inverse() * world_from_query;
    let off = Isometry3::from_parts(
        truth.translation,
        UnitQuaternion::from_scaled_axis(Vector3::new(0.3, 1.0, -0.2).normalize() * 0.05)
            * truth.rotation,
    );
    let (src, dst): (Vec<Vector3<f64>>, Vec<Vector3<f64>>) = (0..q.height)
        .step_by(8)
        .flat_map(|r| (0..q.width).step_by(8).map(move |c| (c, r)))
        .filter_map(|(c, r)| {
            let z = q.depth_m(c, r)?;
            let p = q.intrinsics.backproject(c as f64, r as f64, z);
            Some((p.coords, (truth * Point3::from(p.coords)).coords))
        })
        .unzip();
    g.bench_function("refine_dense", |b| {
        b.iter(|| refine_dense(&q, matched, &off, &src, &dst))
    });
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
