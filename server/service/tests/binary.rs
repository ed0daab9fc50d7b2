//! The `pntr-server` binary itself: refuses bad settings with exit code 2, prints the bound ports on
//! one stdout line, bounds the streams of one connection, closes connections whose peer stopped
//! answering keep-alive PINGs, serves a map with another preset of the same descriptors (`--preset`),
//! says why a frame is NOT_LOCALIZED (its cause, in the answer and the metrics), and on SIGTERM
//! refuses new requests, finishes the ones it holds and exits 0.

use std::net::SocketAddr;
use std::process::Command;
use std::time::{Duration, Instant};

use pntr_service::proto::localizer_client::LocalizerClient;
use pntr_service::tokio;
use pntr_service::wire;

mod common;
use common::{gauge, models, runtime, scrape, wait_serving, KillOnDrop, BIN};

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

/// Start `pntr-server` on `db` with ephemeral ports and `extra` flags; returns it with its gRPC and
/// metrics addresses (read from the line it prints).
fn spawn(db: &std::path::Path, extra: &[&str]) -> (KillOnDrop, SocketAddr, SocketAddr) {
    common::spawn(common::server_command(db, &models(), extra).env("PNTR_LOG", "warn"))
}

/// Fire `n` requests at once, spread over `channels` connections, and return the most requests the
/// server held at any time (its in-flight gauge, polled) and how many were answered.
async fn burst(
    url: &str,
    metrics: SocketAddr,
    channels: usize,
    n: usize,
    req: &pntr_service::proto::LocalizeRequest,
) -> (f64, usize) {
    let mut clients = Vec::new();
    for _ in 0..channels {
        let mut c = LocalizerClient::connect(url.to_string()).await.unwrap();
        // One call first, so the server's SETTINGS frame (with its stream limit) has reached the
        // client: streams opened before that may be refused (REFUSED_STREAM, safe to retry).
        c.get_map_info(pntr_service::proto::GetMapInfoRequest::default())
            .await
            .unwrap();
        clients.push(c);
    }
    let mut calls = tokio::task::JoinSet::new();
    for i in 0..n {
        let (mut c, r) = (clients[i % channels].clone(), req.clone());
        calls.spawn(async move { c.localize(r).await.map(|_| ()) });
    }
    let (mut peak, mut answered) = (0.0f64, 0);
    while !calls.is_empty() {
        peak = peak.max(gauge(&scrape(metrics), "pntr_in_flight_requests"));
        while let Some(done) = calls.try_join_next() {
            match done.unwrap() {
                Ok(()) => answered += 1,
                Err(e) => eprintln!("call failed: {e:?}"),
            }
        }
        tokio::time::sleep(Duration::from_millis(1)).await;
    }
    (peak, answered)
}

#[test]
fn one_connection_holds_at_most_max_streams_per_connection() {
    let dir = tempfile::tempdir().unwrap();
    let (db, query) = common::demo_map(dir.path());
    let (_server, addr, metrics) = spawn(
        &db,
        &[
            "--workers",
            "2",
            "--queue",
            "32",
            "--max-streams-per-connection",
            "2",
        ],
    );
    let req = wire::raw_request(&query.rgb, &query.depth, None);
    runtime().block_on(async {
        let url = format!("http://{addr}");
        wait_serving(&url).await;
        // Eight calls on one connection: the client waits for stream credit, so the server never
        // holds more than two of them, and all eight are answered.
        let (peak, ok) = burst(&url, metrics, 1, 8, &req).await;
        assert_eq!(ok, 8);
        assert!(peak <= 2.0, "one connection held {peak} requests at once");
        // The limit is per connection: over four connections the same burst is held at once.
        let (peak, ok) = burst(&url, metrics, 4, 8, &req).await;
        assert_eq!(ok, 8);
        assert!(peak > 2.0, "four connections never held more than {peak}");
    });
}

#[cfg(unix)]
#[test]
fn a_map_is_served_with_another_preset_of_the_same_descriptors() {
    let dir = tempfile::tempdir().unwrap();
    // Built with `fast` (XFeat, LighterGlue); served with MNN and the int8 backbone, or the float
    // one in bfloat16 on OpenVINO, no rebuild.
    let (db, _) = common::demo_map(dir.path());
    for (preset, extractor) in [
        ("xfeat-mnn-int8", "xfeat-int8"),
        ("xfeat-mnn-bf16", "xfeat-bf16"),
    ] {
        let (info, sent, right) = served(&db, &["--workers", "1", "--preset", preset], dir.path());
        assert_eq!(
            (info.preset.as_str(), info.built_preset.as_str()),
            (preset, "fast")
        );
        assert_eq!(
            (info.extractor.as_str(), info.matcher.as_str()),
            (extractor, "mnn")
        );
        // int8 on ONNX Runtime's CPU provider; bf16 on OpenVINO (f32 where the CPU lacks bf16).
        let engines: &[&str] = match preset {
            "xfeat-mnn-int8" => &["cpu"],
            _ => &["openvino-bf16", "openvino-f32"],
        };
        assert!(
            engines.contains(&info.extractor_engine.as_str()),
            "{info:?}"
        );
        // Every query of the scene: the answers given are right, and most queries get one (this
        // tiny two-Point map leaves one of its three queries without enough MNN matches).
        assert!(
            sent >= 3 && right * 3 >= sent * 2,
            "{preset}: {right} of {sent} localized"
        );
    }
    // A preset of other descriptors (ORB, bag of words) cannot use this map: a setting error (exit
    // 2) before anything is bound, naming both presets and the ones that can.
    let out = common::server_command(&db, &models(), &["--preset", "classical"])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stdout).is_empty());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("preset fast") && err.contains("classical") && err.contains("xfeat-mnn-int8"),
        "{err}"
    );
    // An unknown preset is a setting error (exit 2) before any map is read.
    let out = Command::new(BIN)
        .arg("--db")
        .arg(&db)
        .args(["--preset", "xfeat-mnn-int4"])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).contains("--preset"));
}

/// The answers of a served map over its scene's queries: (sent, LOCALIZED within 0.25 m).
async fn right_answers(
    c: &mut LocalizerClient<pntr_service::tonic::transport::Channel>,
    dataset: &std::path::Path,
) -> (usize, usize) {
    let index = pntr_dataset::DatasetIndex::open(dataset).unwrap();
    let (mut sent, mut right) = (0, 0);
    for point in &index.scenes[0].points {
        let p = point.open().unwrap();
        for i in 0..p.count(pntr_dataset::Role::Query) {
            let v = p.view(pntr_dataset::Role::Query, i).unwrap();
            let r = c
                .localize(wire::raw_request(&v.rgb, &v.depth, None))
                .await
                .unwrap()
                .into_inner();
            sent += 1;
            if r.status == pntr_service::proto::Status::Localized as i32 {
                let pose = wire::pose(r.pose.as_ref()).unwrap();
                let e = (pose.translation.vector - v.world_from_camera.translation.vector).norm();
                assert!(e < 0.25, "{e} m off: {r:?}");
                right += 1;
            }
        }
    }
    (sent, right)
}

/// `pntr-server` started on `db` with `args`: its GetMapInfo, and its answers to the queries of the
/// scene in `dataset` ([`right_answers`]: sent, LOCALIZED within 0.25 m). The server stops after.
fn served(
    db: &std::path::Path,
    args: &[&str],
    dataset: &std::path::Path,
) -> (pntr_service::proto::MapInfo, usize, usize) {
    let (_server, addr, _) = spawn(db, args);
    runtime().block_on(async {
        let url = format!("http://{addr}");
        wait_serving(&url).await;
        let mut c = LocalizerClient::connect(url).await.unwrap();
        let info = c
            .get_map_info(pntr_service::proto::GetMapInfoRequest::default())
            .await
            .unwrap()
            .into_inner();
        let (sent, right) = right_answers(&mut c, dataset).await;
        (info, sent, right)
    })
}

#[cfg(unix)]
#[test]
fn an_xfeat_mnn_map_runs_the_bf16_backbone_where_the_cpu_has_bf16_instructions() {
    let dir = tempfile::tempdir().unwrap();
    let (m, _) = common::synthetic_map_with(dir.path(), 3, 2, 9, "mnn", "xfeat-mnn");
    let db = dir.path().join("mnn.pntrmap");
    pntr_pipeline::mapfile::save(&m, &db).unwrap();
    // By default (`--backbone-precision auto`) a CPU with AVX-512 BF16 runs the map's bf16 twin on
    // OpenVINO, any other the float backbone on ONNX Runtime; `f32` keeps the float one anywhere.
    let bf16 = pntr_features::openvino::cpu_has_bf16();
    for (flags, expected) in [
        (
            &[][..],
            if bf16 {
                ("xfeat-mnn-bf16", "openvino-bf16")
            } else {
                ("xfeat-mnn", "cpu")
            },
        ),
        (&["--backbone-precision", "f32"][..], ("xfeat-mnn", "cpu")),
    ] {
        let mut args = vec!["--workers", "1"];
        args.extend_from_slice(flags);
        let (info, sent, right) = served(&db, &args, dir.path());
        assert_eq!(
            (
                info.preset.as_str(),
                info.extractor_engine.as_str(),
                info.built_preset.as_str()
            ),
            (expected.0, expected.1, "xfeat-mnn"),
            "{flags:?} (CPU with bf16: {bf16})"
        );
        assert!(
            sent >= 6 && right * 3 >= sent * 2,
            "{flags:?}: {right} of {sent} localized"
        );
    }
    // Another value is a setting error (exit 2) naming the two there are.
    let out = common::server_command(&db, &models(), &["--backbone-precision", "half"])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("`half`") && err.contains("auto") && err.contains("f32"),
        "{err}"
    );
}

#[test]
fn sigterm_refuses_new_requests_drains_held_ones_and_exits_zero() {
    let dir = tempfile::tempdir().unwrap();
    let (db, query) = common::demo_map(dir.path());

    // A queue of 8: the five held requests must all be taken whether or not the worker has picked
    // up the first when the fifth arrives (with the default 4 x workers the fifth was sometimes
    // refused as RESOURCE_EXHAUSTED, a race of the test, not of the drain).
    let (mut server, addr, metrics) = spawn(
        &db,
        &["--workers", "1", "--queue", "8", "--drain-timeout-s", "60"],
    );
    let rt = runtime();
    rt.block_on(async {
        let url = format!("http://{addr}");
        wait_serving(&url).await;
        let c = LocalizerClient::connect(url.clone()).await.unwrap();
        let req = wire::raw_request(&query.rgb, &query.depth, None);
        // Five requests held (one running on the only worker, the others queued), then SIGTERM.
        let mut held = tokio::task::JoinSet::new();
        for _ in 0..5 {
            let (mut c, r) = (c.clone(), req.clone());
            held.spawn(async move { c.localize(r).await });
        }
        common::wait_gauge(
            metrics,
            "pntr_in_flight_requests",
            |g| g == 5.0,
            (Duration::from_secs(30), Duration::from_millis(1)),
            "the requests never arrived",
        )
        .await;
        common::signal(&server.0, "TERM");
        // A new request is refused while those five still drain.
        let t = Instant::now();
        let mut answered = Vec::new();
        loop {
            let probe = async {
                let Ok(channel) =
                    pntr_service::tonic::transport::Endpoint::from_shared(url.clone())
                        .unwrap()
                        .connect_timeout(Duration::from_secs(1))
                        .connect()
                        .await
                else {
                    return true; // the listener is closed
                };
                let mut r = pntr_service::tonic::Request::new(req.clone());
                r.set_timeout(Duration::from_millis(200));
                matches!(
                    LocalizerClient::new(channel).localize(r).await,
                    Err(e) if e.code() == pntr_service::tonic::Code::Unavailable
                )
            };
            let refused = probe.await;
            while let Some(done) = held.try_join_next() {
                answered.push(done.unwrap());
            }
            if refused {
                assert!(
                    !held.is_empty(),
                    "new requests were refused only after the drain had finished"
                );
                break;
            }
            assert!(
                t.elapsed() < Duration::from_secs(10),
                "new requests still accepted after SIGTERM"
            );
        }
        // And every held request is answered.
        while let Some(done) = held.join_next().await {
            answered.push(done.unwrap());
        }
        assert_eq!(answered.len(), 5);
        for r in answered {
            let r = r.expect("a held request is answered during the drain");
            assert_eq!(r.into_inner().map_id, "demo");
        }
    });
    let status = common::wait_exit(
        &mut server.0,
        Duration::from_secs(60),
        Duration::from_millis(20),
        "did not exit after SIGTERM",
    );
    assert_eq!(status.code(), Some(0), "{status:?}");
}

/// Open a raw HTTP/2 connection that never answers anything, and watch it for `watch`: returns whether
/// the server sent a PING and whether it closed the connection.
fn silent_http2_peer(addr: SocketAddr, watch: Duration) -> (bool, bool) {
    use std::io::{Read, Write};
    let mut s = std::net::TcpStream::connect(addr).unwrap();
    // Client preface and an empty SETTINGS frame; after that, silence: no SETTINGS ack, no PING ack.
    s.write_all(b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n").unwrap();
    s.write_all(&[0, 0, 0, 4, 0, 0, 0, 0, 0]).unwrap();
    let (mut buf, mut pinged) = (Vec::new(), false);
    let t = Instant::now();
    while t.elapsed() < watch {
        s.set_read_timeout(Some(Duration::from_millis(200)))
            .unwrap();
        let mut chunk = [0u8; 4096];
        match s.read(&mut chunk) {
            Ok(0) => return (pinged, true),
            Ok(n) => buf.extend_from_slice(&chunk[..n]),
            Err(e)
                if matches!(
                    e.kind(),
                    std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                ) => {}
            Err(_) => return (pinged, true), // reset
        }
        // Frames: 3-byte length, type, flags, 4-byte stream id, payload. Type 6 is PING.
        while buf.len() >= 9 {
            let len = u32::from_be_bytes([0, buf[0], buf[1], buf[2]]) as usize;
            if buf.len() < 9 + len {
                break;
            }
            pinged |= buf[3] == 6 && buf[4] & 1 == 0;
            buf.drain(..9 + len);
        }
    }
    (pinged, false)
}

#[test]
fn keepalive_pings_close_connections_whose_peer_is_gone() {
    let dir = tempfile::tempdir().unwrap();
    let (db, _) = common::demo_map(dir.path());
    // A peer that stops answering is found by the unanswered PING and its connection closed.
    let (_server, addr, _) = spawn(
        &db,
        &[
            "--keepalive-interval-s",
            "0.5",
            "--keepalive-timeout-s",
            "0.5",
        ],
    );
    let (pinged, closed) = silent_http2_peer(addr, Duration::from_secs(30));
    assert!(pinged && closed, "pinged {pinged}, closed {closed}");
    // With the PINGs turned off, the same silent peer keeps its connection.
    let (_server, addr, _) = spawn(&db, &["--keepalive-interval-s", "0"]);
    let (pinged, closed) = silent_http2_peer(addr, Duration::from_secs(3));
    assert!(!pinged && !closed, "pinged {pinged}, closed {closed}");
}

#[test]
fn not_localized_answers_say_their_cause_in_the_answer_and_the_metrics() {
    let dir = tempfile::tempdir().unwrap();
    let (db, query) = common::demo_map(dir.path());
    let (_server, addr, metrics) = spawn(&db, &[]);
    let url = format!("http://{addr}");
    runtime().block_on(wait_serving(&url));
    // The map's own view, and the same frame with depth on a 4x4 corner only: no pose can be had
    // from it (too few keypoints on valid depth), whatever the map.
    let mut starved = query.depth.clone();
    let w = starved.width as usize;
    for (i, d) in starved.data.iter_mut().enumerate() {
        if !(i % w < 4 && i / w < 4) {
            *d = 0.0;
        }
    }
    let (good, bad) = runtime().block_on(async {
        let mut c = LocalizerClient::connect(url).await.unwrap();
        let good = c
            .localize(wire::raw_request(&query.rgb, &query.depth, None))
            .await
            .unwrap()
            .into_inner();
        let bad = c
            .localize(wire::raw_request(&query.rgb, &starved, None))
            .await
            .unwrap()
            .into_inner();
        (good, bad)
    });
    use pntr_service::proto::{NotLocalizedCause, Status};
    // A LOCALIZED answer has no cause; a NOT_LOCALIZED one always has one.
    assert_eq!(
        good.status == Status::Localized as i32,
        good.cause == NotLocalizedCause::Unspecified as i32,
        "{good:?}"
    );
    assert_eq!(bad.status, Status::NotLocalized as i32, "{bad:?}");
    assert_eq!(bad.cause, NotLocalizedCause::BadInput as i32, "{bad:?}");
    assert!(bad.reason.starts_with("input: only "), "{}", bad.reason);
    let text = scrape(metrics);
    let counted = |cause: &str| {
        text.lines()
            .find(|l| {
                l.starts_with("pntr_requests_total{")
                    && l.contains("status=\"NOT_LOCALIZED\"")
                    && l.contains(&format!("cause=\"{cause}\""))
            })
            .and_then(|l| l.rsplit(' ').next())
            .and_then(|v| v.parse::<f64>().ok())
    };
    assert_eq!(counted("BAD_INPUT"), Some(1.0), "{text}");
}
