//! Where the right Point sits in the global ranking, and where the shortlist's votes put it: the
//! analysis behind `pntr-pipeline::shortlist` (BENCHMARKS.md, "A deeper shortlist").
//!
//! ```text
//! cargo run --release -p pntr-pipeline --example retrieval_depth -- MAP DATASET [QUERIES] [MODELS]
//! ```
//!
//! For QUERIES evenly spaced queries (default 300) of DATASET, against MAP: the share whose own
//! Point is among the first k of (a) the map's global index, (b) that ranking re-ordered by the
//! number of mutual matches of the 128 strongest keypoints, (c) by the shortlist's vote with 128
//! keypoints (the highest core number of the matches' consistency graph), (d) the shortlist as the
//! pipeline runs it (votes again with 256 keypoints over the first's best 20 and with 512 over the
//! second's best 10; first 5 only), and how many distinct Points its 5 images show. Environment: `DEPTH` (global
//! candidates, default 100), `INDEX` (re-index the map's own descriptors with this faiss index,
//! e.g. `flat`, `pcaw512`, `auto`), `SCENES` (only the map's first N scenes, with `INDEX`).

use std::path::PathBuf;
use std::time::Instant;

use nalgebra::Vector3;
use pntr_dataset::{DatasetIndex, Role};
use pntr_features::config::FeatureConfig;
use pntr_features::mnn::Mnn;
use pntr_features::Matcher;
use pntr_pipeline::mapfile;
use pntr_pipeline::shortlist::{Shortlist, COARSE_KEYPOINTS, FINAL_KEYPOINTS};
use pntr_retrieval::global::Descriptor;
use pntr_retrieval::index::{GlobalIndex, Hit, IndexKind};

const KS: [usize; 6] = [1, 5, 10, 20, 50, 100];

fn env(name: &str) -> Option<String> {
    std::env::var(name).ok()
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    if args.len() < 3 {
        return Err("usage: retrieval_depth MAP DATASET [QUERIES] [MODELS]".into());
    }
    let want: usize = args.get(3).map_or(Ok(300), |s| s.parse())?;
    let models = PathBuf::from(args.get(4).map_or("models", |s| s.as_str()));
    let depth: usize = env("DEPTH").map_or(Ok(100), |s| s.parse())?;
    let scenes: usize = env("SCENES").map_or(Ok(usize::MAX), |s| s.parse())?;
    let map = mapfile::load(&PathBuf::from(&args[1]), |_| {
        Err(pntr_retrieval::RetrievalError::Model(
            "maps with an onnx global model are not supported here".into(),
        ))
    })?;
    let stage = FeatureConfig {
        top_k: map.header.preset.keypoints,
        ..map.header.preset.feature_config(models)
    }
    .build()?;
    let in_scope: Vec<usize> = (0..map.images.len())
        .filter(|&i| (map.images[i].scene as usize) < scenes)
        .collect();
    // The map's own descriptors indexed again, when asked.
    let mut own_index = match env("INDEX") {
        Some(kind) => {
            let t = Instant::now();
            let (mut flat, mut dim) = (Vec::new(), 0);
            for &i in &in_scope {
                if let Descriptor::Dense(v) = map
                    .retriever
                    .describer
                    .describe_features(&map.images[i].features())?
                {
                    dim = v.len();
                    flat.extend(v);
                }
            }
            let ix = GlobalIndex::build(&flat, dim, IndexKind::parse(&kind)?)?;
            println!(
                "index {kind} over {} images built in {:.1} s",
                in_scope.len(),
                t.elapsed().as_secs_f64()
            );
            Some(ix)
        }
        None if scenes < usize::MAX => return Err("SCENES needs INDEX".into()),
        None => None,
    };
    let index = DatasetIndex::open(&PathBuf::from(&args[2]))?;
    let mut all = Vec::new();
    for s in &index.scenes {
        let Some(si) = map.header.scenes.iter().position(|n| *n == s.name) else {
            continue;
        };
        if si >= scenes {
            continue;
        }
        for p in &s.points {
            for qi in 0..p.open()?.count(Role::Query) {
                all.push((p.clone(), qi));
            }
        }
    }
    let step = (all.len() / want.max(1)).max(1);
    let picked: Vec<_> = all.into_iter().step_by(step).take(want).collect();
    let shortlist = Shortlist::new(&map.images, FINAL_KEYPOINTS);
    let mnn = Mnn::default();
    let names = ["global", "match count", "vote", "shortlist"];
    let mut at = vec![[0usize; KS.len()]; names.len()];
    let (mut search_s, mut vote_s, mut shortlist_s) = (0.0, 0.0, 0.0);
    let mut distinct = 0usize;
    for (p, qi) in &picked {
        let v = p.open()?.view(Role::Query, *qi)?;
        let fq = stage.extractor.extract(&v.rgb)?;
        let q_pts: Vec<Option<Vector3<f64>>> = fq
            .keypoints
            .iter()
            .map(|&[x, y]| {
                let z = v.depth.get(x.round() as u32, y.round() as u32)?;
                (z > 0.0).then(|| {
                    v.intrinsics
                        .backproject(x as f64, y as f64, z as f64)
                        .coords
                })
            })
            .collect();
        let desc = map.retriever.describer.describe(&v.rgb, &fq)?;
        let t = Instant::now();
        let hits: Vec<Hit> = match (&mut own_index, &desc) {
            (Some(ix), Descriptor::Dense(d)) => ix
                .search(d, depth)?
                .into_iter()
                .map(|h| Hit {
                    id: in_scope[h.id],
                    score: h.score,
                })
                .collect(),
            _ => map.retriever.search(&desc, depth)?,
        };
        search_s += t.elapsed().as_secs_f64();
        // (b) the plain count of mutual matches of the strongest keypoints.
        let strongest = |f: &pntr_features::Features| {
            let mut o: Vec<usize> = (0..f.len()).collect();
            o.sort_by(|&a, &b| f.scores[b].total_cmp(&f.scores[a]));
            o.truncate(COARSE_KEYPOINTS);
            pntr_features::Features {
                keypoints: o.iter().map(|&i| f.keypoints[i]).collect(),
                scores: o.iter().map(|&i| f.scores[i]).collect(),
                descriptors: o.iter().flat_map(|&i| f.descriptor(i).to_vec()).collect(),
                dim: f.dim,
                binary: Vec::new(),
                image_size: f.image_size,
            }
        };
        let q_strong = strongest(&fq);
        let mut counted: Vec<(usize, usize, Hit)> = Vec::with_capacity(hits.len());
        for (rank, h) in hits.iter().enumerate() {
            let db = strongest(&map.images[h.id].features());
            counted.push((mnn.match_features(&q_strong, &db)?.pairs.len(), rank, *h));
        }
        counted.sort_by(|a, b| b.0.cmp(&a.0).then(a.1.cmp(&b.1)));
        let counted: Vec<Hit> = counted.into_iter().map(|c| c.2).collect();
        // (c) one vote, (d) the shortlist as the pipeline runs it.
        let t = Instant::now();
        let voted = shortlist.ranked_by_vote(
            &map.images,
            &fq,
            &q_pts,
            &hits,
            COARSE_KEYPOINTS,
            &mnn,
            0.1,
        )?;
        vote_s += t.elapsed().as_secs_f64();
        let t = Instant::now();
        let kept = shortlist.rerank(&map.images, &fq, &q_pts, &hits, 5, &mnn, 0.1)?;
        shortlist_s += t.elapsed().as_secs_f64();
        let right = |h: &Hit| {
            let im = &map.images[h.id];
            map.header.scenes[im.scene as usize] == p.scene && im.point == p.index
        };
        let mut points: Vec<(u32, u32)> = kept
            .iter()
            .map(|h| (map.images[h.id].scene, map.images[h.id].point))
            .collect();
        points.sort_unstable();
        points.dedup();
        distinct += points.len();
        for (row, ranking) in at.iter_mut().zip([&hits, &counted, &voted, &kept]) {
            let first = ranking.iter().position(right);
            for (c, &k) in row.iter_mut().zip(&KS) {
                *c += first.is_some_and(|r| r < k) as usize;
            }
        }
    }
    let n = picked.len().max(1) as f64;
    println!(
        "{} queries, {depth} global candidates; right Point among the first k:",
        picked.len()
    );
    println!("| ranking | {} |", KS.map(|k| format!("@{k}")).join(" | "));
    for (name, row) in names.iter().zip(&at) {
        let cells: Vec<String> = row
            .iter()
            .zip(&KS)
            .map(|(&c, &k)| {
                if *name == "shortlist" && k > 5 {
                    "-".to_string()
                } else {
                    format!("{:.3}", c as f64 / n)
                }
            })
            .collect();
        println!("| {name} | {} |", cells.join(" | "));
    }
    println!(
        "distinct Points among the shortlist's 5: {:.2}",
        distinct as f64 / n
    );
    println!(
        "ms per query: global search {:.2}, one vote {:.2}, shortlist {:.2}",
        search_s * 1e3 / n,
        vote_s * 1e3 / n,
        shortlist_s * 1e3 / n
    );
    Ok(())
}
