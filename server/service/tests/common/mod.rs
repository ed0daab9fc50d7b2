//! Helpers shared by this crate's integration tests: small maps built from synthetic scenes, the
//! `pntr-server` binary started, signalled and waited for, its health polled and its metrics read.

// Each test binary uses its own part of this module.
#![allow(dead_code)]

use std::io::{BufRead, BufReader};
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::time::{Duration, Instant};

use pntr_dataset::{DatasetIndex, Role, View};
use pntr_pipeline::{map, mapfile, preset::Preset};
use pntr_service::tonic_health::pb::health_check_response::ServingStatus;
use pntr_service::tonic_health::pb::health_client::HealthClient;
use pntr_service::tonic_health::pb::HealthCheckRequest;

/// The `pntr-server` binary under test.
pub const BIN: &str = env!("CARGO_BIN_EXE_pntr-server");

/// The ONNX models of the workspace.
pub fn models() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../models")
}

/// One synthetic scene of `points` Points with `queries` query draws each, generated into `dir`, and
/// its map `map_id` built with the `fast` preset: (the map, the dataset's index).
pub fn synthetic_map(
    dir: &Path,
    points: usize,
    queries: usize,
    seed: u64,
    map_id: &str,
) -> (map::Map, DatasetIndex) {
    synthetic_map_with(dir, points, queries, seed, map_id, "fast")
}

/// [`synthetic_map`] built with `preset`.
pub fn synthetic_map_with(
    dir: &Path,
    points: usize,
    queries: usize,
    seed: u64,
    map_id: &str,
    preset: &str,
) -> (map::Map, DatasetIndex) {
    let cfg = pntr_synth::SynthConfig {
        points_per_scene: points,
        queries_per_point: queries,
        seed,
        ..Default::default()
    };
    pntr_synth::synthesize(&cfg, dir, pntr_synth::plan_all(&cfg), &|| {}).unwrap();
    let index = DatasetIndex::open(dir).unwrap();
    let preset = Preset::named(preset).unwrap();
    let stage = preset.map_feature_config(models()).build().unwrap();
    let scenes: Vec<_> = index.scenes.iter().collect();
    let m = pntr_mapping::build::build(map_id, &scenes, &preset, &stage, &models(), &mut |_, _| {})
        .unwrap();
    (m, index)
}

/// The first query view of the first Point of the first scene.
pub fn first_query(index: &DatasetIndex) -> View {
    let point = index.scenes[0].points[0].open().unwrap();
    point.view(Role::Query, 0).unwrap()
}

/// A map `demo` (two Points) in `dir`, and one of its query views.
pub fn demo_map(dir: &Path) -> (PathBuf, View) {
    let (m, index) = synthetic_map(dir, 2, 2, 9, "demo");
    let db = dir.join("demo.pntrmap");
    mapfile::save(&m, &db).unwrap();
    (db, first_query(&index))
}

/// The Prometheus text a server's `/metrics` endpoint serves now.
pub fn scrape(addr: SocketAddr) -> String {
    use std::io::{Read, Write};
    let mut s = std::net::TcpStream::connect(addr).unwrap();
    s.write_all(b"GET /metrics HTTP/1.0\r\n\r\n").unwrap();
    let mut out = String::new();
    s.read_to_string(&mut out).unwrap();
    out
}

/// The value of the first series of `name` in scraped text (NaN when absent).
pub fn gauge(text: &str, name: &str) -> f64 {
    text.lines()
        .find(|l| l.starts_with(name))
        .and_then(|l| l.split_whitespace().last())
        .and_then(|v| v.parse().ok())
        .unwrap_or(f64::NAN)
}

/// The values of every series whose line starts with `prefix` in scraped text, summed (over the
/// labels the prefix leaves open, such as `map_id`).
pub fn sum_series(text: &str, prefix: &str) -> f64 {
    text.lines()
        .filter(|l| l.starts_with(prefix))
        .filter_map(|l| l.split_whitespace().last())
        .filter_map(|v| v.parse::<f64>().ok())
        .sum()
}

/// Poll gauge `name` of the server whose metrics are on `metrics` every `poll` until `done` holds
/// for its value; panics with `what` after `limit`.
pub async fn wait_gauge(
    metrics: SocketAddr,
    name: &str,
    done: impl Fn(f64) -> bool,
    (limit, poll): (Duration, Duration),
    what: &str,
) {
    let t = Instant::now();
    while !done(gauge(&scrape(metrics), name)) {
        assert!(t.elapsed() < limit, "{what}");
        pntr_service::tokio::time::sleep(poll).await;
    }
}

/// A two-thread tokio runtime for tests that drive async clients and servers.
pub fn runtime() -> pntr_service::tokio::runtime::Runtime {
    pntr_service::tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .unwrap()
}

/// `pntr-server` serving `db` with the models of `models`, on ephemeral gRPC and metrics ports, with
/// `extra` flags (not started).
pub fn server_command(db: &Path, models: &Path, extra: &[&str]) -> Command {
    let mut c = Command::new(BIN);
    c.arg("--db")
        .arg(db)
        .arg("--models")
        .arg(models)
        .args(["--addr", "127.0.0.1:0", "--metrics-addr", "127.0.0.1:0"])
        .args(extra);
    c
}

/// The first line a started server prints on stdout (empty when it exits first); stdout is taken.
pub fn first_line(child: &mut Child) -> String {
    let mut line = String::new();
    BufReader::new(child.stdout.take().unwrap())
        .read_line(&mut line)
        .unwrap();
    line
}

/// Start `cmd` (a server, stdout piped) and read its ready line: the server, stopped when dropped,
/// with its gRPC and metrics addresses.
pub fn spawn(cmd: &mut Command) -> (KillOnDrop, SocketAddr, SocketAddr) {
    let mut child = cmd.stdout(Stdio::piped()).spawn().unwrap();
    let line = first_line(&mut child);
    let server = KillOnDrop(child);
    // "pntr-server listening on 127.0.0.1:P metrics on 127.0.0.1:Q"
    let words: Vec<&str> = line.split_whitespace().collect();
    assert_eq!(words[..3], ["pntr-server", "listening", "on"], "{line}");
    assert_eq!(words[4..6], ["metrics", "on"], "{line}");
    let addr: SocketAddr = words[3].parse().unwrap();
    let metrics: SocketAddr = words[6].parse().unwrap();
    assert_ne!(addr.port(), 0);
    (server, addr, metrics)
}

/// Stops a server child however the test ends.
pub struct KillOnDrop(pub Child);

impl Drop for KillOnDrop {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// Send signal `name` (`TERM`, `HUP`) to `child`.
pub fn signal(child: &Child, name: &str) {
    let ok = Command::new("kill")
        .args([format!("-{name}"), child.id().to_string()])
        .status()
        .unwrap()
        .success();
    assert!(ok, "kill -{name}");
}

/// Wait until `child` exits, polling every `poll`; panics with `what` after `limit`.
pub fn wait_exit(child: &mut Child, limit: Duration, poll: Duration, what: &str) -> ExitStatus {
    let t = Instant::now();
    loop {
        if let Some(s) = child.try_wait().unwrap() {
            return s;
        }
        assert!(t.elapsed() < limit, "{what}");
        std::thread::sleep(poll);
    }
}

/// A plaintext gRPC channel to a server on `addr`.
pub async fn channel(addr: SocketAddr) -> pntr_service::tonic::transport::Channel {
    pntr_service::tonic::transport::Endpoint::from_shared(format!("http://{addr}"))
        .unwrap()
        .connect()
        .await
        .unwrap()
}

/// The status the health service at `url` reports now, `None` when it cannot be reached or does not
/// answer.
pub async fn health(url: &str) -> Option<i32> {
    let channel = pntr_service::tonic::transport::Endpoint::from_shared(url.to_string())
        .unwrap()
        .connect()
        .await
        .ok()?;
    HealthClient::new(channel)
        .check(HealthCheckRequest::default())
        .await
        .map(|r| r.into_inner().status)
        .ok()
}

/// Poll health until SERVING (panics when it cannot be reached, or after 120 s).
pub async fn wait_serving(url: &str) {
    let t = Instant::now();
    loop {
        let s = health(url).await.expect("the health service answers");
        if s == ServingStatus::Serving as i32 {
            return;
        }
        assert!(t.elapsed() < Duration::from_secs(120), "never SERVING");
        pntr_service::tokio::time::sleep(Duration::from_millis(20)).await;
    }
}
