//! Mutual nearest-neighbour matching of float descriptors, one core: the final matcher's size
//! (1024 x 1024 keypoints), a 256x256 frame's (512: the shortlist's last vote, the turned views)
//! and the shortlist vote's (128 and 256 of the strongest).
//!
//! Baseline in the same run: the similarity matrix product alone (the same sgemm into the same
//! buffer), the floor of any exact MNN; the ratio of the two is the cost of finding the best row
//! and column matches.
#![allow(missing_docs)] // criterion_group! generates undocumented functions

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion};
use pntr_features::mnn::{mutual_nearest, MnnBuffers, MnnParams};
use pntr_features::Matches;

const DIM: usize = 64;

/// `n` unit descriptors from a seeded xorshift.
fn descriptors(n: usize, seed: u64) -> Vec<f32> {
    let mut x = seed.wrapping_mul(0x9e37_79b9_7f4a_7c15) | 1;
    let mut out = Vec::with_capacity(n * DIM);
    for _ in 0..n {
        let v: Vec<f32> = (0..DIM)
            .map(|_| {
                x ^= x << 13;
                x ^= x >> 7;
                x ^= x << 17;
                (x >> 40) as f32 / (1u64 << 24) as f32 - 0.5
            })
            .collect();
        let norm = v.iter().map(|a| a * a).sum::<f32>().sqrt();
        out.extend(v.iter().map(|a| a / norm));
    }
    out
}

/// Two sets of `n` descriptors; every other row of `b` is a perturbed copy of `a`'s, so about half
/// of the rows have a true match (as between two views of one room).
fn pair(n: usize) -> (Vec<f32>, Vec<f32>) {
    let a = descriptors(n, 1);
    let noise = descriptors(n, 2);
    let mut b = noise.clone();
    for j in (0..n).step_by(2) {
        let row: Vec<f32> = a[j * DIM..(j + 1) * DIM]
            .iter()
            .zip(&noise[j * DIM..(j + 1) * DIM])
            .map(|(x, y)| x + 0.25 * y)
            .collect();
        let norm = row.iter().map(|v| v * v).sum::<f32>().sqrt();
        for (d, v) in b[j * DIM..(j + 1) * DIM].iter_mut().zip(&row) {
            *d = v / norm;
        }
    }
    (a, b)
}

fn bench(c: &mut Criterion) {
    let mut g = c.benchmark_group("mnn");
    g.sample_size(20);
    g.warm_up_time(std::time::Duration::from_millis(500));
    g.measurement_time(std::time::Duration::from_secs(2));
    let params = MnnParams::default();
    for n in [128usize, 256, 512, 1024] {
        let (a, b) = pair(n);
        let mut buf = MnnBuffers::default();
        let mut out = Matches::default();
        g.bench_with_input(BenchmarkId::new("mutual_nearest", n), &n, |bench, _| {
            bench.iter(|| {
                out.pairs.clear();
                out.scores.clear();
                mutual_nearest(&a, &b, DIM, &params, &mut buf, &mut out);
                out.pairs.len()
            })
        });
        let mut sim = vec![0f32; n * n];
        g.bench_with_input(BenchmarkId::new("similarity_only", n), &n, |bench, _| {
            bench.iter(|| {
                let av = ndarray::ArrayView2::from_shape((n, DIM), &a[..]).expect("rows");
                let bv = ndarray::ArrayView2::from_shape((n, DIM), &b[..]).expect("rows");
                let mut s =
                    ndarray::ArrayViewMut2::from_shape((n, n), &mut sim[..]).expect("n x n");
                ndarray::linalg::general_mat_mul(1.0, &av, &bv.t(), 0.0, &mut s);
                sim[n + 1]
            })
        });
    }
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
