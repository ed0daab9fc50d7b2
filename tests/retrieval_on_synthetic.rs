//! VLAD retrieval over XFeat descriptors on a synthetic scene: finds the right Point, the faiss index
//! agrees with brute force, and a saved codebook reloads bit for bit.

use std::path::PathBuf;

use pntr_core::Intrinsics;
use pntr_features::config::FeatureConfig;
use pntr_retrieval::index::{brute_force, GlobalIndex, IndexKind};
use pntr_retrieval::vlad::Codebook;
use pntr_synth::{plan_scene, Renderer, SynthConfig};

struct Data {
    db_orb: Vec<Vec<[u8; 32]>>,
    q_orb: Vec<Vec<[u8; 32]>>,
    db_desc: Vec<Vec<f32>>,
    db_point: Vec<usize>,
    q_desc: Vec<Vec<f32>>,
    q_point: Vec<usize>,
}

fn data() -> Data {
    let cfg = SynthConfig {
        points_per_scene: 6,
        queries_per_point: 6,
        seed: 21,
        ..Default::default()
    };
    let planned = plan_scene(&cfg, 0);
    let renderer = Renderer::new(&planned.scene);
    let k = Intrinsics::hpointloc();
    let models = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../models");
    let stage = FeatureConfig {
        models_dir: models,
        top_k: 512,
        ..Default::default()
    }
    .build()
    .unwrap();
    let orb = pntr_features::orb::Orb::default();
    use pntr_features::Extractor;
    let mut d = Data {
        db_orb: vec![],
        q_orb: vec![],
        db_desc: vec![],
        db_point: vec![],
        q_desc: vec![],
        q_point: vec![],
    };
    for (pi, p) in planned.points.iter().enumerate() {
        for (vi, pose) in p.db.iter().enumerate() {
            let rgb = renderer.render(pose, &k, vi as u64).rgb;
            d.db_orb.push(orb.extract(&rgb).unwrap().binary);
            let f = stage.extractor.extract(&rgb).unwrap();
            d.db_desc.push(f.descriptors);
            d.db_point.push(pi);
        }
        for (qi, pose) in p.queries.iter().enumerate() {
            let rgb = renderer.render(pose, &k, 100 + qi as u64).rgb;
            d.q_orb.push(orb.extract(&rgb).unwrap().binary);
            let f = stage.extractor.extract(&rgb).unwrap();
            d.q_desc.push(f.descriptors);
            d.q_point.push(pi);
        }
    }
    d
}

/// Recall@1 and @5 (right Point among the top hits) with the given codebook.
fn recall(d: &Data, book: &Codebook) -> (f64, f64, GlobalIndex, Vec<f32>, Vec<Vec<f32>>) {
    let db: Vec<f32> = d
        .db_desc
        .iter()
        .flat_map(|x| book.vlad(x).unwrap())
        .collect();
    let mut index = GlobalIndex::build(&db, book.vlad_dim(), IndexKind::Flat).unwrap();
    let queries: Vec<Vec<f32>> = d.q_desc.iter().map(|x| book.vlad(x).unwrap()).collect();
    let (mut r1, mut r5) = (0, 0);
    for (q, &pt) in queries.iter().zip(&d.q_point) {
        let hits = index.search(q, 5).unwrap();
        r1 += (d.db_point[hits[0].id] == pt) as usize;
        r5 += hits.iter().any(|h| d.db_point[h.id] == pt) as usize;
    }
    let n = queries.len() as f64;
    (r1 as f64 / n, r5 as f64 / n, index, db, queries)
}

#[test]
fn bow_baseline_finds_the_right_point_and_a_flat_vocabulary_does_not() {
    use pntr_retrieval::bow::{BowParams, InvertedFile, Vocabulary};
    let d = data();
    let recall = |voc: &Vocabulary| {
        let vecs: Vec<_> = d.db_orb.iter().map(|x| voc.bow(x)).collect();
        let inv = InvertedFile::build(voc.words(), &vecs).unwrap();
        let hits = d
            .q_orb
            .iter()
            .zip(&d.q_point)
            .filter(|(q, &pt)| d.db_point[inv.search(&voc.bow(q), 1)[0].id] == pt)
            .count();
        hits as f64 / d.q_orb.len() as f64
    };
    let voc = Vocabulary::train(&d.db_orb, BowParams::default()).unwrap();
    let r1 = recall(&voc);
    eprintln!("BoW ({} words) recall@1 {r1:.3}", voc.words());
    // Weak on a 36-image map (a 1000-word vocabulary learned on 37k descriptors): about 2x chance.
    assert!(r1 >= 0.3, "recall@1 {r1} (chance 1/6)");
    // Two words only: every image looks alike.
    let tiny = Vocabulary::train(
        &d.db_orb,
        BowParams {
            branching: 2,
            depth: 1,
            ..BowParams::default()
        },
    )
    .unwrap();
    let t1 = recall(&tiny);
    assert!(
        t1 < r1,
        "a 2-word vocabulary should do worse ({t1} vs {r1})"
    );
}

#[test]
fn vlad_finds_the_right_point_and_faiss_agrees_with_brute_force() {
    let d = data();
    let all: Vec<f32> = d.db_desc.iter().flatten().copied().collect();
    let book = Codebook::train(&all, 64, 32, 7).unwrap();
    let (r1, r5, mut index, db, queries) = recall(&d, &book);
    eprintln!(
        "VLAD(32 x XFeat-64) on {} queries, 6 Points: recall@1 {r1:.3}, recall@5 {r5:.3}",
        queries.len()
    );
    // Chance is 1/6 for recall@1.
    assert!(r1 >= 0.6, "recall@1 {r1}");
    assert!(r5 >= r1);
    // A broken codebook (all codewords equal) gives descriptors that cannot tell Points apart.
    let broken = Codebook {
        centroids: vec![0.0; 32 * 64],
        ..book.clone()
    };
    let (b1, _, _, _, _) = recall(&d, &broken);
    eprintln!("broken codebook: recall@1 {b1:.3}");
    assert!(
        b1 < r1,
        "a degenerate codebook should do worse ({b1} vs {r1})"
    );

    for q in &queries {
        let got = index.search(q, 5).unwrap();
        let want = brute_force(&db, book.vlad_dim(), q, 5);
        assert_eq!(
            got.iter().map(|h| h.id).collect::<Vec<_>>(),
            want.iter().map(|h| h.id).collect::<Vec<_>>()
        );
        for (g, w) in got.iter().zip(&want) {
            assert!((g.score - w.score).abs() < 1e-4);
        }
    }
    // Among a subset (a prior's region): exactly the brute-force ranking of that subset, for the
    // flat index; an approximate index still returns every allowed image, and nothing else.
    let n_db = db.len() / book.vlad_dim();
    let among: Vec<usize> = (0..n_db).filter(|i| i % 3 != 1).collect();
    let mut ivf = GlobalIndex::build(
        &db,
        book.vlad_dim(),
        IndexKind::Ivf {
            nlist: 4,
            nprobe: 1,
        },
    )
    .unwrap();
    for q in &queries {
        let got = index.search_among(q, 5, &among).unwrap();
        let sub: Vec<f32> = among
            .iter()
            .flat_map(|&i| db[i * book.vlad_dim()..(i + 1) * book.vlad_dim()].to_vec())
            .collect();
        let want: Vec<usize> = brute_force(&sub, book.vlad_dim(), q, 5)
            .iter()
            .map(|h| among[h.id])
            .collect();
        assert_eq!(got.iter().map(|h| h.id).collect::<Vec<_>>(), want);
        let mut all_allowed: Vec<usize> = ivf
            .search_among(q, among.len(), &among)
            .unwrap()
            .iter()
            .map(|h| h.id)
            .collect();
        all_allowed.sort();
        assert_eq!(
            all_allowed, among,
            "an approximate index returns every allowed id"
        );
        assert!(index.search_among(q, 5, &[]).unwrap().is_empty());
        assert!(index.search_among(q, 5, &[n_db + 7]).unwrap().is_empty());
    }
    // An index built on the first images and extended with the rest (a map extended with a new
    // session) answers as the index of all of them: ids continue, scores are the same.
    let half = n_db / 2 * book.vlad_dim();
    let mut grown = GlobalIndex::build(&db[..half], book.vlad_dim(), IndexKind::Flat).unwrap();
    grown.add(&db[half..]).unwrap();
    assert_eq!(grown.len(), n_db);
    assert!(
        grown.add(&db[..book.vlad_dim() - 1]).is_err(),
        "a short vector"
    );
    for q in &queries {
        let got = grown.search(q, 5).unwrap();
        let want = index.search(q, 5).unwrap();
        assert_eq!(
            got.iter().map(|h| h.id).collect::<Vec<_>>(),
            want.iter().map(|h| h.id).collect::<Vec<_>>()
        );
    }
    let mut hnsw = GlobalIndex::build(&db, book.vlad_dim(), IndexKind::Hnsw { m: 16 }).unwrap();
    let agree = queries
        .iter()
        .filter(|q| hnsw.search(q, 1).unwrap()[0].id == index.search(q, 1).unwrap()[0].id)
        .count();
    assert!(
        agree as f64 >= 0.95 * queries.len() as f64,
        "hnsw top-1 agrees on {agree}"
    );
    // Among a subset, HNSW and a flat index read back from its bytes (what a served map holds)
    // rank exactly as brute force over the subset, with its scores; a repeated id counts once.
    let mut reread =
        GlobalIndex::from_bytes(&index.to_bytes().unwrap(), book.vlad_dim(), n_db).unwrap();
    let twice: Vec<usize> = among.iter().chain(&among).copied().collect();
    for q in &queries {
        let sub: Vec<f32> = among
            .iter()
            .flat_map(|&i| db[i * book.vlad_dim()..(i + 1) * book.vlad_dim()].to_vec())
            .collect();
        let want = brute_force(&sub, book.vlad_dim(), q, 5);
        for (name, got) in [
            ("hnsw", hnsw.search_among(q, 5, &among).unwrap()),
            ("re-read flat", reread.search_among(q, 5, &twice).unwrap()),
        ] {
            assert_eq!(
                got.iter().map(|h| h.id).collect::<Vec<_>>(),
                want.iter().map(|h| among[h.id]).collect::<Vec<_>>(),
                "{name}"
            );
            for (g, w) in got.iter().zip(&want) {
                assert!((g.score - w.score).abs() < 1e-4, "{name}: {g:?} {w:?}");
            }
        }
    }

    // Save, load: identical descriptors. A flipped byte is caught by the checksum.
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("codebook.bin");
    book.save(&path).unwrap();
    let back = Codebook::load(&path).unwrap();
    assert_eq!(back, book);
    assert_eq!(
        back.vlad(&d.q_desc[0]).unwrap(),
        book.vlad(&d.q_desc[0]).unwrap()
    );
    let mut bytes = std::fs::read(&path).unwrap();
    bytes[100] ^= 0x40;
    std::fs::write(&path, &bytes).unwrap();
    let e = Codebook::load(&path).unwrap_err().to_string();
    assert!(e.contains("checksum") && e.contains("codebook.bin"), "{e}");
    std::fs::write(&path, b"short").unwrap();
    assert!(Codebook::load(&path)
        .unwrap_err()
        .to_string()
        .contains("not a pntr VLAD codebook"));
    assert!(
        Codebook::train(&all[..64 * 10], 64, 32, 1).is_err(),
        "too few descriptors for 32 codewords"
    );
}

/// `n` unit vectors of `dim` dimensions near a 16-dimensional subspace (like descriptors of one
/// kind of scene), from a seeded generator.
fn low_rank_vectors(n: usize, dim: usize, seed: u64) -> Vec<f32> {
    let mut state = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
    let mut next = move || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        (state >> 40) as f32 / (1u64 << 24) as f32 - 0.5
    };
    let basis: Vec<f32> = (0..16 * dim).map(|_| next()).collect();
    let mut out = Vec::with_capacity(n * dim);
    for _ in 0..n {
        let w: Vec<f32> = (0..16).map(|_| next()).collect();
        let v: Vec<f32> = (0..dim)
            .map(|j| (0..16).map(|k| w[k] * basis[k * dim + j]).sum::<f32>() + 0.05 * next())
            .collect();
        let norm = v.iter().map(|x| x * x).sum::<f32>().sqrt();
        out.extend(v.iter().map(|x| x / norm));
    }
    out
}

#[test]
fn the_auto_index_switches_to_pca_whitening_on_large_maps_and_the_map_records_it() {
    use pntr_retrieval::global::{Describer, Descriptor, Retriever};
    use pntr_retrieval::index::{AUTO_PCA_DIM, AUTO_PCA_FROM};
    let dim = 520;
    assert_eq!(IndexKind::parse("auto").unwrap(), IndexKind::Auto);
    assert_eq!(
        IndexKind::Auto.resolve(AUTO_PCA_FROM - 1, 4096),
        IndexKind::Flat
    );
    assert_eq!(
        IndexKind::Auto.resolve(AUTO_PCA_FROM, 4096),
        IndexKind::PcaWhiten { dim: AUTO_PCA_DIM }
    );
    // Descriptors no longer than the reduced ones stay exact, whatever the map's size.
    assert_eq!(IndexKind::Auto.resolve(100_000, 256), IndexKind::Flat);
    assert_eq!(IndexKind::Flat.resolve(100_000, 4096), IndexKind::Flat);

    let db = low_rank_vectors(AUTO_PCA_FROM, dim, 3);
    let book = Codebook::train(&low_rank_vectors(64, 64, 5), 64, 4, 1).unwrap();
    let descriptors: Vec<Descriptor> = db
        .chunks_exact(dim)
        .map(|v| Descriptor::Dense(v.to_vec()))
        .collect();
    let r = Retriever::build(Describer::Vlad(book), descriptors, IndexKind::Auto).unwrap();
    assert_eq!(
        r.index_kind(),
        Some(IndexKind::PcaWhiten { dim: AUTO_PCA_DIM })
    );
    let back = Retriever::from_bytes(&r.to_bytes().unwrap(), |_| unreachable!("no onnx")).unwrap();
    assert_eq!(back.index_kind(), r.index_kind());
    // The whitened index still finds a database vector from a slightly disturbed copy.
    let noise = low_rank_vectors(20, dim, 11);
    let mut found = 0;
    for (i, id) in (0..AUTO_PCA_FROM)
        .step_by(AUTO_PCA_FROM / 20)
        .take(20)
        .enumerate()
    {
        let q: Vec<f32> = db[id * dim..(id + 1) * dim]
            .iter()
            .zip(&noise[i * dim..(i + 1) * dim])
            .map(|(a, b)| a + 0.1 * b)
            .collect();
        let hits = back.search(&Descriptor::Dense(q), 5).unwrap();
        found += hits.iter().any(|h| h.id == id) as usize;
    }
    assert!(
        found >= 19,
        "{found} of 20 disturbed copies found in the top 5"
    );
}
