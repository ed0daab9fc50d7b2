//! The Python client package (`client/python`, distribution `pntr-client`, module `pntr_client`)
//! installed as a user installs it, against a real server: a synthetic scene and its map made here,
//! the `pntr-service` library started in-process on 127.0.0.1:0 as the binary starts it, and the
//! client run as separate processes from a fresh virtual environment.
//!
//! Each test process makes its own venv in a temporary folder (`<python> -m venv`, with the
//! interpreter of `$PNTR_PYTHON` / `.deps/venv`) and runs `pip install "client/python[hpointloc]"`
//! into it, which needs the Python package index (setuptools to build; grpcio, protobuf, numpy,
//! h5py to run): without it the tests fail, naming the cause. The install is checked: the committed
//! gRPC stubs were shipped inside the package (`pntr_client/_proto/`, with `.pyi` and `py.typed`)
//! byte for byte as the source tree holds them, nothing top-level besides `pntr_client` was
//! installed, grpcio-tools (needed only to regenerate the stubs) was not, and the module imported is
//! the installed one. Every client run gets an empty `HOME` / `XDG_CACHE_HOME`, which must stay
//! empty: nothing is generated or cached at run time. The committed stubs themselves are checked
//! against the proto by `client/python/generate_proto.py --check` (with the grpcio-tools of
//! `$PNTR_PYTHON` / `.deps/venv`, which scripts/setup.sh installs), so they cannot drift from it.
//!
//! Covered: the frames the package reads with h5py and sends are byte-identical to the Rust reader's
//! (RGB, depth decoded to metres, ground-truth poses); the `pntr-client` console script localizes
//! most queries within 0.25 m and reports errors that agree with the poses; a token-protected TLS
//! server refuses a missing or wrong token with a clean UNAUTHENTICATED error and serves the right
//! token over TLS (CA from `--tls-ca`); a closed port, a missing scene and a missing Point file end
//! with one clear line and no traceback (also through `python -m pntr_client`). The typed API:
//! `Client.localize` answers a 4x4 `world_from_camera` close to the Rust reader's ground truth with a
//! 6x6 covariance and per-stage times, `localize_stream` answers in order and reports a malformed
//! frame by index, malformed inputs raise ValueError naming the mistake, a wrong token raises
//! `UnauthenticatedError` (a `PntrError` with code UNAUTHENTICATED), an unknown map NOT_FOUND, a
//! `Prior` (also from `Answer.as_prior`) is answered through the prior region (mode PRIOR), every
//! answer's `map_version` is the server's map version, a uint16 millimetre depth image is sent as
//! UINT16_MILLIMETERS and localizes as the same depth in float32 metres does, and `relocalize`
//! reaches the server (stream frames that ask for it are searched globally where the same stream
//! without it tracks).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::sync::OnceLock;

use nalgebra::{Isometry3, Matrix4};
use pntr_dataset::{Role, View};
use pntr_pipeline::mapfile;
use pntr_service::config::Settings;
use pntr_service::{proto, wire};
use pntr_tests::{free_addr, runtime, serve, stop_on};
use serde_json::Value;

const SCENE: &str = "synth000";

struct Fixture {
    dir: tempfile::TempDir,
    map: PathBuf,
    /// Query views of Point 0, read by the Rust reader.
    point0: Vec<View>,
    /// Ground-truth world_from_camera of every query of the scene, by (Point index, query index).
    truth: BTreeMap<(u32, usize), Isometry3<f64>>,
    /// Query count of the whole scene.
    queries: usize,
}

fn fixture() -> &'static Fixture {
    static F: OnceLock<Fixture> = OnceLock::new();
    F.get_or_init(|| {
        let dir = tempfile::tempdir().unwrap();
        let index = pntr_tests::synthetic_dataset(dir.path(), 3, 3, 5);
        let built = pntr_tests::build_map(&index, "fast", "all");
        let path = dir.path().join("all.pntrmap");
        mapfile::save(&built, &path).unwrap();
        let scene = index.scene(SCENE).unwrap();
        let mut point0 = Vec::new();
        let mut truth = BTreeMap::new();
        for p in &scene.points {
            let r = p.open().unwrap();
            for i in 0..r.count(Role::Query) {
                let v = r.view(Role::Query, i).unwrap();
                truth.insert((p.index, i), v.world_from_camera);
                if p.index == 0 {
                    point0.push(v);
                }
            }
        }
        let queries = truth.len();
        assert!(!point0.is_empty() && queries >= 6, "{queries} queries");
        Fixture {
            dir,
            map: path,
            point0,
            truth,
            queries,
        }
    })
}

/// A fresh virtual environment with `client/python[hpointloc]` installed from this checkout.
struct Venv {
    /// The venv (`venv/`) and the client's empty home (`home/`).
    dir: tempfile::TempDir,
}

impl Venv {
    fn root(&self) -> PathBuf {
        self.dir.path().join("venv")
    }

    fn bin(&self, name: &str) -> PathBuf {
        self.root().join("bin").join(name)
    }

    /// The folder given to every client run as HOME and XDG_CACHE_HOME; it must stay empty.
    fn home(&self) -> PathBuf {
        self.dir.path().join("home")
    }

    /// `program` (a file in the venv's bin/) with an empty home, no token in the environment, and a
    /// working directory outside the repository.
    fn command(&self, program: &str) -> Command {
        let mut c = Command::new(self.bin(program));
        c.current_dir(self.dir.path())
            .env("HOME", self.home())
            .env("XDG_CACHE_HOME", self.home().join(".cache"))
            .env("PYTHONNOUSERSITE", "1")
            .env_remove("PYTHONPATH")
            .env_remove("PNTR_TOKEN")
            .env_remove("PNTR_PROTO_DIR")
            .env_remove("PNTR_CLIENT_CACHE");
        c
    }

    /// Nothing wrote into the client's home (no stub cache, no generated code).
    fn assert_home_untouched(&self) {
        let left: Vec<_> = std::fs::read_dir(self.home())
            .unwrap()
            .map(|e| e.unwrap().path())
            .collect();
        assert!(left.is_empty(), "the client wrote into its HOME: {left:?}");
    }
}

fn venv() -> &'static Venv {
    static V: OnceLock<Venv> = OnceLock::new();
    V.get_or_init(|| {
        let v = Venv {
            dir: tempfile::tempdir().unwrap(),
        };
        std::fs::create_dir(v.home()).unwrap();
        let base = pntr_tests::python();
        let out = Command::new(&base)
            .args(["-m", "venv"])
            .arg(v.root())
            .output()
            .expect("python runs");
        assert!(
            out.status.success(),
            "`{} -m venv` failed (on Debian: apt-get install python3-venv):\n{}",
            base.display(),
            text(&out.stderr)
        );
        let package = pntr_tests::workspace_root().join("client/python");
        let t0 = std::time::Instant::now();
        let out = Command::new(v.bin("python"))
            .args(["-m", "pip", "install", "--disable-pip-version-check"])
            .args(["--no-input", "--retries", "2"])
            .arg(format!("{}[hpointloc]", package.display()))
            .env_remove("PYTHONPATH")
            .output()
            .expect("the venv's python runs");
        let err = text(&out.stderr);
        assert!(
            out.status.success(),
            "pip could not install {}[hpointloc] into a fresh venv ({}). It needs the Python package \
             index (setuptools to build; grpcio, protobuf, numpy, h5py to run): check network \
             access to it. pip said:\n{}\n{}",
            package.display(),
            out.status,
            text(&out.stdout),
            tail(&err, 6000)
        );
        eprintln!(
            "installed pntr-client into a fresh venv in {:.1} s",
            t0.elapsed().as_secs_f64()
        );
        check_installed(&v);
        v
    })
}

/// The gRPC stubs committed in the source tree, which every install must ship unchanged.
const STUB_FILES: [&str; 3] = [
    "localizer_pb2.py",
    "localizer_pb2.pyi",
    "localizer_pb2_grpc.py",
];

/// What the install put into the venv: the committed stubs inside the package, nothing else.
fn check_installed(v: &Venv) {
    let code = r#"
import importlib.metadata as md, importlib.util, json, pathlib, sysconfig
import pntr_client
from pntr_client._proto import localizer_pb2, localizer_pb2_grpc
dist = md.distribution("pntr-client")
print(json.dumps({
    "module": str(pathlib.Path(pntr_client.__file__).resolve().parent),
    "stubs": str(pathlib.Path(localizer_pb2.__file__).resolve().parent),
    "site": str(pathlib.Path(sysconfig.get_paths()["purelib"]).resolve()),
    "files": sorted(str(f) for f in dist.files),
    "top_level": sorted({str(f).split("/")[0] for f in dist.files}),
    "pntr_importable": importlib.util.find_spec("pntr") is not None,
    "grpc_tools_installed": importlib.util.find_spec("grpc_tools") is not None,
    "stubs_have_prior": hasattr(localizer_pb2, "Prior") and hasattr(localizer_pb2, "Mode"),
    "stub": hasattr(localizer_pb2_grpc, "LocalizerStub"),
    "version": pntr_client.__version__,
    "requires": dist.requires,
}))
"#;
    let out = v.command("python").args(["-c", code]).output().unwrap();
    assert!(out.status.success(), "{}", text(&out.stderr));
    let m: Value = serde_json::from_slice(&out.stdout).unwrap();
    eprintln!("installed: {m}");
    let site = PathBuf::from(m["site"].as_str().unwrap());
    assert_eq!(
        PathBuf::from(m["module"].as_str().unwrap()),
        site.join("pntr_client"),
        "pntr_client must be imported from the venv, not from a source tree"
    );
    let files: Vec<&str> = m["files"]
        .as_array()
        .unwrap()
        .iter()
        .map(|f| f.as_str().unwrap())
        .collect();
    for want in [
        "pntr_client/_proto/localizer_pb2.py",
        "pntr_client/_proto/localizer_pb2.pyi",
        "pntr_client/_proto/localizer_pb2_grpc.py",
        "pntr_client/py.typed",
        "pntr_client/cli.py",
    ] {
        assert!(files.contains(&want), "{want} not installed: {files:?}");
    }
    assert!(
        files.iter().any(|f| f.ends_with("bin/pntr-client")),
        "no pntr-client console script: {files:?}"
    );
    // Only the package (plus the script and the metadata) lands in site-packages.
    for top in m["top_level"].as_array().unwrap() {
        let top = top.as_str().unwrap();
        assert!(
            top == "pntr_client" || top == ".." || top.ends_with(".dist-info"),
            "unexpected top-level entry {top:?}"
        );
    }
    assert_eq!(
        m["pntr_importable"], false,
        "a top-level `pntr` was installed"
    );
    assert_eq!(
        m["grpc_tools_installed"], false,
        "grpcio-tools is needed only to regenerate the stubs, not to install or run"
    );
    assert_eq!(m["stubs_have_prior"], true, "stubs not built from proto/");
    assert_eq!(m["stub"], true);
    // The installed stubs are the committed ones (`shipped_stubs_match_the_proto` checks those).
    let shipped = pntr_tests::workspace_root().join("client/python/src/pntr_client/_proto");
    let installed = PathBuf::from(m["stubs"].as_str().unwrap());
    assert_eq!(installed, site.join("pntr_client/_proto"));
    for name in STUB_FILES {
        let want = std::fs::read(shipped.join(name))
            .unwrap_or_else(|e| panic!("{name} missing from {}: {e}", shipped.display()));
        assert!(
            std::fs::read(installed.join(name)).unwrap() == want,
            "the installed {name} differs from {}",
            shipped.display()
        );
    }
    v.assert_home_untouched();
}

/// The stubs committed in `client/python/src/pntr_client/_proto/` are what the proto generates now:
/// `generate_proto.py --check` regenerates them into a temporary folder and compares (byte for
/// byte with the pinned grpcio-tools; with another version, the serialized file descriptors).
#[test]
fn shipped_stubs_match_the_proto() {
    let script = pntr_tests::workspace_root().join("client/python/generate_proto.py");
    let python = pntr_tests::python();
    let out = Command::new(&python)
        .arg(&script)
        .arg("--check")
        .env_remove("PYTHONPATH")
        .output()
        .expect("python runs");
    let said = format!("{}{}", text(&out.stdout), text(&out.stderr));
    eprint!("{said}");
    assert!(
        out.status.success(),
        "the committed gRPC stubs do not match proto/pntr/v1/localizer.proto ({}): regenerate \
         them with `{} {}` and commit the result (grpcio-tools comes with scripts/setup.sh):\n{said}",
        out.status,
        python.display(),
        script.display()
    );
}

/// Run the `pntr-client` console script with `args`.
fn client(args: &[&str]) -> Output {
    venv()
        .command("pntr-client")
        .args(args)
        .output()
        .expect("pntr-client runs")
}

fn text(b: &[u8]) -> String {
    String::from_utf8_lossy(b).into_owned()
}

/// The last `n` bytes of `s` (at a character boundary).
fn tail(s: &str, n: usize) -> &str {
    let mut i = s.len().saturating_sub(n);
    while !s.is_char_boundary(i) {
        i += 1;
    }
    &s[i..]
}

/// The client failed cleanly: exit status `code`, one `error:` line with `needle`, no traceback.
fn assert_clean_failure(out: &Output, code: i32, needle: &str) {
    let err = text(&out.stderr);
    assert_eq!(out.status.code(), Some(code), "stderr:\n{err}");
    assert!(err.starts_with("error: ") && err.contains(needle), "{err}");
    assert!(!err.contains("Traceback"), "{err}");
    eprint!("{err}");
    assert_eq!(err.trim_end().lines().count(), 1, "{err}");
}

fn run_json(args: &[&str]) -> Value {
    let out = client(args);
    assert!(
        out.status.success(),
        "client failed ({}):\n{}",
        out.status,
        text(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).unwrap_or_else(|e| {
        panic!("not JSON ({e}):\n{}", text(&out.stdout));
    })
}

fn f64s(v: &Value) -> Vec<f64> {
    v.as_array()
        .unwrap()
        .iter()
        .map(|x| x.as_f64().unwrap())
        .collect()
}

#[test]
fn client_frames_match_the_rust_reader() {
    let f = fixture();
    let v = venv();
    let out_dir = f.dir.path().join("frames");
    std::fs::create_dir_all(&out_dir).unwrap();
    // The package's own functions: read Point 0 with h5py and build each request, then dump the
    // payloads for comparison with what the Rust reader and `wire::raw_request` make.
    let code = r#"
import json, sys
from pathlib import Path
import pntr_client
from pntr_client.hpointloc import read_point
out = Path(sys.argv[2])
meta = []
for i, rgb, depth, gps, quat in read_point(sys.argv[1]):
    r = pntr_client.make_request(rgb, depth)
    (out / f"rgb{i}").write_bytes(r.rgb.data)
    (out / f"depth{i}").write_bytes(r.depth.data)
    meta.append({"w": r.rgb.width, "h": r.rgb.height, "dw": r.depth.width, "dh": r.depth.height,
                 "enc": r.rgb.encoding, "denc": r.depth.encoding, "k": r.HasField("intrinsics"),
                 "prior": r.HasField("prior"), "gps": [float(v) for v in gps],
                 "quat": [float(v) for v in quat]})
print(json.dumps(meta))
"#;
    let point0 = pntr_dataset::layout::point_path(f.dir.path(), SCENE, 0);
    let out = v
        .command("python")
        .arg("-c")
        .arg(code)
        .arg(&point0)
        .arg(&out_dir)
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", text(&out.stderr));
    let meta: Vec<Value> = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(meta.len(), f.point0.len());
    for (i, (m, v)) in meta.iter().zip(&f.point0).enumerate() {
        let want = wire::raw_request(&v.rgb, &v.depth, None);
        let (rgb, depth) = (want.rgb.unwrap(), want.depth.unwrap());
        assert_eq!(m["w"].as_u64(), Some(rgb.width as u64));
        assert_eq!(m["h"].as_u64(), Some(rgb.height as u64));
        assert_eq!(m["dw"].as_u64(), Some(depth.width as u64));
        assert_eq!(m["dh"].as_u64(), Some(depth.height as u64));
        assert_eq!(m["enc"].as_i64(), Some(rgb.encoding as i64));
        assert_eq!(m["denc"].as_i64(), Some(depth.encoding as i64));
        assert_eq!(
            m["k"],
            Value::Bool(false),
            "intrinsics are left to the server"
        );
        assert_eq!(m["prior"], Value::Bool(false), "no prior unless given");
        assert!(
            std::fs::read(out_dir.join(format!("rgb{i}"))).unwrap() == rgb.data,
            "rgb of query {i} differs"
        );
        assert!(
            std::fs::read(out_dir.join(format!("depth{i}"))).unwrap() == depth.data,
            "depth of query {i} differs from DepthMap::from_hpointloc"
        );
        let (gps, quat) = pntr_core::pose_to_hpointloc(&v.world_from_camera);
        let (pg, pq) = (f64s(&m["gps"]), f64s(&m["quat"]));
        for k in 0..3 {
            assert!((pg[k] - gps[k]).abs() < 1e-6, "{pg:?} vs {gps:?}");
        }
        let s = if pq[0] < 0.0 { -1.0 } else { 1.0 };
        for k in 0..4 {
            assert!((s * pq[k] - quat[k]).abs() < 1e-6, "{pq:?} vs {quat:?}");
        }
    }
    v.assert_home_untouched();
}

#[test]
fn localizes_against_a_real_server() {
    let f = fixture();
    let v = venv();
    let rt = runtime();
    let running = serve(
        &rt,
        Settings::local(vec![f.map.clone()], pntr_tests::models()),
    );
    let addr = running.addr.to_string();
    let dataset = f.dir.path().to_str().unwrap();

    let scene = ["--addr", &addr, "--dataset", dataset, "--scene", SCENE];
    let doc = run_json(&[&scene[..], &["--json"]].concat());
    assert_eq!(doc["server"]["map_id"], "all");
    let queries = doc["queries"].as_array().unwrap();
    assert_eq!(queries.len(), f.queries);
    let mut good = 0;
    for q in queries {
        let status = q["status"].as_str().unwrap();
        assert!(status == "LOCALIZED" || status == "NOT_LOCALIZED", "{q}");
        if status != "LOCALIZED" {
            assert!(!q["reason"].as_str().unwrap().is_empty(), "{q}");
            assert!(!q["cause"].as_str().unwrap().is_empty(), "{q}");
            continue;
        }
        // The reported errors are those of the reported pose against the file's ground truth.
        let (t, gt) = (f64s(&q["translation"]), f64s(&q["gt_translation"]));
        let te = ((t[0] - gt[0]).powi(2) + (t[1] - gt[1]).powi(2) + (t[2] - gt[2]).powi(2)).sqrt();
        let reported = q["translation_error_m"].as_f64().unwrap();
        assert!((te - reported).abs() < 1e-9, "{q}");
        let rot = q["rotation_error_deg"].as_f64().unwrap();
        assert!((0.0..=180.0).contains(&rot), "{q}");
        assert!(q["server_ms"]["total"].as_f64().unwrap() > 0.0, "{q}");
        if reported < 0.25 {
            assert!(rot < 10.0, "within 0.25 m but {rot} degrees off: {q}");
            good += 1;
        }
    }
    eprintln!("{good} of {} queries within 0.25 m", queries.len());
    assert!(
        3 * good >= 2 * queries.len(),
        "{good} of {} queries within 0.25 m",
        queries.len()
    );
    let s = &doc["summary"];
    assert_eq!(s["queries"].as_u64(), Some(queries.len() as u64));
    let localized = queries
        .iter()
        .filter(|q| q["status"] == "LOCALIZED")
        .count();
    assert_eq!(s["localized"].as_u64(), Some(localized as u64));
    assert!(s["recall"]["0.25m_2deg"].as_f64().is_some(), "{s}");

    // One Point, one query, human-readable output.
    let out = client(&[&scene[..], &["--point", "1", "--queries", "1"]].concat());
    assert!(out.status.success(), "{}", text(&out.stderr));
    let lines = text(&out.stdout);
    eprint!("{lines}");
    assert!(lines.contains(&format!("{SCENE}/point1/q0 ")), "{lines}");
    assert!(
        !lines.contains("/q1 ") && !lines.contains("point0"),
        "{lines}"
    );
    assert!(lines.contains("summary: "), "{lines}");

    // Missing input: the scene (through `python -m pntr_client`), a Point.
    let out = v
        .command("python")
        .args(["-m", "pntr_client", "--addr", &addr, "--dataset", dataset])
        .args(["--scene", "nosuch", "--json"])
        .output()
        .unwrap();
    assert_clean_failure(&out, 2, "scene folder not found");
    let out = client(&[&scene[..], &["--point", "99"]].concat());
    assert_clean_failure(&out, 2, "Point file not found");
    stop_on(&rt, running);

    // Nothing listens there any more.
    let closed = free_addr();
    let out = client(&[
        "--addr",
        &closed.to_string(),
        "--dataset",
        dataset,
        "--scene",
        SCENE,
        "--connect-timeout",
        "1",
        "--json",
    ]);
    assert_clean_failure(&out, 1, &format!("cannot reach pntr-server at {closed}"));
    assert!(out.stdout.is_empty(), "{}", text(&out.stdout));
    v.assert_home_untouched();
}

/// A self-signed certificate for localhost and 127.0.0.1 (cert, key), made with the openssl CLI.
fn self_signed(dir: &Path) -> (PathBuf, PathBuf) {
    let (cert, key) = (dir.join("server.crt"), dir.join("server.key"));
    let out = Command::new("openssl")
        .args([
            "req",
            "-x509",
            "-newkey",
            "ec",
            "-pkeyopt",
            "ec_paramgen_curve:prime256v1",
        ])
        .args(["-nodes", "-days", "2", "-subj", "/CN=localhost"])
        .args(["-addext", "subjectAltName=DNS:localhost,IP:127.0.0.1"])
        .arg("-keyout")
        .arg(&key)
        .arg("-out")
        .arg(&cert)
        .output()
        .expect(
            "the openssl command is needed to make a test certificate (apt-get install openssl)",
        );
    assert!(out.status.success(), "{}", text(&out.stderr));
    (cert, key)
}

#[test]
fn token_and_tls() {
    let f = fixture();
    let v = venv();
    let tls_dir = tempfile::tempdir().unwrap();
    let (cert, key) = self_signed(tls_dir.path());
    let rt = runtime();
    let mut s = Settings::local(vec![f.map.clone()], pntr_tests::models());
    s.token = Some("py-t0ken".into());
    s.tls = Some((cert.clone(), key));
    let running = serve(&rt, s);
    let addr = running.addr.to_string();
    let dataset = f.dir.path().to_str().unwrap();
    let ca = cert.to_str().unwrap();
    let scene = ["--addr", &addr, "--dataset", dataset, "--scene", SCENE];
    let one = ["--point", "0", "--queries", "1", "--tls-ca", ca, "--json"];
    let base = [&scene[..], &one].concat();

    let out = client(&base);
    assert_clean_failure(&out, 1, "UNAUTHENTICATED");
    let out = client(&[&base[..], &["--token", "wrong"]].concat());
    assert_clean_failure(&out, 1, "UNAUTHENTICATED");
    assert!(!text(&out.stderr).contains("py-t0ken"));

    let token_file = tls_dir.path().join("token");
    std::fs::write(&token_file, "py-t0ken\n").unwrap();
    let doc = run_json(&[&base[..], &["--token-file", token_file.to_str().unwrap()]].concat());
    assert_eq!(doc["queries"].as_array().unwrap().len(), 1, "{doc}");
    assert_eq!(doc["server"]["map_id"], "all");

    // The same server without TLS on the client's side gets no answer.
    let plain = ["--token", "py-t0ken", "--connect-timeout", "1"];
    let out = client(&[&scene[..], &plain].concat());
    assert_clean_failure(&out, 1, "cannot reach pntr-server");
    stop_on(&rt, running);
    v.assert_home_untouched();
}

/// The typed API, run in the venv: argv = address, token, the scene's Point files. Prints a JSON
/// report; the checks that need the Rust side (ground truth) are made there.
const API_SCRIPT: &str = r#"
import json, sys
import numpy as np
import pntr_client as pc
from pntr_client._proto import localizer_pb2 as pb2
from pntr_client.hpointloc import read_point

addr, token, paths = sys.argv[1], sys.argv[2], sys.argv[3:]
frames = []  # (point, i, rgb, depth)
for path in paths:
    point = int(path.rsplit("_point", 1)[1].split(".")[0])
    frames += [(point, i, rgb, depth) for i, rgb, depth, _, _ in read_point(path)]
rgb0, depth0 = frames[0][2], frames[0][3]
report = {}

def expect_value_error(what, fn, *needles):
    try:
        fn()
    except ValueError as e:
        msg = str(e)
        assert all(n in msg for n in needles), f"{what}: {msg!r} lacks {needles}"
        report.setdefault("value_errors", {})[what] = msg
        return
    raise AssertionError(f"{what}: no ValueError")

def summary(a):
    assert isinstance(a, pc.Answer)
    assert a.status in ("LOCALIZED", "NOT_LOCALIZED"), a.status
    assert a.localized == (a.status == "LOCALIZED")
    assert isinstance(a.map_version, str)
    r = {"status": a.status, "mode": a.mode, "confidence": a.confidence, "inliers": a.inliers,
         "min_confidence": a.min_confidence, "request_id": a.request_id, "map_id": a.map_id,
         "map_version": a.map_version, "reason": a.reason, "stage_ms": a.stage_ms,
         "matched_image_id": a.matched_image_id, "track_state": a.track_state, "cause": a.cause}
    if a.localized:
        assert a.cause == "", a.cause
        assert isinstance(a.pose, np.ndarray) and a.pose.shape == (4, 4) and a.pose.dtype == np.float64
        assert not a.pose.flags.writeable
        r["pose"] = a.pose.tolist()
        if a.covariance is not None:
            assert a.covariance.shape == (6, 6) and a.covariance.dtype == np.float64
            r["covariance"] = a.covariance.tolist()
    else:
        assert a.pose is None and a.reason
        assert a.cause in ("NO_MATCH", "UNVERIFIED", "LOOK_ALIKE", "OUTSIDE_MAP", "BAD_INPUT"), a.cause
    return r

with pc.Client(addr, token=token, timeout_s=120) as c:
    info = c.map_info()
    assert isinstance(info, pc.MapInfo)
    report["map_info"] = {"map_id": info.map_id, "images": info.images, "loaded": list(info.loaded_map_ids),
                          "calibration_source": info.calibration_source, "min_confidence": info.min_confidence,
                          "version": info.version}

    # One call per frame.
    answers = []
    for point, i, rgb, depth in frames:
        a = c.localize(rgb, depth, request_id=f"p{point}q{i}")
        answers.append(a)
        report.setdefault("localize", []).append(dict(summary(a), point=point, i=i))

    # A stream of the same frames, as Frames and dicts, answered in order.
    stream = [pc.Frame(rgb, depth, request_id=f"s{k}") if k % 2 == 0 else
              {"rgb": rgb, "depth": depth, "request_id": f"s{k}"}
              for k, (_, _, rgb, depth) in enumerate(frames)]
    report["stream"] = [summary(a) for a in c.localize_stream(iter(stream))]

    # A malformed frame in a stream: the answers before it, then ValueError naming it.
    got = []
    def bad_stream():
        for a in c.localize_stream([pc.Frame(rgb0, depth0, request_id="ok0"),
                                    {"rgb": rgb0.astype(np.float32), "depth": depth0}]):
            got.append(a.request_id)
    expect_value_error("stream frame 1 float rgb", bad_stream, "frame 1", "uint8")
    assert got == ["ok0"], got

    # Malformed inputs, caught before sending.
    expect_value_error("rgb float", lambda: c.localize(rgb0.astype(np.float32), depth0), "rgb", "uint8")
    expect_value_error("rgb grey", lambda: c.localize(rgb0[..., 0], depth0), "rgb", "HxWx3")
    expect_value_error("depth float millimetres", lambda: c.localize(rgb0, depth0 * 1000), "millimetres", "1000")
    expect_value_error("depth metres in uint16", lambda: c.localize(rgb0, np.round(depth0).astype(np.uint16)),
                       "uint16", "metres stored")
    expect_value_error("depth int32", lambda: c.localize(rgb0, (depth0 * 1000).astype(np.int32)), "int32", "uint16")
    expect_value_error("relocalize not a bool", lambda: pc.make_request(rgb0, depth0, relocalize="yes"),
                       "relocalize")
    expect_value_error("size mismatch", lambda: c.localize(rgb0, depth0[:100, :120]), "depth", "same size")
    expect_value_error("intrinsics count", lambda: c.localize(rgb0, depth0, intrinsics=(128.0, 128.0, 127.5)),
                       "intrinsics", "3 values")
    expect_value_error("prior without region", lambda: pc.Prior(np.eye(4)), "radius_m", "covariance")
    expect_value_error("prior bad pose", lambda: pc.Prior(np.ones((4, 4)), radius_m=1.0), "prior.pose")

    # Server-side refusals as typed errors.
    try:
        c.localize(rgb0, depth0, map_id="nosuch")
        raise AssertionError("unknown map answered")
    except pc.NotFoundError as e:
        report["not_found"] = {"code": e.code, "details": e.details}

    # Priors, on the first frame that localized without one: its position with a radius, then the
    # answer itself as the prior (pose and radius; and pose and covariance, whose 3-sigma region
    # may hold no map image, so the server may fall back to global retrieval).
    k = next(k for k, a in enumerate(answers) if a.localized)
    base, rgb, depth = answers[k], frames[k][2], frames[k][3]
    p = pc.Prior(base.pose[:3, 3].copy(), radius_m=3.0)
    report["prior_position"] = summary(c.localize(rgb, depth, prior=p, request_id="prior-position"))
    report["prior_answer"] = summary(c.localize(rgb, depth, prior=base.as_prior(radius_m=3.0),
                                                request_id="prior-answer"))
    if base.covariance is not None:
        report["prior_covariance"] = summary(c.localize(rgb, depth, prior=base.as_prior(),
                                                        request_id="prior-covariance"))

    # uint16 millimetres (a RealSense or ROS 16UC1 image, 0 = missing) go out as UINT16_MILLIMETERS,
    # unconverted. The server reads them as the float32 metres mm / 1000 are, so the same frame in
    # those metres must get the same answer.
    mm = np.round(np.nan_to_num(depth, nan=0.0, posinf=0.0, neginf=0.0) * 1000).clip(0, 65535).astype(np.uint16)
    metres = mm.astype(np.float32) / np.float32(1000)
    req = pc.make_request(rgb, mm)
    report["uint16"] = {
        "encoding": pb2.DepthEncoding.Name(req.depth.encoding),
        "metres_encoding": pb2.DepthEncoding.Name(pc.make_request(rgb, metres).depth.encoding),
        "raw": req.depth.data == mm.astype("<u2").tobytes(),
        "millimetres": summary(c.localize(rgb, mm, request_id="uint16-millimetres")),
        "metres": summary(c.localize(rgb, metres, request_id="uint16-metres")),
        "stream": [summary(a) for a in c.localize_stream([pc.Frame(rgb, mm, request_id="uint16-stream")])],
    }

    # relocalize: the same frame four times in a stream (a robot standing still). Without the flag the
    # stream tracks once two fixes agree (mode TRACKING); with it on the last two frames (a Frame and a
    # dict), those are searched over the whole map and answered as unary calls are (GLOBAL).
    assert pc.make_request(rgb, depth, relocalize=True).relocalize
    assert not pc.make_request(rgb, depth).relocalize
    still = [pc.Frame(rgb, depth, request_id=f"still{j}") for j in range(4)]
    again = [pc.Frame(rgb, depth, request_id="reloc0"), pc.Frame(rgb, depth, request_id="reloc1"),
             pc.Frame(rgb, depth, request_id="reloc2", relocalize=True),
             {"rgb": rgb, "depth": depth, "request_id": "reloc3", "relocalize": True}]
    report["relocalize"] = {"without": [summary(a) for a in c.localize_stream(still)],
                            "with": [summary(a) for a in c.localize_stream(again)]}

    # Capture stamps (seconds on the camera's clock): the stream judges motion by them, so the same
    # frames sent back to back track when stamped 0.1 s apart and do not when stamped 10 s apart.
    # Another unit is refused before sending, naming it.
    assert pc.make_request(rgb, depth, stamp_s=12.5).stamp_s == 12.5
    assert pc.make_request(rgb, depth, stamp_s=0).HasField("stamp_s")
    assert not pc.make_request(rgb, depth).HasField("stamp_s")
    expect_value_error("stamp in milliseconds", lambda: pc.make_request(rgb, depth, stamp_s=1.767e12), "milliseconds")
    expect_value_error("stamp not a number", lambda: pc.make_request(rgb, depth, stamp_s="12.5"), "stamp_s")
    # The robot's odometry of the camera goes with a frame as a 4x4 pose, checked before sending.
    assert pc.make_request(rgb, depth, odometry=np.eye(4)).HasField("odometry")
    assert not pc.make_request(rgb, depth).HasField("odometry")
    expect_value_error("odometry not a pose", lambda: pc.make_request(rgb, depth, odometry=np.ones((3, 3))), "odometry")
    close = [{"rgb": rgb, "depth": depth, "stamp_s": 50.0 + 0.1 * j, "odometry": np.eye(4)} for j in range(4)]
    apart = [pc.Frame(rgb, depth, stamp_s=50.0 + 10.0 * j) for j in range(4)]
    report["stamps"] = {"close": [summary(a) for a in c.localize_stream(close)],
                        "apart": [summary(a) for a in c.localize_stream(apart)]}
    # A stream re-opened with where the last one left the camera continues its track: a first
    # frame 10 m from that pose 0.1 s later is a look-alike, the same frame continuing from its
    # own place is answered; map fixes that agree overrule the wrong continuation.
    here = base.as_continuation(stamp_s=69.9)
    moved = base.pose.copy()
    moved[0, 3] += 10.0
    away = pc.Continuation(moved, stamp_s=69.9, sigma_m=0.05)
    expect_value_error("continuation not one", lambda: list(c.localize_stream(close, continuation=base)), "as_continuation")
    expect_value_error("negative sigma", lambda: pc.Continuation(np.eye(4), sigma_m=-0.1), "sigma_m")
    refused = pc.Answer("NOT_LOCALIZED", None, 0.0, None, 0, {}, "no candidate")
    expect_value_error("continuation without pose", lambda: refused.as_continuation(), "no pose")
    one = [pc.Frame(rgb, depth, stamp_s=70.0)]
    report["continuation"] = {"here": [summary(a) for a in c.localize_stream(one, continuation=here)],
                              "away": [summary(a) for a in c.localize_stream(one, continuation=away)],
                              "none": [summary(a) for a in c.localize_stream(one)],
                              "overruled": [summary(a) for a in c.localize_stream(
                                  [pc.Frame(rgb, depth, stamp_s=70.0 + 0.1 * j) for j in range(5)], continuation=away)]}

    # ROS conventions, per call and per client: the same answer, re-expressed with the package's own
    # conversion; a ROS answer taken as the next prior is read in ROS conventions.
    ros = c.localize(rgb, depth, frame_convention="ros", request_id="ros")
    expect_value_error("frame convention", lambda: c.localize(rgb, depth, frame_convention="enu"), "frame_convention")
    report["ros"] = {
        "status": ros.status, "convention": ros.frame_convention, "map_convention": base.frame_convention,
        "info_convention": info.frame_convention, "up_axis": info.up_axis, "camera_axes": info.camera_axes,
        "ros_from_map_ok": bool(np.allclose(info.ros_from_map, pc.ros_from_map_world(info.up_axis))),
    }
    if ros.localized:
        expect = pc.map_to_ros(base.pose, info.up_axis, info.camera_axes)
        back = pc.ros_to_map(ros.pose, info.up_axis, info.camera_axes)
        report["ros"].update({
            "position_gap_m": float(np.linalg.norm(ros.pose[:3, 3] - expect[:3, 3])),
            "rotation_gap": float(np.abs(ros.pose[:3, :3] - expect[:3, :3]).max()),
            "back_gap_m": float(np.linalg.norm(back[:3, 3] - base.pose[:3, 3])),
            "w": ros.rotation_wxyz[0],
        })
        if ros.covariance is not None and base.covariance is not None:
            rotated = pc.rotate_covariance(base.covariance, info.ros_from_map)
            report["ros"]["covariance_gap"] = float(np.abs(ros.covariance - rotated).max() / np.abs(rotated).max())
        with pc.Client(addr, token=token, timeout_s=120, frame_convention="ros") as rc:
            p2 = rc.localize(rgb, depth, prior=ros.as_prior(radius_m=1.5), request_id="ros-prior")
            report["ros"]["prior"] = {"status": p2.status, "mode": p2.mode, "convention": p2.frame_convention}

for t in ("wrong", None):
    with pc.Client(addr, token=t) as bad:
        try:
            bad.localize(rgb0, depth0)
            raise AssertionError("answered without the right token")
        except pc.PntrError as e:
            report.setdefault("bad_token", []).append(
                {"token": t, "code": e.code, "type": type(e).__name__, "message": str(e),
                 "unauthenticated": isinstance(e, pc.UnauthenticatedError)})
print(json.dumps(report))
"#;

/// The rotation angle between two rotation matrices, degrees.
fn angle_deg(a: &Matrix4<f64>, b: &Matrix4<f64>) -> f64 {
    let r = a.fixed_view::<3, 3>(0, 0).transpose() * b.fixed_view::<3, 3>(0, 0);
    ((r.trace() - 1.0) / 2.0)
        .clamp(-1.0, 1.0)
        .acos()
        .to_degrees()
}

fn matrix(v: &Value) -> Matrix4<f64> {
    let rows: Vec<Vec<f64>> = v.as_array().unwrap().iter().map(f64s).collect();
    assert_eq!(rows.len(), 4);
    Matrix4::from_fn(|r, c| rows[r][c])
}

#[test]
fn typed_api_against_a_real_server() {
    let f = fixture();
    let v = venv();
    let rt = runtime();
    let mut s = Settings::local(vec![f.map.clone()], pntr_tests::models());
    s.token = Some("api-t0ken".into());
    let running = serve(&rt, s);
    let addr = running.addr.to_string();
    // The server's own word on its map's version, asked from Rust.
    let server_version = rt.block_on(async {
        let mut c = pntr_tests::client(running.addr).await;
        let req = pntr_tests::authed(proto::GetMapInfoRequest::default(), "api-t0ken");
        c.get_map_info(req).await.unwrap().into_inner().version
    });
    assert!(
        !server_version.is_empty(),
        "the server reports no map version"
    );
    let points: Vec<PathBuf> = (0..3)
        .map(|p| pntr_dataset::layout::point_path(f.dir.path(), SCENE, p))
        .collect();
    let out = v
        .command("python")
        .args(["-c", API_SCRIPT, &addr, "api-t0ken"])
        .args(&points)
        .output()
        .unwrap();
    stop_on(&rt, running);
    assert!(
        out.status.success(),
        "the API script failed:\n{}",
        text(&out.stderr)
    );
    let r: Value = serde_json::from_slice(&out.stdout).unwrap_or_else(|e| {
        panic!("not JSON ({e}):\n{}", text(&out.stdout));
    });
    eprintln!("value errors: {:#}", r["value_errors"]);
    assert_eq!(r["map_info"]["map_id"], "all", "{}", r["map_info"]);
    // The map of this test has no calibration of its own: the shipped one, and its threshold.
    assert_eq!(r["map_info"]["calibration_source"], "shipped");
    assert_eq!(
        r["map_info"]["min_confidence"].as_f64().unwrap(),
        pntr_pipeline::calibration::Calibration::embedded().threshold
    );

    // Localize: 4x4 world_from_camera poses close to the Rust reader's ground truth.
    let answers = r["localize"].as_array().unwrap();
    assert_eq!(answers.len(), f.queries);
    let mut good = 0;
    for a in answers {
        let key = (
            a["point"].as_u64().unwrap() as u32,
            a["i"].as_u64().unwrap() as usize,
        );
        assert_eq!(
            a["request_id"].as_str().unwrap(),
            format!("p{}q{}", key.0, key.1)
        );
        assert_eq!(a["map_id"], "all");
        let stages = a["stage_ms"].as_object().unwrap();
        assert!(stages["extraction"].as_f64().unwrap() > 0.0, "{a}");
        assert!(stages["total"].as_f64().unwrap() > 0.0, "{a}");
        if a["status"] != "LOCALIZED" {
            continue;
        }
        let conf = a["confidence"].as_f64().unwrap();
        assert!(conf >= a["min_confidence"].as_f64().unwrap(), "{a}");
        assert_eq!(a["mode"], "GLOBAL", "no prior was sent: {a}");
        let cov = &a["covariance"];
        assert_eq!(cov.as_array().map(Vec::len), Some(6), "{a}");
        for k in 0..6 {
            assert!(cov[k][k].as_f64().unwrap() >= 0.0, "{a}");
        }
        let pose = matrix(&a["pose"]);
        let truth = f.truth[&key].to_homogeneous();
        let te = (pose.fixed_view::<3, 1>(0, 3) - truth.fixed_view::<3, 1>(0, 3)).norm();
        let re = angle_deg(&pose, &truth);
        eprintln!("{key:?}: {te:.3} m, {re:.2} deg");
        if te < 0.25 && re < 10.0 {
            good += 1;
        }
    }
    assert!(
        3 * good >= 2 * answers.len(),
        "{good} of {} answers within 0.25 m and 10 degrees",
        answers.len()
    );

    // The stream answered every frame, in order.
    let stream = r["stream"].as_array().unwrap();
    let ids: Vec<&str> = stream
        .iter()
        .map(|a| a["request_id"].as_str().unwrap())
        .collect();
    let want: Vec<String> = (0..f.queries).map(|k| format!("s{k}")).collect();
    assert_eq!(ids, want);
    let streamed_ok = stream.iter().filter(|a| a["status"] == "LOCALIZED").count();
    assert!(3 * streamed_ok >= 2 * stream.len(), "{stream:?}");

    // Errors.
    assert_eq!(r["not_found"]["code"], "NOT_FOUND", "{}", r["not_found"]);
    for e in r["bad_token"].as_array().unwrap() {
        assert_eq!(e["code"], "UNAUTHENTICATED", "{e}");
        assert_eq!(e["type"], "UnauthenticatedError", "{e}");
        assert_eq!(e["unauthenticated"], true, "{e}");
        assert!(!e["message"].as_str().unwrap().contains("api-t0ken"), "{e}");
    }
    assert_eq!(r["value_errors"].as_object().unwrap().len(), 18);

    // Priors: answered through the prior region, and still verified.
    for name in ["prior_position", "prior_answer"] {
        let a = &r[name];
        eprintln!("{name}: {} mode {}", a["status"], a["mode"]);
        assert_eq!(a["status"], "LOCALIZED", "{name}: {a}");
        assert_eq!(a["mode"], "PRIOR", "{name}: {a}");
    }
    let a = &r["prior_covariance"];
    assert!(!a.is_null(), "a LOCALIZED answer carries a covariance");
    eprintln!("prior_covariance: {} mode {}", a["status"], a["mode"]);
    assert_eq!(a["status"], "LOCALIZED", "{a}");
    assert!(a["mode"] == "PRIOR" || a["mode"] == "GLOBAL", "{a}");

    // ROS conventions from Python.
    let ros = &r["ros"];
    eprintln!("ros: {ros}");
    assert_eq!(ros["status"], "LOCALIZED", "{ros}");
    assert_eq!(ros["convention"], "ros", "{ros}");
    assert_eq!(ros["map_convention"], "map", "{ros}");
    assert_eq!(ros["info_convention"], "map", "{ros}");
    assert_eq!(ros["ros_from_map_ok"], true, "{ros}");
    assert!(ros["position_gap_m"].as_f64().unwrap() < 1e-3, "{ros}");
    assert!(ros["rotation_gap"].as_f64().unwrap() < 1e-3, "{ros}");
    assert!(ros["back_gap_m"].as_f64().unwrap() < 1e-3, "{ros}");
    assert!(ros["w"].as_f64().unwrap() >= 0.0, "{ros}");
    assert!(ros["covariance_gap"].as_f64().unwrap() < 1e-3, "{ros}");
    assert_eq!(ros["prior"]["status"], "LOCALIZED", "{ros}");
    assert_eq!(ros["prior"]["mode"], "PRIOR", "{ros}");
    assert_eq!(ros["prior"]["convention"], "ros", "{ros}");

    // uint16 millimetres: sent raw as UINT16_MILLIMETERS, answered as the same depth in float32
    // metres (mm / 1000, what the server reads) is, and as the frame's own metres were.
    let u = &r["uint16"];
    eprintln!(
        "uint16: {} {} vs metres {} {}",
        u["millimetres"]["status"],
        u["millimetres"]["confidence"],
        u["metres"]["status"],
        u["metres"]["confidence"]
    );
    assert_eq!(u["encoding"], "UINT16_MILLIMETERS", "{u}");
    assert_eq!(u["metres_encoding"], "FLOAT32_METERS", "{u}");
    assert_eq!(u["raw"], true, "uint16 depth was not sent unconverted: {u}");
    let base = answers
        .iter()
        .find(|a| a["status"] == "LOCALIZED")
        .expect("a LOCALIZED answer");
    let (mm, metres) = (&u["millimetres"], &u["metres"]);
    for a in [mm, metres, &u["stream"][0]] {
        assert_eq!(a["status"], "LOCALIZED", "{a}");
        assert_eq!(a["matched_image_id"], mm["matched_image_id"], "{u}");
    }
    let (pose_mm, pose_m) = (matrix(&mm["pose"]), matrix(&metres["pose"]));
    let gap = (pose_mm.fixed_view::<3, 1>(0, 3) - pose_m.fixed_view::<3, 1>(0, 3)).norm();
    assert!(
        gap < 1e-3,
        "uint16 and float32 metres answers {gap} m apart: {u}"
    );
    assert!(angle_deg(&pose_mm, &pose_m) < 0.1, "{u}");
    let conf_gap =
        (mm["confidence"].as_f64().unwrap() - metres["confidence"].as_f64().unwrap()).abs();
    assert!(conf_gap < 1e-3, "{u}");
    // Against the frame's original float depth (rounded to the millimetre here): the same place.
    let original = matrix(&base["pose"]);
    let gap = (pose_mm.fixed_view::<3, 1>(0, 3) - original.fixed_view::<3, 1>(0, 3)).norm();
    assert!(
        gap < 0.05,
        "uint16 answer {gap} m from the float answer: {u} vs {base}"
    );

    // relocalize reaches the server: the stream without it tracks the standing camera, the one with
    // it on its last two frames answers those globally, as unary calls.
    let reloc = &r["relocalize"];
    let modes_of = |v: &serde_json::Value, k: &str| -> Vec<String> {
        v[k].as_array()
            .unwrap()
            .iter()
            .map(|a| a["mode"].as_str().unwrap().to_string())
            .collect()
    };
    let (without, with) = (modes_of(reloc, "without"), modes_of(reloc, "with"));
    eprintln!("relocalize: without {without:?}, with {with:?}");
    assert_eq!(
        without[3], "TRACKING",
        "the stream without relocalize did not track, so relocalize cannot be told apart: {reloc}"
    );
    assert_eq!(with, ["GLOBAL"; 4], "{reloc}");
    let stamps = &r["stamps"];
    assert_eq!(modes_of(stamps, "close")[2..], ["TRACKING"; 2], "{stamps}");
    // The stream says its track is established once it answers from it.
    for a in &stamps["close"].as_array().unwrap()[2..] {
        assert_eq!(a["track_state"], "TRACK_STATE_ESTABLISHED", "{a}");
    }
    assert_eq!(modes_of(stamps, "apart"), ["GLOBAL"; 4], "{stamps}");
    // The continuation reaches the server and decides the first frame's answer.
    let cont = &r["continuation"];
    for k in ["here", "none"] {
        assert_eq!(cont[k][0]["status"], "LOCALIZED", "{k}: {cont}");
    }
    assert_eq!(cont["away"][0]["status"], "NOT_LOCALIZED", "{cont}");
    assert_eq!(cont["away"][0]["cause"], "LOOK_ALIKE", "{cont}");
    // A wrong continuation is the client's word: map fixes that agree overrule it.
    let overruled = cont["overruled"].as_array().unwrap();
    assert_eq!(overruled[0]["cause"], "LOOK_ALIKE", "{cont}");
    assert_eq!(overruled[4]["status"], "LOCALIZED", "{cont}");
    let ids: Vec<&str> = reloc["with"]
        .as_array()
        .unwrap()
        .iter()
        .map(|a| a["request_id"].as_str().unwrap())
        .collect();
    assert_eq!(ids, ["reloc0", "reloc1", "reloc2", "reloc3"]);
    for a in &reloc["with"].as_array().unwrap()[2..] {
        assert_eq!(
            a["status"], "LOCALIZED",
            "a relocalized frame is answered: {a}"
        );
    }

    // Every answer names the map version that answered: the server's.
    assert_eq!(r["map_info"]["version"], server_version.as_str());
    let mut every: Vec<&Value> = answers.iter().chain(stream).collect();
    for name in ["prior_position", "prior_answer", "prior_covariance"] {
        every.push(&r[name]);
    }
    every.extend([mm, metres, &u["stream"][0]]);
    for k in ["without", "with"] {
        every.extend(reloc[k].as_array().unwrap());
    }
    for a in every {
        assert_eq!(a["map_version"], server_version.as_str(), "{a}");
    }
    v.assert_home_untouched();
}
