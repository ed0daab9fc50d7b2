//! User-supplied ONNX extractor and matcher plug in by configuration, checked with tiny models that
//! the test writes (tests/python/make_onnx_models.py) and that follow the documented contracts.

use pntr_core::RgbImage;
use pntr_features::config::FeatureConfig;
use pntr_tests::run_python;

fn image(r: u8, g: u8, b: u8) -> RgbImage {
    RgbImage::new(64, 48, [r, g, b].repeat(64 * 48)).unwrap()
}

#[test]
fn onnx_extractor_and_matcher_follow_the_contract() {
    let dir = tempfile::tempdir().unwrap();
    run_python("make_onnx_models.py", &[dir.path().as_os_str()]);
    let cfg = FeatureConfig {
        extractor: "onnx".into(),
        matcher: "onnx".into(),
        extractor_model: Some(dir.path().join("tiny_extractor.onnx")),
        matcher_model: Some(dir.path().join("tiny_matcher.onnx")),
        matcher_dim: Some(3),
        top_k: 3,
        ..FeatureConfig::default()
    };
    let stage = cfg.build().unwrap();
    let a = stage.extractor.extract(&image(255, 0, 0)).unwrap();
    // Top 3 of 4 by score, highest first; keypoints and descriptors stay aligned.
    assert_eq!(a.keypoints, vec![[20.0, 30.0], [40.0, 15.0], [50.0, 50.0]]);
    assert_eq!(a.scores, vec![0.9, 0.8, 0.7]);
    assert_eq!(a.dim, 3);
    assert!((a.descriptor(0)[0] - 1.0).abs() < 1e-6 && (a.descriptor(0)[2] - 2.0).abs() < 1e-6);
    assert_eq!(a.image_size, (64, 48));
    // Matching a set with itself pairs every keypoint with itself; the dustbin never wins.
    let m = stage.matcher.match_features(&a, &a).unwrap();
    assert_eq!(m.pairs, vec![(0, 0), (1, 1), (2, 2)]);
    // A descriptor length the matcher was not configured for is refused per request.
    let mut wrong = a.clone();
    wrong.dim = 1;
    wrong.descriptors.truncate(3);
    assert!(stage
        .matcher
        .match_features(&wrong, &a)
        .unwrap_err()
        .to_string()
        .contains("3-d descriptors"));
    // The mnn matcher works with any float descriptor.
    let mnn = FeatureConfig {
        matcher: "mnn".into(),
        ..cfg.clone()
    }
    .build()
    .unwrap();
    assert_eq!(mnn.matcher.match_features(&a, &a).unwrap().pairs.len(), 3);
    // A model with the wrong outputs is refused at start-up, naming what is missing.
    let swapped = FeatureConfig {
        extractor_model: Some(dir.path().join("tiny_matcher.onnx")),
        ..cfg.clone()
    };
    let e = swapped.build().unwrap_err().to_string();
    assert!(
        e.contains("tiny_matcher.onnx") && e.contains("has no input `image`"),
        "{e}"
    );
    let missing = FeatureConfig {
        extractor_model: None,
        ..cfg
    };
    assert!(missing
        .build()
        .unwrap_err()
        .to_string()
        .contains("needs a model file"));
}

#[test]
fn onnx_global_descriptor_follows_the_contract_and_a_wrong_shape_is_refused_at_load() {
    use pntr_retrieval::onnx_global::OnnxGlobal;
    let dir = tempfile::tempdir().unwrap();
    run_python("make_onnx_models.py", &[dir.path().as_os_str()]);
    let rt = Default::default();
    let g = OnnxGlobal::load(&dir.path().join("tiny_global.onnx"), &rt, None, None).unwrap();
    assert_eq!(g.dim(), 3);
    // The model sees RGB in 0..1, channel-planar; its output is L2-normalised here.
    let d = g.describe(&image(255, 0, 0)).unwrap();
    assert!(
        (d[0] - 1.0).abs() < 1e-6 && d[1].abs() < 1e-6 && d[2].abs() < 1e-6,
        "{d:?}"
    );
    let d = g.describe(&image(0, 90, 120)).unwrap();
    assert!(
        (d[1] - 0.6).abs() < 1e-3 && (d[2] - 0.8).abs() < 1e-3,
        "{d:?}"
    );
    // A fixed input size resizes the image first.
    let fixed = OnnxGlobal::load(
        &dir.path().join("tiny_global.onnx"),
        &rt,
        Some((32, 32)),
        Some(3),
    )
    .unwrap();
    assert_eq!(
        fixed.describe(&image(0, 0, 7)).unwrap(),
        vec![0.0, 0.0, 1.0]
    );

    let bad = dir.path().join("tiny_global_bad.onnx");
    let e = OnnxGlobal::load(&bad, &rt, None, None)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("tiny_global_bad.onnx") && e.contains("[1, D]") && e.contains("[1, 3, 1, 1]"),
        "{e}"
    );
    let e = OnnxGlobal::load(&dir.path().join("tiny_global.onnx"), &rt, None, Some(256))
        .unwrap_err()
        .to_string();
    assert!(e.contains("expects 256"), "{e}");
    let e = OnnxGlobal::load(&dir.path().join("missing.onnx"), &rt, None, None)
        .unwrap_err()
        .to_string();
    assert!(e.contains("missing.onnx") && e.contains("not found"), "{e}");
}
