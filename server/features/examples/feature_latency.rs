//! Latency of the feature stage: XFeat at 256x256 and 640x480, LighterGlue and MNN at 256/512/1024
//! keypoints per side. Prints a markdown table and one JSON object (for BENCHMARKS.md).
//!
//! `cargo run --release -p pntr-features --example feature_latency -- [--device cpu|cuda:N]
//!  [--threads N] [--iters N] [--models DIR]`
//! The Python counterpart `scripts/bench_features.py` times the same ONNX files through Python
//! onnxruntime on the same shapes, so the ratio shows what the Rust side adds (sparse step, filter).
//! The images come from `models/reference/` (no dataset or HDF5 needed, so the binary runs anywhere).

use std::path::PathBuf;
use std::time::Instant;

use pntr_core::RgbImage;
use pntr_features::lighterglue::LighterGlue;
use pntr_features::mnn::Mnn;
use pntr_features::runtime::{Device, RuntimeOptions};
use pntr_features::xfeat::{XFeat, XFeatParams};
use pntr_features::{Extractor, Features, Matcher};

fn arg(name: &str) -> Option<String> {
    let args: Vec<String> = std::env::args().collect();
    args.iter()
        .position(|a| a == name)
        .and_then(|i| args.get(i + 1).cloned())
}

fn reference_image(models: &std::path::Path) -> RgbImage {
    let bytes =
        std::fs::read(models.join("reference/image_a.npy")).expect("models/reference/image_a.npy");
    let hlen = u16::from_le_bytes([bytes[8], bytes[9]]) as usize;
    RgbImage::new(256, 256, bytes[10 + hlen..].to_vec()).expect("256x256x3")
}

/// Nearest-neighbour upscale to w x h (a larger test image with real structure).
fn upscale(img: &RgbImage, w: u32, h: u32) -> RgbImage {
    let mut data = Vec::with_capacity((w * h * 3) as usize);
    for y in 0..h {
        for x in 0..w {
            let px = img.pixel(x * img.width / w, y * img.height / h);
            data.extend_from_slice(&px);
        }
    }
    RgbImage::new(w, h, data).expect("sized")
}

fn median_ms(iters: usize, mut f: impl FnMut()) -> f64 {
    for _ in 0..3 {
        f();
    }
    let mut t: Vec<f64> = (0..iters)
        .map(|_| {
            let s = Instant::now();
            f();
            s.elapsed().as_secs_f64() * 1e3
        })
        .collect();
    t.sort_by(f64::total_cmp);
    t[t.len() / 2]
}

fn take(f: &Features, k: usize) -> Features {
    let k = k.min(f.len());
    Features {
        keypoints: f.keypoints[..k].to_vec(),
        scores: f.scores[..k].to_vec(),
        descriptors: f.descriptors[..k * f.dim].to_vec(),
        dim: f.dim,
        binary: Vec::new(),
        image_size: f.image_size,
    }
}

fn main() {
    let models = arg("--models")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from("models"));
    let iters: usize = arg("--iters").and_then(|s| s.parse().ok()).unwrap_or(20);
    let threads: usize = arg("--threads").and_then(|s| s.parse().ok()).unwrap_or(1);
    let device = match arg("--device").as_deref() {
        None | Some("cpu") => Device::Cpu,
        Some(d) => Device::Cuda(d.trim_start_matches("cuda:").parse().unwrap_or(0)),
    };
    let runtime = RuntimeOptions {
        threads,
        device,
        ..RuntimeOptions::default()
    };
    let xfeat = XFeat::load(
        &models.join("xfeat_backbone.onnx"),
        XFeatParams {
            top_k: 1024,
            runtime: runtime.clone(),
            ..XFeatParams::default()
        },
    )
    .expect("xfeat");
    let lg = LighterGlue::load(&models.join("lighterglue.onnx"), &runtime).expect("lighterglue");
    let small = reference_image(&models);
    let big = upscale(&small, 640, 480);
    let mut rows = Vec::new();
    for (name, img) in [("xfeat 256x256", &small), ("xfeat 640x480", &big)] {
        let ms = median_ms(iters, || {
            xfeat.extract(img).expect("extract");
        });
        rows.push((name.to_string(), ms));
    }
    // Keypoints for the matchers: the 640x480 image against itself shifted by a few pixels.
    let fa = xfeat.extract(&big).expect("extract");
    let mut shifted = big.clone();
    shifted.data.rotate_left(3 * 3);
    let fb = xfeat.extract(&shifted).expect("extract");
    for k in [256, 512, 1024] {
        let (a, b) = (take(&fa, k), take(&fb, k));
        let ms = median_ms(iters, || {
            lg.match_features(&a, &b).expect("match");
        });
        rows.push((format!("lighterglue {}+{}", a.len(), b.len()), ms));
        let ms = median_ms(iters, || {
            Mnn::default().match_features(&a, &b).expect("match");
        });
        rows.push((format!("mnn {}+{}", a.len(), b.len()), ms));
    }
    // ALIKED and LightGlue-for-ALIKED, when their models are there.
    let cfg = |matcher: &str| pntr_features::config::FeatureConfig {
        extractor: "aliked".into(),
        matcher: matcher.into(),
        models_dir: models.clone(),
        runtime: runtime.clone(),
        ..Default::default()
    };
    match cfg("mnn").build() {
        Err(e) => eprintln!("aliked skipped: {e}"),
        Ok(stage) => {
            for (name, img) in [("aliked 256x256", &small), ("aliked 640x480", &big)] {
                let ms = median_ms(iters.min(10), || {
                    stage.extractor.extract(img).expect("extract");
                });
                rows.push((name.to_string(), ms));
            }
            match cfg("lightglue").build() {
                Err(e) => eprintln!("lightglue(aliked) skipped: {e}"),
                Ok(lga) => {
                    let fa = stage.extractor.extract(&big).expect("extract");
                    let fb = stage.extractor.extract(&shifted).expect("extract");
                    for k in [256, 512, 1024] {
                        let (a, b) = (take(&fa, k), take(&fb, k));
                        let ms = median_ms(iters.min(10), || {
                            lga.matcher.match_features(&a, &b).expect("match");
                        });
                        rows.push((format!("lightglue(aliked) {}+{}", a.len(), b.len()), ms));
                    }
                }
            }
        }
    }
    println!(
        "provider: {} (xfeat), {} (lighterglue); threads {threads}; median of {iters}",
        xfeat.provider(),
        lg.provider()
    );
    println!("| stage | ms |\n|---|---|");
    for (n, ms) in &rows {
        println!("| {n} | {ms:.2} |");
    }
    let json: Vec<String> = rows
        .iter()
        .map(|(n, ms)| format!("\"{n}\": {ms:.3}"))
        .collect();
    println!(
        "{{\"provider\": \"{}\", {}}}",
        xfeat.provider(),
        json.join(", ")
    );
}
