//! Maps from a robot's own recordings, end to end through the `pntr` binary: `pntr synth
//! --mapping-run` renders the drive an operator makes (a TUM folder, optical axes), `pntr build-db
//! --sequence` maps it from its keyframes and checks the frames between them, `pntr info --images`
//! lists the map's images with their stamps and poses, and `pntr eval` localizes the scene's
//! HPointLoc queries (Habitat axes) against the recording's map (optical axes).

mod support;

use std::path::Path;

use nalgebra::{UnitQuaternion, Vector3};
use support::{
    build_db, build_db_refused, eval, json_pose, map_info, mapping_drive, ok, read_json, tum_pose,
    tum_rows, MODELS,
};

/// groundtruth.txt rows: (stamp, translation, rotation).
fn trajectory(path: &Path) -> Vec<(f64, Vector3<f64>, UnitQuaternion<f64>)> {
    tum_rows(path)
        .iter()
        .map(|v| {
            let pose = tum_pose(v);
            (v[0], pose.translation.vector, pose.rotation)
        })
        .collect()
}

#[test]
fn a_mapping_drive_builds_a_map_that_localizes_the_scene_and_its_own_frames() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().join("data");
    let seq = mapping_drive(&root, ("5", "6"), "31", "300", &[]);
    let gt = trajectory(&seq.join("groundtruth.txt"));
    // A mapping run stops after its last Point: well under the 300 s cap.
    assert!(gt.len() > 200 && gt.len() < 3000, "{} frames", gt.len());

    let map = dir.path().join("drive.pntrmap");
    let plots = dir.path().join("plots");
    let out = build_db(
        &map,
        &[
            "--sequence",
            seq.to_str().unwrap(),
            "--map-id",
            "lab",
            "--plot",
            plots.to_str().unwrap(),
            "--json",
        ],
    );
    let s: serde_json::Value = serde_json::from_str(&out).unwrap();
    let images = s["images"].as_u64().unwrap() as usize;
    assert_eq!(s["frames"].as_u64().unwrap() as usize, gt.len(), "{s}");
    assert!(
        images >= 20 && images * 3 < gt.len(),
        "{images} keyframes of {}: {s}",
        gt.len()
    );
    assert!(s["skipped"]["covered"].as_u64().unwrap() > 0, "{s}");
    // Right poses never look contradicted by their images.
    assert!(s["skipped"]["pose_disagrees"].is_null(), "{s}");
    assert_eq!(s["map_id"], "lab");
    assert_eq!(s["camera_axes"], "opencv");
    // The drive's world is y-up, read from the cameras' own "down" axes.
    assert_eq!(s["up_axis"], "y");
    assert_eq!(s["up_axis_inferred"], true);
    for stage in ["read", "select", "describe", "index", "check", "write"] {
        assert!(
            s["stage_seconds"][stage].as_f64().unwrap() >= 0.0,
            "{stage}: {s}"
        );
    }
    let c = &s["check"];
    assert!(c["frames"].as_u64().unwrap() >= 100, "{s}");
    assert!(c["localized_share"].as_f64().unwrap() >= 0.9, "{s}");
    assert!(c["ate_rmse_m"].as_f64().unwrap() <= 0.05, "{s}");
    assert_eq!(c["frames_over_1m"], 0, "{s}");
    assert!(plots.join("map_check.png").is_file());

    // Every map image with its stamp and pose: the recording's own pose at that stamp.
    let info = map_info(&map, &["--images"]);
    assert_eq!(info["camera_axes"], "opencv");
    let list = info["image_list"].as_array().unwrap();
    assert_eq!(list.len(), images);
    let mut places = std::collections::BTreeSet::new();
    for im in list {
        let stamp = im["stamp"].as_f64().expect("a stamp");
        let (_, t, q) = gt
            .iter()
            .find(|g| (g.0 - stamp).abs() < 1e-6)
            .expect("a recorded frame");
        let pose = json_pose(&im["translation"], &im["rotation_wxyz"]);
        assert!((pose.translation.vector - t).norm() < 1e-5, "{im}");
        assert!(pose.rotation.angle_to(q) < 1e-5, "{im}");
        assert!(im["rotation_wxyz"][0].as_f64().unwrap() >= 0.0);
        places.insert(im["place"].as_u64().unwrap());
    }
    assert!(places.len() >= 5, "{places:?}");

    // The scene's HPointLoc queries (Habitat axes) against the drive's map (optical axes).
    let report = dir.path().join("eval.json");
    let eval_plots = dir.path().join("eval_plots");
    ok(&eval(
        &root,
        &map,
        &[
            "--json",
            report.to_str().unwrap(),
            "--plot",
            eval_plots.to_str().unwrap(),
        ],
    ));
    // The drive's keyframes are drawn with the scene's queries, on one picture.
    let pictures: Vec<String> = std::fs::read_dir(&eval_plots)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with("map_") && n.ends_with(".png"))
        .collect();
    assert_eq!(pictures, ["map_synth000.png"], "{pictures:?}");
    let r = read_json(&report);
    let recall = r["recall"]["0.25m_2deg"].as_f64().unwrap();
    assert!(recall >= 0.8, "recall {recall}: {r}");
    // The retrieval row comes from the map images' own poses; the Point rows do not apply.
    assert!(r["retrieval_only"]["5m"].as_f64().unwrap() >= 0.8, "{r}");
    assert!(r["retrieval"]["point_at_1"].is_null(), "{r}");

    // A SLAM trajectory at a fifth of the camera's rate, interpolated at each frame's stamp.
    let slam = dir.path().join("slam.txt");
    let text: String = std::fs::read_to_string(seq.join("groundtruth.txt"))
        .unwrap()
        .lines()
        .filter(|l| !l.starts_with('#'))
        .step_by(5)
        .map(|l| format!("{l}\n"))
        .collect();
    std::fs::write(&slam, text).unwrap();
    let map2 = dir.path().join("slam.pntrmap");
    let (seq_s, slam_s) = (seq.to_str().unwrap(), slam.to_str().unwrap());
    let check = ["--check-sequence", seq_s, "--check-frames", "30"];
    let from_slam = ["--sequence", seq_s, "--trajectory", slam_s, "--json"];
    let out = build_db(&map2, &[&from_slam[..], &check].concat());
    let s2: serde_json::Value = serde_json::from_str(&out).unwrap();
    assert_eq!(s2["check"]["kind"], "another recording", "{s2}");
    assert_eq!(s2["check"]["frames"], 30, "{s2}");
    assert!(
        s2["check"]["localized_share"].as_f64().unwrap() >= 0.9,
        "{s2}"
    );
    // The drive the map was built from lies inside what the map covers.
    assert!(
        s2["check"]["frames_outside_map"].as_u64().unwrap() <= 3,
        "{s2}"
    );
    let n2 = s2["images"].as_u64().unwrap() as usize;
    assert!(
        n2 * 10 >= images * 9 && n2 * 10 <= images * 11,
        "{n2} vs {images}"
    );

    // Pose sources that fail while the camera records on, found from the images themselves (no
    // check, no self-calibration): a stalled publisher repeating one pose for 4 s, and a
    // motion-capture dropout putting three frames 5 m off. Their frames are left out, named in a
    // warning, and every map image stays where it was taken.
    let rows: Vec<String> = std::fs::read_to_string(seq.join("groundtruth.txt"))
        .unwrap()
        .lines()
        .filter(|l| !l.starts_with('#') && !l.trim().is_empty())
        .map(String::from)
        .collect();
    let faulty = |name: &str, edit: &dyn Fn(usize, &mut Vec<String>)| {
        let mut out = Vec::new();
        for (k, row) in rows.iter().enumerate() {
            let mut v: Vec<String> = row.split_whitespace().map(String::from).collect();
            edit(k, &mut v);
            out.push(v.join(" "));
        }
        let path = dir.path().join(format!("{name}.txt"));
        std::fs::write(&path, out.join("\n") + "\n").unwrap();
        path
    };
    let stall_from = rows.len() / 3;
    let stalled: Vec<String> = rows[stall_from]
        .split_whitespace()
        .map(String::from)
        .collect();
    let frozen = faulty("frozen", &|k, v| {
        if (stall_from..stall_from + 40).contains(&k) {
            v[1..].clone_from_slice(&stalled[1..]);
        }
    });
    let jump_at = 2 * rows.len() / 3;
    let jumped = faulty("jumped", &|k, v| {
        if (jump_at..jump_at + 3).contains(&k) {
            let x: f64 = v[1].parse().unwrap();
            v[1] = format!("{}", x + 5.0);
        }
    });
    for (name, trajectory, at_least) in [("frozen", &frozen, 10), ("jumped", &jumped, 3)] {
        let out_map = dir.path().join(format!("{name}.pntrmap"));
        let args = [
            "--sequence",
            seq_s,
            "--trajectory",
            trajectory.to_str().unwrap(),
            "--no-check",
            "--no-self-calibration",
            "--json",
        ];
        let r: serde_json::Value = serde_json::from_str(&build_db(&out_map, &args)).unwrap();
        let left_out = r["skipped"]["pose_disagrees"].as_u64().unwrap_or(0);
        assert!(left_out >= at_least, "{name}: {left_out} left out: {r}");
        assert!(
            r["warnings"]
                .to_string()
                .contains("disagree with their own images"),
            "{name}: {r}"
        );
        for im in map_info(&out_map, &["--images"])["image_list"]
            .as_array()
            .unwrap()
        {
            let stamp = im["stamp"].as_f64().unwrap();
            let (_, t, _) = gt.iter().find(|g| (g.0 - stamp).abs() < 1e-6).unwrap();
            let pose = json_pose(&im["translation"], &im["rotation_wxyz"]);
            let off = (pose.translation.vector - t).norm();
            assert!(
                off < 0.25,
                "{name}: a map image {off:.2} m from where it was taken: {im}"
            );
        }
    }

    // Depth in the wrong unit is named, with the flag that fixes it; so is a missing trajectory
    // and a mismatch of trajectories and sequences.
    let x = dir.path().join("x.pntrmap");
    let refused = |extra: &[&str]| build_db_refused(&seq, &x, extra);
    let e = refused(&["--depth-scale", "5", "--models", MODELS]);
    assert!(
        e.contains("--depth-scale") && e.contains("finer units"),
        "{e}"
    );
    std::fs::remove_file(seq.join("groundtruth.txt")).unwrap();
    let e = refused(&["--models", MODELS]);
    assert!(
        e.contains("no frame has a pose") && e.contains("--trajectory"),
        "{e}"
    );
    let e = refused(&["--trajectory", slam_s, "--trajectory", slam_s]);
    assert!(e.contains("one per sequence"), "{e}");
    assert!(!x.exists());
}

#[test]
fn a_distorted_camera_is_undistorted_as_its_frames_are_read() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().join("data");
    let lens = [
        "--query-camera",
        "320x240",
        "--query-distortion=-0.2,0.05,0,0,0",
    ];
    let seq = mapping_drive(&root, ("4", "4"), "33", "120", &lens);
    let calib = std::fs::read_to_string(seq.join("calibration.txt")).unwrap();
    assert_eq!(calib.split_whitespace().count(), 9, "{calib}");
    let map = dir.path().join("lens.pntrmap");
    // About undistortion: the shipped calibration will do.
    let out = build_db(
        &map,
        &[
            "--sequence",
            seq.to_str().unwrap(),
            "--no-self-calibration",
            "--json",
        ],
    );
    let s: serde_json::Value = serde_json::from_str(&out).unwrap();
    assert!(
        s["check"]["localized_share"].as_f64().unwrap() >= 0.9,
        "{s}"
    );
    assert!(s["check"]["ate_rmse_m"].as_f64().unwrap() <= 0.05, "{s}");
    // The map holds rectified images: its camera has no distortion.
    let info = map_info(&map, &[]);
    let d: Vec<f64> = serde_json::from_value(info["intrinsics"]["distortion"].clone()).unwrap();
    assert!(d.iter().all(|v| *v == 0.0), "{info}");
}
