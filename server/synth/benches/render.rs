//! Rendering throughput of the synthetic generator.
//!
//! Baseline in the same run: the brute-force renderer (every box tested for every ray), so
//! BENCHMARKS.md can report the hierarchy's speed-up as a ratio rather than a machine-bound time.
//! `synth_point` renders all views of one Point (6 database + the queries) with rayon over views, the
//! unit of work `pntr synth` parallelises, and reports frames per second.

#![allow(missing_docs)] // criterion_group! generates undocumented functions

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use pntr_core::Intrinsics;
use pntr_synth::{plan_scene, Renderer, SynthConfig};
use rayon::prelude::*;

fn bench(c: &mut Criterion) {
    let cfg = SynthConfig::default();
    let planned = plan_scene(&cfg, 0);
    let renderer = Renderer::new(&planned.scene);
    let k = Intrinsics::hpointloc();
    let pose = planned.points[0].db[0];
    let mut g = c.benchmark_group("render_frame");
    g.sample_size(10);
    g.throughput(Throughput::Elements(1));
    g.bench_function("bvh", |b| b.iter(|| renderer.render(&pose, &k, 1)));
    g.bench_function("brute_force", |b| {
        b.iter(|| renderer.render_brute_force(&pose, &k, 1))
    });
    g.finish();

    let views: Vec<_> = planned.points[0]
        .db
        .iter()
        .chain(planned.points[0].queries.iter())
        .copied()
        .collect();
    let mut g = c.benchmark_group("synth_point");
    g.sample_size(10);
    g.throughput(Throughput::Elements(views.len() as u64));
    g.bench_function("parallel_views", |b| {
        b.iter(|| {
            views
                .par_iter()
                .enumerate()
                .map(|(i, p)| renderer.render(p, &k, i as u64).depth.valid_count())
                .sum::<usize>()
        })
    });
    g.bench_function("serial_views", |b| {
        b.iter(|| {
            views
                .iter()
                .enumerate()
                .map(|(i, p)| renderer.render(p, &k, i as u64).depth.valid_count())
                .sum::<usize>()
        })
    });
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
