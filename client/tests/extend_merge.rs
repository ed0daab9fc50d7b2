//! Growing maps from more sessions, through the `pntr` binary: `build-db --extend` adds a second
//! session's keyframes (another route, other lighting) to a map and keeps what the map had;
//! `maps merge` finds the transform between two sessions whose SLAM frames differ and joins them,
//! and refuses sessions of another building; an extend killed half-way leaves the old map file.

mod support;

use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use support::{
    build_db, build_db_refused, err, json_pose, map_images, mapping_drive, ok, ok_json, pntr,
    repo_root, runtime, serve, stop, tum_pose, tum_rows, MODELS,
};

/// A mapping drive of the scene of `seed` (four Points, four query draws each), with `extra`
/// arguments.
fn synth(root: &Path, seed: &str, extra: &[&str]) {
    mapping_drive(root, ("4", "4"), seed, "300", extra);
}

/// A map of the sequence `seq` without its check (its own calibration from 40 frames), with `extra`
/// arguments: the build's summary.
fn build(seq: &Path, out: &Path, extra: &[&str]) -> serde_json::Value {
    let source = [
        "--sequence",
        seq.to_str().unwrap(),
        "--no-check",
        "--self-calibration-frames",
        "40",
        "--json",
    ];
    serde_json::from_str(&build_db(out, &[&source[..], extra].concat())).unwrap()
}

/// `(id, world_from_camera)` of every image of a map (`pntr info --images`).
fn images(map: &Path) -> Vec<(String, Isometry3<f64>)> {
    map_images(map)
        .iter()
        .map(|im| {
            (
                im["id"].as_str().unwrap().to_string(),
                json_pose(&im["translation"], &im["rotation_wxyz"]),
            )
        })
        .collect()
}

/// `pntr maps merge A B --out OUT` with `extra` arguments.
fn merge(a: &Path, b: &Path, out: &Path, extra: &[&str]) -> std::process::Output {
    let mut args = vec![
        "maps",
        "merge",
        a.to_str().unwrap(),
        b.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ];
    args.extend_from_slice(extra);
    pntr(&args)
}

/// `pntr maps merge A B --out OUT` refused: its message, after checking that nothing was written.
fn refused_merge(a: &Path, b: &Path, out: &Path) -> String {
    let msg = err(&merge(a, b, out, &[]));
    assert!(!out.exists(), "a refused merge wrote {}", out.display());
    msg
}

/// A TUM trajectory file with every pose moved by `t` (a SLAM session whose origin was elsewhere).
fn move_trajectory(src: &Path, dst: &Path, t: &Isometry3<f64>) {
    let mut out = String::new();
    for v in tum_rows(src) {
        let m = t * tum_pose(&v);
        let (p, q) = (m.translation.vector, m.rotation);
        out += &format!(
            "{:.6} {:.9} {:.9} {:.9} {:.12} {:.12} {:.12} {:.12}\n",
            v[0], p.x, p.y, p.z, q.i, q.j, q.k, q.w
        );
    }
    std::fs::write(dst, out).unwrap();
}

#[test]
fn sessions_extend_and_merge_maps() {
    let dir = tempfile::tempdir().unwrap();
    let (first, second, elsewhere) = (
        dir.path().join("first"),
        dir.path().join("second"),
        dir.path().join("elsewhere"),
    );
    synth(&first, "47", &[]);
    // The same apartment driven along another route, under other lighting.
    synth(
        &second,
        "47",
        &["--route-seed", "2", "--realism", "lighting"],
    );
    synth(&elsewhere, "45", &[]);
    let seq = |root: &Path| root.join("sequences/synth000");

    let a = dir.path().join("a.pntrmap");
    let s = build(&seq(&first), &a, &["--map-id", "lab"]);
    let a_images = images(&a);
    assert_eq!(s["images"].as_u64().unwrap() as usize, a_images.len());

    // Extend: the map keeps its id and every image it had, and gains the views the second
    // session adds (other lighting counts as another view).
    let ext = dir.path().join("ext.pntrmap");
    let e = build(&seq(&second), &ext, &["--extend", a.to_str().unwrap()]);
    assert_eq!(e["map_id"], "lab", "{e}");
    assert_eq!(e["base_images"].as_u64().unwrap() as usize, a_images.len());
    let added = e["images_added"].as_u64().unwrap() as usize;
    assert!(added >= 10, "{e}");
    assert!(e["skipped"]["covered"].as_u64().unwrap() > 0, "{e}");
    let ext_images = images(&ext);
    assert_eq!(ext_images.len(), a_images.len() + added);
    assert_eq!(
        ext_images[..a_images.len()],
        a_images[..],
        "the map's own images are kept"
    );
    // Extending again with the same session is refused, the file untouched.
    let before = std::fs::read(&ext).unwrap();
    let msg = err(&pntr(&[
        "build-db",
        "--extend",
        ext.to_str().unwrap(),
        "--sequence",
        seq(&second).to_str().unwrap(),
        "--models",
        MODELS,
        "--no-check",
    ]));
    assert!(msg.contains("is already in map `lab`"), "{msg}");
    assert_eq!(std::fs::read(&ext).unwrap(), before);
    // An extended map keeps its id: --map-id is refused.
    let other_id = ["--extend", a.to_str().unwrap(), "--map-id", "other"];
    let msg = build_db_refused(&seq(&second), &ext, &other_id);
    assert!(msg.contains("--map-id"), "{msg}");
    // The same later session as a robot's bag (REP 103: a z-up map frame) against this map of a
    // y-up render: poses in another frame, which the map's views cannot judge (they float where no
    // map camera looks). Refused from the cameras' down directions before any frame is described.
    let robot_bag = dir.path().join("robot_bag");
    ok(
        &Command::new(support::python_importing("rosbags, numpy, PIL"))
            .arg(support::repo_root().join("scripts/tum_to_rosbag2.py"))
            .args([seq(&second).as_os_str(), robot_bag.as_os_str()])
            .output()
            .unwrap(),
    );
    let turned = dir.path().join("turned.pntrmap");
    let msg = build_db_refused(
        &robot_bag,
        &turned,
        &[
            "--extend",
            a.to_str().unwrap(),
            "--no-check",
            "--no-self-calibration",
        ],
    );
    assert!(
        msg.contains("its poses are in another frame than map `lab`'s")
            && msg.contains(" deg from the map's")
            && msg.contains("maps merge"),
        "{msg}"
    );
    assert!(!turned.exists());
    // A drive of another apartment whose poses overlap this map's coordinates: the map's own views
    // contradict its new images where they look at the same places; refused, naming the share,
    // whether or not the check runs, and nothing is written.
    let other = dir.path().join("other.pntrmap");
    let msg = build_db_refused(
        &seq(&elsewhere),
        &other,
        &[
            "--extend",
            a.to_str().unwrap(),
            "--no-check",
            "--no-self-calibration",
            "--models",
            MODELS,
        ],
    );
    assert!(
        msg.contains("are contradicted by them") && msg.contains("another building"),
        "{msg}"
    );
    assert!(!other.exists());

    // An extend killed while it writes the new version leaves the map file as it was (it writes a
    // temporary file and renames it), so a server restarted then serves the old map.
    let victim_dir = dir.path().join("victim");
    std::fs::create_dir(&victim_dir).unwrap();
    let victim = victim_dir.join("victim.pntrmap");
    std::fs::copy(&a, &victim).unwrap();
    let original = std::fs::read(&victim).unwrap();
    let mut child = Command::new(env!("CARGO_BIN_EXE_pntr"))
        .args(["build-db", "--extend"])
        .arg(&victim)
        .arg("--sequence")
        .arg(seq(&second))
        .args(["--models", MODELS, "--no-check"])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let writing = || {
        std::fs::read_dir(&victim_dir).unwrap().any(|e| {
            e.unwrap()
                .file_name()
                .to_string_lossy()
                .starts_with("victim.pntrmap.partial-")
        })
    };
    let t = Instant::now();
    loop {
        if writing() {
            break;
        }
        assert!(
            child.try_wait().unwrap().is_none(),
            "the extend finished before it was seen writing"
        );
        assert!(t.elapsed() < Duration::from_secs(600), "never wrote");
        std::thread::sleep(Duration::from_micros(200));
    }
    child.kill().unwrap();
    child.wait().unwrap();
    assert_eq!(
        std::fs::read(&victim).unwrap(),
        original,
        "an extend killed while writing changed the map file"
    );
    assert_eq!(images(&victim), a_images);

    // Merge: the second session mapped by a SLAM whose origin was 7 m away and turned 35 degrees.
    let slam = Isometry3::from_parts(
        Translation3::new(5.0, -1.0, 4.5),
        UnitQuaternion::from_axis_angle(&Vector3::y_axis(), 35f64.to_radians())
            * UnitQuaternion::from_axis_angle(&Vector3::x_axis(), 6f64.to_radians()),
    );
    let moved = dir.path().join("moved.txt");
    move_trajectory(&seq(&second).join("groundtruth.txt"), &moved, &slam);
    let b = dir.path().join("b.pntrmap");
    let sb = build(
        &seq(&second),
        &b,
        &[
            "--trajectory",
            moved.to_str().unwrap(),
            "--no-self-calibration",
        ],
    );
    // The same drive built again (under another name, so its image ids differ) in that other
    // frame is refused rather than merged into a map holding every view twice.
    let copy = dir.path().join("first-copy");
    std::os::unix::fs::symlink(seq(&first), &copy).unwrap();
    let moved_first = dir.path().join("moved-first.txt");
    move_trajectory(&seq(&first).join("groundtruth.txt"), &moved_first, &slam);
    let again = dir.path().join("again.pntrmap");
    build(
        &copy,
        &again,
        &[
            "--trajectory",
            moved_first.to_str().unwrap(),
            "--no-self-calibration",
        ],
    );
    let msg = refused_merge(&a, &again, &dir.path().join("twice.pntrmap"));
    assert!(msg.contains("B is the same drive as A"), "{msg}");
    let merged = dir.path().join("merged.pntrmap");
    let m = ok_json(&merge(&a, &b, &merged, &["--json"]));
    let a_from_b = json_pose(
        &m["transform"]["translation"],
        &m["transform"]["rotation_wxyz"],
    );
    let error = a_from_b * slam;
    assert!(
        error.translation.vector.norm() < 0.05 && error.rotation.angle().to_degrees() < 1.0,
        "transform off by {:.3} m, {:.2} deg: {m}",
        error.translation.vector.norm(),
        error.rotation.angle().to_degrees()
    );
    let tried = m["keyframes_tried"].as_u64().unwrap();
    let support = m["supporting_keyframes"].as_u64().unwrap();
    assert!(support >= 6 && support <= tried, "{m}");
    let cov: Vec<f64> = serde_json::from_value(m["covariance"].clone()).unwrap();
    assert_eq!(cov.len(), 36);
    assert!((0..6).all(|i| cov[i * 7] >= 0.0), "{m}");
    let all = images(&merged);
    assert_eq!(
        all.len(),
        a_images.len() + sb["images"].as_u64().unwrap() as usize
    );
    assert_eq!(m["images"].as_u64().unwrap() as usize, all.len());
    // B's images land where the second session really was (its unmoved poses, in A's frame).
    let truth = super_trajectory(&seq(&second).join("groundtruth.txt"));
    let worst = all[a_images.len()..]
        .iter()
        .map(|(id, pose)| {
            let stamp: f64 = id.rsplit('/').next().unwrap().parse().unwrap();
            let want = truth
                .iter()
                .min_by(|x, y| (x.0 - stamp).abs().total_cmp(&(y.0 - stamp).abs()))
                .unwrap()
                .1;
            (pose.translation.vector - want).norm()
        })
        .fold(0.0, f64::max);
    assert!(worst < 0.1, "a merged image is {worst:.3} m off");

    // A map of one place has no region to hold out and keeps the shipped calibration; one of
    // several fits its own (the extension again). A merged map keeps A's, stale (fitted on A's
    // images alone); refitting it on A's own recording, whose poses are in the merged map's frame,
    // makes it current.
    let own_when_places = |v: &serde_json::Value| {
        let want = if v["places"].as_u64().unwrap() >= 2 {
            "map"
        } else {
            "shipped"
        };
        assert_eq!(v["calibration"]["source"], want, "{v}");
    };
    own_when_places(&s);
    own_when_places(&e);
    let merged_s = merged.to_str().unwrap();
    let info = |m: &str| support::ok(&pntr(&["info", "--db", m, "--images"]));
    let info_json = |m: &str| ok_json(&pntr(&["info", "--db", m, "--json"]));
    if s["calibration"]["source"] == "map" {
        // Said without --images too (the image ids are read either way), in the JSON as well.
        assert!(info(merged_s).contains("STALE"), "{}", info(merged_s));
        let text = support::ok(&pntr(&["info", "--db", merged_s]));
        assert!(text.contains("STALE"), "{text}");
        let j = info_json(merged_s);
        assert_eq!(
            (&j["calibration"]["source"], &j["calibration"]["stale"]),
            (&"map".into(), &true.into()),
            "{j}"
        );
    }
    // The map's own calibration fitted on the first session's frames (60 of them).
    let first_seq = seq(&first);
    let own_fit = [
        "--sequence",
        first_seq.to_str().unwrap(),
        "--self-calibration-frames",
        "60",
        "--models",
        MODELS,
    ];
    let mut args = vec!["calibrate", "--db", merged_s];
    args.extend_from_slice(&own_fit);
    let refit = ok_json(&pntr(&args));
    assert_eq!(refit["source"], "map", "{refit}");
    assert!(refit["held_out_frames"].as_u64().unwrap() > 0, "{refit}");
    assert_eq!(info_json(merged_s)["calibration"]["stale"], false);
    let text = info(merged_s);
    assert!(
        !text.contains("STALE") && text.contains("calibration: the map's own"),
        "{text}"
    );
    // `maps merge --sequence` does both in one step: the same map, byte for byte (its own
    // calibration fitted on the same frames), never stale.
    let merged_fitted = dir.path().join("merged-fitted.pntrmap");
    let m2 = ok_json(&merge(
        &a,
        &b,
        &merged_fitted,
        &[&own_fit[..], &["--json"]].concat(),
    ));
    assert_eq!(
        (&m2["calibration"]["source"], &m2["calibration"]["stale"]),
        (&"map".into(), &false.into()),
        "{m2}"
    );
    assert_eq!(m2["calibration_refit"]["frames"], 60, "{m2}");
    assert_eq!(m2["calibration"]["threshold"], refit["threshold"], "{m2}");
    support::assert_same_map(&merged, &merged_fitted);
    // And it answers the scene's queries at least as well as A, the whole drive's map (B, the
    // shorter session in another frame, covers less), with no wrong answer.
    let answers = |map: &Path| {
        let report = dir.path().join("merged-eval.json");
        ok(&support::eval(
            &first,
            map,
            &["--json", report.to_str().unwrap()],
        ));
        let r = support::read_json(&report);
        (
            r["recall"]["0.25m_2deg"].as_f64().unwrap(),
            r["localized_wrong"].as_u64().unwrap(),
        )
    };
    let ((recall_a, _), (recall_merged, wrong)) = (answers(&a), answers(&merged_fitted));
    assert!(
        recall_merged >= recall_a - 0.02 && wrong == 0,
        "merged map: recall {recall_merged:.3} ({wrong} wrong) against A's {recall_a:.3}"
    );
    // A calibration fitted for the drive's map on the same apartment's dataset and another's: the
    // dataset's poses have Habitat camera axes, the map's OpenCV ones (compared as they are, every
    // in-map answer was 180 degrees off and the fit found no right answer to fit).
    let fitted = dir.path().join("fitted-calibration.json");
    let from_dataset = ok_json(&pntr(&[
        "calibrate",
        "--db",
        a.to_str().unwrap(),
        "--dataset",
        first.to_str().unwrap(),
        "--negatives",
        elsewhere.to_str().unwrap(),
        "--out",
        fitted.to_str().unwrap(),
        "--models",
        MODELS,
    ]));
    assert!(
        from_dataset["positives"].as_u64().unwrap() >= 5,
        "{from_dataset}"
    );

    // A running server extends its map with a recording on its disk, writes the map's file and
    // serves the new version (`pntr maps extend`, the admin token from PNTR_ADMIN_TOKEN).
    let served = dir.path().join("served.pntrmap");
    std::fs::copy(&a, &served).unwrap();
    let rt = runtime();
    let mut settings = pntr_service::config::Settings::local(vec![served.clone()], MODELS.into());
    settings.admin_token = Some("adm1n-t0ken".into());
    settings.workers = 1;
    let [running] = serve(&rt, [settings]);
    let addr = running.addr.to_string();
    let admin = |args: &[&str], token: bool| {
        let mut c = Command::new(env!("CARGO_BIN_EXE_pntr"));
        c.arg("maps").args(args).args(["--addr", &addr]);
        if token {
            c.env("PNTR_ADMIN_TOKEN", "adm1n-t0ken");
        } else {
            c.env_remove("PNTR_ADMIN_TOKEN");
        }
        c.output().unwrap()
    };
    let list = |token| ok_json(&admin(&["list", "--json"], token));
    let before = list(true);
    let v1 = before["maps"][0]["version"].as_str().unwrap().to_string();
    assert_eq!(before["maps"][0]["map_id"], "lab");
    let second_seq = seq(&second);
    let extend = [
        "extend",
        "--map-id",
        "lab",
        "--sequence",
        second_seq.to_str().unwrap(),
    ];
    let change = ok_json(&admin(&[&extend[..], &["--json"]].concat(), true));
    assert_eq!(
        change["images_added"].as_u64().unwrap() as usize,
        added,
        "{change}"
    );
    assert_eq!(change["previous_version"], v1.as_str());
    assert_eq!(change["same_frame"], true, "{change}");
    let after = list(true);
    assert_ne!(after["maps"][0]["version"], v1.as_str());
    // What a robot's client sees of it (GetMapInfo, no admin token needed).
    let info = ok_json(&pntr(&["info", "--addr", &addr, "--json"]));
    assert_eq!(info["version"], after["maps"][0]["version"], "{info}");
    assert_eq!(info["camera_axes"], "opencv", "{info}");
    assert_eq!(info["loaded_map_ids"], serde_json::json!(["lab"]), "{info}");
    // The admin's list and GetMapInfo say the same of the calibration. The server refitted the
    // map's own calibration on the frames it was given (as build-db --extend does): never stale.
    assert_eq!(
        after["maps"][0]["calibration"], info["calibration"],
        "{after}"
    );
    assert_eq!(before["maps"][0]["calibration"]["stale"], false, "{before}");
    assert_eq!(after["maps"][0]["calibration"]["stale"], false, "{after}");
    if before["maps"][0]["calibration"]["source"] == "map" {
        assert_eq!(after["maps"][0]["calibration"]["source"], "map", "{after}");
    }
    // The file on disk carries it too.
    let on_disk = ok_json(&pntr(&["info", "--db", served.to_str().unwrap(), "--json"]));
    assert_eq!(on_disk["calibration"]["stale"], false, "{on_disk}");
    assert_eq!(
        on_disk["calibration"]["threshold"], info["calibration"]["threshold"],
        "{on_disk}"
    );
    assert_eq!(
        after["maps"][0]["images"].as_u64().unwrap() as usize,
        a_images.len() + added
    );
    assert_eq!(
        images(&served).len(),
        a_images.len() + added,
        "written to the map's file"
    );
    // The server extends as `build-db --extend` does (one call for both): the same map, byte for
    // byte, its own calibration refitted on the same frames.
    let by_cli = dir.path().join("extended-by-cli.pntrmap");
    build_db(
        &by_cli,
        &[
            "--sequence",
            second_seq.to_str().unwrap(),
            "--extend",
            a.to_str().unwrap(),
            "--no-check",
        ],
    );
    support::assert_same_map(&served, &by_cli);
    let msg = err(&admin(&extend, true));
    assert!(msg.contains("already in map"), "{msg}");
    // The same drive as a bag with realsense-ros 4.x's topic names (/camera/camera/...): the
    // server reads it with the topics given, as build-db would (and its frames are in the map now).
    let bag = dir.path().join("bag");
    let renamed = dir.path().join("bag_renamed");
    let python = support::python_importing("rosbags, numpy, PIL");
    ok(&Command::new(&python)
        .arg(repo_root().join("scripts/tum_to_rosbag2.py"))
        .args([second_seq.as_os_str(), bag.as_os_str()])
        .arg("--keep-tum-frame")
        .output()
        .unwrap());
    ok(&Command::new(&python)
        .arg(repo_root().join("client/tests/support/bag_faults.py"))
        .args([bag.as_os_str(), renamed.as_os_str()])
        .arg("renamed")
        .output()
        .unwrap());
    let bag_extend = [
        "extend",
        "--map-id",
        "lab",
        "--sequence",
        renamed.to_str().unwrap(),
    ];
    let msg = err(&admin(&bag_extend, true));
    assert!(
        msg.contains("no colour images on /camera/color/image_raw")
            && msg.contains("/camera/camera/color/image_raw/compressed"),
        "{msg}"
    );
    let topics = [
        "--rgb-topic",
        "/camera/camera/color/image_raw",
        "--depth-topic",
        "/camera/camera/aligned_depth_to_color/image_raw",
        "--info-topic",
        "/camera/camera/color/camera_info",
    ];
    let msg = err(&admin(&[&bag_extend[..], &topics[..]].concat(), true));
    assert!(msg.contains("already in map"), "{msg}");
    let msg = err(&admin(&["list"], false));
    assert!(msg.contains("admin token"), "{msg}");
    stop(&rt, [running]);

    // Sessions of another apartment are refused: too few keyframes agree.
    let c = dir.path().join("c.pntrmap");
    build(&seq(&elsewhere), &c, &[]);
    let msg = refused_merge(&a, &c, &dir.path().join("no.pntrmap"));
    assert!(msg.contains("too few keyframes agree"), "{msg}");
    // One map given twice would hold every image twice: refused, saying so.
    let msg = refused_merge(&a, &a, &dir.path().join("twice.pntrmap"));
    assert!(
        msg.contains("already in map A") && msg.contains("maps merge A A"),
        "{msg}"
    );
    // A map extended from A (A's images and more) is the merge already: said so.
    let msg = refused_merge(&a, &ext, &dir.path().join("grown.pntrmap"));
    assert!(
        msg.contains("was extended from A") && msg.contains("merged map already"),
        "{msg}"
    );
}

/// groundtruth.txt rows: (stamp, position).
fn super_trajectory(path: &Path) -> Vec<(f64, Vector3<f64>)> {
    tum_rows(path)
        .iter()
        .map(|v| (v[0], Vector3::new(v[1], v[2], v[3])))
        .collect()
}
