//! Query time against map size: the cost of computing one global descriptor (independent of the map)
//! and of searching maps of 1k, 10k and 100k vectors with each index kind, measured separately.
//!
//! Vectors are random unit vectors of VLAD's size (64 words x 64-d = 4096): search cost depends on the
//! count and length of the vectors, not on what they encode. Prints a markdown table. Agreement with
//! flat is not reported for PCA-whitening (`auto` from 4096 vectors on): random vectors have no
//! dominant directions for it to keep, so its recall is measured on a real map instead
//! (`pntr-pipeline`'s `retrieval_depth` example).
//! Run: `cargo run --release -p pntr-retrieval --example retrieval_scaling [-- 1000,10000,100000]`

use std::time::Instant;

use pntr_retrieval::bow::{BowParams, Vocabulary};
use pntr_retrieval::index::{GlobalIndex, IndexKind};
use pntr_retrieval::vlad::Codebook;
use rand::{Rng, SeedableRng};

fn unit(rng: &mut rand_chacha::ChaCha8Rng, dim: usize) -> Vec<f32> {
    let mut v: Vec<f32> = (0..dim).map(|_| rng.gen_range(-1.0..1.0)).collect();
    pntr_retrieval::l2_normalise(&mut v);
    v
}

fn median_ms(mut t: Vec<f64>) -> f64 {
    t.sort_by(f64::total_cmp);
    1e3 * t[t.len() / 2]
}

fn main() {
    let sizes: Vec<usize> = std::env::args()
        .nth(1)
        .map(|s| s.split(',').map(|x| x.parse().expect("sizes")).collect())
        .unwrap_or_else(|| vec![1_000, 10_000, 100_000]);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
    // Descriptor computation: VLAD of 512 XFeat-sized descriptors, BoW of 1024 ORB descriptors.
    let local: Vec<f32> = (0..20_000).flat_map(|_| unit(&mut rng, 64)).collect();
    let book = Codebook::train(&local, 64, 64, 1).expect("codebook");
    let query_local: Vec<f32> = (0..512).flat_map(|_| unit(&mut rng, 64)).collect();
    let t: Vec<f64> = (0..200)
        .map(|_| {
            let t0 = Instant::now();
            std::hint::black_box(book.vlad(&query_local).expect("vlad"));
            t0.elapsed().as_secs_f64()
        })
        .collect();
    println!(
        "descriptor: VLAD 64 words x 64-d over 512 descriptors: {:.3} ms (median of 200)",
        median_ms(t)
    );
    let images: Vec<Vec<[u8; 32]>> = (0..50)
        .map(|_| (0..1024).map(|_| rng.gen()).collect())
        .collect();
    let voc = Vocabulary::train(&images, BowParams::default()).expect("vocabulary");
    let t: Vec<f64> = (0..200)
        .map(|_| {
            let t0 = Instant::now();
            std::hint::black_box(voc.bow(&images[0]));
            t0.elapsed().as_secs_f64()
        })
        .collect();
    println!(
        "descriptor: BoW ({} words) of 1024 ORB descriptors: {:.3} ms (median of 200)",
        voc.words(),
        median_ms(t)
    );
    println!();
    println!(
        "| vectors | index | build s | search ms (median) | index MB | top-1 agrees with flat |"
    );
    println!("|---|---|---|---|---|---|");
    let dim = 4096;
    for &n in &sizes {
        let db: Vec<f32> = (0..n).flat_map(|_| unit(&mut rng, dim)).collect();
        // Queries near database vectors, so the true top-1 is well defined.
        let queries: Vec<Vec<f32>> = (0..100)
            .map(|i| {
                let j = (i * 7919) % n;
                let noise = unit(&mut rng, dim);
                let mut q: Vec<f32> = db[j * dim..(j + 1) * dim]
                    .iter()
                    .zip(&noise)
                    .map(|(a, b)| a + 0.5 * b)
                    .collect();
                pntr_retrieval::l2_normalise(&mut q);
                q
            })
            .collect();
        let mut flat_top = Vec::new();
        let mut kinds = vec![IndexKind::Flat];
        if IndexKind::Auto.resolve(n, dim) != IndexKind::Flat {
            kinds.push(IndexKind::Auto);
        }
        if n <= 10_000 {
            kinds.push(IndexKind::Hnsw { m: 32 });
        }
        if n >= 10_000 {
            kinds.push(IndexKind::Ivf {
                nlist: (n / 100) as u32,
                nprobe: 16,
            });
        }
        for kind in kinds {
            let t0 = Instant::now();
            let mut index = GlobalIndex::build(&db, dim, kind).expect("index");
            let build = t0.elapsed().as_secs_f64();
            let mut times = Vec::new();
            let mut tops = Vec::new();
            for q in &queries {
                let t0 = Instant::now();
                let hits = index.search(q, 5).expect("search");
                times.push(t0.elapsed().as_secs_f64());
                tops.push(hits[0].id);
            }
            if kind == IndexKind::Flat {
                flat_top = tops.clone();
            }
            let resolved = kind.resolve(n, dim);
            let name = if kind == IndexKind::Auto {
                format!("auto ({})", resolved.name())
            } else {
                kind.name()
            };
            let agree = match resolved {
                IndexKind::PcaWhiten { .. } => "- (random vectors)".to_string(),
                _ => format!(
                    "{}/100",
                    tops.iter().zip(&flat_top).filter(|(a, b)| a == b).count()
                ),
            };
            let mb = index.to_bytes().map_or(f64::NAN, |b| b.len() as f64 / 1e6);
            println!(
                "| {n} | {name} | {build:.2} | {:.3} | {mb:.0} | {agree} |",
                median_ms(times)
            );
        }
    }
}
