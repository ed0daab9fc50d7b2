//! The client commands against a real `pntr-server` started in this process on 127.0.0.1 (ephemeral
//! port) with a map built by `pntr build-db` from a scene generated here: `pntr localize`, `pntr bench`
//! (closed loop, open loop, sweep, robots, the soak), `pntr eval --remote`, and the token check.

mod support;

use pntr_service::config::Settings;
use support::{build_db, ok, ok_json, pntr, read_json, runtime, serve, stop, synth, MODELS};

#[test]
fn localize_bench_and_remote_eval_against_a_live_server() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().to_str().unwrap();
    synth(dir.path(), "3", "3", &["--seed", "12"]);
    let map = dir.path().join("m.pntrmap");
    build_db(&map, &["--dataset", root, "--scene", "synth000"]);

    let rt = runtime();
    let mut open = Settings::local(vec![map.clone()], MODELS.into());
    open.workers = 2;
    let mut locked = open.clone();
    locked.token = Some("s3cret".into());
    let second = open.clone();
    // A TLS server with a certificate for localhost signed by a CA made here.
    let mut ca_params = rcgen::CertificateParams::new(Vec::<String>::new()).unwrap();
    ca_params.is_ca = rcgen::IsCa::Ca(rcgen::BasicConstraints::Unconstrained);
    let ca_key = rcgen::KeyPair::generate().unwrap();
    let ca_pem = ca_params.self_signed(&ca_key).unwrap().pem();
    let issuer = rcgen::Issuer::new(ca_params, ca_key);
    let leaf_key = rcgen::KeyPair::generate().unwrap();
    let leaf = rcgen::CertificateParams::new(vec!["localhost".to_string()])
        .unwrap()
        .signed_by(&leaf_key, &issuer)
        .unwrap();
    let (cert, key, ca) = (
        dir.path().join("cert.pem"),
        dir.path().join("key.pem"),
        dir.path().join("ca.pem"),
    );
    std::fs::write(&cert, leaf.pem()).unwrap();
    std::fs::write(&key, leaf_key.serialize_pem()).unwrap();
    std::fs::write(&ca, ca_pem).unwrap();
    let mut tls = locked.clone();
    tls.tls = Some((cert, key));
    let [a, b, c, t] = serve(&rt, [open, locked, second, tls]);
    let addr = a.addr.to_string();
    // `pntr localize` of the scene's queries and `pntr bench` of the dataset, through the server(s)
    // at `addr`, with further arguments.
    let localize = |addr: &str, extra: &[&str]| {
        let args = [
            "localize",
            "--addr",
            addr,
            "--dataset",
            root,
            "--scene",
            "synth000",
        ];
        pntr(&[&args[..], extra].concat())
    };
    let bench = |addr: &str, extra: &[&str]| {
        pntr(&[&["bench", "--addr", addr, "--dataset", root][..], extra].concat())
    };

    // Verification turns some right poses away (symmetric rooms); most of the first queries pass.
    let answers: Vec<serde_json::Value> = (0..6)
        .map(|q| {
            let q = q.to_string();
            ok_json(&localize(&addr, &["--query", &q, "--json"]))
        })
        .collect();
    for v in &answers {
        if v["status"] == "NOT_LOCALIZED" {
            assert!(v["covariance"].is_null() && v["pose"].is_null(), "{v}");
            assert!(v["reason"].as_str().unwrap().contains(':'), "{v}");
        }
    }
    let localized: Vec<&serde_json::Value> = answers
        .iter()
        .filter(|v| v["status"] == "LOCALIZED")
        .collect();
    assert!(localized.len() >= 3, "{answers:?}");
    let v = localized[0];
    assert!(
        v["ground_truth"]["translation_error_m"].as_f64().unwrap() < 0.25,
        "{v}"
    );
    assert_eq!(v["pose"]["rotation_wxyz"].as_array().unwrap().len(), 4);
    // The covariance robots fuse: 36 numbers, symmetric, positive variances (ROS order).
    let cov: Vec<f64> = v["covariance"]
        .as_array()
        .unwrap_or_else(|| panic!("no covariance: {v}"))
        .iter()
        .map(|x| x.as_f64().unwrap())
        .collect();
    assert_eq!(cov.len(), 36);
    for r in 0..6 {
        assert!(cov[r * 7] > 0.0, "{cov:?}");
        for c in 0..6 {
            assert!((cov[r * 6 + c] - cov[c * 6 + r]).abs() <= 1e-12 * cov[r * 7].max(cov[c * 7]));
        }
    }
    // A LOCALIZED answer is at least as confident as the threshold the server reports.
    let conf = v["confidence"].as_f64().unwrap();
    let threshold = v["min_confidence"].as_f64().unwrap();
    assert!(threshold >= 0.5 && conf >= threshold && conf <= 1.0, "{v}");
    for s in [
        "queue",
        "resampling",
        "extraction",
        "retrieval",
        "matching",
        "registration",
        "verification",
        "total",
    ] {
        assert!(v["stage_ms"][s].as_f64().is_some(), "stage {s}: {v}");
    }

    // Closed loop.
    let report = dir.path().join("bench.json");
    let plots = dir.path().join("plots");
    // `pntr bench` writing its report, with `extra` arguments: its stdout.
    let bench_report = |addr: &str, extra: &[&str]| {
        let json = ["--json", report.to_str().unwrap()];
        ok(&bench(addr, &[extra, &json].concat()))
    };
    // A short run: no warm-up, three frames.
    let brief = |duration| ["--duration", duration, "--warmup", "0", "--frames", "3"];
    let out = bench_report(
        &addr,
        &[
            "--concurrency",
            "2",
            "--duration",
            "2",
            "--warmup",
            "0.5",
            "--frames",
            "5",
        ],
    );
    assert!(out.contains("p99 ms"), "{out}");
    let r = read_json(&report);
    assert!(r["requests"].as_u64().unwrap() >= 2, "{r}");
    assert_eq!(r["errors"], 0, "{r}");
    assert!(r["fps"].as_f64().unwrap() > 0.0);
    for k in ["p50", "p90", "p99", "max"] {
        assert!(r["latency_ms"][k].as_f64().unwrap() > 0.0, "{k}: {r}");
    }
    assert!(r["latency_ms"]["p50"].as_f64() <= r["latency_ms"]["max"].as_f64());
    assert!(r["errors_by_code"].as_object().unwrap().is_empty());
    assert!(r["stage_ms"]["total"].as_f64().unwrap() > 0.0, "{r}");
    assert!(r["localized_share"].as_f64().unwrap() >= 0.5, "{r}");

    // Open loop and a sweep.
    let out = bench_report(&addr, &[&["--rate", "4"][..], &brief("1.5")].concat());
    assert!(out.contains("4/s"), "{out}");
    assert!(read_json(&report)["requests"].as_u64().unwrap() >= 5);
    bench_report(
        &addr,
        &[
            &brief("1")[..],
            &["--sweep", "1,2", "--plot", plots.to_str().unwrap()],
        ]
        .concat(),
    );
    let sweep = read_json(&report)["sweep"].as_array().unwrap().clone();
    support::assert_picture(
        &plots,
        "bench_sweep",
        (1200, 560),
        &[
            "frames per second",
            "latency (ms)",
            "concurrent clients",
            "p99",
        ],
    );
    // The service's overhead, measured against the in-process pipeline on the same frames.
    bench_report(
        &addr,
        &[
            &brief("0.5")[..],
            &["--compare-in-process", map.to_str().unwrap()],
            &["--models", MODELS],
        ]
        .concat(),
    );
    let o = &read_json(&report)["overhead"];
    assert_eq!(o["pairs"], 3, "{o}");
    assert!(
        o["ratio"].as_f64().unwrap() > 0.0 && o["in_process_ms_mean"].as_f64().unwrap() > 0.0,
        "{o}"
    );
    assert_eq!(sweep.len(), 2);
    assert_eq!(sweep[1]["concurrency"], 2);

    // Client-side balancing over two replicas, and a clear error when one is down.
    let both = format!("{addr},{}", c.addr);
    bench_report(
        &both,
        &[&["--concurrency", "2"][..], &brief("1.5")].concat(),
    );
    assert_eq!(read_json(&report)["errors"], 0);
    let out = bench(&format!("{addr},127.0.0.1:9"), &["--duration", "1"]);
    assert!(String::from_utf8_lossy(&out.stderr)
        .contains("cannot reach pntr-server at http://127.0.0.1:9"));

    // The evaluation through the server has the same keys as in process.
    let eval = dir.path().join("eval.json");
    ok(&pntr(&[
        "eval",
        "--dataset",
        root,
        "--remote",
        &addr,
        "--queries",
        "4",
        "--json",
        eval.to_str().unwrap(),
    ]));
    let e = read_json(&eval);
    assert_eq!(e["queries"], 4);
    assert!(e["recall"]["1m"].as_f64().unwrap() >= 0.5, "{e}");

    // The token: refused without it (a clean error naming the code), accepted with it.
    let locked_addr = b.addr.to_string();
    let out = localize(&locked_addr, &["--query", "0"]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("UNAUTHENTICATED") && !err.contains("panicked"),
        "{err}"
    );
    ok(&localize(
        &locked_addr,
        &["--token", "s3cret", "--query", "0"],
    ));
    // TLS with the token, end to end with `pntr`; without the CA the handshake fails cleanly.
    let tls_addr = t.addr.to_string();
    let v = ok_json(&localize(
        &tls_addr,
        &[
            "--tls-ca",
            ca.to_str().unwrap(),
            "--tls-domain",
            "localhost",
            "--token",
            "s3cret",
            "--query",
            "1",
            "--json",
        ],
    ));
    assert_eq!(v["status"], "LOCALIZED", "{v}");
    let out = localize(&tls_addr, &["--token", "s3cret", "--query", "1"]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && !err.contains("panicked"));
    // The plaintext client is told the server expects TLS (not only "transport error").
    assert!(
        err.contains("expects TLS") && err.contains("--tls-ca"),
        "{err}"
    );
    // A closed port is a clear error.
    let out = localize("127.0.0.1:9", &["--query", "0"]);
    assert!(String::from_utf8_lossy(&out.stderr).contains("cannot reach pntr-server"));

    stop(&rt, [a, b, c, t]);
}

/// `pntr bench --robots`: LocalizeStreams that leave and come back; `pntr bench --soak`: its phases
/// one after another against a live server whose memory it reads from /metrics, a map replaced in
/// the `replace` phase, every reading in the JSON and the picture drawn; and what it refuses.
#[test]
fn robots_and_a_soak_against_a_live_server() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().to_str().unwrap();
    synth(dir.path(), "3", "3", &["--seed", "14"]);
    let map = dir.path().join("m.pntrmap");
    build_db(&map, &["--dataset", root, "--scene", "synth000"]);
    let rebuilt = dir.path().join("m-rebuilt.pntrmap");
    std::fs::copy(&map, &rebuilt).unwrap();

    let rt = runtime();
    let mut settings = Settings::local(vec![map.clone()], MODELS.into());
    settings.workers = 2;
    settings.admin_token = Some("soak-admin".into());
    let [server] = serve(&rt, [settings]);
    let (addr, metrics) = (server.addr.to_string(), server.metrics_addr.to_string());
    let bench = |extra: &[&str]| {
        pntr(&[&["bench", "--addr", &addr, "--dataset", root][..], extra].concat())
    };

    // Two robots, each leaving after 3 frames and coming back on a new stream.
    let report = dir.path().join("robots.json");
    ok(&bench(&[
        "--robots",
        "2",
        "--churn-frames",
        "3",
        "--warmup",
        "0.5",
        "--duration",
        "3",
        "--json",
        report.to_str().unwrap(),
    ]));
    let r = read_json(&report);
    assert!(r["requests"].as_u64().unwrap() >= 6, "{r}");
    assert_eq!(r["errors"], 0, "{r}");
    assert_eq!(r["robots"]["robots"], 2, "{r}");
    let opened = r["robots"]["streams_opened"].as_u64().unwrap();
    let answered = r["requests"].as_u64().unwrap();
    assert!(
        opened * 3 + 2 >= answered && opened >= 2,
        "each stream carries at most 3 frames: {r}"
    );

    // The soak: three phases, memory read as they go, the map replaced twice or more.
    let soak = dir.path().join("soak.json");
    let plot = dir.path().join("soak");
    let out = bench(&[
        "--soak",
        "--metrics-addr",
        &metrics,
        "--phases",
        "single,churn,replace",
        "--concurrency",
        "2",
        "--robots",
        "2",
        "--churn-frames",
        "3",
        "--warmup",
        "0.5",
        "--duration",
        "3",
        "--sample-s",
        "0.5",
        "--replace-file",
        rebuilt.to_str().unwrap(),
        "--replace-every-s",
        "1",
        "--admin-token",
        "soak-admin",
        "--json",
        soak.to_str().unwrap(),
        "--plot",
        plot.to_str().unwrap(),
    ]);
    let text = ok(&out);
    let s = read_json(&soak);
    let phases: Vec<&str> = s["soak"]
        .as_array()
        .unwrap()
        .iter()
        .map(|p| p["phase"].as_str().unwrap())
        .collect();
    assert_eq!(phases, ["single", "churn", "replace"], "{s}");
    for p in s["soak"].as_array().unwrap() {
        assert!(p["requests"].as_u64().unwrap() > 0, "{p}");
        assert_eq!(p["errors"], 0, "{p}");
        for side in ["start", "end"] {
            assert!(p[side]["rss_bytes"].as_f64().unwrap() > 1e6, "{p}");
            assert!(p[side]["heap_bytes"].as_f64().unwrap() > 1e6, "{p}");
        }
        assert!(p["heap_bytes_per_request"].as_f64().is_some(), "{p}");
        assert!(text.contains(p["phase"].as_str().unwrap()), "{text}");
    }
    assert!(s["soak"][1]["streams_opened"].as_u64().unwrap() >= 2, "{s}");
    let replace = &s["soak"][2];
    assert!(replace["replaces"].as_u64().unwrap() >= 2, "{replace}");
    assert_eq!(replace["replaces_failed"], 0, "{replace}");
    let samples = s["samples"].as_array().unwrap();
    assert!(samples.len() >= 6, "{} readings", samples.len());
    assert!(samples.iter().all(|x| x["phase"] != ""), "{s}");
    support::assert_picture(
        &plot,
        "soak_memory",
        (1200, 560),
        &[
            "resident memory (MB)",
            "live heap (MB)",
            "single",
            "churn",
            "replace",
        ],
    );

    // Refused before any load, each saying what to give.
    let e = support::fails_cleanly(&bench(&["--soak"]));
    assert!(e.contains("--metrics-addr"), "{e}");
    let e = support::fails_cleanly(&bench(&[
        "--soak",
        "--metrics-addr",
        &metrics,
        "--phases",
        "replace",
    ]));
    assert!(e.contains("--replace-file"), "{e}");
    let e = support::fails_cleanly(&bench(&["--soak", "--metrics-addr", &addr]));
    assert!(e.contains("--metrics-addr"), "{e}");
    stop(&rt, [server]);
}
