//! The map file and the PNTR pipeline on a synthetic scene generated here: a built map saves and
//! reloads identically, corrupted or foreign files are refused with the file and section named, the
//! pipeline localises the queries it should, missing depth is skipped rather than fatal, and the
//! evaluation keeps failures in the denominator.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use pntr_core::Intrinsics;
use pntr_dataset::{DatasetIndex, Role};
use pntr_eval::{self as eval, Answer, EvalOptions};
use pntr_pipeline::map::Map;
use pntr_pipeline::mapfile;
use pntr_pipeline::pipeline::{Pipeline, Query, Status};
use pntr_pipeline::preset::Preset;

fn dataset(root: &Path) -> DatasetIndex {
    pntr_tests::synthetic_dataset(root, 5, 5, 33)
}

fn build(index: &DatasetIndex, preset: &Preset) -> (Map, pntr_features::config::FeatureStage) {
    let models = pntr_tests::models();
    let stage = preset.map_feature_config(models.clone()).build().unwrap();
    let scenes: Vec<_> = index.scenes.iter().collect();
    let mut calls = 0;
    let map = pntr_mapping::build::build("all", &scenes, preset, &stage, &models, &mut |_, _| {
        calls += 1
    })
    .unwrap();
    assert_eq!(calls, map.images.len(), "progress is reported per image");
    (map, stage)
}

fn flip(path: &Path, at: usize) -> PathBuf {
    let mut b = std::fs::read(path).unwrap();
    b[at] ^= 0x10;
    let out = path.with_extension(format!("flip{at}"));
    std::fs::write(&out, b).unwrap();
    out
}

fn load(path: &Path) -> Result<Map, String> {
    mapfile::load(path, |_| panic!("no onnx model in these maps")).map_err(|e| e.to_string())
}

/// Every query of `index` through `pipeline` on `map`: the evaluation report (printed).
fn evaluate(index: &DatasetIndex, pipeline: &Pipeline, map: &Map) -> eval::EvalReport {
    let scenes: Vec<_> = index.scenes.iter().collect();
    let report = eval::run(
        &scenes,
        &EvalOptions::default(),
        &mut |q, _| {
            let l = pipeline.localize(q)?;
            Ok(Answer::of(&l, map))
        },
        &mut |_, _| {},
    )
    .unwrap();
    eprintln!("{}", eval::table(&report));
    report
}

#[test]
fn map_round_trip_pipeline_and_refused_files() {
    let dir = tempfile::tempdir().unwrap();
    let index = dataset(dir.path());
    let preset = Preset::named("fast").unwrap();
    let (map, stage) = build(&index, &preset);
    assert_eq!(map.images.len(), 30);
    // The preset's `auto` index resolves by size, and the header says what was built.
    assert_eq!(preset.index, "auto");
    assert_eq!(map.header.preset.index, "flat");
    // Pairs stay aligned: one 3D point and one instance id per keypoint, NaN only where depth is bad.
    for im in &map.images {
        assert_eq!(im.points.len(), im.keypoints.len());
        assert_eq!(im.instances.len(), im.keypoints.len());
        assert_eq!(im.descriptors.len(), im.keypoints.len() * im.dim);
    }
    assert!(map
        .images
        .iter()
        .any(|im| im.instances.iter().any(|&i| i != 0)));

    // A real camera's images also keep a finer depth for the final polish (none at HPointLoc's
    // f = 128): one image given one, to see it round-trip beside the others' none.
    let mut map = map;
    map.images[1].fine = Some(map.images[1].thumb.clone());
    let path = dir.path().join("scene.pntrmap");
    mapfile::save(&map, &path).unwrap();
    let back = load(&path).unwrap();
    assert_eq!(back.header, map.header);
    assert_eq!(back.images, map.images);
    assert_eq!(mapfile::read_header(&path).unwrap(), map.header);
    // The image ids alone, without decoding the records (the finer depth's record among them).
    let ids: Vec<String> = map.images.iter().map(|im| im.id.clone()).collect();
    assert_eq!(mapfile::read_image_ids(&path).unwrap(), ids);
    let cut = dir.path().join("cut.pntrmap");
    let bytes = std::fs::read(&path).unwrap();
    std::fs::write(&cut, &bytes[..bytes.len() / 4]).unwrap();
    let e = mapfile::read_image_ids(&cut).unwrap_err().to_string();
    assert!(e.contains("cut.pntrmap") && e.contains("truncated"), "{e}");
    std::fs::remove_file(&cut).unwrap();
    // No temporary file is left behind.
    let leftovers: Vec<_> = std::fs::read_dir(dir.path())
        .unwrap()
        .filter_map(|e| e.ok())
        .filter(|e| e.file_name().to_string_lossy().contains("partial"))
        .collect();
    assert!(leftovers.is_empty());

    // Refused files name the file and the problem.
    let len = std::fs::metadata(&path).unwrap().len() as usize;
    let truncated = dir.path().join("truncated.pntrmap");
    std::fs::write(&truncated, &std::fs::read(&path).unwrap()[..len / 2]).unwrap();
    let e = load(&truncated).unwrap_err();
    assert!(
        e.contains("truncated.pntrmap") && e.contains("truncated"),
        "{e}"
    );
    let e = load(&flip(&path, len / 2)).unwrap_err();
    assert!(e.contains("IMGS") && e.contains("checksum"), "{e}");
    let e = load(&flip(&path, 40)).unwrap_err();
    assert!(e.contains("HEAD"), "{e}");
    let e = load(&flip(&path, len - 30)).unwrap_err();
    assert!(e.contains("RETR") || e.contains("END"), "{e}");
    let mut b = std::fs::read(&path).unwrap();
    b[8] = 99;
    let old = dir.path().join("version.pntrmap");
    std::fs::write(&old, b).unwrap();
    let e = load(&old).unwrap_err();
    assert!(e.contains("version 99") && e.contains("build-db"), "{e}");
    let e = load(&dir.path().join("HPointLoc_dataset")).unwrap_err();
    assert!(
        e.contains("HPointLoc_dataset") && e.contains("a folder, not a map file"),
        "{e}"
    );
    // What is not a regular file is named, and a FIFO is refused at once rather than waited on.
    let e = load(Path::new("/dev/zero")).unwrap_err();
    assert!(e.contains("a character device, not a map file"), "{e}");
    let fifo = dir.path().join("pipe.pntrmap");
    let made = std::process::Command::new("mkfifo").arg(&fifo).status();
    if made.is_ok_and(|s| s.success()) {
        let e = load(&fifo).unwrap_err();
        assert!(e.contains("a FIFO (named pipe), not a map file"), "{e}");
        let e = mapfile::read_header(&fifo).unwrap_err().to_string();
        assert!(e.contains("FIFO"), "{e}");
    }
    let e = load(&dir.path().join("absent.pntrmap")).unwrap_err();
    assert!(e.contains("no such file"), "{e}");
    // A map the reader would refuse is never written: a pose with NaN (a recording's bad sample
    // that slipped through) fails the save, and neither the file nor a temporary one is left.
    let kept = map.images[2].world_from_camera;
    map.images[2].world_from_camera.translation.vector.x = f64::NAN;
    let nan_path = dir.path().join("nan.pntrmap");
    let e = mapfile::save(&map, &nan_path).unwrap_err().to_string();
    map.images[2].world_from_camera = kept;
    assert!(
        e.contains("refusing to write") && e.contains("pose is not finite"),
        "{e}"
    );
    assert!(!nan_path.exists());
    assert!(std::fs::read_dir(dir.path())
        .unwrap()
        .filter_map(|e| e.ok())
        .all(|e| !e.file_name().to_string_lossy().contains("partial")));

    // The pipeline on the reloaded map.
    let map = Arc::new(back);
    let classical = Preset::named("classical").unwrap();
    let e = Pipeline::new(map.clone(), stage.clone(), classical)
        .unwrap_err()
        .to_string();
    assert!(e.contains("built with"), "{e}");
    let pipeline = Pipeline::new(map.clone(), stage, preset.clone()).unwrap();
    let k = Intrinsics::hpointloc();
    let (mut good, mut total) = (0, 0);
    for p in &index.scenes[0].points {
        let r = p.open().unwrap();
        for qi in 0..r.count(Role::Query) {
            let v = r.view(Role::Query, qi).unwrap();
            let mut depth = v.depth.clone();
            // Every other row without depth, as NaN (ROS) and 0 (RealSense) cameras send it.
            for (i, d) in depth.data.iter_mut().enumerate() {
                if (i / 256) % 2 == 1 {
                    *d = if i % 3 == 0 { 0.0 } else { f32::NAN };
                }
            }
            let l = pipeline
                .localize(&Query {
                    rgb: v.rgb.clone(),
                    depth,
                    intrinsics: k,
                })
                .unwrap();
            total += 1;
            assert_eq!(l.retrieved.len(), preset.candidates);
            assert!(l.times.total >= l.times.extraction + l.times.retrieval);
            if let (Status::Localized, Some(pose)) = (l.status, l.pose) {
                assert!(l.confidence > 0.0 && l.confidence <= 1.0);
                assert!(l.inliers >= preset.min_inliers);
                let (dt, dr) = eval::pose_error(&pose, &v.world_from_camera, false);
                good += (dt <= 0.25 && dr <= 2.0) as usize;
            } else {
                assert!(l.pose.is_none() && l.reason.is_some());
            }
        }
    }
    eprintln!("{good} of {total} queries within (0.25 m, 2 deg)");
    // With full depth about 95% of demo queries pass; half the rows missing costs some.
    assert!(good as f64 >= 0.7 * total as f64, "{good} of {total}");

    // A frame with no valid depth at all is refused, not localised.
    let v = index.scenes[0].points[0]
        .open()
        .unwrap()
        .view(Role::Query, 0)
        .unwrap();
    let mut depth = v.depth.clone();
    depth.data.iter_mut().for_each(|d| *d = f32::NAN);
    let e = pipeline
        .localize(&Query {
            rgb: v.rgb.clone(),
            depth,
            intrinsics: k,
        })
        .unwrap_err()
        .to_string();
    assert!(e.contains("no valid pixel"), "{e}");

    // Evaluation: an answer that failed counts in the denominator.
    let scenes: Vec<_> = index.scenes.iter().collect();
    let mut n = 0;
    let report = eval::run(
        &scenes,
        &EvalOptions {
            max_queries: 10,
            ..Default::default()
        },
        &mut |q, _| {
            n += 1;
            if n % 2 == 0 {
                return Err(pntr_pipeline::PipelineError::Query("dropped".into()));
            }
            let l = pipeline.localize(q)?;
            Ok(Answer::of(&l, &map))
        },
        &mut |_, _| {},
    )
    .unwrap();
    assert_eq!(report.queries, 10);
    assert_eq!(report.failed_requests, 5);
    assert!(report.recall["5m"] <= 0.5, "{:?}", report.recall);
    assert!(report.retrieval.point_at_5 <= 0.5 + 1e-9);
    assert!(report.retrieval.reranked_point_at_1 <= 0.5 + 1e-9);
    assert!(report.retrieval.reranked_point_at_1 >= report.retrieval.point_at_1 - 0.2);
    assert_eq!(report.recall.len(), 8);
    assert_eq!(report.retrieval_only.len(), 8);
}

#[test]
fn classical_preset_localizes_with_orb_bow_and_pnp() {
    let dir = tempfile::tempdir().unwrap();
    let index = dataset(dir.path());
    let preset = Preset::named("classical").unwrap();
    let (map, stage) = build(&index, &preset);
    let path = dir.path().join("classical.pntrmap");
    mapfile::save(&map, &path).unwrap();
    let map = Arc::new(load(&path).unwrap());
    let pipeline = Pipeline::new(map.clone(), stage, preset).unwrap();
    let report = evaluate(&index, &pipeline, &map);
    // BoW retrieval finds the right Point far above chance (1/5); ORB + PnP localises some queries
    // (a broken pipeline localises none).
    assert!(report.retrieval.point_at_1 >= 0.5, "{:?}", report.retrieval);
    assert!(report.recall["1m_10deg"] >= 0.2, "{:?}", report.recall);
}

#[test]
fn int8_and_bf16_presets_serve_a_map_built_with_the_float_backbone() {
    // A map built with `xfeat-mnn` and queried with the int8 backbone (`xfeat-mnn-int8`) or with
    // the float one in bfloat16 on OpenVINO (`xfeat-mnn-bf16`): the descriptors are the same
    // network's, so the pipeline accepts the map and localizes about as many queries, with no more
    // wrong answers, as the float backbone on the same queries.
    let dir = tempfile::tempdir().unwrap();
    let index = dataset(dir.path());
    let float = Preset::named("xfeat-mnn").unwrap();
    let (map, float_stage) = build(&index, &float);
    let map = Arc::new(map);
    let mut reports = vec![(
        "xfeat-mnn",
        evaluate(
            &index,
            &Pipeline::new(map.clone(), float_stage, float).unwrap(),
            &map,
        ),
    )];
    for (name, query_file, recall_drop) in [
        ("xfeat-mnn-int8", "xfeat_backbone_int8.onnx", 0.05),
        ("xfeat-mnn-bf16", "xfeat_backbone.onnx", 0.02),
    ] {
        let preset = Preset::named(name).unwrap();
        let stage = preset.feature_config(pntr_tests::models()).build().unwrap();
        // The preset's own map: its images described by the float backbone (the same descriptors
        // as the float map's), both models named in the header.
        let (own, _) = build(&index, &preset);
        assert!(own
            .images
            .iter()
            .zip(&map.images)
            .all(|(a, b)| a.descriptors == b.descriptors && a.keypoints == b.keypoints));
        let roles: Vec<(&str, &str, &str)> = own
            .header
            .models
            .iter()
            .map(|m| {
                (
                    m.role.as_str(),
                    m.name.as_str(),
                    m.file.as_deref().unwrap_or(""),
                )
            })
            .collect();
        assert_eq!(
            roles,
            [
                ("extractor", "xfeat", "xfeat_backbone.onnx"),
                ("query_extractor", preset.extractor.as_str(), query_file),
                ("matcher", "mnn", "")
            ]
        );
        // The ALIKED preset still refuses the XFeat map.
        let accurate = Preset::named("accurate").unwrap();
        let e = Pipeline::new(map.clone(), stage.clone(), accurate)
            .unwrap_err()
            .to_string();
        assert!(e.contains("built with"), "{e}");
        let pipeline = Pipeline::new(map.clone(), stage, preset).unwrap();
        let q = evaluate(&index, &pipeline, &map);
        let f = &reports[0].1;
        assert!(
            q.recall["0.25m_2deg"] >= f.recall["0.25m_2deg"] - recall_drop,
            "{name} {:?} against float {:?}",
            q.recall,
            f.recall
        );
        assert!(
            q.localized_wrong <= f.localized_wrong + 1,
            "{name}: {} wrong LOCALIZED answers against float {}",
            q.localized_wrong,
            f.localized_wrong
        );
        reports.push((name, q));
    }
    // Every LOCALIZED answer carries a covariance, and it describes the position errors to within a
    // factor of two at the median (consistent: 1.54; ten times too small a covariance gives about
    // 5 and more).
    for (name, r) in &reports {
        let c = &r.covariance;
        assert_eq!(c.answers, r.localized, "{name}: {c:?}");
        assert!(
            (0.75..=3.0).contains(&c.median_mahalanobis) && c.within_99 >= 0.6,
            "{name}: {c:?}"
        );
    }
}

#[test]
fn a_noisy_depth_sensor_is_measured_and_its_far_matches_kept() {
    // Queries with a poor depth sensor's noise (0.012 z^2: 4.8 cm at 2 m, 19 cm at 4 m), dropouts
    // and lost edges against a clean map. The pipeline measures the noise on each frame and, for
    // candidates the fixed 5 cm bound cannot register, registers again with bounds grown with the
    // range: it must localize at least as many queries right as the fixed bound alone, with no
    // more wrong answers, and answer clean frames exactly as the fixed bound does.
    let dir = tempfile::tempdir().unwrap();
    let index = pntr_tests::synthetic_dataset(dir.path(), 6, 6, 41);
    let preset = Preset::named("xfeat-mnn").unwrap();
    assert_eq!(preset.depth_noise_sigmas, 3.0);
    let (map, stage) = build(&index, &preset);
    let map = Arc::new(map);
    let grown = Pipeline::new(map.clone(), stage.clone(), preset.clone()).unwrap();
    let fixed_preset = Preset {
        depth_noise_sigmas: 0.0,
        ..preset
    };
    let fixed = Pipeline::new(map.clone(), stage, fixed_preset).unwrap();
    let sensor = pntr_synth::effects::RobotEffects {
        depth_noise_per_m2: 0.012,
        ..pntr_synth::effects::RobotEffects::only(&["depth"]).unwrap()
    };
    let scenes: Vec<_> = index.scenes.iter().collect();
    let run = |pipeline: &Pipeline, noisy: bool| {
        let mut seed = 0u64;
        let mut measured = Vec::new();
        let mut registered = 0usize;
        let report = eval::run(
            &scenes,
            &EvalOptions::default(),
            &mut |q, _| {
                seed += 1;
                let mut q = q.clone();
                if noisy {
                    sensor.apply(&mut q.rgb, &mut q.depth, seed);
                }
                measured.push(pntr_pipeline::depth_noise::depth_noise_per_m2(&q.depth));
                let l = pipeline.localize(&q)?;
                registered += l.verified.len();
                Ok(Answer::of(&l, &map))
            },
            &mut |_, _| {},
        )
        .unwrap();
        eprintln!("{}", eval::table(&report));
        (report, measured, registered)
    };
    let (clean_fixed, k_clean, _) = run(&fixed, false);
    let (clean_grown, _, _) = run(&grown, false);
    assert!(k_clean.iter().all(|&k| k == 0.0), "{k_clean:?}");
    // The same answers: both or neither LOCALIZED, errors equal to a micrometre (not bit for bit:
    // the registration's clique search has a time budget, so on a loaded machine, as under the
    // parallel test runner, two runs of one frame can differ by rounding).
    assert_eq!(clean_fixed.per_query.len(), clean_grown.per_query.len());
    for (a, b) in clean_fixed.per_query.iter().zip(&clean_grown.per_query) {
        match (a.error, b.error) {
            (None, None) => {}
            (Some(a), Some(b)) => assert!(
                (a.0 - b.0).abs() < 1e-6 && (a.1 - b.1).abs() < 1e-4,
                "{a:?} vs {b:?}"
            ),
            other => panic!("clean frames answered differently: {other:?}"),
        }
    }
    let (noisy_fixed, k_noisy, registered_fixed) = run(&fixed, true);
    let (noisy_grown, _, registered_grown) = run(&grown, true);
    // Candidates the fixed bound lost to the far noise register with the grown bounds.
    assert!(
        registered_grown > registered_fixed,
        "registered candidates: {registered_grown} with grown bounds, {registered_fixed} fixed"
    );
    let mut k = k_noisy.clone();
    k.sort_by(f64::total_cmp);
    let median = k[k.len() / 2];
    assert!(
        (0.009..=0.015).contains(&median),
        "median measured noise {median} per metre for 0.012"
    );
    let right = |r: &eval::EvalReport| (r.recall["0.25m_2deg"] * r.queries as f64).round();
    assert!(
        right(&noisy_grown) >= right(&noisy_fixed),
        "grown bounds {} right, fixed {}",
        right(&noisy_grown),
        right(&noisy_fixed)
    );
    assert!(noisy_grown.localized >= noisy_fixed.localized);
    assert!(
        noisy_grown.localized_wrong <= noisy_fixed.localized_wrong,
        "{} wrong against {}",
        noisy_grown.localized_wrong,
        noisy_fixed.localized_wrong
    );
    eprintln!(
        "noisy: fixed {} right of {} ({registered_fixed} candidates registered), grown {} \
         ({registered_grown})",
        right(&noisy_fixed),
        noisy_fixed.queries,
        right(&noisy_grown)
    );
}

/// A map fits its own calibration: every region held out yields frames the rest of the map cannot
/// place (its own negatives), the fitted threshold refuses them, the calibration travels inside the
/// map file, is used by the pipeline, and a damaged one is refused when the map is read.
#[test]
fn a_map_fits_its_own_calibration_from_held_out_regions() {
    use pntr_mapping::selfcal::{self, PosedFrame, Regions};
    use pntr_pipeline::calibration::{Calibration, CalibrationSource};
    let dir = tempfile::tempdir().unwrap();
    let index = pntr_tests::synthetic_dataset(dir.path(), 8, 4, 41);
    let preset = Preset::named("xfeat-mnn").unwrap();
    let (map, _) = build(&index, &preset);
    let regions = Regions::of_map(&map).unwrap();
    assert!(regions.count() >= 2, "{} regions", regions.count());
    for r in 0..regions.count() {
        assert!((0..map.images.len()).any(|i| regions.of_image(i) == r));
        // Holding a region out keeps whole places: no place is on both sides.
        let outside = regions.outside(r);
        for (i, im) in map.images.iter().enumerate() {
            let held = regions.of_image(i) == r;
            assert_eq!(held, outside.binary_search(&i).is_err());
            let same_place = map
                .images
                .iter()
                .enumerate()
                .filter(|(_, o)| (o.scene, o.point) == (im.scene, im.point));
            for (j, _) in same_place {
                assert_eq!(regions.of_image(j), regions.of_image(i));
            }
        }
    }
    let models = pntr_tests::models();
    let stage = preset.feature_config(models).build().unwrap();
    let pipeline = Pipeline::new(Arc::new(map), stage.clone(), preset.clone()).unwrap();
    assert_eq!(pipeline.calibration().1, CalibrationSource::Shipped);
    let scenes: Vec<_> = index.scenes.iter().collect();
    let list = pntr_dataset::queries::query_list(scenes.iter().copied(), 0).unwrap();
    let mut views = pntr_dataset::queries::QueryViews::default();
    let mut frame = |i: usize| {
        let (p, qi) = &list[i];
        let v = views.view(p, *qi)?;
        Ok(Some(PosedFrame {
            query: Query {
                rgb: v.rgb,
                depth: v.depth,
                intrinsics: v.intrinsics,
            },
            world_from_camera: v.world_from_camera,
            scene: 0,
        }))
    };
    let n = list.len();
    let mut answers =
        selfcal::pass(&pipeline, &regions, n, false, &mut frame, &mut |_, _| {}).unwrap();
    let held = selfcal::pass(&pipeline, &regions, n, true, &mut frame, &mut |_, _| {}).unwrap();
    assert_eq!((answers.len(), held.len()), (n, n));
    // Against the whole map most frames are placed right; with their region held out, every
    // region contributes frames the rest of the map cannot place right: the map's own negatives.
    let right = |a: &selfcal::Answered| a.samples.candidates.iter().any(|c| c.1);
    assert!(answers.iter().filter(|a| right(a)).count() * 10 >= n * 7);
    for r in 0..regions.count() {
        let negatives = held
            .iter()
            .filter(|a| a.region == r && a.held_out && !right(a))
            .count();
        assert!(negatives > 0, "region {r} gave no negative");
    }
    answers.extend(held);
    let base = Calibration::embedded();
    let fitted = selfcal::fit(&base, &pipeline.map, &regions, &answers, "2026-12-03").unwrap();
    eprintln!("{fitted:#?}");
    assert!(fitted.calibration.threshold >= base.threshold);
    assert!(fitted.false_positives <= fitted.false_positives_base);
    // The recall cap is 1 % of both passes' frames: at most 2 % of the in-map ones.
    let cost = fitted.in_map_recall_base - fitted.in_map_recall;
    assert!(cost <= 2.0 * selfcal::MAX_RECALL_COST + 1e-9, "{cost}");
    assert_eq!(fitted.held_out_queries, n);
    assert_eq!(fitted.regions, regions.count());
    fitted.check(Path::new("x")).unwrap();

    // Stored in the map, read back, used by the pipeline.
    let mut map = Arc::try_unwrap(pipeline.map).unwrap();
    map.header.calibration = Some(fitted.clone());
    assert!(!map.calibration_is_stale());
    let path = dir.path().join("own.pntrmap");
    mapfile::save(&map, &path).unwrap();
    let back = load(&path).unwrap();
    assert_eq!(back.header.calibration.as_ref(), Some(&fitted));
    let p = Pipeline::new(Arc::new(back), stage.clone(), preset.clone()).unwrap();
    assert_eq!(p.calibration().1, CalibrationSource::Map);
    assert_eq!(p.min_confidence(), fitted.calibration.threshold);
    // `--calibration` still overrides it.
    let p = p.with_calibration(Arc::new(base.clone()), None);
    assert_eq!(p.calibration().1, CalibrationSource::File);
    assert_eq!(p.min_confidence(), base.threshold);

    // The ids a header-only reader gets say it is current.
    let ids = mapfile::read_image_ids(&path).unwrap();
    assert!(!fitted.is_stale_for(ids.iter().map(String::as_str)));
    // A map whose images changed since keeps it, stale.
    let ids: Vec<&str> = map.images[1..].iter().map(|im| im.id.as_str()).collect();
    assert!(fitted.is_stale_for(ids));

    // Damaged: a threshold changed without its checksum is refused, naming the map and why.
    let mut damaged = fitted.clone();
    damaged.calibration.threshold = 0.2;
    map.header.calibration = Some(damaged);
    let bad = dir.path().join("damaged.pntrmap");
    mapfile::save(&map, &bad).unwrap();
    let e = load(&bad).unwrap_err();
    assert!(
        e.contains("damaged.pntrmap") && e.contains("own calibration") && e.contains("checksum"),
        "{e}"
    );
    // So is one from a future version.
    let mut future = fitted.clone();
    future.version = 99;
    map.header.calibration = Some(future.sealed());
    mapfile::save(&map, &bad).unwrap();
    let e = load(&bad).unwrap_err();
    assert!(e.contains("version 99"), "{e}");
}

/// A room that looks the same turned round: every box has a twin turned by 180 degrees about the
/// room's centre, light from above; walls and furniture in horizontal stripes (the same seen from
/// either side of the turn, with texture within every few pixels). A map of six Points on a grid
/// the turn maps onto itself and four queries. Returns each query's localization and true pose.
fn symmetric_room() -> Vec<(
    pntr_pipeline::pipeline::Localization,
    nalgebra::Isometry3<f64>,
)> {
    use nalgebra::{Isometry3, Translation3, Vector3};
    use pntr_mapping::build::{MapBuilder, NewImage};
    use pntr_synth::protocol::camera_rotation;
    use pntr_synth::scene::{Scene, SceneBox};
    use pntr_synth::texture::{Material, Pattern};
    let (w, d, h) = (6.0f32, 4.0f32, 2.7f32);
    let plain = |a: [f32; 3], seed: u32| Material::new(Pattern::Plain, a, a, seed);
    // Bands along the height only: a turn about the vertical axis maps them onto themselves.
    let paint = |a: [f32; 3], seed: u32| {
        let b = a.map(|c| c * 0.55);
        let bands = Pattern::Stripes {
            period: 0.12 + 0.02 * seed as f32,
            duty: 0.5,
            vertical: false,
        };
        Material::new(bands, a, b, seed)
    };
    let materials = vec![
        paint([0.8, 0.8, 0.75], 1),
        plain([0.45, 0.35, 0.25], 2),
        plain([0.9, 0.9, 0.9], 3),
        paint([0.2, 0.3, 0.7], 4),
        paint([0.8, 0.2, 0.2], 5),
        paint([0.1, 0.6, 0.2], 6),
        paint([0.9, 0.7, 0.1], 7),
    ];
    let mut boxes = Vec::new();
    let mut add = |min: [f32; 3], max: [f32; 3], m: u16, turned: bool| {
        let b = |min: [f32; 3], max: [f32; 3]| SceneBox {
            min: Vector3::from(min),
            max: Vector3::from(max),
            faces: [m; 6],
            instance: 1,
        };
        boxes.push(b(min, max));
        if turned {
            // 180 degrees about the vertical axis through (w/2, d/2): x -> w - x, z -> d - z.
            boxes.push(b(
                [w - max[0], min[1], d - max[2]],
                [w - min[0], max[1], d - min[2]],
            ));
        }
    };
    let t = 0.1;
    add([-t, -t, -t], [w + t, 0.0, d + t], 1, false); // floor
    add([-t, h, -t], [w + t, h + t, d + t], 2, false); // ceiling
    add([-t, 0.0, -t], [w + t, h, 0.0], 0, true); // walls z = 0 and z = d
    add([-t, 0.0, 0.0], [0.0, h, d], 0, true); // walls x = 0 and x = w
    add([0.6, 0.0, 0.3], [1.6, 0.8, 1.0], 3, true); // furniture and its twin
    add([2.2, 0.0, 0.2], [2.7, 1.6, 0.6], 4, true);
    add([4.3, 0.0, 0.25], [5.6, 0.45, 0.9], 5, true);
    add([1.0, 1.2, 0.0], [2.0, 1.9, 0.04], 6, true); // pictures
    add([3.6, 1.0, 0.0], [4.4, 1.6, 0.04], 4, true);
    add([0.0, 1.1, 1.4], [0.04, 1.8, 2.3], 6, true);
    add([0.0, 0.0, 3.0], [0.5, 1.0, 3.5], 3, true);
    let scene = Scene {
        name: "turned".into(),
        boxes,
        materials,
        instance_categories: vec![0, 1],
        rooms: Vec::new(),
        ceiling_m: h,
        width_m: w,
        depth_m: d,
        lights: [Vector3::y(), Vector3::y()],
    };
    let renderer = pntr_synth::Renderer::new(&scene);
    let k = pntr_core::Intrinsics::hpointloc();
    let pose = |x: f64, z: f64, yaw_deg: f64| {
        Isometry3::from_parts(
            Translation3::new(x, 1.2, z),
            camera_rotation(yaw_deg.to_radians(), 0.0, 0.0),
        )
    };
    // Points on a grid that the turn maps onto itself, six directions each.
    let preset = Preset::named("xfeat-mnn").unwrap();
    let models = pntr_tests::models();
    let stage = preset.map_feature_config(models.clone()).build().unwrap();
    let mut builder = MapBuilder::new(&preset, &stage).unwrap();
    let grid = [
        (1.5, 1.3),
        (3.0, 1.3),
        (4.5, 1.3),
        (1.5, 2.7),
        (3.0, 2.7),
        (4.5, 2.7),
    ];
    for (point, (x, z)) in (0u32..).zip(grid) {
        for yaw in (0..6).map(|i| 60.0 * i as f64 + 15.0) {
            let p = pose(x, z, yaw);
            let f = renderer.render(&p, &k, point as u64 * 10 + (yaw as u64));
            builder
                .add(NewImage {
                    id: format!("turned/point{point}/yaw{yaw}"),
                    scene: 0,
                    point,
                    world_from_camera: p,
                    stamp: None,
                    rgb: &f.rgb,
                    depth: &f.depth,
                    labels: Some(&f.labels),
                    camera: k,
                })
                .unwrap();
        }
    }
    let map = builder
        .finish(
            "turned",
            vec!["turned".into()],
            pntr_core::CameraAxes::Habitat,
            "y",
            &models,
        )
        .unwrap();
    let stage = preset.feature_config(models).build().unwrap();
    let pipeline = Pipeline::new(Arc::new(map), stage, preset).unwrap();
    let queries = [
        (2.1, 1.7, 20.0),
        (2.4, 1.6, 170.0),
        (3.6, 2.2, 80.0),
        (2.0, 2.0, 250.0),
    ];
    queries
        .iter()
        .enumerate()
        .map(|(i, &(x, z, yaw))| {
            let truth = pose(x, z, yaw);
            let f = renderer.render(&truth, &k, 1000 + i as u64);
            let l = pipeline
                .localize(&Query {
                    rgb: f.rgb,
                    depth: f.depth,
                    intrinsics: k,
                })
                .unwrap();
            eprintln!(
                "query {i}: {:?} {:.3} {:?}",
                l.status, l.confidence, l.reason
            );
            (l, truth)
        })
        .collect()
}

/// LOCALIZED answers more than (1 m, 10 deg) from their true poses, and the NOT_LOCALIZED ones
/// whose reason contains every one of `words`.
fn wrong_and_refused_for(
    answers: &[(
        pntr_pipeline::pipeline::Localization,
        nalgebra::Isometry3<f64>,
    )],
    words: &[&str],
) -> (usize, usize, usize) {
    let (mut wrong, mut refused, mut named) = (0, 0, 0);
    for (l, truth) in answers {
        if l.status == Status::Localized {
            let (dt, dr) = eval::pose_error(&l.pose.unwrap(), truth, false);
            wrong += (dt > 1.0 || dr > 10.0) as usize;
            continue;
        }
        refused += 1;
        named += l
            .reason
            .as_deref()
            .is_some_and(|r| words.iter().all(|w| r.contains(w))) as usize;
    }
    (wrong, refused, named)
}

/// A room that looks the same turned round, striped: a query in it verifies at its true pose and at
/// the turned one, so it is answered NOT_LOCALIZED, and the reason names the turned pose (issue 41).
#[test]
fn a_room_that_looks_alike_turned_round_is_refused_naming_it() {
    let answers = symmetric_room();
    let (wrong, refused, named) =
        wrong_and_refused_for(&answers, &["turned by", "looks alike turned round"]);
    // No confident answer at the twin's pose, and the room's symmetry is named.
    assert_eq!(wrong, 0);
    assert!(refused >= 2, "{refused} of {} refused", answers.len());
    assert!(named >= 1, "{named} refusals name the turned pose");
}
