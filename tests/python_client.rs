//! The Python client (`client/python/pntr_client.py`) against a real server: a synthetic scene and
//! its map made here, the `pntr-service` library started in-process on 127.0.0.1:0 as the binary
//! starts it, and the client run as a separate process with the venv's Python (grpcio, grpcio-tools,
//! h5py), generating its stubs from proto/ into a fresh cache folder.
//!
//! Covered: the frames the client reads with h5py and sends are byte-identical to the Rust reader's
//! (RGB, depth decoded to metres, ground-truth poses); most queries are LOCALIZED within 0.25 m and
//! the reported errors agree with the poses; a token-protected TLS server refuses a missing or wrong
//! token with a clean UNAUTHENTICATED error and serves the right token over TLS (CA from `--tls-ca`);
//! a closed port, a missing scene and a missing Point file end with one clear line and no traceback.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::sync::OnceLock;

use pntr_dataset::{Role, View};
use pntr_pipeline::mapfile;
use pntr_service::config::Settings;
use pntr_service::{tokio, wire, Running};
use serde_json::Value;

const SCENE: &str = "synth000";

struct Fixture {
    dir: tempfile::TempDir,
    map: PathBuf,
    /// Query views of Point 0, read by the Rust reader.
    point0: Vec<View>,
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
        let mut queries = 0;
        let mut point0 = Vec::new();
        for p in &scene.points {
            let r = p.open().unwrap();
            queries += r.count(Role::Query);
            if p.index == 0 {
                for i in 0..r.count(Role::Query) {
                    point0.push(r.view(Role::Query, i).unwrap());
                }
            }
        }
        assert!(!point0.is_empty() && queries >= 6, "{queries} queries");
        Fixture {
            dir,
            map: path,
            point0,
            queries,
        }
    })
}

fn runtime() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .unwrap()
}

/// Start a server on `rt` and wait until it has loaded its map.
fn serve(rt: &tokio::runtime::Runtime, s: Settings) -> Running {
    rt.block_on(async {
        let running = pntr_service::start(s).await.unwrap();
        running.ready().await.unwrap();
        running
    })
}

fn stop(rt: &tokio::runtime::Runtime, mut running: Running) {
    rt.block_on(async {
        running.shutdown();
        running.wait().await.unwrap();
    })
}

fn script() -> PathBuf {
    pntr_tests::workspace_root().join("client/python/pntr_client.py")
}

/// Run the client with `args`, a stub cache under the fixture's folder and no token in the env.
fn client(args: &[&str]) -> Output {
    let f = fixture();
    Command::new(pntr_tests::python())
        .arg(script())
        .args(args)
        .env("PNTR_CLIENT_CACHE", f.dir.path().join("stub-cache"))
        .env_remove("PNTR_TOKEN")
        .output()
        .expect("python runs")
}

fn text(b: &[u8]) -> String {
    String::from_utf8_lossy(b).into_owned()
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
    let out_dir = f.dir.path().join("frames");
    std::fs::create_dir_all(&out_dir).unwrap();
    // The client's own functions: read Point 0 with h5py and build each request, then dump the
    // payloads for comparison with what the Rust reader and `wire::raw_request` make.
    let code = r#"
import json, sys
from pathlib import Path
sys.path.insert(0, sys.argv[1])
import pntr_client as c
pb2, _ = c.load_stubs()
out = Path(sys.argv[3])
meta = []
for i, rgb, depth, gps, quat in c.read_point(sys.argv[2]):
    r = c.make_request(pb2, rgb, depth)
    (out / f"rgb{i}").write_bytes(r.rgb.data)
    (out / f"depth{i}").write_bytes(r.depth.data)
    meta.append({"w": r.rgb.width, "h": r.rgb.height, "dw": r.depth.width, "dh": r.depth.height,
                 "enc": r.rgb.encoding, "denc": r.depth.encoding, "k": r.HasField("intrinsics"),
                 "gps": [float(v) for v in gps], "quat": [float(v) for v in quat]})
print(json.dumps(meta))
"#;
    let point0 = pntr_dataset::layout::point_path(f.dir.path(), SCENE, 0);
    let out = Command::new(pntr_tests::python())
        .arg("-c")
        .arg(code)
        .arg(script().parent().unwrap())
        .arg(&point0)
        .arg(&out_dir)
        .env("PNTR_CLIENT_CACHE", f.dir.path().join("stub-cache"))
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
}

#[test]
fn localizes_against_a_real_server() {
    let f = fixture();
    let rt = runtime();
    let running = serve(
        &rt,
        Settings::local(vec![f.map.clone()], pntr_tests::models()),
    );
    let addr = running.addr.to_string();
    let dataset = f.dir.path().to_str().unwrap();

    let doc = run_json(&[
        "--addr",
        &addr,
        "--dataset",
        dataset,
        "--scene",
        SCENE,
        "--json",
    ]);
    assert_eq!(doc["server"]["map_id"], "all");
    let queries = doc["queries"].as_array().unwrap();
    assert_eq!(queries.len(), f.queries);
    let mut good = 0;
    for q in queries {
        let status = q["status"].as_str().unwrap();
        assert!(status == "LOCALIZED" || status == "NOT_LOCALIZED", "{q}");
        if status != "LOCALIZED" {
            assert!(!q["reason"].as_str().unwrap().is_empty(), "{q}");
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
    let out = client(&[
        "--addr",
        &addr,
        "--dataset",
        dataset,
        "--scene",
        SCENE,
        "--point",
        "1",
        "--queries",
        "1",
    ]);
    assert!(out.status.success(), "{}", text(&out.stderr));
    let lines = text(&out.stdout);
    eprint!("{lines}");
    assert!(lines.contains(&format!("{SCENE}/point1/q0 ")), "{lines}");
    assert!(
        !lines.contains("/q1 ") && !lines.contains("point0"),
        "{lines}"
    );
    assert!(lines.contains("summary: "), "{lines}");

    // Missing input: the scene, a Point.
    let out = client(&[
        "--addr",
        &addr,
        "--dataset",
        dataset,
        "--scene",
        "nosuch",
        "--json",
    ]);
    assert_clean_failure(&out, 2, "scene folder not found");
    let out = client(&[
        "--addr",
        &addr,
        "--dataset",
        dataset,
        "--scene",
        SCENE,
        "--point",
        "99",
    ]);
    assert_clean_failure(&out, 2, "Point file not found");
    stop(&rt, running);

    // Nothing listens there any more.
    let closed = free_port();
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
}

/// A loopback address where nothing listens (bound, then closed).
fn free_port() -> SocketAddr {
    let l = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    l.local_addr().unwrap()
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
    let base = [
        "--addr",
        &addr,
        "--dataset",
        dataset,
        "--scene",
        SCENE,
        "--point",
        "0",
        "--queries",
        "1",
        "--tls-ca",
        ca,
        "--json",
    ];

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
    let out = client(&[
        "--addr",
        &addr,
        "--dataset",
        dataset,
        "--scene",
        SCENE,
        "--token",
        "py-t0ken",
        "--connect-timeout",
        "1",
    ]);
    assert_clean_failure(&out, 1, "cannot reach pntr-server");
    stop(&rt, running);
}
