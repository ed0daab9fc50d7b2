//! A robot's drive end to end: `pntr synth --trajectory-seconds` writes a TUM RGB-D sequence beside
//! the dataset, `pntr build-db` maps the dataset, and `pntr replay` streams the drive through a real
//! `pntr-server` (in this process, 127.0.0.1, ephemeral port), with tracking and without, and again
//! from a ROS 2 bag (MCAP) the test writes from the same frames.

use std::path::Path;

mod support;

use pntr_service::config::Settings;
use support::{
    build_db, ok, pntr, read_json, replay, runtime, serve, stop, synth, tum_pose, tum_rows, MODELS,
};

/// `replay --record` of 50 frames, read back with the `mcap` Python reader: every channel with its
/// Foxglove schema and the expected count, and answers that agree with the replay's report.
fn check_recording(path: &Path, report: &serde_json::Value) {
    assert!(!path.with_extension("mcap.partial").exists());
    let m = support::read_mcap(path, "/pntr/answer");
    let topics = &m["topics"];
    let localized = (report["localized_share"].as_f64().unwrap() * 50.0).round() as u64;
    for (topic, schema, count) in [
        ("/pntr/camera/image", "foxglove.CompressedImage", 50),
        ("/pntr/camera/calibration", "foxglove.CameraCalibration", 50),
        ("/pntr/ground_truth", "foxglove.PoseInFrame", 50),
        ("/pntr/answer", "pntr.Answer", 50),
        ("/pntr/pose", "foxglove.PoseInFrame", localized),
        ("/tf", "foxglove.FrameTransforms", localized),
        ("/pntr/map/cameras", "foxglove.PosesInFrame", 1),
    ] {
        let t = &topics[topic];
        assert_eq!(t["schema"], schema, "{topic}: {m:#}");
        assert_eq!(t["count"], count, "{topic}: {t}");
        let encoding = if schema.starts_with("foxglove.") {
            "protobuf"
        } else {
            "json"
        };
        assert_eq!(t["message_encoding"], encoding, "{topic}: {t}");
    }
    // The answers: status as the report counts it, poses in ROS conventions (z up: the y-up scene's
    // camera height, about 1.25 m, is the ROS z) and near the ground truth.
    let answers = m["json"].as_array().unwrap();
    let mut errors = Vec::new();
    for a in answers {
        // Which version of the map answered (a live replace or extend changes it).
        assert!(
            a["map_version"].as_str().is_some_and(|v| !v.is_empty()),
            "{a}"
        );
        if a["status"] == "LOCALIZED" {
            let z = a["pose"]["position"][2].as_f64().unwrap();
            assert!((0.5..2.0).contains(&z), "camera height on ROS z: {a}");
            assert_eq!(a["covariance"].as_array().map(Vec::len), Some(36), "{a}");
            errors.push(a["truth_error_m"].as_f64().unwrap());
        } else {
            assert!(!a["reason"].as_str().unwrap().is_empty(), "{a}");
        }
    }
    assert_eq!(errors.len() as u64, localized);
    errors.sort_by(f64::total_cmp);
    assert!(errors[errors.len() / 2] < 0.25, "median error {errors:?}");
}

#[test]
fn a_synthetic_drive_replays_through_the_stream_with_and_without_tracking() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().to_str().unwrap();
    let drive = ["--seed", "21", "--trajectory-seconds", "5", "--json"];
    let out = synth(dir.path(), "6", "1", &drive);
    let summary: serde_json::Value = serde_json::from_str(&out).unwrap();
    assert_eq!(summary["scenes"][0]["sequence_frames"], 50, "{summary}");
    // The TUM layout: 16-bit depth at 5000 per metre, ground truth of every frame, the camera.
    let seq = dir.path().join("sequences/synth000");
    let gt = tum_rows(&seq.join("groundtruth.txt"));
    assert_eq!(gt.len(), 50);
    assert!(gt.iter().all(|l| l.len() == 8));
    assert!((gt[1][0] - gt[0][0] - 0.1).abs() < 1e-6, "10 Hz");
    // The TUM convention: optical camera axes, so the image's "down" (camera +y) is the scene's
    // down (world -y, the scene being y-up) and the camera looks level (camera +z horizontal).
    for g in &gt {
        let q = tum_pose(g).rotation;
        let down = q * nalgebra::Vector3::y();
        let forward = q * nalgebra::Vector3::z();
        assert!(down.y < -0.99 && forward.y.abs() < 0.1, "{g:?}");
    }
    let speed = ((gt[49][1] - gt[48][1]).powi(2) + (gt[49][3] - gt[48][3]).powi(2)).sqrt() / 0.1;
    assert!(speed <= 0.5 + 1e-6, "{speed} m/s");
    let calib = &tum_rows(&seq.join("calibration.txt"))[0];
    assert_eq!(calib.len(), 4, "fx fy cx cy");
    for (v, want) in calib.iter().zip([128.0, 128.0, 127.5, 127.5]) {
        assert!((v - want).abs() < 1e-9, "{calib:?}");
    }
    let depth = image::open(seq.join("depth/0.000000.png")).unwrap();
    assert!(matches!(depth, image::DynamicImage::ImageLuma16(_)));
    let rgb_list = std::fs::read_to_string(seq.join("rgb.txt")).unwrap();
    assert!(rgb_list.contains("0.100000 rgb/0.100000.png"), "{rgb_list}");

    let map = dir.path().join("m.pntrmap");
    build_db(&map, &["--dataset", root]);
    let rt = runtime();
    let [server] = serve(&rt, [Settings::local(vec![map.clone()], MODELS.into())]);
    let addr = server.addr.to_string();
    // `pntr localize` with a frame of the TUM folder: its 16-bit depth is 5000 per metre, not
    // millimetres, and is read so (said on stderr); the frames localize.
    let mut localized_frames = 0;
    for stamp in ["0.100000", "0.200000", "0.300000"] {
        let out = pntr(&[
            "localize",
            "--addr",
            &server.addr.to_string(),
            "--rgb",
            seq.join(format!("rgb/{stamp}.png")).to_str().unwrap(),
            "--depth",
            seq.join(format!("depth/{stamp}.png")).to_str().unwrap(),
            "--json",
        ]);
        let v: serde_json::Value = serde_json::from_str(&ok(&out)).unwrap();
        assert!(String::from_utf8_lossy(&out.stderr).contains("5000 units per metre"));
        localized_frames += (v["status"] == "LOCALIZED") as usize;
    }
    assert!(
        localized_frames >= 2,
        "{localized_frames} of 3 TUM frames localized"
    );
    let mut reports = Vec::new();
    for (name, extra) in [("tracking", None), ("global", Some("--no-prior"))] {
        let traj = dir.path().join(format!("{name}.txt"));
        let report = dir.path().join(format!("{name}.json"));
        let plots = dir.path().join(format!("{name}-plots"));
        let recording = dir.path().join(format!("{name}.mcap"));
        let mut args = vec!["--rate", "50", "--plot", plots.to_str().unwrap()];
        args.extend(extra);
        if name == "tracking" {
            args.extend([
                "--record",
                recording.to_str().unwrap(),
                "--db",
                map.to_str().unwrap(),
            ]);
        }
        let printed = ok(&replay(&addr, &seq, &traj, &report, &args));
        assert!(
            printed.contains("50 frames") && printed.contains("ATE"),
            "{printed}"
        );
        let r = read_json(&report);
        for k in [
            "frames",
            "localized_share",
            "tracking_share",
            "ate_rmse_m",
            "rpe_trans_rmse_m",
            "rpe_rot_rmse_deg",
            "fps",
            "latency_ms",
            "stage_ms",
        ] {
            assert!(!r[k].is_null(), "{k} missing: {r}");
        }
        for p in ["p50", "p90", "p99"] {
            assert!(r["latency_ms"][p].as_f64().unwrap() > 0.0, "{r}");
        }
        assert_eq!(r["frames"], 50);
        // The estimated trajectory: LOCALIZED frames only, TUM order, near the ground truth.
        let est = tum_rows(&traj);
        let localized = r["localized_share"].as_f64().unwrap();
        assert_eq!(est.len(), (localized * 50.0).round() as usize, "{r}");
        assert!(localized >= 0.5, "{name}: {r}");
        // Every estimate is at a frame's time, and the JSON's errors agree with the trajectory file.
        // Tracking precision on drives is measured in BENCHMARKS.md (a look-alike can still fool it;
        // the tracking region depends on the time between frames, so one short drive on a loaded
        // machine is not a stable place to assert it).
        let mut over_1m = 0;
        for e in &est {
            let g = gt
                .iter()
                .find(|g| (g[0] - e[0]).abs() < 1e-6)
                .expect("a ground-truth time");
            let d = ((e[1] - g[1]).powi(2) + (e[2] - g[2]).powi(2) + (e[3] - g[3]).powi(2)).sqrt();
            over_1m += (d > 1.0) as u64;
        }
        assert_eq!(r["frames_over_1m"].as_u64().unwrap(), over_1m, "{r}");
        assert!(r["ate_rmse_m"].as_f64().unwrap() < 1.0, "{name}: {r}");
        if name == "tracking" {
            check_recording(&recording, &r);
        }
        support::assert_picture(
            &plots,
            "trajectory",
            (900, 900),
            &[
                "ground truth",
                "LOCALIZED answers",
                "map images (database cameras)",
            ],
        );
        reports.push(r);
    }
    // Tracking answers most frames through the stream's state; --no-prior none.
    assert!(
        reports[0]["tracking_share"].as_f64().unwrap() >= 0.4,
        "{}",
        reports[0]
    );
    assert_eq!(reports[1]["tracking_share"], 0.0);
    assert_eq!(reports[1]["modes"]["GLOBAL"], 50);

    // The same drive as a ROS 2 bag (MCAP; colour rgb8, depth 16UC1 millimetres, camera info,
    // ground truth as PoseStamped), written here and replayed the same way.
    let tum = pntr_dataset::tum::TumSequence::open(&seq).unwrap();
    let loaded: Vec<_> = (0..20).map(|i| tum.load(i).unwrap()).collect();
    let frames: Vec<pntr_dataset::bag::BagFrame<'_>> = loaded
        .iter()
        .enumerate()
        .map(|(i, (rgb, depth))| {
            (
                100.0 + tum.frames[i].timestamp,
                rgb,
                depth,
                tum.frames[i].world_from_camera,
            )
        })
        .collect();
    let topics = pntr_dataset::bag::Topics {
        pose: Some("/ground_truth".into()),
        ..Default::default()
    };
    let bag = dir.path().join("drive.mcap");
    pntr_dataset::bag::write_bag(&bag, &frames, &tum.intrinsics.unwrap(), &topics).unwrap();
    let report = dir.path().join("bag.json");
    let printed = ok(&replay(
        &addr,
        &bag,
        &dir.path().join("bag.txt"),
        &report,
        &["--pose-topic", "/ground_truth", "--rate", "50"],
    ));
    assert!(printed.contains("20 frames"), "{printed}");
    let r = read_json(&report);
    // The bag's frames, ground truth and camera arrive (depth is in whole millimetres here, so the
    // answers are not bit-identical to the TUM replay's; tracking precision is measured in
    // BENCHMARKS.md, not asserted on one short drive).
    assert!(r["localized_share"].as_f64().unwrap() >= 0.5, "{r}");
    assert_eq!(r["stamps_sent"], true, "{r}");
    assert!(r["frames_with_ground_truth"].as_u64().unwrap() >= 10, "{r}");
    assert!(r["ate_rmse_m"].as_f64().unwrap() < 1.0, "{r}");
    // A topic the bag lacks is named beside the topics it has.
    let (x_txt, x_json) = (dir.path().join("x.txt"), dir.path().join("x.json"));
    let wrong = replay(&addr, &bag, &x_txt, &x_json, &["--rgb-topic", "/rgb"]);
    assert!(!wrong.status.success());
    let err = String::from_utf8_lossy(&wrong.stderr);
    assert!(
        err.contains("/rgb") && err.contains("/camera/color/image_raw"),
        "{err}"
    );

    // A folder that is not a sequence is named with what was expected.
    let bad = replay(&addr, dir.path(), &x_txt, &x_json, &[]);
    assert!(!bad.status.success());
    let err = String::from_utf8_lossy(&bad.stderr);
    assert!(err.contains("rgb.txt"), "{err}");

    // A recording stamped in milliseconds: its stamps cannot be sent as capture times, and replay
    // says so before sending anything, naming `--no-stamps`, with which it replays.
    let ms = dir.path().join("ms");
    std::fs::create_dir_all(&ms).unwrap();
    for sub in ["rgb", "depth"] {
        std::os::unix::fs::symlink(seq.join(sub), ms.join(sub)).unwrap();
    }
    std::fs::copy(seq.join("calibration.txt"), ms.join("calibration.txt")).unwrap();
    for list in ["rgb.txt", "depth.txt", "groundtruth.txt"] {
        let text = std::fs::read_to_string(seq.join(list)).unwrap();
        let scaled: Vec<String> = text
            .lines()
            .map(|l| match l.split_once(' ') {
                Some((t, rest)) if !l.starts_with('#') => {
                    format!("{:.3} {rest}", t.parse::<f64>().unwrap() * 1000.0 + 1.7e12)
                }
                _ => l.to_string(),
            })
            .collect();
        std::fs::write(ms.join(list), scaled.join("\n") + "\n").unwrap();
    }
    let refused = replay(&addr, &ms, &x_txt, &x_json, &["--frames", "3"]);
    assert!(!refused.status.success());
    let err = String::from_utf8_lossy(&refused.stderr);
    assert!(err.contains("--no-stamps"), "{err}");
    let taken = replay(
        &addr,
        &ms,
        &x_txt,
        &x_json,
        &["--frames", "3", "--no-stamps", "--rate", "20"],
    );
    assert!(
        taken.status.success(),
        "{}",
        String::from_utf8_lossy(&taken.stderr)
    );
    assert_eq!(read_json(&x_json)["stamps_sent"], false);

    // The files are optional: without --trajectory and --json replay prints its summary and, the
    // drive having ground truth, the recalls; the frames log numbers each frame in the drive's
    // order (a new user had to work it out from the stamps).
    let log = dir.path().join("frames.jsonl");
    let printed = ok(&pntr(&[
        "replay",
        "--addr",
        &addr,
        "--sequence",
        seq.to_str().unwrap(),
        "--frames",
        "3",
        "--rate",
        "20",
        "--frames-log",
        log.to_str().unwrap(),
    ]));
    assert!(
        printed.contains("3 frames") && printed.contains("recall (5 cm, 5 deg) "),
        "{printed}"
    );
    let numbered: Vec<u64> = std::fs::read_to_string(&log)
        .unwrap()
        .lines()
        .map(|l| {
            serde_json::from_str::<serde_json::Value>(l).unwrap()["frame"]
                .as_u64()
                .unwrap()
        })
        .collect();
    assert_eq!(numbered, [0, 1, 2]);

    // A full disk under `--record` and `--record-bag`: one error line each, naming the file and
    // the cause, not a warning per message; the replay's report still written; nothing half
    // written left behind. The disk fills here by a file-size limit (`ulimit -f`, the signal it
    // raises ignored, so writes fail with EFBIG as they would with ENOSPC on a full disk): the
    // recordings pass it within a few frames, the report and trajectory stay below it.
    let (full_mcap, full_bag) = (dir.path().join("full.mcap"), dir.path().join("full-bag"));
    let (full_txt, full_json) = (dir.path().join("full.txt"), dir.path().join("full.json"));
    let out = std::process::Command::new("sh")
        .arg("-c")
        .arg("trap '' XFSZ; ulimit -f 400 && exec \"$0\" \"$@\"")
        .arg(env!("CARGO_BIN_EXE_pntr"))
        .args([
            "replay",
            "--addr",
            &addr,
            "--sequence",
            seq.to_str().unwrap(),
        ])
        .args(["--trajectory", full_txt.to_str().unwrap()])
        .args(["--json", full_json.to_str().unwrap(), "--rate", "50"])
        .args(["--record", full_mcap.to_str().unwrap()])
        .args(["--record-bag", full_bag.to_str().unwrap()])
        .env_remove("PNTR_TOKEN")
        .output()
        .unwrap();
    let err = support::fails_cleanly(&out);
    let lines: Vec<&str> = err.lines().filter(|l| l.starts_with("error:")).collect();
    assert!(
        lines.iter().any(|l| l.contains("--record ")
            && l.contains("full.mcap")
            && l.contains("File too large")),
        "{err}"
    );
    assert!(
        lines.iter().any(|l| l.contains("--record-bag ")
            && l.contains("full-bag")
            && l.contains("File too large")),
        "{err}"
    );
    assert!(
        !err.contains("WARN") && !err.contains("attempted another write"),
        "one error per recording, not one per message: {err}"
    );
    let r = read_json(&full_json);
    assert_eq!(r["frames"], 50, "{r}");
    assert_eq!(r["record_errors"].as_array().map(Vec::len), Some(2), "{r}");
    assert_eq!(
        tum_rows(&full_txt).len(),
        (r["localized_share"].as_f64().unwrap() * 50.0).round() as usize
    );
    let left: Vec<_> = std::fs::read_dir(dir.path())
        .unwrap()
        .filter_map(|e| e.ok())
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .filter(|n| n.contains("full") && !n.starts_with("full.txt") && n != "full.json")
        .collect();
    assert!(
        left.is_empty(),
        "half-written recordings left behind: {left:?}"
    );
    stop(&rt, [server]);
}
