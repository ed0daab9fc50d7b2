//! A small map built from a synthetic scene, for this crate's integration tests.

use std::path::PathBuf;

use pntr_dataset::{DatasetIndex, Role, View};
use pntr_pipeline::{map, mapfile, preset::Preset};

/// The ONNX models of the workspace.
pub fn models() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../models")
}

/// A map `demo` (two Points) in `dir`, and one of its query views.
pub fn demo_map(dir: &std::path::Path) -> (PathBuf, View) {
    let cfg = pntr_synth::SynthConfig {
        points_per_scene: 2,
        queries_per_point: 2,
        seed: 9,
        ..Default::default()
    };
    pntr_synth::synthesize(&cfg, dir, pntr_synth::plan_all(&cfg), &|| {}).unwrap();
    let index = DatasetIndex::open(dir).unwrap();
    let preset = Preset::named("fast").unwrap();
    let stage = preset.feature_config(models()).build().unwrap();
    let scenes: Vec<_> = index.scenes.iter().collect();
    let m = map::build("demo", &scenes, &preset, &stage, &models(), &mut |_, _| {}).unwrap();
    let db = dir.join("demo.pntrmap");
    mapfile::save(&m, &db).unwrap();
    let query = index.scenes[0].points[0]
        .open()
        .unwrap()
        .view(Role::Query, 0)
        .unwrap();
    (db, query)
}

/// The Prometheus text a server's `/metrics` endpoint serves now.
#[allow(dead_code)] // not every test file scrapes
pub fn scrape(addr: std::net::SocketAddr) -> String {
    use std::io::{Read, Write};
    let mut s = std::net::TcpStream::connect(addr).unwrap();
    s.write_all(b"GET /metrics HTTP/1.0\r\n\r\n").unwrap();
    let mut out = String::new();
    s.read_to_string(&mut out).unwrap();
    out
}

/// The value of the first series of `name` in scraped text (NaN when absent).
#[allow(dead_code)] // not every test file scrapes
pub fn gauge(text: &str, name: &str) -> f64 {
    text.lines()
        .find(|l| l.starts_with(name))
        .and_then(|l| l.split_whitespace().last())
        .and_then(|v| v.parse().ok())
        .unwrap_or(f64::NAN)
}

/// A two-thread tokio runtime for tests that drive async clients and servers.
#[allow(dead_code)] // not every test file needs one
pub fn runtime() -> pntr_service::tokio::runtime::Runtime {
    pntr_service::tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .unwrap()
}
