//! Mutation fuzzing of what crosses a trust boundary: encoded `LocalizeRequest`s (protobuf decoding,
//! then the server's validation and image/depth decoding) and map files (with section checksums
//! recomputed after mutating, so the mutations reach the record parser instead of stopping at the
//! checksum). Every input must give a value or an error, never a panic.
//!
//! CI runs a fixed-seed budget of iterations (a regression test); `PNTR_FUZZ_SECONDS=N` runs for N
//! seconds per target with a time-derived seed and prints the executions (`scripts/fuzz.sh`). Inputs
//! that ever panicked are kept in `tests/fuzz/` and replayed first.

use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use pntr_service::decode::{query, Limits};
use pntr_service::proto;
use pntr_service::wire;
use prost::Message;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn budget() -> (u64, Option<Duration>) {
    match std::env::var("PNTR_FUZZ_SECONDS")
        .ok()
        .and_then(|s| s.parse::<f64>().ok())
    {
        Some(s) => (
            std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .unwrap()
                .as_nanos() as u64,
            Some(Duration::from_secs_f64(s)),
        ),
        None => (20261122, None),
    }
}

/// One random edit: flip bits, overwrite, insert, delete, truncate, or splice a length-like value.
fn mutate(rng: &mut ChaCha8Rng, b: &mut Vec<u8>) {
    let n = b.len().max(1);
    match rng.gen_range(0..7) {
        0 => {
            for _ in 0..rng.gen_range(1..8) {
                let i = rng.gen_range(0..n);
                if let Some(x) = b.get_mut(i) {
                    *x ^= 1 << rng.gen_range(0..8);
                }
            }
        }
        1 => {
            let i = rng.gen_range(0..n);
            if let Some(x) = b.get_mut(i) {
                *x = [0, 0xff, 0x7f, 0x80, 1][rng.gen_range(0..5)];
            }
        }
        2 => {
            let i = rng.gen_range(0..=b.len());
            let k = rng.gen_range(1..16);
            b.splice(i..i, (0..k).map(|_| rng.gen::<u8>()));
        }
        3 => {
            let i = rng.gen_range(0..n);
            let k = rng.gen_range(1..64).min(b.len().saturating_sub(i));
            b.drain(i..i + k);
        }
        4 => b.truncate(rng.gen_range(0..n)),
        5 => {
            let i = rng.gen_range(0..n);
            let v: u64 = [0, 1, u32::MAX as u64, u64::MAX, 1 << 40][rng.gen_range(0..5)];
            for (k, byte) in v.to_le_bytes().iter().enumerate() {
                if let Some(x) = b.get_mut(i + k) {
                    *x = *byte;
                }
            }
        }
        _ => {
            let i = rng.gen_range(0..n);
            let j = rng.gen_range(0..n);
            if i < b.len() && j < b.len() {
                b.swap(i, j);
            }
        }
    }
}

fn corpus(target: &str) -> Vec<PathBuf> {
    let dir = pntr_tests::workspace_root().join("tests/fuzz").join(target);
    let mut v: Vec<PathBuf> = std::fs::read_dir(&dir)
        .map(|d| d.filter_map(|e| e.ok()).map(|e| e.path()).collect())
        .unwrap_or_default();
    v.retain(|p| {
        !p.file_name()
            .is_some_and(|n| n.to_string_lossy().starts_with('.'))
    });
    v.sort();
    v
}

/// Run `check` on the kept corpus, then on mutations of `seeds`; returns executions.
fn fuzz(target: &str, seeds: &[Vec<u8>], iterations: usize, check: &dyn Fn(&[u8])) -> usize {
    for p in corpus(target) {
        let b = std::fs::read(&p).unwrap();
        let r = catch_unwind(AssertUnwindSafe(|| check(&b)));
        assert!(r.is_ok(), "kept input {} panics again", p.display());
    }
    let (seed, time) = budget();
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let t0 = Instant::now();
    let mut runs = 0;
    loop {
        match time {
            Some(t) if t0.elapsed() >= t => break,
            None if runs >= iterations => break,
            _ => {}
        }
        let mut b = seeds[runs % seeds.len()].clone();
        for _ in 0..rng.gen_range(1..4) {
            mutate(&mut rng, &mut b);
        }
        if catch_unwind(AssertUnwindSafe(|| check(&b))).is_err() {
            let dir = std::env::temp_dir().join(format!("pntr-fuzz-{target}"));
            std::fs::create_dir_all(&dir).unwrap();
            let p = dir.join(format!("crash-{seed}-{runs}"));
            std::fs::write(&p, &b).unwrap();
            panic!(
                "{target}: input {} panicked (kept at {})",
                runs,
                p.display()
            );
        }
        runs += 1;
    }
    eprintln!(
        "{target}: {runs} executions in {:.1} s, seed {seed}, no panic",
        t0.elapsed().as_secs_f64()
    );
    runs
}

fn small_view() -> (pntr_core::RgbImage, pntr_core::DepthMap) {
    let (w, h) = (24u32, 16u32);
    let rgb = pntr_core::RgbImage {
        width: w,
        height: h,
        data: (0..w * h * 3).map(|i| (i * 7) as u8).collect(),
    };
    let depth = pntr_core::DepthMap {
        width: w,
        height: h,
        data: (0..w * h).map(|i| 0.5 + (i % 13) as f32 * 0.1).collect(),
    };
    (rgb, depth)
}

#[test]
fn localize_requests_never_panic_the_decoder() {
    let (rgb, depth) = small_view();
    let k = pntr_core::Intrinsics {
        fx: 20.0,
        fy: 20.0,
        cx: 11.5,
        cy: 7.5,
        width: 24,
        height: 16,
    };
    let seeds: Vec<Vec<u8>> = vec![
        wire::raw_request(&rgb, &depth, Some(&k)).encode_to_vec(),
        wire::png_request(&rgb, &depth, Some(&k))
            .unwrap()
            .encode_to_vec(),
    ];
    let limits = Limits {
        max_width: 256,
        max_height: 256,
    };
    fuzz("request", &seeds, 20000, &|b| {
        if let Ok(req) = proto::LocalizeRequest::decode(b) {
            let _ = query(&req, &limits);
        }
    });
}

/// Recompute every section checksum of a (possibly mutated) map file whose section lengths still fit.
fn fix_checksums(b: &mut [u8]) {
    let mut pos = 12;
    while pos + 12 <= b.len() {
        let len = u64::from_le_bytes(b[pos + 4..pos + 12].try_into().unwrap()) as usize;
        let start = pos + 12;
        let Some(end) = start.checked_add(len).filter(|&e| e + 8 <= b.len()) else {
            return;
        };
        let sum = pntr_core::bytes::fnv1a(&b[start..end]);
        b[end..end + 8].copy_from_slice(&sum.to_le_bytes());
        pos = end + 8;
    }
}

fn small_map(dir: &Path) -> Vec<u8> {
    let cfg = pntr_synth::SynthConfig {
        points_per_scene: 2,
        queries_per_point: 1,
        seed: 4,
        ..Default::default()
    };
    pntr_synth::synthesize(&cfg, dir, pntr_synth::plan_all(&cfg), &|| {}).unwrap();
    let index = pntr_dataset::DatasetIndex::open(dir).unwrap();
    let models = pntr_tests::workspace_root().join("models");
    let preset = pntr_pipeline::preset::Preset {
        keypoints: 32,
        vlad_words: 4,
        ..pntr_pipeline::preset::Preset::named("xfeat-mnn").unwrap()
    };
    let stage = preset.feature_config(models.clone()).build().unwrap();
    let scenes: Vec<_> = index.scenes.iter().collect();
    let m =
        pntr_pipeline::map::build("f", &scenes, &preset, &stage, &models, &mut |_, _| {}).unwrap();
    let p = dir.join("m.pntrmap");
    pntr_pipeline::mapfile::save(&m, &p).unwrap();
    std::fs::read(&p).unwrap()
}

#[test]
fn map_files_never_panic_the_loader() {
    let dir = tempfile::tempdir().unwrap();
    let good = small_map(dir.path());
    let path = dir.path().join("mutated.pntrmap");
    let load = |b: &[u8]| {
        std::fs::write(&path, b).unwrap();
        let _ = pntr_pipeline::mapfile::load(&path, |_| {
            Err(pntr_retrieval::RetrievalError::Model(
                "no onnx model in this test".into(),
            ))
        });
    };
    // Half the mutations keep checksums valid, so they reach the record and section parsers.
    let mut fixed_seed = good.clone();
    fix_checksums(&mut fixed_seed);
    fuzz("mapfile", &[good.clone(), fixed_seed], 2000, &|b| {
        load(b);
        let mut c = b.to_vec();
        fix_checksums(&mut c);
        load(&c);
    });
}
