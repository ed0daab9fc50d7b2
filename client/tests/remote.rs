//! The client commands against a real `pntr-server` started in this process on 127.0.0.1 (ephemeral
//! port) with a map built by `pntr build-db` from a scene generated here: `pntr localize`, `pntr bench`
//! (closed loop, open loop, sweep), `pntr eval --remote`, and the token check.

use std::path::Path;
use std::process::{Command, Output};

mod support;

use pntr_service::config::Settings;
use pntr_service::tokio;

fn pntr(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_pntr"))
        .args(args)
        .env_remove("PNTR_TOKEN")
        .output()
        .expect("pntr runs")
}

fn ok(out: &Output) -> String {
    assert!(
        out.status.success(),
        "{}\n{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8_lossy(&out.stdout).into_owned()
}

fn json(path: &Path) -> serde_json::Value {
    serde_json::from_slice(&std::fs::read(path).unwrap()).unwrap()
}

#[test]
fn localize_bench_and_remote_eval_against_a_live_server() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().to_str().unwrap();
    let models = concat!(env!("CARGO_MANIFEST_DIR"), "/../models");
    ok(&pntr(&[
        "synth",
        "--out",
        root,
        "--points-per-scene",
        "3",
        "--queries-per-point",
        "3",
        "--seed",
        "12",
    ]));
    let map = dir.path().join("m.pntrmap");
    ok(&pntr(&[
        "build-db",
        "--dataset",
        root,
        "--scene",
        "synth000",
        "--out",
        map.to_str().unwrap(),
        "--models",
        models,
    ]));

    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .unwrap();
    let mut open = Settings::local(vec![map.clone()], models.into());
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
    let (a, b, c, t) = rt.block_on(async {
        let a = pntr_service::start(open).await.unwrap();
        let b = pntr_service::start(locked).await.unwrap();
        let c = pntr_service::start(second).await.unwrap();
        let t = pntr_service::start(tls).await.unwrap();
        for s in [&a, &b, &c, &t] {
            s.ready().await.unwrap();
        }
        (a, b, c, t)
    });
    let addr = a.addr.to_string();

    // Verification turns some right poses away (symmetric rooms); most of the first queries pass.
    let answers: Vec<serde_json::Value> = (0..6)
        .map(|q| {
            let q = q.to_string();
            let out = ok(&pntr(&[
                "localize",
                "--addr",
                &addr,
                "--dataset",
                root,
                "--scene",
                "synth000",
                "--query",
                &q,
                "--json",
            ]));
            serde_json::from_str(&out).unwrap()
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
    let out = ok(&pntr(&[
        "bench",
        "--addr",
        &addr,
        "--dataset",
        root,
        "--concurrency",
        "2",
        "--duration",
        "2",
        "--warmup",
        "0.5",
        "--frames",
        "5",
        "--json",
        report.to_str().unwrap(),
    ]));
    assert!(out.contains("p99 ms"), "{out}");
    let r = json(&report);
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
    let out = ok(&pntr(&[
        "bench",
        "--addr",
        &addr,
        "--dataset",
        root,
        "--rate",
        "4",
        "--duration",
        "1.5",
        "--warmup",
        "0",
        "--frames",
        "3",
        "--json",
        report.to_str().unwrap(),
    ]));
    assert!(out.contains("4/s"), "{out}");
    assert!(json(&report)["requests"].as_u64().unwrap() >= 5);
    ok(&pntr(&[
        "bench",
        "--addr",
        &addr,
        "--dataset",
        root,
        "--sweep",
        "1,2",
        "--duration",
        "1",
        "--warmup",
        "0",
        "--frames",
        "3",
        "--json",
        report.to_str().unwrap(),
        "--plot",
        dir.path().join("plots").to_str().unwrap(),
    ]));
    let sweep = json(&report)["sweep"].as_array().unwrap().clone();
    support::assert_picture(
        &dir.path().join("plots"),
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
    ok(&pntr(&[
        "bench",
        "--addr",
        &addr,
        "--dataset",
        root,
        "--duration",
        "0.5",
        "--warmup",
        "0",
        "--frames",
        "3",
        "--compare-in-process",
        map.to_str().unwrap(),
        "--models",
        models,
        "--json",
        report.to_str().unwrap(),
    ]));
    let o = &json(&report)["overhead"];
    assert_eq!(o["pairs"], 3, "{o}");
    assert!(
        o["ratio"].as_f64().unwrap() > 0.0 && o["in_process_ms_mean"].as_f64().unwrap() > 0.0,
        "{o}"
    );
    assert_eq!(sweep.len(), 2);
    assert_eq!(sweep[1]["concurrency"], 2);

    // Client-side balancing over two replicas, and a clear error when one is down.
    let both = format!("{addr},{}", c.addr);
    ok(&pntr(&[
        "bench",
        "--addr",
        &both,
        "--dataset",
        root,
        "--concurrency",
        "2",
        "--duration",
        "1.5",
        "--warmup",
        "0",
        "--frames",
        "3",
        "--json",
        report.to_str().unwrap(),
    ]));
    assert_eq!(json(&report)["errors"], 0);
    let out = pntr(&[
        "bench",
        "--addr",
        &format!("{addr},127.0.0.1:9"),
        "--dataset",
        root,
        "--duration",
        "1",
    ]);
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
    let e = json(&eval);
    assert_eq!(e["queries"], 4);
    assert!(e["recall"]["1m"].as_f64().unwrap() >= 0.5, "{e}");

    // The token: refused without it (a clean error naming the code), accepted with it.
    let locked_addr = b.addr.to_string();
    let out = pntr(&[
        "localize",
        "--addr",
        &locked_addr,
        "--dataset",
        root,
        "--scene",
        "synth000",
        "--query",
        "0",
    ]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("UNAUTHENTICATED") && !err.contains("panicked"),
        "{err}"
    );
    ok(&pntr(&[
        "localize",
        "--addr",
        &locked_addr,
        "--token",
        "s3cret",
        "--dataset",
        root,
        "--scene",
        "synth000",
        "--query",
        "0",
    ]));
    // TLS with the token, end to end with `pntr`; without the CA the handshake fails cleanly.
    let tls_addr = t.addr.to_string();
    let v: serde_json::Value = serde_json::from_str(&ok(&pntr(&[
        "localize",
        "--addr",
        &tls_addr,
        "--tls-ca",
        ca.to_str().unwrap(),
        "--tls-domain",
        "localhost",
        "--token",
        "s3cret",
        "--dataset",
        root,
        "--scene",
        "synth000",
        "--query",
        "1",
        "--json",
    ])))
    .unwrap();
    assert_eq!(v["status"], "LOCALIZED", "{v}");
    let out = pntr(&[
        "localize",
        "--addr",
        &tls_addr,
        "--token",
        "s3cret",
        "--dataset",
        root,
        "--scene",
        "synth000",
        "--query",
        "1",
    ]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && !err.contains("panicked"));
    // The plaintext client is told the server expects TLS (not only "transport error").
    assert!(
        err.contains("expects TLS") && err.contains("--tls-ca"),
        "{err}"
    );
    // A closed port is a clear error.
    let out = pntr(&[
        "localize",
        "--addr",
        "127.0.0.1:9",
        "--dataset",
        root,
        "--scene",
        "synth000",
        "--query",
        "0",
    ]);
    assert!(String::from_utf8_lossy(&out.stderr).contains("cannot reach pntr-server"));

    rt.block_on(async move {
        for mut s in [a, b, c, t] {
            s.shutdown();
            s.wait().await.unwrap();
        }
    });
}
