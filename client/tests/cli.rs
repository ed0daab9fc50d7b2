//! The `pntr` binary as a user runs it: output keys other tools depend on, and clear errors.

use std::process::Command;

mod support;

use support::{build_db, fails_cleanly, ok, ok_json, pntr, read_json, synth, MODELS};

#[test]
fn synth_then_info_report_the_same_dataset() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().to_str().unwrap();
    let out = synth(
        dir.path(),
        "2",
        "3",
        &["--scenes", "2", "--seed", "4", "--json"],
    );
    let v: serde_json::Value = serde_json::from_str(&out).unwrap();
    let scenes = v["scenes"].as_array().unwrap();
    assert_eq!(scenes.len(), 2);
    for s in scenes {
        assert_eq!(s["points"], 2);
        assert_eq!(s["db_views"], 12);
        let q = s["queries"].as_u64().unwrap() + s["discarded_queries"].as_u64().unwrap();
        assert_eq!(q, 6, "every drawn query is kept or discarded");
    }
    let frames = v["frames"].as_u64().unwrap();
    let expected: u64 = scenes
        .iter()
        .map(|s| s["db_views"].as_u64().unwrap() + s["queries"].as_u64().unwrap())
        .sum();
    assert_eq!(frames, expected);
    assert!(v["frames_per_second"].as_f64().unwrap() > 0.0);

    let info = ok_json(&pntr(&["info", "--dataset", root, "--json"]));
    for (a, b) in info["scenes"].as_array().unwrap().iter().zip(scenes) {
        assert_eq!(a["name"], b["name"]);
        assert_eq!(a["queries"], b["queries"]);
        assert_eq!(
            (a["width"].as_u64(), a["height"].as_u64()),
            (Some(256), Some(256))
        );
    }

    // Regenerating with the same seed replaces the scene with identical content.
    let p = dir
        .path()
        .join("HPointLoc_dataset/synth000/synth000_point1.hdf5");
    let before = std::fs::metadata(&p).unwrap().len();
    synth(dir.path(), "2", "3", &["--scenes", "1", "--seed", "4"]);
    assert_eq!(std::fs::metadata(&p).unwrap().len(), before);
    let leftovers: Vec<_> = std::fs::read_dir(dir.path().join("HPointLoc_dataset"))
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with('.'))
        .collect();
    assert!(
        leftovers.is_empty(),
        "temporary folders left: {leftovers:?}"
    );
}

#[test]
fn help_lists_every_preset_where_a_preset_is_chosen() {
    for cmd in ["build-db", "eval", "calibrate"] {
        let out = pntr(&[cmd, "--help"]);
        let help = String::from_utf8_lossy(&out.stdout);
        for name in pntr_pipeline::preset::PRESETS {
            assert!(
                help.contains(name),
                "`pntr {cmd} --help` lacks {name}: {help}"
            );
        }
    }
}

#[test]
fn bad_arguments_and_files_give_clear_errors() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().to_str().unwrap();
    let err = fails_cleanly(&pntr(&["synth", "--out", root, "--points-per-scene", "0"]));
    assert!(err.contains("--points-per-scene"), "{err}");
    let err = fails_cleanly(&pntr(&["synth", "--out", root, "--tilt-sigma-deg", "NaN"]));
    assert!(err.contains("--tilt-sigma-deg"), "{err}");
    let err = fails_cleanly(&pntr(&[
        "synth",
        "--out",
        root,
        "--textures",
        "/nonexistent-textures",
    ]));
    assert!(err.contains("/nonexistent-textures"), "{err}");

    let err = fails_cleanly(&pntr(&["info", "--dataset", root]));
    assert!(err.contains("HPointLoc_dataset"), "{err}");

    let scene = dir.path().join("HPointLoc_dataset/broken");
    std::fs::create_dir_all(&scene).unwrap();
    let bad = scene.join("broken_point0.hdf5");
    std::fs::write(&bad, b"\x89HDF\r\n\x1a\n truncated").unwrap();
    let err = fails_cleanly(&pntr(&["info", "--dataset", root]));
    assert!(err.contains("broken_point0.hdf5"), "{err}");
}

#[test]
fn build_db_refuses_a_map_id_that_cannot_travel_in_metadata() {
    for (id, needle) in [("building a", "' '"), ("", "1 to 128"), ("bâtiment", "'â'")] {
        let out = pntr(&[
            "build-db",
            "--dataset",
            "/nonexistent",
            "--out",
            "/tmp/never.pntrmap",
            "--map-id",
            id,
        ]);
        let err = fails_cleanly(&out);
        assert!(
            err.contains("--map-id") && err.contains(needle),
            "{id}: {err}"
        );
    }
}

#[test]
fn build_db_then_eval_write_the_documented_json_keys() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().to_str().unwrap();
    synth(dir.path(), "3", "3", &["--seed", "8"]);
    let map = dir.path().join("m.pntrmap");
    let map_s = map.to_str().unwrap();
    let out = build_db(&map, &["--dataset", root, "--scene", "synth000", "--json"]);
    let v: serde_json::Value = serde_json::from_str(&out).unwrap();
    assert_eq!(v["map_id"], "synth000");
    assert_eq!(v["images"], 18);
    assert_eq!(v["preset"], "xfeat-mnn");
    // The map describes itself from its header.
    let h = ok_json(&pntr(&["info", "--db", map_s, "--json"]));
    assert_eq!(h["map_id"], "synth000");
    assert_eq!(h["preset"]["name"], "xfeat-mnn");
    assert_eq!(h["models"][0]["role"], "extractor");
    assert_eq!(h["models"][0]["file"], "xfeat_backbone.onnx");
    // Its calibration says where it comes from, as build-db said, and that it is current.
    assert_eq!(
        h["calibration"]["source"], v["calibration"]["source"],
        "{h}"
    );
    assert_eq!(h["calibration"]["stale"], false, "{h}");
    assert!(h["calibration"]["threshold"].as_f64().is_some(), "{h}");
    let out = pntr(&["info", "--db", map_s]);
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success()
            && text.contains("preset xfeat-mnn:")
            && text.contains("scenes (1): synth000"),
        "{text}"
    );
    let missing = dir.path().join("nope.pntrmap");
    let out = pntr(&["info", "--db", missing.to_str().unwrap()]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && err.contains("nope.pntrmap"),
        "{err}"
    );
    let report = dir.path().join("eval.json");
    let eval = [
        "eval",
        "--dataset",
        root,
        "--scene",
        "synth000",
        "--db",
        map_s,
        "--models",
        MODELS,
        "--json",
        report.to_str().unwrap(),
    ];
    // An MNN preset's matching time is 0.0 ms, and the table says why.
    let table = ok(&pntr(&eval));
    assert!(
        table.contains("matching 0.0") && table.contains("inside retrieval's keypoint vote"),
        "{table}"
    );
    // The bf16 preset's engine named wrongly: a clear error naming the variable and the file it
    // should name, no panic (ONNX Runtime's library given for OpenVINO's, a path that is not there).
    let ort_lib = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../.deps/onnxruntime/libonnxruntime.so.1.31.1"
    );
    for (value, says) in [
        (ort_lib, "is not OpenVINO's C library"),
        ("/no/such/libopenvino_c.so.2641", "which is not a file"),
    ] {
        let out = Command::new(env!("CARGO_BIN_EXE_pntr"))
            .env("OPENVINO_DYLIB_PATH", value)
            .args(eval)
            .args(["--preset", "xfeat-mnn-bf16", "--queries", "2"])
            .output()
            .unwrap();
        let err = fails_cleanly(&out);
        assert!(
            err.contains(says) && err.contains("OPENVINO_DYLIB_PATH") && err.contains(value),
            "{err}"
        );
    }
    let r = read_json(&report);
    let n = r["queries"].as_u64().unwrap();
    assert!(n >= 6, "{r}");
    assert!(r["localized"].as_u64().unwrap() <= n);
    for table in ["recall", "retrieval_only"] {
        for k in [
            "5m_20deg",
            "1m_10deg",
            "0.5m_5deg",
            "0.25m_2deg",
            "5m",
            "1m",
            "0.5m",
            "0.25m",
        ] {
            let x = r[table][k]
                .as_f64()
                .unwrap_or_else(|| panic!("{table}.{k} missing: {r}"));
            assert!((0.0..=1.0).contains(&x));
        }
    }
    for k in [
        "retrieval",
        "extraction",
        "matching",
        "registration",
        "total",
    ] {
        assert!(r["stage_ms"][k].as_f64().unwrap() >= 0.0, "stage_ms.{k}");
    }
    assert!(r["fps"].as_f64().unwrap() > 0.0);
    assert_eq!(r["metric"], "geodesic");
    assert!(
        r["recall"]["5m"].as_f64().unwrap() >= 0.5,
        "most queries localise: {r}"
    );
    // Pictures: error distributions, precision/recall over the threshold, the scene from above.
    let plots = dir.path().join("plots");
    let outcomes = dir.path().join("queries.jsonl");
    let eval_map = |extra: &[&str]| support::eval(dir.path(), &map, extra);
    ok(&eval_map(&[
        "--queries",
        "6",
        "--json",
        report.to_str().unwrap(),
        "--plot",
        plots.to_str().unwrap(),
        "--per-query",
        outcomes.to_str().unwrap(),
    ]));
    // One line per query, agreeing with the report: a LOCALIZED query has its error, and its
    // best estimate is that pose.
    let r = read_json(&report);
    let lines: Vec<serde_json::Value> = std::fs::read_to_string(&outcomes)
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(lines.len() as u64, r["queries"].as_u64().unwrap());
    let localized = lines.iter().filter(|q| !q["error"].is_null()).count();
    assert_eq!(localized as u64, r["localized"].as_u64().unwrap());
    for q in &lines {
        assert!(
            q["id"].as_str().unwrap().starts_with("synth000/point"),
            "{q}"
        );
        assert_eq!(q["position_m"].as_array().unwrap().len(), 3, "{q}");
        // The poses in TUM order: the ground truth's position is `position_m`, its quaternion a
        // unit one with qw >= 0; a LOCALIZED answer's estimate lies within its own error.
        let pose =
            |v: &serde_json::Value| -> Vec<f64> { serde_json::from_value(v.clone()).unwrap() };
        let truth = pose(&q["world_from_camera"]);
        assert_eq!(truth.len(), 7, "{q}");
        assert_eq!(truth[..3], pose(&q["position_m"])[..], "{q}");
        let norm = truth[3..].iter().map(|x| x * x).sum::<f64>().sqrt();
        assert!((norm - 1.0).abs() < 1e-6 && truth[6] >= 0.0, "{q}");
        if !q["error"].is_null() {
            let estimate = pose(&q["estimate_world_from_camera"]);
            let moved = (0..3)
                .map(|i| (estimate[i] - truth[i]).powi(2))
                .sum::<f64>()
                .sqrt();
            let error_m = q["error"][0].as_f64().unwrap();
            assert!((moved - error_m).abs() < 1e-6, "{q}");
        }
        let rank = &q["right_point_rank"];
        assert!(
            rank.is_null() || rank.as_u64().is_some_and(|r| r < 10),
            "{q}"
        );
        // A NOT_LOCALIZED query says why; a LOCALIZED one has no reason.
        assert_eq!(q["error"].is_null(), q["reason"].is_string(), "{q}");
        if !q["error"].is_null() {
            assert_eq!(q["error"], q["estimate_error"], "{q}");
            assert!(
                (0.0..=1.0).contains(&q["confidence"].as_f64().unwrap()),
                "{q}"
            );
        }
    }
    support::assert_picture(
        &plots,
        "errors_cdf",
        (1200, 560),
        &[
            "translation error (m)",
            "rotation error (deg)",
            "retrieval only (top-1 database pose)",
            "6 queries",
        ],
    );
    support::assert_picture(
        &plots,
        "precision_recall",
        (1200, 560),
        &[
            "threshold on the calibrated confidence",
            "recall (0.25 m, 2 deg)",
        ],
    );
    support::assert_picture(
        &plots,
        "map_synth000",
        (900, 900),
        &["synth000: 6 queries", "database cameras", "x (m)", "z (m)"],
    );
    let legacy = dir.path().join("legacy.json");
    ok(&eval_map(&[
        "--legacy-metric",
        "--queries",
        "3",
        "--json",
        legacy.to_str().unwrap(),
    ]));
    let l = read_json(&legacy);
    assert!(l["metric"].as_str().unwrap().starts_with("legacy"), "{l}");
    // Without --json the table alone, on stdout.
    let table = ok(&eval_map(&["--queries", "2"]));
    assert!(
        table.contains("pipeline") && table.contains("0.25m_2deg"),
        "{table}"
    );

    // Bad input: a map that is not one, a preset that does not exist, a missing scene.
    std::fs::write(dir.path().join("bad.pntrmap"), b"hello").unwrap();
    let err = fails_cleanly(&pntr(&[
        "eval",
        "--dataset",
        root,
        "--db",
        dir.path().join("bad.pntrmap").to_str().unwrap(),
        "--json",
        report.to_str().unwrap(),
    ]));
    assert!(
        err.contains("bad.pntrmap") && err.contains("pntr map"),
        "{err}"
    );
    let err = fails_cleanly(&pntr(&[
        "build-db",
        "--dataset",
        root,
        "--out",
        map_s,
        "--preset",
        "turbo",
    ]));
    assert!(err.contains("turbo") && err.contains("fast"), "{err}");
    let err = fails_cleanly(&pntr(&[
        "build-db",
        "--dataset",
        root,
        "--scene",
        "nope",
        "--out",
        map_s,
    ]));
    assert!(err.contains("nope"), "{err}");
    // The good map survived the failed builds.
    assert!(
        eval_map(&["--queries", "1", "--json", report.to_str().unwrap()])
            .status
            .success()
    );
}

#[test]
fn build_db_killed_while_replacing_a_map_leaves_the_old_map_loadable() {
    let dir = tempfile::tempdir().unwrap();
    let small = dir.path().join("small");
    let large = dir.path().join("large");
    for (root, points) in [(&small, "2"), (&large, "8")] {
        synth(root, points, "2", &[]);
    }
    let map = dir.path().join("m.pntrmap");
    let build = |root: &std::path::Path| {
        std::process::Command::new(env!("CARGO_BIN_EXE_pntr"))
            .args([
                "build-db",
                "--dataset",
                root.to_str().unwrap(),
                "--out",
                map.to_str().unwrap(),
            ])
            .args(["--models", MODELS])
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::null())
            .spawn()
            .unwrap()
    };
    assert!(build(&small).wait().unwrap().success());
    let original = std::fs::read(&map).unwrap();
    // SIGKILL a rebuild from the larger dataset at several points of its run (loading MODELS,
    // extracting, training, writing): the map in place is always the complete old one, or, once a
    // rebuild got to its rename, the complete new one; it always loads.
    let report = dir.path().join("r.json");
    for delay_ms in [50u64, 400, 1200, 2500, 4000] {
        let mut child = build(&large);
        std::thread::sleep(std::time::Duration::from_millis(delay_ms));
        let _ = child.kill();
        let _ = child.wait();
        let now = std::fs::read(&map).unwrap();
        let out = support::eval(
            &small,
            &map,
            &["--queries", "1", "--json", report.to_str().unwrap()],
        );
        assert!(
            out.status.success(),
            "after a kill at {delay_ms} ms the map does not load: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        if now != original {
            eprintln!("the rebuild completed before the kill at {delay_ms} ms");
        }
    }
}

#[test]
fn models_are_found_from_any_directory() {
    // Run from a folder that is not the repository: the models are found from the executable
    // (a cargo build's target/<profile>/ sits below the source tree's models/).
    let dir = tempfile::tempdir().unwrap();
    let run = |args: &[&str], env: Option<&str>| {
        let mut c = Command::new(env!("CARGO_BIN_EXE_pntr"));
        c.args(args)
            .current_dir(dir.path())
            .env_remove("PNTR_MODELS");
        if let Some(v) = env {
            c.env("PNTR_MODELS", v);
        }
        c.output().expect("pntr runs")
    };
    let synth = ["synth", "--out", "data", "--points-per-scene", "2"];
    ok(&run(
        &[&synth[..], &["--queries-per-point", "1"]].concat(),
        None,
    ));
    let build = ["build-db", "--dataset", "data", "--out", "m.pntrmap"];
    ok(&run(&build, None));
    assert!(dir.path().join("m.pntrmap").is_file());
    // A wrong PNTR_MODELS is named, not silently replaced by another folder.
    let err = fails_cleanly(&run(&build, Some("/nonexistent/models")));
    assert!(err.contains("PNTR_MODELS /nonexistent/models"), "{err}");
    let err = fails_cleanly(&run(
        &[&build[..], &["--models", "elsewhere"]].concat(),
        None,
    ));
    assert!(err.contains("--models elsewhere: no such folder"), "{err}");
}

/// `--help` of a binary and its subcommands, recursively, as Markdown sections.
fn help_sections(bin: &std::path::Path, name: &str, path: &[&str], out: &mut String) {
    let help = Command::new(bin)
        .args(path)
        .arg("--help")
        // No PNTR_* variable of this machine may show up as an `[env: ...=value]`.
        .env_clear()
        .output()
        .unwrap();
    assert!(help.status.success(), "{name} {path:?} --help");
    let text = String::from_utf8(help.stdout).unwrap();
    let title = std::iter::once(name)
        .chain(path.iter().copied())
        .collect::<Vec<_>>()
        .join(" ");
    out.push_str(&format!(
        "## `{title}`\n\n```text\n{}\n```\n\n",
        text.trim_end()
    ));
    let subcommands: Vec<String> = text
        .lines()
        .skip_while(|l| !l.starts_with("Commands:"))
        .skip(1)
        .take_while(|l| l.starts_with("  "))
        .filter_map(|l| l.split_whitespace().next().map(str::to_string))
        .filter(|c| c != "help")
        .collect();
    for c in subcommands {
        let mut p: Vec<&str> = path.to_vec();
        p.push(&c);
        help_sections(bin, name, &p, out);
    }
}

/// docs/reference/cli.md is generated from the clap definitions (every command's `--help`), so it
/// cannot drift: regenerate it with `PNTR_UPDATE_DOCS=1 cargo test -p pntr-cli --test cli cli_reference`.
#[test]
fn cli_reference_matches_the_clap_definitions() {
    let pntr_bin = std::path::PathBuf::from(env!("CARGO_BIN_EXE_pntr"));
    let server = pntr_bin.with_file_name("pntr-server");
    let ros = pntr_bin.with_file_name("pntr-ros");
    for bin in [&server, &ros] {
        assert!(
            bin.is_file(),
            "{} is missing: build the workspace (cargo build --workspace) before this test",
            bin.display()
        );
    }
    let mut doc = String::from(
        "# Command-line reference\n\n<!-- Generated from the clap definitions by client/tests/cli.rs \
         (cli_reference_matches_the_clap_definitions); do not edit by hand: run \
         `PNTR_UPDATE_DOCS=1 cargo test -p pntr-cli --test cli cli_reference`. -->\n\n\
         Every flag of `pntr`, `pntr-server` and `pntr-ros`, as `--help` prints it. Most server flags \
         can also be set by a `PNTR_*` environment variable (shown as `[env: ...]`) or a key of the \
         `--config` file. pntr-ros's ROS 2 parameters are in docs/robot-integration.md.\n\n",
    );
    help_sections(&server, "pntr-server", &[], &mut doc);
    help_sections(&pntr_bin, "pntr", &[], &mut doc);
    help_sections(&ros, "pntr-ros", &[], &mut doc);
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../docs/reference/cli.md");
    if std::env::var_os("PNTR_UPDATE_DOCS").is_some() {
        std::fs::create_dir_all(path.parent().unwrap()).unwrap();
        std::fs::write(&path, &doc).unwrap();
    }
    let committed = std::fs::read_to_string(&path).unwrap_or_default();
    assert!(
        committed == doc,
        "docs/reference/cli.md differs from the binaries' --help: regenerate it with \
         `PNTR_UPDATE_DOCS=1 cargo test -p pntr-cli --test cli cli_reference`"
    );
}

/// `pntr ... | head -1`: a reader that goes away early ends pntr quietly (status 0 when all was
/// written before, 141 as for SIGPIPE otherwise), never with a panic's message and backtrace.
#[test]
fn a_closed_stdout_ends_pntr_quietly() {
    let dir = tempfile::tempdir().unwrap();
    synth(dir.path(), "2", "1", &["--seed", "5"]);
    for _ in 0..3 {
        let mut child = Command::new(env!("CARGO_BIN_EXE_pntr"))
            .args(["info", "--dataset", dir.path().to_str().unwrap()])
            .stdout(std::process::Stdio::piped())
            .stderr(std::process::Stdio::piped())
            .spawn()
            .unwrap();
        // Close the reading end at once: pntr's first line meets a closed pipe.
        drop(child.stdout.take());
        let out = child.wait_with_output().unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!err.contains("panicked"), "{err}");
        assert!(
            out.status.success() || out.status.code() == Some(141),
            "{:?}: {err}",
            out.status
        );
    }
}

#[test]
fn synth_warns_when_a_drive_cannot_reach_every_point() {
    // Seed 11's apartment has a room the furniture closes off (two of its 23 Points, Point 0 among
    // them): the mapping run starts where it can reach the rest, and synth says what it leaves out.
    let dir = tempfile::tempdir().unwrap();
    let out = pntr(&[
        "synth",
        "--out",
        dir.path().to_str().unwrap(),
        "--queries-per-point",
        "1",
        "--seed",
        "11",
        "--trajectory-seconds",
        "20",
        "--mapping-run",
        "--json",
    ]);
    let stderr = String::from_utf8_lossy(&out.stderr).to_string();
    let j = ok_json(&out);
    let scene = &j["scenes"][0];
    assert_eq!(scene["unreachable_points"], 2, "{j}");
    let ids = scene["unreachable_point_ids"].as_array().unwrap();
    assert_eq!(ids.len(), 2, "{j}");
    assert!(ids.iter().any(|i| i == "point0"), "{j}");
    assert_eq!(scene["sequence_frames"], 200, "{j}");
    // The whole run visits the other 21 Points: far longer than one place's circle (8 s).
    assert!(
        scene["mapping_run_seconds"].as_f64().unwrap() > 150.0,
        "{j}"
    );
    let warnings: Vec<&str> = j["warnings"]
        .as_array()
        .unwrap()
        .iter()
        .map(|w| w.as_str().unwrap())
        .collect();
    assert!(
        warnings
            .iter()
            .any(|w| w.contains("2 of its 23 Points (point0, ")
                && w.contains(") lie in rooms the furniture closes off")
                && w.contains("leaves them out")),
        "{warnings:?}"
    );
    assert!(stderr.contains("closes off"), "{stderr}");
}

#[test]
fn synth_warns_when_trajectory_seconds_cut_a_mapping_run() {
    let run = |seconds: &str| {
        let dir = tempfile::tempdir().unwrap();
        let out = pntr(&[
            "synth",
            "--out",
            dir.path().to_str().unwrap(),
            "--points-per-scene",
            "2",
            "--queries-per-point",
            "1",
            "--seed",
            "4",
            "--trajectory-seconds",
            seconds,
            "--mapping-run",
            "--json",
        ]);
        let stderr = String::from_utf8_lossy(&out.stderr).to_string();
        (ok_json(&out), stderr)
    };
    // Two seconds cannot visit two Points and turn a circle at each: said on stderr and in the JSON.
    let (cut, stderr) = run("2");
    let whole = cut["scenes"][0]["mapping_run_seconds"].as_f64().unwrap();
    assert!(whole > 2.0, "{cut}");
    let warnings = cut["warnings"].as_array().unwrap();
    assert_eq!(warnings.len(), 1, "{cut}");
    let w = warnings[0].as_str().unwrap();
    assert!(
        w.contains("cut it at 2.0 s") && w.contains("--trajectory-seconds"),
        "{w}"
    );
    assert!(
        stderr.contains("warning: synth000: the mapping run needs"),
        "{stderr}"
    );
    // Enough seconds: the whole run is drawn and nothing is said.
    let (whole_run, stderr) = run(&format!("{}", whole.ceil() + 5.0));
    assert!(
        whole_run["warnings"].as_array().unwrap().is_empty(),
        "{whole_run}"
    );
    assert!(!stderr.contains("warning:"), "{stderr}");
    let frames = whole_run["scenes"][0]["sequence_frames"].as_u64().unwrap() as f64;
    assert!((frames / 10.0 - whole).abs() < 0.11, "{whole_run}");
}
