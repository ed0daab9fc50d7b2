//! The committed ONNX models through ONNX Runtime: parity with the upstream implementation, match
//! accuracy on synthetic renders with known geometry, and clear errors for bad models and images.

use std::path::PathBuf;

use nalgebra::Point3;
use pntr_core::{convert_axes, CameraAxes, Intrinsics, RgbImage};
use pntr_features::lighterglue::LighterGlue;
use pntr_features::mnn::Mnn;
use pntr_features::openvino::Precision;
use pntr_features::orb::Orb;
use pntr_features::runtime::{Engine, RuntimeOptions};
use pntr_features::xfeat::{XFeat, XFeatParams};
use pntr_features::{Extractor, FeatureError, Features, Matcher};

fn models() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../models")
}

/// A minimal .npy reader (version 1, little-endian, C order) for the reference outputs.
fn npy(name: &str) -> (Vec<usize>, String, Vec<u8>) {
    let bytes = std::fs::read(models().join("reference").join(format!("{name}.npy"))).unwrap();
    assert_eq!(&bytes[..6], b"\x93NUMPY");
    let hlen = u16::from_le_bytes([bytes[8], bytes[9]]) as usize;
    let header = std::str::from_utf8(&bytes[10..10 + hlen]).unwrap();
    let descr = header
        .split("'descr': '")
        .nth(1)
        .unwrap()
        .split('\'')
        .next()
        .unwrap()
        .to_string();
    let shape_s = header
        .split("'shape': (")
        .nth(1)
        .unwrap()
        .split(')')
        .next()
        .unwrap();
    let shape = shape_s
        .split(',')
        .filter(|s| !s.trim().is_empty())
        .map(|s| s.trim().parse().unwrap())
        .collect();
    (shape, descr, bytes[10 + hlen..].to_vec())
}

fn npy_f32(name: &str) -> (Vec<usize>, Vec<f32>) {
    let (shape, descr, data) = npy(name);
    assert_eq!(descr, "<f4", "{name}");
    (
        shape,
        data.chunks_exact(4)
            .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect(),
    )
}

fn reference_features(side: &str) -> Features {
    let (ks, k) = npy_f32(&format!("kpts_{side}"));
    let (_, s) = npy_f32(&format!("scores_{side}"));
    let (ds, d) = npy_f32(&format!("desc_{side}"));
    let f = Features {
        keypoints: k.chunks_exact(2).map(|p| [p[0], p[1]]).collect(),
        scores: s,
        descriptors: d,
        dim: ds[1],
        binary: Vec::new(),
        image_size: (256, 256),
    };
    assert_eq!(f.len(), ks[0]);
    f
}

fn image(name: &str) -> RgbImage {
    let (shape, descr, data) = npy(name);
    assert_eq!(descr, "|u1");
    RgbImage::new(shape[1] as u32, shape[0] as u32, data).unwrap()
}

/// How many reference keypoints `ours` has at the same pixel (within 1e-3), and the largest descriptor
/// difference over those.
fn keypoint_parity(
    ref_kpts: &[[f32; 2]],
    ref_desc: &[f32],
    dim: usize,
    ours: &Features,
) -> (usize, f32) {
    let mut found = 0;
    let mut worst = 0f32;
    for (i, k) in ref_kpts.iter().enumerate() {
        let hit = ours
            .keypoints
            .iter()
            .position(|q| (q[0] - k[0]).abs() < 1e-3 && (q[1] - k[1]).abs() < 1e-3);
        if let Some(j) = hit {
            found += 1;
            let d = ref_desc[i * dim..(i + 1) * dim]
                .iter()
                .zip(ours.descriptor(j))
                .map(|(a, b)| (a - b).abs());
            worst = worst.max(d.fold(0.0, f32::max));
        }
    }
    (found, worst)
}

fn xfeat_from(file: &str) -> XFeat {
    XFeat::load(&models().join(file), XFeatParams::default()).unwrap()
}

fn xfeat() -> XFeat {
    xfeat_from("xfeat_backbone.onnx")
}

#[test]
fn xfeat_and_lighterglue_match_the_upstream_implementation() {
    let ours = xfeat().extract(&image("image_a")).unwrap();
    let refa = reference_features("a");
    // Keypoints as sets: every reference keypoint should be found at the same pixel.
    let (found, worst_desc) = keypoint_parity(&refa.keypoints, &refa.descriptors, refa.dim, &ours);
    let worst_score = refa
        .keypoints
        .iter()
        .zip(&refa.scores)
        .filter_map(|(k, s)| {
            ours.keypoints
                .iter()
                .position(|q| q == k)
                .map(|j| (s - ours.scores[j]).abs())
        })
        .fold(0f32, f32::max);
    eprintln!("parity: {found}/{} reference keypoints found; worst descriptor diff {worst_desc:e}, score diff {worst_score:e}", refa.len());
    assert!(
        found as f64 >= 0.99 * refa.len() as f64,
        "{found} of {}",
        refa.len()
    );
    assert!(worst_desc < 1e-3 && worst_score < 1e-4);

    // LighterGlue on the reference features gives the reference matches.
    let lg = LighterGlue::load(&models().join("lighterglue.onnx"), &Default::default()).unwrap();
    let m = lg.match_features(&refa, &reference_features("b")).unwrap();
    let (_, _, raw) = npy("matches");
    let want: Vec<(u32, u32)> = raw
        .chunks_exact(16)
        .map(|c| {
            (
                i64::from_le_bytes(c[..8].try_into().unwrap()) as u32,
                i64::from_le_bytes(c[8..].try_into().unwrap()) as u32,
            )
        })
        .collect();
    let same = m.pairs.iter().filter(|p| want.contains(p)).count();
    eprintln!(
        "parity: {} matches, {} reference, {same} identical",
        m.pairs.len(),
        want.len()
    );
    assert!(
        same as f64 >= 0.98 * want.len() as f64 && m.pairs.len() <= want.len() + want.len() / 50
    );
}

/// Over query/database pairs of one synthetic Point with real overlap: (pairs, matches with valid depth,
/// matches within 3 px of where depth and poses put them).
fn geometric_accuracy(x: &dyn Extractor, m: &dyn Matcher) -> (usize, usize, usize) {
    let cfg = pntr_synth::SynthConfig {
        points_per_scene: 2,
        queries_per_point: 12,
        seed: 3,
        ..Default::default()
    };
    let planned = pntr_synth::plan_scene(&cfg, 0);
    let renderer = pntr_synth::Renderer::new(&planned.scene);
    let k = Intrinsics::hpointloc();
    let (mut total, mut good, mut pairs) = (0, 0, 0);
    let point = &planned.points[0];
    let forward =
        |p: &nalgebra::Isometry3<f64>| p.rotation * nalgebra::Vector3::new(0.0, 0.0, -1.0);
    for q in &point.queries {
        // The database view looking most nearly the query's way: real overlap.
        let db = point
            .db
            .iter()
            .max_by(|a, b| {
                forward(a)
                    .dot(&forward(q))
                    .total_cmp(&forward(b).dot(&forward(q)))
            })
            .unwrap();
        let (ra, rb) = (renderer.render(q, &k, 1), renderer.render(db, &k, 2));
        let (fa, fb) = (x.extract(&ra.rgb).unwrap(), x.extract(&rb.rgb).unwrap());
        let b_from_a = convert_axes(db, CameraAxes::Habitat, CameraAxes::OpenCv).inverse()
            * convert_axes(q, CameraAxes::Habitat, CameraAxes::OpenCv);
        for (i, j) in m.match_features(&fa, &fb).unwrap().pairs {
            let [u, v] = fa.keypoints[i as usize];
            let Some(z) = ra.depth.get(u.round() as u32, v.round() as u32) else {
                continue;
            };
            let p: Point3<f64> = b_from_a * k.backproject(u as f64, v as f64, z as f64);
            let Some(uv) = k.project(&p) else { continue };
            let [bu, bv] = fb.keypoints[j as usize];
            total += 1;
            good +=
                (((uv.x - bu as f64).powi(2) + (uv.y - bv as f64).powi(2)).sqrt() < 3.0) as usize;
        }
        pairs += 1;
    }
    eprintln!(
        "{} + {}: {pairs} pairs, {total} matches ({:.1}/pair), {:.1}% within 3 px",
        x.name(),
        m.name(),
        total as f64 / pairs as f64,
        100.0 * good as f64 / total.max(1) as f64
    );
    (pairs, total, good)
}

#[test]
fn default_pipeline_matches_agree_with_geometry() {
    let lg = LighterGlue::load(&models().join("lighterglue.onnx"), &Default::default()).unwrap();
    let (pairs, total, good) = geometric_accuracy(&xfeat(), &lg);
    assert!(
        good as f64 >= 0.8 * total as f64,
        "{good} of {total} LighterGlue matches are right"
    );
    assert!(
        total >= 30 * pairs,
        "too few matches: {total} over {pairs} pairs"
    );
}

#[test]
fn mnn_and_orb_matches_on_synthetic_renders() {
    // Baselines: reported, with floors well below what they reach, to catch breakage (a wrong
    // coordinate convention or descriptor layout drops them to near zero).
    let (pairs, total, good) = geometric_accuracy(&xfeat(), &Mnn::default());
    assert!(
        good as f64 >= 0.4 * total as f64 && total >= 30 * pairs,
        "xfeat+mnn: {good}/{total}"
    );
    let (pairs, total, good) = geometric_accuracy(&Orb::default(), &Mnn::default());
    assert!(
        good as f64 >= 0.4 * total as f64 && total >= 10 * pairs,
        "orb+mnn: {good}/{total}"
    );
}

/// How far `other` (another run of XFeat's network) strays from the float model on renders of a
/// scene neither calibration saw (int8 was calibrated on seed 11): (keypoints of `other` with one
/// of the float model's within 1 px, keypoints of `other`, median descriptor cosine of those pairs).
fn agreement(float: &XFeat, other: &XFeat) -> (usize, usize, f32) {
    let cfg = pntr_synth::SynthConfig {
        points_per_scene: 2,
        queries_per_point: 4,
        seed: 5,
        ..Default::default()
    };
    let planned = pntr_synth::plan_scene(&cfg, 0);
    let renderer = pntr_synth::Renderer::new(&planned.scene);
    let k = Intrinsics::hpointloc();
    let (mut kept, mut total, mut cosines) = (0usize, 0usize, Vec::new());
    for (i, pose) in planned.points[0].queries.iter().enumerate() {
        let rgb = renderer.render(pose, &k, i as u64).rgb;
        let (f, q) = (float.extract(&rgb).unwrap(), other.extract(&rgb).unwrap());
        for (j, kq) in q.keypoints.iter().enumerate() {
            total += 1;
            let near = f
                .keypoints
                .iter()
                .position(|kf| (kf[0] - kq[0]).abs() <= 1.0 && (kf[1] - kq[1]).abs() <= 1.0);
            if let Some(n) = near {
                kept += 1;
                let dot: f32 = f
                    .descriptor(n)
                    .iter()
                    .zip(q.descriptor(j))
                    .map(|(a, b)| a * b)
                    .sum();
                cosines.push(dot);
            }
        }
    }
    cosines.sort_by(f32::total_cmp);
    (kept, total, cosines[cosines.len() / 2])
}

#[test]
fn int8_backbone_agrees_with_the_float_one() {
    let (float, int8) = (xfeat(), xfeat_from("xfeat_backbone_int8.onnx"));
    let (kept, total, median) = agreement(&float, &int8);
    eprintln!(
        "int8 vs float: {kept} of {total} keypoints within 1 px, median descriptor cosine {median:.4}"
    );
    assert!(kept as f64 >= 0.8 * total as f64, "{kept} of {total}");
    assert!(median >= 0.98, "median cosine {median}");
    // Matches between renders with known geometry: as many and as right as the float model's.
    let (_, total_f, good_f) = geometric_accuracy(&float, &Mnn::default());
    let (_, total_q, good_q) = geometric_accuracy(&int8, &Mnn::default());
    let (share_f, share_q) = (
        good_f as f64 / total_f as f64,
        good_q as f64 / total_q as f64,
    );
    assert!(
        share_q >= share_f - 0.03 && total_q as f64 >= 0.85 * total_f as f64,
        "int8 {good_q}/{total_q} against float {good_f}/{total_f}"
    );
    // Without its model file the int8 extractor says which file and how to make it.
    let dir = tempfile::tempdir().unwrap();
    std::fs::copy(
        models().join("xfeat_backbone.onnx"),
        dir.path().join("xfeat_backbone.onnx"),
    )
    .unwrap();
    let built = pntr_features::config::FeatureConfig {
        extractor: "xfeat-int8".into(),
        matcher: "mnn".into(),
        models_dir: dir.path().to_path_buf(),
        ..Default::default()
    }
    .build();
    let Err(e) = built else {
        panic!("built without xfeat_backbone_int8.onnx")
    };
    let e = e.to_string();
    assert!(
        e.contains("xfeat_backbone_int8.onnx") && e.contains("models/quantize.py"),
        "{e}"
    );
}

fn xfeat_on(engine: Engine) -> XFeat {
    XFeat::load(
        &models().join("xfeat_backbone.onnx"),
        XFeatParams {
            runtime: RuntimeOptions {
                engine,
                ..RuntimeOptions::default()
            },
            ..XFeatParams::default()
        },
    )
    .unwrap()
}

#[test]
fn openvino_runs_the_float_backbone_as_onnx_runtime_does() {
    // The engine itself, at f32: the same keypoints and descriptors up to summation order.
    let (ort, ov) = (xfeat(), xfeat_on(Engine::OpenVino(Precision::F32)));
    assert_eq!(ov.provider(), "openvino-f32");
    let (kept, total, median) = agreement(&ort, &ov);
    eprintln!("OpenVINO f32 vs ONNX Runtime: {kept} of {total} keypoints within 1 px, median cosine {median:.6}");
    assert!(kept as f64 >= 0.995 * total as f64, "{kept} of {total}");
    assert!(median >= 0.99999, "median cosine {median}");
    // The graph's height and width are free: a 320 x 240 frame (the 256 x 256 render's top rows,
    // widened by a mirror of its right edge) after 256 x 256 ones gets the same keypoints from both.
    let cfg = pntr_synth::SynthConfig {
        seed: 5,
        ..Default::default()
    };
    let planned = pntr_synth::plan_scene(&cfg, 0);
    let rgb = pntr_synth::Renderer::new(&planned.scene)
        .render(&planned.points[0].db[0], &Intrinsics::hpointloc(), 0)
        .rgb;
    let (w, h) = (320usize, 240usize);
    let mut data = Vec::with_capacity(w * h * 3);
    for y in 0..h {
        for x in 0..w {
            let col = if x < 256 { x } else { 511 - x };
            data.extend_from_slice(&rgb.pixel(col as u32, y as u32));
        }
    }
    let wide = RgbImage::new(w as u32, h as u32, data).unwrap();
    let (a, b) = (ort.extract(&wide).unwrap(), ov.extract(&wide).unwrap());
    let near = b
        .keypoints
        .iter()
        .filter(|p| {
            a.keypoints
                .iter()
                .any(|q| (p[0] - q[0]).abs() <= 1.0 && (p[1] - q[1]).abs() <= 1.0)
        })
        .count();
    assert!(
        a.len() > 100 && b.len() == a.len() && near as f64 >= 0.99 * a.len() as f64,
        "{near} of {} keypoints near ONNX Runtime's {}",
        b.len(),
        a.len()
    );
    assert!(
        b.keypoints.iter().any(|p| p[0] > 256.0),
        "no keypoint beyond column 256"
    );
}

#[test]
fn bf16_backbone_agrees_with_the_float_one() {
    // Built by name, as presets build it; bf16 where the CPU has the instructions, else f32.
    let stage = pntr_features::config::FeatureConfig {
        extractor: "xfeat-bf16".into(),
        matcher: "mnn".into(),
        models_dir: models(),
        ..Default::default()
    }
    .build()
    .unwrap();
    assert_eq!(stage.extractor.name(), "xfeat");
    let (float, bf16) = (xfeat(), xfeat_on(Engine::OpenVino(Precision::Bf16)));
    eprintln!("xfeat-bf16 runs on {}", bf16.provider());
    assert!(
        bf16.provider().starts_with("openvino-"),
        "{}",
        bf16.provider()
    );
    let (kept, total, median) = agreement(&float, &bf16);
    eprintln!(
        "bf16 vs float: {kept} of {total} keypoints within 1 px, median descriptor cosine {median:.5}"
    );
    // bf16 keeps 8 bits of mantissa: closer to the float model than int8 (0.8, 0.98 above).
    assert!(kept as f64 >= 0.9 * total as f64, "{kept} of {total}");
    assert!(median >= 0.999, "median cosine {median}");
    let (_, total_f, good_f) = geometric_accuracy(&float, &Mnn::default());
    let (_, total_b, good_b) = geometric_accuracy(&bf16, &Mnn::default());
    let (share_f, share_b) = (
        good_f as f64 / total_f as f64,
        good_b as f64 / total_b as f64,
    );
    assert!(
        share_b >= share_f - 0.01 && total_b as f64 >= 0.95 * total_f as f64,
        "bf16 {good_b}/{total_b} against float {good_f}/{total_f}"
    );
}

#[test]
fn bad_models_and_images_are_clear_errors() {
    let missing =
        XFeat::load(&models().join("no_such_model.onnx"), XFeatParams::default()).unwrap_err();
    assert!(
        matches!(missing, FeatureError::Model { .. })
            && missing.to_string().contains("file not found"),
        "{missing}"
    );
    // A model that does not follow the contract (the extractor given to the matcher).
    let wrong = LighterGlue::load(&models().join("xfeat_backbone.onnx"), &Default::default())
        .unwrap_err()
        .to_string();
    assert!(
        wrong.contains("has no input `kpts0`") && wrong.contains("gray"),
        "{wrong}"
    );
    // A matcher given as XFeat's backbone: neither graph layout, and the error names what each lacks.
    let neither = XFeat::load(&models().join("lighterglue.onnx"), XFeatParams::default())
        .unwrap_err()
        .to_string();
    assert!(
        neither.contains("as layout 1: has no input `gray`")
            && neither.contains("as layout 2: has no input `image`"),
        "{neither}"
    );
    // A file that is not a model at all.
    let dir = std::env::temp_dir().join(format!("pntr-features-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let junk = dir.join("junk.onnx");
    std::fs::write(&junk, b"not a model").unwrap();
    let e = XFeat::load(&junk, XFeatParams::default())
        .unwrap_err()
        .to_string();
    assert!(e.contains("junk.onnx") && e.contains("cannot load"), "{e}");
    let x = xfeat();
    let tiny = RgbImage::new(16, 16, vec![0; 16 * 16 * 3]).unwrap();
    assert!(matches!(x.extract(&tiny), Err(FeatureError::Input(_))));
    let broken = RgbImage {
        width: 64,
        height: 64,
        data: vec![0; 10],
    };
    assert!(x
        .extract(&broken)
        .unwrap_err()
        .to_string()
        .contains("RGB buffer"));
    // A non-multiple-of-32 size is resized internally and keypoints come back in input pixels.
    let img = image("image_a");
    let crop: Vec<u8> = (0..250)
        .flat_map(|r| img.data[r * 256 * 3..(r * 256 + 250) * 3].to_vec())
        .collect();
    let f = x.extract(&RgbImage::new(250, 250, crop).unwrap()).unwrap();
    assert!(f.len() > 50 && f.keypoints.iter().all(|k| k[0] < 250.0 && k[1] < 250.0));
    let _ = std::fs::remove_dir_all(&dir);
}

fn aliked_stage(matcher: &str) -> Result<pntr_features::config::FeatureStage, FeatureError> {
    pntr_features::config::FeatureConfig {
        extractor: "aliked".into(),
        matcher: matcher.into(),
        models_dir: models(),
        ..Default::default()
    }
    .build()
}

#[test]
fn aliked_matches_its_export_reference_and_geometry() {
    let stage = aliked_stage("mnn").unwrap();
    let ours = stage.extractor.extract(&image("image_a")).unwrap();
    let (_, k) = npy_f32("aliked_kpts_a");
    let (_, d) = npy_f32("aliked_desc_a");
    let (_, s) = npy_f32("aliked_scores_a");
    // Padding (score 0) is not a keypoint.
    let reference: Vec<usize> = (0..s.len()).filter(|&i| s[i] > 0.0).collect();
    let ref_kpts: Vec<[f32; 2]> = reference
        .iter()
        .map(|&i| [k[2 * i], k[2 * i + 1]])
        .collect();
    let ref_desc: Vec<f32> = reference
        .iter()
        .flat_map(|&i| d[i * 128..(i + 1) * 128].to_vec())
        .collect();
    let (found, worst) = keypoint_parity(&ref_kpts, &ref_desc, 128, &ours);
    eprintln!(
        "aliked parity: {found}/{} reference keypoints, worst descriptor diff {worst:e}",
        reference.len()
    );
    assert!(found as f64 >= 0.99 * reference.len() as f64 && worst < 1e-4);
    assert_eq!(ours.dim, 128);

    let (pairs, total, good) = geometric_accuracy(stage.extractor.as_ref(), stage.matcher.as_ref());
    assert!(
        good as f64 >= 0.4 * total as f64 && total >= 30 * pairs,
        "aliked+mnn: {good}/{total}"
    );
    match aliked_stage("lightglue") {
        Ok(lg) => {
            let (pairs, total, good) =
                geometric_accuracy(lg.extractor.as_ref(), lg.matcher.as_ref());
            assert!(
                good as f64 >= 0.8 * total as f64,
                "{good} of {total} ALIKED+LightGlue matches are right"
            );
            assert!(
                total >= 30 * pairs,
                "too few matches: {total} over {pairs} pairs"
            );
        }
        Err(e) => {
            // The 48 MB model is produced on demand by models/export.py and not committed.
            assert!(e.to_string().contains("models/export.py"), "{e}");
            eprintln!("SKIPPED aliked+lightglue accuracy: {e}");
        }
    }
}

/// A pipeline asks each image for its own keypoint count (`Preset::keypoints_for`): XFeat's own
/// top-k step and the default (extract, keep the strongest) must both give the strongest `n` of the
/// full extraction, never more than the extractor's configured count.
#[test]
fn extract_at_most_keeps_the_strongest_keypoints() {
    let img = image("image_a");
    let strongest = |f: &Features, n: usize| -> Vec<[f32; 2]> {
        let mut order: Vec<usize> = (0..f.len()).collect();
        order.sort_by(|&a, &b| f.scores[b].total_cmp(&f.scores[a]).then(a.cmp(&b)));
        let mut kept: Vec<usize> = order.into_iter().take(n).collect();
        kept.sort_unstable();
        kept.into_iter().map(|i| f.keypoints[i]).collect()
    };
    let x = xfeat();
    let all = x.extract(&img).unwrap();
    assert!(all.len() > 300, "{} keypoints", all.len());
    let some = x.extract_at_most(&img, 200).unwrap();
    assert_eq!(some.len(), 200);
    let mut got = some.keypoints.clone();
    got.sort_by(|a, b| a[1].total_cmp(&b[1]).then(a[0].total_cmp(&b[0])));
    let mut want = strongest(&all, 200);
    want.sort_by(|a, b| a[1].total_cmp(&b[1]).then(a[0].total_cmp(&b[0])));
    assert_eq!(got, want);
    // Each kept keypoint keeps its own descriptor.
    let j = all
        .keypoints
        .iter()
        .position(|k| *k == some.keypoints[7])
        .unwrap();
    assert_eq!(some.descriptor(7), all.descriptor(j));
    // More than the configured count is not given.
    let params = XFeatParams {
        top_k: 100,
        ..XFeatParams::default()
    };
    let small = XFeat::load(&models().join("xfeat_backbone.onnx"), params).unwrap();
    assert_eq!(small.extract_at_most(&img, 5000).unwrap().len(), 100);
    // The default path (ORB: extract, then keep the strongest), binary descriptors with them.
    let orb = Orb { top_k: 1024 };
    let full = orb.extract(&img).unwrap();
    assert!(full.len() > 150, "{} ORB keypoints", full.len());
    let few = orb.extract_at_most(&img, 150).unwrap();
    assert_eq!(few.len(), 150);
    assert_eq!(few.binary.len(), 150);
    assert_eq!(few.keypoints, strongest(&full, 150));
    let i = full
        .keypoints
        .iter()
        .position(|k| *k == few.keypoints[3])
        .unwrap();
    assert_eq!(few.binary[3], full.binary[i]);
}
