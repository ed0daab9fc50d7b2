//! Registration time against problem size and outlier ratio, one core.
//!
//! Baseline in the same run: plain least squares (Kabsch) on the same input, the cost floor of any
//! solver that touches every correspondence once. The external comparison with Open3D's RANSAC runs
//! from `scripts/bench_registration.py` on identical inputs through `pntr register`.
#![allow(missing_docs)] // criterion_group! generates undocumented functions

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion};
use pntr_registration::problems::generate;
use pntr_registration::teaser::{solve, TeaserParams};

fn bench(c: &mut Criterion) {
    let p = TeaserParams::default();
    let mut g = c.benchmark_group("teaser");
    g.sample_size(10);
    g.warm_up_time(std::time::Duration::from_millis(500));
    g.measurement_time(std::time::Duration::from_secs(2));
    for n in [100usize, 500, 1000, 2000] {
        for ratio in [0.0, 0.5, 0.9, 0.95] {
            let prob = generate(42, n, ratio, 0.01);
            let id = BenchmarkId::new(format!("n{n}"), format!("out{}", (ratio * 100.0) as u32));
            g.bench_with_input(id, &prob, |b, prob| {
                b.iter(|| solve(&prob.src, &prob.dst, &p))
            });
        }
    }
    g.finish();
    let mut g = c.benchmark_group("kabsch_baseline");
    g.sample_size(10);
    g.warm_up_time(std::time::Duration::from_millis(500));
    g.measurement_time(std::time::Duration::from_secs(1));
    for n in [100usize, 500, 1000, 2000] {
        let prob = generate(42, n, 0.0, 0.01);
        g.bench_with_input(BenchmarkId::from_parameter(n), &prob, |b, prob| {
            b.iter(|| pntr_registration::kabsch(&prob.src, &prob.dst))
        });
    }
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
