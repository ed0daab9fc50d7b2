//! Maps and drives from ROS 2 bags written by another tool than pntr: `scripts/tum_to_rosbag2.py`
//! turns a `pntr synth --mapping-run` drive into rosbag2 folders with the Python `rosbags` package
//! (split MCAP files, `CompressedImage` PNG or JPEG colour, `compressedDepth` millimetres, poses only in
//! TF: `/tf_static` base_link -> camera_link -> optical frame and `/tf` map -> odom -> base_link, or a
//! PoseStamped topic), and `pntr build-db --sequence BAG_DIR` and `pntr replay` read them.

mod support;

use std::collections::BTreeMap;
use std::path::Path;
use std::process::Command;

use pntr_service::config::Settings;
use support::{
    build_db, build_db_refused, err, eval, map_images, mapping_drive, ok, read_json, replay,
    repo_root, runtime, serve, stop, tum_rows, MODELS,
};

/// The drive as a bag in the TUM folder's own frame and stamps (`--keep-tum-frame`), so its map
/// compares pose for pose with the folder's.
fn to_bag(seq: &Path, out: &Path, extra: &[&str]) {
    to_robot_bag(seq, out, &[extra, &["--keep-tum-frame"]].concat());
}

/// The drive as a robot would record it (the script's default): a z-up `map` (REP 103) and
/// wall-clock stamps. Returns the script's stderr (what it converted).
fn to_robot_bag(seq: &Path, out: &Path, extra: &[&str]) -> String {
    // `$PNTR_PYTHON` or set-up's venv, which has `rosbags`.
    let o = Command::new(support::python_importing("rosbags, numpy, PIL"))
        .arg(repo_root().join("scripts/tum_to_rosbag2.py"))
        .arg(seq)
        .arg(out)
        .args(extra)
        .output()
        .unwrap();
    ok(&o);
    String::from_utf8_lossy(&o.stderr).into_owned()
}

/// The converter's own checks (a TUM folder it writes, converted three ways and in the robot's
/// frame, read back with `rosbags`): TF chains equal to the ground truth, split files, encodings,
/// and a y-up render's world turned z-up with base_link upright and wall-clock stamps.
#[test]
fn the_stand_in_bag_converter_passes_its_self_test() {
    let o = Command::new(support::python_importing("rosbags, numpy, PIL"))
        .arg(repo_root().join("scripts/tum_to_rosbag2.py"))
        .arg("--selftest")
        .output()
        .unwrap();
    let out = ok(&o);
    assert!(
        out.contains("selftest passed") && out.contains("base_link upright"),
        "{out}"
    );
}

/// A map's images by stamp (ms): (translation, rotation w x y z).
type Images = BTreeMap<i64, (Vec<f64>, Vec<f64>)>;

/// Build a map (no check, the shipped calibration: this file is about reading bags) and list its
/// images: stamp -> (translation, rotation w x y z).
fn build(seq: &Path, map: &Path, extra: &[&str]) -> (serde_json::Value, Images) {
    let source = [
        "--sequence",
        seq.to_str().unwrap(),
        "--no-check",
        "--no-self-calibration",
        "--json",
    ];
    let s: serde_json::Value =
        serde_json::from_str(&build_db(map, &[&source[..], extra].concat())).unwrap();
    let images = map_images(map)
        .iter()
        .map(|im| {
            (
                (im["stamp"].as_f64().unwrap() * 1e3).round() as i64,
                (
                    serde_json::from_value(im["translation"].clone()).unwrap(),
                    serde_json::from_value(im["rotation_wxyz"].clone()).unwrap(),
                ),
            )
        })
        .collect();
    (s, images)
}

fn recall(dataset: &Path, map: &Path) -> f64 {
    let report = map.with_extension("eval.json");
    ok(&eval(dataset, map, &["--json", report.to_str().unwrap()]));
    read_json(&report)["recall"]["0.25m_2deg"].as_f64().unwrap()
}

#[test]
fn rosbag2_folders_with_compressed_images_and_tf_build_the_same_map_as_the_tum_folder() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let seq = mapping_drive(&data, ("5", "6"), "31", "300", &[]);
    let (tum, tum_images) = build(&seq, &dir.path().join("tum.pntrmap"), &[]);

    // PNG colour, compressedDepth, poses only in TF (interpolation not needed), split files.
    let png = dir.path().join("bag_png");
    to_bag(
        &seq,
        &png,
        &["--colour", "png", "--max-messages-per-file", "700"],
    );
    let files = std::fs::read_dir(&png)
        .unwrap()
        .filter(|e| {
            e.as_ref()
                .unwrap()
                .path()
                .extension()
                .is_some_and(|x| x == "mcap")
        })
        .count();
    assert!(files >= 3, "{files} mcap files");
    let (bag, bag_images) = build(&png, &dir.path().join("png.pntrmap"), &[]);
    assert_eq!(bag["frames"], tum["frames"], "{bag}");
    assert_eq!(bag["camera_axes"], "opencv");
    let same = tum_images
        .iter()
        .filter(|(stamp, (t, q))| {
            bag_images.get(stamp).is_some_and(|(bt, bq)| {
                let dt = ((t[0] - bt[0]).powi(2) + (t[1] - bt[1]).powi(2) + (t[2] - bt[2]).powi(2))
                    .sqrt();
                let dot: f64 = q.iter().zip(bq).map(|(a, b)| a * b).sum();
                let deg = (2.0 * dot.abs().min(1.0).acos()).to_degrees();
                dt < 1e-3 && deg < 0.01
            })
        })
        .count();
    assert!(
        same * 100 >= 98 * tum_images.len(),
        "{same} of {} TUM keyframes in the bag's map ({} images)",
        tum_images.len(),
        bag_images.len()
    );

    // The same drive as a robot records it (the converter's default): the render's y-up world is
    // a z-up map (REP 103) and the stamps are wall-clock time. The map is built without flags, its
    // up axis read as z, every keyframe the TUM map's turned +90 degrees about x at its stamp
    // moved to 2026-01-01 UTC.
    let robot = dir.path().join("bag_robot");
    let said = to_robot_bag(&seq, &robot, &["--colour", "png"]);
    assert!(
        said.contains("+y up turned to the map's +z") && said.contains("2026-01-01"),
        "{said}"
    );
    let (r, robot_images) = build(&robot, &dir.path().join("robot.pntrmap"), &[]);
    assert_eq!(r["up_axis"], "z", "{r}");
    assert!(!r["warnings"].to_string().contains("upside down"), "{r}");
    let h = std::f64::consts::FRAC_1_SQRT_2;
    let turned = tum_images
        .iter()
        .filter(|(stamp, (t, q))| {
            robot_images
                .get(&(**stamp + 1_767_225_600_000))
                .is_some_and(|(bt, bq)| {
                    // (x, y, z) -> (x, -z, y); rotation (h, h, 0, 0) * q (w x y z).
                    let want_t = [t[0], -t[2], t[1]];
                    let want_q = [
                        h * (q[0] - q[1]),
                        h * (q[1] + q[0]),
                        h * (q[2] - q[3]),
                        h * (q[3] + q[2]),
                    ];
                    let dt = (0..3)
                        .map(|i| (want_t[i] - bt[i]).powi(2))
                        .sum::<f64>()
                        .sqrt();
                    let dot: f64 = want_q.iter().zip(bq).map(|(a, b)| a * b).sum();
                    dt < 1e-3 && (2.0 * dot.abs().min(1.0).acos()).to_degrees() < 0.01
                })
        })
        .count();
    assert!(
        turned * 100 >= 98 * tum_images.len(),
        "{turned} of {} TUM keyframes turned z-up in the robot bag's map ({} images)",
        tum_images.len(),
        robot_images.len()
    );

    // Two sessions in one frame (the folder and the bag of the same drive): the second adds frames,
    // not keyframes, since the first already has every view.
    let (both, _) = build(
        &seq,
        &dir.path().join("both.pntrmap"),
        &["--sequence", png.to_str().unwrap()],
    );
    assert_eq!(
        both["frames"].as_u64().unwrap(),
        2 * tum["frames"].as_u64().unwrap(),
        "{both}"
    );
    assert_eq!(both["images"], tum["images"], "{both}");

    // JPEG colour and odometry stamped between the images (TF interpolated): recall close to the
    // TUM map's on the scene's 30 HPointLoc queries, at most one query apart (with 6 turned views
    // tried as rivals, one right answer of the JPEG map met a turned pose that verifies too and was
    // refused; issue 41).
    let jpeg = dir.path().join("bag_jpeg");
    to_bag(&seq, &jpeg, &["--colour", "jpeg", "--tf-offset", "0.025"]);
    let jpeg_map = dir.path().join("jpeg.pntrmap");
    let (j, _) = build(&jpeg, &jpeg_map, &[]);
    assert!(j["images"].as_u64().unwrap() > 20, "{j}");
    let (r_tum, r_jpeg) = (
        recall(&data, &dir.path().join("tum.pntrmap")),
        recall(&data, &jpeg_map),
    );
    assert!(
        r_tum >= 0.8 && (r_tum - r_jpeg).abs() <= 1.0 / 30.0 + 1e-9,
        "TUM {r_tum}, JPEG bag {r_jpeg}"
    );

    // Poses from a PoseStamped topic instead of TF.
    let posed = dir.path().join("bag_pose");
    to_bag(&seq, &posed, &["--no-tf", "--pose-topic", "/ground_truth"]);
    let (p, _) = build(
        &posed,
        &dir.path().join("pose.pntrmap"),
        &["--pose-topic", "/ground_truth"],
    );
    assert_eq!(p["images"], tum["images"], "{p}");
    // A pose publisher that never filled the orientation in: every pose left out, and the refusal
    // says so (not that the topic is empty).
    let zero = dir.path().join("bag_zero_poses");
    ok(&Command::new(support::python_importing("rosbags"))
        .arg(repo_root().join("client/tests/support/bag_faults.py"))
        .args([posed.as_os_str(), zero.as_os_str()])
        .arg("zero-poses")
        .output()
        .unwrap());
    let e = build_db_refused(
        &zero,
        &dir.path().join("zero.pntrmap"),
        &["--pose-topic", "/ground_truth"],
    );
    assert!(
        e.contains("no usable poses on /ground_truth")
            && e.contains("are left out")
            && e.contains("a quaternion of norm 0.0000"),
        "{e}"
    );

    // Poses from the body's nav_msgs/Odometry (between the images), carried to the camera by the
    // static transforms.
    let odom = dir.path().join("bag_odom");
    to_bag(
        &seq,
        &odom,
        &["--odometry-topic", "/odom", "--tf-offset", "0.025"],
    );
    let (o, _) = build(
        &odom,
        &dir.path().join("odom.pntrmap"),
        &["--pose-topic", "/odom"],
    );
    let (n_odom, n_tum) = (
        o["images"].as_u64().unwrap(),
        tum["images"].as_u64().unwrap(),
    );
    assert!(n_odom * 10 >= n_tum * 9 && n_odom * 10 <= n_tum * 11, "{o}");
    assert!(o["skipped"]["no_pose"].as_u64().unwrap_or(0) <= 2, "{o}");

    // A camera frame TF does not hold: refused naming both frames and the stamp.
    let x = dir.path().join("x.pntrmap");
    let e = build_db_refused(&png, &x, &["--camera-frame", "camera_depth_optical_frame"]);
    assert!(
        e.contains("no transform from map to camera_depth_optical_frame at"),
        "{e}"
    );

    // A body frame given as the camera frame (x forward, its child the optical frame): refused,
    // naming the optical child, before a map lying on its side is written.
    let body = dir.path().join("body.pntrmap");
    let e = build_db_refused(&png, &body, &["--camera-frame", "camera_link"]);
    assert!(
        e.contains("--camera-frame camera_link is a body frame")
            && e.contains("--camera-frame camera_color_optical_frame"),
        "{e}"
    );
    assert!(!body.exists());

    // Faults of real recordings, each written into the bag by `rosbags` (client/tests/support/
    // bag_faults.py), each found with the check and the self-calibration off.
    let fault = |name: &str| {
        let out = dir.path().join(format!("bag_{name}"));
        let o = Command::new(support::python_importing("rosbags"))
            .arg(repo_root().join("client/tests/support/bag_faults.py"))
            .args([png.as_os_str(), out.as_os_str()])
            .arg(name)
            .output()
            .unwrap();
        ok(&o);
        out
    };
    // base_link under two parents (odometry's odom and another localizer's map, 0.4 m apart): one
    // chain followed throughout, the same poses as the clean bag's, both parents named.
    let (two, two_images) = build(&fault("two-parents"), &dir.path().join("two.pntrmap"), &[]);
    let w = two["warnings"].to_string();
    assert!(
        w.contains("base_link is published under 2 parents")
            && w.contains("odom (")
            && w.contains("map (")
            && w.contains("never a mix"),
        "{two}"
    );
    assert_eq!(two_images.len(), bag_images.len(), "{two}");
    for (stamp, (t, _)) in &two_images {
        let (bt, _) = &bag_images[stamp];
        let d = ((t[0] - bt[0]).powi(2) + (t[1] - bt[1]).powi(2) + (t[2] - bt[2]).powi(2)).sqrt();
        assert!(d < 1e-3, "image {stamp}: {d} m from the clean bag's");
    }
    // The CameraInfo of another camera: refused naming both frames, unless the camera is given.
    let info = fault("info-frame");
    let e = build_db_refused(&info, &x, &["--no-check", "--no-self-calibration"]);
    assert!(
        e.contains("frame camera_depth_optical_frame")
            && e.contains("are of camera_color_optical_frame")
            && e.contains("--info-topic")
            && e.contains("--intrinsics"),
        "{e}"
    );
    assert!(!x.exists());
    let k = std::fs::read_to_string(seq.join("calibration.txt")).unwrap();
    let k = k.split_whitespace().collect::<Vec<_>>().join(",");
    let (given, _) = build(
        &info,
        &dir.path().join("given.pntrmap"),
        &["--intrinsics", &k],
    );
    assert!(given["images"].as_u64().unwrap() > 0, "{given}");
    // Poses with NaN or an all-zero quaternion: left out as tf2 leaves them (the frames needing
    // them have no pose), said in a warning; the map written loads.
    let bad_poses = dir.path().join("bad_poses.pntrmap");
    let (bad, bad_images) = build(&fault("bad-poses"), &bad_poses, &[]);
    let w = bad["warnings"].to_string();
    assert!(
        w.contains("/tf: 3 poses left out, as tf2 leaves them out")
            && w.contains("not finite")
            && w.contains("odom -> base_link"),
        "{bad}"
    );
    assert!(bad_images.len() * 10 >= bag_images.len() * 9, "{bad}");
    ok(&support::pntr(&[
        "info",
        "--db",
        bad_poses.to_str().unwrap(),
    ]));
    // A missing trajectory file names the flag; a folder of .mcap files without metadata.yaml says
    // what to give instead.
    let e = build_db_refused(
        &png,
        &x,
        &[
            "--trajectory",
            dir.path().join("nope.txt").to_str().unwrap(),
        ],
    );
    assert!(e.contains("--trajectory"), "{e}");
    let loose = dir.path().join("loose");
    std::fs::create_dir(&loose).unwrap();
    std::fs::copy(png.join("bag_png_0.mcap"), loose.join("bag_png_0.mcap")).unwrap();
    let e = build_db_refused(&loose, &x, &[]);
    assert!(e.contains("without metadata.yaml"), "{e}");

    // A bag cut short by a power loss: its intact part is read, with a warning.
    let cut = dir.path().join("bag_cut");
    std::fs::create_dir(&cut).unwrap();
    let mut last = None;
    for e in std::fs::read_dir(&png).unwrap() {
        let p = e.unwrap().path();
        std::fs::copy(&p, cut.join(p.file_name().unwrap())).unwrap();
        if p.extension().is_some_and(|x| x == "mcap") {
            last = last.max(Some(p.file_name().unwrap().to_owned()));
        }
    }
    let last = cut.join(last.unwrap());
    let bytes = std::fs::read(&last).unwrap();
    std::fs::write(&last, &bytes[..bytes.len() * 6 / 10]).unwrap();
    let (c, _) = build(&cut, &dir.path().join("cut.pntrmap"), &[]);
    let frames = c["frames"].as_u64().unwrap();
    assert!(
        frames > 0 && frames < tum["frames"].as_u64().unwrap(),
        "{c}"
    );
    assert!(c["warnings"].to_string().contains("cut short"), "{c}");

    // A sqlite3 bag is named as such, with the conversion.
    let db3 = dir.path().join("bag_db3");
    std::fs::create_dir(&db3).unwrap();
    std::fs::write(
        db3.join("metadata.yaml"),
        "rosbag2_bagfile_information:\n  version: 5\n  storage_identifier: sqlite3\n  relative_file_paths: [bag_db3_0.db3]\n",
    )
    .unwrap();
    std::fs::write(db3.join("bag_db3_0.db3"), b"SQLite format 3\0").unwrap();
    let e = build_db_refused(&db3, &x, &[]);
    assert!(
        e.contains("sqlite3") && e.contains("ros2 bag convert"),
        "{e}"
    );

    // The JPEG bag folder replayed through LocalizeStream against the TUM folder's map.
    let rt = runtime();
    let settings = Settings::local(vec![dir.path().join("tum.pntrmap")], MODELS.into());
    let [server] = serve(&rt, [settings]);
    let addr = server.addr.to_string();
    let report = dir.path().join("replay.json");
    let est = dir.path().join("est.txt");
    let recorded = dir.path().join("recorded");
    let recorded_arg = recorded.to_str().unwrap();
    ok(&replay(
        &addr,
        &jpeg,
        &est,
        &report,
        &["--rate", "50", "--frames", "150", "--record", recorded_arg],
    ));
    // A bag folder is never written over (`--record-bag` says it is a bag whatever its name).
    let e = err(&replay(
        &addr,
        &jpeg,
        &dir.path().join("y.txt"),
        &dir.path().join("y.json"),
        &["--record-bag", recorded_arg],
    ));
    assert!(e.contains("already exists"), "{e}");
    // Depth in another unit than the bag says: named before a drive localizes nothing.
    let (x_txt, x_json) = (dir.path().join("x.txt"), dir.path().join("x.json"));
    let e = err(&replay(
        &addr,
        &jpeg,
        &x_txt,
        &x_json,
        &["--depth-scale", "50"],
    ));
    assert!(
        e.contains("--depth-scale") && e.contains("finer units"),
        "{e}"
    );
    stop(&rt, [server]);
    let r = read_json(&report);
    // (A frame recorded before the first map -> odom transform has no pose to compare with.)
    assert!(
        r["frames_with_ground_truth"].as_u64().unwrap() >= 145,
        "{r}"
    );
    assert!(r["localized_share"].as_f64().unwrap() >= 0.9, "{r}");
    assert!(r["ate_rmse_m"].as_f64().unwrap() <= 0.05, "{r}");

    // The run written as a ROS 2 bag, read back by `rosbags` (not pntr's reader): the topics pntr-ros
    // publishes with their ROS types, one pose per LOCALIZED frame, the same path as the trajectory.
    let b = read_bag(&recorded);
    let want = [
        ("/pntr/pose", "geometry_msgs/msg/PoseWithCovarianceStamped"),
        ("/tf", "tf2_msgs/msg/TFMessage"),
        ("/diagnostics", "diagnostic_msgs/msg/DiagnosticArray"),
        ("/pntr/ground_truth", "geometry_msgs/msg/PoseStamped"),
        (
            "/camera/color/image_raw/compressed",
            "sensor_msgs/msg/CompressedImage",
        ),
        ("/camera/color/camera_info", "sensor_msgs/msg/CameraInfo"),
    ];
    for (topic, kind) in want {
        assert_eq!(b["topics"][topic]["type"], kind, "{topic}: {b}");
    }
    let localized = (r["localized_share"].as_f64().unwrap() * 150.0).round() as u64;
    assert_eq!(
        b["topics"]["/pntr/pose"]["count"].as_u64(),
        Some(localized),
        "{b}"
    );
    assert_eq!(
        b["topics"]["/diagnostics"]["count"].as_u64(),
        Some(150),
        "{b}"
    );
    assert_eq!(
        b["topics"]["/camera/color/image_raw/compressed"]["count"].as_u64(),
        Some(150)
    );
    let rows = tum_rows(&est);
    let path = |a: &[f64], z: &[f64]| {
        ((a[0] - z[0]).powi(2) + (a[1] - z[1]).powi(2) + (a[2] - z[2]).powi(2)).sqrt()
    };
    let from_file = path(&rows[0][1..4], &rows[rows.len() - 1][1..4]);
    let poses = b["poses"].as_array().unwrap();
    let p = |v: &serde_json::Value| -> Vec<f64> {
        v.as_array()
            .unwrap()
            .iter()
            .map(|x| x.as_f64().unwrap())
            .collect()
    };
    let from_bag = path(&p(&poses[0]), &p(&poses[poses.len() - 1]));
    assert!(
        (from_file - from_bag).abs() < 1e-6,
        "{from_file} {from_bag}"
    );
    assert_eq!(b["first_level"], 0, "{b}");
    assert!(b["covariance_diagonal_positive"].as_bool().unwrap(), "{b}");

    // `eval --record` to a folder: the dataset's queries as a bag, one status per query.
    let eval_bag = dir.path().join("eval_bag");
    ok(&eval(
        &data,
        &dir.path().join("tum.pntrmap"),
        &["--record", eval_bag.to_str().unwrap()],
    ));
    let b = read_bag(&eval_bag);
    assert_eq!(
        b["topics"]["/diagnostics"]["count"].as_u64(),
        Some(30),
        "{b}"
    );
    assert!(
        b["topics"]["/pntr/pose"]["count"].as_u64().unwrap() >= 20,
        "{b}"
    );
    assert_eq!(
        b["topics"]["/pntr/ground_truth"]["type"],
        "geometry_msgs/msg/PoseStamped"
    );
}

/// A ROS 2 bag folder read with the Python `rosbags` package: each topic's type and count, the
/// positions of `/pntr/pose`, whether their covariance diagonals are positive, the first
/// diagnostic's level.
fn read_bag(bag: &Path) -> serde_json::Value {
    let script = r#"
import json, sys
from pathlib import Path
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore
out = {"topics": {}, "poses": [], "covariance_diagonal_positive": True}
with AnyReader([Path(sys.argv[1])], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as r:
    for c in r.connections:
        out["topics"][c.topic] = {"type": c.msgtype, "count": c.msgcount}
    for c, t, raw in r.messages():
        m = r.deserialize(raw, c.msgtype)
        if c.topic == "/pntr/pose":
            p = m.pose.pose.position
            out["poses"].append([p.x, p.y, p.z])
            out["covariance_diagonal_positive"] &= all(m.pose.covariance[i * 7] > 0 for i in range(6))
        if c.topic == "/diagnostics" and "first_level" not in out:
            out["first_level"] = int(m.status[0].level)
print(json.dumps(out))
"#;
    let o = Command::new(support::python_importing("rosbags"))
        .args(["-c", script])
        .arg(bag)
        .output()
        .unwrap();
    serde_json::from_str(&ok(&o)).unwrap()
}
