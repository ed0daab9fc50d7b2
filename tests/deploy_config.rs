//! deploy/ cannot silently drift from the code: every metric the Grafana dashboard queries is scraped
//! from a live server here, and the Prometheus, compose, Kubernetes and Docker files are parsed and held
//! to the ports, variables, models and set-up commands the code and the README actually use.
//! (No container engine or cluster runs here; schema checks are structural, see deploy/README.md.)

use std::collections::BTreeSet;
use std::io::{Read, Write};
use std::path::{Path, PathBuf};

use pntr_pipeline::preset::{Preset, DEFAULT_PRESET};
use pntr_pipeline::{map, mapfile};
use pntr_service::config::Settings;
use pntr_service::{tokio, wire};
use serde_yaml::Value;

fn root() -> PathBuf {
    pntr_tests::workspace_root()
}

fn deploy(p: &str) -> PathBuf {
    root().join("deploy").join(p)
}

fn scrape(addr: std::net::SocketAddr) -> String {
    let mut s = std::net::TcpStream::connect(addr).unwrap();
    s.write_all(b"GET /metrics HTTP/1.0\r\n\r\n").unwrap();
    let mut out = String::new();
    s.read_to_string(&mut out).unwrap();
    out
}

/// Metric names (`pntr_...`) in a PromQL expression.
fn metric_names(expr: &str) -> Vec<String> {
    let b = expr.as_bytes();
    let mut out = Vec::new();
    let mut i = 0;
    while let Some(j) = expr[i..].find("pntr_") {
        let start = i + j;
        let mut end = start;
        while end < b.len() && (b[end].is_ascii_alphanumeric() || b[end] == b'_') {
            end += 1;
        }
        out.push(expr[start..end].to_string());
        i = end;
    }
    out
}

/// A small synthetic scene in `dir`, its map file and one query view of it.
fn small_map(dir: &Path) -> (PathBuf, PathBuf, pntr_dataset::View) {
    let cfg = pntr_synth::SynthConfig {
        points_per_scene: 2,
        queries_per_point: 2,
        seed: 9,
        ..Default::default()
    };
    pntr_synth::synthesize(&cfg, dir, pntr_synth::plan_all(&cfg), &|| {}).unwrap();
    let index = pntr_dataset::DatasetIndex::open(dir).unwrap();
    let models = root().join("models");
    let preset = Preset::named(DEFAULT_PRESET).unwrap();
    let stage = preset.feature_config(models.clone()).build().unwrap();
    let scenes: Vec<_> = index.scenes.iter().collect();
    let m = map::build(
        "synth000",
        &scenes,
        &preset,
        &stage,
        &models,
        &mut |_, _| {},
    )
    .unwrap();
    let path = dir.join("m.pntrmap");
    mapfile::save(&m, &path).unwrap();
    let view = index.scenes[0].points[0]
        .open()
        .unwrap()
        .view(pntr_dataset::Role::Query, 0)
        .unwrap();
    (path, models, view)
}

/// The PromQL expressions of the Grafana dashboard, panel by panel.
fn dashboard_expressions() -> Vec<String> {
    let dash: serde_json::Value =
        serde_json::from_slice(&std::fs::read(deploy("grafana/dashboards/pntr.json")).unwrap())
            .unwrap();
    let mut exprs = Vec::new();
    for p in dash["panels"].as_array().unwrap() {
        for t in p["targets"].as_array().unwrap() {
            exprs.push(t["expr"].as_str().unwrap().to_string());
        }
    }
    exprs
}

#[test]
fn every_metric_the_dashboard_queries_is_exported_by_a_live_server() {
    let dir = tempfile::tempdir().unwrap();
    let (path, models, view) = small_map(dir.path());
    let rt = tokio::runtime::Runtime::new().unwrap();
    let mut settings = Settings::local(vec![path], models);
    settings.workers = 1;
    let scraped = rt.block_on(async {
        let mut s = pntr_service::start(settings).await.unwrap();
        s.ready().await.unwrap();
        let mut c = pntr_service::proto::localizer_client::LocalizerClient::connect(format!(
            "http://{}",
            s.addr
        ))
        .await
        .unwrap();
        c.localize(wire::raw_request(&view.rgb, &view.depth, None))
            .await
            .unwrap();
        let text = scrape(s.metrics_addr);
        s.shutdown();
        s.wait().await.unwrap();
        text
    });

    let exprs = dashboard_expressions();
    let names: BTreeSet<String> = exprs.iter().flat_map(|e| metric_names(e)).collect();
    assert!(names.len() >= 4, "{names:?}");
    for n in &names {
        assert!(
            scraped
                .lines()
                .any(|l| l.starts_with(&format!("{n}{{")) || l.starts_with(&format!("{n} "))),
            "the dashboard queries {n}, which the server does not export:\n{scraped}"
        );
    }
    // Label values the dashboard selects on exist too.
    for sel in ["stage=\"total\"", "code=\"OK\""] {
        assert!(exprs.iter().any(|e| e.contains(sel)));
        assert!(scraped.contains(sel), "{sel} not in the scrape:\n{scraped}");
    }
    assert!(
        scraped.contains("status=\"LOCALIZED\"") || scraped.contains("status=\"NOT_LOCALIZED\"")
    );
}

fn yaml_docs(path: &Path) -> Vec<Value> {
    let text = std::fs::read_to_string(path).unwrap();
    serde_yaml::Deserializer::from_str(&text)
        .map(|d| {
            serde::Deserialize::deserialize(d).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
        })
        .collect()
}

/// The PNTR_* variables the server and its logging read.
fn known_variables() -> BTreeSet<String> {
    let src = std::fs::read_to_string(root().join("server/service/src/config.rs")).unwrap();
    let mut vars: BTreeSet<String> = src
        .split("env = \"")
        .skip(1)
        .map(|s| s.split('"').next().unwrap().to_string())
        .collect();
    vars.extend(["PNTR_LOG".to_string(), "PNTR_DEMO_DIR".to_string()]);
    assert!(
        vars.contains("PNTR_DB") && vars.contains("PNTR_WORKERS"),
        "{vars:?}"
    );
    vars
}

fn s<'a>(v: &'a Value, path: &[&str]) -> &'a Value {
    path.iter().fold(v, |v, k| &v[*k])
}

#[test]
fn prometheus_compose_kubernetes_and_docker_files_agree_with_the_code() {
    let vars = known_variables();
    // Prometheus scrapes the compose service on the metrics port.
    let prom = &yaml_docs(&deploy("prometheus/prometheus.yml"))[0];
    let target = s(prom, &["scrape_configs"])[0]["static_configs"][0]["targets"][0]
        .as_str()
        .unwrap();
    assert_eq!(target, "pntr:9464");
    let compose = &yaml_docs(&deploy("compose.yaml"))[0];
    let ports: Vec<&str> = s(compose, &["services", "pntr", "ports"])
        .as_sequence()
        .unwrap()
        .iter()
        .map(|p| p.as_str().unwrap())
        .collect();
    assert!(
        ports.contains(&"9464:9464") && ports.contains(&"50051:50051"),
        "{ports:?}"
    );
    for (k, _) in s(compose, &["services", "pntr", "environment"])
        .as_mapping()
        .unwrap()
    {
        assert!(
            vars.contains(k.as_str().unwrap()),
            "compose sets unknown {k:?}"
        );
    }

    // Kubernetes: well-formed objects; gRPC health probes on the gRPC port; only known variables.
    let mut kinds = BTreeSet::new();
    let mut configmaps = BTreeSet::new();
    let mut deployments = Vec::new();
    for f in std::fs::read_dir(deploy("k8s")).unwrap() {
        let f = f.unwrap().path();
        for d in yaml_docs(&f) {
            let kind = d["kind"]
                .as_str()
                .unwrap_or_else(|| panic!("{}: no kind", f.display()));
            assert!(
                d["apiVersion"].is_string(),
                "{}: no apiVersion",
                f.display()
            );
            assert!(
                d["metadata"]["name"].is_string(),
                "{}: no metadata.name",
                f.display()
            );
            kinds.insert(kind.to_string());
            match kind {
                "ConfigMap" => {
                    configmaps.insert(d["metadata"]["name"].as_str().unwrap().to_string());
                    for (k, v) in d["data"].as_mapping().unwrap() {
                        assert!(
                            vars.contains(k.as_str().unwrap()),
                            "{}: unknown {k:?}",
                            f.display()
                        );
                        assert!(v.is_string(), "{}: {k:?} must be a string", f.display());
                    }
                }
                "Deployment" => deployments.push((f.clone(), d)),
                _ => {}
            }
        }
    }
    for k in [
        "Deployment",
        "Service",
        "ConfigMap",
        "HorizontalPodAutoscaler",
    ] {
        assert!(kinds.contains(k), "no {k} in deploy/k8s");
    }
    for (f, d) in &deployments {
        let spec = &d["spec"]["template"]["spec"];
        assert_eq!(
            d["spec"]["selector"]["matchLabels"],
            d["spec"]["template"]["metadata"]["labels"]
        );
        for c in spec["containers"].as_sequence().unwrap() {
            let ports: Vec<i64> = c["ports"]
                .as_sequence()
                .unwrap()
                .iter()
                .map(|p| p["containerPort"].as_i64().unwrap())
                .collect();
            assert_eq!(ports, vec![50051, 9464], "{}", f.display());
            for probe in ["readinessProbe", "livenessProbe"] {
                assert_eq!(
                    c[probe]["grpc"]["port"].as_i64(),
                    Some(50051),
                    "{}: {probe}",
                    f.display()
                );
            }
            for e in c["env"].as_sequence().into_iter().flatten() {
                assert!(
                    vars.contains(e["name"].as_str().unwrap()),
                    "{}: env {:?}",
                    f.display(),
                    e["name"]
                );
            }
            for e in c["envFrom"].as_sequence().into_iter().flatten() {
                let name = e["configMapRef"]["name"].as_str().unwrap();
                assert!(
                    configmaps.contains(name),
                    "{}: no ConfigMap {name}",
                    f.display()
                );
            }
            assert!(
                c["resources"]["requests"]["memory"].is_string(),
                "{}: memory request",
                f.display()
            );
        }
    }

    // Docker: the build runs the README's set-up and builds the server; the models it copies exist;
    // every PNTR_* it sets is one the server reads; the runtime stage is not root.
    let readme = std::fs::read_to_string(root().join("README.md")).unwrap();
    assert!(readme.contains("scripts/setup.sh"));
    for file in ["Dockerfile", "Dockerfile.cuda"] {
        let text = std::fs::read_to_string(deploy(file)).unwrap();
        assert!(text.contains("bash scripts/setup.sh"), "{file}");
        assert!(
            text.contains("cargo build --release -p pntr-service"),
            "{file}"
        );
        assert!(text.contains("USER 10001"), "{file}");
        for word in text.split_whitespace() {
            if let Some(m) = word.strip_prefix("models/") {
                assert!(
                    root().join("models").join(m).is_file(),
                    "{file} copies missing models/{m}"
                );
            }
            if let Some(v) = word.strip_prefix("PNTR_") {
                let name = format!("PNTR_{}", v.split('=').next().unwrap());
                assert!(vars.contains(&name), "{file} sets unknown {name}");
            }
        }
    }
    let dash = std::fs::read_to_string(deploy("grafana/dashboards/pntr.json")).unwrap();
    let provider = &yaml_docs(&deploy("grafana/provisioning/dashboards/pntr.yaml"))[0];
    assert_eq!(
        s(provider, &["providers"])[0]["options"]["path"],
        "/var/lib/grafana/dashboards"
    );
    assert!(dash.contains("\"uid\": \"prometheus\""));
}

/// Run kubernetes-validate (Kubernetes OpenAPI schemas bundled in the PyPI package; no network).
fn kubernetes_validate(files: &[PathBuf]) -> std::process::Output {
    std::process::Command::new(pntr_tests::python())
        .args([
            "-m",
            "kubernetes_validate",
            "-k",
            "1.33.0",
            "--strict",
            "--no-warn",
        ])
        .args(files)
        .output()
        .expect("python runs")
}

#[test]
fn kubernetes_manifests_pass_the_openapi_schemas_and_a_broken_one_does_not() {
    let files: Vec<PathBuf> = std::fs::read_dir(deploy("k8s"))
        .unwrap()
        .map(|f| f.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "yaml"))
        .collect();
    assert!(files.len() >= 5);
    let out = kubernetes_validate(&files);
    assert!(
        out.status.success(),
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    // The check can fail: a port given as text and an unknown field are refused.
    let dir = tempfile::tempdir().unwrap();
    let bad = dir.path().join("bad.yaml");
    let text = std::fs::read_to_string(deploy("k8s/service.yaml"))
        .unwrap()
        .replace("port: 50051", "port: fifty")
        .replace("clusterIP: None", "clusterIP: None\n  sessionAffinty: None");
    std::fs::write(&bad, text).unwrap();
    assert!(!kubernetes_validate(&[bad]).status.success());
}

/// A program from .deps/prometheus (where scripts/setup.sh unpacks it), else on PATH, if installed.
fn program(name: &str) -> Option<PathBuf> {
    let path = std::env::var_os("PATH").unwrap_or_default();
    std::iter::once(root().join(".deps/prometheus/usr/bin"))
        .chain(std::env::split_paths(&path))
        .map(|d| d.join(name))
        .find(|p| p.is_file())
}

/// GET `path_and_query` from an HTTP server on 127.0.0.1:`port`: (status line, body).
fn http_get(port: u16, path_and_query: &str) -> std::io::Result<(String, String)> {
    let mut s = std::net::TcpStream::connect(("127.0.0.1", port))?;
    s.set_read_timeout(Some(std::time::Duration::from_secs(10)))?;
    write!(
        s,
        "GET {path_and_query} HTTP/1.0\r\nHost: 127.0.0.1:{port}\r\n\r\n"
    )?;
    let mut out = String::new();
    s.read_to_string(&mut out)?;
    let status = out.lines().next().unwrap_or_default().to_string();
    let body = out.split_once("\r\n\r\n").map(|x| x.1).unwrap_or_default();
    Ok((status, body.to_string()))
}

/// An instant query through Prometheus's HTTP API: the result's samples as (labels, value).
fn prom_query(port: u16, expr: &str) -> Vec<(serde_json::Value, f64)> {
    let q = percent_encoding::utf8_percent_encode(expr, percent_encoding::NON_ALPHANUMERIC);
    let (status, body) = http_get(port, &format!("/api/v1/query?query={q}")).unwrap();
    let v: serde_json::Value =
        serde_json::from_str(&body).unwrap_or_else(|e| panic!("{expr}: {status}: {e}: {body}"));
    assert_eq!(v["status"], "success", "{expr}: {body}");
    v["data"]["result"]
        .as_array()
        .unwrap_or_else(|| panic!("{expr}: no result array: {body}"))
        .iter()
        .map(|r| {
            let value = r["value"][1].as_str().unwrap().parse::<f64>().unwrap();
            (r["metric"].clone(), value)
        })
        .collect()
}

/// A free TCP port on 127.0.0.1 (bound and released; Prometheus takes its port as a flag).
fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

/// Stops the child when dropped, so a failing assertion does not leave Prometheus running.
struct Child(std::process::Child);

impl Drop for Child {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// deploy/'s Prometheus configuration and the dashboard, run for real: Prometheus (Debian's package,
/// unpacked by scripts/setup.sh) scrapes a live pntr-server with deploy/prometheus/prometheus.yml
/// (only the target and the interval changed), frames go through the server, and every expression of
/// the Grafana dashboard must evaluate to a non-empty, finite result through Prometheus's query API.
#[test]
fn the_dashboard_expressions_evaluate_in_a_real_prometheus() {
    let (Some(prometheus), Some(promtool)) = (program("prometheus"), program("promtool")) else {
        eprintln!(
            "SKIPPED: the prometheus and promtool programs are not installed (scripts/setup.sh \
             unpacks Debian's `prometheus` package into .deps/prometheus)"
        );
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    // The shipped configuration passes promtool as it is.
    let out = std::process::Command::new(&promtool)
        .args(["check", "config"])
        .arg(deploy("prometheus/prometheus.yml"))
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "promtool check config deploy/prometheus/prometheus.yml:\n{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );

    let (path, models, view) = small_map(dir.path());
    let rt = tokio::runtime::Runtime::new().unwrap();
    let mut settings = Settings::local(vec![path], models);
    settings.workers = 1;
    let mut server = rt.block_on(async {
        let s = pntr_service::start(settings).await.unwrap();
        s.ready().await.unwrap();
        s
    });

    // The shipped scrape configuration, pointed at this server and scraping every second.
    let mut cfg = yaml_docs(&deploy("prometheus/prometheus.yml")).remove(0);
    cfg["global"]["scrape_interval"] = Value::from("1s");
    cfg["global"]["evaluation_interval"] = Value::from("1s");
    let jobs = cfg["scrape_configs"].as_sequence_mut().unwrap();
    assert_eq!(jobs.len(), 1, "one scrape job, pntr");
    jobs[0]["static_configs"][0]["targets"] =
        Value::from(vec![Value::from(server.metrics_addr.to_string())]);
    let cfg_path = dir.path().join("prometheus.yml");
    std::fs::write(&cfg_path, serde_yaml::to_string(&cfg).unwrap()).unwrap();
    let out = std::process::Command::new(&promtool)
        .args(["check", "config"])
        .arg(&cfg_path)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );

    let port = free_port();
    let log = std::fs::File::create(dir.path().join("prometheus.log")).unwrap();
    let _prom = Child(
        std::process::Command::new(&prometheus)
            .arg(format!("--config.file={}", cfg_path.display()))
            .arg(format!(
                "--storage.tsdb.path={}",
                dir.path().join("tsdb").display()
            ))
            .arg(format!("--web.listen-address=127.0.0.1:{port}"))
            .stdout(log.try_clone().unwrap())
            .stderr(log)
            .spawn()
            .unwrap(),
    );
    let log_text =
        || std::fs::read_to_string(dir.path().join("prometheus.log")).unwrap_or_default();
    // Wait until Prometheus has scraped the server at least once.
    let start = std::time::Instant::now();
    loop {
        let up = http_get(port, "/api/v1/query?query=up")
            .ok()
            .and_then(|(_, b)| serde_json::from_str::<serde_json::Value>(&b).ok())
            .and_then(|v| {
                v["data"]["result"][0]["value"][1]
                    .as_str()
                    .map(String::from)
            });
        if up.as_deref() == Some("1") {
            break;
        }
        assert!(
            start.elapsed().as_secs() < 60,
            "Prometheus never scraped the server (up = {up:?}):\n{}",
            log_text()
        );
        std::thread::sleep(std::time::Duration::from_millis(250));
    }

    // Traffic across several scrapes: LOCALIZED frames, and refused ones for the errors panel.
    let frame = wire::raw_request(&view.rgb, &view.depth, None);
    rt.block_on(async {
        let mut c = pntr_service::proto::localizer_client::LocalizerClient::connect(format!(
            "http://{}",
            server.addr
        ))
        .await
        .unwrap();
        for round in 0..3 {
            for _ in 0..2 {
                c.localize(frame.clone()).await.unwrap();
            }
            let mut bad = frame.clone();
            bad.depth = None;
            let e = c.localize(bad).await.unwrap_err();
            assert_eq!(e.code(), pntr_service::tonic::Code::InvalidArgument);
            if round < 2 {
                tokio::time::sleep(std::time::Duration::from_millis(1500)).await;
            }
        }
    });
    // Two more scrapes after the last frame.
    std::thread::sleep(std::time::Duration::from_millis(2500));

    let exprs = dashboard_expressions();
    assert!(exprs.len() >= 10, "{exprs:?}");
    for e in &exprs {
        let samples = prom_query(port, e);
        assert!(!samples.is_empty(), "`{e}` is empty in Prometheus");
        for (labels, v) in &samples {
            assert!(v.is_finite(), "`{e}` gives {v} for {labels}");
        }
        // Panels by label show each label value.
        if e.contains("by (le, stage)") {
            let stages: BTreeSet<String> = samples
                .iter()
                .filter_map(|(l, _)| l["stage"].as_str().map(String::from))
                .collect();
            for s in ["total", "extraction", "retrieval", "verification"] {
                assert!(stages.contains(s), "`{e}`: no stage {s} in {stages:?}");
            }
        }
        if e.contains("by (code)") {
            assert!(
                samples
                    .iter()
                    .any(|(l, v)| l["code"] == "INVALID_ARGUMENT" && *v > 0.0),
                "`{e}`: {samples:?}"
            );
        }
    }
    // The request rate counts what was sent: 6 answered frames within the last minute.
    let ok = prom_query(port, "sum(increase(pntr_requests_total{code=\"OK\"}[1m]))");
    assert!(ok[0].1 > 3.0, "{ok:?}");
    server.shutdown();
    rt.block_on(server.wait()).unwrap();
}
