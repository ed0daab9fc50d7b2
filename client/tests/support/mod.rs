//! Helpers and checks shared by the CLI tests: the `pntr` binary run and its output checked, scenes
//! generated and maps built through it, files it writes read back, and servers started in process.

// Each test binary uses its own part of this module.
#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion};
use pntr_service::config::Settings;
use pntr_service::tokio::runtime::Runtime;
use pntr_service::Running;

/// The committed ONNX models.
pub const MODELS: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../models");

/// The repository root (the folder holding the top-level Cargo.toml).
pub fn repo_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("client/ has a parent")
        .to_path_buf()
}

/// Run the `pntr` binary under test (without a token from the environment).
pub fn pntr(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_pntr"))
        .args(args)
        .env_remove("PNTR_TOKEN")
        .output()
        .expect("pntr runs")
}

/// Its stdout, asserting it succeeded (stdout and stderr shown when not).
pub fn ok(out: &Output) -> String {
    assert!(
        out.status.success(),
        "{}\n{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8_lossy(&out.stdout).into_owned()
}

/// Its stdout as JSON, asserting it succeeded.
pub fn ok_json(out: &Output) -> serde_json::Value {
    serde_json::from_str(&ok(out)).unwrap()
}

/// Its stderr, asserting it failed without a panic.
pub fn fails_cleanly(out: &Output) -> String {
    let err = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(
        !out.status.success(),
        "expected failure, got success: {err}"
    );
    assert!(
        !err.contains("panicked"),
        "a panic is not an error message: {err}"
    );
    err
}

/// A JSON file `pntr` wrote.
pub fn read_json(path: &Path) -> serde_json::Value {
    serde_json::from_slice(&std::fs::read(path).unwrap()).unwrap()
}

/// `pntr synth --out root --points-per-scene points --queries-per-point queries` with `extra`
/// arguments; its stdout, asserting it succeeded.
pub fn synth(root: &Path, points: &str, queries: &str, extra: &[&str]) -> String {
    let args = [
        "synth",
        "--out",
        root.to_str().unwrap(),
        "--points-per-scene",
        points,
        "--queries-per-point",
        queries,
    ];
    ok(&pntr(&[&args[..], extra].concat()))
}

/// A robot's mapping drive (`pntr synth --mapping-run`) of at most `seconds` through the scene of
/// `seed` with `points` Points and `queries` query draws each, with `extra` arguments: its TUM folder.
pub fn mapping_drive(
    root: &Path,
    (points, queries): (&str, &str),
    seed: &str,
    seconds: &str,
    extra: &[&str],
) -> PathBuf {
    let drive = [
        "--seed",
        seed,
        "--trajectory-seconds",
        seconds,
        "--mapping-run",
    ];
    synth(root, points, queries, &[&drive[..], extra].concat());
    root.join("sequences/synth000")
}

/// `pntr info --db map` with `extra` arguments, as JSON.
pub fn map_info(map: &Path, extra: &[&str]) -> serde_json::Value {
    let args = ["info", "--db", map.to_str().unwrap(), "--json"];
    ok_json(&pntr(&[&args[..], extra].concat()))
}

/// `pntr build-db --out out --models MODELS` with `source` (`--dataset DIR`, `--sequence DIR`...)
/// and further arguments; its stdout, asserting it succeeded.
pub fn build_db(out: &Path, source: &[&str]) -> String {
    let args = [
        "build-db",
        "--out",
        out.to_str().unwrap(),
        "--models",
        MODELS,
    ];
    ok(&pntr(&[&args[..], source].concat()))
}

/// `pntr build-db --sequence seq --out out` with `extra` arguments, asserting it failed: its stderr.
pub fn build_db_refused(seq: &Path, out: &Path, extra: &[&str]) -> String {
    let args = ["build-db", "--sequence", seq.to_str().unwrap()];
    err(&pntr(
        &[&args[..], &["--out", out.to_str().unwrap()], extra].concat(),
    ))
}

/// `pntr eval --dataset dataset --db db --models MODELS` with `extra` arguments.
pub fn eval(dataset: &Path, db: &Path, extra: &[&str]) -> Output {
    let (data, db) = (dataset.to_str().unwrap(), db.to_str().unwrap());
    let args = ["eval", "--dataset", data, "--db", db, "--models", MODELS];
    pntr(&[&args[..], extra].concat())
}

/// `pntr localize --addr addr --rgb rgb --depth depth --json` with `extra` arguments (one frame's
/// files).
pub fn localize_files(addr: &str, rgb: &Path, depth: &Path, extra: &[&str]) -> Output {
    let (rgb, depth) = (rgb.to_str().unwrap(), depth.to_str().unwrap());
    let args = [
        "localize", "--addr", addr, "--rgb", rgb, "--depth", depth, "--json",
    ];
    pntr(&[&args[..], extra].concat())
}

/// `pntr replay --addr addr --sequence seq --trajectory trajectory --json report` with `extra`
/// arguments.
pub fn replay(addr: &str, seq: &Path, trajectory: &Path, report: &Path, extra: &[&str]) -> Output {
    let input = [
        "replay",
        "--addr",
        addr,
        "--sequence",
        seq.to_str().unwrap(),
    ];
    let (trajectory, report) = (trajectory.to_str().unwrap(), report.to_str().unwrap());
    let output = ["--trajectory", trajectory, "--json", report];
    pntr(&[&input[..], &output, extra].concat())
}

/// The images of a map as `pntr info --images --json` lists them (id, stamp, place, translation,
/// rotation_wxyz).
pub fn map_images(map: &Path) -> Vec<serde_json::Value> {
    map_info(map, &["--images"])["image_list"]
        .as_array()
        .unwrap()
        .clone()
}

/// A pose from JSON `translation` [x, y, z] and `rotation_wxyz` [w, x, y, z].
pub fn json_pose(
    translation: &serde_json::Value,
    rotation_wxyz: &serde_json::Value,
) -> Isometry3<f64> {
    let t: Vec<f64> = serde_json::from_value(translation.clone()).unwrap();
    let q: Vec<f64> = serde_json::from_value(rotation_wxyz.clone()).unwrap();
    Isometry3::from_parts(
        Translation3::new(t[0], t[1], t[2]),
        UnitQuaternion::from_quaternion(Quaternion::new(q[0], q[1], q[2], q[3])),
    )
}

/// The rows of a TUM text file (groundtruth.txt, calibration.txt, a trajectory), comments and blank
/// lines left out, as numbers.
pub fn tum_rows(path: &Path) -> Vec<Vec<f64>> {
    std::fs::read_to_string(path)
        .unwrap()
        .lines()
        .filter(|l| !l.starts_with('#') && !l.trim().is_empty())
        .map(|l| l.split_whitespace().map(|v| v.parse().unwrap()).collect())
        .collect()
}

/// A TUM row's pose: `stamp tx ty tz qx qy qz qw`.
pub fn tum_pose(row: &[f64]) -> Isometry3<f64> {
    Isometry3::from_parts(
        Translation3::new(row[1], row[2], row[3]),
        UnitQuaternion::from_quaternion(Quaternion::new(row[7], row[4], row[5], row[6])),
    )
}

/// A two-thread tokio runtime for the servers and clients of a test.
pub fn runtime() -> Runtime {
    pntr_service::tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .unwrap()
}

/// Servers (the `pntr-service` library, as the binary starts it) started on `rt`, one per settings,
/// each returned once it has loaded its maps.
pub fn serve<const N: usize>(rt: &Runtime, settings: [Settings; N]) -> [Running; N] {
    rt.block_on(async {
        let mut servers = Vec::with_capacity(N);
        for s in settings {
            servers.push(pntr_service::start(s).await.unwrap());
        }
        for s in &servers {
            s.ready().await.unwrap();
        }
        let mut servers = servers.into_iter();
        std::array::from_fn(|_| servers.next().expect("one server per settings"))
    })
}

/// Shut the servers down, one after the other, and wait until each has stopped.
pub fn stop(rt: &Runtime, servers: impl IntoIterator<Item = Running>) {
    rt.block_on(async move {
        for mut s in servers {
            s.shutdown();
            s.wait().await.unwrap();
        }
    });
}

/// The Python interpreter with the test packages: `$PNTR_PYTHON`, else set-up's venv.
pub fn python() -> PathBuf {
    std::env::var_os("PNTR_PYTHON")
        .map(PathBuf::from)
        .unwrap_or_else(|| repo_root().join(".deps/venv/bin/python"))
}

/// [`python`], asserting it can import `modules` (`"rosbags, numpy"`): the fix is named when not.
pub fn python_importing(modules: &str) -> PathBuf {
    let p = python();
    let imported = Command::new(&p)
        .args(["-c", &format!("import {modules}")])
        .status()
        .is_ok_and(|s| s.success());
    let fix = "run `bash scripts/setup.sh` (or set PNTR_PYTHON)";
    assert!(imported, "{} cannot import {modules}: {fix}", p.display());
    p
}

/// An MCAP file read back with the format's own Python reader (`mcap`, not pntr's code): for each
/// topic its schema name and encoding, message encoding and message count, and every JSON message
/// of `json_topic` decoded.
pub fn read_mcap(path: &Path, json_topic: &str) -> serde_json::Value {
    const SCRIPT: &str = r#"
import json, sys
from mcap.reader import make_reader
topics, decoded = {}, []
with open(sys.argv[1], "rb") as f:
    reader = make_reader(f)
    summary = reader.get_summary()
    for schema, channel, message in reader.iter_messages():
        t = topics.setdefault(channel.topic, {"schema": schema.name if schema else "",
                                              "schema_encoding": schema.encoding if schema else "",
                                              "message_encoding": channel.message_encoding, "count": 0})
        t["count"] += 1
        if channel.topic == sys.argv[2]:
            decoded.append(json.loads(message.data))
print(json.dumps({"topics": topics, "json": decoded,
                  "statistics_messages": summary.statistics.message_count if summary and summary.statistics else None}))
"#;
    let out = Command::new(python())
        .args(["-c", SCRIPT])
        .arg(path)
        .arg(json_topic)
        .output()
        .expect("python runs (bash scripts/setup.sh makes .deps/venv, or set PNTR_PYTHON)");
    assert!(
        out.status.success(),
        "the mcap reader failed on {}:\n{}",
        path.display(),
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).expect("JSON from the reader")
}

/// Its stderr, asserting it failed.
pub fn err(out: &Output) -> String {
    assert!(!out.status.success(), "expected a failure");
    String::from_utf8_lossy(&out.stderr).into_owned()
}

/// A picture `pntr ... --plot` wrote: `dir/name.png` decodes at `size` with more than a few colours
/// (lines and text, not a blank canvas), and `dir/name.svg` is an SVG document holding every one of
/// `texts` (titles, axis names, legend entries).
pub fn assert_picture(dir: &Path, name: &str, size: (u32, u32), texts: &[&str]) {
    let png = dir.join(format!("{name}.png"));
    let img = image::open(&png)
        .unwrap_or_else(|e| panic!("{}: {e}", png.display()))
        .to_rgb8();
    assert_eq!(img.dimensions(), size, "{}", png.display());
    let colours: std::collections::BTreeSet<[u8; 3]> = img.pixels().map(|p| p.0).collect();
    assert!(
        colours.len() > 20,
        "{}: only {} colours",
        png.display(),
        colours.len()
    );
    let svg_path = dir.join(format!("{name}.svg"));
    let svg = std::fs::read_to_string(&svg_path).unwrap();
    assert!(
        svg.trim_start().starts_with("<svg") && svg.trim_end().ends_with("</svg>"),
        "{}",
        svg_path.display()
    );
    for t in texts {
        assert!(svg.contains(t), "{} lacks \"{t}\"", svg_path.display());
    }
    // Nothing half-written is left beside them.
    for e in std::fs::read_dir(dir).unwrap() {
        let n = e.unwrap().file_name();
        assert!(!n.to_string_lossy().contains(".partial"), "{n:?}");
    }
}

/// A map file section: its tag and payload.
type Section = ([u8; 4], Vec<u8>);

/// The sections of a map file (`pntr_pipeline::mapfile`'s layout: magic, version, then tag,
/// length, payload, checksum per section), read here independently of the reader under test.
fn map_sections(path: &Path) -> (u32, Vec<Section>) {
    let bytes = std::fs::read(path).unwrap();
    assert_eq!(&bytes[..8], b"PNTRMAP\0", "{}", path.display());
    let version = u32::from_le_bytes(bytes[8..12].try_into().unwrap());
    let (mut at, mut out) = (12, Vec::new());
    while at < bytes.len() {
        let tag: [u8; 4] = bytes[at..at + 4].try_into().unwrap();
        let n = u64::from_le_bytes(bytes[at + 4..at + 12].try_into().unwrap()) as usize;
        out.push((tag, bytes[at + 12..at + 12 + n].to_vec()));
        at += 12 + n + 8;
    }
    (version, out)
}

/// The header without what differs between two builds of the same map: when and how long it was
/// built, and the date a calibration was fitted on (with the checksums that cover it).
fn timeless_header(json: &[u8]) -> serde_json::Value {
    fn drop_dates(v: &mut serde_json::Value) {
        if let Some(o) = v.as_object_mut() {
            o.remove("date");
            o.remove("checksum");
            o.values_mut().for_each(drop_dates);
        }
    }
    let mut h: serde_json::Value = serde_json::from_slice(json).unwrap();
    let o = h.as_object_mut().unwrap();
    o.remove("build_seconds");
    o.remove("built_at_unix_s");
    if let Some(c) = o.get_mut("calibration") {
        drop_dates(c);
    }
    h
}

/// Where two JSON values differ beyond floating-point noise (numbers within 1e-6, relative), as
/// the path to the first difference.
fn json_difference(a: &serde_json::Value, b: &serde_json::Value, path: &str) -> Option<String> {
    use serde_json::Value::{Array, Number, Object};
    match (a, b) {
        (Number(x), Number(y)) => {
            let (x, y) = (x.as_f64().unwrap(), y.as_f64().unwrap());
            ((x - y).abs() > 1e-6 * x.abs().max(y.abs()).max(1e-12))
                .then(|| format!("{path}: {x} vs {y}"))
        }
        (Array(x), Array(y)) if x.len() == y.len() => x
            .iter()
            .zip(y)
            .enumerate()
            .find_map(|(i, (u, v))| json_difference(u, v, &format!("{path}[{i}]"))),
        (Object(x), Object(y)) if x.len() == y.len() => {
            x.iter().find_map(|(k, u)| match y.get(k) {
                Some(v) => json_difference(u, v, &format!("{path}.{k}")),
                None => Some(format!("{path}.{k}: only in the first")),
            })
        }
        _ => (a != b).then(|| format!("{path}: {a} vs {b}")),
    }
}

/// Assert that two map files hold the same map: the same sections of the same sizes, the same
/// header (its calibration included) apart from when it was built, and every image with the same
/// id and pose (to 1e-6 m and 1e-6 rad), in the same order. Floating-point noise is allowed: on a
/// loaded machine a refitted calibration's weights were once seen to differ in their seventh digit
/// between two runs of the same binary (BENCHMARKS.md, "Merged maps and their own calibration").
pub fn assert_same_map(a: &Path, b: &Path) {
    let ((va, sa), (vb, sb)) = (map_sections(a), map_sections(b));
    let what = format!("{} and {}", a.display(), b.display());
    assert_eq!(va, vb, "format versions of {what}");
    let sizes = |s: &[Section]| {
        s.iter()
            .filter(|(t, _)| t != b"HEAD")
            .map(|(t, x)| (String::from_utf8_lossy(t).to_string(), x.len()))
            .collect::<Vec<_>>()
    };
    assert_eq!(sizes(&sa), sizes(&sb), "sections of {what}");
    let head = |s: &[Section]| timeless_header(&s.iter().find(|(t, _)| t == b"HEAD").unwrap().1);
    if let Some(d) = json_difference(&head(&sa), &head(&sb), "header") {
        panic!("headers of {what} differ: {d}");
    }
    let (ia, ib) = (map_images(a), map_images(b));
    assert_eq!(ia.len(), ib.len(), "images of {what}");
    for (x, y) in ia.iter().zip(&ib) {
        assert_eq!(x["id"], y["id"], "images of {what}");
        let (px, py) = (
            json_pose(&x["translation"], &x["rotation_wxyz"]),
            json_pose(&y["translation"], &y["rotation_wxyz"]),
        );
        let d = px.inverse() * py;
        assert!(
            d.translation.vector.norm() < 1e-6 && d.rotation.angle() < 1e-6,
            "image {} of {what}: poses differ by {} m, {} rad",
            x["id"],
            d.translation.vector.norm(),
            d.rotation.angle()
        );
    }
}
