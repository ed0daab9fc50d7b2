//! The `pntr-server` binary itself: refuses bad settings with exit code 2, prints the bound ports on
//! one stdout line, and on SIGTERM finishes an in-flight request and exits 0.

use std::io::{BufRead, BufReader, Read, Write};
use std::net::SocketAddr;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use pntr_service::proto::localizer_client::LocalizerClient;
use pntr_service::tokio;
use pntr_service::tonic_health::pb::health_check_response::ServingStatus;
use pntr_service::tonic_health::pb::health_client::HealthClient;
use pntr_service::tonic_health::pb::HealthCheckRequest;
use pntr_service::wire;

const BIN: &str = env!("CARGO_BIN_EXE_pntr-server");

mod common;
use common::models;

#[test]
fn bad_settings_exit_2_with_the_reason() {
    // A config file that names no map: refused at start.
    let dir = tempfile::tempdir().unwrap();
    let cfg = dir.path().join("server.toml");
    std::fs::write(&cfg, "workers = 1\n").unwrap();
    let out = Command::new(BIN)
        .args(["--addr", "127.0.0.1:0", "--config"])
        .arg(&cfg)
        .env_remove("PNTR_DB")
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("no --db given"), "{err}");
    // No map anywhere: the embedded default, which needs the models and says so when they are missing.
    let out = Command::new(BIN)
        .args(["--addr", "127.0.0.1:0", "--models", "/nonexistent/models"])
        .env_remove("PNTR_DB")
        .env_remove("PNTR_CONFIG")
        .env("PNTR_DEMO_DIR", dir.path())
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("demo map could not be made") && err.contains("/nonexistent/models"),
        "{err}"
    );
    let out = Command::new(BIN)
        .args(["--db", "/nonexistent/map.pntrmap"])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).contains("/nonexistent/map.pntrmap"));
}

fn scrape(addr: SocketAddr) -> String {
    let mut s = std::net::TcpStream::connect(addr).unwrap();
    s.write_all(b"GET /metrics HTTP/1.0\r\n\r\n").unwrap();
    let mut out = String::new();
    s.read_to_string(&mut out).unwrap();
    out
}

#[cfg(unix)]
#[test]
fn sigterm_drains_in_flight_and_exits_zero() {
    let dir = tempfile::tempdir().unwrap();
    let (db, query) = common::demo_map(dir.path());

    let mut child = Command::new(BIN)
        .arg("--db")
        .arg(&db)
        .arg("--models")
        .arg(models())
        .args(["--addr", "127.0.0.1:0", "--metrics-addr", "127.0.0.1:0"])
        .args(["--workers", "1", "--drain-timeout-s", "60"])
        .env("PNTR_LOG", "warn")
        .stdout(Stdio::piped())
        .spawn()
        .unwrap();
    let mut line = String::new();
    BufReader::new(child.stdout.take().unwrap())
        .read_line(&mut line)
        .unwrap();
    // "pntr-server listening on 127.0.0.1:P metrics on 127.0.0.1:Q"
    let words: Vec<&str> = line.split_whitespace().collect();
    assert_eq!(words[..3], ["pntr-server", "listening", "on"], "{line}");
    assert_eq!(words[4..6], ["metrics", "on"], "{line}");
    let addr: SocketAddr = words[3].parse().unwrap();
    let metrics: SocketAddr = words[6].parse().unwrap();
    assert_ne!(addr.port(), 0);

    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .unwrap();
    rt.block_on(async {
        let url = format!("http://{addr}");
        let t = Instant::now();
        loop {
            let channel = pntr_service::tonic::transport::Endpoint::from_shared(url.clone())
                .unwrap()
                .connect()
                .await
                .unwrap();
            let s = HealthClient::new(channel)
                .check(HealthCheckRequest::default())
                .await
                .unwrap()
                .into_inner()
                .status;
            if s == ServingStatus::Serving as i32 {
                break;
            }
            assert!(t.elapsed() < Duration::from_secs(120), "never SERVING");
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        let mut c = LocalizerClient::connect(url).await.unwrap();
        let req = wire::raw_request(&query.rgb, &query.depth, None);
        let in_flight = tokio::spawn(async move { c.localize(req).await });
        // Wait until the server holds the request, then ask it to stop.
        let t = Instant::now();
        while !scrape(metrics).contains("pntr_in_flight_requests 1") {
            assert!(
                t.elapsed() < Duration::from_secs(30),
                "the request never arrived"
            );
            tokio::time::sleep(Duration::from_millis(1)).await;
        }
        let killed = Command::new("kill")
            .args(["-TERM", &child.id().to_string()])
            .status()
            .unwrap();
        assert!(killed.success());
        let r = in_flight
            .await
            .unwrap()
            .expect("the in-flight request is answered during the drain")
            .into_inner();
        assert_eq!(r.map_id, "demo");
    });
    let t = Instant::now();
    let status = loop {
        if let Some(s) = child.try_wait().unwrap() {
            break s;
        }
        assert!(
            t.elapsed() < Duration::from_secs(60),
            "did not exit after SIGTERM"
        );
        std::thread::sleep(Duration::from_millis(20));
    };
    assert_eq!(status.code(), Some(0), "{status:?}");
}
