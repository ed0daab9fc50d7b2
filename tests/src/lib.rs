//! Helpers shared by the end-to-end tests in this folder.
//!
//! These tests cross process and language boundaries (h5py, the CLI, later the gRPC server), so they
//! live in their own crate at the top of the workspace, above every library they exercise.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::process::Command;
use std::time::Duration;

use nalgebra::Isometry3;
use pntr_dataset::{DatasetIndex, Role, View};
use pntr_service::config::Settings;
use pntr_service::proto::localizer_client::LocalizerClient;
use pntr_service::proto::{self};
use pntr_service::tokio::runtime::Runtime;
use pntr_service::tonic::transport::{Channel, Endpoint};
use pntr_service::{tokio, wire, Running};

/// The Python interpreter with h5py and numpy: `$PNTR_PYTHON`, else the venv `scripts/setup.sh` makes.
///
/// Panics with the fix when it is missing: these tests check compatibility with the reference
/// tooling and must not pass silently without it.
pub fn python() -> PathBuf {
    let p = std::env::var_os("PNTR_PYTHON")
        .map(PathBuf::from)
        .map(|p| {
            if p.is_relative() {
                workspace_root().join(p)
            } else {
                p
            }
        })
        .unwrap_or_else(|| workspace_root().join(".deps/venv/bin/python"));
    let ok = Command::new(&p)
        .args(["-c", "import h5py, numpy"])
        .status()
        .is_ok_and(|s| s.success());
    assert!(
        ok,
        "{} cannot import h5py and numpy: run `bash scripts/setup.sh` (or set PNTR_PYTHON)",
        p.display()
    );
    p
}

/// The workspace root (the folder holding the top-level Cargo.toml).
pub fn workspace_root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("tests/ has a parent")
        .to_path_buf()
}

/// Run a Python script from `tests/python/` and return its stdout; panics with stderr on failure.
pub fn run_python(script: &str, args: &[&std::ffi::OsStr]) -> String {
    let out = Command::new(python())
        .arg(workspace_root().join("tests/python").join(script))
        .args(args)
        .output()
        .expect("python runs");
    assert!(
        out.status.success(),
        "{script} failed:\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8(out.stdout).expect("utf-8 output")
}

/// The preset a server answers with for a map built with `xfeat-mnn` when nothing overrides it
/// (`--backbone-precision auto`): its bf16 twin where the CPU has bfloat16 instructions and
/// OpenVINO loads, the map's own elsewhere.
pub fn served_xfeat_mnn() -> &'static str {
    if pntr_features::openvino::cpu_has_bf16() && pntr_features::openvino::init().is_ok() {
        "xfeat-mnn-bf16"
    } else {
        "xfeat-mnn"
    }
}

/// The committed ONNX models.
pub fn models() -> PathBuf {
    workspace_root().join("models")
}

/// Generate one synthetic scene (`synth000`) of `points` Points with `queries` query draws each into
/// `root`, and list it.
pub fn synthetic_dataset(
    root: &std::path::Path,
    points: usize,
    queries: usize,
    seed: u64,
) -> DatasetIndex {
    let cfg = pntr_synth::SynthConfig {
        points_per_scene: points,
        queries_per_point: queries,
        seed,
        ..Default::default()
    };
    pntr_synth::synthesize(&cfg, root, pntr_synth::plan_all(&cfg), &|| {}).expect("synthesize");
    DatasetIndex::open(root).expect("list the generated dataset")
}

/// Build the map `map_id` of every scene of `index` with the named preset and the committed models.
pub fn build_map(index: &DatasetIndex, preset: &str, map_id: &str) -> pntr_pipeline::map::Map {
    let preset = pntr_pipeline::preset::Preset::named(preset).expect("preset");
    build_map_with(index, &preset, map_id)
}

/// Build the map `map_id` of every scene of `index` with `preset` and the committed models.
pub fn build_map_with(
    index: &DatasetIndex,
    preset: &pntr_pipeline::preset::Preset,
    map_id: &str,
) -> pntr_pipeline::map::Map {
    let stage = preset
        .map_feature_config(models())
        .build()
        .expect("models load");
    let scenes: Vec<_> = index.scenes.iter().collect();
    pntr_mapping::build::build(map_id, &scenes, preset, &stage, &models(), &mut |_, _| {})
        .expect("map builds")
}

/// Every query view of the first scene of `index`, Point by Point.
pub fn query_views(index: &DatasetIndex) -> Vec<View> {
    index.scenes[0]
        .points
        .iter()
        .flat_map(|p| {
            let r = p.open().unwrap();
            (0..r.count(Role::Query)).map(move |i| r.view(Role::Query, i).unwrap())
        })
        .collect()
}

/// The first query view of the first Point of the first scene of `index`.
pub fn first_query(index: &DatasetIndex) -> View {
    index.scenes[0].points[0]
        .open()
        .unwrap()
        .view(Role::Query, 0)
        .unwrap()
}

/// A two-thread tokio runtime for tests that drive async clients and servers.
pub fn runtime() -> Runtime {
    tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .unwrap()
}

/// Start a server (the `pntr-service` library, as the binary starts it) and wait until it has loaded
/// its maps.
pub async fn start(s: Settings) -> Running {
    let running = pntr_service::start(s).await.unwrap();
    running.ready().await.unwrap();
    running
}

/// [`start`] on `rt`.
pub fn serve(rt: &Runtime, s: Settings) -> Running {
    rt.block_on(start(s))
}

/// Shut a server down and wait until it has stopped.
pub async fn stop(mut running: Running) {
    running.shutdown();
    running.wait().await.unwrap();
}

/// [`stop`] on `rt`.
pub fn stop_on(rt: &Runtime, running: Running) {
    rt.block_on(stop(running))
}

/// A plaintext gRPC channel to a server on `addr`.
pub async fn channel(addr: SocketAddr) -> Channel {
    Endpoint::from_shared(format!("http://{addr}"))
        .unwrap()
        .connect()
        .await
        .unwrap()
}

/// A Localizer client of a server on `addr` that takes answers of up to 64 MiB.
pub async fn client(addr: SocketAddr) -> LocalizerClient<Channel> {
    LocalizerClient::new(channel(addr).await).max_decoding_message_size(64 << 20)
}

/// `m` with the bearer `token` in its metadata.
pub fn authed<T>(m: T, token: &str) -> pntr_service::tonic::Request<T> {
    let mut r = pntr_service::tonic::Request::new(m);
    r.metadata_mut()
        .insert("authorization", format!("Bearer {token}").parse().unwrap());
    r
}

/// A raw-frame request for `v` in map `map_id` (empty: the server's only map).
pub fn request(v: &View, map_id: &str) -> proto::LocalizeRequest {
    proto::LocalizeRequest {
        map_id: map_id.into(),
        ..wire::raw_request(&v.rgb, &v.depth, None)
    }
}

/// How far (metres) the pose of an answer is from `truth`; `None` when it has no pose.
pub fn translation_error(r: &proto::LocalizeResponse, truth: &Isometry3<f64>) -> Option<f64> {
    let pose = wire::pose(r.pose.as_ref())?;
    Some((pose.translation.vector - truth.translation.vector).norm())
}

/// The Prometheus text a server's `/metrics` endpoint serves now (asserting it answered 200).
pub fn scrape(addr: SocketAddr) -> String {
    use std::io::{Read, Write};
    let mut s = std::net::TcpStream::connect(addr).unwrap();
    s.write_all(b"GET /metrics HTTP/1.0\r\nHost: test\r\n\r\n")
        .unwrap();
    let mut out = String::new();
    s.read_to_string(&mut out).unwrap();
    assert!(
        out.starts_with("HTTP/1.0 200") || out.starts_with("HTTP/1.1 200"),
        "{out}"
    );
    out
}

/// A loopback address where nothing listens (bound, then released).
pub fn free_addr() -> SocketAddr {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
}

/// Poll `done` every `poll` until it holds; panics with `what` after `limit`.
pub async fn wait_until(
    mut done: impl FnMut() -> bool,
    limit: Duration,
    poll: Duration,
    what: &str,
) {
    let t = std::time::Instant::now();
    while !done() {
        assert!(t.elapsed() < limit, "{what}");
        tokio::time::sleep(poll).await;
    }
}

/// Call `check` every `every` until it gives `Ok`, and return its value; once `limit` has passed,
/// panic with the message `fail` makes of the last `Err`.
pub fn retry<T, E>(
    (limit, every): (Duration, Duration),
    mut check: impl FnMut() -> Result<T, E>,
    fail: impl Fn(E) -> String,
) -> T {
    let t = std::time::Instant::now();
    loop {
        match check() {
            Ok(v) => return v,
            Err(e) if t.elapsed() >= limit => panic!("{}", fail(e)),
            Err(_) => std::thread::sleep(every),
        }
    }
}
