//! A robot that drives out of the mapped rooms (issue 49), end to end: a map built from a mapping
//! drive stopped before it covered the whole apartment (`pntr synth --mapping-run
//! --trajectory-seconds 300` of seed 5's 457 s run), and a 60 s drive on another route with a robot
//! camera's effects that leaves the mapped rooms into look-alike ones, replayed through a real
//! `pntr-server` (in this process, 127.0.0.1, ephemeral port) five times faster than it was
//! recorded, with the recording's capture stamps. The old rules answered this drive LOCALIZED up to
//! 4.6 m off (the look-alike room) and, at this pace, re-acquired the mapped rooms late; its
//! refusals out of the map said UNVERIFIED and NO_MATCH, as a camera that sees nothing would.
//! The same drive again with the robot's wheel odometry (`replay --odometry`, drifting as wheels
//! do) and as a 1 Hz stream (`replay --every 10`) against the same frames sent alone (issue 73: a
//! stream is never confidently wrong, and never does worse than its frames alone).
//!
//! And the look-alike made exactly (`synth --twin`): a map of an apartment, and a drive that goes
//! through a door into an exact copy of it, where every map fix is a look-alike one apartment-width
//! off and matches as strongly as the mapped rooms do.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

mod support;

use nalgebra::{UnitQuaternion, Vector3};
use pntr_service::config::Settings;
use support::{build_db, ok, pntr, runtime, serve, stop, tum_pose, tum_rows, MODELS};

/// Poses of a TUM ground-truth file by stamp (milliseconds): position and viewing direction.
fn poses(path: &Path) -> HashMap<i64, (Vector3<f64>, Vector3<f64>)> {
    tum_rows(path)
        .iter()
        .map(|row| {
            let p = tum_pose(row);
            let stamp_ms = (row[0] * 1000.0).round() as i64;
            (stamp_ms, (p.translation.vector, p.rotation * Vector3::z()))
        })
        .collect()
}

#[test]
fn a_drive_out_of_the_mapped_rooms_is_never_answered_far_off() {
    let dir = tempfile::tempdir().unwrap();
    let (mapping, drive) = (dir.path().join("mapping"), dir.path().join("drive"));
    let synth = |out: &Path, extra: &[&str]| {
        ok(&pntr(
            &[
                &["synth", "--out", out.to_str().unwrap(), "--seed", "5"],
                extra,
            ]
            .concat(),
        ))
    };
    synth(&mapping, &["--mapping-run", "--trajectory-seconds", "300"]);
    let robot = [
        "--trajectory-seconds",
        "60",
        "--route-seed",
        "1",
        "--realism",
        "robot",
    ];
    synth(&drive, &robot);
    let (map_seq, drive_seq) = (
        mapping.join("sequences/synth000"),
        drive.join("sequences/synth000"),
    );
    let map = dir.path().join("partial.pntrmap");
    build_db(&map, &["--sequence", map_seq.to_str().unwrap()]);

    let rt = runtime();
    let [server] = serve(&rt, [Settings::local(vec![map], MODELS.into())]);
    let addr = server.addr.to_string();
    let mapping_poses: Vec<_> = poses(&map_seq.join("groundtruth.txt"))
        .into_values()
        .collect();
    let truth = poses(&drive_seq.join("groundtruth.txt"));
    let replay = |name: &str, extra: &[&str]| {
        let frames = replay_drive(&addr, &drive_seq, dir.path(), name, extra);
        score(&frames, &mapping_poses, &truth)
    };

    // The recording five times faster than it was recorded.
    let fast = replay("fast", &["--rate", "50"]);
    let Score {
        mapped,
        mapped_right,
        unmapped,
        unmapped_refused,
        unmapped_outside,
        mapped_outside,
        ref wrong,
        ..
    } = fast;
    eprintln!(
        "{mapped} mapped frames, {mapped_right} right, {mapped_outside} OUTSIDE_MAP; {unmapped} unmapped, {unmapped_refused} refused, {unmapped_outside} OUTSIDE_MAP"
    );
    assert!(
        unmapped >= 150 && mapped >= 150,
        "the drive leaves the map and comes back"
    );
    assert!(wrong.is_empty(), "answered far off: {wrong:#?}");
    assert!(
        mapped_right as f64 >= 0.9 * mapped as f64,
        "{mapped_right} of {mapped} mapped frames right"
    );
    // A supervisor tells the unmapped wing from a camera that sees nothing: most refused frames
    // out of the map say OUTSIDE_MAP (the first second of each stretch keeps its own cause), and
    // the mapped rooms hardly ever do.
    assert!(
        unmapped_outside * 2 >= unmapped_refused,
        "{unmapped_outside} of {unmapped_refused} refused unmapped frames say OUTSIDE_MAP"
    );
    assert!(
        mapped_outside * 20 <= mapped,
        "{mapped_outside} of {mapped} mapped frames say OUTSIDE_MAP"
    );

    // With the robot's wheel odometry (the truth's steps 2% long and turning 1 degree a metre
    // more than the camera did): still nothing far off, the mapped rooms as well answered.
    let odometry = dir.path().join("odometry.txt");
    write_wheel_odometry(&drive_seq.join("groundtruth.txt"), &odometry);
    let with_odometry = replay(
        "odometry",
        &["--rate", "50", "--odometry", odometry.to_str().unwrap()],
    );
    assert!(
        with_odometry.wrong.is_empty(),
        "answered far off with odometry: {:#?}",
        with_odometry.wrong
    );
    assert!(
        with_odometry.mapped_right as f64 >= 0.9 * with_odometry.mapped as f64,
        "with odometry, {} of {} mapped frames right",
        with_odometry.mapped_right,
        with_odometry.mapped
    );

    // A sparse stream (every 10th frame: 1 Hz) gets no fewer frames right than the same frames
    // each sent alone, but for the strong fixes it holds back because it had left the map and
    // its motion since cannot tell them from a look-alike (one a re-entry at 1 Hz); none far off.
    let sparse = replay("sparse", &["--every", "10"]);
    let alone = replay("alone", &["--every", "10", "--no-prior"]);
    eprintln!(
        "1 Hz: stream {} right ({} held back after leaving the map), {} far off; alone {} right, {} far off",
        sparse.right,
        sparse.held_back,
        sparse.wrong.len(),
        alone.right,
        alone.wrong.len()
    );
    assert!(sparse.wrong.is_empty(), "{:#?}", sparse.wrong);
    assert!(
        sparse.right + sparse.held_back >= alone.right,
        "1 Hz: the stream got {} right ({} held back), its frames alone {}",
        sparse.right,
        sparse.held_back,
        alone.right
    );
    stop(&rt, [server]);
}

/// Issue 73's failure made on purpose: the map covers one apartment (a complete mapping run of
/// `synth --twin`'s original half); the drive (a robot camera's effects, the recording's stamps,
/// five times faster) goes from it through the door into the copy beside it. Sent alone, the
/// copy's frames are LOCALIZED one apartment-width off, many with 40 inliers and more; as a stream
/// none may be, with or without the robot's odometry, and the mapped rooms stay answered.
#[test]
fn a_drive_into_a_copy_of_the_mapped_rooms_is_never_answered_there() {
    let dir = tempfile::tempdir().unwrap();
    let (mapping, drive) = (dir.path().join("mapping"), dir.path().join("drive"));
    let synth = |out: &Path, extra: &[&str]| -> serde_json::Value {
        let args = [
            &[
                "synth",
                "--out",
                out.to_str().unwrap(),
                "--seed",
                "5",
                "--twin",
                "--points-per-scene",
                "8",
                "--queries-per-point",
                "1",
                "--json",
            ][..],
            extra,
        ]
        .concat();
        serde_json::from_str(&ok(&pntr(&args))).unwrap()
    };
    let mapped = synth(&mapping, &["--mapping-run", "--trajectory-seconds", "900"]);
    let offset_m = mapped["scenes"][0]["twin_offset_m"].as_f64().unwrap();
    synth(
        &drive,
        &[
            "--trajectory-seconds",
            "60",
            "--route-seed",
            "5",
            "--realism",
            "robot",
        ],
    );
    let (map_seq, drive_seq) = (
        mapping.join("sequences/synth000"),
        drive.join("sequences/synth000"),
    );
    let map = dir.path().join("original.pntrmap");
    build_db(&map, &["--sequence", map_seq.to_str().unwrap()]);
    let mapping_poses: Vec<_> = poses(&map_seq.join("groundtruth.txt"))
        .into_values()
        .collect();
    assert!(
        mapping_poses.iter().all(|(p, _)| p.x < offset_m),
        "the mapping run stays in the original"
    );
    let truth = poses(&drive_seq.join("groundtruth.txt"));
    let in_copy = |stamp_ms: i64| truth[&stamp_ms].0.x > offset_m + 1.5;
    let copy_frames = truth.keys().filter(|&&t| in_copy(t)).count();
    let first = truth.keys().min().unwrap();
    assert!(
        truth[first].0.x < offset_m && copy_frames >= 150,
        "the drive starts in the mapped rooms and spends {copy_frames} frames in the copy"
    );

    let rt = runtime();
    let [server] = serve(&rt, [Settings::local(vec![map], MODELS.into())]);
    let addr = server.addr.to_string();
    let replay = |name: &str, extra: &[&str]| {
        let frames = replay_drive(&addr, &drive_seq, dir.path(), name, extra);
        let text = std::fs::read_to_string(&frames).unwrap();
        let answers: Vec<serde_json::Value> = text
            .lines()
            .map(|l| serde_json::from_str(l).unwrap())
            .collect();
        (score(&frames, &mapping_poses, &truth), answers)
    };
    let stamp_ms =
        |a: &serde_json::Value| (a["timestamp"].as_f64().unwrap() * 1000.0).round() as i64;

    // Alone, the copy is the mapped rooms: LOCALIZED an apartment-width off, strongly.
    let (alone, answers) = replay("alone", &["--no-prior"]);
    let fooled: Vec<_> = answers
        .iter()
        .filter(|a| in_copy(stamp_ms(a)) && a["status"] == "LOCALIZED")
        .filter(|a| (a["error_m"].as_f64().unwrap() - offset_m).abs() < 0.5)
        .collect();
    let strong = fooled
        .iter()
        .filter(|a| a["inliers"].as_u64().unwrap() >= 40)
        .count();
    eprintln!(
        "alone: {} of {copy_frames} frames in the copy LOCALIZED {offset_m:.2} m off ({strong} with 40 inliers or more); {} far off in all",
        fooled.len(),
        alone.wrong.len()
    );
    assert!(
        fooled.len() * 4 >= copy_frames && strong >= 5,
        "the copy must fool single frames for this test to mean anything"
    );

    let odometry = dir.path().join("odometry.txt");
    write_wheel_odometry(&drive_seq.join("groundtruth.txt"), &odometry);
    for (name, extra) in [
        ("stream", vec!["--rate", "50"]),
        (
            "odometry",
            vec!["--rate", "50", "--odometry", odometry.to_str().unwrap()],
        ),
    ] {
        let (s, answers) = replay(name, &extra);
        let refused_in_copy = answers
            .iter()
            .filter(|a| in_copy(stamp_ms(a)) && a["status"] != "LOCALIZED")
            .count();
        eprintln!(
            "{name}: {} of {} mapped frames right, {} far off, {refused_in_copy} of {copy_frames} in the copy refused",
            s.mapped_right,
            s.mapped,
            s.wrong.len()
        );
        assert!(
            s.wrong.is_empty(),
            "{name}: answered far off: {:#?}",
            s.wrong
        );
        assert!(
            s.mapped_right as f64 >= 0.9 * s.mapped as f64,
            "{name}: {} of {} mapped frames right",
            s.mapped_right,
            s.mapped
        );
    }
    stop(&rt, [server]);
}

/// `pntr replay` of the drive `drive_seq` against the server at `addr` with `extra` flags, its
/// report and frames log written into `dir` as `name.json` and `name.jsonl`; the frames log's path.
fn replay_drive(addr: &str, drive_seq: &Path, dir: &Path, name: &str, extra: &[&str]) -> PathBuf {
    let frames = dir.join(format!("{name}.jsonl"));
    let report = dir.join(format!("{name}.json"));
    let args = [
        &[
            "replay",
            "--addr",
            addr,
            "--sequence",
            drive_seq.to_str().unwrap(),
            "--json",
            report.to_str().unwrap(),
            "--frames-log",
            frames.to_str().unwrap(),
        ][..],
        extra,
    ]
    .concat();
    ok(&pntr(&args));
    frames
}

/// What a replay's frames log says against the truth.
struct Score {
    /// Frames a mapping-drive camera stood within 0.5 m of, looking within 30 degrees of its way
    /// (the definition), and those of them LOCALIZED within 0.25 m.
    mapped: usize,
    mapped_right: usize,
    unmapped: usize,
    /// Unmapped frames refused, and those of them that said OUTSIDE_MAP.
    unmapped_refused: usize,
    unmapped_outside: usize,
    mapped_outside: usize,
    /// All frames LOCALIZED within 0.25 m and 2 degrees.
    right: usize,
    /// Strong map fixes held back because the stream had left the map since its last answer.
    held_back: usize,
    /// LOCALIZED more than 1 m or 10 degrees off.
    wrong: Vec<String>,
}

fn score(
    frames: &Path,
    mapping_poses: &[(Vector3<f64>, Vector3<f64>)],
    truth: &HashMap<i64, (Vector3<f64>, Vector3<f64>)>,
) -> Score {
    let mut s = Score {
        mapped: 0,
        mapped_right: 0,
        unmapped: 0,
        unmapped_refused: 0,
        unmapped_outside: 0,
        mapped_outside: 0,
        right: 0,
        held_back: 0,
        wrong: Vec::new(),
    };
    let text = std::fs::read_to_string(frames).unwrap();
    for line in text.lines() {
        let a: serde_json::Value = serde_json::from_str(line).unwrap();
        let stamp_ms = (a["timestamp"].as_f64().unwrap() * 1000.0).round() as i64;
        let (position, forward) = truth[&stamp_ms];
        let is_mapped = mapping_poses.iter().any(|(p, f)| {
            (p - position).norm() <= 0.5 && f.dot(&forward) >= 30f64.to_radians().cos()
        });
        let localized = a["status"] == "LOCALIZED";
        let (error_m, error_deg) = (a["error_m"].as_f64(), a["error_deg"].as_f64());
        let errors = error_m.zip(error_deg);
        if localized && errors.is_some_and(|(m, d)| m > 1.0 || d > 10.0) {
            s.wrong.push(line.to_string());
        }
        s.right += (localized && errors.is_some_and(|(m, d)| m <= 0.25 && d <= 2.0)) as usize;
        s.held_back += a["reason"]
            .as_str()
            .is_some_and(|r| r.starts_with("re-acquiring: the stream left the mapped area"))
            as usize;
        let outside = a["cause"] == "OUTSIDE_MAP";
        if outside {
            let reason = a["reason"].as_str().unwrap_or_default();
            assert!(reason.starts_with("outside the mapped area:"), "{line}");
        }
        if is_mapped {
            s.mapped += 1;
            s.mapped_right += (localized && error_m.is_some_and(|m| m <= 0.25)) as usize;
            s.mapped_outside += outside as usize;
        } else {
            s.unmapped += 1;
            s.unmapped_refused += (!localized) as usize;
            s.unmapped_outside += outside as usize;
        }
    }
    s
}

/// A wheel odometry made from a TUM ground truth (`odom_from_camera`, optical axes, as `pntr replay
/// --odometry` reads it): each step 2% longer than the truth's and turned 1 degree more per metre
/// about the camera's down axis, so it drifts as wheels do.
fn write_wheel_odometry(truth: &Path, out: &Path) {
    let rows = tum_rows(truth);
    let mut odom = tum_pose(&rows[0]);
    let mut previous = odom;
    let mut text = String::from("# timestamp tx ty tz qx qy qz qw\n");
    for row in &rows {
        let now = tum_pose(row);
        let mut step = previous.inverse() * now;
        previous = now;
        let metres = step.translation.vector.norm();
        step.translation.vector *= 1.02;
        step.rotation *= UnitQuaternion::from_axis_angle(&Vector3::y_axis(), metres.to_radians());
        odom *= step;
        let (t, q) = (odom.translation.vector, odom.rotation);
        text += &format!(
            "{} {} {} {} {} {} {} {}\n",
            row[0], t.x, t.y, t.z, q.i, q.j, q.k, q.w
        );
    }
    std::fs::write(out, text).unwrap();
}
